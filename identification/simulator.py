"""Whole-log simulation of one model structure: free run, output sensitivities, EKF innovations.

Everything is built once per model structure as CasADi functions of the full parameter vector
``p`` (order :meth:`Parameters.scalar_names`) and run over the log by ``mapaccum`` in calls of
:data:`CHUNK_ROWS` rows:

- free run ``Y = sim(p)`` from the steady state at the first row (the error for reporting and
  for the fit);
- forward sensitivities ``dY/dtheta`` for the parameters being fitted (Gauss-Newton Jacobian);
- one-step innovations of an extended Kalman filter on the same model (for the statistics).

When the log holds ``water_temp_c`` it replaces the chiller state at every step (a measured
disturbance), so the chiller's hysteresis does not enter the residual. When it does not, the chiller's
two-point control (``two_point``, on by default) drives the model's water as in the simulated plant (the
relay and the thesis's rising and falling slopes, effect ``chiller_asymmetry``): the ramp target of every
sample follows the relay (:func:`hvac_mpc.models.chiller.two_point_targets`, recomputed for the rates and
band of each parameter vector) instead of the logged set point, from the water at the first set point with
the compressor on (ASSUMPTION: the plant's start; docs/identification.md, "Logs without the water
temperature").
"""

from __future__ import annotations

import zlib
from types import SimpleNamespace
from typing import Iterable, Sequence

import casadi as ca
import numpy as np

from hvac_mpc.models import chiller, valves
from hvac_mpc.models.box import INPUTS, HvacModel
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.codegen_background import BackgroundBuilds

from .log_data import LogData

#: Free runs a simulator keeps (their parameter vector, outputs and states; about 1 MB each on a 2 h log).
RUNS_KEPT = 4
#: Rows per call of a mapped step function: a run of the log is a chain of calls of the step mapped over this many
#: rows (and one over the rows left), each from the state the last one ended in. The same steps in the same order as
#: one function mapped over the whole log, so the same values to the bit; building a map over 200 rows takes about
#: 1.5 ms against 25-30 ms over 7200, and the identification builds one per model structure and parameter set
#: (docs/identification.md, "Cheaper runs").
CHUNK_ROWS = 200

#: Quantities inside the model exported for the diagnostics (derived regressors).
INTERNALS = ("heater_temp_c", "mass_flow_kgs", "bypass_fraction", "core_mass_flow_kgs", "motor_rise_c",
             "blower_out_temp_c", "cooler_out_temp_c", "heater_out_temp_c", "heater_electric_w",
             "cooler_drive_c", "heater_rise_c", "mix_temp_c")

#: Parameters of the chiller's two-point control (:func:`hvac_mpc.models.chiller.two_point_targets`).
CHILLER_PARAMETERS = ("water_rate_c_per_s", "water_rise_rate_c_per_s", "water_fall_rate_c_per_s", "chiller_band_c")

#: ASSUMPTION: EKF process-noise standard deviations per state and second (tuning, not physics).
PROCESS_NOISE = {"motor_rise_c": 2e-3, "water_temp_c": 2e-3, "heater_temp_c": 0.05, "supply_sensor_c": 0.01,
                 "trap_air_temp_c": 0.05}
#: ASSUMPTION: initial EKF state standard deviations.
INITIAL_STD = {"motor_rise_c": 0.3, "water_temp_c": 0.5, "heater_temp_c": 3.0, "supply_sensor_c": 0.3,
               "trap_air_temp_c": 3.0}


