"""The real-time iteration's trust region (mpc/trust_region.py, ``MpcSettings.rti_trust_radii``): the QP's input box
around the linearisation point's plan, the settings' checks, and, on the independent box that draws cabin air behind
its inlet sensor (hvac_mpc.mismatch ``recirculation``), the MPC with the identified recirculation term: the region
ends most of valve a's alternation after the warm-up and lowers the tracking error after the step; a cold start is
the plain SQP (on the box whose heater body loses heat to its walls, ``heater_wall_loss``)."""

from __future__ import annotations

import numpy as np
import pytest

from hvac_mpc.mpc.mpc_controller import MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings
from hvac_mpc.mpc.trust_region import check_radii, region_bounds


def test_region_is_the_radius_around_the_plan_inside_the_bounds():
    u_lin = np.array([[0.0, 0.5], [0.9, -0.9]])
    lo, hi = np.full((2, 2), -1.0), np.full((2, 2), 1.0)
    span = np.array([[2.0, 1.0], [2.0, 1.0]])
    r_lo, r_hi = region_bounds(u_lin, lo, hi, span, 0.25)
    np.testing.assert_allclose(r_lo, [[-0.5, 0.25], [0.4, -1.0]])
    np.testing.assert_allclose(r_hi, [[0.5, 0.75], [1.0, -0.65]])


def test_region_of_a_plan_outside_the_bounds_is_the_nearest_bound():
    """The first stage's rate limits may exclude the shifted plan's first move: the region is then the bound
    nearest to it, not an empty box."""
    lo, hi = np.array([[0.2]]), np.array([[0.4]])
    r_lo, r_hi = region_bounds(np.array([[0.9]]), lo, hi, np.array([[2.0]]), 0.1)
    assert r_lo[0, 0] == r_hi[0, 0] == pytest.approx(0.4)
    r_lo, r_hi = region_bounds(np.array([[-0.9]]), lo, hi, np.array([[2.0]]), 0.1)
    assert r_lo[0, 0] == r_hi[0, 0] == pytest.approx(0.2)


@pytest.mark.parametrize("radii", [(0.0,), (1.0,), (0.1, 0.3), (0.5, 0.4, 0.3, 0.2, 0.1), ("0.5",), (True,)])
def test_bad_radii_name_the_field_and_the_range(radii):
    with pytest.raises(InvalidSettings, match=r"rti_trust_radii.*\(0, 1\)|rti_trust_radii.*decrease|rti_trust_radii.*at most"):
        MpcSettings(rti_trust_radii=radii)


def test_radii_default_off_and_accepted_in_order():
    assert MpcSettings().rti_trust_radii == ()
    assert check_radii([0.5, 0.1]) == (0.5, 0.1)
    with pytest.raises(InvalidSettings, match="rti_trust_radii must be a tuple"):
        MpcSettings(rti_trust_radii=[0.5])


#: A move of valve a counted (% of travel).
MOVE_PCT = 5.0
#: From the step to 22 C of the quick trapped_air_release (at 30 s) to 60 s after it.
WINDOW_S = (30.0, 90.0)


def _run(radii: tuple[float, ...], seed: int = 0, **fields) -> dict:
    """The MPC with the recirculation term on the recirculating box (the bench's noise ``seed``; ``fields``:
    MpcSettings fields), quick trapped_air_release up to the end of WINDOW_S: valve a's reversals (a move of at least
    MOVE_PCT against the last such move) in the window, the steps whose plan came from the trust region, and the
    thermocouple IAE (C s) in the window."""
    from test_reversal_damping import on_recirculating_box

    # without the search along the reversing input (on by default): it ends most of the alternation the region is
    # measured on (the plain run of seed 0 with it: 7 reversals, 234.7 C s, against 26 and 252.5)
    sc, mpc, plant = on_recirculating_box(seed, rti_trust_radii=radii, rti_reversal_search=0.0, **fields)
    i_a = mpc.problem.i_valve_a
    a_prev, last_move, reversals, trusted, qps, iae = None, 0.0, 0, 0, 0, 0.0
    for k in range(int(WINDOW_S[1])):
        ref = sc.reference_at(float(k))
        inside = k >= WINDOW_S[0]
        if inside:
            iae += abs(plant.truth()["supply_temp_c"] - ref.supply_temp_c)
        result = mpc.step(plant.read(), ref)
        u = np.asarray(result.command.vector(), float)
        trusted += int(inside and mpc.solver.trust_taken < 1.0)
        qps += int(inside) * result.stats["qp_solves"]
        plant.apply(u)
        plant.advance()
        if a_prev is not None and abs(u[i_a] - a_prev) >= MOVE_PCT:
            move = u[i_a] - a_prev
            reversals += int(inside and move * last_move < 0.0)
            last_move = move
        a_prev = u[i_a]
    return {"reversals": reversals, "trusted": trusted, "qps": qps, "iae": iae}


#: The trust region's radii the tests use.
RADII = (0.25, 0.1, 0.03)


