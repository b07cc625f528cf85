"""A start-up whose moves are slowed until the supply reading has answered one: a dead time nothing has shown yet.

At its start the controller knows nothing of a dead time between the mixed air and the supply thermocouple: the
dead-time estimate (:class:`~.dead_time.DeadTimeEstimator`) starts at 0 and ranks candidates only once a response
has excited it, and the response wait (:mod:`.response_wait`) does not act in the filter's first samples (its own
corrections move the model's air there). On a box with a dead time of 3.5-4 s the MPC's first step strokes valve
a in one sample (55 -> 100 % at the quick flow-out-of-reach scenario's start, the reading 2 degC above its
reference); for the dead time the reading does not move, the filter takes the missing response for a mixed-air
offset (+3.6 degC in four samples), the MPC holds the stroke against that offset, and when the response arrives
the reading overshoots by 1.7 degC and rings for 25 s, a dead time late each swing (docs/robustness.md sec. 2.19,
2.23).

:class:`StartCaution` limits valve a's opening (the scope ``valve_a_opening``, the default scope since
docs/robustness.md sec. 2.25) or valve a's and the heater's moves (``valve_a_and_heater``, sec. 2.23) to ``share``
of their rates from the controller's start until the filter in use has seen a response (its dead-time estimate
informed, :attr:`~.estimator.DisturbanceEkf.response_seen`) or ``duration_s`` has passed, whichever comes first. The
stroke becomes a ramp over a few samples. What that changed on the traced box (S0-10, share 0.4): the reading dips
as deep (16.0 against 16.3 degC), but the dead-time estimate honours 3.5 s at 8 s (4.0 s from 14 s) instead of first
at 31 s, the sample after the flow's jump, so the moves after the dip are answered with the dead time honoured and
the reading comes back to its reference without the second swing (18.1 degC at most against 19.75). Why the ramp's
response ranks the candidates where the stroke's did not (the filter's own corrections in the first samples also
move the model's air the estimate compares) was not analysed. On the built-in plant (no dead time) the estimate has
seen a response 8-9 s into the winter heating steps, so the caution lasts about as long there; it cost that
scenario's full run all the same (sec. 2.23), and the heating cells of the box sweep (S0-10 0.871 -> 0.990), whose
starts close valve a. Slowing valve a's opening only (sec. 2.25) leaves a start that closes valve a (toward the
bypass, the inlet's air) as it was: the winter heating steps' (60 -> 10 %) and S0-10 heating's; the full built-in
bench's ratios are the same to the fourth decimal with it, and the flow-jump cells keep their gain.

On by default (``MpcSettings.start_rate_share`` 0.4 since docs/robustness.md sec. 2.30; 1.0 turns it off), but
not at all where the controller knows a dead time from its start (:func:`known_delay_s`: the transport delay its
prediction carries, or a model file's delay as the estimator's starting dead time): the caution buys time for a dead
time nothing has shown, and a controller told of one only loses time by it (the MPC told of the ``delay_3s`` box's 3
s: 30.1 -> 35.6 C s on a cooling step, sec. 2.27). Where its bound does not bind (a start that closes valve a, or
opens it by less than the share) the commands are the same to the solver's tolerance, not to the bit: the bound is in
the first QPs all the same, and a run whose later QP ends at the solver's iteration limit, or whose loop rings, can
take another way from there (traced in sec. 2.27).

ASSUMPTION: the start is the one moment a dead time is certainly unknown; the stroke worth slowing is an opening one
(toward the core path); a closing one goes toward the bypass, whose air is the inlet's, and slowing it only costs
(measured, sec. 2.25, not derived). After the first response (or ``duration_s``, the longest dead time the filter
honours and a few samples more) the estimate, the response wait and the re-anchor of sec. 2.9 take over. The share
and the duration are chosen on the traced boxes (sec. 2.23), not derived. ASSUMPTION: the dead time is one between
the mixed air and the thermocouple whatever moved the air, so the first response the estimate ranks (of valve a, the
heater or the flow) ends the caution, not valve a's own; and a delay the controller is told of is the box's (a
model file's or the prediction's): the caution is not started then, nor for the part of a dead time beyond it. Pure python, no model code: the controller
feeds it.
"""

from __future__ import annotations

import math

