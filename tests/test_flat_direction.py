"""The outlet flaps' flat direction priced (``Weights.flap_closure_per_pct2``, ``OcpSpec.flap_target_pct``).

The blower and the openings of flaps m, f, w set three outlet flows: "blower down, all flaps open" changes none of
them. The QPs here are captured from the RTI itself (what it hands OSQP), at the same linearisation point with and
without the term, and the flat direction is the model's (the null space of the outlet flows' Jacobian in the blower
and the flaps at each stage, the states following through the linearised dynamics), not the term's.

Budget: about 5 s.
"""

import numpy as np
import osqp
import pytest
import scipy.linalg as sl

from recording_helpers import QpRecorder

from hvac_mpc.contract import Command, Reference
from hvac_mpc.models import Parameters
from hvac_mpc.mpc.ocp import InvalidSettings, OcpSpec, TrackingProblem, Weights
from hvac_mpc.mpc.rti_osqp import U_BLOWER, Y_OUTLETS, RtiOsqpSolver

REF = Reference.from_split(15.0, 0.03, (0.4, 0.3, 0.3))
#: The blower and the three flaps: the decisions of the flat direction.
FLAT_INPUTS = [U_BLOWER, *TrackingProblem.VALVES]
#: A start moved along the flat direction by this much (scaled decisions: 10 % of flap opening per unit vector).
SHIFT = 0.2
#: OSQP's tolerance in the controller (``MpcSettings.osqp_eps``).
EPS = 1e-4


def _captured(weight: float):
    """The cold-start QP of a steady cooling point with a split reference (flaps 90 / 60 / 50 %), as the RTI hands it
    to OSQP: the solver, the QP and the disturbances."""
    pb = TrackingProblem(Parameters(), OcpSpec(weights=Weights(flap_closure_per_pct2=weight)))
    u_prev = pb.scale_u(Command(160.0, 0.0, 40.0, 90.0, 60.0, 50.0).vector())
    d = np.array([28.0, 5.0, -0.3, 0.0])
    x0 = pb.scale_x(pb.model.steady_state(pb.unscale_u(u_prev), np.array([28.0, 5.0, 0.0, 0.0])))
    lo, hi = pb.input_bounds(pb.unscale_u(u_prev))
    rti = RtiOsqpSolver(pb)
    rti._core = rec = QpRecorder(rti._core)
    assert rti.feedback(x0, u_prev, d, pb.reference_vector(REF), pb.output_weights(REF), lo, hi).ok
    return rti, rec.qp, d


def _flat_direction(rti, d) -> np.ndarray:
    """The model's flat direction over the whole plan at the RTI's linearisation point: at each stage the unit vector
    of the blower and flaps that moves no outlet flow (blower down), the states through the linearised dynamics."""
    pb, N, nx, nu = rti.pb, rti.pb.N, rti.pb.nx, rti.pb.nu
    X = rti._z_lin[:rti.iu0].reshape(N + 1, nx)
    U = rti._z_lin[rti.iu0:rti.is0].reshape(N, nu)
    lin = pb.linearise(X, np.vstack([U, U[-1]]), d)
    dz, dx = np.zeros(rti.n), np.zeros(nx)
    for k in range(N):
        null = sl.null_space(lin["D"][k][list(Y_OUTLETS)][:, FLAT_INPUTS])
        assert null.shape[1] == 1  # four decisions, three independent outlet flows
        n = null[:, 0] if null[0, 0] < 0 else -null[:, 0]
        assert n[1:].min() > 0  # blower down, every flap opens
        du = np.zeros(nu)
        du[FLAT_INPUTS] = n
        dz[k * nx:(k + 1) * nx] = dx
        dz[rti.iu0 + k * nu:rti.iu0 + (k + 1) * nu] = du
        dx = lin["A"][k] @ dx + lin["B"][k] @ du
    dz[N * nx:(N + 1) * nx] = dx
    return dz


def _osqp(rti, qp, eps: float, **settings) -> osqp.OSQP:
    solver = osqp.OSQP()
    solver.setup(rti.P.matrix(qp["Px"]), qp["q"], rti.A.matrix(qp["Ax"]), qp["l"], qp["u"], eps_abs=eps, eps_rel=eps,
                 polishing=False, verbose=False, **settings)
    return solver


