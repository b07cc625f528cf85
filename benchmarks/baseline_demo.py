"""``hvac-mpc baseline``: the thesis baseline on the simulated plant (all effects on, seeded).

Three cases, each a reference step after a settling phase under closed-loop control:

- cooling: room/inlet air 32 C (thesis sec. 6 proband tests), chiller set point 5 C, supply
  reference 24 -> 18 C with the thermocouple; time to reach and stay within +-0.5 C (thesis
  sec. 5.4.1 reports a rise of about 60 s) and overshoot.
- calibration: the same cooling step with the old slow sensor (tau 100.4 s) and its PI, for
  which the thesis reports about 400 s (shows the plant's valve-a gain agrees with the thesis).
- volume flow: 0.02 -> 0.04 m3/s tracked by the PI of thesis sec. 5.1; time to reach and stay
  within 5 % and overshoot.
- heating: winter inlet 12 C, chiller water at the inlet temperature (set point = inlet), supply
  reference 13.5 -> 17.5 C, with valve a capped at 80 % (thesis sec. 5.4.2) and, for comparison,
  with the cap lifted; peak deviation above the reference after first reaching +-0.5 C (the
  trapped-air release of thesis fig. 47).

Metrics use the plant's noise-free outputs (``SimulatedPlant.truth``): the thermocouple reading
and the true total flow. Prints a table, writes ``baseline_results.json`` and one PNG per case
into ``--out`` (PNG needs matplotlib: ``pip install -e ".[plot]"``).
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from hvac_mpc.models import Environment, Parameters, SimulatedPlant, chiller

from hvac_mpc.contract import Command
from hvac_mpc.mpc.baseline import BaselineController, BaselineGains
from hvac_mpc.contract import Reference

from .metrics import overshoot as step_overshoot
from .metrics import time_in_band_s

TEMP_BAND_C = 0.5
FLOW_BAND = 0.05
SPLIT_SHARES = (0.5, 0.25, 0.25)  # middle, feet, windshield: summer-like split (thesis fig. 53)


@dataclass
class Trace:
    """Time series of one run; time 0 is the reference step."""

    time_s: np.ndarray
    supply_temp_c: np.ndarray          # thermocouple reading, noise-free
    supply_temp_meas_c: np.ndarray     # what the controller saw
    volume_flow_m3s: np.ndarray        # true total flow
    ref_supply_temp_c: np.ndarray
    ref_volume_flow_m3s: np.ndarray
    blower_power_w: np.ndarray
    heater_cmd_w: np.ndarray
    valve_a_pct: np.ndarray
    valves_mfw_pct: np.ndarray         # (n, 3)
    heater_temp_c: np.ndarray
    mode: list
    step_time_s: np.ndarray


# ---------------------------------------------------------------------- metrics (pure)
def time_to_stay_within(time_s: Sequence[float], y: Sequence[float], ref: float, band: float) -> float | None:
    """First time (s, from the step at t = 0) after which |y - ref| <= band to the end; None if never."""
    t = np.asarray(time_s, float)
    after = t >= 0
    dt_s = float(t[1] - t[0])
    settle = time_in_band_s(np.asarray(y, float)[after], ref, band, dt_s)
    return None if settle is None else float(t[after][0] + settle)


def first_time_within(time_s: Sequence[float], y: Sequence[float], ref: float, band: float) -> float | None:
    """First time (s) at or after the step with |y - ref| <= band; None if never."""
    t = np.asarray(time_s, float)
    inside = (np.abs(np.asarray(y, float) - ref) <= band) & (t >= 0)
    return float(t[np.argmax(inside)]) if inside.any() else None


def overshoot(time_s: Sequence[float], y: Sequence[float], before: float, after: float) -> float:
    """Largest excursion beyond the new reference in the step's direction (units of y, >= 0)."""
    t = np.asarray(time_s, float)
    return step_overshoot(np.asarray(y, float)[t >= 0], before, after)


def peak_after(time_s: Sequence[float], y: Sequence[float], ref: float, start_s: float | None) -> float | None:
    """Largest y - ref at or after ``start_s`` (None when ``start_s`` is None)."""
    if start_s is None:
        return None
    t = np.asarray(time_s, float)
    return float(np.max(np.asarray(y, float)[t >= start_s] - ref))


