"""HPIPM's route of ``benchmarks/qp_hpipm.py``: the RTI's QP written stage by stage is the same QP (objective
and rows at any point whose copies agree), each stage's Hessian block is positive semidefinite as HPIPM's
Riccati recursion needs, and HPIPM reaches OSQP's optimum on QPs recorded from the solve-time loop.

Budget: a few seconds (8 interpreted steps).
"""

import numpy as np
import pytest

from hvac_mpc.benchmarks import qp_dense, qp_hpipm
from hvac_mpc.mpc.mpc_controller import MpcSettings


@pytest.fixture(scope="module")
def recorded():
    qps, lay, _ = qp_dense.record(8, seed=1, settings=MpcSettings(codegen=False))
    return qps, lay, qp_hpipm.StageQp(lay)


def _lift(st, z):
    w = np.zeros(st.n)
    for v, copies in enumerate(st.copies):
        for _, i in copies:
            w[i] = z[v]
    return w


def test_the_stage_wise_qp_is_the_recorded_one_with_psd_stage_blocks(recorded):
    qps, lay, st = recorded
    rng = np.random.default_rng(0)
    for qp in qps[::3]:
        d = st.data(qp)
        H, A = np.array(d["h"]), np.array(d["a"])
        for z in (qp["x"], qp["x"] + 0.1 * rng.standard_normal(qp["x"].size)):
            w = _lift(st, z)
            assert np.allclose(st.compact(w), z)
            f_w = 0.5 * w @ H @ w + d["g"] @ w
            assert f_w == pytest.approx(qp_dense.objective(qp, lay, z), rel=1e-9, abs=1e-6)
        # at OSQP's answer the stage-wise rows and bounds hold to OSQP's tolerance, as the recorded rows do
        w = _lift(st, qp["x"])
        Aw = A @ w
        assert max((d["lba"] - Aw).max(), (Aw - d["uba"]).max(), (d["lbx"] - w).max(), (w - d["ubx"]).max()) < 0.05
        for k in range(st.N + 1):
            b = np.arange(st.off_xi[k], st.off_xi[k] + st.nxs[k] + st.nus[k])
            assert np.linalg.eigvalsh(H[np.ix_(b, b)]).min() > -1e-7


def test_hpipm_reaches_osqps_optimum_on_recorded_qps(recorded):
    qps, lay, st = recorded
    route = qp_hpipm.HpipmRoute(st, "speed_abs")
    for qp in qps:
        _, iterations, z, ok = route.solve(st.data(qp))
        assert ok and iterations < 40
        f_osqp, f_hpipm = qp_dense.objective(qp, lay, qp["x"]), qp_dense.objective(qp, lay, z)
        # OSQP stops within its tolerance (1e-4 relative), its rows too: the objectives agree to that
        assert abs(f_osqp - f_hpipm) <= 1e-4 * abs(f_osqp)
        Az = lay.A(qp["Ax"]) @ z
        assert max((qp["l"] - Az).max(), (Az - qp["u"]).max()) < 1e-5
