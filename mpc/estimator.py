"""Extended Kalman filter on the model states augmented with disturbance states.

Augmented state ``z = [x, mix_offset_c, flow_offset_m3s, inlet_temp_c]``: the model states
(``HvacModel.states``), the two unmeasured offsets the model adds to the mixed supply air
temperature and the total volume flow (random walks: they absorb whatever the plant does that
the model does not), and the inlet air temperature (a random walk measured with noise).
Measurements (each used when present and finite): thermocouple ``supply_temp_c``,
``volume_flow_m3s``, ``water_temp_c``, ``hvac_inlet_temp_c`` and, optionally,
``heater_outlet_temp_c``.

Offset-free tracking: the MPC predicts with the estimated offsets, and at rest the filter
makes the model reproduce the measured supply temperature and flow exactly, so the
controller's steady state has no error in the measured outputs (Pannocchia and Rawlings'
disturbance-model argument: as many integrating disturbances as tracked measured outputs;
docs/architecture.md, 'One control step').

Chiller water (``water_prediction``): ``"hold"`` treats the water temperature as a random walk
(the chiller's two-point switching is unknown to the model, thesis sec. 2.2); ``"setpoint"``
lets it ramp towards the chiller set point as in the model (thesis sec. 4.2).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import casadi as ca
import numpy as np

from hvac_mpc.models.box import HvacModel, rk4
from hvac_mpc.contract import Measurement

from .casadi_eval import BufferedFunction
from .ocp import InvalidSettings, check_number

#: Measurement names in the order of the filter's measurement vector.
MEASURED = ("supply_temp_c", "volume_flow_m3s", "water_temp_c", "hvac_inlet_temp_c", "heater_outlet_temp_c")


@dataclass(frozen=True)
class EkfSettings:
    """Noise levels of the filter (1 sigma; process noise per sample of 1 s). ASSUMPTIONS tuned on
    the simulated plant; measurement noise matches the plant's sensor-noise parameters.

    ``use_heater_outlet`` uses the heater outlet thermocouple when the measurement carries it.
    """

    q_motor_c: float = 0.01
    q_water_c: float = 0.01
    q_heater_c: float = 0.1
    q_sensor_c: float = 0.02
    q_trap_c: float = 0.1
    q_mix_offset_c: float = 0.03
    q_flow_offset_m3s: float = 3e-5
    q_inlet_c: float = 0.01
    r_supply_c: float = 0.05
    r_flow_m3s: float = 4e-4
    r_water_c: float = 0.05
    r_inlet_c: float = 0.05
    r_heater_outlet_c: float = 0.2
    use_heater_outlet: bool = True

    def validate(self, prefix: str = "ekf") -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "use_heater_outlet":
                if not isinstance(value, bool):
                    raise InvalidSettings(f"{prefix}.use_heater_outlet must be True or False")
                continue
            check_number(f"{prefix}.{f.name}", value, 0.0, 100.0, lo_open=True)


class DisturbanceEkf:
    """EKF for the HVAC box; ``predict(u)`` after applying a command, ``update(measurement)`` on arrival."""

    def __init__(self, model: HvacModel, settings: EkfSettings | None = None, dt_s: float = 1.0,
                 water_prediction: str = "hold"):
        self.model = model
        self.settings = s = settings or EkfSettings()
        self.dt_s = float(dt_s)
        self.hold_water = water_prediction == "hold"
        self.nx = len(model.states)
        self.nz = self.nx + 3
        names = model.states.names
        self.i_water = names.index("water_temp_c")
        self.i_sensor = names.index("supply_sensor_c")
        q_state = {"motor_rise_c": s.q_motor_c, "water_temp_c": s.q_water_c, "heater_temp_c": s.q_heater_c,
                   "supply_sensor_c": s.q_sensor_c, "trap_air_temp_c": s.q_trap_c}
        q_state.update({n: s.q_sensor_c for n in model.delay_states})
        q = [q_state[n] for n in names] + [s.q_mix_offset_c, s.q_flow_offset_m3s, s.q_inlet_c]
        self.Q = np.diag(np.square(q))
        self.R_diag = np.square([s.r_supply_c, s.r_flow_m3s, s.r_water_c, s.r_inlet_c, s.r_heater_outlet_c])
        self.use = np.array([True, True, True, True, s.use_heater_outlet])
        self._build()
        self.z: np.ndarray | None = None
        self.P: np.ndarray | None = None

    def _d(self, z, setpoint):
        x = z[:self.nx]
        target = x[self.i_water] if self.hold_water else setpoint
        return ca.vertcat(z[self.nx + 2], target, z[self.nx], z[self.nx + 1])

    def _build(self) -> None:
        m, nx = self.model, self.nx
        z = ca.SX.sym("z", self.nz)
        u = ca.SX.sym("u", len(m.inputs))
        sp = ca.SX.sym("setpoint")
        # the model parameters are an input (HvacModel.p_default order): generated code of these
        # functions serves every parameter set of one model structure (docs/architecture.md)
        p = ca.SX.sym("p", len(m.p_default))
        self.p = np.array(m.p_default, float)
        d = self._d(z, sp)
        x = z[:nx]
        xk = rk4(m.ode, x, u, d, p, self.dt_s, 2)
        zn = ca.vertcat(xk, z[nx:])
        y = m.output(x, u, d, p)
        meas = ca.vertcat(x[self.i_sensor], y[m.outputs.index("volume_flow_m3s")], x[self.i_water], z[nx + 2],
                          y[m.outputs.index("heater_outlet_temp_c")])
        self.f_p = ca.Function("ekf_f", [z, u, sp, p], [zn, ca.jacobian(zn, z)])
        self.h_p = ca.Function("ekf_h", [z, u, sp, p], [meas, ca.jacobian(meas, z)])
        self.f = BufferedFunction(self.f_p)
        self.h = BufferedFunction(self.h_p)
        self.predict_fn = self._predict_function()
        self.update_fn = self._update_function()
        self.use_functions(self.predict_fn, self.update_fn)

    def _predict_function(self) -> ca.Function:
        """(z, P, u, setpoint, p, Q) -> (z+, P+): the time update of :meth:`predict` as one function."""
        nz = self.nz
        z, P = ca.SX.sym("z", nz), ca.SX.sym("P", nz, nz)
        u, sp = ca.SX.sym("u", len(self.model.inputs)), ca.SX.sym("setpoint")
        p, Q = ca.SX.sym("p", len(self.p)), ca.SX.sym("Q", nz, nz)
        zn, F = self.f_p(z, u, sp, p)
        return ca.Function("ekf_predict", [z, P, u, sp, p, Q], [zn, ca.mtimes([F, P, F.T]) + Q],
                           ["z", "P", "u", "setpoint", "p", "Q"], ["z_next", "P_next"])

    def _update_function(self) -> ca.Function:
        """(z, P, y, ok, u, setpoint, p, R) -> (z+, P+): the measurement update of :meth:`update`
        (Joseph form) with the readings where ``ok`` is 1. A reading left out has its row of H and
        its innovation zeroed and a unit variance, so it adds an uncoupled identity block to S and
        a zero column to K: the same update as with the used readings alone."""
        nz, nm = self.nz, len(MEASURED)
        z, P = ca.SX.sym("z", nz), ca.SX.sym("P", nz, nz)
        y, ok = ca.SX.sym("y", nm), ca.SX.sym("ok", nm)
        u, sp = ca.SX.sym("u", len(self.model.inputs)), ca.SX.sym("setpoint")
        p, R = ca.SX.sym("p", len(self.p)), ca.SX.sym("R", nm)
        hz, H = self.h_p(z, u, sp, p)
        H = ca.diag(ok) @ H
        innov = ok * (y - hz)
        Rm = ca.diag(ok * R + (1 - ok))
        S = H @ P @ H.T + Rm
        K = ca.solve(S, H @ P).T
        IKH = ca.DM.eye(nz) - K @ H
        Pn = IKH @ P @ IKH.T + K @ ca.diag(ok * R) @ K.T
        return ca.Function("ekf_update", [z, P, y, ok, u, sp, p, R], [z + K @ innov, 0.5 * (Pn + Pn.T)],
                           ["z", "P", "y", "ok", "u", "setpoint", "p", "R"], ["z_next", "P_next"])

    # ------------------------------------------------------------------ interface
    @property
    def initialised(self) -> bool:
        return self.z is not None

    def reset(self) -> None:
        self.z = None
        self.P = None

    def initialise(self, measurement: Measurement, u: np.ndarray, setpoint_c: float) -> None:
        """Start at the model's rest state for the current command, matched to the first readings."""
        m = self.model
        inlet = _finite(measurement.hvac_inlet_temp_c, 25.0)
        water = _finite(measurement.water_temp_c, setpoint_c)
        target = water if self.hold_water else setpoint_c
        d = m.d_vector(inlet, target)
        try:
            x = m.steady_state(u, d)
            if not np.all(np.isfinite(x)):
                raise ValueError("non-finite rest state")
        except Exception:  # noqa: BLE001 - fall back to a plain guess, the filter converges from it
            x = np.full(self.nx, inlet)
            x[m.states.index("motor_rise_c")] = 0.5
        x[self.i_water] = water
        y = m.outputs.dict(m.y(x, u, d))
        supply = _finite(measurement.supply_temp_c, y["supply_temp_c"])
        flow = _finite(measurement.volume_flow_m3s, y["volume_flow_m3s"])
        mix = supply - y["supply_air_temp_c"]
        x[self.i_sensor] = supply
        for n in m.delay_states:
            x[m.states.index(n)] = supply
        self.z = np.concatenate([x, [mix, flow - y["volume_flow_m3s"], inlet]])
        p0 = {"motor_rise_c": 0.5, "water_temp_c": 0.2, "heater_temp_c": 5.0, "supply_sensor_c": 0.1,
              "trap_air_temp_c": 5.0}
        p0.update({n: 0.1 for n in m.delay_states})
        sd = [p0[n] for n in m.states.names] + [0.5, 2e-3, 0.1]
        self.P = np.diag(np.square(sd))

    def use_functions(self, predict_fn, update_fn) -> None:
        """Evaluate the time and measurement updates with these functions (the same signatures as
        ``predict_fn`` / ``update_fn``, e.g. generated C of them, :mod:`hvac_mpc.mpc.codegen`).
        ``p``, ``Q`` and ``R_diag`` are read here, once: call again after changing them."""
        self._predict = BufferedFunction(predict_fn, fixed={4: self.p, 5: self.Q})
        self._update = BufferedFunction(update_fn, fixed={6: self.p, 7: self.R_diag})

    def predict(self, u: np.ndarray, setpoint_c: float) -> None:
        """Time update over one sample with the command that was applied."""
        zn, Pt = self._predict(self.z, self.P, u, setpoint_c)
        self.z, self.P = zn, Pt.T  # buffers are column-major

    def readings(self, measurement: Measurement) -> tuple[np.ndarray, np.ndarray]:
        """The measured values (order ``MEASURED``, 0 where unused) and which are used (finite and enabled)."""
        values = np.array([_finite(getattr(measurement, n, None), np.nan) for n in MEASURED])
        ok = np.isfinite(values) & self.use
        return np.where(ok, values, 0.0), ok

    def update(self, measurement: Measurement, u: np.ndarray, setpoint_c: float) -> int:
        """Measurement update with the finite readings; returns how many were used."""
        values, ok = self.readings(measurement)
        if not ok.any():
            return 0
        zn, Pt = self._update(self.z, self.P, values, ok, u, setpoint_c)
        self.z, self.P = zn, Pt.T
        return int(ok.sum())

    # ------------------------------------------------------------------ views
    @property
    def x(self) -> np.ndarray:
        return self.z[:self.nx]

    @property
    def mix_offset_c(self) -> float:
        return float(self.z[self.nx])

    @property
    def flow_offset_m3s(self) -> float:
        return float(self.z[self.nx + 1])

    @property
    def inlet_temp_c(self) -> float:
        return float(self.z[self.nx + 2])

    def healthy(self) -> bool:
        return self.z is not None and bool(np.isfinite(self.z).all() and np.isfinite(self.P).all())


def _finite(value, default: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return default
    return v if np.isfinite(v) else default
