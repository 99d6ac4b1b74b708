"""Detection limits of the exo-driven terms: computed at the base's misfit (default), or measured by writing a
known gain or delay into the data and running the candidate's own test on it (refits; only when asked)."""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from scipy import stats as sps

from ..data import savgol_derivative
from . import stats
from .candidates import LIBRARY
from .export import extend
from . import weights
from .fit import predict, train
from .flat import Flat, exo_copy
from .refits import base_fit, held_errors, refit
from .rules import above_noise, own_variation_passes, paired_gain
from .nulls import on_own_variation
from .screen import screen
from .settings import Settings, log


def torque_unit(flat: Flat) -> str:
    """The unit of the errors every gain is measured in: torque per body mass where the data carry a mass
    (layout 1, N m/kg), else the joints' own (layout 2, mass 1: N m revolute, N prismatic)."""
    if not bool((flat.mass == 1.0).all()):
        return "N m/kg"
    kinds = set(flat.joint_types)
    return "N m" if kinds == {"revolute"} else "N" if kinds == {"prismatic"} else "N m or N"


def gain_detection_limit(flat: Flat, model, held: torch.Tensor, w_held: np.ndarray | None, sigma_r: float,
                         s: Settings, predict=predict, level: float = 0.05) -> dict:
    """Per joint with exo torque: how far from 1 a torque gain k must be before these data can show it.

    Physics: the sensor reads k times the applied torque, so the joint's torque differs from the model's by
    θ τ_e with θ = 1 − 1/k, τ_e the recorded exo torque. The part of τ_e that copies the joint torque
    (`exo_copy`) is a function of the motion the base already predicts, so the base absorbs θ times it; only
    the controller's own variation o = τ_e − copy identifies k (rule 3's own-variation null). Fitting θ
    removes δ = θ o from a residual ε, so its held-out gain is, per sample, w (δ² + 2 δ ε) (w: the decision's
    weight, all mass-normalised): mean θ² P with P = mean(w o²), and a sampling error 2 |θ| SE(w o ε) (block
    bootstrap). It is seen when θ² P clears z √(σ_r² + 4 θ² SE²), the refit noise included, z the normal quantile
    of the decision's own two-sided level (`level`: the single-term test's α/m, not 5 %, so that the limit is the
    one the decision can reach); solved for
    |θ| (`theta_limit`), that is k below 1/(1 + |θ|) (`k_below`) or above 1/(1 − |θ|) (`k_above`). An
    estimate under the model's present misfit ε (the reference's, less its share of o, which a gain present
    in the data would put there), not a guarantee, and an optimistic one
    where the base also absorbs part of o (a saturating controller's own variation is partly a function of
    the motion; measured: docs/DIAGNOSIS.md, "Measurements behind the code"): it tells the user that
    a gain closer to 1 than this is not a finding this data set can make.
    """
    return detection_limits(flat, model, held, w_held, sigma_r, s, predict, level)["torque_gain"]


def delay_detection_limit(flat: Flat, model, held: torch.Tensor, w_held: np.ndarray | None, sigma_r: float,
                          s: Settings, predict=predict, level: float = 0.05) -> dict:
    """Per joint with exo torque: the shortest actuation delay d these data can show (seconds, `d_limit`).

    Physics: the limb feels the recorded torque d later, so the joint's torque differs from the model's by
    τ_e(t) − τ_e(t−d) ≈ d τ̇_e (first order in d). As for a gain (`gain_detection_limit`), the part of τ̇_e that
    follows the joint torque's recent past is a function of the motion the base already predicts, so only the
    rate of the controller's own variation ȯ identifies d: the same detection arithmetic with x = ȯ and θ = d.
    First order and at the base's present misfit: a delay near the limit is also estimated short (the base keeps
    part of it; measured: docs/DIAGNOSIS.md, "Measurements behind the code"). It tells the user that a shorter delay
    is not a finding this data set can make, and that one near the limit is estimated with that bias.
    """
    return detection_limits(flat, model, held, w_held, sigma_r, s, predict, level)["actuation_delay"]


def rate_per_trial(x: np.ndarray, flat: Flat) -> np.ndarray:
    """ẋ of a flat series (float64), trial by trial, by the data's Savitzky-Golay derivative
    (`data.savgol_derivative`): a delay shifts the recorded torque's noise too, which identifies nothing (it
    cancels in τ_rec), while a central difference turns that white noise into a large rate and the delay's limit
    into an optimistic one."""
    return np.concatenate([savgol_derivative(seg, flat.dt) for seg in np.split(x, np.cumsum(flat.lengths)[:-1])])


