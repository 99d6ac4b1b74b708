"""Statistics for autocorrelated residuals: block length, block-bootstrap CIs, whiteness, cross-correlation.

Residuals of a dynamics model are strongly autocorrelated (a missing term follows the motion), so i.i.d.
standard errors and t-statistics overstate the evidence. Every interval here is a *circular block
bootstrap* (Politis & Romano) whose block length is read off the series' own autocorrelation function:
the first lag at which the ACF (statsmodels `acf`) enters its 95% band of a white series, doubled, so that
a block spans the correlation time on both sides. (The `arch` package has this resampler but is not a
dependency; the index generation below is the whole of it, the ACF and tests come from statsmodels.)
"""
from __future__ import annotations

import numpy as np
from statsmodels.stats.diagnostic import acorr_ljungbox
from statsmodels.tsa.stattools import acf, ccf


def span_if_disjoint(a, b) -> list | None:
    """Two estimates' intervals that do not overlap: the interval that spans both (a disagreement reported, not
    resolved by picking one); None where they overlap."""
    if a[1] < b[0] or b[1] < a[0]:
        return [min(a[0], b[0]), max(a[1], b[1])]
    return None


def block_length(x: np.ndarray, max_lag: int | None = None) -> int:
    """Block length (samples) from the ACF: 2 x the first lag inside the white-noise band ±1.96/√N."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    N = len(x)
    if N < 8 or np.std(x) == 0:
        return 1
    max_lag = int(min(max_lag or 400, N // 4))
    r = acf(x, nlags=max_lag, fft=True)
    band = 1.96 / np.sqrt(N)
    inside = np.nonzero(np.abs(r[1:]) < band)[0]
    first = int(inside[0]) + 1 if len(inside) else max_lag
    return int(np.clip(2 * first, 1, max(N // 4, 1)))


def circular_block_indices(N: int, block: int, rng: np.random.Generator) -> np.ndarray:
    """One circular-block-bootstrap resample of range(N): random starts, blocks wrap around the end."""
    nb = int(np.ceil(N / block))
    starts = rng.integers(0, N, size=nb)
    idx = (starts[:, None] + np.arange(block)[None, :]) % N
    return idx.reshape(-1)[:N]


def bootstrap_mean(x: np.ndarray, n_boot: int = 1000, alpha: float = 0.05, block: int | None = None,
                   seed: int = 0, ratio_to: np.ndarray | None = None, draws: bool = False) -> dict:
    """Mean of x (or mean(x)/mean(ratio_to), paired) with a circular-block-bootstrap percentile CI.

    `draws=True` also returns the bootstrap replicates (`draws`), for a decision that adds another error to
    the sampling distribution (the refit noise of `rules.above_noise`)."""
    x = np.asarray(x, dtype=np.float64)
    keep = np.isfinite(x) if ratio_to is None else np.isfinite(x) & np.isfinite(ratio_to)
    x = x[keep]
    y = None if ratio_to is None else np.asarray(ratio_to, dtype=np.float64)[keep]
    N = len(x)
    if N == 0:
        return dict(mean=float("nan"), ci=[float("nan"), float("nan")], block=0, n=0)
    b = block or block_length(x)
    rng = np.random.default_rng(seed)
    stat = (lambda i: x[i].mean()) if y is None else (lambda i: x[i].mean() / max(y[i].mean(), 1e-300))
    boots = np.array([stat(circular_block_indices(N, b, rng)) for _ in range(n_boot)])
    est = stat(np.arange(N))
    lo, hi = np.quantile(boots, [alpha / 2, 1 - alpha / 2])
    out = dict(mean=float(est), ci=[float(lo), float(hi)], block=int(b), n=int(N), se=float(boots.std()))
    if draws:
        out["draws"] = boots
    return out


def ljung_box(x: np.ndarray, lags=(10, 50)) -> dict:
    """Ljung-Box whiteness test of a residual (statsmodels); small p = not white."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    lags = [l for l in lags if l < len(x) // 2] or [max(1, len(x) // 4)]
    res = acorr_ljungbox(x - x.mean(), lags=lags, return_df=True)
    return {f"lag{int(l)}": dict(stat=float(res.loc[l, "lb_stat"]), p=float(res.loc[l, "lb_pvalue"])) for l in lags}


def cross_correlation(resid: np.ndarray, feature: np.ndarray, max_lag: int = 40) -> dict:
    """ccf at lags −max_lag..max_lag (feature leading at positive lag) and a 95% band for independence.

    The band accounts for autocorrelation with Bartlett's formula: var ≈ (1 + 2 Σ ρ_x(k) ρ_y(k)) / N.
    """
    r = np.asarray(resid, dtype=np.float64)
    f = np.asarray(feature, dtype=np.float64)
    ok = np.isfinite(r) & np.isfinite(f)
    r, f = r[ok], f[ok]
    N = len(r)
    if N < 4 * max_lag or np.std(r) == 0 or np.std(f) == 0:
        lags = np.arange(-max_lag, max_lag + 1)
        return dict(lags=lags.tolist(), ccf=[0.0] * len(lags), band=float("nan"), peak=0.0, peak_lag=0)
    pos = ccf(r, f, nlags=max_lag + 1, adjusted=False, fft=True)[: max_lag + 1]   # corr(r_t, f_{t-k})... see below
    neg = ccf(f, r, nlags=max_lag + 1, adjusted=False, fft=True)[: max_lag + 1]
    # statsmodels ccf(x, y)[k] = corr(x_{t+k}, y_t): pos[k] = corr(r_{t+k}, f_t) — the feature leads by k
    vals = np.concatenate([neg[:0:-1], pos])
    lags = np.arange(-max_lag, max_lag + 1)
    K = min(max_lag * 5, N // 4)
    ra = acf(r, nlags=K, fft=True)
    fa = acf(f, nlags=K, fft=True)
    var = (1.0 + 2.0 * np.sum(ra[1:] * fa[1:])) / N
    band = float(1.96 * np.sqrt(max(var, 1.0 / N)))
    i = int(np.argmax(np.abs(vals)))
    return dict(lags=lags.tolist(), ccf=vals.tolist(), band=band, peak=float(vals[i]), peak_lag=int(lags[i]))
