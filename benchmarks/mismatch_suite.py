"""``hvac-mpc bench --suite mismatch``: both controllers on every variant of the independent simulator.

The plants come from ``hvac_mpc.mismatch.make_plant`` through the benchmark's plant seam
(:mod:`.plant_seam`), a fresh one per run; the controllers are the default MPC and the untouched
thesis baseline, both on the nominal ``Parameters()`` (neither knows the variant). Each variant
runs the scenarios of :func:`.scenarios.mismatch_scenarios` (cooling steps, heating steps, the
proband sequence, a total-flow reference out of reach). Output in ``--out`` (default
``out/mismatch``): ``results.json``, ``report.md`` with the matrix of MPC/baseline ratios
(thermocouple IAE, flow IAE, energy), the worst cell and the median, and one PNG per variant.
"""

from __future__ import annotations

import dataclasses
import functools
import re
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from hvac_mpc.mismatch.variants import UNSHAPED_VARIANTS, Variant

from . import report, scenarios as scenario_defs

#: The ratios of the matrix: (figure key, column label).
MATRIX_FIGURES = (("temp_iae_cs", "T IAE"), ("flow_iae_m3", "flow IAE"), ("energy_wh", "energy"))
#: What the suite is judged on (issue 11): every cell and the median of the temperature ratio.
CELL_LIMIT = 1.0
MEDIAN_LIMIT = 0.7
#: Fallback steps of one MPC run above which the run counts as a fallback storm (share of its samples).
STORM_SHARE = 0.05
#: Steady state of the out-of-reach scenario: the last this many seconds of each of its segments.
STEADY_WINDOW_S = 30.0
#: Largest steady supply-temperature error allowed with the flow out of reach (degC, issue 11).
OUT_OF_REACH_TEMP_TOL_C = 0.3


#: Registered variants the suite leaves out: not among the variants issue 11 names (the data loop uses them).
NOT_IN_SUITE = ("bypass_flow",) + UNSHAPED_VARIANTS


def variant_names() -> list[str]:
    from hvac_mpc.mismatch import VARIANTS
    return [v for v in VARIANTS if v not in NOT_IN_SUITE]


def variant_factory(variant):
    """Plant factory (keywords seed, dt_s) of one registered variant (a name) or of a ``Variant``."""
    from hvac_mpc.mismatch import make_plant
    return functools.partial(make_plant, variant)


def parse_box(spec: str):
    """(label, Variant) of a box the registry does not have, written ``LABEL:FIELD=VALUE,FIELD=VALUE``.

    FIELD is a field of :class:`hvac_mpc.mismatch.Variant` (its units in its name); a boolean field
    takes true/false (or 1/0). Raises ValueError naming the field and what it allows; the Variant's
    own checks give the allowed ranges."""
    label, sep, body = spec.partition(":")
    label = label.strip()
    if not sep or not re.fullmatch(r"[A-Za-z0-9_.-]+", label) or not body.strip():
        raise ValueError(f"--box {spec!r}: write LABEL:FIELD=VALUE[,FIELD=VALUE...] (LABEL of letters, digits, "
                         "_ . -), e.g. U1:transport_delay_s=2,duct_loss_ua_w_per_k=4")
    fields = {f.name: f for f in dataclasses.fields(Variant)}
    values: dict = {}
    for item in body.split(","):
        key, eq, text = (part.strip() for part in item.partition("="))
        if key not in fields or not eq:
            raise ValueError(f"--box {label}: unknown field {key!r}; allowed: {', '.join(fields)}")
        values[key] = _field_value(label, key, text, type(fields[key].default))
    try:
        return label, Variant(**values)
    except ValueError as exc:
        raise ValueError(f"--box {label}: {exc}") from None


def _field_value(label: str, key: str, text: str, kind: type):
    """One FIELD=VALUE of :func:`parse_box`, as the field's type (bool, int or float)."""
    if kind is bool:
        if text.lower() in ("true", "1", "yes", "on"):
            return True
        if text.lower() in ("false", "0", "no", "off"):
            return False
        raise ValueError(f"--box {label}: {key} takes true or false, got {text!r}")
    try:
        return kind(text)
    except ValueError:
        raise ValueError(f"--box {label}: {key} takes a number ({kind.__name__}), got {text!r}") from None


