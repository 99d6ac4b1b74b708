"""The native training kernels' switch and threads (rust/grad: the Lagrangian's terms, the TCN encoder).

The kernels replace torch's autograd on the CPU in float32 where the extension is built; EXOLAN_NATIVE_TERMS=0
turns them off (benches/bench_train.py --torch-path measures both). A run's CPU threads go to the kernels,
torch's own ops keep one: at two threads torch's small elementwise ops cost more in synchronisation than they
gain, and the kernels split a batch in fixed chunks (docs/TRAINING.md, "Native kernels").
"""
from __future__ import annotations

import contextlib
import os

import torch

try:
    from . import _native
except ImportError:  # a source tree without the built extension: torch's path only
    _native = None

_threads: int | None = None


def enabled(function: str = "terms_forward") -> bool:
    """Whether the native module has `function` and the kernels are not switched off."""
    return _native is not None and hasattr(_native, function) and os.environ.get("EXOLAN_NATIVE_TERMS", "1") != "0"


def as_numpy(t: torch.Tensor):
    """t's values as a contiguous numpy array (a view where t is already contiguous), for a kernel call."""
    return t.detach().contiguous().numpy()


def threads() -> int:
    """Threads of a kernel call: those of the run (`cpu_threads`), else torch's intra-op thread count."""
    return _threads or torch.get_num_threads()


@contextlib.contextmanager
def cpu_threads(n: int):
    """A run's `n` CPU threads: all of them to the native kernels, one to torch's ops where the kernels are on
    (else all n to torch). Restores both on exit."""
    global _threads
    old_torch, old = torch.get_num_threads(), _threads
    try:
        if enabled():
            torch.set_num_threads(1)
            _threads = max(1, n)
        else:
            torch.set_num_threads(max(1, n))
        yield
    finally:
        torch.set_num_threads(old_torch)
        _threads = old
