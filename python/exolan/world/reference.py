"""The world's own leg as a forward-dynamics reference for the learned models.

A learned model's open-loop rollout error means little without what the data allow. The simulated world knows
its true leg and every input, so its rigid-body model is rolled out exactly as a learned model is (from the
recorded state, semi-implicit Euler, compared with the recorded state) under three sets of inputs:

* ``recorded``: only what a learned model is fed: the recorded torque τ and the vertical insole force f_v at the
  recorded centre of pressure, plain gravity, the recorded (pelvis-relative) hip angle. It misses the pelvis'
  tilt and acceleration and the horizontal ground force, which a learned model's context can partly absorb;
* ``true inputs, recorded τ``: the true pelvis motion and ground force, but the recorded τ (what the models
  get: the filtered moments plus the exoskeleton's measured torque);
* ``true inputs``: everything true, the torque too: only sensor noise on the start and target states and the
  integrator remain, the floor of any model.
"""
from __future__ import annotations

import functools

import numpy as np

from . import dynamics as dyn
from .anthropometry import LegParams, leg_params, make_users

MODES = ("recorded", "true inputs, recorded τ", "true inputs")


def true_legs(users: int, seed: int) -> dict[str, LegParams]:
    """Each simulated user's leg (exoskeleton segments included), as `simulate(users=…, seed=…)` drew it."""
    from . import _rng

    return {u.name: leg_params(u, exo=True, seg_scale=u.style["seg_scale"]) for u in make_users(users, _rng(seed, 0))}


def recorded_forward(p: LegParams, q, qd, tau, f_v, cop_x) -> np.ndarray:
    """q̈ of the true leg (plain gravity, hip fixed) under the recorded τ and the vertical insole force f_v at the
    recorded centre of pressure; rows (N, 2)."""
    f = np.stack([np.zeros_like(f_v), f_v], axis=-1)
    loaded = f_v > 0
    cop = np.where(loaded, np.nan_to_num(cop_x), 0.0)
    tau_c = np.where(loaded[:, None], dyn.contact_torque(p, q, dyn.cop_point(p, q, cop), f), 0.0)
    return dyn.forward_dynamics(p, q, qd, tau + tau_c)


@functools.lru_cache(maxsize=None)
def _truth(users: int, seed: int, seconds: float | None, subject: str, task: str) -> dict:
    """Both legs' truth of one trial, re-simulated once (for either side and every reference mode)."""
    from . import _rng, simulate_trial

    people = make_users(users, _rng(seed, 0))
    si = [u.name for u in people].index(subject)
    return simulate_trial(people[si], task, seconds, seed, (), True, subject_index=si)[2]


class TrueTrial:
    """One recorded trial's true inputs, re-simulated with the seeds that made it (same arrays as recorded)."""

    def __init__(self, users: int, seed: int, seconds: float | None, subject: str, task: str, side: str):
        truth = _truth(users, seed, seconds, subject, task)
        s = 0 if side == "l" else 1
        self.p = truth["world"].p
        self.tilt, self.tilt_d, self.tilt_dd = truth["tilt"], truth["tilt_d"], truth["tilt_dd"]
        self.g_eff = truth["g_eff"]
        self.tau = truth["tau_tot"][:, s]
        self.tau_c = dyn.contact_torque(self.p, truth["q_abs"][:, s], truth["point"][:, s], truth["f"][:, s])

    def forward(self, q, qd, tau, t, true_tau: bool) -> np.ndarray:
        """q̈ (pelvis-relative, as recorded) at rows (N, 2) and sample indices t (N,): the dynamics act on the
        thigh's absolute angle q_hip − tilt, with the true pelvis acceleration and ground force."""
        off = np.stack([self.tilt[t], np.zeros(len(t))], axis=-1)
        off_d = np.stack([self.tilt_d[t], np.zeros(len(t))], axis=-1)
        torque = self.tau[t] if true_tau else tau
        qdd_abs = dyn.forward_dynamics(self.p, q - off, qd - off_d, torque + self.tau_c[t], self.g_eff[t])
        return qdd_abs + np.stack([self.tilt_dd[t], np.zeros(len(t))], axis=-1)
