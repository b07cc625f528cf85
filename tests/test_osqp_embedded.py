"""OSQP's generated C for the RTI's QP (mpc/osqp_embedded.py): the Python interface's answers, built once per
structure into the cache, the Python interface where it cannot be built, a workspace per solver, the time
limit, the kept equilibration between updates, the edits of OSQP's solve and the fused matrix update to the bit
(docs/architecture.md "The step's glue, second pass").

Budget: about 15 s on a loaded two-core machine (one build of the generated solver, about 3 s, and short
closed loops with CasADi's interpreter).
"""

import dataclasses

import numpy as np
import osqp
import pytest

from hvac_mpc.benchmarks import qp_dense, solve_time
from hvac_mpc.benchmarks.simulate import DETERMINISTIC_DEADLINE_S
from hvac_mpc.models import Parameters
from hvac_mpc.mpc import codegen, osqp_embedded
from hvac_mpc.mpc.mpc_controller import InvalidSettings, MpcController, MpcSettings
from hvac_mpc.mpc.rti_osqp import _OsqpCore

STEPS = 40  # the solve-time loop's first reference change is at 30 s: a cold start, single QPs, a change's two


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A cache folder of this module's own, the code generation switched on while its tests run."""
    folder = tmp_path_factory.mktemp("cache")
    mp = pytest.MonkeyPatch()
    mp.setenv(codegen.CACHE_ENV, str(folder))
    mp.setenv(codegen.SWITCH_ENV, "1")
    yield folder
    mp.undo()


@pytest.fixture(scope="module")
def recorded(cache):
    """The QPs of 40 steps of the solve-time loop (seed 1) and their layout."""
    qps, lay, _ = qp_dense.record(STEPS, 1, MpcSettings(codegen=False, osqp_codegen=False))
    return qps, lay


def _loop(settings: MpcSettings, params: Parameters | None = None, steps: int = STEPS):
    # the deadline lifted: on a loaded machine a missed wall-clock deadline is the load's, not the solver's
    ctrl = MpcController(params, dataclasses.replace(settings, deadline_s=DETERMINISTIC_DEADLINE_S))
    loop = solve_time.Loop(ctrl, seed=1)
    rows = [loop.step(k) for k in range(steps)]
    assert all(r.stats["fallback"] is None for r in rows)
    return np.array([r.command.vector() for r in rows]), [r.stats["iterations"] for r in rows], ctrl


def _setup(lay, qp) -> osqp.OSQP:
    """OSQP's Python interface set up as the controller sets it up (the gradient zero)."""
    return qp_dense.OsqpReplay([{**qp, "q": np.zeros_like(qp["q"])}], lay).solver


def test_the_generated_solver_gives_the_python_interfaces_commands_built_once_per_structure(cache):
    generated, its_g, ctrl = _loop(MpcSettings(codegen=False))
    assert ctrl.solver.qp_codegen.outcomes == {"osqp": "built"}
    assert ctrl.solver.settings["osqp_generated"]
    assert len(list((cache / "osqp").glob("*.so"))) == 1
    python, its_p, plain = _loop(MpcSettings(codegen=False, osqp_codegen=False))
    assert not plain.solver.settings["osqp_generated"]
    assert np.array_equal(generated, python) and its_g == its_p
    assert max(its_g) > 0 and any(r > 1 for r in its_g)
    # other model parameters: the same structure, so the cached solver, with the Python interface's answers
    # for those parameters (the values the workspace was generated with do not carry over)
    other = Parameters(tau_tc_s=7.5, heater_power_max_w=200.0, blower_power_max_w=280.0)
    other_g, _, other_ctrl = _loop(MpcSettings(codegen=False), other, 15)
    assert other_ctrl.solver.qp_codegen.outcomes == {"osqp": "cached"}
    other_p, _, _ = _loop(MpcSettings(codegen=False, osqp_codegen=False), other, 15)
    assert np.array_equal(other_g, other_p)
    assert not np.allclose(other_g, generated[:15], atol=1e-3)
    assert len(list((cache / "osqp").glob("*.so"))) == 1


