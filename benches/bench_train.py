"""Training epoch time: the sequence-level encoder (one TCN pass per trial chunk, exolan's training path)
versus the windowed encoder (a fresh 63-step TCN pass per sample), printed as a ratio.

    python benches/bench_train.py [--data DIR] [--batches 8] [--threads N] [--device cpu|cuda]

Without --data it simulates the default world (`exolan simulate` defaults: 21 users, 28 tasks) once into
out/bench_world and trains on the paper's training split. Both variants use the same model, batch size
(8192 loss samples), loss (torque only, ExoLaN with LIM) and optimiser step; only the way z is obtained
differs. Each variant runs `--batches` timed batches after one warm-up batch; the epoch time is the mean
batch time times the batches an epoch holds. A benchmark script, not a test.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from exolan.config import TrainConfig
from exolan.data import context_features, load, paper_split
from exolan.losses import torque_loss
from exolan.models import build_model
from exolan.train import _describe, batch_losses, compute_stats, data_scales, make_chunks


def windowed_batches(trials, W: int):
    """Flat arrays of the valid samples plus a zero-prefixed context array to cut 63-step windows from."""
    ctx, keep, idx = [], [], []
    q, qd, qdd, tau, f_v, mass = [], [], [], [], [], []
    offset = 0
    for t in trials:
        T = len(t.q)
        c = context_features(t)
        ctx += [np.zeros((W, c.shape[1])), c]
        keep += [np.zeros(W, bool), np.ones(T, bool)]
        v = np.asarray(t.valid, bool)
        idx.append(offset + W + np.nonzero(v)[0])
        offset += W + T
        q.append(t.q[v]); qd.append(t.qd[v]); qdd.append(t.qdd[v]); tau.append(t.tau[v]); f_v.append(t.f_v[v])
        mass.append(np.full(int(v.sum()), t.mass))
    f = lambda a: torch.as_tensor(np.concatenate(a), dtype=torch.float32)
    return dict(ctx=f(ctx), keep=torch.as_tensor(np.concatenate(keep)), pos=torch.as_tensor(np.concatenate(idx)),
                q=f(q), qd=f(qd), qdd=f(qdd), tau=f(tau), f_v=f(f_v), mass=f(mass))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--batches", type=int, default=8)
    ap.add_argument("--batch-size", type=int, default=8192)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    data = Path(args.data) if args.data else Path("out/bench_world")
    if not args.data and not (data / "subjects.csv").exists():
        from exolan.world import simulate

        print(f"simulating the default world into {data} (once) ...", flush=True)
        simulate(data, progress=True)
    trials = list(paper_split(load(data)).train)
    desc = _describe(trials)
    stats = compute_stats(trials)
    n = stats["n_samples"]
    print(f"training split: {len(trials)} trials, {n} valid samples; batch {args.batch_size}; "
          f"torch threads {torch.get_num_threads()}; device {dev}")

    torch.manual_seed(0)
    model = build_model("exolan", lim=True, joint_types=desc["joint_types"], joint_names=desc["joint_names"],
                        context_channels=desc["context_channels"], **data_scales(stats))
    model.norm.set_stats(stats["ctx_mean"], stats["ctx_std"])
    model.to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, weight_decay=1e-3)
    W = model.receptive_field - 1

    def step(loss):
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    def timed(fn):
        fn(0)                                   # warm-up
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for b in range(1, args.batches + 1):
            fn(b)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        return (time.perf_counter() - t0) / args.batches

    # sequence level: exolan's training path
    cfg = TrainConfig(batch_size=args.batch_size)
    ch = make_chunks(trials, W, cfg.chunk_steps, cfg.horizon).to(dev)
    per_batch = max(1, cfg.batch_size // cfg.chunk_steps)
    K = ch.q.shape[0]
    gen = torch.Generator().manual_seed(0)
    perm = torch.randperm(K, generator=gen)
    one = torch.ones(2, device=dev)

    def seq_batch(b):
        idx = perm[(b * per_batch) % K:][:per_batch].to(dev)
        step(batch_losses(model, ch, idx, cfg, one, one, desc["dt"], gen)["loss"])

    t_seq = timed(seq_batch)
    batches_seq = -(-K // per_batch)

    # windowed: a fresh TCN pass over the 63-step window of every sample
    wb = {k: v.to(dev) for k, v in windowed_batches(trials, W).items()}
    N = len(wb["pos"])
    order = torch.randperm(N, generator=gen)
    offs = torch.arange(-W, 1, device=dev)

    def win_batch(b):
        sel = order[(b * args.batch_size) % N:][:args.batch_size].to(dev)
        rows = wb["pos"][sel].unsqueeze(1) + offs                      # (B, 63)
        z = model.context(wb["ctx"][rows], wb["keep"][rows])[:, -1]
        g = lambda k: wb[k][sel]
        tau_hat = model.inverse(g("q"), g("qd"), g("qdd"), z, g("f_v"))
        mask = torch.ones(len(sel), dtype=torch.bool, device=dev)
        step(torque_loss(tau_hat, g("tau"), g("mass"), mask))

    t_win = timed(win_batch)
    batches_win = -(-N // args.batch_size)

    e_seq, e_win = t_seq * batches_seq, t_win * batches_win
    print(f"sequence-level encoder: {t_seq * 1e3:8.1f} ms/batch x {batches_seq} batches = {e_seq:8.1f} s/epoch")
    print(f"windowed encoder:       {t_win * 1e3:8.1f} ms/batch x {batches_win} batches = {e_win:8.1f} s/epoch")
    print(f"ratio windowed / sequence-level epoch time: {e_win / e_seq:.2f}x")


if __name__ == "__main__":
    main()
