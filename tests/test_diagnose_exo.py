"""Diagnosis building blocks for exo-driven terms: the copy of the joint torque, detection limits (computed and by
injection), the screen, rule 3's nulls and the rivals. Fast (seconds)."""
import math

import numpy as np
import pytest
import torch

from exolan.diagnose.base import make_base
from exolan.diagnose.export import extend
from exolan.diagnose.flat import prepare
from exolan.diagnose.nulls import MIN_FUTURE_LAG, track_lag
from exolan.diagnose.rules import paired_gain
from exolan.diagnose.settings import Settings

from diagnose_helpers import leg_pair


@pytest.mark.parametrize("lag", [2, 7, 12])
def test_track_lag_finds_where_the_exo_torque_copies_the_joint_torque(lag):
    """An assistive controller's torque is a lagged share of the joint torque: the gain's null takes it there,
    but no nearer than the residual's null (5 samples): a torque two samples ahead is nearly the present one."""
    trials = leg_pair(T=2000)
    rng = np.random.default_rng(1)
    for t in trials:
        smooth = np.convolve(rng.normal(0, 10, t.tau.shape[0] + 40), np.hanning(25), "same")[20:-20]
        t.tau = np.stack([smooth, smooth[::-1]], 1)
        t.tau_e = np.zeros_like(t.tau)
        t.tau_e[lag:] = 0.3 * t.tau[:-lag] + rng.normal(0, 0.05, (t.tau.shape[0] - lag, 2))
    flat = prepare(trials)
    want = max(lag, MIN_FUTURE_LAG)     # 7 and 12 found where they are, 2 taken at the minimum (5)
    assert track_lag(flat, 0) == want and track_lag(flat, 1) == want


def test_exo_copy_keeps_the_share_of_the_joint_torque_and_drops_the_controllers_own_variation():
    """The gain's third null: the exo torque replaced by its fit on the joint torque's recent past. A lagged
    share of the joint torque is kept; the controller's own slow variation is what it leaves out."""
    from exolan.diagnose.flat import exo_copy, exo_own

    trials = leg_pair(T=3000)
    rng = np.random.default_rng(2)
    own = []
    for t in trials:
        smooth = np.convolve(rng.normal(0, 10, t.tau.shape[0] + 40), np.hanning(25), "same")[20:-20]
        wiggle = np.convolve(rng.normal(0, 1.0, t.tau.shape[0] + 200), np.hanning(101), "same")[100:-100]
        t.tau = np.stack([smooth, smooth[::-1]], 1)
        t.tau_e = np.zeros_like(t.tau)
        t.tau_e[5:, 0] = 0.2 * t.tau[:-5, 0]
        t.tau_e[:, 0] += wiggle
        t.tau_e[:, 1] = rng.normal(0, 1, t.tau.shape[0])
        own.append(wiggle)
    flat = prepare(trials)
    f = exo_copy(flat, 0)
    share = np.concatenate([np.r_[np.zeros(5), 0.2 * t.tau[:-5, 0]] for t in trials])
    left = flat.tau_e[:, 0].numpy() - f.tau_e[:, 0].numpy()
    ok = np.concatenate([np.arange(len(t.tau)) >= 40 for t in trials])
    assert np.corrcoef(f.tau_e[ok, 0].numpy(), share[ok])[0, 1] > 0.95
    assert np.corrcoef(left[ok], np.concatenate(own)[ok])[0, 1] > 0.9
    assert torch.equal(f.tau_e[:, 1], flat.tau_e[:, 1]) and torch.equal(flat.tau_e[:, 0], prepare(trials).tau_e[:, 0])
    # rule 3's own-variation null reads what the copy leaves over, the other joint untouched
    o = exo_own(flat, 0)
    torch.testing.assert_close(o.tau_e[:, 0], flat.tau_e[:, 0] - f.tau_e[:, 0])
    assert torch.equal(o.tau_e[:, 1], flat.tau_e[:, 1])


