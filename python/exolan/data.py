"""The dataset reader: layout 1 (exoskeleton, the simulated world and the published EPIC files) and
layout 2 (any N-joint recording), see ../shared/DATA_LAYOUT.md and docs/DESIGN.md section 1.

Python API::

    ds = load(path)                 # Dataset (list-like of Trial); layout detected
    split = paper_split(ds)         # Split(train, test_seen, test_unseen), each a Dataset
    x = context_features(trial)     # (T, C) encoder input, names: context_channels(trial)
    flat = stack(ds.trials)         # flat arrays + subject/task/trial indices

Conventions:
  * Layout 1: each recording gives two trials (sides l, r). Flexion is positive for both joints on
    both sides and CoP z is lateral for both feet, so both legs are samples of one model with no
    sign change ("mirroring" is a relabelling of the columns). A side without any valid sample
    (e.g. a leg that was not measured) is left out and listed in ``Dataset.skipped``.
  * Degrees -> radians; tau = moment x mass_kg + recorded exoskeleton torque (N m).
  * qdd = Savitzky-Golay derivative of the recorded velocities (as the paper):
    ``scipy.signal.savgol_filter(qd, window_length=savgol_window(dt), polyorder=SAVGOL_ORDER=3,
    deriv=1, delta=dt)``, applied to each contiguous finite stretch separately (stretches
    shorter than the window stay NaN): a cubic fit over SAVGOL_SECONDS = 55 ms (11 samples at
    200 Hz, the paper's window; the odd sample count nearest to 55 ms at other rates, at least 5),
    which passes gait content (< 15 Hz) and suppresses the noise that a plain difference would
    amplify. The window is fixed in time, not in samples: an 11-sample window on a 1 kHz bench
    recording is 11 ms, and a 14-bit encoder's quantisation then puts 16 % of q̈'s RMS into its
    error (0.6 % at 200 Hz; measured on a sum of sines, 0.2-3 Hz), an error in the regressor
    of the inertia that biases it.
  * Layout 2 without velocity columns: qd = the same Savitzky-Golay filter, derivative of q.
  * NaN stays NaN; ``valid`` marks samples where q, qd, qdd, tau and f_v are all finite.
  * Cache: the parsed dataset is pickled into the user's cache folder (`cache_dir`: ``$EXOLAN_CACHE_DIR``,
    else ``$XDG_CACHE_HOME/exolan`` or ``~/.cache/exolan`` on Linux), never into the data folder (which
    may be read-only, shared or under version control), keyed by a hash of the reader version, its
    settings and the content of every file read.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import re
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
from scipy.signal import savgol_filter

from .runio import atomic_write

PAPER_TRAIN_TASKS = ("walk", "stand", "calisthenics", "push_pull", "jump_in_place", "turn", "cut")

SAVGOL_SECONDS = 0.055   # the paper's 11 samples at 200 Hz (`savgol_window`)
SAVGOL_ORDER = 3
COP_FORCE_THRESHOLD = 20.0  # N: CoP enters the context only when the foot carries more than this
READER_VERSION = "2"
SIDES = ("l", "r")
JOINTS = ("hip", "knee")


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
# low-level readers

def _read_csv(path: Path, data: bytes | None = None) -> dict:
    """CSV -> dict column -> float64 array (empty cells NaN). Raises DataError naming the file."""
    if data is None:
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise DataError(f"{path}: cannot read ({exc})") from exc
    if not data.strip():
        raise DataError(f"{path}: empty file")
    try:
        table = pacsv.read_csv(io.BytesIO(data),
                               convert_options=pacsv.ConvertOptions(strings_can_be_null=True))
    except pa.ArrowInvalid as exc:
        raise DataError(f"{path}: not a readable CSV ({exc})") from exc
    if table.num_rows == 0:
        raise DataError(f"{path}: empty file (a header and no rows)")
    out = {}
    for name, col in zip(table.column_names, table.columns):
        name = name.strip()
        if pa.types.is_floating(col.type) or pa.types.is_integer(col.type) or pa.types.is_null(col.type):
            out[name] = col.to_numpy(zero_copy_only=False).astype(float) if not pa.types.is_null(col.type) \
                else np.full(table.num_rows, np.nan)
            continue
        # a non-numeric column: ignored unless someone asks for it (_col converts or reports it)
        out[name] = col.to_pylist()
    return out


def _col(cols: dict, name: str, path: Path) -> np.ndarray:
    if name not in cols:
        raise DataError(f"{path}: missing column '{name}'")
    x = cols[name]
    if isinstance(x, np.ndarray):
        return x
    vals = np.full(len(x), np.nan)
    for i, v in enumerate(x):
        if v is None or str(v).strip() == "":
            continue
        try:
            vals[i] = float(v)
        except ValueError:
            raise DataError(f"{path}: column '{name}', row {i + 1}: not a number ({v!r})") from None
    cols[name] = vals
    return vals


GAP_FACTOR = 1.5   # a step in time longer than this many sample times is a gap (missing samples)
SLOW_SAMPLE_TIME = 0.05   # s: sampling at 20 Hz or slower cannot resolve a limb's or a drive's dynamics


def _check_time(t: np.ndarray, path: Path) -> float:
    """The sample time of a strictly increasing time column (its median step). Raises DataError."""
    if len(t) < 2:
        raise DataError(f"{path}: column 'time' has {len(t)} row(s); need at least 2")
    bad = np.flatnonzero(~np.isfinite(t))
    if len(bad):
        raise DataError(f"{path}: column 'time', row {bad[0] + 1}: missing or non-finite time")
    d = np.diff(t)
    back = np.flatnonzero(d <= 0)
    if len(back):
        i = back[0]
        raise DataError(f"{path}: column 'time' is not increasing: row {i + 2} (t={t[i + 1]:g} s) "
                        f"{'repeats' if d[i] == 0 else 'comes before'} the previous row's {t[i]:g} s")
    dt = float(np.median(d))
    if dt >= SLOW_SAMPLE_TIME:
        warnings.warn(f"{path}: column 'time' steps by {dt:g} s ({1 / dt:.3g} Hz), too slow for joint dynamics: "
                      f"if it is in milliseconds, give seconds (layout 2: or \"units\": {{\"time\": \"ms\"}})",
                      DataWarning, stacklevel=3)
    return dt


def _uniform(t: np.ndarray, cols: list[dict], dt: float, path: Path) -> tuple[np.ndarray, list[dict]]:
    """The recording on a uniform time grid of step dt: unchanged where it already is one (steps within
    0.1 % of dt). Otherwise every numeric column is linearly interpolated onto t[0] + k dt, and grid points
    inside a gap (a step longer than GAP_FACTOR dt: samples the logger dropped) are NaN, so that the
    derivatives and every fit see separate stretches. Loggers on a PC clock time-stamp with jitter and drop
    samples; refusing such a file would leave a bench recording unusable. Warns (DataWarning) with what
    was done."""
    d = np.diff(t)
    if not (np.abs(d - dt) > 1e-3 * dt + 1e-9).any():
        return t, cols
    n = int(np.floor((t[-1] - t[0]) / dt + 1e-6)) + 1
    grid = t[0] + np.arange(n) * dt
    k = np.clip(np.searchsorted(t, grid, side="right"), 1, len(t) - 1)
    in_gap = (t[k] - t[k - 1] > GAP_FACTOR * dt) & (grid > t[k - 1] + 1e-9 * dt) & (grid < t[k] - 1e-9 * dt)
    out = []
    for c in cols:
        r = {}
        for name, v in c.items():
            if isinstance(v, np.ndarray) and v.shape == t.shape and name != "time":
                x = np.interp(grid, t, v)
                x[in_gap] = np.nan
                r[name] = x
            elif name == "time":
                r[name] = grid
            else:
                r[name] = v
        out.append(r)
    gaps = int((d > GAP_FACTOR * dt).sum())
    jitter = float(np.percentile(np.abs(d[d <= GAP_FACTOR * dt] - dt), 99) / dt) if (d <= GAP_FACTOR * dt).any() else 0.0
    warnings.warn(f"{path}: column 'time' is not uniformly sampled (steps differ from the median {dt:g} s by up to "
                  f"{100 * jitter:.3g} % (99th percentile), {gaps} gap(s) longer than {GAP_FACTOR:g} samples): "
                  f"resampled linearly onto a uniform grid of {n} samples, {int(in_gap.sum())} of them in gaps "
                  f"(NaN, masked)", DataWarning, stacklevel=3)
    return grid, out


def finite_runs(mask: np.ndarray):
    """(start, stop) of the runs of True in mask."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))


