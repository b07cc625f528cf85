"""The joint refit (procedure step 8 of :mod:`.pipeline`): when the supply temperature stays structured after forward
selection, discovery and the pair step, the effects kept and the last round's best candidates are refit all at once,
without the discovered terms, and eliminated backward; discovery then runs on what is left. The result replaces the
forward path's model if it removes ``FORWARD_MIN`` of that model's held-out supply structure
(docs/identification.md, "Effects that only help together", "The joint refit").

Why: forward selection adds one effect at a time, each scored on a fit that its missing partners have bent, and a
pair step frees two at a time. With three or more effects masking one another (a delay just under its gate, a valve
shift whose signature the nominal refit absorbed, a recirculation that a term at the wrong place stood in for) no
single step is taken; a backward elimination from a larger joint set does not need any one member to pay alone.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from hvac_mpc.models.parameters import Parameters

from .candidates import Candidate
from .fitting import Fit, Fitter, FreeParam
from .selection import (BIAS_MIN, FIT_ERRORS, FORWARD_MIN, SAME_RESIDUAL_CORR, STRUCTURE_MIN, CandidateResult,
                        correction_correlation, gains, output_share, record_own, supply_ratio)
from .simulator import OutputPost
from .workers import cpu_seconds, fork_map

#: Candidates of the last forward round joined to the effects kept (the most training cost removed by their
#: screening step, whatever they did on the held-out rows: the pair step's rule).
JOINT_CANDIDATES = 4
#: Share of the training cost a candidate's screening step must have removed to join: one that does not help the
#: training rows even alone has nothing to give the joint set, and every member costs a refit per elimination round.
JOINT_MIN_TRAIN = 0.05
#: Function evaluations of the joint refit (all members at once, and again the members left after the elimination)
#: and of each refit without one member (a step from the joint fit, only to rank and test the members).
JOINT_NFEV = 6
ELIMINATION_NFEV = 2
#: After the first elimination round a member is refit again only while its last margin (the share its removal cost
#: minus the share it needs) was below this (:func:`_eliminate`).
ELIMINATION_SLACK = 0.25


@dataclass
class _Member:
    """One effect of the joint set: its candidate, its result (kept earlier, or scored in the last round)."""

    cand: Candidate
    result: CandidateResult

    @property
    def name(self) -> str:
        return self.cand.name

    @property
    def need(self) -> float:
        return BIAS_MIN if self.cand.kind == "bias" else FORWARD_MIN

    @property
    def primary(self) -> str:
        return self.result.primary_output or "supply_temp_c"


@dataclass
class Structure:
    """A model structure to refit: effects, parameter start, output corrections, free parameters, the outputs whose
    offset and drift or gain are refit (the pair step's start extends it with its term)."""

    effects: frozenset
    p: np.ndarray
    post: OutputPost
    free: list[FreeParam]
    bias: list[str]
    gain: list[str]

    def fit(self, fitter: Fitter, nfev: int) -> Fit:
        return fitter.fit(self.effects, self.p, self.free, self.post, bias_outputs=self.bias, max_nfev=nfev,
                          gain_outputs=gains(self.post, self.gain))


def _own(m: _Member) -> list[FreeParam]:
    return [fp for fp in m.cand.params if fp.name in m.result.params] if m.cand.kind in ("model", "parameter") else []


def _members(accepted: list[CandidateResult], open_round: list[CandidateResult], lib) -> list[_Member]:
    """The effects kept and the ``JOINT_CANDIDATES`` candidates of the last round that removed the most training
    cost (a model or parameter candidate only with parameters of its own that moved)."""
    by_name = {c.name: c for c in lib}
    kept = [_Member(by_name[a.name], a) for a in accepted if a.name in by_name]
    names = {m.name for m in kept}
    scored = sorted((r for r in open_round if r.fit is not None and r.name not in names
                     and r.train_reduction >= JOINT_MIN_TRAIN), key=lambda r: -r.train_reduction)
    new = [_Member(by_name[r.name], r) for r in scored]
    new = [m for m in new if m.cand.kind not in ("model", "parameter") or _own(m)]
    return kept + new[:JOINT_CANDIDATES]


def _structure(fitter: Fitter, current: Fit, free: list[FreeParam], members: list[_Member]) -> Structure:
    """The current model without its terms and with every member in: each new member started where its screening
    step left it (its parameters, its delay); the offsets and gains refit with the rest."""
    p, post = current.p.copy(), current.post.copy()
    effects, free = set(current.effects), list(free)
    names = {fp.name for fp in free}
    for m in members:
        effects |= set(m.cand.effects)
        if m.cand.kind == "delay" and m.result.fit is not None:
            post.delays[m.cand.output] = m.result.fit.post.delays[m.cand.output]
        for fp in _own(m):
            if fp.name not in names:
                i = fitter.names.index(fp.name)
                p[i] = m.result.fit.p[i]
                free.append(fp)
                names.add(fp.name)
    bias = list(dict.fromkeys(list(post.bias) + [m.cand.output for m in members if m.cand.kind == "bias"]))
    gain = [m.cand.output for m in members if m.cand.kind == "gain"]
    return Structure(frozenset(effects), p, post, free, bias, gain)


def _without(fitter: Fitter, s: Structure, fit: Fit, m: _Member, base: Parameters) -> Structure:
    """``s`` at ``fit`` with member ``m`` taken out (its parameters back at the base values)."""
    p, post = fit.p.copy(), fit.post.copy()
    base_vec = np.array(base.vector())
    own = {fp.name for fp in m.cand.params}
    for name in own:
        i = fitter.names.index(name)
        p[i] = base_vec[i]
    if m.cand.kind == "delay":
        post.delays.pop(m.cand.output, None)
    if m.cand.kind in ("bias", "gain"):
        getattr(post, m.cand.kind).pop(m.cand.output, None)
    return Structure(s.effects - frozenset(m.cand.effects), p, post, [fp for fp in s.free if fp.name not in own],
                      [o for o in s.bias if not (m.cand.kind == "bias" and o == m.cand.output)],
                      [o for o in s.gain if not (m.cand.kind == "gain" and o == m.cand.output)])


def _at(s: Structure, fit: Fit) -> Structure:
    return dataclasses.replace(s, p=fit.p.copy(), post=fit.post.copy())


def _eliminate(fitter: Fitter, s: Structure, fit: Fit, members: list[_Member], base: Parameters, max_effects: int,
               say, log: list[str], rounds: list[dict]) -> tuple[Structure, Fit, list[_Member], dict]:
    """Backward elimination: refit without each member (side by side); drop the one with the smallest margin, the share
    of its primary output's held-out structure its removal costs minus the share it needs, while that margin is
    negative (or while more than ``max_effects`` remain); repeat. After the first round only the members whose last
    margin was below ``ELIMINATION_SLACK`` are refit again; the others keep their last share (taking out a member that
    earned too little hardly moves the share of one far above its need; the backward pass re-tests every kept effect
    by a refit). Returns the structure, its fit, the members left and each one's last share; ``rounds`` gets the shares
    of the members refit in each round."""
    shares: dict[str, float] = {}
    while members:
        todo = [i for i, m in enumerate(members) if m.name not in shares or shares[m.name] - m.need < ELIMINATION_SLACK]
        outs = [_without(fitter, s, fit, members[i], base) for i in todo]
        say(f"joint refit: re-testing {', '.join(members[i].name for i in todo)}")
        fits = fork_map(lambda j: outs[j].fit(fitter, ELIMINATION_NFEV), len(todo))
        shares.update({members[i].name: float(output_share(fitter, f, fit, members[i].primary))
                       for i, f in zip(todo, fits)})
        rounds.append({"refit": {members[i].name: shares[members[i].name] for i in todo}})
        k = int(np.argmin([shares[m.name] - m.need for m in members]))
        if shares[members[k].name] >= members[k].need and len(members) <= max_effects:
            break
        m = members[k]
        why = f"needs {100 * m.need:.0f} %" if shares[m.name] < m.need else \
            f"the least needed of {len(members)}, at most {max_effects} effects"
        log.append(f"joint refit: {m.name} eliminated (taking it out costs {100 * shares[m.name]:.0f} % of the "
                   f"held-out structure of {m.primary}; {why})")
        if k in todo:
            j = todo.index(k)
            s, fit = _at(outs[j], fits[j]), fits[j]
        else:  # kept on its last share and yet the least needed: refit without it now
            out = _without(fitter, s, fit, m, base)
            fit = out.fit(fitter, ELIMINATION_NFEV)
            s = _at(out, fit)
        members = members[:k] + members[k + 1:]
    return s, fit, members, shares


def joint_step(fitter: Fitter, current: Fit, free: list[FreeParam], accepted: list[CandidateResult],
               open_round: list[CandidateResult] | None, lib, base: Parameters, max_effects: int, rnd: int,
               discover: Callable[[Fit, list[FreeParam], list[str]], tuple[Fit, dict | None, list]], say,
               notes: list[str]) -> tuple[Fit, list[FreeParam], list[CandidateResult], dict | None, dict | None]:
    """The joint refit (module docstring). Returns the model, its free parameters, the effects kept (those of the
    forward path it keeps and the new ones as results of round ``rnd``), the discovered term's record (``None``: the
    forward path's stands) and the step's record (``None`` if it did not run). A fit that fails (as a candidate's
    fit that fails in forward selection) leaves the forward path's model, the record saying why (``failed``)."""
    if (open_round is None or "supply_temp_c" not in fitter.outputs
            or supply_ratio(fitter, current) < STRUCTURE_MIN):
        return current, free, accepted, None, None
    members = _members(accepted, open_round, lib)
    kept_names = {a.name for a in accepted}
    if not [m for m in members if m.name not in kept_names]:
        return current, free, accepted, None, None
    log: list[str] = []
    try:
        s, fit, left, shares, cpu, rounds = _refit(fitter, current, free, members, base, max_effects, say, log)
        refit, c2 = fit, cpu_seconds()
        fit, discovered, _ = discover(fit, s.free, log)
    except FIT_ERRORS as exc:
        notes.append(f"joint refit of {', '.join(m.name for m in members)}: fit failed ({exc}); the forward path's "
                     "model stands")
        return current, free, accepted, None, {"members": [m.name for m in members], "kept": [], "accepted": False,
                                               "failed": str(exc), "notes": log}
    cpu["discovery"] = cpu_seconds() - c2
    record = {"members": [m.name for m in members], "kept": [m.name for m in left], "shares": shares,
              "term": discovered["formula"] if discovered and discovered.get("accepted") else "", "notes": log,
              "cpu_s": cpu, "elimination": rounds}
    verdict = _decide(fitter, current, fit, record)
    if not record["accepted"]:
        notes.append(verdict)
        return current, free, accepted, None, record
    notes.extend(log)
    notes.append(verdict)
    notes.extend(_replaced_terms(fitter, current, refit, fit, record))
    return fit, s.free, _kept(fitter, accepted, left, refit, fit, shares, rnd), discovered, record


def _replaced_terms(fitter: Fitter, current: Fit, refit: Fit, fit: Fit, record: dict) -> list[str]:
    """The forward path's discovered terms the joint model replaces (a term the pair step kept with its partner, chosen
    on the residual of a model without that partner), in words: whether they and the joint model's term explain the
    same residual (their models' held-out corrections against the joint fit without a term, ``refit``, correlate at
    ``SAME_RESIDUAL_CORR`` or more). ``record`` gets ``replaced_terms``."""
    if not current.terms:
        return []
    corr = correction_correlation(fitter, current, fit, refit)
    record["replaced_terms"] = [{"name": t.name, "formula": t.formula(), "location": t.location,
                                 "correlation": corr} for t in current.terms]
    new = record["term"] or "no term"
    same = (f"explain the same residual ({new} and it, correlation {corr:.2f} of their models' held-out corrections "
            f"against the effects refit together without a term); this log cannot tell them apart, and the joint "
            f"model fits the held-out rows better" if corr >= SAME_RESIDUAL_CORR else
            f"do not explain the same residual (correlation {corr:.2f}); the joint model fits the held-out rows better")
    return [f"joint refit: replaces term {t.formula()} (found on the residual of a model without the effects kept "
            f"now): the two {same}" for t in current.terms]


def _refit(fitter: Fitter, current: Fit, free: list[FreeParam], members: list[_Member], base: Parameters,
           max_effects: int, say, log: list[str]) -> tuple[Structure, Fit, list[_Member], dict, dict, list[dict]]:
    """The joint fit of all members and the backward elimination, the members left refit together as the whole set
    was. Returns the structure, its fit, the members left, each member's last share, the CPU seconds of the two
    parts and the elimination's rounds (the shares of the members refit in each)."""
    c0 = cpu_seconds()
    s = _structure(fitter, current, free, members)
    say(f"joint refit: {', '.join(m.name for m in members)} together, without the discovered terms")
    fit = s.fit(fitter, JOINT_NFEV)
    s = _at(s, fit)
    c1 = cpu_seconds()
    rounds: list[dict] = []
    s, fit, left, shares = _eliminate(fitter, s, fit, members, base, max_effects, say, log, rounds)
    if len(left) < len(members):
        fit = s.fit(fitter, JOINT_NFEV)
        s = _at(s, fit)
    fit.free = tuple(fp.name for fp in s.free)
    return s, fit, left, shares, {"joint_fit": c1 - c0, "elimination": cpu_seconds() - c1}, rounds


def _decide(fitter: Fitter, current: Fit, fit: Fit, record: dict) -> str:
    """Whether the joint model ``fit`` replaces the forward path's ``current``: it must remove ``FORWARD_MIN`` of the
    held-out supply structure that ``current`` leaves and lower the total held-out error. Fills ``record``
    (``accepted`` the decision); returns the verdict in words."""
    gain = output_share(fitter, current, fit, "supply_temp_c")
    record.update(explained_supply=gain, cost_holdout=fit.cost_holdout, cost_holdout_before=current.cost_holdout,
                  supply_rms_before=_supply_rms(fitter, current), supply_rms_after=_supply_rms(fitter, fit),
                  accepted=bool(gain >= FORWARD_MIN and fit.cost_holdout < current.cost_holdout))
    verdict = (f"kept: removes {100 * gain:.0f} % of the held-out structure of supply_temp_c the forward path left"
               if record["accepted"] else
               f"not kept: removes {100 * gain:.0f} % of the held-out structure of supply_temp_c the forward path left "
               f"(needs {100 * FORWARD_MIN:.0f} % and a lower held-out error)")
    return (f"joint refit of {', '.join(record['members'])} without the discovered terms, eliminated backward to "
            f"{', '.join(record['kept']) or 'nothing'}" + (f", then {record['term']}" if record["term"] else "")
            + f": {verdict}")


def _kept(fitter: Fitter, accepted: list[CandidateResult], left: list[_Member], refit: Fit, fit: Fit, shares: dict,
          rnd: int) -> list[CandidateResult]:
    """The effects of the joint model: those of the forward path it keeps (as they were), the forward path's others
    marked removed, the new ones as accepted results of round ``rnd``, all with the fit ``refit`` they were kept in
    (the joint model before discovery: the report's steps give a term found then its own step) and their parameters
    those of the joint model ``fit``."""
    names = {m.name for m in left}
    for a in accepted:
        if a.name not in names:
            a.status = "removed"
            a.reason = (f"eliminated in the joint refit: with the others in, taking it out costs "
                        f"{100 * shares.get(a.name, float('nan')):.0f} % of the held-out structure of {a.primary_output}")
    out = [a for a in accepted if a.name in names]
    for a in out:  # a term it was kept with is not in the joint model
        if a.jointly_with.startswith("term "):  # its step: the joint fit without the term, the new term its own
            a.reason += (f"; kept in the joint refit without the term: taking it out costs "
                         f"{100 * shares[a.name]:.0f} % of the held-out structure of {a.primary_output or 'supply_temp_c'}")
            a.jointly_with, a.fit = "", refit
    old = {a.name for a in out}
    for m in left:
        if m.name in old:
            continue
        acc = dataclasses.replace(
            m.result, round=rnd, status="accepted", fit=refit, cost_train=refit.cost_train,
            cost_holdout=refit.cost_holdout,
            reason=(f"kept in the joint refit: with the others in, taking it out costs {100 * shares[m.name]:.0f} % of "
                    f"the held-out structure of {m.primary}"),
            params={fp.name: float(fit.p[fitter.names.index(fp.name)]) for fp in _own(m)})
        record_own(acc, m.cand, fit, fitter.log.dt_s)
        out.append(acc)
    return out


def _supply_rms(fitter: Fitter, fit: Fit) -> float:
    """Held-out RMS error of the supply temperature, C."""
    j = fitter.outputs.index("supply_temp_c")
    e = (fitter.y_meas[:, j] - fit.y[:, j])[fitter.log.holdout]
    return float(np.sqrt(np.nanmean(e ** 2)))
