"""The stage-wise description (mpc/stage_ocp.py) and its transcription (mpc/stage_nlp.py): one
problem behind the RTI's QP, IPOPT and fatrop.

Budget: about 10 s on a loaded two-core machine (fatrop's set-up takes most of it).
"""

import casadi as ca
import numpy as np
import pytest

from recording_helpers import QpRecorder

from hvac_mpc.contract import Command, Reference
from hvac_mpc.models import Parameters
from hvac_mpc.mpc.ocp import OcpSpec, TrackingProblem, Weights
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver
from hvac_mpc.mpc.stage_nlp import StageNlp
from hvac_mpc.mpc.stage_ocp import StageOcp

REF = Reference.from_split(15.0, 0.03, (0.4, 0.3, 0.3))


@pytest.fixture(scope="module")
def pb():
    return TrackingProblem(Parameters(), OcpSpec())


@pytest.fixture(scope="module")
def ocp(pb):
    return StageOcp(pb)


def _state(pb, command=Command(160.0, 0.0, 40.0, 90.0, 60.0, 50.0)):
    """A steady operating point: scaled estimate, last command, disturbances, reference, weights, bounds."""
    u_prev = pb.scale_u(command.vector())
    d = np.array([28.0, 5.0, -0.3, 0.0])
    x0 = pb.scale_x(pb.model.steady_state(pb.unscale_u(u_prev), np.array([28.0, 5.0, 0.0, 0.0])))
    lo, hi = pb.input_bounds(pb.unscale_u(u_prev))
    return x0, u_prev, d, pb.reference_vector(REF), pb.output_weights(REF), lo, hi


def test_every_coupling_term_lives_within_one_stage(ocp):
    """Rows and costs of the stage-wise layout touch one stage's variables (dynamics: and the next
    stage's state), the condition for fatrop's structure detection."""
    nlp = StageNlp(ocp, "stagewise")
    block = int(nlp.ix[1, 0] - nlp.ix[0, 0])  # xa_k and v_k: (nx + nu + 1) + (nu + 1) variables
    assert block == (ocp.nx + ocp.nu + 1) + (ocp.nu + 1)
    stage_of = np.arange(nlp.n) // block
    assert stage_of[nlp.ix[-1]].tolist() == [ocp.N] * ocp.nx
    jac = ca.jacobian(nlp.g, nlp.w).sparsity()
    rows, cols = jac.get_triplet()
    owner = np.full(len(nlp.lbg), -1)
    owner[nlp.rows["x0"]] = 0
    for k, r in enumerate(nlp.rows["dyn"]):
        owner[r] = k
    for r, c in zip(rows, cols):
        if owner[r] >= 0:  # initial and gap-closing rows: stage k and the state of k + 1
            assert stage_of[c] in (owner[r], owner[r] + 1)
    # path rows: all of one stage's variables, and each stage's rows in a block after its dynamics
    path = np.setdiff1d(np.arange(len(nlp.lbg)), np.where(owner >= 0)[0])
    assert path.size == sum(st.n_rows for st in ocp.stages)
    for r in path:
        assert len({stage_of[c] for c, rr in zip(cols, rows) if rr == r}) == 1
    # the move cost, the terminal cost and the soft rows' slacks: the Hessian couples no two stages
    hess = ca.hessian(nlp.f, nlp.w)[0].sparsity()
    hr, hc = hess.get_triplet()
    assert all(stage_of[i] == stage_of[j] for i, j in zip(hr, hc))
    assert ocp.stages[0].rows == ("floor",) and ocp.stages[-1].rows == ("heater",)
    assert ocp.stages[1].rows == ("rate", "heater", "ptc", "floor")
    assert ocp.stages[1].soft.tolist() == [False] * 6 + [True] * 2 + [False]


def test_both_layouts_have_the_tracking_problems_exact_cost(pb, ocp):
    rng = np.random.default_rng(3)
    X = rng.uniform(-0.5, 0.5, (pb.N + 1, pb.nx))
    U = rng.uniform(-0.9, 0.9, (pb.N, pb.nu))
    S = rng.uniform(0.0, 1.0, pb.N)
    x0, u_prev, d, ref, w_y, _, _ = _state(pb)
    exact = float(pb.cost_function()(X.T, U.T, S, d, ref, w_y, u_prev))
    for layout in ("compact", "stagewise"):
        nlp = StageNlp(ocp, layout)
        w = nlp.pack(X, U, S, u_prev)
        assert [a.tolist() for a in nlp.unpack(w)] == [X.tolist(), U.tolist(), S.tolist()]
        value = float(nlp.cost_function()(w, nlp.parameters(x0, u_prev, d, ref, w_y)))
        assert value == pytest.approx(exact, rel=1e-12)
    with pytest.raises(ValueError, match="layout"):
        StageNlp(ocp, "dense")


