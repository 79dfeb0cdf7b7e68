"""What splitting a volume into independent pieces costs, ours against SPERR's: the MNI volume
(`../shared/data`) at one byte target, compressed whole and in B³ bricks by `wavesplat compress`
(`--target-bytes`, the default effort) and whole and in B³ HDF5 chunks by SPERR (the peers'
codec, `hdf5plugin.Sperr`), each SPERR setting in its rate mode (the same bits per voxel in
every chunk) and its PSNR mode (the same quality in every chunk), searched to the bytes. All
decoded and scored with the peers' own metrics (`../shared/peers/peers.py`: Q_I over two axis
X-ray views and one oblique).

    VENV=/path/to/peers-venv bash scripts/chunk-cost.sh [BYTES] [BRICK ...]

Defaults: 86 245 bytes (0.08 bits per voxel, the 64³ bricks' figure in BENCHMARKS.md), bricks
of 128 and 64. Prints a Markdown table; writes a CSV in $TMPDIR/wavesplat-chunk-cost.
"""

import csv
import math
import os
import subprocess
import sys

import h5py
import hdf5plugin
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "..", "shared", "peers"))
import peers  # noqa: E402  (the peers' X-ray views and metrics, unchanged)


def ours(w, tmp, volume, target, brick):
    """Our file at `target` bytes, whole (`brick` None) or bricked: bytes, decoded volume."""
    name = "whole" if brick is None else f"b{brick}"
    out = os.path.join(tmp, f"mni_{name}.wsp")
    cmd = [w, "compress", volume, "--target-bytes", str(target), "-o", out]
    if brick is not None:
        cmd += ["--brick", str(brick), "--no-resume"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    decoded = os.path.join(tmp, f"mni_{name}.f32")
    subprocess.run([w, "decompress", out, "-o", decoded], check=True, stdout=subprocess.DEVNULL)
    y = np.fromfile(decoded, dtype=np.float32)
    os.remove(decoded)
    return os.path.getsize(out), y


def sperr(x, chunks, mode, target):
    """SPERR over HDF5 chunks at the setting of `mode` whose bytes come closest to `target`
    from below: bytes, decoded volume (x, y, z indexed)."""

    def code(p):
        with h5py.File("chunk-cost.h5", "w", driver="core", backing_store=False) as f:
            ds = f.create_dataset("d", data=x, chunks=chunks,
                                  **hdf5plugin.Sperr(swap=True, **{mode: p}))
            return ds.id.get_storage_size(), ds[...]

    # Bytes grow with the rate and the PSNR; searched on that scale by bisection.
    lo, hi = (0.005, 2.0) if mode == "rate" else (5.0, 90.0)
    best = None
    for _ in range(24):
        mid = (lo + hi) / 2
        size, _ = code(mid)
        if size <= target:
            best, lo = mid, mid
        else:
            hi = mid
    return code(best)


def main():
    args = [a for a in sys.argv[1:]]
    target = int(args[0]) if args else 86245
    bricks = [int(a) for a in args[1:]] or [128, 64]
    w = os.path.join(ROOT, "target", "release", "wavesplat")
    tmp = os.path.join(os.environ.get("TMPDIR", "/tmp"), "wavesplat-chunk-cost")
    os.makedirs(tmp, exist_ok=True)
    volume = os.path.abspath(peers.DATA)
    u8 = peers.load_full()  # x, y, z
    x = u8.astype(np.float32)
    ref = x.astype(np.float64)
    refviews = peers.views(ref)
    rows = []
    for brick in [None, *bricks]:
        size, y = ours(w, tmp, volume, target, brick)
        # Our decoded file is x fastest: z, y, x in C order.
        y = y.reshape(x.shape[::-1]).transpose(2, 1, 0)
        m = peers.metrics(ref, refviews, y)
        rows.append(("wavesplat", "whole" if brick is None else f"{brick}³ bricks", "",
                     size, m["qi_mean"]))
        print(rows[-1], file=sys.stderr, flush=True)
    for brick in [None, *bricks]:
        chunks = x.shape if brick is None else (brick,) * 3
        for mode, label in (("rate", "rate"), ("peak_signal_to_noise_ratio", "PSNR")):
            size, y = sperr(x, chunks, mode, target)
            m = peers.metrics(ref, refviews, y)
            rows.append(("SPERR", "whole" if brick is None else f"{brick}³ chunks", label, size,
                         m["qi_mean"]))
            print(rows[-1], file=sys.stderr, flush=True)
    with open(os.path.join(tmp, f"chunk_cost_{target}.csv"), "w", newline="") as f:
        c = csv.writer(f)
        c.writerow(["codec", "pieces", "mode", "bytes", "qi_mean"])
        c.writerows([[*r[:4], f"{r[4]:.2f}"] for r in rows])
    whole = {codec: max(q for c, p, _, _, q in rows if c == codec and p == "whole")
             for codec in ("wavesplat", "SPERR")}
    print(f"MNI at {target} bytes ({target * 8 / x.size:.4f} bits per voxel), peers' Q_I (mean "
          "of three views)")
    print()
    print("| codec | pieces | SPERR mode | bytes | Q_I | against its best whole |")
    print("|---|---|---|---|---|---|")
    for codec, pieces, mode, size, qi in rows:
        print(f"| {codec} | {pieces} | {mode} | {size} | {qi:.2f} dB | "
              f"{qi - whole[codec]:+.2f} dB |")
    assert all(math.isfinite(r[4]) for r in rows)


if __name__ == "__main__":
    main()
