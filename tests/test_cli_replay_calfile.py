"""A calibration file that the calibration core refused is used, but never silently."""

from __future__ import annotations

from pdr_mag.calibration.model import MagCalibration
from replay.cli import main
from tests.test_cli_replay import rec_dir  # noqa: F401  (module-scoped fixture)
from tests.test_online import B_TRUE, F


def test_refused_calibration_file_warns_on_stderr(rec_dir, tmp_path, capsys):  # noqa: F811
    cal = tmp_path / "cal.json"
    MagCalibration.from_arrays(
        B_TRUE, None, field_uT=F, method="sphere", accepted=False, reasons=["coverage 0.12 < 0.40"]
    ).to_json(cal)
    assert main(["replay", str(rec_dir), "--calibration", str(cal), "-q"]) == 0
    err = capsys.readouterr().err
    assert "not accepted" in err and "coverage 0.12" in err and "cal.json" in err
