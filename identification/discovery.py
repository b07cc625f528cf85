"""Term discovery: a term nobody declared, found by sparse regression on the supply residual.

When the supply temperature's residual stays structured after the candidate library, the
missing physics is looked for as an additive term in the supply-air energy balance
(models/discovered.py): ``dT = sum_i c_i f_i`` over the feature vocabulary
:data:`hvac_mpc.models.discovered.FEATURES` (temperature differences over the mass flow, the core
path, products with the flow, ...), evaluated along the fitted model's free run.

Because the term enters after mixing, the reading sees it through the thermocouple lag (and the
supply delay, if one was found), so every feature is passed through the same lag and delay and
the residual is linear in the coefficients: a sparse linear regression is exact here.

A term can also sit at the cooler core's outlet (location ``cooler_out``: the air leaving the core,
before the split between heater path and bypass), where it changes the air entering the heater too.
There the reading sees a feature through the heater's air node and body and the mixing, so each
feature's view is its response through the model itself: the fit's free run with a small probe term
``c f`` at the core outlet, minus the run without it, over ``c`` (the model is linear in the core outlet
but for the PTC curve, so this is the regression's exact column up to that curvature; the whole-model
refit afterwards takes the rest). A term can also sit in the heater body's energy balance (location
``heater_body``, a heat flow in W: a conductance to the surroundings, a share of the electric power), seen the
same way. Discovery runs the selection at every place and keeps the place whose best term lowers the held-out
error most.

Selection (docs/identification.md, "discovery"): the order in which features enter comes from
the LARS-lasso path of scikit-learn (``sklearn.linear_model.lars_path``, standardised features,
training rows); the number of features from the held-out rows: a feature is kept only if it
lowers the held-out error of the supply temperature by ``MIN_STEP_GAIN`` or more (at most
``MAX_FEATURES``). Why scikit-learn and not PySINDy: the library here is a fixed set of
physical features of one equation and the target is a residual, not a derivative; PySINDy would
add a differentiation and an ODE fit layer that do nothing for this, while ``lars_path`` gives the
whole sparsity path in one deterministic call (no threshold or penalty to tune). The extra is
``discovery`` (scikit-learn), imported only when a discovery runs.
"""

from __future__ import annotations

import numpy as np

from hvac_mpc.models.discovered import FEATURES, LOCATIONS, DiscoveredTerm

from .fitting import Fit, Fitter
from .simulator import shift

#: Share of the held-out supply error (sum of squares) each kept feature must remove.
MIN_STEP_GAIN = 0.05
#: Features the selection may use (the whole vocabulary but the constant, which is always in).
CANDIDATES = ("mix", "inlet", "inv_mass_flow", "mix_over_mass_flow", "inlet_minus_mix_over_mass_flow", "core_share",
              "core_share_x_blower_out", "core_share_x_water", "mass_flow", "mix_x_mass_flow",
              "heater_power_over_mass_flow", "body_minus_mix")
#: Features offered only when the log carries the cabin temperature (without it they are a combination of
#: ``inv_mass_flow`` and ``mix_over_mass_flow`` at the assumed ``Parameters.cabin_temp_c``).
CABIN_CANDIDATES = ("cabin_minus_mix_over_mass_flow",)
#: Features the selection may use at the cooler outlet (the constant is always in). Not ``water`` nor
#: ``core_in_minus_water``: with the cooler's effectiveness free, a step of it is the direction T_w - T_core_in,
#: so they add nothing to the span; offered anyway, the selection hands part of the correction to that step,
#: which the whole-model refit does not follow (cooler_literal seed 17: 0.215 C with ``water``, 0.061 without).
COOLER_CANDIDATES = ("core_in", "mass_flow", "core_in_minus_water_x_mass_flow", "core_in_minus_water_x_core_flow")
#: Features the selection may use in the heater body's balance (the constant is always in): a conductance to the
#: surroundings at the inlet air's temperature, a share of the electric power.
HEATER_CANDIDATES = ("body_minus_inlet", "heater_power")
#: Features the selection may use on the air entering the box (the constant, an inlet sensor's offset, is always in);
#: the cabin's share only when the log carries the cabin temperature (cabin air drawn in behind the inlet sensor).
BOX_IN_CANDIDATES = ("inlet",)
#: Features per location where a term is seen through the model's own response (:func:`probe_view`).
PROBED = {"cooler_out": COOLER_CANDIDATES, "heater_body": HEATER_CANDIDATES, "box_in": BOX_IN_CANDIDATES}
#: Probe coefficient per feature unit for those views: about 0.2 C at the core outlet, a few W into the heater body.
PROBE = {"1": 0.2, "C": 0.01, "kg/s": 4.0, "C kg/s": 0.2}
PROBE_BODY = {"1": 2.0, "C": 0.05, "W": 0.02}
#: Most features in one term.
MAX_FEATURES = 4
#: Prefixes of the LARS path scored on the held-out rows (a term holds at most this many features).
MAX_PATH = MAX_FEATURES


