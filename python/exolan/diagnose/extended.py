"""Step 7 of the learned path: the extended model. Every accepted term fitted jointly (from scratch where the base
was fitted here; a given model: a warm refit), rule 4 again on the joint fit, rule 1 again for the model handed
over (its looks splitting the confirmation's level), the reported estimates (the joint fit's, widened by the
spread to the warm start) and the notes that go with them."""
from __future__ import annotations

import math

from . import stats
from .candidates import LIBRARY
from .export import extend
from .inference import identifiable, param_by_subject, with_refit_spread
from .refits import metrics, refit
from .rules import gain_as_confirmed, gci
from .secondlook import paired_failures, paired_record


def joint_fit(ss, results: list, acc_init: dict):
    """The accepted terms fitted jointly; a term whose parameter that fit does not identify (rule 4 again) is
    reported as ambiguous and the model fitted again without it. Returns (accepted, model, joint CIs by id)."""
    accepted = [e for e in results if e["status"] == "accepted"]
    while accepted:
        effs = [(e["effect"], ss.flat.joints.index(e["joint"])) for e in accepted]
        if ss.from_scratch:     # reused where forward selection already fitted this set
            model = ss.cache.fresh(tuple(sorted(effs)), dict(acc_init))
        else:
            model = extend(ss.base, ss.flat, effs, init=dict(acc_init), max_delay=ss.s.max_delay)
            refit(model, ss.flat, ss.s)
        cis = {id(e): ss.tools.param_ci(model, ss.flat, e["effect"], ss.flat.joints.index(e["joint"]))
               for e in accepted}
        unconfirmed = [e for e in accepted if not identifiable(e["effect"], cis[id(e)], ss.s.max_delay)]
        if not unconfirmed:
            return accepted, model, cis
        for e in unconfirmed:
            est, ci = LIBRARY[e["effect"]].report_param(cis[id(e)])
            how = " from scratch" if ss.from_scratch else ""
            e.update(status="ambiguous", reason=(
                f"passed every rule on warm starts (estimate {e['estimate']:.4g}), but the joint fit of all accepted "
                f"terms{how} does not identify it: {est:.4g} [{ci[0]:.3g}, {ci[1]:.3g}] reaches its no-effect value "
                f"or a bound"))
            ss.log(f"{e['effect']} {e['joint']}: {e['reason']}")
        accepted = [e for e in accepted if e not in unconfirmed]
    return [], None, {}


def confirm_model(ss, accepted: list, model, acc_init: dict) -> dict:
    """Rule 1 once more for the model handed over: with the accepted terms at their joint estimates it must beat
    its base on held-out data. Where the base was fitted here, up to three looks share the confirmation's level
    (Bonferroni, so the order decides only which model is handed over and what is computed, never whether the
    terms are confirmed): a second look already paired over seeds for these terms (made, free), the reference's
    own refit with the terms held at the estimates of their fit from scratch beyond the refit noise (one warm
    refit), the fit from scratch against a base fitted the same way beyond the noise between optima (term-free
    fits from scratch at other seeds), and that fit's second look paired over seeds. The first look that passes
    hands its model over; the cheapest comes first."""
    s, two = ss.s, ss.from_scratch
    effs = [(e["effect"], ss.flat.joints.index(e["joint"])) for e in accepted]
    key = tuple(sorted(effs))
    alpha = ss.budget.confirmation((3 if s.rescue else 2) if two else 1)
    u_ext, d_ext = ss.errors(model)
    base_0 = "a base fitted from scratch with the same recipe" if two and ss.cache.recipe(effs) else "the reference"
    against = f" (against {base_0})" if base_0 != "the reference" else ""
    by_seeds = lambda pr: dict({k: v for k, v in pr.items() if k not in ("twins", "d", "models", "looked")},  # noqa: E731
                               scale=ss.scale, against=base_0,
                               noise=f"the spread of the paired gains over {pr['seeds']} seeds")
    out = dict(confirmed=False, model=model, u_ext=u_ext, effs=effs,
               how=("fitted from scratch with the terms" + against if two else
                    "the given model refitted with the terms (warm start)"))
    pr = ss.cache.paired.get(key) if two else None
    tried = []
    if pr is not None:      # the more powerful look at the same fit, made already (the rescue)
        out.update(confirmed=pr["confirmed"], confirmation=by_seeds(pr))
        tried.append(gci(by_seeds(pr)) + f" from scratch paired over {pr['seeds']} seeds" + (
            "" if pr["confirmed"] else ": " + (", ".join(paired_failures(paired_record(pr))) or "fails")))
    if not out["confirmed"] and two:
        held_at = ss.tools.around_estimates(ss.base, model, ss.flat, s, effs)
        u_h, d_h = ss.errors(held_at)
        g_h = dict(ss.confirm(ss.e_ref, d_h, alpha, twins=ss.twin_d, look="extended: reference refit held"),
                   scale=ss.scale, against="the reference", noise="twin refits")
        ss.log(f"extended {effs}: the reference's refit with the terms held there {gci(g_h)} ({ss.scale}, "
               f"{g_h['combination']})")
        if g_h["passes"] and ss.tools.user_improves(ss.e_ref_user, u_h):
            out.update(confirmed=True, model=held_at, u_ext=u_h, confirmation=g_h,
                       how="the reference's refit with the terms held at the estimates of their fit from scratch")
        tried.append(f"{gci(g_h)} as the reference's refit with the terms held there (beyond the refit noise required)")
    if not out["confirmed"] and pr is None:
        _from_scratch_look(ss, out, key, alpha, (u_ext, d_ext), (base_0, against), by_seeds, tried, acc_init)
    if not out["confirmed"]:
        for e in accepted:
            e.update(status="ambiguous", reason=(
                f"passed every rule term by term (estimate {e['estimate']:.4g}), but the extended model with all "
                f"accepted terms at their joint estimates does not beat the base on held-out data: "
                f"{', '.join(tried)} ({ss.scale}{f', each look at {100 * (1 - alpha):.2f} %' if two else ''})"))
            ss.log(f"{e['effect']} {e['joint']}: {e['reason']}")
    return out


