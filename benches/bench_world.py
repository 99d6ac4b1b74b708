"""Benchmark (not a test): time to generate and to load the default world (21 users x 28 tasks).

    .venv/bin/python benches/bench_world.py [--out DIR] [--users 21] [--tasks all] [--keep]

Prints the generation time, the cold load time (parse + Savitzky-Golay + writing the cache) and
the cached load time (content hash + unpickling), plus sizes.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
import time
from pathlib import Path


def du(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="world directory (default: a temporary one)")
    ap.add_argument("--users", type=int, default=21)
    ap.add_argument("--tasks", default="all")
    ap.add_argument("--seconds", type=float, default=None)
    ap.add_argument("--keep", action="store_true", help="keep the temporary world")
    args = ap.parse_args()

    from exolan.data import load
    from exolan.world import simulate

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="exolan-bench-")) / "world"
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    summary = simulate(out, users=args.users, tasks=args.tasks, seconds=args.seconds, progress=True)
    t_gen = time.perf_counter() - t0
    files_mb = du(out)
    t0 = time.perf_counter()
    ds = load(out)
    t_cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    ds2 = load(out)
    t_warm = time.perf_counter() - t0
    assert len(ds2) == len(ds)
    cpu = subprocess.run(["nproc"], capture_output=True, text=True).stdout.strip()
    print(f"world: {summary['users']} users x {len(summary['tasks'])} tasks, {len(ds)} leg-trials, "
          f"{ds.n_samples} valid samples, CSV {files_mb:.0f} MB, cache {du(out / '.exolan_cache'):.0f} MB "
          f"({cpu} cores visible)")
    print(f"generate:     {t_gen:7.1f} s")
    print(f"load (cold):  {t_cold:7.1f} s")
    print(f"load (cache): {t_warm:7.1f} s")
    if not args.out and not args.keep:
        shutil.rmtree(out.parent)


if __name__ == "__main__":
    main()
