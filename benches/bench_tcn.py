"""The TCN encoder's forward + backward at the training shape (32 chunks of 318 positions, 7 channels, float32):
torch's path against the native kernel (rust/tcn.rs through exolan.native_tcn), interleaved round by round in one
process so that a busy machine slows both alike; min and median over the rounds. A benchmark script, not a test.

    python benches/bench_tcn.py [--threads 1] [--rounds 15]
"""
from __future__ import annotations

import argparse
import time

import exolan  # noqa: F401  (first: its process settings apply before torch loads)
import torch

from exolan import native_tcn
from exolan.encoder import TCNEncoder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=15)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    enc = TCNEncoder(7)
    x = torch.randn(32, 318, 7)
    keep = torch.ones(32, 318, dtype=torch.bool)
    keep[::3, :40] = False                      # a third of the chunks start before their trial
    gz = torch.randn(32, 318, enc.z_dim)
    native = native_tcn.DTYPES

    def step(paths):
        native_tcn.DTYPES = paths
        enc.zero_grad(set_to_none=True)
        enc(x, keep).backward(gz)

    if not native_tcn.enabled():
        raise SystemExit("the native module has no tcn_forward (or EXOLAN_NATIVE_TERMS=0)")
    times = {"torch": [], "native": []}
    for _ in range(args.rounds):
        for name, paths, n in (("torch", (), 3), ("native", native, 10)):
            step(paths)
            t0 = time.perf_counter()
            for _ in range(n):
                step(paths)
            times[name].append((time.perf_counter() - t0) / n * 1e3)
    for name, v in times.items():
        v.sort()
        print(f"{name:6s}: min {v[0]:6.2f} ms, median {v[len(v) // 2]:6.2f} ms ({args.threads} thread(s))")


if __name__ == "__main__":
    main()
