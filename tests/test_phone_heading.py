"""The phone's own heading on the rows whose heading pdr_mag does not know
(:func:`pdr_mag.pipeline.fill_unknown_heading`, used by ``replay``): the rows at σ 180° take the latest
attitude the phone gave at or before them, keep their tilt and their std; the others are untouched."""

from __future__ import annotations

import numpy as np
import pytest

from pdr_mag.calibration.prior import PriorSettings
from pdr_mag.conventions import (
    heading_deg_from_quat,
    quat_multiply,
    quat_rotate,
    rotation_about_up,
    rotation_to_quat,
    wrap_deg,
)
from pdr_mag.estimates import EstimateBatch
from pdr_mag.pipeline import PipelineSettings, fill_unknown_heading
from pdr_mag.pipeline.phone_heading import UNKNOWN_STD_DEG
from pdr_mag.sim import simulate
from replay.recording import Recording, Stream
from replay.run import MemorySink, replay

#: the phone's fusion in the simulated walks: the truth turned by this much about Up, deg
PHONE_OFF_DEG = 7.0


def _yaw(deg):
    """w-first quaternions (N, 4) of turns about Up by ``deg`` (counter-clockwise seen from above)."""
    return rotation_to_quat(rotation_about_up(np.radians(deg)))


def _batch(n=6):
    """Rows 0.1 s apart, tilted 20° about the device's x, headings 10°, 20°, …; rows 1, 2 and 4 unknown."""
    t = 10.0 + 0.1 * np.arange(n)
    tilt = np.array([np.cos(np.radians(10.0)), np.sin(np.radians(10.0)), 0.0, 0.0])
    q = quat_multiply(_yaw(-10.0 * (1 + np.arange(n))), np.tile(tilt, (n, 1)))
    std = np.full(n, 5.0)
    std[[1, 2, 4]] = 180.0
    return EstimateBatch(t=t, q_wd=q, heading_deg=heading_deg_from_quat(q), heading_std_deg=std,
                         mag_used=np.zeros(n, bool), interference=np.zeros(n, bool),
                         cal_state=np.array(["none"] * n))


def test_unknown_rows_take_the_phone_heading_with_their_own_tilt_and_std():
    b = _batch()
    t_ph = np.array([9.0, 10.05, 10.25])  # the row at 10.1 s takes 10.05's, 10.2 s too, 10.4 s 10.25's
    q_ph = quat_multiply(_yaw([-250.0, -300.0, -40.0]), np.tile([np.cos(0.3), 0.0, np.sin(0.3), 0.0], (3, 1)))
    out, rows = fill_unknown_heading(b, t_ph, q_ph)
    assert rows.tolist() == [1, 2, 4]
    np.testing.assert_allclose(wrap_deg(out.heading_deg[[1, 2, 4]] - [300.0, 300.0, 40.0]), 0.0, atol=1e-9)
    np.testing.assert_allclose(out.heading_deg, heading_deg_from_quat(out.q_wd), atol=1e-9)
    up = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(quat_rotate(out.q_wd, np.tile(up, (6, 1)), inverse=True),
                               quat_rotate(b.q_wd, np.tile(up, (6, 1)), inverse=True), atol=1e-12)
    assert np.all(out.q_wd[:, 0] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(out.q_wd, axis=1), 1.0, atol=1e-12)
    for k in (0, 3, 5):  # the rows the filter knows: bitwise as they were
        assert np.array_equal(out.q_wd[k], b.q_wd[k]) and out.heading_deg[k] == b.heading_deg[k]
    assert np.array_equal(out.heading_std_deg, b.heading_std_deg)
    fresh = _batch()  # the input batch is not changed
    assert np.array_equal(b.q_wd, fresh.q_wd) and np.array_equal(b.heading_deg, fresh.heading_deg)


