"""Diagnosis: statistics, a layout-2 system with and without planted friction, and the hidden-effect worlds.

The hidden-effect tests read effects.json only to *check* the report, never to steer the diagnosis. Default
run: the statistics, the layout-2 linear drive (viscous friction with random magnitude and seed / clean), a
clean exoskeleton world and one with hidden knee damping (random magnitude and seed), all through the full
diagnosis (screen, joint refits, decision rule, report) — four to five minutes per world on two quiet cores.
Every hidden-effect world (knee damping, hip Coulomb, exo delay, strap, encoder offset, clean) runs with
`pytest -m slow tests/test_diagnose.py`.
"""
import json
import math
import os

import numpy as np
import pytest

from exolan.diagnose import diagnose, stats
from exolan.diagnose.candidates import LIBRARY
from exolan.diagnose.synthetic import linear_drive


# -- statistics -------------------------------------------------------------------------------------

def _ar1(phi, N, seed):
    rng = np.random.default_rng(seed)
    e = rng.standard_normal(N)
    x = np.empty(N)
    x[0] = e[0]
    for t in range(1, N):
        x[t] = phi * x[t - 1] + e[t]
    return x


def test_block_length_follows_the_autocorrelation():
    b_white = stats.block_length(np.random.default_rng(0).standard_normal(5000))
    b_slow = stats.block_length(_ar1(0.95, 5000, 1))
    assert b_white <= 4 and b_slow >= 20


def test_block_bootstrap_ci_covers_the_mean_of_autocorrelated_series():
    """Coverage of the true mean (0) for AR(1) φ = 0.9: near 95 %, far above what i.i.d. intervals give."""
    hits, hits_iid = 0, 0
    for k in range(40):
        x = _ar1(0.9, 2000, 100 + k)
        b = stats.bootstrap_mean(x, n_boot=300, seed=k)
        hits += b["ci"][0] <= 0 <= b["ci"][1]
        se = x.std() / np.sqrt(len(x))
        hits_iid += abs(x.mean()) <= 1.96 * se
    assert hits >= 32          # ≥ 80 % (nominal 95 %; 40 trials)
    assert hits_iid <= 28      # the naive interval is badly over-confident here


def test_cross_correlation_finds_a_lagged_copy():
    rng = np.random.default_rng(3)
    f = _ar1(0.8, 4000, 4)
    r = np.roll(f, 5) + rng.standard_normal(4000)
    cc = stats.cross_correlation(r, f, max_lag=20)
    assert cc["peak_lag"] == 5 and abs(cc["peak"]) > cc["band"]


# -- layout 2: a prismatic linear drive -------------------------------------------------------------

def _accepted(rep):
    return [(f["effect"], f["joint"]) for f in rep["findings"] if f["status"] == "accepted"]


