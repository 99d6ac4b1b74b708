"""The paired second look: ONE function (`second_look`) used by every caller (the rescue of a friction whose warm
refit failed, forward selection's test of a further term, the extended model's confirmation).

A fit from scratch lands in another optimum than the fit it is compared with; judged across seeds the noise of
two independent optima can exceed a term's gain. The second look fits the terms from scratch at `n_paired`
other seeds too and pairs each with the fit without the judged terms at the same seed (same minibatches and
recipe): the seeds' mean paired gain, beyond the spread of the paired gains, every seed above 0, the user's
error not growing beyond the seeds' spread, and, first, the judged terms' own share of their fit beyond the
refit noise floor. It is a look of the decision that calls it: its level is that decision's share of the budget
(`settings.Budget`)."""
from __future__ import annotations

import math
import time

import numpy as np

from .refits import other_seeds
from .rules import confirm, gci, user_grows
from .settings import Settings, log


def paired_confirm(pairs: list, groups: np.ndarray, kind: str, s: Settings, alpha: float) -> dict:
    """Rules 1 and 2 for a fit from scratch in a paired design over K minibatch seeds: `pairs` holds, per seed,
    the held-out (decision) errors of the term-free base and of the model with the terms, both fitted from
    scratch at that seed with the same recipe. The gain is the seeds' mean paired gain; its noise beside the
    samples' is the spread of the K paired gains, passed to `confirm` as twins (the deviations from their mean
    over √(K − 1), whose RMS of means is the SE of the seeds' mean, per task and in any combination); tasks are
    combined 1/SD as there, the bound normal at level 1 − alpha. And every seed's own gain (in the same
    combination) must lie above 0: the spread has K − 1 degrees of freedom (two with three seeds), so the normal
    bound alone would trust an SD that happened to come out small.

    Why paired: a term changes every gradient from the first step, so a fit with it and the term-free fit land
    in different optima; judged against term-free fits at other seeds (`optimum_twins`), the noise is that of
    two independent optima, while fits at the same seed share their minibatches, and their difference varies
    far less between seeds (measured: docs/DIAGNOSIS.md, "Measurements behind the code")."""
    K = len(pairs)
    D = np.array([np.asarray(f, np.float64) - np.asarray(t, np.float64) for f, t in pairs])
    e_free = np.mean([np.asarray(f, np.float64) for f, _ in pairs], axis=0)
    d_mean = D.mean(0)
    twins = [(Dk - d_mean) / math.sqrt(K - 1) for Dk in D] if K >= 2 else None
    g = confirm(e_free, e_free - d_mean, groups, kind, s, alpha, twins=twins)
    if "weights" in g:
        names = list(g["weights"])
        w = np.array([g["weights"][n] for n in names])
        by_seed = [float(w @ [Dk[groups == n].mean() for n in names]) for Dk in D]
    else:
        by_seed = [float(Dk.mean()) for Dk in D]
    every_seed = bool(all(v > 0 for v in by_seed))
    return dict(g, passes=bool(g["passes"] and every_seed), passes_bound=g["passes"], gain_by_seed=by_seed,
                seeds=K, design="paired over minibatch seeds", twins=twins, d=d_mean)


def paired_failures(pr: dict) -> list[str]:
    """Why a paired comparison over seeds (`paired_record` of `second_look`'s) failed, each condition in words."""
    by_seed = "by seed " + ", ".join(f"{v:.3g}" for v in pr["gain_by_seed"])
    user = pr["user"]
    return ([] if pr["passes_bound"] else [
        f"not beyond the spread of the paired gains over {pr['seeds']} seeds "
        f"({pr['noise_between_seeds']:.3g}; {by_seed})"]) + \
        ([] if min(pr["gain_by_seed"]) > 0 else [f"not every seed gains ({by_seed})"]) + \
        ([] if not user["grows"] else [
            f"the user's torque error grows beyond the seeds' spread (mean user gain {user['gain']:.3g}, one-sided "
            f"bound {user['bound']:.3g} over {user['seeds']} seeds)"]) + \
        ([] if pr["terms_share"]["passes_floor"] else [
            f"switched off, the terms cost their fit only {gci(pr['terms_share'])}: within the refit noise floor "
            "(an effect of this size cannot be told from a refit's noise in these data)"])


