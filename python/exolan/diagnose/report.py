"""The diagnosis report: `diagnosis.json` (the shape of issue 7), `diagnosis.md` and its plots."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..runio import atomic_write, jsonable
from .candidates import library_table
from .report_plots import plot_ccf, plot_gains, plot_residual_vs_velocity, plot_rollouts


def _fmt(x, p=4):
    if x is None:
        return "—"
    if isinstance(x, str):
        return x
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(_fmt(v, p) for v in x) + "]"
    try:
        xf = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(xf):
        return str(xf)
    return f"{xf:.{p}g}"




RULE_TEXT = """Decision rule (every threshold is a statistic of these data, none is tuned to a world):
1. each candidate is first *screened* by a post-hoc least-squares correction of the reference residual
   (fitted on training segments; it must lower held-out error on average, with the physical sign; one correction
   for all data, or one per task, since the model absorbs an effect unevenly across tasks) — only a
   lenient screen, since the fitted model has already absorbed part of any effect (a gain is also screened on the
   controller's own variation alone, the exo torque minus its copy of the joint torque: the copy is what the
   model absorbs);
2. a screened candidate is fitted **jointly** with the whole model (warm start, the same optimiser schedule and
   minibatches as a reference refit of the base model alone); its held-out gain (paired, per sample) must have
   a circular-block-bootstrap 95% CI (block length from the ACF) above 0, **and** stay above 0 when the refit
   noise is added to the bootstrap replicates (their 2.5 % quantile, each plus a draw of N(0, σ_r²)), where σ_r
   is the refit noise (RMS held-out difference between the reference and twin refits that differ only in
   minibatch order; every refit ends on Polyak-averaged network weights, which keeps σ_r small).
   Every refit is a weighted least-squares fit, each trial and joint weighted by the base model's inverse
   misfit there, less what every candidate's column explains of it, so that the tasks the model fits worst do
   not pull a joint's parameter and the trials that carry an effect are not down-weighted for it; every decision
   compares held-out errors with the same weights (the "decision gain"), and the unweighted held-out gain
   (the torque error you see, reported as "held-out gain") must be above 0 too;
