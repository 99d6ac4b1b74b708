"""Terms of known size taken out of the data, and put back into a model.

Where physics first decides some joints and the learned path the others, the learned path must test its joints
against a base that already holds the other joints' accepted terms: a knee strap left in the data moves the
measured knee angle away from the true one, and through the leg's inertial coupling that error reaches the hip's
equation, where a hip term takes part of it (a stiff hip "strap" accepted beside a soft knee strap). `data` removes
the terms at their physical sizes with the model's own physics (`ExtendedModel.applied_exo`, `true_state`,
`friction`, `recording_terms`): the learned path then sees the joints as the parametric base says they are.
`on_raw` wraps a model fitted on such data with the same terms, so that it predicts the recorded data again.
"""
from __future__ import annotations

import copy
from dataclasses import replace

import torch

from ..extensions import ExtendedModel
from . import weights
from .flat import Flat
from .refits import base_fit, refit
from .settings import Settings

# the raw parameters `ExtendedModel` learns for each term (per joint: one entry of each vector)
RAW = {"viscous_damping": ("damping_diag",), "coulomb_friction": ("coulomb_raw",),
       "stribeck_friction": ("stribeck_fs_raw", "stribeck_vs_raw"), "actuation_delay": ("delay_raw",),
       "encoder_offset": ("offset_raw",), "torque_bias": ("bias_raw",), "torque_gain": ("gain_raw",),
       "strap_compliance": ("compliance_raw",), "backlash": ("backlash_raw",)}


class _NoBase(torch.nn.Module):
    """The terms alone (`ExtendedModel` needs a base; `data` calls none of its networks)."""


def terms_model(flat: Flat, terms: list, init: dict, max_delay: float) -> ExtendedModel:
    """The terms (effect, joint) at the sizes of `init` (`physics_path.term_init`), without networks."""
    return ExtendedModel(_NoBase(), flat.n, terms, dt=flat.dt, max_delay=max_delay, init=init, coupled_damping=False)


@torch.no_grad()
def data(flat: Flat, terms: list, init: dict, max_delay: float) -> Flat:
    """A copy of `flat` with the terms removed: the applied exo torque in place of the recorded one (a delay), the
    physical coordinates in place of the measured ones (a strap's deflection, an encoder offset, a backlash), the
    torque the limb feels in place of the recorded one (friction, a bias, a gain). Everything else (the split, the
    weights, the other leg's signals) is shared; the fit weights are left to the base fitted on the copy."""
    m = terms_model(flat, terms, init, max_delay).to(torch.float64)
    rows = torch.arange(flat.q.shape[0])
    d64 = lambda x: x.to(torch.float64)
    hist = flat.exo_lagged(rows, dtype=torch.float64)
    tau_now = hist[0].now()
    app, app_d, app_dd = m.applied_exo(*hist, trial=flat.trial)
    side = tuple(d64(x) for x in (flat.side, flat.side_d, flat.side_dd)) if flat.side is not None else None
    q, qd, qdd = m.true_state(d64(flat.q), d64(flat.qd), d64(flat.qdd), app, app_d, app_dd, trial=flat.trial,
                              side=side)
    tau = d64(flat.tau) - m.friction(qd, trial=flat.trial) - m.recording_terms(tau_now, app, trial=flat.trial)
    like = lambda x, ref: torch.where(torch.isfinite(ref), x.to(ref.dtype), ref)     # keep the gaps as they were
    return replace(flat, q=like(q, flat.q), qd=like(qd, flat.qd), qdd=like(qdd, flat.qdd), tau=like(tau, flat.tau),
                   tau_e=like(app, flat.tau_e), tau_e_d=like(app_d, flat.tau_e_d),
                   tau_e_dd=like(app_dd, flat.tau_e_dd), weight=None)


def _merged(a: dict, b: dict) -> dict:
    """Two `init` dicts of terms on different joints as one (their gates and sizes joined per effect)."""
    out = {**a, **{k: v for k, v in b.items() if k not in ("gates", "sized")}}
    for part in ("gates", "sized"):
        joined = {eff: dict(v) for eff, v in (a.get(part) or {}).items()}
        for eff, v in (b.get(part) or {}).items():
            joined.setdefault(eff, {}).update(v)
        if joined:
            out[part] = joined
    for eff in set(a) & set(b) - {"gates", "sized", "subject_of_trial"}:
        if isinstance(a[eff], dict) and isinstance(b[eff], dict):
            out[eff] = {**a[eff], **b[eff]}
    return out


def on_raw(model, flat: Flat, terms: list, init: dict, max_delay: float) -> ExtendedModel:
    """`model` (fitted on `data(flat, terms, init)`: a base or an `ExtendedModel` of the other joints' terms) with
    the removed terms put back at their sizes: on the recorded data it predicts what `model` predicts on the
    compensated data (the terms act on other joints than the model's own; both are applied in one pass)."""
    own = [(e, j) for e, js in getattr(model, "effects", {}).items() for j in js] if isinstance(model, ExtendedModel) \
        else []
    base = model.base if isinstance(model, ExtendedModel) else model
    sub = model.subject_init() if isinstance(model, ExtendedModel) else {}
    out = ExtendedModel(copy.deepcopy(base), flat.n, own + list(terms), dt=flat.dt, max_delay=max_delay,
                        init=_merged(init, sub), coupled_damping=False)
    with torch.no_grad():
        for e, j in own:
            for name in RAW[e]:
                getattr(out, name)[j] = getattr(model, name)[j]
    return out


def results_on_raw(learned: dict, flat: Flat, terms: list, init: dict, max_delay: float) -> dict:
    """The learned path's result, fitted on the compensated data, with its models on the recorded data again: its
    base, reference and extended model carry the removed terms at their physical sizes (`on_raw`)."""
    out = dict(learned, flat=flat, compensated=list(terms))
    out["report"]["data"]["learned_path_compensated_for"] = [f"{e}:{flat.joints[j]}" for e, j in terms]
    for key in ("base", "ref", "ext_model"):
        if learned.get(key) is not None:
            out[key] = on_raw(learned[key], flat, terms, init, max_delay)
    ext = out["report"].get("extended")
    if learned.get("ext_model") is not None and isinstance(ext, dict):
        ext["held_from_physics_first"] = [f"{e}:{flat.joints[j]}" for e, j in terms]
    return out


def fitted_without(flat: Flat, s: Settings, start: torch.nn.Module, terms: list, init: dict) -> ExtendedModel:
    """The base's recipe (`procedure.fit_base`: its steps and seed from `start`, the misfit weights, the reference's
    refit) on the data with `terms` removed at their sizes, and the terms put back (`on_raw`). Networks that never
    saw the terms cannot imitate them: a warm refit of a base that already imitates a term keeps most of that
    imitation and so doubles the term (docs/DIAGNOSIS.md, "The extended model of physics first")."""
    fc = data(flat, terms, init, s.max_delay)
    m = copy.deepcopy(start)
    base_fit(m, fc, s, "extended model: the base fitted without its terms")
    if s.weighted:
        fc.weight = weights.of_base(m, fc, s)
    refit(m, fc, s)
    return on_raw(m, flat, terms, init, s.max_delay)
