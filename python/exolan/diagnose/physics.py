"""The physics-first decision: forward selection of candidate terms on the parametric base (`ident`), one
family-wise significance budget, a held-out check, rivals, and the learned base's cross-check.

Rule, in plain words (the report states it):

1. Every candidate the data can test (effect x joint; exo-driven ones only with a recorded exo torque) is
   one member of the family; m is their number.
2. Forward selection: at step r every remaining candidate is fitted with the base and the terms accepted so far
   (weighted LS on the training segments, `ident.JointProblem`), and tested against "no effect" with its HAC
   interval (one-sided where only one sign is physical; a Stribeck friction's p is multiplied by its grid's size,
   since its Stribeck velocity is chosen on the data). With several subjects a linear candidate is also tested
   split by subject (an effect in at least one, Bonferroni over the subjects) and its p is twice the smaller of the
   two forms' (`_test`); the form taken enters the later fits. The smallest p is compared with Holm's threshold
   α/(m − r), α = 5 %: the family-wise level of every accept decision together is α. Where it fails, selection
   stops.
3. The held-out check can only remove a term: the model with it must beat the model without it on the held-out
   segments (paired squared errors against τ through the parallel filter, the band the fit is made in,
   block-bootstrap 95 % CI above 0). So can the recordings' check
   (`consistency`): fitted trial by trial, the term's 95 % prediction interval for a new recording must lie on the
   physical side of no effect — a constant of the joint, not a shape of the base's misfit. A term whose column is
   the exo torque (a gain) must also show on the controller's own variation (`own_variation`).
4. Rivals (delay/damping, Coulomb/Stribeck, delay/strap, gain/strap, Coulomb/backlash): an accepted term whose rival, put in its
   place, is significant there (same threshold), sized inside its physical domain with a finite interval (as an
   accepted term must be) and not worse on held-out data (CI of the difference reaching 0) is `ambiguous` with it
   — unless one reduces to the other (Stribeck to Coulomb): the simpler is taken. Where the learned base's
   residual shows only one of the two in their shared place (rule 5's objection to the other), that one is taken
   (`physics_checks.rivals`).
5. Cross-check: the same terms fitted on the learned base's residual (a constant and the terms only). Where
   the two intervals do not overlap, the finding reports both and its interval spans both: the data size the
   effect only up to that disagreement. Where the learned base's residual shows no effect at all (its 95 % interval
   reaches no effect: the span would hold none), or one of the
   other sign (a gain above 1 there below 1: the span holds no effect), the term is `ambiguous` (the parametric
   base may be what misses it).
6. The learned base's check (`physics_path.learned_check`): the learned base with the term held at its parametric
   size, its networks refitted as the reference's were, must not be worse on held-out data than without it (the
   paired gain's 95 % CI not wholly below 0): one accepted term against the reference, several by each one's own
   share (all held against all but this one: a term that mimics another accepted one passes alone by proxy).
   A base that predicts better can absorb a real effect (then it gains nothing, but loses nothing either); where
   holding the term costs it accuracy, the term carries what the parametric base's misfit put in it (an
   exo-driven column copies the joint torque, hence that misfit too), and it is `ambiguous`. A check that can
   only remove: no level is spent.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..runio import jsonable
from . import consistency, ident, parallel_filter, stats, wls
from .candidates import LIBRARY, NESTS, rivals
from .estimates import Z95, TermEstimate, ci_text as _ci_text, report_interval, term_estimate  # noqa: F401
from .flat import exo_own
from .workers import Workers, current


@dataclass
class PhysicsResult:
    """The physics-first identification: accepted terms per joint, every candidate's test, the base."""
    alpha: float
    family: int
    accepted: list = field(default_factory=list)          # [(effect, joint index)]
    estimates: dict = field(default_factory=dict)         # (effect, joint index) -> TermEstimate (final model)
    tests: list = field(default_factory=list)             # every test made, in order
    status: dict = field(default_factory=dict)            # (effect, j) -> (status, reason)
    base: dict = field(default_factory=dict)              # joint name -> {name: (value, se)} for small bases
    heldout: dict = field(default_factory=dict)           # joint name -> rms, r2 (against the recorded τ)
    e_held: dict | None = None                            # per joint, per held row of the flat: squared error (mass-norm.)
    held_rows: np.ndarray | None = None
    cross: dict = field(default_factory=dict)             # (effect, j) -> TermEstimate on the learned residual
    learned_check: dict = field(default_factory=dict)     # (effect, j) -> the learned base's gain with it held (rule 6)
    term_gain: dict = field(default_factory=dict)         # (effect, j) -> held-out gain of the term (final model)
    term_rows: dict = field(default_factory=dict)         # (effect, j) -> that gain per held row of the flat
    forms: dict = field(default_factory=dict)             # (effect, j) -> its subject form (`physics_subjects`)
    forms_refused: dict = field(default_factory=dict)     # (effect, j) -> θ by subject where an unphysical one refused it
    rivalries: list = field(default_factory=list)         # (accepted term, its rival, j): rule 4's ambiguous pairs
    seconds: float = 0.0
    cutoff_hz: float = 0.0

    def summary(self, joints) -> str:
        acc = ", ".join(f"{e}:{joints[j]} {self.estimates[(e, j)].estimate:.4g} "
                        f"[{self.estimates[(e, j)].ci[0]:.4g}, {self.estimates[(e, j)].ci[1]:.4g}]"
                        for e, j in self.accepted) or "nothing"
        fit = "; ".join(f"{k}: held-out rms {v['rms']:.3g}, R² {v['r2']:.4f}" for k, v in self.heldout.items())
        return (f"parametric base + terms ({self.family} candidates, Holm at {100 * self.alpha:g} %): {acc}; {fit} "
                f"({self.seconds:.1f} s)")

    def to_json(self, joints) -> dict:
        return jsonable(dict(
            method=("parametric rigid-body base + candidate terms, weighted LS on the training segments, HAC "
                    f"(Newey-West) intervals; zero-phase low-pass {self.cutoff_hz:g} Hz and central differences; "
                    f"forward selection with Holm's thresholds α/(m − r), α = {self.alpha}, m = {self.family}; a "
                    "term is taken only with a held-out gain (in the fit's band), as a constant across recordings "
                    "(three or more), inside its domain, and (a torque gain) on the controller's own variation alone "
                    "too"),
            accepted=[f"{e}:{joints[j]}" for e, j in self.accepted],
            estimates={f"{e}:{joints[j]}": v.to_json() for (e, j), v in self.estimates.items()},
            cross_check={f"{e}:{joints[j]}": v.to_json() for (e, j), v in self.cross.items()},
            learned_check={f"{e}:{joints[j]}": v for (e, j), v in self.learned_check.items()},
            tests=self.tests, base=self.base, heldout=self.heldout, seconds=self.seconds))


