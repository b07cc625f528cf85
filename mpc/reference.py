"""References from the comfort algorithm: defined in :mod:`hvac_mpc.contract`, re-exported here."""

from hvac_mpc.contract import REFERENCE_RANGES, SPLIT_TOLERANCE, InvalidReference, Reference

__all__ = ["REFERENCE_RANGES", "SPLIT_TOLERANCE", "InvalidReference", "Reference"]
