"""The sign of the supply air's answer to a valve a move, checked against the filter in use (docs/robustness.md
sec. 2.28).

Valve a sets the share of the air that goes through the core and the heater; the rest takes the bypass. Where the
air leaving the heater path is colder than the bypass's, opening valve a cools the supply air; where it is warmer,
opening it warms the supply air. So the sign of d(supply)/d(valve a) is the sign of the difference of the two
paths' air, which the filter's model holds through its states and offsets. With the thesis's cooler fit taken
literally (the core's air about 10 C whatever the inlet) and a 5 C inlet, the core path is the warmer one; a filter
whose model lets the core's air follow the inlet believes the opposite, and after a large opening the reading rises
where its model expects a fall. Its offsets then take the rise in (a larger mixed-air offset), which keeps its
wrong sign, and the MPC keeps valve a open (sec. 2.24, 2.26: S0-7, S2-7). The innovations' size, which the
placement choice (:mod:`~.placement`) compares, sees that late; the sign sees it within a dead time and a
thermocouple lag.

The check (:class:`ValveSignCheck`): from rest (valve a within a quarter of ``move_pct`` and the reading within
half of ``change_c`` over ``rest_s``), a departure of valve a by at least ``move_pct``, answered within
``window_s`` by a change of the reading of at least ``change_c``, is a verdict where the filter in use's predicted
change has the other sign: that model has valve a's gain of the wrong sign. With ``rest_hold_s`` a rest lost to
valve a alone (the reading still at rest) starts a departure from the last rest's means for that long: valve a that
creeps a few % before it opens leaves no rest of the full rule (docs/robustness.md sec. 2.37). A prediction of the
right sign but smaller than the answer is no verdict: the size of the answer within the window depends on the heater
body's and the core's lags, on commands held shorter in the prediction than in the window and on a dead time the model may not
honour yet, and the offsets take a gain that is too small in as the reading comes; only the sign is beyond them
(an offset shifts the supply air at every valve position alike). The predicted change is the filter's model air with
each command of the departure held over a third of the window against the command before it, summed
(:func:`predicted_air_change_c`): on S2-7 the filter in use predicts -0.03 C for valve a 0 -> 90 %, the heater air's
filter +3.6 C, the reading rises 2 C.

The verdict says whether the other filter explains the answer seen (:attr:`SignVerdict.other_explains`: its
prediction of the answer's sign and at least the change the reading has made by then); only then does the
controller switch to it (``MpcSettings.placement_sign_move_pct``), and the switch is a trial
(:meth:`~.placement.PlacementChoice.force`): the sums start afresh and the filter left may take the prediction back
as soon as they show it. A wrong sign can be a passing error of the filter in use (on the built-in plant the heater
body warming after a heating step, sec. 2.28) or a lasting one (the literal cooler); the sums that follow the
switch tell them apart, the verdict alone cannot. Unlike the sums of :mod:`~.placement` the check compares the
reading's change over the window, not each sample's innovation: a filter that has the right sign but no dead time
yet predicts the answer a few samples early and loses the sums on those samples (S2-7, sec. 2.28), not the sign.

ASSUMPTION: a reading at rest before the move, and a change of at least ``change_c`` (0.5 C: ten times the
thermocouple noise's standard deviation of the boxes in ``hvac_mpc.mismatch``) within the window that the filter in
use's model does not explain in sign, is the move's own answer: the other commands of the same samples (the
blower, the heater, valve m) are in the predicted change, the heater body's and the core's lags with them. Other
causes (a change of the inlet air, a disturbance) within the window are not; the rest before the move and the size
of ``change_c`` make them unlikely, not impossible. ASSUMPTION: the model's air answers within a third of the
window (no transport-delay chain of the model's own longer than that). ASSUMPTION: the reading's change at the
verdict (the first sample at least ``change_c`` from the rest, a dead time and part of a lag after the move) is a
part of the move's whole answer, so a model that predicts less than it has valve a's gain too small as well.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque

import casadi as ca
import numpy as np

from .casadi_eval import BufferedFunction
from .codegen import shared

_max, _min, _sum = np.maximum.reduce, np.minimum.reduce, np.add.reduce
#: Valve a "at rest": within this share of ``move_pct`` over the rest window.
REST_SHARE_OF_MOVE = 0.25
#: The reading "at rest": its range over the rest window below this share of ``change_c``.
REST_SHARE_OF_CHANGE = 0.5
#: Index of the model's air (duct air without the mixed-air offset) in the filter's time-update outputs
#: (``DisturbanceEkf.f_p``: next state, its Jacobian, air, flow).
AIR_OUTPUT = 2


def predicted_air_change_c(ekf, u_before: np.ndarray, u_after: np.ndarray, setpoint_c: float,
                           steps: int = 0) -> float:
    """The change of the filter's model air (degC) that ``u_after`` makes against ``u_before``, each held over
    ``steps`` samples from the filter's state now (0: the mixing's algebraic answer alone): what its model expects
    the move to do to the supply air within that time, the heater body's and the core's lags included."""
    if not ekf.initialised:
        return math.nan
    return _held_air_c(ekf, u_after, setpoint_c, steps) - _held_air_c(ekf, u_before, setpoint_c, steps)


def _held_air_c(ekf, u: np.ndarray, setpoint_c: float, steps: int) -> float:
    """The filter's model air (degC) after ``steps`` samples with ``u`` held, from its state now."""
    z = ekf.z
    for _ in range(steps):
        z = ekf.f_p(z, u, setpoint_c, ekf.p)[0]
    return float(ekf.f_p(z, u, setpoint_c, ekf.p)[AIR_OUTPUT])


