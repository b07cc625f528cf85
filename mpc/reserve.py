"""Heater reserve: at rest on a heating reference, valve a held low so the heater body keeps heat for a step up
(a setting, off by default: ``Weights.valve_a_reserve_per_pct2``).

At rest heating has a free direction: the air takes the heater's power whatever valve a's share, so valve a and
the heater body's temperature trade without changing the supply temperature or the energy. The default weight on
valve a while heating (``Weights.valve_a_heating_per_pct2``, 3e-5) leans on that direction lightly. A controller
whose model is right then holds the reference with valve a well open and the body lean (the literal cooler's box:
valve a 53-58 %, the body 33-36 C at 12 C), and a step up the horizon does not see finds the heater at its limit and
no stored heat: the wrong model keeps a reserve by accident (docs/identification.md 'The full scenarios, and the
literal cooler as a library effect').

The reserve raises valve a's weight to ``Weights.valve_a_reserve_per_pct2`` only where the direction is free:

- *at rest*: the heater commanded (the heating weight's own switch), the reference unchanged and the supply reading
  within :data:`REST_BAND_C` of it for :data:`REST_HOLD_S` in a row; the reserve stays on while the reading stays
  within :data:`LEAVE_BAND_C` (hysteresis: closing valve a moves the reading a little before the body follows);
- *the heater not limiting* when the rest begins: the command in force at least :data:`HEADROOM_W` below the power
  the heater can give at the body's estimate (the PTC line): where the heater is at its limit valve a is the last
  lever on the supply temperature. Once on, the reserve itself runs the heater high while the body takes up heat;
- *the body not past the PTC knee*: above the knee the heater's power falls, so a hotter body is of no use to a
  step up and only heat a step down must wait out (on the literal-cooler box the reserve without this bound held
  the body at 86 C at 15 C, and the step down to 11 C and the heater-off segment after it cost more than the step
  up gained). The body's estimate past the knee ends the reserve (it starts again :data:`KNEE_MARGIN_C` below
  it), and so does the box's heater drawing measurably less than its command (the measured heater power, where
  the box has it), whatever the estimate: with valve a low the reading barely sees the body (the estimate 20-30 K
  low on the built-in box at 15 C);
- *the flow priority untouched*: not while the flow weights are lowered (a flow out of reach, or traded for
  temperature, :func:`~.priorities.flow_weight_factor`).

A change of the supply-temperature or total-flow reference ends the rest at once (an outlet-split change alone does
not: it moves no heat), so every step up is served with the default weight and the body's heat. A step *down* while
heating takes the reserve's weight (:func:`descending`) until the reading is within :data:`REST_BAND_C` of the new
reference: the air must lose heat, and valve a closing is both the fast way and the way that keeps the body's heat, so
the weight pulls the way tracking does (where the change's QPs, linearised at the plan for the old reference, leave
valve a partly open, it closes it sooner). The default weight at every step up is what the same weight on valve a at
all times (``valve_a_heating_per_pct2`` 3e-4) lacked: at the 12 -> 22 C step of
the built-in bench's trapped_air_release the QP with the heavy valve-a weight reached OSQP's iteration cap for 28 s
(the shifted plan applied, valve a at 2.5 %, the heater at 30 W, then the baseline's fallback), the step began late
(trapped air 0.508 -> 0.68).

The rest's entry (settings, off by default): ``Weights.valve_a_reserve_ramp_s`` lets the weight rise over some
seconds of the rest (:func:`ramped_weight`) and ``Weights.valve_a_reserve_short_c`` withholds it while the heater is
at its limit with the reading short of the reference (:func:`withholding`): with the full weight at once a right
model's MPC closes valve a at the rest's start faster than the heater's extra power warms the body, and the reading
falls short where the heater limits (docs/identification.md 'The reserve re-measured', 'The reserve's entry').
``Weights.valve_a_reserve_ptc_hold_s`` (a setting, off by default) keeps the reserve out for some seconds after the
box's heater drew less than its command (:func:`past_knee_held`): past the knee the rest otherwise counts again as soon
as the command falls below the PTC line, and the reserve's weight flickers on and off with the body still past the
knee (docs/identification.md 'The reserve's winter cost').

ASSUMPTION: a heating reference held for :data:`REST_HOLD_S` may be followed by a step up the horizon does not see
(the comfort algorithm's steps of 3-4 K, the bench's winter scenario), and keeping the heat for it in the body is
worth the weight on valve a's opening.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: The rest begins once the supply reading has been within this of the reference (K) for :data:`REST_HOLD_S`: the
#: bench's settling band.
REST_BAND_C = 0.5
#: Time (s) the reading must stay in :data:`REST_BAND_C` before the reserve counts. ASSUMPTION:
#: long enough that a step's settling is over (the thermocouple's 5.73 s time constant, twice).
REST_HOLD_S = 12.0
#: Once at rest, the reserve counts while the reading is within this of the reference (K).
LEAVE_BAND_C = 1.0
#: The heater counts as limiting when its command in force is within this of the power available at the body's
#: estimate (W). ASSUMPTION: a tenth of the heater's 240 W rating.
HEADROOM_W = 24.0
#: The box's heater is on its PTC line when its measured power falls this far below the command in force (W).
#: ASSUMPTION: above the power reading's noise.
PTC_SHORTFALL_W = 8.0
#: The reserve starts only with the body's estimate this far below the PTC knee (K), and ends at the knee.
KNEE_MARGIN_C = 5.0
#: A reference change (supply temperature, K; volume flow, m3/s) larger than these ends the rest.
REF_CHANGE_C = 0.05
REF_CHANGE_M3S = 1e-5


def descending(heating: bool, lowered: bool, was_descending: bool, excess_c: float) -> bool:
    """Whether valve a takes the reserve's weight on a step down: the heater commanded, the supply-temperature
    reference lowered (``lowered``: at this step; ``was_descending``: at an earlier one, no other change since) and
    the reading still more than :data:`REST_BAND_C` above it (``excess_c``, K; NaN: no reading, not descending).

    On a step down the air must lose heat, and closing valve a is both the fast way (the air bypasses the heater
    body) and the way that keeps the body's heat: tracking and the reserve pull the same way, so the weight costs
    the step nothing. It decides the first command of the step where the change's QPs have two plans of near-equal
    cost (docs/identification.md 'The reserve on a step down')."""
    return bool(heating and (lowered or was_descending) and excess_c > REST_BAND_C)


def withholding(short_c: float, limiting: bool, error_c: float) -> bool:
    """Whether the rest's weight is withheld at this step: the rule on (``short_c`` > 0, K), the heater at its limit
    (``limiting``: the command in force within :data:`HEADROOM_W` of the power at the body's estimate) and the reading
    more than ``short_c`` below the reference (``error_c``: reading minus reference, K; NaN: not withheld).

    At the limit valve a is the last lever on the supply temperature: the reserve's weight closing it puts the
    heater's power into the body and leaves the air short, so a right model's rest start costs tracking where the
    heater limits (docs/identification.md 'The reserve re-measured', 'The reserve's entry')."""
    return bool(short_c > 0.0 and limiting and error_c < -short_c)


def past_knee_held(since_short_s: float, hold_s: float) -> bool:
    """Whether the box's heater counts as past the PTC knee ``since_short_s`` seconds after the last step where it
    drew measurably less than its command (0: at this step; inf: never): at that step, and with the hold on
    (``hold_s`` > 0, s) for ``hold_s`` after it. ASSUMPTION: the body past the knee cools no faster than the air
    through it takes its heat (tens of seconds to minutes at rest), whatever the command; the shortfall itself ends
    as soon as the command falls below the PTC line (docs/identification.md 'The reserve's winter cost')."""
    return bool(since_short_s <= 0.0 or since_short_s < hold_s)


def ramped_weight(heating_per_pct2: float, reserve_per_pct2: float, on_s: float, ramp_s: float) -> float:
    """Valve a's weight (per %^2 per s) ``on_s`` seconds into the rest: from the heating weight to the reserve's in a
    straight line over ``ramp_s`` (s; 0: the reserve's at once), so valve a closes as the heater's power goes into
    the body, not before it (the entry's dip, docs/identification.md 'The reserve's entry')."""
    if ramp_s <= 0.0 or on_s >= ramp_s:
        return reserve_per_pct2
    return heating_per_pct2 + (reserve_per_pct2 - heating_per_pct2) * max(on_s, 0.0) / ramp_s


@dataclass
class HeaterReserve:
    """The reserve's gate: call :meth:`weight` once per controller step; it returns the valve-a weight of that
    step (the reserve's or the default heating weight)."""

    reserve_per_pct2: float
    heating_per_pct2: float
    dt_s: float
    ramp_s: float = 0.0
    short_c: float = 0.0
    ptc_hold_s: float = 0.0
    _rest_s: float = 0.0
    _ref: tuple[float, float] | None = None
    _on: bool = False
    _descent: bool = False
    _on_s: float = 0.0
    _withheld: bool = False
    _since_short_s: float = math.inf

    def reset(self) -> None:
        self._rest_s, self._ref, self._on, self._descent = 0.0, None, False, False
        self._on_s, self._withheld, self._since_short_s = 0.0, False, math.inf

    @property
    def withheld(self) -> bool:
        """Whether the last step was at rest with the reserve's weight withheld (:func:`withholding`)."""
        return self._withheld

    @property
    def on(self) -> bool:
        """Whether the last step was at rest with the reserve's weight."""
        return self._on

    @property
    def descent(self) -> bool:
        """Whether the last step had the reserve's weight on a step down (:func:`descending`)."""
        return self._descent

    def weight(self, *, supply_ref_c: float, flow_ref_m3s: float, reading_c: float, heating: bool,
               heater_cmd_w: float, available_w: float, flow_factor: float, heater_power_w: float = math.nan,
               body_c: float = -math.inf, knee_c: float = math.inf) -> float:
        """Valve a's weight (per %^2 per s) for this step; 0 when not heating, as the default weight.
        ``available_w``: the heater's power at the body's estimate ``body_c`` (C); ``heater_power_w``: the measured
        heater power (NaN: not measured) for the command in force ``heater_cmd_w``; ``knee_c``: the PTC knee (C)."""
        ref = (float(supply_ref_c), float(flow_ref_m3s))
        changed = self._ref is None or abs(ref[0] - self._ref[0]) > REF_CHANGE_C or \
            abs(ref[1] - self._ref[1]) > REF_CHANGE_M3S
        lowered = self._ref is not None and ref[0] < self._ref[0] - REF_CHANGE_C
        self._ref = ref
        error = abs(reading_c - ref[0]) if math.isfinite(reading_c) and math.isfinite(ref[0]) else math.inf
        self._descent = descending(heating, lowered, self._descent and not changed, reading_c - ref[0])
        band = LEAVE_BAND_C if self._on else REST_BAND_C
        # the box's heater draws less than its command: its body is past the PTC knee, as hot as is of use
        short = math.isfinite(heater_power_w) and heater_power_w < heater_cmd_w - PTC_SHORTFALL_W
        self._since_short_s = 0.0 if short else self._since_short_s + self.dt_s
        # ... and stays so for ptc_hold_s after it: a command lowered below the PTC line ends the shortfall, not
        # the body's heat (the rest would count again after REST_HOLD_S with the body still past the knee)
        ptc_binding = past_knee_held(self._since_short_s, self.ptc_hold_s)
        # the body's estimate at the knee: as hot as is of use (hysteresis: the reserve starts KNEE_MARGIN_C below it)
        ptc_binding = ptc_binding or body_c > knee_c - (0.0 if self._on else KNEE_MARGIN_C)
        if changed or not heating or error > band or ptc_binding:
            self._rest_s = 0.0
        else:
            self._rest_s += self.dt_s
        # the heater's headroom is asked of the rest's start only: once on, the reserve itself runs the heater high
        # while the body takes up heat, and the PTC row prices a body above the knee in the plan
        room = self._on or heater_cmd_w <= available_w - HEADROOM_W
        self._on = self._rest_s >= REST_HOLD_S and room and flow_factor >= 1.0
        limiting = heater_cmd_w > available_w - HEADROOM_W
        self._withheld = self._on and withholding(self.short_c, limiting, reading_c - ref[0])
        # the ramp counts the rest's seconds with the weight in force; a withheld step does not count
        if not self._on:
            self._on_s = 0.0
        elif not self._withheld:
            self._on_s += self.dt_s
        if not heating:
            return 0.0
        if self._descent:
            return self.reserve_per_pct2
        if not self._on or self._withheld:
            return self.heating_per_pct2
        return ramped_weight(self.heating_per_pct2, self.reserve_per_pct2, self._on_s, self.ramp_s)
