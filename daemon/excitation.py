"""Identification excitation as a controller the daemon runs: open-loop commands through the safety layer.

:class:`ExcitationController` ignores the reference and plays a seeded sequence of actuator
targets (random steps, PRBS or a multisine, per actuator within its amplitude range), moved
towards each target no faster than the actuator's rate limit. It runs in the daemon's controller
slot (``controller.name = "excitation"``, a registered entry point), so the sensor
checks, the heater interlock and the shutdown sequence hold as for any controller
(docs/real-box.md, experiments).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from hvac_mpc.contract import INPUTS, Command, Measurement, Reference, StepResult
from hvac_mpc.validation import InvalidValue, check_fields, finite_in, one_of

KINDS = ("steps", "prbs", "multisine")
#: ASSUMPTION: default amplitude ranges per actuator: blower high enough for the heater interlock's flow
#: (0.005 m3/s at about 30 W with open valves, docs/model.md sec. 1), outlet valves never all closed.
DEFAULT_RANGES = {"blower_power_w": (60.0, 260.0), "heater_cmd_w": (0.0, 200.0), "valve_a_pct": (0.0, 100.0),
                  "valve_m_pct": (20.0, 100.0), "valve_f_pct": (20.0, 100.0), "valve_w_pct": (20.0, 100.0)}
#: Rate limits per actuator and second (ASSUMPTION: the daemon's manual-mode limits, valves 20 %/s, powers 60 W/s;
#: the MPC allows its valves 50 %/s, docs/model.md sec. 2).
DEFAULT_RATES = {"blower_power_w": 60.0, "heater_cmd_w": 60.0, "valve_a_pct": 20.0, "valve_m_pct": 20.0,
                 "valve_f_pct": 20.0, "valve_w_pct": 20.0}
LIMITS = {"blower_power_w": (30.0, 300.0), "heater_cmd_w": (0.0, 240.0), "valve_a_pct": (0.0, 100.0),
          "valve_m_pct": (0.0, 100.0), "valve_f_pct": (0.0, 100.0), "valve_w_pct": (0.0, 100.0)}


class InvalidExcitation(InvalidValue):
    """An excitation setting is out of range; the message names it."""


@dataclass(frozen=True)
class ExcitationSpec:
    """What the excitation plays (times in s).

    ``kind``: "steps" (each actuator holds a random level for a random time in
    [hold_min_s, hold_max_s]), "prbs" (each actuator switches between the ends of its range on a
    pseudo-random binary sequence clocked every ``hold_min_s``) or "multisine" (a sum of
    ``sines`` sines with random phases, periods log-spaced from 2 hold_min_s to hold_max_s).
    ``ranges``: per actuator (low, high) within its limits; ``rates``: per actuator and second.
    ``heater_share``: share of the time the heater may be on (in blocks of ``hold_max_s``, the
    rest with the heater off, cooling-like); 1 leaves it to the sequence.
    """

    kind: str = field(default="steps", metadata={"check": one_of(*KINDS)})
    seed: int = field(default=0, metadata={"check": finite_in(0, 2**31, integer=True)})
    hold_min_s: float = field(default=20.0, metadata={"check": finite_in(1.0, 3600.0)})
    hold_max_s: float = field(default=120.0, metadata={"check": finite_in(1.0, 7200.0)})
    sines: int = field(default=4, metadata={"check": finite_in(1, 20, integer=True)})
    heater_share: float = field(default=0.5, metadata={"check": finite_in(0.0, 1.0)})
    ranges: Mapping[str, tuple[float, float]] = field(default_factory=lambda: dict(DEFAULT_RANGES))
    rates: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_RATES))

    def __post_init__(self) -> None:
        check_fields(self, error=InvalidExcitation)
        if self.hold_max_s < self.hold_min_s:
            raise InvalidExcitation(f"hold_max_s = {self.hold_max_s} must be at least hold_min_s = {self.hold_min_s}")
        for name in self.ranges:
            if name not in LIMITS:
                raise InvalidExcitation(f"ranges.{name}: unknown actuator; allowed {list(INPUTS)}")
        for name, rng in self.ranges.items():
            lo, hi = LIMITS[name]
            ok = (isinstance(rng, (list, tuple)) and len(rng) == 2
                  and all(isinstance(v, (int, float)) and math.isfinite(v) for v in rng))
            if not ok or not lo <= rng[0] <= rng[1] <= hi:
                raise InvalidExcitation(f"ranges.{name} = {rng!r}: expected [low, high] with {lo} <= low <= high "
                                        f"<= {hi}")
        for name, r in self.rates.items():
            if name not in LIMITS:
                raise InvalidExcitation(f"rates.{name}: unknown actuator; allowed {list(INPUTS)}")
            if not (isinstance(r, (int, float)) and math.isfinite(r) and 0.0 < r <= 1000.0):
                raise InvalidExcitation(f"rates.{name} = {r!r} is outside the allowed range (0, 1000]")

    def range_of(self, name: str) -> tuple[float, float]:
        return tuple(self.ranges.get(name, DEFAULT_RANGES[name]))  # type: ignore[return-value]

    def rate_of(self, name: str) -> float:
        return float(self.rates.get(name, DEFAULT_RATES[name]))


def targets(spec: ExcitationSpec, n: int, dt_s: float = 1.0) -> np.ndarray:
    """The (n, 6) actuator targets in ``INPUTS`` order (before rate limiting), from ``spec.seed``."""
    rng = np.random.default_rng([spec.seed, KINDS.index(spec.kind)])
    t = np.arange(n) * dt_s
    out = np.zeros((n, len(INPUTS)))
    for j, name in enumerate(INPUTS):
        lo, hi = spec.range_of(name)
        if spec.kind == "steps":
            col, k = np.empty(n), 0
            while k < n:
                hold = int(max(1, round(rng.uniform(spec.hold_min_s, spec.hold_max_s) / dt_s)))
                col[k:k + hold] = rng.uniform(lo, hi)
                k += hold
        elif spec.kind == "prbs":
            clock = max(1, int(round(spec.hold_min_s / dt_s)))
            bits = rng.integers(0, 2, size=n // clock + 1)
            col = np.where(np.repeat(bits, clock)[:n] == 1, hi, lo).astype(float)
        else:
            periods = np.geomspace(2.0 * spec.hold_min_s, spec.hold_max_s, spec.sines)
            phases = rng.uniform(0.0, 2.0 * np.pi, spec.sines)
            s = sum(np.sin(2.0 * np.pi * t / p + ph) for p, ph in zip(periods, phases))
            s = s / max(np.max(np.abs(s)), 1e-9)
            col = 0.5 * (lo + hi) + 0.5 * (hi - lo) * s
        out[:, j] = col
    if spec.heater_share < 1.0:
        block = max(1, int(round(spec.hold_max_s / dt_s)))
        on = rng.random(n // block + 1) < spec.heater_share
        out[~np.repeat(on, block)[:n], INPUTS.index("heater_cmd_w")] = 0.0
    return out


class ExcitationController:
    """Open-loop excitation in the Controller protocol (reference ignored); see the module docstring.

    The daemon builds it with ``ExcitationController(params=..., dt_s=..., **settings)``, settings
    being the fields of :class:`ExcitationSpec` plus ``duration_s`` (the length of the sequence; it
    repeats after that).
    """

    def __init__(self, params: Any = None, dt_s: float = 1.0, duration_s: float = 3600.0, **spec: Any):
        self.dt_s = float(dt_s)
        self.spec = ExcitationSpec(**spec)
        n = int(max(1, round(duration_s / self.dt_s)))
        self._targets = targets(self.spec, n, self.dt_s)
        self._rate = np.array([self.spec.rate_of(n_) * self.dt_s for n_ in INPUTS])
        self._k = 0
        self._u: np.ndarray | None = None

    def reset(self, command: Command | None = None) -> None:
        """Start from the command in force (bumpless: the first move is rate-limited from it)."""
        self._u = None if command is None else command.vector()

    def step(self, measurement: Measurement, reference: Reference) -> StepResult:
        target = self._targets[self._k % len(self._targets)]
        self._k += 1
        u = target.copy() if self._u is None else self._u + np.clip(target - self._u, -self._rate, self._rate)
        self._u = u
        return StepResult(Command.from_vector(u), {"mode": f"excitation:{self.spec.kind}", "iterations": 0,
                                                   "status": "open_loop", "fallback": None})
