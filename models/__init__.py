"""CasADi model of the HVAC box, its parameters, and the simulated plant."""

from .box import DISTURBANCES, INPUTS, MODEL_EFFECTS, OUTPUTS, STATES, HvacModel, Signals, input_upper
from .parameters import Parameters
from .plant import PLANT_EFFECTS, Command, Environment, Measurement, SimulatedPlant

__all__ = ["DISTURBANCES", "INPUTS", "MODEL_EFFECTS", "OUTPUTS", "STATES", "HvacModel", "Signals",
           "input_upper", "Parameters", "PLANT_EFFECTS", "Command", "Environment", "Measurement",
           "SimulatedPlant"]
