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

from rangesurf._checks import check_range_sigma

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


# --------------------------------------------------------------------------
# Public functions.
# --------------------------------------------------------------------------


def estimate_normals(
    points: ArrayLike,
    *,
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
    points = _check_points(points)
    if method not in NORMAL_METHODS:
        raise ValueError(f"method must be one of {NORMAL_METHODS}, got {method!r}")
    window = _check_window(window, "window")
    max_window = _check_window(max_window, "max_window")
    if not (isinstance(depth_jump, (int, float)) and math.isfinite(depth_jump) and depth_jump > 0):
        raise ValueError(f"depth_jump must be a fraction of the range > 0, got {depth_jump!r}")
    distance = np.sqrt(np.einsum("ijk,ijk->ij", points, points))
    valid = np.isfinite(distance) & (distance > 0)
    sigma = None if range_sigma is None else check_range_sigma(np.where(valid, distance, np.nan), range_sigma)
    # A spike would mark its whole neighbourhood as a depth jump and shrink every window near it;
    # it is a reading to ignore, not an edge.
    zero_sigma = np.zeros(distance.shape) if sigma is None else sigma
    spikes = _isolated_readings(np.where(valid, distance, np.nan), zero_sigma, depth_jump)
    if spikes.any():
        valid &= ~spikes
        distance = np.where(valid, distance, np.nan)
        points = np.where(valid[..., None], points, np.nan).astype(np.float32)

    if method == "cross":
        jumps = depth_discontinuities(distance, depth_jump=depth_jump, range_sigma=sigma)
        normals = _cross_normals(points, valid, jumps)
        radius = np.where(valid, 1, -1).astype(np.int16)
        return (normals, radius) if return_window else normals

    origin = points[valid].mean(axis=0) if valid.any() else np.zeros(3)
    moments = _integral_moments(points, valid, origin.astype(np.float64))
    jumps = depth_discontinuities(distance, depth_jump=depth_jump, range_sigma=sigma)
    # Chessboard distance to the nearest jump pixel; a window of radius d - 1 holds none.
    clear = cv2.distanceTransform((~jumps).astype(np.uint8), cv2.DIST_C, 3)
    # With no jump at all the transform is "infinite" (a huge float).
    clear = np.minimum(clear, max(jumps.shape)).astype(np.int32) - 1
    if method == "box":
        radius = np.minimum(clear, window // 2)
    else:
        radius = np.minimum(clear, _adaptive_radius(moments, points, distance, valid, sigma, max_window // 2))
    radius = np.where(valid, radius, -1).astype(np.int16)
    sigma_gate = np.full(distance.shape, np.nan) if sigma is None else sigma
    normals = _box_normals(moments, points, valid, radius, distance, sigma_gate, float(depth_jump), _GATED_RADIUS)
    return (normals, radius) if return_window else normals


def depth_discontinuities(
    range_image: ArrayLike, *, depth_jump: float = 0.05, range_sigma: ArrayLike | float | None = None
) -> np.ndarray:
    """Pixels on either side of a depth jump.

    Two valid neighbours (4-connected, or two apart across one invalid
    pixel) are on opposite sides of a jump when their ranges differ by more
    than ``depth_jump`` times the nearer range and, given ``range_sigma``, by
    more than four noise sigmas of their difference.

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
    image = np.asarray(range_image, dtype=np.float64)
    sigma = np.zeros(image.shape) if range_sigma is None else np.broadcast_to(np.asarray(range_sigma, float), image.shape)
    jumps, _ = _jump_pairs(image, sigma, depth_jump)
    return jumps


def _jump_pairs(image: np.ndarray, sigma: np.ndarray, depth_jump: float) -> tuple[np.ndarray, np.ndarray]:
    """Jump mask, and per pixel how many of its valid 4-neighbours it jumps against."""
    jumps = np.zeros(image.shape, bool)
    against = np.zeros(image.shape, np.int8)
    for step in (1, 2):
        for axis in (0, 1):
            near = [slice(None), slice(None)]
            far = [slice(None), slice(None)]
            near[axis] = slice(0, -step)
            far[axis] = slice(step, None)
            near, far = tuple(near), tuple(far)
            a, b = image[near], image[far]
            with np.errstate(invalid="ignore"):
                limit = np.maximum(depth_jump * np.minimum(a, b), 4.0 * np.hypot(sigma[near], sigma[far]))
                jump = np.abs(a - b) > step * limit
            if step == 2:
                # Across one missing pixel only: with the middle valid the step-1 test decides.
                middle = [slice(None), slice(None)]
                middle[axis] = slice(1, -1)
                jump &= np.isnan(image[tuple(middle)])
            else:
                against[near] += jump
                against[far] += jump
            jumps[near] |= jump
            jumps[far] |= jump
    return jumps, against


def _isolated_readings(image: np.ndarray, sigma: np.ndarray, depth_jump: float) -> np.ndarray:
    """Readings that jump against at least three of their four neighbours (salt-and-pepper spikes)."""
    _, against = _jump_pairs(image, sigma, depth_jump)
    return against >= 3


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


def _check_points(points: Any) -> np.ndarray:
    array = np.asarray(points)
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"points must be an organized (H, W, 3) grid, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.floating):
        raise ValueError(f"points must be a float array (NaN where invalid), got dtype {array.dtype}")
    array = np.ascontiguousarray(array, dtype=np.float32)
    n_infinite = int(np.count_nonzero(np.isinf(array)))
    if n_infinite:
        raise ValueError(f"points contain Inf ({n_infinite} values); mark missing returns with NaN")
    return array


def _check_window(window: Any, name: str) -> int:
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 3 or window % 2 == 0:
        raise ValueError(f"{name} must be an odd integer >= 3, got {window!r}")
    return int(window)


# --------------------------------------------------------------------------
# Adaptive window radius (Mitra & Nguyen).
# --------------------------------------------------------------------------


def _pixel_pitch(points: np.ndarray, distance: np.ndarray, valid: np.ndarray) -> float:
    """Median angle (radians) between the rays of horizontally neighbouring valid pixels."""
    both = valid[:, 1:] & valid[:, :-1]
    if not both.any():
        return 1e-3
    a = points[:, 1:][both] / distance[:, 1:][both, None]
    b = points[:, :-1][both] / distance[:, :-1][both, None]
    return float(np.median(np.linalg.norm(a - b, axis=1))) or 1e-3


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
    footprint = np.maximum(distance * _pixel_pitch(points, distance, valid), 1e-9)
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
                x = points[i, j, 0] - origin[0]
                y = points[i, j, 1] - origin[1]
                z = points[i, j, 2] - origin[2]
                row[0] += 1.0
                row[1] += x
                row[2] += y
                row[3] += z
                row[4] += x * x
                row[5] += x * y
                row[6] += x * z
                row[7] += y * y
                row[8] += y * z
                row[9] += z * z
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
def _smallest_eigen(sums, normal):  # pragma: no cover - compiled
    """Plane fit of window sums: unit normal of least variance into ``normal``; returns that variance.

    Closed-form eigenvalues of the 3x3 covariance (trigonometric method), the
    eigenvector from the largest cross product of two rows of ``C - lambda I``.
    Returns -1 when the fit is undefined (fewer than 3 points, or no plane).
    """
    n = sums[0]
    if n < 3.0:
        return -1.0
    mx = sums[1] / n
    my = sums[2] / n
    mz = sums[3] / n
    a00 = sums[4] / n - mx * mx
    a01 = sums[5] / n - mx * my
    a02 = sums[6] / n - mx * mz
    a11 = sums[7] / n - my * my
    a12 = sums[8] / n - my * mz
    a22 = sums[9] / n - mz * mz
    off = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    b00 = a00 - q
    b11 = a11 - q
    b22 = a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off
    if p2 <= 1e-30 * (q * q + 1e-300):
        return -1.0
    p = math.sqrt(p2 / 6.0)
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)) / (p * p * p)
    half = min(max(det / 2.0, -1.0), 1.0)
    phi = math.acos(half) / 3.0
    smallest = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    # Rows of C - smallest * I; the normal is orthogonal to all of them.
    r0x, r0y, r0z = a00 - smallest, a01, a02
    r1x, r1y, r1z = a01, a11 - smallest, a12
    r2x, r2y, r2z = a02, a12, a22 - smallest
    c0x, c0y, c0z = r0y * r1z - r0z * r1y, r0z * r1x - r0x * r1z, r0x * r1y - r0y * r1x
    c1x, c1y, c1z = r0y * r2z - r0z * r2y, r0z * r2x - r0x * r2z, r0x * r2y - r0y * r2x
    c2x, c2y, c2z = r1y * r2z - r1z * r2y, r1z * r2x - r1x * r2z, r1x * r2y - r1y * r2x
    d0 = c0x * c0x + c0y * c0y + c0z * c0z
    d1 = c1x * c1x + c1y * c1y + c1z * c1z
    d2 = c2x * c2x + c2y * c2y + c2z * c2z
    if d0 >= d1 and d0 >= d2:
        vx, vy, vz, d = c0x, c0y, c0z, d0
    elif d1 >= d2:
        vx, vy, vz, d = c1x, c1y, c1z, d1
    else:
        vx, vy, vz, d = c2x, c2y, c2z, d2
    if d <= 0.0:
        return -1.0
    norm = math.sqrt(d)
    normal[0] = vx / norm
    normal[1] = vy / norm
    normal[2] = vz / norm
    return max(smallest, 0.0)


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


@numba.njit(**_JIT)
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
            x = points[r, c, 0] - ox
            y = points[r, c, 1] - oy
            z = points[r, c, 2] - oz
            sums[0] += 1.0
            sums[1] += x
            sums[2] += y
            sums[3] += z
            sums[4] += x * x
            sums[5] += x * y
            sums[6] += x * z
            sums[7] += y * y
            sums[8] += y * z
            sums[9] += z * z


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


@numba.njit(**_JIT)
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
