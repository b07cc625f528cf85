"""The independent box: states, sub-stepping and the plant interface (apply, advance, read, truth, settle).

Same surface as ``hvac_mpc.models.plant.SimulatedPlant`` so benchmark code can drive either; the
physics are the pure functions of :mod:`.physics`. States: blower-motor temperature rise, chiller
water temperature and its two-point control's on/off, heater body temperature, thermocouple
temperature and the transport-delay line. Flows and the heater's air node are algebraic (the
blower and the 14 mg air node settle far faster than a sub-step).

Outputs are latched at the end of :meth:`IndependentBox.advance` (and by :meth:`settle`), as a
sampled sensor: a command applied at time t shows in the readings from t + dt_s on.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from hvac_mpc.contract import INPUTS, Command, Measurement

from . import constants as k
from . import physics as ph
from .variants import Variant, get_variant

#: Actuator ranges in ``INPUTS`` order (docs/model.md sec. 2).
INPUT_LOWER = np.array([k.BLOWER_MIN_W, 0.0, k.VALVE_MIN_PCT, k.VALVE_MIN_PCT, k.VALVE_MIN_PCT, k.VALVE_MIN_PCT])
INPUT_UPPER = np.array([k.BLOWER_MAX_W, k.HEATER_MAX_W, k.VALVE_MAX_PCT, k.VALVE_MAX_PCT, k.VALVE_MAX_PCT,
                        k.VALVE_MAX_PCT])


@dataclass(frozen=True)
class OperatingPoint:
    """Algebraic part of the box for one command and inlet temperature (flows in m3/s, kg/s; W/K)."""

    blower_w: float
    heater_cmd_w: float
    bypass: float
    shares: tuple[float, float, float]     # outlet shares m, f, w of the total flow
    volume_flow_m3s: float                 # at the inlet (where the flow sensor is, thesis 2)
    mass_flow_kgs: float
    core_capacity_w_per_k: float           # m_dot through the core times c_pa
    heater_ua_w_per_k: float
    motor_target_c: float
    network_dp_pa: float                   # pressure drop over the outlet valves
    cooler_effectiveness: float = k.COOLER_SLOPE


def operating_point(u: np.ndarray, inlet_c: float, variant: Variant, net: ph.ValveNetwork) -> OperatingPoint:
    """Flows and heater coupling for command ``u`` (``INPUTS`` order, already clipped); ``inlet_c``: the air
    entering the box (degC)."""
    blower, heater, a, m, f, w = (float(x) for x in u)
    shift = variant.valve_shift_pct
    bypass = ph.bypass_fraction(ph.effective_angle(a, shift))
    g = net.conductances(*(ph.effective_angle(x, shift) for x in (m, f, w)))
    g_total = sum(g)
    r_net = 1.0 / g_total ** 2
    load = r_net + ph.box_resistance(bypass, net.r_core)
    flow = ph.blower_flow_m3s(blower, k.BLOWER_FLOW_PER_W * variant.blower_gain_scale, net.r_int, net.r_ref, load)
    mass = ph.air_density(inlet_c) * flow
    # the flow follows the valve's geometric split; the mixing share may depend on the flow too
    bypass = ph.flow_dependent_bypass(bypass, mass, variant.bypass_flow_exponent)
    core = (1.0 - bypass) * mass * k.CP_AIR
    effectiveness = (ph.cooler_effectiveness_ntu((1.0 - bypass) * mass, variant.cooler_ntu) if variant.cooler_ntu > 0.0
                     else k.COOLER_SLOPE)
    return OperatingPoint(
        blower_w=blower, heater_cmd_w=heater, bypass=bypass, shares=tuple(x / g_total for x in g),
        volume_flow_m3s=flow, mass_flow_kgs=mass, core_capacity_w_per_k=core,
        heater_ua_w_per_k=ph.heater_effective_ua(k.HEATER_KA_W_PER_K, core),
        motor_target_c=ph.motor_gain_c(blower), network_dp_pa=r_net * flow ** 2, cooler_effectiveness=effectiveness)


@dataclass
class BoxState:
    """Dynamic states (degC) and the chiller's relay."""

    motor_rise_c: float
    water_temp_c: float
    chiller_cooling: bool
    heater_temp_c: float
    sensor_c: float


