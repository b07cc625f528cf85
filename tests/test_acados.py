"""The RTI through acados (mpc/rti_acados.py): built from the stage-wise description, its QP answer is the
OSQP RTI's at the same linearisation point.

acados is an optional extra installed apart (``hvac_mpc.mpc.rti_acados.INSTALL_COMMAND``): without it the
tests that need it skip, naming the command. The solver is generated and compiled once per structure and
cached on disk (the first build of the horizon below takes minutes, hence ``slow``; later solvers load it):
each test gets a solver of its own from the cached build, so no test sees another's state.
"""

import os
from pathlib import Path

import numpy as np
import pytest

from hvac_mpc.contract import Command, Reference
from hvac_mpc.models import Parameters
from hvac_mpc.mpc.ocp import OcpSpec, TrackingProblem
from hvac_mpc.mpc import codegen
from hvac_mpc.mpc.rti_acados import (INSTALL_COMMAND, AcadosMissing, RtiAcadosSolver, _generation_env, _make,
                                     install_id, load_acados)
from hvac_mpc.validation import InvalidValue
from hvac_mpc.mpc.rti_osqp import RtiOsqpSolver

#: A short horizon with three substep variants (1, 2 and 4 RK4 substeps per stage, and 8 at the last).
DURATIONS_S = (1.0, 1.0, 2.0, 8.0, 16.0, 32.0)
LM = 0.1
#: Operating points: cooling (heater off, heater rows inactive) and heating (heater on: flow floor and PTC rows).
POINTS = {"cooling": (Command(150.0, 0.0, 70.0, 100.0, 100.0, 100.0), Reference(14.0, 0.04)),
          "heating": (Command(200.0, 1500.0, 40.0, 60.0, 100.0, 100.0), Reference(30.0, 0.03))}


def test_missing_install_names_the_install_command(monkeypatch, tmp_path):
    monkeypatch.setenv("HVAC_MPC_ACADOS_DIR", str(tmp_path))
    with pytest.raises(AcadosMissing) as err:
        load_acados()
    assert INSTALL_COMMAND.replace("<dir>", str(tmp_path)) in str(err.value)
    assert "HVAC_MPC_ACADOS_DIR" in str(err.value)


@pytest.fixture(scope="module")
def pb():
    try:
        load_acados()
    except AcadosMissing as exc:
        pytest.skip(f"acados is not installed: {exc}")
    return TrackingProblem(Parameters(), OcpSpec(stage_durations_s=DURATIONS_S))


@pytest.fixture(scope="module")
def built(pb):
    """Builds the generated solver once for the module (later solvers load it from the cache)."""
    return RtiAcadosSolver(pb, lm_inputs=LM, qp_tol=1e-9, qp_iter_max=100).codegen


@pytest.fixture
def acados(pb, built):
    return RtiAcadosSolver(pb, lm_inputs=LM, qp_tol=1e-9, qp_iter_max=100)


def _point(pb, name):
    command, reference = POINTS[name]
    u_phys = command.vector()
    x = pb.scale_x(pb.placeholder_state())
    u_prev, d = pb.scale_u(u_phys), np.array([25.0, 5.0, 0.0, 0.0])
    ref = pb.reference_vector(reference)
    w_y = pb.heating_weights(pb.output_weights(reference), heating=pb.heating(u_phys))
    lo, hi = pb.input_bounds(u_phys)
    return x, u_prev, d, ref, w_y, lo, hi


def _solve(solver, pb, name):
    """Prepare at a point, then the feedback from a nearby estimate (the QP's initial-state row moves)."""
    x, u_prev, d, ref, w_y, lo, hi = _point(pb, name)
    solver.reset()
    solver.prepare(x, u_prev, d, ref, w_y)
    return solver.feedback(x + 0.02, u_prev, d, ref, w_y, lo, hi)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(POINTS))
def test_qp_answer_equals_the_osqp_rtis(pb, acados, name):
    osqp_rti = RtiOsqpSolver(pb, eps=1e-9, max_iter=200000, lm_inputs=LM)
    ro, ra = _solve(osqp_rti, pb, name), _solve(acados, pb, name)
    assert ro.ok and ra.ok, (ro.status, ra.status)
    np.testing.assert_allclose(ra.U, ro.U, atol=2e-5)
    np.testing.assert_allclose(ra.X, ro.X, atol=2e-5)
    np.testing.assert_allclose(ra.S, ro.S[:-1], atol=2e-5)  # acados' S: stages 1..N-1 (the terminal one apart)


