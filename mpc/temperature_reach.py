"""Supply temperature out of reach, as the box shows it: the actuators that move it at their limits.

:mod:`hvac_mpc.mpc.priorities` reports the supply temperature out of reach only from its steady-state
problem, and solves that only while the flow reference is in doubt. A temperature that the heater cannot
reach at any flow the controller holds (heating at the heater's power or its PTC line), or that the
cooler cannot reach (the chiller's water too warm), needs no model to show itself: the actuators that
move the supply temperature toward the reference sit at their limits and the reading stays away from
the reference without closing in. :class:`SaturatedTemperature` watches for that and reports the gap
(degC) under ``supply_temp_c`` in ``stats["out_of_reach"]``, the name the priorities use.

Saturated means, in the command just applied (physical units):
- heating (reading below the reference): the heater command at its upper bound of this step (its
  power limit, the PTC line or its rate limit) and valve a at its upper bound (all air through the
  core, or the trapped-air cap);
- cooling (reading above the reference): the heater off and valve a at its upper bound.
The report starts once that has held for ``hold_s`` with the reading more than ``tolerance_c`` from the
reference, and the reading's approach over that window, carried on for ``outlook_s``, would still leave
it more than ``tolerance_c`` away (a heater body still warming up is not out of reach; the window's
first and last ``smooth_n`` readings are averaged against the sensor noise); it ends at once when an
actuator leaves its limit or the reading comes within ``tolerance_c``. The gap reported is the smoothed
distance now. ASSUMPTION: ``hold_s`` 20 s and ``outlook_s`` 60 s, about the heater body's and the
thermocouple's settling (thesis sec. 4.5.2, 5.4); the margins below are the command's resolution,
not physics.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from .ocp import HEATING_CMD_W

#: Distance of a command from its bound that still counts as at the bound: heater W, valve a %.
HEATER_MARGIN_W = 1.0
VALVE_MARGIN_PCT = 1.0


class SaturatedTemperature:
    """Reports the supply temperature out of reach while its actuators are saturated (module docstring)."""

    def __init__(self, i_heater: int, i_valve_a: int, dt_s: float, tolerance_c: float = 0.3,
                 hold_s: float = 20.0, outlook_s: float = 60.0, smooth_n: int = 5):
        self.i_heater, self.i_valve_a = int(i_heater), int(i_valve_a)
        self.tolerance_c = float(tolerance_c)
        self._needed = max(2 * smooth_n, int(round(hold_s / dt_s)))
        self._outlook = outlook_s / ((self._needed - smooth_n) * dt_s)  # outlook over the averages' spacing
        self._smooth_n = int(smooth_n)
        self._errors: deque[float] = deque(maxlen=self._needed)
        self._heating: bool | None = None

    def reset(self) -> None:
        """Forget the history (a new start, a fallback)."""
        self._errors.clear()
        self._heating = None

    def update(self, reading_c: float | None, reference_c: float, u_cmd: np.ndarray, u_hi: np.ndarray) -> float | None:
        """The gap to report (degC, >= 0) after this step's command, or ``None``.

        ``reading_c``: the supply temperature reading (a non-finite or missing reading forgets the
        history); ``u_cmd``, ``u_hi``: the command applied and the upper bounds it was projected on."""
        if reading_c is None or not math.isfinite(reading_c):
            self._errors.clear()
            return None
        error = float(reference_c) - float(reading_c)  # > 0: colder than asked
        if abs(error) <= self.tolerance_c or not self._saturated(error, u_cmd, u_hi):
            self._errors.clear()
            return None
        if self._heating is not None and self._heating != (error > 0):
            self._errors.clear()
        self._heating = error > 0
        self._errors.append(abs(error))
        if len(self._errors) < self._needed:
            return None
        window = np.fromiter(self._errors, float)
        now, then = window[-self._smooth_n:].mean(), window[:self._smooth_n].mean()
        return float(now) if now - self._outlook * max(then - now, 0.0) > self.tolerance_c else None

    def _saturated(self, error: float, u_cmd: np.ndarray, u_hi: np.ndarray) -> bool:
        valve_a_full = u_cmd[self.i_valve_a] >= u_hi[self.i_valve_a] - VALVE_MARGIN_PCT
        if error > 0:
            return bool(valve_a_full and u_cmd[self.i_heater] >= u_hi[self.i_heater] - HEATER_MARGIN_W)
        return bool(valve_a_full and u_cmd[self.i_heater] <= HEATING_CMD_W)