def savgol_window(dt: float, order: int = SAVGOL_ORDER) -> int:
    """The Savitzky-Golay window (odd, samples) that spans SAVGOL_SECONDS at sample time dt: 11 at 200 Hz,
    55 at 1 kHz, 5 at 100 Hz; never shorter than order + 2."""
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"sample time must be positive, got {dt}")
    w = 2 * int(round((SAVGOL_SECONDS / dt - 1.0) / 2.0)) + 1
    return max(w, order + 2 + (order + 1) % 2)


def savgol_derivative(x: np.ndarray, dt: float, window: int | None = None, order: int = SAVGOL_ORDER):
    """Savitzky-Golay first derivative along axis 0, per contiguous finite stretch (NaN elsewhere); the
    window defaults to `savgol_window(dt)` (SAVGOL_SECONDS)."""
    window = savgol_window(dt, order) if window is None else int(window)
    x = np.asarray(x, float)
    out = np.full_like(x, np.nan)
    x2 = x.reshape(len(x), -1)
    o2 = out.reshape(len(x), -1)
    for k in range(x2.shape[1]):
        for a, b in finite_runs(np.isfinite(x2[:, k])):
            if b - a >= window:
                o2[a:b, k] = savgol_filter(x2[a:b, k], window, order, deriv=1, delta=dt)
    return out