@pytest.mark.slow
def test_same_inputs_give_the_same_iterations_status_and_answer(pb, acados):
    first, second = _solve(acados, pb, "heating"), _solve(acados, pb, "heating")
    assert first.ok and second.ok
    assert first.iterations == second.iterations and 0 < first.iterations <= 100
    assert first.extra["acados_status"] == second.extra["acados_status"] == 0
    np.testing.assert_array_equal(first.U, second.U)


@pytest.mark.slow
def test_a_changed_reference_prepares_again_at_the_prepared_iterate_without_shifting(pb, acados):
    x, u_prev, d, ref, w_y, lo, hi = _point(pb, "heating")
    ref2 = ref + 1.0
    acados.reset()
    acados.prepare(x, u_prev, d, ref, w_y)
    changed = acados.feedback(x + 0.02, u_prev, d, ref2, w_y, lo, hi)  # the reference moved after the preparation
    acados.reset()
    acados.prepare(x, u_prev, d, ref2, w_y)
    direct = acados.feedback(x + 0.02, u_prev, d, ref2, w_y, lo, hi)
    assert changed.ok and direct.ok and changed.prep_time_s > 0.0
    np.testing.assert_allclose(changed.U, direct.U, atol=1e-9)
    np.testing.assert_allclose(changed.X, direct.X, atol=1e-9)


@pytest.mark.slow
def test_reset_clears_acados_iterate_and_the_next_step_solves(pb, acados):
    first = _solve(acados, pb, "cooling")
    assert np.any(acados.acados.get(1, "x") != 0.0)
    acados.reset()
    assert not acados.has_trajectory
    assert np.all(acados.acados.get(1, "x") == 0.0) and np.all(acados.acados.get(0, "u") == 0.0)
    assert np.all(acados.acados.get(0, "pi") == 0.0)
    again = _solve(acados, pb, "cooling")
    assert again.ok
    np.testing.assert_allclose(again.U, first.U, atol=1e-9)


@pytest.mark.slow
def test_a_cold_start_takes_the_asked_iterations_and_a_second_solver_loads_the_cached_build(pb, acados):
    solver = RtiAcadosSolver(pb, lm_inputs=LM, cold_start_qps=3)
    assert solver.codegen.outcomes["acados_ocp"] == "cached"  # the module's first solver built it
    x, u_prev, d, ref, w_y, lo, hi = _point(pb, "cooling")
    res = solver.feedback(x, u_prev, d, ref, w_y, lo, hi)  # no preparation before: a cold start
    assert res.ok and res.extra["cold_start"] and res.qp_solves == 3
    again = solver.feedback(x, u_prev, d, ref, w_y, lo, hi)
    assert again.ok and not again.extra["cold_start"] and again.qp_solves == 1


@pytest.mark.slow
def test_failure_on_purpose_reports_it(pb, acados):
    acados.fail_next = 1
    x, u_prev, d, ref, w_y, lo, hi = _point(pb, "cooling")
    res = acados.feedback(x, u_prev, d, ref, w_y, lo, hi)
    assert not res.ok and res.status == "forced failure" and acados.fail_next == 0


def _solve_time(tmp_path, *extra):
    from hvac_mpc.cli import main
    out = tmp_path / "solve_time.json"
    assert main(["solve-time", "--steps", "4", "--no-ipopt", "--no-dompc", "--no-suboptimality",
                 "--acados", "--json", str(out), *extra]) == 0
    import json
    return json.loads(out.read_text())


def test_solve_time_without_acados_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_ACADOS_DIR", str(tmp_path / "none"))
    data = _solve_time(tmp_path, "--no-fatrop")
    assert [r["controller"] for r in data["results"]] == ["rti"]
    assert any(n.startswith("rti-acados skipped") and "pip install --no-deps --target" in n for n in data["notes"])


