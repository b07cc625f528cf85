"""The daemon's measurement log: committed rows are never lost, a failing disk never stops control.

* **Append only.** Each row is one ``os.write`` on an ``O_APPEND`` descriptor, then fsync (with
  ``log.fsync``). A torn last row of a crash is cut in place at start
  (:func:`hvac_mpc.models.measurement_log.repair_tail`); the file is never rewritten.
* **Rotation** by size (``log.rotate_bytes``) or UTC day (``log.rotate_daily``): the active file
  is renamed to ``<stem>.<first UTC>.csv`` and a line is appended to ``<stem>.index.csv`` (segment,
  first and last ``time_s`` and ``utc``, rows). A segment that a crash left out of the index is
  added at the next start. The active file keeps the configured name, so readers of one file
  see the newest rows; an existing file with another header is rotated away, not mixed.
* **Disk full or I/O error**: the row is kept in a memory buffer (``log.buffer_rows``, the oldest
  dropped and counted beyond it), the log reports ``degraded`` and retries every
  ``log.retry_s``; a retry first cuts any partial row back to the last committed byte, then
  writes the buffer in order. ``write`` never raises ``OSError``: the control loop goes on.
"""

from __future__ import annotations

import csv
import datetime as _dt
import io
import logging
import os
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from hvac_mpc.models.measurement_log import COLUMNS, LogFormatError, cell_text, repair_tail, schema_columns

LOG = logging.getLogger("hvac_mpc.daemon")
#: The step after the tail repair's own (:data:`~hvac_mpc.models.measurement_log.REPAIR_STEPS`):
#: the log open for appending again.
REOPENED = "reopened"
INDEX_COLUMNS = ("segment", "first_time_s", "last_time_s", "first_utc", "last_utc", "rows")


_datasync = getattr(os, "fdatasync", os.fsync)


