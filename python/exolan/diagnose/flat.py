"""The diagnosis data: every trial's samples stacked (`Flat`), cut into held-out time segments, with the other
leg's signals where a trial has a partner and the exo torque's copy of the joint torque (`exo_copy`).

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

from ..data import DataError, savgol_window
from ..exo_signals import Lagged, exo_derivatives, gap_side, lag_table, velocity_response

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
    side: torch.Tensor | None = None    # (N, n) the side of a backlash gap the limb rests on (`gap_side`)
    side_d: torch.Tensor | None = None  # its derivatives, as the measured q̇ and q̈ would show them
    side_dd: torch.Tensor | None = None

    def __post_init__(self):
        # the partnered insole input packed once: one gather a fit step instead of five and a cat
        self._insole = (torch.cat([self.f_v[:, None], self.f_o[:, None], self.kin_o, self.surge, self.x_cop[:, None]],
                                  -1) if self.has_partner else self.f_v)

    def forces(self, idx) -> torch.Tensor:
        """The insole input of the models at rows idx: f_v (B,), or with a partner (B, 11): [f_v, f_v,other/(M g),
        q, q̇, q̈ of the other hip, the 5 surge features, x_cop] (the pelvis's vertical load, tilt and fore-aft
        acceleration, `base` module docstring; the own centre of pressure), packed when the Flat is made."""
        return self._insole.index_select(0, idx)

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

    def subjects_of(self, idx: torch.Tensor) -> np.ndarray:
        """The subject of each row idx (its trial's)."""
        return np.array([self.trial_meta[i]["subject"] for i in self.trial[idx].numpy()])

    def user_index(self) -> tuple[list, np.ndarray] | None:
        """The subjects (sorted) and every row's subject index; None for one subject (or recordings named after
        their files, layout 2 without a subject column)."""
        users = sorted({m["subject"] for m in self.trial_meta})
        if len(users) < 2 or all(m["subject"] == m["name"] for m in self.trial_meta):
            return None
        trial_user = np.array([users.index(m["subject"]) for m in self.trial_meta])
        return users, trial_user[self.trial.numpy()]

    def user_masks(self) -> list[np.ndarray] | None:
        """One 0/1 row mask per subject (`user_index`'s order); None for one subject."""
        who = self.user_index()
        return None if who is None else [(who[1] == k).astype(float) for k in range(len(who[0]))]

    def exo_lagged(self, idx: torch.Tensor, dtype: torch.dtype | None = None):
        """The histories of τ_e, τ̇_e, τ̈_e at rows idx as `Lagged` series (in `dtype`, default their own): a delay
        reads two columns of each, not K+1 (a fit's hot path)."""
        shared: dict = {}
        return tuple(Lagged(x if dtype is None else x.to(dtype), self.lag, idx, shared)
                     for x in (self.tau_e, self.tau_e_d, self.tau_e_dd))


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


def folds(flat: Flat, k: int = 4) -> np.ndarray:
    """The cross-fitting fold of every row: 0 the held-out segments, 1..k−1 each trial's other segments in turn,
    so that every segment is held out once (`physics_subjects`: a subject form judged on all the data)."""
    seg, held, trial = flat.segment.numpy(), flat.held.numpy().astype(bool), flat.trial.numpy()
    fold = np.zeros(len(seg), dtype=np.int64)
    for t in np.unique(trial):
        own = (trial == t) & ~held
        _, rank = np.unique(seg[own], return_inverse=True)
        fold[own] = 1 + rank % (k - 1)
    return fold


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
                            "trial", "segment", "held", "side", "side_d", "side_dd")}
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
        side = gap_side(np.asarray(t.q, dtype=np.float64), dt)     # a backlash's shift, through the same filters
        s1, s2 = exo_derivatives(side, dt, response=v_resp, qdd_window=savgol_window(dt))
        cols["side"].append(side); cols["side_d"].append(s1); cols["side_dd"].append(s2)
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
                has_partner=bool(partners == len(trials) and np.abs(cat["f_o"]).max() > 0),
                side=f("side"), side_d=f("side_d"), side_dd=f("side_dd"))
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

