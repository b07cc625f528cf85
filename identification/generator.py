"""Measurement logs made by the simulated plant, for checking the identification end to end.

:func:`simulate_log` runs :class:`~hvac_mpc.models.plant.SimulatedPlant` open loop under an
exciting input sequence (:func:`excitation`) and returns the columns of the measurement-log
schema (docs/model.md sec. 4). Besides the plant's own effects it can switch on effects the plant
does not have, so that the identification meets effects it must find and one it cannot know:

- ``sensor_lag``: the supply thermocouple is slower than the thesis's 5.73 s (generic library
  effect "sensor lag mismatch");
- ``transport_delay``: the supply temperature reading is late by a few samples (generic
  "transport delay");
- ``output_bias``: the supply temperature reading has an offset and a slow drift (generic
  "output bias/drift");
- ``latent_cooling``: moist inlet air condenses on the cooler core, so part of the core's
  cooling goes into latent heat and the core outlet air is warmer; it grows with the inlet
  relative humidity. No candidate of the identification library describes it (on purpose).

All magnitudes below are ASSUMPTIONS chosen to be plausible and visible above sensor noise.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from hvac_mpc.models.box import INPUTS
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.models.plant import PLANT_EFFECTS, Environment, SimulatedPlant

#: Effects the generator adds on top of the plant (see the module docstring).
from hvac_mpc.contract import Command
EXTRA_EFFECTS = ("sensor_lag", "transport_delay", "output_bias", "latent_cooling")
#: Every effect name :func:`simulate_log` accepts (``sensor_noise`` is the ``noise`` flag).
GENERATOR_EFFECTS = tuple(e for e in PLANT_EFFECTS if e != "sensor_noise") + EXTRA_EFFECTS

#: ASSUMPTION: time constant of the slower supply thermocouple for ``sensor_lag``, s.
SENSOR_LAG_TAU_S = 15.0
#: ASSUMPTION: delay of the supply temperature reading for ``transport_delay``, samples.
TRANSPORT_DELAY_SAMPLES = 6
#: ASSUMPTION: offset (C) and drift (C per hour) of the supply reading for ``output_bias``.
BIAS_OFFSET_C, BIAS_DRIFT_C_PER_H = 0.4, 0.6
#: ASSUMPTION: share of the core's sensible cooling lost to condensation at 80 % inlet RH and above.
LATENT_MAX_SHARE = 0.3
#: ASSUMPTION: inlet relative humidity (%) below which no condensation occurs.
LATENT_RH_ONSET_PCT = 35.0
#: Length of one excitation cycle (a cooling half and a heating half), s.
CYCLE_S = 600.0


def excitation(duration_s: float, seed: int = 0, dt_s: float = 1.0) -> dict[str, np.ndarray]:
    """Open-loop input sequence: actuator commands, inlet temperature and inlet humidity.

    Repeats 600 s cycles with random levels: a cooling part (270 s, heater off; valve a, blower
    and outlet valves stepped) and a heating part (heater near full power at low flow with
    valve a saturated at 100 % for 180 s, then valve a released, then the blower raised, then
    the heater lowered). Blower steps are large and held for ~135-180 s so that motor heating
    shows; inlet temperature drifts slowly, humidity alternates between dry and humid.
    Returns ``commands`` (n x 6, model input order), ``inlet_temp_c`` and ``inlet_rh_pct`` (n).
    """
    if not duration_s > 0 or not dt_s > 0:
        raise ValueError(f"duration_s and dt_s must be positive, got {duration_s}, {dt_s}")
    rng = np.random.default_rng(seed)
    n = int(round(duration_s / dt_s))
    t = np.arange(n) * dt_s
    u = np.zeros((n, len(INPUTS)))
    valve_levels = np.array([0.0, 15.0, 25.0, 40.0, 60.0, 80.0, 100.0])

    def valves_mfw():
        kind = rng.integers(3)
        if kind == 0:  # throttled network: every outlet valve nearly closed
            return rng.choice([0.0, 10.0, 20.0], 3)
        if kind == 1:  # one outlet open, the others closed (as in thesis tables 3-5)
            v = np.zeros(3)
            v[rng.integers(3)] = rng.choice([40.0, 70.0, 100.0])
            return v
        return rng.choice(valve_levels, 3)

    for c in range(int(np.ceil(duration_s / CYCLE_S))):
        t0 = c * CYCLE_S
        hi_first = rng.random() < 0.5
        b1 = rng.uniform(260, 300) if hi_first else rng.uniform(30, 45)
        b2 = rng.uniform(30, 45) if hi_first else rng.uniform(260, 300)
        a1, a2 = rng.choice([0.0, 15.0, 30.0]), rng.choice([0.0, 35.0, 55.0, 85.0, 100.0])
        heat_w = rng.uniform(225, 240)
        heat_low_w = rng.uniform(60, 130)
        b_low = rng.uniform(30, 34)
        b_heat = rng.uniform(110, 220)
        a_heat = rng.uniform(55, 80)
        segments = [  # (start offset s, blower W, heater W, valve a %, outlet valves or None)
            (0, b1, 0.0, a1, valves_mfw()), (70, b1, 0.0, a1, valves_mfw()),
            (135, b2, 0.0, a2, valves_mfw()), (200, b2, 0.0, a2, valves_mfw()),
            (270, b_low, heat_w, 100.0, valves_mfw()), (450, b_low, heat_w, a_heat, None),
            (475, b_heat, heat_w, a_heat, None), (530, b_heat, heat_low_w, a_heat, valves_mfw()),
        ]
        current_mfw = None
        for k, (off, blower, heat, a, mfw) in enumerate(segments):
            start = t0 + off
            stop = t0 + (segments[k + 1][0] if k + 1 < len(segments) else CYCLE_S)
            sel = (t >= start) & (t < stop)
            current_mfw = mfw if mfw is not None else current_mfw
            u[sel] = [blower, heat, a, *current_mfw]
    inlet = 25.0 + 1.5 * np.sin(2 * np.pi * t / 2400.0 + rng.uniform(0, 2 * np.pi))
    rh = np.zeros(n)
    k, humid = 0, rng.random() < 0.5
    while k < n:  # alternating dry and humid inlet air
        hold = int(rng.uniform(200, 420) / dt_s)
        rh[k:k + hold] = rng.uniform(60, 90) if humid else rng.uniform(20, 45)
        humid = not humid
        k += hold
    return {"commands": u, "inlet_temp_c": inlet, "inlet_rh_pct": rh}


class _LatentPlant(SimulatedPlant):
    """Simulated plant with condensation on the cooler core (generator effect ``latent_cooling``).

    The core's sensible cooling T_blower - T_core is reduced by the latent share(RH). The
    cooler model T_core = T_b + s (T_w - T_b) is fed a water temperature raised by
    share (T_b - T_w) during each step (with the chiller target raised alike, so the water
    ramp is unchanged); the logged water temperature stays the chiller's. Heater and supply
    temperatures thus see the warmer core air consistently.
    """

    def __init__(self, *args, **kwargs):
        self.inlet_rh_pct = 50.0
        self._dw = 0.0
        super().__init__(*args, **kwargs)

    def _latent_shift_c(self) -> float:
        sx = self.model.states.dict(self.x)
        t_blower = self.env.inlet_temp_c + sx["motor_rise_c"]
        share = LATENT_MAX_SHARE * float(np.clip((self.inlet_rh_pct - LATENT_RH_ONSET_PCT) / 45.0, 0.0, 1.0))
        return share * max(t_blower - sx["water_temp_c"], 0.0)

    def _disturbance_vector(self, chiller_target_c: float) -> np.ndarray:
        return super()._disturbance_vector(chiller_target_c + self._dw)

    def advance(self, n_steps: int = 1) -> None:
        iw = self.model.states.index("water_temp_c")
        for _ in range(n_steps):
            self._dw = self._latent_shift_c()
            self.x[iw] += self._dw
            super().advance(1)
            self.x[iw] -= self._dw

    def truth(self) -> dict[str, float]:
        y = super().truth()
        y["water_temp_c"] -= self._dw
        return y


def simulate_log(effects: Iterable[str] = (), seed: int = 0, duration_s: float = 1800.0, dt_s: float = 1.0,
                 noise: bool = True, params: Parameters | None = None, log_water: bool = True,
                 log_heater: bool = True, chiller_setpoint_c: float = 5.0) -> dict[str, np.ndarray]:
    """Simulate the plant open loop and return measurement-log columns (docs/model.md sec. 4).

    ``effects``: names from :data:`GENERATOR_EFFECTS` switched on (none: the thesis model's
    behaviour). ``noise`` switches the plant's sensor noise. ``log_water`` / ``log_heater``
    include the optional columns water_temp_c / heater_power_w and heater_outlet_temp_c.
    Row k holds the readings at time k dt and the command applied from then on.
    """
    effects = tuple(effects)
    unknown = sorted(set(effects) - set(GENERATOR_EFFECTS))
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; allowed: {list(GENERATOR_EFFECTS)}")
    params = params or Parameters()
    if "sensor_lag" in effects:
        params = params.replace(tau_tc_s=SENSOR_LAG_TAU_S)
    plant_effects = [e for e in effects if e in PLANT_EFFECTS] + (["sensor_noise"] if noise else [])
    ex = excitation(duration_s, seed, dt_s)
    u, inlet, rh = ex["commands"], ex["inlet_temp_c"], ex["inlet_rh_pct"]
    n = len(u)
    env = Environment(float(inlet[0]), chiller_setpoint_c)
    cls = _LatentPlant if "latent_cooling" in effects else SimulatedPlant
    plant = cls(params, plant_effects, seed=seed, dt_s=dt_s, environment=env,
                initial_command=Command.from_vector(u[0]))
    rng = np.random.default_rng(seed + 7919)
    cols: dict[str, list] = {c: [] for c in (
        "time_s", *INPUTS, "hvac_inlet_temp_c", "volume_flow_m3s", "supply_temp_c", "heater_power_w",
        "water_temp_c", "chiller_setpoint_c", "heater_outlet_temp_c", "hvac_inlet_rh_pct", "mode")}
    for k in range(n):
        plant.set_environment(inlet_temp_c=float(inlet[k]))
        if cls is _LatentPlant:
            plant.inlet_rh_pct = float(rh[k])
        m = plant.read()
        applied = plant.apply(u[k])
        cols["time_s"].append(k * dt_s)
        for i, name in enumerate(INPUTS):
            cols[name].append(float(applied[i]))
        cols["hvac_inlet_temp_c"].append(m.hvac_inlet_temp_c)
        cols["volume_flow_m3s"].append(m.volume_flow_m3s)
        cols["supply_temp_c"].append(m.supply_temp_c)
        cols["heater_power_w"].append(m.heater_power_w)
        cols["water_temp_c"].append(m.water_temp_c)
        cols["chiller_setpoint_c"].append(m.chiller_setpoint_c)
        cols["heater_outlet_temp_c"].append(m.heater_outlet_temp_c)
        cols["hvac_inlet_rh_pct"].append(rh[k] + (rng.normal(0.0, 0.5) if noise else 0.0))
        cols["mode"].append("heating" if applied[1] > 0 else "cooling")
        plant.advance()
    out = {k: (np.array(v, dtype=object) if k == "mode" else np.array(v, float)) for k, v in cols.items()}
    supply = out["supply_temp_c"]
    if "transport_delay" in effects:
        d = TRANSPORT_DELAY_SAMPLES
        supply = np.concatenate([np.full(d, supply[0]), supply[:-d]])
    if "output_bias" in effects:
        supply = supply + BIAS_OFFSET_C + BIAS_DRIFT_C_PER_H * out["time_s"] / 3600.0
    out["supply_temp_c"] = supply
    if not log_water:
        for c in ("water_temp_c",):
            out.pop(c)
    if not log_heater:
        for c in ("heater_power_w", "heater_outlet_temp_c"):
            out.pop(c)
    return out
