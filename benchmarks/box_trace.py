"""One box of the sweep on one mismatch scenario, second by second, with the MPC's filter statistics.

    python -m hvac_mpc.benchmarks.box_trace --box LABEL:FIELD=VALUE,... [--scenario NAME] [--quick]
        [--plant-seed 0] [--settings JSON] [--window 30] [--from S] [--to S] [--json FILE]

The box is a ``--box`` text of :mod:`.box_sweep` (``box_sweep --list`` prints them; :func:`.mismatch_suite.parse_box`
reads it). Both controllers run the scenario on the box as the suite runs them (:func:`.bench.run_benchmark`, the
deterministic deadline); the MPC's step is wrapped to record its statistics (the filter in use, its mixed-air offset,
the honoured dead time, the valve a cap). Printed: the thermocouple IAE (the bench's: noise-free against the
reference from the scored start) of both and their ratio per segment of the supply-temperature reference and per
window of ``--window`` s; then, from ``--from`` to ``--to`` s, one row per second: reference, both thermocouples, the
MPC's commands (blower W, heater W, valve a %, valve m %), the baseline's valve a, the filter in use, the offset,
the dead time, and the box's undelayed supply air (``IndependentBox.truth``). Measured in docs/robustness.md
sec. 2.26.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from hvac_mpc.contract import INPUTS
from hvac_mpc.models import Parameters

from . import bench, mismatch_suite, scenarios as scenario_defs
from .box_sweep import mpc_factory_with

#: Statistics of the MPC's step recorded per second (names of ``StepResult.stats``).
RECORDED_STATS = ("offset_placement", "mix_offset_c", "dead_time_s", "valve_a_cap_pct", "fallback")
#: Columns of the command vector printed (:data:`hvac_mpc.contract.INPUTS`).
BLOWER, HEATER, VALVE_A, VALVE_M = (INPUTS.index(n) for n in ("blower_power_w", "heater_cmd_w", "valve_a_pct",
                                                            "valve_m_pct"))


def recording(make_mpc, rows: list):
    """A factory like ``make_mpc`` whose controllers append their step's :data:`RECORDED_STATS` to ``rows``."""
    def factory(command):
        controller = make_mpc(command)
        step = controller.step

        def recorded(measurement, reference):
            result = step(measurement, reference)
            stats = result.stats or {}
            rows.append({k: stats.get(k) for k in RECORDED_STATS})
            return result
        controller.step = recorded
        return controller
    return factory


def run_trace(box: str, scenario_name: str, quick: bool = False, plant_seed: int = 0,
              settings: Mapping[str, Any] | None = None) -> dict:
    """Both controllers on one scenario of one box; the traces, the MPC's recorded statistics and the scenario."""
    label, variant = mismatch_suite.parse_box(box)
    known = scenario_defs.mismatch_scenarios()
    if scenario_name not in known:
        raise ValueError(f"--scenario: unknown {scenario_name!r}; known: {sorted(known)}")
    scenario = known[scenario_name].quick() if quick else known[scenario_name]
    rows: list = []
    factories = {"baseline": bench.baseline_factory(), "mpc": recording(mpc_factory_with(settings), rows)}
    res, traces = bench.run_benchmark([scenario], factories, plant_seed,
                                      plant_factory=mismatch_suite.variant_factory(variant))
    sc = res["scenarios"][scenario.name]
    return {"label": label, "scenario": scenario, "mpc": traces[scenario.name]["mpc"],
            "baseline": traces[scenario.name]["baseline"], "stats": rows,
            "ratio": sc["ratios"].get("temp_iae_cs"),
            "iae": {c: sc[c]["figures"]["temp_iae_cs"] for c in ("mpc", "baseline")}}


#: A move of valve a counted by :func:`reversals` (% of travel): the search's share, 5 % of the range.
REVERSAL_MOVE_PCT = 5.0


