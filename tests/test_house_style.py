"""House style that a machine can check: ruff clean; ``python -m pdr_mag`` is the command line; a missing
real recording skips a test, except under CI=true."""

import subprocess
import sys

import pytest

from tests.conftest import ROOT


def test_ruff_clean():
    """ruff comes with the test extra (pyproject.toml): its absence is a broken install, not a skip."""
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "--quiet", str(ROOT)], capture_output=True,
                         text=True)
    assert "No module named ruff" not in out.stderr, "ruff is not installed: pip install -e '.[test]'"
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-1000:]


def test_python_dash_m_is_the_cli():
    out = subprocess.run([sys.executable, "-m", "pdr_mag", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    for cmd in ("simulate", "calibrate", "replay", "diagnose"):
        assert cmd in out.stdout


def test_missing_datasets_skip_but_fail_under_ci(monkeypatch, tmp_path):
    """tests.conftest.dataset: a real recording that is absent skips the test, except under CI=true."""
    from tests import conftest

    monkeypatch.setattr(conftest, "DATASETS", tmp_path / "no-datasets")
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="not found"):
        conftest.dataset("tyrex-pdrcsv", "calib_mag_Nexus5_d1")
    for value in ("true", "1"):
        monkeypatch.setenv("CI", value)
        with pytest.raises(pytest.fail.Exception, match="required under CI=true"):
            conftest.dataset("tyrex-pdrcsv", "calib_mag_Nexus5_d1")
