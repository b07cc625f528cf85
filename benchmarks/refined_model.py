"""The MPC with a refined model (a model file) against the MPC with the nominal model, in one run.

``hvac-mpc bench --model refined.toml --model-plant VARIANT`` runs both MPCs through the chosen
scenarios on the independent box (:mod:`hvac_mpc.mismatch`) of ``VARIANT``, the plant that carries
the effect the model file was refined for, with the same noise seed, and compares the temperature
IAE on the noise-free thermocouple reading (scored part of each scenario). Both controllers have
the same settings; only the model differs (parameters, effects, discovered terms).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from hvac_mpc.mismatch import make_plant
from hvac_mpc.models.model_file import RefinedModel
from hvac_mpc.models.model_file import load as load_model
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.settings_file import settings_with

from .scenarios import Scenario
from .simulate import DETERMINISTIC_DEADLINE_S, plant_seed


def closed_loop_iae(scenario: Scenario, controller, variant: str, seed: int, dt_s: float = 1.0) -> dict[str, float]:
    """Temperature IAE (C s) of ``controller`` on the independent box of ``variant`` (scored samples), and
    ``run_temp_iae_cs``: the same over the whole run, the unscored warm-up included (where a controller still
    finds what a model file already says, e.g. a transport delay)."""
    plant = make_plant(variant, seed=plant_seed(seed, scenario.seed), dt_s=dt_s,
                       inlet_temp_c=scenario.inlet_temp_c, chiller_setpoint_c=scenario.chiller_setpoint_c,
                       initial_command=scenario.initial_command)
    controller.reset(scenario.initial_command)
    n = int(round(scenario.duration_s / dt_s))
    err_tc, err_air, err_flow, err_run = [], [], [], []
    for k in range(n):
        t = k * dt_s
        r = scenario.reference_at(t)
        m = plant.read()
        y = plant.truth()
        if r.supply_temp_c is not None:
            err_run.append(abs(y["supply_temp_c"] - r.supply_temp_c))
        if t >= scenario.metrics_start_s and r.supply_temp_c is not None:
            err_tc.append(abs(y["supply_temp_c"] - r.supply_temp_c))
            err_air.append(abs(y["supply_air_temp_c"] - r.supply_temp_c))
        if t >= scenario.metrics_start_s and r.volume_flow_m3s is not None:
            err_flow.append(abs(y["volume_flow_m3s"] - r.volume_flow_m3s))
        result = controller.step(m, r)
        u = np.asarray(result.command.vector(), float)
        if np.all(np.isfinite(u)):
            plant.apply(u)
        plant.advance()
    return {"temp_iae_cs": float(np.sum(err_tc) * dt_s), "air_temp_iae_cs": float(np.sum(err_air) * dt_s),
            "flow_iae_m3": float(np.sum(err_flow) * dt_s), "run_temp_iae_cs": float(np.sum(err_run) * dt_s)}


def _without(settings: MpcSettings, effects: Sequence[str]) -> MpcSettings:
    """``settings`` whose prediction model leaves out ``effects``."""
    ocp = settings.ocp
    return dataclasses.replace(settings, ocp=dataclasses.replace(
        ocp, model_effects=tuple(e for e in ocp.model_effects if e not in effects)))


def with_overrides(settings: MpcSettings, overrides: Mapping[str, Any] | None = None,
                   weights: Mapping[str, float] | None = None) -> MpcSettings:
    """``settings`` with fields of :class:`MpcSettings` (``overrides``, sub-tables into the settings it holds,
    :func:`~hvac_mpc.mpc.settings_file.settings_with`) and of its cost weights (``weights``,
    :class:`~hvac_mpc.mpc.ocp.Weights`) replaced; a name that is not a field raises ValueError naming it."""
    def _replace(obj, values, what):
        unknown = sorted(set(values) - {f.name for f in dataclasses.fields(obj)})
        if unknown:
            raise ValueError(f"unknown {what} field(s) {unknown}")
        return dataclasses.replace(obj, **values)
    if overrides:
        settings = settings_with(settings, overrides)
    if weights:
        ocp = settings.ocp
        settings = dataclasses.replace(settings, ocp=dataclasses.replace(
            ocp, weights=_replace(ocp.weights, weights, "Weights")))
    return settings


def compare(model_path: str | Path, variant: str, scenarios: Sequence[Scenario], seed: int = 0,
            attribution: bool = False, deadline_s: float | None = None,
            overrides: Mapping[str, Any] | None = None, weights: Mapping[str, float] | None = None) -> dict:
    """Nominal against refined MPC per scenario: IAEs and the ratio refined / nominal (``total["run_ratio"]``: the
    same over whole runs, warm-up included, :func:`closed_loop_iae`). ``attribution`` adds
    both MPCs without the effects the file says the box lacks (``absent``, e.g. the controller's own
    ``bypass_flow``): ``nominal_as_identified`` and ``refined_as_identified``, what separates the file's content
    from the controller's own structure (docs/identification.md, "The refined model in the controller").
    ``deadline_s``: both MPCs' feedback deadline (None: :data:`DETERMINISTIC_DEADLINE_S`, so a loaded machine's
    slow steps do not go to the fallback and the comparison depends on the models alone). ``overrides`` and
    ``weights``: both MPCs' settings and cost weights changed alike (:func:`with_overrides`)."""
    refined = load_model(model_path)
    out = {"model_file": str(model_path), "plant_variant": variant, "seed": seed,
           "effects": list(refined.effects), "absent": list(refined.absent),
           "terms": [t.as_dict() for t in refined.terms],
           "transport_delay_s": refined.transport_delay_s, "scenarios": {}}
    runs = ("nominal", "refined") + (("nominal_as_identified", "refined_as_identified") if attribution else ())
    for sc in scenarios:
        settings = with_overrides(MpcSettings(
            initial_command=sc.initial_command,
            deadline_s=DETERMINISTIC_DEADLINE_S if deadline_s is None else float(deadline_s)), overrides, weights)
        bare = _without(settings, refined.absent)
        ctrl = {"nominal": lambda: MpcController(settings=settings),
                "refined": lambda: MpcController(settings=settings, model=refined),
                "nominal_as_identified": lambda: MpcController(settings=bare),
                "refined_as_identified": lambda: MpcController(settings=bare, model=refined)}
        row = {k: closed_loop_iae(sc, ctrl[k](), variant, seed) for k in runs}
        row["ratio"] = row["refined"]["temp_iae_cs"] / max(row["nominal"]["temp_iae_cs"], 1e-12)
        if attribution:
            row["ratio_as_identified"] = (row["refined_as_identified"]["temp_iae_cs"]
                                          / max(row["nominal_as_identified"]["temp_iae_cs"], 1e-12))
        out["scenarios"][sc.name] = row
    total = {k: {f: sum(r[k][f] for r in out["scenarios"].values())
                 for f in ("temp_iae_cs", "air_temp_iae_cs", "flow_iae_m3", "run_temp_iae_cs")}
             for k in runs}
    total["ratio"] = total["refined"]["temp_iae_cs"] / max(total["nominal"]["temp_iae_cs"], 1e-12)
    total["run_ratio"] = total["refined"]["run_temp_iae_cs"] / max(total["nominal"]["run_temp_iae_cs"], 1e-12)
    if attribution:
        total["ratio_as_identified"] = (total["refined_as_identified"]["temp_iae_cs"]
                                        / max(total["nominal_as_identified"]["temp_iae_cs"], 1e-12))
    out["total"] = total
    return out


