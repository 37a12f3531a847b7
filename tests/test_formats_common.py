"""The shared chunked parser: the fast (numpy) path and the exact-line path agree, across chunk boundaries."""

from __future__ import annotations

import io
from collections import Counter

import numpy as np
import pytest

from replay.errors import InputError
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
def test_bad_cell_line(chunk):
    rows = ["0.0,1,2,3", "0.1,1,2,3", "0.2,1,zz,3", "0.3,1,2,3"]
    b = StreamBuilder("f.csv", "mag", Counter())
    with pytest.raises(InputError) as ei:
        read_table(io.StringIO("\n".join(rows)), "f.csv", [(b, [1, 2, 3])], 4, delimiter=",", chunk=chunk)
    assert ei.value.line == 3 and ei.value.problem == "not a number: 'zz'"


def test_saturation_limit_in_both_paths():
    for rows in (["0 1 2 250.2", "1 1 2 3"], ["0 1 2 250.2", "", "1 1 2 3"]):
        dropped = Counter()
        b = StreamBuilder("f", "gyro", dropped, limit=250.0)
        read_table(io.StringIO("\n".join(rows)), "f", [(b, [1, 2, 3])], 4)
        assert dropped == {"gyro:saturated": 1} and len(b) == 2
