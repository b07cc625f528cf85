"""MPC settings from a file: ``hvac-mpc bench --mpc-settings`` and the daemon's ``[controller.settings]``."""
import json

import pytest

from hvac_mpc.benchmarks import bench
from hvac_mpc.contract import Command
from hvac_mpc.daemon.controllers import ControllerLoadError, load_controller
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.mpc_controller import MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings
from hvac_mpc.mpc.settings_file import read_settings_file, settings_with

TOML = """placement_dead_time_hold_s = 2.0
rti_step_fractions = [0.5, 0.25]
[ekf]
response_wait_c = 0.0
[ocp.weights]
volume_flow = 3.0
"""


def test_nested_fields_replaced_and_the_rest_kept(tmp_path):
    path = tmp_path / "mpc.toml"
    path.write_text(TOML)
    s = settings_with(MpcSettings(), read_settings_file(path))
    d = MpcSettings()
    assert s.placement_dead_time_hold_s == 2.0 and s.rti_step_fractions == (0.5, 0.25)
    assert s.ekf.response_wait_c == 0.0 and d.ekf.response_wait_c != 0.0
    assert s.ocp.weights.volume_flow == 3.0 and s.ocp.weights.supply_temp == d.ocp.weights.supply_temp
    assert s.ocp.stage_durations_s == d.ocp.stage_durations_s and s.ekf.dead_time_max_s == d.ekf.dead_time_max_s


def test_unknown_field_named_with_its_path_and_the_allowed_ones():
    with pytest.raises(InvalidSettings, match=r"MpcSettings\.ekf: unknown field\(s\) \['respons_wait_c'\].*allowed"):
        settings_with(MpcSettings(), {"ekf": {"respons_wait_c": 0.1}})


def test_value_out_of_range_names_the_field_and_changes_nothing():
    base = MpcSettings()
    with pytest.raises(InvalidSettings, match="response_wait_c"):
        settings_with(base, {"ekf": {"response_wait_c": -1.0}})
    assert base.ekf.response_wait_c == MpcSettings().ekf.response_wait_c


def test_bad_file_is_named(tmp_path):
    path = tmp_path / "mpc.toml"
    path.write_text("ekf = [")
    with pytest.raises(InvalidSettings, match="mpc.toml"):
        read_settings_file(path)


def _args(path):
    from hvac_mpc import cli
    return cli.build_parser().parse_args(["bench", "--mpc-settings", str(path)])


def test_bench_factory_builds_the_mpc_with_the_file(tmp_path):
    path = tmp_path / "mpc.json"
    path.write_text(json.dumps({"ekf": {"response_wait_c": 0.5}, "ocp": {"weights": {"volume_flow": 3.0}}}))
    make = bench.mpc_factory(settings=bench.mpc_settings_values(_args(path)))
    ctrl = make(Command(blower_power_w=40.0))
    assert ctrl.settings.ekf.response_wait_c == 0.5 and ctrl.settings.ocp.weights.volume_flow == 3.0
    assert ctrl.settings.initial_command.blower_power_w == 40.0


def test_bench_refuses_the_fields_it_sets_itself(tmp_path):
    path = tmp_path / "mpc.toml"
    path.write_text("deadline_s = 0.5\n")
    with pytest.raises(ValueError, match=r"--mpc-settings .*\['deadline_s'\]"):
        bench.mpc_settings_values(_args(path))


def test_bench_command_stops_on_a_bad_settings_file(tmp_path, capsys):
    from hvac_mpc import cli
    path = tmp_path / "mpc.toml"
    path.write_text("[ekf]\nresponse_wait_c = 99.0\n")
    rc = cli.main(["bench", "--quick", "--scenario", "summer_cooling_steps", "--no-plots",
                   "--out", str(tmp_path / "out"), "--mpc-settings", str(path)])
    assert rc == 2
    assert "response_wait_c" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_daemon_controller_takes_nested_settings():
    ctrl = load_controller("mpc", Parameters(), 1.0, {"ekf": {"response_wait_c": 0.3}, "rti_step_fractions": [0.5]})
    assert ctrl.settings.ekf.response_wait_c == 0.3 and ctrl.settings.rti_step_fractions == (0.5,)
    with pytest.raises(ControllerLoadError, match="unknown field"):
        load_controller("mpc", Parameters(), 1.0, {"ocp": {"horizn": 10}})
