"""The RTI's QPs solved by HPIPM (CasADi's bundled ``conic`` plugin, the OCP structure given), against OSQP.

    python -m hvac_mpc.benchmarks.qp_hpipm [--steps 240] [--seed 1] [--mode speed_abs] [--json FILE]

The QPs the solve-time loop hands OSQP are recorded (:func:`hvac_mpc.benchmarks.qp_dense.record`, default
:class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`) and replayed in order, one QP of each route in turn:

* ``osqp``: one OSQP workspace as the controller calls it (:class:`~hvac_mpc.benchmarks.qp_dense.OsqpReplay`:
  matrix update with equilibration and refactorisation, vectors, primal warm start, solve);
* ``hpipm``: the same QP written stage by stage (:class:`StageQp`) and solved by HPIPM's interior point,
  which needs no warm start.

HPIPM's form has every cost term and row within one stage, states ``xi_k`` and controls ``nu_k``. The RTI's
QP (variables ``[x_0..x_N, u_0..u_N-1, s_1..s_N]``) has rows across two stages (the rate rows ``u_k -
u_k-1``, the move cost, the heater rows' slack), so the stages carry copies, as the stage-wise description
does (docs/architecture.md 'The stage-wise description'): ``xi_0 = x_0``, ``xi_k = [x_k, u_k-1, s_k]``,
``nu_k = [u_k, s_k+1]``, the copies tied by the dynamics. Each cost entry and row goes to the first stage
holding all its variables; the answer is read from the first copy of each variable. The same QP: at HPIPM's
answer the objective of the recorded QP is compared with OSQP's.

Times are the thread CPU time (``time.thread_time``) of the solver calls: for HPIPM the ``conic`` call with
its matrices already in CasADi's form, so the conversion is not counted (a lower bound of that route).
Reported per route: median, 95th and 99th percentile and largest time per QP, the iterations, and the same
for the QPs on which OSQP took 100 iterations or more (the reference changes and the steps after them,
docs/architecture.md 'Slow steps').
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    if not os.environ.get(_var, "").isdigit() or int(os.environ[_var]) > 2:
        os.environ[_var] = "2"

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

from . import solve_time  # noqa: E402
from hvac_mpc.mpc.rti_osqp import SparsePattern  # noqa: E402

from . import qp_dense  # noqa: E402
from .qp_dense import Layout, OsqpReplay, objective, record  # noqa: E402

#: OSQP iterations from which a recorded QP counts as a hard one (the tail's).
HARD_ITERATIONS = 100
#: HPIPM's modes (its documentation): ``speed_abs`` stops on absolute tolerances; the relative ones did
#: not converge on a small test problem with unbounded variables.
MODES = ("speed_abs", "speed", "balance", "robust")


class StageQp:
    """The map of the RTI's QP (:class:`Layout`) onto HPIPM's stage-wise form (module docstring)."""

    def __init__(self, lay: Layout):
        N, nx, nu = lay.N, lay.nx, lay.nu
        self.lay, self.N = lay, N
        self.iu0, self.is0 = (N + 1) * nx, (N + 1) * nx + N * nu
        self.n_compact = self.is0 + N
        self.nxs = [nx] + [nx + nu + 1] * N
        self.nus = [nu + 1] * N + [0]
        off_xi, off_nu, o = [], [], 0
        for k in range(N + 1):
            off_xi.append(o)
            o += self.nxs[k]
            off_nu.append(o)
            o += self.nus[k]
        self.n = o
        self.off_xi, self.off_nu = off_xi, off_nu
        # copies of every compact variable: (stage, index in the stage-wise variables), first the primary one
        self.copies: list[list[tuple[int, int]]] = [[] for _ in range(self.n_compact)]
        for k in range(N + 1):
            for i in range(nx):
                self.copies[k * nx + i].append((k, off_xi[k] + i))
        for k in range(N):
            for j in range(nu):
                self.copies[self.iu0 + k * nu + j] += [(k, off_nu[k] + j), (k + 1, off_xi[k + 1] + nx + j)]
            self.copies[self.is0 + k] += [(k, off_nu[k] + nu), (k + 1, off_xi[k + 1] + nx + nu)]
        self.primary = np.array([c[0][1] for c in self.copies])
        self._build(lay)

    def _in_stage(self, variables, stage=None) -> tuple[int, list[int]]:
        """The first stage holding a copy of each of ``variables`` (or ``stage``), and those copies."""
        stages = set.intersection(*({s for s, _ in self.copies[v]} for v in variables))
        if not stages:
            raise ValueError(f"variables {variables} share no stage")
        k = min(stages) if stage is None else stage
        return k, [next(i for s, i in self.copies[v] if s == k) for v in variables]

    def _build(self, lay: Layout) -> None:
        N, nx, nu = lay.N, lay.nx, lay.nu
        # P (upper triangle, CSC) -> H (both triangles)
        P = sp.csc_matrix((np.arange(len(lay.P_pattern[0])) + 1.0, *lay.P_pattern[:2]), shape=lay.P_pattern[2])
        Pc = P.tocoo()
        h_r, h_c, h_src = [], [], []
        for r, c, v in zip(Pc.row, Pc.col, Pc.data.astype(int) - 1):
            if r == c:
                _, (i,) = self._in_stage([int(r)])
                h_r.append(i), h_c.append(i), h_src.append(v)
            else:
                _, (i, j) = self._in_stage([int(r), int(c)])
                h_r += [i, j]
                h_c += [j, i]
                h_src += [v, v]
        self.h_rows, self.h_cols, self.h_src = np.array(h_r), np.array(h_c), np.array(h_src)
        # rows of A by kind
        A = sp.csc_matrix((np.arange(len(lay.A_pattern[0])) + 1.0, *lay.A_pattern[:2]), shape=lay.A_pattern[2]).tocsr()
        bound_rows = set(lay.bound_rows.tolist())
        # a bound row holds one variable: its bounds go to that variable's first copy
        self._bound_w = self.primary[[A.indices[A.indptr[r]] for r in lay.bound_rows]]
        general: dict[int, list[int]] = {k: [] for k in range(N + 1)}
        stage_rows: dict[int, tuple[int, list[int], list[int]]] = {}
        for r in range(nx * (N + 1), A.shape[0]):
            if r in bound_rows:
                continue
            cols = A.indices[A.indptr[r]:A.indptr[r + 1]].tolist()
            k, mapped = self._in_stage(cols)
            general[k].append(r)
            stage_rows[r] = (k, cols, mapped)
        x0_rows = list(range(nx))
        general[0] = x0_rows + general[0]
        for r in x0_rows:
            stage_rows[r] = (0, [r], [self.copies[r][0][1]])
        self.ngs = [len(general[k]) for k in range(N + 1)]
        a_r, a_c, a_src, a_sign = [], [], [], []
        lo_src, row_of = [], []  # per stage-wise row: the compact row of its bounds (-1: a copy row, 0 = 0)
        neg_src = []
        row = 0

        def general_rows(k):
            nonlocal row
            for r in general[k]:
                _, cols, mapped = stage_rows[r]
                for c, m in zip(cols, mapped):
                    a_r.append(row), a_c.append(m), a_sign.append(1.0)
                    a_src.append(self._a_slot(A, r, c))
                lo_src.append(r), neg_src.append(False)
                row += 1

        for k in range(N):
            # gap rows: x_k+1 = A x_k + B u_k + e (compact row: x_k+1 - A x_k - B u_k = e), then the copies
            for i in range(nx):
                r = nx + k * nx + i
                cols = A.indices[A.indptr[r]:A.indptr[r + 1]].tolist()
                for c in cols:
                    if c == (k + 1) * nx + i:
                        a_r.append(row), a_c.append(self.off_xi[k + 1] + i), a_sign.append(-1.0)
                    else:
                        _, (m,) = self._in_stage([c], k)
                        a_r.append(row), a_c.append(m), a_sign.append(-1.0)
                    a_src.append(self._a_slot(A, r, c))
                lo_src.append(r), neg_src.append(True)
                row += 1
            for j in range(nu + 1):
                a_r += [row, row]
                a_c += [self.off_nu[k] + j, self.off_xi[k + 1] + nx + j]
                a_sign += [1.0, -1.0]
                a_src += [-1, -1]
                lo_src.append(-1), neg_src.append(False)
                row += 1
            general_rows(k)
        general_rows(N)
        self.m = row
        self.a_rows, self.a_cols = np.array(a_r), np.array(a_c)
        self.a_src, self.a_sign = np.array(a_src), np.array(a_sign)
        self.lo_src, self.neg_src = np.array(lo_src), np.array(neg_src)
        self._ap = SparsePattern((self.m, self.n))
        self._a_ids = self._ap.add(self.a_rows, self.a_cols)
        self._ap.finalise()
        # H: one dense block per stage (xi_k, nu_k), column-major within the matrix
        blocks = [np.arange(self.off_xi[k], self.off_xi[k] + self.nxs[k] + self.nus[k]) for k in range(N + 1)]
        hr, hc = [], []
        for b in blocks:
            for c in b:
                hr.append(b), hc.append(np.full(b.size, c))
        self._h_r, self._h_c = np.concatenate(hr), np.concatenate(hc)
        counts = np.bincount(self._h_c, minlength=self.n)
        self.h_sp = ca.Sparsity(self.n, self.n, np.concatenate([[0], np.cumsum(counts)]).tolist(), self._h_r.tolist())
        # the move cost's cross term u_k-1 u_k sits in stage k (xi_k.up, nu_k.u): its square's share of
        # u_k-1 moves from nu_k-1 to xi_k.up, so that each stage's block stays positive semidefinite
        self._moves = [(self.off_nu[k - 1] + j, self.off_xi[k] + nx + j, self._p_slot(P, self.iu0 + (k - 1) * nu + j,
                                                                                   self.iu0 + k * nu + j))
                       for k in range(1, N) for j in range(nu)]
        # the terminal block couples x_N and u_N-1 (xi_N.x, xi_N.up): the part of u_N-1's square it needs moves too
        self._term_x = np.arange(self.off_xi[N], self.off_xi[N] + nx)
        self._term_u = np.arange(self.off_xi[N] + nx, self.off_xi[N] + nx + nu)
        self._last_u = np.arange(self.off_nu[N - 1], self.off_nu[N - 1] + nu)
        self.a_sp = ca.Sparsity(self.m, self.n, self._ap.indptr.tolist(), self._ap.indices.tolist())

    @staticmethod
    def _p_slot(P: sp.csc_matrix, r: int, c: int) -> int:
        """The CSC data slot of P's upper-triangle entry (r, c) (P built with slot + 1 as its values)."""
        return int(P[min(r, c), max(r, c)]) - 1

    @staticmethod
    def _a_slot(A: sp.csr_matrix, r: int, c: int) -> int:
        """The CSC data slot of A's entry (r, c) (A built with slot + 1 as its values)."""
        return int(A[r, c]) - 1

    def data(self, qp: dict) -> dict[str, Any]:
        """HPIPM's inputs for a recorded QP (CasADi matrices in the fixed sparsity)."""
        Hd = np.zeros((self.n, self.n))
        np.add.at(Hd, (self.h_rows, self.h_cols), qp["Px"][self.h_src])
        for nu_i, xi_i, slot in self._moves:
            c = -qp["Px"][slot]
            Hd[nu_i, nu_i] -= c
            Hd[xi_i, xi_i] += c
        Q = Hd[np.ix_(self._term_x, self._term_x)]
        S = Hd[np.ix_(self._term_x, self._term_u)]
        M = S.T @ np.linalg.pinv(Q) @ S
        M = 0.5 * (M + M.T) + 1e-9 * np.eye(M.shape[0])
        Hd[np.ix_(self._last_u, self._last_u)] -= M
        Hd[np.ix_(self._term_u, self._term_u)] += M
        H = ca.DM(self.h_sp, Hd[self._h_r, self._h_c])
        a_vals = np.where(self.a_src >= 0, qp["Ax"][np.maximum(self.a_src, 0)], 1.0) * self.a_sign
        A = ca.DM(self.a_sp, self._ap.assemble(self._a_ids, a_vals))
        src = np.maximum(self.lo_src, 0)
        lba = np.where(self.lo_src >= 0, qp["l"][src], 0.0)
        uba = np.where(self.lo_src >= 0, qp["u"][src], 0.0)
        lba, uba = np.where(self.neg_src, -uba, lba), np.where(self.neg_src, -lba, uba)
        g = np.zeros(self.n)
        g[self.primary] = qp["q"]
        lbx, ubx = np.full(self.n, -np.inf), np.full(self.n, np.inf)
        b = self.lay.bound_rows
        lbx[self._bound_w], ubx[self._bound_w] = qp["l"][b], qp["u"][b]
        big = 1e19  # OSQP's infinity stands for none
        lba[lba <= -big], uba[uba >= big] = -np.inf, np.inf
        lbx[lbx <= -big], ubx[ubx >= big] = -np.inf, np.inf
        return {"h": H, "a": A, "g": g, "lba": lba, "uba": uba, "lbx": lbx, "ubx": ubx}

    def compact(self, w: np.ndarray) -> np.ndarray:
        """The RTI's variables from the stage-wise ones (each from its first copy)."""
        return w[self.primary]


