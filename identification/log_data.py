"""A measurement log prepared for identification: arrays, checks, the time split.

Conventions (docs/model.md sec. 4): row k holds the sensor readings at time t_k and the command
applied from t_k on. The model's output at row k therefore depends on the state at t_k and
the command of row k-1 (the thesis's unit delay, sec. 4.1.2).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from hvac_mpc.models.box import INPUTS
from hvac_mpc.models.measurement_log import read_log

from . import log_repair

#: Logged outputs the model predicts (log column = model output name).
MODEL_OUTPUTS = ("supply_temp_c", "volume_flow_m3s", "heater_outlet_temp_c", "heater_power_w")
#: Allowed ranges of the logged commands (docs/model.md sec. 2; blower 0 W allowed for 'off').
INPUT_RANGES = {"blower_power_w": (0.0, 300.0), "heater_cmd_w": (0.0, 240.0), "valve_a_pct": (0.0, 100.0),
                "valve_m_pct": (0.0, 100.0), "valve_f_pct": (0.0, 100.0), "valve_w_pct": (0.0, 100.0)}
#: ASSUMPTION: chiller set point when the log has none (docs/model.md sec. 1: 5 C in cooling).
DEFAULT_CHILLER_SETPOINT_C = 5.0
#: Minimum log length, samples (a training and a held-out part of a few minutes each).
MIN_SAMPLES = 600
#: Samples at the start excluded from all errors (initial state taken as the steady state).
BURN_IN_S = 120.0
#: Width of the centred moving average applied to the logged water temperature, s.
WATER_SMOOTHING_S = 15.0


class LogDataError(ValueError):
    """The log cannot be used for identification; the message names the column and the rule."""


@dataclass
class LogData:
    """Arrays of one log. ``u`` and ``u_prev`` are (n, 6) in model input order; ``inlet_temp_c``,
    ``chiller_setpoint_c`` (n,); ``water_temp_c`` and ``cabin_temp_c`` (n,) smoothed or ``None`` when not logged;
    ``outputs`` maps logged model outputs to (n,) arrays (NaN where missing); ``signals`` holds
    every numeric column; ``train`` and ``holdout`` are boolean masks."""

    time_s: np.ndarray
    dt_s: float
    u: np.ndarray
    u_prev: np.ndarray
    inlet_temp_c: np.ndarray
    chiller_setpoint_c: np.ndarray
    water_temp_c: np.ndarray | None
    outputs: dict[str, np.ndarray]
    signals: dict[str, np.ndarray]
    train: np.ndarray
    holdout: np.ndarray
    notes: list[str] = field(default_factory=list)
    source: str = ""
    bad_rows: dict = field(default_factory=dict)
    timing_shift_samples: int = 0
    cabin_temp_c: np.ndarray | None = None

    @property
    def n(self) -> int:
        return len(self.time_s)

    @property
    def split_time_s(self) -> float:
        return float(self.time_s[np.argmax(self.holdout)])

    def output_names(self) -> tuple[str, ...]:
        return tuple(self.outputs)


def _interp_nans(values: np.ndarray) -> np.ndarray:
    ok = np.isfinite(values)
    if ok.all():
        return values
    idx = np.arange(len(values))
    return np.interp(idx, idx[ok], values[ok])


def _moving_average(values: np.ndarray, width: int) -> np.ndarray:
    if width <= 1:
        return values
    pad = width // 2
    padded = np.concatenate([np.full(pad, values[0]), values, np.full(width - 1 - pad, values[-1])])
    return np.convolve(padded, np.ones(width) / width, mode="valid")


def _smoothed(columns: Mapping[str, np.ndarray], name: str, dt: float) -> np.ndarray | None:
    """An optional temperature column, gaps filled and smoothed over WATER_SMOOTHING_S; ``None`` when it
    is missing or empty in more than 10 % of the rows."""
    if name not in columns or np.mean(np.isfinite(np.asarray(columns[name], float))) < 0.9:
        return None
    width = max(1, int(round(WATER_SMOOTHING_S / dt)))
    return _moving_average(_interp_nans(np.asarray(columns[name], float)), width)


def prepare(columns: Mapping[str, np.ndarray], holdout_fraction: float = 1 / 3, source: str = "") -> LogData:
    """Check a log's columns and build :class:`LogData` with the time split.

    The first ``1 - holdout_fraction`` of the log (after a 120 s burn-in) is the training part,
    the rest the held-out part. Raises :class:`LogDataError` naming the column for missing,
    non-finite or out-of-range commands, non-uniform sampling or a log that is too short.
    """
    if not 0.1 <= holdout_fraction <= 0.6:
        raise LogDataError(f"holdout_fraction = {holdout_fraction} is outside the allowed range [0.1, 0.6]")
    notes: list[str] = []
    if len(np.asarray(columns["time_s"])) < MIN_SAMPLES:
        raise LogDataError(f"log has {len(columns['time_s'])} rows; identification needs at least {MIN_SAMPLES} "
                           "(column time_s)")
    t_raw = np.asarray(columns["time_s"], float)
    steps = np.diff(np.sort(t_raw[np.isfinite(t_raw)]))
    steps = steps[steps > 0]
    dt = float(np.median(steps)) if len(steps) else 0.0
    regular = steps[steps < 1.5 * dt]
    if dt <= 0 or np.max(np.abs(regular - dt)) > 0.05 * dt:
        raise LogDataError(f"column time_s: sampling must be uniform (median step {dt} s, steps range "
                           f"{regular.min() if len(regular) else 0}..{regular.max() if len(regular) else 0} s); "
                           "resample the log first")
    columns, bad_rows = log_repair.repair(columns, INPUTS, dt)
    notes += [f"bad rows: {line}" for line in log_repair.describe(bad_rows)]
    t = columns["time_s"]
    n = len(t)
    u = np.zeros((n, len(INPUTS)))
    for i, name in enumerate(INPUTS):
        col = np.asarray(columns[name], float)
        if not np.all(np.isfinite(col)):
            raise LogDataError(f"column {name} has {int((~np.isfinite(col)).sum())} empty or non-finite values; "
                               "commands must be logged in every row")
        lo, hi = INPUT_RANGES[name]
        if col.min() < lo - 1e-6 or col.max() > hi + 1e-6:
            raise LogDataError(f"column {name} has values in [{col.min():g}, {col.max():g}], outside the allowed "
                               f"range [{lo:g}, {hi:g}]")
        u[:, i] = col
    u_prev = np.vstack([u[:1], u[:-1]])
    inlet = np.asarray(columns["hvac_inlet_temp_c"], float)
    if np.mean(np.isfinite(inlet)) < 0.9:
        raise LogDataError("column hvac_inlet_temp_c is empty in more than 10 % of the rows")
    inlet = _moving_average(_interp_nans(inlet), 5)
    if inlet.min() < -30 or inlet.max() > 60:
        raise LogDataError(f"column hvac_inlet_temp_c has values in [{inlet.min():.1f}, {inlet.max():.1f}] C, "
                           "outside the allowed range [-30, 60] C")
    sp = np.asarray(columns.get("chiller_setpoint_c", np.full(n, np.nan)), float)
    if np.mean(np.isfinite(sp)) < 0.5:
        sp = np.full(n, DEFAULT_CHILLER_SETPOINT_C)
        notes.append(f"chiller_setpoint_c not logged: {DEFAULT_CHILLER_SETPOINT_C} C assumed (docs/model.md sec. 1)")
    else:
        sp = _interp_nans(sp)
    water = _smoothed(columns, "water_temp_c", dt)
    notes.append(f"water_temp_c logged: used as a measured disturbance (smoothed over {WATER_SMOOTHING_S:g} s) in "
                 "place of the modelled chiller" if water is not None else
                 "water_temp_c not logged: the model's water follows the chiller's two-point control from the first set "
                 "point (compressor on; ASSUMPTION: the box's start), docs/identification.md")
    cabin = _smoothed(columns, "cabin_temp_c", dt)
    if cabin is not None:
        notes.append(f"cabin_temp_c logged: offered to term discovery (smoothed over {WATER_SMOOTHING_S:g} s)")
    outputs = {}
    for name in MODEL_OUTPUTS:
        if name in columns:
            col = np.asarray(columns[name], float)
            if np.mean(np.isfinite(col)) >= 0.5:
                outputs[name] = col
    if "supply_temp_c" not in outputs or "volume_flow_m3s" not in outputs:
        raise LogDataError("columns supply_temp_c and volume_flow_m3s must hold values in most rows")
    signals = {}
    for name, col in columns.items():
        arr = np.asarray(col)
        if arr.dtype == object or name == "time_s":
            continue
        arr = arr.astype(float)
        if np.mean(np.isfinite(arr)) >= 0.9 and np.nanstd(arr) > 0:
            signals[name] = _interp_nans(arr)
    burn = int(round(BURN_IN_S / dt))
    n_train_end = burn + int(round((n - burn) * (1.0 - holdout_fraction)))
    idx = np.arange(n)
    train = (idx >= burn) & (idx < n_train_end)
    holdout = idx >= n_train_end
    return LogData(t, dt, u, u_prev, inlet, sp, water, outputs, signals, train, holdout, notes, source, bad_rows,
                   cabin_temp_c=cabin)


def load(path: str | Path, mapping: Mapping[str, str] | None = None, holdout_fraction: float = 1 / 3) -> LogData:
    """Read a CSV/Parquet log (``mapping``: file column -> schema name) and :func:`prepare` it."""
    return prepare(read_log(path, mapping), holdout_fraction, source=str(path))
