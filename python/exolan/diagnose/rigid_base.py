"""The parametric rigid-body base of physics first (`ident`): one joint equation's regressor.

Per joint equation (per subject where the data hold several): inertia q̈_k × (1, cos/sin of every
revolute joint but the first: a serial chain's inertia depends on the distal angles), Coriolis/centripetal
q̇_a q̇_b × (cos, sin) of those angles (two or more revolute joints), gravity cos/sin of every revolute angle and
of the sums and differences of pairs (only where it can act: a prismatic axis gets none), a constant (the
torque offset: `torque_bias`, absorbable), and with insoles the contact term f_v × (1, the same angle functions,
x_cop) and the other leg's load.
"""
from __future__ import annotations

import numpy as np

from .parallel_filter import Signals


def _angle_functions(q: np.ndarray, jt: tuple, distal_only: bool) -> list[np.ndarray]:
    rev = [a for a, t in enumerate(jt) if t == "revolute"]
    use = rev[1:] if distal_only else rev
    out = []
    for a in use:
        out += [np.cos(q[:, a]), np.sin(q[:, a])]
    if not distal_only:
        for i, a in enumerate(rev):
            for b in rev[i + 1:]:
                for comb in (q[:, a] + q[:, b], q[:, a] - q[:, b]):
                    out += [np.cos(comb), np.sin(comb)]
    return out


def base_columns(q, qd, qdd, sig: Signals, flat_forces: bool = True) -> tuple[np.ndarray, list[str]]:
    """(N, p) regressor of one joint equation's rigid-body base (shared by every joint's equation: each joint
    fits its own coefficients), with names. Interacted with subject dummies where there are several."""
    jt = sig.joint_types
    N, n = q.shape
    one = np.ones(N)
    distal = [one] + _angle_functions(q, jt, distal_only=True)
    cols, names = [], []
    for k in range(n):
        for i, f in enumerate(distal):
            cols.append(qdd[:, k] * f); names.append(f"qdd{k}*h{i}")
    rev = [a for a, t in enumerate(jt) if t == "revolute"]
    if len(rev) >= 2:
        for a in range(n):
            for b in range(a, n):
                for i, f in enumerate(distal[1:]):
                    cols.append(qd[:, a] * qd[:, b] * f); names.append(f"qd{a}qd{b}*h{i + 1}")
    grav = _angle_functions(q, jt, distal_only=False)
    for i, f in enumerate(grav):
        cols.append(f); names.append(f"g{i}")
    cols.append(one); names.append("const")
    if flat_forces and np.nanmax(np.abs(sig.f_v)) > 0:
        for i, f in enumerate([one] + grav):
            cols.append(sig.f_v * f); names.append(f"fv*g{i}")
        cols.append(sig.f_v * sig.x_cop); names.append("fv*xcop")
        if np.nanmax(np.abs(sig.f_o)) > 0:
            for i, f in enumerate([one] + grav):
                cols.append(sig.f_o * f); names.append(f"fo*g{i}")
    X = np.stack(cols, 1)
    users = np.unique(sig.subject)
    if len(users) > 1:      # every subject's own body: the base's coefficients per subject
        X = np.concatenate([X * (sig.subject == u)[:, None] for u in users], 1)
        names = [f"{u}:{nm}" for u in users for nm in names]
    return X, names
