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
import subprocess
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import casadi as ca

from .codegen import CFLAGS, SWITCH_ENV, compiler, fcntl, generate_into, library

#: Calls of one function run interpreted before its build starts, at the next one. 0: a structure is built at its
#: first use, for the next process above all (an identification runs most structures once to three times; the
#: builds beside an identification from an empty cache cost it 7 % of its time, docs/identification.md "Runs as
#: generated C").
AFTER_CALLS = 0
#: Environment variable switching these builds on (``1``) or off (``0``) whatever ``HVAC_MPC_CODEGEN`` says
#: (a lab may keep the MPC's off, 5-30 s each, and want these, about a second each; the suite keeps both off).
RUN_BUILDS_ENV = "HVAC_MPC_RUN_BUILDS"
#: A failed build's note (``NAME.failed``) older than this, s, no longer stops the structure being built again.
STALE_S = 900.0
#: Builds under way in one cache folder at most, one slot each (each compiler takes 60-80 MB, and on a machine whose
#: cores are busy the lowest priority does not stop dozens of them from sharing a quarter of the cores): a function
#: asked for while every slot is taken stays interpreted until a later call finds one free. Slot ``k`` is the lock
#: file ``.slot_k.lock``, held (``flock``) by the build for as long as it runs, whatever ends it, and the folder
#: ``.slot_k`` it builds in.
MAX_BUILDS = 2
#: Niceness of a detached compiler (0: none).
NICENESS = 19
#: The build: compile, move the shared object into place, or keep the last messages in the failure note; then clear
#: the slot's folder. Arguments after the script: the compiler's whole command line.
_BUILD = ('"$@" >/dev/null 2>"$HVAC_DIR/stderr" && mv -f "$HVAC_OUT" "$HVAC_LIB" 2>>"$HVAC_DIR/stderr" '
          '|| tail -c 2000 "$HVAC_DIR/stderr" >"$HVAC_FAILED"; rm -rf "$HVAC_DIR"')
#: The same detached from the caller, holding the slot's lock (inherited) until it ends: a process group of its own, so
#: a signal to the caller's group, as a time limit or a cancelled job sends it, does not end it half-way; in the
#: caller's session, because with the kernel's automatic grouping by session a session of its own would share the
#: cores with the caller as an equal whatever its niceness (an identification from an empty cache took 66 s instead
#: of 47-54).
_DETACHED = f"({_BUILD}) </dev/null >/dev/null 2>&1 &"


def enabled() -> bool:
    """True when builds may run: ``HVAC_MPC_RUN_BUILDS`` if set, else not ``HVAC_MPC_CODEGEN=0``; and a C compiler,
    ``sh`` and file locks (``fcntl``) are there."""
    switch = os.environ.get(RUN_BUILDS_ENV)
    on = switch != "0" if switch is not None else os.environ.get(SWITCH_ENV, "1") != "0"
    return on and fcntl is not None and compiler() is not None and shutil.which("sh") is not None


@dataclass
class _Entry:
    """One function's state: its shared object's path, the calls counted, the loaded C form once there is one,
    ``done`` once nothing more is to be tried (loaded, or its build failed)."""

    fn: ca.Function
    lib: Path
    calls: int = 0
    started: bool = False
    done: bool = False
    compiled: ca.Function | None = None


class BackgroundBuilds:
    """The builds of one piece of work (an identification's :class:`~hvac_mpc.identification.fitting.Fitter`).

    :meth:`function` gives a function's C form where it is built, else the function itself. ``after``: calls run
    interpreted before a build starts (0: it starts at the first). ``wait``: the caller waits for each build (tests
    compare both forms with it). ``outcomes`` says, per shared object's name: ``"cached"`` (found), ``"built"``
    (started here and loaded), ``"building"``, ``"counted"`` (not started: too early or no free slot), ``"failed:
    NOTE"`` (the compiler failed; its messages in the note beside the cache's shared objects) or ``"interpreted:
    why"`` (the shared object did not load)."""

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
            entry = self._entries[id(fn)] = _Entry(fn, library(fn))
        if not entry.done:
            self._advance(entry)
        return entry.compiled if entry.compiled is not None else fn

    def summary(self) -> dict[str, int]:
        """How many functions ended in each outcome (``cached``, ``built``, ``building``, ``counted``, ...)."""
        return dict(Counter(v.split(":")[0] for v in self.outcomes.values()))

    def _advance(self, entry: _Entry) -> None:
        """Load ``entry``'s shared object if it exists, else count the call and start its build when due."""
        tag = entry.lib.stem
        if entry.lib.exists():
            return self._load(entry)
        entry.calls += 1
        if entry.calls <= self.after:
            self.outcomes.setdefault(tag, "counted")
            return
        if _failed(entry.lib):
            return self._fail(entry)
        if entry.started and not self.wait:  # under way, unless it ended without a result (killed): again later
            if not _building(entry.lib):
                entry.started = False
                self.outcomes[tag] = "counted"
            return
        entry.started = _start(entry.fn, entry.lib, self.wait)
        self.outcomes[tag] = "building" if entry.started else "counted"
        if entry.lib.exists():
            self._load(entry)
        elif self.wait and entry.started:
            self._fail(entry)

    def _load(self, entry: _Entry) -> None:
        """Load ``entry``'s shared object: nothing more is tried for it, whether it loads or not."""
        entry.done = True
        try:
            entry.compiled = ca.external(entry.fn.name(), str(entry.lib))
        except Exception as exc:  # noqa: BLE001 - a broken file: the interpreter gives the same values
            self.outcomes[entry.lib.stem] = f"interpreted: {type(exc).__name__}: {str(exc)[:200]}"
            return
        self.outcomes[entry.lib.stem] = "built" if entry.started else "cached"

    def _fail(self, entry: _Entry) -> None:
        """``entry``'s build failed: nothing more is tried in this piece of work."""
        entry.done = True
        self.outcomes[entry.lib.stem] = f"failed: {_note(entry.lib)}"