def _check_units(cols: dict, path: Path, dt: float) -> tuple:
    """Detectable unit mistakes in a layout-1 Exo.csv: an angle column in radians while its
    velocity is in deg/s (or the velocity in rad/s): the recorded velocity is then ~57 times
    (or 1/57 of) the angle's own derivative. Raises DataError.

    Returns (max |angle|, max |velocity|, name of the largest angle column) for the
    dataset-level check of radians in both columns (``_check_radians``), which a single file
    cannot decide: a person standing still in degrees looks like a moving one in radians."""
    angle_cols, vel_cols = [], []
    for s in SIDES:
        for j in JOINTS:
            a, v = f"{j}_angle_{s}", f"{j}_angle_{s}_velocity_filt"
            if a not in cols or v not in cols:
                continue
            qa, va = _col(cols, a, path), _col(cols, v, path)
            angle_cols.append((a, qa))
            vel_cols.append(va)
            g = np.gradient(qa, dt)
            ok = np.isfinite(g) & np.isfinite(va)
            if ok.sum() < 20:
                continue
            gg, vv = g[ok], va[ok]
            if gg.std() == 0 or vv.std() == 0:
                continue
            r = np.corrcoef(gg, vv)[0, 1]
            if r < 0.5:
                continue
            slope = float(gg @ vv / (gg @ gg))
            if 20 < slope < 150:
                raise DataError(f"{path}: column '{a}' looks like radians (its recorded velocity '{v}' is "
                                f"{slope:.0f} x its derivative, ~180/pi); layout 1 wants degrees")
            if 1 / 150 < slope < 1 / 20:
                raise DataError(f"{path}: column '{v}' looks like rad/s (it is 1/{1 / slope:.0f} of the "
                                f"derivative of '{a}'); layout 1 wants deg/s")
    amax = lambda x: float(np.nanmax(np.abs(x))) if np.isfinite(x).any() else 0.0  # noqa: E731
    if not angle_cols:
        return 0.0, 0.0, ""
    worst = max(angle_cols, key=lambda c: amax(c[1]))
    return amax(worst[1]), max(amax(v) for v in vel_cols), worst[0]


