"""One job of the reproduce sweep: the training backend, and run_job (train one configuration, evaluate it)."""
from __future__ import annotations

import dataclasses
import importlib
import io
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .study import SCALES, RunSpec, Scale, _normalise_groups, real_split
from .reproduce_metrics import _context, _fd_metrics, _inverse, _model_dtype, _plot_arrays, _task_identification

# --------------------------------------------------------------------------------------------------
# Backends
# --------------------------------------------------------------------------------------------------

class RealBackend:
    """exolan's own world, reader, training and models."""

    def simulate(self, out: Path, scale: Scale) -> None:
        from exolan.world import simulate
        simulate(out, users=scale.users, tasks=scale.tasks, seconds=scale.seconds, seed=scale.world_seed,
                 progress=False)

    def load(self, data_dir: str):
        from exolan import data
        return list(data.load(data_dir))

    def split(self, trials):
        from exolan import data
        s = data.paper_split(data.Dataset(list(trials)))
        return list(s.train), list(s.test_seen), list(s.test_unseen)

    def context_features(self, trial) -> np.ndarray:
        from exolan import data
        return data.context_features(trial)

    def task_groups(self) -> dict[str, str]:
        try:
            world = importlib.import_module("exolan.world")
        except ImportError:
            return {}
        tasks = getattr(world, "TASKS", None)  # {task: group}
        return _normalise_groups(tasks) if isinstance(tasks, dict) else {}

    def train(self, spec: RunSpec, train_trials, run_dir: Path, data_dir: str, device: str, threads: int):
        """Train on the given trials (the real-data split is not the paper's user split, so the sweep
        hands trial lists, not a directory) and return the model, in eval mode on the CPU."""
        from exolan import train as tr
        extra = {}
        if spec.w_fd:
            extra["w_fd"] = spec.w_fd
        if spec.w_ms:
            extra.update(w_ms=spec.w_ms, ms_norm=spec.ms_norm, horizon=spec.ms_horizon, n_starts=spec.ms_starts)
        if spec.patience:
            extra.update(patience=spec.patience, val_users=spec.val_users)
        tr.train(list(train_trials), method=spec.arch, lim=spec.lim, epochs=spec.epochs, seed=spec.seed,
                 out=run_dir, resume=True, progress=False, device=device, threads=threads,
                 batch_size=spec.batch_size, **extra)
        model, _ = tr.load_run(run_dir, device="cpu")
        return model


def get_backend(path: str | None = None):
    path = path or os.environ.get("EXOLAN_REPRODUCE_BACKEND")
    if not path:
        return RealBackend()
    mod, cls = path.split(":")
    return getattr(importlib.import_module(mod), cls)()


# --------------------------------------------------------------------------------------------------
# One job: train, evaluate, extract what the report needs
# --------------------------------------------------------------------------------------------------

@dataclass
class JobContext:
    out: str                 # sweep directory (absolute)
    data_dir: str            # world (layout 1) for dataset "world"
    real_dir: str | None     # real recordings for dataset "real"
    scale: str
    backend: str | None      # import path of a stand-in backend, None = RealBackend
    threads: int = 1
    device: str = "cpu"
    plot_seed: int = 0
    groups: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def run_job(spec_d: dict, ctx_d: dict) -> dict:
    """Train one configuration and evaluate it. Pure function of its arguments (and the files they name):
    the same call gives the same result in a local worker and in a Ray task. A failure is returned, not
    raised, so that one diverging run does not stop a sweep of hours; it is not marked complete."""
    try:
        return _run_job(spec_d, ctx_d)
    except Exception as exc:  # noqa: BLE001 - reported in the sweep log and the report
        import traceback
        return {"spec": spec_d, "run_id": RunSpec(**spec_d).run_id, "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc(), "train_seconds": 0.0, "eval_seconds": 0.0}


def _run_job(spec_d: dict, ctx_d: dict) -> dict:
    spec, ctx = RunSpec(**spec_d), JobContext(**ctx_d)
    scale = SCALES[ctx.scale]
    import torch
    torch.set_num_threads(max(1, ctx.threads))
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, ctx.threads)))
    backend = get_backend(ctx.backend)

    if spec.dataset == "real":
        dataset = backend.load(ctx.real_dir)
        train, tests = real_split(dataset)
        data_dir = ctx.real_dir
    else:
        dataset = backend.load(ctx.data_dir)
        train, seen, unseen = backend.split(dataset)
        tests = {"seen": seen, "unseen": unseen}
        data_dir = ctx.data_dir
    run_dir = Path(ctx.out) / "runs" / spec.run_id / "train"
    run_dir.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    model = backend.train(spec, train, run_dir, data_dir, ctx.device, ctx.threads)
    t_train = time.perf_counter() - t0
    model.eval()
    dtype = _model_dtype(model)

    t1 = time.perf_counter()
    result: dict[str, Any] = {"spec": spec.to_dict(), "run_id": spec.run_id, "train_seconds": t_train,
                              "training": _training_summary(run_dir)}
    arrays: dict[str, np.ndarray] = {}
    rows = []
    zcache = {}
    for split, trials in tests.items():
        for i, tr in enumerate(trials):
            z = _context(model, backend, tr, dtype)
            zcache[(split, i)] = z
            pred = _inverse(model, tr, z, dtype)
            err = (pred - tr.tau) ** 2
            ok = tr.valid & np.all(np.isfinite(tr.tau), axis=1)
            rows.append({"subject": tr.subject, "task": tr.task, "name": tr.name, "side": tr.side, "split": split,
                         "n": int(ok.sum()), "sse": np.nansum(np.where(ok[:, None], err, 0.0), axis=0).tolist(),
                         "mass": float(tr.mass)})
    result["torque_rows"] = rows
    if spec.arch == "exolan" and spec.lim and spec.dataset == "world":
        items = [(split, tr, zcache[(split, i)]) for split, trials in tests.items() for i, tr in enumerate(trials)]
        result["fd_rows"] = _fd_metrics(model, items, dtype, scale)

    first_seed = spec.seed == ctx.plot_seed
    if first_seed and spec.dataset == "world":
        arrays.update(_plot_arrays(model, backend, spec, tests, zcache, dtype, scale))
    if (spec.arch in ("exolan", "mlp-tcn") and spec.lim and spec.w_fd == 0 and spec.w_ms == 0
            and spec.dataset == "world"):
        result["taskid"] = _task_identification(model, backend, train, dtype, spec.seed, scale)
    result["eval_seconds"] = time.perf_counter() - t1
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    result["_arrays"] = buf.getvalue() if arrays else None
    return result


def _training_summary(run_dir: Path) -> dict:
    """Epochs run, the best epoch (early stopping) and each loss term's gradient norm per epoch."""
    run = json.loads((run_dir / "run.json").read_text()) if (run_dir / "run.json").exists() else {}
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()] \
        if (run_dir / "metrics.jsonl").exists() else []
    gn = {k: [r.get(k) for r in rows] for k in ("gn_tau", "gn_fd", "gn_ms") if any(k in r for r in rows)}
    return dict(epochs=run.get("epochs"), best_epoch=run.get("best_epoch"), stopped_early=run.get("stopped_early"),
                grad_norms=gn)
