"""The paper's three studies as one resumable sweep, and the report built from it.

``exolan reproduce --scale small|converge|medium|paper --out DIR [--data DIR] [--workers N] [--ray ADDRESS]``

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
job), ``converge`` (the claims: early-stopped, 3 seeds, 51 runs; 106 min on 2 cores), ``medium`` (6 s trials, 30 epochs,
3 seeds), ``paper`` (the default world, 1000 epochs, 5 seeds). On a machine with CUDA, ``medium`` and ``paper``
train on the GPU (``EXOLAN_DEVICE=cpu|cuda`` overrides); ``--workers`` defaults to one per core as far as memory
allows, on a GPU too; evaluation always runs on the CPU in the worker.

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
import json
import os
import shutil
import sys
import time
from pathlib import Path

from .runio import write_json
from .study import SCALES, RunSpec, Scale, plan, real_split  # noqa: F401 (RunSpec, real_split: this module's API)
from .reproduce_job import JobContext, RealBackend, get_backend, run_job  # noqa: F401 (run_job: this module's API)
from .reproduce_metrics import _fd_metrics, reference_fd_rows, rollout_metrics  # noqa: F401 (re-exported)
from .reproduce_exec import _done, execute, load_result
from . import report


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


class SweepClock:
    """This invocation's wall times as one session of out/sweep_clock.json, rewritten after every finished run:
    a resumed sweep reports what the whole sweep cost, a killed invocation included up to its last finished run
    (its session stays `"finished": false`; the report counts them)."""

    def __init__(self, out: Path, where: str):
        self.path = out / "sweep_clock.json"
        self.sessions = json.loads(self.path.read_text())["sessions"] if self.path.exists() else []
        self.mine = {"date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "runs_run": 0, "where": where,
                     "seconds": {}, "finished": False}
        self.sessions.append(self.mine)

    def update(self, seconds: dict[str, float], n_run: int, finished: bool = False) -> dict:
        """Record this invocation's seconds so far; return the totals over every invocation."""
        self.mine.update(runs_run=n_run, finished=finished, seconds={k: round(v, 1) for k, v in seconds.items()})
        keys = {k for s in self.sessions for k in s["seconds"]}
        total = {k: sum(s["seconds"].get(k, 0.0) for s in self.sessions) for k in sorted(keys)}
        clock = {"sessions": self.sessions, "total_seconds": total, "total": sum(total.values())}
        write_json(self.path, clock)
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
        log(f"[reproduce] the {scale.name} world ({scale.users} users, tasks={scale.tasks}, "
            f"{scale.seconds or 'default'} s per trial): simulated once, reused on a re-run")
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
        workers = default_workers(cores)
    # One torch thread per job whatever the executor: float reductions depend on the thread count, and the
    # same sweep must give the same numbers serially, in a process pool and on Ray (EXOLAN_THREADS overrides;
    # more workers, not more threads, is how the sweep uses more cores).
    threads = int(os.environ.get("EXOLAN_THREADS", 1))
    ctx = JobContext(out=str(out), data_dir=str(data_dir), real_dir=real_dir, scale=scale.name,
                     backend=backend or os.environ.get("EXOLAN_REPRODUCE_BACKEND"), threads=threads,
                     device=device, plot_seed=scale.seeds[0], groups=be.task_groups())
    specs = plan(scale, with_real=real_dir is not None)
    sweep = SweepClock(out, f"{workers} worker(s) x {threads} thread(s), {device}, {cores} core(s)")
    t1 = time.perf_counter()
    ran = execute(specs, ctx, workers, ray_address, log=log,
                  on_run=lambda n: sweep.update({"world": t_world, "runs": time.perf_counter() - t1}, n))
    t_runs = time.perf_counter() - t1
    results = {s.run_id: load_result(out, s) for s in specs if _done(out, s, ctx)}
    t2 = time.perf_counter()
    reference = world_reference(out, scale, be, data_dir) if data is None and scale.fd_study else None
    clock = sweep.update({"world": t_world, "runs": t_runs, "reference": time.perf_counter() - t2}, len(ran),
                         finished=True)
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


WORKER_BYTES = 2 * 1024 ** 3   # a converge-scale job peaked at 1.7 GB (docs/RESULTS.md)


def _available_memory() -> int | None:
    """Bytes a new process can take: Linux's MemAvailable (free + reclaimable cache; free pages alone are near 0
    on a machine whose cache is full), else the free pages, else None."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):   # no sysconf (Windows)
        return None


def default_workers(cores: int) -> int:
    """One worker per core, as many as the available memory holds. On a GPU too: the small models leave it
    launch-bound, and 12 workers sharing one H100 each ran at about one core's speed (docs/TRAINING.md)."""
    avail = _available_memory()
    if avail is None:                                  # unknown: trust the cores
        return max(1, cores)
    return max(1, min(cores, int(avail // WORKER_BYTES)))


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
