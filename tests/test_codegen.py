"""Generated C for the hot path: built on first use into the cache, loaded afterwards, the same
results as CasADi's interpreter (also for other model parameters, which are inputs of the
generated code), and the interpreter when no compiler is there.

Budget: about 35 s on a loaded two-core machine (one build of the QP data and the estimator's
functions into an empty cache folder, four short closed loops); the slow test builds the
estimator's update three times (about 10 s).
"""

import casadi as ca
import numpy as np
import pytest

from hvac_mpc.benchmarks import solve_time
from hvac_mpc.models import HvacModel, Parameters
from hvac_mpc.mpc import codegen
from hvac_mpc.mpc.estimator import DisturbanceEkf
from hvac_mpc.mpc.mpc_controller import MpcController, MpcSettings
from hvac_mpc.mpc.ocp import OcpSpec, Weights


def _commands(settings: MpcSettings, steps: int, params: Parameters | None = None
              ) -> tuple[np.ndarray, MpcController]:
    ctrl = MpcController(params, settings)
    loop = solve_time.Loop(ctrl, seed=3)
    out = []
    for k in range(steps):
        # reference changes at 0 and 30 s: a cold start, then the two-QP path
        res = loop.step(k)
        assert res.stats["fallback"] is None
        out.append(res.command.vector())
    return np.array(out), ctrl


@pytest.mark.slow  # builds every generated function at -O3 from an empty cache (about 19 s)
def test_compiled_and_interpreted_closed_loops_give_the_same_commands_from_an_empty_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(codegen.CACHE_ENV, str(tmp_path))
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    compiled_cmds, ctrl = _commands(MpcSettings(codegen=True), 34)
    assert ctrl.codegen.active
    assert set(ctrl.codegen.outcomes.values()) == {"built"}
    assert len(list(tmp_path.glob("*.so"))) == len(ctrl.codegen.outcomes)
    interpreted_cmds, vm = _commands(MpcSettings(codegen=False), 34)
    assert not vm.codegen.active
    assert np.allclose(compiled_cmds, interpreted_cmds, rtol=0.0, atol=1e-9)
    # a second controller with the same model loads the shared objects instead of building them
    again = MpcController(settings=MpcSettings(codegen=True))
    assert set(again.codegen.outcomes.values()) == {"cached"}
    # so does a controller with other model parameters (inputs of the generated code), with the
    # interpreter's results for those parameters
    other = Parameters(tau_tc_s=7.5, heater_power_max_w=200.0, blower_power_max_w=280.0)
    other_cmds, other_ctrl = _commands(MpcSettings(codegen=True), 12, other)
    assert set(other_ctrl.codegen.outcomes.values()) == {"cached"}
    assert len(list(tmp_path.glob("*.so"))) == len(ctrl.codegen.outcomes)
    other_vm, _ = _commands(MpcSettings(codegen=False), 12, other)
    assert np.allclose(other_cmds, other_vm, rtol=0.0, atol=1e-9)
    assert not np.allclose(other_cmds, compiled_cmds[:12], rtol=0.0, atol=1e-3)


def test_weights_are_inputs_of_the_generated_code_and_the_model_is_part_of_its_key(tmp_path, monkeypatch):
    monkeypatch.setenv(codegen.CACHE_ENV, str(tmp_path))
    base = MpcController(settings=MpcSettings(codegen=False)).solver
    reweighted = MpcController(settings=MpcSettings(codegen=False, levenberg_marquardt=0.5, ocp=OcpSpec(
        weights=Weights(move_blower_per_w2=1e-3, slack_l1_per_c=9.0)))).solver
    other_model = MpcController(settings=MpcSettings(codegen=False, ocp=OcpSpec(
        model_effects=("fan_curve", "valve_leakage")))).solver
    other_params = MpcController(Parameters(tau_tc_s=7.5, heater_power_max_w=200.0),
                                 MpcSettings(codegen=False))
    key = codegen.structure_key
    assert key(base.qp_data) == key(reweighted.qp_data)
    assert key(base.qp_gradient) == key(reweighted.qp_gradient)
    assert key(base.qp_data) != key(other_model.qp_data)
    # model parameters are inputs too: another parameter set of the same structure builds nothing new
    assert key(base.qp_data) == key(other_params.solver.qp_data)
    base_ekf = MpcController(settings=MpcSettings(codegen=False)).ekf
    for name in ("update_fn", "predict_fn"):
        assert key(getattr(base_ekf, name)) == key(getattr(other_params.ekf, name))
    # code built for this processor (-march=native) is another build on another processor
    assert "-march=native" in codegen.CFLAGS and codegen.processor()
    here = key(base.qp_data)
    monkeypatch.setattr(codegen, "processor", lambda: "another processor")
    assert key(base.qp_data) != here


