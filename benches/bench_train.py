"""Training throughput: loss samples per second of one optimiser step at the paper's batch (8192), for
ExoLaN+LIM with w_fd and w_ms (H = 4, 256 starts) and for MLP-TCN+LIM (torque loss), at 1 and 2 torch threads;
with `--against REV`, the same measurement of the tree at git revision REV in the same run, and the ratios;
with `--torch-path`, this tree also with its native training kernels off (EXOLAN_NATIVE_TERMS=0).

    python benches/bench_train.py [--against 66a29dd] [--torch-path] [--data DIR] [--batches 6] [--repeats 3] [--threads 1,2]
                                  [--device cpu|cuda]

Each figure is measured in a fresh subprocess (one per tree, configuration and thread count), the trees
alternating within every repeat so that a busy machine slows both alike; a figure is the best of `--repeats`
(the least disturbed run; every repeat is printed and kept in the JSON). The old tree is checked out once into
a git worktree under out/bench_trees/ and measured twice: as it ships, and with this tree's process settings
(exolan/runtime.py: OpenMP's wait policy, glibc's allocator thresholds) given as environment variables, which
says how much of a gain is the code.
Without --data (or with a --data folder that is missing or empty) it simulates the paper's training split (21
users x the 7 training tasks, 6 s per trial) there once (out/bench_world by default). A benchmark script, not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = {
    "exolan+LIM w_fd+w_ms": dict(method="exolan", w_fd=0.01, w_ms=1.0),
    "MLP-TCN+LIM": dict(method="mlp-tcn", w_fd=0.0, w_ms=0.0),
}


def worker(data: str, config: str, threads: int, batches: int, batch_size: int, device: str = "cpu") -> dict:
    """One measurement with whatever `exolan` is importable (this tree's or the old one's)."""
    import exolan  # noqa: F401  (first: a tree's own settings apply before torch loads)
    import torch

    torch.set_num_threads(threads)
    run_threads = None                         # a run's threads as `exolan train` gives them (trees that have it),
    try:                                       # held to the end: a dropped context manager restores torch's threads
        from exolan.native import cpu_threads
        run_threads = cpu_threads(threads)
        run_threads.__enter__()
    except ImportError:
        pass
    from exolan.config import TrainConfig
    from exolan.data import load, paper_split
    from exolan.models import build_model
    from exolan.train import _describe, batch_losses, compute_stats, data_scales, make_chunks

    c = CONFIGS[config]
    trials = list(paper_split(load(data)).train)
    desc, stats = _describe(trials), compute_stats(trials)
    torch.manual_seed(0)
    black_box = {} if c["method"] == "exolan" else dict(state_mean=stats["state_mean"], state_std=stats["state_std"],
                                                        tau_scale=stats["tau_std"])
    model = build_model(c["method"], lim=True, joint_types=desc["joint_types"], joint_names=desc["joint_names"],
                        context_channels=desc["context_channels"], **data_scales(stats), **black_box)
    model.norm.set_stats(stats["ctx_mean"], stats["ctx_std"])
    dev = torch.device(device)
    model.to(dev)
    try:                                       # the optimiser as the tree's exolan train makes it
        from exolan.train import make_optimizer
    except ImportError:
        make_optimizer = lambda params, lr, wd: torch.optim.Adam(params, lr=lr, weight_decay=wd)  # noqa: E731
    opt = make_optimizer(model.parameters(), 1e-3, 1e-3)
    cfg = TrainConfig(method=c["method"], batch_size=batch_size, w_fd=c["w_fd"], w_ms=c["w_ms"])
    ch = make_chunks(trials, model.receptive_field - 1, cfg.chunk_steps, cfg.horizon).to(dev)
    per = max(1, cfg.batch_size // cfg.chunk_steps)
    K = ch.q.shape[0]
    gen = torch.Generator().manual_seed(0)
    perm = torch.randperm(K, generator=gen)
    one = torch.ones(len(desc["joint_names"]), device=dev)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    n_samples = 0

    def step(b):
        idx = perm[(b * per) % K:][:per].to(dev)
        loss = batch_losses(model, ch, idx, cfg, one, one, desc["dt"], gen)["loss"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return int(ch.loss[idx].sum())

    step(0)                                    # warm-up
    sync()
    t0 = time.perf_counter()
    for b in range(1, batches + 1):
        n_samples += step(b)
    sync()                                     # a GPU's queued kernels belong to the time
    dt = time.perf_counter() - t0
    return dict(samples_per_s=n_samples / dt, ms_per_batch=dt / batches * 1e3, torch_threads=torch.get_num_threads())


RUST_SOURCES = ("rust", "Cargo.toml", "Cargo.lock")


def tree_of(rev: str) -> Path:
    """A git worktree of `rev` (made once) with a native module of its own: this tree's copied in where the Rust
    sources are the same as this checkout's, else built from the worktree's sources (once; a few minutes), so that
    a change to the kernels is measured against the old kernels and not against itself."""
    d = ROOT / "out" / "bench_trees" / rev
    if not d.exists():
        d.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(d), rev], check=True,
                       stdout=subprocess.DEVNULL)
    pkg = d / "python" / "exolan"
    mine = list((ROOT / "python" / "exolan").glob("_native*.so"))
    if not list(pkg.glob("_native*.so")) and mine:
        same = subprocess.run(["git", "-C", str(ROOT), "diff", "--quiet", rev, "--", *RUST_SOURCES]).returncode == 0
        if same:
            shutil.copy2(mine[0], pkg / mine[0].name)
        else:
            print(f"[bench] building {rev}'s own native module (its Rust sources differ from this checkout's)",
                  file=sys.stderr, flush=True)
            subprocess.run(["cargo", "build", "--release", "--quiet", "--features", "python"], cwd=d, check=True,
                           env=dict(os.environ, CARGO_TARGET_DIR=str(d / "target")))
            shutil.copy2(d / "target" / "release" / "libexolan.so", pkg / mine[0].name)
    return d


def this_trees_settings() -> dict:
    """This tree's process settings as environment variables, for a tree that lacks them (imported here, in the
    parent: a worker of the old tree must not import this tree's exolan)."""
    from exolan import runtime

    return runtime.ENVIRONMENT


