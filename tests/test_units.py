"""The contract's units checked on a stream's first samples (``pdr_mag/units.py``): by the library's pipeline
(a ``ValueError`` naming the stream and the unit its numbers look like, before they are used) and by the
readers (the same rule, an ``InputError`` naming the file)."""

from __future__ import annotations

import numpy as np
import pytest

from pdr_mag.conventions import GRAVITY
from pdr_mag.estimates import EstimateBatch
from pdr_mag.pipeline import HeadingPipeline
from pdr_mag.units import UnitCheck, time_unit_problem, unit_problem
from tests.test_online import synth_walk
from tests.test_pipeline import META


def _walk() -> dict:
    d = synth_walk(duration=10.0, seed=3)
    return {k: d[k] for k in ("accel", "gyro", "mag")}


@pytest.mark.parametrize(("stream", "scale", "said"), [
    ("accel", 1.0 / GRAVITY, "(wrong unit? in g, × 9.80665 gives 10"),  # iOS CoreMotion's unit
    ("mag", 0.01, "in gauss, × 100 gives"),
    ("mag", 1000.0, "in nT, × 0.001 gives"),
    ("mag", 1e-6, "in T, × 1e+06 gives"),  # ROS sensor_msgs/MagneticField
    ("gyro", 1000.0, "wrong unit?"),  # mrad/s
])
def test_the_pipeline_refuses_a_stream_in_another_unit_and_names_it(stream, scale, said):
    walk = _walk()
    t, xyz = walk[stream]
    walk[stream] = (t, xyz * scale)
    with pytest.raises(ValueError, match=stream) as err:
        HeadingPipeline(meta=dict(META)).run(walk)
    assert said in str(err.value) and "outside the plausible" in str(err.value)


def test_the_pipeline_refuses_times_in_nanoseconds_before_using_them():
    """Android's ``SensorEvent.timestamp`` pushed as seconds: fewer samples than a check waits for, yet the
    first poll raises, so no row is made of intervals read as millions of seconds; pushed together, the three
    streams' starts (milliseconds apart: millions of "seconds") raise the same, not "two clocks"."""
    walk = _walk()
    said = r"median interval between samples is .* \(time not in seconds\? in ns, × 1e-09 gives 0\.01 s\)"
    pipe = HeadingPipeline(meta=dict(META))
    pipe.push_arrays("accel", (walk["accel"][0][:20] + 1000.0) * 1e9, walk["accel"][1][:20])
    with pytest.raises(ValueError, match=said):
        pipe.poll()
    assert pipe.n_outputs == 0
    pipe = HeadingPipeline(meta=dict(META))
    with pytest.raises(ValueError, match=said):
        for name, (t, xyz) in walk.items():
            pipe.push_arrays(name, (t[:20] + 1000.0) * 1e9, xyz[:20])  # fewer than UnitCheck.SAMPLES


def test_the_same_pushes_in_the_contracts_units_pass_in_any_chunking():
    """The check looks at the first samples only, and the rows do not depend on how they were pushed."""
    walk = _walk()
    once = HeadingPipeline(meta=dict(META)).run(walk)
    pipe = HeadingPipeline(meta=dict(META))
    rows = []
    edges = np.arange(0.0, 10.05, 0.05)
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):  # 2- to 5-sample pushes, a poll after each
        for name, (t, xyz) in walk.items():
            m = (t >= lo) & (t < hi)
            pipe.push_arrays(name, t[m], xyz[m])
        rows.append(pipe.poll())
    rows.append(pipe.flush())
    assert not pipe.dropped
    np.testing.assert_array_equal(EstimateBatch.concat(rows).heading_deg, once.heading_deg)


def test_the_rules_on_their_own():
    rng = np.random.default_rng(0)
    field = rng.normal(0.0, 1.0, (100, 3))
    field *= 45.0 / np.linalg.norm(field, axis=1, keepdims=True)
    assert unit_problem("mag", field) is None
    assert "(wrong unit? in gauss, × 100 gives 45 µT)" in unit_problem("mag", field / 100.0, unit_hint="µT")
    assert "(read as µT)" in unit_problem("mag", field / 100.0, unit_hint="µT")
    assert time_unit_problem("gyro", np.arange(0.0, 1.0, 0.005)) is None
    in_ms = time_unit_problem("gyro", np.arange(0.0, 1000.0, 5.0))
    assert "(time not in seconds? in ms, × 0.001 gives 0.005 s)" in in_ms
    assert time_unit_problem("gyro", np.array([0.0, 1e9])) is None  # two times say nothing
    check = UnitCheck("accel")
    check.add(np.arange(2) * 0.01, np.tile([0.0, 0.0, 1.0], (2, 1)))
    check.settle()  # two samples: not judged yet
    assert not check.done
    with pytest.raises(ValueError, match="accel: median .accel. is 1 m/s²"):
        check.add(np.arange(2, 60) * 0.01, np.tile([0.0, 0.0, 1.0], (58, 1)))
    assert check.done


