"""The simulated plant: the stand-in for the real box, with switchable non-ideal effects.

Built on the same component code as :class:`HvacModel` (it *is* an ``HvacModel`` with effects
switched on), plus the discrete parts a smooth model cannot hold: the chiller's two-point
controller and seeded sensor noise. Interface as the hardware will have it::

    plant.apply(command)      # actuator commands, clipped to the actuator ranges
    plant.advance()           # one sample (1 s by default)
    m = plant.read()          # sensor readings
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np

from . import chiller
from hvac_mpc.contract import Command, Measurement

from .box import INPUT_LOWER, INPUTS, MODEL_EFFECTS, HvacModel, input_upper, validate_effects
from .parameters import Parameters

#: All non-ideal effects of the plant, each switchable by name (docs/model.md sec. 1).
PLANT_EFFECTS = ("ptc_power_fall", "chiller_hysteresis", "motor_asymmetry", "bypass_flow",
                 "trapped_air", "sensor_noise", "fan_curve", "valve_leakage")


@dataclass
class Environment:
    """Exogenous conditions: inlet air temperature and chiller set point (degC)."""

    inlet_temp_c: float = 25.0
    chiller_setpoint_c: float = 5.0


class SimulatedPlant:
    """Simulated HVAC box with named non-ideal effects (``PLANT_EFFECTS``) and seeded noise."""

    def __init__(self, params: Parameters | None = None, effects: Iterable[str] = PLANT_EFFECTS,
                 seed: int = 0, dt_s: float = 1.0, environment: Environment | None = None,
                 initial_command: Command | None = None):
        self.params = params or Parameters()
        self.effects = validate_effects(effects, PLANT_EFFECTS)
        model_effects = set(self.effects) & set(MODEL_EFFECTS)
        if "chiller_hysteresis" in self.effects:
            model_effects.add("chiller_asymmetry")
        self.model = HvacModel(self.params, model_effects, dt_s=dt_s, substeps=max(2, int(round(dt_s / 0.5))))
        self.dt_s = float(dt_s)
        self.env = environment or Environment()
        self._rng = np.random.default_rng(seed)
        self._p = self.model.p_default
        self._lo = np.array([INPUT_LOWER[n] for n in INPUTS])
        self._hi = np.array([input_upper(self.params)[n] for n in INPUTS])
        self.time_s = 0.0
        self._u = (initial_command or Command()).vector()
        self._chiller_on = True
        self.x = self.model.steady_state(self._u, self._disturbance_vector(self.env.chiller_setpoint_c))
        self._y = self.model.y(self.x, self._u, self._disturbance_vector(self.env.chiller_setpoint_c), self._p)

    # ------------------------------------------------------------------ interface
    def apply(self, command: Command | Mapping[str, float] | np.ndarray) -> np.ndarray:
        """Set actuator commands (clipped to actuator ranges, as the power stages and servos do)."""
        if isinstance(command, Command):
            u = command.vector()
        elif isinstance(command, Mapping):
            u = np.array([float(command[n]) for n in INPUTS])
        else:
            u = np.asarray(command, float).ravel()
        if u.shape != (len(INPUTS),) or not np.all(np.isfinite(u)):
            raise ValueError(f"command must be {len(INPUTS)} finite values {list(INPUTS)}, got {u!r}")
        self._u = np.clip(u, self._lo, self._hi)
        return self._u.copy()

    def advance(self, n_steps: int = 1) -> None:
        """Advance the plant by ``n_steps`` samples of ``dt_s``."""
        for _ in range(n_steps):
            d = self._disturbance_vector(self._chiller_target())
            self.x = np.asarray(self.model.step(self.x, self._u, d, self._p)).ravel()
            self.time_s += self.dt_s
        self._y = self.model.y(self.x, self._u, self._disturbance_vector(self._chiller_target(update=False)), self._p)

    def read(self) -> Measurement:
        """Sensor readings (with seeded noise when 'sensor_noise' is on)."""
        y = self.truth()
        noise = "sensor_noise" in self.effects
        rnd = (lambda s: float(self._rng.normal(0.0, s))) if noise else (lambda s: 0.0)
        p = self.params
        return Measurement(
            time_s=self.time_s,
            supply_temp_c=y["supply_temp_c"] + rnd(p.noise_supply_temp_c),
            volume_flow_m3s=y["volume_flow_m3s"] + rnd(p.noise_flow_m3s),
            hvac_inlet_temp_c=self.env.inlet_temp_c + rnd(p.noise_inlet_temp_c),
            water_temp_c=y["water_temp_c"] + rnd(p.noise_inlet_temp_c),
            chiller_setpoint_c=self.env.chiller_setpoint_c,
            heater_power_w=y["heater_power_w"],
            heater_outlet_temp_c=y["heater_outlet_temp_c"] + rnd(p.noise_supply_temp_c),
        )

    def truth(self) -> dict[str, float]:
        """Noise-free outputs (model output names), for benchmarks and tests only."""
        return self.model.outputs.dict(self._y)

    @property
    def command(self) -> Command:
        return Command.from_vector(self._u)

    def set_environment(self, inlet_temp_c: float | None = None, chiller_setpoint_c: float | None = None) -> None:
        if inlet_temp_c is not None:
            self.env.inlet_temp_c = float(inlet_temp_c)
        if chiller_setpoint_c is not None:
            self.env.chiller_setpoint_c = float(chiller_setpoint_c)

    def settle(self, command: Command | None = None) -> None:
        """Put the plant at rest for a command and the current environment."""
        if command is not None:
            self.apply(command)
        self.x = self.model.steady_state(self._u, self._disturbance_vector(self.env.chiller_setpoint_c), self._p)
        self._chiller_on = True
        self._y = self.model.y(self.x, self._u, self._disturbance_vector(self.env.chiller_setpoint_c), self._p)

    # ------------------------------------------------------------------ internals
    def _chiller_target(self, update: bool = True) -> float:
        if "chiller_hysteresis" not in self.effects:
            return self.env.chiller_setpoint_c
        water = self.x[self.model.states.index("water_temp_c")]
        target, on = chiller.hysteresis_target_c(water, self.env.chiller_setpoint_c, self._chiller_on, self.params)
        if update:
            self._chiller_on = on
        return target

    def _disturbance_vector(self, chiller_target_c: float) -> np.ndarray:
        return self.model.d_vector(self.env.inlet_temp_c, chiller_target_c)
