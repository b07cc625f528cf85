"""Generated C built beside the caller: a function runs in CasADi's interpreter until its build is done, then as C.

For work that runs a few structures over long arrays a few times each (identification's whole-log runs,
docs/identification.md "Runs as generated C"), where one build (0.3-1.7 s at :data:`.codegen.CFLAGS`) costs more
than one run (0.1-0.4 s on a 2 h log): a function already in the cache of :mod:`.codegen` is loaded on first use;
one that is not runs interpreted and is built from its first use on (:data:`AFTER_CALLS`), by a compiler process of
the lowest priority (``nice 19``) that the caller does not wait for, detached so that a build outlives the process
that started it and serves the next one. The shared object is moved into place atomically under the same name
:func:`.codegen.compiled` gives it, so the MPC's cache and this one are the same folder.

The generated code performs the interpreter's operations in its order (:data:`.codegen.CFLAGS`: no fast-math, no
fused multiply-adds), so a run gives the same values to the bit before and after the switch; the identification's
results do not depend on when a build finishes (tests/test_codegen_background.py).

Switched off by ``HVAC_MPC_CODEGEN=0`` unless ``HVAC_MPC_RUN_BUILDS=1`` (:func:`enabled`), and wherever there is
no C compiler or POSIX shell.
"""

from __future__ import annotations

import os
import shutil
from collections import Counter
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import casadi as ca

from .codegen import CFLAGS, SWITCH_ENV, cache_dir, compiler, structure_key

#: Calls of one function run interpreted before its build starts, at the next one. 0: a structure is built at its
#: first use, for the next process above all (an identification runs most structures once to three times; the
#: builds beside an identification from an empty cache cost it 7 % of its time, docs/identification.md "Runs as
#: generated C").
AFTER_CALLS = 0
#: Environment variable switching these builds on (``1``) or off (``0``) whatever ``HVAC_MPC_CODEGEN`` says
#: (the suite turns the MPC's builds off, 5-30 s each, and keeps these, about a second each).
RUN_BUILDS_ENV = "HVAC_MPC_RUN_BUILDS"
#: A build folder older than this, s, is taken to be a build that was killed, and is started again.
STALE_S = 900.0
#: Builds under way in one cache folder at most (each compiler takes 60-80 MB; on a machine whose cores are busy the
#: lowest priority does not stop dozens of them from sharing a quarter of the cores): a function asked for while
#: this many are under way stays interpreted until a later call finds a place.
MAX_BUILDS = 2
#: The detached build: compile (at the lowest priority, where ``nice`` exists), move the shared object into place,
#: remove the build folder whatever happened. Arguments after the script: the compiler's whole command line.
_SCRIPT = '"$@" >/dev/null 2>&1 && mv -f "$HVAC_OUT" "$HVAC_LIB"; rm -rf "$HVAC_DIR"'


def enabled() -> bool:
    """True when builds may run: ``HVAC_MPC_RUN_BUILDS`` if set, else not ``HVAC_MPC_CODEGEN=0``; and a C compiler and
    ``sh`` are found."""
    switch = os.environ.get(RUN_BUILDS_ENV)
    on = switch != "0" if switch is not None else os.environ.get(SWITCH_ENV, "1") != "0"
    return on and compiler() is not None and shutil.which("sh") is not None


@dataclass
class _Entry:
    """One function's state: its shared object's path, the calls counted, the loaded C form once there is one."""

    fn: ca.Function
    lib: Path
    calls: int = 0
    started: bool = False
    compiled: ca.Function | None = None


