"""The benchmark plant is not the controllers' model: a seeded perturbation of a few physical parameters.

The controllers get the nominal :class:`Parameters`; the simulated plant gets these values.
Each parameter in :data:`PERTURBED` is multiplied by ``1 + s m`` with a random sign ``s`` and a
magnitude ``m`` drawn uniformly from [5 %, 10 %] (the spread of a fitted physical constant between
two boxes of one type; ASSUMPTION). The draw depends only on the seed and the fixed order below.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hvac_mpc.models.parameters import Parameters

#: Parameters that differ between plant and model, with why each matters.
PERTURBED = {
    "heater_ka_w_per_k": "heater heat transfer kA_h (thesis sec. 4.4): heater outlet temperature and lag",
    "flow_per_watt_m3s_per_w": "blower flow per watt (docs/model.md blower curve): volume-flow gain",
    "cooler_slope": "cooler core effectiveness (thesis sec. 4.2 fit): cooling capacity",
    "tau_tc_s": "thermocouple time constant tau_TC (thesis sec. 5.4.1): measured temperature lag",
    "bypass_exponent": "bypass curve b(a) exponent (docs/model.md bypass curve): valve-a gain",
}
#: Range of the relative change, fraction (ASSUMPTION, see module docstring).
MAGNITUDE_RANGE = (0.05, 0.10)


@dataclass(frozen=True)
class Perturbation:
    """A perturbed parameter: nominal value (the controllers'), plant value and relative change."""

    name: str
    nominal: float
    plant: float
    relative: float
    meaning: str


def perturb_parameters(params: Parameters | None = None, seed: int = 0,
                       magnitude: tuple[float, float] = MAGNITUDE_RANGE) -> tuple[Parameters, list[Perturbation]]:
    """Plant parameters drawn from ``seed`` (see module docstring) and the list of changes made."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
    lo, hi = magnitude
    if not 0.0 <= lo <= hi < 1.0:
        raise ValueError(f"magnitude: expected 0 <= low <= high < 1, got {magnitude!r}")
    params = params or Parameters()
    rng = np.random.default_rng([int(seed), 0x9E37])
    changes: dict[str, float] = {}
    record = []
    for name, meaning in PERTURBED.items():
        m = float(rng.uniform(lo, hi))
        s = 1.0 if rng.random() < 0.5 else -1.0
        nominal = float(getattr(params, name))
        value = nominal * (1.0 + s * m)
        changes[name] = value
        record.append(Perturbation(name, nominal, value, s * m, meaning))
    return params.replace(**changes), record
