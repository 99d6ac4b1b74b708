"""The diagnosis' fits side by side: K independent fits from scratch (the term-free base at K minibatch seeds,
as the noise between optima and a second look make them) one after the other, then on `--workers` threads
(`exolan.diagnose.workers.Workers`), in one process; prints both wall times, the ratio, and whether the fitted
weights are the same bits.

    python benches/bench_diagnose.py [--data DIR] [--fits 4] [--steps 300] [--workers 2]

Without --data it simulates a 4-user x 6-task x 20 s world (the size issue 38 times) into
out/bench_diagnose_world once. Each fit runs torch at one thread, as the diagnosis does. A benchmark, not a test:
on a shared machine the ratio is what it measures, alternate runs to see the noise.
"""
from __future__ import annotations

import argparse
import copy
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WORLD = dict(users="4", tasks="walk,run,squat,jump_in_place,sit_to_stand,ball_toss", seconds="20", seed="4242")


def world(path: Path) -> Path:
    if not (path / "S01").exists():
        subprocess.run([sys.executable, "-m", "exolan.cli", "simulate", "--out", str(path)]
                       + [x for k, v in WORLD.items() for x in (f"--{k}", v)], check=True)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--fits", type=int, default=4)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args()
    import torch
    torch.set_num_threads(1)
    from exolan.diagnose.base import make_base
    from exolan.diagnose.flat import prepare
    from exolan.diagnose.procedure import load_trials
    from exolan.diagnose.refits import fresh_fit, other_seeds
    from exolan.diagnose.settings import Settings
    from exolan.diagnose.workers import Workers

    data = Path(a.data) if a.data else world(ROOT / "out" / "bench_diagnose_world")
    s = Settings(steps_base=a.steps, steps_refit=max(a.steps // 8, 1), verbose=False)
    flat = prepare(load_trials(str(data)), max_delay=s.max_delay, seed=s.seed)
    start = make_base(flat, hidden=s.hidden, z_dim=s.z_dim, seed=s.seed, pelvis_surge=s.pelvis_surge,
                      lim_cop=s.lim_cop)
    seeds = other_seeds(s, a.fits)
    jobs = [lambda sk=sk: fresh_fit(flat, sk, (), {}, copy.deepcopy(start)) for sk in seeds]
    fresh_fit(flat, replace(s, steps_base=10, steps_refit=2), (), {}, copy.deepcopy(start))     # warm-up
    t = time.perf_counter()
    one = [job() for job in jobs]
    t_one = time.perf_counter() - t
    t = time.perf_counter()
    side = Workers(a.workers).map(jobs)
    t_side = time.perf_counter() - t
    same = all(torch.equal(x, y) for m1, m2 in zip(one, side)
               for x, y in zip(m1.state_dict().values(), m2.state_dict().values()))
    print(f"{a.fits} fits from scratch ({a.steps} + {s.steps_refit} steps, {flat.q.shape[0]} samples): "
          f"one after the other {t_one:.1f} s, on {a.workers} threads {t_side:.1f} s, "
          f"ratio {t_one / t_side:.2f}x; same weights: {same}")


if __name__ == "__main__":
    main()
