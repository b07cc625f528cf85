"""Figures of merit of one closed-loop run, as pure functions of sampled signals.

Conventions (all signals sampled every ``dt_s`` seconds, sample k holding for one sample):

- integrals are rectangle sums, sum_k |e_k| dt_s (the sample-and-hold view of a 1 s controller;
  BOPTEST integrates its KPIs with the trapezoid rule over continuous signals);
- a *step* is a sample where the reference differs from the previous one; its response runs until
  the next step or the end of the evaluated window;
- *time to band*: from the step to the first sample after which the output stays inside the band
  until the response ends (``None`` when it is outside at the end);
- *actuator travel*: sum of absolute moves of each actuator divided by its range, the discrete
  form of BOPTEST's ``atvl`` D = integral of |du/dt| dt (issue #639 of ibpsa/project1-boptest);
- *time ratio*: mean step wall time / sample time, BOPTEST's ``time_rat`` (kpi_calculator.py).
"""

from __future__ import annotations

import math
from typing import Iterable, Mapping, Sequence

import numpy as np

#: Heater counted as "on" above this electric power (W). ASSUMPTION: a threshold above numerical zero.
HEATER_ON_W = 1.0
#: Minimum volume flow with the heater on (m3/s). ASSUMPTION, the same value as the controller
#: daemon's heater interlock (``daemon/config.py`` ``SafetyConfig.min_flow_m3s``).
HEATER_MIN_FLOW_M3S = 0.004
#: Band around the temperature reference for the time to band (degC), issue 4.
TEMP_BAND_C = 0.5
#: Band around the volume-flow reference for the time to band (fraction of the new reference), issue 4.
FLOW_BAND_FRACTION = 0.05


def _arr(x) -> np.ndarray:
    return np.asarray(x, dtype=float).ravel()


def _check_dt(dt_s: float) -> None:
    if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s: expected a finite sample time > 0 s, got {dt_s!r}")


def iae(output, reference, dt_s: float) -> float:
    """Integral of absolute error, sum |y - r| dt (unit of y times s). Samples with a NaN reference are skipped."""
    _check_dt(dt_s)
    y, r = _arr(output), _arr(reference)
    if y.shape != r.shape:
        raise ValueError(f"output and reference must have the same length, got {y.size} and {r.size}")
    ok = np.isfinite(r)
    return float(np.sum(np.abs(y[ok] - r[ok])) * dt_s)


def rms_error(outputs, references) -> float | None:
    """Root mean square of (y - r) over all samples and columns; rows with any NaN reference are skipped.

    ``outputs`` and ``references`` are (n,) or (n, m) arrays. Returns ``None`` when nothing is left.
    """
    y = np.asarray(outputs, float)
    r = np.asarray(references, float)
    if y.shape != r.shape:
        raise ValueError(f"outputs and references must have the same shape, got {y.shape} and {r.shape}")
    if y.ndim == 1:
        y, r = y[:, None], r[:, None]
    ok = np.all(np.isfinite(r), axis=1)
    if not ok.any():
        return None
    return float(np.sqrt(np.mean((y[ok] - r[ok]) ** 2)))


def step_indices(reference, tol: float = 1e-9) -> list[int]:
    """Indices k >= 1 where the reference differs from sample k-1 by more than ``tol``."""
    r = _arr(reference)
    if r.size < 2:
        return []
    changed = np.abs(np.diff(r)) > tol
    return [int(k) + 1 for k in np.flatnonzero(changed)]


def time_in_band_s(output, reference_value: float, band: float, dt_s: float) -> float | None:
    """Time from the first sample until the output enters ``reference_value +- band`` for good.

    0 when every sample is inside; ``None`` when the last sample is outside (never settled).
    """
    _check_dt(dt_s)
    y = _arr(output)
    if y.size == 0:
        return None
    outside = np.abs(y - reference_value) > band
    if outside[-1]:
        return None
    if not outside.any():
        return 0.0
    last_out = int(np.flatnonzero(outside)[-1])
    return float((last_out + 1) * dt_s)


def overshoot(output, previous_reference: float, new_reference: float) -> float:
    """Largest excursion beyond the new reference in the direction of the step (>= 0, unit of y).

    Zero for a zero step.
    """
    y = _arr(output)
    delta = new_reference - previous_reference
    if delta == 0 or y.size == 0:
        return 0.0
    return float(max(0.0, np.max(np.sign(delta) * (y - new_reference))))


