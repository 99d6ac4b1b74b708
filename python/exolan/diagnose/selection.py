"""Step 5 and 6 of the learned path: forward selection among the candidates that passed term by term, rivals
compared, a further term tested on top of the accepted ones (warm, then from scratch with its second look), at
Holm's level of the budget; and the effect that has no term (a payload), reported by rule."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .candidates import LIBRARY, NESTS, nested_choice, rivals
from .export import extend
from .nulls import failed_text
from .refits import refit
from .rules import gci, invariance_reason
from .screen import screen
from .secondlook import paired_record
from .subjects import gated, with_estimate, with_init
from .workers import Ahead


@dataclass
class Selection:
    accepted: list = field(default_factory=list)    # (effect, j) of the accepted terms, in order
    acc_init: dict = field(default_factory=dict)    # their starts (single-term estimates)
    given: list = field(default_factory=list)       # what a further term must add to: the accepted terms and the
    given_init: dict = field(default_factory=dict)  # better of each ambiguous set (the effect is there, its form open)


def forward(ss, results: list) -> Selection:
    """Take the candidate with the largest decision gain; a rival on its joint that held-out data cannot separate
    from it makes both ambiguous (or, nested, the simpler is taken); every remaining candidate must then add a
    gain on top of the accepted terms and of the better term of each ambiguous set."""
    pool = [e for e in results if e.get("passes") and e.get("status") is None]
    sel, ahead = Selection(), None
    while pool:
        pool.sort(key=lambda e: -e["rank"])
        top = pool.pop(0)
        j = ss.flat.joints.index(top["joint"])
        top = _settle(ss, top, pool, j, sel)
        sel.given.append((top["effect"], j))
        sel.given_init = with_estimate(sel.given_init, top, j)
        if ahead is None and ss.from_scratch and sel.accepted and sel.given == sel.accepted:
            ahead = _extended_ahead(ss, sel)
        if not pool:
            break
        # refit the given set once (the reference for the conditional tests), then each remaining one on top
        cur = extend(ss.base, ss.flat, sel.given, init=sel.given_init, max_delay=ss.s.max_delay)
        refit(cur, ss.flat, ss.s)
        ss.warm_fits[tuple(sorted(sel.given))] = cur
        cur_u, cur_e = ss.errors(cur)
        # each remaining one against the same given set: independent, side by side (the same bits in any order)
        adds = ss.workers.map([lambda e=e: further(ss, e, sel, cur, cur_u, cur_e) for e in pool])
        pool[:] = [e for e, a in zip(pool, adds) if a]
    if ahead is not None and ahead[0] != tuple(sorted(sel.accepted)):
        ahead[1].cancel()
        if ss.optima_ahead is not None and ss.cache.recipe(ahead[0]) != ss.cache.recipe(tuple(sorted(sel.accepted))):
            ss.optima_ahead.cancel()
    return sel


def _extended_ahead(ss, sel: Selection) -> tuple:
    """Step 7's fit from scratch of the terms accepted so far (`extended.joint_fit` asks the fits' cache for the
    same terms and starts), started while the selection tests the rest: most often nothing more is accepted, and
    the selection's lone warm refits leave a core free. Beside it, what that fit is judged against where the
    reference's refit with the terms held does not confirm them (`extended.confirm_model`'s from-scratch look):
    the term-free base fitted from scratch with the same recipe and its optimum twins (`FitCache.optima`), three
    fits that would otherwise start only after it, one at a time; started by the fit once it holds its permit (the
    fit is always wanted, they only where that look is made: they must not take its place), and kept on the
    session (`ss.optima_ahead`) for step 7 to cancel. The caches make each once, so the bits are the same.
    Returns (its terms, the fit's `workers.Ahead`)."""
    key, init = tuple(sorted(sel.accepted)), dict(sel.acc_init)

    def fresh():
        ss.optima_ahead = Ahead(ss.workers, lambda: ss.cache.optima(key))
        return ss.cache.fresh(key, init)
    return key, Ahead(ss.workers, fresh)


def _settle(ss, top, pool: list, j: int, sel: Selection):
    """Rule 6 for the top candidate and its rivals on joint j; accepts it, or marks a set ambiguous, or takes
    the simpler of a nested pair. Returns the term that stands for the set."""
    tie = []
    for rv in rivals(top["effect"]):
        other = next((e for e in pool if e["effect"] == rv and e["joint"] == top["joint"]), None)
        if other is None or (rv, j) not in ss.fitted:
            continue
        if top.get("rescued") or other.get("rescued"):
            # a fit from scratch is compared with one from scratch: both terms so fitted, same seed and recipe
            pair = ((top["effect"], j), (rv, j))
            e_top, e_rv = (ss.errors(ss.cache.fresh(((x["effect"], j),), with_estimate({}, x, j), recipe=pair))[1]
                           for x in (top, other))
        else:
            e_top, e_rv = ss.fitted[(top["effect"], j)][1], ss.fitted[(rv, j)][1]
        d = ss.gain(e_rv, e_top)   # > 0: top is better
        top.setdefault("rivals", {})[rv] = dict(advantage=d["gain"], ci=d["ci"])
        other.setdefault("rivals", {})[top["effect"]] = dict(advantage=-d["gain"], ci=[-d["ci"][1], -d["ci"][0]])
        if d["ci"][0] <= 0:
            tie.append(other)
    simple = nested_choice([top] + tie) if tie else None
    if simple is not None:
        # a nested pair (Stribeck reduces to Coulomb): the simpler term is taken, the other rejected
        for e in [top] + tie:
            if e is not simple:
                e.update(status="rejected", reason=f"reduces to {simple['effect']} as {NESTS[e['effect']][1]} and "
                                                   f"held-out data cannot separate the two: the simpler term is taken")
            if e in pool:
                pool.remove(e)
        top, tie = simple, []
    if tie:
        for e in [top] + tie:
            e.update(status="ambiguous",
                     reason="held-out data cannot separate " + " and ".join(x["effect"] for x in [top] + tie))
            if e in pool:
                pool.remove(e)
        # the better of the set stands in for it in the conditional tests: a term that only soaks up part of the
        # same signature must not be accepted in its place
    else:
        top.status = "accepted"
        sel.accepted.append((top["effect"], j))
        sel.acc_init = with_estimate(sel.acc_init, top, j)
    return top


def further(ss, e, sel: Selection, cur, cur_u, cur_e) -> bool:
    """Whether candidate e adds to the given terms (model `cur`, its errors `cur_u`, `cur_e`): warm (the new term
    starting where `cur`'s residual asks for it), beyond the refit noise, rule 5 and the user's error, at Holm's
    level for the next accepted term; then, where the base was fitted here, both models fitted from scratch
    beyond the noise between optima, or by the second look (the level split between those two looks)."""
    flat, s, jj = ss.flat, ss.s, ss.flat.joints.index(e["joint"])
    level = ss.budget.further(len(sel.accepted))
    # the new term starts where the current model's residual asks for it (the post-hoc screen on `cur`), not at
    # its single-term estimate, which already holds what the accepted terms now explain
    sc = screen(cur, flat, e["effect"], jj, n_boot=max(s.n_boot // 3, 100), seed=s.seed)
    start = LIBRARY[e["effect"]].screen_init(sc)
    init = gated(with_init(sel.given_init, start, jj), e.get("form"), e["effect"], jj)
    terms = sel.given + [(e["effect"], jj)]
    both = extend(ss.base, flat, terms, init=init, max_delay=s.max_delay)
    refit(both, flat, s)
    ss.warm_fits[tuple(sorted(terms))] = both
    u_both, e_both = ss.errors(both)
    g = ss.gain(cur_e, e_both)
    cg = dict(given=[f"{a}:{flat.joints[b]}" for a, b in sel.given], gain=g["gain"], ci=g["ci"], start=start,
              scale=ss.scale, user_gain=float(np.mean(cur_u - u_both)), level=1 - level)
    e.conditional_gain = cg
    ss.log(f"{e['effect']} {e['joint']} on top of {cg['given']}: gain {gci(g)}")
    inv = ss.invariance(cur_e - e_both, both, e["effect"], jj)
    cg["task_invariance"] = inv
    passes = ss.above_noise(g, alpha=level) and inv["passes"] and ss.tools.user_improves(cur_u, u_both)
    if passes and LIBRARY[e["effect"]].needs_exo:
        # rule 3 where the term is added: alone it had to beat its nulls in competition with the given terms
        on = ss.tools.nulls_on_top(ss, e, jj, (sel.given, sel.given_init), cur, sc)
        cg.update(nulls=on["nulls"], null_gain=on["null_gain"])
        if not on["passes"]:
            e.update(status="rejected", reason=f"on top of {', '.join(cg['given'])} it does not beat its null (rule 3: "
                     f"{failed_text(on['null_gain'])}; {gci(on['null_gain'])})")
            return False
    if passes and ss.from_scratch:
        passes, inv = _further_from_scratch(ss, e, sel, jj, init, level, inv)
    if passes:
        e.rank = g["gain"]     # rank the rest by what they add
        ss.fitted[(e["effect"], jj)] = (both, e_both)
        return True
    e.update(status="rejected", reason="adds nothing on held-out data once " + ", ".join(cg["given"]) + " is modelled"
             + ("" if inv["passes"] else f" ({invariance_reason(inv)})"))
    return False


def _further_from_scratch(ss, e, sel: Selection, jj: int, init: dict, level: float, inv: dict) -> tuple[bool, dict]:
    """A further term confirmed from scratch: the accepted terms' warm-started parameters are biased towards "no
    effect", and a term on the same joint can pass by soaking up what they leave over. Both models from scratch
    with the same recipe, beyond the noise between optima (`FitCache.optima`), the tasks combined, the user's
    error not growing beyond that noise on its own scale; where that fails with a positive gain, the second look
    (paired over seeds) on the same fits. Two looks, each at half the level."""
    n_looks = 2 if ss.s.rescue else 1
    k_cur, k_both = tuple(sorted(sel.given)), tuple(sorted(sel.given + [(e["effect"], jj)]))
    u_cur_f, e_cur_f = ss.errors(ss.cache.fresh(k_cur, init, recipe=k_both))
    both_f = ss.cache.fresh(k_both, init)
    u_both_f, e_both_f = ss.errors(both_f)
    tw = ss.cache.optima(k_both)[2]
    gf = ss.confirm(e_cur_f, e_both_f, level / n_looks, twins=tw, look="forward: cross-seed")
    invf = ss.invariance(e_cur_f - e_both_f, both_f, e["effect"], jj, twins=tw)
    user = ss.tools.user_grows_beyond_noise(u_cur_f, u_both_f, ss.cache.user_noise(k_both), ss.s.alpha)
    fs = dict(gain=gf["gain"], ci=gf["ci"], combination=gf["combination"], pooled=gf["pooled"],
              noise_between_optima=gf.get("refit_sd"), task_invariance=invf, user_gain=user["gain"], user=user,
              level=gf["level"])
    e.conditional_gain["from_scratch"] = fs
    ss.log(f"{e['effect']} {e['joint']} on top of {e.conditional_gain['given']}, both fitted from scratch: gain "
           f"{gci(gf)} ({gf['combination']}, beyond the noise between optima: {'passes' if gf['passes'] else 'fails'});"
           f" the user's gain {user['gain']:.3g} (noise between optima on its scale {user['noise']:.3g}: "
           f"{'below 0 beyond it' if user['grows'] else 'not below 0 beyond it'})")
    passes = gf["passes"] and invf["passes"] and not user["grows"]
    if not passes and n_looks == 2 and gf["gain"] > 0:
        pr = ss.second_look(k_both, init, both_f, (u_both_f, e_both_f), level / n_looks, given=k_cur,
                            given_errors=(u_cur_f, e_cur_f))
        share = pr["terms_share"]
        if pr["looked"]:
            invf = ss.invariance(pr["d"], both_f, e["effect"], jj, twins=pr["twins"])
            passes = pr["confirmed"] and invf["passes"]
        second = dict(terms_share=share) if not pr["looked"] else dict(
            paired_record(pr), user_gain=pr["user_gain"], task_invariance=invf)
        fs["paired"] = dict(second, passes=bool(passes))
        ss.log(f"{e['effect']} {e['joint']} on top of {e.conditional_gain['given']}: switched off, the term costs its "
               f"fit from scratch {gci(share)} (σ_r {ss.sigma_r:.3g})" + (
                   ": within the refit noise floor" if not pr["looked"] else
                   f"; paired over {pr['seeds']} seeds {gci(pr)} at {100 * pr['level']:.2f} % (by seed "
                   + ", ".join(f"{v:.3g}" for v in pr["gain_by_seed"]) + ")")
               + f": {'passes' if passes else 'fails'}")
    return passes, (invf if not invf["passes"] else inv)


def without_terms(ss, results: list) -> None:
    """Step 6: effects without a term: a payload changes H and V, which the model learns."""
    for j in ss.joint_ids:
        e = _blank(ss, LIBRARY["payload"], j)
        e.update(unit="kg", status="absorbable", reason="a mass on a segment changes H and V, which the model learns")
        results.append(e)


def _blank(ss, c, j: int):
    from .candidates import blank_entry

    return blank_entry(c.effect, j, ss.flat, ss.subjects)
