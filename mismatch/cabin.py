"""The car's cabin in the loop: a thermal model of the cabin and the recirculation that feeds the box.

Written apart from the box models (numpy-free pure functions plus one coupling class); the
thesis's car recirculates cabin air and mixes outside air in by flaps (thesis sec. 2, fig. 7), so
the box's inlet temperature follows what the controller did earlier. Two nodes:

    C_air dT_air/dt = m_dot c_pa (T_supply - T_air) + hA_int (T_int - T_air) + UA_wall (T_out - T_air) + Q_driver
    C_int dT_int/dt = hA_int (T_air - T_int) + Q_solar

and the box inlet T_inlet = r T_air + (1 - r) T_out (r: recirculated share). Every number is an
ASSUMPTION for a small car's cabin (about 2.5 m3 of air), chosen to be plausible; see
:class:`CabinSetup`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

#: Specific heat of air, J/(kg K).
CP_AIR_J_PER_KGK = 1005.0
#: Sub-step of the cabin integration, s (the fastest cabin time constant is minutes).
CABIN_SUBSTEP_S = 0.5


@dataclass(frozen=True)
class CabinSetup:
    """Cabin parameters and conditions (temperatures degC, powers W, conductances W/K, capacities J/K).

    ASSUMPTIONS (small car cabin): air capacity 2.5 m3 x 1.2 kg/m3 x 1005 J/(kg K) plus light
    trim in contact with it, 1.2e4 J/K; interior masses (seats, dashboard, panels; about 60 kg at
    ~1 kJ/(kg K)) 6e4 J/K; air to interior 40 W/K (about 8 m2 at 5 W/(m2 K)); walls and glazing to
    outside 20 W/K; the driver's sensible heat 100 W; solar load on the interior 0 W unless given;
    recirculated share of the box's inlet air 0.7.
    """

    outside_temp_c: float = 32.0
    cabin_temp_c: float = 32.0
    interior_temp_c: float = 32.0
    recirculation: float = 0.7
    air_capacity_j_per_k: float = 1.2e4
    interior_capacity_j_per_k: float = 6.0e4
    air_interior_w_per_k: float = 40.0
    wall_w_per_k: float = 20.0
    driver_w: float = 100.0
    solar_w: float = 0.0

    def __post_init__(self) -> None:
        for name in ("outside_temp_c", "cabin_temp_c", "interior_temp_c"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and -40.0 <= v <= 80.0):
                raise ValueError(f"{name} = {v!r} is outside the allowed range [-40, 80]")
        if not (isinstance(self.recirculation, (int, float)) and 0.0 <= self.recirculation <= 1.0):
            raise ValueError(f"recirculation = {self.recirculation!r} is outside the allowed range [0, 1]")
        for name in ("air_capacity_j_per_k", "interior_capacity_j_per_k"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 1e2 <= v <= 1e7):
                raise ValueError(f"{name} = {v!r} is outside the allowed range [100, 1e7]")
        for name in ("air_interior_w_per_k", "wall_w_per_k", "driver_w", "solar_w"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.0 <= v <= 1e4):
                raise ValueError(f"{name} = {v!r} is outside the allowed range [0, 1e4]")

    def inlet_c(self, cabin_c: float) -> float:
        """The box's inlet air: recirculated cabin air mixed with outside air (degC)."""
        return self.recirculation * cabin_c + (1.0 - self.recirculation) * self.outside_temp_c


def cabin_rates(setup: CabinSetup, air_c: float, interior_c: float, supply_c: float,
                mass_flow_kgs: float) -> tuple[float, float]:
    """dT_air/dt and dT_int/dt (K/s) of the module docstring's equations."""
    q_supply = max(mass_flow_kgs, 0.0) * CP_AIR_J_PER_KGK * (supply_c - air_c)
    q_int = setup.air_interior_w_per_k * (interior_c - air_c)
    q_wall = setup.wall_w_per_k * (setup.outside_temp_c - air_c)
    d_air = (q_supply + q_int + q_wall + setup.driver_w) / setup.air_capacity_j_per_k
    d_int = (-q_int + setup.solar_w) / setup.interior_capacity_j_per_k
    return d_air, d_int


def cabin_step(setup: CabinSetup, air_c: float, interior_c: float, supply_c: float, mass_flow_kgs: float,
               dt_s: float) -> tuple[float, float]:
    """Cabin air and interior temperatures after ``dt_s`` with the supply air held (Heun sub-steps)."""
    n = max(1, math.ceil(dt_s / CABIN_SUBSTEP_S - 1e-9))
    h = dt_s / n
    for _ in range(n):
        a1, i1 = cabin_rates(setup, air_c, interior_c, supply_c, mass_flow_kgs)
        a2, i2 = cabin_rates(setup, air_c + h * a1, interior_c + h * i1, supply_c, mass_flow_kgs)
        air_c, interior_c = air_c + 0.5 * h * (a1 + a2), interior_c + 0.5 * h * (i1 + i2)
    return air_c, interior_c


class CabinLoop:
    """A box plant with its inlet fed by the cabin: ``apply``/``advance``/``read``/``truth`` as the box's.

    Each sample the cabin takes the box's true supply air (``truth()['supply_air_temp_c']``, its
    mass flow ``mass_flow_kgs``) over the sample, and the box's inlet is set to the mix of cabin and
    outside air (``set_environment(inlet_temp_c=...)``). Readings carry ``cabin_temp_c`` (a slow
    sensor without noise, thesis sec. 2.4) and the inlet the box's own sensor reads.
    """

    def __init__(self, box: Any, setup: CabinSetup):
        self.box = box
        self.setup = setup
        self.air_c = setup.cabin_temp_c
        self.interior_c = setup.interior_temp_c
        self.box.set_environment(inlet_temp_c=setup.inlet_c(self.air_c))
        if hasattr(self.box, "settle"):
            self.box.settle()

    def __getattr__(self, name: str) -> Any:  # dt_s, time_s, command, ... of the box
        return getattr(self.box, name)

    def apply(self, command: Any) -> Any:
        return self.box.apply(command)

    def advance(self, n_steps: int = 1) -> None:
        for _ in range(int(n_steps)):
            y = self.box.truth()
            supply = y.get("supply_air_temp_c", y["supply_temp_c"])
            self.air_c, self.interior_c = cabin_step(self.setup, self.air_c, self.interior_c, supply,
                                                     y["mass_flow_kgs"], self.box.dt_s)
            self.box.advance(1)
            self.box.set_environment(inlet_temp_c=self.setup.inlet_c(self.air_c))

    def read(self):
        return replace(self.box.read(), cabin_temp_c=self.air_c)

    def truth(self) -> dict[str, float]:
        y = dict(self.box.truth())
        y.update({"cabin_temp_c": self.air_c, "cabin_interior_temp_c": self.interior_c,
                  "hvac_inlet_temp_c": self.setup.inlet_c(self.air_c)})
        return y
