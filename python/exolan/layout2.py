"""The layout-2 reader: any N-joint recording, <name>.csv beside <name>.json."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .dataset import DataError, Trial
from .recording import _check_time, _col, _read_csv, _uniform, savgol_derivative


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
