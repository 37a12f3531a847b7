"""The shared chunked parser: the fast (numpy) path and the exact-line path agree, across chunk boundaries."""

from __future__ import annotations

import io
from collections import Counter

import numpy as np
import pytest

from replay.errors import InputError
from replay.formats import read_recording
from replay.formats._common import StreamBuilder, read_table

ROWS = ["0.0 1 2 3", "0.1 1 2 3", "0.1 1 2 3", "0.2 nan 2 3", "0.3 1 2 3", "0.4 1 2 3", "0.5 1 2 3"]


@pytest.mark.parametrize("chunk", [1, 2, 3, 100])
@pytest.mark.parametrize("blank", [False, True])
def test_same_result_any_chunking(chunk, blank):
    rows = ROWS[:5] + ([""] if blank else []) + ROWS[5:]
    dropped = Counter()
    b = StreamBuilder("f.txt", "mag", dropped)
    read_table(io.StringIO("\n".join(rows) + "\n"), "f.txt", [(b, [1, 2, 3])], 4, chunk=chunk)
    t, v = b.arrays()
    np.testing.assert_array_equal(t, [0.0, 0.1, 0.3, 0.4, 0.5])
    assert dropped == {"mag:duplicate_t": 1, "mag:nan": 1} and v.shape == (5, 3)


@pytest.mark.parametrize("chunk", [1, 2, 4, 100])
def test_backwards_line_across_chunks(chunk):
    rows = ["0.0 1 2 3", "0.1 1 2 3", "0.2 1 2 3", "0.15 1 2 3", "0.3 1 2 3"]
    b = StreamBuilder("f.txt", "mag", Counter())
    with pytest.raises(InputError) as ei:
        read_table(
            io.StringIO("\n".join(rows) + "\n"), "f.txt", [(b, [1, 2, 3])], 4, first_line=2, chunk=chunk
        )
    assert ei.value.line == 5 and "time goes backwards" in ei.value.problem


@pytest.mark.parametrize("chunk", [1, 3, 100])
@pytest.mark.parametrize("most", [4, 5])
def test_garbled_rows_are_dropped_whole_and_counted(chunk, most):
    """A row with more fields than the header allows, or with text anywhere in it (a read column, a column
    after them, the time), is dropped and counted, in the fast and the line-by-line path alike; the rows
    around it are read as they are. ``most`` = 5: the header has one more column than is read."""
    wide = ",7" if most == 5 else ""
    rows = [f"0.0,1,2,3{wide}", f"0.1,1,2,3{wide}", "0.2,1,zz,3" + wide, f"0.3,4,5,6{wide}",
            f"10.944458,45.03479,-58.094788,12.3{wide},4x5,abc",  # the row: extra fields, and text
            f"0.4,1,2,3{wide},8", f"x0.5,1,2,3{wide}", f"0.6,1,2,3{wide}", f"0.7,1,2,3{wide}"]
    dropped = Counter()
    b = StreamBuilder("f.csv", "mag", dropped)
    text = io.StringIO("\n".join(rows))
    read_table(text, "f.csv", [(b, [1, 2, 3])], 4, delimiter=",", chunk=chunk, most=most)
    t, v = b.arrays()
    np.testing.assert_array_equal(t, [0.0, 0.1, 0.3, 0.6, 0.7])
    np.testing.assert_array_equal(v[2], [4, 5, 6])
    assert dropped == {"mag:non_numeric": 2, "mag:extra_fields": 2}


def test_a_stream_of_garbled_rows_only_says_why_it_is_empty(tmp_path):
    f = tmp_path / "mag.csv"
    f.write_text("t,x,y,z\n" + "".join(f"{i},5;1,2;3,4;5,6\n" for i in range(5)))  # decimal commas
    with pytest.raises(InputError, match=r"mag: empty stream \(no valid samples; dropped: extra_fields 5\)"):
        read_recording(tmp_path)


def test_saturation_limit_in_both_paths():
    for rows in (["0 1 2 250.2", "1 1 2 3"], ["0 1 2 250.2", "", "1 1 2 3"]):
        dropped = Counter()
        b = StreamBuilder("f", "gyro", dropped, limit=250.0)
        read_table(io.StringIO("\n".join(rows)), "f", [(b, [1, 2, 3])], 4)
        assert dropped == {"gyro:saturated": 1} and len(b) == 2


def test_an_implausible_sample_is_dropped_not_saturated_and_a_stream_of_them_is_empty():
    """A sample beyond :data:`PHYSICAL_LIMITS` on a stream whose range the reader knows (its builder counted
    it ``saturated``, a kept sample) is counted once, as ``implausible``; a stream left with none is
    empty, named as such."""
    from replay.formats._common import StreamSpec

    dropped = Counter({"gyro:saturated": 2})
    conv = StreamSpec("f.txt", "gyro", check=False, limit_known=True).converter(dropped)
    out = conv.push(np.arange(3.0), np.array([[0.0, 0.0, 0.1], [1e308, 0.0, 0.0], [0.0, 0.0, 0.2]]))
    assert dropped == {"gyro:saturated": 1, "gyro:implausible": 1}
    assert sum(len(t) for t, _ in out) == 2
    conv = StreamSpec("f.txt", "gyro", check=False).converter(Counter())
    conv.push(np.arange(3.0), np.full((3, 3), 1e308))
    with pytest.raises(InputError, match="gyro: empty stream .no valid samples; dropped: implausible 3"):
        conv.end()
