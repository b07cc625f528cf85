"""An independent simulation of the HVAC box, written apart from ``hvac_mpc.models``.

It imports nothing from the project's model, MPC, identification or benchmarks (only numpy, scipy
and ``hvac_mpc.contract``): its physics are its own equations, from the thesis and docs/model.md, so a
controller or an identification run tested against it is tested against a truth that is not the
model. See README.md in this folder for the variants and their equations.

    from hvac_mpc.mismatch import make_plant
    plant = make_plant("delay_3s", seed=1)        # also: --plant hvac_mpc.mismatch:make_plant
"""

from __future__ import annotations

from .box import IndependentBox
from .logs import simulate_log
from .variants import VARIANTS, Variant, get_variant

__all__ = ["IndependentBox", "Variant", "VARIANTS", "make_plant", "simulate_log"]


def make_plant(variant: str = "nominal", seed: int = 0, dt_s: float = 1.0, **kwargs) -> IndependentBox:
    """An :class:`IndependentBox` of the registered ``variant`` (a name of :data:`VARIANTS`, or a Variant).

    ``kwargs`` go to :class:`IndependentBox` (inlet_temp_c, chiller_setpoint_c, initial_command, noise).
    Raises ValueError naming the allowed variants for an unknown name.
    """
    get_variant(variant)  # the clear error before anything is built
    return IndependentBox(variant=variant, seed=seed, dt_s=dt_s, **kwargs)
