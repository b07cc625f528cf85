"""One function call whose result is collected at a fixed later point: on a second thread or at once.

The controller uses it to take the reachable-flow problem (:mod:`hvac_mpc.mpc.priorities`) off a
control step's critical path: the call starts in the step whose data it needs and its result is
collected at the start of the next step, waiting there if it is not ready. The answer is the same
whether the call ran on a thread or at once (``thread=False``, the same call inside the first step),
so the closed loop does not depend on the machine's load: a budget in steps, not a wall-clock
deadline. :attr:`BackgroundCall.waited_s` says how long :meth:`~BackgroundCall.result` waited (the
time a step lost to the call); :meth:`~BackgroundCall.wait` lets the caller give the call time
between two steps (the idle part of a sample) without taking its result.

ASSUMPTION: the function releases Python's global interpreter lock while it works; CasADi's
numeric function calls (IPOPT included) do in CasADi 3.8 (``tests/test_background.py`` checks the
installed version; ``benchmarks/step_tail.py`` measures the step time both ways). Where it does
not, the thread costs what the call costs, in the next step instead of this one.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable


class BackgroundCall:
    """``fn(*args)`` started now, its result (or the exception it raised) taken by :meth:`result`."""

    def __init__(self, fn: Callable[..., Any], args: tuple, thread: bool = True):
        self._value: Any = None
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self.waited_s = 0.0  # wall time result() spent waiting for the thread (s)
        if thread:
            self._thread = threading.Thread(target=self._run, args=(fn, args), name="hvac-mpc-background",
                                            daemon=True)
            self._thread.start()
        else:
            self._run(fn, args)

    def _run(self, fn: Callable[..., Any], args: tuple) -> None:
        try:
            self._value = fn(*args)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller of result()
            self._error = exc

    @property
    def done(self) -> bool:
        """True when the call has finished (at once without a thread)."""
        return self._thread is None or not self._thread.is_alive()

    def wait(self, timeout_s: float) -> float:
        """Wait up to ``timeout_s`` (s, >= 0) for the call to finish without taking its result; returns the
        wall time waited (s)."""
        if timeout_s < 0:
            raise ValueError(f"BackgroundCall.wait: timeout_s must be >= 0, got {timeout_s}")
        if self.done:
            return 0.0
        t0 = time.perf_counter()
        self._thread.join(timeout_s)
        return time.perf_counter() - t0

    def result(self) -> Any:
        """The call's return value, after waiting for it (the wait in :attr:`waited_s`); raises what the
        call raised."""
        if not self.done:
            t0 = time.perf_counter()
            self._thread.join()
            self.waited_s = time.perf_counter() - t0
        if self._error is not None:
            raise self._error
        return self._value
