"""External water chiller and cooler core (thesis section 4.2)."""

from __future__ import annotations

import casadi as ca


def water_rate_c_per_s(water_c, target_c, p, asymmetric: bool = False):
    """Water temperature ramp towards a target at the measured slope (thesis sec. 4.2, fig. 23).

    Nominal: +-0.00692 C/s, smoothed over 0.05 C near the target. ``asymmetric`` uses the rising
    and falling slopes 0.00702 / 0.00682 C/s.
    """
    direction = ca.tanh((target_c - water_c) / 0.05)
    if not asymmetric:
        return p.water_rate_c_per_s * direction
    rising = 0.5 * (1.0 + direction)
    return rising * p.water_rise_rate_c_per_s * direction + (1.0 - rising) * p.water_fall_rate_c_per_s * direction


def hysteresis_target_c(water_c: float, setpoint_c: float, on: bool, p) -> tuple[float, bool]:
    """Two-point chiller controller (effect 'chiller_hysteresis', thesis sec. 2.2; band ASSUMPTION).

    Returns the ramp target and the new on/off state: on cools until set - band, off lets the
    water warm until set + band. Pure function for the plant's discrete logic.
    """
    if on and water_c <= setpoint_c - p.chiller_band_c:
        on = False
    elif not on and water_c >= setpoint_c + p.chiller_band_c:
        on = True
    target = setpoint_c - p.chiller_band_c - 5.0 if on else setpoint_c + p.chiller_band_c + 5.0
    return target, on


def cooler_outlet_c(air_in_c, water_c, p, literal: bool = False):
    """Air temperature after the cooler core (thesis sec. 4.2).

    The thesis fit T_a = 0.7564 T_w + 6.312 was measured at one inlet temperature; it equals the
    effectiveness form T_in + eps (T_w - T_in) with eps = 0.7564 at
    T_in = 6.312 / (1 - 0.7564) = 25.9 C (docs/model.md, 'traps'). The effectiveness form is used so
    that the cooler responds to the inlet temperature. ``literal`` (effect ``cooler_literal_fit``): the
    thesis fit as written, ``p.cooler_slope`` T_w + ``p.cooler_offset_c`` whatever the air entering the core,
    for a box whose log shows that (:func:`literal_outlet_c`). ``p.cooler_outlet_offset_c`` (0 in the thesis
    model) is added: the estimator's estimate of the core outlet's error, where a box's core does not follow
    the effectiveness form (docs/robustness.md sec. 2.13).
    """
    if literal:
        return literal_outlet_c(water_c, p) + p.cooler_outlet_offset_c
    return air_in_c + p.cooler_slope * (water_c - air_in_c) + p.cooler_outlet_offset_c


def literal_outlet_c(water_c, p):
    """The thesis cooler fit as written (sec. 4.2): core outlet air ``p.cooler_slope`` T_w + ``p.cooler_offset_c``
    (degC), independent of the air entering the core. Not held between the air and the water: below the fit's
    inlet range (cold air, cold water) it warms the air past both streams, as the fit's equation does; it is the
    model only where identification named the effect on a log (docs/identification.md, "The literal cooler as a
    library effect"). ASSUMPTION: the equation holds outside the log's inlet range as within it."""
    return p.cooler_slope * water_c + p.cooler_offset_c


def cooler_fit_inlet_c(p) -> float:
    """Inlet temperature at which the thesis cooler fit and the effectiveness form agree."""
    return p.cooler_offset_c / (1.0 - p.cooler_slope)


def two_point_targets(setpoint_c, water0_c: float, dt_s: float, p, asymmetric: bool = False, on: bool = True):
    """Ramp targets of the two-point chiller control along a set-point sequence (numpy, degC per sample).

    The water temperature of a box whose chiller is under two-point control (effect 'chiller_hysteresis') is an
    autonomous function of the set points: it ramps at the water rate towards the target of
    :func:`hysteresis_target_c`, and the relay switches at set point -+ band. Simulated here sample by sample from
    ``water0_c`` with the compressor ``on`` (the plant's start), each sample a straight ramp at the model's rate
    (the rising and falling slopes if ``asymmetric``). Returned: the target the model's water state ramps to in
    each sample, so a model fed these targets in place of the set point carries the two-point control while its
    water ramp stays a differentiable function of the rates (docs/identification.md, "Logs without the water
    temperature").
    """
    import numpy as np
    sp = np.asarray(setpoint_c, float)
    targets = np.empty_like(sp)
    water = float(water0_c)
    rise = p.water_rise_rate_c_per_s if asymmetric else p.water_rate_c_per_s
    fall = p.water_fall_rate_c_per_s if asymmetric else p.water_rate_c_per_s
    for k, s in enumerate(sp):
        target, on = hysteresis_target_c(water, float(s), on, p)
        targets[k] = target
        water = water + (-fall * dt_s if on else rise * dt_s)
    return targets
