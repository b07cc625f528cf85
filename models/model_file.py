"""The model file: one versioned file holding a refined model (what ``hvac-mpc identify`` writes,
what ``bench --model``, ``solve-time --model`` and ``daemon --model`` read).

TOML layout (JSON with the same keys is read too)::

    format_version = 2

    [parameters]            # Parameters fields that differ from the defaults (transport_delay_s included)
    fan_k_kg_m7 = 94206.1
    transport_delay_s = 3.0
    valve_a_shift_pct = 9.9 # a shifted valve curve (% of travel, positive: acts less open; 0 when absent)

    [model]
    effects = ["fan_curve"] # HvacModel effects to switch on
    absent = ["bypass_flow"] # effects the log tested and did not support (format 3; for the record and the
                             # controller's own estimates, docs/identification.md "The refined model in the controller")

    [[model.terms]]         # discovered terms (models/discovered.py)
    name = "supply_residual_term"
    location = "supply_air"
    features = ["mix_over_mass_flow", "inv_mass_flow", "one"]
    coefficients = [-0.0029, 0.070, 0.0]
    units = ["C / (C s/kg)", "C / (s/kg)", "C"]
    description = "..."

    [identification]        # what the model cannot hold (output offsets), for the record

Every key is checked on load (pydantic); an error names the field and the allowed values and
nothing is built. Version 1 files (no ``format_version``, no terms) are read as before.

**Controller-owned effects** (:data:`CONTROLLER_EFFECTS`): ``bypass_flow`` is in the MPC's prediction model
as a device of the controller (``OcpSpec.model_effects``: it keeps valve a's gain right in low-flow heating),
not as a statement about the box; the box's identification says whether the box has it (``absent``). The
MPC with a refined model keeps its configured treatment of these effects
(:meth:`RefinedModel.prediction_effects`), so what a model file changes in the controller is what the log
established (parameters, effects, terms, delay), not the controller's own structure.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Literal, Mapping

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from hvac_mpc.validation import describe_error

from .box import MODEL_EFFECTS, validate_effects
from .discovered import FEATURES, LOCATIONS, DiscoveredTerm
from .parameters import Parameters

#: Current version of the file format (1: parameters and effects; 2: + discovered terms, delay; 3: + absent).
FORMAT_VERSION = 3
#: Effects the controller carries as its own device whatever a model file says (module docstring).
CONTROLLER_EFFECTS = ("bypass_flow",)


class ModelFileError(ValueError, KeyError):
    """The model file is unreadable or invalid; the message names the field. Also a ``KeyError`` (what
    an unknown parameter raised before the file was validated as a whole)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class _TermSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    location: Literal[tuple(LOCATIONS)]  # type: ignore[valid-type]
    features: list[Literal[tuple(FEATURES)]]  # type: ignore[valid-type]
    coefficients: list[float]
    units: list[str] = []
    description: str = ""

    @field_validator("coefficients")
    @classmethod
    def _finite(cls, v: list[float]) -> list[float]:
        if not all(math.isfinite(c) for c in v):
            raise ValueError("coefficients must be finite numbers")
        return v


class _ModelTable(BaseModel):
    model_config = ConfigDict(extra="forbid")
    effects: list[Literal[tuple(MODEL_EFFECTS)]] = []  # type: ignore[valid-type]
    terms: list[_TermSpec] = []
    absent: list[Literal[tuple(MODEL_EFFECTS)]] = []  # type: ignore[valid-type]


class _FileSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format_version: Literal[1, 2, 3] = 1
    parameters: dict[str, Any] = {}
    model: _ModelTable = _ModelTable()
    identification: dict[str, Any] = {}


@dataclass(frozen=True)
class RefinedModel:
    """A model as the controller builds it: parameters, effects, discovered terms, extras; ``absent``: effects
    the log tested and did not support."""

    parameters: Parameters = field(default_factory=Parameters)
    effects: tuple[str, ...] = ()
    terms: tuple[DiscoveredTerm, ...] = ()
    extras: Mapping[str, Any] = field(default_factory=dict)
    source: str = ""
    absent: tuple[str, ...] = ()

    @property
    def transport_delay_s(self) -> float:
        return float(self.parameters.transport_delay_s)

    def prediction_effects(self, configured: Iterable[str]) -> tuple[str, ...]:
        """The effects of a controller's prediction model built from this file: the file's effects, and of the
        controller's own (:data:`CONTROLLER_EFFECTS`) those in ``configured`` (the controller's settings),
        whatever the file says about the box (module docstring)."""
        configured = set(configured)
        keep = set(self.effects) | {e for e in CONTROLLER_EFFECTS if e in configured}
        return tuple(e for e in MODEL_EFFECTS if e in keep)


