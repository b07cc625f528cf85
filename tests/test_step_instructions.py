"""The instruction count of the step (benchmarks/step_instructions.py) and the interpreter of a version in
benchmarks/step_versions.py."""

import shutil
from collections import Counter

import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time, step_instructions, step_versions
from hvac_mpc.benchmarks.step_instructions import kind_of, self_costs, summary

SITE = "/v/lib/python3.11/site-packages"


def test_each_shared_object_goes_to_its_kind():
    assert kind_of("/root/.pyenv/versions/3.11.7/lib/libpython3.11.so.1.0") == "python interpreter"
    assert kind_of("/usr/bin/python3.11") == "python interpreter"
    assert kind_of(f"{SITE}/numpy/_core/_multiarray_umath.cpython-311-x86_64-linux-gnu.so") == "numpy"
    assert kind_of(f"{SITE}/numpy.libs/libscipy_openblas64_-32a4b2a6.so") == "openblas"
    assert kind_of(f"{SITE}/scipy.libs/libscipy_openblas-6cdc3b4a.so") == "openblas"
    assert kind_of("/tmp/cache/osqp/tmpcmmweazu.so") == "osqp generated"
    assert kind_of(f"{SITE}/osqp/ext_builtin.cpython-311-x86_64-linux-gnu.so") == "other"
    assert kind_of("/tmp/cache/hvac_qp_data_1485c45e3b1ed494874f.so") == "casadi generated"
    assert kind_of(f"{SITE}/casadi/libcasadi.so.3.7") == "casadi library"
    assert kind_of("/usr/lib/x86_64-linux-gnu/libffi.so.8.1.2") == "libffi (ctypes)"
    assert kind_of("/usr/lib/x86_64-linux-gnu/libc.so.6") == "libc, libm, loader"
    assert kind_of("/usr/lib/x86_64-linux-gnu/libcrypto.so.3") == "other"


def test_self_costs_skip_the_calls_and_carry_the_names(tmp_path):
    first = tmp_path / "cg.1.1-01"
    first.write_text("\n".join([
        "events: Ir", "ob=(1) /lib/libpython3.11.so", "fl=(1) a.c", "fn=(1) f", "10 100", "+1 5",
        "cob=(2) /tmp/cache/osqp/tmpx.so", "cfn=(2) g", "calls=1 0", "12 700",  # inclusive: not counted here
        "ob=(2)", "fl=(2) b.c", "fn=(2) g", "3 700", "totals: 805"]))
    second = tmp_path / "cg.1.2-01"
    second.write_text("\n".join(["events: Ir", "ob=(2)", "fn=(2)", "3 40", "ob=(1)", "fn=(1)", "* 2"]))
    names: dict[str, str] = {}
    assert self_costs(first, names) == Counter({"/lib/libpython3.11.so": 105, "/tmp/cache/osqp/tmpx.so": 700})
    # the second dump names its objects by number only: the names of the first carry over
    assert self_costs(second, names) == Counter({"/tmp/cache/osqp/tmpx.so": 40, "/lib/libpython3.11.so": 2})


def test_summary_counts_steps_and_kinds():
    steps = [{"objects": {"/tmp/c/osqp/a.so": 1000}, "iterations": 50, "qp_solves": 1}] + [
        {"objects": {"/tmp/c/osqp/a.so": 300 + k, "/lib/libpython3.11.so": 100}, "iterations": 15, "qp_solves": 1}
        for k in range(1, 10)]
    s = summary({"steps": steps}, quiet={2, 3, 4})
    totals = np.array([400 + k for k in range(1, 10)], dtype=float)
    assert s["median"] == np.median(totals) and s["max"] == totals.max()
    assert s["quiet_median"] == 403.0 and s["quiet_steps"] == 3
    assert s["osqp_iterations"] == 50 + 9 * 15
    assert s["kinds_quiet_mean"]["osqp generated"] == 303.0
    assert s["kinds_quiet_mean"]["python interpreter"] == 100.0
    assert s["kinds_quiet_share"]["openblas"] == 0.0
    assert abs(sum(s["kinds_quiet_share"].values()) - 1.0) < 1e-12


def test_a_version_runs_on_the_interpreter_asked_for(monkeypatch):
    seen = []

    class Proc:
        def __init__(self, argv, **kwargs):
            seen.append(argv)
            self.stdout = type("R", (), {"readline": staticmethod(lambda: "ready\n")})()

    monkeypatch.setattr(step_versions.subprocess, "Popen", Proc)
    step_versions.Version(None, 1, python="/other/venv/bin/python")
    step_versions.Version(None, 1)
    assert seen[0][0] == "/other/venv/bin/python"
    assert seen[1][0] == step_versions.sys.executable


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None or shutil.which("gcc") is None,
                    reason="needs valgrind and gcc")
def test_the_counted_loop_takes_the_native_path(tmp_path, monkeypatch):
    """Under callgrind with the long deadline the loop gives the commands of the loop run natively with the
    default settings (the deadline never binds there), and the step runs OSQP's and CasADi's generated code."""
    from hvac_mpc.mpc import codegen
    from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")  # the suite runs the interpreter (conftest); the loop is compiled
    steps = 4
    # natively first: the generated code is built (or loaded) here, so the run under valgrind only loads it
    loop = solve_time.Loop(MpcController(settings=MpcSettings()), 1, idle_s=solve_time.IDLE_S)
    native = [list(loop.step(k).command.vector()) for k in range(steps)]
    counted = step_instructions.count(steps, 1, None, tmp_path)
    assert [s["command"] for s in counted["steps"]] == native
    kinds = Counter()
    for obj, n in counted["steps"][-1]["objects"].items():
        kinds[kind_of(obj)] += n
    assert kinds["osqp generated"] > 0 and kinds["casadi generated"] > 0
