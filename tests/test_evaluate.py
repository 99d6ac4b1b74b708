"""Evaluation figures against direct computations, rollouts against the semi-implicit Euler definition,
and the physics checks (positive definite H, energy of the free conservative model)."""
import numpy as np
import pytest
import torch

from exolan.data import context_features, load, paper_split
from exolan.evaluate import evaluate, physics_check, predict_torque
from exolan.models import build_model
from exolan.rollout import free_rollout, rollout
from exolan.train import compute_stats, data_scales


@pytest.fixture(scope="module")
def held_out(small_world):
    sp = paper_split(load(small_world))
    return list(sp.test_seen)[:3] + list(sp.test_unseen)[:2]


def _model(trials, method="exolan", seed=0):
    torch.manual_seed(seed)
    stats = compute_stats(trials)
    m = build_model(method, lim=True, joint_types=trials[0].joint_types, joint_names=trials[0].joints,
                    context_channels=[f"c{i}" for i in range(7)], **data_scales(stats))
    if m.norm is not None:
        m.norm.set_stats(stats["ctx_mean"], stats["ctx_std"])
    return m.double().eval()


def test_torque_figures_equal_direct_computation(held_out):
    m = _model(held_out)
    res = evaluate(m, held_out, stride=7)
    sq, per_task = [], {}
    for t in held_out:
        with torch.no_grad():
            x = torch.as_tensor(context_features(t)).unsqueeze(0)
            z = m.context(x)[0]
            f = lambda a: torch.as_tensor(np.nan_to_num(a))
            tau = m.inverse(f(t.q), f(t.qd), f(t.qdd), z, f(t.f_v)).numpy()
        e = (tau[t.valid] - t.tau[t.valid]) ** 2
        sq.append(e)
        per_task.setdefault(t.task, []).append(e)
        np.testing.assert_allclose(predict_torque(m, t)[t.valid], tau[t.valid], rtol=1e-12)
    sq = np.concatenate(sq)
    assert res["torque"]["mse"] == pytest.approx(sq.mean(), rel=1e-10)
    assert res["torque"]["per_joint"]["knee"] == pytest.approx(sq[:, 1].mean(), rel=1e-10)
    for task, es in per_task.items():
        assert res["torque"]["per_task"][task]["mse"] == pytest.approx(np.concatenate(es).mean(), rel=1e-10)
    fw = res["forward"]
    assert set(fw["q"]) == {"4", "10", "20"} and fw["qdd"]["n"] == sq.shape[0]
    # open-loop errors grow with the horizon
    assert fw["q"]["4"]["mse"] < fw["q"]["10"]["mse"] < fw["q"]["20"]["mse"]


def test_black_box_has_no_forward_figures(held_out):
    res = evaluate(_model(held_out, "mlp-tcn"), held_out[:2])
    assert "forward" not in res and res["torque"]["mse"] > 0


def test_rollout_is_semi_implicit_euler(held_out):
    m = _model(held_out)
    torch.manual_seed(1)
    d = dict(dtype=torch.float64)
    q0, qd0 = torch.randn(3, 2, **d), torch.randn(3, 2, **d)
    tau, z, f_v = torch.randn(3, 5, 2, **d) * 10, torch.rand(3, 5, 16, **d), torch.rand(3, 5, **d) * 500
    with torch.no_grad():
        Q, QD = rollout(m, q0, qd0, tau, 0.005, z, f_v)
        q, qd = q0, qd0
        for k in range(5):
            qdd = m.forward_dynamics(q, qd, tau[:, k], z[:, k], f_v[:, k])
            qd = qd + 0.005 * qdd            # velocity first ...
            q = q + 0.005 * qd               # ... then position with the new velocity
            torch.testing.assert_close(Q[:, k + 1], q, rtol=0, atol=0)
            torch.testing.assert_close(QD[:, k + 1], qd, rtol=0, atol=0)


def test_physics_check_positive_definite_and_energy_conserved(held_out):
    m = _model(held_out, "delan")
    pc = physics_check(m, held_out, n_rollouts=8, seconds=0.5)
    assert pc["positive_definite"] and pc["min_eigenvalue"] >= m.delan.softplus_offset ** 2 * 0.999
    assert 1.0 <= pc["cond_min"] <= pc["cond_median"] <= pc["cond_max"]
    e, e4 = pc["energy"]["dt"], pc["energy"]["dt/4"]
    assert e["finite"] and e4["finite"]
    assert e["median_rel_drift"] < 0.1
    # first-order integrator: the drift shrinks with the step (about 4x for dt/4)
    assert e4["max_abs_drift_J"] < 0.5 * e["max_abs_drift_J"]


def test_free_rollout_of_a_known_pendulum_keeps_energy():
    """A DeLaN set by hand to a pendulum (H = const, V = −m g l cos q): the free rollout's energy stays
    within the first-order band of semi-implicit Euler and the swing keeps its amplitude."""
    m = build_model("delan", lim=False, joint_types=("revolute",), hidden=4, softplus_offset=0.0, v_scale=1.0).double()
    with torch.no_grad():
        for p in m.parameters():
            p.zero_()
        # L: softplus(u) = 1 → u = log(e − 1); the last layer's bias alone sets it
        m.delan.L[2].bias.fill_(float(np.log(np.e - 1.0)))
        # V = −cos q: the input φ = [cos q, sin q]; a first-layer unit a = 0.01 cos q stays in tanh's linear
        # range, so V ≈ −cos q up to a cubic correction
        m.delan.V[0].weight[0, 0] = 0.01
        m.delan.V[1].weight[0, 0] = 1.0
        m.delan.V[2].weight[0, 0] = -100.0
    q0, qd0 = torch.tensor([[1.0]], dtype=torch.float64), torch.tensor([[0.0]], dtype=torch.float64)
    with torch.no_grad():
        Q, QD, T, V = free_rollout(m, q0, qd0, 0.005, 2000)
    E = (T + V)[0]
    assert float((E - E[0]).abs().max()) < 0.02 * float(T.max())
    assert float(Q.abs().max()) == pytest.approx(1.0, abs=0.02)
