"""OSQP's step size ``rho`` at a reference change, chosen from the change QPs' own data (docs/architecture.md, 'The
change's step size').

A reference change's first QP is linearised at the plan made for the old reference; its residuals are far larger
than a plain step's, and OSQP starts it with the step size the plain steps' small warm-started QPs left (about
0.001-0.01), which it adapts only when its estimate differs by more than a factor of 5, a few times in hundreds of
iterations. The QPs after the change then inherit the step size the change's QPs raised. Two rules, each off by
default (:class:`ChangeStepSize`):

- *remembered* (``mode`` "last" or "kind"): a change's first QP starts from the step size OSQP's own adaptation reached
  in the first QP of the last change ("last") or of the last change of the same kind ("kind": the supply-temperature
  reference up, down or unchanged, :func:`change_kind`); the first change (of a kind) keeps OSQP's. "last_each" and
  "kind_each": so each QP of the change (the second from the last change's second QP's, ...), the later QPs' step
  size set in the refactorisation their relinearisation makes anyway.
- *restored* (``restore``): the first preparation after a change sets the step size back to the value it had before
  the change, so the plain steps after it start from the quiet seconds' step size, not the change's.

And two in :class:`.rti_osqp.RtiOsqpSolver`: OSQP's own step-size estimate taken more often (and at a smaller ratio)
in a change's QPs (``change_rho_interval``, ``change_rho_tolerance``, checked by :func:`check_adaptation`); a change's
QPs after the first held at the step size the first ended (or started) with, OSQP's adaptation off in them
(``change_rho_hold``, :data:`HOLD_INTERVAL`, checked by :func:`check_hold`; docs/architecture.md, 'The change's
second QP held').

ASSUMPTION: one change's first QP is like the next's (of the same kind) in its balance of primal and dual residual;
the remembered value is a start only, OSQP still adapts it within each QP.
"""

from __future__ import annotations

import numpy as np

#: :class:`ChangeStepSize`'s modes: "off" (OSQP's step size kept at a change), "last" (the last change's first QP's),
#: "kind" (the last change's of the same kind), "last_each" / "kind_each" (so for each QP of the change).
CHANGE_RHO = ("off", "last", "kind", "last_each", "kind_each")


#: OSQP's adaptation interval (iterations) that holds the step size: beyond any QP's iterations (OSQP's ``max_iter`` is
#: at most 100 000, ``MpcSettings``), so its adaptation check (every interval-th iteration) never comes.
HOLD_INTERVAL = 1_000_000


#: ``change_rho_hold``'s modes: "off" (OSQP adapts the change's later QPs' step size as set up), "end" (they run at
#: the step size the change's first QP ended with), "start" (at the one it started with: the value before the change,
#: or the one ``change_rho`` / ``rho_reset`` set at the change).
CHANGE_RHO_HOLD = ("off", "end", "start")


def check_hold(name: str, hold: str) -> str:
    """``hold`` (:data:`CHANGE_RHO_HOLD`) as given; ValueError naming ``name`` otherwise."""
    if hold not in CHANGE_RHO_HOLD:
        raise ValueError(f"{name} = {hold!r}, allowed: one of {list(CHANGE_RHO_HOLD)}")
    return hold


def change_kind(old_ref: np.ndarray, new_ref: np.ndarray) -> int:
    """The kind of a reference change: the sign of its supply-temperature step (entry 0 of the reference vectors,
    degC): +1 up, -1 down, 0 unchanged (a flow or split change alone)."""
    return int(np.sign(float(new_ref[0]) - float(old_ref[0])))


def check_change_rho(name: str, mode: str, restore: bool) -> None:
    """ValueError naming ``name`` where ``mode`` is not one of :data:`CHANGE_RHO` or ``restore`` not a bool."""
    if mode not in CHANGE_RHO:
        raise ValueError(f"{name} = {mode!r}, allowed: one of {list(CHANGE_RHO)}")
    if not isinstance(restore, bool):
        raise ValueError(f"{name}_restore = {restore!r}, allowed: True or False")


