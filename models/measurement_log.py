"""The measurement-log schema (docs/model.md sec. 4): one row per sample, CSV with a header.

Writers flush every row, so a crash loses at most the row in flight; opening an existing log
appends after repairing a torn last row in place (:func:`repair_tail`: truncated at the last
newline, never rewritten). Readers accept CSV or Parquet (with pyarrow installed) and a column
mapping for a lab's own column names; a column a reader does not know is kept as read (numbers,
or text when it is not numeric), so new columns such as ``utc`` (the wall-clock time of the
sample, ISO 8601 UTC) are additive.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

REQUIRED_COLUMNS = ("time_s", "blower_power_w", "heater_cmd_w", "valve_a_pct", "valve_m_pct", "valve_f_pct",
                    "valve_w_pct", "hvac_inlet_temp_c", "volume_flow_m3s", "supply_temp_c")
OPTIONAL_COLUMNS = ("heater_power_w", "water_temp_c", "chiller_setpoint_c", "hvac_inlet_rh_pct",
                    "heater_outlet_temp_c", "cabin_temp_c", "cabin_rh_pct", "outlet_m_temp_c", "outlet_f_temp_c",
                    "outlet_w_temp_c", "ref_supply_temp_c", "ref_volume_flow_m3s", "ref_flow_m_m3s",
                    "ref_flow_f_m3s", "ref_flow_w_m3s", "mode", "controller", "utc", "supply_rh_pct", "model_hash")
COLUMNS = REQUIRED_COLUMNS + OPTIONAL_COLUMNS
#: Text columns; ``model_hash`` names the model file in force when the row was written (daemon logs).
TEXT_COLUMNS = ("mode", "controller", "utc", "model_hash")


class LogFormatError(ValueError):
    """The log does not follow the schema; the message names the column."""


def cell_text(value: Any) -> str:
    """A log cell: text as is, a finite number as its repr, anything else empty."""
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    value = float(value)
    return "" if not math.isfinite(value) else repr(value)


def schema_columns(columns: Iterable[str]) -> tuple[str, ...]:
    """``columns`` as a tuple, every one a schema column (else :class:`LogFormatError` naming them)."""
    out = tuple(columns)
    unknown = sorted(set(out) - set(COLUMNS))
    if unknown:
        raise LogFormatError(f"unknown log column(s) {unknown}")
    return out


class LogWriter:
    """Appends rows to a CSV log in the schema; each row is flushed and fsynced on write."""

    def __init__(self, path: str | Path, columns: Iterable[str] = COLUMNS, fsync: bool = True):
        self.path = Path(path)
        self.columns = schema_columns(columns)
        self.fsync = fsync
        self._ignored: frozenset[str] = frozenset()
        exists = self.path.exists() and self.path.stat().st_size > 0
        if exists:
            with self.path.open("r", newline="") as fh:
                header = tuple(next(csv.reader(fh), []))
            if header != self.columns:
                self._adopt_older_header(header)
            repair_tail(self.path, fsync=fsync)
        self._fh = self.path.open("a", newline="")
        self._writer = csv.writer(self._fh)
        if not exists:
            self._writer.writerow(self.columns)
            self._flush()

    def _adopt_older_header(self, header: tuple[str, ...]) -> None:
        """Append to a log of an earlier schema version (a subset of the columns asked for, same order):
        the columns it lacks are not written. Anything else raises :class:`LogFormatError`."""
        if not (set(header) <= set(self.columns) and set(REQUIRED_COLUMNS) <= set(header)
                and [c for c in self.columns if c in header] == list(header)):
            raise LogFormatError(f"{self.path}: existing header {list(header)} differs from {list(self.columns)}")
        self._ignored = frozenset(self.columns) - frozenset(header)
        self.columns = header

    def write(self, row: Mapping[str, Any]) -> None:
        """Write one sample; missing columns are left empty, unknown keys raise (keys of columns an
        appended older log lacks are dropped)."""
        unknown = sorted(set(row) - set(self.columns) - self._ignored)
        if unknown:
            raise LogFormatError(f"unknown log column(s) {unknown}")
        self._writer.writerow([cell_text(row.get(c)) for c in self.columns])
        self._flush()

    def _flush(self) -> None:
        self._fh.flush()
        if self.fsync:
            os.fsync(self._fh.fileno())

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> "LogWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: The steps of :func:`repair_tail`, in order, as passed to its ``step`` callback: the file is open
#: and nothing read (``begin``), the last newline found (``found``), the file cut there
#: (``truncated``), the cut on disk (``synced``). ``truncated`` and ``synced`` only when a torn row
#: was found.
REPAIR_STEPS = ("begin", "found", "truncated", "synced")


def repair_tail(path: str | Path, fsync: bool = True, chunk_bytes: int = 65536,
                step: Callable[[str], None] | None = None) -> int:
    """Drop a last line cut short by a crash (no trailing newline), in place; returns the bytes removed.

    Reads backwards from the end to the last newline and truncates the file there (one
    ``ftruncate``, then fsync): committed rows are never rewritten, so a crash during the repair
    loses nothing but the torn row, whatever the size of the log. ``step`` (optional) is called
    with each name of :data:`REPAIR_STEPS` as the repair passes it (tests stop or kill the process
    exactly there)."""
    mark = step or (lambda name: None)
    with open(path, "r+b") as fh:
        mark("begin")
        size = fh.seek(0, os.SEEK_END)
        pos = size
        keep = 0
        while pos > 0:
            start = max(0, pos - chunk_bytes)
            fh.seek(start)
            block = fh.read(pos - start)
            if pos == size and block.endswith(b"\n"):
                mark("found")
                return 0
            i = block.rfind(b"\n")
            if i >= 0:
                keep = start + i + 1
                break
            pos = start
        mark("found")
        if keep == size:
            return 0
        fh.truncate(keep)
        fh.flush()
        mark("truncated")
        if fsync:
            os.fsync(fh.fileno())
        mark("synced")
    return size - keep


def read_log(path: str | Path, mapping: Mapping[str, str] | None = None) -> dict[str, np.ndarray]:
    """Read a CSV or Parquet log into column arrays (floats; NaN for empty; text columns as str).

    ``mapping`` maps the file's column names onto schema names (``{"T_sup": "supply_temp_c"}``).
    Columns outside the schema are kept (as text when not numeric) for the callers to ignore.
    Missing required columns raise :class:`LogFormatError` naming them.
    """
    path = Path(path)
    mapping = dict(mapping or {})
    if path.suffix.lower() in (".parquet", ".pq"):
        try:
            import pyarrow.parquet as pq
        except ImportError as exc:  # pragma: no cover - depends on the optional extra
            raise LogFormatError("reading Parquet needs pyarrow: pip install 'hvac-mpc[parquet]'") from exc
        table = pq.read_table(path)
        raw = {mapping.get(c, c): table.column(c).to_pylist() for c in table.column_names}
    else:
        with path.open("r", newline="") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise LogFormatError(f"{path}: empty file, expected a header with {list(REQUIRED_COLUMNS)}")
            names = [mapping.get(h.strip(), h.strip()) for h in header]
            rows = [r for r in reader if len(r) == len(names)]
        raw = {n: [r[i] for r in rows] for i, n in enumerate(names)}
    missing = [c for c in REQUIRED_COLUMNS if c not in raw]
    if missing:
        raise LogFormatError(f"{path}: missing required column(s) {missing}; map other names with a column mapping")
    out: dict[str, np.ndarray] = {}
    for name, values in raw.items():
        if name in TEXT_COLUMNS:
            out[name] = np.array(["" if v is None else str(v) for v in values], dtype=object)
            continue
        try:
            out[name] = np.array([np.nan if v in ("", None) else float(v) for v in values], float)
        except ValueError as exc:
            if name not in COLUMNS:  # a column this reader does not know: kept as text
                out[name] = np.array(["" if v is None else str(v) for v in values], dtype=object)
                continue
            raise LogFormatError(f"{path}: column {name!r} holds a non-numeric value ({exc})") from None
    return out


def write_log(path: str | Path, columns: Mapping[str, Iterable[Any]]) -> None:
    """Write whole column arrays as a new CSV log (overwrites)."""
    path = Path(path)
    names = [c for c in COLUMNS if c in columns]
    unknown = sorted(set(columns) - set(COLUMNS))
    if unknown:
        raise LogFormatError(f"unknown log column(s) {unknown}")
    if path.exists():
        path.unlink()
    data = {c: list(columns[c]) for c in names}
    n = len(next(iter(data.values()))) if data else 0
    with LogWriter(path, names, fsync=False) as w:
        for i in range(n):
            w.write({c: data[c][i] for c in names})