# ---------------------------------------------------------------------- simulation
def simulate_step(environment: Environment, before: Reference, after: Reference, pre_s: int, post_s: int,
                  seed: int = 0, gains: BaselineGains | None = None, params: Parameters | None = None) -> Trace:
    """Run the baseline on the simulated plant (all effects on): ``before`` for ``pre_s`` s, then ``after``."""
    params = params or Parameters()
    plant = SimulatedPlant(params, seed=seed, environment=environment)
    blower_w = before.volume_flow_m3s / params.flow_per_watt_m3s_per_w
    plant.settle(Command(blower_w, 0.0, 50.0, 100.0, 100.0, 100.0))
    ctrl = BaselineController(params, dt_s=plant.dt_s, gains=gains)
    rows = []
    for k in range(-pre_s, post_s):
        ref = before if k < 0 else after
        meas = plant.read()
        res = ctrl.step(meas, ref)
        plant.apply(res.command)
        plant.advance()
        y = plant.truth()
        c = res.command
        rows.append((k + 1, y["supply_temp_c"], meas.supply_temp_c, y["volume_flow_m3s"], ref.supply_temp_c,
                     ref.volume_flow_m3s, c.blower_power_w, c.heater_cmd_w, c.valve_a_pct,
                     (c.valve_m_pct, c.valve_f_pct, c.valve_w_pct), y["heater_temp_c"], res.stats["mode"],
                     res.stats["step_time_s"]))
    cols = list(zip(*rows))
    return Trace(*(np.asarray(cols[i], float) for i in range(11)), mode=list(cols[11]),
                 step_time_s=np.asarray(cols[12], float))


def step_figures(tr: Trace, before_c: float, after_c: float) -> dict:
    """Settle time, first entry into +-0.5 C and overshoot of a supply-temperature step of ``tr``."""
    t, y = tr.time_s, tr.supply_temp_c
    return {"time_to_stay_within_0p5c_s": time_to_stay_within(t, y, after_c, TEMP_BAND_C),
            "first_within_0p5c_s": first_time_within(t, y, after_c, TEMP_BAND_C),
            "overshoot_c": overshoot(t, y, before_c, after_c)}


def cooling_case(seed: int = 0) -> tuple[Trace, dict]:
    """Cooling step 24 -> 18 C at 32 C inlet, chiller at 5 C, 0.03 m3/s split 50/25/25 %."""
    before = Reference.from_split(24.0, 0.03, SPLIT_SHARES)
    after = Reference.from_split(18.0, 0.03, SPLIT_SHARES)
    tr = simulate_step(Environment(32.0, 5.0), before, after, pre_s=300, post_s=300, seed=seed)
    t, y = tr.time_s, tr.supply_temp_c
    return tr, {
        "inlet_temp_c": 32.0, "chiller_setpoint_c": 5.0, "ref_before_c": 24.0, "ref_after_c": 18.0,
        **step_figures(tr, 24.0, 18.0),
        "mean_abs_error_last_120s_c": float(np.mean(np.abs(y[t > t[-1] - 120] - 18.0))),
        "modes": sorted(set(tr.mode)),
        "mean_step_time_s": float(np.mean(tr.step_time_s)),
    }


def cooling_slow_sensor_case(seed: int = 0) -> tuple[Trace, dict]:
    """Calibration: the same cooling step with the old slow sensor (tau_s = 100.4 s, thesis sec. 2.4)
    and its PI (kp 3, ki 0.09, kaw 0.1, thesis sec. 5.4.1), for which the thesis reports ~400 s."""
    params = Parameters().replace(tau_tc_s=Parameters().tau_slow_sensor_s)
    tr = simulate_step(Environment(32.0, 5.0), Reference(24.0, 0.03), Reference(18.0, 0.03), pre_s=1500,
                       post_s=1500, seed=seed, gains=BaselineGains.slow_sensor(), params=params)
    return tr, {
        "sensor_tau_s": params.tau_tc_s, "ref_before_c": 24.0, "ref_after_c": 18.0,
        **step_figures(tr, 24.0, 18.0),
        "thesis_rise_s": 400.0,
    }