def out_of_reach_steady(trace, scenario: scenario_defs.Scenario) -> dict:
    """Largest |supply temperature error| (thermocouple, noise-free) over the last STEADY_WINDOW_S of
    each segment whose flow reference is out of reach, how many of those samples the controller
    reported it, and whether the flow was reached there after all (within 5 %, a strong blower)."""
    t = trace.time_s
    worst, reported, reached = 0.0, 0, True
    for start, seg in zip(scenario.step_times_s(), scenario.segments):
        if seg.reference.volume_flow_m3s < scenario_defs.UNREACHABLE_FLOW_M3H * scenario_defs.M3H - 1e-9:
            continue
        end = start + seg.duration_s
        sl = (t >= end - STEADY_WINDOW_S) & (t < end)
        err = np.abs(trace.truth["supply_temp_c"][sl] - seg.reference.supply_temp_c)
        worst = max(worst, float(err.max()))
        reached &= bool(trace.truth["volume_flow_m3s"][sl].mean() >= 0.95 * seg.reference.volume_flow_m3s)
        reported += sum(1 for k in np.flatnonzero(sl) if trace.out_of_reach[k]
                        and "volume_flow_m3s" in trace.out_of_reach[k])
    return {"steady_temp_error_max_c": worst, "steady_samples_reported": reported, "flow_reached": reached}


def run_suite(variants: Sequence[str], chosen: Sequence[scenario_defs.Scenario], factories: Mapping,
              seed: int, run_benchmark: Callable[..., tuple[dict, dict]], progress=None,
              boxes: Mapping | None = None) -> tuple[dict, dict]:
    """Every variant on every scenario with both controllers; returns (results, traces by variant).

    ``factories`` and ``run_benchmark`` are those of :mod:`.bench` (passed in: the benchmark command
    calls this module, not the other way round). ``boxes`` (label -> ``Variant``, :func:`parse_box`)
    adds boxes the registry does not have, as rows after the variants."""
    results: dict = {"variants": {}}
    traces: dict = {}
    plants = {v: v for v in variants} | dict(boxes or {})
    for v, variant in plants.items():
        res, tr = run_benchmark(chosen, factories, seed, progress=progress, plant_factory=variant_factory(variant),
                                plant_name=f"hvac_mpc.mismatch:make_plant({variant!r})")
        traces[v] = tr
        row = {}
        for name, sc in res["scenarios"].items():
            m, b = sc["mpc"], sc["baseline"]
            cell = {key: sc["ratios"].get(key) for key, _ in MATRIX_FIGURES}
            n = int(round(sc["duration_s"] - sc["warmup_s"]))
            cell.update({"mpc_temp_iae_cs": m["figures"]["temp_iae_cs"],
                         "baseline_temp_iae_cs": b["figures"]["temp_iae_cs"],
                         "mpc_in_band_share": m["figures"]["temp_in_band_share"],
                         "baseline_in_band_share": b["figures"]["temp_in_band_share"],
                         "mpc_settle_median_s": m["figures"]["temp_settle_median_s"],
                         "baseline_settle_median_s": b["figures"]["temp_settle_median_s"],
                         "mpc_fallbacks": m["figures"]["fallbacks"],
                         "fallback_storm": m["figures"]["fallbacks"] > STORM_SHARE * n,
                         "mpc_violations": m["figures"]["violations_total"],
                         "baseline_violations": b["figures"]["violations_total"],
                         "mpc_out_of_reach": m["details"]["out_of_reach"]})
            scenario = next(s for s in chosen if s.name == name)
            if name == "flow_out_of_reach":
                cell["mpc_steady"] = out_of_reach_steady(tr[name]["mpc"], scenario)
                cell["baseline_steady"] = out_of_reach_steady(tr[name]["baseline"], scenario)
            row[name] = cell
        results["variants"][v] = row
    results["summary"] = summarise(results["variants"])
    return results, traces


