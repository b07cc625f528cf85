"""The condensed QP route of ``benchmarks/qp_dense.py`` (states eliminated, DAQP) against OSQP on QPs
recorded from the solve-time loop: the same optimum to OSQP's tolerance, feasible, and a hot start from
the right active set that needs no more active-set changes.

Budget: a few seconds (12 interpreted steps, 13 QPs condensed in numpy).
"""

import numpy as np
import pytest

pytest.importorskip("daqp", reason="DAQP (the qp-dense extra) is not installed: the route under test needs it")

from hvac_mpc.benchmarks import qp_dense  # noqa: E402
from hvac_mpc.mpc.mpc_controller import MpcSettings  # noqa: E402


@pytest.fixture(scope="module")
def recorded():
    qps, lay, _ = qp_dense.record(12, seed=1, settings=MpcSettings(codegen=False))
    return qps, lay


def _violation(qp, lay, z):
    Az = lay.A(qp["Ax"]) @ z
    return float(max((qp["l"] - Az).max(), (Az - qp["u"]).max()))


def test_condensed_route_reaches_osqps_optimum_within_its_tolerance(recorded):
    qps, lay = recorded
    assert len(qps) >= 12
    route = qp_dense.DaqpRoute()
    eps = lay.settings["eps_rel"]
    iu0 = lay.n_eq
    for qp in qps:
        _, _, z, _ = route.solve(qp_dense.condense(qp, lay))
        assert _violation(qp, lay, z) < 1e-9  # dynamics and every inequality row of the sparse QP
        f_osqp, f_daqp = qp_dense.objective(qp, lay, qp["x"]), qp_dense.objective(qp, lay, z)
        assert abs(f_osqp - f_daqp) <= eps * abs(f_osqp)
        # the first move (the command): OSQP stops within its tolerance, and the Hessian is flat in some
        # directions (redundant actuators), so the plans agree to a few hundredths of the scaled range
        assert np.abs(z[iu0:iu0 + lay.nu] - qp["x"][iu0:iu0 + lay.nu]).max() < 0.1


def test_hot_start_from_the_optimal_active_set_changes_nothing(recorded):
    qps, lay = recorded
    dense = qp_dense.condense(qps[-1], lay)
    route = qp_dense.DaqpRoute()
    _, cold_iterations, z_cold, cold_changes = route.solve(dense)
    assert cold_changes > 10 and cold_iterations > 10  # from an empty active set
    _, iterations, z, changes = route.solve(dense)  # hot: the active set it ended with
    assert changes == 0 and iterations <= 1
    np.testing.assert_allclose(z, z_cold, atol=1e-9)


def test_blocked_inputs_hold_over_each_block_and_cost_no_less(recorded):
    qps, lay = recorded
    blocks = [1, 1, 1, 2, 2, 3, 5, 10]
    qp = qps[-1]
    dense = qp_dense.condense(qp, lay)
    _, _, z_full, _ = qp_dense.DaqpRoute().solve(dense)
    _, _, z, _ = qp_dense.DaqpRoute().solve(qp_dense.block(dense, lay, blocks))
    assert _violation(qp, lay, z) < 1e-9
    U = z[lay.n_eq:lay.n_eq + lay.N * lay.nu].reshape(lay.N, lay.nu)
    starts = np.cumsum([0] + blocks[:-1])
    for a, b in zip(starts, blocks):
        np.testing.assert_allclose(U[a:a + b], np.tile(U[a], (b, 1)), atol=1e-12)
    assert qp_dense.objective(qp, lay, z) >= qp_dense.objective(qp, lay, z_full) - 1e-9
    with pytest.raises(ValueError, match="sum to the horizon"):
        qp_dense.block(dense, lay, [1, 2])
