"""Benchmark output: terminal table, JSON results, Markdown report with PNG plots (matplotlib optional)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .metrics import FLOW_BAND_FRACTION, HEATER_MIN_FLOW_M3S, TEMP_BAND_C

M3H = 3600.0
CONTROLLERS = ("baseline", "mpc")
LABELS = {"baseline": "baseline", "mpc": "MPC"}
COLORS = {"baseline": "tab:blue", "mpc": "tab:orange"}

#: (figure key, label with unit, scale, format) of the per-scenario table, in order.
ROWS = (
    ("temp_iae_cs", "supply temp IAE, thermocouple [C s]", 1.0, "{:.1f}"),
    ("air_temp_iae_cs", "supply air temp IAE, true air [C s]", 1.0, "{:.1f}"),
    ("ideal_temp_iae_cs", "supply temp IAE of the lag-only response [C s]", 1.0, "{:.1f}"),
    ("temp_time_to_band_median_s", f"time to +-{TEMP_BAND_C} C, median [s]", 1.0, "{:.0f}"),
    ("temp_time_to_band_max_s", f"time to +-{TEMP_BAND_C} C, max [s]", 1.0, "{:.0f}"),
    ("temp_unsettled", "temperature steps not settled", 1.0, "{:.0f}"),
    ("temp_overshoot_max_c", "temperature overshoot, max [C]", 1.0, "{:.2f}"),
    ("temp_settle_median_s", f"settle time (first inside +-{TEMP_BAND_C} C), median [s]", 1.0, "{:.0f}"),
    ("temp_in_band_share", f"time inside +-{TEMP_BAND_C} C once settled [%]", 100.0, "{:.1f}"),
    ("flow_iae_m3", "volume-flow IAE [m3]", 1.0, "{:.3f}"),
    ("flow_time_to_band_max_s", f"time to +-{FLOW_BAND_FRACTION:.0%} flow, max [s]", 1.0, "{:.0f}"),
    ("outlet_rms_m3s", "outlet-flow RMS error [m3/h]", M3H, "{:.2f}"),
    ("blower_wh", "blower energy [Wh]", 1.0, "{:.2f}"),
    ("heater_wh", "heater energy [Wh]", 1.0, "{:.2f}"),
    ("energy_wh", "electric energy total [Wh]", 1.0, "{:.2f}"),
    ("travel_mean", "actuator travel, mean [ranges]", 1.0, "{:.2f}"),
    ("violations_bounds", "violations: actuator bounds [samples]", 1.0, "{:.0f}"),
    ("violations_heater_temp", "violations: heater temp limit [samples]", 1.0, "{:.0f}"),
    ("violations_heater_low_flow", "violations: heater on, low flow [samples]", 1.0, "{:.0f}"),
    ("step_median_ms", "step time, median [ms]", 1.0, "{:.2f}"),
    ("step_p99_ms", "step time, 99th percentile [ms]", 1.0, "{:.2f}"),
    ("time_ratio", "time ratio (step / sample)", 1.0, "{:.4f}"),
    ("fallbacks", "fallback steps", 1.0, "{:.0f}"),
    ("out_of_reach_s", "time with a reference reported out of reach [s]", 1.0, "{:.0f}"),
)


def _fmt(value, scale: float, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return fmt.format(value * scale)


def _fmt_ratio(r) -> str:
    if r is None:
        return "-"
    return "inf" if math.isinf(r) else f"{r:.2f}"


def figure_rows(scenario: Mapping) -> list[tuple[str, str, str, str]]:
    """(label, baseline, MPC, ratio) strings of one scenario's table."""
    base, mpc = scenario["baseline"]["figures"], scenario["mpc"]["figures"]
    ratios = scenario["ratios"]
    return [(label, _fmt(base.get(k), s, f), _fmt(mpc.get(k), s, f), _fmt_ratio(ratios.get(k)) if k in ratios else "")
            for k, label, s, f in ROWS]


#: Display scale and unit of a reference's shortfall, by reference name.
SHORTFALL_UNITS = {"volume_flow_m3s": (M3H, "m3/h"), "supply_temp_c": (1.0, "C")}