@pytest.mark.parametrize("viscous", [None, "random"])
def test_linear_drive_viscous_friction_layout2(tmp_path, viscous):
    rng = np.random.default_rng()
    seed = int(rng.integers(1000))
    b = float(rng.uniform(4.0, 12.0)) if viscous else None     # N s/m
    trials, truth = linear_drive(n_trials=3, seconds=16.0, seed=seed, viscous=b)
    rep = diagnose(trials, out=tmp_path, quick=True, hidden=16, steps_base=500, steps_refit=200, physics_first=False,
                   effects=("viscous_damping", "coulomb_friction", "torque_bias"), verbose=False)
    found = _accepted(rep)
    msg = f"seed {seed}, b {b}: findings {rep['findings']}"
    if b is None:
        assert found == [], msg
    else:
        assert found == [("viscous_damping", "x")], msg
        f = rep["findings"][0]
        assert f["unit"] == "N s/m"
        assert abs(f["estimate"] - b) <= 0.2 * b, msg
        assert f["heldout_gain"] > 0 and f["ci"][0] <= f["estimate"] <= f["ci"][1]
        # the reported interval adds the refit spread to the joint fit's own, which excludes no damping (rule 4)
        lo_id, hi_id = f["ci_identification"]
        assert 0 < lo_id <= f["estimate"] <= hi_id and f["ci"][0] <= lo_id and hi_id <= f["ci"][1]
        assert "rule 4 checks against the no-effect value" in (tmp_path / "diagnosis.md").read_text()
        # where the joint fit's own interval and the warm start's do not overlap, the finding says so
        w_lo, w_hi = f["ci_warm_start"]
        assert ("two fits disagree" in (f.get("note") or "")) == (hi_id < w_lo or w_hi < lo_id), msg
        # decided on the misfit-weighted held-out error, reported with the user's unweighted one beside it
        assert f["decision_gain"]["scale"] == "misfit-weighted" and f["decision_gain"]["ci"][0] > 0
    assert rep["baseline"]["noise_floor"]["scale"] == "misfit-weighted"
    # a bench's errors are in its own units (a prismatic axis: N), not per body mass
    md = (tmp_path / "diagnosis.md").read_text()
    assert rep["data"]["torque_unit"] == "N" and "N m/kg" not in md and "held-out torque MSE [(N)²]" in md
    # the report is complete and readable
    j = json.loads((tmp_path / "diagnosis.json").read_text())
    assert set(j) >= {"baseline", "findings", "rejected", "extended"}
    assert (tmp_path / "diagnosis.md").read_text().startswith("# Diagnosis")
    assert (tmp_path / "rollout_error.png").exists() and (tmp_path / "residual_vs_velocity.png").exists()
    assert all(e["status"] in ("rejected", "absorbable", "ambiguous") for e in j["rejected"])


def test_linear_drive_viscous_and_coulomb_friction_both_found(tmp_path):
    """Two effects on one axis (random magnitudes and seed): forward selection accepts the larger one, then
    the other on top of it, each within 20 %. The second term starts where the residual of the first model
    asks for it (a start at its single-term estimate, which had soaked up part of the first, lost: measured)."""
    rng = np.random.default_rng()
    seed = int(rng.integers(1000))
    b, fc = float(rng.uniform(4.0, 12.0)), float(rng.uniform(2.0, 5.0))      # N s/m, N
    trials, truth = linear_drive(n_trials=3, seconds=16.0, seed=seed, viscous=b, coulomb=fc)
    rep = diagnose(trials, out=tmp_path, quick=True, hidden=16, steps_base=500, steps_refit=200, physics_first=False,
                   effects=("viscous_damping", "coulomb_friction", "torque_bias"), verbose=False)
    msg = f"seed {seed}, b {b}, Fc {fc}: findings {rep['findings']}"
    assert sorted(_accepted(rep)) == [("coulomb_friction", "x"), ("viscous_damping", "x")], msg
    est = {f["effect"]: f["estimate"] for f in rep["findings"]}
    assert abs(est["viscous_damping"] - b) <= 0.2 * b, msg
    assert abs(est["coulomb_friction"] - fc) <= 0.2 * fc, msg
    second = next(f for f in rep["findings"] if "conditional_gain" in f)
    assert second["conditional_gain"]["gain"] > 0 and "start" in second["conditional_gain"], msg
    # each reported interval is widened by the spread to the warm refit with both terms, not to its single-term
    # fit, which holds part of the other (measured on a 1 kHz bench: an accepted damping's interval reached -0.014)
    for f in rep["findings"]:
        assert f["warm_start"] == "the reference refitted with every accepted term", msg
        assert "estimate_single_term" in f and f["ci"][0] > 0, msg


# -- hidden-effect worlds ---------------------------------------------------------------------------

