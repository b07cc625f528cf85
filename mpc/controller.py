"""The step interface every controller in this project shares (MPC, baseline, fallbacks)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

from hvac_mpc.models.plant import Command, Measurement

from .reference import Reference


@dataclass
class StepResult:
    """What a control step returns: the command and its statistics.

    ``stats`` keys used across controllers: ``step_time_s`` (wall time of the step),
    ``iterations`` (solver iterations, 0 for the baseline), ``status`` (solver status text),
    ``fallback`` (``None`` or the name of the fallback used), ``mode`` (e.g. "cooling").
    """

    command: Command
    stats: dict[str, Any] = field(default_factory=dict)


class Controller(Protocol):
    """measurement and reference in, actuator command out, once per sample."""

    dt_s: float

    def step(self, measurement: Measurement, reference: Reference) -> StepResult: ...

    def reset(self) -> None: ...
