"""Planar region growing on the organized grid (Poppinga et al. 2008).

A region starts at the smoothest pixel not yet taken (its normal agrees best
with its neighbours'), with that pixel's normal as its plane, and grows
breadth-first over 4-neighbours.  A neighbour joins when

* its distance to the region's plane is within ``distance_sigmas`` noise
  sigmas of its range (the sensor model's sigma, so far and dark pixels get
  the tolerance their noise needs),
* its normal is within ``max_angle`` of the plane's normal, and
* it is not across a depth jump from the pixel it is reached from.

The plane is refitted by total least squares from running sums of the
members' coordinates (Poppinga's incremental fit: O(1) per added point)
whenever the region has grown by a quarter since the last fit, so it follows
the data rather than the seed's noisy normal.  Regions smaller than
``min_size`` pixels are dissolved; their pixels remain free, and only the
failed seed never seeds again.

Then (1) every region absorbs the free pixels around it that fit its final
plane (the pixels at its outline whose normals were spoiled by the depth
edge), and (2) neighbouring regions whose points fit one common plane within
the noise are merged (an edge or a noise line that split one wall).
Coplanar regions that do not touch stay separate segments.

References
----------
.. [1] J. Poppinga, N. Vaskevicius, A. Birk and K. Pathak, "Fast plane
   detection and polygonalization in noisy 3D range images", IROS 2008
   (the thesis's [46]).
.. [2] The reference thesis, Sections 2.2 and 3.1 (``shared/reference/thesis.md``).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numba
import numpy as np
from numpy.typing import ArrayLike

from rangesurf._checks import check_point_grid, check_range_sigma
from rangesurf._grid import ranges
from rangesurf._planefit import add_point, plane_eigen, planes_from_moments
from rangesurf.segment._segmentation import Segmentation

__all__ = ["grow_regions", "refine_upsampled"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")
# Refit the plane when the region has grown by this factor since the last fit.
_REFIT_GROWTH = 1.25
# Default smallest segment: this fraction of the image, and never fewer pixels than the floor.
_MIN_SIZE_FRACTION = 0.002
_MIN_SIZE_FLOOR = 20
# First refit (points): a plane through fewer noisy points is worse than the seed's normal.
_FIRST_FIT = 16
# In-plane spread (noise sigmas, both directions) a region needs before its own fit sets its normal.
_SUPPORT_SIGMAS = 4.0
# Final plane fits use the points this far (pixels) inside a segment's outline, if there are enough.
_INTERIOR_MARGIN = 2
_MIN_INTERIOR = 30
_MIN_INTERIOR_FRACTION = 0.5
# Points beyond this many residual RMS from the first fit are left out of the final one.
_TRIM_RMS = 2.0
# Largest increase of the residual variance that merging two neighbouring segments may cause.
_MERGE_VARIANCE_GAIN = 1.5
# Rings of outline pixels the absorption step may add to a segment.
_ABSORB_SWEEPS = 4
# A segment thinner than this (pixels) whose plane lies between two neighbours' is a rounded crease.
_BEVEL_WIDTH = 6.0
_BEVEL_SLACK = 5.0
# Defaults of the join test (grow_regions documents them).
_DISTANCE_SIGMAS = 3.0
_MAX_ANGLE = 20.0
_DEPTH_JUMP = 0.05
# Neighbour offsets (row, column) for growing and for region adjacency.
_FOUR = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]], dtype=np.int64)


def grow_regions(
    points: ArrayLike,
    normals: ArrayLike,
    *,
    range_sigma: ArrayLike | float,
    distance_sigmas: float = _DISTANCE_SIGMAS,
    max_angle: float = _MAX_ANGLE,
    depth_jump: float = _DEPTH_JUMP,
    min_size: int | None = None,
    merge: bool = True,
) -> Segmentation:
    """Split an organized frame into planar segments by region growing.

    Parameters
    ----------
    points : (H, W, 3) float array
        Sensor-frame points (metres), NaN where invalid (`RangeFrame.points`,
        preferably of the denoised range).
    normals : (H, W, 3) float array
        Unit normals facing the sensor, NaN where unknown
        (`rangesurf.normals.estimate_normals`).
    range_sigma : float or (H, W) array
        Range noise standard deviation (metres), e.g.
        ``frame.sensor.range_sigma(frame.range)``; sets the point-to-plane
        tolerance.
    distance_sigmas : float
        Point-to-plane tolerance in noise sigmas.
    max_angle : float
        Largest angle (degrees) between a joining pixel's normal and the
        region's plane normal.
    depth_jump : float
        Neighbours whose ranges differ by more than this fraction of the
        range are never joined (as in `rangesurf.normals.depth_discontinuities`).
    min_size : int, optional
        Smallest segment kept (pixels). Default: 0.2 % of the image (50
        pixels of an SR-3000 frame, 614 of a 640x480 one), so that the same
        scene gives the same segments at any resolution.
    merge : bool
        Merge neighbouring segments that lie on one plane.

    Returns
    -------
    Segmentation
        Labels (largest segment first), planes, RMS residuals (UL2), sizes.

    Raises
    ------
    ValueError
        On shapes that are not ``(H, W, 3)`` or disagree, Inf values, or
        options out of range.

    References
    ----------
    .. [1] J. Poppinga, N. Vaskevicius, A. Birk and K. Pathak, "Fast plane
       detection and polygonalization in noisy 3D range images", IROS 2008.

    Examples
    --------
    Two planes meeting at a right angle (a floor and a wall), noise-free:

    >>> import numpy as np
    >>> from rangesurf.normals import estimate_normals
    >>> from rangesurf.segment import grow_regions
    >>> rows, cols = np.mgrid[0:60, 0:80].astype(np.float32)
    >>> x = (cols - 40) * 0.02
    >>> z = np.where(cols < 40, 2.0, 2.0 + (cols - 40) * 0.02)
    >>> points = np.dstack([x, (rows - 30) * 0.02, z]).astype(np.float32)
    >>> segments = grow_regions(points, estimate_normals(points), range_sigma=0.002)
    >>> segments.n_segments
    2
    >>> np.round(segments.planes[1:], 3) + 0.0  # n . p + d = 0 of the wall (z = 2) and the slanted face
    array([[ 0.   ,  0.   , -1.   ,  2.   ],
           [ 0.707,  0.   , -0.707,  1.414]])
    """
    points, normals = _check_inputs(points, normals)
    for name, value in (("distance_sigmas", distance_sigmas), ("depth_jump", depth_jump)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be > 0, got {value!r}")
    if not (isinstance(max_angle, (int, float)) and 0 < max_angle < 90):
        raise ValueError(f"max_angle must be in (0, 90) degrees, got {max_angle!r}")
    if min_size is None:
        min_size = default_min_size(*points.shape[:2])
    if isinstance(min_size, bool) or not isinstance(min_size, (int, np.integer)) or min_size < 1:
        raise ValueError(f"min_size must be an integer >= 1, got {min_size!r}")

    distance, valid = ranges(points)
    sigma = check_range_sigma(np.where(valid, distance, np.nan), range_sigma)
    return _grow(points, normals, distance, valid, sigma, float(distance_sigmas), float(max_angle), float(depth_jump), int(min_size), merge)


def _grow(
    points: np.ndarray,
    normals: np.ndarray,
    distance: np.ndarray,
    valid: np.ndarray,
    sigma: np.ndarray,
    distance_sigmas: float = _DISTANCE_SIGMAS,
    max_angle: float = _MAX_ANGLE,
    depth_jump: float = _DEPTH_JUMP,
    min_size: int | None = None,
    merge: bool = True,
) -> Segmentation:
    """`grow_regions` on checked inputs: float32 grids, ``distance`` and ``valid`` from `ranges`, ``sigma`` (H, W).

    ``sigma`` is read only where ``valid``.
    """
    if min_size is None:
        min_size = default_min_size(*valid.shape)
    growable = _with_normal(valid, normals)
    order = _seed_order(normals, growable, math.cos(math.radians(max_angle / 2)))
    labels, moments = _grow_kernel(
        points,
        normals,
        distance,
        sigma,
        growable,
        order,
        distance_sigmas,
        math.cos(math.radians(max_angle)),
        depth_jump,
        min_size,
        float(_FIRST_FIT),
    )
    planes, _ = planes_from_moments(moments)
    _refine_boundaries(points, distance, sigma, labels, planes, moments, depth_jump)
    planes, _ = planes_from_moments(moments)
    # Planes are fitted to what growing found (the core), not to the outline pixels absorbed below.
    core, core_moments = labels.copy(), moments.copy()
    unlabelled = _absorb_kernel(points, distance, sigma, valid, labels, planes, moments, distance_sigmas, depth_jump, _ABSORB_SWEEPS)
    if merge:
        roots, moments = _merge_coplanar(labels, moments, math.cos(math.radians(max_angle)))
        labels, core = roots[labels], roots[core]
        merged_core = np.zeros_like(core_moments)
        np.add.at(merged_core, roots, core_moments)
        core_moments = merged_core
    bevels = _bevels(labels, moments)
    if bevels.size:
        dissolved = np.zeros(len(moments), bool)
        dissolved[bevels] = True
        labels[dissolved[labels]] = 0
        core[dissolved[core]] = 0
        moments[bevels] = 0
        core_moments[bevels] = 0
        planes, _ = planes_from_moments(moments)
        unlabelled = _absorb_kernel(points, distance, sigma, valid, labels, planes, moments, distance_sigmas, depth_jump, _ABSORB_SWEEPS)
    return Segmentation.from_moments(labels, moments, unlabelled, _interior_moments(points, core, core_moments))


def refine_upsampled(
    points: ArrayLike,
    coarse: Segmentation,
    factor: int,
    *,
    range_sigma: ArrayLike | float,
    distance_sigmas: float = _DISTANCE_SIGMAS,
    depth_jump: float = _DEPTH_JUMP,
) -> Segmentation:
    """Carry a segmentation of the grid decimated by ``factor`` (``points[::factor, ::factor]``) to full resolution.

    Each pixel takes its block's label, pixels off their segment's plane by
    more than ``distance_sigmas`` noise sigmas are released, outline pixels
    move to the neighbouring segment whose plane is nearest, and free pixels
    are absorbed ring by ring, as in `grow_regions`; planes are refitted to
    the full-resolution interiors. Growing on a 2x decimated 640x480 frame
    finds the same planes (a 614-pixel segment still has 150 pixels there)
    in about a quarter of the time.

    Parameters
    ----------
    points : (H, W, 3) float array
        Full-resolution sensor-frame points, NaN where invalid.
    coarse : Segmentation
        Of ``points[::factor, ::factor]``.
    factor : int
        Decimation factor, >= 1.
    range_sigma, distance_sigmas, depth_jump
        As for `grow_regions`.

    Returns
    -------
    Segmentation
    """
    points = check_point_grid(points)
    height, width = points.shape[:2]
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise ValueError(f"factor must be an integer >= 1, got {factor!r}")
    expected = (-(-height // factor), -(-width // factor))
    if coarse.labels.shape != expected:
        raise ValueError(f"coarse labels {coarse.labels.shape} do not match ({height}, {width}) decimated by {factor}: {expected}")
    distance, valid = ranges(points)
    sigma = check_range_sigma(np.where(valid, distance, np.nan), range_sigma)
    return _refine_upsampled(points, distance, valid, sigma, coarse, int(factor), float(distance_sigmas), float(depth_jump))


def _refine_upsampled(
    points: np.ndarray,
    distance: np.ndarray,
    valid: np.ndarray,
    sigma: np.ndarray,
    coarse: Segmentation,
    factor: int,
    distance_sigmas: float = _DISTANCE_SIGMAS,
    depth_jump: float = _DEPTH_JUMP,
) -> Segmentation:
    """`refine_upsampled` on checked inputs (as for `_grow`)."""
    planes = np.ascontiguousarray(coarse.planes, dtype=np.float64)
    labels, moments = _upsampled_labels(points, valid, sigma, coarse.labels, factor, planes, distance_sigmas)
    _refine_boundaries(points, distance, sigma, labels, planes, moments, depth_jump)
    core, core_moments = labels.copy(), moments.copy()
    planes, _ = planes_from_moments(moments)
    unlabelled = _absorb_kernel(points, distance, sigma, valid, labels, planes, moments, distance_sigmas, depth_jump, _ABSORB_SWEEPS + factor)
    return Segmentation.from_moments(labels, moments, unlabelled, _interior_moments(points, core, core_moments))


# --------------------------------------------------------------------------
# Input checks.
# --------------------------------------------------------------------------


def default_min_size(height: int, width: int) -> int:
    """Smallest segment kept by default: 0.2 % of the image, and never fewer than 20 pixels."""
    return max(_MIN_SIZE_FLOOR, round(_MIN_SIZE_FRACTION * height * width))


def _check_inputs(points: Any, normals: Any) -> tuple[np.ndarray, np.ndarray]:
    points, normals = check_point_grid(points, "points"), check_point_grid(normals, "normals")
    if points.shape != normals.shape:
        raise ValueError(f"points {points.shape} and normals {normals.shape} must have the same shape")
    return points, normals

# --------------------------------------------------------------------------
# Seeds, planes and merging.
# --------------------------------------------------------------------------


def _seed_order(normals: np.ndarray, growable: np.ndarray, min_coherence: float) -> np.ndarray:
    """Flat indices of the pixels that may seed a region, smoothest first.

    Smoothness is the length of the mean unit normal over 5x5 (1 on a
    plane). Pixels below ``min_coherence`` (on a crease, which smoothing
    rounds into a bevel, or at an edge) never seed: a region started there
    would be a sliver between two faces. They can still join a region.
    """
    filled = _zero_where_not(normals, growable)
    total = cv2.boxFilter(filled, -1, (5, 5), normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(growable.astype(np.float32), -1, (5, 5), normalize=False, borderType=cv2.BORDER_CONSTANT)
    return _seeds_by_coherence(total, count, growable, min_coherence)


def _merge_coplanar(labels: np.ndarray, moments: np.ndarray, cos_max_angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge neighbouring segments that one plane fits as well as their own two (union-find, best pairs first).

    Returns the label each label merges into, and the merged moments.

    The test is on the measured residuals, not the sensor model: merging may
    raise the residual variance by at most ``_MERGE_VARIANCE_GAIN`` over the
    two segments' pooled variance. A wall split by a crack passes; a door
    panel set back from its wall, parallel but a few noise sigmas behind,
    does not.
    """
    pairs = _neighbour_pairs(labels)
    if len(pairs) == 0:
        return np.arange(len(moments), dtype=np.int32), moments
    planes, rms = planes_from_moments(moments)
    variance = np.nan_to_num(rms) ** 2
    cosine = np.abs(np.einsum("kj,kj->k", planes[pairs[:, 0], :3], planes[pairs[:, 1], :3]))
    # Best pairs first (ties by label), as far as they are within the angle.
    order = np.lexsort((pairs[:, 1], pairs[:, 0], -cosine))
    order = order[np.nan_to_num(cosine[order]) >= cos_max_angle]
    return _merge_kernel(np.ascontiguousarray(pairs[order]), moments, variance, _MERGE_VARIANCE_GAIN)