def summarise(matrix: Mapping[str, Mapping[str, Mapping]]) -> dict:
    """Worst cell and median of each ratio; the checks of issue 11."""
    out: dict = {}
    for key, _ in MATRIX_FIGURES:
        cells = [(v, s, c[key]) for v, row in matrix.items() for s, c in row.items() if c.get(key) is not None]
        if not cells:
            continue
        worst = max(cells, key=lambda x: x[2])
        out[key] = {"median": float(np.median([c[2] for c in cells])), "worst": worst[2],
                    "worst_cell": f"{worst[0]} / {worst[1]}"}
    cells = [c for row in matrix.values() for c in row.values()]
    steady = [c["mpc_steady"] for c in cells if "mpc_steady" in c]
    t = out.get("temp_iae_cs", {})
    out["checks"] = {
        f"temperature ratio <= {CELL_LIMIT} in every cell": t.get("worst", np.inf) <= CELL_LIMIT,
        f"temperature ratio median <= {MEDIAN_LIMIT}": t.get("median", np.inf) <= MEDIAN_LIMIT,
        "no fallback storm": not any(c["fallback_storm"] for c in cells),
        "no constraint violation (MPC)": all(c["mpc_violations"] == 0 for c in cells),
        f"flow out of reach: steady supply temperature within {OUT_OF_REACH_TEMP_TOL_C} C": bool(steady) and all(
            s["steady_temp_error_max_c"] <= OUT_OF_REACH_TEMP_TOL_C for s in steady),
        "flow out of reach: reported in steady state (where not reached)": bool(steady) and all(
            s["steady_samples_reported"] > 0 or s.get("flow_reached", False) for s in steady),
    }
    return out


def matrix_table(results: Mapping) -> list[str]:
    """Markdown table: one row per variant, one column per scenario and ratio."""
    variants = results["variants"]
    first = next(iter(variants.values()))
    head = "| variant | " + " | ".join(f"{s} {lab}" for s in first for _, lab in MATRIX_FIGURES) + " |"
    lines = [head, "|---|" + "---|" * (len(first) * len(MATRIX_FIGURES))]
    for v, row in variants.items():
        lines.append(f"| {v} | " + " | ".join(report._fmt_ratio(c.get(key)) for c in row.values()
                                                 for key, _ in MATRIX_FIGURES) + " |")
    return lines


def band_table(results: Mapping) -> list[str]:
    """Markdown table: time inside +-0.5 C once settled and median settle time, MPC / baseline."""
    variants = results["variants"]
    first = next(iter(variants.values()))
    lines = ["| variant | " + " | ".join(f"{s} in band MPC / base [%]; settle MPC / base [s]" for s in first) + " |",
             "|---|" + "---|" * len(first)]
    pct = lambda x: "-" if x is None else f"{100 * x:.0f}"  # noqa: E731
    sec = lambda x: "-" if x is None else f"{x:.0f}"  # noqa: E731
    for v, row in variants.items():
        lines.append(f"| {v} | " + " | ".join(
            f"{pct(c['mpc_in_band_share'])} / {pct(c['baseline_in_band_share'])}; "
            f"{sec(c['mpc_settle_median_s'])} / {sec(c['baseline_settle_median_s'])}" for c in row.values()) + " |")
    return lines


def reach_table(results: Mapping) -> list[str]:
    """Per variant: the flow-out-of-reach scenario's steady temperature error and the reported shortfall."""
    lines = ["| variant | MPC steady temp error max [C] | baseline [C] | MPC reported out of reach |", "|---|---|---|---|"]
    for v, row in results["variants"].items():
        c = row.get("flow_out_of_reach")
        if not c:
            continue
        oor = c["mpc_out_of_reach"] or {}
        text = "; ".join(f"{k}: last shortfall {r['last_shortfall'] * report.SHORTFALL_UNITS.get(k, (1, ''))[0]:.3g} "
                         f"{report.SHORTFALL_UNITS.get(k, (1, ''))[1]} ({r['samples']} samples)"
                         for k, r in oor.items()) or "nothing"
        lines.append(f"| {v} | {c['mpc_steady']['steady_temp_error_max_c']:.2f} | "
                     f"{c['baseline_steady']['steady_temp_error_max_c']:.2f} | {text} |")
    return lines


#: The nominal box's fields, against which a ``--box`` is described in the report.
_NOMINAL_FIELDS = dataclasses.asdict(Variant())


