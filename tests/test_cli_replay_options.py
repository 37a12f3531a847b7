"""replay options: a refused calibration file is used but never silently; --viewer streams to rerun live."""

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


def test_viewer_flag_streams_to_a_live_rerun_viewer(rec_dir, tmp_path, monkeypatch):  # noqa: F811
    """``--viewer`` builds the rerun sink with ``spawn=True`` (the viewer itself is faked here)."""
    import pdr_mag.sinks.rerun as rr_sink

    made = []

    class FakeSink:
        def __init__(self, path=None, *, spawn=False):
            made.append((path, spawn))

        def __getattr__(self, name):
            return lambda *a, **k: None

    monkeypatch.setattr(rr_sink, "RerunSink", FakeSink)
    assert main(["replay", str(rec_dir), "--viewer", "-q"]) == 0
    assert made == [(None, True)]
