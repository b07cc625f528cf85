"""Report of an identification run: Markdown with PNG plots, a JSON summary, the model file.

matplotlib is imported only here and only when plots are wanted; without it the report is
written without plots and says so.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from hvac_mpc.models.parameters import Parameters

from . import localise
from .diagnostics import regressors
from .fitting import IDENTIFIED_REL_SE
from .model_file import write_model_file
from .pipeline import ALPHA, FORWARD_MIN, POLISH, SAME_RESIDUAL_CORR, STRUCTURE_MIN, IdentificationResult
from .selection import CONTRIBUTION_MIN

UNITS = {"supply_temp_c": "C", "volume_flow_m3s": "m3/s", "heater_outlet_temp_c": "C", "heater_power_w": "W"}
PLOT_EXTRA = "pip install 'hvac-mpc[plot]'"


def load_pyplot():
    """matplotlib.pyplot with the Agg backend, or ``None`` when matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def _num(v: Any, digits: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    if not math.isfinite(f):
        return "-"
    if f == 0:
        return "0"
    if abs(f) >= 1e4 or abs(f) < 1e-3:
        return f"{f:.{digits - 1}e}"
    return f"{f:.{digits}g}"


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, frozenset):
        return sorted(obj)
    return obj


def _table(header: list[str], rows: list[list[Any]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(_num(c) if not isinstance(c, str) else c for c in row) + " |" for row in rows]
    return out


def _changed_params(res: IdentificationResult, fit) -> dict[str, tuple[float, float]]:
    base = res.base_params.vector()
    return {n: (base[i], float(fit.p[i])) for i, n in enumerate(res.fitter.names) if fit.p[i] != base[i]}


def _written_params(res: IdentificationResult) -> dict[str, dict[str, float]]:
    """Every parameter the model file holds at another value than the base file's (the refit, or the thesis value
    where the file keeps it: :func:`~.pipeline._keep_unidentified`, ``thesis_unless_moved``)."""
    out = {}
    for name in type(res.params).__dataclass_fields__:
        a, b = getattr(res.base_params, name), getattr(res.params, name)
        if isinstance(b, (int, float)) and not isinstance(b, bool) and a != b:
            out[name] = {"base": float(a), "written": float(b)}
    return out


# ---------------------------------------------------------------------------------------------- plots
def _plot_residuals(plt, res: IdentificationResult, out: Path) -> list[str]:
    files = []
    f = res.fitter
    t_min = res.log.time_s / 60.0
    for j, o in enumerate(f.outputs):
        if np.nanstd(f.y_meas[:, j]) == 0:
            continue
        fig, ax = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
        ax[0].plot(t_min, f.y_meas[:, j], lw=0.7, color="k", label="measured")
        ax[0].plot(t_min, res.nominal.y[:, j], lw=0.9, label="nominal model")
        if res.final is not res.nominal:
            ax[0].plot(t_min, res.final.y[:, j], lw=0.9, label="refined model")
        ax[0].set_ylabel(f"{o} [{UNITS.get(o, '')}]")
        ax[0].legend(loc="upper right", fontsize=8)
        ax[1].plot(t_min, f.y_meas[:, j] - res.nominal.y[:, j], lw=0.7, label="residual before")
        if res.final is not res.nominal:
            ax[1].plot(t_min, f.y_meas[:, j] - res.final.y[:, j], lw=0.7, label="residual after")
        ax[1].axhline(0, color="k", lw=0.5)
        for a in ax:
            a.axvspan(res.log.split_time_s / 60.0, t_min[-1], color="0.9", zorder=0)
        ax[1].set_ylabel("free-run error")
        ax[1].set_xlabel("time [min] (grey: held-out part)")
        ax[1].legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        name = f"residual_{o}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        files.append(name)
    return files


def _plot_effect_diagnostic(plt, res: IdentificationResult, acc, out: Path) -> str | None:
    """Binned free-run residual of the primary output against the candidate's regressor, before/after."""
    f = res.fitter
    o = acc.primary_output
    j = f.outputs.index(o)
    before = regressors(f, res.nominal)
    z = before.get(acc.regressor)
    if z is None:
        return None
    mask = res.log.train | res.log.holdout
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for fit, label in ((res.nominal, "before"), (res.final, "after")):
        e = (f.y_meas[:, j] - fit.y[:, j])[mask]
        ax[0].plot(z[mask], e, ".", ms=1.5, alpha=0.4, label=f"residual {label}")
        from .statistics import binned
        b = binned(e, z[mask], acc.regressor, bins=10)
        ax[1].errorbar(b.centers, b.mean, yerr=2 * b.se, marker="o", capsize=3, label=label)
    for a in ax:
        a.set_xlabel(acc.regressor)
        a.set_ylabel(f"{o} residual [{UNITS.get(o, '')}]")
        a.axhline(0, color="k", lw=0.5)
        a.legend(fontsize=8)
    ax[1].set_title("bin means +- 2 SE", fontsize=9)
    fig.suptitle(f"{acc.name}: residual of {o} against {acc.regressor}", fontsize=10)
    fig.tight_layout()
    name = f"diagnostic_{acc.name.replace(':', '_')}.png"
    fig.savefig(out / name, dpi=90)
    plt.close(fig)
    return name


def _plot_ccf(plt, diag: dict, output: str, out: Path, tag: str) -> str | None:
    ccfs = diag["ccf"].get(output, [])[:4]
    if not ccfs:
        return None
    fig, axes = plt.subplots(1, len(ccfs), figsize=(3.2 * len(ccfs), 3), squeeze=False)
    for ax, c in zip(axes[0], ccfs):
        lags = np.arange(len(c["rho"]))
        ax.bar(lags, c["rho"], color="C0")
        ax.plot(lags, c["band"], "r--", lw=0.8)
        ax.plot(lags, -np.array(c["band"]), "r--", lw=0.8)
        ax.set_title(f"{c['signal']}", fontsize=8)
        ax.set_xlabel("lag [samples]")
    axes[0][0].set_ylabel(f"corr({output} residual, signal)")
    fig.tight_layout()
    name = f"ccf_{tag}_{output}.png"
    fig.savefig(out / name, dpi=90)
    plt.close(fig)
    return name


# ---------------------------------------------------------------------------------------------- summary
def summary(res: IdentificationResult) -> dict:
    """Plain-data summary of a run (the JSON file)."""
    log = res.log
    diag_keep = ("metrics", "structure_holdout", "structure_train", "whiteness", "steps", "chiller", "ekf_nll_train",
                 "holdout_tests")

    def slim(d: dict) -> dict:
        out = {k: d[k] for k in diag_keep if k in d}
        out["ccf_top"] = {o: [{k: v for k, v in c.items() if k not in ("rho", "band")} for c in cs[:5]]
                          for o, cs in d["ccf"].items()}
        out["binned_top"] = {o: [{k: v for k, v in b.items() if k in ("variable", "eta2", "f_stat", "p_value")}
                                 for b in bs[:4]] for o, bs in d["binned"].items()}
        for o, w in out.get("whiteness", {}).items():
            w.pop("acf", None)
        return out

    return _jsonable({
        "log": {"source": log.source, "rows": log.n, "dt_s": log.dt_s,
                "duration_s": float(log.time_s[-1] - log.time_s[0]),
                "outputs": list(res.fitter.outputs), "water_logged": log.water_temp_c is not None},
        "split": {"train_rows": int(log.train.sum()), "holdout_rows": int(log.holdout.sum()),
                  "train_start_s": float(log.time_s[np.argmax(log.train)]), "holdout_start_s": log.split_time_s},
        "noise_sigma": res.sigma,
        "nominal_parameters": {k: {"default": a, "fitted": b}
                               for k, (a, b) in _changed_params(res, res.nominal).items()},
        "effects_added": [a.summary() for a in res.accepted],
        "effects_enabled": list(res.effects),
        "extras": res.extras,
        "parameters_changed": {k: {"base": a, "identified": b}
                               for k, (a, b) in _changed_params(res, res.final).items()},
        "parameter_confidence": res.parameter_confidence,
        "parameters_named": [{"name": c["name"], "change": c["change"], "z": c["z"], "words": c["words"]}
                             for c in res.parameter_confidence if c["moved"] and c["words"]],
        "effects_absent": list(res.absent),
        "holdout_errors": res.holdout_errors(),
        "written_model_holdout_errors": res.written,
        "parameters_written": _written_params(res),
        "steps": res.steps,
        "discovered_terms": [dict(t.as_dict(), formula=t.formula()) for t in res.terms],
        "discovery": res.discovery,
        "pairs": res.pairs,
        "joint": res.joint,
        "log_checks": {"bad_rows": log.bad_rows, "timing_shift_samples": res.timing_shift_samples,
                       "timing_shift_s": res.timing_shift_samples * log.dt_s},
        "candidates": [[r.summary() for r in rnd] for rnd in res.rounds],
        "unexplained": [{k: v for k, v in loc.items() if k != "steps"} | {"text": localise.describe(loc)}
                        for loc in res.localisation],
        "diagnostics_before": slim(res.diag_before),
        "diagnostics_after": slim(res.diag_after),
        "thresholds": {"alpha": ALPHA, "forward_min": FORWARD_MIN, "structure_min": STRUCTURE_MIN,
                       "same_residual_corr": SAME_RESIDUAL_CORR},
        "notes": res.notes,
        "timings_s": res.timings,
    })


def write_report(res: IdentificationResult, out_dir: str | Path, plots: bool = True,
                 model_name: str = "model.toml") -> dict[str, Path]:
    """Write report.md, summary.json, the model file and the plots into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    model_path = write_model_file(out / model_name, res.params, res.effects, res.extras, res.terms, res.absent)
    files["model"] = model_path
    data = summary(res)
    plt = load_pyplot() if plots else None
    plot_note = None
    residual_pngs, effect_pngs, ccf_pngs = [], {}, []
    if plots and plt is None:
        plot_note = f"Plots skipped: matplotlib is not installed ({PLOT_EXTRA})."
    elif not plots:
        plot_note = "Plots skipped on request (--no-plots)."
    else:
        residual_pngs = _plot_residuals(plt, res, out)
        for acc in res.accepted:
            name = _plot_effect_diagnostic(plt, res, acc, out)
            if name:
                effect_pngs[acc.name] = name
        worst = max(res.diag_before["structure_train"], key=lambda k: res.diag_before["structure_train"][k])
        name = _plot_ccf(plt, res.diag_before, worst, out, "before")
        if name:
            ccf_pngs.append(name)
    data["plots"] = {"residuals": residual_pngs, "effects": effect_pngs, "ccf": ccf_pngs, "note": plot_note}
    (out / "summary.json").write_text(json.dumps(data, indent=2))
    files["summary"] = out / "summary.json"
    (out / "report.md").write_text("\n".join(_markdown(res, data, model_path.name)) + "\n")
    files["report"] = out / "report.md"
    return files


def _markdown(res: IdentificationResult, data: dict, model_name: str) -> list[str]:
    log = res.log
    f = res.fitter
    md = [f"# Model identification from {log.source or 'a measurement log'}", ""]
    md += [f"Log: {log.n} rows at {log.dt_s:g} s ({(log.time_s[-1] - log.time_s[0]) / 60:.1f} min); logged outputs "
           f"{', '.join(f.outputs)}. Training part: rows from t = {data['split']['train_start_s']:.0f} s (after the "
           f"burn-in) to t = {log.split_time_s:.0f} s; held-out part: t >= {log.split_time_s:.0f} s "
           f"({data['split']['holdout_rows']} rows), never used to fit.", ""]
    md += ["Noise levels (from the second differences of each output): "
           + ", ".join(f"{o} {_num(s)} {UNITS.get(o, '')}" for o, s in res.sigma.items()) + ".", ""]
    for n in res.notes:
        md.append(f"- {n}")
    md += ["", "## Result", ""]
    if res.accepted:
        for a in res.accepted:
            what = ", ".join(f"{k} = {_num(v)}" for k, v in a.params.items())
            if a.delay_s is not None:
                what = f"delay {a.delay_s:g} s"
            if a.bias is not None:
                what = f"offset {_num(a.bias[0])} at mid-log, drift {_num(a.bias[1])} over the log"
            if a.gain is not None:
                what = f"the reading {_num(a.gain)} times the model's"
            md.append(f"- **{a.name}**: {a.description} ({a.source}); {what}. {a.reason}.")
    else:
        md.append("- No effect of the library was added.")
    joint = res.discovery or {}
    for t in res.terms:
        with_ = joint.get("jointly_with") if joint.get("term", {}).get("name") == t.name else ""
        md.append(f"- **discovered term {t.name}** (not in the library): {t.description}; `{t.formula()}`."
                  + (f" Kept only jointly with {with_}: alone it made the held-out error worse (the two mask each "
                     "other; this log identifies them only together)." if with_ else ""))
    md += ["", f"Effects to enable: `{list(res.effects)}`; model file: `{model_name}` (load with "
           "`hvac_mpc.identification.load_model_file`).", ""]
    if res.extras:
        md.append("Corrections the state model cannot hold (in the model file's [identification] table): "
                  + ", ".join(f"{k} = {_num(v)}" for k, v in res.extras.items()) + ".")
        md.append("")
    md += _steps_md(res)
    md += ["### Held-out error, before (nominal model fitted) and after", ""]
    rows = []
    for o, e in res.holdout_errors().items():
        ratio = e["rms_after"] / e["rms_before"] if e["rms_before"] > 0 else float("nan")
        rows.append([f"{o} [{UNITS.get(o, '')}]", e["rms_before"], e["rms_after"], ratio, e["max_before"],
                     e["max_after"]])
    md += _table(["output", "RMS before", "RMS after", "after/before", "max before", "max after"], rows)
    md.append("")
    if res.localisation:
        md += ["### Not explained by the library", ""]
        for loc in res.localisation:
            md.append(f"- Held-out error {loc['structure_holdout']:.1f}x the noise variance: "
                      f"{localise.describe(loc)}.")
        if not res.accepted and not res.terms:
            md.append("- No candidate effect is claimed for this residual.")
        md.append("")
    plots = data["plots"]
    if plots["note"]:
        md += [plots["note"], ""]
    for name in plots["residuals"]:
        md += [f"![{name}]({name})", ""]
    for eff, name in plots["effects"].items():
        md += [f"Diagnostic that led to {eff}:", "", f"![{name}]({name})", ""]
    md += ["## Procedure", "",
           "1. Fit the nominal model's free parameters on the training rows (free-run output error, each output "
           "scaled by its noise level; scipy least_squares with CasADi forward sensitivities).",
           "2. Residuals: free-run simulation error (levels, cross-correlations, binning) and one-step EKF "
           "innovations (whiteness, likelihood ratios).",
           "3. Score each applicable candidate effect jointly: from its null (or the best point of a small grid) "
           "its own parameters and the model's free parameters take one Gauss-Newton step together (the flow "
           "equation's parameters only for flow-side candidates), evaluated by a free run, so the nominal fit cannot "
           "absorb the effect before it is scored.",
           f"4. Forward selection: the {POLISH} best on the held-out rows are refit fully; a candidate is kept only "
           f"if it lowers the held-out error, removes >= {100 * FORWARD_MIN:.0f} % of the held-out structure of its "
           "primary output, lowers the information criterion on the training rows (BIC form with the residual's "
           f"effective sample size) and its EKF likelihood ratio is significant (alpha = {ALPHA}, Bonferroni over "
           "the round). The best is added; candidates whose held-out corrections correlate with it above "
           f"{SAME_RESIDUAL_CORR} are reported as explaining the same residual. Then term discovery on the supply "
           "temperature if its residual stays structured (a sparse LARS path over physical features, the size "
           "chosen on the held-out rows, the term refit with the whole model), one more forward pass if a term was "
           "added; when the last round kept nothing and structure remains, pairs of its best candidates and of the "
           "discovered terms that lost their refit are screened jointly (one linearised step each) and the best "
           "refit, a pair kept on the same gates if each member also earns its share with the other in (effects "
           "that mask each other, identified only together); when no pair was kept, or the pair kept a discovered "
           "term (chosen on the residual of a model without its partner), and the supply temperature "
           "stays structured, the kept effects and the last round's best candidates are refit all at once without "
           "the discovered terms, eliminated backward (each must earn its share with the others in) and discovery "
           "runs again, that model replacing the forward path's if it removes the same share of the held-out supply "
           "structure the forward path left and lowers the total held-out error (several effects that mask one "
           "another); while a term is in and the supply stays structured, discovery again at the places without a "
           "term (a further term on the same gates: effects outside the library at two places); then a backward "
           "pass that re-tests each kept effect with the others in (dropped if taking it out "
           "costs less than the same share, or if its own change of the held-out readings, the other parameters "
           f"fixed, is below {CONTRIBUTION_MIN:.1f} of the noise variance: below what the procedure calls structure).",
           "5. Whatever structure remains is located instead of being named: the residual is regressed on each "
           "model equation's drive, on every logged signal (a missing input dependence, e.g. on a column the model "
           "does not use) and on their products; the terms that also hold on the held-out rows name the equation "
           "and the signals.", ""]
    md += ["## Nominal fit", ""]
    md += _table(["parameter", "default", "fitted", "source"],
                 [[k, a, b, Parameters.source(k)] for k, (a, b) in _changed_params(res, res.nominal).items()])
    if res.parameter_confidence:
        md += ["", "### Confidence of the refit parameters (final model)", "",
               "Standard error from the Gauss-Newton covariance, inflated by n / n_eff of the autocorrelated residual; "
               f"a parameter is identified when its standard error is at most {IDENTIFIED_REL_SE:.0%} of its value (else "
               "the thesis value is written), moved when it lies more than 2.58 standard errors (99 %) and 5 % from it.", ""]
        md += _table(["parameter", "thesis", "refit", "standard error", "change", "identified", "moved: what it says"],
                     [[c["name"], c["start"], c["value"], c["se"], f"{c['change']:+.1%}", "yes" if c["identified"] else "no",
                       (c["words"] or "calibrated (a stand-in, docs/model.md sec. 1)") if c["moved"] else ""]
                      for c in res.parameter_confidence])
    if res.absent:
        md += ["", f"Effects tested on this log and not supported (written as `absent` in the model file): "
                   f"{', '.join(res.absent)}."]
    md += ["", "## Diagnostics of the nominal model (training rows)", ""]
    md += _diag_md(res.diag_before)
    if plots["ccf"]:
        md += ["", f"![{plots['ccf'][0]}]({plots['ccf'][0]})", ""]
    md += ["", "## Candidates", ""]
    for rnd in res.rounds:
        rows = []
        for r in rnd:
            rows.append([r.name, r.status, r.primary_output or "-", r.train_reduction * 100 if r.fit else None,
                         r.explained_holdout * 100 if r.fit else None, r.explained_primary * 100 if r.fit else None,
                         r.lr, r.p_value, r.reason])
        md += [f"Round {rnd[0].round if rnd else '?'}:", ""]
        md += _table(["candidate", "status", "primary output", "train cost removed %", "held-out structure removed %",
                      "primary removed %", "EKF LR", "p", "reason"], rows)
        md.append("")
    if res.final is not res.nominal:
        md += ["## Diagnostics after", ""]
        md += _diag_md(res.diag_after, short=True)
        md += ["", "Parameters changed from the base file:", ""]
        md += _table(["parameter", "base", "identified"],
                     [[k, a, b] for k, (a, b) in _changed_params(res, res.final).items()])
    md += ["", f"Run time: {res.timings.get('total_s', float('nan')):.1f} s."]
    return md


def _steps_md(res: IdentificationResult) -> list[str]:
    """Log checks, the discovered term, each added effect with the held-out errors it left, and the
    residual tests on the held-out rows before and after."""
    md = ["### Log checks", ""]
    lines = [n for n in res.notes if n.startswith(("bad rows", "log timing"))]
    md += [f"- {n}" for n in lines] or ["- no bad rows found"]
    if not any(n.startswith("bad rows") for n in lines):
        md.append("- bad rows: none found (no NaN, dropout, duplicated or out-of-order timestamp, stuck sensor)")
    md.append("")
    for t in res.terms:
        md += ["### Discovered term", "", f"- In words: {t.description}.", f"- Formula: `{t.formula()}`.",
               "- Coefficients: " + ", ".join(f"{f} {c:+.5g} {u}" for f, c, u in
                                              zip(t.features, t.coefficients, t.as_dict()["units"])) + ".", ""]
    if res.steps:
        md += ["### Step by step (held-out rows)", ""]
        rows = []
        for st_ in res.steps:
            for o, e in st_["holdout"].items():
                rows.append([st_["added"], o, e["rms_before"], e["rms_after"], e["max_before"], e["max_after"]])
        md += _table(["added", "output", "RMS before", "RMS after", "max before", "max after"], rows)
        md.append("")
    md += ["### Residual tests on the held-out rows, before and after", "",
           "Whiteness: Ljung-Box Q of the EKF one-step innovations (25 lags) against chi2 0.99(25); independence: "
           "largest cross-correlation of the free-run residual with a command or the inlet temperature over its "
           "99 % band (lags 0..25, coloured-signal bound) and the joint chi2 test of the worst signal.", ""]
    rows = []
    before, after = res.diag_before.get("holdout_tests", {}), res.diag_after.get("holdout_tests", {})
    for o in before:
        b, a = before[o], after.get(o, before[o])
        wb = max(b["ccf"].items(), key=lambda kv: kv[1]["peak_ratio"]) if b["ccf"] else ("-", {})
        wa = max(a["ccf"].items(), key=lambda kv: kv[1]["peak_ratio"]) if a["ccf"] else ("-", {})
        rows.append([o, b["ljung_box_q"], a["ljung_box_q"], b["threshold"],
                     f"{wb[0]} {wb[1].get('peak_ratio', float('nan')):.2f}",
                     f"{wa[0]} {wa[1].get('peak_ratio', float('nan')):.2f}",
                     wb[1].get("p_value"), wa[1].get("p_value")])
    md += _table(["output", "Q before", "Q after", "chi2 0.99", "worst CCF before (peak/band)",
                  "worst CCF after (peak/band)", "joint p before", "joint p after"], rows)
    md.append("")
    return md


def _diag_md(diag: dict, short: bool = False) -> list[str]:
    md = []
    rows = [[o, w["q"], w["threshold"], w["p_value"], "yes" if w["white"] else "no"]
            for o, w in diag["whiteness"].items()]
    md += ["Whiteness of the EKF one-step innovations (Ljung-Box, 25 lags, 99 %):", ""]
    md += _table(["output", "Q", "chi2 0.99", "p", "white"], rows)
    if short:
        return md
    md += ["", "Strongest cross-correlations of the free-run residual (peak |rho| over its 99 % band, "
           "coloured-signal bound):", ""]
    rows = []
    for o, cs in diag["ccf"].items():
        for c in cs[:4]:
            rows.append([o, c["signal"], c["peak_ratio"], c["peak_lag"], c["p_value"]])
    md += _table(["output", "signal", "peak/band", "lag", "joint p"], rows)
    md += ["", "Residual binned by operating variables (share of residual variance explained by the bin means):", ""]
    rows = []
    for o, bs in diag["binned"].items():
        for b in bs[:3]:
            rows.append([o, b["variable"], b["eta2"], b["p_value"]])
    md += _table(["output", "variable", "eta^2", "p"], rows)
    md += ["", "Step-response asymmetry (mean residual per unit step in the 150 s after a step):", ""]
    rows = []
    for o, ss in diag["steps"].items():
        for s in ss:
            rows.append([o, s["signal"], s["n_up"], s["n_down"], s["mean_up"], s["mean_down"], s["p_value"]])
    md += _table(["output", "input", "up", "down", "mean up", "mean down", "p"], rows)
    ch = diag.get("chiller")
    if ch:
        md += ["", f"Chiller: logged water between {ch['band_low_c']:+.2f} and {ch['band_high_c']:+.2f} C around the "
               f"set point ({'cycling: two-point control, thesis sec. 2.2' if ch['cycling'] else 'no cycling'}); "
               "the logged water temperature is used as a measured disturbance."]
    return md
