"""Plain tanh MLPs from the native training kernel (rust/grad/mlp.rs): `delan.mlp_forward` as one autograd
Function, for the networks that carry no q-tangents: the black-box models' heads and the learned insole mapping.

Why: each layer in eager torch is a product, a bias, a tanh and their autograd nodes, and torch's float32 `tanh`
alone took 5.5 ms of a 24.6 ms MLP-TCN+LIM training step on this machine's CPU (docs/TRAINING.md). The kernel
runs the terms kernel's tiles with one stream (rust/grad/net.rs) and sums the weight gradients in a fixed order.

Used on the CPU for float32 where the native module is built; float64 and CUDA stay on torch's path. The
switch and the threads: `exolan.native`.
"""
from __future__ import annotations

import torch

from . import native
from .native import _native, as_numpy as _np

DTYPES = (torch.float32,)


def usable(layers, x: torch.Tensor) -> bool:
    """Whether the MLP `layers` (nn.Linear, tanh between) at x runs on the kernel: at least one hidden layer, CPU,
    a dtype in `DTYPES`, enabled (the first layer's weight stands for all, as `.to()` moves them together)."""
    w = layers[0].weight
    return (len(layers) >= 2 and x.device.type == "cpu" and x.dtype in DTYPES and w.dtype == x.dtype
            and w.device.type == "cpu" and native.enabled("mlp_forward"))


class _Mlp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, *params):
        y = torch.empty(x.shape[0], params[-1].shape[0], dtype=x.dtype)
        ctx.call = _native.mlp_forward([_np(p) for p in params], _np(x), y.numpy(), any(ctx.needs_input_grad),
                                       native.threads())
        ctx.x_shape = x.shape
        return y

    @staticmethod
    def backward(ctx, dy):
        dx = torch.empty(ctx.x_shape, dtype=dy.dtype) if ctx.needs_input_grad[0] else None
        grads = ctx.call.backward(_np(dy), None if dx is None else dx.numpy(), native.threads())
        return (dx, *(torch.from_numpy(a) for pair in grads for a in pair))


def forward(layers, x: torch.Tensor) -> torch.Tensor:
    """The tanh MLP `layers` at x (..., d_in) -> (..., d_out), as `delan.mlp_forward` computes it."""
    lead = x.shape[:-1]
    params = [t for layer in layers for t in (layer.weight, layer.bias)]
    y = _Mlp.apply(x.reshape(-1, x.shape[-1]), *params)
    return y.reshape(*lead, y.shape[-1])
