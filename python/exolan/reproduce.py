"""The paper's three studies as one resumable sweep, and the report built from it.

``exolan reproduce --scale small|medium|paper --out DIR [--data DIR] [--workers N] [--ray ADDRESS]``

Studies (paper section numbers aside, see ``/work/shared/PAPER_FACTS.md``):

* human intention estimation: 8 architectures x with/without LIM x seeds, trained on the training users
  and tasks, torque MSE on held-out users for seen and unseen tasks (cyclic / non-cyclic breakdown);
* forward dynamics: ExoLaN trained with the inverse loss only, + w_fd, + w_fd and w_ms (H = 4);
  q̈ MSE and open-loop q, q̇ MSE after 4, 10, 20 steps;
* task identification: the context z of trained ExoLaN and MLP-TCN over the training trajectories,
  an MLP 3 x 64 classifier per seed on an 80/20 split.

Every training run is one *job*. A job trains (through a backend, see below), evaluates the trained model
on the held-out data and returns a small JSON-able result plus plot arrays. The driver writes them into
``DIR/runs/<run id>/`` and drops a completion marker ``DONE`` last, so an interrupted sweep re-run with the
same arguments skips every finished job (and the training itself resumes from its own checkpoints).
Jobs run in a local process pool (``--workers``) or as Ray tasks (``--ray ADDRESS``); both call the same
pure function :func:`run_job`, so both give the same numbers.

Scales: ``small`` (~15 min on two cores: 21 users x 28 tasks of 2 s, 3 epochs, 2 seeds; part of the main
job), ``medium`` (6 s trials, 30 epochs, 3 seeds: a few hours on 8-16 cores or a GPU), ``paper`` (the default world, 1000 epochs,
5 seeds). On a machine with CUDA, ``medium`` and ``paper`` train on the GPU (``EXOLAN_DEVICE=cpu|cuda``
overrides), two runs at a time; evaluation always runs on the CPU in the worker.

Ray (``pip install exolan[ray]``): ``--ray ADDRESS`` submits every job as a Ray task (one CPU each, or
``threads`` CPUs); ``--ray local`` starts a fresh Ray instance on this machine for the sweep and stops it
after. The workers must see the same paths as the driver (a shared file system for ``--out``,
the data and the real recordings) and have exolan installed; results travel back to the driver, which
alone writes the completion markers.

The backend is the seam between this orchestration and the other parts of exolan (world, reader,
training, models). ``RealBackend`` uses them; tests may pass a stand-in by its import path
(``EXOLAN_REPRODUCE_BACKEND=module:Class``) so that the orchestration is testable in seconds.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib
import io
import json
import os
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .runio import atomic_write, write_json
from .study import PLOT_TASKS, SCALES, RunSpec, Scale, _normalise_groups, plan, real_split
from . import report

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
            extra.update(w_ms=spec.w_ms, ms_norm=spec.ms_norm)
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


def _model_dtype(model):
    import torch
    for p in model.parameters():
        return p.dtype
    return torch.float32


def _t(x, dtype):
    import torch
    return torch.as_tensor(np.asarray(x), dtype=dtype)


def _context(model, backend, tr, dtype):
    import torch
    x = backend.context_features(tr)
    with torch.no_grad():
        z = model.context(_t(x, dtype)[None])[0]
    return z


def _inverse(model, tr, z, dtype) -> np.ndarray:
    import torch
    with torch.no_grad():
        tau = model.inverse(_t(tr.q, dtype), _t(tr.qd, dtype), _t(tr.qdd, dtype), z, _t(tr.f_v, dtype))
    return tau.double().numpy()


def _forward(model, q, qd, tau, z, f_v):
    import torch
    with torch.no_grad():
        return model.forward_dynamics(q, qd, tau, z, f_v)


def _fd_metrics(model, items, dtype, scale: Scale) -> list[dict]:
    """Per trial: q̈ MSE on every valid sample, and open-loop rollout errors (semi-implicit Euler with the
    recorded τ, z and f_v, DESIGN section 5) from start points every `rollout_stride` samples."""
    def forward(q, qd, tau, z, fv, cop_x, owner, t):
        args = (_t(a, dtype) for a in (q, qd, tau, z, fv))
        return _forward(model, *args).double().numpy()

    return rollout_metrics(forward, [(split, tr, z.double().numpy()) for split, tr, z in items], scale)


def reference_fd_rows(items, scale: Scale, mode: str) -> list[dict]:
    """`_fd_metrics` of the world's true leg under one of exolan.world.reference.MODES of inputs."""
    from exolan.world import reference

    if mode == "recorded":
        legs = reference.true_legs(scale.users, scale.world_seed)
        params = [legs[tr.subject] for _, tr, _ in items]
    else:
        truths = [reference.TrueTrial(scale.users, scale.world_seed, scale.seconds, tr.subject, tr.task, tr.side)
                  for _, tr, _ in items]

    def forward(q, qd, tau, z, fv, cop_x, owner, t):
        out = np.empty_like(q)
        for j in np.unique(owner):                     # one leg per trial
            m = owner == j
            out[m] = (reference.recorded_forward(params[j], q[m], qd[m], tau[m], fv[m], cop_x[m]) if mode == "recorded"
                      else truths[j].forward(q[m], qd[m], tau[m], t[m], mode == "true inputs"))
        return out

    return rollout_metrics(forward, items, scale)


