"""Which place a discovered term takes (identification/pipeline.py ``_discover``): the first place whose term passes
after the whole-model refit (the default), or, with ``best_place``, the place whose term leaves the lowest held-out
error among those that pass. A stand-in for the linear scores and the refits, each place's outcome known: the rule
is what is tested; the whole procedure on measured logs is in tests/test_data_loop.py and
``benchmarks/identify_sweep.py --best-place``."""


import numpy as np
import pytest

from hvac_mpc.identification import discovery, pipeline
from hvac_mpc.identification.fitting import Fit
from hvac_mpc.identification.log_data import load
from hvac_mpc.identification.simulator import OutputPost
from hvac_mpc.mismatch import simulate_log

OUTPUTS = ("supply_temp_c",)


def _fit(cost_holdout: float) -> Fit:
    post = OutputPost(OUTPUTS, np.arange(3.0))
    return Fit(frozenset(), np.zeros(2), post, (), np.zeros((3, 1)), None, cost_holdout, cost_holdout, 3, 3)


class _Fitter:
    outputs = list(OUTPUTS)

    def raw_sensitivity(self, effects, p, free, terms=()):
        return np.zeros((3, 1, 0))


def _discover(monkeypatch, places: dict[str, tuple[float, bool, float]], best_place: bool):
    """``places``: location -> (linear held-out score, passes after the refit, held-out cost after the refit)."""
    monkeypatch.setattr(pipeline, "diagnostics_ratio", lambda fitter, fit: 5.0)
    refit = []

    def select(fitter, fit, dy, location):
        score = places[location][0]
        return ["inlet"], np.array([0.1, 0.0]), {"location": location, "path_order": ["inlet"],
                                                  "holdout_sse_best": score}

    def fit_term(fitter, current, free, term, record, quick):
        _, passes, cost = places[record["location"]]
        refit.append(record["location"])
        record.update({"accepted": passes, "term": {"name": term.name}, "formula": record["location"],
                       "words": "", "explained_holdout": 0.5, "bic_change": -10.0 if passes else 5.0})
        return _fit(cost)
    monkeypatch.setattr(discovery, "select", select)
    monkeypatch.setattr(pipeline, "_fit_term", fit_term)
    notes = []
    fit, record, rejected = pipeline._discover(_Fitter(), _fit(100.0), [], False, lambda m: None, notes,
                                               tuple(places), best_place=best_place)
    return fit, record, rejected, refit, notes


PLACES = {"supply_air": (10.0, True, 60.0), "box_in": (20.0, True, 40.0), "cooler_out": (30.0, True, 10.0)}


def test_by_default_the_first_place_that_passes_is_kept_and_the_next_is_not_refit(monkeypatch):
    fit, record, rejected, refit, _ = _discover(monkeypatch, PLACES, best_place=False)
    assert record["location"] == "supply_air" and record["accepted"] and fit.cost_holdout == 60.0
    assert refit == ["supply_air"] and rejected == [] and "places_passed" not in record


def test_with_best_place_the_lowest_held_out_error_among_the_places_refit_wins(monkeypatch):
    fit, record, rejected, refit, notes = _discover(monkeypatch, PLACES, best_place=True)
    # the places refit are the PLACES_TRIED best by the linear score; of those that pass, the lowest held-out cost
    assert refit == ["supply_air", "box_in"][:pipeline.PLACES_TRIED]
    assert record["location"] == "box_in" and record["accepted"] and fit.cost_holdout == 40.0
    assert [p["location"] for p in record["places_passed"]] == ["supply_air", "box_in"]
    assert any("supply_air passes too" in n for n in notes) and rejected == []


def test_with_best_place_a_place_that_fails_is_rejected_and_one_that_passes_kept(monkeypatch):
    places = {"supply_air": (10.0, False, 5.0), "box_in": (20.0, True, 40.0)}
    fit, record, rejected, refit, _ = _discover(monkeypatch, places, best_place=True)
    assert record["location"] == "box_in" and fit.cost_holdout == 40.0 and rejected == []
    places = {"supply_air": (10.0, False, 5.0), "box_in": (20.0, False, 40.0)}
    fit, record, rejected, refit, _ = _discover(monkeypatch, places, best_place=True)
    assert fit.cost_holdout == 100.0 and [r["location"] for _, r in rejected] == ["supply_air", "box_in"]


def test_best_place_must_be_a_bool(tmp_path):
    path = tmp_path / "log.csv"
    simulate_log(path, "nominal", duration_s=600, seed=3)
    with pytest.raises(TypeError, match="best_place"):
        pipeline.identify(load(path), best_place="yes")
