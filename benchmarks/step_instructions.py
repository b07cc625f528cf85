"""Instructions per control step, counted by valgrind's callgrind: a measure of the step that no load changes.

    python -m hvac_mpc.benchmarks.step_instructions [--steps 240] [--seed 1] [--version REV] [--json FILE]

Runs the solve-time loop (:class:`.solve_time.Loop`, default :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`
but for ``deadline_s``, the sample's idle time between the steps) under ``valgrind --tool=callgrind`` with the
instrumentation switched on only once the controller is built, and the counts zeroed before and written out after
each ``MpcController.step`` (callgrind's client requests, from a small C library built with ``gcc`` into a temporary
folder and called through ``ctypes``). Counted: the instructions the step's thread executes (Ir), by the shared
object they run in, grouped into kinds (:func:`kind_of`): OSQP's generated solver, CasADi's generated functions,
the Python interpreter, numpy, OpenBLAS, libffi (``ctypes``' calls), the C library and the rest.

Under valgrind a step takes some 50 times longer, so ``deadline_s`` is set to an hour (:data:`DEADLINE_S`): with
the default 0.5 s the first QPs would miss it and the fallbacks would take another path. Every other setting is the
default, so the commands are those of the loop run natively (the deadline never binds there).
``--version REV``: the code of a git revision or import root (:func:`.step_versions.import_root`) instead of the
installed one. Instruction counts repeat from run to run on one machine and installation to a few parts in a
thousand per step and a few in ten thousand over the loop (the interpreter's hash seed and addresses change per
process; OpenBLAS and the generated code pick their kernels by processor), whatever the load, so two versions
compare without a side-by-side run; they are not times: a step's time per instruction differs between kinds
(docs/architecture.md 'The step on a slower machine').
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

#: The deadline of the counted loop (s): long enough that valgrind's slowness never makes a step miss it.
DEADLINE_S = 3600.0

#: callgrind's client requests, as C functions ``ctypes`` can call.
CLIENT_C = """
#include <valgrind/callgrind.h>
void hq_cg_start(void) { CALLGRIND_START_INSTRUMENTATION; }
void hq_cg_zero(void) { CALLGRIND_ZERO_STATS; }
void hq_cg_dump(void) { CALLGRIND_DUMP_STATS_AT("step"); }
"""

#: The kinds of code, in the order printed.
KINDS = ("osqp generated", "casadi generated", "python interpreter", "numpy", "openblas", "libffi (ctypes)",
         "ctypes module", "casadi library", "libc, libm, loader", "other")


def kind_of(obj: str) -> str:
    """The kind (:data:`KINDS`) of the shared object at path ``obj`` (callgrind's ``ob=``)."""
    base = obj.rsplit("/", 1)[-1]
    if "libpython" in base or base.startswith("python"):
        return "python interpreter"
    if "openblas" in base:
        return "openblas"
    if "/numpy/" in obj or "numpy" in base:
        return "numpy"
    if "libffi" in base:
        return "libffi (ctypes)"
    if base.startswith("_ctypes"):
        return "ctypes module"
    if "/osqp/" in obj and base.endswith(".so") and "site-packages" not in obj:
        return "osqp generated"
    if "site-packages" not in obj and base.endswith(".so") and re.search(r"_[0-9a-f]{20}\.so$", base):
        return "casadi generated"
    if "casadi" in obj:
        return "casadi library"
    if base.startswith(("libc.", "libm.", "ld-linux")) or "vdso" in base:
        return "libc, libm, loader"
    return "other"


def self_costs(path: Path, names: dict[str, str]) -> Counter:
    """Instructions by shared object in one callgrind dump: the self cost lines, not the calls' inclusive ones.
    ``names``: callgrind's compressed object names, carried from dump to dump (a name is written out once)."""
    out: Counter = Counter()
    current, after_call = "?", False
    for line in path.read_text().splitlines():
        if line.startswith(("ob=", "cob=")):
            m = re.match(r"c?ob=\((\d+)\)(?: (.*))?$", line)
            if m:
                if m.group(2):
                    names[m.group(1)] = m.group(2)
                if line.startswith("ob="):
                    current = names.get(m.group(1), "?")
            elif line.startswith("ob="):
                current = line[3:]
            continue
        if line.startswith("calls="):
            after_call = True
            continue
        if line[:1].isdigit() or line[:1] in "+-*":
            if after_call:
                after_call = False
                continue
            parts = line.split()
            if len(parts) >= 2:
                out[current] += int(parts[1])
    return out


#: The counted loop, run under valgrind (arguments: the client library, steps, seed, the rows' file, the deadline);
#: it imports nothing of this module, so a revision without it (``--version``) runs it as well.
WORKER = """
import ctypes, json, sys
from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
lib = ctypes.CDLL(sys.argv[1])
steps, seed = int(sys.argv[2]), int(sys.argv[3])
ctrl = MpcController(settings=MpcSettings(deadline_s=float(sys.argv[5])))
loop = solve_time.Loop(ctrl, seed, idle_s=solve_time.IDLE_S)
step = ctrl.step
def counted(measurement, reference):
    lib.hq_cg_zero()
    try:
        return step(measurement, reference)
    finally:
        lib.hq_cg_dump()
ctrl.step = counted
lib.hq_cg_start()
rows = []
for k in range(steps):
    res = loop.step(k)
    rows.append([int(res.stats["iterations"]), int(res.stats["qp_solves"]), list(res.command.vector())])
with open(sys.argv[4], "w") as f:
    json.dump(rows, f)
"""


def count(steps: int, seed: int, root: Path | None, workdir: Path) -> dict[str, Any]:
    """Run the loop under callgrind in ``workdir``; per step its instructions by shared object, OSQP iterations,
    QPs and command."""
    lib = workdir / "libhq_cg.so"
    (workdir / "hq_cg.c").write_text(CLIENT_C)
    subprocess.run(["gcc", "-O2", "-shared", "-fPIC", "-o", str(lib), str(workdir / "hq_cg.c")], check=True)
    env = dict(os.environ)
    if root is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    rows_file = workdir / "rows.json"
    subprocess.run(["valgrind", "--tool=callgrind", "--instr-atstart=no", "--separate-threads=yes",
                    f"--callgrind-out-file={workdir}/cg.%p", sys.executable, "-c", WORKER, str(lib), str(steps),
                    str(seed), str(rows_file), repr(DEADLINE_S)], check=True, env=env, cwd=root or workdir,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    dumps = sorted(workdir.glob("cg.*.*-*"), key=lambda p: (int(re.search(r"\.(\d+)-\d+$", p.name).group(1)), p.name))
    names: dict[str, str] = {}
    per_step = []
    for path in dumps:  # every thread's dump read in order, for the names; the step's thread (01) counted
        costs = self_costs(path, names)
        if path.name.endswith("-01"):
            per_step.append(costs)
    rows = json.loads(rows_file.read_text())
    if len(per_step) != len(rows):
        raise RuntimeError(f"{len(per_step)} dumps of the step's thread for {len(rows)} steps")
    return {"steps": [{"objects": dict(c), "iterations": r[0], "qp_solves": r[1], "command": r[2]}
                      for c, r in zip(per_step, rows)]}


def summary(result: dict[str, Any], quiet: set[int]) -> dict[str, Any]:
    """Median, 99th percentile and largest count of the steps (the first excluded), the quiet steps' median, and
    each kind's mean over the quiet steps with its share."""
    steps = result["steps"]
    total = np.array([sum(s["objects"].values()) for s in steps], dtype=float)
    q = sorted(k for k in quiet if k < len(steps))
    kinds: Counter = Counter()
    for k in q:
        for obj, n in steps[k]["objects"].items():
            kinds[kind_of(obj)] += n
    mean_q = total[q].mean() if q else float("nan")
    return {"median": float(np.median(total[1:])), "p99": float(np.percentile(total[1:], 99)),
            "max": float(total[1:].max()), "quiet_median": float(np.median(total[q])) if q else float("nan"),
            "quiet_steps": len(q), "osqp_iterations": int(sum(s["iterations"] for s in steps)),
            "kinds_quiet_mean": {kind: kinds[kind] / len(q) for kind in KINDS if q},
            "kinds_quiet_share": {kind: kinds[kind] / len(q) / mean_q for kind in KINDS if q}}


def main(argv: list[str] | None = None) -> int:
    from . import quiet_profile, step_versions
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=240)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--version", default=None, help="git revision or import root (default: the installed code)")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    for tool in ("valgrind", "gcc"):
        if shutil.which(tool) is None:
            print(f"step_instructions: needs {tool} on the PATH")
            return 2
    with tempfile.TemporaryDirectory() as tmp:
        try:
            root = step_versions.import_root(args.version, Path(tmp) / "version") if args.version else None
        except ValueError as exc:
            print(f"step_instructions: {exc}")
            return 2
        work = Path(tmp) / "cg"
        work.mkdir()
        result = count(args.steps, args.seed, root, work)
    s = summary(result, quiet_profile.quiet_steps(args.steps))
    print(f"instructions per step ({args.steps} steps, seed {args.seed}, the first excluded): median "
          f"{s['median'] / 1e6:.3f} M, 99th percentile {s['p99'] / 1e6:.2f} M, max {s['max'] / 1e6:.2f} M; "
          f"{s['quiet_steps']} quiet steps' median {s['quiet_median'] / 1e6:.3f} M; OSQP iterations "
          f"{s['osqp_iterations']}")
    for kind in KINDS:
        print(f"  {kind:22s} {s['kinds_quiet_mean'][kind] / 1e3:9.1f} k  {100 * s['kinds_quiet_share'][kind]:5.1f} %")
    if args.json is not None:
        args.json.write_text(json.dumps({"summary": s, "version": args.version or "installed", **result}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
