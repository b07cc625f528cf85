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

from .ports import free_port

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
            # the primary returns reset (a cold start): the real loop's budget, half its 1 s period,
            # so the return does not hang on the machine's load (the campaign runs side by side)
            end = 100.0
            cfg = _config(workdir, name, controller, [{"target": "controller", "kind": kind, "start_s": 40.0,
                                                       "end_s": end, **extra}], ticks=170,
                          extra={"loop": {"deadline_s": 0.5}})
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


def slow_header_flood(workdir: Path, n: int, controller: str = "baseline", hold_s: float = 4.0,
                      speedup: float = 4.0) -> Outcome:
    """:class:`SlowHeaderFlood` against an in-process daemon at ``speedup`` times real time (the
    attacker's threads share the daemon's interpreter: a 250 ms tick at 4x is the honest bound
    on a loaded 2-core machine; the process scenario runs at real time)."""
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
                  extra={"api": {"enabled": True, "port": 0, "header_timeout_s": 2.0}, "loop": {"speedup": speedup},
                         "safety": {"cooldown_max_s": 10.0}})
    _, code, samples = _run_inprocess(cfg, hook)
    o = Outcome(f"api_slow_header_flood_{n}", "api", code, rows=len(samples))
    o.violations = check_log(cfg.log.path, cfg.safety)
    if "after" not in state:
        o.violations.append("flood did not finish within the run")
        return o
    flood.judge(o, state["after"][0] - state["before"][0], state["after"][1] - state["before"][1],
                state["dropped"])
    return o


def slow_header_flood_process(workdir: Path, n: int = 200, hold_s: float = 4.0) -> Outcome:
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


def sigterm_shutdown(workdir: Path, controller: str = "baseline",
                     signals: tuple[signal.Signals, ...] = (signal.SIGTERM, signal.SIGINT)) -> list[Outcome]:
    """SIGTERM (and SIGINT) while heating: heater off first, blower running until cooled."""
    results = []
    for sig in signals:
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


def tail_repair_kills(workdir: Path, size_mb: float = 300.0, random_kills: int = 6, seed: int = 0) -> Outcome:
    """SIGKILL during the tail repair of a big log with a torn tail, exactly at each of its steps
    and at random moments, a restart after each (:mod:`hvac_mpc.benchmarks.repair_kills`): no
    committed byte may change."""
    from hvac_mpc.benchmarks.repair_kills import STEPS, kill_during_repair

    rep = kill_during_repair(workdir / "big_log.csv", size_mb, rounds=1, random_kills=random_kills, seed=seed)
    o = Outcome(f"log_sigkill_during_tail_repair_{size_mb:.0f}MB", "log")
    o.injected = {"process:sigkill": sum(rep.step_kills.values()) + rep.random_kills,
                  "log:torn_row": rep.restarts}
    o.violations = list(rep.lost)
    if rep.step_kills != {s: 1 for s in STEPS}:
        o.violations.append(f"kills at the steps {rep.step_kills}, expected one at each of {STEPS}")
    o.detected = sum(rep.step_kills.values()) + rep.random_in_repair
    o.rows = rep.restarts
    o.notes = rep.summary()
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


def _daemon_cli_refuses(name: str, category: str, config: Path, *must_name: str) -> Outcome:
    """``hvac-mpc daemon --config FILE`` on a bad file: exit 2, each of ``must_name`` in the
    one-line message, no traceback, no log started."""
    import argparse
    import contextlib
    import io

    from hvac_mpc.daemon import main as daemon_main

    parser = argparse.ArgumentParser()
    daemon_main.configure(parser)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            code = daemon_main.run(parser.parse_args(["--config", str(config)]))
        except Exception as exc:  # noqa: BLE001 - an escaped exception is the failure counted
            code, err = -1, io.StringIO(f"Traceback: {type(exc).__name__}: {exc}")
    text = err.getvalue()
    o = Outcome(name, category, code)
    if code != 2:
        o.violations.append(f"exit code {code}")
    if not all(m in text for m in must_name) or "Traceback" in text:
        o.violations.append(f"message {text[:200]!r} does not name {must_name!r}")
    if any(p.suffix == ".csv" for p in config.parent.iterdir()):
        o.violations.append("a log was started")
    o.detected = int(not o.violations)
    o.notes = text.strip().replace(f"{config.parent}/", "").split("configuration error: ", 1)[-1]
    return o


