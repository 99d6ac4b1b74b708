"""Is a term a constant of the joint, or a shape of the base's misfit? Its size in every recording, pooled.

Why: the parametric base misses what no recorded signal carries (the pelvis' motion, the horizontal ground
force); that misfit follows each task's motion, repeats in every stride, and so projects onto any candidate
column that also follows the motion (the sign of a knee's velocity marks the gait phase). Such a projection is
significant under any test over time and carries to held-out segments of the same trials, but its size changes
from one recording to the next; a physical constant (a friction, a delay) does not. So each term is also fitted
with its column split by trial, and the trials' estimates are pooled by a random-effects model (Paule-Mandel
between-trial variance τ², statsmodels `combine_effects`). The term is *consistent* when the 95 % prediction
interval for a new recording, μ ± t(k−2) √(τ² + SE(μ)²) (Higgins, Thompson & Spiegelhalter 2009), lies on the
physical side of no effect. With fewer than three trials the spread between recordings cannot be estimated and the
check does not apply (one recording of a drive).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
from scipy import stats as sps
from statsmodels.stats.meta_analysis import combine_effects

from . import ident

MIN_TRIALS = 3


def pooled(theta: np.ndarray, se: np.ndarray, sided: str, neutral: float = 0.0, level: float = 0.95) -> dict:
    """Random-effects pool of per-trial estimates `theta` (SEs `se`); `consistent`: the prediction interval for
    a new trial excludes `neutral` on the physical side (`sided`: "greater" or "two-sided"); None when fewer than
    MIN_TRIALS trials carry an estimate."""
    ok = np.isfinite(theta) & np.isfinite(se) & (se > 0)
    th, s = np.asarray(theta, float)[ok], np.asarray(se, float)[ok]
    k = len(th)
    if k < MIN_TRIALS:
        return dict(k=k, consistent=None, note=f"{k} trial(s) with an estimate: the spread between recordings "
                                                "cannot be estimated, the check does not apply")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")     # it warns that per-trial intervals use the normal law; we use none of them
        r = combine_effects(th, s ** 2, method_re="iterated")
    mu, sd, tau2 = float(r.mean_effect_re), float(r.sd_eff_w_re), float(max(r.tau2, 0.0))
    half = float(sps.t.ppf(0.5 + level / 2, k - 2)) * math.sqrt(tau2 + sd * sd)
    lo, hi = mu - half, mu + half
    consistent = lo > neutral if sided == "greater" else (lo > neutral or hi < neutral)
    return dict(k=k, mean=mu, se=sd, tau=math.sqrt(tau2), prediction=[lo, hi], consistent=bool(consistent),
                i2=float(r.i2))


def text(c: dict, estimate: float) -> str:
    """Why a term failed the check, for the report (`c`: `pooled`, or a split term's per-subject pools)."""
    parts = c.get("by_subject", {"": c})
    said = "; ".join(f"{u + ': ' if u else ''}{v['k']} recordings, mean θ {v['mean']:.3g}, spread between "
                     f"recordings τ {v['tau']:.3g}, prediction interval [{v['prediction'][0]:.3g}, "
                     f"{v['prediction'][1]:.3g}]" for u, v in parts.items() if v.get("consistent") is not None)
    return (f"its size (here {estimate:.4g}) is not a constant of the joint: fitted recording by recording it changes "
            f"more than its intervals allow, and a new recording's 95 % prediction interval holds no effect ({said}); "
            "a misfit of the base that follows the motion looks like this")


def across_trials(prob: ident.JointProblem, f: ident.Fit, e: str, split: bool, flat) -> dict:
    """The term's size in each trial (`ident.JointProblem.by_trial`), pooled: over every trial, or, for a term
    split by subject (an effect in at least one subject), over each subject's trials — consistent where any
    subject's is."""
    th, se, trials = prob.by_trial(f, e)
    sided = ident.TERMS[e].sided
    if not split:
        return pooled(th, se, sided)
    subj = np.array([flat.trial_meta[k]["subject"] for k in trials])
    per = {str(u): pooled(th[subj == u], se[subj == u], sided) for u in np.unique(subj)}
    known = [v["consistent"] for v in per.values() if v["consistent"] is not None]
    return dict(by_subject=per, consistent=any(known) if known else None)
