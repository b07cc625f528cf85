"""Valve a held, not closed, while the heater is at its limit and the supply air well short of its reference.

In heater-limited heating (the heater command at its power limit: the range's top or the PTC line) every
watt the heater gives reaches the supply air through the core's flow, and valve a sets that flow. On a box whose
air enters warmer than the core's water (cabin air drawn in behind the inlet sensor: the recirculating box of
:mod:`hvac_mpc.mismatch`), shutting valve a warms the supply air at rest (the core cools the air the heater then
warms; at 65 W of blower and 160 W of heater the box gives 21.82 / 21.44 / 21.17 C at valve a 20 / 50 / 90 %), while
opening it releases the heat the body holds. The controller's model, right there, makes each real-time-iteration
QP linearise a product of valve a's flow and the body's excess heat; its plans alternate between valve a shut (the
heat stored in the body) and open (docs/identification.md,
"Recirculation in heater-limited heating, traced"). :func:`held_opening` refuses the closing half of that
alternation: a move of valve a towards shut is not applied while the heater is limited and the reading is more
than ``shortfall_c`` below the reference; a move onward is applied whole, and the bounds, rate limits and the
trapped-air cap are applied after it.

ASSUMPTION: while the supply air is short of its reference by more than ``shortfall_c`` with the heater at its
limit, heat kept in the heater body is worth less than the same heat in the supply air now, so valve a does not
close. Near the reference (within ``shortfall_c``) the QP's closing moves are applied as planned. Pure functions,
no model code; ``MpcSettings.valve_a_hold_shortfall_c`` (0: off, the default).
"""

from __future__ import annotations

import math

from .ocp import HEATING_CMD_W as HEATER_ON_W  # the heater command above which it counts as on (W)
from .temperature_reach import HEATER_MARGIN_W  # the distance from the upper bound that counts as at it (W)


def heater_limited(heater_cmd_w: float, heater_upper_w: float, reading_c: float | None, reference_c: float | None,
                   shortfall_c: float) -> bool:
    """True while the heater command is on and at its power limit (``heater_upper_w``, W) and the
    supply reading (degC) is more than ``shortfall_c`` (degC, > 0) below its reference; False where either is
    missing or not finite, or ``shortfall_c`` is 0 (off)."""
    if shortfall_c <= 0.0 or reading_c is None or reference_c is None:
        return False
    if not (math.isfinite(reading_c) and math.isfinite(reference_c)):
        return False
    at_limit = heater_cmd_w >= max(heater_upper_w - HEATER_MARGIN_W, HEATER_ON_W)
    return at_limit and reference_c - reading_c > shortfall_c


def held_opening(previous_pct: float, proposed_pct: float, limited: bool) -> float:
    """Valve a's command (%): ``previous_pct`` where ``limited`` (:func:`heater_limited`) and ``proposed_pct`` would
    close it further, else ``proposed_pct``."""
    return previous_pct if limited and proposed_pct < previous_pct else proposed_pct
