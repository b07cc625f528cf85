"""Heater reserve (mpc/reserve.py): the gate gives valve a the reserve's weight only at rest on a heating reference,
with the heater not limiting and the flow priority untouched, and drops it at a reference change; on the independent
box with the thesis's literal cooler (hvac_mpc.mismatch ``cooler_literal``) an MPC whose model has that cooler holds
the heater body warmer before a step up and serves the step faster."""

import pytest

from heater_body_helpers import body_at_step_and_iae

from hvac_mpc.models.model_file import RefinedModel
from hvac_mpc.models.parameters import Parameters
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings, OcpSpec, Weights
from hvac_mpc.mpc.reserve import HEADROOM_W, KNEE_MARGIN_C, PTC_SHORTFALL_W, REST_HOLD_S, HeaterReserve

RESERVE, HEATING = 3e-4, 3e-5
#: The step up to 15 C of the quick winter_heating_steps (s).
STEP_UP_S = 90


def _gate() -> HeaterReserve:
    return HeaterReserve(RESERVE, HEATING, 1.0)


def _step(gate: HeaterReserve, ref_c: float = 12.0, reading_c: float = 12.0, heating: bool = True,
          cmd_w: float = 100.0, flow_factor: float = 1.0) -> float:
    return gate.weight(supply_ref_c=ref_c, flow_ref_m3s=40.0 / 3600.0, reading_c=reading_c, heating=heating,
                       heater_cmd_w=cmd_w, available_w=240.0, flow_factor=flow_factor)


def test_the_reserve_counts_after_the_hold_at_rest_and_ends_at_a_reference_change():
    gate = _gate()
    hold = int(REST_HOLD_S)
    weights = [_step(gate) for _ in range(hold + 2)]
    assert weights[:hold - 1] == [HEATING] * (hold - 1)  # the first sample is the reference's change
    assert weights[-1] == RESERVE and gate.on
    assert _step(gate, reading_c=12.8) == RESERVE  # hysteresis: inside the wider band once at rest
    assert _step(gate, reading_c=13.2) == HEATING  # out of it
    for _ in range(hold + 1):
        _step(gate)
    assert gate.on
    assert _step(gate, ref_c=15.0, reading_c=12.0) == HEATING  # a step up is served with the default weight
    assert _step(gate, ref_c=15.0, reading_c=15.0) == HEATING  # and the hold starts again
    assert _step(gate, heating=False) == 0.0 and not gate.on
    for _ in range(hold + 1):
        _step(gate, ref_c=float("nan"))  # no supply reference: never at rest
    assert not gate.on


def test_the_reserve_starts_only_where_the_heater_has_room_and_the_flow_priority_is_untouched():
    hold = int(REST_HOLD_S) + 2
    limited, traded, free = _gate(), _gate(), _gate()
    for _ in range(hold):
        _step(limited, cmd_w=240.0 - HEADROOM_W + 1.0)
        _step(traded, flow_factor=0.5)
        _step(free, cmd_w=240.0 - HEADROOM_W - 1.0)
    assert not limited.on and not traded.on and free.on
    # once at rest the reserve itself runs the heater high while the body takes up heat: it stays on
    assert _step(free, cmd_w=240.0) == RESERVE
    assert _step(free, flow_factor=0.5) == HEATING


def test_the_reserve_ends_where_the_box_heater_draws_less_than_its_command():
    """The measured heater power below the command: the body is past the PTC knee, whatever its estimate."""
    gate = _gate()
    for _ in range(int(REST_HOLD_S) + 1):
        gate.weight(supply_ref_c=15.0, flow_ref_m3s=0.011, reading_c=15.0, heating=True, heater_cmd_w=190.0,
                    available_w=240.0, flow_factor=1.0, heater_power_w=189.0)
    assert gate.on
    w = gate.weight(supply_ref_c=15.0, flow_ref_m3s=0.011, reading_c=15.0, heating=True, heater_cmd_w=190.0,
                    available_w=240.0, flow_factor=1.0, heater_power_w=190.0 - PTC_SHORTFALL_W - 1.0)
    assert w == HEATING and not gate.on


def _ptc_step(gate: HeaterReserve, power_w: float) -> float:
    return gate.weight(supply_ref_c=15.0, flow_ref_m3s=0.011, reading_c=15.0, heating=True, heater_cmd_w=190.0,
                       available_w=240.0, flow_factor=1.0, heater_power_w=power_w)