def rollout_metrics(forward, items, scale: Scale) -> list[dict]:
    """q̈ MSE and open-loop rollout errors of any forward dynamics `forward(q, qd, tau, z, f_v, cop_x, owner, t)`
    -> q̈ (numpy rows; `owner` = each row's item index, `t` its sample index in that trial). The rollouts of all
    trials run as one batch (a few forward-dynamics calls instead of thousands)."""
    H = max(scale.horizons)
    rows, Q0, QD0, TAU, Z, FV, CX, QT, QDT, owner, T0 = [], [], [], [], [], [], [], [], [], [], []
    for j, (split, tr, z) in enumerate(items):
        z = np.zeros((len(tr.q), 0)) if z is None else z
        cx = tr.cop[:, 0]
        qdd_hat = forward(tr.q, tr.qd, tr.tau, z, tr.f_v, cx, np.full(len(tr.q), j), np.arange(len(tr.q)))
        ok = tr.valid
        e = (qdd_hat - tr.qdd) ** 2
        n_j = tr.q.shape[1]
        rows.append({"subject": tr.subject, "task": tr.task, "split": split, "dt": float(tr.dt),
                     "n_qdd": int(ok.sum()),
                     "sse_qdd": np.where(ok[:, None], e, 0.0).sum(axis=0).tolist(),
                     "horizons": {str(h): {"n": 0, "sse_q": [0.0] * n_j, "sse_qd": [0.0] * n_j, "nonfinite": 0}
                                  for h in scale.horizons}})
        T = len(tr.q)
        if T <= H:
            continue
        # a start is usable when every sample it touches is valid
        win_ok = np.convolve(ok.astype(int), np.ones(H + 1, int), "valid") == H + 1
        starts = np.flatnonzero(win_ok)[:: scale.rollout_stride]
        if len(starts) == 0:
            continue
        w = starts[:, None] + np.arange(H + 1)[None]
        Q0.append(tr.q[starts]); QD0.append(tr.qd[starts])
        TAU.append(tr.tau[w[:, :H]]); FV.append(tr.f_v[w[:, :H]]); Z.append(z[w[:, :H]]); CX.append(cx[w[:, :H]])
        QT.append(tr.q[w]); QDT.append(tr.qd[w])
        owner.append(np.full(len(starts), j))
        T0.append(starts)
    if not owner:
        return rows
    Q0, QD0, TAU, FV, Z, CX, QT, QDT, owner, T0 = (np.concatenate(a) for a in (Q0, QD0, TAU, FV, Z, CX, QT, QDT, owner,
                                                                               T0))
    dt = float(items[0][1].dt)
    for a in range(0, len(owner), 20000):  # bounded memory on the paper's world
        sl = slice(a, a + 20000)
        qs, qds = Q0[sl], QD0[sl]
        for k in range(H):
            qdd_k = forward(qs, qds, TAU[sl, k], Z[sl, k], FV[sl, k], CX[sl, k], owner[sl], T0[sl] + k)
            qds = qds + dt * qdd_k
            qs = qs + dt * qds
            h = k + 1
            if h not in scale.horizons:
                continue
            with np.errstate(over="ignore", invalid="ignore"):
                eq = (qs - QT[sl, h]) ** 2
                eqd = (qds - QDT[sl, h]) ** 2
            bad = ~(np.isfinite(eq).all(1) & np.isfinite(eqd).all(1))
            # diverged rollouts count as infinite error: dropping them would flatter the model
            eq[bad] = np.inf
            eqd[bad] = np.inf
            own = owner[sl]
            for j in np.unique(own):
                m = own == j
                r = rows[j]["horizons"][str(h)]
                r["n"] += int(m.sum())
                r["nonfinite"] += int(bad[m].sum())
                r["sse_q"] = [float(x) for x in np.asarray(r["sse_q"]) + eq[m].sum(0)]
                r["sse_qd"] = [float(x) for x in np.asarray(r["sse_qd"]) + eqd[m].sum(0)]
    return rows