def step_responses(output, reference, dt_s: float, band: float, relative_band: bool = False) -> list[dict]:
    """One record per reference step: time (s from the start of the arrays), from, to, time to band, overshoot,
    error at the end of the response (output - new reference) and the response length.

    The band is ``band`` in output units, or ``band * |new reference|`` with ``relative_band``.
    A step's response runs to the next step or the end of the arrays.
    """
    y, r = _arr(output), _arr(reference)
    if y.shape != r.shape:
        raise ValueError(f"output and reference must have the same length, got {y.size} and {r.size}")
    steps = step_indices(r)
    out = []
    for i, k in enumerate(steps):
        end = steps[i + 1] if i + 1 < len(steps) else r.size
        new, old = float(r[k]), float(r[k - 1])
        b = band * abs(new) if relative_band else band
        seg = y[k:end]
        out.append({"time_s": k * dt_s, "from": old, "to": new,
                    "time_to_band_s": time_in_band_s(seg, new, b, dt_s),
                    "overshoot": overshoot(seg, old, new),
                    "final_error": float(seg[-1] - new),
                    "response_s": (end - k) * dt_s})
    return out


def in_band_after_settling(output, reference, dt_s: float, band: float) -> dict:
    """The thesis's yardstick beside the IAE: per reference step, the settle time (first sample inside
    +-``band`` of the new reference, s from the step, ``None`` if never) and, from there to the next
    step, the share of samples inside the band; pooled over all steps as ``share`` (``None`` if no
    step settled). The first stretch (before any step) counts as settled from its start."""
    _check_dt(dt_s)
    y, r = _arr(output), _arr(reference)
    if y.shape != r.shape:
        raise ValueError(f"output and reference must have the same length, got {y.size} and {r.size}")
    starts = [0] + [k for k in step_indices(r) if k > 0]
    inside_total, counted, settle = 0, 0, []
    for i, k in enumerate(starts):
        end = starts[i + 1] if i + 1 < len(starts) else r.size
        inside = np.abs(y[k:end] - r[k:end]) <= band
        first = int(np.argmax(inside)) if inside.any() else None
        if i > 0:
            settle.append(None if first is None else first * dt_s)
        if first is not None:
            inside_total += int(inside[first:].sum())
            counted += inside.size - first
    return {"share": inside_total / counted if counted else None, "settle_times_s": settle}


def lagged_reference(reference, tau_s: float, dt_s: float) -> np.ndarray:
    """The reading of a first-order sensor (time constant ``tau_s``) whose input equals the reference.

    The ideal response without overshoot of the measured quantity: the true value is at the
    reference from the sample where it changes (held over each sample), the sensor lags it:
    y[k+1] = r[k] + (y[k] - r[k]) exp(-dt/tau), y[0] = r[0]. NaN references are not allowed.
    """
    _check_dt(dt_s)
    if not (isinstance(tau_s, (int, float)) and math.isfinite(tau_s) and tau_s > 0):
        raise ValueError(f"tau_s: expected a finite time constant > 0 s, got {tau_s!r}")
    r = _arr(reference)
    if not np.all(np.isfinite(r)):
        raise ValueError("reference: expected finite values")
    a = math.exp(-dt_s / tau_s)
    y = np.empty_like(r)
    if r.size:
        y[0] = r[0]
    for k in range(r.size - 1):
        y[k + 1] = r[k] + (y[k] - r[k]) * a
    return y


def energy_wh(power_w, dt_s: float) -> float:
    """Electric energy in Wh of a sampled power (W), held over each sample."""
    _check_dt(dt_s)
    return float(np.sum(_arr(power_w)) * dt_s / 3600.0)


def actuator_travel(commands, lower: Sequence[float], upper: Sequence[float]) -> np.ndarray:
    """Per actuator: sum of |u_k - u_{k-1}| divided by its range (upper - lower); (n, m) commands in."""
    u = np.asarray(commands, float)
    if u.ndim != 2:
        raise ValueError(f"commands must be an (n_samples, n_actuators) array, got shape {u.shape}")
    span = np.asarray(upper, float) - np.asarray(lower, float)
    if span.shape != (u.shape[1],) or np.any(span <= 0):
        raise ValueError("lower and upper must give one positive range per actuator")
    if u.shape[0] < 2:
        return np.zeros(u.shape[1])
    return np.sum(np.abs(np.diff(u, axis=0)), axis=0) / span