def test_trust_region_ends_most_of_valve_a_alternation_on_the_recirculating_box():
    """After the warm-up, the QP linearised at valve a open plans it shut with the blower low, and linearised there
    plans it open again; each plan costs more on the model's own rollout than the plan it was linearised at
    (docs/identification.md, 'Why the right model tracks worse'). The trust region re-solves such a QP near the
    linearisation point: valve a reverses far less often in the 60 s after the step, and the thermocouple IAE
    there is lower (measured with the default reversal damping: 26 -> 14 reversals, 252.5 -> 234.6 C s).

    Without the start-up's caution (``start_rate_share`` 1), as measured: one noise sequence's count of reversals
    scatters more than the bound's margin (docs/robustness.md sec. 2.30). The caution binds once here, the first
    command (valve a 50 -> 70 % against 90 %); from the third sample the commands are those of the plain start within
    0.5 W and 0.1 %, the filter's offset 0.02-0.03 degC higher through the warm-up, and the alternation after the
    step to 22 C takes another course from 33 s (26 -> 23 reversals without the region, 14 -> 16 with it: 0.70). The
    next test holds the defaults to the same bounds over four noise sequences. Both tests without the search along
    the reversing input (``rti_reversal_search`` 0; on by default, :func:`_run`)."""
    off, on = _run((), start_rate_share=1.0), _run(RADII, start_rate_share=1.0)
    assert off["trusted"] == 0
    assert on["trusted"] >= 10, on
    assert on["qps"] >= off["qps"] + on["trusted"], (on, off)  # each plan from the region took a QP more at least
    assert off["reversals"] >= 20, off
    assert on["reversals"] <= 0.65 * off["reversals"], (on, off)
    assert on["iae"] < 0.95 * off["iae"], (on, off)


#: The bench's noise seeds the check with the controller's defaults sums over.
NOISE_SEEDS = (0, 1, 2, 3)


@pytest.mark.slow
def test_trust_region_ends_most_of_valve_a_alternation_over_four_noise_sequences():
    """The last test's bounds with the controller's defaults (the start-up's caution on), the reversals and the IAE
    summed over the bench's noise seeds 0-3: the ratio of one sequence's reversals scatters with the caution or
    without (with ``start_rate_share`` 1: 0.54, 0.56, 0.42, 0.50 for seeds 0-3, seed 5 0.76, above the bound;
    with 0.4: 0.70, 0.52, 0.36, 0.47), the sums do not (107 -> 54 without the caution, 110 -> 55 with it;
    docs/robustness.md sec. 2.30). The region's plans taken at least 10 times in each run. The search along the
    reversing input pinned off (:func:`_run`): with it, on by default, the four plain runs sum 42 reversals and
    970.5 C s."""
    runs = [(_run((), seed), _run(RADII, seed)) for seed in NOISE_SEEDS]
    assert all(on["trusted"] >= 10 and off["trusted"] == 0 for off, on in runs), runs
    off = {k: sum(r[0][k] for r in runs) for k in ("reversals", "iae")}
    on = {k: sum(r[1][k] for r in runs) for k in ("reversals", "iae")}
    assert off["reversals"] >= 20 * len(NOISE_SEEDS), off
    assert on["reversals"] <= 0.65 * off["reversals"], (on, off)
    assert on["iae"] < 0.95 * off["iae"], (on, off)


def _first_step(radii: tuple[float, ...]) -> tuple[np.ndarray, int, float]:
    """The nominal MPC's first step (a cold start) on the independent box whose heater body loses heat to the box walls
    (hvac_mpc.mismatch ``heater_wall_loss``), quick trapped_air_release of the benchmark's seed 0: the command, the
    step's QPs and the radius its plan came from."""
    from hvac_mpc.benchmarks import scenarios
    from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S, plant_seed
    from hvac_mpc.mismatch import make_plant
    from hvac_mpc.mpc.mpc_controller import MpcController

    sc = scenarios.select(["trapped_air_release"], quick=True)[0]
    mpc = MpcController(settings=MpcSettings(initial_command=sc.initial_command, deadline_s=DETERMINISTIC_DEADLINE_S,
                                             rti_trust_radii=radii))
    plant = make_plant("heater_wall_loss", seed=plant_seed(0, sc.seed), dt_s=1.0, inlet_temp_c=sc.inlet_temp_c,
                       chiller_setpoint_c=sc.chiller_setpoint_c, initial_command=sc.initial_command)
    mpc.reset(sc.initial_command)
    result = mpc.step(plant.read(), sc.reference_at(0.0))
    return np.asarray(result.command.vector(), float), result.stats["qp_solves"], mpc.solver.trust_taken


def test_cold_start_is_the_plain_sqp_with_the_region_set():
    """A cold start linearises at the starting command held over the horizon, a guess and not a plan, and iterates
    (``cold_start_qps``); with the region there its first QP's plan, which costs more than that guess, was
    re-solved within 25 % of the guess's inputs, and each further iteration within a radius of the last: the first
    command came from a start held near the guess (on this box the heater at 3 W against 10 W, a leaner heater body
    at the step to 22 C: 386.8 against 355.2 C s for the MPC with the identified heater-body term,
    docs/identification.md, "The trust region at the cold start"). The region is for the real-time iteration's one
    step from the last plan; the cold start's command is the plain SQP's."""
    plain, plain_qps, _ = _first_step(())
    regioned, qps, radius = _first_step(RADII)
    assert radius == 1.0 and qps == plain_qps >= 2, (qps, plain_qps, radius)
    np.testing.assert_array_equal(regioned, plain)
