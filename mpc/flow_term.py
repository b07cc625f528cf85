"""The bypass split's flow dependence learned outside the filter, across settled flow steps.

Inside the filter (``EkfSettings.learn_bypass_flow`` alone) the exponent k of ``b_eff = b (m / m_ref)^k`` is
learned within the transient that shows it, from innovations the dead time, the thermocouple lag and the
sensor noise share; on boxes without the dependence what it learns there is noise, and the prediction moves
with it (docs/robustness.md sec. 2.7). Here the filter keeps k a constant and the split's reference flow
anchored at the recent flow, so that its mixed-air offset takes the whole change of the supply air a flow
step brings; once the flow has been steady again for ``settle_s``, that change of the offset is one
observation of k:

    d_offset = f(k),  f(k) = mix(k, m_ref = m_before) - mix(k, m_ref = m_after),

the model's mixed air at the settled state with the split's reference flow at the flow before the step
against at the flow now (f(0) = 0: without the dependence the model's air does not depend on the anchor).
Linearised at the estimate in use, f(k) ~ f(k_c) + S (k - k_c), each step adds ``S^2`` and
``S (d_offset - f(k_c) + S k_c)`` to the sums of a least-squares fit with a prior (ridge): the estimate
moves only as far as the steps' evidence outweighs the prior (:meth:`FlowStepFit.estimate`).

Pure numpy: the model's air comes from the caller (:meth:`~.estimator.DisturbanceEkf`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class RestPoint:
    """Where the flow rested: ln of the model's mass flow (ln kg/s), the mixed-air offset (degC, averaged
    over the rest) and the other commands that move the supply air (valve a in %, the heater in W)."""

    log_flow: float
    offset_c: float
    others: tuple = ()


class SettledFlowSteps:
    """Find settled flow steps in a stream of (ln mass flow, mixed-air offset) samples.

    The flow rests while it stays within ``gate / 2`` (in ln) of its recent mean (an exponential mean over
    ``average_s``: a step breaks a rest, the slow end of the blower's response does not); a rest counts once
    it has lasted ``settle_s``. :meth:`observe` returns the previous settled rest and the current one when the
    current one has just counted and its flow differs from that rest's by more than ``gate`` (a flow step),
    else None. The offset of
    a rest is its mean over the rest's last ``average_s`` (an exponential mean)."""

    def __init__(self, settle_s: float, gate: float, dt_s: float = 1.0, average_s: float = 5.0):
        self.settle_s, self.gate, self.dt_s = float(settle_s), float(gate), float(dt_s)
        self.alpha = min(1.0, self.dt_s / float(average_s))
        self.reset()

    def reset(self) -> None:
        self._flow: float | None = None  # ln flow averaged over the current rest
        self._rest_s = 0.0
        self._mean: float | None = None  # offset averaged over the current rest
        self._settled: RestPoint | None = None  # the last rest that counted (updated while it lasts)
        self._stepped = False  # the current rest has been reported as a step

    def observe(self, log_flow: float, offset_c: float, eligible: bool = True,
                others: tuple = ()) -> tuple[RestPoint, RestPoint] | None:
        """One sample; ``eligible`` False keeps this sample's rest from counting (e.g. before the dead time is
        known). Returns (the rest before, the rest after) of a flow step that has just settled, else None."""
        if not (math.isfinite(log_flow) and math.isfinite(offset_c)):
            return None
        if self._flow is None or abs(log_flow - self._flow) > 0.5 * self.gate:
            self._flow, self._rest_s, self._mean, self._stepped = log_flow, 0.0, offset_c, False
        else:
            self._rest_s += self.dt_s
            self._flow += self.alpha * (log_flow - self._flow)
            self._mean += self.alpha * (offset_c - self._mean)
        if self._rest_s < self.settle_s or not eligible:
            return None
        before = self._settled
        self._settled = RestPoint(log_flow, self._mean, tuple(others))
        if before is None or self._stepped or abs(log_flow - before.log_flow) <= self.gate:
            return None
        self._stepped = True
        return before, self._settled


class FlowStepFit:
    """Least squares of the exponent over the settled steps, with a prior: the estimate is
    ``(w0 k0 + sum S y) / (w0 + sum S^2)``, ``w0 = (noise_c / prior_sd)^2`` (the offset's noise at rest
    against the prior's spread), held within ``[lo, hi]``."""

    def __init__(self, prior: float, prior_sd: float, noise_c: float, lo: float, hi: float):
        self.prior, self.lo, self.hi = float(prior), float(lo), float(hi)
        self.w0 = (float(noise_c) / float(prior_sd)) ** 2
        self.reset()

    def reset(self) -> None:
        self.sss = 0.0
        self.ssy = 0.0
        self.steps = 0

    def add(self, sensitivity_c: float, target_c: float) -> None:
        """One settled step: ``S`` (degC per unit of the exponent) and ``y = d_offset - f(k_c) + S k_c`` (degC)."""
        if math.isfinite(sensitivity_c) and math.isfinite(target_c):
            self.sss += sensitivity_c * sensitivity_c
            self.ssy += sensitivity_c * target_c
            self.steps += 1

    def estimate(self) -> float:
        k = (self.w0 * self.prior + self.ssy) / (self.w0 + self.sss)
        return min(max(k, self.lo), self.hi)
