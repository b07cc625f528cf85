"""Where the heater outlet reading's error goes, chosen online: two filters compared by their innovations.

The heater outlet reading differs from the model's air for two reasons the model cannot tell apart from that
reading alone: the core leaves the air warmer or colder than the model's (the thesis cooler fit taken literally,
docs/robustness.md sec. 2.13), which an offset of the air leaving the heater carries at every valve a position
(``EkfSettings.q_heater_air_offset_c``), or the heater's own transfer differs (the built-in plant's perturbed kA),
which changes with the core flow and which the reading's own offset keeps out of the prediction
(``q_heater_outlet_offset_c``, the default). Both filters run on the same readings and commands; each keeps the
normalised square of its supply innovation (:attr:`~.estimator.DisturbanceEkf.supply_nis`), capped at ``cap`` (a
start-up transient or a dead time not yet found surprises both alike and would decide the sums for a minute), in a
sum that forgets with ``window_s``. The prediction uses the filter whose sum is lower than ``ratio`` times the other's while the
filter in use is itself inconsistent (its sum above ``evidence`` times the sum a consistent filter would have,
the window's length in samples); the same rule takes it back (hysteresis: ``ratio`` < 1 each way), multiple-model
estimation with two models and a hard choice. With a finite ``margin`` the filter in use (inconsistent, as above)
also gives way where its sum exceeds the other's by more than ``margin``: the difference of the sums is twice the
log-likelihood ratio of the two filters' innovations over the window (each sample capped), which a start-up that
surprises both alike leaves unchanged, where it inflates both sums and so delays the ratio's switch
(docs/robustness.md sec. 2.15). With a ``hold`` (samples) the two filters' innovations count only in pairs, the
same sample's of each, and only where neither filter's honoured dead time changed within the last ``hold`` samples:
a filter that has just moved the sample its supply reading is compared with is surprised by that move for about the
thermocouple's lag, which is no evidence of where the heater outlet's error sits (docs/robustness.md sec. 2.16).

ASSUMPTION: the filter whose supply readings surprise it less predicts the supply air better, valve a's gain
included: the filters differ where the core flow moves, and only there do their innovations differ (at rest each
has taken its error into its offsets). The numbers (``window_s``, ``ratio``, ``evidence``, ``cap``) are chosen on the
boxes of docs/robustness.md sec. 2.14, not tuned over many.
"""

from __future__ import annotations

import math

#: The filters, in the order of :attr:`PlacementChoice.active`: the reading's own offset, the heater air's.
PLACEMENTS = ("heater_outlet", "heater_air")
#: A trial after :meth:`PlacementChoice.force` ends (the full floor again) after this many windows, where a
#: consistent filter's forgetting sum is within 1 - exp(-3) = 95 % of its steady value.
TRIAL_FULL = 3.0


