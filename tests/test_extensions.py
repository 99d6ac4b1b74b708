"""The extension terms of DESIGN.md section 4: signs, passivity, delay, observation corrections, export."""
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from exolan.diagnose.base import SlowContextDeLaN
from exolan.extensions import ExtendedModel, lag_table



@pytest.fixture(autouse=True)
def _float64():
    """float64 for these physics checks, restored afterwards (other test modules share the process)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def _base(n=2, seed=0, types=None):
    torch.manual_seed(seed)
    m = SlowContextDeLaN(types or ("revolute",) * n, n_trials=1, z_dim=2, hidden=16, lim=False, v_scale=5.0)
    return m.double()


def _z(B, m):
    return m.z_of(torch.zeros(B, dtype=torch.long))


def test_dissipation_is_never_negative_for_any_parameters():
    base = _base()
    ext = ExtendedModel(base, 2, [("viscous_damping", 0), ("viscous_damping", 1), ("coulomb_friction", 0),
                                  ("stribeck_friction", 1)], dt=0.005)
    g = torch.Generator().manual_seed(1)
    for _ in range(20):   # random raw parameters, including off-diagonal damping and negative raw values
        with torch.no_grad():
            for p in ext.ext_parameters():
                p.copy_(3 * torch.randn(p.shape, generator=g))
        qd = 5 * torch.randn(500, 2, generator=g)
        assert float(ext.dissipated_power(qd).detach().min()) >= -1e-12
        D = ext.damping_matrix()
        assert torch.allclose(D, D.T) and float(torch.linalg.eigvalsh(D.detach()).min()) >= -1e-12


def test_extended_model_is_passive_energy_never_grows_without_input():
    """Free motion (no torque, no contact) of base + damping + Coulomb + Stribeck: E = ½q̇ᵀHq̇ + V decreases."""
    base = _base(seed=3)
    ext = ExtendedModel(base, 2, [("viscous_damping", 0), ("viscous_damping", 1), ("coulomb_friction", 1),
                                  ("stribeck_friction", 0)], dt=0.001,
                        init={"viscous_damping": 0.3, "coulomb_friction": 0.5, "stribeck_friction": 0.4})
    with torch.no_grad():
        ext.damping_off.fill_(0.4)   # full (coupled) PSD damping
    B = 16
    g = torch.Generator().manual_seed(4)
    q = torch.randn(B, 2, generator=g)
    qd = 3 * torch.randn(B, 2, generator=g)
    z = _z(B, base)
    fv = torch.zeros(B)
    zero = torch.zeros(B, 2)
    dt = 1e-3
    with torch.no_grad():
        def energy(q, qd):
            T, V = base.energy(q, qd, z)
            return T + V
        E0 = energy(q, qd)
        E = E0.clone()
        worst = 0.0
        # free conservative twin for comparison: the same integrator keeps energy within its own error
        for k in range(200):
            qdd = ext.forward_dynamics(q, qd, zero, z, fv)
            qd = qd + dt * qdd           # semi-implicit Euler (DESIGN.md section 5)
            q = q + dt * qd
            En = energy(q, qd)
            worst = max(worst, float((En - E).max()))
            E = En
    # energy decreases overall and never rises by more than the integrator's O(dt²) per-step error
    assert float((E - E0).max()) < 0
    assert worst < 1e-4 * float(E0.abs().max())


def test_friction_terms_have_the_world_signs():
    base = _base()
    ext = ExtendedModel(base, 2, [("viscous_damping", 0), ("coulomb_friction", 1)], dt=0.005,
                        init={"viscous_damping": 1.5, "coulomb_friction": 2.0})
    qd = torch.tensor([[1.0, 1.0], [-1.0, -1.0]], dtype=torch.float64)
    f = ext.friction(qd).detach()
    # τ += D q̇ and Fc tanh(q̇/ε): the actuator must add torque in the direction of motion
    assert f[0, 0] == pytest.approx(1.5, rel=1e-6) and f[1, 0] == pytest.approx(-1.5, rel=1e-6)
    assert f[0, 1] == pytest.approx(2.0 * math.tanh(100.0), rel=1e-6)
    assert ext.estimate("viscous_damping", 0) == pytest.approx(1.5, rel=1e-6)
    assert ext.estimate("coulomb_friction", 1) == pytest.approx(2.0, rel=1e-6)
    assert ext.coulomb()[0] == 0 and ext.damping_matrix()[1, 1] == 0   # inactive joints untouched


def test_warm_start_per_joint():
    """`init` takes a number for every joint or {joint: number}: two damped joints keep their own starts,
    joints left out of the mapping keep the default."""
    ext = ExtendedModel(_base(), 2, [("viscous_damping", 0), ("viscous_damping", 1), ("coulomb_friction", 1),
                                     ("actuation_delay", 1)], dt=0.005,
                        init={"viscous_damping": {0: 0.4, 1: 1.7}, "coulomb_friction": {1: 2.5},
                              "actuation_delay": {1: 0.03}})
    assert ext.estimate("viscous_damping", 0) == pytest.approx(0.4, rel=1e-6)
    assert ext.estimate("viscous_damping", 1) == pytest.approx(1.7, rel=1e-6)
    assert ext.estimate("coulomb_friction", 1) == pytest.approx(2.5, rel=1e-6)
    assert ext.estimate("actuation_delay", 1) == pytest.approx(0.03, rel=1e-6)
    assert float(F.softplus(ext.coulomb_raw[0].detach())) == pytest.approx(0.05, rel=1e-6)   # the default, not 2.5


def test_fractional_delay_is_linear_interpolation_of_the_history():
    base = _base()
    dt = 0.005
    ext = ExtendedModel(base, 2, [("actuation_delay", 1)], dt=dt, max_delay=0.05, init={"actuation_delay": 0.0125})
    T = 200
    t = np.arange(T) * dt
    tau_e = np.stack([np.sin(7 * t), np.cos(5 * t) + t], 1)
    lag = torch.as_tensor(lag_table([T], 11))
    hist = torch.as_tensor(tau_e)[lag]                     # (T, 12, 2)
    app, _, _ = ext.applied_exo(hist)
    # a delay of 0.0125 s is 2.5 samples: half of each neighbour
    want = 0.5 * tau_e[np.maximum(np.arange(T) - 2, 0), 1] + 0.5 * tau_e[np.maximum(np.arange(T) - 3, 0), 1]
    assert np.allclose(app[:, 1].detach().numpy(), want, atol=1e-9)
    assert np.allclose(app[:, 0].detach().numpy(), tau_e[:, 0])     # no delay on joint 0
    # the recorded-torque prediction gains τ_e(t) − τ_e(t−d) on the delayed joint only
    q = torch.zeros(T, 2); z = _z(T, base); fv = torch.zeros(T)
    d_pred = ext.inverse(q, q, q, z, fv, hist) - base.inverse(q, q, q, z, fv)
    assert np.allclose(d_pred[:, 1].detach().numpy(), tau_e[:, 1] - want, atol=1e-9)
    assert np.allclose(d_pred[:, 0].detach().numpy(), 0.0, atol=1e-12)
    # the delay is differentiable (a gradient reaches its parameter)
    ext.zero_grad()
    ext.inverse(q, q, q, z, fv, hist).sum().backward()
    assert ext.delay_raw.grad is not None and float(ext.delay_raw.grad.abs()[1]) > 0


def test_a_lagged_history_gives_the_gathered_historys_bits():
    """`Lagged` reads two columns of a history where the (B, K+1, n) tensor holds all of them: the same predicted
    torque and the same gradients, bit for bit, at rows in any order and near a trial's start (clamped lags);
    a delay on both joints, one between grid points, the strap reading the delayed derivatives."""
    base = _base()
    dt = 0.005
    ext = ExtendedModel(base, 2, [("actuation_delay", 0), ("actuation_delay", 1), ("strap_compliance", 1)], dt=dt,
                        max_delay=0.05, init={"actuation_delay": 0.0137, "strap_compliance": 300.0})
    lengths = [90, 110]
    g = torch.Generator().manual_seed(3)
    series = [torch.randn(sum(lengths), 2, generator=g) for _ in range(3)]
    lag = torch.as_tensor(lag_table(lengths, 10))
    rows = torch.cat([torch.tensor([0, 1, 90, 91, 95]), torch.randint(sum(lengths), (40,), generator=g)])
    B = len(rows)
    q, qd, qdd = (torch.randn(B, 2, generator=g) for _ in range(3))
    fv = torch.rand(B)

    def run(hist):
        ext.zero_grad()
        tau = ext.inverse(q, qd, qdd, _z(B, base), fv, *hist)
        tau.square().sum().backward()
        return tau.detach(), [p.grad.clone() for p in ext.parameters() if p.grad is not None]

    from exolan.exo_signals import Lagged
    tau_a, grads_a = run([x[lag[rows]] for x in series])
    shared: dict = {}
    tau_b, grads_b = run([Lagged(x, lag, rows, shared) for x in series])
    assert torch.equal(tau_a, tau_b)
    assert len(grads_a) == len(grads_b) > 0 and all(torch.equal(a, b) for a, b in zip(grads_a, grads_b))
    assert float(ext.delay_raw.grad.abs().min()) > 0


def test_observation_corrections_encoder_offset_and_strap():
    base = _base()
    ext = ExtendedModel(base, 2, [("encoder_offset", 0), ("strap_compliance", 1)], dt=0.005,
                        init={"encoder_offset": 0.03, "strap_compliance": 200.0})
    B = 10
    g = torch.Generator().manual_seed(0)
    q, qd, qdd = (torch.randn(B, 2, generator=g) for _ in range(3))
    te, ted, tedd = (torch.randn(B, 2, generator=g) for _ in range(3))
    z = _z(B, base); fv = torch.zeros(B)
    got = ext.inverse(q, qd, qdd, z, fv, te, ted, tedd)
    qt = q.clone(); qt[:, 0] -= 0.03; qt[:, 1] -= te[:, 1] / 200.0
    qdt = qd.clone(); qdt[:, 1] -= ted[:, 1] / 200.0
    qddt = qdd.clone(); qddt[:, 1] -= tedd[:, 1] / 200.0
    want = base.inverse(qt, qdt, qddt, z, fv)
    assert torch.allclose(got, want, atol=1e-10)
    assert ext.estimate("strap_compliance", 1) == pytest.approx(200.0, rel=1e-6)


def test_recording_terms_bias_and_gain():
    base = _base()
    ext = ExtendedModel(base, 2, [("torque_bias", 0), ("torque_gain", 1)], dt=0.005,
                        init={"torque_bias": 0.7, "torque_gain": 1.25})
    B = 5
    te = torch.randn(B, 2)
    q = torch.zeros(B, 2); z = _z(B, base); fv = torch.zeros(B)
    d = ext.inverse(q, q, q, z, fv, te) - base.inverse(q, q, q, z, fv)
    assert torch.allclose(d[:, 0], torch.full((B,), 0.7))
    assert torch.allclose(d[:, 1], (1 - 1 / 1.25) * te[:, 1])
    # k > 0 whatever the optimiser does to the raw parameter (rule 4's sign constraint)
    for raw in (-60.0, -30.0, 0.0, 30.0, 60.0):     # k from e^{-6} to e^{6}
        with torch.no_grad():
            ext.gain_raw[1] = raw
        k = ext.estimate("torque_gain", 1)
        assert k > 0 and k == pytest.approx(math.exp(0.1 * raw), rel=1e-6)


def test_a_gated_term_acts_on_its_own_trials_only():
    """`init["gates"]`: a subject-specific term is the full term on the trials marked 1 and absent on the others,
    for every kind of term (friction, delay, observation, recording); without `trial=` it acts everywhere."""
    base = _base()
    effects = [("viscous_damping", 1), ("coulomb_friction", 1), ("actuation_delay", 1), ("encoder_offset", 0),
               ("strap_compliance", 1), ("torque_bias", 0), ("torque_gain", 1)]
    init = {"viscous_damping": 1.3, "coulomb_friction": 0.8, "actuation_delay": 0.0125, "encoder_offset": 0.03,
            "strap_compliance": 150.0, "torque_bias": 0.4, "torque_gain": 1.3}
    whole = ExtendedModel(base, 2, effects, dt=0.005, max_delay=0.05, init=dict(init))
    gates = {e: {j: [0.0, 1.0, 0.0]} for e, j in effects}
    gated = ExtendedModel(base, 2, effects, dt=0.005, max_delay=0.05, init=dict(init, gates=gates))
    assert gated.gated and set(gated.gate_trials()) == {e for e, _ in effects}
    B = 12
    g = torch.Generator().manual_seed(1)
    q, qd, qdd = (torch.randn(B, 2, generator=g) for _ in range(3))
    hist = torch.randn(B, 12, 2, generator=g)
    z = _z(B, base); fv = torch.zeros(B)
    trial = torch.tensor([0, 1, 2] * 4)
    got = gated.inverse(q, qd, qdd, z, fv, hist, hist, hist, trial=trial)
    on = trial == 1
    want_on = whole.inverse(q, qd, qdd, z, fv, hist, hist, hist)
    want_off = base.inverse(q, qd, qdd, z, fv)
    assert torch.allclose(got[on], want_on[on], atol=1e-10)
    assert torch.allclose(got[~on], want_off[~on], atol=1e-10)
    assert not torch.allclose(want_on[~on], want_off[~on])          # the term does change those rows
    assert torch.allclose(gated.inverse(q, qd, qdd, z, fv, hist, hist, hist), want_on, atol=1e-10)
    # forward dynamics and the dissipation follow the same gate; passivity holds per sample
    tau = torch.randn(B, 2, generator=g)
    app = gated.applied_exo(hist, trial=trial)[0]
    fd = gated.forward_dynamics(q, qd, tau, z, fv, hist[:, 0], app, trial=trial)
    assert torch.allclose(fd[~on], base.forward_dynamics(q, qd, tau, z, fv)[~on], atol=1e-10)
    assert bool((gated.dissipated_power(qd, trial=trial) >= 0).all())
    assert torch.allclose(gated.dissipated_power(qd, trial=trial)[~on], torch.zeros(int((~on).sum())))
    # a gate must name a term the model has, with one value per trial
    with pytest.raises(ValueError, match="not among"):
        ExtendedModel(base, 2, [("viscous_damping", 1)], init={"gates": {"coulomb_friction": {1: [1.0]}}})
    with pytest.raises(ValueError, match="no such term"):
        ExtendedModel(base, 2, [("viscous_damping", 1)], init={"gates": {"viscous_damping": {0: [1.0]}}})


def test_a_sized_term_acts_at_each_subjects_own_size():
    """`init["sized"]`: each subject u has θ_u = θ e^{a_u} with the log sizes centred (θ the geometric mean), for
    every term linear in its parameter; on a trial the model equals the shared model at that subject's value,
    `physical(trial)` reports it, the friction stays dissipative, and the sizes are learnt (they get gradients)."""
    base = _base()
    effects = [("viscous_damping", 1), ("coulomb_friction", 1), ("encoder_offset", 0), ("strap_compliance", 1),
               ("torque_bias", 0)]
    init = {"viscous_damping": 1.3, "coulomb_friction": 0.8, "encoder_offset": 0.03, "strap_compliance": 150.0,
            "torque_bias": 0.4}
    a = np.array([0.5, 0.1, -0.3])            # not centred: the model centres them (mean 0.1)
    subject_of_trial = [0, 2, 1, 2]
    sized = ExtendedModel(base, 2, effects, dt=0.005, max_delay=0.05,
                          init=dict(init, sized={e: {j: a} for e, j in effects}, subject_of_trial=subject_of_trial))
    assert set(sized.sized) == {e for e, _ in effects} and set(sized.gated) == set(sized.sized)
    ac = a - a.mean()
    np.testing.assert_allclose(sized.size_values()["viscous_damping"][1], ac, atol=1e-12)
    B = 16
    g = torch.Generator().manual_seed(3)
    q, qd, qdd = (torch.randn(B, 2, generator=g) for _ in range(3))
    hist = torch.randn(B, 12, 2, generator=g)
    z = _z(B, base); fv = torch.zeros(B)
    trial = torch.tensor([0, 1, 2, 3] * 4)
    got = sized.inverse(q, qd, qdd, z, fv, hist, hist, hist, trial=trial)
    for t, u in enumerate(subject_of_trial):
        f = math.exp(ac[u])
        own = {"viscous_damping": 1.3 * f, "coulomb_friction": 0.8 * f, "encoder_offset": 0.03 * f,
               "strap_compliance": 150.0 / f, "torque_bias": 0.4 * f}
        shared = ExtendedModel(base, 2, effects, dt=0.005, max_delay=0.05, init=own)
        rows = trial == t
        assert torch.allclose(got[rows], shared.inverse(q, qd, qdd, z, fv, hist, hist, hist)[rows], atol=1e-9)
        p = sized.physical(t)
        assert p["viscous_damping"][1, 1] == pytest.approx(1.3 * f, rel=1e-9)
        assert p["strap_compliance"][1] == pytest.approx(150.0 / f, rel=1e-9)
        assert sized.trial_factor("coulomb_friction", 1, t) == pytest.approx(f, rel=1e-12)
        assert sized.trial_factor("coulomb_friction", 0, t) == 1.0       # a joint without the term's sizes
    # the geometric mean is the shared parameter; passivity per sample; sizes are learnt
    assert sized.estimate("viscous_damping", 1) == pytest.approx(1.3, rel=1e-9)
    assert bool((sized.dissipated_power(qd, trial=trial) >= 0).all())
    got.sum().backward()
    assert float(sized.size_viscous_damping.grad[:, 1].abs().sum()) > 0
    assert sized.size_viscous_damping in sized.ext_parameters()
    # carried to a refit: the same model again
    again = ExtendedModel(base, 2, effects, dt=0.005, max_delay=0.05, init=dict(init, **sized.subject_init()))
    assert torch.allclose(again.inverse(q, qd, qdd, z, fv, hist, hist, hist, trial=trial), got, atol=1e-12)
    # sizes only for terms linear in their parameter, with a subject per trial, on the model's own terms
    with pytest.raises(ValueError, match="linear in their parameter"):
        ExtendedModel(base, 2, [("actuation_delay", 1)], init={"sized": {"actuation_delay": {1: None}},
                                                               "subject_of_trial": [0, 1]})
    with pytest.raises(ValueError, match="subject_of_trial"):
        ExtendedModel(base, 2, [("viscous_damping", 1)], init={"sized": {"viscous_damping": {1: None}}})
    with pytest.raises(ValueError, match="no such term"):
        ExtendedModel(base, 2, [("viscous_damping", 1)], init={"sized": {"viscous_damping": {0: None}},
                                                               "subject_of_trial": [0, 1]})
    with pytest.raises(ValueError, match="3 values for 2 subjects"):
        ExtendedModel(base, 2, [("viscous_damping", 1)], init={"sized": {"viscous_damping": {1: [0.0, 0.1, 0.2]}},
                                                               "subject_of_trial": [0, 1]})


def test_set_value_writes_a_physical_parameter():
    ext = ExtendedModel(_base(), 2, [("viscous_damping", 1), ("strap_compliance", 0), ("torque_gain", 1),
                                      ("encoder_offset", 1)], dt=0.005)
    for eff, j, v in (("viscous_damping", 1, 2.2), ("strap_compliance", 0, 95.0), ("torque_gain", 1, 1.7),
                      ("encoder_offset", 1, -0.04)):
        ext.set_value(eff, j, v)
        assert ext.estimate(eff, j) == pytest.approx(v, rel=1e-9)
    with pytest.raises(ValueError, match="not set this way"):
        ext.set_value("actuation_delay", 1, 0.01)


def test_without_switches_terms_off_and_keeps_the_rest_as_fitted():
    """`without`: a copy with the named terms neutral (friction 0, gain k = 1), every other term and the base
    as they were, the model itself untouched; a term the model lacks is an error, not a silent no-op."""
    ext = ExtendedModel(_base(), 2, [("viscous_damping", 0), ("coulomb_friction", 1), ("torque_gain", 1)],
                        dt=0.005, init={"viscous_damping": 1.5, "coulomb_friction": 2.0, "torque_gain": 1.4})
    qd = torch.tensor([[1.0, -2.0]], dtype=torch.float64)
    off = ext.without([("coulomb_friction", 1), ("torque_gain", 1)])
    f, f_off = ext.friction(qd).detach(), off.friction(qd).detach()
    assert f_off[0, 1] == 0 and f[0, 1] == pytest.approx(-2.0, rel=1e-6)
    assert f_off[0, 0] == pytest.approx(1.5, rel=1e-6)
    assert off.estimate("torque_gain", 1) == pytest.approx(1.0) and ext.estimate("torque_gain", 1) == pytest.approx(1.4)
    assert all(torch.equal(a, b) for a, b in zip(off.base.state_dict().values(), ext.base.state_dict().values()))
    with pytest.raises(ValueError, match="no 'coulomb_friction' term on joint 0"):
        ext.without([("coulomb_friction", 0)])


def test_ext_tensors_follow_the_design_names_and_shapes():
    base = _base()
    ext = ExtendedModel(base, 2, [("viscous_damping", 1), ("coulomb_friction", 0), ("stribeck_friction", 0),
                                  ("actuation_delay", 1), ("encoder_offset", 0), ("torque_bias", 1),
                                  ("torque_gain", 0), ("strap_compliance", 1)], dt=0.005)
    t = ext.ext_tensors()
    assert set(t) == {"ext.damping", "ext.coulomb", "ext.stribeck_fs", "ext.stribeck_vs", "ext.delay",
                      "ext.encoder_offset", "ext.torque_bias", "ext.torque_gain", "ext.strap_compliance"}
    assert t["ext.damping"].shape == (2, 2) and all(v.dtype == np.float64 for v in t.values())
    assert t["ext.damping"][0, 0] == 0 and t["ext.torque_gain"][1] == 1.0 and np.isinf(t["ext.strap_compliance"][0])
    assert ExtendedModel(base, 2, [], dt=0.005).ext_tensors() == {}


class _Rec:
    """A minimal trial: angle q and the device's velocity qd (T, n)."""
    def __init__(self, q, qd):
        self.q, self.qd = q, qd


