"""The noise-aware IAE of hvac_mpc.benchmarks.noise_iae on synthetic signals whose true error is known:
its band holds the true IAE where the raw reading's IAE is off, the commands recover the error a
feedback loop makes out of sensor noise, and pure noise is reported as not resolved."""

import math

import numpy as np
import pytest

from hvac_mpc.benchmarks.noise_iae import (Cleaning, estimate_iae, moving_average, ratio_band,
                                           second_difference_sigma, sum_band)


def decaying_steps(n: int, every: int, amplitude: float, tau: float) -> np.ndarray:
    """An error that jumps to ``amplitude`` every ``every`` samples and decays with ``tau`` samples."""
    k = np.arange(n) % every
    return amplitude * np.exp(-k / tau) * np.where((np.arange(n) // every) % 2, 1.0, -1.0)


def test_moving_average_is_zero_phase():
    ramp = np.arange(50.0)
    assert np.allclose(moving_average(ramp, 9)[4:-4], ramp[4:-4])  # no lag on a ramp
    spike = np.zeros(21)
    spike[10] = 9.0
    assert np.allclose(moving_average(spike, 9)[6:15], 1.0) and moving_average(spike, 9)[5] == 0.0


def test_band_holds_the_true_iae_that_the_raw_reading_overstates():
    rng = np.random.default_rng(3)
    n, sigma = 400, 0.05
    error = decaying_steps(n, 50, 0.3, 20.0)
    reference = np.full(n, 20.0)
    reading = reference + error + sigma * rng.standard_normal(n)
    true = float(np.sum(np.abs(error)))
    est = estimate_iae(reading, reference, 1.0, 0, cleaning=Cleaning(lags=0, window=3))
    assert est["sigma"] == pytest.approx(sigma, rel=0.2)
    assert est["band"][0] <= true <= est["band"][1] < est["raw"]
    assert est["band"][1] - est["band"][0] < 0.15 * true
    assert abs(est["estimate"] - true) < 0.5 * abs(est["raw"] - true)
    assert est["resolved"]


def test_an_error_long_below_the_noise_is_only_partly_corrected():
    """The documented limit (docs/real-box.md): an error under the noise for half of each block keeps
    part of the noise's excess in the estimate, and the band can miss the true IAE."""
    rng = np.random.default_rng(3)
    error = decaying_steps(400, 50, 0.4, 8.0)
    reference = np.full(400, 20.0)
    est = estimate_iae(reference + error + 0.05 * rng.standard_normal(400), reference, 1.0, 0,
                       cleaning=Cleaning(lags=0, window=3))
    true = float(np.sum(np.abs(error)))
    assert true < est["estimate"] < est["raw"]
    assert est["estimate"] - true < 0.5 * (est["raw"] - true)


def _feedback_loop(rng, n: int, sigma: float, gain_ki: float):
    """A fast first-order plant (pole 0.3) under integral control of its noisy reading: the
    controller turns the sensor noise into true error. Returns reading, reference, commands, error."""
    y, u = 0.0, 0.0
    ref = np.where(np.arange(n) % 100 < 50, 1.0, 1.2)
    ys, us = np.empty(n), np.empty(n)
    for k in range(n):
        ys[k] = y
        ym = y + sigma * rng.standard_normal()
        u += gain_ki * (ref[k] - ym)
        us[k] = u
        y = 0.3 * y + 0.7 * u
    noise = sigma * rng.standard_normal(n)
    return ys + noise, ref, us[:, None], ys - ref


def test_commands_recover_the_error_feedback_makes_of_the_noise():
    rng = np.random.default_rng(5)
    reading, ref, commands, error = _feedback_loop(rng, 600, 0.02, 0.6)
    true = float(np.sum(np.abs(error)))
    aided = estimate_iae(reading, ref, 1.0, 0, commands, Cleaning(lags=2, window=9))
    smoothed = estimate_iae(reading, ref, 1.0, 0, None, Cleaning(lags=0, window=9))
    assert aided["band"][0] <= true <= aided["band"][1], (aided["band"], true)
    assert abs(aided["estimate"] - true) < 0.5 * abs(smoothed["estimate"] - true)
    assert smoothed["estimate"] < 0.9 * true  # a smoothing alone loses the jitter


def test_pure_noise_is_not_resolved_and_opens_its_ratio_band():
    rng = np.random.default_rng(1)
    ref = np.full(300, 0.03)
    noise_only = estimate_iae(ref + 4e-4 * rng.standard_normal(300), ref, 1.0, 0, cleaning=Cleaning(0, 9))
    assert not noise_only["resolved"] and noise_only["band"][0] == 0.0
    assert noise_only["raw"] > 0.25 * 300 * 4e-4  # what a report from the raw reading would score
    signal = estimate_iae(ref + 2e-3 + 4e-4 * rng.standard_normal(300), ref, 1.0, 0, cleaning=Cleaning(0, 9))
    assert signal["resolved"] and signal["band"][0] <= 300 * 2e-3 <= signal["band"][1]
    assert ratio_band(noise_only, noise_only) is None
    _, (lo, hi) = ratio_band(signal, noise_only)  # the baseline may be 0: one-sided
    assert hi == math.inf and 1.0 < lo < signal["band"][0] / (0.5 * noise_only["noise_floor"])
    rho, (lo, hi) = ratio_band(noise_only, signal)
    assert lo == 0.0 and rho < hi < 0.2


def test_sum_band_and_sigma_estimate():
    rng = np.random.default_rng(2)
    power = np.concatenate([np.full(200, 100.0), np.full(200, 300.0)])
    assert sum_band(power, 1.0, 0.0, 1 / 3600) == (pytest.approx(8e4 / 3600), (pytest.approx(8e4 / 3600),
                                                                                pytest.approx(8e4 / 3600)))
    noisy = power + 5.0 * rng.standard_normal(power.size)
    sigma = second_difference_sigma(noisy)
    assert sigma == pytest.approx(5.0, rel=0.15)
    total, (lo, hi) = sum_band(noisy, 1.0, sigma, 1 / 3600)
    assert lo <= 8e4 / 3600 <= hi and hi - lo == pytest.approx(2 * 1.96 * sigma * math.sqrt(400) / 3600)