def _p(prob: ident.JointProblem, f: ident.Fit, eff: str) -> float:
    """The test's p; 1 where the nonlinear parameter ends at an edge of its grid (not identified: the optimum
    lies at or beyond what the grid can say, e.g. a Stribeck velocity at the Coulomb term's own smoothing ε)."""
    if eff in f.split:      # split by subject: effect in at least one subject (Bonferroni over the subjects)
        th, se = f.split[eff]
        p = min(1.0, len(th) * min(ident.p_value(eff, a, b) for a, b in zip(th, se)))
    else:
        p = ident.p_value(eff, f.est[eff], f.se[eff])
    grid = prob.grid(eff)
    if grid is not None:
        if f.nu[eff] in (grid[0], grid[-1]):
            return 1.0
        if not ident.TERMS[eff].fixed:
            p = min(1.0, p * len(grid))     # the nonlinear parameter chosen on the data (Bonferroni over the grid)
    return p


def _z(f: ident.Fit, eff: str) -> float:
    """The test's statistic θ/SE (|θ|/SE where two-sided; the largest subject's where split by subject)."""
    th, se = f.split[eff] if eff in f.split else (np.array([f.est[eff]]), np.array([f.se[eff]]))
    z = np.asarray(th) / np.where(np.asarray(se) > 0, se, np.inf)
    return float(np.max(np.abs(z) if ident.TERMS[eff].sided == "two-sided" else z))


def _edge_text(prob: ident.JointProblem, f: ident.Fit, eff: str) -> str | None:
    """Why a nonlinear parameter at an edge of its grid is not identified, or None."""
    grid = prob.grid(eff)
    if grid is None:
        return None
    if f.nu[eff] == grid[0]:
        return (f"not identified: its nonlinear parameter ends at the smallest value searched ({grid[0]:.3g})"
                + (", the Coulomb term's own smoothing ε" if eff == "stribeck_friction" else ""))
    if f.nu[eff] == grid[-1]:
        return f"not identified: its nonlinear parameter ends at the largest value searched ({grid[-1]:.3g})"
    return None


