#!/usr/bin/env bash
# Rate–distortion curve of wavesplat on the 128^3 MNI volume used by ../shared/peers, scored
# with the peers' own metrics (Q_I of three X-ray views, PSNR). Prints a markdown table.
#   bash scripts/rd_curve.sh [extra compress options...]
# Needs ../shared beside the repository (the peers' venv is created on first use).
set -euo pipefail
source "$(dirname "$0")/peers_setup.sh" rd
echo "| target % | bytes | coefficients | Q_I mean (paper dB) | iSNR (dB) | PSNR (dB) | compress s |"
echo "|---|---|---|---|---|---|---|"
for pct in 0.07 0.15 0.5 1.25 3.0 5.85; do
  bytes=$(python3 -c "print(int(2097152*$pct/100))")
  start=$(date +%s.%N)
  kept=$("$W" compress "$TMP/v128.raw" --dims 128,128,128 --dtype u8 --target-bytes "$bytes" \
      -o "$TMP/v.wsp" "$@" | sed -n 2p | sed -E 's/.*kept ([0-9]+) of.*/\1/')
  end=$(date +%s.%N)
  size=$(stat -c %s "$TMP/v.wsp")
  "$W" decompress "$TMP/v.wsp" -o "$TMP/v.f32" >/dev/null
  eval_out=$(bash "$PEERS/run.sh" --eval "$TMP/v.f32" --variant v128 2>&1)
  qi=$(echo "$eval_out" | awk '/qi_mean/{print $2}')
  isnr=$(echo "$eval_out" | awk '/isnr_mean/{print $2}')
  psnr=$(echo "$eval_out" | awk '/^psnr/{print $2}')
  printf '| %s | %s | %s | %s | %s | %s | %.2f |\n' "$pct" "$size" "$kept" "$qi" "$isnr" "$psnr" \
    "$(python3 -c "print($end-$start)")"
done
