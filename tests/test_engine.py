"""The Rust engine against torch (float64): τ, q̈, H/c/g, 20-step rollouts and the streaming encoder agree
to 1e-9 relative for every DeLaN-based method with and without LIM — on briefly trained models evaluated on
held-out users, and on random-init models with extension terms. Plus the Python API's shapes, errors,
determinism and GIL release."""
from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch

from exolan import Engine, fast_rollout
from exolan.data import context_features, load, paper_split
from exolan.export import export
from exolan.models import build_model
from exolan.rollout import rollout as torch_rollout

RTOL = 1e-9
METHODS = [(m, lim) for m in ("exolan", "delan-lstm", "delan") for lim in (True, False)]
CHANNELS = ["q_hip", "q_knee", "qd_hip", "qd_knee", "f_v", "cop_x", "cop_z"]


def assert_close(rust, ref, what):
    """Relative agreement, scaled by the reference's magnitude (elementwise relative error is
    meaningless at zero crossings)."""
    rust, ref = np.asarray(rust), np.asarray(ref)
    assert rust.shape == ref.shape, (what, rust.shape, ref.shape)
    scale = max(np.max(np.abs(ref)), 1e-300)
    err = np.max(np.abs(rust - ref)) / scale
    assert err < RTOL, f"{what}: relative error {err:.3e}"


@pytest.fixture(scope="module")
def split(small_world):
    return paper_split(load(small_world))


@pytest.fixture(scope="module")
def trained(split, tmp_path_factory):
    """(method, lim) -> (torch model in float64, weight file), trained 2 epochs on two users."""
    from exolan.train import load_run, train

    users = sorted({t.subject for t in split.train})[:2]
    tiny = split.train.select(subjects=users, tasks={"walk", "jump_in_place"})
    root = tmp_path_factory.mktemp("engine_runs")
    out = {}
    for method, lim in METHODS:
        rd = train(tiny, method, lim=lim, epochs=2, seed=0, out=root / f"{method}_{lim}", progress=False,
                   threads=1)
        path = export(rd, root / f"{method}_{lim}.safetensors")
        model, _ = load_run(rd)
        out[(method, lim)] = (model.double().eval(), path)
    return out


def _held_out(split, k=3):
    return [t for t in split.test_seen if len(t.q) > 100][:k]


@pytest.mark.parametrize("method,lim", METHODS)
def test_trained_models_agree_with_torch_on_held_out_data(trained, split, method, lim):
    model, path = trained[(method, lim)]
    eng = Engine(path)
    assert (eng.method, eng.lim) == (model.method, lim)
    H = 20
    for t in _held_out(split):
        x = context_features(t)
        T = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64))
        with torch.no_grad():
            z_t = model.context(T(x)[None])[0].numpy()
        if model.z_dim:
            z_r = eng.encode(x)
            assert_close(z_r, z_t, f"{method} z (streaming vs sequence)")
        else:
            assert z_t.shape[-1] == 0
        z = z_t if model.z_dim else None
        v = np.asarray(t.valid, bool)
        q, qd, qdd, tau, fv = t.q[v], t.qd[v], t.qdd[v], t.tau[v], t.f_v[v]
        zv = None if z is None else z[v]
        fv_arg = fv if lim else None
        with torch.no_grad():
            tau_t = model.inverse(T(q), T(qd), T(qdd), None if zv is None else T(zv), T(fv)).numpy()
            qdd_t = model.forward_dynamics(T(q), T(qd), T(tau), None if zv is None else T(zv), T(fv)).numpy()
            Ht, ct, gt = model.terms(T(q), T(qd), None if zv is None else T(zv))
        assert_close(eng.inverse_dynamics(q, qd, qdd, zv, fv_arg), tau_t, f"{method} tau")
        assert_close(eng.forward_dynamics(q, qd, tau, zv, fv_arg), qdd_t, f"{method} qdd")
        terms = eng.terms(q, qd, zv)
        assert_close(terms.H, Ht.numpy(), "H")
        assert_close(terms.c, ct.numpy(), "c")
        assert_close(terms.g, gt.numpy(), "g")
        # 20-step rollouts from valid windows
        ok = np.lib.stride_tricks.sliding_window_view(np.asarray(t.valid, bool), H + 1).all(axis=1)
        starts = np.nonzero(ok)[0][::17][:24]
        steps = starts[:, None] + np.arange(H)[None]
        zs = None if z is None else z[steps]
        with torch.no_grad():
            qr_t, qdr_t = torch_rollout(model, T(t.q[starts]), T(t.qd[starts]), T(t.tau[steps]), t.dt,
                                        None if zs is None else T(zs), T(t.f_v[steps]))
        qr, qdr = eng.rollout(t.q[starts], t.qd[starts], t.tau[steps], t.dt, z=zs,
                              f_v=t.f_v[steps] if lim else None)
        assert_close(qr, qr_t.numpy(), f"{method} rollout q")
        assert_close(qdr, qdr_t.numpy(), f"{method} rollout qd")
        # the module-level helper gives the same bits
        q2, _ = fast_rollout(path, t.q[starts], t.qd[starts], t.tau[steps], t.dt, z=zs,
                             f_v=t.f_v[steps] if lim else None)
        assert np.array_equal(q2, qr)


