"""The controller's hot path: the estimator's updates as one CasADi function each, the valve
conversions of all three valves in one call, and a reset that starts from a clean solver.

Budget: about 5 s on a loaded two-core machine (two short closed loops, interpreted).
"""

import numpy as np

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.contract import Measurement
from hvac_mpc.models import Environment, Parameters, SimulatedPlant
from hvac_mpc.mpc.estimator import MEASURED, finite_or, measured_values
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.valve_map import VALVE_NAMES, ValveMap


def _textbook_update(ekf, values, ok, u, setpoint):
    """The Joseph-form update on the used readings only (numpy, no masking)."""
    hz, Ht = ekf.h(ekf.z, u, setpoint, ekf.p)
    H = Ht.T[ok]
    R = np.diag(ekf.R_diag[ok])
    S = H @ ekf.P @ H.T + R
    K = np.linalg.solve(S, H @ ekf.P).T
    z = ekf.z + K @ (values[ok] - hz[ok])
    IKH = np.eye(ekf.nz) - K @ H
    P = IKH @ ekf.P @ IKH.T + K @ R @ K.T
    return z, 0.5 * (P + P.T)


def test_estimator_update_with_missing_readings_equals_the_update_on_the_used_ones():
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    ekf = ctrl.ekf
    u = solve_time.INITIAL.vector()
    first = Measurement(0.0, 18.0, 0.03, 26.0, water_temp_c=6.0, heater_outlet_temp_c=20.0)
    ekf.initialise(first, u, 5.0)
    ekf.predict(u, 5.0)
    rng = np.random.default_rng(4)
    ekf.P = ekf.P + 0.01 * np.diag(rng.uniform(size=ekf.nz))  # not diagonal-dominated by the start
    for missing in ((), ("water_temp_c",), ("heater_outlet_temp_c", "volume_flow_m3s"), ("supply_temp_c",)):
        readings = dict(supply_temp_c=18.4, volume_flow_m3s=0.031, hvac_inlet_temp_c=25.7, water_temp_c=6.3,
                        heater_outlet_temp_c=19.0)
        for name in missing:
            readings[name] = float("nan")
        m = Measurement(1.0, readings["supply_temp_c"], readings["volume_flow_m3s"], readings["hvac_inlet_temp_c"],
                        water_temp_c=readings["water_temp_c"], heater_outlet_temp_c=readings["heater_outlet_temp_c"])
        values, ok = ekf.readings(m)
        assert {n for n, used in zip(MEASURED, ok) if not used} == set(missing)
        z_ref, P_ref = _textbook_update(ekf, values, ok, u, 5.0)
        z0, P0 = ekf.z.copy(), ekf.P.copy()
        assert ekf.update(m, u, 5.0) == 5 - len(missing)
        assert np.allclose(ekf.z, z_ref, rtol=1e-10, atol=1e-12)
        assert np.allclose(ekf.P, P_ref, rtol=1e-9, atol=1e-14)
        assert not np.allclose(ekf.z, z0)
        ekf.z, ekf.P = z0, P0


def test_three_valves_convert_in_one_call_as_each_does_alone():
    vm = ValveMap(Parameters())
    rng = np.random.default_rng(0)
    v = np.vstack([rng.uniform(-0.1, 1.1, (500, 3)), [[0, 0, 0], [1, 1, 1], [0.5, 0.0, 1.0]]])
    theta = np.vstack([rng.uniform(-5, 105, (500, 3)), [[0, 0, 0], [100, 100, 100], [50, 0, 100]]])
    one_by_one = np.stack([vm.angle(n, v[:, i]) for i, n in enumerate(VALVE_NAMES)], axis=-1)
    assert np.allclose(vm.angles(v), one_by_one, rtol=0.0, atol=1e-9)
    one_by_one = np.stack([vm.opening(n, theta[:, i]) for i, n in enumerate(VALVE_NAMES)], axis=-1)
    assert np.allclose(vm.openings(theta), one_by_one, rtol=0.0, atol=1e-12)


def _run(ctrl, plant, start_k, steps):
    out = []
    for k in range(start_k, start_k + steps):
        res = ctrl.step(plant.read(), solve_time.reference_at(float(k)))
        plant.apply(res.command)
        plant.advance()
        out.append((res.command.vector(), res.stats["iterations"], res.stats["qp_solves"]))
    return out


def test_a_reset_controller_answers_exactly_as_a_new_one():
    settings = MpcSettings(codegen=False, deadline_s=3600.0)  # no wall-clock fallback on a loaded machine
    used = MpcController(settings=settings)
    plant = SimulatedPlant(seed=5, environment=Environment(solve_time.INLET_C, 5.0))
    plant.settle(solve_time.INITIAL)
    used.reset(plant.command)
    _run(used, plant, 20, 15)  # warm: OSQP's workspace holds multipliers and a step size of this run
    assert not used.solver.clean
    fresh = MpcController(settings=settings)
    runs = []
    for ctrl in (used, fresh):
        plant = SimulatedPlant(seed=6, environment=Environment(solve_time.INLET_C, 5.0))
        plant.settle(solve_time.INITIAL)
        ctrl.reset(plant.command)
        assert ctrl.solver.clean
        runs.append(_run(ctrl, plant, 0, 12))
    for (cmd_a, it_a, qp_a), (cmd_b, it_b, qp_b) in zip(*runs):
        assert np.array_equal(cmd_a, cmd_b)
        assert (it_a, qp_a) == (it_b, qp_b)