def _note(lib: Path) -> Path:
    """The failure note of ``lib``'s build (the compiler's last messages), beside it."""
    return lib.with_name(f"{lib.stem}.failed")


def _failed(lib: Path) -> bool:
    """True while a note says ``lib``'s last build failed (for :data:`STALE_S`; then it is built again)."""
    try:
        return time.time() - _note(lib).stat().st_mtime < STALE_S
    except OSError:
        return False


def _start(fn: ca.Function, lib: Path, wait: bool) -> bool:
    """Generate ``fn``'s C in a free build slot of ``lib``'s cache folder and start its build, detached (``wait``: run
    it to the end). False when ``lib`` is being built in another slot, when no slot is free, or on an error."""
    cache = lib.parent
    try:
        cache.mkdir(parents=True, exist_ok=True)
        if _building(lib):
            return False
        claimed = _claim(cache)
    except OSError:
        return False
    if claimed is None:
        return False
    slot, lock = claimed
    try:
        (slot / "target").write_text(lib.name)
        source = generate_into(fn, f"{lib.stem}.c", slot)
        out = slot / lib.name
        nice = ["nice", "-n", str(NICENESS)] if NICENESS and shutil.which("nice") and not wait else []
        command = [*nice, compiler(), *CFLAGS, str(source), "-o", str(out), "-lm"]
        env = {**os.environ, "HVAC_OUT": str(out), "HVAC_LIB": str(lib), "HVAC_DIR": str(slot),
               "HVAC_FAILED": str(_note(lib))}
        subprocess.run(["sh", "-c", _BUILD if wait else _DETACHED, "sh", *command], env=env, check=False,
                       stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       pass_fds=() if wait else (lock,), process_group=None if wait else 0)
    except Exception:  # noqa: BLE001 - nothing built (no compiler, no process): the interpreter goes on
        shutil.rmtree(slot, ignore_errors=True)
        return False
    finally:
        os.close(lock)  # a detached build holds its own copy until it ends
    return True


def _building(lib: Path) -> bool:
    """True while a slot of ``lib``'s cache folder holds a build of ``lib``."""
    return any(_target(k, lib.parent) == lib.name and _held(k, lib.parent) for k in range(MAX_BUILDS))


def _slot(k: int, cache: Path) -> tuple[Path, Path]:
    """Slot ``k``'s folder and lock file."""
    return cache / f".slot_{k}", cache / f".slot_{k}.lock"


def _target(k: int, cache: Path) -> str | None:
    """The shared object slot ``k`` builds or last built (None: none, or being set up or cleared)."""
    try:
        return (_slot(k, cache)[0] / "target").read_text()
    except OSError:
        return None


def _lock(k: int, cache: Path) -> int | None:
    """Slot ``k``'s lock, taken (a file descriptor holding it), or None while a build holds it."""
    fd = os.open(_slot(k, cache)[1], os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def _held(k: int, cache: Path) -> bool:
    """True while a build holds slot ``k``."""
    fd = _lock(k, cache)
    if fd is None:
        return True
    os.close(fd)
    return False


def _claim(cache: Path) -> tuple[Path, int] | None:
    """A free slot of ``cache`` (its folder made empty, what a killed build left removed) and its lock's descriptor,
    or None while every slot holds a build."""
    for k in range(MAX_BUILDS):
        fd = _lock(k, cache)
        if fd is None:
            continue
        folder = _slot(k, cache)[0]
        try:
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
        except OSError:
            os.close(fd)
            continue
        return folder, fd
    return None
