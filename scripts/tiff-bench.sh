#!/usr/bin/env bash
# Compresses one generated volume from a raw file, a directory of TIFF slices (Deflate), a
# multi-page BigTIFF (uncompressed), a multi-file OME-TIFF (four uncompressed files, the
# first's OME-XML placing every plane, as Micro-Manager writes one) and a multi-page BigTIFF
# whose pages are one Deflate strip each (as some writers store a compressed page), brick by
# brick, and prints each run's wall time and peak RSS: what reading a TIFF stack costs against
# raw samples. Needs python3 with numpy and tifffile (Debian: python3-numpy python3-tifffile)
# and a release build.
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
# The multi-file OME-TIFF: four files of a quarter of the slices each.
os.makedirs(f"{out}/ome", exist_ok=True)
files = 4
per = -(-depth // files)
name = lambda f: f"acq_{f}.ome.tif" if f else "acq.ome.tif"
tiff_data = "".join(
    f'<TiffData FirstZ="{f * per}" IFD="0" PlaneCount="{min(per, depth - f * per)}">'
    f'<UUID FileName="{name(f)}">urn:uuid:{f}</UUID></TiffData>'
    for f in range(files) if f * per < depth)
xml = (f'<?xml version="1.0" encoding="UTF-8"?><OME UUID="urn:uuid:0"><Image ID="Image:0">'
       f'<Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint16" SizeX="{side}" '
       f'SizeY="{side}" SizeZ="{depth}" SizeC="1" SizeT="1">{tiff_data}</Pixels></Image></OME>')
ome = None
strip = tifffile.TiffWriter(f"{out}/one_strip.tif", bigtiff=True)
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
        strip.write(s, compression="zlib", rowsperstrip=side, contiguous=False)
        if z % per == 0:
            if ome is not None:
                ome.close()
            ome = tifffile.TiffWriter(f"{out}/ome/{name(z // per)}", bigtiff=True)
            ome.write(s, contiguous=False, metadata=None,
                      description=xml if z == 0 else
                      '<OME><BinaryOnly MetadataFile="acq.ome.tif" UUID="urn:uuid:0"/></OME>')
        else:
            ome.write(s, contiguous=False, metadata=None)
ome.close()
strip.close()
raw.close()
EOF
fi
for input in "$raw" "$out/slices" "$out/multi.tif" "$out/ome/acq.ome.tif" "$out/one_strip.tif"; do
  /usr/bin/time -f "%e s wall, %M kB peak" "$bin" compress "$input" --brick "$brick" \
    --target-fraction 0.01 --effort fast -o "$out/out.wsp" 2> "$out/time.txt" > /dev/null
  echo "$(basename "$input"): $(tail -1 "$out/time.txt"), $(stat -c %s "$out/out.wsp") bytes"
done
