"""The library of candidate physical effects (the vocabulary of DATA_LAYOUT.md), per joint.

Each candidate states what it means physically, the sign that physics allows, its unit, how it enters the
model (DESIGN.md section 4) and its `kind`:

- `finding`: a term a conservative Lagrangian cannot represent (dissipation, lag, compliance, recording
  gain, a backlash's hysteresis in the measured angle); it may be accepted when the decision rule passes.
- `absorbable`: an effect a flexible conservative model represents by itself (a constant encoder offset is a
  change of coordinates of H and V; a constant torque bias is a linear potential; a payload changes H and
  V). It is reported as absorbable, never as a finding, whatever its held-out gain.

`neutral` is the parameter value meaning "no effect": identifiability asks that the parameter's confidence
interval exclude it. `needs_exo`: the effect acts through the recorded exoskeleton torque and cannot be
tested on data without one.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from ..extensions import COULOMB_EPS
from .fit import predict
from .flat import exo_copy

VS_GRID = (0.02, 0.05, 0.1, 0.2, 0.5, 1.0)   # rad/s (m/s): a log grid across plausible Stribeck velocities


def _start_positive(th: float, sc: dict) -> dict:
    return {"value": th} if th > 0 else {}


def _start_any(th: float, sc: dict) -> dict:
    return {"value": th}


def _start_gain(th: float, sc: dict) -> dict:
    return {"value": 1.0 / (1.0 - th)} if th < 0.9 else {}


def _start_inverse(th: float, sc: dict) -> dict:
    return {"value": 1.0 / th} if th > 0 else {}


def _start_delay(th: float, sc: dict) -> dict:
    return {"value": sc["d"]} if "d" in sc else {}


def delayed(x: torch.Tensor, lengths, d: float, dt: float) -> torch.Tensor:
    """x(t − d) per trial (flat rows, trials of `lengths` samples): linear interpolation between samples, held at
    the trial's first value before its start (as `ExtendedModel` shifts the recorded exo torque)."""
    out = []
    for seg in torch.split(x, [int(n) for n in lengths]):
        v = seg.numpy().astype(np.float64)
        t = np.arange(len(v), dtype=np.float64)
        out.append(np.interp(t - d / dt, t, v))
    return torch.as_tensor(np.concatenate(out), dtype=x.dtype)


def _inject_gain(te: torch.Tensor, th: float, lengths, dt: float) -> torch.Tensor:
    return th * te          # a sensor over-reporting the exo torque by k = 1/(1 − θ)


def _inject_delay(te: torch.Tensor, th: float, lengths, dt: float) -> torch.Tensor:
    return te - delayed(te, lengths, th, dt)     # the limb feels the recorded torque θ seconds late


# -- the screen's features: the change of the predicted recorded torque per unit parameter, (rows, n) on joint j
#    (`screen`); each returns [(extra, F)], one per grid variant

def _onehot(flat, j: int, v: np.ndarray) -> np.ndarray:
    return np.eye(flat.n)[j][None, :] * v[:, None]


def _qd(flat, idx, j: int) -> np.ndarray:
    return flat.qd[idx, j].numpy().astype(np.float64)


def _input_sensitivity(model, flat, idx, j: int, dq, dqd, dqdd, h: float) -> np.ndarray:
    """(τ̂(x + h δ) − τ̂(x − h δ)) / 2h for an input shift δ = (dq, dqd, dqdd) on joint j."""
    out = []
    for sgn in (1.0, -1.0):
        f = copy.copy(flat)
        f.q = flat.q.clone(); f.qd = flat.qd.clone(); f.qdd = flat.qdd.clone()
        f.q[idx, j] += sgn * h * dq
        if dqd is not None:
            f.qd[idx, j] += sgn * h * dqd
        if dqdd is not None:
            f.qdd[idx, j] += sgn * h * dqdd
        out.append(predict(model, f, idx))
    return ((out[0] - out[1]) / (2 * h)).numpy().astype(np.float64)


def _delay_grid(flat) -> list[int]:
    K = flat.lag.shape[1] - 1
    return sorted({k for k in (1, 2, 3, 4, 6, 8, 10, 14, 18) if k <= K})


def _f_viscous(model, flat, idx, j):
    return [({}, _onehot(flat, j, _qd(flat, idx, j)))]


def _f_coulomb(model, flat, idx, j):
    return [({}, _onehot(flat, j, np.tanh(_qd(flat, idx, j) / COULOMB_EPS)))]


