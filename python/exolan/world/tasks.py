"""The 28 tasks: kinematic templates, stance schedules and load profiles.

Each task is a cycle (a stride, a squat, a lunge pair, ...) whose joint-angle shapes are given as
keypoints (phase in [0, 1), degrees) in the style of textbook gait curves (Winter 2009; Perry's
gait phases), turned into a smooth periodic function (periodic cubic spline -> 8 Fourier
harmonics) so that q, qd, qdd are analytic. Variation comes from:
  * the user's style (amplitude, cadence, posture offsets, perturbed harmonics),
  * per-cycle variation: a slowly modulated phase speed, amplitude and posture offset,
  * for unstructured tasks, irregular events (Gaussian bumps: catching, cutting, stepping over).

Stance: ``duty`` < 1 means the foot is on the ground for the first ``duty`` of its cycle (a
phase-based schedule, as gait events are); ``duty`` = 1 means both feet stay on the ground
(standing, squatting, lunging, ...). The vertical force profile over stance is
sin(pi s) + k3 sin(3 pi s) (the double hump of walking for k3 > 0) plus an impact transient, scaled
so that the two feet carry the body weight on average over a cycle.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.interpolate import CubicSpline

N_HARM = 8

CYCLIC, IMPEDANCE, UNSTRUCTURED = "cyclic", "impedance", "unstructured"

PAPER_TRAIN_TASKS = ("walk", "stand", "calisthenics", "push_pull", "jump_in_place", "turn", "cut")


@dataclass(frozen=True)
class TaskSpec:
    group: str
    period: float                 # s, nominal cycle duration
    hip: tuple                    # keypoints ((phase, deg), ...)
    knee: tuple
    duty: float = 1.0             # stance fraction of the cycle; 1 = feet always on the ground
    offset: float = 0.5           # phase of the right leg relative to the left (0.5 alternating)
    k3: float = 0.0               # double-hump factor of the vertical force
    impact: float = 0.0           # impact transient (relative)
    rate_var: float = 0.04        # depth of the phase-speed modulation
    amp_var: float = 0.06         # depth of the amplitude modulation
    bumps: tuple = ()             # (events per s, hip deg, knee deg, width s)
    carry: float = 0.0            # carried load as a fraction of body mass
    lean: float = 0.0             # horizontal force tilt (external pushing/pulling), tan of angle
    shift: float = 0.1            # weight shift between the feet (duty = 1 tasks)
    load: tuple = ()              # duty = 1: keypoints of the fraction of weight on the feet (chair)
    cop: tuple = (0.08, 0.85)     # CoP travel heel -> toe, fractions of the foot length
    reverse: bool = False         # the cycle runs backwards (backward walking)
    grf: str = "hip"              # "hip": GRF aims near the hip; "vertical": quasi-static tasks
    tilt: float = 0.08            # pelvis anterior tilt per rad of mean hip flexion (trunk lean)
    seconds: float = 20.0         # default trial duration


WALK_HIP = ((0, 27), (.15, 24), (.35, 8), (.55, -9), (.62, -6), (.75, 14), (.88, 28))
WALK_KNEE = ((0, 4), (.13, 17), (.35, 5), (.5, 9), (.62, 38), (.72, 60), (.83, 42), (.92, 15), (.98, 5))

TASK_SPECS: dict[str, TaskSpec] = {
    # --- cyclic ---------------------------------------------------------------------------
    "walk": TaskSpec(CYCLIC, 1.1, WALK_HIP, WALK_KNEE, duty=.61, k3=.25, impact=.1),
    "run": TaskSpec(CYCLIC, .72, ((0, 30), (.2, 12), (.38, -12), (.5, 2), (.7, 45), (.88, 38)),
                    ((0, 20), (.14, 40), (.38, 20), (.55, 75), (.7, 100), (.88, 40)),
                    duty=.38, impact=.35, cop=(.35, .85)),
    "incline_walk": TaskSpec(CYCLIC, 1.15, ((0, 40), (.15, 35), (.35, 15), (.58, -5), (.75, 25), (.9, 42)),
                             ((0, 15), (.15, 22), (.4, 8), (.62, 45), (.73, 68), (.9, 30)), duty=.62, k3=.2),
    "decline_walk": TaskSpec(CYCLIC, 1.1, ((0, 20), (.2, 18), (.45, 0), (.6, -8), (.78, 12), (.9, 22)),
                             ((0, 8), (.2, 30), (.45, 25), (.6, 45), (.72, 65), (.88, 20)), duty=.62, k3=.3,
                             impact=.15),
    "stairs_up": TaskSpec(CYCLIC, 1.3, ((0, 60), (.2, 45), (.45, 10), (.62, 8), (.8, 55), (.92, 65)),
                          ((0, 60), (.2, 45), (.45, 10), (.6, 25), (.78, 95), (.92, 75)), duty=.62, k3=.2,
                          cop=(.3, .8)),
    "stairs_down": TaskSpec(CYCLIC, 1.2, ((0, 10), (.3, 18), (.55, 22), (.7, 30), (.85, 20)),
                            ((0, 10), (.15, 25), (.35, 35), (.55, 80), (.72, 95), (.9, 30)), duty=.6, k3=.35, impact=.2,
                            cop=(.4, .6)),
    "backward_walk": TaskSpec(CYCLIC, 1.3, WALK_HIP, WALK_KNEE, duty=.62, k3=.2, reverse=True, cop=(.85, .1)),
    "weighted_walk": TaskSpec(CYCLIC, 1.2, WALK_HIP, WALK_KNEE, duty=.63, k3=.25, impact=.1, carry=.2),
    "side_shuffle": TaskSpec(CYCLIC, .7, ((0, 20), (.5, 30)), ((0, 30), (.3, 40), (.6, 50)), duty=.7,
                             impact=.1, cop=(.3, .7)),
    "jump_in_place": TaskSpec(CYCLIC, .65, ((0, 10), (.2, 35), (.45, 8), (.6, 15), (.8, 25), (.95, 12)),
                              ((0, 20), (.2, 65), (.45, 10), (.6, 25), (.8, 35), (.95, 20)),
                              duty=.55, offset=0.0, impact=.5, cop=(.5, .75)),
    "calisthenics": TaskSpec(CYCLIC, 1.0, ((0, 10), (.25, 5), (.45, 8), (.6, 45), (.75, 75), (.9, 35)),
                             ((0, 15), (.2, 25), (.45, 15), (.6, 60), (.75, 100), (.9, 45)), duty=.5, impact=.25,
                             rate_var=.15, amp_var=.2, cop=(.4, .8)),
    # --- impedance-like (feet on the ground, the body moves against loads) -----------------
    "stand": TaskSpec(IMPEDANCE, 5.0, ((0, 4), (.5, 7)), ((0, 3), (.5, 6)), rate_var=.3, amp_var=.4,
                      shift=.3, grf="vertical"),
    "squat": TaskSpec(IMPEDANCE, 3.5, ((0, 6), (.25, 50), (.5, 95), (.75, 50)),
                      ((0, 4), (.25, 55), (.5, 105), (.75, 55)), offset=0.0, grf="vertical"),
    "sit_to_stand": TaskSpec(IMPEDANCE, 5.0, ((0, 85), (.25, 88), (.4, 60), (.55, 8), (.75, 8), (.9, 60)),
                             ((0, 90), (.25, 92), (.45, 50), (.55, 8), (.75, 8), (.92, 70)), offset=0.0,
                             load=((0, .2), (.25, .2), (.4, 1.05), (.55, 1), (.75, 1), (.9, .5)),
                             grf="vertical"),
    "lunge": TaskSpec(IMPEDANCE, 6.0, ((0, 5), (.12, 60), (.25, 75), (.38, 40), (.5, 5), (.62, -5), (.75, -12),
                                       (.88, -5)),
                      ((0, 5), (.12, 60), (.25, 95), (.38, 50), (.5, 5), (.62, 45), (.75, 90), (.88, 40)),
                      shift=.3, grf="hip"),
    "lift_weight": TaskSpec(IMPEDANCE, 4.0, ((0, 6), (.25, 55), (.5, 100), (.75, 55)),
                            ((0, 4), (.25, 50), (.5, 90), (.75, 50)), offset=0.0, carry=.15, grf="vertical"),
    "push_pull": TaskSpec(IMPEDANCE, 2.0, ((0, 15), (.5, 25)), ((0, 15), (.5, 30)), lean=.15, shift=.3,
                          rate_var=.1, grf="vertical"),
    "tug_of_war": TaskSpec(IMPEDANCE, 3.0, ((0, 20), (.5, 35)), ((0, 20), (.5, 40)), lean=.2, rate_var=.3,
                           amp_var=.2, shift=.3, grf="vertical"),
    "step_up": TaskSpec(IMPEDANCE, 2.0, ((0, 55), (.3, 15), (.55, 5), (.75, 40), (.9, 65)),
                        ((0, 70), (.3, 20), (.55, 5), (.75, 60), (.9, 85)), duty=.7, k3=.15, cop=(.3, .7)),
    "poses": TaskSpec(IMPEDANCE, 12.0, ((0, 10), (.25, 60), (.5, 20), (.75, 45)),
                      ((0, 10), (.25, 70), (.5, 30), (.75, 50)), rate_var=.3, shift=.4, grf="vertical"),
    # --- unstructured --------------------------------------------------------------------
    "ball_toss": TaskSpec(UNSTRUCTURED, 2.5, ((0, 10), (.5, 20)), ((0, 10), (.5, 25)), bumps=(.5, 20, 25, .3),
                          shift=.5, rate_var=.3, grf="vertical"),
    "cut": TaskSpec(UNSTRUCTURED, .9, WALK_HIP, WALK_KNEE, duty=.6, k3=.1, impact=.3, rate_var=.2, amp_var=.25,
                    bumps=(.4, 20, 35, .12)),
    "turn": TaskSpec(UNSTRUCTURED, 1.2, WALK_HIP, WALK_KNEE, duty=.64, k3=.2, rate_var=.25, amp_var=.3,
                     bumps=(.2, 8, 12, .2)),
    "jump_forward": TaskSpec(UNSTRUCTURED, 1.4, ((0, 20), (.2, 60), (.4, 15), (.6, 5), (.75, 45), (.9, 40)),
                             ((0, 30), (.2, 80), (.4, 15), (.6, 10), (.75, 60), (.9, 50)), duty=.65,
                             offset=0.0, impact=.6, rate_var=.2, cop=(.2, .8)),
    "start_stop": TaskSpec(UNSTRUCTURED, 1.15, WALK_HIP, WALK_KNEE, duty=.62, k3=.25, rate_var=.4, amp_var=.4),
    "meander": TaskSpec(UNSTRUCTURED, 1.15, WALK_HIP, WALK_KNEE, duty=.62, k3=.25, rate_var=.15, amp_var=.15),
    "obstacle_step": TaskSpec(UNSTRUCTURED, 1.15, WALK_HIP, WALK_KNEE, duty=.62, k3=.25, rate_var=.1,
                              bumps=(.3, 30, 45, .15)),
    "twister": TaskSpec(UNSTRUCTURED, 4.0, ((0, 10), (.25, 45), (.5, 15), (.75, 35)),
                        ((0, 10), (.25, 50), (.5, 20), (.75, 40)), rate_var=.35, bumps=(.3, 25, 30, .3),
                        shift=.6, grf="vertical"),
}

# tasks where the trunk leans forward with hip flexion (squats, landings, lunges, stairs)
for _name in ("squat", "sit_to_stand", "lift_weight", "jump_in_place", "jump_forward", "poses", "twister",
              "ball_toss", "lunge", "stairs_up"):
    TASK_SPECS[_name] = replace(TASK_SPECS[_name], tilt=0.2)

TASKS: dict[str, str] = {name: spec.group for name, spec in TASK_SPECS.items()}
assert len(TASKS) == 28 and all(t in TASKS for t in PAPER_TRAIN_TASKS)


def fourier_of_keypoints(kp) -> np.ndarray:
    """Keypoints (phase, value) -> (mean, a_1..a_N, b_1..b_N) of the periodic cubic spline."""
    ph = np.array([p for p, _ in kp], float)
    v = np.array([x for _, x in kp], float)
    ph = np.append(ph, 1.0)
    v = np.append(v, v[0])
    if len(kp) == 2:  # two keypoints: a pure cosine between them
        return np.concatenate([[v[:2].mean()], [(v[0] - v[1]) / 2], np.zeros(N_HARM - 1), np.zeros(N_HARM)])
    spl = CubicSpline(ph, v, bc_type="periodic")
    n = 256
    x = spl(np.arange(n) / n)
    X = np.fft.rfft(x) / n
    a = 2 * X.real[1:N_HARM + 1]
    b = -2 * X.imag[1:N_HARM + 1]
    return np.concatenate([[X.real[0]], a, b])


class Smooth:
    """Sum of sinusoids sum_j a_j sin(w_j t + psi_j): a smooth random signal with analytic
    derivatives (value, d/dt, d2/dt2)."""

    def __init__(self, rng, depth, period_range, n=3):
        self.w = 2 * np.pi / rng.uniform(*period_range, size=n)
        a = rng.uniform(0.5, 1.0, size=n)
        self.a = depth * a / a.sum()
        self.psi = rng.uniform(0, 2 * np.pi, size=n)

    def __call__(self, t, d=0):
        arg = np.multiply.outer(t, self.w) + self.psi
        if d == 0:
            return np.sin(arg) @ self.a
        if d == 1:
            return np.cos(arg) @ (self.a * self.w)
        return -np.sin(arg) @ (self.a * self.w ** 2)

    def integral(self, t):
        return -np.cos(np.multiply.outer(t, self.w) + self.psi) @ (self.a / self.w)


def fourier_eval(coef, phi):
    """F, dF/dphi, d2F/dphi2 of the zero-mean part of a Fourier series."""
    k = np.arange(1, N_HARM + 1)
    a, b = coef[1:N_HARM + 1], coef[N_HARM + 1:]
    arg = np.multiply.outer(phi, k)
    c, s = np.cos(arg), np.sin(arg)
    F = c @ a + s @ b
    F1 = -s @ (a * k) + c @ (b * k)
    F2 = -(c @ (a * k * k) + s @ (b * k * k))
    return F, F1, F2