#: What the caution slows. ``valve_a_opening``: valve a's opening only (toward the core path), its closing and
#: the heater free (docs/robustness.md sec. 2.25); ``valve_a_and_heater``: both ways of valve a and the heater
#: (sec. 2.23).
VALVE_A_OPENING = "valve_a_opening"
VALVE_A_AND_HEATER = "valve_a_and_heater"
SCOPES = (VALVE_A_OPENING, VALVE_A_AND_HEATER)

#: Where the scope ``valve_a_opening``'s bound goes (``MpcSettings.start_caution_in_qp``): True a bound of the QP,
#: False the command's only, ``"when_binding"`` the QP's only in the steps where the QP without it opens valve a beyond
#: it (the QP solved again with it; docs/robustness.md sec. 2.45).
START_CAUTION_WHEN_BINDING = "when_binding"
START_CAUTION_IN_QP = (True, False, START_CAUTION_WHEN_BINDING)


def known_delay_s(transport_delay_s: float, initial_dead_time_s: float) -> float:
    """The dead time (s) a controller knows from its start: the transport delay its prediction carries (a lag chain,
    ``Parameters.transport_delay_s``) plus the dead-time estimate's starting value (``EkfSettings.dead_time_initial_s``,
    where a model file's delay goes, ``mpc_controller._delay_to_estimator``). ASSUMPTION: the estimate's prior
    (``EkfSettings.dead_time_prior_s``) is a dead time assumed, not known, and does not count."""
    return max(0.0, float(transport_delay_s)) + max(0.0, float(initial_dead_time_s))


def opening_bound(lo: float, hi: float, previous: float, rise: float) -> float:
    """The upper bound of the next command of a valve whose opening is limited to ``rise`` (the same unit as the
    command, >= 0) above ``previous``: ``hi`` where that is lower, never below ``lo``."""
    return max(min(hi, previous + rise), lo)


class StartCaution:
    """The factor on the start-up's rate limits, and what it slows (``scope``, one of :data:`SCOPES`; the class's
    default is the first rule, valve a and the heater, while ``MpcSettings.start_caution_scope`` defaults to valve a's
    opening alone: the controller always passes its setting).

    ``share`` in (0, 1] (1: off); ``duration_s`` (s, >= 0) the longest the caution lasts; ``dt_s`` the sample
    time (s); ``known_delay_s`` (s, >= 0) the dead time the controller honours from its start (a transport delay its
    prediction carries, or the estimator's starting dead time from a model file): above 0 no caution at all, the
    dead time it buys time for being known (:func:`known_delay_s`). Per control step :meth:`factor` with whether the
    filter in use has seen a response; :meth:`reset` at the controller's reset.
    """

    def __init__(self, share: float, duration_s: float, dt_s: float = 1.0, scope: str = VALVE_A_AND_HEATER,
                 known_delay_s: float = 0.0):
        if not (math.isfinite(known_delay_s) and known_delay_s >= 0.0):
            raise ValueError(f"StartCaution: known_delay_s must be finite and >= 0 s, got {known_delay_s}")
        self.known_delay_s = float(known_delay_s)
        if scope not in SCOPES:
            raise ValueError(f"StartCaution: scope must be one of {list(SCOPES)}, got {scope!r}")
        self.scope = scope
        if not 0.0 < share <= 1.0:
            raise ValueError(f"StartCaution: share must be in (0, 1], got {share}")
        if not (math.isfinite(duration_s) and duration_s >= 0.0):
            raise ValueError(f"StartCaution: duration_s must be finite and >= 0 s, got {duration_s}")
        if not dt_s > 0.0:
            raise ValueError(f"StartCaution: dt_s must be > 0 s, got {dt_s}")
        self.share = float(share)
        self.duration_s = float(duration_s)
        self.dt_s = float(dt_s)
        self.reset()

    def reset(self) -> None:
        """A new start: the caution on again."""
        self._elapsed_s = 0.0
        self.active = self.share < 1.0 and self.known_delay_s <= 0.0

    def factor(self, response_seen: bool) -> float:
        """The factor for this step's command (``share`` while the caution lasts, then 1 for good)."""
        if self.active and (response_seen or self._elapsed_s >= self.duration_s - 1e-9 * self.dt_s):
            self.active = False
        self._elapsed_s += self.dt_s
        return self.share if self.active else 1.0