def reach_lines(scenario: Mapping) -> list[str]:
    """One line per controller and reference it reported out of reach: how long and by how much."""
    lines = []
    for c in CONTROLLERS:
        for name, r in (scenario[c]["details"].get("out_of_reach") or {}).items():
            scale, unit = SHORTFALL_UNITS.get(name, (1.0, ""))
            lines.append(f"{LABELS[c]}: reference {name} out of reach for {r['samples']} samples, shortfall "
                         f"mean {r['mean_shortfall'] * scale:.3g} {unit}, max {r['max_shortfall'] * scale:.3g} {unit}, "
                         f"last {r['last_shortfall'] * scale:.3g} {unit}")
    return lines


def terminal_table(results: Mapping) -> str:
    """Plain-text tables, one block per scenario, then the criteria summary."""
    lines = []
    for name, sc in results["scenarios"].items():
        lines.append(f"{name} ({sc['kind']}, {sc['scored_s']:.0f} s scored)")
        lines.append(f"  {'':44s}{'baseline':>11s}{'MPC':>11s}{'MPC/base':>10s}")
        for label, b, m, r in figure_rows(sc):
            lines.append(f"  {label:44s}{b:>11s}{m:>11s}{r:>10s}")
        lines += [f"  {x}" for x in reach_lines(sc)]
        for c in sc["criteria"]:
            lines.append(f"  [{c['status']:^7s}] {c['criterion']}: {c['value']}"
                         + (f" (ratio {_fmt_ratio(c['ratio'])})" if c["ratio"] is not None else ""))
        lines.append("")
    s = results["summary"]
    lines.append(f"criteria met: {s['met']} of {s['judged']} judged ({s['not_met']} not met, {s['n_a']} n/a)")
    return "\n".join(lines)


def write_json(results: Mapping, path: Path) -> None:
    """Results as JSON (NaN and inf written as null)."""
    path.write_text(json.dumps(_clean(results), indent=2))


