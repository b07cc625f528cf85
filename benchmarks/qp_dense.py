"""The RTI's QPs condensed and solved by a dual active-set solver (DAQP), against OSQP as the controller runs it.

    python -m hvac_mpc.benchmarks.qp_dense [--steps 240] [--seed 1] [--blocks 1,1,1,2,2,3,5,10] [--json FILE]

The QPs the solve-time loop (:mod:`.solve_time`, default :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`)
hands OSQP are recorded (the CSC values of P and A, q, l, u, the primal warm start, OSQP's answer), then
replayed in order, one QP of each route in turn (which goes first alternates):

* ``osqp``: one OSQP workspace set up like the controller's, per QP the matrix update (equilibration and
  refactorisation), the vectors, the primal warm start (the duals those of the last QP) and the solve;
* ``daqp``: the QP condensed (the states eliminated through the dynamics rows, :func:`condense`), solved
  by DAQP hot-started from the active set of the QP before (``daqp_cold``: from an empty one);
* ``qpoases``: the same condensed QP solved by qpOASES (CasADi's plugin, dense, hot-started from its
  last QP);
* ``daqp_blocked`` (``--blocks``): the condensed QP with the inputs held over blocks of stages
  (:func:`block`), a smaller and different QP; ``--cost-seeds`` runs the loop with that QP (solved by
  OSQP, :func:`loop_cost`) against the default one for its closed-loop cost.

Times are the CPU time of the thread (``time.thread_time``) of the solver calls alone. The condensing
runs in numpy and is not counted: DAQP's times are a lower bound on the condensed route's (it
would add the condensing in generated C). Reported: median, 95th and 99th percentile and the largest
time per QP, the iterations, the objective of the sparse QP at each answer (OSQP's minus the
condensed route's: positive where OSQP stopped above the optimum) and the largest difference of the
scaled variables. Needs ``daqp`` (``pip install daqp``, the ``qp-dense`` extra).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import osqp
import scipy.sparse as sp

from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver, _OsqpCore

from . import solve_time

#: DAQP's sense flags of a constraint (its documentation): active, at the lower bound.
ACTIVE, LOWER = 1, 2
#: Bounds at or beyond this are no bounds (OSQP's infinity, and DAQP's).
INFINITE = 1e30


def load_daqp():
    """The ``daqp`` module, or ImportError saying how to install it."""
    try:
        import daqp
    except ImportError:
        raise ImportError("the condensed QP benchmark needs DAQP: pip install daqp "
                          "(or the extra: pip install 'hvac-mpc[qp-dense]')") from None
    return daqp


@dataclass
class Layout:
    """Where the parts of the RTI's sparse QP are (:class:`RtiOsqpSolver`): the variables
    ``[x_0 .. x_N, u_0 .. u_N-1, s_1 .. s_N]``, the rows of the initial state and the dynamics first,
    the input-bound and slack-bound rows (simple bounds), the sparsity of P (upper triangle) and A."""

    N: int
    nx: int
    nu: int
    n_eq: int
    bound_rows: np.ndarray
    P_pattern: tuple
    A_pattern: tuple
    settings: dict

    @classmethod
    def of(cls, s: RtiOsqpSolver) -> "Layout":
        n_eq = s.pb.nx * (s.pb.N + 1)
        # the dynamics rows follow the initial-state rows, and the variables x_0..x_N come first
        assert np.array_equal(np.concatenate([s.r_x0, s.r_dyn.ravel()]), np.arange(n_eq)), "layout changed"
        return cls(s.pb.N, s.pb.nx, s.pb.nu, n_eq, np.concatenate([s.r_u.ravel(), s.r_slack]),
                   (s.P.indices, s.P.indptr, s.P.shape), (s.A.indices, s.A.indptr, s.A.shape),
                   dict(s._osqp_settings))

    def P(self, Px: np.ndarray) -> np.ndarray:
        """P as a dense symmetric matrix (OSQP stores its upper triangle)."""
        P = sp.csc_matrix((Px, *self.P_pattern[:2]), shape=self.P_pattern[2]).toarray()
        return P + np.triu(P, 1).T

    def A(self, Ax: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((Ax, *self.A_pattern[:2]), shape=self.A_pattern[2])


@dataclass
class DenseQp:
    """A condensed QP in DAQP's form: min 0.5 w'Hw + f'w, ``lower <= [w; C w] <= upper`` (the first
    ``H.shape[0]`` rows simple bounds), and the map back to the sparse QP's variables ``z = T w + t``."""

    H: np.ndarray
    f: np.ndarray
    C: np.ndarray
    upper: np.ndarray
    lower: np.ndarray
    T: np.ndarray
    t: np.ndarray


