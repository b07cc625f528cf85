"""References from the comfort algorithm and their validation (design.md sec. 2)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Mapping

#: Allowed ranges of each reference field (inclusive), SI units as in the names.
REFERENCE_RANGES = {
    "supply_temp_c": (5.0, 50.0),
    "volume_flow_m3s": (0.006, 0.06),
    "flow_m_m3s": (0.0, 0.06),
    "flow_f_m3s": (0.0, 0.06),
    "flow_w_m3s": (0.0, 0.06),
}
#: Largest allowed mismatch between the outlet flows' sum and the total (fraction of the total).
SPLIT_TOLERANCE = 0.1


class InvalidReference(ValueError):
    """A reference field is missing, malformed or out of range; the message names it."""


@dataclass(frozen=True)
class Reference:
    """Supply air temperature (degC), total volume flow and outlet flows m, f, w (m3/s).

    Outlet flows may be omitted (``None``): the split is then free and only the total is tracked.
    Construction validates every field and raises :class:`InvalidReference` naming the field and
    its allowed range.
    """

    supply_temp_c: float
    volume_flow_m3s: float
    flow_m_m3s: float | None = None
    flow_f_m3s: float | None = None
    flow_w_m3s: float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None and f.name.startswith("flow_"):
                continue
            lo, hi = REFERENCE_RANGES[f.name]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InvalidReference(f"{f.name}: expected a finite number in [{lo}, {hi}], got {value!r}")
            if not lo <= value <= hi:
                raise InvalidReference(f"{f.name} = {value} is outside the allowed range [{lo}, {hi}]")
        split = self.split
        if split is None and any(getattr(self, n) is not None for n in ("flow_m_m3s", "flow_f_m3s", "flow_w_m3s")):
            raise InvalidReference("flow_m_m3s, flow_f_m3s, flow_w_m3s: give all three outlet flows or none")
        if split is not None:
            total = sum(split)
            if abs(total - self.volume_flow_m3s) > SPLIT_TOLERANCE * self.volume_flow_m3s:
                raise InvalidReference(
                    f"flow_m_m3s + flow_f_m3s + flow_w_m3s = {total:.5f} must be within "
                    f"{SPLIT_TOLERANCE:.0%} of volume_flow_m3s = {self.volume_flow_m3s:.5f}")

    @property
    def split(self) -> tuple[float, float, float] | None:
        """Outlet flows (m, f, w) or ``None`` when the split is free."""
        vals = (self.flow_m_m3s, self.flow_f_m3s, self.flow_w_m3s)
        return None if any(v is None for v in vals) else vals  # type: ignore[return-value]

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> "Reference":
        """Build from a mapping (e.g. parsed JSON); unknown or missing keys raise a clear error."""
        if not isinstance(data, Mapping):
            raise InvalidReference(f"reference must be an object with fields {list(REFERENCE_RANGES)}")
        unknown = sorted(set(data) - set(REFERENCE_RANGES))
        if unknown:
            raise InvalidReference(f"unknown field(s) {unknown}; allowed: {list(REFERENCE_RANGES)}")
        for required in ("supply_temp_c", "volume_flow_m3s"):
            if required not in data:
                lo, hi = REFERENCE_RANGES[required]
                raise InvalidReference(f"{required}: required, a number in [{lo}, {hi}]")
        return cls(**dict(data))

    @classmethod
    def from_split(cls, supply_temp_c: float, volume_flow_m3s: float,
                   shares: tuple[float, float, float]) -> "Reference":
        """Reference from a total flow and outlet shares (normalised to sum to one)."""
        total = sum(shares)
        m, f, w = (volume_flow_m3s * s / total for s in shares)
        return cls(supply_temp_c, volume_flow_m3s, m, f, w)
