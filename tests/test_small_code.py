"""Generated functions written smaller, and calls made fewer, give the numbers of their first formulation to the bit.

The QP's gradient is a loop over the stages (one stage's SX function mapped) instead of every stage written out in
one SX function, the estimator's measurement update has its products as MX (loops in the generated C), the
reachable-flow check's three flows come from one call, and the estimator's time update fused with the QP data is
generated C linked against the two functions it calls: each must be the same floating-point operations on the same
numbers.

Budget: about 5-20 s (interpreted; the generated build only where the code cache does not hold it yet).
"""

import casadi as ca
import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc import codegen, rti_osqp
from hvac_mpc.mpc.codegen import compiled, compiler
from hvac_mpc.mpc.estimator import MEASURED, EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.rti_osqp import Y_FLOW, Y_OUTLETS, Y_TEMP


def _unrolled_gradient(solver) -> ca.Function:
    """The gradient as it was first written: every stage's block in one SX function (the formulation before the
    stages were mapped), kept here as the reference."""
    pb, N, nu, ny = solver.pb, solver.pb.N, solver.pb.nu, solver.pb.ny
    nz, nr = solver.nz_stage, ny + 1
    G2 = ca.SX.sym("Gw2", nr * nz, N + 1)
    C = ca.SX.sym("c_base", nr, N + 1)
    Y = ca.SX.sym("y", ny, N + 1)
    ref = ca.SX.sym("ref", ny)
    dd = ca.SX.sym("dd", 2)
    u_lin = ca.SX.sym("u_lin", N * nu)
    u_prev = ca.SX.sym("u_prev", nu)
    q0, lm, w_du = ca.SX.sym("q0", solver.n), ca.SX.sym("lm", N * nu), ca.SX.sym("w_du", nu)
    c = C - ca.vertcat(ref, 0)
    rows = [c[i, :] for i in range(nr)]
    rows[Y_TEMP] += (1.0 - pb.spec.temperature_sensor_share) * dd[0]
    rows[Y_FLOW] += dd[1]
    for i in Y_OUTLETS:
        rows[i] += dd[1] * Y[i, :] / ca.fmax(Y[Y_FLOW, :], 1e-6)
    c = ca.vertcat(*rows)
    blocks = ca.horzcat(*[ca.mtimes(ca.reshape(G2[:, k], nr, nz).T, c[:, k]) for k in range(N + 1)])
    m_q = rti_osqp._selection(solver.stage_cols.ravel(), solver.n)
    q = q0 + ca.mtimes(m_q, ca.vec(blocks))
    lm_term = ca.vertcat(ca.DM.zeros(solver.iu0), -2.0 * lm * u_lin, ca.DM.zeros(N))
    du_term = ca.vertcat(ca.DM.zeros(solver.iu0), -2.0 * w_du * u_prev, ca.DM.zeros(solver.n - solver.iu0 - nu))
    return ca.Function("unrolled_gradient", [G2, C, Y, ref, dd, u_lin, u_prev, q0, lm, w_du],
                       [q + lm_term + du_term])


def _inputs(fn: ca.Function, rng: np.random.Generator, zeros: bool) -> list[np.ndarray]:
    """Random inputs of ``fn``'s shapes (flows positive and some zero, so the fmax floor is met too)."""
    args = [rng.normal(size=fn.size_in(i)) * 10.0 ** rng.integers(-3, 3) for i in range(fn.n_in())]
    args[2][Y_FLOW, :] = np.abs(args[2][Y_FLOW, :])
    if zeros:
        args[2][Y_FLOW, ::3] = 0.0
        args[4][:] = 0.0
    return args


def test_the_mapped_gradient_is_the_unrolled_one_to_the_bit():
    solver = MpcController(settings=MpcSettings(codegen=False)).solver
    new, old = solver.qp_gradient, _unrolled_gradient(solver)
    assert new.size_out(0) == old.size_out(0)
    rng = np.random.default_rng(11)
    for trial in range(20):
        args = _inputs(old, rng, zeros=trial % 4 == 0)
        a, b = np.asarray(new(*args)), np.asarray(old(*args))
        assert np.array_equal(a, b), trial
        assert np.abs(a).max() > 0


