"""The model file: parameters plus the effects to enable, as written by ``hvac-mpc identify``.

TOML layout (JSON with the same keys is read too)::

    [parameters]            # Parameters fields that differ from the defaults (Parameters.write)
    fan_k_kg_m7 = 94206.1

    [model]
    effects = ["fan_curve"] # HvacModel effects to switch on

    [identification]        # what the model cannot hold (delays, output offsets), for estimators
    supply_temp_c_delay_s = 4.0

Anyone building the model calls::

    params, effects = load_model_file("out/identify/model.toml")
    model = HvacModel(params, effects)
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any, Iterable, Mapping

from hvac_mpc.models.box import MODEL_EFFECTS, validate_effects
from hvac_mpc.models.parameters import Parameters


def _read(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise FileNotFoundError(f"model file {path} does not exist")
    text = path.read_text()
    try:
        return json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"model file {path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'TOML'}"
                         f" ({exc})") from None


def load_model_file(path: str | Path, base: Parameters | None = None) -> tuple[Parameters, tuple[str, ...]]:
    """Parameters and effect names from a model file (a plain parameter file gives no effects).

    Raises ``ValueError`` naming an unknown effect and the allowed ones, ``KeyError`` naming an
    unknown parameter.
    """
    path = Path(path)
    data = _read(path)
    table = data.get("parameters", {})
    if not isinstance(table, Mapping):
        raise ValueError(f"model file {path}: [parameters] must be a table")
    if not table and not {"model", "identification"} & set(data):
        table = data  # a flat parameter file as Parameters.from_file reads it
    params = Parameters.from_mapping(dict(table), base)
    model = data.get("model", {})
    effects = model.get("effects", []) if isinstance(model, Mapping) else []
    if not isinstance(effects, list) or not all(isinstance(e, str) for e in effects):
        raise ValueError(f"model file {path}: [model] effects must be a list of names from {list(MODEL_EFFECTS)}")
    validate_effects(effects, MODEL_EFFECTS)
    return params, tuple(e for e in MODEL_EFFECTS if e in effects)


def load_identification_extras(path: str | Path) -> dict[str, Any]:
    """The ``[identification]`` table (delays, offsets the model cannot hold); empty if absent."""
    extra = _read(Path(path)).get("identification", {})
    return dict(extra) if isinstance(extra, Mapping) else {}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"cannot write a non-finite number {value!r} to TOML")
    return json.dumps(value)


def write_model_file(path: str | Path, params: Parameters, effects: Iterable[str],
                     extras: Mapping[str, Any] | None = None) -> Path:
    """Write ``[parameters]`` (changed fields), ``[model] effects`` and ``[identification]`` extras."""
    path = Path(path)
    effects = validate_effects(effects, MODEL_EFFECTS)
    params.write(path)
    if path.suffix.lower() == ".json":
        data = json.loads(path.read_text())
        data["model"] = {"effects": [e for e in MODEL_EFFECTS if e in effects]}
        if extras:
            data["identification"] = dict(extras)
        path.write_text(json.dumps(data, indent=2))
        return path
    lines = [path.read_text().rstrip("\n"), "", "[model]",
             "effects = " + json.dumps([e for e in MODEL_EFFECTS if e in effects])]
    if extras:
        lines += ["", "[identification]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in extras.items()]
    path.write_text("\n".join(lines) + "\n")
    return path
