"""Growable numeric columns for streams recorded sample by sample (the recorder's in-memory copy)."""

from __future__ import annotations

import numpy as np


class Columns:
    """Growable storage in fixed blocks: O(1) appends, no Python objects per sample, and nothing stored is
    ever copied again (a doubling array copies hundreds of MB on the executor thread in a long recording).
    """

    BLOCK = 65536

    def __init__(self, width: int) -> None:
        self.width = width
        self.blocks: list[tuple[np.ndarray, np.ndarray]] = []
        self.n = 0

    def append(self, stamp: int, values) -> None:
        row = self.n % self.BLOCK
        if row == 0:
            self.blocks.append((np.empty(self.BLOCK, dtype=np.int64), np.empty((self.BLOCK, self.width))))
        stamps, data = self.blocks[-1]
        stamps[row] = stamp
        data[row] = values
        self.n += 1

    def view(self, last: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Stamps and values of every row, or of the last ``last`` rows, as new arrays."""
        count = self.n if last is None else min(last, self.n)
        first = self.n - count
        blocks = self.blocks[first // self.BLOCK :] or [(np.empty(0, dtype=np.int64), np.empty((0, self.width)))]
        start = first % self.BLOCK
        stamps = np.concatenate([b[0] for b in blocks])[start : start + count]
        data = np.concatenate([b[1] for b in blocks])[start : start + count]
        return stamps, data
