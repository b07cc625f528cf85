"""Candidates the training rows do not excite, scored at their documented values.

A log's held-out rows (its last third, :func:`.log_data.prepare`) can hold what its training rows never do: the
seed-31 "steps" log of the independent box commands the heater near full power (237 W) only 52 s after its training
rows end, so the PTC's power fall (the body past the knee, the heater drawing 217 W of it) shows on the held-out rows
alone. There every knee above the hottest training body temperature fits the training rows the same, the candidate's
parameters have no sensitivity there, and :meth:`~.fitting.Fitter.identifiable` calls it "not observable" though the
thesis's curve (knee 60 C) brings the held-out supply error from 0.29 to 0.05 C.

Such a candidate is scored as a hypothesis fixed in advance: the effect switched on at the documented values of its
parameters (the ``base`` :class:`~hvac_mpc.models.parameters.Parameters`, the thesis's), nothing of it fitted, the
nominal parameters refit with it as for any candidate. With no parameter of its own it needs only leave the training
rows no worse (information criterion change <= 0 with q = 0), and its likelihood-ratio test, the one the training rows
give the fitted candidates, is taken on the held-out rows, which nothing was fitted to (:func:`holdout_lr`).
ASSUMPTION: the documented values are the thesis's; a box whose effect is off the thesis's values is named with the
thesis's values (its parameters are fitted only where the training rows excite them).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy import stats

from .candidates import Candidate
from .diagnostics import holdout_nll
from .fitting import Fit, Fitter

#: Smallest change (root of the summed squared noise-scaled change over the held-out rows) the effect at its
#: documented values must make for the held-out rows to test it; the rule of :meth:`~.fitting.Fitter.identifiable`
#: (a parameter column norm below 1 is not excited), applied to the switch of the effect.
HOLDOUT_CHANGE_MIN = 1.0


def documented_start(fitter: Fitter, cand: Candidate, p: np.ndarray) -> np.ndarray:
    """``p`` with the candidate's parameters at the documented (``fitter.base``) values."""
    q = np.array(p, dtype=float)
    base = np.array(fitter.base.vector())
    for fp in cand.params:
        i = fitter.names.index(fp.name)
        q[i] = base[i]
    return q


def holdout_change(fitter: Fitter, current: Fit, effects, p0: np.ndarray) -> float:
    """Root of the summed squared noise-scaled change the effect at ``p0`` makes to the held-out outputs (the
    current effects at ``p0`` the reference)."""
    y_off = current.post.apply(fitter.simulator(current.effects, current.terms).simulate(p0)[0])
    y_on = current.post.apply(fitter.simulator(effects, current.terms).simulate(p0)[0])
    d = (y_on - y_off) / fitter.sigma[None, :]
    ok = np.isfinite(fitter.y_meas) & np.isfinite(d) & fitter.log.holdout[:, None]
    return float(np.sqrt(np.sum(np.where(ok, d, 0.0) ** 2)))


def score_documented(fitter: Fitter, current: Fit, cand: Candidate, effects,
                     screen: Callable[[np.ndarray], tuple[Fit | None, str]]) -> tuple[Fit | None, str]:
    """The candidate as a documented hypothesis (module docstring), or ``None`` and why not. ``screen(p0)``: the
    joint screening step from ``p0`` with no parameter of the candidate free."""
    if cand.kind != "model":
        return None, "its parameters do not change the logged outputs here (not observable)"
    p0 = documented_start(fitter, cand, current.p)
    change = holdout_change(fitter, current, effects, p0)
    if change < HOLDOUT_CHANGE_MIN:
        return None, ("its parameters do not change the logged outputs here (not observable; at its documented "
                      f"values it changes the held-out rows by {change:.2f} noise units either)")
    fit, reason = screen(p0)
    if fit is not None:
        fit.extra["documented"] = True
    return fit, reason


def is_documented(fit: Fit | None) -> bool:
    """Whether ``fit`` is a candidate scored as a documented hypothesis."""
    return fit is not None and bool(fit.extra.get("documented"))


def holdout_lr(fitter: Fitter, current: Fit, fit: Fit, dof: int) -> tuple[float, float]:
    """Likelihood ratio of ``fit`` over ``current`` on the held-out rows and its chi2 p-value with ``dof`` degrees
    (at least one). ASSUMPTION: the candidate's parameter count, as if fitted, so the test is no easier than a fitted
    candidate's on the training rows."""
    lr = holdout_nll(fitter, current) - holdout_nll(fitter, fit)
    return lr, float(stats.chi2.sf(lr, max(dof, 1))) if lr > 0 else 1.0
