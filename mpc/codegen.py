"""C code generation of CasADi functions, compiled once per structure and cached on disk.

:func:`compiled` turns a CasADi function into the same function evaluated by generated C
(``Function.generate``, ``gcc -O3 -march=native``, :data:`CFLAGS`, loaded with ``casadi.external``). The
shared object is cached under :func:`cache_dir` and named by a hash of the function's serialised form (its
whole expression graph, so every model parameter and setting it embeds), the CasADi version,
the compiler flags, the machine and its processor: a changed model or setting gives another hash and a new
build, an unchanged one loads in milliseconds. Weights, bounds and references are inputs of
the functions, not part of the hash.

Without a working compiler (or with ``HVAC_MPC_CODEGEN=0``) the function is returned as it
is and evaluated by CasADi's interpreter: the same expression graph, so the same results up to
floating-point round-off. :class:`CodegenReport` says which happened and how long building took.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca

try:
    import fcntl
except ImportError:  # pragma: no cover - no file locks (Windows)
    fcntl = None

#: Compiler flags of the generated code (no fast-math and no fused multiply-adds, where a processor has them:
#: results stay those of the interpreter). Built for this machine's processor (``-march=native``, the processor in
#: the cache key) at ``-O3``: the QP data's generated call 0.89x and the estimator's update 0.78x the time at ``-O2``
#: with the same values to the bit (docs/architecture.md, 'The estimator's update and the glue, trimmed').
CFLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-fPIC", "-shared")
#: Environment variable naming the cache folder (default ``~/.cache/hvac-mpc``).
CACHE_ENV = "HVAC_MPC_CACHE_DIR"
#: Environment variable switching code generation off (``0``) for a whole process.
SWITCH_ENV = "HVAC_MPC_CODEGEN"


@dataclass
class CodegenReport:
    """What :func:`compiled` did for each function: ``"cached"``, ``"built"`` or ``"interpreted: why"``."""

    outcomes: dict[str, str] = field(default_factory=dict)
    build_time_s: float = 0.0
    #: the shared object each generated function was loaded from (name -> path): what a function calling it is
    #: linked against (:func:`compiled` with ``link``)
    libraries: dict[str, Path] = field(default_factory=dict)

    @property
    def active(self) -> bool:
        """True when every function runs as generated C."""
        return bool(self.outcomes) and all(not v.startswith("interpreted") for v in self.outcomes.values())


def cache_dir() -> Path:
    """Folder of the compiled functions: ``$HVAC_MPC_CACHE_DIR``, else ``$XDG_CACHE_HOME/hvac-mpc``,
    else ``~/.cache/hvac-mpc``."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "hvac-mpc"


def structure_key(fn: ca.Function) -> str:
    """Hash of the function's expression graph, the CasADi version, the flags, the machine and its processor."""
    h = hashlib.sha256()
    h.update(fn.serialize().encode())
    h.update(ca.__version__.encode())
    h.update(" ".join(CFLAGS).encode())
    h.update(platform.machine().encode())
    h.update(processor().encode())
    return h.hexdigest()[:20]


