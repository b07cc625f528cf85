"""Solve-time benchmark (``hvac-mpc solve-time``): the RTI controller against IPOPT and do-mpc.

All controllers run the same closed loop on the simulated plant (all effects on, same seed,
same reference scenario, same estimator and fallback chain), each solving the same discrete
problem (:class:`~hvac_mpc.mpc.ocp.TrackingProblem` at the default horizon), described once stage
by stage (:class:`~hvac_mpc.mpc.stage_ocp.StageOcp`, docs/architecture.md 'The stage-wise
description'):

* ``rti``: the real-time iteration with OSQP (:mod:`hvac_mpc.mpc.rti_osqp`), its QP data and
  estimator as generated C (``--no-codegen``: CasADi's interpreter); its QP is the Gauss-Newton QP
  of the description's compact transcription (``tests/test_stage_ocp.py``, to 1e-9);
* ``ipopt``: the description's compact transcription solved to convergence by CasADi + IPOPT
  (:mod:`hvac_mpc.mpc.ipopt_reference`);
* ``fatrop``: its stage-wise transcription solved to convergence by fatrop
  (:mod:`hvac_mpc.benchmarks.fatrop_reference`);
* ``do-mpc``: do-mpc given the description's functions (optional extra ``compare``;
  :mod:`hvac_mpc.benchmarks.dompc_reference`).
* ``rti-acados`` (``--acados``): the real-time iteration through acados, built from the description
  (:mod:`hvac_mpc.mpc.rti_acados`; optional, installed apart), with its own per-step suboptimality;
  ``--acados-phases`` adds the thread CPU time of its preparations and feedback QPs (``phases`` in its
  result, :class:`PhaseTimer`). With ``--acados`` fatrop is skipped, a note says why: acados' BLASFEO is
  loaded process-wide and CasADi's fatrop plugin carries another build of it.

With ``--jit`` IPOPT's and fatrop's NLP functions run as generated C, compiled once and cached (the
build time is reported apart, as ``codegen_build_s``, not in the step times). fatrop gets the objective
scaling of IPOPT and the tolerance that stops it as close to the optimum
(:mod:`hvac_mpc.benchmarks.fatrop_reference`); after the loops its cost is compared per step with
IPOPT's from the same state and start (``agreement`` in its result).

Every result carries its solver's settings (``settings``: tolerances, compiled or not, and
``description``: what it is built from); ``shared_description`` in the JSON summarises the
description and which solvers share it. The
per-step suboptimality of the RTI against the converged solution from the same state
(:mod:`hvac_mpc.benchmarks.suboptimality`) is measured on a second, untimed run of the RTI loop.

Step time is the wall time of ``MpcController.step`` (estimator, solver, Python overhead), the
first (cold) step excluded from the statistics. The reachable-flow solve that a step starts on the
second thread (:mod:`hvac_mpc.mpc.priorities`) is collected at the start of the next step; on the box
a sample (1 s) lies between the two, here the loop gives the thread up to :data:`IDLE_S` between the
timed steps (``--back-to-back``: none, so the next step may wait for it). Both, and every wait of a
step for the thread all the same, are printed and in the result's ``background``. Closed-loop cost is the MPC's stage cost
evaluated on the plant's noise-free outputs, summed over the run. The problem is not convex
(redundant actuators, valve curves) and one run can settle on another actuator mix than another
after a reference change, so the cost comparison with IPOPT is repeated over ``--cost-seeds``
plant noise seeds (RTI and IPOPT only) and reported per seed. Math libraries are limited to two
threads and the process to at most two cores. Prints a table and writes JSON.
"""

from __future__ import annotations

import os

# limit BLAS/OpenMP pools before numpy, scipy or casadi start them (two threads at most)
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    if not os.environ.get(_var, "").isdigit() or int(os.environ[_var]) > 2:
        os.environ[_var] = "2"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Callable  # noqa: E402

import numpy as np  # noqa: E402

from hvac_mpc.models.plant import Environment, SimulatedPlant  # noqa: E402

from hvac_mpc.contract import Command
from hvac_mpc.mpc.ipopt_reference import IpoptReferenceSolver  # noqa: E402
from hvac_mpc.models.model_file import load as load_model_file  # noqa: E402
from hvac_mpc.mpc.mpc_controller import InvalidSettings, MpcController, MpcSettings  # noqa: E402
from hvac_mpc.mpc.ocp import TrackingProblem  # noqa: E402
from hvac_mpc.mpc.settings_file import settings_with  # noqa: E402
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver  # noqa: E402
from hvac_mpc.mpc.stage_ocp import StageOcp  # noqa: E402
from hvac_mpc.contract import Reference  # noqa: E402

