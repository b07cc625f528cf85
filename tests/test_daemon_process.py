"""The daemon as a process (``python -m hvac_mpc daemon --config ...``) on the simulated plant in
accelerated time: references driven through the HTTP API and tracked (checked on /sample and in
the log), and the same over Modbus TCP with the server stopped and restarted mid-run. About 40 s."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np
import pytest

from hvac_mpc.models.measurement_log import read_log
from hvac_mpc.models.plant import SimulatedPlant
from hvac_mpc.benchmarks.daemon_campaign import (NOT_CONTROLLING, _request, check_log, free_port, process_config,
                                          start_daemon, wait_for)

pytestmark = pytest.mark.slow

REFERENCES = [
    {"supply_temp_c": 16.0, "volume_flow_m3s": 0.025},
    {"supply_temp_c": 23.0, "volume_flow_m3s": 0.04, "flow_m_m3s": 0.02, "flow_f_m3s": 0.01, "flow_w_m3s": 0.01},
    {"supply_temp_c": 13.0, "volume_flow_m3s": 0.045},
    {"supply_temp_c": 21.0, "volume_flow_m3s": 0.02},
]
SEGMENT_S = 150.0


def sample(port: int) -> dict:
    return _request(port, "GET", "/sample")[1] or {}


def wait_plant_time(port: int, t_s: float, proc, timeout_s: float = 60.0) -> dict:
    wait_for(lambda: sample(port).get("time_s", -1) >= t_s, timeout_s, f"plant time {t_s} s", proc)
    return sample(port)


def segments(log: dict) -> list[dict]:
    """Per reference change: settle times (|T err| <= 0.5 C, |V err| <= 10 %) and last-30-s errors."""
    rt, rv = log["ref_supply_temp_c"], log["ref_volume_flow_m3s"]
    modes = list(log["mode"])
    stop = modes.index("shutdown") if "shutdown" in modes else len(modes)
    starts = [int(k) for k in np.flatnonzero(np.diff(rt[:stop]) != 0) + 1]
    out = []
    for i, k in enumerate(starts):
        end = starts[i + 1] if i + 1 < len(starts) else stop
        e_t = np.abs(log["supply_temp_c"][k:end] - rt[k])
        e_v = np.abs(log["volume_flow_m3s"][k:end] - rv[k])

        def settle(ok):
            bad = np.flatnonzero(~ok)
            return 0.0 if len(bad) == 0 else (float(bad[-1] + 1) if bad[-1] + 1 < len(ok) else np.inf)

        out.append({"ref": (rt[k], rv[k]), "n": end - k, "settle_t_s": settle(e_t <= 0.5),
                    "settle_v_s": settle(e_v <= 0.1 * rv[k]), "err_t_c": float(e_t[-30:].mean()),
                    "err_v_m3s": float(e_v[-30:].mean())})
    return out


def _fresh(workdir: Path, name: str) -> None:
    for suffix in (".csv", ".port"):
        (workdir / f"{name}{suffix}").unlink(missing_ok=True)


def test_daemon_process_tracks_references_from_the_api(tmp_path, capsys):
    _fresh(tmp_path, "track")
    cfg = process_config(tmp_path, "track", "mpc", speedup=40.0,
                         reference={"supply_temp_c": 20.0, "volume_flow_m3s": 0.03})
    proc = start_daemon(cfg)
    try:
        wait_for(lambda: (tmp_path / "track.port").exists(), 60, "the API port", proc)
        port = int((tmp_path / "track.port").read_text())
        assert _request(port, "GET", "/health")[0] == 200
        wait_plant_time(port, 60.0, proc)
        finals = []
        for ref in REFERENCES:
            code, body = _request(port, "PUT", "/reference", json.dumps(ref).encode(),
                                  token=(tmp_path / "track.token").read_text().strip())
            assert code == 200 and body["accepted"]["supply_temp_c"] == ref["supply_temp_c"]
            t0 = sample(port)["time_s"]
            finals.append((ref, wait_plant_time(port, t0 + SEGMENT_S, proc)))
        status = _request(port, "GET", "/status")[1]
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err.decode()[-2000:]
    assert status["counters"]["reference_updates"] == len(REFERENCES) and status["controller"] == "mpc"
    for ref, s in finals:  # the latest sample, as the comfort algorithm sees it
        assert abs(s["supply_temp_c"] - ref["supply_temp_c"]) < 0.6, (ref, s)
        assert abs(s["volume_flow_m3s"] - ref["volume_flow_m3s"]) < 0.004, (ref, s)
        assert s["controller"] == "mpc" and s["mode"] not in NOT_CONTROLLING
    log = read_log(tmp_path / "track.csv")
    assert check_log(tmp_path / "track.csv") == []
    segs = segments(log)
    with capsys.disabled():
        print("\ntracking through the API (MPC, 40x real time):")
        for s in segs:
            print(f"  ref {s['ref'][0]:5.1f} C {s['ref'][1]:.3f} m3/s: settled T {s['settle_t_s']:.0f} s, "
                  f"V {s['settle_v_s']:.0f} s; last 30 s |err| {s['err_t_c']:.3f} C, {s['err_v_m3s'] * 1000:.2f} l/s")
    assert [s["ref"][0] for s in segs] == [r["supply_temp_c"] for r in REFERENCES]
    for s in segs:
        assert s["n"] >= SEGMENT_S - 5
        assert s["settle_v_s"] <= 60.0 and s["settle_t_s"] <= 90.0, s
        assert s["err_t_c"] < 0.2 and s["err_v_m3s"] < 0.002, s


def test_daemon_process_over_modbus_survives_server_stop_and_restart(tmp_path, capsys):
    pytest.importorskip("pymodbus", reason="the Modbus backend needs the 'fieldbus' extra (pymodbus)")
    from hvac_mpc.daemon.modbus_sim import PlantModbusServer

    _fresh(tmp_path, "modbus")
    mport = free_port()
    server = PlantModbusServer(SimulatedPlant(seed=5), port=mport, watchdog_samples=5).start()
    cfg = process_config(tmp_path, "modbus", "mpc", speedup=40.0,
                         reference={"supply_temp_c": 27.0, "volume_flow_m3s": 0.02},
                         extra={"backend": {"kind": "modbus", "modbus": {"port": mport, "timeout_s": 0.2}},
                                "safety": {"reconnect_initial_s": 1.0, "reconnect_max_s": 8.0}})
    proc = start_daemon(cfg)
    try:
        wait_for(lambda: (tmp_path / "modbus.port").exists(), 60, "the API port", proc)
        port = int((tmp_path / "modbus.port").read_text())
        s = wait_plant_time(port, 120.0, proc)
        assert s["connected"] and s["heater_cmd_w"] > 0, s  # heating through the fieldbus
        server.stop()
        t_stop = server.history[-1][0]  # the plant's last written sample (the daemon's log may lag it)
        wait_for(lambda: not _request(port, "GET", "/status")[1]["connected"], 30, "the link loss", proc)
        t_lost = sample(port)["time_s"]  # the link is known lost from here at the latest
        s = wait_plant_time(port, t_lost + 41.0, proc)
        assert s["mode"] == "disconnected" and s["heater_cmd_w"] == 0.0 and s["supply_temp_c"] is None
        assert _request(port, "GET", "/health")[0] == 200  # the daemon keeps running
        t_start = sample(port)["time_s"]  # the outage lasts at least until here
        server.start()
        wait_for(lambda: _request(port, "GET", "/status")[1]["connected"], 30, "the reconnection", proc)
        s = wait_plant_time(port, t_start + 60.0, proc)
        assert s["mode"] not in NOT_CONTROLLING and s["heater_cmd_w"] > 0, s
        status = _request(port, "GET", "/status")[1]
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        server.stop()
    assert proc.returncode == 0, err.decode()[-2000:]
    c = status["counters"]
    assert c["reconnects"] >= 1 and c["disconnected_ticks"] >= 40 and c["backend_errors"] >= 1
    assert check_log(tmp_path / "modbus.csv") == []
    log = read_log(tmp_path / "modbus.csv")
    down = log["mode"] == "disconnected"
    assert np.all(log["heater_cmd_w"][down] == 0.0) and np.all(np.isnan(log["supply_temp_c"][down]))
    # the plant side: heater held for the I/O watchdog's 5 samples, then off until the link returned
    held = [h for h in server.history if t_stop + 7 <= h[0] <= t_start]
    assert held and all(h[1] == 0.0 for h in held)
    with capsys.disabled():
        print(f"\nModbus outage: {int(down.sum())} samples disconnected, reconnects {c['reconnects']}, "
              f"backend errors {c['backend_errors']}, plant samples under the I/O watchdog {len(held)}")
