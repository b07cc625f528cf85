"""Model monitoring: the prediction residual of the model in force, computed online.

Every sample the daemon hands the monitor the reading and the command that was applied over the
last sample. The monitor keeps a state estimate of the model (propagated with the applied
commands and the measured inlet temperature and chiller set point; the thermocouple state and,
when logged, the water temperature are set to their readings) and computes two residuals per
output (``supply_temp_c``, ``volume_flow_m3s``, ``heater_outlet_temp_c``):

* one step: the reading minus the model's prediction one sample ahead from the last estimate;
* horizon: every ``every_s`` seconds, a free run of the model over the last ``horizon_s``
  seconds, from the estimate at the window's start, fed with the applied commands and the
  measured disturbances; its RMS error against the readings of the window.

At each evaluation the one-step residuals of the same window give a one-step RMS. Both RMS values are
bounded (windowed, not single samples: one noisy sample or one reference step does not decide);
the larger of horizon RMS / its bound and one-step RMS / its bound is the output's score, and the
model is ``degraded`` after
``degraded_after`` evaluations in a row with a score above 1 and ``ok`` again after as many at
or below 1. The model file's hash (:func:`model_hash`) names the model in every log row
(docs/real-box.md, model monitoring).
"""

from __future__ import annotations

import hashlib
import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import casadi as ca
import numpy as np

from hvac_mpc.contract import Command, Measurement
from hvac_mpc.models.box import HvacModel
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.validation import InvalidValue, check_fields, finite_in

#: Outputs the monitor predicts (model output names, also the measurement's).
MONITORED = ("supply_temp_c", "volume_flow_m3s", "heater_outlet_temp_c")
#: Hash of the built-in model (no model file).
BUILTIN_HASH = "builtin"
#: Bounds on the horizon RMS residual, 1.25 times the largest a healthy box gave (docs/real-box.md,
#: model monitoring: ``python -m hvac_mpc.benchmarks.monitor_bounds``, the bench's perturbed plant, the
#: built-in nominal plant and the independent nominal box, both controllers, three scenarios).
DEFAULT_BOUNDS = {"supply_temp_c": 4.6, "volume_flow_m3s": 0.016, "heater_outlet_temp_c": 26.0}
#: Bounds on the one-step RMS residual over the same window, set the same way.
DEFAULT_ONE_STEP_BOUNDS = {"supply_temp_c": 0.8, "volume_flow_m3s": 0.016, "heater_outlet_temp_c": 26.0}


class InvalidMonitorSettings(InvalidValue):
    """A monitor setting is out of range; the message names it."""


@dataclass(frozen=True)
class MonitorSettings:
    """Window, cadence, bounds and hysteresis of the model monitor (times in s)."""

    horizon_s: float = field(default=60.0, metadata={"check": finite_in(5.0, 3600.0)})
    every_s: float = field(default=10.0, metadata={"check": finite_in(1.0, 3600.0)})
    bound_supply_temp_c: float = field(default=DEFAULT_BOUNDS["supply_temp_c"],
                                       metadata={"check": finite_in(1e-3, 100.0)})
    bound_volume_flow_m3s: float = field(default=DEFAULT_BOUNDS["volume_flow_m3s"],
                                         metadata={"check": finite_in(1e-6, 1.0)})
    bound_heater_outlet_temp_c: float = field(default=DEFAULT_BOUNDS["heater_outlet_temp_c"],
                                              metadata={"check": finite_in(1e-3, 100.0)})
    bound_one_step_supply_temp_c: float = field(default=DEFAULT_ONE_STEP_BOUNDS["supply_temp_c"],
                                                metadata={"check": finite_in(1e-3, 100.0)})
    bound_one_step_volume_flow_m3s: float = field(default=DEFAULT_ONE_STEP_BOUNDS["volume_flow_m3s"],
                                                  metadata={"check": finite_in(1e-6, 1.0)})
    bound_one_step_heater_outlet_temp_c: float = field(default=DEFAULT_ONE_STEP_BOUNDS["heater_outlet_temp_c"],
                                                       metadata={"check": finite_in(1e-3, 100.0)})
    degraded_after: int = field(default=3, metadata={"check": finite_in(1, 1000, integer=True)})

    def __post_init__(self) -> None:
        check_fields(self, error=InvalidMonitorSettings)

    @property
    def bounds(self) -> dict[str, float]:
        return {o: getattr(self, f"bound_{o}") for o in MONITORED}

    @property
    def one_step_bounds(self) -> dict[str, float]:
        return {o: getattr(self, f"bound_one_step_{o}") for o in MONITORED}