def bound_violations(commands, lower: Sequence[float], upper: Sequence[float], tol: float = 1e-6) -> np.ndarray:
    """Per actuator: number of samples whose command lies outside [lower - tol, upper + tol] or is not finite."""
    u = np.asarray(commands, float)
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    bad = ~np.isfinite(u) | (u < lo - tol) | (u > hi + tol)
    return np.sum(bad, axis=0).astype(int)


def threshold_exceedance(signal, limit: float, dt_s: float) -> dict:
    """Samples above ``limit``, time above it (s) and the largest exceedance (unit of the signal, >= 0)."""
    _check_dt(dt_s)
    x = _arr(signal)
    above = x > limit
    return {"samples": int(above.sum()), "time_s": float(above.sum() * dt_s),
            "max_excess": float(max(0.0, np.max(x - limit))) if x.size else 0.0}


def heater_low_flow_samples(heater_power_w, volume_flow_m3s, min_flow_m3s: float = HEATER_MIN_FLOW_M3S,
                            on_w: float = HEATER_ON_W) -> int:
    """Samples with the heater drawing more than ``on_w`` while the volume flow is below ``min_flow_m3s``."""
    p, v = _arr(heater_power_w), _arr(volume_flow_m3s)
    if p.shape != v.shape:
        raise ValueError(f"heater_power_w and volume_flow_m3s must have the same length, got {p.size} and {v.size}")
    return int(np.sum((p > on_w) & (v < min_flow_m3s)))


def step_time_stats(step_times_s, dt_s: float) -> dict:
    """Median and 99th percentile step wall time (ms, linear interpolation) and the mean time ratio."""
    _check_dt(dt_s)
    t = _arr(step_times_s)
    if t.size == 0:
        return {"median_ms": None, "p99_ms": None, "max_ms": None, "time_ratio": None}
    return {"median_ms": float(np.median(t) * 1e3), "p99_ms": float(np.percentile(t, 99) * 1e3),
            "max_ms": float(np.max(t) * 1e3), "time_ratio": float(np.mean(t) / dt_s)}


def count_fallbacks(fallbacks: Iterable) -> dict:
    """Number of steps with a fallback (any value other than ``None``) and the count per fallback name."""
    per: dict[str, int] = {}
    for f in fallbacks:
        if f is not None:
            per[str(f)] = per.get(str(f), 0) + 1
    return {"count": sum(per.values()), "by_name": per}


def summarise_steps(records: Sequence[Mapping]) -> dict:
    """Median and max time to band over steps (settled ones), number of steps and of unsettled ones, max overshoot."""
    times = [r["time_to_band_s"] for r in records if r["time_to_band_s"] is not None]
    return {"steps": len(records),
            "unsettled": sum(1 for r in records if r["time_to_band_s"] is None),
            "median_time_to_band_s": float(np.median(times)) if times else None,
            "max_time_to_band_s": float(max(times)) if times else None,
            "max_overshoot": float(max((r["overshoot"] for r in records), default=0.0))}


def ratio(mpc_value, baseline_value) -> float | None:
    """mpc / baseline; ``None`` when either is missing or not finite; inf when only the baseline is 0."""
    if mpc_value is None or baseline_value is None:
        return None
    a, b = float(mpc_value), float(baseline_value)
    if not (math.isfinite(a) and math.isfinite(b)):
        return None
    if b == 0.0:
        return 1.0 if a == 0.0 else math.inf
    return a / b


# ---------------------------------------------------------------------------- one run
#: Seconds after a step from which the error counts as steady state in the diagnostic split of the IAE.
STEADY_AFTER_S = 60.0


def _steady_mask(time_s: np.ndarray, step_times_s: Sequence[float], start_s: float) -> np.ndarray:
    """True for samples more than STEADY_AFTER_S after the latest step (or the scored start)."""
    last = np.full(time_s.shape, start_s)
    for ts in step_times_s:
        last = np.where(time_s >= ts, ts, last)
    return time_s - last >= STEADY_AFTER_S


