"""The daemon's fixed-rate control loop with its safety layer, log and shutdown sequence.

Each tick (sample time ``time_s = t0 + k * period_s``):

1. read the sensors from the backend (a failure marks the link lost; reconnects follow with a
   doubling backoff, safe outputs are written meanwhile);
2. check every reading (NaN, missing, out of range, stuck; stale sample) and update the heater
   body estimate;
3. compute the command: the controller chain (primary under a deadline, fallbacks), or the safe
   command when a sensor the controller needs is invalid, or the shutdown command;
4. apply the heater interlock (independent of any controller), write the command;
5. append the sample to the measurement log (fsynced; buffered in memory while the disk fails,
   :mod:`hvac_mpc.daemon.log_writer`) and publish it to the API.

The command comes from the operator mode in force (:mod:`hvac_mpc.daemon.modes`): the controller
chain of ``auto-mpc``/``auto-pid``/``auto``, the operator's setting in ``manual``, the safe
command in ``safe-stop``; the interlock acts after it in every mode.

Shutdown (SIGTERM/SIGINT, ``max_ticks`` or a fatal error): heater off at once, the blower
keeps running at least at ``safe_blower_w`` with all outlets open and valve a sending the air
through the heater, until the heater estimate has cooled (or ``cooldown_max_s``); then the
blower goes to its minimum and the daemon exits. A second stop request skips the wait (heater
off, blower left running). The log's time continues across restarts (the new run starts one
sample after the last logged row), so a restarted daemon appends without a gap.
"""

from __future__ import annotations

import bisect
import csv
import errno
import io
import logging
import math
import threading
import time
import traceback
from collections import deque
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from hvac_mpc.models.measurement_log import COLUMNS
from hvac_mpc.models.model_file import load as load_refined_model
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.contract import EXTRA_SIGNALS, Command, Measurement
from hvac_mpc.contract import Reference

from .backends import BackendError, IoBackend, make_backend
from .config import SENSOR_FIELDS, DaemonConfig, resolve
from .controllers import ControllerChain, FaultInjectingController, load_controller
from .log_writer import DurableLog, utc_now_iso
from .modes import (AUTO_CONTROLLERS, MODES, ModeChange, ModeError, ReferenceRamp, heater_refusal, initial_mode,
                    rate_limited)
from .monitor import ModelInForce, ModelLoadError, ModelSlots, MonitorSettings, read_model
from .safety import HeaterEstimator, HeaterInterlock, SensorMonitor, SensorStatus, safe_command
from .watchdog import start_watchdog

LOG = logging.getLogger("hvac_mpc.daemon")
COMMAND_FIELDS = ("blower_power_w", "heater_cmd_w", "valve_a_pct", "valve_m_pct", "valve_f_pct", "valve_w_pct")
REF_COLUMNS = {"supply_temp_c": "ref_supply_temp_c", "volume_flow_m3s": "ref_volume_flow_m3s",
               "flow_m_m3s": "ref_flow_m_m3s", "flow_f_m3s": "ref_flow_f_m3s", "flow_w_m3s": "ref_flow_w_m3s"}
BLOWER_MIN_W = 30.0
#: Upper bounds (s) of the tick-time histogram (/metrics).
TICK_TIME_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5)


def last_logged_time(path: Path) -> float | None:
    """``time_s`` of the last complete row of a log, or ``None`` for a new or empty log."""
    if not path.exists() or path.stat().st_size == 0:
        return None
    with path.open("rb") as fh:
        header = fh.readline().decode("utf-8", "replace")
        size = path.stat().st_size
        fh.seek(max(len(header), size - 65536))
        tail = fh.read().decode("utf-8", "replace")
    names = next(csv.reader([header]))
    if "time_s" not in names:
        return None
    col = names.index("time_s")
    for line in reversed(tail.splitlines()):
        try:
            row = next(csv.reader(io.StringIO(line)))
            if len(row) == len(names):
                return float(row[col])
        except (StopIteration, ValueError, csv.Error):
            continue
    return None


def _lock_log(path: Path):
    """An exclusive lock on the log for the daemon's lifetime: a second daemon on the same log
    would interleave rows, so it is refused. The kernel drops the lock if the process dies."""
    import fcntl

    fh = path.open("a")
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise RuntimeError(f"log {path} is in use by another daemon") from None
    return fh