def _assisted_pair(share: float, own_sd: float, seed: int):
    """Two trials whose hip exo torque is an assistive controller's: `share` of the joint torque 5 samples
    earlier plus its own slow variation (SD about `own_sd` N m); the knee has no exo torque."""
    trials = leg_pair(T=6000)
    rng = np.random.default_rng(seed)
    for t in trials:
        t.tau = np.stack([np.convolve(rng.normal(0, 10, 6040), np.hanning(25), "same")[20:-20]] * 2, 1)
        t.tau_e = np.zeros_like(t.tau)
        t.tau_e[5:, 0] = share * t.tau[:-5, 0]
        t.tau_e[:, 0] += own_sd * np.convolve(rng.normal(0, 1, 6200), np.hanning(101), "same")[100:-100] / 7.0
    return prepare(trials)


def test_the_torque_gains_detection_limit_follows_the_controllers_own_variation():
    """|1 − 1/k| below which a gain cannot show: set by the exo torque's own variation (not its copy of the joint
    torque), the model's misfit and the refit noise. Checked against the closed forms of its two regimes."""
    from exolan.diagnose import limits as P
    from exolan.diagnose.flat import exo_copy

    sigma_eps = 0.02                                         # the model's white misfit, N m/kg
    eps = torch.as_tensor(np.random.default_rng(4).normal(0, sigma_eps, (12000, 2)), dtype=torch.float32)
    predict = lambda model, flat, idx: flat.tau[idx] - eps[idx] * flat.mass[idx, None]    # noqa: E731
    s = Settings(n_boot=300)
    lim = {}
    for own_sd in (1.0, 2.0):
        flat = _assisted_pair(share=0.2, own_sd=own_sd, seed=3)
        held = flat.index("held")
        out = P.gain_detection_limit(flat, None, held, None, 0.0, s, predict)
        assert set(out) == {"hip"}                           # the knee has no exo torque
        v = out["hip"]
        own = (flat.tau_e[held, 0] - exo_copy(flat, 0).tau_e[held, 0]).numpy() / 70.0
        P_own = np.mean(own ** 2)
        # sampling-dominated (σ_r = 0): a = 2·1.96·SE(o ε)/P with SE ≈ rms(o) σ_ε / √N for a white ε
        expect = 2 * 1.96 * np.sqrt(P_own) * sigma_eps / np.sqrt(len(held)) / P_own
        assert 0.75 * expect < v["theta_limit"] < 1.33 * expect
        # θ = 1 − 1/k: the limits on k itself, asymmetric about 1
        assert np.isclose(1 - 1 / v["k_above"], v["theta_limit"]) and np.isclose(1 / v["k_below"] - 1, v["theta_limit"])
        assert 0.5 < v["copy_share"] < 0.99 and v["rms_own"] < v["rms_exo"]
        # refit-noise-dominated: a → √(1.96 σ_r / P)
        big = P.gain_detection_limit(flat, None, held, None, 1e-2, s, predict)["hip"]["theta_limit"]
        assert abs(big / np.sqrt(1.96 * 1e-2 / P_own) - 1) < 0.05
        lim[own_sd] = v["theta_limit"]
    # twice the controller's own variation: half the limit (its copy share alone would not tell)
    assert 0.4 < lim[2.0] / lim[1.0] < 0.6
    # a gain in the data leaves part of θ o in the reference's residual: the limit is that of the data without
    # it, not inflated by the effect it is to detect
    flat = _assisted_pair(share=0.2, own_sd=1.0, seed=3)
    own_all = (flat.tau_e[:, 0] - exo_copy(flat, 0).tau_e[:, 0]) / flat.mass
    with_gain = eps.clone()
    with_gain[:, 0] += 0.3 * own_all
    predict = lambda model, f, idx: f.tau[idx] - with_gain[idx] * f.mass[idx, None]    # noqa: E731
    v = P.gain_detection_limit(flat, None, flat.index("held"), None, 0.0, s, predict)["hip"]
    assert abs(v["theta_limit"] / lim[1.0] - 1) < 0.05


