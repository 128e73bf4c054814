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

For a pinhole camera the fit runs on inverse depth, which is affine in the
pixel coordinates on a plane: the same integral-image idea with five sums
per window (count, ``1/z``, ``1/z`` times column and row, ``(1/z)^2``), and
a ladder of three window sizes tried largest first instead of the Mitra &
Nguyen radius.  The largest size is evaluated for a whole image row in one
branch-free loop the compiler vectorises, and each smaller one for the row's
pixels still without a window likewise; that, and folding the input checks
into the kernels' passes, is what makes it faster than OpenCV's FALS normals
(``benchmarks/results/segmentation.md``).

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
from rangesurf._grid import pixel_pitch
from rangesurf._grid import point_ranges as _point_ranges
from rangesurf._planefit import add_point, eigenvector
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
# Bit 0 and bit 1 of each byte of a word (eight byte flags tested as one word).
_BIT0_BYTES = np.uint64(0x0101010101010101)
_BIT1_BYTES = np.uint64(0x0202020202020202)
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
        coordinates on a plane, over windows of a ladder of sizes (``window``,
        ``max_window`` and their middle; smaller ones clipped by the image
        border): an order of magnitude faster than the general moments path
        used otherwise.
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
        Also return the ``(H, W)`` int16 window radius used per pixel (a
        window clipped by the image border counts with its full radius; -1
        where the range-gated window at a jump was used, or invalid).

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
    normals, radius, _, _ = _normals_and_ranges(
        _point_grid(points), projection, method, window, max_window, range_sigma, depth_jump
    )
    return (normals, radius) if return_window else normals


