import subprocess
import sys

import pytest

from hvac_mpc.cli import SUBCOMMANDS


def test_top_level_help_lists_every_subcommand():
    out = subprocess.run([sys.executable, "-m", "hvac_mpc", "--help"], capture_output=True, text=True, check=True)
    for name in SUBCOMMANDS:
        assert name in out.stdout


@pytest.mark.parametrize("name", sorted(SUBCOMMANDS))
def test_each_subcommand_has_help(name):
    out = subprocess.run([sys.executable, "-m", "hvac_mpc", name, "--help"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "usage: hvac-mpc " + name in out.stdout


def test_unknown_subcommand_fails_with_usage():
    out = subprocess.run([sys.executable, "-m", "hvac_mpc", "frobnicate"], capture_output=True, text=True)
    assert out.returncode == 2 and "invalid choice" in out.stderr
