"""The step's copies and calls cut (docs/architecture.md "The step's glue, third pass"): each cut gives what it
replaces to the bit. ``BufferedFunction.views`` is ``f(*args)`` without the copies; the reversal search's first move
taken once (:func:`~hvac_mpc.mpc.reversal_search.turns_and_moves`) is the two functions it replaces; and closed loops
with the buffers handed back, the generated solver's answer kept without a copy and the move taken once give the
commands, iterations and plans of the same loops with every copy and the two calls put back; the generated solver
takes the address of an array it is handed again only when the array is another."""

from __future__ import annotations

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.mpc import codegen, osqp_embedded, rti_osqp
from hvac_mpc.mpc.casadi_eval import BufferedFunction
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.reversal_search import last_moves, turned_inputs, turns_and_moves


def _bits(a) -> np.ndarray:
    return np.asarray(a, np.float64).view(np.int64)


@pytest.fixture
def route(code_cache, monkeypatch):
    """OSQP's generated solver switched on where a test asks for it (the suite runs with code generation off; the QP
    data stay interpreted, ``codegen=False``), else OSQP's Python interface."""
    def on(generated: bool) -> None:
        if generated:
            monkeypatch.setenv(codegen.CACHE_ENV, str(code_cache))
            monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    return on


def test_views_are_the_calls_values_in_the_buffers_themselves():
    """The same values as the copying call, the result buffers themselves (the next call overwrites them), and a
    result handed back as an argument gives what its copy gives."""
    import casadi as ca
    x = ca.SX.sym("x", 3)
    y = ca.SX.sym("y")
    f = BufferedFunction(ca.Function("f", [x, y], [ca.sin(x) * y, ca.sumsqr(x) + y]))
    a = np.array([0.3, -1.2, 2.5])
    copied = f(a, 0.7)
    seen = f.views(a, 0.7)
    assert all(np.array_equal(_bits(c), _bits(v)) for c, v in zip(copied, seen))
    assert isinstance(seen, tuple) and all(v is r for v, r in zip(seen, f._res))  # not the object's own list
    first = seen[0]
    again = f.views(first, 1.5)  # the last result as the argument: copied in before the buffers are written
    expected = f(copied[0], 1.5)  # (the same inputs: the buffers written with the same values again)
    assert again[0] is first and np.array_equal(_bits(again[0]), _bits(expected[0]))
    assert not np.array_equal(_bits(first), _bits(copied[0]))  # overwritten by the call after


def test_a_held_address_is_the_arrays_own_and_taken_again_for_another_array(route):
    """The generated solver's held addresses (P's and A's values, the gradient): the array's own data address while
    the same array comes back, a new array's at once, and a wrong array refused as before."""
    route(True)
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    loop = solve_time.Loop(ctrl, 1)
    for k in range(3):
        loop.step(k)
    core = ctrl.solver._core
    if not isinstance(core, osqp_embedded.EmbeddedOsqp):
        ctrl.close()
        pytest.skip("no compiler: the generated OSQP is not available")
    q = np.zeros(core.n)
    first = core._held_address(2, q, core.n)
    assert first == osqp_embedded.data_address(q) and core._held[2][0] is q
    assert core._held_address(2, q, core.n) == first
    other = np.ones(core.n)
    assert core._held_address(2, other, core.n) == osqp_embedded.data_address(other) and core._held[2][0] is other
    with pytest.raises(ValueError):
        core._held_address(2, np.zeros(core.n + 1), core.n)
    ctrl.close()


def _draws(rng: np.random.Generator, count: int):
    """Moves, last moves, spans and shares around the thresholds: zeros of both signs, nan, inf, moves exactly at
    the share of the span, no last move, the search off."""
    special = np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 0.05, -0.05, 0.1, -0.1])
    for _ in range(count):
        n = int(rng.integers(1, 8))
        span = rng.choice([1.0, 2.0, 0.5], size=n)
        share = float(rng.choice([0.0, 0.05, 0.1, 0.025]))
        move = rng.normal(0.0, 0.1, n)
        last = rng.normal(0.0, 0.1, n)
        for arr in (move, last):
            mask = rng.random(n) < 0.3
            arr[mask] = rng.choice(special, size=int(mask.sum()))
        at = rng.random(n) < 0.2  # exactly at the threshold: not beyond it
        move[at] = np.where(rng.random(int(at.sum())) < 0.5, 1.0, -1.0) * share * span[at]
        yield (None if rng.random() < 0.15 else last), move, span, share