def reversals(values: np.ndarray, min_move: float = REVERSAL_MOVE_PCT) -> np.ndarray:
    """Indices ``k`` of the samples whose move ``values[k] - values[k-1]`` (beyond ``min_move``) turns against the
    last move beyond ``min_move`` (a sample held between two such moves does not hide the second): the turns of an
    actuator's two-cycle, counted as :func:`hvac_mpc.mpc.reversal_search.turned_inputs` names them in a plan."""
    out, last = [], 0.0
    v = np.asarray(values, float)
    for k in range(1, v.size):
        move = v[k] - v[k - 1]
        if abs(move) > min_move:
            if move * last < 0.0:
                out.append(k)
            last = move
    return np.asarray(out, dtype=int)


def reversals_at_heater_bound(applied: np.ndarray, heater_max_w: float, share: float = 0.02) -> tuple[int, int]:
    """Valve a's :func:`reversals` in the applied commands ``applied`` (T x 6, :data:`hvac_mpc.contract.INPUTS`): all
    of them, and those with the heater command within ``share`` of ``heater_max_w`` (W) at the sample and the one
    before (the heater at its bound)."""
    u = np.asarray(applied, float)
    k = reversals(u[:, VALVE_A])
    at = (u[:, HEATER] >= (1.0 - share) * heater_max_w)
    return int(k.size), int(np.sum(at[k] & at[k - 1])) if k.size else 0


def abs_error(trace, start_s: float) -> np.ndarray:
    """|thermocouple - reference| (noise-free, degC) per sample, zero before ``start_s`` (the scored start)."""
    err = np.abs(trace.truth["supply_temp_c"] - trace.reference["supply_temp_c"])
    err = np.where(np.isfinite(err), err, 0.0)
    return np.where(trace.time_s >= start_s, err, 0.0)


def segment_iae(run: Mapping) -> list[dict]:
    """IAE (C s) of both controllers per segment of the scenario (from the scored start)."""
    sc = run["scenario"]
    dt = run["mpc"].dt_s
    e = {c: abs_error(run[c], sc.metrics_start_s) for c in ("mpc", "baseline")}
    t = run["mpc"].time_s
    out = []
    for start, seg in zip(sc.step_times_s(), sc.segments):
        sl = (t >= start) & (t < start + seg.duration_s)
        out.append({"start_s": float(start), "supply_c": seg.reference.supply_temp_c,
                    "flow_m3h": seg.reference.volume_flow_m3s / scenario_defs.M3H,
                    "mpc": float(e["mpc"][sl].sum() * dt), "baseline": float(e["baseline"][sl].sum() * dt)})
    return out


def window_iae(run: Mapping, window_s: float) -> list[dict]:
    """IAE (C s) of both controllers per window of ``window_s`` from the scenario's start."""
    sc = run["scenario"]
    dt = run["mpc"].dt_s
    e = {c: abs_error(run[c], sc.metrics_start_s) for c in ("mpc", "baseline")}
    n = max(1, int(round(window_s / dt)))
    return [{"start_s": k * dt, "mpc": float(e["mpc"][k:k + n].sum() * dt),
             "baseline": float(e["baseline"][k:k + n].sum() * dt)} for k in range(0, len(e["mpc"]), n)]


def _number(v, fmt: str) -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, fmt)


def seconds(run: Mapping, start_s: float, end_s: float) -> list[str]:
    """One line per second in [start_s, end_s)."""
    m, b = run["mpc"], run["baseline"]
    lines = ["t ref | tc_mpc tc_base | blower_w heater_w a% m% | a%_base | filter offset_c dead_s | air_mpc"]
    for k in np.flatnonzero((m.time_s >= start_s) & (m.time_s < end_s)):
        s = run["stats"][k] if k < len(run["stats"]) else {}
        u = m.applied[k]
        lines.append(
            f"{m.time_s[k]:.0f} {m.reference['supply_temp_c'][k]:.2f} | {m.truth['supply_temp_c'][k]:.2f} "
            f"{b.truth['supply_temp_c'][k]:.2f} | {u[BLOWER]:.0f} {u[HEATER]:.0f} {u[VALVE_A]:.0f} {u[VALVE_M]:.0f} | "
            f"{b.applied[k][VALVE_A]:.0f} | {s.get('offset_placement')} {_number(s.get('mix_offset_c'), '.2f')} "
            f"{_number(s.get('dead_time_s'), '.1f')} | {_number(m.truth['supply_air_temp_c'][k], '.2f')}"
            + (f" fallback={s['fallback']}" if s.get("fallback") else ""))
    return lines


