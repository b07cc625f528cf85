"""hvac-mpc: model predictive control of an automotive HVAC box.

Subpackages: ``hvac_mpc.models`` (plant model, parameters, simulated plant),
``hvac_mpc.mpc`` (MPC, estimator, thesis baseline, daemon), ``hvac_mpc.benchmarks``
(benchmark command) and ``hvac_mpc.identification`` (model refinement from logs).
"""

__version__ = "0.1.0"