def test_the_key_follows_the_sparsity_and_the_settings_not_the_values(cache, recorded):
    qps, lay = recorded
    a, b = _setup(lay, qps[0]), _setup(lay, qps[5])
    key = osqp_embedded.structure_key(a, lay.P_pattern, lay.A_pattern)
    assert osqp_embedded.structure_key(b, lay.P_pattern, lay.A_pattern) == key
    b.update_settings(eps_abs=1e-5)
    assert osqp_embedded.structure_key(b, lay.P_pattern, lay.A_pattern) != key
    indices, indptr, shape = lay.A_pattern
    moved = (np.roll(indices, 1), indptr, shape)
    assert osqp_embedded.structure_key(a, lay.P_pattern, moved) != key


def test_each_solver_has_a_workspace_of_its_own(cache, recorded):
    """Two solvers from the one shared object: the second's QPs do not move the first's state."""
    qps, lay = recorded
    one = osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern)
    two = osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern)
    python = _OsqpCore(_setup(lay, qps[0]))
    for qp in qps[:12]:
        answers = []
        for core in (one, two, python):
            core.update_matrices(qp["Px"], qp["Ax"])
            core.update_vectors(qp["q"], qp["l"], qp["u"])
            core.warm_start(qp["warm"])
            answers.append(core.solve())
        (s1, t1, n1, x1), (s2, _, n2, x2), (s3, t3, n3, x3) = answers
        assert (s1, t1, n1) == (s3, t3, n3) == (s2, t3, n2)
        assert np.array_equal(x1, x3) and np.array_equal(x2, x3)
        assert one.rho == two.rho


def test_bound_arrays_written_in_place_give_the_answers_of_new_ones(cache, recorded):
    """The RTI writes its bounds into the same two arrays every QP, whose addresses the generated solver takes once:
    the values written in place between QPs are the ones solved with (the Python interface's answers, as with new
    arrays each QP), and arrays handed over in their place are checked and taken."""
    qps, lay = recorded
    kept = osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern)
    python = _OsqpCore(_setup(lay, qps[0]))
    lo, hi = np.empty_like(qps[0]["l"]), np.empty_like(qps[0]["u"])
    for qp in qps[:12]:
        lo[:], hi[:] = qp["l"], qp["u"]
        answers = []
        for core, bounds in ((kept, (lo, hi)), (python, (qp["l"], qp["u"]))):
            core.update_matrices(qp["Px"], qp["Ax"])
            core.update_vectors(qp["q"], *bounds)
            core.warm_start(qp["warm"])
            answers.append(core.solve())
        (s1, t1, n1, x1), (s2, t2, n2, x2) = answers
        assert (s1, t1, n1) == (s2, t2, n2) and np.array_equal(x1, x2)
    assert len({float(np.abs(qp["l"] - qps[0]["l"]).max()) for qp in qps[:12]}) > 1  # the bounds did move
    with pytest.raises(ValueError, match="contiguous float64 array of"):
        kept.update_vectors(qps[0]["q"], lo[:-1], hi)


def test_without_a_compiler_the_python_interface_solves(tmp_path, monkeypatch, recorded):
    qps, lay = recorded
    monkeypatch.setenv(codegen.CACHE_ENV, str(tmp_path))
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setenv("PATH", str(tmp_path))  # neither gcc nor cc
    report = codegen.CodegenReport()
    assert osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern, report=report) is None
    assert report.outcomes["osqp"].startswith("interpreted: RuntimeError: no C compiler")
    ctrl = MpcController(settings=MpcSettings(codegen=False))
    assert isinstance(ctrl.solver._core, _OsqpCore)
    assert ctrl.solver.qp_codegen.outcomes["osqp"].startswith("interpreted")
    monkeypatch.setenv(codegen.SWITCH_ENV, "0")
    assert osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern, report=report) is None
    assert report.outcomes["osqp"] == f"interpreted: {codegen.SWITCH_ENV}=0"


