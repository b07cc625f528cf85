"""From a measurement log to a refined model: fit, diagnose, select effects, discover terms, decide.

Procedure (stated in the report):

1. Log checks (:mod:`.log_repair`, :mod:`.timing`): bad rows found, counted and masked; a constant
   shift of the sensor columns against the commands found on the flow, reported and corrected.
2. Split in time: after a 120 s burn-in, the first 2/3 of the log train, the last 1/3 is held
   out. Fit the nominal model's free parameters (:data:`~.fitting.NOMINAL_FREE`, those the data
   excite) on the training rows by free-run output error, each output scaled by its noise level:
   first the flow equation's parameters on the volume flow alone, then the others on all outputs.
3. Diagnose the residuals (:mod:`.diagnostics`), on the training and the held-out rows.
4. Joint screening: every applicable candidate (:mod:`.candidates`) takes one Gauss-Newton step
   together with the free parameters, so that a nominal refit cannot absorb it before it is scored.
5. Forward selection: the best screened candidates are refit fully; a candidate is kept if it
   lowers the held-out error, removes at least ``FORWARD_MIN`` of the held-out structure of its
   primary output (the first output of its signature that is logged and carries structure), lowers
   the information criterion on the training rows and passes the EKF likelihood-ratio test
   (alpha = 0.01, Bonferroni over the round). Candidates whose held-out corrections correlate with
   the kept one above ``SAME_RESIDUAL_CORR`` are reported as explaining the same residual.
   A library effect whose parameters the training rows do not excite but which, at its documented values, changes
   the held-out rows (:mod:`.documented`: the PTC fall of a log whose heater runs hot only after the training rows)
   is scored with those values fixed: it needs the training rows no worse (information criterion with q = 0) and its
   likelihood-ratio test is taken on the held-out rows, nothing of it having been fitted.
6. Term discovery (:mod:`.discovery`) when the supply temperature stays structured; one more
   forward pass when a term was added.
7. Pairs (:mod:`.pairs`): when the last forward round kept nothing and structure remains, the best candidates of
   that round (by the training cost their screening step removed, also those that made the held-out fit worse)
   and the discovered terms that lost their whole-model refit are screened in pairs, each pair by one linearised
   joint step with the free parameters; at most ``PAIR_REFIT`` are refit fully, best first, and the first that passes
   the forward step's gates (its parameters counted together, Bonferroni over the pairs screened) and in which each
   member removes ``FORWARD_MIN`` of the held-out structure the other leaves alone is kept; the report says that
   its members were identified only jointly.
8. Joint refit (:mod:`.joint_step`): when no pair was kept, or the pair kept a discovered term (chosen on the residual
   of a model without its partner), and the supply temperature still carries held-out structure, the kept effects and the last round's ``JOINT_CANDIDATES`` best candidates (by training cost removed)
   are refit all at once without the discovered terms, eliminated backward (each must remove ``FORWARD_MIN`` of its
   primary output's held-out structure with the others in, ``BIAS_MIN`` an offset, at most ``max_effects`` left),
   and discovery runs on what is left; that model replaces the forward path's if it removes ``FORWARD_MIN`` of its
   held-out supply structure and lowers the total held-out error.
   While the model holds a term and the supply stays structured, discovery runs again at the places that hold no
   term yet (a further term on the first's gates; effects outside the library at two places).
   Then a backward pass re-tests every kept effect: dropped if taking it out costs less than ``FORWARD_MIN`` of its
   primary output's held-out structure (where the model holds a term, also with the terms' coefficients refit beside
   it: a term fitted on a residual the effect had shaped leaves room for it), or if its own change of the held-out
   readings (the other parameters fixed) is below ``CONTRIBUTION_MIN`` of the noise variance (a magnitude the
   procedure cannot tell from zero).
9. Whatever structure remains is located (:mod:`.localise`) instead of being named.
10. Only with ``thesis_unless_moved`` (off by default, docs/identification.md "A log that adds nothing"): when
   nothing was added (no effect, term, delay, offset or gain), the model file holds the thesis value of every refit
   nominal parameter the log does not move (Wald test at the procedure's level, alone and jointly), the others refit
   with them there, unless the reverted parameters together pass the effects' gates against that model on some
   output (:func:`_thesis_unless_moved`).
"""

from __future__ import annotations

import dataclasses
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np
from scipy import stats

from hvac_mpc.models.box import MODEL_EFFECTS
from hvac_mpc.models.parameters import Parameters

from . import discovery, localise, timing
from . import statistics as st
from .candidates import MIN_ABS_VALUE, MODEL_CANDIDATES, OPTIONAL_CANDIDATES, Candidate, library
from .discovery import CABIN_CANDIDATES
from .diagnostics import diagnose, training_nll
from .documented import holdout_lr, is_documented, score_documented
from .fitting import (FLOW_PARAMS, IDENTIFIED_REL_SE, MOVED_Z, NOMINAL_FREE, Fit, Fitter, FreeParam, joint_wald,
                      parameter_confidence, parameter_covariance)
from .log_data import LogData
from .joint_step import joint_step
from .pair_step import pair_step
from .selection import (ALPHA, BIAS_MIN, CONTRIBUTION_MIN, DISCOVERY_ALTERNATIONS, FIT_ERRORS, FORWARD_MIN,
                        SAME_RESIDUAL_CORR, STRUCTURE_MIN, CandidateResult, bic_change, contribution,
                        correction_correlation, gains, output_share, record_own, supply_ratio)
from .simulator import OutputPost, Simulator, shift
from .workers import cpu_seconds, fork_map

#: The box's documented physics the identification starts from: the PTC power fall (thesis sec. 2.3)
#: and the flow network (fan curve and closed-valve leaks, thesis sec. 3.2, tables 3-6); the
#: controller's model carries them too (docs/identification.md).
DOCUMENTED_EFFECTS = ("ptc_power_fall", "fan_curve", "valve_leakage")

#: Decision threshold (see the module docstring).
EXPLAIN_MIN = 0.5
#: Share of the training structure a candidate must remove with its own parameters alone to be
#: refitted jointly with the free parameters (screening).
SCREEN_MIN = 0.05
#: Function evaluations of a joint screening fit (the best candidates are then polished).
SCREEN_NFEV = 3
#: Candidates refit fully per round (the best after the joint screening step).
POLISH = 2
#: Places of a discovered term refit and tested, best held-out prefix first (a place that wins on the linear score
#: can lose after the whole-model refit; the next one is tried).
PLACES_TRIED = 2
#: Largest transport delay scanned, s.
MAX_DELAY_S = 30.0


