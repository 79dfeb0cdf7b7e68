#!/usr/bin/env bash
# Time series compressed together (Haar along time in groups of G) against each time point
# alone (G = 1) and SPERR per time point, at equal bytes, scored with the peers' metrics on a
# cine-like and a perfusion-like series (scripts/series_table.py says what they are).
#   bash scripts/series-table.sh [--groups 1,2,4,8,16] [--rates 0.25,0.5,1,2] [--only cine]
# Output: the table on stdout, CSV in $TMPDIR/wavesplat-series/series.csv.
set -euo pipefail
source "$(dirname "$0")/peers_setup.sh" series
"$VENV/bin/python" "$ROOT/scripts/series_table.py" "$W" "$TMP" "$@"
