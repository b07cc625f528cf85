"""A search along a reversing input on the nonlinear cost, on a step whose plan turns against the last one.

The real-time iteration takes one Gauss-Newton QP a sample, linearised at the shifted plan. Where the box's
response is bilinear in an input and a state (valve a's core flow times the heater body's excess over the air
it passes), and that input's pull on the tracked air changes sign between a transient and rest, the QP
linearised at one end of the input's stroke plans the other end, the next QP linearised there plans the first,
and the plans alternate every sample. A second Gauss-Newton QP does not help: the iteration itself has the
two-cycle (a converged SQP alternates the same way), and neither end is the nonlinear cost's best: on the
recirculating box the QP's plan with valve a open over the whole horizon costs 4-53 % less than the cheaper of the
QP's plan and its linearisation point, at every step of the alternation's first 40 s (docs/identification.md, "The
alternation at its root: a search along the reversing input").

So where the step's plan reverses, the QP's linear model is not trusted along that input: :func:`turned_inputs`
names each input whose first move turns against the last step's, both beyond a share of the input's range, and
:func:`candidates` builds the QP's plan with that input's whole profile replaced by the linearisation point's
(the input as the last plan had it), by its upper bound and by its lower bound (the QP's bounds of each stage, the
rate limits of the first). The solver (:class:`.rti_osqp.RtiOsqpSolver`, ``reversal_search``) prices them on the
problem's nonlinear cost (:class:`.plan_merit.PlanMerit`, the model's rollout) and takes the cheapest of these
and the QP's own plan. No QP is added: one call of a generated function prices the three candidates of an input.
Nothing in it knows which input reverses.

The controller's default (``MpcSettings``): the search at 0.05 of each input's range, acting only after 20 plain
steps in a row (:func:`eligible_inputs`) and taking a candidate only where it costs 10 % less than the QP's plan
(docs/identification.md, "The guarded search as the default": the built-in bench today's in every scenario, the
refined MPC's IAE on both recirculating boxes lower). ``MpcSettings.rti_reversal_bound_only`` (off) prices the
linearisation point's profile only where it starts at the input's bound (:func:`at_bound`; docs/identification.md,
"Recirculation's refined winter, traced"). ``MpcSettings.rti_reversal_second_qp`` (off) takes one more Gauss-Newton QP,
linearised at the first QP's plan, on a step whose plan reverses (:func:`at_upper_bound` for its heater rule;
docs/robustness.md sec. 2.41).
"""

from __future__ import annotations

import numpy as np


def check_share(name: str, share, of: str = "each input's range") -> float:
    """``share`` (of ``of``, for the message) as a float in [0, 1) (0: off); ValueError naming ``name`` and the
    range otherwise."""
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not np.isfinite(share) \
            or not 0.0 <= share < 1.0:
        raise ValueError(f"{name} = {share!r}, allowed: a share of {of} in [0, 1) (0: off)")
    return float(share)


def check_wait(name: str, steps) -> int:
    """``steps`` as an int in [0, 3600] (0: no wait); ValueError naming ``name`` and the range otherwise."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 0 <= steps <= 3600:
        raise ValueError(f"{name} = {steps!r}, allowed: an integer number of plain steps in [0, 3600] (0: no wait)")
    return int(steps)


def eligible_inputs(turned: np.ndarray, turned_before: np.ndarray | None, quiet_run: int,
                    wait_steps: int) -> np.ndarray:
    """Of the ``turned`` inputs, those the search prices: none while ``quiet_run`` (plain one-QP steps in a row,
    this one included) is at most ``wait_steps``; with ``turned_before`` (the inputs the last step's plan turned;
    None: no such rule) only those in it, an input whose reversal repeats (a two-cycle)."""
    turned = np.asarray(turned, dtype=int)
    if quiet_run <= wait_steps:
        return turned[:0]
    if turned_before is not None:
        turned = turned[np.isin(turned, turned_before)]
    return turned


def last_moves(last_move: np.ndarray | None, move: np.ndarray, span: np.ndarray, share: float) -> np.ndarray:
    """Per input, the last plan's first move larger than ``share`` x the input's ``span``: ``move`` where it is
    that large, else the one kept in ``last_move`` (0 where there is none), so a step that holds an input between
    two reversing moves does not hide the second."""
    big = np.abs(move) > share * np.asarray(span, float)
    kept = np.zeros_like(move, dtype=float) if last_move is None else last_move
    return np.where(big, move, kept)


def turned_inputs(last_move: np.ndarray | None, move: np.ndarray, span: np.ndarray, share: float) -> np.ndarray:
    """Indices of the inputs whose ``move`` (this plan's first move from the command in force, scaled) turns
    against ``last_move`` (:func:`last_moves`), each larger than ``share`` x that input's ``span`` (its scaled
    range). Empty without a last move or with ``share`` 0."""
    if last_move is None or share <= 0.0:
        return np.zeros(0, dtype=int)
    big = share * np.asarray(span, float)
    turned = (np.sign(move) * np.sign(last_move) < 0) & (np.abs(move) > big) & (np.abs(last_move) > big)
    return np.flatnonzero(turned)


def turns_and_moves(last_move: np.ndarray | None, move: np.ndarray, span: np.ndarray,
                    share: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`turned_inputs` and :func:`last_moves` of one ``move`` (1-D) together: the same two arrays, to the bit,
    in one pass over the few inputs in plain Python (the two calls cost 6-8 us in a dozen numpy calls on six
    values; this 2-3 us). The same operations on the same values: the share of each span as numpy multiplies it
    (``share * span``), then comparisons and a choice, which are exact; a sign product below 0 is a pair of opposite
    nonzero signs (``np.sign`` of nan is nan, of a zero a zero: neither turns, as neither does here)."""
    bigs = (share * np.asarray(span, float)).tolist()
    moves = move.tolist()
    kept = [0.0] * len(moves) if last_move is None else last_move.tolist()
    out = np.array([m if abs(m) > b else k for m, b, k in zip(moves, bigs, kept)], dtype=float)
    if last_move is None or share <= 0.0:
        return np.zeros(0, dtype=int), out
    turned = [i for i, (m, k, b) in enumerate(zip(moves, kept, bigs))
              if ((m < 0.0 < k) or (k < 0.0 < m)) and abs(m) > b and abs(k) > b]
    return np.array(turned, dtype=np.intp), out