def _curvature_and_shift_left(weight: float) -> tuple[float, float]:
    """The captured QP's curvature along the flat direction (per scaled unit^2 of the decisions) and the share of a start
    moved along it (flaps closed, blower up, multipliers of the optimum) that OSQP at the controller's tolerance leaves
    in its answer."""
    rti, qp, d = _captured(weight)
    dz = _flat_direction(rti, d)
    du = dz[rti.iu0:rti.is0]
    P = rti.P.matrix(qp["Px"]).toarray()
    P = P + np.triu(P, 1).T
    curvature = float(dz @ P @ dz / (du @ du))
    exact = _osqp(rti, qp, 1e-9, max_iter=50000).solve()
    assert exact.info.status_val == 1
    solver = _osqp(rti, qp, EPS, max_iter=4000, rho=1e-2, check_termination=5, scaling=10, alpha=1.6)
    solver.warm_start(x=exact.x - SHIFT * dz, y=exact.y)
    answer = solver.solve()
    assert answer.info.status_val == 1
    left = float((exact.x - answer.x)[rti.iu0:rti.is0] @ du / (du @ du)) / SHIFT
    return curvature, left


def test_the_term_gives_the_flat_direction_curvature_and_osqp_leaves_it_no_more():
    """Without the term the captured QP is nearly flat along the direction and OSQP, started from the optimum moved
    along it, stops at its tolerance with almost all of the move left (the answer's mix is the start's); with 1e-4
    the curvature is about a hundred times as high and OSQP brings the answer back."""
    flat, flat_left = _curvature_and_shift_left(0.0)
    priced, priced_left = _curvature_and_shift_left(1e-4)
    assert priced > 30.0 * flat
    assert flat_left > 0.5
    assert abs(priced_left) < 0.05


def test_off_by_default_and_on_only_the_flaps_diagonal_and_gradient():
    """The defaults leave the term out; with it on, the QP handed to OSQP differs from the default's at the same point
    only on the flaps' diagonal entries of P (the structure and every other value the same to the bit) and on the
    flaps' entries of the gradient."""
    assert Weights().flap_closure_per_pct2 == 0.0 and OcpSpec().flap_target_pct == 100.0
    h, g = TrackingProblem(Parameters(), OcpSpec(flap_target_pct=50.0)).flap_closure_hessian()
    assert not h.any() and not g.any()
    rti, on, _ = _captured(1e-4)
    _, off, _ = _captured(0.0)
    N, nu = rti.pb.N, rti.pb.nu
    flaps = (rti.iu0 + np.arange(N)[:, None] * nu + np.array(TrackingProblem.VALVES)[None, :]).ravel()
    pattern = rti.P.matrix(np.arange(rti.P.nnz, dtype=float)).tocsc()
    diagonal = {int(pattern[i, i]) for i in flaps}
    assert set(np.flatnonzero(on["Px"] != off["Px"]).tolist()) == diagonal
    assert set(np.flatnonzero(on["q"] != off["q"]).tolist()) == set(flaps.tolist())
    assert (on["Ax"] == off["Ax"]).all() and (on["l"] == off["l"]).all() and (on["u"] == off["u"]).all()


@pytest.mark.parametrize("fields, name", [
    ({"weights": Weights(flap_closure_per_pct2=-1e-5)}, "flap_closure_per_pct2"),
    ({"weights": Weights(flap_closure_per_pct2=0.1)}, "flap_closure_per_pct2"),
    ({"flap_target_pct": 101.0}, "flap_target_pct"),
    ({"flap_target_pct": float("nan")}, "flap_target_pct"),
    ({"flap_targets_pct": (70.0, 100.0)}, "flap_targets_pct"),
    ({"flap_targets_pct": (70.0, 100.0, -1.0)}, r"flap_targets_pct\[w\]"),
    ({"flap_targets_pct": (float("nan"), 100.0, 30.0)}, r"flap_targets_pct\[m\]"),
    ({"flap_target_from_split": 1}, "flap_target_from_split"),
])
def test_bad_values_are_refused_naming_the_field(fields, name):
    with pytest.raises(InvalidSettings, match=name):
        OcpSpec(**fields).validate()


