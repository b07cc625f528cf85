"""No wait for a predicted response once the dead time is found from a response and honoured
(``EkfSettings.response_wait_unseen_only``, a default; docs/robustness.md sec. 2.21).

Truth is the independent box (``hvac_mpc.mismatch``): open loop a box with a 2.5 s dead time, a duct losing 5 W/K,
valve curves shifted -8 % and a slower thermocouple (its valve gain and its air's flow dependence are not the
model's); closed loop box S0-8 of the seeded sweep (``python -m hvac_mpc.benchmarks.box_sweep --seed 0``): 2.2 s, 5.4
W/K, the literal cooler fit, valves -7.9 %, thermocouple x1.45.
Budget: the open loop about 2 s (two filters over 280 samples), the closed loop (two MPC runs of the quick proband
sequence, the baseline's IAE not needed) about 5 s.
"""

import numpy as np
import pytest

from ekf_helpers import feed_open_loop, quick_proband_on_sweep_box
from hvac_mpc.contract import Command
from hvac_mpc.mismatch import Variant, make_plant
from hvac_mpc.models import HvacModel, Parameters
from hvac_mpc.mpc.estimator import DisturbanceEkf, EkfSettings
from hvac_mpc.mpc.mpc_controller import MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings

HOLD_S = 40
#: (valve a %, blower W) held HOLD_S each: moves of valve a and of the flow together, as a proband sequence's steps.
MOVES = ((30.0, 200.0), (60.0, 200.0), (40.0, 100.0), (70.0, 100.0), (45.0, 200.0), (65.0, 60.0), (35.0, 150.0))
BOX = Variant(transport_delay_s=2.5, duct_loss_ua_w_per_k=5.0, valve_shift_pct=-8.0, thermocouple_tau_scale=1.4)


def open_loop(unseen_only: bool) -> list[tuple[float, bool, bool]]:
    """The filter fed open loop by BOX (inlet 32 C): per sample the mixed-air offset (degC), whether the supply
    reading is being waited for, and whether the dead-time estimate has seen a response. The heat flow into the mixed
    air off: with it (0.5 W per sample) the plain filter does not wait at the fifth move (seven samples without it),
    only one sample at the next, the heat carrying a share of the move of valve a and the flow together
    (docs/robustness.md sec. 2.29)."""
    plant = make_plant(BOX, seed=3)
    plant.set_environment(inlet_temp_c=32.0, chiller_setpoint_c=5.0)
    commands = [Command(blower, 0.0, a, 100.0, 100.0, 100.0) for a, blower in MOVES]
    plant.settle(commands[0])
    ekf = DisturbanceEkf(HvacModel(Parameters()), EkfSettings(response_wait_unseen_only=unseen_only,
                                                              q_supply_heat_w=0.0))
    rows: list = []
    feed_open_loop(ekf, plant, commands, HOLD_S,
                   lambda e: rows.append((e.mix_offset_c, e.response_wait.waiting, e.response_seen)))
    assert ekf.honoured_dead_time_s > 0.0  # the dead time is found and honoured
    return rows


def test_once_the_dead_time_is_found_the_offset_takes_a_gain_error_at_once():
    """Measured: the plain filter waits 7 samples at the fifth move (samples 203-209), long after the response that
    showed the dead time (sample 47), and its offset stays at -0.56 degC there; with the setting none begins after
    it, the offset moves from the move on, and its distance from where it settles over the 22 samples from the move
    is 17.0 -> 13.4 degC s. Before the response both filters are the same to the bit (the setting acts only after)."""
    plain, gated = open_loop(False), open_loop(True)
    seen = next(i for i, row in enumerate(plain) if row[2])
    waited = [i for i, row in enumerate(plain) if row[1] and i > seen]
    assert waited, "the plain filter waits after the dead time is found (the case the setting is for)"
    assert not any(row[1] for row in gated[seen:])
    first = waited[0]
    plain_off, gated_off = (np.array([row[0] for row in rows]) for rows in (plain, gated))
    assert np.array_equal(plain_off[:first], gated_off[:first])
    assert np.ptp(plain_off[first:waited[-1] + 1]) < 0.02  # held while it waits
    assert np.ptp(gated_off[first:waited[-1] + 1]) > 0.3

    def lag(off: np.ndarray) -> float:
        settled = off[(MOVES.index((65.0, 60.0)) + 1) * HOLD_S - 5:(MOVES.index((65.0, 60.0)) + 1) * HOLD_S].mean()
        return float(np.abs(off[first:first + 22] - settled).sum())
    assert first // HOLD_S == MOVES.index((65.0, 60.0))  # the wait is at the move of both valve a and the flow
    assert lag(gated_off) < 0.85 * lag(plain_off)


def test_on_by_default_and_checked():
    assert EkfSettings().response_wait_unseen_only is True
    for bad in (1, "yes", None):
        with pytest.raises(InvalidSettings, match="ekf.response_wait_unseen_only"):
            MpcSettings(ekf=EkfSettings(response_wait_unseen_only=bad))


def proband_on_s0_8(unseen_only: bool):
    """The quick proband sequence on box S0-8 of the seeded sweep, the MPC with or without the setting."""
    return quick_proband_on_sweep_box("S0-8", EkfSettings(response_wait_unseen_only=unseen_only))


@pytest.mark.slow
def test_s0_8_proband_loses_less_without_the_waits_after_the_dead_time():
    """Measured: the MPC's IAE 127.8 -> 121.3 C s (the baseline's 120.9: 1.057 -> 1.004 of it)."""
    plain, _ = proband_on_s0_8(False)
    gated, trace = proband_on_s0_8(True)
    assert gated < 0.97 * plain
    assert not any(trace.fallback)


def test_stop_ends_a_wait_and_compares_nothing_from_before():
    """A wait under way ends at ``stop``; the next sample starts none even where the prediction is far from the one
    before the stop (nothing from before it is compared), and the count of waits is kept."""
    from hvac_mpc.mpc.response_wait import ResponseWait
    rule = ResponseWait(trigger_c=0.2, share=0.5, min_samples=2, max_samples=7)
    assert not rule.observe(18.0, 18.0)
    assert rule.observe(17.0, 18.0)  # the prediction fell 1 degC, the reading stayed: a wait
    rule.stop()
    assert not rule.waiting and rule.waits == 1
    assert not rule.observe(15.0, 18.0)  # 2 degC from the last sample before the stop: not compared
    assert rule.observe(14.0, 18.0)  # the next predicted move starts a wait again
