"""hvac-mpc: model predictive control of an automotive HVAC box.

The public API, importable from the package itself (loaded on first use)::

    from hvac_mpc import (Parameters, HvacModel, SimulatedPlant, Command, Measurement, Reference,
                          MpcController, MpcSettings, BaselineController, load_model_file, identify)

Layers, bottom up (docs/architecture.md): ``contract`` and ``validation``; ``models`` (the box)
and ``mismatch`` (an independent simulation of it); ``mpc`` (MPC and thesis baseline);
``identification`` (the data loop); ``daemon``; ``benchmarks``; ``cli``.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: Public name -> module that defines it.
_PUBLIC = {
    "Parameters": "hvac_mpc.models.parameters",
    "HvacModel": "hvac_mpc.models.box",
    "SimulatedPlant": "hvac_mpc.models.plant",
    "Environment": "hvac_mpc.models.plant",
    "Command": "hvac_mpc.contract",
    "Measurement": "hvac_mpc.contract",
    "Reference": "hvac_mpc.contract",
    "InvalidReference": "hvac_mpc.contract",
    "StepResult": "hvac_mpc.contract",
    "Controller": "hvac_mpc.contract",
    "Plant": "hvac_mpc.contract",
    "InvalidValue": "hvac_mpc.validation",
    "MpcController": "hvac_mpc.mpc.mpc_controller",
    "MpcSettings": "hvac_mpc.mpc.mpc_controller",
    "BaselineController": "hvac_mpc.mpc.baseline",
    "load_model_file": "hvac_mpc.identification.model_file",
    "identify": "hvac_mpc.identification.api",
}

__all__ = sorted(_PUBLIC) + ["__version__"]


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'hvac_mpc' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
