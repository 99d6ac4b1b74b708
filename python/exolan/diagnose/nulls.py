"""Rule 3's nulls for exo-driven terms (the same term on the exo torque taken from the future; a gain also at the
controller's tracking lag and on its own variation), and rule 6 for an exo-driven rival that failed its null."""
from __future__ import annotations

import copy

import numpy as np
import torch

from . import compensate, stats
from .candidates import LIBRARY, rivals
from .export import extend
from .fit import predict
from .flat import Flat, exo_own
from .refits import held_errors, refit
from .rules import gci, own_variation_passes, paired_gain
from .settings import Settings
from .subjects import gated, with_init


def advanced(flat: Flat, k: np.ndarray) -> Flat:
    """The same data with the exo torque of joint j taken k[j] samples in the *future* (clamped at the end).

    The future exo torque cannot act on the limb now, but an assistive controller makes it a copy of the
    human torque now: a term that explains held-out data as well from the future exo torque as from the
    present one exploits that correlation, not physics.
    """
    f = copy.copy(flat)
    f.tau_e, f.tau_e_d, f.tau_e_dd = flat.tau_e.clone(), flat.tau_e_d.clone(), flat.tau_e_dd.clone()
    start = 0
    for T in flat.lengths:
        t = np.arange(T)
        for j in range(flat.n):
            src = torch.as_tensor(start + np.minimum(t + int(k[j]), T - 1))
            for name in ("tau_e", "tau_e_d", "tau_e_dd"):
                getattr(f, name)[start:start + T, j] = getattr(flat, name)[src, j]
        start += T
    return f


def future_null(base, flat: Flat, entry: dict, j: int, lag: int, s: Settings):
    """Rule 3's null for an exo-driven term: the same term, unfitted, on the exo torque of joint j taken `lag`
    samples in the future; (model, advanced data, what, text).

    A delay d on the advanced torque applies τ_e(t + lag − d): the null's delay is held at d ≤ lag, so it reaches
    the present or future torque only. Free up to max_delay it could apply a causal delay of up to max_delay − lag
    (20 ms for a null 80 ms ahead), which is the effect under test, not a null."""
    effect = entry["effect"]
    k = np.zeros(flat.n, dtype=int)
    k[j] = lag
    adv = advanced(flat, k)
    max_delay = min(s.max_delay, lag * flat.dt) if LIBRARY[effect].bounded_by_max_delay else s.max_delay
    init = gated(LIBRARY[effect].screen_init(entry.get("screen", {})), entry.get("form"), effect, j)
    null = extend(base, adv, [(effect, j)], init=init, max_delay=max_delay)
    return null, adv, dict(future_lag_s=float(lag * flat.dt)), f"exo torque {lag} samples in the future"


def future_peak(x: torch.Tensor, tau_e: torch.Tensor, min_lag: int, max_lag: int) -> int:
    """Future lag (samples, min_lag..max_lag) of the exo torque at which |ccf(x, τ_e)| peaks."""
    cc = stats.cross_correlation(x.numpy().astype(np.float64), tau_e.numpy().astype(np.float64), max_lag)
    lags = np.asarray(cc["lags"]); vals = np.abs(np.asarray(cc["ccf"]))
    sel = lags <= -min_lag          # negative lag: the exo torque *after* the sample of x
    return int(-lags[sel][np.argmax(vals[sel])]) if sel.any() else min_lag


# a future null's nearest lag (samples): a torque taken a sample or two ahead is nearly the present one, a null
# that a real term cannot beat either (measured: docs/DIAGNOSIS.md, "Noise above the fit's band", hip gain 9410)
MIN_FUTURE_LAG = 5


def leak_lag(model, flat: Flat, j: int, min_lag: int = MIN_FUTURE_LAG, max_lag: int = 40) -> int:
    """Future lag (samples) at which the exo torque of joint j correlates most with the training residual."""
    tr = flat.index("train")[:40000]
    r = flat.tau[tr, j] - predict(model, flat, tr)[:, j]
    return future_peak(r, flat.tau_e[tr, j], min_lag, max_lag)


def track_lag(flat: Flat, j: int, min_lag: int = MIN_FUTURE_LAG, max_lag: int = 40) -> int:
    """Future lag (samples, min_lag..max_lag) at which the exo torque of joint j copies the recorded joint torque
    best: the assistive controller's tracking lag. A lag-free term on the exo torque (a gain) that only rescales
    the joint's own torque does as well from the exo torque taken there. No nearer than the residual's null
    (`leak_lag`), for the same reason (`MIN_FUTURE_LAG`)."""
    tr = flat.index("train")[:40000]
    return future_peak(flat.tau[tr, j], flat.tau_e[tr, j], min_lag, max_lag)