@dataclass
class IdentificationResult:
    log: LogData
    fitter: Fitter
    base_params: Parameters
    base_effects: frozenset
    nominal: Fit
    final: Fit
    accepted: list[CandidateResult]
    rounds: list[list[CandidateResult]]
    diag_before: dict
    diag_after: dict
    localisation: list[dict]
    params: Parameters
    effects: tuple[str, ...]
    extras: dict
    notes: list[str]
    timings: dict
    terms: tuple = ()
    discovery: dict | None = None
    timing_shift_samples: int = 0
    steps: list = field(default_factory=list)
    parameter_confidence: list = field(default_factory=list)  # fitting.parameter_confidence of the final fit
    pairs: list = field(default_factory=list)  # the pair step's refit pairs (pair_step), empty if it did not run
    joint: dict | None = None  # the joint refit's record (joint_step), None if it did not run
    #: Where the file's model is not ``final`` (nothing added, refit parameters the log does not move written at their
    #: thesis values, ``_thesis_unless_moved``): held-out RMS and max |error| per output, ``*_before`` the final fit's,
    #: ``*_after`` the written model's; else None.
    written: dict | None = None

    @property
    def sigma(self) -> dict[str, float]:
        return {o: float(s) for o, s in zip(self.fitter.outputs, self.fitter.sigma)}

    @property
    def absent(self) -> tuple[str, ...]:
        """Model effects the log tested (scored, with the nominal parameters refit together) and did not support:
        rejected in every round they were scored, not in the final model. Not tested (skipped) is not absent."""
        scored = {e for rnd in self.rounds for r in rnd if r.kind == "model" and r.status == "rejected"
                  for e in _candidate_effects(r.name)}
        return tuple(e for e in MODEL_EFFECTS if e in scored and e not in self.effects)

    def holdout_errors(self) -> dict[str, dict[str, float]]:
        """Held-out RMS and max |error| per output, before (nominal fit) and after."""
        out = {}
        for o in self.fitter.outputs:
            b = self.diag_before["metrics"][o]["holdout"]
            a = self.diag_after["metrics"][o]["holdout"]
            out[o] = {"rms_before": b["rms"], "rms_after": a["rms"], "max_before": b["max_abs"],
                      "max_after": a["max_abs"]}
        return out


def _candidate_effects(name: str) -> tuple[str, ...]:
    """The model effects the library candidate ``name`` switches on."""
    return next((c.effects for c in MODEL_CANDIDATES + OPTIONAL_CANDIDATES if c.name == name), ())


def _grid_start(fitter: Fitter, effects, p: np.ndarray, post: OutputPost, cand: Candidate) -> np.ndarray:
    names = fitter.names
    best, best_cost = None, None
    for point in cand.grid or ({},):
        q = p.copy()
        for k, v in point.items():
            q[names.index(k)] = v
        try:
            cost = fitter.train_cost(effects, q, post)
        except (RuntimeError, np.linalg.LinAlgError):
            continue
        if np.isfinite(cost) and (best_cost is None or cost < best_cost):
            best, best_cost = q, cost
    return p.copy() if best is None else best


def _screen_and_fit(fitter: Fitter, current: Fit, free: list[FreeParam], effects, p0: np.ndarray,
                    own: list[FreeParam], post: OutputPost, bias_outputs=(), flow_side: bool = False,
                    gain_outputs=()) -> tuple[Fit | None, str]:
    """Joint screening: the candidate's own parameters and the free parameters of the current model
    take one Gauss-Newton step together (so a nominal refit cannot absorb the effect before it is
    scored); the best candidates are refit fully afterwards (:func:`_forward`). The flow equation's
    parameters join only for a candidate on the flow side (``flow_side``): they were fitted on the
    measured flow alone, and a temperature-side step must not bend them (procedure step 2 of the module docstring)."""
    dy_free = current.extra.get("dy_free")
    if dy_free is None:
        dy_free = fitter.raw_sensitivity(current.effects, current.p, free, current.terms)
        current.extra["dy_free"] = dy_free
    keep = [k for k, fp in enumerate(free) if flow_side or fp.name not in FLOW_PARAMS]
    return fitter.gn_step(effects, p0, [free[k] for k in keep], dy_free[:, :, keep], own, post, bias_outputs,
                          current.terms, gain_outputs=gains(post, gain_outputs)), ""


def _score_model(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate) -> tuple[Fit | None, str]:
    effects = current.effects | frozenset(cand.effects)
    if cand.screen_each and len(cand.grid) > 1:
        # every grid point screened from the current parameters and from the starting ones (a nominal refit may have
        # absorbed part of the effect), the best screened fit kept
        starts = (current.p, np.array(fitter.base.vector()))
        fits = [_score_from(fitter, current, free, cand, effects, _grid_start(fitter, effects, p, current.post,
                                                                            dataclasses.replace(cand, grid=(g,))),
                            documented=False)
                for g in cand.grid for p in starts]
        good = [f for f in fits if f[0] is not None]
        if good:
            return min(good, key=lambda f: f[0].cost_train)
        # no grid point the training rows excite: the documented values' test on the held-out rows
        return _score_from(fitter, current, free, cand, effects, _grid_start(fitter, effects, current.p, current.post,
                                                                           cand))
    return _score_from(fitter, current, free, cand, effects, _grid_start(fitter, effects, current.p, current.post, cand))


def _score_from(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate, effects,
                p0: np.ndarray, documented: bool = True) -> tuple[Fit | None, str]:
    """The candidate screened and fitted from ``p0``; where the training rows do not excite its parameters, its
    documented values tested on the held-out rows (:mod:`.documented`), unless ``documented`` is False (a grid
    point of a candidate screened at each point: the documented test only when no point is excited)."""
    visible = fitter.identifiable(effects, p0, current.post, cand.params, current.terms)
    if not visible and not documented:
        return None, "its parameters do not change the logged outputs here (not observable)"
    if not visible:  # the training rows do not excite it: the held-out rows may still test its documented values
        return score_documented(fitter, current, cand, effects, lambda p: _screen_and_fit(
            fitter, current, free, effects, p, [], current.post, flow_side="volume_flow_m3s" in cand.signature))
    if cand.screen_each:  # the free parameters' sensitivities at the grid point, not at the current model
        current = dataclasses.replace(current, effects=effects, p=p0, extra={})
    return _screen_and_fit(fitter, current, free, effects, p0, list(visible), current.post,
                           flow_side="volume_flow_m3s" in cand.signature)


def _score_delay(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate) -> tuple[Fit | None, str]:
    o = cand.output
    j = fitter.outputs.index(o)
    y_raw = current.extra.get("y_raw")
    if y_raw is None:
        y_raw = fitter.simulator(current.effects, current.terms).simulate(current.p)[0]
    base_post = current.post.copy()
    base_post.delays.pop(o, None)
    y0 = base_post.apply(y_raw)
    ok = np.isfinite(fitter.y_meas[:, j]) & fitter.log.train
    best_d, best_c = 0, None
    for d in range(1, int(MAX_DELAY_S / fitter.log.dt_s) + 1):
        yd = shift(y0[:, j], d)
        c = float(np.sum(((fitter.y_meas[ok, j] - yd[ok]) / fitter.sigma[j]) ** 2))
        if best_c is None or c < best_c:
            best_d, best_c = d, c
    post = base_post.copy()
    post.delays[o] = best_d
    return _screen_and_fit(fitter, current, free, current.effects, current.p, [], post,
                           flow_side=o == "volume_flow_m3s")


def _score_bias(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate) -> tuple[Fit | None, str]:
    return _screen_and_fit(fitter, current, free, current.effects, current.p, [], current.post,
                           bias_outputs=[cand.output], flow_side=cand.output == "volume_flow_m3s")


def _score_gain(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate) -> tuple[Fit | None, str]:
    return _screen_and_fit(fitter, current, free, current.effects, current.p, [], current.post,
                           gain_outputs=[cand.output], flow_side=cand.output == "volume_flow_m3s")


def _primary(cand: Candidate, outputs: tuple[str, ...], ratios: np.ndarray) -> str:
    """The candidate's primary output: the first of its signature that is logged and carries held-out
    structure (else the first logged one)."""
    logged = [o for o in cand.signature if o in outputs]
    for o in logged:
        if ratios[outputs.index(o)] >= STRUCTURE_MIN:
            return o
    return logged[0]


def _new_params(fitter: Fitter, fit: Fit, current: Fit) -> dict:
    out = {}
    for i, name in enumerate(fitter.names):
        if fit.p[i] != current.p[i]:
            out[name] = float(fit.p[i])
    return out


def _select_free(fitter: Fitter, effects, p, post) -> list[FreeParam]:
    return fitter.identifiable(effects, p, post, NOMINAL_FREE)


