"""What is wrong: inverse-dynamics residuals, their structure, open-loop rollouts and an energy audit.

All functions take a fitted model (the slow-context base or an `ExtendedModel` around it) and a `Flat`.
Residual r = τ_rec − τ̂ in N m (per joint). Summaries use held-out samples unless stated.
"""
from __future__ import annotations

import numpy as np
import torch

from ..extensions import ExtendedModel
from . import stats
from .base import _base_of
from .fit import predict
from .flat import Flat


def residuals(model, flat: Flat, idx: torch.Tensor) -> np.ndarray:
    """τ_rec − τ̂ (len(idx), n), N m."""
    return (flat.tau[idx] - predict(model, flat, idx)).numpy().astype(np.float64)


def torque_metrics(model, flat: Flat, idx: torch.Tensor, n_boot: int = 500, seed: int = 0) -> dict:
    """Held-out torque MSE (N² m²) and mass-normalised MSE ((N m/kg)²), per joint and total, with CIs; R²."""
    r = residuals(model, flat, idx)
    m = flat.mass[idx].numpy().astype(np.float64)
    tau = flat.tau[idx].numpy().astype(np.float64)
    sq = (r ** 2).sum(1)
    sqn = ((r / m[:, None]) ** 2).sum(1)
    tot = stats.bootstrap_mean(sq, n_boot=n_boot, seed=seed)
    totn = stats.bootstrap_mean(sqn, n_boot=n_boot, seed=seed)
    out = dict(torque_mse=tot["mean"], torque_mse_ci=tot["ci"], torque_mse_norm=totn["mean"],
               torque_mse_norm_ci=totn["ci"], n_samples=int(len(idx)), per_joint={})
    for j, name in enumerate(flat.joints):
        var = float(np.var(tau[:, j]))
        mse = float(np.mean(r[:, j] ** 2))
        out["per_joint"][name] = dict(mse=mse, rms=float(np.sqrt(mse)), r2=float(1 - mse / var) if var > 0 else float("nan"))
    return out


def residual_structure(model, flat: Flat, idx: torch.Tensor, max_lag: int = 40) -> dict:
    """Per joint: size, whiteness (Ljung-Box), cross-correlation with q, q̇, q̈, τ_e, τ̇_e, f_v at lags.

    Residuals are concatenated over held-out segments; the few lags that straddle a segment boundary are
    a negligible fraction of the series.
    """
    r = residuals(model, flat, idx)
    feats = {"q": flat.q[idx].numpy(), "qd": flat.qd[idx].numpy(), "qdd": flat.qdd[idx].numpy()}
    if flat.has_exo:
        feats["tau_e"] = flat.tau_e[idx].numpy()
        feats["tau_e_rate"] = flat.tau_e_d[idx].numpy()
    if flat.has_insole:
        feats["f_v"] = np.repeat(flat.f_v[idx].numpy()[:, None], flat.n, axis=1)
    out = {}
    for j, name in enumerate(flat.joints):
        rj = r[:, j]
        entry = dict(rms=float(np.sqrt(np.mean(rj ** 2))), mean=float(rj.mean()),
                     ljung_box=stats.ljung_box(rj), block_length=stats.block_length(rj), ccf={})
        for fname, F in feats.items():
            for k, other in enumerate(flat.joints):
                if fname == "f_v" and k != j:
                    continue
                key = fname if fname == "f_v" else f"{fname}_{other}"
                entry["ccf"][key] = stats.cross_correlation(rj, F[:, k].astype(np.float64), max_lag)
        out[name] = entry
    return out


def energy_audit(model, flat: Flat, idx: torch.Tensor, n_boot: int = 500, seed: int = 0) -> dict:
    """Power the model cannot account for: P_res = q̇ᵀ (τ_rec − τ̂), W.

    A missing dissipation leaves P_res > 0 on average (the actuators supply power the conservative model
    attributes to nothing); a missing energy source gives P_res < 0. Reported with a block-bootstrap CI and
    relative to the mean absolute input power |q̇ᵀ τ_rec|.
    """
    r = residuals(model, flat, idx)
    qd = flat.qd[idx].numpy().astype(np.float64)
    tau = flat.tau[idx].numpy().astype(np.float64)
    p_res = (qd * r).sum(1)
    p_in = np.abs((qd * tau).sum(1)).mean()
    b = stats.bootstrap_mean(p_res, n_boot=n_boot, seed=seed)
    per = {name: float(np.mean(qd[:, j] * r[:, j])) for j, name in enumerate(flat.joints)}
    return dict(residual_power=b["mean"], residual_power_ci=b["ci"], input_power_abs=float(p_in),
                fraction=float(b["mean"] / p_in) if p_in > 0 else float("nan"), per_joint=per)


