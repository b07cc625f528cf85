"""OSQP's options of the real-time iteration that benchmarks/osqp_restart.py compares: further OSQP settings
(``RtiOsqpSolver.set_osqp_options``) and the multipliers restarted at a reference change
(``restart_duals_on_change``)."""

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings

#: The solve-time loop's first two references, the second from step 3 on.
CHANGE_AT = 3
SCENARIO = ((0.0, solve_time.SCENARIO[0][1]), (float(CHANGE_AT), solve_time.SCENARIO[1][1]))


class _Duals:
    """Stands in for the solver's OSQP calls and keeps, per QP, the multipliers its warm start was given."""

    def __init__(self, core):
        self.core, self.given = core, []

    def warm_start(self, x, y=None):
        self.given.append(None if y is None else np.array(y))
        self.core.warm_start(x, y)

    def __getattr__(self, name):
        return getattr(self.core, name)


def _run(restart: bool, steps: int = CHANGE_AT + 2):
    ctrl = MpcController(settings=MpcSettings(codegen=False, deadline_s=3600.0))
    ctrl.solver.restart_duals_on_change = restart
    loop = solve_time.Loop(ctrl, seed=7, scenario=SCENARIO)
    ctrl.solver._core = rec = _Duals(ctrl.solver._core)
    qps = [loop.step(k).stats["qp_solves"] for k in range(steps)]
    return qps, rec.given


def test_the_multipliers_restart_only_for_the_first_qp_of_a_reference_change():
    qps, given = _run(restart=True)
    assert qps[CHANGE_AT] == 2 and all(n == 1 for n in qps[1:CHANGE_AT] + qps[CHANGE_AT + 1:])
    first_of_change = sum(qps[:CHANGE_AT])
    restarted = [i for i, y in enumerate(given) if y is not None]
    assert restarted == [first_of_change] and not given[first_of_change].any()
    assert given[first_of_change].size == MpcController(settings=MpcSettings(codegen=False)).solver.m
    _, kept = _run(restart=False)
    assert all(y is None for y in kept)


def test_further_osqp_settings_reach_osqp_and_an_unknown_name_is_refused():
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    with pytest.raises(ValueError, match="adaptive_rho_intervall"):
        ctrl.solver.set_osqp_options(adaptive_rho_intervall=25)
    ctrl.solver.set_osqp_options(adaptive_rho_interval=25)
    assert ctrl.solver.solver.settings.adaptive_rho_interval == 25
    assert ctrl.solver.settings["adaptive_rho_interval"] == 25
    loop = solve_time.Loop(ctrl, seed=7)
    assert all(loop.step(k).stats["fallback"] is None for k in range(3))
    assert ctrl.solver.solver.settings.adaptive_rho_interval == 25  # kept through the controller's reset
