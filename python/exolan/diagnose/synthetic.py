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


def _plateau_reference(dt: float, levels=(0.1, 0.2, 0.4), accel: float = 2.0, travel: float = 0.2,
                       pause: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """One cycle of a position reference with velocity plateaus: out and back at each speed level, a
    trapezoidal velocity profile (acceleration `accel`), a pause at each end. Returns (x_ref, v_ref)."""
    v = []
    for lv in levels:
        for sgn in (1.0, -1.0):
            ramp = np.arange(0.0, lv, accel * dt)
            flat_t = max(travel / lv - lv / accel, 0.0)
            prof = np.concatenate([ramp, np.full(int(flat_t / dt), lv), ramp[::-1]])
            v.extend(list(sgn * prof) + [0.0] * int(pause / dt))
    v = np.asarray(v)
    return np.cumsum(v) * dt, v


def servo_drive(seconds: float = 25.0, dt: float = 0.001, seed: int = 0, mass: float = 95.0, viscous: float = 0.0,
                coulomb: float = 0.0, offset: float = 0.0, current_noise: float = 3.0, force_noise: float = 1.0,
                encoder_step: float = 1e-6, v_stick: float = 1e-3, substeps: int = 10):
    """An electromechanical linear drive on a horizontal rail, closed loop: a PD position loop (10 Hz, with
    velocity feedforward) tracks a repeated reference with velocity plateaus (`_plateau_reference`); the force the
    current loop applies is the command plus coloured noise (AR(1), std `current_noise` N); the recorded force is
    the applied one plus white noise (`force_noise` N); the encoder quantises x to `encoder_step` m.

    Plant: m ẍ = F − b ẋ − Fc tanh(ẋ/v_stick) − offset (Euler with `substeps` substeps per sample).
    Returns (time, x, F_recorded, truth dict)."""
    rng = np.random.default_rng(seed)
    x_ref, v_ref = _plateau_reference(dt)
    T = int(round(seconds / dt))
    reps = int(np.ceil(T / len(x_ref)))
    x_ref = np.concatenate([x_ref + 0.0 * k for k in range(reps)])[:T]
    v_ref = np.tile(v_ref, reps)[:T]
    w = 2 * np.pi * 10.0
    kp, kd = mass * w * w, 2 * 0.7 * mass * w
    phi = 0.95
    n_cl = np.zeros(T)
    e = rng.standard_normal(T) * current_noise * np.sqrt(1 - phi ** 2)
    for t in range(1, T):
        n_cl[t] = phi * n_cl[t - 1] + e[t]
    x = np.zeros(T); F = np.zeros(T)
    xs, vs = 0.0, 0.0
    h = dt / substeps
    for t in range(T):
        xm = np.round(xs / encoder_step) * encoder_step
        vm = (xm - x[t - 1]) / dt if t else 0.0
        x[t] = xm
        F[t] = kp * (x_ref[t] - xm) + kd * (v_ref[t] - vm) + n_cl[t]
        for _ in range(substeps):
            a = (F[t] - viscous * vs - coulomb * np.tanh(vs / v_stick) - offset) / mass
            vs += a * h
            xs += vs * h
    F_rec = F + force_noise * rng.standard_normal(T)
    truth = dict(mass=mass, viscous=viscous, coulomb=coulomb, offset=offset)
    return np.arange(T) * dt, x, F_rec, truth


def servo_trial(name: str, subject: str = "S", seconds: float = 25.0, seed: int = 0, **truth):
    """One `servo_drive` recording as a duck-typed trial (layout 2: force in N, x in m, q̇ by differences)."""
    t, x, F, _ = servo_drive(seconds=seconds, seed=seed, **truth)
    dt = float(t[1] - t[0])
    return _trial(name, dt, ("x",), ("prismatic",), x[:, None], np.gradient(x, dt)[:, None],
                  np.zeros((len(x), 1)), F[:, None], subject=subject)


def write_layout2(path, time: np.ndarray, q: np.ndarray, tau: np.ndarray, joint: str = "x",
                  joint_type: str = "prismatic") -> None:
    """A 1-DoF layout-2 recording (DATA_LAYOUT.md): <path>.csv (time, q_<joint>, tau_<joint>) and <path>.json."""
    import json
    from pathlib import Path
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path.with_suffix(".csv"), np.column_stack([time, q, tau]), delimiter=",", fmt="%.9g",
               header=f"time,q_{joint},tau_{joint}", comments="")
    units = {"q": "m", "tau": "N"} if joint_type == "prismatic" else {"q": "rad", "tau": "N m"}
    path.with_suffix(".json").write_text(json.dumps({"joints": [{"name": joint, "type": joint_type}], "units": units}))
