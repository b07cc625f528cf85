"""``hvac-mpc sweep``: thousands of closed-loop runs on Dask, one Parquet row per run (docs/sweep.md).

Each run of the sweep spec (:mod:`.sweep_spec`) is one Dask task (:func:`.sweep_run.execute`),
on a ``LocalCluster`` with one single-threaded worker process per core, or on the cluster at
``--scheduler ADDRESS`` (dask-jobqueue, Kubernetes: start the cluster there, pass its address).
Dask schedules, retries (``retries=``) and moves data; a killed worker's tasks are rescheduled.
Only this client writes results, after a task completed: one Parquet part file per batch in
``--out``, so an interrupted sweep resumes where it stopped (run ids hash the inputs, finished
ones are skipped). ``--replay DIR --row N`` recomputes one row and compares its figures.
"""

from __future__ import annotations

import os

# One BLAS thread per process: the sweep's parallelism is its worker processes, and multithreaded
# BLAS on small matrices only contends for the cores (Dask's nannies set the same in workers).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable, Iterable, Sequence  # noqa: E402

import numpy as np  # noqa: E402

from . import report  # noqa: E402
from .bench import ProgressBar  # noqa: E402
from .sweep_run import (INPUT_COLUMNS, KPIS, BAND_KPI, TIMING_KPIS, ControllerCache, differing_kpis, execute,
                        run_from_row)  # noqa: E402
from .sweep_spec import PLANTS, InvalidSweep, RunSpec, SweepSpec, expand, load_spec, make_spec  # noqa: E402

#: Extra naming the optional packages of the sweep.
EXTRA_HINT = 'install the extra: pip install -e ".[sweep]"'
#: KPIs of the summary; each with the direction in which it gets worse.
SUMMARY_KPIS = {"temp_iae_cs": "high", "flow_iae_m3": "high", "energy_wh": "high", BAND_KPI: "low",
                "violations_total": "high", "fallbacks": "high", "step_p99_ms": "high"}
#: KPIs compared as MPC / baseline over paired runs.
RATIO_KPIS = ("temp_iae_cs", "flow_iae_m3", "energy_wh")
#: Dask settings of the LocalCluster's workers.
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}
#: The ``--quick`` sweep: about two minutes on two cores.
QUICK_SPEC = {"scenarios": ["summer_cooling_steps", "winter_heating_steps"], "seeds": [0, 1, 2, 3],
              "plants": ["simulated", "simulated_perturbed", "nominal", "delay_3s", "combo_tc_blower_valve"],
              "length": "quick"}


# ---------------------------------------------------------------------------- optional packages
def _pyarrow():
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise RuntimeError(f"the sweep writes Parquet with pyarrow, which is not installed ({EXTRA_HINT})") from None
    return pa, pq


def _distributed():
    try:
        import distributed
    except ImportError:
        raise RuntimeError(f"the sweep runs on Dask distributed, which is not installed ({EXTRA_HINT})") from None
    return distributed


def local_client(workers: int):
    """A client of a new LocalCluster: ``workers`` processes of one thread each (dashboard on a free port).

    The workers' statistical profiler (a stack sample every 10 ms) is off: it costs CPU the runs need.
    """
    distributed = _distributed()
    import dask

    with dask.config.set(WORKER_CONFIG):
        cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                           dashboard_address=":0")
    return distributed.Client(cluster)


def remote_client(address: str):
    """A client of an existing Dask scheduler (``tcp://host:8786``, a jobqueue or Kubernetes cluster)."""
    return _distributed().Client(address)


# ---------------------------------------------------------------------------- results on disk
def _schema():
    pa, _ = _pyarrow()
    text = {"run_id", "scenario", "length", "plant", "controller", "weights", "stage_durations_s", "model_file",
            "model_hash", "pair_key", "error", "host"}
    cols = ("run_id",) + INPUT_COLUMNS + ("pair_key",) + KPIS + ("error", "elapsed_s", "host")
    return pa.schema([(c, pa.string() if c in text else pa.int64() if c == "seed" else pa.float64()) for c in cols])


