# Sourced by the scripts that score wavesplat with ../shared/peers: builds the release binary,
# writes the peers' 128^3 MNI volume once, and sets ROOT, PEERS, W (the binary), TMP (a work
# directory named after $1) and VENV (the peers' venv, created on first use).
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PEERS="$ROOT/../shared/peers"
W="$ROOT/target/release/wavesplat"
TMP="${TMPDIR:-/tmp}/wavesplat-$1"
export VENV="${VENV:-$TMP/peers-venv}"
mkdir -p "$TMP"
cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml" --bin wavesplat
[ -f "$TMP/v128.raw" ] || bash "$PEERS/run.sh" --write-v128 "$TMP/v128.raw" >/dev/null
