"""``hvac-mpc bench``: the MPC against the thesis baseline on the same scenarios and the same plant.

The plant is the simulated box with all its non-ideal effects, seeded noise, and a seeded
perturbation of physical parameters (:mod:`.perturbation`); the controllers get the nominal
parameters. Output in ``--out`` (default ``out/bench``): ``results.json``, ``report.md``, one PNG
per scenario (matplotlib, extra ``plot``) and the sampled runs as measurement logs in ``logs/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from hvac_mpc.models import measurement_log
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.models.plant import PLANT_EFFECTS
from hvac_mpc.contract import Command

from . import criteria, metrics, mismatch_suite, plant_seam, report, scenarios as scenario_defs
from .perturbation import MAGNITUDE_RANGE, perturb_parameters
from .simulate import DETERMINISTIC_DEADLINE_S, Trace, actuator_bounds, plant_seed, simulate

DT_S = 1.0


# ---------------------------------------------------------------------------- controllers
def baseline_factory() -> Callable[[Command], object]:
    """Factory of the thesis baseline (``hvac_mpc.mpc.baseline``) on the nominal parameters.

    The baseline starts its loops from rest as in the thesis (its flow integrator is preset from
    the first measurement); the initial command is not passed to it.
    """
    try:
        from hvac_mpc.mpc.baseline import BaselineController
    except ImportError as exc:
        raise RuntimeError(f"the thesis baseline hvac_mpc.mpc.baseline.BaselineController is not available: {exc}")
    return lambda initial_command: BaselineController(Parameters(), dt_s=DT_S)


def mpc_factory(params: Parameters | None = None,
                deadline_s: float = DETERMINISTIC_DEADLINE_S,
                settings: Mapping[str, Any] | None = None) -> Callable[[Command], object]:
    """Factory of the MPC (``hvac_mpc.mpc.mpc_controller``) on the nominal parameters (or ``params``,
    e.g. a lab's parameter file with its transport delay) and default settings.

    Its non-default settings are ``initial_command``, the command in force on the plant when the
    scenario starts (the MPC rate-limits its first move from it), and ``deadline_s``: by default
    :data:`DETERMINISTIC_DEADLINE_S`, so the run depends on the iteration caps, not on the machine's
    load (``hvac-mpc bench --deadline-s 0.5`` runs with the box's wall-clock deadline and fallbacks).
    ``settings``: fields of ``MpcSettings`` to change (``--mpc-settings FILE``, :func:`mpc_settings_values`).
    """
    try:
        from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
        from hvac_mpc.mpc.settings_file import settings_with
    except ImportError as exc:
        raise RuntimeError(f"the MPC hvac_mpc.mpc.mpc_controller.MpcController is not available: {exc}")
    chosen = params or Parameters()
    base = settings_with(MpcSettings(deadline_s=deadline_s), settings or {})  # checked here, before any run
    return lambda initial_command: MpcController(chosen, dataclasses.replace(base, initial_command=initial_command))


def describe_controller(ctrl) -> str:
    """Short text of a controller's settings for the report (dataclass fields of ``settings`` if any)."""
    settings = getattr(ctrl, "settings", None)
    name = type(ctrl).__name__
    if settings is not None and dataclasses.is_dataclass(settings):
        fields = {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)}
        simple = {k: v for k, v in fields.items() if isinstance(v, (int, float, str, bool)) or v is None}
        return f"{name}(" + ", ".join(f"{k}={v}" for k, v in simple.items()) + ")"
    return name


# ---------------------------------------------------------------------------- progress
class ProgressBar:
    """Plain text progress bar on a stream (stderr by default), redrawn at most every 0.2 s."""

    def __init__(self, total: int, stream=None, width: int = 30, enabled: bool = True):
        self.total = max(int(total), 1)
        self.done = 0
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.enabled = enabled
        self.label = ""
        self._last = 0.0
        self._t0 = time.perf_counter()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def advance(self, n: int = 1, label: str | None = None) -> None:
        self.done = min(self.done + n, self.total)
        if label is not None:
            self.label = label
        now = time.perf_counter()
        if now - self._last >= (0.2 if self._tty else 5.0) or self.done == self.total:
            self._last = now
            self.draw()

    def draw(self) -> None:
        if not self.enabled:
            return
        frac = self.done / self.total
        fill = int(round(frac * self.width))
        text = (f"[{'#' * fill}{'.' * (self.width - fill)}] {frac:4.0%} {self.label} "
                f"{time.perf_counter() - self._t0:.0f} s")
        self.stream.write(("\r" + text.ljust(90)) if self._tty else text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self._tty:
            self.stream.write("\n")
            self.stream.flush()


# ---------------------------------------------------------------------------- benchmark
def run_benchmark(chosen: Sequence[scenario_defs.Scenario], factories: Mapping[str, Callable[[], object]],
                  seed: int, progress: ProgressBar | None = None,
                  plant_factory: Callable[..., object] | None = None,
                  plant_name: str = "SimulatedPlant") -> tuple[dict, dict[str, dict[str, Trace]]]:
    """Run every controller on every scenario; figures, ratios and criteria from this one run.

    ``factories`` must hold "baseline" and "mpc", each a callable taking the command in force on
    the plant at the start and giving a fresh controller on the nominal parameters (a fresh one per
    scenario, so a scenario's numbers do not depend on which scenarios ran before it).
    ``plant_factory`` (keywords ``seed``, ``dt_s``; :mod:`.plant_seam`) builds a fresh plant per run
    instead of the perturbed built-in one. Returns ``(results, traces)``.
    """
    missing = [c for c in report.CONTROLLERS if c not in factories]
    if missing:
        raise ValueError(f"factories: missing controller(s) {missing}; expected {list(report.CONTROLLERS)}")
    nominal = Parameters()
    plant_params, perturbation = perturb_parameters(nominal, seed)
    if plant_factory is not None:
        plant_params, perturbation = nominal, []
    lower, upper = actuator_bounds(nominal)
    results: dict = {"scenarios": {}}
    traces: dict[str, dict[str, Trace]] = {}
    settings: dict[str, str] = {}
    build_s: dict[str, list[float]] = {c: [] for c in report.CONTROLLERS}
    for sc in chosen:
        runs = {}
        traces[sc.name] = {}
        for cname in report.CONTROLLERS:
            tic = time.perf_counter()
            ctrl = factories[cname](sc.initial_command)
            build_s[cname].append(time.perf_counter() - tic)
            settings.setdefault(cname, describe_controller(ctrl))
            cb = None
            if progress is not None:
                label = f"{sc.name} {report.LABELS[cname]}"
                cb = lambda k, n, label=label: progress.advance(1, label)  # noqa: E731
            plant = None
            if plant_factory is not None:
                plant = plant_seam.build_plant(plant_factory, plant_seed(seed, sc.seed), DT_S, name=plant_name)
            tr = simulate(sc, ctrl, plant_params, seed, name=cname, progress=cb, dt_s=DT_S, plant=plant)
            traces[sc.name][cname] = tr
            runs[cname] = metrics.run_figures(tr, lower, upper, nominal.heater_temp_max_c,
                                              nominal.trap_threshold_pct, plant_params.tau_tc_s)
        b, m = runs["baseline"], runs["mpc"]
        results["scenarios"][sc.name] = {
            "description": sc.description, "kind": sc.kind, "seed": sc.seed, "duration_s": sc.duration_s,
            "warmup_s": sc.metrics_start_s, "scored_s": sc.duration_s - sc.metrics_start_s,
            "inlet_temp_c": sc.inlet_temp_c, "chiller_setpoint_c": sc.chiller_setpoint_c,
            "notes": list(sc.notes) + cabin_notes(sc, traces[sc.name]),
            "step_times_s": sc.step_times_s(),
            "references": [{"from_s": 0.0, **sc.warmup.reference.as_dict()}]
            + [{"from_s": t, **seg.reference.as_dict()} for t, seg in zip(sc.step_times_s(), sc.segments)],
            "baseline": b, "mpc": m,
            "ratios": metrics.ratios(m["figures"], b["figures"]),
            "criteria": criteria.judge(sc.kind, m["figures"], b["figures"], m["details"], b["details"]),
        }
    results["summary"] = report.summarise(results["scenarios"])
    results["criteria_names"] = report.criteria_names(results["scenarios"])
    results["meta"] = {
        "seed": seed, "plant": plant_name,
        "plant_effects": list(PLANT_EFFECTS) if plant_factory is None else [],
        "perturbation": [dataclasses.asdict(p) for p in perturbation],
        "perturbation_rule": (f"Rule: each listed parameter is multiplied by 1 + s m, sign s random, magnitude m "
                              f"uniform in [{MAGNITUDE_RANGE[0]:.0%}, {MAGNITUDE_RANGE[1]:.0%}], drawn from the "
                              f"seed ({seed}) in the order listed (`benchmarks/perturbation.py`)."),
        "heater_temp_max_c": nominal.heater_temp_max_c,
        "controller_settings": settings,
        "controller_build_s": {c: float(np.median(v)) if v else None for c, v in build_s.items()},
        "sample_time_s": DT_S,
    }
    return results, traces


def cabin_notes(sc: scenario_defs.Scenario, runs: Mapping[str, Trace]) -> list[str]:
    """For a scenario with the cabin in the loop: where each controller left the cabin and the inlet."""
    if sc.cabin is None:
        return []
    parts = []
    for cname, tr in runs.items():
        cabin, inlet = tr.measured["cabin_temp_c"], tr.measured["hvac_inlet_temp_c"]
        parts.append(f"{report.LABELS[cname]}: cabin air {cabin[0]:.1f} -> {cabin[-1]:.1f} C, box inlet "
                     f"{np.mean(inlet[:10]):.1f} -> {np.mean(inlet[-10:]):.1f} C")
    return ["Cabin in the loop (" + "; ".join(parts) + ")."]


def write_logs(traces: Mapping[str, Mapping[str, Trace]], folder: Path) -> None:
    """Each run as a measurement log (docs/model.md sec. 4): sensor readings, commands, references."""
    folder.mkdir(parents=True, exist_ok=True)
    for sname, runs in traces.items():
        for cname, tr in runs.items():
            n = tr.time_s.size
            cols = {"time_s": tr.time_s}
            for i, a in enumerate(tr.actuators):
                cols[a] = tr.applied[:, i]
            cols.update({"hvac_inlet_temp_c": tr.measured["hvac_inlet_temp_c"],
                         "cabin_temp_c": tr.measured["cabin_temp_c"],
                         "volume_flow_m3s": tr.measured["volume_flow_m3s"],
                         "supply_temp_c": tr.measured["supply_temp_c"],
                         "heater_power_w": tr.truth["heater_power_w"],
                         "water_temp_c": tr.truth["water_temp_c"],
                         "chiller_setpoint_c": np.full(n, tr.environment["chiller_setpoint_c"]),
                         "heater_outlet_temp_c": tr.truth["heater_outlet_temp_c"]})
            for f in ("supply_temp_c", "volume_flow_m3s", "flow_m_m3s", "flow_f_m3s", "flow_w_m3s"):
                cols[f"ref_{f}"] = tr.reference[f]
            cols["mode"] = ["" if v is None else str(v) for v in tr.mode]
            cols["controller"] = [cname] * n
            measurement_log.write_log(folder / f"{sname}__{cname}.csv", cols)


def write_outputs(results: dict, traces: Mapping[str, Mapping[str, Trace]], out: Path, plots: bool) -> list[str]:
    """results.json, report.md, PNG plots and logs in ``out``; returns notes for the terminal."""
    out.mkdir(parents=True, exist_ok=True)
    notes = []
    plot_files: dict[str, str] = {}
    plot_note = None
    if plots:
        plt = report.import_pyplot()
        if plt is None:
            plot_note = ("No plots: matplotlib is not installed (install the extra: pip install -e \".[plot]\").")
            notes.append(plot_note)
        else:
            for name, runs in traces.items():
                fname = f"{name}.png"
                report.plot_scenario(plt, name, runs, results["scenarios"][name]["warmup_s"], out / fname)
                plot_files[name] = fname
    else:
        plot_note = "Plots switched off (--no-plots)."
    write_logs(traces, out / "logs")
    report.write_json(results, out / "results.json")
    (out / "report.md").write_text(report.markdown(results, plot_files, plot_note))
    return notes


# ---------------------------------------------------------------------------- CLI
def configure(parser: argparse.ArgumentParser) -> None:
    names = list(scenario_defs.all_scenarios())
    parser.add_argument("--quick", action="store_true", help="short version of every scenario (what the tests run)")
    parser.add_argument("--scenario", action="append", metavar="NAME", default=None,
                        help=f"run only this scenario (repeatable); one of: {', '.join(names)}")
    parser.add_argument("--out", default="out/bench", metavar="DIR", help="output folder (default: out/bench)")
    parser.add_argument("--seed", type=int, default=0, metavar="N",
                        help="seed of the plant perturbation and the sensor noise (default: 0)")
    parser.add_argument("--no-plots", action="store_true", help="write the report without PNG plots")
    parser.add_argument("--plant", metavar="MODULE:FACTORY", default=None,
                        help="run on the plant this function builds (keywords seed, dt_s; an object with "
                             "apply/advance/read, optionally set_environment/settle/truth) instead of the "
                             "built-in simulated plant")
    parser.add_argument("--mpc-params", metavar="FILE", default=None,
                        help="the MPC's parameters from this TOML or JSON file (e.g. transport_delay_s of the "
                             "box); the baseline keeps the thesis values")
    parser.add_argument("--mpc-settings", metavar="FILE", default=None,
                        help="the MPC's settings from this TOML or JSON file: fields of MpcSettings, sub-tables "
                             "[ocp], [ocp.weights], [ekf] (docs/extending.md); every run of the MPC, the --model "
                             "comparison's included, uses them; the baseline is untouched")
    parser.add_argument("--suite", choices=("mismatch",), default=None,
                        help="mismatch: both controllers on every variant of the independent simulator "
                             "(hvac_mpc.mismatch) on the cooling, heating and proband scenarios; a matrix of "
                             "MPC/baseline ratios")
    parser.add_argument("--variant", action="append", metavar="NAME", default=None,
                        help="--suite mismatch: run only this registered variant (repeatable; default: all)")
    parser.add_argument("--box", action="append", metavar="LABEL:FIELD=VALUE,...", default=None,
                        help="--suite mismatch: also run a box the registry does not have, the fields of "
                             "hvac_mpc.mismatch.Variant, e.g. U1:transport_delay_s=2,duct_loss_ua_w_per_k=4,"
                             "cooler_literal_fit=true (repeatable)")
    parser.add_argument("--model", metavar="FILE", default=None,
                        help="model file (hvac-mpc identify): also run the MPC with this refined model against the "
                             "nominal MPC on the independent box --model-plant (section in the report)")
    parser.add_argument("--deadline-s", type=float, default=None, metavar="S",
                        help="the MPC's wall-clock deadline per step in s, with the fallbacks when a step misses "
                             "it (the box's default is 0.5); default: none, the run is bounded by iteration caps "
                             "only, so its figures do not depend on the machine's load")
    parser.add_argument("--model-plant", metavar="VARIANT", default="nominal",
                        help="hvac_mpc.mismatch variant the --model comparison runs on (default: nominal)")


def suite_plants(args: argparse.Namespace) -> tuple[list[str], dict]:
    """The suite's rows: the registered variants ``--variant`` picks (all without it; none when only
    ``--box`` is given) and the boxes of ``--box``. Raises ValueError naming what is allowed."""
    allowed = mismatch_suite.variant_names()
    picked = getattr(args, "variant", None)
    unknown = [v for v in picked or [] if v not in allowed]
    if unknown:
        raise ValueError(f"--variant: unknown name(s) {unknown} in the mismatch suite; choose from {allowed}")
    boxes = dict(mismatch_suite.parse_box(spec) for spec in getattr(args, "box", None) or [])
    clash = [label for label in boxes if label in allowed]
    if clash:
        raise ValueError(f"--box: label(s) {clash} are registered variant names; pick another label")
    variants = list(dict.fromkeys(picked)) if picked else ([] if boxes else allowed)
    return variants, boxes


def mpc_deadline(args: argparse.Namespace) -> float:
    """``--deadline-s`` checked (0 < s <= 3600), or the deterministic default."""
    value = getattr(args, "deadline_s", None)
    if value is None:
        return DETERMINISTIC_DEADLINE_S
    if not 0.0 < value <= DETERMINISTIC_DEADLINE_S:
        raise ValueError(f"--deadline-s must be within (0, {DETERMINISTIC_DEADLINE_S:g}] s, got {value}")
    return value


def run(args: argparse.Namespace) -> int:
    if args.seed < 0:
        print(f"hvac-mpc bench: --seed must be an integer >= 0, got {args.seed}", file=sys.stderr)
        return 2
    if getattr(args, "suite", None) == "mismatch":
        return run_mismatch_suite(args)
    if getattr(args, "variant", None) or getattr(args, "box", None):
        print("hvac-mpc bench: --variant and --box choose the rows of --suite mismatch; add --suite mismatch",
              file=sys.stderr)
        return 2
    plant_factory = None
    try:
        if getattr(args, "plant", None):
            plant_factory = plant_seam.load_factory(args.plant)
        chosen = scenario_defs.select(args.scenario, quick=args.quick)
        factories = {"baseline": baseline_factory(), "mpc": mpc_factory(mpc_parameters(args), mpc_deadline(args),
                                                                    mpc_settings_values(args))}
        if args.model:
            from . import refined_model
            refined_model.check(args.model, args.model_plant)
    except (ValueError, RuntimeError, OSError, KeyError) as exc:
        print(f"hvac-mpc bench: {exc}", file=sys.stderr)
        return 2
    command = "hvac-mpc bench" + "".join(f" {shlex.quote(a)}" for a in _argv_from(args))
    t0 = time.perf_counter()
    bar = ProgressBar(sum(int(round(s.duration_s / DT_S)) for s in chosen) * len(report.CONTROLLERS))
    try:
        results, traces = run_benchmark(chosen, factories, args.seed, progress=bar, plant_factory=plant_factory,
                                        plant_name=args.plant or "SimulatedPlant")
    except plant_seam.InvalidPlant as exc:
        print(f"hvac-mpc bench: {exc}", file=sys.stderr)
        return 2
    finally:
        bar.close()
    results["meta"].update({"command": command, "quick": bool(args.quick),
                            "elapsed_s": time.perf_counter() - t0,
                            "platform": f"{platform.system()} {platform.machine()}",
                            "python": platform.python_version()})
    out = Path(args.out)
    notes = write_outputs(results, traces, out, plots=not args.no_plots)
    if args.model:
        refined_model.add_to_outputs(refined_model.compare(args.model, args.model_plant, chosen, args.seed,
                                                            deadline_s=mpc_deadline(args),
                                                            overrides=mpc_settings_values(args)), out)
    print(report.terminal_table(results))
    for n in notes:
        print(n)
    print(f"report: {out / 'report.md'}  results: {out / 'results.json'}")
    return 0


def run_mismatch_suite(args: argparse.Namespace) -> int:
    """``--suite mismatch``: every variant of the independent simulator (:mod:`.mismatch_suite`);
    ``--scenario`` picks among the suite's scenarios; output in ``--out`` (default out/mismatch)."""
    if args.plant:
        print("hvac-mpc bench: --suite mismatch brings its own plants; drop --plant", file=sys.stderr)
        return 2
    known = scenario_defs.mismatch_scenarios()
    names = args.scenario or list(known)
    unknown = [n for n in names if n not in known]
    if unknown:
        print(f"hvac-mpc bench: --scenario: unknown name(s) {unknown} in the mismatch suite; choose from "
              f"{list(known)}", file=sys.stderr)
        return 2
    try:
        factories = {"baseline": baseline_factory(), "mpc": mpc_factory(mpc_parameters(args), mpc_deadline(args),
                                                                    mpc_settings_values(args))}
    except (ValueError, RuntimeError) as exc:
        print(f"hvac-mpc bench: {exc}", file=sys.stderr)
        return 2
    chosen = [known[n].quick() if args.quick else known[n] for n in dict.fromkeys(names)]
    try:
        variants, boxes = suite_plants(args)
    except ValueError as exc:
        print(f"hvac-mpc bench: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    rows = len(variants) + len(boxes)
    bar = ProgressBar(rows * sum(int(round(s.duration_s / DT_S)) for s in chosen) * len(report.CONTROLLERS))
    try:
        results, traces = mismatch_suite.run_suite(variants, chosen, factories, args.seed, run_benchmark,
                                                   progress=bar, boxes=boxes)
    finally:
        bar.close()
    results["meta"] = {"command": "hvac-mpc bench" + "".join(f" {shlex.quote(a)}" for a in _argv_from(args)),
                       "seed": args.seed, "quick": bool(args.quick), "elapsed_s": time.perf_counter() - t0,
                       "scenarios": [s.name for s in chosen], "variants": variants,
                       "boxes": {label: dataclasses.asdict(v) for label, v in boxes.items()}}
    out = Path(args.out if args.out != "out/bench" else "out/mismatch")
    mismatch_suite.write_outputs(results, traces, out, plots=not args.no_plots)
    print(mismatch_suite.terminal_text(results))
    print(f"report: {out / 'report.md'}  results: {out / 'results.json'}")
    return 0


def mpc_parameters(args: argparse.Namespace) -> Parameters | None:
    """The MPC's parameters from ``--mpc-params`` (None: nominal); errors name the file."""
    path = getattr(args, "mpc_params", None)
    if not path:
        return None
    try:
        return Parameters.from_file(path)
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"--mpc-params {path}: {exc}") from exc


def mpc_settings_values(args: argparse.Namespace) -> dict[str, Any]:
    """The MPC's settings from ``--mpc-settings`` ({} without it); errors name the file and the field.
    ``initial_command`` and ``deadline_s`` are the bench's own (each scenario's command, ``--deadline-s``)."""
    path = getattr(args, "mpc_settings", None)
    if not path:
        return {}
    from hvac_mpc.mpc.settings_file import read_settings_file
    values = read_settings_file(path)
    owned = sorted({"initial_command", "deadline_s"} & set(values))
    if owned:
        raise ValueError(f"--mpc-settings {path}: {owned} are set by the bench (each scenario's command, "
                         f"--deadline-s), not by the settings file")
    return values


def _argv_from(args: argparse.Namespace) -> list[str]:
    """The options as typed, rebuilt from the parsed arguments (for the report's command line)."""
    argv = []
    if args.quick:
        argv.append("--quick")
    for s in args.scenario or []:
        argv += ["--scenario", s]
    if args.out != "out/bench":
        argv += ["--out", str(args.out)]
    if args.seed != 0:
        argv += ["--seed", str(args.seed)]
    if args.no_plots:
        argv.append("--no-plots")
    if getattr(args, "plant", None):
        argv += ["--plant", args.plant]
    if getattr(args, "mpc_params", None):
        argv += ["--mpc-params", args.mpc_params]
    if getattr(args, "mpc_settings", None):
        argv += ["--mpc-settings", args.mpc_settings]
    if getattr(args, "suite", None):
        argv += ["--suite", args.suite]
    for v in getattr(args, "variant", None) or []:
        argv += ["--variant", v]
    for b in getattr(args, "box", None) or []:
        argv += ["--box", b]
    if getattr(args, "deadline_s", None) is not None:
        argv += ["--deadline-s", f"{args.deadline_s:g}"]
    if getattr(args, "model", None):
        argv += ["--model", str(args.model), "--model-plant", args.model_plant]
    return argv
