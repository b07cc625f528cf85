"""Wrappers that record what a controller or its QP solver did at each step, for the closed-loop tests."""

import numpy as np

from hvac_mpc.benchmarks import bench


def recording_mpc_factory(settings, **keys):
    """A bench MPC factory (``bench.mpc_factory(settings=settings)``) whose controllers record, at each step, the
    result's ``stats[key]`` for every keyword (its value: the default where the stats lack the key); returns the
    factory and the records, key -> list (every controller the factory makes appends to the same lists)."""
    records = {key: [] for key in keys}
    make_mpc = bench.mpc_factory(settings=settings)

    def mpc(command):
        controller = make_mpc(command)
        step = controller.step

        def recorded(measurement, reference):
            result = step(measurement, reference)
            for key, default in keys.items():
                records[key].append(result.stats.get(key, default))
            return result
        controller.step = recorded
        return controller

    return mpc, records


class StartingRho:
    """Stands in for the generated OSQP solver and keeps, per QP, the step size in force when its solve starts
    (``step``: the control step the caller sets before each)."""

    def __init__(self, core):
        self.core, self.step, self.starts = core, 0, []

    def _at_start(self):
        self.starts.append((self.step, self.core.rho))

    def solve(self):
        self._at_start()
        return self.core.solve()

    def solve_capped(self, max_iter):
        self._at_start()
        return self.core.solve_capped(max_iter)

    def __getattr__(self, name):
        return getattr(self.core, name)


class QpRecorder:
    """Stands between the RTI and OSQP (``RtiOsqpSolver._core``) and keeps the QP last handed over (``qp``: the values of
    P and A, q, l and u)."""

    def __init__(self, core):
        self.core, self.qp = core, {}

    def update_matrices(self, Px, Ax):
        self.qp.update(Px=np.array(Px), Ax=np.array(Ax))
        self.core.update_matrices(Px, Ax)

    def update_vectors(self, q, l, u):
        self.qp.update(q=np.array(q), l=np.array(l), u=np.array(u))
        self.core.update_vectors(q, l, u)

    def __getattr__(self, name):
        return getattr(self.core, name)