def test_flap_by_flap_targets_give_each_flap_its_own_single_target_gradient():
    """``OcpSpec.flap_targets_pct`` sets each flap's target on its own: each flap's Hessian and gradient entries are
    those of the problem with that flap's target as ``flap_target_pct`` for all three (to the bit), and three equal
    targets are ``flap_target_pct`` itself."""
    weights = Weights(flap_closure_per_pct2=1e-4)
    targets = (69.0, 100.0, 32.8)
    h, g = TrackingProblem(Parameters(), OcpSpec(weights=weights, flap_targets_pct=targets)).flap_closure_hessian()
    for j, target in zip(TrackingProblem.VALVES, targets):
        h1, g1 = TrackingProblem(Parameters(), OcpSpec(weights=weights, flap_target_pct=target)).flap_closure_hessian()
        assert (h[:, j] == h1[:, j]).all() and (g[:, j] == g1[:, j]).all() and g[:, j].any() == (target > 0.0)
    same = TrackingProblem(Parameters(), OcpSpec(weights=weights, flap_targets_pct=(70.0,) * 3)).flap_closure_hessian()
    single = TrackingProblem(Parameters(), OcpSpec(weights=weights, flap_target_pct=70.0)).flap_closure_hessian()
    assert all((a == b).all() for a, b in zip(same, single))


def test_the_split_target_is_the_rest_mix_of_least_blower_power():
    """``OcpSpec.flap_target_from_split``'s openings (:mod:`hvac_mpc.mpc.flap_target`) for a split: the flap whose
    conductance limits the network fully open, the others at the shares the split asks of the model's own flows; all
    fully open where the split is not tracked. On the winter split (0.3, 0.5, 0.2) they are the angles the MPC holds
    at rest without the term in the built-in bench's winter_heating_steps (83.4 / 100 / 40.7 %)."""
    pb = TrackingProblem(Parameters(), OcpSpec(flap_target_from_split=True, weights=Weights(flap_closure_per_pct2=1e-4)))
    split = pb.flap_split_target
    winter = split.openings(np.array([0.3, 0.5, 0.2]) * 0.011, True)
    assert winter[1] == pytest.approx(1.0, abs=1e-12) and np.abs(pb.valve_map.angles(winter) - [83.4, 100.0, 40.7]).max() < 0.2
    assert (split.openings(np.array([0.3, 0.5, 0.2]), False) == 1.0).all()
    assert (split.openings(np.zeros(3), True) == 1.0).all()
    for shares in ((0.6, 0.15, 0.25), (0.2, 0.2, 0.6), (0.4, 0.3, 0.3)):
        v = split.openings(np.array(shares) * 0.02, True)
        assert v.max() == pytest.approx(1.0, abs=1e-12)
        angles = pb.valve_map.angles(v)  # the model's outlet flows at these angles split as asked
        u = pb.scale_u(Command(150.0, 0.0, 40.0, *angles).vector())
        d = np.array([28.0, 5.0, 0.0, 0.0])
        y = pb.model.outputs.dict(pb.model.y(pb.model.steady_state(pb.unscale_u(u), d), pb.unscale_u(u), d))
        flows = np.array([y["flow_m_m3s"], y["flow_f_m3s"], y["flow_w_m3s"]], float)
        assert np.abs(flows / flows.sum() - shares).max() < 0.01


