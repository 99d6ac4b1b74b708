#!/usr/bin/env bash
# Every test: the Rust core without Python (cargo test --no-default-features) and pytest.
# Fails on any failure and when no test ran (pytest exit 5 is an error here).
# Extra arguments go to pytest (e.g. -m slow for the long studies).
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
echo "[exolan] cargo test (pure Rust core, no Python)"
cargo test --release --no-default-features
echo "[exolan] pytest"
set +e
python -m pytest "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
    echo "[exolan] pytest collected no tests: failing" >&2
    exit 1
fi
exit "$rc"