def check_adaptation(name: str, interval: int, tolerance: float) -> tuple[int, float]:
    """A change's step-size adaptation (``interval``: iterations in [0, 1000], 0 off; ``tolerance``: 0, OSQP's, or a
    factor in (1, 100]) as (int, float); ValueError naming ``name`` otherwise."""
    if isinstance(interval, bool) or not isinstance(interval, (int, np.integer)) or not 0 <= interval <= 1000:
        raise ValueError(f"{name} = {interval!r}, allowed: an integer in [0, 1000] (0: off)")
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) or not (
            tolerance == 0 or 1.0 < tolerance <= 100.0):
        raise ValueError(f"{name.replace('interval', 'tolerance')} = {tolerance!r}, allowed: 0 (OSQP's) or a factor in "
                         "(1, 100]")
    return int(interval), float(tolerance)


class ChangeStepSize:
    """The step size a reference change's QPs start from and the one the steps after it start from (module doc).

    The caller (:class:`.rti_osqp.RtiOsqpSolver`) calls :meth:`at_change` at a change before its QPs, :meth:`for_qp`
    before each later QP's relinearisation, :meth:`note` after each QP, :meth:`close_change` after the change step's QPs and :meth:`after_change` at each
    preparation's matrix update (the change step's own relinearisations come before :meth:`close_change`, so they
    keep the change's step size)."""

    def __init__(self, mode: str = "off", restore: bool = False):
        check_change_rho("ChangeStepSize: mode", mode, restore)
        self.mode, self.restore = mode, restore
        self.each = mode.endswith("_each")
        self.by_kind = mode.startswith("kind")
        # (change kind (0 for every change with "last"), the QP's index in the change) -> the step size it ended with
        self.remembered: dict[tuple[int, int], float] = {}
        self._key: int | None = None  # the kind of the change whose QPs run
        self._held: float | None = None  # the step size before the change, while its step's QPs run (restore)
        self._before: float | None = None  # the same after them, until the next preparation takes it in

    @property
    def active(self) -> bool:
        return self.mode != "off" or self.restore

    def forget(self) -> None:
        """A cold start: nothing remembered, nothing pending."""
        self.remembered.clear()
        self._key = self._held = self._before = None

    def at_change(self, rho_now: float, old_ref: np.ndarray, new_ref: np.ndarray) -> float | None:
        """A change's QPs are about to start with OSQP's step size ``rho_now``: the step size to start its first QP from
        (None: keep ``rho_now``)."""
        if self.restore:  # a change before the last one's value was taken in: the value before the first
            self._held = float(rho_now) if self._before is None else self._before
            self._before = None
        if self.mode == "off":
            return None
        self._key = change_kind(old_ref, new_ref) if self.by_kind else 0
        return self.remembered.get((self._key, 0))

    def for_qp(self, index: int) -> float | None:
        """The step size the change's QP ``index`` (>= 1) starts from ("_each" modes; None: keep OSQP's)."""
        if self._key is None or not self.each:
            return None
        return self.remembered.get((self._key, index))

    def note(self, index: int, rho_end: float) -> None:
        """The step size the change's QP ``index`` ended with (OSQP's adaptation in it), for the next change (of its
        kind): the first QP's, with an "_each" mode every QP's. Nothing outside a change."""
        if self._key is not None and (index == 0 or self.each):
            self.remembered[(self._key, index)] = float(rho_end)

    def close_change(self) -> None:
        """The change step's QPs are done: the next preparation takes the step size before the change in
        (``restore``)."""
        self._before, self._held, self._key = self._held, None, None

    def after_change(self) -> float | None:
        """At a preparation's matrix update: the step size to set there (the value before the last change, once;
        None: keep)."""
        before, self._before = self._before, None
        return before
