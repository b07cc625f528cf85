"""Calling a CasADi function on numpy arrays without per-call conversions.

``Function.__call__`` converts every argument to a DM and every result back (tens of
microseconds per call); :class:`BufferedFunction` evaluates into preallocated numpy memory
through CasADi's buffer interface instead. Results are dense, column-major as CasADi stores
them: a result of shape (rows, cols) comes back as a numpy array of shape (cols, rows).
"""

from __future__ import annotations

import casadi as ca
import numpy as np


class BufferedFunction:
    """Evaluate ``fn`` (dense inputs; outputs densified) into numpy buffers.

    ``f(*args)`` copies the arguments in, evaluates, and returns copies of the results,
    each of shape (cols, rows) (a column vector comes back flat). ``fixed`` (input index ->
    value) fills inputs that stay the same from call to call once; ``f(*args)`` then takes the
    other inputs, in order.
    """

    def __init__(self, fn: ca.Function, fixed: dict[int, object] | None = None):
        dense = all(fn.sparsity_in(i).is_dense() for i in range(fn.n_in())) and \
            all(fn.sparsity_out(i).is_dense() for i in range(fn.n_out()))
        if dense:
            self.fn = fn
        else:
            sym = fn.sx_in() if fn.is_a("SXFunction") else fn.mx_in()
            self.fn = ca.Function(f"{fn.name()}_dense", sym, [ca.densify(o) for o in fn.call(sym)])
        self._args = [np.zeros(self._shape(fn.size1_in(i), fn.size2_in(i))) for i in range(fn.n_in())]
        self._res = [np.zeros(self._shape(fn.size1_out(i), fn.size2_out(i))) for i in range(fn.n_out())]
        self._buf, self._eval = self.fn.buffer()
        for i, arr in enumerate(self._args):
            self._buf.set_arg(i, memoryview(arr))
        for i, arr in enumerate(self._res):
            self._buf.set_res(i, memoryview(arr))
        self._views = tuple(self._res)  # views' answer: the buffers, in a tuple the caller cannot reorder or extend
        fixed = fixed or {}
        for i, value in fixed.items():
            self._args[i][...] = value
        self._free = [a for i, a in enumerate(self._args) if i not in fixed]

    def set_fixed(self, index: int, value) -> None:
        """Change the value of the fixed input ``index`` (one of ``fixed``) for the calls that follow."""
        if any(a is self._args[index] for a in self._free):
            raise ValueError(f"input {index} is not a fixed input")
        self._args[index][...] = value

    @staticmethod
    def _shape(rows: int, cols: int) -> tuple[int, ...]:
        return (rows,) if cols == 1 else (cols, rows)

    def __call__(self, *args) -> list[np.ndarray]:
        for buf, value in zip(self._free, args):
            buf[...] = value
        self._eval()
        return [r.copy() for r in self._res]

    def views(self, *args) -> tuple[np.ndarray, ...]:
        """As ``f(*args)``, the same values, but the result buffers themselves, not copies: each is overwritten by
        the next call (either form), so a caller copies what it keeps beyond that (a copy of a result costs about
        0.5 us; the fused prediction has 14). The arguments are copied in before the evaluation, so a result of
        the last call may be handed back as an argument. A tuple: the buffers' list itself stays the object's."""
        for buf, value in zip(self._free, args):
            buf[...] = value
        self._eval()
        return self._views
