"""Fitting and predicting with the diagnosis models: the training loop (`train`), predictions and squared errors
on rows of a `Flat`, and the per-trial misfit weights of the weighted least squares (`misfit_weights`)."""
from __future__ import annotations

import functools

import numpy as np
import torch
from torch import nn

from ..delan import solve_inertia
from ..extensions import ExtendedModel
from .base import _base_of, inertia_of
from .flat import DTYPE, Flat
from .workers import Workers, current


def predict(model: nn.Module, flat: Flat, idx: torch.Tensor, chunk: int = 16384) -> torch.Tensor:
    """Predicted recorded torque at rows idx (no grad)."""
    out = []
    base = _base_of(model)
    with torch.no_grad():
        for s in range(0, len(idx), chunk):
            out.append(_forward(model, base, flat, idx[s:s + chunk]))
    return torch.cat(out, 0) if out else flat.tau[:0]


def _inputs(model, base, flat: Flat, b: torch.Tensor) -> tuple:
    """The model's inverse-dynamics arguments at rows b. Only a delay needs the exo torque's history; the
    other terms take the current row; a delay reads two columns of each history (`Lagged`), not all K+1."""
    rows = lambda x: x.index_select(0, b)       # noqa: E731 (a row gather; x[b] costs twice as much)
    args = (rows(flat.q), rows(flat.qd), rows(flat.qdd), base.z_of(rows(flat.trial)), flat.forces(b))
    if not isinstance(model, ExtendedModel):
        return args
    ex = (flat.exo_lagged(b) if "actuation_delay" in model.effects
          else (rows(flat.tau_e), rows(flat.tau_e_d), rows(flat.tau_e_dd)))
    return args + tuple(ex)


def _gate_kw(model, flat: Flat, b: torch.Tensor) -> dict:
    """`trial=` for a model with subject-specific (gated) terms: they act on their own trials only; `side=` for a
    backlash term (the side of its gap and its derivatives at rows b)."""
    kw = {"trial": flat.trial[b]} if getattr(model, "gated", ()) else {}
    if "backlash" in getattr(model, "effects", {}):
        kw["side"] = (flat.side[b], flat.side_d[b], flat.side_dd[b])
    return kw


def _forward(model, base, flat: Flat, b: torch.Tensor) -> torch.Tensor:
    return model.inverse(*_inputs(model, base, flat, b), **_gate_kw(model, flat, b))


def _forward_inertia(model, base, flat: Flat, b: torch.Tensor):
    """(τ̂, H) at rows b, H the inertia the inverse dynamics used: one evaluation of the inertia network per
    fit step instead of two (evaluated here only where the model does not expose it)."""
    args = _inputs(model, base, flat, b)
    kw = _gate_kw(model, flat, b)
    tau, H = (model.inverse_inertia(*args, **kw) if hasattr(model, "inverse_inertia")
              else (model.inverse(*args, **kw), None))
    return tau, (H if H is not None else inertia_of(model, flat.q[b], args[3]))


def sq_errors(model, flat: Flat, idx: torch.Tensor) -> np.ndarray:
    """Per-sample mass-normalised squared torque error, summed over joints ((N m/kg)²) — and per joint."""
    e = (predict(model, flat, idx) - flat.tau[idx]) / flat.mass[idx, None]
    return (e ** 2).numpy().astype(np.float64)


