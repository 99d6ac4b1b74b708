"""Trial signals for the extended model: exo-torque lag tables and derivatives, the recorded velocity's filter."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .data import finite_runs


def lag_table(lengths: Sequence[int], max_lag: int) -> np.ndarray:
    """(N, max_lag+1) flat indices of the sample k steps earlier in the same trial (clamped at its start)."""
    out = []
    start = 0
    for T in lengths:
        t = np.arange(T)
        k = np.arange(max_lag + 1)
        out.append(start + np.maximum(t[:, None] - k[None, :], 0))
        start += T
    return np.concatenate(out, axis=0) if out else np.zeros((0, max_lag + 1), dtype=np.int64)


def velocity_response(trials: Sequence, dt: float, half_width: int = 25,
                      max_rows: int = 200_000) -> np.ndarray | None:
    """The recorded velocity's filter, estimated from the data: symmetric FIR taps per joint (2 K + 1, n).

    A device reports q̇ through its own filter (unknown: a Butterworth, an observer, a Savitzky-Golay
    derivative), and the reader differentiates that q̇ again for q̈. A strap's deflection τ_app/k reaches the
    measured q̇ and q̈ through the same chain, so the model's correction must pass through it too. The taps
    h_k = h_−k (k ≤ K = `half_width` samples) are the least-squares fit of the recorded velocity on the
    central difference of the recorded angle, y_t = Σ_k h_k x_{t−k} (numpy lstsq over every finite stretch).
    The angle's own noise is in both x and y, so it biases nothing, and the time-domain fit has none of a
    spectral ratio's leakage from the motion's large low-frequency power. Symmetric taps: zero phase (a
    causal filter's lag would show as a delay). At most `max_rows` samples per joint enter the fit (whole
    finite stretches, in trial order): 26 taps need far fewer, and a paper-scale dataset would otherwise
    build a design matrix of gigabytes. None where the data are too short or the velocity absent.
    """
    K = int(half_width)
    rows, rhs = None, None
    used = 0
    for t in trials:
        if used >= max_rows:
            break
        q, qd = np.asarray(t.q, dtype=np.float64), np.asarray(t.qd, dtype=np.float64)
        n = q.shape[1]
        if rows is None:
            rows, rhs = [[] for _ in range(n)], [[] for _ in range(n)]
        for a, b in finite_runs(np.isfinite(q).all(1) & np.isfinite(qd).all(1)):
            if b - a < 8 * K:
                continue
            x, v = np.gradient(q[a:b], dt, axis=0), qd[a:b]
            T = b - a
            for j in range(n):
                # column k: x_{t-k} + x_{t+k} (k ≥ 1), column 0: x_t, for t with the whole window inside
                X = [x[K:T - K, j]] + [x[K - k:T - K - k, j] + x[K + k:T - K + k, j] for k in range(1, K + 1)]
                rows[j].append(np.stack(X, 1))
                rhs[j].append(v[K:T - K, j])
            used += T - 2 * K
    if rows is None or not rows[0]:
        return None
    taps = []
    for j in range(len(rows)):
        A, y = np.concatenate(rows[j]), np.concatenate(rhs[j])
        c = np.linalg.lstsq(A, y, rcond=None)[0]
        taps.append(np.concatenate([c[:0:-1], c]))      # h_-K .. h_K
    taps = np.stack(taps, 1)
    return taps if np.isfinite(taps).all() else None


def _fir(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """x (T, n) filtered with symmetric taps (2 K + 1, n), the trial mirrored at both ends (no edge step);
    a trial shorter than the half-width is extended with its end values instead."""
    from scipy.ndimage import convolve1d

    mode = "mirror" if x.shape[0] > (taps.shape[0] - 1) // 2 + 1 else "nearest"
    return np.stack([convolve1d(x[:, j], taps[:, j], mode=mode) for j in range(x.shape[1])], axis=1)


def exo_derivatives(tau_e: np.ndarray, dt: float, window: int = 9,
                    response: np.ndarray | None = None,
                    qdd_window: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First and second time derivatives of one trial's recorded exo torque (T, n), as the measured q̇ and q̈
    would show them.

    With `response` (`velocity_response`: FIR taps of the recorded velocity's own filter) and `qdd_window`
    (the reader's Savitzky-Golay window for q̈): τ̇ is the central difference filtered by that response, and
    τ̈ is the reader's q̈ derivative of that τ̇ — the chain a strap deflection τ_app/k goes through on its way
    into the measured q̇ and q̈. It also keeps the exo torque's sensor noise out: a window-9 second derivative of
    0.05 N m white noise has an SD of 230 N m/s², up to 14 % of τ̈'s variance in a measured strap world, and
    noise in a regressor biases its coefficient (the compliance) towards 0 (measured there: k 22 % high).
    Without them: cubic Savitzky-Golay derivatives over `window` samples. NaN samples are zeroed here only
    for the filter; the caller's `valid` mask keeps them out of every loss.
    """
    from scipy.signal import savgol_filter

    x = np.nan_to_num(np.asarray(tau_e, dtype=np.float64))
    T = x.shape[0]
    if response is not None and qdd_window is not None and T >= max(qdd_window, 5):
        d1 = _fir(np.gradient(x, dt, axis=0), response)
        d2 = savgol_filter(d1, qdd_window, 3, deriv=1, delta=dt, axis=0)
        return d1, d2
    w = min(window, T if T % 2 == 1 else T - 1)
    if w < 5:
        d1 = np.gradient(x, dt, axis=0) if T > 1 else np.zeros_like(x)
        d2 = np.gradient(d1, dt, axis=0) if T > 1 else np.zeros_like(x)
        return d1, d2
    d1 = savgol_filter(x, w, 3, deriv=1, delta=dt, axis=0)
    d2 = savgol_filter(x, w, 3, deriv=2, delta=dt, axis=0)
    return d1, d2
