"""Bad rows of a measurement log: found, counted, handled, never fitted silently.

What is looked for (docs/identification.md, "bad rows"), in this order:

1. timestamps that go back (rows out of order): the rows are put back in time order;
2. duplicated timestamps: the first row of each time is kept, the repeats are dropped;
3. dropouts (a gap of more than 1.5 sampling steps): the missing rows are inserted on the
   uniform grid, commands held from the row before (ASSUMPTION: a logger dropout, not an
   actuator one), their sensor cells empty; the rows right after the gap are masked too
   (``SETTLE_AFTER_GAP_S``) because the commands in the gap are unknown;
4. empty or non-finite command cells: held from the row before, the row's sensors masked;
5. empty or non-finite sensor cells: masked (an output) or interpolated (a measured disturbance,
   such as the inlet or water temperature, counted all the same);
6. a stuck sensor: a noisy output that repeats exactly the same value for at least
   ``STUCK_MIN_SAMPLES`` rows (noise makes that impossible for a live sensor): masked.
   Noise-free columns (``heater_power_w`` at 0 W) are not tested and the report says so.

A masked cell is NaN in the prepared log: the free run goes on through it (the state is
continuous) but no error, fit or statistic uses it. :func:`repair` returns the counts.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

#: Rows masked after a dropout (commands inside the gap unknown), s.
SETTLE_AFTER_GAP_S = 30.0
#: Shortest run of identical values of a noisy sensor taken as stuck, samples.
STUCK_MIN_SAMPLES = 10
#: Sensor columns checked for stuck runs and masked with bad rows.
SENSOR_COLUMNS = ("supply_temp_c", "volume_flow_m3s", "heater_outlet_temp_c", "heater_power_w")


def _runs_of_equal(values: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    """(start, end) index ranges where ``values`` repeats one finite value at least ``min_len`` times."""
    out, start = [], 0
    n = len(values)
    for i in range(1, n + 1):
        if i == n or values[i] != values[start] or not np.isfinite(values[i]):
            if i - start >= min_len and np.isfinite(values[start]):
                out.append((start, i))
            start = i
    return out


def _order_and_dedupe(cols: dict[str, np.ndarray], report: dict) -> dict[str, np.ndarray]:
    t = cols["time_s"]
    finite = np.isfinite(t)
    report["rows_without_time"] = int((~finite).sum())
    back = int(np.sum(np.diff(t[finite]) < 0))
    report["non_monotone_timestamps"] = back
    order = np.argsort(np.where(finite, t, np.inf), kind="stable")[: int(finite.sum())]
    cols = {k: np.asarray(v)[order] for k, v in cols.items()}
    t = cols["time_s"]
    keep = np.concatenate([[True], np.diff(t) > 0])
    report["duplicated_timestamps"] = int((~keep).sum())
    return {k: v[keep] for k, v in cols.items()}


def _fill_gaps(cols: dict[str, np.ndarray], dt: float, report: dict) -> tuple[dict[str, np.ndarray], np.ndarray]:
    t = cols["time_s"]
    idx = np.rint((t - t[0]) / dt).astype(int)
    n = int(idx[-1]) + 1
    present = np.zeros(n, bool)
    present[idx] = True
    gaps = np.flatnonzero(np.diff(idx) > 1)
    report["dropouts"] = len(gaps)
    report["dropout_rows"] = int(n - len(idx))
    report["dropout_time_s"] = [float(t[g] + dt) for g in gaps]  # first missing time
    out = {}
    for k, v in cols.items():
        if v.dtype == object:
            full = np.full(n, "", dtype=object)
        else:
            full = np.full(n, np.nan)
        full[idx] = v
        out[k] = full
    out["time_s"] = t[0] + dt * np.arange(n)
    mask = ~present
    settle = int(round(SETTLE_AFTER_GAP_S / dt))
    for g in gaps:
        end = idx[g + 1]
        mask[end:end + settle] = True
    return out, mask


def _hold(values: np.ndarray) -> np.ndarray:
    """Forward-fill non-finite entries (back-fill a leading run)."""
    ok = np.isfinite(values)
    if ok.all() or not ok.any():
        return values
    pos = np.where(ok, np.arange(len(values)), 0)
    np.maximum.accumulate(pos, out=pos)
    filled = values[pos]
    first = np.argmax(ok)
    filled[:first] = values[first]
    return filled


def repair(columns: Mapping[str, np.ndarray], inputs: tuple[str, ...], dt_hint: float | None = None
           ) -> tuple[dict[str, np.ndarray], dict]:
    """Columns on a uniform time grid with bad cells NaN, and the report of what was found.

    ``inputs``: the command columns (held through bad cells). The report holds counts per kind
    and ``masked_rows`` (rows whose sensors are not used); it is empty of findings for a clean log.
    """
    report: dict = {}
    cols = {k: np.asarray(v) for k, v in columns.items()}
    cols = _order_and_dedupe(cols, report)
    t = cols["time_s"]
    dts = np.diff(t)
    dt = float(dt_hint or np.median(dts))
    cols, mask = _fill_gaps(cols, dt, report)
    bad_cmd = np.zeros(len(mask), bool)
    for name in inputs:
        col = cols[name].astype(float)
        bad = ~np.isfinite(col) & ~mask
        bad_cmd |= bad
        cols[name] = _hold(col)
    report["rows_with_bad_commands"] = int(bad_cmd.sum())
    mask |= bad_cmd
    empty, stuck = {}, {}
    for name, col in cols.items():
        if name in inputs or name == "time_s" or col.dtype == object or not np.isfinite(col.astype(float)).any():
            continue
        n_empty = int((~np.isfinite(col.astype(float)) & ~mask).sum())
        if n_empty:
            empty[name] = n_empty
    for name in SENSOR_COLUMNS:
        if name not in cols or name == "heater_power_w":
            continue
        col = cols[name].astype(float)
        runs = _runs_of_equal(col, STUCK_MIN_SAMPLES)
        if runs:
            stuck[name] = {"runs": len(runs), "rows": int(sum(e - s for s, e in runs)),
                           "start_time_s": [float(cols["time_s"][s]) for s, _ in runs]}
            for s, e in runs:
                col[s:e] = np.nan
        cols[name] = col
    report["empty_sensor_cells"] = empty
    report["stuck_sensor"] = stuck
    for name in SENSOR_COLUMNS:
        if name in cols:
            col = cols[name].astype(float)
            col[mask] = np.nan
            cols[name] = col
    report["masked_rows"] = int(mask.sum())
    report["rows"] = len(mask)
    return cols, report


def describe(report: Mapping) -> list[str]:
    """The findings in words (nothing for a clean log)."""
    out = []
    if report.get("rows_without_time"):
        out.append(f"{report['rows_without_time']} rows without a timestamp dropped")
    if report.get("non_monotone_timestamps"):
        out.append(f"{report['non_monotone_timestamps']} timestamps going back: rows put back in time order")
    if report.get("duplicated_timestamps"):
        out.append(f"{report['duplicated_timestamps']} duplicated timestamps: repeats dropped, first row kept")
    if report.get("dropouts"):
        out.append(f"{report['dropouts']} dropout(s), {report['dropout_rows']} rows missing (from t = "
                   f"{', '.join(f'{t:g}' for t in report['dropout_time_s'])} s): rows inserted with commands held "
                   f"and sensors masked, plus {SETTLE_AFTER_GAP_S:g} s after each gap")
    if report.get("rows_with_bad_commands"):
        out.append(f"{report['rows_with_bad_commands']} rows with an empty command cell: command held, row masked")
    for name, count in report.get("empty_sensor_cells", {}).items():
        what = "masked" if name in SENSOR_COLUMNS else "filled by interpolation (a measured disturbance)"
        out.append(f"{name}: {count} empty or non-finite cell(s) {what}")
    for name, s in report.get("stuck_sensor", {}).items():
        out.append(f"{name}: stuck sensor, {s['runs']} run(s) of {s['rows']} rows repeating one value exactly "
                   f"(from t = {', '.join(f'{t:g}' for t in s['start_time_s'])} s): masked")
    if out:
        out.append(f"{report['masked_rows']} of {report['rows']} rows masked in all in the outputs")
    return out
