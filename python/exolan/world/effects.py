"""Injected effects: parsing, the ground-truth record and units (DATA_LAYOUT.md vocabulary).

The physics of each effect lives where it acts (generate.py, ``TrialWorld``); its semantics follow
DESIGN.md section 4:
  viscous_damping   b:      torque -b qd on the limb (the human supplies +b qd more)
  coulomb_friction  Fc:     -Fc tanh(qd / eps), eps = 0.01 rad/s
  stribeck_friction Fs, vs: -Fs exp(-(qd/vs)^2) tanh(qd / eps)
  actuation_delay   d:      applied exo torque(t) = recorded(t - d)
  encoder_offset    delta:  q_meas = q + delta
  torque_bias       tau0:   recorded = applied + tau0
  torque_gain       k:      recorded = k applied
  strap_compliance  k:      q_meas = q + applied / k
  backlash          width:  q_meas = play(q, width)
  payload           m:      kg added at the COM of the thigh (joint hip) or shank (joint knee)
"""
from __future__ import annotations

from dataclasses import dataclass

UNITS = {
    "viscous_damping": "N m s/rad",
    "coulomb_friction": "N m",
    "stribeck_friction": "N m, rad/s",
    "actuation_delay": "s",
    "encoder_offset": "rad",
    "torque_bias": "N m",
    "torque_gain": "1",
    "strap_compliance": "N m/rad",
    "backlash": "rad",
    "payload": "kg",
}
N_PARAMS = {name: 2 if name == "stribeck_friction" else 1 for name in UNITS}
COULOMB_EPS = 0.01  # rad/s, as in the model (DESIGN.md section 4)
JOINTS = ("hip", "knee")


@dataclass(frozen=True)
class Effect:
    effect: str
    joint: str                 # "hip" | "knee"
    value: float | tuple       # one number, or (Fs, vs) for stribeck_friction
    subjects: tuple | None = None   # None = every subject

    def applies_to(self, subject: str) -> bool:
        return self.subjects is None or subject in self.subjects

    def record(self, all_subjects) -> dict:
        subj = list(self.subjects) if self.subjects is not None else list(all_subjects)
        value = list(self.value) if isinstance(self.value, tuple) else self.value
        return {"effect": self.effect, "joint": self.joint, "subjects": subj, "value": value,
                "unit": UNITS[self.effect]}


def validate(e: Effect) -> Effect:
    if e.effect not in UNITS:
        raise ValueError(f"unknown effect {e.effect!r}; known: {', '.join(UNITS)}")
    if e.joint not in JOINTS:
        raise ValueError(f"effect {e.effect}: joint must be hip, knee or both, not {e.joint!r}")
    vals = e.value if isinstance(e.value, tuple) else (e.value,)
    if len(vals) != N_PARAMS[e.effect]:
        raise ValueError(f"effect {e.effect} takes {N_PARAMS[e.effect]} value(s), got {len(vals)}")
    v0 = vals[0]
    if e.effect in ("viscous_damping", "coulomb_friction", "stribeck_friction", "actuation_delay",
                    "backlash", "payload") and v0 < 0:
        raise ValueError(f"effect {e.effect}: a negative value ({v0}) is not physical")
    if e.effect in ("strap_compliance", "torque_gain") and v0 <= 0:
        raise ValueError(f"effect {e.effect}: value must be > 0, got {v0}")
    if e.effect == "stribeck_friction" and vals[1] <= 0:
        raise ValueError("stribeck_friction: vs must be > 0")
    if e.effect == "actuation_delay" and v0 > 0.2:
        raise ValueError("actuation_delay above 0.2 s is outside the simulated pre-roll")
    return e


def parse_effect(text: str) -> list[Effect]:
    """``NAME:JOINT:VALUE[:SUBJECTS]`` -> effects (JOINT ``both`` gives one per joint).
    VALUE: comma-separated for multi-parameter effects (stribeck ``Fs,vs``); SUBJECTS: '+'-separated."""
    parts = text.split(":")
    if len(parts) not in (3, 4):
        raise ValueError(f"effect {text!r}: expected NAME:JOINT:VALUE[:SUBJECTS]")
    name, joint, value = parts[0].strip(), parts[1].strip(), parts[2]
    try:
        vals = tuple(float(v) for v in value.split(","))
    except ValueError:
        raise ValueError(f"effect {text!r}: VALUE {value!r} is not a number (or comma-separated numbers)")
    val = vals[0] if len(vals) == 1 else vals
    subjects = None
    if len(parts) == 4 and parts[3].strip():
        subjects = tuple(s.strip() for s in parts[3].split("+") if s.strip())
    joints = JOINTS if joint == "both" else (joint,)
    return [validate(Effect(name, j, val, subjects)) for j in joints]


def coerce(effects) -> list[Effect]:
    """Accept Effect objects, spec strings or dicts (the effects.json shape)."""
    out = []
    for e in effects or []:
        if isinstance(e, Effect):
            out.append(validate(e))
        elif isinstance(e, str):
            out.extend(parse_effect(e))
        elif isinstance(e, dict):
            v = e["value"]
            v = tuple(float(x) for x in v) if isinstance(v, (list, tuple)) else float(v)
            subj = e.get("subjects")
            joints = JOINTS if e.get("joint") == "both" else (e["joint"],)
            for j in joints:
                out.append(validate(Effect(e["effect"], j, v, tuple(subj) if subj is not None else None)))
        else:
            raise TypeError(f"cannot interpret effect {e!r}")
    return out