def run_figures(trace, lower: Sequence[float], upper: Sequence[float], heater_temp_max_c: float,
                trap_threshold_pct: float, sensor_tau_s: float) -> dict:
    """All figures of one run (``trace`` as recorded by :func:`hvac_mpc.benchmarks.simulate.simulate`).

    Scored samples are those at or after ``trace.metrics_start_s``. Returns ``{"figures": flat
    headline numbers, "details": per-step records, per-actuator and per-outlet numbers}``.
    Temperature figures use the noise-free thermocouple reading (``truth['supply_temp_c']``);
    the true mixed-air temperature gives the secondary IAE. ``sensor_tau_s`` is the plant's
    thermocouple time constant, for the ideal-response figures (:func:`lagged_reference`), the same
    for every controller: what a controller would score whose air temperature never overshoots.
    """
    dt = trace.dt_s
    t = np.asarray(trace.time_s, float)
    k0 = int(np.searchsorted(t, trace.metrics_start_s - 1e-9))
    sl = slice(k0, None)
    ref, tru = trace.reference, trace.truth
    temp_steps = [s for s in step_responses(tru["supply_temp_c"], ref["supply_temp_c"], dt, TEMP_BAND_C)
                  if s["time_s"] >= trace.metrics_start_s]
    flow_steps = [s for s in step_responses(tru["volume_flow_m3s"], ref["volume_flow_m3s"], dt,
                                            FLOW_BAND_FRACTION, relative_band=True)
                  if s["time_s"] >= trace.metrics_start_s]
    for s in temp_steps + flow_steps:
        s["time_s"] = float(t[0] + s["time_s"])
    ts, fs = summarise_steps(temp_steps), summarise_steps(flow_steps)

    outlets = ("flow_m_m3s", "flow_f_m3s", "flow_w_m3s")
    y_out = np.column_stack([tru[o][sl] for o in outlets])
    r_out = np.column_stack([ref[o][sl] for o in outlets])
    per_outlet = {o: rms_error(y_out[:, i], r_out[:, i]) for i, o in enumerate(outlets)}

    applied = np.asarray(trace.applied, float)[sl]
    requested = np.asarray(trace.requested, float)[sl]
    travel = actuator_travel(applied, lower, upper)
    bounds = bound_violations(requested, lower, upper)
    heater_t = threshold_exceedance(tru["heater_temp_c"][sl], heater_temp_max_c, dt)
    low_flow = heater_low_flow_samples(tru["heater_power_w"][sl], tru["volume_flow_m3s"][sl])
    timing = step_time_stats(np.asarray(trace.step_time_s)[sl], dt)
    fb = count_fallbacks(trace.fallback[k0:])

    ideal = lagged_reference(ref["supply_temp_c"], sensor_tau_s, dt)
    ideal_steps = summarise_steps([s for s in step_responses(ideal, ref["supply_temp_c"], dt, TEMP_BAND_C)
                                   if s["time_s"] >= trace.metrics_start_s])
    e_temp = tru["supply_temp_c"][sl] - ref["supply_temp_c"][sl]
    band = in_band_after_settling(tru["supply_temp_c"][sl], ref["supply_temp_c"][sl], dt, TEMP_BAND_C)
    settled_times = [x for x in band["settle_times_s"] if x is not None]
    reach = out_of_reach_summary(getattr(trace, "out_of_reach", None) or [None] * t.size, k0, dt)
    steady = _steady_mask(t[sl], [s["time_s"] for s in temp_steps], trace.metrics_start_s)
    blower_i, heater_i, a_i = (list(trace.actuators).index(n) for n in ("blower_power_w", "heater_cmd_w",
                                                                          "valve_a_pct"))
    figures = {
        "temp_iae_cs": iae(tru["supply_temp_c"][sl], ref["supply_temp_c"][sl], dt),
        "air_temp_iae_cs": iae(tru["supply_air_temp_c"][sl], ref["supply_temp_c"][sl], dt),
        "ideal_temp_iae_cs": iae(ideal[sl], ref["supply_temp_c"][sl], dt),
        "ideal_temp_time_to_band_max_s": ideal_steps["max_time_to_band_s"],
        "temp_steps": ts["steps"],
        "temp_unsettled": ts["unsettled"],
        "temp_time_to_band_median_s": ts["median_time_to_band_s"],
        "temp_time_to_band_max_s": ts["max_time_to_band_s"],
        "temp_overshoot_max_c": ts["max_overshoot"],
        "temp_in_band_share": band["share"],
        "temp_settle_median_s": float(np.median(settled_times)) if settled_times else None,
        "out_of_reach_s": reach["time_s"],
        "flow_iae_m3": iae(tru["volume_flow_m3s"][sl], ref["volume_flow_m3s"][sl], dt),
        "flow_steps": fs["steps"],
        "flow_unsettled": fs["unsettled"],
        "flow_time_to_band_median_s": fs["median_time_to_band_s"],
        "flow_time_to_band_max_s": fs["max_time_to_band_s"],
        "outlet_rms_m3s": rms_error(y_out, r_out),
        "blower_wh": energy_wh(applied[:, blower_i], dt),
        "heater_wh": energy_wh(tru["heater_power_w"][sl], dt),
        "travel_mean": float(np.mean(travel)),
        "violations_bounds": int(bounds.sum()),
        "violations_heater_temp": heater_t["samples"],
        "violations_heater_low_flow": low_flow,
        "step_median_ms": timing["median_ms"],
        "step_p99_ms": timing["p99_ms"],
        "time_ratio": timing["time_ratio"],
        "fallbacks": fb["count"],
    }
    figures["energy_wh"] = figures["blower_wh"] + figures["heater_wh"]
    figures["violations_total"] = (figures["violations_bounds"] + figures["violations_heater_temp"]
                                   + figures["violations_heater_low_flow"])
    details = {
        "scored_from_s": float(trace.metrics_start_s),
        "scored_samples": int(t.size - k0),
        "temperature_steps": temp_steps,
        "flow_steps": flow_steps,
        "outlet_rms_m3s": per_outlet,
        "travel": {n: float(v) for n, v in zip(trace.actuators, travel)},
        "bound_violations": {n: int(v) for n, v in zip(trace.actuators, bounds)},
        "heater_temp": {**heater_t, "limit_c": heater_temp_max_c},
        "heater_low_flow": {"samples": low_flow, "min_flow_m3s": HEATER_MIN_FLOW_M3S, "on_above_w": HEATER_ON_W},
        "step_time": timing,
        "fallbacks": fb,
        "sensor_tau_s": float(sensor_tau_s),
        "steady_samples": int(steady.sum()),
        "temp_iae_steady_cs": float(np.sum(np.abs(e_temp[steady])) * dt),
        "temp_mean_abs_steady_c": float(np.mean(np.abs(e_temp[steady]))) if steady.any() else None,
        "flow_mean_excess_m3s": float(np.mean(tru["volume_flow_m3s"][sl] - ref["volume_flow_m3s"][sl])),
        "mean_blower_w": float(np.mean(applied[:, blower_i])),
        "mean_heater_cmd_w": float(np.mean(applied[:, heater_i])),
        "valve_a_saturated_s": float(np.sum(applied[:, a_i] >= trap_threshold_pct) * dt),
        "max_heater_temp_c": float(np.max(tru["heater_temp_c"][sl])),
        "temp_band_c": TEMP_BAND_C,
        "temp_settle_times_s": band["settle_times_s"],
        "out_of_reach": reach["by_reference"],
    }
    return {"figures": figures, "details": details}


