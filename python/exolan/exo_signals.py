"""Trial signals for the extended model: exo-torque lag tables, histories read on demand (`Lagged`) and
derivatives, the recorded velocity's filter, the side of a backlash gap (`gap_side`)."""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

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


class Stacked:
    """A series' history as a gathered (B, K+1, n) tensor (column k: k samples earlier), or (B, n) for the
    current sample alone: `now()` (B, n) and `column(k)` (B, n), per joint j the sample k_j steps earlier."""

    def __init__(self, hist: torch.Tensor):
        self.hist = hist.unsqueeze(1) if hist.dim() == 2 else hist
        self.K = self.hist.shape[1] - 1

    def now(self) -> torch.Tensor:
        return self.hist[:, 0]

    def column(self, k: torch.Tensor) -> torch.Tensor:
        B, _, n = self.hist.shape
        return torch.gather(self.hist, 1, k.view(1, 1, n).expand(B, 1, n))[:, 0]


class Lagged:
    """A series' history at B rows read on demand, as `Stacked` reads a gathered one, without gathering the K+1
    columns of which a delay reads two (the gathers were a fifth of a delay fit's step)."""

    def __init__(self, values: torch.Tensor, lag: torch.Tensor, rows: torch.Tensor, shared: dict | None = None):
        self.values, self.lag, self.rows = values, lag, rows     # (N, n), (N, K+1) flat indices, (B,)
        self.shared = {} if shared is None else shared          # row indices by column, shared by series of one lag

    @property
    def K(self) -> int:
        return self.lag.shape[1] - 1

    def now(self) -> torch.Tensor:
        return self.values.index_select(0, self.rows)

    def column(self, k: torch.Tensor) -> torch.Tensor:
        key = tuple(k.tolist())
        if key not in self.shared:
            flat = (self.rows[:, None] * self.lag.shape[1] + k[None, :]).reshape(-1)
            self.shared[key] = self.lag.reshape(-1).index_select(0, flat).view(len(self.rows), -1)
        return self.values.gather(0, self.shared[key])


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


def gap_side(q: np.ndarray, dt: float, k: float = 4.0) -> np.ndarray:
    """(T, n) the side of a backlash gap that the limb rests on, read off one trial's raw measured angles (T, n):
    +1 after a rise, −1 after a fall, so that the limb's angle is q + (w/2) s for a backlash of width w.

    A play operator holds the measured angle while the limb crosses the gap after a reversal. A held stretch is a
    run of at least two steps within k √2 σ, σ the encoder noise (the robust SD of the angle less its low-pass);
    where it ends in a reversal the limb's path through the gap is taken at constant acceleration, s = ±(1 −
    2 (t/T)²), since it starts at rest. Read off the raw angle the gap's ends are sharp to a sample; read off a
    filtered velocity they are blurred, and the inertial shift a backlash makes came out 30 % short that way
    (docs/DIAGNOSIS.md, "Backlash"). Elsewhere s is the sign of the low-passed angle's slope."""
    from scipy.signal import butter

    x = np.asarray(q, dtype=np.float64)
    out = np.zeros_like(x)
    fc = min(0.2 / dt, 50.0)
    sos = butter(4, fc, fs=1.0 / dt, output="sos")
    edge = int(np.ceil(1.0 / (fc * dt)))       # samples at each end of a run where the smoothed slope is the padding's
    for j in range(x.shape[1]):
        for a, b in finite_runs(np.isfinite(x[:, j])):
            if b - a > 30:
                out[a:b, j] = _side_of_run(x[a:b, j], sos, k, edge)
    return out


