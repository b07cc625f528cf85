"""Refining the model from measured data: residuals, diagnostics, candidate effects, refit.

The procedure and its statistics: docs/identification.md.

- :func:`load_model_file` reads the model file ``hvac-mpc identify`` writes: ``(Parameters, effects)``.
- :func:`~hvac_mpc.identification.pipeline.identify` runs the procedure on a prepared log
  (:func:`~hvac_mpc.identification.log_data.load`).
- :func:`~hvac_mpc.identification.generator.simulate_log` makes logs with the simulated plant.
- :mod:`~hvac_mpc.identification.thesis_tables` runs the loop on the thesis's tables 3-6.
"""

from .api import identify
from .model_file import load_identification_extras, load_model_file, write_model_file

__all__ = ["identify", "load_model_file", "load_identification_extras", "write_model_file"]
