"""The diagnosis' base models: a DeLaN + LIM with a learned constant context per trial (`SlowContextDeLaN`), a
given run at its pooled context (`PooledContext`), and the pelvis and centre-of-pressure terms both carry.

Why a slow context: a context encoder that sees a 315 ms window of q, q̇ and forces can make g(q, z) and
B(q, z) f_v vary within a stride and imitate damping, friction or lag (DIAGNOSIS_PITFALLS.md). The
diagnosis therefore judges a DeLaN + LIM whose context z is a *learned constant per trial* (one code per
recording, e.g. one user's leg in one task): it carries body size, mass and the trial's mean loading, but
cannot carry q̇ within a step. A given run (`--model`) is used the same way: its encoder's z is pooled
(averaged) over each trial and becomes that trial's code (`PooledContext`). A run's networks were trained with
a z that moves within a stride; at the pooled z they misfit, so by default (`Settings.adapt_model`) the
diagnosis first fits the pooled model, with the terms below, to the training segments, with its own base's
schedule; the run's weights are the starting point (and an extended model starts there too, its terms present from
the first step, as `refits.fresh_fit` does for a base trained here; measured: docs/DIAGNOSIS.md, "Measurements
behind the code").

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
Measured: docs/DIAGNOSIS.md, "Measurements behind the code".

Why the insole mapping sees the centre of pressure (`Settings.lim_cop`, on by default, needs a partner: the
CoP travels in `Flat.forces`): the insoles measure no shear, and the ground force's moment about the hip is
mostly that of its unmeasured horizontal part (a lever of the hip's height). Where the force aims changes over
the stance (ahead of the hip in loading, behind it at push-off), and the stance phase is what the CoP's
heel-to-toe travel tracks; the joint angles alone do not pin it down, and a slow context cannot carry it. So
the lever arms are B(q, x_cop, z) (one more input to the LIM; 0 force, 0 torque, so it cannot act in swing).
Measured: docs/DIAGNOSIS.md, "Measurements behind the code".
The export holds the CoP input at its training mean (the engine has one insole input; the metadata says so).

Optional (`Settings.pelvis_tilt`, off by default): the pelvis tilts with the hips' flexion (the trunk leans
into squats and landings), so the thigh's angle in an inertial frame is q_hip − τ_t q_hip,other once the
leg's own share is absorbed into its coordinates. With a partner the base can evaluate its Lagrangian at
(q − τ_t q_o e₀, q̇ − τ_t q̇_o e₀, q̈ − τ_t q̈_o e₀), one learned scalar τ_t — a coordinate shift, even in time
reversal, so it cannot imitate dissipation. Not the default: it leaves the hip's damping-like misfit and biases a
planted hip Coulomb friction up (measured: docs/DIAGNOSIS.md, "Measurements behind the code").
"""
from __future__ import annotations

import torch
from torch import nn

from ..delan import Lagrangian, energy as _energy, solve_inertia
from ..lim import LIM
from ..extensions import ExtendedModel
from .flat import DTYPE, F_OTHER_HIP, F_SURGE, F_X_COP, GRAVITY, Flat


class PelvisSurge(nn.Module):
    """Torque on the leg from the pelvis's fore-aft acceleration a_x, estimated from both insoles.

    Physics: the hip rides on the pelvis; in the hip frame its horizontal acceleration acts on the leg like a
    horizontal gravity (d'Alembert), τ = −a_x ∂(m x_com)/∂q. Insoles measure no shear force, but the ground
    force of a loaded foot points roughly from its centre of pressure at the body above the hip, so
    M a_x = Σ_legs f_x ≈ Σ_legs f_v (x_hip − x_cop)/h. Unmodelled, this torque (it follows the gait cycle)
    leaves a hip residual that a damping or a Coulomb term soaks up (measured: module docstring).

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

