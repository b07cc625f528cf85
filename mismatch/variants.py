"""Plant variants: named differences from the nominal independent box, each a field of :class:`Variant`."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

#: ASSUMPTION: duct-to-cabin conductance of the "duct_loss" variant (W/K). At 0.05 m3/s (~60 W/K of
#: capacity flow) it moves the supply air ~5 % of the way to the cabin temperature, ~20 % at 0.012 m3/s.
DUCT_LOSS_UA_W_PER_K = 3.0
#: ASSUMPTION: a fouled cooler core whose effectiveness falls with the air flow through it ("cooler_fouled"): number
#: of transfer units 1.0 at 0.03 kg/s through the core (effectiveness 0.63 there instead of 0.7564), NTU ~ m^-0.4
#: (air-side film coefficient ~ m^0.6): 0.87 at 0.005 kg/s, 0.53 at 0.06 kg/s.
COOLER_FOULED_NTU = 1.0
#: ASSUMPTION: share of cabin air drawn into the box behind the inlet sensor ("recirculation"; a leaking
#: recirculation flap).
RECIRCULATION_SHARE = 0.15
#: ASSUMPTION: share of the heater body's excess over the supply air the thermocouple reads by radiation
#: ("tc_radiation"; a few %: body 100 C over 30 C air reads 2 C high).
TC_RADIATION_SHARE = 0.03
#: ASSUMPTION: conductance of the heater body to the box walls, which are at the air entering the box
#: ("heater_wall_loss"; about 13 % of the body's 2.3 W/K to the air at 0.03 kg/s).
HEATER_WALL_UA_W_PER_K = 0.3


@dataclass(frozen=True)
class Variant:
    """Differences from the nominal box; every default means "nominal".

    transport_delay_s       dead time (s) from the mixing point to the supply sensor and supply air
                            (rounded to whole sub-steps of the box, 0.25 s at dt_s = 1 s)
    duct_loss_ua_w_per_k    duct-to-cabin heat conductance (W/K); cabin at ``cabin_temp_c`` (degC)
    cooler_literal_fit      cooler outlet = 0.7564 T_w + 6.312 whatever the inlet air (thesis 4.2 as written)
    thermocouple_tau_scale  thermocouple time constant times this (nominal 5.73 s, thesis 5.4.1)
    blower_gain_scale       blower volume flow per watt times this
    valve_shift_pct         every valve curve moved this many % of travel to the right (acts less open)
    heater_power_scale      electric power the heater draws (and its PTC curve) times this
    chiller_rate_scale      chiller water ramps times this (0.5 = twice as slow)
    ptc_power_fall          PTC power falling from 240 W at ~60 C to 0 at 165 C (off: constant 240 W)
    outlet_density_correction  outlet volume flows at the supply air's density instead of the inlet's
    log_shift_samples       logs only: output columns this many samples late (negative: early)
    bypass_flow_exponent    bypass share b (m / 0.04 kg/s)^exponent: the split depends on the total mass flow
    cooler_ntu              0: the nominal cooler; > 0: effectiveness 1 - exp(-NTU), NTU this value at 0.03 kg/s
                            through the core and ~ (core mass flow)^-0.4 (a fouled core, flow-dependent)
    recirculation_share     share of cabin air (``cabin_temp_c``) in the air entering the box behind the inlet sensor
    tc_radiation_share      the thermocouple settles at T_air + share (T_heater_body - T_air) (radiation)
    heater_wall_ua_w_per_k  heater body heat loss (W/K) to the box walls at the temperature of the air entering the box
    noise_scale             every sensor's noise standard deviation times this (0: no noise). ASSUMPTION: a noisier
                            installation scales all sensors alike (docs/identification.md, "A sweep over magnitudes")
    """

    transport_delay_s: float = 0.0
    duct_loss_ua_w_per_k: float = 0.0
    cabin_temp_c: float = 24.0
    cooler_literal_fit: bool = False
    thermocouple_tau_scale: float = 1.0
    blower_gain_scale: float = 1.0
    valve_shift_pct: float = 0.0
    heater_power_scale: float = 1.0
    chiller_rate_scale: float = 1.0
    ptc_power_fall: bool = True
    outlet_density_correction: bool = False
    log_shift_samples: int = 0
    bypass_flow_exponent: float = 0.0
    cooler_ntu: float = 0.0
    recirculation_share: float = 0.0
    tc_radiation_share: float = 0.0
    heater_wall_ua_w_per_k: float = 0.0
    noise_scale: float = 1.0

    def __post_init__(self) -> None:
        for name in ("transport_delay_s", "duct_loss_ua_w_per_k", "cabin_temp_c", "valve_shift_pct",
                     "bypass_flow_exponent"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"Variant.{name} must be finite, got {getattr(self, name)!r}")
        for name in ("thermocouple_tau_scale", "blower_gain_scale", "heater_power_scale", "chiller_rate_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"Variant.{name} must be a positive number, got {value!r}")
        if self.transport_delay_s < 0.0 or self.duct_loss_ua_w_per_k < 0.0:
            raise ValueError("Variant.transport_delay_s and duct_loss_ua_w_per_k must be >= 0")
        if not -100.0 <= self.valve_shift_pct <= 100.0:
            raise ValueError(f"Variant.valve_shift_pct must be within [-100, 100], got {self.valve_shift_pct}")
        for name in ("cooler_ntu", "recirculation_share", "tc_radiation_share", "heater_wall_ua_w_per_k", "noise_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"Variant.{name} must be a number >= 0, got {value!r}")
        if self.recirculation_share >= 1.0 or self.tc_radiation_share >= 1.0:
            raise ValueError("Variant.recirculation_share and tc_radiation_share must be below 1")
        if int(self.log_shift_samples) != self.log_shift_samples:
            raise ValueError(f"Variant.log_shift_samples must be an integer, got {self.log_shift_samples!r}")

    def as_dict(self) -> dict:
        return asdict(self)

    def differences(self) -> dict:
        """The fields that differ from nominal, with their values."""
        nominal = Variant()
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) != getattr(nominal, f.name)}


_LOSS = DUCT_LOSS_UA_W_PER_K

#: Named variants for the robustness suite, the identification tests and the sweeps.
VARIANTS: dict[str, Variant] = {
    "nominal": Variant(),
    "delay_1s": Variant(transport_delay_s=1.0),
    "delay_3s": Variant(transport_delay_s=3.0),
    "delay_5s": Variant(transport_delay_s=5.0),
    "duct_loss": Variant(duct_loss_ua_w_per_k=_LOSS),
    "cooler_literal": Variant(cooler_literal_fit=True),
    "tc_fast": Variant(thermocouple_tau_scale=0.5),
    "tc_slow": Variant(thermocouple_tau_scale=1.5),
    "blower_weak": Variant(blower_gain_scale=0.8),
    "blower_strong": Variant(blower_gain_scale=1.2),
    "valve_shift": Variant(valve_shift_pct=10.0),
    "heater_weak": Variant(heater_power_scale=0.85),
    "chiller_slow": Variant(chiller_rate_scale=0.5),
    "combo_delay_loss_cooler": Variant(transport_delay_s=3.0, duct_loss_ua_w_per_k=_LOSS, cooler_literal_fit=True),
    "combo_tc_blower_valve": Variant(thermocouple_tau_scale=1.5, blower_gain_scale=0.8, valve_shift_pct=10.0),
    "combo_heater_chiller_delay": Variant(heater_power_scale=0.85, chiller_rate_scale=0.5, transport_delay_s=3.0),
    # the bypass split depending on the total flow, an effect the thesis names and leaves out of its model
    # (ASSUMPTION: exponent 0.3); for the data loop (a refined model in the controller), not in the
    # robustness suite's list (benchmarks/mismatch_suite.py)
    "bypass_flow": Variant(bypass_flow_exponent=0.3),
    # effects outside the identification's library that its term discovery was not shaped on, for the data loop
    # (docs/identification.md, "Effects the discovery was not shaped on"); not in the robustness suite's list
    "cooler_fouled": Variant(cooler_ntu=COOLER_FOULED_NTU),
    "recirculation": Variant(recirculation_share=RECIRCULATION_SHARE),
    "tc_radiation": Variant(tc_radiation_share=TC_RADIATION_SHARE),
    "heater_wall_loss": Variant(heater_wall_ua_w_per_k=HEATER_WALL_UA_W_PER_K),
    "combo_recirc_delay_valve": Variant(recirculation_share=RECIRCULATION_SHARE, transport_delay_s=3.0,
                                        valve_shift_pct=10.0),
    "combo_radiation_tc_heater": Variant(tc_radiation_share=TC_RADIATION_SHARE, thermocouple_tau_scale=1.5,
                                         heater_power_scale=0.85),
}
#: The variants above the discovery was not shaped on (kept out of the robustness suite, like ``bypass_flow``).
UNSHAPED_VARIANTS = ("cooler_fouled", "recirculation", "tc_radiation", "heater_wall_loss", "combo_recirc_delay_valve",
                     "combo_radiation_tc_heater")


def get_variant(variant: "str | Variant | None") -> tuple[str, Variant]:
    """(name, Variant) for a registry name, a :class:`Variant` (name "custom" unless registered) or None."""
    if variant is None:
        return "nominal", VARIANTS["nominal"]
    if isinstance(variant, Variant):
        name = next((n for n, v in VARIANTS.items() if v == variant), "custom")
        return name, variant
    if isinstance(variant, str) and variant in VARIANTS:
        return variant, VARIANTS[variant]
    raise ValueError(f"unknown plant variant {variant!r}; allowed: {', '.join(VARIANTS)}")
