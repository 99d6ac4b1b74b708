"""Training losses. Each takes a boolean mask of the samples that may enter (DESIGN.md: `valid`); masked
samples are excluded by selection, never by multiplying a NaN with zero."""
from __future__ import annotations

import torch


def _masked_mean(sq: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of sq (..., n) over the samples where mask (...) holds and over joints."""
    sel = sq[mask]
    if sel.numel() == 0:
        return sq.sum() * 0.0          # keeps the graph, contributes nothing
    return sel.mean()


def torque_loss(tau_hat, tau, mass, mask):
    """Mass-normalised torque MSE ((τ̂ − τ)/m)², (N m/kg)²: every user weighs the same."""
    return _masked_mean(((tau_hat - tau) / mass.unsqueeze(-1)) ** 2, mask)


def acceleration_loss(qdd_hat, qdd, mask):
    """Acceleration MSE, (rad/s²)² (m/s² for prismatic joints)."""
    return _masked_mean((qdd_hat - qdd) ** 2, mask)


def multistep_loss(q_hat, qd_hat, q, qd, inv_var_q, inv_var_qd):
    """Rollout error over steps 1..H, each joint's q and q̇ error divided by its training-set variance.

    q_hat, qd_hat, q, qd: (N_s, H, n) (the initial state excluded); inv_var_*: (n,)."""
    return ((q_hat - q) ** 2 * inv_var_q + (qd_hat - qd) ** 2 * inv_var_qd).mean()