@pytest.mark.skipif(compiler() is None, reason="no C compiler: the generated gradient cannot be built here")
def test_the_generated_mapped_gradient_is_the_unrolled_one_to_the_bit_and_smaller(monkeypatch, tmp_path):
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")  # the suite interprets by default (tests/conftest.py)
    solver = MpcController(settings=MpcSettings(codegen=False)).solver
    old = _unrolled_gradient(solver)
    new = compiled(solver.qp_gradient)
    assert new.class_name() == "External"  # built or loaded from the code cache
    rng = np.random.default_rng(12)
    for trial in range(10):
        args = _inputs(old, rng, zeros=trial % 3 == 0)
        assert np.array_equal(np.asarray(new(*args)), np.asarray(old(*args))), trial
    # the stages as a loop: less than a fifth of the C source of the stages written out (about 16 against 217 kB)
    monkeypatch.chdir(tmp_path)
    sizes = [(tmp_path / f.generate(f"{name}.c", {"with_header": False})).stat().st_size
             for name, f in (("mapped", solver.qp_gradient), ("unrolled", old))]
    assert sizes[0] < sizes[1] / 5, sizes


def _flows_apart(reach, x, u, d, step):
    """The three flows as the check and the flow-weight factor compute them alone (two calls each)."""
    u_full = np.array(u, float)
    u_full[reach.i_blower] = reach.u_hi[reach.i_blower]
    u_full[reach.i_outlets] = reach.u_hi[reach.i_outlets]
    moved = [reach.i_blower, *reach.i_outlets]
    u_up = np.array(u, float)
    u_up[moved] = np.minimum(u_up[moved] + step[moved], reach.u_hi[moved])
    return tuple(float(reach.out(x, v, d)[0][0]) for v in (u, u_full, u_up))


@pytest.mark.parametrize("generated", [False, True])
def test_the_reachable_flow_checks_flows_in_one_call_are_those_of_the_calls_apart(generated, monkeypatch):
    if generated and compiler() is None:
        pytest.skip("no C compiler: the generated flows cannot be built here")
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    reach, pb = ctrl.reach, ctrl.problem
    assert reach is not None
    if generated:  # the flows alone as generated C (a controller with codegen would build the QP data too)
        monkeypatch.setenv(codegen.SWITCH_ENV, "1")
        reach.use_flows_function(codegen.compiled(reach.flows_fn))
        assert reach._flows.fn.class_name() == "External"
    step = pb.rate_phys * pb.dt_s
    rng = np.random.default_rng(5)
    loop = solve_time.Loop(ctrl, seed=2)
    seen_up = 0
    for k in range(12):
        loop.step(k)
        d = ctrl._disturbance(5.0)
        for trial in range(5):
            u = np.clip(ctrl.u_prev + rng.normal(size=pb.nu) * (pb.u_hi - pb.u_lo) * 0.3, pb.u_lo, pb.u_hi)
            if trial == 0:
                u[reach.i_blower] = reach.u_hi[reach.i_blower]  # at its bound: the move up is cut there
            flows = reach.flows(ctrl.ekf.x, u, d, step)
            assert tuple(flows) == _flows_apart(reach, ctrl.ekf.x, u, d, step), (k, trial)
            seen_up += flows.up_m3s > flows.now_m3s
    assert seen_up > 0  # the moves up raise the flow somewhere: the third flow is not the first again


def test_the_fused_prediction_linked_as_c_gives_casadis_evaluation_to_the_bit(monkeypatch):
    """The estimator's time update fused with the QP data runs as generated C of its own, linked against the two
    generated functions it calls (``codegen.compiled`` with ``link``); CasADi's evaluation of the same calls (the MX
    function, as without it) gives the same numbers to the bit, on the states of a closed loop."""
    if compiler() is None:
        pytest.skip("no C compiler: nothing generated to compare")
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")  # the code cache of the run: the large functions are built once
    ctrl = MpcController(settings=MpcSettings(codegen=True))
    solver = ctrl.solver
    assert ctrl.codegen.active
    linked = solver._predict_qp
    assert linked.fn.class_name() == "External"
    assert linked.fn.name() == f"hvac_predict_qp_data_{ctrl.ekf.name}"
    # the MX function calling the same generated functions, evaluated by CasADi
    monkeypatch.setattr(type(solver), "_compiled_calling", lambda self, fn, *called: fn)
    predict, fixed = ctrl.ekf.prediction_function()
    plain = solver._fuse(ctrl.ekf, predict, fixed).qp
    assert plain.fn.class_name() == "MXFunction"
    loop = solve_time.Loop(ctrl, seed=3)
    rng = np.random.default_rng(3)
    for k in range(8):
        loop.step(k)
        ekf = ctrl.ekf
        u = ctrl.u_prev + rng.normal(size=ctrl.u_prev.size)
        args = (ekf.z, ekf.P, u, 5.0 + k, float(ekf.learning), solver.X, solver.U, solver.U[0],
                solver._weights(ctrl.problem.w_y_full))
        a, b = linked(*args), plain(*args)
        assert len(a) == len(b) == 14
        for i, (x, y) in enumerate(zip(a, b)):
            assert np.array_equal(x, y), (k, i)