def _num(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


class Daemon:
    """The controller daemon. ``run()`` blocks until stopped and returns the exit code."""

    def __init__(self, config: DaemonConfig, *, backend: IoBackend | None = None,
                 tick_hook: Callable[["Daemon", dict], None] | None = None,
                 initial_command: Command | None = None, monitor: MonitorSettings | None = None):
        """``initial_command``: the command in force on the box when the daemon starts (default: the
        safe command); ``monitor``: settings of the model monitor (:mod:`.monitor`; default: the
        configuration's ``[monitor]``)."""
        self.cfg = config
        self.dt = config.loop.period_s
        self.monitor_settings = monitor or config.monitor.settings()
        pfile, mfile = config.controller.parameters_file, config.controller.model_file
        self.refined = load_refined_model(resolve(config, mfile)) if mfile else None
        source = mfile or pfile
        model = read_model(str(resolve(config, source)) if source else "", self.dt, self.monitor_settings)
        self.params = self.refined.parameters if self.refined is not None else model.params
        self.tick_hook = tick_hook
        self._lock = threading.Lock()
        self._stop_requests = 0
        self._stop_reason = ""
        self._fatal = False

        # log first: its last row fixes the start time (restart appends)
        self.log_path = resolve(config, config.log.path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log_lock = _lock_log(self.log_path)
        self.tick = 0
        self.t0 = 0.0
        try:
            lc = config.log
            self.writer = DurableLog(self.log_path, COLUMNS, fsync=lc.fsync, rotate_bytes=lc.rotate_bytes,
                                     rotate_daily=lc.rotate_daily, buffer_rows=lc.buffer_rows, retry_s=lc.retry_s,
                                     wall_clock=lambda: self.time_s, inject=self._log_fault)
            last = self.writer.last_time_s
            self.t0 = 0.0 if last is None else last + self.dt
            self.backend = backend or make_backend(config, self.params, clock=lambda: self.time_s)
            self.mode = initial_mode(config.controller.name)
            self.chain = model.chain = self._build_chain()
            self.models = ModelSlots(model)
        except BaseException:
            self._log_lock.close()
            raise
        self.chains: dict[str, ControllerChain] = {self.mode: self.chain}
        self._tick_mode = self.mode
        self._switched = False
        self._manual_target: Command | None = None
        self._transfer_until_s = -math.inf
        self._ramp = ReferenceRamp(config.safety.transfer_ramp_c_per_s, config.safety.transfer_ramp_m3s_per_s)
        self.mode_history: deque[ModeChange] = deque(maxlen=200)
        if config.safety.unsafe_overrides():
            LOG.warning("UNSAFE configuration (safety.unsafe = true): %s", ", ".join(config.safety.unsafe_overrides()))
        self.monitor = SensorMonitor(config.safety)
        self.interlock = HeaterInterlock(config.safety, self.params)
        self.estimator = HeaterEstimator(self.params)
        self._estimator_ready = False
        self.reference = config.initial_reference
        self.connected = False
        self._next_reconnect_s = self.t0
        self._backoff_s = config.safety.reconnect_initial_s
        self._held: dict[str, tuple[float, float]] = {}  # field -> (value, time_s of last good reading)
        self._last_cmd = initial_command or safe_command(config.safety)
        self._last_mode = ""
        self._shutdown_start_s: float | None = None
        self.state = "starting"
        self.exit_code = 0
        self.latest: dict[str, Any] | None = None
        self._out_of_reach: dict[str, float] = {}  # references the controller reports out of reach
        self._last_tick_wall = time.monotonic()
        self._started_wall = time.monotonic()
        self.counters: dict[str, Any] = {
            "ticks": 0, "late_ticks": 0, "deadline_misses": 0, "controller_busy": 0, "controller_errors": 0,
            "not_finite_commands": 0, "primary_ticks": 0, "fallback_ticks": {}, "safe_ticks": 0,
            "disconnected_ticks": 0, "backend_errors": 0, "reconnect_attempts": 0, "reconnects": 0,
            "sensor_fault_ticks": {}, "reference_updates": 0, "fatal_errors": 0, "shutdown_ticks": 0,
            "max_step_time_s": 0.0, "max_tick_time_s": 0.0, "solver_status": {}, "inner_fallback_ticks": {},
            "mode_changes": 0, "manual_commands": 0, "manual_refused": 0,
            "tick_time_sum_s": 0.0, "tick_time_buckets": [0] * (len(TICK_TIME_BUCKETS_S) + 1),
        }
        self._fired: set[int] = set()
        self.injected: dict[str, int] = {}
        self.api = None
        self._watchdog = None
        if config.api.enabled:
            self._start_api()

    # ------------------------------------------------------------------ construction
    def _build_chain(self, primary: str | None = None, params: Parameters | None = None) -> ControllerChain:
        """The chain of ``primary`` (default: the configured controller) with ``params`` (default: the
        model in force): primary, then the configured fallbacks; the configured settings go to the
        configured controller only."""
        c = self.cfg.controller
        primary = primary or c.name
        names = [primary] + [f for f in c.fallback if f != primary]
        chain = []
        for i, name in enumerate(names):
            ctrl = load_controller(name, params or self.params, self.dt, c.settings if name == c.name else None,
                                   model=self.refined if name == "mpc" and params is None else None)
            if i == 0 and any(f.target == "controller" for f in self.cfg.faults):
                ctrl = FaultInjectingController(ctrl, self.cfg.faults, clock=lambda: self.time_s)
            chain.append((name, ctrl))
        return ControllerChain(chain, self.cfg.loop.step_deadline_s)

    def _start_api(self) -> None:
        from .server import ApiServer

        self.api = ApiServer(self, self.cfg).start()
        LOG.info("HTTP API on http://%s:%d", self.cfg.api.host, self.api.port)

    def _log_fault(self) -> None:
        """Injected log faults ([[faults]] target 'log'): every write fails in the window."""
        for f in self.cfg.faults:
            if f.target == "log" and f.active(self.time_s):
                key = f"log:{f.kind}"
                self.injected[key] = self.injected.get(key, 0) + 1
                code = errno.ENOSPC if f.kind == "enospc" else errno.EIO
                raise OSError(code, f"injected: {errno.errorcode[code]}")

    # ------------------------------------------------------------------ API side (thread-safe)
    def get_reference(self) -> Reference:
        with self._lock:
            return self.reference

    def set_reference(self, ref: Reference, client: str = "") -> None:
        with self._lock:
            self.reference = ref
            self.counters["reference_updates"] += 1

    def load_model(self, path: str | Path, client: str = "") -> dict[str, Any]:
        """Validate a model file, build its monitor and controllers, and swap them in between two
        samples. Raises :class:`ModelLoadError` (nothing changes) when the file is not usable."""
        model = read_model(str(path), self.dt, self.monitor_settings)
        try:
            model.chain = self._build_chain(AUTO_CONTROLLERS.get(self.mode), model.params)
        except Exception as exc:  # noqa: BLE001 - any build failure leaves the running model alone
            raise ModelLoadError(f"model file {str(path)!r}: controllers cannot be built ({exc})") from None
        with self._lock:
            self._drop(self.models.request(model, client, "load"))
        LOG.info("model %s (%s) requested by %s; swapped in at the next sample", model.hash, path, client or "-")
        return {"hash": model.hash, "path": model.path, "effects": list(model.effects)}

    def rollback_model(self, client: str = "") -> dict[str, Any]:
        """Swap back to the model in force before the last swap (between two samples)."""
        with self._lock:
            prev = self.models.previous
            if prev is None:
                raise ModelLoadError("no earlier model to roll back to")
            self._drop(self.models.request(prev, client, "rollback"))
        LOG.info("rollback to model %s requested by %s", prev.hash, client or "-")
        return {"hash": prev.hash, "path": prev.path}

    def _drop(self, model: ModelInForce | None) -> None:
        """Release the controllers of a requested model replaced by a later request before its swap."""
        if model is not None and model is not self.models.previous and model.chain is not None:
            model.chain.close()

    def _swap_model(self) -> None:
        """At the start of a sample: put a requested model in force (controllers reset bumplessly)."""
        with self._lock:
            displaced = self.models.previous
            swap = self.models.take(self.time_s, time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime()))
        if swap is None:
            return
        old, new, event = swap
        if displaced is not None and displaced is not new and displaced.chain is not None:
            displaced.chain.close()
        for mode, chain in list(self.chains.items()):  # chains of the old parameters are rebuilt on a switch
            if chain is not old.chain:
                chain.close()
        self.chain = new.chain
        self.chains = {self.mode: self.chain}
        self.chain.reset()
        self.params = new.params
        new.monitor.reset()
        LOG.warning("t = %.1f s: model %s -> %s (%s by %s)", self.time_s, old.hash, new.hash, event["action"],
                    event["client"] or "-")

    def model_metrics(self) -> dict[str, float]:
        """The model monitor's gauges (for a metrics exporter)."""
        return self.models.current.monitor.metrics()

    def latest_sample(self) -> dict[str, Any] | None:
        with self._lock:
            return None if self.latest is None else dict(self.latest)

    def get_mode(self) -> dict[str, Any]:
        with self._lock:
            return {"mode": self.mode, "modes": self.available_modes(),
                    "manual_target": None if self._manual_target is None or self.mode != "manual"
                    else self._manual_target.as_dict(),
                    "history": [h.as_dict() for h in list(self.mode_history)[-20:]]}

    def available_modes(self) -> list[str]:
        return [m for m in MODES if m != "auto" or self.cfg.controller.name not in AUTO_CONTROLLERS.values()]

    def set_mode(self, mode: str, client: str) -> dict[str, Any]:
        """Switch the operator mode (applied at the next tick, bumplessly); logged with the client."""
        if mode not in self.available_modes():
            raise ModeError(f"mode {mode!r}: allowed {self.available_modes()}")
        with self._lock:
            chain = self.chains.get(mode)
        if chain is None and mode in AUTO_CONTROLLERS:
            chain = self._build_chain(AUTO_CONTROLLERS[mode])  # outside the lock: building may take seconds
        with self._lock:
            if self.state not in ("starting", "running") or self._stop_requests or self._fatal:
                raise ModeError(f"mode {mode!r} refused: the daemon is {self.state}", 409)
            if chain is not None and mode not in self.chains:
                self.chains[mode] = chain
            elif chain is not None and chain is not self.chains[mode]:
                chain.close()  # a concurrent request built it first
            old = self.mode
            if mode == old:
                return {"mode": mode, "changed": False}
            self.mode = mode
            self._switched = True
            self._manual_target = Command(**self._last_cmd.as_dict()) if mode == "manual" else None
            change = ModeChange(utc_now_iso(), self.time_s, old, mode, client)
            self.mode_history.append(change)
            self.counters["mode_changes"] += 1
        LOG.warning("mode %s -> %s at t = %.1f s (%s) requested by %s", old, mode, change.time_s, change.utc, client)
        return {"mode": mode, "changed": True, "from": old}

    def set_manual(self, values: dict[str, float], client: str) -> dict[str, Any]:
        """Set actuators in manual mode; refused (with the reason, logged) where the interlock would be."""
        with self._lock:
            if self.mode != "manual" or self._manual_target is None:
                raise ModeError(f"manual commands need mode 'manual' (now {self.mode!r}); PUT /mode first", 409)
            target = replace(self._manual_target, **values)
            why = heater_refusal(target.heater_cmd_w, self.latest, self.cfg.safety) \
                if "heater_cmd_w" in values else None
            if why is not None:
                self.counters["manual_refused"] += 1
            else:
                self._manual_target = target
                self.counters["manual_commands"] += 1
            t = self.time_s
        if why is not None:
            LOG.warning("manual command %s from %s refused at t = %.1f s: %s", values, client, t, why)
            raise ModeError(why, 409)
        LOG.info("manual command %s from %s at t = %.1f s", values, client, t)
        return {"accepted": values, "target": target.as_dict()}

    def status(self) -> dict[str, Any]:
        with self._lock:
            counters = {k: (dict(v) if isinstance(v, dict) else list(v) if isinstance(v, list) else v)
                        for k, v in self.counters.items()}
            out = {"state": self.state, "mode": self._last_mode, "operator_mode": self.mode, "time_s": self.time_s,
                   "connected": self.connected, "controller": self.chain.controllers[0][0],
                   "backend": self.cfg.backend.kind, "reference": self.reference.as_dict(), "counters": counters,
                   "interlock_trips": dict(self.interlock.trips), "heater_estimate_c": self.estimator.temp_c,
                   "uptime_s": time.monotonic() - self._started_wall, "log": self.writer.status(),
                   "degraded": self.degraded(), "unsafe": self.cfg.safety.unsafe_overrides(),
                   "tick_time_bounds_s": list(TICK_TIME_BUCKETS_S),
                   "mode_history": [h.as_dict() for h in list(self.mode_history)[-20:]],
                   "model": self.models.status(),
                   "out_of_reach": dict(self._out_of_reach)}
        injected: dict[str, int] = dict(self.injected)
        for obj in (self.backend, self.chain.controllers[0][1]):
            injected.update(getattr(obj, "injected", {}))
        out["injected_faults"] = injected
        if self.api is not None:
            out["api_requests"] = self.api.stats()
        return out

    def degraded(self) -> list[str]:
        """What works but not as it should (the loop still controls): 'log' while rows are buffered."""
        return ["log"] if self.writer.state != "ok" else []

    def health(self) -> tuple[bool, dict[str, Any]]:
        age = time.monotonic() - self._last_tick_wall
        limit = max(5.0 * self.cfg.loop.wall_period_s, 5.0)
        ok = self.state in ("running", "shutdown") and age < limit
        degraded = self.degraded()
        return ok, {"status": ("degraded" if degraded else "ok") if ok else "down", "degraded": degraded,
                    "state": self.state, "mode": self.mode, "last_tick_age_s": round(age, 3),
                    "connected": self.connected, "log": self.writer.state}

    # ------------------------------------------------------------------ control
    @property
    def time_s(self) -> float:
        return self.t0 + self.tick * self.dt

    def request_stop(self, reason: str = "stop") -> None:
        """Start the shutdown sequence (a second request skips the cool-down wait). Signal-safe."""
        self._stop_requests += 1
        if not self._stop_reason:
            self._stop_reason = reason

    def run(self) -> int:
        self.state = "running"
        self._watchdog = start_watchdog(self.cfg.systemd, self.cfg.loop.wall_period_s, lambda: self.state,
                                        lambda: time.monotonic() - self._last_tick_wall, lambda: self.tick)
        LOG.info("daemon starting at t = %.1f s (log %s, controller %s, backend %s)", self.t0, self.log_path,
                 self.cfg.controller.name, self.cfg.backend.kind)
        wall_period = self.cfg.loop.wall_period_s
        next_wall = time.monotonic()
        try:
            while True:
                t_start = time.perf_counter()
                try:
                    done = self._tick()
                except Exception as exc:  # noqa: BLE001 - any fatal error ends in the safe shutdown
                    # the sample was not logged: its time is reused by the first shutdown sample
                    self.counters["fatal_errors"] += 1
                    LOG.error("fatal error at t = %.1f s: %s\n%s", self.time_s, exc, traceback.format_exc())
                    self.exit_code = 1
                    if self.counters["fatal_errors"] > 1:  # the shutdown itself fails: bare cool-down
                        self._emergency_stop()
                        return self.exit_code
                    self._fatal = True
                    self._stop_reason = self._stop_reason or f"fatal: {exc}"
                    done = False
                self._count_tick_time(time.perf_counter() - t_start)
                self._last_tick_wall = time.monotonic()
                if done:
                    break
                if self.cfg.loop.max_ticks and self.tick >= self.cfg.loop.max_ticks and not (
                        self._stop_requests or self._fatal):
                    self.request_stop("max_ticks")
                if wall_period > 0:
                    next_wall += wall_period
                    delay = next_wall - time.monotonic()
                    if delay < 0:
                        self.counters["late_ticks"] += 1
                        if delay < -wall_period:
                            next_wall = time.monotonic()  # too far behind: resynchronise, do not burst
                    else:
                        self._sleep_until(next_wall)
        finally:
            self._close()
        return self.exit_code

    def _count_tick_time(self, dt_s: float) -> None:
        c = self.counters
        with self._lock:
            c["max_tick_time_s"] = max(c["max_tick_time_s"], dt_s)
            c["tick_time_sum_s"] += dt_s
            c["tick_time_buckets"][bisect.bisect_left(TICK_TIME_BUCKETS_S, dt_s)] += 1

    def _sleep_until(self, wall: float) -> None:
        """Sleep in short slices so a stop request (signal or other thread) is seen within 50 ms."""
        seen = self._stop_requests
        while self._stop_requests == seen:
            left = wall - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, 0.05))

    def _try_connect(self) -> None:
        self.counters["reconnect_attempts"] += 1
        try:
            self.backend.connect()
        except BackendError as exc:
            self._next_reconnect_s = self.time_s + self._backoff_s
            LOG.warning("backend connect failed (%s); next attempt in %.1f s", exc, self._backoff_s)
            self._backoff_s = min(2 * self._backoff_s, self.cfg.safety.reconnect_max_s)
            return
        if not self.connected:
            if self.tick > 0:
                self.counters["reconnects"] += 1
                LOG.warning("backend reconnected at t = %.1f s", self.time_s)
        self.connected = True
        self._backoff_s = self.cfg.safety.reconnect_initial_s
        self.monitor.reset()
        self.chain.reset()

    def _lost(self, exc: Exception) -> None:
        self.counters["backend_errors"] += 1
        if self.connected:
            LOG.warning("backend lost at t = %.1f s: %s", self.time_s, exc)
            self._next_reconnect_s = self.time_s + self._backoff_s
        self.connected = False
        try:
            self.backend.close()
        except Exception:  # noqa: BLE001 - closing a broken link may fail too
            pass

    def _sanitised(self, m: Measurement, status: SensorStatus) -> tuple[Measurement | None, list[str]]:
        """The measurement the controller sees (held values standing in), or None if unusable."""
        s = self.cfg.safety
        t = self.time_s
        values: dict[str, Any] = {}
        unusable = []
        for name in SENSOR_FIELDS:
            v = getattr(m, name)
            if status.valid(name):
                self._held[name] = (v, t)
                values[name] = v
                continue
            held = self._held.get(name)
            if name in s.hold_sensors and held is not None and t - held[1] <= s.hold_last_good_s:
                values[name] = held[0]
            elif name in s.control_sensors:
                unusable.append(name)
                values[name] = None
            else:
                values[name] = None
        if unusable:
            return None, unusable
        values.update({n: _num(getattr(m, n, None)) for n in EXTRA_SIGNALS})  # unchecked, passed on
        return Measurement(time_s=t, **values), []

    def _update_estimator(self, m: Measurement | None, status: SensorStatus | None) -> None:
        est = self.estimator
        valve_a = self._last_cmd.valve_a_pct
        if m is None or status is None:
            est.update(self.dt, self._last_cmd.heater_cmd_w, None, est.air_in_bound_c, valve_a)
            return
        air_in = est.inlet_bound_c(m, status)
        power = m.heater_power_w if status.valid("heater_power_w") else self._last_cmd.heater_cmd_w
        if not self._estimator_ready:
            est.initialise(m, status, power if status.valid("heater_power_w") else 0.0)
            self._estimator_ready = True
            return
        flow = m.volume_flow_m3s if status.valid("volume_flow_m3s") else None
        est.update(self.dt, power, flow, air_in, valve_a)

    def _monitor_model(self, m: Measurement | None, status: SensorStatus | None) -> None:
        """Model monitor update with this reading and the command applied over the last sample."""
        mon = self.models.current.monitor
        was = mon.degraded
        try:
            if m is None or status is None or not status.all_valid(("volume_flow_m3s", "hvac_inlet_temp_c")):
                mon.reset()
            else:
                mon.update(m, self._last_cmd)
        except Exception as exc:  # noqa: BLE001 - the monitor never stops the control
            self.counters["monitor_errors"] = self.counters.get("monitor_errors", 0) + 1
            LOG.error("model monitor failed at t = %.1f s: %s", self.time_s, exc)
            mon.reset()
        if mon.degraded != was:
            LOG.warning("t = %.1f s: model %s %s (horizon RMS %s)", self.time_s, mon.hash,
                        "degraded" if mon.degraded else "back within its bounds", mon.horizon_rms)

    def _shutdown_command(self) -> Command:
        s = self.cfg.safety
        blower = max(self._last_cmd.blower_power_w, s.safe_blower_w)
        return safe_command(s, blower_w=blower)

    def _tick(self) -> bool:
        """One sample; returns True when the daemon has finished its shutdown."""
        t = self.time_s
        s = self.cfg.safety
        for f in self.cfg.faults:
            if f.target == "daemon" and f.active(t) and (f.kind == "fatal_repeated" or id(f) not in self._fired):
                self._fired.add(id(f))
                key = f"daemon:{f.kind}"
                self.injected[key] = self.injected.get(key, 0) + 1
                raise RuntimeError(f"injected fatal error at t = {t} s")
        self._swap_model()
        with self._lock:
            ref = self.reference
            switched, self._switched = self._switched, False
            op_mode, manual_target = self.mode, self._manual_target
        if switched:
            self._switch_to(op_mode)
        if (self._stop_requests or self._fatal) and self._shutdown_start_s is None:
            self._shutdown_start_s = t
            self.state = "shutdown"
            LOG.warning("shutdown (%s) at t = %.1f s: heater off, blower running until the heater has cooled",
                        self._stop_reason, t)
        if not self.connected and t >= self._next_reconnect_s:
            self._try_connect()
        m: Measurement | None = None
        if self.connected:
            try:
                m = self.backend.read()
            except BackendError as exc:
                self._lost(exc)
        status = self.monitor.check(m) if m is not None else None
        if status is not None:
            for name, kind in status.faults.items():
                key = f"{name}:{kind}"
                self.counters["sensor_fault_ticks"][key] = self.counters["sensor_fault_ticks"].get(key, 0) + 1
            if status.stale:
                self.counters["sensor_fault_ticks"]["sample:stale"] = \
                    self.counters["sensor_fault_ticks"].get("sample:stale", 0) + 1
        self._update_estimator(m, status)
        self._monitor_model(m, status)

        used = "none"
        events: list[str] = []
        stats: dict[str, Any] = {}
        finished = False
        if self._shutdown_start_s is not None:
            mode = "shutdown"
            cmd = self._shutdown_command()
            self.counters["shutdown_ticks"] += 1
            elapsed = t - self._shutdown_start_s
            flow_ok = status is not None and status.valid("volume_flow_m3s")
            cooled = flow_ok and self.estimator.cooled(s.cooldown_margin_c) and elapsed >= s.cooldown_min_s
            if self._stop_requests >= 2 or cooled or elapsed >= s.cooldown_max_s:
                mode = "stopped"
                finished = True
                if self._stop_requests < 2:  # heater cool: the blower may go to its minimum
                    cmd = safe_command(s, blower_w=BLOWER_MIN_W)
        elif m is None:
            mode = "disconnected"
            cmd = safe_command(s)
            self.counters["disconnected_ticks"] += 1
        else:
            cm, unusable = self._sanitised(m, status)
            if cm is None:
                mode = "safe"
                cmd = safe_command(s)
                events.append("sensors:" + ",".join(unusable))
                self.counters["safe_ticks"] += 1
                self.chain.reset()
            elif op_mode == "safe-stop":
                mode = used = "safe-stop"
                cmd = safe_command(s, blower_w=max(self._last_cmd.blower_power_w, s.safe_blower_w))
            elif op_mode == "manual" and manual_target is not None:
                mode = used = "manual"
                cmd = rate_limited(manual_target, self._last_cmd, s, self.dt)
            else:
                working = self._ramp.working(cm, ref, self.dt)  # bumpless: ramps after a switch
                outcome = self.chain.step(cm, working, self._last_cmd)
                events += outcome.events
                stats = outcome.stats
                self.counters["max_step_time_s"] = max(self.counters["max_step_time_s"], outcome.step_time_s)
                for e in outcome.events:
                    if e == "deadline":
                        self.counters["deadline_misses"] += 1
                    elif e == "busy":
                        self.counters["controller_busy"] += 1
                    elif e.startswith("error") or e.startswith("fallback_error"):
                        self.counters["controller_errors"] += 1
                    elif "not_finite" in e:
                        self.counters["not_finite_commands"] += 1
                if outcome.command is None:
                    mode = "safe"
                    cmd = safe_command(s)
                    self.counters["safe_ticks"] += 1
                else:
                    cmd = outcome.command
                    used = outcome.used or "none"
                    self._count_stats(stats)
                    mode = str(stats.get("mode") or "control")
                    if t < self._transfer_until_s:  # bumpless: rate-limited from the command in force
                        cmd = rate_limited(cmd, self._last_cmd, s, self.dt)
                    if used == self.chain.controllers[0][0]:
                        self.counters["primary_ticks"] += 1
                    else:
                        fb = self.counters["fallback_ticks"]
                        fb[used] = fb.get(used, 0) + 1
                        mode = f"fallback:{mode}"

        cmd, reasons = self.interlock.apply(cmd, m, status, self.estimator.temp_c, backend_ok=m is not None)
        try:
            self.backend.write(cmd)
        except BackendError as exc:
            if self.connected:
                self._lost(exc)
        self._last_cmd = cmd
        if mode != self._last_mode:
            LOG.info("t = %.1f s: mode %s -> %s %s", t, self._last_mode or "-", mode, " ".join(events))
            self._last_mode = mode
        row = self._row(t, m, cmd, ref, mode, used)
        self.writer.write(row)
        self.tick += 1  # the sample is logged: from here on a failure cannot lose or repeat it
        sample = dict(row)
        sample.update({"interlock": reasons, "sensor_faults": dict(status.faults) if status else None,
                       "stale": bool(status.stale) if status else None, "events": events,
                       "connected": self.connected, "heater_estimate_c": round(self.estimator.temp_c, 3),
                       "solver_status": stats.get("status"), "inner_fallback": stats.get("fallback"),
                       "out_of_reach": dict(stats.get("out_of_reach") or {}),
                       "working_reference": self._ramp.status()})
        with self._lock:
            self.latest = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                           for k, v in sample.items()}
            self._out_of_reach = sample["out_of_reach"]
            self.counters["ticks"] += 1
        if self.tick_hook is not None:
            self.tick_hook(self, sample)
        return finished

    def _switch_to(self, op_mode: str) -> None:
        """Apply a mode switch in the loop thread: the new chain is reset (its controller starts
        from the command in force), the transfer window begins and, into an automatic mode, the
        reference ramp from the readings (:class:`.modes.ReferenceRamp`)."""
        if op_mode in self.chains:
            self.chain = self.chains[op_mode]
            self.chain.reset()
        self._transfer_until_s = self.time_s + self.cfg.safety.transfer_s
        if op_mode in AUTO_CONTROLLERS or op_mode == "auto":
            self._ramp.arm()
        else:
            self._ramp.cancel()

    def _count_stats(self, stats: dict[str, Any]) -> None:
        """Count the controller's own solver statuses and fallbacks (bounded number of keys)."""
        for key, value in (("solver_status", stats.get("status")), ("inner_fallback_ticks", stats.get("fallback"))):
            if value is None:
                continue
            counts = self.counters[key]
            name = str(value).split(":", 1)[0][:40]
            if name in counts or len(counts) < 20:
                counts[name] = counts.get(name, 0) + 1

    def _row(self, t: float, m: Measurement | None, cmd: Command, ref: Reference, mode: str, used: str) -> dict:
        row: dict[str, Any] = {"time_s": t}
        row.update({f: getattr(cmd, f) for f in COMMAND_FIELDS})
        for name in SENSOR_FIELDS:
            row[name] = _num(getattr(m, name)) if m is not None else None
        for f, col in REF_COLUMNS.items():
            row[col] = getattr(ref, f)
        for name in EXTRA_SIGNALS:
            row[name] = _num(getattr(m, name, None)) if m is not None else None
        row["mode"] = mode
        row["controller"] = used
        row["utc"] = utc_now_iso()
        row["model_hash"] = self.models.current.hash
        return row

    def _emergency_stop(self) -> None:
        """A fatal error during the shutdown itself: the bare cool-down without log or API.

        Heater off with the blower running (written every sample), until the heater estimate has
        cooled or ``cooldown_max_s`` has passed, or a further stop request arrives; every step
        tolerates failures."""
        s = self.cfg.safety
        cmd = self._shutdown_command()
        LOG.error("emergency stop: heater off, blower %.0f W until the heater has cooled", cmd.blower_power_w)
        requests = self._stop_requests
        start = time.monotonic()
        elapsed_s = 0.0
        while elapsed_s < s.cooldown_max_s and self._stop_requests == requests:
            try:
                self.backend.write(cmd)
                m = self.backend.read()
                st = self.monitor.check(m)
                self.estimator.update(self.dt, 0.0, m.volume_flow_m3s if st.valid("volume_flow_m3s") else None,
                                      self.estimator.inlet_bound_c(m, st), cmd.valve_a_pct)
                if st.valid("volume_flow_m3s") and self.estimator.cooled(s.cooldown_margin_c):
                    break
            except Exception:  # noqa: BLE001 - keep trying to hold the safe outputs
                try:
                    self.backend.connect()
                except Exception:  # noqa: BLE001
                    pass
            self.tick += 1  # the simulated plant advances with the daemon clock
            elapsed_s += self.dt
            if self.cfg.loop.wall_period_s > 0:
                self._sleep_until(start + elapsed_s / self.dt * self.cfg.loop.wall_period_s)
        try:
            self.backend.write(safe_command(s, blower_w=BLOWER_MIN_W if self._stop_requests == requests
                                            else cmd.blower_power_w))
        except Exception:  # noqa: BLE001
            LOG.error("emergency stop: could not write the final safe command")

    def _close(self) -> None:
        self.state = "stopped"
        if self._watchdog is not None:
            self._watchdog.stop()
        previous = self.models.previous
        chains = set(self.chains.values()) | ({previous.chain} if previous is not None and previous.chain else set())
        closers = [c.close for c in chains] + [self.backend.close, self.writer.close]
        for closer in closers:
            try:
                closer()
            except Exception:  # noqa: BLE001
                LOG.exception("while closing")
        if self.api is not None:
            self.api.stop()
        self._log_lock.close()
        LOG.info("daemon stopped at t = %.1f s (%s)", self.time_s, self._stop_reason or "done")

