"""Rule 3 where a term is added: forward selection asks an exo-driven term tested on top of accepted terms to beat
its nulls there too (`nulls.on_top`), before any fit from scratch. Fast (seconds)."""
import numpy as np
import pytest

from exolan.diagnose import procedure, selection
from exolan.diagnose.candidates import blank_entry
from exolan.diagnose.export import extend
from exolan.diagnose.flat import prepare, sample_groups
from exolan.diagnose.refits import refit
from exolan.diagnose.rules import invariance_rule
from exolan.diagnose.session import Tools
from exolan.diagnose.settings import Settings
from exolan.diagnose.subjects import with_estimate
from exolan.diagnose.workers import Workers

from diagnose_helpers import leg_pair


def _assisted_trials(seed: int = 3):
    """Two sides of a recording whose hip torque follows the angle and whose hip exo torque assists: a share of
    the joint torque 5 samples earlier plus the controller's own slow variation, recorded 1.5 times too large."""
    rng = np.random.default_rng(seed)
    trials = leg_pair(T=3000, seed=seed)
    for t in trials:
        t.q = np.cumsum(rng.normal(0, 0.02, t.q.shape), 0)
        t.tau = 8.0 * np.sin(t.q) + rng.normal(0, 0.5, t.q.shape)
        t.tau_e = np.zeros_like(t.tau)
        t.tau_e[5:, 0] = 0.3 * t.tau[:-5, 0]
        t.tau_e[:, 0] += 2.0 * np.convolve(rng.normal(0, 1, 3200), np.hanning(101), "same")[100:-100] / 7.0
        t.tau[:, 0] += (1 - 1 / 1.5) * t.tau_e[:, 0] + 2.0      # a gain of 1.5 and a bias of 2 N m
    return trials


@pytest.mark.parametrize("null_passes", [True, False])
def test_an_exo_driven_term_on_top_of_accepted_ones_must_beat_its_null_there(null_passes):
    """A torque gain tested on top of an accepted torque bias (rules 1, 2 and 5 held open): forward selection asks
    rule 3's nulls on top (`Tools.nulls_on_top`, stubbed: its verdict forced) with the accepted terms and the
    model fitted with them; where they fail, the gain is rejected with rule 3's reason and nothing is fitted from
    scratch; a term that is not exo-driven (a damping) is not asked."""
    trials = _assisted_trials()
    flat = prepare(trials)
    calls = []

    def on_top(ss, e, j, given, cur, sc):
        calls.append(dict(effect=e["effect"], j=j, given=list(given[0]), terms=sorted(cur.effects)))
        null = dict(gain=1e-4 if null_passes else -1e-5, ci=[5e-5, 2e-4] if null_passes else [-3e-5, 1e-5],
                    passes=null_passes, future_lag_s=0.025)
        return dict(nulls=[null], null_gain=null, passes=null_passes)

    tools = Tools(above_noise=lambda g, sigma, seed=0, alpha=0.05: True, user_improves=lambda a, b: True,
                  invariance=lambda *a, **k: dict(invariance_rule(*a, **k), passes=True), nulls_on_top=on_top)
    s = Settings(steps_base=40, steps_refit=10, hidden=8, n_boot=100, verbose=False)
    ss, _ = procedure.reference(flat, s, None, tools, Workers(1), [0, 1])
    ss.base_start = None                     # warm looks only: the test is about the null before them
    ss.sigma_r = 0.0
    ss.groups, ss.group_kind = sample_groups(flat, ss.held)
    bias = blank_entry("torque_bias", 0, flat, ["S01"])
    bias.update(estimate=2.0)
    sel = selection.Selection(accepted=[("torque_bias", 0)], given=[("torque_bias", 0)])
    sel.acc_init = sel.given_init = with_estimate({}, bias, 0)
    cur = extend(ss.base, flat, sel.given, init=sel.given_init)
    refit(cur, flat, s)
    cur_u, cur_e = ss.errors(cur)
    gain = blank_entry("torque_gain", 0, flat, ["S01"])
    kept = selection.further(ss, gain, sel, cur, cur_u, cur_e)
    assert calls == [dict(effect="torque_gain", j=0, given=[("torque_bias", 0)], terms=["torque_bias"])]
    assert gain.conditional_gain["null_gain"]["passes"] is null_passes
    assert kept is null_passes
    if not null_passes:
        assert gain["status"] == "rejected"
        assert gain["reason"].startswith("on top of torque_bias:hip it does not beat its null (rule 3")
        assert "from_scratch" not in gain.conditional_gain
    damping = blank_entry("viscous_damping", 1, flat, ["S01"])
    selection.further(ss, damping, sel, cur, cur_u, cur_e)
    assert len(calls) == 1                   # a damping is not exo-driven: no null asked


