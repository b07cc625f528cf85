"""Heater readiness: a floor on the heater body while the reference asks for heat (a setting, off by default).

The cost of the tracking problem prices the supply temperature over the horizon and nothing after it. A
reference at or just below the air entering the box (a winter warm-up at 9 C with the air at 9.05 C
behind the blower) is then best held by cooling through the core, valve a open, with the heater off; the air
draws the heater body down (33 -> 26 C in 30 s on the recirculating box, docs/identification.md). A step up
that follows finds the heater at its limit and the body's stored heat gone. A controller with a worse model of
the entering air (believing it colder) keeps the heater on and wins by its error.

The floor: while the reference supply temperature is above the inlet air (the heating duty: the box can
reach it only with heat), the body is kept warm enough that the air through the heater, all air through the
core (valve a at its cap), leaves it at the reference plus ``OcpSpec.ready_step_c`` at once, without waiting
for the heater's body time constant (about 90 s):

    T_floor = T_core + (r + dT_ready - T_core) (kA + m_core c_p) / kA

with the core's outlet air ``T_core`` and the core's share of the flow from the prediction model at the
estimate (``HvacModel.algebraic``), the core's mass flow ``m_core`` at the reference flow (not the flow in force:
a floor that rose with the flow would let the controller raise it by raising the flow), and the heater's ``kA`` (thesis sec. 4.3: the heater outlet
``(kA T_h + m c_p T_in) / (kA + m c_p)``). It is held below the PTC knee (where the heater's power starts to
fall): the floor never asks for a body the heater cannot hold at its rating. It is not held below the body from
which the least air through the heater (valve a closed) already mixes to the reference: that cap, measured, takes
the floor away exactly in the warm-up it is for (at 9 C with the air at 9.05 C any warm body costs the reference
at rest; docs/identification.md 'Heater readiness').

The floor asks at most ``OcpSpec.ready_lead_c`` (3 K) above the body's estimate: ``min(T_floor, T_body,est +
lead)``. Once the heater runs at its limit (the hold after a heater-limited step up, the floor at the PTC knee,
10 K above the body), the floor can be approached only by sending less air through the heater, which costs the
supply temperature now; unbounded, the pull grows with the distance, so a controller whose estimate of the body
is right (and lower) pulls harder than one whose model overrates the body, until the reading leaves the band
below and the term drops out, valve a back open: a cycle of a few seconds (measured on the box with the heater's
wall loss, docs/identification.md 'Heater readiness'). Bounded, the pull is at most ``w lead^2`` per second
whatever the estimate, and the floor still rises with the body.

Because the bounded floor rises with the body, it is never met where the body's estimate does not rise: the pull
stands, and at rest it can be paid only in supply temperature (the heater's heat, at rest, goes to the air whatever
the body). After the step down to 15 C of the bench's trapped_air_release (valve a closed, the body hidden from the
reading, its estimate 35 C against the box's 72 C) it held the heater at 140 W and the reading 2.5 K above the
reference for the whole segment. So the floor counts only while the reading is within :data:`READY_BAND_C` of the
reference on both sides: above the band the box already delivers more heat than asked, and the pull's offset is at
most the band (docs/identification.md 'Heater readiness', the trace). The band bounds the pull's cost; it does not
remove the pull: in the bench's full cabin warm-up the body is hidden the same way (estimate 30-40 K below the box's,
above the PTC knee) and the reading sits at the band's edge (MPC / baseline 1.160 against 0.384 off), which is why
the readiness stays off until the body's estimate is right with valve a closed.

ASSUMPTION: while heating, the next reference change may be a step up of ``ready_step_c`` (3 K, the steps of
the bench's winter scenario), and serving it at once is worth ``Weights.heater_ready_per_c2`` per K^2 of the
body below the floor per second (a quadratic one-sided penalty on every predicted stage, out while the reading is more than 0.5 K from the
reference: a step up being served comes first, the side chosen at
the linearisation: :meth:`RtiOsqpSolver` adds it where the plan it linearises at has the body below the floor).
The globalised step's merit (:mod:`.plan_merit`) carries the same penalty, one-sided on its rollout; the exact
cost and the IPOPT problem leave it out.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hvac_mpc.models.box import INPUTS

#: The readiness counts while the supply reading is at most this far from the reference, below or above it (K): at
#: rest on the reference (the bench's settling band, +-0.5 C), not while a step up is served (below) nor while the
#: box already delivers more heat than the reference asks (above; docs/identification.md 'Heater readiness').
READY_BAND_C = 0.5


def heating_duty(supply_ref_c: float | None, inlet_c: float) -> bool:
    """Whether the reference asks the box for heat: a supply-temperature reference (degC) above the inlet air (degC);
    no reference (None or NaN) asks none."""
    return supply_ref_c is not None and supply_ref_c > inlet_c


class HeaterReadiness:
    """The readiness floor of a :class:`~hvac_mpc.mpc.ocp.TrackingProblem` (its model, parameters, scaling)."""

    def __init__(self, problem):
        self.pb = problem
        self.weight = float(problem.spec.weights.heater_ready_per_c2)
        self.step_c = float(problem.spec.ready_step_c)
        lead = problem.spec.ready_lead_c
        self.lead_c = None if lead is None else float(lead)
        self.i_valve_a = INPUTS.index("valve_a_pct")
        m = problem.model
        x, u = ca.SX.sym("x", len(m.states)), ca.SX.sym("u", len(m.inputs))
        d, p = ca.SX.sym("d", len(m.disturbances)), ca.SX.sym("p", len(m.param_names))
        al = m.algebraic(x, u, d, p)
        density = al["mass_flow"] / ca.fmax(al["flow"], 1e-6)  # kg/m3
        self._core = ca.Function("readiness_core", [x, u, d, p], [al["t_cooler"], 1.0 - al["bypass"], density])
        self._flow = ca.Function("readiness_flow", [x, u, d, p], [al["flow"]])

    @property
    def on(self) -> bool:
        return self.weight > 0.0

    def floor_c(self, x_phys: np.ndarray, u_phys: np.ndarray, d: np.ndarray, p: np.ndarray,
                supply_ref_c: float | None, flow_ref_m3s: float | None, valve_a_cap_pct: float,
                supply_now_c: float | None = None) -> float | None:
        """The body floor (degC) at the estimate ``x_phys`` with the command in force ``u_phys`` (valve a at its
        cap), disturbances ``d`` and model parameters ``p``, at the reference flow ``flow_ref_m3s`` (the flow the
        step is served at; the model's flow where there is none), at most ``ready_lead_c`` above the body's
        estimate; None outside the heating duty (the reference at or below the inlet air, ``d[0]``, or no
        temperature reference) and while the supply reading ``supply_now_c`` is more than :data:`READY_BAND_C`
        from the reference: below it a step up is being served (the heater's heat goes to the air, not into the
        body; the floor readies the box at rest for the next one), above it the box already delivers more heat than
        the reference asks, and the floor's pull could only be paid in supply temperature."""
        if not heating_duty(supply_ref_c, float(d[0])):
            return None
        if supply_now_c is not None and abs(supply_ref_c - float(supply_now_c)) > READY_BAND_C:
            return None
        u = np.array(u_phys, float)
        u[self.i_valve_a] = valve_a_cap_pct
        t_core, core_share, density = (float(v) for v in self._core(x_phys, u, d, p))
        flow = float(self._flow(x_phys, u, d, p)) if flow_ref_m3s is None else float(flow_ref_m3s)
        floor = min(self._body_for_outlet(t_core, core_share * density * flow, supply_ref_c + self.step_c),
                    self.pb.params.ptc_knee_c)
        if self.lead_c is not None:
            floor = min(floor, float(x_phys[self.pb.i_heater]) + self.lead_c)
        return float(floor)

    def _body_for_outlet(self, air_in_c: float, mass_flow_kgs: float, outlet_c: float) -> float:
        """The body temperature at which the heater's outlet air is ``outlet_c`` (the outlet balance of
        :func:`hvac_mpc.models.heater.air_outlet_c` solved for the body)."""
        prm = self.pb.params
        g = max(mass_flow_kgs, 1e-4) * prm.cp_air_j_per_kgk
        return air_in_c + (outlet_c - air_in_c) * (prm.heater_ka_w_per_k + g) / prm.heater_ka_w_per_k

    def scaled(self, floor_c: float | None) -> tuple[float, np.ndarray] | None:
        """The floor in the scaled heater state and the penalty's weight per stage 1..N (scaled units: weight
        times the stage's duration times the state's scale squared); None when off or outside the duty."""
        if floor_c is None or not self.on:
            return None
        pb = self.pb
        i = pb.i_heater
        x_f = (floor_c - pb.x_off[i]) / pb.x_sc[i]
        return float(x_f), self.weight * np.asarray(pb.dt, float) * float(pb.x_sc[i]) ** 2

    def cost(self, X_scaled: np.ndarray, target: tuple[float, np.ndarray] | None) -> float:
        """The one-sided penalty of a plan's scaled states ``X_scaled`` (N + 1 rows), stages 1..N."""
        if target is None:
            return 0.0
        x_f, w = target
        short = np.maximum(x_f - np.asarray(X_scaled)[1:, self.pb.i_heater], 0.0)
        return float(np.sum(w * short ** 2))