def candidates(u_qp: np.ndarray, u_lin: np.ndarray, u_lo: np.ndarray, u_hi: np.ndarray, i: int,
               rate: np.ndarray | None = None) -> list[np.ndarray]:
    """The QP's plan ``u_qp`` (N x nu, scaled) with input ``i``'s profile replaced by the linearisation point's
    (``u_lin``), by ``u_hi`` and by ``u_lo`` (N x nu each, the QP's bounds), each within the bounds and, with
    ``rate`` ((N-1) x nu, the QP's largest change between stages k-1 and k, scaled), passed forward through the
    rate limits, so every candidate is a plan the QP could have given."""
    out = []
    for profile in (u_lin[:, i], u_hi[:, i], u_lo[:, i]):
        u = np.array(u_qp, float)
        u[:, i] = rate_limited(profile, u_lo[:, i], u_hi[:, i], None if rate is None else rate[:, i])
        out.append(u)
    return out


#: A profile's first stage within this share of the input's range of the stage's bound is at that bound
#: (:func:`at_bound`). ASSUMPTION: 2 % of the range is beyond the QP's tolerance on an active bound (OSQP's
#: plans on a bound sit on it to a few 0.01 % of the range) and well within the strokes the search is for.
BOUND_SHARE = 0.02


def at_bound(u_lin: np.ndarray, u_lo: np.ndarray, u_hi: np.ndarray, i: int, span: float,
             share: float = BOUND_SHARE) -> bool:
    """True where input ``i``'s profile in ``u_lin`` (N x nu, scaled; the linearisation point's plan) starts at
    an end of the input's stroke, within ``share`` x ``span`` (the input's scaled range) of its lower or upper
    bound: where a two-cycle of the real-time iteration rests (``MpcSettings.rti_reversal_bound_only``). The
    stroke's ends are the last stage's bounds (``u_lo``, ``u_hi``, N x nu, the QP's bounds): the first stage's
    carry the rate window around the applied input, which would count every profile at a bound where the window
    is narrower than the share."""
    tol = share * float(span)
    first = float(u_lin[0, i])
    return bool(abs(first - float(u_hi[-1, i])) <= tol or abs(first - float(u_lo[-1, i])) <= tol)


def at_upper_bound(U: np.ndarray, u_hi: np.ndarray, i: int, span: float, share: float = BOUND_SHARE) -> bool:
    """True where input ``i``'s first stage in ``U`` (N x nu, scaled) is within ``share`` x ``span`` of its range's
    upper end ``u_hi`` (nu, scaled): the input held at its bound (the heater at its full power)."""
    return bool(float(U[0, i]) >= float(u_hi[i]) - share * float(span))


#: The rules of a second Gauss-Newton QP on a reversing step (``MpcSettings.rti_reversal_second_qp``).
SECOND_QP_RULES = ("off", "reversal", "heater_bound")


def check_second_qp(name: str, rule) -> str:
    """``rule`` if it is one of :data:`SECOND_QP_RULES`; ValueError naming ``name`` and the choices otherwise."""
    if rule not in SECOND_QP_RULES:
        raise ValueError(f"{name} = {rule!r}, allowed: one of {list(SECOND_QP_RULES)} ('off': no second QP)")
    return str(rule)


def check_second_qp_with(name: str, rule: str, search_name: str, search: float, one_qp_steps: bool, conflict: str,
                         allowed: str) -> None:
    """``rule`` (:data:`SECOND_QP_RULES`, the field ``name``) refused where it cannot act: without the search's share
    (``search``, the field ``search_name``: it names the reversal) and where no step is a plain one-QP step
    (``one_qp_steps`` False; ``conflict`` names the settings that make it so, ``allowed`` what may be set instead).
    ValueError naming the fields."""
    if rule == "off":
        return
    if not search:
        raise ValueError(f"{name} = {rule!r} needs {search_name} > 0 (the reversal's share of each input's range)")
    if not one_qp_steps:
        raise ValueError(f"{name} = {rule!r} with {conflict}: it never fires there (a plain one-QP step's only); "
                         f"allowed: {allowed}")


def rate_limited(profile: np.ndarray, lo: np.ndarray, hi: np.ndarray, rate: np.ndarray | None) -> np.ndarray:
    """``profile`` (N, scaled) clipped to ``[lo, hi]`` stage by stage and, with ``rate`` (N-1), each stage to
    within ``rate[k-1]`` of the stage before it (forward, from the clipped first stage)."""
    out = np.minimum(np.maximum(np.asarray(profile, float), lo), hi)
    if rate is not None:
        for k in range(1, out.size):
            out[k] = min(max(out[k], out[k - 1] - rate[k - 1], lo[k]), out[k - 1] + rate[k - 1], hi[k])
    return out
