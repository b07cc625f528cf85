"""Identification's whole-log runs as generated C built beside the caller (mpc/codegen_background.py): the same
values to the bit as CasADi's interpreter, built once per structure, found in the cache by the next process."""

import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from hvac_mpc.identification.log_data import load
from hvac_mpc.identification.pipeline import DOCUMENTED_EFFECTS
from hvac_mpc.identification.simulator import Simulator
from hvac_mpc.mismatch import simulate_log
from hvac_mpc.models import Parameters
from hvac_mpc.mpc import codegen_background as cb

pytestmark = pytest.mark.skipif(cb.compiler() is None or shutil.which("sh") is None or cb.fcntl is None,
                                reason="no C compiler, POSIX shell or file locks: the runs stay in CasADi's interpreter")


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """20 min of the independent box with three effects the model lacks (recirculation, a delay, shifted valves)."""
    path = tmp_path_factory.mktemp("log") / "combo.csv"
    simulate_log(path, "combo_recirc_delay_valve", duration_s=1200.0, seed=31)
    return load(path)


def _sim(log, builds=None):
    """The documented model's simulator on ``log``, its step functions with ``builds`` (None: interpreted)."""
    return Simulator(log, Parameters(), DOCUMENTED_EFFECTS, tuple(log.outputs), builds=builds)


def _runs(log, builds):
    """A free run and the sensitivities of four parameters on ``log``, with ``builds`` (None: interpreted)."""
    return _runs_on(_sim(log, builds))


def _runs_on(sim):
    """A free run and the sensitivities of four parameters by ``sim`` (its kept runs forgotten first)."""
    sim._runs = []
    p = np.asarray(Parameters().vector())
    e = np.zeros((len(p), 4))
    for j, i in enumerate((0, 3, 7, 11)):
        e[i, j] = 1.0
    y, states = sim.simulate(p)
    y_s, dy = sim.simulate_with_sensitivity(p, e)
    return y, states, y_s, dy