def _pick(trials, task, prefer_side="l"):
    cands = [t for t in trials if t.task == task]
    if not cands:
        return None
    cands.sort(key=lambda t: (t.subject, t.side != prefer_side, t.name))
    return cands[0]


def _plot_arrays(model, backend, spec, tests, zcache, dtype, scale) -> dict[str, np.ndarray]:
    """Arrays for the figures, from the first seed's models only (figures show one seed)."""
    out: dict[str, np.ndarray] = {}
    alltests = [(s, i, t) for s, ts in tests.items() for i, t in enumerate(ts)]

    def z_of(tr):
        for s, i, t in alltests:
            if t is tr:
                return zcache[(s, i)]
        return _context(model, backend, tr, dtype)

    if spec.arch in ("exolan", "mlp-tcn") and spec.lim and spec.w_fd == 0 and spec.w_ms == 0:
        tasks = [t for t in PLOT_TASKS if any(x.task == t for _, _, x in alltests)]
        # fill up to four tasks with what the held-out set offers (small worlds may lack some)
        for _, _, x in alltests:
            if len(tasks) >= 4:
                break
            if x.task not in tasks:
                tasks.append(x.task)
        for task in tasks[:4]:
            tr = _pick([x for _, _, x in alltests], task)
            pred = _inverse(model, tr, z_of(tr), dtype)
            n = min(len(tr.q), int(round(3.0 / tr.dt)))  # first 3 s
            out[f"torque/{task}/t"] = np.arange(n) * tr.dt
            out[f"torque/{task}/meas"] = tr.tau[:n]
            out[f"torque/{task}/pred"] = pred[:n]
            out[f"torque/{task}/subject"] = np.array(tr.subject)
    if spec.arch == "exolan" and spec.lim:
        tests_all = [x for _, _, x in alltests]
        for task in ("walk", "squat", "run"):
            tr = _pick(tests_all, task)
            if tr is None:
                continue
            z = z_of(tr)
            qdd_hat = _forward(model, _t(tr.q, dtype), _t(tr.qd, dtype), _t(tr.tau, dtype), z,
                               _t(tr.f_v, dtype)).double().numpy()
            n = min(len(tr.q), int(round(2.0 / tr.dt)))
            out[f"acc/{task}/t"] = np.arange(n) * tr.dt
            out[f"acc/{task}/meas"] = tr.qdd[:n]
            out[f"acc/{task}/pred"] = qdd_hat[:n]
        tr = _pick(tests_all, "walk") or tests_all[0]
        out.update(_rollout_arrays(model, tr, z_of(tr), dtype))
    return out