def _nominal(fitter: Fitter, base_effects, p_base, quick: bool, notes: list[str]) -> tuple[Fit, list[FreeParam]]:
    """Nominal fit in two stages: the flow equation on the measured flow (it does not depend on
    temperatures), then the temperature side on all outputs."""
    post0 = OutputPost(fitter.outputs, fitter.log.time_s)
    free = _select_free(fitter, base_effects, p_base, post0)
    dropped = [fp.name for fp in NOMINAL_FREE if fp not in free]
    if dropped:
        notes.append(f"nominal parameters not excited by this log, kept fixed: {dropped}")
    nominal = _two_stage_fit(fitter, base_effects, p_base, free, post0, quick)
    return nominal, list(free)


def _two_stage_fit(fitter: Fitter, effects, p_start: np.ndarray, free: list[FreeParam], post: OutputPost,
                   quick: bool) -> Fit:
    """``free`` fitted from ``p_start``: the flow equation's parameters on the measured flow alone, then the others on
    all outputs (a stage with no parameter of its own is skipped)."""
    flow_free = [fp for fp in free if fp.name in FLOW_PARAMS]
    rest = [fp for fp in free if fp.name not in FLOW_PARAMS]
    p = p_start
    if flow_free:
        p = fitter.fit(effects, p, flow_free, post, max_nfev=8 if quick else 12, only_outputs=("volume_flow_m3s",)).p
    fit = fitter.fit(effects, p, rest, post, max_nfev=10 if quick else 15) if rest else fitter.evaluate(effects, p, post)
    fit.free = tuple(fp.name for fp in free)
    return fit


def check_timing(fitter_log: LogData, base: Parameters, base_effects, notes: list[str]) -> int:
    """Log timing check (:mod:`.timing`) on the nominal model's flow; corrects ``fitter_log`` in place."""
    if "volume_flow_m3s" not in fitter_log.outputs:
        return 0
    sim = Simulator(fitter_log, base, base_effects, ("volume_flow_m3s",))
    y, _ = sim.simulate(np.array(base.vector()))
    s, errors = timing.detect_shift(fitter_log.outputs["volume_flow_m3s"], y[:, 0])
    notes.append(timing.describe(s, fitter_log.dt_s, errors))
    timing.correct(fitter_log, s)
    return s


def _score_round(fitter: Fitter, current: Fit, current_free, lib, rnd: int, say, skip=()) -> list[CandidateResult]:
    """Score every applicable candidate jointly against ``current``."""
    log = fitter.log
    structured = fitter.structure(current.y)
    c_o, n_o = fitter.output_costs(current.y)
    ratios = c_o / np.maximum(n_o, 1)
    results, todo = [], []
    for cand in lib:
        res = CandidateResult(cand.name, cand.kind, rnd, "skipped", description=cand.description,
                              source=cand.source, regressor=cand.regressor)
        results.append(res)
        reason = cand.applicable(log, current.effects)
        if cand.kind == "delay" and cand.output in current.post.delays:
            reason = "already in the model"
        if cand.kind == "bias" and cand.output in current.post.bias:
            reason = "already in the model"
        if cand.kind == "gain" and cand.output in current.post.gain:
            reason = "already in the model"
        if cand.kind == "parameter" and any(fp.name in current.free for fp in cand.params):
            reason = "already in the model"
        if cand.name in skip:
            reason = "removed in the backward pass"
        if reason:
            res.reason = reason
            continue
        todo.append((res, cand))
    say(f"round {rnd}: scoring {', '.join(c.name for _, c in todo)}")
    fits = _map_scores(fitter, current, current_free, [c for _, c in todo])
    for (res, cand), (fit, reason) in zip(todo, fits):
        if fit is None:
            res.reason = reason
            continue
        res.status = "rejected"
        res.fit = fit
        res.params = {k: v for k, v in _new_params(fitter, fit, current).items()
                      if k in {fp.name for fp in cand.params}}
        record_own(res, cand, fit, log.dt_s)
        res.cost_train, res.cost_holdout = fit.cost_train, fit.cost_holdout
        res.train_reduction = 1.0 - fit.cost_train / current.cost_train
        res.explained_holdout = (current.cost_holdout - fit.cost_holdout) / structured if structured > 0 else 0.0
        res.primary_output = _primary(cand, fitter.outputs, ratios)
        jp = fitter.outputs.index(res.primary_output)
        c_new, _ = fitter.output_costs(fit.y)
        excess = c_o[jp] - n_o[jp]
        res.explained_primary = ((c_o[jp] - c_new[jp]) / excess) if excess > 0.1 * n_o[jp] else float("nan")
        res.dof = 0 if is_documented(fit) else {"delay": 1, "bias": 2, "gain": 1}.get(
            cand.kind, len(res.params) or len(cand.params))
        res.bic_change = bic_change(fitter, fit, current, res.dof, res.primary_output)
    return results


def _score_one(fitter: Fitter, current: Fit, current_free, cand: Candidate) -> tuple[Fit | None, str]:
    scorer = {"model": _score_model, "parameter": _score_model, "delay": _score_delay,
              "bias": _score_bias, "gain": _score_gain}[cand.kind]
    try:
        return scorer(fitter, current, list(current_free), cand)
    except FIT_ERRORS as exc:
        return None, f"fit failed ({exc})"


def _slim(fit: Fit | None) -> Fit | None:
    """A fit without what the caller does not need back from a worker (states, sensitivities)."""
    if fit is not None:
        fit.states = None
        fit.extra.pop("dy_free", None)
        fit.extra.pop("y_raw", None)
    return fit


def _map_scores(fitter: Fitter, current: Fit, free, cands: list[Candidate]) -> list[tuple[Fit | None, str]]:
    """Score the candidates side by side (:func:`~.workers.fork_map`)."""
    if "dy_free" not in current.extra:
        current.extra["dy_free"] = fitter.raw_sensitivity(current.effects, current.p, free, current.terms)
        current.extra["y_raw"] = fitter.simulator(current.effects, current.terms).simulate(current.p)[0]

    def task(i):
        fit, reason = _score_one(fitter, current, free, cands[i])
        return _slim(fit), reason
    return fork_map(task, len(cands))


def _polish(fitter: Fitter, current: Fit, free, pairs: list, quick: bool) -> list[tuple[Fit, float]]:
    """Full joint refit of the best screened candidates and their EKF training likelihood, side by side."""
    def task(i):
        r, cand = pairs[i]
        own = list(cand.params) if r.dof else []  # a documented hypothesis keeps its values
        fit = fitter.fit(r.fit.effects, r.fit.p, list(free) + own, r.fit.post,
                         max_nfev=6 if quick else 8, terms=current.terms,
                         bias_outputs=[cand.output] if cand.kind == "bias" else (),
                         gain_outputs=gains(r.fit.post, [cand.output] if cand.kind == "gain" else ()))
        if not fit.cost_train < r.fit.cost_train:
            fit = r.fit
        return _slim(fit), training_nll(fitter, fit)
    return fork_map(task, len(pairs))


