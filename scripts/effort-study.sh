#!/usr/bin/env bash
# The compression-effort study (issue 57): the test set and the whole MNI volume at 0.07, 0.15,
# 1.25 and 5.85 %, each `--effort` timed and scored beside SPERR (scripts/effort_study.py).
#   bash scripts/effort-study.sh [REPEAT] [--only NAMES]
# Writes $TMPDIR/wavesplat-effort-study/out/effort.csv (and effort.png with matplotlib).
set -euo pipefail
source "$(dirname "$0")/peers_setup.sh" effort-study
REPEAT=${1:-1}
shift || true
# The plot of time against Q_I (from PyPI into the peers' venv, once).
"$VENV/bin/python" -c "import matplotlib" 2>/dev/null || "$VENV/bin/pip" install -q matplotlib
[ -f "$TMP/testset/manifest.tsv" ] || "$VENV/bin/python" "$ROOT/scripts/testset.py" make "$TMP/testset"
"$VENV/bin/python" "$ROOT/scripts/effort_study.py" "$W" "$TMP/testset" "$TMP/out" "$REPEAT" "$@"