def test_a_step_makes_one_qp_and_three_calls_into_generated_code_with_one_qp_per_reference_change():
    """Deterministic counts of the hot path (docs/architecture.md, 'One control step'): with
    ``reference_change_qps=1`` one QP per step after the cold start, the reference change at 30 s
    included; per step three calls from Python into generated code (the estimator's measurement
    update, the QP gradient, and the estimator's time update fused with the next QP's data), the
    commands those of the separate calls; a generous time bound."""
    from hvac_mpc.mpc.casadi_eval import BufferedFunction

    def run(fused: bool):
        ctrl = MpcController(settings=MpcSettings(codegen=False, reference_change_qps=1, deadline_s=3600.0))
        if not fused:
            ctrl.solver._predict_qp = None  # the estimator's prediction and the QP data apart
        hot = {id(f): name for name, f in (
            ("ekf_update", ctrl.ekf._update), ("ekf_predict", ctrl.ekf._predict), ("qp_gradient", ctrl.solver._qp_gradient),
            ("qp_data", ctrl.solver._qp_data), ("predict_qp_data", ctrl.solver._predict_qp))}
        calls: list[str] = []
        original, original_views = BufferedFunction.__call__, BufferedFunction.views

        def counted(self, *args):
            if id(self) in hot:
                calls.append(hot[id(self)])
            return original(self, *args)

        def counted_views(self, *args):  # the same call, its result buffers handed back without copies
            if id(self) in hot:
                calls.append(hot[id(self)])
            return original_views(self, *args)

        loop = solve_time.Loop(ctrl, seed=7)
        per_step, solves, times, commands, factors = [], [], [], [], []
        BufferedFunction.__call__, BufferedFunction.views = counted, counted_views
        try:
            for k in range(34):
                calls.clear()
                res = loop.step(k)
                assert res.stats["fallback"] is None
                per_step.append(sorted(calls))
                solves.append(res.stats["qp_solves"])
                times.append(res.stats["step_time_s"])
                commands.append(res.command.vector())
                factors.append(res.stats["flow_weight_factor"])
        finally:
            BufferedFunction.__call__, BufferedFunction.views = original, original_views
        return ctrl, per_step, solves, times, np.array(commands), factors

    def new_weights(factors):  # the flow-trade cap changed the weights: the prepared QP data are made again
        return [k for k in range(1, len(factors)) if factors[k] != factors[k - 1]]

    ctrl, per_step, solves, times, commands, factors = run(fused=True)
    assert solve_time.reference_at(30.0) != solve_time.reference_at(29.0)
    assert 1 <= solves[0] <= ctrl.settings.cold_start_qps
    assert solves[1:] == [1] * 33
    moved = new_weights(factors)
    assert len(moved) < 8
    for k in range(1, 34):
        extra = ["qp_data"] if k in moved else []
        assert per_step[k] == sorted(["ekf_update", "predict_qp_data", "qp_gradient"] + extra), k
    assert np.median(times[1:]) < 0.25  # interpreted, about 2-5 ms quiet, 60 ms seen at load 14; a rebuild per step takes seconds
    _, apart, _, _, commands_apart, factors_apart = run(fused=False)
    assert factors_apart == factors
    for k in range(1, 34):
        extra = ["qp_data"] if k in moved else []
        assert apart[k] == sorted(["ekf_predict", "ekf_update", "qp_data", "qp_gradient"] + extra), k
    assert np.array_equal(commands, commands_apart)


def test_steady_steps_end_in_osqps_first_pass_and_the_settings_reach_osqp():
    """OSQP's first pass without over-relaxation (``MpcSettings.osqp_first_pass_iter``): warm-started
    from the shifted plan, more than half of the steady steps' QPs meet the first pass's tolerance
    (OSQP says solved) where the over-relaxed iterations alone take at least one check interval; the
    equilibration passes and the duality-gap check are what the settings say. These settings are not
    all the defaults (the first pass is off: README "Solve time")."""
    fast = dict(osqp_scaling=4, osqp_check_dualgap=False, osqp_first_pass_iter=4)

    def run(**kw):
        ctrl = MpcController(settings=MpcSettings(codegen=False, deadline_s=3600.0, **kw))
        loop = solve_time.Loop(ctrl, seed=7)
        stats = []
        for k in range(40):
            res = loop.step(k)
            assert res.stats["fallback"] is None
            stats.append(res.stats)
        return ctrl, stats

    ctrl, stats = run(**fast)
    s = ctrl.settings
    assert s.osqp_first_pass_iter < s.osqp_check_termination
    osqp_settings = ctrl.solver.solver.settings
    assert (osqp_settings.scaling, bool(osqp_settings.check_dualgap)) == (s.osqp_scaling, s.osqp_check_dualgap)
    steady = [st for k, st in enumerate(stats) if k >= 12 and st["qp_solves"] == 1]
    in_pass = [st for st in steady if st["iterations"] <= s.osqp_first_pass_iter]
    assert len(in_pass) > 0.5 * len(steady)
    assert all(st["status"] == "solved" for st in in_pass)
    _, stats_off = run(**{**fast, "osqp_first_pass_iter": 0})
    assert all(st["iterations"] >= s.osqp_check_termination for st in stats_off)
    assert sum(st["iterations"] for st in stats[12:]) < 0.6 * sum(st["iterations"] for st in stats_off[12:])