def _gate(r: CandidateResult) -> str:
    """Why a scored candidate cannot be the forward step ('' if it can)."""
    if not r.explained_holdout > 0:
        return "does not lower the held-out error with the nominal parameters refit together with it"
    need = BIAS_MIN if r.kind == "bias" else FORWARD_MIN
    if not r.explained_primary >= need:
        return (f"its primary output {r.primary_output} carries no held-out structure"
                if not np.isfinite(r.explained_primary) else
                f"removes {100 * r.explained_primary:.0f} % of the held-out structure of its primary output "
                f"{r.primary_output} (needs {100 * need:.0f} %)")
    if not (r.bic_change < 0 or (r.dof == 0 and r.bic_change <= 0)):  # q = 0: the training rows no worse
        return f"information criterion on the training rows does not fall (change {r.bic_change:+.1f})"
    least = MIN_ABS_VALUE.get(r.name)
    if least is not None and r.params and max(abs(v) for v in r.params.values()) < least:
        return (f"its parameters stay below {least:g} in size ({', '.join(f'{k} {v:+.2f}' for k, v in r.params.items())}): "
                "a calibration of the nominal parameters, not the effect")
    return ""


def _without(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate, base: Parameters
             ) -> tuple[frozenset, np.ndarray, OutputPost, list[FreeParam]]:
    """The current structure with one kept candidate taken out (its parameters back at the base values)."""
    p = current.p.copy()
    base_vec = np.array(base.vector())
    for fp in cand.params:
        i = fitter.names.index(fp.name)
        p[i] = base_vec[i]
    post = current.post.copy()
    if cand.kind == "delay":
        post.delays.pop(cand.output, None)
    if cand.kind == "bias":
        post.bias.pop(cand.output, None)
    if cand.kind == "gain":
        post.gain.pop(cand.output, None)
    names = {fp.name for fp in cand.params}
    return current.effects - frozenset(cand.effects), p, post, [fp for fp in free if fp.name not in names]


def _forward(fitter: Fitter, nominal: Fit, free: list[FreeParam], lib, max_effects: int, quick: bool, say,
             notes: list[str], first_round: int = 1
             ) -> tuple[Fit, list[FreeParam], list[CandidateResult], list[list[CandidateResult]]]:
    """Forward selection on held-out error, the information criterion and the EKF likelihood ratio."""
    current, current_free = nominal, list(free)
    accepted: list[CandidateResult] = []
    rounds: list[list[CandidateResult]] = []
    for rnd in range(first_round, first_round + max_effects):
        c_o, n_o = fitter.output_costs(current.y)
        ratios = c_o / np.maximum(n_o, 1)
        if not np.any(ratios >= STRUCTURE_MIN):
            notes.append(f"round {rnd}: held-out residual at noise level (scaled cost per sample "
                         f"{', '.join(f'{o} {r:.2f}' for o, r in zip(fitter.outputs, ratios))}; all below "
                         f"{STRUCTURE_MIN}); no further effect scored")
            break
        results = _score_round(fitter, current, current_free, lib, rnd, say)
        rounds.append(results)
        scored = [r for r in results if r.fit is not None]
        for r in scored:
            r.reason = _gate(r)
        eligible = sorted((r for r in scored if not r.reason), key=lambda r: r.cost_holdout)
        best = None
        nll_current = training_nll(fitter, current) if eligible else None
        m = max(len(scored), 1)
        pairs = [(r, next(c for c in lib if c.name == r.name)) for r in eligible[:POLISH]]
        for (r, cand), (polished, nll) in zip(pairs, _polish(fitter, current, current_free, pairs, quick)):
            if polished is not r.fit:
                r.fit, r.cost_train, r.cost_holdout = polished, polished.cost_train, polished.cost_holdout
                r.explained_holdout = (current.cost_holdout - polished.cost_holdout) / fitter.structure(current.y)
                r.explained_primary = output_share(fitter, current, polished, r.primary_output)
                r.params = {k: v for k, v in _new_params(fitter, polished, current).items()
                            if k in {fp.name for fp in cand.params}}
                record_own(r, cand, polished, fitter.log.dt_s)
            r.bic_change = bic_change(fitter, r.fit, current, r.dof, r.primary_output)
            r.lr = nll_current - nll
            r.p_value = float(stats.chi2.sf(r.lr, r.dof)) if r.lr > 0 else 1.0
            rows = "training"
            if not r.dof:  # a documented hypothesis: nothing of it fitted, its test on the held-out rows
                r.lr, r.p_value = holdout_lr(fitter, current, r.fit, len(cand.params))
                rows = "held-out"
            r.p_threshold = ALPHA / m
            if r.p_value >= r.p_threshold:
                r.reason = f"not significant on the {rows} rows (p = {r.p_value:.2g} >= {r.p_threshold:.2g})"
                continue
            r.reason = _gate(r)
            if not r.reason and (best is None or r.cost_holdout < best.cost_holdout):
                best = r
        if best is None:
            current.extra["open_round"] = results  # scored against current, nothing kept: the pair step's members
            break
        best.status = "accepted"
        best.reason = (f"removes {100 * best.explained_holdout:.0f} % of the held-out structure, information "
                       f"criterion {best.bic_change:+.1f}, p = {best.p_value:.2g}" + (
                           "" if best.dof else " on the held-out rows, at its documented values (the training "
                           "rows do not excite it; the held-out errors before and after are this choice's own "
                           "evidence, not an independent check of it: nothing of it is fitted, so only the one "
                           "choice is optimistic)"))
        for r in eligible:
            if r is best or r.reason:
                continue
            corr = correction_correlation(fitter, r.fit, best.fit, current)
            r.same_as = best.name if corr >= SAME_RESIDUAL_CORR else ""
            if r.same_as:
                r.reason = (f"explains the same residual as {best.name} (correlation of their held-out corrections "
                            f"{corr:.2f}); this log cannot tell them apart, {best.name} fits the held-out rows better")
                notes.append(f"round {rnd}: {r.name} and {best.name} explain the same residual (correlation "
                             f"{corr:.2f}); kept {best.name}")
            else:
                r.reason = f"passed the gates but {best.name} fits the held-out rows better"
        accepted.append(best)
        cand = next(c for c in lib if c.name == best.name)
        current_free = current_free + [fp for fp in cand.params if fp.name in best.params]
        current = best.fit
        if current.states is None:
            current.states = fitter.simulator(current.effects, current.terms).simulate(current.p)[1]
        current.free = tuple(fp.name for fp in current_free)
        say(f"round {rnd}: accepted {best.name}")
    return current, current_free, accepted, rounds


def _backward(fitter: Fitter, current: Fit, free: list[FreeParam], accepted: list[CandidateResult], lib,
              base: Parameters, quick: bool, say, notes: list[str]) -> tuple[Fit, list[FreeParam]]:
    """Re-test each kept effect with the others in (the other effects and the discovered terms): refit
    without it; drop it if the held-out error rises by less than FORWARD_MIN of the structure it leaves, or if its
    own change of the held-out readings, the other parameters fixed (:func:`~.selection.contribution`), is below
    ``CONTRIBUTION_MIN``: a fitted magnitude the procedure cannot tell from zero (an exponent of -0.006 that the
    held-out share, measured on a residual at the noise level, kept).
    A lone effect is re-tested too when a term came in after it: the term may explain what it stood in for."""
    if len(accepted) + len(current.terms) < 2:
        return current, free
    for acc in list(accepted):
        cand = next(c for c in lib if c.name == acc.name)
        effects, p, post, free_wo = _without(fitter, current, free, cand, base)
        say(f"backward pass: re-testing {acc.name}")
        fit_wo = fitter.fit(effects, p, free_wo, post, max_nfev=SCREEN_NFEV, terms=current.terms)
        share = output_share(fitter, fit_wo, current, acc.primary_output or "supply_temp_c")
        if share >= FORWARD_MIN and current.terms:
            fit_wo, share = _without_with_terms_refit(fitter, fit_wo, share, current, effects, post, free_wo, acc,
                                                      quick)
        acc.backward_share = float(share)
        # the refit's start: the same parameters without the effect (a run the simulator keeps)
        acc.contribution = contribution(fitter, current, fitter.evaluate(effects, p, post, terms=current.terms))
        if share < FORWARD_MIN or acc.contribution < CONTRIBUTION_MIN:
            acc.status = "removed"
            acc.reason = (f"removed in the backward pass: with the other effects in, taking it out raises the "
                          f"held-out error of {acc.primary_output} by {100 * share:.0f} % of its structure "
                          f"(needs {100 * FORWARD_MIN:.0f} %)" if share < FORWARD_MIN else
                          f"removed in the backward pass: its own change of the held-out readings, the other "
                          f"parameters fixed, is {acc.contribution:.3f} times the noise variance (mean square, on the "
                          f"output it moves most), below the {CONTRIBUTION_MIN:.1f} the procedure can tell from zero")
            notes.append(f"backward pass: {acc.name} removed ({100 * share:.0f} % once the others are in; its own "
                         f"change of the held-out readings {acc.contribution:.3f} times the noise variance)")
            accepted.remove(acc)
            current, free = fit_wo, free_wo
            current.free = tuple(fp.name for fp in free)
        else:
            notes.append(f"backward pass: {acc.name} kept (taking it out costs {100 * share:.0f} % of the held-out "
                         f"structure; its own change of the held-out readings {acc.contribution:.2f} times the noise "
                         "variance)")
    return current, free


