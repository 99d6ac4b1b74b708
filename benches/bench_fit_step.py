"""One diagnosis fit step, this tree against another: the base model and the base with an actuation delay (whose
fits read the exo torque's history), batch 4096, one torch thread, as the diagnosis fits them; prints each tree's
best ms per step, the ratio, and whether the two trees' weights after the same steps are the same bits.

    python benches/bench_fit_step.py [--data DIR] [--against REV] [--steps 150] [--repeats 3]
    python benches/bench_fit_step.py --pieces [--data DIR]

`--pieces`: this tree only, a delay fit's step cut in `refits.FRESH_PIECES` pieces as fits from scratch are, alone
(the second piece on the free core) and with two fits at once (each piece after the other), against uncut.

Without --data it uses the 4-user x 6-task x 20 s world of `bench_diagnose.py`. The other tree is a git worktree
under out/bench_trees/ (`bench_train.tree_of`); the trees run alternately in fresh processes, so that a busy
spell of a shared machine falls on both. A benchmark, not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _setup(data: str):
    """(settings, flat, a maker of the base with the given effects) for `data`, torch on one thread."""
    import copy

    import torch
    torch.set_num_threads(1)
    from exolan.diagnose.flat import prepare
    from exolan.diagnose.procedure import Settings, load_trials, new_base
    from exolan.extensions import ExtendedModel

    s = Settings(verbose=False)
    flat = prepare(load_trials(data), max_delay=s.max_delay, seed=s.seed)
    start = new_base(flat, s)
    return s, flat, lambda effects: ExtendedModel(copy.deepcopy(start), flat.n, effects, dt=flat.dt,
                                                  max_delay=s.max_delay, init={}, coupled_damping=False)


def _digest(model) -> str:
    """A hash of every weight's bits: two trees' fits are the same only if this is."""
    import hashlib

    return hashlib.sha256(b"".join(p.detach().numpy().tobytes() for p in model.parameters())).hexdigest()


def worker(data: str, steps: int) -> dict:
    from exolan.diagnose.fit import train

    s, flat, make = _setup(data)
    out = {}
    for name, effects in (("base", []), ("delay", [("actuation_delay", 1)])):
        m = make(effects)
        train(m, flat, 10, lr=s.lr_base, batch=s.batch, seed=1, w_acc=s.w_acc)     # warm-up
        t = time.perf_counter()
        train(m, flat, steps, lr=s.lr_base, batch=s.batch, seed=0, w_acc=s.w_acc)
        out[name] = dict(ms=(time.perf_counter() - t) / steps * 1e3, weights=_digest(m))
    return out


def pieces(data: str, steps: int) -> None:
    import threading

    from exolan.diagnose.fit import train
    from exolan.diagnose.refits import FRESH_PIECES
    from exolan.diagnose.workers import Workers

    s, flat, make = _setup(data)

    def fit(k: int, pool) -> float:
        m = make([("actuation_delay", 1)])
        t = time.perf_counter()
        train(m, flat, steps, lr=s.lr_base, batch=s.batch, seed=0, w_acc=0.0, weighted=False, pieces=k, pool=pool)
        return (time.perf_counter() - t) / steps * 1e3

    def two(k: int) -> list[float]:
        out: list = []
        ths = [threading.Thread(target=lambda: out.append(fit(k, Workers(1)))) for _ in range(2)]
        for t in ths:
            t.start()
        for t in ths:
            t.join()
        return out

    fit(1, None)        # warm-up
    pool = Workers(2)
    print(f"delay fit, ms per step ({steps} steps, batch 4096): uncut alone {fit(1, None):.2f}; "
          f"{FRESH_PIECES} pieces alone {pool.map([lambda: fit(FRESH_PIECES, pool)])[0]:.2f}; two fits at once: "
          f"uncut {max(two(1)):.2f}, {FRESH_PIECES} pieces {max(two(FRESH_PIECES)):.2f}")


def run(tree: Path, data: str, steps: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree / "python"))
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", "--data", data,
                           "--steps", str(steps)], env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"bench worker ({tree}) failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--against", default=None, help="a git revision to time beside this tree")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--pieces", action="store_true", help="a fit from scratch's pieces alone and two at once")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_diagnose import world
    data = a.data or str(world(ROOT / "out" / "bench_diagnose_world"))
    if a.worker:
        print(json.dumps(worker(data, a.steps)))
        return
    if a.pieces:
        pieces(data, a.steps)
        return
    from bench_train import tree_of
    trees = {"this tree": ROOT} | ({a.against: tree_of(a.against)} if a.against else {})
    runs: dict = {k: [] for k in trees}
    for r in range(a.repeats):
        for name, tree in trees.items():
            runs[name].append(run(tree, data, a.steps))
            print(f"repeat {r + 1}/{a.repeats} {name}: " + ", ".join(
                f"{m} {v['ms']:.2f} ms" for m, v in runs[name][-1].items()), flush=True)
    best = {k: {m: min(x[m]["ms"] for x in v) for m in v[0]} for k, v in runs.items()}
    print(f"\nms per fit step (best of {a.repeats}, {a.steps} steps, batch 4096, one thread):")
    for m in best["this tree"]:
        line = f"  {m:6s} this tree {best['this tree'][m]:.2f}"
        if a.against:
            same = runs["this tree"][0][m].get("weights") == runs[a.against][0][m].get("weights")
            line += (f"  {a.against} {best[a.against][m]:.2f}  ratio {best[a.against][m] / best['this tree'][m]:.2f}x"
                     f"  weights after {a.steps} steps {'the same bits' if same else 'DIFFER'}")
        print(line)


if __name__ == "__main__":
    main()
