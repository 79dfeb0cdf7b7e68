#!/usr/bin/env python3
"""A TCP relay that holds every chunk for a one-way delay in each direction, so that a link
gets latency on a kernel without netem: run it in the client's network namespace and point the
client at it.  The rate limit comes from `tc ... tbf` on the link itself.

    python3 scripts/delay_relay.py LISTEN_PORT TARGET_HOST TARGET_PORT ONE_WAY_MS
"""
import asyncio
import sys
import time


async def pump(reader, writer, delay):
    queue = asyncio.Queue()

    async def send():
        while True:
            due, data = await queue.get()
            if data is None:
                break
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            writer.write(data)
            await writer.drain()
        try:
            writer.write_eof()
        except (OSError, RuntimeError):
            pass

    sender = asyncio.create_task(send())
    try:
        while True:
            data = await reader.read(65536)
            if not data:
                break
            queue.put_nowait((time.monotonic() + delay, data))
    except (ConnectionError, OSError):
        pass
    queue.put_nowait((time.monotonic() + delay, None))
    try:
        await sender
    except (ConnectionError, OSError):
        pass


async def main():
    port, host, target, ms = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    delay = ms / 1000.0

    async def handle(cr, cw):
        try:
            sr, sw = await asyncio.open_connection(host, target)
        except OSError:
            cw.close()
            return
        await asyncio.gather(pump(cr, sw, delay), pump(sr, cw, delay))
        for w in (cw, sw):
            w.close()

    server = await asyncio.start_server(handle, "127.0.0.1", port)
    print(f"relay 127.0.0.1:{port} -> {host}:{target}, {ms} ms each way", flush=True)
    async with server:
        await server.serve_forever()


asyncio.run(main())
