"""Watchdogs: systemd notifications (a bound AF_UNIX datagram socket stands in for systemd) and the
device-side heartbeat watchdog of the simulated device. The fault campaign
(hvac_mpc.benchmarks.daemon_campaign) also kills the daemon process over Modbus and times the
device's heartbeat watchdog, and hangs the loop under the systemd stand-in."""

from __future__ import annotations

import os
import signal
import threading
import time
import uuid
from pathlib import Path

import pytest

from hvac_mpc.benchmarks.daemon_campaign import HangingBackend, NotifySocket
from hvac_mpc.contract import Command, StepResult
from hvac_mpc.daemon.config import config_from_mapping
from hvac_mpc.daemon.loop import Daemon
from hvac_mpc.daemon.watchdog import Notifier, SystemdConfig, watchdog_timeout_s
from hvac_mpc.models.plant import SimulatedPlant


def test_notifier_speaks_to_path_and_abstract_sockets(tmp_path, monkeypatch):
    for path in (str(tmp_path / "notify.sock"), f"@hvac-mpc-test-{uuid.uuid4().hex}"):
        systemd = NotifySocket(path)
        monkeypatch.setenv("NOTIFY_SOCKET", path)
        n = Notifier()
        assert n.active and n.notify("READY=1") and n.notify("WATCHDOG=1")
        time.sleep(0.2)
        systemd.close()
        n.close()
        assert [m for _, m in systemd.messages] == ["READY=1", "WATCHDOG=1"], path
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert not Notifier().active and Notifier().notify("READY=1") is False
    assert Notifier("vsock:2:1234").active is False  # unsupported family: off, not an error
    assert watchdog_timeout_s({"WATCHDOG_USEC": "4000000"}) == 4.0
    assert watchdog_timeout_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": str(os.getpid() + 1)}) is None
    assert watchdog_timeout_s({"WATCHDOG_USEC": "x"}) is None


class BlockingController:
    """A controller that blocks on its fifth step (until released): the chain falls back."""

    def __init__(self, params=None, dt_s: float = 1.0):
        self.n = 0
        self.release = threading.Event()

    def reset(self, command=None):
        pass

    def step(self, measurement, reference):
        self.n += 1
        if self.n >= 5:
            self.release.wait(30.0)
        return StepResult(Command(blower_power_w=150.0, valve_a_pct=60.0), {"status": "ok"})


def _daemon(tmp_path: Path, name: str, backend) -> Daemon:
    cfg = config_from_mapping({
        "loop": {"period_s": 1.0, "speedup": 20.0},  # 50 ms ticks
        "log": {"path": str(tmp_path / f"{name}.csv"), "fsync": False},
        "api": {"enabled": False},
        "controller": {"name": "baseline", "fallback": []},
        "reference": {"supply_temp_c": 18.0, "volume_flow_m3s": 0.03},
        "safety": {"cooldown_min_s": 1.0, "cooldown_max_s": 3.0},
        "systemd": {"stall_s": 0.5, "ping_interval_s": 0.1},
    }, base_dir=tmp_path)
    return Daemon(cfg, backend=backend)


def _run(daemon: Daemon) -> threading.Thread:
    t = threading.Thread(target=daemon.run, daemon=True)
    t.start()
    return t


def test_systemd_ready_pings_while_healthy_none_while_hung_stopping_at_shutdown(tmp_path):
    """READY once, pings every 0.1 s while healthy, none from the stall limit (0.5 s) on while the
    loop hangs in a fieldbus write for 2 s, pings again once it runs, STOPPING at shutdown
    (the checks are the campaign scenario's; it reports the timings)."""
    from hvac_mpc.benchmarks.daemon_campaign import systemd_watchdog

    o = systemd_watchdog(tmp_path)
    print(o.notes)
    assert o.violations == [] and o.detected == 1 and o.exit_code == 0
    assert o.rows > 20  # ticks before the hang and after it