def _check_radians(stats: list) -> None:
    """Radians in both the angle and the velocity columns of layout 1.

    ``stats``: (path, task, max |angle|, max |velocity|, column) per Exo.csv. A moving person
    recorded in degrees leaves +-pi (3 deg) somewhere in a dataset, and a trial of a task leaves
    it when the same task does elsewhere; in radians a walking knee never does. So:
      * every file within +-pi while some velocity exceeds 3 units/s -> the dataset is in radians;
      * one file within +-pi, moving (> 3 units/s), while other files of its task reach 2 pi -> that
        file is in radians."""
    if not stats:
        return
    moving = [s for s in stats if s[3] > 3.0]
    if moving and all(s[2] < np.pi for s in stats):
        p, _, a, v, col = max(moving, key=lambda s: s[3])
        raise DataError(f"{p}: column '{col}' looks like radians: every angle of the dataset stays within "
                        f"+-{max(s[2] for s in stats):.2f} while velocities reach {v:.1f}/s; layout 1 wants degrees")
    by_task: dict = {}
    for s in stats:
        by_task.setdefault(s[1], []).append(s[2])
    for p, task, a, v, col in stats:
        others = sorted(by_task[task])
        others.remove(a)
        if a < np.pi and v > 3.0 and len(others) >= 1 and np.median(others) > 2 * np.pi:
            raise DataError(f"{p}: column '{col}' looks like radians: its angles stay within +-{a:.2f} while "
                            f"other '{task}' trials reach {np.median(others):.0f}; layout 1 wants degrees")


# --------------------------------------------------------------------------------------------
# layout 1

_TRIAL_RE = re.compile(r"^(?P<task>.+)_(?P<k>\d+)_(?P<m>\d+)$")


def _layout1_files(root: Path):
    """[(subject, trial_dir)] for every <SUBJECT>/<trial>/Exo.csv under root."""
    out = []
    for sd in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for td in sorted(p for p in sd.iterdir() if p.is_dir() and not p.name.startswith(".")):
            if (td / "Exo.csv").exists() or (td / "Joint_Moments_Filt.csv").exists():
                out.append((sd.name, td))
    return out


def read_subjects(path: Path) -> tuple[dict, dict]:
    cols = _read_csv(path)
    if "subject" not in cols:
        raise DataError(f"{path}: missing column 'subject'")
    names = cols["subject"]
    names = [("" if v is None else (f"{v:g}" if isinstance(v, float) else str(v))).strip() for v in names]
    mass = _col(cols, "mass_kg", path)
    height = _col(cols, "height_m", path) if "height_m" in cols else np.full(len(names), np.nan)
    masses, heights = {}, {}
    for i, (n, m, h) in enumerate(zip(names, mass, height)):
        if not n:
            raise DataError(f"{path}: row {i + 1}: empty subject name")
        if not np.isfinite(m) or m <= 0:
            raise DataError(f"{path}: column 'mass_kg', row {i + 1} (subject {n}): missing or invalid mass")
        masses[n], heights[n] = float(m), float(h)
    return masses, heights


