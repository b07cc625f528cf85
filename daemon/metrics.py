"""Prometheus metrics of one daemon (``GET /metrics``; needs the ``server`` extra).

A collector reads the daemon's status at scrape time into a registry of its own (no global
registry: two daemons in one process each have theirs). Names carry their units.
"""

from __future__ import annotations

from typing import Any, Iterator

from prometheus_client.core import CollectorRegistry, CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily

P = "hvac_daemon_"


class DaemonCollector:
    """Tick time, deadline misses, fallbacks, solver status, interlock trips, log state, mode."""

    def __init__(self, daemon: Any):
        self.daemon = daemon

    def collect(self) -> Iterator[Any]:
        st = self.daemon.status()
        c = st["counters"]
        buckets, acc = [], 0
        for le, n in zip([*map(str, st["tick_time_bounds_s"]), "+Inf"], c["tick_time_buckets"]):
            acc += n
            buckets.append((le, acc))
        yield HistogramMetricFamily(P + "tick_seconds", "wall time of one control tick", buckets=buckets,
                                    sum_value=c["tick_time_sum_s"])
        for name, key, doc in (
                ("ticks", "ticks", "samples logged"),
                ("deadline_misses", "deadline_misses", "controller steps past their deadline"),
                ("late_ticks", "late_ticks", "ticks that started late"),
                ("controller_errors", "controller_errors", "controller steps that raised"),
                ("safe_ticks", "safe_ticks", "ticks on the safe command (sensors a controller needs invalid)"),
                ("disconnected_ticks", "disconnected_ticks", "ticks without a backend"),
                ("reconnects", "reconnects", "backend reconnections"),
                ("mode_changes", "mode_changes", "operator mode changes"),
                ("manual_refused", "manual_refused", "manual commands refused")):
            yield CounterMetricFamily(P + name, doc, value=c[key])
        fb = CounterMetricFamily(P + "fallback_ticks", "ticks on a fallback controller", labels=["controller"])
        for name, n in c["fallback_ticks"].items():
            fb.add_metric([name], n)
        yield fb
        solver = CounterMetricFamily(P + "solver_status", "controller steps by solver status", labels=["status"])
        for name, n in c["solver_status"].items():
            solver.add_metric([name], n)
        yield solver
        trips = CounterMetricFamily(P + "interlock_trips", "ticks with the heater forced off, by reason",
                                    labels=["reason"])
        for name, n in st["interlock_trips"].items():
            trips.add_metric([name], n)
        yield trips
        log = st["log"]
        yield GaugeMetricFamily(P + "log_degraded", "1 while log rows are buffered in memory (disk failing)",
                                value=float(log["state"] != "ok"))
        yield GaugeMetricFamily(P + "log_buffered_rows", "rows waiting in memory", value=log["buffered_rows"])
        yield CounterMetricFamily(P + "log_rows_dropped", "rows lost beyond the memory buffer",
                                  value=log["rows_dropped"])
        yield CounterMetricFamily(P + "log_write_errors", "failed log writes", value=log["write_errors"])
        mode = GaugeMetricFamily(P + "operator_mode", "1 for the operator mode in force", labels=["mode"])
        mode.add_metric([st["operator_mode"]], 1.0)
        yield mode
        yield GaugeMetricFamily(P + "heater_estimate_celsius", "estimated heater body temperature",
                                value=st["heater_estimate_c"])
        yield GaugeMetricFamily(P + "connected", "1 while the backend is connected", value=float(st["connected"]))
        residual = GaugeMetricFamily(P + "model_residual", "model prediction residual (RMS, signal units)",
                                     labels=["name"])
        for name, value in self.daemon.model_metrics().items():
            if isinstance(value, (int, float)) and value == value:
                residual.add_metric([name], float(value))
        yield residual


def daemon_registry(daemon: Any) -> CollectorRegistry:
    """A registry with this daemon's collector only."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(DaemonCollector(daemon))
    return reg