def bad_config_files(workdir: Path) -> list[Outcome]:
    """Each bad file through ``hvac-mpc daemon --config``: exit 2, the key named, no traceback, no log."""
    results = []
    for name in [*BAD_CONFIGS, "directory"]:
        d = workdir / f"badcfg_{name}"
        d.mkdir(parents=True, exist_ok=True)
        path = d / "daemon.toml"
        if name == "directory":
            path.mkdir(exist_ok=True)
        else:
            path.write_bytes(BAD_CONFIGS[name])
        results.append(_daemon_cli_refuses(f"config_{name}", "config", path, BAD_CONFIG_KEYS[name]))
    return results


def with_changed(data: dict, path: tuple[str, ...], value: Any) -> dict:
    """A deep copy of nested ``data`` with the key at ``path`` set to ``value`` (deleted for None)."""
    import copy

    out = copy.deepcopy(data)
    d = out
    for k in path[:-1]:
        d = d[k]
    if value is None:
        del d[path[-1]]
    else:
        d[path[-1]] = value
    return out


def _calibration_variants() -> dict[str, tuple[dict | bytes, str]]:
    """Bad calibration files made from the shipped one: (content, the field the message must name)."""
    import tomllib
    from importlib import resources

    from hvac_mpc.daemon.calibration import DEFAULT_FILE

    base = tomllib.loads(resources.files("hvac_mpc.daemon").joinpath(DEFAULT_FILE).read_text())

    def changed(path: tuple[str, ...], value: Any) -> dict:
        return with_changed(base, path, value)

    return {
        "not_monotone": (changed(("actuators", "heater_cmd_w", "raw"), [0.0, 2.0, 1.5, 5.0]), "heater_cmd_w.raw"),
        "outside_device_range": (changed(("actuators", "heater_cmd_w", "raw"), [0.0, 6.0]),
                                 "outside the device's range"),
        "range_not_covered": (changed(("actuators", "blower_power_w", "eng"), [50.0, 300.0]),
                              "blower_power_w.eng [50.0, 300.0] does not cover"),
        "actuator_missing": (changed(("actuators", "valve_f_pct"), None), "missing actuator(s) ['valve_f_pct']"),
        "unknown_actuator": (changed(("actuators", "fan_pct"), {"signal": "servo_duty", "open": 0.1, "closed": 0.05}),
                             "unknown actuator(s) ['fan_pct']"),
        "not_toml": (b"[actuators\n", "not valid TOML"),
    }


def bad_calibration_files(workdir: Path) -> list[Outcome]:
    """A daemon set to raw device signals with a bad calibration file: refused at start like a bad
    configuration (exit 2, the calibration field named, no traceback, no log)."""
    results = []
    for name, (content, field_) in _calibration_variants().items():
        d = workdir / f"badcal_{name}"
        d.mkdir(parents=True, exist_ok=True)
        for f in d.glob("*.csv"):
            f.unlink()
        cal = d / "cal.toml"
        if isinstance(content, bytes):
            cal.write_bytes(content)
        else:
            write_toml(cal, content)
        path = d / "daemon.toml"
        write_toml(path, {"backend": {"kind": "modbus", "modbus": {"signals": "raw"}}, "calibration": {"file": "cal.toml"}})
        results.append(_daemon_cli_refuses(f"calibration_{name}", "calibration", path, "calibration.file: ",
                                           field_))
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


# ---------------------------------------------------------------------------------- rotation
def log_rotation(workdir: Path, controller: str = "baseline", rotate_bytes: int = 20000) -> Outcome:
    """Rotation by size during a run: every sample in exactly one segment or the active file, in
    order, and the index lists each segment with its first and last time and its rows."""
    name = "log_rotation"
    for f in workdir.glob(f"{name}.*"):
        f.unlink()
    cfg = _config(workdir, name, controller, [], ticks=300, extra={"log": {"rotate_bytes": rotate_bytes}})
    d, code, samples = _run_inprocess(cfg)
    o = Outcome("log_rotation_by_size", "log", code, rows=len(samples))
    index = d.writer.segments()
    times: list[float] = []
    for seg in index:
        path = workdir / seg["segment"]
        t = list(read_log(path)["time_s"]) if path.exists() else []
        if not t or int(seg["rows"]) != len(t) or float(seg["first_time_s"]) != t[0] or \
                float(seg["last_time_s"]) != t[-1]:
            o.violations.append(f"index line {seg} does not match the segment ({len(t)} rows)")
        o.violations += check_log(path, cfg.safety, expect_stopped=False)
        times += t
    o.violations += check_log(cfg.log.path, cfg.safety)
    times += list(read_log(cfg.log.path)["time_s"])
    if times != [float(k) for k in range(len(samples))]:
        o.violations.append(f"{len(times)} rows across the segments for {len(samples)} samples, or out of order")
    o.detected = len(index)
    if len(index) < 3:
        o.violations.append(f"only {len(index)} rotations")
    o.notes = f"{len(samples)} samples in {len(index)} segments + the active file, index complete"
    return o


