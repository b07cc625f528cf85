"""Helpers shared by the daemon tests: a small test controller, a config writer, process control.

``SimplePi`` is a deliberately plain controller (feed-forward plus PI, no model) so the daemon's
own behaviour can be tested independently of the MPC and the thesis baseline.
"""

from __future__ import annotations

from hvac_mpc.contract import Command
from hvac_mpc.contract import StepResult


class SimplePi:
    """Blower: flow feed-forward (docs/model.md sec. 1: V = 1.9e-4 P) plus PI. Temperature: PI on
    valve a (less a = more warm air bypassing the cooler core), the heater as a second stage
    once valve a is fully open to the bypass."""

    def __init__(self, params=None, dt_s: float = 1.0):
        self.dt_s = dt_s
        self.reset()

    def reset(self) -> None:
        self.i_flow = 0.0
        self.i_valve = 50.0
        self.i_heat = 0.0

    def step(self, measurement, reference) -> StepResult:
        e_v = reference.volume_flow_m3s - measurement.volume_flow_m3s
        self.i_flow = min(max(self.i_flow + 2000.0 * e_v * self.dt_s, -150.0), 150.0)
        blower = reference.volume_flow_m3s / 1.9e-4 + 3000.0 * e_v + self.i_flow
        e_t = reference.supply_temp_c - measurement.supply_temp_c
        self.i_valve = min(max(self.i_valve - 1.5 * e_t * self.dt_s, 0.0), 100.0)
        valve_a = min(max(self.i_valve - 6.0 * e_t, 0.0), 100.0)
        if self.i_valve <= 0.0:
            self.i_heat = min(max(self.i_heat + 1.0 * e_t * self.dt_s, 0.0), 240.0)
        else:
            self.i_heat = max(self.i_heat - 5.0 * self.dt_s, 0.0)
        cmd = Command(blower_power_w=min(max(blower, 30.0), 300.0), heater_cmd_w=self.i_heat,
                      valve_a_pct=valve_a, valve_m_pct=100.0, valve_f_pct=100.0, valve_w_pct=100.0)
        return StepResult(cmd, {"step_time_s": 0.0, "iterations": 0, "status": "ok", "fallback": None,
                                "mode": "heating" if self.i_heat > 0 else "cooling"})