def test_the_injected_limit_scales_the_injections_gain_as_theta_squared():
    """u = (θ/θ0)²: the test's bound u g0 = z √(u se0² + σ_r²), z the normal quantile of the decision's two-sided
    level (1.96 at 5 %). Sampling-dominated, √u = z se0 / g0; refit-noise-dominated, u = z σ_r / g0; an injection
    that did not show gives no limit."""
    from scipy.stats import norm

    from exolan.diagnose.limits import injected_limit as _injected_limit

    z = norm.ppf(0.975)
    assert _injected_limit(4 * z * 1e-5, 1e-5, 0.0, 0.6) == pytest.approx(0.15)
    assert _injected_limit(z * 1e-4, 0.0, 1e-5, 0.4) == pytest.approx(0.4 * math.sqrt(0.1))
    assert _injected_limit(-1e-5, 1e-5, 0.0, 0.4) == math.inf
    z1 = norm.ppf(1 - 0.05 / 24)        # the single-term level of 12 candidates
    assert _injected_limit(4 * z1 * 1e-5, 1e-5, 0.0, 0.6, level=0.05 / 12) == pytest.approx(0.15)
    # both noises: between the two one-noise answers' larger one and their root-sum-square
    both = _injected_limit(1e-4, 1e-5, 1e-5, 0.5)
    one = max(_injected_limit(1e-4, 1e-5, 0.0, 0.5), _injected_limit(1e-4, 0.0, 1e-5, 0.5))
    assert one < both < math.hypot(_injected_limit(1e-4, 1e-5, 0.0, 0.5), _injected_limit(1e-4, 0.0, 1e-5, 0.5))


def test_the_limits_by_injection_write_a_known_gain_and_delay_into_data_cleaned_of_the_own_variations_share(
        small_world):
    """Mechanics of `limits_by_injection` (fits made no-ops): the base is fitted on the recorded joint torque less
    the share of the controller's own variation o (and of its rate ȯ) that the reference leaves (0.3 o + 0.002 ȯ
    here), plus θ0 τ_e (a gain) and τ_e(t) − τ_e(t − d0) (a delay), θ0 and d0 twice the computed limits; a limit
    far from its injection is measured again by a second injection at 1.2 times it."""
    from exolan.data import savgol_derivative
    from exolan.diagnose import limits as P
    from exolan.diagnose.flat import exo_copy
    from exolan.diagnose.procedure import load_trials

    flat = prepare(load_trials(small_world))
    held = flat.index("held")
    split = lambda x: torch.split(x, [int(n) for n in flat.lengths])
    own = {j: flat.tau_e[:, j] - exo_copy(flat, j).tau_e[:, j] for j in range(2)}
    rate = {j: torch.as_tensor(np.concatenate([savgol_derivative(seg.numpy().astype(np.float64), flat.dt)
                                               for seg in split(own[j])]), dtype=flat.tau.dtype) for j in range(2)}
    left = torch.stack([0.3 * own[j] + 0.002 * rate[j] for j in range(2)], 1)
    fitted = []
    stubs = dict(predict=lambda model, f, idx: f.tau[idx] - left[idx],
                 train=lambda model, f, *a, **k: fitted.append(f.tau.clone()), refit=lambda *a, **k: None,
                 screen=lambda *a, **k: {})       # the terms start at their defaults (delay: one sample)
    s = Settings(n_boot=100, hidden=8, verbose=False)
    base = make_base(flat, hidden=8)
    analytic = {"torque_gain": {"hip": dict(theta_limit=0.15), "knee": dict(theta_limit=0.3)},
                "actuation_delay": {"knee": dict(d_limit=0.012)}}

    def delayed(x, d):      # x(t − d) per trial, linear interpolation, held before the start
        out = []
        for seg in split(x):
            t = np.arange(len(seg), dtype=np.float64)
            out.append(np.interp(t - d / flat.dt, t, seg.numpy().astype(np.float64)))
        return torch.as_tensor(np.concatenate(out), dtype=x.dtype)

    def limits(scale, **kw):
        fitted.clear()
        fits = P.InjectionFits(injected_limit=lambda g0, se0, sr, th0, level: scale(th0), **stubs)
        return P.limits_by_injection(flat, s, base, base, held, 1e-6, analytic, fits=fits, **kw)

    tol = lambda j: 2e-3 * float(flat.tau[:, j].abs().max())
    out = limits(lambda th0: th0)            # every limit lies at its injection: one fit
    assert len(fitted) == 1 and set(out["torque_gain"]) == {"hip", "knee"} and set(out["actuation_delay"]) == {"knee"}
    te = flat.tau_e
    expect_hip = flat.tau[:, 0] - 0.3 * own[0] + 0.3 * te[:, 0]
    expect_knee = flat.tau[:, 1] - left[:, 1] + 0.6 * te[:, 1] + te[:, 1] - delayed(te[:, 1], 0.024)
    assert torch.allclose(fitted[0][:, 0], expect_hip, atol=tol(0))
    assert torch.allclose(fitted[0][:, 1], expect_knee, atol=tol(1))
    assert out["torque_gain"]["knee"]["injected_k"] == pytest.approx(1 / 0.4)
    assert out["torque_gain"]["knee"]["k_above"] == pytest.approx(1 / 0.4)
    d = out["actuation_delay"]["knee"]
    # scaled from the larger of the injected and the recovered delay (a delay already in the data adds to it)
    assert d["injected_d"] == pytest.approx(0.024) and d["d_limit"] == pytest.approx(max(0.024, d["recovered_d"]))
    assert "recovered_d" in d and "passes_at_injection" in d and "limit" not in d
    out = limits(lambda th0: th0 / 4)        # far below: measured again at 1.2 times the first answer
    assert len(fitted) == 2
    d1 = max(1.2 * 0.024 / 4, 2 * flat.dt)   # at least two samples
    for j, th0, th1 in ((0, 0.3, 0.1), (1, 0.6, 0.18)):       # 1.2 θ0 / 4, at least 0.1
        assert torch.allclose(fitted[1][:, j] - fitted[0][:, j], (th1 - th0) * te[:, j]
                              + (j == 1) * (delayed(te[:, 1], 0.024) - delayed(te[:, 1], d1)), atol=tol(j))
        v = out["torque_gain"][flat.joints[j]]
        assert v["injected_k"] == pytest.approx(1 / (1 - th1)) and v["first_injection"]["injected_k"] == \
            pytest.approx(1 / (1 - th0))
    assert out["actuation_delay"]["knee"]["injected_d"] == pytest.approx(d1)
    # the gain alone: no delay written, and the delay's limit left as computed
    out = limits(lambda th0: th0, delay=False)
    assert out["actuation_delay"] == {} and torch.allclose(fitted[0][:, 0], expect_hip, atol=tol(0))
    assert P.limits_by_injection(flat, s, None, base, held, 1e-6, analytic) == {"torque_gain": {},
                                                                                  "actuation_delay": {}}


