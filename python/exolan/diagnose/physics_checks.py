"""Rules 5 and 6 of physics first (`physics` docstring), the checks against the learned base: the accepted terms
fitted on the learned base's residual (`cross_check`), rule 4's pairs told apart by it (`rivals`), every term's
verdict with both checks (`verdicts`; rule 6's refits live in `physics_path.learned_check`), and the sizes of the
terms that remain (`settle`)."""
from __future__ import annotations

import numpy as np
from scipy import stats as sps

from . import ident, parallel_filter, physics_subjects
from .physics import PhysicsResult, final_fit, term_estimate
from .stats import span_if_disjoint


def on_residual(res: PhysicsResult, flat, residual: np.ndarray, j: int, terms: list) -> dict:
    """`terms` of joint j fitted on the learned base's residual (training rows, the same low-pass), with a constant
    only: term -> its estimate there."""
    prob = res._probs[j]
    sig = prob.sig
    r = sig.lp(np.where(np.isfinite(residual[:, j]), residual[:, j], 0.0))
    sig_r = parallel_filter.Signals(**{**sig.__dict__, "tau": np.where(np.isfinite(sig.tau), 0.0, np.nan)})
    sig_r.tau[:, j] = r
    p = ident.JointProblem(sig_r, j, np.ones((len(r), 1)), ["const"], prob.ctx, shiftable=False)
    p.w = prob.w
    # in the form each term was taken in: a term of one subject fitted shared would be diluted by the others
    p.split = {e: physics_subjects.form_masks(res.forms[(e, j)], sig.trial) for e in terms if (e, j) in res.forms}
    f = p.fit(terms)
    return {e: term_estimate(p, f, e, flat.joints[j]) for e in terms}


def unsupported(m, c, alpha: float) -> str | None:
    """Rule 5's objection to a term sized `m` by the parametric base and `c` on the learned base's residual, or
    None: the residual shows no such term, or one of the other sign (a two-sided term seen both ways).

    "Shows" is judged by the (1 − α) interval that the finding reports, not by a one-sided p: the finding's interval
    spans both sizes, and one that holds no effect is no finding (rule 4 on what is reported)."""
    if not shows(c, alpha):
        return (f"the learned base's residual shows no such term ({c.estimate:.4g} [{c.ci[0]:.4g}, {c.ci[1]:.4g}], "
                f"p {c.p:.2g}): the parametric base may be what misses it")
    if c.theta * m.theta < 0:
        return (f"on the learned base's residual it points the other way ({c.estimate:.4g} [{c.ci[0]:.4g}, "
                f"{c.ci[1]:.4g}] against {m.estimate:.4g}): the two bases do not agree that there is such an effect")
    return None


def shows(c, alpha: float) -> bool:
    """Whether a size `c` (a `TermEstimate`) is bounded away from no effect (θ = 0) by its two-sided (1 − α)
    interval: a one-sided term's p then below α/2."""
    return bool(c.se > 0 and np.isfinite(c.se) and abs(c.theta) > sps.norm.isf(alpha / 2) * c.se)


def cross_check(res: PhysicsResult, flat, residual: np.ndarray, joint_ids, log=None) -> None:
    """Rule 5: the accepted terms fitted on the learned base's residual (`on_residual`): `res.cross`; a
    disagreement widens the finding's interval or makes it ambiguous."""
    for j in joint_ids:
        terms = [e for e, jj in res.accepted if jj == j and e in res._fits[j].terms]     # not those set aside
        if not terms:
            continue
        for e, c in on_residual(res, flat, residual, j, terms).items():
            res.cross[(e, j)] = c
            if log:
                m_est, m_ci = sized(res, (e, j))
                form = " (in its subject form)" if (e, j) in res.forms else ""
                log(f"cross-check {e} on {flat.joints[j]}{form}: parametric {m_est:.4g} [{m_ci[0]:.4g}, {m_ci[1]:.4g}], "
                    f"on the learned base's residual {c.estimate:.4g} [{c.ci[0]:.4g}, {c.ci[1]:.4g}]")


def sized(res: PhysicsResult, key) -> tuple[float, list]:
    """The parametric size and interval of an accepted term as the finding reports it: its subject form's where it
    has one (the cross-check sizes it in that form too, `on_residual`)."""
    if key in res.forms:
        return res.forms[key]["estimate"], list(res.forms[key]["ci"])
    return res.estimates[key].estimate, list(res.estimates[key].ci)