def rollout_starts(flat: Flat, horizon: int, max_starts: int = 512, seed: int = 0) -> torch.Tensor:
    """Held-out start indices whose next `horizon` samples stay in the same held-out segment and are valid."""
    N = flat.q.shape[0]
    ok = (flat.held & flat.valid).numpy()
    seg = flat.segment.numpy()
    idx = np.arange(N - horizon)
    good = np.ones(len(idx), bool)
    for h in range(horizon + 1):
        good &= ok[idx + h] & (seg[idx + h] == seg[idx])
    cand = idx[good]
    rng = np.random.default_rng(seed)
    if len(cand) > max_starts:
        cand = np.sort(rng.choice(cand, max_starts, replace=False))
    return torch.as_tensor(cand, dtype=torch.long)


def rollout_errors(model, flat: Flat, starts: torch.Tensor, horizon: int = 20) -> dict:
    """Open-loop semi-implicit Euler rollouts (DESIGN.md section 5) from measured states at `starts`.

    The recorded τ, z and f_v drive each step. For an extended model the state is integrated in physical
    coordinates (encoder offset and strap deflection removed) and mapped back to measured coordinates to
    compare. Returns per-horizon mean squared q and q̇ errors (summed over joints), per start.
    """
    base = _base_of(model)
    ext = model if isinstance(model, ExtendedModel) else None
    dt = flat.dt
    B = len(starts)
    eq = np.zeros((B, horizon)); eqd = np.zeros((B, horizon))
    if B == 0:
        return dict(q=[], qd=[], q_per_start=eq, qd_per_start=eqd)
    with torch.no_grad():
        def obs_shift(i):
            """measured − physical coordinates at rows i (q, q̇)."""
            if ext is None:
                z = torch.zeros_like(flat.q[i])
                return z, z
            he, hd, hdd = flat.exo_lagged(i)
            tr = flat.trial[i]
            app, app_d, _ = ext.applied_exo(he, hd, hdd, trial=tr)
            qt, qdt, _ = ext.true_state(flat.q[i], flat.qd[i], None, app, app_d, None, trial=tr)
            return flat.q[i] - qt, flat.qd[i] - qdt

        i = starts.clone()
        dq, dqd = obs_shift(i)
        q = flat.q[i] - dq
        qd = flat.qd[i] - dqd
        z = base.z_of(flat.trial[i])
        for h in range(horizon):
            if ext is None:
                qdd = base.forward_dynamics(q, qd, flat.tau[i], z, flat.forces(i))
            else:
                he, hd, hdd = flat.exo_lagged(i)
                app, _, _ = ext.applied_exo(he, hd, hdd, trial=flat.trial[i])
                qdd = ext.forward_dynamics(q, qd, flat.tau[i], z, flat.forces(i), flat.tau_e[i], app,
                                           trial=flat.trial[i])
            qd = qd + dt * qdd
            q = q + dt * qd
            i = i + 1
            dq, dqd = obs_shift(i)
            eq[:, h] = ((q + dq - flat.q[i]) ** 2).sum(1).numpy()
            eqd[:, h] = ((qd + dqd - flat.qd[i]) ** 2).sum(1).numpy()
    return dict(q=eq.mean(0).tolist(), qd=eqd.mean(0).tolist(), q_per_start=eq, qd_per_start=eqd)


def summarise_rollouts(ro: dict, horizons=(4, 10, 20)) -> dict:
    out = {}
    for H in horizons:
        if len(ro["q"]) >= H:
            out[f"q_mse_{H}"] = float(ro["q"][H - 1])
            out[f"qd_mse_{H}"] = float(ro["qd"][H - 1])
    return out
