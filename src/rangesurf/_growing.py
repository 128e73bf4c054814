"""An array that rows are appended to, for per-frame records of long runs.

A Python list of per-frame objects (a pose array, a float, a dataclass)
costs a hundred bytes or more per frame beyond the numbers it holds; over a
robot's hours that is the memory growth a long run must not show. Here the
numbers sit in one NumPy array whose capacity grows by a quarter when full:
appends stay amortized constant time and the slack stays small however long
the run.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

__all__ = ["GrowingArray"]


class GrowingArray:
    """Rows of shape ``row_shape`` appended one at a time (or many); `values` is a view of those stored.

    >>> poses = GrowingArray((4, 4))
    >>> poses.append(np.eye(4)); poses.append(2 * np.eye(4))
    >>> len(poses), float(poses.values[1, 0, 0])
    (2, 2.0)
    """

    def __init__(self, row_shape: tuple[int, ...] = (), dtype: DTypeLike = np.float64, rows: ArrayLike | None = None) -> None:
        self._data = np.zeros((16,) + tuple(row_shape), dtype)
        self._count = 0
        if rows is not None:
            self.extend(rows)

    def __len__(self) -> int:
        return self._count

    @property
    def values(self) -> np.ndarray:
        """The rows stored (a view: valid until the next append)."""
        return self._data[: self._count]

    def append(self, row: ArrayLike) -> None:
        self._reserve(self._count + 1)
        self._data[self._count] = row
        self._count += 1

    def extend(self, rows: ArrayLike) -> None:
        rows = np.asarray(rows, self._data.dtype).reshape((-1,) + self._data.shape[1:])
        self._reserve(self._count + len(rows))
        self._data[self._count : self._count + len(rows)] = rows
        self._count += len(rows)

    def _reserve(self, needed: int) -> None:
        capacity = len(self._data)
        if needed <= capacity:
            return
        while capacity < needed:
            capacity += max(16, capacity // 4)
        grown = np.zeros((capacity,) + self._data.shape[1:], self._data.dtype)
        grown[: self._count] = self._data[: self._count]
        self._data = grown