def condense(qp: dict, lay: Layout) -> DenseQp:
    """Eliminate the states: the initial-state and dynamics rows (``l = u``) give ``x = Tx w + tx`` for the
    inputs and slacks ``w``; the other rows become simple bounds on ``w`` (input and slack bounds, in
    the order of ``w``) and general rows ``C w``, all of them (a row without a finite bound stays, so that
    the rows are the same from one QP to the next and an active set carries over)."""
    A = lay.A(qp["Ax"])
    n_x = lay.n_eq
    eq = A[:n_x]
    ex, ew = eq[:, :n_x].toarray(), eq[:, n_x:].toarray()  # ex: unit lower triangular
    b = qp["l"][:n_x]
    n_w = ew.shape[1]
    T = np.vstack([-np.linalg.solve(ex, ew), np.eye(n_w)])
    t = np.concatenate([np.linalg.solve(ex, b), np.zeros(n_w)])
    P = lay.P(qp["Px"])
    H = T.T @ P @ T
    f = T.T @ (P @ t + qp["q"])
    rows = np.setdiff1d(np.arange(n_x, A.shape[0]), lay.bound_rows)
    G = A[rows].toarray()
    C, shift = G @ T, G @ t
    lo, up = qp["l"][rows] - shift, qp["u"][rows] - shift
    lower = np.concatenate([qp["l"][lay.bound_rows], lo])
    upper = np.concatenate([qp["u"][lay.bound_rows], up])
    return DenseQp(0.5 * (H + H.T), f, C, np.minimum(upper, INFINITE), np.maximum(lower, -INFINITE), T, t)


def block(d: DenseQp, lay: Layout, blocks: list[int]) -> DenseQp:
    """The condensed QP with each input held over ``blocks`` consecutive stages (summing to N; slacks per
    stage): ``w = E v``; a block's input bounds are the tightest of its stages', general rows that
    become empty are dropped (the rate rows inside a block, whose bounds hold zero)."""
    N, nu = lay.N, lay.nu
    if sum(blocks) != N or min(blocks) < 1:
        raise ValueError(f"blocks = {blocks} must be positive and sum to the horizon {N}")
    stage_block = np.repeat(np.arange(len(blocks)), blocks)
    Eu = np.kron(np.eye(len(blocks))[stage_block], np.eye(nu))
    E = np.block([[Eu, np.zeros((N * nu, N))], [np.zeros((N, Eu.shape[1])), np.eye(N)]])
    lo_u = d.lower[:N * nu].reshape(N, nu)
    up_u = d.upper[:N * nu].reshape(N, nu)
    lo_b = np.array([lo_u[stage_block == j].max(axis=0) for j in range(len(blocks))]).ravel()
    up_b = np.array([up_u[stage_block == j].min(axis=0) for j in range(len(blocks))]).ravel()
    n_w = d.H.shape[0]
    C = d.C @ E
    keep = np.abs(C).sum(axis=1) > 1e-12
    lower = np.concatenate([lo_b, d.lower[N * nu:n_w], d.lower[n_w:][keep]])
    upper = np.concatenate([up_b, d.upper[N * nu:n_w], d.upper[n_w:][keep]])
    return DenseQp(E.T @ d.H @ E, E.T @ d.f, C[keep], upper, lower, d.T @ E, d.t)