# (effect, joint, value range, accepted-effect check)
WORLD_CASES = {
    "knee_damping": ("viscous_damping", "knee", (1.0, 3.0)),
    "hip_coulomb": ("coulomb_friction", "hip", (1.5, 4.0)),
    "exo_delay": ("actuation_delay", "knee", (0.02, 0.05)),
    "strap": ("strap_compliance", "knee", (60.0, 150.0)),
    "encoder_offset": ("encoder_offset", "hip", (0.05, 0.15)),
    # a gain is identified only by the controller's own variation (the base absorbs the rest, a copy of the joint
    # torque): 1.25 was below this world's detection limit, 2.0 was found at 1.97 (measured, notes on issue 7)
    "exo_gain": ("torque_gain", "hip", (1.8, 2.5)),
    # a play in the knee's transmission: the encoder holds while the limb crosses the gap after a reversal
    "backlash": ("backlash", "knee", (0.02, 0.06)),
    "clean": None,
}


# Four tasks: rule 5 sets the task where a gain is largest aside (a quarter of the tasks, at least one), and
# walking, a periodic motion, shows a dissipation's gain hardly at all (the flexible model absorbs it along
# the orbit). With walk, squat and calisthenics the rest was walking and one other task, and a knee damping
# of 1.3 N m s/rad (seed 12) was missed; with turn added (a paper training task: walking with irregular
# strides) the same draw was found at 1.14 (measured, notes on issue 7).
WORLD_TASKS = "walk,squat,calisthenics,turn"


def _world(tmp_path, case, seed, value, users=2, tasks=WORLD_TASKS, seconds=16):
    from exolan.world import simulate

    root = tmp_path / "world"
    effects = []
    if WORLD_CASES[case] is not None:
        eff, joint, _ = WORLD_CASES[case]
        effects = [f"{eff}:{joint}:{value}"]
    simulate(root, users=users, tasks=tasks, seconds=seconds, seed=seed, effects=effects, progress=False)
    return root


def _draw(name: str, value_range=None) -> tuple[int, float | None]:
    """A random world seed and planted value (4 decimals) for the draw `name`. To replay a failed draw:
    EXOLAN_WORLD_DRAW="NAME:SEED[:VALUE]" (the tests' messages print both)."""
    rng = np.random.default_rng()
    seed = int(rng.integers(10000))
    value = None if value_range is None else float(np.round(rng.uniform(*value_range), 4))
    replay = os.environ.get("EXOLAN_WORLD_DRAW", "").split(":")
    if replay[0] == name:
        seed = int(replay[1])
        value = float(replay[2]) if len(replay) > 2 else value
    return seed, value


