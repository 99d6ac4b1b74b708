"""The 8 architectures x LIM on/off (16 methods), selected by name, behind one interface.

    model.context(x)                           # (B, T, C) raw context features -> z (B, T, dz), causal
    model.inverse(q, qd, qdd, z, f_v)          # predicted total actuated torque (..., n)
    model.forward_dynamics(q, qd, tau, z, f_v) # DeLaN-based only: q̈
    model.terms(q, qd, z)                      # DeLaN-based only: Terms(H, c, g)

Physics (DESIGN.md section 2): H q̈ + c + g = τ + B f_v, so inverse = H q̈ + c + g − B f_v and
forward = H⁻¹(τ + B f_v − c − g). Black-box models predict τ directly from [q; q̇; q̈; z].

state_dict names are the export names (DESIGN.md section 3): `norm.*`, `encoder.tcn.{i}.*` /
`encoder.lstm.*`, `delan.L.*`, `delan.V.*`, `lim.*`, `head.*`. Fixed scales (v_scale, lim_scale, the
black-box input/output scaling) are construction arguments kept in `model.config`, not in the state_dict,
so that a run is rebuilt as `build_model(**meta)` + `load_state_dict`.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from . import delan as _delan
from .delan import Lagrangian, Terms, mlp, mlp_forward
from .encoder import LSTMEncoder, Normalizer, TCNEncoder
from .lim import LIM

# name -> (core, encoder); core "delan" | "mlp" (2 x head_hidden) | "linear" (one layer)
ARCHITECTURES = {
    "exolan": ("delan", "tcn"),
    "delan-tcn": ("delan", "tcn"),
    "delan-lstm": ("delan", "lstm"),
    "delan": ("delan", "none"),
    "mlp-tcn": ("mlp", "tcn"),
    "mlp-lstm": ("mlp", "lstm"),
    "mlp": ("mlp", "none"),
    "tcn": ("linear", "tcn"),
    "lstm": ("linear", "lstm"),
}
METHODS = ("exolan", "delan-lstm", "delan", "mlp-tcn", "mlp-lstm", "mlp", "tcn", "lstm")

MODEL_DEFAULTS = dict(
    hidden=64,            # DeLaN networks: 2 x 64
    head_hidden=96,       # black-box MLP: 2 x 96
    lim_hidden=16,        # LIM: 2 x 16
    z_dim=16,             # encoder width = z dimension
    tcn_levels=5,
    tcn_kernel=2,
    lstm_layers=5,
    softplus_offset=1e-2,  # on L's diagonal: H ⪰ offset² I
    v_scale=1.0,           # N m per unit of the potential network's gradient
    lim_scale=0.1,         # m per unit of the LIM output
    state_mean=None,       # black-box input scaling of [q; q̇; q̈] (3n values)
    state_std=None,
    tau_scale=None,        # black-box output scale per joint (n values), N m
)


def canonical_method(method: str) -> str:
    m = method.lower()
    if m == "delan-tcn":
        m = "exolan"
    if m not in ARCHITECTURES:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    return m


class ExoModel(nn.Module):
    def __init__(self, method: str, lim: bool, joint_types: Sequence[str], context_channels: Sequence[str],
                 joint_names: Sequence[str] | None = None, **cfg):
        super().__init__()
        unknown = set(cfg) - set(MODEL_DEFAULTS)
        if unknown:
            raise TypeError(f"unknown model option(s): {', '.join(sorted(unknown))}")
        c = {**MODEL_DEFAULTS, **cfg}
        self.method = canonical_method(method)
        self.core, self.encoder_kind = ARCHITECTURES[self.method]
        self.use_lim = bool(lim)
        self.joint_types = tuple(joint_types)
        self.joint_names = tuple(joint_names) if joint_names is not None else tuple(f"q{j}" for j in range(len(self.joint_types)))
        self.context_channels = tuple(context_channels)
        n = len(self.joint_types)
        self.n = n
        C = len(self.context_channels)

        if self.encoder_kind == "none":
            self.z_dim = 0
            self.norm = None
            self.encoder = None
        else:
            if C == 0:
                raise ValueError("a context encoder needs at least one context channel")
            self.z_dim = int(c["z_dim"])
            self.norm = Normalizer(C)
            if self.encoder_kind == "tcn":
                self.encoder = TCNEncoder(C, self.z_dim, int(c["tcn_levels"]), int(c["tcn_kernel"]))
            else:
                self.encoder = LSTMEncoder(C, self.z_dim, int(c["lstm_layers"]))

        self.delan = None
        self.head = None
        if self.core == "delan":
            self.delan = Lagrangian(self.joint_types, self.z_dim, int(c["hidden"]),
                                    float(c["softplus_offset"]), float(c["v_scale"]))
        else:
            d_in = 3 * n + self.z_dim
            if self.core == "mlp":
                self.head = mlp(d_in, int(c["head_hidden"]), n)
            else:
                self.head = nn.ModuleList([nn.Linear(d_in, n)])
            mean = c["state_mean"] if c["state_mean"] is not None else [0.0] * (3 * n)
            std = c["state_std"] if c["state_std"] is not None else [1.0] * (3 * n)
            tau_scale = c["tau_scale"] if c["tau_scale"] is not None else [1.0] * n
            # not persistent: fixed scales travel in the config, the state_dict holds learned weights only
            self.register_buffer("state_mean", torch.tensor(mean, dtype=torch.float32), persistent=False)
            self.register_buffer("state_std", torch.tensor(std, dtype=torch.float32), persistent=False)
            self.register_buffer("tau_scale", torch.tensor(tau_scale, dtype=torch.float32), persistent=False)
        self.lim = LIM(self.joint_types, self.z_dim, int(c["lim_hidden"]), float(c["lim_scale"])) if self.use_lim else None
        self.config = {k: (list(map(float, v)) if isinstance(v, (list, tuple, torch.Tensor)) else v)
                       for k, v in c.items()}

    # -- descriptive ------------------------------------------------------------------------------
    @property
    def is_lagrangian(self) -> bool:
        return self.delan is not None

    @property
    def receptive_field(self) -> int:
        return self.encoder.receptive_field if self.encoder_kind == "tcn" else 1

    def spec(self) -> dict:
        """Everything `build_model` needs to rebuild this model (JSON-serialisable)."""
        return dict(method=self.method, lim=self.use_lim, joint_types=list(self.joint_types),
                    joint_names=list(self.joint_names), context_channels=list(self.context_channels),
                    **self.config)

    # -- the interface ----------------------------------------------------------------------------
    def context(self, x: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """x (B, T, C) raw context features -> z (B, T, dz). `keep` (B, T): 0 before the trial start
        (for training chunks that begin before it); None = the sequence starts at the trial start."""
        if self.encoder is None:
            return x.new_zeros(*x.shape[:-1], 0)
        return self.encoder(self.norm(x), keep)

    def _z(self, z, like: torch.Tensor) -> torch.Tensor:
        if z is None:
            if self.z_dim:
                raise ValueError(f"method {self.method!r} needs a context z")
            return like.new_zeros(*like.shape[:-1], 0)
        return z

    def contact(self, q, z, f_v) -> torch.Tensor:
        """τ_c = B(q, z) f_v (zero without LIM)."""
        if self.lim is None:
            return torch.zeros_like(q)
        return self.lim.contact_torque(q, self._z(z, q), f_v)

    def terms(self, q, qd, z=None) -> Terms:
        self._need_lagrangian("terms")
        return self.delan.terms(q, qd, self._z(z, q))

    def gravity(self, q, z=None) -> torch.Tensor:
        """g(q, z) = ∂V/∂q alone."""
        self._need_lagrangian("gravity")
        return self.delan.gravity(q, self._z(z, q))

    def inverse(self, q, qd, qdd, z=None, f_v=None) -> torch.Tensor:
        if self.delan is not None:
            return self.inverse_inertia(q, qd, qdd, z, f_v)[0]
        z = self._z(z, q)
        s = (torch.cat([q, qd, qdd], dim=-1) - self.state_mean) / self.state_std
        x = torch.cat([s, z.expand(*q.shape[:-1], self.z_dim)], dim=-1) if self.z_dim else s
        tau = self.tau_scale * mlp_forward(self.head, x)
        if self.lim is not None:
            tau = tau - self.contact(q, z, self._fv(f_v, q))
        return tau

    def inverse_inertia(self, q, qd, qdd, z=None, f_v=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(`inverse`, H) of a DeLaN-based model: τ = H q̈ + c + g − B f_v from one evaluation of the
        Lagrangian's terms, and the inertia it used (a diagnosis fit's acceleration term reuses H instead of
        evaluating the network again)."""
        self._need_lagrangian("inverse_inertia")
        z = self._z(z, q)
        tau, H = _delan.inverse_dynamics_inertia(self.delan, q, qd, qdd, z)
        if self.lim is not None:
            tau = tau - self.contact(q, z, self._fv(f_v, q))
        return tau, H

    def forward_dynamics(self, q, qd, tau, z=None, f_v=None) -> torch.Tensor:
        self._need_lagrangian("forward_dynamics")
        z = self._z(z, q)
        rhs = tau + self.contact(q, z, self._fv(f_v, q)) if self.lim is not None else tau
        return _delan.forward_dynamics(self.delan, q, qd, rhs, z)

    def inverse_and_forward(self, q, qd, qdd, tau, z=None, f_v=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(τ̂, q̈̂) from one evaluation of the terms: the training loss with w_fd needs both."""
        self._need_lagrangian("inverse_and_forward")
        z = self._z(z, q)
        Lm, H, c, g = self.delan.factor_terms(q, qd, z)
        tc = self.contact(q, z, self._fv(f_v, q)) if self.lim is not None else torch.zeros_like(q)
        tau_hat = (H @ qdd.unsqueeze(-1)).squeeze(-1) + c + g - tc
        qdd_hat = _delan.solve_factor(Lm, tau + tc - c - g)
        return tau_hat, qdd_hat

    def energy(self, q, qd, z=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(T, V) of the conservative model."""
        self._need_lagrangian("energy")
        return _delan.energy(self.delan, q, qd, self._z(z, q))

    def _fv(self, f_v, q):
        if f_v is None:
            raise ValueError("a model with LIM needs the insole force f_v")
        return f_v

    def _need_lagrangian(self, what: str) -> None:
        if self.delan is None:
            raise TypeError(f"{what} needs a DeLaN-based method; {self.method!r} is a black box")


def build_model(method: str, lim: bool = True, joint_types: Sequence[str] = ("revolute", "revolute"),
                context_channels: Sequence[str] = (), joint_names: Sequence[str] | None = None,
                **cfg) -> ExoModel:
    """Construct a model by name (`exolan`, `delan-lstm`, `delan`, `mlp-tcn`, `mlp-lstm`, `mlp`, `tcn`,
    `lstm`); `lim=False` is `--no-lim`. Unknown options raise TypeError."""
    return ExoModel(method, lim, joint_types, context_channels, joint_names, **cfg)