def test_the_estimators_numpy_shortcuts_give_the_values_of_their_general_forms():
    """The disturbances as numpy equal the CasADi expression's, and the supply reading's normalised innovation
    against the thermocouple state now (the plain comparison) equals the weighted sums of a dead-time comparison
    at the unit weights, to the bit."""
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    ekf = ctrl.ekf
    u = solve_time.INITIAL.vector()
    ekf.initialise(Measurement(0.0, 18.0, 0.03, 26.0, water_temp_c=6.0, heater_outlet_temp_c=20.0), u, 5.0)
    ekf.predict(u, 5.0)
    ekf.P = ekf.P + 0.01 * np.diag(np.random.default_rng(2).uniform(size=ekf.nz))
    for hold in (True, False):
        ekf.hold_water = hold
        casadi = np.asarray(ekf.disturbance(ekf.z, 4.5), float).ravel()
        assert np.array_equal(ekf.disturbance_values(4.5), casadi)
    unit = ekf.c_now.copy()  # the same weights, not the filter's own array: the general sums
    ekf._note_supply_innovation(18.3, True, ekf.c_now, 0.0025)
    fast = (ekf.supply_innovation_c, ekf.supply_nis)
    ekf._note_supply_innovation(18.3, True, unit, 0.0025)
    assert (ekf.supply_innovation_c, ekf.supply_nis) == fast
    assert np.isfinite(fast[1]) and fast[1] > 0.0


def test_the_readings_converted_at_once_are_those_of_each_alone():
    """The five readings as one array equal each converted on its own (:func:`finite_or`): plain numbers, a missing
    reading (None), nan, numpy scalars, a numeric string; where one is not a number at all, each on its own gives it
    nan. An infinite reading stays infinite, and :meth:`DisturbanceEkf.readings` leaves it unused all the same."""

    class Reading:
        def __init__(self, **values):
            self.__dict__.update(values)

    cases = [dict(supply_temp_c=18.4, volume_flow_m3s=0.031, hvac_inlet_temp_c=25.7, water_temp_c=6.3,
                  heater_outlet_temp_c=19.0),
             dict(supply_temp_c=np.float32(18.4), volume_flow_m3s=np.float64(0.031), hvac_inlet_temp_c=26,
                  water_temp_c=None, heater_outlet_temp_c=float("nan")),
             dict(supply_temp_c="18.5", volume_flow_m3s=True, hvac_inlet_temp_c=25.0),
             dict(supply_temp_c="warm", volume_flow_m3s=object(), hvac_inlet_temp_c=25.0, water_temp_c=[1.0]),
             dict(supply_temp_c=float("inf"), volume_flow_m3s=-float("inf"), hvac_inlet_temp_c=25.0)]
    ekf = MpcController(settings=MpcSettings(codegen=False)).ekf
    for case in cases:
        m = Reading(**case)
        each = np.array([finite_or(getattr(m, n, None), np.nan) for n in MEASURED])
        at_once = measured_values(m)
        finite = np.isfinite(at_once)
        assert np.array_equal(at_once[finite], each[finite]) and np.array_equal(np.isfinite(each), finite)
        values, ok = ekf.readings(m)
        assert np.array_equal(ok, np.isfinite(each) & ekf.use)
        assert np.array_equal(values, np.where(ok, each, 0.0))


def test_the_preparations_comparison_is_numpys_array_equal():
    """:func:`~hvac_mpc.mpc.rti_osqp.same_values` (the reference and weights against the preparation's) answers as
    ``np.array_equal``: equal values, another value, nan (equal to nothing), signed zeros, another shape."""
    from hvac_mpc.mpc.rti_osqp import same_values
    a = np.array([22.0, 0.03, 0.0, 0.0, 0.0, 0.0, 0.0])
    others = [a.copy(), a + 1e-15, np.r_[a[:-1], -0.0], np.r_[np.nan, a[1:]], a[:-1], a.reshape(1, -1),
              np.zeros(7)]
    for b in others:
        assert same_values(a, b) == np.array_equal(a, b)
    nan = np.r_[np.nan, a[1:]]
    assert same_values(nan, nan.copy()) == np.array_equal(nan, nan.copy()) is False
    assert [same_values(a, b) for b in others].count(True) == 2  # the copy and the signed zero
