"""The simulated world: physics self-checks, physiological ranges, effect semantics, the writer."""
from __future__ import annotations

import json

import numpy as np
import pytest

from exolan.world import PAPER_TRAIN_TASKS, TASKS, leg_params, make_users, simulate, simulate_trial
from exolan.world import dynamics as dyn
from exolan.world.anthropometry import G, User


@pytest.fixture(scope="module")
def legs():
    users = make_users(6, np.random.default_rng(3))
    return [leg_params(u, exo=True, seg_scale=u.style["seg_scale"]) for u in users]


def test_task_list_has_28_tasks_in_three_groups():
    assert len(TASKS) == 28
    assert set(TASKS.values()) == {"cyclic", "impedance", "unstructured"}
    assert set(PAPER_TRAIN_TASKS) <= set(TASKS)
    for t in ("run", "squat", "ball_toss", "sit_to_stand", "lunge", "stairs_up", "stairs_down",
              "incline_walk", "jump_forward", "side_shuffle"):
        assert t in TASKS


def test_users_span_50_to_100_kg():
    users = make_users(21, np.random.default_rng(0))
    m = [u.mass for u in users]
    assert 50 <= min(m) and max(m) <= 100 and max(m) - min(m) > 15
    assert len({u.name for u in users}) == 21


def test_segment_parameters_follow_the_tables(legs):
    u = User("X", 70.0, 1.75, {})
    p = leg_params(u, exo=False)
    assert p.m1 == pytest.approx(7.0)                       # Winter: thigh 10 % of body mass
    assert p.m2 == pytest.approx(70 * (0.0465 + 0.0145))     # shank + foot
    assert p.l1 == pytest.approx(0.245 * 1.75)
    assert 0 < p.beta2 < 0.2                                 # foot mass puts the COM slightly forward
    pe = leg_params(u, exo=True)
    assert pe.m1 > p.m1 and pe.m2 > p.m2


def test_mass_matrix_symmetric_positive_definite(legs):
    rng = np.random.default_rng(0)
    q = rng.uniform(-2.5, 2.5, size=(500, 2))
    for p in legs:
        H = dyn.mass_matrix(p, q)
        np.testing.assert_allclose(H, np.swapaxes(H, -1, -2), atol=0)
        assert np.linalg.eigvalsh(H).min() > 1e-3


def test_coriolis_is_the_christoffel_form_of_H(legs):
    """c = Hdot qd - 1/2 d(qd^T H qd)/dq, checked by finite differences of H."""
    p = legs[0]
    rng = np.random.default_rng(1)
    q, qd = rng.uniform(-1, 1, 2), rng.uniform(-5, 5, 2)
    h = 1e-6
    dH = [(dyn.mass_matrix(p, q + h * e) - dyn.mass_matrix(p, q - h * e)) / (2 * h) for e in np.eye(2)]
    Hdot = dH[0] * qd[0] + dH[1] * qd[1]
    c_ref = Hdot @ qd - 0.5 * np.array([qd @ dH[k] @ qd for k in range(2)])
    np.testing.assert_allclose(dyn.coriolis(p, q, qd), c_ref, rtol=1e-6, atol=1e-8)


def test_gravity_is_the_gradient_of_the_potential(legs):
    p = legs[1]
    q = np.array([0.4, 0.9])
    h = 1e-6
    V = lambda x: dyn.energy(p, x, np.zeros(2))  # noqa: E731
    g_ref = np.array([(V(q + h * e) - V(q - h * e)) / (2 * h) for e in np.eye(2)])
    np.testing.assert_allclose(dyn.gravity(p, q), g_ref, rtol=1e-7)


def test_contact_torque_is_J_transpose_f(legs):
    """J from finite differences of a point fixed on the shank-foot body."""
    p = legs[2]
    q = np.array([0.3, 0.5])
    point = dyn.cop_point(p, q, np.array(0.1))
    knee = dyn.points(p, q)["knee"]
    th2 = q[0] - q[1]
    # body-2 coordinates of the point (along the shank, forward normal), then moved with q
    rel = point - knee
    along = rel @ np.array([np.sin(th2), -np.cos(th2)])
    fwd = rel @ np.array([np.cos(th2), np.sin(th2)])

    def fk(x):
        t2 = x[0] - x[1]
        return dyn.points(p, x)["knee"] + along * np.array([np.sin(t2), -np.cos(t2)]) + \
            fwd * np.array([np.cos(t2), np.sin(t2)])

    h = 1e-7
    J = np.stack([(fk(q + h * e) - fk(q - h * e)) / (2 * h) for e in np.eye(2)], axis=1)
    np.testing.assert_allclose(dyn.contact_jacobian(p, q, point), J, atol=1e-7)
    f = np.array([40.0, 700.0])
    np.testing.assert_allclose(dyn.contact_torque(p, q, point, f), J.T @ f, atol=1e-5)


