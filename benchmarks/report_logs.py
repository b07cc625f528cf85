"""``hvac-mpc report LOG...``: the bench's figures, ratios, criteria and plots from logs of real runs.

Each log (the daemon's, or any in the measurement-log schema) becomes a run record like the
bench's: references from the ``ref_*`` columns, outputs from the readings (a real box has no
noise-free truth), commands as applied. Logs are grouped by scenario and paired by controller
(``baseline`` and ``mpc``); a pair gets the MPC / baseline ratios and the criteria of
:mod:`.criteria`. The scenario, warm-up and controller come from the ``LOG.json`` sidecar
``hvac-mpc experiment`` writes, else from ``--warmup`` and the log's ``controller`` column.

Noise. The bench scores the noise-free signals; a log holds the noisy readings. The report
estimates each reading's noise from its second differences (white noise: variance of the second
difference = 6 sigma^2) and states the most the noise can add to an IAE, N sigma sqrt(2/pi) dt
(the mean of |noise| over the scored samples), and the band of each ratio that this allows
(``ratio_noise``). Beside it, the noise-aware figures of :mod:`.noise_iae` (``noise_aware``): the
IAE of the reading cleaned with the applied commands and a centred average, corrected for the
noise left in it, with a 95 % band from a bootstrap over the estimated noise, and the ratios
with their bands; the energy ratio with the band its heater-power reading's noise allows. The
figures table keeps the figures of the readings as they are. Figures that need signals a box
does not measure (outlet flows, true air temperature, heater body temperature, step times) are
left out ("-").
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import Counter
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from hvac_mpc.models.box import INPUTS
from hvac_mpc.models.measurement_log import LogFormatError, read_log
from hvac_mpc.models.parameters import Parameters

from . import criteria, metrics, noise_iae, report
from .noise_iae import second_difference_sigma as noise_sigma
from .simulate import REFERENCE_FIELDS, TRUTH_FIELDS, Trace, actuator_bounds

#: Modes of rows that are not part of the run (the daemon's shutdown and outages).
NOT_SCORED_MODES = ("shutdown", "stopped")
#: Readings whose noise the report estimates, with the IAE figure each one feeds.
NOISY = {"supply_temp_c": "temp_iae_cs", "volume_flow_m3s": "flow_iae_m3"}


def _sidecar(path: Path) -> dict:
    side = path.with_suffix(path.suffix + ".json")
    if side.exists():
        try:
            return json.loads(side.read_text())
        except json.JSONDecodeError as exc:
            raise LogFormatError(f"{side}: not valid JSON ({exc})") from None
    return {}


def _controller_of(cols: Mapping[str, np.ndarray], side: Mapping) -> str:
    name = side.get("controller")
    if name:
        return str(name)
    used = [c for c in cols.get("controller", []) if c and c != "none"]
    return Counter(used).most_common(1)[0][0] if used else "unknown"


def trace_from_log(path: str | Path, warmup_s: float | None = None, scenario: str | None = None) -> tuple[Trace, dict]:
    """A :class:`Trace` of a logged run and its description (scenario, kind, controller, noise)."""
    path = Path(path)
    cols = read_log(path)
    side = _sidecar(path)
    mode = cols.get("mode", np.array([""] * len(cols["time_s"]), dtype=object))
    keep = np.array([not str(m).startswith(NOT_SCORED_MODES) for m in mode])
    if "duration_s" in side:
        keep &= cols["time_s"] - cols["time_s"][0] < float(side["duration_s"]) - 1e-9
    idx = np.flatnonzero(keep)
    if idx.size < 3:
        raise LogFormatError(f"{path}: fewer than 3 rows of the run (rows in shutdown are not scored)")
    t = cols["time_s"][idx]
    dt = float(np.median(np.diff(t)))
    n = idx.size
    nan = np.full(n, np.nan)
    ref = {f: cols.get(f"ref_{f}", nan)[idx] for f in REFERENCE_FIELDS}
    if not np.isfinite(ref["supply_temp_c"]).any():
        raise LogFormatError(f"{path}: column ref_supply_temp_c is empty; a report needs the references")
    truth = {f: nan.copy() for f in TRUTH_FIELDS}
    for f in ("supply_temp_c", "volume_flow_m3s", "heater_power_w", "heater_outlet_temp_c", "water_temp_c",
              "flow_m_m3s", "flow_f_m3s", "flow_w_m3s"):
        if f in cols:
            truth[f] = np.asarray(cols[f], float)[idx]
    if not np.isfinite(truth["heater_power_w"]).any():
        truth["heater_power_w"] = np.asarray(cols["heater_cmd_w"], float)[idx]
    truth["heater_power_w"] = np.nan_to_num(truth["heater_power_w"])
    applied = np.column_stack([np.asarray(cols[a], float)[idx] for a in INPUTS])
    controller = _controller_of(cols, side)
    used = cols.get("controller", np.array([controller] * len(cols["time_s"]), dtype=object))[idx]
    fallback = [None if (u in ("", controller) or controller in ("unknown", "excitation")) else str(u) for u in used]
    warm = float(side.get("warmup_s", 0.0) if warmup_s is None else warmup_s)
    tr = Trace(scenario=str(scenario or side.get("scenario") or path.stem), controller=controller, dt_s=dt,
               time_s=t - t[0], reference=ref, truth=truth,
               measured={"supply_temp_c": truth["supply_temp_c"], "volume_flow_m3s": truth["volume_flow_m3s"],
                         "cabin_temp_c": np.asarray(cols.get("cabin_temp_c", nan), float)[idx] if "cabin_temp_c"
                         in cols else nan},
               requested=applied, applied=applied, step_time_s=nan.copy(), fallback=fallback,
               mode=[str(m) for m in mode[idx]], status=[None] * n, metrics_start_s=warm,
               environment={"inlet_temp_c": float(np.nanmean(cols["hvac_inlet_temp_c"][idx])),
                            "chiller_setpoint_c": float(np.nanmean(cols.get("chiller_setpoint_c", nan)[idx]))
                            if "chiller_setpoint_c" in cols else math.nan})
    scored = int(np.sum(tr.time_s >= warm - 1e-9))
    noise = {}
    for f, fig in NOISY.items():
        sigma = noise_sigma(truth[f][tr.time_s >= warm - 1e-9])
        noise[fig] = {"signal": f, "sigma": sigma, "iae_bound": scored * sigma * math.sqrt(2.0 / math.pi) * dt}
    kind = side.get("kind") or ("heating" if np.nanmean(applied[:, INPUTS.index("heater_cmd_w")]) > 1.0 else "cooling")
    info = {"log": str(path), "controller": controller, "kind": kind, "warmup_s": warm, "scored_samples": scored,
            "noise": noise, "sidecar": side, "description": side.get("description", "")}
    return tr, info


def ratio_band(mpc: float, base: float, mpc_bound: float, base_bound: float) -> tuple[float, float] | None:
    """Lowest and highest MPC / baseline ratio the noise bounds allow (None if undefined)."""
    lo_b, hi_b = base - base_bound, base + base_bound
    if not all(math.isfinite(x) for x in (mpc, base, mpc_bound, base_bound)) or lo_b <= 0:
        return None
    return max(mpc - mpc_bound, 0.0) / hi_b, (mpc + mpc_bound) / lo_b


def _energy_wh(tr: Trace, start: int) -> tuple[float, tuple[float, float], float]:
    """Energy (Wh) of a run from sample ``start`` on, its 95 % band and the heater-power noise (W): the
    blower from its command (exact), the heater from its logged power, whose noise only widens the band."""
    blower = np.asarray(tr.applied, float)[start:, INPUTS.index("blower_power_w")]
    heater = np.asarray(tr.truth["heater_power_w"], float)[start:]
    sigma = noise_iae.second_difference_sigma(heater)
    total, (lo, hi) = noise_iae.sum_band(heater, tr.dt_s, sigma, 1.0 / 3600.0)
    extra = float(np.sum(blower) * tr.dt_s / 3600.0)
    return total + extra, (lo + extra, hi + extra), sigma


def noise_aware(runs: Mapping[str, tuple[Trace, dict]]) -> dict:
    """Per noisy reading's IAE figure, and the energy: each run's noise-aware estimate and band
    (:mod:`.noise_iae`) and the MPC / baseline ratio with its 95 % band."""
    out: dict = {}
    est: dict = {}
    for i, c in enumerate(report.CONTROLLERS):
        tr = runs[c][0]
        k0 = int(np.searchsorted(tr.time_s, tr.metrics_start_s - 1e-9))
        for j, (signal, fig) in enumerate(NOISY.items()):
            est[fig, c] = noise_iae.estimate_iae(tr.truth[signal], tr.reference[signal], tr.dt_s, k0, tr.applied,
                                                 noise_iae.CLEANING[signal], seed=10 * j + i)
        est["energy_wh", c] = _energy_wh(tr, k0)
    for signal, fig in NOISY.items():
        band = noise_iae.ratio_band(est[fig, "mpc"], est[fig, "baseline"])  # (ratio, (low, high)) or None
        cl = noise_iae.CLEANING[signal]
        out[fig] = {"signal": signal, "ratio": band[0] if band else None, "band": list(band[1]) if band else None,
                    "method": {"command_lags": cl.lags, "window_samples": cl.window},
                    **{c: {k: (list(v) if isinstance(v, tuple) else v) for k, v in est[fig, c].items() if k != "errors"}
                       for c in report.CONTROLLERS}}
    (em, (lm, hm), sm), (eb, (lb, hb), sb) = est["energy_wh", "mpc"], est["energy_wh", "baseline"]
    out["energy_wh"] = {"signal": "blower command + heater_power_w", "ratio": metrics.ratio(em, eb),
                        "band": [lm / hb, hm / lb] if lb > 0 else None,
                        "mpc": {"estimate": em, "band": [lm, hm], "heater_sigma_w": sm},
                        "baseline": {"estimate": eb, "band": [lb, hb], "heater_sigma_w": sb}}
    return out


def build_results(logs: Sequence[str | Path], warmup_s: float | None = None, scenario: str | None = None) -> tuple[dict, dict]:
    """Results in the bench's layout (scenarios -> baseline, mpc, ratios, criteria) and the traces."""
    nominal = Parameters()
    lower, upper = actuator_bounds(nominal)
    groups: dict[str, dict[str, tuple[Trace, dict]]] = {}
    for log in logs:
        tr, info = trace_from_log(log, warmup_s, scenario)
        runs = groups.setdefault(tr.scenario, {})
        if tr.controller in runs:
            raise LogFormatError(f"{log}: a second {tr.controller} run of {tr.scenario} "
                                 f"(first: {runs[tr.controller][1]['log']}); give one log per controller and scenario")
        runs[tr.controller] = (tr, info)
    results: dict = {"scenarios": {}, "logs": [str(x) for x in logs]}
    traces: dict = {}
    for name, runs in groups.items():
        traces[name] = {c: tr for c, (tr, _) in runs.items()}
        entry: dict = {"runs": {}}
        for c, (tr, info) in runs.items():
            fig = metrics.run_figures(tr, lower, upper, nominal.heater_temp_max_c, nominal.trap_threshold_pct,
                                      nominal.tau_tc_s)
            fig["figures"] = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                              for k, v in fig["figures"].items()}
            entry[c] = fig
            entry["runs"][c] = info
        first = next(iter(runs.values()))[1]
        entry.update({"kind": first["kind"], "description": first["description"], "warmup_s": first["warmup_s"],
                      "scored_s": first["scored_samples"] * next(iter(runs.values()))[0].dt_s})
        if all(c in runs for c in report.CONTROLLERS):
            m, b = entry["mpc"], entry["baseline"]
            entry["ratios"] = metrics.ratios(m["figures"], b["figures"])
            entry["criteria"] = criteria.judge(entry["kind"], m["figures"], b["figures"], m["details"], b["details"])
            nm, nb = entry["runs"]["mpc"]["noise"], entry["runs"]["baseline"]["noise"]
            entry["ratio_noise"] = {fig: ratio_band(m["figures"][fig], b["figures"][fig], nm[fig]["iae_bound"],
                                                    nb[fig]["iae_bound"]) for fig in NOISY.values()}
            entry["noise_aware"] = noise_aware(runs)
        results["scenarios"][name] = entry
    return results, traces


