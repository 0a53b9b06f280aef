"""A matrix that grows by columns in place: views of one buffer kept with room for the columns to come.

The discovery engine appends a hub law's column to its feature matrices (the features, their standardized
copy, that copy without NaN, the features column-major) once or twice a target. np.hstack copied the whole
matrix each time: on a heavy closed loop's 15,000 rows x 1,600 features, 190 MB a matrix, 0.76 s per law
(line_profiler on seed 71's wy', the column-major copy not counted). Here a column is written into the
room left beside the others; a view handed out before keeps its columns (nothing below `used` is written
again until `truncate`).
"""

from __future__ import annotations

import numpy as np


class ColumnBuffer:
    """Columns (rows, used) in a buffer with room for more, in C (row-major) or F (column-major) order."""

    def __init__(self, rows: int, width: int, room: int, order: str = "C"):
        self.order = order
        self.room = max(int(room), 1)
        self._data = np.empty((rows, width + self.room), order=order)
        self.used = width

    @classmethod
    def holding(cls, M: np.ndarray, room: int, order: str = "C") -> ColumnBuffer:
        """A buffer holding a copy of M (rows, width) with room for `room` more columns."""
        out = cls(M.shape[0], M.shape[1], room, order)
        out._data[:, :M.shape[1]] = M
        return out

    def view(self) -> np.ndarray:
        """The columns held (rows, used): a view, not a copy."""
        return self._data[:, :self.used]

    def truncate(self, width: int) -> np.ndarray:
        """The first `width` columns held, the rest given up (later appends write over them); the view."""
        if not 0 <= width <= self.used:
            raise ValueError(f"cannot truncate {self.used} columns to {width}")
        self.used = width
        return self.view()

    def append(self, columns: np.ndarray) -> np.ndarray:
        """The matrix with `columns` (rows, k) appended; the view. A full buffer is moved to a larger one
        (views handed out before keep the old one alive, unchanged)."""
        k = columns.shape[1]
        if self.used + k > self._data.shape[1]:
            grown = np.empty((self._data.shape[0], self.used + k + self.room), order=self.order)
            grown[:, :self.used] = self._data[:, :self.used]
            self._data = grown
        self._data[:, self.used:self.used + k] = columns
        self.used += k
        return self.view()
