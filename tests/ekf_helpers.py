"""Feeding the estimator open loop from a plant (tests of the estimator without a solver)."""

SETPOINT_C = 5.0


def feed_open_loop(ekf, plant, commands, hold_s: int, record) -> None:
    """Each command held ``hold_s`` samples on ``plant`` (chiller set point 5 C); the estimator updated
    with every reading and predicted with the command; ``record(ekf)`` after each update."""
    for k in range(hold_s * len(commands)):
        command = commands[k // hold_s]
        u = command.vector()
        m = plant.read()
        if ekf.initialised:
            ekf.update(m, u, SETPOINT_C)
        else:
            ekf.initialise(m, u, SETPOINT_C)
        record(ekf)
        ekf.predict(u, SETPOINT_C)
        plant.apply(command)
        plant.advance()
