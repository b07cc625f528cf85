"""Whether the filter is at rest: its model's air and flow and its mixed-air offset have stayed put over a window.

The estimator's random walks (the mixed-air offset, the thermocouple state's process noise) stand for the
model's error, and that error is made where the model moves: a temperature step, a flow change. At rest the
model's error is a constant the offset has already taken, and what moves the supply reading from sample to
sample is its own noise; there the filter's gain for that reading passes the noise on to the commands, and on
the independent box with the flow out of reach most of both controllers' IAE is that noise
(docs/robustness.md sec. 2.10). :class:`RestGate` tells the estimator when that is so, from the model's own
signals: over the last ``window_s`` the model's air at the thermocouple (without the offset) has moved by at most
``air_band_c`` (the mean of the window's last quarter against that of its first), the natural log of its volume
flow has stayed within ``log_flow_band``, and the mixed-air offset has moved by at most ``offset_band_c`` from the
window's first sample to its last (a model error that still drifts, as after a flow change on a box whose split
depends on the flow, is not rest: the offset must follow it). The MPC's own small moves at rest (the noise it
answers) stay within the bands; a step of the reference or of the flow, or the heater body's creep, does not.
Pure numpy, no model code: the estimator feeds it.
"""

from __future__ import annotations

import math
from collections import deque


class RestGate:
    """Rest of the model's air and flow and of the mixed-air offset over the last ``window_s`` (s; samples of ``dt_s``).

    Per sample :meth:`push` with the model's air (degC) and volume flow (m3/s) of the time update and the offset;
    ``at_rest``
    is True once a whole window has been pushed since :meth:`reset` and the air's drift over it is at most
    ``air_band_c`` (degC), the range of ln of the flow at most ``log_flow_band`` and the offset's net change over
    it at most ``offset_band_c`` (degC).
    """

    def __init__(self, window_s: float, air_band_c: float, log_flow_band: float, offset_band_c: float,
                 dt_s: float = 1.0):
        self.n = max(1, int(round(float(window_s) / float(dt_s))))
        self.air_band_c = float(air_band_c)
        self.log_flow_band = float(log_flow_band)
        self.offset_band_c = float(offset_band_c)
        self.reset()

    def reset(self) -> None:
        """Forget the window: not at rest until a whole one has been pushed."""
        self._air: deque[float] = deque(maxlen=self.n)
        self._log_flow: deque[float] = deque(maxlen=self.n)
        self._offset: deque[float] = deque(maxlen=self.n)

    def _air_drift(self) -> float:
        """How far the model's air moved over the window: the difference of the means of its first and last
        quarters (the MPC's own moves at rest average out, a step or a creep does not)."""
        q = max(1, self.n // 4)
        air = list(self._air)
        return abs(sum(air[-q:]) - sum(air[:q])) / q

    def push(self, air_c: float, flow_m3s: float, offset_c: float) -> None:
        """The model's air at the thermocouple (degC) and its volume flow (m3/s) over the coming sample, and the
        mixed-air offset (degC) the last measurement update left."""
        self._air.append(float(air_c))
        self._log_flow.append(math.log(max(float(flow_m3s), 1e-4)))
        self._offset.append(float(offset_c))

    @property
    def at_rest(self) -> bool:
        if len(self._air) < self.n:
            return False
        return (self._air_drift() <= self.air_band_c
                and max(self._log_flow) - min(self._log_flow) <= self.log_flow_band
                and abs(self._offset[-1] - self._offset[0]) <= self.offset_band_c)
