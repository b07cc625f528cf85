"""The data loop's entry point for library users: a log in, an identification result out."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable, Mapping

from hvac_mpc.models.parameters import Parameters

from . import log_data
from .log_data import LogData
from .pipeline import IdentificationResult
from .pipeline import identify as _identify


def identify(log: str | Path | LogData, params: Parameters | None = None, effects: Iterable[str] = (), *,
             mapping: Mapping[str, str] | None = None, holdout_fraction: float = 1 / 3, quick: bool = False,
             max_effects: int = 4, progress: Callable[[str], None] | None = None,
             pairs: bool = True, best_place: bool = False,
             optional_candidates: Iterable[str] = (), thesis_unless_moved: bool = False) -> IdentificationResult:
    """Refine the model from a measurement log (a CSV/Parquet path or a prepared :class:`LogData`).

    ``params``/``effects``: the starting model (default: the thesis model); ``mapping``: log column ->
    schema column; the last ``holdout_fraction`` of the log is held out from fitting. The result
    holds the effects added, the refit parameters and the held-out errors before and after
    (``result.holdout_errors()``); ``hvac_mpc.identification.report.write_report`` writes the report
    and the model file. ``pairs``: screen pairs of effects that only help together when forward
    selection keeps nothing more (docs/identification.md, "Effects that only help together"). ``best_place``: a
    discovered term's place the one whose term leaves the lowest held-out error among those that pass after the
    whole-model refit, not the first that passes (off by default; docs/identification.md, "The term's place").
    ``optional_candidates``: names from ``identification.candidates.OPTIONAL_CANDIDATES`` scored with the library
    (docs/identification.md, "The literal cooler as a library effect"). ``thesis_unless_moved``: where nothing is
    added, the thesis value of every refit parameter the log does not move (off by default; docs/identification.md,
    "A log that adds nothing").
    """
    data = log if isinstance(log, LogData) else log_data.load(log, mapping, holdout_fraction)
    return _identify(data, params or Parameters(), tuple(effects), quick=quick, max_effects=max_effects,
                     progress=progress, pairs=pairs, best_place=best_place, optional_candidates=optional_candidates,
                     thesis_unless_moved=thesis_unless_moved)
