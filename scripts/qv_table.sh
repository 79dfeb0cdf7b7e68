#!/usr/bin/env bash
# Compressed size against Q_V (eq. 19, the oracle's kept energy) on the 128^3 MNI volume of
# ../shared/peers, per family, with the paper's oracle coefficients (--no-refine): the Q_V
# target picks the fewest coefficients whose energy reaches it. Prints a markdown table with
# the peers' mean Q_I of three X-ray views of the decoded volume.
#   bash scripts/qv_table.sh
set -euo pipefail
source "$(dirname "$0")/peers_setup.sh" qv
echo "| family | target Q_V % | coefficients | bytes | % of u8 size | Q_I mean (paper dB) |"
echo "|---|---|---|---|---|---|"
for family in haar linear cubic; do
  for qv in 90 95 98 99 99.5 99.9; do
    kept=$("$W" compress "$TMP/v128.raw" --dims 128,128,128 --dtype u8 --family "$family" \
        --target-qv "$qv" --no-refine -o "$TMP/q.wsp" | sed -n 2p | sed -E 's/.*kept ([0-9]+) of.*/\1/')
    size=$(stat -c %s "$TMP/q.wsp")
    "$W" decompress "$TMP/q.wsp" -o "$TMP/q.f32" >/dev/null
    qi=$(bash "$PEERS/run.sh" --eval "$TMP/q.f32" --variant v128 2>&1 | awk '/qi_mean/{print $2}')
    printf '| %s | %s | %s | %s | %.3f | %s |\n' "$family" "$qv" "$kept" "$size" \
      "$(python3 -c "print(100*$size/2097152)")" "$qi"
  done
done
