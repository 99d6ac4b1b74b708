"""Diagnosis building blocks, the base model: the other leg's load, the pelvis terms, the extended model's inertia,
the refit's averaging, the fit weights and the held-out groups, a given run's base. Fast (seconds)."""
import copy

import numpy as np
import pytest
import torch

from exolan.diagnose.base import inertia_of, make_base
from exolan.diagnose.export import extend
from exolan.diagnose.fit import train
from exolan.diagnose.flat import DTYPE, prepare, sample_groups

from diagnose_helpers import leg_pair


def test_other_leg_load_is_paired_by_recording_and_normalised_by_weight():
    trials = leg_pair()
    flat = prepare(trials)
    assert flat.has_partner
    T = len(trials[0].q)
    np.testing.assert_allclose(flat.f_o[:T].numpy(), trials[1].f_v / (70.0 * 9.81), rtol=1e-5)
    np.testing.assert_allclose(flat.f_o[T:].numpy(), trials[0].f_v / (70.0 * 9.81), rtol=1e-5)
    assert flat.forces(torch.arange(5)).shape == (5, 11)    # f_v, f_o, the other hip's q, q̇, q̈, 5 surge features, x_cop
    np.testing.assert_allclose(flat.kin_o[:T, 1].numpy(), trials[1].qd[:, 0], rtol=1e-5)
    base = make_base(flat, hidden=8)
    assert base.body_load is not None and base.lim is not None
    # a single side has no partner: the base gets no load term
    single = prepare(trials[:1])
    assert not single.has_partner and make_base(single, hidden=8).body_load is None


