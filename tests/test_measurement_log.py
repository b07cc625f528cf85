import numpy as np
import pytest

from hvac_mpc.models.measurement_log import COLUMNS, LogFormatError, LogWriter, read_log, write_log


def row(t):
    return {"time_s": t, "blower_power_w": 100.0, "heater_cmd_w": 0.0, "valve_a_pct": 50.0, "valve_m_pct": 100.0,
            "valve_f_pct": 100.0, "valve_w_pct": 100.0, "hvac_inlet_temp_c": 25.0, "volume_flow_m3s": 0.02,
            "supply_temp_c": 15.0 + t, "mode": "cooling"}


def test_append_after_restart_and_partial_line_dropped(tmp_path):
    path = tmp_path / "log.csv"
    with LogWriter(path) as w:
        w.write(row(0.0))
        w.write(row(1.0))
    with path.open("a") as fh:  # a crash mid-row
        fh.write("2.0,100.0,0.0")
    with LogWriter(path) as w:
        w.write(row(3.0))
    log = read_log(path)
    np.testing.assert_array_equal(log["time_s"], [0.0, 1.0, 3.0])
    assert np.isnan(log["water_temp_c"]).all()
    assert list(log["mode"]) == ["cooling"] * 3


def test_mapping_and_missing_columns(tmp_path):
    path = tmp_path / "lab.csv"
    data = {c: [1.0, 2.0] for c in COLUMNS[:10]}
    write_log(path, data)
    text = path.read_text().replace("supply_temp_c", "T_supply")
    path.write_text(text)
    with pytest.raises(LogFormatError, match="supply_temp_c"):
        read_log(path)
    log = read_log(path, mapping={"T_supply": "supply_temp_c"})
    np.testing.assert_array_equal(log["supply_temp_c"], [1.0, 2.0])


def test_unknown_column_rejected(tmp_path):
    with pytest.raises(LogFormatError, match="bogus"):
        LogWriter(tmp_path / "x.csv", columns=("time_s", "bogus"))