#: Reference scenario (start time s, reference): proband conditions of thesis sec. 6 (room at
#: 32 C), references changing every 30 s instead of every 5 min so the run stays short.
SCENARIO: tuple[tuple[float, Reference], ...] = (
    (0.0, Reference.from_split(16.0, 0.035, (0.4, 0.35, 0.25))),
    (30.0, Reference.from_split(13.0, 0.035, (0.4, 0.35, 0.25))),
    (60.0, Reference.from_split(20.0, 0.025, (0.2, 0.5, 0.3))),
    (90.0, Reference(18.0, 0.045)),
    (120.0, Reference.from_split(24.0, 0.03, (0.5, 0.2, 0.3))),
    (150.0, Reference.from_split(15.0, 0.05, (0.34, 0.33, 0.33))),
    (180.0, Reference.from_split(22.0, 0.02, (0.3, 0.3, 0.4))),
    (210.0, Reference.from_split(17.0, 0.04, (0.45, 0.3, 0.25))),
)
INLET_C = 32.0
INITIAL = Command(150.0, 0.0, 70.0, 100.0, 100.0, 100.0)
FULL_STEPS = 240
QUICK_STEPS = 30
#: Time the loop gives the second thread between two timed steps unless ``--back-to-back`` (s): the
#: sample period of the box, of which a step takes about a millisecond.
IDLE_S = 1.0
#: What the RTI is held to (docs/architecture.md, 'One control step'): whole-step median and 99th
#: percentile (ms, wall time, cold step excluded) and the per-step suboptimality of the move it
#: applies against the converged solution from the same state (``decision``, %).
TARGETS = {"median_ms": 0.5, "p99_ms": 1.5, "decision_median_pct": 1.0, "decision_p95_pct": 5.0}
#: What the RTI's QP is built from: the tracking problem's stage functions, assembled by hand for
#: OSQP; the QP equals the Gauss-Newton QP of the stage-wise description (tests/test_stage_ocp.py).
RTI_DESCRIPTION = ("StageOcp: Gauss-Newton QP of the compact transcription (built in rti_osqp from "
                   "TrackingProblem's stage functions, equal to 1e-9 by test)")


def side_by_side_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of a run of two variants side by side on this loop: --steps, --rounds, --seed, --json."""
    parser.add_argument("--steps", type=int, default=FULL_STEPS, help=f"closed-loop steps (default {FULL_STEPS})")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, each with both anew (default 3)")
    parser.add_argument("--seed", type=int, default=1, help="plant noise seed (default 1)")
    parser.add_argument("--json", type=Path, default=None, help="write the rounds here (JSON)")


def side_by_side_refused(args: argparse.Namespace, prog: str) -> bool:
    """True, with the reason printed, when the options of :func:`side_by_side_arguments` are out of range."""
    if args.steps < 3 or args.rounds < 1:
        print(f"{prog}: --steps must be at least 3 and --rounds at least 1")
        return True
    return False


def reference_at(t_s: float, scenario=SCENARIO) -> Reference:
    """The scenario's reference in force at time ``t_s``."""
    return [r for t0, r in scenario if t_s >= t0][-1]


def stage_cost(problem: TrackingProblem, truth: dict[str, float], reference: Reference, command: np.ndarray,
               previous: np.ndarray) -> dict[str, float]:
    """The MPC's stage cost for one second of closed loop, on noise-free plant outputs, by term."""
    share = problem.spec.temperature_sensor_share
    temp = (1.0 - share) * truth["supply_air_temp_c"] + share * truth["supply_temp_c"]
    y = np.array([temp, truth["volume_flow_m3s"], truth["flow_m_m3s"], truth["flow_f_m3s"],
                  truth["flow_w_m3s"], truth["heater_power_w"], command[problem.i_valve_a]])
    e = (y - problem.reference_vector(reference)) / problem.y_scale
    # the controller's test, on the command in force before
    c = problem.heating_weights(problem.output_weights(reference), problem.heating(previous)) * e * e
    du = problem.scale_u(command) - problem.scale_u(previous)
    return {"temperature": float(c[0]), "flow": float(c[1]), "outlets": float(c[2:5].sum()),
            "valve_a_heating": float(c[6]),
            "energy": float(problem.energy_weight * ((command[0] + truth["heater_power_w"])
                                                      / problem.energy_scale_w) ** 2),
            "moves": float(np.sum(problem.w_du * du * du))}


