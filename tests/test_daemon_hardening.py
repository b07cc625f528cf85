"""The hardened daemon, fast parts: configuration errors (exit 2, key and range named, no
traceback), controllers only through entry points, the log (in-place tail repair, rotation with
index, UTC column, disk full with memory buffer), the API's guards (token, content type,
Host/Origin, overflow), metrics, operator modes and the ``ctl`` client. In-process, a few seconds."""

from __future__ import annotations

import errno
import json
import logging
import urllib.request

import numpy as np
import pytest

from hvac_mpc.benchmarks.daemon_campaign import _request
from hvac_mpc.daemon.config import ConfigError, config_from_mapping
from hvac_mpc.daemon.log_writer import DurableLog
from hvac_mpc.daemon.loop import Daemon
from hvac_mpc.daemon.server import token_path
from hvac_mpc.models.measurement_log import read_log, repair_tail

pytest.importorskip("uvicorn", reason="the API needs the 'server' extra (uvicorn)")


def _cfg(tmp_path, **over):
    data = {"loop": {"speedup": "max", "max_ticks": 40}, "log": {"path": str(tmp_path / "log.csv"), "fsync": False},
            "api": {"port": 0}, "controller": {"name": "baseline", "fallback": []}}
    for k, v in over.items():
        data[k] = {**data.get(k, {}), **v} if isinstance(v, dict) else v
    return config_from_mapping(data)


# ------------------------------------------------------------------------------ configuration
BAD_FILES = {
    "binary": (b"\x00\xff\xfe\x89PNG\r\n", "not a UTF-8 text file"),
    "reference_number": (b"reference = 5\n", "reference: expected a table [reference] with supply_temp_c in [5.0, 50.0]"),
    "reference_text": (b'reference = "abc"\n', "reference: expected a table [reference]"),
    "fallback_number": (b"[controller]\nfallback = [1]\n", "controller.fallback[0]: Input should be a valid string"),
    "unknown_effect": (b'[backend.simulated]\neffects = ["warp_drive"]\n', "backend.simulated.effects[0]"),
    "zero_min_flow": (b"[safety]\nmin_flow_m3s = 0.0\n", "min_flow_m3s = 0.0 must be above 0 (allowed (0, 0.05])"),
    "no_interlock_sensor": (b"[safety]\ninterlock_sensors = []\n", "interlock_sensors: at least one"),
    "module_name_controller": (b'[controller]\nname = "os:system"\n', "never from a 'module:name'"),
    "huge_integer": (b"[loop]\nmax_ticks = 1" + b"0" * 400 + b"\n", "loop.max_ticks = 1000000000000"),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES) + ["directory"])
