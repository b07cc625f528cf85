"""The daemon's fixed-rate control loop with its safety layer, log and shutdown sequence.

Each tick (sample time ``time_s = t0 + k * period_s``):

1. read the sensors from the backend (a failure marks the link lost; reconnects follow with a
   doubling backoff, safe outputs are written meanwhile);
2. check every reading (NaN, missing, out of range, stuck; stale sample) and update the heater
   body estimate;
3. compute the command: the controller chain (primary under a deadline, fallbacks), or the safe
   command when a sensor the controller needs is invalid, or the shutdown command;
4. apply the heater interlock (independent of any controller), write the command;
5. append the sample to the measurement log (flushed and fsynced) and publish it to the API.

Shutdown (SIGTERM/SIGINT, ``max_ticks`` or a fatal error): heater off at once, the blower
keeps running at least at ``safe_blower_w`` with all outlets open and valve a sending the air
through the heater, until the heater estimate has cooled (or ``cooldown_max_s``); then the
blower goes to its minimum and the daemon exits. A second stop request skips the wait (heater
off, blower left running). The log's time continues across restarts (the new run starts one
sample after the last logged row), so a restarted daemon appends without a gap.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Callable

from hvac_mpc.models.measurement_log import COLUMNS, LogWriter
from hvac_mpc.models.model_file import load as load_refined_model
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.contract import Command, Measurement
from hvac_mpc.contract import Reference

from .backends import BackendError, IoBackend, make_backend
from .config import SENSOR_FIELDS, DaemonConfig, resolve
from .controllers import ControllerChain, FaultInjectingController, load_controller
from .safety import HeaterEstimator, HeaterInterlock, SensorMonitor, SensorStatus, safe_command

LOG = logging.getLogger("hvac_mpc.daemon")
COMMAND_FIELDS = ("blower_power_w", "heater_cmd_w", "valve_a_pct", "valve_m_pct", "valve_f_pct", "valve_w_pct")
REF_COLUMNS = {"supply_temp_c": "ref_supply_temp_c", "volume_flow_m3s": "ref_volume_flow_m3s",
               "flow_m_m3s": "ref_flow_m_m3s", "flow_f_m3s": "ref_flow_f_m3s", "flow_w_m3s": "ref_flow_w_m3s"}
BLOWER_MIN_W = 30.0


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
                 tick_hook: Callable[["Daemon", dict], None] | None = None):
        self.cfg = config
        self.dt = config.loop.period_s
        pfile, mfile = config.controller.parameters_file, config.controller.model_file
        self.refined = load_refined_model(resolve(config, mfile)) if mfile else None
        self.params = (self.refined.parameters if self.refined is not None else
                       Parameters.from_file(resolve(config, pfile)) if pfile else Parameters())
        self.tick_hook = tick_hook
        self._lock = threading.Lock()
        self._stop_requests = 0
        self._stop_reason = ""
        self._fatal = False

        # log first: its last row fixes the start time (restart appends)
        self.log_path = resolve(config, config.log.path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log_lock = _lock_log(self.log_path)
        try:
            self.writer = LogWriter(self.log_path, COLUMNS, fsync=config.log.fsync)
            last = last_logged_time(self.log_path)
            self.t0 = 0.0 if last is None else last + self.dt
            self.tick = 0
            self.backend = backend or make_backend(config, self.params, clock=lambda: self.time_s)
            self.chain = self._build_chain()
        except BaseException:
            self._log_lock.close()
            raise
        self.monitor = SensorMonitor(config.safety)
        self.interlock = HeaterInterlock(config.safety, self.params)
        self.estimator = HeaterEstimator(self.params)
        self._estimator_ready = False
        self.reference = config.initial_reference
        self.connected = False
        self._next_reconnect_s = self.t0
        self._backoff_s = config.safety.reconnect_initial_s
        self._held: dict[str, tuple[float, float]] = {}  # field -> (value, time_s of last good reading)
        self._last_cmd = safe_command(config.safety)
        self._last_mode = ""
        self._shutdown_start_s: float | None = None
        self.state = "starting"
        self.exit_code = 0
        self.latest: dict[str, Any] | None = None
        self._last_tick_wall = time.monotonic()
        self._started_wall = time.monotonic()
        self.counters: dict[str, Any] = {
            "ticks": 0, "late_ticks": 0, "deadline_misses": 0, "controller_busy": 0, "controller_errors": 0,
            "not_finite_commands": 0, "primary_ticks": 0, "fallback_ticks": {}, "safe_ticks": 0,
            "disconnected_ticks": 0, "backend_errors": 0, "reconnect_attempts": 0, "reconnects": 0,
            "sensor_fault_ticks": {}, "reference_updates": 0, "fatal_errors": 0, "shutdown_ticks": 0,
            "max_step_time_s": 0.0, "max_tick_time_s": 0.0, "solver_status": {}, "inner_fallback_ticks": {},
        }
        self._fired: set[int] = set()
        self.injected: dict[str, int] = {}
        self.api = None
        if config.api.enabled:
            self._start_api()

    # ------------------------------------------------------------------ construction
    def _build_chain(self) -> ControllerChain:
        c = self.cfg.controller
        names = [c.name] + [f for f in c.fallback if f != c.name]
        chain = []
        for i, name in enumerate(names):
            ctrl = load_controller(name, self.params, self.dt, c.settings if i == 0 else None,
                                   model=self.refined if name == "mpc" else None)
            if i == 0 and any(f.target == "controller" for f in self.cfg.faults):
                ctrl = FaultInjectingController(ctrl, self.cfg.faults, clock=lambda: self.time_s)
            chain.append((name, ctrl))
        return ControllerChain(chain, self.cfg.loop.step_deadline_s)

    def _start_api(self) -> None:
        import os

        from .api import ReferenceApi

        a = self.cfg.api
        token = a.token or (os.environ.get(a.token_env, "") if a.token_env else "")
        if a.token_env and not token and a.host not in ("127.0.0.1", "localhost", "::1"):
            raise ValueError(f"api.token_env = {a.token_env!r} is empty or unset; refusing to serve on {a.host}")
        self.api = ReferenceApi(self, a.host, a.port, token=token, max_body_bytes=a.max_body_bytes,
                                request_timeout_s=a.request_timeout_s).start()
        if a.port_file:
            pf = resolve(self.cfg, a.port_file)
            tmp = pf.with_suffix(pf.suffix + ".tmp")
            tmp.write_text(str(self.api.port))
            tmp.replace(pf)
        LOG.info("reference API on http://%s:%d", a.host, self.api.port)

    # ------------------------------------------------------------------ API side (thread-safe)
    def get_reference(self) -> Reference:
        with self._lock:
            return self.reference

    def set_reference(self, ref: Reference) -> None:
        with self._lock:
            self.reference = ref
            self.counters["reference_updates"] += 1

    def latest_sample(self) -> dict[str, Any] | None:
        with self._lock:
            return None if self.latest is None else dict(self.latest)

    def status(self) -> dict[str, Any]:
        with self._lock:
            counters = {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.counters.items()}
            out = {"state": self.state, "mode": self._last_mode, "time_s": self.time_s, "connected": self.connected,
                   "controller": self.cfg.controller.name, "backend": self.cfg.backend.kind,
                   "reference": self.reference.as_dict(), "counters": counters,
                   "interlock_trips": dict(self.interlock.trips), "heater_estimate_c": self.estimator.temp_c,
                   "uptime_s": time.monotonic() - self._started_wall}
        injected: dict[str, int] = dict(self.injected)
        for obj in (self.backend, self.chain.controllers[0][1]):
            injected.update(getattr(obj, "injected", {}))
        out["injected_faults"] = injected
        if self.api is not None:
            out["api_requests"] = {**self.api.counts, "dropped": self.api.dropped, "refused": self.api.refused}
        return out

    def health(self) -> tuple[bool, dict[str, Any]]:
        age = time.monotonic() - self._last_tick_wall
        limit = max(5.0 * self.cfg.loop.wall_period_s, 5.0)
        ok = self.state in ("running", "shutdown") and age < limit
        return ok, {"state": self.state, "last_tick_age_s": round(age, 3), "connected": self.connected}

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
                self.counters["max_tick_time_s"] = max(self.counters["max_tick_time_s"],
                                                       time.perf_counter() - t_start)
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
        with self._lock:
            ref = self.reference
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
            else:
                outcome = self.chain.step(cm, ref, self._last_cmd)
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
                    if used == self.cfg.controller.name:
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
                       "solver_status": stats.get("status"), "inner_fallback": stats.get("fallback")})
        with self._lock:
            self.latest = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                           for k, v in sample.items()}
            self.counters["ticks"] += 1
        if self.tick_hook is not None:
            self.tick_hook(self, sample)
        return finished

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
        row["mode"] = mode
        row["controller"] = used
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
        for closer in (self.chain.close, self.backend.close, self.writer.close):
            try:
                closer()
            except Exception:  # noqa: BLE001
                LOG.exception("while closing")
        if self.api is not None:
            self.api.stop()
            if self.cfg.api.port_file:
                resolve(self.cfg, self.cfg.api.port_file).unlink(missing_ok=True)
        self._log_lock.close()
        LOG.info("daemon stopped at t = %.1f s (%s)", self.time_s, self._stop_reason or "done")