def _check_world(tmp_path, case, users=2, tasks=WORLD_TASKS, seconds=16, **settings):
    seed, value = _draw(case, WORLD_CASES[case][2] if WORLD_CASES[case] is not None else None)
    root = _world(tmp_path, case, seed, value, users, tasks, seconds)
    rep = diagnose(root, out=tmp_path / "diag", quick=True, verbose=False, **settings)
    truth = json.loads((root / "effects.json").read_text()) if (root / "effects.json").exists() else []
    found = _accepted(rep)
    msg = f"case {case} seed {seed} truth {truth}: findings {rep['findings']}"
    print(msg)      # the draw, also when it passes (pytest -rP shows it): pass rates over draws are measured
    if case in ("clean", "encoder_offset"):
        assert found == [], msg
        if case == "encoder_offset":
            off = [e for e in rep["rejected"] if e["effect"] == "encoder_offset" and e["joint"] == "hip"]
            assert off and off[0]["status"] == "absorbable", msg
        return rep
    eff, joint, _ = WORLD_CASES[case]
    own = [e for e in rep["rejected"] if (e["effect"], e["joint"]) == (eff, joint)]
    if eff == "torque_gain":
        # what the report calls detectable agrees with what was detected: a gain inside the limits the report
        # measured for these data (by injection, `limits.limits_by_injection`) may be missed, but nothing else may be
        # accepted in its place (measured: a hip gain of 1.84, limit 1.80, once let a hip strap through)
        lim = rep["detection_limits"]["torque_gain"][joint]
        assert lim["method"] == "injection", msg
        if lim["k_below"] <= value <= lim["k_above"] and (eff, joint) not in found:
            print(f"a gain of {value} is inside this world's detection limits [{lim['k_below']:.3g}, {lim['k_above']:.3g}]")
            assert found == [], msg
            return rep
    if eff == "actuation_delay" and (eff, joint) not in found:
        # The report states the shortest delay these data can show (d_limit, first order at the base's misfit) and
        # warns that one within twice that limit is estimated short. The zones are the report's own claims:
        # below d_limit a miss is what it predicts; beyond 2 d_limit it must be found. Between, the learned base
        # imitates part of a delay (docs/DIAGNOSIS.md, "A knee delay at the data's limit"), so the misfit shows a
        # shorter one: a miss there must be named `ambiguous` or sized by the report itself under d_limit (what is
        # left in the misfit is below what the data can show). Nothing else may be accepted in its place.
        # (Measured: 24.1 ms beside a limit of 18.7 ms, seed 6220, ambiguous; 22.5 ms beside 19.0 ms, seed 303,
        # sized 17.0 ms and rejected within the refit noise.)
        lim = float(rep["detection_limits"]["actuation_delay"][joint]["d_limit"])
        named = [e for e in own if e["status"] == "ambiguous"]
        short = [e for e in own if e.get("estimate") is not None and e["estimate"] < lim]
        print(f"a delay of {1e3 * value:.3g} ms beside this world's detection limit of {1e3 * lim:.3g} ms: missed")
        assert found == [] and value < 2 * lim, msg
        assert value < lim or named or short, f"a delay under twice the limit must be named or sized under it; {msg}"
        return rep
    if LIBRARY[eff].linear and (eff, joint) not in found and own and own[0].get("size_limit") is not None:
        # A term linear in its size whose warm refit gained but not at its level: the report states the size from
        # which these data would show it (`single.size_limit`). A miss is what the report predicts only where the
        # truth lies below that limit, with the term sized within 20 % and nothing else accepted (measured: hip
        # Coulomb 1.611, seed 3421: sized 1.50, its gain short of the 99.72 % level; docs/DIAGNOSIS.md).
        lim = float(own[0]["size_limit"])
        print(f"a {eff} of {value} beside the size these data would show, {lim:.3g}: missed")
        assert found == [] and value < lim and abs(own[0]["estimate"] - value) <= 0.2 * value, msg
        return rep
    assert (eff, joint) in found, msg
    assert found == [(eff, joint)], f"something besides the planted effect was accepted; {msg}"
    f = next(x for x in rep["findings"] if x["effect"] == eff and x["joint"] == joint)
    if eff == "torque_gain":
        # A gain is identified by the controller's own variation alone (about 6 % of the exo torque's variance in
        # these worlds), part of which the base absorbs too; along the copy of the joint torque it trades against
        # the scale of the base's dynamics, and its fit from scratch ends where it starts (`refits.fresh_fit`;
        # measured: planted 1.87, 1.92, 2.37, 2.24 came out 2.26, 2.36, 2.61, 2.46 from the warm estimates 1.56,
        # 1.74, 2.17, 1.94). So not within 20 %: the report's interval (widened by that spread) must hold the truth.
        assert f["ci"][0] <= value <= f["ci"][1] and f["estimate"] > 1, msg
    else:
        assert abs(f["estimate"] - value) <= 0.2 * value, msg
    assert f["heldout_gain"] > 0, msg
    if eff == "actuation_delay":    # a delay near the detection limit carries the warning that it reads short
        lim = float(rep["detection_limits"]["actuation_delay"][joint]["d_limit"])
        assert ("detection limit" in (f.get("note") or "")) == (math.isfinite(lim) and f["estimate"] < 2 * lim), msg
    return rep


WORLD_SETTINGS = dict(steps_base=1500, steps_refit=400, hidden=64)


