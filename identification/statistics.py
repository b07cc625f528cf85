"""Residual statistics: noise level, whiteness, cross-correlation with confidence bounds, binning,
step asymmetry. Pure numpy/scipy functions.

Sources (see docs/identification.md, statistics): Ljung-Box Q = N(N+2) sum r_k^2/(N-k)
~ chi2(M); the cross-correlation band of Ljung's ``resid`` (99 %, z = 2.58) with the variance
P = sum_k R_e(k) R_u(k), estimated with a Bartlett window so it stays valid for coloured
residuals and inputs; the joint statistic N R' P^-1 R ~ chi2(M+1) over lags 0..M.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

#: Per-lag confidence level of the correlation bands (Ljung's ``resid``: 99 %).
Z_99 = 2.5758
#: Default number of lags (Ljung's ``resid`` default).
MAX_LAG = 25


def noise_sigma(y: np.ndarray, floor: float = 0.0) -> float:
    """Measurement-noise standard deviation from the second differences (robust: MAD).

    For white noise e, var(e_k - 2 e_{k-1} + e_{k-2}) = 6 sigma^2; slow dynamics and the few
    steps in the signal barely move the median.
    """
    y = np.asarray(y, float)
    y = y[np.isfinite(y)]
    if len(y) < 10:
        return floor
    d2 = np.diff(y, 2)
    mad = np.median(np.abs(d2 - np.median(d2)))
    return max(1.4826 * mad / np.sqrt(6.0), floor)


def acf(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Biased autocovariance R(0..max_lag) of a mean-removed series (NaNs dropped as zeros)."""
    x = np.asarray(x, float)
    x = np.where(np.isfinite(x), x - np.nanmean(x), 0.0)
    n = len(x)
    return np.array([np.dot(x[k:], x[:n - k]) / n for k in range(max_lag + 1)])


def ccov(e: np.ndarray, u: np.ndarray, lags) -> np.ndarray:
    """Cross-covariance R_eu(tau) = (1/N) sum_t e(t) u(t - tau) for the given lags (may be negative)."""
    e = np.where(np.isfinite(e), e - np.nanmean(e), 0.0)
    u = np.where(np.isfinite(u), u - np.nanmean(u), 0.0)
    n = len(e)
    out = []
    for tau in lags:
        if tau >= 0:
            out.append(np.dot(e[tau:], u[:n - tau]) / n)
        else:
            out.append(np.dot(e[:n + tau], u[-tau:]) / n)
    return np.array(out)


@dataclass
class Whiteness:
    q: float
    dof: int
    p_value: float
    threshold: float
    acf: np.ndarray  # normalised r(1..M)
    band: float

    @property
    def white(self) -> bool:
        return self.q <= self.threshold


def ljung_box(x: np.ndarray, max_lag: int = MAX_LAG, alpha: float = 0.01) -> Whiteness:
    """Ljung-Box whiteness test of a residual series (NaNs removed)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    n = len(x)
    r = acf(x, max_lag)
    rho = r[1:] / r[0] if r[0] > 0 else np.zeros(max_lag)
    k = np.arange(1, max_lag + 1)
    q = float(n * (n + 2) * np.sum(rho ** 2 / (n - k)))
    return Whiteness(q, max_lag, float(stats.chi2.sf(q, max_lag)), float(stats.chi2.ppf(1 - alpha, max_lag)),
                     rho, Z_99 / np.sqrt(n))


@dataclass
class CrossCorrelation:
    lags: np.ndarray
    rho: np.ndarray        # normalised cross-correlation at each lag
    band: np.ndarray       # 99 % per-lag bound for rho (coloured-signal corrected)
    zeta: float            # joint statistic over the lags
    dof: int
    p_value: float

    @property
    def peak_ratio(self) -> float:
        """Largest |rho| / band over the lags (> 1: outside the 99 % band)."""
        return float(np.max(np.abs(self.rho) / self.band))

    @property
    def peak_lag(self) -> int:
        return int(self.lags[np.argmax(np.abs(self.rho) / self.band)])


def cross_correlation(e: np.ndarray, u: np.ndarray, max_lag: int = MAX_LAG, window: int | None = None
                      ) -> CrossCorrelation:
    """Cross-correlation of residual ``e`` with a signal ``u`` at lags 0..max_lag, with bounds.

    Per-lag band: +-2.58 sqrt(P/N) / sqrt(R_e(0) R_u(0)), P = sum_|k|<L w_k R_e(k) R_u(k)
    (Bartlett weights w_k = 1 - |k|/L). Joint test: zeta = N R' C^-1 R with
    C_ij = sum_k w_k R_e(k) R_u(k + i - j), chi2 with max_lag + 1 degrees of freedom.
    """
    ok = np.isfinite(e) & np.isfinite(u)
    e, u = np.asarray(e, float)[ok], np.asarray(u, float)[ok]
    n = len(e)
    window = window or int(min(max(n // 5, max_lag + 1), 300))
    re, ru = acf(e, window + max_lag), acf(u, window + max_lag)
    lags = np.arange(0, max_lag + 1)
    r = ccov(e, u, lags)
    norm = np.sqrt(re[0] * ru[0]) if re[0] > 0 and ru[0] > 0 else 1.0
    k = np.arange(-window + 1, window)
    w = 1.0 - np.abs(k) / window

    def c(m: int) -> float:
        return float(np.sum(w * re[np.abs(k)] * ru[np.abs(k + m)]))

    cvals = {m: c(m) for m in range(-max_lag, max_lag + 1)}
    cmat = np.array([[cvals[i - j] for j in lags] for i in lags])
    p0 = max(cvals[0], 1e-300)
    band = Z_99 * np.sqrt(p0 / n) / norm * np.ones(len(lags))
    try:
        ev_max = np.linalg.eigvalsh(cmat).max()
        reg = cmat + np.eye(len(lags)) * 1e-6 * max(ev_max, 1e-300)
        zeta = float(n * r @ np.linalg.solve(reg, r))
    except np.linalg.LinAlgError:
        zeta = float(n * np.sum(r ** 2) / p0)
    dof = len(lags)
    return CrossCorrelation(lags, r / norm, band, zeta, dof, float(stats.chi2.sf(zeta, dof)))


def effective_n(x: np.ndarray, max_lag: int = 300) -> float:
    """Effective sample size n / (1 + 2 sum rho_k) of an autocorrelated series (rho summed while > 0)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    n = len(x)
    if n < 4:
        return float(n)
    r = acf(x, min(max_lag, n - 2))
    if r[0] <= 0:
        return float(n)
    rho = r[1:] / r[0]
    cut = np.argmax(rho <= 0) if np.any(rho <= 0) else len(rho)
    return float(max(1.0, n / (1.0 + 2.0 * np.sum(rho[:cut]))))


