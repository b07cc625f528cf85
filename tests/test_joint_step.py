"""The joint refit's bookkeeping on its edge cases (identification/joint_step.py), with a stand-in fitter whose
held-out supply cost is known in closed form: the noise level (1 per sample) plus, for each structure entry missing
from a fit's effects, that entry's cost. No simulation: the elimination, the decision and the failure path are what
is tested; the whole step on a measured log is the slow test in tests/test_data_loop.py.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from hvac_mpc.identification import joint_step as joint_step_module
from hvac_mpc.identification import workers
from hvac_mpc.identification.candidates import library
from hvac_mpc.identification.fitting import Fit
from hvac_mpc.identification.joint_step import joint_step
from hvac_mpc.identification.pipeline import _backward, _same_fit, joint_after_pairs
from hvac_mpc.identification.selection import (CONTRIBUTION_MIN, STRUCTURE_MIN, CandidateResult, contribution,
                                                 correction_correlation)
from hvac_mpc.identification.simulator import OutputPost
from hvac_mpc.models import Parameters
from hvac_mpc.models.discovered import DiscoveredTerm

OUTPUTS = ("supply_temp_c",)
#: Library candidates with effects of their own (the stand-in's cost depends on the effects in a fit).
MEMBERS = ("motor_asymmetry", "bypass_flow", "trapped_air")


class _StandInFitter:
    """``fit`` returns the held-out (and training) supply cost 1 + the structure of the effects left out; an effect
    in ``fail`` makes the fit raise, as a diverging simulation does."""

    outputs = list(OUTPUTS)
    names = Parameters.scalar_names()

    def __init__(self, structure: dict[str, float], fail: tuple[str, ...] = ()):
        self.structure, self.fail = structure, fail
        self.log = SimpleNamespace(dt_s=1.0, holdout=np.array([True]))
        self.y_meas = np.zeros((1, 1))

    def make(self, effects, p: np.ndarray, post: OutputPost) -> Fit:
        c = 1.0 + sum(v for k, v in self.structure.items() if k not in effects)
        return Fit(frozenset(effects), p.copy(), post.copy(), (), np.array([[c]]), None, c, c, 1, 1)

    def fit(self, effects, p, free, post, bias_outputs=(), max_nfev=0, gain_outputs=None, terms=None) -> Fit:
        if set(effects) & set(self.fail):
            raise np.linalg.LinAlgError("singular step")
        return self.make(effects, p, post)


    def evaluate(self, effects, p, post, free=(), nfev=0, message="", terms=()) -> Fit:
        return self.make(effects, p, post)

    def output_costs(self, y, part="holdout"):
        return np.array([y[0, 0]]), np.array([1.0])


def _case(structure: dict[str, float], fail: tuple[str, ...] = (), max_effects: int = 4, members=MEMBERS):
    """The step on a forward path that kept nothing, the last round's candidates ``members`` (each moved its
    parameters, each removed 20 % of the training cost)."""
    fitter = _StandInFitter(structure, fail)
    base = Parameters()
    p0 = np.array(base.vector(), dtype=float)
    post = OutputPost(OUTPUTS, np.array([0.0, 1.0]))
    lib = library(OUTPUTS)
    current = fitter.make(frozenset(), p0, post)
    open_round = []
    for name in members:
        cand = next(c for c in lib if c.name == name)
        p = p0.copy()
        for fp in cand.params:
            p[fitter.names.index(fp.name)] *= 1.5
        open_round.append(CandidateResult(name, cand.kind, 1, "rejected", params={fp.name: 0.0 for fp in cand.params},
                                          train_reduction=0.2, primary_output="supply_temp_c",
                                          fit=fitter.make(frozenset(cand.effects), p, post)))
    notes: list[str] = []
    out = joint_step(fitter, current, [], [], open_round, lib, base, max_effects, 2,
                     lambda fit, free, log: (fit, None, []), lambda _msg: None, notes)
    return current, out, notes


def test_the_joint_set_keeps_the_members_that_earn_their_share_and_eliminates_the_passenger():
    current, (fit, free, kept, term, record), notes = _case({"motor_asymmetry": 4.0, "trapped_air": 3.0,
                                                             "bypass_flow": 0.01})
    assert record["accepted"] and fit is not current
    assert [a.name for a in kept] == ["motor_asymmetry", "trapped_air"]
    assert "bypass_flow" not in fit.effects and record["shares"]["bypass_flow"] < 0.1
    assert record["supply_rms_after"] < record["supply_rms_before"]
    assert notes[-1].startswith("joint refit of") and "kept" in notes[-1]  # the verdict after the elimination's notes
    assert any("bypass_flow eliminated" in n for n in notes[:-1])


def test_after_the_first_round_only_the_members_near_their_need_are_refit(monkeypatch):
    # four members, one passenger: the first round refits all four, the second only the one whose margin was small
    monkeypatch.setattr(joint_step_module, "JOINT_CANDIDATES", 4)
    members = ("motor_asymmetry", "bypass_flow", "trapped_air", "ptc_power_fall")
    structure = {"motor_asymmetry": 4.0, "trapped_air": 3.0, "ptc_power_fall": 0.1, "bypass_flow": 0.01, "other": 0.5}
    _, (fit, _, kept, _, record), _ = _case(structure, members=members)
    assert [a.name for a in kept] == ["motor_asymmetry", "trapped_air", "ptc_power_fall"]
    assert [list(r["refit"]) for r in record["elimination"]] == [list(members), ["ptc_power_fall"]]
    assert record["shares"]["ptc_power_fall"] == pytest.approx(0.1 / 0.61)  # its share in the second round


def test_a_member_far_above_its_need_is_refit_again_when_too_many_are_left(monkeypatch):
    monkeypatch.setattr(joint_step_module, "JOINT_CANDIDATES", 4)
    members = ("motor_asymmetry", "bypass_flow", "trapped_air", "ptc_power_fall")
    structure = {"motor_asymmetry": 4.0, "trapped_air": 3.0, "ptc_power_fall": 2.0, "bypass_flow": 1.0, "other": 0.5}
    _, (fit, _, kept, _, record), _ = _case(structure, members=members, max_effects=2)
    assert [a.name for a in kept] == ["motor_asymmetry", "trapped_air"]
    assert "bypass_flow" not in fit.effects and "ptc_power_fall" not in fit.effects
    assert [list(r["refit"]) for r in record["elimination"]] == [list(members), [], []]


def test_at_most_max_effects_are_kept_even_when_more_earn_their_share():
    _, (fit, _, kept, _, record), _ = _case({"motor_asymmetry": 4.0, "trapped_air": 3.0, "bypass_flow": 2.0},
                                            max_effects=1)
    assert len(kept) == 1 and record["kept"] == [kept[0].name]
    assert any("at most 1 effects" in n for n in record["notes"])


def test_every_member_eliminated_leaves_the_forward_path_when_nothing_is_gained():
    current, (fit, free, kept, term, record), notes = _case({"other": 5.0, "motor_asymmetry": 0.01,
                                                             "trapped_air": 0.01, "bypass_flow": 0.01})
    assert record["kept"] == [] and not record["accepted"]
    assert fit is current and kept == [] and term is None
    assert "not kept" in notes[-1]


def test_a_fit_that_fails_leaves_the_forward_path_and_says_why():
    current, (fit, free, kept, term, record), notes = _case({"motor_asymmetry": 4.0, "trapped_air": 3.0},
                                                            fail=("bypass_flow",))
    assert fit is current and kept == [] and term is None
    assert not record["accepted"] and "singular step" in record["failed"]
    assert "fit failed" in notes[-1]


def test_no_candidate_of_the_last_round_means_no_step():
    fitter = _StandInFitter({"other": 5.0})
    base = Parameters()
    current = fitter.make(frozenset(), np.array(base.vector(), dtype=float), OutputPost(OUTPUTS, np.array([0.0, 1.0])))
    out = joint_step(fitter, current, [], [], [], library(OUTPUTS), base, 4, 2, lambda f, fr, log: (f, None, []),
                     lambda _msg: None, [])
    assert out[0] is current and out[3] is None and out[4] is None


def test_effects_kept_in_one_fit_make_one_step():
    a, b = object(), object()
    res = [CandidateResult(n, "model", 1, "accepted", fit=f) for n, f in (("x", a), ("y", b), ("z", b), ("w", None))]
    assert [[r.name for r in g] for g in _same_fit(res)] == [["x"], ["y", "z"], ["w"]]


def _task(i: int) -> int:
    if i == 2:
        raise ValueError("fit of task 2 failed")
    return i * i


def test_forked_map_returns_in_order_and_passes_a_workers_error_on():
    assert workers.fork_map(lambda i: i * i, 5) == [0, 1, 4, 9, 16]
    with pytest.raises(ValueError, match="task 2"):
        workers.fork_map(_task, 4)
    assert workers._TASK is None  # nothing of the failed map left for the next


def test_the_joint_refit_runs_after_a_pair_with_a_term_and_not_after_a_pair_of_effects():
    round_ = [CandidateResult("bypass_flow", "model", 1, "rejected")]
    pair = [CandidateResult("valve_shift:a", "parameter", 2, "accepted", jointly_with="term supply_residual_term")]
    assert joint_after_pairs(round_, [], None) is round_  # no pair kept
    assert joint_after_pairs(round_, pair, {"accepted": True, "jointly_with": "valve_shift:a"}) is round_
    assert joint_after_pairs(round_, pair + pair, None) is None  # two library effects kept together


def test_a_pairs_term_replaced_by_the_joint_model_is_said_and_its_partner_kept_without_it():
    """The forward path kept ``trapped_air`` only jointly with a discovered term (the pair step); the joint refit,
    without the term, keeps ``trapped_air`` and ``motor_asymmetry``: the partner no longer says it was kept only
    jointly, its step is the joint fit (with the effect the joint refit added), and the replaced term is named."""
    fitter = _StandInFitter({"motor_asymmetry": 4.0, "trapped_air": 3.0, "bypass_flow": 0.01})
    fitter.sigma = np.array([1.0])
    base = Parameters()
    p0 = np.array(base.vector(), dtype=float)
    post = OutputPost(OUTPUTS, np.array([0.0, 1.0]))
    lib = library(OUTPUTS)
    term = DiscoveredTerm("supply_residual_term", "supply_air", ("mix", "one"), (-0.1, 1.0))
    with_term = fitter.make(frozenset({"trapped_air"}), p0, post)
    current = Fit(with_term.effects, p0, post, (), np.array([[4.5]]), None, 4.5, 4.5, 1, 1, terms=(term,))
    partner = CandidateResult("trapped_air", "model", 2, "accepted", params={"trap_air_mass_kg": 0.0},
                              primary_output="supply_temp_c", jointly_with="term supply_residual_term", fit=current,
                              reason="accepted only jointly with term supply_residual_term")
    open_round = [CandidateResult("motor_asymmetry", "model", 1, "rejected", train_reduction=0.2,
                                  params={"tau_motor_heating_s": 0.0, "tau_motor_cooling_s": 0.0},
                                  primary_output="supply_temp_c", fit=fitter.make(frozenset({"motor_asymmetry"}), p0,
                                                                                  post))]
    notes: list[str] = []
    fit, _, kept, _, record = joint_step(fitter, current, [], [partner], open_round, lib, base, 4, 3,
                                         lambda f, fr, log: (f, None, []), lambda _msg: None, notes)
    assert record["accepted"] and [a.name for a in kept] == ["trapped_air", "motor_asymmetry"]
    assert kept[0].jointly_with == "" and "kept in the joint refit without the term" in kept[0].reason
    assert kept[0].fit is kept[1].fit and kept[0].fit is not current  # one step: the joint fit
    (replaced,) = record["replaced_terms"]
    assert replaced["name"] == "supply_residual_term" and "correlation" in replaced  # its value: the test below
    assert any(n.startswith("joint refit: replaces term dT_supply_air") for n in notes), notes


def test_the_correlation_of_two_corrections_is_taken_on_the_held_out_rows_over_the_noise():
    fitter = SimpleNamespace(sigma=np.array([0.05, 2.0]), log=SimpleNamespace(holdout=np.array([False, True, True, True])))
    post = OutputPost(OUTPUTS, np.array([0.0, 1.0]))
    fit = lambda y: Fit(frozenset(), np.zeros(1), post, (), np.asarray(y, float), None, 0.0, 0.0, 1, 1)  # noqa: E731
    current = fit(np.zeros((4, 2)))
    a = fit([[9.0, 9.0], [0.05, 0.0], [0.0, 0.0], [-0.05, 0.0]])  # the training row does not count
    same = fit([[-9.0, 0.0], [0.1, 0.0], [0.0, 0.0], [-0.1, 0.0]])  # twice a's held-out correction
    other = fit([[0.0, 0.0], [0.0, 0.0], [0.1, 0.0], [0.0, 0.0]])  # on a row where a's is zero
    assert correction_correlation(fitter, a, same, current) == pytest.approx(1.0)
    assert correction_correlation(fitter, a, other, current) == pytest.approx(0.0)
    assert correction_correlation(fitter, a, fit(-np.asarray(same.y)), current) == pytest.approx(-1.0)


def test_an_effects_contribution_is_its_mean_square_change_over_the_noise_on_the_output_it_moves_most():
    fitter = SimpleNamespace(sigma=np.array([0.05, 2.0]), log=SimpleNamespace(holdout=np.array([False, True, True, True])))
    post = OutputPost(OUTPUTS, np.array([0.0, 1.0]))
    y = np.array([[9.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    moved = y + np.array([[5.0, 5.0], [0.01, 2.0], [np.nan, 2.0], [-0.01, -2.0]])  # the training row does not count
    fits = [Fit(frozenset(), np.zeros(1), post, (), yy, None, 0.0, 0.0, 1, 1) for yy in (moved, y)]
    # supply: (0.01 / 0.05)^2 = 0.04 on its two readings; the other output (2 / 2)^2 = 1 on three
    assert contribution(fitter, *fits) == pytest.approx(1.0)
    fits[0].y[:, 1] = 0.0
    assert contribution(fitter, *fits) == pytest.approx(0.04)
    assert CONTRIBUTION_MIN == pytest.approx(STRUCTURE_MIN - 1.0)  # derived, not a setting of its own


def test_the_backward_pass_drops_an_effect_whose_own_contribution_is_below_the_noise_resolution():
    """``bypass_flow`` earns 14 % of the held-out structure (above the 10 % share) but changes the readings by 0.08
    noise SDs, a mean square of 0.0064 (below 0.1): dropped; ``motor_asymmetry`` (4 SDs) kept."""
    fitter = _StandInFitter({"motor_asymmetry": 4.0, "bypass_flow": 0.08, "other": 0.5})
    fitter.sigma = np.array([1.0])
    base = Parameters()
    post = OutputPost(OUTPUTS, np.array([0.0, 1.0]))
    current = fitter.make(frozenset({"motor_asymmetry", "bypass_flow"}), np.array(base.vector(), dtype=float), post)
    accepted = [CandidateResult(n, "model", 1, "accepted", primary_output="supply_temp_c")
                for n in ("motor_asymmetry", "bypass_flow")]
    notes: list[str] = []
    fit, _ = _backward(fitter, current, [], accepted, library(OUTPUTS), base, False, lambda _m: None, notes)
    assert [a.name for a in accepted] == ["motor_asymmetry"] and "bypass_flow" not in fit.effects
    dropped = next(n for n in notes if n.startswith("backward pass: bypass_flow removed"))
    assert "0.006 times the noise variance" in dropped
    assert accepted[0].contribution == pytest.approx(16.0)