def test_the_ptc_hold_keeps_the_reserve_out_after_the_box_heater_drew_less_than_its_command():
    """``ptc_hold_s``: after a step with the measured shortfall the rest does not count for that many seconds (the
    command lowered below the PTC line ends the shortfall, not the body's heat); without it (the default) the rest
    counts again at once and the reserve is back after REST_HOLD_S."""
    short_w = 190.0 - PTC_SHORTFALL_W - 1.0
    hold = int(REST_HOLD_S)
    plain, held = _gate(), HeaterReserve(RESERVE, HEATING, 1.0, ptc_hold_s=30.0)
    for gate in (plain, held):
        for _ in range(hold + 1):
            _ptc_step(gate, 190.0)
        assert gate.on
        assert _ptc_step(gate, short_w) == HEATING and not gate.on
    plain_w = [_ptc_step(plain, 190.0) for _ in range(hold + 1)]
    assert plain_w[-1] == RESERVE  # back after the rest's hold
    held_w = [_ptc_step(held, 190.0) for _ in range(29 + hold + 1)]
    assert set(held_w[:29 + hold - 1]) == {HEATING}  # 29 s more of the hold, then the rest's own hold
    assert held_w[-1] == RESERVE and held.on
    assert _ptc_step(held, short_w) == HEATING
    held.reset()
    assert [_ptc_step(held, 190.0) for _ in range(hold + 1)][-1] == RESERVE  # a reset forgets the shortfall


def test_the_reserve_ends_at_the_ptc_knee_and_starts_again_below_it():
    """A body estimated past the PTC knee is as hot as is of use; the reserve starts again KNEE_MARGIN_C below it."""
    def step(gate, body_c):
        return gate.weight(supply_ref_c=15.0, flow_ref_m3s=0.011, reading_c=15.0, heating=True, heater_cmd_w=150.0,
                           available_w=240.0, flow_factor=1.0, body_c=body_c, knee_c=60.0)

    gate = _gate()
    for _ in range(int(REST_HOLD_S) + 1):
        step(gate, 50.0)
    assert gate.on
    assert step(gate, 59.0) == RESERVE
    assert step(gate, 60.5) == HEATING and not gate.on
    for _ in range(int(REST_HOLD_S) + 1):
        step(gate, 57.0)  # below the knee, within the margin: not again
    assert not gate.on
    for _ in range(int(REST_HOLD_S) + 1):
        step(gate, 60.0 - KNEE_MARGIN_C - 0.5)
    assert gate.on


def test_the_entry_ramps_the_weight_in_over_the_rest_and_starts_again_at_the_next_rest():
    """``ramp_s``: the reserve's weight rises in a straight line from the heating weight over the rest's first
    seconds; a reference change ends the rest and the next rest ramps again."""
    gate = HeaterReserve(RESERVE, HEATING, 1.0, ramp_s=10.0)
    weights = [_step(gate) for _ in range(int(REST_HOLD_S) + 12)]
    ramp = [w for w in weights if w != HEATING]
    assert gate.on and ramp[-1] == RESERVE
    assert ramp[0] == pytest.approx(HEATING + (RESERVE - HEATING) / 10.0)  # the first second of the rest
    assert all(b > a for a, b in zip(ramp[:10], ramp[1:10]))  # rising, the full weight after 10 s
    assert ramp[9] == pytest.approx(RESERVE)
    _step(gate, ref_c=15.0, reading_c=15.0)
    again = [_step(gate, ref_c=15.0, reading_c=15.0) for _ in range(int(REST_HOLD_S) + 1)]
    assert again[-2:] == pytest.approx([HEATING + (RESERVE - HEATING) * k / 10.0 for k in (1, 2)])


def test_the_entry_withholds_the_weight_while_the_heater_limits_and_the_reading_is_short():
    """``short_c``: at rest, the heater within HEADROOM_W of its available power and the reading more than
    ``short_c`` below the reference, valve a gets the heating weight (the rest goes on, the ramp waits)."""
    gate = HeaterReserve(RESERVE, HEATING, 1.0, ramp_s=4.0, short_c=0.05)
    for _ in range(int(REST_HOLD_S) + 1):
        _step(gate)
    first = _step(gate, cmd_w=240.0)
    assert HEATING < first < RESERVE
    assert _step(gate, cmd_w=240.0, reading_c=11.9) == HEATING and gate.on and gate.withheld
    # not limiting: counted, the ramp goes on from where it stood before the withheld step (had that step
    # counted, the weight here would be the reserve's, 3e-4)
    assert _step(gate, cmd_w=200.0, reading_c=11.9) == pytest.approx(HEATING + 0.75 * (RESERVE - HEATING))
    assert _step(gate, cmd_w=240.0, reading_c=11.97) > first and not gate.withheld  # within the threshold
    off = HeaterReserve(RESERVE, HEATING, 1.0)  # the rule off: the weight whatever the reading
    for _ in range(int(REST_HOLD_S) + 1):
        _step(off)
    assert _step(off, cmd_w=240.0, reading_c=11.6) == RESERVE and not off.withheld


