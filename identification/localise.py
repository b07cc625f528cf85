"""Locating a residual that no library effect explains: which output, which equation, which signals.

For one output, the free-run residual of the training rows is regressed (forward selection, at
most two terms, with an intercept) on a small feature library:

- the "drive" of each model equation feeding that output (e.g. for the supply temperature:
  the cooling done by the core path, the heat added by the heater, the motor heating, the
  thermocouple's rate of change);
- each logged signal and model quantity alone (a missing input dependence as an offset);
- each drive multiplied by a standardised signal (the equation's effect depends on a signal
  the equation does not use).

The selected terms name the equation and the signals; the held-out rows check them (R^2 of the
training coefficients on the held-out residual). This reports where the model is wrong; it
does not claim a physical effect.
"""

from __future__ import annotations

import numpy as np

from .diagnostics import regressors
from .fitting import Fit, Fitter

#: Equation drives per output: label -> regressor name (a function of the free run).
EQUATIONS = {
    "supply_temp_c": {
        "cooler core, sensible cooling of the core path (models/chiller.py cooler_outlet_c)": "cooler_drive_c",
        "PTC heater, heat added on the core path (models/heater.py)": "heater_rise_c",
        "blower motor heating (models/blower.py motor_rise_rate_c_per_s)": "motor_rise_c",
        "bypass split and mixing at valve a (models/bypass.py)": "mix_drive_c",
        "supply thermocouple dynamics (models/sensors.py lag_rate)": "d_supply_temp_c",
    },
    "volume_flow_m3s": {
        "blower flow and valve network (models/blower.py open_flow_m3s, models/valves.py)": "flow_model_m3s",
    },
    "heater_outlet_temp_c": {
        "PTC heater air node and body (models/heater.py)": "heater_gain_c",
        "cooler core (models/chiller.py cooler_outlet_c)": "core_cooling_c",
    },
    "heater_power_w": {
        "PTC heater electric power (models/heater.py electric_power_w)": "heater_electric_w",
    },
}
#: Signals never used as modulating signals (the outputs' own derivatives, markers).
_SKIP = {"blower_step_sign", "trap_release"}


def _features(fitter: Fitter, fit: Fit, output: str) -> tuple[dict[str, np.ndarray], dict[str, tuple[str, str]]]:
    reg = regressors(fitter, fit)
    j = fitter.outputs.index(output)
    reg["mix_drive_c"] = reg["bypass_fraction"] * (reg["blower_out_temp_c"] - reg["heater_out_temp_c"])
    reg["flow_model_m3s"] = fit.y[:, fitter.outputs.index("volume_flow_m3s")]
    reg["heater_gain_c"] = reg["heater_out_temp_c"] - reg["cooler_out_temp_c"]
    reg["core_cooling_c"] = reg["blower_out_temp_c"] - reg["cooler_out_temp_c"]
    reg[f"d_{output}"] = np.gradient(fit.y[:, j]) / fitter.log.dt_s
    drives = {lbl: reg[name] for lbl, name in EQUATIONS.get(output, {}).items()}
    signals = {k: v for k, v in reg.items()
               if not k.startswith("d_") and k not in _SKIP and k not in drives and np.nanstd(v) > 0}
    feats: dict[str, np.ndarray] = {}
    meaning: dict[str, tuple[str, str]] = {}
    for lbl, g in drives.items():
        feats[f"[{lbl}]"] = g
        meaning[f"[{lbl}]"] = (lbl, "")
    for name, z in signals.items():
        zs = (z - np.mean(z)) / np.std(z)
        feats[name] = zs
        meaning[name] = ("", name)
        for lbl, g in drives.items():
            feats[f"[{lbl}] x {name}"] = g * zs
            meaning[f"[{lbl}] x {name}"] = (lbl, name)
    return feats, meaning


def _r2(e: np.ndarray, x: np.ndarray, coef: np.ndarray) -> float:
    pred = x @ coef
    den = np.sum((e - np.mean(e)) ** 2)
    return float(1.0 - np.sum((e - pred) ** 2) / den) if den > 0 else 0.0