def _f_stribeck(model, flat, idx, j):
    qd = _qd(flat, idx, j)
    return [({"vs": vs}, _onehot(flat, j, np.exp(-(qd / vs) ** 2) * np.tanh(qd / COULOMB_EPS))) for vs in VS_GRID]


def _f_bias(model, flat, idx, j):
    return [({}, _onehot(flat, j, np.ones(len(idx))))]


def _f_gain(model, flat, idx, j):
    te = flat.tau_e[idx, j].numpy().astype(np.float64)
    own = te - exo_copy(flat, j).tau_e[idx, j].numpy().astype(np.float64)
    return [({}, _onehot(flat, j, te)), ({"own_variation": True}, _onehot(flat, j, own))]


def _f_delay(model, flat, idx, j):
    te = flat.tau_e[:, j].numpy().astype(np.float64)
    lag = flat.lag[idx].numpy()
    return [({"d": k * flat.dt}, _onehot(flat, j, te[lag[:, 0]] - te[lag[:, k]])) for k in _delay_grid(flat)]


def _f_offset(model, flat, idx, j):
    return [({}, _input_sensitivity(model, flat, idx, j, torch.full((len(idx),), -1.0), None, None, 1e-2))]


def _f_strap(model, flat, idx, j):
    # parameter = compliance 1/k; the shift is −τ_e/k (and its derivatives); h in rad/(N m)
    return [({}, _input_sensitivity(model, flat, idx, j, -flat.tau_e[idx, j], -flat.tau_e_d[idx, j],
                                    -flat.tau_e_dd[idx, j], 1e-4))]


def _f_backlash(model, flat, idx, j):
    # parameter = width w; the limb is at q + (w/2) s (and its derivatives), s the side of the gap (`gap_side`)
    return [({}, _input_sensitivity(model, flat, idx, j, 0.5 * flat.side[idx, j], 0.5 * flat.side_d[idx, j],
                                    0.5 * flat.side_dd[idx, j], 1e-3))]


@dataclass(frozen=True)
class Candidate:
    """One effect of the vocabulary and its own behaviour in the diagnosis: how its parameter is read off a
    fitted `ExtendedModel` (`theta`), started from the post-hoc screen (`start`), reported (a strap's θ is its
    compliance, reported as k = 1/θ: `inverse`), bounded (`positive`, a delay by the largest delay searched:
    `bounded_by_max_delay`), which nulls it faces (`needs_exo`; a gain, which has no lag of its own, also at
    the controller's tracking lag and on its own variation: `lag_free`), which shape parameter it carries
    (`shape`: Stribeck's vs), which detection
    limit warns that it reads short (`limit_key`) and how a known size of it is written into the recorded torque
    (`inject`: the detection limits by injection)."""
    effect: str
    meaning: str
    sign: str                     # the physically valid sign of the reported parameter
    unit_revolute: str
    unit_prismatic: str
    kind: str                     # finding | absorbable
    neutral: float                # parameter value of "no effect"
    needs_exo: bool = False
    positive: bool = False        # the parameter must be > neutral (dissipation, delay, stiffness)
    inverse: bool = False         # θ (what the model fits) is 1 / the reported parameter (strap: compliance 1/k)
    bounded_by_max_delay: bool = False
    lag_free: bool = False
    shape: str | None = None      # the init key of a nonlinear shape parameter fitted beside θ (Stribeck: vs)
    shape_default: float = 0.1
    limit_key: str | None = None
    domain_lo: float = -float("inf")   # the reported parameter's physical domain lies above this (`sign`)
    linear: bool = False          # adds θ times a signal of the motion: its held-out gain grows as θ² (`size_limit`)
    start: Callable | None = field(default=None, compare=False, repr=False)      # (screen θ, screen) -> {value}
    theta: Callable | None = field(default=None, compare=False, repr=False)      # (model, j) -> (raw, θ())
    inject: Callable | None = field(default=None, compare=False, repr=False)     # (τ_e, θ, lengths, dt) -> Δτ_rec
    features: Callable | None = field(default=None, compare=False, repr=False)   # (model, flat, rows, j) -> [(extra, F)]

    def unit(self, joint_type: str) -> str:
        return self.unit_prismatic if joint_type == "prismatic" else self.unit_revolute

    def outside_domain(self, ci) -> bool:
        """True when the whole interval lies outside the parameter's physical domain (a negative gain, a
        negative damping): such a term is not this effect but absorbs something else in the data."""
        return ci[1] <= self.domain_lo

    @property
    def theta_neutral(self) -> float:
        """The no-effect value of the fitted θ (`raw_and_theta`; a strap's compliance: 0)."""
        return 0.0 if self.inverse else self.neutral

    def raw_and_theta(self, model, j: int):
        """The raw parameter vector of the effect in `model` and a function giving its physical θ on joint j."""
        if self.theta is None:
            raise ValueError(self.effect)
        return self.theta(model, j)

    def injected(self, te: torch.Tensor, th: float, lengths, dt: float) -> torch.Tensor:
        """What the effect at fitted size θ adds to the recorded joint torque, given the recorded exo torque te
        (flat rows, trials of `lengths` samples): the detection limits by injection write it into the data."""
        if self.inject is None:
            raise ValueError(self.effect)
        return self.inject(te, th, lengths, dt)

    def screen_init(self, sc: dict) -> dict:
        """Warm start of the physical parameter from the post-hoc screen `sc` (right sign; Stribeck's vs too)."""
        init = {}
        if self.start is not None:
            v = self.start(float(sc.get("theta", 0.0)), sc)
            if "value" in v:
                init[self.effect] = v["value"]
        if self.shape is not None and self.shape.split("_")[-1] in sc:
            init[self.shape] = sc[self.shape.split("_")[-1]]
        return init

    def report_param(self, pci: dict) -> tuple[float, list[float]]:
        """Vocabulary parameter and CI of a fitted θ (strap: k = 1/compliance)."""
        est, (lo, hi) = pci["estimate"], pci["ci"]
        if self.inverse:
            k = 1.0 / est if est > 0 else float("inf")
            return k, [1.0 / hi if hi > 0 else float("inf"), 1.0 / lo if lo > 0 else float("inf")]
        return est, [lo, hi]

    def within_bounds(self, ci: list[float]) -> list[float]:
        """A reported interval cut at the end of the parameter's space: a damping, friction or delay is ≥ its
        no-effect value by construction (a normal interval widened by the refit spread may reach below it);
        a strap's k = 1/compliance already ends at ∞ (`report_param`)."""
        if self.positive and not self.inverse:
            return [max(ci[0], self.neutral), ci[1]]
        return list(ci)


