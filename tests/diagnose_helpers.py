"""Helpers shared by the diagnosis' building-block tests (importable: pytest puts tests/ on the path)."""
from types import SimpleNamespace

import numpy as np


def leg_pair(T=400, mass=70.0, seed=0):
    """Two sides of one recording with different insole forces (for the partner pairing)."""
    rng = np.random.default_rng(seed)
    out = []
    for side in ("l", "r"):
        q = rng.normal(0, 0.3, (T, 2))
        out.append(SimpleNamespace(subject="S01", task="walk", name="walk_1_1", side=side, mass=mass, dt=0.005,
                                   joints=("hip", "knee"), joint_types=("revolute", "revolute"), q=q,
                                   qd=rng.normal(0, 1, (T, 2)), qdd=rng.normal(0, 5, (T, 2)),
                                   tau=rng.normal(0, 10, (T, 2)), tau_e=np.zeros((T, 2)),
                                   f_v=np.abs(rng.normal(300 if side == "l" else 500, 50, T)),
                                   cop=np.zeros((T, 2)), valid=np.ones(T, bool)))
    return out
