"""A deterministic bound on a step's OSQP iterations (``MpcSettings.osqp_accept_max_iter``): the iterate at
the cap is the QP's answer, so a low cap bounds the step's QP work without falling back."""

import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings


def _loop(settings: MpcSettings, steps: int = 34):
    loop = solve_time.Loop(MpcController(settings=settings), seed=7)
    rows = []
    for k in range(steps):
        st = loop.step(k).stats
        rows.append((st["iterations"], st["qp_solves"], st["fallback"], str(st["status"])))
    return rows


def test_capped_qps_answer_within_the_cap_and_without_the_flag_they_fall_back():
    """OSQP capped at 20 iterations on purpose, so that QPs end at the cap; the retry at the cap
    (``osqp_cap_retry_rho``, 3e-3 and not on a cold start by default since docs/robustness.md sec. 2.44, measured in
    sec. 2.40) set off explicitly, because it solves such a QP once more and adds its own iterations, so
    a step's iterations would no longer be bounded by the cap this test measures."""
    cap = 20
    accepted = _loop(MpcSettings(codegen=False, osqp_max_iter=cap, osqp_accept_max_iter=True, osqp_cap_retry_rho=0.0))
    assert all(fallback is None for _, _, fallback, _ in accepted)
    assert all(its <= qps * cap for its, qps, _, _ in accepted)
    capped = [k for k, (its, qps, _, _) in enumerate(accepted) if its == qps * cap]
    assert len(capped) >= 2 and any("maximum iterations" in accepted[k][3] for k in capped)
    # the same cap without the flag: a QP at the cap is a failure and the fallback chain answers
    refused = _loop(MpcSettings(codegen=False, osqp_max_iter=cap, osqp_accept_max_iter=False, osqp_cap_retry_rho=0.0))
    assert any(fallback is not None for _, _, fallback, _ in refused)


def _inexact_step(heater_w: float, inexact: bool) -> float:
    """The heater command (W) a controller sends when its QP answers ``heater_w`` as its first move, the
    answer inexact or not, from a command in force with the heater off."""
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    loop = solve_time.Loop(ctrl, seed=7)
    loop.step(0)
    feedback = ctrl.solver.feedback

    def answer(*args, **kwargs):
        sol = feedback(*args, **kwargs)
        u0 = ctrl.problem.unscale_u(sol.U[0])
        u0[ctrl.problem.i_heater_cmd] = heater_w
        sol.U[0] = ctrl.problem.scale_u(u0)
        sol.extra["inexact"] = inexact
        return sol

    ctrl.solver.feedback = answer
    assert not ctrl.problem.heating(ctrl.u_prev)
    return float(loop.step(1).command.vector()[ctrl.problem.i_heater_cmd])


def test_an_inexact_answer_does_not_switch_the_heater_on_with_a_few_watts():
    assert _inexact_step(3.0, inexact=True) == 0.0
    assert _inexact_step(3.0, inexact=False) == pytest.approx(3.0)
    assert _inexact_step(25.0, inexact=True) == pytest.approx(25.0)