class ResultStore:
    """The result folder: Parquet part files, each written whole by the client after its runs completed."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self._parts = len(list(self.folder.glob("part-*.parquet"))) if self.folder.is_dir() else 0

    def write(self, rows: Sequence[dict]) -> Path | None:
        """One new part file with ``rows`` (written to a temporary name, then renamed)."""
        if not rows:
            return None
        pa, pq = _pyarrow()
        self.folder.mkdir(parents=True, exist_ok=True)
        schema = _schema()
        table = pa.Table.from_pylist([{c: r.get(c) for c in schema.names} for r in rows], schema=schema)
        while True:
            path = self.folder / f"part-{self._parts:06d}.parquet"
            self._parts += 1
            if not path.exists():
                break
        tmp = path.with_suffix(".tmp")
        pq.write_table(table, tmp)
        tmp.replace(path)
        return path

    def run_ids(self) -> set[str]:
        """Ids of the runs stored so far (only that column is read)."""
        _, pq = _pyarrow()
        files = sorted(self.folder.glob("part-*.parquet")) if self.folder.is_dir() else []
        return {i for f in files for i in pq.read_table(f, columns=["run_id"]).column("run_id").to_pylist()}


def read_results(path: str | Path) -> list[dict]:
    """Rows of a result folder (its part files) or of one Parquet file, each run id once."""
    _, pq = _pyarrow()
    path = Path(path)
    files = sorted(path.glob("part-*.parquet")) if path.is_dir() else [path]
    seen, out = set(), []
    for f in files:
        for row in pq.read_table(f).to_pylist():
            if row["run_id"] not in seen:
                seen.add(row["run_id"])
                out.append(row)
    return out


# ---------------------------------------------------------------------------- running
def _lost_row(run: RunSpec, exc: BaseException) -> dict:
    """The row of a task Dask gave up on (e.g. its workers kept dying): inputs and the error."""
    from .sweep_run import input_columns

    return {"run_id": run.run_id, **input_columns(run), "pair_key": run.pair_key(), **{k: None for k in KPIS},
            "error": f"{type(exc).__name__}: {exc}", "elapsed_s": None, "host": None}


def run_sweep(runs: Sequence[RunSpec], out: str | Path, client=None, batch_size: int = 50, flush_s: float = 30.0,
              progress: bool = True, on_result: Callable[[dict], None] | None = None, retries: int = 2,
              cache: ControllerCache | None = None) -> dict:
    """Run what is not yet in ``out``; rows written every ``batch_size`` runs or ``flush_s`` seconds.

    ``client``: a Dask client (None runs in this process, in order, with the controllers of
    ``cache``, by default this process's cache). ``on_result(row)`` is called
    for every completed run. Returns counts: planned, skipped (already done), ran, failed, elapsed_s.
    """
    store = ResultStore(out)
    done = store.run_ids()
    todo = [r for r in runs if r.run_id not in done]
    bar = ProgressBar(len(todo), enabled=progress)
    pending: list[dict] = []
    counts = {"planned": len(runs), "skipped": len(runs) - len(todo), "ran": 0, "failed": 0}
    t0 = last_flush = time.perf_counter()
    written: set[str] = set()
    try:
        for row in _results(todo, client, retries, cache):
            if row["run_id"] in written:
                continue
            written.add(row["run_id"])
            pending.append(row)
            counts["ran"] += 1
            counts["failed"] += row["error"] is not None
            bar.advance(1, f"{counts['ran']}/{len(todo)} runs, {counts['failed']} failed")
            if on_result is not None:
                on_result(row)
            if len(pending) >= batch_size or time.perf_counter() - last_flush >= flush_s:
                store.write(pending)
                pending, last_flush = [], time.perf_counter()
    finally:
        store.write(pending)
        bar.close()
    counts["elapsed_s"] = time.perf_counter() - t0
    return counts


def _results(todo: Sequence[RunSpec], client, retries: int, cache: ControllerCache | None) -> Iterable[dict]:
    """Result rows in completion order: Dask tasks (``client.map``/``as_completed``) or in-process."""
    if client is None:
        for r in todo:
            yield execute(r.inputs(), cache)
        return
    distributed = _distributed()
    by_key = {f"sweep-run-{r.run_id}": r for r in todo}
    futures = client.map(execute, [r.inputs() for r in todo], key=list(by_key), retries=retries)
    try:
        for fut, result in distributed.as_completed(futures, with_results=True, raise_errors=False):
            if isinstance(result, BaseException):
                yield _lost_row(by_key[fut.key], result)
            else:
                yield result
            fut.release()
    finally:
        client.cancel(futures)


# ---------------------------------------------------------------------------- summary
def _finite(values: Iterable) -> np.ndarray:
    a = np.array([np.nan if v is None else float(v) for v in values], float)
    return a[np.isfinite(a)]


def distribution(rows: Sequence[dict], kpi: str, worse: str = "high") -> dict:
    """n, median, p5, p95 and the worst value with the run id that made it (finite values only)."""
    vals = [(r[kpi], r["run_id"]) for r in rows if r.get(kpi) is not None and math.isfinite(r[kpi])]
    if not vals:
        return {"n": 0, "median": None, "p5": None, "p95": None, "worst": None, "worst_run_id": None}
    a = np.array([v for v, _ in vals])
    i = int(np.argmax(a) if worse == "high" else np.argmin(a))
    return {"n": int(a.size), "median": float(np.median(a)), "p5": float(np.percentile(a, 5)),
            "p95": float(np.percentile(a, 95)), "worst": float(a[i]), "worst_run_id": vals[i][1]}


def mpc_baseline_ratios(rows: Sequence[dict]) -> dict:
    """MPC / baseline per :data:`RATIO_KPIS` over runs paired by everything but the controller.

    Each MPC run is paired with the baseline run of its ``pair_key``; the distribution's worst is
    the highest ratio, named by the MPC run's id.
    """
    from .metrics import ratio

    base = {r["pair_key"]: r for r in rows if r["controller"] == "baseline" and r["error"] is None}
    out = {}
    for kpi in RATIO_KPIS:
        pairs = []
        for r in rows:
            b = base.get(r["pair_key"])
            if r["controller"] != "mpc" or r["error"] is not None or b is None:
                continue
            q = ratio(r[kpi], b[kpi])
            if q is not None:
                pairs.append({"run_id": r["run_id"], kpi: q})
        out[kpi] = distribution(pairs, kpi, "high")
    return out


def summarise(rows: Sequence[dict]) -> dict:
    """Distributions per (plant, controller) and per controller, the MPC/baseline ratios, failures."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        if r["error"] is None:
            groups.setdefault(f"{r['plant']} / {r['controller']}", []).append(r)
            groups.setdefault(f"all / {r['controller']}", []).append(r)
    failed = [r for r in rows if r["error"] is not None]
    return {
        "runs": len(rows), "failed": len(failed),
        "failures": [{"run_id": r["run_id"], "error": r["error"].splitlines()[0]} for r in failed[:50]],
        "groups": {g: {k: distribution(rs, k, w) for k, w in SUMMARY_KPIS.items()} for g, rs in sorted(groups.items())},
        "mpc_over_baseline": mpc_baseline_ratios(rows),
        "mpc_over_baseline_by_plant": {p: mpc_baseline_ratios([r for r in rows if r["plant"] == p])
                                       for p in sorted({r["plant"] for r in rows})},
    }


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.4g}"


