"""Priorities of the references: supply temperature first, then total flow, then the split, then energy.

The tracking cost trades every reference against every other; where all can be met together
that does no harm, but when the blower cannot deliver the total flow at the asked temperature
(for instance 200 m3/h at a 32 C inlet: more flow needs more bypass, more bypass warmer air) a
weighted sum gives up supply temperature for a few percent of flow. This module does the first
stage of a two-stage (lexicographic) scheme (docs/robustness.md sec. 1):

1. :class:`ReachableFlow` solves a small steady-state problem on the controller's model, with the
   estimator's disturbances: the largest total flow whose rest state has the supply temperature at
   its reference (temperature error penalised far above flow, so where the temperature itself is
   out of reach it comes as close as the actuators allow);
2. the MPC then tracks ``min(reference, reachable)`` (outlet flows scaled alike) and reports the
   shortfall in ``stats["out_of_reach"]``.

Once a flow reference is found out of reach it stays so (latched on the flow reference alone, not on
the temperature reference) until the flow is really delivered: the model's reachable flow moves with
the estimator's offsets, which absorb whatever the box does differently (docs/robustness.md sec. 1),
so a new temperature reference must not bring the same flow back into a trade against temperature.
The box itself can say so too: the blower at full power for ``saturated_s`` with the flow still
below the reference latches the reference even where the model thinks it reachable.

While a flow error is large (a flow step the blower closes at its rate limit), the weighted sum buys
flow with valve a as well, and so with supply temperature, for as long as the blower ramps:
:func:`flow_weight_factor` cuts the flow weights for that step so that the pull on valve a of a
flow error (a shortfall beyond what the blower closes within the sample, an excess whole) buys at
most ``trade_c`` of supply temperature (docs/robustness.md sec. 1).

The problem is only solved when the flow reference is high enough to be in doubt (above
``check_fraction`` of the blower's nominal open flow, and above 90 % of what full blower power with
open outlets would give at the present valve a and heater): on a change of the references, and
then every ``every_s`` seconds; warm started; IPOPT with an iteration cap (deterministic). A re-solve
costs 5-15 ms (about 25 IPOPT iterations). With ``skip_unmoved`` (off by default) the periodic
re-solve is skipped while its other inputs (the estimator's disturbances, the valve a cap) have
moved by less than :data:`MATERIAL_CHANGE` since the last solve: fewer slow steps, but measured
worse with the flow out of reach on the independent box (docs/robustness.md sec. 1).

With ``deferred`` a periodic re-solve (the references unchanged) started in one check is applied at the
start of the next check (the next control step), which in between answers from the previous solve; with
``background`` as well the solve runs on a second thread meanwhile (:mod:`hvac_mpc.mpc.background`), off the
step's critical path: one thread per object, started with it and handed each solve
(:class:`~.background.BackgroundWorker`; :meth:`ReachableFlow.close` ends it). Deferred answers are the same
with and without the thread: the solve's inputs are copied when it starts, and the next check waits for it.
A change of the references is solved inside its step unless ``changes_deferred``: one step of tracking an
unreachable flow reference at a reference change doubled the quick mismatch suite's temperature IAE ratio on
flow_out_of_reach (median over the variants 0.77 -> 1.52, measured with every solve deferred, before the
flow weights were cut while a flow error is closed: :func:`flow_weight_factor`). With ``changes_deferred``
that solve too is started in its step and applied from the next one, the step answering from the last solve
meanwhile (docs/architecture.md 'Slow steps': the median 0.788 -> 0.782).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import casadi as ca
import numpy as np

from hvac_mpc.models.box import HvacModel
from hvac_mpc.models.parameters import Parameters

from .background import BackgroundCall, BackgroundWorker
from .casadi_eval import BufferedFunction

#: Temperature error weight of the steady-state problem, per degC^2, against flow in units of FLOW_UNIT_M3S.
TEMP_WEIGHT_PER_C2 = 1e3
FLOW_UNIT_M3S = 0.01
#: Smallest change of an input of the steady-state problem that makes a periodic re-solve worth its
#: time, in the order of the problem's parameters: the model's disturbances (inlet temperature
#: degC, chiller water target degC, mixed-air offset degC, flow offset m3/s) and the valve a cap
#: (%). ASSUMPTION: 0.3 degC moves the reachable flow by about 0.08 L/s (0.27 L/s per degC of the
#: temperature reference, measured on the solve-time scenario at 50 L/s; the mixed-air offset acts as
#: much, the inlet and water temperatures through the cooler less), a flow offset of 0.2 L/s by as
#: much; both far below the 2 % tracking margin (``margin``, about 1 L/s at 50 L/s).
MATERIAL_CHANGE = np.array([0.3, 0.3, 0.3, 2e-4, 1.0])


#: ASSUMPTION: how much supply temperature valve a moves per unit of total flow it moves, degC per L/s:
#: dT/da about 0.25 degC/% against dQ/da about 0.05 (L/s)/% at full blower (docs/robustness.md sec. 1).
#: Where dQ/da is larger (a slower blower) the cap below is stricter than its ``trade_c``, never looser.
TEMP_PER_FLOW_VIA_VALVE_A_C_PER_LPS = 5.0
#: Scale of the flow residuals in the tracking cost (m3/s per unit: 1 L/s, mpc/ocp.py ``y_scale``).
FLOW_RESIDUAL_SCALE_M3S = 1e-3


def flow_weight_factor(flow_error_m3s: float, flow_weight: float, temp_weight: float, trade_c: float) -> float:
    """Factor in (0, 1] on the flow weights that caps what a flow error may cost in supply temperature.

    The QP settles where the two residuals' gradients through valve a balance,
    ``w_T e_T dT/da = w_Q e_Q dQ/da``: a flow error ``e_Q`` (L/s) the blower cannot close at once buys
    ``e_T = w_Q e_Q / (w_T r)`` of supply temperature, ``r`` = :data:`TEMP_PER_FLOW_VIA_VALVE_A_C_PER_LPS`
    (with the default weights, 30 L/s at a flow step buy 12 degC: valve a as far as its rate allows).
    The factor lowers ``w_Q`` to ``w_T r trade_c / |e_Q|`` where that is less, so the price stays at
    ``trade_c`` (degC); the blower's pull stays far above the energy term's (the flow still comes before
    energy). Small errors (below 0.125 L/s with the default weights and 0.05 degC) keep the full weight.
    ``flow_error_m3s``: :meth:`ReachableFlow.transient_flow_error` (a shortfall counts only beyond what the
    blower closes within the sample)."""
    pull = flow_weight * abs(flow_error_m3s) / FLOW_RESIDUAL_SCALE_M3S
    limit = temp_weight * TEMP_PER_FLOW_VIA_VALVE_A_C_PER_LPS * trade_c
    return 1.0 if pull <= limit else limit / pull


class Flows(NamedTuple):
    """The model's total flows (m3/s) a control step reads (:meth:`ReachableFlow.flows`): at the command in force
    (``now_m3s``), with the blower and the outlet valves at their upper bounds (``full_m3s``) and with each of them
    one sample's move up, at most to its bound (``up_m3s``)."""

    now_m3s: float
    full_m3s: float
    up_m3s: float