def held_air_function(ekf, steps: int) -> ca.Function:
    """``(z, u_before, u_after, setpoint, p) -> (air_after, air_before)``: the filter's model air (degC) after
    ``steps`` samples with each command held from the state ``z``, both in one call: what :func:`_held_air_c` gives
    for ``u_after`` and for ``u_before``, to the bit. Each sample is a call of the filter's next state and air
    (``DisturbanceEkf.step_air_fn``: ``f_p``'s expression nodes without its Jacobian, common subexpressions computed
    once, :func:`~.codegen.shared`), so every floating-point operation is the one ``f_p`` evaluates."""
    step = shared(ekf.step_air_fn)
    z = ca.MX.sym("z", ekf.nz)
    u_before, u_after = ca.MX.sym("u_before", step.size1_in(1)), ca.MX.sym("u_after", step.size1_in(1))
    sp, p = ca.MX.sym("setpoint"), ca.MX.sym("p", step.size1_in(3))

    def held(u):
        zk = z
        for _ in range(steps):
            zk = step(zk, u, sp, p)[0]
        return step(zk, u, sp, p)[1]
    return ca.Function(f"{ekf.name}_held_air{steps}", [z, u_before, u_after, sp, p], [held(u_after), held(u_before)],
                       ["z", "u_before", "u_after", "setpoint", "p"], ["air_after", "air_before"])


class HeldAirChange:
    """:func:`predicted_air_change_c` of one filter in one call of :func:`held_air_function` (generated C where the
    controller builds it, :meth:`use_function`), instead of ``2 (steps + 1)`` interpreted calls of ``f_p`` that
    evaluate its Jacobian too and convert every argument: the same number to the bit (``tests/test_step_glue.py``;
    docs/architecture.md "The step's glue")."""

    def __init__(self, ekf, steps: int):
        self.ekf = ekf
        self.steps = int(steps)
        self.function = held_air_function(ekf, self.steps)
        self.use_function(self.function)

    def use_function(self, fn: ca.Function) -> None:
        """Evaluate with ``fn`` (the signature of :attr:`function`, e.g. its generated C)."""
        self._call = BufferedFunction(fn)

    def __call__(self, u_before: np.ndarray, u_after: np.ndarray, setpoint_c: float) -> float:
        """The change of the filter's model air (degC) that ``u_after`` makes against ``u_before`` (physical), each
        held over :attr:`steps` samples from the filter's state now; nan where the filter is not initialised."""
        ekf = self.ekf
        if not ekf.initialised:
            return math.nan
        after, before = self._call.views(ekf.z, u_before, u_after, setpoint_c, ekf.p)  # read at once
        return float(after[0]) - float(before[0])