def train(model: nn.Module, flat: Flat, steps: int, lr: float = 3e-3, lr_ext: float = 3e-2,
          batch: int = 4096, seed: int = 0, weight_decay: float = 0.0, progress=None,
          average: bool = False, w_acc: float = 0.1, weighted: bool = True, pieces: int = 1,
          pool: Workers | None = None) -> list[float]:
    """Minimise the mass-normalised torque MSE (per-joint scaled) on the training segments, plus `w_acc` times
    the acceleration MSE (per-joint scaled by the std of q̈). Where `flat.weight` is set (and `weighted`),
    every sample's squared errors are weighted per joint (`misfit_weights`).

    Why the acceleration term: torque errors alone leave H loose in directions the data excite little, and a
    tiny H makes forward dynamics stiff enough that open-loop rollouts explode within a few steps. Because
    the predicted torque is H q̈ + (terms without q̈), the forward-dynamics error is H⁻¹ (τ − τ̂) exactly: one
    2x2 solve per sample with the H the inverse dynamics just used, no separate forward pass. Its known cost:
    |H⁻¹ e| shrinks as H grows, so the term also pulls H up wherever a torque misfit remains (measured:
    docs/DIAGNOSIS.md, "Measurements behind the code").

    Adam with minibatches; the extension's physical scalars get their own (larger) step because they are
    few and well scaled. `average=True` ends on the running mean of the weights over the second half of
    the steps (Polyak averaging; the networks' weights, not the extension's scalars): the minibatch noise
    of the last iterates averages out, so two refits that
    differ only in minibatch order end closer together — the refit noise every held-out gain is judged
    against. Returns the loss history (every step).

    `pieces` > 1: every step's minibatch is cut into that many pieces whose gradients are summed in order; a
    piece runs on a helper thread where `pool` (default: the running diagnosis', `workers.current`) has a permit
    free, else after the one before. A fit that runs alone so takes both cores, and its bits depend on `pieces`
    only, never on how many permits were free.
    """
    g = torch.Generator().manual_seed(seed)
    tr = flat.index("train")
    base = _base_of(model)
    scale = torch.as_tensor(flat.tau_scale, dtype=DTYPE)
    acc_scale = torch.as_tensor(flat.qdd_scale, dtype=DTYPE)
    if isinstance(model, ExtendedModel):
        groups = [{"params": model.base_parameters(), "lr": lr, "weight_decay": weight_decay},
                  {"params": model.ext_parameters(), "lr": lr_ext, "weight_decay": 0.0}]
    else:
        groups = [{"params": list(model.parameters()), "lr": lr, "weight_decay": weight_decay}]
    opt = torch.optim.Adam(groups, fused=True)      # one kernel per step, as in training
    # cosine decay: the last steps settle the physical parameters instead of jittering around them
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1), eta_min=0.05 * lr)
    hist = []
    # averaged: the networks only. An extension's physical scalar may still be moving towards its value
    # during a refit; its running mean would lag behind (measured: docs/DIAGNOSIS.md).
    params = list(groups[0]["params"])
    trainable = [p for grp in groups for p in grp["params"]]
    pool = pool if pool is not None else current() if pieces > 1 else None
    avg, n_avg, start_avg = None, 0, steps // 2
    for step in range(steps):
        b = tr[torch.randint(len(tr), (min(batch, len(tr)),), generator=g)]
        opt.zero_grad(set_to_none=True)
        if pieces > 1:
            loss = sum(_step_grads(model, base, flat, b, scale, acc_scale, w_acc, weighted, trainable, pieces, pool))
        else:
            loss = _loss(model, base, flat, b, scale, acc_scale, w_acc, weighted)
            loss.backward()
        opt.step()
        sched.step()
        hist.append(float(loss.detach()))
        if average and step >= start_avg:
            with torch.no_grad():
                if avg is None:
                    avg = [p.detach().clone() for p in params]
                else:
                    for a, p in zip(avg, params):
                        a.add_(p.detach() - a, alpha=1.0 / (n_avg + 1))
            n_avg += 1
        if progress is not None:
            progress(step, hist[-1])
    if avg is not None:
        with torch.no_grad():
            for a, p in zip(avg, params):
                p.copy_(a)
    return hist


def _loss(model, base, flat: Flat, b: torch.Tensor, scale, acc_scale, w_acc: float, weighted: bool,
          of: int | None = None) -> torch.Tensor:
    """The fit's loss at rows b: the mean over b, or (`of`) the rows' sum over `of` rows, a piece's share."""
    pred, H = _forward_inertia(model, base, flat, b) if w_acc > 0 else (_forward(model, base, flat, b), None)
    err = pred - flat.tau.index_select(0, b)
    r = err / (flat.mass.index_select(0, b)[:, None] * scale)
    w = flat.weight.index_select(0, b) if weighted and flat.weight is not None else 1.0
    mean = (lambda x: x.sum(-1).mean()) if of is None else (lambda x: x.sum() / of)
    loss = mean(w * r ** 2)
    if w_acc > 0:
        a_err = solve_inertia(H, err) / acc_scale
        loss = loss + w_acc * mean(w * a_err ** 2)
    return loss