@pytest.mark.parametrize("lm, heater_w", [(0.0, 0.0), (0.1, 0.0), (0.1, 120.0)])
def test_the_rti_solves_the_gauss_newton_qp_of_the_description(pb, ocp, lm, heater_w):
    """At the RTI's linearisation point the QP handed to OSQP is the Gauss-Newton QP of the stage-wise
    description (compact layout, the same variables) plus the Levenberg-Marquardt term, to 1e-9: on a
    cold start (the rollout of the last command) and on the next step (the shifted plan, another
    reference); with the heater off (the flow floor's slope in the heater command) and on (the plain
    floor)."""
    x0, u_prev, d, ref, w_y, lo, hi = _state(pb, Command(160.0, heater_w, 40.0, 90.0, 60.0, 50.0))
    rti = RtiOsqpSolver(pb, lm_inputs=lm)
    rti._core = rec = QpRecorder(rti._core)
    nlp = StageNlp(ocp, "compact")
    res = rti.feedback(x0, u_prev, d, ref, w_y, lo, hi)
    assert res.ok
    _assert_same_qp(rti, rec.qp, nlp, (x0, u_prev, d, ref, w_y, lo, hi), lm)
    heater_col = rti.A.matrix(rec.qp["Ax"]).toarray()[rti.r_floor][:, nlp.iu[:, pb.i_heater_cmd]].diagonal()
    assert (np.abs(heater_col) > 1.0).all() if heater_w == 0.0 else (heater_col == 0.0).all()
    warm = Reference(24.0, 0.045)
    x1, u0 = res.X[1], res.U[0]
    ref1, w_y1 = pb.reference_vector(warm), pb.output_weights(warm)
    lo1, hi1 = pb.input_bounds(pb.unscale_u(u0))
    rti.prepare(x1, u0, d, ref1, w_y1)
    assert rti.feedback(x1, u0, d, ref1, w_y1, lo1, hi1).ok
    assert np.abs(rti._z_lin[nlp.ix[1:]] - res.X[1:]).max() > 1e-3  # not the cold start's point
    _assert_same_qp(rti, rec.qp, nlp, (x1, u0, d, ref1, w_y1, lo1, hi1), lm)


@pytest.mark.parametrize("heater_w", [0.0, 120.0])
def test_the_value_of_the_body_heat_is_in_both_qps(heater_w):
    """With ``Weights.body_heat_power_w`` the RTI's QP is still the stage-wise description's Gauss-Newton QP: the
    linear term on the terminal body state in both while the heater is on in the command in force, in neither
    while it is off."""
    pb = TrackingProblem(Parameters(), OcpSpec(weights=Weights(body_heat_power_w=340.0)))
    test_the_rti_solves_the_gauss_newton_qp_of_the_description(pb, StageOcp(pb), 0.1, heater_w)


def test_the_flap_closure_is_in_both_qps_and_the_exact_cost():
    """With ``Weights.flap_closure_per_pct2`` (towards ``OcpSpec.flap_target_pct``) the RTI's QP is still the stage-wise
    description's Gauss-Newton QP, and both layouts of the description have the tracking problem's exact cost."""
    pb = TrackingProblem(Parameters(), OcpSpec(flap_target_pct=70.0, weights=Weights(flap_closure_per_pct2=1e-4)))
    ocp = StageOcp(pb)
    test_the_rti_solves_the_gauss_newton_qp_of_the_description(pb, ocp, 0.0, 0.0)
    test_both_layouts_have_the_tracking_problems_exact_cost(pb, ocp)
    # the term is in the exact cost: a plan with the flaps 10 % of opening further from the target costs more by it
    X = np.zeros((pb.N + 1, pb.nx))
    U = np.tile(pb.flap_target_u, (pb.N, 1))
    x0, u_prev, d, ref, w_y, _, _ = _state(pb)
    cost = pb.cost_function()
    moved = U.copy()
    moved[:, list(pb.VALVES)] -= 0.2  # 10 % of opening (scaled decisions span [-1, 1] over 0-100 %)
    extra = float(cost(X.T, moved.T, np.zeros(pb.N), d, ref, w_y, u_prev) - cost(X.T, U.T, np.zeros(pb.N), d, ref, w_y,
                                                                                 u_prev))
    plain = TrackingProblem(Parameters(), OcpSpec(flap_target_pct=70.0))
    extra_plain = float(plain.cost_function()(X.T, moved.T, np.zeros(pb.N), d, ref, w_y, u_prev)
                        - plain.cost_function()(X.T, U.T, np.zeros(pb.N), d, ref, w_y, u_prev))
    assert extra - extra_plain == pytest.approx(1e-4 * 10.0 ** 2 * 3 * pb.dt.sum(), rel=1e-9)