class Loop:
    """One controller on its own plant of the solve-time scenario, stepped one sample at a time: the
    plant (``seed``, ``inlet_c``, water at 5 C) settled at :data:`INITIAL` and the controller reset to
    it; :meth:`step` applies the controller's command and sums the stage cost per term (``cost``)
    and the step's process and thread CPU times (``cpu_s``, ``thread_s``, seconds).

    ``idle_s`` > 0: after each step (untimed) the loop gives the controller's reachable-flow solve on the
    second thread up to that long to finish (:meth:`MpcController.wait_background`), as the rest of the
    sample does on the box, instead of stepping on at once (0, back to back: the next step may then wait
    for it). The commands are the same either way; ``idle_wait_s`` holds the time given after each step,
    ``step_wait_s`` the time each step itself waited for the solve (``stats["reach_wait_s"]``) or for a split
    reference change's rest (``stats["change_wait_s"]``, ``MpcSettings.change_split_iter``); ``change_rests`` the
    rests collected (``stats["change_finish"]``: their iterations, wall and thread CPU time on the second thread)."""

    def __init__(self, ctrl: MpcController, seed: int, scenario=SCENARIO, inlet_c: float = INLET_C,
                 idle_s: float = 0.0):
        if not 0.0 <= idle_s <= 3600.0:
            raise ValueError(f"Loop: idle_s must be in [0, 3600] s, got {idle_s}")
        self.ctrl, self.scenario, self.idle_s = ctrl, scenario, float(idle_s)
        self.plant = SimulatedPlant(seed=seed, environment=Environment(inlet_c, 5.0))
        self.plant.settle(INITIAL)
        ctrl.reset(self.plant.command)
        self.previous = self.plant.command.vector()
        self.cost: dict[str, float] = {}
        self.cpu_s: list[float] = []
        self.thread_s: list[float] = []
        self.idle_wait_s: list[float] = []
        self.step_wait_s: list[float] = []
        self.change_rests: list[dict[str, Any]] = []

    def step(self, k: int):
        """Step ``k`` (sample k of the scenario); returns the controller's :class:`StepResult`."""
        ref = reference_at(k * self.plant.dt_s, self.scenario)
        measurement = self.plant.read()
        c0, t0 = time.process_time(), time.thread_time()
        res = self.ctrl.step(measurement, ref)
        self.thread_s.append(time.thread_time() - t0)
        self.cpu_s.append(time.process_time() - c0)
        self.step_wait_s.append(float(res.stats.get("reach_wait_s", 0.0)) + float(res.stats.get("change_wait_s", 0.0)))
        if "change_finish" in res.stats:
            self.change_rests.append(res.stats["change_finish"])
        command = self.plant.apply(res.command)
        self.plant.advance()
        for term, value in stage_cost(self.ctrl.problem, self.plant.truth(), ref, command, self.previous).items():
            self.cost[term] = self.cost.get(term, 0.0) + value
        self.previous = command
        wait = getattr(self.ctrl, "wait_background", None)
        self.idle_wait_s.append(wait(self.idle_s) if self.idle_s > 0 and wait is not None else 0.0)
        return res


def lockstep(loops: dict[str, Loop], steps: int):
    """Step the ``loops`` side by side for ``steps`` samples, one step of each in turn, the order rotated from sample
    to sample (with two loops: which goes first alternates), so that the load of other processes falls on each
    alike; yields ``(k, name, StepResult)`` per step."""
    names = list(loops)
    for k in range(steps):
        r = k % len(names)
        for name in names[r:] + names[:r]:
            yield k, name, loops[name].step(k)


def closed_loop(name: str, make: Callable[[], MpcController], steps: int, seed: int, scenario=SCENARIO,
                inlet_c: float = INLET_C, idle_s: float = 0.0) -> dict[str, Any]:
    """Run one controller on a fresh plant; per-step times and the closed-loop cost. ``idle_s``: the time
    given to the second thread between steps (:class:`Loop`); ``background`` in the result says how much
    of it was used and how long steps waited all the same."""
    t_setup = time.perf_counter()
    ctrl = make()
    setup_s = time.perf_counter() - t_setup
    solver_report = getattr(ctrl.solver, "codegen", None)
    settings = dict(getattr(ctrl.solver, "settings", {}) or {})
    settings.setdefault("compiled", bool(solver_report is not None and solver_report.active))
    if isinstance(ctrl.solver, RtiOsqpSolver):
        settings.setdefault("description", RTI_DESCRIPTION)
    # the controller's report: the solver's functions and the estimator's (generated C in every
    # contender alike, MpcSettings.codegen), built or loaded apart from the timed steps
    report = getattr(ctrl, "codegen", None) or solver_report
    settings["estimator_compiled"] = bool(report is not None and any(
        k.startswith("ekf_") and not v.startswith("interpreted") for k, v in report.outcomes.items()))
    loop = Loop(ctrl, seed, scenario, inlet_c, idle_s)
    times, iters, solves, fallbacks, statuses = [], [], [], 0, {}
    for k in range(steps):
        st = loop.step(k).stats
        times.append(st["step_time_s"])
        iters.append(st["iterations"])
        solves.append(st["qp_solves"])
        fallbacks += st["fallback"] is not None
        key = str(st["status"]).split(";")[0]
        statuses[key] = statuses.get(key, 0) + 1
    cost = loop.cost
    t = np.array(times[1:]) * 1e3  # first (cold) step excluded
    c = np.array(loop.cpu_s[1:]) * 1e3
    return {
        "controller": name, "steps": steps, "setup_s": setup_s, "settings": settings,
        "problem": StageOcp(ctrl.problem).summary(),
        "codegen": dict(report.outcomes) if report is not None else {},
        "codegen_build_s": float(report.build_time_s) if report is not None else 0.0,
        "median_ms": float(np.median(t)), "p99_ms": float(np.percentile(t, 99)), "max_ms": float(t.max()),
        # CPU time of this process in the step (time.process_time): what load from other processes
        # on a shared machine inflates least
        "cpu_median_ms": float(np.median(c)), "cpu_p99_ms": float(np.percentile(c, 99)), "cpu_max_ms": float(c.max()),
        "median_iterations": float(np.median(iters[1:])), "max_iterations": int(max(iters)),
        "max_qp_solves": int(max(solves)), "fallback_steps": int(fallbacks), "statuses": statuses,
        "cost": {**cost, "total": float(sum(cost.values()))},
        "background": background_waits(loop, idle_s),
    }


