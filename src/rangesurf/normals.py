"""Surface normals on the organized grid (thesis Section 2.1).

The thesis fits a plane to each point's neighbourhood by total least squares
and takes its normal, with a neighbourhood size that adapts to the local
noise, sampling density and curvature (Mitra & Nguyen 2004).  On an organized
range grid the neighbourhood is a window of pixels, and the sums a plane fit
needs (count, first and second moments of x, y, z) come from integral images
(Holzer et al. 2012), so a window of any size costs the same: eight lookups
per moment.  That makes a per-pixel window size free, which is what the
adaptive neighbourhood needs:

* the window never crosses a depth discontinuity: its radius is capped by the
  chessboard distance to the nearest pixel at a depth jump, and pixels at a
  jump fit only the neighbours on their own side of it (a small window gated
  by range difference), so foreground and background never mix;
* within that cap, the radius follows Mitra & Nguyen's optimum
  ``r^3 = (c1 sigma / sqrt(rho) + c2 sigma^2) / kappa``: noise ``sigma`` from
  the sensor model (or estimated from the fit residuals), sampling density
  ``rho`` from the pixel footprint at that range, curvature ``kappa`` from the
  excess of a first fit's residual over the noise.  Flat surfaces get the
  largest window, curved ones a small one.

Invalid (NaN) neighbours are left out of every sum, and normals face the
sensor (``n . p < 0``).  A cheap cross-product variant (central differences
along rows and columns) is there for speed and for comparison.

References
----------
.. [1] The reference thesis, Section 2.1 (``shared/reference/thesis.md``).
.. [2] N. J. Mitra and A. Nguyen, "Estimating surface normals in noisy point
   cloud data", International Journal of Computational Geometry and
   Applications 14, 261-276, 2004.
.. [3] S. Holzer, R. B. Rusu, M. Dixon, S. Gedikli and N. Navab, "Adaptive
   neighborhood selection for real-time surface normal estimation from
   organized point cloud data using integral images", IROS 2012.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numba
import numpy as np
from numpy.typing import ArrayLike

from rangesurf._checks import check_point_grid, check_range_sigma
from rangesurf._grid import pixel_pitch, ranges
from rangesurf._planefit import add_point
from rangesurf._planefit import smallest_eigen as _smallest_eigen
from rangesurf.frame import PinholeProjection

__all__ = ["NORMAL_METHODS", "estimate_normals", "normal_angle_error", "depth_discontinuities"]

NORMAL_METHODS = ("adaptive", "box", "cross")
_JIT = dict(cache=True, nogil=True, error_model="numpy")
# Window radius (pixels) of the first fit, whose residual gives curvature and noise.
_PROBE_RADIUS = 3
# Half-size of the range-gated window used at depth jumps.
_GATED_RADIUS = 2
# Mitra & Nguyen's constants (their Eq. 10, with the probability term folded into c1).
_C1 = 1.0
_C2 = 4.0
# Variance of z = kappa x^2 / 2 over a uniform window of half-width w is kappa^2 w^4 / 45.
_PARABOLA_VARIANCE = 45.0
_FOUR_NEIGHBOURS = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]], dtype=np.int64)


# --------------------------------------------------------------------------
# Public functions.
# --------------------------------------------------------------------------


def estimate_normals(
    points: ArrayLike,
    *,
    projection: PinholeProjection | None = None,
    method: str = "adaptive",
    window: int = 5,
    max_window: int = 15,
    range_sigma: ArrayLike | float | None = None,
    depth_jump: float = 0.05,
    return_window: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Unit surface normals of an organized point grid.

    Parameters
    ----------
    points : (H, W, 3) float array
        Points in the sensor frame (metres), NaN where there is no return
        (`RangeFrame.points`).
    projection : PinholeProjection, optional
        The camera's intrinsics (``frame.sensor.projection``). For a pinhole
        camera the plane fit runs on inverse depth, which is affine in pixel
        coordinates on a plane, with separable filters: several times faster
        than the general moments path used otherwise.
    method : {"adaptive", "box", "cross"}
        ``"adaptive"``: least-squares plane over a window whose size adapts
        per pixel to noise, sampling density and curvature (Mitra & Nguyen)
        and never crosses a depth jump. ``"box"``: the same fit over a fixed
        ``window``, shrunk only at depth jumps. ``"cross"``: cross product of
        central differences (one-sided at jumps and holes).
    window : int
        Odd window size (pixels) for ``"box"``.
    max_window : int
        Largest odd window size ``"adaptive"`` may use.
    range_sigma : float or (H, W) array, optional
        Range noise standard deviation (metres), e.g.
        ``sensor.range_sigma(range)``. Estimated from the fit residuals when
        omitted.
    depth_jump : float
        Neighbouring ranges that differ by more than this fraction of the
        range (and by more than 4 noise sigmas) are a depth discontinuity.
    return_window : bool
        Also return the ``(H, W)`` int16 window radius used per pixel
        (-1 where the range-gated window at a jump was used, or invalid).

    Returns
    -------
    normals : (H, W, 3) float32
        Unit normals facing the sensor (``n . p < 0``), NaN where the point is
        invalid or has fewer than three usable neighbours.

    Raises
    ------
    ValueError
        If ``points`` is not ``(H, W, 3)``, holds Inf, or an option is out
        of range.

    References
    ----------
    .. [1] N. J. Mitra and A. Nguyen, "Estimating surface normals in noisy
       point cloud data", IJCGA 14, 2004.
    .. [2] S. Holzer et al., "Adaptive neighborhood selection for real-time
       surface normal estimation from organized point cloud data using
       integral images", IROS 2012.

    Examples
    --------
    >>> import numpy as np
    >>> from rangesurf.normals import estimate_normals
    >>> rows, cols = np.mgrid[0:40, 0:50].astype(np.float32)
    >>> points = np.dstack([(cols - 25) * 0.01, (rows - 20) * 0.01, np.full_like(rows, 2.0)])
    >>> normals = estimate_normals(points)
    >>> np.round(normals[20, 25], 3) + 0.0
    array([ 0.,  0., -1.], dtype=float32)
    """
    points = check_point_grid(points)
    if method not in NORMAL_METHODS:
        raise ValueError(f"method must be one of {NORMAL_METHODS}, got {method!r}")
    window = _check_window(window, "window")
    max_window = _check_window(max_window, "max_window")
    if not (isinstance(depth_jump, (int, float)) and math.isfinite(depth_jump) and depth_jump > 0):
        raise ValueError(f"depth_jump must be a fraction of the range > 0, got {depth_jump!r}")
    distance, valid = ranges(points)
    sigma = None if range_sigma is None else check_range_sigma(np.where(valid, distance, np.nan), range_sigma)
    # A spike would mark its whole neighbourhood as a depth jump and shrink every window near it;
    # it is a reading to ignore, not an edge.
    sigma_or_nan = np.full(distance.shape, np.nan) if sigma is None else sigma
    spikes, jumps = _spikes_and_jumps(distance, valid, sigma_or_nan, float(depth_jump))
    if spikes.any():
        valid &= ~spikes
        distance = np.where(valid, distance, np.nan)
        points = np.where(valid[..., None], points, np.nan).astype(np.float32)

    if method == "cross":
        normals = _cross_normals(points, valid, jumps)
        radius = np.where(valid, 1, -1).astype(np.int16)
        return (normals, radius) if return_window else normals
    sizes = (window,) if method == "box" else _window_ladder(window, max_window)
    if isinstance(projection, PinholeProjection):
        normals, radius = _inverse_depth_normals(points, distance, valid, jumps, sigma, projection, sizes, float(depth_jump))
        return (normals, radius) if return_window else normals

    origin = points[valid].mean(axis=0) if valid.any() else np.zeros(3)
    moments = _integral_moments(points, valid, origin.astype(np.float64))
    # Chessboard distance to the nearest jump pixel; a window of radius d - 1 holds none.
    clear = cv2.distanceTransform((~jumps).astype(np.uint8), cv2.DIST_C, 3)
    # With no jump at all the transform is "infinite" (a huge float).
    clear = np.minimum(clear, max(jumps.shape)).astype(np.int32) - 1
    if method == "box":
        radius = np.minimum(clear, window // 2)
    else:
        radius = np.minimum(clear, _adaptive_radius(moments, points, distance, valid, sigma, max_window // 2))
    radius = np.where(valid, radius, -1).astype(np.int16)
    normals = _box_normals(moments, points, valid, radius, distance, sigma_or_nan, float(depth_jump), _GATED_RADIUS)
    return (normals, radius) if return_window else normals


def depth_discontinuities(
    range_image: ArrayLike, *, depth_jump: float = 0.05, range_sigma: ArrayLike | float | None = None
) -> np.ndarray:
    """Pixels on either side of a depth jump.

    Two valid neighbours (4-connected, or two apart across one invalid
    pixel) are on opposite sides of a jump when their ranges differ by more
    than ``depth_jump`` times the nearer range and, given ``range_sigma``, by
    more than four noise sigmas of their difference -- unless the steps on
    both sides of the pair are of the same sign and size (within a factor of
    two): that is a surface seen at a grazing angle, not a jump. A reading
    that jumps against three or four of its neighbours is a spike
    (salt-and-pepper), not an edge: it is ignored, and marks no jump.

    Parameters
    ----------
    range_image : (H, W) float array
        Metres, NaN where invalid.
    depth_jump : float
        Relative range difference that counts as a jump. A plane seen at 80
        degrees incidence changes range by about ``3 %`` per SR-3000 pixel,
        so the default 5 % keeps floors and walls in one piece.
    range_sigma : float or (H, W) array, optional
        Range noise (metres).

    Returns
    -------
    (H, W) bool
    """
    image = np.ascontiguousarray(range_image, dtype=np.float64)
    if image.ndim != 2:
        raise ValueError(f"range image must be 2-D (H, W), got shape {image.shape}")
    valid = np.isfinite(image) & (image > 0)
    sigma = np.full(image.shape, np.nan) if range_sigma is None else check_range_sigma(np.where(valid, image, np.nan), range_sigma)
    _, jumps = _spikes_and_jumps(image, valid, sigma, float(depth_jump))
    return jumps


def normal_angle_error(normals: ArrayLike, reference: ArrayLike) -> np.ndarray:
    """Angle in degrees between two normal fields, NaN where either is NaN.

    Parameters
    ----------
    normals, reference : (H, W, 3) float arrays
        Unit normals (the simulator's ``GroundTruth.normals`` as reference).

    Returns
    -------
    (H, W) float64 degrees in [0, 180].

    Examples
    --------
    >>> import numpy as np
    >>> a = np.array([[[0.0, 0.0, -1.0]]])
    >>> b = np.array([[[0.0, np.sin(0.1), -np.cos(0.1)]]])
    >>> float(np.round(normal_angle_error(a, b)[0, 0], 3))
    5.73
    """
    normals = np.asarray(normals, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if normals.shape != reference.shape or normals.shape[-1:] != (3,):
        raise ValueError(f"normal fields must have the same (..., 3) shape, got {normals.shape} and {reference.shape}")
    cosine = np.einsum("...k,...k->...", normals, reference)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


# --------------------------------------------------------------------------
# Input checks.
# --------------------------------------------------------------------------


def _check_window(window: Any, name: str) -> int:
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 3 or window % 2 == 0:
        raise ValueError(f"{name} must be an odd integer >= 3, got {window!r}")
    return int(window)


# --------------------------------------------------------------------------
# Pinhole cameras: plane fits on inverse depth with separable filters.
# --------------------------------------------------------------------------


def _window_ladder(window: int, max_window: int) -> tuple[int, ...]:
    """Odd window sizes a pixel may use: ``window``, ``max_window`` and their middle.

    Without the middle size the mean error on flat parts barely changes, but
    pixels 3 to 7 pixels from an edge fall back to the smallest window; on raw
    SR-3000 frames that cost region growing a sixth of its correct detections.
    """
    if max_window <= window:
        return (window,)
    middle = (window + max_window) // 2 | 1
    return tuple(sorted({window, middle, max_window}))


def _inverse_depth_normals(
    points: np.ndarray,
    distance: np.ndarray,
    valid: np.ndarray,
    jumps: np.ndarray,
    sigma: np.ndarray | None,
    projection: PinholeProjection,
    sizes: tuple[int, ...],
    depth_jump: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a pinhole grid: least squares of inverse depth over the largest clean window that fits.

    On a plane ``n . p + d = 0`` seen through a pinhole, inverse depth is affine
    in the pixel coordinates, ``1 / z = -(nx u + ny v + nz) / d``; so a window's
    normal is the gradient of a linear fit of ``1 / z``. Over a full window
    the fit needs only a box sum and two ramp-weighted sums of ``1 / z``
    (separable filters), and the residual one box sum of ``(1 / z)^2``. The fit
    measures errors along the viewing rays, the direction of range noise.

    A window is *clean* when all its pixels are valid and none is at a depth
    jump. Each pixel takes the largest clean window whose residual is
    consistent with the noise (larger residual means curvature: a smaller
    window); a pixel with no clean window (at a jump or a hole) gets a total
    least-squares fit of the neighbours on its side of the jump.
    """
    height, width = valid.shape
    # Centred on a median (of a sample: any value near the data's will do), so that float32 sums
    # keep the residual's digits.
    depth = points[..., 2]
    sample = depth[::7, ::7][valid[::7, ::7] & (depth[::7, ::7] > 0)]
    centre = float(np.median(1.0 / sample)) if sample.size else 0.0
    stacked = np.empty((height, width, 3), np.float32)
    centred = np.empty((height, width), np.float32)
    usable = _inverse_depth_channels(points, valid, jumps, centre, stacked, centred)
    boxes = np.empty((len(sizes), height, width, 3), np.float32)
    ramps = np.empty((len(sizes), 2, height, width), np.float32)
    for index, size in enumerate(sizes):
        half = size // 2
        ones = np.ones(size, np.float32)
        ramp = np.arange(-half, half + 1, dtype=np.float32)
        cv2.sepFilter2D(stacked, cv2.CV_32F, ones, ones, dst=boxes[index], borderType=cv2.BORDER_CONSTANT)
        cv2.sepFilter2D(centred, cv2.CV_32F, ramp, ones, dst=ramps[index, 0], borderType=cv2.BORDER_CONSTANT)
        cv2.sepFilter2D(centred, cv2.CV_32F, ones, ramp, dst=ramps[index, 1], borderType=cv2.BORDER_CONSTANT)
    sizes_array = np.asarray(sizes, np.int64)
    if sigma is None:
        # Without a noise model: the median residual of the smallest clean windows, for every pixel.
        noise = _median_window_noise(boxes[0], ramps[0], int(sizes[0]), usable)
        sigma_or_nan = np.full((height, width), np.nan)
    else:
        noise = -1.0
        sigma_or_nan = sigma
    return _ladder_kernel(
        boxes, ramps, sizes_array, centre, noise, points, valid, distance, sigma_or_nan, depth_jump,
        float(projection.fx), float(projection.fy), float(projection.cx), float(projection.cy), _GATED_RADIUS,
    )


def _median_window_noise(box: np.ndarray, ramp: np.ndarray, size: int, usable: np.ndarray) -> float:
    """Variance of 1/z noise: median plane-fit residual variance of the full, clean windows of ``size``."""
    n = float(size * size)
    clean = usable & (box[..., 2] == n)
    if not clean.any():
        return 0.0
    half = size // 2
    energy = size * half * (half + 1) * (2 * half + 1) / 3.0
    total, squares = box[..., 0][clean].astype(np.float64), box[..., 1][clean].astype(np.float64)
    slopes = ramp[0][clean].astype(np.float64) ** 2 + ramp[1][clean].astype(np.float64) ** 2
    residual = np.maximum(squares - total * total / n - slopes / energy, 0.0)
    return float(np.median(residual)) / (n - 3.0)


# --------------------------------------------------------------------------
# Adaptive window radius (Mitra & Nguyen).
# --------------------------------------------------------------------------


def _adaptive_radius(
    moments: np.ndarray,
    points: np.ndarray,
    distance: np.ndarray,
    valid: np.ndarray,
    sigma: np.ndarray | None,
    max_radius: int,
) -> np.ndarray:
    """Per-pixel window radius: Mitra & Nguyen's optimum in pixels, in [1, max_radius]."""
    # Plane-fit residual variance (smallest covariance eigenvalue) of a fixed probe window.
    residual_variance, count = _fixed_window_fit(moments, _PROBE_RADIUS)
    if sigma is None:
        # Plane-fit residual variance over (n - 3) degrees of freedom estimates the noise on flat parts;
        # the median over the frame is dominated by them.
        usable = valid & (count > 9)
        if not usable.any():
            return np.full(distance.shape, 1, np.int32)
        unbiased = residual_variance[usable] * count[usable] / (count[usable] - 3)
        noise_variance = np.full(distance.shape, float(np.median(unbiased)))
    else:
        noise_variance = np.square(np.nan_to_num(sigma, nan=0.0))
    footprint = np.maximum(distance * pixel_pitch(points), 1e-9)
    half_width = (_PROBE_RADIUS + 0.5) * footprint
    # Only the excess beyond three standard errors of a chi-square variance estimate is curvature;
    # anything less is what noise alone produces in half the windows.
    with np.errstate(divide="ignore", invalid="ignore"):
        significance = 1.0 + 3.0 * np.sqrt(2.0 / np.maximum(count - 3.0, 1.0))
    excess = np.maximum(residual_variance - noise_variance * significance, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        curvature = np.sqrt(_PARABOLA_VARIANCE * excess) / np.square(half_width)
        noise = np.sqrt(noise_variance)
        radius_m = np.cbrt((_C1 * noise * footprint + _C2 * noise_variance) / curvature)
        radius_px = np.floor(radius_m / footprint)
    radius_px = np.where(np.isfinite(radius_px), radius_px, max_radius)
    return np.clip(radius_px, 1, max_radius).astype(np.int32)


# --------------------------------------------------------------------------
# Kernels.
# --------------------------------------------------------------------------


@numba.njit(**_JIT)
def _integral_moments(points, valid, origin):  # pragma: no cover - compiled
    """Integral images (H+1, W+1, 10) of n, x, y, z, xx, xy, xz, yy, yz, zz (points minus ``origin``)."""
    height, width = valid.shape
    table = np.zeros((height + 1, width + 1, 10))
    row = np.zeros(10)
    for i in range(height):
        row[:] = 0.0
        for j in range(width):
            if valid[i, j]:
                add_point(row, points[i, j, 0] - origin[0], points[i, j, 1] - origin[1], points[i, j, 2] - origin[2], 1.0)
            for k in range(10):
                table[i + 1, j + 1, k] = table[i, j + 1, k] + row[k]
    return table


@numba.njit(**_JIT, inline="always")
def _window_sums(table, i, j, radius, sums):  # pragma: no cover - compiled
    height = table.shape[0] - 1
    width = table.shape[1] - 1
    top = max(i - radius, 0)
    bottom = min(i + radius + 1, height)
    left = max(j - radius, 0)
    right = min(j + radius + 1, width)
    for k in range(10):
        sums[k] = table[bottom, right, k] - table[top, right, k] - table[bottom, left, k] + table[top, left, k]


@numba.njit(**_JIT)
def _fixed_window_fit(table, radius):  # pragma: no cover - compiled
    height = table.shape[0] - 1
    width = table.shape[1] - 1
    variance = np.full((height, width), np.inf)
    count = np.zeros((height, width))
    sums = np.zeros(10)
    normal = np.zeros(3)
    for i in range(height):
        for j in range(width):
            _window_sums(table, i, j, radius, sums)
            count[i, j] = sums[0]
            value = _smallest_eigen(sums, normal)
            if value >= 0.0:
                variance[i, j] = value
    return variance, count


@numba.njit(**_JIT)
def _box_normals(table, points, valid, radius, distance, sigma, depth_jump, gated_radius):  # pragma: no cover - compiled
    height, width = valid.shape
    normals = np.full((height, width, 3), np.nan, dtype=np.float32)
    sums = np.zeros(10)
    normal = np.zeros(3)
    for i in range(height):
        for j in range(width):
            if not valid[i, j]:
                continue
            if radius[i, j] >= 1:
                _window_sums(table, i, j, radius[i, j], sums)
            else:
                _gated_sums(points, valid, distance, sigma, depth_jump, i, j, gated_radius, sums)
            if _smallest_eigen(sums, normal) < 0.0:
                continue
            facing = normal[0] * points[i, j, 0] + normal[1] * points[i, j, 1] + normal[2] * points[i, j, 2]
            sign = -1.0 if facing > 0.0 else 1.0
            for k in range(3):
                normals[i, j, k] = sign * normal[k]
    return normals


@numba.njit(**_JIT, inline="always")
def _gated_sums(points, valid, distance, sigma, depth_jump, i, j, radius, sums):  # pragma: no cover - compiled
    """Moments of the neighbours on the centre's side of a depth jump (range within the jump threshold)."""
    height, width = valid.shape
    centre = distance[i, j]
    gate = depth_jump * centre
    if sigma[i, j] == sigma[i, j]:
        gate = max(gate, 4.0 * sigma[i, j])
    # Relative to the centre point, for precision.
    ox = points[i, j, 0]
    oy = points[i, j, 1]
    oz = points[i, j, 2]
    sums[:] = 0.0
    for r in range(max(i - radius, 0), min(i + radius + 1, height)):
        for c in range(max(j - radius, 0), min(j + radius + 1, width)):
            if not valid[r, c] or abs(distance[r, c] - centre) > gate:
                continue
            add_point(sums, points[r, c, 0] - ox, points[r, c, 1] - oy, points[r, c, 2] - oz, 1.0)


@numba.njit(**_JIT)
def _spikes_and_jumps(distance, valid, sigma, depth_jump):  # pragma: no cover - compiled
    """Spikes (jump against >= 3 of 4 neighbours), then jumps among the remaining readings."""
    height, width = valid.shape
    # Squared noise limit of each pixel (16 sigma^2, 0 without a model) and the jump of every pair.
    noise = np.zeros((height, width), np.float32)
    for i in range(height):
        for j in range(width):
            if sigma[i, j] == sigma[i, j]:
                noise[i, j] = 16.0 * sigma[i, j] * sigma[i, j]
    across = np.zeros((height, width), np.bool_)  # (i, j) - (i, j + 1)
    down = np.zeros((height, width), np.bool_)  # (i, j) - (i + 1, j)
    for i in range(height):
        for j in range(width):
            if not valid[i, j]:
                continue
            if j + 1 < width and valid[i, j + 1]:
                across[i, j] = _is_jump(distance, noise, depth_jump, i, j, i, j + 1, 1.0) and not _is_ramp(
                    distance, valid, i, j, 0, 1
                )
            if i + 1 < height and valid[i + 1, j]:
                down[i, j] = _is_jump(distance, noise, depth_jump, i, j, i + 1, j, 1.0) and not _is_ramp(
                    distance, valid, i, j, 1, 0
                )
    spikes = np.zeros((height, width), np.bool_)
    for i in range(height):
        for j in range(width):
            count = across[i, j] + down[i, j]
            if j > 0:
                count += across[i, j - 1]
            if i > 0:
                count += down[i - 1, j]
            spikes[i, j] = count >= 3
    jumps = np.zeros((height, width), np.bool_)
    for i in range(height):
        for j in range(width):
            if not valid[i, j] or spikes[i, j]:
                continue
            if across[i, j] and not spikes[i, j + 1]:
                jumps[i, j] = True
                jumps[i, j + 1] = True
            if down[i, j] and not spikes[i + 1, j]:
                jumps[i, j] = True
                jumps[i + 1, j] = True
            # Across one missing pixel.
            if j + 2 < width and not valid[i, j + 1] and valid[i, j + 2] and not spikes[i, j + 2]:
                if _is_jump(distance, noise, depth_jump, i, j, i, j + 2, 2.0):
                    jumps[i, j] = True
                    jumps[i, j + 2] = True
            if i + 2 < height and not valid[i + 1, j] and valid[i + 2, j] and not spikes[i + 2, j]:
                if _is_jump(distance, noise, depth_jump, i, j, i + 2, j, 2.0):
                    jumps[i, j] = True
                    jumps[i + 2, j] = True
    return spikes, jumps


@numba.njit(**_JIT, inline="always")
def _is_jump(distance, noise, depth_jump, i, j, qi, qj, step):  # pragma: no cover - compiled
    a = distance[i, j]
    b = distance[qi, qj]
    relative = depth_jump * min(a, b)
    gap = (a - b) / step
    return gap * gap > max(relative * relative, noise[i, j] + noise[qi, qj])


@numba.njit(**_JIT, inline="always")
def _is_ramp(distance, valid, i, j, di, dj):  # pragma: no cover - compiled
    """Whether the step from (i, j) to the next pixel continues the steps on both sides of it.

    A surface seen at a grazing angle (a floor far ahead) changes range by a
    large step per pixel, but steadily; a depth jump is a step much larger
    than its neighbours. Both neighbouring steps must agree in sign and lie
    within a factor of two of this one.
    """
    height, width = valid.shape
    bi, bj = i - di, j - dj
    ai, aj = i + 2 * di, j + 2 * dj
    if bi < 0 or bj < 0 or ai >= height or aj >= width:
        return False
    if not (valid[bi, bj] and valid[ai, aj]):
        return False
    step = distance[i + di, j + dj] - distance[i, j]
    before = distance[i, j] - distance[bi, bj]
    after = distance[ai, aj] - distance[i + di, j + dj]
    for other in (before, after):
        if other * step <= 0.0 or abs(other) < 0.5 * abs(step) or abs(other) > 2.0 * abs(step):
            return False
    return True


@numba.njit(**_JIT)
def _inverse_depth_channels(points, valid, jumps, centre, stacked, centred):  # pragma: no cover - compiled
    """Fill ``stacked`` (1/z - centre, its square, usable) and ``centred``; returns the usable mask.

    A pixel is usable when valid and not at a depth jump. A one-pixel hole (a
    removed outlier) would spoil every window around it; on a plane the mean
    inverse depth of its two opposite neighbours is exact, so such holes are
    filled (for the sums only) and count as usable.
    """
    height, width = valid.shape
    inverse = np.zeros((height, width), np.float32)
    usable = np.zeros((height, width), np.bool_)
    for i in range(height):
        for j in range(width):
            z = points[i, j, 2]
            if valid[i, j] and z > 0 and not jumps[i, j]:
                inverse[i, j] = 1.0 / z
                usable[i, j] = True
    filled = _fill_pinholes(inverse, usable)
    for i in range(height):
        for j in range(width):
            if filled[i, j]:
                value = inverse[i, j] - centre
                centred[i, j] = value
                stacked[i, j, 0] = value
                stacked[i, j, 1] = value * value
                stacked[i, j, 2] = 1.0
            else:
                centred[i, j] = 0.0
                stacked[i, j, 0] = 0.0
                stacked[i, j, 1] = 0.0
                stacked[i, j, 2] = 0.0
    return filled


@numba.njit(**_JIT)
def _fill_pinholes(inverse, usable):  # pragma: no cover - compiled
    """Fill unusable pixels whose left and right (or upper and lower) neighbours are usable, in place."""
    height, width = usable.shape
    filled = usable.copy()
    for i in range(height):
        for j in range(width):
            if usable[i, j]:
                continue
            if 0 < j < width - 1 and usable[i, j - 1] and usable[i, j + 1]:
                inverse[i, j] = 0.5 * (inverse[i, j - 1] + inverse[i, j + 1])
                filled[i, j] = True
            elif 0 < i < height - 1 and usable[i - 1, j] and usable[i + 1, j]:
                inverse[i, j] = 0.5 * (inverse[i - 1, j] + inverse[i + 1, j])
                filled[i, j] = True
    return filled


@numba.njit(**_JIT)
def _ladder_kernel(boxes, ramps, sizes, centre, noise, points, valid, distance, sigma, depth_jump, fx, fy, cx, cy, gated_radius):  # pragma: no cover - compiled
    """Normals from the window fits (``noise``: variance of 1/z, or < 0 to take it from ``sigma``)."""
    height, width = valid.shape
    normals = np.full((height, width, 3), np.nan, dtype=np.float32)
    radius = np.full((height, width), -1, np.int16)
    sums = np.zeros(10)
    normal = np.zeros(3)
    n_sizes = sizes.shape[0]
    for i in range(height):
        for j in range(width):
            if not valid[i, j]:
                continue
            done = False
            for index in range(n_sizes - 1, -1, -1):
                size = sizes[index]
                n = float(size * size)
                if boxes[index, i, j, 2] != n:
                    continue
                half = size // 2
                energy = size * half * (half + 1) * (2 * half + 1) / 3.0
                total = float(boxes[index, i, j, 0])
                ramp_s = float(ramps[index, 0, i, j])
                ramp_t = float(ramps[index, 1, i, j])
                if index > 0:
                    if noise >= 0.0:
                        variance = noise
                    else:
                        # Range noise as noise of 1/z: d(1/z) = dz / z^2 and dz is about dr z / r.
                        variance = (sigma[i, j] / (distance[i, j] * points[i, j, 2])) ** 2
                    residual = float(boxes[index, i, j, 1]) - total * total / n - (ramp_s * ramp_s + ramp_t * ramp_t) / energy
                    allowed = variance * (n - 3.0) * (1.0 + 3.0 * math.sqrt(2.0 / (n - 3.0)))
                    if residual > allowed:
                        continue
                # 1/z = a s + b t + c around the pixel; as A u + B v + C the plane's normal is -(A, B, C).
                a = ramp_s / energy
                b = ramp_t / energy
                c = total / n + centre
                u0 = (j - cx) / fx
                v0 = (i - cy) / fy
                big_a = a * fx
                big_b = b * fy
                big_c = c - big_a * u0 - big_b * v0
                norm = math.sqrt(big_a * big_a + big_b * big_b + big_c * big_c)
                if norm == 0.0:
                    break
                if big_c * points[i, j, 2] + big_a * points[i, j, 0] + big_b * points[i, j, 1] < 0.0:
                    norm = -norm
                normals[i, j, 0] = -big_a / norm
                normals[i, j, 1] = -big_b / norm
                normals[i, j, 2] = -big_c / norm
                radius[i, j] = half
                done = True
                break
            if done:
                continue
            _gated_sums(points, valid, distance, sigma, depth_jump, i, j, gated_radius, sums)
            if _smallest_eigen(sums, normal) < 0.0:
                continue
            facing = normal[0] * points[i, j, 0] + normal[1] * points[i, j, 1] + normal[2] * points[i, j, 2]
            sign = -1.0 if facing > 0.0 else 1.0
            for k in range(3):
                normals[i, j, k] = sign * normal[k]
    return normals, radius


@numba.njit(**_JIT)
def _cross_normals(points, valid, jumps):  # pragma: no cover - compiled
    height, width = valid.shape
    normals = np.full((height, width, 3), np.nan, dtype=np.float32)
    du = np.zeros(3)
    dv = np.zeros(3)
    for i in range(height):
        for j in range(width):
            if not valid[i, j]:
                continue
            if not _difference(points, valid, jumps, i, j, 0, 1, du):
                continue
            if not _difference(points, valid, jumps, i, j, 1, 0, dv):
                continue
            nx = du[1] * dv[2] - du[2] * dv[1]
            ny = du[2] * dv[0] - du[0] * dv[2]
            nz = du[0] * dv[1] - du[1] * dv[0]
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            if norm == 0.0:
                continue
            if nx * points[i, j, 0] + ny * points[i, j, 1] + nz * points[i, j, 2] > 0.0:
                norm = -norm
            normals[i, j, 0] = nx / norm
            normals[i, j, 1] = ny / norm
            normals[i, j, 2] = nz / norm
    return normals


@numba.njit(**_JIT, inline="always")
def _difference(points, valid, jumps, i, j, di, dj, out):  # pragma: no cover - compiled
    """Central difference along (di, dj), one-sided where a neighbour is missing or across a jump."""
    height, width = valid.shape
    ahead_i, ahead_j = i + di, j + dj
    back_i, back_j = i - di, j - dj
    ahead = ahead_i < height and ahead_j < width and valid[ahead_i, ahead_j]
    back = back_i >= 0 and back_j >= 0 and valid[back_i, back_j]
    if jumps[i, j]:
        # Keep only the neighbour closer in range to the centre.
        centre = points[i, j, 0] ** 2 + points[i, j, 1] ** 2 + points[i, j, 2] ** 2
        if ahead and back:
            gap_ahead = abs(points[ahead_i, ahead_j, 0] ** 2 + points[ahead_i, ahead_j, 1] ** 2
                            + points[ahead_i, ahead_j, 2] ** 2 - centre)
            gap_back = abs(points[back_i, back_j, 0] ** 2 + points[back_i, back_j, 1] ** 2
                           + points[back_i, back_j, 2] ** 2 - centre)
            if gap_ahead < gap_back:
                back = False
            else:
                ahead = False
    if ahead and back:
        for k in range(3):
            out[k] = points[ahead_i, ahead_j, k] - points[back_i, back_j, k]
    elif ahead:
        for k in range(3):
            out[k] = points[ahead_i, ahead_j, k] - points[i, j, k]
    elif back:
        for k in range(3):
            out[k] = points[i, j, k] - points[back_i, back_j, k]
    else:
        return False
    return True


# --------------------------------------------------------------------------
# NumPy reference (tests compare the kernels against it).
# --------------------------------------------------------------------------


def _plane_fit_reference(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares plane normal and residual variance of an (N, 3) point set."""
    centred = points - points.mean(axis=0)
    values, vectors = np.linalg.eigh(centred.T @ centred / len(points))
    return vectors[:, 0], float(values[0])


def _box_normals_reference(points: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Normals from explicit per-pixel windows (``radius >= 1`` only), facing the sensor."""
    height, width = radius.shape
    normals = np.full((height, width, 3), np.nan)
    for i in range(height):
        for j in range(width):
            r = int(radius[i, j])
            if r < 1 or not np.isfinite(points[i, j]).all():
                continue
            window = points[max(i - r, 0) : i + r + 1, max(j - r, 0) : j + r + 1].reshape(-1, 3)
            window = window[np.isfinite(window).all(axis=1)]
            if len(window) < 3:
                continue
            normal, _ = _plane_fit_reference(window.astype(np.float64))
            normals[i, j] = -normal if normal @ points[i, j] > 0 else normal
    return normals


def _inverse_depth_reference(points: np.ndarray, projection: PinholeProjection, size: int) -> np.ndarray:
    """Pinhole-path normals by explicit least squares of 1/z = A u + B v + C over full, valid windows."""
    height, width = points.shape[:2]
    half = size // 2
    normals = np.full((height, width, 3), np.nan)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    u = (cols - projection.cx) / projection.fx
    v = (rows - projection.cy) / projection.fy
    for i in range(half, height - half):
        for j in range(half, width - half):
            window = (slice(i - half, i + half + 1), slice(j - half, j + half + 1))
            depth = points[window][..., 2].astype(np.float64).ravel()
            if not np.isfinite(depth).all():
                continue
            design = np.column_stack([u[window].ravel(), v[window].ravel(), np.ones(depth.size)])
            coefficients = np.linalg.lstsq(design, 1.0 / depth, rcond=None)[0]
            normal = -coefficients / np.linalg.norm(coefficients)
            normals[i, j] = -normal if normal @ points[i, j] > 0 else normal
    return normals
