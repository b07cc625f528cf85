"""Multi-level real-time iteration: steps that keep the QP's matrices and renew only its vectors.

A full preparation of the real-time iteration linearises every stage at the shifted plan (the dynamics
Jacobians ``[A_k B_k]`` and the outputs' Jacobians ``G_k``, the Gauss-Newton Hessian from them) and hands
OSQP new matrices, which it equilibrates and factorises again. A *vector step* (level B of the multi-level
iteration: new residuals, old sensitivities; H. G. Bock, M. Diehl, E. Kostina, J. P. Schloeder, "Constrained
optimal feedback control of systems governed by large differential algebraic equations", 2007; acados'
AS-RTI level B) keeps the matrices of the last full linearisation, made at ``z_f``, and evaluates only the
stage values at the new point ``z``: the dynamics rows ``x_k+1 - [A_k B_k]_f z_k = f(z_k) - [A_k B_k]_f z_k``
(the defects at the new point, the old slopes), the residuals' constant parts ``r(z_k) - G_k,f z_k`` for the
gradient and the flow floor's lower bounds with the floor's old slopes. OSQP then gets ``q``, ``l``, ``u``
only: no equilibration, no refactorisation, and the generated call evaluates no Jacobian.

At a fixed point of vector steps the dynamics hold exactly (the defects are the model's); the gradient uses
the old ``G``, so the answer is that of a QP with slopes that are ``|z - z_f|`` old. :class:`MultiLevel`
therefore asks for a full linearisation every ``every`` preparations and whenever the point has moved from
``z_f`` by more than ``move`` in any scaled state or input (or a disturbance estimate by more than
:data:`D_MOVE`); the solver (:class:`~.rti_osqp.RtiOsqpSolver`) adds the other occasions (a reference
change, a change of the weights, a cold start or a reset after a fallback, a change of the heater
readiness's stages).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hvac_mpc.models.box import DISTURBANCES

from .ocp import TrackingProblem

#: Largest change of each disturbance estimate since the full linearisation for a vector step: inlet and
#: chiller set-point temperatures and the mixed-air offset 0.5 degC, the flow offset 0.5 L/s. ASSUMPTION:
#: the Jacobians move little within these (the disturbances enter the model's lags almost linearly).
D_MOVE = np.array([{"flow_offset_m3s": 5e-4}.get(n, 0.5) for n in DISTURBANCES])


class MultiLevel:
    """When a preparation may be a vector step, and what the last full linearisation left for it.

    Args:
        every: a full linearisation at least on every this many preparations (1: on each, the plain
            real-time iteration; then this class is not used).
        move: largest change of a scaled state or input of any stage since the full linearisation for a
            vector step (the scaled variables span about 1-2).
    """

    def __init__(self, every: int, move: float):
        if isinstance(every, bool) or int(every) != every or every < 2:
            raise ValueError(f"MultiLevel: every = {every!r}, allowed: an integer >= 2")
        if not 0.0 < float(move) <= 10.0:
            raise ValueError(f"MultiLevel: move = {move!r}, allowed: (0, 10] (scaled units)")
        self.every, self.move = int(every), float(move)
        self.full: dict | None = None
        self.since_full = 0
        self.counts = {"full": 0, "vector": 0, "moved": 0}

    def forget(self) -> None:
        """No full linearisation to keep (a reset): the next preparation is a full one."""
        self.full = None

    def record_full(self, X: np.ndarray, U: np.ndarray, d: np.ndarray, ab: np.ndarray, g: np.ndarray,
                    ready: np.ndarray | None) -> None:
        """A full linearisation at ``(X, U, d)`` with the stages' ``-[A B]`` (row major) and ``G`` (column
        major) as the QP data return them, and the heater readiness's weights per stage (None: off)."""
        self.full = dict(X=X.copy(), U=U.copy(), d=np.array(d, float), ab=ab.copy(), g=g.copy(),
                         ready=None if ready is None else ready.copy())
        self.since_full = 0
        self.counts["full"] += 1

    def due(self) -> bool:
        """True when the next preparation must be a full one whatever the point (none kept, or the interval)."""
        return self.full is None or self.since_full + 1 >= self.every

    def keeps(self, X: np.ndarray, U: np.ndarray, d: np.ndarray, ready: np.ndarray | None) -> bool:
        """True when a vector step at ``(X, U, d)`` with the readiness weights ``ready`` may keep the full
        linearisation's matrices (one is kept): within ``move`` and :data:`D_MOVE` of it, the same readiness stages.
        ``counts["moved"]`` counts the points that were not."""
        f = self.full
        same_ready = (ready is None) == (f["ready"] is None) and (ready is None or np.array_equal(ready, f["ready"]))
        near = (same_ready and not (np.abs(np.asarray(d, float) - f["d"]) > D_MOVE).any()
                and float(np.abs(X - f["X"]).max()) <= self.move and float(np.abs(U - f["U"]).max()) <= self.move)
        if not near:
            self.counts["moved"] += 1
        return near

    def vector_step(self) -> None:
        self.since_full += 1
        self.counts["vector"] += 1


