"""Small kernels on organized point grids shared by the stages."""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["ranges"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@numba.njit(**_JIT)
def ranges(points):  # pragma: no cover - compiled
    """Distance ``(H, W)`` float32 of every point to the sensor (NaN where invalid) and the valid mask."""
    height, width = points.shape[:2]
    distance = np.full((height, width), np.nan, np.float32)
    valid = np.zeros((height, width), np.bool_)
    for i in range(height):
        for j in range(width):
            x, y, z = points[i, j, 0], points[i, j, 1], points[i, j, 2]
            squared = x * x + y * y + z * z
            if squared > 0.0:
                distance[i, j] = math.sqrt(squared)
                valid[i, j] = True
    return distance, valid