def _lars_path(x: np.ndarray, y: np.ndarray):
    try:
        from sklearn.linear_model import lars_path
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise ImportError("term discovery needs scikit-learn: pip install 'hvac-mpc[discovery]'") from exc
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    with warnings.catch_warnings():  # collinear features (core inlet and water temperature) drop out of the path
        warnings.simplefilter("ignore", ConvergenceWarning)
        return lars_path(x, y, method="lasso", max_iter=4 * MAX_FEATURES)


def features(fitter: Fitter, fit: Fit) -> dict[str, np.ndarray]:
    """Every vocabulary feature along the fit's free run (n,), before the sensor."""
    sim = fitter.simulator(fit.effects, fit.terms)
    internals = sim.internals(fit.p, fit.states)
    log = fitter.log
    water = log.water_temp_c if log.water_temp_c is not None else fit.states[:, sim.model.states.index("water_temp_c")]
    q = {"t_mix": internals["mix_temp_c"], "t_body": internals["heater_temp_c"], "t_in": log.inlet_temp_c, "t_blower": internals["blower_out_temp_c"],
         "t_water": water, "mass_flow": internals["mass_flow_kgs"], "core_share": 1.0 - internals["bypass_fraction"],
         "p_el": internals["heater_electric_w"],
         "t_cabin": log.cabin_temp_c if log.cabin_temp_c is not None else fit.p[fitter.names.index("cabin_temp_c")]}
    return {name: np.asarray(spec[2](q), float) * np.ones(log.n) for name, spec in FEATURES.items()}


def _lfilter_lag(values: np.ndarray, tau_s: float, dt_s: float) -> np.ndarray:
    from scipy.signal import lfilter
    a = np.exp(-dt_s / tau_s)
    y = lfilter([0.0, 1.0 - a], [1.0, -a], values - values[0]) + values[0]
    return y


