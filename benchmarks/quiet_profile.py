"""Where a quiet control step's thread CPU time goes, by kind of work: OSQP, CasADi's generated calls, numpy, the
project's own Python and the rest.

    python -m hvac_mpc.benchmarks.quiet_profile [--steps 240] [--seed 1] [--settings JSON] [--top 12]

Runs the solve-time loop (:class:`.solve_time.Loop`, default :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`, the
idle time of a sample between the steps) under :mod:`cProfile` with the thread's CPU clock (``time.thread_time``), the
profiler on only in the quiet steps: not the cold start, not a reference change (:func:`.change_start.change_steps`)
nor the :data:`WAKE` steps after one. Each function's own time (``tottime``) goes to one kind:

* ``osqp``: the methods of :mod:`hvac_mpc.mpc.osqp_embedded` and :mod:`osqp` (the generated solver is called through
  ``ctypes``, whose calls the profiler does not see apart: they are in their caller's own time);
* ``casadi``: CasADi's Python layer and its compiled calls (the generated functions of the QP data, the estimator and
  the flow checks, loaded with ``casadi.external``);
* ``numpy``: numpy's functions and array methods;
* ``python``: the project's own functions (the interpreter running the glue between the calls);
* ``other``: the rest (the standard library, builtins such as ``len`` or ``min``).

The profiler costs about a microsecond per call, counted in the own times, so the shares are the profiled run's: the
unprofiled median and mean of the same steps (a second loop stepped alongside, the same commands) are printed beside
them, and each kind's own time less its calls times the profiler's cost per call (the profiled mean's excess over the
unprofiled one, per call: ASSUMPTION: the same for every call). Also printed: the ``--top`` functions by own time,
with their calls per step, and the time of one data address handed to the generated solver both ways
(:func:`address_times`, side by side in one run).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time
from collections import defaultdict

import numpy as np

from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.osqp_embedded import data_address

from . import change_start, solve_time

#: Steps after a reference change that are not quiet (its wake: the slow single QPs, docs/architecture.md).
WAKE = 5
#: The kinds of work, in the order printed.
KINDS = ("osqp", "casadi", "numpy", "python", "other")


def kind_of(filename: str, name: str) -> str:
    """The kind (:data:`KINDS`) of a profiled function from its file and name (``pstats``' key)."""
    base = filename.replace("\\", "/").rsplit("/", 1)[-1]
    if base == "osqp_embedded.py" or "/osqp/" in filename or "osqp" in name:
        return "osqp"
    # casadi_eval.BufferedFunction.__call__ runs a generated function through CasADi's buffer interface
    if base == "casadi_eval.py" or "/casadi/" in filename or "casadi" in name:
        return "casadi"
    if "/numpy/" in filename or "numpy" in name:
        return "numpy"
    if any(f"/{part}/" in filename for part in ("mpc", "models", "hvac_mpc")):
        return "python"
    return "other"


def quiet_steps(steps: int) -> set[int]:
    """The steps of a loop of ``steps`` that are profiled: not the first, not a change nor its wake."""
    noisy = {0}
    for c in change_start.change_steps(steps):
        noisy.update(range(c, c + WAKE + 1))
    return set(range(steps)) - noisy


def measure(steps: int, seed: int, settings: dict | None = None) -> dict:
    """The profiled loop and an unprofiled one alongside; the own time per kind and function, per quiet step."""
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in (settings or {}).items()}
    loops = {name: solve_time.Loop(MpcController(settings=MpcSettings(**fields)), seed, idle_s=solve_time.IDLE_S)
             for name in ("plain", "profiled")}
    profile = cProfile.Profile(time.thread_time)
    chosen = quiet_steps(steps)
    thread_s: dict[str, list[float]] = {"plain": [], "profiled": []}
    commands_equal = True
    ctrl = loops["profiled"].ctrl
    step = ctrl.step

    def profiled_step(*args, **kwargs):  # the controller's step only, not the loop's plant and cost
        profile.enable()
        try:
            return step(*args, **kwargs)
        finally:
            profile.disable()

    for k in range(steps):
        order = ("plain", "profiled") if k % 2 == 0 else ("profiled", "plain")
        out = {}
        for name in order:
            ctrl.step = profiled_step if k in chosen else step
            out[name] = loops[name].step(k)
            if k in chosen:
                thread_s[name].append(loops[name].thread_s[-1])
        commands_equal &= bool(np.array_equal(out["plain"].command.vector(), out["profiled"].command.vector()))
    ctrl.step = step
    for loop in loops.values():
        loop.ctrl.close()
    stats = pstats.Stats(profile)
    by_kind: dict[str, float] = defaultdict(float)
    calls: dict[str, float] = defaultdict(float)
    rows = []
    n = max(len(chosen), 1)
    for (filename, line, name), (_, ncalls, tottime, _, _) in stats.stats.items():
        kind = kind_of(filename, name)
        by_kind[kind] += tottime / n
        calls[kind] += ncalls / n
        rows.append((tottime / n, ncalls / n, kind, f"{filename.rsplit('/', 2)[-1]}:{line}({name})"))
    rows.sort(reverse=True)
    mean = {k: float(np.mean(v)) for k, v in thread_s.items()}
    # the profiler's own cost per call: the profiled step's extra time over the unprofiled one's, per call
    per_call = max(mean["profiled"] - mean["plain"], 0.0) / max(sum(calls.values()), 1.0)
    return {"steps": len(chosen), "commands_equal": commands_equal,
            "median_ms": {k: 1e3 * float(np.median(v)) for k, v in thread_s.items()},
            "mean_ms": {k: 1e3 * float(np.mean(v)) for k, v in thread_s.items()},
            "by_kind_ms": {k: 1e3 * by_kind.get(k, 0.0) for k in KINDS},
            "calls": {k: calls.get(k, 0.0) for k in KINDS}, "profiler_per_call_us": 1e6 * per_call,
            "corrected_ms": {k: 1e3 * max(by_kind.get(k, 0.0) - per_call * calls.get(k, 0.0), 0.0) for k in KINDS},
            "top": [{"ms": 1e3 * t, "calls": c, "kind": kind, "function": f} for t, c, kind, f in rows]}