#: A step's wait for the second thread below this (s) is the join's own cost, not a wait.
WAIT_FLOOR_S = 5e-5


def background_waits(loop: Loop, idle_s: float) -> dict[str, Any]:
    """How the second thread's reachable-flow solves met the steps (first step excluded, as in the times):
    the idle time allowed between steps, the steps after which the loop idled for a solve and for how long
    in all, and the steps that waited for one inside their timed step (their count, the largest wait)."""
    idle = np.array(loop.idle_wait_s[1:]) * 1e3
    waits = np.array(loop.step_wait_s[1:]) * 1e3
    waited = waits[waits > WAIT_FLOOR_S * 1e3]
    return {"idle_between_steps_s": idle_s, "idle_steps": int((idle > 0).sum()),
            "idle_total_ms": float(idle.sum()), "idle_max_ms": float(idle.max(initial=0.0)),
            "steps_waiting": int(waited.size), "step_wait_total_ms": float(waited.sum()),
            "step_wait_max_ms": float(waited.max(initial=0.0)), **change_rests(loop.change_rests)}


def change_rests(rests: list[dict[str, Any]]) -> dict[str, Any]:
    """The split reference changes' rests run on the second thread (``MpcSettings.change_split_iter``): how many,
    their OSQP iterations and their wall and thread CPU times (ms; the second thread's, not in the step times)."""
    wall = np.array([r["wall_s"] for r in rests]) * 1e3
    cpu = np.array([r["thread_cpu_s"] for r in rests]) * 1e3
    return {"change_rests": len(rests), "change_rest_iterations_max": int(max((r["iterations"] for r in rests),
                                                                              default=0)),
            "change_rest_wall_median_ms": float(np.median(wall)) if rests else 0.0,
            "change_rest_wall_max_ms": float(wall.max(initial=0.0)),
            "change_rest_thread_cpu_max_ms": float(cpu.max(initial=0.0)),
            "change_rests_failed": int(sum(not r["ok"] for r in rests))}


def background_line(name: str, bg: dict[str, Any]) -> str:
    """One printed line of :func:`background_waits`: what the step times include and what they do not."""
    if bg["idle_between_steps_s"] > 0:
        how = (f"the loop gave the second thread up to {bg['idle_between_steps_s']:g} s between steps (the rest of "
               f"the sample on the box; untimed): used after {bg['idle_steps']} steps, {bg['idle_total_ms']:.1f} ms "
               f"in all, at most {bg['idle_max_ms']:.2f} ms")
    else:
        how = "steps back to back (--back-to-back): no time between steps for the second thread"
    line = (f"{name} reachable-flow solves on the second thread: {how}; steps that waited for one inside the "
            f"timed step: {bg['steps_waiting']}, {bg['step_wait_total_ms']:.2f} ms in all, at most "
            f"{bg['step_wait_max_ms']:.2f} ms")
    if bg.get("change_rests"):
        line += (f"; split reference changes finished on the second thread: {bg['change_rests']} "
                 f"({bg['change_rests_failed']} failed), up to {bg['change_rest_iterations_max']} OSQP iterations, "
                 f"wall time median {bg['change_rest_wall_median_ms']:.2f} ms, at most "
                 f"{bg['change_rest_wall_max_ms']:.2f} ms ({bg['change_rest_thread_cpu_max_ms']:.2f} ms of that "
                 "thread's CPU), not in the step times")
    return line


def rti_suboptimality(make: Callable[[], MpcController], steps: int, seed: int, jit: bool) -> dict[str, Any]:
    """The RTI loop again (untimed), each feedback recorded, then the converged cost per step."""
    from .suboptimality import FeedbackRecorder, suboptimality
    recorder: list[FeedbackRecorder] = []

    def make_recorded() -> MpcController:
        ctrl = make()
        ctrl.solver = FeedbackRecorder(ctrl.solver)
        recorder.append(ctrl.solver)
        return ctrl

    closed_loop("rti", make_recorded, steps, seed)
    return suboptimality(recorder[0].inner.pb, recorder[0].records, jit=jit)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_STEPS} steps per controller (under a minute)")
    parser.add_argument("--steps", type=int, default=None,
                        help=f"closed-loop steps per controller (default {FULL_STEPS})")
    parser.add_argument("--seed", type=int, default=1, help="plant noise seed (default 1)")
    parser.add_argument("--cost-seeds", type=int, default=None,
                        help="seeds (from --seed on) of the RTI-against-IPOPT cost comparison "
                             "(default 5, 1 with --quick)")
    parser.add_argument("--threads", type=int, default=2, choices=(1, 2), help="cores to use (default 2)")
    parser.add_argument("--back-to-back", action="store_true",
                        help="step on at once after each step; by default the loop gives the reachable-flow solve "
                             f"on the second thread up to {IDLE_S:g} s (one sample) between steps, untimed, as the "
                             "box's sample does (the commands are the same either way)")
    parser.add_argument("--json", type=Path, default=Path("solve_time.json"), help="where to write the results")
    parser.add_argument("--no-ipopt", action="store_true", help="skip the IPOPT reference")
    parser.add_argument("--model", metavar="FILE", default=None,
                        help="model file (hvac-mpc identify): every controller predicts with this refined model")
    parser.add_argument("--no-dompc", action="store_true", help="skip do-mpc")
    parser.add_argument("--no-fatrop", action="store_true", help="skip fatrop")
    parser.add_argument("--jit", action="store_true",
                        help="IPOPT and fatrop with their NLP functions as generated C (built once, cached on "
                             "disk; the first build takes minutes and is reported apart)")
    parser.add_argument("--no-codegen", action="store_true",
                        help="run the RTI's QP data and estimator in CasADi's interpreter")
    parser.add_argument("--rti-settings", metavar="JSON", default=None,
                        help="fields of MpcSettings for the RTI contender, e.g. '{\"change_split_iter\": 30}' "
                             "(default: the defaults)")
    parser.add_argument("--no-suboptimality", action="store_true",
                        help="skip the per-step suboptimality of the RTI against converged IPOPT")
    parser.add_argument("--acados", action="store_true",
                        help="also the RTI through acados (SQP_RTI, HPIPM; optional, installed apart: "
                             "hvac_mpc.mpc.rti_acados.INSTALL_COMMAND), with its own per-step suboptimality")
    parser.add_argument("--acados-phases", action="store_true",
                        help="with --acados: thread CPU time of each acados phase (preparation, feedback QP) "
                             "over the closed loop, in the result's 'phases'")


