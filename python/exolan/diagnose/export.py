"""The extended model: a base wrapped with candidate terms (`extend`), and its export at one context to the
Rust engine's weight format (`to_exo_model`, `export_extended`)."""
from __future__ import annotations

import copy
import json

import torch
from torch import nn

from ..extensions import ExtendedModel
from .base import COP_UNIT, SlowContextDeLaN
from .flat import Flat


def extend(base: nn.Module, flat: Flat, effects, init: dict | None = None, max_delay: float = 0.1) -> ExtendedModel:
    """A deep copy of `base` wrapped with the section-4 terms (warm start: the base's weights as fitted)."""
    return ExtendedModel(copy.deepcopy(base), flat.n, effects, dt=flat.dt, max_delay=max_delay, init=init,
                         coupled_damping=False)


def to_exo_model(base: SlowContextDeLaN, z: torch.Tensor, joint_names=None):
    """The slow-context base at one fixed context z as a context-free `ExoModel` ("delan" ± LIM).

    z enters only the first layer of each network, so W [φ; z] + b = W_φ φ + (W_z z + b): folding W_z z
    into the bias gives the identical function without z — the form the weight file and the Rust engine
    take (DESIGN.md section 3). Used to export the extended model for a chosen trial's (or the mean) z.
    """
    from ..models import build_model

    lag = base.delan
    exo = build_model("delan", lim=base.lim is not None, joint_types=lag.features.joint_types,
                      context_channels=(), joint_names=joint_names, hidden=lag.L[0].out_features,
                      softplus_offset=lag.softplus_offset, v_scale=lag.v_scale,
                      lim_scale=base.lim.lim_scale if base.lim is not None else 0.1).to(torch.float64)
    k = lag.features.dim
    z = z.detach().to(torch.float64).reshape(-1)
    with torch.no_grad():
        pairs = [(exo.delan.L, lag.L, z), (exo.delan.V, lag.V, z)]
        if base.lim is not None:
            # a LIM that sees the centre of pressure is held at the training mean (the engine has no CoP input)
            zl = (torch.cat([z, base.cop_ref.detach().to(torch.float64).reshape(1)])
                  if getattr(base, "lim_cop", False) else z)
            pairs.append((exo.lim, base.lim, zl))
        for dst, src, zc in pairs:
            for i, (ld, ls) in enumerate(zip(dst, src)):
                W = ls.weight.detach().to(torch.float64)
                b = ls.bias.detach().to(torch.float64)
                if i == 0:
                    ld.weight.copy_(W[:, :k])
                    ld.bias.copy_(b + W[:, k:] @ zc)
                else:
                    ld.weight.copy_(W)
                    ld.bias.copy_(b)
    return exo


def export_extended(ext: ExtendedModel, path, z: torch.Tensor, joint_names=None, dt: float | None = None,
                    meta: dict | None = None, trial: int | None = None):
    """Export base (at context z) + `ext.*` tensors through `exolan.export` (the Rust engine's format).

    `trial`: a subject-specific term is written as it acts on that trial (the engine has neither switches nor
    sizes: one file per user): a term switched off there is left out, a sized one takes its subject's value;
    without it every term is written at its shared value."""
    from ..export import export

    exo = to_exo_model(ext.base, z, joint_names)
    factor = lambda e, j: 1.0 if trial is None else ext.trial_factor(e, j, trial)
    eff = [(e, j) for e, js in ext.effects.items() for j in js if factor(e, j) > 0]
    twin = ExtendedModel(exo, ext.n, eff, dt=ext.dt, max_delay=ext.max_delay, coulomb_eps=ext.coulomb_eps,
                         coupled_damping=ext.coupled_damping).to(torch.float64)
    with torch.no_grad():
        params = dict(twin.named_parameters())
        for name, p in ext.named_parameters():
            if not name.startswith("base.") and name in params:     # (not the sizes: the twin has none)
                params[name].copy_(p.detach().to(torch.float64))
    if trial is not None and ext.sized:
        own = ext.physical(trial)
        for e, j in eff:        # a sized term at this trial's subject's value
            if e in ext.sized:
                twin.set_value(e, j, float(own[e][j, j] if e == "viscous_damping" else own[e][j]))
    md = {"dt": repr(float(dt if dt is not None else ext.dt))}
    if getattr(ext.base, "body_load", None) is not None:
        md["omitted"] = ("the diagnosis base's gravity scaling by the other leg's insole force (the engine has one "
                         "insole input)" + (" and its pelvis tilt following the other hip"
                                            if getattr(ext.base, "tilt", None) is not None else "") +
                         (", and the pelvis's fore-aft acceleration from both insoles and the centre-of-pressure "
                          "lever" if getattr(ext.base, "surge", None) is not None else "") +
                         (f"; the insole mapping's centre-of-pressure input is held at its training mean "
                          f"({float(ext.base.cop_ref) * COP_UNIT:.3f} m)" if getattr(ext.base, "lim_cop", False)
                          else "") +
                         "; this file holds the rest of the model")
    if "backlash" in ext.effects:       # a sensor effect: the engine runs the limb, a controller corrects its angles
        w = twin.physical()["backlash"]
        names = list(joint_names) if joint_names is not None else [str(j) for j in range(ext.n)]
        md["sensor_backlash"] = json.dumps({names[j]: float(w[j]) for j in ext.effects["backlash"]})
        md["sensor_backlash_note"] = ("play width w (rad or m) per joint: the limb is at q_measured + (w/2) s, s = +1 "
                                      "after a rise and -1 after a fall; the engine's dynamics are the limb's")
    md.update(meta or {})
    return export(twin, path, meta=md), twin
