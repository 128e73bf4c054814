"""Input checks shared by the stage functions (one wording for one mistake)."""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

__all__ = ["check_point_grid", "check_range_image", "check_range_sigma"]


def check_range_image(range_image: Any, name: str = "range image", *, dtype: Any = np.float32) -> np.ndarray:
    """Return ``range_image`` as a 2-D real array, or raise a ValueError saying what is wrong.

    Parameters
    ----------
    range_image : array_like
        Expected ``(H, W)``, integer or float, NaN (not Inf) where there is
        no return.
    name : str
        What to call it in messages ("denoised range image").
    dtype : dtype or None
        Convert to this dtype (C-contiguous); ``None`` keeps the input's.
    """
    image = np.asarray(range_image)
    if image.ndim != 2:
        raise ValueError(f"{name} must be 2-D (H, W), got shape {image.shape}")
    # Dtype kinds (i, u: integer; f: floating) rather than np.issubdtype, 2 us a call: a frame's stages check
    # their inputs some thirty times.
    if image.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be a real numeric array (float with NaN where invalid), got dtype {image.dtype}")
    if dtype is not None:
        image = np.ascontiguousarray(image, dtype=dtype)
    if image.dtype.kind == "f":
        n_infinite = int(_count_infinite(image.ravel()))
        if n_infinite:
            raise ValueError(f"{name} contains Inf ({n_infinite} values); mark missing returns with NaN")
    return image


def check_range_sigma(image: np.ndarray, range_sigma: Any) -> np.ndarray:
    """Per-pixel noise standard deviation ``(H, W)`` float64 (metres) from a scalar or an array.

    Raises a ValueError unless it is finite and > 0 wherever ``image`` has a
    return and, as an array, has the image's shape.
    """
    if np.ndim(range_sigma) == 0:
        value = float(range_sigma)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"range_sigma must be finite and > 0, got {range_sigma}")
        return np.full(image.shape, value)
    sigma = np.asarray(range_sigma, dtype=np.float64)
    if sigma.shape != image.shape:
        raise ValueError(f"range_sigma shape {sigma.shape} does not match range image shape {image.shape}")
    sigma = np.ascontiguousarray(sigma)
    n_bad = _count_bad_sigma(np.ascontiguousarray(image), sigma)
    if n_bad:
        raise ValueError(f"range_sigma must be finite and > 0 wherever there is a return; {n_bad} pixels are not")
    return sigma


def check_point_grid(points: Any, name: str = "points") -> np.ndarray:
    """Return an organized ``(H, W, 3)`` grid as C-contiguous float32, or raise a ValueError saying what is wrong.

    NaN marks missing values; Inf is refused.
    """
    array = np.asarray(points)
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"{name} must be an organized (H, W, 3) grid, got shape {array.shape}")
    if array.dtype.kind != "f":
        raise ValueError(f"{name} must be a float array (NaN where invalid), got dtype {array.dtype}")
    if array.dtype == np.float32 and not array.flags.c_contiguous:
        # A decimated grid (a strided view): NumPy copies rows of 3-vectors three times slower than this loop.
        array, n_infinite = _compact_grid(array)
    else:
        array = np.ascontiguousarray(array, dtype=np.float32)
        n_infinite = _count_infinite(array.reshape(-1))
    if n_infinite:
        raise ValueError(f"{name} contain Inf ({n_infinite} values); mark missing values with NaN")
    return array


# One pass each, no temporaries: every stage checks its inputs, and a 640x480 frame's checks with NumPy
# temporaries took about 2 ms of the pipeline's frame.
@numba.njit(cache=True, nogil=True)
def _count_bad_sigma(image, sigma):  # pragma: no cover - compiled
    """Pixels where ``image`` is not NaN and ``sigma`` is not finite and > 0 (both (H, W), C-contiguous)."""
    flat_image, flat_sigma = image.reshape(-1), sigma.reshape(-1)
    bad = 0
    for k in range(flat_image.size):
        value = flat_sigma[k]
        bad += np.int64((flat_image[k] == flat_image[k]) & ~((value > 0.0) & (value < np.inf)))
    return bad


@numba.njit(cache=True, nogil=True)
def _count_infinite(values):  # pragma: no cover - compiled
    """How many of the (flat) values are +-Inf."""
    infinity = values.dtype.type(np.inf)
    count = 0
    for k in range(values.size):
        count += np.int64(abs(values[k]) == infinity)  # branch-free: vectorized
    return count


@numba.njit(cache=True, nogil=True)
def _compact_grid(points):  # pragma: no cover - compiled
    """A C-contiguous copy of a float32 (H, W, 3) grid of any layout, and how many of its values are +-Inf."""
    height, width = points.shape[0], points.shape[1]
    compact = np.empty((height, width, 3), np.float32)
    infinity = np.float32(np.inf)
    count = 0
    for i in range(height):
        for j in range(width):
            for axis in range(3):
                value = points[i, j, axis]
                compact[i, j, axis] = value
                count += np.int64(abs(value) == infinity)
    return compact, count