def read_trial_dir(trial_dir, mass: float, subject: str | None = None, files: dict | None = None,
                   return_units: bool = False):
    """Parse one layout-1 trial directory -> (list of Trial (one per side with data), skipped).

    ``files`` may hold the already-read bytes of Exo.csv / Joint_Moments_Filt.csv."""
    td = Path(trial_dir)
    files = files or {}
    subject = subject or td.parent.name
    exo_p, mom_p = td / "Exo.csv", td / "Joint_Moments_Filt.csv"
    for p in (exo_p, mom_p):
        if p.name not in files and not p.exists():
            raise DataError(f"{p}: missing file")
    exo = _read_csv(exo_p, files.get("Exo.csv"))
    mom = _read_csv(mom_p, files.get("Joint_Moments_Filt.csv"))
    t = _col(exo, "time", exo_p)
    dt = _check_time(t, exo_p)
    tm = _col(mom, "time", mom_p)
    if len(tm) != len(t) or not np.allclose(tm, t, atol=1e-6 * max(1.0, abs(t[-1]))):
        raise DataError(f"{mom_p}: column 'time' does not match {exo_p.name} "
                        f"({len(tm)} rows vs {len(t)})")
    t, (exo, mom) = _uniform(t, [exo, mom], dt, exo_p)
    unit_stats = _check_units(exo, exo_p, dt)
    m = _TRIAL_RE.match(td.name)
    task = m.group("task") if m else td.name
    trials, skipped = [], []
    for s in SIDES:
        need = [f"hip_angle_{s}", f"knee_angle_{s}", f"hip_angle_{s}_velocity_filt",
                f"knee_angle_{s}_velocity_filt", f"insole_{s}_force_y", f"insole_{s}_cop_x",
                f"insole_{s}_cop_z", f"hip_angle_{s}_torque_measured", f"knee_angle_{s}_torque_measured"]
        ex = {c: _col(exo, c, exo_p) for c in need}
        mh = _col(mom, f"hip_flexion_{s}_moment", mom_p)
        mk = _col(mom, f"knee_angle_{s}_moment", mom_p)
        q = np.radians(np.stack([ex[f"hip_angle_{s}"], ex[f"knee_angle_{s}"]], 1))
        qd = np.radians(np.stack([ex[f"hip_angle_{s}_velocity_filt"], ex[f"knee_angle_{s}_velocity_filt"]], 1))
        qdd = savgol_derivative(qd, dt)
        tau_e = np.stack([ex[f"hip_angle_{s}_torque_measured"], ex[f"knee_angle_{s}_torque_measured"]], 1)
        tau = np.stack([mh, mk], 1) * mass + tau_e
        f_v = ex[f"insole_{s}_force_y"].copy()
        cop = np.stack([ex[f"insole_{s}_cop_x"], ex[f"insole_{s}_cop_z"]], 1)
        valid = (np.isfinite(q).all(1) & np.isfinite(qd).all(1) & np.isfinite(qdd).all(1)
                 & np.isfinite(tau).all(1) & np.isfinite(f_v))
        tr = Trial(subject=subject, task=task, name=td.name, side=s, mass=float(mass), dt=dt,
                   joints=JOINTS, joint_types=("revolute", "revolute"), q=q, qd=qd, qdd=qdd, tau=tau,
                   tau_e=tau_e, f_v=f_v, cop=cop, valid=valid)
        if valid.any():
            trials.append(tr)
        else:
            skipped.append((tr.key, "no valid sample (side not measured or all NaN)"))
    if return_units:
        return trials, skipped, (exo_p, task) + unit_stats
    return trials, skipped


def _load_layout1(root: Path, digest_files: dict) -> Dataset:
    masses, heights = read_subjects(root / "subjects.csv")
    trials, skipped, units = [], [], []
    for subject, td in _layout1_files(root):
        if subject not in masses:
            raise DataError(f"{root / 'subjects.csv'}: unknown subject mass: no row for subject '{subject}' "
                            f"(found {td})")
        files = {n: digest_files.get(td / n) for n in ("Exo.csv", "Joint_Moments_Filt.csv")}
        tr, sk, us = read_trial_dir(td, masses[subject], subject,
                                    {k: v for k, v in files.items() if v is not None}, return_units=True)
        trials.extend(tr)
        skipped.extend(sk)
        units.append(us)
    _check_radians(units)
    if not trials:
        raise DataError(f"{root}: no trial with data (expected <SUBJECT>/<task>_k_m/Exo.csv)")
    return Dataset(trials, str(root), 1, masses, heights, skipped)