def markdown(results: Mapping, plots: Mapping[str, str], command: str) -> str:
    """The report text (figures from readings; noise bands stated)."""
    out = ["# Report from logs: MPC against the thesis baseline", "", f"Command: `{command}`", "",
           "Figures as in `hvac-mpc bench`, computed from the logged readings (the box's noisy sensors, not a "
           "noise-free truth) and the commands as applied after the daemon's safety layer; rows of the shutdown "
           "sequence are not scored. Figures needing signals the logs do not hold are `-`. Noise: sigma of each "
           "reading from its second differences; 'noise bound' is the most the noise can add to an IAE "
           "(N sigma sqrt(2/pi) dt), and the ratio band is what those bounds allow.", ""]
    for name, sc in results["scenarios"].items():
        out += [f"## {name}", "", sc.get("description") or "", ""]
        for c, info in sc["runs"].items():
            nz = "; ".join(f"{v['signal']} sigma {v['sigma']:.3g}, IAE noise bound {v['iae_bound']:.3g}"
                           for v in info["noise"].values())
            out.append(f"- {c}: `{info['log']}`, {info['scored_samples']} scored samples after "
                       f"{info['warmup_s']:.0f} s warm-up; {nz}")
        out.append("")
        if "ratios" not in sc:
            out += ["Only " + ", ".join(sc["runs"]) + " logged: no ratios.", ""]
            continue
        out += ["| figure | baseline | MPC | MPC/baseline |", "|---|---|---|---|"]
        out += [f"| {label} | {b} | {m} | {r} |" for label, b, m, r in report.figure_rows(sc)]
        out.append("")
        for fig, band in sc["ratio_noise"].items():
            text = (f"noise band [{band[0]:.2f}, {band[1]:.2f}]" if band is not None else
                    "no noise band: the noise bound reaches the baseline's figure, the ratio says little")
            out.append(f"- ratio {fig}: {report._fmt_ratio(sc['ratios'][fig])}, {text}")
        out += ["", "Noise-aware (the reading cleaned with the applied commands and a centred average, zero "
                "phase; corrected for the noise left; 95 % band from a bootstrap over the estimated noise):", "",
                "| figure | noise sigma baseline / MPC | baseline: estimate [band] | MPC: estimate [band] | "
                "MPC/baseline [band] |", "|---|---|---|---|---|"]
        out += [_noise_aware_row(fig, v) for fig, v in sc["noise_aware"].items()]
        out.append("")
        for c in sc["criteria"]:
            line = f"- {c['status']}: {c['criterion']}, {c['value']}"
            if c["ratio"] is not None:
                line += f", ratio {report._fmt_ratio(c['ratio'])}"
            out.append(line)
        if name in plots:
            out += ["", f"![{name}]({plots[name]})"]
        out.append("")
    return "\n".join(out) + "\n"