def on_own_variation(base, flat: Flat, j: int, init: dict, e_ref: np.ndarray, held: torch.Tensor,
                     w_held: np.ndarray | None, s: Settings, refit_fn=refit) -> tuple[dict, float]:
    """Rule 3's own-variation test of a torque gain on joint j: the term refitted (warm, from `base`) on the
    controller's own variation alone (`flat.exo_own`); its paired held-out gain over the errors `e_ref` and its k.
    One home for the data's test and the injection's (`limits_by_injection`), which must run the same test."""
    own = exo_own(flat, j)
    alone = extend(base, own, [("torque_gain", j)], init=init, max_delay=s.max_delay)
    refit_fn(alone, own, s)
    return paired_gain(e_ref, held_errors(alone, own, held, w_held)[1], s), alone.estimate("torque_gain", j)


def rejected_by_its_null_alone(e: dict) -> bool:
    """An exo-driven candidate that passed rules 1, 2, 4 and 5 and failed only rule 3's null."""
    return bool(e.get("status") == "rejected" and e.get("passes_gain") and e.get("passes_floor") and
                e.get("identifiable") and e.get("passes_invariance") and e.get("passes_null") is False)


def outdone_by_a_doubted_rival(results: list[dict], errors, compare) -> None:
    """Rule 6 for rivals of which one fails its null: reject an exo-driven term whose exo-driven rival on the same
    joint (gain/strap, delay/strap) describes the held-out data better but was rejected by its null alone.

    Both terms say the same thing: the exo torque acts on the limb otherwise than recorded. The rival's null says
    that its (larger) part of that signal cannot be told from model error that tracks the joint torque (the future
    exo torque explains it as well), or, for a gain, does not show in the controller's own variation. A term that
    takes a smaller part of the same signal is no better evidence for its own form: accepting it would name an
    effect the better description has just failed to support (measured: docs/DIAGNOSIS.md, "Measurements behind the
    code"). Pairs with a term that is not exo-driven (delay/damping) are left alone: a delay failing its null
    supports a damping rather than casting doubt on it.

    `errors(effect, joint)`: the candidate's held-out decision errors (None if it was not fitted);
    `compare(e_ref, e_new)`: the paired held-out gain of e_new over e_ref (`paired_gain`). Mutates `results`.
    """
    for entry in results:
        if entry.get("status") is not None or not entry.get("passes") or not LIBRARY[entry["effect"]].needs_exo:
            continue
        mine = errors(entry["effect"], entry["joint"])
        for rv in rivals(entry["effect"]):
            other = next((e for e in results if e["effect"] == rv and e["joint"] == entry["joint"]), None)
            if other is None or not LIBRARY[rv].needs_exo or not rejected_by_its_null_alone(other):
                continue
            theirs = errors(rv, entry["joint"])
            if mine is None or theirs is None:
                continue
            d = compare(mine, theirs)           # > 0: the rival describes the held-out data better
            if d["ci"][0] <= 0:
                continue
            entry["rivals"] = {**entry.get("rivals", {}), rv: dict(advantage=-d["gain"], ci=[-d["ci"][1], -d["ci"][0]])}
            entry["passes"] = False
            entry["status"] = "rejected"
            entry["reason"] = (f"its rival {rv} on this joint describes the held-out data better (by {gci(d)}) but "
                               f"failed its null (rule 3): the signal both describe is not shown to be the exo "
                               f"torque's, so the weaker description is not taken in its place")
            break


def failed_text(null: dict) -> str:
    """Why a term failed the hardest of its nulls (`judge`'s `null_gain`), in words."""
    if null.get("own_variation_only"):
        return ("the same term on the controller's own variation alone (the exo torque less its copy of the joint "
                "torque) does not beat the reference beyond the refit noise: a real gain rescales that variation too")
    return "no better than the same term on future exo torque (assistive torque tracks the human torque)"


def run_nulls(ss, results: list) -> None:
    """Rule 3 for every exo-driven candidate that passes so far: the same term fitted on the exo torque taken from
    the future (at the lag where it correlates most with the residual; a lag-free gain also where the exo torque
    copies the joint torque best), and a gain on the controller's own variation alone. The hardest null decides.
    The candidates side by side (`Session.workers`)."""
    todo = [e for e in results if "status" not in e and LIBRARY[e["effect"]].needs_exo
            and e.get("passes_floor") and e.get("identifiable")]
    ss.workers.map([lambda e=e: nulls_of(ss, e) for e in todo])


