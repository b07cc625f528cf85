"""A reference change's QPs traced: OSQP's iterations, step size ``rho`` at the start and the end, and (OSQP's Python
interface only) its residuals and step-size estimate, per QP of each change and of the steps after it.

    python -m hvac_mpc.benchmarks.change_rho [--seeds 1 2 3] [--reserve] [--interface] [--settings JSON] [--json FILE]

Two loops (docs/architecture.md, 'The change's step size'): the solve-time loop (:class:`.solve_time.Loop`, its seven
reference changes) per seed, and the heater reserve's step down at 390 s (``--reserve``; the literal-cooler box of
``tests/test_reserve_step_down.py``, noise seed 0, the reserve's weight 3e-4) with the heat off and with sec. 2.37's
heat package F (``EkfSettings``: ``q_supply_heat_w`` 0.5, released and level-neutral at rest, both holds 10 s).
``--settings``: ``MpcSettings`` fields (JSON, nested tables as mappings) on top of the defaults; ``--interface``: OSQP's
Python interface in place of its generated C (the same arithmetic; it reports the residuals). Deterministic: the
deadline is lifted, so the figures do not depend on the load.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from hvac_mpc.mismatch import make_plant
from hvac_mpc.mpc.estimator import EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import OcpSpec, Weights
from hvac_mpc.mpc.settings_file import settings_with

from . import scenarios, solve_time
from .simulate import DETERMINISTIC_DEADLINE_S, plant_seed

#: Steps after a change whose QPs are listed with it.
WAKE = 5
#: Sec. 2.37's heat package F (the ``ekf`` fields).
HEAT_F = {"q_supply_heat_w": 0.5, "supply_heat_release_at_rest": True, "supply_heat_level_neutral_at_rest": True,
          "supply_heat_release_hold_s": 10.0, "supply_heat_step_hold_s": 10.0}
#: The reserve's step down: 22 C held this long (s), then 15 C scored this long (s) (tests/test_reserve_step_down.py).
HELD_S, AFTER_S = 390, 40


class QpTrace:
    """Stands in for the RTI's OSQP core (``RtiOsqpSolver._core``) and keeps per QP the control step (``step``, set by
    the caller), OSQP's iterations and status, its step size at the start and the end and, where OSQP's Python
    interface answers, its residuals, step-size estimate and adaptations at the end."""

    def __init__(self, core):
        self.core, self.step, self.qps = core, 0, []

    def _traced(self, solve):
        rho0 = self.core.rho
        status_val, status, n, x = solve()
        row = {"step": self.step, "iterations": int(n), "status": str(status), "rho_start": rho0,
               "rho_end": self.core.rho}
        info = getattr(getattr(self.core, "core", None), "info", None)
        if info is not None:
            row.update(prim_res=float(info.prim_res), dual_res=float(info.dual_res),
                       rho_estimate=float(info.rho_estimate), rho_updates=int(info.rho_updates))
        self.qps.append(row)
        return status_val, status, n, x

    def solve(self):
        return self._traced(self.core.solve)

    def solve_capped(self, max_iter):
        return self._traced(lambda: self.core.solve_capped(max_iter))

    def __getattr__(self, name):
        return getattr(self.core, name)


def _traced_controller(settings: MpcSettings) -> tuple[MpcController, QpTrace]:
    ctrl = MpcController(settings=settings)
    solver = ctrl.solver
    trace = QpTrace(solver._core)
    solver._core = trace
    setup = solver._setup_osqp

    def traced_setup(*args, **kw):  # a reset after a fallback sets OSQP up anew: the trace stays in between
        setup(*args, **kw)
        trace.core, solver._core = solver._core, trace

    solver._setup_osqp = traced_setup
    return ctrl, trace


def per_change(trace: QpTrace, changes: list[int], wake: int = WAKE) -> list[dict[str, Any]]:
    """Each change's QPs and those of the ``wake`` steps after it (the trace's rows)."""
    return [{"step": c, "qps": [q for q in trace.qps if q["step"] == c],
             "wake": [q for q in trace.qps if c < q["step"] <= c + wake]} for c in changes]


def loop_run(seed: int, fields: dict, interface: bool, steps: int = solve_time.FULL_STEPS) -> dict[str, Any]:
    """The solve-time loop of ``seed`` with the defaults and ``fields``: the closed-loop cost, OSQP's iterations and
    each change's QPs."""
    settings = settings_with(MpcSettings(deadline_s=DETERMINISTIC_DEADLINE_S, osqp_codegen=not interface), fields)
    ctrl, trace = _traced_controller(settings)
    loop = solve_time.Loop(ctrl, seed)
    iterations, fallbacks = [], 0
    for k in range(steps):
        trace.step = k
        st = loop.step(k).stats
        iterations.append(int(st["iterations"]))
        fallbacks += st["fallback"] is not None
    changes = [k for k in range(1, steps) if solve_time.reference_at(k) != solve_time.reference_at(k - 1)]
    wake = [k for c in changes for k in range(c + 1, c + 1 + WAKE)]
    return {"seed": seed, "cost": float(sum(loop.cost.values())), "iterations": int(sum(iterations[1:])),
            "change_iterations": int(sum(iterations[c] for c in changes)),
            "wake_iterations": int(sum(iterations[k] for k in wake if k < steps)),
            "largest_plain": int(max(v for k, v in enumerate(iterations) if k and k not in changes)),
            "fallbacks": fallbacks, "changes": per_change(trace, changes)}


