"""House style that a machine can check: ruff clean; ``python -m pdr_mag`` is the command line."""

import shutil
import subprocess
import sys

import pytest

from tests.conftest import ROOT


def test_ruff_clean():
    ruff = shutil.which("ruff")
    if ruff is None:
        pytest.skip("ruff is not installed (it comes with the test extra)")
    out = subprocess.run([ruff, "check", "--quiet", str(ROOT)], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout[-3000:]


def test_python_dash_m_is_the_cli():
    out = subprocess.run([sys.executable, "-m", "pdr_mag", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    for cmd in ("simulate", "calibrate", "replay", "diagnose"):
        assert cmd in out.stdout
