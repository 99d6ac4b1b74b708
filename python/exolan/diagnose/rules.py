"""The decision rules of the learned path on held-out errors: the paired gain (rule 1), beyond the refit noise
(rule 2), a property of the joint and not of a task (rule 5), the tasks' gains combined (`balanced`), the
extended model's confirmation (`confirm`) and its reported gain (`gain_as_confirmed`), a term's own share of its
fit (`term_share`). Pure functions of arrays and `Settings`: no fitting here. The levels they run at come from
`settings.Budget`."""
from __future__ import annotations

import math

import numpy as np
from scipy import stats as scipy_stats

from . import stats
from .consistency import pooled
from .inference import cochran_q
from .settings import Settings


def gci(g: dict) -> str:
    """"gain [lo, hi]" of a `paired_gain` (or screen) result, for the log and the reasons."""
    return f"{g['gain']:.3g} [{g['ci'][0]:.3g}, {g['ci'][1]:.3g}]"


def paired_gain(e_ref: np.ndarray, e_new: np.ndarray, s: Settings, seed: int = 0, alpha: float = 0.05) -> dict:
    d = e_ref - e_new
    b = stats.bootstrap_mean(d, n_boot=s.n_boot, seed=seed, draws=True, alpha=alpha)
    rel = stats.bootstrap_mean(d, n_boot=s.n_boot, seed=seed, ratio_to=e_ref, block=b["block"], alpha=alpha)
    return dict(gain=b["mean"], ci=b["ci"], se=b["se"], block=b["block"], rel=rel["mean"], rel_ci=rel["ci"],
                draws=b.get("draws"))


def above_noise(g: dict, sigma_r: float, seed: int = 0, alpha: float = 0.05) -> bool:
    """Rule 2: the gain's lower confidence bound (two-sided level 1 − alpha, 95 % by default), with the refit
    noise added to its sampling error, is above 0.

    The gain's error is the sum of two independent ones: the sampling error of the held-out samples (the
    block bootstrap's replicates, `g["draws"]`) and the refit noise N(0, σ_r²). The bound is the 2.5 %
    quantile of the replicates each plus a normal draw of the refit noise: rule 1's percentile bound when
    σ_r → 0, and gain − 1.96 σ_r when the refit noise dominates. Not gain − 1.96 √(SE² + σ_r²): a gain that
    one task's large misfit carries is right-skewed, its percentile bound lies above that normal one, and
    the normal bound rejected what rule 1 accepted although σ_r was a twelfth of the SE (measured:
    docs/DIAGNOSIS.md, "Measurements behind the code").
    """
    draws = g.get("draws")
    if draws is None:       # no held-out samples (`stats.bootstrap_mean` returns no replicates): no evidence
        return False
    noise = np.random.default_rng(seed).normal(0.0, sigma_r, size=len(draws))
    return bool(np.quantile(draws + noise, alpha / 2) > 0)


def own_variation_passes(g: dict, sigma_r: float, k_own: float, k_term: float) -> bool:
    """Rule 3's own-variation null for a torque gain: the same term fitted on the controller's own variation
    alone (`flat.exo_own`) beats the reference beyond the refit noise (rule 2), *and* its gain lies on the same
    side of 1 as the whole term's. A sensor that over-reports (k > 1) does so on all of its torque; own
    variation that asks for k < 1 while the whole term asks for k > 1 says that the term soaks up something
    else (measured: docs/DIAGNOSIS.md, "Measurements behind the code")."""
    return bool(g["ci"][0] > 0 and above_noise(g, sigma_r) and (k_own - 1.0) * (k_term - 1.0) > 0)


def user_improves(e_before: np.ndarray, e_after: np.ndarray) -> bool:
    """The user's (unweighted) held-out torque error is lower on average: rule 1's second condition, also
    asked of a term on top of others."""
    return bool(np.mean(np.asarray(e_before) - np.asarray(e_after)) > 0)