class Recording:
    """Stands in for the RTI's OSQP calls (``RtiOsqpSolver._core``) and keeps each QP it is handed."""

    def __init__(self, core):
        self.core = core
        self.qps: list[dict] = []
        self._current: dict = {}

    def update_matrices(self, Px, Ax) -> None:
        self._current.update(Px=np.array(Px), Ax=np.array(Ax))
        self.core.update_matrices(Px, Ax)

    def update_vectors(self, q, l, u) -> None:
        self._current.update(q=np.array(q), l=np.array(l), u=np.array(u))
        self.core.update_vectors(q, l, u)

    def warm_start(self, x, y=None) -> None:
        self._current["warm"] = np.array(x)
        self.core.warm_start(x, y)

    def __getattr__(self, name):  # the calls it does not record (the time limit) go through
        return getattr(self.core, name)

    def solve(self):
        status_val, status, n_iter, x = self.core.solve()
        self.qps.append({**self._current, "status": int(status_val), "iterations": int(n_iter), "x": np.array(x)})
        return status_val, status, n_iter, x


def record(steps: int, seed: int, settings: MpcSettings | None = None) -> tuple[list[dict], Layout, float]:
    """The QPs of ``steps`` steps of the solve-time loop (seed ``seed``, the controller's ``settings``,
    default :class:`MpcSettings`), the QP's layout and the loop's cost."""
    ctrl = MpcController(settings=settings or MpcSettings())
    loop = solve_time.Loop(ctrl, seed)
    solver = ctrl.solver
    rec = Recording(solver._core)
    solver._core = rec
    for k in range(steps):
        loop.step(k)
        if solver._core is not rec:  # OSQP set up anew (a reset): record on
            rec.core, solver._core = solver._core, rec
    return rec.qps, Layout.of(solver), float(sum(loop.cost.values()))


def loop_cost(steps: int, seed: int, blocks: list[int] | None = None) -> float:
    """The solve-time loop's closed-loop cost with the default controller, or with its inputs held over
    ``blocks`` (the blocked route's QP, solved by OSQP: the rate rows of the stages inside a block
    bounded to zero, so that an input moves only at the first stage of a block)."""
    ctrl = MpcController(settings=MpcSettings())
    s = ctrl.solver
    if blocks:
        starts = set(np.cumsum([0] + blocks[:-1]).tolist())
        for k in range(1, s.pb.N):
            if k not in starts:  # the row of u_k - u_k-1; the bounds of these rows are constant
                s.l[s.r_rate[k - 1]] = s.u[s.r_rate[k - 1]] = 0.0
    loop = solve_time.Loop(ctrl, seed)
    for k in range(steps):
        loop.step(k)
    return float(sum(loop.cost.values()))


def objective(qp: dict, lay: Layout, z: np.ndarray) -> float:
    return float(0.5 * z @ lay.P(qp["Px"]) @ z + qp["q"] @ z)


class OsqpReplay:
    """One OSQP workspace handed the recorded QPs in order through the controller's own calls (``_OsqpCore``)."""

    def __init__(self, qps: list[dict], lay: Layout):
        first = qps[0]
        self.solver = osqp.OSQP()
        P = sp.csc_matrix((first["Px"], *lay.P_pattern[:2]), shape=lay.P_pattern[2])  # explicit zeros kept
        self.solver.setup(P, first["q"], lay.A(first["Ax"]),
                          first["l"], first["u"], **lay.settings)
        self.core = _OsqpCore(self.solver)

    def solve(self, qp: dict) -> tuple[float, int, np.ndarray]:
        t0 = time.thread_time()
        self.core.update_matrices(qp["Px"], qp["Ax"])
        self.core.update_vectors(qp["q"], qp["l"], qp["u"])
        self.core.warm_start(qp["warm"])
        _, _, iterations, x = self.core.solve()
        elapsed = time.thread_time() - t0
        return elapsed, int(iterations), np.array(x)