def test_a_blocking_controller_does_not_stop_the_pings(tmp_path, monkeypatch):
    """The chain's deadline keeps the loop ticking on the fallback: that is a healthy loop."""
    path = f"@hvac-mpc-test-{uuid.uuid4().hex}"
    systemd = NotifySocket(path)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    backend = HangingBackend()
    daemon = _daemon(tmp_path, "block", backend)
    blocking = BlockingController()
    daemon.chain.controllers[0] = ("blocking", blocking)
    thread = _run(daemon)
    try:
        time.sleep(1.5)
        ticks = daemon.tick
        pings = len(systemd.times("WATCHDOG=1"))
    finally:
        blocking.release.set()
        daemon.request_stop("test")
        daemon.request_stop("test")
        thread.join(20.0)
        systemd.close()
    assert blocking.n >= 5 and ticks >= 15, (blocking.n, ticks)
    assert daemon.counters["deadline_misses"] + daemon.counters["controller_busy"] > 0
    assert pings >= 10, systemd.messages


def test_no_notify_socket_no_watchdog_thread(tmp_path, monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    daemon = _daemon(tmp_path, "plain", HangingBackend())
    thread = _run(daemon)
    time.sleep(0.3)
    daemon.request_stop("test")
    daemon.request_stop("test")
    thread.join(20.0)
    assert daemon._watchdog is None and daemon.tick > 0
    assert SystemdConfig().enabled  # on by default, active only under systemd


@pytest.mark.slow
def test_daemon_process_under_a_systemd_stand_in_ready_pings_stopping(tmp_path):
    """``hvac-mpc daemon`` as systemd starts it: $NOTIFY_SOCKET and $WATCHDOG_USEC in the environment."""
    from hvac_mpc.benchmarks.daemon_campaign import process_config, start_daemon, wait_for

    path = f"@hvac-mpc-test-{uuid.uuid4().hex}"
    systemd = NotifySocket(path)
    cfg = process_config(tmp_path, "unit", "baseline", speedup=10.0,
                         extra={"safety": {"cooldown_max_s": 20.0}})
    proc = start_daemon(cfg, env={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000"})
    try:
        wait_for(lambda: len(systemd.times("WATCHDOG=1")) >= 5, 60, "five watchdog pings", proc)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        time.sleep(0.1)
        systemd.close()
    assert proc.returncode == 0, err.decode()[-2000:]
    ready, pings, stopping = systemd.times("READY=1"), systemd.times("WATCHDOG=1"), systemd.times("STOPPING=1")
    assert len(ready) == 1 and len(stopping) == 1 and ready[0] < pings[0] < stopping[0]
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    assert max(gaps) < 1.0, gaps  # every half WATCHDOG_USEC (0.5 s), never the whole timeout


def test_systemd_opcua_and_calibration_sections_name_the_key():
    from hvac_mpc.daemon.config import ConfigError

    cases = [({"systemd": {"stall_s": -1.0}}, r"systemd\.stall_s = -1.0 is outside the allowed range \[0.0, 3600.0\]"),
             ({"systemd": {"enable": True}}, r"systemd\.enable: unknown key; allowed: \['enabled', 'ping_interval_s', 'stall_s'\]"),
             ({"backend": {"opcua": {"timeout_s": 50}}}, r"backend\.opcua\.timeout_s = 50 is outside the allowed range \[0.01, 10.0\]"),
             ({"backend": {"opcua": {"endpoint": "http://x"}}}, r"backend\.opcua\.endpoint: String should match"),
             ({"backend": {"opcua": {"signals": "volts"}}}, r"backend\.opcua\.signals: Input should be 'engineering' or 'raw'"),
             ({"backend": {"modbus": {"signals": "volts"}}}, r"backend\.modbus\.signals: Input should be 'engineering' or 'raw' \(got 'volts'\)"),
             ({"calibration": {"path": "x.toml"}}, r"calibration\.path: unknown key; allowed: \['file'\]")]
    for data, expected in cases:
        with pytest.raises(ConfigError, match=expected):
            config_from_mapping(data)
    cfg = config_from_mapping({"backend": {"kind": "opcua", "opcua": {"signals": "raw"}}, "systemd": {"enabled": False}})
    assert cfg.backend.opcua.signals == "raw" and not cfg.systemd.enabled


def test_heartbeat_trip_is_checked_against_the_command_held_at_the_trip():
    """The fault campaign's check of the device's command after its heartbeat trip. A loaded machine
    once showed the daemon's last write (blower 118.9 W) reaching the device after the test had read
    the blower (126.3 W) and after SIGKILL: the trip then rightly gave max(118.9, 120) = 120 W, below
    the blower read earlier. The check compares with the command held at the trip and still names a
    blower below it, a heater left on, a valve not open and a write after the trip."""
    from dataclasses import replace

    from hvac_mpc.benchmarks.daemon_campaign import heartbeat_trip_violations
    from hvac_mpc.daemon.device_sim import SimulatedDevice

    dev = SimulatedDevice(SimulatedPlant(seed=5), heartbeat_timeout_s=0.1)
    dev._on_command(Command(blower_power_w=126.3, heater_cmd_w=200.0, valve_a_pct=20.0), 1)
    read_before_kill = dev.command.blower_power_w
    dev._on_command(Command(blower_power_w=118.9, heater_cmd_w=200.0, valve_a_pct=20.0), 2)  # in flight at the kill
    time.sleep(0.15)
    assert dev.check_heartbeat()
    assert dev.command.blower_power_w == 120.0 < read_before_kill
    assert dev.heartbeat_trip_held[-1] == (2, Command(blower_power_w=118.9, heater_cmd_w=200.0, valve_a_pct=20.0))
    assert heartbeat_trip_violations(dev, dev.command) == []
    for broken in (replace(dev.command, blower_power_w=119.0), replace(dev.command, heater_cmd_w=1.0),
                   replace(dev.command, valve_w_pct=0.0)):
        (msg,) = heartbeat_trip_violations(dev, broken)
        assert msg.startswith("device command after the trip") and "held at the trip" in msg
    high = SimulatedDevice(SimulatedPlant(seed=5), heartbeat_timeout_s=0.1)
    high._on_command(Command(blower_power_w=150.0, heater_cmd_w=200.0, valve_a_pct=20.0), 1)
    time.sleep(0.15)
    assert high.check_heartbeat() and high.command.blower_power_w == 150.0
    assert heartbeat_trip_violations(high, high.command) == []
    assert heartbeat_trip_violations(high, replace(high.command, blower_power_w=120.0)) != []
    dev._on_command(Command(blower_power_w=118.9, heater_cmd_w=200.0, valve_a_pct=20.0), 2)  # after the trip
    assert heartbeat_trip_violations(dev, dev.command) == ["1 writes reached the device after the trip"]


def test_device_heartbeat_watchdog_cools_a_heater_that_was_on_and_holds_otherwise():
    from hvac_mpc.daemon.device_sim import SimulatedDevice

    for heater_w, blower_after in ((200.0, 120.0), (0.0, 40.0)):
        dev = SimulatedDevice(SimulatedPlant(seed=1), heartbeat_timeout_s=0.1)
        dev._on_command(Command(blower_power_w=40.0, heater_cmd_w=heater_w, valve_a_pct=20.0), 1)
        dev._on_command(Command(blower_power_w=40.0, heater_cmd_w=0.0, valve_a_pct=20.0), 2)
        assert not dev.check_heartbeat()  # within the timeout
        time.sleep(0.15)
        assert dev.check_heartbeat() and dev.status_bits() & 0x4
        assert dev.command.heater_cmd_w == 0.0 and dev.command.blower_power_w == blower_after
        assert dev.command.valve_a_pct == (100.0 if heater_w else 20.0)
        dev._on_command(Command(blower_power_w=40.0, heater_cmd_w=150.0, valve_a_pct=20.0), 2)
        assert dev.command.heater_cmd_w == 0.0  # an unchanged heartbeat does not release it
        dev._on_command(Command(blower_power_w=40.0, heater_cmd_w=150.0, valve_a_pct=20.0), 3)
        assert dev.command.heater_cmd_w == 150.0 and not dev.status_bits() & 0x4  # a new one does
