"""The rules that keep or drop an effect: the shares of held-out structure a step must remove, the information
criterion, the significance level, and the record of each candidate's scoring (:class:`CandidateResult`).
Shared by forward selection, the backward pass (:mod:`.pipeline`) and the pair step (:mod:`.pair_step`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import statistics as st
from .candidates import Candidate
from .fitting import Fit, Fitter
from .simulator import OutputPost

#: Significance level of the EKF likelihood-ratio test, Bonferroni-corrected over a round.
ALPHA = 0.01
#: Held-out error over the estimated noise variance above which an output still carries structure.
STRUCTURE_MIN = 1.1
#: Alternations between the whole-model refit and the discovered term's coefficients.
DISCOVERY_ALTERNATIONS = 2
#: Share of the held-out structure a forward step must remove (each kept effect, in the backward pass too).
FORWARD_MIN = 0.1
#: Correlation of two corrections on the held-out rows above which they explain the same residual.
SAME_RESIDUAL_CORR = 0.9
#: Smallest contribution of a kept effect (its own change of the held-out readings, every other parameter fixed, as a
#: mean square over the noise variance, on the output it moves most) that the procedure can tell from zero: an output
#: whose held-out error is below ``STRUCTURE_MIN`` times its noise variance carries no structure, so an effect whose
#: whole contribution would not lift any output to that level, were it the only error, is below the procedure's own
#: resolution (:func:`contribution`; the backward pass drops it).
CONTRIBUTION_MIN = STRUCTURE_MIN - 1.0
#: The same for an output offset with drift (a generic two-parameter correction must earn more).
BIAS_MIN = 0.3


@dataclass
class CandidateResult:
    """How one candidate fared in one round."""

    name: str
    kind: str
    round: int
    status: str                      # skipped | rejected | accepted
    reason: str = ""
    description: str = ""
    source: str = ""
    regressor: str = ""
    params: dict = field(default_factory=dict)
    delay_s: float | None = None
    bias: tuple | None = None
    gain: float | None = None
    cost_train: float = float("nan")
    cost_holdout: float = float("nan")
    train_reduction: float = float("nan")     # share of the training cost removed
    explained_holdout: float = float("nan")   # share of the held-out structure removed
    primary_output: str = ""
    explained_primary: float = float("nan")   # share of the primary output's held-out structure removed
    lr: float = float("nan")
    dof: int = 0
    p_value: float = float("nan")
    p_threshold: float = float("nan")
    bic_change: float = float("nan")      # information criterion with it minus without (training rows)
    same_as: str = ""                     # candidate that explains the same residual
    backward_share: float = float("nan")  # held-out structure its removal costs with the others in
    jointly_with: str = ""                # accepted only together with this candidate or term (the pair step)
    fit: Fit | None = None
    contribution: float = float("nan")    # its own change of the held-out readings in the backward pass (contribution)

    def summary(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "fit"}


def gains(post: OutputPost, new=()) -> list[str]:
    """Outputs whose gain is fitted: ``new`` and those already in ``post`` (refit with every candidate, like the
    free parameters: a gain kept in an earlier round took up part of what a later effect explains, the PTC fall
    on the heater power)."""
    return list(dict.fromkeys(list(new) + list(post.gain)))


#: The errors a fit that fails raises (a simulation that diverges, a singular step, non-finite values): the
#: candidate or step is reported as failed and the model it would have changed stands.
FIT_ERRORS = (RuntimeError, np.linalg.LinAlgError, ValueError)


def supply_ratio(fitter: Fitter, fit: Fit) -> float:
    """Held-out scaled cost per sample of the supply temperature (1: at the noise level)."""
    c, n = fitter.output_costs(fit.y)
    j = fitter.outputs.index("supply_temp_c")
    return float(c[j] / max(n[j], 1))


def output_share(fitter: Fitter, worse: Fit, better: Fit, output: str) -> float:
    """Share of ``worse``'s held-out structure on ``output`` (scaled cost beyond the noise) that
    ``better`` removes."""
    j = fitter.outputs.index(output)
    c_w, n = fitter.output_costs(worse.y)
    c_b, _ = fitter.output_costs(better.y)
    excess = c_w[j] - n[j]
    return float((c_w[j] - c_b[j]) / excess) if excess > 0.1 * n[j] else 0.0


def holdout_correction(fitter: Fitter, fit: Fit, current: Fit) -> np.ndarray:
    """What ``fit`` changes against ``current`` on the held-out rows, every output scaled by its noise level
    (flattened; a missing reading counts 0)."""
    d = (fit.y - current.y) / fitter.sigma
    return np.where(np.isfinite(d), d, 0.0)[fitter.log.holdout].ravel()


def correction_correlation(fitter: Fitter, a: Fit, b: Fit, current: Fit) -> float:
    """Correlation of the held-out corrections of ``a`` and of ``b`` against ``current`` (:func:`holdout_correction`):
    at or above ``SAME_RESIDUAL_CORR`` the two explain the same residual."""
    da, db = holdout_correction(fitter, a, current), holdout_correction(fitter, b, current)
    return float(np.dot(da, db) / max(np.linalg.norm(da) * np.linalg.norm(db), 1e-300))


def contribution(fitter: Fitter, fit: Fit, without: Fit) -> float:
    """What an effect contributes to ``fit``: the mean square of the change of the held-out readings it makes
    (``fit`` against ``without``, the same parameters with the effect taken out), each output over its noise variance,
    on the output it moves most (compared with ``CONTRIBUTION_MIN``)."""
    d = (fit.y - without.y) / fitter.sigma
    ho = d[fitter.log.holdout]
    counts = np.sum(np.isfinite(ho), axis=0)
    ms = np.where(counts > 0, np.nansum(ho ** 2, axis=0) / np.maximum(counts, 1), 0.0)
    return float(np.max(ms)) if ms.size else 0.0


def bic_change(fitter: Fitter, new: Fit, current: Fit, q: int, output: str = "supply_temp_c") -> float:
    """Change of the information criterion on the training rows of ``output`` (the candidate's primary
    output; negative: the new structure is worth its q parameters): n_eff ln(C_new / C_cur) + q ln(n_eff),
    BIC form (Schwarz). C is the output's scaled training cost floored at its noise expectation (a cost
    below it carries no evidence); n_eff the effective sample size of its current residual, since an
    autocorrelated residual would otherwise count every row as independent evidence. The other outputs
    are guarded by the held-out gate (the total held-out error must fall)."""
    c_new, n = fitter.output_costs(new.y, "train")
    c_cur, _ = fitter.output_costs(current.y, "train")
    j = fitter.outputs.index(output)
    n_eff = max(st.effective_n((fitter.y_meas[:, j] - current.y[:, j])[fitter.log.train]), 2.0)
    ratio = max(c_new[j], n[j]) / max(c_cur[j], n[j], 1e-300)
    return float(n_eff * np.log(ratio) + q * np.log(n_eff))


def record_own(res: CandidateResult, cand: Candidate, fit: Fit, dt_s: float) -> None:
    """The candidate's own result in ``fit``, by kind: its delay (s), its offset and drift, or its gain."""
    if cand.kind == "delay":
        res.delay_s = fit.post.delays[cand.output] * dt_s
    if cand.kind == "bias":
        res.bias = fit.post.bias[cand.output]
    if cand.kind == "gain":
        res.gain = fit.post.gain[cand.output]
