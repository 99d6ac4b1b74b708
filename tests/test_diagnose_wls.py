"""The identification's weighted least squares (`diagnose.wls`): the base factorised once and partialled out gives
the full regression's coefficients and the full HAC sandwich's block, with and without dependent base columns."""
import numpy as np
import statsmodels.api as sm

from exolan.diagnose import wls


def _data(N=3000, seed=0, dependent=False):
    rng = np.random.default_rng(seed)
    Xb = np.column_stack([np.ones(N), rng.standard_normal((N, 3))])
    if dependent:       # a base column that is a combination of two others (per-subject columns can be)
        Xb = np.column_stack([Xb, Xb[:, 1] - 2 * Xb[:, 2]])
    C = rng.standard_normal((N, 3)) + 0.5 * Xb[:, [1, 2, 3]]     # term columns correlated with the base
    e = np.convolve(rng.standard_normal(N + 10), np.ones(10) / 10, "valid")[:N]
    y = Xb[:, :4] @ np.array([0.3, 1.0, -2.0, 0.5]) + C @ np.array([1.5, 0.0, -0.7]) + e
    w = rng.uniform(0.5, 2.0, N)
    return Xb, C, y, w


def test_the_fit_partialling_the_factorised_base_equals_the_full_weighted_least_squares():
    for dependent in (False, True):
        Xb, C, y, w = _data(dependent=dependent)
        sw = np.sqrt(w)
        th = wls.fit(wls.BaseQR(Xb, sw), C * sw[:, None], y * sw)
        X = np.column_stack([Xb, C])
        ref = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)[0]
        assert np.allclose(th[-3:], ref[-3:], rtol=1e-9, atol=1e-12)          # the terms: unique
        assert np.allclose(X @ th, X @ ref, rtol=1e-9, atol=1e-9)             # the prediction: unique
        if dependent:
            assert np.sum(th[:Xb.shape[1]] == 0.0) == 1     # the dependent column gets no coefficient


def test_the_terms_hac_block_equals_the_full_weighted_regressions():
    Xb, C, y, w = _data(seed=1)
    X = np.column_stack([Xb, C])
    sw = np.sqrt(w)
    full = sm.OLS(y * sw, X * sw[:, None]).fit().get_robustcov_results(cov_type="HAC", maxlags=12,
                                                                           use_correction=True)
    coef, se, L = wls.hac_subset(X, y, w, [5, 6], lags=12)
    assert L == 12
    assert np.allclose(coef, full.params[[5, 6]], rtol=1e-8) and np.allclose(se, full.bse[[5, 6]], rtol=1e-6)
