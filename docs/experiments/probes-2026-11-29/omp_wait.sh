#!/bin/bash
# The OpenMP wait policy at 2 threads (docs/TRAINING.md, "The allocator, and a hand-written backward tried"):
# the bench's worker under each setting; run once on an idle machine and once beside a busy loop.
# usage: bash docs/experiments/probes-2026-11-29/omp_wait.sh [DATA=out/bench_world]
data=${1:-out/bench_world}
run() { # label env...
  local label=$1; shift
  for cfg in "exolan+LIM w_fd+w_ms" "MLP-TCN+LIM"; do
    r=$(env -u OMP_WAIT_POLICY "$@" OMP_NUM_THREADS=2 PYTHONPATH=python .venv/bin/python benches/bench_train.py \
        --worker "$cfg" --data "$data" --threads 2 --batches 8 --batch-size 8192 | tail -1)
    echo "$label | $cfg | $r"
  done
}
run passive OMP_WAIT_POLICY=PASSIVE
run active OMP_WAIT_POLICY=ACTIVE
run spin10k OMP_WAIT_POLICY=PASSIVE GOMP_SPINCOUNT=10000
run spin100k OMP_WAIT_POLICY=PASSIVE GOMP_SPINCOUNT=100000
