"""The simulated exoskeleton world (``exolan simulate``): users, tasks, leg dynamics, contact,
exoskeleton, sensors and injected effects, written in layout 1 (../shared/DATA_LAYOUT.md).

Python API::

    from exolan.world import simulate, TASKS, PAPER_TRAIN_TASKS
    simulate(out, users=21, tasks="all", seconds=None, seed=0, effects=[...], noise=True)
    exo_cols, moment_cols, truth = simulate_trial(user, task, seconds, seed, effects, noise)

``tasks``: "all" (28), "train" (the paper's 7) or a list / comma-separated names; ``seconds``:
per trial (default 20 s, ``task_seconds``). ``effects``: strings ``"NAME:JOINT:VALUE[:SUBJECTS]"``
(as on the command line; JOINT hip|knee|both, SUBJECTS joined by '+'), dicts in the
effects.json shape, or :class:`Effect` objects. Same seed -> byte-identical files.

The world, in short (details in the modules):
  * anthropometry.py: Winter's segment tables scaled by mass and height, + exoskeleton masses.
  * dynamics.py: planar 2-link leg hanging from the pelvis; H, c, g, J^T f, inverse/forward dynamics.
  * tasks.py: 28 tasks (cyclic / impedance / unstructured) as Fourier templates with per-user
    and per-cycle variation, stance schedules and load profiles.
  * generate.py: kinematics first, then GRF (vertical + horizontal, CoP heel -> toe), pelvis
    acceleration and tilt (unobserved), tau_tot = H qdd + c + g - J^T f, exoskeleton controller
    (a lagged, modulated share of tau_tot plus its own variation, saturated at 15 N m), human
    torque = tau_tot - applied exo torque (+ friction effects), sensors:
    encoder noise ENC_NOISE_DEG, velocity = zero-lag Butterworth (VEL_CUTOFF_HZ) derivative of
    the noisy angle, insole noise, low-passed moment noise, occasional NaN gaps in the moments.
  * effects.py: the effect vocabulary with DESIGN.md section 4 semantics; effects.json records it.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from .anthropometry import LegParams, User, leg_params, make_users
from .effects import UNITS as EFFECT_UNITS, Effect, coerce, parse_effect
from .generate import FS, SIDES, TrialWorld, record
from .tasks import PAPER_TRAIN_TASKS, TASK_SPECS, TASKS
from ..runio import write_json
from .writer import resolution, write_csv

__all__ = ["simulate", "simulate_trial", "cli_simulate", "TASKS", "PAPER_TRAIN_TASKS", "TASK_SPECS",
           "Effect", "parse_effect", "EFFECT_UNITS", "make_users", "leg_params", "User", "LegParams",
           "TrialWorld", "task_seconds"]


def task_seconds(task: str) -> float:
    """Default duration of a trial of ``task`` (s)."""
    return TASK_SPECS[task].seconds


def resolve_tasks(tasks) -> list[str]:
    if tasks is None or tasks == "all":
        return list(TASKS)
    if tasks == "train":
        return list(PAPER_TRAIN_TASKS)
    if isinstance(tasks, str):
        tasks = [t.strip() for t in tasks.split(",") if t.strip()]
    unknown = [t for t in tasks if t not in TASKS]
    if unknown:
        raise ValueError(f"unknown task(s) {unknown}; known: {', '.join(TASKS)}")
    return list(tasks)


def _rng(seed, *keys):
    return np.random.default_rng(np.random.SeedSequence([int(seed), *keys]))


def simulate_trial(user: User, task: str, seconds: float | None = None, seed: int = 0,
                   effects=(), noise: bool = True, subject_index: int | None = None):
    """One trial in memory: (exo_columns, moment_columns, truth). ``truth`` holds the true
    q, qd, qdd (T, side, joint), forces, CoP points, effective gravity, torques (see
    TrialWorld.evaluate). Same seeds as simulate()."""
    si = subject_index if subject_index is not None else int(user.name.lstrip("S") or 0) - 1
    ti = list(TASKS).index(task)
    world = TrialWorld(user, task, _rng(seed, 1, si, ti), coerce(effects))
    exo, mom, truth = record(world, seconds or task_seconds(task), _rng(seed, 2, si, ti), noise)
    truth["world"] = world
    return exo, mom, truth


def simulate(out, users: int = 21, tasks="all", seconds: float | None = None, seed: int = 0,
             effects=(), noise: bool = True, progress: bool = True) -> dict:
    """Write a world in layout 1 under ``out``; returns a summary dict.

    The world is built in a temporary sibling directory and moved into place at the end, so a
    failed or interrupted run leaves ``out`` as it was (and nothing half-written). An existing
    world at ``out`` (a directory with subjects.csv, or an empty one) is replaced; any other
    non-empty directory is refused rather than deleted."""
    import shutil
    import tempfile
    from pathlib import Path

    from tqdm import tqdm

    out = Path(out).absolute()
    task_list = resolve_tasks(tasks)
    eff = coerce(effects)
    people = make_users(int(users), _rng(seed, 0))
    names = [u.name for u in people]
    for e in eff:
        if e.subjects is not None:
            bad = [s for s in e.subjects if s not in names]
            if bad:
                raise ValueError(f"effect {e.effect}: unknown subject(s) {bad} (world has {names[0]}..{names[-1]})")
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "subjects.csv").exists())):
        raise ValueError(f"{out} exists and is not a simulated world; refusing to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    t0 = time.time()
    n_rows = 0
    try:
        with tqdm(total=len(people) * len(task_list), desc="simulate", unit="trial", disable=not progress) as bar:
            for si, user in enumerate(people):
                for task in task_list:
                    exo, mom, _ = simulate_trial(user, task, seconds, seed, eff, noise, subject_index=si)
                    d = work / user.name / f"{task}_1_1"
                    dec = None if not noise else {k: resolution(k) for k in list(exo) + list(mom)}
                    write_csv(d / "Exo.csv", exo, dec)
                    write_csv(d / "Joint_Moments_Filt.csv", mom, dec)
                    n_rows += len(exo["time"])
                    bar.update(1)
        _write_subjects(work / "subjects.csv", people)
        write_json(work / "effects.json", [e.record(names) for e in eff])
        old = None
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            out.rename(old / "world")
        work.rename(out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return {"out": str(out), "users": len(people), "tasks": task_list, "samples": n_rows,
            "seconds": time.time() - t0}


def _write_subjects(path, people):
    from ..runio import atomic_write

    lines = ["subject,mass_kg,height_m"] + [f"{u.name},{u.mass},{u.height}" for u in people]
    atomic_write(path, ("\n".join(lines) + "\n").encode())


def cli_simulate(args: argparse.Namespace) -> int:
    # errors (an unknown task or effect: ValueError) become one line in exolan.cli.main
    effects = [e for spec in args.effect for e in parse_effect(spec)]
    summary = simulate(args.out, users=args.users, tasks=args.tasks, seconds=args.seconds,
                       seed=args.seed, effects=effects, noise=not args.noise_free)
    print(f"wrote {summary['users']} users x {len(summary['tasks'])} tasks "
          f"({summary['samples']} samples per side) to {summary['out']} in {summary['seconds']:.1f} s")
    return 0