def test_the_time_limit_stops_a_solve(cache, recorded, tmp_path, monkeypatch):
    qps, lay = recorded
    monkeypatch.setenv(codegen.CACHE_ENV, str(tmp_path))  # its own cache: the module's counts builds
    core = osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern)
    qp = qps[0]
    core.update_matrices(qp["Px"], qp["Ax"])
    core.update_vectors(qp["q"], qp["l"], qp["u"])
    core.set_time_limit(1e-9)
    status_val, status, _, _ = core.solve()
    assert (status_val, status) == (8, "run time limit reached")
    core.set_time_limit(0.0)
    assert core.solve()[0] == 1


def test_arrays_of_the_wrong_size_or_type_are_refused(cache, recorded):
    qps, lay = recorded
    core = osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern)
    with pytest.raises(ValueError, match="contiguous float64 array of"):
        core.update_matrices(qps[0]["Px"][:-1], qps[0]["Ax"])
    with pytest.raises(ValueError, match="contiguous float64 array of"):
        core.warm_start(qps[0]["warm"].astype(np.float32))
    with pytest.raises(InvalidSettings, match="osqp_scaling_interval"):
        MpcSettings(osqp_scaling_interval=0).validate()
    with pytest.raises(ValueError, match="scaling_interval"):
        osqp_embedded.EmbeddedOsqp(cache, _setup(lay, qps[0]), scaling_interval=0)


def test_a_kept_equilibration_solves_the_same_qps_to_osqps_tolerance(cache, recorded):
    """Equilibrating on every third update only: other iterates, the same QPs solved (the objective within
    OSQP's tolerance of the Python interface's, the rows met to it)."""
    qps, lay = recorded
    kept = osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern, scaling_interval=3)
    python = _OsqpCore(_setup(lay, qps[0]))
    differ = 0
    for qp in qps:
        xs = []
        for core in (kept, python):
            core.update_matrices(qp["Px"], qp["Ax"])
            core.update_vectors(qp["q"], qp["l"], qp["u"])
            core.warm_start(qp["warm"])
            status_val, _, _, x = core.solve()
            assert status_val == 1
            xs.append(x)
        f_kept, f_python = (qp_dense.objective(qp, lay, x) for x in xs)
        assert abs(f_kept - f_python) <= 1e-3 * max(1.0, abs(f_python))
        for x in xs:  # OSQP's primal residual test (unscaled), at its tolerance 1e-4
            ax = lay.A(qp["Ax"]) @ x
            z = np.clip(ax, qp["l"], qp["u"])
            assert np.abs(ax - z).max() <= 1e-4 + 1e-4 * max(np.abs(ax).max(), np.abs(z).max())
        differ += not np.array_equal(*xs)
    assert differ > 0  # the kept equilibration does change the iterates


def test_the_first_pass_runs_alike_in_the_generated_solver(cache):
    """With OSQP's first pass (``osqp_first_pass_iter``) the generated solver switches its settings as the
    Python interface does: the same commands and iterations."""
    settings = dict(codegen=False, osqp_first_pass_iter=10)
    generated, its_g, ctrl = _loop(MpcSettings(**settings), steps=STEPS)
    assert ctrl.solver.settings["osqp_generated"]
    python, its_p, _ = _loop(MpcSettings(**settings, osqp_codegen=False), steps=STEPS)
    assert np.array_equal(generated, python) and its_g == its_p


