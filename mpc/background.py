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

A :class:`BackgroundWorker` is one long-lived thread that runs such calls one after the other
(``BackgroundCall(..., worker=w)``): the step hands the call over (a queue put at the step's end,
:meth:`BackgroundWorker.hold`) instead of starting a thread, whose ``Thread.start`` waits inside the step
until the new thread runs (0.1-0.4 ms of the step's thread CPU and 0.3-2 ms of wall time on the solve-time
loop, more on a loaded machine; docs/architecture.md 'Slow steps'). Each owner holds its own worker (no
state shared between controllers); :meth:`BackgroundWorker.close` stops the thread, and so does dropping the
worker.
"""

from __future__ import annotations

import queue
import threading
import time
import weakref
from typing import Any, Callable


class BackgroundCall:
    """``fn(*args)`` started now, its result (or the exception it raised) taken by :meth:`result`: on a thread of
    its own (``thread=True``, no ``worker``), on ``worker``'s thread (:class:`BackgroundWorker`), or at once
    (``thread=False``)."""

    def __init__(self, fn: Callable[..., Any], args: tuple, thread: bool = True,
                 worker: BackgroundWorker | None = None):
        self._value: Any = None
        self._error: BaseException | None = None
        self._finished = threading.Event()
        self._worker = worker if thread else None
        self.waited_s = 0.0  # wall time result() spent waiting for the thread (s)
        if not thread:
            self._run(fn, args)
        elif worker is not None:
            worker.hand_over(lambda: self._run(fn, args))
        else:
            threading.Thread(target=self._run, args=(fn, args), name=THREAD_NAME, daemon=True).start()

    def _run(self, fn: Callable[..., Any], args: tuple) -> None:
        try:
            self._value = fn(*args)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller of result()
            self._error = exc
        finally:
            self._finished.set()

    @property
    def done(self) -> bool:
        """True when the call has finished (at once without a thread)."""
        return self._finished.is_set()

    def wait(self, timeout_s: float) -> float:
        """Wait up to ``timeout_s`` (s, >= 0) for the call to finish without taking its result; returns the
        wall time waited (s)."""
        if timeout_s < 0:
            raise ValueError(f"BackgroundCall.wait: timeout_s must be >= 0, got {timeout_s}")
        if self.done:
            return 0.0
        self._let_run()
        t0 = time.perf_counter()
        self._finished.wait(timeout_s)
        return time.perf_counter() - t0

    def result(self) -> Any:
        """The call's return value, after waiting for it (the wait in :attr:`waited_s`); raises what the
        call raised."""
        if not self.done:
            self._let_run()
            t0 = time.perf_counter()
            self._finished.wait()
            self.waited_s = time.perf_counter() - t0
        if self._error is not None:
            raise self._error
        return self._value

    def _let_run(self) -> None:
        """A call held by its worker (:meth:`BackgroundWorker.hold`) is let go before it is waited for."""
        if self._worker is not None:
            self._worker.release()


#: Name of the threads that run background calls.
THREAD_NAME = "hvac-mpc-background"
_STOP = None  # the job that ends a worker's thread


class BackgroundWorker:
    """One thread, started on the first hand-over (or :meth:`start`), that runs the jobs handed to it one after the
    other. The thread holds the job queue only, not the worker: dropping the worker (or :meth:`close`) ends it.
    A job handed over after :meth:`close`, or after the thread was lost (a fork), starts a new thread.

    Between :meth:`hold` and :meth:`release` jobs handed over wait (a control step holds its worker: the solve it
    hands over starts when the step ends, instead of taking the interpreter lock for its Python parts from the
    rest of the step); waiting for a held call's answer releases it. Hand-over, hold and release are for one thread
    at a time (the one that steps the owner)."""

    def __init__(self):
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self.threads_started = 0  # threads this worker has started so far
        self._held: list[Callable[[], None]] | None = None  # jobs kept until release() (None: not holding)
        self._finalizer = weakref.finalize(self, self._jobs.put, _STOP)

    @property
    def running(self) -> bool:
        """True while the worker's thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        """Start the thread now (outside a control step) unless it runs."""
        if self.running:
            return
        self._thread = threading.Thread(target=_serve, args=(self._jobs,), name=THREAD_NAME, daemon=True)
        self._thread.start()
        self.threads_started += 1

    def hand_over(self, job: Callable[[], None]) -> None:
        """Queue ``job`` (no arguments; its exceptions are its own to catch) for the worker's thread; while held,
        at :meth:`release`."""
        if self._held is not None:
            self._held.append(job)
            return
        self.start()
        self._jobs.put(job)

    def hold(self) -> None:
        """Keep the jobs handed over from now on until :meth:`release`."""
        if self._held is None:
            self._held = []

    def release(self) -> None:
        """Stop holding: queue the jobs held, in the order handed over."""
        held, self._held = self._held, None
        for job in held or ():
            self.hand_over(job)

    def close(self, timeout_s: float = 5.0) -> None:
        """Let the jobs handed over (held ones too) finish, then end the thread (waiting up to ``timeout_s``, s)."""
        self.release()
        if self._thread is None:
            return
        self._jobs.put(_STOP)
        self._thread.join(timeout_s)
        self._thread = None


def _serve(jobs: queue.SimpleQueue) -> None:
    """A worker's thread: run the queued jobs until the stop job."""
    while True:
        job = jobs.get()
        if job is _STOP:
            return
        job()
        job = None  # noqa: F841 - drop the job (and what it holds) before waiting for the next