def measure(tree: Path, data: str, config: str, threads: int, batches: int, batch_size: int,
            settings: dict | None = None, device: str = "cpu") -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree / "python"), OMP_NUM_THREADS=str(threads))
    for k in this_trees_settings():
        env.pop(k, None)                               # each tree as it ships, unless asked otherwise
    env.update(settings or {})
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", config, "--data", data,
           "--threads", str(threads), "--batches", str(batches), "--batch-size", str(batch_size),
           "--device", device]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode:                                # say why, not only that the worker failed
        raise SystemExit(f"bench worker ({config}, {threads} threads, {tree}) failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default=None, help="git revision to compare with (e.g. 66a29dd)")
    ap.add_argument("--data", default=None)
    ap.add_argument("--batches", type=int, default=6)
    ap.add_argument("--batch-size", type=int, default=8192)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--device", default="cpu", help="cpu or cuda (the GPU's figures: compare trees on one device)")
    ap.add_argument("--json", default=None, help="write the figures here")
    ap.add_argument("--torch-path", action="store_true",
                    help="also measure this tree with its native training kernels off (EXOLAN_NATIVE_TERMS=0)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.data, args.worker, int(args.threads), args.batches, args.batch_size,
                                args.device)))
        return
    data = Path(args.data) if args.data else ROOT / "out" / "bench_world"
    # a missing world is made once; a --data folder that holds anything is the user's data, never written into
    given_empty = args.data and not (data.exists() and any(data.iterdir()))
    if given_empty or (not args.data and not (data / "subjects.csv").exists()):
        from exolan.world import simulate

        print(f"simulating the training split into {data} (once) ...", flush=True)
        simulate(data, users=21, tasks="train", seconds=6.0, progress=True)
    trees = {"this tree": (ROOT, None)}
    if args.torch_path:
        # this tree without its native training kernels: their share of the gain
        trees["this tree, torch path"] = (ROOT, {"EXOLAN_NATIVE_TERMS": "0"})
    if args.against:
        old = tree_of(args.against)
        trees[args.against] = (old, None)
        # the old tree with this tree's process settings (wait policy, allocator): how much of a gain is code
        trees[args.against + "+settings"] = (old, this_trees_settings())
    threads = [int(t) for t in args.threads.split(",")]
    configs = [c for c in args.configs.split(",") if c]
    best: dict[tuple, float] = {}
    runs: dict[tuple, list] = {}                       # every figure: best of N hides a slow mode (the allocator's)
    for r in range(args.repeats):
        for config in configs:
            for th in threads:
                for name, (tree, settings) in trees.items():
                    m = measure(tree, str(data), config, th, args.batches, args.batch_size, settings, args.device)
                    key = (config, th, name)
                    best[key] = max(best.get(key, 0.0), m["samples_per_s"])
                    runs.setdefault(key, []).append(m["samples_per_s"])
                    print(f"[repeat {r + 1}/{args.repeats}] {config:22s} {th} thr  {name:18s} "
                          f"{m['samples_per_s']:9.0f} samples/s ({m['ms_per_batch']:.0f} ms/batch; torch's threads "
                          f"{m.get('torch_threads', '?')})", flush=True)
    print(f"\nbest of {args.repeats}, batch {args.batch_size}, {args.device}, samples/s (higher is better):")
    rows = []
    for config in configs:
        for th in threads:
            new = best[(config, th, "this tree")]
            line = f"  {config:22s} {th} thr  this tree {new:9.0f}"
            row = dict(config=config, threads=th, this_tree=new)
            if args.against:
                old = best[(config, th, args.against)]
                line += f"   {args.against} {old:9.0f}   ratio {new / old:5.2f}x"
                row.update(old=old, ratio=new / old)
                olds = best[(config, th, args.against + "+settings")]
                line += f"   (vs {args.against} with this tree's process settings {olds:9.0f}: {new / olds:5.2f}x)"
                row.update(old_settings=olds, ratio_settings=new / olds)
            if args.torch_path:
                tp = best[(config, th, "this tree, torch path")]
                line += f"   (this tree on torch's path {tp:9.0f}: native kernels {new / tp:5.2f}x)"
                row.update(torch_path=tp, ratio_torch_path=new / tp)
            row["all"] = {name: v for (c, t, name), v in runs.items() if (c, t) == (config, th)}
            spread = ", ".join(f"{name} {min(v):.0f}-{max(v):.0f}" for name, v in row["all"].items())
            print(line + f"\n      all repeats: {spread}")
            rows.append(row)
    if args.json:
        Path(args.json).write_text(json.dumps(dict(against=args.against, batch=args.batch_size, device=args.device,
                                                   rows=rows), indent=1))


if __name__ == "__main__":
    main()