def step_down_scenario() -> scenarios.Scenario:
    """trapped_air_release's heater-limited 22 C held :data:`HELD_S`, then its step down to 15 C for :data:`AFTER_S`."""
    base = scenarios.trapped_air_release()
    held, lower = base.segments
    return dataclasses.replace(base, warmup=dataclasses.replace(base.warmup, duration_s=float(HELD_S),
                                                                reference=held.reference),
                               segments=(dataclasses.replace(lower, duration_s=float(AFTER_S)),))


def reserve_run(heat: bool, fields: dict, interface: bool) -> dict[str, Any]:
    """The reserve's step down (module doc) with the heat off or F and ``fields``: valve a's command at 390 s (%), the
    thermocouple IAE from the step on (C s), whether the step fell back, and the change's QPs."""
    sc = step_down_scenario()
    base = MpcSettings(ocp=OcpSpec(weights=Weights(valve_a_reserve_per_pct2=3e-4)), initial_command=sc.initial_command,
                       deadline_s=DETERMINISTIC_DEADLINE_S, osqp_codegen=not interface,
                       ekf=EkfSettings(**HEAT_F) if heat else EkfSettings())
    ctrl, trace = _traced_controller(settings_with(base, fields))
    plant = make_plant("cooler_literal", seed=plant_seed(0, sc.seed), inlet_temp_c=sc.inlet_temp_c,
                       chiller_setpoint_c=sc.chiller_setpoint_c, initial_command=sc.initial_command)
    ctrl.reset(sc.initial_command)
    iae, valve_a, fallback = 0.0, float("nan"), None
    for k in range(int(sc.duration_s)):
        trace.step = k
        r = sc.reference_at(float(k))
        m, truth = plant.read(), plant.truth()
        if k >= HELD_S:
            iae += abs(truth["supply_temp_c"] - r.supply_temp_c)
        res = ctrl.step(m, r)
        u = np.asarray(res.command.vector(), float)
        if k == HELD_S:
            valve_a, fallback = float(u[ctrl.problem.i_valve_a]), res.stats["fallback"]
        plant.apply(u)
        plant.advance()
    return {"heat": "F" if heat else "off", "valve_a_pct": valve_a, "iae_cs": iae, "fallback": fallback,
            "changes": per_change(trace, [HELD_S])}


def _qp(q: dict) -> str:
    res = (f", prim {q['prim_res']:.3g} dual {q['dual_res']:.3g} est {q['rho_estimate']:.3g} upd {q['rho_updates']}"
           if "prim_res" in q else "")
    return f"{q['iterations']} it {q['status']} rho {q['rho_start']:.3g}->{q['rho_end']:.3g}{res}"


def lines(run: dict[str, Any]) -> list[str]:
    head = (f"seed {run['seed']} cost {run['cost']:.2f} iterations {run['iterations']} changes "
            f"{run['change_iterations']} wake {run['wake_iterations']} largest plain {run['largest_plain']} "
            f"fallbacks {run['fallbacks']}" if "seed" in run else
            f"reserve heat {run['heat']}: valve a {run['valve_a_pct']:.1f} % IAE {run['iae_cs']:.2f} C s "
            f"fallback {run['fallback']}")
    out = [head]
    for c in run["changes"]:
        out.append(f"  change {c['step']}: " + " | ".join(_qp(q) for q in c["qps"]))
        out.append("    wake: " + ", ".join(f"{q['step']}: {q['iterations']} ({q['rho_start']:.2g}->{q['rho_end']:.2g})"
                                           for q in c["wake"]))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3], help="solve-time loop seeds (none: skip)")
    parser.add_argument("--reserve", action="store_true", help="also the reserve's step down, heat off and F")
    parser.add_argument("--interface", action="store_true", help="OSQP's Python interface (residuals reported)")
    parser.add_argument("--settings", type=json.loads, default={}, help="MpcSettings fields, JSON")
    parser.add_argument("--json", type=Path, help="write the traces here")
    args = parser.parse_args(argv)
    runs = []
    for seed in args.seeds:
        runs.append(loop_run(seed, args.settings, args.interface))
        print("\n".join(lines(runs[-1])), flush=True)
    if args.reserve:
        for heat in (False, True):
            runs.append(reserve_run(heat, args.settings, args.interface))
            print("\n".join(lines(runs[-1])), flush=True)
    if args.json:
        args.json.write_text(json.dumps({"settings": args.settings, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