def flow_case(seed: int = 0) -> tuple[Trace, dict]:
    """Volume-flow step 0.02 -> 0.04 m3/s at 20 C supply (cooling, inlet 32 C), split 50/25/25 %."""
    before = Reference.from_split(20.0, 0.02, SPLIT_SHARES)
    after = Reference.from_split(20.0, 0.04, SPLIT_SHARES)
    tr = simulate_step(Environment(32.0, 5.0), before, after, pre_s=200, post_s=200, seed=seed)
    t, v = tr.time_s, tr.volume_flow_m3s
    return tr, {
        "ref_before_m3s": 0.02, "ref_after_m3s": 0.04,
        "time_to_stay_within_5pct_s": time_to_stay_within(t, v, 0.04, FLOW_BAND * 0.04),
        "first_within_5pct_s": first_time_within(t, v, 0.04, FLOW_BAND * 0.04),
        "overshoot_pct": 100.0 * overshoot(t, v, 0.02, 0.04) / 0.04,
        "mean_abs_error_last_60s_pct": float(100.0 * np.mean(np.abs(v[t > t[-1] - 60] - 0.04)) / 0.04),
    }


def heating_case(seed: int = 0, valve_a_max_pct: float = 80.0) -> tuple[Trace, dict]:
    """Heating step 13.5 -> 17.5 C at 12 C inlet, chiller water at inlet temperature, 0.02 m3/s."""
    before = Reference(13.5, 0.02)
    after = Reference(17.5, 0.02)
    gains = BaselineGains(heat_valve_a_max_pct=valve_a_max_pct)
    params = Parameters()
    tr = simulate_step(Environment(12.0, 12.0), before, after, pre_s=300, post_s=900, seed=seed, gains=gains,
                       params=params)
    t, y = tr.time_s, tr.supply_temp_c
    first = first_time_within(t, y, 17.5, TEMP_BAND_C)
    return tr, {
        "inlet_temp_c": 12.0, "chiller_setpoint_c": 12.0, "ref_before_c": 13.5, "ref_after_c": 17.5,
        "valve_a_max_pct": valve_a_max_pct,
        "first_within_0p5c_s": first,
        "time_to_stay_within_0p5c_s": time_to_stay_within(t, y, 17.5, TEMP_BAND_C),
        "peak_above_ref_after_first_within_c": peak_after(t, y, 17.5, first),
        "valve_a_peak_pct": float(np.max(tr.valve_a_pct[t >= 0])),
        "seconds_valve_a_above_trap_threshold": int(np.sum(tr.valve_a_pct[t >= 0] > params.trap_threshold_pct)),
        "modes": sorted(set(tr.mode)),
    }


def cooling_grid(seed: int = 0, inlets_c=(25.0, 28.0, 32.0), waters_c=(5.0, 8.0, 12.0),
                 starts_c=(22.0, 24.0, 26.0), steps_c=(3.0, 5.0, 7.0)) -> list[dict]:
    """Cooling steps over operating points: time to stay within +-0.5 C with the thermocouple and
    the thesis PID, and with the slow sensor and its PI (thesis sec. 5.4.1: ~60 s and ~400 s).

    A point is kept when the start lies below the inlet and the target at least 1 C above what
    the cooler core delivers (thesis sec. 4.2 fit, at that inlet and water temperature).
    """
    params = Parameters()
    slow = params.replace(tau_tc_s=params.tau_slow_sensor_s)
    rows = []
    for tin in inlets_c:
        for tw in waters_c:
            core_c = float(chiller.cooler_outlet_c(tin, tw, params))
            for r0 in starts_c:
                for dr in steps_c:
                    r1 = r0 - dr
                    if r0 >= tin - 0.5 or r1 <= core_c + 1.0:
                        continue
                    env, before, after = Environment(tin, tw), Reference(r0, 0.03), Reference(r1, 0.03)
                    fast = simulate_step(env, before, after, 300, 600, seed=seed, params=params)
                    sl = simulate_step(env, before, after, 1500, 2500, seed=seed, gains=BaselineGains.slow_sensor(),
                                       params=slow)
                    rows.append({"inlet_temp_c": tin, "water_setpoint_c": tw, "ref_before_c": r0, "ref_after_c": r1,
                                 "thermocouple_pid_s": step_figures(fast, r0, r1)["time_to_stay_within_0p5c_s"],
                                 "slow_sensor_pi_s": step_figures(sl, r0, r1)["time_to_stay_within_0p5c_s"]})
    return rows


