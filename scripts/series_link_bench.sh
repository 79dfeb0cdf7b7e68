#!/usr/bin/env bash
# Playing a time series over a wide-area link (issue 56): a viewer host and a server host
# (network namespaces on a veth pair, root needed), the link limited to RATE by `tc tbf` on both
# ends and given RTT_MS of round trip by scripts/delay_relay.py in the viewer's namespace (as
# scripts/link_bench.sh does). The beating phantom (X×Y×Z, T time points, groups of 8, 1 % of
# its coefficients) is served by a cache node with its own store and published (.wspx) by nginx.
# From each, on the viewer host:
#   - the window (`view`, CPU backend, under Xvfb) plays two loops at up to FPS time points a
#     second: time points per second over all, in the first loop (each time point streamed)
#     and after it (kept images), and how many it left shown converged;
#   - `render --time-point T/2` (a far time point, a stream of its own): opened, first image,
#     converged, in ms after the request, and the bytes received.
#   sudo bash scripts/series_link_bench.sh [OUT_DIR] [RATE] [RTT_MS] [DIMS X,Y,Z,T] [SIZE] [FPS]
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
OUT="${1:-$ROOT/out/series-link}"
RATE="${2:-30mbit}"
RTT="${3:-30}"
DIMS="${4:-256,256,16,16}"
SIZE="${5:-256x256}"
FPS="${6:-30}"
BIN="${WAVESPLAT_BIN:-$ROOT/target/release/wavesplat}"
[ -x "$BIN" ] || (cd "$ROOT" && cargo build --release -q)
mkdir -p "$OUT/www"
POINTS="${DIMS##*,}"
"$BIN" compress --phantom beating --dims "$DIMS" --target-fraction 0.01 -o "$OUT/cine.wsp" >"$OUT/compress.txt"
"$BIN" publish "$OUT/cine.wsp" -o "$OUT/www/cine.wspx" >/dev/null
V=slv$$; S=sls$$
XPID=
cleanup() {
  [ -n "$XPID" ] && kill "$XPID" 2>/dev/null || true
  ip netns pids "$S" 2>/dev/null | xargs -r kill -9 2>/dev/null || true
  ip netns pids "$V" 2>/dev/null | xargs -r kill -9 2>/dev/null || true
  ip netns del "$V" 2>/dev/null || true
  ip netns del "$S" 2>/dev/null || true
}
trap cleanup EXIT
ip netns add "$V"; ip netns add "$S"
ip link add "${V}e" type veth peer name "${S}e"
ip link set "${V}e" netns "$V"; ip link set "${S}e" netns "$S"
ip -n "$V" addr add 10.211.0.1/24 dev "${V}e"; ip -n "$S" addr add 10.211.0.2/24 dev "${S}e"
for ns in "$V" "$S"; do ip -n "$ns" link set lo up; done
ip -n "$V" link set "${V}e" up; ip -n "$S" link set "${S}e" up
ip netns exec "$V" tc qdisc add dev "${V}e" root tbf rate "$RATE" burst 32kb latency 400ms
ip netns exec "$S" tc qdisc add dev "${S}e" root tbf rate "$RATE" burst 32kb latency 400ms
run_s() { ip netns exec "$S" "$@"; }
run_v() { ip netns exec "$V" "$@"; }
cat > "$OUT/nginx.conf" <<NGX
daemon off; worker_processes 1; pid $OUT/nginx.pid; error_log $OUT/nginx.err;
events { worker_connections 64; }
http { access_log off; server { listen 10.211.0.2:8080; root $OUT/www; } }
NGX
run_s nginx -c "$OUT/nginx.conf" -p "$OUT" &
rm -rf "$OUT/node-db"
run_s "$BIN" serve cache --db "$OUT/node-db" --addr 0.0.0.0:50061 --insecure >/dev/null 2>"$OUT/node.log" &
sleep 2
run_s "$BIN" cache ingest "$OUT/cine.wsp" --name cine --cache http://127.0.0.1:50061 >/dev/null
HALF=$(python3 -c "print($RTT / 2)")
for p in 50061 8080; do
  run_v python3 "$ROOT/scripts/delay_relay.py" "$p" 10.211.0.2 "$p" "$HALF" >/dev/null &
done
Xvfb :91 -screen 0 1280x1024x24 >/dev/null 2>&1 &
XPID=$!
sleep 2
echo "series: $DIMS, $(stat -c %s "$OUT/cine.wsp") bytes (.wspx $(stat -c %s "$OUT/www/cine.wspx")); link $RATE, ${RTT} ms round trip; window $SIZE, up to $FPS time points/s"
echo "| source | played | time points/s | first loop: time points/s | after it: time points/s | left converged |"
echo "|---|---|---|---|---|---|"
play() {  # name, view source arguments...
  local name=$1; shift
  local log
  log=$(DISPLAY=:91 WGPU_BACKEND=vulkan run_v "$BIN" view "$@" --size "$SIZE" --cpu --fps "$FPS" \
        --script "converge; key space; played $((2 * POINTS)); quit" 2>"$OUT/$name-view.err")
  echo "$log" > "$OUT/$name-view.txt"
  python3 - "$name" "$POINTS" <<PY
import re, sys
name, points = sys.argv[1], int(sys.argv[2])
text = open("$OUT/$name-view.txt").read()
m = re.search(r"played (\d+) time points in ([0-9.]+) s \(([0-9.]+) per second\), (\d+) of those", text)
k = re.search(r"(\d+) of them drawn before in this view, shown again at ([0-9.]+) per second", text)
n, s, rate, conv = int(m[1]), float(m[2]), float(m[3]), int(m[4])
kept, kept_rate = (int(k[1]), float(k[2])) if k else (0, 0.0)
first_n = n - kept
first_s = s - (kept / kept_rate if kept_rate > 0 else 0.0)
first = first_n / first_s if first_s > 0 else 0.0
print(f"| {name} | {n} | {rate:.1f} | {first:.1f} ({first_n} in {first_s:.2f} s) | {kept_rate:.1f} ({kept}) | {conv} of {n} |")
PY
}
play "cache node" --cache http://127.0.0.1:50061 --volume cine
play "range requests, nginx" http://127.0.0.1:8080/cine.wspx
echo
echo "| far time point ($((POINTS / 2))) | opened (ms) | first image (ms) | converged (ms) | bytes received |"
echo "|---|---|---|---|---|"
far() {
  local name=$1; shift
  local log
  log=$(run_v "$BIN" render "$@" --time-point $((POINTS / 2)) --size "$SIZE" --frame-ms 16.6 \
        --cpu -o "$OUT/far.png" 2>/dev/null)
  local opened first total bytes
  opened=$(echo "$log" | sed -n 's/^opened in \([0-9.]*\) ms.*/\1/p')
  first=$(echo "$log" | sed -n 's/.*first image \([0-9.]*\) ms.*/\1/p')
  total=$(echo "$log" | sed -n 's/.* done \([0-9.]*\) ms.*/\1/p')
  bytes=$(echo "$log" | sed -n 's/.* packets, \([0-9]*\) bytes received.*/\1/p')
  echo "| $name | $opened | $first | $total | $bytes |"
}
far "cache node" --cache http://127.0.0.1:50061 --volume cine
far "range requests, nginx" http://127.0.0.1:8080/cine.wspx
