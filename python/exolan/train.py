"""Training: trial chunks, losses, run directories, checkpoints and resume.

Batches are made of trial *chunks*: `warmup` context steps (62 = the TCN's receptive field − 1) followed by
`chunk_steps` loss steps. The encoder runs once per chunk, giving z at every loss step exactly as the
whole-trial pass would (chunks that begin before the trial start are masked, see encoder.TCNBlock), instead
of once per sample over a 63-step window. Consecutive chunks of a trial overlap by the warm-up only, so each
sample is a loss sample exactly once per epoch.

Run directory:
    config.json     TrainConfig (all keys, defaults filled in)
    model.json      build_model(**spec) arguments, fixed scales included (export metadata)
    norm.json       normalisation statistics of the training set
    metrics.jsonl   one line per finished epoch
    checkpoint.pt   model, optimiser, epoch, metrics; written to a temporary file, then renamed
    run.json        status ("running" | "done"), data, timings
    physics.json    DeLaN-based models: H positive definite, cond(H) range, energy drift of free rollouts

The LSTM's memory is unbounded: a chunk that starts at its trial's start begins from zero state there, exactly
as in evaluation; a chunk inside a trial begins from zero state `warmup` samples before its loss steps (the
paper's history of 63 samples), a truncation of the whole-trial state used in evaluation.

Determinism: parameters are initialised after torch.manual_seed(seed); each epoch draws its batch order and
rollout starts from a generator seeded by (seed, epoch), so an interrupted run resumed from its last
checkpoint repeats exactly what the uninterrupted run does.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import TrainConfig, load_config, merge
from .losses import acceleration_loss, multistep_loss, torque_loss
from .models import ExoModel, build_model
from .rollout import rollout
from .data import context_channels, context_features, load, paper_split
from .evaluate import physics_check, torque_errors
from .runio import CHECKPOINT, atomic_torch_save, jsonable, load_run, write_json, write_jsonl  # noqa: F401 (load_run: train's API)

# config keys that may differ on --resume: none of them changes the weights an epoch produces
# (epochs only extends the run; the per-epoch generators do not depend on it)
_RESUMABLE_CHANGES = ("epochs", "device", "threads", "val_every", "checkpoint_every", "physics_check")


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


# -- run directory ---------------------------------------------------------------------------------

def _epoch_generator(seed: int, epoch: int) -> torch.Generator:
    return torch.Generator().manual_seed((int(seed) * 1_000_003 + int(epoch) * 7_919 + 17) % (2 ** 63))


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("--device cuda requested but torch sees no CUDA device")
    return torch.device(name)


# -- training --------------------------------------------------------------------------------------

def train(data_or_split, method: str | None = None, lim: bool | None = None, epochs: int | None = None,
          seed: int | None = None, out: str | Path = "run", resume: bool = False, progress: bool = True,
          config: TrainConfig | dict | None = None, **cfg) -> Path:
    """Train a model and return its run directory.

    data_or_split: a dataset directory (paper split; validation = held-out users on seen tasks), a Split
    (`.train`, `.test_seen`) or a list of Trials (all for training). Further keyword arguments are
    TrainConfig keys (lr, w_fd, w_ms, batch_size, ...; `model={...}` for model options); unknown keys raise.
    `resume=True` continues the run in `out` from its last checkpoint (or starts it if there is none).
    Arguments left at None come from `config`, else from TrainConfig's defaults (method "exolan", LIM on).
    """
    base = config.to_dict() if isinstance(config, TrainConfig) else dict(config or {})
    cfg_obj = merge(base, method=method, lim=lim, epochs=epochs, seed=seed, **cfg)
    train_trials, val_trials, data_path = resolve_data(data_or_split)
    if not train_trials:
        raise ValueError("no training trials")
    return _run(cfg_obj, train_trials, val_trials, data_path, Path(out), resume, progress)


def _run(cfg: TrainConfig, train_trials, val_trials, data_path, out: Path, resume: bool, progress: bool) -> Path:
    old_threads = torch.get_num_threads()
    try:
        return _run_inner(cfg, train_trials, val_trials, data_path, out, resume, progress)
    finally:
        torch.set_num_threads(old_threads)        # `threads` applies to this run, not to the caller


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


def _build(cfg: TrainConfig, desc: dict, stats: dict):
    """The model of a run (seeded) and its spec kwargs."""
    scales = data_scales(stats)
    model_opts = {**scales, **cfg.model}               # explicit options beat the data-derived scales
    spec_kwargs = dict(method=cfg.method, lim=cfg.lim, joint_types=desc["joint_types"],
                       joint_names=desc["joint_names"], context_channels=desc["context_channels"], **model_opts)
    if cfg.method in ("mlp", "mlp-tcn", "mlp-lstm", "tcn", "lstm"):
        spec_kwargs.update(state_mean=stats["state_mean"], state_std=stats["state_std"], tau_scale=stats["tau_std"])
        if cfg.w_fd > 0 or cfg.w_ms > 0:
            raise ValueError(f"w_fd and w_ms need forward dynamics; {cfg.method!r} is a black box")
    torch.manual_seed(cfg.seed)
    model = build_model(**spec_kwargs)
    if model.norm is not None:
        model.norm.set_stats(stats["ctx_mean"], stats["ctx_std"])
    return model


def _warmup(cfg: TrainConfig, model: ExoModel) -> int:
    if cfg.warmup >= 0:
        return cfg.warmup
    if model.encoder_kind == "lstm":
        return 62                                      # the paper's history of 63 samples
    return model.receptive_field - 1 if model.encoder is not None else 0


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


class EarlyStop:
    """Best validation loss so far, its epoch and weights; `stop` once `patience` epochs brought no better one."""

    def __init__(self, patience: int, state: dict | None = None):
        self.patience = patience
        self.best = float("inf") if state is None else state["best"]
        self.best_epoch = 0 if state is None else state["best_epoch"]
        self.weights = None if state is None else state["weights"]

    def update(self, epoch: int, loss: float, model: ExoModel) -> None:
        if loss < self.best:
            self.best, self.best_epoch = loss, epoch
            self.weights = {k: v.detach().clone() for k, v in model.state_dict().items()}

    def stop(self, epoch: int) -> bool:
        return self.patience > 0 and epoch - self.best_epoch >= self.patience

    def state(self) -> dict:
        return dict(best=self.best, best_epoch=self.best_epoch, weights=self.weights)


def _run_inner(cfg: TrainConfig, train_trials, test_trials, data_path, out: Path, resume: bool,
               progress: bool) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    ck_path = out / CHECKPOINT
    if ck_path.exists() and not resume:
        raise FileExistsError(f"{out} already holds a run; pass resume=True (--resume) to continue it")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    device = _device(cfg.device)
    train_trials, val_trials = split_validation(train_trials, cfg.val_users)
    desc = _describe(train_trials)
    stats = compute_stats(train_trials, cfg.horizon)
    stats.update(dt=desc["dt"])
    model = _build(cfg, desc, stats)
    spec = model.spec()
    model.to(device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)

    start_epoch, metrics, stopper = 0, [], EarlyStop(cfg.patience)
    if ck_path.exists():
        old_cfg = json.loads((out / "config.json").read_text())
        mine = cfg.to_dict()
        diff = {k for k in set(old_cfg) | set(mine) if k not in _RESUMABLE_CHANGES
                and old_cfg.get(k) != mine.get(k)}
        if diff:
            raise ValueError(f"cannot resume {out}: config differs in {sorted(diff)}")
        ck = torch.load(ck_path, map_location="cpu", weights_only=False)
        model.load_state_dict(ck.get("final_model", ck["model"]))     # training goes on from the last epoch
        model.to(device)
        opt.load_state_dict(ck["optimizer"])
        start_epoch, metrics = int(ck["epoch"]), list(ck["metrics"])
        stopper = EarlyStop(cfg.patience, ck.get("early_stop"))
    write_json(out / "config.json", cfg.to_dict())
    write_json(out / "model.json", spec)
    write_json(out / "norm.json", stats)
    # metrics.jsonl mirrors the checkpoint: epochs after the last checkpoint are dropped on resume
    write_jsonl(out / "metrics.jsonl", metrics)
    run_info = dict(status="running", data=data_path, n_train_trials=len(train_trials),
                    n_val_trials=len(val_trials), n_test_trials=len(test_trials),
                    val_users=sorted({t.subject for t in val_trials}), n_train_samples=stats["n_samples"],
                    device=str(device), torch_threads=torch.get_num_threads())
    write_json(out / "run.json", run_info)

    warmup = _warmup(cfg, model)
    chunks = make_chunks(train_trials, warmup, cfg.chunk_steps, cfg.horizon).to(device)
    val_chunks = make_chunks(val_trials, warmup, cfg.chunk_steps, cfg.horizon).to(device) if val_trials else None
    K = chunks.q.shape[0]
    per_batch = max(1, cfg.batch_size // cfg.chunk_steps)
    n_batches = -(-K // per_batch)
    w_q, w_qd = ms_weights(cfg, stats, device)
    dt = desc["dt"]

    from tqdm.auto import tqdm

    stopped = start_epoch > 0 and stopper.stop(start_epoch)
    bar = tqdm(range(start_epoch, cfg.epochs), initial=start_epoch, total=cfg.epochs,
               disable=not progress or stopped, desc=f"{cfg.method}{'' if cfg.lim else ' (no LIM)'}", unit="epoch")
    for epoch in ([] if stopped else bar):
        t0 = time.perf_counter()
        model.train()
        gen = _epoch_generator(cfg.seed, epoch)
        perm = torch.randperm(K, generator=gen)
        sums: dict[str, float] = {}
        norms: dict[str, float] = {}
        for b in range(n_batches):
            idx = perm[b * per_batch:(b + 1) * per_batch].to(device)
            terms = batch_losses(model, chunks, idx, cfg, w_q, w_qd, dt, gen)
            if b == 0 and len(terms) > 2:
                norms = grad_norms(model, terms, cfg)
            opt.zero_grad(set_to_none=True)
            terms["loss"].backward()
            opt.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach())
        row: dict[str, Any] = {"epoch": epoch + 1, **{k: v / n_batches for k, v in sums.items()}, **norms,
                               "seconds": time.perf_counter() - t0}
        if not math.isfinite(row["loss"]):
            raise FloatingPointError(f"loss became {row['loss']} in epoch {epoch + 1}")
        if val_chunks is not None:
            row.update(validation_loss(model, val_chunks, cfg, w_q, w_qd, dt))
            stopper.update(epoch + 1, row["val_loss"], model)
        done = epoch + 1 == cfg.epochs or stopper.stop(epoch + 1)
        if test_trials and (done or (cfg.val_every and (epoch + 1) % cfg.val_every == 0)):
            model.eval()
            with torch.no_grad():
                row["test_tau_mse"] = torque_errors(model, test_trials)["mse"]
        metrics.append(row)
        bar.set_postfix(loss=f"{row['loss']:.4g}", **({"val": f"{row['val_loss']:.4g}"} if "val_loss" in row else {}))
        if done or (epoch + 1) % cfg.checkpoint_every == 0:
            atomic_torch_save(ck_path, dict(epoch=epoch + 1, model=model.state_dict(), optimizer=opt.state_dict(),
                                            metrics=metrics, early_stop=stopper.state(),
                                            torch_rng=torch.get_rng_state()))
            write_jsonl(out / "metrics.jsonl", metrics)
        if done:
            break
    bar.close()
    _finish(cfg, model, stopper, metrics, test_trials or val_trials or train_trials, out, run_info,
            "held-out trials" if test_trials else ("validation trials" if val_trials else "training trials"))
    return out


def _finish(cfg, model, stopper, metrics, check_trials, out: Path, run_info: dict, on: str) -> None:
    """Keep the best validation weights (early stopping), the physics check, run.json's final status."""
    if stopper.weights is not None:
        model.load_state_dict(stopper.weights)
        write_json(out / "best.json", dict(epoch=stopper.best_epoch, val_loss=stopper.best))
        ck = torch.load(out / CHECKPOINT, map_location="cpu", weights_only=False)
        if "final_model" not in ck:                    # the last epoch's weights stay available
            ck["final_model"], ck["model"] = ck["model"], stopper.weights
            atomic_torch_save(out / CHECKPOINT, ck)
    if model.is_lagrangian and cfg.physics_check:
        # the physics check every user wants: H positive definite with its condition number range on the
        # data, and the energy of the free conservative model under the integrator
        model.eval()
        phys = physics_check(model, check_trials, max_samples=20000, n_rollouts=16)
        phys["on"] = on
        write_json(out / "physics.json", jsonable(phys))
    last = metrics[-1]["epoch"] if metrics else 0
    run_info.update(status="done", epochs=last, stopped_early=last < cfg.epochs,
                    best_epoch=stopper.best_epoch if stopper.weights is not None else last,
                    train_seconds=sum(m["seconds"] for m in metrics))
    write_json(out / "run.json", run_info)


