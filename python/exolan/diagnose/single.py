"""Step 2 and 4 of the learned path: every candidate screened post hoc, the promising ones refitted warm with the
base and judged term by term (rules 1, 2, 4 and 5), a friction whose warm refit failed rule 1 or 2 given its
second look from scratch (`rescue`), and each candidate's single-term verdict with its reasons."""
from __future__ import annotations

import time

import numpy as np

from .candidates import LIBRARY, blank_entry
from .export import extend
from .inference import identifiable
from .limits import injected_limit
from .nulls import failed_text
from .refits import refit
from .rules import gci, invariance_reason
from .screen import screen
from .secondlook import paired_failures, paired_record
from .subjects import take_form


def looks(ss, effect: str) -> int:
    """How many looks a candidate's single-term decision may take: two where a friction's warm refit may be
    followed by the second look from scratch (`rescue`), else one. Each gets an even share of its level."""
    c = LIBRARY[effect]
    return 2 if (ss.s.rescue and ss.s.rescue_frictions and ss.from_scratch and c.kind == "finding"
                 and not c.needs_exo) else 1


def fit_candidates(ss) -> list:
    """Every (effect, joint) the data can test: screened, and where the screen passes refitted and judged, the
    candidates side by side (`Session.workers`: each screen and decision reads only the reference's, so the order
    is free)."""
    results, tasks = [], []
    for effect in ss.s.effects:
        c = LIBRARY[effect]
        for j in ss.joint_ids:
            entry = blank_entry(effect, j, ss.flat, ss.subjects)
            results.append(entry)
            if c.needs_exo and not ss.flat.has_exo:
                entry.update(status="rejected", reason="no exoskeleton torque recorded: not testable")
                continue
            tasks.append(lambda entry=entry, effect=effect, j=j: screened(ss, entry, effect, j))
    ss.workers.map(tasks)
    return results


