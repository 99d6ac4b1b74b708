"""Physics first: every candidate term sized against a parametric rigid-body base by least squares.

Why: a term fitted jointly with a learned base shares the data with a network that can take part of it (a
linear drive's viscous and Coulomb friction came out 0.44x and 1.54x of their published values that way,
issue 38). A base that cannot imitate a term sizes it without that trade: the parametric base (`rigid_base`) has
no velocity-odd part, so no dissipation, lag or compliance can hide in it. This is identification as in the
robotics literature: parallel zero-phase low-pass of q and τ (scipy `sosfiltfilt`), q̇ and q̈ by central
differences (`np.gradient`), weighted least squares on the training segments, intervals by a Newey-West (HAC)
sandwich (statsmodels) over time, since the residuals are autocorrelated.

The base's columns: `rigid_base`. Nonlinear-in-parameter terms are sized by a grid over the nonlinear
parameter with least squares inside (variable projection); their intervals are the HAC sandwich of the
linearised model at the optimum. Terms and their tests live in `TERMS`.
"""
from __future__ import annotations

import copy
import math
import threading
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize
from scipy import stats as sps

from ..extensions import COULOMB_EPS
from . import wls
from .parallel_filter import Signals
from .rigid_base import base_columns
from .shift import ShiftBasis, backlash_col, backlash_grid

_BASIS_LOCK = threading.Lock()     # a shift basis is made once per joint, whichever thread asks first

SLIDING = 3.0           # rows with |q̇| below SLIDING·ε are left out of the fit (`JointProblem`)


# -- candidate terms ------------------------------------------------------------------------------------------

def _delayed(x: np.ndarray, sig: Signals, d: float) -> np.ndarray:
    """x (N,) d seconds earlier within each trial (linear interpolation, clamped at the trial's start)."""
    out = np.empty_like(x)
    s = d / sig.dt
    for a, T in sig.lag_of:
        t = np.arange(T) - s
        out[a:a + T] = np.interp(t, np.arange(T), x[a:a + T])
    return out


@dataclass(frozen=True)
class Term:
    """How one effect enters a joint's torque equation: a column linear in its parameter θ, perhaps at a
    nonlinear parameter ν from a grid (variable projection); `fixed`: the column enters with coefficient 1 and
    ν is the parameter (a delay). `report(θ, ν)` maps to the vocabulary's parameter; `neutral`: no effect."""
    effect: str
    column: object                  # (sig, j, nu, ctx) -> (N,) column
    grid: object = None             # (sig, j, ctx) -> list of ν, None: linear
    fixed: bool = False
    dcol: object = None             # (sig, j, nu) -> ∂column/∂ν (fixed terms: their linearisation)
    report: object = None           # (θ, ν) -> reported parameter
    sided: str = "greater"          # the test of θ against its neutral value: greater | two-sided
    pole: float | None = None       # θ where the reported parameter goes to infinity (a monotone map on each side)
    own_variation: bool = False     # its column is the exo torque itself: asked on the controller's own variation too
    shift: bool = False             # ν moves joint j's coordinates by (ν/2) s: the base is refitted at each ν (`shift`)

    def value(self, theta, nu):
        return self.report(theta, nu) if self.report is not None else theta


def _coulomb(sig, j, nu, ctx):
    return np.tanh(sig.qd[:, j] / COULOMB_EPS)


def _stribeck(sig, j, nu, ctx):
    return np.exp(-(sig.qd[:, j] / nu) ** 2) * np.tanh(sig.qd[:, j] / COULOMB_EPS)


def _stribeck_grid(sig, j, ctx):
    # from where the fit looks (|q̇| ≥ SLIDING·ε, `JointProblem`): a smaller vs puts the term where no row is fitted
    v = np.abs(sig.qd[sig.train, j])
    lo = SLIDING * COULOMB_EPS
    v = v[v >= lo]
    if len(v) == 0:
        return [lo, 2 * lo]
    lo = max(np.quantile(v, 0.05), lo)
    hi = max(np.quantile(v, 0.9), 2 * lo)
    return list(np.geomspace(lo, hi, 10))


def _delay_col(sig, j, nu, ctx):
    te = sig.tau_e[:, j]
    return te - _delayed(te, sig, nu)