# --------------------------------------------------------------------------------------------
# layout 2

def read_layout2(csv_path, data: bytes | None = None, meta_bytes: bytes | None = None) -> Trial:
    csv_path = Path(csv_path)
    jp = csv_path.with_suffix(".json")
    try:
        meta = json.loads(meta_bytes if meta_bytes is not None else jp.read_bytes())
    except FileNotFoundError:
        raise DataError(f"{jp}: missing file (layout 2 needs <name>.json beside <name>.csv)") from None
    except json.JSONDecodeError as exc:
        raise DataError(f"{jp}: invalid JSON ({exc})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("joints"), list) or not meta["joints"]:
        raise DataError(f"{jp}: needs a non-empty 'joints' list")
    names, types = [], []
    for i, j in enumerate(meta["joints"]):
        if not isinstance(j, dict) or "name" not in j:
            raise DataError(f"{jp}: joints[{i}] needs a 'name'")
        ty = j.get("type", "revolute")
        if ty not in ("revolute", "prismatic"):
            raise DataError(f"{jp}: joints[{i}] ('{j['name']}'): type must be revolute or prismatic, not {ty!r}")
        names.append(str(j["name"]))
        types.append(ty)
    cols = _read_csv(csv_path, data)
    units = meta.get("units", {}) or {}
    t = _col(cols, "time", csv_path)
    t_unit = str(units.get("time", "s")).lower()
    if t_unit in ("ms", "millisecond", "milliseconds"):
        t = t / 1000.0
    elif t_unit not in ("s", "sec", "second", "seconds"):
        raise DataError(f"{jp}: units.time must be 's' or 'ms', not {units.get('time')!r}")
    cols["time"] = t
    dt = _check_time(t, csv_path)
    t, (cols,) = _uniform(t, [cols], dt, csv_path)
    q = np.stack([_col(cols, f"q_{n}", csv_path) for n in names], 1)
    if str(units.get("q", "")).lower() in ("deg", "degree", "degrees"):
        rev = np.array([ty == "revolute" for ty in types])
        q[:, rev] = np.radians(q[:, rev])
    tau = np.stack([_col(cols, f"tau_{n}", csv_path) for n in names], 1)
    has_qd = [f"qd_{n}" in cols for n in names]
    if all(has_qd):
        qd = np.stack([_col(cols, f"qd_{n}", csv_path) for n in names], 1)
        if str(units.get("qd", "")).lower() in ("deg/s",):
            rev = np.array([ty == "revolute" for ty in types])
            qd[:, rev] = np.radians(qd[:, rev])
    elif any(has_qd):
        missing = [f"qd_{n}" for n, h in zip(names, has_qd) if not h]
        raise DataError(f"{csv_path}: missing column '{missing[0]}' (velocities must be given for all joints or none)")
    else:
        qd = savgol_derivative(q, dt)
    qdd = savgol_derivative(qd, dt)
    T = len(t)
    valid = np.isfinite(q).all(1) & np.isfinite(qd).all(1) & np.isfinite(qdd).all(1) & np.isfinite(tau).all(1)
    stem = csv_path.stem
    return Trial(subject=str(meta.get("subject", stem)), task=str(meta.get("task", stem)), name=stem, side="",
                 mass=1.0, dt=dt, joints=tuple(names), joint_types=tuple(types), q=q, qd=qd, qdd=qdd,
                 tau=tau, tau_e=np.zeros_like(tau), f_v=np.zeros(T), cop=np.full((T, 2), np.nan), valid=valid)


# --------------------------------------------------------------------------------------------
# cache and the public loader

def cache_dir() -> Path:
    """The reader's cache folder: $EXOLAN_CACHE_DIR, else the platform's per-user cache folder
    ($XDG_CACHE_HOME/exolan or ~/.cache/exolan on Linux, ~/Library/Caches/exolan on macOS,
    %LOCALAPPDATA%/exolan/Cache on Windows). The data folder itself never receives a file."""
    env = os.environ.get("EXOLAN_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        return Path(os.environ["LOCALAPPDATA"]) / "exolan" / "Cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "exolan"
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    # the XDG spec: a relative path in the variable is invalid and is ignored
    return (Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache") / "exolan"


def _input_files(path: Path) -> tuple[int, Path, list]:
    """(layout, root, files) of what load(path) reads."""
    if path.is_file():
        if path.suffix == ".csv":
            if not path.with_suffix(".json").exists():
                raise DataError(f"{path.with_suffix('.json')}: missing file (layout 2 needs <name>.json)")
            return 2, path.parent, [path, path.with_suffix(".json")]
        if path.name == "subjects.csv":
            path = path.parent
        else:
            raise DataError(f"{path}: not a dataset (expected a layout-1 root or a layout-2 <name>.csv)")
    if not path.exists():
        raise DataError(f"{path}: no such file or directory")
    if (path / "subjects.csv").exists():
        files = [path / "subjects.csv"]
        for _, td in _layout1_files(path):
            files += [td / "Exo.csv", td / "Joint_Moments_Filt.csv"]
        return 1, path, files
    pairs = sorted(p for p in path.glob("*.csv") if p.with_suffix(".json").exists())
    if pairs:
        return 2, path, [f for p in pairs for f in (p, p.with_suffix(".json"))]
    if _layout1_files(path):
        raise DataError(f"{path / 'subjects.csv'}: missing file (layout 1 needs subject masses)")
    raise DataError(f"{path}: no dataset found (layout 1: subjects.csv + <SUBJECT>/<trial>/Exo.csv; "
                    f"layout 2: <name>.csv + <name>.json)")


def load(path, cache: bool = True) -> Dataset:
    """Read a dataset (layout detected); repeated loads of unchanged files come from the cache."""
    path = Path(path).expanduser().resolve()
    layout, root, files = _input_files(path)
    contents = {}
    h = hashlib.blake2b(digest_size=20)
    h.update(f"exolan-reader {READER_VERSION} layout {layout} sg {SAVGOL_SECONDS} s {SAVGOL_ORDER}".encode())
    for f in files:
        try:
            b = f.read_bytes()
        except OSError as exc:
            raise DataError(f"{f}: cannot read ({exc})") from exc
        contents[f] = b
        h.update(str(f.relative_to(root)).encode() + b"\0" + hashlib.blake2b(b, digest_size=20).digest())
    key = h.hexdigest()
    cdir = cache_dir() if cache else None
    cfile = cdir / f"dataset-{key}.pkl" if cdir else None
    if cfile is not None and cfile.exists():
        try:
            with open(cfile, "rb") as fh:
                ds = pickle.load(fh)
            ds.root = str(path if layout == 1 else root)
            return ds
        except Exception:  # a corrupt cache entry is rebuilt, never trusted
            pass
    if layout == 1:
        ds = _load_layout1(root, contents)
    else:
        trials = []
        for f in files[::2]:
            trials.append(read_layout2(f, contents[f], contents[f.with_suffix(".json")]))
        ds = Dataset(trials, str(root), 2, {t.subject: 1.0 for t in trials}, {}, [])
    if cfile is not None:
        try:
            atomic_write(cfile, pickle.dumps(ds, protocol=5))
        except OSError:
            pass  # no writable cache: loading still works
    return ds


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


def real_data_path() -> Path:
    """The real recordings (../shared/real relative to the repository, or $EXOLAN_REAL_DATA)."""
    env = os.environ.get("EXOLAN_REAL_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "real"
