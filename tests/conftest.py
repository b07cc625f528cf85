import os

# Two cores at most, as on the target controller (issue: two-core budget).
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
# The MPC's hot path runs as generated C by default, built once per model structure (5-30 s each).
# The suite builds many structures (horizons, effects, delays), so it runs CasADi's interpreter on
# the same functions; tests/test_codegen.py switches the compiler on and checks both agree.
os.environ.setdefault("HVAC_MPC_CODEGEN", "0")
# Identification's whole-log runs stay interpreted too (mpc/codegen_background.py follows the switch above): from an
# empty cache their builds, beside two busy test workers, cost more than they save (27:18 against 22:48 for the
# whole suite, docs/identification.md "Runs as generated C"); tests/test_codegen_background.py switches them on.


import pytest  # noqa: E402


@pytest.fixture
def test_controllers(monkeypatch):
    """Registers the tests' own controllers (tests/daemon_helpers.py) as entry points of the
    daemon's controller group, for this test only (in-process daemons; the group is the only way
    a controller is loaded)."""
    from importlib.metadata import EntryPoint

    from hvac_mpc.daemon import plugins

    real = plugins.entry_points

    def entry_points(group: str):
        eps = list(real(group=group))
        if group == plugins.CONTROLLER_GROUP:
            eps.append(EntryPoint(name="test-simple-pi", value="daemon_helpers:SimplePi", group=group))
        return eps

    monkeypatch.setattr(plugins, "entry_points", entry_points)
    return ["test-simple-pi"]


@pytest.fixture(scope="session")
def code_cache(request, tmp_path_factory):
    """A code cache of this test run, shared by its modules and by pytest-xdist's workers (the folder above each
    local worker's own temporary folder, which the run's controller made for this run): the generated solvers the
    tests switch on are built once per run, not once per module. Builds are atomic (a shared object moved into
    place), so two workers building one structure at once both load a whole one. Tests that count builds or need an
    empty cache keep a folder of their own."""
    base = tmp_path_factory.getbasetemp()
    worker = getattr(request.config, "workerinput", None) is not None  # a pytest-xdist worker of this run
    folder = (base.parent if worker else base) / "shared-code-cache"
    folder.mkdir(parents=True, exist_ok=True)
    return folder
