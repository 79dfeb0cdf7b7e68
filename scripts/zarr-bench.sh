#!/usr/bin/env bash
# Compresses one generated volume from a raw file and from Zarr stores of the same samples
# (zarr-python: a v3 array of 64³ Zstd chunks, the same chunks in 256³ shards, a v2 array of
# 128³ Blosc-LZ4 chunks, an OME-Zarr 0.4 image of 64³ chunks with a lower resolution beside
# it, a v2 array of 64³ gzip chunks: the reader inflates each gzip chunk once to check its size
# before zarrs inflates it, a v3 array of Zstd chunks of one whole plane), brick by brick, and prints each run's wall time, peak RSS and bytes: what reading a
# chunked store costs against one raw file. All must give the same file. Needs a Python with
# zarr-python (`PYTHON`, default the venv `.ci/run` makes) and a release build.
#
#   bash scripts/zarr-bench.sh [SIDE=512] [DEPTH=SIDE] [BRICK=256] [OUT=/tmp/wavesplat-zarr-bench]
set -euo pipefail
cd "$(dirname "$0")/.."
side=${1:-512}
depth=${2:-$side}
brick=${3:-256}
out=${4:-/tmp/wavesplat-zarr-bench}
bin=${WAVESPLAT:-target/release/wavesplat}
python=${PYTHON:-${WAVESPLAT_ZARR_PYTHON:-$HOME/.cache/wavesplat/zarr-venv/bin/python}}
mkdir -p "$out"
raw="$out/vol_${side}x${side}x${depth}_u16.raw"
if [ ! -f "$raw" ]; then
  "$python" - "$out" "$side" "$depth" <<'PY'
import sys
import numpy as np
import zarr, numcodecs
from zarr.codecs import ZstdCodec
out, side, depth = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rng = np.random.default_rng(1)
y, x = np.mgrid[0:side, 0:side].astype(np.float32) / side
shape = (depth, side, side)
stores = {
    "v3_zstd.zarr": zarr.create_array(f"{out}/v3_zstd.zarr", shape=shape, chunks=(64, 64, 64),
                                      dtype="u2", compressors=ZstdCodec(level=1)),
    "v3_sharded.zarr": zarr.create_array(f"{out}/v3_sharded.zarr", shape=shape, shards=(256, 256, 256),
                                         chunks=(64, 64, 64), dtype="u2", compressors=ZstdCodec(level=1)),
    "v2_blosc.zarr": zarr.create_array(f"{out}/v2_blosc.zarr", shape=shape, chunks=(128, 128, 128),
                                       dtype="u2", zarr_format=2, compressors=numcodecs.Blosc(cname="lz4")),
}
ome = zarr.open_group(f"{out}/image.ome.zarr", mode="w", zarr_format=2)
full = ome.create_array("0", shape=shape, chunks=(64, 64, 64), dtype="u2")
half = ome.create_array("1", shape=tuple(-(-s // 2) for s in shape), chunks=(64, 64, 64), dtype="u2")
axes = [{"name": n, "type": "space", "unit": "millimeter"} for n in "zyx"]
ome.attrs["multiscales"] = [{"version": "0.4", "axes": axes, "datasets": [
    {"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1.0, 1.0, 1.0]}]},
    {"path": "1", "coordinateTransformations": [{"type": "scale", "scale": [2.0, 2.0, 2.0]}]}]}]
raw = open(f"{out}/vol_{side}x{side}x{depth}_u16.raw", "wb")
for z0 in range(0, depth, 128):
    slab = []
    for z in range(z0, min(z0 + 128, depth)):
        t = z / depth
        blob = np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2 + (t - 0.5) ** 2) / 0.05)
        rings = 0.3 * np.sin(40 * np.hypot(x - 0.4, y - 0.6) + 8 * t)
        s = (20000 * (blob + rings + 1.0) + rng.normal(0, 200, x.shape)).clip(0, 65535)
        slab.append(s.astype("<u2"))
    slab = np.stack(slab)
    raw.write(slab.tobytes())
    for a in list(stores.values()) + [full]:
        a[z0:z0 + len(slab)] = slab
    half[z0 // 2:(z0 + len(slab) + 1) // 2] = slab[::2, ::2, ::2]
raw.close()
PY
fi
if [ ! -d "$out/v3_planes.zarr" ]; then
  # Chunks of one whole plane, as a stack of slices converted plane by plane is often stored:
  # every brick across a plane shares its chunk.
  "$python" - "$raw" "$out/v3_planes.zarr" "$side" "$depth" <<'PY'
import sys
import numpy as np
import zarr
from zarr.codecs import ZstdCodec
raw, store, side, depth = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
samples = np.memmap(raw, dtype="<u2", mode="r", shape=(depth, side, side))
a = zarr.create_array(store, shape=samples.shape, chunks=(1, side, side), dtype="u2",
                      compressors=ZstdCodec(level=1))
for z0 in range(0, depth, 128):
    a[z0:z0 + 128] = samples[z0:z0 + 128]
PY
fi
if [ ! -d "$out/v2_gzip.zarr" ]; then
  "$python" - "$raw" "$out/v2_gzip.zarr" "$side" "$depth" <<'PY'
import sys
import numpy as np
import zarr, numcodecs
raw, store, side, depth = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
samples = np.memmap(raw, dtype="<u2", mode="r", shape=(depth, side, side))
a = zarr.create_array(store, shape=samples.shape, chunks=(64, 64, 64), dtype="u2", zarr_format=2,
                      compressors=numcodecs.GZip(level=1))
for z0 in range(0, depth, 128):
    a[z0:z0 + 128] = samples[z0:z0 + 128]
PY
fi
for input in "$raw" "$out/v3_zstd.zarr" "$out/v3_sharded.zarr" "$out/v2_blosc.zarr" "$out/image.ome.zarr" \
  "$out/v2_gzip.zarr" "$out/v3_planes.zarr"; do
  /usr/bin/time -f "%e s wall, %M kB peak" "$bin" compress "$input" --brick "$brick" \
    --target-fraction 0.01 --effort fast -o "$out/out.wsp" 2> "$out/time.txt" > /dev/null
  echo "$(basename "$input"): $(tail -1 "$out/time.txt"), $(stat -c %s "$out/out.wsp") bytes, md5 $(md5sum < "$out/out.wsp" | cut -c1-12)"
done
