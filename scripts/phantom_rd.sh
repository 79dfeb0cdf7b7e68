#!/usr/bin/env bash
# Rate–distortion of wavesplat on the built-in phantoms (other content than the MNI volume the
# defaults were measured on): Shepp–Logan 128³, spheres 100×120×90, noise 64³, the RGB head
# 96³ (3 channels). Targets are percentages of one byte per sample. Prints a markdown table with
# the volume SNR and the mean Q_I (paper units) of the three axis X-ray views (sums of the
# decoded samples), against the f32 phantom itself.
#   bash scripts/phantom_rd.sh [BINARY]   (default: this checkout's release build)
# Needs numpy: uses the peers' venv (../shared/peers) like the other scripts.
set -euo pipefail
source "$(dirname "$0")/peers_setup.sh" phantoms
BIN="${1:-$W}"
PY="$VENV/bin/python"
cat > "$TMP/score.py" <<'PYEOF'
import sys, numpy as np
ref = np.fromfile(sys.argv[1], dtype=np.float32).astype(np.float64)
dec = np.fromfile(sys.argv[2], dtype=np.float32).astype(np.float64)
dims = [int(x) for x in sys.argv[3].split(',')]; ch = int(sys.argv[4])
ref = ref.reshape(dims[2], dims[1], dims[0], ch); dec = dec.reshape(ref.shape)
snr = 10*np.log10((ref**2).sum()/max(((ref-dec)**2).sum(), 1e-300))
qi = np.mean([20*np.log10((ref.sum(a)**2).sum()/max(((ref.sum(a)-dec.sum(a))**2).sum(), 1e-300))
              for a in range(3)])
print(f"{snr:.2f} | {qi:.2f}")
PYEOF
echo "| phantom | target % | bytes | volume SNR (dB) | Q_I mean (paper dB) |"
echo "|---|---|---|---|---|"
run() {  # name phantom dims channels pct...
  local name=$1 phantom=$2 dims=$3 ch=$4; shift 4
  "$BIN" phantom "$phantom" --dims "$dims" -o "$TMP/$name.raw" >/dev/null
  local n; n=$(python3 -c "import math; print(math.prod(int(x) for x in '$dims'.split(','))*$ch)")
  for pct in "$@"; do
    local b; b=$(python3 -c "print(int($n*$pct/100))")
    "$BIN" compress "$TMP/$name.raw" --dims "$dims" --dtype f32 --channels "$ch" \
      --target-bytes "$b" -o "$TMP/p.wsp" >/dev/null
    "$BIN" decompress "$TMP/p.wsp" -o "$TMP/p.f32" >/dev/null
    echo "| $name | $pct | $(stat -c %s "$TMP/p.wsp") | $("$PY" "$TMP/score.py" "$TMP/$name.raw" "$TMP/p.f32" "$dims" "$ch") |"
  done
}
run shepp-logan shepp-logan 128,128,128 1 0.5 2 5
run spheres spheres 100,120,90 1 0.5 2 5
run noise noise 64,64,64 1 5 20
run rgb-head rgb-head 96,96,96 3 0.5 2 5
