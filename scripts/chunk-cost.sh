#!/usr/bin/env bash
# What bricking costs, ours against SPERR's chunks, on the MNI volume at one byte target (issue
# 55): see scripts/chunk_cost.py. Needs the peers' Python environment (numpy, scipy, nibabel,
# h5py, hdf5plugin): VENV=DIR names it (default: ../shared/peers/.venv, made by
# `bash ../shared/peers/run.sh`).
#   bash scripts/chunk-cost.sh [BYTES] [BRICK ...]      e.g. bash scripts/chunk-cost.sh 86245 128 64
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
VENV=${VENV:-$ROOT/../shared/peers/.venv}
[ -x "$VENV/bin/python" ] || { echo "no Python environment at $VENV (set VENV, or run ../shared/peers/run.sh once)" >&2; exit 1; }
cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml" --bin wavesplat
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
exec "$VENV/bin/python" "$ROOT/scripts/chunk_cost.py" "$@"
