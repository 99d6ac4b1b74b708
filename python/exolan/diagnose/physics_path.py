"""The diagnosis where the parametric base explains the data: the physics-first findings, the learned base's
cross-check, the extended model (the learned base with the terms held at their physical sizes) and its gain.

When this path is taken (`adequacy`): the parametric base with every linear candidate at once is not worse on
the held-out segments than the learned reference (else the selection is not run at all: a misfitting base pushes
its misfit into every candidate), and then the parametric base with its accepted terms is at least as good as the
learned reference (the paired difference's block-bootstrap 95 % interval does not lie above 0). Then the network has nothing to add that the sizes need, and the expensive joint refits of every
candidate (`procedure.learned_path`) are skipped. Otherwise the learned path runs and every candidate carries
the parametric estimate beside its own (`attach`).
"""
from __future__ import annotations

import numpy as np
import torch

from ..runio import jsonable
from . import physics, stats
from .candidates import LIBRARY, blank_entry
from .export import extend
from .fit import predict

RULE = ("Physics first: every candidate term was fitted jointly with a parametric rigid-body base (inertia, "
        "gravity where it can act, a constant offset, the insole contact where there is one) by weighted least "
        "squares on the training segments; its interval is a Newey-West (HAC) sandwich over time. Forward "
        "selection takes the candidate with the smallest p while p ≤ α/(m − r) (Holm's thresholds, α = 5 % "
        "family-wise over the m candidates tested, r the step), and only where its held-out gain is above 0; in "
        "the final joint fit a term that no longer earns a held-out share beside the others is dropped. "
        "Rivals that held-out data cannot separate are ambiguous (a nested pair: the simpler is taken). The same "
        "terms fitted on the learned base's residual cross-check the sizes: where the two intervals do not "
        "overlap the finding reports both and its interval spans both; where that residual shows no such term "
        "it is ambiguous.")


def adequacy(e_param: np.ndarray, ref, flat, joint_ids, n_boot: int, what: str = "") -> dict:
    """Is the parametric model (held-out squared errors `e_param` on the flat's held rows) at least as good on
    held-out data as the learned reference?"""
    held = flat.index("held")
    e = ((predict(ref, flat, held) - flat.tau[held]) / flat.mass[held, None]).double().numpy() ** 2
    e_learned = e[:, joint_ids].sum(1)
    ok = np.isfinite(e_param)
    b = stats.bootstrap_mean(e_param[ok] - e_learned[ok], n_boot=n_boot)
    return jsonable(dict(parametric_mse=float(np.mean(e_param[ok])), learned_mse=float(np.mean(e_learned[ok])),
                         difference=b["mean"], ci=b["ci"], adequate=bool(b["ci"][0] <= 0), model=what,
                         rule="parametric base adequate where the held-out difference parametric − learned is not "
                              "above 0 (block-bootstrap 95 % CI)"))


def learned_residual(ref, flat) -> np.ndarray:
    idx = torch.arange(flat.q.shape[0])
    return (flat.tau - predict(ref, flat, idx)).double().numpy()


def entries(phys: physics.PhysicsResult, flat, s, joint_ids) -> list[dict]:
    """The report's candidate entries from the physics-first verdicts (the same keys as the learned path's)."""
    ver = physics.verdicts(phys)
    subjects = sorted({m["subject"] for m in flat.trial_meta})
    out = []
    for effect in s.effects:
        c = LIBRARY[effect]
        for j in joint_ids:
            name = flat.joints[j]
            e = blank_entry(effect, j, flat, subjects)
            out.append(e)
            key = (effect, j)
            if c.needs_exo and not flat.has_exo:
                e.update(status="rejected", reason="no exoskeleton torque recorded: not testable")
            elif effect == "torque_bias":
                const = phys.base.get(name, {}).get("const")
                e.update(status="absorbable", reason="the parametric base's constant column: a torque offset is part "
                                                     "of every base (a flexible conservative model represents it)")
                if const:
                    e.update(estimate=const["value"], ci=[const["value"] - physics.Z95 * const["se"],
                                                          const["value"] + physics.Z95 * const["se"]])
            elif effect == "encoder_offset":
                e.update(status="absorbable", reason="a constant offset of the coordinates: the parametric base's "
                                                     "gravity and constant columns represent it exactly")
            elif key in ver:
                v = ver[key]
                e.update(status=v["status"] if c.kind == "finding" else c.kind, reason=v["reason"])
                if v.get("note"):
                    e["note"] = v["note"]
                m = phys.estimates.get(key)
                if m is not None:
                    e.update(estimate=m.estimate, ci=v.get("ci") or m.ci, identifiable=True,
                             ci_method="HAC (Newey-West) sandwich of the parametric base's weighted LS fit"
                                       + (", spanning the learned base's cross-check" if v.get("note") else ""))
                    if m.nu is not None:
                        e["vs"] = m.nu
                    e["parametric"] = m.to_json()
                    g = phys.term_gain.get(key)
                    if g:
                        e.update(heldout_gain=g["gain"], heldout_gain_ci=g["ci"],
                                 decision_gain=dict(g, scale="parametric base, unweighted"))
                if key in phys.cross:
                    e["cross_check"] = phys.cross[key].to_json()
            else:
                e.update(status="rejected" if c.kind == "finding" else c.kind,
                         reason="not tested by the parametric identification (no term for it there)")
    return out