def user_grows(gains_by_seed, alpha: float) -> dict:
    """Rule 1's second condition (the user's unweighted error must not grow) over K paired fits from scratch:
    it grows only where the seeds' mean user gain lies below 0 beyond their spread, mean + t(K − 1, 1 − α) SD/√K
    < 0 (one-sided). The user's error is pooled over samples, so each seed's follows the optimum it lands in on
    the worst-fitted task: its paired gains scatter ten times more than the decision's (docs/DIAGNOSIS.md,
    "`secondlook`"), and the sign at one seed says nothing. One seed: its sign."""
    g = np.asarray(gains_by_seed, np.float64)
    K, mean = len(g), float(g.mean())
    if K < 2:
        return dict(gain=mean, bound=mean, grows=bool(mean <= 0), seeds=K)
    bound = mean + float(scipy_stats.t.ppf(1 - alpha, K - 1)) * float(g.std(ddof=1)) / math.sqrt(K)
    return dict(gain=mean, bound=bound, grows=bool(bound < 0), seeds=K)


def user_grows_beyond_noise(e_before: np.ndarray, e_after: np.ndarray, sigma_u: float, alpha: float) -> dict:
    """Rule 1's second condition for one pair of fits from scratch: the user's error grows only where its mean
    gain lies below 0 beyond the noise between optima on the user's scale σ_u (`FitCache.user_noise`), gain +
    z(1 − α) σ_u < 0 (one-sided, as `user_grows` over seeds). The decision's gain of the same pair is judged
    beyond that noise (rule 2); the user's, pooled over samples, scatters more between optima, and one fit's
    sign sent a term found at every seed to the paired look (docs/DIAGNOSIS.md, "`secondlook`")."""
    gain = float(np.mean(np.asarray(e_before) - np.asarray(e_after)))
    bound = gain + float(scipy_stats.norm.ppf(1 - alpha)) * float(sigma_u)
    return dict(gain=gain, bound=bound, noise=float(sigma_u), grows=bool(bound < 0 if sigma_u > 0 else gain <= 0))