def test_the_split_target_follows_the_reference_into_the_qp():
    """With ``flap_target_from_split`` the QP handed to OSQP is, at the same point, the one with the split's openings
    as fixed targets flap by flap (P, A, bounds and gradient to round-off), and after a change of the split the
    gradient's flap entries are the new split's."""
    weights = Weights(flap_closure_per_pct2=1e-4)
    pb = TrackingProblem(Parameters(), OcpSpec(flap_target_from_split=True, weights=weights))
    u_prev = pb.scale_u(Command(160.0, 0.0, 40.0, 90.0, 60.0, 50.0).vector())
    d = np.array([28.0, 5.0, -0.3, 0.0])
    x0 = pb.scale_x(pb.model.steady_state(pb.unscale_u(u_prev), np.array([28.0, 5.0, 0.0, 0.0])))
    lo, hi = pb.input_bounds(pb.unscale_u(u_prev))

    def qp(problem, ref):
        rti = RtiOsqpSolver(problem)
        rti._core = rec = QpRecorder(rti._core)
        assert rti.feedback(x0, u_prev, d, problem.reference_vector(ref), problem.output_weights(ref), lo, hi).ok
        return rti, rec

    rti, rec = qp(pb, REF)
    openings = pb.flap_split_target.openings(pb.reference_vector(REF)[2:5], True)
    _, fixed = qp(TrackingProblem(Parameters(), OcpSpec(flap_targets_pct=tuple(100.0 * openings), weights=weights)), REF)
    for key in ("Px", "Ax", "l", "u", "q"):
        assert np.allclose(rec.qp[key], fixed.qp[key], rtol=1e-12, atol=1e-12), key
    other = Reference.from_split(15.0, 0.03, (0.2, 0.2, 0.6))
    lo, hi = pb.input_bounds(pb.unscale_u(u_prev))
    assert rti.feedback(x0, u_prev, d, pb.reference_vector(other), pb.output_weights(other), lo, hi).ok
    target = pb.flap_target_for(pb.reference_vector(other), True)
    _, g = pb.flap_closure_hessian(target)
    flaps = list(TrackingProblem.VALVES)
    assert np.allclose(rti._q_const[rti.iu0:rti.is0].reshape(pb.N, pb.nu)[:, flaps], g[:, flaps], rtol=1e-12)
    assert not np.allclose(target[flaps], pb.flap_target_for(pb.reference_vector(REF), True)[flaps])


def test_acados_refuses_the_term_it_does_not_hold():
    """The acados RTI builds its cost from the residuals alone: with the term on it refuses, naming the field (before
    acados itself is needed)."""
    from hvac_mpc.mpc.rti_acados import RtiAcadosSolver
    pb = TrackingProblem(Parameters(), OcpSpec(weights=Weights(flap_closure_per_pct2=1e-4)))
    with pytest.raises(ValueError, match="flap_closure_per_pct2"):
        RtiAcadosSolver(pb)


def test_the_do_mpc_reference_refuses_the_term_it_does_not_hold():
    """do-mpc's objective is built from the stage-wise description's residuals: with the term on it refuses, naming
    the field (before do-mpc itself is needed), instead of solving another problem."""
    from hvac_mpc.benchmarks.dompc_reference import DoMpcSolver
    pb = TrackingProblem(Parameters(), OcpSpec(weights=Weights(flap_closure_per_pct2=1e-4)))
    with pytest.raises(ValueError, match="flap_closure_per_pct2"):
        DoMpcSolver(pb)


@pytest.mark.parametrize("spec", [OcpSpec(weights=Weights(flap_closure_per_pct2=1e-4)),
                                  OcpSpec(flap_target_from_split=True, weights=Weights(flap_closure_per_pct2=1e-4))],
                         ids=["fixed", "from_split"])
def test_the_plan_merit_prices_the_term_as_the_qp_does(spec):
    """The globalised step and the trust region judge plans by :class:`~hvac_mpc.mpc.plan_merit.PlanMerit`'s cost: with
    the term on, that cost is the cost without it plus the term over the horizon's stages (towards the fixed target, or
    the reference's split's), so a plan's pull toward the flaps' target is not priced as a loss."""
    from hvac_mpc.mpc.plan_merit import PlanMerit

    on = TrackingProblem(Parameters(), spec)
    off = TrackingProblem(Parameters(), OcpSpec())
    f_on, f_off = PlanMerit(on, (0.5,)).cost_function(), PlanMerit(off, (0.5,)).cost_function()
    u_prev = on.scale_u(Command(160.0, 0.0, 40.0, 90.0, 60.0, 50.0).vector())
    d = np.array([28.0, 5.0, -0.3, 0.0])
    x0 = on.scale_x(on.model.steady_state(on.unscale_u(u_prev), d))
    U = np.tile(u_prev[:, None], (1, on.N))
    U[list(TrackingProblem.VALVES), 3] -= 0.1  # one stage's flaps 10 % of opening further shut
    ref = on.reference_vector(REF)
    args = dict(x0=x0, U=U, d=d, SW=np.ones(f_on.size_in(3)), ref=ref, u_prev=u_prev,
                p=on.model.p_default, ready_floor=0.0, ready_w=np.zeros(on.N))
    target = on.flap_target_for(ref, True)
    term = sum(float(on.flap_closure_cost(U[:, k], k, target)) for k in range(on.N))
    assert term > 0.0
    assert float(f_on(**args)["cost"]) - float(f_off(**args)["cost"]) == pytest.approx(term, rel=1e-6)
