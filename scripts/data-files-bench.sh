#!/usr/bin/env bash
# Compresses one generated volume from a raw file, from a detached NRRD header listing one raw
# file per slice (`data file: LIST`), from a MetaImage header naming the same slices by a
# pattern (`ElementDataFile = slice_%04d.raw 0 N 1`) and from an NRRD pattern of gzip slices,
# brick by brick, and prints each run's wall time, peak RSS and bytes: what reading a volume
# cut into files costs against one file. Needs python3 with numpy and a release build.
#
#   bash scripts/data-files-bench.sh [SIDE=512] [DEPTH=SIDE] [BRICK=256] [OUT=/tmp/wavesplat-files-bench]
set -euo pipefail
cd "$(dirname "$0")/.."
side=${1:-512}
depth=${2:-$side}
brick=${3:-256}
out=${4:-/tmp/wavesplat-files-bench}
bin=${WAVESPLAT:-target/release/wavesplat}
python=${PYTHON:-/usr/bin/python3}
mkdir -p "$out"
raw="$out/vol_${side}x${side}x${depth}_u16.raw"
if [ ! -f "$raw" ]; then
  "$python" - "$out" "$side" "$depth" <<'EOF'
import sys, os, gzip
import numpy as np
out, side, depth = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rng = np.random.default_rng(1)
y, x = np.mgrid[0:side, 0:side].astype(np.float32) / side
os.makedirs(f"{out}/slices", exist_ok=True)
raw = open(f"{out}/vol_{side}x{side}x{depth}_u16.raw", "wb")
for z in range(depth):
    t = z / depth
    blob = np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2 + (t - 0.5) ** 2) / 0.05)
    rings = 0.3 * np.sin(40 * np.hypot(x - 0.4, y - 0.6) + 8 * t)
    s = (20000 * (blob + rings + 1.0) + rng.normal(0, 200, x.shape)).clip(0, 65535)
    b = s.astype("<u2").tobytes()
    raw.write(b)
    open(f"{out}/slices/slice_{z:04d}.raw", "wb").write(b)
    open(f"{out}/slices/slice_{z:04d}.raw.gz", "wb").write(gzip.compress(b, compresslevel=1))
raw.close()
head = f"NRRD0004\ntype: uint16\ndimension: 3\nsizes: {side} {side} {depth}\nendian: little\n"
names = "\n".join(f"slices/slice_{z:04d}.raw" for z in range(depth))
open(f"{out}/list.nhdr", "w").write(f"{head}encoding: raw\ndata file: LIST\n{names}\n")
open(f"{out}/gzip.nhdr", "w").write(
    f"{head}encoding: gzip\ndata file: slices/slice_%04d.raw.gz 0 {depth - 1} 1\n")
open(f"{out}/pattern.mhd", "w").write(
    f"ObjectType = Image\nNDims = 3\nDimSize = {side} {side} {depth}\nElementType = MET_USHORT\n"
    f"ElementDataFile = slices/slice_%04d.raw 0 {depth - 1} 1\n")
EOF
fi
for input in "$raw" "$out/list.nhdr" "$out/pattern.mhd" "$out/gzip.nhdr"; do
  /usr/bin/time -f "%e s wall, %M kB peak" "$bin" compress "$input" --brick "$brick" \
    --target-fraction 0.01 --effort fast -o "$out/out.wsp" 2> "$out/time.txt" > /dev/null
  echo "$(basename "$input"): $(tail -1 "$out/time.txt"), $(stat -c %s "$out/out.wsp") bytes"
done
