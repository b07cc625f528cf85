"""The optimal control problem of the MPC, kept apart from any solver (acados style).

:class:`OcpSpec` says *what* is optimised: the horizon as stage durations (move blocking: the
inputs are held over each stage), weights, rate limits, the soft heater-temperature limit and
the trapped-air guard. :class:`TrackingProblem` turns a spec and the plant parameters into the
scaled discrete model every solver shares (``rti_osqp``, ``ipopt_reference``, do-mpc in the
benchmark): one CasADi stage function returning ``(x_next, A, B, y, C, D)`` mapped over the
horizon, the bounds, and the exact cost.

The discrete problem (scaled variables ``x = (x_phys - x_off) / x_sc``, likewise ``u``)::

    min  sum_k dt_k [ sum_i w_i ((y_i(x_k, u_k) - r_i) / s_i)^2 + w_e ((P_blower + P_heater_el)(x_k, u_k) / 100 W)^2 ]
       + T_term sum_i w_i ((y_i(x_N, u_{N-1}) - r_i) / s_i)^2
       + sum_k sum_j w_du_j (u_k,j - u_k-1,j)^2          (u_-1 = last applied command)
       + sum_k dt_k-1 (w_l1 s_k + w_l2 s_k^2)
       + sum_k dt_k w_f sum_j (T - v_j(u_k))^2           (flaps m, f, w; w_f = Weights.flap_closure_per_pct2, 0 by default)
    s.t. x_0 = estimate,  x_k+1 = F(x_k, u_k, d, dt_k)  (RK4)
         u_lo <= u_k <= u_hi,  |u_k - u_k-1| <= rate * dt_k-1  (dt_-1 = one sample)
         heater_temp(x_k) <= heater_temp_max + s_k,  s_k >= 0,  k = 1..N
         heater_cmd_k / c + heater_temp(x_k) <= T_zero + s_k,  k = 1..N-1   (PTC limit, ptc_limit)
         Q(x_k, u_k) >= Q_min min(1, heater_cmd_k / P_on),  k = 0..N-1      (flow floor, heater_min_flow_m3s)

Tracked outputs ``y``: supply temperature, total volume flow, outlet flows m, f, w (outlet
weights are zero when the reference leaves the split free) and, while the heater is on, valve a's
opening against 0 % (``Weights.valve_a_heating_per_pct2``: the heater body carries the heat, valve a
keeps its authority); ``P_heater_el`` is the model's
electric heater power (PTC fall included when the model has it). The valves m, f, w are
decided as openings (:mod:`hvac_mpc.mpc.valve_map`); their plan-stage rate limit is on the
opening (:meth:`TrackingProblem.rate_bounds`), the applied move's on the angle.

Which supply temperature is tracked (``OcpSpec.tracked_temperature``, default ``"blend"``): a
quarter the true mixed air at the thermocouple (model output ``duct_air_temp_c``: ``supply_air_temp_c``,
mixed-air offset included, after the transport delay if the parameters set one, docs/robustness.md
sec. 2) and three quarters the thermocouple reading (tau 5.73 s, thesis sec. 5.4.1). Tracking the air
alone leaves the reading, which is what the reference is judged on, a sensor lag behind;
tracking the reading alone makes the controller overshoot the air to hurry the sensor, and rings
where the box has a dead time the estimator has not seen yet. The blend (``sensor_share`` 0.75, a
tuning choice on the independent simulator's variants, docs/robustness.md sec. 2.3) overshoots the
air for a few seconds at a step and hurries the reading. At rest air and reading agree, so
offset-free tracking holds for both.

The flow floor (``OcpSpec.heater_min_flow_m3s``, docs/robustness.md sec. 2.2): while the heater is
on, the total volume flow stays at or above the heater's minimum flow. "On" is a switch, which no
convex row holds; the row ``Q >= Q_min min(1, P / P_on)`` (``P`` the heater command, ``P_on``
``OcpSpec.heater_on_w``) is a plain floor ``Q >= Q_min`` wherever the linearisation has the heater at
``P_on`` or more and ``Q >= Q_min P / P_on`` (no floor with the heater off, the full floor from
``P_on`` on) where it has it below. It is a hard row; where the first move cannot reach the floor
within its rate limits (after a fallback, say) the real-time iteration asks of stage 0 only what that
move can reach, and the blower raises the flow from stage 1 on.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields
from typing import Any, Callable, NamedTuple

import casadi as ca
import numpy as np

from hvac_mpc.validation import Check, InvalidValue, finite_in, flag
from hvac_mpc.models import heater, valves
from hvac_mpc.models.box import INPUT_LOWER, INPUTS, MODEL_EFFECTS, HvacModel, input_upper, rk4
from hvac_mpc.models.parameters import Parameters

from .casadi_eval import BufferedFunction
from hvac_mpc.contract import Reference
from .flap_target import SplitTarget
from .valve_map import VALVE_NAMES, ValveMap

#: Tracked outputs (model output names) in the order of the residual vector; the first is
#: replaced by ``supply_temp_c`` when the sensor reading is tracked.
TRACKED = ("supply_air_temp_c", "volume_flow_m3s", "flow_m_m3s", "flow_f_m3s", "flow_w_m3s")
#: Stage-function outputs: the tracked ones plus the electric heater power for the energy term and valve a's
#: opening, penalised while heating (:attr:`Weights.valve_a_heating_per_pct2`).
STAGE_OUTPUTS = TRACKED + ("heater_power_w", "valve_a_pct")
#: The tracked flows among the stage outputs (the total and the three outlets' volume flows, m3/s), as a slice.
FLOW_OUTPUTS = slice(TRACKED.index("volume_flow_m3s"), TRACKED.index("flow_w_m3s") + 1)
#: Valve a's row of the stage outputs.
Y_VALVE_A = STAGE_OUTPUTS.index("valve_a_pct")
#: Outlet m's row of the stage outputs: its weight is on where the reference's split is tracked.
_Y_OUTLET_M = STAGE_OUTPUTS.index("flow_m_m3s")

#: Default horizon: 25 stages covering 104 s, fine where the thermocouple (tau 5.73 s) and
#: valve moves matter, coarse where only the heater body (tau ~90 s) and motor lag still move.
DEFAULT_STAGES_S = (1.0,) * 8 + (2.0,) * 6 + (4.0,) * 5 + (8.0,) * 4 + (16.0,) * 2

#: Unit of the flow-floor row: L/s per m3/s (rows of order one beside the others).
FLOOR_SCALE = 1e3
#: Heater command (W) above which the controller is heating (valve a's heating weight, the step's mode).
HEATING_CMD_W = 1.0

#: Largest flap-closure weight (per %^2 per s, :attr:`Weights.flap_closure_per_pct2`): at 1e-2 a flap 10 % from its
#: target weighs like 1.4 L/s of outlet-flow error (weight 0.5 per (L/s)^2), beyond which the term is no longer small
#: beside the tracking.
FLAP_CLOSURE_MAX = 1e-2
#: The longest ramp of the heater reserve's weight (s, ``Weights.valve_a_reserve_ramp_s``): ten minutes, longer than
#: any rest of the scenarios.
RESERVE_RAMP_MAX_S = 600.0
#: The largest shortfall threshold of the reserve's withholding rule (K, ``Weights.valve_a_reserve_short_c``): the
#: rest's own band (``reserve.LEAVE_BAND_C``), beyond which the rest has ended anyway.
RESERVE_SHORT_MAX_C = 1.0
#: The longest hold of the heater reserve after the box's heater drew less than its command (s,
#: ``Weights.valve_a_reserve_ptc_hold_s``): ten minutes, as the ramp.
RESERVE_PTC_HOLD_MAX_S = 600.0

#: Offsets and scales of the states (degC): scaled value = (physical - offset) / scale.
STATE_SCALING = {"motor_rise_c": (1.0, 1.0), "water_temp_c": (5.0, 5.0), "heater_temp_c": (40.0, 40.0),
                 "supply_sensor_c": (20.0, 10.0), "trap_air_temp_c": (40.0, 40.0)}
#: Offsets and scales of the inputs (W, %): scaled inputs lie in about [-1, 1].
INPUT_SCALING = {"blower_power_w": (165.0, 135.0), "heater_cmd_w": (120.0, 120.0),
                 "valve_a_pct": (50.0, 50.0), "valve_m_pct": (50.0, 50.0), "valve_f_pct": (50.0, 50.0),
                 "valve_w_pct": (50.0, 50.0)}


class InvalidSettings(InvalidValue):
    """A setting is out of range or malformed; the message names the field and the allowed range."""


@functools.lru_cache(maxsize=None)
def _number_check(lo: float, hi: float, integer: bool, lo_open: bool) -> Check:
    return finite_in(lo, hi, integer=integer, lo_open=lo_open)


def check_number(name: str, value: Any, lo: float, hi: float, *, integer: bool = False,
                 lo_open: bool = False) -> None:
    """Raise :class:`InvalidSettings` unless ``value`` is a finite number (integer) in the range
    (the project's one validation mechanism, :mod:`hvac_mpc.validation`)."""
    if integer and isinstance(value, float) and value.is_integer():
        value = int(value)  # 100.0 iterations are 100
    _number_check(float(lo), float(hi), integer, lo_open)(name, value, InvalidSettings)


_FLAG = flag()


def check_flag(name: str, value: Any) -> None:
    """Raise :class:`InvalidSettings` unless ``value`` is True or False (strict: not 0 or 1)."""
    _FLAG(name, value, InvalidSettings)


@dataclass(frozen=True)
class Weights:
    """Cost weights (per second of horizon unless said otherwise); tuning choices on the simulated
    plant (ASSUMPTIONS, nothing here comes from the thesis).

    ``supply_temp`` 5 against ``volume_flow`` 2: supply temperature comes first (docs/robustness.md
    sec. 1); where the heater is at its limit the flow is the only lever left, and the MPC gives up
    flow for temperature down to the flow floor (``OcpSpec.heater_min_flow_m3s``; measured on the
    quick mismatch suite, docs/robustness.md sec. 2.2).

    Residuals are divided by their scale first: temperature by 1 degC, flows by 1 L/s, electric
    power (blower plus heater) by 100 W. The energy term is a least-squares residual too: it
    prefers the least power among the actuator settings that track equally well (the redundant
    blower/outlet-valve and valve a/heater directions) and, unlike a linear term, gives the
    Gauss-Newton Hessian curvature along those directions. ``move_*`` penalise the change of an
    input between consecutive stages (per unit squared, not per s).

    ``valve_a_heating_per_pct2`` (per %^2 per s): while the heater is on, valve a's opening is penalised
    (towards closed, :meth:`TrackingProblem.heating_weights`). At rest heating has a free direction: the air
    takes k_p times the heater's power whatever valve a's share, so valve a and the heater body's temperature
    trade without changing the supply temperature or the energy, and where the MPC ends up depended on the
    path: after a step it had drawn on the body's stored heat and sat at valve a's cap with the body cooled
    (27 C against 29-39 C), so the next step up waited for the body (docs/identification.md, "The
    refined model in the controller"). Valve a low holds the body as hot as the heat demand allows, with the
    heater's air far above the bypass air: valve a then moves the supply temperature fast either way and the
    body holds heat for a step up. 3e-5 weighs valve a at 50 % like 0.27 degC of supply error, which the free
    direction lets the body take instead; the PTC fall and the soft heater limit bound it. ASSUMPTION, chosen
    on winter_heating_steps over variants of the mismatch suite (3e-5 and 5e-5 about equal and best of 3e-5,
    5e-5, 1e-4, 3e-4; from 5e-5 on a step up at 40 m3/h overshoots by 0.5 C while valve a closes,
    docs/identification.md).

    ``body_heat_power_w`` (W; 0: off): a value on the heat stored in the heater body. The energy term prices
    the electric power drawn, not the heat the air takes from the body, so drawing the body down is free in the
    cost although a later step up must buy that heat back with the heater. With this weight the heat content
    change over the horizon, ``C_body (T_body,0 - T_body,N)`` (J, ``C_body`` the body's heat capacity), is
    priced at the energy term's marginal price of electric energy at this power (blower plus heater):
    ``2 energy_per_100w2 P / (100 W)^2`` per J, a linear term on the terminal body temperature
    (:meth:`TrackingProblem.body_heat_coefficient`), while the heater is commanded in the command in force (as
    valve a's heating weight; in cooling the body's heat is no value but a load, and the term is left out).
    ASSUMPTION: heat in the body is worth what the heater's energy costs at that power; 240 W plus a blower's
    100 W is the heater-limited heating where stored heat decides a step up. Off by default (measured, docs/identification.md 'A value on the heat stored in the
    heater body').

    ``heater_ready_per_c2`` (per K^2 per s; 0: off): the heater readiness, a one-sided penalty on the predicted
    heater body below a floor while the reference is above the inlet air (:mod:`hvac_mpc.mpc.readiness`; the
    floor from ``OcpSpec.ready_step_c``). Off by default (measured, docs/identification.md 'Heater readiness').

    ``valve_a_reserve_per_pct2`` (per %^2 per s; 0: off): the heater reserve, valve a's weight in place of
    ``valve_a_heating_per_pct2`` while heating at rest on the reference with the heater not limiting and the flow
    priority untouched (:mod:`hvac_mpc.mpc.reserve`): the free direction at rest leaned on harder, so the heater body
    keeps heat for a step up. Off by default (measured, docs/identification.md 'A heater reserve at rest').
    ``valve_a_reserve_ramp_s`` (s; 0: at once, the default): the reserve's entry, its weight rising in a straight
    line from ``valve_a_heating_per_pct2`` over this many seconds of the rest. ``valve_a_reserve_short_c`` (K; 0: the
    rule off, the default): the reserve's weight withheld at a step of the rest where the heater is at its limit (the
    command in force within the reserve's headroom of the power at the body's estimate) and the supply reading more
    than this below its reference; a withheld step does not count towards the ramp. Both act only with the reserve on
    (docs/identification.md 'The reserve's entry'). ``valve_a_reserve_ptc_hold_s`` (s; 0: off, the default): after
    a step where the box's heater drew measurably less than its command (its body past the PTC knee), the reserve
    stays out for this many seconds, not only while the shortfall lasts (docs/identification.md 'The reserve's
    winter cost').

    ``flap_closure_per_pct2`` (per %^2 of opening per s; 0: off): the flat direction of the outlet flaps priced. Four
    actuators (the blower and the openings of flaps m, f, w) set three outlet flows, so "blower power down, all flaps
    opened" changes no tracked output, and a flap near fully open hardly moves its flow; only the energy term prices
    these directions (its curvature about 2.5e-6 per %^2 of all three flaps' opening at once), so answers within
    OSQP's tolerance differ along them by watts and tens of percent of flap travel, and the closed loop's actuator mix
    is set by the solver's path (docs/architecture.md, 'The flat direction priced'). This weight adds
    ``dt_k w (T - v_j,k)^2`` for each flap j's opening ``v`` (%, :mod:`hvac_mpc.mpc.valve_map`) at each stage k, ``T``
    the target :attr:`OcpSpec.flap_target_pct` (fully open by default, the direction the energy term already prefers:
    the largest flap at its end, the blower as low as the flows allow; below it a reserve of opening for a flow step),
    so the mix is the cost's. ASSUMPTION: where the split holds a flap away from the target, the term's pull on it is
    weighed against the outlet flow's error: at 1e-5 and a flap 50 % away, about 0.01 L/s with an outlet gain of
    0.1 L/s per % of opening. Constant in the QP (its Hessian and gradient are inputs of the generated code, not part of
    its structure). Off by default: with 1e-5 or 1e-4 the built-in bench's winter_heating_steps loses 0.02-0.04 of its
    ratio (measured in the same section). Traced in 'The flat direction priced, winter traced': towards a fixed 70 % the
    term moves the winter split's rest mix (flap f 100 -> 62 % of its angle) and costs that scenario +2.7 % of its IAE
    over plant seeds 0-9; towards the split's own rest mix (``OcpSpec.flap_target_from_split``) +0.25 % (OSQP's
    tolerance 10 % tighter, nothing else changed: -0.33 %), but on the bench's seed 0 still above the rule's fourth
    decimal (the seed-0 figure moves by several % with any change to OSQP's iterates).
    """

    supply_temp: float = 5.0
    volume_flow: float = 2.0
    outlet_flow: float = 0.5
    energy_per_100w2: float = 5e-2
    move_blower_per_w2: float = 2e-5
    move_heater_per_w2: float = 1e-5
    move_valve_per_pct2: float = 1e-4
    terminal_s: float = 16.0
    slack_l1_per_c: float = 5.0
    slack_l2_per_c2: float = 1.0
    valve_a_heating_per_pct2: float = 3e-5
    body_heat_power_w: float = 0.0
    heater_ready_per_c2: float = 0.0
    valve_a_reserve_per_pct2: float = 0.0
    valve_a_reserve_ramp_s: float = 0.0
    valve_a_reserve_short_c: float = 0.0
    valve_a_reserve_ptc_hold_s: float = 0.0
    flap_closure_per_pct2: float = 0.0

    def validate(self, prefix: str = "weights") -> None:
        # the fields with a narrower range first, so that the error names their own range
        check_number(f"{prefix}.body_heat_power_w", self.body_heat_power_w, 0.0, 2000.0)
        check_number(f"{prefix}.flap_closure_per_pct2", self.flap_closure_per_pct2, 0.0, FLAP_CLOSURE_MAX)
        check_number(f"{prefix}.valve_a_reserve_ramp_s", self.valve_a_reserve_ramp_s, 0.0, RESERVE_RAMP_MAX_S)
        check_number(f"{prefix}.valve_a_reserve_short_c", self.valve_a_reserve_short_c, 0.0, RESERVE_SHORT_MAX_C)
        check_number(f"{prefix}.valve_a_reserve_ptc_hold_s", self.valve_a_reserve_ptc_hold_s, 0.0,
                     RESERVE_PTC_HOLD_MAX_S)
        for f in fields(self):
            check_number(f"{prefix}.{f.name}", getattr(self, f.name), 0.0, 1e6)
        if self.supply_temp <= 0 or self.volume_flow <= 0:
            raise InvalidSettings(f"{prefix}.supply_temp and {prefix}.volume_flow must be > 0 (range (0, 1e6])")


@dataclass(frozen=True)
class OcpSpec:
    """What the MPC optimises (no solver settings here).

    Attributes:
        stage_durations_s: duration of each stage (s); inputs are held over a stage (move
            blocking). The first equals the sample time; the sum is the horizon (>= 60 s so the
            one-minute requirement of docs/model.md sec. 2 is inside it).
        max_substep_s: longest RK4 substep (s); a stage uses ceil(its duration / this) substeps.
        tracked_temperature: ``"air"`` tracks the true mixed supply air (model output
            ``supply_air_temp_c``), ``"sensor"`` the thermocouple state ``supply_temp_c``,
            ``"blend"`` the mix ``(1 - sensor_share) air + sensor_share sensor``.
        sensor_share: weight of the thermocouple in the ``"blend"`` temperature, in [0, 1].
        rate_blower_w_per_s, rate_heater_w_per_s, rate_valve_pct_per_s: actuator rate limits
            (ASSUMPTIONS: the thesis gives none; the servo valves are taken to cross their range in
            2 s, 50 %/s, and the power stages to ramp 60 W/s, a full blower range in under 5 s).
            The valve limit is a bound on the servos, not a tuning: the thesis calls the actuator
            "really fast for the chosen sampling rate" (sec. 5.4.1) and its PI/PID loops move the
            valves in one sample; 20 %/s (the earlier value) held valve a back at every temperature
            step (docs/robustness.md sec. 2.3).
        heater_temp_max_c: soft upper limit of the heater body (None: ``Parameters.heater_temp_max_c``).
        trap_margin_pct: valve a is capped at ``trap_threshold_pct - trap_margin_pct`` while the heater
            is warm (thesis sec. 5.4.2; see :func:`trap_cap_pct`).
        trap_warm_c: the heater counts as warm when its estimated temperature exceeds the air
            entering it by more than this (degC), or the heater is commanded on.
        model_effects: structural effects of the prediction model (subset of ``MODEL_EFFECTS``).
            Default: the fan curve and the closed-valve leakage (both fitted to thesis tables 3-5),
            steady physics the outlet split cannot be tracked without, because the outlet flows are
            not measured; and the bypass split's dependence on the mass flow (thesis sec. 4.5.1
            names it; the identification finds it in a log, ``hvac-mpc identify``): it changes the
            gain of valve a on the supply temperature, which the estimator's additive offsets
            cannot represent; without it heating at low flow drifts valve a to the wrong end.
            The dynamic effects (motor asymmetry, chiller hysteresis, trapped air) are left to the
            estimator's disturbance states and the trapped-air guard.
        ptc_limit: the PTC power fall (thesis sec. 2.3, fig. 12) enters as a linear constraint
            ``heater_cmd <= P_max (T_zero - T_h) / (T_zero - T_knee)`` (soft, the heater slack)
            instead of ``min(cmd, available)`` in the dynamics: a command above the available power
            changes nothing in the plant, so the min has a zero gradient there and a Gauss-Newton
            iteration can sit at full command while the supply air is too warm (measured on the
            simulated plant). The estimator keeps the min (it sees what was really applied).
        heater_min_flow_m3s: the flow floor while the heater is on (m3/s; None: no floor), a hard row
            of stages 0..N-1 (module docstring). ASSUMPTION: the daemon's heater interlock
            (``SafetyConfig.min_flow_m3s``, 0.004 m3/s = 14.4 m3/h) with 25 % margin for the model's
            flow error; without it a heavy temperature weight trades the flow away without limit where
            the temperature is out of reach (docs/robustness.md sec. 2.2). Stage 1 alone is not
            enough: the first stage's flow, which the command applied sets, is what the box sees.
        heater_on_w: heater command (W) from which the floor holds in full; below it the floor is
            ``heater_min_flow_m3s * command / heater_on_w``.
        ready_step_c: the step up of the supply temperature (K) the heater body is kept ready to serve at once
            while the reference asks for heat (:mod:`hvac_mpc.mpc.readiness`; only with
            ``Weights.heater_ready_per_c2`` above 0). ASSUMPTION: 3 K, the steps of the winter scenario.
        ready_lead_c: the most the readiness floor asks above the heater body's estimate (K; None: no bound): the
            pull of the floor on the plan is bounded, the same for a body estimated far below the floor as for one
            estimated near it (:mod:`hvac_mpc.mpc.readiness`; measured, docs/identification.md 'Heater readiness').
        flap_target_pct: the opening of flaps m, f, w (% of the opening ``v``, :mod:`hvac_mpc.mpc.valve_map`) the
            flap-closure term pulls each flap towards (only with ``Weights.flap_closure_per_pct2`` above 0): 100, fully
            open, the mix of least blower power; below it a reserve of opening each way for a flow step (measured,
            docs/architecture.md 'The flat direction priced').
        flap_targets_pct: the targets of flaps m, f and w one by one (% of the opening ``v``, each in [0, 100]) in
            place of ``flap_target_pct`` for all three; None (the default): ``flap_target_pct``. A target at a split's
            rest mix (the largest flap fully open, the others at the openings that split the flow) puts the term's
            pull where the energy term already holds the flaps at rest, so only the flat direction's curvature is
            added (measured on winter_heating_steps, docs/architecture.md 'The flat direction priced, winter traced').
        flap_target_from_split: the flap-closure term's targets from the reference at each step in place of
            ``flap_target_pct`` / ``flap_targets_pct``: the openings of least blower power that give the reference's
            outlet shares (the flap that limits the network's conductance fully open, the others at the conductance
            their share asks; all fully open where the split is not tracked; :mod:`hvac_mpc.mpc.flap_target`). Off by
            default (measured in the same section).
    """

    stage_durations_s: tuple[float, ...] = DEFAULT_STAGES_S
    max_substep_s: float = 4.0
    tracked_temperature: str = "blend"
    sensor_share: float = 0.75
    weights: Weights = field(default_factory=Weights)
    rate_blower_w_per_s: float = 60.0
    rate_heater_w_per_s: float = 60.0
    rate_valve_pct_per_s: float = 50.0
    heater_temp_max_c: float | None = None
    trap_margin_pct: float = 5.0
    trap_warm_c: float = 5.0
    model_effects: tuple[str, ...] = ("fan_curve", "valve_leakage", "bypass_flow")
    ptc_limit: bool = True
    heater_min_flow_m3s: float | None = 0.005
    heater_on_w: float = 10.0
    ready_step_c: float = 3.0
    ready_lead_c: float | None = 3.0
    flap_target_pct: float = 100.0
    flap_targets_pct: tuple[float, float, float] | None = None
    flap_target_from_split: bool = False

    @property
    def temperature_sensor_share(self) -> float:
        """Share of the thermocouple in the tracked temperature: 0 air, 1 sensor, ``sensor_share`` blend."""
        return {"air": 0.0, "sensor": 1.0}.get(self.tracked_temperature, float(self.sensor_share))

    def validate(self, dt_s: float = 1.0, prefix: str = "ocp") -> None:
        """Raise :class:`InvalidSettings` naming the first bad field and its allowed range."""
        durations = self.stage_durations_s
        if not isinstance(durations, (tuple, list)) or not 2 <= len(durations) <= 200:
            raise InvalidSettings(f"{prefix}.stage_durations_s must be a sequence of 2 to 200 durations (s)")
        for i, d in enumerate(durations):
            check_number(f"{prefix}.stage_durations_s[{i}]", d, 0.0, 60.0, lo_open=True)
        if abs(float(durations[0]) - dt_s) > 1e-9:
            raise InvalidSettings(f"{prefix}.stage_durations_s[0] = {durations[0]} must equal the sample "
                                  f"time dt_s = {dt_s} (range [{dt_s}, {dt_s}])")
        if sum(durations) < 60.0:
            raise InvalidSettings(f"{prefix}.stage_durations_s must sum to at least 60 s (range [60, 12000]), "
                                  f"got {sum(durations)}")
        check_number(f"{prefix}.max_substep_s", self.max_substep_s, 0.05, 60.0)
        if not (isinstance(self.sensor_share, (int, float)) and 0.0 <= self.sensor_share <= 1.0):
            raise InvalidSettings(f"{prefix}.sensor_share = {self.sensor_share!r} must be a number in [0, 1]")
        if self.tracked_temperature not in ("air", "sensor", "blend"):
            raise InvalidSettings(f"{prefix}.tracked_temperature = {self.tracked_temperature!r} must be "
                                  f"'air' or 'sensor'")
        if not isinstance(self.weights, Weights):
            raise InvalidSettings(f"{prefix}.weights must be a Weights instance")
        self.weights.validate(f"{prefix}.weights")
        check_number(f"{prefix}.rate_blower_w_per_s", self.rate_blower_w_per_s, 1.0, 1000.0)
        check_number(f"{prefix}.rate_heater_w_per_s", self.rate_heater_w_per_s, 1.0, 1000.0)
        check_number(f"{prefix}.rate_valve_pct_per_s", self.rate_valve_pct_per_s, 0.5, 100.0)
        if self.heater_temp_max_c is not None:
            check_number(f"{prefix}.heater_temp_max_c", self.heater_temp_max_c, 20.0, 200.0)
        check_number(f"{prefix}.trap_margin_pct", self.trap_margin_pct, 0.0, 50.0)
        check_number(f"{prefix}.trap_warm_c", self.trap_warm_c, 0.0, 100.0)
        if self.heater_min_flow_m3s is not None:
            check_number(f"{prefix}.heater_min_flow_m3s", self.heater_min_flow_m3s, 0.0, 0.05)
        check_number(f"{prefix}.heater_on_w", self.heater_on_w, 0.0, 1000.0, lo_open=True)
        check_number(f"{prefix}.ready_step_c", self.ready_step_c, 0.0, 30.0)
        if self.ready_lead_c is not None:
            check_number(f"{prefix}.ready_lead_c", self.ready_lead_c, 0.0, 100.0, lo_open=True)
        check_flag(f"{prefix}.ptc_limit", self.ptc_limit)
        check_flag(f"{prefix}.flap_target_from_split", self.flap_target_from_split)
        check_number(f"{prefix}.flap_target_pct", self.flap_target_pct, 0.0, 100.0)
        if self.flap_targets_pct is not None:
            if not isinstance(self.flap_targets_pct, (tuple, list)) or len(self.flap_targets_pct) != 3:
                raise InvalidSettings(f"{prefix}.flap_targets_pct = {self.flap_targets_pct!r}: expected three openings "
                                      f"(%, flaps m, f, w, each in [0, 100]) or None")
            for name, value in zip("mfw", self.flap_targets_pct):
                check_number(f"{prefix}.flap_targets_pct[{name}]", value, 0.0, 100.0)
        unknown = sorted(set(self.model_effects) - set(MODEL_EFFECTS))
        if unknown:
            raise InvalidSettings(f"{prefix}.model_effects has unknown effect(s) {unknown}; allowed: "
                                  f"{list(MODEL_EFFECTS)}")


def trap_cap_pct(heater_temp_c: float, heater_in_c: float, heater_cmd_w: float, params: Parameters,
                 spec: OcpSpec) -> float:
    """Upper limit of valve a (%) against the trapped hot-air release (thesis sec. 5.4.2).

    The pocket at valve a closes only when a sits in saturation (above ``trap_threshold_pct``)
    and heats towards the heater temperature; the error appears when a leaves saturation with
    a hot heater. The release cannot happen if a never saturates while the heater is warm, so
    a is capped at ``trap_threshold_pct - trap_margin_pct`` whenever the heater body is more
    than ``trap_warm_c`` above the air entering it or the heater is commanded on; with a cold
    heater the pocket holds cold air and a may use its full travel (cooling needs it). This is
    a constraint rather than a model of the pocket: its tanh switch would make the
    linearisations of the real-time iteration unreliable. (The thesis capped a at 80 % in
    heating mode for the same reason.) The threshold is on the valve's effective angle, so a
    shifted valve-a curve (``valve_a_shift_pct``, models/valves.py) moves the cap on the command by
    the shift.
    """
    warm = (heater_temp_c - heater_in_c > spec.trap_warm_c) or heater_cmd_w > HEATING_CMD_W
    return min(100.0, params.trap_threshold_pct - spec.trap_margin_pct + params.valve_a_shift_pct) if warm else 100.0


class HeaterOffBound:
    """Upper bound of the heater body temperature from what was commanded, for the trapped-air guard.

    The estimator's heater temperature is not measured on every box: where the thermocouple reading
    is all it has, it may move the heater body to explain a supply-temperature error (measured in the
    cabin pull-down: 31.6 C estimated against 14.9 C true, the heater off since the start), and the
    guard then holds valve a at its cap for nothing. A heater body without power can
    only relax towards the air reaching it, with its time constant (thesis sec. 4.3-4.4,
    :func:`hvac_mpc.models.heater.time_constant_s`), so while the heater is off the guard uses the
    lesser of the estimate and that relaxation from the estimate at switch-off. While the heater is on
    the estimate stands (docs/robustness.md sec. 1). Where the prediction model adds a discovered heat flow to
    the body (a ``heater_body`` term, models/discovered.py), ``update`` takes the model's body balance
    (``body_rate``) instead: the relaxation above knows only the air, and a term that adds heat would put the
    bound below the body.
    """

    def __init__(self, params: Parameters, dt_s: float):
        self.params = params
        self.dt_s = float(dt_s)
        self.reset()

    def reset(self) -> None:
        self.bound_c: float | None = None

    def update(self, heater_est_c: float, heater_in_c: float, heater_cmd_w: float, mass_flow_kgs: float,
               body_rate: Callable[[float], float] | None = None) -> float:
        """The heater temperature the guard should use (degC), after one sample under ``heater_cmd_w``.
        ``body_rate``: the body's rate of change (degC/s) at a body temperature (degC) under the inputs in force,
        from the prediction model; the bound then follows it over the sample (RK4) instead of the relaxation
        towards ``heater_in_c``."""
        if self.bound_c is None or heater_cmd_w > HEATING_CMD_W or not math.isfinite(self.bound_c):
            self.bound_c = float(heater_est_c)
        elif body_rate is not None:
            self.bound_c = float(rk4(lambda t_c, *_: body_rate(t_c), self.bound_c, None, None, None, self.dt_s, 1))
        else:
            tau = float(heater.time_constant_s(max(float(mass_flow_kgs), 1e-3), self.params))
            self.bound_c = heater_in_c + (self.bound_c - heater_in_c) * math.exp(-self.dt_s / tau)
        return min(float(heater_est_c), self.bound_c)


class ParameterRows(NamedTuple):
    """The constants of the soft rows and of the body's heat that follow from the model parameters
    (:meth:`TrackingProblem.parameter_rows`; floats, or CasADi expressions of a symbolic ``p``)."""
    heater_bound_c: Any  # the heater row's bound (degC, scaled state's offset removed)
    ptc_coef_u: Any  # the PTC row's coefficient of the scaled heater command (degC per scaled unit)
    ptc_bound_c: Any  # the PTC row's bound (degC)
    body_heat_coef: Any  # :meth:`TrackingProblem.body_heat_coefficient`


class TrackingProblem:
    """The scaled discrete OCP data shared by all solvers (built once per controller).

    Decision inputs ``u`` (scaled): blower power, heater command and valve a as they are, and
    for valves m, f, w the opening ``v`` of :mod:`hvac_mpc.mpc.valve_map` (the angle is
    ``theta(v)``). :meth:`scale_u` / :meth:`unscale_u` convert between actuator commands
    (W, %) and scaled decisions.

    Attributes: ``N`` stages of durations ``dt`` (s) and node times ``t_nodes``; sizes ``nx``,
    ``nu``, ``nd``, ``ny``; scalings ``x_off``/``x_sc``/``u_off``/``u_sc``; decision bounds
    ``u_lo``/``u_hi``; ``rate_phys`` (W/s, %/s); ``heater_row_coef``/``heater_row_bound`` (soft
    heater row in degC); ``y_scale`` residual scales; ``w_du`` scaled move weights;
    ``energy_grad_u`` (W per scaled decision). CasADi functions: ``stages`` (one stage function
    per RK4 substep count, evaluated over the horizon by ``horizon`` in :meth:`linearise`;
    ``stages_p`` the same with the model parameters as a last input ``p``),
    ``F_by_substeps`` (x_next only), ``Y`` (outputs only), ``theta`` (valve angles of a decision).
    """

    VALVES = (3, 4, 5)  # decision indices of valves m, f, w (openings)

    def __init__(self, params: Parameters | None, spec: OcpSpec, dt_s: float = 1.0, terms: tuple = ()):
        """``terms``: discovered terms of a refined model (models/discovered.py) in the prediction."""
        spec.validate(dt_s)
        self.params = params or Parameters()
        self.spec = spec
        self.dt_s = float(dt_s)
        self.model = HvacModel(self.params, spec.model_effects, dt_s=dt_s, terms=terms)
        self.valve_map = ValveMap(self.params)
        m = self.model
        self.state_names = m.states.names
        self.nx, self.nu = len(m.states), len(m.inputs)
        self.nd = len(m.disturbances)
        self.dt = np.array(spec.stage_durations_s, float)
        self.N = len(self.dt)
        self.t_nodes = np.concatenate([[0.0], np.cumsum(self.dt)])
        # the transport-delay lags carry air temperatures: scaled like the thermocouple
        scaling = {n: STATE_SCALING.get(n, STATE_SCALING["supply_sensor_c"]) for n in self.state_names}
        self.x_off = np.array([scaling[n][0] for n in self.state_names])
        self.x_sc = np.array([scaling[n][1] for n in self.state_names])
        # RK4 stays stable and accurate on the delay lags with substeps of at most two lag time constants
        self.max_substep_s = float(spec.max_substep_s)
        if m.delay_states:
            lag_s = self.params.transport_delay_s / len(m.delay_states)
            self.max_substep_s = min(self.max_substep_s, 2.0 * lag_s)
        self.u_off = np.array([INPUT_SCALING[n][0] for n in INPUTS])
        self.u_sc = np.array([INPUT_SCALING[n][1] for n in INPUTS])
        self.valve_mask = np.zeros(self.nu, bool)
        self.valve_mask[list(self.VALVES)] = True
        # in the order of VALVE_NAMES; a slice (a view, where a list of indices copies: ~4 us a conversion)
        self._valve_cols = slice(self.VALVES[0], self.VALVES[-1] + 1)
        assert tuple(range(self.nu))[self._valve_cols] == self.VALVES, "ASSUMPTION: valves m, f, w decide side by side"
        self.u_off[self.valve_mask] = 0.5  # openings v in [0, 1]
        self.u_sc[self.valve_mask] = 0.5
        self.u_lo_phys = np.array([INPUT_LOWER[n] for n in INPUTS])
        self.u_hi_phys = np.array([input_upper(self.params)[n] for n in INPUTS])
        # valve a with a shifted curve is decided over the travel where it acts: at a command inside the shift the
        # prediction's gradient in valve a is zero and the iteration could not leave it (models/valves.py)
        ia = INPUTS.index("valve_a_pct")
        self.u_lo_phys[ia], self.u_hi_phys[ia] = valves.acting_travel(self.params.valve_a_shift_pct)
        self.u_lo, self.u_hi = self.scale_u(self.u_lo_phys), self.scale_u(self.u_hi_phys)
        self._u_lo_tiled = np.tile(self.u_lo, (self.N, 1))
        self._u_hi_tiled = np.tile(self.u_hi, (self.N, 1))
        self.rate_phys = np.array([spec.rate_blower_w_per_s, spec.rate_heater_w_per_s]
                                  + [spec.rate_valve_pct_per_s] * 4)
        self.rate = self.rate_phys / self.u_sc  # meaningful for the non-valve decisions only
        self.i_heater = self.state_names.index("heater_temp_c")
        self.i_valve_a = INPUTS.index("valve_a_pct")
        # the farthest valve a can close by each node (scaled), for the cap of input_bounds
        self._a_travel = self.rate_phys[self.i_valve_a] * self.t_nodes[1:] / self.u_sc[self.i_valve_a]
        self.i_heater_cmd = INPUTS.index("heater_cmd_w")
        hmax = spec.heater_temp_max_c if spec.heater_temp_max_c is not None else self.params.heater_temp_max_c
        self.heater_max_phys = float(hmax)
        # soft row in degC: x_sc * x_heater - s <= heater_max - x_off
        self.heater_row_coef = float(self.x_sc[self.i_heater])
        # PTC row in degC, stages k = 1..N-1 (x_k with u_k, slack s_k):
        # cmd / c + T_h - s <= T_zero with c = P_max / (T_zero - T_knee) (W/K), the falling part of
        # heater.available_power_w
        self.ptc_limit = bool(spec.ptc_limit)
        self.energy_weight = spec.weights.energy_per_100w2
        self.energy_scale_w = 100.0
        rows = self.parameter_rows(self.model.p_default)
        self.heater_row_bound, self.ptc_row_coef_u, self.ptc_row_bound, self.body_heat_coef = map(float, rows)
        # flow floor while the heater is on (module docstring), in L/s
        self.floor = bool(spec.heater_min_flow_m3s)
        self.floor_m3s = float(spec.heater_min_flow_m3s or 0.0)
        self.floor_on_w = float(spec.heater_on_w)
        self.floor_scale = FLOOR_SCALE
        w = spec.weights
        self.ny = len(STAGE_OUTPUTS)
        self.y_scale = np.array([1.0, 1e-3, 1e-3, 1e-3, 1e-3, 1.0, 1.0])
        self.w_y_full = np.array([w.supply_temp, w.volume_flow, w.outlet_flow, w.outlet_flow, w.outlet_flow, 0.0, 0.0])
        self.valve_a_heating_weight = w.valve_a_heating_per_pct2
        # move weights per unit^2 of the command; for the valve openings per (1 % of opening)^2
        move = np.array([w.move_blower_per_w2, w.move_heater_per_w2] + [w.move_valve_per_pct2] * 4)
        unit = np.where(self.valve_mask, self.u_sc * 100.0, self.u_sc)
        self.w_du = move * unit ** 2
        self.flap_closure_weight = w.flap_closure_per_pct2
        # the flaps' opening the closure term pulls towards (scaled decisions; zero off the flaps)
        self.flap_target_u = np.where(self.valve_mask, (self.flap_targets_opening(spec) - self.u_off) / self.u_sc, 0.0)
        # with OcpSpec.flap_target_from_split the targets follow the reference's split (flap_target_for)
        self.flap_split_target = (SplitTarget(self.params, self.valve_map, "valve_leakage" in spec.model_effects)
                                  if spec.flap_target_from_split else None)
        # d(P_blower)/d(u scaled): the blower term of the energy is linear in the input
        self.energy_grad_u = np.zeros(self.nu)
        self.energy_grad_u[INPUTS.index("blower_power_w")] = self.u_sc[INPUTS.index("blower_power_w")]
        # slacks are in degC (not scaled): they stay O(1) beside the other variables
        self.slack_l1 = w.slack_l1_per_c
        self.slack_l2 = w.slack_l2_per_c2
        self.terminal_s = w.terminal_s
        self._build_functions()

    def parameter_rows(self, p) -> ParameterRows:
        """The constants of the soft rows and of the body's heat that follow from the model parameters ``p``
        (:attr:`HvacModel.p_default` order; numpy or CasADi, the same operations): the heater row's bound (degC;
        :attr:`OcpSpec.heater_temp_max_c` where set), the PTC row's coefficient of the scaled heater command and its
        bound (degC), and :meth:`body_heat_coefficient`. From the symbolic ``p`` in generated code (the plans'
        merit, :mod:`.plan_merit`), so that code serves every parameter set of the same structure."""
        names = Parameters.scalar_names()

        def at(name):
            return p[names.index(name)]
        ih = self.i_heater_cmd
        hmax = self.spec.heater_temp_max_c if self.spec.heater_temp_max_c is not None else at("heater_temp_max_c")
        slope_w_per_k = at("heater_power_max_w") / (at("ptc_zero_c") - at("ptc_knee_c"))
        return ParameterRows(hmax - self.x_off[self.i_heater], self.u_sc[ih] / slope_w_per_k,
                             at("ptc_zero_c") - self.u_off[ih] / slope_w_per_k - self.x_off[self.i_heater],
                             self.body_heat_coefficient(at("heater_mass_kg") * at("heater_c_j_per_kgk")))

    def body_heat_coefficient(self, capacity_j_per_k=None):
        """Cost per unit of the scaled terminal heater-body state (:attr:`Weights.body_heat_power_w`): the
        value of the stored heat enters the cost as ``coef * x_N[i_heater]`` (negative: a hotter body at the
        horizon's end costs less); 0 when off. Price per J ``2 w_E P / (100 W)^2`` times ``C_body`` (J/K;
        ``capacity_j_per_k``, by default the parameters', numpy or CasADi) times the state's scale (K per scaled
        unit)."""
        w = self.spec.weights
        price_per_j = 2.0 * self.energy_weight * w.body_heat_power_w / self.energy_scale_w ** 2
        if capacity_j_per_k is None:
            capacity_j_per_k = self.params.heater_mass_kg * self.params.heater_c_j_per_kgk
        return -price_per_j * capacity_j_per_k * float(self.x_sc[self.i_heater])

    def body_heat_on(self, u_prev):
        """1 where the value of the body's heat counts (the scaled command in force ``u_prev`` has the heater on,
        :meth:`heating`), else 0; numpy or CasADi (``if_else``)."""
        ih = self.i_heater_cmd
        cmd_w = self.u_off[ih] + self.u_sc[ih] * u_prev[ih]
        if isinstance(cmd_w, (ca.SX, ca.MX)):
            return ca.if_else(cmd_w > HEATING_CMD_W, 1.0, 0.0)
        return float(cmd_w > HEATING_CMD_W)

    def body_heat_cost(self, x0, x_end, u_prev, coef=None):
        """The value of the body's heat (:attr:`Weights.body_heat_power_w`) for a plan from the scaled state
        ``x0`` to ``x_end`` with the command in force ``u_prev`` (scaled): ``coef (x_end - x0)`` of the heater
        body while heating, else 0 (``coef`` by default :attr:`body_heat_coef`)."""
        coef = self.body_heat_coef if coef is None else coef
        return self.body_heat_on(u_prev) * coef * (x_end[self.i_heater] - x0[self.i_heater])

    def flap_targets_opening(self, spec: OcpSpec) -> np.ndarray:
        """The flap-closure term's target openings (fraction of the opening ``v``, per decision; 0 off the flaps):
        :attr:`OcpSpec.flap_targets_pct` flap by flap where set, else :attr:`OcpSpec.flap_target_pct` for all."""
        target = np.zeros(self.nu)
        per_flap = spec.flap_targets_pct or (spec.flap_target_pct,) * len(self.VALVES)
        target[list(self.VALVES)] = np.asarray(per_flap, float) / 100.0
        return target

    def flap_target_for(self, ref, tracked):
        """The flap-closure term's targets (scaled decisions, nu entries, zero off the flaps) for the reference
        vector ``ref`` (:meth:`reference_vector`) where ``tracked`` (the split's weights on): from its split with
        :attr:`OcpSpec.flap_target_from_split` (:mod:`~.flap_target`), else the fixed :attr:`flap_target_u`. numpy in,
        numpy out; CasADi in, a list of nu entries out."""
        if self.flap_split_target is None:
            return self.flap_target_u
        openings = self.flap_split_target.openings(ref[2:5], tracked)
        if isinstance(openings, np.ndarray):
            target = np.zeros(self.nu)
            target[list(self.VALVES)] = (openings - self.u_off[list(self.VALVES)]) / self.u_sc[list(self.VALVES)]
            return target
        target = [0.0] * self.nu
        for j, v in zip(self.VALVES, openings):
            target[j] = (v - self.u_off[j]) / self.u_sc[j]
        return target

    def flap_closure_hessian(self, target_u: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The flap-closure term (:attr:`Weights.flap_closure_per_pct2`) as ``1/2 u' H u + g' u`` per stage, in scaled
        decisions: diagonals ``H`` (N, nu) and gradients ``g`` (N, nu), zero off the flaps and when off. The term is
        ``dt_k w (c (u_T - u))^2`` per flap, ``u_T`` the target opening (``target_u``, scaled; by default
        :attr:`flap_target_u`, from :attr:`OcpSpec.flap_target_pct`), ``c`` the % of opening per scaled unit."""
        h = np.zeros((self.N, self.nu))
        g = np.zeros((self.N, self.nu))
        if not self.flap_closure_weight:
            return h, g
        target = self.flap_target_u if target_u is None else np.asarray(target_u, float)
        c2 = (self.u_sc * 100.0) ** 2
        w = self.flap_closure_weight * self.dt[:, None] * np.where(self.valve_mask, c2, 0.0)[None, :]
        h[:] = 2.0 * w
        g[:] = -2.0 * w * target[None, :]
        return h, g

    def flap_closure_cost(self, u, k: int, target_u=None):
        """The flap-closure term of stage k for its scaled decisions ``u`` (numpy or CasADi; 0 when off), towards
        ``target_u`` (scaled, nu entries; by default :attr:`flap_target_u`)."""
        if not self.flap_closure_weight:
            return 0.0
        target = self.flap_target_u if target_u is None else target_u
        cost = 0.0
        for j in self.VALVES:
            closure_pct = self.u_sc[j] * 100.0 * (target[j] - u[j])
            cost = cost + self.dt[k] * self.flap_closure_weight * closure_pct * closure_pct
        return cost

    # ------------------------------------------------------------------ scaling
    def scale_x(self, x_phys):
        return (np.asarray(x_phys, float) - self.x_off) / self.x_sc

    def unscale_x(self, x):
        return np.asarray(x, float) * self.x_sc + self.x_off

    def scale_u(self, u_phys):
        """Actuator commands (..., 6) in W and % -> scaled decisions (valve angles to openings)."""
        u = np.array(u_phys, float)
        u[..., self._valve_cols] = self.valve_map.openings(u[..., self._valve_cols])
        return (u - self.u_off) / self.u_sc

    def unscale_u(self, u):
        """Scaled decisions (..., 6) -> actuator commands in W and % (openings to angles)."""
        out = np.asarray(u, float) * self.u_sc + self.u_off
        out[..., self._valve_cols] = self.valve_map.angles(out[..., self._valve_cols])
        return out

    def placeholder_state(self) -> np.ndarray:
        """A plausible physical state (degC) for solver set-up: motor rise 1, water 5, the rest 15."""
        guess = {"motor_rise_c": 1.0, "water_temp_c": 5.0}
        return np.array([guess.get(n, 15.0) for n in self.state_names])

    def ptc_available_w(self, heater_temp_c: float) -> float:
        """Heater power available at ``heater_temp_c`` (W), the line of :attr:`OcpSpec.ptc_limit`."""
        return float(heater.available_power_w(heater_temp_c, self.params))

    def ptc_row(self, heater_x, heater_u, rows=None):
        """PTC row, ``<= 0`` when kept (degC, before its slack), of the scaled heater temperature
        ``heater_x`` and scaled heater command ``heater_u`` of the same stage (CasADi or numpy; the
        QP of ``rti_osqp`` holds the same coefficients); ``rows``: :meth:`parameter_rows` of other (e.g.
        symbolic) parameters, by default this problem's."""
        if rows is None:
            coef_u, bound = self.ptc_row_coef_u, self.ptc_row_bound
        else:
            coef_u, bound = rows.ptc_coef_u, rows.ptc_bound_c
        return self.heater_row_coef * heater_x + coef_u * heater_u - bound

    def floor_row(self, flow_m3s, heater_cmd_w):
        """Flow-floor row, ``>= 0`` when kept (L/s), of the total flow and the heater command of one stage
        (CasADi): ``Q - Q_min min(1, P / P_on)``."""
        return self.floor_scale * (flow_m3s - self.floor_m3s * ca.fmin(1.0, heater_cmd_w / self.floor_on_w))

    def floor_linearisation(self, heater_u) -> tuple[np.ndarray, np.ndarray]:
        """The floor's heater part ``Q_min min(1, P / P_on)`` at scaled heater commands ``heater_u`` (numpy or
        CasADi, the same operations): its value (m3/s) and its slope per scaled command (what :meth:`floor_row`
        gives CasADi's Jacobian)."""
        ih = self.i_heater_cmd
        symbolic = isinstance(heater_u, (ca.SX, ca.MX))
        where = ca.if_else if symbolic else np.where
        p_w = float(self.u_off[ih]) + float(self.u_sc[ih]) * (heater_u if symbolic else np.asarray(heater_u, float))
        ratio = p_w / self.floor_on_w
        below = ratio < 1.0
        value = self.floor_m3s * where(below, ratio, 1.0)
        slope = where(below, self.floor_m3s * self.u_sc[ih] / self.floor_on_w, 0.0)
        return value, slope

    def command_bounds(self, u_prev_phys: np.ndarray, cap_a_pct: float = 100.0,
                       heater_temp_c: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Physical bounds of the next command: actuator ranges, rate limits over one sample, the
        valve a cap (never tighter than valve a can follow from ``u_prev_phys``) and, with
        ``ptc_limit`` and a heater temperature, the PTC's available power (never tighter than the
        heater command can follow)."""
        step = self.rate_phys * self.dt_s
        lo = np.maximum(self.u_lo_phys, u_prev_phys - step)
        hi = np.minimum(self.u_hi_phys, u_prev_phys + step)
        ia = self.i_valve_a
        hi[ia] = min(hi[ia], max(cap_a_pct, u_prev_phys[ia] - step[ia]))
        if self.ptc_limit and heater_temp_c is not None and math.isfinite(heater_temp_c):
            ih = self.i_heater_cmd
            hi[ih] = min(hi[ih], max(self.ptc_available_w(heater_temp_c), lo[ih]))
        lo = np.minimum(lo, hi)
        return lo, hi

    def input_bounds(self, u_prev_phys: np.ndarray, cap_a_pct: float = 100.0,
                     heater_temp_c: float | None = None,
                     command: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Scaled decision bounds (N, nu): ranges everywhere, the first stage's rate limits folded in
        exactly (the opening is monotone in the angle), the first stage's PTC limit (later stages
        carry it as a row of the problem), and the valve a cap, which tightens stage by stage no
        faster than valve a may move, so the bounds always hold a feasible point. ``command``: the
        :meth:`command_bounds` of the same arguments where the caller has them already."""
        lo = self._u_lo_tiled.copy()
        hi = self._u_hi_tiled.copy()
        ia = self.i_valve_a
        cap = (min(cap_a_pct, 100.0) - self.u_off[ia]) / self.u_sc[ia]
        reachable = (u_prev_phys[ia] - self.u_off[ia]) / self.u_sc[ia] - self._a_travel
        hi[:, ia] = np.minimum(hi[:, ia], np.maximum(cap, reachable))
        first = self.scale_u(command or self.command_bounds(u_prev_phys, cap_a_pct, heater_temp_c))  # (2, nu)
        lo0, hi0 = lo[0], hi[0]  # views: the first stage's rows changed in place
        np.maximum(lo0, first[0], out=lo0)
        np.minimum(hi0, first[1], out=hi0)
        np.minimum(lo0, hi0, out=lo0)
        return lo, hi

    def rate_bounds(self) -> np.ndarray:
        """Largest change between stage k-1 and k, k = 1..N-1, shape (N-1, nu), scaled: rate * dt_{k-1}.

        For valves m, f, w the plan limits the opening instead of the angle: rate / 100 per s of
        opening, the angle's average speed (theta spans 100 % over v in [0, 1]). This keeps the
        constraint linear and always feasible; the move actually applied (stage 0) is limited
        exactly in angle by :meth:`input_bounds`.
        """
        rate = self.rate.copy()
        rate[self.valve_mask] = self.rate_phys[self.valve_mask] / 100.0 / self.u_sc[self.valve_mask]
        return rate[None, :] * self.dt[:-1, None]

    # ------------------------------------------------------------------ references
    def output_weights(self, reference: Reference) -> np.ndarray:
        """Output weights for a reference: outlet flows weigh zero when the split is free."""
        w = self.w_y_full.copy()
        if reference.split is None:
            w[2:5] = 0.0
        return w

    def reference_vector(self, reference: Reference) -> np.ndarray:
        """Reference of the stage outputs (physical units; 0 where not tracked). Valve a's row is the command at
        which the model reads its curve shut (``valve_a_shift_pct``, %; 0 for the unshifted curve): its weight
        while heating (:attr:`Weights.valve_a_heating_per_pct2`, and the reserve's in its place) is on the valve's
        opening as the model reads it, the command less the shift, as the trapped-air cap is
        (:func:`trap_cap_pct`); on the command itself a shifted curve's shut valve would be weighed as open by the
        shift (docs/identification.md, "The variants that still lose, traced"). A negative shift puts the row below
        valve a's lower bound (0 %): the weight then pulls towards the command the model reads as shut, which the bound
        does not reach."""
        split = reference.split or (0.0, 0.0, 0.0)
        return np.array([reference.supply_temp_c, reference.volume_flow_m3s, *split, 0.0,
                         float(self.params.valve_a_shift_pct)])

    def heating(self, u_phys: np.ndarray) -> bool:
        """Whether the command ``u_phys`` (physical) has the heater on (above :data:`HEATING_CMD_W`)."""
        return bool(u_phys[self.i_heater_cmd] > HEATING_CMD_W)

    def heating_weights(self, w_y: np.ndarray, heating: bool) -> np.ndarray:
        """``w_y`` with valve a's weight (:attr:`Weights.valve_a_heating_per_pct2`) on while ``heating`` (the heater
        commanded), off otherwise."""
        w_y[Y_VALVE_A] = self.valve_a_heating_weight if heating else 0.0
        return w_y

    # ------------------------------------------------------------------ CasADi
    def _stage_function(self, substeps: int) -> ca.Function:
        """One stage (x, u, d, dt) -> stacked [x_next, vec A, vec B, y, vec C, vec D] with RK4 substeps,
        at the problem's parameters (:meth:`_stage_function_p` with ``p`` fixed)."""
        f = self.stages_p[substeps]
        xs, us, d, dt = ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu), ca.SX.sym("d", self.nd), ca.SX.sym("dt")
        return ca.Function(f"stage{substeps}", [xs, us, d, dt], [f(xs, us, d, dt, ca.DM(self.model.p_default))],
                           ["x", "u", "d", "dt"], ["out"])

    def _stage_function_p(self, substeps: int) -> ca.Function:
        """:meth:`_stage_function` with the model parameters ``p`` (``HvacModel.p_default`` order) as
        an input, so generated code built from it serves every parameter set of one structure."""
        xs, us, d, dt, p = self._stage_symbols()
        xn, y = self._stage_values(xs, us, d, dt, p, substeps)
        out = ca.densify(ca.vertcat(xn, ca.vec(ca.jacobian(xn, xs)), ca.vec(ca.jacobian(xn, us)), y,
                                    ca.vec(ca.jacobian(y, xs)), ca.vec(ca.jacobian(y, us))))
        return ca.Function(f"stage{substeps}_p", [xs, us, d, dt, p], [out], ["x", "u", "d", "dt", "p"], ["out"])

    def stage_values_function(self, substeps: int) -> ca.Function:
        """One stage without its Jacobians: ``(x, u, d, dt, p) -> (x_next, y)`` (scaled states, the stage
        outputs :data:`STAGE_OUTPUTS`), the values of :meth:`_stage_function_p` (for rollouts of a plan)."""
        xs, us, d, dt, p = self._stage_symbols()
        xn, y = self._stage_values(xs, us, d, dt, p, substeps)
        return ca.Function(f"stage_values{substeps}", [xs, us, d, dt, p], [xn, y], ["x", "u", "d", "dt", "p"],
                           ["x_next", "y"])

    def _stage_symbols(self) -> tuple:
        """CasADi symbols of one stage's arguments: scaled x and u, d, dt, the model parameters p."""
        return (ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu), ca.SX.sym("d", self.nd), ca.SX.sym("dt"),
                ca.SX.sym("p", len(self.model.p_default)))

    def _stage_values(self, xs, us, d, dt, p, substeps: int) -> tuple:
        """Scaled next state (RK4, ``substeps``) and the stage outputs of one stage, symbolically."""
        m = self.model
        x_off, x_sc = ca.DM(self.x_off), ca.DM(self.x_sc)
        u_phys = self._command_expr(us)
        x_phys = x_off + x_sc * xs
        xk = rk4(m.ode, x_phys, u_phys, d, p, dt, substeps)
        xn = (xk - x_off) / x_sc
        y_all = m.output(x_phys, u_phys, d, p)
        share = self.spec.temperature_sensor_share
        # the air where the thermocouple sits: the mixed air after the transport delay (the same
        # with no delay)
        temp = ((1.0 - share) * y_all[m.outputs.index("duct_air_temp_c")]
                + share * y_all[m.outputs.index("supply_temp_c")])
        y = ca.vertcat(temp, *[y_all[m.outputs.index(n)] for n in STAGE_OUTPUTS[1:-1]], u_phys[self.i_valve_a])
        return xn, y

    def _command_expr(self, us):
        """Actuator commands (W, %) of scaled decisions, symbolically (valve openings -> angles)."""
        parts = []
        for j in range(self.nu):
            value = self.u_off[j] + self.u_sc[j] * us[j]
            if self.valve_mask[j]:
                value = self.valve_map.theta_expr(VALVE_NAMES[self.VALVES.index(j)], value)
            parts.append(value)
        return ca.vertcat(*parts)

    def command_expr(self, us):
        """Actuator commands (W, %) of scaled decisions ``us``, symbolically (valve openings -> angles)."""
        return self._command_expr(us)

    def theta(self, us):
        """Valve angles m, f, w (%) of scaled decisions (CasADi)."""
        return self._command_expr(us)[list(self.VALVES)]

    def _build_functions(self) -> None:
        nx, nu = self.nx, self.nu
        # substeps per stage: the longest RK4 substep is max_substep_s; the terminal stage only
        # needs outputs, so one substep
        ns = [max(1, int(math.ceil(dt / self.max_substep_s - 1e-9))) for dt in self.dt] + [1]
        self.stage_substeps = np.array(ns)
        self.stages_p = {n: self._stage_function_p(n) for n in sorted(set(ns))}
        self.stages = {n: self._stage_function(n) for n in sorted(set(ns))}
        groups, start = [], 0
        for k in range(1, len(ns) + 1):
            if k == len(ns) or ns[k] != ns[start]:
                groups.append((start, k, ns[start]))
                start = k
        self.groups = groups
        xs = ca.SX.sym("x", nx)
        us = ca.SX.sym("u", nu)
        d = ca.SX.sym("d", self.nd)
        dt = ca.SX.sym("dt")
        max_ns = int(self.stage_substeps.max())
        # F and Y for rollouts and NLP solvers: the stage's own substep count
        self.F_by_substeps = {n: ca.Function(f"F{n}", [xs, us, d, dt], [f(xs, us, d, dt)[:nx]],
                                             ["x", "u", "d", "dt"], ["x_next"]) for n, f in self.stages.items()}
        f1 = self.stages[1] if 1 in self.stages else self.stages[max_ns]
        o = nx + nx * nx + nx * nu
        self.Y = ca.Function("Y", [xs, us, d], [f1(xs, us, d, 1.0)[o:o + self.ny]], ["x", "u", "d"], ["y"])
        o, sl = 0, {}
        for name, size in (("xn", nx), ("A", nx * nx), ("B", nx * nu), ("y", self.ny), ("C", self.ny * nx),
                           ("D", self.ny * nu)):
            sl[name] = slice(o, o + size)
            o += size
        self.out_slices = sl
        self.n_out = o
        self.set_stage_functions(self.stages)

    def set_stage_functions(self, functions: dict) -> None:
        """Use these stage functions (substeps -> Function), e.g. JIT-compiled ones.

        All stages are evaluated by one MX function calling each group's mapped stage function,
        so a linearisation is a single call from Python.
        """
        X = ca.MX.sym("X", self.nx, self.N + 1)
        U = ca.MX.sym("U", self.nu, self.N + 1)
        d = ca.MX.sym("d", self.nd)
        dt = np.append(self.dt, self.dt[-1])
        parts = [functions[n].map(b - a, "serial")(X[:, a:b], U[:, a:b], d, ca.DM(dt[None, a:b]))
                 for a, b, n in self.groups]
        self.horizon = ca.Function("horizon", [X, U, d], [ca.horzcat(*parts)], ["X", "U", "d"], ["out"])
        self._horizon = BufferedFunction(self.horizon)

    def F(self, x, u, d, k: int):
        """x_next of stage k (its own substeps)."""
        return self.F_by_substeps[int(self.stage_substeps[k])](x, u, d, self.dt[k])

    def linearise(self, X: np.ndarray, U: np.ndarray, d: np.ndarray) -> dict[str, np.ndarray]:
        """Evaluate all N+1 stages at states X (N+1, nx) and inputs U (N+1, nu).

        Stage N is the terminal output evaluation (its x_next, A, B are unused). Returns arrays
        with a leading stage axis: xn (N+1, nx), A (N+1, nx, nx), B (N+1, nx, nu), y (N+1, ny),
        C (N+1, ny, nx), D (N+1, ny, nu).
        """
        out = self._horizon(X, U, d)[0]  # (N+1, n_out): CasADi's column-major (n_out, N+1)
        s, K, nx, nu, ny = self.out_slices, self.N + 1, self.nx, self.nu, self.ny
        # CasADi vec() is column-major: reshape to (stage, col, row) and swap
        return {
            "xn": out[:, s["xn"]],
            "A": out[:, s["A"]].reshape(K, nx, nx).transpose(0, 2, 1),
            "B": out[:, s["B"]].reshape(K, nu, nx).transpose(0, 2, 1),
            "y": out[:, s["y"]],
            "C": out[:, s["C"]].reshape(K, nx, ny).transpose(0, 2, 1),
            "D": out[:, s["D"]].reshape(K, nu, ny).transpose(0, 2, 1),
        }

    def rollout(self, x0: np.ndarray, u: np.ndarray, d: np.ndarray) -> np.ndarray:
        """States (N+1, nx) from x0 holding the scaled input u over the whole horizon."""
        X = np.empty((self.N + 1, self.nx))
        X[0] = x0
        for k in range(self.N):
            X[k + 1] = np.asarray(self.F(X[k], u, d, k)).ravel()
        return X

    # ------------------------------------------------------------------ exact cost
    def symbolic_cost(self, X, U, S, d, ref, w_y, u_prev):
        """Exact cost (module docstring) for CasADi X (nx, N+1), U (nu, N), S (N, 1) and parameters."""
        cost = 0
        sw = w_y / ca.DM(self.y_scale ** 2)
        for k in range(self.N + 1):
            uk = U[:, min(k, self.N - 1)]
            y = self.Y(X[:, k], uk, d)
            e = y - ref
            weight = self.dt[k] if k < self.N else self.terminal_s
            cost += weight * ca.dot(sw, e * e)
            if k < self.N:
                ib = INPUTS.index("blower_power_w")
                blower_w = uk[ib] * self.u_sc[ib] + self.u_off[ib]
                heater_w = y[STAGE_OUTPUTS.index("heater_power_w")]
                cost += self.dt[k] * self.energy_weight * ((blower_w + heater_w) / self.energy_scale_w) ** 2
        prev = u_prev
        for k in range(self.N):
            du = U[:, k] - prev
            cost += ca.dot(ca.DM(self.w_du), du * du)
            prev = U[:, k]
        cost += ca.dot(ca.DM(self.dt), self.slack_l1 * S + self.slack_l2 * S * S)
        cost += self.body_heat_cost(X[:, 0], X[:, self.N], u_prev)
        target = self.flap_target_for(ref, w_y[_Y_OUTLET_M] > 0.0) if self.flap_closure_weight else None
        for k in range(self.N):
            cost += self.flap_closure_cost(U[:, k], k, target)
        return cost

    def cost_function(self) -> ca.Function:
        """Exact cost as a function of (X (nx, N+1), U (nu, N), S (N), d, ref, w_y, u_prev), all scaled."""
        X = ca.SX.sym("X", self.nx, self.N + 1)
        U = ca.SX.sym("U", self.nu, self.N)
        S = ca.SX.sym("S", self.N)
        d, ref, w_y = ca.SX.sym("d", self.nd), ca.SX.sym("ref", self.ny), ca.SX.sym("w_y", self.ny)
        u_prev = ca.SX.sym("u_prev", self.nu)
        return ca.Function("cost", [X, U, S, d, ref, w_y, u_prev],
                           [self.symbolic_cost(X, U, S, d, ref, w_y, u_prev)])


