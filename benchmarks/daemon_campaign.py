"""Fault campaign: every fault the daemon must survive, tried and checked, with counts.

Each scenario runs the daemon on the simulated plant (in accelerated time) with faults from a
``[[faults]]`` configuration, or attacks it from outside (hostile API input, Modbus server
stopped and restarted, the process killed with SIGKILL or stopped with SIGTERM). Every logged
sample is then checked by :func:`check_log`, independently of the daemon's own safety code:

* every actuator command finite and in range, heater in [0, 240] W;
* heater 0 whenever the logged flow is missing, implausible or below the minimum, the logged
  heater outlet temperature is missing or implausible, or the daemon is not controlling
  (safe, disconnected, shutdown, stopped);
* the shutdown: heater 0, blower at least the safe power, outlets open, valve a at its safe
  position, and a final 'stopped' row;
* sample times consecutive (no lost, repeated or corrupted row).

:func:`run_campaign` returns the counts (scenarios, faults injected by kind, hostile requests,
violations); ``python -m hvac_mpc.benchmarks.daemon_campaign`` prints them.
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from hvac_mpc.models.measurement_log import read_log
from hvac_mpc.contract import Command
from hvac_mpc.contract import StepResult

from hvac_mpc.daemon.ctl import request
from hvac_mpc.daemon.config import DEFAULT_SENSOR_RANGES, DaemonConfig, SafetyConfig, config_from_mapping
from hvac_mpc.daemon.loop import Daemon
from hvac_mpc.daemon.server import token_path

HEATING_REFERENCE = {"supply_temp_c": 32.0, "volume_flow_m3s": 0.02}
SENSOR_SIGNALS = ("volume_flow_m3s", "supply_temp_c", "heater_outlet_temp_c", "hvac_inlet_temp_c")
SENSOR_KINDS = ("nan", "stuck", "out_of_range", "missing")
NOT_CONTROLLING = ("safe", "disconnected", "shutdown", "stopped")


class GreedyHeater:
    """A misbehaving controller for interlock tests: full heater, blower at its minimum and all
    outlets closed, so the real flow falls below the heater's minimum."""

    def __init__(self, params=None, dt_s: float = 1.0):
        self.dt_s = dt_s

    def reset(self) -> None:
        pass

    def step(self, measurement, reference) -> StepResult:
        return StepResult(Command(30.0, 240.0, 100.0, 0.0, 0.0, 0.0),
                          {"step_time_s": 0.0, "iterations": 0, "status": "ok", "fallback": None, "mode": "heating"})


# ---------------------------------------------------------------------------------- checks
def _invalid(value: float, name: str, ranges: dict) -> bool:
    lo, hi = ranges.get(name, DEFAULT_SENSOR_RANGES[name])
    return not (math.isfinite(value) and lo <= value <= hi)


def check_log(path: str | Path, safety: SafetyConfig | None = None, dt_s: float = 1.0,
              expect_stopped: bool = True) -> list[str]:
    """Safety violations found in a daemon log (empty list: none). See the module docstring."""
    s = safety or SafetyConfig()
    log = read_log(path)
    v: list[str] = []
    t = log["time_s"]
    if len(t) == 0:
        return ["log is empty"]
    raw_lines = Path(path).read_text().splitlines()
    if len(raw_lines) - 1 != len(t):
        v.append(f"{len(raw_lines) - 1 - len(t)} corrupted row(s)")
    steps = np.diff(t)
    if len(steps) and not np.allclose(steps, dt_s):
        bad = np.flatnonzero(~np.isclose(steps, dt_s))
        v.append(f"times not consecutive at rows {bad[:5].tolist()} (steps {steps[bad[:5]].tolist()})")
    ranges = s.sensor_ranges
    for i in range(len(t)):
        heater = log["heater_cmd_w"][i]
        cmd = {c: log[c][i] for c in ("blower_power_w", "heater_cmd_w", "valve_a_pct", "valve_m_pct",
                                      "valve_f_pct", "valve_w_pct")}
        if not all(math.isfinite(x) for x in cmd.values()):
            v.append(f"t={t[i]}: non-finite command {cmd}")
            continue
        if not 0.0 <= heater <= 240.0 or not 30.0 <= cmd["blower_power_w"] <= 300.0 or not all(
                0.0 <= cmd[c] <= 100.0 for c in ("valve_a_pct", "valve_m_pct", "valve_f_pct", "valve_w_pct")):
            v.append(f"t={t[i]}: command out of range {cmd}")
        if heater > 0.0:
            flow = log["volume_flow_m3s"][i]
            mode = str(log["mode"][i])
            if _invalid(flow, "volume_flow_m3s", ranges) or flow < s.min_flow_m3s:
                v.append(f"t={t[i]}: heater {heater:.1f} W with flow reading {flow}")
            if _invalid(log["heater_outlet_temp_c"][i], "heater_outlet_temp_c", ranges):
                v.append(f"t={t[i]}: heater {heater:.1f} W with heater outlet reading {log['heater_outlet_temp_c'][i]}")
            elif log["heater_outlet_temp_c"][i] >= s.heater_outlet_max_c:
                v.append(f"t={t[i]}: heater {heater:.1f} W with heater outlet at {log['heater_outlet_temp_c'][i]} C")
            if mode in NOT_CONTROLLING:
                v.append(f"t={t[i]}: heater {heater:.1f} W in mode {mode}")
        if str(log["mode"][i]) in ("shutdown", "stopped"):
            if any(log[c][i] != 100.0 for c in ("valve_m_pct", "valve_f_pct", "valve_w_pct")) or \
                    log["valve_a_pct"][i] != s.safe_valve_a_pct:
                v.append(f"t={t[i]}: valves not in the safe position during shutdown")
            if str(log["mode"][i]) == "shutdown" and log["blower_power_w"][i] < s.safe_blower_w:
                v.append(f"t={t[i]}: blower {log['blower_power_w'][i]} W below the cool-down power during shutdown")
    if expect_stopped and str(log["mode"][-1]) != "stopped":
        v.append(f"last row is {log['mode'][-1]!r}, not 'stopped'")
    return v[:20]


# ---------------------------------------------------------------------------------- results
@dataclass
class Outcome:
    name: str
    category: str
    exit_code: int | None = None
    detected: int = 0
    rows: int = 0
    violations: list[str] = field(default_factory=list)
    injected: dict[str, int] = field(default_factory=dict)
    notes: str = ""

    @property
    def ok(self) -> bool:
        return not self.violations


def _config(workdir: Path, name: str, controller: str, faults: list[dict], ticks: int,
            reference: dict | None = None, extra: dict | None = None) -> DaemonConfig:
    log = workdir / f"{name}.csv"
    if log.exists():
        log.unlink()
    data: dict[str, Any] = {
        "loop": {"speedup": "max", "max_ticks": ticks, "deadline_s": 0.25},
        "log": {"path": str(log), "fsync": False},
        "api": {"enabled": False},
        "controller": {"name": controller, "fallback": ["baseline"]},
        "safety": {"reconnect_initial_s": 2.0, "reconnect_max_s": 8.0},
        "reference": reference or HEATING_REFERENCE,
        "faults": faults,
    }
    for k, val in (extra or {}).items():
        data[k] = {**data.get(k, {}), **val} if isinstance(val, dict) else val
    return config_from_mapping(data)


