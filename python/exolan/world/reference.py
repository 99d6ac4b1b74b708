"""The world's own leg as a forward-dynamics reference for the learned models.

A learned model's open-loop rollout error is only meaningful beside what the recorded signals allow: the
simulated world knows its true leg (segment parameters per user), so its rigid-body model can be fed exactly
what a learned model is fed (the recorded angles, velocities, actuated torque τ and vertical insole force f_v
at the recorded centre of pressure) and rolled out the same way. It still misses what is not recorded: the
pelvis' tilt and acceleration (the recorded hip angle is relative to the pelvis) and the horizontal ground
force. A learned model can beat it where its context z captures those (e.g. the average pelvis tilt); it is a
reference, not a bound.
"""
from __future__ import annotations

import numpy as np

from . import dynamics as dyn
from .anthropometry import LegParams, leg_params, make_users


def true_legs(users: int, seed: int) -> dict[str, LegParams]:
    """Each simulated user's leg (exoskeleton segments included), as `simulate(users=…, seed=…)` drew it."""
    from . import _rng

    return {u.name: leg_params(u, exo=True, seg_scale=u.style["seg_scale"]) for u in make_users(users, _rng(seed, 0))}


def forward(p: LegParams, q, qd, tau, f_v, cop_x) -> np.ndarray:
    """q̈ of the true leg (plain gravity, hip fixed) under the recorded τ and the vertical insole force f_v at the
    recorded centre of pressure; rows (N, 2)."""
    f = np.stack([np.zeros_like(f_v), f_v], axis=-1)
    loaded = f_v > 0
    cop = np.where(loaded, np.nan_to_num(cop_x), 0.0)
    tau_c = np.where(loaded[:, None], dyn.contact_torque(p, q, dyn.cop_point(p, q, cop), f), 0.0)
    return dyn.forward_dynamics(p, q, qd, tau + tau_c)
