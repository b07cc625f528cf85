"""The model file ``hvac-mpc identify`` writes; the format belongs to the model
(:mod:`hvac_mpc.models.model_file`), re-exported here for the public API.

Anyone building the model calls::

    params, effects = load_model_file("out/identify/model.toml")
    model = HvacModel(params, effects)
    refined = load_refined_model("out/identify/model.toml")   # + discovered terms and the delay
    model = HvacModel(refined.parameters, refined.effects, terms=refined.terms)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

from hvac_mpc.models import model_file as _mf
from hvac_mpc.models.discovered import DiscoveredTerm
from hvac_mpc.models.model_file import ModelFileError, RefinedModel
from hvac_mpc.models.parameters import Parameters

__all__ = ["ModelFileError", "RefinedModel", "load_identification_extras", "load_model_file", "load_refined_model",
           "write_model_file"]


def load_refined_model(path: str | Path, base: Parameters | None = None) -> RefinedModel:
    """Parameters, effects, discovered terms and extras of a model file, validated."""
    return _mf.load(path, base)


def load_model_file(path: str | Path, base: Parameters | None = None) -> tuple[Parameters, tuple[str, ...]]:
    """Parameters and effect names from a model file (a plain parameter file gives no effects).

    Raises :class:`ModelFileError` (a ``ValueError``) naming a bad field and its allowed values.
    """
    refined = _mf.load(path, base)
    return refined.parameters, refined.effects


def load_identification_extras(path: str | Path) -> dict[str, Any]:
    """The ``[identification]`` table (output offsets the model cannot hold); empty if absent."""
    return dict(_mf.load(path).extras)


def write_model_file(path: str | Path, params: Parameters, effects: Iterable[str],
                     extras: Mapping[str, Any] | None = None, terms: Iterable[DiscoveredTerm] = (),
                     absent: Iterable[str] = ()) -> Path:
    """Write the model file: changed parameters, effects, discovered terms, extras and the effects the log
    tested and did not support (``IdentificationResult.absent``)."""
    return _mf.write(path, params, effects, extras, terms, absent)
