"""The OPC UA backend against a real asyncua server on loopback (the simulated plant behind it):
control, link loss and reconnection, bad values caught by the sensor checks, safe stop, raw
signals, and the per-tick latency. About 30 s (an asyncua server takes ~4 s to start)."""

from __future__ import annotations

import statistics
import threading
import time

import pytest

from hvac_mpc.contract import INPUTS, Command
from hvac_mpc.models.plant import SimulatedPlant

pytestmark = pytest.mark.slow
asyncua = pytest.importorskip("asyncua", reason="the OPC UA backend needs the 'opcua' extra (asyncua)")

from hvac_mpc.benchmarks.daemon_campaign import free_port  # noqa: E402
from hvac_mpc.daemon.config import config_from_mapping  # noqa: E402
from hvac_mpc.daemon.io import BackendError  # noqa: E402
from hvac_mpc.daemon.loop import Daemon  # noqa: E402
from hvac_mpc.daemon.opcua import OpcUaBackend, OpcUaConfig  # noqa: E402
from hvac_mpc.daemon.opcua_sim import PlantOpcUaServer  # noqa: E402


def wait_until(pred, timeout_s: float, what: str, thread: threading.Thread | None = None) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return
        if thread is not None and not thread.is_alive():
            raise AssertionError(f"daemon ended while waiting for {what}")
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


class Recorder:
    """Tick hook: every logged sample, and the daemon's plant time."""

    def __init__(self):
        self.samples: list[dict] = []

    def __call__(self, daemon, sample):
        self.samples.append(sample)

    @property
    def last(self) -> dict:
        return self.samples[-1] if self.samples else {}

    def since(self, t_s: float) -> list[dict]:
        return [s for s in self.samples if s["time_s"] >= t_s]


def _config(tmp_path, name: str, endpoint: str, signals: str = "engineering", speedup: float = 25.0,
            reference=None):
    return config_from_mapping({
        "loop": {"speedup": speedup},
        "log": {"path": str(tmp_path / f"{name}.csv"), "fsync": False},
        "api": {"enabled": False},
        "controller": {"name": "mpc"},
        "backend": {"kind": "opcua", "opcua": {"endpoint": endpoint, "timeout_s": 0.3, "signals": signals}},
        "reference": reference or {"supply_temp_c": 27.0, "volume_flow_m3s": 0.02},
        "safety": {"reconnect_initial_s": 1.0, "reconnect_max_s": 4.0, "cooldown_max_s": 60.0},
    }, base_dir=tmp_path)


def test_daemon_controls_the_plant_over_opcua_through_outage_bad_values_and_safe_stop(tmp_path, capsys):
    server = PlantOpcUaServer(SimulatedPlant(seed=4), port=free_port(), heartbeat_timeout_s=3.0).start()
    rec = Recorder()
    daemon = Daemon(_config(tmp_path, "opcua", server.endpoint), tick_hook=rec)
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    try:
        # 1. control: heating towards 27 C through the OPC UA nodes (the heater body's ~90 s time
        #    constant makes this slow: the MPC on the simulated backend is at 23.7 C after 60 s)
        wait_until(lambda: rec.last.get("time_s", 0) >= 90, 60, "90 s of control", thread)
        s = rec.last
        assert s["connected"] and s["mode"] not in ("disconnected", "safe") and s["heater_cmd_w"] > 0
        assert s["controller"] == "mpc" and s["supply_temp_c"] > max(23.0, rec.samples[0]["supply_temp_c"] + 7.0), s
        assert abs(s["volume_flow_m3s"] - 0.02) < 0.002, s
        assert server.command.heater_cmd_w == pytest.approx(s["heater_cmd_w"])  # the device applies it
        # 2. link loss: server stopped
        server.stop()
        wait_until(lambda: not daemon.connected, 10, "the link loss", thread)
        t_lost = rec.last["time_s"]
        wait_until(lambda: rec.last["time_s"] >= t_lost + 10, 10, "10 s disconnected", thread)
        down = rec.since(t_lost + 1)
        assert down and all(x["mode"] == "disconnected" and x["heater_cmd_w"] == 0.0 for x in down)
        # 3. reconnection
        server.start()
        wait_until(lambda: daemon.connected, 30, "the reconnection", thread)
        t_back = rec.last["time_s"]
        wait_until(lambda: rec.last["time_s"] >= t_back + 30, 20, "30 s after reconnecting", thread)
        assert rec.last["mode"] not in ("disconnected", "safe") and rec.last["heater_cmd_w"] > 0
        # 4. bad values on the nodes: NaN flow, out-of-range heater outlet, no value (bad status)
        for signal, value, fault in (("volume_flow_m3s", float("nan"), "nan"),
                                     ("heater_outlet_temp_c", 500.0, "out_of_range"),
                                     ("volume_flow_m3s", None, "missing")):
            server.sensor_override[signal] = value
            t0 = rec.last["time_s"]
            wait_until(lambda: rec.last["time_s"] >= t0 + 5, 10, f"{signal} = {value}", thread)
            bad = rec.since(t0 + 2)
            assert all(x["heater_cmd_w"] == 0.0 and x["sensor_faults"].get(signal) == fault for x in bad), bad[-1]
            assert server.command.heater_cmd_w == 0.0
            del server.sensor_override[signal]
            t1 = rec.last["time_s"]
            wait_until(lambda: rec.last["time_s"] >= t1 + 20, 20, "recovery", thread)
            assert rec.last["heater_cmd_w"] > 0 and not rec.last["sensor_faults"]
        # 5. safe stop: heater off, blower on until cooled, then the blower to its minimum
        t_stop = rec.last["time_s"]
        daemon.request_stop("test")
        thread.join(60)
        assert not thread.is_alive() and daemon.exit_code == 0
    finally:
        daemon.request_stop("test")
        daemon.request_stop("test")
        thread.join(30)
        latency = list(getattr(daemon.backend, "latency_s", []))
        server.stop()
    shutdown = [x for x in rec.since(t_stop) if x["mode"] in ("shutdown", "stopped")]
    assert shutdown and all(x["heater_cmd_w"] == 0.0 for x in shutdown)
    assert all(x["blower_power_w"] >= 120.0 for x in shutdown[:-1]) and shutdown[-1]["mode"] == "stopped"
    assert server.command.heater_cmd_w == 0.0 and server.command.blower_power_w == pytest.approx(30.0)
    c = daemon.counters
    assert c["reconnects"] >= 1 and c["disconnected_ticks"] >= 10
    assert len(latency) > 200
    med, p99 = statistics.median(latency), sorted(latency)[int(0.99 * len(latency))]
    with capsys.disabled():
        print(f"\nOPC UA per-tick read + write latency over {len(latency)} ticks: median {med * 1e3:.2f} ms, "
              f"99th percentile {p99 * 1e3:.2f} ms, max {max(latency) * 1e3:.1f} ms (sample 1 s)")
    assert p99 < 0.1  # well below the 1 s sample