def test_without_a_compiler_the_interpreter_runs_the_same_function(tmp_path, monkeypatch):
    monkeypatch.setenv(codegen.CACHE_ENV, str(tmp_path))
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")
    monkeypatch.setattr(codegen, "compiler", lambda: None)
    x = ca.SX.sym("x", 2)
    fn = ca.Function("hvac_test_square", [x], [x * x])
    report = codegen.CodegenReport()
    out = codegen.compiled(fn, report)
    assert out is fn
    assert report.outcomes["hvac_test_square"].startswith("interpreted: RuntimeError: no C compiler")
    assert not report.active
    assert not list(tmp_path.glob("*.so"))
    monkeypatch.setenv(codegen.SWITCH_ENV, "0")
    assert codegen.compiled(fn, report) is fn
    assert "HVAC_MPC_CODEGEN=0" in report.outcomes["hvac_test_square"]


def test_cache_folder_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv(codegen.CACHE_ENV, str(tmp_path / "c"))
    assert codegen.cache_dir() == tmp_path / "c"
    monkeypatch.delenv(codegen.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert codegen.cache_dir() == tmp_path / "xdg" / "hvac-mpc"


@pytest.mark.slow
def test_a_change_of_structure_builds_anew_and_a_change_of_parameters_does_not(tmp_path, monkeypatch):
    monkeypatch.setenv(codegen.CACHE_ENV, str(tmp_path))
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")

    def outcome(params=None, effects=("fan_curve", "valve_leakage", "bypass_flow")):
        ekf = DisturbanceEkf(HvacModel(params or Parameters(), effects))
        report = codegen.CodegenReport()
        codegen.compiled(ekf.update_fn, report)
        return report.outcomes["ekf_update"]

    assert outcome() == "built"
    assert outcome() == "cached"
    assert outcome(Parameters(tau_tc_s=7.5, heater_power_max_w=200.0)) == "cached"
    assert outcome(effects=("fan_curve", "valve_leakage", "trapped_air")) == "built"  # one more state
    assert outcome(Parameters(transport_delay_s=2.0)) == "built"  # delay lags are states
    assert len(list(tmp_path.glob("ekf_update_*.so"))) == 3


def test_the_small_functions_of_the_step_run_compiled_with_the_interpreters_values(monkeypatch):
    """The open-loop shadow's step and airs and the reachable-flow check's outputs run as generated C with codegen on
    (each step calls them), and give the interpreter's values to the bit on states, commands and disturbances
    drawn over the box's range (no fast-math, no fused multiply-adds: the same operations in the same order)."""
    from hvac_mpc.mpc.casadi_eval import BufferedFunction
    monkeypatch.setenv(codegen.SWITCH_ENV, "1")  # the code cache of the run: the large functions are built once
    ctrl = MpcController(settings=MpcSettings(codegen=True))
    ekf = ctrl.ekf
    functions = [ekf.shadow.step_fn, ekf.shadow.air_fn, ctrl.reach.out_fn]
    for fn in functions:
        assert ctrl.codegen.outcomes[fn.name()] in ("built", "cached")
    assert ctrl.ekf.shadow._step.fn.is_a("External") and ctrl.reach._out.fn.is_a("External")
    rng = np.random.default_rng(11)
    nx, n_own = ekf.nx, len(ekf.shadow.idx)
    pairs = [(BufferedFunction(fn), BufferedFunction(codegen.compiled(fn))) for fn in functions]
    for _ in range(300):
        x = rng.uniform(0.0, 45.0, nx)
        u = rng.uniform(0.0, 1.0, 6) * np.array([300.0, 250.0, 100.0, 100.0, 100.0, 100.0])
        d = np.array([rng.uniform(-10.0, 40.0), rng.uniform(2.0, 12.0), rng.uniform(-2.0, 2.0),
                      rng.uniform(-0.01, 0.01)])
        own = rng.uniform(0.0, 45.0, n_own)
        args = [(x, own, u, d, ekf.p), (x, u, d, ekf.p), (x, u, d, ctrl.reach._p)]
        for (vm, c), a in zip(pairs, args):
            for r_vm, r_c in zip(vm(*a), c(*a)):
                assert np.array_equal(r_vm, r_c)


def test_kept_builds_once_per_key_and_holds_the_last_ones(monkeypatch):
    """codegen.kept: the first call with a key builds, the next ones return that function as it is; another key
    builds its own; past KEPT_MAX keys the least recently asked for is built again, one asked for since is not."""
    monkeypatch.setattr(codegen, "_KEPT", {})  # an empty memo, whatever the process built before
    x = ca.SX.sym("x")
    built = []

    def build(k):
        built.append(k)
        return ca.Function(f"f{k}", [x], [x * k])

    first = codegen.kept("test kept 1", lambda: build(1))
    assert codegen.kept("test kept 1", lambda: build(1)) is first and built == [1]
    assert float(codegen.kept("test kept 2", lambda: build(2))(3.0)) == 6.0 and built == [1, 2]
    for k in range(codegen.KEPT_MAX - 2):
        codegen.kept(f"test kept fill {k}", lambda: ca.Function("g", [x], [x]))
    assert codegen.kept("test kept 1", lambda: build(1)) is first  # asked for again: now the most recent
    codegen.kept("test kept fill last", lambda: ca.Function("g", [x], [x]))  # one more: key 2, the least recent, goes
    assert codegen.kept("test kept 1", lambda: build(1)) is first and built == [1, 2]
    codegen.kept("test kept 2", lambda: build(2))
    assert built == [1, 2, 2]


def test_two_controllers_of_one_structure_share_their_stages_qp_data_and_another_structure_does_not(monkeypatch):
    """The stages' QP data (rti_osqp._stage_qp_function, common subexpressions found once per expression): a second
    controller of the same structure takes the first one's functions, one of other model effects builds its own."""
    from hvac_mpc.mpc import rti_osqp
    built = []
    real = rti_osqp.kept
    monkeypatch.setattr(rti_osqp, "kept", lambda key, build: real(key, lambda: built.append(key) or build()))
    one = MpcController(settings=MpcSettings(codegen=False)).solver
    n_one = len(built)  # 0 where an earlier test of this process built the structure
    two = MpcController(settings=MpcSettings(codegen=False)).solver
    assert len(built) == n_one  # the second controller built none of the stages' QP data
    other = MpcController(settings=MpcSettings(codegen=False, ocp=OcpSpec(
        model_effects=("fan_curve", "valve_leakage")))).solver
    for n, stage in one.pb.stages_p.items():
        assert one._stage_qp_function(stage) is two._stage_qp_function(two.pb.stages_p[n])
        assert one._stage_qp_function(stage) is not other._stage_qp_function(other.pb.stages_p[n])
    assert codegen.structure_key(one.qp_data) == codegen.structure_key(two.qp_data)


def test_two_threads_asking_for_one_structure_at_once_build_it_once(tmp_path, monkeypatch):
    """The build lock (``codegen._ensure``): the second asker waits for the first's build and loads it."""
    import contextlib
    import threading
    import time

    lib = tmp_path / "f_demo_0123.so"
    calls, asked, at_lock = [], [], threading.Event()
    real = codegen._build_lock

    @contextlib.contextmanager
    def lock(path):
        asked.append(path)
        if len(asked) == 2:
            at_lock.set()  # the second asker has found no file and is at the lock
        with real(path):
            yield

    monkeypatch.setattr(codegen, "_build_lock", lock)

    def build():
        calls.append(threading.get_ident())
        assert at_lock.wait(10.0)
        time.sleep(0.2)  # without a lock the second asker would be building by now
        lib.write_bytes(b"built")

    outcomes = {}

    def ask(name):
        outcomes[name] = codegen._ensure(lib, build, codegen.CodegenReport())

    threads = [threading.Thread(target=ask, args=(name,)) for name in ("first", "second")]
    threads[0].start()
    while not calls:
        time.sleep(0.01)
    threads[1].start()
    for thread in threads:
        thread.join(30.0)
    assert len(calls) == 1 and outcomes == {"first": "built", "second": "cached"}
