"""One term's size as the parametric identification gives it: the estimate in the vocabulary's units, its 95 %
interval (mapped through the term's report function, poles included), θ, its SE and p."""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..runio import jsonable
from . import ident

Z95 = 1.959963984540054


@dataclass
class TermEstimate:
    """One (effect, joint) as the parametric identification sizes it."""
    effect: str
    joint: str
    estimate: float
    ci: list
    theta: float                # the linear coefficient (ν for a fixed term)
    se: float
    p: float
    nu: float | None = None     # the nonlinear parameter (Stribeck velocity)

    def to_json(self) -> dict:
        return jsonable(self.__dict__)


def term_estimate(prob: ident.JointProblem, f: ident.Fit, eff: str, joint: str) -> TermEstimate:
    t = ident.TERMS[eff]
    th, se = f.est[eff], f.se[eff]
    lo, hi = th - Z95 * se, th + Z95 * se
    if t.fixed:
        est, ci = th, [max(lo, 0.0), hi]
    else:
        est = t.value(th, f.nu.get(eff))
        ci = report_interval(t, lo, hi, f.nu.get(eff))
    nu = f.nu.get(eff)
    return TermEstimate(eff, joint, float(est), [float(ci[0]), float(ci[1])], float(th), float(se),
                        ident.p_value(eff, th, se), None if nu is None or t.fixed else float(nu))


def report_interval(t: ident.Term, lo: float, hi: float, nu) -> list[float]:
    """θ's interval [lo, hi] in the reported parameter. Where it holds the map's pole (θ at which the reported
    value is infinite: a gain k = 1/(1 − θ) at θ = 1, a stiffness 1/c at c = 0), the reported interval reaches
    infinity: its image is two rays, and the one on the estimate's side is unbounded (the data cannot bound the
    size). Not the two ends sorted, which would give a finite interval that does not even hold the estimate."""
    ends = [t.value(lo, nu), t.value(hi, nu)]
    if t.pole is not None and lo <= t.pole <= hi:
        inside = [v for v in ends if math.isfinite(v) and v > 0]       # the ray in the domain (k > 0)
        return [float(min(inside)), math.inf] if inside else [-math.inf, math.inf]
    return sorted(ends)


def ci_text(ci) -> str:
    return f"[{ci[0]:.4g}, {ci[1]:.4g}]"
