"""Execution of the reproduce sweep: completion markers, stored results, a local process pool or Ray."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import signal
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from .runio import atomic_write, write_json
from .study import SCALES, RunSpec
from .reproduce_job import JobContext, run_job

# --------------------------------------------------------------------------------------------------
# The sweep: planning, resumable execution, local pool or Ray
# --------------------------------------------------------------------------------------------------

# Scale fields that only say which runs a sweep holds: each run's own values are in its spec, so adding a run
# to a scale (a seed, an architecture, a horizon) leaves every finished run's marker valid.
_PLAN_ONLY = frozenset({"seeds", "architectures", "lims", "nolim_also", "fd_study", "w_fd", "w_ms", "ms_norm",
                        "ms_horizons", "ms_rollout_steps", "epochs", "batch_size", "patience", "val_users", "real",
                        "real_epochs", "real_seeds", "real_batch_size"})


def _non_default(obj) -> dict:
    """A dataclass's fields without those at their default: a field added later keeps old markers valid."""
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)
            if f.default is dataclasses.MISSING or getattr(obj, f.name) != f.default}


def _spec_key(spec: RunSpec, ctx: JobContext) -> str:
    # what the DONE marker certifies: the run configuration, its data and the evaluation settings
    data = ctx.data_dir if spec.dataset == "world" else ctx.real_dir
    if data and Path(data).resolve() == (Path(ctx.out) / "world").resolve():
        data = "<out>/world"  # the sweep's own world is identified by the scale; the sweep may be moved
    scale = {k: v for k, v in dataclasses.asdict(SCALES[ctx.scale]).items() if k not in _PLAN_ONLY}
    payload = json.dumps({"spec": _non_default(spec), "scale": scale, "data": data}, sort_keys=True)
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


def _die_with_parent() -> None:
    """Linux: a pool worker gets SIGTERM when the sweep's process ends. A sweep stopped by `kill` (not Ctrl-C,
    which reaches the whole process group) otherwise left its workers training on, 1.4 GB each (measured)."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # 1 = PR_SET_PDEATHSIG
        except OSError:
            return
        if os.getppid() == 1:                    # the parent ended before the line above: follow it now
            os.kill(os.getpid(), signal.SIGTERM)


def _worker_init(threads: int) -> None:
    _die_with_parent()
    # one BLAS/OpenMP pool per worker of `threads` threads: workers x threads = the cores given
    os.environ["OMP_NUM_THREADS"] = str(threads)
    os.environ["MKL_NUM_THREADS"] = str(threads)
    import torch
    torch.set_num_threads(threads)


def execute(specs: list[RunSpec], ctx: JobContext, workers: int, ray_address: str | None = None,
            log=print, on_run=None) -> dict[str, float]:
    """Run the unfinished jobs; return {run_id: wall seconds} of those run now. `on_run(n)` is called after each
    stored run with the number stored so far."""
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
        if on_run is not None:
            on_run(len(timings))
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