def shift_maps(t_nodes: np.ndarray, shift_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index and weight maps that move a trajectory on the stage grid forward by ``shift_s``.

    Returns (i0, w1, j): new node k interpolates old nodes i0[k] and i0[k]+1 with weight w1[k]
    (held at the end), and new stage k takes the input of old stage j[k] (the block containing
    the new stage's start, last block beyond the horizon).
    """
    N = len(t_nodes) - 1
    tau = np.minimum(t_nodes + shift_s, t_nodes[-1])
    i0 = np.clip(np.searchsorted(t_nodes, tau, side="right") - 1, 0, N - 1)
    w1 = (tau - t_nodes[i0]) / (t_nodes[i0 + 1] - t_nodes[i0])
    j = np.clip(np.searchsorted(t_nodes, t_nodes[:-1] + shift_s, side="right") - 1, 0, N - 1)
    return i0, np.clip(w1, 0.0, 1.0), j


def shift_nodes(X: np.ndarray, i0: np.ndarray, w1: np.ndarray) -> np.ndarray:
    """Node trajectory ``X`` ((N+1) x n) moved forward with the maps of :func:`shift_maps`."""
    w = w1[:, None]
    return X[i0] * (1.0 - w) + X[np.minimum(i0 + 1, len(X) - 1)] * w

