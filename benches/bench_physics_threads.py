"""Physics first's least squares (`physics.setup` then `physics.select`, both joints) with numpy's BLAS on one
thread and on its default (one per core), alternated in one process; prints each wall time and the ratio.

    python benches/bench_physics_threads.py [--data DIR] [--repeats 2]

Without --data it simulates the main job's world size (3 users x the paper's 7 tasks x 8 s) into
out/bench_physics_world once. Why it exists: `exolan.diagnose.diagnose` limits BLAS to `EXOLAN_THREADS` (default 1)
threads, because OpenBLAS' threads spin while they wait and collapse on a machine that runs anything else. Run it
once alone and once beside other work (e.g. `sh -c 'while :; do :; done'`): a benchmark, not a test.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def world(path: Path) -> Path:
    if not (path / "S01").exists():
        subprocess.run([sys.executable, "-m", "exolan.cli", "simulate", "--out", str(path), "--users", "3",
                        "--tasks", "train", "--seconds", "8", "--seed", "11"], check=True)
    return path


def one(flat, s) -> float:
    from exolan.diagnose import physics

    t0 = time.perf_counter()
    res = physics.setup(flat, s.effects, [0, 1], alpha=s.alpha, cutoff_hz=s.cutoff_hz, max_delay=s.max_delay)
    physics.select(res, flat, n_boot=200)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    from threadpoolctl import threadpool_info, threadpool_limits

    from exolan.diagnose import procedure
    from exolan.diagnose.flat import prepare
    from exolan.diagnose.settings import Settings

    s = Settings()
    data = Path(a.data) if a.data else world(ROOT / "out" / "bench_physics_world")
    flat = prepare(procedure.load_trials(data), max_delay=s.max_delay, seed=s.seed)
    default = max(d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas")
    times = {1: [], default: []}
    for _ in range(a.repeats):
        for n in times:
            with threadpool_limits(limits=n, user_api="blas"):
                times[n].append(one(flat, s))
            print(f"BLAS threads {n}: {times[n][-1]:.1f} s", flush=True)
    best = {n: min(t) for n, t in times.items()}
    print(f"best of {a.repeats}: 1 thread {best[1]:.1f} s, {default} threads {best[default]:.1f} s; "
          f"ratio {best[default] / best[1]:.2f} (> 1: one thread is faster)")


if __name__ == "__main__":
    main()
