"""A hash table from integer grid coordinates to slots, for sparse 3-D grids (TSDF blocks; patch cells: `rangesurf._tilegrid`).

Open addressing with linear probing over a power-of-two table, kept at most
half full by the caller (which grows it and calls `rehash`). Keys are
``(x, y, z)`` int32 rows; 2-D grids use ``z = 0``. Compiled helpers only:
callers are Numba kernels.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["lookup", "insert", "rehash", "empty_table"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")


def empty_table(capacity: int) -> tuple[np.ndarray, np.ndarray]:
    """Keys ``(capacity, 3)`` int32 and slots ``(capacity,)`` int32 (-1: free); ``capacity`` a power of two."""
    return np.zeros((capacity, 3), np.int32), np.full(capacity, -1, np.int32)


@numba.njit(**_JIT)
def _hash(x, y, z, mask):  # pragma: no cover - compiled
    return ((np.int64(x) * 73856093) ^ (np.int64(y) * 19349669) ^ (np.int64(z) * 83492791)) & mask


@numba.njit(**_JIT)
def lookup(keys, slots, x, y, z):  # pragma: no cover - compiled
    """Slot of (x, y, z), -1 if absent."""
    mask = len(slots) - 1
    h = _hash(x, y, z, mask)
    while slots[h] >= 0:
        if keys[h, 0] == x and keys[h, 1] == y and keys[h, 2] == z:
            return slots[h]
        h = (h + 1) & mask
    return -1


@numba.njit(**_JIT)
def insert(keys, slots, x, y, z, slot):  # pragma: no cover - compiled
    """Store (x, y, z) -> slot; the key must be absent."""
    mask = len(slots) - 1
    h = _hash(x, y, z, mask)
    while slots[h] >= 0:
        h = (h + 1) & mask
    keys[h, 0], keys[h, 1], keys[h, 2] = x, y, z
    slots[h] = slot


@numba.njit(**_JIT)
def rehash(keys, slots, coords, count):  # pragma: no cover - compiled
    """Insert the first ``count`` rows of ``coords`` (N, 3) as slots 0..count-1."""
    for slot in range(count):
        insert(keys, slots, coords[slot, 0], coords[slot, 1], coords[slot, 2], slot)
