"""Discovered terms: additive terms found in data, written to the model file, built into the model.

A term is a named linear combination ``sum_i c_i f_i`` of features from :data:`FEATURES` (each a
physically meaningful function of quantities the model already computes), added to one balance
(:data:`LOCATIONS`). ``supply_air``: added to the mixed supply air temperature after mixing, i.e. an
extra heat flow in the supply-air energy balance divided by the air's capacity flow
(docs/model.md, "discovered terms"). ``cooler_out``: added to the air leaving the cooler core, before
the split between the heater path and the bypass, so it also changes the air entering the heater
(docs/identification.md, "A term at the cooler core's outlet"); its features are the ones known there
(:data:`COOLER_OUT_FEATURES`). The same feature functions serve numpy (identification) and CasADi
(the model), so the term the identification fits is the term the controller predicts with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping

#: Where a term can be added: name -> (what it changes, unit of the term).
LOCATIONS = {"supply_air": ("mixed supply air temperature after mixing (supply-air energy balance)", "C"),
             "cooler_out": ("air temperature leaving the cooler core, before the split between heater path and "
                            "bypass (cooler energy balance)", "C"),
             "heater_body": ("heat flow into the heater body (heater energy balance)", "W"),
             "box_in": ("air temperature entering the box, before the blower, the bypass and the cooler core (the "
                        "logged inlet temperature is the air outside it)", "C")}


def _f(description: str, unit: str, fn: Callable[[Mapping[str, Any]], Any]) -> tuple[str, str, Callable]:
    return description, unit, fn


#: Feature vocabulary: name -> (words, unit, function of the quantities ``q``). ``q`` keys:
#: t_mix (C, not at ``cooler_out``), t_in (C, inlet), t_blower (C, after the motor), t_water (C), mass_flow (kg/s),
#: core_share (1 - bypass fraction), p_el (W, heater electric power), t_cabin (C, cabin air: the logged
#: cabin temperature in identification, ``Parameters.cabin_temp_c`` in the model), t_body (C, heater body).
FEATURES: dict[str, tuple[str, str, Callable]] = {
    "one": _f("a constant", "1", lambda q: 1.0 + 0.0 * q["t_in"]),
    "inv_mass_flow": _f("one over the mass flow", "s/kg", lambda q: 1.0 / q["mass_flow"]),
    "mix_over_mass_flow": _f("mixed air temperature over the mass flow", "C s/kg",
                             lambda q: q["t_mix"] / q["mass_flow"]),
    "inlet_minus_mix_over_mass_flow": _f("inlet minus mixed air temperature over the mass flow", "C s/kg",
                                         lambda q: (q["t_in"] - q["t_mix"]) / q["mass_flow"]),
    "core_share": _f("share of the air through the core", "1", lambda q: q["core_share"]),
    "core_share_x_blower_out": _f("core share times the air temperature entering the core", "C",
                                  lambda q: q["core_share"] * q["t_blower"]),
    "core_share_x_water": _f("core share times the water temperature", "C",
                             lambda q: q["core_share"] * q["t_water"]),
    "mix": _f("mixed air temperature", "C", lambda q: q["t_mix"]),
    "inlet": _f("inlet air temperature", "C", lambda q: q["t_in"]),
    "mass_flow": _f("mass flow", "kg/s", lambda q: q["mass_flow"]),
    "mix_x_mass_flow": _f("mixed air temperature times the mass flow", "C kg/s",
                          lambda q: q["t_mix"] * q["mass_flow"]),
    "heater_power_over_mass_flow": _f("heater electric power over the mass flow", "W s/kg",
                                      lambda q: q["p_el"] / q["mass_flow"]),
    "cabin_minus_mix_over_mass_flow": _f("cabin minus mixed air temperature over the mass flow", "C s/kg",
                                         lambda q: (q["t_cabin"] - q["t_mix"]) / q["mass_flow"]),
    "core_in": _f("air temperature entering the cooler core (inlet plus motor rise)", "C", lambda q: q["t_blower"]),
    "water": _f("water temperature", "C", lambda q: q["t_water"]),
    "core_in_minus_water": _f("core inlet air minus water temperature", "C",
                              lambda q: q["t_blower"] - q["t_water"]),
    "core_in_minus_water_x_mass_flow": _f("core inlet air minus water temperature times the mass flow", "C kg/s",
                                          lambda q: (q["t_blower"] - q["t_water"]) * q["mass_flow"]),
    "core_in_minus_water_x_core_flow": _f("core inlet air minus water temperature times the mass flow through the core",
                                          "C kg/s", lambda q: (q["t_blower"] - q["t_water"]) * q["mass_flow"]
                                          * q["core_share"]),
    "body_minus_mix": _f("heater body minus mixed air temperature", "C", lambda q: q["t_body"] - q["t_mix"]),
    "body_minus_inlet": _f("heater body minus inlet air temperature", "C", lambda q: q["t_body"] - q["t_in"]),
    "heater_power": _f("heater electric power", "W", lambda q: q["p_el"]),
    "cabin_minus_inlet": _f("cabin minus inlet air temperature", "C", lambda q: q["t_cabin"] - q["t_in"]),
}

#: Features of an exchange between the supply air and a reservoir over the duct: feature -> the reservoir's
#: temperature in ``q``. Fitted linear in one over the mass flow (the exchange's number of transfer units UA / (m_dot
#: c_p), small over a log's flows), the model evaluates such a term with a positive coefficient c = UA / c_p as the
#: exchanger it is, (T_res - T_mix) (1 - exp(-c / m_dot)) (:func:`exchange_c`).
EXCHANGE_FEATURES = {"cabin_minus_mix_over_mass_flow": "t_cabin", "inlet_minus_mix_over_mass_flow": "t_in"}

#: Features a ``cooler_out`` term may use: functions of the quantities known before the cooler core's outlet
#: (t_in, t_blower, t_water, mass_flow, core_share).
COOLER_OUT_FEATURES = ("one", "inlet", "core_in", "water", "core_in_minus_water", "mass_flow",
                       "core_in_minus_water_x_mass_flow", "core_in_minus_water_x_core_flow", "core_share")
#: Features a ``heater_body`` term may use: the body, the inlet air and the electric power (t_body, t_in, p_el).
HEATER_BODY_FEATURES = ("one", "body_minus_inlet", "heater_power")
#: Features a ``box_in`` term may use: the logged inlet and the cabin temperature (t_in, t_cabin).
BOX_IN_FEATURES = ("one", "inlet", "cabin_minus_inlet")
#: Locations whose terms are restricted to the quantities known there.
LOCATION_FEATURES = {"cooler_out": COOLER_OUT_FEATURES, "heater_body": HEATER_BODY_FEATURES, "box_in": BOX_IN_FEATURES}


def coefficient_unit(feature: str, location: str = "supply_air") -> str:
    """Unit of a coefficient: the term's unit over the feature's."""
    term_unit = LOCATIONS[location][1]
    f_unit = FEATURES[feature][1]
    return term_unit if f_unit == "1" else f"{term_unit} / ({f_unit})"


@dataclass(frozen=True)
class DiscoveredTerm:
    """``name``: short identifier; ``location``: key of :data:`LOCATIONS`; ``features`` and
    ``coefficients``: the linear combination; ``description``: the term in words."""

    name: str
    location: str
    features: tuple[str, ...]
    coefficients: tuple[float, ...]
    description: str = ""

    def __post_init__(self) -> None:
        if self.location not in LOCATIONS:
            raise ValueError(f"discovered term {self.name!r}: location {self.location!r} unknown; "
                             f"allowed: {list(LOCATIONS)}")
        unknown = [f for f in self.features if f not in FEATURES]
        if unknown:
            raise ValueError(f"discovered term {self.name!r}: feature(s) {unknown} unknown; allowed: {list(FEATURES)}")
        allowed = LOCATION_FEATURES.get(self.location, tuple(FEATURES))
        misplaced = [f for f in self.features if f not in allowed]
        if misplaced:
            raise ValueError(f"discovered term {self.name!r}: feature(s) {misplaced} not known at the "
                             f"{self.location.replace('_out', ' outlet').replace('_', ' ')}; "
                             f"allowed there: {list(allowed)}")
        if len(self.features) != len(self.coefficients):
            raise ValueError(f"discovered term {self.name!r}: {len(self.features)} features but "
                             f"{len(self.coefficients)} coefficients")
        if not all(isinstance(c, (int, float)) and math.isfinite(c) for c in self.coefficients):
            raise ValueError(f"discovered term {self.name!r}: coefficients must be finite numbers")

    def value(self, q: Mapping[str, Any]) -> Any:
        """The term for quantities ``q`` (numpy or CasADi)."""
        total = 0.0
        for f, c in zip(self.features, self.coefficients):
            if f in EXCHANGE_FEATURES and c > 0.0:
                total = total + exchange_c(c, q[EXCHANGE_FEATURES[f]] - q["t_mix"], q["mass_flow"])
            else:
                total = total + c * FEATURES[f][2](q)
        return total

    def formula(self) -> str:
        """The term as a formula with its coefficients and units."""
        parts = [f"{c:+.4g} [{coefficient_unit(f, self.location)}] * {f}" for f, c in zip(self.features,
                                                                                       self.coefficients)]
        return f"dT_{self.location} = " + " ".join(parts)

    def as_dict(self) -> dict:
        return {"name": self.name, "location": self.location, "features": list(self.features),
                "coefficients": [float(c) for c in self.coefficients], "description": self.description,
                "units": [coefficient_unit(f, self.location) for f in self.features]}


def terms_at(terms, location: str, q: Mapping[str, Any]) -> Any:
    """Sum of the terms added at ``location``."""
    total = 0.0
    for t in terms:
        if t.location == location:
            total = total + t.value(q)
    return total


def exchange_c(ua_over_cp_kgs: float, difference_c: Any, mass_flow_kgs: Any) -> Any:
    """Temperature change (degC) of air at ``mass_flow_kgs`` exchanging heat over the duct with a reservoir
    ``difference_c`` warmer than it, through a conductance UA = ``ua_over_cp_kgs`` c_p: plug flow past a wall at the
    reservoir's temperature, difference (1 - exp(-UA / (m_dot c_p))) (numpy or CasADi). Its first order in
    UA / (m_dot c_p) is the linear feature the term was fitted with (``difference / m_dot``, :data:`EXCHANGE_FEATURES`),
    the same within half the number of transfer units over a log's flows; below them the linear form grows without
    bound as the flow falls, past the reservoir's temperature (second law), where the exchange tends to the
    difference (docs/identification.md, "The literal cooler and the duct exchange at low flow").
    ASSUMPTION: the duct wall stores no heat and the reservoir's temperature holds along the duct."""
    import casadi as ca
    ntu = ua_over_cp_kgs / mass_flow_kgs
    if isinstance(ntu, (ca.SX, ca.MX, ca.DM)):
        return difference_c * (1.0 - ca.exp(-ntu))
    import numpy as np
    return difference_c * -np.expm1(-ntu)


def core_outlet_bounded_c(t_out_c: Any, t_air_in_c: Any, t_water_c: Any) -> Any:
    """The cooler core's outlet air with a discovered term, held between the air entering the core and the water
    (degC; CasADi or numpy). A core is a passive heat exchanger: its outlet air cannot leave the range of its two
    inlet streams (second law). A term fitted on a log holds inside that range where the log lies; extrapolated
    (a linear term in the air temperature, far outside the log's inlet temperatures) it can leave it, and the model
    would then heat or cool the air beyond both streams (docs/identification.md, "A term at the cooler core's
    outlet")."""
    import casadi as ca
    if isinstance(t_out_c, (ca.SX, ca.MX, ca.DM)):
        return ca.fmin(ca.fmax(t_out_c, ca.fmin(t_air_in_c, t_water_c)), ca.fmax(t_air_in_c, t_water_c))
    import numpy as np
    return np.clip(t_out_c, np.minimum(t_air_in_c, t_water_c), np.maximum(t_air_in_c, t_water_c))