def nulls_of(ss, entry: dict) -> None:
    """`run_nulls` for one candidate: its nulls and `passes_null` on its entry."""
    j = ss.flat.joints.index(entry["joint"])
    judged = judge(ss, entry, j, ss.base, ss.flat, ss.ref, ss.fitted[(entry["effect"], j)][1], ss.e_ref,
                   entry["estimate"])
    entry["nulls"] = judged["nulls"]
    entry["null_gain"] = judged["null_gain"]
    entry["passes_null"] = judged["passes"]


def judge(ss, entry: dict, j: int, base, data: Flat, resid_model, e_term: np.ndarray, e_ref: np.ndarray,
          k_term: float, what: str = "") -> dict:
    """Rule 3 for the exo-driven term of `entry` on joint j, on `data` with `base` as its base: the term's held-out
    errors `e_term` against the same term fitted on the exo torque from the future (at the lag where the exo torque
    correlates most with the residual of `resid_model`; a lag-free gain also at the controller's tracking lag), and
    a gain on the controller's own variation alone against `e_ref` (the base's). Returns {nulls, null_gain, passes}:
    the hardest null decides."""
    s, c = ss.s, LIBRARY[entry["effect"]]
    lags = [leak_lag(resid_model, data, j)]
    if c.lag_free:
        # a gain has no lag of its own: its null also takes the exo torque where it copies the joint torque
        # best (a clean world's knee "gain" beat the residual-chosen null; docs/DIAGNOSIS.md)
        lags = sorted({lags[0], track_lag(data, j)})
    nulls = []
    for null, adv, lag_s, text in [future_null(base, data, entry, j, lag, s) for lag in lags]:
        refit(null, adv, s)
        gn = ss.gain(ss.errors(null, adv)[1], e_term)
        nulls.append(dict(gain=gn["gain"], ci=gn["ci"], passes=bool(gn["ci"][0] > 0), **lag_s))
        ss.log(f"null {entry['effect']} {entry['joint']}{what}: beats the same term on {text} by {gci(gn)}")
    if c.lag_free:
        # ... and it must show in the controller's own variation (the exo torque less its copy of the joint
        # torque): the same term on that variation alone must beat the reference beyond the refit noise (a
        # term that soaks up model error correlated with the joint torque finds nothing there)
        init = gated(c.screen_init(entry.get("screen", {})), entry.get("form"), c.effect, j)
        gn, k_own = on_own_variation(base, data, j, init, e_ref, ss.held, ss.w_held, s)
        nulls.append(dict(gain=gn["gain"], ci=gn["ci"], own_variation_only=True, estimate=k_own,
                          passes=own_variation_passes(gn, ss.sigma_r, k_own, k_term)))
        ss.log(f"null {entry['effect']} {entry['joint']}{what}: the same term on the controller's own variation "
               f"alone (k {k_own:.3g}) beats the reference by {gci(gn)}")
    return dict(nulls=nulls, null_gain=min(nulls, key=lambda x: (x["passes"], x["ci"][0])),
                passes=all(x["passes"] for x in nulls))


def on_top(ss, entry: dict, j: int, sel_given: tuple, cur, sc: dict) -> dict:
    """Rule 3 for an exo-driven term tested on top of given terms: the nulls of `judge` where the term is added,
    not only where it stood alone. `sel_given`: (the given terms, their `init`); `cur`: the model fitted with them;
    `sc`: the term's screen on `cur`. The given terms are taken out of the data at `cur`'s sizes
    (`compensate.data`), the networks are `cur`'s, and the term and its nulls are each refitted warm there. Alone,
    a term competes with the others for one signal and so do its nulls; on top of them it may take only what they
    leave over, and that is where it must beat its nulls."""
    given, sizes = sel_given
    fitted = cur.physical()
    for eff, jj in given:
        shape = LIBRARY[eff].shape
        sizes = with_init(sizes, {eff: cur.estimate(eff, jj), **({shape: float(fitted[shape][jj])} if shape else {})},
                          jj)
    sizes = {**sizes, **cur.subject_init()}         # the switches and per-subject sizes as fitted too
    comp = compensate.data(ss.flat, given, sizes, ss.s.max_delay)
    c, base = LIBRARY[entry["effect"]], cur.base
    entry = dict(effect=entry["effect"], joint=entry["joint"], form=entry.get("form"), screen=sc)
    term = extend(base, comp, [(c.effect, j)], max_delay=ss.s.max_delay,
                  init=gated(with_init({}, c.screen_init(sc), j), entry.get("form"), c.effect, j))
    refit(term, comp, ss.s)
    return judge(ss, entry, j, base, comp, term, ss.errors(term, comp)[1], ss.errors(base, comp)[1],
                 term.estimate(c.effect, j),
                 what=" on top of " + ", ".join(f"{e}:{ss.flat.joints[jj]}" for e, jj in given))
