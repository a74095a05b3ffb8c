"""Train/validation/test splits by contiguous time blocks: a trajectory's neighbours never straddle them."""

from __future__ import annotations

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.fit import split, split_summary
from hybrid_kinematics_ros.io.pairs import Pairs


def _trajectory_pairs(n: int) -> Pairs:
    """Pairs 9 ms apart along a smooth path, as a recording gives them."""
    t = 0.009 * np.arange(n)
    q = np.column_stack([np.sin(0.3 * t + k) for k in range(6)])
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = q[:, :3]
    return Pairs(q, T, (1e9 * t).astype(np.int64), tuple(f"joint_{i + 1}" for i in range(6)), "base_link")


def _runs(stamps: np.ndarray, all_stamps: np.ndarray) -> int:
    """How many contiguous runs of the full sequence ``stamps`` forms."""
    index = np.searchsorted(all_stamps, stamps)
    return int(1 + np.sum(np.diff(index) > 1))


def test_blocks_hold_out_whole_stretches_of_the_recording():
    pairs = _trajectory_pairs(10_000)
    train, val, test = split(pairs, seed=3)
    assert len(train) + len(val) + len(test) == len(pairs)
    assert len(val) == len(test) == 1000
    assert not set(train.stamps) & set(test.stamps) and not set(val.stamps) & set(test.stamps)
    # 10 blocks of 100 pairs each at most: a test pair's neighbours are test pairs, except at 20 block edges
    assert _runs(test.stamps, pairs.stamps) <= 10 and _runs(val.stamps, pairs.stamps) <= 10
    gap = np.min(np.abs(test.stamps[:, None] - train.stamps[None, :]), axis=1)
    assert np.mean(gap > 0.05e9) > 0.8  # most test pairs are more than 50 ms from any training pair
    again = split(pairs, seed=3)
    np.testing.assert_array_equal(again[2].stamps, test.stamps)


def test_random_pairs_when_asked_and_the_summary_says_which():
    pairs = _trajectory_pairs(2000)
    _, _, test = split(pairs, seed=3, blocks=None)
    assert _runs(test.stamps, pairs.stamps) > 150  # scattered single pairs
    assert split_summary(None, False, False)["test"] == "random pairs"
    assert "time blocks" in split_summary(100, False, True)["validation"]
    assert split_summary(100, False, True)["test"] == "separate bags"
    train, val, _ = split(pairs, seed=0, fractions=(0.1, 0.0))  # a separate test bag: nothing held out for it
    assert len(train) + len(val) == len(pairs)


def test_too_few_pairs_is_an_error():
    with pytest.raises(CalibrationError, match="only 5 pairs"):
        split(_trajectory_pairs(5), seed=0)
