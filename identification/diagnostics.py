"""Diagnostics of a fitted model's residuals: error levels, whiteness, cross-correlations against
every logged signal and derived regressor, residual binned by operating variables, step
asymmetry, chiller cycling.

Free-run (simulation) errors are used for levels, cross-correlations and binning; the EKF
one-step innovations for the whiteness test (docs/identification.md, statistics). The structure
statistics use the training rows only; levels are given for training and held-out rows.
"""

from __future__ import annotations

import numpy as np

from hvac_mpc.models.box import INPUTS

from . import statistics as st
from .fitting import Fit, Fitter
from .log_data import MODEL_OUTPUTS

#: Operating variables the residual is binned by.
BIN_VARIABLES = ("heater_temp_c", "mass_flow_kgs", "valve_a_pct", "network_resistance_kg_m7", "blower_power_w",
                 "heater_cmd_w", "hvac_inlet_temp_c", "hvac_inlet_rh_pct", "cooler_drive_c", "time_s")
#: Minimum step sizes for the step-asymmetry test.
STEP_SIGNALS = {"blower_power_w": 40.0, "heater_cmd_w": 40.0, "valve_a_pct": 15.0}


def _decaying_marker(events: np.ndarray, signs: np.ndarray, n: int, tau: float) -> np.ndarray:
    out = np.zeros(n)
    k = np.arange(n)
    for e, s in zip(events, signs):
        sel = k >= e
        out[sel] = s * np.exp(-(k[sel] - e) / tau)
    return out


def regressors(fitter: Fitter, fit: Fit) -> dict[str, np.ndarray]:
    """Logged signals and derived regressors along the fitted model's free run."""
    log = fitter.log
    out: dict[str, np.ndarray] = {}
    for name, col in log.signals.items():
        if name in MODEL_OUTPUTS:
            continue
        out[name] = col
    sim = fitter.simulator(fit.effects, fit.terms)
    out.update(sim.internals(fit.p, fit.states))
    n = log.n
    pb = log.u[:, INPUTS.index("blower_power_w")]
    du = np.diff(pb, prepend=pb[0])
    steps = np.flatnonzero(np.abs(du) >= STEP_SIGNALS["blower_power_w"])
    out["blower_step_sign"] = _decaying_marker(steps, np.sign(du[steps]), n, 200.0 / log.dt_s)
    a = log.u[:, INPUTS.index("valve_a_pct")]
    heat = log.u[:, INPUTS.index("heater_cmd_w")] > 20.0
    sat = (a >= 95.0) & heat
    leaves = np.flatnonzero(sat[:-1] & ~sat[1:]) + 1
    out["trap_release"] = _decaying_marker(leaves, np.ones(len(leaves)), n, 20.0 / log.dt_s)
    for j, o in enumerate(fitter.outputs):
        out[f"d_{o}"] = np.gradient(fit.y[:, j]) / log.dt_s
    out["time_s"] = log.time_s
    return out


def metrics(fitter: Fitter, fit: Fit) -> dict[str, dict[str, dict[str, float]]]:
    """RMS, max |error|, mean error and NRMSE fit per output for training and held-out rows."""
    res = {}
    for j, o in enumerate(fitter.outputs):
        e = fitter.y_meas[:, j] - fit.y[:, j]
        res[o] = {}
        for part, mask in (("train", fitter.log.train), ("holdout", fitter.log.holdout)):
            ej = e[mask]
            res[o][part] = {"rms": st.rms(ej), "max_abs": st.max_abs(ej), "mean": float(np.nanmean(ej)),
                            "fit_pct": st.fit_percent(fitter.y_meas[mask, j], fit.y[mask, j])}
    return res


def structure_ratio(fitter: Fitter, fit: Fit, part: str = "holdout") -> dict[str, float]:
    """Per output: sum of squared noise-scaled errors over its count (about 1 at noise level)."""
    mask = fitter.log.holdout if part == "holdout" else fitter.log.train
    r2 = fitter.scaled(fit.y) ** 2
    ok = np.isfinite(fitter.y_meas)
    return {o: float(r2[mask, j].sum() / max(ok[mask, j].sum(), 1)) for j, o in enumerate(fitter.outputs)}


