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


def quick_proband_on_sweep_box(label: str, ekf):
    """The quick proband sequence on box ``label`` of the seeded sweep (seed 0; ``python -m
    hvac_mpc.benchmarks.box_sweep --seed 0``), the MPC with EkfSettings ``ekf`` on the deterministic deadline: its
    thermocouple IAE against the reference from the metrics' start (degC s) and the trace."""
    return quick_scenario_on_sweep_box(label, ekf)


def quick_scenario_on_sweep_box(label: str, ekf, scenario: str = "proband_sequence", record=None):
    """The quick mismatch scenario ``scenario`` on box ``label`` (``S<seed>-<index>``) of the seeded sweep (``python
    -m hvac_mpc.benchmarks.box_sweep --seed <seed>``), the MPC with EkfSettings ``ekf`` on the deterministic deadline:
    its thermocouple IAE against the reference from the metrics' start (degC s) and the trace. ``record(controller)``
    after each of the MPC's steps, where given."""
    import numpy as np

    from hvac_mpc.benchmarks import bench, mismatch_suite, scenarios, simulate
    from hvac_mpc.benchmarks.box_sweep import draw_boxes
    from hvac_mpc.benchmarks.plant_seam import build_plant
    from hvac_mpc.models import Parameters
    from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings

    seed, index = (int(part) for part in label[1:].split("-"))
    drawn_label, variant = draw_boxes(seed, index + 1)[index]
    assert drawn_label == label
    sc = scenarios.mismatch_scenarios()[scenario].quick()
    settings = MpcSettings(initial_command=sc.initial_command, deadline_s=bench.DETERMINISTIC_DEADLINE_S, ekf=ekf)
    plant = build_plant(mismatch_suite.variant_factory(variant), simulate.plant_seed(0, sc.seed), bench.DT_S,
                        name=label)
    controller = MpcController(Parameters(), settings)
    if record is not None:
        step = controller.step

        def recorded(measurement, reference):
            result = step(measurement, reference)
            record(controller)
            return result
        controller.step = recorded
    trace = simulate.simulate(sc, controller, Parameters(), 0, dt_s=bench.DT_S, plant=plant)
    sl = trace.time_s >= sc.metrics_start_s
    iae = float(np.abs(trace.truth["supply_temp_c"][sl] - trace.reference["supply_temp_c"][sl]).sum() * trace.dt_s)
    return iae, trace
