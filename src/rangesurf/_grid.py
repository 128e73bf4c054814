"""Small kernels on organized point grids shared by the stages."""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["ranges", "point_ranges", "pixel_pitch", "points_along_rays", "pooled_grid"]

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


@numba.njit(**_JIT)
def pooled_grid(points, valid, distance, sigma, factor, fx, fy, cx, cy):  # pragma: no cover - compiled
    """A grid ``factor`` times coarser whose every point pools the middle of a ``factor`` x ``factor`` block of ``points``.

    The pooled point lies at the median range of the valid points
    (``valid``, their ranges ``distance``) among the block's central 2 x 2
    pixels (the whole block at 2x) for an even ``factor``, or at its centre
    pixel's range for an odd one: on the block's central ray ``((u - cx) /
    fx, (v - cy) / fy, 1)``, ``u`` and ``v`` the block's centre pixel, when
    ``fx > 0`` (a pinhole camera: the coarse grid is then a pinhole grid with
    ``fx / factor`` and ``cx' = (cx - (factor - 1) / 2) / factor``); else
    along the mean of their unit rays. The median keeps a spike or a flying
    pixel out, where taking every ``factor``-th pixel would keep it as often
    as any other; and with less noise in each point, a coarse grid's normals
    and plane tests lose less against full resolution (`segment_planes`:
    176x144 SR-3000 frames pooled 2x, 107 correct detections of 110 against
    95 when subsampled). An odd factor has no central 2 x 2; the median of
    its central 3 x 3 took 5 ms of a 640x480 frame (3x) and found the same
    planes there (56 of 56) as the centre pixel.

    ``sigma`` (H, W) float64 is the points' range noise; the pooled sigma is
    the mean of the pooled pixels' times the standard error of the median
    of ``n`` normal readings. Returns the coarse points ``(ceil(H / factor),
    ceil(W / factor), 3)`` float32 (NaN where no pooled pixel is valid) and
    their sigma (float64, 1.0 there).
    """
    height, width = valid.shape
    rows = -(-height // factor)
    columns = -(-width // factor)
    pooled = np.full((rows, columns, 3), np.nan, np.float32)
    pooled_sigma = np.ones((rows, columns))
    span = 2 if factor % 2 == 0 else 1
    start = (factor - span) // 2
    if span == 1:
        # The centre pixel's point is already on its block's central ray (a block cut short by the border
        # takes its last pixel, a little off that ray, rather than nothing).
        for i in range(rows):
            for j in range(columns):
                a, b = min(factor * i + start, height - 1), min(factor * j + start, width - 1)
                if valid[a, b]:
                    for k in range(3):
                        pooled[i, j, k] = points[a, b, k]
                    pooled_sigma[i, j] = sigma[a, b]
        return pooled, pooled_sigma
    pinhole = fx > 0.0
    half = 0.5 * (factor - 1)
    ray_u = (factor * np.arange(columns) + half - cx) / fx if pinhole else np.zeros(columns)
    for i in range(rows):
        ray_v = (factor * i + half - cy) / fy if pinhole else 0.0
        for j in range(columns):
            n = 0
            sigma_sum = total = 0.0
            smallest, largest = math.inf, -math.inf
            ray_x = ray_y = ray_z = 0.0
            for a in range(factor * i + start, min(factor * i + start + span, height)):
                for b in range(factor * j + start, min(factor * j + start + span, width)):
                    if not valid[a, b]:
                        continue
                    value = np.float64(distance[a, b])
                    total += value
                    smallest = min(smallest, value)
                    largest = max(largest, value)
                    n += 1
                    sigma_sum += sigma[a, b]
                    if not pinhole:
                        ray_x += points[a, b, 0] / value
                        ray_y += points[a, b, 1] / value
                        ray_z += points[a, b, 2] / value
            if n == 0:
                continue
            if n <= 2:
                median = total / n
            else:
                # The middle one of three, or the mean of the middle two of four, without sorting.
                median = (total - smallest - largest) / (n - 2)
            if pinhole:
                ray_x = ray_u[j]
                ray_y = ray_v
                ray_z = 1.0
            scale = median / math.sqrt(ray_x * ray_x + ray_y * ray_y + ray_z * ray_z)
            pooled[i, j, 0] = ray_x * scale
            pooled[i, j, 1] = ray_y * scale
            pooled[i, j, 2] = ray_z * scale
            pooled_sigma[i, j] = sigma_sum / n * _median_standard_error(n)
    return pooled, pooled_sigma


@numba.njit(**_JIT, inline="always")
def _median_standard_error(n):  # pragma: no cover - compiled
    """Standard deviation of the median of ``n`` <= 4 unit-variance normal readings (of their middle two for even ``n``)."""
    if n == 1:
        return 1.0
    if n == 2:
        return 0.7071
    if n == 3:
        return 0.6698
    return 0.5460