class PlacementChoice:
    """The choice between two filters from their supply innovations (module docstring)."""

    def __init__(self, window_s: float, ratio: float, evidence: float, dt_s: float, cap: float = math.inf,
                 margin: float = math.inf, hold: int = 0):
        self.forget = math.exp(-dt_s / window_s)
        self.window_steps = window_s / dt_s
        self.cap = float(cap)  # the most one sample adds
        self.ratio = float(ratio)
        self.margin = float(margin)  # a lead of the other's sum that switches whatever the ratio (inf: none)
        self.floor = float(evidence) * window_s / dt_s  # a consistent filter's sum, times evidence
        self.hold = int(hold)  # samples after a change of either filter's honoured dead time that count nothing (0: off)
        self.trial_steps: int | None = None  # after force(): decisions since (the floor counts from it); None: none
        self._trial_floors: dict[int, float] = {}  # trial_floor by decisions since force(), each computed once
        self.reset()

    def reset(self) -> None:
        """Forget both sums, back to the first filter."""
        self.restart()
        self.active = 0
        self.trial_steps = None

    def restart(self) -> None:
        """Forget both sums (a filter started afresh: its first innovations are no evidence), keeping the filter
        in use."""
        self.sums = [0.0, 0.0]
        self._pending = None  # with a hold: the filter in use's (nis, dead time) of the last sample, not yet paired
        self._dead_times = [0.0, 0.0]  # with a hold: each filter's honoured dead time at its last paired sample (s)
        self._steady = 0  # with a hold: paired samples since either honoured dead time last changed

    def observe(self, index: int, nis: float, dead_time_s: float = 0.0) -> None:
        """The normalised square innovation of filter ``index`` at one sample (nan: no reading, nothing added) and
        the dead time (s) its supply reading was compared at (used with a ``hold`` only). With a hold the filter in
        use reports a sample first and the other the same sample next: the pair counts, or neither does."""
        if self.hold <= 0:
            self._add(index, nis)
        elif index == self.active:
            self._pending = (nis, dead_time_s)
        elif self._pending is not None:
            (mine, my_dead), self._pending = self._pending, None
            self._observe_pair(mine, my_dead, nis, dead_time_s)

    def _add(self, index: int, nis: float) -> None:
        if math.isfinite(nis):
            self.sums[index] = self.forget * self.sums[index] + min(nis, self.cap)

    def _observe_pair(self, mine: float, my_dead_s: float, other: float, other_dead_s: float) -> None:
        """One sample of both filters (the one in use first): counted where both have a reading and neither honoured
        dead time changed within the last ``hold`` samples."""
        dead = [0.0, 0.0]
        dead[self.active], dead[1 - self.active] = my_dead_s, other_dead_s
        if dead != self._dead_times:
            self._dead_times, self._steady = dead, 0
        else:
            self._steady += 1
        if self._steady >= self.hold and math.isfinite(mine) and math.isfinite(other):
            self._add(self.active, mine)
            self._add(1 - self.active, other)

    def force(self) -> None:
        """Switch to the other filter whatever the sums say, and forget both (the evidence that decided it is of
        another kind: the sign of valve a's answer, :mod:`~.sign_check`). The switch is a trial: until the sums
        have had :data:`TRIAL_FULL` windows the floor counts from here (:func:`trial_floor`), so the filter left
        takes the prediction back as soon as its innovations show it the better one, not a window later (a wrong
        sign may pass: the heater body warming after a step, docs/robustness.md sec. 2.28)."""
        self.active = 1 - self.active
        self.restart()
        self.trial_steps = 0

    def decide(self) -> bool:
        """Switch to the other filter where the rule says so; True where it switched."""
        mine, other = self.sums[self.active], self.sums[1 - self.active]
        if mine > self._floor() and (other < self.ratio * mine or mine - other > self.margin):
            self.active = 1 - self.active
            self.trial_steps = None
            return True
        return False

    def _floor(self) -> float:
        """The sum of the filter in use above which a switch is considered: ``evidence`` times a consistent filter's
        sum over the window; on trial after :meth:`force` (the sums forgotten there) the sum a consistent filter
        passes over the decisions since as seldom as it passes that floor over the window (:func:`trial_floor`)."""
        if self.trial_steps is None:
            return self.floor
        self.trial_steps += 1
        if self.trial_steps >= TRIAL_FULL * self.window_steps:
            self.trial_steps = None
            return self.floor
        if self.trial_steps not in self._trial_floors:
            self._trial_floors[self.trial_steps] = trial_floor(self.floor, self.forget, self.trial_steps)
        return self._trial_floors[self.trial_steps]


def trial_floor(floor: float, forget: float, steps: int) -> float:
    """The floor of a sum started afresh ``steps`` samples ago: the value a consistent filter's sum (normalised
    squares of its innovations, chi-square with one degree each, forgotten by ``forget`` per sample) exceeds as
    seldom as its steady sum exceeds ``floor``. A floor scaled with the samples alone would let one or two samples of
    a consistent filter decide (one normalised square exceeds 1.5 in 22 % of samples); this one asks of a few
    samples the confidence the window's floor asks of the window. ASSUMPTION: a forgetting sum of chi-square terms
    is taken as a scaled chi-square with its first two moments (Satterthwaite)."""
    from scipy.stats import chi2  # the sign check's (off by default), which loads it when it is built

    rare = chi2.sf(floor / _scale(forget, math.inf), _degrees(forget, math.inf))
    return float(_scale(forget, steps) * chi2.isf(rare, _degrees(forget, steps)))


def _weights(forget: float, steps: float) -> tuple[float, float]:
    """The sums of the forgetting weights and of their squares over ``steps`` samples (inf: steady)."""
    return (1.0 - forget ** steps) / (1.0 - forget), (1.0 - forget ** (2.0 * steps)) / (1.0 - forget ** 2)


def _degrees(forget: float, steps: float) -> float:
    """The degrees of freedom of the scaled chi-square with the forgetting sum's moments."""
    s1, s2 = _weights(forget, steps)
    return s1 * s1 / s2


def _scale(forget: float, steps: float) -> float:
    """The scale of the scaled chi-square with the forgetting sum's moments."""
    s1, s2 = _weights(forget, steps)
    return s2 / s1
