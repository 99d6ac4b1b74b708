"""The layout-1 reader (exoskeleton recordings: subjects.csv + <SUBJECT>/<trial>/Exo.csv), with its unit checks."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .dataset import DataError, Dataset, Trial
from .recording import _check_time, _col, _read_csv, _uniform, savgol_derivative


SIDES = ("l", "r")
JOINTS = ("hip", "knee")


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
