"""Controllers for the daemon: loading by name, fault injection, and the deadline-guarded chain.

The chain runs the primary controller in a worker thread with a wall-time deadline. When the
step raises, returns a non-finite command, or misses its deadline (or is still busy with an
earlier late step), the next controller of the chain takes this sample; the daemon's safe
command is the last resort. A controller that was not in use is ``reset()`` before it takes
over, so it starts from the current measurement (no stale integrator state).
"""

from __future__ import annotations

import importlib
import inspect
import math
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

from hvac_mpc.models.parameters import Parameters
from hvac_mpc.contract import Command, Measurement
from hvac_mpc.contract import Controller, StepResult
from hvac_mpc.contract import Reference

from .config import FaultSpec
from .plugins import CONTROLLER_GROUP, registered_controllers

class ControllerLoadError(ValueError):
    """The configured controller cannot be found or built; the message says which and why."""


def load_controller(spec: str, params: Parameters, dt_s: float, settings: Mapping[str, Any] | None = None,
                    model: Any = None) -> Controller:
    """Build a registered controller by name: 'mpc', 'baseline' or a plug-in's entry-point name.

    'mpc' gets ``MpcController(params, MpcSettings(**settings), model=model)`` (``model``: a refined
    model from a model file, or None); 'baseline' gets ``BaselineController(params, dt_s)``; a plug-in
    class gets ``Class(params=..., dt_s=..., **settings)``.
    """
    settings = dict(settings or {})
    known = registered_controllers()
    if spec not in known:
        raise ControllerLoadError(f"controller {spec!r} is not registered (entry point group {CONTROLLER_GROUP}); "
                                  f"registered: {sorted(known)}")
    try:
        cls = known[spec].load()
    except (ImportError, AttributeError) as exc:
        raise ControllerLoadError(f"controller {spec!r}: cannot import {known[spec].value} ({exc})") from None
    try:
        if spec == "mpc":
            from hvac_mpc.mpc.settings_file import settings_with  # the MPC's own module, loaded with it
            settings_cls = getattr(importlib.import_module(cls.__module__), "MpcSettings")
            if "dt_s" in getattr(settings_cls, "__dataclass_fields__", {}) and "dt_s" not in settings:
                settings["dt_s"] = dt_s
            if model is not None:
                return cls(params, settings_with(settings_cls(), settings), model=model)
            return cls(params, settings_with(settings_cls(), settings))
        if spec == "baseline":
            return cls(params, dt_s=dt_s, **settings)
        return cls(params=params, dt_s=dt_s, **settings)
    except (TypeError, ValueError) as exc:
        raise ControllerLoadError(f"controller {spec!r}: bad settings {sorted(settings)} ({exc})") from None


def reset_controller(ctrl: Controller, command: Command | None) -> None:
    """``reset()``, telling the controller the command in force when its reset accepts one."""
    try:
        accepts = "command" in inspect.signature(ctrl.reset).parameters
    except (TypeError, ValueError):
        accepts = False
    if accepts and command is not None:
        ctrl.reset(command=command)
    else:
        ctrl.reset()
        track = getattr(ctrl, "track", None)
        if callable(track) and command is not None:
            track(command)  # bumpless: the thesis baseline presets its integrators from the command


class InjectedFailure(RuntimeError):
    """A solver failure injected by the fault configuration."""


class FaultInjectingController:
    """Wraps a controller; injects 'fail' (raises), 'nan' (NaN command) and 'delay' (slow step)
    faults of the ``[[faults]]`` configuration by daemon time."""

    def __init__(self, inner: Controller, faults: Sequence[FaultSpec], clock: Callable[[], float]):
        self.inner = inner
        self.faults = [f for f in faults if f.target == "controller"]
        self.clock = clock
        self.dt_s = getattr(inner, "dt_s", 1.0)
        self.injected: dict[str, int] = {}

    def step(self, measurement: Measurement, reference: Reference) -> StepResult:
        t = self.clock()
        for f in self.faults:
            if not f.active(t):
                continue
            key = f"controller:{f.kind}"
            self.injected[key] = self.injected.get(key, 0) + 1
            if f.kind == "fail":
                raise InjectedFailure(f"injected solver failure until t = {f.end_s} s")
            if f.kind == "solver" and hasattr(self.inner, "force_solver_failure"):
                self.inner.force_solver_failure(1)  # the controller's own fallback chain answers
            if f.kind == "delay":
                time.sleep(f.delay_s)
            if f.kind == "nan":
                result = self.inner.step(measurement, reference)
                return StepResult(Command(blower_power_w=math.nan, heater_cmd_w=math.nan), dict(result.stats))
        return self.inner.step(measurement, reference)

    def reset(self, command: Command | None = None) -> None:
        reset_controller(self.inner, command)

    def wait_background(self, timeout_s: float) -> float:
        """The wrapped controller's work between steps (:func:`between_steps`)."""
        return between_steps(self.inner, timeout_s)

    def close(self) -> None:
        """The wrapped controller's ``close``, if it has one."""
        close = getattr(self.inner, "close", None)
        if callable(close):
            close()


def between_steps(ctrl: Controller, timeout_s: float = 0.0) -> float:
    """Work a controller defers out of its step (``wait_background``, e.g. the MPC's second filter), given up to
    ``timeout_s`` (s) for what runs on its other threads; nothing for a controller without it. Returns the time
    waited (s)."""
    between = getattr(ctrl, "wait_background", None)
    return float(between(timeout_s)) if callable(between) else 0.0


def _finite(cmd: Any) -> bool:
    return isinstance(cmd, Command) and all(
        isinstance(v, (int, float)) and math.isfinite(v) for v in cmd.as_dict().values())


