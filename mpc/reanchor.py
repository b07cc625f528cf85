"""States the readings do not tell apart, re-anchored to their physics once a dead time is found.

Before the dead-time estimate (:class:`~.dead_time.DeadTimeEstimator`) has found a dead time, the filter compares
the reading with the model's undelayed air, and the controller's first moves answer a dead time late; the
innovation then goes where the covariance lets it, into states nothing but the model tells from the mixed-air
offset: the motor rise (pushed to -2.5 degC for a box's +0.9 degC on a 4 s dead time) and the unpowered heater body.
Once the dead time is honoured they unwind with their own time constants (the motor's 268 s lag), a ramp the
offset's random walk follows with a lag (docs/robustness.md sec. 2.8, 2.9).

Here those states are also run open loop beside the filter (:class:`OpenLoopShadow`: the model's own equations
with the commands applied and the filter's other states, no measurement update) from the filter's start. While the
filter holds them (:meth:`~.estimator.DisturbanceEkf`, ``EkfSettings.reanchor_*``: from the first sample a dead time
is honoured until a while after it last changed) they are set to the shadow's values every sample and the mixed-air
offset (and the heater outlet reading's offset) take the difference of the model's air, so the supply air the
filter explains does not move; the covariance follows the same map linearised (:func:`reanchor`). What the late
response had put into them is then in the offset, which the readings do see. ASSUMPTION: the shadow's physics (the
nominal motor gain and heater body) is nearer the box than what a misplaced late response made of them; the box
has been near rest when the filter starts (the shadow starts at the filter's start state).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hvac_mpc.models.box import HvacModel, rk4

from .casadi_eval import BufferedFunction

#: The states that may be re-anchored: those only the model tells from the mixed-air offset.
REANCHORABLE = ("motor_rise_c", "heater_temp_c", "trap_air_temp_c")


@dataclass(frozen=True)
class FilterLayout:
    """Where the re-anchor acts in the filter's state: the model states' count, the mixed-air offset's index and
    the heater outlet reading's offset's index (None: the filter has none)."""

    nx: int
    i_mix_offset: int
    i_outlet_offset: int | None


class OpenLoopShadow:
    """Chosen model states run open loop with the commands applied (the other states taken from the filter)."""

    def __init__(self, model: HvacModel, names: tuple[str, ...], dt_s: float):
        unknown = [n for n in names if n not in REANCHORABLE]
        if unknown:
            raise ValueError(f"reanchor_states: {unknown} not among {REANCHORABLE}")
        self.idx = np.array([model.states.index(n) for n in names if n in model.states.names], int)
        x, u = ca.SX.sym("x", len(model.states)), ca.SX.sym("u", len(model.inputs))
        d, p = ca.SX.sym("d", len(model.disturbances)), ca.SX.sym("p", len(model.param_names))
        own = ca.SX.sym("own", len(self.idx))  # the shadowed states' values, the rest of x the filter's
        xs = ca.vertcat(*[own[list(self.idx).index(i)] if i in self.idx else x[i] for i in range(x.shape[0])])
        step = rk4(model.ode, xs, u, d, p, dt_s, 2)
        self.step_fn = ca.Function("shadow_step", [x, own, u, d, p], [ca.vertcat(*[step[int(i)] for i in self.idx])])
        y = model.output(x, u, d, p)
        air = y[model.outputs.index("supply_air_temp_c")] - d[model.disturbances.index("mix_offset_c")]
        self.air_fn = ca.Function("shadow_air", [x, u, d, p], [air, y[model.outputs.index("heater_outlet_temp_c")]])
        self.use_functions(self.step_fn, self.air_fn)
        self.values: np.ndarray | None = None

    def use_functions(self, step_fn, air_fn) -> None:
        """Evaluate the open-loop step and the airs with these functions (the signatures of :attr:`step_fn` and
        :attr:`air_fn`, e.g. generated C of them, :func:`~.codegen.compiled`)."""
        self._step = BufferedFunction(step_fn)
        self._air = BufferedFunction(air_fn)

    def start(self, x: np.ndarray) -> None:
        """Start at the filter's state (its start, where the box is assumed near rest)."""
        self.values = np.asarray(x, float)[self.idx].copy()

    def advance(self, x: np.ndarray, u: np.ndarray, d: np.ndarray, p: np.ndarray) -> None:
        """One sample with command ``u`` in force: the shadowed states from their last values, the others the
        filter's now (an approximation: they are a sample newer; the shadowed states' rates depend on them
        through the water and inlet temperatures, which change slowly)."""
        if self.values is None:
            return
        self.values = self._step(x, self.values, u, d, p)[0].reshape(-1)

    def air(self, x: np.ndarray, u: np.ndarray, d: np.ndarray, p: np.ndarray) -> tuple[float, float]:
        """The model's mixed air without the offset and its heater outlet air (degC) at state ``x``."""
        a, o = self._air.views(x, u, d, p)  # read at once: no copies
        return float(a[0]), float(o[0])


def reanchor(shadow: OpenLoopShadow, z: np.ndarray, P: np.ndarray, layout: FilterLayout, sd: np.ndarray,
             u: np.ndarray, d: np.ndarray, p: np.ndarray) -> float:
    """Set the shadowed states of filter state ``z`` (covariance ``P``, both changed in place) to the shadow's,
    the offsets taking the change of the model's air. The covariance follows the same map linearised: each
    offset becomes itself plus its air's sensitivity times each moved state's error, the moved states
    independent of the rest with standard deviations ``sd`` (degC). The offsets keep their
    correlations with the history of the thermocouple state (through them a reading compared a dead time late
    tells the offset at all). Returns the mixed-air offset's change (degC)."""
    x = z[:layout.nx].copy()
    air0, out0 = shadow.air(x, u, d, p)
    moved = x.copy()
    moved[shadow.idx] = shadow.values
    air1, out1 = shadow.air(moved, u, d, p)
    offsets = [(layout.i_mix_offset, air0 - air1, 0)]
    if layout.i_outlet_offset is not None:
        offsets.append((layout.i_outlet_offset, out0 - out1, 1))
    T = np.eye(len(z))
    for i, h in zip(shadow.idx, _steps(shadow.values)):  # sensitivities of the model's airs, forward differences
        nudged = moved.copy()
        nudged[i] += h
        airs = np.subtract(shadow.air(nudged, u, d, p), (air1, out1)) / h
        for j, _, k in offsets:
            T[j, i] = airs[k]
        T[i, :] = 0.0
    P[:] = T @ P @ T.T
    for i, sd_i in zip(shadow.idx, sd):
        P[i, i] = float(sd_i) ** 2
    z[:layout.nx] = moved
    for j, change, _ in offsets:
        z[j] += change
    return air0 - air1


def _steps(values: np.ndarray) -> np.ndarray:
    """Forward-difference steps (degC) for states of these values."""
    return 1e-4 * np.maximum(1.0, np.abs(values))
