"""Open-loop measurement logs of the independent box, with optional bad rows, for identification tests.

A log is a 1 Hz CSV with a header (docs/model.md sec. 4 column names, missing value = empty field).
Row k holds the sensors read at ``time_s`` and the command applied from ``time_s`` on (the order
of a controller: read, then act), so a blower step shows in the flow one row later.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hvac_mpc.contract import INPUTS

from . import constants as k
from .box import INPUT_LOWER, INPUT_UPPER, IndependentBox
from .variants import Variant, get_variant

#: Sensor columns, in file order (these are shifted by ``Variant.log_shift_samples``).
SENSOR_COLUMNS = ("hvac_inlet_temp_c", "volume_flow_m3s", "supply_temp_c", "heater_power_w", "water_temp_c",
                  "heater_outlet_temp_c", "cabin_temp_c")
#: All columns, in file order.
COLUMNS = ("time_s",) + INPUTS + ("hvac_inlet_temp_c", "volume_flow_m3s", "supply_temp_c", "heater_power_w",
                                  "water_temp_c", "chiller_setpoint_c", "heater_outlet_temp_c", "cabin_temp_c")
#: "steps": cooling and heating phases with random steps; "hot_heater": the same, but the heating phases
#: run the heater near full power at low flow, so its body passes the PTC's knee (~60 C) and the PTC
#: power fall shows in the logged heater power; "short_holds": the "steps" ranges with shorter holds (5-90 s),
#: another excitation than the one the identification was developed on.
EXCITATIONS = ("steps", "hot_heater", "short_holds")

HOLD_S = (20, 300)                 # ASSUMPTION: hold times of the steps (s)
SHORT_HOLD_S = (5, 90)             # ASSUMPTION: hold times of the "short_holds" excitation (s)
PHASE_S = (900, 1800)              # ASSUMPTION: length of a cooling or heating phase
COOLING_SETPOINT_C = 5.0           # docs/model.md sec. 1: chiller at 5 C while cooling
HEATING_SETPOINT_C = 20.0          # ASSUMPTION: chiller set point while heating (water ramps up)
HEATING_MIN_BLOWER_W = 80.0        # ASSUMPTION: heater only with flow (~0.015 m3/s at least)
HEATING_HEATER_W = (40.0, k.HEATER_MAX_W)
HEATING_VALVE_A_PCT = (20.0, 80.0)  # valve a partly open while heating (thesis 5.4.2 caps it at 80 %)
HOT_HEATER_W = (200.0, k.HEATER_MAX_W)   # ASSUMPTION: "hot_heater" heater steps (the fall bites above ~200-215 W)
HOT_BLOWER_W = (HEATING_MIN_BLOWER_W, 180.0)  # ASSUMPTION: "hot_heater" blower steps (low flow)
INLET_MEAN_C, INLET_SLOW_C, INLET_FAST_C = 26.0, 4.0, 2.0   # inlet between 20 and 32 C
INLET_PERIODS_S = (3600.0, 1100.0)

# bad rows (bad_rows=True)
N_MISSING_CELLS = 6
DROPOUT_SAMPLES = 30
N_DUPLICATES = 3
DUPLICATE_SPACING = 15
N_SWAPS = 2
SWAP_SPACING = 20
STUCK_SAMPLES = 60
MIN_BAD_ROWS_DURATION_S = 900


@dataclass(frozen=True)
class Schedule:
    """Open-loop excitation, one entry per sample: commands (n x 6), chiller set point and inlet (degC)."""

    commands: np.ndarray
    setpoint_c: np.ndarray
    inlet_c: np.ndarray


def _steps(n: int, lo: float, hi: float, rng: np.random.Generator, hold_s: tuple[int, int] = HOLD_S) -> np.ndarray:
    """Random piecewise-constant signal in [lo, hi] with hold times of ``hold_s`` samples (20-300)."""
    out = np.empty(n)
    i = 0
    while i < n:
        hold = int(rng.integers(hold_s[0], hold_s[1] + 1))
        out[i:i + hold] = rng.uniform(lo, hi)
        i += hold
    return out


def _phase_commands(n: int, heating: bool, rng: np.random.Generator, hot: bool = False,
                    hold_s: tuple[int, int] = HOLD_S) -> np.ndarray:
    """Commands of one phase: cooling (heater off, valve a anywhere) or heating (heater on, a partly open);
    ``hot``: heating near full heater power at low flow (the "hot_heater" excitation); ``hold_s``: hold times."""
    u = np.empty((n, len(INPUTS)))
    blower = HOT_BLOWER_W if heating and hot else (HEATING_MIN_BLOWER_W if heating else k.BLOWER_MIN_W,
                                                     k.BLOWER_MAX_W)
    u[:, 0] = _steps(n, *blower, rng, hold_s)
    u[:, 1] = _steps(n, *(HOT_HEATER_W if hot else HEATING_HEATER_W), rng, hold_s) if heating else 0.0
    u[:, 2] = _steps(n, *HEATING_VALVE_A_PCT, rng, hold_s) if heating else _steps(n, 0.0, 100.0, rng, hold_s)
    for j in (3, 4, 5):
        u[:, j] = _steps(n, 0.0, 100.0, rng, hold_s)
    return u


def excitation_schedule(n: int, rng: np.random.Generator, excitation: str = "steps") -> Schedule:
    """Alternating cooling and heating phases (cooling first) and a slowly varying inlet temperature
    (``excitation``: one of :data:`EXCITATIONS`)."""
    commands, setpoint = np.empty((n, len(INPUTS))), np.empty(n)
    i, heating = 0, False
    while i < n:
        length = min(n - i, int(rng.integers(PHASE_S[0], PHASE_S[1] + 1)))
        commands[i:i + length] = _phase_commands(length, heating, rng, hot=excitation == "hot_heater",
                                                 hold_s=SHORT_HOLD_S if excitation == "short_holds" else HOLD_S)
        setpoint[i:i + length] = HEATING_SETPOINT_C if heating else COOLING_SETPOINT_C
        i, heating = i + length, not heating
    t = np.arange(n, dtype=float)
    phase = rng.uniform(0.0, 2.0 * np.pi, 2)
    inlet = (INLET_MEAN_C + INLET_SLOW_C * np.sin(2 * np.pi * t / INLET_PERIODS_S[0] + phase[0])
             + INLET_FAST_C * np.sin(2 * np.pi * t / INLET_PERIODS_S[1] + phase[1]))
    return Schedule(np.clip(commands, INPUT_LOWER, INPUT_UPPER), setpoint, inlet)


def run_open_loop(box: IndependentBox, schedule: Schedule, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Drive ``box`` with ``schedule``: read, then apply, then advance. Returns (applied n x 6, sensors n x 7)."""
    n = len(schedule.setpoint_c)
    applied, sensors = np.empty((n, len(INPUTS))), np.empty((n, len(SENSOR_COLUMNS)))
    for i in range(n):
        box.set_environment(inlet_temp_c=schedule.inlet_c[i], chiller_setpoint_c=schedule.setpoint_c[i])
        m = box.read()
        cabin = box.cabin_temp_c + (box.variant.noise_scale * k.NOISE_OTHER_C * rng.normal() if box.noise else 0.0)
        sensors[i] = (m.hvac_inlet_temp_c, m.volume_flow_m3s, m.supply_temp_c, m.heater_power_w, m.water_temp_c,
                      m.heater_outlet_temp_c, cabin)
        applied[i] = box.apply(schedule.commands[i])
        box.advance()
    return applied, sensors