def test_the_weight_is_a_checked_setting_off_by_default():
    assert Weights().valve_a_reserve_per_pct2 == 0.0
    assert MpcController().reserve is None
    with pytest.raises(InvalidSettings, match="valve_a_reserve_per_pct2"):
        OcpSpec(weights=Weights(valve_a_reserve_per_pct2=-1.0)).validate()
    assert Weights().valve_a_reserve_ramp_s == 0.0 and Weights().valve_a_reserve_short_c == 0.0
    with pytest.raises(InvalidSettings, match="valve_a_reserve_ramp_s"):
        OcpSpec(weights=Weights(valve_a_reserve_ramp_s=601.0)).validate()
    with pytest.raises(InvalidSettings, match="valve_a_reserve_short_c"):
        OcpSpec(weights=Weights(valve_a_reserve_short_c=-0.1)).validate()
    assert Weights().valve_a_reserve_ptc_hold_s == 0.0
    with pytest.raises(InvalidSettings, match="valve_a_reserve_ptc_hold_s"):
        OcpSpec(weights=Weights(valve_a_reserve_ptc_hold_s=601.0)).validate()
    with pytest.raises(InvalidSettings, match=r"valve_a_reserve_ptc_hold_s.*600"):  # its own range named
        OcpSpec(weights=Weights(valve_a_reserve_ptc_hold_s=-1.0)).validate()
    mpc = MpcController(settings=MpcSettings(ocp=OcpSpec(weights=Weights(valve_a_reserve_per_pct2=RESERVE,
                                                                valve_a_reserve_ramp_s=20.0,
                                                                valve_a_reserve_short_c=0.1,
                                                                valve_a_reserve_ptc_hold_s=60.0))))
    assert (mpc.reserve.ramp_s, mpc.reserve.short_c, mpc.reserve.ptc_hold_s) == (20.0, 0.1, 60.0)


def _literal_cooler_model() -> RefinedModel:
    """The controller's model with the thesis's cooler fit as written (the box's slope and offset), the effects
    identification names on that box (docs/identification.md, 'The literal cooler as a library effect')."""
    return RefinedModel(Parameters(),
                        ("ptc_power_fall", "fan_curve", "valve_leakage", "cooler_literal_fit"),
                        absent=("bypass_flow",))


def _second_step(weight: float) -> tuple[float, float, list[bool]]:
    """Quick winter_heating_steps (12 C, then 15 C at 90 s) on the literal-cooler box (noise seed 0): the box's heater
    body at the step up (C), the thermocouple IAE from the step on (C s), whether the reserve counted at each step."""
    on = []
    settings = MpcSettings(ocp=OcpSpec(weights=Weights(valve_a_reserve_per_pct2=weight)))
    body, iae = body_at_step_and_iae("winter_heating_steps", "cooler_literal", settings, _literal_cooler_model(),
                                     step_s=STEP_UP_S, observe=lambda c: on.append(c.reserve is not None and c.reserve.on))
    return body, iae, on


def test_on_the_literal_cooler_box_the_reserve_keeps_the_body_warm_for_the_step_up():
    """The MPC with the box's cooler holds 12 C with valve a at 53-58 % and the body at 33-36 C (docs); with the
    reserve (3e-4) it moves heat into the body at rest and serves the step to 15 C faster (measured: body 49.9
    against 36.4 C, IAE from the step on 12.7 against 28.8 C s)."""
    body_off, iae_off, on_off = _second_step(0.0)
    body_on, iae_on, on_on = _second_step(RESERVE)
    assert not any(on_off)
    assert any(on_on[:STEP_UP_S])  # at rest on 12 C
    assert not on_on[STEP_UP_S]  # the step up itself with the default weight
    assert body_on > body_off + 8.0, (body_on, body_off)
    assert iae_on < 0.6 * iae_off, (iae_on, iae_off)


def test_a_step_down_while_heating_takes_the_reserve_weight_until_the_reading_is_near_the_reference():
    """On a step down valve a closing is the fast way and keeps the body's heat: the reserve's weight, not the rest."""
    gate = _gate()
    for _ in range(int(REST_HOLD_S) + 1):
        _step(gate, ref_c=15.0, reading_c=15.0)
    assert gate.on
    assert _step(gate, ref_c=11.0, reading_c=15.0) == RESERVE and gate.descent and not gate.on
    assert _step(gate, ref_c=11.0, reading_c=12.0) == RESERVE  # still more than REST_BAND_C above
    assert _step(gate, ref_c=11.0, reading_c=11.4) == HEATING and not gate.descent  # near it: the hold begins
    assert _step(gate, ref_c=11.0, reading_c=12.0) == HEATING  # no new step down: it does not come back
    assert _step(gate, ref_c=14.0, reading_c=12.0) == HEATING  # a step up never
    _step(gate, ref_c=10.0, reading_c=12.0)
    assert gate.descent
    assert _step(gate, ref_c=10.0, reading_c=12.0, heating=False) == 0.0 and not gate.descent  # the heater off
    assert _step(gate, ref_c=9.0, reading_c=9.3) == HEATING  # lowered with the reading already near it
    assert _step(gate, ref_c=8.0, reading_c=float("nan")) == HEATING  # no reading
    _step(gate, ref_c=7.0, reading_c=9.0)
    assert _step(gate, ref_c=7.0, reading_c=9.0, cmd_w=100.0, flow_factor=1.0) == RESERVE
    gate.weight(supply_ref_c=7.0, flow_ref_m3s=50.0 / 3600.0, reading_c=9.0, heating=True, heater_cmd_w=100.0,
                available_w=240.0, flow_factor=1.0)
    assert not gate.descent  # a flow change during the step down ends it