def _normals_and_ranges(
    points: np.ndarray,
    projection: PinholeProjection | None = None,
    method: str = "adaptive",
    window: int = 5,
    max_window: int = 15,
    range_sigma: ArrayLike | float | None = None,
    depth_jump: float = 0.05,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`estimate_normals` of a C-contiguous float32 grid (`_point_grid`): normals, window radius, and the ranges and valid mask.

    The ranges and the valid mask (spikes included) are those of
    `rangesurf._grid.point_ranges`, which region growing needs too: passing
    them on saves it a pass over the points.
    """
    if method not in NORMAL_METHODS:
        raise ValueError(f"method must be one of {NORMAL_METHODS}, got {method!r}")
    window = _check_window(window, "window")
    max_window = _check_window(max_window, "max_window")
    if not (isinstance(depth_jump, (int, float)) and math.isfinite(depth_jump) and depth_jump > 0):
        raise ValueError(f"depth_jump must be a fraction of the range > 0, got {depth_jump!r}")
    distance, valid, n_infinite = _point_ranges(points)
    if n_infinite:
        check_point_grid(points)  # raises, in the shared wording
    sigma, unchecked = _noise_sigma(range_sigma, distance, valid)
    # A spike would mark its whole neighbourhood as a depth jump and shrink every window near it;
    # it is a reading to ignore, not an edge. Kernels skip what ``usable`` excludes.
    sigma_or_nan = np.full(distance.shape, np.nan, np.float32) if sigma is None else sigma
    usable, jumps, sigma_ok = _spikes_and_jumps(distance, valid, sigma_or_nan, float(depth_jump), unchecked)
    if not sigma_ok:
        check_range_sigma(distance, range_sigma)  # raises, in the shared wording

    if method == "cross":
        normals, radius = _cross_normals(points, usable, jumps)
        return normals, radius, distance, valid
    sizes = (window,) if method == "box" else _window_ladder(window, max_window)
    if isinstance(projection, PinholeProjection):
        normals, radius = _inverse_depth_normals(points, distance, usable, jumps, sigma, projection, sizes, float(depth_jump))
        return normals, radius, distance, valid

    usable_distance = np.where(usable, distance, np.nan)
    usable_points = np.where(usable[..., None], points, np.nan).astype(np.float32)
    origin = usable_points[usable].mean(axis=0) if usable.any() else np.zeros(3)
    moments = _integral_moments(usable_points, usable, origin.astype(np.float64))
    # Chessboard distance to the nearest jump pixel; a window of radius d - 1 holds none.
    clear = cv2.distanceTransform((~jumps).astype(np.uint8), cv2.DIST_C, 3)
    # With no jump at all the transform is "infinite" (a huge float).
    clear = np.minimum(clear, max(jumps.shape)).astype(np.int32) - 1
    if method == "box":
        radius = np.minimum(clear, window // 2)
    else:
        radius = np.minimum(clear, _adaptive_radius(moments, usable_points, usable_distance, usable, sigma, max_window // 2))
    radius = np.where(usable, radius, -1).astype(np.int16)
    normals = _box_normals(moments, usable_points, usable, radius, usable_distance, sigma_or_nan, float(depth_jump), _GATED_RADIUS)
    return normals, radius, distance, valid


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
    _, jumps, _ = _spikes_and_jumps(image, valid, sigma, float(depth_jump))
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


def _point_grid(points: Any) -> np.ndarray:
    """``points`` as a C-contiguous float32 (H, W, 3) grid; the Inf scan is left to `_point_ranges`.

    Anything but that layout goes through `check_point_grid`, which converts
    it or says what is wrong.
    """
    array = np.asarray(points)
    if array.dtype == np.float32 and array.ndim == 3 and array.shape[2] == 3 and array.flags.c_contiguous:
        return array
    return check_point_grid(array)


def _noise_sigma(range_sigma: Any, distance: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray | None, bool]:
    """Per-pixel noise sigma (H, W) or None, and whether it is still to be checked where ``valid``.

    A float32 or float64 array of the right shape is taken as it is (no
    copy), to be checked by `_spikes_and_jumps` in its pass over the pixels;
    anything else goes through `check_range_sigma`, which converts it or says
    what is wrong.
    """
    if range_sigma is None:
        return None, False
    if isinstance(range_sigma, np.ndarray) and range_sigma.shape == valid.shape and range_sigma.dtype in (np.float32, np.float64):
        return np.ascontiguousarray(range_sigma), True
    return check_range_sigma(distance, range_sigma), False


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
    normal is the gradient of a linear fit of ``1 / z``. Over a rectangle of
    pixels, with coordinates taken from its centre, the fit's normal equations
    are diagonal: it needs only the sums of ``1 / z``, of ``1 / z`` times the
    column and times the row, and (for the residual) of ``(1 / z)^2``. One
    pass builds integral images of these and of the pixel count, and then any
    window costs four lookups per sum, whatever its size. The fit measures
    errors along the viewing rays, the direction of range noise.

    A window is *clean* when all its pixels are valid and none is at a depth
    jump. Each pixel takes the largest clean window whose residual is
    consistent with the noise (larger residual means curvature: a smaller
    window); a pixel with no clean window (at a jump or a hole) gets a total
    least-squares fit of the neighbours on its side of the jump. Near the
    image border the smaller sizes are clipped by it (a pixel fits an
    off-centre rectangle), the largest is not: reaching far past the pixel on
    one side, it would cross creases near the border that its residual test
    misses.
    """
    pad = max(sizes) // 2
    table, inverse, centre = _inverse_depth_table(points, valid, jumps, pad)
    noise = -1.0
    if sigma is None:
        sigma = np.full(valid.shape, np.nan, np.float32)
        if len(sizes) > 1:
            # Without a noise model: the median residual of the smallest clean windows, for every pixel.
            residuals = _window_residuals(table, pad, valid, sizes[0])
            noise = float(np.median(residuals)) / (sizes[0] ** 2 - 3.0) if residuals.size else 0.0
    return _ladder_kernel(
        table, inverse, np.asarray(sizes, np.int64), centre, noise, points, valid, distance, sigma, depth_jump,
        float(projection.fx), float(projection.fy), float(projection.cx), float(projection.cy), _GATED_RADIUS,
    )


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
    gated_rows, gated_cols = np.nonzero(valid & (radius < 1))
    gated = _gated_sums(points, valid, distance, sigma, depth_jump, gated_rows, gated_cols, gated_radius)
    n_gated = 0
    sums = np.zeros(10)
    normal = np.zeros(3)
    for i in range(height):
        for j in range(width):
            if not valid[i, j]:
                continue
            if radius[i, j] >= 1:
                _window_sums(table, i, j, radius[i, j], sums)
            else:
                # Gated pixels come in raster order, as in the list.
                sums[:] = gated[n_gated]
                n_gated += 1
            if _smallest_eigen(sums, normal) < 0.0:
                continue
            facing = normal[0] * points[i, j, 0] + normal[1] * points[i, j, 1] + normal[2] * points[i, j, 2]
            sign = -1.0 if facing > 0.0 else 1.0
            for k in range(3):
                normals[i, j, k] = sign * normal[k]
    return normals


@numba.njit(**_JIT)
def _gated_sums(points, valid, distance, sigma, depth_jump, rows, cols, radius):  # pragma: no cover - compiled
    """Moments ``(n, 10)`` of the neighbours on the centre's side of a depth jump (range within the jump threshold), for each pixel ``(rows[k], cols[k])``.

    One call for all the pixels that need them: a function taking the
    arrays, called (or inlined) once per pixel, costs more in reference
    counting of its array arguments than in arithmetic.
    """
    height, width = valid.shape
    sums = np.empty((rows.size, 10))
    for k in range(rows.size):
        i = rows[k]
        j = cols[k]
        centre = distance[i, j]
        gate = depth_jump * centre
        if sigma[i, j] == sigma[i, j]:
            gate = max(gate, 4.0 * sigma[i, j])
        # Relative to the centre point, for precision; summed in registers (a sum in memory waits on
        # its previous update at every point).
        ox = points[i, j, 0]
        oy = points[i, j, 1]
        oz = points[i, j, 2]
        n = sx = sy = sz = sxx = sxy = sxz = syy = syz = szz = 0.0
        first = max(j - radius, 0)
        last = min(j + radius + 1, width)
        for r in range(max(i - radius, 0), min(i + radius + 1, height)):
            for c in range(first, last):
                # Branch-free: whether a neighbour is in is unpredictable, a mispredicted branch costs more.
                inside = valid[r, c] & (abs(distance[r, c] - centre) <= gate)
                x = np.float64(points[r, c, 0] - ox) if inside else 0.0
                y = np.float64(points[r, c, 1] - oy) if inside else 0.0
                z = np.float64(points[r, c, 2] - oz) if inside else 0.0
                n += 1.0 if inside else 0.0
                sx += x
                sy += y
                sz += z
                sxx += x * x
                sxy += x * y
                sxz += x * z
                syy += y * y
                syz += y * z
                szz += z * z
        sums[k, 0] = n
        sums[k, 1] = sx
        sums[k, 2] = sy
        sums[k, 3] = sz
        sums[k, 4] = sxx
        sums[k, 5] = sxy
        sums[k, 6] = sxz
        sums[k, 7] = syy
        sums[k, 8] = syz
        sums[k, 9] = szz
    return sums


@numba.njit(**_JIT)
def _spikes_and_jumps(distance, valid, sigma, depth_jump, check_sigma=False):  # pragma: no cover - compiled
    """Readings that are not spikes (a jump against >= 3 of 4 neighbours), then jumps among them.

    Returns the valid pixels that are not spikes, the pixels at a jump, and
    whether ``sigma`` checked out. ``sigma`` is NaN where there is no noise
    model. With ``check_sigma`` the third result says whether ``sigma`` is
    finite and > 0 at every valid pixel (the check of `check_range_sigma`,
    in the same pass).

    Branch-free loops over the flattened grid, on views shifted by a pixel
    or a row so that each loop indexes by its counter alone (which the
    compiler vectorises): the candidate jumps between neighbours, then the
    ramp test on the few candidates; then spikes, and the jumps from the
    pair flags. The flags are padded so that every pixel's four neighbours
    are in the arrays; a pair leaving the grid is never flagged. The ramp
    test and the test across a missing pixel look at eight pixels at a
    time, as the bytes of a word, and skip them while none is a candidate.
    """
    height, width = valid.shape
    size = height * width
    distance_flat = distance.reshape(size)
    valid_flat = valid.reshape(size)
    sigma_flat = sigma.reshape(size)
    # Squared noise limit of each pixel: 16 sigma^2, 0 without a model.
    noise = np.empty(size, np.float32)
    bad_sigma = 0
    for k in range(size):
        here = sigma_flat[k]
        noise[k] = 16.0 * here * here if here == here else 0.0
        bad_sigma += valid_flat[k] & ~((here > 0.0) & (here < math.inf))
    # Pair flags, padded: pixel k and its right neighbour at across[k + 1], pixel k and the one below at
    # down[k + width]. Every shifted index goes through a view, indexed by the loop counter alone (an
    # access at k + width gets a wrap-around test, since width might be negative, and stays scalar).
    across = np.zeros(size + 1, np.bool_)
    down = np.zeros(size + 2 * width, np.bool_)
    right_pair = across[1:]
    below_pair = down[width:]
    _pair_jumps(distance_flat[:-1], distance_flat[1:], noise[:-1], noise[1:], valid_flat[:-1], valid_flat[1:],
                depth_jump, right_pair[:-1])
    for i in range(1, height + 1):
        across[i * width] = False  # the last pixel of a row has no right neighbour
    _pair_jumps(distance_flat[:-width], distance_flat[width:], noise[:-width], noise[width:], valid_flat[:-width],
                valid_flat[width:], depth_jump, below_pair[: size - width])
    # What the ramp test below and the test across a missing pixel further down look for, a byte per
    # pixel: bit 0 a flagged pair, bit 1 a missing pixel. Most bytes are 0, and both tests skip eight
    # pixels at a time (a word) while they are: a loop over single pixels costs about a cycle for each.
    n_words = (size + 7) // 8
    attention = np.zeros(8 * n_words, np.uint8)
    for k in range(size):
        attention[k] = np.uint8(right_pair[k] | below_pair[k]) | (np.uint8(~valid_flat[k]) << 1)
    words = attention.view(np.uint64)
    for word in range(n_words):
        if words[word] & _BIT0_BYTES == 0:
            continue
        for k in range(8 * word, min(8 * word + 8, size)):
            i, j = k // width, k % width
            # A ramp needs a valid pixel before the pair and one after it.
            if right_pair[k] and 0 < j < width - 2 and valid_flat[k - 1] and valid_flat[k + 2]:
                right_pair[k] = not _is_ramp(distance_flat[k - 1], distance_flat[k], distance_flat[k + 1], distance_flat[k + 2])
            if below_pair[k] and 0 < i < height - 2 and valid_flat[k - width] and valid_flat[k + 2 * width]:
                below_pair[k] = not _is_ramp(
                    distance_flat[k - width], distance_flat[k], distance_flat[k + width], distance_flat[k + 2 * width]
                )
    # Spikes: a jump against three or four neighbours. Clean: valid and not a spike (pixel k at clean[k + width]).
    clean = np.zeros(size + 2 * width, np.bool_)
    _clean_flags(right_pair[:size], across[:size], below_pair[:size], down[:size], valid_flat, clean[width : width + size])
    # Jumps: both pixels of a flagged pair, if both are clean.
    jumps = np.empty(size, np.bool_)
    _jump_flags(right_pair[:size], across[:size], below_pair[:size], down[:size], clean[width : width + size],
                clean[width + 1 : width + 1 + size], clean[width - 1 : width - 1 + size], clean[2 * width :], clean[:size], jumps)
    # Across one missing pixel (rare: tested here, not in the loops above).
    for word in range(n_words):
        if words[word] & _BIT1_BYTES == 0:
            continue
        for k in range(8 * word, min(8 * word + 8, size)):
            if valid_flat[k]:
                continue
            i, j = k // width, k % width
            if 0 < j < width - 1 and clean[k - 1 + width] and clean[k + 1 + width]:
                if _is_jump(distance_flat[k - 1], distance_flat[k + 1], noise[k - 1] + noise[k + 1], depth_jump, 2.0):
                    jumps[k - 1] = True
                    jumps[k + 1] = True
            if 0 < i < height - 1 and clean[k] and clean[k + 2 * width]:
                if _is_jump(distance_flat[k - width], distance_flat[k + width], noise[k - width] + noise[k + width], depth_jump, 2.0):
                    jumps[k - width] = True
                    jumps[k + width] = True
    return clean[width : width + size].reshape((height, width)), jumps.reshape((height, width)), not (check_sigma and bad_sigma > 0)


@numba.njit(**_JIT)
def _pair_jumps(a, b, noise_a, noise_b, valid_a, valid_b, depth_jump, out):  # pragma: no cover - compiled
    """``out[k]``: both valid and neighbouring ranges ``a[k]``, ``b[k]`` differ by more than the jump threshold and the noise."""
    for k in range(out.shape[0]):
        out[k] = valid_a[k] & valid_b[k] & _is_jump(a[k], b[k], noise_a[k] + noise_b[k], depth_jump, 1.0)


@numba.njit(**_JIT)
def _clean_flags(right, left, below, above, valid, clean):  # pragma: no cover - compiled
    """Per pixel: valid and not a spike (a jump against >= 3 of its 4 neighbours, the pair flags given)."""
    for k in range(clean.shape[0]):
        count = np.int32(right[k]) + np.int32(left[k]) + np.int32(below[k]) + np.int32(above[k])
        clean[k] = valid[k] & (count < 3)


@numba.njit(**_JIT)
def _jump_flags(right, left, below, above, clean, clean_right, clean_left, clean_below, clean_above, jumps):  # pragma: no cover - compiled
    """Per pixel: clean, and a flagged pair with a clean neighbour."""
    for k in range(jumps.shape[0]):
        jumps[k] = clean[k] & ((right[k] & clean_right[k]) | (left[k] & clean_left[k])
                               | (below[k] & clean_below[k]) | (above[k] & clean_above[k]))


@numba.njit(**_JIT, inline="always")
def _is_jump(a, b, noise, depth_jump, step):  # pragma: no cover - compiled
    """Whether ranges ``a`` and ``b``, ``step`` pixels apart, differ by more than ``depth_jump`` times the nearer and the noise limit."""
    relative = depth_jump * min(a, b)
    gap = (a - b) / step
    return gap * gap > max(relative * relative, noise)


@numba.njit(**_JIT, inline="always")
def _is_ramp(before, here, there, after):  # pragma: no cover - compiled
    """Whether the step between the ranges ``here`` and ``there`` of neighbouring pixels continues the steps on both sides of it.

    ``before`` and ``after`` are the ranges of the pixels before and after
    the pair along the same line. A surface seen at a grazing angle (a floor
    far ahead) changes range by a large step per pixel, but steadily; a depth
    jump is a step much larger than its neighbours. Both neighbouring steps
    must agree in sign and lie within a factor of two of this one. (Ranges,
    not the arrays: a function taking arrays costs atomic reference-count
    updates at every call.)
    """
    step = there - here
    for other in (here - before, after - there):
        if other * step <= 0.0 or abs(other) < 0.5 * abs(step) or abs(other) > 2.0 * abs(step):
            return False
    return True


@numba.njit(**_JIT)
def _inverse_depth_table(points, valid, jumps, pad):  # pragma: no cover - compiled
    """Integral images of the usable pixels' count, v, c v, r v and v^2, padded; inverse depth; its mean.

    ``v = 1/z - mean``; ``c`` and ``r`` are the column and row counted from
    the image centre (centred sums lose fewer digits). A pixel is usable when
    valid and not at a depth jump; the inverse depth (H, W) float64 is NaN
    elsewhere. A one-pixel hole (a removed outlier) would spoil every window
    around it; on a plane the mean inverse depth of its two opposite
    neighbours is exact, so such holes are filled (for the sums only) and
    count as usable.

    The table is (5, H + 1 + 2 pad, W + 1 + 2 pad): entry ``[k, pad + i, pad
    + j]`` sums rows < i and columns < j, and the pad repeats the edge
    values, so that a window reaching up to ``pad`` pixels past the border
    sums what lies inside the image (the window clipped by the border).
    """
    height, width = valid.shape
    inverse = np.empty((height, width))
    total = 0.0
    count = 0
    for i in range(height):
        for j in range(width):
            z = points[i, j, 2]
            if valid[i, j] and z > 0 and not jumps[i, j]:
                inverse[i, j] = 1.0 / z
                total += inverse[i, j]
                count += 1
            else:
                inverse[i, j] = np.nan
    centre = total / count if count else 0.0
    # Entries above the first row or left of the first column sum nothing; the loops below write all others.
    table = np.empty((5, height + 1 + 2 * pad, width + 1 + 2 * pad))
    table[:, : pad + 1, :] = 0.0
    table[:, :, : pad + 1] = 0.0
    column_offset = width // 2
    row_offset = height // 2
    for i in range(height):
        r = float(i - row_offset)
        n = 0.0
        values = 0.0
        by_column = 0.0
        by_row = 0.0
        squares = 0.0
        above = pad + i
        for j in range(width):
            value = inverse[i, j]
            if not value == value:
                if 0 < j < width - 1:
                    value = 0.5 * (inverse[i, j - 1] + inverse[i, j + 1])
                if not value == value and 0 < i < height - 1:
                    value = 0.5 * (inverse[i - 1, j] + inverse[i + 1, j])
            if value == value:
                v = value - centre
                n += 1.0
                values += v
                by_column += (j - column_offset) * v
                by_row += r * v
                squares += v * v
            column = pad + j + 1
            table[0, above + 1, column] = table[0, above, column] + n
            table[1, above + 1, column] = table[1, above, column] + values
            table[2, above + 1, column] = table[2, above, column] + by_column
            table[3, above + 1, column] = table[3, above, column] + by_row
            table[4, above + 1, column] = table[4, above, column] + squares
        for k in range(5):
            for column in range(pad + width + 1, width + 1 + 2 * pad):
                table[k, above + 1, column] = table[k, above + 1, pad + width]
    for k in range(5):
        for row in range(pad + height + 1, height + 1 + 2 * pad):
            table[k, row, :] = table[k, pad + height, :]
    return table, inverse, centre


@numba.njit(**_JIT, inline="always")
def _rectangle_sum(table, top, bottom, left, right, k):  # pragma: no cover - compiled
    return table[k, bottom, right] - table[k, top, right] - table[k, bottom, left] + table[k, top, left]


@numba.njit(**_JIT)
def _window_residuals(table, pad, valid, size):  # pragma: no cover - compiled
    """Plane-fit residual sums of squares of 1/z over every full, clean ``size`` window centred on a valid pixel."""
    height, width = valid.shape
    half = size // 2
    n = float(size * size)
    inverse_energy = 12.0 / (n * (size * size - 1))
    residuals = np.empty(max(height - 2 * half, 0) * max(width - 2 * half, 0))
    found = 0
    for i in range(half, height - half):
        for j in range(half, width - half):
            top, bottom, left, right = pad + i - half, pad + i + half + 1, pad + j - half, pad + j + half + 1
            if not valid[i, j] or _rectangle_sum(table, top, bottom, left, right, 0) != n:
                continue
            total = _rectangle_sum(table, top, bottom, left, right, 1)
            slope_s = _rectangle_sum(table, top, bottom, left, right, 2) - (j - width // 2) * total
            slope_t = _rectangle_sum(table, top, bottom, left, right, 3) - (i - height // 2) * total
            squares = _rectangle_sum(table, top, bottom, left, right, 4)
            residuals[found] = max(squares - total * total / n - (slope_s * slope_s + slope_t * slope_t) * inverse_energy, 0.0)
            found += 1
    return residuals[:found]


@numba.njit(**_JIT)
def _clipped_extent(index, half, length):  # pragma: no cover - compiled
    """Pixels of the window ``index - half .. index + half`` inside ``0 .. length - 1``, and its centre's offset from ``index``."""
    first = max(index - half, 0)
    last = min(index + half, length - 1)
    return last - first + 1, 0.5 * (first + last) - index


@numba.njit(**_JIT)
def _ladder_kernel(table, inverse, sizes, centre, noise, points, valid, distance, sigma, depth_jump, fx, fy, cx, cy, gated_radius):  # pragma: no cover - compiled
    """Normals from the window fits; ``noise`` is the variance of 1/z noise, or < 0 to take it from ``sigma``.

    ``table`` is padded by the largest half size (`_inverse_depth_table`).
    Range noise as noise of 1/z: d(1/z) = dz / z^2 and dz is about dr z / r,
    so its sigma is ``sigma / (r z)``. Windows are clipped by the image
    border; a clipped window is fitted about its own centre (where the normal
    equations are diagonal) and evaluated at the pixel.

    Row by row, the largest window's fit is computed for every pixel in one
    branch-free loop (which the compiler vectorises); the pixels it does not
    suit go down the ladder, each smaller size fitted for all of the row's
    pixels left in such a loop (`_ladder_fits`; a pixel at a time, down
    the ladder, these fits took a third of the kernel's time). Those with no
    clean window at all are fitted together after the last row
    (`_gated_sums`, `_plane_normals`).
    """
    height, width = valid.shape
    normals = np.empty((height, width, 3), dtype=np.float32)
    radius = np.empty((height, width), np.int16)
    n_sizes = sizes.shape[0]
    column_offset = width // 2
    row_offset = height // 2
    largest = sizes[n_sizes - 1] // 2
    pad = largest
    # Without a smaller size to fall back on, any clean window is taken.
    any_residual = n_sizes == 1
    # Per column, the largest window's width, its centre's offset from the pixel, and the factors of
    # the fit: slope along the row = ramp sum * 12 / (n (w^2 - 1)) with n = w h.
    column_count = np.empty(width)
    column_middle = np.empty(width)
    for j in range(width):
        column_count[j], column_middle[j] = _clipped_extent(j, largest, width)
    column_reciprocal = 1.0 / column_count
    column_factor = 12.0 / (column_count * (column_count * column_count - 1.0))
    column_centre = np.arange(width) - column_offset + column_middle
    # Per column for each smaller size: the window's width, its centre's offset from the pixel, and that
    # centre counted from the image centre.
    level_columns = np.empty((n_sizes - 1, width), np.int64)
    level_middle = np.empty((n_sizes - 1, width))
    level_centre = np.empty((n_sizes - 1, width))
    for index in range(n_sizes - 1):
        for j in range(width):
            level_columns[index, j], level_middle[index, j] = _clipped_extent(j, sizes[index] // 2, width)
            level_centre[index, j] = j - column_offset + level_middle[index, j]
    # Per row: whether each pixel goes down the ladder, in whole words of eight flags for the listing
    # below (those past the row's end stay False).
    n_words = (width + 7) // 8
    waiting = np.zeros(8 * n_words, np.bool_)
    waiting_words = waiting.view(np.uint64)
    # Per row: the columns of the pixels still going down the ladder (unsigned: no wrap-around test where
    # they index) and their noise variance of 1/z; room for `_ladder_fits`' inputs and one size's fits.
    pending = np.empty(8 * n_words, np.uint32)
    pending_variance = np.empty(width)
    gathered = np.empty((9, width))
    fitted = np.zeros(width, np.bool_)
    fit = np.empty((4, width))
    # Pixels without a clean window, fitted after the rows (`_gated_sums`).
    gated_rows = np.empty(height * width, np.int64)
    gated_cols = np.empty(height * width, np.int64)
    n_gated = 0
    for i in range(height):
        rows, row_middle = _clipped_extent(i, largest, height)
        row_reciprocal = 1.0 / rows
        row_factor = 12.0 / (rows * (rows * rows - 1.0))
        row_centre = i - row_offset + row_middle
        top = pad + i - largest
        bottom = pad + i + largest + 1
        # Window sums of pixel j as element j of these slices (plain indices vectorise).
        span = 2 * largest + 1
        count_br, count_tr = table[0, bottom, span:], table[0, top, span:]
        count_bl, count_tl = table[0, bottom, :width], table[0, top, :width]
        total_br, total_tr = table[1, bottom, span:], table[1, top, span:]
        total_bl, total_tl = table[1, bottom, :width], table[1, top, :width]
        column_br, column_tr = table[2, bottom, span:], table[2, top, span:]
        column_bl, column_tl = table[2, bottom, :width], table[2, top, :width]
        row_br, row_tr = table[3, bottom, span:], table[3, top, span:]
        row_bl, row_tl = table[3, bottom, :width], table[3, top, :width]
        square_br, square_tr = table[4, bottom, span:], table[4, top, span:]
        square_bl, square_tl = table[4, bottom, :width], table[4, top, :width]
        sigma_row = sigma[i]
        inverse_row = inverse[i]
        distance_row = distance[i]
        valid_row = valid[i]
        out = normals[i]
        radius_row = radius[i]
        v_offset = i - cy
        for j in range(width):
            count = count_br[j] - count_tr[j] - count_bl[j] + count_tl[j]
            total = total_br[j] - total_tr[j] - total_bl[j] + total_tl[j]
            slope_s = column_br[j] - column_tr[j] - column_bl[j] + column_tl[j] - column_centre[j] * total
            slope_t = row_br[j] - row_tr[j] - row_bl[j] + row_tl[j] - row_centre * total
            squares = square_br[j] - square_tr[j] - square_bl[j] + square_tl[j]
            n = rows * column_count[j]
            a = slope_s * column_factor[j] * row_reciprocal
            b = slope_t * row_factor * column_reciprocal[j]
            mean = total * row_reciprocal * column_reciprocal[j]
            residual = squares - total * mean - slope_s * a - slope_t * b
            # The fit's value at the pixel (off the window's centre when clipped).
            c = mean - a * column_middle[j] - b * row_middle
            # 1/z = a s + b t + c about the pixel; as A u + B v + C the plane's normal is -(A, B, C).
            big_c = c + centre - a * (j - cx) - b * v_offset
            big_a = a * fx
            big_b = b * fy
            norm_squared = big_a * big_a + big_b * big_b + big_c * big_c
            if noise >= 0.0:
                variance = noise
            else:
                scaled = sigma_row[j] * inverse_row[j] / distance_row[j]
                variance = scaled * scaled
            degrees = max(n - 3.0, 1.0)
            allowed = degrees * (1.0 + 3.0 * math.sqrt(2.0 / degrees))
            # Clipped by the border, the largest window is used only as the sole size: off-centre it
            # reaches far past the pixel on one side, across creases near the border that its residual
            # test misses (smaller windows reach less far).
            accepted = (count == n) & ((n == span * span) | any_residual) & (any_residual | (residual <= variance * allowed)) & (norm_squared > 0.0)
            # Facing the sensor (n . p < 0): n . p has the sign of -(fitted 1/z at the pixel) = -(c + centre).
            scale = -math.copysign(1.0, c + centre) / math.sqrt(norm_squared)
            # An invalid pixel gets no normal; one the largest window does not suit gets its normal and
            # radius further down the ladder.
            out[j, 0] = big_a * scale if valid_row[j] else np.nan
            out[j, 1] = big_b * scale if valid_row[j] else np.nan
            out[j, 2] = big_c * scale if valid_row[j] else np.nan
            radius_row[j] = largest if accepted & valid_row[j] else -1
            waiting[j] = valid_row[j] & ~accepted
        # The pixels the largest window does not suit go down the ladder, a size at a time, each size fitted
        # for all of the row's pixels left at once (`_ladder_fits`). Listed without a branch (whether a
        # pixel is listed is hard to predict): each is written at the end of the list, which grows if it is.
        # Eight pixels (a word of flags) are skipped at a time while none is listed: most of a row is not.
        n_pending = 0
        for word in range(n_words):
            if waiting_words[word] == 0:
                continue
            for j in range(8 * word, 8 * word + 8):
                pending[n_pending] = j
                n_pending += waiting[j]
        for k in range(n_pending):
            j = pending[k]
            if noise >= 0.0:
                pending_variance[k] = noise
            else:
                scaled = sigma[i, j] / (distance[i, j] * points[i, j, 2])
                pending_variance[k] = scaled * scaled
        # The largest window was tried above; the smaller ones may be clipped by the border.
        for index in range(n_sizes - 2, -1, -1):
            if n_pending == 0:
                break
            half = sizes[index] // 2
            _ladder_fits(table, pad, i, half, height, level_columns[index], level_middle[index], level_centre[index],
                         pending_variance, index > 0, centre, fx, fy, cx, cy, pending[:n_pending], gathered, fitted, fit)
            left = 0
            for k in range(n_pending):
                j = pending[k]
                if not fitted[k]:
                    pending[left] = j
                    pending_variance[left] = pending_variance[k]
                    left += 1
                    continue
                # Fitted, but with no normal (NaN): the pixel stays without one.
                radius[i, j] = half if fit[3, k] > 0.0 else -1
                normals[i, j, 0] = fit[0, k]
                normals[i, j, 1] = fit[1, k]
                normals[i, j, 2] = fit[2, k]
            n_pending = left
        for k in range(n_pending):
            # No clean window: a total least-squares plane through the neighbours on this side of the
            # depth jump. (Least squares of 1/z is more accurate on average there, but region growing
            # finds more planes with these normals: thin strips between a jump and the border.)
            radius[i, pending[k]] = -1
            gated_rows[n_gated] = i
            gated_cols[n_gated] = pending[k]
            n_gated += 1
    gated = _plane_normals(
        _gated_sums(points, valid, distance, sigma, depth_jump, gated_rows[:n_gated], gated_cols[:n_gated], gated_radius)
    )
    for k in range(n_gated):
        i = gated_rows[k]
        j = gated_cols[k]
        nx, ny, nz = gated[0, k], gated[1, k], gated[2, k]
        sign = -1.0 if nx * points[i, j, 0] + ny * points[i, j, 1] + nz * points[i, j, 2] > 0.0 else 1.0
        normals[i, j, 0] = sign * nx
        normals[i, j, 1] = sign * ny
        normals[i, j, 2] = sign * nz
    return normals, radius


@numba.njit(**_JIT, inline="always")
def _ladder_fits(table, pad, i, half, height, columns, column_middle, column_centre, variance, residual_test,
                 centre, fx, fy, cx, cy, pending, gathered, fitted, fit):  # pragma: no cover - compiled
    """One smaller size of `_ladder_kernel`'s ladder for the pixels of row ``i`` in the columns ``pending``.

    ``columns``, ``column_middle`` and ``column_centre`` are per column the
    window's width (clipped by the border), its centre's offset from the
    pixel and that centre counted from the image centre; ``variance`` the
    noise variance of 1/z of each pixel listed. ``fitted[k]``: pixel
    ``pending[k]``'s window is clean and (with ``residual_test``) its
    residual is noise; ``fit[:, k]``: its normal and 1 if there is one,
    else NaN and 0.

    The window sums and the column's factors are gathered into the rows of
    ``gathered`` (9, W) first, a sum at a time for all the pixels listed
    (the pixel's column indexes four rows of the table: at a pixel at a
    time, the twenty rows' addresses do not all fit in registers); then the
    fits, with their divisions, run in a loop over those rows that the
    compiler vectorises (which leaves each pixel's arithmetic as it is: a
    pixel's normal does not depend on the others listed).
    """
    rows, middle_row = _clipped_extent(i, half, height)
    row_centre = i - (height // 2) + middle_row
    top = pad + i - half
    bottom = pad + i + half + 1
    v_offset = i - cy
    n_pending = pending.size
    # The window sums of the pixel in column j: differences of the table's columns left + j and right + j.
    right = pad + half + 1
    left = pad - half
    for m in range(5):
        bottom_right, top_right = table[m, bottom, right:], table[m, top, right:]
        bottom_left, top_left = table[m, bottom, left:], table[m, top, left:]
        sums = gathered[m]
        for k in range(n_pending):
            j = pending[k]
            sums[k] = bottom_right[j] - top_right[j] - bottom_left[j] + top_left[j]
    for k in range(n_pending):
        j = pending[k]
        gathered[5, k] = columns[j]
        gathered[6, k] = column_middle[j]
        gathered[7, k] = column_centre[j]
        gathered[8, k] = j - cx
    count, total_sum, column_sum, row_sum, square_sum = gathered[0], gathered[1], gathered[2], gathered[3], gathered[4]
    width_of, middle_of, centre_of, offset_of = gathered[5], gathered[6], gathered[7], gathered[8]
    fit_x, fit_y, fit_z, has_fit = fit[0], fit[1], fit[2], fit[3]
    for k in range(n_pending):
        n = rows * width_of[k]
        total = total_sum[k]
        slope_s = column_sum[k] - centre_of[k] * total
        slope_t = row_sum[k] - row_centre * total
        a = 12.0 * slope_s / (n * (width_of[k] * width_of[k] - 1.0))
        b = 12.0 * slope_t / (n * (rows * rows - 1.0))
        residual = square_sum[k] - total * total / n - slope_s * a - slope_t * b
        clean = (rows >= 2) & (width_of[k] >= 2.0) & (count[k] == n)
        fitted[k] = clean & ((not residual_test) | (residual <= variance[k] * _chi_square_allowance(n)))
        c = total / n - a * middle_of[k] - b * middle_row
        big_a = a * fx
        big_b = b * fy
        big_c = c + centre - a * offset_of[k] - b * v_offset
        norm_squared = big_a * big_a + big_b * big_b + big_c * big_c
        # Facing the sensor (n . p < 0): n . p has the sign of -(fitted 1/z at the pixel) = -(c + centre).
        scale = -math.copysign(1.0, c + centre) / math.sqrt(norm_squared)
        has_normal = norm_squared > 0.0
        fit_x[k] = big_a * scale if has_normal else np.nan
        fit_y[k] = big_b * scale if has_normal else np.nan
        fit_z[k] = big_c * scale if has_normal else np.nan
        has_fit[k] = 1.0 if has_normal else 0.0


@numba.njit(**_JIT)
def _plane_normals(moments):  # pragma: no cover - compiled
    """Total least-squares plane normals of many sets of moments ``moments`` (n, 10): (3, n), NaN where a set has none.

    `rangesurf._planefit.smallest_eigen` without its trigonometry: the
    smallest eigenvalue of each 3x3 covariance by Newton's method on the
    characteristic polynomial from 0 (below the smallest root the polynomial
    is convex and falling, so the steps rise to that root monotonically),
    then the eigenvector as the largest cross product of two rows of
    ``C - lambda I``. Several times faster, the same normal.

    The sets take their Newton steps together, a step of every set still
    going in one loop the compiler vectorises (a set that has stopped keeps
    its root), until all have stopped: one set at a time, each step waits
    for the one before.
    """
    count = moments.shape[0]
    # The covariance (a00, a01, a02, a11, a12, a22) of each set, and the coefficients of
    # det(C - l I) = -l^3 + trace l^2 - minors l + det.
    covariance = np.empty((6, count))
    trace = np.empty(count)
    minors = np.empty(count)
    det = np.empty(count)
    has_plane = np.empty(count, np.bool_)
    for k in range(count):
        n = moments[k, 0]
        reciprocal = 1.0 / n
        mx = moments[k, 1] * reciprocal
        my = moments[k, 2] * reciprocal
        mz = moments[k, 3] * reciprocal
        a00 = moments[k, 4] * reciprocal - mx * mx
        a01 = moments[k, 5] * reciprocal - mx * my
        a02 = moments[k, 6] * reciprocal - mx * mz
        a11 = moments[k, 7] * reciprocal - my * my
        a12 = moments[k, 8] * reciprocal - my * mz
        a22 = moments[k, 9] * reciprocal - mz * mz
        covariance[0, k], covariance[1, k], covariance[2, k] = a00, a01, a02
        covariance[3, k], covariance[4, k], covariance[5, k] = a11, a12, a22
        trace[k] = a00 + a11 + a22
        minors[k] = (a11 * a22 - a12 * a12) + (a00 * a22 - a02 * a02) + (a00 * a11 - a01 * a01)
        det[k] = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
        has_plane[k] = (n >= 3.0) & (trace[k] > 0.0)
    smallest = np.zeros(count)
    going = has_plane & (det > 0.0)
    for _ in range(50):
        still = 0
        for k in range(count):
            root = smallest[k]
            value = ((trace[k] - root) * root - minors[k]) * root + det[k]
            slope = (2.0 * trace[k] - 3.0 * root) * root - minors[k]
            step = value / slope
            moves = going[k] & (slope < 0.0)
            smallest[k] = root - step if moves else root
            going[k] = moves & ~(-step <= 1e-12 * trace[k])
            still += going[k]
        if still == 0:
            break
    normals = np.empty((3, count))
    for k in range(count):
        vx, vy, vz, d = eigenvector(covariance[0, k], covariance[1, k], covariance[2, k], covariance[3, k],
                                    covariance[4, k], covariance[5, k], smallest[k])
        found = has_plane[k] & (d > 0.0)
        scale = 1.0 / math.sqrt(d)
        normals[0, k] = vx * scale if found else np.nan
        normals[1, k] = vy * scale if found else np.nan
        normals[2, k] = vz * scale if found else np.nan
    return normals


@numba.njit(**_JIT, inline="always")
def _chi_square_allowance(n):  # pragma: no cover - compiled
    """Largest residual sum of squares of an n-pixel plane fit, in noise variances, that is still noise.

    ``n - 3`` degrees of freedom plus three standard errors of the chi-square
    distribution; anything more is curvature.
    """
    dof = max(n - 3.0, 1.0)
    return dof * (1.0 + 3.0 * math.sqrt(2.0 / dof))


@numba.njit(**_JIT)
def _cross_normals(points, valid, jumps):  # pragma: no cover - compiled
    """Cross product of central differences along the row and the column; also the radius map (1, or -1 where invalid)."""
    height, width = valid.shape
    normals = np.empty((height, width, 3), dtype=np.float32)
    radius = np.empty((height, width), np.int16)
    for i in range(height):
        for j in range(width):
            normals[i, j, 0] = np.nan
            normals[i, j, 1] = np.nan
            normals[i, j, 2] = np.nan
            radius[i, j] = 1 if valid[i, j] else -1
            if not valid[i, j]:
                continue
            right = j + 1 < width and valid[i, j + 1]
            left = j > 0 and valid[i, j - 1]
            down = i + 1 < height and valid[i + 1, j]
            up = i > 0 and valid[i - 1, j]
            if jumps[i, j]:
                # Keep only the neighbour closer in range to the centre.
                if right and left:
                    if _range_gap(points, i, j, i, j + 1) < _range_gap(points, i, j, i, j - 1):
                        left = False
                    else:
                        right = False
                if down and up:
                    if _range_gap(points, i, j, i + 1, j) < _range_gap(points, i, j, i - 1, j):
                        up = False
                    else:
                        down = False
            if not (right or left) or not (down or up):
                continue
            # One-sided where a neighbour is missing: the centre stands in for it.
            ja = j + 1 if right else j
            jb = j - 1 if left else j
            ia = i + 1 if down else i
            ib = i - 1 if up else i
            ux = points[i, ja, 0] - points[i, jb, 0]
            uy = points[i, ja, 1] - points[i, jb, 1]
            uz = points[i, ja, 2] - points[i, jb, 2]
            vx = points[ia, j, 0] - points[ib, j, 0]
            vy = points[ia, j, 1] - points[ib, j, 1]
            vz = points[ia, j, 2] - points[ib, j, 2]
            nx = uy * vz - uz * vy
            ny = uz * vx - ux * vz
            nz = ux * vy - uy * vx
            norm_squared = nx * nx + ny * ny + nz * nz
            if not norm_squared > 0.0:
                continue
            scale = 1.0 / math.sqrt(norm_squared)
            if nx * points[i, j, 0] + ny * points[i, j, 1] + nz * points[i, j, 2] > 0.0:
                scale = -scale
            normals[i, j, 0] = nx * scale
            normals[i, j, 1] = ny * scale
            normals[i, j, 2] = nz * scale
    return normals, radius


@numba.njit(**_JIT)
def _range_gap(points, i, j, qi, qj):  # pragma: no cover - compiled
    """Difference of squared ranges of two pixels."""
    here = points[i, j, 0] ** 2 + points[i, j, 1] ** 2 + points[i, j, 2] ** 2
    there = points[qi, qj, 0] ** 2 + points[qi, qj, 1] ** 2 + points[qi, qj, 2] ** 2
    return abs(there - here)


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
    """Pinhole-path normals by explicit least squares of 1/z = A u + B v + C over clean windows.

    The window is clipped by the image border (at least 2 x 2 pixels left);
    a window with any invalid point gives NaN.
    """
    height, width = points.shape[:2]
    half = size // 2
    normals = np.full((height, width, 3), np.nan)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    u = (cols - projection.cx) / projection.fx
    v = (rows - projection.cy) / projection.fy
    for i in range(height):
        for j in range(width):
            window = (slice(max(i - half, 0), i + half + 1), slice(max(j - half, 0), j + half + 1))
            depth = points[window][..., 2].astype(np.float64)
            if min(depth.shape) < 2 or not np.isfinite(depth).all():
                continue
            depth = depth.ravel()
            design = np.column_stack([u[window].ravel(), v[window].ravel(), np.ones(depth.size)])
            coefficients = np.linalg.lstsq(design, 1.0 / depth, rcond=None)[0]
            normal = -coefficients / np.linalg.norm(coefficients)
            normals[i, j] = -normal if normal @ points[i, j] > 0 else normal
    return normals