def test_only_an_attitude_at_or_before_the_row_and_at_most_max_age_old_is_taken():
    b = _batch()
    later = fill_unknown_heading(b, np.array([10.45]), _yaw([-90.0]))  # after rows 1, 2 and 4 (10.4 s)
    assert len(later[1]) == 0 and np.array_equal(later[0].q_wd, b.q_wd)
    old = fill_unknown_heading(b, np.array([9.0]), _yaw([-90.0]), max_age_s=1.15)  # 1.1, 1.2, 1.4 s old
    assert old[1].tolist() == [1] and old[0].heading_deg[1] == pytest.approx(90.0)
    assert old[0].heading_deg[2] == b.heading_deg[2] and old[0].heading_deg[4] == b.heading_deg[4]
    bad = fill_unknown_heading(b, np.array([10.0]), np.array([[np.nan, 0.0, 0.0, 0.0]]))
    assert len(bad[1]) == 0
    scaled = fill_unknown_heading(b, np.array([10.0]), 3.0 * _yaw([-70.0]))  # not a unit quaternion
    np.testing.assert_allclose(scaled[0].heading_deg[[1, 2, 4]], 70.0, atol=1e-9)
    assert len(fill_unknown_heading(b, np.empty(0), np.empty((0, 4)))[1]) == 0
    with pytest.raises(ValueError, match="2 times for 1 attitudes"):
        fill_unknown_heading(b, np.array([1.0, 2.0]), _yaw([0.0]))


def _pocket(references: bool, settings=None):
    """The simulated pocket walk (seed 1: no heading for its first 15 s, the online calibration's first
    fit), replayed without a calibration; with ``references`` the phone's attitude is the truth turned by
    ``PHONE_OFF_DEG``.  Returns the rows, the summary and the phone's attitude."""
    res = simulate("pocket", seed=1)
    t_ph, q_true = res.truth
    q_ph = quat_multiply(_yaw(-PHONE_OFF_DEG * np.ones(len(t_ph))), q_true)
    rec = Recording(mag=Stream(*res.mag), accel=Stream(*res.accel), gyro=Stream(*res.gyro), meta=res.meta,
                    truth=res.truth, references={"os": (t_ph, q_ph)} if references else {})
    sink = MemorySink()
    summary = replay(rec, sinks=[sink], settings=settings, progress=False)
    return EstimateBatch.concat(sink.batches), summary, (t_ph, q_ph)


@pytest.fixture(scope="module")
def pocket():
    return _pocket(False), _pocket(True)


def test_replay_gives_the_rows_without_a_heading_the_phones(pocket):
    (plain, s_plain, _), (filled, s_filled, (t_ph, q_ph)) = pocket
    unknown = plain.heading_std_deg >= UNKNOWN_STD_DEG
    assert unknown.sum() > 500 and s_plain["phone_heading_rows"] == 0
    assert s_filled["phone_heading_rows"] == unknown.sum()
    k = np.searchsorted(t_ph, filled.t[unknown], side="right") - 1
    np.testing.assert_allclose(wrap_deg(filled.heading_deg[unknown] - heading_deg_from_quat(q_ph[k])), 0.0,
                               atol=1e-9)
    # everything else is the same run: the filter never reads the phone's attitude
    assert np.array_equal(filled.q_wd[~unknown], plain.q_wd[~unknown])
    assert np.array_equal(filled.heading_std_deg, plain.heading_std_deg)
    assert [e["kind"] for e in s_filled["events"]] == [e["kind"] for e in s_plain["events"]]
    # the phone's own score leaves those rows out: they agree with it by construction
    assert s_filled["heading_error"]["os"]["n_epochs"] == len(filled) - unknown.sum()
    assert s_filled["heading_error"]["truth"]["n_epochs"] == len(filled)


def test_a_run_that_ignores_what_the_phone_knows_leaves_its_heading_out():
    settings = PipelineSettings(prior=PriorSettings(use_phone=False))
    b, summary, _ = _pocket(True, settings)
    plain, _, _ = _pocket(False, settings)
    assert summary["phone_heading_rows"] == 0 and np.array_equal(b.q_wd, plain.q_wd)


def test_an_attitude_series_is_put_in_time_order_without_what_is_no_attitude():
    """A reader's series with a repeated and an out-of-order time, a NaN time and an all-zero row: in time
    order, the first of a repeated time kept, the NaN time and the zero row left out — as both the scores and
    the phone's heading take it."""
    from replay.heading_scores import attitude_series

    t = np.array([0.0, 2.0, 1.0, 2.0, np.nan, 3.0, 4.0])
    q = _yaw([0.0, 20.0, 10.0, 99.0, 50.0, 30.0, 0.0])
    q[6] = 0.0
    t2, q2 = attitude_series(t, q)
    assert t2.tolist() == [0.0, 1.0, 2.0, 3.0]
    np.testing.assert_allclose(-wrap_deg(heading_deg_from_quat(q2)), [0.0, 10.0, 20.0, 30.0], atol=1e-9)