def _delay_grid(sig, j, ctx):
    step = max(sig.dt, 0.0025)     # 2.5 ms resolution: finer than any delay these data can show
    return list(np.arange(1, int(round(ctx.get("max_delay", 0.1) / step)) + 1) * step)


def _strap_col(sig, j, nu, ctx):
    """Linearised strap: the physics at q − c τ_e: −c (∂τ̂/∂q τ_e + ∂τ̂/∂q̇ τ̇_e + ∂τ̂/∂q̈ τ̈_e), ∂τ̂ from the
    base's coefficients `ctx['base_theta']` (the fit with the strap, `physics._strap_point`); linear in c = 1/k."""
    G = ctx.setdefault("strap_G", {})
    if j not in G:      # the base columns' derivative along the deflection: linear in θ, made once per joint
        h, Gj = 1e-4, 0.0
        for name, src in (("q", sig.tau_e), ("qd", sig.tau_e_d), ("qdd", sig.tau_e_dd)):
            kin = {"q": sig.q.copy(), "qd": sig.qd.copy(), "qdd": sig.qdd.copy()}
            kin[name][:, j] += h
            Gj = Gj + (base_columns(kin["q"], kin["qd"], kin["qdd"], sig)[0] - ctx["base_raw"]) / h * src[:, j:j + 1]
        G[j] = Gj
    return -(G[j] @ ctx["base_theta"][j])


TERMS: dict[str, Term] = {t.effect: t for t in [
    Term("viscous_damping", lambda sig, j, nu, ctx: sig.qd[:, j]),
    Term("coulomb_friction", _coulomb),
    Term("stribeck_friction", _stribeck, grid=_stribeck_grid),
    Term("torque_gain", lambda sig, j, nu, ctx: sig.tau_e[:, j], report=lambda th, nu: 1.0 / (1.0 - th),
         sided="two-sided", pole=1.0, own_variation=True),
    Term("actuation_delay", _delay_col, grid=_delay_grid, fixed=True,
         dcol=lambda sig, j, nu: _delayed(sig.tau_e_d[:, j], sig, nu)),
    Term("strap_compliance", _strap_col, report=lambda th, nu: 1.0 / th if th > 0 else math.inf, pole=0.0),
    Term("backlash", backlash_col, grid=backlash_grid, fixed=True, shift=True),
]}


# -- one joint equation's fits ------------------------------------------------------------------------------

@dataclass
class Fit:
    """One fitted model of a joint equation: the base plus `terms` [(effect, ν)]."""
    terms: list
    theta: np.ndarray
    names: list
    nu: dict
    pred: np.ndarray            # (N,) prediction on every row
    se: dict = field(default_factory=dict)      # effect -> SE of its parameter (θ, or ν for fixed terms)
    est: dict = field(default_factory=dict)     # effect -> θ (or ν for fixed terms)
    lags: int = 0
    split: dict = field(default_factory=dict)   # effect -> (θ by subject, SE by subject) of a term split by subject