def _rollout_arrays(model, tr, z, dtype, n_starts=4, H=40) -> dict[str, np.ndarray]:
    """Open-loop rollouts of H steps (200 ms at 200 Hz) from a few evenly spaced starts of one trial."""
    import torch
    T = len(tr.q)
    ok = tr.valid
    cand = [s for s in range(0, max(T - H - 1, 0)) if ok[s:s + H + 1].all()]
    if not cand:
        return {}
    starts = np.array([cand[int(i)] for i in np.linspace(0, len(cand) - 1, n_starts)])
    q, qd, tau, fv = (_t(a, dtype) for a in (tr.q, tr.qd, tr.tau, tr.f_v))
    idx = torch.as_tensor(starts)
    qs, qds = q[idx].clone(), qd[idx].clone()
    Q, QD = [qs.double().numpy()], [qds.double().numpy()]
    for k in range(H):
        qdd_k = _forward(model, qs, qds, tau[idx + k], z[idx + k], fv[idx + k])
        qds = qds + tr.dt * qdd_k
        qs = qs + tr.dt * qds
        Q.append(qs.double().numpy())
        QD.append(qds.double().numpy())
    steps = np.arange(H + 1)
    return {
        "roll/starts": starts, "roll/dt": np.array(tr.dt), "roll/task": np.array(tr.task),
        "roll/q_pred": np.stack(Q, 1), "roll/qd_pred": np.stack(QD, 1),
        "roll/q_meas": np.stack([tr.q[s + steps] for s in starts]),
        "roll/qd_meas": np.stack([tr.qd[s + steps] for s in starts]),
        "roll/trace_t": np.arange(min(T, starts[-1] + H + 20)) * tr.dt,
        "roll/trace_q": tr.q[: min(T, starts[-1] + H + 20)],
        "roll/trace_qd": tr.qd[: min(T, starts[-1] + H + 20)],
    }


def _task_identification(model, backend, train, dtype, seed: int, scale: Scale) -> dict:
    """z over the training trajectories -> task label with an MLP 3 x 64 (ReLU), softmax cross-entropy
    with inverse-training-frequency class weights (the paper's protocol). Two 80/20 splits per seed:
    by sample (as the paper) and by trajectory (no temporal leakage: neighbouring samples share z)."""
    import torch
    rng = np.random.default_rng(seed)
    Z, Y, G = [], [], []
    tasks = sorted({t.task for t in train})
    for gi, tr in enumerate(train):
        z = _context(model, backend, tr, dtype).double().numpy()
        ok = np.flatnonzero(tr.valid & np.isfinite(z).all(1))
        if len(ok) == 0:
            continue
        take = ok if len(ok) <= scale.taskid_per_trial else np.sort(rng.choice(ok, scale.taskid_per_trial, False))
        Z.append(z[take])
        Y.append(np.full(len(take), tasks.index(tr.task)))
        G.append(np.full(len(take), gi))
    Z, Y, G = np.concatenate(Z), np.concatenate(Y), np.concatenate(G)
    out = {"tasks": tasks, "n_samples": int(len(Y))}
    # split 1: samples
    perm = rng.permutation(len(Y))
    n_tr = int(0.8 * len(Y))
    out["sample_split"] = _classify(Z, Y, perm[:n_tr], perm[n_tr:], len(tasks), seed, scale)
    # split 2: whole trajectories
    # stratified by task: 80 % of each task's trajectories train, so every task appears on both sides
    g_tr = set()
    for c in range(len(tasks)):
        gs = rng.permutation(np.unique(G[Y == c]))
        g_tr.update(gs[: max(1, int(round(0.8 * len(gs))))].tolist())
    m = np.array([g in g_tr for g in G])
    out["trajectory_split"] = _classify(Z, Y, np.flatnonzero(m), np.flatnonzero(~m), len(tasks), seed, scale)
    out["tasks_names_majority"] = {k: tasks[v["majority_class"]] for k, v in out.items()
                                   if isinstance(v, dict) and "majority_class" in v}
    return out


def _classify(Z, Y, itr, ite, k, seed, scale: Scale) -> dict:
    import torch
    from torch import nn
    g = torch.Generator().manual_seed(seed)
    mu, sd = Z[itr].mean(0), Z[itr].std(0) + 1e-8
    Xtr = torch.as_tensor((Z[itr] - mu) / sd, dtype=torch.float32)
    Xte = torch.as_tensor((Z[ite] - mu) / sd, dtype=torch.float32)
    ytr, yte = torch.as_tensor(Y[itr]), torch.as_tensor(Y[ite])
    counts = np.bincount(Y[itr], minlength=k).astype(float)
    w = np.where(counts > 0, counts.sum() / np.maximum(counts, 1) / k, 0.0)
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(Z.shape[1], 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(),
                        nn.Linear(64, 64), nn.ReLU(), nn.Linear(64, k))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, weight_decay=1e-4)
    lossf = nn.CrossEntropyLoss(weight=torch.as_tensor(w, dtype=torch.float32))
    bs = 4096
    for _ in range(scale.taskid_epochs):
        perm = torch.randperm(len(ytr), generator=g)
        for a in range(0, len(ytr), bs):
            b = perm[a:a + bs]
            opt.zero_grad()
            loss = lossf(net(Xtr[b]), ytr[b])
            loss.backward()
            opt.step()
    with torch.no_grad():
        acc = float((net(Xte).argmax(1) == yte).float().mean())
    maj = int(np.argmax(counts))
    return {"accuracy": acc, "majority_accuracy": float((Y[ite] == maj).mean()), "majority_class": maj,
            "n_train": int(len(itr)), "n_test": int(len(ite))}