def _random_model(method, lim, seed=0, **cfg):
    torch.manual_seed(seed)
    m = build_model(method, lim=lim, context_channels=CHANNELS, joint_names=("hip", "knee"),
                    v_scale=7.3, lim_scale=0.13, **cfg).double().eval()
    if m.norm is not None:
        rng = np.random.default_rng(seed)
        m.norm.set_stats(rng.normal(size=7), rng.uniform(0.5, 2.0, size=7))
    return m


@pytest.fixture(scope="module")
def exolan_file(tmp_path_factory):
    m = _random_model("exolan", True)
    return m, export(m, tmp_path_factory.mktemp("eng") / "exolan.safetensors", {"dt": 0.005})


def test_extension_terms_agree_with_torch(tmp_path):
    from exolan.extensions import ExtendedModel, exo_derivatives, lag_table

    base = _random_model("exolan", True, seed=3)
    effects = [("viscous_damping", 0), ("viscous_damping", 1), ("coulomb_friction", 0), ("stribeck_friction", 1),
               ("actuation_delay", 1), ("encoder_offset", 0), ("torque_bias", 1), ("torque_gain", 0),
               ("strap_compliance", 1)]
    ext = ExtendedModel(base, 2, effects, dt=0.005, init=dict(
        viscous_damping=1.3, coulomb_friction=0.8, stribeck_friction=0.5, stribeck_vs=0.3,
        actuation_delay=0.0123, encoder_offset=0.02, torque_bias=-1.5, torque_gain=1.2, strap_compliance=150.0)).double()
    with torch.no_grad():
        ext.damping_off[1, 0] = 0.4  # a full PSD matrix, not just a diagonal
    path = export(ext, tmp_path / "ext.safetensors", {"dt": 0.005})
    eng = Engine(path)
    assert set(eng.extensions) == {"ext.damping", "ext.coulomb", "ext.stribeck_fs", "ext.stribeck_vs", "ext.delay",
                                   "ext.encoder_offset", "ext.torque_bias", "ext.torque_gain", "ext.strap_compliance"}
    rng = np.random.default_rng(5)
    T = 150
    tt = np.arange(T) * 0.005
    q = np.stack([0.5 * np.sin(3 * tt), 0.8 + 0.6 * np.sin(4 * tt + 1)], 1)
    qd, qdd = rng.normal(0, 2, (T, 2)), rng.normal(0, 10, (T, 2))
    fv = rng.uniform(0, 700, T)
    tau_e = np.stack([5 * np.sin(6 * tt), 8 * np.cos(5 * tt)], 1)
    x = rng.normal(size=(T, 7))
    z = eng.encode(x)
    d1, d2 = exo_derivatives(tau_e, 0.005)
    K = 10
    idx = torch.as_tensor(lag_table([T], K))
    hist = lambda a: torch.as_tensor(a)[idx]
    Tt = torch.as_tensor
    with torch.no_grad():
        tau_t = ext.inverse(Tt(q), Tt(qd), Tt(qdd), Tt(z), Tt(fv), hist(tau_e), hist(d1), hist(d2)).numpy()
        app_t, _, _ = ext.applied_exo(hist(tau_e))
    app = eng.applied_exo(tau_e, 0.005)
    assert_close(app, app_t.numpy(), "applied exo torque (delay)")
    tau_r = eng.inverse_dynamics(q, qd, qdd, z, fv, tau_e=tau_e, tau_app=app,
                                 tau_app_d=eng.applied_exo(d1, 0.005), tau_app_dd=eng.applied_exo(d2, 0.005))
    assert_close(tau_r, tau_t, "extended tau")
    # the terms matter (otherwise the comparison proves little)
    assert np.max(np.abs(tau_r - Engine(export(base, tmp_path / "b.safetensors")).inverse_dynamics(q, qd, qdd, z, fv))) > 0.1
    tau = rng.normal(0, 20, (T, 2))
    with torch.no_grad():
        qdd_t = ext.forward_dynamics(Tt(q), Tt(qd), Tt(tau), Tt(z), Tt(fv), Tt(tau_e), app_t).numpy()
    assert_close(eng.forward_dynamics(q, qd, tau, z, fv, tau_e=tau_e, tau_app=app), qdd_t, "extended qdd")


