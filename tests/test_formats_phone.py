"""What a recording states about the phone (replay/formats/_phone.py): the OS's offset estimates, the stated
date; the keys every reader sets, and their round trip through pdr-csv's meta.json and our MCAP."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest

from replay.formats import read_recording
from replay.formats._phone import OsEstimate, put_date, stated_date
from replay.recording import Recording, Stream
from tests.conftest import dataset

#: every form a phone app writes that the parser accepts, and the calendar date it states
ACCEPTED = [
    ("Thu Sep 12 10:22:32 GMT+02:00 2019", "2019-09-12"),  # GetSensorData: Java's Date.toString()
    ("Thu Sep 12 23:59:59 CEST 2019", "2019-09-12"),  # the zone as an abbreviation: the date as written
    ("Mon Jan 06 08:00:00 UTC 2020", "2020-01-06"),
    ("Fri Feb 28 17:03:11 GMT-05:00 2020", "2020-02-28"),
    ("Sat Feb 29 09:00:00 2020", "2020-02-29"),  # no zone; a leap day
    ("2019-09-12 10:22:32", "2019-09-12"),
    ("2019/09/12", "2019-09-12"),
    ("2019-9-2", "2019-09-02"),
    ("2019-09-12T10:22:32.5Z", "2019-09-12"),
    ("2026-02-02 20:10:00.000 UTC+05:30", "2026-02-02"),  # phyphox's time.csv
    ("2024-05-29_16-26-40", "2024-05-29"),  # Sensor Logger's Metadata.csv
]
UNREADABLE = [
    "12/09/2019",  # day first: ambiguous
    "jeu. sept. 12 10:22:32 CEST 2019",  # localised names
    "Thu Sep 31 10:22:32 GMT 2019",  # no such day
    "2019-02-29",  # not a leap year
    "2019-09-12 25:61:00",
    "Thu Sep 12 2019",
    "yesterday",
    "1568276552",
]


@pytest.mark.parametrize("text,day", ACCEPTED)
def test_stated_date_accepted(text, day):
    assert stated_date(text) == day
    meta: dict = {}
    put_date(meta, f"  {text} ")
    assert meta == {"date": day}


@pytest.mark.parametrize("text", UNREADABLE)
def test_stated_date_unreadable_is_kept_as_text(text):
    assert stated_date(text) is None
    meta: dict = {}
    put_date(meta, text)
    assert meta == {"date_unreadable": text}


def test_os_estimate_first_value_changes_and_odd_cells():
    dropped: Counter = Counter()
    est = OsEstimate("mag_os_bias", dropped)
    est.add(0.00, ["x", "1", "2"])  # before any readable value: odd, no first value yet
    est.add(0.02, ["50.0", "-90", "-300"])
    est.add(0.04, ["50", "-90.0", "-300"])  # the same numbers written differently: no change
    est.add(0.06, ["51", "-90", "nan"])  # odd: the estimate in force stays
    est.add(0.08, ["51", "-90"])  # a missing column: odd
    est.add(0.10, ["51", "-90", "-301"])
    est.add(0.12, ["50", "-90", "-300"])  # back to the first value: a change too
    meta: dict = {}
    est.to_meta(meta)
    assert meta == {
        "mag_os_bias_uT": [50.0, -90.0, -300.0],
        "mag_os_bias_changes": [[0.10, 51.0, -90.0, -301.0], [0.12, 50.0, -90.0, -300.0]],
    }
    assert dropped == {"mag_os_bias:nan": 3}


def test_os_estimate_blocks_as_samples():
    """Streaming: the estimate read in blocks of any size is the estimate read sample by sample."""
    rng = np.random.default_rng(1)
    n = 500
    t = np.arange(n) * 0.02
    level = np.cumsum(rng.random(n) < 0.02)  # a new value now and then
    v = np.column_stack([level * 1.5, -level, 0.25 * level + 400.0])
    v[rng.random(n) < 0.03] = np.nan  # odd cells
    one_dropped: Counter = Counter()
    one = OsEstimate("gyro_os_bias", one_dropped)
    for ti, vi in zip(t, v, strict=True):
        one.add(ti, vi)
    for size in (1, 7, 64, n):
        blk = OsEstimate("gyro_os_bias", Counter())
        for i in range(0, n, size):
            blk.add_block(t[i : i + size], v[i : i + size])
        assert blk.first == one.first and blk.changes == one.changes and blk.dropped == one_dropped
    assert len(one.changes) == len({tuple(r) for r in v[np.all(np.isfinite(v), axis=1)]}) - 1
    assert one_dropped["gyro_os_bias:nan"] == int(np.isnan(v[:, 0]).sum())


def test_os_estimate_zero_states_no_estimate():
    """Bias columns of exactly zero are an OS without an estimate: not one, not an odd cell — sample by
    sample and in blocks alike."""
    rows = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [50.0, -90.0, -300.0], [0.0, 0.0, 0.0], [51.0, -90.0, -300.0]]
    t = [0.0, 0.02, 0.04, 0.06, 0.08]
    for blocks in (False, True):
        est = OsEstimate("mag_os_bias", Counter())
        if blocks:
            est.add_block(np.array(t[:2]), np.array(rows[:2]))
            est.add_block(np.array(t[2:]), np.array(rows[2:]))
        else:
            for ti, r in zip(t, rows, strict=True):
                est.add(ti, [str(x) for x in r])
        meta: dict = {}
        est.to_meta(meta)
        assert meta == {"mag_os_bias_uT": [50.0, -90.0, -300.0],
                        "mag_os_bias_changes": [[0.08, 51.0, -90.0, -300.0]]}
        assert not est.dropped
    never = OsEstimate("gyro_os_bias", Counter())
    never.add_block(np.array(t), np.zeros((5, 3)))
    meta = {}
    never.to_meta(meta)
    assert meta == {}


def test_os_estimate_nothing_stated():
    meta: dict = {}
    OsEstimate("mag_os_bias", Counter()).to_meta(meta)
    assert meta == {}
    with pytest.raises(ValueError, match="key"):
        OsEstimate("accel_os_bias", Counter())


@pytest.mark.parametrize(
    "parts",
    [
        ("broad", "data_mat", "01_undisturbed_slow_rotation_A.mat"),
        ("sunsided-marg", "set-2", "full-sphere"),
        ("xio-fusion", "sensor_data.csv"),
    ],
)
def test_lab_imus_are_raw(parts):
    rec = read_recording(dataset(*parts))
    assert rec.meta["mag_os_calibrated"] is False and rec.meta["gyro_os_calibrated"] is False
    assert not any(k in rec.meta for k in ("mag_os_bias_uT", "gyro_os_bias_rad_s", "device_id"))


def test_ros2_bag_is_raw(tmp_path):
    from tests.test_formats_ros2 import write_bag

    rec = read_recording(write_bag(tmp_path / "bag.mcap"))
    assert rec.meta["mag_os_calibrated"] is False and rec.meta["gyro_os_calibrated"] is False


PHONE_META = {
    "device": "LGE Nexus 5",
    "device_id": "03bd36a425202217",
    "date": "2016-06-02",
    "mag_os_calibrated": False,
    "gyro_os_calibrated": False,
    "mag_os_bias_uT": [58.569336, -74.22638, 412.05902],
    "mag_os_bias_changes": [[12.345678901234567, 60.1, -70.2, 410.3], [98.7, 61.0, -69.0, 409.0]],
    "gyro_os_bias_rad_s": [0.008499147, -0.003982544, 0.068847656],
    "gyro_os_bias_changes": [],
}


def _rec():
    rng = np.random.default_rng(0)
    t = np.arange(200) * 0.01
    return Recording(
        mag=Stream(t, np.array([60.0, -70.0, 410.0]) + rng.standard_normal((200, 3))),
        accel=Stream(t, np.array([0.0, 0.0, 9.81]) + 0.1 * rng.standard_normal((200, 3))),
        gyro=Stream(t, 0.01 * rng.standard_normal((200, 3))),
        meta=dict(PHONE_META),
    )


def test_pdrcsv_meta_json_passes_the_keys_on(tmp_path):
    from replay.formats import pdrcsv

    pdrcsv.write(_rec(), tmp_path / "r")
    assert json.loads((tmp_path / "r" / "meta.json").read_text()) == PHONE_META
    assert read_recording(tmp_path / "r").meta == PHONE_META


def test_mcap_meta_round_trip(tmp_path):
    """A replay's MCAP keeps what the recording stated about the phone, exactly (the same floats)."""
    from tests.test_formats_mcap import _write

    got = read_recording(_write(_rec(), tmp_path / "r.mcap")).meta
    assert {k: got[k] for k in PHONE_META} == PHONE_META
    assert got["mag_os_bias_changes"][0][0] == 12.345678901234567


def test_replay_mcap_round_trip_of_a_real_trace(tmp_path):
    """`pdr-mag replay --mcap` of the mall trace whose OS bias changes, read back: the same meta keys."""
    from pdr_mag.sinks.mcap import McapSink
    from replay.run import replay

    f = dataset("ms-indoor-location-2020", "site1", "F1", "path_data_files", "5dd9fd619191710006b570f0.txt")
    rec = read_recording(f)
    replay(f, sinks=[McapSink(tmp_path / "r.mcap")])
    back = read_recording(tmp_path / "r.mcap")
    keys = [k for k in rec.meta if k.startswith(("mag_os", "gyro_os")) or k in ("date", "device")]
    assert len(keys) == 8
    assert {k: back.meta[k] for k in keys} == {k: rec.meta[k] for k in keys}
