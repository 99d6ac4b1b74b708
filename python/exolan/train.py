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
import time
from pathlib import Path
from typing import Any

import torch

from . import native
from .config import TrainConfig, load_config, merge
from .models import ExoModel, build_model
from .batches import (_describe, batch_losses, compute_stats, data_scales, grad_norms, make_chunks, ms_weights,
                      resolve_data, split_validation, validation_loss)
from .batches import context_of  # noqa: F401 (train's API)
from .evaluate import physics_check, torque_errors
from .runio import CHECKPOINT, atomic_torch_save, jsonable, load_run, write_json, write_jsonl  # noqa: F401 (load_run: train's API)

# config keys that may differ on --resume: none of them changes the weights an epoch produces
# (epochs only extends the run; the per-epoch generators do not depend on it)
_RESUMABLE_CHANGES = ("epochs", "device", "threads", "val_every", "checkpoint_every", "physics_check")


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
        if _device(cfg.device).type == "cpu":
            # the run's threads go to the native kernels, torch's own ops keep one (exolan.native)
            with native.cpu_threads(cfg.threads or old_threads):
                return _run_inner(cfg, train_trials, val_trials, data_path, out, resume, progress)
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        return _run_inner(cfg, train_trials, val_trials, data_path, out, resume, progress)
    finally:
        torch.set_num_threads(old_threads)        # `threads` applies to this run, not to the caller


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


def make_optimizer(params, lr: float, weight_decay: float) -> torch.optim.Adam:
    """The training optimiser. Fused: one kernel over every parameter instead of a dozen ops per tensor (3.7 ->
    0.6 ms a step for ExoLaN+LIM on one core here, docs/TRAINING.md)."""
    return torch.optim.Adam(params, lr=lr, weight_decay=weight_decay, fused=True)


def _warmup(cfg: TrainConfig, model: ExoModel) -> int:
    if cfg.warmup >= 0:
        return cfg.warmup
    if model.encoder_kind == "lstm":
        return 62                                      # the paper's history of 63 samples
    return model.receptive_field - 1 if model.encoder is not None else 0


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
    device = _device(cfg.device)
    train_trials, val_trials = split_validation(train_trials, cfg.val_users)
    desc = _describe(train_trials)
    stats = compute_stats(train_trials, cfg.horizon)
    stats.update(dt=desc["dt"])
    model = _build(cfg, desc, stats)
    spec = model.spec()
    model.to(device)
    opt = make_optimizer(model.parameters(), cfg.lr, cfg.weight_decay)

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
                    device=str(device), torch_threads=torch.get_num_threads(), native_threads=native.threads()
                    if device.type == "cpu" and native.enabled() else 0)
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
                     ms_norm=args.ms_norm, patience=args.patience, val_users=args.val_users, device=args.device,
                     threads=args.threads)
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