def cli_train(args) -> int:
    base = load_config(args.config) if args.config else {}
    data = args.data or base.pop("data", None)     # a TOML may name its data set
    base.pop("data", None)
    overrides = dict(method=args.method, epochs=args.epochs, seed=args.seed, w_fd=args.w_fd, w_ms=args.w_ms,
                     ms_norm=args.ms_norm, patience=args.patience, val_users=args.val_users, device=args.device)
    if args.no_lim:
        overrides["lim"] = False
    cfg = merge(base, **overrides)
    if data is None:
        raise SystemExit("exolan train: --data DIR is required")
    train_trials, val_trials, data_path = resolve_data(data)
    out = _run(cfg, train_trials, val_trials, data_path, Path(args.out), args.resume, progress=True)
    m = json.loads((out / "metrics.jsonl").read_text().splitlines()[-1])
    print(f"trained {cfg.method}{'' if cfg.lim else ' (no LIM)'} for {m['epoch']} epochs: loss {m['loss']:.4g}"
          + (f", held-out torque MSE {m['test_tau_mse']:.4g} N² m²" if "test_tau_mse" in m else "") + f" -> {out}")
    if (out / "physics.json").exists():
        pc = json.loads((out / "physics.json").read_text())
        e = pc["energy"]["dt"]
        print(f"physics ({pc['on']}): H positive definite: {pc['positive_definite']}, cond(H) in "
              f"[{pc['cond_min']:.3g}, {pc['cond_max']:.3g}]; free rollout energy drift / max T: median "
              f"{e['median_rel_drift']:.3g}, max {e['max_rel_drift']:.3g} at dt = {e['dt']:.4g} s")
    return 0