def model_hash(path: str | Path | None) -> str:
    """First 16 hex digits of the SHA-256 of a model file's bytes; :data:`BUILTIN_HASH` for none."""
    if path is None or str(path) == "":
        return BUILTIN_HASH
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def _window_function(model: HvacModel, n: int) -> ca.Function:
    """Free run over ``n`` samples: (x0, Z, p) -> (X, Y); column k of Z is [u; d; water; has_water]."""
    nx, nu, nd = len(model.states), len(model.inputs), len(model.disturbances)
    iw = model.states.index("water_temp_c")
    x = ca.SX.sym("x", nx)
    z = ca.SX.sym("z", nu + nd + 2)
    p = ca.SX.sym("p", len(model.param_names))
    u, d, water, flag = z[:nu], z[nu:nu + nd], z[nu + nd], z[nu + nd + 1]
    pin = ca.DM.zeros(nx)
    pin[iw] = 1.0
    xo = x + flag * (water - x[iw]) * pin
    xn = model.step(xo, u, d, p)
    idx = [model.outputs.index(o) for o in MONITORED]
    y = model.output(xn, u, d, p)[idx]
    one = ca.Function("one", [x, z, p], [xn, y])
    return one.mapaccum("window", n)


class ModelMonitor:
    """Online prediction residual of one model (parameters and effects); see the module docstring."""

    def __init__(self, params: Parameters | None = None, effects: Iterable[str] = (), dt_s: float = 1.0,
                 settings: MonitorSettings | None = None, model_hash: str = BUILTIN_HASH):
        self.settings = settings or MonitorSettings()
        self.params = params or Parameters()
        self.model = HvacModel(self.params, tuple(effects), dt_s=dt_s)
        self.dt_s = float(dt_s)
        self.hash = model_hash
        self.n_window = max(2, int(round(self.settings.horizon_s / self.dt_s)))
        self.every = max(1, int(round(self.settings.every_s / self.dt_s)))
        self._window = _window_function(self.model, self.n_window)
        self._one = self._window_function_one()
        self._p = self.model.p_default
        self._iw = self.model.states.index("water_temp_c")
        self._is = self.model.states.index("supply_sensor_c")
        self.reset()

    def _window_function_one(self) -> ca.Function:
        return _window_function(self.model, 1)

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the history (after a lost link or a model swap of the daemon)."""
        self._x: np.ndarray | None = None
        self._z_prev: np.ndarray | None = None
        # per sample: (state estimate at its start, z applied over it, readings at its end)
        self._hist: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=self.n_window)
        self._since_eval = 0
        self._beyond = 0
        self._within = 0
        self.degraded = False
        self.samples = 0
        self.evaluations = 0
        self.one_step: dict[str, float | None] = {o: None for o in MONITORED}
        self._one_sq: dict[str, deque] = {o: deque(maxlen=self.n_window) for o in MONITORED}
        self.horizon_rms: dict[str, float | None] = {o: None for o in MONITORED}
        self.horizon_rms_history: list[tuple[float, dict[str, float | None]]] = []
        self.one_step_window_rms: dict[str, float | None] = {o: None for o in MONITORED}
        self.one_step_rms_history: list[tuple[float, dict[str, float | None]]] = []

    def _z(self, m: Measurement, u: np.ndarray) -> np.ndarray | None:
        inlet, sp = m.hvac_inlet_temp_c, m.chiller_setpoint_c
        if not _ok(inlet):
            return None
        d = self.model.d_vector(inlet, sp if _ok(sp) else 5.0)
        water = m.water_temp_c
        has = 1.0 if _ok(water) else 0.0
        return np.concatenate([u, d, [water if has else 0.0, has]])

    def update(self, m: Measurement, applied: Command) -> None:
        """One sample: reading ``m`` at t_k, ``applied`` the command in force over [t_{k-1}, t_k)
        (and, for a first sample, the command in force before it)."""
        u = applied.vector()
        z = self._z(m, u)
        if z is None:
            self.reset()
            return
        y = np.array([_val(getattr(m, o)) for o in MONITORED])
        if self._x is None:
            x = self.model.steady_state(u, z[len(u):len(u) + 4], self._p)
            self._x = self._corrected(x, m)
            self._z_prev = z
            return
        x_start = self._x
        xn, yp = self._one(x_start, self._z_prev, self._p)
        yp = np.asarray(yp).ravel()
        for i, o in enumerate(MONITORED):
            r = y[i] - yp[i]
            self.one_step[o] = None if not math.isfinite(r) else float(r)
            if math.isfinite(r):
                self._one_sq[o].append(r * r)
        self._hist.append((x_start, self._z_prev, y))
        self._x = self._corrected(np.asarray(xn).ravel(), m)
        self._z_prev = z
        self.samples += 1
        self._since_eval += 1
        if len(self._hist) == self.n_window and self._since_eval >= self.every:
            self._evaluate(float(m.time_s))

    def _corrected(self, x: np.ndarray, m: Measurement) -> np.ndarray:
        x = x.copy()
        if _ok(m.supply_temp_c):
            x[self._is] = m.supply_temp_c
        if _ok(m.water_temp_c):
            x[self._iw] = m.water_temp_c
        return x

    def _evaluate(self, time_s: float) -> None:
        self._since_eval = 0
        x0 = self._hist[0][0]
        zs = np.column_stack([h[1] for h in self._hist])
        ys = np.column_stack([h[2] for h in self._hist])
        _, yp = self._window(x0, zs, np.tile(self._p[:, None], (1, self.n_window)))
        err = ys - np.asarray(yp)
        for i, o in enumerate(MONITORED):
            e = err[i][np.isfinite(err[i])]
            self.horizon_rms[o] = float(np.sqrt(np.mean(e * e))) if e.size >= self.n_window // 2 else None
            q = self._one_sq[o]
            self.one_step_window_rms[o] = float(np.sqrt(np.mean(q))) if len(q) >= self.n_window // 2 else None
        self.evaluations += 1
        self.horizon_rms_history.append((time_s, dict(self.horizon_rms)))
        self.one_step_rms_history.append((time_s, dict(self.one_step_window_rms)))
        if len(self.horizon_rms_history) > 1000:
            del self.horizon_rms_history[:500]
            del self.one_step_rms_history[:500]
        if self.score() > 1.0:
            self._beyond += 1
            self._within = 0
        else:
            self._within += 1
            self._beyond = 0
        n = self.settings.degraded_after
        if not self.degraded and self._beyond >= n:
            self.degraded = True
        elif self.degraded and self._within >= n:
            self.degraded = False

    # ------------------------------------------------------------------ results
    def scores(self) -> dict[str, float | None]:
        """Per output the larger of horizon RMS / its bound and one-step RMS over the window / its
        bound (``None`` before the first evaluation)."""
        b, b1 = self.settings.bounds, self.settings.one_step_bounds
        out: dict[str, float | None] = {}
        for o in MONITORED:
            parts = [v / bound for v, bound in ((self.horizon_rms[o], b[o]), (self.one_step_window_rms[o], b1[o]))
                     if v is not None]
            out[o] = max(parts) if parts else None
        return out

    def score(self) -> float:
        """The largest score over the outputs (0 before the first evaluation)."""
        return max((s for s in self.scores().values() if s is not None), default=0.0)

    @property
    def state(self) -> str:
        if self.evaluations == 0:
            return "warming_up"
        return "degraded" if self.degraded else "ok"

    def status(self) -> dict[str, Any]:
        """What the daemon's status shows (plain numbers, JSON-ready)."""
        one_rms = {o: (float(np.sqrt(np.mean(q))) if q else None) for o, q in self._one_sq.items()}
        return {"state": self.state, "degraded": self.degraded, "model_hash": self.hash,
                "horizon_s": self.n_window * self.dt_s, "evaluations": self.evaluations,
                "one_step_residual": dict(self.one_step), "one_step_rms": one_rms,
                "horizon_rms": dict(self.horizon_rms), "scores": self.scores(), "bounds": self.settings.bounds,
                "one_step_window_rms": dict(self.one_step_window_rms),
                "one_step_bounds": self.settings.one_step_bounds}

    def metrics(self) -> dict[str, float]:
        """Flat numeric gauges (name -> value) for a metrics exporter; missing values left out."""
        out: dict[str, float] = {"model_degraded": float(self.degraded), "model_score": self.score()}
        for o in MONITORED:
            if self.horizon_rms[o] is not None:
                out[f"model_horizon_rms_{o}"] = self.horizon_rms[o]
            if self.one_step[o] is not None:
                out[f"model_one_step_residual_{o}"] = self.one_step[o]
        return out


