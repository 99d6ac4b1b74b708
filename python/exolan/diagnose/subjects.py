"""Subject forms: whether a candidate is a property of some subjects only (a switch over their trials) or of every
subject at their own size, proposed from the training rows (`subject_form`) and taken only where the form's
refit beats the shared term on held-out data (`take_form`)."""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy import stats as scipy_stats

from ..extensions import SIZEABLE
from .candidates import LIBRARY
from .fit import predict
from .flat import Flat
from .inference import cochran_q, hac_step
from .rules import gci, invariance_reason
from .screen import features


def subject_form(model, flat: Flat, effect: str, j: int, sc: dict, predict=predict) -> dict | None:
    """Whether (effect, joint j) looks like a property of some subjects only, from the training rows alone.

    An effect may sit in some users only (one user's strap, one exoskeleton unit's friction). A term shared by
    every subject then fits a diluted value that helps the subjects who have it and hurts the others, and the
    fit weights (the base misfits those users' trials most) shrink the evidence further (measured:
    docs/DIAGNOSIS.md, "Measurements behind the code").

    Per subject, the post-hoc θ of the screen's feature (its grid variant, `sc`) on the model's training
    residual, with its HAC SE. The term is gated to the subjects whose θ has the physical sign and clears
    z = Φ⁻¹(1 − 0.025/n_subjects) (Bonferroni over the subjects) when the others do not, and the subjects' θ
    differ (Cochran's Q, p < 0.05). Post-hoc θ is biased towards 0 (the model has absorbed part of the effect),
    so it only proposes the form: `run` takes it only where the gated term, refitted, beats one shared term on
    held-out data beyond the refit noise (a shared effect that the base absorbed in some subjects more than in
    others gives the same post-hoc picture), and the gated term must then pass every rule like any other.
    Returns None for a pooled term (every subject, or data with one subject), and the record with `refused` where
    a subject's θ is as clearly unphysical (`carriers`).
    """
    users = sorted({m["subject"] for m in flat.trial_meta})
    if len(users) < 2 or all(m["subject"] == m["name"] for m in flat.trial_meta):
        return None     # one subject, or recordings named after their files (layout 2 without a subject column)
    tr = flat.index("train")
    subj = flat.subjects_of(tr)
    rows = []                   # each subject's training rows, in time order (at most 20000 per subject)
    for u in users:
        idx = tr[torch.as_tensor(subj == u)]
        rows.append(idx[torch.linspace(0, len(idx) - 1, 20000).long()] if len(idx) > 20000 else idx)
    idx = torch.cat(rows)
    keys = [k for k in ("d", "vs", "own_variation") if k in sc]      # the screen's grid variant
    variants = features(model, flat, idx, effect, j)
    F = next((F for extra, F in variants if all(extra.get(k) == sc[k] for k in keys)), variants[0][1])
    m = flat.mass[idx].numpy().astype(np.float64)
    a_all = F[:, j] / m
    r_all = (flat.tau[idx, j] - predict(model, flat, idx)[:, j]).numpy().astype(np.float64) / m
    th, se = {}, {}
    start = 0
    for u, rw in zip(users, rows):
        a, r = a_all[start:start + len(rw)], r_all[start:start + len(rw)]
        start += len(rw)
        if not np.std(a) > 0:
            return None
        th[u], se[u], _ = hac_step(a, r, len(rw))
    on, out = carriers(effect, users, np.array([th[u] for u in users]), np.array([se[u] for u in users]))
    if not on:          # no form; where an unphysical subject refused it, the record says why (`take_form` logs it)
        return dict(out, refused=True) if out["unphysical_subjects"] else None
    if len(on) < len(users):    # a switch: the term on these subjects' trials only
        trial_on = np.array([flat.trial_meta[i]["subject"] in on for i in range(len(flat.trial_meta))], dtype=float)
        out.update(subjects=on, trials=trial_on)
    if effect in SIZEABLE:      # every subject at their own size (θ_u = θ e^{a_u}, `ExtendedModel`'s sizes)
        out["subject_of_trial"] = np.array([users.index(m["subject"]) for m in flat.trial_meta], dtype=np.int64)
        out["users"] = users
    return out if ("subjects" in out or "users" in out) else None