class JointProblem:
    """Weighted LS of joint j's torque equation on the training rows; the base regressor built once."""

    def __init__(self, sig: Signals, j: int, X_base: np.ndarray, base_names: list, ctx: dict, shiftable: bool = True):
        """`shiftable`: X_base is `base_columns` of the signals (a shift term refits it in moved coordinates);
        False for another base (a constant), where a shift term enters linearised (`shift.backlash_col`)."""
        self.sig, self.j, self.ctx = sig, j, ctx
        self._shiftable = shiftable and sig.side is not None
        self._shift: ShiftBasis | None = None
        self._at: tuple = (None, None)      # (u, X(u)): the last shifted design
        self.Xb, self.base_names = X_base, base_names
        self.y = sig.tau[:, j]
        rows = sig.ok & np.isfinite(X_base).all(1)
        # fitted where the friction law's smoothing no longer matters (|q̇| ≥ 3ε, tanh(3) = 0.995): near rest the
        # data's own law (stiction, pre-sliding) is unknown and the model's tanh(q̇/ε) is a numerical choice
        moving = np.abs(np.nan_to_num(sig.qd[:, j])) >= SLIDING * COULOMB_EPS
        self.rows, self.train, self.held = rows, rows & sig.train & moving, rows & sig.held
        self.w = np.ones(len(self.y))
        self._cols: dict = {}
        self._grids: dict = {}      # effect -> its grid of ν (`grid`; `col` caches there only)
        self.split: dict = {}       # effect -> row masks: the term's column split by subject (`physics.select`)

    @property
    def w(self) -> np.ndarray:
        """Fit weight per row (feasible WLS); setting it drops the base's factorisation made for the old one."""
        return self._w

    @w.setter
    def w(self, w: np.ndarray):
        self._w, self._qr = w, {}
        if getattr(self, "_shift", None) is not None:
            self._shift.forget()

    def _u(self, terms: list, nu: dict) -> float:
        """The coordinate shift u = ν/2 of a shift term among `terms` (0: none, or the base cannot move)."""
        if self._shiftable:
            for e in terms:
                if TERMS[e].shift and nu.get(e) is not None:
                    return 0.5 * float(nu[e])
        return 0.0

    def _basis(self) -> ShiftBasis:
        root = self.__dict__.get("_root", self)     # a view's basis is its problem's: made once, shared
        with _BASIS_LOCK:
            if root._shift is None:
                h = 0.25 * min(min(root.grid(e)) for e in TERMS if TERMS[e].shift)
                root._shift = ShiftBasis(root.sig, root.j, root.Xb, h, base_columns)
            return root._shift

    def view(self) -> "JointProblem":
        """This problem for one thread (`physics.select` tests a step's candidates side by side): the data, the
        weights and the column caches shared; the last shifted design, the factorisations and the subject splits
        its own (a fit sets them as it goes). A view's fits are the problem's, bit for bit."""
        v = copy.copy(self)
        v._at, v._qr, v.split, v._root = (None, None), dict(self._qr), dict(self.split), self.__dict__.get("_root", self)
        return v

    def _X(self, u: float) -> np.ndarray:
        """The base's design at the shift u (the measured coordinates at 0); the last shifted one kept."""
        if u == 0.0:
            return self.Xb
        if self._at[0] != u:
            self._at = (u, self._basis().at(u))
        return self._at[1]

    def _base(self, u: float = 0.0) -> wls.BaseQR:
        """The weighted base on the training rows at the shift u, factorised once per weighting (the measured
        coordinates' and the last shifted one's kept)."""
        qr = self._qr.get(u)
        if qr is None:
            self._qr = {k: v for k, v in self._qr.items() if k == 0.0}
            qr = self._qr[u] = wls.BaseQR(self._X(u)[self.train], np.sqrt(self.w[self.train]))
        return qr

    def _wls(self, X: np.ndarray, z: np.ndarray, u: float = 0.0) -> np.ndarray:
        """Coefficients of the weighted LS fit of z on X (training rows; its first columns the base at u)."""
        sw = np.sqrt(self.w[self.train])
        return wls.fit(self._base(u), X[:, len(self.base_names):] * sw[:, None], z * sw)

    def _hac(self, X: np.ndarray, z: np.ndarray, sub: list, u: float = 0.0) -> tuple:
        """HAC coefficients and SEs of the term columns `sub` of the weighted fit of z on X (training rows; its
        first columns the base, partialled out by its factorisation; any other term columns by their own)."""
        nb = len(self.base_names)
        assert min(sub, default=nb) >= nb, "only term columns have intervals here"
        sw = np.sqrt(self.w[self.train])
        qr = self._base(u)
        A, Z = qr.residual(X[:, sub] * sw[:, None]), qr.residual(z * sw)
        other = [i for i in range(nb, X.shape[1]) if i not in sub]
        if other:
            q2 = wls.BaseQR(qr.residual(X[:, other] * sw[:, None]), np.ones(len(sw)))
            A, Z = q2.residual(A), q2.residual(Z)
        return wls.hac_partialled(A, Z, X.shape[1])

    def col(self, effect: str, nu):
        """A term's column (filtered as τ) at ν; cached at ν on the term's grid only (a refined ν is one of many)."""
        key = (effect, None if nu is None else float(nu))
        c = self._cols.get(key)
        if c is None:
            t = TERMS[effect]
            c = t.column(self.sig, self.j, nu, self.ctx)
            c = c if t.shift else np.nan_to_num(self.sig.lp(c))       # a shift's linearisation is filtered already
            if nu is None or float(nu) in (self.grid(effect) or ()):
                self._cols[key] = c
        return c

    def grid(self, effect: str) -> list | None:
        """The term's grid of ν on this joint's data (None: linear), made once."""
        if effect not in self._grids:
            g = TERMS[effect].grid
            self._grids[effect] = None if g is None else [float(v) for v in g(self.sig, self.j, self.ctx)]
        return self._grids[effect]

    def _columns(self, eff: str, c: np.ndarray) -> list:
        """A linear term's columns with their names: one, or one per subject where the term is split."""
        if eff in self.split:
            return [(f"{eff}#{k}", c * m) for k, m in enumerate(self.split[eff])]
        return [(eff, c)]

    def _moves(self, eff: str) -> bool:
        """A shift term that moves the base's coordinates here (no column of its own)."""
        return TERMS[eff].shift and self._shiftable

    def _parts(self, terms: list, nu: dict, leave_out: str | None = None) -> tuple[np.ndarray, list]:
        """What `terms` at ν add to the base on every row: the fixed terms' columns summed (an offset) and the
        linear terms' named columns; a term that moves the base adds none."""
        offset, cols = np.zeros(len(self.y)), []
        for eff in terms:
            if eff == leave_out or self._moves(eff):
                continue
            c = self.col(eff, nu.get(eff))
            if TERMS[eff].fixed:
                offset += c
            else:
                cols += self._columns(eff, c)
        return offset, cols

    def _design(self, terms: list, nu: dict):
        offset, cols = self._parts(terms, nu)
        X = np.concatenate([self._X(self._u(terms, nu))] + [c[:, None] for _, c in cols], 1)
        return X, list(self.base_names) + [name for name, _ in cols], offset

    def _partial(self, v: np.ndarray, u: float = 0.0) -> np.ndarray:
        """v (training rows, weighted) less its projection on the weighted base at the shift u."""
        return self._base(u).residual(v)

    def sse(self, terms: list, nu: dict) -> float:
        """Weighted training SSE of the base plus `terms` at ν (the base partialled out: a small LS)."""
        tr = self.train
        sw = np.sqrt(self.w[tr])
        u = self._u(terms, nu)
        off, cols = self._parts(terms, nu)
        rz = self._partial((self.y[tr] - off[tr]) * sw, u)
        if cols:
            Cz = self._partial(np.stack([c[tr] for _, c in cols], 1) * sw[:, None], u)
            rz = rz - Cz @ np.linalg.lstsq(Cz, rz, rcond=None)[0]
        return float(rz @ rz)

    def fit(self, terms: list, intervals: bool = True) -> Fit:
        """Fit the base plus `terms`, ν of nonlinear terms by grid (coordinate-wise, two passes)."""
        nu = {e: None for e in terms}
        grids = {e: self.grid(e) for e in terms if TERMS[e].grid is not None}
        for e in grids:
            nu[e] = grids[e][len(grids[e]) // 2]
        for _ in range(2 if len(grids) > 1 else 1):
            for e, g in grids.items():
                sse = self._profile(terms, nu, e)
                nu[e] = g[int(np.argmin([sse(v) for v in g]))]
        for e, g in grids.items():
            nu[e] = self._refine(self._profile(terms, nu, e), nu[e], g)
        X, names, off = self._design(terms, nu)
        tr = self.train
        th = self._wls(X[tr], (self.y - off)[tr], self._u(terms, nu))
        f = Fit(terms=list(terms), theta=th, names=names, nu=nu, pred=X @ th + off)
        if intervals and terms:
            self._intervals(f, X, off)
        return f

    def _profile(self, terms: list, nu: dict, e: str):
        """ν -> the training SSE with `e` at ν and every other term at `nu`. A shift term's by its Gram profile
        (`shift.Profile`: the base refitted at every ν without a factorisation of the rows)."""
        if not self._moves(e):
            return lambda v: self.sse(terms, dict(nu, **{e: float(v)}))
        off, cols = self._parts(terms, nu, leave_out=e)
        C = np.stack([c for _, c in cols], 1) if cols else np.zeros((len(self.y), 0))
        prof = self._basis().profile(self.train, self.w, self.y - off, C)
        return lambda v: prof(0.5 * float(v))

    def _refine(self, sse, nu_e: float, grid: list) -> float:
        """ν of `e` between the grid's neighbours of its grid optimum (bounded Brent on the training SSE): a grid
        step is no resolution of the data, and a linear rival fits the step's error (a delay 2.3 ms off its grid
        point lost to a negative damping, `tests/test_diagnose_drive.py`). An optimum at an edge of the grid stays
        there: it is not identified (`physics._p`)."""
        i = int(np.argmin(np.abs(np.asarray(grid, dtype=float) - float(nu_e))))
        if i == 0 or i == len(grid) - 1:
            return nu_e
        lo, hi = float(grid[i - 1]), float(grid[i + 1])
        r = optimize.minimize_scalar(sse, bounds=(lo, hi), method="bounded", options={"xatol": (hi - lo) * 1e-3})
        return float(r.x) if r.fun < sse(nu_e) else nu_e

    def dcol(self, e: str, f: Fit) -> np.ndarray:
        """∂prediction/∂ν of a fixed term at `f` (filtered as τ): its linearisation, for intervals and trials."""
        t = TERMS[e]
        if self._moves(e):
            return 0.5 * self._basis().derivative(0.5 * f.nu[e], f.theta[:len(self.base_names)])
        if t.shift:
            return self.ctx["shift_D"][self.j]
        return np.nan_to_num(self.sig.lp(t.dcol(self.sig, self.j, f.nu[e])))

    def _intervals(self, f: Fit, X, off):
        """HAC SE of every term's parameter; fixed terms (a delay) through their linearisation in ν."""
        tr = self.train
        extra, which = [], []
        for e in f.terms:
            if TERMS[e].fixed:
                extra.append(self.dcol(e, f)[:, None])
                which.append(e)
        Xa = np.concatenate([X] + extra, 1) if extra else X
        r = self.y - f.pred
        lin_names = [n for n in f.names if n.split("#")[0] in f.terms and not TERMS[n.split("#")[0]].fixed]
        lin = [f.names.index(n) for n in lin_names]
        sub = lin + list(range(X.shape[1], Xa.shape[1]))
        # the linearised model's residual regression: a Gauss-Newton step from the fit (zero for linear terms)
        coef, se, L = self._hac(Xa[tr], r[tr] + (Xa[tr][:, lin] @ f.theta[lin] if lin else 0), sub,
                                self._u(f.terms, f.nu))
        parts: dict = {}
        for k, n in enumerate(lin_names + which):
            e = n.split("#")[0]
            if TERMS[e].fixed:
                f.est[e], f.se[e] = float(f.nu[e]), float(se[k])
            elif "#" in n:
                parts.setdefault(e, []).append((float(coef[k]), float(se[k])))
            else:
                f.est[e], f.se[e] = float(coef[k]), float(se[k])
        for e, v in parts.items():      # a split term: its θ by subject, and their inverse-variance pool
            th, s = np.array([a for a, _ in v]), np.array([b for _, b in v])
            w = 1.0 / np.square(s)
            f.split[e] = (th, s)
            f.est[e], f.se[e] = float(np.sum(w * th) / np.sum(w)), float(1.0 / math.sqrt(np.sum(w)))
        f.lags = L

    def _split_design(self, f: Fit, effect: str | None, masks: list | None) -> tuple:
        """`f`'s design (its ν fixed) with the linear term `effect`'s column split into one per row mask."""
        X, names, off = self._design(f.terms, f.nu)
        if masks is None:
            return X, names, off
        k = names.index(effect)
        return np.concatenate([np.delete(X, k, axis=1)] + [(X[:, k] * m)[:, None] for m in masks], 1), names, off

    def cross_sq(self, f: Fit, effect: str | None = None, masks: list | None = None) -> np.ndarray:
        """Squared error as `held_sq`'s, cross-fitted: every fold's usable rows (`Signals.fold`; 0 the held-out
        segments) predicted by `f`'s model (its ν and the weights as fitted; `effect` split by `masks` as in
        `fit_split`) refitted without that fold; NaN elsewhere. Every segment is held out once: four times the
        held-out rows alone (a subject form judged by them: `physics_subjects`). This problem is left as it was."""
        X, _, off = self._split_design(f, effect, masks)
        y, u, fold = self.y - off, self._u(f.terms, f.nu), self.sig.fold
        v = self.view()             # one view: the shifted design made once, each fold's factorisation its own
        out = np.full(len(self.y), np.nan)
        for k in np.unique(fold[self.rows]):
            ev, tr = self.rows & (fold == k), self.train & (fold != k)
            if tr.sum() >= 2 * self.Xb.shape[1]:        # else too few rows left to refit the base: the fold sits out
                v.train, v._qr = tr, {}
                r = (self.sig.tau[ev, self.j] - (X @ v._wls(X[tr], y[tr], u) + off)[ev]) / self.sig.mass[ev]
                out[ev] = r * r
        return out

    def fit_split(self, f: Fit, effect: str, masks: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, Fit]:
        """`f` with the linear term `effect`'s column split into one column per row mask (a subject's rows, or a
        group of subjects'): the coefficients and HAC SEs of the split columns, and the fit (its `pred`)."""
        X, names, off = self._split_design(f, effect, masks)
        tr, u = self.train, self._u(f.terms, f.nu)
        th = self._wls(X[tr], (self.y - off)[tr], u)
        sub = list(range(X.shape[1] - len(masks), X.shape[1]))
        coef, se, L = self._hac(X[tr], (self.y - off)[tr], sub, u)
        return coef, se, Fit(terms=list(f.terms), theta=th, names=names, nu=f.nu, pred=X @ th + off, lags=L)

    def by_trial(self, f: Fit, effect: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`effect`'s parameter in each trial (`consistency`): `f` refitted with the term's column split into one
        column per trial (every other column shared); a fixed term (a delay) by its linearisation in ν around
        f's value. Returns (estimate by trial, HAC SE by trial, the trials); trials without training rows are
        left out."""
        X, names, off = self._design(f.terms, f.nu)
        t = TERMS[effect]
        if t.fixed:
            col, center, keep = self.dcol(effect, f), f.nu[effect], X
        else:       # the unsplit column: a subject split's columns are masked copies of it
            idx = [i for i, n in enumerate(names) if n.split("#")[0] == effect]
            col, center, keep = X[:, idx].sum(1), 0.0, np.delete(X, idx, axis=1)
        tr = self.train
        trials = np.array([k for k in np.unique(self.sig.trial[tr])
                           if np.any(col[tr & (self.sig.trial == k)] != 0)], dtype=int)
        Xs = np.concatenate([keep] + [(col * (self.sig.trial == k))[:, None] for k in trials], 1)
        sub = list(range(keep.shape[1], Xs.shape[1]))
        coef, se, _ = self._hac(Xs[tr], (self.y - off)[tr], sub, self._u(f.terms, f.nu))
        return center + coef, se, trials

    def held_sq(self, f: Fit, rows: np.ndarray | None = None, recorded: bool = False) -> np.ndarray:
        """Squared error, mass-normalised, on the held-out rows (or `rows`: NaN where the filtered signals are not
        usable): against τ through the parallel filter, the band the fit was made in (a term's held-out gain
        between two parametric fits: the recording's noise above the cut-off, which neither model can predict,
        only widens its interval), or with `recorded` against the recorded τ (the user's error, and the gate's
        comparison with the learned base, whose predictions are not band-limited)."""
        sel = self.held if rows is None else rows
        r = ((self.sig.tau_raw if recorded else self.sig.tau)[sel, self.j] - f.pred[sel]) / self.sig.mass[sel]
        return r * r

    def set_weights(self, f: Fit):
        """Weights per trial: the inverse mean squared training residual of `f` there (feasible WLS)."""
        r2 = (self.y - f.pred) ** 2
        w = np.ones(len(self.y))
        for t in np.unique(self.sig.trial):
            m = (self.sig.trial == t) & self.train
            if m.any():
                w[self.sig.trial == t] = 1.0 / max(float(np.mean(r2[m])), 1e-12)
        self.w = w / np.median(w[self.train])


def p_value(effect: str, est: float, se: float) -> float:
    """One-sided (dissipation, delay, compliance: only > 0 is physical) or two-sided test against no effect."""
    if not (se > 0 and math.isfinite(se)):
        return 1.0
    z = est / se
    if TERMS[effect].sided == "two-sided":
        return float(2 * sps.norm.sf(abs(z)))
    return float(sps.norm.sf(z))