def test_an_accelerometer_without_gravity_is_named_as_such():
    """Android's ``TYPE_LINEAR_ACCELERATION`` pushed as the accelerometer: its median norm is a g's size
    too, but its samples share no direction — the message says gravity was taken out, not "in g"."""
    walk = _walk()
    t, acc = walk["accel"]
    rng = np.random.default_rng(1)
    walk["accel"] = (t, rng.normal(0.0, 0.8, acc.shape))  # a walker's accelerations, gravity removed
    with pytest.raises(ValueError, match="gravity taken out") as err:
        HeadingPipeline(meta=dict(META)).run(walk)
    assert "in g," not in str(err.value)


def test_streams_stamped_by_two_clocks_are_refused_by_the_pipeline():
    """The magnetometer stamped with the time since the epoch, the IMU with the time since boot: the
    pipeline raises when the three streams' first samples are in (replay says the same, exit 2)."""
    walk = _walk()
    t, mag = walk["mag"]
    walk["mag"] = (t + 1.7e9, mag)
    pipe = HeadingPipeline(meta=dict(META))
    pipe.push_arrays("accel", *walk["accel"])
    pipe.push_arrays("gyro", *walk["gyro"])
    with pytest.raises(ValueError, match=r"the streams start 1\.7e\+09 s apart .*: not one clock\?"):
        pipe.push_arrays("mag", *walk["mag"])
    ok = HeadingPipeline(meta=dict(META))
    ok.push_arrays("mag", t + 500.0, mag)  # less than ten minutes after the others: one clock
    ok.push_arrays("accel", *walk["accel"])
    ok.push_arrays("gyro", *walk["gyro"])


def test_a_backend_that_refills_its_buffers_between_pushes_gets_the_same_rows():
    """The pipeline keeps what it needs of a push (the unit check's first samples, the gap finder's first
    times) as copies: one buffer refilled for every push gives the rows of separate arrays."""
    walk = _walk()
    once = HeadingPipeline(meta=dict(META)).run(walk)
    pipe = HeadingPipeline(meta=dict(META))
    buf_t, buf_x = np.empty(64), np.empty((64, 3))
    rows = []
    edges = np.arange(0.0, 10.1, 0.1)
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):  # 0.1 s of each stream, through one buffer
        for name, (t, xyz) in walk.items():
            m = (t >= lo) & (t < hi)
            k = int(m.sum())
            buf_t[:k], buf_x[:k] = t[m], xyz[m]
            pipe.push_arrays(name, buf_t[:k], buf_x[:k])
        rows.append(pipe.poll())
    rows.append(pipe.flush())
    got = EstimateBatch.concat(rows)
    np.testing.assert_array_equal(got.heading_deg, once.heading_deg)
    assert pipe.summary()["stream_gaps"]["n"] == 0


def test_replay_leaves_the_units_to_its_readers(tmp_path):
    """A logger whose accelerometer writes zeros for its first 30 samples: the pipeline alone judges its first
    50 and refuses them; ``pdr-mag replay`` judges the file's first 4096 (the readers' rule, which the file
    passes) and runs it, no traceback — the pipeline's own check is off there (``check_inputs``)."""
    from replay.cli import main
    from replay.formats import pdrcsv
    from replay.recording import Recording, Stream

    d = synth_walk(duration=30.0, seed=3)
    t, acc = d["accel"]
    acc = acc.copy()
    acc[:30] = 0.0
    walk = {"accel": (t, acc), "gyro": d["gyro"], "mag": d["mag"]}
    with pytest.raises(ValueError, match="accel: median .accel. is 0 m/s²"):
        HeadingPipeline(meta=dict(META)).run(walk)
    rec = Recording(accel=Stream(t, acc), gyro=Stream(*d["gyro"]), mag=Stream(*d["mag"]), meta=dict(META))
    pdrcsv.write(rec, tmp_path / "walk")
    assert main(["replay", str(tmp_path / "walk"), "--no-progress", "-q"]) == 0