def carriers(effect: str, users: list, th: np.ndarray, se: np.ndarray) -> tuple[list, dict]:
    """The subjects that carry an effect by their own θ (with SEs): where the subjects differ (Cochran's Q,
    p < 0.05), those whose θ has the physical sign and clears z = Φ⁻¹(1 − 0.025/S) (Bonferroni over the S
    subjects); none where they do not differ. And the record of the test (θ by subject, Q, the z bound).

    A subject whose θ clears the same bound on the side no physical size takes (a negative damping, stiffness,
    delay) shows how far the column's misfit reaches: what the base or another joint's wrongly sized term leaves
    in one subject's residual can sit on either side of 0 (seed 66 of the slow suite: a hip "strap" of +1.3e-4 in
    S01 and −1.1e-4 in S02, both the knee strap's leak). A carrier must then also clear the bound against the
    mirror of the most unphysical θ, (θ_u − |θ_m|) / √(SE_u² + SE_m²) (`unphysical_subjects` names them)."""
    Q, p_het = cochran_q(th, se)
    z_crit = float(scipy_stats.norm.ppf(1 - 0.025 / len(users)))
    z = th / se
    positive = LIBRARY[effect].positive
    on = [k for k in range(len(users)) if (z[k] if positive else abs(z[k])) > z_crit] if p_het < 0.05 else []
    against = [k for k in range(len(users)) if positive and z[k] < -z_crit] if on else []
    if against:
        m = max(against, key=lambda k: -th[k])
        on = [k for k in on if (th[k] + th[m]) / math.hypot(se[k], se[m]) > z_crit]
    rec = dict(theta_by_subject={u: dict(theta=float(th[k]), se=float(se[k])) for k, u in enumerate(users)},
               heterogeneity=dict(Q=Q, df=len(users) - 1, p=p_het), z_crit=z_crit,
               unphysical_subjects=[users[k] for k in against])
    return [users[k] for k in on], rec


def gated(init: dict, form: dict | None, effect: str, j: int) -> dict:
    """`init` with a candidate's subject form (`take_form`'s: `kind` "switch" or "sizes") for (effect, joint j),
    where it has one: a switch over the trials, or per-subject sizes (started at the fitted ones where the form
    holds them)."""
    if not form:
        return init
    out = dict(init)
    if form.get("kind", "switch") == "switch":
        gates = {k: dict(v) for k, v in (out.get("gates") or {}).items()}
        gates.setdefault(effect, {})[j] = form["trials"]
        out["gates"] = gates
    else:
        sized = {k: dict(v) for k, v in (out.get("sized") or {}).items()}
        sized.setdefault(effect, {})[j] = form.get("log_sizes")
        out["sized"] = sized
        out["subject_of_trial"] = form["subject_of_trial"]
    return out


def theta_text(form: dict) -> str:
    """A form record's θ by subject with SEs, for the log."""
    return ", ".join(f"{u} {v['theta']:.3g} ± {v['se']:.2g}" for u, v in form["theta_by_subject"].items())


def refused_text(form: dict) -> str:
    """Why a refused form (`carriers`' record with unphysical subjects) keeps the term shared, for the log."""
    return (f"θ by subject {theta_text(form)}; none stands out from the mirror of "
            f"{', '.join(form['unphysical_subjects'])}'s, as clearly on the unphysical side: the subjects' spread is "
            "not this term's")


def sizes_text(form: dict) -> str:
    """A sizes form's factors e^{a_u} by user, for the log (the fit from scratch's where there is one)."""
    return ", ".join(f"{u} ×{math.exp(a):.3g}" for u, a in
                     zip(form["users"], form.get("log_sizes_from_scratch", form["log_sizes"])))


