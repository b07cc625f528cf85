"""Actuator calibration: thesis table 1 round trip, the device decoding the daemon's raw
registers within one count (real Modbus server on loopback), and clear errors for bad files."""

from __future__ import annotations


import pytest

from hvac_mpc.contract import INPUTS, Command
from hvac_mpc.daemon.calibration import (CalibrationError, calibration_from_mapping, load_calibration)
from hvac_mpc.daemon.modbus import STATUS_RAW, decode_command, encode_command
from hvac_mpc.models.plant import SimulatedPlant

#: Thesis table 1, PPM duty cycle (open, closed), typed in from the thesis for this check.
TABLE_1 = {"valve_a_pct": (0.1, 0.055), "valve_w_pct": (0.06, 0.1), "valve_m_pct": (0.07, 0.04),
           "valve_f_pct": (0.1, 0.075)}


def test_thesis_table_1_round_trip_both_directions():
    cal = load_calibration()
    for name, (open_, closed) in TABLE_1.items():
        m = cal.actuators[name]
        assert m.to_raw(100.0) == pytest.approx(open_, abs=1e-12)
        assert m.to_raw(0.0) == pytest.approx(closed, abs=1e-12)
        assert m.to_eng(open_) == pytest.approx(100.0) and m.to_eng(closed) == pytest.approx(0.0)
        assert m.reversed == (open_ < closed)
        for pct in (0.0, 12.5, 50.0, 87.3, 100.0):  # through the fieldbus counts and back
            assert abs(m.from_count(m.to_count(pct)) - pct) <= m.eng_per_count(pct)
    assert [n for n in TABLE_1 if cal.actuators[n].reversed] == ["valve_w_pct"]
    # the same through the Modbus holding registers the daemon writes and the device decodes: 0 % and
    # 100 % are table 1's duty cycles to the count (1e-5), and decode back to 0 % and 100 %
    for name, (open_, closed) in TABLE_1.items():
        i = INPUTS.index(name)
        for pct, duty in ((100.0, open_), (0.0, closed)):
            regs = encode_command(Command(**{name: pct}), 0, cal)
            assert regs[i] == round(duty / 1e-5)
            assert getattr(decode_command(regs, cal)[0], name) == pytest.approx(pct, abs=1e-9)
    # a raw signal rises with the opening for a, m, f and falls for w
    assert cal.actuators["valve_w_pct"].to_raw(25.0) > cal.actuators["valve_w_pct"].to_raw(75.0)
    assert cal.actuators["valve_m_pct"].to_raw(25.0) < cal.actuators["valve_m_pct"].to_raw(75.0)
    assert cal.actuators["heater_cmd_w"].to_raw(240.0) == pytest.approx(5.0)
    assert cal.actuators["blower_power_w"].to_raw(150.0) == pytest.approx(0.5)
    for name in ("heater_cmd_w", "blower_power_w"):
        assert "ASSUMPTION" in cal.actuators[name].source
    for name in TABLE_1:
        assert "table 1" in cal.actuators[name].source


def test_modbus_raw_registers_decode_to_the_engineering_command_within_one_count():
    cal = load_calibration()
    cmds = [Command(30.0, 0.0, 0.0, 0.0, 0.0, 0.0), Command(300.0, 240.0, 100.0, 100.0, 100.0, 100.0),
            Command(151.3, 97.77, 33.3, 66.6, 12.34, 99.99)]
    for cmd in cmds:
        regs = encode_command(cmd, 7, cal)
        back, hb = decode_command(regs, cal)
        assert hb == 7
        for n in INPUTS:
            v = getattr(cmd, n)
            assert abs(getattr(back, n) - v) <= cal.actuators[n].eng_per_count(v) + 1e-12, n
    # servo counts are duty cycles in 1e-5: valve w open is 6000, closed 10000
    assert encode_command(Command(valve_w_pct=100.0), 0, cal)[5] == 6000
    assert encode_command(Command(valve_w_pct=0.0), 0, cal)[5] == 10000