def test_pelvis_surge_sums_both_insoles_and_enters_the_inverse_dynamics_as_mass_accel_times_moment():
    """(And the centre-of-pressure lever.) Surge features: Σ over both legs of f_v/G ⊙ [1, sin q_h, sin q_h cos q_k, cos q_h sin q_k, x_cop]; the term
    adds G (features · β) (C ψ(q)) to the inverse dynamics (zero while C = 0) and forward dynamics inverts it."""
    trials = leg_pair()
    rng = np.random.default_rng(3)
    for t in trials:
        t.cop = np.stack([rng.uniform(0.0, 0.25, len(t.q)), np.zeros(len(t.q))], 1)
    flat = prepare(trials)
    T = len(trials[0].q)

    def phi(t):
        qh, qk = t.q[:, 0], t.q[:, 1]
        return (t.f_v / 9.81)[:, None] * np.stack([np.ones(T), np.sin(qh), np.sin(qh) * np.cos(qk),
                                                   np.cos(qh) * np.sin(qk), t.cop[:, 0]], 1)
    both = phi(trials[0]) + phi(trials[1])
    np.testing.assert_allclose(flat.surge[:T].numpy(), both, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(flat.surge[T:].numpy(), both, rtol=1e-4, atol=1e-3)   # one pelvis, both legs

    plain = make_base(flat, hidden=8, seed=2, pelvis_surge=False)
    surged = make_base(flat, hidden=8, seed=2)
    assert plain.surge is None and surged.surge is not None
    surged.load_state_dict(plain.state_dict(), strict=False)
    b = torch.arange(0, 60)
    z = plain.z_of(flat.trial[b])
    args = (flat.q[b], flat.qd[b], flat.qdd[b], z, flat.forces(b))
    with torch.no_grad():
        torch.testing.assert_close(surged.inverse(*args), plain.inverse(*args))
        surged.surge.C.copy_(torch.tensor([[0.05, 0.02, -0.01], [0.0, -0.03, 0.01]]))
        tau = surged.inverse(*args)
        qh, qk = flat.q[b, 0], flat.q[b, 1]
        psi = torch.stack([torch.cos(qh), torch.cos(qh) * torch.cos(qk), torch.sin(qh) * torch.sin(qk)], -1)
        expect = 9.81 * (flat.surge[b] @ surged.surge.beta)[:, None] * (psi @ surged.surge.C.T)
        torch.testing.assert_close(tau - plain.inverse(*args), expect, rtol=1e-3, atol=1e-3)
        qdd = surged.forward_dynamics(flat.q[b], flat.qd[b], tau, z, flat.forces(b))
        torch.testing.assert_close(qdd, flat.qdd[b], rtol=1e-3, atol=1e-3)
        # the contact torque's part that follows the centre of pressure: − d ⊙ f_v x_cop (a contact torque)
        surged.cop_lever.copy_(torch.tensor([0.5, -1.0]))
        moved = surged.inverse(*args) - tau
        torch.testing.assert_close(moved, -torch.tensor([0.5, -1.0]) * (flat.f_v[b] * flat.x_cop[b])[:, None],
                                   rtol=1e-3, atol=1e-3)
        np.testing.assert_allclose(flat.x_cop[:T].numpy(), trials[0].cop[:, 0], rtol=1e-5)
    # without a partner there is no pelvis estimate: no term
    single = make_base(prepare(trials[:1]), hidden=8)
    assert single.surge is None and single.cop_lever is None and not single.lim_cop


def test_pelvis_tilt_is_a_coordinate_shift_by_the_other_hip():
    """The optional tilt term: zero leaves the model unchanged; non-zero evaluates the Lagrangian at
    q − τ_t q_o e₀ (and rates), so forward dynamics inverts inverse dynamics and the shift reaches q̈."""
    flat = prepare(leg_pair())
    torch.manual_seed(0)
    plain = make_base(flat, hidden=8, seed=2)
    tilted = make_base(flat, hidden=8, seed=2, pelvis_tilt=True)
    tilted.load_state_dict(plain.state_dict(), strict=False)
    b = torch.arange(0, 40)
    z = plain.z_of(flat.trial[b])
    args = (flat.q[b], flat.qd[b], flat.qdd[b], z, flat.forces(b))
    with torch.no_grad():
        assert torch.allclose(plain.inverse(*args), tilted.inverse(*args))
        tilted.tilt.fill_(0.3)
        tau = tilted.inverse(*args)
        assert not torch.allclose(tau, plain.inverse(*args))
        qdd = tilted.forward_dynamics(flat.q[b], flat.qd[b], tau, z, flat.forces(b))
        torch.testing.assert_close(qdd, flat.qdd[b], rtol=1e-3, atol=1e-3)
        # the same as the plain model at shifted coordinates (the LIM and load term see the measured q)
        sh = 0.3 * flat.kin_o[b]
        e0 = torch.tensor([1.0, 0.0])
        q_a, qd_a, qdd_a = (flat.q[b] - sh[:, :1] * e0, flat.qd[b] - sh[:, 1:2] * e0, flat.qdd[b] - sh[:, 2:3] * e0)
        H, c, g = plain.delan.terms(q_a, qd_a, z)
        g = g * (1.0 + plain.body_load * flat.f_o[b, None])
        expect = (H @ qdd_a.unsqueeze(-1)).squeeze(-1) + c + g - plain.lim.contact_torque(
            flat.q[b], plain._lim_context(flat.q[b], z, flat.forces(b)), flat.f_v[b])
        torch.testing.assert_close(tau, expect, rtol=1e-4, atol=1e-4)


def test_forward_error_is_inertia_inverse_of_torque_error():
    """The acceleration term of the fits: q̈(τ) − q̈ = H⁻¹ (τ − τ̂(q̈)), with the LIM and the load term active."""
    flat = prepare(leg_pair())
    base = make_base(flat, hidden=8, seed=1)
    with torch.no_grad():
        base.body_load.fill_(0.7)
        b = torch.arange(0, 50)
        z = base.z_of(flat.trial[b])
        f = flat.forces(b)
        tau_hat = base.inverse(flat.q[b], flat.qd[b], flat.qdd[b], z, f)
        qdd_fd = base.forward_dynamics(flat.q[b], flat.qd[b], flat.tau[b], z, f)
        H = inertia_of(base, flat.q[b], z)
        rhs = torch.linalg.solve(H.double(), (flat.tau[b] - tau_hat).double().unsqueeze(-1))[..., 0]
        # the fits take H from the inverse dynamics itself: the same H and τ̂
        tau_shared, H_shared = base.inverse_inertia(flat.q[b], flat.qd[b], flat.qdd[b], z, f)
    np.testing.assert_allclose((qdd_fd - flat.qdd[b]).double().numpy(), rhs.numpy(), rtol=2e-3, atol=2e-3)
    assert torch.equal(H_shared, H) and torch.equal(tau_shared, tau_hat)


def test_extended_model_shares_the_inertia_at_its_physical_coordinates():
    """The fits' acceleration term takes H where the inverse dynamics evaluated it: after the encoder offset."""
    flat = prepare(leg_pair())
    base = make_base(flat, hidden=8, seed=1)
    ext = extend(base, flat, [("encoder_offset", 0)], init={"encoder_offset": 0.1})
    with torch.no_grad():
        b = torch.arange(0, 50)
        z = base.z_of(flat.trial[b])
        args = (flat.q[b], flat.qd[b], flat.qdd[b], z, flat.forces(b), flat.tau_e[b])
        tau, H = ext.inverse_inertia(*args)
        assert torch.equal(tau, ext.inverse(*args))
        torch.testing.assert_close(H, inertia_of(ext, flat.q[b] - torch.tensor([0.1, 0.0]), z))
        assert not torch.allclose(H, inertia_of(ext, flat.q[b], z))


def test_refit_averages_the_networks_but_not_the_physical_scalars(arm):
    base = make_base(arm, hidden=8, seed=0)
    ext = extend(base, arm, [("viscous_damping", 0)])
    snaps = []

    def grab(step, loss):
        snaps.append((copy.deepcopy(ext.base.delan.V[0].weight.detach()), float(ext.damping_diag[0].detach())))

    steps = 10
    train(ext, arm, steps, batch=256, seed=0, average=True, progress=grab)
    mean_w = torch.stack([w for w, _ in snaps[steps // 2:]]).mean(0)
    torch.testing.assert_close(ext.base.delan.V[0].weight.detach(), mean_w, rtol=1e-5, atol=1e-6)
    assert float(ext.damping_diag[0].detach()) == pytest.approx(snaps[-1][1])   # last iterate, not the mean
    assert snaps[-1][1] != pytest.approx(np.mean([d for _, d in snaps[steps // 2:]]))


def test_held_out_groups_fall_back_to_trials_for_a_single_task(arm):
    held = arm.index("held")
    g, kind = sample_groups(arm, held)
    assert kind == "trial" and len(set(g)) == 2


def test_fit_weights_follow_the_inverse_misfit_of_each_trial_and_joint(arm):
    """Weighted least squares (fit.misfit_weights): a trial whose residual variance is 100x the others' gets
    about 1/50 of their weight (halfway shrinkage to the median); joints are weighted separately; with a
    single trial everything stays 1; the weights the fits use average 1 over each joint's training rows."""
    from exolan.diagnose.fit import misfit_weights, trial_weights

    rng = np.random.default_rng(0)
    trial = np.repeat(np.arange(3), 2000)
    r = rng.standard_normal((6000, 2))
    r[trial == 1, 0] *= 10.0                     # trial 1: hip misfit 10x (variance 100x); knee as the others
    w = trial_weights(r, trial, 3)
    assert w[1, 0] / w[0, 0] == pytest.approx(1 / 50.5, rel=0.1)
    assert w[1, 1] / w[0, 1] == pytest.approx(1.0, rel=0.1)
    np.testing.assert_array_equal(trial_weights(r[:2000], trial[:2000], 3), np.ones((3, 2)))
    base = make_base(arm, hidden=8, seed=0)
    wf = misfit_weights(base, arm)
    tr = arm.index("train")
    assert wf.shape == arm.tau.shape and torch.all(wf > 0)
    np.testing.assert_allclose(wf[tr].mean(0).numpy(), 1.0, rtol=1e-4)


def test_fit_weights_count_the_misfit_no_candidate_explains(arm):
    """`weights.explained_misfit_weights`: a hip damping in every trial misfits the faster trial most, and the
    base's misfit alone down-weights that trial with the effect in it; less what the candidates' columns
    explain, both trials weigh about the same. A misfit no candidate has the shape of (noise 10x in one trial)
    still down-weights its trial as `fit.misfit_weights` does."""
    from exolan.diagnose.fit import misfit_weights, predict
    from exolan.diagnose.weights import explained_misfit_weights

    base = make_base(arm, hidden=8, seed=0)
    every = torch.arange(arm.q.shape[0])
    fitted = predict(base, arm, every)
    rng = np.random.default_rng(1)
    hip = lambda f: float(f[arm.trial == 1, 0].mean() / f[arm.trial == 0, 0].mean())
    effects = ("viscous_damping", "coulomb_friction", "torque_bias")

    damped = copy.copy(arm)
    noise = torch.as_tensor(0.2 * rng.standard_normal(arm.tau.shape), dtype=arm.tau.dtype)
    damped.tau = fitted + noise
    damped.tau[:, 0] += 3.0 * arm.qd[:, 0]              # the faster trial (1) moves 2.7x as fast at the hip
    assert hip(misfit_weights(base, damped)) < 0.6      # two trials: the shrinkage keeps it above 1/3
    assert hip(explained_misfit_weights(base, damped, effects, [0, 1])) == pytest.approx(1.0, abs=0.15)

    # a damping in one subject only: one shared column would move half its misfit to the other subject's trials
    two = copy.copy(arm)
    two.trial_meta = [dict(m, subject=f"S0{i + 1}") for i, m in enumerate(arm.trial_meta)]
    two.tau = fitted + noise
    two.tau[:, 0] += 3.0 * arm.qd[:, 0] * (arm.trial == 1)
    assert hip(misfit_weights(base, two)) < 0.6
    assert hip(explained_misfit_weights(base, two, effects, [0, 1])) == pytest.approx(1.0, abs=0.15)

    noisy = copy.copy(arm)
    noisy.tau = fitted + noise * torch.where(arm.trial == 1, 10.0, 1.0)[:, None]
    w_plain, w_left = misfit_weights(base, noisy), explained_misfit_weights(base, noisy, effects, [0, 1])
    assert hip(w_left) < 0.4
    assert hip(w_left) == pytest.approx(hip(w_plain), rel=0.1)


def test_decisions_weight_held_out_errors_as_the_fits_do_and_users_see_them_unweighted(arm):
    """`_held_errors`: the user's error is the plain sum over joints of the mass-normalised squared torque
    error; the decision's weights each joint's error by its trial's fit weight; without weights both agree."""
    from exolan.diagnose.fit import sq_errors
    from exolan.diagnose.refits import held_errors as _held_errors

    base = make_base(arm, hidden=8, seed=0)
    held = arm.index("held")
    e = sq_errors(base, arm, held)
    w = np.ones_like(e)
    w[:, 1] = 0.25                                   # knee errors count a quarter
    w[arm.trial[held].numpy() == 1, 0] = 4.0         # the hip of trial 1 four times
    user, decision = _held_errors(base, arm, held, w)
    np.testing.assert_allclose(user, e.sum(1))
    np.testing.assert_allclose(decision, (e * w).sum(1))
    assert not np.allclose(user, decision)
    user0, decision0 = _held_errors(base, arm, held, None)
    np.testing.assert_array_equal(user0, decision0)


def test_a_given_runs_base_starts_as_the_run_and_learns_the_centre_of_pressure_part_of_the_contact_torque():
    """`--model RUN`: the pooled base predicts exactly what the run predicts until the data move it; its added
    insole correction ΔB(q, x_cop) f_v then takes up a contact torque that depends on the centre of pressure
    nonlinearly, which the run's B(q, z) and the linear CoP lever cannot (the lever alone is the control)."""
    from exolan.diagnose.base import PooledContext, inertia_of
    from exolan.diagnose.fit import predict, sq_errors
    from exolan.models import build_model

    torch.manual_seed(0)
    T = 1500
    trials = leg_pair(T=T)
    run = build_model("delan", lim=True, hidden=16).to(DTYPE)
    rng = np.random.default_rng(6)
    for t in trials:
        x = np.convolve(rng.uniform(-0.05, 0.2, T + 40), np.hanning(9) / np.hanning(9).sum(), "same")[20:-20]
        t.cop = np.stack([x, np.zeros(T)], 1)
        args = [torch.as_tensor(v, dtype=DTYPE) for v in (t.q, t.qd, t.qdd)]
        with torch.no_grad():
            tau_run = run.inverse(*args, None, torch.as_tensor(t.f_v, dtype=DTYPE)).numpy()
        lever = 0.04 * np.tanh((x - 0.07) / 0.03)[:, None] * np.array([1.0, -0.5])   # m, odd in the CoP's travel
        t.tau = tau_run - lever * t.f_v[:, None]
    flat = prepare(trials)
    idx = flat.index("all")
    errs = {}
    for lim_cop in (False, True):
        base = PooledContext(copy.deepcopy(run), torch.zeros(2, 0, dtype=DTYPE), other_leg_load=True, lim_cop=lim_cop)
        assert (base.lim_cop is not None) == lim_cop
        with torch.no_grad():
            start = predict(base, flat, idx)
        with torch.no_grad():
            own = run.inverse(flat.q[idx], flat.qd[idx], flat.qdd[idx], None, flat.f_v[idx])
        torch.testing.assert_close(start, own)
        # the inertia the fits' acceleration term reuses is the run's own H(q, z)
        tau_h, H = base.inverse_inertia(flat.q[idx], flat.qd[idx], flat.qdd[idx], base.z_of(flat.trial[idx]),
                                        flat.forces(idx))
        torch.testing.assert_close(tau_h, base.inverse(flat.q[idx], flat.qd[idx], flat.qdd[idx],
                                                       base.z_of(flat.trial[idx]), flat.forces(idx)))
        torch.testing.assert_close(H, inertia_of(base, flat.q[idx], base.z_of(flat.trial[idx])))
        train(base, flat, 600, lr=3e-3, batch=1024, seed=0, w_acc=0.0)
        errs[lim_cop] = sq_errors(base, flat, flat.index("held")).sum(1).mean()
    assert errs[True] < 0.3 * errs[False], errs