def address_times(size: int = 279, rounds: int = 20, calls: int = 2000) -> dict[str, float]:
    """Thread CPU time (us) of one data address of a float64 array of ``size`` values (the QP's variables), the
    generated solver's way (:func:`~hvac_mpc.mpc.osqp_embedded.data_address`) and numpy's (``ndarray.ctypes.data``),
    ``rounds`` rounds of ``calls`` calls each, the two alternating; the medians over the rounds and their ratio."""
    a = np.zeros(size)
    ways = {"data_address": lambda: data_address(a), "ndarray.ctypes.data": lambda: a.ctypes.data}
    times: dict[str, list[float]] = {k: [] for k in ways}
    for r in range(rounds):
        for name in (list(ways) if r % 2 == 0 else list(ways)[::-1]):
            f = ways[name]
            t0 = time.thread_time()
            for _ in range(calls):
                f()
            times[name].append((time.thread_time() - t0) / calls * 1e6)
    out = {k: float(np.median(v)) for k, v in times.items()}
    out["ratio"] = out["data_address"] / out["ndarray.ctypes.data"]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hvac_mpc.benchmarks.quiet_profile",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--settings", type=json.loads, default=None,
                        help='MpcSettings fields as a JSON object, e.g. \'{"osqp_scaling_interval": 2}\'')
    parser.add_argument("--top", type=int, default=12, help="functions listed by own time")
    args = parser.parse_args(argv)
    if args.steps < 2 or args.top < 0:
        parser.error("--steps must be at least 2 and --top at least 0")
    out = measure(args.steps, args.seed, args.settings)
    total = sum(out["by_kind_ms"].values())
    print(f"{out['steps']} quiet steps (seed {args.seed}), thread CPU per step: unprofiled median "
          f"{out['median_ms']['plain']:.3f} ms (mean {out['mean_ms']['plain']:.3f}), profiled median "
          f"{out['median_ms']['profiled']:.3f} ms (mean {out['mean_ms']['profiled']:.3f}); the same commands: "
          f"{out['commands_equal']}")
    corrected = sum(out["corrected_ms"].values())
    print(f"own time per step by kind: profiled (mean {total:.3f} ms), and less the profiler's "
          f"{out['profiler_per_call_us']:.2f} us per call (mean {corrected:.3f} ms):")
    for kind in KINDS:
        ms, est = out["by_kind_ms"][kind], out["corrected_ms"][kind]
        print(f"  {kind:<8} {ms:7.3f} ms {ms / max(total, 1e-12):6.1%} | {out['calls'][kind]:6.1f} calls | "
              f"{est:7.3f} ms {est / max(corrected, 1e-12):6.1%}")
    print(f"the {args.top} largest own times per step:")
    for row in out["top"][:args.top]:
        print(f"  {row['ms']:7.3f} ms  {row['calls']:6.1f} calls  {row['kind']:<7} {row['function']}")
    addr = address_times()
    print(f"a data address handed to the generated solver: data_address {addr['data_address']:.2f} us, "
          f"ndarray.ctypes.data {addr['ndarray.ctypes.data']:.2f} us ({addr['ratio']:.2f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
