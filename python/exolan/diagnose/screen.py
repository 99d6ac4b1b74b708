"""A cheap first look at every candidate: post-hoc least squares of the reference residual.

This is *only a screen* that decides which candidates deserve a joint refit (the expensive step). Regressing
the residual after the fact recovers just a fraction of a parameter — the fitted model has already absorbed
part of the effect (DIAGNOSIS_PITFALLS.md) — so nothing here is reported as an estimate and nothing is
accepted on it. For the same reason the screen is lenient: a candidate goes on when its post-hoc
correction, fitted on the training segments, lowers the held-out error on average (point estimate above 0;
its CI is reported) with the physically allowed sign — with one θ for all data, or one θ per task (the base
absorbs an effect unevenly across tasks, `screen`). A measured 35 ms exo delay had a post-hoc gain whose
CI still reached below 0 but a joint-refit gain well clear of every noise; only candidates that do not
help held-out data at all even after the fact are dropped here.

Each candidate is linearised as a feature F (N, n) — the change of the predicted recorded torque per unit
parameter — so the correction is θ F with one scalar θ:
  damping: q̇_j on joint j; Coulomb: tanh(q̇_j/ε); Stribeck: e^{−(q̇_j/vs)²} tanh(q̇_j/ε), vs on a grid;
  delay: τ_e,j(t) − τ_e,j(t−d), d on a grid; gain: τ_e,j, or its own variation τ_e,j − copy; bias: 1;
  encoder offset and strap: the model's own sensitivity to shifting q_j (by −1, or by −τ_e,j with q̇, q̈
  shifted by −τ̇_e,j, −τ̈_e,j), by central finite differences.

The gain's second feature: a gain error adds (k − 1) τ_e, and the part of τ_e that copies the joint torque
(`flat.exo_copy`) is a function of the motion, which the fitted base has already absorbed; what it leaves is
(k − 1) times the controller's own variation o = τ_e − copy. Regressed on the whole τ_e the post-hoc θ shrinks by
that share of own variation and its held-out gain drowns in noise (measured: docs/DIAGNOSIS.md, "Measurements behind
the code").
"""
from __future__ import annotations

import numpy as np
import torch

from . import stats
from .candidates import LIBRARY
from .fit import predict
from .flat import Flat, sample_groups

def features(model, flat: Flat, idx: torch.Tensor, effect: str, j: int) -> list[tuple[dict, np.ndarray]]:
    """Candidate features (one or several grid variants) at rows idx: [(extra, F (len(idx), n))], each effect's
    own (`candidates.Candidate.features`)."""
    c = LIBRARY.get(effect)
    if c is None or c.features is None:
        raise ValueError(effect)
    return c.features(model, flat, idx, j)


def _per_group_theta(a: np.ndarray, r: np.ndarray, code: np.ndarray, n_groups: int, positive: bool) -> np.ndarray:
    """Least-squares θ of r ≈ θ a within every group (a, r: (N, n); code: each row's group index), held at 0
    where the sign is unphysical or the group's feature is zero."""
    num = np.bincount(code, weights=(a * r).sum(1), minlength=n_groups)
    den = np.bincount(code, weights=(a ** 2).sum(1), minlength=n_groups)
    th = np.divide(num, den, out=np.zeros(n_groups), where=den > 0)
    return np.maximum(th, 0.0) if positive else th


def screen(model, flat: Flat, effect: str, j: int, n_boot: int = 300, seed: int = 0) -> dict:
    """Post-hoc fit on training rows, held-out gain with CI; `passes` when it helps held-out data.

    Two forms: one θ for all data, and one θ per task (per trial on a single-task bench). A flexible base
    absorbs an effect unevenly: on a periodic task its context (the TCN sees the motion's history) can learn a
    pseudo-dissipation, on a task with slow reversals it cannot, so the share left in the residual differs by task
    and a pooled θ can help none of them (measured: docs/DIAGNOSIS.md, "Measurements behind the code"). The
    candidate goes on when either form helps held-out data (each group's θ is fitted on that group's training rows
    and kept at 0 where its sign is unphysical)."""
    tr, he = flat.index("train"), flat.index("held")
    if len(tr) > 30000:
        tr = tr[torch.linspace(0, len(tr) - 1, 30000).long()]
    m_tr = flat.mass[tr].numpy().astype(np.float64)[:, None]
    m_he = flat.mass[he].numpy().astype(np.float64)[:, None]
    r_tr = (flat.tau[tr] - predict(model, flat, tr)).numpy().astype(np.float64) / m_tr
    r_he = (flat.tau[he] - predict(model, flat, he)).numpy().astype(np.float64) / m_he
    # group index of every row; a held-out group without training rows gets θ = 0 (the extra last slot)
    labels, code_tr = np.unique(sample_groups(flat, tr)[0], return_inverse=True)
    g_he = sample_groups(flat, he)[0]
    at = np.minimum(np.searchsorted(labels, g_he), len(labels) - 1)
    code_he = np.where(labels[at] == g_he, at, len(labels))
    c = LIBRARY[effect]
    best, best_g = None, None
    for (extra, F_tr), (_, F_he) in zip(features(model, flat, tr, effect, j), features(model, flat, he, effect, j)):
        a = F_tr / m_tr
        den = float((a ** 2).sum())
        if den <= 0:
            continue
        theta = float((a * r_tr).sum()) / den
        sse = float(((r_tr - theta * a) ** 2).sum())
        if best is None or sse < best[0]:
            best = (sse, theta, extra, F_he)
        th_g = np.append(_per_group_theta(a, r_tr, code_tr, len(labels), c.positive), 0.0)
        sse_g = float(((r_tr - th_g[code_tr, None] * a) ** 2).sum())
        if best_g is None or sse_g < best_g[0]:
            best_g = (sse_g, th_g, extra, F_he, theta)
    if best is None:
        return dict(passes=False, theta=0.0, gain=0.0, ci=[0.0, 0.0], reason="feature is identically zero")

    def held_gain(th_row, F_he):
        d = (r_he ** 2).sum(1) - ((r_he - th_row * F_he / m_he) ** 2).sum(1)
        return stats.bootstrap_mean(d, n_boot=n_boot, seed=seed)

    _, theta, extra, F_he = best
    b = held_gain(theta, F_he)
    sign_ok = theta > 0 if c.positive else True
    _, th_g, extra_g, F_he_g, theta_g = best_g
    bg = held_gain(th_g[code_he, None], F_he_g)
    pooled_ok, grouped_ok = bool(b["mean"] > 0 and sign_ok), bool(bg["mean"] > 0)
    by_group = dict(gain=bg["mean"], ci=bg["ci"], theta={str(g): float(v) for g, v in zip(labels, th_g)}, **extra_g)
    if grouped_ok and not pooled_ok:
        # the grid variant (vs, d) of the per-group form, and its pooled θ (`Candidate.screen_init` takes a
        # warm start from it only where its sign is physical)
        return dict(passes=True, theta=theta_g, gain=bg["mean"], ci=bg["ci"], sign_ok=True, reason="", form="per group",
                    pooled=dict(gain=b["mean"], ci=b["ci"]), by_group=by_group, **extra_g)
    reason = "" if pooled_ok else ("post-hoc estimate has the unphysical sign" if not sign_ok and b["mean"] > 0 else
                                   "no held-out gain even after the fact (one θ, or one per task)")
    return dict(passes=pooled_ok, theta=theta, gain=b["mean"], ci=b["ci"], sign_ok=bool(sign_ok), reason=reason,
                form="pooled", by_group=by_group, **extra)
