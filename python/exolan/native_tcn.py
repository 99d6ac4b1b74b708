"""The TCN context encoder from the native training kernel (rust/tcn.rs): `TCNEncoder.forward` as one autograd
Function whose forward pass and reverse pass are written out by hand in Rust.

Why: in eager torch the encoder is five blocks of small convolutions, ReLUs, masks and residual sums over a
(32, 16, 318) batch, each its own kernel with its own autograd node, about a quarter of a training step. The
kernel runs each conv as one matrix product per tap over a sequence's positions, keeps what the reverse pass
needs in one tape, and sums every weight gradient in a fixed order, so its results do not depend on the thread
count.

Used on the CPU for float32 whenever the native module is built; float64 stays on torch's path (the oracle the
tests compare against), as do CUDA tensors. The switch and the threads, shared with the terms kernel:
`exolan.native`.
"""
from __future__ import annotations

import torch

from . import native
from .native import _native, as_numpy as _np

DTYPES = (torch.float32,)


def enabled() -> bool:
    return native.enabled("tcn_forward")


def usable(enc, x: torch.Tensor) -> bool:
    """Whether `enc` at x (B, T, C) runs on the kernel: CPU, a dtype in `DTYPES`, enabled. The weights are taken
    to be alike (as `.to()` leaves them): the first conv's weight stands for all (checking 22 costs 40 µs a call)."""
    w = enc.tcn[0].conv1.weight
    return (x.device.type == "cpu" and x.dtype in DTYPES and x.dim() == 3 and enabled()
            and w.dtype == x.dtype and w.device.type == "cpu")


def _params(enc) -> list[torch.Tensor]:
    """[W, b, …] of every conv in the order the kernel takes them: per block conv1, conv2, res (where there is one)."""
    convs = (c for block in enc.tcn for c in (block.conv1, block.conv2, block.res) if c is not None)
    return [t for c in convs for t in (c.weight, c.bias)]


class _Encode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, enc, tape: bool, x, keep, *params):
        B, T, C = x.shape
        z = torch.empty(B, T, enc.z_dim, dtype=x.dtype)
        ctx.call = _native.tcn_forward(C, enc.z_dim, enc.levels, enc.kernel, [_np(p) for p in params], _np(x),
                                       _np(keep), z.numpy(), tape, native.threads())
        ctx.x_shape = x.shape
        return z

    @staticmethod
    def backward(ctx, dz):
        dx = torch.empty(ctx.x_shape, dtype=dz.dtype) if ctx.needs_input_grad[2] else None
        grads = ctx.call.backward(_np(dz), None if dx is None else dx.numpy(), native.threads())
        return (None, None, dx, None, *(torch.from_numpy(a) for pair in grads for a in pair))


def encode(enc, x: torch.Tensor, keep: torch.Tensor | None) -> torch.Tensor:
    """z (B, T, hidden) from x (B, T, C) and keep (B, T) or None, as `TCNEncoder.forward` computes it."""
    params = _params(enc)
    k = torch.ones(x.shape[:2], dtype=x.dtype) if keep is None else keep.to(x.dtype)
    # no tape where no gradient is wanted (evaluation, torch.no_grad)
    tape = torch.is_grad_enabled() and (x.requires_grad or any(p.requires_grad for p in params))
    return _Encode.apply(enc, tape, x, k, *params)