def group_gains(d: np.ndarray, groups: np.ndarray, s: Settings, twins: list | None = None) -> dict:
    """The held-out gain series d by group (task, or trial): each group's mean, its block-bootstrap SE, the
    twin refits' mean difference there (`twins`: per-sample held-out differences reference − twin, aligned
    with d) and the group's SD from both, √(SE² + mean twin difference²). Rule 5 and the extended model's
    confirmation (`balanced`) combine groups from these."""
    gain, se, sd, twin = {}, {}, {}, {}
    for g in (str(x) for x in np.unique(groups)):
        on = groups == g
        b = stats.bootstrap_mean(d[on], n_boot=max(s.n_boot // 2, 100), seed=s.seed)
        # every twin refit's mean held-out difference per group: the refit noise of a group, and of any
        # weighted combination of groups, is the RMS over the twins
        twin[g] = np.array([t[on].mean() for t in twins] if twins else [0.0])
        gain[g], se[g] = float(b["mean"]), float(b["se"])
        sd[g] = math.sqrt(se[g] ** 2 + float(np.mean(twin[g] ** 2)))
    return dict(gain=gain, se=se, sd=sd, twin=twin)


def balanced(gg: dict, names: list[str], alpha: float = 0.05) -> dict:
    """The gains of the groups `names` (of a `group_gains`) combined with weights 1/SD: the weighted z-test
    of Stouffer, in which every group's z-score counts alike. Its SE from the groups' block-bootstrap SEs
    (independent groups), its refit noise from the twins' differences in the same combination (the twins
    are shared by the groups), the interval normal at level 1 − alpha, and `above_noise` as rule 2:
    gain − z √(SE² + σ²) > 0.

    Not the pooled mean, which the noisiest group dominates; and not inverse-variance weights (a fixed-effect
    meta-analysis), which assume one gain shared by every group: a real effect's gain differs between tasks, and the
    group measured most precisely is the most stereotyped motion, where a flexible conservative model absorbs the
    most of a dissipative term (a periodic orbit: along it almost any torque is a function of q). Measured:
    docs/DIAGNOSIS.md, "Measurements behind the code"."""
    w = np.array([1.0 / max(gg["sd"][g], 1e-300) for g in names])      # the floor: a noise-free group
    w /= w.sum()
    gain, se, ci, z = _weighted(gg, names, w, alpha)
    sigma = float(np.sqrt(np.mean((w @ np.array([gg["twin"][g] for g in names])) ** 2)))
    return dict(gain=gain, ci=ci, se=se, refit_sd=sigma,
                above_noise=bool(gain - z * math.sqrt(se ** 2 + sigma ** 2) > 0),
                weights={g: float(v) for g, v in zip(names, w)})


def _weighted(gg: dict, names: list[str], w: np.ndarray, alpha: float) -> tuple[float, float, list, float]:
    """The groups' gains combined with weights w (independent groups): (gain, SE, normal interval at 1 − alpha, z)."""
    gain = float(w @ np.array([gg["gain"][g] for g in names]))
    se = float(math.sqrt(np.sum(np.square(w * np.array([gg["se"][g] for g in names])))))
    z = float(scipy_stats.norm.ppf(1 - alpha / 2))
    return gain, se, [gain - z * se, gain + z * se], z


def invariance_rule(d: np.ndarray, groups: np.ndarray, kind: str, s: Settings, by_group=None, neutral: float = 0.0,
            twins: list | None = None, param_path: bool = True, family: int = 1, positive: bool = False) -> dict:
    """Rule 5: the held-out gain per group, and whether the evidence holds beyond the groups where it is largest.

    The quarter of the groups (≥ 1) with the largest gain is set aside. The rule passes by the *gain path* when
    the rest still show a gain: their groups' gains combined with weights 1/SD (each group's SD from its
    block-bootstrap SE and refit noise: a weighted Stouffer test, every group's z-score counts alike), and, as in
    rule 2, gain − 1.96 √(SE² + σ²) > 0 with σ the twin refits' RMS difference in the same combination; and,
    given `by_group` (name → mask over the held-out samples → `param_by_group`), the rest must identify the
    parameter on their own (θ_rest's CI excludes the no-effect value). It passes by the
    *parameter path* when the rest identify the parameter on their own and every group shows it: the groups
    agree (Cochran's Q of the per-group θ, HAC SEs, p > 0.05), or, where they differ, a new group would still
    show it: the θ pooled by a random-effects model, the 95 % prediction interval for a new group on the
    physical side of no effect (`consistency.pooled`, the recordings' check; `positive`: only θ above `neutral`
    is physical; three groups or more). Exact agreement alone asks too much: with this much data Q rejects any
    difference of the base's bias between tasks, also beside a real effect (a knee delay of 30 ms fitted at
    26-35 ms in six tasks, Q's p 0.03: docs/DIAGNOSIS.md, "Rule 5 asks for a new task"). The parameter test is
    the more sensitive one for a small effect: it asks only for the direction the residual wants, while a gain
    has to beat a refit's noise; a term that lives on some tasks' misfit wants a different θ in each task, on
    either side of no effect. The rest's gain must still point the right way (mean above 0): where a flexible
    model already represents a stereotyped motion's pseudo-dissipation (walking) the parameter step agrees with
    anything while the gain stays at 0 or below (measured: docs/DIAGNOSIS.md, "Measurements behind the code").

    Identified by the rest means θ_rest's interval at the family-wise 95 % level excludes the no-effect value:
    `family` is the number of (effect, joint) candidates the run considers, Bonferroni, two-sided (z = 2.96 for
    16). Every candidate gets this chance to look identified in the rest, and the rest's θ is a one-step
    estimate whose HAC SE holds the networks fixed.

    `param_path=False` (the caller's choice for velocity-driven terms) reports θ per group but decides by
    the gain alone: friction acts wherever the joint moves, so a real one shows a gain in walking as much
    as in calisthenics, while an exo-driven term's excitation (the exo torque's rate) is task-dependent and
    vanishes where the actuator saturates (DIAGNOSIS_PITFALLS.md).

    And a property of the joint makes no group worse: a group whose gain lies below 0 by more than its
    sampling and refit uncertainty (block-bootstrap SE and the twin refits' RMS difference on that group;
    `twins`: the per-sample held-out differences reference − twin, aligned with `d`), at a Bonferroni-corrected 95% over the groups, fails the rule. A term that soaks up the
    misfit of some tasks typically costs accuracy on others.
    """
    labels = [str(g) for g in np.unique(groups)]
    out = dict(by=kind, groups={g: float(d[groups == g].mean()) for g in labels})
    if kind == "none" or len(labels) < 2:
        out.update(passes=True, note="a single recording: task invariance not testable")
        return out
    gg = group_gains(d, groups, s, twins)
    per, sd = gg["gain"], gg["sd"]
    z = float(scipy_stats.norm.ppf(1 - 0.025 / len(labels)))
    hurt = [g for g in labels if per[g] + z * sd[g] < 0]
    out.update(group_sd=sd, hurt=hurt)
    k = max(1, int(math.ceil(len(labels) / 4)))
    top = sorted(per, key=lambda g: -per[g])[:k]
    in_top = np.isin(groups, top)
    # the rest's gain: the groups' gains combined with weights 1/SD (`balanced`, why there)
    rest = [g for g in labels if g not in top]
    b = balanced(gg, rest)
    out.update(dropped=top, gain_rest=b["gain"], ci_rest=b["ci"], refit_sd_rest=b["refit_sd"],
               rest_weights=b["weights"], passes=b["above_noise"])
    if by_group is not None:
        pg = by_group({"rest": ~in_top, **{g: groups == g for g in labels}})
        have = [g for g in labels if g in pg]
        if "rest" in pg and len(have) >= 2:
            rest = pg["rest"]
            th, se_g = np.array([pg[g]["estimate"] for g in have]), np.array([pg[g]["se"] for g in have])
            Q, p_het = cochran_q(th, se_g)
            new_group = pooled(th, se_g, "greater" if positive else "two-sided", neutral)
            lo, hi = rest["estimate"] - 1.96 * rest["se"], rest["estimate"] + 1.96 * rest["se"]
            z_id = float(scipy_stats.norm.ppf(1 - 0.025 / max(family, 1)))
            z_rest = float(abs(rest["estimate"] - neutral) / rest["se"])
            identified = bool(z_rest > z_id)
            every = p_het > 0.05 or bool(new_group["consistent"])
            consistent = bool(identified and every)
            out.update(theta_by_group={g: v for g, v in pg.items() if g != "rest"}, theta_rest=rest["estimate"],
                       theta_rest_ci=[lo, hi], theta_rest_z=z_rest,
                       identification_z=z_id, heterogeneity=dict(Q=Q, df=len(th) - 1, p=p_het),
                       new_group=new_group, consistent=consistent)
            out["rest_identifies"] = identified
            if out["passes"] and not identified:
                # the gain path asks for the parameter too: the rest's gain must come with a θ that they
                # identify on their own (rule 4 on the rest), or it is a flexible term's help, not this effect
                out["passes"] = False
                out["note"] = (f"without {', '.join(top)} the gain is above 0 but those {kind}s do not identify "
                               f"the parameter (θ {rest['estimate']:.3g} is {z_rest:.2g} SEs from its "
                               f"no-effect value, {z_id:.3g} needed for {family} candidates)")
            if param_path and consistent and not out["passes"] and out["gain_rest"] > 0:
                out["passes"] = True
                out["note"] = (f"without {', '.join(top)} the held-out gain is not significant, but the other "
                               f"{kind}s identify the parameter on their own and a new {kind} would show it")
    if hurt:
        out["passes"] = False
    return out


def invariance_reason(ti: dict) -> str:
    """Why rule 5 failed, in words."""
    if ti.get("hurt"):
        return (f"it makes {', '.join(ti['hurt'])} worse on held-out data (a property of the joint makes no "
                f"{ti['by']} worse)")
    why = (f"the gain rests on {', '.join(ti['dropped'])}: without it the held-out gain (the other {ti['by']}s "
           f"weighted by 1/SD) is {ti['gain_rest']:.3g} "
           f"[{ti['ci_rest'][0]:.3g}, {ti['ci_rest'][1]:.3g}] (a property of the joint helps in every {ti['by']})")
    if "theta_rest" in ti:
        why += (f"; there the parameter is {ti['theta_rest']:.3g} [{ti['theta_rest_ci'][0]:.3g}, "
                f"{ti['theta_rest_ci'][1]:.3g}], {ti['theta_rest_z']:.2g} SEs from its no-effect value "
                f"({'identified' if ti['rest_identifies'] else 'not identified'}: {ti['identification_z']:.3g} "
                f"needed, family-wise over the candidates)")
        ng = ti.get("new_group") or {}
        if ti["heterogeneity"]["p"] <= 0.05 and ng.get("consistent") is not None:
            why += (f", and the {ti['by']}s' estimates differ (Cochran Q p = {ti['heterogeneity']['p']:.2g}); a new "
                    f"{ti['by']}'s 95 % prediction interval from them (mean {ng['mean']:.3g}, spread between "
                    f"{ti['by']}s τ {ng['tau']:.3g}) is [{ng['prediction'][0]:.3g}, {ng['prediction'][1]:.3g}]"
                    f"{'' if ng['consistent'] else ', which holds no effect'}")
        else:
            why += (f", and the {ti['by']}s' estimates {'agree' if ti['heterogeneity']['p'] > 0.05 else 'differ'} "
                    f"(Cochran Q p = {ti['heterogeneity']['p']:.2g})")
    return why


def subject_gains(d: np.ndarray, subjects_of_held: np.ndarray, s: Settings) -> dict:
    """Held-out gain per subject with its block-bootstrap CI: who carries the evidence."""
    out = {}
    for subj in np.unique(subjects_of_held):
        b = stats.bootstrap_mean(d[subjects_of_held == subj], n_boot=max(s.n_boot // 2, 100), seed=s.seed)
        out[str(subj)] = dict(gain=b["mean"], ci=b["ci"])
    return out


def confirm(e_before: np.ndarray, e_after: np.ndarray, groups: np.ndarray, kind: str, s: Settings, alpha: float,
            twins: list | None = None, look: str = "") -> dict:
    """Rule 1 for a fit from scratch or the extended model: does `e_after` beat `e_before` on held-out data?
    (`look` names the caller's look, for the log and for tests' stubs; it changes nothing.)

    Given `twins` (the per-sample held-out differences that measure the noise of this comparison apart from the
    samples': twin refits of the reference, for a model that differs from it by its terms and one refit; or
    term-free fits from scratch at other seeds, `optimum_twins`, for a fit from scratch against the base so
    fitted) and held-out data in several groups (tasks, or trials of one task), the decision is on the groups'
    gains combined with weights 1/SD (`balanced`), as rule 5 combines them, beyond that noise as rule 2: a
    group where the twins differ much counts little. Without twins (a given model's warm refit) the pooled
    gain decides. Why a fit from scratch needs its own twins: term-free fits from scratch at other seeds beat the
    reference by as much as a real term does. Combined, not pooled, where the noise is measured: the pooled
    interval is set by the noisiest tasks (both measured: docs/DIAGNOSIS.md, "Measurements behind the code").
    The pooled gain stays in the record (`pooled`). A single group: the pooled gain, its block-bootstrap
    interval (and, given `twins`, rule 2's bound with their refit noise σ_r, the RMS of their mean differences)."""
    g = paired_gain(e_before, e_after, s, alpha=alpha)
    pooled = dict(gain=g["gain"], ci=g["ci"])
    if twins and kind != "none" and len(np.unique(groups)) >= 2:
        gg = group_gains(e_before - e_after, groups, s, twins)
        b = balanced(gg, list(gg["gain"]), alpha=alpha)
        return dict(gain=b["gain"], ci=b["ci"], level=1 - alpha, passes=b["above_noise"], pooled=pooled,
                    combination=f"{kind}s weighted 1/SD", weights=b["weights"], refit_sd=b["refit_sd"])
    sigma_r = float(np.sqrt(np.mean([t.mean() ** 2 for t in twins]))) if twins else 0.0
    passes = g["ci"][0] > 0 and (above_noise(g, sigma_r, alpha=alpha) if twins else True)
    return dict(gain=g["gain"], ci=g["ci"], level=1 - alpha, passes=bool(passes), pooled=pooled,
                combination="pooled", refit_sd=sigma_r)


def gain_as_confirmed(e_before: np.ndarray, e_after: np.ndarray, groups: np.ndarray, confirmation: dict, s: Settings,
                      alpha: float = 0.05) -> dict:
    """The gain of `e_after` over `e_before` (the user's errors, say) in the combination its `confirm` decided by:
    where the confirmation combined groups, their mean gains with the confirmation's weights, each group's
    block-bootstrap SE (independent groups, a normal interval at level 1 − alpha) and the relative gain over the
    base's error in the same combination (its interval the gain's over that error, whose own spread is left out);
    where it pooled, the pooled `paired_gain`. The pooled gain stays in `pooled`. One statistic for the claim and
    its interval: pooled beside a combined decision, the interval is set by the noisiest task and can hold 0 for a
    model the confirmation handed over (docs/DIAGNOSIS.md, "The extended model's reported gain, combined as its
    confirmation")."""
    g = paired_gain(e_before, e_after, s, alpha=alpha)
    pooled = dict(gain=g["gain"], ci=g["ci"], rel=g["rel"], rel_ci=g["rel_ci"])
    weights = confirmation.get("weights")
    if not weights:
        return dict(pooled, combination="pooled", pooled=pooled)
    names = list(weights)
    w = np.array([weights[n] for n in names])
    gain, _, ci, _ = _weighted(group_gains(np.asarray(e_before) - np.asarray(e_after), groups, s), names, w, alpha)
    base = float(w @ [np.mean(np.asarray(e_before)[groups == n]) for n in names])
    return dict(gain=gain, ci=ci, rel=gain / base, rel_ci=[c / base for c in ci],
                combination=confirmation["combination"], weights=dict(weights), pooled=pooled)


def term_share(e_off: np.ndarray, e_with: np.ndarray, sigma_r: float, s: Settings) -> dict:
    """Rule 2 for a term's own share of a gain: the held-out (decision) errors of a fitted model with its terms
    switched off (`ExtendedModel.without`) less those of the model itself — what the terms alone are worth to
    their fit — must clear the refit noise floor as a warm refit's gain must (`above_noise`, σ_r).

    Why: rule 2's floor is the size the data can show. A fit from scratch is judged paired over seeds
    (`paired_confirm`), whose noise is the spread of the paired gains: a term that steadily soaks up a small
    misfit of the base has a tiny spread, so a gain far inside the floor passed. Its own share is the size
    of the effect the term claims on these data; it is where an absorbed effect shows (the base took much of
    it, so the paired gain is small, but the term carries all of it) and where a misfit's echo does not
    (measured: docs/DIAGNOSIS.md, "Measurements behind the code").
    """
    g = paired_gain(e_off, e_with, s)
    return dict(gain=g["gain"], ci=g["ci"], passes_floor=above_noise(g, sigma_r), refit_noise=sigma_r)