def screened(ss, entry, effect: str, j: int) -> None:
    """One candidate's post-hoc screen (`screen`) and, where it passes, its warm refit and rules (`fit_candidate`)."""
    c = LIBRARY[effect]
    sc = screen(ss.ref, ss.flat, effect, j, n_boot=max(ss.s.n_boot // 3, 100), seed=ss.s.seed)
    entry.screen = {k: v for k, v in sc.items() if k in ("gain", "ci", "theta", "vs", "d", "form")}
    if sc["passes"]:
        return fit_candidate(ss, entry, effect, j, sc)
    entry.update(status="absorbable" if c.kind == "absorbable" else "rejected",
                 reason=("a flexible conservative model represents this effect; " if c.kind == "absorbable"
                         else "") + "screen: " + sc["reason"], heldout_gain=sc["gain"], heldout_gain_ci=sc["ci"])
    ss.log(f"{effect:18s} {ss.flat.joints[j]:9s} screen gain {gci(sc)}: {sc['reason']}")


def fit_candidate(ss, entry, effect: str, j: int, sc: dict) -> None:
    """Rules 1, 2, 4 and 5 for one candidate refitted warm with the base (in its subject form, where one is
    taken), at its share of the budget; the rescue where its warm refit identifies it but fails on its gain."""
    c, t1 = LIBRARY[effect], time.time()
    ext = extend(ss.base, ss.flat, [(effect, j)], init=c.screen_init(sc), max_delay=ss.s.max_delay)
    refit(ext, ss.flat, ss.s)
    e_user, e = ss.errors(ext)
    level = ss.budget.single(looks(ss, effect))

    judged = {}    # id(model) -> judge's fields and gains: the form taken is not judged a second time

    def could_pass(model, model_user, model_e) -> bool:     # a form's warm fit judged alone: no fit from scratch
        judged[id(model)] = judge(ss, effect, j, model, model_user, model_e, level)
        return rules_pass(judged[id(model)][0])

    ext, e_user, e = take_form(ss, entry, effect, j, sc, ext, e_user, e, could_pass=could_pass)
    verdict, g, gu = judged.get(id(ext)) or judge(ss, effect, j, ext, e_user, e, level)
    entry.update(**verdict)
    entry.fit_seconds = round(time.time() - t1, 1)
    ss.fitted[(effect, j)] = (ext, e)
    est, ci = entry["estimate"], entry["ci"]
    ss.log(f"{effect:18s} {ss.flat.joints[j]:9s} est {est:.4g} ci [{ci[0]:.3g}, {ci[1]:.3g}] gain {gci(gu)} "
           f"rel {gu['rel']:.3f}; decision ({ss.scale}) {gci(g)}, level {100 * (1 - level):.2f} % "
           f"({time.time() - t1:.0f} s)")
    # the absorbed case only: the warm fit identifies the term (rule 4) and fails on its gain alone
    if (looks(ss, effect) == 2 and "form" not in entry and entry.identifiable and
            not (entry.passes_gain and entry.passes_floor)):
        rescue(ss, entry, effect, j, sc, level)


def judge(ss, effect: str, j: int, ext, e_user, e, level: float) -> tuple[dict, dict, dict]:
    """Rules 1, 2, 4 and 5 of one candidate's warm fit `ext` (user and decision errors `e_user`, `e`) at its
    `level`. Returns the verdict's fields (for `Verdict.update`) and the decision's and the user's paired gains
    (for the log)."""
    c = LIBRARY[effect]
    g = ss.gain(ss.e_ref, e)                  # the decision's gain (its interval at 95 % for the report)
    gu = ss.gain(ss.e_ref_user, e_user)       # the user's
    pci = ss.tools.param_ci(ext, ss.flat, effect, j)
    est, ci = c.report_param(pci)
    v = dict(pci=pci, rank=g["gain"], level=level, estimate=est, ci=ci, heldout_gain=gu["gain"],
             heldout_gain_ci=gu["ci"], relative_gain=gu["rel"], relative_gain_ci=gu["rel_ci"], block=g["block"],
             decision_gain=dict(gain=g["gain"], ci=g["ci"], scale=ss.scale, level=1 - level),
             identifiable=identifiable(effect, pci, ss.s.max_delay))
    if c.shape is not None:
        v["vs"] = float(ext.stribeck()[1][j].detach())
    # rule 1 at the candidate's level on the decision's scale, and the user's torque error must not grow
    v["passes_gain"] = bool(ss.passes_at(g, level) and gu["gain"] > 0)
    v["passes_floor"] = ss.above_noise(g, alpha=level)
    if c.linear and g["gain"] > 0 and not (v["passes_gain"] and v["passes_floor"]):
        v["size_limit"] = size_limit(g, ss.sigma_r, abs(est - c.neutral), level)
    # rule 5 for every term, exo-driven ones included (a clean world's hip "delay" rested on two tasks)
    v["task_invariance"] = ss.invariance(ss.e_ref - e, ext, effect, j)
    v["passes_invariance"] = v["task_invariance"]["passes"]
    v["subject_gains"] = ss.subject_gains(ss.e_ref_user - e_user)
    return v, g, gu


def rules_pass(entry) -> bool:
    """Rules 1, 2, 4 and 5 as `judge` wrote them (step 4's verdict adds rule 3's nulls for exo-driven terms)."""
    return bool(entry["passes_gain"] and entry["passes_floor"] and entry["identifiable"] and
                entry["passes_invariance"])


def rescue(ss, entry, effect: str, j: int, sc: dict, level: float) -> None:
    """The second look of a friction whose screen asked for it and whose warm refit identifies it but failed rule
    1 or 2 (a base that absorbed most of the effect leaves little to a warm start): the term fitted from scratch,
    gaining at the reference's seed against the term-free base, then `second_look` at the candidate's other
    half of its level. Where it passes, the fit from scratch stands for the candidate in every later rule (its
    estimate and gains; rule 5 on the seeds' mean paired gain with their spread as noise), the warm fit kept
    in `warm_fit`. Frictions only: an exo-driven term's fit from scratch is not identified alone."""
    key, t1, flat = ((effect, j),), time.time(), ss.flat
    init = LIBRARY[effect].screen_init(sc)
    m = ss.cache.fresh(key, init)
    u_f, e_f = ss.errors(m)
    u_0, e_0, tw = ss.cache.optima(key)
    gf = ss.confirm(e_0, e_f, level, twins=tw, look="rescue: cross-seed")
    pf = ss.tools.param_ci(m, flat, effect, j)
    est, ci = LIBRARY[effect].report_param(pf)
    ok = identifiable(effect, pf, ss.s.max_delay)
    record = dict(estimate=est, ci=ci, identified=ok, cross_seed=dict(
        gain=gf["gain"], ci=gf["ci"], level=gf["level"], combination=gf["combination"],
        noise_between_optima=gf.get("refit_sd"), above_noise=gf["passes"], scale=ss.scale))
    entry.from_scratch = record
    head = (f"{effect:18s} {flat.joints[j]:9s} its warm refit failed rule 1 or 2; from scratch est {est:.4g} "
            f"ci [{ci[0]:.3g}, {ci[1]:.3g}]")
    if not (ok and gf["gain"] > 0):
        record.update(passes=False, user_gain=float(np.mean(u_0 - u_f)),
                      why="not identified" if not ok else "no gain at the reference's seed")
        ss.log(f"{head}, {record['why']} ({gci(gf)}): fails ({time.time() - t1:.0f} s)")
        return
    pr = ss.second_look(key, init, m, (u_f, e_f), level)
    if not pr["looked"]:
        share = pr["terms_share"]
        record.update(passes=False, user_gain=float(np.mean(u_0 - u_f)), terms_share=share,
                      why=f"switched off, the term costs its fit only {gci(share)}: within the refit noise "
                          "floor (an effect of this size cannot be told from a refit's noise in these data); "
                          "not fitted at the other seeds")
        ss.log(f"{head}, gain {gci(gf)} at the reference's seed, but {record['why']} (σ_r {ss.sigma_r:.3g}): fails "
               f"({time.time() - t1:.0f} s)")
        return
    ests = [float(mk.estimate(effect, j)) for mk in pr["models"]]
    passes = pr["confirmed"]
    record.update(passes=passes, user_gain=pr["user_gain"], user_gain_by_seed=pr["user_gain_by_seed"],
                  estimates_by_seed=ests, decision_gain=dict(paired_record(pr), scale=ss.scale))
    ss.log(f"{head} (" + ", ".join(f"{v:.4g}" for v in ests) + f" at {pr['seeds']} seeds), paired gain {gci(pr)} "
           f"at {100 * pr['level']:.2f} % ({pr['combination']}; by seed "
           + ", ".join(f"{v:.3g}" for v in pr["gain_by_seed"]) + f"; noise between seeds {pr['refit_sd']:.3g}); "
           f"switched off, the term costs its fit {gci(pr['terms_share'])} (refit noise σ_r {ss.sigma_r:.3g}): "
           f"{'passes' if passes else 'fails'} ({time.time() - t1:.0f} s)")
    if not passes:
        return
    gu = ss.gain(u_0, u_f)
    entry.warm_fit = {k: entry[k] for k in ("estimate", "ci", "heldout_gain", "heldout_gain_ci", "decision_gain")}
    entry.update(estimate=est, ci=ci, pci=pf, rank=pr["pooled"]["gain"], rescued=True,
                 heldout_gain=gu["gain"], heldout_gain_ci=gu["ci"], relative_gain=gu["rel"],
                 relative_gain_ci=gu["rel_ci"], block=gu["block"], identifiable=True,
                 decision_gain=dict(record["decision_gain"], fitted="from scratch"),
                 passes_gain=bool(gu["gain"] > 0), passes_floor=True,
                 task_invariance=ss.invariance(pr["d"], m, effect, j, twins=pr["twins"]),
                 subject_gains=ss.subject_gains(u_0 - u_f))
    entry.passes_invariance = entry.task_invariance["passes"]
    ss.fitted[(effect, j)] = (m, e_f)


def size_limit(g: dict, sigma_r: float, theta: float, level: float) -> float:
    """The size from which a term linear in θ (`Candidate.linear`) would pass rules 1 and 2 in these data, given
    its warm refit at |θ − no effect| = `theta` with decision gain g: the gain grows as θ², its sampling error
    as θ (`limits.injected_limit`, the fit itself taken as the injection). The refit's gain holds what the base
    absorbed of the term, so this is the limit of the learned path as it decided, first order in θ."""
    return injected_limit(g["gain"], g["se"], sigma_r, theta, level)


def _why_rejected(entry, c) -> list[str]:
    why = []
    if not entry["passes_gain"]:
        why.append("held-out gain CI includes 0" if not entry["decision_gain"]["ci"][0] > 0 else
                   "the unweighted held-out torque error grows" if entry["heldout_gain"] <= 0 else
                   f"held-out gain not above 0 at the candidate's level ({100 * (1 - entry['level']):.2f} %)")
    elif not entry["passes_floor"]:
        why.append("gain within the refit noise floor")
    if entry.get("size_limit") is not None and not (entry["passes_gain"] and entry["passes_floor"]):
        unit = f" {entry['unit']}" if entry.get("unit") else ""
        why.append(f"these data show a term of this kind from about {entry['size_limit']:.3g}{unit} (its gain, "
                   f"{entry['decision_gain']['gain']:.3g} at {entry['estimate']:.3g}, grows as the size squared)")
    fs = entry.get("from_scratch")
    if fs and not fs["passes"]:
        dg = fs.get("decision_gain")
        if dg is None:      # stopped at the reference's seed
            cs = fs["cross_seed"]
            gained = f"{cs['gain']:.3g} [{cs['ci'][0]:.3g}, {cs['ci'][1]:.3g}]"
            why.append(f"fitted from scratch ({fs['estimate']:.4g}) " + (
                f"it gains {gained} at the reference's seed ({cs['combination']}), but {fs['why']}"
                if "terms_share" in fs else f"{fs['why']} ({gained}, {cs['combination']})"))
        else:
            why.append(f"fitted from scratch ({fs['estimate']:.4g}) it gains {dg['gain']:.3g} "
                       f"[{dg['ci'][0]:.3g}, {dg['ci'][1]:.3g}] paired over seeds ({dg['combination']}, "
                       f"{100 * dg['level']:.2f} %): " + ", ".join(paired_failures(dg)))
    if not entry["identifiable"]:
        why.append("parameter not identified (CI reaches the no-effect value / boundary)")
    if entry["passes_gain"] and not entry["passes_invariance"]:
        why.append(invariance_reason(entry["task_invariance"]))
    if c.needs_exo and entry.get("passes_null") is False:
        why.append(failed_text(entry["null_gain"]))
    return why


def verdicts(results: list) -> None:
    """Step 4: each candidate's single-term verdict (rules 1-5, the nulls of rule 3 for exo-driven terms)."""
    for entry in results:
        if "status" in entry:
            continue
        c = LIBRARY[entry["effect"]]
        passes = rules_pass(entry) and (entry.get("passes_null", True) if c.needs_exo else True)
        entry.passes = passes
        if c.kind == "absorbable":
            entry.update(status="absorbable", reason=(
                "a flexible conservative model represents this effect (coordinates of H and V, or a potential); "
                + ("it still improved held-out torque" if passes else "no held-out gain beyond the refit noise floor")))
        elif not passes:
            entry.update(status="rejected", reason="; ".join(_why_rejected(entry, c)))