def _from_scratch_look(ss, out: dict, key: tuple, alpha: float, errors: tuple, judged_against: tuple, by_seeds,
                       tried: list, acc_init: dict) -> None:
    """`confirm_model`'s look at the fit itself: from scratch against a base fitted the same way beyond the noise
    between optima (a given model: the warm refit against the reference), then, where it gained but did not pass,
    its second look paired over seeds (`Settings.rescue`)."""
    s, two, model, (u_ext, d_ext), (base_0, against) = ss.s, ss.from_scratch, out["model"], errors, judged_against
    u_0, e_0, between = (ss.cache.optima(key) if two else (ss.e_ref_user, ss.e_ref, None))
    noise = "between optima (term-free fits from scratch at other seeds)" if between else None
    g_dec = dict(ss.confirm(e_0, d_ext, alpha, twins=between, look="extended: from scratch" if two else
                            "extended: warm"), scale=ss.scale, against=base_0, noise=noise)
    out["confirmation"] = g_dec
    if g_dec["passes"] and ss.tools.user_improves(u_0, u_ext):
        out["confirmed"] = True
        return
    tried.append(gci(g_dec) + (" from scratch" + against if two else ""))
    ss.log(f"extended {out['effs']}: {tried[-1]} ({ss.scale}, {g_dec.get('combination', 'pooled')}): fails")
    if not (two and s.rescue and g_dec["gain"] > 0):
        return
    pr = ss.second_look(key, dict(acc_init), model, (u_ext, d_ext), alpha)
    if pr["looked"] and pr["confirmed"]:
        out.update(confirmed=True, confirmation=by_seeds(pr))
    elif pr["looked"]:
        tried.append(f"{gci(by_seeds(pr))} paired over {pr['seeds']} seeds: "
                     + (", ".join(paired_failures(paired_record(pr))) or "fails"))
    else:
        tried.append(f"switched off, the terms cost that fit only {gci(pr['terms_share'])}: within the refit noise "
                     "floor (not fitted at other seeds)")