def test_daemon_writes_raw_signals_through_the_modbus_server_and_the_device_decodes_them(tmp_path):
    pytest.importorskip("pymodbus", reason="the Modbus backend needs the 'fieldbus' extra (pymodbus)")
    from hvac_mpc.benchmarks.daemon_campaign import free_port
    from hvac_mpc.daemon.config import config_from_mapping
    from hvac_mpc.daemon.loop import Daemon
    from hvac_mpc.daemon.modbus_sim import PlantModbusServer

    cal = load_calibration()
    port = free_port()
    server = PlantModbusServer(SimulatedPlant(seed=2), port=port, calibration=cal).start()
    written: dict[int, Command] = {}

    def hook(daemon, sample):
        written[(int(round(sample["time_s"])) + 1) & 0xFFFF] = Command(**{n: sample[n] for n in INPUTS})

    base = {"loop": {"speedup": "max", "max_ticks": 40}, "api": {"enabled": False},
            "log": {"path": str(tmp_path / "raw.csv"), "fsync": False},
            "reference": {"supply_temp_c": 26.0, "volume_flow_m3s": 0.025},
            "safety": {"cooldown_max_s": 5.0}}
    try:
        cfg = config_from_mapping({**base, "backend": {"kind": "modbus", "modbus": {"port": port,
                                                                                    "signals": "raw"}}},
                                  base_dir=tmp_path)
        daemon = Daemon(cfg, tick_hook=hook)
        assert daemon.run() == 0
        assert server.input_registers()[10] & STATUS_RAW
        # the same device with a daemon set to engineering values: refused, nothing written
        writes = server.writes
        cfg2 = config_from_mapping({**base, "log": {"path": str(tmp_path / "eng.csv"), "fsync": False},
                                    "loop": {"speedup": "max", "max_ticks": 3},
                                    "backend": {"kind": "modbus", "modbus": {"port": port}}}, base_dir=tmp_path)
        d2 = Daemon(cfg2)
        d2.run()
    finally:
        server.stop()
    assert server.writes == writes and d2.counters["backend_errors"] >= 1 and d2.counters["primary_ticks"] == 0
    received = [(hb, cmd) for hb, _, cmd in server.received if hb in written]
    assert len(received) >= 35
    assert any(c.heater_cmd_w > 0 for _, c in received)  # heating: the heater channel carried a value
    for hb, cmd in received:
        sent = written[hb]
        for n in INPUTS:
            v = getattr(sent, n)
            assert abs(getattr(cmd, n) - v) <= cal.actuators[n].eng_per_count(v) + 1e-12, (hb, n, v, getattr(cmd, n))


GOOD_SERVO = {"signal": "servo_duty", "open": 0.1, "closed": 0.055}
GOOD = {"actuators": {
    "blower_power_w": {"signal": "pwm_duty", "eng": [0.0, 300.0], "raw": [0.0, 1.0]},
    "heater_cmd_w": {"signal": "voltage_v", "device_range": [0.0, 5.0], "eng": [0.0, 240.0], "raw": [0.0, 5.0]},
    **{n: GOOD_SERVO for n in TABLE_1}}}


def _with(path: tuple, value) -> dict:
    from hvac_mpc.benchmarks.daemon_campaign import with_changed

    return with_changed(GOOD, path, value)


@pytest.mark.parametrize("data, expected", [
    (_with(("actuators", "heater_cmd_w", "raw"), [0.0, 2.0, 1.5, 5.0]), r"heater_cmd_w\.raw: .*not strictly monotone"),
    (_with(("actuators", "heater_cmd_w", "eng"), [0.0, 100.0, 100.0, 240.0]), r"heater_cmd_w\.eng: .*not strictly increasing"),
    (_with(("actuators", "heater_cmd_w", "raw"), [0.0, 6.0]), r"heater_cmd_w: .*raw \[6.0\] outside the device's range \[0.0, 5.0\]"),
    (_with(("actuators", "valve_w_pct"), {"signal": "servo_duty", "open": 0.2, "closed": 0.1}), r"valve_w_pct: .*raw \[0.2\] outside"),
    (_with(("actuators", "valve_a_pct"), {"signal": "servo_duty", "open": 0.1}), r"valve_a_pct: .*open and closed go together"),
    (_with(("actuators", "blower_power_w", "eng"), [50.0, 300.0]), r"blower_power_w\.eng \[50.0, 300.0\] does not cover the command range \[30.0, 300.0\]"),
    (_with(("actuators", "valve_f_pct"), None), r"missing actuator\(s\) \['valve_f_pct'\]"),
    (_with(("actuators", "fan_pct"), GOOD_SERVO), r"unknown actuator\(s\) \['fan_pct'\]"),
    (_with(("actuators", "heater_cmd_w", "signal"), "volts"), r"heater_cmd_w\.signal: Input should be 'servo_duty'"),
    (_with(("actuators", "heater_cmd_w", "gain"), 2.0), r"heater_cmd_w\.gain: Extra inputs are not permitted"),
    (_with(("actuators", "heater_cmd_w", "raw"), [0.0, float("nan")]), r"heater_cmd_w\.raw: .*finite"),
    (_with(("actuators", "heater_cmd_w", "raw"), [0.0, 2.5, 5.0]), r"heater_cmd_w: .*eng has 2 points, raw 3"),
    (_with(("actuators", "heater_cmd_w", "device_range"), [0.0, 50.0]), r"heater_cmd_w: .*exceeds the voltage_v stage"),
    (_with(("sensors",), {"cabin_co2_ppm": {"signal": "voltage_v", "raw": [0, 10], "eng": [0, 5000]}}),
     r"sensors: .*unknown sensor\(s\) \['cabin_co2_ppm'\]"),
])
def test_bad_calibrations_are_refused_with_the_field_named(data, expected):
    with pytest.raises(CalibrationError, match=expected):
        calibration_from_mapping(data)