# ---------------------------------------------------------------------------------- watchdogs
class NotifySocket:
    """systemd's side of ``$NOTIFY_SOCKET``: a bound datagram socket collecting (monotonic time,
    message) pairs. ``path`` is a file path or an abstract ``@name``."""

    def __init__(self, path: str):
        import threading

        from hvac_mpc.daemon.watchdog import socket_address

        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(socket_address(path))
        self.sock.settimeout(0.05)
        self.messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._collect, daemon=True)
        self._thread.start()

    def _collect(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except socket.timeout:
                continue
            for line in data.decode().splitlines():
                self.messages.append((time.monotonic(), line))

    def times(self, message: str) -> list[float]:
        return [t for t, m in self.messages if m == message]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


class HangingBackend:
    """The simulated plant as a backend whose write blocks while ``hang`` is set (a fieldbus call
    without a timeout): the loop itself hangs."""

    def __init__(self):
        import threading

        from hvac_mpc.models.plant import SimulatedPlant

        self.plant = SimulatedPlant(seed=3, initial_command=Command(blower_power_w=120.0, valve_a_pct=100.0))
        self.hang = threading.Event()
        self.release = threading.Event()

    def connect(self):
        pass

    def read(self):
        return self.plant.read()

    def write(self, command):
        if self.hang.is_set():
            self.release.wait(30.0)
        self.plant.apply(command)
        self.plant.advance()

    def close(self):
        pass


def systemd_watchdog(workdir: Path, stall_s: float = 0.5, hang_s: float = 2.0) -> Outcome:
    """The daemon under a systemd stand-in (``$NOTIFY_SOCKET``, pings every 0.1 s, 50 ms ticks):
    READY once, WATCHDOG pings while healthy, none while the loop hangs in a fieldbus write, pings
    again once it runs, STOPPING at shutdown."""
    import threading

    path = f"@hvac-mpc-campaign-{os.getpid()}-{time.monotonic_ns()}"
    systemd = NotifySocket(path)
    backend = HangingBackend()
    cfg = config_from_mapping({
        "loop": {"period_s": 1.0, "speedup": 20.0},
        "log": {"path": str(workdir / "systemd_watchdog.csv"), "fsync": False},
        "api": {"enabled": False},
        "controller": {"name": "baseline", "fallback": []},
        "reference": {"supply_temp_c": 18.0, "volume_flow_m3s": 0.03},
        "safety": {"cooldown_min_s": 1.0, "cooldown_max_s": 3.0},
        "systemd": {"stall_s": stall_s, "ping_interval_s": 0.1},
    }, base_dir=workdir)
    (workdir / "systemd_watchdog.csv").unlink(missing_ok=True)
    daemon = Daemon(cfg, backend=backend)
    thread = threading.Thread(target=daemon.run, daemon=True)
    old = os.environ.get("NOTIFY_SOCKET")
    os.environ["NOTIFY_SOCKET"] = path  # read once, when the loop starts its watchdog thread
    try:
        thread.start()
        wait_for(lambda: systemd.times("READY=1"), 30, "READY=1")
    finally:
        if old is None:
            os.environ.pop("NOTIFY_SOCKET", None)
        else:
            os.environ["NOTIFY_SOCKET"] = old
    try:
        time.sleep(1.0)
        backend.hang.set()
        t_hang = time.monotonic()
        time.sleep(hang_s)
        ticks_hung = daemon.tick
        t_release = time.monotonic()
        backend.release.set()
        backend.hang.clear()
        time.sleep(1.0)
        ticks_after = daemon.tick
    finally:
        backend.release.set()
        daemon.request_stop("campaign")
        daemon.request_stop("campaign")
        thread.join(30.0)
        time.sleep(0.1)
        systemd.close()
    pings = systemd.times("WATCHDOG=1")
    o = Outcome("systemd_watchdog_loop_hang", "watchdog", daemon.exit_code, rows=daemon.tick)
    last = max((t for t in pings if t < t_release), default=float("nan"))
    resumed = min((t for t in pings if t > t_release), default=float("inf"))
    healthy = [t for t in pings if t < t_hang]
    # the last tick ends within one 50 ms tick of t_hang; a margin of 0.5 s for a loaded machine
    late = [t for t in pings if t_hang + stall_s + 0.5 <= t <= t_release]
    o.notes = (f"{len(healthy)} pings in 1 s healthy; last ping {last - t_hang:.2f} s after the hang "
               f"(stall limit {stall_s} s), none for the rest of the {hang_s:.0f} s hang; resumed "
               f"{resumed - t_release:.2f} s after it")
    o.detected = int(not late and resumed < math.inf)
    if late:
        o.violations.append(f"{len(late)} pings while the loop hung")
    if len(healthy) < 5:
        o.violations.append(f"only {len(healthy)} pings in the healthy second")
    if not ticks_after > ticks_hung or resumed == math.inf:
        o.violations.append("the loop or the pings did not resume")
    if len(systemd.times("READY=1")) != 1 or len(systemd.times("STOPPING=1")) != 1:
        o.violations.append(f"READY/STOPPING not once each: {[m for _, m in systemd.messages if m != 'WATCHDOG=1']}")
    if thread.is_alive() or daemon.exit_code != 0:
        o.violations.append(f"daemon did not stop cleanly (exit {daemon.exit_code})")
    return o


def heartbeat_trip_violations(server, cmd: Command) -> list[str]:
    """The device's command ``cmd`` after its heartbeat trip against the command it held when it
    tripped (``server.heartbeat_trip_held``): heater off, the blower at least that command's and the
    cool-down's, valve a and the outlets open; and no write reached the device after the trip. The
    held command is the daemon's last write, which can be later than any the test read before the
    kill: a write the daemon sent just before SIGKILL is read by the server after it."""
    writes, held = server.heartbeat_trip_held[-1]
    out = []
    if server.writes != writes:
        out.append(f"{server.writes - writes} writes reached the device after the trip")
    valves = (cmd.valve_a_pct, cmd.valve_m_pct, cmd.valve_f_pct, cmd.valve_w_pct)
    if (cmd.heater_cmd_w != 0.0 or cmd.blower_power_w < max(held.blower_power_w, server.cooldown_blower_w) - 1e-9
            or any(v != 100.0 for v in valves)):
        out.append(f"device command after the trip {cmd} (held at the trip: {held})")
    return out


def device_heartbeat_after_sigkill(workdir: Path, timeout_s: float = 0.5) -> Outcome:
    """The daemon process heating over Modbus TCP, then SIGKILL: the simulated device's heartbeat
    watchdog switches the heater off within its timeout and keeps the blower running."""
    from hvac_mpc.daemon.modbus_sim import PlantModbusServer
    from hvac_mpc.models.plant import SimulatedPlant

    mport = free_port()
    server = PlantModbusServer(SimulatedPlant(seed=5), port=mport, heartbeat_timeout_s=timeout_s).start()
    cfg = process_config(workdir, "heartbeat_kill", "baseline", speedup=20.0,
                         reference={"supply_temp_c": 30.0, "volume_flow_m3s": 0.02},
                         extra={"backend": {"kind": "modbus", "modbus": {"port": mport, "timeout_s": 0.2}},
                                "api": {"enabled": False}})
    (workdir / "heartbeat_kill.csv").unlink(missing_ok=True)
    o = Outcome("device_heartbeat_after_sigkill", "watchdog")
    o.injected = {"process:sigkill": 1}
    proc = start_daemon(cfg)
    try:
        wait_for(lambda: server.command.heater_cmd_w > 100.0, 90, "the heater on through Modbus", proc)
        blower_before = server.command.blower_power_w
        tripped_before = server.heartbeat_tripped
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        wait_for(lambda: server.heartbeat_tripped, 10, "the heartbeat watchdog")
        off_s = server.heartbeat_trips[-1] - t_kill
        cmd = server.command
        trip_violations = heartbeat_trip_violations(server, cmd)
        time.sleep(0.3)
        status = server.input_registers()[10]
        held = server.command.heater_cmd_w
        trip_violations += [v for v in heartbeat_trip_violations(server, server.command) if v not in trip_violations]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        server.stop()
    o.exit_code = proc.returncode
    o.detected = int(cmd.heater_cmd_w == 0.0)
    o.notes = (f"heater off {off_s:.2f} s after SIGKILL (heartbeat timeout {timeout_s} s); blower "
               f"{blower_before:.0f} (read before the kill) / {server.heartbeat_trip_held[-1][1].blower_power_w:.0f}"
               f" (held at the trip) -> {cmd.blower_power_w:.0f} W, valve a {cmd.valve_a_pct:.0f} %")
    if tripped_before:
        o.violations.append("heartbeat watchdog tripped while the daemon ran")
    if off_s > timeout_s + 0.3:  # the timeout, the device's 50 ms check, scheduling on a loaded machine
        o.violations.append(f"heater off {off_s:.2f} s after the kill, timeout {timeout_s} s")
    o.violations += trip_violations
    if not status & 0x4 or held != 0.0:
        o.violations.append(f"status bits {status:#x}, heater {held} W 0.3 s later")
    return o


# ---------------------------------------------------------------------------------- OPC UA
def device_matches_log(server, samples: list[dict], thread) -> list[str]:
    """The device's heater command is one the daemon logged. The device is read first, then two
    more ticks are awaited: a write completes on the server before the daemon logs its row, so the
    device may be one tick ahead of the log when it is read, never behind it by more than a few."""
    device_w, tripped = server.command.heater_cmd_w, server.heartbeat_tripped
    n = len(samples)
    wait_for(lambda: len(samples) >= n + 2 or not thread.is_alive(), 10, "two more ticks")
    logged = [x["heater_cmd_w"] for x in samples[max(n - 3, 0):n + 2]]
    if any(abs(device_w - w) < 1e-6 for w in logged):
        return []
    return [f"the device's heater command {device_w:.6g} W is none of the ones the daemon logged around it "
            f"({', '.join(f'{w:.6g}' for w in logged)} W; heartbeat watchdog tripped: {tripped})"]


def opcua_link_faults(workdir: Path, speedup: float = 25.0) -> Outcome:
    """The MPC controls the simulated plant through a real asyncua server on loopback: heating,
    the server stopped (link loss) and restarted (reconnection), bad values on the sensor nodes
    (NaN, out of range, bad status), then the safe stop."""
    import threading

    from hvac_mpc.daemon.opcua_sim import PlantOpcUaServer
    from hvac_mpc.models.plant import SimulatedPlant

    # an asyncua server takes ~4 s of CPU to start: a minute for a loaded machine
    server = PlantOpcUaServer(SimulatedPlant(seed=4), port=free_port(), heartbeat_timeout_s=3.0).start(60.0)
    samples: list[dict] = []
    (workdir / "opcua.csv").unlink(missing_ok=True)
    cfg = config_from_mapping({
        "loop": {"speedup": speedup},
        "log": {"path": str(workdir / "opcua.csv"), "fsync": False},
        "api": {"enabled": False},
        "controller": {"name": "mpc"},
        "backend": {"kind": "opcua", "opcua": {"endpoint": server.endpoint, "timeout_s": 0.3}},
        "reference": {"supply_temp_c": 27.0, "volume_flow_m3s": 0.02},
        "safety": {"reconnect_initial_s": 1.0, "reconnect_max_s": 4.0, "cooldown_max_s": 30.0},
    }, base_dir=workdir)
    daemon = Daemon(cfg, tick_hook=lambda d, s: samples.append(s))
    thread = threading.Thread(target=daemon.run, daemon=True)
    o = Outcome("opcua_control_link_loss_bad_values_safe_stop", "opcua")
    v = o.violations
    last = lambda: samples[-1] if samples else {}  # noqa: E731
    since = lambda t: [x for x in samples if x["time_s"] >= t]  # noqa: E731

    def plant_time(t_s: float, what: str, timeout_s: float = 30.0) -> None:
        wait_for(lambda: last().get("time_s", 0) >= t_s or not thread.is_alive(), timeout_s, what)

    thread.start()
    notes = []
    try:
        plant_time(60, "60 s of control")
        s = last()
        if not (s["connected"] and s["controller"] == "mpc" and s["heater_cmd_w"] > 0
                and s["supply_temp_c"] > samples[0]["supply_temp_c"] + 4.0):
            v.append(f"not heating through OPC UA after 60 s: {s['supply_temp_c']:.1f} C, {s['heater_cmd_w']:.0f} W")
        v += device_matches_log(server, samples, thread)
        notes.append(f"supply {samples[0]['supply_temp_c']:.1f} -> {s['supply_temp_c']:.1f} C in 60 s")
        server.stop()  # link loss
        wait_for(lambda: not daemon.connected, 10, "the link loss")
        t_lost = last()["time_s"]
        plant_time(t_lost + 8, "8 s disconnected")
        down = since(t_lost + 1)
        if not down or any(x["mode"] != "disconnected" or x["heater_cmd_w"] != 0.0 for x in down):
            v.append("heater not off or mode not 'disconnected' while the server was down")
        server.start(60.0)  # reconnection
        wait_for(lambda: daemon.connected, 30, "the reconnection")
        t_back = last()["time_s"]
        plant_time(t_back + 15, "15 s after reconnecting")
        if last()["mode"] in NOT_CONTROLLING:
            v.append(f"not controlling 15 s after the reconnection ({last()['mode']})")
        notes.append(f"link lost at {t_lost:.0f} s, back at {t_back:.0f} s")
        for sig, value, fault in (("volume_flow_m3s", float("nan"), "nan"),
                                  ("heater_outlet_temp_c", 500.0, "out_of_range"),
                                  ("volume_flow_m3s", None, "missing")):
            server.sensor_override[sig] = value
            t0 = last()["time_s"]
            plant_time(t0 + 5, f"{sig} = {value}")
            bad = since(t0 + 2)
            if not all(x["heater_cmd_w"] == 0.0 and x["sensor_faults"].get(sig) == fault for x in bad):
                v.append(f"{sig} = {value}: heater on or fault not seen as {fault}")
            if server.command.heater_cmd_w != 0.0:
                v.append(f"{sig} = {value}: the device's heater on")
            o.detected += len(bad)
            del server.sensor_override[sig]
            t1 = last()["time_s"]
            plant_time(t1 + 12, "recovery")
            if last()["heater_cmd_w"] <= 0 or last()["sensor_faults"]:
                v.append(f"no recovery 12 s after {sig} = {value} ended")
        t_stop = last()["time_s"]
        daemon.request_stop("campaign")  # safe stop
        thread.join(60)
        shutdown = [x for x in since(t_stop) if x["mode"] in ("shutdown", "stopped")]
        if not shutdown or any(x["heater_cmd_w"] != 0.0 for x in shutdown) or shutdown[-1]["mode"] != "stopped" \
                or any(x["blower_power_w"] < 120.0 for x in shutdown[:-1]):
            v.append("safe stop: heater not off, blower not cooling or no final 'stopped' row")
        if server.command.heater_cmd_w != 0.0 or abs(server.command.blower_power_w - 30.0) > 1e-6:
            v.append(f"device command after the stop {server.command}")
        notes.append(f"cool-down {len(shutdown) - 1} s")
    except (TimeoutError, RuntimeError, KeyError, IndexError) as exc:
        v.append(f"{type(exc).__name__}: {exc}")
    finally:
        daemon.request_stop("campaign")
        daemon.request_stop("campaign")
        thread.join(30)
        latency = sorted(getattr(daemon.backend, "latency_s", []))
        server.stop()
    o.exit_code = daemon.exit_code
    o.rows = len(samples)
    o.injected = {"opcua:server_stopped": 1, "opcua:bad_value": 3}
    v += check_log(cfg.log.path, cfg.safety)
    c = daemon.counters
    if c["reconnects"] < 1:
        v.append("never reconnected")
    if len(latency) < 100:
        v.append(f"only {len(latency)} ticks over OPC UA")
    else:
        p99 = latency[int(0.99 * (len(latency) - 1))]
        notes.append(f"read+write median {latency[len(latency) // 2] * 1e3:.1f} ms, 99th percentile "
                     f"{p99 * 1e3:.1f} ms over {len(latency)} ticks")
        # half the 1 s sample: beyond it the read and write would crowd the tick. Generous: the campaign runs
        # scenarios side by side and other processes share the cores (276 ms seen at a load average of 28)
        if p99 > 0.5:
            v.append(f"99th percentile of the per-tick OPC UA latency {p99 * 1e3:.0f} ms")
    o.notes = "; ".join(notes)
    return o


# ---------------------------------------------------------------------------------- campaign
#: The scenarios by name: ``fn(workdir, controller, mpc, big_log_mb) -> list[Outcome]``.
SCENARIOS: dict[str, Callable[[Path, str, str, float], list[Outcome]]] = {
    "sensor": lambda w, c, m, b: sensor_scenarios(w, c),
    "controller": lambda w, c, m, b: controller_scenarios(w, m),
    "backend": lambda w, c, m, b: backend_scenarios(w, c),
    "api": lambda w, c, m, b: api_scenarios(w, c),
    "disk_full": lambda w, c, m, b: [disk_full(w, c)],
    "rotation": lambda w, c, m, b: [log_rotation(w, c)],
    "config": lambda w, c, m, b: bad_config_files(w),
    "calibration": lambda w, c, m, b: bad_calibration_files(w),
    "modes": lambda w, c, m, b: [mode_switches_over_modbus(w)],
    "systemd": lambda w, c, m, b: [systemd_watchdog(w)],
    "opcua": lambda w, c, m, b: [opcua_link_faults(w)],
    "sigkill": lambda w, c, m, b: sigkill_restart(w, c),
    "sigterm": lambda w, c, m, b: sigterm_shutdown(w, c, (signal.SIGTERM,)),
    "sigint": lambda w, c, m, b: sigterm_shutdown(w, c, (signal.SIGINT,)),
    "heartbeat": lambda w, c, m, b: [device_heartbeat_after_sigkill(w)],
    "tail_repair": lambda w, c, m, b: [tail_repair_kills(w, b)],
    "flood_16": lambda w, c, m, b: [slow_header_flood(w, 16, c)],
    "flood_200": lambda w, c, m, b: [slow_header_flood(w, 200, c)],
    "flood_200_process": lambda w, c, m, b: [slow_header_flood_process(w)],
}
#: In-process daemons that use the CPU: two processes of their own, each running its group in turn.
INPROCESS = (("modes", "systemd", "backend", "api", "disk_full", "rotation", "config", "calibration"),
             ("controller", "sensor"))
#: Mostly waiting on daemon processes or a protocol server: side by side in threads, beside INPROCESS.
PROCESSES = ("sigterm", "sigint", "heartbeat", "opcua", "sigkill", "tail_repair")
#: /health within 1 s and no late tick under connection floods: alone, after the rest.
TIMING = ("flood_16", "flood_200", "flood_200_process")


def run_scenarios(names: tuple[str, ...] | list[str], workdir: str | Path, controller: str = "baseline",
                  mpc: str = "mpc", big_log_mb: float = 300.0, threads: int = 1,
                  log_level: int | None = None) -> tuple[list[Outcome], dict[str, float]]:
    """Run the named scenarios (``threads`` > 1: side by side); the outcomes in the order of
    ``names`` and the wall time of each scenario."""
    import logging
    from concurrent.futures import ThreadPoolExecutor

    if log_level is not None:
        logging.getLogger("hvac_mpc.daemon").setLevel(log_level)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)

    def one(name: str) -> tuple[list[Outcome], float]:
        t = time.perf_counter()
        try:
            outs = SCENARIOS[name](workdir, controller, mpc, big_log_mb)
        except Exception as exc:  # noqa: BLE001 - a scenario that breaks is a failed scenario, not the end
            outs = [Outcome(name, "broken", violations=[f"{type(exc).__name__}: {exc}"])]
        return outs, time.perf_counter() - t

    with ThreadPoolExecutor(max(1, threads)) as pool:
        done = list(pool.map(one, names))
    return [o for outs, _ in done for o in outs], {n: w for n, (_, w) in zip(names, done)}


