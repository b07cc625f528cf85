"""Two versions of the code side by side on the solve-time loop: the step time of a code change.

    python -m hvac_mpc.benchmarks.step_versions --before REV [--after REV] [--steps 240] [--rounds 3]
                                                [--seed 1] [--json FILE] [--after-settings JSON] [--idle]
                                                [--after-python PATH]

``REV`` is a git revision of the repository this package is installed from (e.g. ``main``), laid
out as installed in a temporary folder, or an import root holding a ``hvac_mpc`` package (its
subpackages in the installed layout, ``hvac_mpc/mpc``, ``hvac_mpc/models``, ...); without
``--after`` the installed version is the other one. Each version runs in a process of its own (the
same interpreter, the same generated-code cache), both with the default
:class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`
on the solve-time scenario (:class:`.solve_time.Loop`: the same plant, seed and references), stepped
in lockstep, one step of each in turn (which goes first alternates), so that the load of other
processes on a shared machine falls on both alike; which goes first at a given step also alternates from
round to round (a reference change falls on the same steps every round: without it one version would take
every change's step first, which biased the 99th percentile's ratio by 1.03-1.10x on identical code). Step
times are the CPU time of the thread that runs ``MpcController.step`` (``time.thread_time``), the cold first
step excluded. Reported per round: median, 99th percentile and their ratios (after / before), the median of
the quiet steps (:func:`.quiet_profile.quiet_steps`: not a reference change nor the steps of its wake) and its
ratio, the closed-loop cost of each and the largest difference between the two versions' commands (0 when the
change keeps the arithmetic). ``--idle``: each loop gives the controller's second thread the sample's idle time
between its steps (:data:`.solve_time.IDLE_S`, as ``hvac-mpc solve-time`` does), so the filter not in use is
updated there and not in the step; without it the steps run back to back.
``--after-settings '{"rti_step_fractions": [0.5, 0.25]}'`` runs the version after with these
:class:`~hvac_mpc.mpc.mpc_controller.MpcSettings` fields (JSON lists become tuples): the step time of a setting,
e.g. ``--before HEAD`` with the installed version and a setting that is off by default.
``--after-python PATH`` runs the version after on another interpreter (e.g. another virtual environment's
``bin/python`` with this package installed): the step time of an interpreter build (docs/architecture.md 'The step
on a slower machine').
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from . import quiet_profile, solve_time

#: The worker each version runs: builds the loop, then answers ``step k`` with the step's thread CPU
#: time (s), its OSQP iterations and the command, and ``cost`` with the closed-loop cost so far.
WORKER = """
import json, sys
from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
fields = json.loads(sys.argv[2]) if len(sys.argv) > 2 else {}
fields = {k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()}
idle = float(sys.argv[3]) if len(sys.argv) > 3 else 0.0
loop = solve_time.Loop(MpcController(settings=MpcSettings(**fields)), int(sys.argv[1]), idle_s=idle)
print("ready", flush=True)
for line in sys.stdin:
    word, *rest = line.split()
    if word == "step":
        res = loop.step(int(rest[0]))
        out = [loop.thread_s[-1], int(res.stats["iterations"]), list(res.command.vector())]
    else:
        out = float(sum(loop.cost.values()))
    print(json.dumps(out), flush=True)
"""


#: The repository this package is installed from (an editable install; a revision is read from its git).
REPOSITORY = Path(__file__).resolve().parents[1]


def installed_layout(source: Path, dest: Path) -> Path:
    """The package of the source tree ``source`` laid out as installed under ``dest`` (its import root):
    ``hvac_mpc`` with the subpackages of ``[tool.setuptools.package-dir]`` in ``pyproject.toml``."""
    cfg = tomllib.loads((source / "pyproject.toml").read_text())
    ignore = shutil.ignore_patterns("__pycache__")
    shutil.copytree(source / "hvac_mpc", dest / "hvac_mpc", ignore=ignore)
    for package, folder in cfg["tool"]["setuptools"]["package-dir"].items():
        shutil.copytree(source / folder, dest / package.replace(".", "/"), ignore=ignore)
    return dest


def import_root(version: str, workdir: Path) -> Path:
    """The import root of ``version``: a folder holding ``hvac_mpc/mpc`` as it is, else a git revision of
    :data:`REPOSITORY` laid out as installed in ``workdir``. Raises ValueError naming the version otherwise."""
    path = Path(version)
    if (path / "hvac_mpc" / "mpc").is_dir():
        return path.resolve()
    try:
        archive = subprocess.run(["git", "-C", str(REPOSITORY), "archive", version], capture_output=True)
    except FileNotFoundError:
        raise ValueError(f"version {version!r} is no import root holding hvac_mpc/mpc, and reading a revision "
                         "needs git") from None
    if archive.returncode != 0:
        raise ValueError(f"version {version!r} is neither an import root holding hvac_mpc/mpc nor a git revision "
                         f"of {REPOSITORY}: {archive.stderr.decode().strip()}")
    source = workdir / "source"
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(source, filter="data")
    return installed_layout(source, workdir / "root")


class Version:
    """One version's worker process (``root``: its import root, None for the installed version)."""

    def __init__(self, root: Path | None, seed: int, settings: str | None = None, idle_s: float = 0.0,
                 python: str | None = None):
        env = dict(os.environ)
        if root is not None:
            env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        extra = [settings or "{}", repr(float(idle_s))] if idle_s else ([settings] if settings else [])
        self.proc = subprocess.Popen([python or sys.executable, "-c", WORKER, str(seed), *extra],
                                     stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env, cwd=root or None)
        if self.proc.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the worker of {root or 'the installed version'} did not start")

    def ask(self, line: str) -> Any:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


