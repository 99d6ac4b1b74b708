"""Training configuration: paper defaults, TOML/JSON files, strict keys.

A TOML file holds the keys of `TrainConfig` at top level and the model options in a `[model]` table:

    method = "exolan"
    lim = true
    epochs = 50
    w_fd = 0.01
    [model]
    hidden = 64

Every key must be known: a misspelt key raises instead of being silently ignored.
"""
from __future__ import annotations

import dataclasses
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .models import MODEL_DEFAULTS, canonical_method

# model options a user may set; the black-box input/output scaling always comes from the data
USER_MODEL_KEYS = ("hidden", "head_hidden", "lim_hidden", "z_dim", "tcn_levels", "tcn_kernel", "lstm_layers",
                   "softplus_offset", "v_scale", "lim_scale")


@dataclass
class TrainConfig:
    method: str = "exolan"
    lim: bool = True
    epochs: int = 1000             # paper: 1000
    seed: int = 0
    lr: float = 1e-3               # Adam
    weight_decay: float = 1e-3
    batch_size: int = 8192         # loss samples per batch (chunks x chunk_steps)
    w_fd: float = 0.0              # weight of the acceleration (forward dynamics) MSE
    w_ms: float = 0.0              # weight of the multi-step rollout loss
    horizon: int = 4               # H, steps of the multi-step loss
    ms_norm: str = "state"         # multi-step errors divided by: "state" = the training variance of q and q̇
                                   # (paper); "increment" = the variance of their h-step change (docs/RESULTS.md)
    patience: int = 0              # early stopping: epochs without a better validation loss (0 = off)
    val_users: int = 0             # training users carved out as the validation set for early stopping
    n_starts: int = 256            # N_s rollout starts per batch
    chunk_steps: int = 256         # loss steps per trial chunk (plus the encoder's warm-up before them)
    warmup: int = -1               # context steps before a chunk's loss steps; -1 = receptive field − 1 (62)
    device: str = "auto"           # auto | cpu | cuda
    threads: int = 0               # CPU threads of the run (exolan.native.cpu_threads); 0 = torch's default
    val_every: int = 10            # epochs between held-out torque MSE figures (0 = only the last epoch)
    checkpoint_every: int = 1      # epochs between checkpoints (the last epoch always)
    physics_check: bool = True     # DeLaN-based: write physics.json (PD inertia, energy drift) after training
    model: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.method = canonical_method(self.method)
        unknown = set(self.model) - set(USER_MODEL_KEYS)
        if unknown:
            raise ValueError(f"unknown model option(s) in config: {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(USER_MODEL_KEYS)})")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be auto, cpu or cuda, not {self.device!r}")
        for name in ("epochs", "batch_size", "horizon", "n_starts", "chunk_steps"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be ≥ 1")
        if self.w_fd < 0 or self.w_ms < 0:
            raise ValueError("loss weights must be ≥ 0")
        if self.ms_norm not in ("state", "increment"):
            raise ValueError(f"ms_norm must be 'state' or 'increment', not {self.ms_norm!r}")
        if self.patience < 0 or self.val_users < 0 or self.threads < 0:
            raise ValueError("patience, val_users and threads must be ≥ 0")
        if self.patience and not self.val_users:
            raise ValueError("early stopping (patience > 0) needs a validation set: set val_users ≥ 1")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown config key(s): {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(sorted(known))})")
        return cls(**d)

    def replace(self, **kw) -> "TrainConfig":
        return TrainConfig.from_dict({**self.to_dict(), **kw})


def load_config(path: str | Path) -> dict:
    """Read a TOML (or JSON) config file into a dict of TrainConfig keys (not yet validated)."""
    p = Path(path)
    if p.suffix == ".json":
        return json.loads(p.read_text())
    with open(p, "rb") as f:
        return tomllib.load(f)


def merge(base: dict, **overrides) -> TrainConfig:
    """Config from a file's dict, then non-None overrides (command-line flags win); strict keys."""
    d = dict(base)
    for k, v in overrides.items():
        if v is None:
            continue
        if k == "model":
            d["model"] = {**d.get("model", {}), **v}
        else:
            d[k] = v
    return TrainConfig.from_dict(d)


assert set(USER_MODEL_KEYS) <= set(MODEL_DEFAULTS)
