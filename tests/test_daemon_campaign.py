"""The daemon's fault campaign (hvac_mpc.benchmarks.daemon_campaign): sensor NaN/stuck/out of range/
missing/stale/wrong value, controller failure/NaN/missed deadline/solver failure, backend
disconnect (injected and a real Modbus server stopped and restarted), a controller driving the
flow below the heater minimum, a fatal error, hostile API input (token, content type, Host and
Origin, overflow, slow headers and bodies), 16 and 200 slow-header connections (200 also against
the daemon process at real time), the disk full for 60 s, log rotation, SIGKILL at every step of
the tail repair of a 300 MB log and at random moments, every bad configuration and calibration
file, operator modes switched over the real Modbus server, the systemd watchdog with the loop
hung, the device's heartbeat watchdog after SIGKILL of the daemon, the MPC over a real OPC UA
server through link loss, bad values and the safe stop, SIGKILL with a restart, SIGTERM and
SIGINT. Every logged sample is checked for safety; the counts are printed. About 100 s."""

from __future__ import annotations

import logging

import pytest

from hvac_mpc.benchmarks.daemon_campaign import format_report, run_campaign

pytestmark = pytest.mark.slow

pytest.importorskip("pymodbus", reason="the Modbus scenarios need the 'fieldbus' extra (pymodbus)")
pytest.importorskip("asyncua", reason="the OPC UA scenario needs the 'opcua' extra (asyncua)")


def test_fault_campaign_keeps_actuators_safe(tmp_path, capsys):
    logging.getLogger("hvac_mpc.daemon").setLevel(logging.CRITICAL)
    result = run_campaign(tmp_path)
    with capsys.disabled():
        print("\n" + format_report(result))
    counts = result["counts"]
    failed = {o.name: o.violations for o in result["outcomes"] if not o.ok}
    assert failed == {}
    assert counts["violations"] == 0 and counts["passed"] == counts["scenarios"]
    by = counts["by_category"]
    assert by["sensor"]["tried"] == 19 and by["controller"]["tried"] == 4 and by["process"]["tried"] == 4
    assert by["api"]["tried"] >= 50 and by["backend"]["tried"] == 2
    assert by["log"]["tried"] == 3 and by["config"]["tried"] == 11 and by["modes"]["tried"] == 1
    assert by["calibration"]["tried"] == 6 and by["watchdog"]["tried"] == 2 and by["opcua"]["tried"] == 1
    named = {o.name: o for o in result["outcomes"]}
    assert {"api_slow_header_flood_16", "api_slow_header_flood_200", "api_slow_header_flood_200_process_1x",
            "api_no_token", "api_foreign_host", "api_foreign_origin", "api_no_content_type",
            "api_integer_10_pow_400", "log_disk_full_60s", "log_rotation_by_size", "systemd_watchdog_loop_hang",
            "device_heartbeat_after_sigkill", "opcua_control_link_loss_bad_values_safe_stop"} <= set(named)
    repair = named["log_sigkill_during_tail_repair_300MB"]
    assert "5 kills at the repair's steps (begin, found, truncated, synced, reopened)" in repair.notes
    assert "committed bytes changed 0 times" in repair.notes
    injected = counts["injected_fault_ticks"]
    for kind in ("sensor:nan", "sensor:stuck", "sensor:out_of_range", "sensor:missing", "sensor:stale",
                 "controller:fail", "controller:nan", "controller:delay", "controller:solver",
                 "backend:disconnect", "daemon:fatal", "process:sigkill", "process:SIGTERM", "log:enospc",
                 "log:torn_row", "opcua:server_stopped"):
        assert injected.get(kind, 0) > 0, kind
    assert all(o.detected > 0 for o in result["outcomes"]), [o.name for o in result["outcomes"] if not o.detected]
