"""A log that adds nothing: the model file holds the thesis value of every refit nominal parameter the log does not
move (docs/identification.md, "A log that adds nothing: the thesis values unless the log moves them").

The log comes from the independent box (``hvac_mpc.mismatch``, the nominal variant: the box's PTC fall is the
thesis's), identified from the documented physics, the fall included: the seed-5 log of the ``steps`` excitation runs
the heater body past the knee on its held-out rows only (from 6467 s, the heater up to 7 W below its command), and
identified without the fall it names the fall at the thesis's knee (identification/documented.py), so it adds nothing
only with the fall in. Slow: a 2 h log and a whole identification (about 25 s on the shared machine).
"""

import pytest

from hvac_mpc.identification import load_refined_model, write_model_file
from hvac_mpc.identification import pipeline
from hvac_mpc.identification.fitting import MOVED_Z
from hvac_mpc.identification.log_data import load
from hvac_mpc.identification.pipeline import DOCUMENTED_EFFECTS, identify
from hvac_mpc.identification.report import summary
from hvac_mpc.mismatch import simulate_log
from hvac_mpc.models import Parameters

WITHOUT_PTC = tuple(e for e in DOCUMENTED_EFFECTS if e != "ptc_power_fall")
#: The refit parameters the seed-5 log leaves within MOVED_Z standard errors of the thesis (measured: z between
#: -2.4 and +1.1); the flow equation's core loss moves (z -3.9, -12 %, on every log of the independent box).
NOT_MOVED = ("flow_per_watt_m3s_per_w", "motor_gain_max_c", "bypass_exponent", "cooler_slope", "heater_kp")


@pytest.fixture(scope="module")
def log_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("logs") / "nominal_seed5.csv"
    simulate_log(path, "nominal", duration_s=7200, seed=5)
    return path


@pytest.fixture(scope="module")
def identified(log_path):
    return identify(load(log_path), Parameters(), DOCUMENTED_EFFECTS, thesis_unless_moved=True)


def test_the_rule_is_reached_only_when_asked(tmp_path, monkeypatch):
    """Off by default: on a short log of the nominal box that adds nothing, ``identify`` writes the refit without
    reaching the rule, and with ``thesis_unless_moved=True`` reaches it once (a 20-minute log, quick fits)."""
    path = tmp_path / "nominal_short.csv"
    simulate_log(path, "nominal", duration_s=1200, seed=5)
    calls = []

    def spy(fitter, final, *args):
        calls.append(final)
        return final

    monkeypatch.setattr(pipeline, "_thesis_unless_moved", spy)
    res = identify(load(path), Parameters(), WITHOUT_PTC, quick=True, discover=False)
    assert res.accepted == [] and res.terms == ()  # nothing added: the case the rule is for
    assert calls == [] and res.written is None
    written = summary(res)["parameters_written"]  # what the file holds: the refit, where it differs from the base
    assert written and all(v["written"] == getattr(res.params, k) != v["base"] for k, v in written.items())
    identify(load(path), Parameters(), WITHOUT_PTC, quick=True, discover=False, thesis_unless_moved=True)
    assert len(calls) == 1