def _without_with_terms_refit(fitter: Fitter, fit_wo: Fit, share_wo: float, current: Fit, effects, post: OutputPost,
                              free_wo: list[FreeParam], acc: CandidateResult, quick: bool) -> tuple[Fit, float]:
    """The backward pass's model without ``acc`` once more, the discovered terms' coefficients alternated with the
    refit (as when a term is added, :func:`_fit_term`): a term fitted on a residual that an effect kept before it had
    shaped stays at the coefficients that left room for the effect, and the refit without the effect, the terms
    fixed, does not show what the terms take up without it (``duct_ua10`` seed 211: a heater-power gain the box does
    not have, beside a duct term that holds half the box's conductance). Returns the model and the share taking
    ``acc`` out costs; the quick refit's (``fit_wo``, ``share_wo``) if that is lower."""
    side = [fp for fp in free_wo if fp.name not in FLOW_PARAMS]
    fit, terms = fit_wo, current.terms
    try:
        for _ in range(DISCOVERY_ALTERNATIONS):
            for k in range(len(terms)):
                terms = terms[:k] + (discovery.refit_coefficients(fitter, fit, terms[k]),) + terms[k + 1:]
                fit = fitter.evaluate(effects, fit.p, post, fit.free, terms=terms)
            fit = fitter.fit(effects, fit.p, side, post, max_nfev=4 if quick else 6, terms=terms)
    except FIT_ERRORS:
        return fit_wo, share_wo
    share = output_share(fitter, fit, current, acc.primary_output or "supply_temp_c")
    return (fit, share) if share < share_wo else (fit_wo, share_wo)


def _records_of_refit_terms(discovered: dict | None, terms: tuple) -> None:
    """The term records (the kept one and the further ones) with the coefficients of the final model's terms of the
    same name: the backward pass refits them where it takes an effect out (:func:`_without_with_terms_refit`)."""
    by_name = {t.name: t for t in terms}
    for record in ([discovered] + list(discovered.get("further", ()))) if discovered else ():
        term = by_name.get((record.get("term") or {}).get("name"))
        if record.get("accepted") and term is not None and term.as_dict() != record["term"]:
            record.update(term=term.as_dict(), formula=term.formula(), words=term.description)


def _drop_removed_partners(accepted: list[CandidateResult], discovered: dict | None) -> None:
    """A pair member whose partner the backward pass removed was kept on its own in the end: it no longer says
    it was kept only jointly."""
    names = {a.name for a in accepted}
    for a in accepted:
        if a.jointly_with and not a.jointly_with.startswith("term ") and a.jointly_with not in names:
            a.jointly_with = ""
    if discovered and discovered.get("jointly_with") and discovered["jointly_with"] not in names:
        discovered["jointly_with"] = ""


def _discover(fitter: Fitter, current: Fit, free: list[FreeParam], quick: bool, say, notes: list[str],
              locations=tuple(discovery.TERM_NAMES), best_place: bool = False
              ) -> tuple[Fit, dict | None, list[tuple[Fit, dict]]]:
    """Term discovery on the supply temperature when its residual stays structured (:mod:`.discovery`), at the
    places ``locations``. Returns the model, the record of the term kept (or of the best place) and the terms refit
    and rejected, each with its fit (for the pair step). ``best_place``: every place refit (up to
    ``PLACES_TRIED``) and, of those whose term passes, the one with the lowest held-out error kept; else the first
    that passes."""
    if "supply_temp_c" not in fitter.outputs or not locations:
        return current, None, []
    ratios = diagnostics_ratio(fitter, current)
    if ratios < STRUCTURE_MIN:
        return current, None, []
    say("discovery: sparse regression of the supply residual on physical features")
    dy = fitter.raw_sensitivity(current.effects, current.p, [fp for fp in free if fp.name not in FLOW_PARAMS],
                                current.terms)
    dy = current.post.apply(np.zeros(dy.shape[:2]), dy)[1]
    dy_supply = dy[:, fitter.outputs.index("supply_temp_c"), :]
    # every place (after mixing; at the cooler core's outlet, before the split; the heater body; the air entering the
    # box), ranked by their best prefix's held-out error; the first whose term passes after the whole-model refit wins
    tried = sorted((discovery.select(fitter, current, dy_supply, location) for location in locations),
                   key=lambda t: t[2]["holdout_sse_best"])
    for _, _, rec in tried:
        rec["other_locations"] = [{"location": r["location"], "path_order": r["path_order"],
                                   "holdout_sse_best": r["holdout_sse_best"]} for _, _, r in tried if r is not rec]
        rec["structure_before"] = ratios
    if not tried[0][0]:
        notes.append("discovery: no prefix of the LARS path lowers the held-out supply error by "
                     f"{100 * discovery.MIN_STEP_GAIN:.0f} % (LARS path order: {tried[0][2]['path_order'][:5]})")
        return current, tried[0][2], []
    rejected, passed = [], []
    for chosen, coef, record in [t for t in tried if t[0]][:PLACES_TRIED]:
        fit = _fit_term(fitter, current, free, discovery.term_from(chosen, coef, location=record["location"]),
                        record, quick)
        if record["accepted"]:
            passed.append((fit, record))
            if not best_place:
                break
            continue
        rejected.append((fit, record))
        notes.append(f"discovery: term {record['formula']} rejected (removes {100 * record['explained_holdout']:.0f} % "
                     f"of the held-out structure, information criterion {record['bic_change']:+.1f})")
    if not passed:
        return current, tried[0][2], rejected
    fit, record = min(passed, key=lambda fr: fr[0].cost_holdout)
    fit.free = tuple(fp.name for fp in free)
    if best_place:
        record["places_passed"] = [{"location": r["location"], "formula": r["formula"],
                                    "holdout_cost": float(f.cost_holdout)} for f, r in passed]
        for f, r in passed:
            if r is not record:
                r["accepted"] = False
                notes.append(f"discovery: term {r['formula']} passes too, but {record['term']['name']} leaves a lower "
                             f"held-out error ({f.cost_holdout:.0f} against {fit.cost_holdout:.0f}, scaled)")
    notes.append(f"discovery: added {record['term']['name']}: {record['formula']} ({record['words']}); "
                 f"removes {100 * record['explained_holdout']:.0f} % of the held-out structure of supply_temp_c")
    return fit, record, []


