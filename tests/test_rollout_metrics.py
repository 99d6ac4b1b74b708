"""Forward-dynamics metrics of the study (`reproduce.rollout_metrics`, `_fd_metrics`, `report.fd_stats`): exact
models, integrated vs compounding errors, and where an error shows (per task and joint)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from exolan import reproduce as R
from standin import FakeModel, StandInBackend, fake_world

def test_forward_dynamics_metrics_on_a_model_that_is_exact():
    """A model whose inverse dynamics produced the torques recovers q̈ exactly; its open-loop rollouts
    then only carry the integrator's error, which grows with the horizon, and match a plain loop."""
    scale = R.SCALES["tiny"]
    tr = fake_world(users=1, tasks=("walk",), T=200)[0]
    m = FakeModel(3, 0)
    with torch.no_grad():
        m.W.copy_(torch.randn(m.W.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.1)
        m.a.copy_(torch.tensor([0.5, 0.3], dtype=torch.float64))
        z = m.context(torch.as_tensor(StandInBackend().context_features(tr))[None])[0]
        tau = m.inverse(*(torch.as_tensor(a) for a in (tr.q, tr.qd, tr.qdd)), z, torch.as_tensor(tr.f_v))
    tr = dataclasses.replace(tr, tau=tau.numpy())
    rows = R._fd_metrics(m, [("seen", tr, z)], torch.float64, scale)
    assert sum(rows[0]["sse_qdd"]) / rows[0]["n_qdd"] < 1e-20
    h = rows[0]["horizons"]
    mse = [sum(h[str(k)]["sse_q"]) / h[str(k)]["n"] for k in scale.horizons]
    assert 0 < mse[0] < mse[1] < mse[2] < 1e-3
    # the first start, integrated by hand
    s = int(np.flatnonzero(np.convolve(tr.valid.astype(int), np.ones(21, int), "valid") == 21)[0])
    q, qd = torch.as_tensor(tr.q[s]), torch.as_tensor(tr.qd[s])
    for k in range(4):
        qdd = m.forward_dynamics(q, qd, tau[s + k], z[s + k], torch.as_tensor(tr.f_v[s + k]))
        qd = qd + tr.dt * qdd
        q = q + tr.dt * qd
    assert h["4"]["n"] >= 1
    assert float(((q.numpy() - tr.q[s + 4]) ** 2).sum()) <= h["4"]["sse_q"][0] + h["4"]["sse_q"][1] + 1e-15


def test_rollout_amplification_separates_integrated_from_compounding_errors():
    """A persistent q̈ error is integrated as it is (A ≈ 1 at every horizon), one that flips sign every step
    mostly cancels (A ≪ 1), and one that feeds back through the rolled-out velocity compounds (A grows with
    the horizon): the number the report uses to say why a multi-step loss can or cannot help."""
    from exolan import report

    scale = R.SCALES["tiny"]
    tr = fake_world(users=1, tasks=("walk",), T=200)[0]
    T, dt, n = len(tr.q), tr.dt, tr.q.shape[1]
    qdd = np.tile([[0.7, -0.4]], (T, 1))               # constant acceleration: semi-implicit Euler is exact
    qd = np.cumsum(np.vstack([np.zeros((1, n)), dt * qdd[:-1]]), axis=0) + 0.2
    q = np.cumsum(np.vstack([np.zeros((1, n)), dt * qd[1:]]), axis=0)
    tr = dataclasses.replace(tr, q=q, qd=qd, qdd=qdd, valid=np.ones(T, bool))
    bias = np.array([3.0, -2.0])

    def amp(error):
        def forward(q_, qd_, tau, z, fv, cx, owner, t):
            return qdd[t] + error(qd_ - qd[t], t)
        rows = R.rollout_metrics(forward, [("seen", tr, None)], scale)
        st = report.fd_stats([{"fd_rows": rows, "torque_rows": []}], scale.horizons, rows[0]["dt"])
        return [st["mean_std"][f"amp{h}"][0] for h in scale.horizons]

    persistent = amp(lambda dqd, t: bias)
    assert np.allclose(persistent, 1.0, atol=1e-9)
    flipping = amp(lambda dqd, t: bias * np.where(t % 2 == 0, 1.0, -1.0)[:, None])
    assert max(flipping) < 0.1
    compounding = amp(lambda dqd, t: bias + 60.0 * dqd)
    assert 1.0 < compounding[0] < compounding[1] < compounding[2]
    assert compounding[2] > 3.0


def test_forward_dynamics_errors_are_located_per_task_and_joint():
    """A q̈ error planted on one task's knee shows on that task and joint only, and the report's table puts the
    multi-step loss' change where it happened: how a reader sees where the multi-step claim fails."""
    from exolan import report
    from exolan.report.markdown import _fd_where_table

    scale = R.SCALES["tiny"]
    def integrated(tr):                                # q, q̇ exactly what semi-implicit Euler makes of q̈
        qd = tr.qd[0] + np.vstack([np.zeros((1, 2)), np.cumsum(tr.dt * tr.qdd[:-1], axis=0)])
        q = tr.q[0] + np.vstack([np.zeros((1, 2)), np.cumsum(tr.dt * qd[1:], axis=0)])
        return dataclasses.replace(tr, q=q, qd=qd, valid=np.ones(len(tr.q), bool))

    walk, squat = (integrated(tr) for tr in fake_world(users=1, tasks=("walk", "squat"), T=200)[::2])
    items = [("seen", walk, None), ("unseen", squat, None)]

    def stats(knee_error):
        def forward(q, qd, tau, z, fv, cx, owner, t):
            out = np.where(owner[:, None] == 0, walk.qdd[t], squat.qdd[t])
            return out + np.where(owner == 1, knee_error, 0.0)[:, None] * np.array([0.0, 1.0])
        rows = R.rollout_metrics(forward, items, scale)
        return report.fd_stats([{"fd_rows": rows, "torque_rows": []}], scale.horizons, rows[0]["dt"])

    a, b = stats(2.0), stats(1.0)
    h = scale.horizons[-1]
    assert a["per_task"]["walk"]["split"] == "seen" and a["per_task"]["squat"]["split"] == "unseen"
    assert a["per_task"]["walk"][f"qd{h}"] < 1e-20
    hip, knee = a["per_task"]["squat"][f"qd{h}_joints"]
    assert hip < 1e-20 < knee
    assert a["per_task"]["squat"]["qdd"] == pytest.approx(2.0, rel=1e-9)          # (0 + 2²) / 2 joints
    assert a["per_joint"]["qdd"][0] < 1e-20 < a["per_joint"]["qdd"][1]
    assert np.mean(a["per_joint"][f"qd{h}"]) == pytest.approx(a["mean_std"][f"qd{h}"][0], rel=1e-9)
    table = "\n".join(_fd_where_table({"w_fd": a, "w_fd+w_ms": b}, h))
    squat_row = next(line for line in table.splitlines() if line.startswith("| squat |"))
    change = squat_row.split(" | ")[5]
    assert change.startswith("-75.0% (") and change.endswith(" / -75.0%)")   # half the error: a quarter of the MSE
    assert squat_row.endswith("| — | — |")                                   # no floor given