@pytest.mark.slow
def test_a_log_that_adds_nothing_writes_the_thesis_values_it_does_not_move(identified, tmp_path):
    res = identified
    assert res.accepted == [] and res.terms == ()
    thesis = Parameters()
    conf = {c["name"]: c for c in res.parameter_confidence}
    for name in NOT_MOVED:
        assert abs(conf[name]["z"]) <= MOVED_Z, conf[name]
        # the refit moved it a little; the file holds the thesis value
        assert res.final.p[res.fitter.names.index(name)] != getattr(thesis, name)
        assert getattr(res.params, name) == getattr(thesis, name), name
    # the parameter the log does move is refit with the others at their thesis values
    assert abs(conf["core_flow_loss"]["z"]) > MOVED_Z
    # (0.0851 refit with the others at their thesis values; the full refit's is 0.0883)
    assert res.params.core_flow_loss == pytest.approx(0.0851, abs=0.001)
    assert abs(res.params.core_flow_loss - res.final.p[res.fitter.names.index("core_flow_loss")]) > 0.002
    refined = load_refined_model(write_model_file(tmp_path / "m.toml", res.params, res.effects, res.extras,
                                                  res.terms, res.absent))
    assert {n: getattr(refined.parameters, n) for n in NOT_MOVED} == {n: getattr(thesis, n) for n in NOT_MOVED}
    # the written model predicts the held-out rows at the noise level: reverting costs nothing the log can show
    w = res.written["supply_temp_c"]
    assert w["rms_after"] <= 1.15 * res.sigma["supply_temp_c"], w
    written = summary(res)["parameters_written"]
    assert written["core_flow_loss"]["written"] == res.params.core_flow_loss and not set(NOT_MOVED) & set(written)
    note = next(n for n in res.notes if n.startswith("nothing added: the refit nominal parameters"))
    assert "do not pass the effects' gates" in note


@pytest.mark.slow
def test_a_refit_the_log_moves_is_written_as_it_is(identified):
    """Every refit parameter moved by the log (its confidence record says so): the final fit is the written model."""
    res = identified
    moved = [dict(c, z=10.0 * MOVED_Z, identified=True) for c in res.parameter_confidence]
    notes: list[str] = []
    assert pipeline._thesis_unless_moved(res.fitter, res.final, moved, Parameters(), False, notes) is res.final
    assert notes == []


@pytest.mark.slow
def test_the_reverted_block_is_kept_where_it_passes_the_effects_gates(identified):
    """The same rule on a thesis model that is far off (k_p 20 % low as the thesis value): the refit's k_p, though
    the confidence record is made to call it unmoved, passes the effects' gates as a block and the refit is kept."""
    res = identified
    base = Parameters().replace(heater_kp=0.8 * Parameters().heater_kp)
    unmoved = [dict(c, z=0.0) for c in res.parameter_confidence]
    notes: list[str] = []
    # the joint test alone already keeps k_p (it lies 20 % from the base value): take it out to reach the gates
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "_jointly_unmoved", lambda fitter, final, base, reverted, notes: (reverted, 0.0))
        out = pipeline._thesis_unless_moved(res.fitter, res.final, unmoved, base, False, notes)
    assert out is res.final
    assert any("pass the effects' gates together" in n for n in notes), notes
    # with the joint test k_p (its z made 0 here) is kept first at the refit's value, the core loss (its z too) next
    notes = []
    out = pipeline._thesis_unless_moved(res.fitter, res.final, unmoved, base, False, notes)
    assert any(n.startswith("nothing added: ['heater_kp'") and "jointly moved" in n for n in notes), notes
    assert out.p[res.fitter.names.index("heater_kp")] > 1.1 * base.heater_kp


def test_the_joint_wald_statistic_counts_the_estimates_correlation():
    """Two estimates correlated +0.98, each 2 standard errors from its start (within MOVED_Z alone): moved the same
    way they are jointly plausible (statistic 4.04 on 2 degrees of freedom), moved apart they are not (400); a
    log-transformed parameter is measured in log(p / p0)."""
    import math

    import numpy as np

    from hvac_mpc.identification.fitting import FreeParam, joint_wald

    free = [FreeParam("core_flow_loss", "lin", 0.05), FreeParam("cooler_slope", "lin", 0.05),
            FreeParam("heater_kp", "log")]
    cov = np.array([[1.0, 0.98, 0.0], [0.98, 1.0, 0.0], [0.0, 0.0, 0.01]])
    names = ["core_flow_loss", "cooler_slope", "heater_kp"]
    start = np.array([0.10, 0.75, 0.669])
    together = start + np.array([2 * 0.05, 2 * 0.05, 0.0])
    apart = start + np.array([2 * 0.05, -2 * 0.05, 0.0])
    pair = ["core_flow_loss", "cooler_slope"]
    assert joint_wald(cov, free, together, start, names, pair) == pytest.approx(0.16 / 0.0396, rel=1e-9)
    assert joint_wald(cov, free, apart, start, names, pair) == pytest.approx(15.84 / 0.0396, rel=1e-9)
    kp = start.copy()
    kp[2] = 0.669 * math.exp(0.1)
    assert joint_wald(cov, free, kp, start, names, ["heater_kp"]) == pytest.approx(1.0, rel=1e-9)
    assert joint_wald(cov, free, kp, start, names, []) == 0.0