def _further_terms(fitter: Fitter, current: Fit, free: list[FreeParam], discovered: dict | None, quick: bool, say,
                   notes: list[str], best_place: bool = False) -> tuple[Fit, dict | None]:
    """Discovery again, at the places that hold no term yet, while a term is in and the supply stays structured: two
    effects outside the library at two places (cabin air drawn in at the box inlet and a duct losing heat after the
    mixing point) leave, after the first term, the other's residual, which no term at the first place can take. Each
    further term passes the gates of the first (:func:`_fit_term`); its record goes to ``discovered["further"]``."""
    while current.terms:
        used = {t.location for t in current.terms}
        fit, record, _ = _discover(fitter, current, free, quick, say, notes,
                                   tuple(loc for loc in discovery.TERM_NAMES if loc not in used), best_place)
        if not (record and record.get("accepted")):
            break
        current = fit
        if discovered is not None:
            discovered.setdefault("further", []).append(record)
        else:
            discovered = record
    return current, discovered


def _joint(fitter: Fitter, current: Fit, free: list[FreeParam], accepted: list[CandidateResult], open_round, lib,
           base: Parameters, max_effects: int, quick: bool, rnd: int, discovered: dict | None, say, notes: list[str],
           terms: bool = True, best_place: bool = False
           ) -> tuple[Fit, list[FreeParam], list[CandidateResult], dict | None, dict | None]:
    """Procedure step 8 (:mod:`.joint_step`), its discovery that of step 6 (none without ``terms``); the forward
    path's term record stays unless the joint model replaces that path's model."""
    def discover(fit, fit_free, log):
        return (_discover(fitter, fit, fit_free, quick, say, log, best_place=best_place) if terms else
                (fit, None, []))
    current, free, accepted, joint_term, record = joint_step(fitter, current, free, accepted, open_round, lib, base,
                                                             max_effects, rnd, discover, say, notes)
    return current, free, accepted, (joint_term if record and record["accepted"] else discovered), record


def _fit_term(fitter: Fitter, current: Fit, free: list[FreeParam], term, record: dict, quick: bool) -> Fit:
    """The whole model refit with a discovered ``term``, its coefficients alternated with the refit; ``record`` gets
    the term, its share of the held-out structure, the information criterion's change and whether it passes."""
    fit = current
    side = [fp for fp in free if fp.name not in FLOW_PARAMS]  # a temperature term leaves the flow equation alone
    for _ in range(DISCOVERY_ALTERNATIONS):  # the whole model with the term, then its coefficients (exact)
        trial_terms = tuple(t for t in current.terms if t.name != term.name) + (term,)
        fit = fitter.fit(current.effects, fit.p, side, current.post, max_nfev=4 if quick else 6,
                         terms=trial_terms)
        term = discovery.refit_coefficients(fitter, fit, term)
    trial_terms = tuple(t for t in current.terms if t.name != term.name) + (term,)
    fit = fitter.evaluate(current.effects, fit.p, current.post, fit.free, terms=trial_terms)
    gain = output_share(fitter, current, fit, "supply_temp_c")
    record.update({"term": term.as_dict(), "formula": term.formula(), "words": term.description,
                   "explained_holdout": gain, "bic_change": bic_change(fitter, fit, current, len(term.features))})
    record["accepted"] = bool(gain >= FORWARD_MIN and record["bic_change"] < 0
                              and fit.cost_holdout < current.cost_holdout)
    return fit


def _errors(fitter: Fitter, before: Fit, after_y: np.ndarray) -> dict:
    out = {}
    ho = fitter.log.holdout
    for j, o in enumerate(fitter.outputs):
        eb = (fitter.y_meas[:, j] - before.y[:, j])[ho]
        ea = (fitter.y_meas[:, j] - after_y[:, j])[ho]
        out[o] = {"rms_before": st.rms(eb), "rms_after": st.rms(ea), "max_before": st.max_abs(eb),
                  "max_after": st.max_abs(ea)}
    return out


def _step_errors(fitter: Fitter, nominal: Fit, accepted, discovered: dict | None, final: Fit) -> list[dict]:
    """Held-out RMS and max error per output before and after each added effect (in the order added;
    the last step ends at the final model)."""
    steps, prev = [], nominal
    term_added = bool(discovered and discovered.get("accepted") and not discovered.get("jointly_with"))
    names = [a.name for a in accepted]
    accepted = [a for i, a in enumerate(accepted) if a.jointly_with not in names[:i]]  # a pair's second: the first's step
    groups = _same_fit(accepted)
    for i, group in enumerate(groups):
        a = group[0]
        last = i == len(groups) - 1 and not term_added
        fit = final if last or a.fit is None else a.fit
        added = (a.name + (f" + {a.jointly_with} (jointly)" if a.jointly_with else "") if len(group) == 1 else
                 " + ".join(g.name for g in group) + " (refit together)")
        steps.append({"added": added, "holdout": _errors(fitter, prev, fit.y)})
        prev = fit
    if term_added:
        steps.append({"added": f"term {discovered['term']['name']}", "holdout": _errors(fitter, prev, final.y)})
    return steps


def _same_fit(accepted: list[CandidateResult]) -> list[list[CandidateResult]]:
    """The kept effects in order, those kept in one and the same fit (the joint refit's) in one group: one step."""
    groups: list[list[CandidateResult]] = []
    for a in accepted:
        if groups and a.fit is not None and a.fit is groups[-1][0].fit:
            groups[-1].append(a)
        else:
            groups.append([a])
    return groups


def diagnostics_ratio(fitter: Fitter, fit: Fit) -> float:
    """Held-out scaled cost per sample of the supply temperature (:func:`~.selection.supply_ratio`)."""
    return supply_ratio(fitter, fit)


class _Clock:
    """Wall and CPU time per part of the run (``<part>_s`` wall, ``<part>_cpu_s`` CPU, ``total_s``, ``total_cpu_s``).

    CPU time counts this process and its forked workers; on a shared machine it is the honest measure
    (wall time grows with the other jobs' load)."""

    def __init__(self) -> None:
        self.t0, self.c0 = time.perf_counter(), cpu_seconds()
        self.t, self.c = self.t0, self.c0
        self.parts: dict[str, float] = {}

    def lap(self, part: str) -> None:
        t, c = time.perf_counter(), cpu_seconds()
        self.parts[f"{part}_s"] = self.parts.get(f"{part}_s", 0.0) + t - self.t
        self.parts[f"{part}_cpu_s"] = self.parts.get(f"{part}_cpu_s", 0.0) + c - self.c
        self.t, self.c = t, c

    def totals(self) -> dict[str, float]:
        return dict(self.parts, total_s=self.t - self.t0, total_cpu_s=self.c - self.c0)


