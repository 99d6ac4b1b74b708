#!/usr/bin/env bash
# The allocation test under contention: one busy loop per core (or HOGS) beside it, RUNS runs in a row
# (default 20); fails at the first run that fails. EXOLAN_ALLOC_BACKTRACE=1 is set, so a failure prints
# where each counted allocation came from.
#
#     scripts/alloc_stress.sh [RUNS]        # HOGS=4 scripts/alloc_stress.sh 50
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
runs="${1:-20}"
hogs="${HOGS:-$(nproc)}"

cargo test --release --no-default-features --test alloc --no-run >/dev/null 2>&1 \
    || cargo test --release --no-default-features --test alloc --no-run

pids=()
stop_hogs() {
    for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
}
trap stop_hogs EXIT
for _ in $(seq "$hogs"); do
    # the hogs inherit the caller's priority, as the test does: they compete on equal terms
    ( while :; do :; done ) &
    pids+=("$!")
done
echo "[alloc_stress] $hogs busy loops (pids ${pids[*]}), $runs runs of tests/alloc.rs"

passed=0
for i in $(seq "$runs"); do
    if EXOLAN_ALLOC_BACKTRACE=1 cargo test --release --no-default-features --test alloc -q >"/tmp/alloc_stress.$$.log" 2>&1; then
        passed=$((passed + 1))
        echo "[alloc_stress] run $i: ok"
    else
        echo "[alloc_stress] run $i: FAILED"
        cat "/tmp/alloc_stress.$$.log"
        rm -f "/tmp/alloc_stress.$$.log"
        echo "[alloc_stress] $passed of $i runs passed"
        exit 1
    fi
done
rm -f "/tmp/alloc_stress.$$.log"
echo "[alloc_stress] $passed of $runs runs passed with $hogs busy loops beside"