@pytest.mark.heavy
def test_clean_world_finds_nothing(tmp_path):
    """A clean exoskeleton world (random seed): "nothing found" — no accepted finding."""
    rep = _check_world(tmp_path, "clean", inject_gain=True, **WORLD_SETTINGS)    # the measured limits, asked for
    assert rep["extended"].get("note", "").startswith("nothing found")
    md = (tmp_path / "diag" / "diagnosis.md").read_text()
    assert "Nothing found" in md
    # the report says how far from 1 an exo torque gain would have to be to show in these data
    limits = rep["detection_limits"]["torque_gain"]
    assert set(limits) == {"hip", "knee"} and all(0 < v["k_below"] < 1 < v["k_above"] for v in limits.values())
    # ... measured by writing a known gain into the data (`limits.limits_by_injection`), the computed one beside it
    assert all(v["method"] == "injection" and v["injected_k"] > 1 and "computed" in v for v in limits.values())
    assert "written into the data was recovered as" in md
    # ... and how long an actuation delay would have to be (computed: its injection is off by default)
    delays = rep["detection_limits"]["actuation_delay"]
    assert set(delays) == {"hip", "knee"} and all(0 < v["d_limit"] < 0.1 for v in delays.values())
    assert all("method" not in v for v in delays.values()) and "ms written into the data" not in md
    assert "What these data cannot show" in md and "a delay can show only above d" in md
    assert rep["data"]["torque_unit"] == "N m/kg" and "held-out torque MSE / mass² [(N m/kg)²]" in md


@pytest.mark.heavy
def test_hidden_knee_damping_is_found(tmp_path):
    """Knee viscous damping of random magnitude (1..3 N m s/rad) and seed: named on the knee within 20 %, with
    a positive held-out gain, and nothing else accepted; the evidence is reported per task and subject."""
    rep = _check_world(tmp_path, "knee_damping", **WORLD_SETTINGS)
    assert [(f["effect"], f["joint"]) for f in rep["findings"]] == [("viscous_damping", "knee")], rep["findings"]
    f = rep["findings"][0]
    assert set(f["task_invariance"]["groups"]) == set(WORLD_TASKS.split(","))
    assert set(f["subject_gains"]) == {"S01", "S02"}
    ext = rep["extended"]
    assert ext["heldout_gain_ci"][0] > 0 and ext["terms"] == ["viscous_damping:knee"]
    assert (tmp_path / "diag" / "extended.safetensors").exists()


def _train_run(tmp_path, root, epochs: int, hidden: int, threads: int):
    """An `exolan train --method exolan` run on the world at root (the CLI, as a user would); its directory."""
    import subprocess
    import sys

    run = tmp_path / "run"
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(f"batch_size = 2048\nthreads = {threads}\n[model]\nhidden = {hidden}\n")
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "train", "--data", str(root), "--method", "exolan",
                        "--epochs", str(epochs), "--seed", "0", "--config", str(cfg), "--device", "cpu",
                        "--out", str(run)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return run