def command_vector(command: Any) -> np.ndarray:
    """A command as a float array in ``INPUTS`` order (Command-like object, mapping or sequence)."""
    if hasattr(command, "vector"):
        u = np.asarray(command.vector(), float).ravel()
    elif isinstance(command, Mapping):
        missing = [n for n in INPUTS if n not in command]
        if missing:
            raise ValueError(f"command: missing {missing}; needs {list(INPUTS)}")
        u = np.array([float(command[n]) for n in INPUTS])
    else:
        u = np.asarray(command, float).ravel()
    if u.shape != (len(INPUTS),):
        raise ValueError(f"command must have {len(INPUTS)} values {list(INPUTS)}, got shape {u.shape}")
    bad = [n for n, x in zip(INPUTS, u) if not math.isfinite(x)]
    if bad:
        raise ValueError(f"command: {', '.join(bad)} not finite ({u.tolist()}); every input must be a finite number")
    return u


def _finite(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return value


class IndependentBox:
    """Simulated HVAC box written apart from the project's model, with a :class:`Variant` of its physics."""

    def __init__(self, variant: Variant | str | None = None, seed: int = 0, dt_s: float = 1.0,
                 inlet_temp_c: float = 25.0, chiller_setpoint_c: float = 5.0,
                 initial_command: Command | None = None, noise: bool = True):
        self.variant_name, self.variant = get_variant(variant)
        self.dt_s = _finite("dt_s", dt_s)
        if self.dt_s <= 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        self._n_sub = max(1, math.ceil(self.dt_s / k.SUBSTEP_S - 1e-9))
        self._h = self.dt_s / self._n_sub
        self._delay_n = int(round(self.variant.transport_delay_s / self._h))
        self._motor_factor = math.exp(-self._h / k.MOTOR_TAU_S)
        self._sensor_factor = math.exp(-self._h / (k.THERMOCOUPLE_TAU_S * self.variant.thermocouple_tau_scale))
        self._net = ph.valve_network()
        self._rng = np.random.default_rng(seed)
        self.noise = bool(noise)
        self.inlet_temp_c = _finite("inlet_temp_c", inlet_temp_c)
        self.chiller_setpoint_c = _finite("chiller_setpoint_c", chiller_setpoint_c)
        self.cabin_temp_c = self.variant.cabin_temp_c
        self.time_s = 0.0
        self._u = np.clip(command_vector(Command() if initial_command is None else initial_command), INPUT_LOWER, INPUT_UPPER)
        self._op = self._operating_point()
        self._delay: deque[float] = deque(maxlen=max(1, self._delay_n))
        self.state = BoxState(0.0, self.chiller_setpoint_c, True, self.inlet_temp_c, self.inlet_temp_c)
        self._y: dict[str, float] = {}
        self.settle()

    # ------------------------------------------------------------------ interface
    @property
    def command(self) -> Command:
        """The applied (clipped) command."""
        return Command.from_vector(self._u)

    def apply(self, command: Command | Mapping[str, float] | np.ndarray) -> np.ndarray:
        """Set the actuators, clipped to blower [30, 300] W, heater [0, 240] W, valves [0, 100] %.

        Returns the applied vector in ``INPUTS`` order; raises ValueError for a non-finite input.
        """
        self._u = np.clip(command_vector(command), INPUT_LOWER, INPUT_UPPER)
        self._op = self._operating_point()
        return self._u.copy()

    def advance(self, n_steps: int = 1) -> None:
        """Move ``n_steps`` samples of ``dt_s`` on (each in sub-steps of at most 0.25 s)."""
        if int(n_steps) != n_steps or n_steps < 0:
            raise ValueError(f"n_steps must be a non-negative integer, got {n_steps!r}")
        for _ in range(int(n_steps)):
            for _ in range(self._n_sub):
                self._substep()
            self.time_s += self.dt_s
        self._y = self._outputs()

    def read(self) -> Measurement:
        """Sensor readings at ``time_s`` (seeded Gaussian noise unless ``noise`` is off)."""
        y = self._y
        scale = self.variant.noise_scale
        e = (scale * self._rng.normal(0.0, 1.0, 5)).tolist() if self.noise else [0.0] * 5
        return Measurement(
            time_s=self.time_s,
            supply_temp_c=y["supply_temp_c"] + k.NOISE_SUPPLY_C * e[0],
            volume_flow_m3s=y["volume_flow_m3s"] + k.NOISE_FLOW_M3S * e[1],
            hvac_inlet_temp_c=self.inlet_temp_c + k.NOISE_INLET_C * e[2],
            water_temp_c=y["water_temp_c"] + k.NOISE_OTHER_C * e[3],
            chiller_setpoint_c=self.chiller_setpoint_c,
            heater_power_w=y["heater_power_w"],
            heater_outlet_temp_c=y["heater_outlet_temp_c"] + k.NOISE_OTHER_C * e[4],
        )

    def truth(self) -> dict[str, float]:
        """Noise-free outputs and internal signals at ``time_s`` (a copy)."""
        return dict(self._y)

    def set_environment(self, inlet_temp_c: float | None = None, chiller_setpoint_c: float | None = None,
                        cabin_temp_c: float | None = None) -> None:
        """Change the inlet air temperature, the chiller set point or the cabin temperature (degC)."""
        if inlet_temp_c is not None:
            self.inlet_temp_c = _finite("inlet_temp_c", inlet_temp_c)
            self._op = self._operating_point()
        if chiller_setpoint_c is not None:
            self.chiller_setpoint_c = _finite("chiller_setpoint_c", chiller_setpoint_c)
        if cabin_temp_c is not None:
            self.cabin_temp_c = _finite("cabin_temp_c", cabin_temp_c)
            if self.variant.recirculation_share:
                self._op = self._operating_point()

    def settle(self, command: Command | None = None) -> None:
        """Put the box at rest for ``command`` (or the current one): every state at its steady value,
        the chiller water at its set point with the compressor on."""
        if command is not None:
            self.apply(command)
        op, v = self._op, self.variant
        rise = op.motor_target_c
        cooled = ph.cooler_outlet_c(self._entering_c() + rise, self.chiller_setpoint_c, v.cooler_literal_fit,
                                    op.cooler_effectiveness)
        heater = ph.heater_steady_c(cooled, op.heater_cmd_w, op.heater_ua_w_per_k, v.heater_power_scale,
                                    v.ptc_power_fall, v.heater_wall_ua_w_per_k, self._entering_c())
        self.state = BoxState(rise, self.chiller_setpoint_c, True, heater, 0.0)
        mixed = self._mixed_c()
        self._delay.clear()
        self._delay.extend([mixed] * self._delay_n)
        self.state.sensor_c = self._sensor_target_c(self._supply_air_c(mixed))
        self._y = self._outputs()

    # ------------------------------------------------------------------ internals
    def _operating_point(self) -> OperatingPoint:
        return operating_point(self._u, self._entering_c(), self.variant, self._net)

    def _entering_c(self) -> float:
        """Air entering the box (the logged inlet air unless cabin air is drawn in behind the sensor)."""
        return ph.entering_air_c(self.inlet_temp_c, self.cabin_temp_c, self.variant.recirculation_share)

    def _sensor_target_c(self, supply_air_c: float) -> float:
        return ph.thermocouple_target_c(supply_air_c, self.state.heater_temp_c, self.variant.tc_radiation_share)

    def _cooled_c(self) -> float:
        return ph.cooler_outlet_c(self._entering_c() + self.state.motor_rise_c, self.state.water_temp_c,
                                  self.variant.cooler_literal_fit, self._op.cooler_effectiveness)

    def _heated_c(self, cooled_c: float) -> float:
        return ph.heater_air_outlet_c(self.state.heater_temp_c, cooled_c, k.HEATER_KA_W_PER_K,
                                      self._op.core_capacity_w_per_k)

    def _mixed_c(self) -> float:
        return ph.mix_c(self._op.bypass, self._entering_c() + self.state.motor_rise_c,
                        self._heated_c(self._cooled_c()))

    def _supply_air_c(self, arriving_c: float) -> float:
        return ph.duct_outlet_c(arriving_c, self.cabin_temp_c, self.variant.duct_loss_ua_w_per_k,
                                self._op.mass_flow_kgs)

    def _arriving_c(self, mixed_c: float) -> float:
        """Mixed air arriving at the sensor now: the value ``transport_delay_s`` ago (or now)."""
        return self._delay[0] if self._delay_n else mixed_c

    def _substep(self) -> None:
        s, op, v, h = self.state, self._op, self.variant, self._h
        cooled = self._cooled_c()
        entering = self._entering_c()
        mixed = ph.mix_c(op.bypass, entering + s.motor_rise_c, self._heated_c(cooled))
        arriving = self._arriving_c(mixed)
        if self._delay_n:
            self._delay.append(mixed)
        s.sensor_c = ph.relax(s.sensor_c, self._sensor_target_c(self._supply_air_c(arriving)), self._sensor_factor)
        s.heater_temp_c = ph.heater_body_step(s.heater_temp_c, cooled, op.heater_cmd_w, op.heater_ua_w_per_k, h,
                                              v.heater_power_scale, v.ptc_power_fall, v.heater_wall_ua_w_per_k,
                                              entering)
        s.motor_rise_c = ph.relax(s.motor_rise_c, op.motor_target_c, self._motor_factor)
        s.chiller_cooling = ph.chiller_relay(s.water_temp_c, self.chiller_setpoint_c, s.chiller_cooling)
        s.water_temp_c = ph.chiller_ramp(s.water_temp_c, self.chiller_setpoint_c, s.chiller_cooling, h,
                                         v.chiller_rate_scale)

    def _outputs(self) -> dict[str, float]:
        s, op, v = self.state, self._op, self.variant
        cooled = self._cooled_c()
        heated = self._heated_c(cooled)
        mixed = ph.mix_c(op.bypass, self._entering_c() + s.motor_rise_c, heated)
        supply_air = self._supply_air_c(self._arriving_c(mixed))
        outlet_total = op.volume_flow_m3s
        if v.outlet_density_correction:
            outlet_total = op.mass_flow_kgs / ph.air_density(supply_air)
        flow_m, flow_f, flow_w = (share * outlet_total for share in op.shares)
        return {
            "supply_temp_c": s.sensor_c,
            "supply_air_temp_c": supply_air,
            "mixed_air_temp_c": mixed,
            "volume_flow_m3s": ph.flow_sensor_m3s(op.volume_flow_m3s, self.inlet_temp_c),
            "flow_m_m3s": flow_m, "flow_f_m3s": flow_f, "flow_w_m3s": flow_w,
            "mass_flow_kgs": op.mass_flow_kgs,
            "bypass_fraction": op.bypass,
            "network_dp_pa": op.network_dp_pa,
            "motor_rise_c": s.motor_rise_c,
            "cooler_outlet_temp_c": cooled,
            "heater_temp_c": s.heater_temp_c,
            "heater_power_w": ph.heater_electric_w(op.heater_cmd_w, s.heater_temp_c, v.heater_power_scale,
                                                   v.ptc_power_fall),
            "heater_outlet_temp_c": heated,
            "water_temp_c": s.water_temp_c,
            "chiller_cooling": float(s.chiller_cooling),
            "chiller_setpoint_c": self.chiller_setpoint_c,
            "hvac_inlet_temp_c": self.inlet_temp_c,
            "cabin_temp_c": self.cabin_temp_c,
        }