def _table_row(label: str, s: dict) -> str:
    return (f"| {label} | {s['n']} | {_fmt(s['median'])} | {_fmt(s['p5'])} | {_fmt(s['p95'])} | {_fmt(s['worst'])} | "
            f"{s['worst_run_id'] or '-'} |")


def summary_markdown(summary: dict) -> str:
    """The summary as Markdown tables (median [p5, p95], worst and its run)."""
    lines = ["# Sweep summary", "", f"{summary['runs']} runs, {summary['failed']} failed.", ""]
    for kpi in SUMMARY_KPIS:
        lines += [f"## {kpi}", "", "| plant / controller | n | median | p5 | p95 | worst | worst run |",
                  "|---|---|---|---|---|---|---|"]
        for g, d in summary["groups"].items():
            lines.append(_table_row(g, d[kpi]))
        lines.append("")
    lines += ["## MPC / baseline (paired runs; < 1: the MPC is better)", "",
              "| figure | pairs | median | p5 | p95 | worst | worst run |", "|---|---|---|---|---|---|---|"]
    lines += [_table_row(kpi, s) for kpi, s in summary["mpc_over_baseline"].items()]
    lines += ["", "MPC / baseline per plant, temperature IAE:", "",
              "| plant | pairs | median | p5 | p95 | worst | worst run |", "|---|---|---|---|---|---|---|"]
    lines += [_table_row(p, r["temp_iae_cs"]) for p, r in summary["mpc_over_baseline_by_plant"].items()]
    if summary["failures"]:
        lines += ["", "## Failed runs", ""] + [f"- {f['run_id']}: {f['error']}" for f in summary["failures"]]
    return "\n".join(lines) + "\n"


