"""Physics first's signals: the rows of a `flat.Flat` through two zero-phase low-passes (`signals`), q̇ and q̈
(and τ̇_e, τ̈_e) by central differences of the first, τ and every regressor column through the second (parallel
filtering, `Signals.lp`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from ..data import finite_runs
from .flat import folds

CUTOFF_HZ = 25.0        # default low-pass of q and τ: above a limb's or a drive's motion, below encoder noise


@dataclass
class Signals:
    """Signals on the rows of a `flat.Flat` (the same order): kinematics and exo torque low-passed for
    differentiation, τ through the parallel filter (`lp`); `ok`: rows where they are usable."""
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    tau_e: np.ndarray
    tau_e_d: np.ndarray
    tau_e_dd: np.ndarray
    f_v: np.ndarray
    f_o: np.ndarray
    x_cop: np.ndarray
    tau_raw: np.ndarray     # the recorded τ, unfiltered: held-out errors are the user's
    mass: np.ndarray        # (N,) body mass of each row (1 for layout 2): errors are mass-normalised as elsewhere
    ok: np.ndarray
    train: np.ndarray
    held: np.ndarray
    trial: np.ndarray
    subject: np.ndarray
    joint_types: tuple
    dt: float
    lag_of: list            # per trial: start row, length (delay shifts stay inside their trial)
    cutoff: float
    runs: list              # (start, stop) rows of every finite run
    sos: tuple              # the second (parallel) filter and its pad length
    side: np.ndarray | None = None      # (N, n) the side of a backlash gap (`Flat.side`), filtered and differentiated
    side_d: np.ndarray | None = None    # as q is: the limb's kinematics are q + (w/2) s and its derivatives
    side_dd: np.ndarray | None = None
    fold: np.ndarray | None = None      # (N,) cross-fitting fold (`flat.folds`): 0 the held-out segments

    def lp(self, x: np.ndarray) -> np.ndarray:
        """x (N,) or (N, k) low-passed with the parallel filter per finite run (NaN kept where it is)."""
        sos, pad = self.sos
        out = np.full(x.shape, np.nan)
        for a, b in self.runs:
            seg = x[a:b]
            fin = np.isfinite(seg).all(axis=tuple(range(1, seg.ndim))) if seg.ndim > 1 else np.isfinite(seg)
            if b - a > pad + 3 and fin.all():
                out[a:b] = signal.sosfiltfilt(sos, seg, axis=0, padlen=pad)
        return out


def _filtered(x: np.ndarray, runs, sos, padlen: int, dt: float):
    """(x_f, x_f', x_f'') of x (T, k) over the given finite runs; NaN outside runs too short to filter."""
    out = [np.full_like(x, np.nan) for _ in range(3)]
    for a, b in runs:
        if b - a <= padlen + 3:
            continue
        xf = signal.sosfiltfilt(sos, x[a:b], axis=0, padlen=padlen)
        d1 = np.gradient(xf, dt, axis=0)
        out[0][a:b], out[1][a:b], out[2][a:b] = xf, d1, np.gradient(d1, dt, axis=0)
    return out


def _design(fc: float, dt: float):
    return signal.butter(4, fc, fs=1.0 / dt, output="sos"), int(min(3 * round(1.0 / (fc * dt)), 500))


def _differentiation_filter(fc: float, dt: float):
    """`signals`' first low-pass, at four times the cutoff: only for differentiating q and τ_e."""
    return _design(min(4 * fc, 0.4 / dt), dt)


def run_edges(runs, N: int, width: int) -> np.ndarray:
    """(N,) True on the first and last `width` rows of every run."""
    edge = np.zeros(N, bool)
    for a, b in runs:
        edge[a:min(b, a + width)] = True
        edge[max(a, b - width):b] = True
    return edge


def exo_like(sig: Signals, x: np.ndarray) -> np.ndarray:
    """x (N,), a signal of the exo torque's kind on the flat's rows, filtered as `signals` filters τ_e and then as
    a regressor column (`lp`): what a gain's column is when x stands in for τ_e."""
    sos1, pad1 = _differentiation_filter(sig.cutoff, sig.dt)
    return np.nan_to_num(sig.lp(_filtered(x[:, None], sig.runs, sos1, pad1, sig.dt)[0][:, 0]))


def signals(flat, cutoff_hz: float = CUTOFF_HZ) -> Signals:
    """Two zero-phase Butterworth low-passes (order 4), per trial and finite run. The first, at four times the
    cutoff, only for differentiation: q̇, q̈ (and τ̇_e, τ̈_e) by central differences of the low-passed q (τ_e).
    The second, at the cutoff, filters τ and every regressor column built from those signals (`Signals.lp`),
    the same filter on both sides of the equation (parallel filtering): a nonlinear column such as the sign of
    q̇ is then smoothed exactly as the torque's own friction part is — low-passing q̇ before taking its sign
    would leave a friction-like misfit at every reversal, which a Stribeck term then takes."""
    dt = float(flat.dt)
    fc = min(float(cutoff_hz), 0.4 / dt)
    sos1, pad1 = _differentiation_filter(fc, dt)
    valid = flat.valid.numpy().astype(bool)
    N, n = flat.q.shape
    cols = {k: np.full((N, n), np.nan) for k in ("q", "qd", "qdd", "tau_e", "tau_e_d", "tau_e_dd")}
    if flat.side is not None:
        cols.update({k: np.full((N, n), np.nan) for k in ("side", "side_d", "side_dd")})
    one = {k: np.full(N, np.nan) for k in ("f_v", "f_o", "x_cop")}
    lag_of, runs_all, start = [], [], 0
    for T in flat.lengths:
        sl = slice(start, start + T)
        runs = list(finite_runs(valid[sl]))
        runs_all += [(start + a, start + b) for a, b in runs]
        cols["q"][sl], cols["qd"][sl], cols["qdd"][sl] = _filtered(flat.q[sl].double().numpy(), runs, sos1, pad1, dt)
        te = _filtered(flat.tau_e[sl].double().numpy(), runs, sos1, pad1, dt)
        cols["tau_e"][sl], cols["tau_e_d"][sl], cols["tau_e_dd"][sl] = te
        if flat.side is not None:
            sd = _filtered(flat.side[sl].double().numpy(), runs, sos1, pad1, dt)
            cols["side"][sl], cols["side_d"][sl], cols["side_dd"][sl] = sd
        for k in one:
            one[k][sl] = _filtered(getattr(flat, k)[sl].double().numpy()[:, None], runs, sos1, pad1, dt)[0][:, 0]
        lag_of.append((start, T))
        start += T
    held = flat.held.numpy().astype(bool)
    trial = flat.trial.numpy()
    subject = np.array([flat.trial_meta[i]["subject"] for i in range(len(flat.lengths))])[trial]
    sig = Signals(**cols, **one, tau=None, tau_raw=flat.tau.double().numpy(), mass=flat.mass.double().numpy(),
                  ok=valid, train=None, held=None, trial=trial, subject=subject, joint_types=tuple(flat.joint_types),
                  dt=dt, lag_of=lag_of, cutoff=fc, runs=runs_all, sos=_design(fc, dt))
    sig.tau = sig.lp(sig.tau_raw)
    # a zero-phase filter's first and last rows of a run are shaped by its padding, not by the data: the columns
    # built from q̈ there (both filters in series) are not the recording's (measured: docs/DIAGNOSIS.md, "Filter edges")
    edge = run_edges(runs_all, N, pad1 + sig.sos[1])
    sig.ok = valid & np.isfinite(cols["q"]).all(1) & np.isfinite(sig.tau).all(1) & ~edge
    sig.train, sig.held, sig.fold = sig.ok & ~held, sig.ok & held, folds(flat)
    return sig