def text(run: Mapping, window_s: float, start_s: float | None, end_s: float | None) -> str:
    lines = [f"{run['label']} / {run['scenario'].name}: MPC {run['iae']['mpc']:.1f} C s, baseline "
             f"{run['iae']['baseline']:.1f} C s, ratio {run['ratio']:.3f}", "segment: start s, ref C, flow m3/h, "
             "MPC, baseline IAE C s"]
    lines += [f"  {s['start_s']:.0f} {s['supply_c']:.2f} {s['flow_m3h']:.0f}: {s['mpc']:.1f} {s['baseline']:.1f}"
              for s in segment_iae(run)]
    total, at_bound = reversals_at_heater_bound(run["mpc"].applied, Parameters().heater_power_max_w)
    lines.append(f"MPC valve a reversals (moves beyond {REVERSAL_MOVE_PCT:.0f} %): {total}, with the heater at its "
                 f"bound: {at_bound}")
    lines.append(f"windows of {window_s:.0f} s (start: MPC, baseline; difference above 1 C s marked *)")
    lines += [f"  {w['start_s']:.0f}: {w['mpc']:.1f} {w['baseline']:.1f}" + (" *" if w["mpc"] - w["baseline"] > 1.0
                                                                            else "")
              for w in window_iae(run, window_s)]
    if start_s is not None:
        lines += seconds(run, start_s, end_s if end_s is not None else start_s + 60.0)
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hvac_mpc.benchmarks.box_trace", description=__doc__.split("\n")[0])
    p.add_argument("--box", required=True, help="LABEL:FIELD=VALUE,... (box_sweep --list)")
    p.add_argument("--scenario", default="winter_heating_steps", help="a mismatch scenario's name")
    p.add_argument("--quick", action="store_true", help="the quick scenario (default: full length)")
    p.add_argument("--plant-seed", type=int, default=0, help="the suite's --seed (the plant's noise)")
    p.add_argument("--settings", type=json.loads, default=None, help="MpcSettings fields, JSON")
    p.add_argument("--window", type=float, default=30.0, help="IAE window (s)")
    p.add_argument("--from", dest="start_s", type=float, default=None, help="first second printed")
    p.add_argument("--to", dest="end_s", type=float, default=None, help="end of the seconds printed")
    p.add_argument("--json", type=Path, default=None, help="write the per-second rows to this file")
    args = p.parse_args(argv)
    try:
        run = run_trace(args.box, args.scenario, args.quick, args.plant_seed, args.settings)
    except ValueError as exc:
        print(f"box_trace: {exc}", file=sys.stderr)
        return 2
    print(text(run, args.window, args.start_s, args.end_s))
    if args.json:
        m, b = run["mpc"], run["baseline"]
        args.json.write_text(json.dumps({
            "time_s": m.time_s.tolist(), "reference_c": m.reference["supply_temp_c"].tolist(),
            "mpc_tc_c": m.truth["supply_temp_c"].tolist(), "baseline_tc_c": b.truth["supply_temp_c"].tolist(),
            "mpc_applied": m.applied.tolist(), "baseline_applied": b.applied.tolist(),
            "mpc_air_c": m.truth["supply_air_temp_c"].tolist(), "stats": run["stats"],
            "segments": segment_iae(run)}, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