def _rows(applied: np.ndarray, setpoint: np.ndarray, sensors: np.ndarray, n: int, pad: int, shift: int) -> list[list]:
    """Log rows: inputs from sample pad + r, sensors from sample pad + r - shift (r = 0 .. n-1)."""
    rows = []
    for r in range(n):
        i, j = pad + r, pad + r - shift
        values = dict(zip(SENSOR_COLUMNS, sensors[j].tolist()))
        values.update(zip(INPUTS, applied[i].tolist()))
        values["time_s"] = float(r)
        values["chiller_setpoint_c"] = float(setpoint[i])
        rows.append([values[c] for c in COLUMNS])
    return rows


def _segment(n: int, index: int, parts: int, width: int, rng: np.random.Generator) -> int:
    """A random start in the ``index``-th of ``parts`` equal segments with room for ``width`` rows."""
    lo, hi = index * n // parts, (index + 1) * n // parts - width - 2
    return int(rng.integers(lo + 2, max(lo + 3, hi)))


_COL = {c: i for i, c in enumerate(COLUMNS)}
_T, _SUPPLY = _COL["time_s"], _COL["supply_temp_c"]
_PARTS = 6  # each kind of bad row goes into its own sixth of the log


def _stick_supply(rows: list[list], rng: np.random.Generator) -> dict:
    """Part 5: the supply sensor repeats one value for STUCK_SAMPLES rows."""
    s0 = _segment(len(rows), 5, _PARTS, STUCK_SAMPLES, rng)
    value = rows[s0][_SUPPLY]
    for r in range(s0, s0 + STUCK_SAMPLES):
        rows[r][_SUPPLY] = value
    return {"start_s": rows[s0][_T], "n_samples": STUCK_SAMPLES, "value": value}


