"""Learned insole mapping (LIM): contact torque τ_c = B(q, z) f_v.

The contact torque of a foot is J_cᵀ f_c; with only the vertical insole force measured, the paper learns
the lever arms B(q, z) (n values, metres) with a small tanh MLP on the same input as the DeLaN networks,
[φ(q); z]. `lim_scale` (m) sets the output unit so that one network unit is a plausible lever arm.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from .delan import JointFeatures, mlp_forward


class LIM(nn.ModuleList):
    """A ModuleList of the three nn.Linear layers, so that mounted at `lim` its state_dict names are
    `lim.{0,1,2}.weight/bias` (DESIGN.md section 3); the feature map and the scale are plain attributes."""

    def __init__(self, joint_types: Sequence[str], z_dim: int, hidden: int = 16, lim_scale: float = 0.1):
        features = JointFeatures(joint_types)
        d_in = features.dim + z_dim
        super().__init__([nn.Linear(d_in, hidden), nn.Linear(hidden, hidden), nn.Linear(hidden, features.n)])
        self.features = features
        self.z_dim = int(z_dim)
        self.lim_scale = float(lim_scale)

    def lever(self, q: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        """B(q, z) (..., n), metres."""
        lead = q.shape[:-1]
        phi = self.features.phi(q.reshape(-1, q.shape[-1]))
        if self.z_dim:
            x = torch.cat([phi, z.expand(*lead, self.z_dim).reshape(phi.shape[0], -1)], dim=-1)
        else:
            x = phi
        return (self.lim_scale * mlp_forward(self, x)).reshape(*lead, -1)

    def contact_torque(self, q: torch.Tensor, z: torch.Tensor | None, f_v: torch.Tensor) -> torch.Tensor:
        """τ_c = B(q, z) f_v, (..., n); f_v (...,) in N."""
        return self.lever(q, z) * f_v.unsqueeze(-1)