@pytest.mark.heavy
def test_cli_diagnose_with_a_trained_run(tmp_path):
    """`exolan diagnose DATA --model RUN --out DIR`: a trained ExoLaN run (TCN context, pooled per trial) is
    the base; the report says so and is complete; the options reach the settings. Bad options fail with a clear
    message. `--computed-gain-limit --no-rescue` keep this test short (the gain's injection and a clean world's
    rescue, 67 s and 134 s of its 279 s, measured; both run in `test_clean_world_finds_nothing`)."""
    import subprocess
    import sys

    root = _world(tmp_path, "clean", seed=5, value=None, users=2, tasks="walk,squat", seconds=12)
    run = _train_run(tmp_path, root, epochs=2, hidden=32, threads=1)
    out = tmp_path / "diag"
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "diagnose", str(root), "--model", str(run), "--out",
                        str(out), "--quick", "--effects", "viscous_damping,coulomb_friction,encoder_offset",
                        "--unweighted", "--computed-gain-limit", "--no-rescue"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "report:" in r.stdout
    j = json.loads((out / "diagnosis.json").read_text())
    assert j["baseline"]["source"].startswith("given model") and j["settings"]["weighted"] is False
    assert "adapted to the data's training segments" in j["baseline"]["source"] and j["settings"]["adapt_model"]
    assert j["settings"]["rescue"] is False and j["settings"]["inject_gain"] is False
    assert all("method" not in v for v in j["detection_limits"]["torque_gain"].values())
    assert not any("from_scratch" in e for e in j["findings"] + j["rejected"])
    tested = {(e["effect"], e["joint"]) for e in j["findings"] + j["rejected"]}
    assert {("viscous_damping", "hip"), ("coulomb_friction", "knee"), ("encoder_offset", "hip")} <= tested
    assert not any(e["effect"] == "actuation_delay" for e in j["findings"] + j["rejected"])
    assert [e for e in j["rejected"] if e["effect"] == "encoder_offset"][0]["status"] == "absorbable"
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "diagnose", str(root), "--out", str(tmp_path / "x"),
                        "--effects", "viscous_damping,warp_drive"], capture_output=True, text=True)
    assert r.returncode != 0 and "warp_drive" in (r.stderr + r.stdout)
    r = subprocess.run([sys.executable, "-m", "exolan.cli", "diagnose", str(root), "--out", str(tmp_path / "x"),
                        "--paired-seeds", "0"], capture_output=True, text=True)
    assert r.returncode != 0 and "argument --paired-seeds: must be at least 1" in (r.stderr + r.stdout)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["knee_damping", "hip_coulomb", "exo_delay", "strap", "encoder_offset", "exo_gain",
                                  "backlash", "clean"])
def test_hidden_effect_worlds(tmp_path, case):
    # the gain case is judged against the limits measured by injection (off by default: refits only when asked)
    _check_world(tmp_path, case, **WORLD_SETTINGS, **(dict(inject_gain=True) if case == "exo_gain" else {}))


@pytest.mark.slow
def test_a_damping_in_one_subject_only_is_found_on_that_subject(tmp_path):
    """A knee damping in one of two users (random magnitude 1.5..3 N m s/rad, user and seed; effects.json's
    `subjects`): named on the knee for that user alone, its parameter within 20 % — a term shared by both users
    dilutes it (2.0 came out 0.23 and was rejected, notes on issue 7) — and nothing else accepted."""
    from exolan.world import simulate

    seed, value = _draw("one_subject", (1.5, 3.0))
    user = ("S01", "S02")[seed % 2]
    root = tmp_path / "world"
    simulate(root, users=2, tasks=WORLD_TASKS, seconds=16, seed=seed, effects=[f"viscous_damping:knee:{value}:{user}"],
             progress=False)
    rep = diagnose(root, out=tmp_path / "diag", quick=True, verbose=False, **WORLD_SETTINGS)
    msg = f"seed {seed} knee damping {value} in {user}: findings {rep['findings']}"
    print(msg)
    assert _accepted(rep) == [("viscous_damping", "knee")], msg
    f = rep["findings"][0]
    assert f["subjects"] == [user] and f["subject_form"]["subjects"] == [user], msg
    assert abs(f["estimate"] - value) <= 0.2 * value and f["heldout_gain"] > 0, msg
    assert "only (fitted on their trials" in (tmp_path / "diag" / "diagnosis.md").read_text()
    # one engine file per user: the damping in the user's own, not in the other's
    from safetensors import safe_open

    for u in ("S01", "S02"):
        with safe_open(str(tmp_path / "diag" / f"extended_{u}.safetensors"), "np") as fh:
            assert ("ext.damping" in fh.keys()) == (u == user), msg


