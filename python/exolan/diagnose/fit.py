"""Data preparation, the slow-context base model and the joint (warm-start) refits of the diagnosis.

Why a slow context: a context encoder that sees a 315 ms window of q, q̇ and forces can make g(q, z) and
B(q, z) f_v vary within a stride and imitate damping, friction or lag (DIAGNOSIS_PITFALLS.md). The
diagnosis therefore judges a DeLaN + LIM whose context z is a *learned constant per trial* (one code per
recording, e.g. one user's leg in one task): it carries body size, mass and the trial's mean loading, but
cannot carry q̇ within a step. A given run (`--model`) is used the same way: its encoder's z is pooled
(averaged) over each trial and becomes that trial's code (`PooledContext`). A run's networks were trained with
a z that moves within a stride; at the pooled z they misfit, so by default (`Settings.adapt_model`) the
diagnosis first fits the pooled model, with the terms below, to the training segments, with its own base's
schedule; the run's weights are the starting point (and an extended model starts there too, its terms present
from the first step, as `refits.fresh_fit` does for a base trained here). Measured (an `exolan` run trained
300 epochs on a world of 2 users × walk, squat, calisthenics, turn × 16 s with a knee damping of 1.06 N m s/rad,
seed 5962; test settings): judged as given, the reference's held-out MSE was 0.0177 (N m/kg)², the refit noise
σ_r 2.9e-4, and the damping was missed (0.60, within the noise); adapted, 2.4e-3 and 3.6e-6, and the damping was
found at 1.05. Adapted with the refits' smaller step the damping came out 0.84 (warm start); and with a CoP
correction that did not see z, a clean world (seed 6394) accepted a hip Coulomb friction of 0.38 N m.

Why the other leg's insole force: the hip rides on the pelvis, whose vertical acceleration is set by the
ground reaction of *both* feet (Newton on the whole body: M a_p = f_v,left + f_v,right − M g). In the hip
frame that acceleration changes the effective gravity on the leg (d'Alembert): the gravity torque scales
with the total vertical load, g(q)(f_v,own + f_v,other)/(M g). The leg's own share is within reach of the
insole mapping B(q, z) f_v; the other leg's share is not measured on this leg. Unmodelled, it leaves a hip
residual that follows the gait cycle and that damping, friction or an exo gain soak up, worst in jumps and
calisthenics. Where a trial's partner (same subject and recording, other side) exists, the base therefore
adds κ ⊙ g(q, z) f_v,other/(M g) with one learned gain κ per joint: the shape of the term is the model's own
gravity torque, so unlike a free second insole network it cannot imitate a velocity-dependent torque (a
free network B_o(q, z) f_v,other halved a planted knee damping in a measured world). It is part of the
diagnosis base only: the engine's weight format has one insole input, so an exported extended model leaves
it out (its metadata says so).

Why the pelvis's fore-aft acceleration and the centre of pressure (`Settings.pelvis_surge`, on by default,
both need a partner): the pelvis also accelerates forwards and backwards (braking early in stance, pushing
late), and in the hip frame that acts on the leg like a horizontal gravity. Insoles measure no shear force,
but a loaded foot's ground force points roughly from its centre of pressure at the body above the hip, so both
insoles with both legs' angles give an estimate (`PelvisSurge`: eleven learned scalars, no network).
And a foot's contact torque moves with its centre of pressure, which travels some 0.2 m from heel to toe: the
LIM's lever arms B(q, z) see only q, so the base adds d ⊙ f_v x_cop (`cop_torque`, one scalar per joint).
Measured (the base alone: `make_base` + `train`, 1500 steps, hidden 64, on a clean simulated world of 2 users
× walk, squat, calisthenics, turn × 16 s, seed 12; one fit each): held-out hip MSE 8.27e-3 → 7.32e-3 (surge) →
4.79e-3 (surge + CoP) (N m/kg)², knee 2.22e-3 → 2.04e-3 → 1.74e-3. With the world's pelvis fore-aft
acceleration switched off, the clean hip's pseudo-damping (0.37 N m s/rad accepted in a 3-user world) and a
+24 % bias of a planted hip Coulomb friction (2.78 → 3.46 N m) disappeared (found 2.86) — the motive for the
term.

Why the insole mapping sees the centre of pressure (`Settings.lim_cop`, on by default, needs a partner: the
CoP travels in `Flat.forces`): the insoles measure no shear, and the ground force's moment about the hip is
mostly that of its unmeasured horizontal part (a lever of the hip's height). Where the force aims changes over
the stance (ahead of the hip in loading, behind it at push-off), and the stance phase is what the CoP's
heel-to-toe travel tracks; the joint angles alone do not pin it down, and a slow context cannot carry it. So
the lever arms are B(q, x_cop, z) (one more input to the LIM; 0 force, 0 torque, so it cannot act in swing).
Measured (clean world seed 6394, 2 users × walk, squat, calisthenics, turn × 16 s, test settings): with B(q, z)
the reference's held-out MSE was 4.6e-3 (N m/kg)² and a hip "viscous damping" of 0.92 N m s/rad was accepted;
in the same world generated without the shear force's contact moment the sign of that misfit flipped — it is
the shear's moment. With B(q, x_cop, z): 1.8e-3 (N m/kg)², the refit noise σ_r 2.1e-5 → 1.5e-6, nothing found.
The export holds the CoP input at its training mean (the engine has one insole input; the metadata says so).

Optional (`Settings.pelvis_tilt`, off by default): the pelvis tilts with the hips' flexion (the trunk leans
into squats and landings), so the thigh's angle in an inertial frame is q_hip − τ_t q_hip,other once the
leg's own share is absorbed into its coordinates. With a partner the base can evaluate its Lagrangian at
(q − τ_t q_o e₀, q̇ − τ_t q̇_o e₀, q̈ − τ_t q̈_o e₀), one learned scalar τ_t — a coordinate shift, even in time
reversal, so it cannot imitate dissipation. Measured (2 users × walk, squat, calisthenics × 16 s, test
settings, one run each): reference held-out MSE −31 % (clean, seed 11) and −24 % (hip Coulomb, seed 21);
a clean world still finds nothing and a knee damping of 2.0 is still 1.86; but the hip's damping-like misfit
stays (a clean hip "damping" 0.43 either way) and a planted hip Coulomb of 2.5 came out 3.40 from scratch
(3.02 without the term) — so it is not the default.

Why held-out *time*: every trial is cut into contiguous segments; one segment in four (rotating phase per
trial) is held out. The model is tested where it was trained (same user, same task, same loads) but on
samples it never fitted, so a gain measures the planted physics, not extrapolation to unseen loads.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch
from torch import nn

from ..data import DataError, savgol_window
from ..delan import Lagrangian, energy as _energy, solve_inertia
from ..lim import LIM
from ..extensions import ExtendedModel, exo_derivatives, lag_table, velocity_response

DTYPE = torch.float32   # diagnosis fits run in float32 (speed); export converts to float64


@dataclass
class Flat:
    """All samples of a dataset stacked, with the held-out mask and the exo-torque histories."""
    q: torch.Tensor
    qd: torch.Tensor
    qdd: torch.Tensor
    tau: torch.Tensor
    tau_e: torch.Tensor
    tau_e_d: torch.Tensor
    tau_e_dd: torch.Tensor
    f_v: torch.Tensor
    f_o: torch.Tensor         # (N,) the other leg's insole force / (M g) at the same instant (0 without a partner)
    kin_o: torch.Tensor       # (N, 3) the other leg's hip q, q̇, q̈ at the same instant (0 without a partner)
    surge: torch.Tensor       # (N, 5) Σ over both legs of f_v,leg/G ⊙ φ(leg) (`PelvisSurge`; 0 without a partner)
    x_cop: torch.Tensor       # (N,) the leg's own centre of pressure along the foot (m; 0 where not measured)
    mass: torch.Tensor
    valid: torch.Tensor
    trial: torch.Tensor       # (N,) trial index
    segment: torch.Tensor     # (N,) global segment index (held-out blocks)
    held: torch.Tensor        # (N,) bool: held-out time segment
    lag: torch.Tensor         # (N, K+1) flat indices k samples earlier (same trial)
    lengths: list[int]
    joints: tuple[str, ...]
    joint_types: tuple[str, ...]
    dt: float
    trial_meta: list[dict]    # subject, task, name, side per trial
    has_exo: bool
    has_insole: bool
    has_partner: bool = False # every trial has its other-side recording (layout 1, both legs)
    tau_scale: np.ndarray = field(default_factory=lambda: np.ones(1))   # per-joint std of τ/m (train)
    qdd_scale: np.ndarray = field(default_factory=lambda: np.ones(1))   # per-joint std of q̈ (train)
    weight: torch.Tensor | None = None  # (N, n) fit weight per sample and joint (`misfit_weights`); None: all 1

    def forces(self, idx) -> torch.Tensor:
        """The insole input of the models at rows idx: f_v (B,), or with a partner (B, 11): [f_v, f_v,other/(M g),
        q, q̇, q̈ of the other hip, the 5 surge features, x_cop] (the pelvis's vertical load, tilt and fore-aft
        acceleration, module docstring; the own centre of pressure)."""
        if not self.has_partner:
            return self.f_v[idx]
        return torch.cat([self.f_v[idx, None], self.f_o[idx, None], self.kin_o[idx], self.surge[idx],
                          self.x_cop[idx, None]], -1)

    @property
    def n(self) -> int:
        return self.q.shape[1]

    def index(self, which: str) -> torch.Tensor:
        """Valid sample indices of 'train', 'held' or 'all'."""
        m = self.valid.clone()
        if which == "train":
            m &= ~self.held
        elif which == "held":
            m &= self.held
        return torch.nonzero(m, as_tuple=False)[:, 0]

    def exo_hist(self, idx: torch.Tensor):
        """(B, K+1, n) histories of τ_e, τ̇_e, τ̈_e for the rows idx."""
        lg = self.lag[idx]
        return self.tau_e[lg], self.tau_e_d[lg], self.tau_e_dd[lg]


SURGE_FEATURES = 5
# columns of the partnered insole input (`Flat.forces`): f_v, the other leg's load, the other hip's q, q̇, q̈,
# the surge features, the own centre of pressure
F_OTHER_HIP = slice(2, 5)
F_SURGE = slice(5, 5 + SURGE_FEATURES)
F_X_COP = 5 + SURGE_FEATURES
GRAVITY = 9.81


def _x_cop(trial, T: int) -> np.ndarray:
    """(T,) a trial's centre of pressure along the foot (m); 0 where not measured."""
    cop = getattr(trial, "cop", None)
    return np.nan_to_num(np.asarray(cop, dtype=np.float64)[:, 0]) if cop is not None else np.zeros(T)


