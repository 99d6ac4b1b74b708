"""Atomic writing of layout-1 files.

Every file is written to a temporary name in its destination folder and renamed into place
(os.replace is atomic on POSIX), so an interrupted run never leaves a half-written CSV behind.
CSV numbers are written by Arrow's shortest round-trip formatting: a float64 read back is
bit-identical, which the inverse-dynamics self-check (1e-8 N m) relies on. Noisy data are rounded
to their sensor resolution first, which keeps the files small.
"""
from __future__ import annotations

import io

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

from ..runio import atomic_write


def csv_bytes(columns: dict, decimals: dict | None = None) -> bytes:
    """dict name -> float array -> CSV bytes; NaN becomes an empty cell."""
    arrays, names = [], []
    for name, x in columns.items():
        x = np.asarray(x, float)
        if decimals is not None:
            x = np.round(x, decimals.get(name, 6))
        arrays.append(pa.array(x, mask=np.isnan(x)))
        names.append(name)
    buf = io.BytesIO()
    buf.write((",".join(names) + "\n").encode())
    pacsv.write_csv(pa.table(arrays, names=names), buf,
                    write_options=pacsv.WriteOptions(include_header=False, quoting_style="none"))
    return buf.getvalue()


def write_csv(path, columns: dict, decimals: dict | None = None) -> None:
    atomic_write(path, csv_bytes(columns, decimals))




def resolution(name: str) -> int:
    """Decimals kept for a noisy column (its sensor resolution, well below the noise)."""
    if name == "time":
        return 6
    if name.endswith("_velocity_filt"):
        return 3
    if name.endswith("_torque_measured"):
        return 4
    if "_cop_" in name:
        return 5
    if name.endswith("_force_y"):
        return 2
    if name.endswith("_moment"):
        return 5
    return 4  # angles, deg