def run(args: argparse.Namespace) -> int:
    steps = args.steps if args.steps is not None else (QUICK_STEPS if args.quick else FULL_STEPS)
    if steps < 3:
        print(f"--steps must be at least 3, got {steps}")
        return 2
    cost_seeds = args.cost_seeds if args.cost_seeds is not None else (1 if args.quick else 5)
    if not 1 <= cost_seeds <= 20:
        print(f"--cost-seeds must be in [1, 20], got {cost_seeds}")
        return 2
    try:
        rti_settings(args)
    except (ValueError, TypeError, InvalidSettings) as exc:
        print(f"--rti-settings: {exc}")
        return 2
    if getattr(args, "model", None):
        try:
            load_model_file(args.model)
        except (ValueError, FileNotFoundError) as exc:
            print(f"--model: {exc}")
            return 2
    saved = pin_cores(args.threads)
    try:
        return _run(args, steps, cost_seeds)
    finally:
        if saved is not None:
            os.sched_setaffinity(0, saved)


def pin_cores(n: int) -> set[int] | None:
    """Run this process on at most ``n`` of the cores it may use now (the benchmarks' two-core budget); returns the
    cores it could use before (to restore them), None where the platform has no affinity."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    saved = os.sched_getaffinity(0)
    os.sched_setaffinity(0, sorted(saved)[:n])
    return saved


@dataclass
class Contenders:
    """The controllers of one solve-time run, each as a factory of a fresh :class:`MpcController`,
    and what the run keeps beside them (acados' phase timers, fatrop's recorded starts, notes)."""

    make_rti: Callable[[], MpcController]
    make_ipopt: Callable[[], MpcController]
    make_acados: Callable[[], MpcController] | None
    order: list[tuple[str, Callable[[], MpcController]]]
    notes: list[str] = field(default_factory=list)
    phase_timers: list[PhaseTimer] = field(default_factory=list)
    fatrop_recorders: list = field(default_factory=list)


def rti_settings(args: argparse.Namespace) -> MpcSettings:
    """The RTI contender's settings: the defaults, ``--no-codegen``, and the fields of ``--rti-settings`` (a JSON
    object, sub-tables as nested objects, e.g. ``{"ocp": {"weights": {...}}}``; a field MpcSettings does not have or a
    value out of range raises InvalidSettings naming it)."""
    fields = json.loads(args.rti_settings) if getattr(args, "rti_settings", None) else {}
    if not isinstance(fields, dict):
        raise ValueError(f"expected a JSON object of MpcSettings fields, got {args.rti_settings!r}")
    return settings_with(MpcSettings(codegen=not getattr(args, "no_codegen", False)), fields)


def _contenders(args: argparse.Namespace) -> Contenders:
    """The run's controllers from the options: the RTI first, then acados, IPOPT, fatrop, do-mpc."""
    rti = rti_settings(args)
    model = load_model_file(args.model) if getattr(args, "model", None) else None
    make_rti = lambda: MpcController(settings=rti, model=model)  # noqa: E731
    # the reference must not be cut short by the real-time deadline
    ipopt_settings = MpcSettings(solver="ipopt", deadline_s=600.0)
    jit = bool(getattr(args, "jit", False))
    make_ipopt = lambda: MpcController(  # noqa: E731
        settings=ipopt_settings, model=model, solver_factory=lambda pb: IpoptReferenceSolver(
            pb, tol=ipopt_settings.ipopt_tol, max_iter=ipopt_settings.ipopt_max_iter, jit=jit))
    c = Contenders(make_rti, make_ipopt, None, [("rti", make_rti)])
    c.make_acados = _acados_contender(args, rti, model, c.notes, c.phase_timers)
    if c.make_acados is not None:
        c.order.append(("rti-acados", c.make_acados))
    if not args.no_ipopt:
        c.order.append(("ipopt", make_ipopt))
    if c.make_acados is not None and not getattr(args, "no_fatrop", False):
        c.notes.append(FATROP_WITH_ACADOS)
        print(FATROP_WITH_ACADOS, flush=True)
    elif not getattr(args, "no_fatrop", False):
        from .fatrop_reference import IPOPT_TOL_FACTOR, FatropSolver, StartRecorder

        def make_fatrop() -> MpcController:
            ctrl = MpcController(settings=ipopt_settings, model=model, solver_factory=lambda pb: FatropSolver(
                pb, tol=IPOPT_TOL_FACTOR * ipopt_settings.ipopt_tol, max_iter=ipopt_settings.ipopt_max_iter,
                jit=jit))
            ctrl.solver = StartRecorder(ctrl.solver)
            c.fatrop_recorders.append(ctrl.solver)
            return ctrl
        c.order.append(("fatrop", make_fatrop))
    if not args.no_dompc:
        try:
            from .dompc_reference import DoMpcSolver, _import_do_mpc
            _import_do_mpc()
            c.order.append(("do-mpc", lambda: MpcController(settings=MpcSettings(deadline_s=600.0), model=model,
                                                            solver_factory=lambda pb: DoMpcSolver(pb))))
        except ImportError as exc:
            c.notes.append(f"do-mpc skipped: {exc}")
    return c


