#!/usr/bin/env bash
# Compresses every volume of the test set (`testset.py make DIR`) at 0.15, 1.25 and 5.85 % of
# its sample bytes and prints, per point: target and file bytes, user CPU and wall seconds,
# Q_I / PSNR of the decoded volume, the depths compared (M:view error of the oracle's file) and
# each refinement the byte search ran (K:kept:bytes of the whole refined set).
#
#   scripts/testset-sweep.sh WAVESPLAT_BINARY TESTSET_DIR [TAG]    (PY= the peers' venv python;
#   ARGS= further compress options, e.g. ARGS="--coder fast")
set -euo pipefail
BIN=$1; D=$2; TAG=${3:-run}
PY=${PY:-python3}
read -r -a EXTRA <<< "${ARGS:-}"
HERE=$(cd "$(dirname "$0")" && pwd)
TMP=$(mktemp -d); trap 'rm -rf "$TMP"' EXIT
while IFS=$'\t' read -r name dims dt ch _; do
  vox=$(( $(echo "$dims" | tr ',' '*') ))
  case $dt in u8) bps=1 ;; u16|i16) bps=2 ;; f32) bps=4 ;; esac
  for pct in 15 125 585; do
    bytes=$(( vox * bps * ch * pct / 10000 ))
    O=$TMP/$name
    /usr/bin/time -f "%U %e" -o "$O.time" "$BIN" compress "$D/$name.raw" --dims "$dims" \
      --dtype "$dt" --channels "$ch" --target-bytes "$bytes" -o "$O.wsp" \
      --log wavesplat_compressor=debug "${EXTRA[@]}" 2>"$O.log" >/dev/null
    tries=$(sed 's/\x1b\[[0-9;]*m//g' "$O.log" | grep 'refined set encoded whole' \
      | sed 's/.*k=\([0-9]*\) count=\([0-9]*\) bytes=\([0-9]*\).*/\1:\2:\3/' | tr '\n' ' ' || true)
    depths=$(sed 's/\x1b\[[0-9;]*m//g' "$O.log" | grep 'depth candidate levels=' \
      | sed 's/.*levels=\([0-9]*\).*view_error=\(-\{0,1\}[0-9.]\{1,6\}\).*/M\1:\2/' | tr '\n' ' ' || true)
    "$BIN" decompress "$O.wsp" -o "$O.f32" >/dev/null
    q=$("$PY" "$HERE/testset.py" qi "$D" "$name" "$O.f32" | tr '\n' ' ')
    echo "$TAG $name $pct target $bytes got $(stat -c %s "$O.wsp") cpu_wall $(cat "$O.time") | $q| $depths| $tries"
  done
done < "$D/manifest.tsv"