def _held_gain(e_without: np.ndarray, e_with: np.ndarray, n_boot: int, seed: int = 0) -> dict:
    b = stats.bootstrap_mean(e_without - e_with, n_boot=n_boot, seed=seed)
    return dict(gain=float(b["mean"]), ci=[float(b["ci"][0]), float(b["ci"][1])])


def setup(flat, effects, joint_ids, alpha: float = 0.05, cutoff_hz: float = parallel_filter.CUTOFF_HZ,
          max_delay: float = 0.1) -> PhysicsResult:
    """The parametric base fitted per joint (weighted) and the family of candidates; no selection yet."""
    t0 = time.time()
    sig = parallel_filter.signals(flat, cutoff_hz)
    X_raw, names = ident.base_columns(sig.q, sig.qd, sig.qdd, sig)
    Xb = sig.lp(X_raw)
    ctx = dict(max_delay=max_delay, base_theta={}, base_raw=X_raw)
    probs, cur = {}, {}
    masks = flat.user_masks()
    for j in joint_ids:
        prob = ident.JointProblem(sig, j, Xb, names, ctx)
        ctx["base_theta"][j] = prob.fit([], intervals=False).theta      # provisional: the strap's column reads it
        # the weights per trial from the most flexible linear model (every linear candidate, split by subject):
        # from the base alone they would be lowest on the trials that carry an effect, hiding it from its test
        lin = [e for e in effects if e in ident.TERMS and ident.TERMS[e].grid is None and not ident.TERMS[e].fixed
               and (flat.has_exo or not LIBRARY[e].needs_exo)]
        if masks is not None:
            prob.split = {e: masks for e in lin}
        strap = "strap_compliance" in lin
        if strap:
            _strap_point(prob)
        prob.set_weights(prob.fit(lin, intervals=False))
        prob.split = {}
        f0 = prob.fit([], intervals=False)
        ctx["base_theta"][j] = f0.theta
        prob._cols = {}         # columns made with the provisional base (the strap's) are made again
        if strap:
            _strap_point(prob)
        probs[j], cur[j] = prob, f0
    cands = [(e, j) for e in effects if e in ident.TERMS for j in joint_ids
             if (flat.has_exo or not LIBRARY[e].needs_exo) and (sig.side is not None or not ident.TERMS[e].shift)]
    res = PhysicsResult(alpha=alpha, family=len(cands), cutoff_hz=sig.cutoff)
    res._probs, res._fits, res._cands, res._joint_ids = probs, cur, cands, list(joint_ids)
    res._base_fits = dict(cur)          # each selection starts from the bare bases (`select` may run again)
    res.seconds = time.time() - t0
    return res


def _strap_point(prob: ident.JointProblem, tol: float = 1e-3, max_iter: int = 40) -> None:
    """The strap column's linearisation point (`ident._strap_col` reads `ctx['base_theta']`): the base's
    coefficients of the fit of the base *with* the strap term, iterated to a fixed point. The base-only fit's
    coefficients carry the strap's own misfit (the base absorbs part of it), and a soft strap linearised there came
    out 10-36 % too soft (docs/DIAGNOSIS.md); at the fixed point the equations of base and strap hold together."""
    j, nb, key = prob.j, len(prob.base_names), ("strap_compliance", None)
    c_old = None
    for _ in range(max_iter):
        f = prob.fit(["strap_compliance"], intervals=False)
        c = float(f.theta[nb])
        prob.ctx["base_theta"][j] = f.theta[:nb]
        prob._cols.pop(key, None)
        if c_old is not None and abs(c - c_old) <= tol * max(abs(c), 1e-12):
            return
        c_old = c


def saturated_held(res: PhysicsResult, flat) -> dict[int, np.ndarray]:
    """Per joint, per held-out row of the flat: the squared error (mass-normalised) of the parametric base with
    every linear candidate term at once — the most the parametric family explains without a grid."""
    held_idx = flat.index("held").numpy()
    out = {}
    for j, prob in res._probs.items():
        lin = [x for x, jj in res._cands if jj == j and ident.TERMS[x].grid is None]
        out[j] = prob.held_sq(prob.fit(lin, intervals=False), held_idx, recorded=True)
    return out