class HpipmRoute:
    """HPIPM through CasADi's ``conic`` plugin on :class:`StageQp`'s form (the structure given, no detection)."""

    def __init__(self, st: StageQp, mode: str):
        self.st = st
        opts = {"N": st.N, "nx": st.nxs, "nu": st.nus, "ng": st.ngs, "error_on_fail": False,
                "hpipm": {"mode": mode, "iter_max": 200}}
        self.solver = ca.conic("rti_hpipm", "hpipm", {"h": st.h_sp, "a": st.a_sp}, opts)

    def solve(self, data: dict) -> tuple[float, int, np.ndarray, bool]:
        """Thread CPU time (s) of the call, iterations, the answer in the RTI's variables, converged or not."""
        t0 = time.thread_time()
        r = self.solver(**data)
        elapsed = time.thread_time() - t0
        stats = self.solver.stats()
        return elapsed, int(stats.get("iter_count", -1)), self.st.compact(np.array(r["x"]).ravel()), bool(
            stats["success"])


def _stats(values) -> dict[str, float]:
    """Median, 95th and 99th percentile and largest (:func:`hvac_mpc.benchmarks.qp_dense._stats`); empty for none."""
    return qp_dense._stats(values) if len(values) else {}


def replay(qps: list[dict], lay: Layout, mode: str) -> dict[str, Any]:
    """The recorded QPs through OSQP and HPIPM, one QP of each in turn (which goes first alternates)."""
    st = StageQp(lay)
    osqp_route, hpipm = OsqpReplay(qps, lay), HpipmRoute(st, mode)
    rows = {"osqp": [], "hpipm": []}
    for i, qp in enumerate(qps):
        data = st.data(qp)
        order = ("osqp", "hpipm") if i % 2 == 0 else ("hpipm", "osqp")
        for name in order:
            if name == "osqp":
                t, it, z = osqp_route.solve(qp)
                ok = True
            else:
                t, it, z, ok = hpipm.solve(data)
            rows[name].append((t * 1e3, it, objective(qp, lay, z), ok, np.abs(z - qp["x"]).max()))
    hard = [i for i, qp in enumerate(qps) if qp["iterations"] >= HARD_ITERATIONS]
    out: dict[str, Any] = {"qps": len(qps), "hard_qps": len(hard), "mode": mode}
    for name, r in rows.items():
        out[name] = {"time_ms": _stats([x[0] for x in r]), "iterations": _stats([x[1] for x in r]),
                     "hard_time_ms": _stats([r[i][0] for i in hard]),
                     "hard_iterations": _stats([r[i][1] for i in hard]),
                     "failures": int(sum(not x[3] for x in r))}
    f_o = np.array([x[2] for x in rows["osqp"]])
    f_h = np.array([x[2] for x in rows["hpipm"]])
    out["objective_osqp_minus_hpipm"] = _stats(f_o - f_h)
    out["objective_relative_median"] = float(np.median((f_o - f_h) / np.maximum(np.abs(f_o), 1e-9)))
    out["hpipm_answer_minus_recorded_max"] = _stats([x[4] for x in rows["hpipm"]])
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=solve_time.FULL_STEPS)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--mode", default="speed_abs", choices=MODES, help="HPIPM's mode (default speed_abs)")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    if args.steps < 3:
        p.error("--steps must be at least 3")
    solve_time.pin_cores(2)
    qps, lay, _ = record(args.steps, args.seed)
    out = replay(qps, lay, args.mode)
    for name in ("osqp", "hpipm"):
        r = out[name]
        print(f"{name:<6} all {out['qps']} QPs: thread CPU median {r['time_ms']['median']:.3f} p99 "
              f"{r['time_ms']['p99']:.3f} max {r['time_ms']['max']:.3f} ms, iterations median "
              f"{r['iterations']['median']:.0f} max {r['iterations']['max']:.0f}; the {out['hard_qps']} hard QPs "
              f"(OSQP >= {HARD_ITERATIONS} iterations): median {r['hard_time_ms'].get('median', float('nan')):.3f} "
              f"max {r['hard_time_ms'].get('max', float('nan')):.3f} ms, iterations median "
              f"{r['hard_iterations'].get('median', float('nan')):.0f}; failures {r['failures']}")
    print(f"objective, OSQP's answer minus HPIPM's: median {out['objective_osqp_minus_hpipm']['median']:.2e} "
          f"(relative {out['objective_relative_median']:.2e}), largest "
          f"{out['objective_osqp_minus_hpipm']['max']:.2e}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