def plot_summary(rows: Sequence[dict], out: Path) -> list[str]:
    """Box plots per plant and controller and the ratio histogram (matplotlib, extra ``plot``)."""
    plt = report.import_pyplot()
    if plt is None:
        return []
    ok = [r for r in rows if r["error"] is None]
    groups = sorted({(r["plant"], r["controller"]) for r in ok})
    files = []
    for kpi in ("temp_iae_cs", "energy_wh", BAND_KPI):
        data = [_finite(r[kpi] for r in ok if (r["plant"], r["controller"]) == g) for g in groups]
        fig, ax = plt.subplots(figsize=(max(6.0, 0.6 * len(groups) + 2), 4.5))
        ax.boxplot(data, showfliers=True)
        ax.set_xticks(range(1, len(groups) + 1), [f"{p}\n{c}" for p, c in groups], rotation=60, fontsize=7)
        ax.set_ylabel(kpi)
        ax.set_title(f"{kpi} per plant and controller")
        fig.tight_layout()
        name = f"box_{kpi}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(name)
    base = {r["pair_key"]: r for r in ok if r["controller"] == "baseline"}
    fig, ax = plt.subplots(figsize=(6, 4))
    for kpi in RATIO_KPIS:
        q = _finite((r[kpi] / base[r["pair_key"]][kpi]) if base[r["pair_key"]][kpi] else None
                    for r in ok if r["controller"] == "mpc" and r["pair_key"] in base)
        if q.size:
            ax.hist(q, bins=30, alpha=0.5, label=kpi)
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_xlabel("MPC / baseline")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "ratios.png", dpi=110)
    plt.close(fig)
    return files + ["ratios.png"]


def write_summary(folder: Path, plots: bool = True, run_ids: set[str] | None = None) -> dict:
    """summary.json, summary.md and plots from the rows in ``folder`` (only ``run_ids`` if given)."""
    rows = [r for r in read_results(folder) if run_ids is None or r["run_id"] in run_ids]
    summary = summarise(rows)
    (folder / "summary.json").write_text(json.dumps(summary, indent=2))
    (folder / "summary.md").write_text(summary_markdown(summary))
    if plots:
        summary["plots"] = plot_summary(rows, folder)
    return summary


