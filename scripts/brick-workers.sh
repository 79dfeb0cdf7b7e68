#!/usr/bin/env bash
# A bricked job spread over workers (issue 55): the CT phantom at N³ written as a raw f32 file
# on "shared storage" (a local directory every worker reads), submitted as one bricked job
# (`archive submit --brick B --target-fraction F`) to an orchestrator and a cache on loopback,
# then compressed by W workers, each with one compression thread and pinned with taskset to a
# core of its own. The time is from submission until the job is done; each worker's peak
# resident memory is read from /proc (VmHWM) before it is stopped. One CSV row a run, and a
# Markdown table on stdout.
#   bash scripts/brick-workers.sh [SIZE] [WORKERS] [BRICK] [FRACTION]
#   e.g. bash scripts/brick-workers.sh 512 "1 2" 128 0.01
# WORKERS: worker counts (default "1 2"; more than the machine's cores are skipped, unless
# OVERSUBSCRIBE=1 pins them to the cores in turn: for how many jobs' parts each worker sees,
# not for time per core).
# UPLOAD=1 submits the file with --upload (one worker compresses it, reading its bricks from
# its temporary copy of the upload); DETACHED=1 submits the same samples behind a detached
# MetaImage header (two files: uploaded, a bundle); WAVESPLAT=PATH runs another build;
# SUBMIT_FLAGS adds options to the submission (e.g. SUBMIT_FLAGS="--effort fast"); JOBS=K
# submits K such volumes at once (K bricked jobs in flight on the same workers, the time until
# the last is done; the same samples under K names).
# Writes $TMPDIR/wavesplat-workers/workers.csv (size,workers,brick,parts,seconds,
# peak_rss_mb_max,bytes,ns_per_voxel_core,jobs,from_tops; bytes of the first job listed;
# from_tops: the encode parts the workers coded from a top they kept, of all encode parts).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
N=${1:-512}
WORKERS=${2:-"1 2"}
BRICK=${3:-128}
FRACTION=${4:-0.01}
W="${WAVESPLAT:-$ROOT/target/release/wavesplat}"
JOBS=${JOBS:-1}
UPLOAD_FLAG=()
[ "${UPLOAD:-0}" = 1 ] && UPLOAD_FLAG=(--upload)
TMP="${TMPDIR:-/tmp}/wavesplat-workers"
command -v taskset >/dev/null || { echo "needs taskset (util-linux)" >&2; exit 1; }
[ -n "${WAVESPLAT:-}" ] || cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml" --bin wavesplat
# One directory per size: the submission takes every volume in its directory.
mkdir -p "$TMP/shared_$N"
SRC="$TMP/shared_$N/ct_${N}x${N}x${N}_f32.raw"
[ -f "$SRC" ] || "$W" phantom ct --dims "$N,$N,$N" -o "$SRC"
SUBMIT="$TMP/shared_$N"
if [ "${DETACHED:-0}" = 1 ]; then
  # The same samples behind a detached MetaImage header: a source of two files (uploaded as
  # a bundle), its data a hard link to the raw file.
  SUBMIT="$TMP/detached_$N"
  mkdir -p "$SUBMIT"
  [ -f "$SUBMIT/ct.raw" ] || ln "$SRC" "$SUBMIT/ct.raw"
  printf 'ObjectType = Image\nNDims = 3\nDimSize = %s %s %s\nElementType = MET_FLOAT\nElementDataFile = ct.raw\n' \
    "$N" "$N" "$N" >"$SUBMIT/ct.mhd"
fi
if [ "$JOBS" -gt 1 ]; then
  # K volumes: hard links to the same samples under K names, one bricked job each.
  SUBMIT="$TMP/jobs_${N}_$JOBS"
  mkdir -p "$SUBMIT"
  for k in $(seq 1 "$JOBS"); do
    [ -f "$SUBMIT/ct${k}_${N}x${N}x${N}_f32.raw" ] || ln "$SRC" "$SUBMIT/ct${k}_${N}x${N}x${N}_f32.raw"
  done
