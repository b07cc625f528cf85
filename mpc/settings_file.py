"""MPC settings from a mapping or a TOML / JSON file.

``hvac-mpc bench --mpc-settings FILE`` and the daemon's ``[controller.settings]`` table both go
through :func:`settings_with`: the file names fields of :class:`~hvac_mpc.mpc.mpc_controller.MpcSettings`
at its top level and fields of the settings it holds in sub-tables (``[ocp]``, ``[ocp.weights]``,
``[ekf]``); every field not named keeps its default. A name that is not a field raises
:class:`~hvac_mpc.mpc.ocp.InvalidSettings` naming it and the fields allowed there; a value out of range
raises the settings' own error (naming the field and the range) when the settings are built.
"""
from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path
from typing import Any, Mapping, TypeVar

from .ocp import InvalidSettings

S = TypeVar("S")


def settings_with(base: S, values: Mapping[str, Any], path: str = "") -> S:
    """``base`` (a settings dataclass) with the fields in ``values`` replaced, sub-tables into the
    dataclasses ``base`` holds; lists become tuples (the settings' sequences are tuples)."""
    name = path or type(base).__name__
    known = {f.name for f in dataclasses.fields(base)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise InvalidSettings(f"{name}: unknown field(s) {unknown}; allowed: {sorted(known)}")
    changes = {}
    for key, value in values.items():
        current = getattr(base, key)
        if isinstance(value, Mapping) and dataclasses.is_dataclass(current):
            changes[key] = settings_with(current, value, f"{name}.{key}")
        else:
            changes[key] = tuple(value) if isinstance(value, list) else value
    try:
        return dataclasses.replace(base, **changes)
    except TypeError as exc:
        raise InvalidSettings(f"{name}: {exc}") from None


def read_settings_file(path: str | Path) -> dict[str, Any]:
    """The mapping in a TOML (``.toml``) or JSON (``.json``) settings file; errors name the file."""
    path = Path(path)
    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (OSError, ValueError) as exc:
        raise InvalidSettings(f"settings file {path}: {exc}") from None
    if not isinstance(data, dict):
        raise InvalidSettings(f"settings file {path}: the top level must be a table of MpcSettings fields")
    return data
