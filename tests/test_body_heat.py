"""The value of the heat stored in the heater body (``Weights.body_heat_power_w``, mpc/ocp.py): the heat content
change over the horizon priced at the energy term's marginal price of electric energy at that power, the same term
in the exact cost, the globalised step's merit and the QP."""

import numpy as np
import pytest

from heater_body_helpers import body_at_step_and_iae
from hvac_mpc.contract import Reference
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import InvalidSettings, OcpSpec, Weights

POWER_W = 340.0


@pytest.fixture(scope="module")
def controllers():
    def make(power_w):
        return MpcController(settings=MpcSettings(ocp=OcpSpec(weights=Weights(body_heat_power_w=power_w)),
                                                  rti_step_fractions=(0.5, 0.25)))
    return make(0.0), make(POWER_W)


def _plan(pb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States (model rollout), inputs and disturbances of a plan that cools the heater body: heater off, valve a
    at 60 %, 15 C air through a 45 C body."""
    d = np.array([15.0, 5.0, 0.0, 0.0])
    x_phys = pb.placeholder_state()
    x_phys[pb.i_heater] = 45.0
    U = np.tile(pb.scale_u(np.array([150.0, 0.0, 60.0, 50.0, 50.0, 50.0])), (pb.N, 1))
    X = np.empty((pb.N + 1, pb.nx))
    X[0] = pb.scale_x(x_phys)
    for k in range(pb.N):
        X[k + 1] = np.asarray(pb.F(X[k], U[k], d, k)).ravel()
    return X, U, d


def test_the_heat_drawn_from_the_body_costs_what_the_heaters_energy_costs(controllers):
    """The exact cost with the weight minus without it is the body's heat content lost over the horizon,
    C_body (T_0 - T_N) in J with the thesis' 243 g of aluminium (897 J/kg/K), times the energy term's marginal
    price at 340 W: d/dP [w (P / 100 W)^2] = 2 w P / 1e4 per J."""
    (plain, priced) = (c.problem for c in controllers)
    X, U, d = _plan(plain)
    T = plain.unscale_x(X)[:, plain.i_heater]
    assert T[0] - T[-1] > 5.0  # the plan draws the body down
    ref = plain.reference_vector(Reference(supply_temp_c=15.0, volume_flow_m3s=0.01))
    w_y, S = plain.w_y_full.copy(), np.zeros(plain.N)
    cost = [float(pb.cost_function()(X.T, U.T, S, d, ref, w_y, _heating(pb))) for pb in (plain, priced)]
    heat_j = 0.243 * 897.0 * (T[0] - T[-1])
    price_per_j = 2.0 * Weights().energy_per_100w2 * POWER_W / 100.0 ** 2
    assert cost[1] - cost[0] == pytest.approx(price_per_j * heat_j, rel=1e-9)
    # with the heater off in the command in force (cooling) the term is left out
    off = [float(pb.cost_function()(X.T, U.T, S, d, ref, w_y, U[0])) for pb in (plain, priced)]
    assert off[1] == off[0]


def _heating(pb) -> np.ndarray:
    """A command in force with the heater on (100 W), scaled."""
    return pb.scale_u(np.array([150.0, 100.0, 60.0, 50.0, 50.0, 50.0]))


def test_the_merit_and_the_qp_carry_the_same_term(controllers):
    """The globalised step's merit (mpc/plan_merit.py) equals the exact cost with the weight on (no slack on this
    plan), and the QP's linear term on the terminal body state is the exact cost's slope there."""
    ctrl = controllers[1]
    pb, solver = ctrl.problem, ctrl.solver
    X, U, d = _plan(pb)
    ref = pb.reference_vector(Reference(supply_temp_c=15.0, volume_flow_m3s=0.01))
    w_y, u_prev = pb.w_y_full.copy(), _heating(pb)
    exact = float(pb.cost_function()(X.T, U.T, np.zeros(pb.N), d, ref, w_y, u_prev))
    merit = solver._merit.cost_function()(X[0], U.T, d, solver._stage_weights(w_y).T, ref, u_prev,
                                          pb.model.p_default, 0.0, np.zeros(pb.N))
    assert float(merit) == pytest.approx(exact, rel=1e-9)
    i = pb.N * pb.nx + pb.i_heater
    plain = controllers[0].solver
    assert solver._q_heating[i] - plain._q_heating[i] == pytest.approx(pb.body_heat_coef)
    assert solver._q_const[i] == plain._q_const[i]  # off while the heater is off
    slopes = [(_cost(c.problem, _bump(X, pb), U, d, ref, w_y, u_prev) - _cost(c.problem, X, U, d, ref, w_y, u_prev))
              / 1e-6 for c in controllers]
    assert slopes[1] - slopes[0] == pytest.approx(pb.body_heat_coef, rel=1e-4)


def _cost(pb, X, U, d, ref, w_y, u_prev) -> float:
    """The exact cost of a plan without slack."""
    return float(pb.cost_function()(X.T, U.T, np.zeros(pb.N), d, ref, w_y, u_prev))


def _bump(X: np.ndarray, pb) -> np.ndarray:
    """X with the terminal body state moved by 1e-6 (scaled)."""
    Xb = X.copy()
    Xb[-1, pb.i_heater] += 1e-6
    return Xb


@pytest.mark.parametrize("value", [-1.0, 2500.0, float("nan"), "340"])
def test_body_heat_power_out_of_range_names_the_field(value):
    with pytest.raises(InvalidSettings, match="body_heat_power_w"):
        MpcSettings(ocp=OcpSpec(weights=Weights(body_heat_power_w=value)))


def test_with_the_value_the_mpc_holds_the_body_warmer_for_a_step_up():
    """The independent nominal box (hvac_mpc.mismatch), the quick cabin_warmup_winter scenario, the nominal MPC:
    holding 9 C with the heater on, the MPC with the value runs more heater and less air through it, so the body
    is warmer when the reference steps up at 30 s (measured: 48.2 against 46.8 C) and the thermocouple follows the
    step sooner (31.4 against 34.2 C s over the scored part)."""
    def run(power_w):
        return body_at_step_and_iae("cabin_warmup_winter", "nominal",
                                    MpcSettings(ocp=OcpSpec(weights=Weights(body_heat_power_w=power_w))))

    body_plain, iae_plain = run(0.0)
    body_priced, iae_priced = run(POWER_W)
    assert body_priced > body_plain + 0.5, (body_priced, body_plain)
    assert iae_priced < 0.95 * iae_plain, (iae_priced, iae_plain)