def surge_features(trial) -> np.ndarray:
    """(T, 5) one leg's share of the pelvis's fore-aft acceleration features: f_v/G ⊙ φ, in kg.

    φ = [1, sin q_h, sin q_h cos q_k, cos q_h sin q_k, x_cop]: the terms of (x_hip − x_cop)/h, the slope of a
    ground force aimed from the centre of pressure at the hip (inverted pendulum), with the foot's position
    below the hip expanded in the hip and knee angles (either knee sign convention) and x_cop the insole's
    centre of pressure along the foot (m). An unloaded foot contributes f_v ≈ 0.
    """
    q = np.nan_to_num(np.asarray(trial.q, dtype=np.float64))
    T = q.shape[0]
    f = np.nan_to_num(np.asarray(trial.f_v, dtype=np.float64)) / GRAVITY if getattr(trial, "f_v", None) is not None \
        else np.zeros(T)
    qh = q[:, 0]
    qk = q[:, 1] if q.shape[1] > 1 else np.zeros(T)
    x_cop = _x_cop(trial, T)
    phi = np.stack([np.ones(T), np.sin(qh), np.sin(qh) * np.cos(qk), np.cos(qh) * np.sin(qk), x_cop], 1)
    return f[:, None] * phi


class PelvisSurge(nn.Module):
    """Torque on the leg from the pelvis's fore-aft acceleration a_x, estimated from both insoles.

    Physics: the hip rides on the pelvis; in the hip frame its horizontal acceleration acts on the leg like a
    horizontal gravity (d'Alembert), τ = −a_x ∂(m x_com)/∂q. Insoles measure no shear force, but the ground
    force of a loaded foot points roughly from its centre of pressure at the body above the hip, so
    M a_x = Σ_legs f_x ≈ Σ_legs f_v (x_hip − x_cop)/h. Unmodelled, this torque (it follows the gait cycle)
    leaves a hip residual that a damping or a Coulomb term soaks up: in a simulated world a clean hip showed
    a "damping" of about 0.4 N m s/rad and a planted hip Coulomb friction came out +20 % (both gone when the
    world's pelvis had no fore-aft acceleration).

    Form: a_x/G·M = β · Σ_legs f_v/G φ(leg) (`surge_features`, five learned slopes β shared by every trial);
    the leg's mass moment ∂(m x_com)/∂q ∝ C ψ(q), ψ = [cos q_h, cos q_h cos q_k, sin q_h sin q_k] for a two-link
    chain (C, n × 3, learned from 0, in m). Eleven scalars, no network, every input even under time reversal:
    the term cannot follow q̇ freely the way a network of the other leg's signals could.
    """

    def __init__(self, n: int):
        super().__init__()
        # β from the inverted pendulum with 0.43 m segments, a 0.05 m heel-to-ankle offset and a 0.9 m leg
        self.beta = nn.Parameter(torch.tensor([0.055, -0.53, -0.53, 0.53, -1.1]))
        self.C = nn.Parameter(torch.zeros(n, 3))

    def forward(self, q: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        qh = q[..., 0]
        qk = q[..., 1] if q.shape[-1] > 1 else torch.zeros_like(qh)
        psi = torch.stack([torch.cos(qh), torch.cos(qh) * torch.cos(qk), torch.sin(qh) * torch.sin(qk)], -1)
        mass_accel = GRAVITY * (feats @ self.beta)          # M a_x (N)
        return mass_accel.unsqueeze(-1) * (psi @ self.C.T)


def _surge_inputs(q: torch.Tensor, f_v: torch.Tensor):
    """The surge features inside the models' insole input (`Flat.forces`), or None without them."""
    if f_v.dim() != q.dim() or f_v.shape[-1] < F_SURGE.stop:
        return None
    return f_v[..., F_SURGE]


def pelvis_terms(surge, cop_lever, q: torch.Tensor, f_v: torch.Tensor):
    """The surge torque minus the CoP part of the contact torque, as it enters τ̂ (None without either)."""
    feats = _surge_inputs(q, f_v) if surge is not None else None
    out = surge(q, feats) if feats is not None else None
    ct = cop_torque(cop_lever, q, f_v)
    if ct is not None:
        out = -ct if out is None else out - ct
    return out


def cop_torque(d, q: torch.Tensor, f_v: torch.Tensor):
    """d ⊙ f_v x_cop: the part of a foot's contact torque that moves with its centre of pressure.

    A vertical force f_v at a point x_cop along a flat foot has the moment f_v (x_foot(q) − x_joint) + f_v x_cop
    about each joint; the LIM's lever arms B(q, z) carry the first part, the second is linear in x_cop with a
    coefficient of about ±1 per joint (the foot's direction; learned from 0). Without it a slow-context base
    must guess the CoP's heel-to-toe travel (some 0.2 m, tens of N m) from q alone. None without the inputs.
    """
    x = _x_cop_of(q, f_v) if d is not None else None
    return None if x is None else d * (f_v[..., 0] * x).unsqueeze(-1)


COP_UNIT = 0.1      # m: the LIM's centre-of-pressure input is x_cop / COP_UNIT (a foot is some 0.25 m long)


def cop_context(q: torch.Tensor, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """An insole mapping's context with the centre of pressure: [z; x_cop / COP_UNIT], z broadcast over the rows."""
    return torch.cat([z.expand(*q.shape[:-1], z.shape[-1]), (x / COP_UNIT).unsqueeze(-1)], -1)


def _x_cop_of(q: torch.Tensor, f_v: torch.Tensor):
    """The own centre of pressure from the insole input of `Flat.forces` (its last column); None without it."""
    if f_v.dim() != q.dim() or f_v.shape[-1] <= F_X_COP:
        return None
    return f_v[..., F_X_COP]


def _segments(T: int, dt: float, seg_seconds: float, rng: np.random.Generator, every: int):
    """Segment id per sample and whether it is held out: ~seg_seconds blocks, one in `every` held out."""
    L = max(int(round(seg_seconds / dt)), 20)
    nseg = max(int(math.ceil(T / L)), 1)
    if nseg < 2:          # a very short trial: cut it in two halves so that it contributes to both sides
        nseg = 2 if T >= 40 else 1
    bounds = np.linspace(0, T, nseg + 1).astype(int)
    seg = np.zeros(T, dtype=np.int64)
    for k in range(nseg):
        seg[bounds[k]:bounds[k + 1]] = k
    phase = int(rng.integers(every))
    held_seg = np.array([(k + phase) % every == 0 for k in range(nseg)])
    if nseg >= 2 and held_seg.all():
        held_seg[1:] = False
    if nseg >= 2 and not held_seg.any():
        held_seg[nseg // 2] = True
    return seg, held_seg[seg] if nseg >= 2 else np.zeros(T, dtype=bool)


def prepare(trials: Sequence, seg_seconds: float = 2.0, every: int = 4, max_delay: float = 0.1,
            seed: int = 0) -> Flat:
    """Stack trials (DESIGN.md section 1 `Trial`s, duck-typed) into a `Flat`."""
    if not trials:
        raise DataError("diagnosis needs at least one trial")
    t0 = trials[0]
    joints, jtypes, dt = tuple(t0.joints), tuple(t0.joint_types), float(t0.dt)
    for t in trials:
        if tuple(t.joints) != joints or abs(float(t.dt) - dt) > 1e-9:
            raise DataError(f"trial {t.subject}/{t.name}: joints or sample time differ from the first trial "
                            f"({t0.subject}/{t0.name}: {joints}, {dt:g} s; this one: {tuple(t.joints)}, {float(t.dt):g} s)")
    rng = np.random.default_rng(seed)
    K = int(math.ceil(max_delay / dt)) + 1
    cols = {k: [] for k in ("q", "qd", "qdd", "tau", "tau_e", "tau_e_d", "tau_e_dd", "f_v", "x_cop", "mass", "valid",
                            "trial", "segment", "held")}
    seg_base = 0
    lengths, meta = [], []
    # the strap's q̇/q̈ correction goes through the measured velocity's own filter and the reader's q̈ filter
    v_resp = velocity_response(trials, dt)
    for i, t in enumerate(trials):
        T = np.asarray(t.q).shape[0]
        lengths.append(T)
        n = len(joints)
        tau_e = np.asarray(t.tau_e, dtype=np.float64) if getattr(t, "tau_e", None) is not None else np.zeros((T, n))
        d1, d2 = exo_derivatives(tau_e, dt, response=v_resp, qdd_window=savgol_window(dt))
        seg, held = _segments(T, dt, seg_seconds, rng, every)
        f_v = np.asarray(t.f_v, dtype=np.float64) if getattr(t, "f_v", None) is not None else np.zeros(T)
        valid = np.asarray(t.valid, dtype=bool).copy() if getattr(t, "valid", None) is not None else np.ones(T, bool)
        for name in ("q", "qd", "qdd", "tau"):
            valid &= np.isfinite(np.asarray(getattr(t, name))).all(axis=1)
        valid &= np.isfinite(f_v) & np.isfinite(tau_e).all(axis=1)
        cols["q"].append(np.asarray(t.q)); cols["qd"].append(np.asarray(t.qd)); cols["qdd"].append(np.asarray(t.qdd))
        cols["tau"].append(np.asarray(t.tau)); cols["tau_e"].append(np.nan_to_num(tau_e))
        cols["tau_e_d"].append(d1); cols["tau_e_dd"].append(d2); cols["f_v"].append(np.nan_to_num(f_v))
        cols["x_cop"].append(_x_cop(t, T))
        cols["mass"].append(np.full(T, float(t.mass))); cols["valid"].append(valid)
        cols["trial"].append(np.full(T, i)); cols["segment"].append(seg + seg_base); cols["held"].append(held)
        seg_base += int(seg.max()) + 1
        meta.append(dict(subject=str(t.subject), task=str(t.task), name=str(t.name), side=str(getattr(t, "side", ""))))
    # the other leg of the same recording (layout 1 stores both sides of a trial with the same name)
    side_of = {(str(t.subject), str(t.name), str(getattr(t, "side", ""))): i for i, t in enumerate(trials)}
    cols["f_o"], cols["kin_o"], cols["surge"] = [], [], []
    partners = 0
    for i, t in enumerate(trials):
        side = str(getattr(t, "side", ""))
        other = {"l": "r", "r": "l"}.get(side)
        o = side_of.get((str(t.subject), str(t.name), other)) if other else None
        if o is not None and lengths[o] == lengths[i] and getattr(trials[o], "f_v", None) is not None:
            cols["f_o"].append(np.nan_to_num(np.asarray(trials[o].f_v, dtype=np.float64)) / (float(t.mass) * 9.81))
            cols["kin_o"].append(np.nan_to_num(np.stack([np.asarray(getattr(trials[o], k), dtype=np.float64)[:, 0]
                                                         for k in ("q", "qd", "qdd")], -1)))
            cols["surge"].append(surge_features(t) + surge_features(trials[o]))
            partners += 1
        else:
            cols["f_o"].append(np.zeros(lengths[i]))
            cols["kin_o"].append(np.zeros((lengths[i], 3)))
            cols["surge"].append(np.zeros((lengths[i], SURGE_FEATURES)))
    cat = {k: np.concatenate(v, axis=0) for k, v in cols.items()}
    f = lambda k: torch.as_tensor(np.nan_to_num(cat[k]), dtype=DTYPE)
    flat = Flat(q=f("q"), qd=f("qd"), qdd=f("qdd"), tau=f("tau"), tau_e=f("tau_e"), tau_e_d=f("tau_e_d"),
                tau_e_dd=f("tau_e_dd"), f_v=f("f_v"), f_o=f("f_o"), kin_o=f("kin_o"), surge=f("surge"), x_cop=f("x_cop"), mass=f("mass"),
                valid=torch.as_tensor(cat["valid"]), trial=torch.as_tensor(cat["trial"]),
                segment=torch.as_tensor(cat["segment"]), held=torch.as_tensor(cat["held"]),
                lag=torch.as_tensor(lag_table(lengths, K)), lengths=lengths, joints=joints, joint_types=jtypes,
                dt=dt, trial_meta=meta, has_exo=bool(np.abs(cat["tau_e"]).max() > 0),
                has_insole=bool(np.abs(cat["f_v"]).max() > 0),
                has_partner=bool(partners == len(trials) and np.abs(cat["f_o"]).max() > 0))
    tr = flat.index("train")
    s = (flat.tau[tr] / flat.mass[tr, None]).std(0).numpy()
    flat.tau_scale = np.where(s > 1e-9, s, 1.0)
    a = flat.qdd[tr].std(0).numpy()
    flat.qdd_scale = np.where(a > 1e-9, a, 1.0)
    return flat


def sample_groups(flat: Flat, idx: torch.Tensor) -> tuple[np.ndarray, str]:
    """Group label of every sample in idx: its task, or its trial where the data hold a single task (a test
    bench); ("", "none") when there is a single trial. The groups of rule 5 and of the screen's per-group fit."""
    tri = flat.trial[idx].numpy()
    tasks = np.array([flat.trial_meta[i]["task"] for i in tri])
    if len(np.unique(tasks)) >= 2:
        return tasks, "task"
    if len(flat.lengths) >= 2:
        return np.array([flat.trial_meta[i]["name"] + f"#{i}" for i in tri]), "trial"
    return np.zeros(len(tri), dtype=str), "none"


def exo_copy(flat: Flat, j: int, max_lag: int = 40) -> Flat:
    """The same data with the exo torque of joint j replaced by its copy of the joint's torque: per trial, the
    least-squares fit (training rows) of the recorded exo torque on the recorded total joint torque 1..max_lag
    samples earlier. Only ``tau_e`` changes, so it serves terms that read the present exo torque alone (a gain).

    An assistive controller's output is mostly such a copy (it follows the torque the joint needs, with its own
    lag); what the copy leaves over is the controller's own variation (modulation, wiggle, saturation). A real
    gain error scales the whole recorded torque, that variation included; a term that only soaks up model
    error correlated with the joint torque does as well from the copy.
    """
    f = copy.copy(flat)
    f.tau_e = flat.tau_e.clone()
    train = (~flat.held & flat.valid).numpy()
    tau = flat.tau[:, j].numpy().astype(np.float64)
    te = flat.tau_e[:, j].numpy().astype(np.float64)
    start = 0
    for T in flat.lengths:
        t = np.arange(T)
        X = np.stack([np.ones(T)] + [tau[start + np.maximum(t - l, 0)] for l in range(1, max_lag + 1)], 1)
        rows = train[start:start + T] & (t >= max_lag)
        if rows.sum() > 2 * X.shape[1]:
            coef = np.linalg.lstsq(X[rows], te[start:start + T][rows], rcond=None)[0]
            f.tau_e[start:start + T, j] = torch.as_tensor(X @ coef, dtype=flat.tau_e.dtype)
        start += T
    return f


def exo_own(flat: Flat, j: int) -> Flat:
    """The same data with the exo torque of joint j replaced by the controller's own variation: the recorded
    exo torque less its copy of the joint torque (`exo_copy`). A term on it reads only what the copy leaves
    over, so it helps only where the torque carries that variation (a gain error scales it with the rest)."""
    f = exo_copy(flat, j)
    f.tau_e[:, j] = flat.tau_e[:, j] - f.tau_e[:, j]
    return f


class SlowContextDeLaN(nn.Module):
    """DeLaN (+ LIM) with a learned constant context code per trial: z cannot carry q̇ within a step.

    Same networks as the project's DeLaN (`exolan.delan.Lagrangian`, `exolan.lim.LIM`); the caller passes
    z = codes[trial] to `inverse` / `forward_dynamics` (the interface of DESIGN.md section 2).
    """

    def __init__(self, joint_types, n_trials: int, z_dim: int = 4, hidden: int = 64, lim: bool = True,
                 v_scale: float = 1.0, lim_scale: float = 0.1, lim_other: bool = False, pelvis_tilt: bool = False,
                 pelvis_surge: bool = True, lim_cop: bool = False):
        super().__init__()
        self.delan = Lagrangian(joint_types, z_dim, hidden, softplus_offset=1e-2, v_scale=v_scale)
        # the insole mapping's lever arms see the centre of pressure too, B(q, x_cop, z) (module docstring); the
        # CoP comes with the partner's columns of `Flat.forces`
        self.lim_cop = bool(lim and lim_other and lim_cop)
        self.lim = LIM(joint_types, z_dim + int(self.lim_cop), 16, lim_scale) if lim else None
        # the (scaled) centre of pressure an export holds the LIM at: the loaded training samples' mean (`make_base`)
        self.register_buffer("cop_ref", torch.zeros(()))
        # the other leg's load scales the effective gravity (module docstring): κ per joint
        self.body_load = nn.Parameter(torch.zeros(len(joint_types))) if lim_other else None
        # the pelvis tilts with the other hip's flexion: the leg's first coordinate seen from an inertial
        # frame is q_0 − τ_t q_0,other (module docstring); τ_t learned from 0
        self.tilt = nn.Parameter(torch.zeros(())) if (lim_other and pelvis_tilt) else None
        # the pelvis's fore-aft acceleration from both insoles (`PelvisSurge`)
        self.surge = PelvisSurge(len(joint_types)) if (lim_other and pelvis_surge) else None
        # the contact torque's lever follows the centre of pressure along the foot: + d ⊙ f_v x_cop (`cop_torque`)
        self.cop_lever = nn.Parameter(torch.zeros(len(joint_types))) if (lim and lim_other and pelvis_surge) else None
        self.codes = nn.Embedding(n_trials, z_dim)
        nn.init.normal_(self.codes.weight, std=0.01)
        self.z_dim = z_dim

    def z_of(self, trial_idx: torch.Tensor) -> torch.Tensor:
        return self.codes(trial_idx)

    def _split(self, q, f_v):
        """f_v (B,) or (B, 2) = [own force, other leg's load ratio] (`Flat.forces`)."""
        return (f_v[..., 0], f_v[..., 1]) if f_v.dim() == q.dim() else (f_v, None)

    def _tilt_shift(self, q, f_v):
        """(Δq, Δq̇, Δq̈) of the pelvis tilt that follows the other hip; None without the term or a partner.
        (The fits' acceleration term takes the H of the tilted coordinates, the one the inverse dynamics used.)"""
        if self.tilt is None or f_v.dim() != q.dim() or f_v.shape[-1] < F_OTHER_HIP.stop:
            return None
        e0 = torch.zeros(q.shape[-1], dtype=q.dtype); e0[0] = 1.0
        return tuple(self.tilt * f_v[..., k].unsqueeze(-1) * e0 for k in range(F_OTHER_HIP.start, F_OTHER_HIP.stop))

    def _rhs_terms(self, q, qd, z, f_v):
        """H, c + g_eff − B f_v,own: everything on the left of H q̈ + ... = τ except H q̈ (at the tilted
        coordinates), and the tilt's Δq̈ (or None)."""
        own, other = self._split(q, f_v)
        sh = self._tilt_shift(q, f_v)
        qa, qda = (q, qd) if sh is None else (q - sh[0], qd - sh[1])
        H, c, g = self.delan.terms(qa, qda, z)
        if self.body_load is not None and other is not None:
            g = g * (1.0 + self.body_load * other.unsqueeze(-1))
        rest = c + g
        extra = pelvis_terms(self.surge, self.cop_lever, q, f_v)
        if extra is not None:
            rest = rest + extra
        if self.lim is not None:
            rest = rest - self.lim.contact_torque(q, self._lim_context(q, z, f_v), own)
        return H, rest, (None if sh is None else sh[2])

    def _lim_context(self, q, z, f_v):
        """The LIM's context: z, with the own centre of pressure (in units of COP_UNIT) appended (`lim_cop`)."""
        if not self.lim_cop:
            return z
        x = _x_cop_of(q, f_v)
        if x is None:
            raise ValueError("this base's insole mapping needs the centre of pressure: pass Flat.forces(idx)")
        return cop_context(q, z, x)

    def inverse(self, q, qd, qdd, z, f_v):
        return self.inverse_inertia(q, qd, qdd, z, f_v)[0]

    def inverse_inertia(self, q, qd, qdd, z, f_v):
        """(τ̂, H): the inverse dynamics and the inertia it used (the fits' acceleration term reuses H)."""
        H, rest, dqdd = self._rhs_terms(q, qd, z, f_v)
        qdd_a = qdd if dqdd is None else qdd - dqdd
        return (H @ qdd_a.unsqueeze(-1)).squeeze(-1) + rest, H

    def forward_dynamics(self, q, qd, tau, z, f_v):
        H, rest, dqdd = self._rhs_terms(q, qd, z, f_v)
        qdd = solve_inertia(H, tau - rest)
        return qdd if dqdd is None else qdd + dqdd

    def terms(self, q, qd, z):
        return self.delan.terms(q, qd, z)

    def energy(self, q, qd, z):
        return _energy(self.delan, q, qd, z)


class PooledContext(nn.Module):
    """A trained run's model with its context pooled (averaged) per trial — a slow context.

    The pooled codes are the starting values of learned constants per trial (as `SlowContextDeLaN`'s codes):
    the run's networks were trained with a z that moves within a stride, and at a frozen mean z they leave a
    misfit that the diagnosis adapts away before it judges anything (`procedure.run`, `Settings.adapt_model`).

    With `other_leg_load` the diagnosis adds the same gravity scaling by the other leg's load as its own base
    (module docstring): κ ⊙ g(q, z) f_v,other/(M g), κ learned from 0. The trained run never saw the other
    insole; without the term its hip keeps the misfit of the pelvis's vertical acceleration. The pelvis surge
    and the centre-of-pressure lever are the base's too; and since a run's insole mapping B(q, z) cannot see the
    centre of pressure, `lim_cop` adds a correction ΔB(q, z, x_cop) f_v (a LIM on [φ(q); z; x_cop/COP_UNIT], its
    last layer zero, so the given model is unchanged until the data move it; module docstring).
    """

    def __init__(self, model: nn.Module, z_trials: torch.Tensor, other_leg_load: bool = False,
                 pelvis_surge: bool = True, lim_cop: bool = False):
        super().__init__()
        self.model = model
        self.z_trials = nn.Parameter(z_trials.detach().clone())
        self.body_load = (nn.Parameter(torch.zeros(len(model.joint_types), dtype=z_trials.dtype))
                          if other_leg_load else None)
        self.surge = (PelvisSurge(len(model.joint_types)).to(z_trials.dtype)
                      if (other_leg_load and pelvis_surge) else None)
        has_lim = getattr(model, "lim", None) is not None
        self.cop_lever = (nn.Parameter(torch.zeros(len(model.joint_types), dtype=z_trials.dtype))
                          if (other_leg_load and pelvis_surge and has_lim) else None)
        self.lim_cop = None
        if other_leg_load and lim_cop and has_lim:
            self.lim_cop = LIM(model.joint_types, z_trials.shape[-1] + 1, 16,
                               float(getattr(model.lim, "lim_scale", 0.1))).to(z_trials.dtype)
            with torch.no_grad():
                self.lim_cop[-1].weight.zero_()
                self.lim_cop[-1].bias.zero_()

    def z_of(self, trial_idx):
        return self.z_trials[trial_idx]

    def _load_torque(self, q, z, f_v):
        """κ ⊙ g(q, z) f_v,other + the pelvis surge torque − the CoP part of the contact torque − ΔB(q, z, x_cop)
        f_v (None without the terms or without a partner)."""
        if self.body_load is None or f_v.dim() != q.dim():
            return None
        out = self.body_load * self.model.gravity(q, z) * f_v[..., 1].unsqueeze(-1)
        extra = pelvis_terms(self.surge, self.cop_lever, q, f_v)
        out = out if extra is None else out + extra
        x = _x_cop_of(q, f_v) if self.lim_cop is not None else None
        if x is not None:
            out = out - self.lim_cop.contact_torque(q, cop_context(q, z, x), f_v[..., 0])
        return out

    @staticmethod
    def _own(q, f_v):
        return f_v[..., 0] if f_v.dim() == q.dim() else f_v     # a given run has its own insole only

    def inverse(self, q, qd, qdd, z, f_v):
        return self.inverse_inertia(q, qd, qdd, z, f_v)[0]

    def inverse_inertia(self, q, qd, qdd, z, f_v):
        """(τ̂, H): the run's inverse dynamics plus the added load terms, and the inertia it used (the fits'
        acceleration term reuses H)."""
        tau, H = self.model.inverse_inertia(q, qd, qdd, z, self._own(q, f_v))
        extra = self._load_torque(q, z, f_v)
        return (tau if extra is None else tau + extra), H

    def forward_dynamics(self, q, qd, tau, z, f_v):
        extra = self._load_torque(q, z, f_v)
        return self.model.forward_dynamics(q, qd, tau if extra is None else tau - extra, z, self._own(q, f_v))

    def terms(self, q, qd, z):
        return self.model.terms(q, qd, z)

    def energy(self, q, qd, z):
        return self.model.energy(q, qd, z)


def make_base(flat: Flat, hidden: int = 64, z_dim: int = 4, seed: int = 0, pelvis_tilt: bool = False,
              pelvis_surge: bool = True, lim_cop: bool = True) -> SlowContextDeLaN:
    torch.manual_seed(seed)
    tr = flat.index("train")
    # v_scale: one network unit of ∂V/∂q ≈ the torque spread; lim_scale: lever arms of ~0.1 m (or the
    # torque spread per unit insole force where that is larger)
    v_scale = float(flat.tau[tr].std(0).max().clamp(min=1e-3))
    m = SlowContextDeLaN(flat.joint_types, len(flat.lengths), z_dim, hidden, lim=flat.has_insole,
                         v_scale=v_scale, lim_scale=0.1, lim_other=flat.has_insole and flat.has_partner,
                         pelvis_tilt=pelvis_tilt, pelvis_surge=pelvis_surge, lim_cop=lim_cop)
    if m.lim_cop:
        loaded = tr[flat.f_v[tr] > 0]
        if len(loaded):
            m.cop_ref.fill_(float(flat.x_cop[loaded].mean()) / COP_UNIT)
    return m.to(DTYPE)


def inertia_of(model: nn.Module, q: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """H(q, z) of the Lagrangian inside a diagnosis model (slow-context base, pooled run, or extended)."""
    base = _base_of(model)
    lag = base.delan if isinstance(base, SlowContextDeLaN) else base.model.delan
    return lag.inertia(q, z)


def _base_of(model: nn.Module) -> nn.Module:
    return model.base if isinstance(model, ExtendedModel) else model


def predict(model: nn.Module, flat: Flat, idx: torch.Tensor, chunk: int = 16384) -> torch.Tensor:
    """Predicted recorded torque at rows idx (no grad)."""
    out = []
    base = _base_of(model)
    with torch.no_grad():
        for s in range(0, len(idx), chunk):
            out.append(_forward(model, base, flat, idx[s:s + chunk]))
    return torch.cat(out, 0) if out else flat.tau[:0]


def _inputs(model, base, flat: Flat, b: torch.Tensor) -> tuple:
    """The model's inverse-dynamics arguments at rows b. Only a delay needs the exo torque's history; the
    other terms take the current row (gathering the (B, K+1, n) histories costs 4 % of a diagnosis)."""
    args = (flat.q[b], flat.qd[b], flat.qdd[b], base.z_of(flat.trial[b]), flat.forces(b))
    if not isinstance(model, ExtendedModel):
        return args
    ex = (flat.exo_hist(b) if "actuation_delay" in model.effects
          else (flat.tau_e[b], flat.tau_e_d[b], flat.tau_e_dd[b]))
    return args + tuple(ex)


def _gate_kw(model, flat: Flat, b: torch.Tensor) -> dict:
    """`trial=` for a model with subject-specific (gated) terms: they act on their own trials only."""
    return {"trial": flat.trial[b]} if getattr(model, "gated", ()) else {}


def _forward(model, base, flat: Flat, b: torch.Tensor) -> torch.Tensor:
    return model.inverse(*_inputs(model, base, flat, b), **_gate_kw(model, flat, b))


def _forward_inertia(model, base, flat: Flat, b: torch.Tensor):
    """(τ̂, H) at rows b, H the inertia the inverse dynamics used: one evaluation of the inertia network per
    fit step instead of two (evaluated here only where the model does not expose it)."""
    args = _inputs(model, base, flat, b)
    kw = _gate_kw(model, flat, b)
    tau, H = (model.inverse_inertia(*args, **kw) if hasattr(model, "inverse_inertia")
              else (model.inverse(*args, **kw), None))
    return tau, (H if H is not None else inertia_of(model, flat.q[b], args[3]))


def sq_errors(model, flat: Flat, idx: torch.Tensor) -> np.ndarray:
    """Per-sample mass-normalised squared torque error, summed over joints ((N m/kg)²) — and per joint."""
    e = (predict(model, flat, idx) - flat.tau[idx]) / flat.mass[idx, None]
    return (e ** 2).numpy().astype(np.float64)


def train(model: nn.Module, flat: Flat, steps: int, lr: float = 3e-3, lr_ext: float = 3e-2,
          batch: int = 4096, seed: int = 0, weight_decay: float = 0.0, progress=None,
          average: bool = False, w_acc: float = 0.1, weighted: bool = True) -> list[float]:
    """Minimise the mass-normalised torque MSE (per-joint scaled) on the training segments, plus `w_acc` times
    the acceleration MSE (per-joint scaled by the std of q̈). Where `flat.weight` is set (and `weighted`),
    every sample's squared errors are weighted per joint (`misfit_weights`).

    Why the acceleration term: torque errors alone leave H loose in directions the data excite little, and a
    tiny H makes forward dynamics stiff enough that open-loop rollouts explode within a few steps. Because
    the predicted torque is H q̈ + (terms without q̈), the forward-dynamics error is H⁻¹ (τ − τ̂) exactly: one
    2x2 solve per sample with the H the inverse dynamics just used, no separate forward pass. Its known cost:
    |H⁻¹ e| shrinks as H grows, so the term also pulls H up wherever a torque misfit remains. In a world with
    a 50 ms knee delay the fitted inertia's small eigenvalue came out about 4x the world's (0.53 vs 0.13 kg m²)
    and a from-scratch delay fit ended at 35 ms (44 ms without the term, but then H collapses at a few states
    and rollouts diverge within 20 steps).

    Adam with minibatches; the extension's physical scalars get their own (larger) step because they are
    few and well scaled. `average=True` ends on the running mean of the weights over the second half of
    the steps (Polyak averaging; the networks' weights, not the extension's scalars): the minibatch noise
    of the last iterates averages out, so two refits that
    differ only in minibatch order end closer together — the refit noise every held-out gain is judged
    against. Returns the loss history (every step).
    """
    g = torch.Generator().manual_seed(seed)
    tr = flat.index("train")
    base = _base_of(model)
    scale = torch.as_tensor(flat.tau_scale, dtype=DTYPE)
    acc_scale = torch.as_tensor(flat.qdd_scale, dtype=DTYPE)
    if isinstance(model, ExtendedModel):
        groups = [{"params": model.base_parameters(), "lr": lr, "weight_decay": weight_decay},
                  {"params": model.ext_parameters(), "lr": lr_ext, "weight_decay": 0.0}]
    else:
        groups = [{"params": list(model.parameters()), "lr": lr, "weight_decay": weight_decay}]
    opt = torch.optim.Adam(groups)
    # cosine decay: the last steps settle the physical parameters instead of jittering around them
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1), eta_min=0.05 * lr)
    hist = []
    # averaged: the networks only. An extension's physical scalar may still be moving towards its value
    # during a refit; its running mean would lag behind (measured: knee damping 0.96 instead of 1.8).
    params = list(groups[0]["params"])
    avg, n_avg, start_avg = None, 0, steps // 2
    for step in range(steps):
        b = tr[torch.randint(len(tr), (min(batch, len(tr)),), generator=g)]
        pred, H = _forward_inertia(model, base, flat, b) if w_acc > 0 else (_forward(model, base, flat, b), None)
        err = pred - flat.tau[b]
        r = err / (flat.mass[b, None] * scale)
        w = flat.weight[b] if weighted and flat.weight is not None else 1.0
        loss = (w * r ** 2).sum(-1).mean()
        if w_acc > 0:
            a_err = solve_inertia(H, err) / acc_scale
            loss = loss + w_acc * (w * a_err ** 2).sum(-1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        hist.append(float(loss.detach()))
        if average and step >= start_avg:
            with torch.no_grad():
                if avg is None:
                    avg = [p.detach().clone() for p in params]
                else:
                    for a, p in zip(avg, params):
                        a.add_(p.detach() - a, alpha=1.0 / (n_avg + 1))
            n_avg += 1
        if progress is not None:
            progress(step, hist[-1])
    if avg is not None:
        with torch.no_grad():
            for a, p in zip(avg, params):
                p.copy_(a)
    return hist


def misfit_weights(model: nn.Module, flat: Flat) -> torch.Tensor:
    """Fit weights (N, n): per trial and joint, the inverse of the model's mean squared training residual there,
    shrunk halfway to the median over trials, normalised to mean 1 over the training rows of each joint.

    Why (feasible weighted least squares): how well a conservative model fits differs a lot between tasks —
    a task whose unmeasured drivers (the pelvis's horizontal acceleration and horizontal ground force in
    jumps and calisthenics) the model cannot see leaves residuals ten times the variance of walking's. In an
    unweighted fit those residuals pull a physical parameter towards whatever part of them it can mimic:
    a planted hip Coulomb friction of 2.5 N m came out 3.00 unweighted, 2.48 weighted (one world, same fits).
    Weighting each trial by its inverse misfit is the efficient estimator under such heteroscedasticity and
    a property of the joint, the same in every task, should be fitted where the model is trustworthy. The
    shrinkage (halfway to the median) keeps a trial the model happens to fit almost exactly from dominating;
    the held-out gains stay unweighted (the user's torque error).
    """
    tr = flat.index("train")
    scale = torch.as_tensor(flat.tau_scale, dtype=DTYPE)
    r = ((predict(model, flat, tr) - flat.tau[tr]) / (flat.mass[tr, None] * scale)).numpy().astype(np.float64)
    w_trial = trial_weights(r, flat.trial[tr].numpy(), len(flat.lengths))
    w = torch.as_tensor(w_trial, dtype=DTYPE)[flat.trial]
    return w / w[tr].mean(0)


def trial_weights(r: np.ndarray, trial: np.ndarray, n_trials: int) -> np.ndarray:
    """(n_trials, n) inverse mean squared residual per trial and joint, the variance shrunk halfway to the
    median over trials (`misfit_weights`); trials without rows get the median's weight; all 1 when fewer
    than two trials have rows."""
    r = np.asarray(r, np.float64).reshape(len(trial), -1)
    var = np.ones((n_trials, r.shape[1]))
    seen = np.zeros(n_trials, bool)
    for i in np.unique(trial):
        var[i] = np.mean(r[trial == i] ** 2, 0)
        seen[i] = True
    if seen.sum() < 2:
        return np.ones_like(var)
    med = np.median(var[seen], 0)
    var = np.where(seen[:, None], 0.5 * (var + med), med)
    return 1.0 / np.maximum(var, 1e-30)


def extend(base: nn.Module, flat: Flat, effects, init: dict | None = None, max_delay: float = 0.1) -> ExtendedModel:
    """A deep copy of `base` wrapped with the section-4 terms (warm start: the base's weights as fitted)."""
    return ExtendedModel(copy.deepcopy(base), flat.n, effects, dt=flat.dt, max_delay=max_delay, init=init,
                         coupled_damping=False)


def to_exo_model(base: SlowContextDeLaN, z: torch.Tensor, joint_names=None):
    """The slow-context base at one fixed context z as a context-free `ExoModel` ("delan" ± LIM).

    z enters only the first layer of each network, so W [φ; z] + b = W_φ φ + (W_z z + b): folding W_z z
    into the bias gives the identical function without z — the form the weight file and the Rust engine
    take (DESIGN.md section 3). Used to export the extended model for a chosen trial's (or the mean) z.
    """
    from ..models import build_model

    lag = base.delan
    exo = build_model("delan", lim=base.lim is not None, joint_types=lag.features.joint_types,
                      context_channels=(), joint_names=joint_names, hidden=lag.L[0].out_features,
                      softplus_offset=lag.softplus_offset, v_scale=lag.v_scale,
                      lim_scale=base.lim.lim_scale if base.lim is not None else 0.1).to(torch.float64)
    k = lag.features.dim
    z = z.detach().to(torch.float64).reshape(-1)
    with torch.no_grad():
        pairs = [(exo.delan.L, lag.L, z), (exo.delan.V, lag.V, z)]
        if base.lim is not None:
            # a LIM that sees the centre of pressure is held at the training mean (the engine has no CoP input)
            zl = (torch.cat([z, base.cop_ref.detach().to(torch.float64).reshape(1)])
                  if getattr(base, "lim_cop", False) else z)
            pairs.append((exo.lim, base.lim, zl))
        for dst, src, zc in pairs:
            for i, (ld, ls) in enumerate(zip(dst, src)):
                W = ls.weight.detach().to(torch.float64)
                b = ls.bias.detach().to(torch.float64)
                if i == 0:
                    ld.weight.copy_(W[:, :k])
                    ld.bias.copy_(b + W[:, k:] @ zc)
                else:
                    ld.weight.copy_(W)
                    ld.bias.copy_(b)
    return exo


def export_extended(ext: ExtendedModel, path, z: torch.Tensor, joint_names=None, dt: float | None = None,
                    meta: dict | None = None, trial: int | None = None):
    """Export base (at context z) + `ext.*` tensors through `exolan.export` (the Rust engine's format).

    `trial`: a subject-specific term is written as it acts on that trial (the engine has neither switches nor
    sizes: one file per user): a term switched off there is left out, a sized one takes its subject's value;
    without it every term is written at its shared value."""
    from ..export import export

    exo = to_exo_model(ext.base, z, joint_names)
    factor = lambda e, j: 1.0 if trial is None else ext.trial_factor(e, j, trial)
    eff = [(e, j) for e, js in ext.effects.items() for j in js if factor(e, j) > 0]
    twin = ExtendedModel(exo, ext.n, eff, dt=ext.dt, max_delay=ext.max_delay, coulomb_eps=ext.coulomb_eps,
                         coupled_damping=ext.coupled_damping).to(torch.float64)
    with torch.no_grad():
        params = dict(twin.named_parameters())
        for name, p in ext.named_parameters():
            if not name.startswith("base.") and name in params:     # (not the sizes: the twin has none)
                params[name].copy_(p.detach().to(torch.float64))
    if trial is not None and ext.sized:
        own = ext.physical(trial)
        for e, j in eff:        # a sized term at this trial's subject's value
            if e in ext.sized:
                twin.set_value(e, j, float(own[e][j, j] if e == "viscous_damping" else own[e][j]))
    md = {"dt": repr(float(dt if dt is not None else ext.dt))}
    if getattr(ext.base, "body_load", None) is not None:
        md["omitted"] = ("the diagnosis base's gravity scaling by the other leg's insole force (the engine has one "
                         "insole input)" + (" and its pelvis tilt following the other hip"
                                            if getattr(ext.base, "tilt", None) is not None else "") +
                         (", and the pelvis's fore-aft acceleration from both insoles and the centre-of-pressure "
                          "lever" if getattr(ext.base, "surge", None) is not None else "") +
                         (f"; the insole mapping's centre-of-pressure input is held at its training mean "
                          f"({float(ext.base.cop_ref) * COP_UNIT:.3f} m)" if getattr(ext.base, "lim_cop", False)
                          else "") +
                         "; this file holds the rest of the model")
    md.update(meta or {})
    return export(twin, path, meta=md), twin