def verdicts(res: PhysicsResult) -> dict:
    """(effect, j) -> dict(status, reason, estimate, ci, note): rules 2-6 together."""
    out = {}
    for key, (status, reason) in res.status.items():
        v = dict(status=status, reason=reason)
        if key in res.estimates and status == "accepted":
            m = res.estimates[key]
            v.update(estimate=m.estimate, ci=list(m.ci))
            c = res.cross.get(key)
            if c is not None:
                m_est, m_ci = sized(res, key)
                why, both = unsupported(m, c, res.alpha), span_if_disjoint(m_ci, c.ci)
                if why:
                    v.update(status="ambiguous", reason=reason + "; but " + why)
                elif both:
                    v["ci"] = both
                    v["note"] = (f"sizes disagree: parametric base {m_est:.4g} [{m_ci[0]:.4g}, {m_ci[1]:.4g}], "
                                 f"the learned base's residual {c.estimate:.4g} [{c.ci[0]:.4g}, {c.ci[1]:.4g}]; the "
                                 "interval spans both")
            lc = res.learned_check.get(key)
            if lc is not None and v["status"] == "accepted" and lc["ci"][1] < 0:
                v.update(status="ambiguous", reason=v["reason"] + (
                    f"; but the learned base with it held at this size is worse on held-out data than without it (gain "
                    f"{lc['gain']:.3g} [{lc['ci'][0]:.3g}, {lc['ci'][1]:.3g}]): it carries what the parametric "
                    "base misfits, not an effect both bases show"))
        out[key] = v
    return out


def settle(res: PhysicsResult, flat, residual: np.ndarray, joint_ids, n_boot: int, log=None) -> list:
    """A term the checks set aside leaves its joint's fit: the terms that remain are sized by the joint fit without
    it (a term held beside them takes part of their signal: a knee gain beside a strap moved its stiffness by a
    quarter), their subject forms and cross-checks redone, until no further term is set aside. The set-aside term
    keeps the size it had when it was accepted. Returns the joints refitted."""
    redone = []
    while True:
        ver = verdicts(res)
        aside = {j: [e for e in res._fits[j].terms if (e, j) in ver and ver[(e, j)]["status"] != "accepted"]
                 for j in joint_ids if j in res._fits}
        redo = [j for j, out in aside.items() if out]
        if not redo:
            return redone
        for j in redo:
            keep = [e for e in res._fits[j].terms if e not in aside[j]]
            if log:
                log(f"physics: {', '.join(aside[j])} on {flat.joints[j]} set aside; "
                    + (f"{', '.join(keep)} sized without it" if keep else "no term left in the joint fit"))
            for e in res._fits[j].terms:
                res.forms.pop((e, j), None)
            res._probs[j].split = {}
            final_fit(res, flat, j, keep, n_boot)
        physics_subjects.take(res, flat, n_boot, log=log, joints=redo)
        cross_check(res, flat, residual, redo, log=log)
        redone += [j for j in redo if j not in redone]


def rivals(res: PhysicsResult, flat, residual: np.ndarray, joint_ids, n_boot: int, log=None, cross=None) -> list:
    """Rule 5 for rule 4's pairs: held-out data could not separate a term and its rival; each is fitted in the place
    they share (beside the joint's accepted terms) on the parametric base and on the learned base's residual. Where
    exactly one of them meets rule 5's objection (`unsupported`), the other is accepted: the learned base tells them
    apart. Both were significant at the same Holm threshold, so no level is spent. Returns the joints refitted.
    `cross` (j, terms -> estimates on the learned residual; default `on_residual`): tests pass a stub."""
    cross = cross or (lambda j, terms: on_residual(res, flat, residual, j, terms))
    redone = []
    for e, rv, j in res.rivalries:
        if j not in joint_ids or {res.status[(e, j)][0], res.status[(rv, j)][0]} != {"ambiguous"}:
            continue
        prob, keep = res._probs[j], list(res._fits[j].terms)
        why = {}
        for t in (e, rv):
            m = term_estimate(prob, prob.fit(keep + [t]), t, flat.joints[j])
            why[t] = unsupported(m, cross(j, keep + [t])[t], res.alpha)
        if (why[e] is None) == (why[rv] is None):
            continue
        win, lose = (e, rv) if why[e] is None else (rv, e)
        res.status[(win, j)] = ("accepted", res.status[(win, j)][1] + f"; but in its place {lose} fails the learned "
                                "base's cross-check, and this term passes it")
        res.status[(lose, j)] = ("rejected", res.status[(lose, j)][1] + "; in the place they share, " + why[lose])
        if log:
            log(f"physics: {win} on {flat.joints[j]} taken for its rival {lose}, which {why[lose]}")
        for t in keep:
            res.forms.pop((t, j), None)
        prob.split = {}
        terms = keep + [win]
        final_fit(res, flat, j, terms, n_boot)          # drops a term that no longer earns its held-out share
        if win in terms:
            res.accepted.append((win, j))
        redone.append(j)
    if redone:
        physics_subjects.take(res, flat, n_boot, log=log, joints=redone)
        cross_check(res, flat, residual, redone, log=log)
    return redone
