#!/usr/bin/env bash
# Every test: the Rust core without Python (cargo test --no-default-features) and pytest.
# Fails on any failure and when no test ran (pytest exit 5 is an error here).
# Extra arguments go to pytest (e.g. -m slow for the long studies). pytest-xdist runs the tests on
# EXOLAN_TEST_WORKERS processes (default: one per core), one torch thread each (tests/conftest.py).
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
echo "[exolan] cargo test (pure Rust core, no Python)"
cargo test --release --no-default-features
echo "[exolan] pytest"
set +e
python -m pytest -n "${EXOLAN_TEST_WORKERS:-auto}" --dist load --maxschedchunk 1 "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
    echo "[exolan] pytest collected no tests: failing" >&2
    exit 1
fi
exit "$rc"
