"""Least-squares fitting of a model structure to the training part of a log.

The cost is the free-run simulation error of the logged outputs, each scaled by its noise
level, summed over the training rows. Parameters are fitted in scaled coordinates theta:
``log`` parameters as p = p_start exp(theta), ``lin`` ones as p = p_start + scale theta;
output offsets (bias and drift) in units of the output's noise level. Jacobians come from the
model's forward sensitivities (Gauss-Newton, scipy ``least_squares`` with bounds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import numpy as np
from scipy.optimize import least_squares

from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.codegen_background import BackgroundBuilds

from . import statistics as st
from .pairs import gauss_newton_step
from .log_data import LogData
from .simulator import OutputPost, Simulator

#: Noise floors per output (a noise-free logged signal would otherwise get an infinite weight).
SIGMA_FLOOR = {"supply_temp_c": 0.01, "volume_flow_m3s": 2e-5, "heater_outlet_temp_c": 0.01,
               "heater_power_w": 0.5}


@dataclass(frozen=True)
class FreeParam:
    """A model parameter to fit: ``log`` (p = p0 e^theta) or ``lin`` (p = p0 + scale theta)."""

    name: str
    transform: str = "log"
    scale: float = 1.0
    lo: float | None = None
    hi: float | None = None

    def bounds(self) -> tuple[float, float]:
        f = Parameters.__dataclass_fields__[self.name]
        lo, hi = f.metadata["range"]
        lo = lo if self.lo is None else max(lo, self.lo)
        hi = hi if self.hi is None else min(hi, self.hi)
        return lo, hi


#: Free parameters of the nominal (thesis) model: the ones the thesis fitted or that stand in
#: for missing figures (docs/model.md sec. 1). Thesis-measured constants (masses, tau_TC, tau_m,
#: slopes of the chiller) stay fixed. The first two set the flow equation only.
NOMINAL_FREE = (
    FreeParam("flow_per_watt_m3s_per_w", "log"),
    FreeParam("core_flow_loss", "lin", 0.05, 0.0, 0.4),
    FreeParam("motor_gain_max_c", "log", lo=0.05, hi=8.0),
    FreeParam("bypass_exponent", "log", lo=0.3, hi=4.0),
    FreeParam("cooler_slope", "lin", 0.05, 0.3, 0.98),
    FreeParam("heater_kp", "log", lo=0.2, hi=1.0),
)
#: Range of an output gain's step theta (gain = 1 + theta): a reading between 20 % and twice the model's.
GAIN_THETA = (-0.8, 1.0)
#: Nominal parameters of the flow equation (models/blower.py), fitted on the volume flow alone first.
FLOW_PARAMS = ("flow_per_watt_m3s_per_w", "core_flow_loss")


@dataclass
class Fit:
    """A fitted model structure: effects, full parameter vector, output corrections, costs."""

    effects: frozenset
    p: np.ndarray
    post: OutputPost
    free: tuple[str, ...]
    y: np.ndarray                 # free-run prediction incl. output corrections (n x n_y)
    states: np.ndarray
    cost_train: float             # sum of squared scaled errors on the training rows
    cost_holdout: float
    n_train: int
    n_holdout: int
    nfev: int = 0
    message: str = ""
    extra: dict = field(default_factory=dict)
    terms: tuple = ()             # discovered terms (models/discovered.py) in the structure

    def residual(self, y_meas: np.ndarray) -> np.ndarray:
        return y_meas - self.y


class Fitter:
    """Fits model structures to one log; caches one :class:`Simulator` per effect set."""

    def __init__(self, log: LogData, base: Parameters, quick: bool = False):
        self.log = log
        self.base = base
        self.quick = quick
        self.outputs = log.output_names()
        self.y_meas = np.column_stack([log.outputs[o] for o in self.outputs])
        self.sigma = np.array([st.noise_sigma(log.outputs[o][log.train], SIGMA_FLOOR.get(o, 0.0))
                               for o in self.outputs])
        self.names = Parameters.scalar_names()
        self._sims: dict[frozenset, Simulator] = {}
        #: the simulators' step functions as generated C once built (docs/identification.md "Runs as generated C")
        self.builds = BackgroundBuilds()
        #: Rows up to the last training row: a fit's residual and Jacobian, a screening step and a training cost
        #: use these alone (the held-out rows are the log's last part, log_data.prepare), so runs stop there.
        self.train_rows = int(np.flatnonzero(log.train)[-1]) + 1 if np.any(log.train) else log.n

    def simulator(self, effects: Iterable[str], terms: tuple = ()) -> Simulator:
        key = (frozenset(effects), tuple(terms))
        if key not in self._sims:
            self._sims[key] = Simulator(self.log, self.base, key[0], self.outputs, key[1], builds=self.builds)
        return self._sims[key]

    # ------------------------------------------------------------------ costs
    def scaled(self, y: np.ndarray) -> np.ndarray:
        r = (self.y_meas - y) / self.sigma
        return np.where(np.isfinite(r), r, 0.0)

    def costs(self, y: np.ndarray) -> tuple[float, float]:
        r2 = self.scaled(y) ** 2
        return float(r2[self.log.train].sum()), float(r2[self.log.holdout].sum())

    def output_costs(self, y: np.ndarray, part: str = "holdout") -> tuple[np.ndarray, np.ndarray]:
        """Per output: sum of squared scaled errors and number of samples on one part."""
        mask = self.log.holdout if part == "holdout" else self.log.train
        r2 = self.scaled(y) ** 2
        ok = np.isfinite(self.y_meas)
        return r2[mask].sum(axis=0), ok[mask].sum(axis=0)

    def structure(self, y: np.ndarray, part: str = "holdout") -> float:
        """Held-out cost beyond the noise expectation, summed over outputs: sum_o max(C_o - N_o, 0)."""
        c, n = self.output_costs(y, part)
        return float(np.sum(np.maximum(c - n, 0.0)))

    def counts(self) -> tuple[int, int]:
        ok = np.isfinite(self.y_meas)
        return int(ok[self.log.train].sum()), int(ok[self.log.holdout].sum())

    def evaluate(self, effects: Iterable[str], p: np.ndarray, post: OutputPost, free: Sequence[str] = (),
                 nfev: int = 0, message: str = "", terms: tuple = ()) -> Fit:
        sim = self.simulator(effects, terms)
        y, states = sim.simulate(p)
        y = post.apply(y)
        ct, ch = self.costs(y)
        nt, nh = self.counts()
        return Fit(frozenset(effects), p.copy(), post.copy(), tuple(free), y, states, ct, ch, nt, nh, nfev, message,
                   terms=tuple(terms))

    # ------------------------------------------------------------------ fitting
    def train_cost(self, effects: Iterable[str], p: np.ndarray, post: OutputPost, terms: tuple = ()) -> float:
        """The training cost of :meth:`evaluate` (the same value), from a run of the training rows alone."""
        y = post.apply(self.simulator(effects, terms).simulate(p, self.train_rows)[0])
        return float((self.scaled(y) ** 2)[self.log.train].sum())

    def identifiable(self, effects, p, post, free: Sequence[FreeParam], terms: tuple = ()) -> list[FreeParam]:
        """Drop free parameters the training data barely excite (theta column norm < 1)."""
        if not free:
            return []
        sim = self.simulator(effects, terms)
        e = self._e_matrix(p, free)
        _, dy = sim.simulate_with_sensitivity(p, e, self.train_rows)
        dy = post.apply(np.zeros(dy.shape[:2]), dy)[1]
        scaled = dy / self.sigma[None, :, None]
        ok = np.isfinite(self.y_meas) & self.log.train[:, None]
        norms = np.sqrt(np.sum(np.where(ok[:, :, None], scaled, 0.0) ** 2, axis=(0, 1)))
        return [fp for fp, nrm in zip(free, norms) if nrm >= 1.0]

    def raw_sensitivity(self, effects, p: np.ndarray, free: Sequence[FreeParam], terms: tuple = ()) -> np.ndarray:
        """dY/dtheta of the free run before the output corrections (n x n_y x len(free))."""
        if not free:
            return np.zeros((self.log.n, len(self.outputs), 0))
        return self.simulator(effects, terms).simulate_with_sensitivity(p, self._e_matrix(p, free))[1]

    def gn_step(self, effects, p0: np.ndarray, free: Sequence[FreeParam], dy_free: np.ndarray,
                own: Sequence[FreeParam], post: OutputPost, bias_outputs: Sequence[str] = (), terms: tuple = (),
                damping: float = 1e-2, gain_outputs: Sequence[str] = ()) -> Fit:
        """One joint Gauss-Newton step from ``p0``: the free parameters (sensitivities ``dy_free``, taken
        from the current model) and the candidate's own parameters (and offsets) together, evaluated by a
        free run (the step halved up to twice while the training cost rises; no step at all if it still does). The score of a candidate with the nominal
        parameters refit together with it, at the cost of about two free runs."""
        sim = self.simulator(effects, terms)
        post = post.copy()
        for o in bias_outputs:
            post.bias.pop(o, None)
        for o in gain_outputs:
            post.gain.pop(o, None)
        kept = self._kept_bias(post, gain_outputs)
        rows = self.train_rows  # the step is taken on the training rows
        y0, dy_own = (sim.simulate_with_sensitivity(p0, self._e_matrix(p0, own), rows) if own else
                      (sim.simulate(p0, rows)[0], None))
        cols = [dy_free] + ([dy_own] if own else [])
        d = np.concatenate(cols, axis=2)
        y0, d = post.apply(y0, d)
        y_gain = y0.copy()  # the outputs a gain multiplies (without their offsets, which it does not)
        y0 = OutputPost(self.outputs, self.log.time_s, bias=kept).apply(y0)
        bias_idx = [self.outputs.index(o) for o in bias_outputs]
        gain_idx = [self.outputs.index(o) for o in gain_outputs]
        extra = self.offset_gain_columns(bias_idx, gain_idx, y_gain, post.ramp)
        if extra:
            d = np.concatenate([d] + extra, axis=2)
        step, cost_start = gauss_newton_step(self.y_meas, y0, d, self.sigma, self.log.train, damping)
        all_free = list(free) + list(own)
        best = None
        for scale in (1.0, 0.5, 0.25, 0.0):
            theta = scale * step
            p = self.step_params(p0, all_free, theta)
            trial = post.copy()
            trial.bias.update(kept)
            for k, j in enumerate(bias_idx):
                b = len(all_free) + 2 * k
                trial.bias[self.outputs[j]] = (float(theta[b] * self.sigma[j]), float(theta[b + 1] * self.sigma[j]))
            for k, j in enumerate(gain_idx):
                trial.gain[self.outputs[j]] = float(1.0 + np.clip(theta[len(all_free) + 2 * len(bias_idx) + k],
                                                                  *GAIN_THETA))
            cost = self.train_cost(effects, p, trial, terms)  # the whole log is run for the scale kept only
            if best is None or cost < best[0]:
                best = (cost, p, trial)
            if np.isfinite(cost) and cost <= cost_start:
                break
        best = self.evaluate(effects, best[1], best[2], [fp.name for fp in all_free], 1, "one Gauss-Newton step", terms)
        best.extra["start_p"] = p0.copy()  # where the step started (a pair's linear screening starts there too)
        return best

    def step_params(self, p0: np.ndarray, free: Sequence[FreeParam], theta: np.ndarray) -> np.ndarray:
        """The parameter vector ``p0`` moved by a step ``theta`` of the scaled ``free`` parameters (their first
        ``len(free)`` entries; a log step at most e^3), within each parameter's bounds."""
        p = p0.copy()
        for k, fp in enumerate(free):
            i = self.names.index(fp.name)
            lo, hi = fp.bounds()
            v = p0[i] * math.exp(np.clip(theta[k], -3.0, 3.0)) if fp.transform == "log" else p0[i] + fp.scale * theta[k]
            p[i] = min(max(v, lo), hi)
        return p

    def offset_gain_columns(self, bias_idx: Sequence[int], gain_idx: Sequence[int], y_gain: np.ndarray | None,
                             ramp: np.ndarray) -> list[np.ndarray]:
        """Jacobian columns (n, outputs, k) of the fitted offsets and gains: per offset output a constant and a
        drift (``ramp``) in units of its sigma, per gain output the output itself (``y_gain``, without the
        offsets a gain does not multiply: y_j -> (1 + theta) y_j)."""
        cols = []
        for j in bias_idx:
            block = np.zeros((self.log.n, len(self.outputs), 2))
            block[:, j, 0] = self.sigma[j]
            block[:, j, 1] = self.sigma[j] * ramp
            cols.append(block)
        for j in gain_idx:
            block = np.zeros((self.log.n, len(self.outputs), 1))
            block[:, j, 0] = np.nan_to_num(y_gain[:, j])
            cols.append(block)
        return cols

    @staticmethod
    def _kept_bias(post: OutputPost, gain_outputs: Sequence[str]) -> dict:
        """Takes the offsets of the outputs whose gain is fitted out of ``post`` (a gain multiplies the model's
        output, not the offset added after it) and returns them, to be added back unchanged."""
        return {o: post.bias.pop(o) for o in gain_outputs if o in post.bias}

    def _e_matrix(self, p: np.ndarray, free: Sequence[FreeParam]) -> np.ndarray:
        e = np.zeros((len(self.names), len(free)))
        for j, fp in enumerate(free):
            i = self.names.index(fp.name)
            e[i, j] = p[i] if fp.transform == "log" else fp.scale
        return e

    def fit(self, effects: Iterable[str], p_start: np.ndarray, free: Sequence[FreeParam], post: OutputPost,
            bias_outputs: Sequence[str] = (), max_nfev: int | None = None,
            only_outputs: Sequence[str] | None = None, terms: tuple = (), gain_outputs: Sequence[str] = ()) -> Fit:
        """Fit ``free`` model parameters (and offset+drift of ``bias_outputs``, the gain of ``gain_outputs``) on
        the training rows (of ``only_outputs`` when given, else of every logged output)."""
        effects = frozenset(effects)
        sim = self.simulator(effects, terms)
        free = list(free)
        p0 = p_start.copy()
        idx = [self.names.index(fp.name) for fp in free]
        for fp, i in zip(free, idx):  # start inside the bounds
            lo, hi = fp.bounds()
            p0[i] = min(max(p0[i], lo if fp.transform == "lin" else max(lo, 1e-300)), hi)
        bias_idx = [self.outputs.index(o) for o in bias_outputs]
        post = post.copy()
        for o in bias_outputs:
            post.bias.pop(o, None)
        gain_idx = [self.outputs.index(o) for o in gain_outputs]
        for o in gain_outputs:
            post.gain.pop(o, None)
        kept = self._kept_bias(post, gain_outputs)
        n_model = len(free)
        n_bias = 2 * len(bias_idx)
        lo_b, hi_b = [], []
        for fp, i in zip(free, idx):
            lo, hi = fp.bounds()
            if fp.transform == "log":
                lo_b.append(math.log(max(lo, 1e-300) / p0[i]) if lo > 0 else -30.0)
                hi_b.append(math.log(hi / p0[i]))
            else:
                lo_b.append((lo - p0[i]) / fp.scale)
                hi_b.append((hi - p0[i]) / fp.scale)
        lo_b += [-np.inf] * n_bias + [GAIN_THETA[0]] * len(gain_idx)
        hi_b += [np.inf] * n_bias + [GAIN_THETA[1]] * len(gain_idx)
        lo_b = np.array(lo_b)
        hi_b = np.array(hi_b)
        train = self.log.train
        ok = np.isfinite(self.y_meas) & train[:, None]
        if only_outputs is not None:
            ok &= np.array([o in only_outputs for o in self.outputs])[None, :]
        ramp = post.ramp

        def params(theta):
            p = p0.copy()
            for j, (fp, i) in enumerate(zip(free, idx)):
                p[i] = p0[i] * math.exp(theta[j]) if fp.transform == "log" else p0[i] + fp.scale * theta[j]
            return p

        def add_bias(y, theta):
            y = y.copy()
            for k, j in enumerate(gain_idx):
                y[:, j] *= 1.0 + theta[n_model + n_bias + k]
                b0, b1 = kept.get(self.outputs[j], (0.0, 0.0))
                y[:, j] += b0 + b1 * ramp
            for k, j in enumerate(bias_idx):
                b0, b1 = theta[n_model + 2 * k] * self.sigma[j], theta[n_model + 2 * k + 1] * self.sigma[j]
                y[:, j] += b0 + b1 * ramp
            return y

        ahead: dict[bytes, tuple] = {}  # the sensitivity run of the last evaluation (the solver's next Jacobian)
        evaluations = [0]

        def resid(theta):
            evaluations[0] += 1
            p = params(theta)
            ahead.clear()
            if n_model and evaluations[0] < max_nfev:
                # the solver asks for the Jacobian at each point it accepts (every point, in the fits here): one run
                # gives both; after the last evaluation no Jacobian is used (capped_least_squares)
                y, dy = sim.simulate_with_sensitivity(p, self._e_matrix(p, free), self.train_rows)
                ahead[theta.tobytes()] = (y, dy)
            else:
                y, _ = sim.simulate(p, self.train_rows)
            y = add_bias(post.apply(y), theta)
            r = np.where(ok, (y - self.y_meas) / self.sigma, 0.0)
            return r[train].ravel()

        def jac(theta):
            p = params(theta)
            cols = []
            if n_model:
                run = ahead.pop(theta.tobytes(), None)
                y, dy = run if run is not None else sim.simulate_with_sensitivity(p, self._e_matrix(p, free),
                                                                                  self.train_rows)
                y, dy = post.apply(y, dy)
                for k, j in enumerate(gain_idx):
                    dy[:, j, :] *= 1.0 + theta[n_model + n_bias + k]
                cols.append(dy)
            elif gain_idx:
                y = post.apply(sim.simulate(p, self.train_rows)[0])
            cols += self.offset_gain_columns(bias_idx, gain_idx, y if gain_idx else None, ramp)
            d = np.concatenate(cols, axis=2) if cols else np.zeros((self.log.n, len(self.outputs), 0))
            d = np.where(ok[:, :, None], d / self.sigma[None, :, None], 0.0)
            return d[train].reshape(-1, d.shape[2])

        # start a little inside the bounds: trf's scaling freezes variables that sit on a bound
        width = np.where(np.isfinite(hi_b - lo_b), np.minimum(hi_b - lo_b, 10.0), 10.0)
        theta0 = np.zeros(n_model + n_bias + len(gain_idx))
        at_lo, at_hi = theta0 - lo_b < 1e-3 * width, hi_b - theta0 < 1e-3 * width
        theta0 = np.where(at_lo, lo_b + 0.02 * width, np.where(at_hi, hi_b - 0.02 * width, theta0))
        if len(theta0) == 0:
            return self.evaluate(effects, p0, post, terms=terms)
        max_nfev = max_nfev or (12 if self.quick else 40)
        sol = capped_least_squares(resid, jac, theta0, (lo_b, hi_b), max_nfev)
        p = params(sol.x)
        for k, j in enumerate(bias_idx):
            post.bias[self.outputs[j]] = (float(sol.x[n_model + 2 * k] * self.sigma[j]),
                                          float(sol.x[n_model + 2 * k + 1] * self.sigma[j]))
        for k, j in enumerate(gain_idx):
            post.gain[self.outputs[j]] = float(1.0 + sol.x[n_model + n_bias + k])
        post.bias.update(kept)
        fit = self.evaluate(effects, p, post, [fp.name for fp in free], sol.nfev, sol.message, terms)
        fit.extra["theta"] = sol.x.tolist()
        return fit


