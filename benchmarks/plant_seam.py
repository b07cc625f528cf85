"""The benchmark's plant seam: ``--plant MODULE:FACTORY`` names a function that builds a plant.

A lab brings its own simulator (or the mismatch suite its variants) as any object with the
``Plant`` protocol of ``hvac_mpc.contract``: ``apply(command)``, ``advance()``, ``read()``;
optionally ``set_environment(inlet_temp_c, chiller_setpoint_c)``, ``settle(command)`` and
``truth()`` (noise-free outputs by the model's output names). The factory is called once per run
(one controller on one scenario) with the keyword arguments it accepts among ``seed`` (int) and
``dt_s`` (sample time, s), and must return a fresh plant each time.

The code is imported only because the user typed its name on the command line.
"""

from __future__ import annotations

import importlib
import inspect
from typing import Any, Callable

#: Methods a plant must have (``hvac_mpc.contract.Plant``).
PLANT_METHODS = ("apply", "advance", "read")


class InvalidPlant(ValueError):
    """The ``--plant`` specification or the object its factory returned is unusable; the message says why."""


def load_factory(spec: str) -> Callable[..., Any]:
    """The callable named by ``MODULE:FACTORY`` (e.g. ``my_lab.box:make_plant``); clear errors otherwise."""
    if not isinstance(spec, str) or spec.count(":") != 1:
        raise InvalidPlant(f"--plant {spec!r}: expected MODULE:FACTORY, e.g. my_lab.box:make_plant")
    module_name, attr = (p.strip() for p in spec.split(":"))
    if not module_name or not attr or not attr.replace("_", "a").replace(".", "a").isalnum():
        raise InvalidPlant(f"--plant {spec!r}: expected MODULE:FACTORY with a module path and a function name")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise InvalidPlant(f"--plant {spec!r}: cannot import module {module_name!r} ({exc})") from exc
    obj: Any = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise InvalidPlant(f"--plant {spec!r}: module {module_name!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise InvalidPlant(f"--plant {spec!r}: {attr!r} is not callable")
    return obj


def build_plant(factory: Callable[..., Any], seed: int, dt_s: float, name: str = "plant factory") -> Any:
    """Call the factory with the keywords it accepts (``seed``, ``dt_s``) and check the plant's interface."""
    offered = {"seed": int(seed), "dt_s": float(dt_s)}
    try:
        params = inspect.signature(factory).parameters
        takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
        kwargs = offered if takes_any else {k: v for k, v in offered.items() if k in params}
    except (TypeError, ValueError):
        kwargs = offered
    try:
        plant = factory(**kwargs)
    except TypeError as exc:
        raise InvalidPlant(f"{name}: calling it with {sorted(kwargs)} failed ({exc}); a factory takes the "
                           "keywords seed and dt_s (or a subset) and returns a plant") from exc
    missing = [m for m in PLANT_METHODS if not callable(getattr(plant, m, None))]
    if missing:
        raise InvalidPlant(f"{name}: returned {type(plant).__name__}, which lacks {missing}; a plant needs "
                           f"{list(PLANT_METHODS)} (hvac_mpc.contract.Plant)")
    plant_dt = getattr(plant, "dt_s", dt_s)
    try:
        plant_dt = float(plant_dt)
    except (TypeError, ValueError):
        raise InvalidPlant(f"{name}: plant.dt_s = {plant_dt!r} is not a number") from None
    if abs(plant_dt - float(dt_s)) > 1e-9:
        raise InvalidPlant(f"{name}: plant.dt_s = {plant_dt} s must equal the benchmark's sample time {dt_s} s")
    return plant