def _bevels(labels: np.ndarray, moments: np.ndarray) -> np.ndarray:
    """Labels of slivers that are the rounded crease between two other segments.

    Smoothing rounds a crease into a narrow band whose normals turn from one
    face's to the other's; growing can make that band a segment of its own.
    Such a segment is thin (under ``_BEVEL_WIDTH`` pixels across, from the
    second moments of its pixel coordinates) and its plane lies between two
    of its neighbours': the angles from each neighbour to it add up to the
    angle between the neighbours (within ``_BEVEL_SLACK`` degrees), and
    neither is small. A thin face that is not between two others (a box side
    seen edge-on, a strip cut off by the image border) stays.
    """
    pixel = _pixel_moments(labels, len(moments))
    count = pixel[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_r, mean_c = pixel[:, 1] / count, pixel[:, 2] / count
        rr = pixel[:, 3] / count - mean_r**2
        rc = pixel[:, 4] / count - mean_r * mean_c
        cc = pixel[:, 5] / count - mean_c**2
    # Smaller eigenvalue of the 2x2 pixel covariance; a band of width w has variance w^2 / 12 across.
    minor = (rr + cc) / 2 - np.sqrt(((rr - cc) / 2) ** 2 + rc**2)
    thin = np.flatnonzero((count > 0) & (np.sqrt(12 * np.maximum(minor, 0)) < _BEVEL_WIDTH))
    thin = thin[thin > 0]
    if thin.size == 0:
        return thin
    pairs = _neighbour_pairs(labels)
    planes, _ = planes_from_moments(moments)
    normals = planes[:, :3]
    bevels = []
    for sliver in thin:
        around = np.concatenate([pairs[pairs[:, 0] == sliver, 1], pairs[pairs[:, 1] == sliver, 0]])
        around = around[np.isfinite(normals[around]).all(axis=1)]
        if len(around) < 2 or not np.isfinite(normals[sliver]).all():
            continue
        to_sliver = np.degrees(np.arccos(np.clip(np.abs(normals[around] @ normals[sliver]), 0.0, 1.0)))
        between = np.degrees(np.arccos(np.clip(np.abs(normals[around] @ normals[around].T), 0.0, 1.0)))
        # Pairs (a, b) of neighbours with the sliver's plane between theirs, neither close to it.
        sums = to_sliver[:, None] + to_sliver[None, :]
        apart = (to_sliver[:, None] > _BEVEL_SLACK) & (to_sliver[None, :] > _BEVEL_SLACK)
        if (apart & (sums <= between + _BEVEL_SLACK) & ~np.eye(len(around), dtype=bool)).any():
            bevels.append(sliver)
    return np.asarray(bevels, dtype=np.int64)


def _interior_moments(points: np.ndarray, labels: np.ndarray, moments: np.ndarray) -> np.ndarray:
    """Moments of each segment's interior (2 pixels in from its outline; the image border does not count).

    The outline is where a segment meets another at a crease, and smoothing
    rounds creases: fitting the plane to the interior keeps that bevel out of
    it. Segments with too small an interior keep all their points.
    """
    as_float = labels.astype(np.float32)  # exact for any realistic segment count (< 2**24)
    kernel = np.ones((2 * _INTERIOR_MARGIN + 1,) * 2, np.uint8)
    low = cv2.erode(as_float, kernel, borderType=cv2.BORDER_REPLICATE)
    high = cv2.dilate(as_float, kernel, borderType=cv2.BORDER_REPLICATE)
    # Interior pixels: the label is both the minimum and the maximum of the window.
    fit = _masked_moments(points, labels, low == high, len(moments))
    # Segments with too small an interior are fitted whole.
    whole = fit[:, 0] < np.maximum(_MIN_INTERIOR, _MIN_INTERIOR_FRACTION * moments[:, 0])
    fit[whole] = moments[whole]
    # One trimming pass: points more than _TRIM_RMS residual RMS off the plane (a rounded crease,
    # a stray pixel) leave the fit.
    planes, rms = planes_from_moments(fit)
    limits = _TRIM_RMS * np.nan_to_num(rms, nan=np.inf)
    refit = _trimmed_kernel(points, labels, low, high, whole, planes, limits, len(moments))
    keep = refit[:, 0] >= np.maximum(3, 0.5 * fit[:, 0])
    fit[keep] = refit[keep]
    return fit


def _neighbour_pairs(labels: np.ndarray) -> np.ndarray:
    """Distinct (a, b), a < b, of segments within two pixels of each other along a row or column."""
    codes = _neighbour_codes(labels, int(labels.max(initial=0)) + 1)
    count = int(labels.max(initial=0)) + 1
    codes = np.unique(codes)
    return np.stack([codes // count, codes % count], axis=1).astype(np.int64)


@numba.njit(**_JIT)
def _merge_kernel(pairs, moments, variance, gain):  # pragma: no cover - compiled
    """Union-find over ``pairs`` in their order: merge when one plane fits both within ``gain`` of their pooled variance.

    Returns the root label of every label and the merged moments.
    """
    count = moments.shape[0]
    parent = np.arange(count)
    merged = moments.copy()
    variance = variance.copy()
    normal = np.empty(3)
    for k in range(pairs.shape[0]):
        ra = pairs[k, 0]
        while parent[ra] != ra:
            parent[ra] = parent[parent[ra]]
            ra = parent[ra]
        rb = pairs[k, 1]
        while parent[rb] != rb:
            parent[rb] = parent[parent[rb]]
            rb = parent[rb]
        if ra == rb:
            continue
        union = merged[ra] + merged[rb]
        union_variance, _ = plane_eigen(union, normal)
        if union_variance < 0.0:
            continue  # no plane through the union
        pooled = (variance[ra] * merged[ra, 0] + variance[rb] * merged[rb, 0]) / union[0]
        if union_variance <= gain * pooled:
            parent[rb] = ra
            merged[ra] = union
            merged[rb] = 0.0
            variance[ra] = union_variance
    roots = np.empty(count, np.int32)
    for index in range(count):
        root = index
        while parent[root] != root:
            root = parent[root]
        roots[index] = root
    return roots, merged


@numba.njit(**_JIT)
def _neighbour_codes(labels, count):  # pragma: no cover - compiled
    """``a * count + b`` for every pixel pair (a < b, both labelled) one or two apart along a row or column."""
    height, width = labels.shape
    codes = np.empty(4 * height * width, np.int64)
    found = 0
    for i in range(height):
        for j in range(width):
            a = labels[i, j]
            if a <= 0:
                continue
            for di, dj in ((0, 1), (0, 2), (1, 0), (2, 0)):
                qi, qj = i + di, j + dj
                if qi >= height or qj >= width:
                    continue
                b = labels[qi, qj]
                if b <= 0 or b == a:
                    continue
                codes[found] = min(a, b) * count + max(a, b)
                found += 1
    return codes[:found]


# --------------------------------------------------------------------------
# Kernels.
# --------------------------------------------------------------------------


@numba.njit(**_JIT)
def _with_normal(valid, normals):  # pragma: no cover - compiled
    """Valid pixels whose normal is known."""
    height, width = valid.shape
    usable = np.zeros((height, width), np.bool_)
    for i in range(height):
        for j in range(width):
            usable[i, j] = valid[i, j] and normals[i, j, 0] == normals[i, j, 0] and normals[i, j, 2] == normals[i, j, 2]
    return usable


@numba.njit(**_JIT)
def _zero_where_not(values, mask):  # pragma: no cover - compiled
    """Copy of ``values`` (H, W, C) with 0 where ``mask`` is False."""
    out = np.zeros(values.shape, np.float32)
    height, width = mask.shape
    for i in range(height):
        for j in range(width):
            if mask[i, j]:
                for k in range(values.shape[2]):
                    out[i, j, k] = values[i, j, k]
    return out


@numba.njit(**_JIT)
def _seeds_by_coherence(total, count, growable, min_coherence):  # pragma: no cover - compiled
    """Flat indices of pixels with coherence >= ``min_coherence``, most coherent first (counting sort, 65536 bins)."""
    height, width = growable.shape
    bins = 65536
    # Only the buckets of coherences >= min_coherence are ever filled: the histogram stops there.
    used = min(int((1.0 - min(max(min_coherence, 0.0), 1.0)) * (bins - 1)), bins - 1) + 1
    key = np.full(height * width, -1, np.int64)
    histogram = np.zeros(used + 1, np.int64)
    for i in range(height):
        for j in range(width):
            if not growable[i, j] or count[i, j] <= 0:
                continue
            coherence = math.sqrt(total[i, j, 0] ** 2 + total[i, j, 1] ** 2 + total[i, j, 2] ** 2) / count[i, j]
            if coherence < min_coherence:
                continue
            bucket = min(int((1.0 - min(coherence, 1.0)) * (bins - 1)), used - 1)
            key[i * width + j] = bucket
            histogram[bucket + 1] += 1
    for b in range(used):
        histogram[b + 1] += histogram[b]
    order = np.empty(histogram[used], np.int64)
    for index in range(height * width):
        bucket = key[index]
        if bucket >= 0:
            order[histogram[bucket]] = index
            histogram[bucket] += 1
    return order


@numba.njit(**_JIT, inline="always")
def _add_moments(moments, region, x, y, z, weight=1.0):  # pragma: no cover - compiled
    """`add_point` on one region's row of ``moments``."""
    add_point(moments[region], x, y, z, weight)


@numba.njit(**_JIT)
def _fit(moments, region, plane, noise, normal):  # pragma: no cover - compiled
    """Refit ``plane`` (nx, ny, nz, d) from the region's moments.

    The fitted normal replaces the current one only once the region spreads
    over more than ``_SUPPORT_SIGMAS`` noise sigmas in both in-plane
    directions; before that, a fit through a small noisy patch is worse than
    the seed pixel's normal (estimated over a whole window), so only the
    offset is moved to the region's centroid.
    """
    smallest, middle = plane_eigen(moments[region], normal)
    if smallest >= 0.0 and middle > (_SUPPORT_SIGMAS * noise) ** 2:
        for k in range(3):
            plane[k] = normal[k]
    n = moments[region, 0]
    d = -(plane[0] * moments[region, 1] + plane[1] * moments[region, 2] + plane[2] * moments[region, 3]) / n
    if d < 0.0:
        for k in range(3):
            plane[k] = -plane[k]
        d = -d
    plane[3] = d


@numba.njit(**_JIT)
def _grow_kernel(points, normals, distance, sigma, growable, order, distance_sigmas, cos_angle, depth_jump, min_size, first_fit):  # pragma: no cover - compiled
    height, width = growable.shape
    labels = np.zeros((height, width), np.int32)
    # Pixels of dissolved regions: free to join, never a seed again.
    spent = np.zeros((height, width), np.bool_)
    # Rows and columns in separate queues: no integer division per visited pixel.
    queue_i = np.empty(height * width, np.int32)
    queue_j = np.empty(height * width, np.int32)
    moments = np.zeros((64, 10))
    plane = np.empty(4)
    normal = np.empty(3)
    region = 0
    for seed in order:
        si, sj = seed // width, seed % width
        if labels[si, sj] != 0 or spent[si, sj]:
            continue
        region += 1
        if region >= moments.shape[0]:
            grown = np.zeros((2 * moments.shape[0], 10))
            grown[: moments.shape[0]] = moments
            moments = grown
        for k in range(3):
            plane[k] = normals[si, sj, k]
        plane[3] = -(plane[0] * points[si, sj, 0] + plane[1] * points[si, sj, 1] + plane[2] * points[si, sj, 2])
        n0, n1, n2, n3 = plane[0], plane[1], plane[2], plane[3]
        seed_noise = sigma[si, sj]
        labels[si, sj] = region
        # The region's moments live in registers while it grows; memory sees them at each refit.
        grown = _run_add(_EMPTY_RUN, np.float64(points[si, sj, 0]), np.float64(points[si, sj, 1]), np.float64(points[si, sj, 2]))
        queue_i[0] = si
        queue_j[0] = sj
        head, tail = 0, 1
        next_fit = first_fit
        while head < tail:
            ci = queue_i[head]
            cj = queue_j[head]
            head += 1
            range_c = distance[ci, cj]
            for direction in range(4):
                qi = ci + _FOUR[direction, 0]
                qj = cj + _FOUR[direction, 1]
                if qi < 0 or qj < 0 or qi >= height or qj >= width:
                    continue
                if labels[qi, qj] != 0 or not growable[qi, qj]:
                    continue
                # Join test: no depth jump, on the plane within the noise, normal agrees (plane in registers).
                range_q = distance[qi, qj]
                if abs(range_q - range_c) > depth_jump * min(range_q, range_c):
                    continue
                x = points[qi, qj, 0]
                y = points[qi, qj, 1]
                z = points[qi, qj, 2]
                if abs(n0 * x + n1 * y + n2 * z + n3) > distance_sigmas * sigma[qi, qj]:
                    continue
                if not (n0 * normals[qi, qj, 0] + n1 * normals[qi, qj, 1] + n2 * normals[qi, qj, 2] >= cos_angle):
                    continue
                labels[qi, qj] = region
                grown = _run_add(grown, np.float64(x), np.float64(y), np.float64(z))
                queue_i[tail] = qi
                queue_j[tail] = qj
                tail += 1
                if tail >= next_fit:
                    for k in range(10):
                        moments[region, k] = grown[k]
                    _fit(moments, region, plane, seed_noise, normal)
                    n0, n1, n2, n3 = plane[0], plane[1], plane[2], plane[3]
                    next_fit = tail * _REFIT_GROWTH
        for k in range(10):
            moments[region, k] = grown[k]
        if tail < min_size:
            # Only the seed is spent: a failed start (a noisy seed normal) must not
            # take its neighbours' chance to seed a region of their own.
            for k in range(tail):
                labels[queue_i[k], queue_j[k]] = 0
                spent[queue_i[k], queue_j[k]] = True
            moments[region, :] = 0.0
            region -= 1
    return labels, moments[: region + 1].copy()


@numba.njit(**_JIT)
def _refine_boundaries(points, distance, sigma, labels, planes, moments, depth_jump):  # pragma: no cover - compiled
    """Move each boundary pixel to the neighbouring segment whose plane it fits best (in place).

    Growing is greedy: the region that reaches a pixel first keeps it, so
    near a crease or a small surface some pixels end up on the wrong side.
    A pixel with a differently labelled 8-neighbour is given to whichever of
    the segments around it (its own included) has the plane nearest to it,
    in noise sigmas, unless that neighbour is across a depth jump.
    """
    height, width = labels.shape
    original = labels.copy()
    for i in range(height):
        for j in range(width):
            own = original[i, j]
            if own <= 0:
                continue
            # Most pixels are inside their segment, all eight neighbours alike: nothing to move.
            if 0 < i < height - 1 and 0 < j < width - 1:
                if ((original[i - 1, j - 1] == own) & (original[i - 1, j] == own) & (original[i - 1, j + 1] == own)
                        & (original[i, j - 1] == own) & (original[i, j + 1] == own)
                        & (original[i + 1, j - 1] == own) & (original[i + 1, j] == own) & (original[i + 1, j + 1] == own)):
                    continue
            x = points[i, j, 0]
            y = points[i, j, 1]
            z = points[i, j, 2]
            best = own
            best_distance = abs(planes[own, 0] * x + planes[own, 1] * y + planes[own, 2] * z + planes[own, 3])
            if not (best_distance == best_distance):
                continue
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    qi = i + di
                    qj = j + dj
                    if qi < 0 or qj < 0 or qi >= height or qj >= width:
                        continue
                    other = original[qi, qj]
                    if other <= 0 or other == best or other == own:
                        continue
                    if abs(distance[qi, qj] - distance[i, j]) > depth_jump * min(distance[qi, qj], distance[i, j]):
                        continue
                    gap = abs(planes[other, 0] * x + planes[other, 1] * y + planes[other, 2] * z + planes[other, 3])
                    if gap < best_distance:
                        best = other
                        best_distance = gap
            if best != own and best_distance <= 3.0 * sigma[i, j]:
                labels[i, j] = best
                _add_moments(moments, own, -x, -y, -z, -1.0)
                _add_moments(moments, best, x, y, z, 1.0)


@numba.njit(**_JIT, inline="always")
def _run_add(run, x, y, z):  # pragma: no cover - compiled
    """`add_point` on a run of moments held as a tuple (in registers, not memory)."""
    return (run[0] + 1.0, run[1] + x, run[2] + y, run[3] + z, run[4] + x * x, run[5] + x * y,
            run[6] + x * z, run[7] + y * y, run[8] + y * z, run[9] + z * z)


@numba.njit(**_JIT, inline="always")
def _run_flush(moments, label, run):  # pragma: no cover - compiled
    """Add a run's moments to ``label``'s row (nothing for label <= 0)."""
    if label > 0:
        for k in range(10):
            moments[label, k] += run[k]


_EMPTY_RUN = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@numba.njit(**_JIT)
def _upsampled_labels(points, valid, sigma, coarse_labels, factor, planes, distance_sigmas):  # pragma: no cover - compiled
    """Every valid pixel takes its block's coarse label, unless it is off that plane by more than ``distance_sigmas`` sigmas.

    Returns the labels (H, W) int32 and their point moments (one row per
    plane; row 0 empty). Moments are summed along runs of one label before
    they go to memory: consecutive updates of one row would wait on each
    other.
    """
    height, width = valid.shape
    labels = np.zeros((height, width), np.int32)
    moments = np.zeros((planes.shape[0], 10))
    # Coarse column of every column (a division per pixel would cost more than the rest).
    coarse_column = np.arange(width) // factor
    current = 0
    run = _EMPTY_RUN
    for i in range(height):
        coarse_row = coarse_labels[i // factor]
        for j in range(width):
            label = coarse_row[coarse_column[j]]
            if label <= 0 or not valid[i, j]:
                continue
            x = np.float64(points[i, j, 0])
            y = np.float64(points[i, j, 1])
            z = np.float64(points[i, j, 2])
            offset = abs(planes[label, 0] * x + planes[label, 1] * y + planes[label, 2] * z + planes[label, 3])
            if offset > distance_sigmas * sigma[i, j]:
                continue
            labels[i, j] = label
            if label != current:
                _run_flush(moments, current, run)
                current = label
                run = _EMPTY_RUN
            run = _run_add(run, x, y, z)
    _run_flush(moments, current, run)
    return labels, moments


@numba.njit(**_JIT)
def _masked_moments(points, labels, mask, n_labels):  # pragma: no cover - compiled
    """Point moments (n_labels, 10) of each label's pixels where ``mask`` holds (row 0: unlabelled, left empty)."""
    height, width = labels.shape
    moments = np.zeros((n_labels, 10))
    current = 0
    run = _EMPTY_RUN
    for i in range(height):
        for j in range(width):
            label = labels[i, j]
            if label > 0 and mask[i, j]:
                if label != current:
                    _run_flush(moments, current, run)
                    current = label
                    run = _EMPTY_RUN
                run = _run_add(run, np.float64(points[i, j, 0]), np.float64(points[i, j, 1]), np.float64(points[i, j, 2]))
    _run_flush(moments, current, run)
    return moments


@numba.njit(**_JIT)
def _trimmed_kernel(points, labels, low, high, whole, planes, limits, n_labels):  # pragma: no cover - compiled
    """Moments of the fitted pixels (interior, or all of a ``whole`` label) within ``limits`` of their plane."""
    height, width = labels.shape
    moments = np.zeros((n_labels, 10))
    current = 0
    run = _EMPTY_RUN
    for i in range(height):
        for j in range(width):
            label = labels[i, j]
            if label <= 0 or not (whole[label] or low[i, j] == high[i, j]):
                continue
            x = np.float64(points[i, j, 0])
            y = np.float64(points[i, j, 1])
            z = np.float64(points[i, j, 2])
            offset = abs(planes[label, 0] * x + planes[label, 1] * y + planes[label, 2] * z + planes[label, 3])
            if offset <= limits[label]:
                if label != current:
                    _run_flush(moments, current, run)
                    current = label
                    run = _EMPTY_RUN
                run = _run_add(run, x, y, z)
    _run_flush(moments, current, run)
    return moments


@numba.njit(**_JIT)
def _pixel_moments(labels, n_labels):  # pragma: no cover - compiled
    """Per label: pixel count and sums of row, column, row^2, row*column, column^2."""
    height, width = labels.shape
    moments = np.zeros((n_labels, 6))
    for i in range(height):
        for j in range(width):
            label = labels[i, j]
            if label > 0:
                moments[label, 0] += 1.0
                moments[label, 1] += i
                moments[label, 2] += j
                moments[label, 3] += i * i
                moments[label, 4] += i * j
                moments[label, 5] += j * j
    return moments


def _label_moments(points: np.ndarray, labels: np.ndarray, n_labels: int) -> np.ndarray:
    """Point moments (n_labels, 10) of every label (row 0: unlabelled, left empty)."""
    return _masked_moments(points, labels, labels > 0, n_labels)


@numba.njit(**_JIT)
def _absorb_kernel(points, distance, sigma, valid, labels, planes, moments, distance_sigmas, depth_jump, sweeps):  # pragma: no cover - compiled
    """Give free pixels to the neighbouring segment whose plane is nearest, ring by ring (in place).

    Outline pixels often have spoiled normals (their window straddled the
    crease or the jump), so growing left them out; by distance alone, each
    joins the adjacent segment whose plane it is nearest to, if within
    ``distance_sigmas`` noise sigmas and not across a depth jump. Each sweep
    decides on the labels of the previous one, so the order of the scan does
    not matter; ``sweeps`` rings are added at most. Returns the number of
    valid pixels left free.
    """
    height, width = labels.shape
    # The free valid pixels, in scan order; each sweep decides on the labels of the previous one, so its
    # choices are applied after it.
    free_i = np.empty(height * width, np.int32)
    free_j = np.empty(height * width, np.int32)
    n_free = 0
    for i in range(height):
        for j in range(width):
            if labels[i, j] == 0 and valid[i, j]:
                free_i[n_free] = i
                free_j[n_free] = j
                n_free += 1
    chosen = np.empty(n_free, np.int32)
    for _ in range(sweeps):
        changed = 0
        for k in range(n_free):
            i = free_i[k]
            j = free_j[k]
            x = points[i, j, 0]
            y = points[i, j, 1]
            z = points[i, j, 2]
            best = 0
            best_gap = distance_sigmas * sigma[i, j]
            for direction in range(4):
                qi = i + _FOUR[direction, 0]
                qj = j + _FOUR[direction, 1]
                if qi < 0 or qj < 0 or qi >= height or qj >= width:
                    continue
                other = labels[qi, qj]
                if other <= 0:
                    continue
                if abs(distance[qi, qj] - distance[i, j]) > depth_jump * min(distance[qi, qj], distance[i, j]):
                    continue
                gap = abs(planes[other, 0] * x + planes[other, 1] * y + planes[other, 2] * z + planes[other, 3])
                if gap <= best_gap:
                    best = other
                    best_gap = gap
            chosen[k] = best
            changed += best > 0
        if changed == 0:
            break
        remaining = 0
        for k in range(n_free):
            i = free_i[k]
            j = free_j[k]
            best = chosen[k]
            if best > 0:
                labels[i, j] = best
                _add_moments(moments, best, points[i, j, 0], points[i, j, 1], points[i, j, 2], 1.0)
            else:
                free_i[remaining] = i
                free_j[remaining] = j
                remaining += 1
        n_free = remaining
    return n_free
