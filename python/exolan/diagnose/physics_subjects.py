"""Physics first, per subject: an accepted term that the subjects carry at different sizes, or that only some of
them carry (one user's strap, one exoskeleton unit's friction), found in the parametric joint fit itself.

A term shared by every subject fits a value between the subjects' own and misfits each of them. The selection
already tests every candidate split by subject too (`physics._test`), so such a term is found; here its form is
decided against the joint fit with every term shared: the accepted term's column is split into one column per
subject in the joint fit (`ident.JointProblem.fit_split`, the base and the other terms shared): its per-subject θ
with HAC SEs. The rule is the learned path's (`subjects.subject_form`)
applied to these fitted θ instead of post-hoc ones: the subjects must differ (Cochran's Q, p < 0.05), a subject
carries the term where its θ has the physical sign and clears z = Φ⁻¹(1 − 0.025/S) (Bonferroni over the S
subjects); some subjects only: a switch (the term on their trials, one θ); all of them: every subject at their
own size. The form is taken only where it beats the shared term on held-out data (paired squared errors,
block-bootstrap 95 % CI above 0), cross-fitted so that every segment is held out once (`JointProblem.cross_sq`):
the held-out segments alone, a quarter of the data, could not tell apart two subjects' sizes that the joint fit
separates at 8 SEs (docs/DIAGNOSIS.md, "A subject form cross-fitted"). It changes how an accepted term is sized,
not whether it is accepted: the family's significance budget is untouched.
"""
from __future__ import annotations

import math

import numpy as np

from ..extensions import SIZEABLE
from . import ident, physics
from .candidates import LIBRARY
from .subjects import carriers, refused_text, theta_text


def _ci(effect: str, th: float, se: float) -> tuple[float, list]:
    """The vocabulary's parameter and 95 % interval of a linear θ (a strap's k = 1/θ)."""
    return LIBRARY[effect].report_param(dict(estimate=th, ci=[th - physics.Z95 * se, th + physics.Z95 * se]))


def form_of(prob: ident.JointProblem, f: ident.Fit, effect: str, users: list, row_user: np.ndarray, flat,
            n_boot: int) -> dict | None:
    """The subject form of the accepted linear term `effect` in the joint fit `f` (module docstring), or None; the
    record with `refused` where a subject's θ is as clearly unphysical (`carriers`). `users`, `row_user`:
    `Flat.user_index`."""
    masks = [(row_user == k).astype(float) for k in range(len(users))]
    th, se, split = prob.fit_split(f, effect, masks)
    if not np.all(np.isfinite(se) & (se > 0)):
        return None
    on_users, out = carriers(effect, users, th, se)
    out["method"] = "the joint fit with the term split by subject (weighted LS, HAC SE)"
    if not on_users:    # where an unphysical subject refused every carrier, the record says why (`take` keeps it)
        return dict(out, refused=True) if out["unphysical_subjects"] else None
    on = [users.index(u) for u in on_users]
    trial_user = np.array([users.index(m["subject"]) for m in flat.trial_meta], dtype=np.int64)
    if len(on) < len(users):        # a switch: the term on these subjects' trials only, one θ
        mask = np.isin(row_user, on).astype(float)
        (th_on,), (se_on,), fit = prob.fit_split(f, effect, [mask])
        est, ci = _ci(effect, float(th_on), float(se_on))
        out.update(kind="switch", subjects=[users[k] for k in on], trials=np.isin(trial_user, on).astype(float),
                   theta=float(th_on), estimate=est, ci=ci)
    elif effect in SIZEABLE and np.all(th > 0):     # every subject at their own size: θ_u = θ e^{a_u}
        log_th = np.log(th)
        sd = float(np.sqrt(np.sum((se / th) ** 2))) / len(users)     # of the mean log size (delta method)
        fit = split
        theta = float(math.exp(log_th.mean()))
        est, ci = LIBRARY[effect].report_param(dict(estimate=theta, ci=[math.exp(log_th.mean() - physics.Z95 * sd),
                                                                         math.exp(log_th.mean() + physics.Z95 * sd)]))
        out.update(kind="sizes", users=list(users), subject_of_trial=trial_user,
                   log_sizes=[float(v) for v in log_th - log_th.mean()], theta=theta, estimate=est, ci=ci,
                   estimate_by_subject={u: dict(zip(("estimate", "ci"), _ci(effect, float(th[k]), float(se[k]))))
                                        for k, u in enumerate(users)})
    else:
        return None
    e_shared, e_form = prob.cross_sq(f), prob.cross_sq(f, effect, masks if out["kind"] == "sizes" else [mask])
    g = physics._held_gain(e_shared, e_form, n_boot)
    out["advantage_over_shared"] = dict(gain=g["gain"], ci=g["ci"], rows=int(np.isfinite(e_shared - e_form).sum()),
                                        scale="parametric base, unweighted, cross-fitted over every segment")
    if not g["ci"][0] > 0:      # kept shared, and the record says why (the report's "one term for every subject")
        adv = out.pop("advantage_over_shared")
        kept = {k: v for k, v in out.items() if k not in ("trials", "subject_of_trial")}
        return dict(kept, not_taken=True, **{("sizes_advantage_over_shared" if out["kind"] == "sizes"
                                              else "advantage_over_shared"): adv})
    out["fit"] = fit
    return out


