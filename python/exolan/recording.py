"""Reading one recording: CSV columns, the time column (checked, resampled onto a uniform grid), derivatives."""
from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
from scipy.signal import savgol_filter

from .dataset import DataError, DataWarning


SAVGOL_SECONDS = 0.055   # the paper's 11 samples at 200 Hz (`savgol_window`)
SAVGOL_ORDER = 3


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
