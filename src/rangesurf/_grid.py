"""Small kernels on organized point grids shared by the stages."""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["ranges", "point_ranges", "pixel_pitch", "points_along_rays"]

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


@numba.njit(**_JIT)
def points_along_rays(rays, range_image):  # pragma: no cover - compiled
    """``rays * range_image[..., None]`` as a C-contiguous float32 (H, W, 3) grid, multiplied in float32.

    The same values as ``np.multiply(rays, range_image[..., None], dtype=np.float32)``
    in a quarter of its time (640x480: 0.3 ms against 1.3): one pass, no
    broadcast. ``rays`` (H, W, 3) and ``range_image`` (H, W) C-contiguous.
    """
    height, width = range_image.shape
    points = np.empty((height, width, 3), np.float32)
    flat_rays = rays.reshape(height * width, 3)
    flat_points = points.reshape(height * width, 3)
    flat_range = range_image.reshape(height * width)
    for k in range(height * width):
        value = np.float32(flat_range[k])
        for axis in range(3):
            flat_points[k, axis] = np.float32(flat_rays[k, axis]) * value
    return points


@numba.njit(**_JIT)
def point_ranges(points):  # pragma: no cover - compiled
    """Distance (H, W) float32 of every point to the sensor (NaN where invalid), the valid mask, and the Inf count.

    `ranges` in float64 with the Inf scan of `check_point_grid` folded in:
    one pass over the points (C-contiguous) instead of two. One branch-free
    loop over the flattened grid, which the compiler vectorises (nested
    loops over rows and columns it does not).
    """
    height, width = points.shape[:2]
    size = height * width
    flat = points.reshape(size * 3)
    distance = np.empty(size, np.float32)
    valid = np.empty(size, np.bool_)
    n_infinite = 0
    for k in range(size):
        x = float(flat[3 * k])
        y = float(flat[3 * k + 1])
        z = float(flat[3 * k + 2])
        squared = x * x + y * y + z * z
        inside = (squared > 0.0) & (squared < math.inf)
        distance[k] = math.sqrt(squared) if inside else np.nan
        valid[k] = inside
        n_infinite += (abs(x) == math.inf) | (abs(y) == math.inf) | (abs(z) == math.inf)
    return distance.reshape((height, width)), valid.reshape((height, width)), n_infinite


def pixel_pitch(points: np.ndarray) -> float:
    """Median angle (radians) between the rays of horizontally neighbouring valid points of a grid.

    From rows spread over the grid, about 8,000 pairs: a median needs no more.
    1e-3 when no two valid points are neighbours.
    """
    height, width = points.shape[:2]
    points = points[:: max(1, height * width // 8000)]
    both = np.isfinite(points[:, 1:, 0]) & np.isfinite(points[:, :-1, 0])
    if not both.any():
        return 1e-3
    a = points[:, 1:][both].astype(np.float64)
    b = points[:, :-1][both].astype(np.float64)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    return float(np.median(np.linalg.norm(a - b, axis=1))) or 1e-3


@numba.njit(**_JIT)
def median_footprint(angles, range_image, rows, columns):  # pragma: no cover - compiled
    """Median of ``angles * range_image[::rows, 1::columns]`` over its finite values > 0 (0.0 without any).

    ``angles`` (float32, shaped like the sample) are those between neighbouring rays; the products are
    float32 and their median as `np.median` of them gives it. One compiled pass: as NumPy (a product, a
    mask, a compaction, a median) it cost 0.15 ms of every SR-3000 frame in the pipeline.
    """
    sample = range_image[::rows, 1::columns]
    values = np.empty(sample.shape[0] * sample.shape[1], np.float32)
    count = 0
    for i in range(sample.shape[0]):
        for j in range(sample.shape[1]):
            value = np.float32(angles[i, j] * sample[i, j])
            if value > 0 and value < np.inf:
                values[count] = value
                count += 1
    if count == 0:
        return 0.0
    return float(np.median(values[:count]))
