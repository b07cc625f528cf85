"""Sweep throughput: the same N short runs serially in this process and on a LocalCluster, side by side.

    python -m hvac_mpc.benchmarks.sweep_scaling [--runs 80] [--workers 2] [--max-duration-s 60]

Both sides start warm (modules imported; the cluster's workers started and importing the
project), run the same chunks alternately (:func:`measure`), and both build their controllers as they go, once per structure per process
(:class:`.sweep_run.ControllerCache`). Throughput is runs per second of wall time from the first
run to the last result; the ratio is cluster / serial. The CPU seconds per run of this process
(serial) and of the workers (cluster) are reported too: on a machine other processes share, the
wall-clock ratio depends on their load, the CPU cost per run does not. Both sides compute the same figures,
which is checked (step-time figures aside). Results written to ``--out`` (JSON).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # the same single-threaded BLAS as the cluster's workers

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from . import sweep  # noqa: E402
from .sweep_run import ControllerCache, differing_kpis  # noqa: E402
from .sweep_spec import expand, make_spec  # noqa: E402

#: Short runs: two scenarios, two plants, both controllers, cut to ``max_duration_s``.
SCALING_SPEC = {"scenarios": ["summer_cooling_steps", "winter_heating_steps"], "plants": ["simulated", "nominal"],
                "controllers": ["mpc", "baseline"], "length": "quick"}


def scaling_runs(n: int, max_duration_s: float):
    """``n`` distinct short runs (seeds 0, 1, ... over the spec's eight combinations)."""
    per_seed = 8
    spec = make_spec({**SCALING_SPEC, "seeds": list(range(-(-n // per_seed))), "max_duration_s": max_duration_s})
    return expand(spec)[:n]


def _warm_worker() -> str:
    """Import what a run needs (the first run on a worker should not pay the imports)."""
    from hvac_mpc.benchmarks import sweep_run  # noqa: F401
    from hvac_mpc.mpc import baseline, mpc_controller  # noqa: F401

    return "ready"


def _cpu_s(client, side: str) -> float:
    """CPU seconds used so far by this process (serial) or summed over the cluster's workers."""
    if side == "serial":
        return time.process_time()
    return float(sum(client.run(time.process_time).values()))


def measure(n: int, workers: int, max_duration_s: float, folder: Path, rounds: int = 4,
            progress: bool = False) -> dict:
    """Serial and cluster throughput on the same runs; both result sets compared.

    The runs go in ``rounds`` chunks, each chunk serially and on the cluster one after the other
    (serial first in even rounds, cluster first in odd ones), so both see the same machine load
    when other processes share the cores; the times are summed over the rounds.
    """
    runs = scaling_runs(n, max_duration_s)
    _warm_worker()
    cache = ControllerCache()
    client = sweep.local_client(workers)
    elapsed = {"serial": 0.0, "cluster": 0.0}
    cpu = {"serial": 0.0, "cluster": 0.0}
    failed = 0
    load = [os.getloadavg()[0]]
    try:
        client.run(_warm_worker)
        size = -(-len(runs) // max(1, rounds))
        for i in range(0, len(runs), size):
            chunk = runs[i:i + size]
            order = ("serial", "cluster") if (i // size) % 2 == 0 else ("cluster", "serial")
            for side in order:
                c0 = _cpu_s(client, side)
                res = sweep.run_sweep(chunk, folder / side, None if side == "serial" else client, progress=progress,
                                      cache=cache)
                cpu[side] += _cpu_s(client, side) - c0
                elapsed[side] += res["elapsed_s"]
                failed += res["failed"]
            load.append(os.getloadavg()[0])
    finally:
        client.close()
        client.cluster.close()
    a = {r["run_id"]: r for r in sweep.read_results(folder / "serial")}
    b = {r["run_id"]: r for r in sweep.read_results(folder / "cluster")}
    mismatched = sorted(k for k in a if k not in b or differing_kpis(a[k], b[k]))
    s_rate, c_rate = len(runs) / elapsed["serial"], len(runs) / elapsed["cluster"]
    return {"runs": len(runs), "workers": workers, "max_duration_s": max_duration_s, "rounds": rounds,
            "serial_s": elapsed["serial"], "cluster_s": elapsed["cluster"],
            "serial_runs_per_s": s_rate, "cluster_runs_per_s": c_rate, "ratio": c_rate / s_rate,
            "serial_cpu_s_per_run": cpu["serial"] / len(runs), "cluster_cpu_s_per_run": cpu["cluster"] / len(runs),
            # what the ratio would be with one free core per worker (not measured: an estimate that
            # leaves out the scheduler's and the nannies' CPU)
            "cpu_bound_ratio_estimate": workers * cpu["serial"] / cpu["cluster"],
            "failed": failed, "results_differ": mismatched, "load_average_1min": load,
            "cpu_count": os.cpu_count(), "platform": f"{platform.system()} {platform.machine()}",
            "python": platform.python_version()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=80, help="number of runs (default 80)")
    p.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (default 2)")
    p.add_argument("--max-duration-s", type=float, default=60.0, help="length of each run, s (default 60)")
    p.add_argument("--rounds", type=int, default=4, help="alternating serial/cluster chunks (default 4)")
    p.add_argument("--out", default="out/sweep_scaling.json", help="result file (JSON)")
    p.add_argument("--progress", action="store_true", help="progress bars on stderr")
    args = p.parse_args(argv)
    if args.runs < 1 or args.workers < 1 or args.rounds < 1:
        print("sweep_scaling: --runs, --workers and --rounds must be >= 1", file=sys.stderr)
        return 2
    folder = Path(tempfile.mkdtemp(prefix="sweep_scaling_"))
    try:
        res = measure(args.runs, args.workers, args.max_duration_s, folder, args.rounds, args.progress)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))
    print(f"{res['runs']} runs of {res['max_duration_s']:.0f} s: serial {res['serial_runs_per_s']:.2f} runs/s "
          f"({res['serial_s']:.1f} s), {res['workers']} workers {res['cluster_runs_per_s']:.2f} runs/s "
          f"({res['cluster_s']:.1f} s), ratio {res['ratio']:.2f}; failed {res['failed']}, "
          f"differing results {len(res['results_differ'])}; CPU s per run serial {res['serial_cpu_s_per_run']:.3f}, "
          f"workers {res['cluster_cpu_s_per_run']:.3f} (ratio with a free core per worker, estimated from CPU "
          f"time: {res['cpu_bound_ratio_estimate']:.2f}); 1-min load average "
          f"{min(res['load_average_1min']):.1f}-{max(res['load_average_1min']):.1f} on {res['cpu_count']} cores")
    return 0 if not res["failed"] and not res["results_differ"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
