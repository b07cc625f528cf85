"""Boxes outside the registry, drawn from a seeded generator: the mismatch suite's scenarios on each.

    python -m hvac_mpc.benchmarks.box_sweep [--seed 0] [--count 12] [--plant-seed 0] [--full] [--only LABEL ...]
                                            [--settings JSON] [--ekf JSON] [--json FILE] [--list]

Issue 11 asks the suite's checks on an independent plant that is not in this repository. This draws boxes of
:class:`hvac_mpc.mismatch.Variant` (the independent equations) over the four named effects and smaller errors
(:data:`RANGES`), writes each as a ``--box`` option of ``hvac-mpc bench --suite mismatch`` (the same
:func:`.mismatch_suite.parse_box` reads it back, so a row repeats with that command), runs the suite's scenarios
(quick by default) with the default MPC and the thesis baseline on each, and prints the matrix of MPC / baseline
thermocouple IAE, the worst cell, the median and the count of cells above :data:`.mismatch_suite.CELL_LIMIT`.

- ``--seed``: the generator's seed (which boxes); ``--plant-seed``: the suite's ``--seed`` (the plant's noise).
- ``--only``: run only these boxes of the draw (e.g. to split a sweep over two processes); ``--list``: print the
  boxes' ``--box`` options and stop.
- ``--settings`` / ``--ekf``: the MPC's settings changed (JSON of :class:`MpcSettings` / :class:`EkfSettings`
  fields), the baseline untouched; to measure a setting on the same boxes before it is a default.
- ``--json``: the matrix and the boxes to this file.

The flow out of reach is the suite's own scenario (``flow_out_of_reach``), run on every box. The closed-loop runs
use the bench's deterministic deadline, so the ratios repeat; one box takes about a minute of quick scenarios on
one core. The seed-0 sweep, its cells above 1.0 traced and what was built on them: docs/robustness.md sec. 2.19.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from hvac_mpc.mismatch.variants import Variant

from . import mismatch_suite, scenarios as scenario_defs

#: The four named effects of issue 11: the dead time (s) and the duct loss (W/K) drawn uniformly within these,
#: the literal cooler fit on with :data:`LITERAL_COOLER_SHARE`. ASSUMPTION: ranges of a box built like the thesis's
#: (a dead time of a duct of 0.5-2 m at 1-2 m/s and a thermocouple mount; a duct of a few W/K).
TRANSPORT_DELAY_S = (1.0, 5.0)
DUCT_LOSS_UA_W_PER_K = (0.0, 8.0)
LITERAL_COOLER_SHARE = 0.5
#: Smaller errors, each drawn uniformly within its range (scales and % of travel).
RANGES: dict[str, tuple[float, float]] = {
    "thermocouple_tau_scale": (0.6, 1.5),
    "blower_gain_scale": (0.85, 1.15),
    "valve_shift_pct": (-10.0, 10.0),
    "heater_power_scale": (0.85, 1.0),
    "chiller_rate_scale": (0.5, 1.0),
}
#: Digits a drawn value is rounded to (so the ``--box`` text gives the same box).
DIGITS = 2
#: Label prefix of a drawn box (``S<seed>-<index>``).
LABEL = "S{seed}-{index}"


def draw_boxes(seed: int, count: int) -> list[tuple[str, Variant]]:
    """``count`` boxes (label, Variant) from the generator seeded ``seed``; the same seed gives the same boxes,
    and a larger count the same first boxes."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    rng = np.random.default_rng(seed)
    boxes = []
    for index in range(count):
        values: dict[str, Any] = {
            "transport_delay_s": round(float(rng.uniform(*TRANSPORT_DELAY_S)), DIGITS),
            "duct_loss_ua_w_per_k": round(float(rng.uniform(*DUCT_LOSS_UA_W_PER_K)), DIGITS),
            "cooler_literal_fit": bool(rng.random() < LITERAL_COOLER_SHARE),
        }
        values.update({name: round(float(rng.uniform(lo, hi)), DIGITS) for name, (lo, hi) in RANGES.items()})
        boxes.append((LABEL.format(seed=seed, index=index), Variant(**values)))
    return boxes


def box_option(label: str, variant: Variant) -> str:
    """The ``--box`` text of a box (the fields that differ from nominal); :func:`.mismatch_suite.parse_box` reads
    it back to the same Variant."""
    items = []
    for name, value in variant.differences().items():
        items.append(f"{name}={str(value).lower() if isinstance(value, bool) else value}")
    return f"{label}:" + ",".join(items)


