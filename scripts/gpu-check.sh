#!/usr/bin/env bash
# The GPU backend on whatever adapter wgpu finds (issue 57, part 3): one prepared run that puts
# the device's figures beside the CPU's.
#
# For the MNI volume at 1.25 % and 5 % of its coefficients (a 128³ Shepp-Logan phantom when
# ../shared/data lacks it), at 256², 512² and 1024²:
#   - the image of the GPU backend against the CPU's (SNR, dB; goal > 100 dB: the same
#     coefficients summed in another order),
#   - splats per second of each backend in the one-pass render (its splatting stage: records
#     made on the CPU, accumulated, the image read back),
#   - the GPU's mean frame time in the progressive frame loop (frames at 16.6 ms budgets),
# and `render FILE -o x.png` from process start to PNG (the default backend choice) against the
# process floor (`wavesplat --version`). Prints a markdown table and writes gpu-check.csv.
# With BACKEND_BENCH naming the viewer's `backend` bench binary (`cargo bench -p
# wavesplat-viewer --bench backend --no-run` prints its path), it also times the display pass
# (accumulated sums → the texture a window draws) at 256², 512² and 1024² and writes
# display.csv.
#
#   bash scripts/gpu-check.sh [OUT_DIR] [--quick]
#
# --quick: the phantom at 64³, 256² only (what CI runs on lavapipe, the software Vulkan driver,
# to keep the script working where there is no GPU). WAVESPLAT_BIN picks another build;
# WAVESPLAT_VOLUME another volume (default ../shared/data/mni152_t1_1mm.nii.gz).
# Exits non-zero when a render fails or the GPU's image differs from the CPU's by more than
# summation order (below 60 dB; the > 100 dB goal is reported, not enforced).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
OUT="${1:-$ROOT/out/gpu-check}"
QUICK="${2:-}"
BIN="${WAVESPLAT_BIN:-$ROOT/target/release/wavesplat}"
[ -x "$BIN" ] || (cd "$ROOT" && cargo build --release -q)
mkdir -p "$OUT"
VOL="${WAVESPLAT_VOLUME:-$ROOT/../shared/data/mni152_t1_1mm.nii.gz}"
SIZES="256 512 1024"
FRACTIONS="0.0125 0.05"
if [ "$QUICK" = "--quick" ]; then
  SIZES="256"
  FRACTIONS="0.05"
  VOL=""
fi
source_args() {
  if [ -n "$VOL" ] && [ -f "$VOL" ]; then
    echo "$VOL"
  elif [ "$QUICK" = "--quick" ]; then
    echo "--phantom shepp-logan --dims 64,64,64"
  else
    echo "--phantom shepp-logan --dims 128,128,128"
  fi
}
NAME=$( [ -n "$VOL" ] && [ -f "$VOL" ] && echo mni || echo phantom )
ms_now() { date +%s%N | awk '{printf "%.1f", $1 / 1e6}'; }