def single_term(res: PhysicsResult, effect: str, j: int, joint: str) -> TermEstimate | None:
    """One term alone with the parametric base (the learned path's cross-check of its own findings)."""
    if effect not in ident.TERMS or (effect, j) not in res._cands:
        return None
    prob = res._probs[j]
    return term_estimate(prob, prob.fit([effect]), effect, joint)


def identify(flat, effects, joint_ids, alpha: float = 0.05, cutoff_hz: float = parallel_filter.CUTOFF_HZ,
             max_delay: float = 0.1, n_boot: int = 400, log=None) -> PhysicsResult:
    """Physics first (module docstring): the parametric base and forward selection of the candidate terms."""
    return select(setup(flat, effects, joint_ids, alpha, cutoff_hz, max_delay), flat, n_boot, log)


def select(res: PhysicsResult, flat, n_boot: int = 400, log=None, joints=None) -> PhysicsResult:
    """Forward selection under Holm's thresholds, rivals, and the final joint fits (module docstring). `joints`:
    the joints whose candidates physics first decides (None: all); the rest are left to the learned path and not
    tested here. Holm's thresholds keep m = every candidate of the family (both paths'): each path's own
    step-down at α/(m − r) bounds the family-wise level of the two together by α (`procedure.run`)."""
    t0 = time.time() - res.seconds
    log = log or (lambda msg: None)
    reset(res)
    probs, cur, cands, joint_ids, alpha = res._probs, res._fits, res._cands, res._joint_ids, res.alpha
    pool, r = [c for c in cands if joints is None or c[1] in joints], 0
    accepted = {j: [] for j in joint_ids}
    masks = flat.user_masks()
    tests = {}          # a candidate's test depends only on its joint's accepted terms: made once per such set
    while pool:
        todo = [(e, j) for e, j in pool if (e, j, tuple(accepted[j])) not in tests]
        for row in _test_all(probs, accepted, todo, masks, lambda e, j, r=r: log(
                f"physics step {r + 1}: testing {e} on {flat.joints[j]}")):
            tests[(row[3], row[4], tuple(accepted[row[4]]))] = row
        if len(todo) < len(pool):
            log(f"physics step {r + 1}: {len(pool) - len(todo)} candidates as tested before (their joint's terms "
                f"unchanged since)")
        tried = [tests[(e, j, tuple(accepted[j]))] for e, j in pool]
        tried.sort(key=lambda x: (x[0], -_z(x[1], x[3])))      # p underflows to 0 past z ≈ 38: then the larger z
        p, f, split, e, j = tried[0]
        tried = [(pe, ee, jj, ff) for pe, ff, _, ee, jj in tried]
        thr = alpha / (len(cands) - r)
        gain = _held_gain(probs[j].held_sq(cur[j]), probs[j].held_sq(f), n_boot)
        te = term_estimate(probs[j], f, e, flat.joints[j])
        rec = dict(step=r + 1, effect=e, joint=flat.joints[j], p=p, threshold=thr, estimate=te.estimate, ci=te.ci,
                   heldout_gain=gain["gain"], heldout_gain_ci=gain["ci"])
        res.tests.append(rec)
        r += 1
        if p > thr:
            for pe, ee, jj, ff in tried:
                res.status[(ee, jj)] = ("rejected", _edge_text(probs[jj], ff, ee) or (
                    f"not significant (p {pe:.3g} > Holm's threshold {thr:.3g} at step {r} of {len(cands)})"))
            break
        pool.remove((e, j))
        why, rec["consistency"] = _objection(probs[j], flat, accepted[j], f, e, te, split, gain, alpha)
        if why:
            res.status[(e, j)] = ("rejected", f"significant (p {p:.3g}) but {why}")
            log(f"physics: {e} on {flat.joints[j]} rejected: {why}")
            continue
        accepted[j].append(e)
        cur[j] = f
        tests = {k: v for k, v in tests.items() if k[1] != j}     # its joint's earlier tests: never asked again
        if split:           # it enters the later steps' fits split by subject
            probs[j].split[e] = masks
        res.status[(e, j)] = ("accepted", f"p {p:.3g} ≤ Holm's threshold {thr:.3g}; held-out gain {gain['gain']:.3g} "
                                          f"[{gain['ci'][0]:.3g}, {gain['ci'][1]:.3g}]")
        log(f"physics: {e} on {flat.joints[j]} accepted at {te.estimate:.4g} [{te.ci[0]:.4g}, {te.ci[1]:.4g}] "
            f"(p {p:.2g}, step {r})")
    _rivals(res, probs, cur, accepted, flat, alpha / max(len(cands), 1), n_boot)
    # the final joint fits: every accepted term's estimate and interval, its own held-out share, the base's size
    res.held_rows = flat.index("held").numpy()
    res.e_held = {}
    res._probs, res._fits = probs, cur      # for the cross-check and the extended model
    for j in joint_ids:
        final_fit(res, flat, j, accepted[j], n_boot)
        res.accepted += [(e, j) for e in accepted[j]]
    res.seconds = time.time() - t0
    return res


