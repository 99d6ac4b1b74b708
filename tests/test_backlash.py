"""Backlash: the side of its gap read off a measured angle (`gap_side`), the extended model's term, physics first's
column, and the engine export (a sensor effect: the limb's dynamics are left as they are)."""
import json
import sys

import numpy as np
import pytest
import torch
from scipy import signal

from exolan.diagnose.base import SlowContextDeLaN
from exolan.exo_signals import gap_side
from exolan.extensions import ExtendedModel
from exolan.world.generate import play

DT = 0.005
T = 8000
NOISE = 1.7e-4          # rad: a 14-bit encoder's 0.01°


def _motion(seed: int) -> np.ndarray:
    """Two sines of a few tenths of a radian: reversals from slow to fast, none inside a gap."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    return (rng.uniform(0.25, 0.4) * np.sin(2 * np.pi * rng.uniform(0.5, 0.9) * t + rng.uniform(0, 6))
            + rng.uniform(0.05, 0.1) * np.sin(2 * np.pi * rng.uniform(1.2, 1.8) * t + rng.uniform(0, 6)))


def _derivatives(x: np.ndarray):
    """A zero-phase low-pass at 80 Hz and central differences (physics first's differentiation at 200 Hz)."""
    xf = signal.sosfiltfilt(signal.butter(4, 80.0, fs=1 / DT, output="sos"), x)
    d1 = np.gradient(xf, DT)
    return xf, d1, np.gradient(d1, DT)


@pytest.mark.parametrize("width", [0.01, 0.04])
def test_the_gaps_side_carries_what_a_backlash_does_to_the_measured_kinematics(width):
    """A play operator of width w holds the measured angle while the limb crosses the gap: the limb is at
    q_meas + (w/2) s. The side read off the noisy measured angle carries that shift in the angle and, through the
    same differentiation, in q̇ and q̈ (where a backlash moves the torque: the limb accelerates while the angle
    stands still): the angle within 1 %, q̈ within 15 % and R² ≥ 0.9 (measured 0.88-0.99 of the q̈ shift; a side
    signal from the filtered velocity's dwell gave 0.6-0.7 in gait, docs/DIAGNOSIS.md). Where the limb turns back
    inside the gap the measured angle never shows it: what is left is that."""
    for seed in range(3):
        q = _motion(seed)
        meas = play(q, width)
        s = gap_side((meas + np.random.default_rng(seed).normal(0, NOISE, T))[:, None], DT)[:, 0]
        for tol, truth, col in zip((0.01, 0.05, 0.15), _derivatives(q - meas), _derivatives(0.5 * width * s)):
            k = slice(100, -100)          # the filter's edges
            th = float(col[k] @ truth[k] / (col[k] @ col[k]))
            r2 = 1 - np.var(truth[k] - th * col[k]) / np.var(truth[k])
            assert abs(th - 1) < tol and r2 > 0.9, (seed, th, r2)


def test_without_a_gap_the_side_is_the_direction_of_motion():
    """No backlash: s is the direction of motion, ±1 away from the reversals, and it changes sign only within a few
    samples of one (at a fast reversal a noise step may make it change three times there)."""
    q = _motion(4)
    s = gap_side((q + np.random.default_rng(0).normal(0, NOISE, T))[:, None], DT)[:, 0]
    direction = np.sign(np.gradient(q))
    far = np.abs(np.gradient(q, DT)) > 0.3            # away from the reversals (slower steps are within the noise)
    assert np.all(s[far] == direction[far])
    flips, turns = np.flatnonzero(np.diff(np.sign(s)) != 0), np.flatnonzero(np.diff(direction) != 0)
    assert all(np.min(np.abs(turns - f)) <= 5 for f in flips)
    assert all(np.any(np.abs(flips - t) <= 5) for t in turns)


def test_the_extended_model_takes_the_limb_at_the_measured_angle_plus_half_the_gap():
    torch.manual_seed(0)
    base = SlowContextDeLaN(("revolute", "revolute"), n_trials=1, z_dim=2, hidden=16, lim=False, v_scale=5.0).double()
    ext = ExtendedModel(base, 2, [("backlash", 1)], dt=DT, init={"backlash": 0.03}).double()
    B = 12
    g = torch.Generator().manual_seed(1)
    q, qd, qdd, s, sd, sdd = (torch.randn(B, 2, generator=g, dtype=torch.float64) for _ in range(6))
    z, fv = base.z_of(torch.zeros(B, dtype=torch.long)), torch.zeros(B, dtype=torch.float64)
    got = ext.inverse(q, qd, qdd, z, fv, side=(s, sd, sdd))
    shift = torch.tensor([0.0, 0.015], dtype=torch.float64)
    want = base.inverse(q + shift * s, qd + shift * sd, qdd + shift * sdd, z, fv)
    assert torch.allclose(got, want, atol=1e-12)
    assert ext.estimate("backlash", 1) == pytest.approx(0.03, rel=1e-6) and ext.estimate("backlash", 0) == 0.0
    assert torch.allclose(ext.inverse(q, qd, qdd, z, fv), base.inverse(q, qd, qdd, z, fv))    # no side: the limb


def _turns(seed: int) -> np.ndarray:
    """Three sines, quick turns (q̈ about 20 rad/s² there, as a knee's in gait; near a few of them the faster parts
    turn the limb back inside the gap, which the measured angle does not show: docs/DIAGNOSIS.md)."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    return sum(a * rng.uniform(0.8, 1.2) * np.sin(2 * np.pi * f * rng.uniform(0.9, 1.1) * t + rng.uniform(0, 6))
               for a, f in ((0.5, 1.0), (0.1, 2.1), (0.03, 3.7)))


def _pendulum(width: float, coulomb: float, seed: int, name: str = "p", motion=_turns):
    from types import SimpleNamespace

    rng = np.random.default_rng(seed)
    q = motion(seed)
    qd, qdd = np.gradient(q, DT), np.gradient(np.gradient(q, DT), DT)
    tau = 0.3 * qdd + 4.0 * np.sin(q) + coulomb * np.tanh(qd / 0.01) + 0.02 * rng.standard_normal(T)
    meas = (play(q, width) if width > 0 else q) + rng.normal(0, NOISE, T)
    qdm = np.gradient(meas, DT)
    col = lambda x: x[:, None]
    return SimpleNamespace(subject="S", task="bench", name=name, side="", mass=1.0, dt=DT, joints=("knee",),
                           joint_types=("revolute",), q=col(meas), qd=col(qdm), qdd=col(np.gradient(qdm, DT)),
                           tau=col(tau), tau_e=np.zeros((T, 1)), f_v=np.zeros(T), cop=np.full((T, 2), np.nan),
                           valid=np.ones(T, bool))


def _physics_first(width: float, coulomb: float, seed: int):
    from exolan.diagnose import physics
    from exolan.diagnose.flat import prepare

    flat = prepare([_pendulum(width, coulomb, s, f"p{s}") for s in range(seed, seed + 3)])
    return physics.identify(flat, ("viscous_damping", "coulomb_friction", "stribeck_friction", "backlash"), [0])


def test_the_profiled_sse_is_the_base_refitted_in_the_shifted_coordinates():
    """Physics first sizes a backlash by variable projection: at every width the base refitted at q + (w/2) s. The
    Gram profile (`shift.Profile`) must be that fit's SSE (as the rows' QR gives it), and the design's quadratic in
    the shift the base rebuilt from the shifted kinematics, at the widths a play has."""
    from exolan.diagnose import ident, physics
    from exolan.diagnose.flat import prepare

    flat = prepare([_pendulum(0.03, 0.0, s, f"p{s}") for s in range(2)])
    prob = physics.setup(flat, ("backlash",), [0])._probs[0]
    prof = prob._profile(["backlash"], {"backlash": 0.0}, "backlash")
    sig, tr = prob.sig, prob.train
    for w in (0.0, 0.01, 0.03, 0.08):
        want = prob.sse(["backlash"], {"backlash": w})
        assert prof(w) == pytest.approx(want, rel=1e-8)
        u = w / 2
        q, qd, qdd = sig.q + u * sig.side, sig.qd + u * sig.side_d, sig.qdd + u * sig.side_dd
        exact = sig.lp(ident.base_columns(q, qd, qdd, sig)[0])[tr]
        moved = np.abs(exact - prob.Xb[tr]).max()
        assert np.abs(prob._basis().at(u)[tr] - exact).max() <= 0.01 * moved + 1e-12, w


def test_physics_first_names_a_backlash_alone_at_its_size():
    """A pendulum seen through a backlash (three recordings), 24 draws of 0.01-0.04 rad: physics first names it alone,
    within 10 % (measured 0.95-1.00 of the width in 48 draws). A column beside a fixed base sized a knee's 0.04 rad
    at 0.016 (docs/DIAGNOSIS.md): the base has to move with the coordinates. Before the side was read only inside a
    run's ends, 12 of 48 such draws were sized 0.56-0.88 and rejected: a two-sample flip of the side at a trial's
    start."""
    for width in (0.01, 0.02, 0.03, 0.04):
        for seed in range(0, 18, 3):
            res = _physics_first(width, 0.0, seed)
            assert [e for e, _ in res.accepted] == ["backlash"], (width, seed, res.status)
            assert abs(res.estimates[("backlash", 0)].estimate / width - 1) < 0.1, (width, seed, res.estimates)


def test_a_backlash_in_short_recordings_with_a_fast_start_is_named_at_its_size(monkeypatch):
    """Eight recordings of 3 s, each starting as the limb is released (q̈ 500 rad/s² at the first sample): the zero-
    phase filters' padding shapes a run's first and last rows, where the shifted base's q̈ columns are not the
    recording's. Physics first leaves those rows out (`parallel_filter.run_edges`). Measured with them in: 2 of 10
    draws rejected ("no held-out gain"), the rest sized 0.75-0.98 of the width; without: 10 of 10, 0.98-1.00. The
    same mechanism missed a knee backlash of 0.0389 rad in a world of 2 users (seed 3049; docs/DIAGNOSIS.md)."""
    from exolan.diagnose import physics
    from exolan.diagnose.flat import prepare

    monkeypatch.setattr(sys.modules[__name__], "T", 600)

    def released(seed):
        t = np.arange(T) * DT
        return _turns(seed) + 0.05 * np.exp(-t / 0.01)

    for width in (0.02, 0.04):
        for seed in range(0, 60, 12):
            flat = prepare([_pendulum(width, 0.0, s, f"p{s}", motion=released) for s in range(seed, seed + 8)])
            res = physics.identify(flat, ("viscous_damping", "coulomb_friction", "stribeck_friction", "backlash"), [0])
            assert [e for e, _ in res.accepted] == ["backlash"], (width, seed, res.status)
            assert abs(res.estimates[("backlash", 0)].estimate / width - 1) < 0.05, (width, seed, res.estimates)


@pytest.mark.parametrize("coulomb, want", [(1.0, ["coulomb_friction"]), (0.0, [])])
def test_physics_first_does_not_name_a_backlash_for_a_friction_or_for_nothing(coulomb, want):
    """A Coulomb friction also steps the torque at every reversal: it is named alone; clean data name nothing."""
    for seed in (0, 3):
        res = _physics_first(0.0, coulomb, seed)
        assert [e for e, _ in res.accepted] == want, res.status


def test_the_engine_file_leaves_the_backlash_to_its_metadata(tmp_path):
    engine = pytest.importorskip("exolan.engine")
    from exolan.diagnose.export import export_extended

    torch.manual_seed(0)
    b = SlowContextDeLaN(("revolute", "revolute"), 3, z_dim=4, hidden=16, lim=True, v_scale=5.0).double()
    ext = ExtendedModel(b, 2, [("backlash", 1), ("viscous_damping", 0)], dt=DT,
                        init={"backlash": 0.02, "viscous_damping": 0.4}).double()
    z = b.codes.weight[0].detach()
    path, twin = export_extended(ext, tmp_path / "ext.safetensors", z, joint_names=("hip", "knee"))
    eng = engine.Engine(str(path))
    assert set(eng.extensions) == {"ext.damping"}
    from safetensors import safe_open
    with safe_open(str(path), "np") as f:
        meta = f.metadata()
    assert json.loads(meta["sensor_backlash"]) == pytest.approx({"knee": 0.02})
    q, qd, qdd = (np.random.default_rng(k).standard_normal((8, 2)) for k in range(3))
    with torch.no_grad():        # the limb's dynamics: the model without a side signal
        want = ext.inverse(*(torch.as_tensor(x) for x in (q, qd, qdd)), z.expand(8, 4),
                           torch.zeros(8, dtype=torch.float64)).numpy()
    got = eng.inverse_dynamics(q, qd, qdd, f_v=np.zeros(8))
    assert np.abs(got - want).max() <= 1e-9 * np.abs(want).max()


def test_a_steps_candidates_tested_side_by_side_give_the_same_selection_bit_for_bit():
    """`physics.select` tests a step's candidates on the running diagnosis' workers, each on its own view of the
    joint's problem (`JointProblem.view`; the shift basis of a backlash made once and shared). Two workers must
    give what one gives, bit for bit: every step's p and estimate, every status; and the problem keeps no split."""
    import copy

    from exolan.diagnose import physics
    from exolan.diagnose.flat import prepare
    from exolan.diagnose.workers import Workers, running

    flat = prepare([_pendulum(0.03, 0.4, s, f"p{s}") for s in range(3)])
    base = physics.setup(flat, ("viscous_damping", "coulomb_friction", "stribeck_friction", "backlash"), [0])
    out = []
    for n in (1, 2):
        res = copy.deepcopy(base)
        with running(Workers(n)):
            physics.select(res, flat)
        out.append(res)
        assert res._probs[0].split == {} and ("backlash", 0) in res.accepted
    one, two = out
    assert [(t["effect"], t["p"], t["estimate"], t["ci"]) for t in one.tests] == \
        [(t["effect"], t["p"], t["estimate"], t["ci"]) for t in two.tests]
    assert one.status == two.status and one.accepted == two.accepted