def _ok(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _val(v: Any) -> float:
    return float(v) if _ok(v) else math.nan


class ModelLoadError(ValueError):
    """A model file cannot be loaded (missing, invalid, or its model does not run); nothing changed."""


@dataclass
class ModelInForce:
    """A model the daemon runs: its file (``""`` for the built-in one), hash, parameters, effects,
    monitor, and the controller chain built on its parameters."""

    path: str
    hash: str
    params: Parameters
    effects: tuple[str, ...]
    monitor: ModelMonitor
    chain: Any


class ModelSlots:
    """The model in force, the one before it (for a rollback) and a swap waiting for the next sample.

    ``request`` is called from any thread; the loop calls ``take`` at the start of a sample, so a
    swap always falls between two samples. ``events`` records every swap (who asked, when, what).
    """

    def __init__(self, current: ModelInForce):
        self.current = current
        self.previous: ModelInForce | None = None
        self._pending: tuple[ModelInForce, str, str] | None = None
        self.events: list[dict[str, Any]] = []

    def request(self, model: ModelInForce, client: str, action: str) -> ModelInForce | None:
        """Ask for ``model`` at the next sample; returns a model that was waiting and is now dropped."""
        dropped = None if self._pending is None else self._pending[0]
        self._pending = (model, client, action)
        return dropped

    def pending(self) -> bool:
        return self._pending is not None

    def status(self) -> dict[str, Any]:
        """The monitor's status of the model in force, its file, effects and the last swaps."""
        c = self.current
        return {**c.monitor.status(), "path": c.path, "effects": list(c.effects), "swap_pending": self.pending(),
                "events": list(self.events[-10:])}

    def take(self, time_s: float, wall_time: str) -> tuple[ModelInForce, ModelInForce, dict] | None:
        """Swap in the waiting model; returns (old, new, event) or None when nothing waits."""
        if self._pending is None:
            return None
        model, client, action = self._pending
        self._pending = None
        old = self.current
        self.previous, self.current = old, model
        event = {"time_s": time_s, "wall_time": wall_time, "client": client, "action": action,
                 "from_hash": old.hash, "to_hash": model.hash, "path": model.path}
        self.events.append(event)
        del self.events[:-100]
        return old, model, event


def read_model(path: str, dt_s: float, settings: MonitorSettings | None = None) -> ModelInForce:
    """A model file (``""``: the built-in model) read, validated and run once, with its monitor; the
    controller chain is left to the daemon. Raises :class:`ModelLoadError` naming the problem."""
    from hvac_mpc.identification.model_file import load_model_file

    try:
        params, effects = load_model_file(path) if path else (Parameters(), ())
        mon = ModelMonitor(params, effects, dt_s, settings, model_hash(path or None))
        probe = mon.model.steady_state(Command().vector(), mon.model.d_vector(25.0, 5.0), mon.model.p_default)
        if not np.all(np.isfinite(probe)):
            raise ValueError("its steady state at the default command is not finite")
    except (OSError, ValueError, KeyError, TypeError, RuntimeError) as exc:
        raise ModelLoadError(f"model file {path!r}: {exc}") from None
    return ModelInForce(path, mon.hash, params, tuple(effects), mon, None)
