"""Online estimate of a dead time between the model's mixed air and the supply thermocouple.

A bank of candidate delays D = 0, 1/2, 1, ..., ``max_steps`` samples. Each candidate passes the
model's mixed-air temperature (the estimator's model, without its offset state), delayed by D
samples (linear interpolation between samples), through the thermocouple's first-order lag (tau
from the parameters), and is ranked by how well its change from sample to sample explains the
change of the thermocouple reading over a sliding window (exponential forgetting): the residual
of the least-squares fit ``d reading ~ gain * d candidate``. Changes, not levels, so that an
offset and a slow drift (a cabin warming the inlet air) decide nothing, and a fitted gain so that
a gain error of the model (a cooler fit, a duct loss) does not either: only the timing of a
response does. docs/robustness.md sec. 2.1.

The estimate moves only when the window holds a response (the root mean square of the candidates'
changes over the window above ``min_excitation_c`` per sample) and another candidate explains the
reading clearly better than the current one (residual below ``switch_ratio`` times the current
one's), or one that stays ahead of it (below ``LEAD_RATIO`` times its residual) for ``LEAD_SAMPLES``
samples in a row (with ``lead_reach_steps`` > 0, a leader within that many samples of the one before continues the
row: the same minimum's neighbouring half sample does not restart it; with ``count_quiet``, samples without
excitation count for a lead that stands; with ``lead_tie_hold``, an estimate the lead rule moved to gives way to a
tie only within that reach, else to a clearly better candidate or another lead); while nothing moves it stays where
it is. Of
separate minima that explain the reading about equally (within ``TIE_RATIO``) the shortest is taken, of one minimum
its bottom
(:func:`shortest_tied_minimum`; docs/robustness.md sec. 2.11); with ``prefer_longest`` (set by the filter for
``EkfSettings.dead_time_step_longest_s`` after a change of the reference) the longest, where it is longer than the
estimate (:func:`longest_tied_minimum`; sec. 2.46). A starting value (``initial_steps``, or
``prior_steps`` where none is given) gives way only to a clearly better candidate, not to a tie.
Pure numpy, no model code: the estimator feeds it.
"""

from __future__ import annotations

import math

import numpy as np

from .arrays import min_reduce

#: A candidate that stays ahead of the estimate (residual below LEAD_RATIO times its) for LEAD_SAMPLES
#: samples in a row after the first takes over (samples without excitation neither count nor break the row),
#: however flat the ranking: a response the model's air explains poorly
#: (a gain or shape error) never makes the true dead time "clearly" better, only persistently so.
#: ASSUMPTION: 0.9 and 20 samples (a third of the window), not tuned.
LEAD_RATIO = 0.9
LEAD_SAMPLES = 20
#: Candidates whose residual is within this factor of the least count as explaining the reading
#: equally; the shortest of them is taken.
TIE_RATIO = 1.1
#: Rows of the estimator's sums: each candidate's squared change, and its change times the reading's.
SSS, SSY = 0, 1


def tied_minima(res: np.ndarray) -> np.ndarray:
    """Which candidates are local minima of the residuals ``res`` within TIE_RATIO of the least one (bool array)."""
    res = np.maximum(res, 0.0)  # a least-squares residual, >= 0 but for round-off
    tied = res <= TIE_RATIO * min_reduce(res)
    right, left = res[1:], res[:-1]
    tied[1:] &= right <= left  # lower than (or as low as) the left neighbour; the first has none
    tied[:-1] &= left <= right  # ... and the right one; the last has none
    return tied


def shortest_tied_minimum(res: np.ndarray) -> int:
    """Index of the shortest local minimum of the residuals within TIE_RATIO of the least one.

    A loop that rang on a wrong dead time leaves data that longer candidates, a period later, explain
    about as well: separate minima, of which the shortest is taken. Within one minimum its bottom is
    taken, not its shorter flank: a response the model's air explains poorly (a gain or shape error)
    flattens the residuals around the true dead time, and the flank's shorter delays are the ones
    that make the loop ring."""
    tied = tied_minima(res)
    first = int(tied.argmax())  # the first True: there is one (the least residual's) unless a residual is nan
    if not tied[first]:
        raise IndexError("shortest_tied_minimum: no minimum among non-finite residuals")
    return first


def is_flat(res: np.ndarray) -> bool:
    """Whether every candidate's residual is within TIE_RATIO of the least one: a ranking that tells no candidate from
    another (its "separate minima" the reading's noise, the last candidate one for want of a right neighbour)."""
    res = np.maximum(res, 0.0)
    return bool(np.max(res) <= TIE_RATIO * min_reduce(res))