@dataclass
class ChainOutcome:
    """Which controller produced the command and what went wrong before (if anything)."""

    command: Command | None
    used: str | None
    stats: dict[str, Any] = field(default_factory=dict)
    events: list[str] = field(default_factory=list)
    step_time_s: float = 0.0


class ControllerChain:
    """Primary controller under a deadline, then fallbacks, then ``None`` (the safe command).

    A fallback is reset when it takes over; the primary is reset when it returns after more than
    ``primary_reset_after`` samples out (a short miss keeps its warm start).
    """

    def __init__(self, controllers: Sequence[tuple[str, Controller]], deadline_s: float, threaded: bool = True,
                 primary_reset_after: int = 10):
        if not controllers:
            raise ValueError("the controller chain needs at least one controller")
        self.controllers = list(controllers)
        self.deadline_s = deadline_s
        self.primary_reset_after = primary_reset_after
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="controller") if threaded else None
        self._pending: Future | None = None
        self._between_job: Future | None = None  # the primary's work between steps (_between)
        self._last_used: str | None = None
        self._primary_out = 10**9  # samples since the primary last produced the command

    def reset(self) -> None:
        """Reset every controller before its next use (after an outage or safe mode)."""
        self._last_used = None
        self._primary_out = 10**9

    def step(self, measurement: Measurement, reference: Reference, last_command: Command | None = None
             ) -> ChainOutcome:
        """The command of the first controller that delivers one in time (``last_command``: the
        command in force, handed to a controller that is reset)."""
        out = ChainOutcome(None, None)
        name, primary = self.controllers[0]
        reset_primary = self._primary_out > self.primary_reset_after
        t0 = time.perf_counter()
        result = None
        if self._executor is None:
            try:
                result = _run(primary, reset_primary, measurement, reference, last_command)
            except Exception as exc:  # noqa: BLE001 - any controller failure goes down the chain
                out.events.append(f"error:{type(exc).__name__}")
            if result is not None and time.perf_counter() - t0 > self.deadline_s:
                out.events.append("deadline")
                result = None
        elif self._pending is not None and not self._pending.done():
            out.events.append("busy")  # a late step of the primary is still running
        elif not self._between_done():
            out.events.append("busy_between")  # its work between steps is still running
        else:
            self._pending = None
            fut = self._executor.submit(_run, primary, reset_primary, measurement, reference, last_command)
            try:
                result = fut.result(timeout=self.deadline_s)
            except TimeoutError:
                self._pending = fut
                out.events.append("deadline")
            except Exception as exc:  # noqa: BLE001
                out.events.append(f"error:{type(exc).__name__}")
        out.step_time_s = time.perf_counter() - t0
        self._between(primary, result is not None)
        if result is not None:
            if _finite(result.command):
                out.command, out.used, out.stats = result.command, name, dict(result.stats)
                self._primary_out = 0
                self._last_used = name
                return out
            out.events.append("not_finite")
        self._primary_out += 1
        for fb_name, fb in self.controllers[1:]:
            try:
                r = _run(fb, self._last_used != fb_name, measurement, reference, last_command)
            except Exception as exc:  # noqa: BLE001
                out.events.append(f"fallback_error:{fb_name}:{type(exc).__name__}")
                continue
            if _finite(r.command):
                out.command, out.used, out.stats = r.command, fb_name, dict(r.stats)
                self._last_used = fb_name
                return out
            out.events.append(f"fallback_not_finite:{fb_name}")
        self._last_used = None
        return out

    def _between(self, primary: Controller, stepped: bool) -> None:
        """After a step of the primary delivered in time, the work it defers out of its steps
        (:func:`between_steps`) on the primary's worker, never beside a step: the next step waits up to the
        deadline for it (:meth:`_between_done`). Unthreaded, nothing: the controller does that work in its next
        step, and the command of this one is not held back for it."""
        if not stepped or self._executor is None:
            return
        try:
            self._between_job = self._executor.submit(_quiet_between, primary)
        except RuntimeError:  # the chain was closed meanwhile
            self._between_job = None

    def _between_done(self) -> bool:
        """True once the primary's work between steps is done, waited for up to the deadline (its own wait, so a
        step is timed from its own start); False if it still runs (the sample goes down the chain)."""
        job, self._between_job = self._between_job, None
        if job is None:
            return True
        try:
            job.result(timeout=self.deadline_s)
        except TimeoutError:
            self._pending = job  # still running: the primary is busy until it ends
            return False
        return True

    def close(self) -> None:
        """Stop the chain without waiting: the queued steps are dropped; on a thread of its own, once a step still
        running has ended, each controller's ``close`` (if it has one: the MPC's second thread) is called."""
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
        closers = [c for c in (getattr(ctrl, "close", None) for _, ctrl in self.controllers) if callable(c)]
        if closers:
            threading.Thread(target=_close_after, args=(self._executor, closers), name=CLOSE_THREAD_NAME,
                             daemon=True).start()


#: Name of the thread that closes a chain's controllers.
CLOSE_THREAD_NAME = "hvac-chain-close"


def _close_after(executor: ThreadPoolExecutor | None, closers: list[Callable[[], None]]) -> None:
    """Wait for the step still running on ``executor`` (if any), then call each controller's ``close``."""
    if executor is not None:
        executor.shutdown(wait=True)
    for close in closers:
        try:
            close()
        except Exception:  # noqa: BLE001 - a controller that fails to close is dropped all the same
            pass


def _quiet_between(ctrl: Controller) -> None:
    try:
        between_steps(ctrl)
    except Exception:  # noqa: BLE001 - the command of the last step stands
        pass


def _run(ctrl: Controller, reset: bool, m: Measurement, ref: Reference, last: Command | None) -> StepResult:
    if reset:
        reset_controller(ctrl, last)
    return ctrl.step(m, ref)