def test_the_nulls_on_top_take_the_given_terms_out_at_the_fitted_sizes(monkeypatch):
    """`nulls.on_top` judges the term on the data with the given terms removed at the sizes of the model fitted
    with them (not at their starts), with that model's networks; its nulls are those of the term alone (the
    future torque at the residual's and the tracking lag, the controller's own variation), the hardest deciding."""
    import torch

    from exolan.diagnose import compensate, nulls

    flat = prepare(_assisted_trials())
    s = Settings(steps_base=20, steps_refit=5, hidden=8, n_boot=100, verbose=False)
    ss, _ = procedure.reference(flat, s, None, Tools(), Workers(1), [0, 1])
    ss.sigma_r = 0.0
    given, init = [("torque_bias", 0)], {"torque_bias": {0: 0.5}}
    cur = extend(ss.base, flat, given, init=init)
    with torch.no_grad():
        cur.bias_raw[0] = cur.bias_raw[0] * 4.0            # as if its fit had moved the bias from 0.5 to 2
    seen, bases = [], []
    real_data, real_judge = compensate.data, nulls.judge

    def data(f, terms, sizes, max_delay):
        seen.append((list(terms), sizes["torque_bias"][0]))
        return real_data(f, terms, sizes, max_delay)

    def judge(ss_, entry, j, base, *a, **k):
        bases.append(base)
        return real_judge(ss_, entry, j, base, *a, **k)

    monkeypatch.setattr(compensate, "data", data)
    monkeypatch.setattr(nulls, "judge", judge)
    out = nulls.on_top(ss, blank_entry("torque_gain", 0, flat, ["S01"]), 0, (given, init), cur, {})
    assert seen == [(given, pytest.approx(2.0, rel=1e-6))]
    assert bases == [cur.base]
    assert any(n.get("own_variation_only") for n in out["nulls"]) and len(out["nulls"]) in (2, 3)
    assert out["passes"] == all(n["passes"] for n in out["nulls"])
    assert out["null_gain"] == min(out["nulls"], key=lambda n: (n["passes"], n["ci"][0]))


def test_the_nulls_on_top_take_a_shaped_term_out_at_its_fitted_shape(monkeypatch):
    """A given Stribeck friction is taken out at the force and the velocity scale its model fitted, not at the
    velocity scale it started from."""
    import torch

    from exolan.diagnose import compensate, nulls

    flat = prepare(_assisted_trials())
    s = Settings(steps_base=20, steps_refit=5, hidden=8, n_boot=100, verbose=False)
    ss, _ = procedure.reference(flat, s, None, Tools(), Workers(1), [0, 1])
    given, init = [("stribeck_friction", 1)], {"stribeck_friction": {1: 1.0}, "stribeck_vs": {1: 0.1}}
    cur = extend(ss.base, flat, given, init=init)
    with torch.no_grad():
        cur.stribeck_vs_raw[1] = cur.stribeck_vs_raw[1] + 1.0      # as if its fit had moved vs
    fitted = cur.physical()
    assert abs(fitted["stribeck_vs"][1] - 0.1) > 1e-3
    seen = []
    real_data = compensate.data
    monkeypatch.setattr(compensate, "data", lambda f, terms, sizes, md: seen.append(sizes) or real_data(f, terms, sizes, md))
    nulls.on_top(ss, blank_entry("torque_gain", 0, flat, ["S01"]), 0, (given, init), cur, {})
    assert seen[0]["stribeck_vs"][1] == pytest.approx(float(fitted["stribeck_vs"][1]), rel=1e-6)
    assert seen[0]["stribeck_friction"][1] == pytest.approx(float(fitted["stribeck_friction"][1]), rel=1e-6)


def test_the_nulls_on_top_take_a_per_subject_term_out_at_each_subjects_fitted_size(monkeypatch):
    """A given knee damping with a size per subject is taken out at each subject's fitted size (its model's
    `subject_init`), not at the subjects' shared start: the torque the nulls are judged on is the recorded one
    minus θ_u q̇ with θ_u each subject's own."""
    import torch

    from exolan.diagnose import compensate, nulls

    trials = _assisted_trials()
    for t in _assisted_trials(seed=4):
        t.subject = "S02"
        trials.append(t)
    flat = prepare(trials)
    s = Settings(steps_base=20, steps_refit=5, hidden=8, n_boot=100, verbose=False)
    ss, _ = procedure.reference(flat, s, None, Tools(), Workers(1), [0, 1])
    ss.sigma_r = 0.0
    subject_of_trial = np.array([0, 0, 1, 1])
    given = [("viscous_damping", 1)]
    init = {"viscous_damping": {1: 1.0}, "sized": {"viscous_damping": {1: np.zeros(2)}},
            "subject_of_trial": subject_of_trial}
    cur = extend(ss.base, flat, given, init=init)
    with torch.no_grad():
        getattr(cur, "size_viscous_damping")[:, 1] = torch.tensor([-0.4, 0.4])   # as if fitted apart
    own = [cur.physical(trial=t)["viscous_damping"][1, 1] for t in (0, 2)]
    assert own[1] / own[0] == pytest.approx(np.exp(0.8), rel=1e-6)
    made = []
    real_data = compensate.data
    monkeypatch.setattr(compensate, "data",
                        lambda f, terms, sizes, md: made.append(real_data(f, terms, sizes, md)) or made[-1])
    nulls.on_top(ss, blank_entry("torque_gain", 0, flat, ["S01", "S02"]), 0, (given, init), cur, {})
    comp = made[0]
    for t, theta in zip((0, 2), own):
        rows = flat.trial == t
        removed = (flat.tau[rows, 1] - comp.tau[rows, 1]).double()
        assert torch.allclose(removed, theta * flat.qd[rows, 1].double(), rtol=1e-5, atol=1e-5)