CSV="$OUT/gpu-check.csv"
echo "volume,fraction,size,device,snr_db,cpu_splats_per_s,gpu_splats_per_s,gpu_frame_ms" > "$CSV"
DEVICE=""
WORST=1000
echo "| volume | kept | image | GPU vs CPU (dB) | CPU splats/s | GPU splats/s | GPU frame (ms, progressive) |"
echo "|---|---|---|---|---|---|---|"
for f in $FRACTIONS; do
  FILE="$OUT/$NAME-$f.wsp"
  # shellcheck disable=SC2046
  "$BIN" compress $(source_args) --target-fraction "$f" -o "$FILE" >/dev/null
  for s in $SIZES; do
    cpu=$("$BIN" render "$FILE" --cpu --size "${s}x${s}" -o "$OUT/cpu.png" --raw "$OUT/cpu.f32" 2>&1)
    gpu=$("$BIN" render "$FILE" --gpu --size "${s}x${s}" -o "$OUT/gpu.png" --raw "$OUT/gpu.f32" 2>&1)
    prog=$("$BIN" render "$FILE" --gpu --progressive --frame-ms 16.6 --size "${s}x${s}" -o "$OUT/prog.png" 2>&1)
    DEVICE=$(echo "$gpu" | sed -n 's/^backend: gpu (\(.*\)) (asked for)$/\1/p' | head -1)
    coeffs=$(echo "$cpu" | sed -n 's/.* \([0-9]\+\) coefficients splatted.*/\1/p' | head -1)
    cpu_ms=$(echo "$cpu" | sed -n 's/.*splatting \([0-9.]\+\) ms.*/\1/p')
    gpu_ms=$(echo "$gpu" | sed -n 's/.*splatting \([0-9.]\+\) ms.*/\1/p')
    frames=$(echo "$prog" | sed -n 's/.* \([0-9]\+\) frames in \([0-9.]\+\) ms.*/\1 \2/p')
    read -r snr cpu_rate gpu_rate frame_ms < <(python3 - "$OUT/cpu.f32" "$OUT/gpu.f32" "$coeffs" "$cpu_ms" "$gpu_ms" "$frames" <<'PY'
import array, math, sys
def load(p):
    a = array.array("f")
    with open(p, "rb") as f:
        a.frombytes(f.read())
    return a
c, g = load(sys.argv[1]), load(sys.argv[2])
signal = sum(x * x for x in c)
noise = sum((x - y) ** 2 for x, y in zip(c, g))
snr = 300.0 if noise == 0 else 10 * math.log10(signal / noise) if signal > 0 else 0.0
n = float(sys.argv[3])
rate = lambda ms: n / (float(ms) / 1e3) if ms and float(ms) > 0 else 0.0
frames = sys.argv[6].split()
frame_ms = float(frames[1]) / int(frames[0]) if len(frames) == 2 and int(frames[0]) > 0 else 0.0
print(f"{snr:.1f} {rate(sys.argv[4]):.3g} {rate(sys.argv[5]):.3g} {frame_ms:.1f}")
PY
)
    echo "| $NAME | $f | ${s}² | $snr | $cpu_rate | $gpu_rate | $frame_ms |"
    echo "$NAME,$f,$s,\"$DEVICE\",$snr,$cpu_rate,$gpu_rate,$frame_ms" >> "$CSV"
    WORST=$(python3 -c "print(min($WORST, $snr))")
  done
done
# Start-up: process start to PNG with the default backend choice, against the process floor.
LAST="$OUT/$NAME-$(echo "$FRACTIONS" | awk '{print $NF}').wsp"
t0=$(ms_now); "$BIN" --version >/dev/null; t1=$(ms_now)
"$BIN" render "$LAST" -o "$OUT/start.png" >/dev/null 2>&1; t2=$(ms_now)
floor=$(python3 -c "print(f'{$t1 - $t0:.1f}')")
start=$(python3 -c "print(f'{$t2 - $t1:.1f}')")
echo
echo "device: ${DEVICE:-none found}"
if [ -n "${BACKEND_BENCH:-}" ]; then
  # Criterion prints each benchmark's name, then "time: [low median high]" (on the same line
  # when the name is short).
  "$BACKEND_BENCH" --bench display --warm-up-time 1 --measurement-time 3 2>/dev/null \
    | python3 -c '
import re, sys
for m in re.finditer(r"^(display/\S+ [a-z ]+?)\s+time:\s+\[\S+ \S+ (\S+ \S+)", sys.stdin.read(), re.M):
    print(f"{m.group(1)},{m.group(2)}")' > "$OUT/display.txt"
  echo "display pass (median): $(tr '\n' ';' < "$OUT/display.txt")"
  { echo "pass,median"; cat "$OUT/display.txt"; } > "$OUT/display.csv"
fi
echo "render start-up (process start → PNG, default backend, 256²): $start ms; process floor $floor ms"
if python3 -c "import sys; sys.exit(0 if $WORST >= 60 else 1)"; then
  python3 -c "print('GPU against CPU: worst %.1f dB (goal > 100 dB: %s)' % ($WORST, 'met' if $WORST > 100 else 'not met'))"
else
  echo "GPU against CPU: worst $WORST dB: the images differ by more than summation order" >&2
  exit 1
fi
