"""Soak run: the daemon on the simulated plant for many plant hours at full speed.

References change every ``reference_every_s`` plant seconds (seeded random, sent through the
HTTP API like the comfort algorithm does). Memory is sampled at the end of every plant hour:
the process's resident set size and, optionally, the bytes traced by ``tracemalloc``. The
check: no growth from the first hour to the last, and a log with one row per sample at
consecutive times. ::

    python -m hvac_mpc.daemon.soak --hours 24 --controller mpc --log soak.csv
    hvac-mpc daemon --soak 24 --soak-controller mpc --soak-log soak.csv
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import time
import tracemalloc
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np

from hvac_mpc.models.measurement_log import read_log

from .config import config_from_mapping
from .server import token_path
from .loop import Daemon

#: Allowed memory growth from the end of the first plant hour to the end of the last.
RSS_GROWTH_LIMIT_MB = 2.0
TRACED_GROWTH_LIMIT_KB = 256.0


def rss_mb() -> float:
    """Resident set size of this process (MB), from /proc (Linux)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def random_reference(rng: np.random.Generator) -> dict[str, float]:
    """A comfort-algorithm-like reference: supply 14-24 C, flow 0.015-0.045 m3/s, half with a split."""
    ref = {"supply_temp_c": round(float(rng.uniform(14.0, 24.0)), 2),
           "volume_flow_m3s": round(float(rng.uniform(0.015, 0.045)), 4)}
    if rng.random() < 0.5:
        shares = rng.dirichlet([4.0, 4.0, 4.0])
        ref.update({k: round(float(ref["volume_flow_m3s"] * s), 5)
                    for k, s in zip(("flow_m_m3s", "flow_f_m3s", "flow_w_m3s"), shares)})
    return ref


