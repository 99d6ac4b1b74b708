"""Weighted least squares against a fixed base, with HAC intervals: the linear algebra of `ident.JointProblem`.

Every candidate fit of a joint equation shares the same base columns and weights; only a few term columns
change. So the weighted base is factorised once per weighting (`BaseQR`, a rank-revealing QR) and every fit
partials it out (Frisch-Waugh-Lovell): the terms' coefficients come from a regression with a few columns, the
base's from one triangular solve, and the HAC sandwich of the terms is that block of the full one. Measured
(docs/DIAGNOSIS.md, "Time"): a fresh QR and a full lstsq per fit were three quarters of the identification.
"""
from __future__ import annotations

import math

import numpy as np
import statsmodels.api as sm
from scipy import linalg

from . import stats


def hac_lags(r: np.ndarray) -> int:
    """Newey-West lags: the block length of the residual's ACF (`stats.block_length`), at least 1."""
    return int(max(1, min(stats.block_length(r), 500)))


class BaseQR:
    """The weighted base `Xb * sqrt(w)` (training rows) factorised with column pivoting; columns that are linear
    combinations of others (relative diagonal below 1e-10) are left out of the basis, so `residual` projects onto
    exactly the base's column span."""

    def __init__(self, Xb: np.ndarray, sw: np.ndarray):
        Q, R, P = linalg.qr(Xb * sw[:, None], mode="economic", pivoting=True)
        d = np.abs(np.diag(R))
        r = int(np.sum(d > d[0] * 1e-10)) if len(d) else 0
        self.Q, self.R, self.P, self.n = Q[:, :r], R[:r, :r], P[:r], Xb.shape[1]

    def residual(self, V: np.ndarray) -> np.ndarray:
        """V (weighted training rows) less its projection on the weighted base."""
        return V - self.Q @ (self.Q.T @ V)

    def coefficients(self, v: np.ndarray) -> np.ndarray:
        """Base coefficients of the weighted LS fit of v (a basic solution: dependent columns get 0)."""
        th = np.zeros(self.n)
        th[self.P] = linalg.solve_triangular(self.R, self.Q.T @ v)
        return th


def fit(qr: BaseQR, C: np.ndarray, yw: np.ndarray) -> np.ndarray:
    """Coefficients [base, C] of the weighted LS fit of yw on the base and the weighted term columns C."""
    if C.shape[1] == 0:
        return qr.coefficients(yw)
    th_t = np.linalg.lstsq(qr.residual(C), qr.residual(yw), rcond=None)[0]
    return np.concatenate([qr.coefficients(yw - C @ th_t), th_t])


def hac_partialled(A: np.ndarray, Z: np.ndarray, n_cols: int, lags: int | None = None):
    """Coefficients and HAC SEs of the regression of Z on A, both with every other column of the full regression
    (`n_cols` in all) partialled out; the small-sample factor N/(N − n_cols) is the full regression's."""
    ols = sm.OLS(Z, A).fit()
    L = hac_lags(ols.resid) if lags is None else lags
    r = ols.get_robustcov_results(cov_type="HAC", maxlags=L, use_correction=False)
    N = len(Z)
    return np.asarray(r.params), np.asarray(r.bse) * math.sqrt(N / max(N - n_cols, 1)), L


def hac_subset(X, y, w, subset: list[int], lags: int | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Coefficients and HAC SEs of the columns `subset` of a weighted LS fit, by Frisch-Waugh-Lovell: the
    other columns partialled out, the sandwich of the small regression is that block of the full one."""
    sw = np.sqrt(w)
    Xw, yw = X * sw[:, None], y * sw
    rest = [i for i in range(X.shape[1]) if i not in subset]
    A, Z = Xw[:, subset], yw
    if rest:
        qr = BaseQR(X[:, rest], sw)
        A, Z = qr.residual(A), qr.residual(Z)
    return hac_partialled(A, Z, X.shape[1], lags)
