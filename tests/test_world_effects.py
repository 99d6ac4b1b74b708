"""Planted effects survive the sensor pipeline: with the world's own (otherwise unobserved) physics
-- pelvis motion, full GRF -- an oracle recovers each planted parameter from the *recorded* files
(noisy angles, filtered velocities, Savitzky-Golay accelerations, noisy moments) within 10 %.
This is the ceiling for diagnosis: if an oracle could not see an effect, no model could."""
from __future__ import annotations

import numpy as np
import pytest

from exolan.data import load, savgol_derivative
from exolan.world import make_users, simulate, simulate_trial
from exolan.world import dynamics as dyn
from exolan.world.generate import VEL_CUTOFF_HZ, _lowpass

SEED, USERS, SECONDS, TASKS = 3, 2, 8.0, ("walk", "cut", "squat")


def _world(tmp_path, effect):
    simulate(tmp_path, users=USERS, tasks=list(TASKS), seconds=SECONDS, seed=SEED, effects=[effect],
             progress=False)
    ds = load(tmp_path, cache=False)
    users = make_users(USERS, np.random.default_rng(np.random.SeedSequence([SEED, 0])))
    rows = []
    for tr in ds:
        u = users[int(tr.subject[1:]) - 1]
        truth = simulate_trial(u, tr.task, SECONDS, seed=SEED, noise=False, effects=[effect])[2]
        rows.append((tr, truth, "lr".index(tr.side)))
    return rows


def _residual(tr, truth, s, q=None, qd=None, qdd=None):
    """Recorded total torque minus the true rigid-body + contact torque at the given kinematics."""
    q, qd, qdd = (np.array(x if x is not None else d) for x, d in ((q, tr.q), (qd, tr.qd), (qdd, tr.qdd)))
    q[:, 0] -= truth["tilt"]
    qd[:, 0] -= truth["tilt_d"]
    qdd[:, 0] -= truth["tilt_dd"]
    tau = dyn.inverse_dynamics(truth["world"].p, q, qd, qdd, truth["g_eff"], truth["f"][:, s], truth["point"][:, s])
    return tr.tau - tau


def _scan(rows, grid, residual_of):
    cost = []
    for v in grid:
        e = np.concatenate([residual_of(tr, truth, s, v)[tr.valid][15:-15] for tr, truth, s in rows])
        cost.append(np.mean(e ** 2))
    i = int(np.argmin(cost))
    print(dict(zip(np.round(grid, 4), np.round(cost, 3))))
    assert 0 < i < len(grid) - 1, "minimum at the edge of the scan"
    return grid[i]


def test_oracle_recovers_knee_damping(tmp_path):
    rows = _world(tmp_path, "viscous_damping:knee:1.5")
    R = np.concatenate([_residual(*r)[r[0].valid] for r in rows])
    V = np.concatenate([r[0].qd[r[0].valid] for r in rows])
    b = V[:, 1] @ R[:, 1] / (V[:, 1] @ V[:, 1])
    b_hip = V[:, 0] @ R[:, 0] / (V[:, 0] @ V[:, 0])
    assert b == pytest.approx(1.5, rel=0.1)
    assert abs(b_hip) < 0.15


def test_oracle_recovers_hip_coulomb(tmp_path):
    rows = _world(tmp_path, "coulomb_friction:hip:2.0")
    R = np.concatenate([_residual(*r)[r[0].valid] for r in rows])
    F = np.tanh(np.concatenate([r[0].qd[r[0].valid] for r in rows]) / 0.01)
    assert F[:, 0] @ R[:, 0] / (F[:, 0] @ F[:, 0]) == pytest.approx(2.0, rel=0.1)
    assert abs(F[:, 1] @ R[:, 1] / (F[:, 1] @ F[:, 1])) < 0.2


def test_oracle_recovers_actuation_delay(tmp_path):
    rows = _world(tmp_path, "actuation_delay:both:0.025")

    def res(tr, truth, s, d):
        t = np.arange(len(tr.q)) * tr.dt
        late = np.stack([np.interp(t - d, t, tr.tau_e[:, j]) for j in range(2)], 1)
        return _residual(tr, truth, s) - (tr.tau_e - late)

    d = _scan(rows, np.arange(0.0, 0.0525, 0.0025), res)
    assert d == pytest.approx(0.025, rel=0.1)


def test_oracle_recovers_encoder_offset(tmp_path):
    rows = _world(tmp_path, "encoder_offset:knee:0.05")

    def res(tr, truth, s, delta):
        q = tr.q.copy()
        q[:, 1] -= delta
        return _residual(tr, truth, s, q=q)

    assert _scan(rows, np.arange(-0.02, 0.1, 0.0025), res) == pytest.approx(0.05, rel=0.1)


def test_oracle_recovers_strap_compliance(tmp_path):
    rows = _world(tmp_path, "strap_compliance:hip:150")

    def res(tr, truth, s, k):
        # the strap's share of the measured velocity went through the same sensor filter
        ted = _lowpass(np.gradient(tr.tau_e, tr.dt, axis=0), VEL_CUTOFF_HZ)
        q, qd = tr.q.copy(), tr.qd.copy()
        q[:, 0] -= tr.tau_e[:, 0] / k
        qd[:, 0] -= ted[:, 0] / k
        qdd = savgol_derivative(qd, tr.dt)
        return _residual(tr, truth, s, q=q, qd=qd, qdd=qdd)

    k = _scan(rows, np.arange(100.0, 205.0, 5.0), res)
    assert k == pytest.approx(150, rel=0.1)
