"""SIGKILL during the tail repair of a big daemon log: exactly at each step, and at random moments.

A torn last row is cut in place when the log is opened (:class:`hvac_mpc.daemon.log_writer.DurableLog`,
the code the daemon runs at start): find the last newline, truncate there, fsync, reopen for
appending (:data:`STEPS`). The repair takes a few milliseconds, so a kill at a random moment of
the daemon's start almost never lands inside it. Here a child process opens the log the way the
daemon does and reports every step through a pipe (with the monotonic clock, shared by all
processes); with a stop step it stops itself (SIGSTOP) there and is killed (SIGKILL) exactly at
that point. Then the log is opened again (the restart: the same repair) and every committed byte
is compared with its digest from before the first kill. Random kills, timed from the child's
first step, count how many landed inside the repair (between its first step and the reopen).

The children are forked from one process that imported the log code once (:class:`Forker`), so
a trial costs milliseconds, not an interpreter start. ``python -m
hvac_mpc.benchmarks.repair_kills --size-mb 400`` prints the counts.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from hvac_mpc.daemon.log_writer import REOPENED, DurableLog
from hvac_mpc.models.measurement_log import COLUMNS, REPAIR_STEPS

#: Every step boundary a kill is aimed at, in order.
STEPS = (*REPAIR_STEPS, REOPENED)
TORN_ROW = b"123456789.0,120.0,0.0,1"
#: The committed bytes compared after every restart (all of them once at the end).
TAIL_CHECK_BYTES = 4 * 2**20

_FORKER = r"""
import os, signal, sys, time
from hvac_mpc.daemon.log_writer import DurableLog

def trial(path, stop_at, delay_s):
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the process killed: opens the log as the daemon's start does
        os.close(r)
        def step(name):
            os.write(w, f"{name}@{time.monotonic():.6f}\n".encode())
            if name == stop_at:
                os.kill(os.getpid(), signal.SIGSTOP)
        try:
            DurableLog(path, repair_step=step).close()
        finally:
            os._exit(0)
    os.close(w)
    steps = os.fdopen(r, "rb")
    first = b""
    if stop_at:
        _, status = os.waitpid(pid, os.WUNTRACED)
        if not os.WIFSTOPPED(status):
            return "error: ended before " + stop_at
        os.kill(pid, signal.SIGKILL)
    elif delay_s >= 0:
        first = steps.readline()  # the repair's first step
        time.sleep(delay_s)
        os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    return " ".join((first + steps.read()).decode().split())

print("ready", flush=True)
for line in sys.stdin:
    path, stop_at, delay_s = line.rstrip("\n").split("\t")
    print(trial(path, stop_at, float(delay_s)), flush=True)