def _blank_cells(rows: list[list], rng: np.random.Generator) -> list[dict]:
    """Part 1: one sensor cell missing in a few rows, alternately an empty field and NaN."""
    n = len(rows)
    picked = sorted(rng.choice(np.arange(n // _PARTS + 2, 2 * n // _PARTS - 2), N_MISSING_CELLS, replace=False))
    missing = []
    for r in (int(x) for x in picked):
        name = str(rng.choice(SENSOR_COLUMNS))
        kind = "empty" if len(missing) % 2 == 0 else "nan"
        rows[r][_COL[name]] = None if kind == "empty" else math.nan
        missing.append({"time_s": rows[r][_T], "column": name, "as": kind})
    return missing


def _swap_rows(rows: list[list], rng: np.random.Generator) -> list[float]:
    """Part 4: adjacent rows swapped, SWAP_SPACING apart; returns the times that go back."""
    first = _segment(len(rows), 4, _PARTS, 2 + SWAP_SPACING * N_SWAPS, rng)
    back = []
    for r in range(first, first + SWAP_SPACING * N_SWAPS, SWAP_SPACING):
        rows[r], rows[r + 1] = rows[r + 1], rows[r]
        back.append(rows[r + 1][_T])
    return back


def _duplicate_rows(rows: list[list], rng: np.random.Generator) -> list[float]:
    """Part 3: rows repeated right after themselves; returns their times."""
    start = _segment(len(rows), 3, _PARTS, DUPLICATE_SPACING * N_DUPLICATES, rng)
    picked = [start + DUPLICATE_SPACING * j for j in range(N_DUPLICATES)]
    times = [rows[r][_T] for r in picked]
    for r in reversed(picked):  # from the end, so earlier indices stay valid
        rows.insert(r + 1, list(rows[r]))
    return times


def _drop_rows(rows: list[list], rng: np.random.Generator) -> dict:
    """Part 2: DROPOUT_SAMPLES consecutive rows removed."""
    d0 = _segment(len(rows), 2, _PARTS, DROPOUT_SAMPLES, rng)
    gap = {"start_s": rows[d0][_T], "end_s": rows[d0 + DROPOUT_SAMPLES - 1][_T], "n_samples": DROPOUT_SAMPLES}
    del rows[d0:d0 + DROPOUT_SAMPLES]
    return gap


def inject_bad_rows(rows: list[list], rng: np.random.Generator) -> dict:
    """Spoil ``rows`` in place, each kind in its own part of the log; returns what was injected (by time_s).

    Edits in place come first, then the row moves from the end of the log backwards (parts 3, 2),
    so each injection's indices are still the original ones.
    """
    stuck = _stick_supply(rows, rng)
    missing = _blank_cells(rows, rng)
    back = _swap_rows(rows, rng)
    duplicated = _duplicate_rows(rows, rng)
    dropout = _drop_rows(rows, rng)
    return {"missing_cells": missing, "n_missing_cells": len(missing), "dropout": dropout,
            "duplicated_time_s": duplicated, "n_duplicated": len(duplicated),
            "non_monotone_time_s": back, "n_non_monotone": len(back), "stuck_supply": stuck}


def _cell(x) -> str:
    if x is None:
        return ""
    if isinstance(x, float) and math.isnan(x):
        return "NaN"
    return format(float(x), ".7g")


#: Columns a log may leave out (``simulate_log(..., omit=...)``): the optional sensors.
OPTIONAL_COLUMNS = ("water_temp_c", "heater_outlet_temp_c", "cabin_temp_c", "heater_power_w", "chiller_setpoint_c")


def write_csv(path: Path, rows: list[list], omit: tuple[str, ...] = ()) -> None:
    """Write the log with its header; None is an empty field; the columns in ``omit`` are left out."""
    keep = [i for i, c in enumerate(COLUMNS) if c not in omit]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([COLUMNS[i] for i in keep])
        w.writerows([_cell(row[i]) for i in keep] for row in rows)


def simulate_log(path: str | Path, variant: str | Variant = "nominal", duration_s: float = 7200, seed: int = 0,
                 excitation: str = "steps", bad_rows: bool = False, omit: tuple[str, ...] = ()) -> dict:
    """Excite the box open loop for ``duration_s`` s and write a 1 Hz CSV log to ``path``.

    ``omit``: optional sensor columns (:data:`OPTIONAL_COLUMNS`) the log leaves out, as a box without
    that sensor would (e.g. ``("water_temp_c",)``: no chiller water reading).

    Returns what the log holds: the variant and its fields, row counts, the output shift and, with
    ``bad_rows``, what was injected (missing cells, a dropout, duplicated and non-monotone timestamps,
    a stuck supply sensor), all located by ``time_s``.
    """
    name, var = get_variant(variant)
    if excitation not in EXCITATIONS:
        raise ValueError(f"unknown excitation {excitation!r}; allowed: {', '.join(EXCITATIONS)}")
    bad_columns = [c for c in omit if c not in OPTIONAL_COLUMNS]
    if bad_columns:
        raise ValueError(f"omit: column(s) {bad_columns} cannot be left out; allowed: {', '.join(OPTIONAL_COLUMNS)}")
    n = int(round(duration_s))
    if n < 2 or (bad_rows and n < MIN_BAD_ROWS_DURATION_S):
        raise ValueError(f"duration_s must be at least {MIN_BAD_ROWS_DURATION_S if bad_rows else 2} s, got {duration_s}")
    shift = int(var.log_shift_samples)
    pad = abs(shift)
    rng_exc, rng_sens, rng_bad = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    schedule = excitation_schedule(n + 2 * pad, rng_exc, excitation)
    box = IndependentBox(var, seed=seed, inlet_temp_c=schedule.inlet_c[0], chiller_setpoint_c=schedule.setpoint_c[0],
                         initial_command=schedule.commands[0])
    applied, sensors = run_open_loop(box, schedule, rng_sens)
    rows = _rows(applied, schedule.setpoint_c, sensors, n, pad, shift)
    injected = inject_bad_rows(rows, rng_bad) if bad_rows else {}
    path = Path(path)
    write_csv(path, rows, tuple(omit))
    return {"path": str(path), "variant": name, "variant_fields": var.as_dict(), "seed": seed,
            "duration_s": float(n), "excitation": excitation, "samples": n, "rows_written": len(rows),
            "columns": [c for c in COLUMNS if c not in omit], "log_shift_samples": shift,
            "input_to_flow_lag_samples": 1 + shift, "bad_rows": bool(bad_rows), "injected": injected}