def test_a_function_calling_a_library_not_there_is_left_to_casadi(tmp_path, monkeypatch):
    """Where the shared objects to link against are missing, ``compiled`` hands the function back (the same
    calls, evaluated by CasADi) and says why."""
    if compiler() is None:
        pytest.skip("no C compiler: nothing is built either way")
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    cache = tmp_path / "a cache, with a comma"  # the run path reaches the linker as it is
    monkeypatch.setenv(codegen.CACHE_ENV, str(cache))
    x = ca.SX.sym("x", 2)
    inner = compiled(ca.Function("small_inner", [x], [2.0 * x]))
    assert inner.class_name() == "External"
    y = ca.MX.sym("y", 2)
    outer = ca.Function("small_outer", [y], [inner(y) + 1.0])
    report = codegen.CodegenReport()
    out = codegen.compiled(outer, report, link=(tmp_path / "not_there.so",))
    assert out is outer and report.outcomes["small_outer"].startswith("interpreted")
    lib = next(cache.glob("small_inner_*.so"))
    linked = codegen.compiled(outer, report, link=(lib,))
    assert report.outcomes["small_outer"] == "built" and linked.class_name() == "External"
    assert np.array_equal(np.asarray(linked([0.25, -3.0])), [[1.5], [-5.0]])


@pytest.mark.parametrize("learn", [False, True])
def test_the_estimators_update_with_mx_products_is_the_sx_one_to_the_bit(learn, monkeypatch):
    """The measurement update's products as MX (generated C loops over them) give the SX function's numbers to the
    bit: interpreted, and as generated C against the interpreted SX function, on the states of a closed loop with
    readings left out, other weights and variances, with and without the bypass-flow exponent learned."""
    ctrl = MpcController(settings=MpcSettings(codegen=False, ekf=EkfSettings(learn_bypass_flow=learn)))
    pairs = []
    for ekf in ctrl._filters:
        assert ekf.learns_bypass_flow == learn
        assert ekf.update_fn.is_a("MXFunction")
        pairs.append((ekf, ekf.update_fn, ekf._update_function(ca.SX)))  # the first formulation: SX
    if compiler() is not None:
        monkeypatch.setenv(codegen.SWITCH_ENV, "1")
        pairs += [(ekf, compiled(new), old) for ekf, new, old in pairs[:1]]
        assert pairs[-1][1].class_name() == "External"
    loop = solve_time.Loop(ctrl, seed=4)
    rng = np.random.default_rng(4)
    nm = len(MEASURED)
    compared = [0] * len(pairs)
    for k in range(30):
        loop.step(k)
        for i, (ekf, new, old) in enumerate(pairs):
            if not ekf.initialised:  # the second filter starts with its first sample in use
                continue
            compared[i] += 1
            ok = (rng.uniform(size=nm) > 0.25).astype(float)
            ok[k % nm] = 0.0
            A = rng.normal(size=(ekf.nz, ekf.nz))
            P = ekf.P + 1e-3 * A @ A.T
            args = [ekf.z, P, rng.normal(size=nm) + ekf.z[0], ok, ctrl.u_prev, 5.0 + k,
                    rng.uniform(size=ekf.n_hist + 1), ekf.p, ekf.R_diag * rng.uniform(0.5, 2.0, nm), float(k % 2)]
            for a, b in zip(new(*args), old(*args)):
                assert np.array_equal(np.asarray(a), np.asarray(b)), (k, ekf.name)
    assert min(compared) >= 20


