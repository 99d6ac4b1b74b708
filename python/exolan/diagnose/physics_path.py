"""The diagnosis where the parametric base explains the data: the physics-first findings, the learned base's
cross-check, the extended model (the learned base with the terms held at their physical sizes) and its gain.

When this path decides (`adequacy`, per joint equation): in a joint's equation, the parametric base with every
linear candidate at once is not worse on the held-out segments than the learned reference (else that joint's
selection is not run: a misfitting base pushes its misfit into every candidate), and then the parametric base with
its accepted terms is at least as good as the learned reference (the paired difference's block-bootstrap 95 %
interval does not lie above 0). Then the network has nothing to add that the sizes need, and the expensive joint
refits of that joint's candidates (`procedure.learned_path`) are skipped. The other joints' candidates are decided
by the learned path, and each of them carries the parametric estimate beside its own (`attach`).
"""
from __future__ import annotations

import copy
import json
import threading

import numpy as np
import torch

from ..runio import jsonable
from . import physics, physics_checks, rules, stats, subjects
from .candidates import LIBRARY, blank_entry
from .export import extend
from .fit import predict, sq_errors
from .flat import sample_groups
from .workers import Ahead, Cancelled, stop_or_go

RULE = ("Physics first: every candidate term was fitted jointly with a parametric rigid-body base (inertia, "
        "gravity where it can act, a constant offset, the insole contact where there is one) by weighted least "
        "squares on the training segments; its interval is a Newey-West (HAC) sandwich over time. Forward "
        "selection takes the candidate with the smallest p while p ≤ α/(m − r) (Holm's thresholds, α = 5 % "
        "family-wise over the m candidates tested, r the step), and only where its held-out gain is above 0 (the "
        "torque through the same low-pass as the fit: the recording's noise above it no model predicts; with "
        "several subjects each candidate is tested shared and split by subject, its p doubled for the two forms, "
        "and the trials weighted by the misfit of the most flexible linear model), and only where, fitted "
        "recording by recording, its 95 % prediction interval for a new recording (random effects over the "
        "recordings) holds no zero: a constant of the joint, not a shape of the base's misfit; in "
        "the final joint fit a term that no longer earns a held-out share beside the others is dropped. "
        "Rivals that held-out data cannot separate are ambiguous (a nested pair: the simpler is taken). The same "
        "terms fitted on the learned base's residual cross-check the sizes: where the two intervals do not "
        "overlap the finding reports both and its interval spans both; where that residual shows no such term (its "
        "95 % interval reaches no effect), "
        "or one of the other sign, it is ambiguous. Last, the terms are held at their sizes in the learned base, "
        "whose networks are refitted as the reference's: where that base is worse on held-out data with a term "
        "than without it (beside the other accepted terms), the term carries what the parametric base misfits "
        "and is ambiguous. The extended model is the learned base fitted from its start on the data with the "
        "accepted terms taken out at their sizes, the terms put back: networks that never saw a term cannot "
        "imitate it.")


def adequacy(e_param: dict[int, np.ndarray], ref, flat, joint_ids, n_boot: int, what: str = "") -> dict:
    """Is the parametric model (held-out squared errors per joint, `e_param[j]` on the flat's held rows) at least as
    good on held-out data as the learned reference, in each joint's equation (`joints`: per joint name)? Each joint's
    terms are fitted in its own equation, so each needs its own evidence: pooled over joints, a joint where the
    reference misses an effect can carry the comparison for another where the parametric base misfits
    (docs/DIAGNOSIS.md, seed 684). `adequate`: in every joint's equation."""
    held = flat.index("held")
    e = sq_errors(ref, flat, held)
    joints, ok_all, tot_p, tot_l = {}, True, 0.0, 0.0
    for j in joint_ids:
        ok = np.isfinite(e_param[j]) & np.isfinite(e[:, j])
        b = stats.bootstrap_mean(e_param[j][ok] - e[ok, j], n_boot=n_boot)
        adequate = bool(b["ci"][0] <= 0)
        ok_all &= adequate
        mp, ml = float(np.mean(e_param[j][ok])), float(np.mean(e[ok, j]))
        tot_p, tot_l = tot_p + mp, tot_l + ml
        joints[flat.joints[j]] = dict(parametric_mse=mp, learned_mse=ml, difference=b["mean"], ci=b["ci"],
                                      adequate=adequate)
    return jsonable(dict(parametric_mse=tot_p, learned_mse=tot_l, joints=joints, adequate=ok_all, model=what,
                         rule="physics first decides a joint's candidates where, in that joint's equation, the held-out "
                              "difference parametric − learned is not above 0 (block-bootstrap 95 % CI); the learned "
                              "path decides the other joints' candidates"))