def run_campaign(workdir: str | Path, include_processes: bool = True, controller: str = "baseline",
                 mpc: str = "mpc", big_log_mb: float = 300.0, parallel: bool = True) -> dict[str, Any]:
    """Run every scenario; returns ``{"outcomes": [...], "counts": {...}}``.

    With ``parallel``, the in-process scenarios run in two child processes while the process and
    protocol scenarios run in threads here; the connection floods run last, alone."""
    import logging
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    side = [n for n in PROCESSES if include_processes or n == "opcua"]
    timing = [n for n in TIMING if include_processes or n != "flood_200_process"]
    args = (workdir, controller, mpc, big_log_mb)
    level = logging.getLogger("hvac_mpc.daemon").getEffectiveLevel()
    inprocess = [name for group in INPROCESS for name in group]
    if parallel:
        with ProcessPoolExecutor(len(INPROCESS), mp_context=multiprocessing.get_context("spawn")) as pool:
            groups = [pool.submit(run_scenarios, group, *args, log_level=level) for group in INPROCESS]
            outs_side, wall_side = run_scenarios(side, *args, threads=3)
            done = [g.result() for g in groups]
        by_name = {o_name: w for _, walls in done for o_name, w in walls.items()}
        outs_in = [o for outs, _ in done for o in outs]
        wall_in = {n: by_name[n] for n in inprocess}
    else:
        outs_in, wall_in = run_scenarios(inprocess, *args)
        outs_side, wall_side = run_scenarios(side, *args)
    t_parallel = time.perf_counter() - t0
    outs_timing, wall_timing = run_scenarios(timing, *args)
    outcomes = outs_in + outs_side + outs_timing
    counts: dict[str, Any] = {"scenarios": len(outcomes), "passed": sum(o.ok for o in outcomes),
                              "violations": sum(len(o.violations) for o in outcomes), "by_category": {},
                              "injected_fault_ticks": {}, "wall_s": 0.0,
                              "scenario_wall_s": {**wall_in, **wall_side, **wall_timing},
                              "phase_wall_s": {"side_by_side" if parallel else "in_turn": t_parallel}}
    for o in outcomes:
        c = counts["by_category"].setdefault(o.category, {"tried": 0, "passed": 0})
        c["tried"] += 1
        c["passed"] += o.ok
        for k, n in o.injected.items():
            counts["injected_fault_ticks"][k] = counts["injected_fault_ticks"].get(k, 0) + n
    counts["wall_s"] = time.perf_counter() - t0
    counts["phase_wall_s"]["floods"] = counts["wall_s"] - t_parallel
    return {"outcomes": outcomes, "counts": counts}