# ---------------------------------------------------------------------------- replay
def replay(path: str | Path, row: int | None = None, run_id: str | None = None,
           cache: ControllerCache | None = None) -> tuple[dict, dict, list[str]]:
    """Recompute a stored row (index ``row`` in :func:`read_results` order, or ``run_id``).

    Returns ``(stored, recomputed, differing KPI names)``; step-time KPIs are not compared.
    """
    rows = read_results(path)
    if run_id is not None:
        match = [r for r in rows if r["run_id"] == run_id]
        if not match:
            raise InvalidSweep(f"--run-id: no run {run_id!r} in {path}")
        stored = match[0]
    else:
        if row is None or not 0 <= row < len(rows):
            raise InvalidSweep(f"--row: expected an index in [0, {len(rows) - 1}], got {row}")
        stored = rows[row]
    run = run_from_row(stored)
    if run.run_id != stored["run_id"]:
        raise InvalidSweep(f"row {stored['run_id']}: its inputs hash to {run.run_id}; the row was altered")
    new = execute(run.inputs(), cache if cache is not None else ControllerCache())
    return stored, new, differing_kpis(stored, new)


# ---------------------------------------------------------------------------- CLI
def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--spec", metavar="FILE", help="sweep spec, TOML or JSON (docs/sweep.md); options below "
                                                       "override its fields")
    parser.add_argument("--quick", action="store_true", help="a small sweep that finishes in about two minutes")
    parser.add_argument("--sampling", choices=("grid", "lhs"), help="cross all axes, or a Latin hypercube sample")
    parser.add_argument("--samples", type=int, metavar="N", help="number of Latin hypercube points")
    parser.add_argument("--sample-seed", type=int, metavar="N", help="seed of the Latin hypercube")
    parser.add_argument("--scenario", action="append", metavar="NAME", help="scenario (repeatable)")
    parser.add_argument("--seeds", type=int, metavar="N", help="noise seeds 0..N-1")
    parser.add_argument("--plant", action="append", metavar="NAME",
                        help=f"plant (repeatable): {', '.join(PLANTS)}")
    parser.add_argument("--controller", action="append", choices=("mpc", "baseline"), help="controller (repeatable)")
    parser.add_argument("--inlet-temp-c", action="append", type=float, metavar="C",
                        help="inlet air temperature replacing the scenario's (repeatable)")
    parser.add_argument("--model-file", action="append", metavar="FILE", help="controllers' model file (repeatable)")
    parser.add_argument("--length", choices=("full", "quick"), help="scenario length (default quick)")
    parser.add_argument("--max-duration-s", type=float, metavar="S", help="cut every scenario to this length")
    parser.add_argument("--out", default="out/sweep", metavar="DIR", help="result folder (default out/sweep)")
    parser.add_argument("--scheduler", metavar="ADDRESS", help="address of an existing Dask scheduler")
    parser.add_argument("--workers", type=int, metavar="N", help="LocalCluster worker processes (default: cores)")
    parser.add_argument("--serial", action="store_true", help="run in this process, no Dask")
    parser.add_argument("--batch-size", type=int, default=50, metavar="N", help="runs per Parquet part file")
    parser.add_argument("--no-plots", action="store_true", help="summary without PNG plots")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    parser.add_argument("--dry-run", action="store_true", help="print the number of runs and stop")
    parser.add_argument("--replay", metavar="RESULTS", help="result folder or Parquet file to replay a row of")
    parser.add_argument("--row", type=int, metavar="N", help="with --replay: row index")
    parser.add_argument("--run-id", metavar="ID", help="with --replay: run id")


