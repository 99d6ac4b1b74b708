"""Semi-implicit Euler rollouts in torch (DESIGN.md section 5).

    q̈_k = forward_dynamics(q_k, q̇_k, τ_k, z_k, f_v,k)
    q̇_{k+1} = q̇_k + dt q̈_k
    q_{k+1} = q_k + dt q̇_{k+1}

τ, z and f_v are the recorded ones at step k (z held constant within a step). The same update is used by
the multi-step loss, the evaluation and the energy check, and by the Rust engine.
"""
from __future__ import annotations

import torch


def euler_step(q, qd, qdd, dt):
    """One semi-implicit Euler step: velocity first, then position with the new velocity."""
    qd1 = qd + dt * qdd
    return q + dt * qd1, qd1


def rollout(model, q0, qd0, tau, dt, z=None, f_v=None, qdd0=None):
    """Open-loop rollout of a DeLaN-based model over H = tau.shape[-2] steps.

    q0, qd0 (B, n); tau (B, H, n); z (B, H, dz) or None; f_v (B, H) or None. `qdd0` (B, n), where given, is
    the model's q̈ at the initial state (the training batch has already computed it: the multi-step loss
    then evaluates the model H − 1 times per start instead of H).
    Returns q, qd (B, H + 1, n), index 0 being the initial state.
    """
    H = tau.shape[-2]
    qs, qds = [q0], [qd0]
    q, qd = q0, qd0
    for k in range(H):
        if k == 0 and qdd0 is not None:
            qdd = qdd0
        else:
            qdd = model.forward_dynamics(q, qd, tau[..., k, :],
                                         None if z is None else z[..., k, :],
                                         None if f_v is None else f_v[..., k])
        q, qd = euler_step(q, qd, qdd, dt)
        qs.append(q)
        qds.append(qd)
    return torch.stack(qs, dim=-2), torch.stack(qds, dim=-2)


def free_rollout(model, q0, qd0, dt, steps, z=None):
    """Unforced rollout of the conservative part of the model (no input, no LIM, z frozen).

    Returns q, qd (B, steps + 1, n) and the kinetic and potential energies T, V (B, steps + 1)."""
    from .delan import energy, forward_dynamics

    lag = model.delan
    zz = model._z(z, q0)
    zero = torch.zeros_like(q0)
    qs, qds = [q0], [qd0]
    q, qd = q0, qd0
    for _ in range(steps):
        qdd = forward_dynamics(lag, q, qd, zero, zz)
        q, qd = euler_step(q, qd, qdd, dt)
        qs.append(q)
        qds.append(qd)
    Q, QD = torch.stack(qs, dim=-2), torch.stack(qds, dim=-2)
    T, V = energy(lag, Q, QD, zz.unsqueeze(-2).expand(*Q.shape[:-1], zz.shape[-1]))
    return Q, QD, T, V