def test_the_flap_target_from_the_split_is_in_both_qps_and_the_exact_cost():
    """With ``OcpSpec.flap_target_from_split`` (the flaps' targets from the reference's outlet shares, a function of
    the reference in the description's parameters) the RTI's QP is still the description's Gauss-Newton QP and both
    layouts have the exact cost; that cost is the one with the split's openings as fixed targets flap by flap
    (``flap_targets_pct``), and its flap term moves with the split."""
    weights = Weights(flap_closure_per_pct2=1e-4)
    pb = TrackingProblem(Parameters(), OcpSpec(flap_target_from_split=True, weights=weights))
    ocp = StageOcp(pb)
    test_the_rti_solves_the_gauss_newton_qp_of_the_description(pb, ocp, 0.0, 0.0)
    test_both_layouts_have_the_tracking_problems_exact_cost(pb, ocp)
    x0, u_prev, d, ref, w_y, _, _ = _state(pb)
    openings = pb.flap_split_target.openings(ref[2:5], True)
    fixed = TrackingProblem(Parameters(), OcpSpec(flap_targets_pct=tuple(100.0 * openings), weights=weights))
    X, U, S = np.zeros((pb.nx, pb.N + 1)), np.tile(u_prev[:, None], (1, pb.N)), np.zeros(pb.N)
    from_split = float(pb.cost_function()(X, U, S, d, ref, w_y, u_prev))
    assert from_split == pytest.approx(float(fixed.cost_function()(X, U, S, d, ref, w_y, u_prev)), rel=1e-12)
    other = ref.copy()
    other[2:5] = other[2:5][::-1]  # the same flow, the split reversed: other targets, another flap term
    assert float(pb.cost_function()(X, U, S, d, other, w_y, u_prev)) != pytest.approx(
        float(fixed.cost_function()(X, U, S, d, other, w_y, u_prev)), rel=1e-9)


def _assert_same_qp(rti, qp, nlp, data, lm):
    x0, u_prev, d, ref, w_y, lo, hi = data
    z_lin = rti._z_lin.copy()
    gn = nlp.gauss_newton_qp(z_lin, nlp.parameters(x0, u_prev, d, ref, w_y))
    lbx, ubx = nlp.bounds(lo, hi)
    # Hessian (OSQP holds the upper triangle) and gradient
    P = rti.P.matrix(qp["Px"]).toarray()
    P = P + np.triu(P, 1).T
    iu = nlp.iu.ravel()
    lm_P = np.zeros(nlp.n)
    lm_P[iu] = 2.0 * lm
    scale = np.abs(gn["P"]).max()
    assert np.abs(P - gn["P"] - np.diag(lm_P)).max() <= 1e-9 * scale
    lm_q = np.zeros(nlp.n)
    lm_q[iu] = -2.0 * lm * z_lin[iu]
    assert np.abs(qp["q"] - gn["q"] - lm_q).max() <= 1e-9 * max(1.0, np.abs(gn["q"]).max())
    # rows: the same groups, the gap-closing rows negated (x_k+1 - A x_k - B u_k = e)
    A = rti.A.matrix(qp["Ax"]).toarray()
    l, u = qp["l"], qp["u"]
    big = 1e20  # OSQP's infinity stands for inf
    pairs = [(rti.r_x0, nlp.rows["x0"], 1.0), (rti.r_dyn.ravel(), nlp.rows["dyn"].ravel(), -1.0),
             (rti.r_rate.ravel(), nlp.rows["rate"], 1.0), (rti.r_soft, nlp.rows["heater"], 1.0),
             (rti.r_ptc, nlp.rows["ptc"], 1.0), (rti.r_floor, nlp.rows["floor"], 1.0)]
    for r_rti, r_gn, sign in pairs:
        assert len(r_rti) == len(r_gn) > 0
        assert np.abs(A[r_rti] - sign * gn["A"][r_gn]).max() <= 1e-9
        lo_gn, hi_gn = (gn["lg"][r_gn], gn["ug"][r_gn]) if sign > 0 else (-gn["ug"][r_gn], -gn["lg"][r_gn])
        for mine, theirs in ((l[r_rti], lo_gn), (u[r_rti], hi_gn)):
            theirs = np.clip(theirs, -big, big)
            finite = np.abs(theirs) < big
            assert np.array_equal(np.abs(mine) >= big, ~finite)
            assert np.abs(mine[finite] - theirs[finite]).max(initial=0.0) <= 1e-9
    # variable bounds of the description are rows of the RTI's QP: inputs and s >= 0
    for r_rti, idx in ((rti.r_u.ravel(), iu), (rti.r_slack, nlp.i_slack_bound)):
        assert np.array_equal(A[r_rti][:, idx], np.eye(len(idx)))
        assert np.abs(l[r_rti] - lbx[idx]).max() <= 1e-12
        finite = np.isfinite(ubx[idx])
        assert np.array_equal(u[r_rti] < big, finite)
        assert np.abs(u[r_rti][finite] - ubx[idx][finite]).max(initial=0.0) <= 1e-12
    covered = sum(len(r) for r, _, _ in pairs) + rti.r_u.size + rti.r_slack.size
    assert covered == rti.m  # nothing else in the RTI's QP