def test_free_leg_conserves_energy(legs):
    """Hip fixed, zero torque, plain gravity: RK4 at 0.2 ms for 1 s keeps T + V constant."""
    p = legs[3]
    x = np.array([1.0, 1.2, 0.0, 0.0])

    def f(s):
        return np.concatenate([s[2:], dyn.forward_dynamics(p, s[:2], s[2:], np.zeros(2))])

    E0 = dyn.energy(p, x[:2], x[2:])
    h = 2e-4
    drift = vmax = 0.0
    for _ in range(5000):
        k1 = f(x); k2 = f(x + h / 2 * k1); k3 = f(x + h / 2 * k2); k4 = f(x + h * k3)  # noqa: E702
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        drift = max(drift, abs(dyn.energy(p, x[:2], x[2:]) - E0))
        vmax = max(vmax, np.abs(x[2:]).max())
    scale = (p.m1 + p.m2) * G * (p.l1 + p.l2)   # the energy the leg exchanges, ~ 100 J
    assert vmax > 3.0                          # it really swung
    assert drift < 1e-9 * scale


def test_inverse_dynamics_of_recorded_noise_free_kinematics_reproduces_total_torque(tmp_path):
    """Written CSV (noise-free) -> q, qd read back; with the true qdd and the unobserved pelvis
    motion (tilt, acceleration) and GRF, H qdd + c + g - J^T f equals the recorded
    moment x mass + exoskeleton torque to 1e-8. The chain hangs from the tilting pelvis, so
    the thigh's absolute angle is q_hip - tilt."""
    from exolan.data import load

    tasks = ["walk", "run", "squat", "cut"]
    simulate(tmp_path, users=2, tasks=tasks, seconds=3, seed=5, noise=False, progress=False)
    ds = load(tmp_path, cache=False)
    users = make_users(2, np.random.default_rng(np.random.SeedSequence([5, 0])))
    worst = 0.0
    for tr in ds:
        u = users[int(tr.subject[1:]) - 1]
        _, _, truth = simulate_trial(u, tr.task, 3, seed=5, noise=False)
        s = "lr".index(tr.side)
        p = truth["world"].p
        np.testing.assert_allclose(tr.q, truth["q"][:, s], atol=1e-13)
        q, qd = tr.q.copy(), tr.qd.copy()
        q[:, 0] -= truth["tilt"]
        qd[:, 0] -= truth["tilt_d"]
        qdd = truth["qdd"][:, s].copy()
        qdd[:, 0] -= truth["tilt_dd"]
        tau = dyn.inverse_dynamics(p, q, qd, qdd, truth["g_eff"], truth["f"][:, s], truth["point"][:, s])
        worst = max(worst, float(np.abs(tau - tr.tau).max()))
    assert worst < 1e-8


def _ranges(task, seconds=12, users=3):
    out = []
    for u in make_users(users, np.random.default_rng(11)):
        exo, mom, truth = simulate_trial(u, task, seconds, seed=2, noise=False)
        bw = u.mass * G
        hip = np.concatenate([mom["hip_flexion_l_moment"], mom["hip_flexion_r_moment"]])
        knee = np.concatenate([mom["knee_angle_l_moment"], mom["knee_angle_r_moment"]])
        fv = np.maximum(exo["insole_l_force_y"], exo["insole_r_force_y"]) / bw
        tot = (exo["insole_l_force_y"] + exo["insole_r_force_y"]) / bw
        out.append(dict(hip=(hip.min(), hip.max()), knee=(knee.min(), knee.max()), fv=fv.max(),
                        tot_mean=tot.mean(), exo=max(np.abs(exo[c]).max() for c in exo if "torque" in c)))
    return out