def form_masks(form: dict, row_trial: np.ndarray) -> list:
    """A taken form's row masks (`form_of`'s record; `row_trial`: each row's trial): a switch's one mask over its
    subjects' trials, or one per subject for their own sizes, as `ident.JointProblem.split` takes them."""
    if form["kind"] == "switch":
        return [np.asarray(form["trials"], float)[row_trial]]
    subject = np.asarray(form["subject_of_trial"])[row_trial]
    return [(subject == k).astype(float) for k in range(len(form["users"]))]


def take(res: physics.PhysicsResult, flat, n_boot: int, log=None, joints=None) -> None:
    """Every accepted linear term of `res` in its joint's fit given its subject form where the data ask for one
    (`res.forms`); the joint's held-out errors (`res.e_held`, which the second gate reads) then those of the form's
    fit. `joints`: only these (default: every joint with an accepted term)."""
    who = flat.user_index()
    if who is None:
        return
    users, row_user = who
    for j in sorted({jj for _, jj in res.accepted if joints is None or jj in joints}):
        prob, forms = res._probs[j], {}
        prob.split = {}             # the forms are judged against the joint fit with every term shared
        shared = prob.fit(res._fits[j].terms, intervals=False)
        for e in [x for x in res._fits[j].terms if not ident.TERMS[x].fixed]:   # a delay's size is its ν
            form = form_of(prob, shared, e, users, row_user, flat, n_boot)
            if form is not None and (form.get("refused") or form.get("not_taken")):
                res.forms_refused[(e, j)] = form
                if log:
                    log(f"physics: {e} on {flat.joints[j]} kept shared: " + (refused_text(form) if form.get("refused")
                                                                             else not_taken_text(form)))
            elif form is not None:
                forms[e] = form
        if not forms:
            continue
        # one form per joint equation: the one that gains most over the shared fit (the others stay shared)
        e = max(forms, key=lambda x: forms[x]["advantage_over_shared"]["gain"])
        form = forms[e]
        res.forms[(e, j)] = form
        res.e_held[j] = prob.held_sq(form["fit"], res.held_rows, recorded=True)
        if log:
            what = (f"{', '.join(form['subjects'])} only" if form["kind"] == "switch" else
                    "every subject at their own size: " + ", ".join(
                        f"{u} {v['estimate']:.4g}" for u, v in form["estimate_by_subject"].items()))
            log(f"physics: {e} on {flat.joints[j]} differs by subject (Q {form['heterogeneity']['Q']:.3g}, "
                f"p {form['heterogeneity']['p']:.2g}): {what}, {form['estimate']:.4g} [{form['ci'][0]:.4g}, "
                f"{form['ci'][1]:.4g}]; beats the shared term on held-out data by "
                f"{form['advantage_over_shared']['gain']:.3g}")


def not_taken_text(form: dict) -> str:
    """Why a form the subjects' θ ask for keeps the term shared (`form_of`: no held-out advantage), for the log."""
    what = (f"a term of {', '.join(form['subjects'])} only" if form["kind"] == "switch" else "a size per subject")
    adv = form.get("advantage_over_shared") or form["sizes_advantage_over_shared"]
    return (f"θ by subject {theta_text(form)}; {what} does not beat the shared term on held-out data "
            f"({adv['gain']:.3g} [{adv['ci'][0]:.3g}, {adv['ci'][1]:.3g}])")