def test_the_delays_detection_limit_follows_the_rate_of_the_controllers_own_variation():
    """The shortest delay d that can show: the gain's arithmetic with the rate ȯ of the controller's own
    variation in place of o (a delay changes the joint torque by τ_e(t) − τ_e(t−d) ≈ d τ̇_e). Checked against the
    sampling-dominated closed form, and a faster own variation (same size) gives a shorter limit; the torque
    sensor's white noise, which a delay shifts without identifying anything, hardly moves it."""
    from exolan.data import savgol_derivative
    from exolan.diagnose import limits as P
    from exolan.diagnose.flat import exo_copy

    sigma_eps = 0.02
    eps = torch.as_tensor(np.random.default_rng(4).normal(0, sigma_eps, (12000, 2)), dtype=torch.float32)
    predict = lambda model, flat, idx: flat.tau[idx] - eps[idx] * flat.mass[idx, None]    # noqa: E731
    s = Settings(n_boot=300)
    flat = _assisted_pair(share=0.2, own_sd=1.0, seed=3)
    held = flat.index("held")
    out = P.delay_detection_limit(flat, None, held, None, 0.0, s, predict)
    assert set(out) == {"hip"}
    v = out["hip"]
    own = (flat.tau_e[:, 0] - exo_copy(flat, 0).tau_e[:, 0]).numpy()
    rate = np.concatenate([savgol_derivative(x, flat.dt) for x in np.split(own, np.cumsum(flat.lengths)[:-1])])
    x = rate[held.numpy()] / 70.0
    P_rate = np.mean(x ** 2)
    expect = 2 * 1.96 * np.sqrt(P_rate) * sigma_eps / np.sqrt(len(held)) / P_rate
    assert 0.75 * expect < v["d_limit"] < 1.33 * expect
    # at the decision's own level (the single-term test's α/m, here m = 12) the limit is the one it can reach:
    # sampling-dominated (σ_r = 0) it scales with the normal quantile (the exo-delay miss of the slow suite,
    # docs/DIAGNOSIS.md: a 22 ms delay beside a 5 %-level limit of 20 ms, rejected at 0.42 %)
    from scipy.stats import norm

    strict = P.delay_detection_limit(flat, None, held, None, 0.0, s, predict, level=0.05 / 12)["hip"]
    assert strict["d_limit"] / v["d_limit"] == pytest.approx(norm.ppf(1 - 0.05 / 24) / norm.ppf(0.975), rel=1e-6)
    assert strict["level"] == pytest.approx(0.05 / 12) and v["level"] == 0.05
    # the gain's limit on the same data is in other units (θ = 1 − 1/k) and set by o, not ȯ
    g = P.gain_detection_limit(flat, None, held, None, 0.0, s, predict)["hip"]
    assert g["rms_own"] == v["rms_own"] and g["theta_limit"] != v["d_limit"]
    # the same own variation, smoothed less (faster): its rate is larger, the delay limit shorter
    fast = _assisted_pair(share=0.2, own_sd=1.0, seed=3)
    for t0, T in zip(np.cumsum([0] + list(fast.lengths[:-1])), fast.lengths):
        o = own[t0:t0 + T]
        fast.tau_e[t0:t0 + T, 0] += torch.as_tensor(np.gradient(o) * 3.0, dtype=fast.tau_e.dtype)
    assert P.delay_detection_limit(fast, None, held, None, 0.0, s, predict)["hip"]["d_limit"] < v["d_limit"]
    # white sensor noise of 5 % of the own variation's size: a central difference read it as rate and shortened
    # the limit by 24 % (0.0120 to 0.0091 s); the data's derivative filter by 6 %
    noisy = _assisted_pair(share=0.2, own_sd=1.0, seed=3)
    noisy.tau_e[:, 0] += torch.as_tensor(np.random.default_rng(9).normal(0, 0.05 * own.std(), len(own)),
                                         dtype=noisy.tau_e.dtype)
    d_noisy = P.delay_detection_limit(noisy, None, held, None, 0.0, s, predict)["hip"]["d_limit"]
    assert d_noisy > 0.8 * v["d_limit"]


