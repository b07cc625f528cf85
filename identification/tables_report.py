"""Report of the thesis-tables loop (:mod:`.thesis_tables`): Markdown, plots, JSON, model file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .model_file import write_model_file
from .report import PLOT_EXTRA, _jsonable, _num, _table, load_pyplot
from .thesis_tables import MIN_IMPROVEMENT, TablesResult


def _plot(plt, res: TablesResult, out: Path) -> list[str]:
    rows = np.arange(1, len(res.rows) + 1)
    meas = np.array([r["measured"] for r in res.rows])
    thesis = np.array([r["thesis"] for r in res.rows])
    refined = np.array([r["refined"] for r in res.rows])
    fig, ax = plt.subplots(figsize=(10, 3.6))
    w = 0.27
    ax.bar(rows - w, meas[:, 0], w, label="measured (table 6)", color="k")
    ax.bar(rows, thesis[:, 0], w, label="thesis model")
    ax.bar(rows + w, refined[:, 0], w, label="refined model (held-out row)")
    ax.set_xlabel("table 6 row")
    ax.set_ylabel("total flow [m3/s]")
    ax.set_xticks(rows)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "table6_total_flow.png", dpi=90)
    plt.close(fig)
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6))
    lim = max(meas[:, 1:].max(), thesis[:, 1:].max(), refined[:, 1:].max()) * 1.05
    for k, (ax, name) in enumerate(zip(axes, ("m", "f", "w"))):
        ax.plot(meas[:, k + 1], thesis[:, k + 1], "o", label="thesis model")
        ax.plot(meas[:, k + 1], refined[:, k + 1], "s", label="refined")
        ax.plot([0, lim], [0, lim], "k--", lw=0.7)
        ax.set_xlabel(f"measured flow {name} [m3/s]")
        ax.set_ylabel("predicted [m3/s]")
        ax.set_xlim(0, lim)
        ax.set_ylim(0, lim)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "table6_split.png", dpi=90)
    plt.close(fig)
    return ["table6_total_flow.png", "table6_split.png"]


def write_tables_report(res: TablesResult, out_dir: str | Path, plots: bool = True) -> dict[str, Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = write_model_file(out / "model.toml", res.params, res.effects,
                             {"source": "thesis tables 3-6", "branch_scale_m_f_w": list(res.branch_scale)})
    pngs, note = [], None
    plt = load_pyplot() if plots else None
    if plots and plt is None:
        note = f"Plots skipped: matplotlib is not installed ({PLOT_EXTRA})."
    elif plots:
        pngs = _plot(plt, res, out)
    data = {"before": res.before, "after": res.after, "accepted": res.accepted, "candidates": res.steps,
            "fan_curve": res.fan, "branch_scale_m_f_w": res.branch_scale, "effects": list(res.effects),
            "diagnostics": res.diagnostics, "rows": res.rows, "notes": res.notes, "plots": pngs}
    (out / "summary.json").write_text(json.dumps(_jsonable(data), indent=2))
    md = ["# Thesis tables 3-6: the valve network against table 6", ""]
    md += ["Training data: tables 3-5 (43 rows, one valve moved, the others closed). Check data: table 6 "
           "(13 valve settings), each row predicted by a model fitted without it (leave-one-row-out; anything "
           "fitted on table 6, including the outlet-area calibration of the measured split, uses the other 12 "
           "rows). Table 6 columns alpha, beta, gamma are valves m, f, w; outlets mm and mf belong to m, wd and ww "
           "to w; outlet flows are velocity x area x 2 (left/right symmetry, thesis sec. 5.3).", ""]
    md += [f"- {n}" for n in res.notes]
    md += ["", "## Table 6 errors, thesis model and refined model (held-out rows)", ""]
    keys = (("total_rms_m3s", "total flow RMS [m3/s]"), ("total_max_m3s", "total flow max [m3/s]"),
            ("total_rms_pct", "total flow RMS [%]"), ("split_rms_m3s", "outlet flows m, f, w RMS [m3/s]"),
            ("split_max_m3s", "outlet flows max [m3/s]"), ("share_rms_pct", "outlet shares RMS [% points]"),
            ("combined_rms_m3s", "all four flows RMS [m3/s]"))
    md += _table(["error", "thesis model", "refined"], [[label, res.before[k], res.after[k]] for k, label in keys])
    md += ["", f"Effects added, in order: {', '.join(res.accepted) or 'none'}. Model file `{model.name}` enables "
           f"`{list(res.effects)}`" + (" with the valve tables rewritten as the branches' own resistances "
                                       f"(branch factors m, f, w = {', '.join(f'{s:.3f}' for s in res.branch_scale)})"
                                       if "branch_scale" in res.accepted else "") + ".", ""]
    md += ["## Diagnostics on the training tables", "", res.diagnostics["text"], "",
           f"For reference, the thesis model's outlet flows against flows from the measured areas A_m: RMS "
           f"{res.diagnostics['thesis_split_vs_measured_areas_rms_m3s']:.4f} m3/s.", ""]
    md += ["## Candidates", "",
           f"Kept if the held-out error (all four flows) falls by at least {100 * MIN_IMPROVEMENT:.0f} %.", ""]
    md += _table(["round", "candidate", "status", "total RMS", "outlet RMS", "all RMS", "improvement %"],
                 [[s["round"], s["candidate"], s["status"], s["total_rms_m3s"], s["split_rms_m3s"],
                   s["combined_rms_m3s"], 100 * s["improvement"]] for s in res.steps])
    md += ["", "branch_scale is confounded with the outlet-area calibration of the measured split (both act per "
           "branch); the velocity data cannot separate a branch's own resistance from its outlets' effective area.",
           ""]
    md += ["## Rows", ""]
    md += _table(["row", "m, f, w [%]", "measured total, m, f, w", "thesis", "refined"],
                 [[r["row"], ", ".join(f"{a:g}" for a in r["angles_pct"]),
                   ", ".join(_num(v, 3) for v in r["measured"]), ", ".join(_num(v, 3) for v in r["thesis"]),
                   ", ".join(_num(v, 3) for v in r["refined"])] for r in res.rows])
    if note:
        md += ["", note]
    for p in pngs:
        md += ["", f"![{p}]({p})"]
    (out / "report.md").write_text("\n".join(md) + "\n")
    return {"report": out / "report.md", "summary": out / "summary.json", "model": model}