class DaqpRoute:
    """DAQP on condensed QPs, hot-started from the last QP's active set (``hot``) or from none."""

    def __init__(self, hot: bool = True):
        self.daqp = load_daqp()
        self.hot = hot
        self.sense: np.ndarray | None = None

    def solve(self, d: DenseQp) -> tuple[float, int, np.ndarray, int]:
        """Thread CPU time (s), iterations, the sparse QP's variables and the changes of the active set."""
        m = d.upper.size
        start = self.sense if self.hot and self.sense is not None and self.sense.size == m else np.zeros(m, np.int32)
        t0 = time.thread_time()
        w, _, flag, info = self.daqp.solve(d.H, d.f, d.C, d.upper, d.lower, start)
        elapsed = time.thread_time() - t0
        if flag != 1:
            raise RuntimeError(f"DAQP exit flag {flag}")
        lam = np.asarray(info["lam"])
        self.sense = ((lam != 0) * (ACTIVE + LOWER * (lam < 0))).astype(np.int32)
        changes = int(np.count_nonzero((start & ACTIVE) != (self.sense & ACTIVE)))
        return elapsed, int(info["iterations"]), d.T @ w + d.t, changes


class QpoasesRoute:
    """qpOASES (CasADi's ``conic`` plugin, dense) on condensed QPs: from the second call on the plugin
    hot-starts from the last QP's active set and factorisation."""

    def __init__(self, first: DenseQp):
        import casadi as ca

        n_w, m = first.H.shape[0], first.C.shape[0]
        self.n_w = n_w
        self.solver = ca.conic("qp_dense_qpoases", "qpoases", {"h": ca.Sparsity.dense(n_w, n_w),
                                                               "a": ca.Sparsity.dense(m, n_w)},
                               {"printLevel": "none", "sparse": False, "error_on_fail": False})

    def solve(self, d: DenseQp) -> tuple[float, int, np.ndarray, int]:
        n = self.n_w
        t0 = time.thread_time()
        r = self.solver(h=d.H, g=d.f, a=d.C, lbx=d.lower[:n], ubx=d.upper[:n], lba=d.lower[n:], uba=d.upper[n:])
        elapsed = time.thread_time() - t0
        stats = self.solver.stats()
        if not stats["success"]:
            raise RuntimeError(f"qpOASES: {stats['return_status']}")
        return elapsed, int(stats.get("iter_count", -1)), d.T @ np.array(r["x"]).ravel() + d.t, -1


def _stats(values) -> dict[str, float]:
    v = np.asarray(values, float)
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "p99": float(np.percentile(v, 99)),
            "max": float(v.max())}


def replay(qps: list[dict], lay: Layout, blocks: list[int] | None) -> dict[str, Any]:
    """The recorded QPs through every route, one QP of each route in turn; per route the statistics."""
    routes: dict[str, Any] = {"osqp": OsqpReplay(qps, lay), "daqp": DaqpRoute(), "daqp_cold": DaqpRoute(hot=False),
                              "qpoases": QpoasesRoute(condense(qps[0], lay))}
    if blocks:
        routes["daqp_blocked"] = DaqpRoute()
    rows: dict[str, list] = {name: [] for name in routes}
    names = list(routes)
    for i, qp in enumerate(qps):
        dense = condense(qp, lay)
        problems = {"osqp": qp, "daqp": dense, "daqp_cold": dense, "qpoases": dense}
        if blocks:
            problems["daqp_blocked"] = block(dense, lay, blocks)
        for name in (names if i % 2 == 0 else names[::-1]):
            out = routes[name].solve(problems[name])
            rows[name].append((out[0] * 1e3, out[1], objective(qp, lay, out[2]), out[2], *out[3:]))
    result: dict[str, Any] = {}
    z_osqp = [r[3] for r in rows["osqp"]]
    f_osqp = np.array([r[2] for r in rows["osqp"]])
    for name, r in rows.items():
        result[name] = {"time_ms": _stats([x[0] for x in r]), "iterations": _stats([x[1] for x in r]),
                        "total_iterations": int(sum(x[1] for x in r))}
        if name != "osqp":
            result[name]["osqp_objective_minus_this"] = _stats(f_osqp - np.array([x[2] for x in r]))
            result[name]["largest_difference"] = _stats([np.abs(x[3] - z).max() for x, z in zip(r, z_osqp)])
            result[name]["active_set_changes"] = _stats([x[4] for x in r])
            result[name]["median_ratio"] = result[name]["time_ms"]["median"] / result["osqp"]["time_ms"]["median"]
            result[name]["p99_ratio"] = result[name]["time_ms"]["p99"] / result["osqp"]["time_ms"]["p99"]
    return result