def test_the_gains_screen_regresses_on_the_controllers_own_variation_that_the_base_leaves(monkeypatch):
    """A fitted base has absorbed (k − 1) times the exo torque's copy of the joint torque; its residual holds
    (k − 1) times the controller's own variation only. Regressed on the whole exo torque (90 % copy here) the
    post-hoc θ would shrink to the own share; the screen's own-variation feature recovers it."""
    from exolan.diagnose import screen as S
    from exolan.diagnose.flat import exo_copy

    flat = _assisted_pair(share=0.3, own_sd=2.0, seed=5)
    own = flat.tau_e[:, 0] - exo_copy(flat, 0).tau_e[:, 0]
    assert 0.02 < float(own.var() / flat.tau_e[:, 0].var()) < 0.2
    theta = 0.4                                              # k = 1/(1 − θ) ≈ 1.67
    eps = torch.as_tensor(np.random.default_rng(6).normal(0, 0.01, (12000, 2)), dtype=torch.float32)
    resid = eps * flat.mass[:, None]
    resid[:, 0] += theta * own
    monkeypatch.setattr(S, "predict", lambda model, f, idx: f.tau[idx] - resid[idx])
    sc = S.screen(None, flat, "torque_gain", 0, n_boot=200)
    assert sc["passes"] and sc.get("own_variation") is True and sc["ci"][0] > 0
    assert abs(sc["theta"] - theta) < 0.1 * theta
    # the whole exo torque alone: θ diluted to the own share, far from the planted one
    whole = S.features(None, flat, flat.index("train"), "torque_gain", 0)[0][1][:, 0]
    r_tr = resid[flat.index("train"), 0].numpy()
    assert abs(float(whole @ r_tr / (whole @ whole))) < 0.3 * theta