def _noise_aware_row(fig: str, v: Mapping) -> str:
    """One markdown row of the noise-aware table."""
    def one(x: Mapping) -> str:
        text = f"{x['estimate']:.4g} [{x['band'][0]:.4g}, {x['band'][1]:.4g}]"
        if x.get("resolved") is False:
            text += f", not resolved (noise floor {x['noise_floor']:.3g})"
        return text
    sig = " / ".join(f"{v[c].get('sigma', v[c].get('heater_sigma_w')):.3g}" for c in report.CONTROLLERS)
    m = v.get("method")
    if m is None:
        how = " (blower command, heater power reading)"
    elif m["command_lags"]:
        how = f" (commands lagged 1-{m['command_lags']} samples, window {m['window_samples']} samples)"
    else:
        how = f" (window {m['window_samples']} samples)"
    if not v["band"]:
        band = "no band: neither figure is above the noise floor"
    elif math.isinf(v["band"][1]):
        band = f"at least {v['band'][0]:.2f} (the baseline's figure is below the noise floor)"
    else:
        band = f"{v['ratio']:.2f} [{v['band'][0]:.2f}, {v['band'][1]:.2f}]"
    return f"| {fig}{how} | {sig} | {one(v['baseline'])} | {one(v['mpc'])} | {band} |"