def spec_from_args(args: argparse.Namespace) -> SweepSpec:
    """The spec file (or the quick or default spec) with the options given on the command line."""
    if args.spec and args.quick:
        raise InvalidSweep("--quick and --spec: choose one (--quick is a spec of its own)")
    data = load_spec(args.spec).model_dump() if args.spec else (dict(QUICK_SPEC) if args.quick else {})
    given = {"sampling": args.sampling, "samples": args.samples, "sample_seed": args.sample_seed,
             "scenarios": args.scenario, "seeds": None if args.seeds is None else list(range(args.seeds)),
             "plants": args.plant, "controllers": args.controller, "inlet_temps_c": args.inlet_temp_c,
             "model_files": args.model_file, "length": args.length, "max_duration_s": args.max_duration_s}
    if args.seeds is not None and args.seeds < 1:
        raise InvalidSweep(f"--seeds: expected an integer >= 1, got {args.seeds}")
    data.update({k: v for k, v in given.items() if v is not None})
    return make_spec(data, "")


def run(args: argparse.Namespace) -> int:
    try:
        if args.replay:
            return _run_replay(args)
        spec = spec_from_args(args)
        runs = expand(spec)
        if args.batch_size < 1:
            raise InvalidSweep(f"--batch-size: expected an integer >= 1, got {args.batch_size}")
        if args.workers is not None and args.workers < 1:
            raise InvalidSweep(f"--workers: expected an integer >= 1, got {args.workers}")
    except (InvalidSweep, RuntimeError) as exc:
        print(f"hvac-mpc sweep: {exc}", file=sys.stderr)
        return 2
    print(f"{len(runs)} runs planned", file=sys.stderr)
    if args.dry_run:
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "spec.json").write_text(spec.model_dump_json(indent=2))
    try:
        counts = _execute(runs, out, args)
    except RuntimeError as exc:
        print(f"hvac-mpc sweep: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"hvac-mpc sweep: interrupted; finished runs are in {out}, the same command resumes", file=sys.stderr)
        return 130
    summary = write_summary(out, plots=not args.no_plots, run_ids={r.run_id for r in runs})
    print(f"{counts['ran']} runs in {counts['elapsed_s']:.1f} s ({counts['skipped']} already done), "
          f"{counts['failed']} failed; {summary['runs']} rows in {out}")
    for kpi, s in summary["mpc_over_baseline"].items():
        print(f"MPC/baseline {kpi}: median {_fmt(s['median'])}, p5 {_fmt(s['p5'])}, p95 {_fmt(s['p95'])}, "
              f"worst {_fmt(s['worst'])} ({s['worst_run_id'] or '-'})")
    print(f"summary: {out / 'summary.md'}")
    return 0


def _execute(runs: list[RunSpec], out: Path, args: argparse.Namespace) -> dict:
    kw = dict(batch_size=args.batch_size, progress=not args.no_progress)
    if args.serial:
        return run_sweep(runs, out, None, **kw)
    if args.scheduler:
        with remote_client(args.scheduler) as client:
            return run_sweep(runs, out, client, **kw)
    with local_client(args.workers or os.cpu_count() or 1) as client:
        try:
            return run_sweep(runs, out, client, **kw)
        finally:
            client.cluster.close()


def _run_replay(args: argparse.Namespace) -> int:
    if (args.row is None) == (args.run_id is None):
        raise InvalidSweep("--replay needs exactly one of --row N or --run-id ID")
    stored, new, diff = replay(args.replay, args.row, args.run_id)
    print(f"run {stored['run_id']}: {stored['scenario']}, seed {stored['seed']}, plant {stored['plant']}, "
          f"controller {stored['controller']}")
    for k in KPIS:
        mark = "  (timing, not compared)" if k in TIMING_KPIS else ("  DIFFERS" if k in diff else "")
        print(f"  {k:32s} stored {_fmt(stored.get(k)):>12s}  replayed {_fmt(new.get(k)):>12s}{mark}")
    if new["error"]:
        print(f"  replay error: {new['error'].splitlines()[0]}")
    print("replay: identical figures" if not diff else f"replay: {len(diff)} figure(s) differ: {', '.join(diff)}")
    return 0 if not diff else 1