def _side_of_run(x: np.ndarray, sos, k: float, edge: int, m: int = 6) -> np.ndarray:
    from scipy.signal import sosfiltfilt

    smooth = sosfiltfilt(sos, x)
    r = x - smooth
    sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    held = np.abs(np.diff(x)) <= k * np.sqrt(2.0) * sigma         # the step i -> i + 1 within the noise
    # the side between held stretches: the smoothed slope's sign, kept where the slope is within its own noise
    slope = np.gradient(smooth)
    gain = np.std(np.gradient(sosfiltfilt(sos, np.random.default_rng(0).standard_normal(4096))))
    sure = np.abs(slope) > k * sigma * gain
    # near a run's ends the smoothed slope is the filter's padding: a side read there flipped for two samples at a
    # trial's start, and its second derivative (4e4 rad/s² per unit) wrecked the rows around it; the side there is
    # the nearest one read inside
    sure[:edge] = False
    sure[len(sure) - edge:] = False
    idx = np.maximum.accumulate(np.where(sure, np.arange(len(slope)), -1))
    first = np.sign(slope[int(np.argmax(sure))]) if sure.any() else 1.0
    s = np.where(idx >= 0, np.sign(slope[np.maximum(idx, 0)]), first)
    n = len(x)
    for i, j in _held_runs(x, held, k * sigma):
        if j - i >= 2 and i >= m and j + m < n:
            t0, before, t1, after = _gap_ends(x, i, j, m)
            lo, hi = min(int(np.floor(t0)), i), max(int(np.ceil(t1)) + 1, j + 1)
            if before != 0 and after == -before:       # a reversal: the limb crosses the gap at constant acceleration
                u = np.clip((np.arange(lo, hi, dtype=np.float64) - t0) / (t1 - t0), 0.0, 1.0)
                s[lo:hi] = before * (1.0 - 2.0 * u ** 2)
            else:                                       # a rest: the side it was reached from
                s[i:hi] = s[i - 1]
            while hi < n and not sure[hi]:              # until the slope is sure again, the side it left on
                s[hi] = s[hi - 1]
                hi += 1
    return s


def _held_runs(x: np.ndarray, held: np.ndarray, tol: float) -> list[tuple[int, int]]:
    """[(i, j)]: stretches of samples i..j joined by held steps; two stretches a noise step or two apart whose
    levels (medians) lie within `tol` of each other are one (a long gap's noise breaks it otherwise)."""
    out: list[tuple[int, int]] = []
    for i, j in ((int(a), int(b)) for a, b in finite_runs(held)):     # steps i..j-1 held: samples i..j
        if out and i - out[-1][1] <= 2 and abs(np.median(x[i:j + 1]) - np.median(x[out[-1][0]:out[-1][1] + 1])) <= tol:
            out[-1] = (out[-1][0], j)
        else:
            out.append((i, j))
    return out


def _gap_ends(x: np.ndarray, i: int, j: int, m: int, step: float = 0.25) -> tuple[float, float, float, float]:
    """Around a held stretch [i, j]: where the measured angle stopped (the limb's reversal) and from which side
    (+1: rising), and where it moved again (the limb at the gap's other side) and to which side, in fractional
    samples. The stop is the knot of a level with a quadratic approach, y0 + c min(t − t0, 0)², the start the knot
    of a level with a departure, y0 + b max(t − t1, 0) + c' max(t − t1, 0)², each by least squares profiled over
    the knot (a noise threshold alone starts the gap where a slow approach comes within the noise, tens of ms
    early at a slow reversal; a difference of a few samples reads the side off noise)."""
    def knot(lo: int, hi: int, grid: np.ndarray, cols) -> tuple[float, np.ndarray]:
        t = np.arange(lo, hi + 1, dtype=np.float64)
        y = x[lo:hi + 1] - x[lo:hi + 1].mean()          # centred: the level's column stays well scaled
        d = t[None, :] - grid[:, None]                   # (knots, samples): every knot's fit at once
        A = np.stack([np.ones_like(d)] + [c(d) for c in cols], -1)
        AtA = np.einsum("gtp,gtq->gpq", A, A) + 1e-12 * np.eye(A.shape[-1])
        beta = np.linalg.solve(AtA, np.einsum("gtp,t->gp", A, y)[..., None])[..., 0]
        sse = ((y[None, :] - np.einsum("gtp,gp->gt", A, beta)) ** 2).sum(1)
        g = int(np.argmin(sse))
        return float(grid[g]), beta[g]

    t0, c0 = knot(i - m, j, np.arange(i - m, j + step / 2, step), [lambda d: np.minimum(d, 0.0) ** 2])
    start = max(i, int(t0))
    t1, c1 = knot(start, j + m, np.arange(start, j + m - 1 + step / 2, step),
                  [lambda d: np.maximum(d, 0.0), lambda d: np.maximum(d, 0.0) ** 2])
    before, after = -float(np.sign(c0[1])), float(np.sign(c1[1] + c1[2] * (j + m - t1)))
    if t1 - t0 < 1.0:
        t0, t1 = i - 0.5, j + 0.5
    return t0, before, t1, after