"""


class Forker:
    """A process that has imported the log code once and forks one child per trial: the child
    opens the log as the daemon's start does (tail repair, reopen), reporting each step; the
    forker stops it at a step (the child's own SIGSTOP) or after a delay and SIGKILLs it."""

    def __init__(self):
        env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
        self.proc = subprocess.Popen([sys.executable, "-c", _FORKER], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, env=env, text=True)
        if self.proc.stdout.readline().strip() != "ready":
            raise RuntimeError("the forker did not start")

    def trial(self, log: Path, stop_at: str = "", delay_s: float = -1.0) -> list[tuple[str, float]]:
        """One child on ``log``: killed at ``stop_at``, else ``delay_s`` after the repair's first
        step, else (both unset) run through; the (step, monotonic time) pairs it reported."""
        self.proc.stdin.write(f"{log}\t{stop_at}\t{delay_s}\n")
        self.proc.stdin.flush()
        reply = self.proc.stdout.readline().strip()
        if reply.startswith("error") or not reply:
            raise RuntimeError(f"repair trial: {reply or 'forker died'}")
        return [(name, float(t)) for name, t in (item.split("@") for item in reply.split())]

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(10)


def write_big_log(path: Path, size_mb: float, chunk_rows: int = 20000) -> int:
    """A daemon log of about ``size_mb`` MB (header, rows of consecutive ``time_s``), fsynced as
    the daemon's own rows are; returns its size in bytes. Fast: rows are formatted in chunks."""
    header = (",".join(COLUMNS) + "\n").encode()
    cells = ["{t}", "120.0", "0.0", "100.0", "100.0", "100.0", "100.0", "25.0", "0.03", "20.0"]
    cells += [""] * (len(COLUMNS) - len(cells) - 3) + ["control", "baseline", "2026-11-23T10:00:00.000Z"]
    row = ",".join(cells) + "\n"
    target = int(size_mb * 2**20)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        written = os.write(fd, header)
        k = 0
        while written < target:
            block = "".join(row.format(t=float(i)) for i in range(k, k + chunk_rows)).encode()
            written += os.write(fd, block)
            k += chunk_rows
        os.fsync(fd)
    finally:
        os.close(fd)
    return written


def prefix_digest(path: Path, n: int, start: int = 0) -> str:
    """SHA-1 of the bytes ``start`` to ``n`` of a file."""
    h = hashlib.sha1()
    with path.open("rb") as fh:
        fh.seek(start)
        left = n - start
        while left:
            block = fh.read(min(left, 1 << 22))
            if not block:
                break
            h.update(block)
            left -= len(block)
    return h.hexdigest()


@dataclass
class KillReport:
    """What :func:`kill_during_repair` did and found."""

    size_bytes: int = 0
    committed_bytes: int = 0
    step_kills: dict[str, int] = field(default_factory=dict)  # step -> kills exactly there
    random_kills: int = 0
    random_in_repair: int = 0  # random kills that landed between the first step and the reopen
    repair_window_ms: float = 0.0  # first step to reopen, median of three uninterrupted starts
    restarts: int = 0
    lost: list[str] = field(default_factory=list)  # committed bytes changed: must stay empty

    def summary(self) -> str:
        return (f"{sum(self.step_kills.values())} kills at the repair's steps ({', '.join(self.step_kills)}) and "
                f"{self.random_kills} at random moments ({self.random_in_repair} inside the repair, which "
                f"takes {self.repair_window_ms:.1f} ms) on a {self.size_bytes / 2**20:.0f} MB log; "
                f"{self.restarts} restarts, committed bytes changed {len(self.lost)} times")


def kill_during_repair(log: Path, size_mb: float = 300.0, rounds: int = 1, random_kills: int = 8,
                       seed: int = 0) -> KillReport:
    """Kill a process opening a big log with a torn tail at each repair step (``rounds`` times)
    and at ``random_kills`` random moments; after each kill, restart (open the log again) and
    check that the committed bytes are there: after each restart the size, the file (inode) and
    the last 4 MB, at the end all of them (a change in any round would persist to the end). The
    log is deleted at the end."""
    import random

    rng = random.Random(seed)
    rep = KillReport()
    forker = Forker()
    try:
        rep.committed_bytes = write_big_log(log, size_mb)
        tail = max(0, rep.committed_bytes - TAIL_CHECK_BYTES)
        digests = (prefix_digest(log, rep.committed_bytes), prefix_digest(log, rep.committed_bytes, tail))
        inode = log.stat().st_ino
        plan = ["time"] * 3 + [s for _ in range(rounds) for s in STEPS] + ["random"] * random_kills
        windows = []
        for aim in plan:
            with log.open("ab") as fh:  # the crash's torn row
                fh.write(TORN_ROW)
            if aim == "time":  # uninterrupted starts: how long the repair window is (the median of 3)
                steps = dict(forker.trial(log))
                windows.append((steps[REOPENED] - steps["begin"]) * 1e3)
                rep.repair_window_ms = sorted(windows)[len(windows) // 2]
            elif aim == "random":  # the kill lands up to one window after the child's first step
                steps = dict(forker.trial(log, delay_s=rng.uniform(0.0, rep.repair_window_ms / 1e3)))
                rep.random_kills += 1
                rep.random_in_repair += int(REOPENED not in steps)
            else:
                reported = [name for name, _ in forker.trial(log, stop_at=aim)]
                if reported[-1:] != [aim]:
                    raise RuntimeError(f"killed after {reported}, aimed at {aim!r}")
                rep.step_kills[aim] = rep.step_kills.get(aim, 0) + 1
            _check(log, rep, f"after the kill at {aim}")
            DurableLog(log).close()  # the restart: the daemon's start repairs what the kill left
            rep.restarts += 1
            _check(log, rep, f"after the restart from {aim}", inode, (tail, digests[1]))
        rep.size_bytes = log.stat().st_size
        _check(log, rep, "at the end", inode, (0, digests[0]))
    finally:
        forker.close()
        log.unlink(missing_ok=True)
    return rep


def _check(log: Path, rep: KillReport, when: str, inode: int | None = None,
           digest: tuple[int, str] | None = None) -> None:
    """After a kill: nothing committed cut. After a restart: exactly the committed bytes, in the
    same file, ``digest`` = (start, SHA-1) of the committed bytes from start unchanged."""
    st = log.stat()
    if st.st_size < rep.committed_bytes or (inode is not None and st.st_size != rep.committed_bytes):
        rep.lost.append(f"{when}: size {st.st_size}, committed {rep.committed_bytes}")
    elif inode is not None and st.st_ino != inode:
        rep.lost.append(f"{when}: the log was replaced (inode {st.st_ino}, was {inode})")
    elif digest is not None and prefix_digest(log, rep.committed_bytes, digest[0]) != digest[1]:
        rep.lost.append(f"{when}: committed bytes changed")


def main(argv: list[str] | None = None) -> int:
    import argparse
    import tempfile

    ap = argparse.ArgumentParser(description="SIGKILL during the tail repair of a big daemon log")
    ap.add_argument("--size-mb", type=float, default=300.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--random-kills", type=int, default=10)
    ap.add_argument("--dir", default=None, help="where the log is written (default: a temporary directory)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        rep = kill_during_repair(Path(d) / "big.csv", args.size_mb, args.rounds, args.random_kills)
    print(rep.summary())
    return 0 if not rep.lost else 1


if __name__ == "__main__":
    raise SystemExit(main())