def per_joint(joints: dict, rule: str) -> dict:
    """The gate's record for the report: each joint's numbers (from the last gate it met) and `paths`, joint name ->
    the path that decides that joint's candidates; `path`: "physics first", "learned", or "per joint" where both do."""
    paths = {nm: "physics first" if v["adequate"] else "learned" for nm, v in joints.items()}
    kinds = set(paths.values())
    return jsonable(dict(joints=joints, paths=paths, path=kinds.pop() if len(kinds) == 1 else "per joint",
                         adequate=all(v["adequate"] for v in joints.values()), rule=rule))


def section(phys: physics.PhysicsResult, flat, adequate: dict) -> dict:
    """The report's physics-first section: the identification, the gate per joint and which path decided."""
    return dict(phys.to_json(flat.joints), adequacy=adequate, path=adequate["path"], paths=adequate["paths"],
                rule=RULE)


def learned_residual(ref, flat) -> np.ndarray:
    idx = torch.arange(flat.q.shape[0])
    return (flat.tau - predict(ref, flat, idx)).double().numpy()


def evidence(phys: physics.PhysicsResult, s, key: tuple, groups: np.ndarray, kind: str, subj: np.ndarray) -> dict:
    """Which data carry a physics-first term's held-out gain (its own share in the joint fit, per held row): the
    gain by task (or trial) and by subject (`groups`, `subj`: of the held rows). Reported, not decided on: the
    physics-first rules do not look again."""
    d = phys.term_rows.get(key)
    if d is None:
        return {}
    ok = np.isfinite(d)
    inv = dict(by=kind, groups={str(g): float(d[ok & (groups == g)].mean()) for g in np.unique(groups[ok])},
               scale="parametric base, unweighted",
               note="which data carry the gain; reported, not a decision rule of the physics-first path")
    return dict(task_invariance=inv, subject_gains=rules.subject_gains(d[ok], subj[ok], s))


def entries(phys: physics.PhysicsResult, flat, s, joint_ids) -> list[dict]:
    """The report's candidate entries from the physics-first verdicts (the same keys as the learned path's)."""
    ver = physics_checks.verdicts(phys)
    subjects = sorted({m["subject"] for m in flat.trial_meta})
    held = flat.index("held")
    groups, kind = sample_groups(flat, held)
    subj = flat.subjects_of(held)
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
                    e.update(**evidence(phys, s, key, groups, kind, subj))
                    if key in phys.forms and e["status"] == "accepted":
                        with_form(e, phys.forms[key])
                        if v.get("note"):           # the form's size and the cross-check's disagree: the span
                            e.update(ci=v["ci"], ci_method=e["ci_method"] + ", spanning the learned base's cross-check")
                    elif key in phys.forms_refused and e["status"] == "accepted":
                        e.subject_form_not_taken = phys.forms_refused[key]
                if key in phys.cross:
                    e["cross_check"] = phys.cross[key].to_json()
            else:
                e.update(status="rejected" if c.kind == "finding" else c.kind,
                         reason="not tested by the parametric identification (no term for it there)")
    return out


def with_form(e, form: dict) -> None:
    """An accepted physics-first entry sized by its subject form (`physics_subjects`): a switch's one θ on its
    subjects' trials, or the subjects' own sizes (the estimate their geometric mean), as the learned path reports."""
    e.form = {k: v for k, v in form.items() if k not in ("fit", "estimate_by_subject")}
    e.subject_form = {k: v for k, v in form.items()
                      if k not in ("fit", "trials", "subject_of_trial", "estimate_by_subject", "estimate", "ci")}
    e.update(estimate=form["estimate"], ci=form["ci"],
             ci_method="HAC (Newey-West) sandwich of the parametric base's weighted LS fit, the term split by subject")
    if form["kind"] == "switch":
        e.subjects = list(form["subjects"])
    else:
        e.estimate_by_subject = form["estimate_by_subject"]