def _put(port: int, body: dict, token: str) -> int:
    req = urllib.request.Request(f"http://127.0.0.1:{port}/reference", data=json.dumps(body).encode(),
                                 method="PUT", headers={"Content-Type": "application/json",
                                                        "Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(req, timeout=5) as resp:
            return resp.status
    except urllib.error.HTTPError as exc:
        return exc.code


def run_soak(hours: float, log_path: str | Path, controller: str = "baseline", reference_every_s: float = 300.0,
             seed: int = 1, tracemalloc_on: bool = False, settings: dict | None = None,
             fallback: list | None = None, memory_every_s: float = 3600.0) -> dict[str, Any]:
    """Run the daemon for ``hours`` plant hours at full speed; returns the report (``ok`` says pass).

    Memory is sampled every ``memory_every_s`` plant seconds (an hour by default); the first and
    last samples are compared."""
    log_path = Path(log_path)
    if log_path.exists():
        log_path.unlink()
    n_ticks = int(round(hours * 3600))
    cfg = config_from_mapping({
        "loop": {"speedup": "max", "max_ticks": n_ticks},
        "log": {"path": str(log_path.resolve())},
        "api": {"port": 0},
        "controller": {"name": controller, "settings": settings or {},
                       "fallback": ["baseline"] if fallback is None else fallback},
        "reference": {"supply_temp_c": 20.0, "volume_flow_m3s": 0.03},
    })
    rng = np.random.default_rng(seed)
    memory: list[dict[str, float]] = []
    sent = {"sent": 0, "accepted": 0}
    if tracemalloc_on:
        tracemalloc.start()

    def hook(d: Daemon, sample: dict) -> None:
        k = int(round(sample["time_s"] / d.dt)) + 1  # samples done
        if k > n_ticks:
            return
        if k < n_ticks and k % int(round(reference_every_s / d.dt)) == 0:
            sent["sent"] += 1
            sent["accepted"] += _put(d.api.port, random_reference(rng), token_path(d.cfg).read_text().strip()) == 200
        if k % int(round(memory_every_s / d.dt)) == 0:
            gc.collect()
            memory.append({"hour": k * d.dt / 3600.0, "rss_mb": rss_mb(),
                           "traced_kb": tracemalloc.get_traced_memory()[0] / 1024 if tracemalloc_on else float("nan")})

    t0 = time.perf_counter()
    daemon = Daemon(cfg, tick_hook=hook)
    code = daemon.run()
    wall = time.perf_counter() - t0
    status = daemon.status()
    if tracemalloc_on:
        tracemalloc.stop()
    log = read_log(log_path)
    t = log["time_s"]
    run_rows = int(np.sum(t < n_ticks * cfg.loop.period_s))
    steps = np.diff(t)
    consecutive = bool(len(t) > 0 and t[0] == 0.0 and np.allclose(steps, cfg.loop.period_s))
    # tracking in the last 30 s before each reference change (settled)
    ref_t, ref_v = log["ref_supply_temp_c"], log["ref_volume_flow_m3s"]
    every = int(round(reference_every_s / cfg.loop.period_s))
    idx = np.concatenate([np.arange(k - 30, k) for k in range(every, run_rows, every)]) if run_rows > every \
        else np.arange(0)
    err_t = np.abs(log["supply_temp_c"][idx] - ref_t[idx]) if len(idx) else np.array([np.nan])
    err_v = np.abs(log["volume_flow_m3s"][idx] - ref_v[idx]) if len(idx) else np.array([np.nan])
    first, last = (memory[0], memory[-1]) if memory else ({}, {})
    rss_growth = last.get("rss_mb", np.nan) - first.get("rss_mb", np.nan)
    traced_growth = last.get("traced_kb", np.nan) - first.get("traced_kb", np.nan)
    report = {
        "hours": hours, "controller": controller, "wall_s": wall, "exit_code": code,
        "rows": int(len(t)), "run_rows": run_rows, "expected_rows": n_ticks, "consecutive": consecutive,
        "missed_samples": int(n_ticks - run_rows), "references_sent": sent["sent"],
        "references_accepted": sent["accepted"], "memory": memory,
        "rss_first_hour_mb": first.get("rss_mb"), "rss_last_hour_mb": last.get("rss_mb"),
        "rss_growth_mb": rss_growth, "traced_first_hour_kb": first.get("traced_kb"),
        "traced_last_hour_kb": last.get("traced_kb"), "traced_growth_kb": traced_growth,
        "median_abs_temp_error_c": float(np.nanmedian(err_t)), "median_abs_flow_error_m3s": float(np.nanmedian(err_v)),
        "deadline_misses": status["counters"]["deadline_misses"], "fallback_ticks": status["counters"]["fallback_ticks"],
        "max_step_time_s": status["counters"]["max_step_time_s"], "interlock_trips": status["interlock_trips"],
        "solver_status": status["counters"]["solver_status"],
        "inner_fallback_ticks": status["counters"]["inner_fallback_ticks"],
    }
    mem_ok = len(memory) >= 2 and rss_growth <= RSS_GROWTH_LIMIT_MB and (
        not tracemalloc_on or traced_growth <= TRACED_GROWTH_LIMIT_KB)
    report["memory_ok"] = bool(mem_ok)
    report["memory_every_s"] = memory_every_s
    report["ok"] = bool(code == 0 and consecutive and run_rows == n_ticks and mem_ok
                        and sent["accepted"] == sent["sent"])
    return report


def print_report(r: dict[str, Any]) -> None:
    print(f"soak: {r['hours']} plant h with {r['controller']} in {r['wall_s']:.0f} s wall; exit code {r['exit_code']}")
    print(f"  rows {r['rows']} (run {r['run_rows']} of {r['expected_rows']}, rest the shutdown), "
          f"consecutive times: {r['consecutive']}, missed samples: {r['missed_samples']}")
    print(f"  references sent {r['references_sent']}, accepted {r['references_accepted']}; settled median "
          f"|error| {r['median_abs_temp_error_c']:.3f} C, {r['median_abs_flow_error_m3s'] * 1000:.2f} l/s")
    mem = r["memory"]
    if len(mem) < 2:
        print(f"  memory: {len(mem)} sample(s), too few to compare (one every {r['memory_every_s']:.0f} plant s)")
    else:
        print(f"  RSS {r['rss_first_hour_mb']:.2f} MB and {r['rss_last_hour_mb']:.2f} MB after {mem[0]['hour']:.2f} h "
              f"and {mem[-1]['hour']:.2f} h (growth {r['rss_growth_mb']:+.2f} MB, limit {RSS_GROWTH_LIMIT_MB} MB)")
    if len(mem) >= 2 and np.isfinite(r["traced_first_hour_kb"]):
        print(f"  Python allocations {r['traced_first_hour_kb']:.1f} kB and {r['traced_last_hour_kb']:.1f} kB "
              f"(growth {r['traced_growth_kb']:+.1f} kB, limit {TRACED_GROWTH_LIMIT_KB} kB)")
    print(f"  deadline misses {r['deadline_misses']}, fallback ticks {r['fallback_ticks']}, "
          f"max step {r['max_step_time_s'] * 1000:.1f} ms, interlock trips {r['interlock_trips']}")
    print(f"  controller statuses {r['solver_status']}, its own fallbacks {r['inner_fallback_ticks']}")
    print(f"  RSS every {r['memory_every_s']:.0f} plant s (MB): {[round(m['rss_mb'], 2) for m in r['memory']]}")
    print("  PASS" if r["ok"] else "  FAIL")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=24.0)
    ap.add_argument("--log", default="soak_log.csv")
    ap.add_argument("--controller", default="baseline")
    ap.add_argument("--every-s", type=float, default=300.0)
    ap.add_argument("--tracemalloc", action="store_true")
    ap.add_argument("--json", help="also write the report as JSON")
    args = ap.parse_args(argv)
    r = run_soak(args.hours, args.log, controller=args.controller, reference_every_s=args.every_s,
                 tracemalloc_on=args.tracemalloc)
    print_report(r)
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=2, default=float))
    return 0 if r["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