def _step_grads(model, base, flat: Flat, b: torch.Tensor, scale, acc_scale, w_acc: float, weighted: bool,
                params: list, pieces: int, pool: Workers | None) -> list[torch.Tensor]:
    """One step's gradients in `params`' .grad (the minibatch `b` in `pieces` pieces, summed in order) and each
    piece's share of the step's loss (its rows' terms over the whole minibatch's size: the shares add up to it)."""
    n = len(b)
    live = [p for p in params if p.requires_grad]

    def piece(rows):
        loss = _loss(model, base, flat, rows, scale, acc_scale, w_acc, weighted, of=n)
        return loss.detach(), torch.autograd.grad(loss, live, allow_unused=True)

    jobs = [lambda rows=rows: piece(rows) for rows in b.tensor_split(int(pieces)) if len(rows)]
    outs = pool.map(jobs) if pool is not None else [job() for job in jobs]
    for i, p in enumerate(live):
        parts = [g[i] for _, g in outs if g[i] is not None]
        if parts:
            p.grad = functools.reduce(torch.add, parts)
    return [share for share, _ in outs]


def misfit_weights(model: nn.Module, flat: Flat) -> torch.Tensor:
    """Fit weights (N, n): per trial and joint, the inverse of the model's mean squared training residual there,
    shrunk halfway to the median over trials, normalised to mean 1 over the training rows of each joint.

    Why (feasible weighted least squares): how well a conservative model fits differs a lot between tasks —
    a task whose unmeasured drivers (the pelvis's horizontal acceleration and horizontal ground force in
    jumps and calisthenics) the model cannot see leaves residuals ten times the variance of walking's. In an
    unweighted fit those residuals pull a physical parameter towards whatever part of them it can mimic:
    a planted hip Coulomb friction came out 20 % high unweighted, within 1 % weighted (docs/DIAGNOSIS.md).
    Weighting each trial by its inverse misfit is the efficient estimator under such heteroscedasticity and
    a property of the joint, the same in every task, should be fitted where the model is trustworthy. The
    shrinkage (halfway to the median) keeps a trial the model happens to fit almost exactly from dominating;
    the held-out gains stay unweighted (the user's torque error).
    """
    tr, r, _ = training_residual(model, flat)
    return row_weights(r, flat, tr)


def training_residual(model: nn.Module, flat: Flat) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """(training rows, the model's residual there in units of each row's mass times the joint's torque scale,
    that unit (rows, n)): the misfit the fit weights are made from."""
    tr = flat.index("train")
    norm = flat.mass[tr, None] * torch.as_tensor(flat.tau_scale, dtype=DTYPE)
    r = ((predict(model, flat, tr) - flat.tau[tr]) / norm).numpy().astype(np.float64)
    return tr, r, norm.numpy().astype(np.float64)


def row_weights(r: np.ndarray, flat: Flat, tr: torch.Tensor) -> torch.Tensor:
    """Fit weights (N, n) from a residual r at the training rows tr (`trial_weights`), normalised to mean 1 over
    the training rows of each joint."""
    w_trial = trial_weights(r, flat.trial[tr].numpy(), len(flat.lengths))
    w = torch.as_tensor(w_trial, dtype=DTYPE)[flat.trial]
    return w / w[tr].mean(0)


def trial_weights(r: np.ndarray, trial: np.ndarray, n_trials: int) -> np.ndarray:
    """(n_trials, n) inverse mean squared residual per trial and joint, the variance shrunk halfway to the
    median over trials (`misfit_weights`); trials without rows get the median's weight; all 1 when fewer
    than two trials have rows."""
    r = np.asarray(r, np.float64).reshape(len(trial), -1)
    var = np.ones((n_trials, r.shape[1]))
    seen = np.zeros(n_trials, bool)
    for i in np.unique(trial):
        var[i] = np.mean(r[trial == i] ** 2, 0)
        seen[i] = True
    if seen.sum() < 2:
        return np.ones_like(var)
    med = np.median(var[seen], 0)
    var = np.where(seen[:, None], 0.5 * (var + med), med)
    return 1.0 / np.maximum(var, 1e-30)