@dataclass
class Binned:
    variable: str
    centers: np.ndarray
    mean: np.ndarray
    se: np.ndarray
    count: np.ndarray
    eta2: float          # share of the residual variance explained by the bin means
    f_stat: float        # between-bin F with effective sample size
    p_value: float


def binned(residual: np.ndarray, z: np.ndarray, variable: str, bins: int = 8) -> Binned:
    """Residual mean +- standard error in quantile bins of an operating variable ``z``.

    Standard errors and the F test use the effective sample size of the residual
    (autocorrelation), so a smooth residual is not over-counted.
    """
    ok = np.isfinite(residual) & np.isfinite(z)
    r, z = residual[ok], z[ok]
    n = len(r)
    edges = np.unique(np.quantile(z, np.linspace(0, 1, bins + 1)))
    if len(edges) < 3:
        return Binned(variable, np.array([np.mean(z)]), np.array([np.mean(r)]), np.array([np.nan]),
                      np.array([n]), 0.0, 0.0, 1.0)
    idx = np.clip(np.searchsorted(edges, z, side="right") - 1, 0, len(edges) - 2)
    k = len(edges) - 1
    centers, means, ses, counts = [], [], [], []
    shrink = effective_n(r) / n
    for b in range(k):
        sel = idx == b
        if not sel.any():
            continue
        centers.append(float(np.mean(z[sel])))
        means.append(float(np.mean(r[sel])))
        counts.append(int(sel.sum()))
        ses.append(float(np.std(r[sel]) / np.sqrt(max(sel.sum() * shrink, 1.0))))
    means_a, counts_a = np.array(means), np.array(counts)
    grand = np.mean(r)
    between = float(np.sum(counts_a * (means_a - grand) ** 2))
    total = float(np.sum((r - grand) ** 2))
    within = max(total - between, 1e-300)
    kk = len(means_a)
    n_eff = max(effective_n(r), kk + 1.0)
    f_stat = (between / max(kk - 1, 1)) / (within / max(n - kk, 1)) * (n_eff / n)
    p = float(stats.f.sf(f_stat, max(kk - 1, 1), max(n_eff - kk, 1)))
    return Binned(variable, np.array(centers), means_a, np.array(ses), counts_a,
                  between / total if total > 0 else 0.0, f_stat, p)


@dataclass
class StepAsymmetry:
    signal: str
    n_up: int
    n_down: int
    mean_up: float     # mean residual per unit step in the window after up-steps
    mean_down: float   # same after down-steps
    t_stat: float
    p_value: float


def step_asymmetry(residual: np.ndarray, u: np.ndarray, signal: str, min_step: float, window: int = 150
                   ) -> StepAsymmetry:
    """Mean residual in the window after each step of ``u``, normalised by the step, up against down.

    A model whose dynamics are right up to a gain gives the same normalised value for up- and
    down-steps; a direction-dependent time constant (motor heating faster than cooling) gives
    values of opposite sign. Welch t-test between the two groups.
    """
    du = np.diff(u, prepend=u[0])
    steps = np.flatnonzero(np.abs(du) >= min_step)
    ups, downs = [], []
    for i, s in enumerate(steps):
        end = min(s + window, steps[i + 1] if i + 1 < len(steps) else len(u))
        seg = residual[s:end]
        seg = seg[np.isfinite(seg)]
        if len(seg) < 10:
            continue
        val = float(np.mean(seg) / abs(du[s]))
        (ups if du[s] > 0 else downs).append(val)
    if len(ups) >= 2 and len(downs) >= 2:
        t, p = stats.ttest_ind(ups, downs, equal_var=False)
        t, p = float(t), float(p)
    else:
        t, p = 0.0, 1.0
    return StepAsymmetry(signal, len(ups), len(downs), float(np.mean(ups)) if ups else np.nan,
                         float(np.mean(downs)) if downs else np.nan, t, p)


def rms(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")


def max_abs(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.max(np.abs(x))) if len(x) else float("nan")


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> float:
    """NRMSE fit in %: 100 (1 - ||y - y_hat|| / ||y - mean(y)||)."""
    ok = np.isfinite(y) & np.isfinite(y_hat)
    if not ok.any():
        return float("nan")
    den = np.linalg.norm(y[ok] - np.mean(y[ok]))
    return float(100.0 * (1.0 - np.linalg.norm(y[ok] - y_hat[ok]) / den)) if den > 0 else float("nan")