class Solution(NamedTuple):
    """One reachable-flow solve: the steady state of the largest flow (stacked x, u), its flow (m3/s), its
    supply-temperature error against the reference (degC) and whether IPOPT converged."""

    w: np.ndarray
    flow_m3s: float
    temp_error_c: float
    converged: bool


@dataclass
class Reach:
    """Result of one reachability check: the flow to track and what is out of reach (name -> shortfall)."""

    flow_m3s: float | None
    out_of_reach: dict


class ReachableFlow:
    """Largest steady total flow with the supply temperature at its reference, on the controller's model.

    ``undecided``: a changed reference's solve is running (``changes_deferred``) and the check answered from an
    earlier solve, or from none; the controller then trades no flow for temperature (docs/robustness.md sec. 2.6).
    """

    def __init__(self, model: HvacModel, u_lo: np.ndarray, u_hi: np.ndarray, heater_temp_max_c: float,
                 params: Parameters, every_s: float = 10.0, check_fraction: float = 0.6, margin: float = 0.02,
                 temp_tolerance_c: float = 0.2, max_iter: int = 60, saturated_s: float = 5.0,
                 skip_unmoved: bool = False, deferred: bool = False, background: bool = False,
                 changes_deferred: bool = False):
        if background and not deferred:
            raise ValueError("ReachableFlow: background=True needs deferred=True (the result is used one check later)")
        if changes_deferred and not deferred:
            raise ValueError("ReachableFlow: changes_deferred=True needs deferred=True")
        self.model = model
        self.deferred = bool(deferred)
        self.changes_deferred = bool(changes_deferred)
        self.background = bool(background)
        self._pending: BackgroundCall | None = None
        # one thread of this object's own for all its deferred solves, started here (not inside a step)
        self.worker: BackgroundWorker | None = BackgroundWorker() if self.background else None
        if self.worker is not None:
            self.worker.start()
        self._pending_change = False  # the pending solve is of a changed reference (not a periodic look)
        self.last_wait_s = 0.0  # wall time the last check waited for a solve on the second thread (s)
        self.skip_unmoved = bool(skip_unmoved)
        self.saturated_s = float(saturated_s)
        self.every_s = float(every_s)
        self.margin = float(margin)
        self.temp_tolerance_c = float(temp_tolerance_c)
        self.check_flow_m3s = check_fraction * params.flow_per_watt_m3s_per_w * params.blower_power_max_w
        self.headroom = 0.9
        self.u_hi = np.asarray(u_hi, float)
        self.i_blower = model.inputs.index("blower_power_w")
        self.i_outlets = [model.inputs.index(n) for n in ("valve_m_pct", "valve_f_pct", "valve_w_pct")]
        nx, nu, nd = len(model.states), len(model.inputs), len(model.disturbances)
        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        d, t_ref, a_cap = ca.SX.sym("d", nd), ca.SX.sym("t_ref"), ca.SX.sym("a_cap")
        # the model parameters are a parameter of the problem: the estimator may change one (the
        # bypass-flow exponent, mpc/estimator.py) from step to step
        p = ca.SX.sym("p", len(model.p_default))
        self._p = np.array(model.p_default, float)
        y = model.output(x, u, d, p)
        flow = y[model.outputs.index("volume_flow_m3s")]
        temp = y[model.outputs.index("duct_air_temp_c")]
        heater = x[model.states.index("heater_temp_c")]
        i_a = model.inputs.index("valve_a_pct")
        cost = TEMP_WEIGHT_PER_C2 * (temp - t_ref) ** 2 - flow / FLOW_UNIT_M3S
        g = ca.vertcat(model.ode(x, u, d, p), heater, u[i_a] - a_cap)
        nlp = {"x": ca.vertcat(x, u), "p": ca.vertcat(d, t_ref, a_cap, p), "f": cost, "g": g}
        opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.max_iter": int(max_iter), "ipopt.tol": 1e-6,
                "ipopt.sb": "yes"}
        self.solver = ca.nlpsol("reachable_flow", "ipopt", nlp, opts)
        self.out_fn = ca.Function("reach_out", [x, u, d, p], [flow, temp])
        self.use_out_function(self.out_fn)
        self.flows_fn = self._flows_function(model, x, u, d, p)
        self.use_flows_function(self.flows_fn)
        # the same outputs as a function object of its own for the solve, which may run on a second
        # thread: no memory shared with the buffered calls of the step
        self._out_fn = ca.Function("reach_solution_out", [x, u, d, p], [flow, temp])
        self.lbx = np.concatenate([np.full(nx, -np.inf), u_lo])
        self.ubx = np.concatenate([np.full(nx, np.inf), u_hi])
        self.lbg = np.concatenate([np.zeros(nx), [-np.inf, -np.inf]])
        self.ubg = np.concatenate([np.zeros(nx), [heater_temp_max_c, 0.0]])
        self.nx = nx
        self.reset()

    def use_out_function(self, fn) -> None:
        """Evaluate :meth:`out` with ``fn`` (the signature of :attr:`out_fn`, e.g. generated C of it,
        :func:`~.codegen.compiled`), numpy in and out."""
        self._out = BufferedFunction(fn)

    def _flows_function(self, model: HvacModel, x, u, d, p) -> ca.Function:
        """(x, u, d, p, step, u_hi) -> the three flows of :class:`Flows`: the model's flow evaluated at the three
        commands in one function (the same expression as :attr:`out_fn`'s flow at each, so the same numbers as
        three calls of it; the bounds and moves are inputs, not constants, so nothing is folded at build time)."""
        step, hi = ca.SX.sym("step", u.numel()), ca.SX.sym("u_hi", u.numel())
        moved = [self.i_blower, *self.i_outlets]
        full = ca.vertcat(*[hi[i] if i in moved else u[i] for i in range(u.numel())])
        up = ca.vertcat(*[ca.fmin(u[i] + step[i], hi[i]) if i in moved else u[i] for i in range(u.numel())])
        i_flow = model.outputs.index("volume_flow_m3s")
        flows = [model.output(x, v, d, p)[i_flow] for v in (u, full, up)]
        return ca.Function("reach_flows", [x, u, d, p, step, hi], flows)

    def use_flows_function(self, fn) -> None:
        """Evaluate :meth:`flows` with ``fn`` (the signature of :attr:`flows_fn`, e.g. generated C of it)."""
        self._flows = BufferedFunction(fn, fixed={5: self.u_hi})

    def flows(self, x: np.ndarray, u: np.ndarray, d: np.ndarray, step: np.ndarray) -> Flows:
        """The model's flows a step reads (:class:`Flows`) at the estimate ``x``, the command ``u`` and the
        disturbances ``d`` (physical), ``step`` each input's largest move in a sample: one call, where
        :meth:`check` and :meth:`transient_flow_error` alone make two each (the same values)."""
        now, full, up = self._flows.views(x, u, d, self._p, step)  # read at once: no copies
        return Flows(float(now[0]), float(full[0]), float(up[0]))

    def set_parameters(self, p: np.ndarray) -> None:
        """Model parameters (``HvacModel.p_default`` order) of the checks that follow."""
        self._p[...] = p

    def out(self, x: np.ndarray, u: np.ndarray, d: np.ndarray) -> list[np.ndarray]:
        """The model's total flow and air at the thermocouple (m3/s, degC) at the current parameters."""
        return self._out(x, u, d, self._p)

    def transient_flow_error(self, x: np.ndarray, u: np.ndarray, d: np.ndarray, flow_m3s: float,
                             step: np.ndarray, flows: Flows | None = None) -> float:
        """The flow error (m3/s, the target less the model's flow at the estimate ``x``) whose pull on valve a
        :func:`flow_weight_factor` caps. A flow above the target counts whole: it is never a hazard, and the
        energy term pulls it down as well. A flow below it counts only beyond what the blower and the outlet
        valves reach within one sample at their rate limits (``step``: each input's largest move in a sample,
        physical), valve a and the heater held: a shortfall the MPC chose itself, giving up flow for a supply
        temperature out of reach, keeps the full weight, so the flow is not let go further (the heater's
        minimum flow). ``flows``: :meth:`flows` at the same arguments, where the step has them already."""
        flows = flows if flows is not None else self.flows(x, u, d, step)
        excess = flow_m3s - flows.now_m3s
        return excess if excess <= 0.0 else max(flow_m3s - flows.up_m3s, 0.0)

    def reset(self) -> None:
        self._drop_pending()
        self._w: np.ndarray | None = None
        self._age_s = np.inf
        self._last = Reach(None, {})
        self._key: tuple | None = None
        self._inputs: np.ndarray | None = None  # disturbances and valve a cap of the last solve
        self._latched: float | None = None  # the flow reference (m3/s) held out of reach
        self._saturated_for_s = 0.0

    def check(self, x: np.ndarray, u: np.ndarray, d: np.ndarray, temp_ref_c: float, flow_ref_m3s: float,
              a_cap_pct: float, dt_s: float, flows: Flows | None = None) -> Reach:
        """The flow to track (``None``: the reference as it is) and the out-of-reach report.

        ``x``, ``u``, ``d``: the estimate, the command in force and the disturbances (physical).
        Re-solved when the reference changes or every ``every_s``; otherwise the last answer.
        With ``deferred`` a periodic re-solve started here is applied at the start of the next check.
        ``flows``: :meth:`flows` at the same ``x``, ``u``, ``d``, where the step has them already (one call).
        """
        failed = self._collect()
        if flow_ref_m3s < self.check_flow_m3s:
            self.reset()
            return self._last
        # plainly within reach: the blower at full power with the outlets open gives the reference
        # with headroom without moving valve a or the heater (so without touching the temperature)
        flows = flows if flows is not None else self.flows(x, u, d, np.zeros_like(self.u_hi))
        flow_now = flows.now_m3s
        if flow_ref_m3s <= self.headroom * flows.full_m3s:
            self.reset()
            return self._last
        key = (round(temp_ref_c, 6), round(flow_ref_m3s, 9))
        self._age_s += dt_s
        self._note_saturation(u, flow_ref_m3s, flow_now, dt_s)
        inputs = np.append(d, a_cap_pct)
        if key == self._key and (self._age_s < self.every_s or (self.skip_unmoved and not self._moved(inputs))):
            if self._age_s >= self.every_s:
                self._age_s = 0.0  # looked again: nothing moved
            return self._last if failed else self._limit(flow_ref_m3s, flow_now)
        periodic = key == self._key
        self._key, self._age_s, self._inputs = key, 0.0, inputs
        w0 = self._w if self._w is not None else np.concatenate([x, u])
        # copies: the model parameters may change before a deferred solve has run
        args = (w0.copy(), np.concatenate([d, [temp_ref_c, a_cap_pct], self._p]), np.array(d, float), temp_ref_c)
        if self.deferred and (periodic or self.changes_deferred):
            # a change answers from the last solve meanwhile: the reachable flow moves little with the
            # temperature reference (0.27 L/s per degC, MATERIAL_CHANGE); without one, the reference as it is
            self._pending = BackgroundCall(self._solve, args, thread=self.background, worker=self.worker)
            self._pending_change = not periodic
            return self._last if failed else self._limit(flow_ref_m3s, flow_now)
        if not self._apply(self._solve(*args)):
            return self._last
        return self._limit(flow_ref_m3s, flow_now)

    def _solve(self, w0: np.ndarray, p: np.ndarray, d: np.ndarray, temp_ref_c: float) -> Solution | None:
        """The solve from ``w0``, or ``None`` where it gives no finite answer. Touches no state of this object:
        it may run on a second thread while the controller goes on."""
        try:
            sol = self.solver(x0=w0, p=p, lbx=self.lbx, ubx=self.ubx, lbg=self.lbg, ubg=self.ubg)
            w = np.asarray(sol["x"]).ravel()
            converged = self._converged()
            flow, temp = (float(v) for v in self._solution_out(w, d, p))
        except Exception:  # noqa: BLE001 - no answer: track the reference as it is
            return None
        if not (np.all(np.isfinite(w)) and np.isfinite(flow) and np.isfinite(temp)):
            return None
        return Solution(w, flow, temp - temp_ref_c, converged)

    def _solution_out(self, w: np.ndarray, d: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Flow and temperature of a solution (m3/s, degC), through the solve's own function object."""
        nd = len(d)
        out = self._out_fn(w[:self.nx], w[self.nx:], d, p[nd + 2:])
        return np.array([float(out[0]), float(out[1])])

    def _apply(self, result: Solution | None) -> bool:
        """Take a solve's answer; without one, track the reference as it is (False)."""
        if result is None:
            self._last = Reach(None, {})
            return False
        if self._w is not None and not result.converged:
            # stopped short (iteration cap): keep the last converged answer and warm start (quick mismatch suite,
            # blower_weak with the flow out of reach: a capped solve said -7 m3/h was reachable, the MPC cut
            # the blower to 30 W and heated)
            return True
        self._w, self._reachable, self._temp_error = result.w, result.flow_m3s, result.temp_error_c
        return True

    def _converged(self) -> bool:
        """Whether the last solve converged (IPOPT's ``success``; a solver without statistics counts as converged)."""
        stats = getattr(self.solver, "stats", None)
        return True if stats is None else bool(stats().get("success", False))

    @property
    def undecided(self) -> bool:
        """A changed reference's solve is still pending (class docstring)."""
        return self._pending is not None and self._pending_change

    def _collect(self) -> bool:
        """Apply the deferred solve of the previous check, waiting for it (the wait in :attr:`last_wait_s`);
        True where it gave no answer."""
        self.last_wait_s = 0.0
        if self._pending is None:
            return False
        pending, self._pending = self._pending, None
        result = pending.result()
        self.last_wait_s = pending.waited_s
        return not self._apply(result)

    def wait_background(self, timeout_s: float) -> float:
        """Give a solve running on the second thread up to ``timeout_s`` (s) to finish, outside a check (the
        idle rest of a sample); its answer is still applied by the next check, so the commands do not change.
        Returns the wall time waited (s); 0 when no solve is running."""
        pending = self._pending
        return 0.0 if pending is None else pending.wait(timeout_s)

    def close(self) -> None:
        """Wait for a running solve and end the second thread (a later deferred solve starts it again)."""
        self._drop_pending()
        if self.worker is not None:
            self.worker.close()

    def _drop_pending(self) -> None:
        """Wait for a running solve (the solver must not run twice at once) and forget its answer."""
        pending = getattr(self, "_pending", None)
        self._pending = None
        if pending is not None:
            pending.result()

    def _moved(self, inputs: np.ndarray) -> bool:
        """True when an input has moved by :data:`MATERIAL_CHANGE` or more since the last solve."""
        return self._inputs is None or bool(np.any(np.abs(inputs - self._inputs) >= MATERIAL_CHANGE))

    def _note_saturation(self, u: np.ndarray, flow_ref_m3s: float, flow_now_m3s: float, dt_s: float) -> None:
        """Count how long the blower has been at full power with the flow short of the reference; past
        ``saturated_s`` the box has shown the reference out of reach, whatever the model says."""
        full = u[self.i_blower] >= self.u_hi[self.i_blower] - 1.0
        short = flow_now_m3s < (1.0 - self.margin) * flow_ref_m3s
        self._saturated_for_s = self._saturated_for_s + dt_s if (full and short) else 0.0
        if self._saturated_for_s >= self.saturated_s:
            self._latched = round(flow_ref_m3s, 9)

    def _limit(self, flow_ref_m3s: float, flow_now_m3s: float) -> Reach:
        """Out of reach once the model or the box says so, latched for this flow reference whatever the
        temperature reference does (the model's reachable flow moves with the estimator's offsets; a
        reference must not flip back into a trade of temperature for flow) until the flow is actually
        there. Shortfall: the reference less what is delivered now or reachable, whichever is less."""
        if self._w is None:
            return self._last
        reach: dict = {}
        track = None
        flow_key = round(flow_ref_m3s, 9)
        if flow_now_m3s >= flow_ref_m3s or (self._latched is not None and self._latched != flow_key):
            self._latched = None
        if flow_ref_m3s > self._reachable or self._latched == flow_key:
            self._latched = flow_key
            reach["volume_flow_m3s"] = float(max(0.0, flow_ref_m3s - min(self._reachable, flow_now_m3s)))
            track = float(min(self._reachable, flow_ref_m3s) * (1.0 - self.margin))
        if abs(self._temp_error) > self.temp_tolerance_c:
            reach["supply_temp_c"] = float(abs(self._temp_error))
        self._last = Reach(track, reach)
        return self._last
