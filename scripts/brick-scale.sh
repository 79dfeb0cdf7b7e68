#!/usr/bin/env bash
# How bricked compression scales with the volume's size (issue 55): the CT phantom (air, fat,
# soft tissue, lungs, a vertebra, ribs and seeded noise) at N³ voxels, generated a brick at a
# time by `compress --phantom ct --brick B` (no file, nothing holds the whole), compressed with
# one and with two threads (each pinned with taskset to as many cores), timed (wall) with its
# peak resident memory (`/usr/bin/time`). One CSV row a run, and a Markdown table on stdout.
#   bash scripts/brick-scale.sh [SIZES] [THREADS] [BRICK] [FRACTION]
#   e.g. bash scripts/brick-scale.sh "256 512 1024" "1 2" 256 0.01
# SIZES: edges N (default "256 512"); THREADS: thread counts (default "1 2"; more than the
# machine's cores are skipped); BRICK: brick edge (default 256); FRACTION: the share of
# coefficients kept (default 0.01; a fraction, not a byte target, so that each run compresses
# every brick once and the time is the compressor's, not a rate search's).
# Writes $TMPDIR/wavesplat-scale/scale.csv (size,threads,brick,bricks,seconds,peak_rss_mb,
# bytes,ns_per_voxel_core,load_before) and leaves the compressed files beside it.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
SIZES=${1:-"256 512"}
THREADS=${2:-"1 2"}
BRICK=${3:-256}
FRACTION=${4:-0.01}
W="$ROOT/target/release/wavesplat"
TMP="${TMPDIR:-/tmp}/wavesplat-scale"
mkdir -p "$TMP"
command -v /usr/bin/time >/dev/null || { echo "needs /usr/bin/time (apt install time)" >&2; exit 1; }
command -v taskset >/dev/null || { echo "needs taskset (util-linux)" >&2; exit 1; }
cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml" --bin wavesplat
CSV="$TMP/scale.csv"
echo "size,threads,brick,bricks,seconds,peak_rss_mb,bytes,ns_per_voxel_core,load_before" >"$CSV"
CORES=$(nproc)
echo "CT phantom, bricks of $BRICK, $FRACTION of the coefficients kept, $CORES cores, $(date -u +%F)"
echo
echo "| volume | threads | bricks | wall s | peak RSS | bytes | ns per voxel and core |"
echo "|---|---|---|---|---|---|---|"
for n in $SIZES; do
  for t in $THREADS; do
    [ "$t" -le "$CORES" ] || continue
    out="$TMP/ct${n}_t${t}.wsp"
    load=$(cut -d' ' -f1 /proc/loadavg)
    cpus=$(seq -s, 0 $((t - 1)))
    log="$TMP/ct${n}_t${t}.log"
    RAYON_NUM_THREADS=$t taskset -c "$cpus" /usr/bin/time -f "TIME %e %M" \
      "$W" compress --phantom ct --dims "$n,$n,$n" --brick "$BRICK" \
      --target-fraction "$FRACTION" -o "$out" >"$log" 2>&1 || { cat "$log" >&2; exit 1; }
    read -r secs kb < <(sed -n 's/^TIME \([0-9.]*\) \([0-9]*\)$/\1 \2/p' "$log")
    bricks=$(sed -n 's/.*bricked: \([0-9]*\) bricks.*/\1/p' "$log")
    bytes=$(stat -c %s "$out")
    mb=$((kb / 1024))
    ns=$(echo "$secs * $t * 1000000000 / ($n * $n * $n)" | bc -l | xargs printf '%.0f')
    echo "$n,$t,$BRICK,$bricks,$secs,$mb,$bytes,$ns,$load" >>"$CSV"
    echo "| ${n}³ | $t | $bricks | $secs | $mb MB | $bytes | $ns |"
  done
done
echo
echo "CSV: $CSV"