@pytest.mark.slow
def test_a_damping_of_a_different_size_in_each_subject_is_found_at_each_size(tmp_path):
    """A knee damping in both users at different sizes (random: 0.9..1.6 in one, 2.0..3.0 N m s/rad in the other):
    named on the knee for every user at their own size, each within 20 % (or, where the sizes are too close for
    held-out data to separate, as one term within 20 % of both), and nothing else accepted. The base
    absorbs much of the smaller one (post-hoc θ −0.07 ± 0.04 for 1.2 beside 0.77 ± 0.05 for 2.4), so a term of
    the larger user alone was found before and the smaller missed (notes on issue 7). The users' engine files
    hold their own damping."""
    from exolan.world import simulate

    seed, small = _draw("subject_sizes", (0.9, 1.6))
    large = float(np.round(2.0 + (seed % 1000) / 1000.0, 4))        # 2.0..3.0, from the seed (a replay repeats it)
    sizes = {"S01": small, "S02": large} if seed % 2 else {"S01": large, "S02": small}
    root = tmp_path / "world"
    simulate(root, users=2, tasks=WORLD_TASKS, seconds=16, seed=seed, progress=False,
             effects=[f"viscous_damping:knee:{v}:{u}" for u, v in sizes.items()])
    rep = diagnose(root, out=tmp_path / "diag", quick=True, verbose=False, **WORLD_SETTINGS)
    msg = f"seed {seed} knee damping {sizes}: findings {rep['findings']}"
    print(msg)
    assert _accepted(rep) == [("viscous_damping", "knee")], msg
    f = rep["findings"][0]
    assert f["subjects"] == ["S01", "S02"] and f["heldout_gain"] > 0, msg
    if (f.get("subject_form") or {}).get("kind") != "sizes":
        # sizes close enough that held-out data do not separate them (measured: 1.58 and 2.12, seed 1117, found
        # as one term of 1.81) must then both lie within 20 % of the one value
        assert all(abs(f["estimate"] - v) <= 0.2 * v for v in sizes.values()), msg
        return
    by = f["estimate_by_subject"]
    for u, v in sizes.items():
        assert abs(by[u]["estimate"] - v) <= 0.2 * v, msg
    assert "every subject at their own size" in (tmp_path / "diag" / "diagnosis.md").read_text()
    from safetensors import safe_open

    for u in sizes:
        with safe_open(str(tmp_path / "diag" / f"extended_{u}.safetensors"), "np") as fh:
            assert fh.get_tensor("ext.damping")[1, 1] == pytest.approx(by[u]["estimate"], rel=1e-5), msg


@pytest.mark.slow
def test_a_trained_run_as_base_finds_a_hidden_knee_damping(tmp_path):
    """`--model RUN` on data with a planted knee damping (random magnitude and seed): a trained ExoLaN run (TCN
    context) is the base, adapted at its pooled context; the damping is named within 20 % and nothing else."""
    seed, value = _draw("trained_run", (1.0, 3.0))
    root = _world(tmp_path, "knee_damping", seed, value)
    run = _train_run(tmp_path, root, epochs=300, hidden=64, threads=2)
    rep = diagnose(root, model=run, out=tmp_path / "diag", quick=True, verbose=False, **WORLD_SETTINGS)
    msg = f"seed {seed} knee damping {value}: findings {rep['findings']}"
    print(msg)
    assert _accepted(rep) == [("viscous_damping", "knee")], msg
    assert abs(rep["findings"][0]["estimate"] - value) <= 0.2 * value, msg


@pytest.mark.heavy
def test_real_recordings_without_exoskeleton(tmp_path, real_data):
    """Real human recordings (OpenSim inverse dynamics, 15 tasks, nobody wore an exoskeleton): the diagnosis
    runs end to end on them; every exo-driven term is reported as not testable; nothing else is accepted —
    a leg's biological joints carry no friction, delay or strap that a leg model could name."""
    rep = diagnose(real_data, out=tmp_path / "diag", quick=True, verbose=False, **WORLD_SETTINGS)
    assert rep["findings"] == [], rep["findings"]
    exo = [e for e in rep["rejected"] if e["effect"] in ("actuation_delay", "torque_gain", "strap_compliance")]
    assert exo and all("not testable" in e["reason"] for e in exo)
    assert rep["baseline"]["torque_mse"] > 0 and rep["data"]["has_exo"] is False
    assert rep["detection_limits"] == {"torque_gain": {}, "actuation_delay": {}}
    assert (tmp_path / "diag" / "diagnosis.md").read_text().startswith("# Diagnosis")