# --------------------------------------------------------------------------------------------------
# The sweep: planning, resumable execution, local pool or Ray
# --------------------------------------------------------------------------------------------------

def _spec_key(spec: RunSpec, ctx: JobContext) -> str:
    # what the DONE marker certifies: the run configuration and the evaluation settings
    data = ctx.data_dir if spec.dataset == "world" else ctx.real_dir
    if data and Path(data).resolve() == (Path(ctx.out) / "world").resolve():
        data = "<out>/world"  # the sweep's own world is identified by the scale; the sweep may be moved
    payload = json.dumps({"spec": spec.to_dict(), "scale": dataclasses.asdict(SCALES[ctx.scale]),
                          "data": data}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _done(out: Path, spec: RunSpec, ctx: JobContext) -> bool:
    m = out / "runs" / spec.run_id / "DONE"
    return m.exists() and m.read_text().strip() == _spec_key(spec, ctx)


def _store(out: Path, spec: RunSpec, ctx: JobContext, result: dict) -> None:
    d = out / "runs" / spec.run_id
    d.mkdir(parents=True, exist_ok=True)
    arr = result.pop("_arrays", None)
    if arr:
        atomic_write(d / "plots.npz", arr)
    write_json(d / "result.json", result, indent=1)
    atomic_write(d / "DONE", (_spec_key(spec, ctx) + "\n").encode())  # last: marks the run complete


def load_result(out: Path, spec: RunSpec) -> dict:
    d = out / "runs" / spec.run_id
    r = json.loads((d / "result.json").read_text())
    p = d / "plots.npz"
    if p.exists():
        with np.load(p) as z:
            r["arrays"] = {k: z[k] for k in z.files}
    return r


def _worker_init(threads: int) -> None:
    # one BLAS/OpenMP pool per worker of `threads` threads: workers x threads = the cores given
    os.environ["OMP_NUM_THREADS"] = str(threads)
    os.environ["MKL_NUM_THREADS"] = str(threads)
    import torch
    torch.set_num_threads(threads)


def execute(specs: list[RunSpec], ctx: JobContext, workers: int, ray_address: str | None = None,
            log=print) -> dict[str, float]:
    """Run the unfinished jobs; return {run_id: wall seconds} of those run now."""
    out = Path(ctx.out)
    todo = [s for s in specs if not _done(out, s, ctx)]
    log(f"[reproduce] {len(specs)} runs, {len(specs) - len(todo)} already complete, {len(todo)} to run "
        f"({'ray ' + ray_address if ray_address else f'{workers} local worker(s)'} x {ctx.threads} thread(s))")
    timings: dict[str, float] = {}
    if not todo:
        return timings
    ctx_d = ctx.to_dict()
    t0 = time.perf_counter()
    failed: list[str] = []

    def finish(spec, res, i):
        if "error" in res:
            failed.append(spec.run_id)
            log(f"[reproduce] {i}/{len(todo)} {spec.run_id}: FAILED {res['error']}\n{res.get('traceback', '')}")
            return
        _store(out, spec, ctx, res)
        timings[spec.run_id] = res.get("train_seconds", 0.0) + res.get("eval_seconds", 0.0)
        log(f"[reproduce] {i}/{len(todo)} {spec.run_id}: train {res['train_seconds']:.1f}s "
            f"eval {res['eval_seconds']:.1f}s (elapsed {time.perf_counter() - t0:.0f}s)")

    if ray_address:
        import ray
        # "local": a fresh Ray instance on this machine for this sweep (no dashboard); any other address joins a
        # running cluster ("auto": the one `ray start` made on this machine, or $RAY_ADDRESS). What this call
        # started or joined, it leaves at the end; a Ray session the caller opened stays open.
        started = not ray.is_initialized()
        if started:
            ray.init(address=ray_address, log_to_driver=False,
                     **({"include_dashboard": False} if ray_address == "local" else {}))
        try:
            remote = ray.remote(num_cpus=ctx.threads)(_ray_job)
            refs = {remote.remote(s.to_dict(), ctx_d): s for s in todo}
            i = 0
            pending = list(refs)
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                i += 1
                finish(refs[ready[0]], ray.get(ready[0]), i)
        finally:
            if started:
                ray.shutdown()
    elif workers <= 1:
        _worker_init(ctx.threads)
        for i, s in enumerate(todo, 1):
            finish(s, run_job(s.to_dict(), ctx_d), i)
    else:
        import multiprocessing as mp
        # spawn: no fork of a process that already holds torch thread pools
        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                 initializer=_worker_init, initargs=(ctx.threads,)) as pool:
            futs = {pool.submit(run_job, s.to_dict(), ctx_d): s for s in todo}
            for i, f in enumerate(as_completed(futs), 1):
                finish(futs[f], f.result(), i)
    if failed:
        log(f"[reproduce] {len(failed)} run(s) failed (not marked complete; a re-run retries them): "
            + ", ".join(failed))
    return timings