def detection_limits(flat: Flat, model, held: torch.Tensor, w_held: np.ndarray | None, sigma_r: float,
                     s: Settings, predict=predict, level: float = 0.05) -> dict:
    """`{"torque_gain": gain_detection_limit, "actuation_delay": delay_detection_limit}` in one pass: the model's
    held-out misfit and each joint's own variation o = τ_e − copy are computed once. Both limits solve the
    arithmetic of `gain_detection_limit`'s docstring for an effect δ = θ x (mass-normalised): x = o for a gain
    (θ = 1 − 1/k), x = ȯ for a delay (θ = d), at the decision's two-sided `level`."""
    z = float(sps.norm.ppf(1.0 - level / 2.0))
    gain, delay = {}, {}
    if not flat.has_exo or not len(held):
        return {"torque_gain": gain, "actuation_delay": delay}
    h = held.numpy()
    m = flat.mass[held].numpy().astype(np.float64)
    eps = ((flat.tau[held] - predict(model, flat, held)) / flat.mass[held, None]).numpy().astype(np.float64)

    def theta_limit(x: np.ndarray, e: np.ndarray, w: np.ndarray) -> float | None:
        P = float(np.mean(w * x ** 2))
        # the misfit without the effect: ε less its own (weighted least-squares) share of x. Where the effect is
        # there, the reference's ε holds part of θ x, which inflated SE(w x ε) by the effect itself
        # (docs/DIAGNOSIS.md)
        r = e - (float(np.sum(w * x * e) / np.sum(w * x ** 2)) * x if P > 0 else 0.0)
        se = float(stats.bootstrap_mean(w * x * r, n_boot=s.n_boot, seed=s.seed).get("se", np.nan))
        if not (P > 0 and np.isfinite(se)):
            return None
        b = 4.0 * z ** 2 * se ** 2
        return math.sqrt((b + math.sqrt(b * b + 4.0 * P ** 2 * (z * sigma_r) ** 2)) / (2.0 * P ** 2))

    for j, name in enumerate(flat.joints):
        te_all = flat.tau_e[:, j].numpy().astype(np.float64)
        te = te_all[h]
        if not np.abs(te).max() > 0:
            continue
        own_all = te_all - exo_copy(flat, j).tau_e[:, j].numpy().astype(np.float64)
        own = own_all[h]
        rate = np.nan_to_num(rate_per_trial(own_all, flat)[h])
        w = w_held[:, j] if w_held is not None else np.ones(len(te))
        var_te = float(np.var(te))
        sizes = dict(level=level, copy_share=float(1.0 - np.var(own) / var_te) if var_te > 0 else float("nan"),
                     rms_exo=float(np.sqrt(np.mean(te ** 2))), rms_own=float(np.sqrt(np.mean(own ** 2))))
        theta = theta_limit(own / m, eps[:, j], w)
        if theta is not None:
            gain[name] = dict(theta_limit=theta, k_below=1.0 / (1.0 + theta),
                              k_above=1.0 / (1.0 - theta) if theta < 1.0 else float("inf"), **sizes)
        d = theta_limit(rate / m, eps[:, j], w)
        if d is not None:
            delay[name] = dict(d_limit=d, **sizes)
    return {"torque_gain": gain, "actuation_delay": delay}


def injected_limit(g0: float, se0: float, sigma_r: float, theta0: float, level: float = 0.05) -> float:
    """The |θ| at which rule 3's own-variation test would just pass, scaled from one injection at θ0 that gave the
    held-out gain g0 with bootstrap SE se0: the gain grows as θ² and its sampling error (2 θ SE(w o ε)) as θ, so
    with u = (θ/θ0)² the test's bound u g0 = z √(u se0² + σ_r²) is a quadratic in u (z: the normal quantile of the
    decision's two-sided `level`). Infinite where the injection itself did not show (g0 ≤ 0)."""
    if not (g0 > 0 and np.isfinite(se0)):
        return float("inf")
    z2 = float(sps.norm.ppf(1.0 - level / 2.0)) ** 2
    u = (z2 * se0 ** 2 + math.sqrt(z2 ** 2 * se0 ** 4 + 4.0 * g0 ** 2 * z2 * sigma_r ** 2)) / (2.0 * g0 ** 2)
    return theta0 * math.sqrt(u)


@dataclass
class InjectionFits:
    """What `limits_by_injection` fits and predicts with (tests pass stubs)."""
    predict: Callable = predict
    train: Callable = train
    refit: Callable = refit
    screen: Callable = screen
    injected_limit: Callable = injected_limit