def test_a_block_each_unmoved_alone_but_jointly_moved_keeps_the_parameter_that_moves_it(monkeypatch):
    """The reverted block shrinks until its joint test passes: three parameters each 2 standard errors from the
    thesis, two of them correlated +0.98 and moved apart (jointly far outside), keep the one whose leaving lowers
    the statistic most, say so, and revert the rest (their statistic within the chi-square bound)."""
    from types import SimpleNamespace

    import numpy as np

    thesis = Parameters()
    base_vec = np.array(thesis.vector())
    all_names = list(Parameters.scalar_names())
    p = base_vec.copy()
    p[all_names.index("core_flow_loss")] += 2 * 0.05
    p[all_names.index("cooler_slope")] -= 2 * 0.05
    p[all_names.index("heater_kp")] *= np.exp(2 * 0.1)
    free = ["core_flow_loss", "cooler_slope", "heater_kp"]
    cov = np.diag([1.0, 1.0, 0.01])
    cov[0, 1] = cov[1, 0] = 0.98
    monkeypatch.setattr(pipeline, "parameter_covariance", lambda fitter, final, fps: cov)
    fitter = SimpleNamespace(names=all_names)
    final = SimpleNamespace(p=p, free=free)
    notes: list[str] = []
    block, wald = pipeline._jointly_unmoved(fitter, final, thesis, sorted(free), notes)
    assert len(block) == 2 and "heater_kp" in block
    assert wald == pytest.approx(8.0, rel=1e-6)  # two uncorrelated 2-sigma moves: 4 + 4, within the bound 9.2
    assert len(notes) == 1 and "jointly moved by the log" in notes[0]
    # moved together, the block holds as it is
    p[all_names.index("cooler_slope")] += 4 * 0.05
    notes = []
    block, wald = pipeline._jointly_unmoved(fitter, final, thesis, sorted(free), notes)
    assert sorted(block) == sorted(free) and notes == []


def test_the_rule_is_off_by_default_and_refuses_a_non_boolean():
    """Off unless asked: ``identify`` without it writes the refit (the rule is reached only with the flag), and a
    non-boolean is refused naming the argument."""
    import inspect

    from hvac_mpc.identification import identify as api_identify

    for fn in (identify, api_identify):
        assert inspect.signature(fn).parameters["thesis_unless_moved"].default is False
    with pytest.raises(TypeError, match="thesis_unless_moved must be True or False"):
        identify(None, thesis_unless_moved="yes")


def test_refined_variants_passes_the_log_excitation_and_refuses_an_unknown_one(tmp_path, monkeypatch, capsys):
    """``refined_variants --excitation hot_heater`` identifies a log of that excitation (the PTC fall's log); an
    unknown excitation is refused naming the allowed ones."""
    from hvac_mpc.benchmarks import refined_variants

    seen = {}

    class Stop(Exception):
        pass

    def fake_log(path, variant, duration_s, seed, excitation):
        seen.update(variant=variant, excitation=excitation)
        raise Stop

    monkeypatch.setattr(refined_variants, "simulate_log", fake_log)
    with pytest.raises(Stop):
        refined_variants.main(["--variant", "ptc_fall", "--excitation", "hot_heater"])
    assert seen == {"variant": "nominal", "excitation": "hot_heater"}
    with pytest.raises(SystemExit):
        refined_variants.main(["--variant", "ptc_fall", "--excitation", "warm"])
    assert "hot_heater" in capsys.readouterr().err
