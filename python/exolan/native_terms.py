"""The Lagrangian's terms from the native training kernel (rust/grad): `Lagrangian.factor_terms` as one
autograd Function whose forward pass and reverse pass are written out by hand in Rust.

Why: in eager torch a training step of ExoLaN is hundreds of small kernels over (N, n, 64) tangent tensors
and their autograd bookkeeping, memory-bound, with torch's float32 `tanh` alone slower than the matrix
products on some CPUs (docs/TRAINING.md). The kernel fuses each layer's value and tangent streams into one
product per tile of samples, keeps the tile in cache through the elementwise chain, and sums every weight
gradient in a fixed order, so its results do not depend on the thread count.

Used on the CPU for float32 (training and the diagnosis' fits) whenever the native module is built; float64
stays on torch's path (the oracle the engine's parity tests compare against), as do CUDA tensors. The switch
and the threads: `exolan.native`.
"""
from __future__ import annotations

import torch

from .native import _native, as_numpy as _np, enabled, threads

DTYPES = (torch.float32,)
MAX_JOINTS = 3


def usable(lag, q: torch.Tensor) -> bool:
    """Whether `lag`'s terms at q run on the kernel: CPU, a dtype in `DTYPES`, at most 3 joints, enabled."""
    return (q.device.type == "cpu" and q.dtype in DTYPES and lag.n <= MAX_JOINTS and enabled()
            and all(p.dtype == q.dtype and p.device.type == "cpu" for p in lag.parameters()))


def _params(lag) -> list[torch.Tensor]:
    return [t for net in (lag.L, lag.V) for layer in net for t in (layer.weight, layer.bias)]


class _Terms(torch.autograd.Function):
    @staticmethod
    def forward(ctx, lag, n_l: int, q, qd, z, *params):
        N, n = q.shape
        dev = dict(dtype=q.dtype)
        L, H = torch.empty(N, n, n, **dev), torch.empty(N, n, n, **dev)
        c, g = torch.empty(N, n, **dev), torch.empty(N, n, **dev)
        arrays = [_np(p) for p in params]
        keep = any(ctx.needs_input_grad)
        ctx.call = _native.terms_forward(
            list(lag.features.joint_types), lag.z_dim, lag.softplus_offset, lag.v_scale, arrays[:n_l], arrays[n_l:],
            _np(q), _np(qd), _np(z), L.numpy(), H.numpy(), c.numpy(), g.numpy(), keep, threads())
        ctx.shapes = (q.shape, z.shape)
        return L, H, c, g

    @staticmethod
    def backward(ctx, dL, dH, dc, dg):
        (qs, zs) = ctx.shapes
        dq, dqd, dz = torch.empty(qs, dtype=dL.dtype), torch.empty(qs, dtype=dL.dtype), torch.empty(zs, dtype=dL.dtype)
        gl, gv = ctx.call.backward(_np(dL), _np(dH), _np(dc), _np(dg), dq.numpy(), dqd.numpy(), dz.numpy(),
                                   threads())
        grads = [torch.from_numpy(a) for pair in list(gl) + list(gv) for a in pair]
        # V's output bias shifts V, not g = ∂V/∂q: no gradient, as in torch's graph (Adam then leaves it alone)
        grads[-1] = None
        return (None, None, dq, dqd, dz, *grads)


def factor_terms(lag, q: torch.Tensor, qd: torch.Tensor, z: torch.Tensor):
    """(L, H, c, g) at flat q, qd (N, n) and z (N, dz), as `Lagrangian.factor_terms` computes them."""
    params = _params(lag)
    return _Terms.apply(lag, 2 * len(lag.L), q, qd, z, *params)
