"""The recorder's growable columns: every row back, in order, across block boundaries."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_kinematics_ros.io.columns import Columns


@pytest.fixture
def columns():
    c = Columns(3)
    c.BLOCK = 5  # small blocks, so that views cross several boundaries
    for i in range(23):
        c.append(i, (i, 2 * i, 3 * i))
    return c


def test_everything_comes_back_in_order(columns):
    stamps, data = columns.view()
    np.testing.assert_array_equal(stamps, np.arange(23))
    np.testing.assert_array_equal(data, np.arange(23)[:, None] * [1, 2, 3])


@pytest.mark.parametrize("last", [0, 1, 4, 5, 6, 22, 23, 30])
def test_the_last_rows(columns, last):
    stamps, data = columns.view(last)
    expected = np.arange(23)[23 - min(last, 23) :]
    np.testing.assert_array_equal(stamps, expected)
    np.testing.assert_array_equal(data, expected[:, None] * [1, 2, 3])


def test_views_are_copies_and_empty_columns_have_shape():
    c = Columns(2)
    stamps, data = c.view()
    assert stamps.shape == (0,) and data.shape == (0, 2)
    c.append(7, (1.0, 2.0))
    stamps, data = c.view()
    data[0] = 0.0
    np.testing.assert_array_equal(c.view()[1], [[1.0, 2.0]])


def test_old_blocks_are_dropped_and_the_rest_reads_as_before(columns):
    assert columns.drop_before(12) == 10  # rows 0-9: two full blocks; 10-14 hold 12 and up, so they stay
    assert columns.retained == 13 and columns.n == 23
    stamps, data = columns.view()
    np.testing.assert_array_equal(stamps, np.arange(10, 23))
    np.testing.assert_array_equal(data, np.arange(10, 23)[:, None] * [1, 2, 3])
    np.testing.assert_array_equal(columns.view(4)[0], np.arange(19, 23))
    np.testing.assert_array_equal(columns.view(99)[0], np.arange(10, 23))
    columns.append(23, (23, 46, 69))
    np.testing.assert_array_equal(columns.view()[0], np.arange(10, 24))
    assert columns.drop_before(10**9) == 10  # the block being filled (20-24) is never dropped
    np.testing.assert_array_equal(columns.view()[0], np.arange(20, 24))