@contextmanager
def one_blas_thread():
    """The linear algebra library on one thread while the identification runs (where ``threadpoolctl``, which
    scikit-learn brings, is installed). Its matrices are tall and thin (a Jacobian of a few tens of thousands of rows
    and 10-30 columns): on two cores shared with the forked scoring workers and other jobs, OpenBLAS's second thread
    only waits. The SVD of scipy's trust-region step on such a matrix: 0.35 CPU s on two threads under load, 0.025 s
    on one, the same values (docs/identification.md, "Cheaper runs")."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - without it the library keeps its threads
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def identify(log: LogData, base: Parameters | None = None, base_effects: Iterable[str] = (),
             quick: bool = False, max_effects: int = 4, progress: Callable[[str], None] | None = None,
             discover: bool = True, pairs: bool = True, joint: bool = True,
             best_place: bool = False, optional_candidates: Iterable[str] = (),
             thesis_unless_moved: bool = False) -> IdentificationResult:
    """Run the whole procedure of the module docstring on a prepared log (``pairs``: its step 7, the pairs of
    effects that only help together; ``joint``: its step 8, the joint refit; ``best_place``: a discovered term's
    place the one whose term leaves the lowest held-out error after the whole-model refit among those that pass,
    instead of the first that passes; ``optional_candidates``: names from :data:`~.candidates.OPTIONAL_CANDIDATES`
    scored with the library; ``thesis_unless_moved``: where nothing is added, the file holds the thesis value of
    every refit parameter the log does not move, :func:`_thesis_unless_moved`, off by default). The linear algebra
    runs on one thread (:func:`one_blas_thread`)."""
    for name, flag in (("best_place", best_place), ("thesis_unless_moved", thesis_unless_moved)):
        if not isinstance(flag, bool):
            raise TypeError(f"{name} must be True or False, not {flag!r}")
    with one_blas_thread():
        return _identify(log, base, base_effects, quick, max_effects, progress, discover, pairs, joint, best_place,
                         optional_candidates, thesis_unless_moved)


def _identify(log: LogData, base: Parameters | None, base_effects: Iterable[str], quick: bool, max_effects: int,
              progress: Callable[[str], None] | None, discover: bool, pairs: bool, joint: bool,
              best_place: bool, optional_candidates: Iterable[str] = (),
              thesis_unless_moved: bool = False) -> IdentificationResult:
    """:func:`identify` on the library's threads as they are set."""
    say = progress or (lambda _msg: None)
    clock = _Clock()
    base = base or Parameters()
    base_effects = frozenset(base_effects)
    notes = list(log.notes)
    shift_samples = check_timing(log, base, base_effects, notes)
    fitter = Fitter(log, base, quick)
    p_base = np.array(base.vector())
    say("fitting the nominal model")
    nominal, free = _nominal(fitter, base_effects, p_base, quick, notes)
    clock.lap("nominal_fit")
    say("diagnosing the nominal residuals")
    diag_before = diagnose(fitter, nominal)
    clock.lap("diagnostics")
    lib = library(fitter.outputs, optional_candidates)
    current, current_free, accepted, rounds = _forward(fitter, nominal, free, lib, max_effects, quick, say, notes)
    clock.lap("candidates")
    discovered, rejected_terms = None, []
    if discover:
        current, discovered, rejected_terms = _discover(fitter, current, current_free, quick, say, notes,
                                                        best_place=best_place)
    clock.lap("discovery")
    if discovered and discovered.get("accepted") and len(accepted) < max_effects:
        # with the term in, effects its residual hid may now show: one more forward pass
        current, current_free, more, more_rounds = _forward(fitter, current, current_free, lib,
                                                            max_effects - len(accepted), quick, say, notes,
                                                            first_round=len(rounds) + 1)
        accepted += more
        rounds += more_rounds
    clock.lap("candidates")
    pair_records, open_round = [], current.extra.get("open_round")
    if pairs:
        current, current_free, pair_kept, pair_term, pair_records = pair_step(
            fitter, current, current_free, lib, rejected_terms, max_effects - len(accepted), quick, len(rounds) + 1,
            say, notes)
        accepted += pair_kept
        discovered = pair_term or discovered
        open_round = joint_after_pairs(open_round, pair_kept, pair_term)
    current.extra.pop("open_round", None)  # the last round's fits: not kept alive in the final model
    clock.lap("pairs")
    joint_record = None
    if joint:
        current, current_free, accepted, discovered, joint_record = _joint(
            fitter, current, current_free, accepted, open_round, lib, base, max_effects, quick, len(rounds) + 1,
            discovered, say, notes, discover, best_place)
    clock.lap("joint")
    further_cpu_s = 0.0  # the further discovery's share of the discovery's time (a term at a second place)
    if discover:
        c_further = cpu_seconds()
        current, discovered = _further_terms(fitter, current, current_free, discovered, quick, say, notes, best_place)
        further_cpu_s = cpu_seconds() - c_further
    clock.lap("discovery")
    current, current_free = _backward(fitter, current, current_free, accepted, lib, base, quick, say, notes)
    _drop_removed_partners(accepted, discovered)
    _records_of_refit_terms(discovered, current.terms)
    clock.lap("candidates")
    final = current
    for a in accepted:  # the final model's values (later steps refit them with the others)
        a.params = {k: float(final.p[fitter.names.index(k)]) for k in a.params}
    diag_after = diag_before if final is nominal else diagnose(fitter, final)
    localisation = []
    after_struct = diag_after["structure_holdout"]
    for o in sorted(after_struct, key=lambda k: -after_struct[k]):
        if after_struct[o] >= STRUCTURE_MIN:
            loc = localise.locate(fitter, final, o)
            loc["structure_holdout"] = after_struct[o]
            if loc["equations"] or loc["signals"]:
                localisation.append(loc)
            else:
                notes.append(f"{o}: held-out error {after_struct[o]:.2f}x the estimated noise variance, but no "
                             "equation or signal term explains it on the held-out rows (R^2 <= 0.1)")
    params, effects, extras = model_outputs(fitter, final, base, diag_after)
    confidence = parameter_confidence(fitter, final, [fp for fp in NOMINAL_FREE if fp.name in final.free], p_base)
    params = _keep_unidentified(params, base, confidence, notes)
    written = None
    if thesis_unless_moved and _nothing_added(final, accepted):
        written = _thesis_unless_moved(fitter, final, confidence, base, quick, notes)
        params = model_outputs(fitter, written, base, diag_after)[0] if written is not final else params
    clock.lap("final_diagnostics")
    timings = dict(clock.totals(), further_discovery_cpu_s=further_cpu_s)
    res = IdentificationResult(log, fitter, base, base_effects, nominal, final, accepted, rounds, diag_before,
                               diag_after, localisation, params, effects, extras, notes, timings)
    res.terms = final.terms
    res.steps = _step_errors(fitter, nominal, accepted, discovered, final)
    res.discovery = discovered
    res.timing_shift_samples = shift_samples
    res.parameter_confidence = confidence
    res.pairs = pair_records
    res.joint = joint_record
    res.written = None if written is None or written is final else _errors(fitter, final, written.y)
    return res


def joint_after_pairs(open_round, pair_kept: list, pair_term: dict | None):
    """The last round's results the joint refit (procedure step 8) starts from after the pair step: none when the pair
    step kept two library effects (the joint refit is not needed); the round when it kept nothing, or an effect with a
    discovered term: that term was chosen on the residual of a model without its partner (it lost its refit there),
    so it may stand in for what the library explains once the partner is in, and the joint refit re-tests the effects
    without it and runs discovery on their residual."""
    return None if pair_kept and not pair_term else open_round


def _keep_unidentified(params: Parameters, base: Parameters, confidence: list[dict], notes: list[str]) -> Parameters:
    """The written parameters with the base (thesis) value wherever the log does not identify the refit one
    (standard error above ``IDENTIFIED_REL_SE`` of the value, :func:`~.fitting.parameter_confidence`); notes
    the parameters the log moved, in words."""
    keep = {c["name"]: getattr(base, c["name"]) for c in confidence if not c["identified"]}
    if keep:
        notes.append(f"nominal parameters refit but not identified by this log (standard error above "
                     f"{IDENTIFIED_REL_SE:.0%} of the value), the thesis values kept: {sorted(keep)}")
    for c in confidence:
        if c["moved"]:
            what = c["words"] or "a stand-in for a figure the thesis does not give, calibrated (docs/model.md sec. 1)"
            notes.append(f"the log moved {c['name']} from {c['start']:.4g} to {c['value']:.4g} ({c['change']:+.1%}, "
                         f"{abs(c['z']):.0f} standard errors): {what}")
    return params.replace(**keep) if keep else params