def paired_record(pr: dict) -> dict:
    """What the report keeps of a paired comparison over seeds (`run`'s `paired`)."""
    return dict(gain=pr["gain"], ci=pr["ci"], level=pr["level"], combination=pr["combination"], pooled=pr["pooled"],
                design=pr["design"], seeds=pr["seeds"], gain_by_seed=pr["gain_by_seed"],
                noise_between_seeds=pr.get("refit_sd"), above_noise=pr["passes"], passes_bound=pr["passes_bound"],
                terms_share=pr["terms_share"], user=pr["user"], user_gain_by_seed=pr["user_gain_by_seed"])


def second_look(ss, key: tuple, init: dict, first, first_errors: tuple, level: float, given: tuple = (),
                given_errors: tuple | None = None) -> dict:
    """The one paired second look. The terms `key` fitted from scratch: `first` at the reference's seed (its
    (user, decision) held-out errors `first_errors`), and at `Settings.n_paired` other seeds (made once per terms
    and recipe, `FitCache.at_seeds`), each paired with the fit of its seed without the judged terms (`key` less
    `given`), same recipe: the term-free base (`FitCache.free_at_seeds`), or the terms `given` so fitted
    (`given_errors`: their errors at the reference's seed). `ss` is the run's `session.Session`.

    First, needing no other fit: the judged terms' own share of `first` (`rules.term_share`) must clear the refit
    noise floor; where it does not, nothing more is fitted (`looked` False). Then `paired_confirm` at `level`
    (the calling decision's share of the budget), with the user's gain of `first` against its comparison (the
    fit handed over; the other seeds' fits are never handed over). `confirmed`: all of that passes. A look
    against the term-free base is kept per terms (`FitCache.paired`) for the extended model to reuse."""
    judged = tuple(k for k in key if k not in given)
    u_f, e_f = first_errors
    share = ss.own_share(first, judged, e_f)
    if not share["passes_floor"]:
        return dict(looked=False, confirmed=False, terms_share=share)
    t1 = time.time()
    conf = ss.cache.recipe(key)
    if given:
        u_0, e_0 = given_errors
        without = lambda: [ss.errors(m) for m in ss.cache.at_seeds(given, init, conf)]    # noqa: E731
    else:
        u_0, e_0, _ = ss.cache.optima(key)
        without = lambda: ss.cache.free_at_seeds(key, other_seeds(ss.s, ss.s.n_paired))  # noqa: E731
    # the fits with and without the judged terms side by side (`Session.workers`)
    others, with_terms = ss.workers.map([without, lambda: ss.cache.at_seeds(key, init, conf)])
    pairs, users, models = [(e_0, e_f)], [(u_0, u_f)], [first]
    for m_k, (u_k, e_k) in zip(with_terms, others, strict=True):
        u_t, e_t = ss.errors(m_k)
        pairs.append((e_k, e_t))
        users.append((u_k, u_t))
        models.append(m_k)
    out = ss.tools.paired_confirm(pairs, ss.groups, ss.group_kind, ss.s, level)
    out["terms_share"] = dict(share, pooled_by_seed=[share["gain"]] + [
        float(np.mean(ss.errors(m.without(judged))[1] - t)) for m, (_, t) in zip(models[1:], pairs[1:])])
    # the user's error must not grow (rule 1) beyond the spread of the seeds' paired user gains (`rules.user_grows`)
    out["user_gain_by_seed"] = [float(np.mean(a - b)) for a, b in users]
    out["user_gain"] = out["user_gain_by_seed"][0]
    out["user"] = user_grows(out["user_gain_by_seed"], ss.s.alpha)
    out["confirmed"] = bool(out["passes"] and not out["user"]["grows"] and out["terms_share"]["passes_floor"])
    out["models"], out["looked"] = models, True
    if not given:
        ss.cache.paired[key] = out
    log(ss.s, f"{[f'{a}:{ss.flat.joints[b]}' for a, b in key]} paired over {out['seeds']} seeds: {gci(out)} at "
              f"{100 * (1 - level):.2f} % ({'confirmed' if out['confirmed'] else 'not confirmed'}; "
              f"{time.time() - t1:.0f} s)")
    return out