@pytest.mark.slow
def test_solve_time_runs_acados_beside_the_osqp_rti_and_records_its_settings(pb, built, tmp_path):
    data = _solve_time(tmp_path, "--acados-phases")  # fatrop not skipped on the command line: --acados skips it
    by_name = {r["controller"]: r for r in data["results"]}
    assert sorted(by_name) == ["rti", "rti-acados"]
    assert any(n.startswith("fatrop skipped") and "BLASFEO" in n for n in data["notes"])
    r = by_name["rti-acados"]
    assert r["fallback_steps"] == 0 and r["steps"] == 4
    assert 1 <= r["median_iterations"] <= r["settings"]["qp_solver_iter_max"]
    assert np.isfinite(r["cost"]["total"]) and r["cost"]["total"] > 0.0
    ph = r["phases"]  # every step has a feedback QP and at least one preparation
    assert ph["feedbacks"] >= 4 and ph["preparations"] >= 4 and ph["qp_iterations_median"] >= 1
    assert 0.0 < ph["feedback_median_ms"] <= ph["feedback_p99_ms"]
    assert r["settings"]["qp_solver"] == "PARTIAL_CONDENSING_HPIPM" and r["settings"]["nlp_solver"] == "SQP_RTI"
    assert r["settings"]["description"].startswith("StageOcp") and data["shared_description"]["all_share"]


@pytest.mark.parametrize("option, value, allowed", [
    ("hpipm_mode", "FAST", "one of"), ("cond_n", 0, r"\[1, 6\]"), ("warm_start", 3, "one of"),
    ("disturbances", "input", "one of"), ("qp_tol", 0.0, r"\(0.0, 1.0\]"), ("qp_tol", float("inf"), r"\(0.0, 1.0\]"),
    ("lm_inputs", float("inf"), r"\[0.0, 10000.0\]"), ("qp_iter_max", 2.5, "integer"),
    ("cold_start_qps", 0, r"\[1, 100\]"), ("reference_change_qps", 0, r"\[1, 100\]")])
def test_bad_options_are_named_with_their_range_before_anything_is_built(option, value, allowed):
    pb = TrackingProblem(Parameters(), OcpSpec(stage_durations_s=DURATIONS_S))
    with pytest.raises(InvalidValue, match=rf"RtiAcadosSolver\.{option}.*{allowed}"):
        RtiAcadosSolver(pb, **{option: value})


def test_the_install_identity_follows_libacados(tmp_path):
    ids = []
    for name, content in (("a", b"one build"), ("b", b"another build")):
        (tmp_path / name / "lib").mkdir(parents=True)
        (tmp_path / name / "lib" / "libacados.so").write_bytes(content)
        ids.append(install_id(tmp_path / name))
    assert ids[0] != ids[1] and ids[0] == install_id(tmp_path / "a")


def test_a_failed_compile_names_the_error_and_leaves_nothing_behind(tmp_path):
    src = tmp_path / "broken.c"
    src.write_text("int f(void) { return undeclared_name; }\n")
    lib = tmp_path / "cache" / "broken.so"
    with pytest.raises(RuntimeError, match="undeclared_name"):
        codegen.compile_shared(src, lib, ("-O2", "-fPIC", "-shared"))
    assert list(lib.parent.iterdir()) == []


def test_generation_settings_hold_only_while_generating(tmp_path, monkeypatch):
    monkeypatch.setenv("ACADOS_SOURCE_DIR", "/elsewhere/acados")
    monkeypatch.delenv("ACADOS_PYTHON_INTERFACE_PATH", raising=False)
    cwd = os.getcwd()
    install, folder = tmp_path / "acados" / "install", tmp_path / "solver"
    folder.mkdir()
    with _generation_env(install, folder):
        assert os.environ["ACADOS_SOURCE_DIR"] == str(install) and Path(os.getcwd()) == folder
    assert os.environ["ACADOS_SOURCE_DIR"] == "/elsewhere/acados"
    assert "ACADOS_PYTHON_INTERFACE_PATH" not in os.environ and os.getcwd() == cwd


def test_a_failed_solver_build_names_the_folder_and_make_s_message(tmp_path):
    (tmp_path / "Makefile").write_text("ocp_shared_lib:\n\t@echo missing_source_file >&2; exit 3\n")
    with pytest.raises(RuntimeError, match=r"make exit 2.*missing_source_file") as err:
        _make(tmp_path)
    assert str(tmp_path) in str(err.value)
