"""An independent simulation of the HVAC box, written apart from ``hvac_mpc.models``.

It imports nothing from the model: its physics are its own equations, from the thesis and
docs/model.md, so that a controller or an identification run tested against it is tested
against a truth that is not the model.
"""
