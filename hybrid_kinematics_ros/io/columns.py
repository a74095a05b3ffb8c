"""Growable numeric columns for streams recorded sample by sample (the recorder's in-memory copy)."""

from __future__ import annotations

import numpy as np


class Columns:
    """Growable storage in fixed blocks: O(1) appends, no Python objects per sample, and nothing stored is
    ever copied again (a doubling array copies hundreds of MB on the executor thread in a long recording).

    Whole blocks whose samples are all older than a cutoff can be dropped (:meth:`drop_before`), which
    bounds a long recording's memory by what is still needed plus one block.
    """

    BLOCK = 65536

    def __init__(self, width: int, block: int | None = None) -> None:
        self.width = width
        if block is not None:
            self.BLOCK = block
        self.blocks: list[tuple[np.ndarray, np.ndarray]] = []
        self.n = 0  # rows appended so far, dropped ones included
        self.dropped = 0  # rows dropped from the front (whole blocks)

    @property
    def retained(self) -> int:
        """Rows held in memory."""
        return self.n - self.dropped

    def append(self, stamp: int, values) -> None:
        row = self.n % self.BLOCK
        if row == 0:
            self.blocks.append((np.empty(self.BLOCK, dtype=np.int64), np.empty((self.BLOCK, self.width))))
        stamps, data = self.blocks[-1]
        stamps[row] = stamp
        data[row] = values
        self.n += 1

    def view(self, last: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Stamps and values of every retained row, or of the last ``last`` rows, as new arrays."""
        count = self.retained if last is None else min(last, self.retained)
        first = self.n - count - self.dropped  # row index within the retained blocks
        blocks = self.blocks[first // self.BLOCK :] or [(np.empty(0, dtype=np.int64), np.empty((0, self.width)))]
        start = first % self.BLOCK
        stamps = np.concatenate([b[0] for b in blocks])[start : start + count]
        data = np.concatenate([b[1] for b in blocks])[start : start + count]
        return stamps, data

    def drop_before(self, stamp: int) -> int:
        """Drop the leading full blocks whose stamps are all below ``stamp``; returns the rows dropped.

        Only full blocks go (never the one being filled), so rows keep their places and appends their O(1).
        """
        dropped = 0
        while len(self.blocks) > 1 and self.blocks[0][0].max() < stamp:
            del self.blocks[0]
            dropped += self.BLOCK
        self.dropped += dropped
        return dropped
