"""Real-time iteration (RTI) for the tracking problem: multiple shooting, Gauss-Newton, OSQP.

The QP lives in absolute scaled variables ``z = [x_0 .. x_N, u_0 .. u_N-1, s_1 .. s_N]``. Its
sparsity is fixed at construction; every step only values change:

* **preparation** (:meth:`RtiOsqpSolver.prepare`, before the next measurement): shift the last
  solution one sample along the non-uniform stage grid, linearise all stages at it with one
  mapped CasADi call, write the new values into ``P`` (Gauss-Newton Hessian of the least-squares
  residuals) and ``A`` (dynamics Jacobians) with ``OSQP.update(Px=..., Ax=...)`` (one numeric
  refactorisation), and the dynamics right-hand sides into ``l``/``u``;
* **feedback** (:meth:`RtiOsqpSolver.feedback`, when the estimate arrives): insert the estimated
  state, the input bounds and the reference / disturbance-estimate changes into ``q``, ``l``,
  ``u`` (no refactorisation) and solve, warm-started from the shifted trajectory.

With ``sqp_max_iter > 1`` the feedback re-linearises at the new iterate and solves again until
the step is below ``sqp_tol`` (a Gauss-Newton SQP to a tolerance).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import osqp
import scipy.sparse as sp

from .ocp import TrackingProblem, shift_maps


@dataclass
class SolveResult:
    """A solver's answer for one step (scaled trajectories) and its statistics."""

    ok: bool
    status: str
    X: np.ndarray | None = None
    U: np.ndarray | None = None
    S: np.ndarray | None = None
    iterations: int = 0
    qp_solves: int = 0
    prep_time_s: float = 0.0
    feedback_time_s: float = 0.0
    extra: dict = field(default_factory=dict)