def test_a_reset_controller_answers_as_a_new_one_with_the_generated_solver(cache):
    """``reset()`` loads a fresh copy of the workspace: the multipliers and step size of the run before are gone."""
    first, _, ctrl = _loop(MpcSettings(codegen=False), steps=15)
    used = ctrl.solver._core
    loop = solve_time.Loop(ctrl, seed=1)  # resets the controller to the plant's state
    again = np.array([loop.step(k).command.vector() for k in range(15)])
    assert ctrl.solver._core is not used and ctrl.solver.settings["osqp_generated"]
    assert np.array_equal(again, first)


def test_a_reset_never_compiles_it_loads_from_the_cache_or_keeps_the_python_interface(recorded, tmp_path, monkeypatch):
    """A reset runs on a failure path inside a control step: it may load the generated solver from the cache but
    must not build it there (a build takes seconds)."""
    qps, lay = recorded
    monkeypatch.setenv(codegen.CACHE_ENV, str(tmp_path))
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    report = codegen.CodegenReport()
    assert osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern, report=report, build=False) is None
    assert "not in the cache" in report.outcomes["osqp"] and not list(tmp_path.glob("osqp/*.so"))
    assert osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern, report=report) is not None
    assert osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern, report=report, build=False) is not None
    assert report.outcomes["osqp"] == "cached"


def test_the_edits_of_osqps_solve_apply_once_to_the_installed_sources_and_refuse_other_text():
    """:data:`~hvac_mpc.mpc.osqp_embedded.SOLVE_EDITS` on the installed OSQP's ``osqp_api.c``: each text found once and
    replaced (the build would fail otherwise); a source without one of them is refused with the edit's name."""
    import pathlib

    source = (pathlib.Path(osqp.__file__).parent / "codegen" / "codegen_src" / "src" / "osqp_api.c").read_text()
    edited = osqp_embedded.edit_solve(source)
    for what, old, new in osqp_embedded.SOLVE_EDITS:
        assert source.count(old) == 1 and old not in edited and new in edited, what
    what, old, _ = osqp_embedded.SOLVE_EDITS[1]
    with pytest.raises(ValueError, match=what):
        osqp_embedded.edit_solve(source.replace(old, ""))


def test_the_fused_matrix_update_leaves_osqps_own_workspace_and_the_edited_solve_its_answers(cache, recorded):
    """The fused matrix update (one sweep over A and one over P a Ruiz pass) against OSQP's own
    ``osqp_update_data_mat`` (``hq_update_mat``) in two generated solvers: after every QP of the recorded loop the saved
    workspaces (scaled P and A, D, E, their inverses, the cost scaling, the multipliers, the step size) are equal to
    the bit; the edited solve's answers, statuses and iterations are the Python interface's, also when capped at 1 to 7
    iterations (the loop ended without a termination check, the first iteration's residuals not computed)."""
    qps, lay = recorded
    fused = osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern)
    own = osqp_embedded.load(_setup(lay, qps[0]), lay.P_pattern, lay.A_pattern)
    python = _OsqpCore(_setup(lay, qps[0]))
    for i, qp in enumerate(qps):
        fused.update_matrices(qp["Px"], qp["Ax"])
        own._check(own._lib.hq_update_mat(own._p(qp["Px"], own._nnz_p), own._p(qp["Ax"], own._nnz_a)), "update")
        python.update_matrices(qp["Px"], qp["Ax"])
        assert fused.save_state()["buf"].tobytes() == own.save_state()["buf"].tobytes(), i
        answers = []
        for core in (fused, own, python):
            core.update_vectors(qp["q"], qp["l"], qp["u"])
            core.warm_start(qp["warm"])
            answers.append(core.solve_capped(1 + i % 7) if i % 3 == 2 else core.solve())
        (s1, t1, n1, x1), (s2, t2, n2, x2), (s3, t3, n3, x3) = answers
        assert (s1, t1, n1) == (s2, t2, n2) == (s3, t3, n3), i
        assert x1.tobytes() == x2.tobytes() == np.asarray(x3).tobytes(), i
    assert fused.rho == own.rho
