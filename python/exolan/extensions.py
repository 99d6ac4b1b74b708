"""Model extensions found by diagnosis: dissipation, actuation delay, sensor and strap corrections.

A conservative Lagrangian (H q̈ + c + g = τ + B f_v) cannot represent friction, delays or compliance. This
module wraps any DeLaN-based model of DESIGN.md section 2 and adds the terms of DESIGN.md section 4 *inside
the physics*, each with a parametrisation that enforces its physical sign:

| effect             | enters as                                              | constraint              |
|--------------------|--------------------------------------------------------|-------------------------|
| viscous_damping    | τ += D q̇, D = L_D L_Dᵀ                                 | D PSD (Cholesky factor) |
| coulomb_friction   | τ += Fc ⊙ tanh(q̇/ε)                                    | Fc = softplus(·) ≥ 0    |
| stribeck_friction  | τ += Fs e^{−(q̇/vs)²} tanh(q̇/ε)                        | Fs ≥ 0, vs > 0          |
| actuation_delay    | τ_rec += τ_e(t) − τ_e(t−d), fractional linear shift    | 0 ≤ d ≤ max_delay       |
| encoder_offset     | physics at q_meas − δ                                  | free sign               |
| torque_bias        | τ_rec += τ0                                            | free sign               |
| torque_gain        | τ_rec += (1 − 1/k) τ_e,rec                             | k = e^{0.1 raw} > 0     |
| strap_compliance   | physics at q_meas − τ_e,app / k (and its derivatives)  | 1/k = softplus(·) ≥ 0   |
| backlash           | physics at q_meas + (w/2) s (and its derivatives)      | w = softplus(·) ≥ 0     |

Because D is PSD and Fc, Fs ≥ 0, the dissipated power q̇ᵀ(D q̇ + Fc tanh(q̇/ε) + ...) is never negative:
the extended model is passive — its energy ½ q̇ᵀ H q̇ + V never grows without input power
(`dissipated_power`, tested).

Sequences: the delay needs the history of the exoskeleton torque. Samples are rows (B, ·); the exo torque
comes either as (B, n) (current sample) or as a history (B, K+1, n), column k = k steps earlier in the same
trial, clamped at the trial's start (`lag_table(lengths, K)` gives the flat indices to gather it), or as a
`Lagged` series that reads only the columns the delay needs. The strap needs τ̇_e and τ̈_e in the same form
(`exo_derivatives`); a backlash the side of its gap, `side=(s, ṡ, s̈)` (`gap_side`), a sensor effect that the
engine's export leaves out (the limb's dynamics are the base's; its width is metadata).
"""
from __future__ import annotations

import copy
import math
from typing import Iterable

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from .exo_signals import Lagged, Stacked, exo_derivatives, lag_table, velocity_response  # noqa: F401 (re-exported)

EFFECTS_MODELLED = ("viscous_damping", "coulomb_friction", "stribeck_friction", "actuation_delay",
                    "encoder_offset", "torque_bias", "torque_gain", "strap_compliance", "backlash")
# terms linear in their parameter, which can carry a size per subject (θ_u = θ e^{a_u})
SIZEABLE = ("viscous_damping", "coulomb_friction", "stribeck_friction", "encoder_offset", "torque_bias",
            "strap_compliance")
COULOMB_EPS = 0.01   # rad/s (or m/s): the tanh smoothing of sign(q̇), the same in the world and the engine


def _inv_softplus(y: float) -> float:
    return float(y + math.log(-math.expm1(-y)))


# physical value (vocabulary units) → the raw parameter that `ExtendedModel` learns, per effect
_TO_RAW = {
    "viscous_damping": ("damping_diag", lambda d: _inv_softplus(math.sqrt(d))),     # D_jj = softplus(raw)²
    "coulomb_friction": ("coulomb_raw", lambda f: _inv_softplus(f)),
    "stribeck_friction": ("stribeck_fs_raw", lambda f: _inv_softplus(f)),
    "encoder_offset": ("offset_raw", lambda o: o / 0.01),
    "torque_bias": ("bias_raw", lambda b: b),
    # ln k in units of 0.1: k = e^{0.1 raw} > 0 (the sign constraint), a = 1 − 1/k ≈ 0.1 raw near k = 1
    "torque_gain": ("gain_raw", lambda k: math.log(max(k, 1e-3)) / 0.1),
    # compliance 1/k in units of 0.01 rad/(N m): strap stiffnesses of 10..1000 N m/rad are O(0.01..1)
    "strap_compliance": ("compliance_raw", lambda k: _inv_softplus(max(1.0 / k / 0.01, 1e-4))),
    "backlash": ("backlash_raw", lambda w: _inv_softplus(max(w / 0.01, 1e-4))),     # width in units of 0.01 rad
}


