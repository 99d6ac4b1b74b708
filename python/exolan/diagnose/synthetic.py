"""Small analytic systems with a planted effect, for testing the diagnosis without the exoskeleton world.

- `two_link(...)`: a planar 2-link arm in a vertical plane (revolute joints, point masses at the link
  ends... with link inertias), kinematics first (sums of sines), torques by analytic inverse dynamics.
- `linear_drive(...)`: a prismatic axis (a carriage of mass m on an inclined rail) — a layout-2 system.

Trials are duck-typed like `exolan.data.Trial` (layout 2: mass 1, no insole, no exo torque unless asked).
Planted effects follow DESIGN.md section 4; `effects` is returned separately (ground truth, for tests only).
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

G = 9.81


def _kinematics(rng, T, dt, n, amp, freqs=(0.3, 2.0)):
    t = np.arange(T) * dt
    q = np.zeros((T, n)); qd = np.zeros((T, n)); qdd = np.zeros((T, n))
    for j in range(n):
        for _ in range(4):
            a = amp[j] * rng.uniform(0.2, 0.6)
            w = 2 * np.pi * rng.uniform(*freqs)
            p = rng.uniform(0, 2 * np.pi)
            q[:, j] += a * np.sin(w * t + p)
            qd[:, j] += a * w * np.cos(w * t + p)
            qdd[:, j] += -a * w * w * np.sin(w * t + p)
    return q, qd, qdd


def _two_link_id(q, qd, qdd, m1=2.0, m2=1.5, l1=0.4, l2=0.35):
    """Inverse dynamics of a 2-link arm, joint 0 measured from the downward vertical."""
    r1, r2 = l1 / 2, l2 / 2
    I1, I2 = m1 * l1 ** 2 / 12, m2 * l2 ** 2 / 12
    c2, s2 = np.cos(q[:, 1]), np.sin(q[:, 1])
    H11 = I1 + I2 + m1 * r1 ** 2 + m2 * (l1 ** 2 + r2 ** 2 + 2 * l1 * r2 * c2)
    H12 = I2 + m2 * (r2 ** 2 + l1 * r2 * c2)
    H22 = I2 + m2 * r2 ** 2
    h = m2 * l1 * r2 * s2
    c1 = -h * (2 * qd[:, 0] * qd[:, 1] + qd[:, 1] ** 2)
    cc2 = h * qd[:, 0] ** 2
    g1 = (m1 * r1 + m2 * l1) * G * np.sin(q[:, 0]) + m2 * r2 * G * np.sin(q[:, 0] + q[:, 1])
    g2 = m2 * r2 * G * np.sin(q[:, 0] + q[:, 1])
    tau = np.stack([H11 * qdd[:, 0] + H12 * qdd[:, 1] + c1 + g1, H12 * qdd[:, 0] + H22 * qdd[:, 1] + cc2 + g2], 1)
    return tau


def _trial(name, dt, joints, jtypes, q, qd, qdd, tau, tau_e=None, subject="S0"):
    T, n = q.shape
    return SimpleNamespace(subject=subject, task="bench", name=name, side="", mass=1.0, dt=dt,
                           joints=tuple(joints), joint_types=tuple(jtypes), q=q, qd=qd, qdd=qdd, tau=tau,
                           tau_e=np.zeros((T, n)) if tau_e is None else tau_e, f_v=np.zeros(T),
                           cop=np.full((T, 2), np.nan), valid=np.ones(T, bool))


def two_link(n_trials=4, seconds=20.0, dt=0.005, seed=0, damping=None, coulomb=None, noise=0.05):
    """Trials of a 2-link arm; damping / coulomb: (joint index, value) planted on the limb."""
    rng = np.random.default_rng(seed)
    T = int(seconds / dt)
    trials = []
    for i in range(n_trials):
        q, qd, qdd = _kinematics(rng, T, dt, 2, amp=(1.2, 1.0))
        q[:, 1] += 0.6
        tau = _two_link_id(q, qd, qdd)
        if damping is not None:
            j, b = damping
            tau[:, j] += b * qd[:, j]
        if coulomb is not None:
            j, fc = coulomb
            tau[:, j] += fc * np.tanh(qd[:, j] / 0.01)
        tau = tau + noise * rng.standard_normal(tau.shape)
        trials.append(_trial(f"arm_{i}", dt, ("shoulder", "elbow"), ("revolute", "revolute"), q, qd, qdd, tau))
    effects = []
    if damping is not None:
        effects.append({"effect": "viscous_damping", "joint": ("shoulder", "elbow")[damping[0]], "value": damping[1]})
    if coulomb is not None:
        effects.append({"effect": "coulomb_friction", "joint": ("shoulder", "elbow")[coulomb[0]], "value": coulomb[1]})
    return trials, effects


def linear_drive(n_trials=3, seconds=20.0, dt=0.005, seed=0, mass=3.0, incline=0.3, viscous=None, coulomb=None,
                 noise=0.2):
    """A carriage on an inclined rail (prismatic joint x, metres, force in N); viscous: N s/m; coulomb: N."""
    rng = np.random.default_rng(seed)
    T = int(seconds / dt)
    trials = []
    for i in range(n_trials):
        q, qd, qdd = _kinematics(rng, T, dt, 1, amp=(0.15,), freqs=(0.5, 3.0))
        tau = mass * qdd + mass * G * np.sin(incline)
        if viscous is not None:
            tau = tau + viscous * qd
        if coulomb is not None:
            tau = tau + coulomb * np.tanh(qd / 0.01)
        tau = tau + noise * rng.standard_normal(tau.shape)
        trials.append(_trial(f"drive_{i}", dt, ("x",), ("prismatic",), q, qd, qdd, tau))
    effects = [{"effect": "viscous_damping", "joint": "x", "value": viscous}] if viscous is not None else []
    if coulomb is not None:
        effects.append({"effect": "coulomb_friction", "joint": "x", "value": coulomb})
    return trials, effects
