"""Probe, tried and dropped (docs/TRAINING.md, "The allocator, and a hand-written backward tried"): a tanh MLP's
value and its q-tangents in one pass, with a hand-written backward. For the measurement `delan.mlp_tangents`
returned `tangent_mlp(layers, x, tx)` split into slot 0 and slots 1.. (tangents slot-major); it was no faster.

The DeLaN networks carry, next to each layer's value, its derivatives along the n joint angles
(`delan.mlp_tangents`). Written with autograd, each of those elementwise steps records its own backward, and
a step of ExoLaN+LIM was thought to spend its time there (measured: it did not). Here the value and the tangents
sit in one slot-major tensor (1 + n, N, width): slot 0 the value, slots 1..n the tangents, so a hidden layer
is one matrix product over all slots, and the backward of a layer is two matrix products and four
elementwise passes. For one layer (a = W x + b, h = tanh a, s = 1 − h², tangents t = W ẋ, p = s t):

    ∂/∂t = s · ∂/∂p,    ∂/∂a = s · (∂/∂h − 2 h Σ_k t_k ∂/∂p_k)

The first layer reads the tangents of the first k inputs only (φ(q); the context z does not depend on q).
Only first derivatives are supported (nothing in exolan differentiates a gradient of these networks).
"""
from __future__ import annotations

import torch


def _tanh_slope(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """tanh(a) and its derivative 1 − tanh²(a)."""
    h = torch.tanh(a)
    return h, torch.addcmul(torch.ones((), dtype=h.dtype, device=h.device), h, h, value=-1.0)


class TangentMLP(torch.autograd.Function):
    """apply(x (N, d), t (n, N, k), W0, b0, W1, b1, ...) -> (1 + n, N, d_out): the output layer's value in
    slot 0 and its tangents in slots 1..n; every layer but the last is followed by tanh."""

    @staticmethod
    def forward(ctx, x, t, *params):
        Ws, bs = params[0::2], params[1::2]
        n, N, k = t.shape
        A = x.new_empty(1 + n, N, Ws[0].shape[0])
        torch.addmm(bs[0], x, Ws[0].t(), out=A[0])
        torch.mm(t.reshape(n * N, k), Ws[0][:, :k].t(), out=A[1:].view(n * N, -1))
        saved = []
        for W, b in zip(Ws[1:], bs[1:]):
            h, s = _tanh_slope(A[0])
            Y = torch.empty_like(A)
            Y[0] = h
            torch.mul(A[1:], s, out=Y[1:])
            saved += [A[1:], s, Y]
            A = (Y.view((1 + n) * N, -1) @ W.t()).view(1 + n, N, -1)
            A[0] += b
        ctx.save_for_backward(x, t, *saved, *Ws)
        ctx.layers = len(Ws)
        return A

    @staticmethod
    def backward(ctx, G):
        L = ctx.layers
        x, t, *rest = ctx.saved_tensors
        acts, Ws = rest[: 3 * (L - 1)], rest[3 * (L - 1):]
        n, N, k = t.shape
        S = 1 + n
        G = G.contiguous()
        grads: list = [None] * (2 * L)
        for i in range(L - 1, 0, -1):
            T, s, Y = acts[3 * (i - 1): 3 * i]
            Gf = G.view(S * N, -1)
            grads[2 * i] = Gf.t() @ Y.view(S * N, -1)
            grads[2 * i + 1] = G[0].sum(0)
            GY = (Gf @ Ws[i]).view(S, N, -1)
            GA = torch.empty_like(GY)
            torch.mul(GY[1:], s, out=GA[1:])
            gs = (GY[1:] * T).sum(0)                                 # Σ_k t_k ∂/∂p_k
            torch.addcmul(GY[0], Y[0], gs, value=-2.0, out=GA[0])
            GA[0].mul_(s)
            G = GA
        Gt = G[1:].reshape(n * N, -1)
        gW0 = G[0].t() @ x
        gW0[:, :k].addmm_(Gt.t(), t.reshape(n * N, k))
        grads[0], grads[1] = gW0, G[0].sum(0)
        gx = G[0] @ Ws[0] if ctx.needs_input_grad[0] else None
        gt = (Gt @ Ws[0][:, :k]).view(n, N, k) if ctx.needs_input_grad[1] else None
        return (gx, gt, *grads)


def tangent_mlp(layers, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """`TangentMLP` of an nn.ModuleList of nn.Linear (see `delan.mlp`)."""
    params = []
    for m in layers:
        params += [m.weight, m.bias]
    return TangentMLP.apply(x, t.contiguous(), *params)