def processor() -> str:
    """The processor's model and instruction-set flags (``-march=native`` code runs only where they are)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor()
    keys = ("model name", "flags", "Features", "CPU implementer", "CPU architecture", "CPU variant", "CPU part")
    return "|".join(sorted({ln.split(":", 1)[1].strip() for ln in lines if ln.startswith(keys) and ":" in ln}))


def compiler() -> str | None:
    """The C compiler to use (``$CC``, else gcc, else cc), or None."""
    for name in (os.environ.get("CC"), "gcc", "cc"):
        if name and shutil.which(name):
            return name
    return None


def shared(fn: ca.Function) -> ca.Function:
    """``fn`` (an SX function) with its common subexpressions computed once (``casadi.cse``): the same operations on
    the same values, so the same numbers to the bit, in fewer instructions (the open-loop shadow's step a third of
    them, the estimator's time update 0.7x), so less generated code to fetch inside a step. Its name, inputs and
    outputs are ``fn``'s; a function that is not SX is returned as it is."""
    if not fn.is_a("SXFunction"):
        return fn
    sym = fn.sx_in()
    return ca.Function(fn.name(), sym, ca.cse(fn.call(sym)), fn.name_in(), fn.name_out())


#: How many functions :func:`kept` holds for the constructions after it (a default controller keeps six: its three
#: stages' QP data and its three mapped plan merits, 10-20 MB; 24: the last four structures, so a process that builds
#: many, such as a sweep over boxes of other model effects, holds at most some 80 MB beyond its live controllers).
KEPT_MAX = 24
#: The functions :func:`kept` built in this process, by key, the least recently asked for first: a memo of
#: immutable functions.
_KEPT: dict[str, ca.Function] = {}
#: Guards :data:`_KEPT`'s reads and writes (not the builds).
_KEPT_LOCK = threading.Lock()


def kept(key: str, build: Callable[[], ca.Function]) -> ca.Function:
    """The function built for ``key`` earlier in this process, else ``build()``, kept for the next call with that key
    (the :data:`KEPT_MAX` last asked for). For functions whose common subexpressions take long to find
    (``casadi.cse``: the stages' QP data and the mapped plan merits, 7 of 8 s of a default controller's construction):
    ``key`` names the expression (:func:`expression_key` of it before the search), the same expression gives the same
    function to the bit, and a CasADi function is not changed by its calls (each
    :class:`.casadi_eval.BufferedFunction` evaluates into buffers of its own), so controllers of one structure share
    it (docs/architecture.md 'The suite's time')."""
    with _KEPT_LOCK:
        fn = _KEPT.pop(key, None)
    if fn is None:
        fn = build()  # outside the lock: two threads may build one key, both get an equal function
    with _KEPT_LOCK:  # the daemon's API threads build controllers while its loop runs
        _KEPT.pop(key, None)
        while len(_KEPT) >= KEPT_MAX:
            _KEPT.pop(next(iter(_KEPT)), None)  # the least recently asked for
        _KEPT[key] = fn  # last: the most recently asked for
    return fn


def expression_key(fn: ca.Function) -> str:
    """sha256 of ``fn``'s serialised form: its whole expression graph, its name and its inputs' and outputs' names."""
    return hashlib.sha256(fn.serialize().encode()).hexdigest()


def compiled(fn: ca.Function, report: CodegenReport | None = None, link: tuple[Path, ...] = ()) -> ca.Function:
    """``fn`` as generated C (built on first use, then loaded from the cache), or ``fn`` itself
    when code generation is off or fails (the reason goes into ``report``).

    ``link``: the shared objects of generated functions ``fn`` calls (an MX function calling functions loaded by this
    module, their paths in a report's ``libraries``): ``fn``'s own operations (index, scale, shift) are generated and
    linked against them instead of compiling what they hold again (a build of a second or so), the libraries' names
    (their hashes) in the cache key. Where one is missing the build fails and ``fn`` is evaluated by CasADi."""
    report = report if report is not None else CodegenReport()
    name = fn.name()
    if os.environ.get(SWITCH_ENV, "1") == "0":
        report.outcomes[name] = f"interpreted: {SWITCH_ENV}=0"
        return fn
    try:
        lib = library(fn, link)
        outcome = _ensure(lib, lambda: _build(fn, lib.parent, lib, _link_flags(link)), report)
        ext = ca.external(name, str(lib))
        report.outcomes[name] = outcome
        report.libraries[name] = lib
        return ext
    except Exception as exc:  # noqa: BLE001 - no compiler, read-only cache, ...: the interpreter works
        report.outcomes[name] = f"interpreted: {type(exc).__name__}: {str(exc)[:200]}"
        return fn


def library(fn: ca.Function, link: tuple[Path, ...] = ()) -> Path:
    """The shared object ``fn``'s generated C is cached as (``link``: as in :func:`compiled`)."""
    return cache_dir() / f"{fn.name()}_{_linked_key(fn, link)}.so"


def _linked_key(fn: ca.Function, link: tuple[Path, ...]) -> str:
    """:func:`structure_key`, with the names of the shared objects linked against where there are any."""
    if not link:
        return structure_key(fn)
    h = hashlib.sha256(structure_key(fn).encode())
    for path in link:
        h.update(Path(path).name.encode())
    return h.hexdigest()[:20]


def _link_flags(link: tuple[Path, ...]) -> tuple[str, ...]:
    """The linker's arguments: the shared objects by path, their folders as run paths (handed to the linker as they
    are, commas included), and the maths library."""
    paths = [Path(path).resolve() for path in link]
    rpaths = [arg for d in sorted({str(p.parent) for p in paths}) for arg in ("-Xlinker", "-rpath", "-Xlinker", d)]
    return (*map(str, paths), *rpaths, "-lm")


def _ensure(lib: Path, build, report: CodegenReport) -> str:
    """``"cached"`` if ``lib`` exists, else build it (time into ``report``) and say ``"built"``. A process that finds
    another building ``lib`` (the lock ``lib.lock``, held while it builds) waits for it and loads its result:
    ``"cached"``."""
    if lib.exists():
        return "cached"
    with _build_lock(lib):
        if lib.exists():  # built by the process this one waited for
            return "cached"
        t0 = time.perf_counter()
        build()
        report.build_time_s += time.perf_counter() - t0
    return "built"


@contextlib.contextmanager
def _build_lock(lib: Path):
    """An exclusive lock on ``lib``'s lock file while it is built (``flock``: released when the holder ends, whatever
    ends it), so two processes or threads asking for one structure at once build it once (the suite's two workers,
    a daemon's API threads). Where there is no ``fcntl`` or the folder is not writable, no lock: both build, and the
    atomic move leaves one whole file."""
    try:
        if fcntl is None:
            raise OSError("no file locks")
        lib.parent.mkdir(parents=True, exist_ok=True)
        handle = open(lib.with_name(f"{lib.stem}.lock"), "a")  # noqa: SIM115 - held until the build ends
    except OSError:
        yield
        return
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        yield


def _build(fn: ca.Function, folder: Path, lib: Path, libs: tuple[str, ...] = ("-lm",)) -> None:
    """Generate C for ``fn``, compile it (linked with ``libs``) and move the shared object into place atomically."""
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        source = generate_into(fn, f"{lib.stem}.c", Path(tmp))
        compile_shared(source, lib, CFLAGS, libs, timeout_s=600)


def generate_into(fn: ca.Function, name: str, folder: Path) -> Path:
    """``fn``'s C source (``Function.generate``'s code, without a header) written as ``folder / name``, the working
    directory left alone (a daemon builds controllers on its API threads while its loop runs)."""
    generator = ca.CodeGenerator(name, {"with_header": False})
    generator.add(fn)
    return Path(generator.generate(f"{folder}{os.sep}"))


def compiled_nlpsol(name: str, plugin: str, nlp: dict, opts: dict, report: CodegenReport | None = None,
                    flags: tuple[str, ...] = ("-O1", "-fPIC", "-shared")) -> ca.Function:
    """``casadi.nlpsol(name, plugin, nlp, opts)`` with the NLP's functions (objective, constraints
    and their derivatives) as generated C, built once and cached like :func:`compiled` (a whole
    NLP is large: ``-O1`` by default). Falls back to the interpreted solver, reason in ``report``."""
    report = report if report is not None else CodegenReport()
    solver = ca.nlpsol(name, plugin, nlp, opts)
    if os.environ.get(SWITCH_ENV, "1") == "0":
        report.outcomes[name] = f"interpreted: {SWITCH_ENV}=0"
        return solver
    try:
        structure = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
        h = hashlib.sha256(structure_key(structure).encode())
        h.update((plugin + " ".join(flags)).encode())
        lib = cache_dir() / f"{name}_{h.hexdigest()[:20]}.so"
        outcome = _ensure(lib, lambda: _build_dependencies(solver, lib, flags), report)
        out = ca.nlpsol(name, plugin, str(lib), opts)
        report.outcomes[name] = outcome
        return out
    except Exception as exc:  # noqa: BLE001 - the interpreted solver solves the same problem
        report.outcomes[name] = f"interpreted: {type(exc).__name__}: {str(exc)[:200]}"
        return solver


def _build_dependencies(solver: ca.Function, lib: Path, flags: tuple[str, ...]) -> None:
    lib.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        cwd = os.getcwd()
        try:
            os.chdir(tmp)
            source = solver.generate_dependencies(f"{lib.stem}.c")
        finally:
            os.chdir(cwd)
        compile_shared(Path(tmp) / source, lib, flags, ("-lm",), timeout_s=1800)


def compile_shared(src: Path, lib: Path, flags: tuple[str, ...], libs: tuple[str, ...] = (),
                   timeout_s: float = 600.0) -> None:
    """Compile ``src`` into the shared object ``lib``: built in a temporary folder beside ``lib`` (removed
    whatever happens) and moved into place atomically, so two processes building at once both end with a
    whole file. A failed compile raises with the compiler's messages."""
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set CC or install gcc)")
    lib.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        out = Path(tmp) / lib.name
        res = subprocess.run([cc, *flags, str(src), "-o", str(out), *libs], capture_output=True, text=True,
                             timeout=timeout_s)
        if res.returncode != 0:
            raise RuntimeError(f"compiling {src.name} failed ({cc} exit {res.returncode}): {res.stderr[-2000:]}")
        os.replace(out, lib)
