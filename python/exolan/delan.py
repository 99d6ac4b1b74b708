"""Lagrangian core: inertia H(q,z) = L Lᵀ, potential V(q,z), and the rigid-body terms c and g.

Every derivative with respect to q is computed *analytically, forward mode*: each layer carries the
Jacobian of its output with respect to q next to its value (dh/dq through tanh is (1 − h²)·da/dq), so one
pass yields H, ∂H/∂q and ∂V/∂q without double backward through autograd. Training still back-propagates
through this pass (the Jacobians are ordinary differentiable tensors).

Shapes: q, qd, qdd, tau (..., n); z (..., dz) (dz may be 0); H (..., n, n). Leading dimensions are free.

The functions at the bottom (`inverse_dynamics`, `forward_dynamics`, `energy`) take the `Lagrangian`
module as their first argument so that the rollout, the losses and the extensions compose them freely.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
from torch import nn
import torch.nn.functional as F

from . import native_mlp, native_terms

REVOLUTE = "revolute"
PRISMATIC = "prismatic"


class Terms(NamedTuple):
    """The rigid-body terms of H q̈ + c + g = τ."""
    H: torch.Tensor  # (..., n, n) inertia, symmetric positive definite
    c: torch.Tensor  # (..., n) Coriolis and centrifugal torque
    g: torch.Tensor  # (..., n) gravity / potential torque ∂V/∂q


def feature_dim(joint_types: Sequence[str]) -> int:
    """Length of φ(q): two entries per revolute joint, one per prismatic joint."""
    for t in joint_types:
        if t not in (REVOLUTE, PRISMATIC):
            raise ValueError(f"unknown joint type {t!r} (expected {REVOLUTE!r} or {PRISMATIC!r})")
    n_rev = sum(t == REVOLUTE for t in joint_types)
    return 2 * n_rev + (len(joint_types) - n_rev)


class JointFeatures:
    """φ(q) = [cos q_rev; sin q_rev; q_prism] and its Jacobian dφ/dq (constant structure, no weights).

    The cos/sin embedding makes the networks periodic in revolute angles; prismatic joints enter as is.
    A plain object, not an nn.Module, so that it adds no names to any state_dict.
    """

    def __init__(self, joint_types: Sequence[str]):
        self.joint_types = tuple(joint_types)
        self.n = len(self.joint_types)
        self.dim = feature_dim(self.joint_types)
        self.rev = [j for j, t in enumerate(self.joint_types) if t == REVOLUTE]
        self.pri = [j for j, t in enumerate(self.joint_types) if t == PRISMATIC]
        # (n, d_phi) 0/1: feature i depends on joint k
        self._owner = torch.zeros(self.n, self.dim, dtype=torch.float64)
        r = len(self.rev)
        for i, j in enumerate(self.rev):
            self._owner[j, i] = self._owner[j, r + i] = 1.0
        for i, j in enumerate(self.pri):
            self._owner[j, 2 * r + i] = 1.0

    def phi(self, q: torch.Tensor) -> torch.Tensor:
        """φ(q) (N, d_phi) alone."""
        parts = []
        if self.rev:
            qr = q if len(self.rev) == self.n else q[:, self.rev]
            parts += [torch.cos(qr), torch.sin(qr)]
        if self.pri:
            parts.append(q[:, self.pri])
        return torch.cat(parts, dim=-1)

    def tangents(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """φ(q) (N, d_phi) and its q-tangents (N, n, d_phi): row k is ∂φ/∂q_k. Each feature depends on one
        joint, so the tangents are the features' own derivatives (−sin, cos, 1) masked by that joint."""
        parts, dparts = [], []
        if self.rev:
            qr = q if len(self.rev) == self.n else q[:, self.rev]
            cos, sin = torch.cos(qr), torch.sin(qr)
            parts += [cos, sin]
            dparts += [-sin, cos]
        if self.pri:
            parts.append(q[:, self.pri])
            dparts.append(torch.ones_like(q[:, self.pri]))
        return torch.cat(parts, dim=-1), torch.cat(dparts, dim=-1).unsqueeze(1) * self._owner.to(q)

    def __call__(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """q (N, n) -> φ (N, d_phi), dφ/dq (N, d_phi, n)."""
        phi, t = self.tangents(q)
        return phi, t.transpose(1, 2)


def mlp(d_in: int, hidden: int, d_out: int, layers: int = 2) -> nn.ModuleList:
    """A ModuleList of `layers` hidden nn.Linear plus the output layer (names .0, .1, ..., .layers)."""
    dims = [d_in] + [hidden] * layers
    mods = [nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:])]
    mods.append(nn.Linear(dims[-1], d_out))
    return nn.ModuleList(mods)


