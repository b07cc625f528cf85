"""The OPC UA backend against a real asyncua server on loopback (the simulated plant behind it): raw
signals and a silent server. Control, link loss and reconnection, bad values caught by the sensor
checks, the safe stop and the per-tick latency are a scenario of the fault campaign
(hvac_mpc.benchmarks.daemon_campaign ``opcua_link_faults``). About 10 s (an asyncua server takes
~4 s to start)."""

from __future__ import annotations

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
