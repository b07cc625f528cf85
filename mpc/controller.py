"""The step interface every controller shares: defined in :mod:`hvac_mpc.contract`, re-exported here."""

from hvac_mpc.contract import Controller, StepResult

__all__ = ["Controller", "StepResult"]
