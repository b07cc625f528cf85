"""Whether the supply reading is still to show a response the filter's model has already made.

Where the box has a dead time the filter does not honour yet (none found: nothing has excited the estimate,
docs/robustness.md sec. 2.4), a large move of the controller's own makes the model's thermocouple state move at
once while the reading stays where it was for the dead time. The plain measurement update takes that difference
for a model error: the mixed-air offset integrates each sample of the missing response (on the independent box
with a 3 s dead time, a temperature step with the flow out of reach: +2.4 degC in four samples), the MPC answers
the offset with a larger move still, and when the response arrives the air overshoots the reference by more than
the step itself (docs/robustness.md sec. 2.17).

:class:`ResponseWait` tells the estimator when that is so, from the filter's own signals: the prediction of the
reading at the dead time honoured now (the estimate's candidate of :class:`~.dead_time.DeadTimeEstimator`,
the model's air without the offset through the thermocouple lag) and the reading. A wait starts at a sample
whose predicted change is at least ``trigger_c`` while the reading's change is less than ``share`` of it (in the
predicted direction). It ends once the dead time the prediction honours moves (the filter then compares the
reading with the model's state of that dead time ago), at once where the reading's change since the wait began
reaches ``share`` of the predicted one within ``min_samples`` (a dead time shorter than the filter honours),
otherwise as many samples after that as the response took to begin (the dead-time estimate ranks the response
meanwhile), and after ``max_samples`` at the latest. While it waits the estimator leaves the supply reading out of its
measurement update: the model's states run open loop over the wait, the controller steers the response the
model predicts (a Smith predictor for the samples of the wait), and the offsets stay where the last rest left
them. A box without a dead time shows the response in the sample of the move (the thermocouple's lag moves the
reading at once), so no wait starts there but on the noise (a predicted change of 0.2 degC against a reading
noise of 0.05 degC: about one move in twelve, for a sample or two). Pure Python, no model code: the estimator
feeds it.
"""

from __future__ import annotations

import math


class ResponseWait:
    """A wait for the reading to follow a predicted change (module docstring).

    Per sample :meth:`observe` with the prediction of the reading (degC), the reading (degC) and the dead time
    the prediction honours (samples); ``waiting`` is True while the reading is to be left out. ``trigger_c``
    (degC, > 0), ``share`` (in (0, 1]), ``min_samples`` (>= 1) and ``max_samples`` (>= ``min_samples``) as in the
    module docstring."""

    def __init__(self, trigger_c: float, share: float, min_samples: int, max_samples: int):
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
        self.reset()

    def reset(self) -> None:
        """Forget the last sample and any wait."""
        self._last: tuple[float, float, float] | None = None  # (prediction, reading, dead time) of the last sample
        self._start: tuple[float, float, float] | None = None  # ... of the sample before the wait began
        self._samples = 0  # samples of the wait so far
        self._end = self.max_samples  # the wait's last sample
        self.waits = 0  # waits begun since the reset

    @property
    def waiting(self) -> bool:
        return self._start is not None

    def _followed(self, predicted_c: float, read_c: float) -> bool:
        """The reading's change ``read_c`` is at least ``share`` of the predicted ``predicted_c``, same direction."""
        return read_c * math.copysign(1.0, predicted_c) >= self.share * abs(predicted_c)

    def _continue(self, prediction_c: float, reading_c: float, steps: float) -> None:
        """One more sample of the wait: it ends where the dead time honoured moved, at its last sample, or at once
        where the response began within ``min_samples`` (a dead time too short to honour); a response that began
        later keeps the wait for as long again (the estimate of the dead time ranks it meanwhile)."""
        self._samples += 1
        p0, y0, steps0 = self._start
        if self._end == self.max_samples and self._followed(prediction_c - p0, reading_c - y0):
            self._end = 0 if self._samples <= self.min_samples else min(2 * self._samples, self.max_samples)
        if steps != steps0 or self._samples > self._end:
            self._start = None

    def observe(self, prediction_c: float, reading_c: float, steps: float = 0.0) -> bool:
        """One sample's prediction of the reading, the reading and the dead time (samples) the prediction honours;
        returns :attr:`waiting` for this sample."""
        if not (math.isfinite(prediction_c) and math.isfinite(reading_c)):
            return self.waiting
        last, self._last = self._last, (float(prediction_c), float(reading_c), float(steps))
        if self._start is not None:
            self._continue(prediction_c, reading_c, float(steps))
            return self.waiting
        if last is None or last[2] != float(steps):  # a new dead time honoured: its prediction is not comparable
            return False
        dp = prediction_c - last[0]
        if abs(dp) >= self.trigger_c and not self._followed(dp, reading_c - last[1]):
            self._start, self._samples, self._end = last, 1, self.max_samples
            self.waits += 1
        return self.waiting
