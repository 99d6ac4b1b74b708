"""The claims' statistics: the paired tests and the verdict rule (issue 37: a claim holds only by a size that
matters, significant over held-out users and over seeds)."""
import pytest


def test_paired_statistics():
    from exolan import report
    a = {f"u{i}": 1.0 + 0.01 * i for i in range(7)}
    b = {f"u{i}": 2.0 + 0.01 * i for i in range(7)}
    r = report.paired(a, b, [1.0, 1.1], [2.0, 2.2])
    assert r["rel_change"] < 0 and r["users_better"] == 7
    assert r["p_wilcoxon_users"] == pytest.approx(1 / 64)  # exact two-sided, all 7 in one direction
    assert report.stats._holds(r, -0.05) == "holds"
    assert report.stats._holds(r, +0.05) == "reversed (significant)"


def test_verdict_needs_a_size_that_matters():
    from exolan.report import verdict
    # the small scale's multi-step result: -0.4 % at p < 0.05 where the paper has -93 %: not a result
    assert verdict(-0.004, 0.01, -0.93) == "same direction, negligible"
    assert verdict(-0.30, 0.01, -0.93) == "holds"                       # ≥ a quarter of -93 %
    assert verdict(-0.22, 0.01, -0.93) == "same direction, negligible"  # < 23.25 %
    assert verdict(-0.30, 0.20, -0.93) == "same direction, not significant"
    assert verdict(+0.031, 0.01, -0.07) == "reversed (significant)"
    assert verdict(+0.031, 0.30, -0.07) == "reversed, not significant"
    # direction-only claims (LIM improves a model): at least 5 %
    assert verdict(-0.04, 0.001, None) == "same direction, negligible"
    assert verdict(-0.06, 0.001, None) == "holds"
    assert verdict(float("nan"), 0.01, -0.5) == "n/a"
    # the seeds are training's replicates: significant over users but not over seeds is not significant
    # (the converge sweep's multi-step claim, +13.5 % with p 0.016 over users and 0.079 over seeds)
    assert verdict(+0.135, 0.0156, -0.93, p_seeds=0.079) == "reversed, not significant"
    assert verdict(-0.32, 0.0156, -0.07, p_seeds=0.0057) == "holds"
    assert verdict(-0.32, 0.0156, -0.07, p_seeds=0.2) == "same direction, not significant"
    assert verdict(-0.32, 0.0156, -0.07, p_seeds=float("nan")) == "holds"     # one seed: users alone