def innovations_nll(fitter: Fitter, fit: Fit) -> tuple[np.ndarray, np.ndarray, float]:
    """EKF innovations, variances and the training negative log-likelihood (x2, constants dropped)."""
    sim = fitter.simulator(fit.effects, fit.terms)
    nu, s = sim.innovations(fit.p, fitter.y_meas, fitter.sigma ** 2, fit.post)
    train = fitter.log.train
    ok = np.isfinite(nu) & train[:, None]
    nll = float(np.sum(np.where(ok, nu ** 2 / s + np.log(s), 0.0)))
    return nu, s, nll


def training_nll(fitter: Fitter, fit: Fit) -> float:
    """The training negative log-likelihood of :func:`innovations_nll` (the same value), from a filter run over the
    training rows alone (the log's first part)."""
    sim = fitter.simulator(fit.effects, fit.terms)
    nu, s = sim.innovations(fit.p, fitter.y_meas, fitter.sigma ** 2, fit.post, fitter.train_rows)
    return _nll_on(nu, s, fitter.log.train)


def holdout_nll(fitter: Fitter, fit: Fit) -> float:
    """The same negative log-likelihood over the held-out rows, from a filter run over the whole log."""
    sim = fitter.simulator(fit.effects, fit.terms)
    nu, s = sim.innovations(fit.p, fitter.y_meas, fitter.sigma ** 2, fit.post)
    return _nll_on(nu, s, fitter.log.holdout)


def _nll_on(nu: np.ndarray, s: np.ndarray, rows: np.ndarray) -> float:
    """EKF negative log-likelihood (x2, constants dropped) of the innovations ``nu`` (variances ``s``) on ``rows``."""
    ok = np.isfinite(nu) & rows[:, None]
    return float(np.sum(np.where(ok, nu ** 2 / s + np.log(s), 0.0)))


def holdout_tests(fitter: Fitter, fit: Fit, nu: np.ndarray, s: np.ndarray) -> dict:
    """Residual tests on the held-out rows, per output: Ljung-Box whiteness of the EKF innovations
    and the cross-correlation of the free-run residual with each command and the inlet temperature
    (lags 0..25, 99 % coloured-signal band, joint chi2 test)."""
    log = fitter.log
    ho = log.holdout
    signals = {name: log.u[:, i] for i, name in enumerate(INPUTS)}
    signals["hvac_inlet_temp_c"] = log.inlet_temp_c
    out = {}
    for j, o in enumerate(fitter.outputs):
        e = (fitter.y_meas[:, j] - fit.y[:, j])[ho]
        if np.sum(np.isfinite(e)) < 100 or np.nanstd(e) == 0:
            continue
        wt = st.ljung_box((nu[:, j] / np.sqrt(s[:, j]))[ho])
        rec = {"ljung_box_q": wt.q, "threshold": wt.threshold, "p_value": wt.p_value, "white": wt.white,
               "acf_band": wt.band, "ccf": {}}
        for name, z in signals.items():
            if np.nanstd(z[ho]) == 0:
                continue
            cc = st.cross_correlation(e, z[ho])
            rec["ccf"][name] = {"peak_ratio": cc.peak_ratio, "peak_lag": cc.peak_lag, "zeta": cc.zeta, "dof": cc.dof,
                                "p_value": cc.p_value, "independent": bool(cc.p_value >= 0.01)}
        out[o] = rec
    return out