# ---------------------------------------------------------------------------- CLI
def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOG", help="measurement logs (CSV/Parquet), e.g. daemon logs")
    parser.add_argument("--out", default="out/report", metavar="DIR", help="output folder (default: out/report)")
    parser.add_argument("--warmup", type=float, default=None, metavar="S",
                        help="seconds at the start not scored (default: from the LOG.json sidecar, else 0)")
    parser.add_argument("--scenario", default=None, metavar="NAME",
                        help="scenario name for logs without a sidecar (default: from the sidecar or the file name)")
    parser.add_argument("--no-plots", action="store_true", help="write the report without PNG plots")


def run(args: argparse.Namespace) -> int:
    if args.warmup is not None and not (math.isfinite(args.warmup) and args.warmup >= 0):
        print(f"hvac-mpc report: --warmup must be a number >= 0, got {args.warmup}", file=sys.stderr)
        return 2
    try:
        results, traces = build_results(args.logs, args.warmup, args.scenario)
    except (LogFormatError, FileNotFoundError, KeyError) as exc:
        print(f"hvac-mpc report: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plots: dict[str, str] = {}
    if not args.no_plots:
        plt = report.import_pyplot()
        if plt is None:
            print("no plots: matplotlib is not installed (pip install -e \".[plot]\")", file=sys.stderr)
        else:
            for name, runs in traces.items():
                report.plot_scenario(plt, name, runs, results["scenarios"][name]["warmup_s"], out / f"{name}.png")
                plots[name] = f"{name}.png"
    command = "hvac-mpc report " + " ".join(args.logs)
    report.write_json(results, out / "results.json")
    (out / "report.md").write_text(markdown(results, plots, command))
    for name, sc in results["scenarios"].items():
        if "ratios" in sc:
            r = sc["ratios"]
            band = sc["ratio_noise"]["temp_iae_cs"]
            print(f"{name}: temp IAE ratio {report._fmt_ratio(r['temp_iae_cs'])}"
                  + (f" (noise band {band[0]:.2f}-{band[1]:.2f})" if band else "")
                  + f", flow IAE {report._fmt_ratio(r['flow_iae_m3'])}, energy {report._fmt_ratio(r['energy_wh'])}")
            na = "; ".join(f"{fig} {v['ratio']:.2f} [{v['band'][0]:.2f}, {v['band'][1]:.2f}]"
                           if math.isfinite(v["band"][1]) else f"{fig} at least {v['band'][0]:.2f}"
                           for fig, v in sc["noise_aware"].items() if v["band"])
            print(f"{name}: noise-aware ratios (95 % band): {na or 'none resolved'}")
        else:
            print(f"{name}: {', '.join(sc['runs'])} only")
    print(f"report: {out / 'report.md'}  results: {out / 'results.json'}")
    return 0