def side_by_side(roots: dict[str, Path | None], steps: int, seed: int,
                 after_settings: str | None = None, idle_s: float = 0.0, swap: bool = False,
                 pythons: dict[str, str | None] | None = None) -> dict[str, Any]:
    """One round: both versions in lockstep; each one's summary, the ratios and the commands' difference
    (``after_settings``: JSON of MpcSettings fields of the version after; ``idle_s``: the idle time given to the
    second thread after each step, :class:`.solve_time.Loop`; ``swap``: the other version first at even steps;
    ``pythons``: the interpreter of a version, by name, where it is not this one)."""
    pythons = pythons or {}
    versions = {name: Version(root, seed, after_settings if name == "after" else None, idle_s, pythons.get(name))
                for name, root in roots.items()}
    times = {name: [] for name in versions}
    iterations = {name: [] for name in versions}
    commands = {name: [] for name in versions}
    order = list(versions)
    try:
        for k in range(steps):
            for name in (order if (k + swap) % 2 == 0 else order[::-1]):
                t, n, u = versions[name].ask(f"step {k}")
                times[name].append(t)
                iterations[name].append(n)
                commands[name].append(u)
        costs = {name: v.ask("cost") for name, v in versions.items()}
    finally:
        for v in versions.values():
            v.close()
    out: dict[str, Any] = {}
    quiet = sorted(quiet_profile.quiet_steps(steps))
    for name in versions:
        t = np.array(times[name][1:]) * 1e3
        out[name] = {"thread_median_ms": float(np.median(t)), "thread_p99_ms": float(np.percentile(t, 99)),
                     "quiet_median_ms": float(np.median(np.array(times[name])[quiet]) * 1e3),
                     "total_iterations": int(sum(iterations[name])), "cost": costs[name]}
    out["median_ratio"] = out["after"]["thread_median_ms"] / out["before"]["thread_median_ms"]
    out["p99_ratio"] = out["after"]["thread_p99_ms"] / out["before"]["thread_p99_ms"]
    out["quiet_median_ratio"] = out["after"]["quiet_median_ms"] / out["before"]["quiet_median_ms"]
    out["command_difference"] = float(np.abs(np.array(commands["after"]) - np.array(commands["before"])).max())
    return out


def version_arguments(p: argparse.ArgumentParser) -> None:
    """``--before`` and ``--after``: the two versions compared (:func:`import_root`)."""
    p.add_argument("--before", required=True, help="git revision or import root of the version before")
    p.add_argument("--after", default=None, help="git revision or import root of the version after "
                                                 "(default: the installed one)")


def version_roots(args: argparse.Namespace, workdir: Path, prog: str) -> dict[str, Path | None] | None:
    """The import roots of ``--before`` and ``--after`` (None: the installed version) under ``workdir``; None
    after printing why where a version cannot be had."""
    try:
        return {name: import_root(getattr(args, name), workdir / name) if getattr(args, name) else None
                for name in ("before", "after")}
    except ValueError as exc:
        print(f"{prog}: {exc}")
        return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    version_arguments(p)
    p.add_argument("--after-settings", default=None, metavar="JSON",
                   help="MpcSettings fields of the version after, as a JSON object (lists become tuples)")
    p.add_argument("--idle", action="store_true",
                   help=f"give the second thread the sample's idle time ({solve_time.IDLE_S} s) between the steps, "
                        "as hvac-mpc solve-time does (default: back to back)")
    p.add_argument("--after-python", default=None, metavar="PATH",
                   help="the interpreter of the version after (e.g. another virtual environment's bin/python with "
                        "this package and its dependencies installed): the step time of an interpreter build; "
                        "default: this one")
    solve_time.side_by_side_arguments(p)
    args = p.parse_args(argv)
    if args.after_settings is not None:
        try:
            if not isinstance(json.loads(args.after_settings), dict):
                raise ValueError("not an object")
        except ValueError as exc:
            print(f"step_versions: --after-settings must be a JSON object of MpcSettings fields: {exc}")
            return 2
    if solve_time.side_by_side_refused(args, "step_versions"):
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        roots = version_roots(args, Path(tmp), "step_versions")
        if roots is None:
            return 2
        idle_s = solve_time.IDLE_S if args.idle else 0.0
        rounds = [side_by_side(roots, args.steps, args.seed, args.after_settings, idle_s, swap=bool(r % 2),
                               pythons={"after": args.after_python})
                  for r in range(args.rounds)]
    for i, r in enumerate(rounds, 1):
        b, a = r["before"], r["after"]
        print(f"round {i}: median {b['thread_median_ms']:.3f} -> {a['thread_median_ms']:.3f} ms "
              f"({r['median_ratio']:.2f}x), p99 {b['thread_p99_ms']:.2f} -> {a['thread_p99_ms']:.2f} ms "
              f"({r['p99_ratio']:.2f}x), quiet steps' median {b['quiet_median_ms']:.3f} -> "
              f"{a['quiet_median_ms']:.3f} ms ({r['quiet_median_ratio']:.2f}x), OSQP iterations {b['total_iterations']} -> {a['total_iterations']}, "
              f"cost {b['cost']:.2f} -> {a['cost']:.2f}, largest command difference {r['command_difference']:.3g}")
    if args.json is not None:
        args.json.write_text(json.dumps({"versions": {"before": args.before, "after": args.after or "installed",
                                                      "after_settings": args.after_settings,
                                                      "after_python": args.after_python},
                                         "steps": args.steps, "idle": bool(args.idle),
                                         "seed": args.seed, "rounds": rounds}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