def utc_now_iso(now_s: float | None = None) -> str:
    """ISO 8601 UTC with milliseconds, e.g. ``2026-11-23T13:05:00.123Z``."""
    t = _dt.datetime.fromtimestamp(time.time() if now_s is None else now_s, _dt.timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%M:%S.") + f"{t.microsecond // 1000:03d}Z"


def _csv_line(values: Iterable[str]) -> bytes:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(list(values))
    return buf.getvalue().encode("utf-8")


def _row_fields(line: bytes, names: list[str]) -> dict[str, str] | None:
    try:
        row = next(csv.reader([line.decode("utf-8")]))
    except (StopIteration, csv.Error, UnicodeDecodeError):
        return None
    return dict(zip(names, row)) if len(row) == len(names) else None


def _first_line(path: Path) -> bytes:
    with path.open("rb") as fh:
        return fh.readline()


def _last_line(path: Path, chunk: int = 65536) -> bytes:
    """The last complete line of a file (reads only its tail)."""
    with path.open("rb") as fh:
        size = fh.seek(0, os.SEEK_END)
        fh.seek(max(0, size - chunk))
        tail = fh.read()
    lines = tail.rstrip(b"\n").split(b"\n")
    return lines[-1] if lines else b""


class DurableLog:
    """Append-only CSV log with in-place tail repair, rotation, an index and a degraded mode.

    ``inject``: called before every physical write (fault injection: it may raise ``OSError``).
    ``repair_step``: called with each step of the tail repair at start (the names of
    :data:`~hvac_mpc.models.measurement_log.REPAIR_STEPS`, then ``reopened`` once the file is open
    for appending), so a test can kill the process exactly between two steps.
    """

    def __init__(self, path: str | Path, columns: Iterable[str] = COLUMNS, *, fsync: bool = True,
                 rotate_bytes: int = 0, rotate_daily: bool = False, buffer_rows: int = 86400,
                 retry_s: float = 5.0, wall_clock: Callable[[], float] = time.time,
                 inject: Callable[[], None] | None = None, repair_step: Callable[[str], None] | None = None):
        self.path = Path(path)
        self.columns = schema_columns(columns)
        self.fsync = fsync
        self.rotate_bytes = rotate_bytes
        self.rotate_daily = rotate_daily
        self.retry_s = retry_s
        self.wall_clock = wall_clock
        self.inject = inject
        self.repair_step = repair_step
        self.index_path = self.path.with_name(self.path.stem + ".index.csv")
        self._buffer: deque[tuple[bytes, dict[str, str]]] = deque(maxlen=buffer_rows)
        self.counters = {"rows_written": 0, "rows_dropped": 0, "write_errors": 0, "rotations": 0,
                         "tail_bytes_repaired": 0, "degraded_episodes": 0}
        self.state = "ok"
        self.last_error = ""
        self._next_retry = 0.0
        self._fd = -1
        self._committed = 0
        self._first: dict[str, str] | None = None
        self._last: dict[str, str] | None = None
        self._open()

    # ------------------------------------------------------------------ opening and rotation
    def _open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._reconcile_index()
        if self.path.exists() and self.path.stat().st_size > 0:
            self.counters["tail_bytes_repaired"] += repair_tail(self.path, fsync=self.fsync, step=self.repair_step)
        header = _first_line(self.path) if self.path.exists() else b""
        if header and header.rstrip(b"\r\n") != _csv_line(self.columns).rstrip(b"\n"):
            LOG.warning("log %s has another header: kept as a segment, a new file begins", self.path)
            self._rotate_file()
            header = b""
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._committed = os.fstat(self._fd).st_size
        if self.repair_step is not None:
            self.repair_step(REOPENED)
        if not header:
            self._physical_write(_csv_line(self.columns))
        else:
            self._first = _row_fields(self._second_line(), list(self.columns))
            self._last = _row_fields(_last_line(self.path), list(self.columns))
            if self._last is not None and self._last.get("time_s") == "time_s":
                self._last = None

    def _second_line(self) -> bytes:
        with self.path.open("rb") as fh:
            fh.readline()
            return fh.readline().rstrip(b"\n")

    def _segment_name(self) -> Path:
        stamp = (self._first or {}).get("utc") or utc_now_iso(self.wall_clock())
        stamp = stamp.replace(":", "").replace("-", "").replace(".", "")[:15] + "Z"
        for n in range(1000):
            name = self.path.with_name(f"{self.path.stem}.{stamp}{'' if n == 0 else f'-{n}'}{self.path.suffix}")
            if not name.exists():
                return name
        raise OSError(f"no free segment name for {self.path}")

    def _rotate_file(self) -> None:
        """Rename the active file to a segment and index it (fsync of the directory between)."""
        target = self._segment_name()
        os.rename(self.path, target)
        self._fsync_dir()
        self._index_segment(target)
        self.counters["rotations"] += 1
        self._first = self._last = None

    def _rotate(self) -> None:
        os.close(self._fd)
        self._fd = -1
        self._rotate_file()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._committed = 0
        self._physical_write(_csv_line(self.columns))

    def _fsync_dir(self) -> None:
        if not self.fsync:
            return
        fd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def _index_segment(self, segment: Path) -> None:
        names = _first_line(segment).decode("utf-8", "replace").rstrip("\r\n").split(",")
        with segment.open("rb") as fh:
            fh.readline()
            first = _row_fields(fh.readline().rstrip(b"\n"), names) or {}
            rows = 1 + sum(1 for _ in fh) if first else 0
        last = _row_fields(_last_line(segment), names) or {}
        line = _csv_line([segment.name, first.get("time_s", ""), last.get("time_s", ""), first.get("utc", ""),
                          last.get("utc", ""), str(rows)])
        new = not self.index_path.exists() or self.index_path.stat().st_size == 0
        fd = os.open(self.index_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, (_csv_line(INDEX_COLUMNS) if new else b"") + line)
            if self.fsync:
                os.fsync(fd)
        finally:
            os.close(fd)

    def _reconcile_index(self) -> None:
        """Index the segments a crash between rename and index line left out."""
        listed = {r["segment"] for r in self.segments()}
        pattern = f"{self.path.stem}.*{self.path.suffix}"
        for seg in sorted(self.path.parent.glob(pattern)):
            if seg.name not in listed and seg != self.index_path and seg != self.path:
                repair_tail(seg, fsync=self.fsync)
                self._index_segment(seg)

    def segments(self) -> list[dict[str, str]]:
        """The index: one dict per rotated segment, oldest first."""
        if not self.index_path.exists():
            return []
        with self.index_path.open(newline="") as fh:
            return [r for r in csv.DictReader(fh) if r.get("segment")]

    @property
    def last_time_s(self) -> float | None:
        """``time_s`` of the last committed row (the active file, else the newest segment)."""
        for row in ([self._last] if self._last else []) + [
                {"time_s": s["last_time_s"]} for s in reversed(self.segments())]:
            try:
                return float(row["time_s"])
            except (KeyError, TypeError, ValueError):
                continue
        return None

    # ------------------------------------------------------------------ writing
    def write(self, row: Mapping[str, Any]) -> bool:
        """Log one sample; True when it (and any buffered rows) reached the file. Never raises OSError."""
        unknown = sorted(set(row) - set(self.columns))
        if unknown:
            raise LogFormatError(f"unknown log column(s) {unknown}")
        cells = [cell_text(row.get(c)) for c in self.columns]
        entry = (_csv_line(cells), dict(zip(self.columns, cells)))
        if len(self._buffer) == self._buffer.maxlen:
            self.counters["rows_dropped"] += 1
        self._buffer.append(entry)
        if self.state != "ok" and self.wall_clock() < self._next_retry:
            return False
        return self._drain()

    def _drain(self) -> bool:
        try:
            if self.state != "ok":
                self._cut_back()
            while self._buffer:
                line, fields_ = self._buffer[0]
                self._maybe_rotate(fields_)
                self._physical_write(line)
                self._buffer.popleft()
                self._first = self._first or fields_
                self._last = fields_
                self.counters["rows_written"] += 1
        except OSError as exc:
            self.counters["write_errors"] += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            self._next_retry = self.wall_clock() + self.retry_s
            if self.state == "ok":
                self.counters["degraded_episodes"] += 1
                LOG.error("log %s degraded (%s): rows buffered in memory (up to %d)", self.path, self.last_error,
                          self._buffer.maxlen)
            self.state = "degraded"
            return False
        if self.state != "ok":
            LOG.warning("log %s writing again; buffered rows written", self.path)
        self.state = "ok"
        return True

    def _cut_back(self) -> None:
        """Before a retry: remove any partial row a failed write left (back to the committed size)."""
        if self._fd < 0:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        if os.fstat(self._fd).st_size != self._committed:
            os.ftruncate(self._fd, self._committed)

    def _maybe_rotate(self, fields_: Mapping[str, str]) -> None:
        if self._first is None:
            return
        if self.rotate_bytes and self._committed >= self.rotate_bytes:
            self._rotate()
        elif self.rotate_daily and fields_.get("utc", "")[:10] != (self._first.get("utc") or "")[:10]:
            self._rotate()

    def _physical_write(self, data: bytes) -> None:
        if self.inject is not None:
            self.inject()
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
        if self.fsync:
            _datasync(self._fd)  # the file size is data here: an appended row survives a power loss
        self._committed += len(data)

    # ------------------------------------------------------------------ status and closing
    def status(self) -> dict[str, Any]:
        return {"state": self.state, "buffered_rows": len(self._buffer), "last_error": self.last_error,
                "path": str(self.path), **self.counters}

    def close(self) -> None:
        """Write what is buffered (one last attempt), then close."""
        if self._buffer:
            self._next_retry = 0.0
            self._drain()
            if self._buffer:
                LOG.error("log %s closed with %d rows unwritten (%s)", self.path, len(self._buffer), self.last_error)
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> "DurableLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