class SparsePattern:
    """Collects (row, col) entries, fixes a CSC pattern, and assembles values into it.

    Entries may repeat (their values add). ``add`` returns entry ids; ``finalise`` fixes the
    pattern (CSC order); ``assemble`` sums values per CSC slot with one ``bincount``; ``matrix``
    builds the CSC matrix once (placeholder values keep explicit zeros in the pattern).
    """

    def __init__(self, shape: tuple[int, int]):
        self.shape = shape
        self._rows: list[np.ndarray] = []
        self._cols: list[np.ndarray] = []
        self._count = 0

    def add(self, rows, cols) -> np.ndarray:
        rows, cols = np.broadcast_arrays(np.asarray(rows, np.int64), np.asarray(cols, np.int64))
        ids = np.arange(self._count, self._count + rows.size).reshape(rows.shape)
        self._rows.append(rows.ravel())
        self._cols.append(cols.ravel())
        self._count += rows.size
        return ids

    def finalise(self) -> None:
        rows = np.concatenate(self._rows)
        cols = np.concatenate(self._cols)
        n_rows, n_cols = self.shape
        keys = cols * n_rows + rows  # CSC order: by column, then row
        uniq, inverse = np.unique(keys, return_inverse=True)
        self.slot = inverse  # entry id -> position in CSC data
        self.nnz = uniq.size
        self.indices = (uniq % n_rows).astype(np.int32)
        counts = np.bincount(uniq // n_rows, minlength=n_cols)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)

    def assemble(self, entry_ids: np.ndarray, values: np.ndarray) -> np.ndarray:
        return np.bincount(self.slot[entry_ids.ravel()], weights=values.ravel(), minlength=self.nnz)

    def matrix(self, data: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((data, self.indices, self.indptr), shape=self.shape)


class RtiOsqpSolver:
    """RTI / Gauss-Newton SQP on :class:`TrackingProblem` with OSQP set up once.

    Args:
        problem: the shared OCP data.
        eps: OSQP absolute and relative tolerance.
        max_iter: OSQP iteration cap per QP.
        sqp_max_iter: QPs per step (1 = real-time iteration).
        sqp_tol: SQP stops when the largest change of a scaled variable is below this.
        check_termination: OSQP checks convergence every this many iterations.
        lm_inputs: Levenberg-Marquardt weight on the inputs' step from the linearisation point.
        cold_start_qps: QPs allowed (Gauss-Newton SQP to ``sqp_tol``) on a cold start, when there
            is no previous solution to start from (first step, after a reset or a failure).
        reference_change_qps: QPs allowed on a step whose reference differs from the one the
            preparation used: the shifted plan was made for the old reference, so one damped
            Gauss-Newton step from it is far from the new optimum.
    """

    def __init__(self, problem: TrackingProblem, *, eps: float = 1e-4, max_iter: int = 400,
                 sqp_max_iter: int = 1, sqp_tol: float = 1e-3, check_termination: int = 5,
                 lm_inputs: np.ndarray | float = 0.0, cold_start_qps: int = 1, reference_change_qps: int = 1):
        self.pb = pb = problem
        self.name = "rti" if sqp_max_iter == 1 else "sqp"
        self.lm = np.broadcast_to(np.asarray(lm_inputs, float), (pb.nu,)).copy()
        self.sqp_max_iter = int(sqp_max_iter)
        self.cold_start_qps = int(cold_start_qps)
        self.reference_change_qps = int(reference_change_qps)
        self.sqp_tol = float(sqp_tol)
        N, nx, nu = pb.N, pb.nx, pb.nu
        self.nz_stage = nx + nu
        self.n = (N + 1) * nx + N * nu + N
        self.iu0 = (N + 1) * nx
        self.is0 = self.iu0 + N * nu
        self._lm_all = np.tile(self.lm, N)
        self._build_pattern()
        self._i0, self._w1, self._j = shift_maps(pb.t_nodes, pb.dt_s)
        self.fail_next = 0  # steps to fail on purpose (tests of the fallback chain)
        self._osqp_settings = dict(eps_abs=eps, eps_rel=eps, max_iter=int(max_iter), polishing=False,
                                   warm_starting=True, adaptive_rho=True, verbose=False,
                                   check_termination=int(check_termination), scaling=10)
        self._setup_osqp()
        self.reset()

    # ------------------------------------------------------------------ structure
    def _build_pattern(self) -> None:
        pb, N, nx, nu = self.pb, self.pb.N, self.pb.nx, self.pb.nu
        n, nzs = self.n, self.nz_stage
        # stage column indices: x_k then u_k (terminal stage N uses u_{N-1})
        cols = np.empty((N + 1, nzs), np.int64)
        for k in range(N + 1):
            cols[k, :nx] = k * nx + np.arange(nx)
            cols[k, nx:] = self.iu0 + min(k, N - 1) * nu + np.arange(nu)
        self.stage_cols = cols
        iu = np.triu_indices(nzs)
        self._triu = iu
        P = SparsePattern((n, n))
        self._P_var = P.add(cols[:, iu[0]], cols[:, iu[1]])  # (N+1, ntriu)
        # constant part: move suppression and slack L2
        const_r, const_c, const_v = [], [], []
        for k in range(N):
            base = self.iu0 + k * nu + np.arange(nu)
            mult = 2.0 if k < N - 1 else 1.0
            const_r.append(base), const_c.append(base), const_v.append(2.0 * pb.w_du * mult)
            if k > 0:
                const_r.append(base - nu), const_c.append(base), const_v.append(-2.0 * pb.w_du)
        # Levenberg-Marquardt term lm * |u_k - u_k_lin|^2 (damped Gauss-Newton steps)
        u_all = self.iu0 + np.arange(N * nu)
        const_r.append(u_all), const_c.append(u_all), const_v.append(2.0 * np.tile(self.lm, N))
        s_idx = self.is0 + np.arange(N)
        const_r.append(s_idx), const_c.append(s_idx), const_v.append(2.0 * pb.slack_l2 * pb.dt)
        self._P_const_ids = P.add(np.concatenate(const_r), np.concatenate(const_c))
        self._P_const_vals = np.concatenate(const_v)
        P.finalise()
        self.P = P
        self._P_const = P.assemble(self._P_const_ids, self._P_const_vals)

        # constraints
        rows = 0
        A = SparsePattern((0, n))
        entries_const = []
        self.r_x0 = np.arange(nx)
        entries_const.append((self.r_x0, np.arange(nx), np.ones(nx)))
        rows = nx
        self.r_dyn = rows + np.arange(N * nx).reshape(N, nx)
        rows += N * nx
        dyn_r = np.repeat(self.r_dyn[:, :, None], nx + nu, axis=2)  # (N, nx, nx+nu)
        dyn_c = np.broadcast_to(cols[:N, None, :], (N, nx, nx + nu))
        for k in range(N):
            entries_const.append((self.r_dyn[k], (k + 1) * nx + np.arange(nx), np.ones(nx)))
        self.r_u = rows + np.arange(N * nu).reshape(N, nu)
        rows += N * nu
        for k in range(N):
            entries_const.append((self.r_u[k], self.iu0 + k * nu + np.arange(nu), np.ones(nu)))
        self.r_rate = rows + np.arange((N - 1) * nu).reshape(N - 1, nu)
        rows += (N - 1) * nu
        for k in range(1, N):
            entries_const.append((self.r_rate[k - 1], self.iu0 + k * nu + np.arange(nu), np.ones(nu)))
            entries_const.append((self.r_rate[k - 1], self.iu0 + (k - 1) * nu + np.arange(nu), -np.ones(nu)))
        self.r_soft = rows + np.arange(N)
        rows += N
        entries_const.append((self.r_soft, np.arange(1, N + 1) * nx + pb.i_heater, np.full(N, pb.heater_row_coef)))
        entries_const.append((self.r_soft, self.is0 + np.arange(N), -np.ones(N)))
        self.r_slack = rows + np.arange(N)
        rows += N
        entries_const.append((self.r_slack, self.is0 + np.arange(N), np.ones(N)))
        # PTC limit, stages 1..N-1: coef_u u_k + x_sc T_h,k - s_k <= bound (degC, shares the heater slack)
        self.r_ptc = rows + np.arange(N - 1 if pb.ptc_limit else 0)
        if pb.ptc_limit:
            rows += N - 1
            k = np.arange(1, N)
            entries_const.append((self.r_ptc, k * nx + pb.i_heater, np.full(N - 1, pb.heater_row_coef)))
            entries_const.append((self.r_ptc, self.iu0 + k * nu + pb.i_heater_cmd, np.full(N - 1, pb.ptc_row_coef_u)))
            entries_const.append((self.r_ptc, self.is0 + k - 1, -np.ones(N - 1)))
        self.m = rows
        A.shape = (rows, n)
        self._A_var = A.add(dyn_r, dyn_c)  # values -[A_k B_k]
        c_ids = [A.add(r, c) for r, c, _ in entries_const]
        A.finalise()
        self.A = A
        self._A_const = A.assemble(np.concatenate([i.ravel() for i in c_ids]),
                                   np.concatenate([v for _, _, v in entries_const]))
        self._A_var_slots = A.slot[self._A_var.ravel()]

        # constant bounds
        self.l = np.zeros(rows)
        self.u = np.zeros(rows)
        rb = pb.rate_bounds()
        self.l[self.r_rate] = -rb
        self.u[self.r_rate] = rb
        self.l[self.r_soft] = -np.inf
        self.u[self.r_soft] = pb.heater_row_bound
        self.l[self.r_slack] = 0.0
        self.u[self.r_slack] = np.inf
        self.l[self.r_ptc] = -np.inf
        self.u[self.r_ptc] = pb.ptc_row_bound
        self.l[self.r_u] = pb.u_lo
        self.u[self.r_u] = pb.u_hi
        # q scatter for the per-stage gradient blocks
        self._q_const = np.zeros(n)
        self._q_const[self.is0:] = pb.slack_l1 * pb.dt

    def _setup_osqp(self) -> None:
        pb = self.pb
        # a plausible trajectory so that the placeholder values are representative for scaling
        x0 = pb.scale_x(pb.placeholder_state())
        u0 = pb.scale_u(np.array([150.0, 0.0, 60.0, 100.0, 100.0, 100.0]))
        d = np.array([25.0, 5.0, 0.0, 0.0])
        X = np.tile(x0, (pb.N + 1, 1))
        U = np.tile(u0, (pb.N, 1))
        w_y = pb.w_y_full
        Px, Ax, _ = self._matrices(X, U, d, w_y)
        self.solver = osqp.OSQP()
        self.solver.setup(self.P.matrix(Px), np.zeros(self.n), self.A.matrix(Ax), self.l.copy(), self.u.copy(),
                          **self._osqp_settings)

    # ------------------------------------------------------------------ numerics
    def _matrices(self, X, U, d, w_y):
        """Linearise at (X, U) and return P and A data plus the stage data for q and l/u."""
        pb, N = self.pb, self.pb.N
        Ue = np.vstack([U, U[-1:]])
        lin = pb.linearise(X, Ue, d)
        G = np.concatenate([lin["C"], lin["D"]], axis=2)  # (N+1, ny, nz)
        # energy residual (P_blower + P_heater_el) / 100 W as one more least-squares row
        g_e = G[:, 5, :].copy()
        g_e[:, pb.nx:] += pb.energy_grad_u
        y_e = lin["y"][:, 5] + Ue[:, 0] * pb.u_sc[0] + pb.u_off[0]
        G = np.concatenate([G, g_e[:, None, :]], axis=1)  # (N+1, ny+1, nz)
        y = np.concatenate([lin["y"], y_e[:, None]], axis=1)
        stage_w = np.append(pb.dt, pb.terminal_s)
        sw = np.empty((N + 1, pb.ny + 1))
        sw[:, :pb.ny] = stage_w[:, None] * (w_y / pb.y_scale ** 2)[None, :]
        sw[:, pb.ny] = np.append(pb.dt, 0.0) * pb.energy_weight / pb.energy_scale_w ** 2
        Gw2 = 2.0 * G * sw[:, :, None]
        H = np.einsum("kiy,kiz->kyz", G, Gw2)
        Px = self._P_const + self.P.assemble(self._P_var, H[:, self._triu[0], self._triu[1]])
        AB = np.concatenate([lin["A"][:N], lin["B"][:N]], axis=2)  # (N, nx, nz)
        Ax = self._A_const.copy()
        Ax[self._A_var_slots] = -AB.ravel()
        Z = np.concatenate([X, Ue], axis=1)  # stage linearisation points (N+1, nz)
        e_dyn = lin["xn"][:N] - np.einsum("kij,kj->ki", AB, Z[:N])
        c_base = y - np.einsum("kiz,kz->ki", G, Z)
        data = dict(Gw2=Gw2, c_base=c_base, e_dyn=e_dyn, y=lin["y"])
        return Px, Ax, data

    def _scatter_q(self, blocks: np.ndarray) -> np.ndarray:
        return np.bincount(self.stage_cols.ravel(), weights=blocks.ravel(), minlength=self.n)

    def reset(self) -> None:
        """Forget the trajectory (cold start at the next step)."""
        self.X = self.U = self.S = None
        self._prepared = None

    @property
    def has_trajectory(self) -> bool:
        return self.X is not None

    def _shifted(self, x_first: np.ndarray):
        w1 = self._w1[:, None]
        X = self.X[self._i0] * (1.0 - w1) + self.X[np.minimum(self._i0 + 1, self.pb.N)] * w1
        X[0] = x_first
        U = self.U[self._j]
        S = self.S[np.minimum(self._j, self.pb.N - 1)]
        return X, U, S

    def _load(self, X, U, S, d, ref, w_y, u_prev) -> None:
        """Write the linearisation at (X, U) into OSQP (values only)."""
        Px, Ax, data = self._matrices(X, U, d, w_y)
        self.solver.update(Px=Px, Ax=Ax)
        self.l[self.r_dyn] = data["e_dyn"]
        self.u[self.r_dyn] = data["e_dyn"]
        q_lin = self._q_const.copy()
        self._prepared = dict(data=data, d=d.copy(), w_y=w_y.copy(), q_lin=q_lin, ref=np.array(ref, float))
        self._z_lin = np.concatenate([X.ravel(), U.ravel(), S])

    def prepare(self, x_pred: np.ndarray, u_prev: np.ndarray, d: np.ndarray, ref: np.ndarray,
                w_y: np.ndarray) -> float:
        """Preparation phase: shift, linearise, refactorise. Returns its wall time (s).

        ``x_pred`` is the estimator's prediction of the next state and ``u_prev`` the command just
        applied: the first stage is linearised at the actuators' actual position (the shifted plan
        may have planned other values there), the later stages at the shifted plan.
        """
        t0 = time.perf_counter()
        if self.X is None:
            self._initialise(x_pred, u_prev, d)
        else:
            self.X, self.U, self.S = self._shifted(x_pred)
            self.U[0] = u_prev
        self._load(self.X, self.U, self.S, d, ref, w_y, u_prev)
        return time.perf_counter() - t0

    def _initialise(self, x0, u_prev, d) -> None:
        pb = self.pb
        self.X = pb.rollout(x0, u_prev, d)
        self.U = np.tile(u_prev, (pb.N, 1))
        self.S = np.zeros(pb.N)

    def feedback(self, x0: np.ndarray, u_prev: np.ndarray, d: np.ndarray, ref: np.ndarray, w_y: np.ndarray,
                 u_lo: np.ndarray, u_hi: np.ndarray, time_limit_s: float = 0.0) -> SolveResult:
        """Feedback phase: insert the estimate and bounds, solve (and iterate in SQP mode)."""
        t0 = time.perf_counter()
        prep = 0.0
        cold = self.X is None
        max_qps = max(self.sqp_max_iter, self.cold_start_qps) if cold else self.sqp_max_iter
        if self._prepared is not None and not np.array_equal(self._prepared["ref"], ref):
            max_qps = max(max_qps, self.reference_change_qps)
        if self._prepared is None or not np.array_equal(self._prepared["w_y"], w_y):
            prep = self.prepare(x0, u_prev, d, ref, w_y)
        if self.fail_next > 0:
            self.fail_next -= 1
            return SolveResult(False, "forced failure", prep_time_s=prep,
                               feedback_time_s=time.perf_counter() - t0 - prep)
        N, nx, nu = self.pb.N, self.pb.nx, self.pb.nu
        self.l[self.r_x0] = x0
        self.u[self.r_x0] = x0
        self.l[self.r_u] = u_lo
        self.u[self.r_u] = u_hi
        iterations = 0
        solves = 0
        status = "unsolved"
        z = None
        for it in range(max_qps):
            if it > 0:
                prep += self._relinearise(z, x0, d, ref, w_y, u_prev)
            q = self._q(ref, d, u_prev)
            self.solver.update(q=q, l=self.l, u=self.u)
            self.solver.warm_start(x=self._z_lin)
            if time_limit_s > 0:
                remaining = time_limit_s - (time.perf_counter() - t0)
                if remaining <= 0:
                    status = "deadline"
                    break
                self.solver.update_settings(time_limit=remaining)
            res = self.solver.solve(raise_error=False)
            solves += 1
            iterations += int(res.info.iter)
            status = str(res.info.status)
            if res.info.status_val not in (1, 2):  # solved, solved inaccurate
                z = None
                break
            z = np.array(res.x)
            if not np.all(np.isfinite(z)):
                status = "non-finite solution"
                z = None
                break
            step = float(np.max(np.abs(z - self._z_lin)))
            if step < self.sqp_tol:
                break
        feedback = time.perf_counter() - t0 - prep
        if z is None:
            return SolveResult(False, status, iterations=iterations, qp_solves=solves, prep_time_s=prep,
                               feedback_time_s=feedback, extra={"cold_start": cold})
        X = z[:(N + 1) * nx].reshape(N + 1, nx)
        U = z[self.iu0:self.is0].reshape(N, nu)
        S = z[self.is0:]
        self.X, self.U, self.S = X, U, S
        return SolveResult(True, status, X=X.copy(), U=U.copy(), S=S.copy(), iterations=iterations,
                           qp_solves=solves, prep_time_s=prep, feedback_time_s=feedback,
                           extra={"cold_start": cold})

    def _relinearise(self, z, x0, d, ref, w_y, u_prev) -> float:
        t0 = time.perf_counter()
        N, nx, nu = self.pb.N, self.pb.nx, self.pb.nu
        X = z[:(N + 1) * nx].reshape(N + 1, nx).copy()
        X[0] = x0
        U = z[self.iu0:self.is0].reshape(N, nu)
        S = z[self.is0:]
        self._load(X, U, S, d, ref, w_y, u_prev)
        return time.perf_counter() - t0

    def _q(self, ref: np.ndarray, d: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Gradient for the current reference, disturbance estimates and last input."""
        pr = self._prepared
        data = pr["data"]
        c = data["c_base"].copy()
        c[:, :self.pb.ny] -= ref[None, :]
        # disturbance estimates that moved since preparation enter the outputs additively:
        # the mixed-air offset adds to the supply temperature, the flow offset to the total
        # flow and, in proportion, to each outlet
        d_mix = d[2] - pr["d"][2]
        d_flow = d[3] - pr["d"][3]
        if d_mix or d_flow:
            c[:, 0] += (1.0 - self.pb.spec.temperature_sensor_share) * d_mix
            y = data["y"]
            c[:, 1] += d_flow
            c[:, 2:5] += d_flow * y[:, 2:5] / np.maximum(y[:, 1:2], 1e-6)
        blocks = np.einsum("kiz,ki->kz", data["Gw2"], c)
        q = pr["q_lin"] + self._scatter_q(blocks)
        q[self.iu0:self.is0] -= 2.0 * self._lm_all * self._z_lin[self.iu0:self.is0]
        q[self.iu0:self.iu0 + self.pb.nu] -= 2.0 * self.pb.w_du * u_prev
        return q