def _ray_job(spec_d: dict, ctx_d: dict) -> dict:
    _worker_init(ctx_d.get("threads", 1))
    return run_job(spec_d, ctx_d)


# --------------------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------------------

def default_real_dir() -> str | None:
    env = os.environ.get("EXOLAN_REAL_DATA")
    if env:
        return env
    root = Path(__file__).resolve().parents[2]  # <repo>/python/exolan -> <repo>
    p = root.parent / "shared" / "real"
    return str(p) if (p / "subjects.csv").exists() else None


def ensure_world(out: Path, scale: Scale, backend) -> Path:
    world = out / "world"
    marker = world / ".complete"
    key = json.dumps({"users": scale.users, "tasks": scale.tasks, "seconds": scale.seconds,
                      "seed": scale.world_seed})
    if marker.exists() and marker.read_text() == key:
        return world
    if world.exists():
        shutil.rmtree(world)
    backend.simulate(world, scale)
    marker.write_text(key)
    return world


def world_reference(out: Path, scale: Scale, backend, data_dir: Path) -> dict[str, list[dict]] | None:
    """Rollout errors of the world's true leg on the held-out trials under each of exolan.world.reference.MODES
    of inputs, for the forward-dynamics table; cached in out/reference.json. None for a backend that did not
    simulate exolan's world."""
    if not isinstance(backend, RealBackend):
        return None
    path = out / "reference.json"
    if path.exists():
        return json.loads(path.read_text())
    from .world.reference import MODES

    _, seen, unseen = backend.split(backend.load(str(data_dir)))
    items = [("seen", t, None) for t in seen] + [("unseen", t, None) for t in unseen]
    rows = {mode: reference_fd_rows(items, scale, mode) for mode in MODES}
    write_json(path, rows, indent=None)
    return rows


def _sample_period(backend, data_dir: Path, results: dict) -> float | None:
    """The data's sample period (the rollouts' step): from the runs' rollout rows, else read from the data."""
    for r in results.values():
        for row in r.get("fd_rows", []):
            if "dt" in row:
                return float(row["dt"])
    trials = list(backend.load(str(data_dir)))
    return float(trials[0].dt) if trials else None


def sweep_clock(out: Path, seconds: dict[str, float], n_run: int, where: str) -> dict:
    """Add this invocation's wall times to out/sweep_clock.json and return the totals over every invocation:
    a resumed sweep still reports what the whole sweep cost (the report prints it)."""
    path = out / "sweep_clock.json"
    sessions = json.loads(path.read_text())["sessions"] if path.exists() else []
    sessions.append({"date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "runs_run": n_run, "where": where,
                     "seconds": {k: round(v, 1) for k, v in seconds.items()}})
    total = {k: sum(s["seconds"].get(k, 0.0) for s in sessions) for k in seconds}
    clock = {"sessions": sessions, "total_seconds": total, "total": sum(total.values())}
    write_json(path, clock)
    return clock


