"""A move of one actuator that reverses its last move, applied in part: the real-time iteration's two-cycle damped.

The real-time iteration takes one full Gauss-Newton step per sample, linearised at the shifted plan. Where an
actuator's pull on the tracked output changes sign between two linearisation points (on the recirculating box after
a warm-up that drained the heater body, valve a: the core's air hardly warmer than the bypass's, docs/
identification.md, "The recirculation traced again"), the QP at one point plans the actuator to the other end and
the QP there plans it back: the command alternates from sample to sample (valve a 0 <-> 50 % for 20 s) and the
iteration never settles. The same two-cycle remains with five Gauss-Newton QPs per sample (``solver="sqp"``): it is
the iteration's on a problem that is not convex there (the body's heat, and so valve a's pull, depends on valve a),
not a gate, a fallback or the warm start. :func:`damped_move` applies only ``share`` of a move that reverses the last
applied move (both beyond ``min_move``); the next QP's first stage is linearised at the command applied, between
the two ends, as a trust region shrunk on a reversal would have it. A move in the same direction is applied whole.
The controller applies it to valve a (``MpcSettings.valve_a_reversal_share``, 0.3 by default; measured in
docs/identification.md, "The recirculation traced again").

ASSUMPTION: an actuator's applied move reversing its last one within one sample (both beyond ``min_move``) is
the iteration's two-cycle, not a wanted change of direction; a wanted one is delayed by a sample or two only, as
each further move in the new direction is applied whole. Pure functions, no model code.
"""

from __future__ import annotations


def damped_move(previous: float, last_move: float, proposed: float, share: float, min_move: float) -> float:
    """The command to apply: ``proposed`` unless its move from ``previous`` reverses ``last_move`` (the last applied
    move, same units) with both at least ``min_move`` in size; then ``previous`` plus ``share`` (in (0, 1]) of it."""
    move = proposed - previous
    if abs(move) < min_move or abs(last_move) < min_move or move * last_move >= 0.0:
        return proposed
    return previous + share * move