def describe(ss, accepted: list, conf: dict, cis: dict, acc_init: dict, starts, ro_base) -> tuple[dict, dict]:
    """The extended model's metrics and gains for the report, and each accepted term's reported estimate: the
    joint fit's, its interval widened by the spread to the warm start (with several terms: the reference refitted
    with all of them, a single-term fit holding what the others explain)."""
    flat, s, model, effs = ss.flat, ss.s, conf["model"], conf["effs"]
    extended, ro_ext = metrics(model, flat, s, starts)
    # the user's (unweighted) gain, combined over tasks as the confirmation was
    g = gain_as_confirmed(ss.e_ref_user, conf["u_ext"], ss.groups, conf["confirmation"], s)
    extended.update(terms=[f"{a}:{flat.joints[j]}" for a, j in effs], model=conf["how"],
                    confirmation=conf["confirmation"], heldout_gain=g["gain"], heldout_gain_ci=g["ci"],
                    relative_gain=g["rel"], relative_gain_ci=g["rel_ci"], heldout_gain_combination=g["combination"],
                    heldout_gain_pooled=g["pooled"],
                    parameters={f"{a}:{flat.joints[j]}": model.estimate(a, j) for a, j in effs}, rollout_gain={})
    for H in (4, 10, 20):
        if H <= s.horizon and len(starts):
            d = ro_base["q_per_start"][:, H - 1] - ro_ext["q_per_start"][:, H - 1]
            b = stats.bootstrap_mean(d, n_boot=s.n_boot // 2)
            extended["rollout_gain"][f"q_mse_{H}"] = dict(gain=b["mean"], ci=b["ci"])
    warm = None
    if len(accepted) > 1:
        warm = ss.warm_fits.get(tuple(sorted(effs)))
        if warm is None:
            warm = extend(ss.base, flat, effs, init=dict(acc_init), max_delay=s.max_delay)
            refit(warm, flat, s)
    for e in accepted:
        c = LIBRARY[e["effect"]]
        if warm is not None:
            e.pci = ss.tools.param_ci(warm, flat, c.effect, flat.joints.index(e["joint"]))
            e.update(estimate_single_term=e["estimate"], ci_single_term=e["ci"],
                     warm_start="the reference refitted with every accepted term")
            e.estimate, e.ci = c.report_param(e.pci)
        elif e.get("rescued"):
            e.warm_start = ("none: the reference refitted with this term alone failed rule 1 or 2 (its estimate in "
                            "warm_fit), the fit from scratch stands in")
        else:
            e.warm_start = "the reference refitted with this term alone"
        est, ci = c.report_param(with_refit_spread(cis[id(e)], e.pci))
        e.update(estimate_warm_start=e["estimate"], ci_warm_start=e["ci"], estimate=est, ci=c.within_bounds(ci))
        # the joint fit's own interval, the one rule 4 checked: the widened one may reach the no-effect value
        e.ci_identification = c.report_param(cis[id(e)])[1]
        e.ci_method = ("HAC sandwich (statsmodels, Newey-West) of the joint refit, widened by its spread to the "
                       f"warm-start fit ({e['warm_start']})")
        own, w_ci = e["ci_identification"], e["ci_warm_start"]
        if stats.span_if_disjoint(own, w_ci):    # the two fits of one model: its size is not identified better
            e.add_note(f"the learned path's two fits disagree: joint fit {est:.4g} [{own[0]:.4g}, {own[1]:.4g}], "
                       f"warm start {e['estimate_warm_start']:.4g} [{w_ci[0]:.4g}, {w_ci[1]:.4g}]; the networks and "
                       "the term share the effect differently in each, and the interval spans both")
    ss.log(f"extended {extended['terms']}: held-out gain {gci(g)}")
    return extended, ro_ext


def notes(ss, results: list, ext_model, limits: dict) -> None:
    """A subject form's record and per-subject sizes; a shared term whose held-out gain clears 0 for some users
    only; a delay within twice the data's detection limit (estimated short)."""
    flat = ss.flat
    for e in results:
        if e.get("form"):
            e.subject_form = {k: v for k, v in e.form.items() if k not in ("trials", "subject_of_trial")}
            if e["status"] == "accepted" and e.form["kind"] == "sizes" and ext_model is not None:
                e.estimate_by_subject = param_by_subject(ext_model, flat, e["effect"], flat.joints.index(e["joint"]),
                                                         e.form["users"])
                ss.log(f"{e['effect']} {e['joint']} by subject: " + ", ".join(
                    f"{u} {v['estimate']:.4g} [{v['ci'][0]:.3g}, {v['ci'][1]:.3g}]"
                    for u, v in e.estimate_by_subject.items()))
            continue
        if e["status"] == "accepted" and e.get("subject_gains"):
            sig = sorted(k for k, v in e["subject_gains"].items() if v["ci"][0] > 0)
            if sig and len(sig) < len(e["subject_gains"]):
                e.add_note("held-out gain above 0 only for " + ", ".join(sig) + " (parameter fitted on all subjects)")
    for e in results:
        key = LIBRARY[e["effect"]].limit_key
        lim = limits.get(e["effect"], {}).get(e["joint"], {}).get(key) if key else None
        if e["status"] == "accepted" and lim and math.isfinite(lim) and e["estimate"] < 2.0 * lim:
            e.add_note(f"within twice these data's detection limit for a delay ({1e3 * lim:.3g} ms): likely "
                       f"estimated short (the base keeps part of a delay near the limit; measured: 24 ms planted, "
                       f"computed limit 19.8 ms, found 18.4 ms)")
