"""Physics first's terms taken out of the learned path's data (`diagnose.compensate`), and put back into its models."""
from types import SimpleNamespace

import numpy as np
import torch

from exolan.diagnose import compensate
from exolan.diagnose.base import make_base
from exolan.diagnose.fit import predict
from exolan.diagnose.flat import prepare
from exolan.extensions import ExtendedModel


def _leg(rng, subject: str, k_knee: float = np.inf):
    """Two joints under an exo torque; the knee's encoder on the exo's side of a strap of stiffness k_knee."""
    dt, T = 0.005, 3000
    t = np.arange(T) * dt
    wave = lambda: sum(rng.uniform(0.1, 0.3) * np.sin(2 * np.pi * rng.uniform(0.3, 1.5) * t + rng.uniform(0, 6))
                       for _ in range(3))
    q = np.stack([wave(), wave() + 0.6], 1)
    te = np.stack([1.5 * np.sin(2 * np.pi * 0.7 * t), 2.0 * np.sin(q[:, 1]) + wave()], 1)
    tau = 3.0 * np.sin(q) + 0.05 * rng.standard_normal((T, 2))
    qm = q.copy()
    qm[:, 1] += te[:, 1] / k_knee
    qd = np.gradient(qm, dt, axis=0)
    return SimpleNamespace(subject=subject, task="bench", name=f"{subject}-p", side="", mass=70.0, dt=dt,
                           joints=("hip", "knee"), joint_types=("revolute", "revolute"), q=qm, qd=qd,
                           qdd=np.gradient(qd, dt, axis=0), tau=tau, tau_e=te, f_v=np.zeros(T),
                           cop=np.full((T, 2), np.nan), valid=np.ones(T, bool)), q


def test_a_model_fitted_on_compensated_data_predicts_the_recorded_data_with_the_terms_put_back():
    """`on_raw(M)`'s residual on the recorded rows equals M's on the compensated rows: the knee's strap, damping,
    gain and delay removed from the data by `data` and restored by `on_raw` are the same physics, beside M's own
    hip term and with a per-subject size on one of them."""
    rng = np.random.default_rng(3)
    flat = prepare([_leg(rng, "A")[0], _leg(rng, "B")[0]])
    terms = [("strap_compliance", 1), ("viscous_damping", 1), ("torque_gain", 1), ("actuation_delay", 1)]
    subj = np.array([0, 1])
    init = {"strap_compliance": {1: 150.0}, "viscous_damping": {1: 0.8}, "torque_gain": {1: 1.2},
            "actuation_delay": {1: 0.03}, "sized": {"viscous_damping": {1: np.array([0.3, -0.3])}},
            "subject_of_trial": subj}
    comp = compensate.data(flat, terms, init, max_delay=0.1)
    assert not torch.equal(comp.q[:, 1], flat.q[:, 1]) and torch.equal(comp.q[:, 0], flat.q[:, 0])
    base = make_base(comp, hidden=16, z_dim=2, seed=0)
    own = ExtendedModel(base, 2, [("coulomb_friction", 0)], dt=flat.dt, init={"coulomb_friction": {0: 0.7}},
                        coupled_damping=False)
    rows = flat.index("all")
    for model in (base, own):
        back = compensate.on_raw(model, flat, terms, init, max_delay=0.1)
        on_comp, on_raw = predict(model, comp, rows) - comp.tau[rows], predict(back, flat, rows) - flat.tau[rows]
        assert torch.allclose(on_raw, on_comp, atol=1e-5 * float(flat.tau.abs().max())), \
            float((on_raw - on_comp).abs().max())
        if model is own:
            assert abs(back.estimate("coulomb_friction", 0) - 0.7) < 1e-6


def test_a_knee_strap_of_known_stiffness_is_taken_out_of_the_measured_angle():
    """The compensated knee angle is the true one (the strap's deflection τ_e/k removed), the hip's untouched."""
    rng = np.random.default_rng(5)
    k = 90.0
    tr, q_true = _leg(rng, "A", k_knee=k)
    flat = prepare([tr])
    comp = compensate.data(flat, [("strap_compliance", 1)], {"strap_compliance": {1: k}}, max_delay=0.1)
    err_raw = float((flat.q[:, 1].double() - torch.as_tensor(q_true[:, 1])).abs().max())
    err_comp = float((comp.q[:, 1].double() - torch.as_tensor(q_true[:, 1])).abs().max())
    assert err_raw > 0.02 and err_comp < 1e-5, (err_raw, err_comp)
    assert torch.equal(comp.q[:, 0], flat.q[:, 0])