def test_bad_calibration_files_give_clear_errors(tmp_path):
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    bad_toml = tmp_path / "bad.toml"
    bad_toml.write_text("[actuators\n")
    cases = [(tmp_path / "missing.toml", "no such calibration file"), (tmp_path, "not a readable text file"),
             (binary, "not a readable text file"), (bad_toml, "not valid TOML")]
    for path, expected in cases:
        with pytest.raises(CalibrationError, match=expected):
            load_calibration(path)


def test_sensor_maps_decode_raw_readings_and_keep_over_range_implausible():
    cal = calibration_from_mapping({**GOOD, "sensors": {
        "volume_flow_m3s": {"signal": "voltage_v", "raw": [0.0, 10.0], "eng": [0.0, 0.1]},
        "heater_outlet_temp_c": {"signal": "current_ma", "raw": [4.0, 20.0], "eng": [-50.0, 150.0]}}})
    assert cal.sensor_to_eng("volume_flow_m3s", 3.0) == pytest.approx(0.03)
    assert cal.sensor_to_eng("heater_outlet_temp_c", 12.0) == pytest.approx(50.0)
    assert cal.sensor_to_eng("heater_outlet_temp_c", 0.0) == pytest.approx(-100.0)  # wire break: implausible
    assert cal.sensor_to_eng("supply_temp_c", 21.5) == 21.5  # no map: reported in its unit
    assert cal.sensor_to_eng("volume_flow_m3s", None) is None
    assert cal.sensor_to_raw("heater_outlet_temp_c", 50.0) == pytest.approx(12.0)


def test_daemon_refuses_a_bad_calibration_file_at_configuration(tmp_path):
    from hvac_mpc.daemon.config import ConfigError, config_from_mapping

    bad = tmp_path / "cal.toml"
    bad.write_text('[actuators.valve_a_pct]\nsignal = "servo_duty"\nopen = 0.3\nclosed = 0.055\n')
    data = {"backend": {"kind": "modbus", "modbus": {"signals": "raw"}}, "calibration": {"file": "cal.toml"}}
    with pytest.raises(ConfigError, match=r"calibration\.file: .*cal.toml: .*valve_a_pct: .*raw \[0.3\] outside"):
        config_from_mapping(data, base_dir=tmp_path)
    assert list(tmp_path.iterdir()) == [bad]  # nothing written
    with pytest.raises(ConfigError, match=r"calibration\.file: .*no such calibration file"):
        config_from_mapping({**data, "calibration": {"file": "nope.toml"}}, base_dir=tmp_path)
    # engineering signals: the calibration file is not used, so not required
    assert config_from_mapping({"calibration": {"file": "nope.toml"}}, base_dir=tmp_path).calibration.file


def test_modbus_raw_sensor_registers_round_trip_within_one_count():
    from hvac_mpc.contract import Measurement
    from hvac_mpc.daemon.modbus import decode_measurement, encode_measurement, raw_sensor_registers, sensors_from_raw

    cal = calibration_from_mapping({**GOOD, "sensors": {
        "volume_flow_m3s": {"signal": "voltage_v", "raw": [0.0, 10.0], "eng": [0.0, 0.1]},
        "heater_outlet_temp_c": {"signal": "current_ma", "raw": [4.0, 20.0], "eng": [-50.0, 150.0]}}})
    m = Measurement(time_s=12.0, supply_temp_c=18.25, volume_flow_m3s=0.03117, hvac_inlet_temp_c=25.0,
                    heater_outlet_temp_c=63.4, heater_power_w=None)
    regs = raw_sensor_registers(encode_measurement(m), m, cal)
    assert regs[3] == 3117  # 3.117 V in mV
    back = sensors_from_raw(regs, decode_measurement(regs)[0], cal)
    assert back.volume_flow_m3s == pytest.approx(0.03117, abs=0.1 / 10.0 * 1e-3)
    assert back.heater_outlet_temp_c == pytest.approx(63.4, abs=200.0 / 16.0 * 1e-3)
    assert back.supply_temp_c == pytest.approx(18.25) and back.heater_power_w is None