def out_of_reach_summary(records: Sequence, start: int, dt_s: float) -> dict:
    """Seconds with any reference reported out of reach and, per reference name, the samples, the mean
    and the largest shortfall (unit of the reference) from sample ``start`` on; records are per
    sample ``None`` or a mapping name -> shortfall (a controller's ``stats["out_of_reach"]``)."""
    per: dict[str, list[float]] = {}
    n = 0
    for rec in list(records)[start:]:
        if rec:
            n += 1
            for name, short in rec.items():
                per.setdefault(str(name), []).append(float(short))
    return {"time_s": n * dt_s,
            "by_reference": {k: {"samples": len(v), "mean_shortfall": float(np.mean(v)),
                                 "max_shortfall": float(np.max(v)), "last_shortfall": v[-1]}
                             for k, v in per.items()}}


#: Figures compared as MPC / baseline (all lower-is-better).
RATIO_FIGURES = ("temp_iae_cs", "air_temp_iae_cs", "temp_time_to_band_max_s", "flow_iae_m3", "outlet_rms_m3s",
                 "blower_wh", "heater_wh", "energy_wh", "travel_mean", "step_median_ms", "step_p99_ms")


def ratios(mpc: Mapping, baseline: Mapping) -> dict:
    """MPC / baseline for each of :data:`RATIO_FIGURES` (``None`` where undefined)."""
    return {k: ratio(mpc.get(k), baseline.get(k)) for k in RATIO_FIGURES}