def markdown(cmp: dict) -> list[str]:
    """The comparison as a report section."""
    lines = ["", "## Refined model against the nominal model", "",
             f"MPC with the model file `{cmp['model_file']}` (effects {cmp['effects']}, absent on the box "
             f"{cmp.get('absent', [])} (the MPC keeps its own bypass_flow), "
             f"{len(cmp['terms'])} discovered term(s), transport delay {cmp['transport_delay_s']:g} s) against the "
             f"MPC with the nominal model, both on the independent box variant `{cmp['plant_variant']}` "
             f"(hvac_mpc.mismatch), seed {cmp['seed']}; temperature IAE on the noise-free thermocouple reading.", "",
             "| scenario | IAE nominal (C s) | IAE refined (C s) | refined / nominal | air IAE nominal | air IAE refined "
             "| flow IAE nominal (m3) | flow IAE refined (m3) |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in list(cmp["scenarios"].items()) + [("all scenarios", cmp["total"])]:
        lines.append(f"| {name} | {r['nominal']['temp_iae_cs']:.1f} | {r['refined']['temp_iae_cs']:.1f} | "
                     f"{r['ratio']:.3f} | {r['nominal']['air_temp_iae_cs']:.1f} | {r['refined']['air_temp_iae_cs']:.1f} | "
                     f"{r['nominal'].get('flow_iae_m3', float('nan')):.2f} | "
                     f"{r['refined'].get('flow_iae_m3', float('nan')):.2f} |")
    run = cmp["total"]
    if "run_ratio" in run:
        lines += ["", f"Whole runs, the unscored warm-up included (where the nominal MPC still finds what the file "
                      f"says, e.g. a delay): nominal {run['nominal']['run_temp_iae_cs']:.1f}, refined "
                      f"{run['refined']['run_temp_iae_cs']:.1f} C s (refined / nominal {run['run_ratio']:.3f})."]
    return lines


def check(model_path: str | Path, variant: str) -> RefinedModel:
    """Load and validate the model file and the plant variant before a long run (clear errors)."""
    from hvac_mpc.mismatch import VARIANTS
    if variant not in VARIANTS:
        raise ValueError(f"--model-plant {variant!r} is not a variant; allowed: {', '.join(VARIANTS)}")
    return load_model(model_path)


def add_to_outputs(cmp: dict, out: Path) -> None:
    """Append the comparison to report.md and results.json in ``out``; print it."""
    import json
    section = markdown(cmp)
    report_md = out / "report.md"
    if report_md.exists():
        report_md.write_text(report_md.read_text().rstrip("\n") + "\n" + "\n".join(section) + "\n")
    results = out / "results.json"
    if results.exists():
        data = json.loads(results.read_text())
        data["refined_model"] = cmp
        results.write_text(json.dumps(data, indent=2))
    print("\n".join(section))


def describe(model: RefinedModel) -> str:
    """One line about a refined model (for the other commands' output)."""
    return (f"model file {model.source}: effects {list(model.effects)}, {len(model.terms)} discovered term(s), "
            f"transport delay {model.transport_delay_s:g} s")