@dataclasses.dataclass
class SignVerdict:
    """A valve a move answered with the other sign than the filter in use predicted."""
    measured_c: float  # the reading's change since the rest before the move (degC)
    predicted_c: float  # the filter in use's predicted change (degC)
    other_predicted_c: float  # the other filter's (degC; nan without one)

    @property
    def other_right(self) -> bool:
        """Whether the other filter predicted the sign the reading showed."""
        return self.other_predicted_c * self.measured_c > 0.0

    @property
    def other_explains(self) -> bool:
        """Whether the other filter predicted the sign the reading showed and at least the change seen so far: the
        answer at the verdict is its first part (a dead time and a lag into it), so a model that predicts less than
        that has valve a's gain too small as well, and the answer is one neither model explains."""
        return self.other_predicted_c * math.copysign(1.0, self.measured_c) >= abs(self.measured_c)


@dataclasses.dataclass
class _Departure:
    reading_c: float  # the reading at rest before it (mean over the rest window)
    valve_a_pct: float  # valve a at rest before it (mean over the rest window)
    predicted_c: float = 0.0
    other_predicted_c: float = 0.0
    samples: int = 0


class ValveSignCheck:
    """The sign of the reading's answer to a valve a departure from rest (module docstring)."""

    def __init__(self, move_pct: float, change_c: float, window_s: float, rest_s: float, dt_s: float,
                 rest_hold_s: float = 0.0):
        import scipy.stats  # noqa: F401  the trial floor's (placement.trial_floor): loaded here, not in a control step

        self.move_pct = float(move_pct)
        self.change_c = float(change_c)
        self.window = max(1, int(round(window_s / dt_s)))
        #: samples the predicted change holds each command for (:func:`predicted_air_change_c`)
        self.horizon = max(1, int(round(window_s / (3.0 * dt_s))))
        self.rest_tol_pct = REST_SHARE_OF_MOVE * self.move_pct  # valve a "still": within this of its rest
        self.rest_tol_c = REST_SHARE_OF_CHANGE * self.change_c  # the reading "still": its range below this
        self.rest = max(2, int(round(rest_s / dt_s)))
        #: samples a rest lost to valve a alone still starts a departure (``rest_hold_s``; 0: none)
        self.rest_hold = max(0, int(round(rest_hold_s / dt_s)))
        self.verdicts = 0
        self.reset()

    def reset(self) -> None:
        """Forget the rest and any departure."""
        self._history: deque = deque(maxlen=self.rest)  # (valve a %, reading degC) before this sample
        self._departure: _Departure | None = None
        self._rest_of: tuple[float, float] | None | bool = False  # _rest of the history as it is (False: not known)
        self._samples = 0  # samples observed
        self._last_rest: tuple[tuple[float, float], int] | None = None  # the last rest and the sample it was seen

    def abandon(self) -> None:
        """Forget the departure under way, keeping the rest: the prediction has moved to the other filter, so the
        predicted changes summed so far are the filter's no longer in use (a verdict on them would judge it)."""
        self._departure = None

    def _rest(self) -> tuple[float, float] | None:
        """(valve a %, reading degC) at rest over the last ``rest`` samples (their means), or None; with
        ``rest_hold`` the last rest also while valve a alone has left it within that many samples (it creeps before
        it opens) and the reading is still at rest, within ``rest_tol_c`` of the held rest's mean (a rest of both is
        kept as the last rest where ``rest_hold`` is set). Computed once per sample: a step asks up to three times
        (:meth:`wants_prediction` before and in :meth:`observe`, the departure's start); what it depends on changes
        where :meth:`observe` appends to the history (the cache cleared there) and where a departure takes the held
        rest, just before that append."""
        if self._rest_of is False:
            self._rest_of = self._rest_now()
        return self._rest_of

    def _rest_now(self) -> tuple[float, float] | None:
        if len(self._history) < self.rest:
            return None
        valve, reading = np.array(self._history).T
        # np.ptp and np.mean without their Python wrappers: the reductions they run on the same 1-D views, so the
        # same numbers (tests/test_step_glue.py)
        if _max(reading) - _min(reading) > self.rest_tol_c:
            return None
        if _max(valve) - _min(valve) <= self.rest_tol_pct:
            n = valve.shape[0]
            rest = float(_sum(valve) / n), float(_sum(reading) / n)
            if self.rest_hold > 0:
                self._last_rest = (rest, self._samples)  # a rest of both, not one held
            return rest
        if self._last_rest is None or self._samples - self._last_rest[1] > self.rest_hold:
            return None
        held = self._last_rest[0]
        if abs(_sum(reading) / reading.shape[0] - held[1]) > self.rest_tol_c:
            return None  # the reading has moved on from the held rest's level: no departure from a stale level
        return held

    def wants_prediction(self, valve_a_after_pct: float) -> bool:
        """Whether :meth:`observe` will use this sample's predicted changes: a departure is under way, or this
        command begins one (valve a leaves its rest)."""
        if self._departure is not None:
            return True
        rest = self._rest()
        return rest is not None and abs(valve_a_after_pct - rest[0]) > self.rest_tol_pct

    def observe(self, reading_c: float, valve_a_after_pct: float, predicted_c: float = math.nan,
                other_predicted_c: float = math.nan) -> SignVerdict | None:
        """One sample: the supply reading (degC), valve a after this sample's command (%), and the change of the
        model air that command makes in the filter in use and in the other (degC; :func:`predicted_air_change_c`,
        needed where :meth:`wants_prediction`). A verdict where the departure under way is answered with the
        other sign (module docstring), else None."""
        if not math.isfinite(reading_c):
            return None
        self._rest()  # this sample's rest (a rest of both is kept for the hold) before the departure moves on
        verdict = self._follow(reading_c, valve_a_after_pct, predicted_c, other_predicted_c)
        if self._departure is None and verdict is None and self.wants_prediction(valve_a_after_pct):
            valve0, reading0 = self._rest()
            self._departure = _Departure(reading0, valve0, _finite(predicted_c), _finite(other_predicted_c))
            self._last_rest = None  # a held rest starts one departure at most
        self._history.append((valve_a_after_pct, reading_c))
        self._rest_of = False
        self._samples += 1
        return verdict

    def _follow(self, reading_c: float, valve_a_pct: float, predicted_c: float,
                other_predicted_c: float) -> SignVerdict | None:
        """The departure under way, if any, one sample on; a verdict where its answer has the other sign."""
        dep = self._departure
        if dep is None:
            return None
        dep.samples += 1
        verdict = None
        if abs(valve_a_pct - dep.valve_a_pct) >= self.move_pct:
            verdict = self._judge(reading_c - dep.reading_c, dep.predicted_c, dep.other_predicted_c)
        dep.predicted_c += _finite(predicted_c)  # this sample's command counts from the next sample on
        dep.other_predicted_c += _finite(other_predicted_c)
        if verdict is not None or dep.samples >= self.window:
            self._departure = None
        if verdict is not None:
            self.verdicts += 1
        return verdict

    def _judge(self, measured_c: float, predicted_c: float, other_predicted_c: float) -> SignVerdict | None:
        """A verdict where the reading moved by at least ``change_c`` and the filter in use's predicted change
        has the other sign (none predicted: no sign, no verdict)."""
        if abs(measured_c) < self.change_c:
            return None
        if predicted_c * measured_c >= 0.0:
            return None
        return SignVerdict(measured_c, predicted_c, other_predicted_c)


def _finite(value: float) -> float:
    return value if math.isfinite(value) else 0.0