def held_terms(phys: physics.PhysicsResult, joint_ids) -> tuple[list, dict]:
    """The terms physics first accepts on `joint_ids` so far (rules 1-5; rule 6 needs the learned base's refits)
    and their `init` at the physical sizes: what the learned path's data are compensated for (`compensate`)."""
    ver = physics_checks.verdicts(phys)
    keys = [k for k in phys.accepted if k[1] in joint_ids and ver[k]["status"] == "accepted"]
    return keys, term_init(phys, keys)


def select_terms(phys: physics.PhysicsResult, flat, s, joint_ids, log) -> None:
    """Physics first's selection on `joint_ids` and its subject forms (`physics.select`, `physics_subjects.take`):
    the gate's run and the one started ahead (`extended_ahead`) must be the same for the latter's key to match."""
    from . import physics_subjects
    n_boot = max(s.n_boot // 2, 200)
    physics.select(phys, flat, n_boot=n_boot, log=log, joints=joint_ids)
    physics_subjects.take(phys, flat, n_boot=n_boot, log=log)


def extended_ahead(phys: physics.PhysicsResult, flat, s, joint_ids, workers, make) -> "ExtendedAhead":
    """Physics first's extended model started while the learned base is fitted, on the core that fit leaves free
    (`make`: terms, init -> model; the extended model fitted without its terms takes as long as the base fit, and
    needs neither the learned base nor the gate): the selection on a copy of `phys` (the main flow selects on
    `phys` meanwhile), run on every joint before the gate; its accepted terms and sizes are the key."""
    return ExtendedAhead(copy.deepcopy(phys), flat, s, joint_ids, workers, make)


class ExtendedAhead:
    """`extended_ahead`'s fit on a thread of its own (`workers.Ahead`); `take` hands the model over where the final
    terms and sizes are those it was started for, else cancels it (the selection and the fit stop at their next
    candidate or step)."""

    def __init__(self, phys, flat, s, joint_ids, workers, make):
        self.key, self._keyed, self._workers = None, threading.Event(), workers
        self._ahead = Ahead(workers, lambda: self._work(phys, flat, s, joint_ids, make))

    def _work(self, phys, flat, s, joint_ids, make):
        from .settings import log
        try:
            select_terms(phys, flat, s, joint_ids, lambda msg: stop_or_go())    # every candidate's line asks
            accepted = list(phys.accepted)
            if not accepted:
                return None
            init = term_init(phys, accepted)
            self.key = _terms_key(accepted, init)
        finally:
            self._keyed.set()
        log(s, "physics first's extended model started ahead, beside the base fit (kept if the gate and the checks "
               "leave the same terms: " + ", ".join(f"{e}:{flat.joints[j]}" for e, j in accepted) + ")")
        return make(accepted, init)

    def cancel(self) -> None:
        self._ahead.cancel()

    def take(self, accepted: list, init: dict):
        """The model where it was started for these terms at these sizes, else None (and the fit is cancelled)."""
        if self._ahead.cancelled:
            return None
        self._workers.wait(self._keyed.wait)
        if self.key is None or self.key != _terms_key(accepted, init):
            self.cancel()
            return None
        try:
            return self._ahead.result()
        except Cancelled:
            return None


def _terms_key(accepted: list, init: dict) -> str:
    return json.dumps([sorted([e, int(j)] for e, j in accepted), init], sort_keys=True,
                      default=lambda o: np.asarray(o).tolist())


def term_init(phys: physics.PhysicsResult, accepted: list) -> dict:
    """`ExtendedModel`'s init of the accepted terms at their physical sizes (a subject form's per subject)."""
    init: dict = {}
    for eff, j in accepted:
        m = phys.estimates[(eff, j)]
        form = phys.forms.get((eff, j))
        value = m.estimate                          # in the vocabulary's units (a strap's k), as `extend` takes it
        if form:
            value = 1.0 / form["theta"] if LIBRARY[eff].inverse else form["theta"]
        init.setdefault(eff, {})[j] = value
        if m.nu is not None:
            init.setdefault("stribeck_vs", {})[j] = m.nu
        if form:
            init = subjects.gated(init, form, eff, j)
    return init


def extended_model(base, flat, s, accepted: list, phys: physics.PhysicsResult, refit_frozen):
    """The learned base with the accepted terms held at their physical sizes (`term_init`), its networks refitted
    with the reference's schedule and minibatches (so it differs from the reference by the terms alone)."""
    ext = extend(base, flat, accepted, init=term_init(phys, accepted), max_delay=s.max_delay)
    refit_frozen(ext, flat, s, 1)
    return ext


def learned_check(phys: physics.PhysicsResult, base, ref, flat, s, joint_ids, log, fit=None, errors=None) -> dict:
    """Rule 6 (`physics` docstring): every physics-first term held at its physical size (its subject form's) in the
    learned base, whose networks are refitted as the reference's, and judged on held-out data (the user's
    unweighted error) by its own share: one term against the reference; several, the model with all of them
    against the same without this one (a term that mimics another accepted term would pass alone by proxy).
    Fills `phys.learned_check`; returns frozenset(terms) -> each model fitted (one is the extended model).
    `fit` (terms -> model) and `errors` (model -> held-out squared error per row): tests pass stubs."""
    from .refits import refit_terms_frozen
    from .rules import paired_gain
    from .workers import Workers, current

    held = flat.index("held")
    fit = fit or (lambda terms: extended_model(base, flat, s, terms, phys, refit_terms_frozen))
    errors = errors or (lambda m: sq_errors(m, flat, held).sum(1))
    ver = physics_checks.verdicts(phys)
    keys = [k for k in phys.accepted if k[1] in joint_ids and ver[k]["status"] == "accepted"]
    if not keys:
        return {}
    combos = [keys] + ([[x for x in keys if x != k] for k in keys] if len(keys) > 1 else [])
    log(f"the learned base's check: {', '.join(f'{e}:{flat.joints[j]}' for e, j in keys)} held at their physical "
        f"sizes, the networks refitted ({len(combos)} refits)")
    # the run's pool where there is one: a fit started ahead (a twin) holds one of its permits
    models = (current() or Workers(s.workers)).map([lambda c=c: fit(c) for c in combos])
    errs = [errors(m) for m in models]
    e_ref = errors(ref)
    for i, (eff, j) in enumerate(keys):
        g = paired_gain(e_ref if len(keys) == 1 else errs[1 + i], errs[0], s)
        phys.learned_check[(eff, j)] = jsonable(dict(
            gain=g["gain"], ci=g["ci"], relative=g["rel"],
            model="the reference's refit with this term alone held at the parametric size" if len(keys) == 1 else
                  "the reference's refit with every accepted term held at its parametric size, against the same "
                  "without this term"))
        log(f"the learned base's check: {eff}:{flat.joints[j]} held-out gain {g['gain']:.3g} "
            f"[{g['ci'][0]:.3g}, {g['ci'][1]:.3g}] ({100 * g['rel']:+.1f} %)")
    return {frozenset(c): m for c, m in zip(combos, models)}


def checked(phys: physics.PhysicsResult, base, ref, flat, s, joint_ids, residual, log, fit=None, errors=None) -> dict:
    """Rule 6 until nothing changes: a term it sets aside leaves its joint's fit (`physics_checks.settle`), the terms
    that remain are sized without it, and rule 6 judges them again at those sizes (their share was measured beside
    it). Returns the last check's models (`learned_check`; `fit`, `errors`: stubs in tests)."""
    models = learned_check(phys, base, ref, flat, s, joint_ids, log, fit=fit, errors=errors)
    while physics_checks.settle(phys, flat, residual, joint_ids, n_boot=max(s.n_boot // 2, 200), log=log):
        models = learned_check(phys, base, ref, flat, s, joint_ids, log, fit=fit, errors=errors)
    return models


def attach(results: list, phys: physics.PhysicsResult, flat) -> None:
    """The learned path: every candidate entry carries the parametric estimate; a disagreement beyond both
    intervals is said in a note and not resolved by picking one: the finding keeps its learned size, its interval
    spans both (the learned one kept as `ci_learned`), as physics first's cross-check does the other way round. A
    parametric size that physics first could not take (outside the physical domain, unbounded) spans nothing."""
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
            bad = physics.inadmissible(e["effect"], m)
            if bad:     # outside the domain or unbounded: not a size of this effect, so nothing to span
                note = f"the parametric base's size is no size of this effect ({bad})"
                e["note"] = f"{e['note']}; {note}" if e.get("note") else note
                continue
            both = stats.span_if_disjoint([lo, hi], m.ci)
            if both:
                e["ci_learned"], e["ci"] = [lo, hi], both
                note = (f"the parametric base sizes it {m.estimate:.4g} [{m.ci[0]:.4g}, {m.ci[1]:.4g}], outside the "
                        f"learned path's interval [{lo:.4g}, {hi:.4g}]: the two bases disagree, and the interval "
                        "spans both")
                e["note"] = f"{e['note']}; {note}" if e.get("note") else note


def report(flat, s, trials, base, ref, base_source, noise, phys, adequate: dict, joint_ids, held, limits, log,
           held_models: dict, learned: dict | None = None, fit_without=None) -> dict:
    """The physics-first diagnosis' result dict (`procedure.run`'s return shape) for the joints `joint_ids`;
    `held_models`: rule 6's models (`checked`, run before the learned path); `learned`: the learned path's result
    for the other joints (None: physics first decides every joint); `fit_without` (terms, init -> model): the
    extended model fitted from the base's start on the data without its terms (`compensate.fitted_without`; None
    where the base was given as is: rule 6's warm refit stands in)."""
    results = entries(phys, flat, s, joint_ids)
    accepted = [(e["effect"], flat.joints.index(e["joint"])) for e in results if e["status"] == "accepted"]
    if learned is not None and (not accepted or any(e["status"] == "accepted" for e in learned["results"])):
        return beside(learned, results, phys, flat, adequate)
    from . import residuals as R
    from .limits import torque_unit
    from .refits import metrics as _metrics
    from .results import public as _public, strip as _strip

    results += learned["results"] if learned else []        # the learned path's joints: nothing accepted there
    starts = R.rollout_starts(flat, s.horizon, seed=s.seed)
    baseline, ro_base = _metrics(ref, flat, s, starts)
    baseline["source"] = base_source
    baseline["noise_floor"] = noise
    structure = R.residual_structure(ref, flat, held)
    ext_model, ro_ext, extended = None, None, None
    if accepted:
        ext_model, extended, ro_ext = _extended(base, ref, flat, s, accepted, phys, held, starts, ro_base, log,
                                                ready=held_models.get(frozenset(accepted)), fit_without=fit_without)
        if extended["heldout_gain_ci"][1] <= 0:
            for e in results:
                if e["status"] == "accepted":
                    e["note"] = ((e.get("note") + "; ") if e.get("note") else "") + (
                        "the learned base with the terms held at these sizes does not gain on held-out data")
    findings = [_public(e) for e in results if e["status"] == "accepted"]
    rejected = [_public(e) for e in results if e["status"] != "accepted"]
    rep = {"baseline": _strip(baseline), "findings": findings, "rejected": rejected,
           "extended": _strip(extended) if extended else {"note": "nothing found: the base model is kept",
                                                         **_strip(baseline)},
           "physics": section(phys, flat, adequate),
           "residuals": structure, "detection_limits": limits,
           "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in s.__dict__.items()},
           "data": dict(trials=len(trials), samples=int(flat.q.shape[0]), heldout=int(len(held)),
                        torque_unit=torque_unit(flat), joints=list(flat.joints), joint_types=list(flat.joint_types),
                        has_exo=flat.has_exo, has_insole=flat.has_insole,
                        split="held-out time segments (1 in 4, ~2 s) within every trial")}
    if learned and learned.get("compensated"):
        rep["data"]["learned_path_compensated_for"] = learned["report"]["data"]["learned_path_compensated_for"]
    return dict(report=rep, flat=flat, base=base, ref=ref, ext_model=ext_model, ro_base=ro_base, ro_ext=ro_ext,
                results=results)


def beside(learned: dict, results: list, phys: physics.PhysicsResult, flat, adequate: dict) -> dict:
    """The learned path's result (it accepted terms on its joints, or physics first accepted none on its own) with
    physics first's verdicts on the other joints beside its own. Its extended model carries its own terms only:
    a physics-first finding there says it is sized by the parametric base alone."""
    from .results import public as _public

    held = set(learned.get("compensated") or ())     # terms the learned path's data were compensated for
    for e in results:
        if e["status"] == "accepted":
            e["note"] = ((e.get("note") + "; ") if e.get("note") else "") + (
                "sized by the parametric base (physics first decided this joint); " +
                ("the extended model holds it at that size (the learned path was fitted with it taken out of the data)"
                 if (e["effect"], flat.joints.index(e["joint"])) in held else
                 "the extended model carries the learned path's terms only"))
    rep = learned["report"]
    rep["findings"] += [_public(e) for e in results if e["status"] == "accepted"]
    rep["rejected"] += [_public(e) for e in results if e["status"] != "accepted"]
    rep["physics"] = section(phys, flat, adequate)
    learned["results"] += results
    return learned


def _extended(base, ref, flat, s, accepted: list, phys, held, starts, ro_base, log, ready=None, fit_without=None):
    """The extended model with the accepted terms at their physical sizes, its held-out and rollout gains. Where
    the base was fitted here (`fit_without`), its networks are fitted from the base's start on the data without the
    terms: a warm refit of the reference keeps most of what it learned to imitate of them (a knee damping: +15 % at
    the reference's 400 refit steps, +51 % fitted without it; docs/DIAGNOSIS.md). Else `ready` (one of rule 6's
    warm refits) or that refit made here."""
    from .limits import torque_unit
    from .refits import metrics as _metrics, refit_terms_frozen as _refit_terms_frozen
    from .rules import paired_gain as _gain

    terms = ', '.join(f'{a}:{flat.joints[j]}' for a, j in accepted)
    if fit_without is not None:
        log(f"extended model: the base's networks fitted from its start on the data without {terms} (taken out at "
            "their physical sizes), the terms put back")
        ext_model = fit_without(accepted, term_init(phys, accepted))
        how = ("the base's recipe from its start on the data without the terms (removed at the parametric base's "
               "estimates), the terms put back at those sizes")
    else:
        log(f"extended model: the learned base with {terms} held at their physical sizes, its networks refitted")
        ext_model = ready if ready is not None else extended_model(base, flat, s, accepted, phys, _refit_terms_frozen)
        how = "the reference's refit with the terms held at the parametric base's estimates"
    e_ref, e_ext = sq_errors(ref, flat, held), sq_errors(ext_model, flat, held)
    g = _gain(e_ref.sum(1), e_ext.sum(1), s)
    extended, ro_ext = _metrics(ext_model, flat, s, starts)
    extended.update(terms=[f"{a}:{flat.joints[j]}" for a, j in accepted], model=how,
                    heldout_gain=g["gain"], heldout_gain_ci=g["ci"], relative_gain=g["rel"],
                    relative_gain_ci=g["rel_ci"],
                    parameters={f"{a}:{flat.joints[j]}": ext_model.estimate(a, j) for a, j in accepted})
    extended["rollout_gain"] = {}
    for H in (4, 10, 20):
        if H <= s.horizon and len(starts):
            d = ro_base["q_per_start"][:, H - 1] - ro_ext["q_per_start"][:, H - 1]
            b = stats.bootstrap_mean(d, n_boot=s.n_boot // 2)
            extended["rollout_gain"][f"q_mse_{H}"] = dict(gain=b["mean"], ci=b["ci"])
    log(f"extended model: held-out gain {g['gain']:.4g} [{g['ci'][0]:.4g}, {g['ci'][1]:.4g}] ({torque_unit(flat)})²")
    return ext_model, extended, ro_ext
