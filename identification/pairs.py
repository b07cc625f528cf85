"""Joint screening of pairs: two effects that only help together.

Forward selection (:mod:`.pipeline`) adds one effect at a time. Two effects can mask each other: with one of
them missing, the nominal refit bends a free parameter to absorb part of it, and the other, scored alone on that
bent fit, makes the held-out error worse; the same holds the other way round, so neither is ever added
(docs/identification.md, "Effects that only help together"). Such a pair shows only when scored together.

This module holds the linear algebra of that screening. Each member of a pair (a library candidate of the last
round, or the best term of a discovery place that lost its whole-model refit) is described at the current fit by
its start, the model's outputs where its screening step starts (its grid point, its delay), and by its Jacobian
columns (its own parameters' sensitivities, its offset and drift, its gain, a term's features); the free
parameters' columns are the current model's. The linearised score of a pair is the one joint Gauss-Newton step of
the free parameters and both members' parameters from the current fit, the step the screening takes for a single
candidate, evaluated on the linear model instead of by a free run: predicted costs per output on the training and
the held-out rows. The same step with one member gives what each does alone. A pair is offered for a full refit
only if each member, in that prediction, removes at least ``min_share`` of the held-out structure the other leaves
alone (else one member does the work and the other rides along); the pipeline refits the best and decides.

Everything here is plain numpy on arrays (n rows, outputs, columns), so the rule can be checked on synthetic data.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Sequence

import numpy as np

#: Levenberg-Marquardt damping of the step, relative to the diagonal (the candidates' screening step's).
DAMPING = 1e-2


@dataclass
class Member:
    """One side of a pair, linearised at the current fit.

    ``y0``: the model's outputs at the member's start, output corrections applied (n, outputs); ``cols``: their
    Jacobian in the member's own scaled parameters (n, outputs, k; k may be 0, a delay); ``flow_side``: the member
    acts on the flow equation, so the free parameters fitted on the flow alone join its step."""

    name: str
    y0: np.ndarray
    cols: np.ndarray
    flow_side: bool = False


@dataclass
class Frame:
    """What the scores are measured against: logged outputs (n, outputs), their noise levels, the training and
    held-out rows (bool, n)."""

    y_meas: np.ndarray
    sigma: np.ndarray
    train: np.ndarray
    holdout: np.ndarray

    def costs(self, y: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per output: sum of squared scaled errors on ``rows`` and the number of logged samples there."""
        r = (self.y_meas - y) / self.sigma
        ok = np.isfinite(r) & rows[:, None]
        return (np.where(ok, r, 0.0) ** 2).sum(axis=0), ok.sum(axis=0)

    def structure(self, y: np.ndarray) -> float:
        """Held-out cost beyond the noise expectation, summed over the outputs (``Fitter.structure``)."""
        c, n = self.costs(y, self.holdout)
        return float(np.sum(np.maximum(c - n, 0.0)))


@dataclass
class Step:
    """A linearised joint step: the members' indices, the step (free parameters' columns first, then each member's
    in order), the predicted outputs' held-out costs per output and structure, and the training cost."""

    members: tuple[int, ...]
    theta: np.ndarray
    cost_train: float
    cost_holdout: np.ndarray
    structure: float
    joint_share: float = float("nan")  # pairs: the least share of the structure a member removes with the other in


def linear_step(frame: Frame, y_cur: np.ndarray, j_free: np.ndarray, members: Sequence[Member],
                damping: float = DAMPING) -> tuple[np.ndarray, np.ndarray]:
    """One damped Gauss-Newton step of the free parameters (``j_free``, n x outputs x k) and the members' own
    parameters together, from their combined start (each member's change of the outputs at its start added to
    ``y_cur``); the step and the outputs it predicts (linear, no simulation)."""
    y_base = y_cur + sum((m.y0 - y_cur for m in members), np.zeros_like(y_cur))
    jac = np.concatenate([j_free] + [m.cols for m in members], axis=2)
    theta, _ = gauss_newton_step(frame.y_meas, y_base, jac, frame.sigma, frame.train, damping)
    return theta, y_base + np.nan_to_num(np.einsum("nok,k->no", jac, theta))


def gauss_newton_step(y_meas: np.ndarray, y_start: np.ndarray, jac: np.ndarray, sigma: np.ndarray,
                      train: np.ndarray, damping: float) -> tuple[np.ndarray, float]:
    """One Levenberg-Marquardt-damped Gauss-Newton step of the parameters whose output sensitivities are ``jac``
    (n x outputs x k) from the outputs ``y_start`` (n x outputs), on the training rows (bool per row) with a
    reading, each output scaled by its noise level ``sigma``; the step and the start's cost (sum of the scaled
    squared residuals)."""
    ok = np.isfinite(y_meas) & train[:, None]
    r = np.where(ok, (y_meas - y_start) / sigma, 0.0)[train].ravel()
    jm = np.where(ok[:, :, None], jac / sigma[None, :, None], 0.0)[train].reshape(-1, jac.shape[2])
    jtj = jm.T @ jm
    return np.linalg.solve(jtj + damping * np.diag(np.diag(jtj) + 1e-12), jm.T @ r), float(r @ r)


def score(frame: Frame, y_cur: np.ndarray, j_free: np.ndarray, flow_cols: np.ndarray, members: Sequence[Member],
          chosen: tuple[int, ...]) -> Step:
    """The linearised step of the members ``chosen`` (indices into ``members``); ``flow_cols`` (bool per column of
    ``j_free``) marks the flow equation's parameters, which join only when a member is on the flow side."""
    use = [members[i] for i in chosen]
    keep = np.ones(j_free.shape[2], bool) if any(m.flow_side for m in use) else ~np.asarray(flow_cols, bool)
    theta, y = linear_step(frame, y_cur, j_free[:, :, keep], use)
    full = np.zeros(j_free.shape[2] + sum(m.cols.shape[2] for m in use))
    full[np.flatnonzero(np.concatenate([keep, np.ones(len(full) - len(keep), bool)]))] = theta
    c_tr, _ = frame.costs(y, frame.train)
    c_ho, _ = frame.costs(y, frame.holdout)
    return Step(tuple(chosen), full, float(c_tr.sum()), c_ho, frame.structure(y))


def screen_pairs(frame: Frame, y_cur: np.ndarray, j_free: np.ndarray, flow_cols: np.ndarray,
                 members: Sequence[Member], min_share: float, exclude: Sequence[tuple[int, int]] = ()
                 ) -> tuple[list[Step], list[Step]]:
    """Every pair of ``members`` (but those in ``exclude``) scored by its linearised joint step, and each member
    alone. Returns the pairs that lower the held-out structure of ``y_cur`` and in which each member removes at
    least ``min_share`` of the structure the other leaves alone, best predicted held-out cost first, and the
    singles (in the members' order)."""
    singles = [score(frame, y_cur, j_free, flow_cols, members, (i,)) for i in range(len(members))]
    s_cur = frame.structure(y_cur)
    kept = []
    for a, b in combinations(range(len(members)), 2):
        if (a, b) in exclude or (b, a) in exclude:
            continue
        step = score(frame, y_cur, j_free, flow_cols, members, (a, b))
        step.joint_share = min(structure_share(singles[b].structure, step.structure),
                               structure_share(singles[a].structure, step.structure))
        if step.structure < s_cur and step.joint_share >= min_share:
            kept.append(step)
    return sorted(kept, key=lambda s: float(s.cost_holdout.sum())), singles


def structure_share(before: float, after: float) -> float:
    """Share of the structure ``before`` that ``after`` removes (0 when there is none to remove)."""
    return (before - after) / before if before > 0 else 0.0