def vector_function(pb: TrackingProblem, nr: int, y_power: int, y_flow: int, u_blower: int) -> ca.Function:
    """``hvac_qp_vectors(X, U, d, p, AB, G, uh) -> (e_dyn, c_base, y, floor_l)``: the QP's vectors at the new point
    ``(X, U)`` with the slopes of the full linearisation (``AB``: the stages' ``-[A B]`` row major, N columns;
    ``G``: the residuals' Jacobians column major, N + 1 columns; ``uh``: the scaled heater commands the flow
    floor was linearised at), the outputs as ``hvac_qp_data`` has them. Evaluates the stages' values only."""
    N, nx, nu = pb.N, pb.nx, pb.nu
    nz = nx + nu
    X, U, d = ca.MX.sym("X", nx, N + 1), ca.MX.sym("U", nu, N), ca.MX.sym("d", pb.nd)
    p = ca.MX.sym("p", len(pb.model.p_default))
    AB, G = ca.MX.sym("AB", nx * nz, N), ca.MX.sym("G", nr * nz, N + 1)
    n_f = N if pb.floor else 0
    uh = ca.MX.sym("uh", n_f)
    stages = {n: _stage_vector_function(pb, n, nr, y_power, u_blower) for n in sorted(set(pb.stage_substeps))}
    Ue = ca.horzcat(U, U[:, N - 1])
    ABe = ca.horzcat(AB, ca.DM.zeros(nx * nz, 1))  # the terminal stage's dynamics are not used
    dt = np.append(pb.dt, pb.dt[-1])
    parts = [stages[n].map(b - a, "serial")(X[:, a:b], Ue[:, a:b], d, ca.DM(dt[None, a:b]), p, ABe[:, a:b], G[:, a:b])
             for a, b, n in pb.groups]
    e_dyn = ca.horzcat(*[q[0] for q in parts])[:, :N]
    c_base = ca.horzcat(*[q[1] for q in parts])
    y = ca.horzcat(*[q[2] for q in parts])
    floor_l = ca.MX(0, 1)
    if n_f:  # the floor's lower bounds at the new heater commands, the slopes in A those at ``uh``
        heater_u = U[pb.i_heater_cmd, :n_f].T
        value, _ = pb.floor_linearisation(heater_u)
        _, slope = pb.floor_linearisation(uh)
        floor_l = pb.floor_scale * (value - slope * heater_u - c_base[y_flow, :n_f].T)
    return ca.Function("hvac_qp_vectors", [X, U, d, p, AB, G, uh], [ca.vec(e_dyn), c_base, y, floor_l],
                       ["X", "U", "d", "p", "AB", "G", "uh"], ["e_dyn", "c_base", "y", "floor_l"])


def _stage_vector_function(pb: TrackingProblem, substeps: int, nr: int, y_power: int, u_blower: int) -> ca.Function:
    """One stage's vectors: the defect ``x_next - [A B]_f z`` and the residual's constant part ``r - G_f z``
    (``r``: the stage outputs and the electric power row, as :meth:`~.rti_osqp.RtiOsqpSolver._stage_qp_function`
    has them), and the outputs."""
    nx, nu = pb.nx, pb.nu
    nz = nx + nu
    x, u, d, dt = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("d", pb.nd), ca.SX.sym("dt")
    p = ca.SX.sym("p", len(pb.model.p_default))
    ab, g = ca.SX.sym("ab", nx * nz), ca.SX.sym("g", nr * nz)
    xn, y = pb.stage_values_function(substeps)(x, u, d, dt, p)
    y_e = y[y_power] + u[u_blower] * pb.u_sc[u_blower] + pb.u_off[u_blower]
    z = ca.vertcat(x, u)
    minus_ab = ca.reshape(ab, nz, nx).T  # -[A B], stored row major
    e = xn + ca.mtimes(minus_ab, z)
    c = ca.vertcat(y, y_e) - ca.mtimes(ca.reshape(g, nr, nz), z)
    return ca.Function(f"qp_vectors{substeps}", [x, u, d, dt, p, ab, g], [e, c, y])