def test_the_functions_with_common_subexpressions_computed_once_give_the_same_numbers(monkeypatch):
    """``codegen.shared`` (``casadi.cse``) on the step's small functions: fewer instructions, and on the arguments
    the step hands them in a closed loop the same numbers to the bit as the functions as written, interpreted and
    as the generated C the controller loads."""
    from hvac_mpc.mpc.casadi_eval import BufferedFunction
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    ekf = ctrl.ekf
    targets = {f.name(): f for f in (ekf.shadow.step_fn, ekf.shadow.air_fn, ctrl.reach.out_fn, ctrl.reach.flows_fn)}
    seen: dict[str, list] = {name: [] for name in targets}
    original, original_views = BufferedFunction.__call__, BufferedFunction.views

    def recorded(self, *args, _call=original):
        out = _call(self, *args)
        if self.fn.name() in seen:
            seen[self.fn.name()].append([a.copy() for a in self._args])
        return out

    def recorded_views(self, *args):  # the flows' call hands back its buffers (read at once)
        return recorded(self, *args, _call=original_views)
    monkeypatch.setattr(BufferedFunction, "__call__", recorded)
    monkeypatch.setattr(BufferedFunction, "views", recorded_views)
    loop = solve_time.Loop(ctrl, seed=6)
    predict_args = []
    for k in range(25):
        loop.step(k)
        predict_args.append([ekf.z.copy(), ekf.P.copy(), ctrl.u_prev.copy(), 5.0 + 0.1 * k, ekf.p, ekf.Q,
                             float(ekf.learning)])
    monkeypatch.setattr(BufferedFunction, "__call__", original)
    monkeypatch.setattr(BufferedFunction, "views", original_views)
    targets[ekf.predict_fn.name()] = ekf.predict_fn
    seen[ekf.predict_fn.name()] = predict_args
    # the shadow's airs (read where it re-anchors) and the reachable-flow outputs (the flows' call reads them in the
    # step) on the states, commands and disturbances of the flows' calls, with the parameters of each
    flows = ctrl.reach.flows_fn
    for fn, p in ((ekf.shadow.air_fn, ekf.p), (ctrl.reach.out_fn, ctrl.reach._p)):
        assert [fn.size_in(i) for i in range(4)] == [flows.size_in(i) for i in range(4)]
        seen[fn.name()] += [[*args[:3], p] for args in seen[flows.name()]]
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    for name, fn in targets.items():
        assert len(seen[name]) >= 20, name
        cut = codegen.shared(fn)
        assert cut.n_instructions() < fn.n_instructions(), name
        variants = [cut] + ([compiled(cut)] if compiler() is not None else [])
        for args in seen[name]:
            want = [np.asarray(v) for v in fn(*args)] if fn.n_out() > 1 else [np.asarray(fn(*args))]
            for f in variants:
                got = [np.asarray(v) for v in f(*args)] if f.n_out() > 1 else [np.asarray(f(*args))]
                assert all(np.array_equal(a, b) for a, b in zip(got, want)), (name, f.class_name())


def test_one_build_of_the_fused_prediction_serves_other_weights_and_parameters(monkeypatch):
    """The fused prediction takes the scaling and the constant parts of P and A as inputs: a controller with other
    cost weights and other model parameters loads the library the first one built (the same file, 'cached'), and
    its linked call still gives CasADi's evaluation of the same calls to the bit."""
    if compiler() is None:
        pytest.skip("no C compiler: nothing generated to share")
    import dataclasses
    from hvac_mpc.models.parameters import Parameters
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    first = MpcController(settings=MpcSettings(codegen=True))
    name = first.solver._predict_qp.fn.name()
    spec = first.settings.ocp
    weights = dataclasses.replace(spec.weights, move_valve_per_pct2=3 * spec.weights.move_valve_per_pct2,
                                  volume_flow=1.5 * spec.weights.volume_flow)
    other = MpcController(Parameters().replace(heater_kp=1.2 * Parameters().heater_kp),
                          MpcSettings(codegen=True, ocp=dataclasses.replace(spec, weights=weights)))
    assert other.solver._predict_qp.fn.class_name() == "External"
    assert other.codegen.libraries[name] == first.codegen.libraries[name]
    assert other.codegen.outcomes[name] == "cached"
    # its numbers are the other controller's: the linked call against CasADi's evaluation of the same calls
    linked = other.solver._predict_qp
    monkeypatch.setattr(type(other.solver), "_compiled_calling", lambda self, fn, *called: fn)
    predict, fixed = other.ekf.prediction_function()
    plain = other.solver._fuse(other.ekf, predict, fixed).qp
    solver = other.solver
    loop = solve_time.Loop(other, seed=3)
    for k in range(6):
        loop.step(k)
        ekf = other.ekf
        args = (ekf.z, ekf.P, other.u_prev, 5.0 + k, float(ekf.learning), solver.X, solver.U, solver.U[0],
                solver._weights(other.problem.w_y_full))
        for x, y in zip(linked(*args), plain(*args)):
            assert np.array_equal(x, y), k