def _objection(prob: ident.JointProblem, flat, accepted: list, f: ident.Fit, e: str, te: TermEstimate, split: bool,
               gain: dict, alpha: float) -> tuple[str | None, dict | None]:
    """Why a significant term cannot be taken (None: it can) and its recordings' check: inside its domain with a
    bounded size, a constant across recordings, a held-out gain, and (a gain) on the controller's own variation."""
    why = inadmissible(e, te)
    if why:
        return why, None
    cons = consistency.across_trials(prob, f, e, split, flat)
    if cons["consistent"] is False:
        return consistency.text(cons, te.estimate), cons
    if gain["ci"][0] <= 0:
        return f"no held-out gain: {gain['gain']:.3g} [{gain['ci'][0]:.3g}, {gain['ci'][1]:.3g}]", cons
    if ident.TERMS[e].own_variation:
        return own_variation(prob, flat, accepted, te, alpha), cons
    return None, cons


def own_variation(prob: ident.JointProblem, flat, accepted: list, te: TermEstimate, alpha: float) -> str | None:
    """Rule 3 (the learned path's own-variation null, `nulls.on_own_variation`) for a term whose column is the exo
    torque: why it fails, or None. An assistive controller's torque mostly copies the joint torque (`flat.exo_copy`),
    so such a column also takes whatever misfit of the base follows the joint torque; a real gain error scales the
    controller's own variation (the rest) as much. Fitted beside the accepted terms with its column made of that
    variation alone, the term must still be significant (at α: a check that can only remove spends nothing) and
    on the same side of no effect."""
    j, key = prob.j, (te.effect, None)
    whole = prob.col(te.effect, None)
    prob._cols[key] = parallel_filter.exo_like(prob.sig, exo_own(flat, j).tau_e[:, j].double().numpy())
    try:
        o = term_estimate(prob, prob.fit(accepted + [te.effect]), te.effect, te.joint)
    finally:
        prob._cols[key] = whole
    if o.p > alpha:
        return (f"on the controller's own variation alone it is not significant ({o.estimate:.4g} {_ci_text(o.ci)}, "
                f"p {o.p:.2g}): it rests on the copy of the joint torque, which carries the base's misfit too")
    if o.theta * te.theta < 0:
        return (f"on the controller's own variation alone it points the other way ({o.estimate:.4g} "
                f"{_ci_text(o.ci)} against {te.estimate:.4g}): it rests on the copy of the joint torque, which "
                "carries the base's misfit too")
    return None


def final_fit(res: PhysicsResult, flat, j: int, terms: list, n_boot: int) -> None:
    """Joint j's final fit of `terms` (a term that no longer earns its held-out share, or whose interval leaves its
    domain, is dropped: `_held_out_fit`): every term's estimate and interval, its own held-out share, the base's
    sizes and the joint's held-out errors. Also where a later rule sets a term aside (`physics_checks.settle`)."""
    prob, held_idx = res._probs[j], res.held_rows
    f, gains, withouts = _held_out_fit(res, prob, terms, flat.joints[j], j, n_boot)
    res._fits[j] = f
    for e in terms:
        if ident.TERMS[e].shift:        # the learned residual's check sizes it linearised here (`shift.backlash_col`)
            prob.ctx.setdefault("shift_D", {})[j] = prob.dcol(e, f)
        res.estimates[(e, j)] = term_estimate(prob, f, e, flat.joints[j])
        res.term_gain[(e, j)] = gains[e]
        res.term_rows[(e, j)] = prob.held_sq(withouts[e], held_idx) - prob.held_sq(f, held_idx)
    res.base[flat.joints[j]] = _base_sizes(prob, f)
    res.e_held[j] = prob.held_sq(f, held_idx, recorded=True)
    sel = prob.held
    y = prob.sig.tau_raw[sel, j]
    mse = float(np.mean((y - f.pred[sel]) ** 2))
    res.heldout[flat.joints[j]] = dict(rms=math.sqrt(mse), r2=float(1 - mse / np.var(y)),
                                       rms_filtered=float(np.sqrt(np.mean((prob.y - f.pred)[sel] ** 2))))


