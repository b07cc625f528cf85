"""All numeric parameters of the HVAC box in one place.

Every field names its source: a thesis table, equation or section
(docs/model.md lists them), or ``ASSUMPTION`` where a figure's data is missing
from the text and a stand-in curve is used (docs/model.md sec. 1).
Assumptions can be replaced from a TOML or JSON file without touching code::

    params = Parameters.from_file("my_box.toml")     # keys are field names
    params = Parameters().replace(tau_tc_s=6.1)

Units are in the field names; temperatures in degC, powers in W, flows in m3/s,
resistances in kg/m^7 (Pa per (m3/s)^2), angles in % of servo travel.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

from hvac_mpc.validation import InvalidValue, check_fields, finite_in


def _p(default: float, source: str, lo: float = -math.inf, hi: float = math.inf) -> Any:
    return field(default=default, metadata={"source": source, "range": (lo, hi), "check": finite_in(lo, hi)})


@dataclass(frozen=True)
class Parameters:
    """Physical parameters of the box. ``source`` metadata says where each comes from."""

    # --- air ------------------------------------------------------------------
    rho_slope_kgm3_per_c: float = _p(-0.004395, "thesis sec. 4, rho(T) fit (fig. 16)")
    rho_offset_kgm3: float = _p(1.23, "thesis sec. 4, rho(T) fit (fig. 16)", 0.5, 2.0)
    cp_air_j_per_kgk: float = _p(1007.0, "thesis sec. 4.4 (c_pa at 26.85 C, ref. [3])", 900, 1100)

    # --- blower ---------------------------------------------------------------
    blower_power_min_w: float = _p(30.0, "docs/model.md sec. 2 (actuator range)", 0, 300)
    blower_power_max_w: float = _p(300.0, "thesis sec. 2.1 (15 V x 20 A)", 30, 1000)
    flow_per_watt_m3s_per_w: float = _p(
        1.9e-4, "ASSUMPTION docs/model.md sec. 1 (fig. 20 stand-in; 0.057 m3/s at 300 W, table 6)", 1e-6, 1e-2)
    core_flow_loss: float = _p(
        0.1, "thesis sec. 4.5.1 (fig. 33: ~10 % less flow when all air crosses the core)", 0.0, 0.5)
    motor_gain_max_c: float = _p(
        2.4, "ASSUMPTION docs/model.md sec. 1 (fig. 18 stand-in; thesis sec. 4.1.1: >2 C at full power)", 0, 10)
    motor_gain_exponent: float = _p(1.5, "ASSUMPTION docs/model.md sec. 1 (fig. 18 stand-in)", 0.5, 3)
    tau_motor_s: float = _p(268.0, "thesis sec. 4.1.1 (tau_m)", 1, 5000)

    # --- chiller and cooler core ----------------------------------------------
    water_rate_c_per_s: float = _p(0.00692, "thesis sec. 4.2 (mean slope, fig. 23)", 1e-5, 1)
    water_rise_rate_c_per_s: float = _p(0.00702, "thesis sec. 4.2 (rising slope, fig. 23)", 1e-5, 1)
    water_fall_rate_c_per_s: float = _p(0.00682, "thesis sec. 4.2 (falling slope, fig. 23)", 1e-5, 1)
    chiller_band_c: float = _p(1.0, "ASSUMPTION docs/model.md sec. 1 (two-point band +-1 C)", 0, 10)
    cooler_slope: float = _p(0.7564, "thesis sec. 4.2 eq. T_a = 0.7564 T_w + 6.312", 0, 1)
    cooler_offset_c: float = _p(6.312, "thesis sec. 4.2 eq. T_a = 0.7564 T_w + 6.312", -50, 50)

    # --- PTC heater ------------------------------------------------------------
    heater_power_max_w: float = _p(240.0, "thesis sec. 2.3 (max ~240 W at low temperature)", 0, 1000)
    heater_mass_kg: float = _p(0.243, "thesis sec. 4.4 (m_h = 243 g)", 1e-3, 10)
    heater_c_j_per_kgk: float = _p(897.0, "thesis sec. 4.4 (c_h, aluminium)", 100, 2000)
    heater_air_mass_kg: float = _p(14.21e-6, "thesis sec. 4.4 (m_ah = 14.21 mg)", 1e-8, 1e-2)
    heater_ka_w_per_k: float = _p(2.49, "thesis sec. 4.4 (kA_h = 2.49 W/K)", 0.01, 100)
    heater_kp: float = _p(0.669, "thesis sec. 4.4 eq. (5), table 2", 0.05, 1.0)
    ptc_knee_c: float = _p(60.0, "ASSUMPTION docs/model.md sec. 1 (fig. 12 stand-in: full power below ~60 C)", 0, 300)
    ptc_zero_c: float = _p(165.0, "thesis sec. 2.3 (temperature limited at ~165 C)", 1, 400)
    heater_temp_max_c: float = _p(
        140.0, "ASSUMPTION operating limit below the 165 C PTC self-limit (thesis sec. 2.3)", 20, 200)

    # --- bypass valve a ----------------------------------------------------------
    bypass_max: float = _p(0.9, "thesis sec. 4.5.1 (fig. 36: at least 10 % crosses the core)", 0, 1)
    bypass_exponent: float = _p(1.3, "ASSUMPTION docs/model.md sec. 1 (fig. 36 stand-in)", 0.2, 5)

    # --- valve curve shifts (% of servo travel; 0 in the thesis model, set by identification) ---------
    # ASSUMPTION (sign convention): a positive shift moves the valve's curve to the right, so the valve acts
    # that much less open than commanded: its curve is read at clip(angle - shift, 0, 100) %
    # (models/valves.py effective_angle; docs/model.md sec. 1).
    valve_a_shift_pct: float = _p(
        0.0, "ASSUMPTION valve a's curve (bypass split) moved this many % of travel; positive: acts less open", -50, 50)
    valve_m_shift_pct: float = _p(
        0.0, "ASSUMPTION valve m's curve (table 3) moved this many % of travel; positive: acts less open", -50, 50)
    valve_f_shift_pct: float = _p(
        0.0, "ASSUMPTION valve f's curve (table 4) moved this many % of travel; positive: acts less open", -50, 50)
    valve_w_shift_pct: float = _p(
        0.0, "ASSUMPTION valve w's curve (table 5) moved this many % of travel; positive: acts less open", -50, 50)

    # --- sensors ---------------------------------------------------------------------
    tau_tc_s: float = _p(5.73, "thesis sec. 5.4.1 (thermocouple tau_TC, fig. 44)", 0.1, 500)
    tau_slow_sensor_s: float = _p(100.4, "thesis sec. 2.4 (old sensor tau_s, fig. 14)", 1, 1000)
    flow_sensor_c_m3s: float = _p(0.0097, "thesis sec. 2.4 (pipe constant C)", 1e-4, 1)
    transport_delay_s: float = _p(
        0.0, "ASSUMPTION dead time from the mixing point to the supply sensor; 0 in the thesis model, "
        "set from a parameter file or by identification", 0.0, 10.0)
    cabin_temp_c: float = _p(
        24.0, "ASSUMPTION cabin air around the supply duct, used only by a discovered term on the cabin "
        "temperature (models/discovered.py); identification sets it to the logged cabin temperature's median",
        -30.0, 60.0)

    # --- fan curve (plant effect 'fan_curve') ----------------------------------------
    fan_k_kg_m7: float = _p(
        75900.0, "ASSUMPTION fan curve dp = p0 - k V^2 through tables 3-5 (closed and open rows)", 1, 1e7)

    # --- valve network leakage (plant effect 'valve_leakage') -------------------------
    valve_closed_leak_share: float = _p(
        1.0, "ASSUMPTION closed valves leak equally: tables 3-5 closed rows are the network of 3 leaks",
        0, 1)

    # --- non-ideal effects of the simulated plant (all ASSUMPTIONS, docs/model.md sec. 5) --
    tau_motor_heating_s: float = _p(150.0, "ASSUMPTION thesis sec. 4.1.1 (heating faster than cooling)", 1, 5000)
    tau_motor_cooling_s: float = _p(420.0, "ASSUMPTION thesis sec. 4.1.1 (cooling slower)", 1, 5000)
    bypass_flow_exponent: float = _p(
        0.4, "ASSUMPTION thesis sec. 4.5.1 (split depends on mass flow)", -3, 3)
    bypass_ref_mass_flow_kgs: float = _p(0.04, "ASSUMPTION reference mass flow of fig. 36", 1e-3, 1)
    trap_threshold_pct: float = _p(95.0, "ASSUMPTION thesis sec. 5.4.2 (valve a saturated)", 50, 100)
    trap_air_mass_kg: float = _p(4e-3, "ASSUMPTION thesis sec. 5.4.2 (trapped air pocket, fig. 47)", 0, 0.1)
    tau_trap_heat_s: float = _p(60.0, "ASSUMPTION pocket heats towards heater temperature", 1, 5000)
    tau_trap_release_s: float = _p(3.0, "ASSUMPTION pocket released within seconds", 0.1, 100)
    noise_supply_temp_c: float = _p(0.05, "ASSUMPTION thermocouple noise (1 sigma)", 0, 5)
    noise_flow_m3s: float = _p(4e-4, "ASSUMPTION volume-flow sensor noise (1 sigma)", 0, 0.05)
    noise_inlet_temp_c: float = _p(0.05, "ASSUMPTION inlet temperature noise (1 sigma)", 0, 5)
    cooler_outlet_offset_c: float = _p(
        0.0, "ASSUMPTION none: an offset of the air leaving the cooler core, the estimator's own (docs/robustness.md "
        "sec. 2.13)", -30, 30)
    heater_air_offset_c: float = _p(
        0.0, "ASSUMPTION none: an offset of the air leaving the heater as it mixes and is read (not as the heater body "
        "sees it), the estimator's own (docs/robustness.md sec. 2.13)", -30, 30)
    supply_heat_w: float = _p(
        0.0, "ASSUMPTION none: a heat flow (W) into the mixed air on its way to the thermocouple (a duct's gain from "
        "the cabin, negative for a loss), its effect on the air that over the mass flow times c_p; the estimator's "
        "own (docs/robustness.md sec. 2.22)", -2000, 2000)

    # --- measured tables (thesis tables 3-5): angle %, resistance kg/m^7 -------------
    valve_m_table: tuple = field(default=(
        (0, 231696), (10, 227218), (20, 224775), (30, 218077), (40, 194700), (50, 160605),
        (60, 103448), (70, 65217), (80, 35586), (90, 22585), (100, 16483)),
        metadata={"source": "thesis table 3 (R_m, valves f and w closed)"})
    valve_f_table: tuple = field(default=(
        (0, 230688), (3, 231984), (6, 223602), (9, 220484), (12, 219239), (15, 200104),
        (18, 172562), (21, 154152), (24, 118750), (27, 67331), (30, 56498), (40, 40486),
        (50, 24400), (60, 14800), (70, 15200), (80, 14085), (90, 13694), (100, 11360)),
        metadata={"source": "thesis table 4 (R_f, valves m and w closed)"})
    valve_w_table: tuple = field(default=(
        (0, 215502), (10, 211765), (14, 211765), (18, 203698), (22, 145558), (26, 108555),
        (30, 85771), (40, 56020), (50, 31853), (60, 20345), (70, 15147), (80, 13111),
        (90, 11118), (100, 11489)),
        metadata={"source": "thesis table 5 (R_w, valves m and f closed)"})

    def __post_init__(self) -> None:
        check_fields(self, prefix="parameter ")
        for f in fields(self):
            if f.name.endswith("_table"):
                _check_table(f.name, getattr(self, f.name))
        if self.ptc_zero_c <= self.ptc_knee_c:
            raise InvalidValue(f"parameter ptc_zero_c = {self.ptc_zero_c} must be above ptc_knee_c = {self.ptc_knee_c}")

    # ------------------------------------------------------------------------------
    @classmethod
    def scalar_names(cls) -> tuple[str, ...]:
        """Names of the scalar parameters, the order of the symbolic parameter vector."""
        return tuple(f.name for f in fields(cls) if not f.name.endswith("_table"))

    def vector(self) -> list[float]:
        """Scalar parameters as a list in :meth:`scalar_names` order."""
        return [float(getattr(self, n)) for n in self.scalar_names()]

    @classmethod
    def source(cls, name: str) -> str:
        """Where a parameter comes from (thesis reference or ASSUMPTION)."""
        for f in fields(cls):
            if f.name == name:
                return f.metadata["source"]
        raise KeyError(name)

    @classmethod
    def assumptions(cls) -> tuple[str, ...]:
        """Names of parameters that stand in for missing thesis data."""
        return tuple(f.name for f in fields(cls) if f.metadata["source"].startswith("ASSUMPTION"))

    def replace(self, **changes: Any) -> "Parameters":
        """A copy with some fields changed; unknown names raise a KeyError naming them."""
        known = {f.name for f in fields(self)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise KeyError(f"unknown parameter(s) {unknown}; known: {sorted(known)}")
        changes = {k: (tuple(tuple(r) for r in v) if k.endswith("_table") else v) for k, v in changes.items()}
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: (list(map(list, getattr(self, f.name))) if f.name.endswith("_table")
                         else getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], base: "Parameters | None" = None) -> "Parameters":
        """Parameters from a flat mapping of field names (a ``[parameters]`` table is accepted)."""
        if "parameters" in data and isinstance(data["parameters"], Mapping):
            data = data["parameters"]
        return (base or cls()).replace(**dict(data))

    @classmethod
    def from_file(cls, path: str | Path, base: "Parameters | None" = None) -> "Parameters":
        """Load overrides from a TOML (``.toml``) or JSON (``.json``) file."""
        path = Path(path)
        text = path.read_text()
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
        return cls.from_mapping(data, base)

    def write(self, path: str | Path, only_changed: bool = True) -> None:
        """Write the parameters (by default only those differing from the defaults) as TOML or JSON."""
        path = Path(path)
        default = Parameters()
        data = {k: v for k, v in self.to_dict().items()
                if not only_changed or v != default.to_dict()[k]}
        if path.suffix.lower() == ".json":
            path.write_text(json.dumps({"parameters": data}, indent=2))
            return
        lines = ["[parameters]"]
        for k, v in data.items():
            lines.append(f"{k} = {json.dumps(v)}")
        path.write_text("\n".join(lines) + "\n")


def _check_table(name: str, table: Any) -> None:
    try:
        rows = [(float(a), float(r)) for a, r in table]
    except (TypeError, ValueError) as exc:
        raise InvalidValue(f"parameter {name}: expected rows of (angle_pct, resistance_kg_m7)") from exc
    if len(rows) < 4:
        raise InvalidValue(f"parameter {name}: needs at least 4 rows, got {len(rows)}")
    angles = [a for a, _ in rows]
    if angles != sorted(angles) or len(set(angles)) != len(angles) or angles[0] < 0 or angles[-1] > 100:
        raise InvalidValue(f"parameter {name}: angles must increase strictly within [0, 100] %")
    if any(r <= 0 for _, r in rows):
        raise InvalidValue(f"parameter {name}: resistances must be positive")
