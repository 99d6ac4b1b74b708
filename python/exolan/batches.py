"""Training batches: the training set's statistics and scales, trial chunks, and the loss terms of one batch."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import torch

from .config import TrainConfig
from .losses import acceleration_loss, multistep_loss, torque_loss
from .models import ExoModel
from .rollout import rollout
from .data import context_channels, context_features, load, paper_split

# -- data ------------------------------------------------------------------------------------------

def resolve_data(data_or_split) -> tuple[list, list, str | None]:
    """(train trials, validation trials, data path) from a directory, a Split or a list of Trials."""
    if isinstance(data_or_split, (str, os.PathLike)):
        split = paper_split(load(data_or_split))
        return list(split.train), list(split.test_seen), str(data_or_split)
    if hasattr(data_or_split, "train"):
        return list(data_or_split.train), list(getattr(data_or_split, "test_seen", [])), None
    return list(data_or_split), [], None


def context_of(trial) -> np.ndarray:
    return np.asarray(context_features(trial), dtype=np.float64)


def channels_of(trial) -> list[str]:
    return list(context_channels(trial))


def _describe(trials) -> dict:
    t0 = trials[0]
    for t in trials:
        if tuple(t.joints) != tuple(t0.joints) or tuple(t.joint_types) != tuple(t0.joint_types):
            raise ValueError(f"trial {t.subject}/{t.name} has joints {t.joints}, expected {t0.joints}")
        if not math.isclose(t.dt, t0.dt, rel_tol=1e-9):
            raise ValueError(f"trial {t.subject}/{t.name} has dt {t.dt}, expected {t0.dt}")
    return dict(joint_names=list(t0.joints), joint_types=list(t0.joint_types), dt=float(t0.dt),
                context_channels=channels_of(t0))


def increment_variances(trials, horizon: int) -> tuple[list, list]:
    """Per step h = 1..H and joint: the variance of q(t+h) − q(t) and of q̇(t+h) − q̇(t) over the valid
    windows of the trials: the size of the motion that an H-step rollout has to follow."""
    dq = [[] for _ in range(horizon)]
    dqd = [[] for _ in range(horizon)]
    for t in trials:
        v = np.asarray(t.valid, bool)
        for h in range(1, horizon + 1):
            if len(v) <= h:
                continue
            ok = v[h:] & v[:-h]
            dq[h - 1].append((t.q[h:] - t.q[:-h])[ok])
            dqd[h - 1].append((t.qd[h:] - t.qd[:-h])[ok])
    var = lambda parts: [np.maximum(np.concatenate(p).var(axis=0), 1e-12).tolist() for p in parts]
    return var(dq), var(dqd)


def split_validation(trials, users: int) -> tuple[list, list]:
    """(training, validation) trials: the last `users` training users (sorted by id) become the validation
    set for early stopping. A fixed choice, so every method and seed trains on the same trials."""
    if users <= 0:
        return list(trials), []
    subjects = sorted({t.subject for t in trials})
    if users >= len(subjects):
        raise ValueError(f"val_users={users} leaves no training user (the training set has {len(subjects)})")
    held = set(subjects[-users:])
    return [t for t in trials if t.subject not in held], [t for t in trials if t.subject in held]


def compute_stats(trials, horizon: int = 4) -> dict:
    """Normalisation statistics of the training set (valid samples only; context: finite entries)."""
    v = np.concatenate([t.valid for t in trials])
    cat = lambda name: np.concatenate([getattr(t, name) for t in trials])[v]
    q, qd, qdd, tau, f_v = cat("q"), cat("qd"), cat("qdd"), cat("tau"), cat("f_v")
    ctx = np.concatenate([context_of(t) for t in trials])
    with np.errstate(invalid="ignore"):
        ctx_mean = np.nanmean(np.where(np.isfinite(ctx), ctx, np.nan), axis=0)
        ctx_std = np.nanstd(np.where(np.isfinite(ctx), ctx, np.nan), axis=0)
    ctx_mean = np.nan_to_num(ctx_mean, nan=0.0)
    ctx_std = np.nan_to_num(ctx_std, nan=1.0)
    state = np.concatenate([q, qd, qdd], axis=1)
    var_dq, var_dqd = increment_variances(trials, horizon)
    tau_std = tau.std(axis=0)
    fv_std = float(f_v.std())
    return dict(
        n_samples=int(v.sum()),
        ctx_mean=ctx_mean.tolist(), ctx_std=ctx_std.tolist(),
        state_mean=state.mean(axis=0).tolist(), state_std=np.maximum(state.std(axis=0), 1e-6).tolist(),
        tau_mean=tau.mean(axis=0).tolist(), tau_std=np.maximum(tau_std, 1e-6).tolist(),
        tau_var=tau.var(axis=0).tolist(),
        var_q=np.maximum(q.var(axis=0), 1e-12).tolist(), var_qd=np.maximum(qd.var(axis=0), 1e-12).tolist(),
        fv_std=fv_std,
        mass_mean=float(np.mean([t.mass for t in trials])),
        horizon=int(horizon), var_dq=var_dq, var_dqd=var_dqd,
    )


def data_scales(stats: dict) -> dict:
    """Fixed output scales of the networks, from the data (stored in model.json for the export):
    v_scale (N m) = mean torque std, so ∂V/∂q ~ one network unit spans the torque spread;
    lim_scale (m) = torque std / insole force std (0.1 m where there is no insole force)."""
    tau_s = float(np.mean(stats["tau_std"]))
    lim_scale = tau_s / stats["fv_std"] if stats["fv_std"] > 1e-6 else 0.1
    return dict(v_scale=tau_s, lim_scale=float(lim_scale))


@dataclass
class Chunks:
    """Trial chunks as tensors; position axis = warmup + steps."""
    ctx: torch.Tensor      # (K, P, C) raw context features (NaN allowed)
    keep: torch.Tensor     # (K, P) position lies inside the trial
    q: torch.Tensor        # (K, P, n)  invalid samples set to 0 (they never enter a loss)
    qd: torch.Tensor
    qdd: torch.Tensor
    tau: torch.Tensor
    f_v: torch.Tensor      # (K, P)
    mass: torch.Tensor     # (K,)
    loss: torch.Tensor     # (K, P) sample enters the per-sample losses
    ms_start: torch.Tensor  # (K, P) a multi-step rollout of `horizon` steps may start here
    warmup: int
    steps: int

    def to(self, device) -> "Chunks":
        kw = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in self.__dict__.items()}
        return Chunks(**kw)

    @property
    def n_loss_samples(self) -> int:
        return int(self.loss.sum())


def make_chunks(trials, warmup: int, steps: int, horizon: int, dtype=torch.float32) -> Chunks:
    W, S, P = warmup, steps, warmup + steps
    out = {k: [] for k in ("ctx", "keep", "q", "qd", "qdd", "tau", "f_v", "mass", "loss", "ms_start")}
    for t in trials:
        T = len(t.q)
        K = -(-T // S)
        right = K * S - T
        valid = np.asarray(t.valid, dtype=bool)
        # rollout starts: the start and the next `horizon` samples all valid and inside the trial
        ms = np.zeros(T, dtype=bool)
        if T > horizon:
            win = np.lib.stride_tricks.sliding_window_view(valid, horizon + 1)
            ms[: T - horizon] = win.all(axis=1)

        def chunked(a, fill=0.0):
            a = np.asarray(a)
            pad = [(W, right)] + [(0, 0)] * (a.ndim - 1)
            ap = np.pad(a, pad, constant_values=fill)
            idx = np.arange(K)[:, None] * S + np.arange(P)[None, :]
            return ap[idx]

        clean = lambda a: np.where(valid.reshape(-1, *([1] * (np.ndim(a) - 1))), a, 0.0)
        inside = chunked(np.ones(T, dtype=bool), False)
        loss_region = np.zeros(P, dtype=bool)
        loss_region[W:] = True
        ms_region = loss_region.copy()
        ms_region[P - horizon:] = False        # the rollout's targets must lie in the same chunk
        out["ctx"].append(chunked(context_of(t)))
        out["keep"].append(inside)
        out["q"].append(chunked(clean(t.q)))
        out["qd"].append(chunked(clean(t.qd)))
        out["qdd"].append(chunked(clean(t.qdd)))
        out["tau"].append(chunked(clean(t.tau)))
        out["f_v"].append(chunked(clean(t.f_v)))
        out["mass"].append(np.full(K, float(t.mass)))
        out["loss"].append(chunked(valid, False) & loss_region)
        out["ms_start"].append(chunked(ms, False) & ms_region)
    cat = {k: np.concatenate(v) for k, v in out.items()}
    f = lambda a: torch.as_tensor(a, dtype=dtype)
    b = lambda a: torch.as_tensor(a, dtype=torch.bool)
    return Chunks(ctx=f(cat["ctx"]), keep=b(cat["keep"]), q=f(cat["q"]), qd=f(cat["qd"]), qdd=f(cat["qdd"]),
                  tau=f(cat["tau"]), f_v=f(cat["f_v"]), mass=f(cat["mass"]), loss=b(cat["loss"]),
                  ms_start=b(cat["ms_start"]), warmup=W, steps=S)


# -- one batch -------------------------------------------------------------------------------------

def batch_losses(model: ExoModel, ch: Chunks, idx: torch.Tensor, cfg: TrainConfig, w_q, w_qd,
                 dt: float, gen: torch.Generator | None) -> dict[str, torch.Tensor]:
    """Loss terms of the chunks `idx`: the encoder runs once over each whole chunk. w_q, w_qd: the multi-step
    error weights, (n,) or per step (H, n) (see `ms_weights`)."""
    W = ch.warmup
    z_full = model.context(ch.ctx[idx], ch.keep[idx])                   # (b, P, dz)
    q, qd, qdd, tau, f_v = (a[idx][:, W:] for a in (ch.q, ch.qd, ch.qdd, ch.tau, ch.f_v))
    z = z_full[:, W:]
    mask = ch.loss[idx][:, W:]
    mass = ch.mass[idx].unsqueeze(1).expand_as(mask)
    out = {}
    qdd_hat = None
    if cfg.w_fd > 0 or cfg.w_ms > 0:
        tau_hat, qdd_hat = model.inverse_and_forward(q, qd, qdd, tau, z, f_v)
        if cfg.w_fd > 0:
            out["fd"] = acceleration_loss(qdd_hat, qdd, mask)
    else:
        tau_hat = model.inverse(q, qd, qdd, z, f_v)
    out["tau"] = torque_loss(tau_hat, tau, mass, mask)
    if cfg.w_ms > 0:
        starts = ch.ms_start[idx].nonzero()                                # (M, 2): chunk row, position
        if len(starts):
            pick = torch.randperm(len(starts), generator=gen)[: cfg.n_starts].to(starts.device)
            r, k = starts[pick, 0], starts[pick, 1]
            H = cfg.horizon
            steps = k.unsqueeze(1) + torch.arange(H + 1, device=k.device)    # (N_s, H + 1)
            rows = idx[r].unsqueeze(1)
            g = lambda a: a[rows, steps]
            qs, qds = g(ch.q), g(ch.qd)
            zs = z_full[r.unsqueeze(1), steps[:, :H]]
            # the first step's q̈ at a recorded state is the batch's own forward dynamics there
            q_hat, qd_hat = rollout(model, qs[:, 0], qds[:, 0], g(ch.tau)[:, :H], dt, zs, g(ch.f_v)[:, :H],
                                    qdd0=qdd_hat[r, k - W])
            out["ms"] = multistep_loss(q_hat[:, 1:], qd_hat[:, 1:], qs[:, 1:], qds[:, 1:], w_q, w_qd)
        else:
            out["ms"] = tau_hat.sum() * 0.0
    total = out["tau"]
    if cfg.w_fd > 0:
        total = total + cfg.w_fd * out["fd"]
    if cfg.w_ms > 0:
        total = total + cfg.w_ms * out["ms"]
    out["loss"] = total
    return out


def ms_weights(cfg: TrainConfig, stats: dict, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The multi-step loss' error weights: (n,) inverse training variances of q and q̇ ("state", the paper's)
    or (H, n) inverse variances of their h-step change ("increment": an error the size of the motion within
    the horizon weighs 1 at every step, whatever the sampling rate)."""
    if cfg.ms_norm == "state":
        vq, vqd = stats["var_q"], stats["var_qd"]
    else:
        if stats.get("horizon") != cfg.horizon:
            raise ValueError(f"increment variances were computed for H = {stats.get('horizon')}, not {cfg.horizon}")
        vq, vqd = stats["var_dq"], stats["var_dqd"]
    t = lambda v: 1.0 / torch.tensor(v, dtype=torch.float32, device=device)
    return t(vq), t(vqd)