def _run_inprocess(cfg: DaemonConfig, hook: Callable | None = None) -> tuple[Daemon, int, list[dict]]:
    samples: list[dict] = []

    def keep(d, sample):
        samples.append({k: sample.get(k) for k in ("time_s", "mode", "controller", "sensor_faults", "stale",
                                                   "interlock", "events", "connected", "inner_fallback",
                                                   "supply_temp_c", "volume_flow_m3s", *Command().as_dict())})
        if hook is not None:
            hook(d, sample)

    d = Daemon(cfg, tick_hook=keep)
    code = d.run()
    return d, code, samples


def _link_recovery_violations(status: dict, samples: list[dict], when: str) -> list[str]:
    """A backend outage ending at 100 s: the daemon must reconnect and control again within 20 s."""
    found = []
    if status["counters"]["reconnects"] < 1:
        found.append("never reconnected")
    if not _recovered(samples, 100.0, 20.0):
        found.append(f"did not return to control within 20 s {when}")
    return found


def _recovered(samples: list[dict], after_s: float, within_s: float) -> bool:
    return any(after_s <= s["time_s"] <= after_s + within_s and s["mode"] not in NOT_CONTROLLING
               for s in samples)


def sensor_scenarios(workdir: Path, controller: str = "baseline") -> list[Outcome]:
    out = []
    cases = [(sig, kind, 1e4) for sig in SENSOR_SIGNALS for kind in SENSOR_KINDS]
    cases += [("supply_temp_c", "stale", 0.0), ("volume_flow_m3s", "value", 0.001),
              ("heater_outlet_temp_c", "value", 120.0)]
    for sig, kind, value in cases:
        name = f"sensor_{kind}_{sig}"
        fault = {"target": "sensor", "kind": kind, "signal": sig, "start_s": 40.0, "end_s": 100.0, "value": value}
        cfg = _config(workdir, name, controller, [fault], ticks=170)
        d, code, samples = _run_inprocess(cfg)
        o = Outcome(name, "sensor", code, rows=len(samples), injected=d.status()["injected_faults"])
        expect = {"stale": None, "value": None}.get(kind, kind)
        if kind == "stale":
            o.detected = sum(1 for s in samples if s["stale"])
        elif kind == "value" and sig == "volume_flow_m3s":
            o.detected = sum(1 for s in samples if "flow_low" in (s["interlock"] or []))
        elif kind == "value":
            o.detected = sum(1 for s in samples if "outlet_too_hot" in (s["interlock"] or []))
        else:
            o.detected = sum(1 for s in samples if (s["sensor_faults"] or {}).get(sig) == expect)
        o.violations = check_log(cfg.log.path, cfg.safety)
        if code != 0:
            o.violations.append(f"exit code {code}")
        if o.detected == 0:
            o.violations.append("fault not detected")
        in_fault = [s for s in samples if 40.0 + 31.0 <= s["time_s"] < 100.0]
        if sig in ("volume_flow_m3s", "heater_outlet_temp_c") and any(s["heater_cmd_w"] > 0 for s in in_fault):
            o.violations.append("heater on while an interlock sensor was faulty")
        if not _recovered(samples, 100.0, 60.0):
            o.violations.append("did not return to control within 60 s after the fault")
        out.append(o)
    return out


def controller_scenarios(workdir: Path, controller: str = "mpc") -> list[Outcome]:
    out = []
    for kind, extra in (("fail", {}), ("nan", {}), ("delay", {"delay_s": 0.6}), ("solver", {})):
        name = f"controller_{kind}"
        if kind == "delay":
            # a slow step takes wall time: run at 50x real time so the late step finishes while the
            # daemon goes on (about 30 samples busy), and cool so the shutdown is short
            end = 44.0
            cfg = _config(workdir, name, controller, [{"target": "controller", "kind": kind, "start_s": 40.0,
                                                       "end_s": end, **extra}], ticks=130,
                          reference={"supply_temp_c": 18.0, "volume_flow_m3s": 0.03},
                          extra={"loop": {"speedup": 50.0}})
        else:
            end = 100.0
            cfg = _config(workdir, name, controller, [{"target": "controller", "kind": kind, "start_s": 40.0,
                                                       "end_s": end, **extra}], ticks=170)
        d, code, samples = _run_inprocess(cfg)
        st = d.status()
        o = Outcome(name, "controller", code, rows=len(samples), injected=st["injected_faults"])
        c = st["counters"]
        if kind == "solver":
            inner = [s["inner_fallback"] for s in samples if 40 <= s["time_s"] < end and s["inner_fallback"]]
            o.detected = len(inner)
            o.notes = f"controller's own fallback chain: {sorted(set(inner))}"
        else:
            o.detected = c["deadline_misses"] + c["controller_busy"] + c["controller_errors"] + c["not_finite_commands"]
            o.notes = f"fallback ticks {c['fallback_ticks']}, deadline misses {c['deadline_misses']}"
        o.violations = check_log(cfg.log.path, cfg.safety)
        if code != 0:
            o.violations.append(f"exit code {code}")
        if o.detected == 0:
            o.violations.append("fault not detected")
        if kind != "solver" and not c["fallback_ticks"]:
            o.violations.append("fallback controller never used")
        if not any(s["time_s"] > end + 5 and s["controller"] == controller for s in samples):
            o.violations.append("primary controller did not return")
        out.append(o)
    return out


def backend_scenarios(workdir: Path, controller: str = "baseline") -> list[Outcome]:
    out = []
    name = "backend_disconnect_injected"
    cfg = _config(workdir, name, controller, [{"target": "backend", "kind": "disconnect", "start_s": 40.0,
                                               "end_s": 100.0}], ticks=170)
    d, code, samples = _run_inprocess(cfg)
    st = d.status()
    o = Outcome(name, "backend", code, rows=len(samples), injected=st["injected_faults"])
    o.detected = st["counters"]["disconnected_ticks"]
    o.violations = check_log(cfg.log.path, cfg.safety)
    o.violations += _link_recovery_violations(st, samples, "after the link came back")
    out.append(o)
    out.append(modbus_outage(workdir, controller))
    out.append(greedy_heater(workdir))
    out.append(fatal_error(workdir, controller))
    out.append(repeated_fatal_error(workdir, controller))
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def modbus_outage(workdir: Path, controller: str = "baseline") -> Outcome:
    """Daemon over Modbus TCP to the plant simulator; the server is stopped and restarted."""
    from hvac_mpc.models.plant import SimulatedPlant

    from hvac_mpc.daemon.modbus_sim import PlantModbusServer

    port = free_port()
    server = PlantModbusServer(SimulatedPlant(seed=3), port=port).start()
    events = {"stopped_at": None, "restarted_at": None}

    def hook(d, sample):
        if sample["time_s"] == 60.0:
            server.stop()
            events["stopped_at"] = 60.0
        elif sample["time_s"] == 100.0:
            server.start()
            events["restarted_at"] = 100.0

    cfg = _config(workdir, "modbus_outage", controller, [], ticks=200,
                  extra={"backend": {"kind": "modbus", "modbus": {"port": port, "timeout_s": 0.2}}})
    try:
        d, code, samples = _run_inprocess(cfg, hook)
    finally:
        server.stop()
    st = d.status()
    o = Outcome("modbus_server_stop_restart", "backend", code, rows=len(samples))
    o.injected = {"modbus:server_stopped": 1}
    o.detected = st["counters"]["disconnected_ticks"]
    o.violations = check_log(cfg.log.path, cfg.safety)
    o.violations += _link_recovery_violations(st, samples, "of the server's restart")
    held = [h for h in server.history if 60.0 + 6 < h[0] <= 100.0]
    if any(h[1] > 0 for h in held):
        o.violations.append("plant heater on during the outage after the I/O watchdog time")
    o.notes = f"plant samples under the I/O watchdog {len(held)}, reconnects {st['counters']['reconnects']}"
    return o


