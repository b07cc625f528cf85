"""Whether the supply reading is still to show a response the filter's model has already made.

Where the box has a dead time the filter does not honour yet (none found: nothing has excited the estimate,
docs/robustness.md sec. 2.4), a large move of the controller's own makes the model's thermocouple state move at
once while the reading stays where it was for the dead time. The plain measurement update takes that difference
for a model error: the mixed-air offset integrates each sample of the missing response (on the independent box
with a 3 s dead time, a temperature step with the flow out of reach: +2.4 degC in four samples), the MPC answers
the offset with a larger move still, and when the response arrives the air overshoots the reference by more than
the step itself (docs/robustness.md sec. 2.17).

:class:`ResponseWait` tells the estimator when that is so, from the filter's own signals: the prediction of the
reading at the dead time honoured now (the estimate's candidate of :class:`~.dead_time.DeadTimeEstimator`, the
model's air without the offset through the thermocouple lag) and the reading. A wait starts at a sample whose
predicted change is at least ``trigger_c`` while the reading's change is less than ``share`` of it (in the
predicted direction), and only at the onset of the predicted change (:data:`ONSET_SHARE`). It ends once the dead
time the prediction honours moves (the filter then compares the reading with the model's state of that dead time
ago); at once where the reading's change since the wait began reaches ``share`` of the predicted one within
``min_samples`` (a dead time shorter than the filter honours), otherwise as many samples after that as the
response took to begin (the dead-time estimate ranks the response meanwhile); at once where the reading moves
against the prediction by ``share`` of it or stays put for ``max_samples`` (a model error, not a dead time: on the
built-in plant, whose split depends on the flow as the filter's model's does not, a flow change moved the
prediction and not the reading). While it waits the estimator leaves the supply reading out of its measurement
update: the model's states run open loop over the wait, the controller steers the response the model predicts (a
Smith predictor for the samples of the wait), and the offsets stay where they were. A box without a dead time shows
the response in the sample of the move (the thermocouple's lag moves the reading at once), so a wait starts there
only where the reading's noise or a model error hides that (sec. 2.17 has what that cost on the built-in plant).

A wait that ends as a model error (the reading moved against the prediction or stayed put too long) is evidence
that what the model predicts for a move of its own is not coming at the dead time honoured, and the next move of
the controller makes the same prediction: with ``rearm_samples`` no wait begins for that many samples after it
(``EkfSettings.response_wait_rearm_s``). Without it, on a box whose valve gain differs from the model's (its curves
shifted, a duct losing heat) with the dead time already found, each move the controller makes to answer the
offset starts a wait of ``max_samples`` again, and the offset stays where it was for most of a step
(docs/robustness.md sec. 2.19).
Pure Python, no model code: the estimator feeds it.
"""

from __future__ import annotations

import math


#: A wait begins only at the onset of a predicted change: the prediction's change in the sample before below this share
#: of ``trigger_c``. Within a transient already under way (the prediction moving for a while) a reading that stops
#: short of the model's is a model error, not a dead time (on the built-in plant, the second sample of a cooling
#: step: the reading settled 1.2 degC above the model's air while the model kept falling). ASSUMPTION: a half.
ONSET_SHARE = 0.5


