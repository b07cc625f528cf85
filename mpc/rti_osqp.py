"""Real-time iteration (RTI) for the tracking problem: multiple shooting, Gauss-Newton, OSQP.

The QP lives in absolute scaled variables ``z = [x_0 .. x_N, u_0 .. u_N-1, s_1 .. s_N]``. Its
sparsity is fixed at construction; every step only values change:

* **preparation** (:meth:`RtiOsqpSolver.prepare`, before the next measurement): shift the last
  solution one sample along the non-uniform stage grid, linearise all stages at it with one
  call of ``hvac_qp_data`` (generated C by default, the model parameters an input), write the
  new values into ``P`` (Gauss-Newton Hessian of the least-squares residuals) and ``A``
  (dynamics Jacobians) in OSQP (one numeric refactorisation), and the dynamics right-hand sides
  into ``l``/``u``;
* **feedback** (:meth:`RtiOsqpSolver.feedback`, when the estimate arrives): insert the estimated
  state, the input bounds and the reference / disturbance-estimate changes into ``q`` (one call
  of ``hvac_qp_gradient``), ``l``, ``u`` (no refactorisation) and solve, warm-started from the
  shifted trajectory (the duals from the last solve).

docs/architecture.md, 'One control step', lists what runs as generated C and what in Python.

With ``sqp_max_iter > 1`` the feedback re-linearises at the new iterate and solves again until
the step is below ``sqp_tol`` (a Gauss-Newton SQP to a tolerance). With ``steady_start`` the QPs of a
reference change (every one, or with ``steady_start_on="temperature"`` those of the supply temperature's)
are linearised at the plan toward the new reference's steady-state target instead of the shifted plan
(:mod:`.steady_target`). With ``relinearise_every`` > 1 most preparations keep OSQP's matrices
and renew only the vectors at the shifted plan (:mod:`.multilevel`, multi-level steps).
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sp

from hvac_mpc.models.box import DISTURBANCES, INPUTS

from . import osqp_embedded
from .arrays import all_finite, all_reduce, sum_reduce
from .casadi_eval import BufferedFunction
from .change_rho import HOLD_INTERVAL, ChangeStepSize, check_adaptation, check_change_rho, check_hold
from .codegen import CodegenReport, compiled, expression_key, kept
from .multilevel import MultiLevel, vector_function
from .ocp import STAGE_OUTPUTS, TRACKED, TrackingProblem, check_flag, check_number, shift_maps, shift_nodes
from .osqp_embedded import FIRST_PASS_EPS_RATIO  # noqa: F401 - the first pass's tolerance, named here too
from .plan_merit import MERIT_TOLERANCE, PlanMerit
from .reversal_search import (at_bound, at_upper_bound, candidates, check_second_qp, check_second_qp_with, check_share,
                              check_wait, eligible_inputs, last_moves, turned_inputs, turns_and_moves)
from .steady_target import SteadyStart, check_steady_start_on, starts_at_target
from .trust_region import check_radii, region_bounds

#: Rows of the stage outputs (``STAGE_OUTPUTS``) by signal: the tracked temperature, the total
#: flow, the outlet flows and the electric heater power (the energy residual's heater part).
Y_TEMP = STAGE_OUTPUTS.index(TRACKED[0])
Y_FLOW = STAGE_OUTPUTS.index("volume_flow_m3s")
Y_OUTLETS = tuple(STAGE_OUTPUTS.index(n) for n in ("flow_m_m3s", "flow_f_m3s", "flow_w_m3s"))
Y_POWER = STAGE_OUTPUTS.index("heater_power_w")
#: Decision index of the blower power (the energy residual's blower part).
U_BLOWER = INPUTS.index("blower_power_w")
#: Disturbance entries estimated by the EKF that enter the gradient without a new linearisation:
#: the mixed-air offset and the flow offset.
D_OFFSETS = [DISTURBANCES.index("mix_offset_c"), DISTURBANCES.index("flow_offset_m3s")]
#: The same as an index array (indexing with it skips the list's conversion every step).
_D_OFFSETS_IDX = np.array(D_OFFSETS)
#: Margin (L/s) below the most stage 0's flow-floor row can reach within the first move's bounds, where
#: that is below the floor (``RtiOsqpSolver._floor_bounds``): a bound on the edge of the feasible set is
#: left to the QP solver's tolerance otherwise.
FLOOR_TOLERANCE_LS = 0.01
#: When ``RtiOsqpSolver(rho_reset=...)`` sets OSQP's step size: at every preparation's matrix update, or for the QPs of a
#: reference change only.
RHO_RESET_ON = ("preparation", "change")
#: The damped steps of the merit function a trust region builds when no globalised step is configured (its
#: ``choose`` is not called then; :class:`.plan_merit.PlanMerit` needs one).
TRUST_MERIT_FRACTIONS = (0.5,)
#: OSQP's time limit when none is wanted (s): OSQP's own default (its Python interface refuses 0).
NO_TIME_LIMIT_S = 1e10


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


@dataclass
class FusedPrediction:
    """One filter's time update fused with the QP data (:meth:`RtiOsqpSolver.build_prediction`): the filter,
    its time-update function the fusion was built from, that function's fixed inputs, and the buffered
    functions with the index of the QP parameters' input (``vec``: the multi-level step's, or None)."""
    ekf: object
    predict: object
    fixed: dict
    qp: BufferedFunction
    i_p_qp: int
    vec: BufferedFunction | None = None
    i_p_vec: int = -1


class RtiOsqpSolver:
    """RTI / Gauss-Newton SQP on :class:`TrackingProblem` with OSQP set up once.

    Args:
        problem: the shared OCP data.
        eps: OSQP absolute and relative tolerance.
        max_iter: OSQP iteration cap per QP.
        sqp_max_iter: QPs per step (1 = real-time iteration).
        sqp_tol: SQP stops when the largest change of a scaled variable is below this.
        check_termination: OSQP checks convergence every this many iterations.
        scaling: OSQP's Ruiz equilibration passes, run again on every matrix update (each pass
            costs about as much as the numeric refactorisation itself).
        alpha: OSQP's relaxation parameter in (0, 2).
        check_dualgap: also require OSQP's duality gap below the tolerance (OSQP >= 1.0) before it
            stops; the primal and dual residuals are checked either way.
        first_pass_iter: iterations of OSQP's first pass without over-relaxation (0: none), see
            :class:`_OsqpCore`.
        lm_inputs: Levenberg-Marquardt weight on the inputs' step from the linearisation point.
        cold_start_qps: QPs allowed (Gauss-Newton SQP to ``sqp_tol``) on a cold start, when there
            is no previous solution to start from (first step, after a reset or a failure).
        reference_change_qps: QPs allowed on a step whose reference differs from the one the
            preparation used: the shifted plan was made for the old reference, so one damped
            Gauss-Newton step from it is far from the new optimum.
        accept_max_iter: take OSQP's iterate at ``max_iter`` (status "maximum iterations reached")
            as the QP's answer instead of a failure: an inexact QP step, as the real-time iteration
            takes an inexact NLP step; the next QP starts from it (primal shifted, dual kept).
            ``SolveResult.extra["inexact"]`` says when the step's answer is such an iterate.
        restart_duals_on_change: on a step whose reference differs from the preparation's, start the first
            QP from zero multipliers instead of the last QP's (off: measured no fewer iterations,
            ``benchmarks/osqp_restart.py``).
        step_fractions: a globalised step (:class:`.plan_merit.PlanMerit`): after each QP the nonlinear cost of
            its plan is compared with the linearisation point's, and where it is higher the damped steps of
            these fractions are tried and the least cost taken (``SolveResult.extra["step_fraction"]``).
            Empty (the default): the QP's plan is taken whole, the plain real-time iteration.
        trust_radii: a trust region (:mod:`.trust_region`): where a QP's plan costs more on the nonlinear cost
            than the linearisation point's (beyond :data:`.plan_merit.MERIT_TOLERANCE`), the same QP is solved
            again with each stage's inputs within radius x their range of the linearisation point's plan, for
            these radii in turn, and the first plan no worse is taken (else the cheapest of those solved;
            ``trust_taken`` says which radius the last one came from, 1 the QP's own). Before the damped step
            where both are set. Not on a cold start: its linearisation point is the starting command held over
            the horizon, a guess and not a plan, and its QPs iterate from there (``cold_start_qps``); with the
            region each iteration stayed within a radius of the last, and the first command came from near the
            guess (:mod:`.trust_region`). Empty (the default): off.
        reversal_search: a search along a reversing input (:mod:`.reversal_search`): on a plain step (one QP: not a
            cold start, not a reference change, not split) where the plan's first move of an input turns against the
            last step's first move, both by more than this share of the input's range, the QP's plan with that
            input's profile replaced by the linearisation point's, by its upper and by its lower bound is priced on
            the nonlinear cost (:class:`.plan_merit.PlanMerit`) and the cheapest of these and the QP's plan taken
            (``reversal_searched`` says when the search ran, ``reversal_taken`` when a candidate was taken). No QP
            is added. 0 (the default): off.
        reversal_wait_steps: the search acts only after this many plain one-QP steps in a row (a cold start, a
            reference change and a split step start the count again; 0: from the first plain step).
        reversal_repeat: the search prices only an input whose plan turned on the step before as well.
        reversal_margin: a candidate is taken only where its cost is below (1 - this share) x the QP plan's.
        reversal_bound_only: the linearisation point's profile of a reversing input is a candidate only where its
            first stage is at that input's bound (:func:`.reversal_search.at_bound`); the two bounds' profiles are
            candidates as before.
        reversal_second_qp: a second Gauss-Newton QP, linearised at the first QP's plan, on a plain step whose plan
            turns an input against its last first move (beyond ``reversal_search``'s share; needs it > 0):
            ``"reversal"`` on every such step, ``"heater_bound"`` only where the plan's heater command starts at its
            upper bound (:func:`.reversal_search.at_upper_bound`); ``"off"`` (the default): none. The search then
            prices the second QP's plan against the candidates of the step's own linearisation point
            (``reversal_relinearised`` says when it ran). Refused with ``sqp_max_iter`` > 1 and with
            ``split_every_step`` (with ``change_split_iter``): no step there is a plain one-QP step.
        valve_a_prox: a proximal (Levenberg-Marquardt) weight on valve a's deviation from the linearisation point's
            plan (per scaled unit squared, 1 = 50 % of valve a's travel; every stage), added to ``lm_inputs`` only
            where the linearisation point's heater command starts at its upper bound
            (:func:`.reversal_search.at_upper_bound`): there the QP's curvature along valve a is the move and
            Levenberg-Marquardt terms' and the flow's, the supply temperature's a tenth of it at mid-travel, against a
            linear pull that asks 1-4 times valve a's travel (docs/robustness.md sec. 2.43). 0 (the default): off.
            ``valve_a_prox_on`` says whether the last linearisation had it; a multi-level vector step
            (``relinearise_every`` > 1) keeps the full linearisation's P and so its term, as it keeps its matrices.
        codegen: evaluate the QP data as generated C (:func:`.codegen.compiled`, cached on disk);
            otherwise (or without a compiler) CasADi's interpreter runs the same functions.
            ``self.codegen`` reports what happened.
        osqp_codegen: solve the QPs with OSQP's generated C (:mod:`.osqp_embedded`, built once per
            structure and cached on disk; the same answers as OSQP's Python interface), else or
            without a compiler with OSQP's Python interface (``self.qp_codegen.outcomes["osqp"]`` says which).
        scaling_interval: OSQP's equilibration on every this many matrix updates, the updates between
            keeping the last one's (1: every update, OSQP's own behaviour). Needs ``osqp_codegen``; without
            the generated solver every update equilibrates.
        steady_start: on a step whose reference differs from the preparation's, linearise the QPs at and
            warm-start them from the plan toward the new reference's steady-state target
            (:class:`.steady_target.SteadyStart`: the inputs that hold it at rest on the model, ramped to at the
            rate limits, the model's rollout) instead of the shifted plan made for the old reference
            (``self.last_target``: the target of the last change, scaled inputs).
        relinearise_every: multi-level steps (:mod:`.multilevel`): a full linearisation (new matrices, OSQP's
            equilibration and refactorisation) at least on every this many preparations, the ones between vector
            steps that keep the matrices of the last full one and renew the QP's vectors only, where the point has
            moved by at most ``relinearise_move`` (scaled states and inputs) since (1: every preparation is a
            full one, the plain real-time iteration). ``self.levels`` counts the full and the vector steps.
        relinearise_move: the largest move of a scaled state or input of any stage since the last full
            linearisation for a vector step.
        rho_reset: with ``rho_reset_on="preparation"``, OSQP's step size ``rho`` set to this value with every matrix
            update (every full linearisation), in the refactorisation the update makes anyway (generated solver;
            OSQP's Python interface factorises once more), instead of the value the last QP's adaptation left (None:
            kept, OSQP's warm-start behaviour). OSQP still adapts it within each QP. ``rho_reset_on="change"``: only
            for the QPs of a reference change (their matrices written again with it: one refactorisation more in that
            step). Measured in docs/architecture.md, 'Slow steps'.
        change_split_iter: a reference change's QPs split between the step and :meth:`finish_change` (0: off, the
            change solved in the step): the step solves the change's QPs with at most this many OSQP iterations each
            (the iterate at the cap taken, ``SolveResult.extra["inexact"]``) and answers with them
            (``extra["change_split"]``); :meth:`finish_change`, which the controller runs on its second thread
            after the step, solves the change to convergence from the same state, and the next preparation
            starts from that plan. Measured in docs/architecture.md, 'A reference change finished on the second
            core'.
        split_every_step: with ``change_split_iter``, every step's QPs capped so; a step whose QP reaches the cap
            is finished by :meth:`finish_change` as a change is (its last QP to convergence, then
            ``reference_change_qps`` - 1 further relinearised QPs), one whose QPs meet the tolerance is not.
        split_keeps_rho: with ``change_split_iter``, :meth:`finish_change` leaves OSQP's step size ``rho`` as the
            step found it (off: as the rest's QPs adapted it).
        split_replays_change: with ``change_split_iter``, :meth:`finish_change` solves the step's QPs again as the
            unsplit step would have, from OSQP's workspace and the prepared QP as the step found them (saved before
            the capped QPs, restored after them: the multipliers, the step size, the scaled matrices and their
            factorisation), instead of continuing the capped iterate: the plan and the workspace the next step
            starts from are those of the unsplit step (to the bit with the generated solver; with OSQP's Python
            interface the multipliers' scaling differs). Only the command of the change's own step is the capped one.
        reweigh_in_place: where the output weights change after the preparation (the flow's weight factor), the
            QP linearised again at the plan the preparation already shifted (True) instead of :meth:`prepare`
            again, which shifts that plan once more, a sample ahead (False, the behaviour the bench was tuned
            with). Measured in docs/architecture.md, 'Slow steps'.
        steady_start_on: with ``steady_start``, which changes start there (:data:`.steady_target.STEADY_START_ON`):
            "any" change of the reference, or only those of the supply "temperature" reference (a flow or
            split change alone then starts from the shifted plan).
        rho_max: a ceiling on OSQP's step size ``rho`` that each matrix update (every full linearisation) starts
            the next QPs from: where the last QP's adaptation left ``rho`` above it, it is set to ``rho_max`` in the
            refactorisation the update makes anyway (generated solver; OSQP's Python interface factorises once more),
            else kept (None: always kept, OSQP's warm-start behaviour). OSQP still adapts it within each QP.
            Measured in docs/architecture.md, 'The wake of a reference change'.
        plain_qp_cap: OSQP iterations at most in each QP of a step that is neither a reference change nor a cold
            start (0: off, ``max_iter`` only): the iterate at the cap is taken (``SolveResult.extra["inexact"]``) and
            the next step's QP starts from it (the plan shifted, OSQP's multipliers and step size kept), so a QP's
            remaining convergence is carried into the next step as the real-time iteration carries the NLP's.
        plain_cap_run: with ``plain_qp_cap``, at most this many plain steps in a row with a QP stopped at the cap;
            the next plain step's QPs are then uncapped (``max_iter`` only); that step, a plain step whose QPs all end
            below the cap, a reference change and a cold start start the count again (0: no limit, every plain step
            capped).
        change_rho: OSQP's step size at a reference change (:mod:`.change_rho`): "off" (kept as the steps before left
            it), "last" (the value OSQP's adaptation reached in the first QP of the last change; the first change
            keeps it) or "kind" (so per kind of change: the supply-temperature reference up, down or unchanged); set
            with one refactorisation more in the change's step; "last_each" / "kind_each": so each QP of the change
            (the later ones in their relinearisation's refactorisation). Not with ``rho_reset`` on "change".
        change_rho_interval: OSQP's step size adapted every this many iterations in a change's QPs (0: off, OSQP's
            set-up interval); ``change_rho_tolerance``: where its estimate differs by more than this factor (0: OSQP's
            set-up tolerance, 5). OSQP's own estimate (from the QP's residuals) chooses the step size sooner; each
            adaptation refactorises. The generated solver only (OSQP's interface fixes both at set-up: there no
            effect). The steps after the change adapt as set up.
        change_rho_restore: the first preparation after a change sets OSQP's step size back to the value it had
            before the change (in the refactorisation the update makes anyway), so the steps after the change do not
            inherit the step size the change's QPs adapted to. Measured in docs/architecture.md, 'The change's step
            size'.
        change_rho_hold: a reference change's QPs after the first held, OSQP's adaptation off in them
            (:data:`.change_rho.HOLD_INTERVAL`; set back for the steps after the change), at the step size the first
            QP ended with ("end") or started with ("start", set in the second QP's relinearisation's refactorisation);
            "off": OSQP adapts them as set up. So the second QP's late raise is not made and the steps after the change
            start from the held value. The adaptation is switched off in the generated solver only (OSQP's interface
            fixes it at set-up: there "start" only sets the second QP's start, "end" is refused). Refused with
            ``rho_reset`` on "preparation" and with ``change_rho``'s "_each" modes (each sets the held QPs' step size;
            :func:`check_hold_with`). Measured in docs/architecture.md, 'The change's second QP held'.
        cap_retry_on_cold_start: with ``cap_retry_rho`` / ``cap_retry_share`` set, the QPs of a cold start (the first
            step after the solver is built or :meth:`reset`, which the controller calls after a failure too) are
            retried at the cap as the later steps' are (True); False: not retried there, the capped answer taken
            or failing as without the retry; the next step retries again. A cold start's QPs iterate from a guess
            (the command held over the horizon), and its retried answer can move the run to another operating point
            (docs/robustness.md sec. 2.44). Without a retry set it does nothing. The solver's own defaults keep the
            retry off (``cap_retry_rho`` 0, ``cap_retry_on_cold_start`` True); ``MpcController`` passes
            ``MpcSettings``' (3e-3, False since sec. 2.44).
    """

    def __init__(self, problem: TrackingProblem, *, eps: float = 1e-4, max_iter: int = 400,
                 sqp_max_iter: int = 1, sqp_tol: float = 1e-3, check_termination: int = 5,
                 lm_inputs: np.ndarray | float = 0.0, cold_start_qps: int = 1, reference_change_qps: int = 1,
                 codegen: bool = False, scaling: int = 10, alpha: float = 1.6, check_dualgap: bool = True,
                 first_pass_iter: int = 0, accept_max_iter: bool = False, step_fractions: tuple[float, ...] = (),
                 restart_duals_on_change: bool = False, osqp_codegen: bool = False, scaling_interval: int = 1,
                 steady_start: bool = False, steady_start_on: str = "any", relinearise_every: int = 1,
                 relinearise_move: float = 0.3, rho_reset: float | None = None, rho_reset_on: str = "preparation",
                 reweigh_in_place: bool = False, change_split_iter: int = 0,
                 split_every_step: bool = False, split_keeps_rho: bool = False, split_replays_change: bool = False,
                 rho_max: float | None = None, plain_qp_cap: int = 0, trust_radii: tuple[float, ...] = (),
                 plain_cap_run: int = 0, reversal_search: float = 0.0, reversal_wait_steps: int = 0,
                 reversal_repeat: bool = False, reversal_margin: float = 0.0, reversal_bound_only: bool = False,
                 reversal_second_qp: str = "off",
                 change_rho: str = "off", change_rho_restore: bool = False, change_rho_interval: int = 0,
                 change_rho_tolerance: float = 0.0, cap_retry_rho: float = 0.0, cap_retry_share: float = 0.0,
                 cap_retry_cold: bool = False, change_rho_hold: str = "off", valve_a_prox: float = 0.0,
                 cap_retry_on_cold_start: bool = True):
        self.pb = pb = problem
        self.valve_a_prox = check_prox("RtiOsqpSolver: valve_a_prox", valve_a_prox)
        self.valve_a_prox_on = False  # the last linearisation added the proximal term on valve a
        self.reversal_search = check_share("RtiOsqpSolver: reversal_search", reversal_search)
        self.reversal_wait_steps = check_wait("RtiOsqpSolver: reversal_wait_steps", reversal_wait_steps)
        check_flag("RtiOsqpSolver: reversal_repeat", reversal_repeat)  # the settings' one flag check
        self.reversal_repeat = reversal_repeat
        self.reversal_margin = check_share("RtiOsqpSolver: reversal_margin", reversal_margin, "the QP plan's cost")
        check_flag("RtiOsqpSolver: reversal_bound_only", reversal_bound_only)
        self.reversal_bound_only = reversal_bound_only
        self.reversal_second_qp = check_second_qp("RtiOsqpSolver: reversal_second_qp", reversal_second_qp)
        check_second_qp_with("RtiOsqpSolver: reversal_second_qp", self.reversal_second_qp, "reversal_search",
                             self.reversal_search,
                             int(sqp_max_iter) == 1 and not (split_every_step and change_split_iter),
                             f"sqp_max_iter = {sqp_max_iter!r} / split_every_step = {split_every_step!r} "
                             f"(change_split_iter = {change_split_iter!r})",
                             "sqp_max_iter 1 and split_every_step False with it")
        self.reversal_relinearised = False  # the last step took a second QP on a reversal
        self._quiet_run = 0  # plain one-QP steps in a row, the last included
        self._turned_before = np.zeros(0, dtype=int)  # the inputs the last step's plan turned
        self._last_move: np.ndarray | None = None  # the last steps' first moves beyond the share (scaled inputs)
        self.reversal_searched = self.reversal_taken = False  # the last step searched / took a candidate
        self.rho_max = _checked_step_size("rho_max", rho_max)
        self.plain_qp_cap = _checked_cap("plain_qp_cap", plain_qp_cap, max_iter)
        if isinstance(plain_cap_run, bool) or not isinstance(plain_cap_run, (int, np.integer)) or plain_cap_run < 0:
            raise ValueError(f"RtiOsqpSolver: plain_cap_run = {plain_cap_run!r}, allowed: 0 (no limit) or an integer >= 1")
        self.plain_cap_run = int(plain_cap_run)
        self._capped_run = 0  # plain steps in a row whose QP reached plain_qp_cap
        self._reached_cap = False  # the last _solve_qps had a QP stop at its cap
        self.change_split_iter = _checked_cap("change_split_iter", change_split_iter, max_iter)
        self.split_every_step = bool(split_every_step)
        self.split_keeps_rho = bool(split_keeps_rho)
        if not isinstance(split_replays_change, bool):
            raise ValueError(f"RtiOsqpSolver: split_replays_change = {split_replays_change!r}, allowed: True or False")
        if split_replays_change and self.split_keeps_rho:
            raise ValueError("RtiOsqpSolver: split_replays_change and split_keeps_rho both True; allowed: one of them "
                             "(the replay restores the step size with the whole workspace)")
        self.split_replays_change = split_replays_change
        self._held_adaptation: tuple[int, float] | None = None  # OSQP's adaptation while change_rho_hold holds it
        self._change_rest: dict | None = None  # what finish_change needs of a split change (None: none pending)
        if not isinstance(reweigh_in_place, bool):
            raise ValueError(f"RtiOsqpSolver: reweigh_in_place = {reweigh_in_place!r}, allowed: True or False")
        self.reweigh_in_place = reweigh_in_place
        self.rho_reset = _checked_step_size("rho_reset", rho_reset)
        if rho_reset_on not in RHO_RESET_ON:
            raise ValueError(f"RtiOsqpSolver: rho_reset_on = {rho_reset_on!r}, allowed: one of {list(RHO_RESET_ON)}")
        self.rho_reset_on = rho_reset_on
        check_change_rho("RtiOsqpSolver: change_rho", change_rho, change_rho_restore)
        if change_rho != "off" and self.rho_reset is not None and rho_reset_on == "change":
            raise ValueError("RtiOsqpSolver: change_rho and rho_reset with rho_reset_on='change' both set a change's "
                             "step size; allowed: one of them")
        self._change_rho = ChangeStepSize(change_rho, change_rho_restore)
        self.change_rho_interval, self.change_rho_tolerance = check_adaptation(
            "RtiOsqpSolver: change_rho_interval", change_rho_interval, change_rho_tolerance)
        self.change_rho_hold = check_hold("RtiOsqpSolver: change_rho_hold", change_rho_hold)
        if self.change_split_iter and (change_rho != "off" or change_rho_restore or self.change_rho_interval
                                       or change_rho_hold != "off"):
            raise ValueError("RtiOsqpSolver: change_rho / change_rho_restore / change_rho_interval / change_rho_hold "
                             "with change_split_iter: not supported; allowed: change_split_iter 0 with them")
        check_hold_with("RtiOsqpSolver: change_rho_hold", change_rho_hold, change_rho, rho_reset, rho_reset_on,
                         osqp_codegen)
        self.cap_retry_rho, self.cap_retry_share, self.cap_retry_cold = check_cap_retry(
            "RtiOsqpSolver: cap_retry", cap_retry_rho, cap_retry_share, cap_retry_cold)
        self._cap_retry_on = bool(self.cap_retry_rho or self.cap_retry_share)  # either form set
        check_flag("RtiOsqpSolver: cap_retry_on_cold_start", cap_retry_on_cold_start)
        self.cap_retry_on_cold_start = cap_retry_on_cold_start
        self.cap_retries: list[dict] = []  # the last step's retries at the cap: both solves' iterations, status, rho
        self.steady_start_on = check_steady_start_on("RtiOsqpSolver: steady_start_on", steady_start_on)
        if isinstance(relinearise_every, bool) or int(relinearise_every) != relinearise_every or relinearise_every < 1:
            raise ValueError(f"RtiOsqpSolver: relinearise_every = {relinearise_every!r}, allowed: an integer >= 1")
        if not 0.0 < float(relinearise_move) <= 10.0:
            raise ValueError(f"RtiOsqpSolver: relinearise_move = {relinearise_move!r}, allowed: (0, 10] (scaled units)")
        self._ml = MultiLevel(relinearise_every, relinearise_move) if relinearise_every != 1 else None
        self._vector_prepared = False  # the QP in OSQP is a vector step's (the matrices of an earlier point)
        self._osqp_codegen = bool(osqp_codegen)
        if isinstance(scaling_interval, bool) or int(scaling_interval) != scaling_interval or scaling_interval < 1:
            raise ValueError(f"RtiOsqpSolver: scaling_interval = {scaling_interval!r}, allowed: an integer >= 1")
        self.scaling_interval = int(scaling_interval)
        self.restart_duals_on_change = bool(restart_duals_on_change)
        # OSQP status values taken as an answer: solved, solved inaccurate (and maximum iterations reached)
        self._accepted = (1, 2, 7) if accept_max_iter else (1, 2)
        self._accepted_capped = (1, 2, 7)  # a capped QP (change_split_iter) takes its iterate at the cap
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
        self._p = np.array(pb.model.p_default, float)  # model parameters: an input of the QP data
        self._fused: dict[int, FusedPrediction] = {}  # per filter (id), its fused prediction (build_prediction)
        self._build_pattern()
        self._i0, self._w1, self._j = shift_maps(pb.t_nodes, pb.dt_s)
        self._j_slack = np.minimum(self._j, pb.N - 1)  # the slacks' shift (N of them), computed once
        self._build_qp_functions()
        self.codegen = CodegenReport()
        self.qp_codegen = CodegenReport()  # OSQP's generated solver (``outcomes["osqp"]``)
        wrap = (lambda f: compiled(f, self.codegen)) if codegen else (lambda f: f)
        # constant inputs filled once: P0, A0 and p of the QP data, q0, lm and w_du of the gradient
        self._qp_data = BufferedFunction(wrap(self.qp_data), fixed={4: self._P_const, 5: self._A_const, 6: self._p})
        self._qp_gradient = BufferedFunction(wrap(self.qp_gradient),
                                             fixed={7: self._q_const, 8: self._lm_all, 9: pb.w_du})
        self._sw_key = None
        self._merit = PlanMerit(pb, tuple(step_fractions), wrap) if step_fractions else None
        self.trust_radii = check_radii(trust_radii)
        self._trust_merit = (self._merit or PlanMerit(pb, TRUST_MERIT_FRACTIONS, wrap)) if self.trust_radii else None
        self._search_merit = PlanMerit(pb, TRUST_MERIT_FRACTIONS, wrap, several=3) if self.reversal_search else None
        self._trust_span = np.tile(pb.u_hi - pb.u_lo, (N, 1))  # each input's scaled range
        self.trust_taken: float = 1.0  # the radius of the last step's plan (1: the QP's own)
        self._steady = SteadyStart(pb, wrap) if steady_start else None
        if self._ml is not None:
            self._qp_vectors = BufferedFunction(wrap(vector_function(pb, pb.ny + 1, Y_POWER, Y_FLOW, U_BLOWER)),
                                                fixed={3: self._p})
        self.last_target: np.ndarray | None = None  # the steady-state target of the last change (scaled inputs)
        self._first_pass_iter = int(first_pass_iter)
        self.fail_next = 0  # steps to fail on purpose (tests of the fallback chain)
        self._osqp_settings = dict(eps_abs=eps, eps_rel=eps, max_iter=int(max_iter), polishing=False,
                                   warm_starting=True, adaptive_rho=True, verbose=False,
                                   check_termination=int(check_termination), scaling=int(scaling), alpha=float(alpha),
                                   check_dualgap=bool(check_dualgap))
        self._setup_osqp()
        self.reset()

    def set_osqp_options(self, **options) -> None:
        """Further OSQP settings by OSQP's own names (e.g. ``adaptive_rho_interval``, an iteration count) for
        the QPs that follow. OSQP's workspace is set up anew with them, so the solver answers from then on as
        one built with them and the next step starts cold (call it before the first step); a name OSQP does
        not know raises ValueError naming it."""
        known = {n for n in dir(self.solver.settings) if not n.startswith("_")}
        unknown = sorted(set(options) - known)
        if unknown:
            raise ValueError(f"RtiOsqpSolver.set_osqp_options: unknown OSQP setting(s) {unknown}; "
                             f"OSQP's settings are {sorted(known)}")
        self._osqp_settings.update(options)
        self._setup_osqp()
        self.X = self.U = self.S = None
        self._prepared = None

    @property
    def settings(self) -> dict:
        """The QP solver's settings and whether the QP data run as generated C (benchmark reports)."""
        return {"qp_solver": "osqp", **self._osqp_settings, "first_pass_iter": self._first_pass_iter,
                "restart_duals_on_change": self.restart_duals_on_change,
                "steady_start": self._steady is not None, "steady_start_on": self.steady_start_on,
                "accept_max_iter": 7 in self._accepted,
                "sqp_max_iter": self.sqp_max_iter,
                "reference_change_qps": self.reference_change_qps, "compiled": self.codegen.active,
                "osqp_generated": isinstance(self._core, osqp_embedded.EmbeddedOsqp),
                "scaling_interval": self.scaling_interval,
                "relinearise_every": self._ml.every if self._ml else 1,
                "relinearise_move": self._ml.move if self._ml else None, "rho_reset": self.rho_reset,
                "rho_reset_on": self.rho_reset_on, "reweigh_in_place": self.reweigh_in_place,
                "change_split_iter": self.change_split_iter, "split_every_step": self.split_every_step,
                "split_keeps_rho": self.split_keeps_rho, "split_replays_change": self.split_replays_change,
                "rho_max": self.rho_max, "plain_qp_cap": self.plain_qp_cap, "plain_cap_run": self.plain_cap_run,
                "change_rho": self._change_rho.mode, "change_rho_restore": self._change_rho.restore,
                "change_rho_interval": self.change_rho_interval, "change_rho_tolerance": self.change_rho_tolerance,
                "cap_retry_rho": self.cap_retry_rho, "cap_retry_share": self.cap_retry_share,
                "cap_retry_cold": self.cap_retry_cold, "cap_retry_on_cold_start": self.cap_retry_on_cold_start,
                "change_rho_hold": self.change_rho_hold,
                "reversal_second_qp": self.reversal_second_qp, "valve_a_prox": self.valve_a_prox,
                "step_fractions": list(self._merit.fractions) if self._merit else [],
                "trust_radii": list(self.trust_radii)}

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
        # the flap-closure term (Weights.flap_closure_per_pct2) on the flaps' diagonal, zero when off: entries of the
        # stage blocks already in the pattern, so the weight is a value of P0, not a change of the structure
        flap_h, self._flap_g = pb.flap_closure_hessian()
        const_r.append(u_all), const_c.append(u_all), const_v.append(flap_h.ravel())
        self._P_const_ids = P.add(np.concatenate(const_r), np.concatenate(const_c))
        self._P_const_vals = np.concatenate(const_v)
        P.finalise()
        self.P = P
        self._P_const = P.assemble(self._P_const_ids, self._P_const_vals)
        # the heater body's diagonal entries of stages 1..N (the heater readiness, mpc/readiness.py)
        j_body = int(np.flatnonzero((iu[0] == pb.i_heater) & (iu[1] == pb.i_heater))[0])
        self._P_body_slots = P.slot[self._P_var[1:, j_body]]
        self._i_body = (np.arange(1, N + 1) * nx + pb.i_heater)
        # valve a's diagonal entries of stages 0..N-1 (valve_a_prox; the terminal stage's block is u_{N-1}'s) and
        # their columns of the decision vector
        j_a = int(np.flatnonzero((iu[0] == nx + pb.i_valve_a) & (iu[1] == nx + pb.i_valve_a))[0])
        self._P_valve_a_slots = P.slot[self._P_var[:N, j_a]]
        self._i_valve_a = self.iu0 + np.arange(N) * nu + pb.i_valve_a
        self.readiness_target = None  # (scaled floor, weights of stages 1..N) while the readiness counts
        self._ready_q = None

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
        # contiguous rows as slices: a view each step where the index arrays copy
        self._r_dyn_rows, self._r_u_rows = slice(nx, rows), slice(rows, rows + N * nu)
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
        # flow floor while the heater is on, stages 0..N-1 (L/s): the flow's Jacobian row over x_k, u_k
        # (values from the QP data) and the heater command's slope of the floor (set per linearisation)
        self.r_floor = rows + np.arange(N if pb.floor else 0)
        self._floor_rows = slice(rows, rows + self.r_floor.size)  # the same rows as a slice (a cheaper assignment)
        rows += self.r_floor.size
        self.m = rows
        A.shape = (rows, n)
        self._A_var = A.add(dyn_r, dyn_c)  # values -[A_k B_k]
        self._A_floor = A.add(np.repeat(self.r_floor[:, None], nzs, axis=1), cols[:self.r_floor.size])
        c_ids = [A.add(r, c) for r, c, _ in entries_const]
        A.finalise()
        self.A = A
        self._A_const = A.assemble(np.concatenate([i.ravel() for i in c_ids]),
                                   np.concatenate([v for _, _, v in entries_const]))
        self._A_var_slots = A.slot[self._A_var.ravel()]
        self._A_floor_slots = A.slot[self._A_floor.ravel()]
        self._floor_heater_slots = A.slot[self._A_floor[:, nx + pb.i_heater_cmd]]

        # constant bounds
        self.l = np.zeros(rows)
        self.u = np.zeros(rows)
        rb = self._rate_bounds = pb.rate_bounds()
        self.l[self.r_rate] = -rb
        self.u[self.r_rate] = rb
        self.l[self.r_soft] = -np.inf
        self.u[self.r_soft] = pb.heater_row_bound
        self.l[self.r_slack] = 0.0
        self.u[self.r_slack] = np.inf
        self.l[self.r_ptc] = -np.inf
        self.u[self.r_ptc] = pb.ptc_row_bound
        self.l[self.r_floor] = -np.inf
        self.u[self.r_floor] = np.inf
        self.l[self.r_u] = pb.u_lo
        self.u[self.r_u] = pb.u_hi
        # constant part of the gradient: the slacks' L1 penalty
        self._q_const = np.zeros(n)
        self._q_const[self.is0:] = pb.slack_l1 * pb.dt
        self._q_const[self.iu0:self.is0] = self._flap_g.ravel()
        # with the value of the heat stored in the heater body (Weights.body_heat_power_w), linear in x_N, while
        # heating: the constant gradient with it, in place of _q_const as the gradient function's fixed input (_q)
        self._q_heating = self._q_const.copy()
        self._q_heating[N * nx + pb.i_heater] += pb.body_heat_coef
        self._q_body_on = False
        self._flap_key = None  # the reference's split and whether it is tracked, as the flaps' gradient last had them

    def _setup_osqp(self, build: bool = True) -> None:
        """OSQP's workspace set up afresh; ``build`` False: OSQP's generated solver only from the code cache."""
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
        inf = self.solver.constant("OSQP_INFTY")
        # OSQP's infinity in place of inf, as its Python interface would put it on every update
        np.clip(self.l, -inf, inf, out=self.l)
        np.clip(self.u, -inf, inf, out=self.u)
        self.solver.setup(self.P.matrix(Px), np.zeros(self.n), self.A.matrix(Ax), self.l.copy(), self.u.copy(),
                          **self._osqp_settings)
        self._core = self._make_core(build)
        self._zero_duals = np.zeros(self.m)
        self._workspace_used = False
        self._time_limit = None

    def _make_core(self, build: bool = True):
        """OSQP's generated solver of this set-up (:mod:`.osqp_embedded`) with ``osqp_codegen`` where it builds or
        loads, else OSQP's Python interface."""
        if self._osqp_codegen:
            core = osqp_embedded.load(self.solver, (self.P.indices, self.P.indptr, self.P.shape),
                                      (self.A.indices, self.A.indptr, self.A.shape), self._first_pass_iter,
                                      self.qp_codegen, self.scaling_interval, build=build)
            if core is not None:
                return core
        return _OsqpCore(self.solver, self._first_pass_iter)

    # ------------------------------------------------------------------ numerics
    def _build_qp_functions(self) -> None:
        """The QP data as two CasADi functions (generated C when ``codegen``, see :mod:`.codegen`).

        ``qp_data(X, U, d, SW, P0, A0, p) -> (Px, Ax, e_dyn, Gw2, c_base, y)`` linearises every stage
        at the model parameters ``p`` and returns the CSC values of P and A as OSQP stores them
        (``P0``, ``A0`` their constant parts);
        ``qp_gradient(Gw2, c_base, y, ref, dd, u_lin, u_prev, q0, lm, w_du) -> q`` the gradient for
        the reference, the disturbance-estimate change ``dd`` since the linearisation (mixed-air
        and flow offsets), the linearisation inputs and the last applied input. Weights enter as
        inputs (``SW``, ``P0``, ``A0``, ``q0``, ``lm``, ``w_du``), and so do the model parameters
        (``p``): the generated code depends on the model's structure (effects, discovered terms,
        valve tables, delay states), the horizon and the scaling only.
        """
        pb, N, nx, nu, ny = self.pb, self.pb.N, self.pb.nx, self.pb.nu, self.pb.ny
        nz, nr = self.nz_stage, ny + 1
        ntri = len(self._triu[0])
        stage_fns = {n: self._stage_qp_function(f) for n, f in pb.stages_p.items()}
        X = ca.MX.sym("X", nx, N + 1)
        U = ca.MX.sym("U", nu, N)
        d = ca.MX.sym("d", pb.nd)
        SW = ca.MX.sym("SW", nr, N + 1)
        P0 = ca.MX.sym("P0", self.P.nnz)
        A0 = ca.MX.sym("A0", self.A.nnz)
        p = ca.MX.sym("p", len(pb.model.p_default))
        Ue = ca.horzcat(U, U[:, N - 1])
        dt = np.append(pb.dt, pb.dt[-1])
        parts = [stage_fns[n].map(b - a, "serial")(X[:, a:b], Ue[:, a:b], d, ca.DM(dt[None, a:b]), SW[:, a:b], p)
                 for a, b, n in pb.groups]
        e_dyn = ca.horzcat(*[p[0] for p in parts])[:, :N]
        ab = ca.horzcat(*[p[1] for p in parts])[:, :N]
        htri = ca.horzcat(*[p[2] for p in parts])
        gw2 = ca.horzcat(*[p[3] for p in parts])
        c_base = ca.horzcat(*[p[4] for p in parts])
        y = ca.horzcat(*[p[5] for p in parts])
        m_p = _selection(self.P.slot[self._P_var.ravel()], self.P.nnz)
        m_a = _selection(self._A_var_slots, self.A.nnz)
        Px = P0 + ca.mtimes(m_p, ca.vec(htri))
        Ax = A0 + ca.mtimes(m_a, ca.vec(ab))
        n_f = self.r_floor.size
        floor_l = ca.MX(0, 1)
        if n_f:  # the flow's Jacobian rows of stages 0..N-1, in L/s
            g_flow = ca.horzcat(*[p[6] for p in parts])[:, :n_f]
            Ax += ca.mtimes(_selection(self._A_floor_slots, self.A.nnz), pb.floor_scale * ca.vec(g_flow))
            # the heater command's slope of the floor, and the rows' lower bound without the flow-offset
            # change (_floor_bounds adds it): flow = c_base + G z (the residual's constant part), so
            # G z - slope u >= floor - slope u_lin - c_base
            heater_u = U[pb.i_heater_cmd, :n_f].T
            value, slope = pb.floor_linearisation(heater_u)
            Ax += ca.mtimes(_selection(self._floor_heater_slots, self.A.nnz), -(pb.floor_scale * slope))
            floor_l = pb.floor_scale * (value - slope * heater_u - c_base[Y_FLOW, :n_f].T)
        # with multi-level steps also the slopes a vector step keeps (:mod:`.multilevel`): -[A B] and G per stage
        more = [ab, ca.horzcat(*[p[7] for p in parts])] if self._ml is not None else []
        self.qp_data = ca.Function("hvac_qp_data", [X, U, d, SW, P0, A0, p],
                                   [Px, Ax, ca.vec(e_dyn), gw2, c_base, y, floor_l, *more],
                                   ["X", "U", "d", "SW", "P0", "A0", "p"],
                                   ["Px", "Ax", "e_dyn", "Gw2", "c_base", "y", "floor_l", "AB", "G"][:7 + len(more)])
        self.qp_gradient = self._gradient_function()

    def _gradient_function(self) -> ca.Function:
        """``qp_gradient`` (:meth:`_build_qp_functions`): each stage's block 2 (W G)' c of the gradient from one SX
        function mapped over the N + 1 stages (a loop in the generated code), then the blocks put in place with the
        move and Levenberg-Marquardt terms by elementwise MX operations over vectors (loops too): a fifth of the C of
        the stages written out in one SX function, so less to fetch inside a step. Every value is the same
        operations in the same order as that function's (``tests/test_small_code.py``), so the same numbers to the
        bit."""
        pb, N, nx, nu, ny = self.pb, self.pb.N, self.pb.nx, self.pb.nu, self.pb.ny
        nz, nr = self.nz_stage, ny + 1
        g2 = ca.SX.sym("gw2", nr * nz)
        c_k = ca.SX.sym("c_base", nr)
        y_k = ca.SX.sym("y", ny)
        ref = ca.SX.sym("ref", ny)
        dd = ca.SX.sym("dd", 2)
        c = c_k - ca.vertcat(ref, 0)
        # disturbance estimates that moved since preparation enter the outputs additively: the
        # mixed-air offset adds to the supply temperature, the flow offset to the total flow
        # and, in proportion, to each outlet
        rows = [c[i] for i in range(nr)]
        rows[Y_TEMP] += (1.0 - pb.spec.temperature_sensor_share) * dd[0]
        rows[Y_FLOW] += dd[1]
        for i in Y_OUTLETS:
            rows[i] += dd[1] * y_k[i] / ca.fmax(y_k[Y_FLOW], 1e-6)
        block = ca.mtimes(ca.reshape(g2, nr, nz).T, ca.vertcat(*rows))
        stage = ca.Function("qp_gradient_stage", [g2, c_k, y_k, ref, dd], [block])
        G2 = ca.MX.sym("Gw2", nr * nz, N + 1)
        C, Y = ca.MX.sym("c_base", nr, N + 1), ca.MX.sym("y", ny, N + 1)
        ref_m, dd_m = ca.MX.sym("ref", ny), ca.MX.sym("dd", 2)
        u_lin, u_prev = ca.MX.sym("u_lin", N * nu), ca.MX.sym("u_prev", nu)
        q0, lm, w_du = ca.MX.sym("q0", self.n), ca.MX.sym("lm", N * nu), ca.MX.sym("w_du", nu)
        blocks = stage.map(N + 1, "serial")(G2, C, Y, ref_m, dd_m)
        # the blocks put in place (stage_cols, _build_pattern): x_k's block at x_k, u_k's at u_k, the terminal
        # stage's u-block added to u_{N-1}'s (after it, as the selection matrix's product added them); then the
        # Levenberg-Marquardt term on every u and the move term on u_0: each an elementwise operation over a vector
        q_x = q0[:self.iu0] + ca.vec(blocks[:nx, :])
        b_u = ca.horzcat(blocks[nx:, :N - 1], blocks[nx:, N - 1] + blocks[nx:, N])
        q_u = (q0[self.iu0:self.is0] + ca.vec(b_u)) + -2.0 * lm * u_lin
        q_u = ca.vertcat(q_u[:nu] + -2.0 * w_du * u_prev, q_u[nu:])
        return ca.Function("hvac_qp_gradient", [G2, C, Y, ref_m, dd_m, u_lin, u_prev, q0, lm, w_du],
                           [ca.vertcat(q_x, q_u, q0[self.is0:])],
                           ["Gw2", "c_base", "y", "ref", "dd", "u_lin", "u_prev", "q0", "lm", "w_du"], ["q"])

    def _stage_qp_function(self, stage: ca.Function) -> ca.Function:
        """One stage's QP data from the model's stage function: dynamics residual, -[A B] (row
        major), upper triangle of the Gauss-Newton Hessian, 2 W G, the residual's constant part
        and the outputs. The residual is the tracked outputs plus the electric power (blower plus
        heater) as one more least-squares row; ``sw`` holds the weights per residual."""
        pb, nx, nu, ny = self.pb, self.pb.nx, self.pb.nu, self.pb.ny
        x, u, d, dt = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("d", pb.nd), ca.SX.sym("dt")
        sw = ca.SX.sym("sw", ny + 1)
        p = ca.SX.sym("p", len(pb.model.p_default))
        out = stage(x, u, d, dt, p)
        sl = pb.out_slices
        xn = out[sl["xn"]]
        A = ca.reshape(out[sl["A"]], nx, nx)
        B = ca.reshape(out[sl["B"]], nx, nu)
        y = out[sl["y"]]
        G = ca.horzcat(ca.reshape(out[sl["C"]], ny, nx), ca.reshape(out[sl["D"]], ny, nu))
        g_e = G[Y_POWER, :] + ca.horzcat(ca.DM.zeros(1, nx), ca.DM(pb.energy_grad_u).T)
        y_e = y[Y_POWER] + u[U_BLOWER] * pb.u_sc[U_BLOWER] + pb.u_off[U_BLOWER]
        G = ca.vertcat(G, g_e)
        r = ca.vertcat(y, y_e)
        z = ca.vertcat(x, u)
        AB = ca.horzcat(A, B)
        gw2 = 2.0 * G * ca.repmat(sw, 1, self.nz_stage)
        H = ca.mtimes(G.T, gw2)
        htri = ca.vertcat(*[H[i, j] for i, j in zip(*self._triu)])
        outs = [xn - ca.mtimes(AB, z), ca.vec(-AB.T), htri, ca.vec(gw2), r - ca.mtimes(G, z), y, G[Y_FLOW, :].T]
        if self._ml is not None:
            outs.append(ca.vec(G))
        # common subexpressions computed once (the Jacobians repeat much of the model): about
        # 40 % fewer operations, the same values; found once per expression in a process (codegen.kept)
        args = [x, u, d, dt, sw, p]
        plain = ca.Function(f"qp_{stage.name()}", args, outs)
        return kept(f"stage qp {expression_key(plain)}", lambda: ca.Function(plain.name(), args, ca.cse(outs)))

    def _stage_weights(self, w_y: np.ndarray) -> np.ndarray:
        """Weights of the residuals per stage (N + 1, ny + 1): dt_k w_y / s^2, the terminal
        weight at stage N, and the energy weight (none at the terminal stage)."""
        pb, N = self.pb, self.pb.N
        stage_w = np.append(pb.dt, pb.terminal_s)
        sw = np.empty((N + 1, pb.ny + 1))
        sw[:, :pb.ny] = stage_w[:, None] * (w_y / pb.y_scale ** 2)[None, :]
        sw[:, pb.ny] = np.append(pb.dt, 0.0) * pb.energy_weight / pb.energy_scale_w ** 2
        return sw

    def _weights(self, w_y: np.ndarray) -> np.ndarray:
        """Stage weights for ``w_y``, computed again only when ``w_y`` changes."""
        key = w_y.tobytes()
        if key != self._sw_key:
            self._sw, self._sw_key = self._stage_weights(w_y), key
        return self._sw

    def _matrices(self, X, U, d, w_y):
        """Linearise at (X, U) and return P and A data plus the stage data for q and l/u."""
        return self._unpack(*self._qp_data(X, U, d, self._weights(w_y)))

    @staticmethod
    def _unpack(Px, Ax, e_dyn, gw2, c_base, y, floor_l, *slopes):
        """P and A data and the stage data of the QP data's outputs (with multi-level steps the slopes too)."""
        data = dict(e_dyn=e_dyn, gw2=gw2, c_base=c_base, y=y, floor_l=floor_l)
        if slopes:
            data["ab"], data["g"] = slopes
        return Px, Ax, data

    def use_prediction(self, ekf) -> None:
        """Fuse the estimator's time update with the QP data into one call of the preparation
        (:meth:`prepare_predicted`): the predicted state becomes the first node, its disturbance
        estimates the QP's ``d``. ``ekf`` is a :class:`~.estimator.DisturbanceEkf` (any state size);
        its functions in use (generated C or not) and ``qp_data`` in use are called inside one CasADi
        function, so the values are those of the two calls one after the other. A filter fused before
        (:meth:`build_prediction`) is bound again without a rebuild, its fixed inputs refreshed."""
        fused = self.build_prediction(ekf)
        self._predict_qp, self._i_p_qp = fused.qp, fused.i_p_qp
        self._predict_vec, self._i_p_vec = fused.vec, fused.i_p_vec
        for i, value in fused.fixed.items():
            self._predict_qp.set_fixed(i, value)
            if self._predict_vec is not None:
                self._predict_vec.set_fixed(i, value)
        self._ekf = ekf
        self.set_parameters(self._p)

    def build_prediction(self, ekf) -> "FusedPrediction":
        """The fused time update and QP data of ``ekf`` (:meth:`use_prediction`), built once per filter and
        kept, so binding another filter later costs no rebuild (1-1.5 ms of CasADi construction inside a
        step). Built again where the filter's time-update function in use has changed since."""
        predict, fixed = ekf.prediction_function()
        fused = self._fused.get(id(ekf))
        if fused is not None and fused.ekf is ekf and fused.predict is predict:
            fused.fixed = fixed
            return fused
        fused = self._fuse(ekf, predict, fixed)
        self._fused[id(ekf)] = fused
        return fused

    def _fuse(self, ekf, predict, fixed) -> "FusedPrediction":
        """Build the fused functions of :meth:`build_prediction`."""
        pb, N, nx = self.pb, self.pb.N, self.pb.nx
        args = predict.mx_in()
        z, sp = args[0], args[3]
        zn, Pn, air, flow = predict.call(args)
        # the scaling and the constant parts of P and A are inputs (fixed), not constants: the generated code of one
        # structure serves every parameter set and weight (:meth:`_compiled_calling`)
        x_off, x_sc = ca.MX.sym("x_off", nx), ca.MX.sym("x_sc", nx)
        P0, A0 = ca.MX.sym("P0", self._P_const.size), ca.MX.sym("A0", self._A_const.size)
        x0 = (ekf.model_state(zn) - x_off) / x_sc
        d = ekf.disturbance(zn, sp)
        X_last, U_last = ca.MX.sym("X_last", nx, N + 1), ca.MX.sym("U_last", pb.nu, N)
        u_prev, SW = ca.MX.sym("u_prev", pb.nu), ca.MX.sym("SW", pb.ny + 1, N + 1)
        p_qp = ca.MX.sym("p_qp", self._p.size)  # the QP's model parameters (set_parameters), not the filter's
        # the last solution shifted one sample along the stage grid, as shift_nodes does (the same
        # operations, so the same values): nodes 1..N, and the inputs with u_prev first
        i0, w1 = self._i0[1:], np.tile(self._w1[1:], (nx, 1))
        X1 = X_last[:, i0.tolist()] * ca.DM(1.0 - w1) + X_last[:, np.minimum(i0 + 1, N).tolist()] * ca.DM(w1)
        X, U = ca.horzcat(x0, X1), ca.horzcat(u_prev, U_last[:, self._j[1:].tolist()])
        data = self._qp_data.fn.call([X, U, d, SW, P0, A0, p_qp])
        fn = ca.Function(f"hvac_predict_qp_data_{ekf.name}", [*args, X_last, U_last, u_prev, SW, p_qp, x_off, x_sc, P0, A0],
                         [zn, Pn, air, flow, X, U, d, *data])
        fn = self._compiled_calling(fn, predict, self._qp_data.fn)
        i_p_qp = len(args) + 4
        constants = {i_p_qp + 1: pb.x_off, i_p_qp + 2: pb.x_sc, i_p_qp + 3: self._P_const, i_p_qp + 4: self._A_const}
        fused = FusedPrediction(ekf, predict, fixed, BufferedFunction(fn, fixed={**fixed, i_p_qp: self._p, **constants}),
                                i_p_qp)
        if self._ml is not None:  # the same with the vectors of a multi-level step in place of the QP data
            AB, G = ca.MX.sym("AB", *self._qp_vectors.fn.size_in(4)), ca.MX.sym("G", *self._qp_vectors.fn.size_in(5))
            uh = ca.MX.sym("uh", self.r_floor.size)
            vec = self._qp_vectors.fn.call([X, U, d, p_qp, AB, G, uh])
            fn = ca.Function("hvac_predict_qp_vectors", [*args, X_last, U_last, u_prev, p_qp, AB, G, uh, x_off, x_sc],
                             [zn, Pn, air, flow, X, U, d, *vec])
            fused.i_p_vec = len(args) + 3
            scaling = {fused.i_p_vec + 4: pb.x_off, fused.i_p_vec + 5: pb.x_sc}
            fused.vec = BufferedFunction(fn, fixed={**fixed, fused.i_p_vec: self._p, **scaling})
        return fused

    def _compiled_calling(self, fn: ca.Function, *called: ca.Function) -> ca.Function:
        """``fn`` as generated C linked against the generated functions it calls (:func:`~.codegen.compiled` with ``link``:
        the shift and the scaling in C, not in CasADi's MX virtual machine, about 10 us of a step), where every one of
        them runs as generated C loaded through this solver's code report; else ``fn`` (the same values)."""
        libraries = [self.codegen.libraries.get(f.name()) for f in called]
        if not all(f.class_name() == "External" for f in called) or None in libraries:
            return fn
        if not all(_same_signature(f, ca.external(f.name(), str(lib))) for f, lib in zip(called, libraries)):
            return fn  # the report's library of that name is another function's (names are not unique across reports)
        return compiled(fn, self.codegen, link=tuple(libraries))

    @property
    def fused_prediction(self) -> bool:
        """True when :meth:`prepare_predicted` can prepare the next QP now (a trajectory to shift)."""
        return getattr(self, "_predict_qp", None) is not None and self.X is not None

    def prepare_predicted(self, u_cmd: np.ndarray, setpoint_c: float, u_prev: np.ndarray, ref: np.ndarray,
                          w_y: np.ndarray) -> float:
        """The estimator's time update with the command ``u_cmd`` (physical) and :meth:`prepare` at
        its prediction, in one call (:meth:`use_prediction`). Returns the wall time (s)."""
        t0 = time.perf_counter()
        if self._ml is not None and not self._ml.due() and self._prepared is not None \
                and same_values(self._prepared["w_y"], w_y):
            self._prepare_vectors(u_cmd, setpoint_c, u_prev, ref, w_y)
            return time.perf_counter() - t0
        ekf = self._ekf
        # the buffers themselves (without multi-level steps, whose kept linearisation copies its own): the filter's
        # state and the plan are kept and copied here; the rest is read before the next call (the air and flow at
        # once, d copied by _write) or held only until the next preparation replaces it (P and A's values, the
        # stage data), the one that overwrites the buffers
        call = self._predict_qp.views if self._ml is None else self._predict_qp
        zn, Pt, air, flow, X, U, d, *data = call(
            ekf.z, ekf.P, u_cmd, setpoint_c, float(ekf.learning), self.X, self.U, u_prev, self._weights(w_y))
        if self._ml is None:
            zn, Pt, X, U = zn.copy(), Pt.copy(), X.copy(), U.copy()
        ekf.accept_prediction(zn, Pt, air, flow)
        S = self.S[self._j_slack]
        self.X, self.U, self.S = X, U, S
        self._write(X, U, S, d, ref, w_y, *self._unpack(*data))
        return time.perf_counter() - t0

    def _prepare_vectors(self, u_cmd, setpoint_c, u_prev, ref, w_y) -> None:
        """A multi-level preparation (:mod:`.multilevel`) after the estimator's time update: the QP's vectors at the
        shifted plan with the last full linearisation's slopes where the plan is near enough to it (a vector step:
        OSQP's matrices and factorisation kept), else a full linearisation there."""
        ekf, ml = self._ekf, self._ml
        zn, Pt, air, flow, X, U, d, e_dyn, c_base, y, floor_l = self._predict_vec(
            ekf.z, ekf.P, u_cmd, setpoint_c, float(ekf.learning), self.X, self.U, u_prev, ml.full["ab"],
            ml.full["g"], ml.full["U"][:self.r_floor.size, self.pb.i_heater_cmd])
        ekf.accept_prediction(zn, Pt, air, flow)
        S = self.S[self._j_slack]
        self.X, self.U, self.S = X, U, S
        if not ml.keeps(X, U, d, self._readiness_weights(X)):
            self._load(X, U, S, d, ref, w_y, u_prev)
            return
        ml.vector_step()
        gw2 = self._prepared["data"]["gw2"]  # the weights are those of the full linearisation (else it re-prepares)
        self._write_vectors(X, U, S, d, ref, w_y, dict(e_dyn=e_dyn, gw2=gw2, c_base=c_base, y=y, floor_l=floor_l))
        self._vector_prepared = True

    def reset(self) -> None:
        """Forget the trajectory and OSQP's workspace (cold start at the next step): a fresh
        workspace holds no multipliers, step size or factorisation of the run before, so a reset
        controller answers as a new one does."""
        self.X = self.U = self.S = None
        self._prepared = None
        self._change_rest = None
        self._capped_run = 0
        self._change_rho.forget()
        self._last_move, self._quiet_run, self._turned_before = None, 0, np.zeros(0, dtype=int)
        if self._ml is not None:
            self._ml.forget()
        if getattr(self, "_workspace_used", False):
            self._setup_osqp(build=False)  # a failure path inside a control step: the cache only, no compiler

    def set_parameters(self, p: np.ndarray) -> None:
        """Model parameters (``HvacModel.p_default`` order) of the next linearisations, e.g. with an
        estimated bypass-flow exponent (:class:`~.estimator.DisturbanceEkf`); no rebuild."""
        if self._ml is not None and not np.array_equal(self._p, p):
            self._ml.forget()  # other parameters, other slopes: the next preparation linearises in full
        self._p[...] = p
        self._qp_data.set_fixed(6, self._p)
        if getattr(self, "_predict_qp", None) is not None:
            self._predict_qp.set_fixed(self._i_p_qp, self._p)
        if self._ml is not None:
            self._qp_vectors.set_fixed(3, self._p)
            if getattr(self, "_predict_vec", None) is not None:
                self._predict_vec.set_fixed(self._i_p_vec, self._p)

    @property
    def clean(self) -> bool:
        """True when OSQP's workspace has not been used since it was set up (or reset)."""
        return not self._workspace_used

    @property
    def levels(self) -> dict[str, int]:
        """Preparations so far by kind with multi-level steps (:mod:`.multilevel`): ``full`` (new matrices, OSQP's
        refactorisation) and ``vector`` (the matrices kept); empty without them."""
        return dict(self._ml.counts) if self._ml is not None else {}

    @property
    def has_trajectory(self) -> bool:
        return self.X is not None

    def _shifted(self, x_first: np.ndarray):
        X = shift_nodes(self.X, self._i0, self._w1)
        X[0] = x_first
        U = self.U[self._j]
        S = self.S[self._j_slack]
        return X, U, S

    def _load(self, X, U, S, d, ref, w_y, u_prev) -> None:
        """Write the linearisation at (X, U) into OSQP (values only)."""
        Px, Ax, data = self._matrices(X, U, d, w_y)
        self._write(X, U, S, d, ref, w_y, Px, Ax, data)

    def _write(self, X, U, S, d, ref, w_y, Px, Ax, data) -> None:
        """Put a linearisation's values into OSQP and keep what the feedback needs (stage 0's flow-floor
        row coefficients among them)."""
        self._floor_a0 = Ax[self._A_floor_slots[:self.nz_stage]]
        Px = self._with_valve_a_prox(U, self._with_readiness(X, Px))
        restored = self._change_rho.after_change() if self._change_rho.restore else None
        if restored is not None:  # the first preparation after a change: the step size before it
            self._core.rho_next_update(restored)
        if self.rho_reset is not None and self.rho_reset_on == "preparation":
            self._core.rho_next_update(self.rho_reset)
        elif self.rho_max is not None:
            self._cap_rho()
        self._core.update_matrices(Px, Ax)
        self._written = (Px, Ax)
        self._workspace_used = True
        if self._ml is not None:
            self._ml.record_full(X, U, d, data["ab"], data["g"], self._readiness_weights(X))
        self._vector_prepared = False
        self._write_vectors(X, U, S, d, ref, w_y, data)

    def _write_vectors(self, X, U, S, d, ref, w_y, data) -> None:
        """The dynamics rows' bounds of a linearisation, and what the feedback needs of it."""
        self.l[self._r_dyn_rows] = self.u[self._r_dyn_rows] = data["e_dyn"]
        self._prepared = dict(data=data, d=d.copy(), w_y=w_y.copy(), ref=np.array(ref, float))
        self._z_lin = np.concatenate([X.ravel(), U.ravel(), S])

    def _with_readiness(self, X, Px):
        """``Px`` with the heater readiness (:mod:`.readiness`) on the stages where the plan ``X`` linearised at
        has the body below the floor: ``w (x - x_f)^2`` there (Hessian ``2 w``, gradient ``-2 w x_f``, kept for
        :meth:`_q`); ``Px`` itself when off."""
        self._ready_q = None
        active = self._readiness_weights(X)
        if active is None:
            return Px
        Px = np.array(Px, float)
        Px[self._P_body_slots] += 2.0 * active
        self._ready_q = -2.0 * active * self.readiness_target[0]
        return Px

    def _with_valve_a_prox(self, U, Px):
        """``Px`` with ``valve_a_prox`` on valve a's diagonal (Hessian ``2 w`` at every stage; the gradient's
        ``-2 w u_lin`` added in :meth:`_q`) where the plan ``U`` linearised at starts with the heater command at its
        upper bound; ``Px`` itself otherwise (and when off)."""
        self.valve_a_prox_on = False
        if not self.valve_a_prox:
            return Px
        ih = self.pb.i_heater_cmd
        self.valve_a_prox_on = at_upper_bound(U, self.pb.u_hi, ih, float(self.pb.u_hi[ih] - self.pb.u_lo[ih]))
        if not self.valve_a_prox_on:
            return Px
        Px = np.array(Px, float)
        Px[self._P_valve_a_slots] += 2.0 * self.valve_a_prox
        return Px

    def _readiness_weights(self, X) -> np.ndarray | None:
        """The heater readiness's weights of stages 1..N at the plan ``X`` (zero where the body is above the
        floor); None where it does not count (off, or no stage below the floor)."""
        target = self.readiness_target
        if target is None:
            return None
        x_f, w = target
        active = np.where(X[1:, self.pb.i_heater] < x_f, w, 0.0)
        return active if active.any() else None

    def _floor_bounds(self, d: np.ndarray, x0: np.ndarray, u_lo: np.ndarray, u_hi: np.ndarray) -> None:
        """Lower bounds of the floor rows with the flow offset's change since the linearisation. Stage 0's
        row asks no more than its first move can reach within that move's bounds (``u_lo[0]``, ``u_hi[0]``:
        the rate limits from the command in force) from the estimate ``x0``, less FLOOR_TOLERANCE_LS,
        where that is below the floor (after a fallback, say); the rows of stage 1 on hold it in full."""
        if self.r_floor.size:
            dd = d[D_OFFSETS[1]] - self._prepared["d"][D_OFFSETS[1]]
            rows = self._floor_rows
            self.l[rows] = self._prepared["data"]["floor_l"] - self.pb.floor_scale * dd
            a_x, a_u = self._floor_a0[:self.pb.nx], self._floor_a0[self.pb.nx:]
            lo, hi = u_lo[0], u_hi[0]
            most = float(a_x @ x0 + sum_reduce(np.maximum(a_u * lo, a_u * hi), axis=None))  # ndarray.sum's reduction
            first = rows.start
            self.l[first] = min(self.l[first], most - FLOOR_TOLERANCE_LS)

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

    def _reweigh(self, x0: np.ndarray, u_prev: np.ndarray, d: np.ndarray, ref: np.ndarray, w_y: np.ndarray) -> float:
        """The prepared QP linearised again at its plan, which the preparation has already shifted (shifting it
        again would put the plan a sample ahead), with the reference ``ref`` and output weights ``w_y``, the first
        node at ``x0`` and the first input at ``u_prev`` as :meth:`prepare` takes them. Returns its wall time (s)."""
        t0 = time.perf_counter()
        self.X[0] = x0
        self.U[0] = u_prev
        self._load(self.X, self.U, self.S, d, ref, w_y, u_prev)
        return time.perf_counter() - t0

    def rebase(self, x_first: np.ndarray, d: np.ndarray) -> float:
        """The prepared QP linearised again at its (already shifted) plan with another first node ``x_first``
        (scaled) and disturbances ``d`` (physical), as :meth:`prepare` takes them, its reference, weights and
        OSQP's warm start kept: another estimator's prediction of the same sample (a switch of filter) without
        a cold start. Does nothing without a prepared QP. Returns its wall time (s)."""
        if self.X is None or self._prepared is None:
            return 0.0
        return self._reweigh(x_first, self.U[0].copy(), d, self._prepared["ref"], self._prepared["w_y"])

    def _initialise(self, x0, u_prev, d) -> None:
        pb = self.pb
        self.X = pb.rollout(x0, u_prev, d)
        self.U = np.tile(u_prev, (pb.N, 1))
        self.S = np.zeros(pb.N)

    def feedback(self, x0: np.ndarray, u_prev: np.ndarray, d: np.ndarray, ref: np.ndarray, w_y: np.ndarray,
                 u_lo: np.ndarray, u_hi: np.ndarray, time_limit_s: float = 0.0,
                 u_hi_binding: np.ndarray | None = None) -> SolveResult:
        """Feedback phase: insert the estimate and bounds, solve (and iterate in SQP mode).

        ``u_hi_binding`` (scaled, the shape of ``u_hi``; None: not used): tighter upper bounds that enter the QPs
        only where they bind. The step's QPs are solved with ``u_hi``; only where the answer's first stage exceeds
        ``u_hi_binding`` by more than OSQP's absolute tolerance in some input it bounds tighter than ``u_hi``, the
        solver's state is set back to what the step's QPs started from (:meth:`_save_step`, the reversal search's
        memory, the step-size schedule) and the QPs are solved again with ``u_hi_binding`` (``extra["binding_solved_again"]`` True; the iterations and QP solves of
        both passes counted). So a step where they do not bind is the step without them to the bit, and a step
        where they bind is the step with them from the start (the generated OSQP's restore is exact; OSQP's
        Python interface restores the multipliers rescaled, :meth:`_Core.save_state`). ASSUMPTION: a first move
        beyond the bound by less than ``eps`` (scaled) is what the QP with the bound may answer as well, so not
        solved again (the caller's projection cuts it)."""
        t0 = time.perf_counter()
        prep = 0.0
        cold = self.X is None
        self.cap_retries = []  # this step's retries at the cap (all its QPs': a second QP's added to the first's)
        max_qps = max(self.sqp_max_iter, self.cold_start_qps) if cold else self.sqp_max_iter
        changed = self._prepared is not None and not same_values(self._prepared["ref"], ref)
        old_ref = self._prepared["ref"] if changed else None
        if changed:
            max_qps = max(max_qps, self.reference_change_qps)
        started = False
        if changed and self._steady is not None and starts_at_target(self.steady_start_on, self._prepared["ref"], ref):
            prep, started = self._start_steady(x0, u_prev, d, ref, w_y, u_lo, u_hi)
        reweigh = not started and self._prepared is not None and not same_values(self._prepared["w_y"], w_y)
        if reweigh and self.reweigh_in_place:
            prep += self._reweigh(x0, u_prev, d, ref, w_y)
        elif not started and (self._prepared is None or reweigh):
            prep += self.prepare(x0, u_prev, d, ref, w_y)
        elif not started and changed and self._vector_prepared:  # a change linearises in full at the prepared point
            prep += self._relinearise(self._z_lin, self._z_lin[:self.pb.nx], self._prepared["d"], ref, w_y, u_prev)
        self.reversal_searched = self.reversal_taken = self.reversal_relinearised = False
        if self.fail_next > 0:
            self.fail_next -= 1
            return SolveResult(False, "forced failure", prep_time_s=prep,
                               feedback_time_s=time.perf_counter() - t0 - prep)
        if changed and self._change_rho.active:  # (the value before the change noted before any reset)
            start_rho = self._change_rho.at_change(self._core.rho, old_ref, ref)
            prep += 0.0 if start_rho is None else self._reset_rho(start_rho)
        if changed and self.rho_reset is not None and self.rho_reset_on == "change":
            prep += self._reset_rho(self.rho_reset)
        def run(hi: np.ndarray):  # the step's QPs with the upper bounds hi
            return self._feedback_qps(x0, u_prev, d, ref, w_y, u_lo, hi, t0, time_limit_s, changed, cold, max_qps)

        before = self._save_pass() if u_hi_binding is not None else None
        z, status, iterations, solves, qp_prep, inexact, fraction, split, rho, saved = run(u_hi)
        bound = before is not None and z is not None and self._exceeds(z, u_hi, u_hi_binding)
        if bound:  # the pass without the tighter bounds set aside: the QPs again with them from the same state
            self._restore_pass(before)
            z, status, it2, solves2, qp_prep2, inexact, fraction, split, rho, saved = run(u_hi_binding)
            iterations, solves, qp_prep = iterations + it2, solves + solves2, qp_prep + qp_prep2
            u_hi = u_hi_binding
        prep += qp_prep
        feedback = time.perf_counter() - t0 - prep
        result = self._result(z, status, iterations, solves, prep, feedback, cold, inexact, fraction)
        if u_hi_binding is not None:
            result.extra["binding_solved_again"] = bound
        plain = not (split or changed or cold)
        self._capped_run = self._capped_run + 1 if plain and self._reached_cap else 0
        if split and result.ok and (changed or inexact):
            self._change_rest = dict(x0=x0.copy(), u_prev=u_prev.copy(), d=d.copy(), ref=np.array(ref, float),
                                     w_y=w_y.copy(), u_lo=u_lo.copy(), u_hi=u_hi.copy(), z=z.copy(),
                                     qps=max(self.sqp_max_iter, self.reference_change_qps), solved=not inexact,
                                     rho=rho, saved=saved, max_qps=max_qps,
                                     restart=changed and self.restart_duals_on_change)
            result.extra["change_split"] = True
        return result

    def _exceeds(self, z: np.ndarray, u_hi: np.ndarray, u_hi_binding: np.ndarray) -> bool:
        """True where the answer ``z``'s first stage exceeds the scaled upper bounds ``u_hi_binding``'s first row by more
        than OSQP's absolute tolerance in some input where that bound is below the QP's own (``u_hi``; where they are
        the same the QP had the bound already)."""
        first, tighter = z[self.iu0:self.iu0 + self.pb.nu], u_hi_binding[0] < u_hi[0]
        return bool(np.any(tighter & (first > u_hi_binding[0] + self._osqp_settings["eps_abs"])))

    def _save_pass(self) -> dict:
        """What :meth:`_feedback_qps` changes, for :meth:`_restore_pass`: :meth:`_save_step`'s state, the reversal
        search's memory and the step-size schedule of a change."""
        return {"step": self._save_step(), "search": (self._last_move, self._quiet_run, self._turned_before),
                "change_rho": copy.deepcopy(self._change_rho)}

    def _restore_pass(self, saved: dict) -> None:
        """The state :meth:`_save_pass` saved, put back (the retries at the cap of the pass set aside kept in the
        step's list: they were made)."""
        self._restore_step(saved["step"])
        self._last_move, self._quiet_run, self._turned_before = saved["search"]
        self._change_rho = copy.deepcopy(saved["change_rho"])
        self.reversal_searched = self.reversal_taken = self.reversal_relinearised = False

    def _feedback_qps(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, t0, time_limit_s, changed, cold, max_qps):
        """:meth:`feedback`'s QPs with the bounds ``u_lo``, ``u_hi`` (its arguments; ``changed``, ``cold``: a
        reference change's, a cold start's step; ``max_qps`` the QPs allowed): the answer, status, iterations, QP
        solves, the relinearisations' time (s), whether inexact, the globalised fraction, and for a split change
        whether split, the step size before it and the state saved for its replay."""
        nx = self.pb.nx
        prep = 0.0
        self.l[:nx] = self.u[:nx] = x0  # rows r_x0
        self.l[self._r_u_rows] = u_lo.ravel()
        self.u[self._r_u_rows] = u_hi.ravel()
        # a change's QPs capped (with split_every_step any step's); finish_change goes on
        split = (changed or self.split_every_step) and not cold and self.change_split_iter > 0
        # OSQP's step size before the capped QPs, for finish_change to restore (split_keeps_rho only)
        rho = self._core.rho if split and self.split_keeps_rho else None
        # the step's state before the capped QPs, for finish_change to solve them again (split_replays_change only)
        saved = self._save_step() if split and self.split_replays_change else None
        adaptation = self._change_adaptation() if changed and self.change_rho_interval else None
        try:
            z, status, iterations, solves, qp_prep, inexact, fraction = self._solve_qps(
                x0, u_prev, d, ref, w_y, u_lo, u_hi, max_qps, restart=changed and self.restart_duals_on_change,
                t0=t0, time_limit_s=time_limit_s, cap=self._qp_cap(split, changed, cold), trust=not cold,
                hold=self.change_rho_hold if changed else "off", retry=self.cap_retry_on_cold_start or not cold)
        finally:  # OSQP's own adaptation again for the steps after the change
            if adaptation is not None:
                self._core.set_rho_adaptation(*adaptation)
        prep += qp_prep
        if changed and self._change_rho.active:
            self._change_rho.close_change()
        plain = not (split or changed or cold)  # a change's or a cold start's QPs break the run
        if plain and max_qps == 1 and z is not None and self._reverses_at_bound(z, u_prev):
            z_lin = self._z_lin.copy()  # the search's linearisation point stays the step's own
            reached = self._reached_cap
            z2, status2, it2, solves2, prep2, inexact2, fraction2 = self._solve_qps(
                x0, u_prev, d, ref, w_y, u_lo, u_hi, 1, t0=t0, time_limit_s=time_limit_s,
                cap=self._qp_cap(split, changed, cold), trust=True, at=z)
            iterations, solves, prep = iterations + it2, solves + solves2, prep + prep2
            if z2 is not None and z2 is not z:  # (``z`` back: the deadline came before the second QP)
                z, status, inexact, fraction = z2, status2, inexact2, min(fraction, fraction2)
                self.reversal_relinearised = True
            self._z_lin, self._reached_cap = z_lin, reached or self._reached_cap
        if self._search_merit is not None:
            z = self._searched(z, x0, d, ref, w_y, u_prev, u_lo, u_hi, plain and max_qps == 1)
        return z, status, iterations, solves, prep, inexact, fraction, split, rho, saved

    def _solve_qps(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, max_qps: int, *, restart: bool = False, t0: float = 0.0,
                   time_limit_s: float = 0.0, cap: int = 0, start: np.ndarray | None = None, trust: bool = True,
                   hold: str = "off", at: np.ndarray | None = None, retry: bool = True):
        """Up to ``max_qps`` QPs (Gauss-Newton SQP to ``sqp_tol``) with the prepared data: the first warm-started from
        ``start`` (default: the linearisation point; the multipliers OSQP's, zero with ``restart``); with ``cap`` > 0,
        each QP at most ``cap`` OSQP iterations, its iterate at the cap taken; ``trust``: the trust region applies (where
        radii are set; not on a cold start). Returns the answer (None: failed), status,
        iterations, QP solves, the relinearisations' time (s), whether the answer is an iterate at a cap, and the
        smallest globalised step fraction. ``hold``: the QPs after the first without OSQP's step-size adaptation,
        at the first QP's step size at its end or start (``change_rho_hold``'s mode; the adaptation in force set back
        after them). ``at``: the first QP linearised at that plan (a further Gauss-Newton QP). ``retry``: a QP at
        OSQP's cap is retried where a retry is set (False: not, ``cap_retry_on_cold_start`` off on a cold start)."""
        try:
            return self._qp_run(x0, u_prev, d, ref, w_y, u_lo, u_hi, max_qps, restart, t0, time_limit_s, cap, start,
                                trust, hold, at, retry)
        finally:  # OSQP's own adaptation again for the steps after
            if self._held_adaptation is not None:
                self._core.set_rho_adaptation(*self._held_adaptation)
                self._held_adaptation = None

    def _hold_rho(self) -> None:
        """OSQP's step-size adaptation off from the next QP on (``change_rho_hold``: the interval beyond any QP's
        iterations), the adaptation in force kept in ``_held_adaptation`` for :meth:`_solve_qps` to set back."""
        before = self._core.rho_adaptation
        if self._core.set_rho_adaptation(HOLD_INTERVAL, before[1]):
            self._held_adaptation = before

    def _qp_run(self, x0, u_prev, d, ref, w_y, u_lo, u_hi, max_qps, restart, t0, time_limit_s, cap, start, trust,
                hold, at, retry_set):
        """:meth:`_solve_qps`'s QPs (its arguments; ``hold``: :meth:`_hold_rho` before the second QP)."""
        rho_first = self._core.rho if hold == "start" else None  # the step size the first QP starts from
        iterations = 0
        solves = 0
        status = "unsolved"
        inexact = False
        fraction = 1.0
        prep = 0.0
        self._reached_cap = False
        self.trust_taken = 1.0  # the QP's own plan until the trust region takes a radius
        z = at  # with ``at``: the first QP linearised at that plan (a further Gauss-Newton QP)
        for it in range(max_qps):
            if it > 0 or at is not None:
                if hold != "off" and it == 1:
                    self._hold_rho()
                rho_next = self._change_rho.for_qp(it) if rho_first is None else rho_first
                if rho_next is not None:  # taken in by the relinearisation's refactorisation
                    self._core.rho_next_update(rho_next)
                prep += self._relinearise(z, x0, d, ref, w_y, u_prev)
            q = self._q(ref, d, u_prev)
            self._floor_bounds(d, x0, u_lo, u_hi)
            self._core.update_vectors(q, self.l, self.u)
            # primal: the shifted plan; dual: OSQP keeps the last QP's multipliers in its workspace
            # (measured on the solve-time loop when this was chosen: 5935 OSQP iterations in 240
            # steps, against 7585 with the multipliers shifted like the plan and 7790 with zero
            # multipliers; 6225 with the model parameters as inputs of the generated code, whose
            # round-off moves the loop from step ~124 on)
            first = it == 0 and start is not None
            self._core.warm_start(start if first else self._z_lin,
                                  self._zero_duals if (it == 0 and restart) else None)
            if not self._time_left(t0, time_limit_s):
                status = "deadline"
                break
            capped = cap > 0
            retry = not capped and self._cap_retry_on and retry_set
            rho_start = self._core.rho if retry else 0.0
            status_val, status, n_iter, x = self._core.solve_capped(cap) if capped else self._core.solve()
            solves += 1
            iterations += n_iter
            # at OSQP's cap and not solved to its tolerance (inexact or at the cap)
            if retry and status_val != 1 and n_iter >= self._osqp_settings["max_iter"]:
                (status_val, status, n_iter, x), again, retry_prep = self._retry_at_cap(
                    (status_val, status, n_iter, x), rho_start, t0, time_limit_s)
                solves += again > 0
                iterations += again
                prep += retry_prep
            if self._change_rho.mode != "off":
                self._change_rho.note(it, self._core.rho)  # (a change's QPs only: nothing pending otherwise)
            self._reached_cap = self._reached_cap or (capped and n_iter >= cap)
            status = str(status)
            if status_val not in (self._accepted_capped if capped else self._accepted):
                z = None
                break
            z = x if self._core.fresh_solution else np.array(x)  # the generated solver's is the step's own already
            inexact = status_val == 7  # taken at the cap without meeting even OSQP's inaccurate tolerance
            if not all_finite(z):
                status = "non-finite solution"
                z = None
                break
            if self._trust_merit is not None and trust:
                z, again = self._trusted(z, x0, d, ref, w_y, u_prev, u_lo, u_hi)
                solves += again
            if self._merit is not None:
                z, taken = self._globalised(z, x0, d, ref, w_y, u_prev)
                fraction = min(fraction, taken)
            if it + 1 < max_qps and float(np.abs(z - self._z_lin).max()) < self.sqp_tol:
                break
        return z, status, iterations, solves, prep, inexact, fraction

    def _retry_at_cap(self, first: tuple, rho_start: float, t0: float, time_limit_s: float) -> tuple[tuple, int, float]:
        """A QP that reached OSQP's ``max_iter`` solved once more (``cap_retry_rho`` / ``cap_retry_share``): OSQP's step
        size set to ``cap_retry_rho``, or to ``cap_retry_share`` times ``rho_start`` (the value the QP started from),
        the matrices written again with it (one refactorisation), and OSQP warm-started from the capped iterate (its
        multipliers kept) or, with ``cap_retry_cold``, from the linearisation point with zero multipliers. ``first``:
        the capped solve's (status value, status, iterations, primal iterate), not solved to OSQP's tolerance (the
        caller retries only then: "solved inaccurate" or "maximum iterations reached"). Returns the solve taken: the
        retry's where it is solved, or where it is an answer and the capped one is not; else the capped one's; the
        retry's iterations (0: none, no time left before or after the refactorisation) and the wall time (s) of its
        refactorisations. Within the step's time limit where one is set. Where the capped solve's is taken, OSQP's
        workspace is set back to its state before the retry (``save_state`` / ``restore_state``: step size, matrices,
        multipliers; one refactorisation more), so the steps after, and ``change_rho``'s note of the step size, find
        OSQP as the capped solve left it."""
        if not self._time_left(t0, time_limit_s):
            return first, 0, 0.0
        saved = self._core.save_state()
        rho = self.cap_retry_rho if self.cap_retry_rho > 0 else self.cap_retry_share * rho_start
        prep = self._reset_rho(rho)
        again = None
        if self._time_left(t0, time_limit_s):  # (the refactorisation's time counted: checked again after it)
            if self.cap_retry_cold:
                self._core.warm_start(self._z_lin, self._zero_duals)
            else:
                self._core.warm_start(np.array(first[3], float))
            again = self._core.solve()
        self.cap_retries.append({"iterations": (first[2], 0 if again is None else again[2]),
                                 "status": (str(first[1]), "deadline" if again is None else str(again[1])),
                                 "rho": (rho_start, rho)})
        if again is not None and (again[0] == 1 or (again[0] in self._accepted and first[0] not in self._accepted)):
            return again, again[2], prep
        t1 = time.perf_counter()
        self._core.restore_state(saved)
        return first, 0 if again is None else again[2], prep + time.perf_counter() - t1

    def _result(self, z, status, iterations, solves, prep, feedback, cold, inexact, fraction) -> SolveResult:
        """The answer ``z`` as the solver's plan and a :class:`SolveResult` (a failure where ``z`` is None); with the
        retry at the cap set, ``extra["cap_retries"]``: the retries of the step (or of finish_change's rest)."""
        N, nx, nu = self.pb.N, self.pb.nx, self.pb.nu
        retries = {"cap_retries": len(self.cap_retries)} if self._cap_retry_on else {}
        if z is None:
            return SolveResult(False, status, iterations=iterations, qp_solves=solves, prep_time_s=prep,
                               feedback_time_s=feedback, extra={"cold_start": cold, **retries})
        X = z[:(N + 1) * nx].reshape(N + 1, nx)
        U = z[self.iu0:self.is0].reshape(N, nu)
        S = z[self.is0:]
        self.X, self.U, self.S = X, U, S
        return SolveResult(True, status, X=X.copy(), U=U.copy(), S=S.copy(), iterations=iterations,
                           qp_solves=solves, prep_time_s=prep, feedback_time_s=feedback,
                           extra={"cold_start": cold, "inexact": inexact, "step_fraction": fraction, **retries})

    @property
    def change_pending(self) -> bool:
        """True between a step that solved a reference change's QPs capped (``change_split_iter``) and
        :meth:`finish_change`."""
        return self._change_rest is not None

    def finish_change(self) -> SolveResult:
        """The rest of a reference change split by ``change_split_iter``: the step's last QP continued from its
        iterate at the cap (the same data; OSQP's multipliers and step size as the capped solve left them) to
        OSQP's tolerance, then up to ``reference_change_qps`` - 1 further QPs (Gauss-Newton, relinearised at each
        answer, to ``sqp_tol``) from the same state, reference and bounds. Its plan
        becomes the solver's (the next preparation shifts it, OSQP's multipliers stay in its workspace). Meant to
        run after the step, before the next preparation (the controller's second thread). With ``split_keeps_rho``
        OSQP's step size ``rho`` is set back to the value it had before the step's capped QPs (the rest's first QP,
        continued from a capped iterate, may adapt it, and OSQP holds a step size until a later QP moves it by its
        factor of 5: docs/architecture.md, 'The rest of a split change, traced'). Returns the answer (a failure
        where there is no change to finish or a QP fails: the caller then resets the solver)."""
        rest, self._change_rest = self._change_rest, None
        t0 = time.perf_counter()
        self.cap_retries = []  # the rest's retries at the cap
        if rest is None:
            return SolveResult(False, "no change to finish")
        try:
            return self._finish(rest, t0)
        finally:  # OSQP's step size as the step found it: the next matrix update (the preparation) takes it in
            if self.split_keeps_rho:
                self._core.rho_next_update(rest["rho"])

    def _finish(self, rest: dict, t0: float) -> SolveResult:
        """:meth:`finish_change`'s QPs (``rest``: what the step left for them; ``t0``: its start, perf_counter s)."""
        if self._time_limit is not None:  # the step's wall-clock limit must not bound the rest: a budget of one step
            self._core.set_time_limit(NO_TIME_LIMIT_S)
            self._time_limit = None
        x0, u_prev, d, ref, w_y = (rest[k] for k in ("x0", "u_prev", "d", "ref", "w_y"))
        args = (x0, u_prev, d, ref, w_y, rest["u_lo"], rest["u_hi"])
        if rest["saved"] is not None:
            return self._replay(rest, args, t0)
        qps, z, prep = rest["qps"], rest["z"], 0.0
        if rest["solved"]:  # the first QP met OSQP's tolerance within the cap: on from its answer
            if qps == 1 or float(np.abs(z - self._z_lin).max()) < self.sqp_tol:
                return self._result(z, "solved", 0, 0, 0.0, time.perf_counter() - t0, False, False, 1.0)
            prep = self._relinearise(z, x0, d, ref, w_y, u_prev)
            qps, z = qps - 1, None
        z, status, iterations, solves, qp_prep, inexact, fraction = self._solve_qps(*args, qps, start=z)
        prep += qp_prep
        return self._result(z, status, iterations, solves, prep, time.perf_counter() - t0 - prep, False, inexact,
                            fraction)

    def _save_step(self) -> dict:
        """What :meth:`_replay` restores: OSQP's workspace (``save_state``) and the prepared QP as the feedback found
        it before its QPs (the linearisation and its bounds; the relinearisations of the QPs replace, not change,
        these objects, so references are kept and the two bound arrays copied)."""
        return {"core": self._core.save_state(), "l": self.l.copy(), "u": self.u.copy(),
                "prepared": self._prepared, "z_lin": self._z_lin, "floor_a0": self._floor_a0,
                "written": self._written, "ready_q": self._ready_q, "vector_prepared": self._vector_prepared,
                "valve_a_prox_on": self.valve_a_prox_on, "ml": copy.deepcopy(self._ml)}

    def _restore_step(self, saved: dict) -> None:
        """The state :meth:`_save_step` saved, put back (OSQP's workspace, the prepared QP, its bounds, and whether
        its P carries the proximal term on valve a, so the gradient :meth:`_q` builds agrees with it)."""
        self._core.restore_state(saved["core"])
        self.l[...] = saved["l"]
        self.u[...] = saved["u"]
        self._prepared, self._z_lin, self._floor_a0 = saved["prepared"], saved["z_lin"], saved["floor_a0"]
        self._written, self._ready_q = saved["written"], saved["ready_q"]
        self.valve_a_prox_on = saved["valve_a_prox_on"]
        self._vector_prepared, self._ml = saved["vector_prepared"], saved["ml"]

    def _replay(self, rest: dict, args: tuple, t0: float) -> SolveResult:
        """:meth:`finish_change` with ``split_replays_change``: the step's state before its capped QPs restored, then
        its QPs solved as the unsplit feedback solves them (the same calls, no cap, no time limit)."""
        self._restore_step(rest["saved"])
        z, status, iterations, solves, prep, inexact, fraction = self._solve_qps(
            *args, rest["max_qps"], restart=rest["restart"])
        return self._result(z, status, iterations, solves, prep, time.perf_counter() - t0 - prep, False, inexact,
                            fraction)

    def _cap_rho(self) -> None:
        """OSQP's step size down to ``rho_max`` where the last QP's adaptation left it above, taken in by the matrix
        update that follows (:meth:`_write`)."""
        if self._core.rho > self.rho_max:
            self._core.rho_next_update(self.rho_max)

    def _qp_cap(self, split: bool, changed: bool, cold: bool) -> int:
        """OSQP's iteration cap of this step's QPs, the iterate at it taken (0: none, ``max_iter`` only): a split
        change's (``change_split_iter``), else a plain step's (``plain_qp_cap``; not a change, not a cold start)."""
        if split:
            return self.change_split_iter
        if changed or cold or (self.plain_cap_run and self._capped_run >= self.plain_cap_run):
            return 0
        return self.plain_qp_cap

    def _change_adaptation(self) -> tuple[int, float] | None:
        """OSQP's step-size adaptation for a change's QPs (``change_rho_interval``, ``change_rho_tolerance``; the
        generated solver only): the adaptation in force before, to set back after them (None: not changed)."""
        before = self._core.rho_adaptation
        tolerance = self.change_rho_tolerance or before[1]
        return before if self._core.set_rho_adaptation(self.change_rho_interval, tolerance) else None

    def _reset_rho(self, rho: float) -> float:
        """OSQP's step size set to ``rho`` for the QPs of a reference change (``rho_reset`` or ``change_rho``'s): the
        matrices in OSQP written again (the same values, one refactorisation more). Returns its wall time (s)."""
        t0 = time.perf_counter()
        self._core.rho_next_update(rho)
        self._core.update_matrices(*self._written)
        return time.perf_counter() - t0

    def _start_steady(self, x0, u_prev, d, ref, w_y, u_lo, u_hi) -> tuple[float, bool]:
        """At a reference change: linearise at the plan toward the new reference's steady-state target
        (:class:`.steady_target.SteadyStart`) instead of the shifted plan (the slacks at zero). Returns its wall
        time (s) and whether it did (not where the target is not finite: the shifted plan stays)."""
        t0 = time.perf_counter()
        start = self._steady.start(x0, u_prev, d, self._p, ref, w_y, u_lo, u_hi)
        self.last_target = None if start is None else start[0]
        if start is not None:
            _, U, X = start
            self._load(X, U, np.zeros(self.pb.N), d, ref, w_y, u_prev)
        return time.perf_counter() - t0, start is not None

    def _globalised(self, z, x0, d, ref, w_y, u_prev) -> tuple[np.ndarray, float]:
        """The QP's answer ``z``, or the damped step towards it from the linearisation point that the nonlinear
        cost prefers (:meth:`.plan_merit.PlanMerit.choose`), with the fraction taken."""
        N, nu = self.pb.N, self.pb.nu
        U_lin = self._z_lin[self.iu0:self.is0].reshape(N, nu)
        U_qp = z[self.iu0:self.is0].reshape(N, nu)
        fraction = self._merit.choose(U_lin, U_qp, x0, d, self._weights(w_y), ref, u_prev, self._p,
                                      self.readiness_target)
        if fraction == 1.0:
            return z, fraction
        z = self._z_lin + fraction * (z - self._z_lin)
        z[:self.pb.nx] = x0
        return z, fraction

    def _trusted(self, z, x0, d, ref, w_y, u_prev, u_lo, u_hi) -> tuple[np.ndarray, int]:
        """The QP's answer ``z``, or, where its plan's nonlinear cost exceeds the linearisation point's by more
        than :data:`.plan_merit.MERIT_TOLERANCE`, the same QP's answer within the first trust radius whose plan
        does not (else the least cost of those solved; :mod:`.trust_region`), and the number of QPs solved again.
        The QP's vectors are left as the problem's bounds make them."""
        N, nu = self.pb.N, self.pb.nu
        merit, sw = self._trust_merit, self._weights(w_y)
        U_lin = self._z_lin[self.iu0:self.is0].reshape(N, nu)
        args = (x0, d, sw, ref, u_prev, self._p, self.readiness_target)
        c_lin, c_best = merit.pair(U_lin, z[self.iu0:self.is0].reshape(N, nu), *args)
        self.trust_taken = 1.0
        if c_best <= c_lin * (1.0 + MERIT_TOLERANCE):
            return z, 0
        best, solved = z, 0
        for radius in self.trust_radii:
            lo, hi = region_bounds(U_lin, u_lo, u_hi, self._trust_span, radius)
            self.l[self._r_u_rows], self.u[self._r_u_rows] = lo.ravel(), hi.ravel()
            self._core.update_vectors(self._q(ref, d, u_prev), self.l, self.u)
            self._core.warm_start(self._z_lin, None)
            status_val, _, _, x = self._core.solve()
            solved += 1
            if status_val not in self._accepted or not np.isfinite(x).all():
                continue
            cand = np.array(x)
            _, c = merit.pair(U_lin, cand[self.iu0:self.is0].reshape(N, nu), *args)
            if c < c_best:
                best, c_best, self.trust_taken = cand, c, radius
            if c <= c_lin * (1.0 + MERIT_TOLERANCE):
                break
        self.l[self._r_u_rows], self.u[self._r_u_rows] = u_lo.ravel(), u_hi.ravel()
        self._core.update_vectors(self._q(ref, d, u_prev), self.l, self.u)
        return best, solved

    def _reverses_at_bound(self, z: np.ndarray, u_prev: np.ndarray) -> bool:
        """True where ``reversal_second_qp`` asks for a second QP on this plain step's plan ``z``: an input's first
        move turns against its last (:func:`.reversal_search.turned_inputs` at ``reversal_search``'s share) and,
        with ``"heater_bound"``, the plan's heater command starts at its upper bound
        (:func:`.reversal_search.at_upper_bound`)."""
        if self.reversal_second_qp == "off":
            return False
        nu = self.pb.nu
        span = self.pb.u_hi - self.pb.u_lo
        if not turned_inputs(self._last_move, z[self.iu0:self.iu0 + nu] - u_prev, span, self.reversal_search).size:
            return False
        if self.reversal_second_qp == "reversal":
            return True
        ih = self.pb.i_heater_cmd
        U = z[self.iu0:self.is0].reshape(self.pb.N, nu)
        return at_upper_bound(U, self.pb.u_hi, ih, float(span[ih]))

    def _searched(self, z, x0, d, ref, w_y, u_prev, u_lo, u_hi, plain: bool):
        """On a plain step (``plain``: one QP) whose plan ``z`` reverses an input's last first move
        (:func:`.reversal_search.turned_inputs`; with ``reversal_repeat`` only an input the last step's plan turned
        as well; with ``reversal_wait_steps`` only after that many plain steps in a row), the cheapest on the
        nonlinear cost of ``z`` and the candidates along each reversing input (:func:`.reversal_search.candidates`;
        with ``reversal_margin`` a candidate only where it costs less than (1 - margin) x the QP plan's cost; the
        states stay the QP's, the next preparation linearises at them); else ``z``. Keeps each input's last first
        move beyond the share. (The step's flags are reset by :meth:`feedback` before any return.)"""
        if z is None:
            self._last_move, self._quiet_run, self._turned_before = None, 0, np.zeros(0, dtype=int)
            return z
        nu, N = self.pb.nu, self.pb.N
        span = self.pb.u_hi - self.pb.u_lo
        # the plan's first move once for both: the inputs it turns and, unless a candidate is taken, the moves kept
        turned, moves = turns_and_moves(self._last_move, z[self.iu0:self.iu0 + nu] - u_prev, span,
                                        self.reversal_search)
        self._quiet_run = self._quiet_run + 1 if plain else 0
        searched = eligible_inputs(turned, self._turned_before if self.reversal_repeat else None,
                                   self._quiet_run, self.reversal_wait_steps) if plain else turned[:0]
        self._turned_before = turned
        if searched.size:
            self.reversal_searched = True
            merit = self._search_merit
            args = (x0, d, self._weights(w_y), ref, u_prev, self._p, self.readiness_target)
            U_lin = self._z_lin[self.iu0:self.is0].reshape(N, nu)
            U_best = z[self.iu0:self.is0].reshape(N, nu)
            _, c_best = merit.pair(U_lin, U_best, *args)
            c_take = c_best - self.reversal_margin * abs(c_best)  # a candidate taken only below this
            for i in searched:
                plans = candidates(U_best, U_lin, u_lo, u_hi, int(i), self._rate_bounds)
                costs = np.asarray(merit.costs(plans, *args), float)
                costs[~np.isfinite(costs)] = np.inf  # a candidate the model cannot price is not taken
                if self.reversal_bound_only and not at_bound(U_lin, u_lo, u_hi, int(i), float(span[i])):
                    costs[0] = np.inf  # the last plan's profile in mid-stroke: not a candidate
                j = int(np.argmin(costs))
                if costs[j] < min(c_best, c_take):
                    U_best, c_best, self.reversal_taken = plans[j], float(costs[j]), True
            if self.reversal_taken:
                z = z.copy()
                z[self.iu0:self.is0] = U_best.ravel()
                moves = last_moves(self._last_move, z[self.iu0:self.iu0 + nu] - u_prev, span, self.reversal_search)
        self._last_move = moves
        return z

    def _time_left(self, t0: float, time_limit_s: float) -> bool:
        """False where the step's time limit ``time_limit_s`` (s, from ``t0``; 0: none) is spent; else True, OSQP's
        time limit set to what is left (:meth:`_limit_time`)."""
        if time_limit_s <= 0:
            return True
        remaining = time_limit_s - (time.perf_counter() - t0)
        if remaining <= 0:
            return False
        self._limit_time(remaining, time_limit_s)
        return True

    def _limit_time(self, remaining_s: float, budget_s: float) -> None:
        """OSQP's time limit: what remains of the feedback budget, set again only when it has shrunk
        by more than a tenth of the budget since it was last set (each setting is a call into OSQP;
        the controller checks the whole feedback time against its deadline anyway)."""
        if self._time_limit is None or abs(self._time_limit - remaining_s) > 0.1 * budget_s:
            self._core.set_time_limit(remaining_s)
            self._time_limit = remaining_s

    def _relinearise(self, z, x0, d, ref, w_y, u_prev) -> float:
        t0 = time.perf_counter()
        N, nx, nu = self.pb.N, self.pb.nx, self.pb.nu
        X = z[:(N + 1) * nx].reshape(N + 1, nx).copy()
        X[0] = x0
        U = z[self.iu0:self.is0].reshape(N, nu)
        S = z[self.is0:]
        self._load(X, U, S, d, ref, w_y, u_prev)
        return time.perf_counter() - t0

    def _flap_gradient_for(self, ref: np.ndarray, w_y: np.ndarray) -> None:
        """The flaps' entries of the constant gradient for the targets of the reference's split
        (``OcpSpec.flap_target_from_split``), written again only where the split or its weights changed."""
        tracked = bool(w_y[Y_OUTLETS[0]] > 0.0)
        key = (np.asarray(ref, float)[2:5].tobytes(), tracked)
        if key == self._flap_key:
            return
        self._flap_key = key
        _, flap_g = self.pb.flap_closure_hessian(self.pb.flap_target_for(np.asarray(ref, float), tracked))
        self._q_const[self.iu0:self.is0] = self._q_heating[self.iu0:self.is0] = flap_g.ravel()
        self._qp_gradient.set_fixed(7, self._q_heating if self._q_body_on else self._q_const)

    def _q(self, ref: np.ndarray, d: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
        """Gradient for the current reference, disturbance estimates and last input: valid until the next call (the
        gradient function's buffer where the readiness is off)."""
        pr = self._prepared
        data = pr["data"]
        dd = d[_D_OFFSETS_IDX] - pr["d"][_D_OFFSETS_IDX]
        on = bool(self.pb.body_heat_coef) and self.pb.body_heat_on(u_prev) > 0.0
        if on != self._q_body_on:
            self._qp_gradient.set_fixed(7, self._q_heating if on else self._q_const)
            self._q_body_on = on
        if self.pb.flap_split_target is not None:
            self._flap_gradient_for(ref, pr["w_y"])
        # the call's buffer itself: every caller hands it to OSQP at once (which copies it into its workspace) before
        # the next call; a copy where the readiness adds to it
        q = self._qp_gradient.views(data["gw2"], data["c_base"], data["y"], ref, dd,
                                    self._z_lin[self.iu0:self.is0], u_prev)[0]
        if self._ready_q is not None:
            q = np.array(q, float)
            q[self._i_body] += self._ready_q
        if self.valve_a_prox_on:
            q = np.array(q, float)
            q[self._i_valve_a] -= 2.0 * self.valve_a_prox * self._z_lin[self._i_valve_a]
        return q


class _OsqpCore(osqp_embedded.TwoPassSolve):
    """The calls of the RTI into OSQP, made on the compiled solver object of OSQP's Python interface
    (osqp >= 1.0, ``OSQP._solver``) when it is there: the interface's own ``update`` and ``solve``
    add per call what the RTI does not need (bounds clamped to OSQP's infinity again, a copy for
    its derivative cache, a namespace of the whole info), about a third of the QP's own time on
    this problem. Without that object the public interface is used.

    ``first_pass_iter > 0``: each solve first runs up to that many iterations without
    over-relaxation (``alpha = 1``, convergence checked at the end of the pass, at
    ``FIRST_PASS_EPS_RATIO`` times OSQP's tolerance) and returns when they converged; otherwise OSQP
    continues from where the pass left off with its own settings (``alpha``, tolerances,
    ``check_termination``, ``max_iter`` counting the pass's iterations). A warm start from the shifted plan and the last
    multipliers often meets the tolerance at once, but over-relaxed first iterations move away from
    it before they come back."""

    def __init__(self, wrapper: osqp.OSQP, first_pass_iter: int = 0):
        self.wrapper = wrapper
        self.core = getattr(wrapper, "_solver", None)
        self._matrices: tuple | None = None  # the matrices last written (save_state)
        self._last = None  # the last solve's result (save_state reads its multipliers, unscaled)
        self._passes(wrapper.settings, first_pass_iter)

    def update_matrices(self, Px: np.ndarray, Ax: np.ndarray) -> None:
        if self.core is None:
            self.wrapper.update(Px=Px, Ax=Ax)
        else:
            self.core.update_data_mat(P_x=Px, P_i=None, A_x=Ax, A_i=None)
        # for save_state: the caller's arrays by reference, not copies. After a full preparation they are the fused
        # prediction's result buffers, which its next evaluation overwrites; a saved state (``_save_step``, the retry at
        # the cap) stays valid because it is restored before that evaluation: within the step's own QPs, or in
        # finish_change, which the controller's ``_finish_change`` calls before ``prepare_predicted``
        self._matrices = (Px, Ax)

    def save_state(self) -> dict:
        """What :meth:`restore_state` needs to bring OSQP back to now: the step size, the matrices last written and
        the last solve's multipliers. The Python interface hands out the multipliers unscaled only, so the restored
        workspace holds them scaled with the equilibration of the restored matrices, not with the one they were found
        with: the next solve's iterates close to, not the same as, those it would have taken now (the generated
        solver's :meth:`~.osqp_embedded.EmbeddedOsqp.save_state` keeps the workspace itself)."""
        y = None if self._last is None else np.array(self._last_y(), float)  # None: saved before any solve
        return {"rho": self.rho, "matrices": self._matrices, "y": y}

    def _last_y(self) -> np.ndarray:
        """The last solve's multipliers (unscaled), as OSQP's Python interface or its core hands them out."""
        return self._last.solution.y if self.core is not None else self._last.y

    def restore_state(self, state: dict) -> None:
        """OSQP set back to :meth:`save_state`'s step size, matrices (equilibrated and factorised again) and
        multipliers (zero where it was saved before any solve, as a fresh workspace's)."""
        self.rho_next_update(state["rho"])
        self.update_matrices(*state["matrices"])
        if state["y"] is not None:
            self.wrapper.warm_start(y=state["y"])
        elif self._last is not None:  # saved before any solve, solved since: a fresh workspace's zeros
            self.wrapper.warm_start(y=np.zeros(np.shape(self._last_y())))

    def update_vectors(self, q: np.ndarray, l: np.ndarray, u: np.ndarray) -> None:
        """``l``, ``u`` already within OSQP's infinity."""
        if self.core is None:
            self.wrapper.update(q=q, l=l, u=u)
        else:
            self.core.update_data_vec(q=q, l=l, u=u)

    def warm_start(self, x: np.ndarray, y: np.ndarray | None = None) -> None:
        """Primal warm start; the duals stay those of the last solve (see ``feedback``) unless ``y`` is given."""
        (self.core or self.wrapper).warm_start(x, y)

    def set_time_limit(self, seconds: float) -> None:
        """OSQP's time limit of each solve from now on (s)."""
        self.wrapper.update_settings(time_limit=seconds)

    @property
    def rho(self) -> float:
        """OSQP's step size now (it adapts during solves and is kept from one QP to the next)."""
        return float((self.core or self.wrapper._solver).get_settings().rho)

    @property
    def rho_adaptation(self) -> tuple[int, float]:
        """OSQP's step-size adaptation as set up: its interval (iterations) and tolerance (a factor)."""
        st = (self.core or self.wrapper._solver).get_settings()
        return int(st.adaptive_rho_interval), float(st.adaptive_rho_tolerance)

    def set_rho_adaptation(self, interval: int, tolerance: float) -> bool:
        """Not available here: OSQP's interface fixes the adaptation at set-up (its ``update_settings`` leaves both
        as they are). Returns False (nothing changed); the generated solver's does it."""
        return False

    def rho_next_update(self, rho: float) -> None:
        """OSQP's step size set to ``rho`` (OSQP's ``update_rho``: a factorisation of its own here, where the
        generated solver's :meth:`~.osqp_embedded.EmbeddedOsqp.rho_next_update` leaves it to the matrix update)."""
        if self.core is None:
            self.wrapper.update_settings(rho=rho)
        else:
            self.core.update_rho(rho)

    def _apply(self, values: dict) -> None:
        if self.core is None:
            self.wrapper.update_settings(**values)
        else:  # the interface's settings object, changed in place and handed over as a whole
            for name, value in values.items():
                setattr(self.wrapper.settings, name, value)
            self.core.update_settings(self.wrapper.settings)

    def _solve_once(self) -> tuple[int, str, int, np.ndarray]:
        if self.core is None:
            res = self.wrapper.solve(raise_error=False)
            info, x = res.info, res.x
        else:
            self.core.solve()
            info, x = self.core.info, self.core.solution.x
            res = self.core
        self._last = res
        return info.status_val, info.status, int(info.iter), x


def check_prox(name: str, weight) -> float:
    """``weight`` (``valve_a_prox``, per scaled unit squared of valve a) as a float in [0, 1e4] (0: off);
    :class:`.ocp.InvalidSettings` (a ValueError) naming ``name`` and the range otherwise."""
    check_number(name, weight, 0.0, 1e4)
    return float(weight)


def _checked_step_size(name: str, rho: float | None) -> float | None:
    """A step-size argument of ``RtiOsqpSolver`` (``name``): None or a number in OSQP's range of step sizes
    [1e-6, 1e6]."""
    if rho is not None and (isinstance(rho, bool) or not isinstance(rho, (int, float)) or not 1e-6 <= rho <= 1e6):
        raise ValueError(f"RtiOsqpSolver: {name} = {rho!r}, allowed: None or a number in [1e-6, 1e6]")
    return None if rho is None else float(rho)


def check_hold_with(name: str, hold: str, change_rho: str, rho_reset, rho_reset_on: str, generated: bool,
                    prefix: str = "") -> None:
    """``change_rho_hold`` (``name``) refused where another setting overrides it silently: ``rho_reset`` on
    "preparation" (set with every matrix update, the relinearisations between a change's QPs among them),
    ``change_rho``'s "_each" modes (each QP's start set) and "end" without the generated solver (the Python interface
    cannot switch the adaptation off: it does nothing). ValueError naming both fields (the others' names with
    ``prefix``: "osqp_" for ``MpcSettings``') and what is allowed."""
    if hold == "off":
        return
    if rho_reset is not None and rho_reset_on == "preparation":
        raise ValueError(f"{name} = {hold!r} with {prefix}rho_reset = {rho_reset!r} on 'preparation': the reset sets "
                         f"the step size at every matrix update, the held one among them; allowed: {prefix}rho_reset "
                         f"None or {prefix}rho_reset_on 'change' with it")
    if str(change_rho).endswith("_each"):
        raise ValueError(f"{name} = {hold!r} with {prefix}change_rho = {change_rho!r}: each QP's start is set by it; "
                         f"allowed: {prefix}change_rho 'off', 'last' or 'kind' with it")
    if hold == "end" and not generated:
        raise ValueError(f"{name} = 'end' with osqp_codegen = False: the Python interface cannot hold the step size "
                         "(it does nothing); allowed: osqp_codegen True, or 'start' / 'off'")


def check_cap_retry(name: str, rho: float, share: float, cold: bool) -> tuple[float, float, bool]:
    """The retry at OSQP's cap (``RtiOsqpSolver``'s ``cap_retry_rho``, ``cap_retry_share``, ``cap_retry_cold``):
    ``rho`` 0 (off) or a step size in [1e-6, 1e6], ``share`` 0 (off) or a factor in (0, 1], not both set; ``cold`` a
    flag. Returns them as floats and a bool; ValueError naming the field otherwise."""
    for field_name, value, hi in (("rho", rho, 1e6), ("share", share, 1.0)):
        number = not isinstance(value, bool) and isinstance(value, (int, float, np.floating))
        if not number or not (value == 0 or (1e-6 <= value <= hi if field_name == "rho" else 0 < value <= hi)):
            allowed = "0 (off) or a step size in [1e-6, 1e6]" if field_name == "rho" else "0 (off) or a factor in (0, 1]"
            raise ValueError(f"{name}_{field_name} = {value!r}, allowed: {allowed}")
    if rho and share:
        raise ValueError(f"{name}_rho = {rho!r} and {name}_share = {share!r} both set; allowed: one of them")
    check_flag(f"{name}_cold", cold)
    return float(rho), float(share), cold


def _checked_cap(name: str, cap: int, max_iter: int) -> int:
    """An iteration-cap argument of ``RtiOsqpSolver`` (``name``): 0 (off) or an integer in [1, max_iter]."""
    if isinstance(cap, bool) or not isinstance(cap, (int, float, np.integer)) or int(cap) != cap \
            or not (cap == 0 or 1 <= cap <= int(max_iter)):
        raise ValueError(f"RtiOsqpSolver: {name} = {cap!r}, allowed: 0 (off) or an integer in "
                         f"[1, max_iter = {max_iter}]")
    return int(cap)


def _selection(slots: np.ndarray, size: int) -> ca.DM:
    """Sparse 0/1 matrix adding entry e of a vector into position ``slots[e]`` (size rows)."""
    slots = np.asarray(slots, np.int64).ravel()
    sp_m = sp.csc_matrix((np.ones(slots.size), (slots, np.arange(slots.size))), shape=(size, slots.size))
    return ca.DM(ca.Sparsity(size, slots.size, sp_m.indptr.tolist(), sp_m.indices.tolist()), sp_m.data.tolist())


def same_values(a: np.ndarray, b: np.ndarray) -> bool:
    """``np.array_equal(a, b)`` for two numpy arrays (the same shape and every value equal; nan equals nothing),
    without its conversions: the references and weights a step compares with the preparation's."""
    return a.shape == b.shape and bool(all_reduce(a == b, axis=None))  # ndarray.all's reduction, without its wrapper


def _same_signature(a: ca.Function, b: ca.Function) -> bool:
    """True when ``a`` and ``b`` take and give arguments of the same sparsity (a linked call's sizes agree)."""
    if (a.n_in(), a.n_out()) != (b.n_in(), b.n_out()):
        return False
    return (all(a.sparsity_in(i) == b.sparsity_in(i) for i in range(a.n_in()))
            and all(a.sparsity_out(i) == b.sparsity_out(i) for i in range(a.n_out())))