def markdown(results: Mapping, plots: Mapping[str, str]) -> str:
    meta, s = results["meta"], results["summary"]
    out = ["# Mismatch suite: MPC against the thesis baseline on the independent simulator", "",
           f"Command: `{meta['command']}`  ", f"Seed {meta['seed']}, {'quick' if meta['quick'] else 'full'} "
           f"scenarios, {meta['elapsed_s']:.0f} s wall time.", "",
           "Plants: `hvac_mpc.mismatch.make_plant(variant)` (its own equations, mismatch/README.md); controllers "
           "on the nominal `Parameters()` (the MPC on `--mpc-params` if given), neither told the variant. Cells are "
           "MPC / baseline (lower is better).", ""]
    for label, fields in meta.get("boxes", {}).items():
        differs = ", ".join(f"{k}={v}" for k, v in fields.items() if v != _NOMINAL_FIELDS.get(k))
        out.append(f"- Box `{label}` (not in the registry, `--box`): {differs or 'nominal'}")
    for key, lab in MATRIX_FIGURES:
        if key in s:
            out.append(f"- {lab}: median {s[key]['median']:.2f}, worst {s[key]['worst']:.2f} ({s[key]['worst_cell']})")
    out += ["", "## Checks", ""] + [f"- {'met' if ok else 'NOT met'}: {name}" for name, ok in s["checks"].items()]
    out += ["", "## Ratios", ""] + matrix_table(results)
    out += ["", f"## Time inside +-0.5 C once settled, settle time (median)", ""] + band_table(results)
    out += ["", "## Flow out of reach", ""] + reach_table(results)
    if plots:
        out += ["", "## Plots", ""] + [f"![{v}]({f})" for v, f in plots.items()]
    return "\n".join(out) + "\n"


def terminal_text(results: Mapping) -> str:
    s = results["summary"]
    lines = ["MPC / baseline, thermocouple IAE:"]
    variants = results["variants"]
    first = next(iter(variants.values()))
    lines.append(f"  {'variant':28s}" + "".join(f"{n[:16]:>18s}" for n in first))
    for v, row in variants.items():
        lines.append(f"  {v:28s}" + "".join(f"{report._fmt_ratio(c['temp_iae_cs']):>18s}" for c in row.values()))
    for key, lab in MATRIX_FIGURES:
        if key in s:
            lines.append(f"{lab}: median {s[key]['median']:.2f}, worst {s[key]['worst']:.2f} ({s[key]['worst_cell']})")
    lines += [f"[{'met' if ok else 'NOT met':^7s}] {name}" for name, ok in s["checks"].items()]
    return "\n".join(lines)


def plot_variant(plt, variant: str, traces: Mapping[str, Mapping[str, object]], path: Path) -> None:
    """Supply temperature and volume flow of both controllers on each scenario of one variant."""
    names = list(traces)
    fig, ax = plt.subplots(2, len(names), figsize=(4.5 * len(names), 6), squeeze=False)
    for j, name in enumerate(names):
        runs = traces[name]
        first = next(iter(runs.values()))
        t = first.time_s
        ax[0, j].step(t, first.reference["supply_temp_c"], "k--", where="post", lw=1, label="reference")
        ax[1, j].step(t, first.reference["volume_flow_m3s"] * report.M3H, "k--", where="post", lw=1, label="reference")
        for c, tr in runs.items():
            ax[0, j].plot(t, tr.truth["supply_temp_c"], color=report.COLORS.get(c), lw=1.0, label=report.LABELS[c])
            ax[1, j].plot(t, tr.truth["volume_flow_m3s"] * report.M3H, color=report.COLORS.get(c), lw=1.0,
                          label=report.LABELS[c])
        ax[0, j].set_title(name, fontsize=9)
        ax[0, j].set_ylabel("supply temp [C]")
        ax[1, j].set_ylabel("volume flow [m3/h]")
        ax[1, j].set_xlabel("time [s]")
        for a in ax[:, j]:
            a.grid(True, lw=0.3)
            a.axvspan(t[0], first.metrics_start_s, color="0.92", lw=0)
        ax[0, j].legend(fontsize=7)
    fig.suptitle(f"variant {variant}")
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def write_outputs(results: Mapping, traces: Mapping, out: Path, plots: bool) -> None:
    """results.json, report.md and (with matplotlib) one PNG per variant in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}
    plt = report.import_pyplot() if plots else None
    if plt is not None:
        for v, tr in traces.items():
            files[v] = f"{v}.png"
            plot_variant(plt, v, tr, out / files[v])
    report.write_json(results, out / "results.json")
    (out / "report.md").write_text(markdown(results, files))