def test_the_generated_runs_give_the_interpreters_values_to_the_bit_and_the_next_process_finds_them(
        log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    reference = _runs(log, None)
    builds = cb.BackgroundBuilds(after=0, wait=True, on=True)
    compiled = _runs(log, builds)
    assert builds.summary() == {"built": 2}, builds.outcomes  # the free run's step and the sensitivities' step
    for a, b in zip(reference, compiled):
        assert np.array_equal(a, b, equal_nan=True)
    assert len(list(tmp_path.glob("*.so"))) == 2 and not _slot_folders(tmp_path)
    again = cb.BackgroundBuilds(after=0, wait=True, on=True)
    for a, b in zip(reference, _runs(log, again)):
        assert np.array_equal(a, b, equal_nan=True)
    assert again.summary() == {"cached": 2}, again.outcomes


def test_a_function_is_built_only_after_the_calls_asked_for(log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    sim = _sim(log)
    builds = cb.BackgroundBuilds(after=2, wait=True, on=True)
    assert builds.function(sim.f_step_y) is sim.f_step_y
    assert builds.function(sim.f_step_y) is sim.f_step_y
    assert builds.summary() == {"counted": 1} and not list(tmp_path.glob("*.so"))
    third = builds.function(sim.f_step_y)
    assert third is not sim.f_step_y and builds.summary() == {"built": 1}
    assert builds.function(sim.f_step_y) is third  # loaded once


def _hold(cache, k: int, target: str) -> int:
    """Build slot ``k`` of ``cache`` held as another process's build holds it (building ``target``): the descriptor
    holding its lock (closing it ends that build)."""
    (cache / f".slot_{k}").mkdir()
    (cache / f".slot_{k}" / "target").write_text(target)
    fd = os.open(cache / f".slot_{k}.lock", os.O_RDWR | os.O_CREAT)
    cb.fcntl.flock(fd, cb.fcntl.LOCK_EX)
    return fd


def _stem(sim) -> str:
    probe = cb.BackgroundBuilds(after=10, on=True)  # counts, starts nothing
    probe.function(sim.f_y)
    (stem,) = probe.outcomes
    return stem


def _slot_folders(cache):
    return sorted(p for p in cache.glob(".slot_*") if p.is_dir())


def test_a_build_under_way_elsewhere_is_not_started_again_and_a_killed_ones_slot_is_taken_over(log, tmp_path,
                                                                                              monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    sim = _sim(log)
    fd = _hold(tmp_path, 0, f"{_stem(sim)}.so")  # another process builds it
    held = cb.BackgroundBuilds(after=0, wait=True, on=True)
    assert held.function(sim.f_y) is sim.f_y and held.summary() == {"counted": 1}
    assert _slot_folders(tmp_path) == [tmp_path / ".slot_0"]  # no second build of it
    os.close(fd)  # that build was killed: its lock is free, its folder left behind
    assert held.function(sim.f_y) is not sim.f_y and held.summary() == {"built": 1}
    assert _slot_folders(tmp_path) == []


def test_no_build_starts_while_every_slot_is_taken(log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    sim = _sim(log)
    fds = [_hold(tmp_path, k, f"other_{k}.so") for k in range(cb.MAX_BUILDS)]
    builds = cb.BackgroundBuilds(after=0, wait=True, on=True)
    assert builds.function(sim.f_y) is sim.f_y and builds.summary() == {"counted": 1}
    assert [(p / "target").read_text() for p in _slot_folders(tmp_path)] == [f"other_{k}.so" for k in
                                                                              range(cb.MAX_BUILDS)]
    os.close(fds[-1])  # one build ends
    assert builds.function(sim.f_y) is not sim.f_y and builds.summary() == {"built": 1}  # its slot taken
    for fd in fds[:-1]:
        os.close(fd)


def test_a_detached_build_is_loaded_once_it_is_there_with_the_same_values(log, tmp_path, monkeypatch):
    """The mode an identification runs in: the caller goes on interpreted, the build ends on its own (at the caller's
    priority here: at the lowest, beside two busy test workers, it may take minutes)."""
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(cb, "NICENESS", 0)
    reference = _runs(log, None)
    builds = cb.BackgroundBuilds(after=0, on=True)
    sim = _sim(log, builds)
    first = _runs_on(sim)
    assert set(builds.outcomes.values()) <= {"building", "built"}, builds.outcomes  # not waited for
    deadline = time.monotonic() + 120.0
    while len(list(tmp_path.glob("*.so"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert len(list(tmp_path.glob("*.so"))) == 2, list(tmp_path.iterdir())
    deadline = time.monotonic() + 10.0  # the slot is freed just after the move
    while _slot_folders(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _slot_folders(tmp_path)
    second = _runs_on(sim)
    assert builds.summary() == {"built": 2}, builds.outcomes  # the same simulator switched to the C form
    for a, b, c in zip(reference, first, second):
        assert np.array_equal(a, b, equal_nan=True) and np.array_equal(a, c, equal_nan=True)


def test_a_failed_build_leaves_a_note_and_is_not_tried_again_until_the_note_is_old(log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(cb, "CFLAGS", ("-no-such-flag",))
    sim = _sim(log)
    builds = cb.BackgroundBuilds(after=0, wait=True, on=True)
    assert builds.function(sim.f_y) is sim.f_y
    (outcome,) = builds.outcomes.values()
    assert outcome.startswith("failed: ") and "no-such-flag" in Path(outcome[8:]).read_text()
    again = cb.BackgroundBuilds(after=0, wait=True, on=True)
    assert again.function(sim.f_y) is sim.f_y and again.summary() == {"failed": 1}
    assert not _slot_folders(tmp_path)  # no build started


def test_switched_off_the_runs_stay_interpreted_and_nothing_is_written(log, tmp_path, monkeypatch):
    monkeypatch.setenv("HVAC_MPC_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv(cb.RUN_BUILDS_ENV, "0")
    builds = cb.BackgroundBuilds(after=0, wait=True)
    assert not builds.on
    sim = _sim(log, builds)
    sim.simulate(np.asarray(Parameters().vector()))
    assert builds.outcomes == {} and not any(tmp_path.iterdir())
    monkeypatch.setenv(cb.RUN_BUILDS_ENV, "1")
    monkeypatch.setenv("HVAC_MPC_CODEGEN", "0")
    assert cb.BackgroundBuilds().on  # the MPC's switch off, these builds asked for
    monkeypatch.delenv(cb.RUN_BUILDS_ENV)
    assert not cb.BackgroundBuilds().on  # the MPC's switch alone turns them off too

