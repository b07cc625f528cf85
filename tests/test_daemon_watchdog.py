"""Watchdogs: systemd notifications (a bound AF_UNIX datagram socket stands in for systemd) and the
device-side heartbeat watchdog of the simulated Modbus device after the daemon is killed."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
import uuid
from pathlib import Path

import pytest

from hvac_mpc.contract import Command, StepResult
from hvac_mpc.daemon.config import config_from_mapping
from hvac_mpc.daemon.loop import Daemon
from hvac_mpc.daemon.watchdog import Notifier, SystemdConfig, socket_address, watchdog_timeout_s
from hvac_mpc.models.plant import SimulatedPlant


class NotifySocket:
    """systemd's side: a bound datagram socket collecting (monotonic time, message) pairs."""

    def __init__(self, path: str):
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


class HangingBackend:
    """The simulated plant as a backend whose write blocks while ``hang`` is set (a fieldbus call
    without a timeout): the loop itself hangs."""

    def __init__(self):
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


def test_systemd_ready_pings_while_healthy_none_while_hung_stopping_at_shutdown(tmp_path, monkeypatch):
    path = str(tmp_path / "notify.sock")
    systemd = NotifySocket(path)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    backend = HangingBackend()
    daemon = _daemon(tmp_path, "hang", backend)
    thread = _run(daemon)
    try:
        time.sleep(1.0)  # healthy: READY, then pings every 0.1 s
        healthy_pings = len(systemd.times("WATCHDOG=1"))
        backend.hang.set()
        time.sleep(0.3)
        t_hang = time.monotonic()
        time.sleep(1.5)  # the loop is stuck in write()
        ticks_during_hang = daemon.tick
        backend.hang.clear()
        backend.release.set()
        time.sleep(0.6)  # healthy again
        daemon.request_stop("test")
        thread.join(20.0)
    finally:
        backend.release.set()
        daemon.request_stop("test")
        daemon.request_stop("test")
        thread.join(20.0)
        time.sleep(0.1)
        systemd.close()
    assert not thread.is_alive()
    ready, pings, stopping = systemd.times("READY=1"), systemd.times("WATCHDOG=1"), systemd.times("STOPPING=1")
    assert len(ready) == 1 and len(stopping) == 1
    assert healthy_pings >= 5, systemd.messages  # ~9 expected in 0.9 s at 0.1 s
    # the last tick before the hang finished about t_hang - 0.3; the stall limit is 0.5 s, so no
    # ping from t_hang + 0.5 (a margin for a slow last tick) until the loop ran again
    hung = [t for t in pings if t_hang + 0.5 <= t <= t_hang + 1.5]
    assert hung == [], f"{len(hung)} pings while the loop hung"
    assert daemon.tick > ticks_during_hang
    assert any(t > t_hang + 1.5 for t in pings), "pings did not resume once the loop ran again"
    assert ready[0] < pings[0] and stopping[0] > max(t for t in pings if t < stopping[0])


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
def test_sigkill_daemon_modbus_device_switches_heater_off_within_heartbeat_timeout(tmp_path):
    pytest.importorskip("pymodbus", reason="the Modbus backend needs the 'fieldbus' extra (pymodbus)")
    from hvac_mpc.benchmarks.daemon_campaign import free_port, process_config, start_daemon, wait_for
    from hvac_mpc.daemon.modbus_sim import PlantModbusServer

    timeout_s = 0.5
    mport = free_port()
    server = PlantModbusServer(SimulatedPlant(seed=5), port=mport, heartbeat_timeout_s=timeout_s).start()
    cfg = process_config(tmp_path, "kill", "baseline", speedup=20.0,
                         reference={"supply_temp_c": 30.0, "volume_flow_m3s": 0.02},
                         extra={"backend": {"kind": "modbus", "modbus": {"port": mport, "timeout_s": 0.2}}})
    proc = start_daemon(cfg)
    try:
        wait_for(lambda: server.command.heater_cmd_w > 100.0, 90, "the heater on through Modbus", proc)
        blower_before = server.command.blower_power_w
        assert not server.heartbeat_tripped
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        wait_for(lambda: server.heartbeat_tripped, 5, "the heartbeat watchdog")
        t_off = server.heartbeat_trips[-1]
        cmd = server.command
        time.sleep(0.3)
        status = server.input_registers()[10]
    finally:
        if proc.poll() is None:
            proc.kill()
        server.stop()
    print(f"\nheater {cmd.heater_cmd_w} W, blower {cmd.blower_power_w} W {t_off - t_kill:.2f} s after SIGKILL "
          f"(heartbeat timeout {timeout_s} s)")
    assert t_off - t_kill <= timeout_s + 0.25  # the timeout, plus the device's 50 ms check and scheduling
    assert cmd.heater_cmd_w == 0.0 and cmd.blower_power_w >= max(blower_before, 120.0) - 1e-9
    assert cmd.valve_a_pct == 100.0 and status & 0x4
    assert server.command.heater_cmd_w == 0.0  # held off: nobody moved the heartbeat


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
