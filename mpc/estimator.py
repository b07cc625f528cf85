"""Extended Kalman filter on the model states augmented with disturbance states.

Augmented state ``z = [x, mix_offset_c, flow_offset_m3s, inlet_temp_c]``: the model states
(``HvacModel.states``), the two unmeasured offsets the model adds to the mixed supply air
temperature and the total volume flow (random walks: they absorb whatever the plant does that
the model does not), and the inlet air temperature (a random walk measured with noise).
Measurements (each used when present and finite): thermocouple ``supply_temp_c``,
``volume_flow_m3s``, ``water_temp_c``, ``hvac_inlet_temp_c`` and, optionally,
``heater_outlet_temp_c``.

Offset-free tracking: the MPC predicts with the estimated offsets, and at rest the filter
makes the model reproduce the measured supply temperature and flow exactly, so the
controller's steady state has no error in the measured outputs (Pannocchia and Rawlings'
disturbance-model argument: as many integrating disturbances as tracked measured outputs;
docs/architecture.md, 'One control step').

Dead time (``EkfSettings.dead_time_max_s``): the thermocouple may see the mixed air later than
the model says (a transport delay the parameters do not name). The filter keeps the last
``dead_time_max_s`` samples of the model's undelayed thermocouple state as states of its own
(a shift register: each is a copy of the one before), and compares the reading with the entry
of the estimated dead time, which :class:`~.dead_time.DeadTimeEstimator` picks online from the
same readings, once it reaches ``dead_time_min_s`` (optionally starting from a prior,
``dead_time_prior_s``). The model states, and so the MPC's
prediction, stay undelayed: the controller
steers the response it will see a dead time later (a Smith predictor in state-space form), and
the mixed-air offset integrates only what the delayed comparison leaves, not the delay itself.
With an estimate of 0 the filter is the plain one. docs/robustness.md sec. 2.

Bypass split against flow (models with the ``bypass_flow`` effect): the exponent k of
``b_eff = b (m / m_ref)^k`` (``Parameters.bypass_flow_exponent``, an ASSUMPTION the thesis model
leaves out) is the filter's own, ``EkfSettings.bypass_flow_exponent_prior`` (0: the thesis model),
and the MPC predicts with it (:attr:`DisturbanceEkf.bypass_flow_exponent`). With
``learn_bypass_flow`` it is one more state, a slow random walk. At a steady flow its effect on the
supply temperature is a constant the mixed-air offset takes as well, so it is learned only while the
flow moves (the model's flow more than ``bypass_flow_gate`` in log from its running mean); otherwise
it is a constant to the filter (its column of the Jacobians and its row of the gain zeroed, its
correlations dropped, its variance kept). docs/robustness.md sec. 1. With ``bypass_flow_anchored`` the
split's reference flow is a state too (its logarithm, no process noise, no variance: the filter does not
estimate it): before each measurement update it moves towards the model's mass flow, and the mixed-air
offset takes the model's change at the command in force, so the exponent acts only on a flow away from the
recent one, never on the level (docs/robustness.md sec. 2.7).

Core path (``EkfSettings.q_cooler_offset_c``, ``q_heater_air_offset_c``): offsets of the air leaving the cooler core
or the heater, states of the filter in place of the model's parameters ``cooler_outlet_offset_c`` and
``heater_air_offset_c``, so the model's own mixing gives them the effect on the supply air that valve a's position
makes of it; the prediction uses the estimates (docs/robustness.md sec. 2.13). Which of the heater outlet reading's
own offset and the heater air's the prediction uses is chosen online by the controller, a filter of each compared by
their supply innovations (:attr:`DisturbanceEkf.supply_nis`, :mod:`~.placement`, sec. 2.14).

Heat into the supply air (``EkfSettings.q_supply_heat_w``): a heat flow (W) into the mixed air, a state of the filter
in place of the model's parameter ``supply_heat_w``, whose effect on the air the model divides by its mass flow: a
duct's gain from the cabin steps the needed offset at every flow change, which the heat flow does by itself
(docs/robustness.md sec. 2.22).

Chiller water (``water_prediction``): ``"hold"`` treats the water temperature as a random walk
(the chiller's two-point switching is unknown to the model, thesis sec. 2.2); ``"setpoint"``
lets it ramp towards the chiller set point as in the model (thesis sec. 4.2).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import casadi as ca
import numpy as np

from hvac_mpc.models import air as air_props, blower
from hvac_mpc.models.box import HvacModel, rk4
from hvac_mpc.contract import Measurement

from .arrays import all_finite
from .casadi_eval import BufferedFunction
from .dead_time import DeadTimeEstimator
from .flow_term import FlowStepFit, SettledFlowSteps
from .reanchor import REANCHORABLE, FilterLayout, OpenLoopShadow, reanchor
from .response_wait import ResponseWait
from .rest_gate import RestGate
from .ocp import InvalidSettings, check_flag, check_number

#: Process noise of the history entries (degC per sample): exact copies, a floor for the numerics.
HIST_Q_C = 1e-4
#: Range of the bypass-flow exponent (that of Parameters.bypass_flow_exponent); the estimate is clipped to it.
BYPASS_FLOW_EXPONENT_RANGE = (-3.0, 3.0)
#: Ranges of settings with their own: ``bypass_flow_after_s`` (s) at most an hour, a start-up and not a run (the
#: dead-time estimate's window has the same bound); ``motor_sd_after_response_c`` (degC) at most the largest motor
#: rise the parameters allow (``Parameters.motor_gain_max_c`` at most 10 degC).
#: ``reanchor_hold_s`` (s) at most an hour as well.
OWN_RANGES = {"bypass_flow_after_s": (0.0, 3600.0), "motor_sd_after_response_c": (0.0, 10.0),
              "bypass_flow_settle_s": (1.0, 3600.0), "reanchor_hold_s": (0.0, 3600.0),
              "r_supply_rest_c": (0.0, 100.0), "rest_window_s": (1.0, 3600.0), "rest_air_band_c": (0.0, 100.0),
              "rest_log_flow_band": (0.0, 10.0), "rest_offset_band_c": (0.0, 100.0),
              "response_wait_c": (0.0, 10.0), "response_wait_share": (0.01, 1.0), "response_wait_flat_c": (0.0, 10.0),
              "response_wait_rearm_s": (0.0, 3600.0), "q_mix_offset_per_air_change": (0.0, 1.0),
              "q_supply_heat_w": (0.0, 100.0), "supply_heat_sd0_w": (1.0, 1000.0),
              "supply_heat_flow_gate_s": (0.0, 3600.0), "supply_heat_walk_flow_m3h": (0.0, 1000.0),
              "supply_heat_release_hold_s": (0.0, 3600.0), "supply_heat_step_hold_s": (0.0, 3600.0),
              "dead_time_step_longest_s": (0.0, 3600.0), "dead_time_first_settle_s": (0.0, 3600.0),
              "offset_walk_after_temp_step_s": (0.0, 3600.0)}
#: Settings that shape the learning of the bypass-flow exponent and do nothing without ``learn_bypass_flow``
#: (field -> its value that leaves learning as it is).
BYPASS_FLOW_LEARNING_GATES = {"bypass_flow_anchored": False, "bypass_flow_after_response": False,
                              "bypass_flow_after_s": 0.0, "bypass_flow_commit_at_rest": False,
                              "bypass_flow_at_rest": False}
#: Refinements of the longest tied dead time after a change of the reference that do nothing without it
#: (``dead_time_step_longest_s`` > 0; field -> its inert value).
DEAD_TIME_STEP_LONGEST_SHAPES = {"dead_time_step_longest_temp_only": False,
                                 "dead_time_step_longest_reach_moves": False,
                                 "dead_time_step_longest_not_flat": False}
#: Settings that shape the heat flow into the mixed air and do nothing without ``q_supply_heat_w`` (field -> its value
#: that leaves the heat flow as it is).
SUPPLY_HEAT_SHAPES = {"supply_heat_sd0_w": 5.0, "supply_heat_level_neutral": False, "supply_heat_flow_gate_s": 0.0,
                      "supply_heat_release_at_rest": False, "supply_heat_walk_flow_m3h": 0.0,
                      "supply_heat_walk_at_rest": False, "supply_heat_release_hold_s": 0.0,
                      "supply_heat_level_neutral_at_rest": False, "supply_heat_step_hold_s": 0.0,
                      "supply_heat_hold_correlated": False}
#: The heat flow's flow gate (``EkfSettings.supply_heat_flow_gate_s``): the model's flow counts as moving while ln of
#: it is more than this from its running mean over :data:`SUPPLY_HEAT_FLOW_WINDOW_S`. ASSUMPTION: as the rest gate's
#: and the exponent's gate's band (``rest_log_flow_band``, ``bypass_flow_gate``, 0.05: a 5 % change of the flow).
SUPPLY_HEAT_FLOW_BAND = 0.05
#: The running mean's time constant (s) of that gate. ASSUMPTION: as ``bypass_flow_window_s`` (10 s).
SUPPLY_HEAT_FLOW_WINDOW_S = 10.0
#: Largest change of the heater command (W) across a flow step that still counts for the exponent fitted at rest
#: (``EkfSettings.bypass_flow_at_rest``). ASSUMPTION: 50 W move the supply air about 1.7 degC at 90 m3/h, as much as
#: 5-7 percentage points of valve a (about 0.25 degC per point), the valve's bound in the measured setting.
REST_HEATER_TOL_W = 50.0
#: Offsets of the model's air the filter may estimate in place of its parameters: setting (the random walk, 0: not
#: estimated) -> parameter (docs/robustness.md sec. 2.13); the last a heat flow into the mixed air (W, sec. 2.22).
OWN_OFFSETS = (("q_cooler_offset_c", "cooler_outlet_offset_c"), ("q_heater_air_offset_c", "heater_air_offset_c"),
               ("q_supply_heat_w", "supply_heat_w"))
#: Standard deviation (degC) of those offsets at the start. ASSUMPTION: as the heater outlet reading's offset's.
OWN_OFFSET_SD0_C = 1.0
#: No wait for a predicted response (``EkfSettings.response_wait_c``) within this long after the filter starts (s):
#: its own corrections move the model's air then. ASSUMPTION: as ``rest_window_s`` and ``reanchor_hold_s`` (20 s).
RESPONSE_WAIT_AFTER_S = 20.0
#: Measurement names in the order of the filter's measurement vector.
MEASURED = ("supply_temp_c", "volume_flow_m3s", "water_temp_c", "hvac_inlet_temp_c", "heater_outlet_temp_c")


@dataclass(frozen=True)
class EkfSettings:
    """Noise levels of the filter (1 sigma; process noise per sample of 1 s). ASSUMPTIONS tuned on
    the simulated plant; measurement noise matches the plant's sensor-noise parameters.

    ``use_heater_outlet`` uses the heater outlet thermocouple when the measurement carries it.
    ``dead_time_max_s``: longest dead time of the thermocouple beyond the model's that the filter
    estimates and honours (s, whole samples; 0 turns the dead-time handling off);
    ``dead_time_window_s``: the estimate's window (forgetting time, s); ``dead_time_excitation_c``:
    the least root mean square change per sample of the predicted reading over the window for the
    estimate to move (degC); ``dead_time_min_s``: the shortest estimate the measurement model honours (below it
    the thermocouple state's process noise absorbs the delay, as in the plain filter: honouring
    1 s made the 1 s delay's proband sequence worse, 0.91 -> 1.00 of the baseline's IAE);
    ``dead_time_initial_s``: the estimate before the readings move it (a delay identified from a log; at most
    ``dead_time_max_s``). ``dead_time_prior_s``: a dead time honoured from the first sample where neither
    ``dead_time_initial_s`` nor the model's parameters name one, given way (as a starting value) only to a
    candidate that explains a response clearly better (0: none, the default). 1.5 s, the shortest honoured,
    took the quick mismatch suite's flow-out-of-reach cell of ``combo_delay_loss_cooler`` from 1.10 to 0.80 of
    the baseline's IAE (nothing there excites the estimate, and the dead time not honoured turns the sensor
    noise into ringing), but the built-in plant's quick ``flow_split_changes`` (no delay, no temperature step)
    from 0.78 to 1.08: not a default (docs/robustness.md sec. 2.4). Module docstring; ASSUMPTIONS tuned on the
    independent simulator's variants. ``dead_time_lead_reach_s``: a candidate ahead of the estimate continues the
    lead's count (:data:`~.dead_time.LEAD_SAMPLES` samples in a row switch the estimate) while it moves by at most
    this from one sample to the next (s in [0, ``dead_time_max_s``]; 0: only the same candidate, as before; 0.5 at
    1 s samples: the neighbouring half sample of the same minimum, which otherwise restarts the count; the default
    since 28 November 2026, docs/robustness.md sec. 2.38, 2.39). ``dead_time_lead_count_quiet``: samples whose
    window holds too little response to rank the candidates (below ``dead_time_excitation_c``) count for a candidate that stands ahead, instead of neither
    counting nor breaking the row; the switch still waits for a ranked sample with it ahead (the default; sec. 2.38).
    ASSUMPTION: nothing in a quiet window argues against the lead it left standing. ``dead_time_lead_tie_hold``: a
    dead time the lead rule switched to gives way only to a clearly better candidate, another lead, or a tie within
    ``dead_time_lead_reach_s`` (the same minimum's bottom), not to a shorter tie farther away (the tie rule took a
    lead's 3.5 s back to 0 s within 4 s on a flat ranking; the default; sec. 2.38). ``dead_time_step_longest_s``:
    for this long (s, in [0, 3600]; 0: off, the default) after a change of the reference (:meth:`note_reference`),
    of separate minima of the ranking within :data:`~.dead_time.TIE_RATIO` the longest is taken where it is longer
    than the estimate (instead of the shortest); within that time no shorter tie moves it down, after it it is held
    against a shorter tie beyond ``dead_time_lead_reach_s`` only with ``dead_time_lead_tie_hold`` (as a lead-made
    estimate; it leaves a starting value's hold). The reference compared exactly: a ramped reference re-arms it every
    step (docs/robustness.md sec. 2.46). ``dead_time_first_settle_s``: for this long (s, in [0, 3600]; 0: off, the
    default) of ranked samples after the estimate's first ranked one (the window's first response), the least
    residual's minimum (of separate tied minima the shortest, as the tie rule) is taken wherever its residual is below
    the estimate's, longer or shorter; then the switch, tie and lead rules as before. A starting value
    (``dead_time_initial_s``, ``dead_time_prior_s``) is not moved by it. ASSUMPTION: the first ranked samples hold a
    response's onset only, on which a shorter dead time than the box's can rank clearly best (the box's sensor lag and
    gains shape an onset); measured with 15 s, about 2.6 of the model's thermocouple lag (10 s gives S1-8 the same
    figure), not tuned (docs/robustness.md sec. 2.47). The count includes the first ranked sample: 15 s settles the
    2nd to the 15th. While the longest tied dead time's window is open (``dead_time_step_longest_s``) it does not
    settle: that window's rule governs there. ``dead_time_step_longest_temp_only``: that window opens only at a change
    of the supply air's reference (degC), not at a step of the flow's alone (off, the default: at either; a flow
    step's answer has a part without the transport delay, the duct's loss and the blower's own heat moving with the
    flow now, and the ranking after it is flat: on S0-6's flow jump the longest tie took 6.0 s for a 1.34 s box, sec.
    2.48). ``dead_time_step_longest_reach_moves``: within that window a shorter tie within ``dead_time_lead_reach_s``
    of the estimate (its minimum's bottom) moves it as outside the window (off, the default: no shorter tie moves it
    down there; on S0-8's cooling 3.0 s was held against 2.5 s, sec. 2.48). ``dead_time_step_longest_not_flat``: within
    that window the longest tie is taken only from a ranking that is not flat, some candidate's residual above
    :data:`~.dead_time.TIE_RATIO` times the least (off, the default: from any ranking). ASSUMPTION: where every
    candidate explains the reading equally the ranking holds no response, and its separate minima are the reading's
    noise (on the built-in chiller step the window's first ranking, made at rest before the step, put 6.0 s, the last
    candidate, in use for one sample, every residual within 0.1-0.2 % of the least: chiller 0.4297 -> 0.4802, sec. 2.50).
    The three refinements are refused unless ``dead_time_step_longest_s`` > 0 (they do nothing without it).

    ``q_mix_offset_c``: random walk (degC per sample) of the mixed-air offset. 0.015 (0.03 before): with
    the faster valve and the reading-heavy tracked temperature (``OcpSpec``) the offset's sample-to-sample
    noise fed a limit cycle where a dead time had not been seen yet (quick mismatch suite, flow out of reach
    on ``combo_delay_loss_cooler``: 1.95 of the baseline's IAE at 0.03, 0.92 at 0.015; docs/robustness.md
    sec. 2.3).

    ``q_mix_offset_unseen_c``: the mixed-air offset's random walk (degC per sample) while the dead-time estimate
    has seen no response (:attr:`~.dead_time.DeadTimeEstimator.informed`; with the dead-time handling on), in
    place of ``q_mix_offset_c`` (0: no difference, the default). Where no response has shown the dead time the
    filter cannot honour it, and the offset's walk is what turns the sensor noise into ringing
    (docs/robustness.md sec. 2.4, 2.8).

    ``q_mix_offset_per_log_flow_c``: more variance for the mixed-air offset at a change of the model's flow,
    (this times the change of ln of the flow)^2 degC^2 in the time update where the flow changed (0: none, the
    default): a box whose supply air depends on the flow as the model's does not (a duct loss shrinking with the
    flow, a cooler's effectiveness) shows a step of the offset at a flow step, which a random walk of the rate
    at rest takes tens of seconds to follow; only once the dead-time estimate has seen a response (before, the
    raised variance took the MPC's own late answer: combo_delay_loss_cooler 1.10 -> 1.45 of the baseline's IAE
    with the flow out of reach; docs/robustness.md sec. 2.8). ``q_mix_offset_flow_deadband``: the part
    of that change (in ln, per sample) that adds nothing (the MPC's own small flow moves; 0: none).

    ``q_mix_offset_per_air_change`` (share, in [0, 1]): more variance for the mixed-air offset where the model's
    mixed air moves, (this times the change of the model's mixed air in the sample)^2 degC^2 (0: none, the
    default): a box whose valve curves or gains differ from the model's answers a move by a share more or less than
    the model predicts, so the offset has to step by that share of the move, which its random walk follows slowly.
    Only once the dead-time estimate has seen a response, as the flow's. ASSUMPTION: the share is the model's gain
    uncertainty (0.1: a tenth of a predicted change may be wrong). A setting, off (docs/robustness.md sec. 2.20).

    ``q_supply_heat_w``: random walk (W per sample) of a heat flow into the mixed air on its way to the thermocouple,
    the filter's own value of ``Parameters.supply_heat_w`` (0: none, the default; in [0, 100]), beside the mixed-air
    offset: its effect on the air is the heat over the model's mass flow times c_p (the flow held at least at the
    blower's least, :func:`~hvac_mpc.models.blower.least_mass_flow_kgs`), so a constant heat gain (a duct's from the
    cabin, a loss on the heater's side) gives the right offset at every flow without the estimate moving, where an
    offset in degC has to step at each flow change. At a steady flow the two are one to the readings; a flow change
    tells them apart. The prediction takes the estimate (:meth:`DisturbanceEkf.model_parameters`), so the MPC
    predicts a planned flow change with it. The heat is held at the parameter's value (no variance, no walk) until
    the dead-time estimate has seen a response and a dead time is honoured, or ``dead_time_window_s`` after the first
    response where none is (:meth:`DisturbanceEkf._release_heat`: before, a late response looks like a heat).
    ``supply_heat_sd0_w``: its standard deviation when released (W, in [1, 1000]). ``supply_heat_level_neutral``:
    its variance (release and walk) along the direction that leaves the air at the flow in force as it is, the
    offset taking minus the heat's effect, so at a steady flow the filter's level walks as the plain one's (off: the
    heat's walk adds to the level's). ASSUMPTIONS: the heat does not depend on the air's temperature (a duct's gain
    UA (T_cabin - T_air) does; the mixed-air offset takes that part); 5 W at the release (0.2 degC at 90 m3/h).
    A setting, off: measured with 2 W per sample in docs/robustness.md sec. 2.22; at a steady flow the heat's walk
    adds to the level's, and 2 W (0.055 degC per sample at 120 m3/h, nearly four times the offset's walk) passes the
    reading's noise on (the built-in plant's cool-down 0.457 -> 0.474 of the baseline's IAE); 0.5 W, the offset's
    walk at 90 m3/h, keeps the gain at the flow steps without that cost (sec. 2.29).
    ``supply_heat_release_at_rest``: the release waits, beyond the dead time, for the first settled period after the
    first response (:mod:`~.rest_gate`, the gate ``r_supply_rest_c`` uses, built for it where that is 0: a whole
    ``rest_window_s`` with the model's air, flow and the offset still), so what the start-up's transient and the first moves leave (a late
    response, valve a's answer of the other sign the placement must see) goes to the offset alone, as in the filter
    without the heat (docs/robustness.md sec. 2.31). ``supply_heat_flow_gate_s`` (s, in [0, 3600]; 0: none): once
    released, the heat takes the readings and walks only within this long after ln of the model's flow left its
    running mean over :data:`SUPPLY_HEAT_FLOW_WINDOW_S` by more than :data:`SUPPLY_HEAT_FLOW_BAND`; held otherwise
    (:attr:`DisturbanceEkf.heat_held`): at a steady flow the heat and the offset are one to the readings, and the
    offset alone takes the level. Both settings, off: measured in docs/robustness.md sec. 2.31 (with 0.5 W the release
    at rest keeps S0-7's placement switch and the full built-in bench below today's in every scenario; the flow gate
    costs that bench four scenarios).
    Five shapes of the heat's walk and release, all off (docs/robustness.md sec. 2.35; with
    ``supply_heat_release_at_rest``, the release hold at 10 s, the level-neutral walk at rest on and the step hold at
    10 s, the candidate measured there):
    ``supply_heat_walk_flow_m3h`` (m3/h, in
    [0, 1000]; 0: none): below this model flow the walk is scaled with the mass flow, ``q_supply_heat_w`` times
    (m_dot c_p) over its value at this flow, so its effect on the air per sample stays that of ``q_supply_heat_w``
    at this flow (at a low flow 0.5 W moves the air most: 0.037 degC at 40 m3/h against the offset's walk of 0.015,
    sec. 2.33); above it the walk is ``q_supply_heat_w``. ``supply_heat_walk_at_rest``: the walk is added only while
    the rest gate is at rest, frozen in every transient (a step, a flow change, the heater body's creep), whose error
    the offset's walk and the heat's variance already take. ``supply_heat_release_hold_s`` (s, in [0, 3600]; 0:
    none): no release within this long of a change of the reference (:meth:`DisturbanceEkf.note_reference`, the
    controller's supply-air and total-flow references; a change of the outlet split alone does not count): a release
    within this long after one waits, and one a change follows within this long is taken back (the heat back to the
    parameter's value, the offset taking its effect at the flow in force, so the air is as it was; its variance 0)
    and waits for the next settled period: a heat released just before a step takes the
    step's transient with its whole release variance (the literal-cooler box's trapped-air run, sec. 2.33).
    ``supply_heat_level_neutral_at_rest``: the heat's walk level-neutral, as with ``supply_heat_level_neutral``, only
    while the rest gate is at rest; its release variance as without it: at rest the level walks at the offset's rate
    (the heat's walk passed the reading's noise into it there, sec. 2.33), in a transient the heat's walk adds to it
    (a release level-neutral as well took S0-3's quick proband 0.974 -> 1.019 of the baseline's IAE, sec. 2.35).
    ``supply_heat_step_hold_s`` (s, in [0, 3600]; 0: none): the released heat held
    (:attr:`DisturbanceEkf.heat_held`: out of the measurement update, no walk) within this long after a change of the
    reference, whose first seconds are the model's own answer to the step, the offset's to take (the built-in trapped
    air's step down: the heater air's filter's heat -53 W within 7 s of the step without it, sec. 2.35). ASSUMPTION
    for both holds: a step's first answer is over in about 10 s (a hold of 20 s lost the trapped air's gain, sec. 2.35).
    ``supply_heat_hold_correlated`` (needs a hold: ``supply_heat_step_hold_s`` or ``supply_heat_flow_gate_s``): the
    held heat taken out of the update as a known value, its correlations kept (:meth:`DisturbanceEkf._hide_heat`: the
    other states conditioned on it, then its variance and covariances put back along the same regression), where
    without it the correlations are dropped: the level-neutral walk's share of the offset's variance (the walk's
    variance times the heat's effect squared, held level-neutral by the correlation) then acts on the offset alone
    for the hold's seconds, and the heat comes back from the hold with its variance uncorrelated, free to take the
    step's transient (the literal-cooler box, docs/robustness.md sec. 2.42). A setting, off: with F it takes the
    plain-start literal-cooler compare over four noise seeds 0.9949 -> 0.9901, but F's gains on the built-in bench go
    with it (winter 0.6014 -> 0.6944, flow split 0.4387 -> 0.4795), which come from that loose hold.

    ``q_heater_outlet_offset_c``: random walk (degC per sample) of an offset of the heater outlet
    reading, its own integrating disturbance (0: none). Without it a persistent error of that reading
    (a cooler core whose outlet differs from the model's) biases the mixed-air offset and so the supply
    temperature at rest (0.03 degC on the independent box's ``cooler_literal`` with the flow out of
    reach); with it every measured output has its integrator and the filter stays offset-free.

    ``q_cooler_offset_c``: random walk (degC per sample) of an offset of the air leaving the cooler core, the
    filter's own value of ``Parameters.cooler_outlet_offset_c`` (0: none, the model's parameter as it is). It
    passes through the heater branch and the bypass with the model's own mixing, so its effect on the supply air
    depends on valve a, which an offset added to the mixed air cannot carry: a box whose core leaves the air warmer
    than the model's whatever the inlet (the thesis cooler fit taken literally, about 10 degC in winter) has a
    valve a gain several times the model's in heating, and the mixed-air offset swung 0 -> 4.5 degC with each
    stroke of a ringing loop. The prediction takes the estimate (:meth:`DisturbanceEkf.model_parameters`).
    Observability (ASSUMPTION): the heater outlet reading tells it directly (with ``q_heater_outlet_offset_c`` 0
    that reading has no offset of its own); without that reading only valve a's moves tell it from the mixed-air
    offset, and at rest it keeps its value. Off by default: it costs the built-in plant's quick warm-up, cool-down
    and proband (0.423 -> 0.638, 0.701 -> 0.728, 0.520 -> 0.532 of the baseline's IAE). docs/robustness.md sec. 2.13.

    ``q_heater_air_offset_c``: the same for an offset of the air leaving the heater as it mixes and is read (the
    heater body sees the model's air), the filter's own value of ``Parameters.heater_air_offset_c`` (0: none). The
    heater outlet reading sees exactly this air, so it tells the offset at any valve position, whether the error is
    the core's or the heater's; with ``q_heater_outlet_offset_c`` 0 (the reading without an offset of its own)
    valve a's gain in the prediction is the box's at the operating point. Off by default: it costs the built-in
    plant's warm-up (quick ``cabin_warmup_winter`` 0.42 -> 0.64 of the baseline's IAE), where the error at the heater
    outlet is the heater's transfer coefficient, which an offset carries at one core flow only
    (docs/robustness.md sec. 2.13). ``MpcSettings.choose_offset_placement`` (on) runs a second filter with it beside
    this one and chooses between them online (sec. 2.14).

    ``initial_sd_motor_c``: standard deviation (degC) of the motor rise at the start, where the filter puts it
    at the rest state of the command in force. Nothing but the model tells it from the mixed-air offset (both
    move the supply air alike), so a start-up transient the model misses (a dead time not yet found) moved it
    as far as its uncertainty allowed: 0.5 (the default) let it go from +0.7 to -1.1 degC (the box's rise 0.7)
    in 15 s, and its slow return to its target (268 s lag) then fed the offset a ramp: a steady error with the
    flow out of reach. 0.1 (ASSUMPTION: the motor lag, minutes, is near rest when the controller starts) helps
    the independent box's flow-out-of-reach cells but costs the built-in plant's quick summer_cooling_steps
    (0.48 -> 0.51 of the baseline's IAE), so it is not the default (docs/robustness.md sec. 2.6).

    ``bound_motor_rise``: hold the motor rise within what the motor can give, [0, ``Parameters.motor_gain_max_c``],
    after each measurement update (:meth:`DisturbanceEkf.bound_state`). Nothing but the model tells it from the
    mixed-air offset, and a start-up transient the model misses (a dead time not yet found) pushed it to -2.5 degC
    (the box's +0.9) on a box with a 4 s dead time; its slow return (the motor's 268 s lag) then fed the offset a
    ramp, a steady error after a flow change (docs/robustness.md sec. 2.8). On by default (sec. 2.11): on boxes
    outside the suite's registry (a 4.5 s dead time with the literal cooler fit, a weak blower behind 3.5 s) the
    unbounded filter ran the rise to -28 degC against a +22 degC offset while the dead time was not yet found, and
    the MPC rang between the valve's ends (up to 23 times the baseline's IAE).

    ``bypass_flow_exponent_prior``: the exponent of the bypass split's flow dependence the filter
    and the MPC's prediction use where the model carries the ``bypass_flow`` effect (0 = the thesis
    model, which leaves the dependence out), in place of ``Parameters.bypass_flow_exponent``.
    ``learn_bypass_flow`` (off by default: measured worse on the delayed mismatch variants,
    docs/robustness.md sec. 1): estimate it (module docstring), starting from the prior with standard
    deviation ``bypass_flow_exponent_sd``, random walk ``q_bypass_flow_exponent`` per sample;
    ``bypass_flow_gate`` the least |ln(flow / running mean of the flow)| for it to be learned,
    ``bypass_flow_window_s`` that running mean's time constant (s). ASSUMPTIONS.

    ``bypass_flow_anchored`` (with ``learn_bypass_flow``): the split's reference mass flow
    (``Parameters.bypass_ref_mass_flow_kgs``) is a state of the filter that follows the model's mass flow
    with the time constant ``bypass_flow_window_s``, the mixed-air offset taking the change of the model's
    mixed air as it moves (module docstring). At the flow in force the exponent then does not move the
    model's air at all: it is told only by a flow that differs from the recent one, and learning it cannot
    step the prediction; the MPC predicts a planned flow change with it. ``bypass_flow_exponent_min`` /
    ``_max``: the range the estimate is held in (the prior within it). ``bypass_flow_after_response``: learn
    only once the dead-time estimate has seen a response (:attr:`~.dead_time.DeadTimeEstimator.informed`;
    always with the dead-time handling off). ``motor_sd_after_response_c``: once a response is seen, the
    motor rise's standard deviation is raised to this (degC in [0, 10], the largest motor rise the parameters
    allow; 0: never), for ``initial_sd_motor_c`` small until the timing of a response is known; it acts with or
    without the learning. ``bypass_flow_after_s``: no learning in the first seconds after
    :meth:`~DisturbanceEkf.initialise` (the filter's own start-up; s in [0, 3600]). ``bypass_flow_commit_at_rest``:
    the parameters handed to the prediction (:meth:`~DisturbanceEkf.model_parameters`) take the learned exponent
    only while it is not being learned, so a flow change is predicted with the value from before it, never a
    half-learned one. ``bypass_flow_anchored``, ``bypass_flow_after_response``, ``bypass_flow_after_s``,
    ``bypass_flow_commit_at_rest`` and ``bypass_flow_at_rest`` shape the learning: set without
    ``learn_bypass_flow`` they are an error (:meth:`validate`). ``bypass_flow_exponent_min`` <
    ``bypass_flow_exponent_max``, both in [-3, 3]. docs/robustness.md sec. 2.7.

    ``bypass_flow_at_rest`` (with ``bypass_flow_anchored``): the filter never learns the exponent itself; it is
    fitted outside the filter from the change of the mixed-air offset across each flow step once the flow has
    rested ``bypass_flow_settle_s`` again (s in [1, 3600]; a step: the model's mass flow more than
    ``bypass_flow_gate`` in log from the last rest's), a least-squares fit with the prior
    (``bypass_flow_exponent_sd``) against the offset's noise at rest ``bypass_flow_rest_noise_c`` (degC):
    :mod:`~.flow_term`. The gates ``bypass_flow_after_response`` and ``bypass_flow_after_s`` hold back the rests
    that count; a step across which valve a moved more than ``bypass_flow_rest_valve_pct`` (percentage points) or
    the heater more than :data:`REST_HEATER_TOL_W` does not count (the offset's change then holds the model's valve
    and heater errors too: on the suite's boxes the proband sequence's steps, which move the flow with the
    temperature, taught a wrong exponent, delay_3s proband 0.77 -> 1.06 of the baseline's IAE). ASSUMPTIONS (20 s,
    0.05 degC, 100: no valve bound). docs/robustness.md sec. 2.8.

    ``reanchor_states``: model states (of :data:`~.reanchor.REANCHORABLE`: the motor rise, the heater body, the
    trapped air) run open loop beside the filter from its start (an open-loop shadow) and, from the first sample a
    dead time is honoured until ``reanchor_hold_s`` (s in [0, 3600]) after the honoured dead time last changed,
    held at that open-loop value every sample, the mixed-air offset (and the heater outlet reading's offset)
    taking the change of the model's air, the covariance mapped alike (() : none). While held the mixed-air offset
    walks at ``reanchor_hold_q_mix_c`` (degC per sample; 0: ``q_mix_offset_c``): what it took while the dead time
    was not honoured was a late response compared too early. ``reanchor_before_response`` (off by default: it costs the
    built-in plant, whose perturbed motor gain the motor rise then cannot take before the first response): hold
    them from the start as well, until ``reanchor_hold_s`` after the dead-time estimate first saw a response. What
    a late response put into the states then sits in the offset, which the readings see, instead of unwinding with
    the motor's 268 s lag. Without a dead time honoured (and without ``reanchor_before_response``) the filter is
    the plain one. Defaults: the motor rise and the heater body, 20 s, 0.05 degC per sample (ASSUMPTIONS: 20 s is
    the longest dead time, 6 s, and about two and a half thermocouple lags; the states' physics is nearer the box
    than what a late response made of them): on the quick mismatch suite's flow-out-of-reach column (seeds 0-4)
    cells above 1.0 1 / 8 / 2 / 2 / 4 -> 1 / 6 / 1 / 0 / 5 (the worst at or below the base's on every seed), on four
    boxes not in the suite 6 -> 1 of 12, the full suite's worst cell 1.03 -> 1.01, the built-in bench unchanged
    (:mod:`~.reanchor`; docs/robustness.md sec. 2.9).
    ``offset_walk_after_temp_step_s`` (s in [0, 3600]; 0: off, the default): for this long after a change of the
    supply air's reference (degC; :meth:`DisturbanceEkf.note_reference`'s first value), with a dead time honoured,
    the mixed-air offset walks at ``reanchor_hold_q_mix_c`` as in the re-anchor hold, without re-anchoring the
    states. The hold starts only at a change of the honoured dead time, so a step's model error was learnt at the
    hold's walk where the step's response also moved the estimate and at the plain walk where the estimate was
    already right (box S1-5 of the seeded sweep's proband sequence: the offset 0.95 against 1.47 degC 29 s after a
    step, docs/robustness.md sec. 2.49). ASSUMPTION: a temperature step's answer shows the model's gain error there
    as the offset's change within about the hold's 20 s (measured with 20 s, not tuned).

    ``r_supply_rest_c``: the supply reading's standard deviation (degC) the measurement update assumes while the
    filter is at rest (:class:`~.rest_gate.RestGate`; 0: ``r_supply_c`` always, the plain filter). At rest the
    model's error is a constant the offset has taken, and what moves the reading is its noise, which the filter's
    gain sized for transients passes on to the commands: with the flow out of reach on the independent box most of
    both controllers' IAE is that noise (docs/robustness.md sec. 2.10). A larger value there gives the gains of a
    process noise (``r_supply_c`` / ``r_supply_rest_c``)^2 times smaller; off rest the filter weighs the reading as
    the plain one does (its covariance, grown while the reading weighed less, gives the first gains of a
    transient about the plain filter's). Rest: over the last ``rest_window_s`` (s in [1, 3600]) the model's air at
    the thermocouple moved at most ``rest_air_band_c`` (degC, the mean of the window's last quarter against its
    first), ln of its volume flow stayed within ``rest_log_flow_band`` and the mixed-air offset's net change was at
    most ``rest_offset_band_c`` (degC; a model error that still drifts is not rest). Defaults 0.1 degC, 20 s, 0.2 degC,
    0.05, 0.07 degC. ASSUMPTIONS: twice the box's noise (0.05 degC); three and a half thermocouple lags; the MPC's own
    moves at rest (0.05-0.15 degC per sample of the model's air) average out within 0.2 degC while a step or the
    heater body's creep does not; the gate of the bypass-flow fit; about twice the offset's noise wander at rest.
    Measured (sec. 2.10): the quick mismatch suite's flow-out-of-reach column, seeds 0-4, and the unlisted boxes
    improve on every seed, the built-in bench within 0.005 of before in every scenario.

    ``response_wait_c``: leave the supply reading out of the measurement update while a response the model predicts
    is still to show (degC in [0, 10]; 0: never; 0.2 the default, docs/robustness.md sec. 2.18): a wait starts at a sample whose prediction of the
    reading at the dead time honoured (the model's air without the offset, through the thermocouple lag) changed by at
    least this while the reading changed by less than ``response_wait_share`` (in [0.01, 1]) of it (not within the
    filter's first ``RESPONSE_WAIT_AFTER_S``), and ends when the honoured dead time moves, at once where the reading
    followed within ``dead_time_min_s``, else as long again after the response began; at once where the reading moves
    against the prediction or stays put longer than ``dead_time_max_s`` (a model error, not a dead time;
    :mod:`~.response_wait`). Where the box has a dead time nothing has shown yet, the plain update takes the missing
    response of a large move for a model error and the MPC overshoots when it arrives (the full mismatch suite's
    worst cells, a temperature step with the flow
    out of reach). ``response_wait_flat_c`` (degC in [0, 10]; 0: no bound): a wait begins only where the reading's
    change in that sample is at most this as well (a reading that stays put; a response smaller than the model's
    starts none). ASSUMPTIONS: 0.2 degC, four times the reading's noise; 0.5. docs/robustness.md sec. 2.17.
    ``response_wait_rearm_s`` (s in [0, 3600]; 0: none): after a wait that ended as a model error (the reading moved
    against the prediction or stayed put longer than any dead time), no wait begins for this long: the model's error
    for a move of its own is a gain the next move shares, not a dead time. Default 60 s. ASSUMPTION: a valve or
    heater gain error lasts at least the dead-time estimate's window (``dead_time_window_s``, 60 s), over which that
    estimate ranks the same responses (docs/robustness.md sec. 2.19).
    ``response_wait_unseen_only``: no wait once the dead-time estimate has seen a response and a dead time is honoured
    (default on, docs/robustness.md sec. 2.21: the built-in bench and the quick mismatch suite on seeds 0, 3 and 4
    give the same figures with it; ``False`` waits at every predicted move, as before). A wait is for a dead time the filter does not know;
    once a response has shown it and the reading is compared at it, a reading that does not follow a move of the
    model's is the model's error (a valve gain, a duct's loss that changes with the flow), which the offsets have to
    take now: on boxes of the seeded sweep a wait at each reference step held the offset 7-10 samples while the
    reading sat 0.6-1 degC off the reference. ASSUMPTION: the dead time found from a response is the box's (a longer
    one would show as a model error until the estimate moves to it).
    """

    q_motor_c: float = 0.01
    initial_sd_motor_c: float = 0.5
    bound_motor_rise: bool = True
    motor_sd_after_response_c: float = 0.0
    q_water_c: float = 0.01
    q_heater_c: float = 0.1
    q_sensor_c: float = 0.02
    q_trap_c: float = 0.1
    q_mix_offset_c: float = 0.015
    q_mix_offset_unseen_c: float = 0.0
    q_mix_offset_per_log_flow_c: float = 0.0
    q_mix_offset_flow_deadband: float = 0.0
    q_mix_offset_per_air_change: float = 0.0
    q_supply_heat_w: float = 0.0
    supply_heat_sd0_w: float = 5.0
    supply_heat_level_neutral: bool = False
    supply_heat_flow_gate_s: float = 0.0
    supply_heat_release_at_rest: bool = False
    supply_heat_walk_flow_m3h: float = 0.0
    supply_heat_walk_at_rest: bool = False
    supply_heat_release_hold_s: float = 0.0
    supply_heat_level_neutral_at_rest: bool = False
    supply_heat_step_hold_s: float = 0.0
    supply_heat_hold_correlated: bool = False
    q_flow_offset_m3s: float = 3e-5
    q_inlet_c: float = 0.01
    r_supply_c: float = 0.05
    r_flow_m3s: float = 4e-4
    r_water_c: float = 0.05
    r_inlet_c: float = 0.05
    r_heater_outlet_c: float = 0.2
    use_heater_outlet: bool = True
    dead_time_max_s: float = 6.0
    dead_time_window_s: float = 60.0
    dead_time_excitation_c: float = 0.05
    dead_time_min_s: float = 1.5
    dead_time_initial_s: float = 0.0
    dead_time_prior_s: float = 0.0
    dead_time_lead_reach_s: float = 0.5
    dead_time_lead_count_quiet: bool = True
    dead_time_lead_tie_hold: bool = True
    dead_time_step_longest_s: float = 0.0
    dead_time_first_settle_s: float = 0.0
    dead_time_step_longest_temp_only: bool = False
    dead_time_step_longest_reach_moves: bool = False
    dead_time_step_longest_not_flat: bool = False
    q_heater_outlet_offset_c: float = 0.01
    q_cooler_offset_c: float = 0.0
    q_heater_air_offset_c: float = 0.0
    learn_bypass_flow: bool = False
    bypass_flow_exponent_prior: float = 0.0
    bypass_flow_exponent_sd: float = 0.1
    q_bypass_flow_exponent: float = 1e-3
    bypass_flow_gate: float = 0.05
    bypass_flow_window_s: float = 10.0
    bypass_flow_anchored: bool = False
    bypass_flow_after_response: bool = False
    bypass_flow_after_s: float = 0.0
    bypass_flow_commit_at_rest: bool = False
    bypass_flow_exponent_min: float = -3.0
    bypass_flow_exponent_max: float = 3.0
    bypass_flow_at_rest: bool = False
    bypass_flow_settle_s: float = 20.0
    bypass_flow_rest_noise_c: float = 0.05
    bypass_flow_rest_valve_pct: float = 100.0
    reanchor_states: tuple[str, ...] = ("motor_rise_c", "heater_temp_c")
    reanchor_hold_s: float = 20.0
    reanchor_before_response: bool = False
    reanchor_hold_q_mix_c: float = 0.05
    offset_walk_after_temp_step_s: float = 0.0
    r_supply_rest_c: float = 0.1
    rest_window_s: float = 20.0
    rest_air_band_c: float = 0.2
    rest_log_flow_band: float = 0.05
    rest_offset_band_c: float = 0.07
    response_wait_c: float = 0.2
    response_wait_share: float = 0.5
    response_wait_flat_c: float = 0.0
    response_wait_rearm_s: float = 60.0
    response_wait_unseen_only: bool = True

    def validate(self, prefix: str = "ekf") -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "reanchor_states":
                check_state_names(f"{prefix}.{f.name}", value)
                continue
            if f.name in ("use_heater_outlet", "learn_bypass_flow", "bypass_flow_anchored", "bound_motor_rise",
                          "reanchor_before_response", "response_wait_unseen_only", "supply_heat_level_neutral",
                          "supply_heat_release_at_rest", "supply_heat_walk_at_rest",
                          "supply_heat_level_neutral_at_rest", "supply_heat_hold_correlated",
                          "bypass_flow_after_response", "bypass_flow_commit_at_rest", "bypass_flow_at_rest",
                          "dead_time_lead_count_quiet", "dead_time_lead_tie_hold",
                          "dead_time_step_longest_temp_only", "dead_time_step_longest_reach_moves",
                          "dead_time_step_longest_not_flat"):
                check_flag(f"{prefix}.{f.name}", value)
                continue
            if f.name in ("bypass_flow_exponent_prior", "bypass_flow_exponent_min", "bypass_flow_exponent_max"):
                check_number(f"{prefix}.{f.name}", value, *BYPASS_FLOW_EXPONENT_RANGE)
                continue
            if f.name in ("dead_time_max_s", "dead_time_min_s", "dead_time_prior_s", "q_heater_outlet_offset_c",
                          "q_mix_offset_unseen_c", "q_mix_offset_per_log_flow_c", "q_mix_offset_flow_deadband",
                          "reanchor_hold_q_mix_c", "q_cooler_offset_c", "q_heater_air_offset_c"):
                check_number(f"{prefix}.{f.name}", value, 0.0, 30.0)
                continue
            if f.name in OWN_RANGES:
                check_number(f"{prefix}.{f.name}", value, *OWN_RANGES[f.name])
                continue
            if f.name in ("dead_time_initial_s", "dead_time_lead_reach_s"):
                check_number(f"{prefix}.{f.name}", value, 0.0, float(self.dead_time_max_s))
                continue
            check_number(f"{prefix}.{f.name}", value, 0.0, 100.0 if f.name != "dead_time_window_s" else 3600.0,
                         lo_open=True)
        self._validate_bypass_flow(prefix)
        self._validate_supply_heat(prefix)
        if self.dead_time_step_longest_s <= 0.0:
            self._refuse_inert(prefix, DEAD_TIME_STEP_LONGEST_SHAPES,
                               "the longest tied dead time after a change of the reference",
                               f"{prefix}.dead_time_step_longest_s > 0")

    def _validate_supply_heat(self, prefix: str) -> None:
        """The heat flow's shape settings only with the heat flow on (``q_supply_heat_w`` > 0)."""
        if self.q_supply_heat_w <= 0.0:
            self._refuse_inert(prefix, SUPPLY_HEAT_SHAPES, "the heat flow into the mixed air",
                               f"{prefix}.q_supply_heat_w > 0")
        elif self.supply_heat_hold_correlated and not (self.supply_heat_step_hold_s > 0.0
                                                       or self.supply_heat_flow_gate_s > 0.0):
            raise InvalidSettings(f"{prefix}.supply_heat_hold_correlated = True shapes the heat flow's hold and needs "
                                  f"{prefix}.supply_heat_step_hold_s > 0 or {prefix}.supply_heat_flow_gate_s > 0 "
                                  f"(else leave it at False)")

    def _refuse_inert(self, prefix: str, gates: Mapping[str, Any], what: str, needs: str) -> None:
        """Refuse a setting of ``gates`` (field -> its inert value) moved off its inert value while the setting it
        shapes (``what``) is off (``needs``: what turns it on), naming the field."""
        for name, inert in gates.items():
            value = getattr(self, name)
            if value != inert:
                raise InvalidSettings(f"{prefix}.{name} = {value!r} shapes {what} and needs {needs} (else leave it "
                                      f"at {inert!r})")

    def _validate_bypass_flow(self, prefix: str) -> None:
        """The exponent's range before the prior within it; the learning's gates only with the learning."""
        if not self.bypass_flow_exponent_min < self.bypass_flow_exponent_max:
            raise InvalidSettings(f"{prefix}.bypass_flow_exponent_min must be less than "
                                  f"{prefix}.bypass_flow_exponent_max; got {self.bypass_flow_exponent_min} and "
                                  f"{self.bypass_flow_exponent_max}")
        if not self.bypass_flow_exponent_min <= self.bypass_flow_exponent_prior <= self.bypass_flow_exponent_max:
            raise InvalidSettings(f"{prefix}.bypass_flow_exponent_prior must lie within [{prefix}.bypass_flow_exponent_min, "
                                  f"{prefix}.bypass_flow_exponent_max] ({self.bypass_flow_exponent_min}, "
                                  f"{self.bypass_flow_exponent_max}); got {self.bypass_flow_exponent_prior}")
        if self.learn_bypass_flow and self.bypass_flow_at_rest and not self.bypass_flow_anchored:
            raise InvalidSettings(f"{prefix}.bypass_flow_at_rest = True needs {prefix}.bypass_flow_anchored = True "
                                  "(the offset takes a flow step's whole change only with the split anchored)")
        if not self.learn_bypass_flow:
            self._refuse_inert(prefix, BYPASS_FLOW_LEARNING_GATES, "the learning of the bypass-flow exponent",
                               f"{prefix}.learn_bypass_flow = True")


class DisturbanceEkf:
    """EKF for the HVAC box; ``predict(u)`` after applying a command, ``update(measurement)`` on arrival."""

    def __init__(self, model: HvacModel, settings: EkfSettings | None = None, dt_s: float = 1.0,
                 water_prediction: str = "hold", learn_bypass_flow: bool = True, name: str = "ekf"):
        """``learn_bypass_flow``: False keeps the model's bypass-flow exponent fixed whatever the
        settings say (for a prediction that cannot take a changed parameter). ``name``: the prefix of the time and
        measurement updates' function names (``NAME_predict``, ``NAME_update``; generated code is cached by them),
        for two filters of one controller."""
        self.model = model
        self.name = str(name)
        self.settings = s = settings or EkfSettings()
        self.dt_s = float(dt_s)
        self.hold_water = water_prediction == "hold"
        self.nx = len(model.states)
        self.i_exponent_p = model.param_names.index("bypass_flow_exponent")
        # the filter's own bypass-flow exponent (the prior, learned if so set) where the model has the effect
        self.adapts_bypass_flow = bool(learn_bypass_flow and "bypass_flow" in model.effects)
        self.learns_bypass_flow = self.adapts_bypass_flow and s.learn_bypass_flow
        # ... with its reference mass flow a state following the flow (EkfSettings.bypass_flow_anchored)
        self.anchors_bypass_flow = self.learns_bypass_flow and s.bypass_flow_anchored
        self.i_ref_p = model.param_names.index("bypass_ref_mass_flow_kgs")
        # model states, disturbance states and, when learned, the bypass-flow exponent
        # ... and the heater outlet reading's own offset (an integrating disturbance per measured output)
        self.has_outlet_offset = bool(s.use_heater_outlet and s.q_heater_outlet_offset_c > 0.0)
        # ... and the offsets of the air leaving the cooler core or the heater, parameters of the model (OWN_OFFSETS)
        own = [(param, getattr(s, q)) for q, param in OWN_OFFSETS if getattr(s, q) > 0.0]
        self.own_offsets = tuple(param for param, _ in own)
        self.i_own_p = [model.param_names.index(param) for param in self.own_offsets]
        self.nc = (self.nx + 3 + int(self.learns_bypass_flow) + int(self.anchors_bypass_flow)
                   + int(self.has_outlet_offset) + len(own))
        # the disturbance states follow the model states (module docstring)
        self.i_mix_offset, self.i_flow_offset, self.i_inlet = self.nx, self.nx + 1, self.nx + 2
        self.i_exponent = self.i_inlet + 1 if self.learns_bypass_flow else None
        # ln of the reference mass flow (kg/s), next to the exponent
        self.i_anchor = self.i_exponent + 1 if self.anchors_bypass_flow else None
        self.i_own = list(range(self.nc - len(own), self.nc))
        self._own_idx = (np.array(self.i_own_p, int), np.array(self.i_own, int))  # model_parameters' copy, once
        self.i_outlet_offset = self.nc - 1 - len(own) if self.has_outlet_offset else None
        # the heat flow into the mixed air (EkfSettings.q_supply_heat_w), among the own states
        self.i_heat = (self.i_own[self.own_offsets.index("supply_heat_w")] if "supply_heat_w" in self.own_offsets
                       else None)
        self.n_hist = int(round(s.dead_time_max_s / self.dt_s))
        self.nz = self.nc + self.n_hist  # ... and the history of the undelayed thermocouple state
        names = model.states.names
        self.i_water = names.index("water_temp_c")
        self.i_sensor = names.index("supply_sensor_c")
        q_state = {"motor_rise_c": s.q_motor_c, "water_temp_c": s.q_water_c, "heater_temp_c": s.q_heater_c,
                   "supply_sensor_c": s.q_sensor_c, "trap_air_temp_c": s.q_trap_c}
        q_state.update({n: s.q_sensor_c for n in model.delay_states})
        # the offset's walk: the smaller of its two rates in Q, the rest added while it applies (accept_prediction)
        self._q_mix = (s.q_mix_offset_c, s.q_mix_offset_unseen_c or s.q_mix_offset_c)
        self._q_mix_in_q = min(self._q_mix) ** 2  # the part of the offset's walk that Q holds (accept_prediction)
        q = [q_state[n] for n in names] + [min(self._q_mix), s.q_flow_offset_m3s, s.q_inlet_c]
        q += [s.q_bypass_flow_exponent] * int(self.learns_bypass_flow) + [0.0] * int(self.anchors_bypass_flow)
        q += [s.q_heater_outlet_offset_c] * int(self.has_outlet_offset)
        # the heat flow's walk is added once released (accept_prediction, _release_heat), not held in Q
        q += [0.0 if param == "supply_heat_w" else q_own for param, q_own in own] + [HIST_Q_C] * self.n_hist
        self.Q = np.diag(np.square(q))
        # the prior stands for a dead time the parameters do not name: none where they name one
        self.dead_time_prior_s = s.dead_time_prior_s if model.params.transport_delay_s <= 0.0 else 0.0
        self.dead_time = DeadTimeEstimator(self.n_hist, model.params.tau_tc_s, self.dt_s, s.dead_time_window_s,
                                           s.dead_time_excitation_c, initial_steps=s.dead_time_initial_s / self.dt_s,
                                           prior_steps=self.dead_time_prior_s / self.dt_s,
                                           lead_reach_steps=s.dead_time_lead_reach_s / self.dt_s,
                                           count_quiet=s.dead_time_lead_count_quiet,
                                           lead_tie_hold=s.dead_time_lead_tie_hold,
                                           first_settle_steps=s.dead_time_first_settle_s / self.dt_s,
                                           longest_reach_moves=s.dead_time_step_longest_reach_moves,
                                           longest_not_flat=s.dead_time_step_longest_not_flat)
        self.R_diag = np.square([s.r_supply_c, s.r_flow_m3s, s.r_water_c, s.r_inlet_c, s.r_heater_outlet_c])
        # the supply reading's deviation at rest (EkfSettings.r_supply_rest_c): the rest gate and the variances there
        self.rest_gate = self._new_rest_gate() if s.r_supply_rest_c > 0.0 else None
        # the rest the heat flow's release waits for (EkfSettings.supply_heat_release_at_rest): the same gate
        gated = (s.supply_heat_release_at_rest or s.supply_heat_walk_at_rest or s.supply_heat_level_neutral_at_rest
                 or s.supply_heat_release_hold_s > 0.0)  # the settings that ask whether the filter is at rest
        self.heat_rest_gate = (self.rest_gate or self._new_rest_gate()) if s.q_supply_heat_w > 0.0 and gated else None
        gate = self.rest_gate or self.heat_rest_gate  # one at most: the heat's is the reading's where that is on
        self._rest_gates = () if gate is None else (gate,)
        # the supply reading left out while a predicted response is still to show (EkfSettings.response_wait_c)
        self.response_wait = (ResponseWait(s.response_wait_c, s.response_wait_share,
                                           max(1, math.ceil(s.dead_time_min_s / self.dt_s - 1e-9)),
                                           self.n_hist + 1, int(round(RESPONSE_WAIT_AFTER_S / self.dt_s)),
                                           s.response_wait_flat_c,
                                           int(round(s.response_wait_rearm_s / self.dt_s)))
                              if s.response_wait_c > 0.0 and self.n_hist else None)
        self.use = np.array([True, True, True, True, s.use_heater_outlet])
        # the filter states the supply reading is compared with: the thermocouple state now and its history
        self._supply_idx = np.array([self.i_sensor] + list(range(self.nc, self.nz)))
        self._supply_block = np.ix_(self._supply_idx, self._supply_idx)  # their block of the covariance
        self._build()
        self.z: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.time_updates = 0  # time updates taken since the filter was built (a count, never reset)
        self._restart()
        self._mix = BufferedFunction(self.mix_fn, fixed={3: self.p}) if self.anchors_bypass_flow else None
        # the exponent fitted outside the filter across settled flow steps (EkfSettings.bypass_flow_at_rest)
        self.rest_steps = self.rest_fit = None
        self.i_valve_a, self.i_heater_cmd = model.inputs.index("valve_a_pct"), model.inputs.index("heater_cmd_w")
        # the states re-anchored once a dead time is found (EkfSettings.reanchor_states), with the dead-time handling
        self.shadow = OpenLoopShadow(model, s.reanchor_states, self.dt_s) if s.reanchor_states and self.n_hist else None
        self._sd0 = None
        if self.anchors_bypass_flow and s.bypass_flow_at_rest:
            self.rest_steps = SettledFlowSteps(s.bypass_flow_settle_s, s.bypass_flow_gate, self.dt_s)
            self.rest_fit = FlowStepFit(s.bypass_flow_exponent_prior, s.bypass_flow_exponent_sd,
                                        s.bypass_flow_rest_noise_c, s.bypass_flow_exponent_min,
                                        s.bypass_flow_exponent_max)

    def _new_rest_gate(self) -> RestGate:
        """A rest gate of the settings' window and bands (:mod:`~.rest_gate`)."""
        s = self.settings
        return RestGate(s.rest_window_s, s.rest_air_band_c, s.rest_log_flow_band, s.rest_offset_band_c, self.dt_s)

    def _d(self, z, setpoint):
        x = z[:self.nx]
        target = x[self.i_water] if self.hold_water else setpoint
        return ca.vertcat(z[self.i_inlet], target, z[self.i_mix_offset], z[self.i_flow_offset])

    def disturbance_values(self, setpoint_c: float) -> np.ndarray:
        """The prediction model's disturbances (``DISTURBANCES`` order) at the estimate now, as numpy: the values of
        :meth:`disturbance` without a CasADi call (a few microseconds instead of tens)."""
        z = self.z
        target = z[self.i_water] if self.hold_water else setpoint_c
        return np.array([z[self.i_inlet], target, z[self.i_mix_offset], z[self.i_flow_offset]], float)

    def _restart(self) -> None:
        """Forget what the last run left besides the state and its covariance: the dead-time estimate, the
        exponent's gate, start-up clock and committed value, and the motor rise's release."""
        self.dead_time.reset()
        self._log_flow_mean: float | None = None
        self._last_log_flow: float | None = None  # the model's flow at the last time update (ln m3/s)
        self._last_air_c: float | None = None  # the model's mixed air at the last time update (degC)
        self.learning = False  # the bypass-flow exponent's gate: the flow moves
        self._motor_released = False  # the motor rise's variance raised once a response was seen
        self._heat_released = False  # the heat flow into the mixed air estimated (_release_heat)
        self._heat_seen_at_s: float | None = None  # when the heat's release first saw a response
        self._heat_gain = 0.0  # the heat's effect on the air at the last time update's flow (degC per W)
        self._heat_flow_mean: float | None = None  # ln of the model's flow, its running mean (supply_heat_flow_gate_s)
        self._heat_open_until_s = -math.inf  # the heat takes the readings until then (supply_heat_flow_gate_s)
        self._rested = False  # the rest gate at rest since the first response (supply_heat_release_at_rest)
        self._heat_released_at_s = -math.inf  # when the heat was released (supply_heat_release_hold_s)
        self._heat_taken_back = False  # a release taken back: the next waits for rest (supply_heat_release_hold_s)
        self._reference: tuple[float, ...] | None = None  # the reference last noted (note_reference)
        self._reference_moved_at_s = -math.inf  # when it last changed
        self._temp_reference_moved_at_s = -math.inf  # when its first value (the supply air's degC) last changed
        self._honoured_lag: float | None = None  # the dead time (samples) honoured at the last re-anchor
        self._hold_until_s = 0.0  # the shadowed states are re-anchored every sample until then (reanchor_hold_s)
        self._seen_at_s: float | None = None  # when the dead-time estimate first saw a response
        self._pinned = False  # the shadowed states held at the shadow at the last sample
        self._relearning = False  # within reanchor_hold_s of a newly honoured dead time
        self._age_s = 0.0  # time since initialise
        self.supply_innovation_c = self.supply_nis = math.nan  # no measurement update of this run yet
        for gate in self._rest_gates:
            gate.reset()
        if self.response_wait is not None:
            self.response_wait.reset()
        self._committed = self.settings.bypass_flow_exponent_prior  # the exponent at the end of the last flow change
        for learner in (getattr(self, "rest_steps", None), getattr(self, "rest_fit", None)):
            if learner is not None:
                learner.reset()

    def _build(self) -> None:
        m, nx, nc = self.model, self.nx, self.nc
        z = ca.SX.sym("z", self.nz)
        u = ca.SX.sym("u", len(m.inputs))
        sp = ca.SX.sym("setpoint")
        # the model parameters are an input (HvacModel.p_default order): generated code of these
        # functions serves every parameter set of one model structure (docs/architecture.md)
        p = ca.SX.sym("p", len(m.p_default))
        self.p = np.array(m.p_default, float)
        if self.adapts_bypass_flow:  # the filter's own exponent (module docstring)
            self.p[self.i_exponent_p] = self.settings.bypass_flow_exponent_prior
        # weights of the supply reading over [thermocouple state now, history entries 1..n]: the
        # dead time the reading is compared at (unit weight on "now" = the plain filter)
        c = ca.SX.sym("c", self.n_hist + 1)
        self.c_now = np.eye(self.n_hist + 1)[0]
        zc = z[:nc]
        d = self._d(zc, sp)
        x = zc[:nx]
        pm = p
        own = {}  # the filter's own states in place of parameters
        if self.learns_bypass_flow:  # the estimated exponent (and anchor)
            own[self.i_exponent_p] = zc[self.i_exponent]
            if self.anchors_bypass_flow:
                own[self.i_ref_p] = ca.exp(zc[self.i_anchor])
        for i_p, i_z in zip(self.i_own_p, self.i_own):  # the estimated offsets of the core's or heater's air
            own[i_p] = zc[i_z]
        if own:
            pm = ca.vertcat(*[own.get(i, p[i]) for i in range(p.shape[0])])
        xk = rk4(m.ode, x, u, d, pm, self.dt_s, 2)
        # shift register: the newest history entry is the thermocouple state now, the others move on
        hist = z[nc:]
        zn = ca.vertcat(xk, zc[nx:], x[self.i_sensor], hist[:-1]) if self.n_hist else ca.vertcat(xk, zc[nx:])
        y = m.output(x, u, d, pm)
        supply = ca.dot(c, ca.vertcat(x[self.i_sensor], hist))
        outlet = y[m.outputs.index("heater_outlet_temp_c")]
        if self.has_outlet_offset:
            outlet = outlet + zc[self.i_outlet_offset]
        meas = ca.vertcat(supply, y[m.outputs.index("volume_flow_m3s")], x[self.i_water], zc[self.i_inlet], outlet)
        # the model's air at the thermocouple (after the model's own transport delay, if its parameters
        # set one) without the offset state, for the dead time beyond the model's
        air = y[m.outputs.index("duct_air_temp_c")] - zc[self.i_mix_offset]
        flow = y[m.outputs.index("volume_flow_m3s")]
        # the model's mixed air and mass flow, for the anchor's move (bypass_flow_anchored only)
        self.mix_fn = ca.Function("ekf_mix", [z, u, sp, p], [y[m.outputs.index("supply_air_temp_c")],
                                                          y[m.outputs.index("mass_flow_kgs")]]
                                  ) if self.anchors_bypass_flow else None
        self.f_p = ca.Function("ekf_f", [z, u, sp, p], [zn, ca.jacobian(zn, z), air, flow])
        # f_p's next state and air without its Jacobian (the same expression nodes, so the same values to the bit):
        # the sign check's held commands (:func:`~.sign_check.held_air_function`)
        self.step_air_fn = ca.Function("ekf_step_air", [z, u, sp, p], [zn, air], ["z", "u", "setpoint", "p"],
                                       ["z_next", "air"])
        self.h_p = ca.Function("ekf_h", [z, u, sp, p, c], [meas, ca.jacobian(meas, z)])
        self.h = BufferedFunction(self.h_p, fixed={4: self.c_now})
        self.predict_fn = self._predict_function()
        self.update_fn = self._update_function()
        self.use_functions(self.predict_fn, self.update_fn)

    def _predict_function(self) -> ca.Function:
        """(z, P, u, setpoint, p, Q, learn) -> (z+, P+, air, flow): the time update of :meth:`predict` as one
        function; ``air`` is the model's air at the thermocouple before the update (dead-time estimate),
        ``flow`` its total volume flow (m3/s, the bypass-flow exponent's gate)."""
        nz = self.nz
        z, P = ca.SX.sym("z", nz), ca.SX.sym("P", nz, nz)
        u, sp = ca.SX.sym("u", len(self.model.inputs)), ca.SX.sym("setpoint")
        p, Q = ca.SX.sym("p", len(self.p)), ca.SX.sym("Q", nz, nz)
        learn = ca.SX.sym("learn")
        zn, F, air, flow = self.f_p(z, u, sp, p)
        if self.learns_bypass_flow:  # its column zeroed but for its own 1 (a constant to the filter)
            unit = ca.DM.zeros(nz, nz)
            unit[self.i_exponent, self.i_exponent] = 1.0
            F = F @ ca.diag(self._exponent_mask(learn)) + (1.0 - learn) * unit
        return ca.Function(f"{self.name}_predict", [z, P, u, sp, p, Q, learn], [zn, ca.mtimes([F, P, F.T]) + Q, air, flow],
                           ["z", "P", "u", "setpoint", "p", "Q", "learn"], ["z_next", "P_next", "air", "flow"])

    def _exponent_mask(self, learn):
        """Ones, with ``learn`` at the bypass-flow exponent (if learned): scales its column of the
        Jacobians and its row of the gain, so that with ``learn`` 0 the exponent is a constant to the
        filter (the plain filter for the other states) and keeps its variance."""
        if not self.learns_bypass_flow:
            return ca.DM.ones(self.nz)
        return ca.vertcat(ca.DM.ones(self.i_exponent), learn, ca.DM.ones(self.nz - self.i_exponent - 1))

    def _update_function(self, sym=ca.MX) -> ca.Function:
        """(z, P, y, ok, u, setpoint, c, p, R, learn) -> (z+, P+): the measurement update of
        :meth:`update` (Joseph form) with the readings where ``ok`` is 1 and the supply reading
        compared at the weights ``c``. A reading left out has its row of H and its innovation zeroed
        and a unit variance, so it adds an uncoupled identity block to S and a zero column to K: the
        same update as with the used readings alone. ``learn`` (0 or 1) scales the bypass-flow
        exponent's column of H and row of the gain (0: a constant to the filter, see :meth:`_exponent_mask`).

        The matrix products are MX (``sym``), so generated C loops over them (a third of the C an SX function writes
        out, less code to fetch inside a step); they add in the order the SX products (``sym=ca.SX``, the first
        formulation) did, and the solve for the gain is the SX function's (:meth:`_gain_solve`), so the numbers are the
        same (``tests/test_small_code.py``)."""
        nz, nm = self.nz, len(MEASURED)
        z, P = sym.sym("z", nz), sym.sym("P", nz, nz)
        y, ok = sym.sym("y", nm), sym.sym("ok", nm)
        u, sp = sym.sym("u", len(self.model.inputs)), sym.sym("setpoint")
        c = sym.sym("c", self.n_hist + 1)
        p, R = sym.sym("p", len(self.p)), sym.sym("R", nm)
        hz, H = self.h_p(z, u, sp, p, c)
        learn = sym.sym("learn")
        mask = ca.diag(self._exponent_mask(learn))
        H = ca.diag(ok) @ H @ mask
        innov = ok * (y - hz)
        Rm = ca.diag(ok * R + (1 - ok))
        S = H @ P @ H.T + Rm
        HP = H @ P
        K = mask @ self._gain_solve(S.sparsity(), HP.sparsity())(S, HP).T
        IKH = ca.DM.eye(nz) - K @ H
        Pn = IKH @ P @ IKH.T + K @ ca.diag(ok * R) @ K.T
        return ca.Function(f"{self.name}_update", [z, P, y, ok, u, sp, c, p, R, learn], [z + K @ innov, 0.5 * (Pn + Pn.T)],
                           ["z", "P", "y", "ok", "u", "setpoint", "c", "p", "R", "learn"], ["z_next", "P_next"])

    @staticmethod
    def _gain_solve(s_sparsity: ca.Sparsity, b_sparsity: ca.Sparsity) -> ca.Function:
        """``(S, B) -> S \\ B`` as CasADi solves it on SX (the measurement update's gain, :meth:`_update_function`)."""
        S, B = ca.SX.sym("S", s_sparsity), ca.SX.sym("B", b_sparsity)
        return ca.Function("ekf_gain_solve", [S, B], [ca.solve(S, B)])

    # ------------------------------------------------------------------ interface
    @property
    def initialised(self) -> bool:
        return self.z is not None

    def reset(self) -> None:
        """Forget the estimate: the next :meth:`initialise` starts afresh, and until then
        :meth:`model_parameters` is that of a filter never run (the prior exponent)."""
        self.z = None
        self.P = None
        self._restart()

    @property
    def dead_time_s(self) -> float:
        """The dead time of the thermocouple beyond the model's that the filter honours now (s)."""
        return self.dead_time.seconds

    @property
    def honoured_dead_time_s(self) -> float:
        """The dead time (s) the supply reading is compared at: :attr:`dead_time_s` once it reaches
        ``dead_time_min_s``, else 0 (the reading against the thermocouple state now; :meth:`_supply_weights`)."""
        seconds = self.dead_time_s if self.n_hist else 0.0
        return seconds if self._honours(seconds) else 0.0

    def _honours(self, seconds: float) -> bool:
        """Whether a dead time of ``seconds`` (s) is honoured: ``dead_time_min_s`` at least (the one rule of
        :meth:`_supply_weights` and :attr:`honoured_dead_time_s`)."""
        return seconds >= self.settings.dead_time_min_s

    def initialise(self, measurement: Measurement, u: np.ndarray, setpoint_c: float) -> None:
        """Start at the model's rest state for the current command, matched to the first readings."""
        m = self.model
        inlet = finite_or(measurement.hvac_inlet_temp_c, 25.0)
        water = finite_or(measurement.water_temp_c, setpoint_c)
        target = water if self.hold_water else setpoint_c
        d = m.d_vector(inlet, target)
        # anchored, the split at the flow in force is the thesis model's whatever the exponent
        p = self.model_parameters(0.0 if self.anchors_bypass_flow else self.settings.bypass_flow_exponent_prior)
        try:
            x = m.steady_state(u, d, p)
            if not np.all(np.isfinite(x)):
                raise ValueError("non-finite rest state")
        except Exception:  # noqa: BLE001 - fall back to a plain guess, the filter converges from it
            x = np.full(self.nx, inlet)
            x[m.states.index("motor_rise_c")] = 0.5
        x[self.i_water] = water
        y = m.outputs.dict(m.y(x, u, d, p))
        supply = finite_or(measurement.supply_temp_c, y["supply_temp_c"])
        flow = finite_or(measurement.volume_flow_m3s, y["volume_flow_m3s"])
        mix = supply - y["supply_air_temp_c"]
        x[self.i_sensor] = supply
        for n in m.delay_states:
            x[m.states.index(n)] = supply
        self.z = np.concatenate([x, [mix, flow - y["volume_flow_m3s"], inlet], np.full(self.n_hist, supply)])
        p0 = {"motor_rise_c": self.settings.initial_sd_motor_c, "water_temp_c": 0.2, "heater_temp_c": 5.0,
              "supply_sensor_c": 0.1, "trap_air_temp_c": 5.0}
        p0.update({n: 0.1 for n in m.delay_states})
        s = self.settings
        exponent = [s.bypass_flow_exponent_prior] * int(self.learns_bypass_flow)
        mass_flow = y["mass_flow_kgs"] * flow / max(y["volume_flow_m3s"], 1e-6)  # the measured flow's
        anchor = [math.log(max(mass_flow, 1e-5))] * int(self.anchors_bypass_flow)
        outlet = [0.0] * int(self.has_outlet_offset)
        own = [float(self.p[i]) for i in self.i_own_p]  # the states of OWN_OFFSETS start at the parameters' values
        self.z = np.concatenate([self.z[:self.i_inlet + 1], exponent, anchor, outlet, own,
                                 self.z[self.i_inlet + 1:]])
        sd = [p0[n] for n in m.states.names] + [0.5, 2e-3, 0.1]
        sd += [s.bypass_flow_exponent_sd] * len(exponent)
        sd += [0.0] * len(anchor)
        sd += [1.0] * len(outlet) + [self._own_sd0(param) for param in self.own_offsets] + [0.1] * self.n_hist
        self.P = np.diag(np.square(sd))
        self._restart()
        if self.shadow is not None:
            self.shadow.start(x)
            self._sd0 = np.array(sd)[self.shadow.idx]

    @staticmethod
    def _own_sd0(param: str) -> float:
        """Standard deviation at the start of the filter's own value of model parameter ``param`` (:data:`OWN_OFFSETS`):
        :data:`OWN_OFFSET_SD0_C` (degC) for an offset; 0 for the heat flow into the mixed air, held at the parameter's
        value until a response is seen (:meth:`_release_heat`)."""
        return 0.0 if param == "supply_heat_w" else OWN_OFFSET_SD0_C

    @property
    def supply_heat_w(self) -> float:
        """The heat flow into the mixed air the filter's model uses (W; ``EkfSettings.q_supply_heat_w``): the estimate,
        or the parameter's value where it is not estimated."""
        return self.own_offset_c("supply_heat_w")

    @property
    def supply_heat_effect_c(self) -> float:
        """The heat flow's effect on the model's air at the last time update's flow (degC; 0 where the heat is not
        estimated): with :attr:`mix_offset_c` the level the filter explains the supply air's error by."""
        return self.supply_heat_w * self._heat_gain

    def use_functions(self, predict_fn, update_fn) -> None:
        """Evaluate the time and measurement updates with these functions (the same signatures as
        ``predict_fn`` / ``update_fn``, e.g. generated C of them, :mod:`hvac_mpc.mpc.codegen`).
        ``p``, ``Q`` and ``R_diag`` are read here, once: call again after changing them (the variances at rest,
        ``R_diag`` with the supply reading's ``r_supply_rest_c``, are derived here too)."""
        self._predict_in_use = predict_fn
        self._predict = BufferedFunction(predict_fn, fixed={4: self.p, 5: self.Q})
        self._update = BufferedFunction(update_fn, fixed={7: self.p, 8: self.R_diag})
        self._r_in_use = self.R_diag  # the reading variances in the update's input (update)
        self._R_rest = self.R_diag.copy()
        self._R_rest[0] = self.settings.r_supply_rest_c ** 2

    def prediction_function(self) -> tuple[ca.Function, dict[int, np.ndarray]]:
        """The time update in use, ``(z, P, u, setpoint, p, Q, learn) -> (z+, P+, air, flow)``, and its fixed
        inputs (index -> value): for a caller that fuses it with more work into one call (the MPC's
        preparation, :meth:`~.rti_osqp.RtiOsqpSolver.use_prediction`), which then hands the results to
        :meth:`accept_prediction`."""
        return self._predict_in_use, {4: self.p, 5: self.Q}

    def model_state(self, z):
        """The model states within a filter state ``z`` (numpy or CasADi)."""
        return z[:self.nx]

    def disturbance(self, z, setpoint):
        """The prediction model's disturbances (``DISTURBANCES`` order) from a filter state (CasADi)."""
        return self._d(z, setpoint)

    def predict(self, u: np.ndarray, setpoint_c: float) -> None:
        """Time update over one sample with the command that was applied."""
        self.accept_prediction(*self._predict(self.z, self.P, u, setpoint_c, float(self.learning)))

    def accept_prediction(self, z_next: np.ndarray, P_next_t: np.ndarray, air: np.ndarray, flow: np.ndarray) -> None:
        """Take the time update's results (as the time-update function returns them, ``P`` column-major)."""
        walks = self._walks_after_temp_step()  # the sample's start, before the clock moves
        self.z, self.P = z_next, P_next_t.T  # buffers are column-major
        self._age_s += self.dt_s
        self.time_updates += 1
        q_mix = self._q_mix[0] if self.response_seen else self._q_mix[1]
        if (self._relearning or walks) and self.settings.reanchor_hold_q_mix_c > 0.0:
            q_mix = self.settings.reanchor_hold_q_mix_c
        air_c, flow_m3s = float(air[0]), float(flow[0])
        self.P[self.i_mix_offset, self.i_mix_offset] += (q_mix * q_mix - self._q_mix_in_q + self._flow_step_var(flow_m3s)
                                                          + self._air_step_var(air_c))
        if self.i_heat is not None:
            self._heat_gain = self._heat_effect_c_per_w(flow_m3s)
            self._note_heat_flow(flow_m3s)
            if self._heat_released and not self.heat_held:  # the heat flow's walk (EkfSettings.q_supply_heat_w)
                self._add_heat_variance(self._heat_walk_w(flow_m3s) ** 2, walk=True)
        if self.n_hist:
            self.dead_time.push_air(air_c)
        for gate in self._rest_gates:
            gate.push(air_c, flow_m3s, self.mix_offset_c)
        if self.learns_bypass_flow and not self.anchors_bypass_flow:
            self._gate(flow_m3s)

    def _walks_after_temp_step(self) -> bool:
        """Whether the mixed-air offset walks at ``reanchor_hold_q_mix_c`` in this time update because the supply
        air's reference changed less than ``EkfSettings.offset_walk_after_temp_step_s`` ago (s, before this update's
        sample) with a dead time honoured (no re-anchor of the states: the walk of the hold only)."""
        window_s = self.settings.offset_walk_after_temp_step_s
        return (window_s > 0.0 and self._age_s - self._temp_reference_moved_at_s < window_s
                and self.honoured_dead_time_s > 0.0)

    @property
    def response_seen(self) -> bool:
        """True once the dead-time estimate has seen a response (:attr:`~.dead_time.DeadTimeEstimator.informed`),
        and always without the dead-time handling (no history of the air): the gate of every setting that waits
        for the timing of a response."""
        return self.dead_time.informed or not self.n_hist

    def _flow_step_var(self, flow_m3s: float) -> float:
        """The mixed-air offset's added variance (degC^2) for the change of the model's flow since the last time
        update (``EkfSettings.q_mix_offset_per_log_flow_c``)."""
        per = self.settings.q_mix_offset_per_log_flow_c
        log_flow = math.log(max(flow_m3s, 1e-4))
        last, self._last_log_flow = self._last_log_flow, log_flow
        # before a response has shown the dead time, the raised variance takes the MPC's own late answer instead
        if per <= 0.0 or last is None or not self.response_seen:
            return 0.0
        return (per * max(0.0, abs(log_flow - last) - self.settings.q_mix_offset_flow_deadband)) ** 2

    def _air_step_var(self, air_c: float) -> float:
        """The mixed-air offset's added variance (degC^2) for the change of the model's mixed air since the last
        time update (``EkfSettings.q_mix_offset_per_air_change``)."""
        share = self.settings.q_mix_offset_per_air_change
        if share <= 0.0:
            return 0.0
        last, self._last_air_c = self._last_air_c, air_c
        if last is None or not self.response_seen:
            return 0.0
        return (share * (air_c - last)) ** 2

    def _gate(self, flow_m3s: float) -> None:
        """Open the bypass-flow exponent's gate while the model's flow is more than ``bypass_flow_gate``
        (in log) away from its running mean over ``bypass_flow_window_s`` (module docstring)."""
        s = self.settings
        log_flow, self._log_flow_mean = log_flow_and_mean(self._log_flow_mean, flow_m3s, self.dt_s,
                                                          s.bypass_flow_window_s)
        self._set_learning(abs(log_flow - self._log_flow_mean) > s.bypass_flow_gate)

    def _set_learning(self, flow_moves: bool) -> None:
        """Learn the exponent while the flow moves (and, with ``bypass_flow_after_response``, once the dead-time
        estimate has seen a response); otherwise it is a constant to the filter, without correlations."""
        s = self.settings
        seen = self.response_seen or not s.bypass_flow_after_response
        self.learning = bool(flow_moves and seen and self._age_s >= s.bypass_flow_after_s
                             and not s.bypass_flow_at_rest)
        if not self.learning:  # a constant to the filter: no correlation with the other states
            self._decorrelate(self.i_exponent)
            self._committed = float(self.z[self.i_exponent])

    def _release_motor(self) -> None:
        """Once the dead-time estimate has seen a response (or with no dead-time handling), raise the motor
        rise's standard deviation to ``motor_sd_after_response_c`` (if it is below): before, the timing of a
        response is not known and the filter would take a late one for the motor (docs/robustness.md sec. 2.7)."""
        sd = self.settings.motor_sd_after_response_c
        if self._motor_released or sd <= 0.0 or not self.response_seen:
            return
        i = self.model.states.index("motor_rise_c")
        self.P[i, i] = max(self.P[i, i], sd * sd)
        self._motor_released = True

    def _release_heat(self, weights: np.ndarray) -> None:
        """Once the dead-time estimate has seen a response and the reading is compared at a dead time honoured
        (``weights`` off the reading now), or ``dead_time_window_s`` after the first response where none is honoured
        (a box without a dead time beyond the model's; at once without the dead-time handling), give the heat flow
        into the mixed air (``EkfSettings.q_supply_heat_w``) its standard deviation ``supply_heat_sd0_w`` and its
        walk. Before, a late response looks like a heat: at the start-up's moves it wound up (a box with a 3.5 s dead
        time: -120 then +350 W in 35 s, -175 W released at the first response, against the box's +18 W), and what it
        took came back as an error at the next flow change."""
        if self._heat_released or self.i_heat is None or not self.response_seen:
            return
        if (self.settings.supply_heat_release_at_rest or self._heat_taken_back) and not self._rested:
            self._rested = self.heat_rest_gate.at_rest  # the first settled period after the first response
            if not self._rested:
                return
        if self._age_s - self._reference_moved_at_s < self.settings.supply_heat_release_hold_s:
            return  # too soon after a change of the reference (EkfSettings.supply_heat_release_hold_s)
        if self._heat_seen_at_s is None:
            self._heat_seen_at_s = self._age_s
        waited = self._age_s - self._heat_seen_at_s >= self.settings.dead_time_window_s
        if self.n_hist and weights is self.c_now and not waited:
            return
        self._add_heat_variance(self.settings.supply_heat_sd0_w ** 2)
        self._heat_released = True
        self._heat_released_at_s = self._age_s

    def _heat_walk_w(self, flow_m3s: float) -> float:
        """The heat flow's walk this sample (W): ``EkfSettings.q_supply_heat_w``, scaled down with the mass flow below
        ``supply_heat_walk_flow_m3h`` and 0 outside rest with ``supply_heat_walk_at_rest`` (:class:`EkfSettings`)."""
        s = self.settings
        if s.supply_heat_walk_at_rest and not self.heat_rest_gate.at_rest:
            return 0.0
        walk = s.q_supply_heat_w
        if s.supply_heat_walk_flow_m3h > 0.0:  # at no flow too: the effect per W is largest there
            # the effect per W falls with the mass flow: the walk's effect held at the reference flow's
            walk *= min(1.0, self._heat_effect_c_per_w(s.supply_heat_walk_flow_m3h / 3600.0) / self._heat_gain)
        return walk

    def _take_back_heat(self) -> None:
        """With ``EkfSettings.supply_heat_release_hold_s``: a release a change of the reference follows within that
        long is taken back: the heat to the parameter's value, the mixed-air offset taking its effect at the last
        time update's flow (the air as it was), its variance and correlations 0; the next release waits for rest."""
        hold = self.settings.supply_heat_release_hold_s
        if (hold <= 0.0 or not self._heat_released
                or not 0.0 <= self._reference_moved_at_s - self._heat_released_at_s <= hold):
            return
        i = self.i_heat
        prior = float(self.p[self.i_own_p[self.i_own.index(i)]])
        self.z[self.i_mix_offset] += (float(self.z[i]) - prior) * self._heat_gain
        self.z[i] = prior
        self._decorrelate(i)
        self.P[i, i] = 0.0
        self._heat_released = self._rested = False
        self._heat_taken_back = True

    def note_reference(self, *values: float | None) -> None:
        """The controller's reference this step (its values, e.g. the supply air's degC and the flow's m3/s): a change
        from the last noted is when ``EkfSettings.supply_heat_release_hold_s`` counts from (:meth:`_take_back_heat`,
        :meth:`_release_heat`); the first noted is not a change."""
        now = tuple(values)
        if self._reference is not None and now != self._reference:
            self._reference_moved_at_s = self._age_s
            if now[:1] != self._reference[:1]:
                self._temp_reference_moved_at_s = self._age_s
        self._reference = now

    @property
    def heat_held(self) -> bool:
        """Whether the heat flow into the mixed air is held as it is this sample, out of the measurement update and
        without its walk: with ``EkfSettings.supply_heat_flow_gate_s`` while the model's flow has not moved within
        that long, with ``supply_heat_step_hold_s`` within that long after a change of the reference. Held, the
        mixed-air offset alone takes the supply reading's error, as in the filter without the heat."""
        s = self.settings
        if self._age_s - self._reference_moved_at_s < s.supply_heat_step_hold_s:
            return True  # the first seconds of a change of the reference (EkfSettings.supply_heat_step_hold_s)
        return s.supply_heat_flow_gate_s > 0.0 and self._age_s > self._heat_open_until_s

    def _note_heat_flow(self, flow_m3s: float) -> None:
        """The heat flow's flow gate (``EkfSettings.supply_heat_flow_gate_s``): open for that long after ln of the
        model's flow leaves its running mean (:data:`SUPPLY_HEAT_FLOW_WINDOW_S`) by more than
        :data:`SUPPLY_HEAT_FLOW_BAND`; at a steady flow the heat and the offset are one to the readings."""
        gate = self.settings.supply_heat_flow_gate_s
        if gate <= 0.0:
            return
        log_flow, self._heat_flow_mean = log_flow_and_mean(self._heat_flow_mean, flow_m3s, self.dt_s,
                                                           SUPPLY_HEAT_FLOW_WINDOW_S)
        if abs(log_flow - self._heat_flow_mean) > SUPPLY_HEAT_FLOW_BAND:
            self._heat_open_until_s = self._age_s + gate

    def _hide_heat(self) -> tuple[float, np.ndarray | None]:
        """Take the heat flow out of the coming measurement update (its variance set to 0, so its gain is 0); returns
        its variance (W^2) and, with ``EkfSettings.supply_heat_hold_correlated``, the other states' regression on it
        (their covariance with it over its variance), which :meth:`_show_heat` puts back after the update. Without
        that setting its correlations are dropped; with it the other states are conditioned on the heat (their
        covariance less the part the heat explains), so the update sees the heat as a known value."""
        i = self.i_heat
        var = float(self.P[i, i])
        if not (self.settings.supply_heat_hold_correlated and var > 0.0):
            self._decorrelate(i)
            self.P[i, i] = 0.0
            return var, None
        along = self.P[:, i] / var
        self.P -= var * np.outer(along, along)
        self.P[i, :] = 0.0  # 0 up to rounding already
        self.P[:, i] = 0.0
        return var, along

    def _show_heat(self, var_w2: float, along: np.ndarray | None) -> None:
        """Put the heat flow's variance (W^2) back after a held update; ``along`` (from :meth:`_hide_heat`): its
        covariances too, the other states' regression on the heat as before the update."""
        if along is None:
            self.P[self.i_heat, self.i_heat] = var_w2
            return
        self.P += var_w2 * np.outer(along, along)

    def _heat_effect_c_per_w(self, flow_m3s: float) -> float:
        """The heat flow's effect on the model's air per W (degC/W), 1 / (m_dot c_p) at the model's volume flow
        ``flow_m3s`` and the inlet air's density, the mass flow held at the blower's least (as the model's,
        :func:`~hvac_mpc.models.air.heat_gain_c`)."""
        prm, t_in = self.model.params, float(self.z[self.i_inlet])
        mass_flow = float(air_props.density_kgm3(t_in, prm)) * flow_m3s
        return float(air_props.heat_gain_c(1.0, mass_flow, blower.least_mass_flow_kgs(t_in, prm), prm))

    def _add_heat_variance(self, var_w2: float, walk: bool = False) -> None:
        """Variance ``var_w2`` (W^2) for the heat flow; with ``EkfSettings.supply_heat_level_neutral`` along the
        direction that leaves the air at the flow in force as it is: the heat up by w, the mixed-air offset down by
        w / (m_dot c_p), so the heat's walk shapes only how the air changes with the flow and the level at a steady
        flow walks at the offset's rate, as in the plain filter. Without it the heat's walk adds to the level's (at 90
        m3/h 1 W per sample is 0.033 degC, the offset's 0.015); with ``supply_heat_level_neutral_at_rest`` so for the
        ``walk`` while the rest gate is at rest."""
        i, j = self.i_heat, self.i_mix_offset
        s = self.settings
        neutral = s.supply_heat_level_neutral or (walk and s.supply_heat_level_neutral_at_rest
                                                  and self.heat_rest_gate.at_rest)
        g = self._heat_gain if neutral else 0.0
        self.P[i, i] += var_w2
        self.P[j, j] += var_w2 * g * g
        self.P[i, j] -= var_w2 * g
        self.P[j, i] -= var_w2 * g

    def _decorrelate(self, i: int) -> None:
        """Drop the correlations of filter state ``i`` with the others (its variance kept)."""
        keep = self.P[i, i]
        self.P[i, :] = 0.0
        self.P[:, i] = 0.0
        self.P[i, i] = keep

    def _move_anchor(self, u: np.ndarray, setpoint_c: float) -> None:
        """Move the bypass split's reference mass flow towards the model's mass flow (time constant
        ``bypass_flow_window_s``) and let the mixed-air offset take the change of the model's mixed air, so that
        the prediction at the command in force does not move: the exponent shapes only the response to a flow
        that differs from the recent one (``EkfSettings.bypass_flow_anchored``). Opens the exponent's gate."""
        s, i = self.settings, self.i_anchor
        air_before, mass_flow = (float(v[0]) for v in self._mix(self.z, u, setpoint_c))
        log_flow = math.log(max(mass_flow, 1e-5))
        self.z[i] += min(1.0, self.dt_s / s.bypass_flow_window_s) * (log_flow - self.z[i])
        air_after = float(self._mix(self.z, u, setpoint_c)[0][0])
        self.z[self.i_mix_offset] += air_before - air_after
        self._set_learning(abs(log_flow - self.z[i]) > s.bypass_flow_gate)

    def _rest_observation(self, before, now, u: np.ndarray, setpoint_c: float) -> tuple[float, float]:
        """One settled flow step as an observation of the exponent (:mod:`~.flow_term`): the sensitivity ``S`` of
        ``f(k) = mix(k, anchor before) - mix(k, anchor now)`` at the estimate in use ``k_c`` (degC per unit, a
        central difference) and ``y = d_offset - f(k_c) + S k_c`` (degC), so that ``y ~ S k``."""
        k_c, h = float(self.z[self.i_exponent]), 0.05

        def effect(k: float) -> float:  # f(k) at the settled state
            z = self.z.copy()
            z[self.i_exponent] = k
            z[self.i_anchor] = before.log_flow
            then = float(self._mix(z, u, setpoint_c)[0][0])
            z[self.i_anchor] = now.log_flow
            return then - float(self._mix(z, u, setpoint_c)[0][0])
        sensitivity = (effect(k_c + h) - effect(k_c - h)) / (2.0 * h)
        return sensitivity, now.offset_c - before.offset_c - effect(k_c) + sensitivity * k_c

    def readings(self, measurement: Measurement) -> tuple[np.ndarray, np.ndarray]:
        """The measured values (order ``MEASURED``, 0 where unused) and which are used (finite and enabled)."""
        values = measured_values(measurement)
        ok = np.isfinite(values) & self.use
        return np.where(ok, values, 0.0), ok

    def update(self, measurement: Measurement, u: np.ndarray, setpoint_c: float) -> int:
        """Measurement update with the finite readings; returns how many were used."""
        self.supply_innovation_c = self.supply_nis = math.nan  # until this update's supply reading is weighed
        values, ok = self.readings(measurement)
        used = int(np.count_nonzero(ok))
        if not used:
            return 0
        if self.anchors_bypass_flow:
            self._move_anchor(u, setpoint_c)
        self._release_motor()
        weights = self._supply_weights(values[0], ok[0])
        if self.i_heat is not None:
            self._take_back_heat()
        self._release_heat(weights)
        if ok[0] and self._response_due(values[0], weights):
            ok[0] = False  # the reading left out while the response the model made is still to show
        if self.shadow is not None:
            self._follow_shadow(u, setpoint_c, weights)
        r_diag = self.R_diag
        if self.rest_gate is not None:  # the supply reading's variance at rest or in a transient (EkfSettings)
            r_diag = self._R_rest if self.rest_gate.at_rest else self.R_diag
            if r_diag is not self._r_in_use:  # copied into the call's input only when it changes
                self._update.set_fixed(8, r_diag)
                self._r_in_use = r_diag
        self._note_supply_innovation(values[0], ok[0], weights, float(r_diag[0]))
        held = self._heat_released and self.heat_held
        heat_var, along = self._hide_heat() if held else (0.0, None)
        zn, Pt = self._update(self.z, self.P, values, ok, u, setpoint_c, weights, float(self.learning))
        self.z, self.P = zn, Pt.T
        if held:
            self._show_heat(heat_var, along)
        if self.settings.bound_motor_rise:
            self.bound_state("motor_rise_c", 0.0, float(self.model.params.motor_gain_max_c))
        if self.learns_bypass_flow:
            s = self.settings
            self.z[self.i_exponent] = np.clip(self.z[self.i_exponent], s.bypass_flow_exponent_min,
                                              s.bypass_flow_exponent_max)
        if self.rest_steps is not None:
            self._learn_at_rest(u, setpoint_c)
        return used

    def _response_due(self, supply_c: float, weights: np.ndarray) -> bool:
        """Whether the supply reading is still to show a response the model predicts at the dead time honoured now
        (:mod:`~.response_wait`, ``EkfSettings.response_wait_c``; False without it, and with
        ``response_wait_unseen_only`` once a response has been seen and a dead time is honoured)."""
        if self.response_wait is None:
            return False
        if self.settings.response_wait_unseen_only and self.response_seen and weights is not self.c_now:
            self.response_wait.stop()  # a dead time found from a response and honoured: a missing response is a
            return False               # model error, which the offsets take at once
        steps = 0.0 if weights is self.c_now else self.dead_time.steps
        return self.response_wait.observe(self.dead_time.prediction_c(steps), supply_c, steps)

    def _note_supply_innovation(self, supply_c: float, used: bool, weights: np.ndarray, r_c2: float) -> None:
        """Keep the supply reading's innovation (degC) against the filter's prediction at the dead time honoured and
        its normalised square (innovation^2 over its variance, the reading's ``r_c2`` degC^2 included;
        :attr:`supply_nis`, nan where the reading is not used): what a choice between filters compares
        (:mod:`~.placement`)."""
        if not used:
            self.supply_innovation_c = self.supply_nis = math.nan
            return
        if weights is self.c_now:  # the reading against the thermocouple state now: the sums below, whose other terms are 0
            i = self.i_sensor
            innovation = supply_c - float(self.z[i])
            variance = float(self.P[i, i]) + r_c2
        else:
            innovation = supply_c - float(weights @ self.z[self._supply_idx])
            variance = float(weights @ self.P[self._supply_block] @ weights) + r_c2
        self.supply_innovation_c = innovation
        self.supply_nis = innovation * innovation / variance

    def _follow_shadow(self, u: np.ndarray, setpoint_c: float, weights: np.ndarray) -> None:
        """Advance the open-loop shadow over the sample with ``u`` in force and re-anchor the shadowed states to it
        (:mod:`~.reanchor`) at the first sample a dead time is honoured (``weights`` off the reading now) and then
        every sample until ``reanchor_hold_s`` after the honoured dead time last changed (the moves made before it
        keep arriving a dead time and a thermocouple lag later); with ``reanchor_before_response`` also every
        sample until ``reanchor_hold_s`` after the dead-time estimate first saw a response (the estimate may take
        that long to move to the dead time the response shows)."""
        x = self.z[:self.nx]
        d = self.disturbance_values(setpoint_c)
        p = self.model_parameters()
        self.shadow.advance(x, u, d, p)
        honoured = weights is not self.c_now
        if honoured and self.dead_time.steps != self._honoured_lag:
            self._honoured_lag = self.dead_time.steps
            self._hold_until_s = self._age_s + self.settings.reanchor_hold_s
        if self._seen_at_s is None and self.response_seen:
            self._seen_at_s = self._age_s
        held = self._relearning = honoured and self._age_s <= self._hold_until_s
        unseen = self._seen_at_s is None or self._age_s <= self._seen_at_s + self.settings.reanchor_hold_s
        idx = self.shadow.idx
        if held or (self.settings.reanchor_before_response and unseen):
            # held at the shadow: the states' deviations one sample's process noise, so the readings leave them be
            layout = FilterLayout(self.nx, self.i_mix_offset, self.i_outlet_offset)
            reanchor(self.shadow, self.z, self.P, layout, np.sqrt(self.Q[idx, idx]), u, d, p)
            self._pinned = True
        elif self._pinned:  # released: the start's deviations again
            self.P[idx, idx] = np.maximum(self.P[idx, idx], np.square(self._sd0))
            self._pinned = False

    def _learn_at_rest(self, u: np.ndarray, setpoint_c: float) -> None:
        """Fit the exponent to the mixed-air offset's change across a flow step that has just settled
        (``EkfSettings.bypass_flow_at_rest``, :mod:`~.flow_term`); the offset takes the change of the model's air
        the new exponent brings, so the supply air the filter explains does not move."""
        s = self.settings
        mass_flow = float(self._mix(self.z, u, setpoint_c)[1][0])
        seen = self.response_seen or not s.bypass_flow_after_response
        others = (float(u[self.i_valve_a]), float(u[self.i_heater_cmd]))
        step = self.rest_steps.observe(math.log(max(mass_flow, 1e-5)), self.mix_offset_c,
                                       seen and self._age_s >= s.bypass_flow_after_s, others)
        if step is None:
            return
        before, now = step
        if (abs(now.others[0] - before.others[0]) > s.bypass_flow_rest_valve_pct
                or abs(now.others[1] - before.others[1]) > REST_HEATER_TOL_W):
            return  # the supply air moved with valve a or the heater too: the offset's change is not the flow's
        self.rest_fit.add(*self._rest_observation(before, now, u, setpoint_c))
        air_before = float(self._mix(self.z, u, setpoint_c)[0][0])
        self.z[self.i_exponent] = self.rest_fit.estimate()
        self.z[self.i_mix_offset] += air_before - float(self._mix(self.z, u, setpoint_c)[0][0])
        self._committed = float(self.z[self.i_exponent])

    def _supply_weights(self, supply_c: float, used: bool) -> np.ndarray:
        """Weights of the supply reading over [thermocouple state now, history 1..n]: the undelayed
        state of the estimated dead time ago, between the two samples around it (``self.c_now``
        while no dead time of at least ``dead_time_min_s`` is found)."""
        if not (self.n_hist and used):
            return self.c_now
        s = self.settings
        moved_at_s = (self._temp_reference_moved_at_s if s.dead_time_step_longest_temp_only
                      else self._reference_moved_at_s)
        self.dead_time.prefer_longest = self._age_s - moved_at_s < s.dead_time_step_longest_s
        lag = self.dead_time.observe(supply_c)
        if not self._honours(lag * self.dt_s):
            return self.c_now
        j0 = math.floor(lag)  # int(np.floor(lag)) of a finite float
        w1 = lag - j0
        c = np.zeros(self.n_hist + 1)
        c[j0] += 1.0 - w1
        c[min(j0 + 1, self.n_hist)] += w1
        return c

    def bound_state(self, name: str, lo: float, hi: float) -> None:
        """Hold model state ``name`` within [``lo``, ``hi``] where physics bounds it and the readings hardly
        observe it (the heater body without power, docs/robustness.md sec. 2.6): a value outside is set to
        the nearer end and the state's correlations with the others are dropped (its variance kept), so
        that the readings do not push it out again against the offsets."""
        i = self.model.states.index(name)
        value = float(self.z[i])
        if lo <= value <= hi:
            return
        self.z[i] = min(max(value, lo), hi)
        self._decorrelate(i)

    # ------------------------------------------------------------------ views
    @property
    def x(self) -> np.ndarray:
        return self.z[:self.nx]

    @property
    def mix_offset_c(self) -> float:
        return float(self.z[self.i_mix_offset])

    @property
    def flow_offset_m3s(self) -> float:
        return float(self.z[self.i_flow_offset])

    @property
    def inlet_temp_c(self) -> float:
        return float(self.z[self.i_inlet])

    @property
    def bypass_flow_exponent(self) -> float:
        """The bypass-flow exponent the filter's model uses now: the estimate, or the parameter where
        it is not learned."""
        if self.learns_bypass_flow and self.z is not None:
            return float(self.z[self.i_exponent])
        return float(self.p[self.i_exponent_p])

    def model_parameters(self, exponent: float | None = None) -> np.ndarray:
        """The model parameters (``HvacModel.p_default`` order) with the bypass-flow exponent the
        filter uses (or ``exponent``; with ``bypass_flow_commit_at_rest`` the value from the end of the last flow
        change) and, anchored, the split's reference mass flow at the anchor, for a prediction consistent with
        the estimate."""
        p = self.p.copy()
        if exponent is None and self.learns_bypass_flow and self.settings.bypass_flow_commit_at_rest:
            exponent = self._committed  # the prediction takes a learned value only once its flow change is over
        if self.adapts_bypass_flow:
            p[self.i_exponent_p] = self.bypass_flow_exponent if exponent is None else exponent
        if self.anchors_bypass_flow and self.z is not None:
            p[self.i_ref_p] = math.exp(float(self.z[self.i_anchor]))
        if self.z is not None and self.own_offsets:
            p[self._own_idx[0]] = self.z[self._own_idx[1]]
        return p

    @property
    def adapts_parameters(self) -> bool:
        """True where the prediction's parameters follow the filter (:meth:`model_parameters`): the bypass-flow
        exponent learned, or an offset of :data:`OWN_OFFSETS` (the cooler core's or the heater's air) estimated."""
        return self.learns_bypass_flow or bool(self.own_offsets)

    @property
    def has_cooler_offset(self) -> bool:
        """True where the filter estimates the offset of the air leaving the cooler core."""
        return "cooler_outlet_offset_c" in self.own_offsets

    def own_offset_c(self, param: str) -> float:
        """The estimate of model parameter ``param`` (one of :data:`OWN_OFFSETS`; degC, W for the heat flow), the
        parameter's own value where the filter does not estimate it."""
        if param in self.own_offsets and self.z is not None:
            return float(self.z[self.i_own[self.own_offsets.index(param)]])
        return float(self.p[self.model.param_names.index(param)])

    @property
    def cooler_offset_c(self) -> float:
        """The offset of the air leaving the cooler core the filter uses (degC)."""
        return self.own_offset_c("cooler_outlet_offset_c")

    def healthy(self) -> bool:
        return self.z is not None and all_finite(self.z) and all_finite(self.P)


def log_flow_and_mean(mean: float | None, flow_m3s: float, dt_s: float, window_s: float) -> tuple[float, float]:
    """ln of the model's flow (m3/s, floored at 1e-4) and its running mean over ``window_s`` (s) after one sample of
    ``dt_s`` (s); ``mean`` None starts the mean at this sample. The flow gates' measure of a moving flow."""
    log_flow = math.log(max(flow_m3s, 1e-4))
    mean = log_flow if mean is None else mean
    return log_flow, mean + min(1.0, dt_s / window_s) * (log_flow - mean)


def check_state_names(name: str, value) -> None:
    """``value`` a tuple of distinct names of :data:`~.reanchor.REANCHORABLE`, else a clear error."""
    if not isinstance(value, tuple) or any(v not in REANCHORABLE for v in value) or len(set(value)) != len(value):
        raise InvalidSettings(f"{name} must be a tuple of distinct names among {REANCHORABLE}; got {value!r}")


def measured_values(measurement: Measurement) -> np.ndarray:
    """The readings of ``MEASURED`` as floats, nan where a reading is missing (``None``) or not a number: one
    conversion of the five (a few microseconds a step less than :func:`finite_or` on each), each value on its own
    where one is not a plain number. An infinite reading stays infinite here; :meth:`DisturbanceEkf.readings`
    leaves it unused as :func:`finite_or`'s nan."""
    raw = [getattr(measurement, n, None) for n in MEASURED]
    try:
        return np.array(raw, float)
    except (TypeError, ValueError):
        return np.array([finite_or(v, np.nan) for v in raw])


def finite_or(value, default: float) -> float:
    """``value`` as a float when it is a finite number, else ``default``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return default
    return v if math.isfinite(v) else default  # a float: math's test, numpy's answer without its call
