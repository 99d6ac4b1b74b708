"""The dataset in memory: Trial, Dataset, Split, input errors, context features, the paper's split, stacking."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np


PAPER_TRAIN_TASKS = ("walk", "stand", "calisthenics", "push_pull", "jump_in_place", "turn", "cut")
COP_FORCE_THRESHOLD = 20.0  # N: CoP enters the context only when the foot carries more than this


class DataError(ValueError):
    """Bad input: the message names the file and the column or row."""


class DataWarning(UserWarning):
    """Input that was read with a correction the user should know of (irregular time stamps)."""


@dataclass
class Trial:
    subject: str
    task: str
    name: str
    side: str
    mass: float
    dt: float
    joints: tuple
    joint_types: tuple
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    tau_e: np.ndarray
    f_v: np.ndarray
    cop: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return len(self.q)

    @property
    def key(self) -> str:
        """A readable identifier: subject/name/side."""
        return f"{self.subject}/{self.name}" + (f"/{self.side}" if self.side else "")


@dataclass
class Dataset:
    trials: list
    root: str = ""
    layout: int = 1
    masses: dict = field(default_factory=dict)    # subject -> kg
    heights: dict = field(default_factory=dict)   # subject -> m (NaN if unknown)
    skipped: list = field(default_factory=list)   # (trial key, reason)

    def __len__(self):
        return len(self.trials)

    def __iter__(self):
        return iter(self.trials)

    def __getitem__(self, i):
        return self.trials[i]

    @property
    def subjects(self) -> list:
        return sorted({t.subject for t in self.trials})

    @property
    def tasks(self) -> list:
        return sorted({t.task for t in self.trials})

    @property
    def n_samples(self) -> int:
        return int(sum(int(t.valid.sum()) for t in self.trials))

    def select(self, subjects=None, tasks=None, sides=None) -> "Dataset":
        """A sub-dataset (same root, layout and masses) restricted to the given values."""
        keep = [t for t in self.trials
                if (subjects is None or t.subject in subjects)
                and (tasks is None or t.task in tasks)
                and (sides is None or t.side in sides)]
        return Dataset(keep, self.root, self.layout, dict(self.masses), dict(self.heights), [])


class Split(NamedTuple):
    train: Dataset
    test_seen: Dataset
    test_unseen: Dataset


# --------------------------------------------------------------------------------------------
# features, splits, stacking

def context_channels(trial: Trial) -> list:
    ch = [f"q_{j}" for j in trial.joints] + [f"qd_{j}" for j in trial.joints]
    if trial.side:  # layout 1
        ch += ["f_v", "cop_x", "cop_z"]
    return ch


def context_features(trial: Trial) -> np.ndarray:
    """(T, C) encoder input: q, qd, and for layout 1 f_v and the CoP gated by f_v > 20 N
    (0 when the foot is unloaded; other NaNs stay NaN)."""
    parts = [trial.q, trial.qd]
    if trial.side:
        loaded = (trial.f_v > COP_FORCE_THRESHOLD)[:, None]
        parts += [trial.f_v[:, None], np.where(loaded, trial.cop, 0.0)]
    return np.concatenate(parts, axis=1)


def paper_split(dataset: Dataset, train_tasks=PAPER_TRAIN_TASKS) -> Split:
    """The paper's split: subjects sorted by name, the last third held out (7 of 21);
    train = training users x training tasks, test_seen = held-out users x training tasks,
    test_unseen = held-out users x the other tasks."""
    subjects = dataset.subjects
    n = len(subjects)
    n_test = int(round(n / 3)) if n >= 2 else 0
    train_s, test_s = subjects[: n - n_test], subjects[n - n_test:]
    tasks = set(train_tasks)
    other = [t for t in dataset.tasks if t not in tasks]
    return Split(dataset.select(subjects=train_s, tasks=tasks),
                 dataset.select(subjects=test_s, tasks=tasks),
                 dataset.select(subjects=test_s, tasks=other))


def stack(trials) -> dict:
    """Concatenate trials into flat arrays with indices back into the trials:
    q, qd, qdd, tau, tau_e (N, n), f_v (N,), cop (N, 2), valid (N,), mass (N,),
    subject_idx, task_idx, trial_idx, side_idx (N,) and the name lists subjects, tasks, sides."""
    trials = list(trials)
    if not trials:
        raise ValueError("stack: no trials")
    subjects = sorted({t.subject for t in trials})
    tasks = sorted({t.task for t in trials})
    sides = sorted({t.side for t in trials})
    out = {k: np.concatenate([getattr(t, k) for t in trials]) for k in
           ("q", "qd", "qdd", "tau", "tau_e", "f_v", "cop", "valid")}
    lens = [len(t) for t in trials]
    rep = lambda vals: np.repeat(np.asarray(vals), lens)  # noqa: E731
    out["mass"] = rep([t.mass for t in trials]).astype(float)
    out["subject_idx"] = rep([subjects.index(t.subject) for t in trials])
    out["task_idx"] = rep([tasks.index(t.task) for t in trials])
    out["side_idx"] = rep([sides.index(t.side) for t in trials])
    out["trial_idx"] = rep(np.arange(len(trials)))
    out["time_idx"] = np.concatenate([np.arange(n) for n in lens])
    out.update(subjects=subjects, tasks=tasks, sides=sides)
    return out


# task families of names that are not the world's own (the real recordings, the EPIC files)
_GROUP_ALIASES = {"walk": "cyclic", "run": "cyclic", "sprint": "cyclic", "stairs": "cyclic", "incline": "cyclic",
                  "decline": "cyclic", "jump": "cyclic", "stand": "impedance", "squat": "impedance",
                  "sit": "impedance", "lunge": "impedance", "lift": "impedance", "push": "impedance",
                  "drop": "unstructured", "cut": "unstructured", "turn": "unstructured", "ball": "unstructured"}


def task_group(task: str) -> str:
    """The paper's task group of a task name: "cyclic", "impedance" or "unstructured" (the
    world's table, then the name's first word, e.g. walk_fast -> cyclic); "unknown" otherwise."""
    from .world.tasks import TASKS

    if task in TASKS:
        return TASKS[task]
    return _GROUP_ALIASES.get(task.split("_")[0], "unknown")