def _seconds(v: float | None) -> str:
    return "never" if v is None else f"{v:.0f}"


def grid_table(rows: list[dict]) -> str:
    """The printed cooling grid and its range."""
    lines = [f"{'inlet C':>7} {'water C':>7} {'step C':>13} {'thermocouple+PID s':>19} {'slow sensor+PI s':>17}"]
    for r in rows:
        lines.append(f"{r['inlet_temp_c']:>7.0f} {r['water_setpoint_c']:>7.0f} "
                     f"{r['ref_before_c']:>6.0f} -> {r['ref_after_c']:<3.0f} {_seconds(r['thermocouple_pid_s']):>19} "
                     f"{_seconds(r['slow_sensor_pi_s']):>17}")
    fast = [r["thermocouple_pid_s"] for r in rows if r["thermocouple_pid_s"] is not None]
    slow = [r["slow_sensor_pi_s"] for r in rows if r["slow_sensor_pi_s"] is not None]
    if fast and slow:
        lines.append(f"{len(rows)} points: thermocouple + PID {min(fast):.0f}-{max(fast):.0f} s (thesis ~60 s), "
                     f"slow sensor + PI {min(slow):.0f}-{max(slow):.0f} s (thesis ~400 s)")
    return "\n".join(lines)


# ---------------------------------------------------------------------- output
def _fmt(v, unit: str = "") -> str:
    if v is None:
        return "never"
    return f"{v:.2f}{unit}" if isinstance(v, float) else f"{v}{unit}"


def results_table(results: dict) -> str:
    """The printed summary: one row per (case, metric)."""
    c, s, f, h, n = (results[k] for k in ("cooling_step", "cooling_step_slow_sensor", "flow_step",
                                            "heating_step", "heating_step_no_cap"))
    trap = f"valve a > {Parameters().trap_threshold_pct:.0f} % for {n['seconds_valve_a_above_trap_threshold']} s"
    rows = [
        ("cooling 24->18 C (32 C)", "time to reach and stay within +-0.5 C",
         _fmt(c["time_to_stay_within_0p5c_s"], " s"), "thesis: ~60 s rise"),
        ("", "overshoot", _fmt(c["overshoot_c"], " C"), ""),
        ("", "mean |error|, last 120 s", _fmt(c["mean_abs_error_last_120s_c"], " C"), ""),
        ("  slow sensor, thesis PI", "time to reach and stay within +-0.5 C",
         _fmt(s["time_to_stay_within_0p5c_s"], " s"), "thesis: ~400 s rise"),
        ("", "first within +-0.5 C", _fmt(s["first_within_0p5c_s"], " s"), ""),
        ("flow 0.02->0.04 m3/s", "time to reach and stay within 5 %", _fmt(f["time_to_stay_within_5pct_s"], " s"), ""),
        ("", "overshoot", _fmt(f["overshoot_pct"], " %"), ""),
        ("heating 13.5->17.5 C", "time to reach and stay within +-0.5 C",
         _fmt(h["time_to_stay_within_0p5c_s"], " s"), ""),
        ("  valve a <= 80 %", "peak above reference after reaching +-0.5 C",
         _fmt(h["peak_above_ref_after_first_within_c"], " C"), ""),
        ("  cap lifted (<= 100 %)", "peak above reference after reaching +-0.5 C",
         _fmt(n["peak_above_ref_after_first_within_c"], " C"), trap),
    ]
    lines = [f"{'case':<25} {'metric':<45} {'value':>9}"]
    lines += [f"{a:<25} {b:<45} {v:>9}  {note}".rstrip() for a, b, v, note in rows]
    return "\n".join(lines)


def _pyplot():
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise SystemExit("plots need matplotlib: install the 'plot' extra (pip install -e \".[plot]\") "
                         "or pass --no-plots") from exc
    return plt