3. terms driven by the recorded exo torque (delay, gain, strap) must beat the same term fitted on the exo torque
   taken from the future (at the lag ≥ 25 ms where it correlates most with the residual; a gain also at the
   controller's tracking lag, no nearer than 25 ms either): the future exo torque cannot act now but shares the
   assistive controller's correlation with the human torque; a gain must also show in the controller's own variation (the exo torque
   less its copy of the joint torque, the copy being its fit on the joint torque's recent past): the same term
   on that variation alone must beat the reference beyond the refit noise, with its k on the same side of 1 as
   the whole term's, since a real gain rescales it too; a term tested on top of accepted ones must beat its
   nulls there as well (the accepted terms taken out of the data at their fitted sizes);
4. the parameter's 95% CI (HAC sandwich, statsmodels) must exclude the no-effect value; signs are physics
   (damping, friction, delay, compliance ≥ 0 by construction; a fit at the boundary is not identified);
5. a property of the joint helps in every task: the held-out gain without the quarter of the tasks (at least
   one; trials where the data hold one task) where it is largest — the other tasks' gains combined with
   weights 1/SD (Stouffer: every task's z-score counts alike, so that neither the noisiest task nor the most
   stereotyped one, where a conservative model absorbs the most, decides) — must still be above 0 beyond its
   sampling and refit noise, and those tasks must identify the parameter on their own (its interval at the
   family-wise 95% level, Bonferroni over the candidates considered, excludes the no-effect value) — a term that
   only soaks up the misfit of the worst-fitted tasks is rejected. Exo-driven terms, whose excitation depends
   on the task, may instead show that the other tasks identify the parameter on their own (Gauss-Newton step,
   HAC SE) and that every task shows it — the tasks' θ agree (Cochran's Q, p > 0.05) or, where they differ, a
   new task's 95 % prediction interval from their random-effects pool lies on the physical side of no effect —,
   with a mean gain above 0 there. No task
   may be made worse beyond its sampling and refit noise (Bonferroni over the tasks);
6. confusable rivals on the same joint that held-out data cannot separate are `ambiguous` (where one reduces to
   the other in a limit, Stribeck to Coulomb as vs → ∞, the simpler is taken); an exo-driven term whose exo-driven
   rival (gain/strap, delay/strap) describes the held-out data better but failed its null (rule 3) is rejected:
   the signal both describe is not shown to be the exo torque's; a further term must add held-out
   gain beyond the noise floor (and lower the unweighted error) on top of the already accepted ones and of the
   better term of each ambiguous set (forward selection), confirmed with both models fitted from scratch where
   the base was fitted here (there the unweighted error may not grow beyond the noise between optima on its own
   scale, nor, paired over seeds, beyond the seeds' spread); the extended model with the terms at their joint estimates must beat the base on
   held-out data as in rule 1 (fitted from scratch, or else the base's own refit with the terms held there,
   beyond the refit noise; its looks share the confirmation's 5 %), or its terms are `ambiguous`;
7. encoder offset, torque bias, payload are `absorbable` (never findings).
One significance budget: every accept decision spends from one family-wise 5 % over the m candidates the data can
test: a candidate's single-term test (rules 1 and 2) at α/m (Bonferroni), a further term in forward selection,
after r accepted ones, at α/(m − r) (Holm); a decision that may pass by a second look (the same terms fitted from
scratch and judged paired over seeds) splits its level evenly between its looks (docs/DIAGNOSIS.md).
Where the data hold several subjects, a candidate whose post-hoc correction on the training rows is wanted by
some subjects only (their θ clears a Bonferroni z over the subjects, the others' does not, Cochran's Q p < 0.05)
is fitted as a term of those subjects only (switched off on the other subjects' trials) where that term beats one
shared term on held-out data beyond the refit noise (a shared effect that the base absorbed more in some subjects
looks the same post hoc), and judged by the same rules. Where the subjects' post-hoc θ differ and the term is
linear in its parameter, the term is also fitted in every subject at their own size (θ_u = θ e^(a_u), the log
sizes centred), taken where it beats the shared term, and the switched one, beyond the refit noise (the sizes and
the switched term compared fitted from scratch where the base was fitted here: a warm start keeps what the base
absorbed of a smaller size)."""


def write(out: Path, res: dict) -> dict:
    """Write diagnosis.json, diagnosis.md and the PNGs into `out`; returns the JSON dict."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rep = res["report"]
    flat = res["flat"]
    plots = {}
    try:
        plots["residual_vs_velocity"] = plot_residual_vs_velocity(out, flat, res["ref"], res.get("ext_model"))
        plots["ccf"] = plot_ccf(out, rep["residuals"], flat)
        plots["rollouts"] = plot_rollouts(out, flat, res["ro_base"], res.get("ro_ext"))
        g = plot_gains(out, res["results"], _unit(rep))
        if g:
            plots["gains"] = g
    except Exception as exc:   # a plotting failure must not lose the diagnosis itself
        plots["error"] = repr(exc)
    rep = dict(rep)
    rep["plots"] = plots
    atomic_write(out / "diagnosis.json", json.dumps(jsonable(rep), indent=1, default=str))
    atomic_write(out / "diagnosis.md", markdown(rep))
    return rep


def _unit(rep: dict) -> str:
    """The unit of the report's torque errors (`procedure.torque_unit`; reports written before it: N m/kg)."""
    return (rep.get("data") or {}).get("torque_unit", "N m/kg")


def _metric_rows(b: dict, e: dict | None, unit: str = "N m/kg") -> list[str]:
    rows = ["| metric | base model | extended model |", "|---|---|---|"]
    def get(m, k):
        return m.get(k) if m else None
    raw = "N m" if unit == "N m/kg" else unit
    rows.append(f"| held-out torque MSE [({raw})²] | {_fmt(get(b, 'torque_mse'))} {_fmt(get(b, 'torque_mse_ci'), 3)} | "
                f"{_fmt(get(e, 'torque_mse'))} {_fmt(get(e, 'torque_mse_ci'), 3)} |")
    if unit == "N m/kg":
        rows.append(f"| held-out torque MSE / mass² [(N m/kg)²] | {_fmt(get(b, 'torque_mse_norm'))} | "
                    f"{_fmt(get(e, 'torque_mse_norm'))} |")
    for j, v in (b.get("per_joint") or {}).items():
        ev = (e or {}).get("per_joint", {}).get(j, {})
        rows.append(f"| {j}: rms residual / R² | {_fmt(v['rms'])} / {_fmt(v['r2'], 3)} | {_fmt(ev.get('rms'))} / {_fmt(ev.get('r2'), 3)} |")
    for k, v in (b.get("rollout") or {}).items():
        rows.append(f"| rollout {k} | {_fmt(v)} | {_fmt((e or {}).get('rollout', {}).get(k))} |")
    be, ee = b.get("energy", {}), (e or {}).get("energy", {})
    rows.append(f"| unexplained power q̇ᵀ(τ−τ̂) [W] | {_fmt(be.get('residual_power'))} {_fmt(be.get('residual_power_ci'), 3)} | "
                f"{_fmt(ee.get('residual_power'))} {_fmt(ee.get('residual_power_ci'), 3)} |")
    rows.append(f"| … as fraction of mean abs. input power | {_fmt(be.get('fraction'), 3)} | {_fmt(ee.get('fraction'), 3)} |")
    return rows


def _evidence_lines(f: dict) -> list[str]:
    """Which data carried the evidence of a finding: its held-out gain per task (or trial) and per subject."""
    out = []
    ti = f.get("task_invariance") or {}
    if ti.get("groups"):
        per = ", ".join(f"{g} {_fmt(v, 3)}" for g, v in sorted(ti["groups"].items(), key=lambda kv: -kv[1]))
        rest = (f"; without {', '.join(ti['dropped'])} (the others weighted by 1/SD): {_fmt(ti['gain_rest'], 3)} "
                f"CI {_fmt(ti['ci_rest'], 3)}"
                if ti.get("dropped") else f" ({ti['note']})" if ti.get("note") else "")
        out.append(f"  - gain by {ti['by']}{' (' + ti['scale'] + ')' if ti.get('scale') else ''}: {per}{rest}")
    if ti.get("theta_by_group"):
        th = ", ".join(f"{g} {_fmt(v['estimate'], 3)} ± {_fmt(v['se'], 2)}" for g, v in ti["theta_by_group"].items())
        het = ti.get("heterogeneity") or {}
        ng = ti.get("new_group") or {}
        out.append(f"  - parameter by {ti['by']} (one Gauss-Newton step on its held-out samples, HAC SE): {th}; "
                   f"Cochran's Q {_fmt(het.get('Q'), 3)} on {het.get('df')} df, p {_fmt(het.get('p'), 2)}"
                   + (f"; a new {ti['by']}'s 95 % prediction interval {_fmt(ng['prediction'], 3)} (random effects, "
                      f"τ {_fmt(ng['tau'], 3)})" if ng.get("prediction") else ""))
    if ti.get("note") and ti.get("dropped"):
        out.append(f"  - {ti['note']}")
    for n in f.get("nulls") or []:      # rule 3, for terms driven by the recorded exo torque
        what = (f"the same term on the controller's own variation alone (k {_fmt(n.get('estimate'), 3)}) beats the "
                f"reference by" if n.get("own_variation_only") else
                f"beats the same term on the exo torque {_fmt(1e3 * n['future_lag_s'], 3)} ms in the future by")
        out.append(f"  - null: {what} {_fmt(n['gain'], 3)} CI {_fmt(n['ci'], 3)}{'' if n.get('passes') else ' (not passed)'}")
    def by_subject(form: dict) -> str:
        return ", ".join(f"{u} {_fmt(v['theta'], 3)} ± {_fmt(v['se'], 2)}" for u, v in form["theta_by_subject"].items())

    sf = f.get("subject_form") or {}
    # where θ by subject comes from: the learned path's post-hoc look, or physics first's split joint fit
    theta_from = sf.get("method") or "post-hoc θ by subject on the training rows (HAC SE)"
    if sf.get("subjects"):
        th = by_subject(sf)
        het = sf.get("heterogeneity") or {}
        adv = sf.get("advantage_over_shared") or {}
        out.append(f"  - a term of {', '.join(sf['subjects'])} only (fitted on their trials): {theta_from} {th}; "
                   f"Cochran's Q {_fmt(het.get('Q'), 3)} on {het.get('df')} df, "
                   f"p {_fmt(het.get('p'), 2)}; it beats one shared term by {_fmt(adv.get('gain'), 3)} "
                   f"CI {_fmt(adv.get('ci'), 3)}")
        over = sf.get("sizes_advantage_over_switch")
        if over:
            sizes = (" (" + ", ".join(f"{u} ×{_fmt(math.exp(a), 3)}" for u, a in zip(over["users"], over["log_sizes"]))
                     + " of their geometric mean)") if over.get("log_sizes") is not None else ""
            out.append(f"  - every subject at their own size{sizes} did not beat this term beyond the refit noise: "
                       f"{_fmt(over.get('gain'), 3)} CI {_fmt(over.get('ci'), 3)} (both fitted "
                       f"{over.get('fitted', 'warm start')})")
    if sf.get("kind") == "sizes":
        het = sf.get("heterogeneity") or {}
        adv = sf.get("advantage_over_shared") or {}
        over = sf.get("advantage_over_switch")
        by = f.get("estimate_by_subject") or {}
        out.append("  - every subject at their own size (θ_u = θ e^(a_u), θ the subjects' geometric mean): "
                   + ", ".join(f"{u} {_fmt(v['estimate'])} CI {_fmt(v['ci'], 3)}" for u, v in by.items())
                   + ("" if sf.get("method") else " (HAC on each subject's training rows, conditional on the "
                      "networks: narrower than the shared estimate's interval, which adds the spread to the warm start)")
                   + f"; {theta_from} {by_subject(sf)}, Cochran's Q "
                   f"{_fmt(het.get('Q'), 3)} on {het.get('df')} df, p {_fmt(het.get('p'), 2)}; it beats one shared "
                   f"term by {_fmt(adv.get('gain'), 3)} CI {_fmt(adv.get('ci'), 3)}"
                   + (f" and the term of the subjects whose post-hoc θ clears alone by {_fmt(over.get('gain'), 3)} "
                      f"CI {_fmt(over.get('ci'), 3)} (both fitted {over.get('fitted', 'warm start')})" if over else ""))
    nt = f.get("subject_form_not_taken") or {}
    said = f"θ by subject from {nt['method']}" if nt.get("method") else "post-hoc θ by subject"
    if nt.get("refused"):
        out.append(f"  - one term for every subject: the {said} ({by_subject(nt)}) differ, but "
                   f"{', '.join(nt['unphysical_subjects'])} as clearly on the side no physical size takes, and none "
                   "stands out from its mirror: the subjects' spread is something else the term's column carries")
    if nt.get("subjects"):
        th = by_subject(nt)
        adv = nt.get("advantage_over_shared") or {}
        out.append(f"  - one term for every subject: the {said} ({th}) asked for a term of "
                   f"{', '.join(nt['subjects'])} only, which did not beat the shared one ({_fmt(adv.get('gain'), 3)} "
                   f"CI {_fmt(adv.get('ci'), 3)}): the base absorbs a shared effect more in some subjects than others")
    if nt.get("sizes_advantage_over_shared"):
        adv = nt["sizes_advantage_over_shared"]
        out.append(f"  - one size for every subject: a size per subject ({said} {by_subject(nt)}) did not beat the "
                   f"shared term ({_fmt(adv.get('gain'), 3)} CI {_fmt(adv.get('ci'), 3)})")
    sg = f.get("subject_gains") or {}
    if sg:
        out.append("  - gain by subject: " + ", ".join(f"{k} {_fmt(v['gain'], 3)} {_fmt(v['ci'], 3)}" for k, v in sg.items()))
    if f.get("note"):
        out.append(f"  - note: {f['note']}")
    return out


def _k_cell(k) -> str:
    """A gain limit's table cell: "none" where no gain on that side shows (θ limit ≥ 1: k ≤ 0.5 … 0, or ∞)."""
    return "none" if k is not None and (k == 0 or not np.isfinite(k)) else _fmt(k, 3)


def _ms_cell(d) -> str:
    """A delay limit (s) as a table cell in ms: "none" where no delay up to the injected one shows (∞)."""
    if d is None:
        return "—"
    return "none" if not math.isfinite(float(d)) else _fmt(1e3 * float(d), 3)


def _level_text(*limits: dict) -> str:
    """' (two-sided x %, the single-term test's share of the family-wise level)' from the limits' records."""
    lv = [v["level"] for lim in limits for v in lim.values() if "level" in v]
    return f" (two-sided {_fmt(100 * lv[0], 2)} %, the single-term test's share of the family-wise level)" if lv else ""


def _limit_lines(limits: dict) -> list[str]:
    """The 'What these data cannot show' section: the torque gain's and the actuation delay's detection limits
    per joint."""
    gain = limits.get("torque_gain") or {}
    delay = limits.get("actuation_delay") or {}
    if not gain and not delay:
        return []
    measured = any(v.get("method") == "injection" for v in gain.values())
    measured_d = any(v.get("method") == "injection" for v in delay.values())
    L = ["## What these data cannot show",
         "A torque gain error k or an actuation delay d shows only through the controller's own variation: the "
         "part of the exo torque that copies the joint torque is absorbed by a base that predicts the joint torque "
         "from the motion (rule 3's own-variation null). A gain acts through that variation, a delay (to first "
         "order) through its rate. Gains between the limits below, and delays shorter than the one below, would "
         f"not clear the sampling and refit noise of these data at the level the decision uses{_level_text(gain, delay)} "
         "(an estimate at the base's present misfit, "
         "optimistic where the base absorbs part of the own variation too; a delay near its limit is also "
         "estimated short; `limits.gain_detection_limit`, `limits.delay_detection_limit`). Beyond them a term "
         "must still pass rule 3's future-torque nulls, which a real gain can fail where the exo torque copies "
         "the joint torque closely (docs/DIAGNOSIS.md, \"Seven more 4-user worlds\"), and a size beyond them can "
         "still be missed: the limits say what cannot show, not what will (a knee gain of 0.6, beyond a computed "
         "0.682, was missed; docs/DIAGNOSIS.md, \"Four more 4-user worlds and a gain below 1\")." +
         (" The gain's limits here are measured, not computed: a known gain was written into the recorded joint "
          "torque, the base fitted again from its start and rule 3's own-variation test run on it as on the data; "
          "its held-out gain, scaled as θ², gives the gain at which the test would just pass "
          "(`limits.limits_by_injection`; per joint below the table)."
          if measured else "") +
         (" The delay's limit is measured the same way: a known delay written into the recorded joint torque "
          "(τ_e(t) − τ_e(t − d)), the base fitted again, the delay term refitted on it and held to rules 1 and 2."
          if measured_d else ""), "",
         "| joint | exo torque rms [N m] | share that copies the joint torque | own variation rms [N m] | "
         "a gain can show only below k = | or only above k = | a delay can show only above d = [ms] |",
         "|---|---|---|---|---|---|---|"]
    for j in list(dict.fromkeys(list(gain) + list(delay))):
        v = gain.get(j) or delay.get(j)
        dl = delay.get(j, {}).get("d_limit")
        L.append(f"| {j} | {_fmt(v['rms_exo'], 3)} | {100 * v['copy_share']:.0f} % | {_fmt(v['rms_own'], 3)} | "
                 f"{_k_cell(gain.get(j, {}).get('k_below'))} | {_k_cell(gain.get(j, {}).get('k_above'))} | "
                 f"{_ms_cell(dl)} |")
    L.append("")
    for j, v in gain.items():
        if v.get("method") == "injection":
            c = v["computed"]
            L.append(f"- {j}: a gain of {_fmt(v['injected_k'], 3)} written into the data was recovered as "
                     f"{_fmt(v['recovered_k'], 3)} on the own variation alone, held-out gain {_fmt(v['injected_gain'], 3)} "
                     f"[{_fmt(v['injected_gain_ci'][0], 3)}, {_fmt(v['injected_gain_ci'][1], 3)}] "
                     f"({'passes' if v['passes_at_injection'] else 'does not pass'} rule 3 there"
                     f"{'' if np.isfinite(v['k_above']) else ': no gain up to that size shows in these data at the base’s misfit'}"
                     f"); computed at the "
                     f"base's misfit the limits would be k = {_fmt(c['k_below'], 3)} and {_fmt(c['k_above'], 3)}.")
    for j, v in delay.items():
        if v.get("method") == "injection":
            shows = math.isfinite(float(v["d_limit"]))
            L.append(f"- {j}: a delay of {_fmt(1e3 * v['injected_d'], 3)} ms written into the data was recovered as "
                     f"{_fmt(1e3 * v['recovered_d'], 3)} ms, held-out gain {_fmt(v['injected_gain'], 3)} "
                     f"[{_fmt(v['injected_gain_ci'][0], 3)}, {_fmt(v['injected_gain_ci'][1], 3)}] "
                     f"({'passes' if v['passes_at_injection'] else 'does not pass'} rules 1 and 2 there"
                     f"{'' if shows else ': no delay up to that size shows in these data at the base’s misfit'}); "
                     f"computed at the base's misfit the limit would be {_fmt(1e3 * v['computed']['d_limit'], 3)} ms.")
    if measured or measured_d:
        L.append("")
    return L


def _physics_lines(ph: dict | None, unit: str) -> list[str]:
    """The physics-first identification (`physics`): its base's fit, every accepted term beside the learned base's
    cross-check and check (rule 6), the Holm steps, and which path decided."""
    if not ph:
        return []
    ad = ph.get("adequacy") or {}
    L = ["", "## Physics first: the parametric base", "", ph.get("method", ""), ""]
    L.append(f"Decided by: **{ph.get('path')}** path ({ad.get('rule', '')}); held-out MSE ({unit})², per joint:")
    paths = ph.get("paths") or {}
    for j, v in (ad.get("joints") or {}).items():
        L.append(f"- {j}: decided by the **{paths.get(j, '?')}** path — {v.get('model', 'the parametric base')} "
                 f"{_fmt(v['parametric_mse'])}, the learned reference {_fmt(v['learned_mse'])}, difference "
                 f"{_fmt(v['difference'], 3)} CI {_fmt(v['ci'], 3)}: {'adequate' if v['adequate'] else 'not adequate'}")
    for j, v in (ph.get("heldout") or {}).items():
        L.append(f"- {j}: held-out rms {_fmt(v.get('rms'))} against the recorded torque ({_fmt(v.get('rms_filtered'))} "
                 f"against its low-pass), R² {_fmt(v.get('r2'), 4)}")
    for j, b in (ph.get("base") or {}).items():
        if "columns" not in b:
            L.append(f"- {j} base: " + ", ".join(f"{k} {_fmt(v['value'])} ± {_fmt(v['se'], 2)}" for k, v in b.items()))
    cross, held = ph.get("cross_check") or {}, ph.get("learned_check") or {}
    for k, v in (ph.get("estimates") or {}).items():
        c, h = cross.get(k), held.get(k)
        L.append(f"- {k}: {_fmt(v['estimate'])} CI {_fmt(v['ci'], 3)} (p {_fmt(v['p'], 2)})"
                 + (f"; on the learned base's residual {_fmt(c['estimate'])} CI {_fmt(c['ci'], 3)}" if c else "")
                 + (f"; held at this size in the learned base, held-out gain {_fmt(h['gain'], 3)} ({unit})² "
                    f"CI {_fmt(h['ci'], 3)}" if h else ""))
    if ph.get("tests"):
        L.append("")
        L.append("| step | candidate | p | Holm threshold | estimate | held-out gain [CI] |")
        L.append("|---|---|---|---|---|---|")
        for t in ph["tests"]:
            L.append(f"| {t['step']} | {t['effect']}:{t['joint']} | {_fmt(t['p'], 2)} | {_fmt(t['threshold'], 2)} | "
                     f"{_fmt(t['estimate'])} | {_fmt(t['heldout_gain'], 3)} {_fmt(t['heldout_gain_ci'], 3)} |")
    if ph.get("rule"):
        L += ["", ph["rule"]]
    return L


def _finding_lines(f: dict, U: str) -> list[str]:
    """The verdict's lines for one finding: its size and gain, how its interval was made, the comparisons that
    accepted it, and its evidence."""
    L = []
    unit = "" if f["unit"] == "1" else f" {f['unit']}"      # a gain is a pure number
    who = f" of **{', '.join(f['subjects'])}** only" if (f.get("subject_form") or {}).get("subjects") else ""
    sized = f.get("estimate_by_subject")
    size_text = (" (geometric mean of the subjects' own sizes: " + ", ".join(
        f"{u} {_fmt(v['estimate'])}{unit} CI {_fmt(v['ci'], 3)}" for u, v in sized.items()) + ")") if sized else ""
    L.append(f"- **{f['effect']}** on **{f['joint']}**{who}: {_fmt(f['estimate'])}{unit} "
             f"(95% CI {_fmt(f['ci'], 3)}){size_text}, held-out gain {_fmt(f['heldout_gain'], 3)} ({U})² "
             f"CI {_fmt(f.get('heldout_gain_ci'), 3)}, relative {_fmt(f.get('relative_gain'), 3)}.")
    if f.get("ci_identification") is not None:
        how = f.get("warm_start", "the reference refitted with this term alone")
        L.append(f"  - the interval above adds the spread between the joint fit and the warm start ({how}: "
                 f"{_fmt(f.get('estimate_warm_start'))}; a sign-constrained parameter's interval ends at its "
                 f"no-effect value); the joint fit's own (HAC) interval, which "
                 f"rule 4 checks against the no-effect value: {_fmt(f['ci_identification'], 3)}")
    dg = f.get("decision_gain")
    if dg:
        L.append(f"  - decision gain ({dg.get('scale')}): {_fmt(dg['gain'], 3)} CI {_fmt(dg['ci'], 3)}"
                 + (f" ({dg['combination']}, {100 * dg['level']:.1f}% CI, fitted from scratch at "
                    f"{dg.get('seeds')} seeds, each paired with the term-free fit of its seed: beyond the "
                    f"spread of the paired gains {_fmt(dg.get('noise_between_seeds'), 3)}, by seed "
                    f"{_fmt(dg.get('gain_by_seed'), 3)})"
                    if dg.get("fitted") == "from scratch" else ""))
    share = (dg or {}).get("terms_share")
    if share:
        L.append(f"  - switched off, the term costs its fit {_fmt(share['gain'], 3)} CI "
                 f"{_fmt(share['ci'], 3)}: its own share, beyond the refit noise σ_r "
                 f"{_fmt(share['refit_noise'], 3)} (rule 2)")
    cg = f.get("conditional_gain")
    if cg:      # accepted in forward selection: what it adds to the terms accepted before it
        L.append(f"  - on top of {', '.join(cg['given'])} (warm start): {_fmt(cg['gain'], 3)} CI {_fmt(cg['ci'], 3)}")
        fs = cg.get("from_scratch")
        if fs:
            L.append(f"  - on top of them, both fitted from scratch: {_fmt(fs['gain'], 3)} CI {_fmt(fs['ci'], 3)} "
                     f"({fs.get('combination')}, beyond the noise between optima "
                     f"{_fmt(fs.get('noise_between_optima'), 3)})" + (
                         f"; the user's (unweighted) gain {_fmt(fs['user']['gain'], 3)}, "
                         f"{'below 0 beyond' if fs['user']['grows'] else 'not below 0 beyond'} the noise between "
                         f"optima on that scale {_fmt(fs['user']['noise'], 3)} (rule 1)" if fs.get("user") else ""))
            pr = fs.get("paired") or {}
            if pr.get("seeds"):
                L.append(f"  - paired over {pr['seeds']} seeds (each with the fit of the terms before it at "
                         f"that seed): {_fmt(pr['gain'], 3)} CI {_fmt(pr['ci'], 3)} at "
                         f"{100 * pr['level']:.1f} %, by seed {_fmt(pr['gain_by_seed'], 3)}; switched off, the "
                         f"term costs its fit {_fmt(pr['terms_share']['gain'], 3)} CI "
                         f"{_fmt(pr['terms_share']['ci'], 3)} (σ_r {_fmt(pr['terms_share']['refit_noise'], 3)})")
    wf = f.get("warm_fit")
    if wf:
        wg = wf["decision_gain"]
        L.append(f"  - the reference refitted with this term (warm start) failed rule 1 or 2: estimate "
                 f"{_fmt(wf['estimate'])}, decision gain {_fmt(wg['gain'], 3)} CI {_fmt(wg['ci'], 3)} (a warm "
                 f"start keeps what the base absorbed of the effect); the term was fitted from scratch")
    L += _evidence_lines(f)
    return L


def markdown(rep: dict) -> str:
    d = rep.get("data", {})
    U = _unit(rep)
    findings = rep["findings"]
    L = ["# Diagnosis: what the model's physics gets wrong", ""]
    L.append(f"Data: {d.get('trials')} trial{'' if d.get('trials') == 1 else 's'}, {d.get('samples')} samples, joints {d.get('joints')} "
             f"({d.get('joint_types')}); exo torque recorded: {d.get('has_exo')}; insole: {d.get('has_insole')}. "
             f"Decisions on {d.get('heldout')} held-out samples ({d.get('split')}).")
    L.append(f"Base model: {rep['baseline'].get('source', '')}.")
    L.append("")
    L.append("## Verdict")
    if findings:
        for f in findings:
            L += _finding_lines(f, U)
    else:
        L.append("- **Nothing found**: no candidate effect passed the decision rule on held-out data.")
    amb = [e for e in rep["rejected"] if e["status"] == "ambiguous"]
    for e in amb:
        L.append(f"- ambiguous: {e['effect']} on {e['joint']} — {e.get('reason', '')}")
    L += _physics_lines(rep.get("physics"), U)
    L.append("")
    L.append("## Before and after (held-out)")
    ext = rep.get("extended", {})
    L += _metric_rows(rep["baseline"], ext if findings else None, U)
    # the power's interval resamples the held-out samples of one fitted model; a refit lands in another optimum
    # whose power differs beyond it (docs/DIAGNOSIS.md), so a small power is no evidence by itself, and the
    # decisions never use it
    L.append("\nThe unexplained power's interval is over held-out samples for these fitted models only; fits from "
             "another minibatch order land elsewhere (in clean simulated worlds up to about 1 % of the input power, "
             "its interval excluding 0 in two of five), so a value of that size is no evidence by itself (the "
             "decisions above do not use it).")
    if findings and ext.get("heldout_gain") is not None:
        L.append("")
        L.append(f"Extended model ({', '.join(ext.get('terms', []))}) held-out gain: {_fmt(ext['heldout_gain'], 3)} "
                 f"({U})², 95% CI {_fmt(ext.get('heldout_gain_ci'), 3)}; relative {_fmt(ext.get('relative_gain'), 3)}"
                 + (f" ({ext['model']})." if ext.get("model") else "."))
        if (pl := ext.get("heldout_gain_pooled")) and ext.get("heldout_gain_combination", "pooled") != "pooled":
            L.append(f"- that gain combines the {ext['heldout_gain_combination']} as the confirmation did; pooled over "
                     f"the samples: {_fmt(pl['gain'], 3)} CI {_fmt(pl['ci'], 3)}")
        cf = ext.get("confirmation")
        if cf:
            L.append(f"- confirmed against {cf['against']}: {_fmt(cf['gain'], 3)} ({U})², "
                     f"{100 * cf['level']:.1f}% CI {_fmt(cf['ci'], 3)} ({cf['scale']}"
                     + (f"; {cf['combination']}, pooled {_fmt(cf['pooled']['gain'], 3)} CI {_fmt(cf['pooled']['ci'], 3)}"
                        if cf.get("combination", "pooled") != "pooled" else "")
                     + (f"; its noise: {cf['noise']}" if cf.get("noise") else "") + ")")
        for k, v in (ext.get("rollout_gain") or {}).items():
            L.append(f"- rollout {k} reduction: {_fmt(v['gain'], 3)} CI {_fmt(v['ci'], 3)}")
    nf = rep["baseline"].get("noise_floor")
    if nf:
        L.append(f"\nRefit noise σ_r (RMS held-out difference of {len(nf.get('twin_differences', [])) or 1} twin refits "
                 f"from the reference, {nf.get('scale', 'unweighted')}): {_fmt(nf.get('sigma'), 3)} ({U})²; "
                 f"first twin {_fmt(nf['gain'], 3)} CI {_fmt(nf['ci'], 3)}.")
    plots = rep.get("plots", {})
    L.append("")
    L.append("## Plots")
    for key, title in (("residual_vs_velocity", "Residual vs velocity per joint"),
                       ("ccf", "Residual cross-correlations with 95% bands"),
                       ("rollouts", "Rollout error vs horizon, before and after"),
                       ("gains", "Held-out gain of every fitted candidate")):
        if key in plots:
            L.append(f"### {title}\n\n![{title}]({plots[key]})\n")
    L.append("## Residuals of the base model (held-out)")
    L.append("| joint | rms | Ljung-Box p (lag 10) | block length | strongest cross-correlation |")
    L.append("|---|---|---|---|---|")
    for j, r in rep.get("residuals", {}).items():
        lb = r["ljung_box"].get("lag10", {}).get("p")
        best = max(r["ccf"].items(), key=lambda kv: abs(kv[1]["peak"])) if r["ccf"] else None
        bs = f"{best[0]} {best[1]['peak']:.2f} at lag {best[1]['peak_lag']} (band ±{best[1]['band']:.2f})" if best else "—"
        L.append(f"| {j} | {_fmt(r['rms'])} | {_fmt(lb, 3)} | {r['block_length']} | {bs} |")
    L.append("")
    L.append("## Every candidate")
    L.append("| effect | joint | subjects | status | estimate | 95% CI | unit | held-out gain [CI] | reason |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for e in findings + rep["rejected"]:
        sf = e.get("subject_form") or {}
        who = ", ".join(e["subjects"]) if sf.get("subjects") else ("all, own sizes" if sf.get("kind") == "sizes" else "all")
        L.append(f"| {e['effect']} | {e['joint']} | {who} | {e['status']} | {_fmt(e.get('estimate'))} | {_fmt(e.get('ci'), 3)} | "
                 f"{e.get('unit', '')} | {_fmt(e.get('heldout_gain'), 3)} {_fmt(e.get('heldout_gain_ci'), 3)} | "
                 f"{e.get('reason', '')} |")
    L.append("")
    L += _limit_lines(rep.get("detection_limits") or {})
    L.append("## How it was decided")
    L.append(RULE_TEXT)
    L.append("")
    L.append("## Candidate library")
    L.append(library_table())
    L.append("")
    return "\n".join(L)