def mpc_factory_with(settings: Mapping[str, Any] | None = None, ekf: Mapping[str, Any] | None = None):
    """The bench's MPC factory with ``MpcSettings`` fields (``settings``) and ``EkfSettings`` fields (``ekf``)
    replaced (:func:`~hvac_mpc.mpc.settings_file.settings_with`, checked here: a name that is not a field raises
    ValueError naming it and the allowed ones)."""
    from .bench import mpc_factory
    values = dict(settings or {})
    if ekf:
        values["ekf"] = {**values.get("ekf", {}), **ekf}
    return mpc_factory(settings=values)


def run_sweep(boxes: Sequence[tuple[str, Variant]], plant_seed: int = 0, quick: bool = True,
              settings: Mapping[str, Any] | None = None, ekf: Mapping[str, Any] | None = None) -> dict:
    """The suite's scenarios on every box; the suite's results (``variants`` by box label, ``summary``)."""
    from .bench import baseline_factory, run_benchmark

    known = scenario_defs.mismatch_scenarios()
    chosen = [s.quick() if quick else s for s in known.values()]
    factories = {"baseline": baseline_factory(), "mpc": mpc_factory_with(settings, ekf)}
    results, _ = mismatch_suite.run_suite([], chosen, factories, plant_seed, run_benchmark, boxes=dict(boxes))
    return results


def sweep_summary(results: Mapping) -> dict:
    """Worst cell, median and the count of cells above the suite's limit (temperature ratio)."""
    cells = [(box, name, cell["temp_iae_cs"]) for box, row in results["variants"].items()
             for name, cell in row.items() if cell.get("temp_iae_cs") is not None]
    worst = max(cells, key=lambda c: c[2])
    return {"cells": len(cells), "median": float(np.median([c[2] for c in cells])), "worst": worst[2],
            "worst_cell": f"{worst[0]} / {worst[1]}",
            "above_limit": sum(1 for c in cells if c[2] > mismatch_suite.CELL_LIMIT),
            "above_limit_cells": [f"{b} / {n} {r:.3f}" for b, n, r in cells if r > mismatch_suite.CELL_LIMIT]}


def text(results: Mapping, options: Mapping[str, str]) -> str:
    """The matrix (one row per box, the temperature ratio per scenario), the summary and the boxes' options."""
    names = list(next(iter(results["variants"].values())))
    lines = ["box | " + " | ".join(names)]
    for box, row in results["variants"].items():
        lines.append(f"{box} | " + " | ".join(f"{row[n]['temp_iae_cs']:.3f}" for n in names))
    s = sweep_summary(results)
    lines.append(f"cells {s['cells']}: median {s['median']:.3f}, worst {s['worst']:.3f} ({s['worst_cell']}), "
                 f"above {mismatch_suite.CELL_LIMIT}: {s['above_limit']} {s['above_limit_cells']}")
    lines += [f"--box {options[box]}" for box in results["variants"]]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m hvac_mpc.benchmarks.box_sweep", description=__doc__.split("\n")[0])
    p.add_argument("--seed", type=int, default=0, help="the generator's seed (which boxes)")
    p.add_argument("--count", type=int, default=12, help="how many boxes")
    p.add_argument("--plant-seed", type=int, default=0, help="the suite's --seed (the plant's noise)")
    p.add_argument("--full", action="store_true", help="the full-length scenarios (default: quick)")
    p.add_argument("--only", nargs="+", default=None, metavar="LABEL", help="run only these boxes of the draw")
    p.add_argument("--settings", type=json.loads, default=None, help="MpcSettings fields, JSON")
    p.add_argument("--ekf", type=json.loads, default=None, help="EkfSettings fields, JSON")
    p.add_argument("--json", type=Path, default=None, help="write the results to this file")
    p.add_argument("--list", action="store_true", help="print the boxes' --box options and stop")
    args = p.parse_args(argv)
    try:
        boxes = draw_boxes(args.seed, args.count)
    except ValueError as exc:
        print(f"box_sweep: {exc}", file=sys.stderr)
        return 2
    options = {label: box_option(label, v) for label, v in boxes}
    if args.only:
        unknown = sorted(set(args.only) - set(options))
        if unknown:
            print(f"box_sweep: --only: unknown box(es) {unknown}; drawn: {list(options)}", file=sys.stderr)
            return 2
        boxes = [(label, v) for label, v in boxes if label in args.only]
    if args.list:
        print("\n".join(f"--box {options[label]}" for label, _ in boxes))
        return 0
    try:
        results = run_sweep(boxes, args.plant_seed, quick=not args.full, settings=args.settings, ekf=args.ekf)
    except ValueError as exc:
        print(f"box_sweep: {exc}", file=sys.stderr)
        return 2
    print(text(results, options))
    if args.json:
        args.json.write_text(json.dumps({"boxes": options, "summary": sweep_summary(results),
                                         "variants": results["variants"]}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
