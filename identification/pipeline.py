"""From a measurement log to a refined model: fit, diagnose, score candidate effects, decide.

Procedure (stated in the report):

1. Split in time: after a 120 s burn-in, the first 2/3 of the log train, the last 1/3 is held
   out (``holdout_fraction``). The initial state is the steady state at the first row.
2. Fit the nominal model's free parameters (:data:`~.fitting.NOMINAL_FREE`, those the data
   excite) on the training rows by free-run output error, each output scaled by its noise
   level (estimated from the log's second differences): first the flow equation's parameters
   on the volume flow alone, then the others on all outputs. Candidate fits refit all jointly.
3. Diagnose the residuals (:mod:`.diagnostics`).
4. Score every applicable candidate (:mod:`.candidates`): start from its null (or the best of a
   small grid), refit it together with the free parameters on the training rows.
5. Keep a candidate only if (a) the held-out rows carry structure beyond noise (scaled cost at
   least 1.1 per sample on some output), (b) it removes at least half of that held-out
   structure, summed over the outputs and on its own primary output (the first output of its
   signature, the outputs where the effect must show if it is the cause, that is logged and
   carries held-out structure), and (c) it is
   significant on the training rows: likelihood ratio of the EKF one-step innovations
   against chi2(q) at alpha = 0.01, Bonferroni-corrected over the candidates of the round.
   Among those kept, take the one with the lowest held-out error; repeat with the rest.
6. If structure remains and nothing fits, locate it (:mod:`.localise`) instead of naming an effect.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np
from scipy import stats

from hvac_mpc.models.box import MODEL_EFFECTS
from hvac_mpc.models.parameters import Parameters

from . import localise
from .candidates import Candidate, library
from .diagnostics import diagnose, innovations_nll
from .fitting import FLOW_PARAMS, NOMINAL_FREE, Fit, Fitter, FreeParam
from .log_data import LogData
from .simulator import OutputPost, shift

#: Decision thresholds (see the module docstring).
ALPHA = 0.01
EXPLAIN_MIN = 0.5
STRUCTURE_MIN = 1.1
#: Share of the training structure a candidate must remove with its own parameters alone to be
#: refitted jointly with the free parameters (screening).
SCREEN_MIN = 0.05
#: Largest transport delay scanned, s.
MAX_DELAY_S = 30.0


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
    fit: Fit | None = None

    def summary(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "fit"}


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

    @property
    def sigma(self) -> dict[str, float]:
        return {o: float(s) for o, s in zip(self.fitter.outputs, self.fitter.sigma)}

    def holdout_errors(self) -> dict[str, dict[str, float]]:
        """Held-out RMS and max |error| per output, before (nominal fit) and after."""
        out = {}
        for o in self.fitter.outputs:
            b = self.diag_before["metrics"][o]["holdout"]
            a = self.diag_after["metrics"][o]["holdout"]
            out[o] = {"rms_before": b["rms"], "rms_after": a["rms"], "max_before": b["max_abs"],
                      "max_after": a["max_abs"]}
        return out


def _grid_start(fitter: Fitter, effects, p: np.ndarray, post: OutputPost, cand: Candidate) -> np.ndarray:
    names = fitter.names
    best, best_cost = None, None
    for point in cand.grid or ({},):
        q = p.copy()
        for k, v in point.items():
            q[names.index(k)] = v
        try:
            cost = fitter.evaluate(effects, q, post).cost_train
        except (RuntimeError, np.linalg.LinAlgError):
            continue
        if np.isfinite(cost) and (best_cost is None or cost < best_cost):
            best, best_cost = q, cost
    return p.copy() if best is None else best


def _screen_and_fit(fitter: Fitter, current: Fit, free: list[FreeParam], effects, p0: np.ndarray,
                    own: list[FreeParam], post: OutputPost, bias_outputs=()) -> tuple[Fit | None, str]:
    """Screen with the candidate's own parameters only (cheap); refit jointly if it removes any
    of the training structure (docs/identification.md, 'The loop': screen, then refit the promising few)."""
    screen = fitter.fit(effects, p0, own, post, bias_outputs=bias_outputs, max_nfev=8) if (own or bias_outputs) \
        else fitter.evaluate(effects, p0, post)
    excess = fitter.structure(current.y, "train")
    gain = (current.cost_train - screen.cost_train) / excess if excess > 0 else 0.0
    if gain < SCREEN_MIN:
        screen.extra["screened_out"] = gain
        return screen, ""
    return fitter.fit(effects, screen.p, free + list(own), screen.post, bias_outputs=bias_outputs), ""


def _score_model(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate) -> tuple[Fit | None, str]:
    effects = current.effects | frozenset(cand.effects)
    p0 = _grid_start(fitter, effects, current.p, current.post, cand)
    visible = fitter.identifiable(effects, p0, current.post, cand.params)
    if not visible:
        return None, "its parameters do not change the logged outputs here (not observable)"
    return _screen_and_fit(fitter, current, free, effects, p0, list(visible), current.post)


def _score_delay(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate) -> tuple[Fit | None, str]:
    o = cand.output
    j = fitter.outputs.index(o)
    sim = fitter.simulator(current.effects)
    y_raw, _ = sim.simulate(current.p)
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
    return _screen_and_fit(fitter, current, free, current.effects, current.p, [], post)


def _score_bias(fitter: Fitter, current: Fit, free: list[FreeParam], cand: Candidate) -> tuple[Fit | None, str]:
    return _screen_and_fit(fitter, current, free, current.effects, current.p, [], current.post,
                           bias_outputs=[cand.output])


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


def identify(log: LogData, base: Parameters | None = None, base_effects: Iterable[str] = (), quick: bool = False,
             max_effects: int = 4, progress: Callable[[str], None] | None = None) -> IdentificationResult:
    """Run the whole procedure of the module docstring on a prepared log."""
    say = progress or (lambda _msg: None)
    t_start = time.perf_counter()
    timings = {}
    base = base or Parameters()
    base_effects = frozenset(base_effects)
    fitter = Fitter(log, base, quick)
    notes = list(log.notes)
    post0 = OutputPost(fitter.outputs, log.time_s)
    p_base = np.array(base.vector())
    say("fitting the nominal model")
    free = fitter.identifiable(base_effects, p_base, post0, NOMINAL_FREE)
    dropped = [fp.name for fp in NOMINAL_FREE if fp not in free]
    if dropped:
        notes.append(f"nominal parameters not excited by this log, kept fixed: {dropped}")
    # two stages: the flow equation on the measured flow (it does not depend on temperatures), then the
    # temperature side on all outputs, so that a temperature-side error cannot bend the flow parameters
    flow_free = [fp for fp in free if fp.name in FLOW_PARAMS]
    rest = [fp for fp in free if fp.name not in FLOW_PARAMS]
    stage1 = fitter.fit(base_effects, p_base, flow_free, post0, max_nfev=30 if quick else 60,
                        only_outputs=("volume_flow_m3s",))
    nominal = fitter.fit(base_effects, stage1.p, rest, post0, max_nfev=30 if quick else 60)
    nominal.free = tuple(fp.name for fp in free)
    timings["nominal_fit_s"] = time.perf_counter() - t_start
    say("diagnosing the nominal residuals")
    diag_before = diagnose(fitter, nominal)
    timings["diagnostics_s"] = time.perf_counter() - t_start - timings["nominal_fit_s"]
    current, current_free = nominal, list(free)
    accepted: list[CandidateResult] = []
    rounds: list[list[CandidateResult]] = []
    lib = library(fitter.outputs)
    t_cand = time.perf_counter()
    for rnd in range(1, max_effects + 1):
        structured = fitter.structure(current.y)
        c_o, n_o = fitter.output_costs(current.y)
        ratios = c_o / np.maximum(n_o, 1)
        if not np.any(ratios >= STRUCTURE_MIN):
            notes.append(f"round {rnd}: held-out residual at noise level (scaled cost per sample "
                         f"{', '.join(f'{o} {r:.2f}' for o, r in zip(fitter.outputs, ratios))}; all below "
                         f"{STRUCTURE_MIN}); no further effect scored")
            break
        results: list[CandidateResult] = []
        for cand in lib:
            res = CandidateResult(cand.name, cand.kind, rnd, "skipped", description=cand.description,
                                  source=cand.source, regressor=cand.regressor)
            results.append(res)
            reason = cand.applicable(log, current.effects)
            if cand.kind == "delay" and cand.output in current.post.delays:
                reason = "already in the model"
            if cand.kind == "bias" and cand.output in current.post.bias:
                reason = "already in the model"
            if reason:
                res.reason = reason
                continue
            say(f"round {rnd}: scoring {cand.name}")
            scorer = {"model": _score_model, "parameter": _score_model, "delay": _score_delay,
                      "bias": _score_bias}[cand.kind]
            try:
                fit, reason = scorer(fitter, current, current_free, cand)
            except (RuntimeError, np.linalg.LinAlgError, ValueError) as exc:
                fit, reason = None, f"fit failed ({exc})"
            if fit is None:
                res.reason = reason
                continue
            res.status = "rejected"
            res.fit = fit
            if "screened_out" in fit.extra:
                res.reason = (f"screened out: with its own parameters alone it removes "
                              f"{100 * fit.extra['screened_out']:.1f} % of the training structure "
                              f"(needs {100 * SCREEN_MIN:.0f} %)")
            res.params = {k: v for k, v in _new_params(fitter, fit, current).items()
                          if k in {fp.name for fp in cand.params}}
            if cand.kind == "delay":
                res.delay_s = fit.post.delays[cand.output] * log.dt_s
            if cand.kind == "bias":
                res.bias = fit.post.bias[cand.output]
            res.cost_train, res.cost_holdout = fit.cost_train, fit.cost_holdout
            res.train_reduction = 1.0 - fit.cost_train / current.cost_train
            res.explained_holdout = (current.cost_holdout - fit.cost_holdout) / structured
            res.primary_output = _primary(cand, fitter.outputs, ratios)
            jp = fitter.outputs.index(res.primary_output)
            c_new, _ = fitter.output_costs(fit.y)
            excess = c_o[jp] - n_o[jp]
            res.explained_primary = ((c_o[jp] - c_new[jp]) / excess) if excess > 0.1 * n_o[jp] else float("nan")
        scored = [r for r in results if r.fit is not None]
        m = max(len(scored), 1)
        nll_current = None
        for r in scored:
            if r.reason:
                continue
            if r.explained_holdout < EXPLAIN_MIN:
                r.reason = (f"explains {100 * r.explained_holdout:.0f} % of the held-out structure "
                            f"(needs {100 * EXPLAIN_MIN:.0f} %)")
                continue
            if not r.explained_primary >= EXPLAIN_MIN:
                r.reason = (f"its primary output {r.primary_output} carries no held-out structure"
                            if not np.isfinite(r.explained_primary) else
                            f"explains {100 * r.explained_primary:.0f} % of the held-out structure of its "
                            f"primary output {r.primary_output} (needs {100 * EXPLAIN_MIN:.0f} %)")
                continue
            if nll_current is None:
                nll_current = innovations_nll(fitter, current)[2]
            nll = innovations_nll(fitter, r.fit)[2]
            cand = next(c for c in lib if c.name == r.name)
            r.dof = {"delay": 1, "bias": 2}.get(cand.kind, len(r.params) or len(cand.params))
            r.lr = nll_current - nll
            r.p_value = float(stats.chi2.sf(r.lr, r.dof)) if r.lr > 0 else 1.0
            r.p_threshold = ALPHA / m
            if r.p_value >= r.p_threshold:
                r.reason = f"not significant on the training rows (p = {r.p_value:.2g} >= {r.p_threshold:.2g})"
        eligible = [r for r in scored if not r.reason]
        rounds.append(results)
        if not eligible:
            break
        best = min(eligible, key=lambda r: r.cost_holdout)
        best.status = "accepted"
        best.reason = (f"explains {100 * best.explained_holdout:.0f} % of the held-out structure, "
                       f"p = {best.p_value:.2g}")
        for r in eligible:
            if r is not best:
                r.reason = f"passed the gates but {best.name} fits the held-out rows better"
        accepted.append(best)
        cand = next(c for c in lib if c.name == best.name)
        current_free = current_free + [fp for fp in cand.params if fp.name in best.params]
        # polish the accepted structure so that the next round compares against a converged fit
        current = fitter.fit(best.fit.effects, best.fit.p, current_free, best.fit.post,
                             max_nfev=20 if quick else 40)
        if current.cost_train > best.fit.cost_train:
            current = best.fit
        say(f"round {rnd}: accepted {best.name}")
    timings["candidates_s"] = time.perf_counter() - t_cand
    final = current
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
    timings["total_s"] = time.perf_counter() - t_start
    return IdentificationResult(log, fitter, base, base_effects, nominal, final, accepted, rounds, diag_before,
                                diag_after, localisation, params, effects, extras, notes, timings)


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
    return params, effects, extras
