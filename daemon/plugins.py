"""Registered controllers: the entry-point group through which user code enters the daemon.

A package registers its controller class in its own ``pyproject.toml``::

    [project.entry-points."hvac_mpc.controllers"]
    my-controller = "my_package.module:MyController"

and the configuration names it (``[controller] name = "my-controller"``). A ``module:name``
written in a configuration file or sent to the API is never imported (README, daemon section).
"""

from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points

#: Entry-point group of the daemon's controllers (this project registers mpc and baseline).
CONTROLLER_GROUP = "hvac_mpc.controllers"


def registered_controllers() -> dict[str, EntryPoint]:
    """The registered controllers by name."""
    return {ep.name: ep for ep in entry_points(group=CONTROLLER_GROUP)}