def format_report(result: dict[str, Any]) -> str:
    c = result["counts"]
    lines = [f"fault campaign: {c['scenarios']} scenarios, {c['passed']} passed, {c['violations']} violations, "
             f"{c['wall_s']:.1f} s (" + ", ".join(f"{k} {v:.1f} s" for k, v in c.get("phase_wall_s", {}).items()) + ")"]
    if c.get("scenario_wall_s"):
        lines.append("  wall time: " + ", ".join(f"{k} {v:.1f}" for k, v in c["scenario_wall_s"].items()))
    for cat, n in c["by_category"].items():
        lines.append(f"  {cat:<11} tried {n['tried']:>3}  passed {n['passed']:>3}")
    lines.append("  injected (fault-ticks): " + ", ".join(f"{k} {v}" for k, v in sorted(c["injected_fault_ticks"].items())))
    for o in result["outcomes"]:
        flag = "ok  " if o.ok else "FAIL"
        lines.append(f"  {flag} {o.name:<40} exit={o.exit_code!s:<5} detected={o.detected:<4} {o.notes[:300]}"
                     + ("" if o.ok else f"  <- {o.violations[:3]}"))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import argparse
    import logging

    ap = argparse.ArgumentParser(description="run the daemon's fault campaign")
    ap.add_argument("--workdir", default="daemon_campaign")
    ap.add_argument("--no-processes", action="store_true")
    ap.add_argument("--big-log-mb", type=float, default=300.0,
                    help="size of the log killed during its tail repair")
    ap.add_argument("--serial", action="store_true", help="every scenario in turn, none side by side")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("hvac_mpc.daemon").setLevel(logging.CRITICAL)
    result = run_campaign(args.workdir, include_processes=not args.no_processes, big_log_mb=args.big_log_mb,
                          parallel=not args.serial)
    print(format_report(result))
    return 0 if result["counts"]["violations"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