def reproduce(scale_name: str, out: str | Path, data: str | None = None, workers: int | None = None,
              ray_address: str | None = None, real_dir: str | None = "auto", backend: str | None = None,
              device: str | None = None, log=print, write_report: bool = True) -> dict:
    """Run (or resume) the sweep and write the report; returns the results dictionary
    (without the report, `write_report=False`: the runs' results by run id)."""
    scale = SCALES[scale_name]
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    be = get_backend(backend)
    t0 = time.perf_counter()
    if data is None:
        log(f"[reproduce] simulating the {scale.name} world ({scale.users} users, tasks={scale.tasks}, "
            f"{scale.seconds or 'default'} s per trial)")
        data_dir = ensure_world(out, scale, be)
    else:
        data_dir = Path(data).resolve()
    t_world = time.perf_counter() - t0
    if real_dir == "auto":
        real_dir = default_real_dir() if scale.real else None
    cores = os.cpu_count() or 1
    if device is None:
        device = os.environ.get("EXOLAN_DEVICE") or _default_device(scale)
    if workers is None:
        # one worker per core on CPU; on a GPU a few workers share the device
        workers = min(cores, 4) if device == "cpu" else 2
    # One torch thread per job whatever the executor: float reductions depend on the thread count, and the
    # same sweep must give the same numbers serially, in a process pool and on Ray (EXOLAN_THREADS overrides;
    # more workers, not more threads, is how the sweep uses more cores).
    threads = int(os.environ.get("EXOLAN_THREADS", 1))
    ctx = JobContext(out=str(out), data_dir=str(data_dir), real_dir=real_dir, scale=scale.name,
                     backend=backend or os.environ.get("EXOLAN_REPRODUCE_BACKEND"), threads=threads,
                     device=device, plot_seed=scale.seeds[0], groups=be.task_groups())
    specs = plan(scale, with_real=real_dir is not None)
    t1 = time.perf_counter()
    ran = execute(specs, ctx, workers, ray_address, log=log)
    t_runs = time.perf_counter() - t1
    results = {s.run_id: load_result(out, s) for s in specs if _done(out, s, ctx)}
    t2 = time.perf_counter()
    reference = world_reference(out, scale, be, data_dir) if data is None and scale.fd_study else None
    clock = sweep_clock(out, {"world": t_world, "runs": t_runs, "reference": time.perf_counter() - t2},
                        len(ran), f"{workers} worker(s) x {threads} thread(s), {device}, {cores} core(s)")
    missing = [s.run_id for s in specs if s.run_id not in results]
    specs = [s for s in specs if s.run_id in results]
    meta = {"scale": dataclasses.asdict(scale), "data": str(data_dir), "real_data": real_dir,
            "workers": workers, "threads_per_worker": threads, "device": device,
            "executor": f"ray {ray_address}" if ray_address else "local process pool",
            "seconds": {"world": t_world, "runs": t_runs}, "sweep_clock": clock, "task_groups": ctx.groups,
            "n_runs": len(specs), "failed_runs": missing, "reference_fd_rows": reference,
            "dt": _sample_period(be, data_dir, results) if scale.fd_study else None}
    if not write_report:
        return results
    summary = report.build(out, scale, specs, results, meta, log=log)
    meta["seconds"]["total"] = time.perf_counter() - t0
    log(f"[reproduce] done in {meta['seconds']['total']:.0f}s: {out / 'report.md'}")
    return summary


def _default_device(scale: Scale) -> str:
    try:
        import torch
        if torch.cuda.is_available() and scale.name in ("medium", "paper"):
            return "cuda"
    except ImportError:
        pass
    return "cpu"


def cli_reproduce(args: argparse.Namespace) -> int:
    scale = getattr(args, "scale", "small")
    summary = reproduce(scale, args.out, data=args.data, workers=args.workers, ray_address=args.ray)
    failed = (summary.get("meta") or {}).get("failed_runs") or []
    if failed:   # the report leaves them out and says so; a re-run retries them
        print(f"exolan reproduce: {len(failed)} run(s) failed and are missing from the report: "
              f"{', '.join(failed[:5])}{' ...' if len(failed) > 5 else ''} (re-run the same command to retry them)",
              file=sys.stderr)
        return 1
    return 0
