"""Small numpy operations of the control step with less per-call overhead, each giving what its general form gives.

A quiet control step makes about a hundred numpy calls on arrays of a few to a few hundred values, where the
Python wrappers around numpy's C (``np.all``, ``ndarray.all``'s ``_methods._all``, ``np.interp``'s checks) cost
as much as the work. The functions here skip the wrappers, not the arithmetic: the same booleans and the same
floating-point numbers to the bit (``tests/test_quiet_step.py``; docs/architecture.md "The quiet step's glue").
"""

from __future__ import annotations

import numpy as np

try:  # the compiled routine np.interp calls for real values (numpy 1.x and 2.x keep it at these places)
    from numpy._core.multiarray import interp as _compiled_interp
except ImportError:  # pragma: no cover - an older numpy
    try:
        from numpy.core.multiarray import interp as _compiled_interp
    except ImportError:
        _compiled_interp = None

#: The reductions behind ``ndarray.all()``, ``ndarray.sum()`` and ``ndarray.min()`` (numpy's ``_methods`` wrappers
#: call these with ``axis=None``; pass it, as the wrappers do, for arrays of more than one dimension).
all_reduce = np.logical_and.reduce
sum_reduce = np.add.reduce
min_reduce = np.minimum.reduce
_isfinite = np.isfinite


def all_finite(a: np.ndarray) -> bool:
    """``bool(np.isfinite(a).all())``: the reduction ``ndarray.all`` runs, without its Python wrapper (a sum of the
    values would answer sooner where they are finite, but warns where they are not or overflow)."""
    return bool(all_reduce(_isfinite(a), axis=None))


def interp(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``np.interp(x, xp, fp)`` for real float64 tables: the compiled routine it calls, without its checks."""
    if _compiled_interp is None:  # pragma: no cover - an older numpy
        return np.interp(x, xp, fp)
    return _compiled_interp(x, xp, fp, None, None)
