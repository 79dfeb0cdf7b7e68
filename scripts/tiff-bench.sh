#!/usr/bin/env bash
# Compresses one generated volume from a raw file, a directory of TIFF slices (Deflate) and a
# multi-page BigTIFF (uncompressed), brick by brick, and prints each run's wall time and peak
# RSS: what reading a TIFF stack costs against raw samples. Needs python3 with numpy and
# tifffile (Debian: python3-numpy python3-tifffile) and a release build.
#
#   bash scripts/tiff-bench.sh [SIDE=512] [DEPTH=SIDE] [BRICK=256] [OUT=/tmp/wavesplat-tiff-bench]
set -euo pipefail
cd "$(dirname "$0")/.."
side=${1:-512}
depth=${2:-$side}
brick=${3:-256}
out=${4:-/tmp/wavesplat-tiff-bench}
bin=${WAVESPLAT:-target/release/wavesplat}
python=${PYTHON:-/usr/bin/python3}
mkdir -p "$out"
raw="$out/vol_${side}x${side}x${depth}_u16.raw"
if [ ! -f "$raw" ]; then
  "$python" - "$out" "$side" "$depth" <<'EOF'
import sys, os
import numpy as np
import tifffile
out, side, depth = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rng = np.random.default_rng(1)
y, x = np.mgrid[0:side, 0:side].astype(np.float32) / side
os.makedirs(f"{out}/slices", exist_ok=True)
raw = open(f"{out}/vol_{side}x{side}x{depth}_u16.raw", "wb")
with tifffile.TiffWriter(f"{out}/multi.tif", bigtiff=True) as multi:
    for z in range(depth):
        t = z / depth
        blob = np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2 + (t - 0.5) ** 2) / 0.05)
        rings = 0.3 * np.sin(40 * np.hypot(x - 0.4, y - 0.6) + 8 * t)
        s = (20000 * (blob + rings + 1.0) + rng.normal(0, 200, x.shape)).clip(0, 65535)
        s = s.astype(np.uint16)
        raw.write(s.tobytes())
        tifffile.imwrite(f"{out}/slices/slice_{z}.tif", s, compression="zlib")
        multi.write(s, contiguous=False)
raw.close()
EOF
fi
for input in "$raw" "$out/slices" "$out/multi.tif"; do
  /usr/bin/time -f "%e s wall, %M kB peak" "$bin" compress "$input" --brick "$brick" \
    --target-fraction 0.01 --effort fast -o "$out/out.wsp" 2> "$out/time.txt" > /dev/null
  echo "$(basename "$input"): $(tail -1 "$out/time.txt"), $(stat -c %s "$out/out.wsp") bytes"
done
