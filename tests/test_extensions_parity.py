"""Rust parity of the extended model: the diagnosis' `ExtendedModel` exported through `exolan.export`
(base folded at a fixed context z, `ext.*` tensors) and run by the engine agrees with torch in float64."""
import math

import numpy as np
import pytest
import torch

from exolan.diagnose.base import SlowContextDeLaN
from exolan.diagnose.export import export_extended
from exolan.extensions import ExtendedModel, lag_table

engine = pytest.importorskip("exolan.engine")

ALL = {"viscous_damping": 0.5, "coulomb_friction": 1.0, "stribeck_friction": 0.7, "encoder_offset": 0.02,
       "torque_bias": 0.3, "torque_gain": 1.2, "strap_compliance": 150.0, "actuation_delay": 0.0137}


def _extended(effects, seed=0):
    torch.manual_seed(seed)
    b = SlowContextDeLaN(("revolute", "revolute"), 3, z_dim=4, hidden=16, lim=True, v_scale=5.0).double()
    with torch.no_grad():
        b.codes.weight.normal_()
    ext = ExtendedModel(b, 2, effects, dt=0.005, max_delay=0.05, init=ALL).double()
    with torch.no_grad():
        ext.damping_off.fill_(0.3)
    return b, ext


def test_extended_inverse_and_forward_dynamics_match_the_engine(tmp_path):
    effects = [("viscous_damping", 0), ("viscous_damping", 1), ("coulomb_friction", 1), ("stribeck_friction", 0),
               ("encoder_offset", 0), ("torque_bias", 1), ("torque_gain", 0), ("strap_compliance", 1)]
    b, ext = _extended(effects)
    z = b.codes.weight[1].detach()
    path, twin = export_extended(ext, tmp_path / "ext.safetensors", z, joint_names=("hip", "knee"))
    eng = engine.Engine(str(path))
    assert set(eng.extensions) == {"ext.damping", "ext.coulomb", "ext.stribeck_fs", "ext.stribeck_vs",
                                   "ext.encoder_offset", "ext.torque_bias", "ext.torque_gain", "ext.strap_compliance"}
    B = 64
    g = torch.Generator().manual_seed(1)
    q, qd, qdd, te, ted, tedd = (torch.randn(B, 2, generator=g, dtype=torch.float64) for _ in range(6))
    fv = 300 * torch.rand(B, generator=g, dtype=torch.float64)
    with torch.no_grad():
        t_torch = ext.inverse(q, qd, qdd, z.expand(B, 4), fv, te, ted, tedd).numpy()
    n = lambda x: x.numpy()
    t_eng = eng.inverse_dynamics(n(q), n(qd), n(qdd), f_v=n(fv), tau_e=n(te), tau_app=n(te), tau_app_d=n(ted),
                                 tau_app_dd=n(tedd))
    assert np.abs(t_eng - t_torch).max() <= 1e-9 * np.abs(t_torch).max()
    tau = 10 * torch.randn(B, 2, generator=g, dtype=torch.float64)
    with torch.no_grad():
        a_torch = ext.forward_dynamics(q, qd, tau, z.expand(B, 4), fv, te).numpy()
    a_eng = eng.forward_dynamics(n(q), n(qd), n(tau), f_v=n(fv), tau_e=n(te), tau_app=n(te))
    assert np.abs(a_eng - a_torch).max() <= 1e-9 * np.abs(a_torch).max()


def test_actuation_delay_matches_the_engine(tmp_path):
    b, ext = _extended([("actuation_delay", 0), ("actuation_delay", 1)])
    z = b.codes.weight[0].detach()
    path, _ = export_extended(ext, tmp_path / "d.safetensors", z)
    eng = engine.Engine(str(path))
    T = 300
    t = np.arange(T) * 0.005
    tau_e = np.stack([np.sin(9 * t), 3 * np.cos(4 * t) + t], 1)
    hist = torch.as_tensor(tau_e)[torch.as_tensor(lag_table([T], 11))]
    with torch.no_grad():
        app_torch, _, _ = ext.applied_exo(hist)
    app_eng = eng.applied_exo(tau_e)
    assert np.abs(app_eng - app_torch.numpy()).max() <= 1e-12 * np.abs(tau_e).max()
    # and the inverse dynamics with that applied torque
    rng = np.random.default_rng(2)
    q, qd, qdd = (rng.standard_normal((T, 2)) for _ in range(3))
    fv = np.zeros(T)
    with torch.no_grad():
        t_torch = ext.inverse(*(torch.as_tensor(x) for x in (q, qd, qdd)), z.expand(T, 4), torch.as_tensor(fv),
                              hist).numpy()
    t_eng = eng.inverse_dynamics(q, qd, qdd, f_v=fv, tau_e=tau_e, tau_app=app_eng)
    assert np.abs(t_eng - t_torch).max() <= 1e-9 * np.abs(t_torch).max()