def mlp_forward(layers: nn.ModuleList, x: torch.Tensor) -> torch.Tensor:
    """tanh MLP without derivatives (the heads, the LIM); on the CPU in float32, the native kernel (native_mlp)."""
    if native_mlp.usable(layers, x):
        return native_mlp.forward(layers, x)
    # indexing, not slicing: slicing a ModuleList subclass (the LIM) would re-run its constructor
    h = x
    last = len(layers) - 1
    for i in range(last):
        h = torch.tanh(layers[i](h))
    return layers[last](h)


def mlp_forward_jac(layers: nn.ModuleList, x: torch.Tensor, dx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """tanh MLP value and its Jacobian with respect to q: x (N, d_in); dx (N, k, n), the derivative of the
    first k inputs (φ(q)). Returns y (N, d_out), dy/dq (N, d_out, n) (`mlp_tangents` in the other layout)."""
    y, dy = mlp_tangents(layers, x, dx.transpose(1, 2))
    return y, dy.transpose(1, 2)


def mlp_tangents(layers: nn.ModuleList, x: torch.Tensor, tx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """tanh MLP value y (N, d_out) and its q-tangents dy (N, n, d_out), carried forward layer by layer.

    tx (N, n, k): the tangents of the first k inputs (φ(q)); the remaining inputs (z) do not depend on q, so
    the first layer's tangent GEMM reads only its first k columns. Value and tangents stay separate contiguous
    tensors (the training hot path: every elementwise op runs over contiguous memory).
    """
    first = layers[0]
    a = F.linear(x, first.weight, first.bias)
    da = F.linear(tx, first.weight[:, : tx.shape[-1]])
    for i in range(1, len(layers)):
        h = torch.tanh(a)
        da = (1.0 - h * h).unsqueeze(1) * da                      # tanh' = 1 − tanh²
        a = F.linear(h, layers[i].weight, layers[i].bias)
        da = F.linear(da, layers[i].weight)
    return a, da


def tril_indices(n: int) -> tuple[list[int], list[int]]:
    """Strictly-lower entries in row-major order: (1,0), (2,0), (2,1), ... (DESIGN.md section 2)."""
    rows, cols = [], []
    for i in range(1, n):
        for j in range(i):
            rows.append(i)
            cols.append(j)
    return rows, cols


class Lagrangian(nn.Module):
    """L(q, q̇, z) = ½ q̇ᵀ H(q,z) q̇ − V(q,z) with H = L Lᵀ; holds the networks `L` and `V`.

    Its state_dict names are `L.{0,1,2}.*` and `V.{0,1,2}.*` (the model mounts it at `delan`).
    `softplus_offset` keeps H strictly positive definite; `v_scale` (N m, set from the torque spread of the
    data) makes ∂V/∂q of order one network unit.
    """

    def __init__(self, joint_types: Sequence[str], z_dim: int = 0, hidden: int = 64,
                 softplus_offset: float = 1e-3, v_scale: float = 1.0):
        super().__init__()
        self.features = JointFeatures(joint_types)
        self.n = self.features.n
        self.z_dim = int(z_dim)
        self.softplus_offset = float(softplus_offset)
        self.v_scale = float(v_scale)
        d_in = self.features.dim + self.z_dim
        n = self.n
        self.L = mlp(d_in, hidden, n * (n + 1) // 2)
        self.V = mlp(d_in, hidden, 1)
        self._tril = tril_indices(n)
        self._scatters: dict = {}

    # -- the networks with their q-Jacobians -------------------------------------------------------
    def _inputs(self, q: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        phi, dphi = self.features(q)
        x = torch.cat([phi, z], dim=-1) if self.z_dim else phi
        return x, dphi

    def _scatter(self, like: torch.Tensor) -> torch.Tensor:
        """(m, n·n) 0/1: network output o -> its entry of L (diagonal first, then the strict lower part)."""
        key = (like.dtype, like.device)
        if key not in self._scatters:
            n = self.n
            S = torch.zeros(n * (n + 1) // 2, n * n, dtype=like.dtype)
            for o in range(n):
                S[o, o * n + o] = 1.0
            for o, (i, j) in enumerate(zip(*self._tril)):
                S[n + o, i * n + j] = 1.0
            self._scatters[key] = S.to(like.device)
        return self._scatters[key]

    def _factor(self, u: torch.Tensor, du: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """L (N, n, n) from the network output u (N, m), and its q-tangents dL (N, k, n, n) from du (N, k, m):
        softplus + offset on the diagonal (softplus' = sigmoid), the rest as is; one GEMM places the entries."""
        n, N = self.n, u.shape[0]
        d = u[:, :n]
        S = self._scatter(u)
        Lm = (torch.cat([F.softplus(d) + self.softplus_offset, u[:, n:]], dim=1) @ S).view(N, n, n)
        if du is None:
            return Lm, None
        du2 = torch.cat([torch.sigmoid(d).unsqueeze(1) * du[:, :, :n], du[:, :, n:]], dim=2)
        return Lm, (du2 @ S).view(N, du.shape[1], n, n)

    def _flatten(self, *xs: torch.Tensor) -> tuple[tuple[int, ...], list[torch.Tensor]]:
        lead = xs[0].shape[:-1]
        N = lead.numel()
        return lead, [x.reshape(N, x.shape[-1]) for x in xs]

    def _z(self, z: torch.Tensor | None, q: torch.Tensor) -> torch.Tensor:
        if z is None:
            if self.z_dim:
                raise ValueError(f"this Lagrangian needs a context z of dimension {self.z_dim}")
            return q.new_zeros(*q.shape[:-1], 0)
        if z.shape[-1] != self.z_dim:
            raise ValueError(f"z has {z.shape[-1]} channels, expected {self.z_dim}")
        return z.expand(*q.shape[:-1], self.z_dim)

    # -- public pieces -----------------------------------------------------------------------------
    def inertia(self, q: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        z = self._z(z, q)
        lead, (qf, zf) = self._flatten(q, z)
        if native_terms.usable(self, qf):
            # the same bits as the H of `factor_terms` (the fits use either)
            return native_terms.factor_terms(self, qf, torch.zeros_like(qf), zf)[1].reshape(*lead, self.n, self.n)
        phi = self.features.phi(qf)
        x = torch.cat([phi, zf], dim=-1) if self.z_dim else phi
        Lm, _ = self._factor(mlp_forward(self.L, x), None)
        return (Lm @ Lm.transpose(-1, -2)).reshape(*lead, self.n, self.n)

    def potential(self, q: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        """V(q, z) (...,), J (or N m)."""
        z = self._z(z, q)
        lead, (qf, zf) = self._flatten(q, z)
        x, _ = self._inputs(qf, zf)
        return (self.v_scale * mlp_forward(self.V, x)[:, 0]).reshape(lead)

    def gravity(self, q: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        """g = ∂V/∂q (..., n) alone, without the inertia network (the diagnosis's load term needs only g)."""
        z = self._z(z, q)
        lead, (qf, zf) = self._flatten(q, z)
        x, dphi = self._inputs(qf, zf)
        return self._gravity(x, dphi).reshape(*lead, self.n)

    def _gravity(self, x: torch.Tensor, dphi: torch.Tensor) -> torch.Tensor:
        _, dv = mlp_forward_jac(self.V, x, dphi)
        return self.v_scale * dv[:, 0, :]

    def terms(self, q: torch.Tensor, qd: torch.Tensor, z: torch.Tensor | None = None) -> Terms:
        """H, c = Ḣ q̇ − ½ ∂(q̇ᵀ H q̇)/∂q and g = ∂V/∂q, all from one forward-mode pass."""
        Lm, H, c, g = self.factor_terms(q, qd, z)
        return Terms(H, c, g)

    def factor_terms(self, q: torch.Tensor, qd: torch.Tensor, z: torch.Tensor | None = None):
        """(L, H, c, g): `terms` and the Cholesky factor L of H that the networks produce (a forward-dynamics
        solve needs no factorisation then)."""
        z = self._z(z, q)
        lead, (qf, qdf, zf) = self._flatten(q, qd, z)
        N, n = qf.shape
        if native_terms.usable(self, qf):
            Lm, H, c, g = native_terms.factor_terms(self, qf, qdf, zf)
            return (Lm.reshape(*lead, n, n), H.reshape(*lead, n, n), c.reshape(*lead, n), g.reshape(*lead, n))
        phi, tphi = self.features.tangents(qf)                                   # (N, d_phi), (N, n, d_phi)
        x = torch.cat([phi, zf], dim=-1) if self.z_dim else phi
        u, du = mlp_tangents(self.L, x, tphi)
        _, dv = mlp_tangents(self.V, x, tphi)
        Lm, dL = self._factor(u, du)                                             # dL[b, k] = ∂L/∂q_k
        H = Lm @ Lm.transpose(-1, -2)
        # Ḣ q̇ = L̇ (Lᵀ q̇) + L (L̇ᵀ q̇) with L̇ = Σ_k ∂L/∂q_k q̇_k
        w = (Lm.transpose(-1, -2) @ qdf.unsqueeze(-1))                           # (N, n, 1) = Lᵀ q̇
        Ld = (qdf.unsqueeze(1) @ dL.reshape(N, n, n * n)).view(N, n, n)
        Hd_qd = Ld @ w + Lm @ (Ld.transpose(-1, -2) @ qdf.unsqueeze(-1))
        # ½ ∂(q̇ᵀ L Lᵀ q̇)/∂q_k = q̇ᵀ (∂L/∂q_k) (Lᵀ q̇)
        dT = ((dL @ w.unsqueeze(1)).squeeze(-1) * qdf.unsqueeze(1)).sum(-1)   # (N, n)
        c = Hd_qd.squeeze(-1) - dT
        g = self.v_scale * dv[:, :, 0]
        return (Lm.reshape(*lead, n, n), H.reshape(*lead, n, n), c.reshape(*lead, n), g.reshape(*lead, n))


# -- pure functions of a Lagrangian ----------------------------------------------------------------

def inverse_dynamics(lag: Lagrangian, q, qd, qdd, z=None) -> torch.Tensor:
    """τ = H q̈ + c + g (no contact or extension terms)."""
    return inverse_dynamics_inertia(lag, q, qd, qdd, z)[0]


def inverse_dynamics_inertia(lag: Lagrangian, q, qd, qdd, z=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(τ, H): `inverse_dynamics` and the inertia it used (a fit's acceleration term reuses H instead of
    evaluating the network again)."""
    H, c, g = lag.terms(q, qd, z)
    return (H @ qdd.unsqueeze(-1)).squeeze(-1) + c + g, H


def solve_inertia(H: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """H⁻¹ rhs (H is SPD by construction): a leg's 1 or 2 joints in closed form (a batched LAPACK factorisation
    and its backward cost 7x more, 12 % of a diagnosis fit step), else through a Cholesky factorisation."""
    n = H.shape[-1]
    if n == 1:
        return rhs / H[..., 0]
    if n == 2:
        a, b, c, d = H[..., 0, 0], H[..., 0, 1], H[..., 1, 0], H[..., 1, 1]
        det = a * d - b * c
        if bool((det > 0).all()):
            r0, r1 = rhs[..., 0], rhs[..., 1]
            return torch.stack([d * r0 - b * r1, a * r1 - c * r0], -1) / det.unsqueeze(-1)
    Lc, info = torch.linalg.cholesky_ex(H)
    if bool((info != 0).any()):
        # only round-off can make L Lᵀ + offset fail to factorise (e.g. offset 0 in float32): fall back to LU
        return torch.linalg.solve(H, rhs.unsqueeze(-1)).squeeze(-1)
    return torch.cholesky_solve(rhs.unsqueeze(-1), Lc).squeeze(-1)


def solve_factor(Lm: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """H⁻¹ rhs for H = L Lᵀ with L lower triangular (..., n, n): forward then back substitution written out
    over the batch (O(n²) elementwise ops; faster than a batched LAPACK call for the few joints of a leg)."""
    n = rhs.shape[-1]
    y: list[torch.Tensor] = []
    for i in range(n):
        acc = rhs[..., i]
        for j in range(i):
            acc = acc - Lm[..., i, j] * y[j]
        y.append(acc / Lm[..., i, i])
    x: list[torch.Tensor] = [rhs[..., 0]] * n
    for i in reversed(range(n)):
        acc = y[i]
        for j in range(i + 1, n):
            acc = acc - Lm[..., j, i] * x[j]
        x[i] = acc / Lm[..., i, i]
    return torch.stack(x, dim=-1)


def forward_dynamics(lag: Lagrangian, q, qd, tau, z=None) -> torch.Tensor:
    """q̈ = H⁻¹ (τ − c − g); τ is every generalised force acting besides the rigid-body terms."""
    Lm, _, c, g = lag.factor_terms(q, qd, z)
    return solve_factor(Lm, tau - c - g)


def energy(lag: Lagrangian, q, qd, z=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Kinetic T = ½ q̇ᵀ H q̇ and potential V, each (...,)."""
    H = lag.inertia(q, z)
    T = 0.5 * (qd.unsqueeze(-2) @ H @ qd.unsqueeze(-1)).squeeze(-1).squeeze(-1)
    return T, lag.potential(q, z)
