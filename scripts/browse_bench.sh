#!/usr/bin/env bash
# Browsing a cached volume over loopback (issue 11): compresses the MNI volume, serves it from a
# cache on 127.0.0.1, and renders an axis-aligned, an oblique and a zoomed-corner view from the
# cache with the progressive session at a 16.6 ms frame budget, recording per frame the time,
# the bytes received and Q_I against the image of all the data. Prints, per view, the time from
# the request (client start-up included) to the first image, Q_I (paper units, against the image of all the data: the
# splats' own error is not in it) when growing shares of the bytes had arrived and at fixed
# times, when everything had arrived and when the image had converged; the per-frame CSVs stay
# in OUT/VIEW/frames.csv and the PNGs of frames 1, 2, 4, … beside them.
#   bash scripts/browse_bench.sh [OUT_DIR] [BINARY]
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
OUT="${1:-$ROOT/out/browse}"
BIN="${2:-$ROOT/target/release/wavesplat}"
VOL="$ROOT/../shared/data/mni152_t1_1mm.nii.gz"
[ -x "$BIN" ] || (cd "$ROOT" && cargo build --release -q)
mkdir -p "$OUT"
[ -f "$OUT/mni.wsp" ] || "$BIN" compress "$VOL" -o "$OUT/mni.wsp" >/dev/null
PORT=$((20000 + RANDOM % 20000))
rm -rf "$OUT/cache"
"$BIN" serve cache --db "$OUT/cache" --addr "127.0.0.1:$PORT" 2>"$OUT/cache.log" &
CACHE=$!
trap 'kill $CACHE 2>/dev/null || true' EXIT
URL="http://127.0.0.1:$PORT"
for _ in $(seq 100); do
  "$BIN" cache list --cache "$URL" >/dev/null 2>&1 && break
  sleep 0.1
done
"$BIN" cache ingest "$OUT/mni.wsp" --name mni --cache "$URL" >/dev/null
echo "file: $(stat -c %s "$OUT/mni.wsp") bytes"
echo "| view | first image (ms) | Q_I when 10 % / 25 % / 50 % / 100 % of the bytes had arrived | Q_I at 100 / 250 / 500 ms | all bytes at (ms) | converged at (ms) | frames, p95 frame (ms) |"
echo "|---|---|---|---|---|---|---|"
view() {  # name, view options...
  local name=$1; shift
  rm -rf "$OUT/$name"
  local log
  log=$("$BIN" render --cache "$URL" --volume mni "$@" --size 256x256 --frame-ms 16.6 \
        --reference --record "$OUT/$name" -o "$OUT/$name.png" 2>/dev/null)
  local first
  first=$(echo "$log" | sed -n 's/.*first image \([0-9.]*\) ms.*/\1/p')
  python3 - "$OUT/$name/frames.csv" "$name" "$first" <<'PYEOF'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
total = float(rows[-1]["bytes"])
q = lambda r: float(r["q_i_paper_db"])
def at_bytes(frac):
    return next(r for r in rows if float(r["bytes"]) >= frac * total)
def at_time(ms):
    before = [r for r in rows if float(r["t_ms"]) <= ms]
    return q(before[-1]) if before else float("nan")
qb = " / ".join(f"{q(at_bytes(f)):.1f}" for f in (0.1, 0.25, 0.5, 1.0))
qt = " / ".join(f"{at_time(ms):.1f}" for ms in (100, 250, 500))
done = next(r for r in rows if int(r["pending"]) == 0 and float(r["bytes"]) >= total)
frames = sorted(float(r["frame_ms"]) for r in rows[:-1] or rows)
p95 = frames[min(len(frames) - 1, int(0.95 * len(frames)))]
print(f"| {sys.argv[2]} | {sys.argv[3]} | {qb} | {qt} | {float(at_bytes(1.0)['t_ms']):.0f} "
      f"| {float(done['t_ms']):.0f} | {len(rows)}, {p95:.1f} |")
PYEOF
}
view axis --alpha 0 --beta 0
view oblique --alpha 0.66 --beta 0.91
view zoomed-corner --alpha 0.66 --beta 0.91 --zoom 3 --pan 40,40
