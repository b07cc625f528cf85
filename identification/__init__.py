"""Refining the model from measured data: residuals, diagnostics, candidate effects, refit.

The procedure and its statistics: docs/identification.md.

- :func:`load_model_file` reads the model file ``hvac-mpc identify`` writes: ``(Parameters, effects)``;
  :func:`load_refined_model` reads all of it (parameters with the delay, effects, discovered terms),
  validated (the format is :mod:`hvac_mpc.models.model_file`).
- :func:`~hvac_mpc.identification.pipeline.identify` runs the procedure on a prepared log
  (:func:`~hvac_mpc.identification.log_data.load`).
- logs to check it against come from the independent simulator, :func:`hvac_mpc.mismatch.simulate_log`.
- :mod:`~hvac_mpc.identification.thesis_tables` runs the loop on the thesis's tables 3-6.
"""

from .api import identify
from .model_file import load_identification_extras, load_model_file, load_refined_model, write_model_file

__all__ = ["identify", "load_model_file", "load_refined_model", "load_identification_extras", "write_model_file"]