LIBRARY: dict[str, Candidate] = {c.effect: c for c in [
    Candidate("viscous_damping", "joint friction proportional to velocity: torque −b q̇ dissipates b q̇² of power",
              "b ≥ 0", "N m s/rad", "N s/m", "finding", 0.0, positive=True, domain_lo=0.0, start=_start_positive,
              linear=True, features=_f_viscous, theta=lambda m, j: (m.damping_diag, lambda: float(m.damping_matrix()[j, j]))),
    Candidate("coulomb_friction", "dry friction of constant magnitude opposing motion: −Fc sign(q̇)",
              "Fc ≥ 0", "N m", "N", "finding", 0.0, positive=True, domain_lo=0.0, start=_start_positive,
              linear=True, features=_f_coulomb, theta=lambda m, j: (m.coulomb_raw, lambda: float(m.coulomb()[j]))),
    Candidate("stribeck_friction", "static friction in excess of Coulomb that vanishes above a Stribeck velocity vs: "
              "−Fs exp(−(q̇/vs)²) sign(q̇)", "Fs ≥ 0, vs > 0", "N m", "N", "finding", 0.0, positive=True,
              shape="stribeck_vs", domain_lo=0.0, start=_start_positive,
              features=_f_stribeck, theta=lambda m, j: (m.stribeck_fs_raw, lambda: float(m.stribeck()[0][j]))),
    Candidate("actuation_delay", "the exoskeleton applies its recorded torque d seconds late: τ_e,app(t) = τ_e,rec(t−d)",
              "d ≥ 0", "s", "s", "finding", 0.0, needs_exo=True, positive=True, bounded_by_max_delay=True,
              limit_key="d_limit", domain_lo=0.0, start=_start_delay, inject=_inject_delay,
              features=_f_delay, theta=lambda m, j: (m.delay_raw, lambda: float(m.delay()[j]))),
    Candidate("torque_gain", "the torque sensor reads k times the applied exoskeleton torque",
              "k > 0", "1", "1", "finding", 1.0, needs_exo=True, lag_free=True, domain_lo=0.0, start=_start_gain,
              inject=_inject_gain, features=_f_gain, theta=lambda m, j: (m.gain_raw, lambda: float(1.0 / (1.0 - m.gain_term()[j])))),
    Candidate("strap_compliance", "a spring of stiffness k between exoskeleton and limb: the encoder reads the limb "
              "angle plus τ_e,app / k", "k > 0", "N m/rad", "N/m", "finding", float("inf"), needs_exo=True,
              positive=True, inverse=True, domain_lo=0.0, start=_start_inverse,
              features=_f_strap, theta=lambda m, j: (m.compliance_raw, lambda: float(m.compliance()[j]))),
    Candidate("encoder_offset", "a constant angle offset of the encoder: q_meas = q + δ", "any", "rad", "m",
              "absorbable", 0.0, start=_start_any,
              features=_f_offset, theta=lambda m, j: (m.offset_raw, lambda: float(m.encoder_offset()[j]))),
    Candidate("torque_bias", "a constant offset of the recorded torque: τ_rec = τ + τ0", "any", "N m", "N",
              "absorbable", 0.0, start=_start_any,
              features=_f_bias, theta=lambda m, j: (m.bias_raw, lambda: float(m.torque_bias()[j]))),
    Candidate("payload", "mass added to a segment (changes inertia and gravity)", "m ≥ 0", "kg", "kg",
              "absorbable", 0.0),
    Candidate("backlash", "play of width w in the transmission: the encoder lags the limb by w/2 after a reversal",
              "w ≥ 0", "rad", "m", "finding", 0.0, positive=True, domain_lo=0.0, start=_start_positive,
              features=_f_backlash, theta=lambda m, j: (m.backlash_raw, lambda: float(m.backlash()[j]))),
]}