def extended_model(base, flat, s, accepted: list, phys: physics.PhysicsResult, refit_frozen):
    """The learned base with the accepted terms held at their physical sizes, its networks refitted with the
    reference's schedule and minibatches (so it differs from the reference by the terms alone)."""
    init: dict = {}
    for eff, j in accepted:
        m = phys.estimates[(eff, j)]
        init.setdefault(eff, {})[j] = m.estimate
        if m.nu is not None:
            init.setdefault("stribeck_vs", {})[j] = m.nu
    ext = extend(base, flat, accepted, init=init, max_delay=s.max_delay)
    refit_frozen(ext, flat, s, 1)
    return ext


def attach(results: list, phys: physics.PhysicsResult, flat) -> None:
    """The learned path: every candidate entry carries the parametric estimate; a disagreement beyond both
    intervals is said in a note (not resolved by picking one)."""
    for e in results:
        key = (e["effect"], flat.joints.index(e["joint"]))
        st, why = phys.status.get(key, (None, None))
        m = phys.estimates.get(key)
        if st is None:
            if e.get("status") != "accepted":
                continue
            # the selection did not run (the parametric family explains less than the learned base): the
            # learned path's finding beside the same term alone with the parametric base
            m = physics.single_term(phys, e["effect"], key[1], e["joint"])
            if m is None:
                continue
            st, why = "not selected", "the parametric base explains less than the learned base: a single-term fit"
        e["parametric"] = dict(status=st, reason=why, **(m.to_json() if m else {}))
        if m and e.get("status") == "accepted" and e.get("ci"):
            lo, hi = e["ci"]
            if m.ci[1] < lo or m.ci[0] > hi:
                note = (f"the parametric base sizes it {m.estimate:.4g} [{m.ci[0]:.4g}, {m.ci[1]:.4g}], outside this "
                        f"interval: the two bases disagree")
                e["note"] = f"{e['note']}; {note}" if e.get("note") else note


def report(flat, s, trials, base, ref, base_source, noise, phys, adequate: dict, joint_ids, held, limits, log) -> dict:
    """The physics-first diagnosis' result dict (`procedure.run`'s return shape)."""
    from . import residuals as R
    from .limits import torque_unit
    from .refits import metrics as _metrics, refit_terms_frozen as _refit_terms_frozen
    from .results import public as _public, strip as _strip
    from .rules import paired_gain as _gain

    results = entries(phys, flat, s, joint_ids)
    accepted = [(e["effect"], flat.joints.index(e["joint"])) for e in results if e["status"] == "accepted"]
    starts = R.rollout_starts(flat, s.horizon, seed=s.seed)
    baseline, ro_base = _metrics(ref, flat, s, starts)
    baseline["source"] = base_source
    baseline["noise_floor"] = noise
    structure = R.residual_structure(ref, flat, held)
    ext_model, ro_ext, extended = None, None, None
    if accepted:
        log(f"extended model: the learned base with {', '.join(f'{a}:{flat.joints[j]}' for a, j in accepted)} held at "
            f"their physical sizes, its networks refitted")
        ext_model = extended_model(base, flat, s, accepted, phys, _refit_terms_frozen)
        e_ref = ((predict(ref, flat, held) - flat.tau[held]) / flat.mass[held, None]).double().numpy() ** 2
        e_ext = ((predict(ext_model, flat, held) - flat.tau[held]) / flat.mass[held, None]).double().numpy() ** 2
        g = _gain(e_ref.sum(1), e_ext.sum(1), s)
        extended, ro_ext = _metrics(ext_model, flat, s, starts)
        extended.update(terms=[f"{a}:{flat.joints[j]}" for a, j in accepted],
                        model="the reference's refit with the terms held at the parametric base's estimates",
                        heldout_gain=g["gain"], heldout_gain_ci=g["ci"], relative_gain=g["rel"],
                        relative_gain_ci=g["rel_ci"],
                        parameters={f"{a}:{flat.joints[j]}": ext_model.estimate(a, j) for a, j in accepted})
        extended["rollout_gain"] = {}
        for H in (4, 10, 20):
            if H <= s.horizon and len(starts):
                d = ro_base["q_per_start"][:, H - 1] - ro_ext["q_per_start"][:, H - 1]
                b = stats.bootstrap_mean(d, n_boot=s.n_boot // 2)
                extended["rollout_gain"][f"q_mse_{H}"] = dict(gain=b["mean"], ci=b["ci"])
        log(f"extended model: held-out gain {g['gain']:.4g} [{g['ci'][0]:.4g}, {g['ci'][1]:.4g}] "
            f"({torque_unit(flat)})²")
        if g["ci"][1] <= 0:
            for e in results:
                if e["status"] == "accepted":
                    e["note"] = ((e.get("note") + "; ") if e.get("note") else "") + (
                        "the learned base with the terms held at these sizes does not gain on held-out data")
    findings = [_public(e) for e in results if e["status"] == "accepted"]
    rejected = [_public(e) for e in results if e["status"] != "accepted"]
    rep = {"baseline": _strip(baseline), "findings": findings, "rejected": rejected,
           "extended": _strip(extended) if extended else {"note": "nothing found: the base model is kept",
                                                         **_strip(baseline)},
           "physics": dict(phys.to_json(flat.joints), adequacy=adequate, path="physics first", rule=RULE),
           "residuals": structure, "detection_limits": limits,
           "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in s.__dict__.items()},
           "data": dict(trials=len(trials), samples=int(flat.q.shape[0]), heldout=int(len(held)),
                        torque_unit=torque_unit(flat), joints=list(flat.joints), joint_types=list(flat.joint_types),
                        has_exo=flat.has_exo, has_insole=flat.has_insole,
                        split="held-out time segments (1 in 4, ~2 s) within every trial")}
    return dict(report=rep, flat=flat, base=base, ref=ref, ext_model=ext_model, ro_base=ro_base, ro_ext=ro_ext,
                results=results)
