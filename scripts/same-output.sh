#!/usr/bin/env bash
# Shows that two builds of `wavesplat` write the same bytes: every .wsp a set of compressions
# writes (phantoms of every kind, every coder, colour space, family, layering and format
# version, and the real MRI volume when ../shared/data has it) and every image a set of renders
# draws from them (single view, multiview, depth cue, clipped margins, every family) and every
# volume `decompress` decodes from them must be byte-identical, and `bench stability --quick`
# (the one-shot renderer against the reference ray caster on stiff cases) must give the same
# errors. A render of a whole local file is one pass (`open::draw_whole_file`); the flags
# below (`--no-preview --frame-ms 60000`: exact tables from the start, one long frame) make
# builds before it render in one batch too: a progressive render splats in batches that follow the clock, and f32
# sums in another order differ in the last bits (~1e-6 of the peak, measured between two runs
# of one build), so only the one-batch render is bit-reproducible. A depth-cued view draws
# coefficients whose cut tables are still being built with stand-ins first (even then), so
# its renders (marked `~`) must agree within 1e-5 of the image's peak instead. A restructure that
# claims "no change of behaviour" runs this with the build before and the build after.
#
#   bash scripts/same-output.sh BIN_BEFORE BIN_AFTER [WORKDIR]
#
# Prints one line per artefact and exits non-zero when any differs.
set -euo pipefail
A=$(realpath "$1")
B=$(realpath "$2")
W=${3:-$(mktemp -d)}
mkdir -p "$W/a" "$W/b"
HERE=$(cd "$(dirname "$0")/.." && pwd)
MNI="$HERE/../shared/data/mni152_t1_1mm.nii.gz"

# name | compress arguments
COMPRESS=(
  "shepp|--phantom shepp-logan --dims 48,40,36"
  "shepp-haar|--phantom shepp-logan --family haar --dims 32,32,32"
  "shepp-cubic|--phantom shepp-logan --family cubic --dims 40,40,40 --target-fraction 0.02"
  "shepp-fast|--phantom shepp-logan --coder fast --dims 48,48,48"
  "shepp-range|--phantom shepp-logan --coder range --dims 32,32,32"
  "shepp-huffman|--phantom shepp-logan --coder huffman --dims 32,32,32 --no-refine"
  "shepp-bytes|--phantom shepp-logan --dims 64,64,64 --target-bytes 20000"
  "shepp-v7|--phantom shepp-logan --dims 48,48,48 --no-coarse-layer --layer-growth 4"
  "shepp-single|--phantom shepp-logan --dims 32,32,32 --single-sequence"
  "spheres|--phantom spheres --dims 40,33,27 --margin 0"
  "rgb-pca|--phantom rgb-head --dims 40,40,40"
  "rgb-yiq|--phantom rgb-head --dims 32,32,32 --colorspace yiq --target-qv 99"
  "rgb-rgb|--phantom rgb-head --dims 32,32,32 --colorspace rgb --lossless-selection"
  "constant|--phantom constant --dims 16,16,16"
  "zero|--phantom zero --dims 8,8,8"
  "noise|--phantom noise --dims 24,24,24 --tile 8"
  "ct|--phantom ct --dims 32,28,24"
  "bricked|--phantom shepp-logan --dims 48,40,36 --brick 24 --target-fraction 0.05"
)
if [[ -f "$MNI" ]]; then
  COMPRESS+=("mni|$MNI --target-fraction 0.0125")
fi