def _clean(x):
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def markdown(results: Mapping, plots: Mapping[str, str], plot_note: str | None) -> str:
    """The report text; ``plots`` maps scenario names to PNG file names relative to the report."""
    meta = results["meta"]
    out = ["# Benchmark: MPC against the thesis baseline", "",
           f"Command: `{meta['command']}`  ", f"Seed {meta['seed']}, {'quick' if meta['quick'] else 'full'} run, "
           f"{meta['elapsed_s']:.0f} s wall time on {meta['platform']} (Python {meta['python']}).", ""]
    out += ["## Set-up", ""]
    if meta.get("plant", "SimulatedPlant") != "SimulatedPlant":
        out += [f"Both controllers run on the plant built by `{meta['plant']}` (a fresh one per run, seeded); "
                "the controllers get the nominal `Parameters()`.", ""]
    else:
        out += ["Both controllers run on the same simulated plant (`SimulatedPlant`, all non-ideal effects on: "
                + ", ".join(meta["plant_effects"]) + "), with seeded sensor noise (the same noise sequence for both "
                "controllers in a scenario). The plant's parameters are perturbed from the controllers' model; the "
                "controllers get the nominal `Parameters()`:", "",
                "| parameter | nominal (controllers) | plant | change | meaning |", "|---|---|---|---|---|"]
        for p in meta["perturbation"]:
            out.append(f"| `{p['name']}` | {p['nominal']:.6g} | {p['plant']:.6g} | {p['relative']:+.1%} | {p['meaning']} |")
        out += ["", meta["perturbation_rule"], ""]
    out += ["Figures (scored after each scenario's warm-up; sample time 1 s, rectangle sums):", "",
            "- supply-temperature IAE from the noise-free thermocouple reading (`plant.truth()['supply_temp_c']`, "
            "the sensor the controllers see, without its noise); the IAE of the true mixed air temperature "
            "is the secondary figure; the lag-only IAE is what a controller would score whose air temperature "
            "sits exactly at the reference from the step on (the plant's thermocouple lag, no overshoot);",
            f"- time to +-{TEMP_BAND_C} C: from a reference step until the thermocouple reading enters the band for "
            "good (until the next step); 'not settled' if it is outside at the next step; overshoot beyond the new "
            "reference in the step's direction;",
            f"- volume-flow IAE (m3) and time to +-{FLOW_BAND_FRACTION:.0%} of the new flow reference; outlet-flow RMS "
            "error of the true outlet flows against the reference split, over the three outlets;",
            "- energy: blower command power (electric) and the plant's heater electric power (PTC-limited), in Wh;",
            "- actuator travel: sum of absolute moves of each applied command divided by its range, averaged over "
            "the six actuators (BOPTEST's `atvl`);",
            f"- violations: samples with a requested command outside its bounds, the heater above "
            f"`heater_temp_max_c` = {meta['heater_temp_max_c']:.0f} C, or the heater drawing power with the flow "
            f"below {HEATER_MIN_FLOW_M3S} m3/s;",
            "- step time: wall time around `controller.step`, median and 99th percentile; time ratio = mean step "
            "time / sample time (BOPTEST's `time_rat`); fallbacks = steps whose stats name a fallback. Wall times "
            "depend on the machine and on whatever else runs on it.", ""]
    if meta.get("controller_settings"):
        out += ["Controllers: " + "; ".join(f"{k}: {v}" for k, v in meta["controller_settings"].items()), ""]
    out += ["## Criteria", "", "| scenario | " + " | ".join(results["criteria_names"]) + " |",
            "|---|" + "---|" * len(results["criteria_names"])]
    for name, sc in results["scenarios"].items():
        cells = []
        for c in sc["criteria"]:
            cells.append(c["status"] + (f" ({_fmt_ratio(c['ratio'])})" if c["ratio"] is not None else ""))
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    s = results["summary"]
    out += ["", f"Met {s['met']} of {s['judged']} judged criteria ({s['not_met']} not met, {s['n_a']} n/a). "
            "Ratios are MPC / baseline.", ""]
    not_met = [(n, c) for n, sc in results["scenarios"].items() for c in sc["criteria"] if c["status"] == "not met"]
    if not_met:
        out += ["### Where and why not", ""]
        for n, c in not_met:
            out.append(f"- **{n}**, {c['criterion']} ({c['value']}): {c['why']}")
        out.append("")
    if plot_note:
        out += [f"*{plot_note}*", ""]
    out.append("## Scenarios")
    for name, sc in results["scenarios"].items():
        out += ["", f"### {name}", "", sc["description"], "",
                f"Seed {sc['seed']}, {sc['duration_s']:.0f} s of which the first {sc['warmup_s']:.0f} s are warm-up "
                f"(not scored); inlet {sc['inlet_temp_c']:.1f} C, chiller set point {sc['chiller_setpoint_c']:.1f} C.",
                ""]
        for note in sc.get("notes", []):
            out += [f"Note: {note}", ""]
        out += ["References (warm-up first): " + "; ".join(_ref_text(r) for r in sc["references"]) + ".", ""]
        out += ["| figure | baseline | MPC | MPC/baseline |", "|---|---|---|---|"]
        for label, b, m, r in figure_rows(sc):
            out.append(f"| {label} | {b} | {m} | {r} |")
        out.append("")
        out += [f"- {x}" for x in reach_lines(sc)] + ([""] if reach_lines(sc) else [])
        steps = zip(sc["baseline"]["details"]["temperature_steps"], sc["mpc"]["details"]["temperature_steps"])
        rows = [f"| {b['time_s']:.0f} | {b['from']:.2f} -> {b['to']:.2f} | {_t(b['time_to_band_s'])} | "
                f"{b['overshoot']:.2f} | {_t(m['time_to_band_s'])} | {m['overshoot']:.2f} |" for b, m in steps]
        if rows:
            out += [f"| temperature step at [s] | reference [C] | baseline time to +-{TEMP_BAND_C} C | baseline "
                    f"overshoot [C] | MPC time to +-{TEMP_BAND_C} C | MPC overshoot [C] |", "|---|---|---|---|---|---|",
                    *rows, ""]
        for c in sc["criteria"]:
            line = f"- {c['status']}: {c['criterion']}, {c['value']}"
            if c["ratio"] is not None:
                line += f", ratio {_fmt_ratio(c['ratio'])}"
            if c["why"]:
                line += f". Why: {c['why']}"
            if c.get("note"):
                line += f". Note: {c['note']}"
            out.append(line)
        if name in plots:
            out += ["", f"![{name}]({plots[name]})"]
    return "\n".join(out) + "\n"