class BackgroundBuilds:
    """The builds of one piece of work (an identification's :class:`~hvac_mpc.identification.fitting.Fitter`).

    :meth:`function` gives a function's C form where it is built, else the function itself. ``after``: calls run
    interpreted before a build starts (0: it starts at the first). ``wait``: the caller waits for each build (tests compare both forms with it).
    ``outcomes`` says, per function name and key, ``"cached"`` (found), ``"built"`` (started here and loaded),
    ``"building"`` or ``"counted"`` (not built yet)."""

    def __init__(self, after: int = AFTER_CALLS, wait: bool = False, on: bool | None = None):
        self.after = int(after)
        self.wait = bool(wait)
        self.on = enabled() if on is None else bool(on)
        self.outcomes: dict[str, str] = {}
        self._entries: dict[int, _Entry] = {}  # by id of the function (the entry holds it, so the id is not reused)

    def function(self, fn: ca.Function) -> ca.Function:
        """``fn``'s C form if its shared object is there, else ``fn`` (the call counted, a build started after
        ``after`` of them); the same values either way."""
        if not self.on:
            return fn
        entry = self._entries.get(id(fn))
        if entry is None:
            entry = self._entries[id(fn)] = _Entry(fn, cache_dir() / f"{fn.name()}_{structure_key(fn)}.so")
        if entry.compiled is None:
            self._advance(entry)
        return entry.compiled if entry.compiled is not None else fn

    def summary(self) -> dict[str, int]:
        """How many functions ended in each outcome (``cached``, ``built``, ``building``, ``counted``, ...)."""
        return dict(Counter(v.split(":")[0] for v in self.outcomes.values()))

    def _advance(self, entry: _Entry) -> None:
        """Load ``entry``'s shared object if it exists, else count the call and start its build when due."""
        tag = entry.lib.stem
        if not entry.lib.exists():
            entry.calls += 1
            if entry.started or entry.calls <= self.after:
                self.outcomes.setdefault(tag, "counted")
                return
            entry.started = _start(entry.fn, entry.lib, self.wait)
            self.outcomes[tag] = "building" if entry.started else "counted"
            if not entry.lib.exists():
                return
        try:
            entry.compiled = ca.external(entry.fn.name(), str(entry.lib))
        except Exception as exc:  # noqa: BLE001 - a broken file: the interpreter gives the same values
            self.outcomes[tag] = f"interpreted: {type(exc).__name__}"
            entry.started = True
            return
        self.outcomes[tag] = "built" if entry.started else "cached"


def _start(fn: ca.Function, lib: Path, wait: bool) -> bool:
    """Generate ``fn``'s C in a build folder claimed beside ``lib`` and start its detached build (``wait``: run it to
    the end). False when another process's build of ``lib`` is under way or the folder cannot be made."""
    folder = lib.parent / f".build_{lib.stem}"
    try:
        lib.parent.mkdir(parents=True, exist_ok=True)
        if _under_way(lib.parent) >= MAX_BUILDS:
            return False
        _claim(folder)
    except OSError:
        return False
    try:
        generator = ca.CodeGenerator(f"{lib.stem}.c", {"with_header": False})
        generator.add(fn)
        source = Path(generator.generate(f"{folder}{os.sep}"))  # into the folder, the working directory left alone
    except Exception:  # noqa: BLE001 - nothing built: the interpreter goes on
        shutil.rmtree(folder, ignore_errors=True)
        return False
    out = folder / lib.name
    nice = ["nice", "-n", "19"] if shutil.which("nice") and not wait else []
    command = [*nice, compiler(), *CFLAGS, str(source), "-o", str(out), "-lm"]
    env = {**os.environ, "HVAC_OUT": str(out), "HVAC_LIB": str(lib), "HVAC_DIR": str(folder)}
    script = _SCRIPT if wait else f"({_SCRIPT}) </dev/null >/dev/null 2>&1 &"
    subprocess.run(["sh", "-c", script, "sh", *command], env=env, check=False, stdin=subprocess.DEVNULL)
    return True


def _under_way(cache: Path) -> int:
    """Builds under way in ``cache``: its build folders younger than :data:`STALE_S`."""
    now = time.time()
    count = 0
    for folder in cache.glob(".build_*"):
        try:
            count += now - folder.stat().st_mtime < STALE_S
        except OSError:  # finished meanwhile
            pass
    return count


def _claim(folder: Path) -> None:
    """Make ``folder`` (this process's claim on a build); one left by a build killed :data:`STALE_S` ago is taken
    over. Raises FileExistsError while another build holds it."""
    try:
        folder.mkdir()
    except FileExistsError:
        if time.time() - folder.stat().st_mtime < STALE_S:
            raise
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
