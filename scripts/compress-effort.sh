#!/usr/bin/env bash
# What compression time buys: the MNI volume compressed to 1.25 % of its bytes with the defaults
# and with the flags that leave out the depth comparison (`--levels`) and the least-squares
# refinement's rounds (`--refine-rounds 0`: refits of the oracle's set only) or all of it
# (`--no-refine`), each timed (wall, min of REPEAT) and scored with the peers' metrics (Q_I, the
# paper's dB over the three X-ray views) beside SPERR at the same bytes, timed in the same run.
#   bash scripts/compress-effort.sh [REPEAT]
set -euo pipefail
source "$(dirname "$0")/peers_setup.sh" effort
N=${1:-3}
VOL="$ROOT/../shared/data/mni152_t1_1mm.nii.gz"
[ -f "$VOL" ] || { echo "needs $VOL" >&2; exit 1; }
TARGET=108441  # 1.25 % of the volume's 8 675 289 one-byte samples
min_seconds() {
  for _ in $(seq "$N"); do
    local s e; s=$(date +%s.%N); "$@" >/dev/null 2>&1; e=$(date +%s.%N); echo "$e - $s" | bc -l
  done | sort -g | head -1 | xargs printf '%.2f'
}
row() {
  local tag=$1; shift
  local t; t=$(min_seconds "$W" compress "$VOL" -o "$TMP/$tag.wsp" --target-bytes "$TARGET" "$@")
  "$W" decompress "$TMP/$tag.wsp" -o "$TMP/$tag.f32" >/dev/null
  local q; q=$(bash "$PEERS/run.sh" --eval "$TMP/$tag.f32" --variant full | sed -n 's/.*qi_mean: \([0-9.]*\).*/\1/p')
  echo "| \`${*:-(defaults)}\` | $t | $(stat -c %s "$TMP/$tag.wsp") | $q |"
}
echo "MNI 1.25 % ($TARGET bytes), $(nproc) cores, wall s min of $N"
echo
echo "| compress flags | s | bytes | Q_I (dB) |"
echo "|---|---|---|---|"
row defaults
row m2 --levels 2
row r0 --refine-rounds 0
row m2r0 --levels 2 --refine-rounds 0
row nr --no-refine
row m2nr --levels 2 --no-refine
row m3nr --levels 3 --no-refine
"$VENV/bin/python" - "$ROOT/scripts" "$TARGET" "$N" <<'EOF'
import sys
sys.path.insert(0, sys.argv[1])
import testset
from testset import peers
ref = peers.load_full()
size, _, dec, ts, _ = testset.sperr_timed([ref.astype("float32")], int(sys.argv[2]), int(sys.argv[3]))
m = peers.metrics(ref, peers.views(ref), dec[0])
print(f"| SPERR (one thread, same run) | {min(ts):.2f} | {size} | {m['qi_mean']:.2f} |")
EOF
