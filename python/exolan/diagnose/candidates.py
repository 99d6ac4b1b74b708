"""The library of candidate physical effects (the vocabulary of DATA_LAYOUT.md), per joint.

Each candidate states what it means physically, the sign that physics allows, its unit, how it enters the
model (DESIGN.md section 4) and its `kind`:

- `finding`: a term a conservative Lagrangian cannot represent (dissipation, lag, compliance, recording
  gain); it may be accepted when the decision rule passes.
- `absorbable`: an effect a flexible conservative model represents by itself (a constant encoder offset is a
  change of coordinates of H and V; a constant torque bias is a linear potential; a payload changes H and
  V). It is reported as absorbable, never as a finding, whatever its held-out gain.
- `not_modelled`: backlash (a hysteresis in the measured angle) has no term; it is confusable with Coulomb
  friction and strap compliance and is reported as ambiguous when those explain something, never accepted.

`neutral` is the parameter value meaning "no effect": identifiability asks that the parameter's confidence
interval exclude it. `needs_exo`: the effect acts through the recorded exoskeleton torque and cannot be
tested on data without one.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Candidate:
    effect: str
    meaning: str
    sign: str                     # the physically valid sign of the reported parameter
    unit_revolute: str
    unit_prismatic: str
    kind: str                     # finding | absorbable | not_modelled
    neutral: float                # parameter value of "no effect"
    needs_exo: bool = False
    positive: bool = False        # the parameter must be > neutral (dissipation, delay, stiffness)

    def unit(self, joint_type: str) -> str:
        return self.unit_prismatic if joint_type == "prismatic" else self.unit_revolute


LIBRARY: dict[str, Candidate] = {c.effect: c for c in [
    Candidate("viscous_damping", "joint friction proportional to velocity: torque −b q̇ dissipates b q̇² of power",
              "b ≥ 0", "N m s/rad", "N s/m", "finding", 0.0, positive=True),
    Candidate("coulomb_friction", "dry friction of constant magnitude opposing motion: −Fc sign(q̇)",
              "Fc ≥ 0", "N m", "N", "finding", 0.0, positive=True),
    Candidate("stribeck_friction", "static friction in excess of Coulomb that vanishes above a Stribeck velocity vs: "
              "−Fs exp(−(q̇/vs)²) sign(q̇)", "Fs ≥ 0, vs > 0", "N m", "N", "finding", 0.0, positive=True),
    Candidate("actuation_delay", "the exoskeleton applies its recorded torque d seconds late: τ_e,app(t) = τ_e,rec(t−d)",
              "d ≥ 0", "s", "s", "finding", 0.0, needs_exo=True, positive=True),
    Candidate("torque_gain", "the torque sensor reads k times the applied exoskeleton torque",
              "k > 0", "1", "1", "finding", 1.0, needs_exo=True),
    Candidate("strap_compliance", "a spring of stiffness k between exoskeleton and limb: the encoder reads the limb "
              "angle plus τ_e,app / k", "k > 0", "N m/rad", "N/m", "finding", float("inf"), needs_exo=True,
              positive=True),
    Candidate("encoder_offset", "a constant angle offset of the encoder: q_meas = q + δ", "any", "rad", "m",
              "absorbable", 0.0),
    Candidate("torque_bias", "a constant offset of the recorded torque: τ_rec = τ + τ0", "any", "N m", "N",
              "absorbable", 0.0),
    Candidate("payload", "mass added to a segment (changes inertia and gravity)", "m ≥ 0", "kg", "kg",
              "absorbable", 0.0),
    Candidate("backlash", "play of width w in the transmission: the encoder lags the limb by w/2 after a reversal",
              "w ≥ 0", "rad", "m", "not_modelled", 0.0),
]}

# rival explanations the held-out data must separate before either is accepted. A strap and a torque gain:
# the strap's deflection τ_e/k moves the coordinates at which the physics acts, so to first order it adds
# −(∂τ̂/∂q) τ_e/k, a torque in proportion to the exo torque — a torque gain whose size follows the joint's
# stiffness (measured: a strap world of k = 143 N m/rad, seed 1446, gave a knee "torque gain" of 1.5 that
# beat its future-torque nulls)
CONFUSABLE = [("actuation_delay", "viscous_damping"), ("coulomb_friction", "stribeck_friction"),
              ("actuation_delay", "strap_compliance"), ("torque_gain", "strap_compliance")]

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

# effects fitted jointly with the model (payload and backlash have no term: reported by rule)
FITTED = ("viscous_damping", "coulomb_friction", "stribeck_friction", "actuation_delay", "torque_gain",
          "strap_compliance", "encoder_offset", "torque_bias")


def rivals(effect: str) -> list[str]:
    return [b if a == effect else a for a, b in CONFUSABLE if effect in (a, b)]


def library_table() -> str:
    """Markdown table of the library, for the report."""
    rows = ["| effect | meaning | sign | unit (revolute / prismatic) | kind |", "|---|---|---|---|---|"]
    for c in LIBRARY.values():
        rows.append(f"| `{c.effect}` | {c.meaning} | {c.sign} | {c.unit_revolute} / {c.unit_prismatic} | {c.kind} |")
    return "\n".join(rows)


def blank_entry(effect: str, j: int, flat, subjects: list) -> dict:
    """A candidate's report entry before any test: effect, joint, the users it concerns, unit and kind (the same
    keys on the physics-first and the learned path)."""
    c = LIBRARY[effect]
    return dict(effect=effect, joint=flat.joints[j], subjects=subjects, unit=c.unit(flat.joint_types[j]), kind=c.kind,
                estimate=None, ci=None, heldout_gain=None)
