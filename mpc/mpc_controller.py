"""The MPC: one receding-horizon controller for blower, heater and valves a, m, f, w.

Usage::

    ctrl = MpcController(params, MpcSettings())
    result = ctrl.step(measurement, reference)      # once per sample, never raises
    plant.apply(result.command); result.stats["step_time_s"], result.stats["fallback"]

Each step: EKF update with the measurement -> feedback (insert the estimate, solve the QP
prepared during the previous step) -> command, projected onto the actuator bounds and rate
limits -> EKF prediction with that command -> preparation of the next QP. With
``solver="ipopt"`` the same problem is solved to convergence instead (reference, slow).

Failures (QP status not solved, non-finite data, a missed ``deadline_s``, any exception) never
leave ``step``: the controller applies the shifted previous plan for up to ``plan_fallback_s``,
then the thesis baseline (``hvac_mpc.mpc.baseline.BaselineController``, imported when first
needed, handed the command in force), and as a last resort holds the last command;
``stats["fallback"]`` names which. The warm start is reset after a failure; a valid reference
replaces an invalid one (the last valid one is kept); missing readings are skipped by the
estimator. Every command, fallbacks included, is projected onto the actuator ranges, the rate
limits and the trapped-air cap before it leaves.

Stats of a step: ``step_time_s`` (the whole step), ``feedback_time_s`` (measurement to command),
``prep_time_s`` (preparation of the next QP), ``iterations`` (OSQP iterations, or IPOPT's),
``qp_solves``, ``cold_start``, ``status``, ``fallback``, ``mode`` ("heating" while the heater is commanded,
else "cooling"), ``solver``, ``valve_a_cap_pct``, ``mix_offset_c``, ``flow_offset_m3s``, ``out_of_reach``
(reference name -> shortfall in its unit, e.g. ``{"volume_flow_m3s": 0.004}``; empty when every
reference is within reach, :mod:`hvac_mpc.mpc.priorities`; ``supply_temp_c`` also while the heater or
the cooler is saturated and the reading stays away, :mod:`hvac_mpc.mpc.temperature_reach`), ``flow_weight_factor`` (the factor on the
flow weights of the step: 1, less out of reach or while a large flow error is closed), ``valve_a_held`` (valve
a's closing move of the step not applied, ``valve_a_hold_shortfall_c``, :mod:`hvac_mpc.mpc.valve_a_hold`), ``dead_time_s``
(the thermocouple's dead time beyond the model's that the estimator has found and honours, :mod:`hvac_mpc.mpc.estimator`),
``bypass_flow_exponent`` (the exponent of the bypass split's flow dependence the prediction uses: the
estimator's estimate where it learns it, :mod:`hvac_mpc.mpc.estimator`), ``reach_wait_s`` (wall time the
step waited for the reachable-flow solve started on the second thread the step before, :mod:`hvac_mpc.mpc.priorities`);
with ``change_split_iter``: ``change_wait_s`` (wall time the step waited for the last reference change's rest,
finished on the second thread) and ``change_finish`` (collected in the step after a split change: that rest's
``iterations``, ``qp_solves``, ``ok``, its wall time ``wall_s`` and its thread's CPU time ``thread_cpu_s``).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from hvac_mpc.models import air, chiller
from hvac_mpc.models.heater import available_power_w
from hvac_mpc.models.box import INPUTS, HvacModel
from hvac_mpc.models.model_file import RefinedModel
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.contract import Command, Measurement

from hvac_mpc.contract import StepResult
from .codegen import CodegenReport, compiled, shared, structure_key
from .estimator import DisturbanceEkf, EkfSettings, finite_or
from .priorities import ReachableFlow, flow_weight_factor
from .ocp import (FLOW_OUTPUTS, HEATING_CMD_W, Y_VALVE_A, HeaterOffBound, InvalidSettings, OcpSpec, TrackingProblem,
                  check_flag, check_number, trap_cap_pct)
from hvac_mpc.contract import InvalidReference, Reference
from .placement import PLACEMENTS, PlacementChoice
from .sign_check import HeldAirChange, ValveSignCheck
from .readiness import HeaterReadiness, heating_duty
from .reserve import HeaterReserve
from .reversal_damping import damped_move
from .reversal_search import check_second_qp, check_second_qp_with, check_share, check_wait
from .valve_a_hold import heater_limited, held_opening
from .arrays import all_finite
from .background import BackgroundCall, BackgroundWorker
from .ring_gate import RingGate
from .start_caution import SCOPES as START_CAUTION_SCOPES, START_CAUTION_IN_QP, START_CAUTION_WHEN_BINDING, VALVE_A_AND_HEATER, \
    StartCaution, known_delay_s, opening_bound
from .rti_osqp import RHO_RESET_ON, RtiOsqpSolver, SolveResult, check_cap_retry, check_hold_with, check_prox
from .steady_target import check_steady_start_on
from .change_rho import check_adaptation, check_change_rho, check_hold
from .trust_region import check_radii
from .temperature_reach import SaturatedTemperature

SOLVERS = ("rti", "sqp", "ipopt")
#: Factor on the flow weights while the flow reference is out of reach (docs/robustness.md sec. 1).
#: The reachable flow is a model estimate and may lie a few L/s above what the box delivers; the
#: QP then settles where the gradients of the two residuals through valve a balance,
#: e_T = w_Q e_Q (dQ/da) / (w_T dT/da): with the default weights (w_T 1 per degC^2, w_Q 2 per
#: (L/s)^2), dT/da about 0.25 degC/% and dQ/da about 0.05 (L/s)/% at full blower, a 3 L/s excess costs
#: 0.12 degC at a factor 0.1 and about 0.01 degC at 0.01 (measured: 0.17 and 0.03 degC steady error on
#: the independent box). At 0.01 a residual above 0.4 L/s still pulls the blower harder than the energy
#: term holds it back (2 w_Q e_Q 0.19 (L/s)/W against 2 w_e P / (100 W)^2), so flow still comes before
#: energy.
OUT_OF_REACH_FLOW_WEIGHT = 0.01
#: Heater command (W) below which an inexact QP answer (OSQP stopped at its iteration bound) leaves the heater
#: off where it is off. ASSUMPTION: an iterate at the bound is within a few watts of the QP's solution in the
#: heater (2.8 W measured once in the summer pull-down, where the solution is 0 W), and where heat is wanted the
#: QP asks for tens of watts within a step (the heater's rate limit is 60 W/s); a demand below this
#: bound is delayed by a step, not lost (the next QP goes on from the shifted plan).
INEXACT_HEATER_OFF_W = 10.0


#: OSQP's step size for the retry of a QP at its cap, the default since docs/robustness.md sec. 2.44 (dimensionless).
DEFAULT_CAP_RETRY_RHO = 3e-3


@dataclass(frozen=True)
class MpcSettings:
    """Settings of :class:`MpcController` (validated on construction; errors name the field).

    Attributes:
        dt_s: sample time (s).
        ocp: the optimal control problem (horizon, weights, rates, soft limits), :class:`OcpSpec`.
        solver: ``"rti"`` (one QP per step), ``"sqp"`` (Gauss-Newton SQP to ``sqp_tol``, at most
            ``sqp_max_iter`` QPs) or ``"ipopt"`` (the full NLP to convergence; reference only).
        osqp_eps: OSQP absolute/relative tolerance; osqp_max_iter: OSQP iteration cap per QP (1000: with the
            supply-temperature weight 5 the QP of a large heating step needed more than 400, and the
            failed step's cold starts then missed the deadline, docs/robustness.md sec. 2.2);
            osqp_check_termination: OSQP convergence-check interval (iterations).
        osqp_scaling: OSQP's equilibration passes, run again on every matrix update (the
            preparation's refactorisation); osqp_alpha: OSQP's relaxation parameter;
            osqp_check_dualgap: also hold OSQP's duality gap to ``osqp_eps``;
            osqp_first_pass_iter: each QP first gets up to this many OSQP iterations without
            over-relaxation and stops there when they converge (0: off), :mod:`hvac_mpc.mpc.rti_osqp`.
            The defaults are measured in the README, "Solve time".
        osqp_accept_max_iter: take OSQP's iterate at ``osqp_max_iter`` as the QP's answer (an inexact
            QP step; the next step's QP goes on from it) instead of a failure and the fallback chain:
            with a low cap (``osqp_max_iter=60``), a deterministic bound on a step's OSQP iterations.
            Off: measured with 60, the heating step down at low flow of ``tests/test_mpc.py`` settles in
            117 s instead of 62 s (100: 117 s, 150: 111 s; docs/architecture.md 'Slow steps'). An answer
            taken at the cap does not switch the heater on: a heater command below
            :data:`INEXACT_HEATER_OFF_W` from it is taken as off while the heater is off in the command
            in force.
        osqp_codegen: solve the QPs with OSQP's generated C (:mod:`hvac_mpc.mpc.osqp_embedded`, built
            once per structure into the code cache; the same answers as OSQP's Python interface); without
            a compiler or with ``HVAC_MPC_CODEGEN=0`` OSQP's Python interface solves them.
        osqp_scaling_interval: OSQP's equilibration on every this many matrix updates, the ones between
            keeping the last equilibration (1: on every update, OSQP's own behaviour); needs the generated
            solver (``osqp_codegen``). Measured in docs/architecture.md, "One control step".
        sqp_max_iter, sqp_tol: SQP iteration cap and step tolerance (scaled variables).
        levenberg_marquardt: weight of lm * |u_k - u_k_lin|^2 (scaled inputs, every stage) added to
            each QP: damps Gauss-Newton steps along the flat directions the redundant actuators
            leave; it vanishes at a converged solution, so it changes the iterates, not the optimum.
        cold_start_qps: on a cold start (first step, after a reset or a failure) there is no
            previous solution to start from, so up to this many QPs are solved (Gauss-Newton SQP
            to ``sqp_tol``); every other step of ``solver="rti"`` solves exactly one, except:
        reference_change_qps: on a step whose reference differs from the previous one, up to this
            many QPs (Gauss-Newton SQP to ``sqp_tol``): the shifted plan was made for the old
            reference, and a single damped step from it leaves the RTI's closed loop several
            percent from the converged IPOPT controller's (measured with ``hvac-mpc solve-time``).
        rti_step_fractions: a globalised step for ``rti``/``sqp`` (:mod:`hvac_mpc.mpc.plan_merit`): after each QP
            the nonlinear cost of its plan (the model's rollout) is compared with the linearisation point's;
            where it is higher, the damped steps of these fractions (each in (0, 1)) are tried and the least
            cost taken. Empty: the QP's plan whole (the plain real-time iteration).
        rti_trust_radii: a trust region for ``rti``/``sqp`` (:mod:`hvac_mpc.mpc.trust_region`): where the QP's plan
            raises the nonlinear cost above the linearisation point's, the QP is solved again with each stage's
            inputs within radius x their range of the linearisation point's plan, for these radii in turn
            (each in (0, 1), decreasing, at most four), and the first plan no worse is taken; not on a cold start
            (the plain SQP from the held starting command). Empty: off.
        rti_reversal_search: a search along a reversing input for ``rti`` (:mod:`hvac_mpc.mpc.reversal_search`):
            where the plan's first move of an input turns against the last step's first move, both by more than this
            share of the input's range (in [0, 1)), the QP's plan with that input's profile replaced by the
            linearisation point's, by its upper and by its lower bound is priced on the nonlinear cost (the model's
            rollout) and the cheapest of these and the QP's plan taken (``stats["reversal_searched"]``,
            ``stats["reversal_taken"]``); only on a plain step (one QP), no QP added. 0: off; 0.05 by default, with
            the wait and the margin below (docs/identification.md, "The guarded search as the default").
        rti_reversal_wait_steps: with ``rti_reversal_search``, the plain steps (one QP each, 1 s apart at the bench's
            sample) after a cold start, a reference change or a split step on which the search does not act (an
            integer in [0, 3600]; 0: it acts from the first; 20 by default). The bench's takes in a change's wake moved
            the path and the later steps (docs/identification.md, "The search's cost on the built-in bench, traced; a
            wait and a margin").
        rti_reversal_repeat: with ``rti_reversal_search``, only an input whose plan turned on the step before as
            well (a two-cycle). False: every turned input.
        rti_reversal_margin: with ``rti_reversal_search``, a candidate is taken only where its nonlinear cost is
            below (1 - this share) x the QP plan's (a share in [0, 1); 0: any candidate cheaper than the QP's plan;
            0.1 by default).
        rti_reversal_bound_only: with ``rti_reversal_search``, the linearisation point's profile of a reversing input
            is a candidate only where its first stage is at the input's bound (within 2 % of its range,
            :func:`hvac_mpc.mpc.reversal_search.at_bound`); the bounds' profiles stay candidates. False (the
            default): that profile wherever it is. Taken in mid-stroke it holds the input where the last plan had it
            on every step the QP's plan is dearer, and on the recirculating box's refined model that held valve a
            at 43 % through winter heating's first heater-limited rise (docs/identification.md, "Recirculation's
            refined winter, traced").
        rti_reversal_second_qp: with ``rti_reversal_search`` (its share names a reversal), a second Gauss-Newton QP
            linearised at the first QP's plan on a plain step whose plan turns an input against its last first move:
            ``"reversal"`` on every such step, ``"heater_bound"`` only where the plan's heater command starts at its
            upper bound (within 2 % of its range); ``"off"`` (the default): none. Measured on valve a's two-cycle at
            the heater's bound in the box sweep's heating cells (docs/robustness.md sec. 2.41): it breaks the
            cycle, and costs the cells where the box's valve a answers less than the model's near closed. Only with
            ``solver="rti"`` and without ``split_every_step`` (it never fires otherwise).
        rti_valve_a_prox: a proximal (Levenberg-Marquardt) weight on valve a's deviation from the linearisation
            point's plan, per scaled unit squared (1 = 50 % of valve a's travel; 0.1 % of the travel squared costs
            ``4e-6`` of it), added to ``levenberg_marquardt`` at every stage only where the linearisation point's
            heater command starts at its upper bound (within 2 % of its range). There the QP's curvature along valve
            a is about 2-3 per scaled unit squared, a tenth of it the supply temperature's at mid-travel, against a
            linear pull of 5-15 that asks 1-4 times valve a's travel: the plan goes from end to end; the nonlinear cost's
            curvature there is 4-30 times the QP's at 18-55 % of travel (docs/robustness.md sec. 2.43). The term adds
            ``2 * rti_valve_a_prox`` to that curvature (the cost is ``w * (a - a_lin)**2``). Measured at 30 (60 on the
            curvature):
            the two-cycle broken in the sweep's heating cells (S1-13 0.951 -> 0.822), S1-11 1.009 -> 1.029 (the cycle's
            strokes had let its dead-time estimate find the box's), so not the default. A value in [0, 1e4]; 0 (the
            default): off. The OSQP solvers only (``rti``, ``sqp``).
        ipopt_tol, ipopt_max_iter: IPOPT tolerance and iteration cap.
        deadline_s: longest feedback time (measurement to command); beyond it the solution is
            discarded and the fallback chain used.
        plan_fallback_s: how long the shifted previous plan may stand in for a failed solver
            before the thesis baseline takes over (s).
        jit: compile the mapped stage function with the C compiler (about 1 s at construction;
            falls back to the CasADi virtual machine if compiling fails).
        codegen: evaluate the hot path (the QP data of ``rti``/``sqp``, the estimator's time and
            measurement updates) as generated C, built with the C compiler on first use and cached on
            disk per model structure and horizon (:mod:`hvac_mpc.mpc.codegen`); weights, bounds,
            references and the model parameters are inputs of the generated functions, so a new
            parameter set or weight does not build anew. Without a compiler (or with
            ``HVAC_MPC_CODEGEN=0``) CasADi's interpreter runs the same functions (results equal up to
            round-off). On by default.
        water_prediction: ``"hold"`` or ``"setpoint"``, see :mod:`hvac_mpc.mpc.estimator`.
        chiller_setpoint_c: chiller set point used when the measurement carries none (degC).
        initial_command: the command in force before the first step (the first move is
            rate-limited from it).
        ekf: noise settings of the estimator, :class:`EkfSettings`.
        priorities: supply temperature before total flow (:mod:`hvac_mpc.mpc.priorities`): when the
            model says the flow reference cannot be held at the temperature reference, track the
            reachable flow instead and report the shortfall in ``stats["out_of_reach"]``.
        reach_every_s: how often the reachable flow is recomputed while the flow reference is in doubt (s).
        reach_skip_unmoved: skip that periodic re-solve while its inputs have not moved materially
            (``mpc/priorities.py`` ``MATERIAL_CHANGE``; off: measured worse with the flow out of reach).
        reach_deferred: a periodic reachable-flow re-solve (the references unchanged) started in one
            step is applied from the next step on (that step answers from the previous solve); the
            commands do not depend on where or how fast the solve runs. A change of the references
            is solved inside its step (``mpc/priorities.py``) unless ``reach_changes_deferred``.
        reach_background: with ``reach_deferred``, run that solve on a second thread between the two
            steps, off the step's critical path (:mod:`hvac_mpc.mpc.background`); the commands are
            those of ``reach_background=False`` bit for bit.
        reach_changes_deferred: with ``reach_deferred`` (ignored without), the solve at a change of the
            references too: the step answers from the last solve (with none, the flow reference as it
            is) and the new answer is used from the next step on
            (:meth:`~.priorities.ReachableFlow.check`; docs/architecture.md 'Slow steps').
        flow_trade_c: the most supply temperature (degC) a flow error may buy through valve a while the
            blower closes it at its rate limit: the flow weights are cut for the step where the error
            would buy more (:func:`hvac_mpc.mpc.priorities.flow_weight_factor`; with ``priorities`` only;
            None: the plain weighted sum, which bought 1.8 degC at a flow step, docs/robustness.md sec. 1).
        bound_heater_estimate: while the heater is off, hold the estimator's heater body between the air
            reaching it and its relaxation from the estimate at switch-off (:class:`~.ocp.HeaterOffBound`,
            :meth:`~.estimator.DisturbanceEkf.bound_state`): unbounded, the filter parked supply-temperature
            errors in the unpowered body (23 C for a true 11.7 C) and the prediction then released that
            phantom heat at the next flow change. Off by default: on the built-in plant, whose bypass split
            depends on the flow as the filter's model does not, the wandering body stood in for that
            dependence (quick flow_split_changes 0.80 -> 0.89 of the baseline's IAE with it on;
            docs/robustness.md sec. 2.6).
        ring_detune: the ringing gate (:class:`~.ring_gate.RingGate`, docs/robustness.md sec. 2.12): while the
            supply error (reading minus reference) swings across +-``ring_amplitude_c`` (degC) ``ring_crossings``
            times within ``ring_window_s`` (s), each further swing multiplies a factor on valve a's and the
            heater's rate limits for the applied command by ``ring_detune``, down to ``ring_floor``; without a
            swing for ``ring_relax_s`` (s) the factor doubles every ``ring_relax_s`` back to 1. 1.0 (the
            default): off. Measured with 0.5 (sec. 2.12): the ringing boxes' heating cells lower, three cells
            of the quick suite higher; so not the default.
        start_rate_share: the start-up's caution (:class:`~.start_caution.StartCaution`, docs/robustness.md sec.
            2.23, 2.25): from the controller's start (a reset) the moves ``start_caution_scope`` names are limited to
            this share of their rates until the filter in use has seen a response of the supply air (its dead-time
            estimate informed, :attr:`~.estimator.DisturbanceEkf.response_seen`) or ``start_caution_s`` (s) has
            passed: a stroke made before anything has shown a dead time becomes a ramp the filter and the dead-time
            estimate can follow. 0.4 by default (sec. 2.30; a share in (0, 1], 1.0: off). Not started
            where the controller knows a dead time from its start (a transport delay in its prediction, or a model file's delay as the estimator's
            starting dead time, :func:`~.start_caution.known_delay_s`). Measured with 0.4 and the scope
            ``valve_a_opening`` (sec. 2.25, 2.27): the quick box sweep's worst cells (flow out of reach, 2.88 / 2.56 /
            1.67) 0.55-0.62, the full built-in bench the same to the fourth decimal. Where its bound does not bind it
            still moves the first QPs' answers slightly, and a run whose later QP sits at the solver's iteration limit
            or whose loop rings can take another way from there (sec. 2.27). With the scope
            ``valve_a_and_heater`` (sec. 2.23) the sweep's heating cells higher and the full built-in bench's winter
            heating steps 0.675 -> 0.704.
        start_caution_scope: what ``start_rate_share`` slows (:data:`~.start_caution.SCOPES`):
            ``"valve_a_opening"`` (the default scope, docs/robustness.md sec. 2.25) valve a's opening only, toward the
            core path, its closing (toward the bypass, whose air is the inlet's) and the heater free;
            ``"valve_a_and_heater"`` both ways of valve a and the heater (sec. 2.23).
        start_caution_in_qp: with the scope ``valve_a_opening``, the caution's bound on valve a's opening is a bound
            of the QP (True, the default) or only of the command the QP's answer is projected onto (False): then a
            step where the bound does not bind is the plain start's step to the bit, and where it binds valve a is
            cut to the bound with the other inputs as the QP planned them. Measured (docs/robustness.md sec. 2.32):
            the quick box sweeps of seeds 0 / 1 / 2 with False the plain start's where the bound never binds (seed 2
            0.771 / 1.251 / 4 above 1.0, in the QP 0.779 / 1.248 / 5) and the caution's gain where it binds (seed 0
            0.837 / 1.054 / 4, as in the QP; seed 1 0.791 / 1.568 / 9, in the QP 8). Not the default: valve a's
            reversal damping on the recirculating box removes fewer reversals with it (over noise seeds 0-3, 72 -> 47
            against 69 -> 33 with the plain start), and the reserve's step-down test goes the other way.
            ``"when_binding"`` (docs/robustness.md sec. 2.45): the QP without the bound first, and only in a step
            whose answer opens valve a beyond it (by more than OSQP's absolute tolerance) the step's QPs solved again
            with it from the state they started from (:meth:`.RtiOsqpSolver.feedback`'s ``u_hi_binding``; the step's
            ``stats["start_caution_solved_again"]``, its QP count both passes'): a step where the bound does not bind
            is the plain start's to the bit, a step where it binds the bound-in-the-QP step's (to the bit with the
            generated OSQP; through OSQP's Python interface, whose restore rescales the multipliers, within its
            tolerance). With IPOPT's reference (``solver="ipopt"``) the bound is in the QP as with True. Measured
            (sec. 2.45): the literal-cooler check 0.990 (in the QP 1.002), the quick sweeps of seeds 1 / 2 the
            command-only form's figures (S1-8's heating 1.051, in the QP 0.949; S2-9's 1.017, in the QP 1.240), the
            reserve's step-down test failing (the change's QP at OSQP's cap, a fallback): not the default.
            Re-measured with OSQP's cap retry the default (sec. 2.47): the same sweep cells, the literal-cooler check
            over noise seeds 0-3 0.9873 (in the QP 0.9897), the step-down test's contrast gone through OSQP's Python
            interface (every run closes valve a at once, no fallback); S1-8's heating traced to the dead-time
            estimate (``EkfSettings.dead_time_first_settle_s``, which lowers it to 0.856 but raises S1-5's proband
            above 1.0): still not the default.
        valve_a_weight_on_duty: valve a's heating weight (``Weights.valve_a_heating_per_pct2``, per %^2 per s) also
            while the heater is off, where the supply-temperature reference is above the inlet air (the heating duty,
            the readiness's condition, :mod:`.readiness`); False (the default) weighs valve a only while the heater is
            commanded (above :data:`~.ocp.HEATING_CMD_W`). With the heater off the weight's switch leaves valve a
            free, and at a heating rest held with the heater off the plan may open it to its cap: the core's air
            then draws the heater body down, and the next step up finds no stored heat (S2-9's and S2-5's quick
            winter heating, the body 18 C at the step against the baseline's 37 C; docs/robustness.md sec. 2.51).
        valve_a_weight_on_duty_open_pct: with ``valve_a_weight_on_duty``, the weight while the heater is off counts
            only once valve a in the command in force has opened beyond this share of its travel (%) with the heater
            off, and from then on until the reference stops asking for heat; 0.0 (the default) weighs it from
            the duty's first step. At a rest with valve a at its lower bound the weight changes no optimum, only
            OSQP's stopping points, and a path parted there may fall differently into valve a's two-cycle at the
            heater's bound later (S1-13's quick winter heating, the 9 C warm-up with the heater off and valve a
            at 0 %: 0.947 -> 1.029 with the plain setting; docs/robustness.md sec. 2.52). Refused above 0 without
            ``valve_a_weight_on_duty`` (it would do nothing).
        valve_a_weight_on_duty_scale: with ``valve_a_weight_on_duty``, valve a's weight while the heater is off on the
            duty is ``Weights.valve_a_heating_per_pct2`` times this factor (dimensionless); 1.0 (the default) the same
            weight as with the heater on. At the weight's own size a rest above the reference with the heater off
            still opens valve a to its cap to cool the supply (S2-5's quick 12 C rest with the opening gate: 84-90 %,
            the body 17.4 C at the step); ten times holds it shut (docs/robustness.md sec. 2.52). Refused other than
            1.0 without ``valve_a_weight_on_duty``.
        steady_start: the QPs of a reference change (``rti``/``sqp``) start from the plan toward the new
            reference's steady-state target on the model with the estimator's disturbances (the inputs that hold
            it at rest, ramped to at the rate limits; :mod:`hvac_mpc.mpc.steady_target`) instead of the plan
            shifted from the last step, made for the old reference. Measured in docs/architecture.md, 'Slow
            steps' ('A reference change started at the steady-state target').
        choose_offset_placement: where the heater outlet reading's error goes, chosen online
            (:mod:`~.placement`, docs/robustness.md sec. 2.14): beside the filter of ``ekf`` (the reading's own
            offset) a second one with an offset of the air leaving the heater (``EkfSettings.q_heater_air_offset_c``
            ``placement_q_heater_air_c``, the reading's own offset off) runs on the same readings and commands; the
            prediction uses the one whose supply innovations are the smaller (:class:`~.placement.PlacementChoice`:
            normalised squares, each capped at ``placement_cap``, summed with a forgetting time
            ``placement_window_s`` (s); a switch where the other's sum is below ``placement_ratio`` times the sum of
            the one in use and that is above ``placement_evidence`` times a consistent filter's). The filter not in
            use is brought up to date at the start of the next step, or between steps by :meth:`wait_background`.
            Where ``ekf`` places the error itself (an offset of the core path's air, no heater outlet reading or no
            offset of its own) there is nothing to choose and one filter runs. A switch costs one step the
            preparation of the QP (with ``placement_warm_switch`` off a cold start, as after a reset); each
            filter's prediction fused with the QP data is built with the controller, so a switch builds nothing.
        placement_margin: a second way to switch (:class:`~.placement.PlacementChoice`, docs/robustness.md sec.
            2.15): where the sum of the filter in use (itself inconsistent, as above) exceeds the other's by more
            than this (normalised squares; twice the log-likelihood ratio of the two filters' innovations over the
            window), whatever their ratio. A start-up both filters are surprised by alike (each sample capped)
            inflates both sums and so delays the ratio's switch, not the difference's. 50 (the default since
            docs/robustness.md sec. 2.24; 100 before, with ``placement_dead_time_hold_s`` 6, measured in sec. 2.16
            and 2.18); inf: off.
        placement_from_response: forget both sums once, when the filter in use first sees a response of the
            supply air (its dead-time estimate informed, :attr:`~.estimator.DisturbanceEkf.response_seen`): what
            came before is a dead time not yet found, which surprises both filters alike and tells nothing of
            where the error sits. On by default (sec. 2.18).
        placement_warm_switch: at a switch, linearise the QP prepared at the other filter's prediction again at
            the new filter's (its first node and disturbances, the shifted plan and OSQP's warm start kept) instead
            of a cold start; the switch step then costs a preparation, not a cold QP (docs/robustness.md sec. 2.15).
            On by default (sec. 2.18).
        placement_dead_time_hold_s: with a positive value (s, at most 600) the two filters' innovations count in
            :class:`~.placement.PlacementChoice` only in pairs (the same sample of each, both with a reading) and only
            where neither filter's honoured dead time (:attr:`~.estimator.DisturbanceEkf.honoured_dead_time_s`)
            changed within this time: a filter that has just moved the sample its reading is compared with is
            surprised by that move, not by where the heater outlet's error sits (docs/robustness.md sec. 2.16).
            0: off, each filter's innovations count as they come; 6 (the default; ASSUMPTION: the model's
            thermocouple time constant, 5.7 s, rounded up) is what sec. 2.16 and 2.18 measure.
        placement_sign_move_pct: with a finite value (%, 1-100) the sign of the supply reading's answer to a
            departure of valve a from rest by at least this much is checked against the filter in use's model
            (:mod:`~.sign_check`, docs/robustness.md sec. 2.28): where the reading moves by at least
            ``placement_sign_change_c`` (degC) within ``placement_sign_window_s`` and that model's predicted change
            has the other sign, while the other filter's prediction has the answer's sign and at least the change
            seen, the prediction moves to the other filter at the next step, on trial (both sums forgotten and the
            evidence floor counted from there, :meth:`~.placement.PlacementChoice.force`: the sums may take it
            back within seconds). "At rest": over ``placement_sign_rest_s`` (s) before the move valve a within a
            quarter of the move and the reading within half the change. 20 (the default, sec. 2.34: the built-in
            bench, the quick mismatch suite of seed 4 and the quick box sweeps of seeds 0-2 unchanged to the digit,
            S2-7's full heating 1.015 -> 0.733); inf: off. Without ``choose_offset_placement`` there is no other filter
            and the check is not run, whatever this value.
        placement_sign_change_c: the smallest change of the reading (degC, 0.1-5) the check counts as an answer; 0.5
            (ASSUMPTION: ten times the thermocouple noise's standard deviation of the boxes).
        placement_sign_window_s: how long after the departure began its answer is looked for (s, 2-120); 15
            (ASSUMPTION: the boxes' dead time, at most 5 s, and about two of the model's thermocouple time constants).
        placement_sign_rest_s: the rest required before the departure (s, 2-600); 10.
        placement_sign_rest_hold_s: a rest lost to valve a alone (its range over the rest window above a quarter of
            the move, the reading still at rest) still starts a departure from the last rest's means for this long
            after it was last seen (s, 0-600; 0, the default: off): valve a that creeps a few % before it opens
            (S2-7 with the heat released at rest: 5.1 % at 150 s, then 3.3, 0, 6.6, 13.5, 37.9, 90 %) leaves no
            rest of the full rule before its opening (docs/robustness.md sec. 2.37). The held rest counts only while
            the reading's mean is within the rest tolerance of the held one; below half a sample it rounds to off.
        rti_relinearise_every: multi-level steps (``rti``, :mod:`hvac_mpc.mpc.multilevel`): a full linearisation
            of the QP (new Jacobians and Hessian, OSQP's equilibration and refactorisation) at least on every this
            many preparations; the ones between keep the QP's matrices of the last full one and renew only its
            vectors (the dynamics defects, the residuals, the flow floor's bounds at the shifted plan) while that
            plan is within ``rti_relinearise_move`` (scaled states and inputs) of the point of the full one. A
            reference change, a change of the weights, a reset or fallback, new model parameters and a change
            of the heater readiness's stages linearise in full. 1 (the default): every preparation is a full
            one. Measured in docs/architecture.md, 'Multi-level steps'.
        rti_relinearise_move: the largest move (scaled units) of any stage's state or input since the last full
            linearisation for a step that keeps the matrices (0.3: the bound that kept the per-step suboptimality
            within its target in the measurements).
        steady_start_on: with ``steady_start`` (ignored without), which reference changes start at the target:
            "any" (every change of the tracked reference, the flow's and split's too) or "temperature" (only a
            change of the supply-temperature reference; a flow or split change alone starts from the shifted
            plan). :data:`hvac_mpc.mpc.steady_target.STEADY_START_ON`.
        osqp_rho_reset: OSQP's step size ``rho`` set to this value at every preparation's matrix update (in its
            refactorisation; OSQP still adapts it within each QP) instead of the value the last QP's adaptation left
            (None: kept). ``osqp_rho_reset_on``: "preparation" (every one) or "change" (only the QPs of a reference
            change, their matrices written again with it: one refactorisation more in that step). Measured in
            docs/architecture.md, 'Slow steps' ('OSQP's step size reset').
        reweigh_in_place: where the output weights change after the preparation (the flow's weight factor), the
            QP linearised again at the plan already shifted, not shifted a second time (off: the behaviour the
            bench was tuned with). Measured in docs/architecture.md, 'Slow steps' ('The weights changed after
            the preparation').
        change_split_iter: a reference change's QPs split between the step and the second thread (``rti``/``sqp``;
            0, the default: off, the change solved in its step): the step answers with the change's QPs capped at
            this many OSQP iterations each (at most ``osqp_max_iter``), the rest of the change (those QPs to
            convergence from the same state) and the next preparation run on the controller's worker thread
            (:mod:`hvac_mpc.mpc.background`; the reachable-flow solve's where there is one) and the next step
            collects them before anything else, waiting if need be (``stats["change_wait_s"]``,
            ``stats["change_finish"]``): the commands do not depend on the thread. Not the default: the built-in
            bench's winter_heating_steps worse by 0.017-0.054 (docs/architecture.md, 'A reference change finished
            on the second core'; traced in 'The rest of a split change, traced').
        change_split_thread: with ``change_split_iter``, the rest on the second thread (True) or at once at the
            step's end (False: inside the step, the same commands).
        split_every_step: with ``change_split_iter``, every step's QPs capped so, the rest handed over where a QP
            reached the cap (and at every change).
        split_keeps_rho: with ``change_split_iter``, the rest leaves OSQP's step size as the change step found it
            instead of as the rest's QPs adapted it (False, the default). Measured in docs/architecture.md, 'The
            rest of a split change, traced'.
        split_replays_change: with ``change_split_iter``, the rest solves the change's QPs again as the unsplit step
            would have, from OSQP's workspace as the step found it (saved before the capped QPs, restored on the
            second thread), so the next step starts from the unsplit change's plan and workspace; only the change
            step's command is the capped one (False, the default). Measured in docs/architecture.md, 'The change
            replayed from the saved workspace'.
        osqp_rho_max: a ceiling on OSQP's step size ``rho`` at each preparation's matrix update (in its
            refactorisation): where the last QP's adaptation left it above, the next QPs start from this value (None,
            the default: kept). OSQP still adapts it within each QP. Measured in docs/architecture.md, 'The wake of a
            reference change'.
        osqp_plain_qp_cap: OSQP iterations at most in each QP of a step that is neither a reference change nor a
            cold start, the iterate at the cap taken and carried into the next step (``rti``/``sqp``; 0, the default:
            off, ``osqp_max_iter`` only). Measured in docs/architecture.md, 'The wake of a reference change'.
        osqp_plain_cap_run: with ``osqp_plain_qp_cap``, at most this many plain steps in a row with a QP at the cap,
            the next plain step uncapped (0, the default: no limit). Measured in docs/architecture.md, 'The wake of
            a reference change'.
        osqp_change_rho: OSQP's step size ``rho`` (dimensionless) a reference change's QPs start from
            (``rti``/``sqp``; :mod:`~.change_rho`): "off" (the default: as the steps before left it), "last" (the value
            OSQP's adaptation reached in the last change's first QP) or "kind" (so per kind of change: the
            supply-temperature reference up, down or unchanged); one refactorisation more in the change's step;
            "last_each" / "kind_each": so each QP of the change. Not
            with ``osqp_rho_reset`` on "change". ``osqp_change_rho_restore`` (off by default): the first preparation
            after a change sets the step size back to the value before the change. ``osqp_change_rho_interval``
            (iterations in [0, 1000], 0 the default: off) and ``osqp_change_rho_tolerance`` (a factor in (1, 100],
            0 the default: OSQP's 5; only with an interval): OSQP's step size adapted so often (where its estimate
            differs by more than that factor) in a change's QPs; the generated solver only (``osqp_codegen``; with the
            Python interface, or after a fallback to it, the interval does nothing). None of the four with
            ``change_split_iter``. Measured in
            docs/architecture.md, 'The change's step size'.
        osqp_cap_retry_rho: a QP that reaches ``osqp_max_iter`` OSQP iterations (``rti``/``sqp``; not a split
            change's or a plain step's own cap) is solved once more with OSQP's step size ``rho`` (dimensionless) set
            to this value (3e-3, the default since docs/robustness.md sec. 2.44; 0: off; else in [1e-6, 1e6]), or
            with ``osqp_cap_retry_share`` (0, the
            default: off; else a factor in (0, 1]; set, it replaces the default step size; with a step size other
            than 0 or the default, refused as both set) times the step size that QP started from; the matrices
            written again (one refactorisation) and the retry warm-started from the capped iterate with its
            multipliers, or with ``osqp_cap_retry_cold`` (off) from the linearisation point with zero multipliers.
            Only a QP not solved to OSQP's tolerance at the cap is retried; the retry's answer is taken where it is
            solved, or where it is an answer and the capped one is not, else OSQP's workspace is set back to its
            state before the retry; within the step's deadline (checked
            before and after the refactorisation). The step's retries: ``SolveResult.extra["cap_retries"]``. With
            ``solver="ipopt"`` the step size does nothing (as ``osqp_max_iter``); the share and the cold retry are
            refused there. Only steps whose QP reaches the cap change. Measured in docs/robustness.md sec. 2.40.
        osqp_cap_retry_on_cold_start: with the retry set (``osqp_cap_retry_rho`` / ``osqp_cap_retry_share``), a cold
            start's QPs (the first step after the controller is built or reset, or after a failed step, whose reset
            the next step starts cold from) retried at the cap as any later step's (True), or not (False, the default:
            the capped answer taken, or the step failing, as without the retry; the steps after retry again). A cold
            start's QPs iterate from a guess, and an exact answer there can put the run on another operating point
            (the PTC-line step down: docs/robustness.md sec. 2.44). Without a retry set it does nothing.
        osqp_change_rho_hold: a reference change's QPs after the first run at a held OSQP step size ``rho``
            (dimensionless), OSQP's adaptation off in them: "end" the value the first QP ended with, "start" the value
            it started with ("off", the default: OSQP adapts them as set up), so the second QP's late raise (1e-4 ->
            0.03-0.10) is not made and the steps after the change start from the held value (with
            ``osqp_change_rho_restore``: the value before the change). The
            adaptation is switched off in the generated solver only (``osqp_codegen``; with the Python interface
            "start" only sets the second QP's start; "end" is refused there). Not with
            ``change_split_iter``, with ``osqp_rho_reset`` on "preparation" or with ``osqp_change_rho``'s "_each"
            modes (each overrides the held value). Measured slower (the change's later QPs want the raise: 1200 -> 3025-4935 OSQP
            iterations on the solve-time loop's seeds 1-3; "end" falls back) in docs/architecture.md, 'The change's
            second QP held'.
        valve_a_reversal_share: the share of a move of valve a that reverses its last applied move (both at least
            ``valve_a_reversal_min_pct`` (% of travel)) applied, in (0, 1], 1 off (:mod:`~.reversal_damping`: the
            Gauss-Newton iteration's two-cycle where valve a's pull depends on valve a, the plan alternating between
            valve a shut and open). 0.3 (the default): measured in docs/identification.md, "The recirculation traced
            again" (the full built-in bench lower in seven scenarios, chiller +0.0003).
        valve_a_hold_shortfall_c: degC in [0, 20]; while the heater command is at its power limit (the range's top
            or, with ``ocp.ptc_limit``, the PTC line at the heater estimate) and the supply reading is more than this
            below its reference, a move of valve a towards shut is not applied (:mod:`~.valve_a_hold`: heater-limited heating on a box whose air enters warmer than
            the core's water, where the plans alternate between storing the heater's heat in the body and
            releasing it). 0, the default: off. Measured in docs/identification.md, "Recirculation in
            heater-limited heating, traced".
    """

    dt_s: float = 1.0
    ocp: OcpSpec = field(default_factory=OcpSpec)
    solver: str = "rti"
    osqp_eps: float = 1e-4
    osqp_max_iter: int = 1000
    osqp_check_termination: int = 5
    osqp_scaling: int = 10
    osqp_alpha: float = 1.6
    osqp_check_dualgap: bool = True
    osqp_first_pass_iter: int = 0
    osqp_accept_max_iter: bool = False
    sqp_max_iter: int = 5
    levenberg_marquardt: float = 0.1
    cold_start_qps: int = 10
    reference_change_qps: int = 2
    sqp_tol: float = 2e-2
    rti_step_fractions: tuple[float, ...] = ()
    rti_trust_radii: tuple[float, ...] = ()
    rti_reversal_search: float = 0.05
    rti_reversal_wait_steps: int = 20
    rti_reversal_repeat: bool = False
    rti_reversal_margin: float = 0.1
    rti_reversal_bound_only: bool = False
    rti_reversal_second_qp: str = "off"
    rti_valve_a_prox: float = 0.0
    ipopt_tol: float = 1e-6
    ipopt_max_iter: int = 300
    deadline_s: float = 0.5
    plan_fallback_s: float = 30.0
    jit: bool = False
    codegen: bool = True
    water_prediction: str = "hold"
    chiller_setpoint_c: float = 5.0
    initial_command: Command = field(default_factory=Command)
    ekf: EkfSettings = field(default_factory=EkfSettings)
    priorities: bool = True
    reach_every_s: float = 10.0
    reach_skip_unmoved: bool = False
    reach_deferred: bool = True
    reach_background: bool = True
    reach_changes_deferred: bool = True
    flow_trade_c: float | None = 0.05
    bound_heater_estimate: bool = False
    osqp_codegen: bool = True
    osqp_scaling_interval: int = 1
    ring_detune: float = 1.0
    ring_amplitude_c: float = 0.6
    ring_window_s: float = 40.0
    ring_crossings: int = 3
    ring_floor: float = 0.05
    ring_relax_s: float = 30.0
    start_rate_share: float = 0.4
    start_caution_s: float = 10.0
    start_caution_scope: str = "valve_a_opening"
    start_caution_in_qp: bool | str = True
    valve_a_weight_on_duty: bool = False
    valve_a_weight_on_duty_open_pct: float = 0.0
    valve_a_weight_on_duty_scale: float = 1.0
    steady_start: bool = False
    choose_offset_placement: bool = True
    placement_q_heater_air_c: float = 0.01
    placement_window_s: float = 60.0
    placement_ratio: float = 0.6
    placement_evidence: float = 1.5
    placement_cap: float = 50.0
    placement_margin: float = 50.0
    placement_from_response: bool = True
    placement_warm_switch: bool = True
    placement_dead_time_hold_s: float = 6.0
    placement_sign_move_pct: float = 20.0
    placement_sign_change_c: float = 0.5
    placement_sign_window_s: float = 15.0
    placement_sign_rest_s: float = 10.0
    placement_sign_rest_hold_s: float = 0.0
    rti_relinearise_every: int = 1
    rti_relinearise_move: float = 0.3
    steady_start_on: str = "any"
    osqp_rho_reset: float | None = None
    osqp_rho_reset_on: str = "preparation"
    reweigh_in_place: bool = False
    change_split_iter: int = 0
    change_split_thread: bool = True
    split_every_step: bool = False
    split_keeps_rho: bool = False
    split_replays_change: bool = False
    osqp_rho_max: float | None = None
    osqp_plain_qp_cap: int = 0
    osqp_plain_cap_run: int = 0
    osqp_change_rho: str = "off"
    osqp_change_rho_restore: bool = False
    osqp_change_rho_interval: int = 0
    osqp_change_rho_tolerance: float = 0.0
    osqp_cap_retry_rho: float = DEFAULT_CAP_RETRY_RHO
    osqp_cap_retry_share: float = 0.0
    osqp_cap_retry_cold: bool = False
    osqp_cap_retry_on_cold_start: bool = False
    osqp_change_rho_hold: str = "off"
    valve_a_reversal_share: float = 0.3
    valve_a_reversal_min_pct: float = 5.0
    valve_a_hold_shortfall_c: float = 0.0

    @property
    def cap_retry_rho_used(self) -> float:
        """The retry's step size the solver gets: ``osqp_cap_retry_rho``, or 0 where ``osqp_cap_retry_share`` is
        set (the share replaces the default step size; another step size with it is refused as both set)."""
        return 0.0 if self.osqp_cap_retry_share else self.osqp_cap_retry_rho

    def __post_init__(self) -> None:
        p = "MpcSettings"
        check_number(f"{p}.dt_s", self.dt_s, 0.0, 60.0, lo_open=True)
        if not isinstance(self.ocp, OcpSpec):
            raise InvalidSettings(f"{p}.ocp must be an OcpSpec")
        self.ocp.validate(self.dt_s, f"{p}.ocp")
        if self.solver not in SOLVERS:
            raise InvalidSettings(f"{p}.solver = {self.solver!r} must be one of {list(SOLVERS)}")
        check_number(f"{p}.osqp_eps", self.osqp_eps, 1e-8, 1e-1)
        check_number(f"{p}.osqp_max_iter", self.osqp_max_iter, 10, 100000, integer=True)
        check_number(f"{p}.osqp_check_termination", self.osqp_check_termination, 1, 1000, integer=True)
        check_number(f"{p}.osqp_scaling", self.osqp_scaling, 0, 100, integer=True)
        alpha = self.osqp_alpha
        if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0.0 < alpha < 2.0:
            raise InvalidSettings(f"{p}.osqp_alpha = {alpha!r} is outside the allowed open range (0, 2) "
                                  "(OSQP's relaxation)")
        check_number(f"{p}.osqp_first_pass_iter", self.osqp_first_pass_iter, 0, 1000, integer=True)
        check_number(f"{p}.osqp_scaling_interval", self.osqp_scaling_interval, 1, 100000, integer=True)
        check_number(f"{p}.sqp_max_iter", self.sqp_max_iter, 1, 100, integer=True)
        check_number(f"{p}.rti_relinearise_every", self.rti_relinearise_every, 1, 1000, integer=True)
        check_number(f"{p}.rti_relinearise_move", self.rti_relinearise_move, 0.0, 10.0, lo_open=True)
        if self.osqp_rho_reset is not None:
            _check_or_off(f"{p}.osqp_rho_reset", self.osqp_rho_reset, 1e-6, 1e6, "None")
        check_flag(f"{p}.reweigh_in_place", self.reweigh_in_place)
        check_number(f"{p}.change_split_iter", self.change_split_iter, 0, self.osqp_max_iter, integer=True)
        check_flag(f"{p}.change_split_thread", self.change_split_thread)
        check_flag(f"{p}.split_every_step", self.split_every_step)
        check_flag(f"{p}.split_keeps_rho", self.split_keeps_rho)
        check_flag(f"{p}.split_replays_change", self.split_replays_change)
        if self.split_replays_change and self.split_keeps_rho:
            raise InvalidSettings(f"{p}.split_replays_change and {p}.split_keeps_rho are both True; allowed: one of "
                                  "them (the replay restores the step size with OSQP's whole workspace)")
        if self.change_split_iter and self.solver not in ("rti", "sqp"):
            raise InvalidSettings(f"{p}.change_split_iter = {self.change_split_iter!r} needs solver 'rti' or 'sqp' "
                                  f"(the OSQP solvers; solver is {self.solver!r}); 0 turns it off")
        for name in ("split_every_step", "split_keeps_rho", "split_replays_change"):
            if getattr(self, name) and not self.change_split_iter:
                raise InvalidSettings(f"{p}.{name} needs change_split_iter in [1, {self.osqp_max_iter}] "
                                      "(the cap it splits at)")
        if self.osqp_rho_max is not None:
            _check_or_off(f"{p}.osqp_rho_max", self.osqp_rho_max, 1e-6, 1e6, "None")
        check_number(f"{p}.osqp_plain_qp_cap", self.osqp_plain_qp_cap, 0, self.osqp_max_iter, integer=True)
        check_number(f"{p}.osqp_plain_cap_run", self.osqp_plain_cap_run, 0, 1000, integer=True)
        if self.osqp_plain_cap_run and not self.osqp_plain_qp_cap:
            raise InvalidSettings(f"{p}.osqp_plain_cap_run needs osqp_plain_qp_cap in [1, {self.osqp_max_iter}] "
                                  "(the cap whose run it limits)")
        try:
            check_change_rho(f"{p}.osqp_change_rho", self.osqp_change_rho, self.osqp_change_rho_restore)
            check_adaptation(f"{p}.osqp_change_rho_interval", self.osqp_change_rho_interval,
                             self.osqp_change_rho_tolerance)
            check_hold(f"{p}.osqp_change_rho_hold", self.osqp_change_rho_hold)
            check_hold_with(f"{p}.osqp_change_rho_hold", self.osqp_change_rho_hold, self.osqp_change_rho,
                            self.osqp_rho_reset, self.osqp_rho_reset_on, self.osqp_codegen, prefix="osqp_")
            check_cap_retry(f"{p}.osqp_cap_retry", self.osqp_cap_retry_rho, 0.0, False)
            explicit_rho = self.osqp_cap_retry_rho not in (0.0, DEFAULT_CAP_RETRY_RHO)
            check_cap_retry(f"{p}.osqp_cap_retry", self.osqp_cap_retry_rho if explicit_rho else 0.0,
                            self.osqp_cap_retry_share, self.osqp_cap_retry_cold)
        except ValueError as exc:
            raise InvalidSettings(str(exc)) from None
        check_flag(f"{p}.osqp_cap_retry_on_cold_start", self.osqp_cap_retry_on_cold_start)
        if self.solver not in ("rti", "sqp") and (self.osqp_cap_retry_share or self.osqp_cap_retry_cold):
            raise InvalidSettings(f"{p}.osqp_cap_retry_share / osqp_cap_retry_cold with "
                                  f"{p}.solver = {self.solver!r}: OSQP's retry at its cap; allowed: solver 'rti' or "
                                  "'sqp' with them, or both off (0, False)")
        if self.solver not in ("rti", "sqp") and self.rti_valve_a_prox:
            raise InvalidSettings(f"{p}.rti_valve_a_prox = {self.rti_valve_a_prox!r} with {p}.solver = "
                                  f"{self.solver!r}: a term of the OSQP solvers' QP; allowed: solver 'rti' or 'sqp' "
                                  "with it, or 0 (off)")
        if self.osqp_change_rho_tolerance and not self.osqp_change_rho_interval:
            raise InvalidSettings(f"{p}.osqp_change_rho_tolerance = {self.osqp_change_rho_tolerance!r} needs "
                                  f"{p}.osqp_change_rho_interval in [1, 1000] (the adaptation it tunes)")
        if self.change_split_iter and (self.osqp_change_rho != "off" or self.osqp_change_rho_restore
                                       or self.osqp_change_rho_interval or self.osqp_change_rho_hold != "off"):
            raise InvalidSettings(f"{p}.osqp_change_rho / osqp_change_rho_restore / osqp_change_rho_interval / "
                                  f"osqp_change_rho_hold with "
                                  f"{p}.change_split_iter = {self.change_split_iter}: not supported (a split change's "
                                  "rest runs after the change is closed); allowed: change_split_iter 0 with them")
        if self.osqp_change_rho != "off" and self.osqp_rho_reset is not None and self.osqp_rho_reset_on == "change":
            raise InvalidSettings(f"{p}.osqp_change_rho = {self.osqp_change_rho!r} and {p}.osqp_rho_reset with "
                                  "osqp_rho_reset_on 'change' both set a change's step size; allowed: one of them")
        if self.osqp_rho_reset_on not in RHO_RESET_ON:
            raise InvalidSettings(f"{p}.osqp_rho_reset_on = {self.osqp_rho_reset_on!r} must be one of {list(RHO_RESET_ON)}")
        check_number(f"{p}.sqp_tol", self.sqp_tol, 1e-10, 1.0, lo_open=True)
        check_number(f"{p}.levenberg_marquardt", self.levenberg_marquardt, 0.0, 1e4)
        check_number(f"{p}.cold_start_qps", self.cold_start_qps, 1, 100, integer=True)
        check_number(f"{p}.reference_change_qps", self.reference_change_qps, 1, 100, integer=True)
        if not isinstance(self.rti_trust_radii, tuple):
            raise InvalidSettings(f"{p}.rti_trust_radii must be a tuple of decreasing radii in (0, 1)")
        try:
            check_radii(self.rti_trust_radii)
        except ValueError as exc:
            raise InvalidSettings(f"{p}.rti_trust_radii: {exc}") from None
        try:
            check_share(f"{p}.rti_reversal_search", self.rti_reversal_search)
            check_wait(f"{p}.rti_reversal_wait_steps", self.rti_reversal_wait_steps)
            check_flag(f"{p}.rti_reversal_repeat", self.rti_reversal_repeat)
            check_share(f"{p}.rti_reversal_margin", self.rti_reversal_margin, "the QP plan's cost")
            check_flag(f"{p}.rti_reversal_bound_only", self.rti_reversal_bound_only)
            check_second_qp(f"{p}.rti_reversal_second_qp", self.rti_reversal_second_qp)
            check_second_qp_with(f"{p}.rti_reversal_second_qp", self.rti_reversal_second_qp, "rti_reversal_search",
                                 self.rti_reversal_search, self.solver == "rti" and not self.split_every_step,
                                 f"{p}.solver = {self.solver!r} / {p}.split_every_step = {self.split_every_step!r}",
                                 "solver 'rti' and split_every_step False")
            check_prox(f"{p}.rti_valve_a_prox", self.rti_valve_a_prox)
        except ValueError as exc:
            raise InvalidSettings(str(exc)) from None
        if not isinstance(self.rti_step_fractions, tuple) or len(self.rti_step_fractions) > 8:
            raise InvalidSettings(f"{p}.rti_step_fractions must be a tuple of at most 8 fractions in (0, 1)")
        for i, a in enumerate(self.rti_step_fractions):
            check_number(f"{p}.rti_step_fractions[{i}]", a, 0.0, 1.0, lo_open=True)
            if a >= 1.0:
                raise InvalidSettings(f"{p}.rti_step_fractions[{i}] = {a!r} must be below 1 (range (0, 1))")
        check_number(f"{p}.ipopt_tol", self.ipopt_tol, 1e-12, 1e-2, lo_open=True)
        check_number(f"{p}.ipopt_max_iter", self.ipopt_max_iter, 1, 100000, integer=True)
        check_number(f"{p}.deadline_s", self.deadline_s, 0.0, 3600.0, lo_open=True)
        check_number(f"{p}.plan_fallback_s", self.plan_fallback_s, 0.0, 3600.0)
        check_flag(f"{p}.jit", self.jit)
        check_flag(f"{p}.codegen", self.codegen)
        if self.water_prediction not in ("hold", "setpoint"):
            raise InvalidSettings(f"{p}.water_prediction = {self.water_prediction!r} must be 'hold' or 'setpoint'")
        check_number(f"{p}.chiller_setpoint_c", self.chiller_setpoint_c, -10.0, 30.0)
        if not isinstance(self.initial_command, Command):
            raise InvalidSettings(f"{p}.initial_command must be a Command")
        u = self.initial_command.vector()
        for name, value in zip(INPUTS, u):
            hi = 300.0 if name.endswith("_w") else 100.0
            check_number(f"{p}.initial_command.{name}", value, 0.0, hi)
        if not isinstance(self.ekf, EkfSettings):
            raise InvalidSettings(f"{p}.ekf must be an EkfSettings")
        self.ekf.validate(f"{p}.ekf")
        for flag in ("priorities", "reach_skip_unmoved", "reach_deferred", "reach_background", "reach_changes_deferred",
                     "osqp_accept_max_iter", "osqp_codegen", "steady_start",
                     "osqp_check_dualgap"):
            check_flag(f"{p}.{flag}", getattr(self, flag))
        check_steady_start_on(f"{p}.steady_start_on", self.steady_start_on, InvalidSettings)
        if self.reach_background and not self.reach_deferred:
            raise InvalidSettings(f"{p}.reach_background = True needs {p}.reach_deferred = True "
                                  "(the solve's answer is used from the next step on)")
        check_number(f"{p}.reach_every_s", self.reach_every_s, 1.0, 3600.0)
        if self.flow_trade_c is not None:
            check_number(f"{p}.flow_trade_c", self.flow_trade_c, 0.0, 10.0, lo_open=True)
        check_number(f"{p}.ring_detune", self.ring_detune, 0.0, 1.0, lo_open=True)
        check_number(f"{p}.ring_amplitude_c", self.ring_amplitude_c, 0.0, 20.0, lo_open=True)
        check_number(f"{p}.ring_window_s", self.ring_window_s, self.dt_s, 3600.0)
        check_number(f"{p}.ring_crossings", self.ring_crossings, 1, 100, integer=True)
        check_number(f"{p}.ring_floor", self.ring_floor, 0.0, 1.0, lo_open=True)
        check_number(f"{p}.ring_relax_s", self.ring_relax_s, self.dt_s, 3600.0)
        check_number(f"{p}.start_rate_share", self.start_rate_share, 0.0, 1.0, lo_open=True)
        check_number(f"{p}.start_caution_s", self.start_caution_s, 0.0, 600.0)
        if self.start_caution_scope not in START_CAUTION_SCOPES:
            raise InvalidSettings(f"{p}.start_caution_scope = {self.start_caution_scope!r} must be one of "
                                  f"{list(START_CAUTION_SCOPES)}")
        mode = self.start_caution_in_qp
        if not (mode is True or mode is False or (isinstance(mode, str) and mode == START_CAUTION_WHEN_BINDING)):
            raise InvalidSettings(f"{p}.start_caution_in_qp = {self.start_caution_in_qp!r} must be one of "
                                  f"{list(START_CAUTION_IN_QP)}")
        check_number(f"{p}.valve_a_reversal_share", self.valve_a_reversal_share, 0.0, 1.0, lo_open=True)
        check_number(f"{p}.valve_a_reversal_min_pct", self.valve_a_reversal_min_pct, 0.0, 100.0)
        check_number(f"{p}.valve_a_hold_shortfall_c", self.valve_a_hold_shortfall_c, 0.0, 20.0)
        check_flag(f"{p}.valve_a_weight_on_duty", self.valve_a_weight_on_duty)
        if self.valve_a_weight_on_duty and self.ocp.weights.valve_a_reserve_per_pct2 > 0:
            raise InvalidSettings(f"{p}.valve_a_weight_on_duty = True with {p}.ocp.weights.valve_a_reserve_per_pct2 > 0: "
                                  "the heater reserve sets valve a's weight from the heater command alone, so the "
                                  "setting would do nothing; use one or the other")
        check_number(f"{p}.valve_a_weight_on_duty_open_pct", self.valve_a_weight_on_duty_open_pct, 0.0, 100.0)
        if self.valve_a_weight_on_duty_open_pct > 0 and not self.valve_a_weight_on_duty:
            raise InvalidSettings(f"{p}.valve_a_weight_on_duty_open_pct = {self.valve_a_weight_on_duty_open_pct} > 0 "
                                  f"with {p}.valve_a_weight_on_duty = False: the opening gates the setting's weight, "
                                  "so alone it would do nothing")
        check_number(f"{p}.valve_a_weight_on_duty_scale", self.valve_a_weight_on_duty_scale, 0.0, 1000.0, lo_open=True)
        if self.valve_a_weight_on_duty_scale != 1.0 and not self.valve_a_weight_on_duty:
            raise InvalidSettings(f"{p}.valve_a_weight_on_duty_scale = {self.valve_a_weight_on_duty_scale} with "
                                  f"{p}.valve_a_weight_on_duty = False: it scales the setting's weight, so alone it "
                                  "would do nothing")
        check_flag(f"{p}.choose_offset_placement", self.choose_offset_placement)
        check_number(f"{p}.placement_q_heater_air_c", self.placement_q_heater_air_c, 0.0, 1.0, lo_open=True)
        check_number(f"{p}.placement_window_s", self.placement_window_s, self.dt_s, 3600.0)
        check_number(f"{p}.placement_ratio", self.placement_ratio, 0.0, 1.0, lo_open=True)
        check_number(f"{p}.placement_evidence", self.placement_evidence, 0.0, 100.0)
        check_number(f"{p}.placement_cap", self.placement_cap, 0.0, 1e9, lo_open=True)
        if self.placement_margin != math.inf:
            _check_or_off(f"{p}.placement_margin", self.placement_margin, 0.0, 1e9, "inf", lo_open=True)
        check_flag(f"{p}.placement_from_response", self.placement_from_response)
        check_flag(f"{p}.placement_warm_switch", self.placement_warm_switch)
        check_number(f"{p}.placement_dead_time_hold_s", self.placement_dead_time_hold_s, 0.0, 600.0)
        self._validate_sign_check(p)

    def _validate_sign_check(self, p: str) -> None:
        """The fields of the valve a sign check (:mod:`~.sign_check`)."""
        if self.placement_sign_move_pct != math.inf:
            _check_or_off(f"{p}.placement_sign_move_pct", self.placement_sign_move_pct, 1.0, 100.0, "inf")
        check_number(f"{p}.placement_sign_change_c", self.placement_sign_change_c, 0.1, 5.0)
        check_number(f"{p}.placement_sign_window_s", self.placement_sign_window_s, 2.0, 120.0)
        check_number(f"{p}.placement_sign_rest_s", self.placement_sign_rest_s, 2.0, 600.0)
        check_number(f"{p}.placement_sign_rest_hold_s", self.placement_sign_rest_hold_s, 0.0, 600.0)


def _check_or_off(name: str, value, lo: float, hi: float, off: str, lo_open: bool = False) -> None:
    """:func:`check_number` for a setting that also takes an off value (``off``), which the error names too."""
    try:
        check_number(name, value, lo, hi, lo_open=lo_open)
    except InvalidSettings as exc:
        raise InvalidSettings(f"{exc}; or {off} (off)") from None


def _with_model_effects(settings: MpcSettings, model: RefinedModel | None) -> MpcSettings:
    """Settings whose prediction model holds the refined model's effects, the structure its parameters were
    identified with, and the controller's own effects as configured (``RefinedModel.prediction_effects``; the
    PTC power fall stays a constraint where ``ptc_limit`` carries it); where the file has the bypass split's
    flow dependence, its identified exponent is the estimator's prior."""
    if model is None:
        return settings
    ocp = settings.ocp
    effects = tuple(e for e in model.prediction_effects(ocp.model_effects)
                    if not (e == "ptc_power_fall" and ocp.ptc_limit))
    settings = dataclasses.replace(settings, ocp=dataclasses.replace(ocp, model_effects=effects))
    if "bypass_flow" in model.effects:  # identified with the model's own exponent: the prediction starts from it
        settings = dataclasses.replace(settings, ekf=dataclasses.replace(
            settings.ekf, bypass_flow_exponent_prior=float(model.parameters.bypass_flow_exponent)))
    return settings


def _chooses_placement(ekf: EkfSettings) -> bool:
    """True where the filter's settings leave the heater outlet reading's error to its own offset (the default),
    the placement ``MpcSettings.choose_offset_placement`` may move to the heater air (:mod:`~.placement`); settings
    that place it themselves (an offset of the core path's air, no reading or no offset of its own) are kept."""
    return (ekf.use_heater_outlet and ekf.q_heater_outlet_offset_c > 0.0 and ekf.q_heater_air_offset_c == 0.0
            and ekf.q_cooler_offset_c == 0.0)


def _delay_to_estimator(settings: MpcSettings, params: Parameters) -> tuple[MpcSettings, Parameters]:
    """A model file's transport delay as the estimator's starting dead time rather than a lag chain in the
    model, where the estimator handles dead times that long (``EkfSettings.dead_time_max_s``): the delay the log
    showed and the one the readings show are then one estimate (docs/identification.md, "The refined model in
    the controller"). Longer delays stay in the model."""
    delay_s = round(params.transport_delay_s / settings.dt_s) * settings.dt_s
    if not 0.0 < delay_s <= settings.ekf.dead_time_max_s:
        return settings, params
    ekf = dataclasses.replace(settings.ekf, dead_time_initial_s=float(delay_s))
    return dataclasses.replace(settings, ekf=ekf), params.replace(transport_delay_s=0.0)


def _model_symbols(model: HvacModel) -> tuple:
    """CasADi symbols of ``model``'s states, inputs and disturbances (x, u, d)."""
    import casadi as ca
    return tuple(ca.SX.sym(n, len(s)) for n, s in (("x", model.states), ("u", model.inputs),
                                                    ("d", model.disturbances)))


def _heater_inlet_function(model: HvacModel) -> Callable | None:
    """(x, u, d) -> air entering the heater (degC) of ``model`` where discovered terms or the literal cooler fit
    change it (a term at the cooler core's outlet or on the air entering the box, effect ``cooler_literal_fit``),
    else None (the cooler equation alone, as the trapped-air guard reads it)."""
    if "cooler_literal_fit" not in model.effects and not any(t.location in ("cooler_out", "box_in")
                                                             for t in model.terms):
        return None
    import casadi as ca
    x, u, d = _model_symbols(model)
    t_cooler = model.algebraic(x, u, d, model.params)["t_cooler"]
    return ca.Function("heater_inlet", [x, u, d], [t_cooler])


def _heater_body_rate_function(model: HvacModel) -> Callable | None:
    """(x, u, d, p) -> the heater body's rate of change (degC/s) of ``model`` with the model parameters ``p``
    (``HvacModel.p_default`` order: those the prediction uses, the learned bypass-flow exponent and anchor
    included) where a discovered term adds a heat flow to the body (a ``heater_body`` term), else None (the
    trapped-air guard's bound relaxes towards the air then, :class:`~.ocp.HeaterOffBound`)."""
    if not any(t.location == "heater_body" for t in model.terms):
        return None
    import casadi as ca
    x, u, d = _model_symbols(model)
    p = ca.SX.sym("p", len(model.p_default))
    rate = model.ode(x, u, d, p)[model.states.index("heater_temp_c")]
    return ca.Function("heater_body_rate", [x, u, d, p], [rate])


def _heater_reserve(problem: TrackingProblem, dt_s: float) -> HeaterReserve | None:
    """The heater reserve's gate where ``Weights.valve_a_reserve_per_pct2`` is above 0 (:mod:`.reserve`), else None."""
    w = problem.spec.weights
    if w.valve_a_reserve_per_pct2 <= 0:
        return None
    return HeaterReserve(w.valve_a_reserve_per_pct2, w.valve_a_heating_per_pct2, dt_s,
                         ramp_s=w.valve_a_reserve_ramp_s, short_c=w.valve_a_reserve_short_c,
                         ptc_hold_s=w.valve_a_reserve_ptc_hold_s)


class MpcController:
    """Receding-horizon controller of all six actuators (Controller protocol).

    Instances share nothing: each owns its CasADi functions, OSQP workspace, estimator and
    fallback controller, so several can run side by side in one process.
    """

    def __init__(self, params: Parameters | None = None, settings: MpcSettings | None = None, *,
                 solver_factory: Callable[[TrackingProblem], Any] | None = None, model: RefinedModel | None = None):
        """``solver_factory(problem)`` may supply another solver with the interface of
        :class:`RtiOsqpSolver` (``reset``, ``prepare``, ``feedback``, ``fail_next``), e.g. the
        do-mpc reference of the solve-time benchmark; by default ``settings.solver`` decides.
        ``model``: a refined model (``hvac_mpc.models.model_file.load``): its parameters (unless
        ``params`` is given), effects and discovered terms enter the prediction and the estimator; the
        controller keeps its own ``bypass_flow`` as configured, and a transport delay up to the estimator's
        ``dead_time_max_s`` starts the estimator's dead time instead of a lag chain (docs/identification.md,
        "The refined model in the controller")."""
        self.params = params or (model.parameters if model is not None else Parameters())
        self.settings = _with_model_effects(settings or MpcSettings(), model)
        if model is not None:
            self.settings, self.params = _delay_to_estimator(self.settings, self.params)
        terms = model.terms if model is not None else ()
        s = self.settings
        if "bypass_flow" in s.ocp.model_effects:  # one exponent for every solver: the estimator's prior
            self.params = self.params.replace(bypass_flow_exponent=s.ekf.bypass_flow_exponent_prior)
        self.dt_s = s.dt_s
        self.problem = TrackingProblem(self.params, s.ocp, s.dt_s, terms=terms)
        self.jit_active = False
        if s.jit:
            self.jit_active = _try_jit(self.problem)
        self.solver = solver_factory(self.problem) if solver_factory is not None else self._make_solver()
        # the estimator sees the commands really applied (fallbacks included), so it keeps the PTC
        # power fall in its model even where the OCP carries it as a constraint (OcpSpec.ptc_limit)
        ekf_model = self.problem.model
        if s.ocp.ptc_limit and "ptc_power_fall" not in s.ocp.model_effects:
            ekf_model = HvacModel(self.params, tuple(s.ocp.model_effects) + ("ptc_power_fall",), dt_s=s.dt_s,
                                  terms=terms)
        # the bypass-flow exponent is learned, and the placement chosen, only where the prediction can take the
        # model parameters at run time (``set_parameters``: the RTI/SQP solver and, since the stage-wise NLP takes
        # them as parameters, the converged references too, so every contender runs the same estimator)
        self.ekf = DisturbanceEkf(ekf_model, s.ekf, s.dt_s, s.water_prediction,
                                  learn_bypass_flow=hasattr(self.solver, "set_parameters"))
        self._filters = [self.ekf]  # with choose_offset_placement, the heater air's filter too (mpc/placement.py)
        self.placement = None
        if s.choose_offset_placement and _chooses_placement(s.ekf) and hasattr(self.solver, "set_parameters"):
            air_settings = dataclasses.replace(s.ekf, q_heater_air_offset_c=s.placement_q_heater_air_c,
                                               q_heater_outlet_offset_c=0.0)
            self._filters.append(DisturbanceEkf(ekf_model, air_settings, s.dt_s, s.water_prediction,
                                                learn_bypass_flow=True, name="ekf_heater_air"))
            self.placement = PlacementChoice(s.placement_window_s, s.placement_ratio, s.placement_evidence, s.dt_s,
                                             s.placement_cap, s.placement_margin,
                                             hold=int(round(s.placement_dead_time_hold_s / s.dt_s)))
        self.sign_check = None  # with placement_sign_move_pct: the sign of valve a's answer (mpc/sign_check.py)
        if self.placement is not None and s.placement_sign_move_pct != math.inf:
            self.sign_check = ValveSignCheck(s.placement_sign_move_pct, s.placement_sign_change_c,
                                             s.placement_sign_window_s, s.placement_sign_rest_s, s.dt_s,
                                             s.placement_sign_rest_hold_s)
        # each filter's predicted change of the air in one call (the check's held commands; by the filter's id)
        self._air_change = {id(f): HeldAirChange(f, self.sign_check.horizon) for f in self._filters
                            } if self.sign_check is not None else {}
        self._sign_switch = False  # a verdict of the sign check: the next step predicts with the other filter
        self._pending = None  # the other filter's update and time update of the last step, not yet run
        pb = self.problem
        self.reach = ReachableFlow(pb.model, pb.u_lo_phys, pb.u_hi_phys, pb.heater_max_phys, self.params,
                                   every_s=s.reach_every_s, skip_unmoved=s.reach_skip_unmoved,
                                   deferred=s.reach_deferred, background=s.reach_background,
                                   changes_deferred=s.reach_changes_deferred and s.reach_deferred
                                   ) if s.priorities else None
        self.heater_bound = HeaterOffBound(self.params, s.dt_s)
        self.readiness = HeaterReadiness(pb) if pb.spec.weights.heater_ready_per_c2 > 0 else None
        self.reserve = _heater_reserve(pb, s.dt_s)
        self._heater_inlet = _heater_inlet_function(pb.model)
        self._heater_body_rate = _heater_body_rate_function(pb.model)
        self.temp_reach = SaturatedTemperature(pb.i_heater_cmd, pb.i_valve_a, s.dt_s)
        self.ring = RingGate(s.ring_amplitude_c, s.ring_window_s, s.ring_crossings, s.ring_detune, s.ring_floor,
                             s.ring_relax_s, s.dt_s) if s.ring_detune < 1.0 else None
        self.start_caution = StartCaution(s.start_rate_share, s.start_caution_s, s.dt_s, s.start_caution_scope,
                                          known_delay_s(self.params.transport_delay_s, s.ekf.dead_time_initial_s))
        self.codegen = getattr(self.solver, "codegen", None) or CodegenReport()
        if s.codegen:
            self._compile_small_functions()
        if hasattr(self.solver, "use_prediction"):
            for f in self._filters[1:]:  # each filter's fused prediction built now: a switch binds it, no rebuild
                self.solver.build_prediction(f)
            self.solver.use_prediction(self.ekf)  # prediction and QP data in one call
        self._baseline = None
        self._change_call: BackgroundCall | None = None  # the last split change's rest (finish_change), not collected
        self._change_plan: np.ndarray | None = None  # the rest's converged plan (scaled inputs), set on its thread
        self._own_worker: BackgroundWorker | None = None  # its thread where the reachable-flow solve has none
        if s.change_split_iter and s.change_split_thread:
            self._worker(create=True).start()  # with the controller, not inside a step
        self.reset()

    def _compile_small_functions(self) -> None:
        """The estimators' time and measurement updates, their open-loop shadows and the reachable-flow check's
        outputs as generated C (:func:`~.codegen.compiled`; each the interpreted function where it cannot be built)."""
        done: dict[str, Any] = {}  # structure key -> the generated function: one load per structure

        def once(fn):
            fn = shared(fn)
            key = structure_key(fn)
            if key not in done:
                done[key] = compiled(fn, self.codegen)
            return done[key]
        for f in self._filters:
            f.use_functions(compiled(shared(f.predict_fn), self.codegen), compiled(shared(f.update_fn), self.codegen))
            if f.shadow is not None:  # the filters' shadows are one function where they share the model
                f.shadow.use_functions(once(f.shadow.step_fn), once(f.shadow.air_fn))
        for change in self._air_change.values():
            change.use_function(compiled(change.function, self.codegen))
        if self.reach is not None:
            self.reach.use_out_function(once(self.reach.out_fn))
            self.reach.use_flows_function(once(self.reach.flows_fn))

    def _make_solver(self):
        s, pb = self.settings, self.problem
        if s.solver == "ipopt":
            from .ipopt_reference import IpoptReferenceSolver
            return IpoptReferenceSolver(pb, tol=s.ipopt_tol, max_iter=s.ipopt_max_iter)
        sqp_iter = 1 if s.solver == "rti" else s.sqp_max_iter
        return RtiOsqpSolver(pb, eps=s.osqp_eps, max_iter=s.osqp_max_iter, sqp_max_iter=sqp_iter,
                             sqp_tol=s.sqp_tol, check_termination=s.osqp_check_termination,
                             lm_inputs=s.levenberg_marquardt, cold_start_qps=s.cold_start_qps,
                             reference_change_qps=s.reference_change_qps, codegen=s.codegen,
                             scaling=s.osqp_scaling, alpha=s.osqp_alpha, check_dualgap=s.osqp_check_dualgap,
                             first_pass_iter=s.osqp_first_pass_iter, accept_max_iter=s.osqp_accept_max_iter,
                             step_fractions=s.rti_step_fractions, osqp_codegen=s.osqp_codegen,
                             scaling_interval=s.osqp_scaling_interval, steady_start=s.steady_start,
                             relinearise_every=s.rti_relinearise_every, relinearise_move=s.rti_relinearise_move,
                             steady_start_on=s.steady_start_on, rho_reset=s.osqp_rho_reset,
                             rho_reset_on=s.osqp_rho_reset_on, reweigh_in_place=s.reweigh_in_place,
                             change_split_iter=s.change_split_iter, split_every_step=s.split_every_step,
                             split_keeps_rho=s.split_keeps_rho, split_replays_change=s.split_replays_change,
                             rho_max=s.osqp_rho_max, plain_qp_cap=s.osqp_plain_qp_cap,
                             trust_radii=s.rti_trust_radii, plain_cap_run=int(s.osqp_plain_cap_run),
                             reversal_search=float(s.rti_reversal_search),
                             reversal_wait_steps=int(s.rti_reversal_wait_steps),
                             reversal_repeat=bool(s.rti_reversal_repeat),
                             reversal_margin=float(s.rti_reversal_margin),
                             reversal_bound_only=bool(s.rti_reversal_bound_only),
                             reversal_second_qp=s.rti_reversal_second_qp, change_rho=s.osqp_change_rho,
                             change_rho_restore=s.osqp_change_rho_restore,
                             change_rho_interval=int(s.osqp_change_rho_interval),
                             change_rho_tolerance=float(s.osqp_change_rho_tolerance),
                             cap_retry_rho=s.cap_retry_rho_used, cap_retry_share=float(s.osqp_cap_retry_share),
                             cap_retry_cold=s.osqp_cap_retry_cold,
                             cap_retry_on_cold_start=s.osqp_cap_retry_on_cold_start,
                             change_rho_hold=s.osqp_change_rho_hold,
                             valve_a_prox=float(s.rti_valve_a_prox))

    # ------------------------------------------------------------------ protocol
    def reset(self, command: Command | None = None) -> None:
        """Forget estimates, plans and warm starts; ``command`` is the command now in force."""
        self._settle_change()
        self.u_prev = (command or self.settings.initial_command).vector().copy()
        self._valve_a_move = 0.0  # the last applied move of valve a (%), for valve_a_reversal_share
        for f in self._filters:
            f.reset()
        self._pending = None
        self._response_noted = False
        self._switch_setpoint = None
        if self.placement is not None:
            self.placement.reset()
            self._use_filter(self._filters[0])
        if self.sign_check is not None:
            self.sign_check.reset()
        self._sign_switch = False
        self.solver.reset()
        self._plan: tuple[np.ndarray, float] | None = None  # (U scaled (N, nu), age s), unscaled when used
        self._reference: Reference | None = None
        self._prepared_for_next = False
        self._in_baseline = False
        self._last_solution: SolveResult | None = None
        self._u_prev_scaled: tuple[np.ndarray, np.ndarray] | None = None
        self._out_of_reach: dict = {}
        self._flow_factor = 1.0
        self._valve_a_held = False
        self._duty_weight_on = False  # valve_a_weight_on_duty_open_pct: valve a opened on the duty, weighed since
        if self.reach is not None:
            self.reach.reset()
        self.temp_reach.reset()
        if self.reserve is not None:
            self.reserve.reset()
        self.heater_bound.reset()
        if self.ring is not None:
            self.ring.reset()
        self.start_caution.reset()

    def close(self) -> None:
        """End the reachable-flow solve's second thread (after the solve running on it; a split change's rest is
        collected first); a later step starts it again. Dropping the controller ends it too."""
        self._settle_change()
        if self.reach is not None:
            self.reach.close()
        if self._own_worker is not None:
            self._own_worker.close()

    def force_solver_failure(self, steps: int) -> None:
        """Make the next ``steps`` solves fail (tests of the fallback chain; this instance only)."""
        self.solver.fail_next = int(steps)

    def step(self, measurement: Measurement, reference: Reference | Mapping[str, Any]) -> StepResult:
        """One control step; never raises. See the module docstring for the fallback chain."""
        t0 = time.perf_counter()
        # a reachable-flow solve (or a split change's rest) handed to the second thread in this step starts when the
        # step ends: its Python parts would take the interpreter lock from the step (docs/architecture.md 'Slow steps')
        worker = self._worker(create=False)
        try:
            self._collect_change()  # the last change's rest: its plan prepared and the filter's time update taken
            if worker is not None:  # after the collection, whose wait lets the worker go
                worker.hold()
            self._updates_at_start = self.ekf.time_updates
            return self._step(measurement, reference, t0)
        except Exception as exc:  # noqa: BLE001 - a control step must always return a command
            return self._recover(measurement, t0, exc)
        finally:
            if worker is not None:
                worker.release()

    def _recover(self, measurement: Measurement, t0: float, exc: Exception) -> StepResult:
        """After an unexpected error: fallback command, projected, and a fresh start next step."""
        self._settle_change()
        self.solver.reset()
        self._prepared_for_next = False
        self._pending = None
        if self.placement is not None:  # the filter not in use misses this sample: it starts afresh
            for f in self._filters:
                if f is not self.ekf:
                    f.reset()
            self.placement.restart()
        try:
            cmd, fallback = self._fallback_command(measurement, self._reference)
        except Exception:  # noqa: BLE001 - nothing may escape a control step
            cmd, fallback = self.u_prev.copy(), "hold_last_command"
        if not np.all(np.isfinite(cmd)):
            cmd, fallback = self.u_prev.copy(), "hold_last_command"
        cmd = np.clip(cmd, *self.problem.command_bounds(self.u_prev))
        self.u_prev = cmd
        try:  # the time update once per step: not again where the step failed after taking it
            if self.ekf.healthy() and self.ekf.time_updates == self._updates_at_start:
                self.ekf.predict(cmd, self._setpoint(measurement))
        except Exception:  # noqa: BLE001
            self.ekf.reset()
        return StepResult(Command.from_vector(cmd), self._stats(t0, status=f"error: {exc!r}", fallback=fallback))

    # ------------------------------------------------------------------ internals
    def _setpoint(self, measurement: Measurement) -> float:
        sp = getattr(measurement, "chiller_setpoint_c", None)
        try:
            sp = float(sp)
        except (TypeError, ValueError):
            return self.settings.chiller_setpoint_c
        return sp if math.isfinite(sp) else self.settings.chiller_setpoint_c

    def _valid_reference(self, reference) -> Reference | None:
        if isinstance(reference, Reference):
            return reference
        if isinstance(reference, Mapping):
            try:
                return Reference.from_mapping(reference)
            except InvalidReference:
                return None
        return None

    def _step(self, measurement: Measurement, reference, t0: float) -> StepResult:
        s, pb = self.settings, self.problem
        self._valve_a_held = False  # this step's, also where it returns before the solve
        ref = self._valid_reference(reference)
        ref_status = None
        if ref is None:
            ref_status = "invalid reference, keeping the last valid one"
            ref = self._reference
            if ref is None:
                cmd = self.u_prev.copy()
                return StepResult(Command.from_vector(cmd), self._stats(t0, status="invalid reference",
                                                                        fallback="hold_last_command"))
        self._reference = ref
        if self.placement is not None:  # the other filter's deferred sample first, as between steps (its holds
            self._run_other_filter()  # count from this note on its clock: wait_background must not change them)
        for f in self._filters:  # the heat flow's release kept away from a change of the reference (EkfSettings)
            f.note_reference(ref.supply_temp_c, ref.volume_flow_m3s)
        setpoint = self._setpoint(measurement)
        u_in = self.u_prev
        self._switch_setpoint = setpoint
        self._choose_filter()
        # --- estimation
        if not self.ekf.healthy():
            self.ekf.initialise(measurement, self.u_prev, setpoint)
            self._prepared_for_next = False
            used = 5
        else:
            used = self.ekf.update(measurement, self.u_prev, setpoint)
        if not self.ekf.healthy():
            self.ekf.reset()
            raise FloatingPointError("state estimate is not finite")
        if self.placement is not None:
            self._placement_from_response()
            self.placement.observe(self.placement.active, self.ekf.supply_nis, self.ekf.honoured_dead_time_s)
        self._use_estimated_parameters()
        cap = self._trap_cap(measurement)  # bounds the heater estimate too: before the state is used
        x0 = pb.scale_x(self.ekf.x)
        d = self._disturbance(setpoint)
        u_prev_s = self._scaled_prev()
        heater_c = float(self.ekf.x[pb.i_heater])
        ring, start = self._ring_factor(measurement, ref), self.start_caution.factor(self.ekf.response_seen)
        if self.start_caution.scope == VALVE_A_AND_HEATER:
            ring = min(ring, start)
        bounds = pb.command_bounds(self.u_prev, cap, heater_c)  # of the command, and folded into the QP's
        if ring < 1.0:
            bounds = self._ring_slowed(bounds, ring)
        qp_bounds, u_hi_binding = bounds, None
        if start < 1.0 and self.start_caution.scope != VALVE_A_AND_HEATER:
            bounds = self._start_opening_slowed(bounds, start)
            qp_bounds, u_hi_binding = self._start_caution_bounds(bounds, qp_bounds, cap, heater_c)
        u_lo, u_hi = pb.input_bounds(self.u_prev, cap, heater_c, command=qp_bounds)
        y_ref = self._tracked_reference(ref, d, cap)
        w_y = self._output_weights(ref, d, y_ref, measurement)
        self._set_readiness(ref, d, cap, measurement)
        # --- feedback
        if not self._prepared_for_next:
            self.solver.reset()
        t_fb = time.perf_counter()
        binding = {} if u_hi_binding is None else {"u_hi_binding": u_hi_binding}
        sol = self.solver.feedback(x0, u_prev_s, d, y_ref, w_y, u_lo, u_hi, time_limit_s=s.deadline_s, **binding)
        feedback_elapsed = time.perf_counter() - t_fb
        fallback = None
        status = sol.status
        if sol.ok and feedback_elapsed > s.deadline_s:
            sol.ok = False
            status = f"deadline missed ({feedback_elapsed:.3f} s > {s.deadline_s} s)"
        if sol.ok:
            u_cmd = pb.unscale_u(sol.U[0])
            if (sol.extra.get("inexact") and not pb.heating(self.u_prev)
                    and u_cmd[pb.i_heater_cmd] < INEXACT_HEATER_OFF_W):
                u_cmd[pb.i_heater_cmd] = 0.0
            if not all_finite(u_cmd):
                sol.ok = False
                status = "non-finite command"
        if sol.ok:
            self._plan = (sol.U, 0.0)
            self._in_baseline = False
            self._last_solution = sol
        else:
            self.solver.reset()
            u_cmd, fallback = self._fallback_command(measurement, ref)
        if sol.ok:
            self._damp_reversal(u_cmd)  # the QP's answer only: a fallback's command stands as its layer made it
            self._hold_valve_a(u_cmd, heater_c, measurement, ref)
        # project onto bounds, rate limits and the trapped-air cap (np.clip costs ~10 us on 6 values)
        u_cmd = np.minimum(np.maximum(u_cmd, bounds[0]), bounds[1])
        self._valve_a_move = float(u_cmd[pb.i_valve_a] - self.u_prev[pb.i_valve_a])
        self.u_prev = u_cmd
        self._note_temperature_reach(measurement, ref, u_cmd, bounds[1])
        self._check_valve_sign(measurement, u_in, u_cmd, setpoint)
        # --- prediction and preparation of the next step
        prep_time = sol.prep_time_s
        self._prepared_for_next = False
        if sol.ok and sol.extra.get("change_split"):
            self._defer_change(u_cmd, setpoint, y_ref, w_y)
        elif sol.ok and getattr(self.solver, "fused_prediction", False):
            prep_time += self.solver.prepare_predicted(u_cmd, setpoint, self._scaled_prev(), y_ref, w_y)
            self._prepared_for_next = True
        else:
            self.ekf.predict(u_cmd, setpoint)
        if sol.ok and not self._prepared_for_next:
            prep_time += self.solver.prepare(pb.scale_x(self.ekf.x), self._scaled_prev(), self._disturbance(setpoint),
                                             y_ref, w_y)
            self._prepared_for_next = True
        if self.placement is not None:
            self._pending = (measurement, u_in, setpoint, u_cmd)
        if ref_status:
            status = f"{status}; {ref_status}"
        if used == 0:
            status = f"{status}; no finite measurement, state predicted open loop"
        stats = self._stats(t0, status=status, fallback=fallback, prep=prep_time,
                            feedback=sol.feedback_time_s, iterations=sol.iterations, qp_solves=sol.qp_solves,
                            cap=cap, healthy=True)
        stats["cold_start"] = bool(sol.extra.get("cold_start", False))
        if "binding_solved_again" in sol.extra:  # start_caution_in_qp "when_binding", while the caution lasts
            stats["start_caution_solved_again"] = bool(sol.extra["binding_solved_again"])
        if s.rti_reversal_search > 0.0:
            stats["reversal_searched"] = bool(getattr(self.solver, "reversal_searched", False))
            stats["reversal_taken"] = bool(getattr(self.solver, "reversal_taken", False))
        stats["reach_wait_s"] = self.reach.last_wait_s if self.reach is not None else 0.0
        if self.sign_check is not None:
            stats["sign_verdicts"] = self.sign_check.verdicts
        if self.settings.change_split_iter:
            stats["change_wait_s"] = self._change_wait_s
            if self._change_finish is not None:
                stats["change_finish"] = self._change_finish
        return StepResult(Command.from_vector(u_cmd), stats)

    # ------------------------------------------------------------------ a reference change split (change_split_iter)
    def _worker(self, create: bool) -> BackgroundWorker | None:
        """The controller's second thread: the reachable-flow solve's worker where it has one, else (with
        ``change_split_iter`` and ``change_split_thread``) one of the controller's own, made when ``create``."""
        if self.reach is not None and self.reach.worker is not None:
            return self.reach.worker
        if self._own_worker is None and create:
            self._own_worker = BackgroundWorker()
        return self._own_worker

    def _defer_change(self, u_cmd: np.ndarray, setpoint: float, y_ref: np.ndarray, w_y: np.ndarray) -> None:
        """Hand the rest of a split reference change (:meth:`RtiOsqpSolver.finish_change`) and the next step's
        preparation from its plan to the second thread (at once, inside the step, without
        ``change_split_thread``). The next step collects it before anything else, waiting for it if need be:
        a budget of one step, not a wall-clock deadline, so the commands do not depend on the thread."""
        thread = self.settings.change_split_thread
        self._change_call = BackgroundCall(self._finish_change, (u_cmd.copy(), setpoint, self._scaled_prev(),
                                                                 y_ref.copy(), w_y.copy()),
                                           thread=thread, worker=self._worker(create=True) if thread else None)
        self._prepared_for_next = True  # by the rest, collected at the start of the next step

    def _finish_change(self, u_cmd, setpoint, u_prev_s, y_ref, w_y) -> dict[str, Any]:
        """The second thread's part of a split change: the change's QPs to convergence, then the estimator's time
        update with the command applied and the next QP prepared at the converged plan shifted (as a step ends).
        Never raises: where it fails the solver is reset (the next step starts cold) and the time update taken."""
        t0, c0 = time.perf_counter(), time.thread_time()
        updates = self.ekf.time_updates
        sol = SolveResult(False, "not run")
        prepared = False
        self._change_plan = None
        try:
            sol = self.solver.finish_change()
            if sol.ok:
                self._change_plan = sol.U.copy()  # the fallback's plan from the next step on (read after the call)
            if sol.ok and getattr(self.solver, "fused_prediction", False):
                self.solver.prepare_predicted(u_cmd, setpoint, u_prev_s, y_ref, w_y)
                prepared = True
        except Exception:  # noqa: BLE001 - the next step starts cold instead
            prepared = False
        if not prepared:
            self.solver.reset()
            try:
                if self.ekf.time_updates == updates:
                    self.ekf.predict(u_cmd, setpoint)
            except Exception:  # noqa: BLE001 - the next step re-initialises an unhealthy filter
                self.ekf.reset()
        return {"ok": bool(sol.ok), "prepared": prepared, "iterations": int(sol.iterations),
                "qp_solves": int(sol.qp_solves), "wall_s": time.perf_counter() - t0,
                "thread_cpu_s": time.thread_time() - c0}

    def _collect_change(self) -> None:
        """At the start of a step: take the last split change's rest (waiting for it; the wait in
        ``stats["change_wait_s"]``)."""
        self._change_wait_s = 0.0
        self._change_finish = None
        call, self._change_call = self._change_call, None
        if call is None:
            return
        self._change_finish = call.result()
        self._change_wait_s = call.waited_s
        if self._change_plan is not None and self._plan is not None:
            self._plan = (self._change_plan, self._plan[1])  # the converged plan, not the capped iterate's
        if not self._change_finish["prepared"]:
            self._prepared_for_next = False

    def _settle_change(self) -> None:
        """Wait for a split change's rest still running (before the solver or the filter is touched otherwise)."""
        if self._change_call is not None:
            self._collect_change()

    def _choose_filter(self) -> None:
        """With ``choose_offset_placement``: bring the other filter up to this sample (the last step's readings
        and command) and let :class:`~.placement.PlacementChoice` choose the filter the prediction uses."""
        if self.placement is None:
            return
        self._run_other_filter()
        if not self._filters[1 - self.placement.active].healthy():
            return  # never to a filter that has not run
        if self._sign_switch:
            self._switch_on_sign()
            return
        if self.placement.decide():
            self._use_active_filter()
            if self.sign_check is not None:
                self.sign_check.abandon()

    def _use_active_filter(self) -> None:
        """Predict with the filter the choice has just made active; where that fails the filter in use stays."""
        try:
            self._use_filter(self._filters[self.placement.active])
        except Exception:
            self.placement.active = 1 - self.placement.active  # the filter in use stays
            raise

    def _check_valve_sign(self, measurement: Measurement, u_in: np.ndarray, u_cmd: np.ndarray,
                          setpoint: float) -> None:
        """With ``placement_sign_move_pct``: this step's reading and valve a command to the sign check, with the
        change of the model air the command makes in each filter; a verdict whose other filter predicted the sign
        shown switches the prediction to that filter at the next step (:mod:`~.sign_check`)."""
        if self.sign_check is None:
            return
        a = float(u_cmd[self.problem.i_valve_a])
        mine = theirs = math.nan
        if self.sign_check.wants_prediction(a):
            other = self._filters[1 - self.placement.active]
            mine = self._air_change[id(self.ekf)](u_in, u_cmd, setpoint)
            if other.healthy():
                theirs = self._air_change[id(other)](u_in, u_cmd, setpoint)
        verdict = self.sign_check.observe(finite_or(measurement.supply_temp_c, math.nan), a, mine, theirs)
        if verdict is not None and verdict.other_explains:
            self._sign_switch = True

    def _switch_on_sign(self) -> None:
        """A sign check's verdict: the prediction moves to the other filter, both sums forgotten."""
        self._sign_switch = False
        self.placement.force()
        self._use_active_filter()

    def _placement_from_response(self) -> None:
        """With ``placement_from_response``: forget both sums once, when the filter in use first sees a response
        of the supply air (its dead-time estimate informed): before it both filters are surprised alike by a dead
        time not yet found, which is no evidence of where the error sits."""
        if self.settings.placement_from_response and not self._response_noted and self.ekf.response_seen:
            self._response_noted = True
            self.placement.restart()

    def _run_other_filter(self) -> None:
        """The filter not in use: the measurement update with the last step's readings and the time update with
        its command (deferred out of the step: :meth:`wait_background` runs it between steps where it is called)."""
        if self._pending is None:
            return
        measurement, u_in, setpoint, u_cmd = self._pending
        self._pending = None
        other = self._filters[1 - self.placement.active]
        try:
            if not other.healthy():
                other.initialise(measurement, u_in, setpoint)
            else:
                other.update(measurement, u_in, setpoint)
                self.placement.observe(1 - self.placement.active, other.supply_nis, other.honoured_dead_time_s)
            other.predict(u_cmd, setpoint)
            ok = other.healthy()
        except Exception:  # noqa: BLE001 - the filter not in use must not take the step down
            ok = False
        if not ok:
            other.reset()
            self.placement.restart()

    def _use_filter(self, ekf: DisturbanceEkf) -> None:
        """Predict with ``ekf`` from now on: its prediction fused with the QP's preparation, its parameters in the
        prediction, and the next QP prepared afresh (the last one was made with the other filter's estimate)."""
        if ekf is self.ekf:
            return
        warm = self.settings.placement_warm_switch and self._prepared_for_next and hasattr(self.solver, "rebase")
        self._prepared_for_next = False
        old = self.ekf
        self._bind_filter(ekf)
        if warm and self._switch_setpoint is not None:  # the QP prepared again at this filter's prediction
            try:
                self.solver.rebase(self.problem.scale_x(ekf.x), self._disturbance(self._switch_setpoint))
            except Exception:
                self._bind_filter(old)  # where the rebase fails, the old filter stays bound and in use
                raise
            self._prepared_for_next = True

    def _bind_filter(self, ekf: DisturbanceEkf) -> None:
        """``ekf``'s fused prediction bound to the solver, its parameters in the prediction and the reach solve."""
        if hasattr(self.solver, "use_prediction"):
            self.solver.use_prediction(ekf)  # first: where it fails, the old filter stays bound and in use
        self.ekf = ekf
        self._updates_at_start = ekf.time_updates  # the recovery's count (step) follows the filter in use
        p = ekf.model_parameters()
        self.solver.set_parameters(p)
        if self.reach is not None:
            self.reach.set_parameters(p)

    def wait_background(self, timeout_s: float) -> float:
        """Between two steps: give the reachable-flow solve (and a split change's rest) running on the second thread
        up to ``timeout_s`` (s) to finish, so that the next step need not wait for it (the rest of the sample on the box). The
        commands do not depend on it (the answer is applied by the next step either way). Returns the wall
        time waited (s)."""
        t0 = time.perf_counter()
        # a split change's rest first: it takes the time update of the filter in use, beside which the other one
        # is not run
        waited = self._change_call.wait(timeout_s) if self._change_call is not None else 0.0
        if self.placement is not None and (self._change_call is None or self._change_call.done):
            self._run_other_filter()
        remaining = max(0.0, timeout_s - (time.perf_counter() - t0))
        return waited + (self.reach.wait_background(remaining) if self.reach else 0.0)

    def _tracked_reference(self, ref: Reference, d: np.ndarray, cap: float) -> np.ndarray:
        """Reference vector of the stage outputs with the priorities applied: the total flow (and the
        outlet flows alike) lowered to what the model can deliver at the temperature reference."""
        y_ref = self.problem.reference_vector(ref)
        self._out_of_reach = {}
        if self.reach is None:
            return y_ref
        # the model's flows the check and the flow-weight factor read, in one call (the same values as theirs)
        pb = self.problem
        self._reach_flows = self.reach.flows(self.ekf.x, self.u_prev, d, pb.rate_phys * pb.dt_s)
        reach = self.reach.check(self.ekf.x, self.u_prev, d, ref.supply_temp_c, ref.volume_flow_m3s, cap,
                                 self.settings.dt_s, flows=self._reach_flows)
        self._out_of_reach = dict(reach.out_of_reach)
        if reach.flow_m3s is not None and reach.flow_m3s < ref.volume_flow_m3s:
            y_ref[FLOW_OUTPUTS] *= reach.flow_m3s / ref.volume_flow_m3s
        return y_ref

    def _note_temperature_reach(self, measurement: Measurement, ref: Reference, u_cmd: np.ndarray,
                                u_hi: np.ndarray) -> None:
        """Add ``supply_temp_c`` to the out-of-reach report while the heater (heating) or the cooler
        (cooling) is saturated and the reading stays away (:mod:`hvac_mpc.mpc.temperature_reach`), where
        the reachable-flow check has not already reported it."""
        gap = self.temp_reach.update(getattr(measurement, "supply_temp_c", None), ref.supply_temp_c, u_cmd, u_hi)
        if gap is not None and "supply_temp_c" not in self._out_of_reach:
            self._out_of_reach["supply_temp_c"] = gap

    def _flow_weight_factor(self, y_ref: np.ndarray, d: np.ndarray) -> float:
        """Factor on the flow weights: :data:`OUT_OF_REACH_FLOW_WEIGHT` while the flow reference is out of
        reach, less while a flow error (a shortfall beyond one sample of the blower's rate, an excess whole)
        would buy supply temperature through valve a (:func:`~.priorities.flow_weight_factor`,
        ``MpcSettings.flow_trade_c``), whichever is less."""
        # temperature first: a flow reference whose reach is still being solved trades no more than one out of reach
        undecided = self.reach is not None and self.reach.undecided
        factor = OUT_OF_REACH_FLOW_WEIGHT if "volume_flow_m3s" in self._out_of_reach or undecided else 1.0
        trade_c = self.settings.flow_trade_c
        if self.reach is None or trade_c is None:
            return factor
        pb = self.problem
        error_m3s = self.reach.transient_flow_error(self.ekf.x, self.u_prev, d, float(y_ref[1]),
                                                    pb.rate_phys * pb.dt_s, flows=self._reach_flows)
        w = pb.w_y_full
        return min(factor, flow_weight_factor(error_m3s, w[1], w[0], trade_c))

    def _damp_reversal(self, u_cmd: np.ndarray) -> None:
        """Valve a's move in ``u_cmd`` (in place, before the projection onto the bounds) applied in part where it
        reverses the last applied move (``valve_a_reversal_share``, off at 1)."""
        s, i = self.settings, self.problem.i_valve_a
        if s.valve_a_reversal_share < 1.0:
            u_cmd[i] = damped_move(float(self.u_prev[i]), self._valve_a_move, float(u_cmd[i]),
                                   s.valve_a_reversal_share, s.valve_a_reversal_min_pct)

    def _hold_valve_a(self, u_cmd: np.ndarray, heater_c: float, measurement: Measurement, ref: Reference) -> None:
        """Valve a in ``u_cmd`` (in place, before the projection onto the bounds) not closed while the heater is
        limited (its power limit: the range's top or, with ``ptc_limit``, the PTC line at the heater estimate
        ``heater_c``, degC) and the reading short of its reference (``valve_a_hold_shortfall_c``, off at 0)."""
        shortfall = self.settings.valve_a_hold_shortfall_c
        if shortfall <= 0.0:
            return
        pb = self.problem
        upper_w = float(pb.u_hi_phys[pb.i_heater_cmd])
        if pb.ptc_limit and math.isfinite(heater_c):
            upper_w = min(upper_w, float(pb.ptc_available_w(heater_c)))
        limited = heater_limited(float(u_cmd[pb.i_heater_cmd]), upper_w,
                                 getattr(measurement, "supply_temp_c", None), ref.supply_temp_c, shortfall)
        proposed = float(u_cmd[pb.i_valve_a])
        u_cmd[pb.i_valve_a] = held_opening(float(self.u_prev[pb.i_valve_a]), proposed, limited)
        self._valve_a_held = bool(u_cmd[pb.i_valve_a] != proposed)

    def _ring_factor(self, measurement: Measurement, ref: Reference) -> float:
        """Factor on valve a's and the heater's rate limits: below 1 while the supply reading rings about its
        reference (:class:`~.ring_gate.RingGate`, ``MpcSettings.ring_*``), 1 without the gate."""
        if self.ring is None:
            return 1.0
        self.ring.push(finite_or(getattr(measurement, "supply_temp_c", None), float("nan")), ref.supply_temp_c)
        return self.ring.factor

    def _ring_slowed(self, bounds: tuple[np.ndarray, np.ndarray], ring: float) -> tuple[np.ndarray, np.ndarray]:
        """The next command's bounds with valve a's and the heater's moves limited to ``ring`` of their rate (the
        heater's fall too; the daemon's safety layer, ``hvac_mpc.daemon.safety``, cuts it at low airflow regardless)."""
        pb = self.problem
        lo, hi = bounds[0].copy(), bounds[1].copy()
        for i in (pb.i_valve_a, pb.i_heater_cmd):
            step = pb.rate_phys[i] * pb.dt_s * ring
            lo[i] = min(max(lo[i], self.u_prev[i] - step), hi[i])
            hi[i] = opening_bound(lo[i], hi[i], self.u_prev[i], step)
        return lo, hi

    def _start_caution_bounds(self, slowed: tuple[np.ndarray, np.ndarray], plain: tuple[np.ndarray, np.ndarray],
                              cap: float, heater_c: float) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray | None]:
        """The command bounds the QP is built with while the start's caution (scope ``valve_a_opening``) slows valve
        a's opening, and the scaled upper bounds the solver adds only where they bind (None: none), from
        ``start_caution_in_qp``: True the ``slowed`` bounds in the QP; False the ``plain`` ones (the caution on the
        command only); ``"when_binding"`` the ``plain`` ones, the slowed ones' upper bounds to the solver
        (:meth:`.RtiOsqpSolver.feedback`'s ``u_hi_binding``) where it takes them, else (IPOPT's reference) in the
        QP as with True."""
        mode = self.settings.start_caution_in_qp
        if mode is False:
            return plain, None
        if mode == START_CAUTION_WHEN_BINDING and isinstance(self.solver, RtiOsqpSolver):
            return plain, self.problem.input_bounds(self.u_prev, cap, heater_c, command=slowed)[1]
        return slowed, None

    def _start_opening_slowed(self, bounds: tuple[np.ndarray, np.ndarray], share: float
                              ) -> tuple[np.ndarray, np.ndarray]:
        """The next command's bounds with valve a's opening limited to ``share`` of its rate (the start-up's caution
        of scope ``valve_a_opening``, :mod:`.start_caution`); its closing and the heater as they were."""
        pb, i = self.problem, self.problem.i_valve_a
        hi = bounds[1].copy()
        hi[i] = opening_bound(float(bounds[0][i]), float(hi[i]), float(self.u_prev[i]),
                              float(pb.rate_phys[i] * pb.dt_s * share))
        return bounds[0], hi

    def _output_weights(self, ref: Reference, d: np.ndarray, y_ref: np.ndarray, measurement: Measurement) -> np.ndarray:
        """The tracked outputs' weights of this step: valve a's heating weight (:meth:`_valve_a_weighed`, scaled by
        ``valve_a_weight_on_duty_scale`` while the heater is off), the flows' factor, then the heater reserve's
        valve-a weight in place of both where the reserve is on."""
        pb = self.problem
        w_y = pb.heating_weights(pb.output_weights(ref), heating=self._valve_a_weighed(ref, d))
        if self.settings.valve_a_weight_on_duty_scale != 1.0 and not pb.heating(self.u_prev):
            w_y[Y_VALVE_A] *= self.settings.valve_a_weight_on_duty_scale
        self._flow_factor = self._flow_weight_factor(y_ref, d)
        w_y[FLOW_OUTPUTS] *= self._flow_factor
        self._set_reserve(w_y, ref, measurement)
        return w_y

    def _valve_a_weighed(self, ref: Reference, d: np.ndarray) -> bool:
        """Whether valve a takes its heating weight this step: the heater commanded in the command in force, or with
        ``valve_a_weight_on_duty`` the supply-temperature reference above the inlet air (``d[0]``); with
        ``valve_a_weight_on_duty_open_pct`` > 0 the latter only once valve a in force has opened beyond it on the
        duty with the heater off (then held until the duty ends)."""
        s = self.settings
        duty = s.valve_a_weight_on_duty and heating_duty(finite_or(ref.supply_temp_c, float("nan")), float(d[0]))
        heating = self.problem.heating(self.u_prev)
        if not duty:
            self._duty_weight_on = False
        elif not heating and float(self.u_prev[self.problem.i_valve_a]) > s.valve_a_weight_on_duty_open_pct:
            self._duty_weight_on = True
        return heating or (duty and (self._duty_weight_on or s.valve_a_weight_on_duty_open_pct <= 0.0))

    def _set_reserve(self, w_y: np.ndarray, ref: Reference, measurement: Measurement) -> None:
        """Valve a's weight in ``w_y`` (in place) from the heater reserve's gate (:mod:`.reserve`; a setting, off by
        default)."""
        if self.reserve is None:
            return
        pb = self.problem
        reading = finite_or(getattr(measurement, "supply_temp_c", None), float("nan"))
        body_c = float(self.ekf.x[pb.i_heater])
        w_y[Y_VALVE_A] = self.reserve.weight(
            supply_ref_c=finite_or(ref.supply_temp_c, float("nan")),
            flow_ref_m3s=finite_or(ref.volume_flow_m3s, float("nan")), reading_c=reading,
            heating=pb.heating(self.u_prev), heater_cmd_w=float(self.u_prev[pb.i_heater_cmd]),
            available_w=float(available_power_w(body_c, pb.params)), flow_factor=self._flow_factor,
            heater_power_w=finite_or(getattr(measurement, "heater_power_w", None), float("nan")),
            body_c=body_c, knee_c=float(pb.params.ptc_knee_c))

    def _set_readiness(self, ref: Reference, d: np.ndarray, cap: float, measurement: Measurement) -> None:
        """The heater readiness's floor for the QPs of this step (:mod:`.readiness`; a setting, off by default)."""
        if self.readiness is None:
            return
        reading = finite_or(getattr(measurement, "supply_temp_c", None), float("nan"))
        floor = self.readiness.floor_c(self.ekf.x, self.u_prev, d, self._prediction_parameters(),
                                       ref.supply_temp_c, ref.volume_flow_m3s, cap,
                                       None if not np.isfinite(reading) else reading)
        self.solver.readiness_target = self.readiness.scaled(floor)

    def _use_estimated_parameters(self) -> None:
        """The prediction (the next QPs) and the reachable-flow check use the learned bypass-flow exponent
        (docs/robustness.md sec. 1) and the estimated offsets of the core path's air (sec. 2.13). Unlearned, the
        exponent is the prior the problem was built with, and nothing needs copying."""
        if not self.ekf.adapts_parameters:
            return
        p = self._prediction_parameters()
        self.solver.set_parameters(p)
        if self.reach is not None:
            self.reach.set_parameters(p)

    def _prediction_parameters(self) -> np.ndarray:
        """The model parameters (``HvacModel.p_default`` order) the prediction uses now: the filter's
        (:meth:`~.estimator.DisturbanceEkf.model_parameters`) where it learns the bypass-flow exponent or estimates
        an offset of the core path's air, else those the problem was built with."""
        if self.ekf.adapts_parameters:
            return self.ekf.model_parameters()
        return self.problem.model.p_default

    def _disturbance(self, setpoint: float) -> np.ndarray:
        e = self.ekf
        target = e.x[e.i_water] if self.settings.water_prediction == "hold" else setpoint
        return np.array([e.inlet_temp_c, target, e.mix_offset_c, e.flow_offset_m3s])

    def _trap_cap(self, measurement: Measurement | None = None) -> float:
        """Valve a cap (%) of the trapped-air guard, with the heater temperature bounded by what was
        commanded (:class:`HeaterOffBound`; the measured flow sets the heater's time constant). The air
        entering the heater is the prediction model's, discovered terms at the core outlet or on the air
        entering the box included."""
        e, m = self.ekf, self.problem.model
        x = e.x
        if self._heater_inlet is None:
            t_blower = e.inlet_temp_c + x[m.states.index("motor_rise_c")]
            heater_in = float(chiller.cooler_outlet_c(t_blower, x[e.i_water], self.params))
            if e.has_cooler_offset:  # the filter's estimate of the core outlet's offset in place of the parameter's
                heater_in += e.cooler_offset_c - self.params.cooler_outlet_offset_c
        else:
            # the chiller set point and the mixed-air offset do not reach the heater inlet: the water state stands in
            heater_in = float(self._heater_inlet(x, self.u_prev, self._disturbance(float(x[e.i_water]))))
        cmd = float(self.u_prev[self.problem.i_heater_cmd])
        flow = finite_or(getattr(measurement, "volume_flow_m3s", None), 0.0)
        mass_flow = float(air.density_kgm3(e.inlet_temp_c, self.params)) * max(flow, 0.0)
        heater = self.heater_bound.update(float(x[m.states.index("heater_temp_c")]), heater_in, cmd, mass_flow,
                                          body_rate=self._body_rate_at(x))
        if self.settings.bound_heater_estimate and cmd <= HEATING_CMD_W:
            e.bound_state("heater_temp_c", *sorted((heater_in, self.heater_bound.bound_c)))
        return trap_cap_pct(heater, heater_in, cmd, self.params, self.settings.ocp)

    def _body_rate_at(self, x: np.ndarray) -> Callable[[float], float] | None:
        """The heater body's rate (degC/s) as a function of its temperature, the other states ``x`` and the command
        in force held, where the model adds a heat flow to the body (else None)."""
        if self._heater_body_rate is None:
            return None
        i_heater = self.problem.model.states.index("heater_temp_c")
        d = self._disturbance(float(x[self.ekf.i_water]))
        state = np.array(x, float)
        p = self._prediction_parameters()  # the prediction's: the bound follows the model the QP predicts with

        def rate(t_body_c: float) -> float:
            state[i_heater] = t_body_c
            return float(self._heater_body_rate(state, self.u_prev, d, p))
        return rate

    def _fallback_command(self, measurement: Measurement, ref: Reference | None) -> tuple[np.ndarray, str]:
        """Shifted previous plan while it lasts, then the thesis baseline, then the last command."""
        s = self.settings
        if self._plan is not None and not self._in_baseline:
            U, age = self._plan
            age += s.dt_s
            horizon = float(self.problem.t_nodes[-1])
            if age < min(s.plan_fallback_s, horizon):
                j = int(np.searchsorted(self.problem.t_nodes, age, side="right") - 1)
                self._plan = (U, age)
                return self.problem.unscale_u(U[min(j, len(U) - 1)]), "shifted_plan"
        self._plan = None
        if ref is not None:
            try:
                baseline = self._get_baseline()
                if not self._in_baseline:
                    # bumpless hand-over: the thesis loops continue from the command in force
                    baseline.reset()
                    if hasattr(baseline, "track"):
                        baseline.track(Command.from_vector(self.u_prev))
                    self._in_baseline = True
                cmd = baseline.step(measurement, ref).command.vector()
                if np.all(np.isfinite(cmd)):
                    return cmd, "baseline"
            except Exception:  # noqa: BLE001 - the baseline must not take the controller down
                pass
        return self.u_prev.copy(), "hold_last_command"

    def _get_baseline(self):
        if self._baseline is None:
            module = importlib.import_module("hvac_mpc.mpc.baseline")
            self._baseline = module.BaselineController(self.params, dt_s=self.dt_s)
        return self._baseline

    def _scaled_prev(self) -> np.ndarray:
        """The command in force as scaled decisions (converted once per command)."""
        if self._u_prev_scaled is None or self._u_prev_scaled[0] is not self.u_prev:
            self._u_prev_scaled = (self.u_prev, self.problem.scale_u(self.u_prev))
        return self._u_prev_scaled[1]

    def _stats(self, t0: float, status: str, fallback: str | None, prep: float = 0.0, feedback: float = 0.0,
               iterations: int = 0, qp_solves: int = 0, cap: float | None = None,
               healthy: bool | None = None) -> dict[str, Any]:
        """The step's statistics (names in the module docstring); ``healthy``: the estimator's state
        is known to be finite (checked when None)."""
        heating = self.problem.heating(self.u_prev)
        stats = {
            "step_time_s": time.perf_counter() - t0,
            "prep_time_s": prep,
            "feedback_time_s": feedback,
            "iterations": int(iterations),
            "qp_solves": int(qp_solves),
            "status": status,
            "fallback": fallback,
            "mode": "heating" if heating else "cooling",
            "solver": getattr(self.solver, "name", self.settings.solver),
            "out_of_reach": dict(getattr(self, "_out_of_reach", {})),
            "flow_weight_factor": float(getattr(self, "_flow_factor", 1.0)),
            "valve_a_held": self._valve_a_held,
        }
        if cap is not None:
            stats["valve_a_cap_pct"] = cap
        if healthy if healthy is not None else self.ekf.healthy():
            stats["mix_offset_c"] = self.ekf.mix_offset_c
            stats["flow_offset_m3s"] = self.ekf.flow_offset_m3s
            stats["dead_time_s"] = self.ekf.dead_time_s
            stats["bypass_flow_exponent"] = self.ekf.bypass_flow_exponent
        stats["offset_placement"] = self.offset_placement
        return stats

    @property
    def offset_placement(self) -> str:
        """Where the filter the prediction uses puts the heater outlet reading's error (one of
        :data:`~.placement.PLACEMENTS`): the reading's own offset, or the air leaving the heater."""
        return PLACEMENTS[self.placement.active] if self.placement is not None else PLACEMENTS[0]


def _try_jit(problem: TrackingProblem) -> bool:
    """Use JIT-compiled stage functions (one per substep count); False if compiling fails."""
    import casadi as ca
    try:
        opts = {"jit": True, "compiler": "shell", "jit_options": {"flags": ["-O1"], "verbose": False},
                "jit_temp_suffix": True}
        compiled = {n: ca.Function(f"{f.name()}_jit", f.sx_in(), f.call(f.sx_in()), opts)
                    for n, f in problem.stages.items()}
        problem.set_stage_functions(compiled)
        return True
    except Exception:  # noqa: BLE001 - no compiler: the virtual machine works too
        return False
