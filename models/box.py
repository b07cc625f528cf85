"""The HVAC box as a CasADi model that knows its states, inputs, disturbances and outputs by name.

Air path (thesis fig. 7, docs/model.md sec. 1): blower (flow, motor heating) -> valve a splits
into bypass b(a) and core path -> cooler core (chilled water) -> PTC heater -> mixing ->
thermocouple -> parallel valves m, f, w.

The numeric parameters enter as a symbolic vector ``p`` (names: :meth:`Parameters.scalar_names`),
so the same functions serve simulation, control and identification. Non-ideal effects are
structural switches chosen when the model is built (:data:`MODEL_EFFECTS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Iterable, Mapping, Sequence

import casadi as ca
import numpy as np

from hvac_mpc.contract import INPUTS

from . import air, blower, bypass, chiller, heater, sensors, valves
from .discovered import DiscoveredTerm, core_outlet_bounded_c, terms_at
from .parameters import Parameters

STATES = ("motor_rise_c", "water_temp_c", "heater_temp_c", "supply_sensor_c")
TRAP_STATE = "trap_air_temp_c"
#: Longest time constant of one lag of the transport-delay chain (s): a delay of D seconds becomes
#: ceil(D / this) first-order lags of D / n each (docs/robustness.md sec. 2).
DELAY_LAG_MAX_S = 1.0
DISTURBANCES = ("inlet_temp_c", "chiller_setpoint_c", "mix_offset_c", "flow_offset_m3s")
OUTPUTS = ("supply_temp_c", "volume_flow_m3s", "flow_m_m3s", "flow_f_m3s", "flow_w_m3s",
           "heater_temp_c", "supply_air_temp_c", "heater_outlet_temp_c", "heater_power_w",
           "water_temp_c", "mass_flow_kgs", "duct_air_temp_c")

#: Continuous effects the model can include (each off in the thesis model).
MODEL_EFFECTS = ("ptc_power_fall", "motor_asymmetry", "bypass_flow", "trapped_air", "fan_curve",
                 "valve_leakage", "chiller_asymmetry", "cooler_literal_fit")

INPUT_LOWER = {"blower_power_w": 30.0, "heater_cmd_w": 0.0, "valve_a_pct": 0.0,
               "valve_m_pct": 0.0, "valve_f_pct": 0.0, "valve_w_pct": 0.0}


@dataclass(frozen=True)
class Signals:
    """Named vector helper: index of each name and conversion to and from dicts."""

    names: tuple[str, ...]

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"unknown signal {name!r}; known: {list(self.names)}") from None

    def vector(self, values: Mapping[str, float], default: Mapping[str, float] | None = None) -> np.ndarray:
        merged = dict(default or {})
        merged.update(values)
        missing = [n for n in self.names if n not in merged]
        if missing:
            raise KeyError(f"missing signal(s) {missing}")
        return np.array([float(merged[n]) for n in self.names])

    def dict(self, vector: Sequence[float]) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, np.asarray(vector, float).ravel())}

    def __len__(self) -> int:
        return len(self.names)


def input_upper(p: Parameters) -> dict[str, float]:
    """Actuator upper bounds (docs/model.md sec. 2)."""
    return {"blower_power_w": p.blower_power_max_w, "heater_cmd_w": p.heater_power_max_w,
            "valve_a_pct": 100.0, "valve_m_pct": 100.0, "valve_f_pct": 100.0, "valve_w_pct": 100.0}


def validate_effects(effects: Iterable[str], allowed: Sequence[str]) -> frozenset[str]:
    effects = frozenset(effects)
    unknown = sorted(effects - set(allowed))
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; allowed: {list(allowed)}")
    return effects


def delay_lag_count(transport_delay_s: float) -> int:
    """Number of first-order lags standing in for a transport delay (0 for no delay)."""
    d = float(transport_delay_s)
    return 0 if d <= 0.0 else int(np.ceil(d / DELAY_LAG_MAX_S - 1e-9))


def delay_state_names(transport_delay_s: float) -> tuple[str, ...]:
    """States of the transport-delay chain between the mixing point and the thermocouple."""
    return tuple(f"duct_air_{i + 1}_c" for i in range(delay_lag_count(transport_delay_s)))


def rk4(ode, x, u, d, p, dt_s, substeps: int):
    """``substeps`` classical Runge-Kutta steps of ``ode(x, u, d, p)`` over ``dt_s`` (inputs held)."""
    h = dt_s / substeps
    for _ in range(substeps):
        k1 = ode(x, u, d, p)
        k2 = ode(x + h / 2 * k1, u, d, p)
        k3 = ode(x + h / 2 * k2, u, d, p)
        k4 = ode(x + h * k3, u, d, p)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


class HvacModel:
    """CasADi model of the box.

    Attributes ``states``, ``inputs``, ``disturbances``, ``outputs`` are :class:`Signals`;
    ``ode``, ``output`` and ``step`` are CasADi functions of ``(x, u, d, p)``.
    """

    def __init__(self, params: Parameters | None = None, effects: Iterable[str] = (), dt_s: float = 1.0,
                 substeps: int = 2, terms: Iterable[DiscoveredTerm] = ()):
        """``terms``: discovered terms (models/discovered.py) added to their balances."""
        self.params = params or Parameters()
        self.effects = validate_effects(effects, MODEL_EFFECTS)
        self.terms = tuple(terms)
        self.dt_s = float(dt_s)
        # the transport delay (Parameters.transport_delay_s) is a chain of equal lags from the mixed air to
        # the thermocouple; its length is structure (fixed here), its time constant a parameter
        self.delay_states = delay_state_names(self.params.transport_delay_s)
        state_names = STATES + self.delay_states + ((TRAP_STATE,) if "trapped_air" in self.effects else ())
        self.states = Signals(state_names)
        self.inputs = Signals(INPUTS)
        self.disturbances = Signals(DISTURBANCES)
        self.outputs = Signals(OUTPUTS)
        self.param_names = Parameters.scalar_names()
        self._curves = valves.curves(self.params)

        x = ca.SX.sym("x", len(self.states))
        u = ca.SX.sym("u", len(self.inputs))
        d = ca.SX.sym("d", len(self.disturbances))
        p = ca.SX.sym("p", len(self.param_names))
        xdot, y = self._equations(x, u, d, p)
        self.ode = ca.Function("ode", [x, u, d, p], [xdot], ["x", "u", "d", "p"], ["xdot"])
        self.output = ca.Function("output", [x, u, d, p], [y], ["x", "u", "d", "p"], ["y"])
        self.step = self.make_step(self.dt_s, substeps)
        self.p_default = np.array(self.params.vector())

    # ------------------------------------------------------------------ equations
    def _symbolic_params(self, p: ca.SX) -> SimpleNamespace:
        ns = {name: p[i] for i, name in enumerate(self.param_names)}
        for name in ("valve_m_table", "valve_f_table", "valve_w_table"):
            ns[name] = getattr(self.params, name)
        return SimpleNamespace(**ns)

    def algebraic(self, x, u, d, p) -> dict:
        """All intermediate quantities of the box for states x, inputs u, disturbances d."""
        e = self.effects
        prm = self._symbolic_params(p) if isinstance(p, ca.SX) else p
        sx = {n: x[i] for i, n in enumerate(self.states.names)}
        su = {n: u[i] for i, n in enumerate(INPUTS)}
        sd = {n: d[i] for i, n in enumerate(DISTURBANCES)}
        t_in = sd["inlet_temp_c"]
        p_b = su["blower_power_w"]
        a = su["valve_a_pct"]

        angles = valves.shifted_angles([su["valve_m_pct"], su["valve_f_pct"], su["valve_w_pct"]], prm)
        g = valves.branch_conductances(angles, prm, self._curves, leakage="valve_leakage" in e)
        b0 = bypass.bypass_fraction(a, prm)
        flow = blower.open_flow_m3s(p_b, prm) * blower.core_flow_factor(b0, prm)
        if "fan_curve" in e:
            g_open = valves.branch_conductances([100.0, 100.0, 100.0], prm, self._curves,
                                                leakage="valve_leakage" in e)
            flow = flow * blower.fan_curve_factor(valves.network_resistance(g),
                                                  valves.network_resistance(g_open), prm)
        flow = flow + sd["flow_offset_m3s"]
        mass_flow = air.density_kgm3(t_in, prm) * flow
        b = bypass.flow_dependent_bypass(b0, mass_flow, prm) if "bypass_flow" in e else b0

        t_enter = t_in  # discovered terms on the air entering the box (models/discovered.py)
        if any(t.location == "box_in" for t in self.terms):
            t_enter = t_in + terms_at(self.terms, "box_in", dict(t_in=t_in, t_cabin=prm.cabin_temp_c))
        t_blower = t_enter + sx["motor_rise_c"]
        t_cooler = chiller.cooler_outlet_c(t_blower, sx["water_temp_c"], prm, literal="cooler_literal_fit" in e)
        if any(t.location == "cooler_out" for t in self.terms):  # discovered terms on the air leaving the core,
            # before the split, the outlet held between the air entering the core and the water (models/discovered.py)
            t_cooler = core_outlet_bounded_c(t_cooler + terms_at(self.terms, "cooler_out", dict(
                t_in=t_in, t_blower=t_blower, t_water=sx["water_temp_c"], mass_flow=mass_flow, core_share=1.0 - b)),
                t_blower, sx["water_temp_c"])
        p_el = heater.electric_power_w(su["heater_cmd_w"], sx["heater_temp_c"], prm, ptc="ptc_power_fall" in e)
        core_flow = (1.0 - b) * mass_flow
        t_heater_out = heater.air_outlet_c(sx["heater_temp_c"], t_cooler, core_flow, prm)
        # the air leaving the heater as it mixes and is read: with an offset the heater body does not see (0 in the
        # thesis model; the estimator's own, docs/robustness.md sec. 2.13)
        t_heater_air = t_heater_out + prm.heater_air_offset_c
        t_mix = bypass.mix_c(b, t_blower, t_heater_air)
        if "trapped_air" in e:
            t_mix = t_mix + bypass.trap_release_c(sx[TRAP_STATE], t_mix, a, mass_flow, prm)
        # a heat flow into the mixed air (0 in the thesis model; the estimator's own, docs/robustness.md sec. 2.22)
        t_supply = t_mix + sd["mix_offset_c"] + air.heat_gain_c(
            prm.supply_heat_w, mass_flow, blower.least_mass_flow_kgs(t_in, prm), prm)
        if self.terms:
            t_supply = t_supply + terms_at(self.terms, "supply_air", dict(
                t_mix=t_mix, t_in=t_in, t_blower=t_blower, t_water=sx["water_temp_c"], mass_flow=mass_flow,
                core_share=1.0 - b, p_el=p_el, t_cabin=prm.cabin_temp_c, t_body=sx["heater_temp_c"]))
        t_duct = sx[self.delay_states[-1]] if self.delay_states else t_supply
        outlet = valves.split_flows(flow, g)
        return dict(prm=prm, sx=sx, su=su, sd=sd, flow=flow, mass_flow=mass_flow, bypass=b,
                    t_blower=t_blower, t_cooler=t_cooler, p_el=p_el, t_heater_out=t_heater_out,
                    t_heater_air=t_heater_air, t_mix=t_mix, t_supply=t_supply, t_duct=t_duct, outlet=outlet)

    def _equations(self, x, u, d, p):
        e = self.effects
        q = self.algebraic(x, u, d, p)
        prm, sx, su, sd = q["prm"], q["sx"], q["su"], q["sd"]
        rates = {
            "motor_rise_c": blower.motor_rise_rate_c_per_s(sx["motor_rise_c"], su["blower_power_w"], prm,
                                                            asymmetric="motor_asymmetry" in e),
            "water_temp_c": chiller.water_rate_c_per_s(sx["water_temp_c"], sd["chiller_setpoint_c"], prm,
                                                       asymmetric="chiller_asymmetry" in e),
            "heater_temp_c": heater.body_rate_c_per_s(sx["heater_temp_c"], q["t_heater_out"], q["p_el"], prm),
            "supply_sensor_c": sensors.lag_rate(sx["supply_sensor_c"], q["t_duct"], prm.tau_tc_s),
        }
        if any(t.location == "heater_body" for t in self.terms):  # a discovered heat flow into the body (W)
            rates["heater_temp_c"] = rates["heater_temp_c"] + terms_at(self.terms, "heater_body", dict(
                t_body=sx["heater_temp_c"], t_in=sd["inlet_temp_c"], p_el=q["p_el"])) / (
                prm.heater_mass_kg * prm.heater_c_j_per_kgk)
        if self.delay_states:
            tau = ca.fmax(prm.transport_delay_s, 1e-3) / len(self.delay_states)
            upstream = q["t_supply"]
            for name in self.delay_states:
                rates[name] = sensors.lag_rate(sx[name], upstream, tau)
                upstream = sx[name]
        if "trapped_air" in e:
            t_mix_no_trap = bypass.mix_c(q["bypass"], q["t_blower"], q["t_heater_air"])
            rates[TRAP_STATE] = bypass.trap_rate_c_per_s(sx[TRAP_STATE], sx["heater_temp_c"], t_mix_no_trap,
                                                         su["valve_a_pct"], prm)
        xdot = ca.vertcat(*[rates[n] for n in self.states.names])
        y = ca.vertcat(sx["supply_sensor_c"], q["flow"], *q["outlet"], sx["heater_temp_c"], q["t_supply"],
                       q["t_heater_air"], q["p_el"], sx["water_temp_c"], q["mass_flow"], q["t_duct"])
        return xdot, y

    # ------------------------------------------------------------------ discretisation
    def make_step(self, dt_s: float, substeps: int = 2) -> ca.Function:
        """Discrete step x+ = F(x, u, d, p) over ``dt_s`` by RK4 with ``substeps`` (inputs held)."""
        x = ca.SX.sym("x", len(self.states))
        u = ca.SX.sym("u", len(self.inputs))
        d = ca.SX.sym("d", len(self.disturbances))
        p = ca.SX.sym("p", len(self.param_names))
        xk = rk4(self.ode, x, u, d, p, dt_s, substeps)
        return ca.Function("step", [x, u, d, p], [xk], ["x", "u", "d", "p"], ["x_next"])

    def step_jacobians(self, step: ca.Function | None = None) -> ca.Function:
        """Function (x, u, d, p) -> (x_next, dF/dx, dF/du) for linearisation."""
        step = step or self.step
        x = ca.SX.sym("x", len(self.states))
        u = ca.SX.sym("u", len(self.inputs))
        d = ca.SX.sym("d", len(self.disturbances))
        p = ca.SX.sym("p", len(self.param_names))
        xn = step(x, u, d, p)
        return ca.Function("step_jac", [x, u, d, p], [xn, ca.jacobian(xn, x), ca.jacobian(xn, u)],
                           ["x", "u", "d", "p"], ["x_next", "A", "B"])

    # ------------------------------------------------------------------ conveniences
    def p_vector(self, params: Parameters | None = None) -> np.ndarray:
        return np.array((params or self.params).vector())

    def d_vector(self, inlet_temp_c: float, chiller_setpoint_c: float, mix_offset_c: float = 0.0,
                 flow_offset_m3s: float = 0.0) -> np.ndarray:
        return np.array([inlet_temp_c, chiller_setpoint_c, mix_offset_c, flow_offset_m3s], float)

    def y(self, x, u, d, p=None) -> np.ndarray:
        """Outputs as a numpy vector."""
        return np.asarray(self.output(x, u, d, self.p_default if p is None else p)).ravel()

    def steady_state(self, u, d, p=None) -> np.ndarray:
        """States at rest for constant inputs and disturbances (Newton on the ODE)."""
        p = self.p_default if p is None else p
        x = ca.SX.sym("x", len(self.states))
        g = ca.Function("g", [x], [self.ode(x, u, d, p)])
        solver = ca.rootfinder("ss", "newton", g, {"abstol": 1e-10, "max_iter": 200})
        t_in, t_set = float(d[0]), float(d[1])
        x0 = np.full(len(self.states), t_in)
        x0[self.states.index("motor_rise_c")] = 1.0
        x0[self.states.index("water_temp_c")] = t_set
        x0[self.states.index("heater_temp_c")] = t_in + 20.0
        return np.asarray(solver(x0)).ravel()