class ResponseWait:
    """A wait for the reading to follow a predicted change (module docstring).

    Per sample :meth:`observe` with the prediction of the reading (degC), the reading (degC) and the dead time
    the prediction honours (samples); ``waiting`` is True while the reading is to be left out. ``trigger_c``
    (degC, > 0), ``share`` (in (0, 1]), ``min_samples`` (>= 1) and ``max_samples`` (>= ``min_samples``) as in the
    module docstring; no wait begins within the first ``after_samples`` samples after a reset (the filter's start-up,
    whose own corrections move the model's air while the reading does not). ``flat_c`` (degC, 0: no bound): a wait
    begins only where the reading's change in that sample is also at most this (a reading that stays put, as behind
    a dead time; a response smaller than the model's, a gain error, does not start one). ``rearm_samples`` (>= 0; 0:
    none): after a wait that ended as a model error, no wait begins for at least this many samples (counted on the
    samples that reach the onset test; a sample that returns early, a new dead time honoured or a reading that is
    not finite, does not count)."""

    def __init__(self, trigger_c: float, share: float, min_samples: int, max_samples: int, after_samples: int = 0,
                 flat_c: float = 0.0, rearm_samples: int = 0):
        if not trigger_c > 0.0:
            raise ValueError(f"ResponseWait: trigger_c must be > 0 degC, got {trigger_c}")
        if not 0.0 < share <= 1.0:
            raise ValueError(f"ResponseWait: share must be in (0, 1], got {share}")
        if not 1 <= int(min_samples) <= int(max_samples):
            raise ValueError(f"ResponseWait: need 1 <= min_samples <= max_samples, got {min_samples}, {max_samples}")
        self.trigger_c = float(trigger_c)
        self.share = float(share)
        self.min_samples = int(min_samples)
        self.max_samples = int(max_samples)
        self.after_samples = max(0, int(after_samples))
        self.flat_c = float(flat_c)
        if int(rearm_samples) < 0:
            raise ValueError(f"ResponseWait: rearm_samples must be >= 0, got {rearm_samples}")
        self.rearm_samples = int(rearm_samples)
        self.reset()

    def reset(self) -> None:
        """Forget the last sample and any wait."""
        self._last: tuple[float, float, float] | None = None  # (prediction, reading, dead time) of the last sample
        self._start: tuple[float, float, float] | None = None  # ... of the sample before the wait began
        self._samples = 0  # samples of the wait so far
        self._seen = 0  # samples observed since the reset
        self._last_dp = 0.0  # the prediction's change in the last sample (degC)
        self._end: int | None = None  # the wait's last sample, once known
        self.waits = 0  # waits begun since the reset
        self.model_errors = 0  # waits ended as a model error since the reset
        self._quiet = 0  # samples left in which no wait begins (after a model error, ``rearm_samples``)

    def stop(self) -> None:
        """End a wait under way and forget the last sample (the estimator does not wait for now:
        ``EkfSettings.response_wait_unseen_only``), so the next :meth:`observe` compares nothing from before; the
        counts and the re-arm's quiet time are kept."""
        self._start = None
        self._last = None
        self._last_dp = 0.0  # as after a reset

    @property
    def waiting(self) -> bool:
        return self._start is not None

    def _followed(self, predicted_c: float, read_c: float) -> bool:
        """The reading's change ``read_c`` is at least ``share`` of the predicted ``predicted_c``, same direction."""
        return read_c * math.copysign(1.0, predicted_c) >= self.share * abs(predicted_c)

    def _continue(self, prediction_c: float, reading_c: float, steps: float) -> None:
        """One more sample of the wait. It ends where the dead time honoured moved; where the reading moved against
        the prediction by ``share`` of it (a model error, not a dead time); where the reading stayed put for
        ``max_samples`` (longer than any dead time honoured); at once where the response began within
        ``min_samples`` (a dead time too short to honour); otherwise as many samples after the response began as it
        took to begin (the estimate of the dead time ranks the response meanwhile)."""
        self._samples += 1
        p0, y0, steps0 = self._start
        moved_c, read_c = prediction_c - p0, reading_c - y0
        if self._end is None:  # the response has not begun
            if self._followed(moved_c, read_c):
                self._end = 0 if self._samples <= self.min_samples else 2 * self._samples
            elif self._followed(-moved_c, read_c) or self._samples > self.max_samples:
                self._end = 0
                self._model_error()
        if steps != steps0 or (self._end is not None and self._samples > self._end):
            self._start = None

    def _model_error(self) -> None:
        """A wait ended as a model error: no wait begins for ``rearm_samples`` samples."""
        self.model_errors += 1
        self._quiet = self.rearm_samples

    def observe(self, prediction_c: float, reading_c: float, steps: float = 0.0) -> bool:
        """One sample's prediction of the reading, the reading and the dead time (samples) the prediction honours;
        returns :attr:`waiting` for this sample."""
        if not (math.isfinite(prediction_c) and math.isfinite(reading_c)):
            return self.waiting
        last, self._last = self._last, (float(prediction_c), float(reading_c), float(steps))
        if self._start is not None:
            self._continue(prediction_c, reading_c, float(steps))
            return self.waiting
        self._seen += 1
        if last is None or last[2] != float(steps) or self._seen <= self.after_samples:
            return False  # a new dead time honoured (its prediction is not comparable), or the filter's start-up
        dp = prediction_c - last[0]
        dy, onset = reading_c - last[1], abs(self._last_dp) < ONSET_SHARE * self.trigger_c
        self._last_dp = dp
        flat = self.flat_c <= 0.0 or abs(dy) <= self.flat_c
        armed, self._quiet = self._quiet <= 0, max(0, self._quiet - 1)
        if armed and abs(dp) >= self.trigger_c and onset and flat and not self._followed(dp, dy):
            self._start, self._samples, self._end = last, 1, None
            self.waits += 1
        return self.waiting
