"""Sensors (thesis section 2.4): first-order temperature lags."""

from __future__ import annotations


def lag_rate(sensor_value, true_value, tau_s):
    """d(sensor)/dt of a first-order sensor lag with time constant ``tau_s``."""
    return (true_value - sensor_value) / tau_s