def _ratios(results: list[dict[str, Any]]) -> None:
    """Each result's median and p99 against the RTI's and, with IPOPT in the run, its cost against IPOPT's."""
    rti = results[0]
    by_name = {r["controller"]: r for r in results}
    for r in results:
        r["median_ratio_vs_rti"] = r["median_ms"] / rti["median_ms"]
        r["p99_ratio_vs_rti"] = r["p99_ms"] / rti["p99_ms"]
        if "ipopt" in by_name:
            r["cost_vs_ipopt_pct"] = 100.0 * (r["cost"]["total"] / by_name["ipopt"]["cost"]["total"] - 1.0)


def _cost_by_seed(c: Contenders, by_name: dict[str, dict[str, Any]], steps: int, seed: int,
                  cost_seeds: int) -> list[dict[str, Any]]:
    """Closed-loop cost of the RTI and IPOPT on ``cost_seeds`` plant noise seeds from ``seed`` on
    (the first from the run itself); empty without IPOPT in the run."""
    if "ipopt" not in by_name:
        return []
    seeds_cost = [{"seed": seed, "rti": by_name["rti"]["cost"]["total"], "ipopt": by_name["ipopt"]["cost"]["total"]}]
    for s in range(seed + 1, seed + cost_seeds):
        print(f"cost comparison, seed {s}: rti and ipopt for {steps} steps ...", flush=True)
        seeds_cost.append({"seed": s, "rti": closed_loop("rti", c.make_rti, steps, s)["cost"]["total"],
                           "ipopt": closed_loop("ipopt", c.make_ipopt, steps, s)["cost"]["total"]})
    for row in seeds_cost:
        row["rti_vs_ipopt_pct"] = 100.0 * (row["rti"] / row["ipopt"] - 1.0)
    return seeds_cost


def _per_step_checks(args: argparse.Namespace, c: Contenders, by_name: dict[str, dict[str, Any]],
                     steps: int) -> None:
    """The RTI's (and acados') per-step suboptimality against converged IPOPT, and fatrop's agreement
    with IPOPT from fatrop's own states, into their results."""
    jit = bool(getattr(args, "jit", False))
    if not getattr(args, "no_suboptimality", False):
        print(f"per-step suboptimality: rti for {steps} steps, then converged IPOPT from each step's state ...",
              flush=True)
        by_name["rti"]["suboptimality"] = rti_suboptimality(c.make_rti, steps, args.seed, jit)
        if c.make_acados is not None:
            print(f"per-step suboptimality: rti-acados for {steps} steps, then converged IPOPT from each step's "
                  "state ...", flush=True)
            by_name["rti-acados"]["suboptimality"] = rti_suboptimality(c.make_acados, steps, args.seed, jit)
    if c.fatrop_recorders:
        from .fatrop_reference import agreement
        print(f"fatrop against IPOPT per step: IPOPT from fatrop's {steps} states and starts ...", flush=True)
        by_name["fatrop"]["agreement"] = agreement(c.fatrop_recorders[-1].inner.pb, c.fatrop_recorders[-1].records)