def test_a_lim_that_sees_the_centre_of_pressure_exports_at_its_training_mean(tmp_path):
    """The diagnosis base's B(q, x_cop, z): the lever arms move with the CoP; the engine (one insole input) gets the
    LIM held at the stored mean CoP, and agrees with torch there."""
    from exolan.diagnose.base import COP_UNIT
    from exolan.diagnose.flat import SURGE_FEATURES

    torch.manual_seed(3)
    b = SlowContextDeLaN(("revolute", "revolute"), 3, z_dim=4, hidden=16, lim=True, v_scale=5.0, lim_other=True,
                         lim_cop=True).double()
    assert b.lim_cop and b.lim[0].in_features == b.lim.features.dim + 5
    with torch.no_grad():
        b.codes.weight.normal_()
        b.cop_ref.fill_(1.3)
    ext = ExtendedModel(b, 2, [("viscous_damping", 1)], dt=0.005, init=ALL).double()
    z = b.codes.weight[2].detach()
    path, _ = export_extended(ext, tmp_path / "c.safetensors", z)
    eng = engine.Engine(str(path))
    B = 32
    g = torch.Generator().manual_seed(4)
    q, qd, qdd = (torch.randn(B, 2, generator=g, dtype=torch.float64) for _ in range(3))
    fv = 300 * torch.rand(B, generator=g, dtype=torch.float64)

    def forces(x_cop):
        f = torch.zeros(B, 6 + SURGE_FEATURES, dtype=torch.float64)
        f[:, 0], f[:, -1] = fv, x_cop
        return f
    with torch.no_grad():
        at_mean = ext.inverse(q, qd, qdd, z.expand(B, 4), forces(1.3 * COP_UNIT)).numpy()
        heel = ext.inverse(q, qd, qdd, z.expand(B, 4), forces(0.02)).numpy()
    assert np.abs(heel - at_mean).max() > 1e-3 * np.abs(at_mean).max()       # the CoP moves the lever arms
    t_eng = eng.inverse_dynamics(q.numpy(), qd.numpy(), qdd.numpy(), f_v=fv.numpy())
    assert np.abs(t_eng - at_mean).max() <= 1e-9 * np.abs(at_mean).max()
    assert "centre-of-pressure input is held at its training mean (0.130 m)" in eng.metadata["omitted"]


def test_a_users_export_holds_that_users_subject_specific_terms_and_matches_torch(tmp_path):
    """The engine has no gates: a user's file (`export_extended(..., trial=)`) holds the terms that act on that
    user's trials and agrees with the gated torch model there; a user without the gated term gets none."""
    effects = [("viscous_damping", 1), ("coulomb_friction", 0)]
    torch.manual_seed(0)
    b = SlowContextDeLaN(("revolute", "revolute"), 3, z_dim=4, hidden=16, lim=True, v_scale=5.0).double()
    ext = ExtendedModel(b, 2, effects, dt=0.005, max_delay=0.05,
                        init=dict(ALL, gates={"viscous_damping": {1: [1.0, 0.0, 1.0]}})).double()
    B = 32
    g = torch.Generator().manual_seed(2)
    q, qd, qdd = (torch.randn(B, 2, generator=g, dtype=torch.float64) for _ in range(3))
    fv = 300 * torch.rand(B, generator=g, dtype=torch.float64)
    for trial, has_damping in ((0, True), (1, False)):
        z = b.codes.weight[trial].detach()
        path, _ = export_extended(ext, tmp_path / f"t{trial}.safetensors", z, trial=trial)
        eng = engine.Engine(str(path))
        assert ("ext.damping" in eng.extensions) == has_damping and "ext.coulomb" in eng.extensions
        with torch.no_grad():
            t_torch = ext.inverse(q, qd, qdd, z.expand(B, 4), fv, trial=torch.full((B,), trial)).numpy()
        t_eng = eng.inverse_dynamics(q.numpy(), qd.numpy(), qdd.numpy(), f_v=fv.numpy())
        assert np.abs(t_eng - t_torch).max() <= 1e-9 * np.abs(t_torch).max()


def test_a_users_export_holds_that_users_own_size_of_a_sized_term(tmp_path):
    """A term with per-subject sizes is written at each user's own value and agrees with the torch model on
    that user's trials."""
    effects = [("viscous_damping", 1), ("coulomb_friction", 0)]
    torch.manual_seed(1)
    b = SlowContextDeLaN(("revolute", "revolute"), 3, z_dim=4, hidden=16, lim=True, v_scale=5.0).double()
    ext = ExtendedModel(b, 2, effects, dt=0.005, max_delay=0.05,
                        init=dict(ALL, sized={"viscous_damping": {1: [0.4, -0.4]}, "coulomb_friction": {0: [0.2, 0.0]}},
                                  subject_of_trial=[0, 1, 1])).double()
    B = 32
    g = torch.Generator().manual_seed(4)
    q, qd, qdd = (torch.randn(B, 2, generator=g, dtype=torch.float64) for _ in range(3))
    fv = 300 * torch.rand(B, generator=g, dtype=torch.float64)
    damping = []
    for trial in (0, 2):
        z = b.codes.weight[trial].detach()
        path, twin = export_extended(ext, tmp_path / f"s{trial}.safetensors", z, trial=trial)
        eng = engine.Engine(str(path))
        with torch.no_grad():
            t_torch = ext.inverse(q, qd, qdd, z.expand(B, 4), fv, trial=torch.full((B,), trial)).numpy()
        t_eng = eng.inverse_dynamics(q.numpy(), qd.numpy(), qdd.numpy(), f_v=fv.numpy())
        assert np.abs(t_eng - t_torch).max() <= 1e-9 * np.abs(t_torch).max()
        damping.append(twin.estimate("viscous_damping", 1))
    assert damping[0] / damping[1] == pytest.approx(math.exp(0.8), rel=1e-9)
