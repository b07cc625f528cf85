"""The pair step (procedure step 7 of :mod:`.pipeline`): when forward selection keeps nothing more and structure
remains, pairs of the last round's best candidates and of the discovered terms that lost their refit are screened
jointly (:mod:`.pairs`, one linearised step each), the best refit, and a pair kept if it passes the forward step's
gates with both members counted and each member needed by the other (docs/identification.md, "Effects that only
help together")."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

from . import discovery
from .candidates import MIN_ABS_VALUE, Candidate
from .diagnostics import training_nll
from .fitting import FLOW_PARAMS, Fit, Fitter, FreeParam
from .joint_step import Structure
from .pairs import Frame, Member, Step, screen_pairs, structure_share
from .selection import (ALPHA, BIAS_MIN, DISCOVERY_ALTERNATIONS, FORWARD_MIN, STRUCTURE_MIN, CandidateResult,
                        bic_change, gains, output_share, record_own)

if TYPE_CHECKING:
    from hvac_mpc.models.discovered import DiscoveredTerm


#: Candidates of the last round offered to the pair step (the most training cost removed by their screening step).
PAIR_CANDIDATES = 4
#: Pairs refit fully, in the order of their linearised joint step, until one passes the gates.
PAIR_REFIT = 2


@dataclass
class _Side:
    """One member of a pair: a candidate of the last round (``result``, ``cand``, its own parameters ``own`` and the
    parameter vector its screening step started from) or a discovered term that lost its whole-model refit
    (``term``, ``record``); its linearisation at the current fit, its fit alone, its primary output and its
    parameter count."""

    member: Member
    alone_fit: Fit
    primary: str
    dof: int
    result: CandidateResult | None = None
    cand: Candidate | None = None
    own: tuple[FreeParam, ...] = ()
    start_p: np.ndarray | None = None
    term: DiscoveredTerm | None = None
    record: dict | None = None

    @property
    def name(self) -> str:
        return self.member.name

    def alone(self) -> str:
        """What it did alone, in words: the share of its primary output's held-out structure it removed (negative:
        it made the fit worse)."""
        share = float(self.record["explained_holdout"] if self.term is not None else self.result.explained_primary)
        return (f"removed {100 * share:.0f} % of the held-out structure of {self.primary}" if np.isfinite(share)
                else f"left {self.primary} without held-out structure to remove")


def _candidate_side(fitter: Fitter, current: Fit, r: CandidateResult, cand: Candidate) -> _Side | None:
    """A candidate of the last round linearised at ``current``: its start (grid point, delay) and its own columns
    (parameters' sensitivities, offset and drift, gain), as its screening step had them."""
    y_raw = current.extra.get("y_raw")
    if y_raw is None:
        y_raw = fitter.simulator(current.effects, current.terms).simulate(current.p)[0]
    y0, cols, own, start = current.y, np.zeros(current.y.shape + (0,)), (), None
    j = fitter.outputs.index(cand.output) if cand.output else None
    if cand.kind in ("model", "parameter"):
        own = tuple(fp for fp in cand.params if fp.name in r.params)
        if not own:
            return None
        start = r.fit.extra.get("start_p", current.p)
        effects = current.effects | frozenset(cand.effects)
        y0, cols = current.post.apply(fitter.simulator(effects, current.terms).simulate(start)[0],
                                      fitter.raw_sensitivity(effects, start, own, current.terms))
    elif cand.kind == "delay":
        y0 = r.fit.post.apply(y_raw)
    elif cand.kind == "bias":
        cols = fitter.offset_gain_columns([j], [], None, current.post.ramp)[0]
    else:  # gain: the column is the output without its offsets
        post = current.post.copy()
        post.bias.pop(cand.output, None)
        cols = fitter.offset_gain_columns([], [j], post.apply(y_raw), current.post.ramp)[0]
    member = Member(cand.name, y0, cols, "volume_flow_m3s" in cand.signature or _moves_flow(fitter, cols))
    return _Side(member, r.fit, r.primary_output, r.dof, r, cand, own, start)


def _moves_flow(fitter: Fitter, cols: np.ndarray) -> bool:
    """Whether a member's own columns move the logged flow on the training rows (scaled column norm at least 1, the
    rule of :meth:`~.fitting.Fitter.identifiable`): valve a's shift does, through the core's flow loss, though its
    signature is on the temperatures. Such a member's pair is refit with the flow equation's parameters."""
    if "volume_flow_m3s" not in fitter.outputs or cols.shape[2] == 0:
        return False
    j = fitter.outputs.index("volume_flow_m3s")
    ok = np.isfinite(fitter.y_meas[:, j]) & fitter.log.train
    return bool(np.any(np.sqrt(np.sum((cols[ok, j, :] / fitter.sigma[j]) ** 2, axis=0)) >= 1.0))


def _term_side(fitter: Fitter, current: Fit, alone: Fit, record: dict) -> _Side:
    """A discovered term that lost its whole-model refit, linearised at ``current`` (its coefficients from 0)."""
    t = alone.terms[-1]
    cols = discovery.term_columns(fitter, current, t)
    return _Side(Member(f"term {t.name}", current.y, cols), alone, "supply_temp_c", len(t.features),
                 term=t, record=record)


def _pair_sides(fitter: Fitter, current: Fit, open_round: list[CandidateResult], lib, rejected_terms
                ) -> list[_Side]:
    """The pair step's members: the ``PAIR_CANDIDATES`` candidates of the last round whose screening step removed
    the most training cost (whatever it did on the held-out rows), and the discovered terms that lost their
    whole-model refit."""
    scored = sorted((r for r in open_round if r.fit is not None), key=lambda r: -r.train_reduction)
    sides = [_candidate_side(fitter, current, r, next(c for c in lib if c.name == r.name))
             for r in scored[:PAIR_CANDIDATES]]
    return [sd for sd in sides if sd is not None] + [_term_side(fitter, current, f, rec) for f, rec in rejected_terms]


@dataclass
class _PairModel(Structure):
    """A pair's structure and its start for the full refit (the linearised step applied)."""

    term: DiscoveredTerm | None = None


def _pair_model(fitter: Fitter, current: Fit, free: list[FreeParam], sides: list[_Side], step: Step
                ) -> _PairModel:
    """The structure of ``current`` with both members in, started at the linearised joint step ``step``."""
    flow = any(sd.member.flow_side for sd in sides)
    moved = [(fp, step.theta[k]) for k, fp in enumerate(free) if flow or fp.name not in FLOW_PARAMS]
    p, effects, post = current.p.copy(), current.effects, current.post.copy()
    model = _PairModel(effects, p, post, [fp for fp, _ in moved], [], [], None)
    k = len(free)
    for sd in sides:
        theta = step.theta[k:k + sd.member.cols.shape[2]]
        k += len(theta)
        if sd.term is not None:
            model.term = discovery.term_from(list(sd.term.features[:-1]), theta, sd.term.name, sd.term.location)
        elif sd.cand.kind in ("model", "parameter"):
            model.effects |= frozenset(sd.cand.effects)
            for fp, th in zip(sd.own, theta):
                i = fitter.names.index(fp.name)
                p[i] = sd.start_p[i]
                moved.append((fp, th))
        elif sd.cand.kind == "delay":
            post.delays[sd.cand.output] = sd.result.fit.post.delays[sd.cand.output]
        else:
            (model.bias if sd.cand.kind == "bias" else model.gain).append(sd.cand.output)
    model.free = [fp for fp, _ in moved]
    model.p = fitter.step_params(p, model.free, np.array([th for _, th in moved]))
    return model


def _refit_pair(fitter: Fitter, current: Fit, model: _PairModel, quick: bool) -> Fit:
    """The whole model refit with both members (a term's coefficients alternated with the refit, as in discovery)."""
    term, p, post = model.term, model.p, model.post
    for _ in range(DISCOVERY_ALTERNATIONS if term else 1):
        terms = current.terms + ((term,) if term else ())
        fit = fitter.fit(model.effects, p, model.free, post, bias_outputs=model.bias, max_nfev=6 if quick else 8,
                         terms=terms, gain_outputs=gains(post, model.gain))
        p, post = fit.p, fit.post
        if term:
            term = discovery.refit_coefficients(fitter, fit, term)
    if term:
        fit = fitter.evaluate(model.effects, p, post, fit.free, terms=current.terms + (term,))
    return fit


def _pair_gate(fitter: Fitter, current: Fit, fit: Fit, sides: list[_Side], lr: float, m: int) -> tuple[str, dict]:
    """Why a refit pair cannot be kept ('' if it can), and its figures: the forward step's gates with both members'
    parameters counted together (each member's primary output), and each member must remove ``FORWARD_MIN`` of the
    held-out structure the other leaves alone."""
    q = sum(sd.dof for sd in sides)
    p_value = float(stats.chi2.sf(lr, q)) if lr > 0 else 1.0
    info = {"explained_holdout": (current.cost_holdout - fit.cost_holdout) / max(fitter.structure(current.y), 1e-300),
            "lr": lr, "dof": q, "p_value": p_value, "p_threshold": ALPHA / m}
    if not fit.cost_holdout < current.cost_holdout:
        return "does not lower the held-out error", info
    for sd in sides:
        need = BIAS_MIN if sd.cand is not None and sd.cand.kind == "bias" else FORWARD_MIN
        share, bic = output_share(fitter, current, fit, sd.primary), bic_change(fitter, fit, current, q, sd.primary)
        info[f"explained_{sd.primary}"], info[f"bic_change_{sd.primary}"] = share, bic
        if share < need:
            return (f"removes {100 * share:.0f} % of the held-out structure of {sd.primary} (needs "
                    f"{100 * need:.0f} %)"), info
        if not bic < 0:
            return f"information criterion on the training rows of {sd.primary} does not fall ({bic:+.1f})", info
    if p_value >= ALPHA / m:
        return f"not significant on the training rows (p = {p_value:.2g} >= {ALPHA / m:.2g})", info
    for sd, other in zip(sides, sides[::-1]):
        share = structure_share(fitter.structure(other.alone_fit.y), fitter.structure(fit.y))
        info[f"needed_{sd.name}"] = share
        if share < FORWARD_MIN:
            return (f"{sd.name} removes {100 * share:.0f} % of the held-out structure {other.name} leaves alone "
                    f"(needs {100 * FORWARD_MIN:.0f} %): the pair is {other.name} with a passenger"), info
        least = MIN_ABS_VALUE.get(sd.name)
        if least is not None and max(abs(fit.p[fitter.names.index(fp.name)]) for fp in sd.own) < least:
            return f"{sd.name}'s parameters stay below {least:g} in size", info
    return "", info


def pair_step(fitter: Fitter, current: Fit, free: list[FreeParam], lib, rejected_terms, room: int, quick: bool,
               rnd: int, say, notes: list[str]
               ) -> tuple[Fit, list[FreeParam], list[CandidateResult], dict | None, list[dict]]:
    """Pairs of effects that only help together (procedure step 7 of :mod:`.pipeline`). Returns the model, its
    free parameters, the candidates kept (as results of round ``rnd``), the record of a term kept with one, and the
    refit pairs' records."""
    open_round = current.extra.get("open_round")
    c_o, n_o = fitter.output_costs(current.y)
    if open_round is None or room < 1 or not np.any(c_o / np.maximum(n_o, 1) >= STRUCTURE_MIN):
        return current, free, [], None, []
    sides = _pair_sides(fitter, current, open_round, lib, rejected_terms)
    exclude = [(a, b) for a in range(len(sides)) for b in range(a + 1, len(sides))
               if (sides[a].term is None) == (sides[b].term is None) and (sides[a].term is not None or room < 2)]
    m = len(sides) * (len(sides) - 1) // 2 - len(exclude)
    if m < 1:
        return current, free, [], None, []
    dy = current.extra.get("dy_free")
    dy = fitter.raw_sensitivity(current.effects, current.p, free, current.terms) if dy is None else dy
    frame = Frame(fitter.y_meas, fitter.sigma, fitter.log.train, fitter.log.holdout)
    ranked, _ = screen_pairs(frame, current.y, current.post.apply(np.zeros(dy.shape[:2]), dy)[1],
                             np.array([fp.name in FLOW_PARAMS for fp in free]), [sd.member for sd in sides],
                             FORWARD_MIN, exclude)
    top = [([sides[i] for i in st_.members], st_) for st_ in ranked[:PAIR_REFIT]]
    say(f"pairs: {m} screened jointly, refitting {', '.join(' + '.join(sd.name for sd in two) for two, _ in top)}")
    if not top:
        notes.append(f"pairs: {m} pairs of {', '.join(sd.name for sd in sides)} screened jointly; in none does each "
                     f"member remove {100 * FORWARD_MIN:.0f} % of the held-out structure the other leaves alone")
    records, nll_current = [], training_nll(fitter, current) if top else 0.0
    for two, st_ in top:  # best linearised step first; the first pair that passes the gates is kept
        fit = _refit_pair(fitter, current, _pair_model(fitter, current, free, two, st_), quick)
        reason, info = _pair_gate(fitter, current, fit, two, nll_current - training_nll(fitter, fit), m)
        records.append(dict(info, members=[sd.name for sd in two], screened_pairs=m, status="rejected" if reason else
                            "accepted", reason=reason, linear_holdout_cost=float(st_.cost_holdout.sum()),
                            linear_joint_share=st_.joint_share, cost_holdout=fit.cost_holdout))
        notes.append(f"pairs: {' + '.join(records[-1]['members'])} {records[-1]['status']}"
                     + (f" ({reason})" if reason else ""))
        if not reason:
            return (*_accept_pair(fitter, current, free, two, fit, info, rnd, notes), records)
    return current, free, [], None, records


def _accept_pair(fitter: Fitter, current: Fit, free: list[FreeParam], sides: list[_Side], fit: Fit, info: dict,
                 rnd: int, notes: list[str]) -> tuple[Fit, list[FreeParam], list[CandidateResult], dict | None]:
    """Keeps a pair: its candidates as accepted results, its term in the model; says that they were found only
    jointly and how each fared alone."""
    kept, term_record = [], None
    for sd, other in zip(sides, sides[::-1]):
        together = output_share(fitter, current, fit, sd.primary)
        why = (f"accepted only jointly with {other.name}: alone (the other missing) it {sd.alone()}, together "
               f"they remove {100 * together:.0f} % (information criterion {info[f'bic_change_{sd.primary}']:+.1f}, "
               f"p = {info['p_value']:.2g}); the two mask each other, this log identifies them only together")
        notes.append(f"pairs: {sd.name} {why}")
        if sd.term is not None:
            t = fit.terms[-1]
            term_record = dict(sd.record, term=t.as_dict(), formula=t.formula(), words=t.description,
                               explained_holdout=together, bic_change=info["bic_change_supply_temp_c"], accepted=True,
                               jointly_with=other.name)
            continue
        acc = dataclasses.replace(sd.result, round=rnd, status="accepted", reason=why, jointly_with=other.name,
                                  fit=fit, cost_train=fit.cost_train, cost_holdout=fit.cost_holdout,
                                  explained_holdout=info["explained_holdout"], explained_primary=together,
                                  bic_change=info[f"bic_change_{sd.primary}"], lr=info["lr"], dof=info["dof"],
                                  p_value=info["p_value"], p_threshold=info["p_threshold"],
                                  params={fp.name: float(fit.p[fitter.names.index(fp.name)]) for fp in sd.own})
        record_own(acc, sd.cand, fit, fitter.log.dt_s)
        kept.append(acc)
        free = free + [fp for fp in sd.own if fp not in free]
    fit.states = fitter.simulator(fit.effects, fit.terms).simulate(fit.p)[1]
    fit.free = tuple(fp.name for fp in free)
    return fit, free, kept, term_record
