"""The start of a reference change: the plan moved toward the inputs that hold the new reference at rest.

At a reference change the real-time iteration's QPs start from the plan shifted from the last step, made
for the old reference: the first QP is linearised there and damped toward it (the Levenberg-Marquardt
term), so it is a large step from a point far from the new optimum. :class:`SteadyStart` gives the QPs
of a change another start, in one call of one CasADi function (generated C with the rest):

1. **the steady-state target**: the inputs ``u_T`` whose rest state on the prediction model (the
   estimator's disturbances, the model parameters in use) minimises the problem's own stage cost at
   rest (the weighted output errors, the energy term) plus the move from the command in force spread
   over the horizon (``w_du / H``, H the horizon's weight in seconds: one move against H seconds of rest
   cost), within the last stage's input bounds. Solved by a fixed number of projected Gauss-Newton
   steps (:data:`GN_STEPS`), the rest state of each by a fixed number of Newton steps on the model's
   equations from the estimate (:data:`NEWTON_STEPS`), its sensitivity to the inputs by the implicit
   function theorem;
2. **the plan**: from the command in force toward ``u_T``, each stage as far as the first move's
   bounds, the rate rows and the stage's bounds allow (a ramp at the rate limits);
3. **the states**: the model's rollout of that plan from the estimate (single shooting), so the QP's
   dynamics rows start without defects.

The QPs of the change are then linearised at that plan and warm-started from it
(:meth:`~.rti_osqp.RtiOsqpSolver.feedback`, ``steady_start``), at the changes :func:`starts_at_target`
admits (``steady_start_on``: every change of the reference, or only those of the supply temperature's).
ASSUMPTION: the model's rest state is
reached from the estimate by Newton's method on its equations (the states are lags toward algebraic
targets, so their Jacobian is regular); where it is not, the target is not finite and the change starts
from the shifted plan as without this start.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hvac_mpc.models.box import INPUTS

from .casadi_eval import BufferedFunction
from .ocp import STAGE_OUTPUTS, TrackingProblem

#: Newton steps on the model's equations for the rest state at given inputs.
NEWTON_STEPS = 4
#: Projected Gauss-Newton steps of the steady-state target.
GN_STEPS = 8
#: Largest move of one scaled input in one Gauss-Newton step (a trust region; the scaled inputs span 2): a full
#: step from far away can land on a bound where a valve's effect is flat, and the steps stall there.
GN_MAX_MOVE = 0.4
#: Levenberg-Marquardt weight of the target's Gauss-Newton steps (scaled inputs): keeps each step's system
#: regular along the directions the redundant actuators leave flat.
GN_DAMPING = 1e-3
#: An input within this of a bound (scaled) counts as at it for the projected steps.
BOUND_TOLERANCE = 1e-9
#: Which reference changes start at the target (``steady_start_on``): "any" change of the stage outputs'
#: reference, or only one of the supply "temperature" reference (a flow or split change alone keeps the
#: shifted plan: it leaves the temperature mix where it was, docs/architecture.md 'Slow steps').
STEADY_START_ON = ("any", "temperature")
#: Row of the supply temperature in the stage outputs' reference.
REF_TEMPERATURE = STAGE_OUTPUTS.index("supply_air_temp_c")


def check_steady_start_on(name: str, value, error: type[ValueError] = ValueError) -> str:
    """``value`` if it is one of :data:`STEADY_START_ON`, else ``error`` naming the field ``name``."""
    if not isinstance(value, str) or value not in STEADY_START_ON:
        raise error(f"{name} = {value!r} must be one of {list(STEADY_START_ON)}")
    return value


def starts_at_target(on: str, old_ref: np.ndarray, new_ref: np.ndarray) -> bool:
    """Whether a step whose stage outputs' reference goes from ``old_ref`` to ``new_ref`` (a change: they
    differ) starts at the steady-state target under ``steady_start_on = on`` (:data:`STEADY_START_ON`)."""
    return on == "any" or old_ref[REF_TEMPERATURE] != new_ref[REF_TEMPERATURE]


class SteadyStart:
    """``start(x0, u_prev, d, p, ref, w_y, lo, hi) -> (u_T, U, X)``, all scaled: the steady-state target, the
    plan toward it and the plan's rollout (module docstring) for :class:`~.ocp.TrackingProblem` ``problem``.

    ``wrap`` turns the CasADi function into the one evaluated (e.g. :func:`.codegen.compiled`)."""

    def __init__(self, problem: TrackingProblem, wrap=lambda f: f):
        self.pb = problem
        self.function = self._build()
        self._fn = BufferedFunction(wrap(self.function))
        horizon_s = float(problem.t_nodes[-1] + problem.terminal_s)
        self._reg = problem.w_du / horizon_s
        self._rb = problem.rate_bounds()

    def start(self, x0: np.ndarray, u_prev: np.ndarray, d: np.ndarray, p: np.ndarray, ref: np.ndarray,
              w_y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Target, plan (N, nu) and states (N + 1, nx) for the estimate ``x0`` (scaled), the command in force
        ``u_prev`` (scaled), the disturbances ``d``, model parameters ``p``, the stage outputs' reference
        ``ref`` and weights ``w_y`` (physical units, :data:`~.ocp.STAGE_OUTPUTS`) and the QP's input bounds
        ``lo``, ``hi`` (N, nu); None where any of them is not finite."""
        u_t, U, X = self._fn(x0, u_prev, d, p, ref, w_y, self._reg, lo, hi, self._rb)
        if not (np.isfinite(u_t).all() and np.isfinite(U).all() and np.isfinite(X).all()):
            return None
        return u_t, U, X

    # ------------------------------------------------------------------ the function
    def _build(self) -> ca.Function:
        pb = self.pb
        nx, nu, nd, ny, N = pb.nx, pb.nu, pb.nd, pb.ny, pb.N
        x0, u_prev, d = ca.SX.sym("x0", nx), ca.SX.sym("u_prev", nu), ca.SX.sym("d", nd)
        p = ca.SX.sym("p", len(pb.model.p_default))
        ref, w_y, reg = ca.SX.sym("ref", ny), ca.SX.sym("w_y", ny), ca.SX.sym("reg", nu)
        lo, hi, rb = ca.SX.sym("lo", nu, N), ca.SX.sym("hi", nu, N), ca.SX.sym("rb", nu, N - 1)
        u_t = self._target(x0, u_prev, d, p, ref, w_y, reg, lo[:, N - 1], hi[:, N - 1])
        U = self._ramp(u_t, u_prev, lo, hi, rb)
        X = self._rollout(x0, U, d, p)
        return ca.Function("hvac_steady_start", [x0, u_prev, d, p, ref, w_y, reg, lo, hi, rb], [u_t, U, X],
                           ["x0", "u_prev", "d", "p", "ref", "w_y", "reg", "lo", "hi", "rb"], ["u_T", "U", "X"])

    def _residual_function(self) -> ca.Function:
        """(x_phys, u scaled, d, p, ref, w_y, reg, u_prev) -> (model rates, weighted residuals at rest)."""
        pb = self.pb
        x, u, d = ca.SX.sym("x", pb.nx), ca.SX.sym("u", pb.nu), ca.SX.sym("d", pb.nd)
        p, ref, w_y = ca.SX.sym("p", len(pb.model.p_default)), ca.SX.sym("ref", pb.ny), ca.SX.sym("w_y", pb.ny)
        reg, u_prev = ca.SX.sym("reg", pb.nu), ca.SX.sym("u_prev", pb.nu)
        u_phys = pb.command_expr(u)
        xdot = pb.model.ode(x, u_phys, d, p)
        xs = (x - ca.DM(pb.x_off)) / ca.DM(pb.x_sc)
        y = pb.stage_values_function(1)(xs, u, d, 1.0, p)[1]  # the stage outputs at x (the step's x_next unused)
        i_power, i_blower = STAGE_OUTPUTS.index("heater_power_w"), INPUTS.index("blower_power_w")
        energy = (y[i_power] + u_phys[i_blower]) * np.sqrt(pb.energy_weight) / pb.energy_scale_w
        r = ca.vertcat(ca.sqrt(w_y) * (y - ref) / ca.DM(pb.y_scale), energy, ca.sqrt(reg) * (u - u_prev))
        return ca.Function("rest", [x, u, d, p, ref, w_y, reg, u_prev], [xdot, r])

    def _target(self, x0, u_prev, d, p, ref, w_y, reg, lo, hi):
        """Projected Gauss-Newton on the rest cost, the rest state by Newton steps (unrolled, SX)."""
        pb = self.pb
        rest = self._residual_function()
        xs, us = ca.SX.sym("x", pb.nx), ca.SX.sym("u", pb.nu)
        args = [d, p, ref, w_y, reg, u_prev]
        f, r = rest(xs, us, *args)
        f_x, f_u = ca.jacobian(f, xs), ca.jacobian(f, us)
        r_x, r_u = ca.jacobian(r, xs), ca.jacobian(r, us)
        newton = ca.Function("newton", [xs, us, *args], [xs - ca.solve(f_x, f)])
        # the residual's sensitivity to the inputs along the rest state: dr/du - dr/dx f_x^-1 f_u
        sens = ca.Function("sens", [xs, us, *args], [r, r_u - ca.mtimes(r_x, ca.solve(f_x, f_u))])
        x = pb.x_off + pb.x_sc * x0
        u = ca.fmin(ca.fmax(u_prev, lo), hi)
        eye = ca.DM.eye(pb.nu)
        for _ in range(GN_STEPS):
            for _ in range(NEWTON_STEPS):
                x = newton(x, u, *args)
            res, J = sens(x, u, *args)
            g = ca.mtimes(J.T, res)
            at_lo = ca.logic_and(u <= lo + BOUND_TOLERANCE, g > 0)
            at_hi = ca.logic_and(u >= hi - BOUND_TOLERANCE, g < 0)
            free = 1 - ca.logic_or(at_lo, at_hi)
            M = ca.diag(free)
            H = ca.mtimes(J.T, J) + GN_DAMPING * eye
            step = -ca.solve(ca.mtimes([M, H, M]) + (eye - M), free * g)
            step = step * ca.fmin(1.0, GN_MAX_MOVE / ca.fmax(ca.mmax(ca.fabs(step)), 1e-12))
            u = ca.fmin(ca.fmax(u + step, lo), hi)
        return u

    def _ramp(self, u_t, u_prev, lo, hi, rb):
        """Stage by stage from ``u_prev`` toward ``u_t``: the stage's bounds (stage 0's hold the first move's
        rate limits) and the rate rows to the stage before."""
        cols = []
        prev = u_prev
        for k in range(self.pb.N):
            u = u_t if k == 0 else ca.fmin(ca.fmax(u_t, prev - rb[:, k - 1]), prev + rb[:, k - 1])
            u = ca.fmin(ca.fmax(u, lo[:, k]), hi[:, k])
            cols.append(u)
            prev = u
        return ca.horzcat(*cols)

    def _rollout(self, x0, U, d, p):
        """The model's states along the plan ``U`` from ``x0`` (scaled), each stage with its own substeps."""
        pb = self.pb
        fns = {n: pb.stage_values_function(n) for n in set(int(s) for s in pb.stage_substeps[:pb.N])}
        cols = [x0]
        x = x0
        for k in range(pb.N):
            x = fns[int(pb.stage_substeps[k])](x, U[:, k], d, float(pb.dt[k]), p)[0]
            cols.append(x)
        return ca.horzcat(*cols)
