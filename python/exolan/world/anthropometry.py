"""Users and their legs: segment parameters from standard anthropometric tables.

Segment mass fractions, centre-of-mass positions and radii of gyration are Winter's
(Biomechanics and Motor Control of Human Movement, 4th ed., 2009, table 4.1); segment lengths as
fractions of body height are Drillis & Contini's (as tabulated by Winter, fig. 4.1). The foot is
lumped into the shank (the ankle is not actuated by this exoskeleton and not modelled), so the
shank-foot body's centre of mass lies off the shank axis: it is described by a distance ``r2`` from
the knee and an angle ``beta2`` from the shank axis toward the front.

Exoskeleton segments (thigh cuff + knee actuator on the thigh, shank cuff on the shank) add mass
at fixed fractions of the segment; the hip actuator sits on the pelvis and does not load the leg.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Winter (2009) table 4.1: mass fraction of body mass, COM from proximal end as fraction of
# segment length, radius of gyration about the COM as fraction of segment length.
WINTER = {
    "thigh": dict(mass=0.100, com=0.433, rg=0.323),
    "shank": dict(mass=0.0465, com=0.433, rg=0.302),
    "foot": dict(mass=0.0145, com=0.50, rg=0.475),
}
# Drillis & Contini segment lengths as fractions of height H.
LEN_THIGH = 0.245   # hip (greater trochanter) to knee
LEN_SHANK = 0.246   # knee to ankle
ANKLE_HEIGHT = 0.039  # ankle to sole
FOOT_LENGTH = 0.152
HEEL_TO_ANKLE = 0.035  # horizontal distance heel -> ankle (about a quarter of the foot length)

# Exoskeleton segment masses (kg) and where they sit (fraction of segment length from the
# proximal joint): a hip-knee device of the EPIC type has ~1.6 kg on each thigh (cuff, knee
# motor) and ~0.5 kg on each shank (cuff, strut).
EXO_THIGH = dict(mass=1.6, at=0.75, rg=0.25)
EXO_SHANK = dict(mass=0.5, at=0.35, rg=0.30)

G = 9.81  # m/s^2


@dataclass
class User:
    name: str
    mass: float       # kg
    height: float     # m
    style: dict = field(default_factory=dict)  # per-user gait style (amplitude, period factors, ...)


@dataclass
class LegParams:
    """Planar 2-link leg: link 1 thigh, link 2 shank with the foot lumped.

    Link 1 COM on the thigh axis at c1 from the hip; link 2 COM at distance r2 from the knee,
    rotated by beta2 from the shank axis toward the front. I1, I2 are about the COMs.
    """
    m1: float
    c1: float
    I1: float
    l1: float
    m2: float
    r2: float
    beta2: float
    I2: float
    l2: float             # knee to ankle
    ankle_height: float   # ankle to sole
    heel_to_ankle: float
    foot_length: float

    def with_payload(self, segment: str, kg: float) -> "LegParams":
        """Point mass ``kg`` added at the segment's COM (payload effect): the COM stays, the
        mass grows, the inertia about the COM is unchanged (a point mass at the COM)."""
        p = LegParams(**self.__dict__)
        if segment == "thigh":
            p.m1 += kg
        elif segment == "shank":
            p.m2 += kg
        else:
            raise ValueError(f"unknown segment {segment!r}")
        return p


def _combine(parts):
    """Masses at 2-D points with own inertias -> (mass, com (2,), inertia about com)."""
    m = sum(p[0] for p in parts)
    com = sum(p[0] * np.asarray(p[1], float) for p in parts) / m
    inertia = sum(p[2] + p[0] * float(np.sum((np.asarray(p[1], float) - com) ** 2)) for p in parts)
    return m, com, inertia


def leg_params(user: User, exo: bool = True, seg_scale: float = 1.0) -> LegParams:
    """Segment parameters of one leg of ``user`` (plus the exoskeleton segments when ``exo``).

    ``seg_scale`` scales segment mass fractions per user (people differ from the table mean).
    Shank-frame coordinates: (along the shank axis from the knee, forward perpendicular).
    """
    M, H = user.mass, user.height
    l1, l2 = LEN_THIGH * H, LEN_SHANK * H
    ha, lf, hta = ANKLE_HEIGHT * H, FOOT_LENGTH * H, HEEL_TO_ANKLE * H
    w = WINTER
    # thigh (+ exo thigh), points along the axis: (distance from hip, 0)
    thigh = [(seg_scale * w["thigh"]["mass"] * M, (w["thigh"]["com"] * l1, 0.0),
              seg_scale * w["thigh"]["mass"] * M * (w["thigh"]["rg"] * l1) ** 2)]
    shank = [(seg_scale * w["shank"]["mass"] * M, (w["shank"]["com"] * l2, 0.0),
              seg_scale * w["shank"]["mass"] * M * (w["shank"]["rg"] * l2) ** 2)]
    # foot: COM half-way along the foot, half the ankle height below the ankle
    mf = seg_scale * w["foot"]["mass"] * M
    shank.append((mf, (l2 + 0.5 * ha, 0.5 * lf - hta), mf * (w["foot"]["rg"] * lf) ** 2))
    if exo:
        thigh.append((EXO_THIGH["mass"], (EXO_THIGH["at"] * l1, 0.0),
                      EXO_THIGH["mass"] * (EXO_THIGH["rg"] * l1) ** 2))
        shank.append((EXO_SHANK["mass"], (EXO_SHANK["at"] * l2, 0.0),
                      EXO_SHANK["mass"] * (EXO_SHANK["rg"] * l2) ** 2))
    m1, com1, I1 = _combine(thigh)
    m2, com2, I2 = _combine(shank)
    return LegParams(m1=m1, c1=float(com1[0]), I1=I1, l1=l1, m2=m2,
                     r2=float(np.hypot(com2[0], com2[1])), beta2=float(np.arctan2(com2[1], com2[0])),
                     I2=I2, l2=l2, ankle_height=ha, heel_to_ankle=hta, foot_length=lf)


def make_users(n: int, rng: np.random.Generator) -> list[User]:
    """``n`` users S01..Sn: height ~ N(1.74, 0.08) m, BMI 19-29, mass clipped to 50-100 kg,
    and a gait style (amplitude, cadence, posture offsets) drawn per user."""
    users = []
    for i in range(n):
        h = float(np.clip(rng.normal(1.74, 0.08), 1.55, 1.95))
        m = float(np.clip(rng.uniform(19.0, 29.0) * h * h, 50.0, 100.0))
        style = dict(
            amp=float(rng.uniform(0.88, 1.12)),          # joint excursion scale
            period=float(rng.uniform(0.9, 1.1)),         # cadence scale (1/speed)
            hip_off=float(rng.normal(0.0, 3.0)),         # deg, posture
            knee_off=float(rng.normal(0.0, 2.0)),        # deg
            harm=rng.normal(0.0, 0.06, size=(2, 8)),     # relative perturbation of Fourier coefficients
            seg_scale=float(rng.uniform(0.93, 1.07)),    # segment mass fractions vs the table
            load=float(rng.uniform(0.95, 1.08)),         # GRF peak style
            cop_off=float(rng.normal(0.0, 0.005)),       # m, lateral CoP habit
            assist=float(rng.uniform(0.7, 1.3)),         # exoskeleton assistance level for this user
        )
        users.append(User(name=f"S{i + 1:02d}", mass=round(m, 1), height=round(h, 3), style=style))
    return users