def test_the_first_move_taken_once_is_the_two_functions_to_the_bit():
    """:func:`turns_and_moves` against :func:`turned_inputs` and :func:`last_moves` over 20000 draws: the same
    indices (and their dtype) and the same kept moves, bit for bit (the sign of a zero and nan included)."""
    rng = np.random.default_rng(13)
    turned_any = kept_any = 0
    with np.errstate(invalid="ignore"):
        for last, move, span, share in _draws(rng, 20000):
            turned, moves = turns_and_moves(last, move, span, share)
            ref_turned = turned_inputs(last, move, span, share)
            ref_moves = last_moves(last, move, span, share)
            assert turned.dtype == ref_turned.dtype and turned.tolist() == ref_turned.tolist()
            assert moves.dtype == ref_moves.dtype and np.array_equal(_bits(moves), _bits(ref_moves))
            turned_any += turned.size > 0
            kept_any += last is not None and bool(np.any(_bits(moves) != _bits(move)))
    assert turned_any > 1000 and kept_any > 1000  # both branches exercised


def _loop(steps: int, settings: dict, copies: bool, monkeypatch) -> dict:
    """A solve-time loop (seed 1) with the cuts, or with every copy and the two calls of the reversal search put
    back (``copies``): the commands, the plans, the OSQP iterations and whether the search searched and took."""
    with monkeypatch.context() as m:
        if copies:
            m.setattr(BufferedFunction, "views", lambda self, *args: self(*args))
            m.setattr(osqp_embedded.EmbeddedOsqp, "fresh_solution", False)
            m.setattr(osqp_embedded.EmbeddedOsqp, "_held_address", lambda self, slot, a, size: self._p(a, size))
            m.setattr(rti_osqp, "turns_and_moves",
                      lambda last, move, span, share: (turned_inputs(last, move, span, share),
                                                       last_moves(last, move, span, share)))
        ctrl = MpcController(settings=MpcSettings(codegen=False, **settings))
        loop = solve_time.Loop(ctrl, 1)
        out = {"commands": [], "plans": [], "iterations": [], "searched": 0, "taken": 0, "generated": False}
        for k in range(steps):
            res = loop.step(k)
            out["commands"].append(res.command.vector())
            out["iterations"].append(res.stats["iterations"])
            out["plans"].append(None if ctrl.solver.U is None else ctrl.solver.U.copy())
            out["searched"] += bool(res.stats.get("reversal_searched"))
            out["taken"] += bool(res.stats.get("reversal_taken"))
        out["generated"] = isinstance(ctrl.solver._core, osqp_embedded.EmbeddedOsqp)
        ctrl.close()
    return out


@pytest.mark.parametrize("generated", [True, False], ids=["generated OSQP", "OSQP's Python interface"])
@pytest.mark.parametrize("settings", [{}, {"rti_reversal_wait_steps": 0, "rti_reversal_margin": 0.0}],
                         ids=["defaults", "search_every_step"])
def test_a_closed_loop_with_the_cuts_is_the_loop_with_the_copies_to_the_bit(settings, generated, route, monkeypatch):
    """70 steps of the solve-time loop (reference changes at 30 and 60 s and their wakes included), with the
    defaults and with the reversal search acting on every step it turns (so candidates are taken), through OSQP's
    generated solver (its answer kept without a copy, its addresses held) and its Python interface: the commands and
    the plans equal in every bit, the same OSQP iterations, searches and takes."""
    route(generated)
    cut = _loop(70, settings, copies=False, monkeypatch=monkeypatch)
    full = _loop(70, settings, copies=True, monkeypatch=monkeypatch)
    if generated:
        assert cut["generated"] and full["generated"], "the generated OSQP did not load"
    assert np.array_equal(_bits(cut["commands"]), _bits(full["commands"]))
    assert all((a is None and b is None) or np.array_equal(_bits(a), _bits(b))
               for a, b in zip(cut["plans"], full["plans"]))
    assert cut["iterations"] == full["iterations"]
    assert (cut["searched"], cut["taken"]) == (full["searched"], full["taken"])
    if settings:
        assert full["searched"] > 0 and full["taken"] > 0  # the search's branch with a taken candidate ran
