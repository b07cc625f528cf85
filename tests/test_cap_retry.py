"""The retry of a QP at OSQP's iteration cap (``MpcSettings.osqp_cap_retry_rho`` / ``osqp_cap_retry_share``;
docs/robustness.md sec. 2.40): the reserve's step down at 390 s on the independent literal-cooler box
(tests/test_reserve_step_down.py's run) with sec. 2.37's heat package F, whose change's first QP ends at OSQP's 1000
iterations without an answer and so falls back to the shifted plan."""

import pytest

from hvac_mpc.benchmarks.change_rho import reserve_run
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings


@pytest.mark.slow
def test_the_reserves_step_down_with_the_heat_package_is_answered_by_the_retry_at_the_cap():
    """Measured: the change's first QP at OSQP's cap ("maximum iterations reached", the step size 0.009 it started
    from) takes 150 iterations from 3e-3 warm-started at the capped iterate; its second QP (1000, solved inaccurate)
    460; no fallback, valve a 0.0 % (41.3 % on the shifted plan without the retry), IAE from 390 s 40.86 C s (46.43
    without)."""
    run = reserve_run(True, {"osqp_cap_retry_rho": 3e-3}, interface=False)
    assert run["fallback"] is None, run["fallback"]
    qps = run["changes"][0]["qps"]  # each OSQP solve of the step at 390 s, the retries included
    capped, retried = qps[0], qps[1]
    assert capped["iterations"] == 1000 and capped["status"] == "maximum iterations reached", capped
    assert retried["rho_start"] == 3e-3 and retried["iterations"] < 500 and retried["status"] == "solved", retried
    assert run["valve_a_pct"] < 10.0, run["valve_a_pct"]
    assert run["iae_cs"] < 44.0, run["iae_cs"]


def test_the_retry_settings_are_checked():
    for fields, named in ((dict(osqp_cap_retry_rho=-1.0), "osqp_cap_retry_rho"),
                          (dict(osqp_cap_retry_rho=1e7), "osqp_cap_retry_rho"),
                          (dict(osqp_cap_retry_share=1.5), "osqp_cap_retry_share"),
                          (dict(osqp_cap_retry_rho=3e-3, osqp_cap_retry_share=0.3), "both set"),
                          (dict(osqp_cap_retry_cold=1), "osqp_cap_retry_cold")):
        with pytest.raises(InvalidSettings, match=named):
            MpcSettings(**fields)
    s = MpcSettings()
    assert (s.osqp_cap_retry_rho, s.osqp_cap_retry_share, s.osqp_cap_retry_cold) == (0.0, 0.0, False)
    solver = MpcController(settings=MpcSettings(osqp_cap_retry_share=0.3, osqp_cap_retry_cold=True)).solver
    assert (solver.settings["cap_retry_share"], solver.settings["cap_retry_cold"]) == (0.3, True)
