"""Whether the loop rings: the supply reading swinging about its reference, and the detuning that answers it.

A model whose gain is not the box's (on a box outside the registry: the literal cooler fit warms winter air to
about 10 C whatever the inlet, so valve a's effect on the supply air is not the model's, docs/robustness.md
sec. 2.12) makes the MPC's moves wrong in size; behind a dead time the loop then rings, each swing answered by a
move of valve a and the heater to the other end, and the filter's mixed-air offset following each swing.
:class:`RingGate` counts the swings of the supply error (reading minus reference) across a band of
``amplitude_c`` either side (hysteresis: the sensor's noise crosses no band) and calls the loop ringing when
``crossings`` of them fall within ``window_s``; a step answered with an overshoot makes one, a damped one two, a
sustained oscillation one per half period. While it rings :attr:`factor` is multiplied by ``detune`` at each
further crossing down to ``floor``; the controller limits valve a's and the heater's moves to that share of their
rates, so a swing of the error can no longer be answered by a full stroke within the dead time: the loop's gain
at the ringing period is lowered until the swings stop. Without a crossing for ``relax_s`` the factor recovers,
doubling every ``relax_s`` up to 1.

ASSUMPTION: a sustained oscillation of the supply error of more than ``amplitude_c`` is the loop's own (a gain
wrong for its dead time), not the box's; the numbers (0.6 C, 3 crossings in 40 s, halving, a floor of 0.05, 30 s)
are chosen on the traced boxes of sec. 2.12, not tuned over many. Pure python, no model code.
"""

from __future__ import annotations

import math
from collections import deque


class RingGate:
    """Counts the supply error's swings across ``+-amplitude_c`` (degC) and keeps the rate limits' factor.

    Per sample :meth:`push` the supply reading and its reference (degC; a non-finite reading is skipped);
    :attr:`factor` is in [``floor``, 1]: 1 while the loop does not ring.
    """

    def __init__(self, amplitude_c: float, window_s: float, crossings: int, detune: float, floor: float,
                 relax_s: float, dt_s: float = 1.0):
        self.amplitude_c = float(amplitude_c)
        self.window_s = float(window_s)
        self.crossings = int(crossings)
        self.detune = float(detune)
        self.floor = float(floor)
        self.relax_s = float(relax_s)
        self.dt_s = float(dt_s)
        self.reset()

    def reset(self) -> None:
        """Forget the swings: the factor back to 1."""
        self.factor = 1.0
        self._side = 0  # +1 above the band, -1 below, 0 not yet outside it
        self._t = 0.0
        self._since_crossing_s = math.inf
        self._times: deque[float] = deque()

    def _crossed(self, error_c: float) -> bool:
        """Whether the error left the band on the side opposite to its last exit (a swing)."""
        side = 1 if error_c > self.amplitude_c else (-1 if error_c < -self.amplitude_c else 0)
        if side == 0:
            return False
        crossed = self._side != 0 and side != self._side
        self._side = side
        return crossed

    def push(self, reading_c: float, reference_c: float) -> None:
        """One sample: the supply reading and its reference (degC)."""
        self._t += self.dt_s
        self._since_crossing_s += self.dt_s
        if not (math.isfinite(reading_c) and math.isfinite(reference_c)):
            return
        if self._crossed(reading_c - reference_c):
            self._times.append(self._t)
            self._since_crossing_s = 0.0
        while self._times and self._times[0] <= self._t - self.window_s:
            self._times.popleft()
        if self._since_crossing_s == 0.0 and len(self._times) >= self.crossings:
            self.factor = max(self.floor, self.factor * self.detune)
        elif self._since_crossing_s >= self.relax_s and self.factor < 1.0:
            self.factor = min(1.0, self.factor * 2.0 ** (self.dt_s / self.relax_s))

    @property
    def ringing(self) -> bool:
        """Whether the last ``window_s`` held ``crossings`` swings or more."""
        return len(self._times) >= self.crossings
