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

    def __call__(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """q (N, n) -> φ (N, d_phi), dφ/dq (N, d_phi, n)."""
        N, n = q.shape
        r = len(self.rev)
        phi_parts, dphi = [], q.new_zeros(N, self.dim, n)
        if r:
            qr = q[:, self.rev]
            cos, sin = torch.cos(qr), torch.sin(qr)
            phi_parts += [cos, sin]
            for i, j in enumerate(self.rev):
                dphi[:, i, j] = -sin[:, i]          # d cos q_j / d q_j
                dphi[:, r + i, j] = cos[:, i]       # d sin q_j / d q_j
        if self.pri:
            phi_parts.append(q[:, self.pri])
            for i, j in enumerate(self.pri):
                dphi[:, 2 * r + i, j] = 1.0
        return torch.cat(phi_parts, dim=-1), dphi


def mlp(d_in: int, hidden: int, d_out: int, layers: int = 2) -> nn.ModuleList:
    """A ModuleList of `layers` hidden nn.Linear plus the output layer (names .0, .1, ..., .layers)."""
    dims = [d_in] + [hidden] * layers
    mods = [nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:])]
    mods.append(nn.Linear(dims[-1], d_out))
    return nn.ModuleList(mods)


def mlp_forward(layers: nn.ModuleList, x: torch.Tensor) -> torch.Tensor:
    """tanh MLP without derivatives (the heads, the LIM)."""
    # indexing, not slicing: slicing a ModuleList subclass (the LIM) would re-run its constructor
    h = x
    last = len(layers) - 1
    for i in range(last):
        h = torch.tanh(layers[i](h))
    return layers[last](h)


def mlp_forward_jac(layers: nn.ModuleList, x: torch.Tensor, dx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """tanh MLP value and its Jacobian with respect to q, carried forward layer by layer.

    x (N, d_in); dx (N, k, n): the derivative of the first k inputs (φ(q)) with respect to q — the
    remaining inputs (z) do not depend on q, so only the first layer's first k columns see dx.
    Returns y (N, d_out), dy/dq (N, d_out, n).

    Internally the Jacobian is carried as n tangent rows (N, n, width), so that every layer's
    derivative is one plain GEMM, da = dh Wᵀ, over N·n rows (no batched matmul with a broadcast W).
    """
    first = layers[0]
    k = dx.shape[1]
    a = first(x)
    da = F.linear(dx.transpose(1, 2), first.weight[:, :k])       # (N, n, h)
    for i in range(1, len(layers)):
        lin = layers[i]
        h = torch.tanh(a)
        dh = (1.0 - h * h).unsqueeze(1) * da                      # tanh' = 1 − tanh²
        a = lin(h)
        da = F.linear(dh, lin.weight)
    return a, da.transpose(1, 2)


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

    # -- the networks with their q-Jacobians -------------------------------------------------------
    def _inputs(self, q: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        phi, dphi = self.features(q)
        x = torch.cat([phi, z], dim=-1) if self.z_dim else phi
        return x, dphi

    def _cholesky(self, x: torch.Tensor, dphi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """L (N, n, n) lower triangular and dL/dq (N, n, n, n), last index = q_k."""
        n = self.n
        u, du = mlp_forward_jac(self.L, x, dphi)         # (N, m), (N, m, n)
        N = u.shape[0]
        Lm = u.new_zeros(N, n, n)
        dL = u.new_zeros(N, n, n, n)
        diag = torch.arange(n)
        d_u = u[:, :n]
        Lm[:, diag, diag] = F.softplus(d_u) + self.softplus_offset
        dL[:, diag, diag, :] = torch.sigmoid(d_u).unsqueeze(-1) * du[:, :n]   # softplus' = sigmoid
        if n > 1:
            rows, cols = self._tril
            Lm[:, rows, cols] = u[:, n:]
            dL[:, rows, cols, :] = du[:, n:]
        return Lm, dL

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
        x, dphi = self._inputs(qf, zf)
        Lm, _ = self._cholesky(x, dphi)
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
        z = self._z(z, q)
        lead, (qf, qdf, zf) = self._flatten(q, qd, z)
        x, dphi = self._inputs(qf, zf)
        Lm, dL = self._cholesky(x, dphi)
        H = Lm @ Lm.transpose(-1, -2)
        # Time derivative of L along the motion: L̇ = Σ_k ∂L/∂q_k q̇_k; Ḣ = L̇ Lᵀ + L L̇ᵀ.
        Ld = torch.einsum("bijk,bk->bij", dL, qdf)
        Hd_qd = Ld @ (Lm.transpose(-1, -2) @ qdf.unsqueeze(-1)) + Lm @ (Ld.transpose(-1, -2) @ qdf.unsqueeze(-1))
        # ∂(q̇ᵀ L Lᵀ q̇)/∂q_k = 2 (∂L/∂q_k ᵀ q̇) · (Lᵀ q̇), so the ½ cancels the 2.
        Lt_qd = (Lm.transpose(-1, -2) @ qdf.unsqueeze(-1)).squeeze(-1)            # (N, n)
        dLt_qd = torch.einsum("bijk,bi->bjk", dL, qdf)                            # (N, n, n): [j, k]
        dT = torch.einsum("bjk,bj->bk", dLt_qd, Lt_qd)
        c = Hd_qd.squeeze(-1) - dT
        g = self._gravity(x, dphi)
        n = self.n
        return Terms(H.reshape(*lead, n, n), c.reshape(*lead, n), g.reshape(*lead, n))


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
    """H⁻¹ rhs through a Cholesky factorisation (H is SPD by construction); general n."""
    Lc, info = torch.linalg.cholesky_ex(H)
    if bool((info != 0).any()):
        # only round-off can make L Lᵀ + offset fail to factorise (e.g. offset 0 in float32): fall back to LU
        return torch.linalg.solve(H, rhs.unsqueeze(-1)).squeeze(-1)
    return torch.cholesky_solve(rhs.unsqueeze(-1), Lc).squeeze(-1)


def forward_dynamics(lag: Lagrangian, q, qd, tau, z=None) -> torch.Tensor:
    """q̈ = H⁻¹ (τ − c − g); τ is every generalised force acting besides the rigid-body terms."""
    H, c, g = lag.terms(q, qd, z)
    return solve_inertia(H, tau - c - g)


def energy(lag: Lagrangian, q, qd, z=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Kinetic T = ½ q̇ᵀ H q̇ and potential V, each (...,)."""
    H = lag.inertia(q, z)
    T = 0.5 * (qd.unsqueeze(-2) @ H @ qd.unsqueeze(-1)).squeeze(-1).squeeze(-1)
    return T, lag.potential(q, z)