def _nothing_added(final: Fit, accepted: list[CandidateResult]) -> bool:
    """No effect, term, delay, offset or gain kept: the final model is the nominal structure refit."""
    post = final.post
    return not accepted and not final.terms and not (post.delays or post.bias or post.gain)


def _thesis_unless_moved(fitter: Fitter, final: Fit, confidence: list[dict], base: Parameters, quick: bool,
                         notes: list[str]) -> Fit:
    """The model the file holds when nothing was added (docs/identification.md, "A log that adds nothing"): each
    refit nominal parameter is a hypothesis "the thesis value is wrong", kept only where the log rejects the thesis
    value at the procedure's level (Wald test, abs(z) above :data:`~.fitting.MOVED_Z`, two-sided 1 %); the others
    go back to their thesis values, as far as their joint Wald test lets them (:func:`_jointly_unmoved`), and the
    kept ones are refit with them there. ``final`` itself where every refit parameter passes or where the reverted
    block passes the effects' gates on any output (no correction for the several outputs: it errs toward writing
    the refit, the default's file); the thesis model where none passes or where the restricted
    refit does not lower the thesis model's held-out error."""
    moved = {c["name"] for c in confidence if c["identified"] and abs(c["z"]) > MOVED_Z}
    reverted, wald = _jointly_unmoved(fitter, final, base, sorted(set(final.free) - moved), notes)
    moved = set(final.free) - set(reverted)
    if not reverted:
        return final
    p_thesis, p_base = final.p.copy(), np.array(base.vector())
    for name in final.free:
        i = fitter.names.index(name)
        p_thesis[i] = p_base[i]
    thesis = fitter.evaluate(final.effects, p_thesis, final.post)
    free = [fp for fp in NOMINAL_FREE if fp.name in moved and fp.name in final.free]
    fit = _two_stage_fit(fitter, final.effects, p_thesis, free, final.post, quick) if free else thesis
    if fit.cost_holdout >= thesis.cost_holdout:
        fit = thesis
    gates = {o: (output_share(fitter, fit, final, o), bic_change(fitter, final, fit, len(reverted), o))
             for o in fitter.outputs}
    share, bic = gates["supply_temp_c"] if "supply_temp_c" in gates else (0.0, 0.0)
    passed = [o for o, (sh, b) in gates.items() if sh >= FORWARD_MIN and b < 0]
    if final.cost_holdout < fit.cost_holdout and passed:
        notes.append(f"nothing added: the refit nominal parameters {reverted}, within {MOVED_Z} standard errors of "
                     f"their thesis values each, pass the effects' gates together on {passed} (information "
                     f"criterion {', '.join(f'{gates[o][1]:+.1f}' for o in passed)}): the refit is written")
        return final
    kept = [fp.name for fp in free] if fit is not thesis else []
    rms = _errors(fitter, final, fit.y)
    notes.append(f"nothing added: the refit nominal parameters the log does not move from their thesis values "
                 f"(|z| <= {MOVED_Z}, two-sided 1 %) written at the thesis values: {reverted}"
                 + (f"; refit with them there: {kept}" if kept else "; no parameter refit")
                 + f"; jointly within the test too (Wald {wald:.1f} on {len(reverted)} degrees of freedom, "
                   f"{100 * (1 - ALPHA):.0f} % bound {stats.chi2.ppf(1 - ALPHA, len(reverted)):.1f})"
                 + f"; together they do not pass the effects' gates against it on any output (they remove "
                   f"{100 * share:.0f} % of its held-out supply structure, information criterion {bic:+.1f}; need "
                   f"{100 * FORWARD_MIN:.0f} % and < 0)"
                 + "".join(f"; held-out {o} RMS of the written model {e['rms_after']:.4g} (the full refit's "
                           f"{e['rms_before']:.4g})" for o, e in rms.items() if o == "supply_temp_c"))
    return fit


def _jointly_unmoved(fitter: Fitter, final: Fit, base: Parameters, reverted: list[str],
                     notes: list[str]) -> tuple[list[str], float]:
    """A part of ``reverted``, found greedily (backward, not the largest such part in general), (each within :data:`~.fitting.MOVED_Z` of its thesis value alone) that the
    log does not move jointly either: while the block's Wald statistic exceeds the chi-square bound at the
    procedure's level (:data:`~.selection.ALPHA`), the parameter whose leaving lowers it most is kept at its refit
    value. Correlated estimates can each lie near their thesis values and together far from them (a joint move the
    per-parameter test does not see). Returns the block and its statistic."""
    free = [fp for fp in NOMINAL_FREE if fp.name in final.free]
    cov = parameter_covariance(fitter, final, free)
    start = np.array(base.vector())

    def wald(block: list[str]) -> float:
        return joint_wald(cov, free, final.p, start, fitter.names, block)

    block, kept = list(reverted), []
    while block and wald(block) > stats.chi2.ppf(1 - ALPHA, len(block)):
        out = min(block, key=lambda n: wald([b for b in block if b != n]))
        block.remove(out)
        kept.append(out)
    if kept:
        notes.append(f"nothing added: {kept} each within {MOVED_Z} standard errors of the thesis value but jointly "
                     f"moved by the log (Wald {wald(list(reverted)):.1f} on {len(reverted)} degrees of freedom): "
                     "not reverted with the others (refit with those at their thesis values, or written at the thesis "
                     "values too where that refit does not lower the thesis model's held-out error: the next note)")
    return block, wald(block)


def model_outputs(fitter: Fitter, final: Fit, base: Parameters, diag: dict) -> tuple[Parameters, tuple, dict]:
    """Updated parameters, effects to enable and the extras the model cannot hold."""
    changes = {}
    base_vec = base.vector()
    for i, name in enumerate(fitter.names):
        if final.p[i] != base_vec[i]:
            changes[name] = float(final.p[i])
    chiller = diag.get("chiller")
    if chiller and chiller["cycling"]:
        lo_b, hi_b = Parameters.__dataclass_fields__["chiller_band_c"].metadata["range"]
        changes["chiller_band_c"] = float(min(max(chiller["half_band_c"], lo_b), hi_b))
    if "supply_temp_c" in final.post.delays:
        lo_d, hi_d = Parameters.__dataclass_fields__["transport_delay_s"].metadata["range"]
        changes["transport_delay_s"] = float(min(max(final.post.delays["supply_temp_c"] * fitter.log.dt_s, lo_d), hi_d))
    cabin = fitter.log.cabin_temp_c
    if cabin is not None and any(f in CABIN_CANDIDATES for t in final.terms for f in t.features):
        # a controller without a cabin reading predicts with the logged cabin temperature's median
        lo_c, hi_c = Parameters.__dataclass_fields__["cabin_temp_c"].metadata["range"]
        changes["cabin_temp_c"] = float(min(max(np.median(cabin), lo_c), hi_c))
    params = base.replace(**changes)
    effects = tuple(e for e in MODEL_EFFECTS if e in final.effects)
    extras = {}
    for o, d in final.post.delays.items():
        extras[f"{o}_delay_s"] = float(d * fitter.log.dt_s)
    span_h = (fitter.log.time_s[-1] - fitter.log.time_s[0]) / 3600.0
    for o, (b0, b1) in final.post.bias.items():
        # offset at the log's mid-time and drift per hour (b1 spans the whole log)
        extras[f"{o}_offset"] = float(b0)
        extras[f"{o}_drift_per_h"] = float(b1 / span_h) if span_h > 0 else 0.0
    for o, g in final.post.gain.items():
        extras[f"{o}_gain"] = float(g)
    return params, effects, extras