def test_every_bad_config_file_exits_2_naming_the_key_without_traceback(tmp_path, capsys, name):
    from hvac_mpc.cli import main

    if name == "directory":
        path, expect = tmp_path / "conf.d", "is a directory"
        path.mkdir()
    else:
        content, expect = BAD_FILES[name]
        path = tmp_path / "bad.toml"
        path.write_bytes(content)
    assert main(["daemon", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert expect in err and "Traceback" not in err, err
    assert not any(p.suffix == ".csv" for p in tmp_path.iterdir())  # nothing started, no log


def test_unsafe_override_is_explicit_and_logged(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="hvac_mpc.daemon"):
        cfg = config_from_mapping({"safety": {"unsafe": True, "min_flow_m3s": 0.0, "interlock_sensors": []}})
    assert cfg.safety.unsafe_overrides() == ["min_flow_m3s = 0.0", "interlock_sensors = []"]
    assert "safety bounds overridden" in caplog.text
    with pytest.raises(ConfigError, match=r"safety.heater_max_w = 300.0 is outside the allowed range \[0.0, 240.0\]"):
        config_from_mapping({"safety": {"unsafe": True, "heater_max_w": 300.0}})  # hard limits stay


def test_public_bind_needs_authenticated_reads():
    with pytest.raises(ConfigError, match=r"api: host = '0.0.0.0' is not loopback: set api.auth_reads = true"):
        config_from_mapping({"api": {"host": "0.0.0.0"}})
    assert config_from_mapping({"api": {"host": "0.0.0.0", "auth_reads": True}}).api.auth_reads


def test_controllers_come_only_from_the_entry_point_group(test_controllers):
    from hvac_mpc.daemon.plugins import registered_controllers

    names = registered_controllers()
    assert {"mpc", "baseline", "campaign-greedy-heater", "test-simple-pi"} <= set(names)
    assert config_from_mapping({"controller": {"name": "test-simple-pi", "fallback": []}}).controller.name
    with pytest.raises(ConfigError, match="'daemon_helpers:SimplePi' is not a registered controller"):
        config_from_mapping({"controller": {"name": "daemon_helpers:SimplePi"}})


# ------------------------------------------------------------------------------ log
def _rows(n, t0=0.0, utc="2026-11-23T10:00:00.000Z"):
    return [{"time_s": t0 + k, "blower_power_w": 100.0, "supply_temp_c": 20.0 + 0.1 * k, "mode": "ok", "utc": utc}
            for k in range(n)]


def test_tail_repair_is_in_place_and_keeps_every_committed_byte(tmp_path):
    path = tmp_path / "log.csv"
    with DurableLog(path, fsync=False) as log:
        for row in _rows(50):
            log.write(row)
    committed = path.read_bytes()
    inode = path.stat().st_ino
    with path.open("ab") as fh:
        fh.write(b"50.0,100.0,0.0,1")  # a row torn by a crash
    assert repair_tail(path) == len(b"50.0,100.0,0.0,1")
    assert path.read_bytes() == committed and path.stat().st_ino == inode  # truncated, not rewritten
    assert repair_tail(path) == 0
    with path.open("ab") as fh:
        fh.write(b"x" * 200_000)  # a torn tail longer than one read chunk
    assert repair_tail(path, chunk_bytes=4096) == 200_000 and path.read_bytes() == committed
    with DurableLog(path, fsync=False) as log:  # restart: continues after the last committed row
        assert log.last_time_s == 49.0
        log.write(_rows(1, t0=50.0)[0])
    assert list(read_log(path)["time_s"]) == [float(k) for k in range(51)]


def test_tail_repair_reports_each_step_with_the_file_as_it_is_there(tmp_path):
    from hvac_mpc.daemon.log_writer import REOPENED
    from hvac_mpc.models.measurement_log import REPAIR_STEPS

    path = tmp_path / "log.csv"
    with DurableLog(path, fsync=False) as log:
        for row in _rows(20):
            log.write(row)
    committed = path.stat().st_size
    with path.open("ab") as fh:
        fh.write(b"20.0,100.0,0.0,1")
    seen = []
    DurableLog(path, repair_step=lambda name: seen.append((name, path.stat().st_size))).close()
    torn = committed + len(b"20.0,100.0,0.0,1")
    assert seen == [("begin", torn), ("found", torn), ("truncated", committed), ("synced", committed),
                    (REOPENED, committed)]
    assert [name for name, _ in seen] == [*REPAIR_STEPS, REOPENED]
    seen.clear()
    DurableLog(path, repair_step=lambda name: seen.append(name)).close()  # nothing torn: nothing cut
    assert seen == ["begin", "found", REOPENED] and path.stat().st_size == committed


def test_sigkill_at_every_step_of_the_tail_repair_and_at_random_loses_no_committed_byte(tmp_path):
    """A small log here (fast); the fault campaign does the same on a 300 MB log."""
    from hvac_mpc.benchmarks.repair_kills import STEPS, kill_during_repair

    log = tmp_path / "big.csv"
    rep = kill_during_repair(log, size_mb=4.0, rounds=2, random_kills=4, seed=1)
    assert rep.lost == [], rep.lost
    assert rep.step_kills == {s: 2 for s in STEPS} and rep.random_kills == 4
    assert rep.restarts == 2 * len(STEPS) + 4 + 3 and rep.size_bytes == rep.committed_bytes >= 4 * 2**20
    assert 0.0 < rep.repair_window_ms < 5000.0
    assert not log.exists()  # cleaned up


def test_rotation_by_size_and_day_keeps_an_index_and_every_row(tmp_path):
    path = tmp_path / "log.csv"
    with DurableLog(path, fsync=False, rotate_bytes=2000) as log:
        for row in _rows(60):
            log.write(row)
        for row in _rows(5, t0=60.0, utc="2026-11-24T00:00:01.000Z"):
            log.write(row)
        assert log.counters["rotations"] >= 2
    with DurableLog(path, fsync=False, rotate_daily=True) as log:
        log.write(_rows(1, t0=65.0, utc="2026-11-25T00:00:00.000Z")[0])  # a new day: rotated at this row
        segments = log.segments()
        assert log.last_time_s == 65.0
    times = []
    for seg in segments:
        data = read_log(tmp_path / seg["segment"])
        assert float(seg["first_time_s"]) == data["time_s"][0] and float(seg["last_time_s"]) == data["time_s"][-1]
        assert int(seg["rows"]) == len(data["time_s"])
        times += list(data["time_s"])
    times += list(read_log(path)["time_s"])
    assert times == [float(k) for k in range(66)]
    old = tmp_path / "old.csv"  # a log with another header (an older version): kept as a segment
    old.write_text("time_s,blower_power_w\n0.0,100.0\n")
    with DurableLog(old, fsync=False) as log:
        log.write(_rows(1)[0])
        assert log.segments()[0]["rows"] == "1"
    assert read_log(old)["utc"][0] == "2026-11-23T10:00:00.000Z"


class DiskFull:
    """A disk that is full while ``full`` is set: every write raises ENOSPC after half a row."""

    def __init__(self):
        self.full = False

    def __call__(self):
        if self.full:
            raise OSError(errno.ENOSPC, "No space left on device")


def test_disk_full_buffers_rows_reports_degraded_and_resumes(tmp_path):
    path = tmp_path / "log.csv"
    disk = DiskFull()
    clock = [0.0]
    log = DurableLog(path, fsync=True, buffer_rows=30, retry_s=5.0, wall_clock=lambda: clock[0], inject=disk)
    rows = _rows(100)
    for k, row in enumerate(rows):
        clock[0] = float(k)
        disk.full = 20 <= k < 60
        with open(path, "ab") as fh:  # a partial row as a real ENOSPC can leave it
            if disk.full:
                fh.write(b"20.0,1")
        ok = log.write(row)
        if 20 <= k < 60:
            assert not ok and log.state == "degraded"
    assert log.state == "ok" and log.status()["buffered_rows"] == 0
    assert log.counters["rows_dropped"] == 40 - 30 + 1  # the bound: the oldest rows went first
    log.close()
    t = read_log(path)["time_s"]
    assert np.all(np.diff(t) > 0) and t[0] == 0.0 and t[-1] == 99.0
    assert len(t) == 100 - log.counters["rows_dropped"]
    assert b"20.0,1\n" not in path.read_bytes() and path.read_bytes().count(b"\n") == len(t) + 1


def test_daemon_controls_on_while_the_disk_is_full_and_logs_everything_after(tmp_path):
    cfg = _cfg(tmp_path, loop={"max_ticks": 150}, api={"enabled": False}, log={"retry_s": 5.0},
               faults=[{"target": "log", "kind": "enospc", "start_s": 20.0, "end_s": 80.0}])
    seen = {}

    def hook(d, sample):
        ok, info = d.health()
        seen[sample["time_s"]] = (ok, info["status"], d.status()["log"]["buffered_rows"], sample["controller"])

    d = Daemon(cfg, tick_hook=hook)
    assert d.run() == 0
    assert all(seen[t][0] for t in seen)  # health: up throughout
    assert {seen[t][1] for t in range(21, 79)} == {"degraded"} and seen[100.0][1] == "ok"
    assert seen[79.0][2] > 50  # rows held in memory during the minute
    assert all(seen[t][3] == "baseline" for t in range(5, 140))  # the controller ran on
    log = read_log(cfg.log.path)
    assert np.allclose(np.diff(log["time_s"]), 1.0) and log["time_s"][0] == 0.0 and len(log["time_s"]) >= 150
    utc = log["utc"]
    assert all(u.endswith("Z") and u[:2] == "20" for u in utc)
    assert d.injected["log:enospc"] > 5


# ------------------------------------------------------------------------------ API guards
def test_writes_need_token_json_and_own_host_and_origin_and_change_nothing(tmp_path):
    cfg = _cfg(tmp_path)
    out = {}

    def hook(d, sample):
        if sample["time_s"] != 5.0:
            return
        port, token = d.api.port, token_path(d.cfg).read_text().strip()
        body = json.dumps({"supply_temp_c": 30.0, "volume_flow_m3s": 0.02}).encode()
        for name, headers, tok in (("no_token", {}, None), ("wrong_token", {}, "x" * 43),
                                   ("text_plain", {"Content-Type": "text/plain"}, token),
                                   ("no_type", {"Content-Type": ""}, token),
                                   ("host", {"Host": "rebind.example:%d" % port}, token),
                                   ("origin", {"Origin": "http://evil.example"}, token)):
            out[name] = _request(port, "PUT", "/reference", body, headers, token=tok)
            out[name + "_mode"] = _request(port, "PUT", "/mode", b'{"mode": "safe-stop"}', headers, token=tok)[0]
        big = b'{"supply_temp_c": 1' + b"0" * 400 + b', "volume_flow_m3s": 0.02}'
        out["overflow"] = _request(port, "PUT", "/reference", big, token=token)
        out["ref_after"] = _request(port, "GET", "/reference")[1]
        out["mode_after"] = _request(port, "GET", "/mode")[1]["mode"]
        out["read_host"] = _request(port, "GET", "/status", headers={"Host": "rebind.example"})[0]
        out["own_origin"] = _request(port, "PUT", "/reference", body, {"Origin": f"http://127.0.0.1:{port}"},
                                     token=token)[0]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
            out["metrics"] = r.read().decode()

    assert Daemon(cfg, tick_hook=hook).run() == 0
    expect = {"no_token": 401, "wrong_token": 401, "text_plain": 415, "no_type": 415, "host": 403, "origin": 403}
    for name, code in expect.items():
        assert out[name][0] == code and out[name + "_mode"] == code, (name, out[name])
    assert "Host 'rebind.example" in out["host"][1]["error"]
    assert out["overflow"][0] == 400 and "401 digits" in out["overflow"][1]["error"]
    assert out["ref_after"]["supply_temp_c"] == 20.0 and out["mode_after"] == "auto-pid"  # nothing changed
    assert out["read_host"] == 403 and out["own_origin"] == 200
    for name in ("hvac_daemon_tick_seconds_bucket", "hvac_daemon_deadline_misses_total",
                 "hvac_daemon_fallback_ticks", "hvac_daemon_solver_status_total", "hvac_daemon_interlock_trips",
                 "hvac_daemon_log_degraded 0.0", 'hvac_daemon_operator_mode{mode="auto-pid"} 1.0'):
        assert name in out["metrics"], name


def test_two_daemons_have_their_own_metrics(tmp_path):
    from hvac_mpc.daemon.metrics import daemon_registry
    from prometheus_client import generate_latest

    a = Daemon(_cfg(tmp_path / "a", api={"enabled": False}, loop={"max_ticks": 3}))
    b = Daemon(_cfg(tmp_path / "b", api={"enabled": False}, loop={"max_ticks": 7}))
    a.run(), b.run()
    ta, tb = (generate_latest(daemon_registry(x)).decode() for x in (a, b))
    na, nb = a.counters["ticks"], b.counters["ticks"]
    assert na != nb and f"hvac_daemon_ticks_total {float(na)}" in ta and f"hvac_daemon_ticks_total {float(nb)}" in tb


# ------------------------------------------------------------------------------ modes and ctl
def test_modes_switch_bumplessly_manual_is_bounded_and_ctl_drives_it(tmp_path, capsys):
    from hvac_mpc.cli import main

    cfg = _cfg(tmp_path, loop={"max_ticks": 400}, reference={"supply_temp_c": 30.0, "volume_flow_m3s": 0.02},
               api={"port_file": str(tmp_path / "port")})
    conf = tmp_path / "d.toml"
    conf.write_text(f'[log]\npath = "{cfg.log.path}"\n[api]\nport_file = "{tmp_path / "port"}"\n')
    rows, out = [], {}

    def ctl(*argv):
        code = main(["ctl", "--config", str(conf), *argv])
        cap = capsys.readouterr()
        return code, cap.out + cap.err

    def hook(d, sample):
        rows.append(sample)
        t = sample["time_s"]
        if t == 100.0:
            out["manual"] = ctl("mode", "manual")
        elif t == 110.0:
            out["set"] = ctl("set", "blower_power_w=30", "valve_m_pct=0", "valve_f_pct=0", "valve_w_pct=0",
                             "heater_cmd_w=0")
        elif t == 150.0:
            out["heater_low_flow"] = ctl("set", "heater_cmd_w=200")
            out["range"] = ctl("set", "blower_power_w=900")
        elif t == 160.0:
            out["restore"] = ctl("set", "blower_power_w=150", "valve_m_pct=100", "valve_f_pct=100",
                                 "valve_w_pct=100")
        elif t == 220.0:
            out["heat"] = ctl("set", "heater_cmd_w=150")
        elif t == 260.0:
            out["pid"] = ctl("mode", "auto-pid")
        elif t == 300.0:
            out["stop"] = ctl("mode", "safe-stop")
        elif t == 320.0:
            out["status"] = ctl("mode")

    assert Daemon(cfg, tick_hook=hook).run() == 0
    assert out["manual"][0] == 0 and out["set"][0] == 0 and out["restore"][0] == 0 and out["heat"][0] == 0
    assert out["heater_low_flow"][0] == 1 and "heater refused: measured volume flow" in out["heater_low_flow"][1]
    assert out["range"][0] == 1 and "blower_power_w" in out["range"][1] and "300" in out["range"][1]
    by_t = {r["time_s"]: r for r in rows}
    lim = {"blower_power_w": 60.0, "heater_cmd_w": 60.0}
    for t in list(range(101, 131)) + list(range(161, 175)) + list(range(261, 291)):  # after each switch/setting
        for name in ("blower_power_w", "heater_cmd_w", "valve_a_pct", "valve_m_pct"):
            step = abs(by_t[t][name] - by_t[t - 1][name])
            assert step <= lim.get(name, 20.0) + 1e-9, (t, name, step)
    assert by_t[150.0]["volume_flow_m3s"] < 0.005 and all(by_t[t]["heater_cmd_w"] == 0.0 for t in range(150, 161))
    assert by_t[240.0]["heater_cmd_w"] == 150.0 and by_t[240.0]["controller"] == "manual"
    assert by_t[280.0]["controller"] == "baseline"
    assert all(by_t[t]["heater_cmd_w"] == 0.0 and by_t[t]["controller"] == "safe-stop" for t in range(301, 400))
    history = json.loads(out["status"][1])["history"]
    assert [h["to"] for h in history] == ["manual", "auto-pid", "safe-stop"]
    assert all("hvac-mpc-ctl" in h["client"] and h["utc"].endswith("Z") for h in history)


def test_example_configuration_is_valid():
    import tomllib

    from hvac_mpc.daemon.config import EXAMPLE_TOML

    cfg = config_from_mapping(tomllib.loads(EXAMPLE_TOML))
    assert cfg.controller.name == "mpc" and cfg.api.header_timeout_s == 2.0 and not cfg.safety.unsafe


def test_readers_keep_columns_they_do_not_know(tmp_path):
    from hvac_mpc.models.measurement_log import REQUIRED_COLUMNS

    path = tmp_path / "future.csv"
    header = list(REQUIRED_COLUMNS) + ["utc", "model_sha256"]
    path.write_text(",".join(header) + "\n" + ",".join(["1.0"] * len(REQUIRED_COLUMNS)
                                                       + ["2026-11-23T10:00:00.000Z", "ab12"]) + "\n")
    log = read_log(path)
    assert log["utc"][0] == "2026-11-23T10:00:00.000Z" and log["model_sha256"][0] == "ab12"
    assert log["supply_temp_c"][0] == 1.0


def test_authenticated_reads_when_configured(tmp_path):
    cfg = _cfg(tmp_path, api={"auth_reads": True}, loop={"max_ticks": 10})
    out = {}

    def hook(d, sample):
        if sample["time_s"] == 3.0:
            token = token_path(d.cfg).read_text().strip()
            out["health"] = _request(d.api.port, "GET", "/health")[0]
            out["status"] = _request(d.api.port, "GET", "/status")[0]
            out["status_token"] = _request(d.api.port, "GET", "/status", token=token)[0]

    assert Daemon(cfg, tick_hook=hook).run() == 0
    assert out == {"health": 200, "status": 401, "status_token": 200}
