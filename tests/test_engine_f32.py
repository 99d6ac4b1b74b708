"""The engine's float32 batched rollouts (`Engine.rollout(..., precision="f32")`, `fast_rollout`): agreement
with the float64 engine and with torch float32 over 20 steps, shapes, determinism, and clear errors; and the
float32 single-sample calls (`Engine.inverse_dynamics(..., precision="f32")` etc.)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from exolan import Engine, fast_rollout
from exolan.export import export
from exolan.models import build_model
from exolan.rollout import rollout as torch_rollout

CHANNELS = ["q_hip", "q_knee", "qd_hip", "qd_knee", "f_v", "cop_x", "cop_z"]
# measured on this model: 3.4e-7 against the float64 engine and against torch float32 (torch float32 itself
# is 3.1e-7 from the float64 engine)
RTOL = 1e-4


def _rel(a, ref):
    """Normwise relative error per rollout (max over steps and joints), worst rollout."""
    a, ref = np.asarray(a), np.asarray(ref)
    assert a.shape == ref.shape
    err = np.abs(a - ref).reshape(a.shape[0], -1).max(1) / np.abs(ref).reshape(ref.shape[0], -1).max(1)
    return float(err.max())


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    torch.manual_seed(0)
    m = build_model("exolan", lim=True, context_channels=CHANNELS, joint_names=("hip", "knee")).double().eval()
    return m, export(m, tmp_path_factory.mktemp("eng32") / "exolan.safetensors", {"dt": 0.005})


@pytest.fixture(scope="module")
def batch():
    rng = np.random.default_rng(1)
    B, T = 37, 20  # two full groups of 16 and a partial one
    return dict(q0=rng.normal(size=(B, 2)) * 0.5, qd0=rng.normal(size=(B, 2)), tau=rng.normal(size=(B, T, 2)) * 5,
                z=rng.normal(size=(B, T, 16)) * 0.5, f_v=rng.uniform(0, 600, size=(B, T)))


def test_f32_agrees_with_f64_and_torch_float32(model_file, batch):
    model, path = model_file
    eng = Engine(path)
    b = batch
    q64, qd64 = eng.rollout(b["q0"], b["qd0"], b["tau"], 0.005, z=b["z"], f_v=b["f_v"])
    q32, qd32 = eng.rollout(b["q0"], b["qd0"], b["tau"], 0.005, z=b["z"], f_v=b["f_v"], precision="f32")
    assert q32.shape == q64.shape == (37, 21, 2) and q32.dtype == np.float64
    assert np.array_equal(q32[:, 0], b["q0"])
    assert _rel(q32, q64) < RTOL and _rel(qd32, qd64) < RTOL
    assert not np.array_equal(q32, q64)  # it is float32 arithmetic
    m32 = build_model("exolan", lim=True, context_channels=CHANNELS, joint_names=("hip", "knee")).eval()
    m32.load_state_dict({k: v.float() for k, v in model.state_dict().items()})
    with torch.no_grad():
        qt, qdt = torch_rollout(m32, *[torch.as_tensor(b[k]).float() for k in ("q0", "qd0", "tau")], 0.005,
                                torch.as_tensor(b["z"]).float(), torch.as_tensor(b["f_v"]).float())
    assert _rel(q32, qt.double().numpy()) < RTOL and _rel(qd32, qdt.double().numpy()) < RTOL
    # a constant z per rollout, and the unbatched form
    zc = b["z"][:, 0]
    qc32, _ = eng.rollout(b["q0"], b["qd0"], b["tau"], 0.005, z=zc, f_v=b["f_v"], precision="f32")
    qc64, _ = eng.rollout(b["q0"], b["qd0"], b["tau"], 0.005, z=zc, f_v=b["f_v"])
    assert _rel(qc32, qc64) < RTOL
    q1, qd1 = eng.rollout(b["q0"][5], b["qd0"][5], b["tau"][5], 0.005, z=zc[5], f_v=b["f_v"][5], precision="f32")
    assert q1.shape == (21, 2) and _rel(q1[None], qc64[5:6]) < RTOL


def test_f32_is_deterministic_across_threads_and_calls(model_file, batch):
    _, path = model_file
    b = batch
    args = (b["q0"], b["qd0"], b["tau"], 0.005)
    ref = fast_rollout(path, *args, z=b["z"], f_v=b["f_v"], threads=1, precision="f32")
    for threads in (1, 2, None):
        q, qd = fast_rollout(path, *args, z=b["z"], f_v=b["f_v"], threads=threads, precision="f32")
        assert np.array_equal(q, ref[0]) and np.array_equal(qd, ref[1])


def test_f32_errors_are_clear(model_file, batch, tmp_path):
    _, path = model_file
    eng = Engine(path)
    b = batch
    args = (b["q0"], b["qd0"], b["tau"], 0.005)
    for bad in ("f16", "float32", "F32", ""):
        with pytest.raises(ValueError, match='precision must be "f64" or "f32"'):
            eng.rollout(*args, z=b["z"], f_v=b["f_v"], precision=bad)
    tau = b["tau"].copy()
    tau[3, 7, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite input: batch element 3: tau"):
        eng.rollout(b["q0"], b["qd0"], tau, 0.005, z=b["z"], f_v=b["f_v"], precision="f32")
    # an exploding rollout: in float32 the state may leave sin/cos's range before it leaves the finite numbers,
    # so it can stop on a NaN inertia matrix rather than a non-finite state; ArithmeticError either way
    with pytest.raises(ArithmeticError, match="diverged|ill-conditioned"):
        eng.rollout(b["q0"], b["qd0"], np.full((37, 400, 2), 1e30), 0.005, z=b["z"][:, 0], f_v=np.zeros((37, 400)),
                    precision="f32")
    # extension terms: refused with the reason, not computed without them
    from exolan.extensions import ExtendedModel

    torch.manual_seed(2)
    base = build_model("delan", lim=False, context_channels=CHANNELS, joint_names=("hip", "knee")).double()
    ext = ExtendedModel(base, 2, [("viscous_damping", 0)], dt=0.005, init=dict(viscous_damping=0.5)).double()
    eng_ext = Engine(export(ext, tmp_path / "ext.safetensors", {"dt": 0.005}))
    with pytest.raises(ValueError, match="unsupported model: .*extension terms.*use float64"):
        eng_ext.rollout(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 5, 2)), 0.005, precision="f32")


def test_f32_singular_inertia_raises_arithmetic_error(tmp_path):
    torch.manual_seed(9)
    m = build_model("delan", lim=False, context_channels=CHANNELS, joint_names=("hip", "knee"),
                    softplus_offset=0.0).double().eval()
    with torch.no_grad():
        m.delan.L[2].weight.zero_()
        m.delan.L[2].bias.copy_(torch.tensor([0.0, -60.0, 0.0], dtype=torch.float64))
    eng = Engine(export(m, tmp_path / "s.safetensors"))
    with pytest.raises(ArithmeticError, match="batch element 0: .*ill-conditioned|ill-conditioned"):
        eng.rollout(np.zeros((3, 2)), np.zeros((3, 2)), np.ones((3, 4, 2)), 0.005, precision="f32")


def test_f32_single_sample_calls(model_file, batch, tmp_path):
    """`precision="f32"` on one sample: inverse/forward dynamics and a single rollout in float32, float64 in
    and out, within float32 rounding of the float64 engine; deterministic; clear errors."""
    _, path = model_file
    eng = Engine(path)
    b = batch
    rng = np.random.default_rng(3)
    for i in range(8):
        q, qd, qdd = rng.normal(size=2), rng.normal(size=2), rng.normal(size=2) * 5
        z, fv = b["z"][i, 0], float(b["f_v"][i, 0])
        tau64 = eng.inverse_dynamics(q, qd, qdd, z, fv)
        tau32 = eng.inverse_dynamics(q, qd, qdd, z, fv, precision="f32")
        assert tau32.shape == (2,) and tau32.dtype == np.float64
        assert _rel(tau32[None], tau64[None]) < RTOL and not np.array_equal(tau32, tau64)
        assert np.array_equal(eng.inverse_dynamics(q, qd, qdd, z, fv, precision="f32"), tau32)
        a64 = eng.forward_dynamics(q, qd, tau64, z, fv)
        a32 = eng.forward_dynamics(q, qd, tau64, z, fv, precision="f32")
        assert _rel(a32[None], a64[None]) < RTOL
        assert _rel(a32[None], qdd[None]) < RTOL  # forward inverts inverse
    # a single rollout (unbatched, and B = 1) runs the float32 single-sample pass
    q1, qd1 = eng.rollout(b["q0"][0], b["qd0"][0], b["tau"][0], 0.005, z=b["z"][0], f_v=b["f_v"][0], precision="f32")
    q64, qd64 = eng.rollout(b["q0"][0], b["qd0"][0], b["tau"][0], 0.005, z=b["z"][0], f_v=b["f_v"][0])
    assert q1.shape == (21, 2) and _rel(q1[None], q64[None]) < RTOL and _rel(qd1[None], qd64[None]) < RTOL
    qb, _ = eng.rollout(b["q0"][:1], b["qd0"][:1], b["tau"][:1], 0.005, z=b["z"][:1], f_v=b["f_v"][:1], precision="f32")
    assert np.array_equal(qb[0], q1)
    # errors: a bad precision, more than one sample, exo torques
    q, z = b["q0"][0], b["z"][0, 0]
    for bad in ("f16", "float32", "F32", ""):
        with pytest.raises(ValueError, match='precision must be "f64" or "f32"'):
            eng.inverse_dynamics(q, q, q, z, 1.0, precision=bad)
        with pytest.raises(ValueError, match='precision must be "f64" or "f32"'):
            eng.forward_dynamics(b["q0"], b["q0"], b["q0"], b["z"][:, 0], b["f_v"][:, 0], precision=bad)
        with pytest.raises(ValueError, match='precision must be "f64" or "f32"'):
            eng._e.inverse_dynamics_one(q, q, q, z, 1.0, bad)
    with pytest.raises(ValueError, match='precision="f32" takes one plain sample'):
        eng.inverse_dynamics(b["q0"], b["q0"], b["q0"], b["z"][:, 0], b["f_v"][:, 0], precision="f32")
    with pytest.raises(ValueError, match="does not take exo torques"):
        eng.forward_dynamics(q, q, q, z, 1.0, tau_e=q, precision="f32")
    with pytest.raises(ValueError, match="non-finite input: q"):
        eng.inverse_dynamics(np.array([0.1, np.nan]), q, q, z, 1.0, precision="f32")
    from exolan.extensions import ExtendedModel

    torch.manual_seed(2)
    base = build_model("delan", lim=False, context_channels=CHANNELS, joint_names=("hip", "knee")).double()
    ext = ExtendedModel(base, 2, [("viscous_damping", 0)], dt=0.005, init=dict(viscous_damping=0.5)).double()
    eng_ext = Engine(export(ext, tmp_path / "ext.safetensors", {"dt": 0.005}))
    with pytest.raises(ValueError, match="unsupported model: .*extension terms.*use float64"):
        eng_ext.inverse_dynamics(q, q, q, precision="f32")
    with pytest.raises(ValueError, match="unsupported model: .*extension terms.*use float64"):
        eng_ext.rollout(q, q, np.zeros((5, 2)), 0.005, precision="f32")
