"""Real-time iteration with acados (SQP_RTI, HPIPM on BLASFEO's AVX2 kernels): :class:`RtiAcadosSolver`.

docs/architecture.md, 'Solver comparison', subsection 'acados'. An optional extra: acados is found
under ``$HVAC_MPC_ACADOS_DIR`` (default: the folder ``acados`` of the code cache, :func:`.codegen.cache_dir`),
installed there apart from the project's environment (:data:`INSTALL_COMMAND`; the wheel carries a
CasADi of its own that must not replace the project's). Nothing of it is imported before a solver is built.

The OCP is built from the stage-wise description (:class:`~.stage_ocp.StageOcp`), acados' ``AcadosOcp``:

* **state** ``xa = [x, u_prev, d]``: the description's augmented state with the disturbances as constant
  states (``d_next = d``), so a step sets only the initial state: the disturbance estimates that moved
  since the preparation enter the QP through its Jacobians, as the estimate does;
* **input** ``[u, s]``: the inputs and the stage's slack of the soft rows (heater body, PTC), one slack
  shared by the stage's soft rows as in the description (acados' own slacks would give each row its own);
  ``s >= 0`` by its bounds; the terminal stage's one soft row (heater body) takes acados' slack;
* **dynamics** DISCRETE: the description's ``dynamics`` of the stage's substep count, chosen at run time by a
  stage parameter (a CasADi ``conditional``: only the stage's own variant runs); ``dt`` a stage parameter;
* **cost** NONLINEAR_LS: the description's residual, then ``u`` against the linearisation point (the
  Levenberg-Marquardt term of the OSQP RTI, ``MpcSettings.levenberg_marquardt``), then ``s`` against
  ``-l1 / (2 l2)``, which is ``l1 s + l2 s^2`` up to a constant (assumption: ``l2 > 0``); weights twice
  the description's (acados halves them); terminal: the terminal residual;
* **rows** ``h``: stage 1's rows of the description (rate, heater, PTC, floor) on every stage 0..N-1 with
  each stage's own bounds (absent rows unbounded), the soft rows minus ``s``; stage 0's flow-floor row plus
  ``s`` at a high price (:data:`FLOOR_SLACK_L1`): the OSQP RTI lowers that row's bound to what the first move
  can reach, where an exact penalty lets the QP reach as far as it can; terminal: the terminal rows;
* **parameters** per stage: the model parameters, ``dt``, the substep variant and the stage-0 floor factor.

Weights, references and bounds are set at run time: nothing is rebuilt when they change. The generated
solver is cached per structure (a hash of the functions, the grid and the acados install, :func:`install_id`)
under the code cache; the small C helper ``acados_step.c`` (the same folder) moves all stages' data in one call
per phase.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import casadi as ca
import numpy as np

from hvac_mpc.validation import finite_in, one_of

from .codegen import CodegenReport, cache_dir, compile_shared
from .ocp import TrackingProblem, shift_maps, shift_nodes
from .rti_osqp import SolveResult
from .stage_ocp import StageOcp

#: Environment variable naming the acados install (the folder ``pip install --target`` filled).
ACADOS_ENV = "HVAC_MPC_ACADOS_DIR"
#: The one command that installs acados where :func:`acados_dir` looks.
INSTALL_COMMAND = "pip install --no-deps --target <dir> comma-deps-acados"
#: acados' libraries, in the order they depend on each other.
LIBRARIES = ("libblasfeo.so", "libhpipm.so", "libqpOASES_e.so", "libacados.so")
#: Price of stage 0's flow-floor slack per L/s and (L/s)^2: an exact penalty (assumption: above any
#: multiplier of that row; the tracking costs are of order 1-100 per step).
FLOOR_SLACK_L1, FLOOR_SLACK_L2 = 1.0e4, 1.0e2
#: Bound standing for "none" on rows a stage does not carry (acados' rows need finite numbers).
BIG = 1.0e8
#: Options set on the generated solver at run time (:meth:`RtiAcadosSolver._set_runtime_options`), not part
#: of its structure: changing them rebuilds nothing.
RUNTIME_OPTIONS = ("qp_solver_iter_max", "qp_tol", "qp_solver_warm_start")
#: HPIPM's modes.
HPIPM_MODES = ("SPEED_ABS", "SPEED", "BALANCE", "ROBUST")
#: Allowed ranges of the solver's options (:func:`_check_options`); ``cond_n`` is checked against the horizon.
OPTION_CHECKS = {"disturbances": one_of("state", "parameter"), "hpipm_mode": one_of(*HPIPM_MODES),
                 "warm_start": one_of(0, 1, 2), "qp_iter_max": finite_in(1, 10000, integer=True),
                 "qp_tol": finite_in(0.0, 1.0, lo_open=True), "lm_inputs": finite_in(0.0, 1.0e4),
                 "cold_start_qps": finite_in(1, 100, integer=True),
                 "reference_change_qps": finite_in(1, 100, integer=True)}  # MpcSettings' ranges
#: Offsets of the stage parameters after the model parameters: step duration (s), substep variant, stage-0
#: floor factor, then (disturbances as parameters) the disturbances.
PAR_DT, PAR_VARIANT, PAR_FLOOR, PAR_DIST = 0, 1, 2, 3
#: acados status values: success, and "maximum iterations" (an RTI step's QP at HPIPM's cap).
ACADOS_SUCCESS, ACADOS_MAXITER = 0, 2


class AcadosMissing(RuntimeError):
    """acados is not installed where :func:`acados_dir` looks."""


def acados_dir() -> Path:
    """The acados install: ``$HVAC_MPC_ACADOS_DIR``, else ``<code cache>/acados``."""
    env = os.environ.get(ACADOS_ENV)
    return Path(env) if env else cache_dir() / "acados"


def load_acados() -> Path:
    """Make acados' Python interface importable and its libraries loaded; returns its ``install`` folder.
    Raises :class:`AcadosMissing` naming the install command.

    Process-wide effects: the wheel's ``acados`` folder is appended to ``sys.path`` and acados' libraries
    (BLASFEO, HPIPM, qpOASES, acados) are loaded with ``RTLD_GLOBAL``. CasADi's fatrop and hpipm plugins carry a
    BLASFEO of their own: a process that loads both may mix the two builds, so ``solve-time --acados`` does not
    run fatrop in the same process. acados' environment variables are set only while a solver is generated
    (:func:`_generation_env`)."""
    root = acados_dir() / "acados"
    install = root / "install"
    if not (install / "lib" / "libacados.so").exists() or not (root / "acados_template").is_dir():
        raise AcadosMissing(f"acados not found in {acados_dir()} (set {ACADOS_ENV}); install it with: "
                            f"{INSTALL_COMMAND.replace('<dir>', str(acados_dir()))}")
    for name in LIBRARIES:  # found by the generated solver without LD_LIBRARY_PATH
        ctypes.CDLL(str(install / "lib" / name), mode=ctypes.RTLD_GLOBAL)
    if str(root) not in sys.path:
        sys.path.append(str(root))  # the folder itself holds the wheel's CasADi: never on the path
    return install


class _Ocp(ctypes.Structure):
    """``hvac_ocp`` of acados_step.c."""

    _fields_ = [(n, ctypes.c_void_p) for n in ("config", "dims", "nlp_in", "nlp_out", "solver", "opts", "capsule",
                                                "update_params")] + \
               [(n, ctypes.c_int) for n in ("N", "nx", "nu", "ny", "ny_e", "np")]


def install_id(install: Path) -> str:
    """Identity of an acados install: a hash of its ``libacados.so`` (a solver or helper built against one
    install is not reused with another)."""
    return hashlib.sha256((install / "lib" / "libacados.so").read_bytes()).hexdigest()[:16]


#: Held while acados' code generator runs: it changes the process's working directory and environment
#: (:func:`_generation_env`); two solvers generated at once in one process would see each other's.
_GENERATION_LOCK = threading.Lock()


@contextmanager
def _generation_env(install: Path, folder: Path):
    """acados' code generator's settings, only while it runs: ``ACADOS_SOURCE_DIR`` and
    ``ACADOS_PYTHON_INTERFACE_PATH`` point at ``install`` (restored after), the working directory is
    ``folder`` (acados writes relative to it). Process-wide for that time (the generation of the C, not its
    compilation, which runs in a child process), under :data:`_GENERATION_LOCK`."""
    values = {"ACADOS_SOURCE_DIR": str(install),
              "ACADOS_PYTHON_INTERFACE_PATH": str(install.parent / "acados_template")}
    with _GENERATION_LOCK:
        saved = {k: os.environ.get(k) for k in values}
        cwd = os.getcwd()
        os.environ.update(values)
        try:
            os.chdir(folder)
            yield
        finally:
            os.chdir(cwd)
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


def _ptr(a: np.ndarray):
    return a.ctypes.data_as(ctypes.c_void_p)


class RtiAcadosSolver:
    """RTI on :class:`TrackingProblem` through acados (module docstring); the interface of
    :class:`~.rti_osqp.RtiOsqpSolver` that :class:`~.mpc_controller.MpcController` drives (``reset``,
    ``prepare``, ``feedback``, ``set_parameters``, ``fail_next``).

    Args:
        problem: the shared OCP data.
        lm_inputs: Levenberg-Marquardt weight on the inputs' step from the linearisation point.
        cold_start_qps: RTI iterations on a cold start (no plan to start from).
        reference_change_qps: RTI iterations on a step whose reference or weights differ from the preparation's.
        qp_iter_max: HPIPM's iteration cap; qp_tol: its tolerance (all four residuals).
        hpipm_mode: HPIPM's mode (``SPEED_ABS``, ``SPEED``, ``BALANCE``, ``ROBUST``).
        cond_n: partial condensing horizon (None: acados' default, the horizon itself).
        warm_start: HPIPM's warm start (0 none, 1 primal, 2 primal and dual).
        disturbances: ``"state"`` (constant augmented states, set with the initial state) or ``"parameter"``
            (stage parameters, set at the preparation: changes until the feedback are not seen).
    """

    def __init__(self, problem: TrackingProblem, *, lm_inputs: float = 0.0, cold_start_qps: int = 1,
                 reference_change_qps: int = 1, qp_iter_max: int = 50, qp_tol: float = 1e-6,
                 hpipm_mode: str = "SPEED", cond_n: int | None = None, warm_start: int = 1,
                 disturbances: str = "state"):
        self.pb = pb = problem
        self.name = "rti-acados"
        if pb.body_heat_coef:
            raise ValueError("RtiAcadosSolver: weights.body_heat_power_w must be 0 (range [0, 0]); the value of the "
                             "heater body's heat is in the OSQP and IPOPT solvers only")
        if pb.flap_closure_weight:
            raise ValueError("RtiAcadosSolver: weights.flap_closure_per_pct2 must be 0 (range [0, 0]); the flaps' "
                             "closure term is in the OSQP and IPOPT solvers only")
        _check_options(dict(disturbances=disturbances, hpipm_mode=hpipm_mode, warm_start=warm_start,
                            qp_iter_max=qp_iter_max, qp_tol=qp_tol, lm_inputs=lm_inputs, cold_start_qps=cold_start_qps,
                            reference_change_qps=reference_change_qps), cond_n, pb.N)
        self.desc = StageOcp(problem)
        self.lm = float(lm_inputs)
        self.cold_start_qps, self.reference_change_qps = int(cold_start_qps), int(reference_change_qps)
        self.options = dict(qp_solver="PARTIAL_CONDENSING_HPIPM", qp_solver_iter_max=int(qp_iter_max),
                            qp_tol=float(qp_tol), hpipm_mode=hpipm_mode, qp_solver_warm_start=int(warm_start),
                            qp_solver_cond_N=int(cond_n) if cond_n is not None else pb.N)
        N, nx, nu, nd = pb.N, pb.nx, pb.nu, pb.nd
        self.d_state = disturbances == "state"
        self.nxa, self.nua = nx + nu + (nd if self.d_state else 0), nu + 1
        self.npar = self._p_size() + PAR_DIST + (0 if self.d_state else nd)
        self._s_col = nu  # the slack's column of the input [u, s]
        self._rows = self.desc.stages[min(1, N - 1)].row_slices(nu)
        self.codegen = CodegenReport()
        self._i0, self._w1, self._j = shift_maps(pb.t_nodes, pb.dt_s)
        self._p = np.array(pb.model.p_default, float)
        self._build()
        self.fail_next = 0
        self.reset()

    def _p_size(self) -> int:
        return len(self.pb.model.p_default)

    # ------------------------------------------------------------------ structure
    def _symbols(self):
        pb, d = self.pb, self.desc
        xa = ca.MX.sym("xa", self.nxa)
        ua = ca.MX.sym("ua", self.nua)
        par = ca.MX.sym("par", self.npar)
        x_u = xa[:d.nxa]
        n = self._p.size
        dist = xa[d.nxa:] if self.d_state else par[n + PAR_DIST:]
        u, s = ua[:pb.nu], ua[self._s_col]
        p, dt, variant, floor_c = par[:n], par[n + PAR_DT], par[n + PAR_VARIANT], par[n + PAR_FLOOR]
        return xa, ua, par, x_u, dist, u, s, p, dt, variant, floor_c

    def _model(self, AcadosModel, name: str):
        pb, desc = self.pb, self.desc
        xa, ua, par, x_u, dist, u, s, p, dt, variant, floor_c = self._symbols()
        self.variants = sorted(desc.dynamics)
        fns = [desc.dynamics[n] for n in self.variants]
        dyn = ca.Function.conditional("dyn_variant", fns[:-1], fns[-1]) if len(fns) > 1 else None
        args = [x_u, u, dist, dt, p]
        x_next = dyn(variant, *args) if dyn is not None else fns[0](*args)
        m = AcadosModel()
        m.name = name
        m.x, m.u, m.p = xa, ua, par
        m.disc_dyn_expr = ca.vertcat(x_next, dist) if self.d_state else x_next
        m.cost_y_expr = ca.vertcat(desc.residual(x_u, u, dist, p), u, s)
        m.cost_y_expr_e = desc.terminal_residual(x_u, dist, p)
        h = desc.stages[min(1, pb.N - 1)].h(x_u, u, dist, p)
        soft = np.zeros(h.shape[0])
        for kind in ("heater", "ptc"):
            if kind in self._rows:
                soft[self._rows[kind]] = 1.0
        floor = np.zeros(h.shape[0])
        if "floor" in self._rows:
            floor[self._rows["floor"]] = 1.0
        m.con_h_expr = h - ca.DM(soft) * s + ca.DM(floor) * floor_c * s
        st_e = desc.stages[pb.N]
        if st_e.n_rows:
            m.con_h_expr_e = st_e.h(x_u, dist, p)
        return m

    def _key(self, install: Path) -> str:
        """Hash of what the generated solver depends on: the description's functions, the grid, the options and
        the acados install (:func:`install_id`)."""
        desc, h = self.desc, hashlib.sha256(install_id(install).encode())
        for f in [*desc.dynamics.values(), desc.residual, desc.terminal_residual,
                  desc.stages[min(1, desc.N - 1)].h, desc.stages[desc.N].h]:
            h.update(f.serialize().encode())
        built_in = {k: v for k, v in self.options.items() if k not in RUNTIME_OPTIONS}
        h.update(repr((self.pb.dt.tolist(), self.pb.stage_substeps.tolist(), sorted(built_in.items()),
                       self.d_state, ca.__version__)).encode())
        return h.hexdigest()[:16]

    def _ocp(self, folder: Path, name: str, install: Path):
        from acados_template import AcadosModel, AcadosOcp  # noqa: PLC0415 - optional extra, imported lazily
        pb, desc, N = self.pb, self.desc, self.pb.N
        ocp = AcadosOcp(acados_path=str(install))
        ocp.model = self._model(AcadosModel, name)
        ocp.dims.N = N
        ny, ny_e = desc.nr + pb.nu + 1, desc.nr_e
        ocp.cost.cost_type, ocp.cost.cost_type_e = "NONLINEAR_LS", "NONLINEAR_LS"
        ocp.cost.W, ocp.cost.yref = np.eye(ny), np.zeros(ny)
        ocp.cost.W_e, ocp.cost.yref_e = np.eye(ny_e), np.zeros(ny_e)
        c = ocp.constraints
        c.x0 = np.zeros(self.nxa)
        c.idxbu = np.arange(self.nua)
        c.lbu, c.ubu = -BIG * np.ones(self.nua), BIG * np.ones(self.nua)
        nh = ocp.model.con_h_expr.shape[0]
        c.lh, c.uh = -BIG * np.ones(nh), BIG * np.ones(nh)
        st_e = desc.stages[N]
        if st_e.n_rows:
            c.lh_e, c.uh_e = -BIG * np.ones(st_e.n_rows), BIG * np.ones(st_e.n_rows)
            if st_e.has_slack:
                c.idxsh_e = np.flatnonzero(st_e.soft)
                ns = c.idxsh_e.size
                ocp.cost.zl_e = ocp.cost.zu_e = np.full(ns, st_e.slack_l1)
                ocp.cost.Zl_e = ocp.cost.Zu_e = np.full(ns, 2.0 * st_e.slack_l2)
        ocp.parameter_values = np.zeros(self.npar)
        o = ocp.solver_options
        o.integrator_type, o.nlp_solver_type, o.hessian_approx = "DISCRETE", "SQP_RTI", "GAUSS_NEWTON"
        o.tf = float(pb.dt.sum())
        o.time_steps = pb.dt.astype(float)
        for k, v in self.options.items():
            if k not in RUNTIME_OPTIONS:
                setattr(o, k, v)
        ocp.code_export_directory = str(folder)
        return ocp

    def _build(self) -> None:
        """The generated solver, loaded from the cache or generated (in this process, :func:`_generation_env`)
        and compiled (``make`` in a child process whose working directory is the solver's folder)."""
        install = load_acados()
        from acados_template import AcadosOcpSolver  # noqa: PLC0415
        name = f"hvac_{self._key(install)}"
        folder = cache_dir() / "acados_ocp" / name
        json_file = str(folder / f"{name}.json")
        built = (folder / f"libacados_ocp_solver_{name}.so").exists()
        t0 = time.perf_counter()
        folder.mkdir(parents=True, exist_ok=True)
        ocp = self._ocp(folder, name, install)
        if not built:
            with _generation_env(install, folder):
                AcadosOcpSolver.generate(ocp, json_file=json_file)
            _make(folder)
        self.acados = AcadosOcpSolver(ocp, json_file=json_file, generate=False, build=False, verbose=False)
        self.codegen.outcomes["acados_ocp"] = "cached" if built else "built"
        self._step_lib = _helper(install, self.codegen)
        self.codegen.build_time_s += 0.0 if built else time.perf_counter() - t0
        self._bind(name)
        self._set_stage_parameters()
        self._set_runtime_options()
        self._unit_cost_scaling()

    def _unit_cost_scaling(self) -> None:
        """acados multiplies each stage's cost by the stage's duration; the description's weights carry it
        already (``StageOcp.weights``): scaling 1 on every stage."""
        a, one = self.acados, ctypes.c_double(1.0)
        setter = ctypes.CDLL(None).ocp_nlp_cost_model_set
        for k in range(self.pb.N):
            setter(ctypes.c_void_p(a.nlp_config), ctypes.c_void_p(a.nlp_dims), ctypes.c_void_p(a.nlp_in), k,
                   b"scaling", ctypes.byref(one))

    def _set_runtime_options(self) -> None:
        """HPIPM's iteration cap, tolerances and warm start, through acados' options setter."""
        a, o = self.acados, self.options
        setter = ctypes.CDLL(None).ocp_nlp_solver_opts_set  # libacados, loaded globally by load_acados
        setter.restype = None
        ints = {"qp_iter_max": o["qp_solver_iter_max"], "qp_warm_start": o["qp_solver_warm_start"]}
        doubles = {f"qp_tol_{n}": o["qp_tol"] for n in ("stat", "eq", "ineq", "comp")}
        for field, value in [*((f, ctypes.c_int(v)) for f, v in ints.items()),
                             *((f, ctypes.c_double(v)) for f, v in doubles.items())]:
            setter(ctypes.c_void_p(a.nlp_config), ctypes.c_void_p(a.nlp_opts), field.encode(), ctypes.byref(value))

    def _bind(self, name: str) -> None:
        a, pb, desc = self.acados, self.pb, self.desc
        upd = getattr(a.shared_lib, f"{name}_acados_update_params")
        self._ny, self._ny_e = desc.nr + pb.nu + 1, desc.nr_e
        self._o = _Ocp(a.nlp_config, a.nlp_dims, a.nlp_in, a.nlp_out, a.nlp_solver, a.nlp_opts, a.capsule,
                       ctypes.cast(upd, ctypes.c_void_p).value, pb.N, self.nxa, self.nua, self._ny, self._ny_e,
                       self.npar)
        self._op = ctypes.byref(self._o)
        lib = self._step_lib
        for f in ("hvac_set_iterate", "hvac_get_iterate", "hvac_set_cost", "hvac_set_bounds", "hvac_set_params"):
            getattr(lib, f).restype = None
        lib.hvac_solve.restype = ctypes.c_int
        self._qp_iter = ctypes.c_int(0)
        N = pb.N
        self._X = np.zeros((N + 1, self.nxa))
        self._U = np.zeros((N, self.nua))
        self._lbu = np.zeros((N, self.nua))
        self._ubu = np.zeros((N, self.nua))
        self._ubu[:, self._s_col] = BIG
        self._yref = np.zeros((N, self._ny))
        self._yref[1:, -1] = [-st.slack_l1 / (2.0 * st.slack_l2) if st.has_slack else 0.0
                              for st in desc.stages[1:N]]
        self._yref[0, -1] = -FLOOR_SLACK_L1 / (2.0 * FLOOR_SLACK_L2)
        self._yref_e = np.zeros(self._ny_e)
        self._W = np.zeros((N, self._ny, self._ny))
        self._W_e = np.zeros((self._ny_e, self._ny_e))
        self._x0 = np.zeros(self.nxa)
        self._bounds_prepared = (self._lbu.copy(), self._ubu.copy())
        self._set_rows()

    def _set_rows(self) -> None:
        """Each stage's row bounds (absent rows unbounded), once: they do not change from step to step."""
        a, pb, desc = self.acados, self.pb, self.desc
        full = desc.stages[min(1, pb.N - 1)]
        for k in range(pb.N):
            st = desc.stages[k]
            lh, uh = -BIG * np.ones(full.n_rows), BIG * np.ones(full.n_rows)
            mine = st.row_slices(pb.nu)
            for kind, sl in full.row_slices(pb.nu).items():
                if kind in mine:
                    lh[sl] = np.maximum(st.lh[mine[kind]], -BIG)
                    uh[sl] = np.minimum(st.uh[mine[kind]], BIG)
            a.constraints_set(k, "lh", lh)
            a.constraints_set(k, "uh", uh)
        st_e = desc.stages[pb.N]
        if st_e.n_rows:
            a.constraints_set(pb.N, "lh", np.maximum(st_e.lh, -BIG))
            a.constraints_set(pb.N, "uh", np.minimum(st_e.uh, BIG))

    def _set_stage_parameters(self) -> None:
        pb = self.pb
        P = np.zeros((pb.N + 1, self.npar))
        P[:, :self._p.size] = self._p
        n = self._p.size
        P[:, n + PAR_DT] = np.append(pb.dt, pb.dt[-1])
        P[:, n + PAR_VARIANT] = [self.variants.index(v) for v in pb.stage_substeps]
        P[0, n + PAR_FLOOR] = 1.0 if "floor" in self._rows else 0.0
        self._P = np.ascontiguousarray(P)
        self._step_lib.hvac_set_params(self._op, _ptr(self._P))

    @property
    def settings(self) -> dict:
        """acados' settings (benchmark reports)."""
        return {"description": "StageOcp: its functions as acados' AcadosOcp (rti_acados)",
                "qp_solver": "acados", "nlp_solver": "SQP_RTI", **self.options,
                "hessian": "GAUSS_NEWTON", "integrator": "DISCRETE", "levenberg_marquardt": self.lm,
                "cold_start_qps": self.cold_start_qps, "reference_change_qps": self.reference_change_qps,
                "disturbances": "constant augmented states" if self.d_state else "stage parameters", "compiled": True,
                "compile_flags": "acados_template's Makefile (gcc -O2 -fPIC)", "blasfeo": "AVX2/FMA kernels (wheel)"}

    # ------------------------------------------------------------------ interface
    def reset(self) -> None:
        """Forget the trajectory (cold start at the next step) and acados' iterate (states, inputs, slacks and
        multipliers set to zero by acados' reset). acados' QP memory is kept: its reset
        (``reset_qp_solver_mem``) ends the process with a segmentation fault in the wheel's acados (measured:
        the next preparation crashes, before or after a first solve); HPIPM's warm start may then start from
        the last QP's answer."""
        self.X = self.U = self.S = None
        self._prepared = None
        self.acados.reset(reset_qp_solver_mem=0)

    def set_parameters(self, p: np.ndarray) -> None:
        """Model parameters (``HvacModel.p_default`` order) of the next linearisations; no rebuild."""
        if not np.array_equal(p, self._p):
            self._p[...] = p
            self._P[:, :self._p.size] = self._p
            self._step_lib.hvac_set_params(self._op, _ptr(self._P))

    @property
    def has_trajectory(self) -> bool:
        return self.X is not None

    def _weights(self, w_y: np.ndarray) -> None:
        pb, desc = self.pb, self.desc
        nr = desc.nr
        for k in range(pb.N):
            st = desc.stages[k]
            w = np.empty(self._ny)
            w[:nr] = desc.weights(k, w_y)
            w[nr:nr + pb.nu] = self.lm
            w[-1] = st.slack_l2 if (k > 0 and st.has_slack) else (FLOOR_SLACK_L2 if k == 0 else 0.0)
            np.fill_diagonal(self._W[k], 2.0 * w)
        np.fill_diagonal(self._W_e, 2.0 * desc.weights(pb.N, w_y))

    def _load(self, X, U, S, d, ref, w_y, u_prev) -> None:
        """Write the iterate (X, U, S) and the cost data into acados (before a preparation)."""
        pb, nx, nu = self.pb, self.pb.nx, self.pb.nu
        self._X[:, :nx] = X
        self._X[0, nx:nx + nu] = u_prev
        self._X[1:, nx:nx + nu] = U
        if self.d_state:
            self._X[:, nx + nu:] = d
        else:
            self._P[:, self._p.size + PAR_DIST:] = d
            self._step_lib.hvac_set_params(self._op, _ptr(self._P))
        self._U[:, :nu] = U
        self._U[:, self._s_col] = S
        self._yref[:, :pb.ny] = ref
        self._yref[:, self.desc.nr:self.desc.nr + nu] = U
        self._yref_e[:] = ref
        new_w = self._prepared is None or not np.array_equal(self._prepared["w_y"], w_y)
        if new_w:
            self._weights(w_y)
        lib = self._step_lib
        lib.hvac_set_iterate(self._op, _ptr(self._X), _ptr(self._U))
        lib.hvac_set_cost(self._op, _ptr(self._yref), _ptr(self._yref_e), _ptr(self._W) if new_w else None,
                          _ptr(self._W_e) if new_w else None)
        self._prepared = dict(w_y=w_y.copy(), ref=np.array(ref, float))

    def prepare(self, x_pred: np.ndarray, u_prev: np.ndarray, d: np.ndarray, ref: np.ndarray,
                w_y: np.ndarray) -> float:
        """Preparation phase: shift, load, and acados' preparation (linearisation). Returns its wall time (s)."""
        t0 = time.perf_counter()
        if self.X is None:
            self.X, self.U, self.S = self.pb.rollout(x_pred, u_prev, d), np.tile(u_prev, (self.pb.N, 1)), \
                np.zeros(self.pb.N)
        else:
            self.X = shift_nodes(self.X, self._i0, self._w1)
            self.X[0] = x_pred
            self.U = self.U[self._j]
            self.U[0] = u_prev
            self.S = self.S[self._j]
        self._load(self.X, self.U, self.S, d, ref, w_y, u_prev)
        self._prepare_phase()
        return time.perf_counter() - t0

    def _prepare_again(self, u_prev: np.ndarray, d: np.ndarray, ref: np.ndarray, w_y: np.ndarray) -> float:
        """The preparation again at the iterate in place (already shifted by :meth:`prepare`), with another
        reference or weights: load and linearise, no shift. Returns its wall time (s)."""
        t0 = time.perf_counter()
        self._load(self.X, self.U, self.S, d, ref, w_y, u_prev)
        self._prepare_phase()
        return time.perf_counter() - t0

    def _prepare_phase(self) -> None:
        """acados' preparation at the iterate in place, with the bounds in place (kept to compare)."""
        self._step_lib.hvac_solve(self._op, 1, ctypes.byref(self._qp_iter))
        self._bounds_prepared = (self._lbu.copy(), self._ubu.copy())

    def feedback(self, x0: np.ndarray, u_prev: np.ndarray, d: np.ndarray, ref: np.ndarray, w_y: np.ndarray,
                 u_lo: np.ndarray, u_hi: np.ndarray, time_limit_s: float = 0.0) -> SolveResult:
        """Feedback phase: insert the estimate and the bounds, solve the prepared QP (more RTI iterations on a
        cold start or a changed reference). ``time_limit_s`` is not passed on (HPIPM has no time limit here):
        the controller checks the whole feedback's time against its deadline."""
        t0 = time.perf_counter()
        prep = 0.0
        cold = self.X is None
        qps = self.cold_start_qps if cold else 1
        changed = self._prepared is not None and not (np.array_equal(self._prepared["ref"], ref)
                                                       and np.array_equal(self._prepared["w_y"], w_y))
        if changed:
            qps = max(qps, self.reference_change_qps)
        pb, nx, nu = self.pb, self.pb.nx, self.pb.nu
        self._x0[:nx], self._x0[nx:nx + nu] = x0, u_prev
        if self.d_state:
            self._x0[nx + nu:] = d
        self._lbu[:, :nu], self._ubu[:, :nu] = u_lo, u_hi
        self._ubu[0, self._s_col] = BIG if "floor" in self._rows else 0.0
        lib = self._step_lib
        # acados' preparation puts the bounds into the QP (its feedback embeds only the initial state):
        # bounds other than the prepared ones need a preparation again
        lib.hvac_set_bounds(self._op, _ptr(self._x0), _ptr(self._lbu), _ptr(self._ubu))
        bounds_moved = not (np.array_equal(self._lbu, self._bounds_prepared[0])
                            and np.array_equal(self._ubu, self._bounds_prepared[1]))
        if self._prepared is None:
            prep = self.prepare(x0, u_prev, d, ref, w_y)
        elif changed:
            prep = self._prepare_again(u_prev, d, ref, w_y)
        elif bounds_moved:
            self._prepare_phase()
        if self.fail_next > 0:
            self.fail_next -= 1
            return SolveResult(False, "forced failure", prep_time_s=prep,
                               feedback_time_s=time.perf_counter() - t0 - prep)
        iterations, status, solves = 0, ACADOS_SUCCESS, 0
        for it in range(qps):  # qps >= 1 (_check_options)
            if it > 0:  # linearise again at the last answer, the inputs' damping anchored there
                self._yref[:, self.desc.nr:self.desc.nr + nu] = self._U[:, :nu]
                lib.hvac_set_cost(self._op, _ptr(self._yref), _ptr(self._yref_e), None, None)
                lib.hvac_set_iterate(self._op, _ptr(self._X), _ptr(self._U))
                self._prepare_phase()
            status = lib.hvac_solve(self._op, 2, ctypes.byref(self._qp_iter))
            iterations += self._qp_iter.value
            solves += 1
            lib.hvac_get_iterate(self._op, _ptr(self._X), _ptr(self._U))
            if status not in (ACADOS_SUCCESS, ACADOS_MAXITER):
                break
        feedback = time.perf_counter() - t0 - prep
        if status not in (ACADOS_SUCCESS, ACADOS_MAXITER) or not np.isfinite(self._U).all():
            return SolveResult(False, f"acados status {status}", iterations=iterations, qp_solves=solves,
                               prep_time_s=prep, feedback_time_s=feedback, extra={"cold_start": cold})
        self.X = self._X[:, :nx].copy()
        self.U = self._U[:, :nu].copy()
        self.S = self._U[:, self._s_col].copy()
        return SolveResult(True, "solved", X=self.X.copy(), U=self.U.copy(), S=self.S[1:].copy(),
                           iterations=iterations, qp_solves=solves, prep_time_s=prep, feedback_time_s=feedback,
                           extra={"cold_start": cold, "acados_status": status})


def _check_options(values: dict, cond_n, N: int) -> None:
    """A clear error naming the option and its allowed range or choices (:data:`OPTION_CHECKS`)."""
    for name, check in OPTION_CHECKS.items():
        check(f"RtiAcadosSolver.{name}", values[name])
    if cond_n is not None:
        finite_in(1, N, integer=True)("RtiAcadosSolver.cond_n", cond_n)


def _make(folder: Path) -> None:
    """Compile the generated solver with its Makefile, in a child process working in ``folder``; a failure
    raises with make's output."""
    res = subprocess.run(["make", "ocp_shared_lib"], cwd=folder, capture_output=True, text=True, timeout=1800)
    if res.returncode != 0:
        raise RuntimeError(f"building the acados solver in {folder} failed (make exit {res.returncode}): "
                           f"{(res.stderr or res.stdout)[-2000:]}")


def _helper(install: Path, report: CodegenReport) -> ctypes.CDLL:
    """acados_step.c compiled against acados (cached by the source's hash and :func:`install_id`), loaded."""
    src = Path(__file__).with_name("acados_step.c")
    key = hashlib.sha256(src.read_bytes() + install_id(install).encode()).hexdigest()[:16]
    lib = cache_dir() / f"acados_step_{key}.so"
    report.outcomes["acados_step"] = "cached" if lib.exists() else "built"
    if not lib.exists():
        compile_shared(src, lib, ("-O2", "-fPIC", "-shared"), (f"-L{install / 'lib'}", "-lacados",
                                                               f"-Wl,-rpath,{install / 'lib'}"), timeout_s=120)
    return ctypes.CDLL(str(lib))


__all__ = ["ACADOS_ENV", "INSTALL_COMMAND", "AcadosMissing", "RtiAcadosSolver", "acados_dir", "install_id",
           "load_acados"]
