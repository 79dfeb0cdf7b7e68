#!/usr/bin/env bash
# The speed rows of issue 35 measured side by side in one run on the real MRI volume
# (../shared/data), against SPERR through its HDF5 filter (the peers' venv, created on first
# use): compression to 1.25 % of the bytes, decompression, `render` from process start to the
# PNG (one pass and --progressive), bytes in memory to the exact image (`stages`), decoding per
# core (codec's `decode` example, one thread) and on the pool, and splat accumulation against
# the same-loop ceiling (`bench throughput`), the last byte and convergence of a 10 Mbit/s session
# (`bench refine`), and compression of the test set's thin MR slab and RGB volume against SPERR
# (`testset.py`, written once). Prints a markdown table; REPEAT runs each (min and median). Run it
# on a quiet machine: every figure is wall time.
#   bash scripts/speed-table.sh [REPEAT]
set -euo pipefail
source "$(dirname "$0")/peers_setup.sh" speed
N=${1:-5}
VOL="$ROOT/../shared/data/mni152_t1_1mm.nii.gz"
[ -f "$VOL" ] || { echo "needs $VOL" >&2; exit 1; }
cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml" -p wavesplat-viewer --example stages
cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml" -p wavesplat-codec --example decode
EX="$ROOT/target/release/examples"
TARGET=108441  # 1.25 % of the volume's 8 675 289 one-byte samples
F="$TMP/mni125.wsp"

# min and median of the numbers on stdin
stats() { sort -g | awk '{v[NR]=$1} END {printf "%.3g / %.3g", v[1], v[int((NR+1)/2)]}'; }
seconds() { local s e; s=$(date +%s.%N); "$@" >/dev/null 2>&1; e=$(date +%s.%N); echo "$e - $s" | bc -l; }

comp=$(for _ in $(seq "$N"); do seconds "$W" compress "$VOL" -o "$F" --target-bytes "$TARGET"; done | stats)
bytes=$(stat -c %s "$F")
sperr=$("$VENV/bin/python" - "$ROOT/scripts" "$VOL" "$bytes" "$N" <<'EOF'
import sys
sys.path.insert(0, sys.argv[1])
import numpy as np, nibabel as nib, testset
v = np.asarray(nib.load(sys.argv[2]).dataobj).astype(np.float32)
x = np.ascontiguousarray(v.transpose(2, 1, 0))
size, _, _, ct, dt = testset.sperr_timed([x], int(sys.argv[3]), int(sys.argv[4]))
st = lambda a: f"{min(a):.3g} / {sorted(a)[(len(a) - 1) // 2]:.3g}"
print(f"{size}|{st(ct)}|{st(dt)}")
EOF
)
IFS='|' read -r sperr_bytes sperr_comp sperr_dec <<<"$sperr"

render_done() { "$W" render "$F" -o "$TMP/r.png" --cpu "$@" | sed -n 's/.*done \([0-9.]*\) ms.*/\1/p'; }
one=$(for _ in $(seq "$N"); do seconds "$W" render "$F" -o "$TMP/r.png" --cpu; done | stats)
one_done=$(for _ in $(seq "$N"); do render_done; done | stats)
prog=$(for _ in $(seq "$N"); do seconds "$W" render "$F" -o "$TMP/r.png" --cpu --progressive; done | stats)
prog_done=$(for _ in $(seq "$N"); do render_done --progressive; done | stats)
stages=$("$EX/stages" "$F" 256 15)
inproc=$(echo "$stages" | sed -n 's/^bytes to exact image: \([0-9.]*\) ms.*/\1/p')
onepass=$(echo "$stages" | sed -n 's/^one pass (draw_whole_file): \([0-9.]*\) ms.*/\1/p')
core=$("$EX/decode" "$F" 30 | sed -n 's/.*, \([0-9.]*\) M coefficients\/s.*/\1/p')
tp=$("$W" bench throughput "$VOL" -o "$TMP/throughput.csv" 2>/dev/null)
field() { echo "$tp" | awk -v k="$1" -v c="$2" 'index($0, k) == 1 {print $c}'; }
dec=$(field "linear decode" 5)
lin=$(field "linear splat 256" 8)
cub=$(field "cubic splat 512" 8)
# the accumulation loop over each view's own footprints (the figure after "loop's")
view_ceil() { echo "$tp" | awk -v k="$1" 'index($0, k) == 1 {for (i = 1; i < NF; i++) if ($i == "loop'"'"'s") print $(i + 1)}'; }
lin_ceil=$(view_ceil "linear splat 256")
cub_ceil=$(view_ceil "cubic splat 512")
ceil16=$(field "accumulation loop, 16x16" 5)
ceil48=$(field "accumulation loop, 48x48" 5)
threads=$(echo "$tp" | sed -n 's/.* voxels, \([0-9]*\) threads.*/\1/p')
g() { echo "($1) / 1000000000" | bc -l | xargs printf '%.2f'; }
ratio() { echo "($1) / ($2)" | bc -l | xargs printf '%.2f'; }