def test_the_screen_keeps_a_damping_that_the_base_absorbed_on_one_task_but_not_on_another(monkeypatch):
    """A base absorbs an effect unevenly across tasks; the residual's share of a knee damping differs by task.
    Here a fast task (calisthenics, q̇ 4x squat's) holds a noisy, segment-specific share (θ +0.3 on the training
    rows, −0.2 held out) and the slow squat the whole 2 N m s/rad. One θ for all data is set by the fast task and
    loses held-out accuracy; one θ per task recovers squat's and helps (measured in a world: notes on issue 7)."""
    from exolan.diagnose import screen as S

    rng = np.random.default_rng(8)
    trials = []
    for task, speed in (("calisthenics", 4.0), ("squat", 1.0)):
        for rep in (1, 2):
            for t in leg_pair(T=3000, seed=rep + 10 * int(speed)):
                t.task, t.name = task, f"{task}_{rep}_1"
                t.qd = speed * np.convolve(rng.normal(0, 1, 3040), np.hanning(41), "same")[20:-20, None] * [1, 1] / 4
                trials.append(t)
    flat = prepare(trials)
    held = torch.zeros(len(flat.tau), dtype=torch.bool)
    held[flat.index("held")] = True
    fast = torch.as_tensor(np.array([flat.trial_meta[i]["task"] == "calisthenics" for i in flat.trial.numpy()]))
    theta = torch.where(fast, torch.where(held, -0.2, 0.3), 2.0).to(flat.tau.dtype)
    resid = torch.zeros_like(flat.tau)
    resid[:, 1] = theta * flat.qd[:, 1]
    resid += torch.as_tensor(rng.normal(0, 0.05, resid.shape), dtype=resid.dtype) * flat.mass[:, None]
    monkeypatch.setattr(S, "predict", lambda model, f, idx: f.tau[idx] - resid[idx])
    sc = S.screen(None, flat, "viscous_damping", 1, n_boot=200)
    assert sc["pooled"]["gain"] < 0                      # one θ for all data: worse held out
    assert sc["passes"] and sc["form"] == "per group" and sc["gain"] > 0
    assert sc["by_group"]["theta"]["squat"] == pytest.approx(2.0, rel=0.05)
    assert sc["by_group"]["theta"]["calisthenics"] == pytest.approx(0.3, abs=0.05)
    # a residual that asks for negative damping on every task: each group's θ is held at 0, the candidate dropped
    resid[:, 1] = -0.5 * flat.qd[:, 1]
    sc = S.screen(None, flat, "viscous_damping", 1, n_boot=200)
    assert not sc["passes"] and "unphysical sign" in sc["reason"] and set(sc["by_group"]["theta"].values()) == {0.0}


def test_a_nested_rival_pair_that_held_out_data_cannot_separate_takes_the_simpler_term():
    """Stribeck (Fs e^{-(v/vs)^2}) is Coulomb friction as vs → ∞: an inseparable pair takes Coulomb; a set
    that is not nested (delay and damping) has no such choice and stays ambiguous."""
    from exolan.diagnose.candidates import nested_choice

    c, s = dict(effect="coulomb_friction"), dict(effect="stribeck_friction")
    assert nested_choice([s, c]) is c and nested_choice([c, s]) is c
    assert nested_choice([dict(effect="actuation_delay"), dict(effect="viscous_damping")]) is None
    assert nested_choice([s, dict(effect="viscous_damping")]) is None