# rival explanations the held-out data must separate before either is accepted. A strap and a torque gain:
# the strap's deflection τ_e/k moves the coordinates at which the physics acts, so to first order it adds
# −(∂τ̂/∂q) τ_e/k, a torque in proportion to the exo torque — a torque gain whose size follows the joint's
# stiffness (measured: docs/DIAGNOSIS.md, "Measurements behind the code"). A backlash and Coulomb friction: both
# change the torque in a step at every reversal
CONFUSABLE = [("actuation_delay", "viscous_damping"), ("coulomb_friction", "stribeck_friction"),
              ("actuation_delay", "strap_compliance"), ("torque_gain", "strap_compliance"),
              ("coulomb_friction", "backlash")]

# rivals one of which reduces to the other in a limit: an excess static friction that vanishes above vs,
# Fs e^{−(q̇/vs)²} tanh(q̇/ε), is Coulomb friction as vs → ∞. Where held-out data cannot separate such a pair,
# the simpler term explains them as well with a parameter fewer (parsimony), so it is the one taken.
NESTS = {"stribeck_friction": ("coulomb_friction", "vs → ∞")}     # effect: (what it reduces to, in which limit)


def nested_choice(group: list[dict]) -> dict | None:
    """The member of an inseparable rival set (dicts with "effect") that every other member reduces to
    (`NESTS`), or None when the set is not nested."""
    for e in group:
        if all(o is e or NESTS.get(o["effect"], ("",))[0] == e["effect"] for o in group):
            return e
    return None

# effects fitted jointly with the model (a payload has no term: reported by rule)
FITTED = ("viscous_damping", "coulomb_friction", "stribeck_friction", "actuation_delay", "torque_gain",
          "strap_compliance", "encoder_offset", "torque_bias", "backlash")


def rivals(effect: str) -> list[str]:
    return [b if a == effect else a for a, b in CONFUSABLE if effect in (a, b)]


def library_table() -> str:
    """Markdown table of the library, for the report."""
    rows = ["| effect | meaning | sign | unit (revolute / prismatic) | kind |", "|---|---|---|---|---|"]
    for c in LIBRARY.values():
        rows.append(f"| `{c.effect}` | {c.meaning} | {c.sign} | {c.unit_revolute} / {c.unit_prismatic} | {c.kind} |")
    return "\n".join(rows)


def blank_entry(effect: str, j: int, flat, subjects: list):
    """A candidate's verdict before any test (`results.Verdict`): effect, joint, the users it concerns, unit and
    kind (the same fields on the physics-first and the learned path)."""
    from .results import Verdict

    c = LIBRARY[effect]
    return Verdict(effect=effect, joint=flat.joints[j], subjects=subjects, unit=c.unit(flat.joint_types[j]),
                   kind=c.kind, estimate=None, ci=None, heldout_gain=None)