def test_walking_is_physiological():
    for r in _ranges("walk"):
        assert -1.3 < r["hip"][0] < -0.3 and 0.3 < r["hip"][1] < 1.3, r
        assert -1.3 < r["knee"][0] < -0.2 and r["knee"][1] < 1.0, r
        assert 1.0 < r["fv"] < 1.35, r           # ~1.1 BW double hump
        assert 0.9 < r["tot_mean"] < 1.15, r     # the feet carry the body on average
        assert 3.0 < r["exo"] <= 15.0, r


def test_running_and_landing_forces():
    for r in _ranges("run"):
        assert 2.0 < r["fv"] < 3.2, r
        assert r["hip"][1] - r["hip"][0] > 1.0
    for r in _ranges("jump_in_place"):
        assert 2.5 < 2 * r["fv"] < 5.0, r        # both feet land together


@pytest.mark.parametrize("task", sorted(TASKS))
def test_every_task_stays_in_human_ranges(task):
    for r in _ranges(task, seconds=8, users=2):
        assert -3.5 < r["hip"][0] and r["hip"][1] < 3.5, (task, r)
        assert -3.5 < r["knee"][0] and r["knee"][1] < 3.5, (task, r)
        assert r["fv"] < 5.0, (task, r)
        assert r["exo"] <= 15.0 + 1e-9


def _pair(effect, task="walk", seconds=4):
    u = make_users(1, np.random.default_rng(0))[0]
    a = simulate_trial(u, task, seconds, seed=1, noise=False)[2]
    b = simulate_trial(u, task, seconds, seed=1, noise=False, effects=[effect])[2]
    return a, b


def test_effect_viscous_damping_adds_b_qd_to_the_human_torque_on_one_joint():
    a, b = _pair("viscous_damping:knee:2.0")
    np.testing.assert_allclose(b["tau_h"][..., 1] - a["tau_h"][..., 1], 2.0 * a["qd"][..., 1], atol=1e-9)
    np.testing.assert_allclose(b["tau_h"][..., 0], a["tau_h"][..., 0], atol=1e-12)


def test_effect_coulomb_and_stribeck():
    a, b = _pair("coulomb_friction:hip:1.5")
    np.testing.assert_allclose(b["tau_h"][..., 0] - a["tau_h"][..., 0], 1.5 * np.tanh(a["qd"][..., 0] / 0.01),
                               atol=1e-9)
    a, b = _pair("stribeck_friction:knee:2.0,0.5")
    v = a["qd"][..., 1]
    np.testing.assert_allclose(b["tau_h"][..., 1] - a["tau_h"][..., 1],
                               2.0 * np.exp(-(v / 0.5) ** 2) * np.tanh(v / 0.01), atol=1e-9)


def test_effect_actuation_delay_applies_the_recorded_torque_late():
    a, b = _pair("actuation_delay:both:0.025")
    w = b["world"]
    t = b["t"]
    np.testing.assert_allclose(b["tau_e_rec"], a["tau_e_rec"], atol=1e-12)
    np.testing.assert_allclose(b["tau_e_app"], w.exo_command(t - 0.025), atol=1e-12)
    # recorded total = tau_h + recorded = tau_tot + recorded(t) - recorded(t - d)
    total = b["tau_h"] + b["tau_e_rec"]
    np.testing.assert_allclose(total - b["tau_tot"], b["tau_e_rec"] - w.exo_command(t - 0.025), atol=1e-9)
    assert np.abs(total - b["tau_tot"]).max() > 1.0   # a visible effect


def test_effect_observation_effects():
    a, b = _pair("encoder_offset:hip:0.05")
    np.testing.assert_allclose(b["q_meas"][..., 0] - a["q"][..., 0], 0.05, atol=1e-12)
    a, b = _pair("strap_compliance:knee:300")
    np.testing.assert_allclose(b["q_meas"][..., 1] - a["q"][..., 1], b["tau_e_app"][..., 1] / 300, atol=1e-12)
    w, t, h = b["world"], b["t"], 1e-5   # the measured velocity is the derivative of the measured angle
    dq = (w.evaluate(t + h)["q_meas"][..., 1] - w.evaluate(t - h)["q_meas"][..., 1]) / (2 * h)
    assert np.abs(dq - b["qd_meas"][..., 1]).max() < 1e-5 * np.abs(dq).max()
    a, b = _pair("torque_bias:hip:2.0")
    np.testing.assert_allclose(b["tau_e_rec"][..., 0] - b["tau_e_app"][..., 0], 2.0, atol=1e-12)
    a, b = _pair("torque_gain:knee:1.2")
    np.testing.assert_allclose(b["tau_e_rec"][..., 1], 1.2 * b["tau_e_app"][..., 1], atol=1e-12)
    a, b = _pair("backlash:hip:0.02")
    assert np.abs(b["q_meas"][..., 0] - a["q"][..., 0]).max() <= 0.01 + 1e-12
    a, b = _pair("payload:knee:2.0")
    assert np.abs(b["tau_tot"] - a["tau_tot"]).max() > 1.0