# [~]file | render arguments (`~`: equal within 1e-5 of the peak, see above)
RENDER=(
  "shepp|--alpha 0.3 --beta 0.2"
  "shepp|--multiview --size 96x96"
  "~shepp|--cue-k 0.05 --size 128x96"
  "shepp|--alpha 0 --beta 0"
  "shepp-haar|--alpha 0.4 --beta 1.2"
  "~shepp-cubic|--alpha 1.0 --beta 0.5 --cue-k 0.02 --cue-dir 0.2,0.3"
  "shepp-fast|--bytes 4000"
  "shepp-v7|--alpha 1.5707963 --beta 0"
  "spheres|--alpha 0.7 --beta 0.1"
  "rgb-pca|--multiview --size 64x64"
  "rgb-yiq|--alpha 0.2 --beta 0.9"
  "constant|"
  "noise|--zoom 3 --pan 2,1"
  "ct|--alpha 0.3 --beta 0.4"
  "bricked|--alpha 0.3 --beta 0.2"
  "bricked|--multiview --size 96x96"
)
if [[ -f "$MNI" ]]; then
  RENDER+=("mni|" "mni|--view anterior" "~mni|--cue-k 0.01")
fi

status=0
compare() { # what, file a, file b
  if cmp -s "$2" "$3"; then echo "same      $1"; else echo "DIFFERENT $1"; status=1; fi
}
for entry in "${COMPRESS[@]}"; do
  name=${entry%%|*}; args=${entry#*|}
  for side in a b; do
    bin=$A; [[ $side == b ]] && bin=$B
    # shellcheck disable=SC2086
    "$bin" compress $args -o "$W/$side/$name.wsp" >/dev/null 2>"$W/$side/$name.compress.err"
  done
  compare "$name.wsp" "$W/a/$name.wsp" "$W/b/$name.wsp"
  for side in a b; do
    bin=$A; [[ $side == b ]] && bin=$B
    "$bin" decompress "$W/$side/$name.wsp" -o "$W/$side/$name.f32" >/dev/null 2>&1
  done
  compare "decompress $name" "$W/a/$name.f32" "$W/b/$name.f32"
done
i=0
for entry in "${RENDER[@]}"; do
  name=${entry%%|*}; args=${entry#*|}; i=$((i + 1)); close=0
  if [[ $name == "~"* ]]; then name=${name#\~}; close=1; fi
  for side in a b; do
    bin=$A; [[ $side == b ]] && bin=$B
    # shellcheck disable=SC2086
    "$bin" render "$W/$side/$name.wsp" --cpu --no-preview --frame-ms 60000 $args -o "$W/$side/r$i.png" --raw "$W/$side/r$i.f32" \
      >/dev/null 2>"$W/$side/r$i.err"
  done
  if [[ $close == 1 ]]; then
    if python3 - "$W/a/r$i.f32" "$W/b/r$i.f32" <<'EOF'
import array, sys
a = array.array("f", open(sys.argv[1], "rb").read())
b = array.array("f", open(sys.argv[2], "rb").read())
peak = max((abs(x) for x in a), default=0.0)
sys.exit(0 if len(a) == len(b) and all(abs(x - y) <= 1e-5 * peak for x, y in zip(a, b)) else 1)
EOF
    then echo "close     render $i ($name $args)"; else echo "DIFFERENT render $i ($name $args)"; status=1; fi
  else
    compare "render $i ($name $args)" "$W/a/r$i.f32" "$W/b/r$i.f32"
    compare "render $i PNG" "$W/a/r$i.png" "$W/b/r$i.png"
  fi
done
for side in a b; do
  bin=$A; [[ $side == b ]] && bin=$B
  "$bin" bench stability --quick --out "$W/$side/stability" >/dev/null 2>&1 || true
  # The error columns only: drop any column whose header names a time.
  python3 - "$W/$side/stability/stability.csv" >"$W/$side/stability.errors" <<'EOF'
import csv, sys
rows = list(csv.reader(open(sys.argv[1])))
keep = [i for i, h in enumerate(rows[0]) if "ms" not in h and "time" not in h and "second" not in h]
for r in rows:
    print(",".join(r[i] for i in keep))
EOF
done
compare "bench stability --quick (errors)" "$W/a/stability.errors" "$W/b/stability.errors"
exit $status
