#!/usr/bin/env bash
# Bricked compression beside chunked SPERR on the N³ CT phantom (issue 55): see
# scripts/brick_sperr.py. Needs the peers' Python environment (numpy, scipy, h5py, hdf5plugin):
# VENV=DIR names it (default: ../shared/peers/.venv, made by `bash ../shared/peers/run.sh`).
#   bash scripts/brick-sperr.sh [N] [BRICK] [FRACTION] [--volume ct|mni] [--whole]
#   e.g. bash scripts/brick-sperr.sh 512 256 0.01 --volume mni --whole
# WAVESPLAT_FLAGS="--effort fast" passes more flags to `wavesplat compress`; CORE=K pins the
# one-thread runs to core K (default 0).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
VENV=${VENV:-$ROOT/../shared/peers/.venv}
[ -x "$VENV/bin/python" ] || { echo "no Python environment at $VENV (set VENV, or run ../shared/peers/run.sh once)" >&2; exit 1; }
command -v taskset >/dev/null || { echo "needs taskset (util-linux)" >&2; exit 1; }
cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml" --bin wavesplat
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
exec taskset -c "${CORE:-0}" "$VENV/bin/python" "$ROOT/scripts/brick_sperr.py" "$@"