def test_extended_model_stays_passive_in_rust(tmp_path):
    """Unforced rollout with damping and Coulomb friction: energy never grows."""
    from exolan.extensions import ExtendedModel

    base = _random_model("delan", False, seed=4)
    ext = ExtendedModel(base, 2, [("viscous_damping", 0), ("viscous_damping", 1), ("coulomb_friction", 1)],
                        dt=0.005, init=dict(viscous_damping=0.5, coulomb_friction=0.3)).double()
    eng = Engine(export(ext, tmp_path / "p.safetensors", {"dt": 0.005}))
    Tn = 3000
    q, qd = eng.rollout([0.4, -0.9], [2.0, -1.0], np.zeros((Tn, 2)), 1e-4)
    Hm = eng.terms(q, qd).H
    kin = 0.5 * np.einsum("ti,tij,tj->t", qd, Hm, qd)
    with torch.no_grad():
        _, V = base.energy(torch.as_tensor(q), torch.as_tensor(qd))
    E = kin + V.numpy()
    assert E[-1] < E[0] - 1e-3 * kin[0]  # it dissipates
    assert np.all(np.diff(E) < 1e-6 * kin[0])  # and never gains (up to the integrator's O(dt²))


def test_shapes_broadcasting_and_batching(exolan_file):
    model, path = exolan_file
    eng = Engine(path)
    rng = np.random.default_rng(0)
    q, qd, qdd = rng.normal(size=(3, 4, 5, 2))[:3]
    z = rng.normal(size=16)
    fv = 300.0
    tau = eng.inverse_dynamics(q, qd, qdd, z, fv)
    assert tau.shape == (4, 5, 2)
    one = eng.inverse_dynamics(q[2, 3], qd[2, 3], qdd[2, 3], z, fv)
    assert one.shape == (2,)
    assert np.array_equal(one, tau[2, 3])  # bit-identical single vs batched
    # large batches run in parallel chunks: still bit-identical to one-at-a-time
    Q = rng.normal(size=(700, 2))
    big = eng.forward_dynamics(Q, Q, Q, z, fv)
    assert np.array_equal(big[517], eng.forward_dynamics(Q[517], Q[517], Q[517], z, fv))
    assert np.array_equal(big, eng.forward_dynamics(Q, Q, Q, z, fv))
    t = eng.terms(q, qd, z)
    assert t.H.shape == (4, 5, 2, 2) and t.c.shape == (4, 5, 2) and t.B.shape == (4, 5, 2)
    # rollouts: unbatched, batched with const z, per-step z
    q1, qd1 = eng.rollout([0.1, 0.2], [0.0, 0.0], np.zeros((7, 2)), 0.005, z=z, f_v=np.zeros(7))
    assert q1.shape == (8, 2) and np.array_equal(q1[0], [0.1, 0.2])
    qb, _ = eng.rollout(np.zeros((3, 2)), np.zeros((3, 2)), np.zeros((3, 7, 2)), 0.005, z=np.tile(z, (3, 7, 1)),
                        f_v=np.zeros((3, 7)))
    assert qb.shape == (3, 8, 2)
    x = rng.normal(size=(2, 40, 7))
    zz = eng.encode(x)
    assert zz.shape == (2, 40, 16)
    assert np.array_equal(zz[1], eng.encode(x[1]))
    with torch.no_grad():
        assert_close(zz, model.context(torch.as_tensor(x)).numpy(), "batched encode")