def _print_summary(results: list[dict[str, Any]], seeds_cost: list[dict[str, Any]], notes: list[str]) -> dict:
    """The table, the headline figures (returned, without their printed lines), suboptimality,
    per-seed costs, fatrop's agreement, acados' phases and the notes."""
    by_name = {r["controller"]: r for r in results}
    print_table(results)
    for r in results:
        print(background_line(r["controller"], r["background"]))
    figures = headline(results)
    for line in figures.pop("lines"):
        print(line)
    for r in (r for r in results if "suboptimality" in r):
        so = r["suboptimality"]
        print(f"{r['controller']} suboptimality per step against converged IPOPT from the same state "
              f"({so['steps']} steps, IPOPT failures {so['ipopt_failures']}):")
        for name in ("decision", "plan"):
            if name in so:
                v = so[name]
                print(f"  {name:<8} median {v['median_pct']:.3f} %, p95 {v['p95_pct']:.3f} %, "
                      f"max {v['max_pct']:.3f} %, min {v['min_pct']:.3f} %")
    if seeds_cost:
        print("closed-loop cost, RTI against IPOPT, per plant noise seed: "
              + ", ".join(f"seed {c['seed']} {c['rti_vs_ipopt_pct']:+.2f} %" for c in seeds_cost)
              + f"; median {float(np.median([c['rti_vs_ipopt_pct'] for c in seeds_cost])):+.2f} %, "
              f"largest RTI excess {max(c['rti_vs_ipopt_pct'] for c in seeds_cost):+.2f} %")
    if "agreement" in by_name.get("fatrop", {}):
        from .fatrop_reference import agreement_line
        print(agreement_line(by_name["fatrop"]["agreement"]))
    if "phases" in by_name.get("rti-acados", {}):
        print(phases_line(by_name["rti-acados"]["phases"]))
    for note in notes:
        print(note)
    return figures


def _run(args: argparse.Namespace, steps: int, cost_seeds: int) -> int:
    c = _contenders(args)
    results = []
    for name, make in c.order:
        print(f"running {name} for {steps} steps ...", flush=True)
        results.append(closed_loop(name, make, steps, args.seed,
                                   idle_s=0.0 if getattr(args, "back_to_back", False) else IDLE_S))
        if name == "rti-acados" and c.phase_timers:
            results[-1]["phases"] = c.phase_timers[0].summary(steps)
    _ratios(results)
    by_name = {r["controller"]: r for r in results}
    seeds_cost = _cost_by_seed(c, by_name, steps, args.seed, cost_seeds)
    _per_step_checks(args, c, by_name, steps)
    figures = _print_summary(results, seeds_cost, c.notes)
    out = {"steps": steps, "seed": args.seed, "threads": args.threads, "scenario_inlet_c": INLET_C,
           "python": platform.python_version(), "machine": platform.machine(), "notes": c.notes, "results": results,
           "cost_by_seed": seeds_cost, "figures": figures, "shared_description": shared_description(results)}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.json}")
    return 0


#: Why ``--acados`` skips fatrop in the same run.
FATROP_WITH_ACADOS = ("fatrop skipped: with --acados acados' BLASFEO is loaded process-wide beside the BLASFEO of "
                      "CasADi's fatrop plugin, and two BLASFEO builds in one process may mix; run fatrop without "
                      "--acados")


class PhaseTimer:
    """Stands in for the acados solver's C helper (``RtiAcadosSolver._step_lib``) and times each
    ``hvac_solve`` call by phase (1 preparation, 2 feedback) in thread CPU time, with the feedback's HPIPM
    iterations."""

    def __init__(self, lib):
        self._lib = lib
        self.cpu_s: dict[int, list[float]] = {1: [], 2: []}
        self.qp_iterations: list[int] = []

    def __getattr__(self, name: str):
        return getattr(self._lib, name)

    def hvac_solve(self, op, phase: int, qp_iter):
        t0 = time.thread_time()
        status = self._lib.hvac_solve(op, phase, qp_iter)
        self.cpu_s[phase].append(time.thread_time() - t0)
        if phase == 2:
            self.qp_iterations.append(qp_iter._obj.value)
        return status

    def summary(self, steps: int) -> dict[str, Any]:
        """Medians and p99 (ms) of each phase, preparations per step, feedback CPU time per HPIPM iteration."""
        prep, qp = np.array(self.cpu_s[1]) * 1e3, np.array(self.cpu_s[2]) * 1e3
        it = np.array(self.qp_iterations)
        per_it = qp[it > 0] / it[it > 0]
        return {"clock": "time.thread_time", "preparations": len(prep), "feedbacks": len(qp), "steps": steps,
                "preparation_median_ms": float(np.median(prep)), "feedback_median_ms": float(np.median(qp)),
                "feedback_p99_ms": float(np.percentile(qp, 99)), "qp_iterations_median": float(np.median(it)),
                "feedback_per_iteration_median_us": float(np.median(per_it) * 1e3)}


def phases_line(ph: dict[str, Any]) -> str:
    return (f"rti-acados phases (thread CPU time over {ph['steps']} steps): {ph['preparations']} preparations, "
            f"median {ph['preparation_median_ms']:.3f} ms; {ph['feedbacks']} feedback QPs, median "
            f"{ph['feedback_median_ms']:.3f} ms, p99 {ph['feedback_p99_ms']:.3f} ms, "
            f"{ph['qp_iterations_median']:.0f} HPIPM iterations median, "
            f"{ph['feedback_per_iteration_median_us']:.0f} us per iteration (median)")