def with_init(init: dict, values: dict, j: int) -> dict:
    """`init` (ExtendedModel's warm start: effect → number or {joint: number}) with `values` set on joint j
    only: two accepted terms of one effect on different joints keep their own starts."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in init.items()}
    for key in ("gates", "sized"):
        if key in out:
            out[key] = {k: dict(v) for k, v in out[key].items()}
    for k, v in values.items():
        out[k] = {**(out[k] if isinstance(out.get(k), dict) else {}), j: float(v)}
    return out


def with_estimate(init: dict, entry: dict, j: int) -> dict:
    """`init` with a candidate's single-term estimate as the start of its term at joint j (and Stribeck's vs)."""
    c = LIBRARY[entry["effect"]]
    init = gated(with_init(init, {c.effect: entry["estimate"]}, j), entry.get("form"), c.effect, j)
    if c.shape is not None:
        init = with_init(init, {c.shape: entry.get(c.shape.split("_")[-1], c.shape_default)}, j)
    return init


def _try(ss, entry, effect: str, j: int, sc: dict, form: dict, e_user, e) -> tuple[dict, list]:
    """Each form the proposal holds (a switch over some subjects' trials; every subject at their own size), refitted
    warm, and whether it beats the shared term (errors `e_user`, `e`) beyond the refit noise."""
    from .export import extend
    from .refits import refit

    kinds = (["switch"] if "subjects" in form else []) + (["sizes"] if "users" in form else [])
    tried = {}
    for kind in kinds:
        drop = ("users", "subject_of_trial") if kind == "switch" else ("subjects", "trials")
        f = dict({k: v for k, v in form.items() if k not in drop}, kind=kind)
        m = extend(ss.base, ss.flat, [(effect, j)], max_delay=ss.s.max_delay,
                   init=gated(LIBRARY[effect].screen_init(sc), f, effect, j))
        refit(m, ss.flat, ss.s)
        if kind == "sizes":
            f["log_sizes"] = m.size_values()[effect][j]
        m_user, m_e = ss.errors(m)
        adv = ss.gain(e, m_e)
        f["advantage_over_shared"] = dict(gain=adv["gain"], ci=adv["ci"], scale=ss.scale)
        tried[kind] = dict(form=f, model=m, user=m_user, err=m_e,
                           beats=ss.above_noise(adv) and ss.tools.user_improves(e_user, m_user))
    return tried, kinds


def _sizes_or_switch(ss, effect: str, j: int, sc: dict, form: dict, tried: dict) -> list[str]:
    """Both forms beat the shared term: the sizes nest the switch (a size → 0) and are taken only where they beat
    it beyond the refit noise, rule 5 and the user's error too (what any added term must pass). Where the base was
    fitted here both are fitted from scratch first: a warm start keeps what the base absorbed of the smaller size
    (same seed and recipe; the sizes start equal); the one taken is cached as the term's fit from scratch."""
    sw, sz = tried["switch"], tried["sizes"]
    how = "warm start" if not ss.from_scratch else "from scratch"
    if ss.from_scratch:
        for t in (sw, sz):
            f0 = dict(t["form"], log_sizes=None) if t is sz else t["form"]
            t["fresh"] = ss.tools.fresh_fit(ss.flat, ss.s, [(effect, j)], gated(
                LIBRARY[effect].screen_init(sc), f0, effect, j), ss.base_start,
                confused=ss.cache.recipe([(effect, j)]))
            t["cmp_user"], t["cmp_err"] = ss.errors(t["fresh"])
        sz["form"]["log_sizes_from_scratch"] = sz["fresh"].size_values()[effect][j]
    e_sw, e_sz = sw.get("cmp_err", sw["err"]), sz.get("cmp_err", sz["err"])
    adv = ss.gain(e_sw, e_sz)
    inv = ss.invariance(e_sw - e_sz, sz.get("fresh", sz["model"]), effect, j)
    wins = (ss.above_noise(adv) and inv["passes"] and
            ss.tools.user_improves(sw.get("cmp_user", sw["user"]), sz.get("cmp_user", sz["user"])))
    sz["form"]["advantage_over_switch"] = dict(gain=adv["gain"], ci=adv["ci"], scale=ss.scale, fitted=how,
                                               task_invariance=inv)
    take = ["sizes"] if wins else ["switch"]
    if not wins:    # the switch's report says what the sizes did against it
        sw["form"]["sizes_advantage_over_switch"] = dict(
            sz["form"]["advantage_over_switch"], users=sz["form"]["users"],
            log_sizes=sz["form"].get("log_sizes_from_scratch"))
    if ss.from_scratch:
        ss.cache.put(((effect, j),), tried[take[0]]["fresh"])
    ss.log(f"{effect:18s} {ss.flat.joints[j]:9s} a size per subject ({sizes_text(sz['form'])}) against a term of "
           f"{', '.join(form['subjects'])} only, both fitted {how}: {gci(adv)}"
           + ("" if inv["passes"] else f"; {invariance_reason(inv)}"))
    return take


def take_form(ss, entry, effect: str, j: int, sc: dict, ext, e_user, e, could_pass=None) -> tuple:
    """The subject form of (effect, joint j), where the training rows propose one (`Tools.subject_form`) and its
    refit beats the shared term on held-out data beyond the refit noise (a shared effect that the base absorbed
    in some subjects more than in others gives the same post-hoc picture). Returns the model, user and decision
    errors that stand for the candidate (the shared term's where no form is taken); records the form on `entry`.

    Where both forms beat it, `_sizes_or_switch` chooses, from scratch where the base was fitted here: two fits,
    made only where `could_pass(model, e_user, e)` (the candidate's own rules on a form's warm fit) holds for
    either form. A candidate that fails in both forms fails in whichever is chosen, so no verdict moves; the
    switch then stands for it (the nested form) and its record says the two were not compared."""
    form = ss.tools.subject_form(ss.ref, ss.flat, effect, j, sc)
    if form is None:
        return ext, e_user, e
    name = ss.flat.joints[j]
    post = theta_text(form)
    if form.get("refused"):
        entry.subject_form_not_taken = form
        ss.log(f"{effect:18s} {name:9s} kept shared: post-hoc {refused_text(form)}")
        return ext, e_user, e
    tried, kinds = _try(ss, entry, effect, j, sc, form, e_user, e)
    take = [k for k in kinds if tried[k]["beats"]]
    if len(take) == 2:
        if ss.from_scratch and could_pass is not None and not any(
                could_pass(tried[k]["model"], tried[k]["user"], tried[k]["err"]) for k in kinds):
            take = ["switch"]
            tried["switch"]["form"]["sizes_advantage_over_switch"] = dict(
                compared=False, why="not compared from scratch: the candidate fails its rules in either form")
            ss.log(f"{effect:18s} {name:9s} a size per subject and a term of {', '.join(form['subjects'])} only "
                   "both beat the shared term, but the candidate fails its rules warm in either form: not "
                   "compared from scratch")
        else:
            take = _sizes_or_switch(ss, effect, j, sc, form, tried)
    if take:
        t = tried[take[0]]
        f = t["form"]
        entry.form = f
        if f["kind"] == "switch":
            entry.subjects = f["subjects"]
            ss.log(f"{effect:18s} {name:9s} a term of {', '.join(f['subjects'])} only: post-hoc θ by subject {post} "
                   f"(Q's p {f['heterogeneity']['p']:.2g}); beats the shared term by {gci(f['advantage_over_shared'])}")
        else:
            ss.log(f"{effect:18s} {name:9s} every subject at their own size ({sizes_text(f)}): post-hoc θ by subject "
                   f"{post} (Q's p {f['heterogeneity']['p']:.2g}); beats the shared term by "
                   f"{gci(f['advantage_over_shared'])}")
        return t["model"], t["user"], t["err"]
    nt = {k: v for k, v in form.items() if k not in ("trials", "subject_of_trial")}
    if "switch" in tried:
        nt["advantage_over_shared"] = tried["switch"]["form"]["advantage_over_shared"]
    if "sizes" in tried:
        nt["sizes_advantage_over_shared"] = tried["sizes"]["form"]["advantage_over_shared"]
    entry.subject_form_not_taken = nt
    what = {"switch": f"a term of {', '.join(form.get('subjects', []))} only", "sizes": "a size per subject"}
    forms = [f"{what[k]} ({gci(tried[k]['form']['advantage_over_shared'])})" for k in kinds]
    ss.log(f"{effect:18s} {name:9s} kept shared: post-hoc θ by subject {post}; "
           + (f"neither {forms[0]} nor {forms[1]} beats" if len(forms) == 2 else f"{forms[0]} does not beat")
           + " the shared term beyond the refit noise")
    return ext, e_user, e