def test_errors_carry_the_engine_message(exolan_file, tmp_path):
    _, path = exolan_file
    eng = Engine(path)
    z = np.zeros(16)
    with pytest.raises(ValueError, match="bad input shape"):
        eng.inverse_dynamics(np.zeros(3), np.zeros(3), np.zeros(3), z, 0.0)
    with pytest.raises(ValueError, match="non-finite input: q"):
        eng.inverse_dynamics([0.0, np.nan], [0, 0], [0, 0], z, 0.0)
    with pytest.raises(ValueError, match="non-finite input: z"):
        eng.forward_dynamics([0.0, 0.0], [0, 0], [0, 0], np.full(16, np.inf), 0.0)
    with pytest.raises(ValueError, match="needs a context z"):
        eng.inverse_dynamics([0.0, 0.0], [0, 0], [0, 0])
    with pytest.raises(ValueError, match="insole force"):
        eng.inverse_dynamics([0.0, 0.0], [0, 0], [0, 0], z)
    with pytest.raises(ValueError, match="tau has shape"):
        eng.rollout(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((3, 5, 2)), 0.005, z=np.zeros((2, 16)),
                    f_v=np.zeros((2, 5)))
    with pytest.raises(ValueError, match="non-finite input: tau"):
        eng.rollout([0, 0], [0, 0], np.full((5, 2), np.nan), 0.005, z=z, f_v=np.zeros(5))
    with pytest.raises(ArithmeticError, match="diverged"):
        eng.rollout([0, 0], [0, 0], np.full((400, 2), 1e300), 0.005, z=z, f_v=np.zeros(400))
    with pytest.raises(OSError, match="cannot read"):
        Engine(tmp_path / "missing.safetensors")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(path.read_bytes()[:500])
    with pytest.raises(ValueError, match="not a valid safetensors"):
        Engine(bad)


def test_singular_inertia_raises_arithmetic_error(tmp_path):
    m = _random_model("delan", False, seed=9, softplus_offset=0.0)
    with torch.no_grad():
        m.delan.L[2].weight.zero_()
        m.delan.L[2].bias.copy_(torch.tensor([0.0, -60.0, 0.0], dtype=torch.float64))
    eng = Engine(export(m, tmp_path / "s.safetensors"))
    with pytest.raises(ArithmeticError, match="ill-conditioned"):
        eng.forward_dynamics([0.1, 0.2], [0.0, 0.0], [1.0, 1.0])


def test_gil_is_released_during_work(exolan_file):
    _, path = exolan_file
    eng = Engine(path)
    B, T = 64, 400
    args = (np.zeros((B, 2)), np.zeros((B, 2)), np.ones((B, T, 2)), 0.005)
    kw = dict(z=np.zeros((B, 16)), f_v=np.zeros((B, T)))
    t0 = time.perf_counter()
    eng.rollout(*args, **kw)
    if time.perf_counter() - t0 < 0.02:
        pytest.skip("rollout too fast to observe")
    ticks = [0]
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            ticks[0] += 1

    th = threading.Thread(target=spin)
    th.start()
    time.sleep(0.01)
    before = ticks[0]
    eng.rollout(*args, **kw)
    during = ticks[0] - before
    stop.set()
    th.join()
    assert during > 100, "a Python thread made no progress while the engine worked: GIL held"


def test_import_exolan_does_not_import_torch():
    r = subprocess.run([sys.executable, "-c", "import sys, exolan; from exolan import fast_rollout, Engine; "
                        "print('torch' in sys.modules)"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"