def replay_arguments(description: str) -> argparse.ArgumentParser:
    """The options of a benchmark that records the loop's QPs and replays them: steps, seed, rounds."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--steps", type=int, default=solve_time.FULL_STEPS, help="closed-loop steps recorded")
    p.add_argument("--seed", type=int, default=1, help="plant noise seed (default 1)")
    p.add_argument("--rounds", type=int, default=2, help="replays of the recorded QPs (default 2)")
    return p


def main(argv: list[str] | None = None) -> int:
    p = replay_arguments(__doc__.splitlines()[0])
    p.add_argument("--blocks", default="1,1,1,2,2,3,5,10",
                   help="stages per input block of the blocked route, summing to the horizon ('' for none)")
    p.add_argument("--cost-seeds", default="",
                   help="also the closed-loop cost with and without the blocks on these seeds, e.g. 1,2,3")
    p.add_argument("--json", type=Path, default=None, help="write the results here (JSON)")
    args = p.parse_args(argv)
    if args.steps < 3 or args.rounds < 1:
        print("qp_dense: --steps must be at least 3 and --rounds at least 1")
        return 2
    try:
        load_daqp()
        blocks = [int(b) for b in args.blocks.split(",")] if args.blocks else None
    except (ImportError, ValueError) as exc:
        print(f"qp_dense: {exc}")
        return 2
    qps, lay, cost = record(args.steps, args.seed)
    if blocks and (sum(blocks) != lay.N or min(blocks) < 1):
        print(f"qp_dense: --blocks {args.blocks} must be positive and sum to the horizon {lay.N}")
        return 2
    rounds = [replay(qps, lay, blocks) for _ in range(args.rounds)]
    print(f"{len(qps)} QPs recorded in {args.steps} steps (seed {args.seed}, closed-loop cost {cost:.2f})")
    for i, r in enumerate(rounds, 1):
        for name, v in r.items():
            t, it = v["time_ms"], v["iterations"]
            line = (f"round {i} {name:13s} thread CPU median {t['median']:.3f} p95 {t['p95']:.3f} p99 {t['p99']:.3f} "
                    f"max {t['max']:.3f} ms, iterations median {it['median']:.0f} max {it['max']:.0f}")
            if name != "osqp":
                line += (f" ({v['median_ratio']:.2f}x / {v['p99_ratio']:.2f}x OSQP's median / p99), objective OSQP "
                         f"minus this median {v['osqp_objective_minus_this']['median']:.3g}, largest difference "
                         f"median {v['largest_difference']['median']:.3g}")
            print(line)
    costs = {}
    for seed in [int(c) for c in args.cost_seeds.split(",") if c] if blocks else []:
        costs[seed] = {"default": loop_cost(args.steps, seed), "blocked": loop_cost(args.steps, seed, blocks)}
        print(f"closed-loop cost seed {seed}: default {costs[seed]['default']:.1f}, inputs blocked "
              f"{costs[seed]['blocked']:.1f}")
    if args.json is not None:
        args.json.write_text(json.dumps({"steps": args.steps, "seed": args.seed, "blocks": blocks, "qps": len(qps),
                                         "cost": cost, "rounds": rounds, "costs": costs}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