fi
CSV="$TMP/workers.csv"
[ -f "$CSV" ] || echo "size,workers,brick,parts,seconds,peak_rss_mb_max,bytes,ns_per_voxel_core,jobs,from_tops" >"$CSV"
CORES=$(nproc)
PIDS=()
cleanup() { for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done; }
trap cleanup EXIT
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
echo "$JOBS × CT phantom ${N}³ f32 on shared storage, bricks of $BRICK, $FRACTION of the coefficients, $CORES cores, $(date -u +%F)"
echo
echo "| workers | parts | wall s | peak RSS per worker | bytes | ns per voxel and core | coded from a kept top |"
echo "|---|---|---|---|---|---|---|"
for w in $WORKERS; do
  [ "$w" -le "$CORES" ] || [ "${OVERSUBSCRIBE:-0}" = 1 ] || continue
  run="$TMP/run_w$w"
  rm -rf "$run" && mkdir -p "$run"
  cp=$(free_port); op=$(free_port)
  "$W" serve cache --db "$run/cache.db" --addr "127.0.0.1:$cp" >"$run/cache.log" 2>&1 &
  PIDS+=($!)
  "$W" serve orchestrator --db "$run/orch.db" --addr "127.0.0.1:$op" >"$run/orch.log" 2>&1 &
  PIDS+=($!)
  sleep 1
  start=$(date +%s.%N)
  "$W" archive submit "$SUBMIT" --orchestrator "http://127.0.0.1:$op" --detach \
    --brick "$BRICK" --target-fraction "$FRACTION" "${UPLOAD_FLAG[@]}" ${SUBMIT_FLAGS:-} \
    >"$run/submit.log"
  WP=()
  for i in $(seq 0 $((w - 1))); do
    taskset -c "$((i % CORES))" "$W" worker --orchestrator "http://127.0.0.1:$op" \
      --cache "http://127.0.0.1:$cp" --threads 1 --id "w$i" >"$run/w$i.log" 2>&1 &
    WP+=($!); PIDS+=($!)
  done
  # Until the bricked jobs (not their parts) are done; a failure stops the script.
  while :; do
    listed=$("$W" jobs list --orchestrator "http://127.0.0.1:$op")
    if grep -q $'\t'failed$'\t' <<<"$listed"; then
      echo "failed: $(grep $'\t'failed$'\t' <<<"$listed")" >&2; exit 1
    fi
    [ "$(grep -c $'\t'done$'\t' <<<"$listed" || true)" -ge "$JOBS" ] && break
    sleep 0.5
  done
  line=$(sed -n 1p <<<"$listed")
  end=$(date +%s.%N)
  peak=0
  for p in "${WP[@]}"; do
    kb=$(awk '/^VmHWM:/ {print $2}' "/proc/$p/status")
    [ "$kb" -gt "$peak" ] && peak=$kb
  done
  parts=$("$W" jobs list --parts --orchestrator "http://127.0.0.1:$op" | grep -c "part of" || true)
  bytes=$(echo "$line" | sed -n 's/.*bytes=\([0-9]*\).*/\1/p')
  secs=$(echo "$end - $start" | bc -l | xargs printf '%.1f')
  ns=$(echo "$secs * $w * 1000000000 / ($JOBS * $N * $N * $N)" | bc -l | xargs printf '%.0f')
  encodes=$("$W" jobs list --parts --orchestrator "http://127.0.0.1:$op" | grep -c "coding" || true)
  from_tops=$(cat "$run"/w*.log | grep -c "part coded from the top this worker kept" || true)
  echo "$N,$w,$BRICK,$parts,$secs,$((peak / 1024)),$bytes,$ns,$JOBS,$from_tops/$encodes" >>"$CSV"
  echo "| $w | $parts | $secs | $((peak / 1024)) MB | $bytes | $ns | $from_tops of $encodes |"
  cleanup; PIDS=(); sleep 1
done
echo
echo "CSV: $CSV"