def diagnose(fitter: Fitter, fit: Fit, top: int = 8) -> dict:
    """All diagnostics of one fit (see the module docstring); plain data for the report."""
    log = fitter.log
    train = log.train
    reg = regressors(fitter, fit)
    nu, s, nll = innovations_nll(fitter, fit)
    out: dict = {"metrics": metrics(fitter, fit), "structure_holdout": structure_ratio(fitter, fit, "holdout"),
                 "structure_train": structure_ratio(fitter, fit, "train"), "ekf_nll_train": nll,
                 "whiteness": {}, "ccf": {}, "binned": {}, "steps": {}}
    out["holdout_tests"] = holdout_tests(fitter, fit, nu, s)
    for j, o in enumerate(fitter.outputs):
        e = (fitter.y_meas[:, j] - fit.y[:, j])[train]
        if np.nanstd(e) == 0 or np.sum(np.isfinite(e)) < 100:
            continue
        innov = (nu[:, j] / np.sqrt(s[:, j]))[train]
        wt = st.ljung_box(innov)
        out["whiteness"][o] = {"q": wt.q, "dof": wt.dof, "p_value": wt.p_value, "threshold": wt.threshold,
                               "white": wt.white, "acf": wt.acf.tolist(), "band": wt.band}
        ccfs = []
        for name, z in reg.items():
            if name == f"d_{o}" or np.nanstd(z[train]) == 0:
                continue
            cc = st.cross_correlation(e, z[train])
            ccfs.append({"signal": name, "peak_ratio": cc.peak_ratio, "peak_lag": cc.peak_lag, "zeta": cc.zeta,
                         "dof": cc.dof, "p_value": cc.p_value, "rho": cc.rho.tolist(), "band": cc.band.tolist()})
        # the model output's own derivative (lag / delay signature) is kept, named explicitly
        dz = reg.get(f"d_{o}")
        if dz is not None and np.nanstd(dz[train]) > 0:
            cc = st.cross_correlation(e, dz[train])
            ccfs.append({"signal": f"d_{o}", "peak_ratio": cc.peak_ratio, "peak_lag": cc.peak_lag, "zeta": cc.zeta,
                         "dof": cc.dof, "p_value": cc.p_value, "rho": cc.rho.tolist(), "band": cc.band.tolist()})
        ccfs.sort(key=lambda c: -c["peak_ratio"])
        out["ccf"][o] = ccfs[:top]
        bins = []
        for name in BIN_VARIABLES:
            z = reg.get(name)
            if z is None or np.nanstd(z[train]) == 0:
                continue
            b = st.binned(e, z[train], name)
            bins.append({"variable": name, "eta2": b.eta2, "f_stat": b.f_stat, "p_value": b.p_value,
                         "centers": b.centers.tolist(), "mean": b.mean.tolist(), "se": b.se.tolist()})
        bins.sort(key=lambda b: -b["eta2"])
        out["binned"][o] = bins
        steps = []
        for name, min_step in STEP_SIGNALS.items():
            u = log.u[:, INPUTS.index(name)][train]
            sa = st.step_asymmetry(e, u, name, min_step, window=max(10, int(round(150.0 / log.dt_s))))
            if sa.n_up + sa.n_down == 0:
                continue
            steps.append({"signal": name, "n_up": sa.n_up, "n_down": sa.n_down, "mean_up": sa.mean_up,
                          "mean_down": sa.mean_down, "t_stat": sa.t_stat, "p_value": sa.p_value})
        out["steps"][o] = steps
    out["chiller"] = chiller_cycling(fitter)
    return out


def _cycling_rows(setpoint_c: np.ndarray, dev: np.ndarray) -> np.ndarray:
    """Rows where the water cycles about its set point: after the set point last changed, from the first
    crossing of the set point on (the ramp towards a new set point is not the band)."""
    rows = np.zeros(len(dev), bool)
    starts = np.concatenate([[0], np.flatnonzero(np.diff(setpoint_c) != 0) + 1, [len(dev)]])
    for a, b in zip(starts[:-1], starts[1:]):
        cross = np.flatnonzero(np.diff(np.sign(dev[a:b])) != 0)
        if len(cross):
            rows[a + cross[0] + 1:b] = True
    return rows


def chiller_cycling(fitter: Fitter) -> dict | None:
    """Chiller two-point cycling seen in the logged water temperature (thesis sec. 2.2, 4.2).

    Returns the observed water band around the set point, or ``None`` if water is not logged.
    The thesis model's chiller holds the set point; with the water logged, the identification
    uses the logged value as a measured disturbance, so the cycling does not enter the residual.
    """
    log = fitter.log
    if log.water_temp_c is None:
        return None
    dev = log.water_temp_c - log.chiller_setpoint_c
    rows = (log.train | log.holdout) & _cycling_rows(log.chiller_setpoint_c, dev)
    if rows.sum() < 60:
        return None
    dev = dev[rows]
    lo, hi = np.percentile(dev, [1, 99])
    half = 0.5 * float(hi - lo)
    crossings = int(np.sum(np.diff(np.sign(dev - np.median(dev))) != 0))
    return {"band_low_c": float(lo), "band_high_c": float(hi), "half_band_c": half,
            "cycling": bool(half > 0.3 and crossings >= 2), "crossings": crossings}
