"""The layers hold (import-linter contracts in pyproject.toml) and the public API stays stable.

The package's subpackages live in top-level folders (``models/`` -> ``hvac_mpc.models``); the
linter walks one folder per package, so the test lays the package out as installed, in a
temporary folder, and lints that copy.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from hvac_mpc.benchmarks.step_versions import installed_layout

ROOT = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")


def _installed_layout(dest: Path) -> Path:
    return installed_layout(ROOT, dest)


def _lint(tree: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(tree))
    return subprocess.run([str(LINT), "--config", str(ROOT / "pyproject.toml"), "--no-cache"], cwd=tree, env=env,
                          capture_output=True, text=True, timeout=120)


def test_layers_hold_and_no_import_cycles(tmp_path):
    result = _lint(_installed_layout(tmp_path))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "2 kept, 0 broken" in result.stdout


def test_the_linter_catches_an_upward_import_and_a_cycle(tmp_path):
    tree = _installed_layout(tmp_path)
    with open(tree / "hvac_mpc/models/air.py", "a") as f:
        f.write("\nfrom hvac_mpc.mpc import baseline  # upward\n")
    with open(tree / "hvac_mpc/daemon/io.py", "a") as f:
        f.write("\nfrom hvac_mpc.daemon import backends  # cycle with backends -> io\n")
    result = _lint(tree)
    assert result.returncode != 0
    assert "hvac_mpc.models.air -> hvac_mpc.mpc.baseline" in result.stdout
    assert "0 kept, 2 broken" in result.stdout


def test_public_api_from_the_package():
    import hvac_mpc

    names = {"Parameters", "HvacModel", "SimulatedPlant", "Command", "Measurement", "Reference",
             "MpcController", "MpcSettings", "BaselineController", "load_model_file", "identify"}
    assert names <= set(hvac_mpc.__all__)
    for name in names:
        assert getattr(hvac_mpc, name) is not None
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        getattr(hvac_mpc, "Nope")
    from hvac_mpc.contract import Command
    from hvac_mpc.models.plant import Command as PlantCommand
    from hvac_mpc.mpc.reference import Reference as OldReference
    assert hvac_mpc.Command is Command is PlantCommand and hvac_mpc.Reference is OldReference


def test_readme_example_runs_as_written():
    """The README's ten-line example, extracted and run in a fresh interpreter."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```python\n(.*?)```", text, re.S)
    assert block, "README has no ```python example"
    code = block.group(1)
    assert len(code.strip().splitlines()) <= 15
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert "supply" in result.stdout


def test_no_source_file_points_outside_the_repository():
    pattern = re.compile(r"\.\./shared|shared/|design\.md|thesis\.md|research/")
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    folders = ["hvac_mpc", "tests", *cfg["tool"]["setuptools"]["package-dir"].values()]
    offenders = [f"{p.relative_to(ROOT)}:{i}" for folder in folders for p in (ROOT / folder).rglob("*.py")
                 if p.name != "test_architecture.py"
                 for i, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert offenders == [], offenders
