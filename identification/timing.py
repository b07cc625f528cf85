"""Log timing check: a constant shift between the commands and the sensor columns.

Row k of a log holds the readings at t_k and the command applied from t_k on, so a blower step
shows in the volume flow one row later (docs/model.md sec. 4). A logger that writes its sensor
columns late (or early) by whole samples breaks that. The volume flow follows the blower with no
dynamics worth a sample (the flow sensor is a pressure tap), so it shows the shift cleanly and
apart from a transport delay of the temperature, which only moves ``supply_temp_c``.

The check: the nominal model's free-run flow, compared to the measured flow read ``s`` samples
earlier for s in -MAX_SHIFT..MAX_SHIFT, with an affine correction (gain and offset fitted
per s by least squares, so a wrong flow gain does not bias it). The shift with the smallest
error is taken if it beats s = 0 by the factor ``MIN_IMPROVEMENT``.
"""

from __future__ import annotations

import numpy as np

from .log_data import LogData

#: Largest shift looked for, samples. It was 3: a log 4 samples late was reported and corrected as 3 late, and the
#: samples left went into transport delays (a clean log 5 samples late got three; docs/identification.md, "Fresh
#: seeds 307 and 419").
#: ASSUMPTION: a logger misaligns its columns by at most 30 samples (30 s at 1 Hz, the largest transport delay scanned);
#: a shift at the edge of the scan is reported as possibly larger.
MAX_SHIFT = 30
#: Error ratio (s = 0 over best s) needed to declare a shift.
MIN_IMPROVEMENT = 1.5


def _affine_sse(y: np.ndarray, yhat: np.ndarray) -> float:
    ok = np.isfinite(y) & np.isfinite(yhat)
    a = np.column_stack([yhat[ok], np.ones(ok.sum())])
    coef, *_ = np.linalg.lstsq(a, y[ok], rcond=None)
    r = y[ok] - a @ coef
    return float(np.mean(r ** 2))


def shifted(values: np.ndarray, s: int) -> np.ndarray:
    """``values`` read ``s`` samples later (s > 0: row k gets row k + s), NaN where it runs out."""
    out = np.full(len(values), np.nan)
    if s > 0:
        out[:-s] = values[s:]
    elif s < 0:
        out[-s:] = values[:s]
    else:
        out[:] = values
    return out


def detect_shift(measured_flow: np.ndarray, predicted_flow: np.ndarray) -> tuple[int, dict[int, float]]:
    """Shift s (samples the sensor columns are late; negative = early) and the error per s."""
    errors = {s: _affine_sse(shifted(measured_flow, s), predicted_flow) for s in range(-MAX_SHIFT, MAX_SHIFT + 1)}
    best = min(errors, key=errors.get)
    if best != 0 and errors[0] >= MIN_IMPROVEMENT * errors[best]:
        return best, errors
    return 0, errors


#: Logged columns that are sensor readings besides the model's outputs: they move with the outputs.
SENSOR_SIGNALS = ("water_temp_c", "hvac_inlet_temp_c", "cabin_temp_c", "heater_outlet_temp_c", "heater_power_w")


def correct(log: LogData, s: int) -> None:
    """Move the sensor columns of ``log`` back by ``s`` samples in place (outputs, water, inlet, cabin and their
    signals), then drop the ``|s|`` rows at the end (s > 0) or the start (s < 0) whose sensor values ran out: no row
    keeps a reading from before the correction, and none is NaN for it."""
    if s == 0:
        return
    for name in list(log.outputs):
        log.outputs[name] = shifted(log.outputs[name], s)
    for attr in ("water_temp_c", "inlet_temp_c", "cabin_temp_c"):
        if getattr(log, attr) is not None:
            setattr(log, attr, shifted(getattr(log, attr), s))
    for name in list(log.signals):
        if name in log.outputs or name in SENSOR_SIGNALS:
            log.signals[name] = shifted(log.signals[name], s)
    _keep_rows(log, slice(0, -s) if s > 0 else slice(-s, None))
    log.timing_shift_samples = s


def _keep_rows(log: LogData, rows: slice) -> None:
    """Keep only ``rows`` of every per-row array of ``log`` (in place)."""
    for attr in ("time_s", "u", "u_prev", "inlet_temp_c", "chiller_setpoint_c", "water_temp_c", "cabin_temp_c",
                 "train", "holdout"):
        value = getattr(log, attr)
        if value is not None:
            setattr(log, attr, value[rows])
    for table in (log.outputs, log.signals):
        for name in list(table):
            table[name] = table[name][rows]


def describe(s: int, dt_s: float, errors: dict[int, float]) -> str:
    """The finding in words."""
    ratio = errors[0] / max(errors[s], 1e-300) if s else 1.0
    if s == 0:
        return "log timing: sensor columns in step with the commands (no shift between inputs and outputs)"
    when = "late" if s > 0 else "early"
    edge = (f"; the largest shift looked for is {abs(s)} samples, the columns may be further off"
            if abs(s) >= max(abs(k) for k in errors) else "")
    return (f"log timing: the sensor columns are {abs(s)} sample(s) ({abs(s) * dt_s:g} s) {when} against the "
            f"commands (the flow follows a blower step {1 + s:+d} rows after it instead of +1; flow error {ratio:.1f}x "
            f"smaller once moved back); corrected by moving them {abs(s)} sample(s) "
            f"{'earlier' if s > 0 else 'later'} before fitting{edge}")