def capped_least_squares(resid: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray],
                         theta0: np.ndarray, bounds: tuple, max_nfev: int):
    """scipy's bounded trust-region least squares (``trf``, Jacobian scaling) of ``resid`` from ``theta0``, at most
    ``max_nfev`` evaluations, without the Jacobian it would compute after its last evaluation.

    ``trf`` computes the Jacobian at every accepted point, also after the evaluation that reaches ``max_nfev``, and
    then stops without using it; here that Jacobian is the last one computed (the solution, its cost and evaluation
    count are those of the plain call). The fits of the identification mostly stop at their evaluation cap, and a
    Jacobian is a forward-sensitivity run of the whole log, the most expensive part of a fit."""
    calls = {"fun": 0, "jac": None}

    def counted(theta):
        calls["fun"] += 1
        return resid(theta)

    def jac_used(theta):
        if calls["fun"] >= max_nfev and calls["jac"] is not None:
            return calls["jac"]  # after the last evaluation: trf stops before it uses this Jacobian
        calls["jac"] = jac(theta)
        return calls["jac"]

    return least_squares(counted, theta0, jac=jac_used, bounds=bounds, method="trf", x_scale="jac",
                         max_nfev=max_nfev, ftol=1e-8, xtol=1e-8, gtol=1e-10)


