"""Valve a's duty weight pinned off for tests measured on the path without it.

``MpcSettings.valve_a_weight_on_duty`` with its opening gate and scale (docs/robustness.md sec. 2.51-2.53) is off by
default; tests that check another setting's mechanism on a path this weight would change name all three, so they keep
that path whatever the defaults become.
"""

#: The three settings of valve a's duty weight at their values without it (MpcSettings fields).
DUTY_WEIGHT_OFF = {"valve_a_weight_on_duty": False, "valve_a_weight_on_duty_open_pct": 0.0,
                   "valve_a_weight_on_duty_scale": 1.0}
