#!/usr/bin/env bash
# The workspace's tests, as `cargo test --workspace ARGS` runs them, one test binary at a time,
# each binary deleted once it passed: the disk then holds the dependencies, the workspace's
# libraries and one test binary at a time, not all ~60 test binaries (each links wgpu, tonic
# and rustls; a whole `cargo test --workspace` target is several GB more than this one's peak).
# Every invocation selects the whole workspace, so features unify as in one `cargo test
# --workspace` and no dependency is built twice.
#
#   bash scripts/test-each.sh [CARGO TEST ARGS, e.g. --features jpeg-ls]
#
# Steps: the libraries' and binaries' unit tests, each integration test by name, then the doc
# tests. Stops at the first failing step with its exit code; each step's target size is
# printed. Examples, which plain `cargo test` only builds, are left out: selected explicitly
# they would be built and run as test binaries; `cargo clippy --all-targets` (CI) checks them.
set -euo pipefail
cd "$(dirname "$0")/.."

# The target directory, then the integration tests' names across the workspace's members,
# each once (two members may have a test of the same name: `--test NAME` then runs both), from
# one `cargo metadata`.
target_and_tests() {
  cargo metadata --format-version 1 --no-deps | python3 -c '
import json, sys
meta = json.load(sys.stdin)
members = set(meta["workspace_members"])
names = sorted({t["name"] for p in meta["packages"] if p["id"] in members
                for t in p["targets"] if "test" in t["kind"]})
print("\n".join([meta["target_directory"]] + names))'
}

# Builds one selection's test binaries (cargo's arguments only: the test binaries' are
# `test_args`), runs them through cargo (its environment and working
# directory, as `cargo test` gives them), then deletes them.
run_step() {
  local executables
  executables=$(cargo test --workspace "$@" --no-run --message-format=json-render-diagnostics </dev/null |
    python3 -c '
import json, sys
for line in sys.stdin:
    try:
        msg = json.loads(line)
    except ValueError:
        continue
    if msg.get("reason") == "compiler-artifact" and msg.get("profile", {}).get("test") and msg.get("executable"):
        print(msg["executable"])')
  # stdin closed: nothing a test starts reads the caller's input.
  cargo test --workspace "$@" -- ${test_args[@]+"${test_args[@]}"} </dev/null
  if [ -n "$executables" ]; then
    while IFS= read -r exe; do
      rm -f -- "$exe" "${exe}.d"
    done <<<"$executables"
  fi
  echo "test-each: after ${*}: target $(du -sh "$TARGET" 2>/dev/null | cut -f1), disk $(df -h "$TARGET" | tail -1 | awk '{print $4}') free"
}

# Cargo's own arguments (features) come before `--`; the test binaries' after it.
cargo_args=()
test_args=()
seen_dashes=0
for a in "$@"; do
  if [ "$seen_dashes" -eq 1 ]; then
    test_args+=("$a")
  elif [ "$a" = "--" ]; then
    seen_dashes=1
  else
    cargo_args+=("$a")
  fi
done

# Listed before the loop, so that a failing `cargo metadata` stops the script rather than
# leaving the loop empty.
listing=$(target_and_tests)
TARGET=$(head -n 1 <<<"$listing")
names=$(tail -n +2 <<<"$listing")
if [ -z "$names" ]; then
  echo "test-each: no integration tests found in the workspace" >&2
  exit 1
fi
run_step ${cargo_args[@]+"${cargo_args[@]}"} --lib --bins
while IFS= read -r name; do
  run_step ${cargo_args[@]+"${cargo_args[@]}"} --test "$name"
done <<<"$names"
cargo test --workspace ${cargo_args[@]+"${cargo_args[@]}"} --doc -- ${test_args[@]+"${test_args[@]}"} </dev/null
