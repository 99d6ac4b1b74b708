"""Parameter inference for a term of a fitted `ExtendedModel`: its θ's sensitivity, the Gauss-Newton step with a
Newey-West (HAC) standard error, the estimate's interval, per group and per subject, and rule 4 (identified)."""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy import stats as scipy_stats

from ..extensions import ExtendedModel
from . import stats
from .candidates import LIBRARY
from .fit import predict
from .flat import DTYPE, Flat


def sensitivity(model: ExtendedModel, flat: Flat, effect: str, j: int, idx: torch.Tensor):
    """The fitted physical parameter θ of (effect, joint j), and at the rows idx the mass-normalised residual
    r and its sensitivity J = ∂τ̂/∂θ (central finite difference through the raw parameter), both stacked
    joint-major and scaled by the square root of the fit weights where the fits are weighted. None for J when
    θ does not move (a parameter at a hard bound)."""
    raw, theta = LIBRARY[effect].raw_and_theta(model, j)
    scale = torch.as_tensor(flat.tau_scale, dtype=DTYPE)
    norm = flat.mass[idx, None] * scale
    if flat.weight is not None:      # the fits' weighted least squares (fit.misfit_weights)
        norm = norm / flat.weight[idx].sqrt()
    h = 1e-2
    with torch.no_grad():
        p0 = raw.data[j].clone()
        est = theta()
        raw.data[j] = p0 + h; tp = predict(model, flat, idx); th_p = theta()
        raw.data[j] = p0 - h; tm = predict(model, flat, idx); th_m = theta()
        raw.data[j] = p0
        t0 = predict(model, flat, idx)
    r = ((flat.tau[idx] - t0) / norm).numpy().astype(np.float64).T.reshape(-1)
    dth = th_p - th_m
    if not np.isfinite(dth) or abs(dth) < 1e-15:
        return float(est), None, r
    J = ((tp - tm) / dth / norm).numpy().astype(np.float64).T.reshape(-1)
    return float(est), (J if np.std(J) > 0 else None), r


def hac_step(J: np.ndarray, r: np.ndarray, n_rows: int) -> tuple[float, float, int]:
    """Gauss-Newton step of θ that the residual r asks for along the sensitivity J, and its Newey-West SE
    (statsmodels OLS, HAC lags = the ACF block length of the first joint's residual)."""
    import statsmodels.api as sm

    lags = stats.block_length(r[:n_rows])
    fitres = sm.OLS(r, J[:, None]).fit(cov_type="HAC", cov_kwds={"maxlags": int(lags)})
    return float(fitres.params[0]), float(fitres.bse[0]), int(lags)


def param_ci(model: ExtendedModel, flat: Flat, effect: str, j: int) -> dict:
    """Estimate and 95% CI of (effect, joint) by the HAC sandwich on the training residuals.

    Linearise the prediction in the physical parameter θ at its fitted value, regress the residual on that
    sensitivity with statsmodels OLS and a Newey-West covariance; the coefficient's SE is θ's conditional
    standard error given the rest of the model (it ignores the networks' flexibility, so it is a lower bound
    on the uncertainty; the held-out gain and the rivals' comparison guard against over-confidence).
    """
    tr = flat.index("train")
    if len(tr) > 20000:
        tr = tr[torch.linspace(0, len(tr) - 1, 20000).long()]
    est, J, r = sensitivity(model, flat, effect, j, tr)
    if J is None:
        return dict(estimate=float(est), ci=[float("nan"), float("nan")], se=float("nan"))
    _, se, lags = hac_step(J, r, len(tr))
    return dict(estimate=float(est), ci=[float(est - 1.96 * se), float(est + 1.96 * se)], se=se, hac_lags=lags)


