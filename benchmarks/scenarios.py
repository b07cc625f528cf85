"""Named, seeded benchmark scenarios: piecewise-constant references and plant conditions.

Each scenario starts the plant at rest for ``initial_command`` in its environment, holds the
``warmup`` reference for a while (not scored: the controllers' integrators and estimators settle),
then plays ``segments``. ``seed`` selects the plant's sensor noise. :meth:`Scenario.quick` gives the
short version the tests run (fewer, shorter segments).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from hvac_mpc.mismatch.cabin import CabinSetup
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.contract import Command
from hvac_mpc.contract import Reference

M3H = 1.0 / 3600.0  # m3/s per m3/h


@dataclass(frozen=True)
class Segment:
    """A reference held for ``duration_s`` seconds."""

    duration_s: float
    reference: Reference

    def __post_init__(self) -> None:
        if not (isinstance(self.duration_s, (int, float)) and math.isfinite(self.duration_s)
                and self.duration_s >= 1.0):
            raise ValueError(f"duration_s: expected a finite duration >= 1 s, got {self.duration_s!r}")
        if not isinstance(self.reference, Reference):
            raise TypeError(f"reference: expected a Reference, got {type(self.reference).__name__}")


@dataclass(frozen=True)
class Scenario:
    """A benchmark scenario; times in s, temperatures in degC.

    ``kind`` is "cooling" or "heating" (the mode its temperature steps need; the cooling-step aim
    of issue 4 applies to "cooling"). ``quick_warmup_s``/``quick_segment_s``/``quick_segments``
    shorten it for :meth:`quick` (``None`` keeps the full value).
    """

    name: str
    description: str
    seed: int
    kind: str
    inlet_temp_c: float
    chiller_setpoint_c: float
    initial_command: Command
    warmup: Segment
    segments: tuple[Segment, ...]
    quick_warmup_s: float | None = 30.0
    quick_segment_s: float | None = 60.0
    quick_segments: int | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)
    #: The cabin feeding the box's inlet (``None``: the inlet held at ``inlet_temp_c``).
    cabin: CabinSetup | None = None

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("_", "").isalnum():
            raise ValueError(f"name: expected letters, digits and '_', got {self.name!r}")
        if self.kind not in ("cooling", "heating"):
            raise ValueError(f"kind: expected 'cooling' or 'heating', got {self.kind!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed: expected an integer >= 0, got {self.seed!r}")
        for fname, lo, hi in (("inlet_temp_c", -30.0, 50.0), ("chiller_setpoint_c", -5.0, 40.0)):
            v = getattr(self, fname)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"{fname} = {v!r} is outside the allowed range [{lo}, {hi}]")
        if not self.segments:
            raise ValueError("segments: expected at least one segment")

    # ------------------------------------------------------------------ timeline
    @property
    def metrics_start_s(self) -> float:
        """Time the scored part begins (end of the warm-up), s."""
        return self.warmup.duration_s

    @property
    def duration_s(self) -> float:
        """Total duration including the warm-up, s."""
        return self.warmup.duration_s + sum(s.duration_s for s in self.segments)

    def step_times_s(self) -> list[float]:
        """Start times of the scored segments (the reference changes there), s."""
        t, out = self.warmup.duration_s, []
        for s in self.segments:
            out.append(t)
            t += s.duration_s
        return out

    def reference_at(self, time_s: float) -> Reference:
        """The reference in force at ``time_s`` (piecewise constant; the last one after the end)."""
        if time_s < self.warmup.duration_s:
            return self.warmup.reference
        t = self.warmup.duration_s
        for s in self.segments:
            t += s.duration_s
            if time_s < t:
                return s.reference
        return self.segments[-1].reference

    def quick(self) -> "Scenario":
        """The short version: warm-up, segment lengths and count cut to the ``quick_*`` fields."""
        warm = self.warmup if self.quick_warmup_s is None else replace(
            self.warmup, duration_s=min(self.warmup.duration_s, self.quick_warmup_s))
        segs = self.segments[: self.quick_segments] if self.quick_segments else self.segments
        if self.quick_segment_s is not None:
            segs = tuple(replace(s, duration_s=min(s.duration_s, self.quick_segment_s)) for s in segs)
        return replace(self, warmup=warm, segments=tuple(segs))


# ---------------------------------------------------------------------------- definitions
SUMMER_INLET_C = 32.0  # thesis sec. 6: room at about 32 C in the proband tests
SUMMER_CHILLER_C = 5.0  # thesis sec. 4.2 / docs/model.md sec. 1: chiller set point 5 C when cooling
SPLIT_SUMMER = (0.6, 0.15, 0.25)  # mostly middle outlet in summer (thesis sec. 6.2, fig. 53)
SPLIT_WINTER = (0.3, 0.5, 0.2)  # ASSUMPTION: feet and windshield favoured when heating


def _ref(temp_c: float, flow_m3h: float, shares=SPLIT_SUMMER) -> Reference:
    return Reference.from_split(temp_c, flow_m3h * M3H, shares)


def _blower_for(flow_m3h: float) -> float:
    """Blower power giving roughly a flow with the nominal blower curve (docs/model.md sec. 1), W."""
    return float(np.clip(flow_m3h * M3H / Parameters().flow_per_watt_m3s_per_w, 30.0, 300.0))


def summer_cooling_steps() -> Scenario:
    segs = tuple(Segment(180.0, _ref(t, 90.0)) for t in (15.0, 18.0, 20.0, 16.0))
    return Scenario(
        name="summer_cooling_steps", seed=11, kind="cooling",
        description="Cooling steps between 15 and 20 C at 90 m3/h, inlet (room) 32 C, chiller set point 5 C "
                    "(thesis sec. 6 proband conditions).",
        inlet_temp_c=SUMMER_INLET_C, chiller_setpoint_c=SUMMER_CHILLER_C,
        initial_command=Command(_blower_for(90.0), 0.0, 55.0, 100.0, 100.0, 100.0),
        warmup=Segment(90.0, _ref(20.0, 90.0)), segments=segs, quick_segments=2)


def winter_heating_steps() -> Scenario:
    segs = tuple(Segment(180.0, _ref(t, 40.0, SPLIT_WINTER)) for t in (12.0, 15.0, 11.0, 14.0))
    return Scenario(
        name="winter_heating_steps", seed=12, kind="heating",
        description="Heating steps between 9 and 15 C at 40 m3/h with a cold inlet of 5 C; the chiller set point "
                    "equals the inlet temperature (water at inlet temperature, its two-point control still cycling "
                    "+-1 C).",
        inlet_temp_c=5.0, chiller_setpoint_c=5.0,
        initial_command=Command(_blower_for(40.0), 80.0, 60.0, 100.0, 100.0, 100.0),
        warmup=Segment(120.0, _ref(9.0, 40.0, SPLIT_WINTER)), segments=segs, quick_segments=2)


def flow_split_changes() -> Scenario:
    plan = ((120.0, SPLIT_SUMMER), (60.0, (0.3, 0.4, 0.3)), (100.0, (0.2, 0.2, 0.6)), (40.0, (0.5, 0.3, 0.2)),
            (80.0, (0.7, 0.1, 0.2)))
    segs = tuple(Segment(150.0, _ref(18.0, q, shares)) for q, shares in plan)
    return Scenario(
        name="flow_split_changes", seed=13, kind="cooling",
        description="Volume-flow steps between 40 and 120 m3/h with outlet-split changes at a constant 18 C, "
                    "summer conditions (inlet 32 C, chiller 5 C).",
        inlet_temp_c=SUMMER_INLET_C, chiller_setpoint_c=SUMMER_CHILLER_C,
        initial_command=Command(_blower_for(90.0), 0.0, 65.0, 100.0, 100.0, 100.0),
        warmup=Segment(90.0, _ref(18.0, 90.0, (0.4, 0.3, 0.3))), segments=segs, quick_segment_s=50.0,
        quick_segments=3)


def proband_references(seed: int = 14) -> tuple[Reference, ...]:
    """Seven references like the thesis proband tests (sec. 6.2, fig. 51 and 53), drawn from ``seed``.

    Temperatures around 15, 18 or 20 C (+-0.7 C; consecutive ones differ), volume flows 40-130 m3/h
    (all below the 130 m3/h most thesis references stay under), outlet shares mostly middle:
    middle 0.45-0.7, feet 0.1-0.25, windshield the rest. The first is the 'optimal start' 18 C, 90 m3/h.
    """
    rng = np.random.default_rng(seed)
    refs = [_ref(18.0, 90.0)]
    level = 18.0
    while len(refs) < 7:
        level = float(rng.choice([c for c in (15.0, 18.0, 20.0) if c != level]))
        temp = round(level + float(rng.uniform(-0.7, 0.7)), 2)
        flow = round(float(rng.uniform(40.0, 130.0)), 1)
        m = float(rng.uniform(0.45, 0.7))
        f = float(rng.uniform(0.1, 0.25))
        refs.append(_ref(temp, flow, (m, f, 1.0 - m - f)))
    return tuple(refs)


def proband_sequence() -> Scenario:
    refs = proband_references(14)
    return Scenario(
        name="proband_sequence", seed=14, kind="cooling",
        description="Proband-like test (thesis sec. 6): seven references five minutes apart (minutes 0, 5, ..., 30), "
                    "temperatures around 15/18/20 C, flows 40-130 m3/h, mostly middle outlet; room 32 C, chiller 5 C.",
        inlet_temp_c=SUMMER_INLET_C, chiller_setpoint_c=SUMMER_CHILLER_C,
        initial_command=Command(_blower_for(90.0), 0.0, 65.0, 100.0, 100.0, 100.0),
        warmup=Segment(60.0, refs[0]), segments=tuple(Segment(300.0, r) for r in refs),
        quick_segment_s=40.0)


def chiller_switch_times_s(params: Parameters | None = None, setpoint_c: float = SUMMER_CHILLER_C) -> tuple[float, float]:
    """When the chiller's two-point control switches off and on again, from rest at the set point, s.

    The plant starts with the water at the set point and the chiller on: it cools at the falling
    slope to set - band, switches off, warms at the rising slope to set + band, switches on
    (thesis sec. 4.2 slopes; band ASSUMPTION, ``models/chiller.py``).
    """
    p = params or Parameters()
    t_off = p.chiller_band_c / p.water_fall_rate_c_per_s
    t_on = t_off + 2.0 * p.chiller_band_c / p.water_rise_rate_c_per_s
    return t_off, t_on


def chiller_hysteresis_step() -> Scenario:
    t_off, t_on = chiller_switch_times_s()
    first = float(math.ceil(t_off)) + 5.0  # the step arrives just after the chiller switched off
    second = float(math.ceil(t_on)) + 5.0  # and the next just after it switched on again
    return Scenario(
        name="chiller_hysteresis_step", seed=15, kind="cooling",
        description=f"Cooling steps timed on the chiller's two-point control: 20 -> 15 C at {first:.0f} s, just after "
                    f"the chiller switches off (water starts warming), 15 -> 18 C at {second:.0f} s, just after it "
                    "switches on (the quick version stops after the first); 80 m3/h, inlet 32 C, chiller 5 C +-1 C.",
        inlet_temp_c=SUMMER_INLET_C, chiller_setpoint_c=SUMMER_CHILLER_C,
        initial_command=Command(_blower_for(80.0), 0.0, 55.0, 100.0, 100.0, 100.0),
        warmup=Segment(first, _ref(20.0, 80.0)),
        segments=(Segment(second - first, _ref(15.0, 80.0)), Segment(240.0, _ref(18.0, 80.0))),
        quick_warmup_s=None, quick_segment_s=60.0, quick_segments=1,
        notes=(f"Chiller switch times from rest (nominal slopes): off at {t_off:.0f} s, on at {t_on:.0f} s.",))


def trapped_air_release() -> Scenario:
    return Scenario(
        name="trapped_air_release", seed=16, kind="heating",
        description="Heating at a demand the heater cannot meet (12 -> 22 C at 40 m3/h, inlet and water 10 C), "
                    "which pushes valve a towards saturation and tempts the trapped-air pocket (thesis sec. 5.4.2, "
                    "fig. 47); then a lower reference of 15 C releases whatever was trapped.",
        inlet_temp_c=10.0, chiller_setpoint_c=10.0,
        initial_command=Command(_blower_for(40.0), 60.0, 50.0, 100.0, 100.0, 100.0),
        warmup=Segment(90.0, _ref(12.0, 40.0, SPLIT_WINTER)),
        segments=(Segment(300.0, _ref(22.0, 40.0, SPLIT_WINTER)), Segment(180.0, _ref(15.0, 40.0, SPLIT_WINTER))),
        quick_segment_s=120.0, quick_warmup_s=30.0,
        notes=("The quick version keeps 120 s of high demand: the pocket heats with a 60 s lag (ASSUMPTION "
               "tau_trap_heat_s).",))


# ---------------------------------------------------------------------------- the cabin in the loop
def cabin_cooldown_summer() -> Scenario:
    """A sun-soaked cabin pulled down: outside 32 C, cabin air 40 C and interior 45 C at the start,
    400 W of sun on the interior (ASSUMPTION), 70 % recirculated air (mismatch/cabin.py)."""
    cabin = CabinSetup(outside_temp_c=32.0, cabin_temp_c=40.0, interior_temp_c=45.0, solar_w=400.0)
    segs = (Segment(300.0, _ref(14.0, 120.0)), Segment(300.0, _ref(16.0, 90.0)), Segment(300.0, _ref(18.0, 70.0)))
    return Scenario(
        name="cabin_cooldown_summer", seed=17, kind="cooling",
        description="Cabin in the loop, summer pull-down: the box's inlet is 70 % cabin air (40 C at the start, "
                    "interior 45 C, 400 W of sun) and 30 % outside air at 32 C, so the inlet temperature follows the "
                    "supply air the controller delivered earlier; supply steps 14 -> 16 -> 18 C as the flow falls "
                    "from 120 to 70 m3/h; chiller 5 C.",
        inlet_temp_c=cabin.inlet_c(cabin.cabin_temp_c), chiller_setpoint_c=SUMMER_CHILLER_C,
        initial_command=Command(_blower_for(120.0), 0.0, 80.0, 100.0, 100.0, 100.0),
        warmup=Segment(60.0, _ref(16.0, 120.0)), segments=segs, quick_warmup_s=30.0, quick_segment_s=40.0,
        quick_segments=2, cabin=cabin,
        notes=("Cabin parameters are ASSUMPTIONS for a small car (mismatch/cabin.py: air 1.2e4 J/K, interior "
               "6e4 J/K, air-interior 40 W/K, walls 20 W/K, driver 100 W).",))


def cabin_warmup_winter() -> Scenario:
    """A cold cabin warmed: outside 0 C, cabin and interior 2 C, 70 % recirculated air, heater only."""
    cabin = CabinSetup(outside_temp_c=0.0, cabin_temp_c=2.0, interior_temp_c=2.0)
    segs = (Segment(300.0, _ref(11.0, 40.0, SPLIT_WINTER)), Segment(300.0, _ref(13.0, 40.0, SPLIT_WINTER)),
            Segment(300.0, _ref(12.0, 50.0, SPLIT_WINTER)))
    return Scenario(
        name="cabin_warmup_winter", seed=18, kind="heating",
        description="Cabin in the loop, winter warm-up: the box's inlet is 70 % cabin air (2 C at the start) and "
                    "30 % outside air at 0 C; supply steps 11 -> 13 -> 12 C at 40-50 m3/h with the heater alone "
                    "(chiller set point 5 C); the 240 W heater lifts the air about 12 K at 40 m3/h, so the supply "
                    "reference is met only as the cabin (and with it the inlet) warms.",
        inlet_temp_c=cabin.inlet_c(cabin.cabin_temp_c), chiller_setpoint_c=5.0,
        initial_command=Command(_blower_for(40.0), 120.0, 80.0, 100.0, 100.0, 100.0),
        warmup=Segment(60.0, _ref(9.0, 40.0, SPLIT_WINTER)), segments=segs, quick_warmup_s=30.0,
        quick_segment_s=40.0, quick_segments=2, cabin=cabin,
        notes=("Cabin parameters are ASSUMPTIONS for a small car (mismatch/cabin.py).",))


def all_scenarios() -> dict[str, Scenario]:
    """All scenarios by name, in report order."""
    items = (summer_cooling_steps(), winter_heating_steps(), flow_split_changes(), proband_sequence(),
             chiller_hysteresis_step(), trapped_air_release(), cabin_cooldown_summer(), cabin_warmup_winter())
    return {s.name: s for s in items}


def select(names: list[str] | None, quick: bool = False) -> list[Scenario]:
    """Scenarios by name (all when ``names`` is empty), quick versions if asked; unknown names raise ValueError."""
    known = all_scenarios()
    if names:
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(f"--scenario: unknown name(s) {unknown}; choose from {list(known)}")
        chosen = [known[n] for n in dict.fromkeys(names)]
    else:
        chosen = list(known.values())
    return [s.quick() for s in chosen] if quick else chosen


#: A total volume flow the blower cannot deliver at summer conditions (200 m3/h; the box gives about
#: 0.057 m3/s = 205 m3/h at 300 W with every valve open and full bypass, less through the core, thesis table 6).
UNREACHABLE_FLOW_M3H = 200.0


def flow_out_of_reach() -> Scenario:
    segs = (Segment(240.0, _ref(18.0, UNREACHABLE_FLOW_M3H)), Segment(180.0, _ref(16.0, UNREACHABLE_FLOW_M3H)),
            Segment(120.0, _ref(18.0, 90.0)))
    return Scenario(
        name="flow_out_of_reach", seed=17, kind="cooling",
        description=f"A total-flow reference out of reach: {UNREACHABLE_FLOW_M3H:.0f} m3/h at 18 and 16 C with a "
                    "32 C inlet (summer conditions), then back to 90 m3/h. The supply temperature comes first: it "
                    "should hold its reference and the flow fall short, reported as out of reach.",
        inlet_temp_c=SUMMER_INLET_C, chiller_setpoint_c=SUMMER_CHILLER_C,
        initial_command=Command(_blower_for(90.0), 0.0, 55.0, 100.0, 100.0, 100.0),
        warmup=Segment(60.0, _ref(18.0, 90.0)), segments=segs, quick_warmup_s=30.0, quick_segment_s=150.0,
        quick_segments=1)


def mismatch_scenarios() -> dict[str, Scenario]:
    """The scenarios of the mismatch suite: cooling steps, heating steps, the proband sequence and a
    total-flow reference out of reach."""
    items = (summer_cooling_steps(), winter_heating_steps(), proband_sequence(), flow_out_of_reach())
    return {s.name: s for s in items}