def greedy_heater(workdir: Path) -> Outcome:
    """A controller demanding full heat with the outlets closed: the real flow drops below the minimum."""
    cfg = _config(workdir, "interlock_low_flow", "campaign-greedy-heater", [], ticks=120,
                  extra={"controller": {"fallback": []}})
    truth: list[dict] = []

    def watch(d, sample):
        if sample["mode"] == "heating":
            truth.append(d.backend.plant.truth())

    d, code, samples = _run_inprocess(cfg, watch)
    o = Outcome("interlock_real_low_flow", "interlock", code, rows=len(samples))
    o.detected = sum(1 for s in samples if "flow_low" in (s["interlock"] or []))
    o.violations = check_log(cfg.log.path, cfg.safety)
    low = min(t["volume_flow_m3s"] for t in truth)
    hottest = max(t["heater_temp_c"] for t in truth)
    o.notes = f"true flow down to {low:.4f} m3/s, hottest heater body {hottest:.1f} C"
    if o.detected == 0:
        o.violations.append("interlock never cut the heater although the flow was low")
    if low >= cfg.safety.min_flow_m3s:
        o.violations.append("the scenario did not bring the flow below the minimum")
    if hottest >= d.interlock.heater_temp_max_c:
        o.violations.append(f"heater body reached {hottest:.1f} C")
    return o


def repeated_fatal_error(workdir: Path, controller: str = "baseline") -> Outcome:
    """An error on every sample from t = 60 s (the loop itself is broken): the bare cool-down."""
    cfg = _config(workdir, "fatal_repeated", controller, [{"target": "daemon", "kind": "fatal_repeated",
                                                           "start_s": 60.0, "end_s": 1e6}], ticks=0)
    d, code, samples = _run_inprocess(cfg)
    plant = d.backend.plant
    o = Outcome("fatal_error_repeated", "daemon", code, rows=len(samples), injected=d.status()["injected_faults"])
    o.violations = check_log(cfg.log.path, cfg.safety, expect_stopped=False)
    final, truth = plant.command, plant.truth()
    o.notes = (f"bare cool-down {plant.time_s - 60.0:.0f} s; final command heater {final.heater_cmd_w} W, blower "
               f"{final.blower_power_w} W; true heater body {truth['heater_temp_c']:.1f} C")
    o.detected = int(code == 1)
    if code != 1:
        o.violations.append(f"exit code {code}, expected 1")
    if final.heater_cmd_w != 0.0 or any(getattr(final, v) != 100.0 for v in ("valve_m_pct", "valve_f_pct",
                                                                              "valve_w_pct")):
        o.violations.append(f"final command not safe: {final}")
    if truth["heater_temp_c"] > truth["supply_air_temp_c"] + 30.0 or plant.time_s - 60.0 < 30.0:
        o.violations.append("the heater was not cooled before the exit")
    return o


def fatal_error(workdir: Path, controller: str = "baseline") -> Outcome:
    cfg = _config(workdir, "fatal_error", controller, [{"target": "daemon", "kind": "fatal", "start_s": 60.0,
                                                        "end_s": 61.0}], ticks=0)
    d, code, samples = _run_inprocess(cfg)
    o = Outcome("fatal_error", "daemon", code, rows=len(samples), injected=d.status()["injected_faults"])
    o.detected = int(code == 1)
    o.violations = check_log(cfg.log.path, cfg.safety)
    if code != 1:
        o.violations.append(f"exit code {code}, expected 1 after a fatal error")
    if not any(s["mode"] == "shutdown" for s in samples):
        o.violations.append("no shutdown sequence after the fatal error")
    return o


# ---------------------------------------------------------------------------------- API
def _request(port: int, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
             timeout: float = 5.0, token: str | None = None) -> tuple[int, dict | None]:
    auth = {"Authorization": f"Bearer {token}"} if token else {}
    return request(f"http://127.0.0.1:{port}", method, path, body,
                   {"Content-Type": "application/json", **auth, **(headers or {})}, timeout)


def _raw(port: int, data: bytes, timeout: float = 5.0) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(data)
        chunks = []
        try:
            while True:
                c = s.recv(65536)
                if not c:
                    break
                chunks.append(c)
        except (socket.timeout, ConnectionResetError):
            pass
    return b"".join(chunks)