def test_a_term_outdone_by_an_exo_driven_rival_that_failed_its_null_is_rejected():
    """Rule 6 with a doubted rival: a hip strap that passes alone is rejected where a hip torque gain describes
    the held-out data better but failed its null; not where the gain failed another rule too, nor where the two
    cannot be separated, nor for a damping whose rival delay failed its null (a damping is not exo-driven)."""
    from exolan.diagnose.nulls import outdone_by_a_doubted_rival

    rng = np.random.default_rng(0)
    e0 = 1.0 + rng.random(3000)
    null_only = dict(status="rejected", passes=False, passes_gain=True, passes_floor=True, identifiable=True,
                     passes_invariance=True, passes_null=False)

    def verdicts(rival_errors, **rival_changes):
        res = [dict(effect="strap_compliance", joint="hip", passes=True),
               dict(effect="torque_gain", joint="hip", **{**null_only, **rival_changes}),
               dict(effect="viscous_damping", joint="knee", passes=True),
               dict(effect="actuation_delay", joint="knee", **null_only)]
        errs = {("strap_compliance", "hip"): e0 - 0.05, ("torque_gain", "hip"): rival_errors,
                ("viscous_damping", "knee"): e0 - 0.05, ("actuation_delay", "knee"): e0 - 0.4}
        outdone_by_a_doubted_rival(res, lambda eff, nm: errs.get((eff, nm)),
                                   lambda a, b: paired_gain(a, b, Settings(n_boot=200)))
        return {(e["effect"], e["joint"]): e for e in res}

    out = verdicts(e0 - 0.4)
    strap = out[("strap_compliance", "hip")]
    assert strap["status"] == "rejected" and not strap["passes"]
    assert "torque_gain" in strap["reason"] and strap["rivals"]["torque_gain"]["ci"][1] < 0
    damping = out[("viscous_damping", "knee")]
    assert damping.get("status") is None and damping["passes"]
    # the gain failed another rule as well: nothing says the signal is the exo torque's or not
    assert verdicts(e0 - 0.4, passes_invariance=False)[("strap_compliance", "hip")].get("status") is None
    # the two describe the held-out data alike: no better description has failed
    tie = e0 - 0.05 + 0.01 * rng.standard_normal(e0.size)
    assert verdicts(tie)[("strap_compliance", "hip")].get("status") is None


def test_the_report_shows_rule_3s_nulls_of_an_exo_driven_finding():
    """A finding driven by the recorded exo torque lists every null it was held against (rule 3), the
    own-variation one with its own k, and marks a null that was not passed."""
    from exolan.diagnose.report import _evidence_lines

    f = dict(nulls=[dict(gain=2.66e-5, ci=[1.27e-5, 3.94e-5], passes=True, future_lag_s=0.02),
                    dict(gain=3.0e-5, ci=[-4.3e-6, 6.0e-5], passes=False, own_variation_only=True, estimate=1.394)])
    lines = _evidence_lines(f)
    assert len(lines) == 2
    assert "20 ms in the future by 2.66e-05" in lines[0] and "not passed" not in lines[0]
    assert "own variation alone (k 1.39)" in lines[1] and lines[1].endswith("(not passed)")
    assert _evidence_lines({}) == []


def test_rule_3s_future_torque_null_for_a_delay_reaches_no_causal_delay():
    """The delay term on the exo torque taken L samples ahead applies τ_e(t + L − d). Free up to max_delay
    (100 ms) with L = 80 ms, that null reaches a causal delay of 20 ms — the effect under test; held at d ≤ L
    its applied torque is at most the present one."""
    from exolan.diagnose.nulls import future_null

    flat = _assisted_pair(share=0.3, own_sd=2.0, seed=5)
    base = make_base(flat, hidden=8)
    s = Settings(max_delay=0.1)
    lag = 16                                                 # 80 ms at 200 Hz
    null, adv, what, _ = future_null(base, flat, dict(effect="actuation_delay"), 0, lag, s)
    free = extend(base, adv, [("actuation_delay", 0)], max_delay=s.max_delay)
    assert what["future_lag_s"] == pytest.approx(0.08)
    rows = torch.arange(100, flat.lengths[0] - 100)         # inside the first trial: nothing clamped

    def applied_at_longest_delay(model):
        with torch.no_grad():
            model.delay_raw[0] = 20.0                        # sigmoid → 1: the longest delay allowed
            return model.applied_exo(*adv.exo_lagged(rows))[0][:, 0]

    te = flat.tau_e[:, 0]
    torch.testing.assert_close(applied_at_longest_delay(free), te[rows - 4], rtol=0, atol=1e-4)   # 20 ms ago
    torch.testing.assert_close(applied_at_longest_delay(null), te[rows], rtol=0, atol=1e-4)       # now
    assert float(null.delay().detach()[0]) <= 0.08 + 1e-9