def test_effects_json_records_exactly_what_was_injected(tmp_path):
    simulate(tmp_path, users=3, tasks=["stand"], seconds=1, seed=0, progress=False,
             effects=["viscous_damping:knee:1.5:S02", "actuation_delay:both:0.02", "stribeck_friction:hip:1,0.3"])
    rec = json.loads((tmp_path / "effects.json").read_text())
    assert rec[0] == {"effect": "viscous_damping", "joint": "knee", "subjects": ["S02"], "value": 1.5,
                      "unit": "N m s/rad"}
    assert [(r["effect"], r["joint"]) for r in rec[1:3]] == [("actuation_delay", "hip"), ("actuation_delay", "knee")]
    assert rec[1]["subjects"] == ["S01", "S02", "S03"] and rec[1]["unit"] == "s"
    assert rec[3]["value"] == [1.0, 0.3]


def test_bad_effect_specs_are_refused():
    from exolan.world import parse_effect

    for bad in ("viscous_damping:ankle:1", "nonsense:knee:1", "viscous_damping:knee:-1", "viscous_damping:knee",
                "stribeck_friction:knee:1", "coulomb_friction:hip:abc"):
        with pytest.raises(ValueError):
            parse_effect(bad)


def test_simulate_layout_and_columns(small_world):
    root = small_world
    assert (root / "subjects.csv").read_text().splitlines()[0] == "subject,mass_kg,height_m"
    assert json.loads((root / "effects.json").read_text()) == []
    header = (root / "S01" / "walk_1_1" / "Exo.csv").read_text().splitlines()[0].split(",")
    for s in "lr":
        for c in (f"hip_angle_{s}", f"knee_angle_{s}", f"hip_angle_{s}_velocity_filt",
                  f"knee_angle_{s}_velocity_filt", f"insole_{s}_force_y", f"insole_{s}_cop_x",
                  f"insole_{s}_cop_z", f"hip_angle_{s}_torque_measured", f"knee_angle_{s}_torque_measured"):
            assert c in header
    mh = (root / "S01" / "walk_1_1" / "Joint_Moments_Filt.csv").read_text().splitlines()
    assert mh[0].split(",") == ["time", "hip_flexion_l_moment", "knee_angle_l_moment", "hip_flexion_r_moment",
                                "knee_angle_r_moment"]
    assert len(mh) == 1 + 4 * 200
    assert not list(root.rglob(".tmp-*"))


def test_simulation_is_deterministic(tmp_path):
    simulate(tmp_path / "a", users=2, tasks=["walk"], seconds=1, seed=3, progress=False)
    simulate(tmp_path / "b", users=2, tasks=["walk"], seconds=1, seed=3, progress=False)
    fa = (tmp_path / "a" / "S02" / "walk_1_1" / "Exo.csv").read_bytes()
    assert fa == (tmp_path / "b" / "S02" / "walk_1_1" / "Exo.csv").read_bytes()


def test_cli_simulate(tmp_path):
    from exolan.cli import main

    rc = main(["simulate", "--out", str(tmp_path), "--users", "2", "--tasks", "walk,squat", "--seconds", "1",
               "--effect", "viscous_damping:knee:1.0:S01"])
    assert rc == 0
    assert (tmp_path / "S02" / "squat_1_1" / "Exo.csv").exists()
    assert main(["simulate", "--out", str(tmp_path / "x"), "--tasks", "flying"]) == 2


def test_plot_trial_writes_a_png(small_world, tmp_path):
    from exolan.cli import main

    out = tmp_path / "walk.png"
    assert main(["plot", str(small_world / "S01" / "walk_1_1"), "--out", str(out)]) == 0
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 30_000
    assert main(["plot", str(tmp_path / "nothing_here"), "--out", str(tmp_path / "x.png")]) == 2