def sensor_view(fitter: Fitter, fit: Fit, feats: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each feature as the supply reading would show it (lag and delay of ``fit``)."""
    tau = float(fit.p[fitter.names.index("tau_tc_s")])
    delay = fit.post.delays.get("supply_temp_c", 0)
    return {k: shift(_lfilter_lag(v, tau, fitter.log.dt_s), delay) for k, v in feats.items()}


def _probe_responses(fitter: Fitter, fit: Fit, location: str, names, rows: int | None = None) -> np.ndarray:
    """The model's free-run response on every logged output per unit coefficient of each feature in ``names`` at
    ``location`` (a key of :data:`PROBED`), before the output corrections (n, outputs, len(names); ``rows``: of the
    first rows only, NaN after)."""
    probes = PROBE_BODY if location == "heater_body" else PROBE
    y0 = fitter.simulator(fit.effects, fit.terms).simulate(fit.p, rows)[0]
    out = np.zeros(y0.shape + (len(names),))
    for k, f in enumerate(names):
        c = probes[FEATURES[f][1]]
        probe = DiscoveredTerm("probe_" + f, location, (f,), (c,))
        out[:, :, k] = (fitter.simulator(fit.effects, fit.terms + (probe,)).simulate(fit.p, rows)[0] - y0) / c
    return out


def probe_view(fitter: Fitter, fit: Fit, location: str, names=None, rows: int | None = None) -> dict[str, np.ndarray]:
    """Each feature of ``location`` (a key of :data:`PROBED`) as the supply reading shows it: the model's response
    per unit coefficient (n,; ``rows``: the first rows only, NaN after)."""
    names = _candidates(fitter, location) + ("one",) if names is None else names
    j = fitter.outputs.index("supply_temp_c")
    resp = _probe_responses(fitter, fit, location, names, rows)
    return {f: shift(resp[:, j, k], fit.post.delays.get("supply_temp_c", 0)) for k, f in enumerate(names)}


def term_columns(fitter: Fitter, fit: Fit, term: DiscoveredTerm) -> np.ndarray:
    """The Jacobian of every logged output of ``fit`` (its output corrections applied) in ``term``'s coefficients
    (n, outputs, features): exact, the outputs are linear in them (but for the PTC curve's bend). A term after the
    mixing point changes the supply reading only; one at the other places the heater outlet too."""
    if term.location in PROBED:
        resp = _probe_responses(fitter, fit, term.location, term.features)
        return fit.post.apply(np.zeros(resp.shape[:2]), resp)[1]
    view = sensor_view(fitter, fit, features(fitter, fit))
    cols = np.zeros((fitter.log.n, len(fitter.outputs), len(term.features)))
    for k, f in enumerate(term.features):
        cols[:, fitter.outputs.index("supply_temp_c"), k] = view[f]
    return cols


def views(fitter: Fitter, fit: Fit, location: str, names=None, rows: int | None = None) -> dict[str, np.ndarray]:
    """The features of ``location`` as the supply reading shows them (linear in the coefficients; ``rows``: a place
    seen through the model's response is run over the first rows only, NaN after)."""
    if location in PROBED:
        return probe_view(fitter, fit, location, None if names is None else tuple(names), rows)
    return sensor_view(fitter, fit, features(fitter, fit))


def _candidates(fitter: Fitter, location: str) -> tuple[str, ...]:
    if location == "box_in" and fitter.log.cabin_temp_c is not None:
        return BOX_IN_CANDIDATES + ("cabin_minus_inlet",)
    if location in PROBED:
        return PROBED[location]
    return CANDIDATES + (CABIN_CANDIDATES if fitter.log.cabin_temp_c is not None else ())


def select(fitter: Fitter, fit: Fit, dy_free: np.ndarray | None = None, location: str = "supply_air"
           ) -> tuple[list[str], np.ndarray, dict]:
    """Sparse choice of features for the supply residual of ``fit``: names, coefficients, the record.

    ``dy_free`` (n x k): the supply reading's sensitivities to the model's free parameters. They
    are always in the regression (unpenalised, projected out before the LARS path), so the term is
    chosen with the nominal parameters refit together with it, not on a residual they have bent.
    """
    j = fitter.outputs.index("supply_temp_c")
    resid = fitter.y_meas[:, j] - fit.y[:, j]
    view = views(fitter, fit, location)
    allowed = _candidates(fitter, location)
    names = [k for k in view if k in allowed]
    x_all = np.column_stack([view[k] for k in names])
    base = np.column_stack([view["one"]] + ([dy_free] if dy_free is not None and dy_free.size else []))
    ok = np.isfinite(resid) & np.all(np.isfinite(x_all), axis=1) & np.all(np.isfinite(base), axis=1)
    tr, ho = ok & fitter.log.train, ok & fitter.log.holdout
    q, _ = np.linalg.qr(base[tr])
    x_tr = x_all[tr] - q @ (q.T @ x_all[tr])
    r_tr = resid[tr] - q @ (q.T @ resid[tr])
    sd = x_tr.std(axis=0)
    usable = sd > 1e-9 * np.maximum(np.abs(x_all[tr]).max(axis=0), 1e-300)
    _, _, coefs = _lars_path(x_tr[:, usable] / sd[usable], r_tr)
    nonzero = np.abs(coefs) > 0
    entered = [int(np.argmax(row)) if row.any() else None for row in nonzero]  # path step where each enters
    idx = sorted((k for k, e in enumerate(entered) if e is not None), key=lambda k: entered[k])
    order = [names[i] for i in np.flatnonzero(usable)[idx]]
    record = {"location": location, "path_order": order, "steps": []}
    c0, *_ = np.linalg.lstsq(base[tr], resid[tr], rcond=None)
    sse_start = float(np.sum((resid[ho] - base[ho] @ c0) ** 2))
    record["holdout_sse_start"] = sse_start
    fits = []
    for k in range(1, min(len(order), MAX_PATH) + 1):  # every prefix of the path, scored on the held-out rows
        a = np.column_stack([view[f] for f in order[:k]] + [base])
        c, *_ = np.linalg.lstsq(a[tr], resid[tr], rcond=None)
        sse = float(np.sum((resid[ho] - a[ho] @ c) ** 2))
        fits.append((order[:k], c[:k + 1], sse))
        record["steps"].append({"features": order[:k], "holdout_sse": sse})
    chosen: list[str] = []
    coef = np.zeros(0)
    record["holdout_sse_best"] = min((sse for _, _, sse in fits), default=sse_start)
    if fits:
        best = min(sse for _, _, sse in fits)
        if best <= (1.0 - MIN_STEP_GAIN) * sse_start:
            # the smallest prefix within MIN_STEP_GAIN of the best improvement
            limit = best + MIN_STEP_GAIN * (sse_start - best)
            chosen, coef, _ = next(f for f in fits if f[2] <= limit)
    return chosen, coef, record


def describe_term(chosen: list[str], coef: np.ndarray, location: str = "supply_air") -> str:
    """The term in words (and physically, when it has the form of a heat loss to surroundings)."""
    words = " plus ".join(FEATURES[f][0] for f in chosen)
    if location == "heater_body":
        return _describe_body(chosen, coef, words)
    if location == "box_in":
        return _describe_box_in(chosen, coef, words)
    if location == "cooler_out":
        text = f"an additive term on the {LOCATIONS[location][0]}, linear in {words} and a constant"
        c = dict(zip(chosen, coef))
        if "core_in" in c:
            text += (f"; the core outlet follows the air entering the core with {c['core_in']:+.3f} C/C more than "
                     "the effectiveness form (a slope near -(1 - effectiveness) means an outlet that does not "
                     "depend on the inlet air)")
        return text
    text = f"an additive term in the supply-air energy balance, linear in {words} and a constant"
    c = dict(zip(chosen, coef))
    if set(chosen) >= {"mix_over_mass_flow", "inv_mass_flow"} and c["mix_over_mass_flow"] < 0:
        ua = -c["mix_over_mass_flow"] * 1007.0
        t_env = c["inv_mass_flow"] / -c["mix_over_mass_flow"]
        text += (f"; it has the form of a heat loss from the duct to surroundings at about {t_env:.1f} C with a "
                 f"conductance UA of about {ua:.2f} W/K (dT = UA/(m_dot c_p) (T_env - T_mix))")
    if c.get("cabin_minus_mix_over_mass_flow", 0.0) > 0:
        ua = c["cabin_minus_mix_over_mass_flow"] * 1007.0
        text += (f"; it has the form of heat exchange between the duct and the cabin with a conductance UA of "
                 f"about {ua:.2f} W/K (dT = UA/(m_dot c_p) (T_cabin - T_mix), T_cabin the logged cabin temperature)")
    if set(chosen) & {"core_share", "core_share_x_blower_out", "core_share_x_water"}:
        text += "; it acts on the air through the cooler core (an error of the core outlet temperature)"
    if "body_minus_mix" in c:
        text += (f"; the supply reading follows the heater body by {c['body_minus_mix']:+.3f} C/C of its excess over the "
                 "mixed air (the sensor seeing the heater body, by radiation or conduction)")
    return text


def _describe_box_in(chosen: list[str], coef: np.ndarray, words: str) -> str:
    text = (f"an additive term on the air entering the box (the logged inlet temperature is the air outside it), "
            f"linear in {words} and a constant")
    share = dict(zip(chosen, coef)).get("cabin_minus_inlet", 0.0)
    if 0.0 < share < 1.0:
        text += (f"; it has the form of a share of about {share:.2f} of cabin air drawn into the box behind the inlet "
                 "sensor (recirculation, a leak)")
    return text


def _describe_body(chosen: list[str], coef: np.ndarray, words: str) -> str:
    text = f"an additive heat flow into the heater body, linear in {words} and a constant"
    c = dict(zip(chosen, coef))
    if c.get("body_minus_inlet", 0.0) < 0:
        text += (f"; it has the form of a heat loss of the body to surroundings at the inlet air's temperature with a "
                 f"conductance of about {-c['body_minus_inlet']:.2f} W/K")
    if "heater_power" in c:
        text += f"; {c['heater_power']:+.3f} of the electric power goes into the body beyond k_p's share"
    return text


#: Name of the discovered term per location.
TERM_NAMES = {"supply_air": "supply_residual_term", "cooler_out": "cooler_outlet_term", "heater_body": "heater_body_term",
              "box_in": "box_inlet_term"}


def term_from(chosen: list[str], coef: np.ndarray, name: str | None = None, location: str = "supply_air"
              ) -> DiscoveredTerm:
    """The discovered term (the regression's constant included as feature ``one``)."""
    feats = tuple(chosen) + ("one",)
    return DiscoveredTerm(name or TERM_NAMES[location], location, feats, tuple(float(c) for c in coef),
                          describe_term(chosen, coef[:-1], location))


def refit_coefficients(fitter: Fitter, fit: Fit, term: DiscoveredTerm) -> DiscoveredTerm:
    """Least-squares update of the term's coefficients on the training rows of ``fit`` (which holds the
    term): the residual is linear in them, so one solve is the exact optimum for fixed parameters."""
    j = fitter.outputs.index("supply_temp_c")
    resid = fitter.y_meas[:, j] - fit.y[:, j]
    view = views(fitter, fit, term.location, term.features, fitter.train_rows)  # the training rows are used alone
    a = np.column_stack([view[k] for k in term.features])
    ok = np.isfinite(resid) & fitter.log.train & np.all(np.isfinite(a), axis=1)
    dc, *_ = np.linalg.lstsq(a[ok], resid[ok], rcond=None)
    return DiscoveredTerm(term.name, term.location, term.features,
                          tuple(float(c + d) for c, d in zip(term.coefficients, dc)),
                          describe_term(list(term.features[:-1]), np.array(term.coefficients) + dc, term.location))