@pytest.mark.slow  # above 7 s on a loaded machine; the whole suite runs it
def test_ipopt_and_fatrop_built_from_the_description_reach_the_same_optimum(pb):
    """Tight tolerances, no objective scaling (at the IPOPT reference's default 1e-3 scaling IPOPT stops
    on the redundant actuators' flat directions about 2e-4 above the optimum from this state)."""
    from hvac_mpc.benchmarks.fatrop_reference import FatropSolver
    from hvac_mpc.mpc.ipopt_reference import IpoptReferenceSolver

    x0, u_prev, d, ref, w_y, lo, hi = _state(pb)
    ip = IpoptReferenceSolver(pb, tol=1e-10, obj_scaling=1.0)
    fa = FatropSolver(pb, tol=1e-10, obj_scaling=1.0)
    ri = ip.feedback(x0, u_prev, d, ref, w_y, lo, hi)
    rf = fa.feedback(x0, u_prev, d, ref, w_y, lo, hi)
    assert ri.ok and rf.ok and ri.iterations > 0 and rf.iterations > 0
    cost = pb.cost_function()
    c_ip = float(cost(ri.X.T, ri.U.T, ri.S, d, ref, w_y, u_prev))
    c_fa = float(cost(rf.X.T, rf.U.T, rf.S, d, ref, w_y, u_prev))
    assert c_ip == pytest.approx(ri.extra["objective"], rel=1e-12)
    assert c_fa == pytest.approx(rf.extra["objective"], rel=1e-12)
    assert c_fa == pytest.approx(c_ip, rel=1e-8)
    assert np.max(np.abs(pb.unscale_u(rf.U) - pb.unscale_u(ri.U))) < 1e-2  # W and %, whole plan
    assert np.max(np.abs(rf.X - ri.X)) < 1e-5
    for solver in (ip, fa):
        assert solver.settings["description"].startswith("StageOcp")


#: The solve-time scenario's reference changes on which fatrop failed with its objective unscaled
#: (status 1 from 60, 120 and 180 s on), each with the command the loop held before it (W, W, %).
SCENARIO_CHANGES = (
    (Command(205.0, 0.0, 86.0, 100.0, 53.0, 49.0), Reference.from_split(20.0, 0.025, (0.2, 0.5, 0.3))),
    (Command(254.0, 0.0, 58.0, 100.0, 87.0, 100.0), Reference.from_split(24.0, 0.03, (0.5, 0.2, 0.3))),
    (Command(288.0, 0.0, 75.0, 100.0, 56.0, 64.0), Reference.from_split(22.0, 0.02, (0.3, 0.3, 0.4))),
)


@pytest.mark.slow  # above 7 s on a loaded machine; the whole suite runs it
def test_fatrop_solves_the_reference_changes_of_the_solve_time_scenario_to_ipopts_cost(pb):
    """From the steady state at the command held before each change (inlet 32 degC, water 4.6 degC) and a
    cold start, fatrop at its benchmark settings converges and reaches IPOPT's cost; unscaled (before
    the objective scaling) it failed on all three (line search, then restoration)."""
    from hvac_mpc.benchmarks.fatrop_reference import FatropSolver
    from hvac_mpc.mpc.ipopt_reference import IpoptReferenceSolver

    with pytest.raises(ValueError, match="obj_scaling"):
        FatropSolver(pb, obj_scaling=0.0)
    fa, ip = FatropSolver(pb), IpoptReferenceSolver(pb, warm_start_init_point=False)
    d = np.array([32.0, 4.6, 0.0, 0.0])
    for command, ref in SCENARIO_CHANGES:
        u_prev = pb.scale_u(command.vector())
        x0 = pb.scale_x(pb.model.steady_state(command.vector(), d))
        lo, hi = pb.input_bounds(command.vector())
        args = (x0, u_prev, d, pb.reference_vector(ref), pb.output_weights(ref), lo, hi)
        fa.reset(), ip.reset()
        rf, ri = fa.feedback(*args), ip.feedback(*args)
        assert rf.ok, (ref, rf.status)
        assert ri.ok and rf.iterations <= 100
        assert rf.extra["objective"] == pytest.approx(ri.extra["objective"], rel=1e-4)
        assert abs(pb.unscale_u(rf.U[0]) - pb.unscale_u(ri.U[0])).max() < 1.0  # the move applied (W, %)