def hostile_requests() -> list[tuple[str, str, str, bytes | None, dict, int, str]]:
    """(name, method, path, body, headers, expected status, field the message must name)."""
    ok = {"supply_temp_c": 20.0, "volume_flow_m3s": 0.03}
    j = lambda o: json.dumps(o).encode()  # noqa: E731
    return [
        ("bad_json", "PUT", "/reference", b"{", {}, 400, "JSON"),
        ("json_array", "PUT", "/reference", b"[]", {}, 400, "object"),
        ("json_string", "PUT", "/reference", b'"hello"', {}, 400, "object"),
        ("json_null", "POST", "/reference", b"null", {}, 400, "object"),
        ("wrong_type_string", "PUT", "/reference", j({**ok, "supply_temp_c": "hot"}), {}, 400, "supply_temp_c"),
        ("wrong_type_bool", "PUT", "/reference", j({**ok, "volume_flow_m3s": True}), {}, 400, "volume_flow_m3s"),
        ("wrong_type_object", "PUT", "/reference", j({**ok, "supply_temp_c": {"a": 1}}), {}, 400, "supply_temp_c"),
        ("wrong_type_list", "PUT", "/reference", j({**ok, "supply_temp_c": [20]}), {}, 400, "supply_temp_c"),
        ("unknown_field", "PUT", "/reference", j({**ok, "heater_cmd_w": 240}), {}, 400, "heater_cmd_w"),
        ("missing_field", "PUT", "/reference", j({"supply_temp_c": 20.0}), {}, 400, "volume_flow_m3s"),
        ("temp_too_high", "PUT", "/reference", j({**ok, "supply_temp_c": 80.0}), {}, 400, "supply_temp_c"),
        ("temp_too_low", "PUT", "/reference", j({**ok, "supply_temp_c": -5.0}), {}, 400, "supply_temp_c"),
        ("flow_too_high", "PUT", "/reference", j({**ok, "volume_flow_m3s": 1.0}), {}, 400, "volume_flow_m3s"),
        ("flow_negative", "PUT", "/reference", j({**ok, "volume_flow_m3s": -0.01}), {}, 400, "volume_flow_m3s"),
        ("nan_literal", "PUT", "/reference", b'{"supply_temp_c": NaN, "volume_flow_m3s": 0.03}', {}, 400, "NaN"),
        ("infinity_number", "PUT", "/reference", b'{"supply_temp_c": 1e999, "volume_flow_m3s": 0.03}', {}, 400,
         "supply_temp_c"),
        ("split_mismatch", "PUT", "/reference", j({**ok, "flow_m_m3s": 0.03, "flow_f_m3s": 0.03, "flow_w_m3s": 0.03}),
         {}, 400, "flow_m_m3s"),
        ("split_partial", "PUT", "/reference", j({**ok, "flow_m_m3s": 0.01}), {}, 400, "flow_m_m3s"),
        ("deep_nesting", "PUT", "/reference", b"[" * 2000 + b"]" * 2000, {}, 400, ""),
        ("integer_10_pow_400", "PUT", "/reference", b'{"supply_temp_c": 1' + b"0" * 400 + b', "volume_flow_m3s": 0.03}',
         {}, 400, "digits"),
        ("float_1e400", "PUT", "/reference", b'{"supply_temp_c": 20.0, "volume_flow_m3s": 1e400}', {}, 400,
         "volume_flow_m3s"),
        ("invalid_utf8", "PUT", "/reference", b'{"supply_temp_c": "\xff\xfe"}', {}, 400, "JSON"),
        ("large_body", "PUT", "/reference", b" " * 5000 + j(ok), {}, 413, "limit"),
        ("wrong_content_type", "PUT", "/reference", j(ok), {"Content-Type": "text/plain"}, 415, "Content-Type"),
        ("no_content_type", "PUT", "/reference", j(ok), {"Content-Type": ""}, 415, "Content-Type"),
        ("form_content_type", "POST", "/reference", j(ok), {"Content-Type": "application/x-www-form-urlencoded"}, 415,
         "Content-Type"),
        ("no_token", "PUT", "/reference", j(ok), {"Authorization": ""}, 401, "token"),
        ("wrong_token", "PUT", "/reference", j(ok), {"Authorization": "Bearer nope"}, 401, "token"),
        ("basic_auth", "PUT", "/reference", j(ok), {"Authorization": "Basic czNjcmV0"}, 401, "token"),
        ("foreign_host", "PUT", "/reference", j(ok), {"Host": "attacker.example:8750"}, 403, "Host"),
        ("foreign_origin", "PUT", "/reference", j(ok), {"Origin": "http://attacker.example"}, 403, "Origin"),
        ("null_origin", "PUT", "/reference", j(ok), {"Origin": "null"}, 403, "Origin"),
        ("cross_site_fetch", "PUT", "/reference", j(ok), {"Sec-Fetch-Site": "cross-site"}, 403, "cross-site"),
        ("mode_unknown", "PUT", "/mode", j({"mode": "turbo"}), {}, 400, "mode"),
        ("mode_no_token", "PUT", "/mode", j({"mode": "manual"}), {"Authorization": ""}, 401, "token"),
        ("manual_outside_manual_mode", "PUT", "/manual", j({"blower_power_w": 150.0}), {}, 409, "manual"),
        ("unknown_path", "GET", "/admin", None, {}, 404, "path"),
        ("path_traversal", "GET", "/../../etc/passwd", None, {}, 404, "path"),
        ("put_on_status", "PUT", "/status", j(ok), {}, 405, ""),
        ("delete_reference", "DELETE", "/reference", None, {}, 405, ""),
        ("huge_url", "GET", "/" + "a" * 5000, None, {}, 414, "path"),
    ]


