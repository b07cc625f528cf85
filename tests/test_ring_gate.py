"""The ringing gate (``MpcSettings.ring_*``, :mod:`hvac_mpc.mpc.ring_gate`; docs/robustness.md sec. 2.12).

Truth for the closed loop is the independent box (``hvac_mpc.mismatch``): a box outside the registry (4.5 s
dead time, the literal cooler fit, a thermocouple 30 % faster) on which the MPC rings in heating. Budget: the
gate's own tests take milliseconds; the closed loop two quick heating runs of the MPC (a few seconds).
"""

import functools
import math

import numpy as np
import pytest

from hvac_mpc.benchmarks import bench, mismatch_suite, plant_seam, scenarios
from hvac_mpc.benchmarks.simulate import plant_seed, simulate
from hvac_mpc.mismatch import make_plant
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings
from hvac_mpc.mpc.ring_gate import RingGate

RINGING_BOX = "R4:transport_delay_s=4.5,thermocouple_tau_scale=0.7,cooler_literal_fit=true"


def factors(errors, **kw):
    """The gate's factor after each sample of a supply error (degC) about a reference of 12 degC."""
    args = dict(amplitude_c=0.6, window_s=40.0, crossings=3, detune=0.5, floor=0.05, relax_s=30.0)
    gate = RingGate(**{**args, **kw})
    out = []
    for e in errors:
        gate.push(12.0 + e, 12.0)
        out.append(gate.factor)
    return np.array(out)


def test_noise_and_a_damped_step_leave_the_rates_alone():
    rng = np.random.default_rng(0)
    assert np.all(factors(0.1 * rng.standard_normal(300)) == 1.0)  # noise inside the band (the box: 0.05 C)
    t = np.arange(120.0)
    damped = -3.0 * np.exp(-t / 8.0) * np.cos(2 * np.pi * t / 16.0)  # a step answered with two swings
    assert np.all(factors(damped) == 1.0)
    assert np.all(factors([math.nan] * 50 + [2.0, -2.0] * 5)[:50] == 1.0)  # a missing reading is skipped


def test_a_sustained_swing_lowers_the_rates_to_the_floor_and_quiet_restores_them():
    t = np.arange(200.0)
    ringing = 2.0 * np.sin(2 * np.pi * t / 16.0)
    f = factors(np.concatenate([ringing, np.zeros(300)]))
    first = int(np.argmax(f < 1.0))
    assert 16 <= first <= 30  # the third swing, within two periods
    assert f[199] == pytest.approx(0.05)  # each further swing halves it, down to the floor
    assert np.allclose(f[200:222], 0.05)  # held for the relax time (30 s) from the last swing, at most 8 s before
    assert f[-1] == 1.0 and np.all(np.diff(f[200:]) >= 0.0)  # then doubling back to 1


def test_ring_settings_are_checked():
    for field, bad in (("ring_detune", 0.0), ("ring_detune", 1.5), ("ring_amplitude_c", -1.0),
                       ("ring_window_s", 0.5), ("ring_crossings", 0), ("ring_floor", 0.0), ("ring_relax_s", 0.1)):
        with pytest.raises(InvalidSettings, match=f"MpcSettings.{field}"):
            MpcSettings(**{field: bad})
    assert MpcController(settings=MpcSettings()).ring is None  # off by default


def heating_run(ring_detune: float, **settings):
    """The quick winter heating steps on the ringing box (seed 0): the MPC's thermocouple IAE (degC s) over
    the scored part, its valve a commands (%) and the gate's least factor. Without the online choice of the heater
    outlet error's placement (``MpcSettings.choose_offset_placement``, docs/robustness.md sec. 2.14), which takes
    the ringing at its cause (2.33 -> 1.43 of the baseline's IAE on this box): the gate is measured on the loop
    that rings. ``settings``: further ``MpcSettings`` fields."""
    label, variant = mismatch_suite.parse_box(RINGING_BOX)
    sc = scenarios.mismatch_scenarios()["winter_heating_steps"].quick()
    plant = plant_seam.build_plant(functools.partial(make_plant, variant), plant_seed(0, sc.seed), 1.0)
    settings = MpcSettings(initial_command=sc.initial_command, deadline_s=bench.DETERMINISTIC_DEADLINE_S,
                           ring_detune=ring_detune, choose_offset_placement=False, **settings)
    ctrl = MpcController(Parameters(), settings)
    least = [1.0]
    step = ctrl.step

    def watched(measurement, reference):
        out = step(measurement, reference)
        least[0] = min(least[0], ctrl.ring.factor if ctrl.ring is not None else 1.0)
        return out

    ctrl.step = watched
    tr = simulate(sc, ctrl, Parameters(), 0, name="mpc", dt_s=1.0, plant=plant)
    scored = tr.time_s >= tr.metrics_start_s
    iae = float(np.sum(np.abs(tr.truth["supply_temp_c"] - tr.reference["supply_temp_c"])[scored]))
    return iae, tr.applied[:, 2], least[0]


@pytest.mark.slow
def test_the_gate_damps_the_ringing_on_a_box_whose_valve_gain_is_not_the_model():
    """Without the gate valve a swings between its ends all through the scored part and the MPC's IAE is 2.33 of
    the baseline's; with ``ring_detune`` 0.5 the gate reaches its floor, valve a's moves after the first minute
    stay within the slowed rate, and the IAE falls to 0.67 of the ungated (1.55 of the baseline's; measured).
    Without the start-up's caution (``start_rate_share`` 1), as measured: see the next test with the caution."""
    plain_iae, plain_a, plain_least = heating_run(1.0, start_rate_share=1.0)
    gated_iae, gated_a, least = heating_run(0.5, start_rate_share=1.0)
    assert plain_least == 1.0 and least == pytest.approx(0.05)
    assert np.max(np.abs(np.diff(plain_a[60:]))) > 40.0
    assert np.max(np.abs(np.diff(gated_a[60:]))) < 10.0
    assert gated_iae < 0.75 * plain_iae


@pytest.mark.slow
def test_the_gate_damps_the_ringing_with_the_start_caution():
    """The same runs with the start-up's caution (``start_rate_share`` 0.4, docs/robustness.md sec. 2.27). Here the caution's
    bound never binds: the start closes valve a (10 -> 0 %) and holds it shut until the caution ends by its duration
    (10 s, the 4.5 s dead time not yet honoured). The bound in the first QPs moves their answers within the solver's
    tolerance, and the ringing loop takes another way from 11 s (valve a 57 against 59 %, 0 against 67 % at 20 s):
    measured, the ungated IAE 172.0 -> 132.7 degC s, the gated 118.0 -> 102.0 (0.77 of the ungated), the gate's
    least factor 0.125 (three swings) instead of its floor. The gate still halves the rates and holds valve a's
    moves after the first minute within the slowed rate."""
    plain_iae, plain_a, plain_least = heating_run(1.0, start_rate_share=0.4)
    gated_iae, gated_a, least = heating_run(0.5, start_rate_share=0.4)
    assert plain_least == 1.0 and least <= 0.125 + 1e-9
    assert np.max(np.abs(np.diff(plain_a[60:]))) > 40.0
    assert np.max(np.abs(np.diff(gated_a[60:]))) < 10.0
    assert gated_iae < 0.85 * plain_iae
