#!/usr/bin/env bash
# Before/after in one sitting: benches/bench_engine.py run alternately in OLD_TREE (a checkout of the older
# engine with its exolan/_native built in place) and in this tree, ROUNDS rounds per thread count.
#
#     benches/ab_engine.sh OLD_TREE [ROUNDS] [OLD_PYTHON]     # e.g. git archive 414916c | tar -x -C /tmp/old
set -euo pipefail
old="$(cd "$1" && pwd)"
rounds="${2:-2}"
old_py="${3:-python}"
new="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
for th in 1 2; do
    for r in $(seq "$rounds"); do
        echo "== threads $th round $r: OLD ($old)"
        (cd "$old" && "$old_py" benches/bench_engine.py --threads "$th" | tail -6)
        echo "== threads $th round $r: NEW ($new)"
        (cd "$new" && python benches/bench_engine.py --threads "$th" | tail -7)
    done
done