def _test_all(probs: dict, accepted: dict, pool: list, masks, log) -> list:
    """`_test` of every candidate (effect, joint) in `pool` against its joint's accepted terms, in `pool`'s order
    with the candidate appended: side by side on the running diagnosis' workers (`workers.current`), each on its own
    view of the joint's problem (the tests are independent; numpy releases the GIL in its products)."""
    def one(e, j):
        log(e, j)
        return _test(probs[j].view(), accepted[j], e, masks) + (e, j)
    return (current() or Workers()).map([lambda e=e, j=j: one(e, j) for e, j in pool])


def _test(prob: ident.JointProblem, accepted: list, e: str, masks) -> tuple:
    """A candidate's p with the accepted terms: its shared column, and where the data hold several subjects and
    the term is linear, also its column split by subject (an effect that some subjects lack or carry at another
    size leaves the shared column a misfit as long as their trials, which widens its interval until it is missed);
    p = 2 min of the two (Bonferroni over the two forms). Returns (p, the fit of the smaller, split or not)."""
    f = prob.fit(accepted + [e])
    p = _p(prob, f, e)
    if masks is None or ident.TERMS[e].fixed:
        return p, f, False
    prob.split[e] = masks
    try:
        fs = prob.fit(accepted + [e])
        ps = _p(prob, fs, e)
    finally:
        del prob.split[e]
    return (min(1.0, 2 * p), f, False) if p <= ps else (min(1.0, 2 * ps), fs, True)


def reset(res: PhysicsResult) -> None:
    """Forget an earlier selection: a selection rerun on fewer joints must not count the acceptances of a joint
    it no longer decides in Holm's step-down (they would loosen every later threshold)."""
    res.accepted, res.estimates, res.tests, res.status = [], {}, [], {}
    res.base, res.heldout, res.cross, res.term_gain, res.term_rows, res.forms = {}, {}, {}, {}, {}, {}
    res.learned_check, res.rivalries, res.forms_refused = {}, [], {}
    res.e_held, res.held_rows = None, None
    res._fits = dict(res._base_fits)
    for prob in getattr(res, "_probs", {}).values():
        prob.split = {}


def _physical_fit(res: PhysicsResult, prob: ident.JointProblem, accepted: list, joint: str, j: int) -> ident.Fit:
    """The joint fit of the accepted terms, without those whose interval in it lies wholly outside their
    physical domain (`Candidate.outside_domain`: they absorb something else), refitted until none is."""
    while True:
        f = prob.fit(accepted)
        bad = [(e, te) for e in accepted for te in [term_estimate(prob, f, e, joint)]
               if LIBRARY[e].outside_domain(te.ci)]
        if not bad:
            return f
        for e, te in bad:
            accepted.remove(e)
            res.status[(e, j)] = ("rejected", _outside_domain_text(e, te, " in the joint fit"))


def _held_out_fit(res: PhysicsResult, prob: ident.JointProblem, accepted: list, joint: str, j: int, n_boot: int):
    """The joint fit in which every accepted term still earns its place on held-out data: a term accepted at its
    step can lose its held-out share once later terms are in, and is then dropped (the weakest first, then refit;
    the selection's own held-out rule applied to the final model, so it only removes). Returns the fit, every
    remaining term's own held-out gain and the fit without that term."""
    while True:
        f = _physical_fit(res, prob, accepted, joint, j)
        withouts = {e: prob.fit([x for x in accepted if x != e], intervals=False) for e in accepted}
        gains = {e: _held_gain(prob.held_sq(withouts[e]), prob.held_sq(f), n_boot) for e in accepted}
        weak = [e for e in accepted if gains[e]["ci"][0] <= 0]
        if not weak:
            return f, gains, withouts
        e = min(weak, key=lambda x: gains[x]["gain"])
        g = gains[e]
        accepted.remove(e)
        res.status[(e, j)] = ("rejected", f"no held-out gain in the joint fit with the other accepted terms: "
                                          f"{g['gain']:.3g} [{g['ci'][0]:.3g}, {g['ci'][1]:.3g}]")