#: A refit nominal parameter counts as identified when its standard error is at most this share of its value.
IDENTIFIED_REL_SE = 0.25
#: ... and as moved by the log (named in the report) when it lies this many standard errors and this share of
#: its value away from the value it started from.
MOVED_Z = 2.58  # two-sided 99 %, the level of the other tests (pipeline.ALPHA)
MOVED_REL = 0.05

#: What a move of a thesis-measured nominal parameter says about the box, in words (the report names it as an
#: effect). The other free parameters are stand-ins for figures the thesis does not give (docs/model.md sec. 1,
#: ASSUMPTIONS): their move is a calibration, reported but not named (the flow equation's core loss moves
#: 0.10 -> 0.088 on every log of the independent box, the clean one too).
PARAMETER_WORDS = {
    "cooler_slope": "the cooler core's effectiveness differs from the thesis's fit (its outlet follows the water "
                    "by a different share)",
    "heater_kp": "the heater gives a different share of its electric power to the air than the thesis's k_p "
                 "(a weaker or stronger heater)",
}


def parameter_confidence(fitter: Fitter, fit: Fit, free: Sequence[FreeParam], start: np.ndarray) -> list[dict]:
    """Standard error of each refit parameter at ``fit`` and whether the log identifies and moved it.

    Gauss-Newton covariance (sum_o w_o J_o' J_o / s_o^2)^-1 over the logged outputs o on the training rows, with
    s_o^2 the output's scaled residual variance and w_o = n_eff,o / n_o (n_eff its effective sample size,
    :func:`statistics.effective_n`): the residual is autocorrelated, so a smooth residual does not count every
    row as independent evidence. ``identified``: standard
    error at most :data:`IDENTIFIED_REL_SE` of the value; ``moved``: identified and more than :data:`MOVED_Z`
    standard errors and :data:`MOVED_REL` of the value away from ``start`` (the parameter vector the fit
    started from, the thesis values)."""
    free = list(free)
    if not free:
        return []
    cov = parameter_covariance(fitter, fit, free)
    out = []
    for k, fp in enumerate(free):
        i = fitter.names.index(fp.name)
        value, begin = float(fit.p[i]), float(start[i])
        se_theta = float(math.sqrt(max(cov[k, k], 0.0)))
        se = abs(value) * se_theta if fp.transform == "log" else fp.scale * se_theta
        identified = se <= IDENTIFIED_REL_SE * abs(value)
        z = (value - begin) / se if se > 0 else float("inf")
        moved = identified and abs(z) > MOVED_Z and abs(value - begin) > MOVED_REL * abs(begin)
        out.append({"name": fp.name, "start": begin, "value": value, "se": se, "z": float(z),
                    "change": (value - begin) / begin if begin else float("nan"),
                    "identified": bool(identified), "moved": bool(moved), "words": PARAMETER_WORDS.get(fp.name, "")})
    return out