# The issue's link row: MNI at 5 % over a simulated 10 Mbit/s link, 16.6 ms frames; the last
# byte the session takes and its first converged frame, from the step opened at rest (step 0).
"$W" bench refine --volume "$VOL" --budgets 16.6 --links 10 --no-table4 --cpu --out "$TMP/refine" >/dev/null 2>&1
link=$(awk -F, 'NR > 1 && $4 == 0 {if ($8 > mb) {mb = $8; tb = $5} if ($17 == "true" && !c) c = $5}
  END {printf "last byte %.0f ms, converged %.0f ms (%.0f ms later; %d bytes)", tb, c, c - tb, mb}' "$TMP/refine/refine.csv")

# The other volumes of the compression row: the test set's 16-slice MR slab and its RGB volume
# at 1.25 % of their sample bytes, against SPERR at the same bytes (per channel, one rate).
TS="$TMP/testset"
for v in slab16 mni-rgb; do
  grep -q "^$v	" "$TS/manifest.tsv" 2>/dev/null || "$VENV/bin/python" "$ROOT/scripts/testset.py" make "$TS" --only "$v" >/dev/null
done
others=""
while IFS=$'\t' read -r name dims dt ch _; do
  case $name in slab16|mni-rgb) ;; *) continue ;; esac
  target=$(( $(echo "$dims" | tr ',' '*') * ch * 125 / 10000 ))
  t=$(for _ in $(seq "$N"); do seconds "$W" compress "$TS/$name.raw" --dims "$dims" --dtype "$dt" \
      --channels "$ch" --target-bytes "$target" -o "$TMP/$name.wsp"; done | stats)
  "$W" decompress "$TMP/$name.wsp" -o "$TMP/$name.f32" >/dev/null
  q=$("$VENV/bin/python" "$ROOT/scripts/testset.py" qi "$TS" "$name" "$TMP/$name.f32" | awk '{print $2}')
  s=$("$VENV/bin/python" - "$ROOT/scripts" "$TS" "$name" "$target" "$N" <<'EOF'
import sys
sys.path.insert(0, sys.argv[1])
import numpy as np, testset
ref, _ = testset.load(sys.argv[2], sys.argv[3])
chans = [np.ascontiguousarray(ref[..., c]) for c in range(ref.shape[3])]
size, _, dec, ts, _ = testset.sperr_timed(chans, int(sys.argv[4]), int(sys.argv[5]))
q, _ = testset.qi_psnr(ref, np.stack(dec, axis=-1))
print(f"{min(ts):.3g} / {sorted(ts)[(len(ts) - 1) // 2]:.3g} s ({size} bytes), Q_I {q:.2f} dB")
EOF
)
  others="$others| compress $name ($dims x$ch) to 1.25 %, defaults (s) | $t, Q_I $q dB | SPERR $s |
"
done < "$TS/manifest.tsv"

echo "MNI 1.25 %: wavesplat $bytes bytes, SPERR $sperr_bytes bytes; $(nproc) cores; min / median of $N"
echo
echo "| row | wavesplat | reference |"
echo "|---|---|---|"
echo "| compress MNI to 1.25 %, defaults (s) | $comp | SPERR $sperr_comp (one thread) |"
printf '%s' "$others"
echo "| file → 256² image, \`render --cpu\`, process start to PNG (s) | one pass $one; --progressive $prog | SPERR decompress alone $sperr_dec |"
echo "| the same, done after the request (ms) | one pass $one_done; --progressive $prog_done | |"
echo "| bytes in memory → exact 256² image (ms, median of 15) | stages $inproc; one pass $onepass | |"
echo "| MNI 5 % over 10 Mbit/s, 16.6 ms frames (\`bench refine\`) | $link | |"
echo "| decode, default coder (M coefficients/s) | $core per core (one thread); $(echo "$dec / 1000000" | bc -l | xargs printf '%.1f') on $threads threads (MNI 5 %) | |"
echo "| splat, linear 256² / cubic 512² (G pixel updates/s per core, MNI 5 %) | $(g "$lin / $threads") / $(g "$cub / $threads") | ceiling 16² $(g "$ceil16"), 48² $(g "$ceil48") per core: cubic at $(ratio "$cub / $threads" "$ceil48") of 48², linear at $(ratio "$lin / $threads" "$ceil16") of 16²; the loop over each view's own footprints $(g "$lin_ceil") / $(g "$cub_ceil"): $(ratio "$lin / $threads" "$lin_ceil") / $(ratio "$cub / $threads" "$cub_ceil") of it |"