def param_by_group(model: ExtendedModel, flat: Flat, effect: str, j: int, held: torch.Tensor,
                    masks: dict) -> dict:
    """θ as the held-out samples of each subset (name → mask over `held`) would have it (rule 5).

    One Gauss-Newton step from the fitted θ on each subset, with the networks fixed: θ_S = θ̂ + β_S where β_S
    regresses the subset's held-out residual on the sensitivity ∂τ̂/∂θ (HAC SE). A term that soaks up one
    task's misfit wants a large θ there and another elsewhere; a property of the joint wants the same θ
    wherever the data carry evidence, and an uninformative subset (a joint that barely moves, an actuator
    at its limit) has a wide interval that contradicts nothing. Subsets too small or without sensitivity
    are left out.
    """
    out = {}
    for name, mask in masks.items():
        idx = held[torch.as_tensor(np.asarray(mask, bool))]
        if len(idx) < 50:
            continue
        if len(idx) > 20000:
            idx = idx[torch.linspace(0, len(idx) - 1, 20000).long()]
        est, J, r = sensitivity(model, flat, effect, j, idx)
        if J is None:
            continue
        step, se, _ = hac_step(J, r, len(idx))
        out[name] = dict(estimate=est + step, se=se)
    return out


def cochran_q(theta: np.ndarray, se: np.ndarray) -> tuple[float, float]:
    """Cochran's Q of estimates θ with standard errors se (inverse-variance weights) and its χ² p-value
    (df = len − 1): do the groups want the same θ?"""
    w = 1.0 / np.square(se)
    Q = float(np.sum(w * (theta - np.sum(w * theta) / np.sum(w)) ** 2))
    return Q, float(scipy_stats.chi2.sf(Q, len(theta) - 1))


def param_by_subject(model: ExtendedModel, flat: Flat, effect: str, j: int, users: list[str]) -> dict:
    """A sized term's value for each subject, θ_u = θ e^{a_u}, with a 95 % CI by the HAC sandwich on that
    subject's training rows (as `param_ci`, conditional on the networks and the other subjects' sizes),
    in vocabulary units (strap: k)."""
    tr = flat.index("train")
    subj = flat.subjects_of(tr)
    out = {}
    for u in users:
        idx = tr[torch.as_tensor(subj == u)]
        if len(idx) < 50:
            continue
        if len(idx) > 20000:
            idx = idx[torch.linspace(0, len(idx) - 1, 20000).long()]
        size = model.trial_factor(effect, j, int(flat.trial[idx[0]]))
        est, J, r = sensitivity(model, flat, effect, j, idx)
        th_u = est * size
        se = float("nan") if J is None else hac_step(J / size, r, len(idx))[1]
        val, ci = LIBRARY[effect].report_param(dict(estimate=th_u, ci=[th_u - 1.96 * se, th_u + 1.96 * se]))
        out[u] = dict(estimate=val, ci=ci, size=size)
    return out


def with_refit_spread(pci: dict, other: dict) -> dict:
    """The joint fit's estimate with an interval that includes the optimisation's own uncertainty.

    The HAC sandwich SE is conditional on the fitted networks. The joint refit (from scratch, every accepted
    term present) and the single-term warm start are two fits of the same parameter from different
    starting points; their difference d estimates the refit SD as |d|/√2, added in quadrature. (A pull shared
    by both fits is in neither part; the held-out gain, not this interval, carries the decision.)
    """
    est, se = pci["estimate"], pci.get("se", float("nan"))
    d = est - other.get("estimate", est)
    if not (np.isfinite(se) and np.isfinite(d)):
        return pci
    se_tot = float(math.sqrt(se ** 2 + d ** 2 / 2.0))
    return dict(pci, se=se_tot, se_hac=se, ci=[est - 1.96 * se_tot, est + 1.96 * se_tot])


def identifiable(effect: str, pci: dict, max_delay: float = float("inf")) -> bool:
    """The parameter's CI excludes the no-effect value and stays inside the searched physical range.

    A delay whose CI reaches the largest delay searched means the data want "more of this feature", not a
    particular lag: the exo torque is standing in for something else (it is a lagged copy of the human
    torque), so it is not identified as a delay.
    """
    lo, hi = pci["ci"]
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return False
    if LIBRARY[effect].bounded_by_max_delay and hi >= 0.95 * max_delay:
        return False
    neutral = LIBRARY[effect].theta_neutral   # strap: compliance CI excludes 0 ⇔ stiffness CI excludes ∞
    if LIBRARY[effect].positive:
        return lo > neutral
    return not (lo <= neutral <= hi)