def api_scenarios(workdir: Path, controller: str = "baseline") -> list[Outcome]:
    """Hostile input against a running daemon (real HTTP), then the token checks."""
    results: list[Outcome] = []
    state: dict[str, Any] = {}

    def attack(d, sample):
        if sample["time_s"] != 20.0:
            return
        port = d.api.port
        token = token_path(d.cfg).read_text().strip()
        before = (_request(port, "GET", "/reference")[1], _request(port, "GET", "/mode")[1]["mode"])
        for name, method, path, body, headers, expect, must in hostile_requests():
            code, payload = _request(port, method, path, body, headers, token=token)
            after = (_request(port, "GET", "/reference")[1], _request(port, "GET", "/mode")[1]["mode"])
            o = Outcome(f"api_{name}", "api", code, detected=int(code == expect))
            if code != expect:
                o.violations.append(f"status {code}, expected {expect}")
            msg = (payload or {}).get("error", "") if isinstance(payload, dict) else ""
            if must and must.lower() not in msg.lower():
                o.violations.append(f"message {msg!r} does not name {must!r}")
            if after != before:
                o.violations.append(f"reference changed to {after}")
            o.notes = msg[:80]
            results.append(o)
        # header- and socket-level abuse
        o = Outcome("api_bad_content_length", "api")
        reply = _raw(port, b"PUT /reference HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: abc\r\n\r\n")
        o.detected = int(b" 400 " in reply.split(b"\r\n", 1)[0])
        o.violations = [] if o.detected else [f"reply {reply[:60]!r}, expected 400"]
        results.append(o)
        o = Outcome("api_huge_body_announced", "api")  # 1 MB announced: refused before reading it
        reply = _raw(port, b"PUT /reference HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                           b"Authorization: Bearer " + token.encode() + b"\r\nContent-Length: 1000000\r\n\r\n")
        o.detected = int(b" 413 " in reply.split(b"\r\n", 1)[0])
        o.violations = [] if o.detected else [f"reply {reply[:60]!r}, expected 413"]
        results.append(o)
        o = Outcome("api_huge_header_line", "api")  # beyond h11's limit for an incomplete request
        reply = _raw(port, b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Pad: " + b"a" * 70000 + b"\r\n\r\n")
        o.detected = int(reply.split(b"\r\n", 1)[0].split(b" ")[1:2] in ([b"400"], [b"431"]))
        o.violations = [] if o.detected else [f"reply {reply[:60]!r}, expected 400 or 431"]
        results.append(o)
        o = Outcome("api_slow_body", "api")  # headers complete, body never: 408 after body_timeout_s
        t_wall = time.monotonic()
        reply = _raw(port, b"PUT /reference HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                           b"Authorization: Bearer " + token.encode() + b"\r\nContent-Length: 50\r\n\r\n{\"supply",
                     timeout=10.0)
        waited = time.monotonic() - t_wall
        o.detected = int(b" 408 " in reply.split(b"\r\n", 1)[0])
        o.notes = f"answered after {waited:.1f} s"
        o.violations = [] if o.detected else [f"reply {reply[:60]!r}, expected 408"]
        results.append(o)
        o = Outcome("api_slow_headers", "api")  # headers never complete: dropped after header_timeout_s
        slow = socket.create_connection(("127.0.0.1", port))
        slow.sendall(b"PUT /reference HTTP/1.1\r\nHost: 127")
        code, _ = _request(port, "GET", "/health", timeout=3.0)
        slow.settimeout(5.0)
        t_wall = time.monotonic()
        try:
            dropped = slow.recv(100) == b""
        except (socket.timeout, ConnectionResetError):
            dropped = False
        o.detected = int(code == 200 and dropped)
        o.notes = f"dropped after {time.monotonic() - t_wall:.1f} s more"
        o.violations = [] if o.detected else [f"/health {code}, slow connection dropped: {dropped}"]
        results.append(o)
        state["slow"] = slow
        good = {"supply_temp_c": 24.5, "volume_flow_m3s": 0.025}
        code, payload = _request(port, "PUT", "/reference", json.dumps(good).encode(), token=token)
        state["good"] = (code, _request(port, "GET", "/reference")[1])

    cfg = _config(workdir, "api_hostile", controller, [], ticks=60, extra={"api": {
        "enabled": True, "port": 0, "header_timeout_s": 1.0, "body_timeout_s": 1.0}})
    d, code, samples = _run_inprocess(cfg, attack)
    state["slow"].close()
    o = Outcome("api_valid_reference_after_attacks", "api", code, rows=len(samples))
    good_code, ref = state["good"]
    o.detected = int(good_code == 200 and ref["supply_temp_c"] == 24.5)
    o.violations = check_log(cfg.log.path, cfg.safety)
    if not o.detected:
        o.violations.append(f"valid reference not accepted ({good_code}, {ref})")
    results.append(o)
    for n in (16, 200):
        results.append(slow_header_flood(workdir, n, controller))
    results += token_scenarios(workdir, controller)
    return results


class SlowHeaderFlood:
    """``n`` connections trickling request headers (one byte every 0.5 s, reconnecting at once when
    dropped) for ``hold_s`` wall seconds, and /health polled every 0.1 s, from two threads."""

    def __init__(self, n: int, hold_s: float):
        import threading

        self.n, self.hold_s = n, hold_s
        self.health_s: list[float] = []
        self.codes: list[int] = []
        self.reconnects = 0
        self.stop = threading.Event()

    def start(self, port: int) -> None:
        import threading

        for fn in (self._trickle, self._poll):
            threading.Thread(target=fn, args=(port,), daemon=True).start()

    def _connect(self, port: int) -> socket.socket | None:
        try:
            s_ = socket.create_connection(("127.0.0.1", port), timeout=2.0)
            s_.sendall(b"GET /status HTTP/1.1\r\n")
            return s_
        except OSError:
            return None

    def _trickle(self, port: int) -> None:
        socks = [self._connect(port) for _ in range(self.n)]
        end = time.monotonic() + self.hold_s
        while time.monotonic() < end:
            for i, s_ in enumerate(socks):
                try:
                    if s_ is None:
                        raise OSError
                    s_.sendall(b"X")
                except OSError:  # dropped by the server: the attacker comes back at once
                    if s_ is not None:
                        s_.close()
                    socks[i] = self._connect(port)
                    self.reconnects += 1
            time.sleep(0.5)
        for s_ in socks:
            if s_ is not None:
                s_.close()
        self.stop.set()

    def _poll(self, port: int) -> None:
        while not self.stop.is_set():
            t = time.monotonic()
            try:
                code = _request(port, "GET", "/health", timeout=2.0)[0]
            except OSError:
                code = 0
            self.health_s.append(time.monotonic() - t)
            self.codes.append(code)
            time.sleep(0.1)

    def judge(self, o: Outcome, late: int, missed: int, dropped: int) -> None:
        """/health within 1 s every time, no late tick, no deadline miss, slow connections dropped."""
        worst = max(self.health_s) if self.health_s else float("inf")
        bad = [c for c in self.codes if c != 200]
        o.notes = (f"/health {len(self.codes)} polls, worst {worst * 1000:.0f} ms; late ticks {late}, deadline "
                   f"misses {missed}; dropped {dropped}, reconnected {self.reconnects}")
        o.detected = int(dropped > 0)
        if worst > 1.0 or bad:
            o.violations.append(f"/health: worst {worst:.2f} s, non-200 answers {bad[:5]}")
        if late or missed:
            o.violations.append(f"loop: {late} late ticks, {missed} deadline misses during the flood")
        if not o.detected:
            o.violations.append("no slow-header connection was dropped")


def slow_header_flood(workdir: Path, n: int, controller: str = "baseline", hold_s: float = 6.0) -> Outcome:
    """:class:`SlowHeaderFlood` against an in-process daemon at 10x real time."""
    flood = SlowHeaderFlood(n, hold_s)
    state: dict[str, Any] = {}

    def hook(d, sample):
        if sample["time_s"] == 10.0:
            state["before"] = (d.counters["late_ticks"], d.counters["deadline_misses"])
            flood.start(d.api.port)
        elif "before" in state and "after" not in state and flood.stop.is_set():
            state["after"] = (d.counters["late_ticks"], d.counters["deadline_misses"])
            state["dropped"] = d.api.stats()["header_timeouts"]
            d.request_stop("flood checked")

    cfg = _config(workdir, f"api_slow_headers_{n}", controller, [], ticks=0,
                  reference={"supply_temp_c": 20.0, "volume_flow_m3s": 0.03},
                  extra={"api": {"enabled": True, "port": 0, "header_timeout_s": 2.0}, "loop": {"speedup": 10.0}})
    _, code, samples = _run_inprocess(cfg, hook)
    o = Outcome(f"api_slow_header_flood_{n}", "api", code, rows=len(samples))
    o.violations = check_log(cfg.log.path, cfg.safety)
    if "after" not in state:
        o.violations.append("flood did not finish within the run")
        return o
    flood.judge(o, state["after"][0] - state["before"][0], state["after"][1] - state["before"][1],
                state["dropped"])
    return o


def slow_header_flood_process(workdir: Path, n: int = 200, hold_s: float = 6.0) -> Outcome:
    """:class:`SlowHeaderFlood` against the daemon process at real time (1 s samples)."""
    cfg = process_config(workdir, "flood_process", speedup=1.0, reference={"supply_temp_c": 20.0,
                                                                          "volume_flow_m3s": 0.03},
                         extra={"api": {"header_timeout_s": 2.0}})
    port_file = workdir / "flood_process.port"
    for f in (workdir / "flood_process.csv", port_file):
        f.unlink(missing_ok=True)
    flood = SlowHeaderFlood(n, hold_s)
    p = start_daemon(cfg)
    o = Outcome(f"api_slow_header_flood_{n}_process_1x", "api")
    try:
        wait_for(port_file.exists, 60, "the API port", p)
        port = int(port_file.read_text())
        wait_for(lambda: (_request(port, "GET", "/sample")[1] or {}).get("time_s", -1) >= 2.0, 30, "3 samples", p)
        before = _request(port, "GET", "/status")[1]["counters"]
        flood.start(port)
        wait_for(flood.stop.is_set, hold_s + 30, "the end of the flood", p)
        status = _request(port, "GET", "/status")[1]
        for _ in range(2):  # the second request skips the cool-down wait
            p.send_signal(signal.SIGTERM)
            time.sleep(0.2)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    o.exit_code = p.returncode
    after = status["counters"]
    flood.judge(o, after["late_ticks"] - before["late_ticks"], after["deadline_misses"] - before["deadline_misses"],
                status["api_requests"]["header_timeouts"])
    o.violations += check_log(workdir / "flood_process.csv", SafetyConfig())
    if p.returncode != 0:
        o.violations.append(f"exit code {p.returncode}: {err.decode()[-300:]}")
    return o


def token_scenarios(workdir: Path, controller: str = "baseline") -> list[Outcome]:
    """The token file (generated, mode 0600, kept across restarts) and its use from loopback."""
    results: list[Outcome] = []
    cfg = _config(workdir, "api_token", controller, [], ticks=20, extra={"api": {"enabled": True, "port": 0}})
    tfile = token_path(cfg)
    tfile.unlink(missing_ok=True)
    seen: dict[str, Any] = {}

    def attack(d, sample):
        if sample["time_s"] != 10.0:
            return
        body = json.dumps({"supply_temp_c": 21.0, "volume_flow_m3s": 0.02}).encode()
        seen["without"] = _request(d.api.port, "PUT", "/reference", body)[0]
        seen["with"] = _request(d.api.port, "PUT", "/reference", body, token=tfile.read_text().strip())[0]

    _run_inprocess(cfg, attack)
    first = tfile.read_text()
    o = Outcome("api_token_file_generated_0600", "api")
    mode = tfile.stat().st_mode & 0o777
    o.detected = int(mode == 0o600 and len(first.strip()) >= 32)
    o.notes = f"mode {mode:o}, {len(first.strip())} characters"
    o.violations = [] if o.detected else [f"token file mode {mode:o} or short token"]
    results.append(o)
    o = Outcome("api_token_required_on_loopback", "api", detected=int(seen.get("without") == 401))
    o.violations = [] if seen.get("without") == 401 and seen.get("with") == 200 else [f"answers {seen}"]
    results.append(o)
    os.chmod(tfile, 0o644)  # someone loosened it: the next start makes it private again, same token
    _run_inprocess(_config(workdir, "api_token", controller, [], ticks=5, extra={"api": {"enabled": True,
                                                                                        "port": 0}}))
    o = Outcome("api_token_kept_and_made_private", "api")
    o.detected = int(tfile.read_text() == first and tfile.stat().st_mode & 0o777 == 0o600)
    o.violations = [] if o.detected else ["token changed or left readable"]
    results.append(o)
    return results


# ---------------------------------------------------------------------------------- processes
def write_toml(path: Path, data: dict) -> None:
    """A small TOML writer for daemon configurations (tables, arrays of tables, scalars, lists)."""
    def val(x):
        if isinstance(x, bool):
            return "true" if x else "false"
        if isinstance(x, str):
            return json.dumps(x)
        if isinstance(x, float) and math.isinf(x):
            return "inf"
        if isinstance(x, (list, tuple)):
            return "[" + ", ".join(val(i) for i in x) + "]"
        return repr(x)

    lines: list[str] = []

    def table(prefix: str, d: dict):
        scalars = {k: x for k, x in d.items() if not isinstance(x, dict) and not (
            isinstance(x, list) and x and isinstance(x[0], dict))}
        if prefix:
            lines.append(f"[{prefix}]")
        lines.extend(f"{k} = {val(x)}" for k, x in scalars.items())
        for k, x in d.items():
            if isinstance(x, dict):
                table(f"{prefix}.{k}" if prefix else k, x)
            elif isinstance(x, list) and x and isinstance(x[0], dict):
                for item in x:
                    lines.append(f"[[{prefix + '.' if prefix else ''}{k}]]")
                    lines.extend(f"{a} = {val(b)}" for a, b in item.items())

    table("", data)
    path.write_text("\n".join(lines) + "\n")


def start_daemon(config_path: Path, extra_args: list[str] | None = None, env: dict | None = None
                 ) -> subprocess.Popen:
    """``python -m hvac_mpc daemon --config FILE`` as a child process."""
    e = dict(os.environ)
    e.setdefault("OMP_NUM_THREADS", "1")
    e.setdefault("OPENBLAS_NUM_THREADS", "1")
    e.update(env or {})
    return subprocess.Popen([sys.executable, "-m", "hvac_mpc", "daemon", "--config", str(config_path),
                             *(extra_args or [])], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=e)


def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str, proc: subprocess.Popen | None = None
             ) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"daemon exited ({proc.returncode}) while waiting for {what}: "
                               f"{proc.stderr.read().decode()[-2000:]}")
        time.sleep(0.05)
    raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")


def _rows(path: Path) -> int:
    try:
        return max(0, len(path.read_bytes().splitlines()) - 1)
    except FileNotFoundError:
        return 0


def process_config(workdir: Path, name: str, controller: str = "baseline", speedup: float = 25.0,
                   reference: dict | None = None, extra: dict | None = None) -> Path:
    data: dict[str, Any] = {
        "loop": {"speedup": speedup},
        "log": {"path": str(workdir / f"{name}.csv")},
        "api": {"port": 0, "port_file": str(workdir / f"{name}.port")},
        "controller": {"name": controller},
        "reference": reference or HEATING_REFERENCE,
    }
    for k, v in (extra or {}).items():
        data[k] = {**data.get(k, {}), **v} if isinstance(v, dict) else v
    path = workdir / f"{name}.toml"
    write_toml(path, data)
    return path


def sigkill_restart(workdir: Path, controller: str = "baseline") -> list[Outcome]:
    """SIGKILL mid-run, a torn last row added on top, restart: the log appends cleanly."""
    cfg = process_config(workdir, "sigkill", controller, speedup=50.0)
    log = workdir / "sigkill.csv"
    for f in (log, workdir / "sigkill.port"):
        if f.exists():
            f.unlink()
    p = start_daemon(cfg)
    try:
        wait_for(lambda: _rows(log) >= 60, 60, "60 logged rows", p)
        p.send_signal(signal.SIGKILL)
        p.wait(10)
    finally:
        if p.poll() is None:
            p.kill()
    rows_before = _rows(log)
    last_before = read_log(log)["time_s"][-1]
    with log.open("a") as fh:  # a crash in the middle of a row
        fh.write(f"{last_before + 1.0},120.0,0.0,10")
    o1 = Outcome("process_sigkill", "process", p.returncode, rows=rows_before, detected=int(p.returncode == -9))
    o1.injected = {"process:sigkill": 1, "log:torn_row": 1}
    p2 = start_daemon(cfg, ["--max-ticks", "40", "--speedup", "max"])
    out, err = p2.communicate(timeout=120)
    o2 = Outcome("process_restart_appends", "process", p2.returncode)
    data = read_log(log)
    o2.rows = len(data["time_s"])
    o2.violations = check_log(log, SafetyConfig())
    if p2.returncode != 0:
        o2.violations.append(f"restart exit code {p2.returncode}: {err.decode()[-500:]}")
    if o2.rows < rows_before + 40:
        o2.violations.append(f"log has {o2.rows} rows after restart, expected at least {rows_before + 40}")
    if data["time_s"][0] != 0.0:
        o2.violations.append("log does not start at its first row any more (overwritten?)")
    o2.detected = int(not o2.violations)
    o2.notes = f"rows before kill {rows_before}, after restart {o2.rows}; the torn row was dropped"
    return [o1, o2]


def sigterm_shutdown(workdir: Path, controller: str = "baseline") -> list[Outcome]:
    """SIGTERM (and SIGINT) while heating: heater off first, blower running until cooled."""
    results = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        name = f"sig_{sig.name.lower()}"
        cfg = process_config(workdir, name, controller, speedup=40.0)
        log = workdir / f"{name}.csv"
        port_file = workdir / f"{name}.port"
        for f in (log, port_file):
            if f.exists():
                f.unlink()
        p = start_daemon(cfg)
        try:
            wait_for(lambda: port_file.exists(), 60, "the API port", p)
            port = int(port_file.read_text())
            def heated() -> bool:
                sample = _request(port, "GET", "/sample")[1] or {}
                return sample.get("time_s", 0) >= 150 and sample.get("heater_cmd_w", 0) > 100

            wait_for(heated, 60, "150 s of heating", p)
            p.send_signal(sig)
            _, err = p.communicate(timeout=120)
        finally:
            if p.poll() is None:
                p.kill()
        data = read_log(log)
        o = Outcome(f"process_{sig.name}", "process", p.returncode, rows=len(data["time_s"]))
        o.injected = {f"process:{sig.name}": 1}
        o.violations = check_log(log, SafetyConfig())
        modes = list(data["mode"])
        if "shutdown" not in modes:
            o.violations.append("no shutdown rows")
        else:
            i = modes.index("shutdown")
            if data["heater_cmd_w"][i - 1] <= 0:
                o.violations.append("heater was not on before the signal")
            cool = modes.count("shutdown")
            o.notes = f"heater on until the signal, then {cool} s of cool-down with the blower running"
            o.detected = int(data["heater_cmd_w"][i] == 0.0 and cool > 10)
        if p.returncode != 0:
            o.violations.append(f"exit code {p.returncode}: {err.decode()[-500:]}")
        results.append(o)
    return results


# ---------------------------------------------------------------------------------- log, config, modes
def disk_full(workdir: Path, controller: str = "baseline", outage_s: float = 60.0) -> Outcome:
    """Every log write fails with ENOSPC for ``outage_s`` daemon seconds: control goes on, /health
    says degraded, the rows are held in memory and written when the disk takes them again."""
    start = 40.0
    state: dict[str, Any] = {"health": {}}

    def hook(d, sample):
        t = sample["time_s"]
        if t in (start - 5, start + outage_s / 2, start + outage_s + 30):
            state["health"][t] = _request(d.api.port, "GET", "/health")[1]

    cfg = _config(workdir, "log_disk_full", controller, [{"target": "log", "kind": "enospc", "start_s": start,
                                                          "end_s": start + outage_s}], ticks=200,
                  extra={"api": {"enabled": True, "port": 0}, "log": {"retry_s": 5.0}})
    d, code, samples = _run_inprocess(cfg, hook)
    o = Outcome("log_disk_full_60s", "log", code, rows=len(samples))
    o.injected = {k: v for k, v in d.injected.items() if k.startswith("log:")}
    o.violations = check_log(cfg.log.path, cfg.safety)
    h = state["health"]
    status = [h.get(t, {}).get("status") for t in sorted(h)]
    if status != ["ok", "degraded", "ok"]:
        o.violations.append(f"/health status before, during, after: {status}")
    controlling = [s for s in samples if start <= s["time_s"] < start + outage_s and s["controller"] == controller]
    if len(controlling) < outage_s - 1:
        o.violations.append(f"controller ran {len(controlling)} of {outage_s:.0f} samples during the outage")
    rows = len(read_log(cfg.log.path)["time_s"])
    if rows != len(samples):
        o.violations.append(f"{rows} rows in the log for {len(samples)} samples")
    o.detected = int(status[1:2] == ["degraded"])
    o.notes = f"{rows} rows of {len(samples)} samples logged, {d.writer.counters['write_errors']} failed writes"
    return o


def _committed(path: Path) -> int:
    """Bytes up to and including the last newline (the committed rows)."""
    with path.open("rb") as fh:
        size = fh.seek(0, os.SEEK_END)
        fh.seek(max(0, size - 65536))
        tail = fh.read()
    return size - len(tail) + tail.rfind(b"\n") + 1


def _prefix_digest(path: Path, n: int) -> str:
    import hashlib

    h = hashlib.sha256()
    with path.open("rb") as fh:
        left = n
        while left:
            block = fh.read(min(left, 1 << 22))
            if not block:
                break
            h.update(block)
            left -= len(block)
    return h.hexdigest()


def big_log(path: Path, size_mb: float) -> int:
    """A valid daemon log of about ``size_mb`` MB (consecutive samples) with a torn last row."""
    from hvac_mpc.models.measurement_log import COLUMNS

    header = ",".join(COLUMNS) + "\n"
    row = ",".join(["{t}", "120.0", "0.0", "100.0", "100.0", "100.0", "100.0", "25.0", "0.03", "20.0"]
                   + [""] * (len(COLUMNS) - 12) + ["control", "baseline", "2026-11-23T10:00:00.000Z"]) + "\n"
    n = int(size_mb * 2**20 / len(row))
    with path.open("w") as fh:
        fh.write(header)
        for start in range(0, n, 10000):
            fh.write("".join(row.format(t=float(k)) for k in range(start, min(n, start + 10000))))
        fh.write(row.format(t=float(n))[:25])  # torn by a crash
        fh.flush()
        os.fsync(fh.fileno())  # on disk, as a daemon's log is
    return n


def tail_repair_kills(workdir: Path, size_mb: float = 20.0, kills: int = 6, seed: int = 0) -> Outcome:
    """SIGKILL at random moments of the daemon's start (tail repair included) on a big log with a
    torn tail, repeated (a new torn row each time): no committed byte may change."""
    rng = np.random.default_rng(seed)
    log = workdir / "big_log.csv"
    big_log(log, size_mb)
    from hvac_mpc.models.measurement_log import repair_tail

    t_wall = time.perf_counter()
    repair_tail(log)  # how long the repair takes on this log (the window a kill could hit)
    repair_ms = (time.perf_counter() - t_wall) * 1000
    with log.open("ab") as fh:
        fh.write(b"123456789.0,120.0,0.0,1")
    cfg = process_config(workdir, "big_log", speedup=math.inf, extra={"api": {"enabled": False}})
    o = Outcome(f"log_sigkill_during_tail_repair_{size_mb:.0f}MB", "log")
    o.injected = {"process:sigkill": 0, "log:torn_row": 0}
    repaired = 0
    for _ in range(kills):
        n = _committed(log)
        digest = _prefix_digest(log, n)
        p = start_daemon(cfg)
        time.sleep(float(rng.uniform(0.3, 2.5)))
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        o.injected["process:sigkill"] += 1
        if log.stat().st_size < n or _prefix_digest(log, n) != digest:
            o.violations.append(f"committed bytes changed (size {log.stat().st_size}, committed {n})")
            break
        repaired += int(_committed(log) == log.stat().st_size)
        with log.open("ab") as fh:  # the next crash's torn row
            fh.write(b"123456789.0,120.0,0.0,1")
        o.injected["log:torn_row"] += 1
    o.rows = _committed(log)
    o.detected = repaired
    o.notes = (f"{kills} kills on a {log.stat().st_size / 2**20:.0f} MB log, tail repaired before {repaired} of "
               f"them; one repair {repair_ms:.1f} ms")
    return o


BAD_CONFIGS = {
    "binary": b"\x00\xff\xfe\x89PNG\r\n",
    "reference_number": b"reference = 5\n",
    "reference_text": b'reference = "abc"\n',
    "fallback_number": b"[controller]\nfallback = [1]\n",
    "unknown_effect": b'[backend.simulated]\neffects = ["warp_drive"]\n',
    "zero_min_flow": b"[safety]\nmin_flow_m3s = 0.0\n",
    "no_interlock_sensor": b"[safety]\ninterlock_sensors = []\n",
    "module_name_controller": b'[controller]\nname = "os:system"\n',
    "huge_integer": b"[loop]\nperiod_s = 1" + b"0" * 400 + b"\n",
    "public_bind_open_reads": b'[api]\nhost = "0.0.0.0"\n',
}
BAD_CONFIG_KEYS = {"binary": "UTF-8", "reference_number": "reference", "reference_text": "reference",
                   "fallback_number": "controller.fallback", "unknown_effect": "backend.simulated.effects",
                   "zero_min_flow": "min_flow_m3s", "no_interlock_sensor": "interlock_sensors",
                   "module_name_controller": "controller.name", "huge_integer": "loop.period_s",
                   "public_bind_open_reads": "api.auth_reads",
                   "directory": "directory"}


def bad_config_files(workdir: Path) -> list[Outcome]:
    """Each bad file through ``hvac-mpc daemon --config``: exit 2, the key named, no traceback, no log."""
    import contextlib
    import io

    import argparse

    from hvac_mpc.daemon import main as daemon_main

    def cli_main(argv: list[str]) -> int:  # what ``hvac-mpc daemon`` runs
        parser = argparse.ArgumentParser()
        daemon_main.configure(parser)
        return daemon_main.run(parser.parse_args(argv[1:]))

    results = []
    for name in [*BAD_CONFIGS, "directory"]:
        d = workdir / f"badcfg_{name}"
        d.mkdir(parents=True, exist_ok=True)
        path = d / "daemon.toml"
        if name == "directory":
            path.mkdir(exist_ok=True)
        else:
            path.write_bytes(BAD_CONFIGS[name])
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            try:
                code = cli_main(["daemon", "--config", str(path)])
            except Exception as exc:  # noqa: BLE001 - an escaped exception is the failure counted
                code, err = -1, io.StringIO(f"Traceback: {type(exc).__name__}: {exc}")
        text = err.getvalue()
        o = Outcome(f"config_{name}", "config", code)
        if code != 2:
            o.violations.append(f"exit code {code}")
        if BAD_CONFIG_KEYS[name] not in text or "Traceback" in text:
            o.violations.append(f"message {text[:120]!r}")
        if (d / "hvac_daemon_log.csv").exists():
            o.violations.append("a log was started")
        o.detected = int(not o.violations)
        o.notes = text.strip().split(": ", 2)[-1][:70]
        results.append(o)
    return results


def mode_switches_over_modbus(workdir: Path) -> Outcome:
    """MPC -> PID -> manual -> MPC through the API on the simulated plant behind the real Modbus
    server (:mod:`.mode_transfer`): the reference held across each switch and changed between them,
    the last time in manual; no actuator faster than its rate limit after a switch, the supply
    temperature within 0.5 C of its value at the switch for the next 10 s; in manual, heater on at
    starved flow refused and logged."""
    from . import mode_transfer

    r = mode_transfer.run(workdir)
    o = Outcome("modes_mpc_pid_manual_mpc_over_modbus", "modes", r["exit_code"], rows=r["rows"])
    o.violations = r["violations"] + check_log(r["log"], r["safety"])
    o.detected = int(r["refusal_answer"][0] == 409)
    o.notes = ("max |dT| 10 s after switch: " + ", ".join(f"{s['to']} {s['max_dT_10s_c']:.2f} C (gap "
                                                          f"{s['gap_c']:+.1f} C)" for s in r["switches"])
               + f"; refused at flow {r['refused_flow_m3s']:.4f} m3/s")
    return o


# ---------------------------------------------------------------------------------- campaign
def run_campaign(workdir: str | Path, include_processes: bool = True, controller: str = "baseline",
                 mpc: str = "mpc", big_log_mb: float = 20.0) -> dict[str, Any]:
    """Run every scenario; returns ``{"outcomes": [...], "counts": {...}}``."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    outcomes: list[Outcome] = []
    outcomes += sensor_scenarios(workdir, controller)
    outcomes += controller_scenarios(workdir, mpc)
    outcomes += backend_scenarios(workdir, controller)
    outcomes += api_scenarios(workdir, controller)
    outcomes.append(disk_full(workdir, controller))
    outcomes += bad_config_files(workdir)
    outcomes.append(mode_switches_over_modbus(workdir))
    if include_processes:
        outcomes += sigkill_restart(workdir, controller)
        outcomes += sigterm_shutdown(workdir, controller)
        outcomes.append(tail_repair_kills(workdir, big_log_mb))
        outcomes.append(slow_header_flood_process(workdir))
    counts: dict[str, Any] = {"scenarios": len(outcomes), "passed": sum(o.ok for o in outcomes),
                              "violations": sum(len(o.violations) for o in outcomes), "by_category": {},
                              "injected_fault_ticks": {}, "wall_s": 0.0}
    for o in outcomes:
        c = counts["by_category"].setdefault(o.category, {"tried": 0, "passed": 0})
        c["tried"] += 1
        c["passed"] += o.ok
        for k, n in o.injected.items():
            counts["injected_fault_ticks"][k] = counts["injected_fault_ticks"].get(k, 0) + n
    counts["wall_s"] = time.perf_counter() - t0
    return {"outcomes": outcomes, "counts": counts}


def format_report(result: dict[str, Any]) -> str:
    c = result["counts"]
    lines = [f"fault campaign: {c['scenarios']} scenarios, {c['passed']} passed, {c['violations']} violations, "
             f"{c['wall_s']:.1f} s"]
    for cat, n in c["by_category"].items():
        lines.append(f"  {cat:<11} tried {n['tried']:>3}  passed {n['passed']:>3}")
    lines.append("  injected (fault-ticks): " + ", ".join(f"{k} {v}" for k, v in sorted(c["injected_fault_ticks"].items())))
    for o in result["outcomes"]:
        flag = "ok  " if o.ok else "FAIL"
        lines.append(f"  {flag} {o.name:<40} exit={o.exit_code!s:<5} detected={o.detected:<4} {o.notes[:70]}"
                     + ("" if o.ok else f"  <- {o.violations[:3]}"))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import argparse
    import logging

    ap = argparse.ArgumentParser(description="run the daemon's fault campaign")
    ap.add_argument("--workdir", default="daemon_campaign")
    ap.add_argument("--no-processes", action="store_true")
    ap.add_argument("--big-log-mb", type=float, default=20.0,
                    help="size of the log killed during its tail repair (e.g. 400)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    result = run_campaign(args.workdir, include_processes=not args.no_processes, big_log_mb=args.big_log_mb)
    print(format_report(result))
    return 0 if result["counts"]["violations"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