def _device(x, dt, cutoff):
    from scipy.signal import butter, filtfilt
    b, a = butter(2, cutoff * 2 * dt)
    return filtfilt(b, a, x, axis=0)


@pytest.mark.parametrize("cutoff", [12.0, 30.0])
def test_velocity_response_recovers_the_devices_filter(cutoff):
    """The recorded velocity's filter, estimated from angle and velocity alone, matches the filter that made it
    (a zero-phase Butterworth of the angle's difference quotient), including its roll-off, at any cut-off."""
    from scipy.signal import butter, freqz
    from exolan.extensions import velocity_response
    dt, rng = 0.005, np.random.default_rng(3)
    trials = []
    for k in range(3):
        t = np.arange(4000) * dt
        q = np.stack([np.sin(2 * np.pi * 1.1 * t + k), 0.5 * np.sin(2 * np.pi * 0.7 * t)], 1)
        q = q + rng.normal(0, 2e-4, q.shape)            # encoder noise: power at every frequency
        trials.append(_Rec(q, _device(np.gradient(q, dt, axis=0), dt, cutoff)))
    taps = velocity_response(trials, dt)
    assert np.allclose(taps, taps[::-1])                                 # zero phase
    f = np.linspace(0, 60, 49)
    b, a = butter(2, cutoff * 2 * dt)
    _, h = freqz(b, a, worN=2 * np.pi * f * dt)
    want = np.abs(h) ** 2                                                # filtfilt: |H|², zero phase
    for j in range(2):
        _, g = freqz(taps[:, j], 1, worN=2 * np.pi * f * dt)
        assert np.max(np.abs(np.abs(g) - want)) < 0.03, np.c_[f, np.abs(g), want]
    assert velocity_response([_Rec(q[:100], q[:100])], dt) is None       # too short to estimate
    # a gap (NaN) in a recording: the fit uses the finite stretches on either side, aligned
    gap = [_Rec(t.q.copy(), t.qd.copy()) for t in trials]
    gap[0].qd[1000:1040] = np.nan
    np.testing.assert_allclose(velocity_response(gap, dt), taps, atol=2e-3)