class Simulator:
    """One model structure (effects) over one log; ``outputs`` are the logged outputs to predict."""

    def __init__(self, log: LogData, params: Parameters, effects: Iterable[str], outputs: Sequence[str],
                 terms: tuple = (), two_point: bool = True, builds: BackgroundBuilds | None = None):
        """``two_point``: without a logged water temperature, the model's water follows the chiller's two-point
        control (module docstring); False: it ramps to the logged set point and stays there. ``builds``: the step
        functions run as generated C once built (:mod:`hvac_mpc.mpc.codegen_background`; the same values to the
        bit); None: always in CasADi's interpreter."""
        self.log = log
        self.builds = builds
        self.params = params
        self.two_point = bool(two_point and log.water_temp_c is None)
        # the two-point control as the plant has it (models/plant.py): the relay and the thesis's two water slopes
        self.effects = frozenset(effects) | ({"chiller_asymmetry"} if self.two_point else frozenset())
        self.terms = tuple(terms)
        self.model = HvacModel(params, self.effects, dt_s=log.dt_s, substeps=2, terms=self.terms)
        self.outputs = tuple(outputs)
        self.names = self.model.param_names
        m = self.model
        self.nx, self.nu, self.nd, self.np = len(m.states), len(m.inputs), len(m.disturbances), len(self.names)
        self.ny = len(self.outputs)
        self._y_idx = [m.outputs.index(o) for o in self.outputs]
        self._iw = m.states.index("water_temp_c")
        self._flag = 1.0 if log.water_temp_c is not None else 0.0
        self._i_target = 2 * self.nu + m.disturbances.index("chiller_setpoint_c")
        self._i_chiller = [self.names.index(k) for k in CHILLER_PARAMETERS]
        self._z_cache: tuple[tuple, np.ndarray] | None = None
        n = log.n
        water = log.water_temp_c if log.water_temp_c is not None else np.zeros(n)
        d = np.zeros((n, self.nd))
        d[:, m.disturbances.index("inlet_temp_c")] = log.inlet_temp_c
        d[:, m.disturbances.index("chiller_setpoint_c")] = log.chiller_setpoint_c
        self._d = d
        cabin = log.cabin_temp_c
        self._cabin_flag = 0.0 if cabin is None else 1.0
        cabin = np.zeros(n) if cabin is None else cabin
        self._ic = self.names.index("cabin_temp_c")
        # z_k = [u_k, u_{k-1}, d_k, water_k, flag, cabin_k, cabin flag]
        self.z = np.hstack([log.u, log.u_prev, d, water[:, None], np.full((n, 1), self._flag), cabin[:, None],
                            np.full((n, 1), self._cabin_flag)]).T.copy()
        self.nz = self.z.shape[0]
        self._build()
        self._aug_cache: dict[tuple, ca.Function] = {}
        self._maps: dict[tuple, ca.Function] = {}
        self._internals_map: ca.Function | None = None
        self._f_internals: ca.Function | None = None  # (step function's name, rows): the step mapped over rows
        self._ekf_fn: ca.Function | None = None
        self._runs: list[tuple[bytes, "_Run"]] = []  # the last free runs, newest first

    # ------------------------------------------------------------------ building blocks
    def _sym(self):
        return (ca.SX.sym("x", self.nx), ca.SX.sym("z", self.nz), ca.SX.sym("p", self.np))

    def _split_z(self, z):
        nu, nd = self.nu, self.nd
        return z[:nu], z[nu:2 * nu], z[2 * nu:2 * nu + nd], z[2 * nu + nd], z[2 * nu + nd + 1]

    def z_for(self, p: np.ndarray) -> np.ndarray:
        """The per-row inputs of the mapped functions for parameters ``p``: with ``two_point``, the set-point row
        holds the two-point control's ramp targets for ``p``'s water rates and band (cached per value)."""
        if not self.two_point:
            return self.z
        key = tuple(float(p[i]) for i in self._i_chiller)
        if self._z_cache is None or self._z_cache[0] != key:
            prm = SimpleNamespace(**dict(zip(CHILLER_PARAMETERS, key)))
            sp = self.log.chiller_setpoint_c
            z = self.z.copy()
            z[self._i_target] = chiller.two_point_targets(sp, sp[0], self.log.dt_s, prm,
                                                          asymmetric="chiller_asymmetry" in self.effects)
            self._z_cache = (key, z)
        return self._z_cache[1]

    def _first_row(self, p: np.ndarray) -> np.ndarray:
        """Inputs of the first row for the steady state; with ``two_point`` the water pinned to the first set point."""
        z0 = self.z_for(p)[:, 0].copy()
        if self.two_point:
            z0[2 * self.nu + self.nd] = self.log.chiller_setpoint_c[0]
            z0[2 * self.nu + self.nd + 1] = 1.0
        return z0

    def _params(self, z, p):
        """The parameter vector with the logged cabin temperature in place of ``cabin_temp_c`` (when logged)."""
        e = np.zeros(self.np)
        e[self._ic] = 1.0
        cabin, flag = z[self.nz - 2], z[self.nz - 1]
        return p + ca.DM(e) * (flag * (cabin - p[self._ic]))

    def _override(self, x, z):
        _, _, _, w, flag = self._split_z(z)
        e = np.zeros(self.nx)
        e[self._iw] = 1.0
        return x + ca.DM(e) * (flag * (w - x[self._iw]))

    def _build(self) -> None:
        m = self.model
        x, z, p = self._sym()
        u, up, d, _, _ = self._split_z(z)
        xe = self._override(x, z)
        pz = self._params(z, p)
        x_next = m.step(xe, u, d, pz)
        y_all = m.output(xe, up, d, pz)
        y = ca.vertcat(*[y_all[i] for i in self._y_idx])
        self.f_step = ca.Function("f_step", [x, z, p], [x_next])
        self.f_y = ca.Function("f_y", [x, z, p], [y])
        self.f_step_y = ca.Function("f_step_y", [x, z, p], [x_next, y])
        # steady state at the first row: ode = 0 (water state pinned to the logged value)
        xdot = m.ode(xe, u, d, pz)
        e = np.zeros(self.nx)
        e[self._iw] = 1.0
        _, _, _, w, flag = self._split_z(z)
        g = xdot + ca.DM(e) * (flag * (x[self._iw] - w) - flag * xdot[self._iw])
        self.f_g = ca.Function("f_g", [x, z, p], [g, ca.jacobian(g, x), ca.jacobian(g, p)])

    @property
    def f_internals(self) -> ca.Function:
        """Quantities inside the model (:data:`INTERNALS`) at one row, for the diagnostics and discovery (built on
        first use: most simulators, a discovery's probes among them, never need it)."""
        if self._f_internals is None:
            m = self.model
            x, z, p = self._sym()
            _, up, d, _, _ = self._split_z(z)
            q = m.algebraic(self._override(x, z), up, d, self._params(z, p))
            b = q["bypass"]
            internals = {
                "heater_temp_c": q["sx"]["heater_temp_c"], "mass_flow_kgs": q["mass_flow"], "bypass_fraction": b,
                "core_mass_flow_kgs": (1 - b) * q["mass_flow"], "motor_rise_c": q["sx"]["motor_rise_c"],
                "blower_out_temp_c": q["t_blower"], "cooler_out_temp_c": q["t_cooler"],
                "heater_out_temp_c": q["t_heater_out"], "heater_electric_w": q["p_el"],
                "cooler_drive_c": (1 - b) * (q["t_blower"] - q["t_cooler"]),
                "heater_rise_c": (1 - b) * (q["t_heater_out"] - q["t_cooler"]), "mix_temp_c": q["t_mix"]}
            self._f_internals = ca.Function("f_int", [x, z, p], [ca.vertcat(*[internals[k] for k in INTERNALS])])
        return self._f_internals

    # ------------------------------------------------------------------ steady state
    def initial_state(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Steady state at the first row and its Jacobian with respect to ``p`` (n_x x n_p)."""
        z0 = self._first_row(p)
        log = self.log
        x = np.zeros(self.nx)
        x[self.model.states.index("motor_rise_c")] = 1.0
        x[self._iw] = log.water_temp_c[0] if log.water_temp_c is not None else log.chiller_setpoint_c[0]
        x[self.model.states.index("heater_temp_c")] = log.inlet_temp_c[0] + 20.0
        x[self.model.states.index("supply_sensor_c")] = log.outputs["supply_temp_c"][np.isfinite(
            log.outputs["supply_temp_c"])][0]
        if "trap_air_temp_c" in self.model.states.names:
            x[self.model.states.index("trap_air_temp_c")] = log.inlet_temp_c[0]
        for _ in range(60):
            g, gx, _ = (np.asarray(v) for v in self.f_g(x, z0, p))
            dx = np.linalg.solve(gx, -g.ravel())
            x = x + dx
            if np.max(np.abs(dx)) < 1e-9:
                break
        g, gx, gp = (np.asarray(v) for v in self.f_g(x, z0, p))
        if not np.all(np.isfinite(x)) or np.max(np.abs(g)) > 1e-6:
            x = self._settle_by_simulation(p)
            g, gx, gp = (np.asarray(v) for v in self.f_g(x, z0, p))
        try:
            dx_dp = -np.linalg.solve(gx, gp)
        except np.linalg.LinAlgError:
            dx_dp = np.zeros((self.nx, self.np))
        return x, dx_dp

    def _settle_by_simulation(self, p: np.ndarray) -> np.ndarray:
        x = np.full(self.nx, float(self.log.inlet_temp_c[0]))
        x[self.model.states.index("motor_rise_c")] = 0.0
        z0 = self._first_row(p)
        for _ in range(4000):
            x = np.asarray(self.f_step(x, z0, p)).ravel()
        return x

    # ------------------------------------------------------------------ free run
    def simulate(self, p: np.ndarray, rows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Free-run outputs (n x n_y) and states (n x n_x; state k is the state at row k).

        ``rows``: only the first ``rows`` rows are run (the others NaN): a fit's residual and Jacobian use the
        training rows, the first part of the log, alone. A run of the whole log continues a kept shorter run of the
        same vector from its last state (the same steps in the same order: the same values to the bit).
        The last ``RUNS_KEPT`` runs are kept (copies returned): a fit's final evaluation is at the point of its last
        accepted step, and the next step starts from it, so the same vector is run again and again."""
        n = self.log.n
        rows = n if rows is None else int(min(max(rows, 1), n))
        key = np.asarray(p, dtype=float).tobytes()
        hit = next((run for k, run in self._runs if k == key and run.rows >= rows), None)
        if hit is None:
            part = next((run for k, run in self._runs if k == key), None)
            hit = self._keep(p, self._continue(p, part, rows) if part is not None else self._run(p, rows))
        return hit.rows_of(n, rows)

    def _keep(self, p: np.ndarray, run: "_Run") -> "_Run":
        """``run`` kept as the newest run of ``p`` (unless a longer one of ``p`` is kept)."""
        key = np.asarray(p, dtype=float).tobytes()
        if any(k == key and r.rows > run.rows for k, r in self._runs):
            return run
        self._runs = ([(key, run)] + [(k, r) for k, r in self._runs if k != key])[:RUNS_KEPT]
        return run

    def _mapped(self, fn: ca.Function, step: ca.Function, rows: int) -> ca.Function:
        """``fn`` (a step: state, row inputs, constants -> next state, row outputs) mapped over ``rows`` rows, in the
        form ``step`` (``fn`` itself or its generated C, :attr:`builds`)."""
        key = (id(fn), rows, step is not fn)  # the functions live as long as the simulator: their ids stay theirs
        if key not in self._maps:
            self._maps[key] = step.mapaccum(f"{fn.name()}_{rows}", rows, [0], [0])
        return self._maps[key]

    def _chain(self, fn: ca.Function, x0: np.ndarray, z: np.ndarray, *const, per_row: tuple = ()
               ) -> tuple[np.ndarray, np.ndarray]:
        """``fn(x, z, *const, *per_row)`` run over the columns of ``z`` (and of the arrays ``per_row``, one column
        per row too) from the state ``x0``, in calls of :data:`CHUNK_ROWS` rows: the states after each row and the
        outputs of each row (one column per row)."""
        xs, ys = [], []
        x = x0
        step = fn if self.builds is None else self.builds.function(fn)  # one run: one call asked for
        for k in range(0, z.shape[1], CHUNK_ROWS):
            zk = z[:, k:k + CHUNK_ROWS]
            x_k, y_k = self._mapped(fn, step, zk.shape[1])(x, zk, *const, *(a[:, k:k + CHUNK_ROWS] for a in per_row))
            xs.append(np.asarray(x_k))
            ys.append(np.asarray(y_k))
            x = xs[-1][:, -1]
        return np.hstack(xs), np.hstack(ys)

    def _run(self, p: np.ndarray, rows: int) -> "_Run":
        """The first ``rows`` rows run from the steady state at the first row."""
        x0, _ = self.initial_state(p)
        xs, ys = self._chain(self.f_step_y, x0, self.z_for(p)[:, :rows], p)
        xs = xs.T
        return _Run(ys.T, np.vstack([x0[None, :], xs[:-1]]), xs[-1])

    def _continue(self, p: np.ndarray, part: "_Run", rows: int) -> "_Run":
        """``part`` (a run of the first rows of ``p``) continued to ``rows`` rows from its last state."""
        start = part.rows
        xs, ys = self._chain(self.f_step_y, part.x_end, self.z_for(p)[:, start:rows], p)
        xs = xs.T
        return _Run(np.vstack([part.y, ys.T]), np.vstack([part.states, part.x_end[None, :], xs[:-1]]), xs[-1])

    def _aug(self, idx: tuple[int, ...]) -> ca.Function:
        """The step with the forward sensitivities of the parameters ``idx`` (one step; :meth:`_chain` runs it)."""
        if idx in self._aug_cache:
            return self._aug_cache[idx]
        n_theta = len(idx)
        x, z, p = self._sym()
        s = ca.SX.sym("s", self.nx, n_theta)
        c = ca.SX.sym("c", n_theta)
        x_next, y = self.f_step_y(x, z, p)
        p_sel = ca.vertcat(*[p[i] for i in idx])
        a, bp = ca.jacobian(x_next, x), ca.jacobian(x_next, p_sel)
        cy, dp = ca.jacobian(y, x), ca.jacobian(y, p_sel)
        s_next = ca.mtimes(a, s) + ca.mtimes(bp, ca.diag(c))
        dy = ca.mtimes(cy, s) + ca.mtimes(dp, ca.diag(c))
        # named by the parameters (not by the order they were asked for), so one structure has one name everywhere
        f = ca.Function(f"f_aug_{zlib.crc32(repr(idx).encode()):08x}", [ca.vertcat(x, ca.vec(s)), z, p, c],
                        [ca.vertcat(x_next, ca.vec(s_next)), ca.vertcat(y, ca.vec(dy))])
        self._aug_cache[idx] = f
        return f

    def simulate_with_sensitivity(self, p: np.ndarray, e: np.ndarray, rows: int | None = None
                                  ) -> tuple[np.ndarray, np.ndarray]:
        """Free run and dY/dtheta for p = p(theta) with dp/dtheta = ``e`` (n_p x n_theta).

        Each column of ``e`` must have one non-zero entry (one parameter per theta).
        Returns ``y`` (n x n_y) and ``dy`` (n x n_y x n_theta). ``rows``: only the first ``rows`` rows are run (the
        others NaN; the same values to the bit in those rows).
        """
        n = self.log.n
        rows = n if rows is None else int(min(max(rows, 1), n))
        n_theta = e.shape[1]
        idx = tuple(int(np.flatnonzero(e[:, j])[0]) if np.any(e[:, j]) else 0 for j in range(n_theta))
        scale = np.array([e[i, j] for j, i in enumerate(idx)])
        x0, dx0 = self.initial_state(p)
        s0 = dx0 @ e
        xa0 = np.concatenate([x0, s0.ravel(order="F")])
        xs, out = self._chain(self._aug(idx), xa0, self.z_for(p)[:, :rows], p, scale)
        xs = xs[:self.nx].T
        self._keep(p, _Run(out[:self.ny].T, np.vstack([x0[None, :], xs[:-1]]), xs[-1]))  # its free run
        out = _padded(out.T, n)
        y = out[:, :self.ny]
        dy = out[:, self.ny:].reshape(n, self.ny, n_theta, order="F")
        return y, dy

    def internals(self, p: np.ndarray, states: np.ndarray) -> dict[str, np.ndarray]:
        """Derived regressors along a free run (heater temperature, mass flow, bypass ...)."""
        if self._internals_map is None:
            self._internals_map = self.f_internals.map(self.log.n)
        f = self._internals_map
        vals = np.asarray(f(states.T, self.z_for(p), p)).T
        out = {k: vals[:, i] for i, k in enumerate(INTERNALS)}
        out["network_resistance_kg_m7"] = network_resistance(self.params, self.log.u)
        return out

    # ------------------------------------------------------------------ one-step residuals
    def _ekf(self) -> ca.Function:
        if self._ekf_fn is not None:
            return self._ekf_fn
        nx, ny = self.nx, self.ny
        x, z, p = self._sym()
        pv = ca.SX.sym("P", nx * nx)
        ym, mask, r, q = ca.SX.sym("ym", ny), ca.SX.sym("mask", ny), ca.SX.sym("r", ny), ca.SX.sym("q", nx)
        xs = ca.SX.sym("xs", nx)
        h_jac = ca.Function("h_jac", [xs, z, p], [self.f_y(xs, z, p), ca.jacobian(self.f_y(xs, z, p), xs)])
        f_jac = ca.Function("f_jac", [xs, z, p], [self.f_step(xs, z, p), ca.jacobian(self.f_step(xs, z, p), xs)])
        cov = ca.reshape(pv, nx, nx)
        xk = x
        nus, ss = [], []
        for j in range(ny):
            yh, hh = h_jac(xk, z, p)
            hj = hh[j, :]
            s = ca.mtimes(ca.mtimes(hj, cov), hj.T) + r[j]
            gain = ca.mtimes(cov, hj.T) / s
            nu = (ym[j] - yh[j]) * mask[j]
            xk = xk + gain * nu
            cov = cov - mask[j] * ca.mtimes(gain, ca.mtimes(hj, cov))
            nus.append(nu)
            ss.append(s)
        x_next, a = f_jac(xk, z, p)
        cov = ca.mtimes(ca.mtimes(a, cov), a.T) + ca.diag(q)
        cov = 0.5 * (cov + cov.T)
        self._ekf_fn = ca.Function("ekf", [ca.vertcat(x, pv), z, p, r, q, ym, mask],
                                   [ca.vertcat(x_next, ca.vec(cov)), ca.vertcat(*nus, *ss)])
        return self._ekf_fn

    def innovations(self, p: np.ndarray, y_meas: np.ndarray, r_var: np.ndarray,
                    post: "OutputPost | None" = None, rows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """EKF one-step innovations ``nu`` and their variances ``s`` (both n x n_y; ``rows``: of the first rows
        only, NaN after).

        ``y_meas`` (n x n_y, NaN = missing) is first mapped through ``post`` inverse (output
        delays and offsets are taken off the measurement). ``r_var`` are the measurement-noise
        variances per output.
        """
        names = self.model.states.names
        q = np.array([PROCESS_NOISE[nm] ** 2 for nm in names]) * self.log.dt_s
        if self._flag:
            q[self._iw] = 0.0
        x0, _ = self.initial_state(p)
        p0 = np.diag([INITIAL_STD[nm] ** 2 for nm in names])
        ym = y_meas if post is None else post.undo(y_meas)
        mask = np.isfinite(ym).astype(float)
        ym = np.where(mask > 0, ym, 0.0)
        rows = self.log.n if rows is None else int(min(max(rows, 1), self.log.n))
        _, out = self._chain(self._ekf(), np.concatenate([x0, p0.ravel()]), self.z_for(p)[:, :rows], p,
                             np.asarray(r_var, float), q, per_row=(ym.T[:, :rows], mask.T[:, :rows]))
        out = _padded(out.T, self.log.n)
        nu = out[:, :self.ny]
        s = out[:, self.ny:]
        nu[mask == 0] = np.nan
        return nu, s


class OutputPost:
    """Output-side corrections the state model does not hold: delays (samples), gains and offset+drift.

    Applied in that order: y_o(t) -> gain_o y_o(t - delay_o) + b0 + b1 ramp(t)."""

    def __init__(self, outputs: Sequence[str], time_s: np.ndarray, delays: dict[str, int] | None = None,
                 bias: dict[str, tuple[float, float]] | None = None, gain: dict[str, float] | None = None):
        self.outputs = tuple(outputs)
        self.time_s = time_s
        self.delays = {k: int(v) for k, v in (delays or {}).items() if v}
        self.bias = {k: tuple(v) for k, v in (bias or {}).items()}
        self.gain = {k: float(v) for k, v in (gain or {}).items()}
        span = max(float(time_s[-1] - time_s[0]), 1.0)
        self.ramp = (time_s - time_s[0]) / span - 0.5

    def copy(self) -> "OutputPost":
        return OutputPost(self.outputs, self.time_s, dict(self.delays), dict(self.bias), dict(self.gain))

    def apply(self, y: np.ndarray, dy: np.ndarray | None = None):
        y = y.copy()
        dy = None if dy is None else dy.copy()
        for name, dl in self.delays.items():
            j = self.outputs.index(name)
            y[:, j] = shift(y[:, j], dl)
            if dy is not None:
                dy[:, j, :] = shift(dy[:, j, :], dl)
        for name, g in self.gain.items():
            j = self.outputs.index(name)
            y[:, j] *= g
            if dy is not None:
                dy[:, j, :] *= g
        for name, (b0, b1) in self.bias.items():
            j = self.outputs.index(name)
            y[:, j] += b0 + b1 * self.ramp
        return y if dy is None else (y, dy)

    def undo(self, y_meas: np.ndarray) -> np.ndarray:
        """Measurement mapped back to model time, gain and offset (for one-step filtering)."""
        y = y_meas.copy()
        for name, (b0, b1) in self.bias.items():
            j = self.outputs.index(name)
            y[:, j] -= b0 + b1 * self.ramp
        for name, g in self.gain.items():
            y[:, self.outputs.index(name)] /= g
        for name, dl in self.delays.items():
            j = self.outputs.index(name)
            y[:, j] = np.concatenate([y[dl:, j], np.full(dl, np.nan)])
        return y

    def describe(self) -> dict:
        return {"delays_samples": dict(self.delays), "bias": {k: list(v) for k, v in self.bias.items()},
                "gain": dict(self.gain)}


class _Run:
    """A free run of the first ``rows`` rows: outputs, states (state k at row k) and the state after the last row."""

    def __init__(self, y: np.ndarray, states: np.ndarray, x_end: np.ndarray):
        self.y, self.states, self.x_end = y, states, np.asarray(x_end, float).copy()

    @property
    def rows(self) -> int:
        return self.y.shape[0]

    def rows_of(self, n: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the outputs and states of the first ``rows`` rows, NaN up to ``n`` rows."""
        return _padded(self.y[:rows], n), _padded(self.states[:rows], n)


def _padded(values: np.ndarray, n: int) -> np.ndarray:
    """``values`` (rows first) as a new array of ``n`` rows, the rows it lacks NaN."""
    out = np.full((n,) + values.shape[1:], np.nan)
    out[:values.shape[0]] = values
    return out


def shift(values: np.ndarray, lag: int) -> np.ndarray:
    """Delay an array along axis 0 by ``lag`` samples, holding the first value."""
    if lag <= 0:
        return values
    head = np.repeat(values[:1], lag, axis=0)
    return np.concatenate([head, values[:-lag]], axis=0)


def network_resistance(params: Parameters, u: np.ndarray) -> np.ndarray:
    """Parallel network resistance of valves m, f, w (thesis sec. 5.2 formula) per row, kg/m^7."""
    curves = valves.curves(params)
    angles = valves.shifted_angles([u[:, INPUTS.index(f"valve_{v}_pct")] for v in valves.VALVES], params)
    g = sum(1.0 / np.sqrt(valves.resistance(a, curves[v])) for a, v in zip(angles, valves.VALVES))
    return 1.0 / g ** 2