def test_opcua_raw_signals_decoded_by_the_device_and_format_mismatch_refused(tmp_path):
    from hvac_mpc.daemon.calibration import load_calibration

    cal = load_calibration()
    server = PlantOpcUaServer(SimulatedPlant(seed=6), port=free_port(), calibration=cal).start()
    written: dict[int, Command] = {}

    def hook(daemon, sample):
        written[(int(round(sample["time_s"])) + 1) & 0xFFFF] = Command(**{n: sample[n] for n in INPUTS})

    try:
        cfg = _config(tmp_path, "raw", server.endpoint, signals="raw", speedup=float("inf"))
        cfg = config_from_mapping({"loop": {"speedup": "max", "max_ticks": 30}, "api": {"enabled": False},
                                   "log": {"path": str(tmp_path / "raw.csv"), "fsync": False},
                                   "backend": {"kind": "opcua", "opcua": cfg.backend.opcua.model_dump()},
                                   "reference": {"supply_temp_c": 26.0, "volume_flow_m3s": 0.025},
                                   "safety": {"cooldown_max_s": 5.0}}, base_dir=tmp_path)
        daemon = Daemon(cfg, tick_hook=hook)
        assert daemon.run() == 0
        eng = OpcUaBackend(OpcUaConfig(endpoint=server.endpoint, timeout_s=0.3))
        with pytest.raises(BackendError, match="the device takes raw signals, the daemon is set to engineering"):
            eng.connect()
        eng.close()
        # a silent server (its event loop blocked, as behind a pulled cable): a read ends in timeout_s
        raw = OpcUaBackend(OpcUaConfig(endpoint=server.endpoint, timeout_s=0.3), calibration=cal)
        raw.connect()
        raw.read()
        server._loop.call_soon_threadsafe(time.sleep, 1.5)
        time.sleep(0.05)
        t0 = time.monotonic()
        with pytest.raises(BackendError, match="read failed"):
            raw.read()
        silent_s = time.monotonic() - t0
        time.sleep(1.6)
        raw.connect()  # the server answers again: reconnected
        assert raw.read().time_s > 0
        raw.close()
    finally:
        server.stop()
    received = [(hb, cmd) for hb, _, cmd in server.received if hb in written]
    assert len(received) >= 25 and any(c.heater_cmd_w > 0 for _, c in received)
    for hb, cmd in received:
        for n in INPUTS:
            assert getattr(cmd, n) == pytest.approx(getattr(written[hb], n), abs=1e-9), (hb, n)
    # the nodes carried duty cycles and volts, not W and %
    raws = [r for _, r, _ in server.received]
    assert all(0.04 <= r["valve_m_pct"] <= 0.07 and 0.0 <= r["heater_cmd_w"] <= 5.0 for r in raws)
    assert silent_s < 0.3 + 0.5, silent_s