def test_strap_derivatives_follow_the_measured_chain_and_keep_sensor_noise_out():
    """With the velocity filter, the exo torque's τ̇ and τ̈ are what a deflection τ/k would show in the measured
    q̇ (device filter) and q̈ (the reader's derivative of q̇); its white sensor noise reaches τ̈ far less than
    through a plain second derivative."""
    from scipy.signal import savgol_filter
    from exolan.extensions import exo_derivatives, velocity_response
    dt, rng = 0.005, np.random.default_rng(4)
    t = np.arange(3000) * dt
    tau = np.stack([3 * np.sin(2 * np.pi * 1.3 * t) * (1 + 0.2 * np.sin(2 * np.pi * 8 * t)),
                    np.cos(2 * np.pi * 2.1 * t)], 1)
    q = 0.3 * np.sin(2 * np.pi * np.outer(t, [0.9, 1.4])) + rng.normal(0, 2e-4, (len(t), 2))
    resp = velocity_response([_Rec(q, _device(np.gradient(q, dt, axis=0), dt, 20.0))], dt)
    d1, d2 = exo_derivatives(tau, dt, response=resp, qdd_window=11)
    want1 = _device(np.gradient(tau, dt, axis=0), dt, 20.0)
    want2 = savgol_filter(want1, 11, 3, deriv=1, delta=dt, axis=0)
    inner = slice(100, -100)
    assert np.max(np.abs(d1[inner] - want1[inner])) < 0.01 * np.abs(want1).max()
    assert np.max(np.abs(d2[inner] - want2[inner])) < 0.01 * np.abs(want2).max()
    noise = rng.normal(0, 0.05, tau.shape)
    _, n_chain = exo_derivatives(noise, dt, response=resp, qdd_window=11)
    _, n_plain = exo_derivatives(noise, dt)
    assert n_chain[inner].var() < n_plain[inner].var() / 3      # measured: 0.26 with a 20 Hz device filter