def _stiffness(compliance: np.ndarray) -> np.ndarray:
    """k = 1/compliance, +inf where the compliance is 0 (no strap term on that joint)."""
    c = np.asarray(compliance, dtype=np.float64)
    out = np.full_like(c, np.inf)
    np.divide(1.0, c, out=out, where=c > 0)
    return out


class ExtendedModel(nn.Module):
    """A base DeLaN-type model plus the section-4 terms on chosen joints.

    `effects`: iterable of (effect, joint index) pairs; an effect may appear on several joints (damping on
    several joints gives a full PSD matrix over those joints). `dt` is the sample time (delay in samples),
    `max_delay` (s) bounds the delay (the lag table must reach max_delay/dt + 1 samples).
    `coupled_damping=False` keeps D diagonal: each joint's own friction, as the diagnosis tests it.
    The base model's parameters stay trainable: `ext_parameters()` and `base_parameters()` separate the
    groups so that a joint refit can use a larger step for the few physical scalars.

    Subject-specific terms: `init["gates"] = {effect: {joint: per-trial 0/1}}` switches a term off on the
    trials marked 0 (an effect present in some users only: one user's loose strap, one exoskeleton unit's
    friction). The per-sample gate needs the trial index (`trial=` of `inverse`, `forward_dynamics`, ...);
    without it every term acts everywhere. Parameters are shared by the trials where the term is on.

    Per-subject sizes: `init["sized"] = {effect: {joint: None or per-subject log sizes}}` with
    `init["subject_of_trial"]` (a subject index per trial) gives every subject u its own value θ_u = θ e^{a_u}
    of a term linear in its parameter (the frictions, the offset, the bias, the compliance; not the delay,
    whose gate is a switch, nor the gain, whose θ_u could cross k = ∞). The log sizes are learnt with the
    other terms and centred (Σ_u a_u = 0), so θ stays the subjects' geometric mean; e^{a_u} > 0 keeps every
    subject's friction dissipative. `physical(trial)` gives a trial's own values (its subject's).
    """

    def __init__(self, base: nn.Module, n: int, effects: Iterable[tuple[str, int]] = (), dt: float = 0.005,
                 max_delay: float = 0.1, coulomb_eps: float = COULOMB_EPS, init: dict | None = None,
                 coupled_damping: bool = True):
        super().__init__()
        self.base = base
        # False: D stays diagonal (independent joint friction); True: a full PSD D over the damped joints
        self.coupled_damping = bool(coupled_damping)
        self.n = int(n)
        self.dt = float(dt)
        self.max_delay = float(max_delay)
        self.coulomb_eps = float(coulomb_eps)
        self.effects: dict[str, list[int]] = {}
        for eff, j in effects:
            if eff not in EFFECTS_MODELLED:
                raise ValueError(f"effect {eff!r} cannot be modelled (modelled: {', '.join(EFFECTS_MODELLED)})")
            if not 0 <= int(j) < self.n:
                raise ValueError(f"joint index {j} out of range for {self.n} joints")
            self.effects.setdefault(eff, [])
            if int(j) not in self.effects[eff]:
                self.effects[eff].append(int(j))
        init = dict(init or {})
        gates = init.pop("gates", None) or {}
        sized = init.pop("sized", None) or {}
        subject_of_trial = init.pop("subject_of_trial", None)
        n = self.n
        dtype = next(base.parameters()).dtype if any(True for _ in base.parameters()) else torch.float64
        self.gated: tuple[str, ...] = ()
        self.sized: tuple[str, ...] = ()
        if sized:
            if subject_of_trial is None:
                raise ValueError("init['sized'] needs init['subject_of_trial'] (a subject index per trial)")
            subj = torch.as_tensor(np.asarray(subject_of_trial, dtype=np.int64).reshape(-1))
            if len(subj) == 0 or int(subj.min()) < 0:
                raise ValueError("init['subject_of_trial'] must hold a subject index >= 0 for every trial")
            self.register_buffer("subject_of_trial", subj, persistent=False)
            n_subj = int(subj.max()) + 1
        for eff, per_joint in sized.items():
            if eff not in SIZEABLE:
                raise ValueError(f"per-subject sizes for {eff!r}: only terms linear in their parameter have them "
                                 f"({', '.join(SIZEABLE)})")
            if eff not in self.effects:
                raise ValueError(f"per-subject sizes for {eff!r}, which is not among the model's effects")
            a = torch.zeros(n_subj, n, dtype=dtype)
            on = torch.zeros(n, dtype=dtype)
            for j, v in per_joint.items():
                if int(j) not in self.effects[eff]:
                    raise ValueError(f"per-subject sizes for {eff!r} on joint {j}, where the model has no such term")
                on[int(j)] = 1.0
                if v is not None:
                    v = torch.as_tensor(np.asarray(v, dtype=np.float64).reshape(-1), dtype=dtype)
                    if len(v) != n_subj:
                        raise ValueError(f"per-subject sizes for {eff!r} on joint {j}: {len(v)} values for "
                                         f"{n_subj} subjects")
                    a[:, int(j)] = v
            self.register_parameter(f"size_{eff}", nn.Parameter(a))
            self.register_buffer(f"sized_{eff}", on, persistent=False)
            self.sized += (eff,)
        for eff, per_joint in gates.items():
            if eff not in self.effects:
                raise ValueError(f"gate for {eff!r}, which is not among the model's effects")
            rows = {int(j): np.asarray(v, dtype=np.float64).reshape(-1) for j, v in per_joint.items()}
            n_trials = {len(v) for v in rows.values()}
            if len(n_trials) != 1:
                raise ValueError(f"gates of {eff!r} differ in their number of trials")
            g = torch.ones(n_trials.pop(), n, dtype=dtype)
            for j, v in rows.items():
                if j not in self.effects[eff]:
                    raise ValueError(f"gate for {eff!r} on joint {j}, where the model has no such term")
                g[:, j] = torch.as_tensor(v, dtype=dtype)
            self.register_buffer(f"gate_{eff}", g, persistent=False)
            self.gated += (eff,)
        self.switched = self.gated           # terms switched off on some trials (`gates`)
        self.gated = tuple(dict.fromkeys(self.gated + self.sized))     # every term that needs `trial=`

        def mask(eff):
            m = torch.zeros(n, dtype=dtype)
            m[self.effects.get(eff, [])] = 1.0
            return m

        for eff in EFFECTS_MODELLED:
            self.register_buffer(f"mask_{eff}", mask(eff))
        # Raw (unconstrained) parameters. Initial values are small but not zero so that gradients of
        # softplus-squared terms do not vanish; `init` (physical units) overrides them for warm starts: a
        # number for every joint, or {joint index: number} per joint (the others keep the default).
        def start(eff, default, raw):
            v = init.get(eff, default)
            vals = [v.get(j, default) for j in range(n)] if isinstance(v, dict) else [v] * n
            return nn.Parameter(torch.tensor([float(raw(float(x))) for x in vals], dtype=dtype))

        sp = _inv_softplus
        self.damping_diag = start("viscous_damping", 0.05, _TO_RAW["viscous_damping"][1])
        self.damping_off = nn.Parameter(torch.zeros(n, n, dtype=dtype))
        self.coulomb_raw = start("coulomb_friction", 0.05, _TO_RAW["coulomb_friction"][1])
        self.stribeck_fs_raw = start("stribeck_friction", 0.05, _TO_RAW["stribeck_friction"][1])
        self.stribeck_vs_raw = start("stribeck_vs", 0.1, sp)
        # delay in samples, as a fraction of the maximum through a sigmoid: bounded on both sides
        def logit_delay(d):
            frac = min(max(d / self.max_delay, 1e-3), 1 - 1e-3)
            return math.log(frac / (1 - frac))
        self.delay_raw = start("actuation_delay", self.dt, logit_delay)
        self.offset_raw = start("encoder_offset", 0.0, _TO_RAW["encoder_offset"][1])
        self.bias_raw = start("torque_bias", 0.0, _TO_RAW["torque_bias"][1])
        self.gain_raw = start("torque_gain", 1.0, _TO_RAW["torque_gain"][1])
        self.compliance_raw = start("strap_compliance", 1000.0, _TO_RAW["strap_compliance"][1])
        self.backlash_raw = start("backlash", 1e-4, _TO_RAW["backlash"][1])

    def set_value(self, effect: str, j: int, value: float) -> None:
        """Set (effect, joint j)'s parameter to `value` in vocabulary units (strap: stiffness k). Damping sets
        the joint's own D_jj (its Cholesky diagonal; the diagnosis keeps D diagonal)."""
        if effect not in _TO_RAW:
            raise ValueError(f"set_value: {effect!r} is not set this way (settable: {', '.join(_TO_RAW)})")
        name, to_raw = _TO_RAW[effect]
        with torch.no_grad():
            getattr(self, name)[int(j)] = float(to_raw(float(value)))

    def log_sizes(self, effect: str) -> torch.Tensor:
        """(n_subjects, n) centred log sizes a_u of a sized term (0 on the joints without sizes)."""
        a = getattr(self, f"size_{effect}")
        return (a - a.mean(0, keepdim=True)) * getattr(self, f"sized_{effect}")

    def gate(self, effect: str, trial: torch.Tensor | None):
        """Per-sample factor of a term, (B, n) at the rows' trial indices (its switch, times its subject's size
        e^{a_u} where it has sizes), or 1 (everywhere on)."""
        if trial is None or effect not in self.gated:
            return 1.0
        g = getattr(self, f"gate_{effect}")[trial] if effect in self.switched else 1.0
        if effect in self.sized:
            g = g * torch.exp(self.log_sizes(effect))[self.subject_of_trial[trial]]
        return g

    def gate_trials(self) -> dict[str, dict[int, np.ndarray]]:
        """The switches in `init["gates"]` form (only switched terms): carried to refits and exports."""
        return {eff: {j: getattr(self, f"gate_{eff}")[:, j].cpu().numpy().copy() for j in self.effects[eff]}
                for eff in self.switched}

    def size_values(self) -> dict[str, dict[int, np.ndarray]]:
        """The centred per-subject log sizes in `init["sized"]` form (only sized joints)."""
        with torch.no_grad():
            return {eff: {j: self.log_sizes(eff)[:, j].cpu().numpy().copy() for j in self.effects[eff]
                          if float(getattr(self, f"sized_{eff}")[j]) > 0} for eff in self.sized}

    def subject_init(self) -> dict:
        """The `init` entries that rebuild this model's switches and sizes (at their fitted values)."""
        out = {}
        if self.switched:
            out["gates"] = self.gate_trials()
        if self.sized:
            out["sized"] = self.size_values()
            out["subject_of_trial"] = self.subject_of_trial.cpu().numpy().copy()
        return out

    def trial_factor(self, effect: str, j: int, trial: int) -> float:
        """The factor (switch × size) of (effect, joint j) on one trial."""
        with torch.no_grad():
            g = self.gate(effect, torch.tensor([int(trial)]))
        return float(g[0, j]) if torch.is_tensor(g) else float(g)

    # -- physical parameters -----------------------------------------------------------------------
    def damping_matrix(self) -> torch.Tensor:
        """D = L_D L_Dᵀ restricted to the damped joints: PSD by construction."""
        m = self.mask_viscous_damping
        Lm = torch.tril(self.damping_off, -1) * (m[:, None] * m[None, :]) * float(self.coupled_damping)
        Lm = Lm + torch.diag(F.softplus(self.damping_diag) * m)
        return Lm @ Lm.T

    def coulomb(self) -> torch.Tensor:
        return F.softplus(self.coulomb_raw) * self.mask_coulomb_friction

    def stribeck(self) -> tuple[torch.Tensor, torch.Tensor]:
        return (F.softplus(self.stribeck_fs_raw) * self.mask_stribeck_friction,
                F.softplus(self.stribeck_vs_raw) + 1e-3)

    def delay(self) -> torch.Tensor:
        """Seconds, in [0, max_delay]."""
        return torch.sigmoid(self.delay_raw) * self.max_delay * self.mask_actuation_delay

    def encoder_offset(self) -> torch.Tensor:
        return 0.01 * self.offset_raw * self.mask_encoder_offset

    def torque_bias(self) -> torch.Tensor:
        return self.bias_raw * self.mask_torque_bias

    def gain_term(self) -> torch.Tensor:
        """a = 1 − 1/k: the recorded exo torque's excess over the applied one, per unit recorded torque.

        1/k = e^{−0.1 raw}, so a < 1 and k > 0 for every raw value: a fit cannot reach a negative gain (an
        additive a, unbounded, did: a from-scratch fit in a strap world drove it to 1.014, k = −72, the
        recorded exo torque ignored)."""
        return -torch.expm1(-0.1 * self.gain_raw) * self.mask_torque_gain

    def compliance(self) -> torch.Tensor:
        """1/k in rad/(N m) (m/N for prismatic joints); 0 where no strap term is active."""
        return 0.01 * F.softplus(self.compliance_raw) * self.mask_strap_compliance

    def backlash(self) -> torch.Tensor:
        """The play's width w in rad (m for prismatic joints); 0 where no backlash term is active."""
        return 0.01 * F.softplus(self.backlash_raw) * self.mask_backlash

    def physical(self, trial: int | None = None) -> dict[str, np.ndarray]:
        """Every parameter in the units of the effect vocabulary (DATA_LAYOUT.md), per joint; with `trial`, the
        values that act on that trial (a switched-off term neutral, a sized term at its subject's size)."""
        with torch.no_grad():
            t = None if trial is None else torch.tensor([int(trial)])
            f = lambda eff: (lambda g: g[0] if torch.is_tensor(g) else g)(self.gate(eff, t))
            fs, vs = self.stribeck()
            c = self.compliance() * f("strap_compliance")
            a = self.gain_term() * f("torque_gain")
            gd = torch.sqrt(torch.as_tensor(f("viscous_damping"), dtype=vs.dtype) * torch.ones_like(vs))
            return {
                # diag(√g) D diag(√g): PSD, and each joint's own damping times its factor (D is diagonal in
                # the diagnosis)
                "viscous_damping": (gd[:, None] * self.damping_matrix() * gd[None, :]).cpu().numpy().copy(),
                "coulomb_friction": (self.coulomb() * f("coulomb_friction")).cpu().numpy().copy(),
                "stribeck_friction": (fs * f("stribeck_friction")).cpu().numpy().copy(),
                "stribeck_vs": vs.cpu().numpy().copy(),
                "actuation_delay": (self.delay() * f("actuation_delay")).cpu().numpy().copy(),
                "encoder_offset": (self.encoder_offset() * f("encoder_offset")).cpu().numpy().copy(),
                "torque_bias": (self.torque_bias() * f("torque_bias")).cpu().numpy().copy(),
                "torque_gain": (1.0 / (1.0 - a)).cpu().numpy().copy(),
                "strap_compliance": _stiffness(c.cpu().numpy()),
                "backlash": (self.backlash() * f("backlash")).cpu().numpy().copy(),
            }

    def without(self, terms: Iterable[tuple[str, int]]) -> "ExtendedModel":
        """A copy with the terms (effect, joint) switched off (their masks 0: every term is then neutral, a gain
        k = 1, a delay 0), the rest of the model as fitted: what the model owes to those terms alone."""
        out = copy.deepcopy(self)
        for effect, j in terms:
            if int(j) not in self.effects.get(effect, []):
                raise ValueError(f"without: the model has no {effect!r} term on joint {j}")
            getattr(out, f"mask_{effect}")[int(j)] = 0.0
        return out

    def estimate(self, effect: str, joint: int) -> float:
        """The scalar parameter that the vocabulary reports for (effect, joint)."""
        p = self.physical()
        if effect == "viscous_damping":
            return float(p[effect][joint, joint])
        return float(p[effect][joint])

    def ext_parameters(self) -> list[nn.Parameter]:
        base_ids = {id(p) for p in self.base.parameters()}
        return [p for p in self.parameters() if id(p) not in base_ids]

    def base_parameters(self) -> list[nn.Parameter]:
        return list(self.base.parameters())

    # -- pieces of the physics ---------------------------------------------------------------------
    @staticmethod
    def _hist(x):
        """A history (`Lagged`, or a (B, K+1, n) or (B, n) tensor as `Stacked`), or None."""
        return x if x is None or isinstance(x, Lagged) else Stacked(x)

    def _shift(self, hist, d: torch.Tensor) -> torch.Tensor:
        """x(t − d) per joint by linear interpolation between the two bracketing samples of the history."""
        if hist.K < 1:
            raise ValueError("a delay needs the exo-torque history (B, K+1, n) with K >= 1")
        s = torch.clamp(d / self.dt, 0.0, hist.K - 1e-9)     # (n,) samples
        k0 = torch.floor(s).detach()
        frac = s - k0                                          # differentiable in d
        k0 = k0.long()
        return (1.0 - frac) * hist.column(k0) + frac * hist.column(k0 + 1)

    def applied_exo(self, tau_e, tau_e_d=None, tau_e_dd=None, trial=None):
        """τ_e,app and its derivatives at the current sample, from (B, n) or history (B, K+1, n) inputs.

        The applied torque is the recorded one delayed by d where the delay term is active.
        """
        h, hd, hdd = self._hist(tau_e), self._hist(tau_e_d), self._hist(tau_e_dd)
        now = lambda x: None if x is None else x.now()     # noqa: E731
        if "actuation_delay" not in self.effects:
            return now(h), now(hd), now(hdd)
        d = self.delay()
        m = self.mask_actuation_delay * self.gate("actuation_delay", trial)
        sh = lambda x: None if x is None else m * self._shift(x, d) + (1 - m) * x.now()
        return sh(h), sh(hd), sh(hdd)

    def true_state(self, q, qd, qdd, tau_app=None, tau_app_d=None, tau_app_dd=None, trial=None, side=None):
        """Measured -> physical coordinates: remove the encoder offset, the strap deflection and the backlash gap."""
        if "backlash" in self.effects and side is not None:
            h = 0.5 * self.backlash() * self.gate("backlash", trial)
            q, qd, qdd = q + h * side[0], qd + h * side[1], (qdd + h * side[2] if qdd is not None else None)
        if "encoder_offset" in self.effects:
            q = q - self.encoder_offset() * self.gate("encoder_offset", trial)
        if "strap_compliance" in self.effects and tau_app is not None:
            c = self.compliance() * self.gate("strap_compliance", trial)
            q = q - c * tau_app
            if tau_app_d is not None:
                qd = qd - c * tau_app_d
            if tau_app_dd is not None and qdd is not None:
                qdd = qdd - c * tau_app_dd
        return q, qd, qdd

    def friction(self, qd: torch.Tensor, trial=None) -> torch.Tensor:
        """Generalised dissipative force (the torque the actuators must add to overcome it). A gate scales a
        joint's whole friction torque by 0 or 1 (D diagonal, as the diagnosis fits it), so passivity holds."""
        out = torch.zeros_like(qd)
        if "viscous_damping" in self.effects:
            out = out + (qd @ self.damping_matrix().T) * self.gate("viscous_damping", trial)
        sgn = torch.tanh(qd / self.coulomb_eps)
        if "coulomb_friction" in self.effects:
            out = out + self.coulomb() * sgn * self.gate("coulomb_friction", trial)
        if "stribeck_friction" in self.effects:
            fs, vs = self.stribeck()
            out = out + fs * torch.exp(-(qd / vs) ** 2) * sgn * self.gate("stribeck_friction", trial)
        return out

    def dissipated_power(self, qd: torch.Tensor, trial=None) -> torch.Tensor:
        """q̇ᵀ friction(q̇) (...,): never negative (passivity)."""
        return (qd * self.friction(qd, trial)).sum(-1)

    def recording_terms(self, tau_e, tau_app, trial=None) -> torch.Tensor:
        """τ_rec − τ_physical: what the recorded total torque holds beyond the torque the limb feels."""
        out = torch.zeros_like(tau_e)
        if "actuation_delay" in self.effects:
            # tau_app is the recorded torque itself where a gate has the delay off
            out = out + (tau_e - tau_app) * self.mask_actuation_delay
        if "torque_bias" in self.effects:
            out = out + self.torque_bias() * self.gate("torque_bias", trial)
        if "torque_gain" in self.effects:
            out = out + self.gain_term() * tau_e * self.gate("torque_gain", trial)
        return out

    # -- the model interface -----------------------------------------------------------------------
    def inverse(self, q, qd, qdd, z, f_v, tau_e=None, tau_e_d=None, tau_e_dd=None, trial=None, side=None):
        """Predicted recorded total torque τ_rec (B, n).

        tau_e, tau_e_d, tau_e_dd: recorded exo torque and its smoothed derivatives, either (B, n) for the
        current sample or (B, K+1, n) histories (column k = k samples earlier, clamped at the trial start;
        `lag_table` builds the indices), or `Lagged` series. The delay term needs the history. `trial` (B,):
        the rows' trial indices, for gated (subject-specific) terms. `side`: (s, ṡ, s̈) of a backlash gap
        (`gap_side`).
        """
        return self.inverse_inertia(q, qd, qdd, z, f_v, tau_e, tau_e_d, tau_e_dd, trial, side)[0]

    def inverse_inertia(self, q, qd, qdd, z, f_v, tau_e=None, tau_e_d=None, tau_e_dd=None, trial=None, side=None):
        """(`inverse`, H): H(q, z) at the physical coordinates the base used, or None where the base does not
        expose its inertia (a fit's acceleration term reuses it instead of evaluating the network again)."""
        if tau_e is None:
            tau_e = torch.zeros_like(q)
        tau_now = self._hist(tau_e).now()
        tau_app, tau_app_d, tau_app_dd = self.applied_exo(tau_e, tau_e_d, tau_e_dd, trial)
        qt, qdt, qddt = self.true_state(q, qd, qdd, tau_app, tau_app_d, tau_app_dd, trial, side)
        if hasattr(self.base, "inverse_inertia"):
            tau, H = self.base.inverse_inertia(qt, qdt, qddt, z, f_v)
        else:
            tau, H = self.base.inverse(qt, qdt, qddt, z, f_v), None
        return tau + self.friction(qdt, trial) + self.recording_terms(tau_now, tau_app, trial), H

    def forward_dynamics(self, q, qd, tau, z, f_v, tau_e=None, tau_app=None, trial=None):
        """q̈ in *physical* coordinates (q, q̇ physical) for the recorded total torque τ.

        τ_phys = τ − recording terms; the friction opposes q̇. `tau_app` (delayed exo torque) defaults to
        τ_e (no delay).
        """
        if tau_e is None:
            tau_e = torch.zeros_like(q)
        if tau_app is None:
            tau_app = tau_e
        tau_phys = tau - self.recording_terms(tau_e, tau_app, trial) - self.friction(qd, trial)
        return self.base.forward_dynamics(q, qd, tau_phys, z, f_v)

    def terms(self, q, qd, z):
        return self.base.terms(q, qd, z)

    def context(self, x):
        return self.base.context(x)

    # -- export (DESIGN.md section 4) ----------------------------------------------------------------
    def ext_tensors(self, trial: int | None = None) -> dict[str, np.ndarray]:
        """`ext.*` float64 tensors for the weight file; only the active effects are written (absent = off).

        Joints without the effect get the neutral value: 0 for additive terms, k = 1 for torque_gain,
        k = +inf (compliance 0) for strap_compliance; stribeck_vs is written for every joint (unused where
        Fs = 0). `trial`: the values that act on that trial (`physical`), for a user's own file.
        """
        p = self.physical(trial)
        out: dict[str, np.ndarray] = {}
        f64 = lambda x: np.ascontiguousarray(np.asarray(x, dtype=np.float64))
        if "viscous_damping" in self.effects:
            out["ext.damping"] = f64(p["viscous_damping"])
        if "coulomb_friction" in self.effects:
            out["ext.coulomb"] = f64(p["coulomb_friction"])
        if "stribeck_friction" in self.effects:
            out["ext.stribeck_fs"] = f64(p["stribeck_friction"])
            out["ext.stribeck_vs"] = f64(p["stribeck_vs"])
        if "actuation_delay" in self.effects:
            out["ext.delay"] = f64(p["actuation_delay"])
        if "encoder_offset" in self.effects:
            out["ext.encoder_offset"] = f64(p["encoder_offset"])
        if "torque_bias" in self.effects:
            out["ext.torque_bias"] = f64(p["torque_bias"])
        if "torque_gain" in self.effects:
            out["ext.torque_gain"] = f64(p["torque_gain"])
        if "strap_compliance" in self.effects:
            out["ext.strap_compliance"] = f64(p["strap_compliance"])
        return out
