"""The fits' weights: per trial and joint, the inverse misfit of the base once every candidate term has had its say.

`fit.misfit_weights` weights a trial by the inverse of the base's mean squared training residual there, so that the
tasks whose unrecorded drivers the base cannot see do not pull a joint's parameter. But a planted effect is part of
that misfit too, and an effect that lives in some tasks (a backlash in the fast ones) makes exactly those trials
misfit most: weighted by the base alone they are down-weighted with the effect in them, and the decision, which
weights as the fits do, loses the effect's gain (docs/DIAGNOSIS.md, "Weights after the candidates"). So the misfit
that sets a weight is the base's residual less its least-squares projection on every candidate's linearised column
at once (`candidates.Candidate.features`, every grid variant, split by subject as the candidates may be): what no
candidate can explain. The same weights for every candidate (not one set per candidate, which would judge each on
weights of its own making). Physics first weights its least squares the same way (`physics.setup`)."""
from __future__ import annotations

import numpy as np
import torch

from .candidates import LIBRARY
from .fit import misfit_weights, row_weights, training_residual
from .flat import Flat

ROWS = 30000        # the projection's rows (training rows, evenly spaced): ~40 columns need far fewer


def columns(model, flat: Flat, idx: torch.Tensor, effects, joint_ids) -> np.ndarray:
    """(len(idx) · n, p): every candidate's features at rows idx, each (rows, n) flattened to one column, and
    split by subject where there are several (a subject form is a member of the family too: a term one subject
    lacks, projected as one shared column, would leave its misfit in that subject's trials and move it to the
    other's)."""
    users = flat.user_index()
    split = [np.ones(len(idx), bool)] if users is None else \
        [users[1][idx.numpy()] == u for u in range(len(users[0]))]
    cols = []
    for eff in effects:
        c = LIBRARY[eff]
        if c.features is None or (c.needs_exo and not flat.has_exo):
            continue
        for j in joint_ids:
            cols += [(F * m[:, None]).reshape(-1) for _, F in c.features(model, flat, idx, j) for m in split]
    return np.stack(cols, 1) if cols else np.zeros((len(idx) * flat.n, 0))


def explained_misfit_weights(model, flat: Flat, effects, joint_ids) -> torch.Tensor:
    """Fit weights (N, n) as `fit.misfit_weights`, from the base's training residual less what every candidate's
    column explains (one least-squares projection over all joints, each joint's rows scaled to unit variance so
    that both equations count; fitted on up to `ROWS` training rows, applied to all)."""
    tr, r, norm = training_residual(model, flat)
    sub = np.unique(np.linspace(0, len(tr) - 1, min(ROWS, len(tr))).astype(int))
    X = columns(model, flat, tr[sub], effects, joint_ids)
    if X.shape[1] == 0:                  # no candidate: the base's misfit alone (`fit.misfit_weights`)
        return row_weights(r, flat, tr)
    sd = r[sub].std(0) + 1e-30                                  # each joint's equation in its own unit
    Xs = (X.reshape(len(sub), flat.n, -1) / (norm[sub][:, :, None] * sd[None, :, None])).reshape(X.shape)
    beta = np.linalg.lstsq(Xs, (r[sub] / sd).reshape(-1), rcond=None)[0]
    # the projection on all training rows: the features again, in chunks (the input shifts predict twice each)
    left = np.empty_like(r)
    for a in range(0, len(tr), ROWS):
        rows = tr[a:a + ROWS]
        F = columns(model, flat, rows, effects, joint_ids).reshape(len(rows), flat.n, -1)
        left[a:a + len(rows)] = r[a:a + len(rows)] - (F / norm[a:a + len(rows), :, None]) @ beta
    return row_weights(left, flat, tr)


def of_base(model, flat: Flat, s) -> torch.Tensor:
    """The fit weights of a base fitted on `flat` under settings `s` (`Settings.weights_explained`)."""
    if not s.weights_explained:
        return misfit_weights(model, flat)
    return explained_misfit_weights(model, flat, s.effects, s.joint_ids(flat))