def _describe(err: ValidationError) -> str:
    """Pydantic's messages, with the allowed values spelt out for a name that is not one of them."""
    lines = []
    for e in err.errors():
        if e["type"] == "literal_error":
            key = ".".join(str(p) for p in e["loc"])
            lines.append(f"{key}: {e['input']!r} is not allowed; allowed: {e['ctx']['expected']}")
        else:
            lines.append(describe_error(ValidationError.from_exception_data(err.title, [e])))
    return "; ".join(lines)


def _read(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise FileNotFoundError(f"model file {path} does not exist")
    text = path.read_text()
    try:
        return json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ModelFileError(f"model file {path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'TOML'}"
                             f" ({exc})") from None


def load(path: str | Path, base: Parameters | None = None) -> RefinedModel:
    """The refined model in ``path``, validated; :class:`ModelFileError` names the bad field."""
    path = Path(path)
    data = _read(path)
    if not {"parameters", "model", "identification", "format_version"} & set(data):
        data = {"parameters": data}  # a flat parameter file as Parameters.from_file reads it
    try:
        spec = _FileSpec.model_validate(data)
    except ValidationError as err:
        raise ModelFileError(f"model file {path}: {_describe(err)}") from None
    try:
        params = Parameters.from_mapping(dict(spec.parameters), base)
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFileError(f"model file {path}: parameters: {exc}") from None
    terms = []
    for i, t in enumerate(spec.model.terms):
        try:
            terms.append(DiscoveredTerm(t.name, t.location, tuple(t.features), tuple(t.coefficients), t.description))
        except ValueError as exc:
            raise ModelFileError(f"model file {path}: model.terms.{i}: {exc}") from None
    effects = tuple(e for e in MODEL_EFFECTS if e in spec.model.effects)
    absent = tuple(e for e in MODEL_EFFECTS if e in spec.model.absent)
    if set(effects) & set(absent):
        raise ModelFileError(f"model file {path}: model.absent: {sorted(set(effects) & set(absent))} also in "
                             f"model.effects; an effect is either in the model or absent")
    return RefinedModel(params, effects, tuple(terms), dict(spec.identification), str(path), absent)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"cannot write a non-finite number {value!r} to TOML")
    return json.dumps(value)


def write(path: str | Path, params: Parameters, effects: Iterable[str], extras: Mapping[str, Any] | None = None,
          terms: Iterable[DiscoveredTerm] = (), absent: Iterable[str] = ()) -> Path:
    """Write the model file (format :data:`FORMAT_VERSION`); ``absent``: effects the log tested and did not
    support (not in ``effects``)."""
    path = Path(path)
    effects = validate_effects(effects, MODEL_EFFECTS)
    absent = validate_effects(absent, MODEL_EFFECTS) - effects
    terms = tuple(terms)
    params.write(path)
    effect_list = [e for e in MODEL_EFFECTS if e in effects]
    absent_list = [e for e in MODEL_EFFECTS if e in absent]
    if path.suffix.lower() == ".json":
        data = {"format_version": FORMAT_VERSION, **json.loads(path.read_text())}
        data["model"] = {"effects": effect_list, "terms": [t.as_dict() for t in terms]}
        if absent_list:
            data["model"]["absent"] = absent_list
        if extras:
            data["identification"] = dict(extras)
        path.write_text(json.dumps(data, indent=2))
        return path
    lines = [f"format_version = {FORMAT_VERSION}", "", path.read_text().rstrip("\n"), "", "[model]",
             "effects = " + json.dumps(effect_list)]
    if absent_list:
        lines.append("absent = " + json.dumps(absent_list))
    for t in terms:
        lines += ["", "[[model.terms]]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in t.as_dict().items()]
    if extras:
        lines += ["", "[identification]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in extras.items()]
    path.write_text("\n".join(lines) + "\n")
    return path
