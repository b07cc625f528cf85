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

Dead time (``EkfSettings.dead_time_max_s``): the thermocouple may see the mixed air later than
the model says (a transport delay the parameters do not name). The filter keeps the last
``dead_time_max_s`` samples of the model's undelayed thermocouple state as states of its own
(a shift register: each is a copy of the one before), and compares the reading with the entry
of the estimated dead time, which :class:`~.dead_time.DeadTimeEstimator` picks online from the
same readings, once it reaches ``dead_time_min_s``. The model states, and so the MPC's
prediction, stay undelayed: the controller
steers the response it will see a dead time later (a Smith predictor in state-space form), and
the mixed-air offset integrates only what the delayed comparison leaves, not the delay itself.
With an estimate of 0 the filter is the plain one. docs/robustness.md sec. 2.

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
from .dead_time import DeadTimeEstimator
from .ocp import InvalidSettings, check_number

#: Process noise of the history entries (degC per sample): exact copies, a floor for the numerics.
HIST_Q_C = 1e-4
#: Measurement names in the order of the filter's measurement vector.
MEASURED = ("supply_temp_c", "volume_flow_m3s", "water_temp_c", "hvac_inlet_temp_c", "heater_outlet_temp_c")


@dataclass(frozen=True)
class EkfSettings:
    """Noise levels of the filter (1 sigma; process noise per sample of 1 s). ASSUMPTIONS tuned on
    the simulated plant; measurement noise matches the plant's sensor-noise parameters.

    ``use_heater_outlet`` uses the heater outlet thermocouple when the measurement carries it.
    ``dead_time_max_s``: longest dead time of the thermocouple beyond the model's that the filter
    estimates and honours (s, whole samples; 0 turns the dead-time handling off);
    ``dead_time_window_s``: the estimate's window (forgetting time, s); ``dead_time_excitation_c``:
    the least root mean square change per sample of the predicted reading over the window for the
    estimate to move (degC); ``dead_time_min_s``: the shortest estimate the measurement model honours (below it
    the thermocouple state's process noise absorbs the delay, as in the plain filter: honouring
    1 s made the 1 s delay's proband sequence worse, 0.91 -> 1.00 of the baseline's IAE). Module
    docstring; ASSUMPTIONS tuned on the independent simulator's variants.
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
    dead_time_max_s: float = 6.0
    dead_time_window_s: float = 60.0
    dead_time_excitation_c: float = 0.05
    dead_time_min_s: float = 1.5

    def validate(self, prefix: str = "ekf") -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "use_heater_outlet":
                if not isinstance(value, bool):
                    raise InvalidSettings(f"{prefix}.use_heater_outlet must be True or False")
                continue
            if f.name in ("dead_time_max_s", "dead_time_min_s"):
                check_number(f"{prefix}.{f.name}", value, 0.0, 30.0)
                continue
            check_number(f"{prefix}.{f.name}", value, 0.0, 100.0 if f.name != "dead_time_window_s" else 3600.0,
                         lo_open=True)


class DisturbanceEkf:
    """EKF for the HVAC box; ``predict(u)`` after applying a command, ``update(measurement)`` on arrival."""

    def __init__(self, model: HvacModel, settings: EkfSettings | None = None, dt_s: float = 1.0,
                 water_prediction: str = "hold"):
        self.model = model
        self.settings = s = settings or EkfSettings()
        self.dt_s = float(dt_s)
        self.hold_water = water_prediction == "hold"
        self.nx = len(model.states)
        self.nc = self.nx + 3  # model states and disturbance states
        self.n_hist = int(round(s.dead_time_max_s / self.dt_s))
        self.nz = self.nc + self.n_hist  # ... and the history of the undelayed thermocouple state
        names = model.states.names
        self.i_water = names.index("water_temp_c")
        self.i_sensor = names.index("supply_sensor_c")
        q_state = {"motor_rise_c": s.q_motor_c, "water_temp_c": s.q_water_c, "heater_temp_c": s.q_heater_c,
                   "supply_sensor_c": s.q_sensor_c, "trap_air_temp_c": s.q_trap_c}
        q_state.update({n: s.q_sensor_c for n in model.delay_states})
        q = [q_state[n] for n in names] + [s.q_mix_offset_c, s.q_flow_offset_m3s, s.q_inlet_c]
        q += [HIST_Q_C] * self.n_hist
        self.Q = np.diag(np.square(q))
        self.dead_time = DeadTimeEstimator(self.n_hist, model.params.tau_tc_s, self.dt_s, s.dead_time_window_s,
                                           s.dead_time_excitation_c)
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
        z = ca.SX.sym("z", self.nc)
        u = ca.SX.sym("u", len(m.inputs))
        sp = ca.SX.sym("setpoint")
        p = ca.DM(m.p_default)
        d = self._d(z, sp)
        x = z[:nx]
        xk = rk4(m.ode, x, u, d, p, self.dt_s, 2)
        zn = ca.vertcat(xk, z[nx:])
        y = m.output(x, u, d, p)
        meas = ca.vertcat(x[self.i_sensor], y[m.outputs.index("volume_flow_m3s")], x[self.i_water], z[nx + 2],
                          y[m.outputs.index("heater_outlet_temp_c")])
        self.f = BufferedFunction(ca.Function("ekf_f", [z, u, sp], [zn, ca.jacobian(zn, z)]))
        self.h = BufferedFunction(ca.Function("ekf_h", [z, u, sp], [meas, ca.jacobian(meas, z)]))
        # the model's air at the thermocouple (after the model's own transport delay, if its parameters
        # set one) without the offset state, for the dead time beyond the model's
        air = y[m.outputs.index("duct_air_temp_c")] - z[nx]
        self.air = BufferedFunction(ca.Function("ekf_air", [z, u, sp], [air]))

    # ------------------------------------------------------------------ interface
    @property
    def initialised(self) -> bool:
        return self.z is not None

    def reset(self) -> None:
        self.z = None
        self.P = None
        self.dead_time.reset()

    @property
    def dead_time_s(self) -> float:
        """The dead time of the thermocouple beyond the model's that the filter honours now (s)."""
        return self.dead_time.seconds

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
        self.z = np.concatenate([x, [mix, flow - y["volume_flow_m3s"], inlet], np.full(self.n_hist, supply)])
        p0 = {"motor_rise_c": 0.5, "water_temp_c": 0.2, "heater_temp_c": 5.0, "supply_sensor_c": 0.1,
              "trap_air_temp_c": 5.0}
        p0.update({n: 0.1 for n in m.delay_states})
        sd = [p0[n] for n in m.states.names] + [0.5, 2e-3, 0.1] + [0.1] * self.n_hist
        self.P = np.diag(np.square(sd))
        self.dead_time.reset()

    def predict(self, u: np.ndarray, setpoint_c: float) -> None:
        """Time update over one sample with the command that was applied."""
        nc, z = self.nc, self.z
        zn, Ft = self.f(z[:nc], u, setpoint_c)
        F = np.zeros((self.nz, self.nz))
        F[:nc, :nc] = Ft.T  # buffers are column-major
        if self.n_hist:
            # shift register: the newest entry is the thermocouple state now, the others move on
            F[nc, self.i_sensor] = 1.0
            F[nc + 1:, nc:-1] = np.eye(self.n_hist - 1)
            self.dead_time.push_air(float(np.ravel(self.air(z[:nc], u, setpoint_c)[0])[0]))
        self.z = np.concatenate([zn, [z[self.i_sensor]], z[nc:-1]]) if self.n_hist else zn
        self.P = F @ self.P @ F.T + self.Q

    def update(self, measurement: Measurement, u: np.ndarray, setpoint_c: float) -> int:
        """Measurement update with the finite readings; returns how many were used."""
        values = np.array([_finite(getattr(measurement, n, None), np.nan) for n in MEASURED])
        ok = np.isfinite(values) & self.use
        if not ok.any():
            return 0
        nc = self.nc
        hz, Ht = self.h(self.z[:nc], u, setpoint_c)
        H = np.zeros((len(MEASURED), self.nz))
        H[:, :nc] = Ht.T
        if self.n_hist and ok[0]:
            # the reading is the undelayed thermocouple state of the estimated dead time ago
            lag = self.dead_time.observe(values[0])
            if lag * self.dt_s >= self.settings.dead_time_min_s:
                # entry j of the register (0 = now) between the two samples around the dead time
                j0 = int(np.floor(lag))
                w1 = lag - j0
                H[0] = 0.0
                for j, w in ((j0, 1.0 - w1), (min(j0 + 1, self.n_hist), w1)):
                    H[0, self.i_sensor if j == 0 else nc + j - 1] += w
                hz[0] = H[0] @ self.z
        hz = hz[ok]
        H = H[ok]
        innov = values[ok] - hz
        S = H @ self.P @ H.T + np.diag(self.R_diag[ok])
        K = np.linalg.solve(S, H @ self.P).T
        self.z = self.z + K @ innov
        IKH = np.eye(self.nz) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ np.diag(self.R_diag[ok]) @ K.T  # Joseph form
        self.P = 0.5 * (self.P + self.P.T)
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
        return self.z is not None and bool(np.all(np.isfinite(self.z)) and np.all(np.isfinite(self.P)))


def _finite(value, default: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return default
    return v if np.isfinite(v) else default