def parameter_covariance(fitter: Fitter, fit: Fit, free: Sequence[FreeParam]) -> np.ndarray:
    """Gauss-Newton covariance of the refit parameters ``free`` at ``fit``, in the fit's own coordinates (theta:
    log(p / p0) for a ``log`` parameter, (p - p0) / scale for a ``lin`` one), weighted as
    :func:`parameter_confidence` says."""
    free = list(free)
    dy = fitter.raw_sensitivity(fit.effects, fit.p, free, fit.terms)
    dy = fit.post.apply(np.zeros(dy.shape[:2]), dy)[1]
    ok = np.isfinite(fitter.y_meas) & fitter.log.train[:, None]
    resid = fitter.scaled(fit.y)
    info = np.zeros((len(free), len(free)))
    for j in range(resid.shape[1]):
        rows = ok[:, j]
        if rows.sum() <= len(free):
            continue
        jm = dy[rows, j, :] / fitter.sigma[j]
        s2 = float(np.mean(resid[rows, j] ** 2))
        w = min(st.effective_n(resid[rows, j]) / rows.sum(), 1.0)
        info += w * (jm.T @ jm) / max(s2, 1e-12)
    return np.linalg.pinv(info)


def joint_wald(cov: np.ndarray, free: Sequence[FreeParam], value: np.ndarray, start: np.ndarray,
               names: Sequence[str], subset: Sequence[str]) -> float:
    """Wald statistic of the hypothesis "every parameter of ``subset`` is at its ``start`` value" from the refit
    ``value`` and the covariance ``cov`` of ``free`` (:func:`parameter_covariance`); chi-square with len(subset)
    degrees of freedom under the hypothesis. It counts the estimates' correlation, which per-parameter z values do
    not: six parameters each within 2.6 standard errors can lie jointly far outside."""
    free = list(free)
    ks = [k for k, fp in enumerate(free) if fp.name in set(subset)]
    if not ks:
        return 0.0
    d = np.array([_theta(free[k], float(value[names.index(free[k].name)]), float(start[names.index(free[k].name)]))
                  for k in ks])
    block = cov[np.ix_(ks, ks)]
    return float(d @ np.linalg.pinv(block) @ d)


def _theta(fp: FreeParam, value: float, begin: float) -> float:
    """The fit's coordinate of ``value`` measured from ``begin`` (see :class:`FreeParam`)."""
    if fp.transform == "log":
        return math.log(value / begin) if value > 0 and begin > 0 else float("inf")
    return (value - begin) / fp.scale