def longest_tied_minimum(res: np.ndarray) -> int:
    """Index of the longest local minimum of the residuals within TIE_RATIO of the least one (of one minimum its
    bottom, as :func:`shortest_tied_minimum`): the rule while :attr:`DeadTimeEstimator.prefer_longest` is set."""
    tied = tied_minima(res)
    last = tied.size - 1 - int(tied[::-1].argmax())  # the last True
    if not tied[last]:
        raise IndexError("longest_tied_minimum: no minimum among non-finite residuals")
    return last


class DeadTimeEstimator:
    """Rank candidate dead times 0..``max_steps`` samples (in half samples) by the thermocouple
    prediction error.

    Per sample: :meth:`push_air` with the model's mixed air over the coming sample (degC), then,
    one sample later, :meth:`observe` with the thermocouple reading (degC). ``steps`` is the
    current estimate in samples (a multiple of 1/2), ``seconds`` in s.
    """

    #: Candidates per sample.
    SUBDIVISION = 2

    def __init__(self, max_steps: int, sensor_tau_s: float, dt_s: float = 1.0, window_s: float = 60.0,
                 min_excitation_c: float = 0.05, switch_ratio: float = 0.7, initial_steps: float = 0.0,
                 prior_steps: float = 0.0, lead_reach_steps: float = 0.0, count_quiet: bool = False,
                 lead_tie_hold: bool = False, first_settle_steps: float = 0.0,
                 longest_reach_moves: bool = False, longest_not_flat: bool = False):
        """``initial_steps``: the estimate before the readings move it (samples; e.g. a delay identified from
        a log, docs/identification.md), rounded to the nearest candidate; it gives way only to a clearly
        better candidate, not to a tie. ``prior_steps``: the same for a dead time assumed, not identified,
        where no ``initial_steps`` is given (samples). ``lead_reach_steps``: how far (samples) the candidate
        ahead of the estimate may move from one sample to the next and still continue the lead's count (0: only
        the same candidate, the rule before; 0.5: its neighbouring half samples; docs/robustness.md sec. 2.38).
        ``count_quiet``: a sample without excitation adds to the count of a candidate that stands ahead (False: it
        neither counts nor breaks the row, the rule before); the switch itself still waits for a ranked sample in
        which that candidate is ahead. ``lead_tie_hold``: an estimate the lead rule switched to gives way only to a
        clearly better candidate, another lead, or a tie within ``lead_reach_steps`` (its minimum's bottom moving to
        the neighbour), not to a shorter tie farther away, another minimum (False: to any tie, the rule before): on a
        flat ranking the tie rule otherwise takes the estimate back to 0 within samples. ``first_settle_steps``
        (samples; 0: off, the rule before): up to this many ranked samples, the first counted (the window's first
        response; the 2nd to the N-th settle), and not while ``prefer_longest`` is set, the least residual's minimum
        (of tied separate minima the shortest, as the tie rule) is taken wherever it explains the reading better than
        the estimate, longer or shorter (:meth:`_settle`; docs/robustness.md sec. 2.47). ``longest_reach_moves``:
        while ``prefer_longest`` is set a shorter tie within ``lead_reach_steps`` (the same minimum's bottom) still
        moves the estimate down (False: none does, sec. 2.46; docs/robustness.md sec. 2.48). ``longest_not_flat``: while
        ``prefer_longest`` is set the longest tie is taken only from a ranking that is not flat (some candidate's
        residual above ``TIE_RATIO`` times the least, :func:`is_flat`; False: from any ranking, sec. 2.46;
        docs/robustness.md sec. 2.50)."""
        self.first_settle_steps = float(first_settle_steps)
        self.lead_reach_steps = float(lead_reach_steps)
        self.count_quiet = bool(count_quiet)
        self.lead_tie_hold = bool(lead_tie_hold)
        self.longest_reach_moves = bool(longest_reach_moves)
        self.longest_not_flat = bool(longest_not_flat)
        self.initial_steps = float(initial_steps)
        self.prior_steps = float(prior_steps)
        self.max_steps = int(max_steps)
        self.dt_s = float(dt_s)
        self.lag = math.exp(-self.dt_s / float(sensor_tau_s))  # exact first-order lag over one sample
        self._lag_c = 1.0 - self.lag
        self.forget = math.exp(-self.dt_s / float(window_s))
        self.min_var = float(min_excitation_c) ** 2
        self.switch_ratio = float(switch_ratio)
        self.reset()

    def reset(self) -> None:
        n = self.SUBDIVISION * self.max_steps + 1
        self.candidates = np.arange(n) / self.SUBDIVISION  # samples
        self._i0 = np.floor(self.candidates).astype(int)
        self._w1 = self.candidates - self._i0
        self._w0 = 1.0 - self._w1  # the weights of the two samples around each candidate's delay
        self._i1 = np.minimum(self._i0 + 1, self.max_steps)
        start = self.initial_steps if self.initial_steps > 0.0 else self.prior_steps
        self._best = int(np.argmin(np.abs(self.candidates - start)))
        self._at_start = self._best > 0  # still at a given starting value
        self._air = None  # model air, newest first (max_steps + 1 samples)
        self._pred = np.zeros(n)  # each candidate's predicted reading for the next sample
        self._last_pred = None  # ... and for the sample before
        self._last_reading = None
        self._w = 0.0
        self._syy = 0.0
        # the forgetting sums of each candidate's squared change (row SSS) and of its change times the reading's
        # (row SSY), and a buffer of the changes of the sample (row SSS: the candidate's, row SSY: the reading's)
        self._sums = np.zeros((2, n))
        self._moves = np.zeros((2, n))
        self.residuals = np.full(n, np.nan)
        self.informed = False  # the window has held a response (the candidates ranked at least once)
        self._lead = None  # a candidate ahead of the estimate by LEAD_RATIO ...
        self._lead_samples = 0  # ... for this many samples in a row
        self._by_lead = False  # the estimate is one the lead rule moved to (not a clearly better one)
        self._ranked = 0  # ranked samples so far (the first_settle_steps' count)
        #: set by the filter for each sample within ``EkfSettings.dead_time_step_longest_s`` after a change of the
        #: reference: a longer tied minimum than the estimate is moved to (:meth:`_rank`)
        self.prefer_longest = False

    @property
    def steps(self) -> float:
        return float(self.candidates[self._best])

    @property
    def seconds(self) -> float:
        return self.steps * self.dt_s

    def prediction_c(self, steps: float) -> float:
        """The prediction of the reading last observed (or next, before :meth:`observe`) by the candidate of
        ``steps`` samples (degC; the model's air without its offset, through the thermocouple lag; nan before
        any air)."""
        if self._air is None:
            return math.nan
        at = float(steps) * self.SUBDIVISION
        if 0.0 <= at <= self._pred.size - 1 and at.is_integer():  # a candidate's own delay: its index (they are
            return float(self._pred[int(at)])                     # distinct multiples of 1/SUBDIVISION)
        return float(self._pred[int(np.argmin(np.abs(self.candidates - float(steps))))])

    def push_air(self, air_c: float) -> None:
        """The model's mixed-air temperature held over the coming sample (degC)."""
        if not math.isfinite(air_c):
            return
        if self._air is None:
            self._air = np.full(self.max_steps + 1, air_c)
            self._pred[:] = air_c
            self._last_pred = self._pred.copy()
        else:
            self._last_pred = self._pred  # no copy: the line below makes the next prediction a new array
            self._air[1:] = self._air[:-1]  # newest first (numpy copies overlapping slices correctly)
            self._air[0] = air_c
        delayed = self._w0 * self._air[self._i0] + self._w1 * self._air[self._i1]
        self._pred = self.lag * self._pred + self._lag_c * delayed

    def _within_reach(self, a: int, b: int) -> bool:
        """Whether candidates ``a`` and ``b`` (indices) are within ``lead_reach_steps`` samples of each other."""
        return abs(a - b) <= self.lead_reach_steps * self.SUBDIVISION + 1e-9  # the reach in candidates (half samples)

    def _continues_lead(self, lead: int | None) -> bool:
        """Whether the candidate ahead of the estimate now (index; None: none) continues the count of the one
        ahead before: the same candidate, or one within ``lead_reach_steps`` samples of it."""
        return lead is not None and self._lead is not None and self._within_reach(lead, self._lead)

    def observe(self, reading_c: float) -> float:
        """Score every candidate on a thermocouple reading; returns the estimate (samples)."""
        if self._air is None or not math.isfinite(reading_c):
            return self.steps
        y, last = float(reading_c), self._last_reading
        self._last_reading = y
        if last is None:
            return self.steps
        f, dy = self.forget, y - last
        self._w = f * self._w + 1.0
        self._syy = f * self._syy + dy * dy
        # both sums in one pass: f * sss + ds * ds and f * ssy + ds * dy (the same operations as apart)
        moves = self._moves
        move_s = moves[SSS]  # a view of row SSS, taken here so a copy of the estimator keeps its own
        np.subtract(self._pred, self._last_pred, out=move_s)
        moves[SSY] = dy
        sums = f * self._sums
        sums += moves * move_s
        self._sums = sums
        w, sss, ssy = self._w, sums[SSS], sums[SSY]
        if min_reduce(sss) / w < self.min_var:
            self.residuals[:] = np.nan
            if self.count_quiet and self._lead is not None:  # nothing ranked: the lead stands, its time counts
                self._lead_samples += 1
            return self.steps
        self.informed = True
        # least-squares gain per candidate, syy - ssy^2 / sss; a response of the wrong sign (ssy <= 0) explains
        # nothing: its residual is syy less 0
        explained = np.maximum(ssy, 0.0)
        explained *= explained
        explained /= sss
        res = self._syy - explained
        self.residuals = res / w
        return self._rank(res)

    def _take_longest_tie(self, res: np.ndarray) -> bool:
        """Move the estimate to the longest tied minimum where that is longer than the estimate (a starting value
        included: it then no longer holds as one; held against a shorter tie afterwards as a lead-made estimate, with
        ``lead_tie_hold`` only; while ``prefer_longest`` is set a shorter
        tie moves no estimate down, :meth:`_rank`); whether it moved. ASSUMPTION: right
        after a change of the reference the controller's own moves are the response; where separate minima explain
        it equally, the longer dead time is the loop's safe side (a plan on too short a one rings, docs/robustness.md
        sec. 2.3-2.4; on too long a one it is slower). docs/robustness.md sec. 2.46. With ``longest_not_flat`` a flat
        ranking (:func:`is_flat`) moves nothing here: it holds no response that tells the candidates apart (the built-in
        chiller step's, made at rest before the step and taken on the step's own sample: 6.0 s, the last candidate;
        docs/robustness.md sec. 2.50)."""
        if self.longest_not_flat and is_flat(res):
            return False
        longest = longest_tied_minimum(res)
        if longest <= self._best:
            return False
        self._at_start = False
        self._move_to(longest, by_lead=True)
        return True

    def _move_to(self, best: int, by_lead: bool) -> None:
        """Make candidate ``best`` the estimate (``by_lead``: as the lead rule's, held against a shorter tie with
        ``lead_tie_hold``) and start the lead's count afresh."""
        self._best, self._by_lead = best, by_lead
        self._lead, self._lead_samples = None, 0

    def _settle(self, res: np.ndarray) -> bool:
        """From the second to the ``first_settle_steps``-th ranked sample (a starting value aside: it gives way only
        to a clearly better candidate; not while ``prefer_longest`` is set, whose window rule governs), move the
        estimate to the least residual's minimum (the tie rule's, of separate tied minima the shortest) where its
        residual is below the estimate's, longer or shorter; whether it did. ASSUMPTION: the window's first ranked
        samples hold the onset of the first response only, whose least residual moves over the next samples (a sensor
        lag or a valve gain the model's air lacks shapes an onset more than a whole response): the first switch is the
        clearly better rule's on the onset, and the lead rule's 20 samples would otherwise keep an onset's estimate
        through the next stroke (docs/robustness.md sec. 2.47)."""
        settling = 1 < self._ranked <= self.first_settle_steps + 1e-9
        if not settling or self._at_start or self.prefer_longest:
            return False
        best = shortest_tied_minimum(res)
        if best == self._best or not float(res[best]) < float(res[self._best]):
            return False
        self._move_to(best, by_lead=False)
        return True

    def _rank(self, res: np.ndarray) -> float:
        """Move the estimate on the candidates' residuals ``res`` of a ranked sample (the switch, the tie and the lead
        rules); returns the estimate (samples)."""
        self._ranked += 1
        if self.prefer_longest and self._take_longest_tie(res):
            return self.steps
        if self._settle(res):
            return self.steps
        best = shortest_tied_minimum(res)
        cur = self._best
        r_best, r_cur = float(res[best]), float(res[cur])
        # a starting value (initial_steps) gives way only to a clearly better candidate, not to a tie
        lead_held = self.lead_tie_hold and self._by_lead and not self._within_reach(best, cur)
        held_against_tie = self._at_start or lead_held
        # after a change of the reference (prefer_longest) a shorter tie does not move the estimate down
        # (with longest_reach_moves, one within lead_reach_steps still does: the same minimum's bottom)
        longest_blocks = self.prefer_longest and not (self.longest_reach_moves and self._within_reach(best, cur))
        tie_moves = best < cur and r_best <= r_cur and not held_against_tie and not longest_blocks
        lead = best if best != cur and r_best < LEAD_RATIO * r_cur else None
        self._lead_samples = self._lead_samples + 1 if self._continues_lead(lead) else 0
        self._lead = lead
        held = self._lead_samples >= LEAD_SAMPLES and not self._at_start  # a starting value: only clearly
        clearly = r_best < self.switch_ratio * r_cur
        if clearly or tie_moves or held:
            self._at_start = self._at_start and best == cur
            # a lead-made estimate stays one across a tie within reach (its minimum's bottom moving to the neighbour)
            kept = self._by_lead and tie_moves and not clearly and self._within_reach(best, cur)
            self._move_to(best, by_lead=(held and not clearly) or kept)
        return self.steps