def grad_norms(model: ExoModel, terms: dict[str, torch.Tensor], cfg: TrainConfig) -> dict[str, float]:
    """‖∂(w_k · loss_k)/∂θ‖ of each weighted loss term: which term drives the update (loss values alone do
    not say: a small term can have large gradients and the reverse)."""
    params = [p for p in model.parameters() if p.requires_grad]
    weight = {"tau": 1.0, "fd": cfg.w_fd, "ms": cfg.w_ms}
    out = {}
    for k, w in weight.items():
        if k in terms and w > 0 and terms[k].requires_grad:
            gs = torch.autograd.grad(w * terms[k], params, retain_graph=True, allow_unused=True)
            out[f"gn_{k}"] = float(torch.sqrt(sum((g.double() ** 2).sum() for g in gs if g is not None)))
    return out


def validation_loss(model: ExoModel, ch: Chunks, cfg: TrainConfig, w_q, w_qd, dt: float) -> dict[str, float]:
    """The training objective and its terms on the validation chunks (fixed rollout starts)."""
    per_batch = max(1, cfg.batch_size // cfg.chunk_steps)
    K = ch.q.shape[0]
    gen = torch.Generator().manual_seed(12345)
    sums: dict[str, float] = {}
    weight = 0.0
    model.eval()
    with torch.no_grad():
        for b in range(0, K, per_batch):
            idx = torch.arange(b, min(K, b + per_batch), device=ch.q.device)
            n = float(ch.loss[idx].sum())
            for k, v in batch_losses(model, ch, idx, cfg, w_q, w_qd, dt, gen).items():
                sums[k] = sums.get(k, 0.0) + n * float(v)
            weight += n
    model.train()
    return {f"val_{k}": v / max(weight, 1.0) for k, v in sums.items()}
