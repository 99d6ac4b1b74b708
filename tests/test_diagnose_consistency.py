"""The recordings' check of physics first (`diagnose.consistency`): a term is taken only as a constant of the
joint. On drives whose Coulomb friction is planted recording by recording: the per-recording sizes are recovered,
a friction that changes between recordings (as a misfit that follows the motion does) is rejected although it is
significant over all of them, and the same friction at one size in every recording is accepted."""
import numpy as np
import pytest

from exolan.diagnose import consistency, physics
from exolan.diagnose.candidates import FITTED
from exolan.diagnose.flat import prepare
from exolan.diagnose.synthetic import servo_trial


def test_pooled_estimates_that_agree_are_consistent_and_a_scatter_around_zero_is_not():
    rng = np.random.default_rng(0)
    se = np.full(8, 0.1)
    same = consistency.pooled(2.0 + 0.1 * rng.standard_normal(8), se, "greater")
    assert same["consistent"] and same["prediction"][0] > 1.5 and same["tau"] < 0.2
    scatter = np.array([1.4, 1.5, -0.1, 0.8, 0.2, 0.05, 0.6, 2.5])        # mean 0.87: significant, not constant
    r = consistency.pooled(scatter, se, "greater")
    assert scatter.mean() / (0.1 / np.sqrt(8)) > 3                    # over all recordings at once: significant
    assert r["consistent"] is False and r["prediction"][0] < 0 < r["mean"]
    below = consistency.pooled(-scatter - 3.0, se, "two-sided", neutral=0.0)
    assert below["consistent"] and below["prediction"][1] < 0          # a two-sided term: either side of neutral
    assert consistency.pooled(np.array([1.0, 1.1]), np.array([0.1, 0.1]), "greater")["consistent"] is None
    assert consistency.pooled(np.array([1.0, np.nan, 1.2, 0.9]), np.array([0.1, 0.1, 0.0, 0.1]),
                              "greater")["consistent"] is None            # only two usable estimates


def _recordings(coulombs, viscous=200.0, seconds=8.0):
    return prepare([servo_trial(f"run{k}", seconds=seconds, seed=100 + k, mass=95.0, viscous=viscous, coulomb=c,
                                offset=-3.0) for k, c in enumerate(coulombs)])


@pytest.mark.parametrize("coulombs, taken", [((40.0, 10.0, 30.0, 12.0, 45.0, 8.0), False),
                                             ((20.0,) * 6, True)])
def test_a_friction_is_taken_only_where_every_recording_carries_it(coulombs, taken):
    flat = _recordings(coulombs)
    res = physics.identify(flat, FITTED, [0])
    msg = f"{coulombs}: {res.summary(('x',))}; {res.status.get(('coulomb_friction', 0))}"
    assert ("viscous_damping", 0) in res.accepted, msg
    assert (("coulomb_friction", 0) in res.accepted) == taken, msg
    test = next(t for t in res.tests if t["effect"] == "coulomb_friction")
    assert test["p"] <= test["threshold"], msg        # significant over all recordings either way
    if not taken:
        st, why = res.status[("coulomb_friction", 0)]
        assert st == "rejected" and "not a constant of the joint" in why, msg
    else:
        assert abs(res.estimates[("coulomb_friction", 0)].estimate / 20.0 - 1) <= 0.10, msg
    # the per-recording sizes, with the viscous friction in the fit
    prob = res._probs[0]
    th, se, trials = prob.by_trial(prob.fit(["viscous_damping", "coulomb_friction"]), "coulomb_friction")
    assert list(trials) == list(range(len(coulombs))), msg
    assert np.all(np.abs(th - np.array(coulombs)) <= 0.1 * np.array(coulombs) + 2.0), (th, se)
