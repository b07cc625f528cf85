"""One validation mechanism for the whole project: pydantic checks, clear errors.

Settings objects, references, config files, API bodies and model files all validate through
pydantic. Dataclass fields carry their check in ``metadata["check"]`` (built with
:func:`finite_in`, :func:`one_of`, :func:`flag`); :func:`check_fields` runs them. Pydantic models
are turned into messages by :func:`describe_error`. Every message names the field, the value and
the allowed range or choices; bad input raises and changes nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Annotated, Any, Literal

from pydantic import Field, TypeAdapter, ValidationError


class InvalidValue(ValueError):
    """A value is missing, malformed or out of range; the message names the field and the range."""


@dataclass(frozen=True)
class Check:
    """A pydantic check of one value with a description of what it allows."""

    adapter: TypeAdapter
    allowed: str
    optional: bool = False
    lo: float | None = None  # the range of a finite_in check, for a config field that states it again
    hi: float | None = None

    def __call__(self, name: str, value: Any, error: type[InvalidValue] = InvalidValue) -> Any:
        if value is None and self.optional:
            return None
        try:
            return self.adapter.validate_python(value)
        except ValidationError:
            pass
        if _is_finite_number(value) and self.lo is not None:  # a number out of a finite_in range
            raise error(f"{name} = {value!r} is outside the allowed range {self.allowed}")
        raise error(f"{name}: expected {self.describe()}, got {value!r}")

    def describe(self) -> str:
        return self.allowed if self.allowed.startswith(("one of", "True")) else f"a finite number in {self.allowed}"


def _is_finite_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def finite_in(lo: float, hi: float, *, integer: bool = False, lo_open: bool = False,
              optional: bool = False) -> Check:
    """A finite number (an integer with ``integer``) in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``)."""
    bound = {"gt": lo} if lo_open else {"ge": lo}
    kind = int if integer else float
    adapter = TypeAdapter(Annotated[kind, Field(strict=True, le=hi, allow_inf_nan=False, **bound)])
    left = "(" if lo_open else "["
    return Check(adapter, f"{left}{lo}, {hi}]" + (" (integer)" if integer else ""), optional, lo, hi)


def one_of(*choices: Any) -> Check:
    """One of the given values."""
    return Check(TypeAdapter(Literal[choices]), f"one of {list(choices)}")


def flag() -> Check:
    """True or False."""
    return Check(TypeAdapter(Annotated[bool, Field(strict=True)]), "True or False")


def check_fields(obj: Any, prefix: str = "", error: type[InvalidValue] = InvalidValue) -> None:
    """Run the ``metadata["check"]`` of every dataclass field of ``obj``; raise on the first bad one."""
    for f in fields(obj):
        check = f.metadata.get("check")
        if check is not None:
            check(f"{prefix}{f.name}", getattr(obj, f.name), error)


def describe_error(err: ValidationError, prefix: str = "") -> str:
    """One line per problem of a pydantic ``ValidationError``: ``key: message (got value)``."""
    lines = []
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"]) or "(top level)"
        got = e.get("input")
        shown = "" if isinstance(got, dict) else f" (got {got!r})"
        lines.append(f"{prefix}{key}: {e['msg']}{shown}")
    return "; ".join(lines)