def test_the_own_variation_null_asks_for_a_gain_on_the_same_side_of_1():
    """Rule 3's own-variation null for a torque gain passes only when its gain beats the reference beyond the
    refit noise and its k lies on the same side of 1 as the whole term's (a spurious clean-world hip gain of
    1.295 beside an own-variation k of 0.845 is not a sensor's scale error)."""
    from exolan.diagnose.rules import own_variation_passes as _own_variation_passes

    rng = np.random.default_rng(0)
    g = dict(gain=3e-5, ci=[1e-5, 5e-5], draws=rng.normal(3e-5, 1e-5, 2000))
    assert _own_variation_passes(g, 1e-6, 1.39, 1.87)
    assert _own_variation_passes(g, 1e-6, 0.7, 0.8)
    assert not _own_variation_passes(g, 1e-6, 0.845, 1.295)
    assert not _own_variation_passes(g, 1e-6, 1.2, 0.9)
    assert not _own_variation_passes(g, 5e-5, 1.39, 1.87)            # within the refit noise
    assert not _own_variation_passes(dict(g, ci=[-1e-6, 5e-5]), 1e-6, 1.39, 1.87)


def test_the_reports_limits_table_says_none_where_no_gain_shows_and_lists_each_injection():
    """A measured gain limit that the injection could not reach is "none" in the table, and its line says so; a
    finite one is shown with the injection that measured it and the computed limit beside it."""
    from exolan.diagnose.report import _limit_lines

    sizes = dict(rms_exo=5.0, copy_share=0.94, rms_own=1.3)
    inj = dict(method="injection", injected_k=5.0, recovered_k=2.5, injected_gain=-2e-5, injected_gain_ci=[-1e-4, 1e-4],
               passes_at_injection=False, computed=dict(k_below=0.47, k_above=float("inf")))
    gain = {"hip": dict(sizes, k_below=0.0, k_above=float("inf"), **inj),
            "knee": dict(sizes, k_below=0.8, k_above=1.25, **dict(inj, injected_k=1.6, recovered_k=1.5,
                                                                      injected_gain=5e-5, passes_at_injection=True))}
    text = "\n".join(_limit_lines({"torque_gain": gain, "actuation_delay": {"hip": dict(sizes, d_limit=0.02)}}))
    assert "| hip | 5 | 94 % | 1.3 | none | none | 20 |" in text
    assert "| knee | 5 | 94 % | 1.3 | 0.8 | 1.25 | — |" in text
    assert "measured, not computed" in text
    hip_line = next(x for x in text.splitlines() if x.startswith("- hip"))
    assert "no gain up to that size shows" in hip_line and "does not pass" in hip_line
    knee_line = next(x for x in text.splitlines() if x.startswith("- knee"))
    assert "a gain of 1.6 written into the data" in knee_line and "no gain up to" not in knee_line
    # a measured delay limit: its line beside the gain's; "none" where the injected delay did not show
    dinj = dict(method="injection", injected_d=0.03, recovered_d=0.026, injected_gain=4e-5,
                injected_gain_ci=[1e-5, 7e-5], passes_at_injection=True, computed=dict(d_limit=0.016))
    text = "\n".join(_limit_lines({"torque_gain": gain, "actuation_delay": {
        "hip": dict(sizes, d_limit=0.021, **dinj),
        "knee": dict(sizes, d_limit=float("inf"), **dict(dinj, injected_gain=-1e-5, passes_at_injection=False))}}))
    assert "| hip | 5 | 94 % | 1.3 | none | none | 21 |" in text and "| knee | 5 | 94 % | 1.3 | 0.8 | 1.25 | none |" in text
    assert "The delay's limit is measured the same way" in text
    lines = [x for x in text.splitlines() if "ms written into the data" in x]
    assert len(lines) == 2 and "a delay of 30 ms written into the data was recovered as 26 ms" in lines[0]
    assert "computed at the base's misfit the limit would be 16 ms" in lines[0]
    assert "no delay up to that size shows" in lines[1] and "does not pass rules 1 and 2" in lines[1]