def locate(fitter: Fitter, fit: Fit, output: str, max_terms: int = 2) -> dict:
    """Forward-select up to ``max_terms`` features for the residual of ``output``; see module doc."""
    j = fitter.outputs.index(output)
    e_all = fitter.y_meas[:, j] - fit.y[:, j]
    feats, meaning = _features(fitter, fit, output)
    names = list(feats)
    x_all = np.column_stack([feats[n] for n in names])
    tr = fitter.log.train & np.isfinite(e_all)
    ho = fitter.log.holdout & np.isfinite(e_all)
    e_tr, x_tr = e_all[tr], x_all[tr]
    chosen: list[int] = []
    steps = []
    for _ in range(max_terms):
        best, best_sse = None, None
        for k in range(len(names)):
            if k in chosen or np.std(x_tr[:, k]) == 0:
                continue
            cols = np.column_stack([np.ones(len(e_tr)), x_tr[:, chosen + [k]]])
            coef, *_ = np.linalg.lstsq(cols, e_tr, rcond=None)
            sse = float(np.sum((e_tr - cols @ coef) ** 2))
            if best_sse is None or sse < best_sse:
                best, best_sse = k, sse
        if best is None:
            break
        chosen.append(best)
        cols_tr = np.column_stack([np.ones(len(e_tr)), x_tr[:, chosen]])
        coef, *_ = np.linalg.lstsq(cols_tr, e_tr, rcond=None)
        cols_ho = np.column_stack([np.ones(ho.sum()), x_all[ho][:, chosen]])
        steps.append({"terms": [names[c] for c in chosen], "r2_train": _r2(e_tr, cols_tr, coef),
                      "r2_holdout": _r2(e_all[ho], cols_ho, coef)})
    # single-term ranking: the best term of each equation and of each signal
    single = []
    for k, name in enumerate(names):
        if np.std(x_tr[:, k]) == 0:
            continue
        cols = np.column_stack([np.ones(len(e_tr)), x_tr[:, k]])
        coef, *_ = np.linalg.lstsq(cols, e_tr, rcond=None)
        cols_ho = np.column_stack([np.ones(ho.sum()), x_all[ho][:, k]])
        single.append((name, _r2(e_tr, cols, coef), _r2(e_all[ho], cols_ho, coef)))
    eq_rank: dict[str, tuple[float, float, str]] = {}
    sig_rank: dict[str, tuple[float, float, str]] = {}
    for name, r2t, r2h in single:
        eq, sig = meaning[name]
        for key, table in ((eq, eq_rank), (sig, sig_rank)):
            if key and (key not in table or r2t > table[key][0]):
                table[key] = (r2t, r2h, name)
    rank = lambda t: [{"name": k, "r2_train": v[0], "r2_holdout": v[1], "term": v[2]}  # noqa: E731
                      for k, v in sorted(t.items(), key=lambda kv: -kv[1][0])]
    # keep the second term only if it adds on the held-out rows
    final = steps[0] if steps else {"terms": [], "r2_train": 0.0, "r2_holdout": 0.0}
    if len(steps) > 1 and steps[1]["r2_holdout"] > steps[0]["r2_holdout"] + 0.05:
        final = steps[1]
    eq_list, sig_list = rank(eq_rank), rank(sig_rank)
    # the equation and signals the residual points to: the best-ranked ones that hold on the held-out rows
    equations = [e["name"] for e in eq_list[:1] if e["r2_holdout"] > 0.1]
    signals = [s_["name"] for s_ in sig_list[:2] if s_["r2_holdout"] > 0.1]
    confirmed = True
    if not equations and not signals and (eq_list or sig_list):
        # nothing holds on the held-out rows: name what the training rows show, marked unconfirmed
        equations = [e["name"] for e in eq_list[:1] if e["r2_train"] > 0.3]
        signals = [s_["name"] for s_ in sig_list[:2] if s_["r2_train"] > 0.3]
        confirmed = False
    return {"output": output, "terms": final["terms"], "r2_train": final["r2_train"],
            "r2_holdout": final["r2_holdout"], "equations": equations, "signals": signals, "confirmed": confirmed,
            "equation_ranking": eq_list[:4], "signal_ranking": sig_list[:5], "steps": steps}


def describe(loc: dict) -> str:
    """One sentence for the report."""
    eq = "; ".join(loc["equations"]) or "no model equation in particular"
    sig = ", ".join(loc["signals"]) or "no logged signal in particular"
    best_eq = loc["equation_ranking"][0] if loc["equation_ranking"] else None
    best_sig = loc["signal_ranking"][0] if loc["signal_ranking"] else None
    detail = []
    if best_eq:
        detail.append(f"best equation term {best_eq['term']}: R^2 {best_eq['r2_train']:.2f} training, "
                      f"{best_eq['r2_holdout']:.2f} held-out")
    if best_sig:
        detail.append(f"best signal term {best_sig['term']}: R^2 {best_sig['r2_train']:.2f} / "
                      f"{best_sig['r2_holdout']:.2f}")
    tail = "" if loc.get("confirmed", True) else "; seen on the training rows only, not confirmed on the held-out rows"
    return f"the residual of {loc['output']} points to {eq}, and to the signals {sig} ({'; '.join(detail)}{tail})"
