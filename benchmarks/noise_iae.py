"""A noise-aware IAE from a logged, noisy reading, with a band from the reading's own noise.

The bench scores the plant's noise-free signals; a log holds readings y_m = y + n with white sensor
noise n. Scored on y_m, an IAE grows by up to N sigma sqrt(2/pi) dt, which for the volume flow
(sigma 4e-4 m3/s against errors of 1e-4 m3/s) is most of the figure. This module estimates the IAE
of y from the log alone (docs/real-box.md, 'Reports from logs'):

1. **Clean the reading.** y_hat = fit + A_W(y_m - fit): ``fit`` is a least-squares regression of
   the reading on the applied commands, each lagged 1..``lags`` samples (plus a constant), over
   the scored samples; A_W is a centred moving average over W samples (zero phase: no lag; its
   time resolution is W samples). The volume flow follows the blower and the valves within a few
   samples, so the commands explain its fast part, including the part a feedback controller puts
   there by reacting to the sensor noise (a smoothing alone loses that part, and the baseline's
   flow error is mostly that). The supply temperature follows through heat capacities and the
   thermocouple's lag, so it uses no commands and a short average. The lagged commands are
   independent of the noise of the same sample (a command acts from the next sample on).
2. **Noise.** sigma from the residual y_m - fit: 1.4826 MAD of its second differences / sqrt(6)
   (white noise: the second difference has variance 6 sigma^2; the median ignores steps).
3. **Correction and band: parametric bootstrap over the residual noise.** Replicates
   y_hat + sigma* n* (n* white Gaussian; sigma* drawn around sigma with the MAD estimate's spread,
   so the band carries the noise estimate's own uncertainty) go through step 1 again; their IAE
   minus the IAE of y_hat is the estimator's error in a world whose truth is y_hat. Its mean is
   the bias (the noise left after step 1 raises an IAE, the average lowers it), subtracted from the
   estimate; its 2.5 and 97.5 percentiles give the 95 % band. A ratio's band is the same over
   paired replicates of the two runs (basic bootstrap interval).
4. **Resolution.** The same replicates give the IAE that the cleaned noise alone reaches (its 97.5
   percentile, the noise floor). A cleaned IAE below it is not resolved: the error may be zero, so
   the band starts at 0 (the bias correction cannot be trusted where the error is far below the
   noise: the bootstrap's truth, y_hat, still carries some noise). A ratio whose baseline figure is
   not resolved gets a one-sided band (its MPC figure resolved) or none.

What it cannot see: a noise that is not white, or a true error faster than W samples that the
commands do not explain (the supply temperature's sharp transients lose a few percent to A_W).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from hvac_mpc.contract import INPUTS

#: Confidence of the stated bands (two-sided percentiles of the bootstrap).
BAND_PERCENTILES = (2.5, 97.5)
#: Bootstrap replicates per run (deterministic: the generator is seeded, see :func:`estimate_iae`).
REPLICATES = 200
#: Relative efficiency of a MAD scale estimate against the standard deviation for Gaussian data
#: (0.37): the noise estimate counts as one from 0.37 (N - 2) degrees of freedom.
MAD_EFFICIENCY = 0.37


@dataclass(frozen=True)
class Cleaning:
    """How a reading is cleaned: commands lagged 1..``lags`` samples (0: none) and the window (samples)."""

    lags: int
    window: int
    #: command columns left out of the regression (they do not act on this reading)
    skip: tuple[int, ...] = ()


#: Per reading: the cleaning (see the module docstring for why these; the heater does not act on the flow).
CLEANING = {"supply_temp_c": Cleaning(lags=0, window=3),
            "volume_flow_m3s": Cleaning(lags=2, window=9, skip=(INPUTS.index("heater_cmd_w"),))}


def second_difference_sigma(values: np.ndarray) -> float:
    """White-noise standard deviation of a sampled signal: 1.4826 MAD of its second differences / sqrt(6)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size < 4:
        return math.nan
    d2 = np.diff(v, 2)
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average over ``window`` samples (odd), the ends held (zero phase)."""
    if window <= 1:
        return np.array(x, float)
    h = window // 2
    padded = np.concatenate([np.full(h, x[0]), x, np.full(h, x[-1])])
    c = np.cumsum(np.concatenate([[0.0], padded]))
    return (c[window:] - c[:-window]) / window


def lagged_design(commands: np.ndarray, lags: int) -> np.ndarray:
    """Regressors: a constant and each command column lagged 1..``lags`` samples (the first value held)."""
    n = commands.shape[0]
    cols = [np.ones(n)]
    for i in range(commands.shape[1] if lags else 0):
        for j in range(1, lags + 1):
            c = np.empty(n)
            c[:j] = commands[0, i]
            c[j:] = commands[: n - j, i]
            cols.append(c)
    return np.column_stack(cols)


def clean(reading: np.ndarray, design: np.ndarray, window: int, start: int) -> tuple[np.ndarray, np.ndarray]:
    """The cleaned reading (fit on the commands + moving average of the rest) and the residual."""
    beta, *_ = np.linalg.lstsq(design[start:], reading[start:], rcond=None)
    fit = design @ beta
    return fit + moving_average(reading - fit, window), reading - fit


def _design(commands: np.ndarray | None, cleaning: Cleaning, start: int, n: int) -> np.ndarray:
    """The regressors of a run; the commands that move over the scored samples, while the regression
    keeps at least 4 samples per coefficient (else fewer lags, else none)."""
    if commands is None or cleaning.lags == 0:
        return np.ones((n, 1))
    u = np.asarray(commands, float)[:n]
    moving = u[:, [i for i in range(u.shape[1]) if i not in cleaning.skip and np.ptp(u[start:, i]) > 0]]
    for lags in range(cleaning.lags, 0, -1):
        if 1 + moving.shape[1] * lags <= (n - start) / 4:
            return lagged_design(moving, lags)
    return np.ones((n, 1))


def estimate_iae(reading, reference, dt_s: float, start: int, commands=None, cleaning: Cleaning = Cleaning(0, 3),
                 replicates: int = REPLICATES, seed: int = 0) -> dict:
    """Noise-aware IAE of ``reading`` against ``reference`` from sample ``start`` on (unit of the reading x s).

    ``commands``: (n, m) applied commands (for ``cleaning.lags`` > 0). Returns ``estimate`` (bias
    corrected), ``band`` (95 %), ``raw`` (the IAE of the reading as it is), ``cleaned`` (of the cleaned
    reading, before the bias correction), ``sigma`` (the noise estimate), ``bias`` and ``errors``
    (the bootstrap's estimator errors, for ratio bands)."""
    y = np.asarray(reading, float)
    r = np.asarray(reference, float)
    n = y.size
    design = _design(commands, cleaning, start, n)
    y_hat, resid = clean(y, design, cleaning.window, start)
    sigma = second_difference_sigma(resid[start:])
    cleaned = float(np.sum(np.abs(y_hat - r)[start:]) * dt_s)
    rng = np.random.default_rng(seed)
    dof = max(MAD_EFFICIENCY * (n - start - 2), 1.0)
    errors, floor = np.empty(replicates), np.empty(replicates)
    for i in range(replicates):
        s = sigma * math.sqrt(rng.chisquare(dof) / dof)
        noise = s * rng.standard_normal(n)
        y_star, _ = clean(y_hat + noise, design, cleaning.window, start)
        errors[i] = np.sum(np.abs(y_star - r)[start:]) * dt_s - cleaned
        floor[i] = np.sum(np.abs(clean(noise, design, cleaning.window, start)[0])[start:]) * dt_s
    bias = float(np.mean(errors))
    lo, hi = np.percentile(errors, BAND_PERCENTILES)
    noise_floor = float(np.percentile(floor, BAND_PERCENTILES[1]))
    resolved = bool(cleaned > noise_floor)
    return {"estimate": max(cleaned - bias, 0.0),
            "band": (max(cleaned - hi, 0.0) if resolved else 0.0, max(cleaned - lo, 0.0)),
            "raw": float(np.sum(np.abs(y - r)[start:]) * dt_s), "cleaned": cleaned, "sigma": sigma, "bias": bias,
            "noise_floor": noise_floor, "resolved": resolved,
            "regressors": int(design.shape[1]), "window": int(cleaning.window), "errors": errors}


def ratio_band(mpc: Mapping, baseline: Mapping) -> tuple[float, tuple[float, float]] | None:
    """MPC / baseline of two :func:`estimate_iae` results and its 95 % band (paired replicates, basic
    bootstrap interval). An MPC figure the log does not resolve (``resolved`` False: its cleaned IAE
    within what the cleaned noise alone gives) may be 0, so the band starts at 0. A baseline figure
    it does not resolve may be 0 too: with a resolved MPC figure the band is one-sided, from the
    MPC's lowest over the baseline's highest IAE to infinity. None when neither is resolved, or
    the baseline's estimate or a replicate's is not positive."""
    em, eb = mpc["cleaned"], baseline["cleaned"]
    bm, bb = mpc["bias"], baseline["bias"]
    if not baseline["resolved"]:
        if not mpc["resolved"] or baseline["band"][1] <= 0:
            return None
        rho = (em - bm) / (eb - bb) if eb - bb > 0 else math.inf
        return max(rho, 0.0), (mpc["band"][0] / baseline["band"][1], math.inf)
    if eb - bb <= 0 or eb <= 0:
        return None
    rho = (em - bm) / (eb - bb)
    den = eb + baseline["errors"] - bb
    if np.any(den <= 0):
        return None
    delta = (em + mpc["errors"] - bm) / den - em / eb
    lo, hi = np.percentile(delta, BAND_PERCENTILES)
    if mpc["resolved"]:
        return max(rho, 0.0), (max(rho - hi, 0.0), max(rho - lo, 0.0))
    # unresolved: the bias correction may take the MPC's estimate below 0 and the paired band with it; the
    # band's top is then the MPC's highest IAE over the baseline's lowest, and where that is 0 too the log
    # bounds nothing (the band is [0, inf), not a claim that the ratio is 0)
    top = mpc["band"][1] / baseline["band"][0] if baseline["band"][0] > 0 else math.inf
    top = max(rho - lo, top)
    return max(rho, 0.0), (0.0, top if top > 0 else math.inf)


def sum_band(values, dt_s: float, sigma: float, scale: float = 1.0) -> tuple[float, tuple[float, float]]:
    """A sum of a noisy reading (e.g. energy; no absolute value, so noise adds no bias) and its 95 %
    band: +-1.96 sigma sqrt(N) dt (white noise), both times ``scale`` (e.g. 1/3600 for Wh)."""
    v = np.asarray(values, float)
    total = float(np.sum(v) * dt_s * scale)
    half = 1.96 * (sigma if math.isfinite(sigma) else 0.0) * math.sqrt(v.size) * dt_s * scale
    return total, (total - half, total + half)