def _acados_contender(args: argparse.Namespace, settings: MpcSettings, model, notes: list[str],
                      phase_timers: list | None = None):
    """The acados RTI's controller factory for ``--acados`` (the OSQP RTI's settings where they apply), or None
    (not asked for, or acados missing: the reason goes into ``notes``). With ``--acados-phases`` each solver's
    C helper is timed (:class:`PhaseTimer`, appended to ``phase_timers``)."""
    if not getattr(args, "acados", False):
        return None
    from hvac_mpc.mpc.rti_acados import AcadosMissing, RtiAcadosSolver, load_acados
    try:
        load_acados()
    except AcadosMissing as exc:
        notes.append(f"rti-acados skipped: {exc}")
        return None
    timed = getattr(args, "acados_phases", False) and phase_timers is not None

    def solver(pb):
        s = RtiAcadosSolver(pb, lm_inputs=settings.levenberg_marquardt, cold_start_qps=settings.cold_start_qps,
                            reference_change_qps=settings.reference_change_qps)
        if timed:
            s._step_lib = PhaseTimer(s._step_lib)
            phase_timers.append(s._step_lib)
        return s
    return lambda: MpcController(settings=settings, model=model, solver_factory=solver)


def shared_description(results: list[dict[str, Any]]) -> dict[str, Any]:
    """The stage-wise description the contenders are built from, and what each says it uses."""
    uses = {r["controller"]: r["settings"].get("description", "own formulation") for r in results}
    return {"problem": results[0]["problem"], "solvers": uses,
            "all_share": all(str(v).startswith("StageOcp") for v in uses.values())
            and all(r["problem"] == results[0]["problem"] for r in results)}


def headline(results: list[dict[str, Any]]) -> dict[str, Any]:
    """The RTI's figures against :data:`TARGETS`, the ratios of the others from the same run, and the
    compile times (apart from the step times); ``lines`` holds them as printed."""
    rti = results[0]
    out: dict[str, Any] = {"targets": TARGETS, "rti": {k: rti[k] for k in ("median_ms", "p99_ms", "max_ms",
                                                                            "cpu_median_ms", "cpu_p99_ms")}}
    met = {"median_ms": rti["median_ms"] <= TARGETS["median_ms"], "p99_ms": rti["p99_ms"] <= TARGETS["p99_ms"]}
    lines = [f"RTI whole step: median {rti['median_ms']:.3f} ms (target <= {TARGETS['median_ms']}: "
             f"{'met' if met['median_ms'] else 'not met'}), p99 {rti['p99_ms']:.3f} ms (target <= "
             f"{TARGETS['p99_ms']}: {'met' if met['p99_ms'] else 'not met'}), max {rti['max_ms']:.3f} ms; "
             f"process CPU time median {rti['cpu_median_ms']:.3f} ms, p99 {rti['cpu_p99_ms']:.3f} ms"]
    so = rti.get("suboptimality", {}).get("decision")
    if so:
        met["decision_median_pct"] = so["median_pct"] <= TARGETS["decision_median_pct"]
        met["decision_p95_pct"] = so["p95_pct"] <= TARGETS["decision_p95_pct"]
        out["rti"].update(decision_median_pct=so["median_pct"], decision_p95_pct=so["p95_pct"])
        lines.append(f"RTI per-step suboptimality of the applied move (converged optimum with the first move "
                     f"fixed to the RTI's, against the free optimum, same state): median {so['median_pct']:.3f} % "
                     f"(target <= {TARGETS['decision_median_pct']}), p95 {so['p95_pct']:.3f} % "
                     f"(target <= {TARGETS['decision_p95_pct']})")
    out["met"] = met
    out["ratios"] = {r["controller"]: {"median": r["median_ratio_vs_rti"], "p99": r["p99_ratio_vs_rti"],
                                       "cpu_median": r["cpu_median_ms"] / rti["cpu_median_ms"],
                                       "compiled": bool(r["settings"].get("compiled"))}
                     for r in results[1:]}
    for name, q in out["ratios"].items():
        lines.append(f"{name} ({'compiled' if q['compiled'] else 'interpreted'}): median step {q['median']:.0f}x "
                     f"the RTI's, p99 {q['p99']:.0f}x, CPU median {q['cpu_median']:.0f}x (same run)")
    out["compile_s"] = {r["controller"]: r["codegen_build_s"] for r in results}
    lines.append("compile time, apart from the step times: " + ", ".join(
        f"{r['controller']} {r['codegen_build_s']:.1f} s" + (f" ({sorted(set(r['codegen'].values()))})"
                                                           if r["codegen"] else "") for r in results))
    out["lines"] = lines
    return out


def print_table(results: list[dict[str, Any]]) -> None:
    head = (f"{'controller':<10} {'median ms':>10} {'p99 ms':>9} {'max ms':>9} {'cpu med':>8} {'x rti med':>9} "
            f"{'x rti p99':>9} {'iters':>6} {'fallback':>8} {'cost':>9} {'vs ipopt':>9}")
    print(head)
    print("-" * len(head))
    for r in results:
        vs = f"{r['cost_vs_ipopt_pct']:+.1f} %" if "cost_vs_ipopt_pct" in r else "-"
        print(f"{r['controller']:<10} {r['median_ms']:>10.2f} {r['p99_ms']:>9.2f} {r['max_ms']:>9.2f} "
              f"{r['cpu_median_ms']:>8.2f} "
              f"{r['median_ratio_vs_rti']:>9.1f} {r['p99_ratio_vs_rti']:>9.1f} {r['median_iterations']:>6.0f} "
              f"{r['fallback_steps']:>8d} {r['cost']['total']:>9.1f} {vs:>9}")