def inadmissible(e: str, te) -> str | None:
    """Why a significant term's size cannot be taken (outside its physical domain, or an interval that reaches
    infinity: a size the data do not bound), or None."""
    if LIBRARY[e].outside_domain(te.ci):
        return _outside_domain_text(e, te, "")
    if not all(math.isfinite(v) for v in te.ci):        # rule 4 of both paths
        return f"its size is not identified: the interval {_ci_text(te.ci)} reaches infinity"
    return None


def _outside_domain_text(e: str, te, where: str) -> str:
    """The status of a term whose interval lies wholly outside its physical domain (selection and joint fit alike)."""
    return (f"outside its physical domain ({LIBRARY[e].sign}){where}: {te.estimate:.4g} {_ci_text(te.ci)}; "
            "the term absorbs something else")


def _base_sizes(prob: ident.JointProblem, f: ident.Fit) -> dict:
    """The base's coefficients with HAC SEs where the base is small (a drive's mass and offset); else values."""
    nb = len(prob.base_names)
    if nb > 8:
        return {"columns": nb}
    X, names, off = prob._design(f.terms, f.nu)
    tr = prob.train
    coef, se, _ = wls.hac_subset(X[tr], (prob.y - off)[tr], prob.w[tr], list(range(nb)))
    return {nm: dict(value=float(c), se=float(s)) for nm, c, s in zip(names[:nb], coef, se)}


def _rivals(res, probs, cur, accepted, flat, thr, n_boot):
    """Rule 4: an accepted term and a rival that explains the held-out data as well, and is a constant of the joint
    too (`consistency.across_trials`), are ambiguous (or the simpler of a nested pair is taken). Rivals come from
    the run's candidate family: an effect the caller did not ask for is neither tested nor named (nor in the
    family-wise budget's m)."""
    for j, terms in accepted.items():
        for e in list(terms):
            for rv in rivals(e):
                if (rv, j) not in res._cands or rv in terms:
                    continue
                alt_terms = [x if x != e else rv for x in terms]
                alt = probs[j].fit(alt_terms)
                if _p(probs[j], alt, rv) > thr:
                    continue
                te = term_estimate(probs[j], alt, rv, flat.joints[j])
                if inadmissible(rv, te) or (ident.TERMS[rv].own_variation and own_variation(
                        probs[j], flat, [x for x in alt_terms if x != rv], te, res.alpha)):
                    continue                # what an accepted term must be, a rival must be too
                if consistency.across_trials(probs[j], alt, rv, rv in alt.split, flat)["consistent"] is False:
                    continue                # a rival that is no constant of the joint explains nothing physical
                d = _held_gain(probs[j].held_sq(alt), probs[j].held_sq(cur[j]), n_boot)    # > 0: e is better
                if d["ci"][0] > 0:
                    continue
                if NESTS.get(rv, ("",))[0] == e:           # the rival reduces to e: e is the simpler, kept
                    res.status[(rv, j)] = ("rejected", f"reduces to {e} ({NESTS[rv][1]}) and held-out data cannot "
                                                       f"separate them: the simpler term is taken")
                    continue
                if NESTS.get(e, ("",))[0] == rv:           # e reduces to the rival: the rival replaces it
                    terms[terms.index(e)] = rv
                    cur[j] = alt
                    res.status[(rv, j)] = ("accepted", f"taken for {e}, which reduces to it ({NESTS[e][1]}) and "
                                                       f"held-out data cannot separate them")
                    res.status[(e, j)] = ("rejected", f"reduces to {rv}: the simpler term is taken")
                    break
                terms.remove(e)
                cur[j] = probs[j].fit(terms)
                why = (f"held-out data cannot separate {e} and {rv} (advantage {d['gain']:.3g} "
                       f"[{d['ci'][0]:.3g}, {d['ci'][1]:.3g}])")
                res.status[(e, j)] = ("ambiguous", why)
                res.status[(rv, j)] = ("ambiguous", why)
                res.rivalries.append((e, rv, j))
                break