def plot_temperature_case(path: Path, title: str, traces: dict[str, Trace]) -> None:
    plt = _pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    for label, tr in traces.items():
        ax1.plot(tr.time_s, tr.supply_temp_c, label=f"supply (thermocouple) {label}")
        ax2.plot(tr.time_s, tr.valve_a_pct, label=f"valve a {label}")
        if np.any(tr.heater_cmd_w > 0):
            ax2.plot(tr.time_s, tr.heater_cmd_w / 2.4, "--", label=f"heater /2.4 W {label}")
    tr0 = next(iter(traces.values()))
    ax1.plot(tr0.time_s, tr0.ref_supply_temp_c, "k:", label="reference")
    ax1.fill_between(tr0.time_s, tr0.ref_supply_temp_c - TEMP_BAND_C, tr0.ref_supply_temp_c + TEMP_BAND_C,
                     color="0.85", label="+-0.5 C")
    ax1.set_ylabel("temperature (C)")
    ax2.set_ylabel("valve a (%), heater (W/2.4)")
    ax2.set_xlabel("time after the reference step (s)")
    ax1.set_title(title)
    ax1.legend(fontsize=7)
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_flow_case(path: Path, tr: Trace) -> None:
    plt = _pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    ax1.plot(tr.time_s, tr.volume_flow_m3s * 3600, label="volume flow")
    ax1.plot(tr.time_s, tr.ref_volume_flow_m3s * 3600, "k:", label="reference")
    ax1.set_ylabel("volume flow (m3/h)")
    ax2.plot(tr.time_s, tr.blower_power_w, label="blower (W)")
    for i, name in enumerate("mfw"):
        ax2.plot(tr.time_s, tr.valves_mfw_pct[:, i], "--", label=f"valve {name} (%)")
    ax2.set_xlabel("time after the reference step (s)")
    ax1.set_title("baseline: volume-flow step (PI, thesis sec. 5.1)")
    ax1.legend(fontsize=7)
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _clean(obj):
    """JSON-safe: non-finite floats become None."""
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


# ---------------------------------------------------------------------- command line
def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="out/baseline", help="output directory (default: out/baseline)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the plant's sensor noise (default: 0)")
    parser.add_argument("--no-plots", action="store_true", help="write no PNG files (no matplotlib needed)")
    parser.add_argument("--cooling-grid", action="store_true",
                        help="only the cooling step over 67 operating points, thermocouple + PID against slow "
                             "sensor + PI (about 1 min); writes cooling_grid.json")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if getattr(args, "cooling_grid", False):
        out.mkdir(parents=True, exist_ok=True)
        rows = cooling_grid(args.seed)
        (out / "cooling_grid.json").write_text(json.dumps(_clean(rows), indent=2))
        print(grid_table(rows))
        print(f"wrote {out / 'cooling_grid.json'}")
        return 0
    if not args.no_plots:
        _pyplot()  # fail early with the install hint
    out.mkdir(parents=True, exist_ok=True)
    cool_tr, cool = cooling_case(args.seed)
    slow_tr, slow = cooling_slow_sensor_case(args.seed)
    flow_tr, flow = flow_case(args.seed)
    heat_tr, heat = heating_case(args.seed, 80.0)
    free_tr, free = heating_case(args.seed, 100.0)
    results = {"seed": args.seed, "effects": "all plant effects on",
               "cooling_step": cool, "cooling_step_slow_sensor": slow, "flow_step": flow,
               "heating_step": heat, "heating_step_no_cap": free}
    (out / "baseline_results.json").write_text(json.dumps(_clean(results), indent=2))
    print(results_table(results))
    written = [out / "baseline_results.json"]
    if not args.no_plots:
        plot_temperature_case(out / "cooling_step.png", "baseline: cooling step, thermocouple (thesis sec. 5.4.1)",
                              {"": cool_tr})
        plot_temperature_case(out / "cooling_step_slow_sensor.png",
                              "calibration: cooling step, slow sensor tau 100.4 s, thesis PI (sec. 5.4.1)",
                              {"": slow_tr})
        plot_flow_case(out / "flow_step.png", flow_tr)
        plot_temperature_case(out / "heating_step.png", "baseline: heating step (thesis sec. 5.4.2)",
                              {"a <= 80 %": heat_tr, "a <= 100 %": free_tr})
        written += [out / n for n in ("cooling_step.png", "cooling_step_slow_sensor.png", "flow_step.png",
                                      "heating_step.png")]
    print("wrote " + ", ".join(str(p) for p in written))
    return 0