def _t(x) -> str:
    return "not settled" if x is None else f"{x:.0f} s"


def _ref_text(r: Mapping) -> str:
    text = f"{r['from_s']:.0f} s: {r['supply_temp_c']:.2f} C, {r['volume_flow_m3s'] * M3H:.0f} m3/h"
    if r.get("flow_m_m3s") is not None:
        text += (f" (m/f/w {r['flow_m_m3s'] * M3H:.0f}/{r['flow_f_m3s'] * M3H:.0f}/"
                 f"{r['flow_w_m3s'] * M3H:.0f})")
    return text


# ---------------------------------------------------------------------------- plots
def import_pyplot():
    """matplotlib.pyplot with the Agg backend, or None when matplotlib (extra 'plot') is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def plot_scenario(plt, name: str, traces: Mapping[str, object], warmup_s: float, path: Path) -> None:
    """One figure: references, outputs and actuators of both controllers on shared time axes."""
    fig, ax = plt.subplots(6, 1, figsize=(10, 15), sharex=True)
    first = next(iter(traces.values()))
    t = first.time_s
    ref = first.reference
    for a in ax:
        a.axvspan(t[0], warmup_s, color="0.92", lw=0)
        a.grid(True, lw=0.3)
    ax[0].step(t, ref["supply_temp_c"], "k--", where="post", lw=1, label="reference")
    ax[1].step(t, ref["volume_flow_m3s"] * M3H, "k--", where="post", lw=1, label="reference")
    styles = {"flow_m_m3s": "-", "flow_f_m3s": "--", "flow_w_m3s": ":"}
    for o, ls in styles.items():
        ax[2].step(t, ref[o] * M3H, color="k", ls=ls, where="post", lw=0.8, label=f"ref {o.split('_')[1]}")
    for c, tr in traces.items():
        col, lab = COLORS.get(c, None), LABELS.get(c, c)
        ax[0].plot(t, tr.truth["supply_temp_c"], color=col, lw=1.2, label=f"{lab} thermocouple")
        ax[0].plot(t, tr.truth["supply_air_temp_c"], color=col, lw=0.5, alpha=0.6, label=f"{lab} true air")
        ax[1].plot(t, tr.truth["volume_flow_m3s"] * M3H, color=col, lw=1.2, label=lab)
        for o, ls in styles.items():
            ax[2].plot(t, tr.truth[o] * M3H, color=col, ls=ls, lw=1.0, label=f"{lab} {o.split('_')[1]}")
        u = tr.applied
        ax[3].step(t, u[:, 0], color=col, where="post", lw=1.0, label=f"{lab} blower")
        ax[3].step(t, u[:, 1], color=col, ls="--", where="post", lw=1.0, label=f"{lab} heater cmd")
        ax[4].step(t, u[:, 2], color=col, where="post", lw=1.0, label=lab)
        for i, (v, ls) in enumerate(zip("mfw", ("-", "--", ":"))):
            ax[5].step(t, u[:, 3 + i], color=col, ls=ls, where="post", lw=1.0, label=f"{lab} {v}")
    labels = ("supply temp [C]", "volume flow [m3/h]", "outlet flows [m3/h]", "power [W]", "valve a [%]",
              "valves m, f, w [%]")
    for a, lab in zip(ax, labels):
        a.set_ylabel(lab)
        a.legend(fontsize=7, ncol=3, loc="best")
    ax[-1].set_xlabel("time [s] (grey: warm-up, not scored)")
    fig.suptitle(name)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def summarise(scenarios: Mapping) -> dict:
    """Counts of criteria statuses over all scenarios."""
    statuses = [c["status"] for sc in scenarios.values() for c in sc["criteria"]]
    return {"met": statuses.count("met"), "not_met": statuses.count("not met"), "n_a": statuses.count("n/a"),
            "judged": statuses.count("met") + statuses.count("not met")}


def criteria_names(scenarios: Mapping) -> Sequence[str]:
    first = next(iter(scenarios.values()))
    return [c["criterion"] for c in first["criteria"]]