def limits_by_injection(flat: Flat, s: Settings, base_start, ref, held: torch.Tensor, sigma_r: float,
                        analytic: dict, gain: bool = True, delay: bool = True,
                        fits: InjectionFits | None = None, level: float = 0.05) -> dict:
    """The torque gain and the actuation delay these data can show, per joint of `analytic`
    (`detection_limits`), measured by injection and recovery instead of computed at the base's present misfit:
    `{"torque_gain": {joint: ...}, "actuation_delay": {joint: ...}}` (a kind not asked for is left empty).

    The share of the controller's own variation o (and of its rate ȯ) that the reference leaves in its training
    residual comes out of the recorded torque first (an effect already in the data would add to the injected
    one); then a gain k0 = 1/(1 − θ0) is written as τ_rec + θ0 τ_e and a delay d0 as τ_rec + τ_e(t) − τ_e(t − d0),
    the base fitted again from its start, and the candidate's own test run on it (a gain: rule 3's own-variation
    test; a delay: rules 1 and 2). The injection's gain and SE scale as θ² to where the test just passes
    (`injected_limit`); θ0 is twice the computed limit, and an answer outside [0.6, 1.5] θ0 is measured again at
    1.2 times it. Where the base is a given run the computed limits are kept (empty result). Why, and what it
    measured: docs/DIAGNOSIS.md ("Measurement log", detection limits)."""
    fits = fits or InjectionFits()
    g_lim, d_lim = (analytic.get("torque_gain") or {}), (analytic.get("actuation_delay") or {})
    gj = [j for j, nm in enumerate(flat.joints) if gain and nm in g_lim]
    dj = [j for j, nm in enumerate(flat.joints) if delay and nm in d_lim]
    out = {"torque_gain": {}, "actuation_delay": {}}
    if base_start is None or not (gj or dj):
        return out
    d_lo, d_hi = 2.0 * flat.dt, 0.5 * s.max_delay
    first_at = {("torque_gain", j): float(np.clip(2.0 * g_lim[flat.joints[j]]["theta_limit"], 0.2, 0.8)) for j in gj}
    first_at.update({("actuation_delay", j): float(np.clip(2.0 * d_lim[flat.joints[j]]["d_limit"], d_lo, d_hi))
                     for j in dj})
    train_rows = flat.index("train")
    resid = flat.tau[train_rows] - fits.predict(ref, flat, train_rows)
    cleaned = flat.tau.clone()
    for j in sorted(set(gj) | set(dj)):
        # the data may hold the effect already, which an injection would add to (docs/DIAGNOSIS.md). So
        # the share of the own variation (and of its rate) that the reference leaves in its training residual
        # (least squares) comes out first, as the computed limit does: what is left is absorbed by the base anyway
        o = flat.tau_e[:, j] - exo_copy(flat, j).tau_e[:, j]
        cols = [o] + ([torch.as_tensor(rate_per_trial(o.numpy().astype(np.float64), flat), dtype=o.dtype)]
                      if j in dj else [])
        X = torch.stack(cols, 1).double()
        beta = torch.linalg.lstsq(X[train_rows], resid[:, j:j + 1].double()).solution[:, 0]
        cleaned[:, j] = flat.tau[:, j] - (X @ beta).to(flat.tau.dtype)

    def measure(at: dict) -> dict:
        inj = copy.copy(flat)
        inj.tau = cleaned.clone()
        for (eff, j), v in at.items():
            te = flat.tau_e[:, j]
            inj.tau[:, j] += LIBRARY[eff].injected(te, v, flat.lengths, flat.dt)
        inj.weight = None
        base_i = copy.deepcopy(base_start)
        base_fit(base_i, inj, s, "detection limit by injection: base fit", trainer=fits.train)
        if s.weighted:
            inj.weight = weights.of_base(base_i, inj, s)
        w = inj.weight[held].numpy().astype(np.float64) if s.decide_weighted and inj.weight is not None else None
        ref_i = copy.deepcopy(base_i)
        fits.refit(ref_i, inj, s)
        e_ref = held_errors(ref_i, inj, held, w)[1]
        res = {}
        for (eff, j), v in at.items():
            sc = fits.screen(ref_i, inj, eff, j, n_boot=max(s.n_boot // 3, 100), seed=s.seed)
            if LIBRARY[eff].lag_free:       # a gain shows only on the controller's own variation (rule 3)
                g, k_hat = on_own_variation(base_i, inj, j, LIBRARY[eff].screen_init(sc), e_ref, held, w, s,
                                              refit_fn=fits.refit)
                th = fits.injected_limit(g["gain"], g["se"], sigma_r, v, level)
                k0 = 1.0 / (1.0 - v)
                res[(eff, j)] = dict(theta_limit=th, k_below=1.0 / (1.0 + th),
                                     k_above=1.0 / (1.0 - th) if th < 1.0 else float("inf"),
                                     injected_k=k0, recovered_k=k_hat, injected_gain=g["gain"],
                                     injected_gain_ci=g["ci"], passes_at_injection=own_variation_passes(
                                         g, sigma_r, k_hat, k0), limit=th)
            else:
                term = extend(base_i, inj, [(eff, j)], init=LIBRARY[eff].screen_init(sc), max_delay=s.max_delay)
                fits.refit(term, inj, s)
                g = paired_gain(e_ref, held_errors(term, inj, held, w)[1], s)
                d_hat = term.estimate(eff, j)
                # a delay already in the data that the base had absorbed adds to the injected one once the term
                # is there (docs/DIAGNOSIS.md): the gain is that of the delay the term found, so it scales from
                # the larger of the two
                dl = fits.injected_limit(g["gain"], g["se"], sigma_r, max(v, d_hat), level)
                res[(eff, j)] = dict(d_limit=dl, injected_d=v, recovered_d=d_hat,
                                     injected_gain=g["gain"], injected_gain_ci=g["ci"],
                                     passes_at_injection=bool(g["ci"][0] > 0 and above_noise(g, sigma_r)), limit=dl)
        return res

    first = measure(first_at)
    # the θ² scaling holds near the injection (the base absorbs a share of it that need not be the same for a small
    # and a large effect; docs/DIAGNOSIS.md): where the limit lies far from it, a second injection at the limit (1.2
    # times it) gives the answer
    bounds = {"torque_gain": (0.1, 0.8), "actuation_delay": (d_lo, d_hi)}
    again = {key: float(np.clip(1.2 * v["limit"], *bounds[key[0]])) for key, v in first.items()
             if not 0.6 * first_at[key] <= v["limit"] <= 1.5 * first_at[key]}
    again = {key: v for key, v in again.items() if abs(v - first_at[key]) > 1e-6}
    if again:
        second = measure({**first_at, **again})
        first.update({key: dict(second[key], first_injection=first[key]) for key in again})
    for (eff, j), v in first.items():
        v.pop("limit")
        v.get("first_injection", {}).pop("limit", None)
        out[eff][flat.joints[j]] = v
    return out


def all_limits(flat: Flat, s: Settings, base_start, ref, held: torch.Tensor, w_held, sigma_r: float,
               level: float) -> dict:
    """The detection limits of the exo-driven terms at the decision's two-sided `level` (`Budget.single`): computed
    at the base's misfit; measured by injection (refits) only where asked (`Settings.inject_gain`, `inject_delay`)."""
    limits = detection_limits(flat, ref, held, w_held, sigma_r, s, level=level)
    if s.inject_gain or s.inject_delay:
        t1 = time.time()
        measured = limits_by_injection(flat, s, base_start, ref, held, sigma_r, limits, gain=s.inject_gain, level=level,
                                       delay=s.inject_delay)
        for name, v in measured["torque_gain"].items():
            computed = limits["torque_gain"][name]
            limits["torque_gain"][name] = dict(computed, **v, method="injection", computed=dict(
                theta_limit=computed["theta_limit"], k_below=computed["k_below"], k_above=computed["k_above"]))
            log(s, f"torque gain on {name}: a gain of {v['injected_k']:.3g} written into the data was recovered as "
                    f"{v['recovered_k']:.3g} on the own variation, held-out gain {v['injected_gain']:.3g} "
                    f"[{v['injected_gain_ci'][0]:.3g}, {v['injected_gain_ci'][1]:.3g}] ({time.time() - t1:.0f} s)")
        for name, v in measured["actuation_delay"].items():
            computed = limits["actuation_delay"][name]
            limits["actuation_delay"][name] = dict(computed, **v, method="injection",
                                                   computed=dict(d_limit=computed["d_limit"]))
            log(s, f"actuation delay on {name}: a delay of {1e3 * v['injected_d']:.3g} ms written into the data was "
                    f"recovered as {1e3 * v['recovered_d']:.3g} ms, held-out gain {v['injected_gain']:.3g} "
                    f"[{v['injected_gain_ci'][0]:.3g}, {v['injected_gain_ci'][1]:.3g}] ({time.time() - t1:.0f} s)")
    for name, v in limits["torque_gain"].items():
        log(s, f"torque gain on {name}: not detectable between k ≈ {v['k_below']:.3g} and {v['k_above']:.3g} (the "
                f"copy of the joint torque is {100 * v['copy_share']:.0f} % of the exo torque's variance)")
    for name, v in limits["actuation_delay"].items():
        log(s, f"actuation delay on {name}: not detectable below d ≈ {1e3 * v['d_limit']:.3g} ms" if math.isfinite(
            v["d_limit"]) else f"actuation delay on {name}: no delay up to {1e3 * v['injected_d']:.3g} ms shows")

    return limits
