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
``min_size`` pixels are dissolved; their pixels remain free to join another
region, but none of them seeds one.

Then (1) every region absorbs the free pixels around it that fit its final
plane (the pixels at its outline whose normals were spoiled by the depth
edge), and (2) neighbouring regions whose points fit one common plane within
the noise are merged (an edge or a noise line that split one wall).
Coplanar regions that do not touch stay separate segments. Finally each
segment's plane is fitted to its interior along the sensor's rays, where
range noise lies (`rangesurf._planefit.ray_planes_kernel`): the running
total least-squares fit that guides growing leans toward the sensor on
noisy frames (3-4 degrees on raw SR-3000 segments).

The clean-up after growing works on per-segment sums wherever it can: one
pass over the labels gives the neighbouring segments and every segment's
shape, so merging and the bevel test only add up rows of sums; the interior
fit takes the few outline and outlier pixels off a segment's moments instead
of summing the rest again.

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

import numba
import numpy as np
from numpy.typing import ArrayLike

from rangesurf._checks import check_point_grid, check_range_sigma
from rangesurf._grid import point_ranges, ranges
from rangesurf._planefit import add_point, plane_eigen, plane_rms, planes_kernel, ray_planes_kernel, ray_weight
from rangesurf.segment._segmentation import Segmentation, _from_moments_kernel, _relabel_kernel

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
# Carried to full resolution, a coarse pixel keeps its label only if its normal is within this angle of the
# segment's plane: a coarse segment reaches past a crease by a block, and without the test those pixels
# tilted a 1,400-pixel wall by 5 degrees (176x144 raw SR-3000 frames pooled 2x: mean normal error 1.16 ->
# 0.95 degrees; at 20 degrees, which noisy coarse normals at outlines fail, 9 fewer of 110 planes found).
_REFINE_MAX_ANGLE = 45.0
# Frames of at least this many pixels fit their final planes on every second row.
_LARGE_FRAME = 100_000
# Rings of outline pixels the absorption step may add to a segment.
_ABSORB_SWEEPS = 4
# Passes of the boundary refinement, each moving a boundary by at most a pixel (the later ones over the pixels
# around the last moves only). Pixels whose segment is not the majority of their true surface, one pass against
# eight (simulated seed-5 frames, every 5th, diffusion-denoised): SR-3000 arena 3.37 -> 1.06 %, corridor 1.70 ->
# 1.64 %; Kinect arena 0.76 -> 0.22 %, corridor 0.98 -> 0.34 %. benchmarks/segmentation.py's frames: the same or
# more planes found on every input, diffusion-denoised SR-3000 normals 2.06 -> 1.86 degrees off. The cost: on raw
# white noise (two planes 12-18 degrees apart, sigma 1 cm at 3 m) the boundary wanders further into the ambiguous
# band where both planes fit within the noise (pixels more than 3 columns past the crease: 68 -> 208 of 576 rows
# at 18 degrees); diffused first, both leave none. Letting only pixels over 2 sigmas off their own plane move
# after the first pass kept the raw case at 69 but the arena at 1.91 %.
_BOUNDARY_PASSES = 8
# A segment thinner than this (pixels) whose plane lies between two neighbours' is a rounded crease.
_BEVEL_WIDTH = 6.0
_BEVEL_SLACK = 5.0
# Defaults of the join test (grow_regions documents them).
_DISTANCE_SIGMAS = 3.0
_MAX_ANGLE = 20.0
_DEPTH_JUMP = 0.05
# Range noise moves a point along its ray, so off a plane by sigma |cos(incidence)|: a wall seen at grazing
# incidence lets its points stray far less along its normal than their range noise. The boundary steps measure
# a pixel's distance to each neighbouring plane in those units, the cosine floored here (about 72.5 degrees, so
# that a plane seen nearly edge-on does not refuse its own pixels; of floors 0.1-0.5 on the benchmark's frames,
# 0.3 found the most planes). Metric distances gave a wall seen edge-on the first column or two of a door jamb
# it meets (benchmarks/segmentation.py, 176x144 SR-3000 raw frames: correct detections 105 -> 109 of 110;
# 103 -> 108 on the frames of seed 33).
_MIN_INCIDENCE_COS = 0.3
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

    distance, valid, _ = point_ranges(points)
    sigma = check_range_sigma(distance, range_sigma)
    return _grow(points, normals, sigma, distance, valid, float(distance_sigmas), float(max_angle), float(depth_jump), int(min_size), merge)


def _grow(
    points: np.ndarray,
    normals: np.ndarray,
    sigma: np.ndarray,
    distance: np.ndarray,
    valid: np.ndarray,
    distance_sigmas: float = _DISTANCE_SIGMAS,
    max_angle: float = _MAX_ANGLE,
    depth_jump: float = _DEPTH_JUMP,
    min_size: int | None = None,
    merge: bool = True,
) -> Segmentation:
    """`grow_regions` on checked inputs: C-contiguous float32 grids, ``sigma`` (H, W) float64, and the points' ranges and valid mask (`rangesurf._grid.point_ranges`).

    ``sigma`` is read only where a point is valid. All the steps run in one
    compiled call: at 176x144 a dozen separate calls cost as much in
    dispatch as the steps themselves.
    """
    if min_size is None:
        min_size = default_min_size(*sigma.shape)
    labels, planes, residuals, sizes = _grow_steps(
        points, normals, sigma, distance, valid, distance_sigmas, math.cos(math.radians(max_angle)),
        math.cos(math.radians(max_angle / 2)), depth_jump, min_size, merge,
    )
    return Segmentation(labels=labels, planes=planes, residuals=residuals, sizes=sizes)


@numba.njit(**_JIT)
def _grow_steps(points, normals, sigma, distance, valid, distance_sigmas, cos_max_angle, min_coherence, depth_jump, min_size, merge):  # pragma: no cover - compiled
    """The steps of `_grow`: seeds, growing, boundaries, absorption, merging, bevels, interior fits; the parts of a `Segmentation`."""
    state, order = _growing_grid(valid, normals, min_coherence)
    labels, moments = _grow_kernel(
        points, normals, distance, sigma, state, order, distance_sigmas, cos_max_angle, depth_jump, min_size, float(_FIRST_FIT)
    )
    planes, _ = planes_kernel(moments)
    free_rows, free_cols = _refine_boundaries(points, distance, sigma, valid, labels, planes, moments, depth_jump)
    planes, _ = planes_kernel(moments)
    free_rows, free_cols = _absorb_kernel(
        points, distance, sigma, labels, planes, moments, free_rows, free_cols, distance_sigmas, depth_jump, _ABSORB_SWEEPS
    )
    # Merging and the bevel test need only per-segment sums: one pass over the labels gives them for the
    # segments as grown, and a merge just adds up the rows of the segments it joins.
    pairs, shapes = _adjacency(labels, moments.shape[0])
    lookup = np.arange(moments.shape[0]).astype(np.int32)
    if merge:
        lookup, moments = _merge_coplanar(pairs, moments, cos_max_angle)
        shapes = _sum_into(shapes, lookup)
        pairs = _merged_pairs(pairs, lookup)
    planes, _ = planes_kernel(moments)
    bevels = _bevel_kernel(pairs, shapes, planes, _BEVEL_WIDTH, _BEVEL_SLACK)
    if bevels.size:
        # A bevel is dissolved: its pixels leave every segment, its sums go.
        dissolved = np.zeros(lookup.size, np.bool_)
        for bevel in bevels:
            dissolved[bevel] = True
            moments[bevel] = 0.0
        for label in range(lookup.size):
            if dissolved[lookup[label]]:
                lookup[label] = 0
    fitted = _interior_planes(points, sigma, labels, lookup, moments)
    if bevels.size:
        # The bevels' pixels are free again, for their neighbours to absorb.
        labels = _relabel_kernel(labels.reshape(labels.size), lookup).reshape(labels.shape)
        lookup = np.arange(moments.shape[0]).astype(np.int32)
        planes, _ = planes_kernel(moments)
        free_rows, free_cols = _free_pixels(labels, valid)
        free_rows, free_cols = _absorb_kernel(
            points, distance, sigma, labels, planes, moments, free_rows, free_cols, distance_sigmas, depth_jump, _ABSORB_SWEEPS
        )
    return _from_moments_kernel(labels, moments, fitted, lookup, free_rows.size)


def refine_upsampled(
    points: ArrayLike,
    coarse: Segmentation,
    factor: int,
    *,
    range_sigma: ArrayLike | float,
    normals: ArrayLike | None = None,
    distance_sigmas: float = _DISTANCE_SIGMAS,
    depth_jump: float = _DEPTH_JUMP,
) -> Segmentation:
    """Carry a segmentation of a grid ``factor`` times coarser (pooled, or ``points[::factor, ::factor]``) to full resolution.

    Each pixel takes its block's label (unless the block's ``normals`` are
    given and its normal is more than 45 degrees off the label's plane),
    pixels off their segment's plane by
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
        Of the coarse grid.
    factor : int
        Decimation factor, >= 1.
    normals : (H', W', 3) array, optional
        The coarse grid's normals (`segment_planes` grows with them).
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
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != (*expected, 3):
            raise ValueError(f"normals {normals.shape} must match the coarse labels, {(*expected, 3)}")
    distance, valid = ranges(points)
    sigma = check_range_sigma(distance, range_sigma)
    return _refine_upsampled(points, distance, valid, sigma, coarse, int(factor), normals, float(distance_sigmas),
                             float(depth_jump))


def _refine_upsampled(
    points: np.ndarray,
    distance: np.ndarray,
    valid: np.ndarray,
    sigma: np.ndarray,
    coarse: Segmentation,
    factor: int,
    normals: np.ndarray | None = None,
    distance_sigmas: float = _DISTANCE_SIGMAS,
    depth_jump: float = _DEPTH_JUMP,
) -> Segmentation:
    """`refine_upsampled` on checked inputs (as for `_grow`)."""
    cos_angle = math.cos(math.radians(_REFINE_MAX_ANGLE))
    if normals is None:
        normals, cos_angle = np.zeros((*coarse.labels.shape, 3), np.float32), -1.0
    labels, planes, residuals, sizes = _refine_steps(
        points, distance, valid, sigma, np.ascontiguousarray(coarse.labels, dtype=np.int32),
        np.ascontiguousarray(coarse.planes, dtype=np.float64), factor, np.ascontiguousarray(normals, dtype=np.float32),
        cos_angle, distance_sigmas, depth_jump,
    )
    return Segmentation(labels=labels, planes=planes, residuals=residuals, sizes=sizes)


@numba.njit(**_JIT)
def _refine_steps(points, distance, valid, sigma, coarse_labels, coarse_planes, factor, normals, cos_angle, distance_sigmas, depth_jump):  # pragma: no cover - compiled
    """The steps of `_refine_upsampled` in one compiled call; the parts of a `Segmentation`.

    A coarse pixel whose normal is off its label's plane by more than
    ``acos(cos_angle)`` leaves its block unlabelled (``cos_angle`` -1: none).
    """
    coarse_labels = _agreeing_labels(coarse_labels, coarse_planes, normals, cos_angle)
    labels, moments = _upsampled_labels(points, valid, sigma, coarse_labels, factor, coarse_planes, distance_sigmas)
    free_rows, free_cols = _refine_boundaries(points, distance, sigma, valid, labels, coarse_planes, moments, depth_jump)
    planes, _ = planes_kernel(moments)
    free_rows, free_cols = _absorb_kernel(
        points, distance, sigma, labels, planes, moments, free_rows, free_cols, distance_sigmas, depth_jump, _ABSORB_SWEEPS + factor
    )
    identity = np.arange(moments.shape[0]).astype(np.int32)
    # A large frame's interior fits take every second row (at 176x144 that raised the mean normal error on raw
    # SR-3000 frames from 0.95 to 1.18 degrees).
    fitted = _interior_planes(points, sigma, labels, identity, moments, 2 if labels.size >= _LARGE_FRAME else 1)
    return _from_moments_kernel(labels, moments, fitted, identity, free_rows.size)


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
# Merging, bevels and interiors (on per-segment sums where possible).
# --------------------------------------------------------------------------


@numba.njit(**_JIT)
def _merge_coplanar(pairs, moments, cos_max_angle):  # pragma: no cover - compiled
    """Merge neighbouring segments that one plane fits as well as their own two (union-find, best pairs first).

    ``pairs`` are the neighbouring segments (`_adjacency`). Returns the label
    each label merges into, and the merged moments.

    The test is on the measured residuals, not the sensor model: merging may
    raise the residual variance by at most ``_MERGE_VARIANCE_GAIN`` over the
    two segments' pooled variance. A wall split by a crack passes; a door
    panel set back from its wall, parallel but a few noise sigmas behind,
    does not.
    """
    if pairs.shape[0] == 0:
        return np.arange(moments.shape[0]).astype(np.int32), moments
    planes, rms = planes_kernel(moments)
    return _merge_kernel(pairs, moments, planes, rms, cos_max_angle, _MERGE_VARIANCE_GAIN)


@numba.njit(**_JIT)
def _interior_planes(points, sigma, labels, lookup, moments, row_step=1):  # pragma: no cover - compiled
    """Plane of each segment's interior (2 pixels in from its outline; the image border does not count), fitted along the rays.

    ``labels`` are mapped through ``lookup`` first; ``moments`` are those of
    each segment's pixels; returns a plane per row of ``moments``. The
    outline is where a segment meets another at a crease, and smoothing
    rounds creases: fitting the plane to the interior keeps that bevel out
    of it. Segments with too small an interior keep all their points. The
    fit is `ray_planes_kernel`'s, weighted by each pixel's range noise
    ``sigma``: a total least-squares fit of raw SR-3000 segments is tilted
    3-4 degrees toward the rays. One trimming pass then leaves out the
    points more than ``_TRIM_RMS`` residual RMS off the plane (a rounded
    crease, a stray pixel).

    With ``row_step`` > 1 the fits take every ``row_step``-th row only (the
    interior is still found at full resolution): a large frame's segments
    have pixels to spare (simulated 640x480 frames, every 2nd row: the same
    detections, mean normal error 0.14 -> 0.17 degrees on raw arena frames,
    unchanged on denoised ones; `refine_upsampled` 5.3 -> 4.3 ms).
    """
    labels, interior = _interior_kernel(labels, lookup)
    outline, weighted, outline_weighted, sampled = _outline_and_weighted_moments(
        points, sigma, labels, interior, moments.shape[0], row_step)
    # The interior's point moments: all of a segment's less its outline's; sampled rows, the interior's own.
    fit = moments - outline if row_step == 1 else sampled
    # Segments with too small an interior are fitted whole.
    whole = np.empty(moments.shape[0], np.bool_)
    for label in range(moments.shape[0]):
        whole[label] = fit[label, 0] * row_step < max(float(_MIN_INTERIOR), _MIN_INTERIOR_FRACTION * moments[label, 0])
        if whole[label]:
            fit[label] = moments[label] if row_step == 1 else sampled[label] + outline[label]
            weighted[label] += outline_weighted[label]
    # Where the rays give no plane (too few points, or all on one ray), the total least-squares one.
    fallback, _ = planes_kernel(fit)
    planes = _or_fallback(ray_planes_kernel(weighted), fallback)
    limits = _TRIM_RMS * plane_rms(fit, planes)
    for label in range(moments.shape[0]):
        if not limits[label] == limits[label]:
            limits[label] = math.inf  # no plane at all: nothing to trim
    outliers, off = _outlier_moments(points, sigma, labels, interior, whole, planes, limits, row_step)
    refit = _or_fallback(ray_planes_kernel(weighted - outliers), planes)
    for label in range(moments.shape[0]):
        if fit[label, 0] - off[label] >= max(3.0, 0.5 * fit[label, 0]):
            planes[label] = refit[label]
    return planes


@numba.njit(**_JIT)
def _or_fallback(planes, fallback):  # pragma: no cover - compiled
    """``planes``, with the rows that are NaN taken from ``fallback``."""
    for label in range(planes.shape[0]):
        if not planes[label, 3] == planes[label, 3]:
            planes[label] = fallback[label]
    return planes


@numba.njit(**_JIT)
def _merge_kernel(pairs, moments, planes, rms, cos_max_angle, gain):  # pragma: no cover - compiled
    """Union-find over ``pairs`` within ``cos_max_angle``, most parallel first.

    Two segments merge when one plane fits both within ``gain`` of their
    pooled variance. ``planes`` and ``rms`` are the segments' own fits
    (`planes_from_moments`; a segment without a plane counts as variance 0).
    Returns the root label of every label and the merged moments.
    """
    n_pairs = pairs.shape[0]
    cosine = np.empty(n_pairs)
    for k in range(n_pairs):
        a = pairs[k, 0]
        b = pairs[k, 1]
        cosine[k] = abs(planes[a, 0] * planes[b, 0] + planes[a, 1] * planes[b, 1] + planes[a, 2] * planes[b, 2])
    # NaN (a segment without a plane) fails the angle test too.
    candidates = np.flatnonzero(cosine >= cos_max_angle)
    # A stable sort: equally parallel pairs keep their order by label.
    order = candidates[np.argsort(-cosine[candidates], kind="mergesort")]
    count = moments.shape[0]
    parent = np.arange(count)
    merged = moments.copy()
    variance = np.where(rms == rms, rms, 0.0) ** 2
    normal = np.empty(3)
    for k in order:
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
def _sum_into(rows, lookup):  # pragma: no cover - compiled
    """Rows summed into the row ``lookup`` sends them to (`np.add.at` with ``lookup`` as the index)."""
    summed = np.zeros_like(rows)
    for k in range(rows.shape[0]):
        for column in range(rows.shape[1]):
            summed[lookup[k], column] += rows[k, column]
    return summed


@numba.njit(**_JIT)
def _unique_pairs(codes, count):  # pragma: no cover - compiled
    """Sorted distinct pairs (a, b) of the codes ``a * count + b``."""
    codes = np.unique(codes)
    pairs = np.empty((codes.size, 2), np.int64)
    for k in range(codes.size):
        pairs[k, 0] = codes[k] // count
        pairs[k, 1] = codes[k] % count
    return pairs


@numba.njit(**_JIT)
def _merged_pairs(pairs, lookup):  # pragma: no cover - compiled
    """The neighbouring segments after the merge that sends label k to ``lookup[k]``."""
    count = lookup.size
    codes = np.empty(pairs.shape[0], np.int64)
    found = 0
    for k in range(pairs.shape[0]):
        a = lookup[pairs[k, 0]]
        b = lookup[pairs[k, 1]]
        if a != b:
            codes[found] = min(a, b) * count + max(a, b)
            found += 1
    return _unique_pairs(codes[:found], count)


@numba.njit(**_JIT)
def _adjacency(labels, count):  # pragma: no cover - compiled
    """Neighbouring segments and the shape of every segment, in one pass over the labels.

    Returns (P, 2) int64: the distinct pairs (a, b), a < b, sorted, of
    segments within two pixels of each other along a row or column; and
    (count, 6) float64 per label: pixel count and sums of row, column,
    row^2, row*column, column^2 (row 0: unlabelled, left empty).
    """
    height, width = labels.shape
    shapes = np.zeros((count, 6))
    # A border repeats its pair pixel after pixel: only a change of pair is written.
    codes = np.empty(4 * height * width, np.int64)
    found = 0
    last = -1
    # The last two columns are never alike: their pixels ahead along the row are missing.
    alike = np.zeros(width, np.bool_)
    for i in range(height):
        # Each run of one label along the row adds its pixel coordinates' sums in closed form.
        start = 0
        for j in range(1, width + 1):
            if j < width and labels[i, j] == labels[i, start]:
                continue
            a = labels[i, start]
            if a > 0:
                n = j - start
                columns = (start + j - 1) * n / 2
                squares = _square_sum(j - 1) - _square_sum(start - 1)
                shapes[a, 0] += n
                shapes[a, 1] += i * n
                shapes[a, 2] += columns
                shapes[a, 3] += i * i * n
                shapes[a, 4] += i * columns
                shapes[a, 5] += squares
            start = j
        # Inside a segment (the common case) none of the four pixels ahead holds another segment's label;
        # which of the row's pixels are such is found first, in a loop the compiler vectorises.
        if i + 2 < height:
            # Rows as views, indexed by the column alone (a run-time row offset would keep the loop scalar).
            here, below, further = labels[i], labels[i + 1], labels[i + 2]
            for j in range(width - 2):
                a = here[j]
                alike[j] = (_own_or_none(here[j + 1], a) & _own_or_none(here[j + 2], a) & _own_or_none(below[j], a)
                            & _own_or_none(further[j], a))
        else:
            alike[:] = False
        for j in range(width):
            a = labels[i, j]
            if alike[j] or a <= 0:
                continue
            for di, dj in ((0, 1), (0, 2), (1, 0), (2, 0)):
                qi, qj = i + di, j + dj
                if qi >= height or qj >= width:
                    continue
                b = labels[qi, qj]
                if b <= 0 or b == a:
                    continue
                code = min(a, b) * count + max(a, b)
                if code != last:
                    codes[found] = code
                    found += 1
                    last = code
    return _unique_pairs(codes[:found], count), shapes


@numba.njit(**_JIT, inline="always")
def _square_sum(m):  # pragma: no cover - compiled
    """0^2 + 1^2 + ... + m^2 (0 for m < 1), as a float (exact below 2^53)."""
    return max(m, 0) * (m + 1.0) * (2.0 * m + 1.0) / 6.0


@numba.njit(**_JIT)
def _bevel_kernel(pairs, shapes, planes, max_width, slack):  # pragma: no cover - compiled
    """Labels of slivers that are the rounded crease between two other segments.

    Smoothing rounds a crease into a narrow band whose normals turn from one
    face's to the other's; growing can make that band a segment of its own.
    Such a segment is thin (under ``max_width`` pixels across, from the
    second moments of its pixel coordinates, ``shapes`` of `_adjacency`) and
    its plane lies between two of its neighbours': the angles from each
    neighbour to it add up to the angle between the neighbours (within
    ``slack`` degrees), and neither is small. A thin face that is not
    between two others (a box side seen edge-on, a strip cut off by the
    image border) stays.
    """
    count = shapes.shape[0]
    bevels = np.empty(count, np.int64)
    n_bevels = 0
    around = np.empty(count, np.int64)
    to_sliver = np.empty(count)
    for sliver in range(1, count):
        n = shapes[sliver, 0]
        if not n > 0 or not np.isfinite(planes[sliver, 0]):
            continue
        mean_r = shapes[sliver, 1] / n
        mean_c = shapes[sliver, 2] / n
        rr = shapes[sliver, 3] / n - mean_r**2
        rc = shapes[sliver, 4] / n - mean_r * mean_c
        cc = shapes[sliver, 5] / n - mean_c**2
        # Smaller eigenvalue of the 2x2 pixel covariance; a band of width w has variance w^2 / 12 across.
        minor = (rr + cc) / 2 - math.sqrt(((rr - cc) / 2) ** 2 + rc**2)
        if not math.sqrt(12 * max(minor, 0.0)) < max_width:
            continue
        n_around = 0
        for k in range(pairs.shape[0]):
            other = pairs[k, 1] if pairs[k, 0] == sliver else (pairs[k, 0] if pairs[k, 1] == sliver else -1)
            if other >= 0 and np.isfinite(planes[other, 0]):
                around[n_around] = other
                n_around += 1
        for k in range(n_around):
            to_sliver[k] = _angle_between(planes, around[k], sliver)
        # A pair of neighbours with the sliver's plane between theirs, neither close to it.
        between = False
        for a in range(n_around):
            for b in range(n_around):
                if a != b and to_sliver[a] > slack and to_sliver[b] > slack:
                    between |= to_sliver[a] + to_sliver[b] <= _angle_between(planes, around[a], around[b]) + slack
        if between:
            bevels[n_bevels] = sliver
            n_bevels += 1
    return bevels[:n_bevels]


@numba.njit(**_JIT, inline="always")
def _angle_between(planes, a, b):  # pragma: no cover - compiled
    """Angle (degrees, 0-90) between the planes ``a`` and ``b``."""
    cosine = abs(planes[a, 0] * planes[b, 0] + planes[a, 1] * planes[b, 1] + planes[a, 2] * planes[b, 2])
    return math.degrees(math.acos(min(max(cosine, 0.0), 1.0)))


@numba.njit(**_JIT)
def _interior_kernel(labels, lookup):  # pragma: no cover - compiled
    """``lookup[labels]`` and its interior.

    A pixel is interior when its label (> 0) fills the window of
    ``_INTERIOR_MARGIN`` pixels around it, clipped by the image border (as a
    minimum and a maximum filter with the border replicated agree), that
    is, when no two neighbouring pixels in the window differ. Such pairs are
    found once, and each spoils the windows it lies in: a box filter (an OR)
    along the rows and then down the columns, in loops the compiler
    vectorises.
    """
    height, width = labels.shape
    margin = _INTERIOR_MARGIN
    mapped = np.empty((height, width), np.int32)
    for i in range(height):
        for j in range(width):
            mapped[i, j] = lookup[np.uint32(labels[i, j])]  # unsigned: no wrap-around test (labels are >= 0)
    # Differing pairs across columns j, j + 1 and across rows i, i + 1, at column j + margin (the margin
    # columns each side stay False).
    across = np.zeros((height, width + 2 * margin), np.bool_)
    down = np.zeros((height, width + 2 * margin), np.bool_)
    for i in range(height):
        for j in range(width - 1):
            across[i, j + margin] = mapped[i, j] != mapped[i, j + 1]
        if i + 1 < height:
            for j in range(width):
                down[i, j + margin] = mapped[i, j] != mapped[i + 1, j]
    # Pairs within a window's columns (j - margin .. j + margin), at row i + margin (the margin rows stay False).
    across_near = np.zeros((height + 2 * margin, width), np.bool_)
    down_near = np.zeros((height + 2 * margin, width), np.bool_)
    for i in range(height):
        for j in range(width):
            near_across = False
            for offset in range(2 * margin):
                near_across |= across[i, j + offset]
            near_down = False
            for offset in range(2 * margin + 1):
                near_down |= down[i, j + offset]
            across_near[i + margin, j] = near_across
            down_near[i + margin, j] = near_down
    # ... and within its rows (i - margin .. i + margin).
    interior = np.empty((height, width), np.bool_)
    for i in range(height):
        for j in range(width):
            spoiled = False
            for offset in range(2 * margin + 1):
                spoiled |= across_near[i + offset, j]
            for offset in range(2 * margin):
                spoiled |= down_near[i + offset, j]
            interior[i, j] = (mapped[i, j] > 0) & ~spoiled
    return mapped, interior


@numba.njit(**_JIT)
def _outline_and_weighted_moments(points, sigma, labels, interior, n_labels, row_step):  # pragma: no cover - compiled
    """In one pass over every ``row_step``-th row: each label's point moments outside its ``interior``, and
    `ray_planes_kernel`'s weighted moments inside it and outside it; with ``row_step`` > 1 also the point
    moments inside it (else empty).

    The outline is the few pixels: with every row read, the caller takes its
    point moments off the segment's rather than summing the interior's again.
    """
    height, width = labels.shape
    outline = np.zeros((n_labels, 10))
    inside_weighted = np.zeros((n_labels, 10))
    outside_weighted = np.zeros((n_labels, 10))
    sampled = np.zeros((n_labels if row_step > 1 else 0, 10))
    current = 0
    inside = outside = outside_plain = inside_plain = _EMPTY_RUN
    for i in range(0, height, row_step):
        for j in range(width):
            label = labels[i, j]
            if label <= 0:
                continue
            if label != current:
                _run_flush(outline, current, outside_plain)
                _run_flush(inside_weighted, current, inside)
                _run_flush(outside_weighted, current, outside)
                if row_step > 1:
                    _run_flush(sampled, current, inside_plain)
                current = label
                inside = outside = outside_plain = inside_plain = _EMPTY_RUN
            x = np.float64(points[i, j, 0])
            y = np.float64(points[i, j, 1])
            z = np.float64(points[i, j, 2])
            w = ray_weight(x, y, z, sigma[i, j])
            if interior[i, j]:
                inside = _run_add_weighted(inside, x, y, z, w)
                if row_step > 1:
                    inside_plain = _run_add(inside_plain, x, y, z)
            else:
                outside = _run_add_weighted(outside, x, y, z, w)
                outside_plain = _run_add(outside_plain, x, y, z)
    _run_flush(outline, current, outside_plain)
    _run_flush(inside_weighted, current, inside)
    _run_flush(outside_weighted, current, outside)
    if row_step > 1:
        _run_flush(sampled, current, inside_plain)
    return outline, inside_weighted, outside_weighted, sampled


@numba.njit(**_JIT)
def _outlier_moments(points, sigma, labels, interior, whole, planes, limits, row_step):  # pragma: no cover - compiled
    """`ray_planes_kernel`'s weighted moments of each label's fitted pixels (interior, or all of a ``whole`` label) beyond ``limits`` of its plane, and their count.

    A label without a plane (NaN) has all its fitted pixels beyond it unless
    its limit is infinite. These are the few pixels (a rounded crease, a
    stray pixel) to take off the sums of all. Every ``row_step``-th row only,
    as in `_interior_planes`.
    """
    height, width = labels.shape
    weighted = np.zeros((planes.shape[0], 10))
    counts = np.zeros(planes.shape[0])
    current = 0
    run = _EMPTY_RUN
    count = 0.0
    for i in range(0, height, row_step):
        for j in range(width):
            label = labels[i, j]
            if label <= 0 or not (whole[label] or interior[i, j]) or limits[label] == math.inf:
                continue
            x = np.float64(points[i, j, 0])
            y = np.float64(points[i, j, 1])
            z = np.float64(points[i, j, 2])
            if abs(planes[label, 0] * x + planes[label, 1] * y + planes[label, 2] * z + planes[label, 3]) <= limits[label]:
                continue
            if label != current:
                _run_flush(weighted, current, run)
                counts[current] += count
                current, run, count = label, _EMPTY_RUN, 0.0
            run = _run_add_weighted(run, x, y, z, ray_weight(x, y, z, sigma[i, j]))
            count += 1.0
    _run_flush(weighted, current, run)
    counts[current] += count
    return weighted, counts


# --------------------------------------------------------------------------
# Growing.
# --------------------------------------------------------------------------


@numba.njit(**_JIT)
def _growing_grid(valid, normals, min_coherence):  # pragma: no cover - compiled
    """Growing state and seed order of a frame whose valid points are ``valid``.

    Returns

    * state ((H + 2) * (W + 2),) int32, the grid framed by one pixel: 0
      where a region may grow (a valid pixel with a known normal), -1
      elsewhere and on the frame, so that growing needs no bounds checks;
    * order: indices into ``state`` of the pixels that may seed a region,
      smoothest first.

    Smoothness (coherence) is the length of the mean unit normal over the
    5x5 window of pixels that may grow (1 on a plane). Pixels below
    ``min_coherence`` (on a crease, which smoothing rounds into a bevel, or
    at an edge) never seed: a region started there would be a sliver between
    two faces. They can still join a region. The window sums are float64
    rounded to float32, as ``cv2.boxFilter`` gives them; the order is a
    counting sort on coherence (65536 bins; raster order within one). Each
    step is a loop of its own, simple enough for the compiler to vectorise.
    """
    height, width = valid.shape
    stride = width + 2
    size = height * width
    flat_normals = normals.reshape(size * 3)
    flat_valid = valid.reshape(size)
    state = np.full((height + 2) * stride, -1, np.int32)
    bins = 65536
    # Only the buckets of coherences >= min_coherence are ever filled: the histogram stops there.
    used = min(int((1.0 - min(max(min_coherence, 0.0), 1.0)) * (bins - 1)), bins - 1) + 1
    keys = np.empty((height, width), np.int32)
    # One row of the normals (zero where a region may not grow) and of growth flags, framed by two zeros
    # each side; the window sums along the last five rows (a ring); and their sum down the columns, which
    # slides: the entering row added, the leaving one taken off.
    row = np.zeros((4, width + 4))
    row_sums = np.empty((5, 4, width))
    window = np.zeros((4, width))
    coherence = np.empty(width, np.float32)
    for entering in range(height + 2):
        if entering < height:
            # Views indexed by the column alone: an index with a run-time offset keeps the loop from vectorising.
            base = entering * width
            normals_row = flat_normals[3 * base : 3 * (base + width)]
            valid_row = flat_valid[base : base + width]
            state_row = state[(entering + 1) * stride + 1 : (entering + 1) * stride + 1 + width]
            row_x, row_y, row_z, row_n = row[0, 2:], row[1, 2:], row[2, 2:], row[3, 2:]
            for j in range(width):
                x = normals_row[3 * j]
                y = normals_row[3 * j + 1]
                z = normals_row[3 * j + 2]
                grows = valid_row[j] & (x == x) & (z == z)
                state_row[j] = 0 if grows else -1
                row_x[j] = x if grows else 0.0
                row_y[j] = y if grows else 0.0
                row_z[j] = z if grows else 0.0
                row_n[j] = 1.0 if grows else 0.0
            sums = row_sums[entering % 5]
            for channel in range(4):
                for j in range(width):
                    sums[channel, j] = (row[channel, j] + row[channel, j + 1] + row[channel, j + 2] + row[channel, j + 3]
                                        + row[channel, j + 4])
            for channel in range(4):
                for j in range(width):
                    window[channel, j] += sums[channel, j]
        i = entering - 2
        if i < 0:
            continue
        for j in range(width):
            total0 = np.float32(window[0, j])
            total1 = np.float32(window[1, j])
            total2 = np.float32(window[2, j])
            coherence[j] = math.sqrt(total0**2 + total1**2 + total2**2) / np.float32(window[3, j])
        state_row = state[(i + 1) * stride + 1 : (i + 1) * stride + 1 + width]
        count = window[3]
        keys_row = keys[i]
        for j in range(width):
            seeds = (state_row[j] == 0) & (count[j] > 0) & (coherence[j] >= min_coherence)
            smoothness = coherence[j] if seeds else 1.0
            keys_row[j] = min(int((1.0 - min(smoothness, 1.0)) * (bins - 1)), used - 1) if seeds else -1
        if i >= 2:
            leaving = row_sums[(i - 2) % 5]
            for channel in range(4):
                for j in range(width):
                    window[channel, j] -= leaving[channel, j]
    histogram = np.zeros(used + 1, np.int64)
    for i in range(height):
        for j in range(width):
            if keys[i, j] >= 0:
                histogram[keys[i, j] + 1] += 1
    for key in range(used):
        histogram[key + 1] += histogram[key]
    order = np.empty(histogram[used], np.int32)
    for i in range(height):
        for j in range(width):
            key = keys[i, j]
            if key >= 0:
                order[histogram[key]] = (i + 1) * stride + j + 1
                histogram[key] += 1
    return state, order


@numba.njit(**_JIT)
def _grow_kernel(points, normals, distance, sigma, state, order, distance_sigmas, cos_angle, depth_jump, min_size, first_fit):  # pragma: no cover - compiled
    """Grow a region from each seed of ``order`` not yet taken (the module docstring says how).

    ``state`` and ``order`` are `_growing_grid`'s; ``state`` is updated in
    place. Returns the labels (H, W) int32 (0: no region) and the moments
    of each region (row 0 empty).
    """
    height, width = distance.shape
    stride = width + 2
    # A pixel is p in the framed state and d in the (unframed, flattened) data; its neighbours right, down,
    # left and up are p + steps[k] and d + data_steps[k]. The frame stops growth at the border.
    # Arrays, not tuples: indexed by a loop variable, a tuple compiles to slower code (a sixth of this kernel).
    steps = np.array([1, stride, -1, -stride], np.int64)
    data_steps = np.array([1, width, -1, -width], np.int64)
    point = points.reshape((height * width, 3))
    normal_of = normals.reshape((height * width, 3))
    range_of = distance.reshape(height * width)
    noise = sigma.reshape(height * width)
    # Pixels of dissolved regions: free to join, never a seed again.
    spent = np.zeros(state.size, np.bool_)
    # Unsigned, as the neighbours' indices below.
    queue = np.empty(height * width, np.uint32)
    queue_data = np.empty(height * width, np.uint32)
    moments = np.zeros((64, 10))
    plane = np.empty(4)
    normal = np.empty(3)
    region = 0
    for seed in order:
        if state[seed] != 0 or spent[seed]:
            continue
        region += 1
        if region >= moments.shape[0]:
            grown = np.zeros((2 * moments.shape[0], 10))
            grown[: moments.shape[0]] = moments
            moments = grown
        # Unframed index: the frame adds stride + 1 before row 0 and 2 per row.
        s = seed - stride - 1 - 2 * (seed // stride - 1)
        for k in range(3):
            plane[k] = normal_of[s, k]
        plane[3] = -(plane[0] * point[s, 0] + plane[1] * point[s, 1] + plane[2] * point[s, 2])
        n0, n1, n2, n3 = plane[0], plane[1], plane[2], plane[3]
        seed_noise = noise[s]
        state[seed] = region
        # The region's moments live in registers while it grows; memory sees them at each refit.
        grown = _run_add(_EMPTY_RUN, np.float64(point[s, 0]), np.float64(point[s, 1]), np.float64(point[s, 2]))
        queue[0] = seed
        queue_data[0] = s
        head, tail = 0, 1
        next_fit = first_fit
        while head < tail:
            c = queue[head]
            dc = queue_data[head]
            head += 1
            range_c = range_of[dc]
            for direction in range(4):
                # Unsigned: an index that may be negative gets a wrap-around test at every access.
                q = np.uint64(c + steps[direction])
                if state[q] != 0:
                    continue
                dq = np.uint64(dc + data_steps[direction])
                # Join test: no depth jump, on the plane within the noise, normal agrees (plane in registers).
                range_q = range_of[dq]
                if abs(range_q - range_c) > depth_jump * min(range_q, range_c):
                    continue
                x = point[dq, 0]
                y = point[dq, 1]
                z = point[dq, 2]
                if abs(n0 * x + n1 * y + n2 * z + n3) > distance_sigmas * noise[dq]:
                    continue
                if not (n0 * normal_of[dq, 0] + n1 * normal_of[dq, 1] + n2 * normal_of[dq, 2] >= cos_angle):
                    continue
                state[q] = region
                grown = _run_add(grown, np.float64(x), np.float64(y), np.float64(z))
                queue[tail] = q
                queue_data[tail] = dq
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
            # The failed region's pixels are free to join another, but none seeds again.
            for k in range(tail):
                state[queue[k]] = 0
                spent[queue[k]] = True
            moments[region, :] = 0.0
            region -= 1
    labels = np.empty((height, width), np.int32)
    for i in range(height):
        for j in range(width):
            labels[i, j] = max(state[(i + 1) * stride + j + 1], 0)
    return labels, moments[: region + 1].copy()


@numba.njit(**_JIT)
def _refine_boundaries(points, distance, sigma, valid, labels, planes, moments, depth_jump):  # pragma: no cover - compiled
    """Move each boundary pixel to the neighbouring segment whose plane it fits best (in place), until they settle.

    Growing is greedy: the region that reaches a pixel first keeps it, so
    near a crease or a small surface some pixels end up on the wrong side.
    A pixel with a differently labelled 8-neighbour is given to whichever of
    the segments around it (its own included) has the plane nearest to it,
    in noise sigmas along that plane's normal (`_noise_distance`), unless
    that neighbour is across a depth jump. Every pixel decides on the labels
    as they were; the moves are made after the scan. A move can only shift a
    boundary by a pixel, so the scan is repeated (up to
    ``_BOUNDARY_PASSES`` times) on the pixels around the ones just moved,
    with the planes refitted to the moved pixels: between two planes that
    meet at a shallow angle (the arena's ramp, 18 degrees off the floor) a
    region grows several pixels past the crease, all within its distance
    test (`_BOUNDARY_PASSES` gives the figures).

    Returns the rows and the columns of the valid pixels no segment holds
    (raster order), which the first scan finds on its way.
    """
    height, width = labels.shape
    free_rows = np.empty(height * width, np.int32)
    free_cols = np.empty(height * width, np.int32)
    n_free = 0
    moved_rows = np.empty(height * width, np.int32)
    moved_cols = np.empty(height * width, np.int32)
    moved_to = np.empty(height * width, np.int32)
    n_moved = 0
    # Most pixels have no other segment among their eight neighbours (each is of their own or of none):
    # nothing to move. Which of a row's pixels are such is found first, in a loop the compiler vectorises
    # (the border's pixels are left to the full test).
    inside = np.zeros(width, np.bool_)
    for i in range(height):
        if 0 < i < height - 1:
            # Rows as views, indexed by the column alone (a run-time row offset would keep the loop scalar).
            above, here, below = labels[i - 1], labels[i], labels[i + 1]
            for j in range(1, width - 1):
                own = here[j]
                inside[j] = (_own_or_none(above[j - 1], own) & _own_or_none(above[j], own)
                             & _own_or_none(above[j + 1], own) & _own_or_none(here[j - 1], own)
                             & _own_or_none(here[j + 1], own) & _own_or_none(below[j - 1], own)
                             & _own_or_none(below[j], own) & _own_or_none(below[j + 1], own))
        else:
            inside[:] = False
        for j in range(width):
            own = labels[i, j]
            if own <= 0:
                if valid[i, j]:
                    free_rows[n_free] = i
                    free_cols[n_free] = j
                    n_free += 1
                continue
            if inside[j]:
                continue
            best = _best_boundary_label(points, distance, sigma, labels, planes, i, j, depth_jump)
            if best != own:
                moved_rows[n_moved] = i
                moved_cols[n_moved] = j
                moved_to[n_moved] = best
                n_moved += 1
    _move(points, labels, moments, moved_rows, moved_cols, moved_to, n_moved)
    # Later passes: the 3x3 neighbourhoods of the pixels just moved (each pixel once per pass).
    seen = np.zeros((height, width), np.int32)
    candidate_rows = np.empty(height * width, np.int32)
    candidate_cols = np.empty(height * width, np.int32)
    for sweep in range(1, _BOUNDARY_PASSES):
        if n_moved == 0:
            break
        planes, _ = planes_kernel(moments)
        n_candidates = 0
        for k in range(n_moved):
            for qi in range(max(moved_rows[k] - 1, 0), min(moved_rows[k] + 2, height)):
                for qj in range(max(moved_cols[k] - 1, 0), min(moved_cols[k] + 2, width)):
                    if seen[qi, qj] != sweep and labels[qi, qj] > 0:
                        seen[qi, qj] = sweep
                        candidate_rows[n_candidates] = qi
                        candidate_cols[n_candidates] = qj
                        n_candidates += 1
        n_moved = 0
        for k in range(n_candidates):
            i, j = candidate_rows[k], candidate_cols[k]
            best = _best_boundary_label(points, distance, sigma, labels, planes, i, j, depth_jump)
            if best != labels[i, j]:
                moved_rows[n_moved] = i
                moved_cols[n_moved] = j
                moved_to[n_moved] = best
                n_moved += 1
        _move(points, labels, moments, moved_rows, moved_cols, moved_to, n_moved)
    return free_rows[:n_free], free_cols[:n_free]


@numba.njit(**_JIT, inline="always")
def _best_boundary_label(points, distance, sigma, labels, planes, i, j, depth_jump):  # pragma: no cover - compiled
    """The label `_refine_boundaries` gives the labelled pixel ``(i, j)``: its own or a nearer neighbour plane's."""
    height, width = labels.shape
    own = labels[i, j]
    x = points[i, j, 0]
    y = points[i, j, 1]
    z = points[i, j, 2]
    best = own
    best_distance = _noise_distance(planes, own, x, y, z, distance[i, j])
    if not (best_distance == best_distance):
        return own
    for di in range(-1, 2):
        for dj in range(-1, 2):
            qi = i + di
            qj = j + dj
            if qi < 0 or qj < 0 or qi >= height or qj >= width:
                continue
            other = labels[qi, qj]
            if other <= 0 or other == best or other == own:
                continue
            if abs(distance[qi, qj] - distance[i, j]) > depth_jump * min(distance[qi, qj], distance[i, j]):
                continue
            gap = _noise_distance(planes, other, x, y, z, distance[i, j])
            if gap < best_distance:
                best = other
                best_distance = gap
    return best if best_distance <= 3.0 * sigma[i, j] else own


@numba.njit(**_JIT, inline="always")
def _move(points, labels, moments, rows, cols, to, count):  # pragma: no cover - compiled
    """Relabel the pixels ``rows[k], cols[k]`` to ``to[k]`` (k < ``count``), moving their points' moments along."""
    for k in range(count):
        i = rows[k]
        j = cols[k]
        x = points[i, j, 0]
        y = points[i, j, 1]
        z = points[i, j, 2]
        _add_moments(moments, labels[i, j], -x, -y, -z, -1.0)
        _add_moments(moments, to[k], x, y, z, 1.0)
        labels[i, j] = to[k]


@numba.njit(**_JIT, inline="always")
def _noise_distance(planes, label, x, y, z, distance):  # pragma: no cover - compiled
    """Distance of the point ``(x, y, z)`` (``distance`` from the sensor) to ``label``'s plane, per unit of range noise.

    That is, divided by how far a unit of range noise moves the point off
    the plane: ``|cos(incidence)|``, floored at ``_MIN_INCIDENCE_COS``.
    Compared with ``k * sigma``, it is the plane's own ``k``-sigma test.
    """
    along = planes[label, 0] * x + planes[label, 1] * y + planes[label, 2] * z
    return abs(along + planes[label, 3]) / max(abs(along) / distance, _MIN_INCIDENCE_COS)


@numba.njit(**_JIT, inline="always")
def _own_or_none(label, own):  # pragma: no cover - compiled
    """Whether a neighbour labelled ``label`` belongs to segment ``own`` or to none (it is no other segment)."""
    return (label == own) | (label <= 0)


@numba.njit(**_JIT)
def _free_pixels(labels, valid):  # pragma: no cover - compiled
    """Rows and columns of the valid pixels no segment holds, in raster order."""
    height, width = labels.shape
    rows = np.empty(height * width, np.int32)
    cols = np.empty(height * width, np.int32)
    n_free = 0
    for i in range(height):
        for j in range(width):
            if labels[i, j] <= 0 and valid[i, j]:
                rows[n_free] = i
                cols[n_free] = j
                n_free += 1
    return rows[:n_free], cols[:n_free]


@numba.njit(**_JIT)
def _absorb_kernel(points, distance, sigma, labels, planes, moments, free_rows, free_cols, distance_sigmas, depth_jump, sweeps):  # pragma: no cover - compiled
    """Give free pixels to the neighbouring segment whose plane is nearest, ring by ring (in place).

    Outline pixels often have spoiled normals (their window straddled the
    crease or the jump), so growing left them out; by distance alone, each
    joins the adjacent segment whose plane it is nearest to, if within
    ``distance_sigmas`` noise sigmas along that plane's normal
    (`_noise_distance`) and not across a depth jump. Each sweep
    decides on the labels of the previous one, so the order of the scan does
    not matter; ``sweeps`` rings are added at most. ``free_rows`` and
    ``free_cols`` are the free valid pixels (`_free_pixels`); returns those
    left free, in the same arrays' first entries.
    """
    height, width = labels.shape
    n_free = free_rows.size
    chosen = np.empty(n_free, np.int32)
    for _ in range(sweeps):
        changed = 0
        for k in range(n_free):
            i = free_rows[k]
            j = free_cols[k]
            # Unsigned copies for the pixel's own entries: an index that may be negative gets a wrap-around test.
            row, column = np.uint64(i), np.uint64(j)
            x = points[row, column, 0]
            y = points[row, column, 1]
            z = points[row, column, 2]
            here = distance[row, column]
            best = 0
            best_gap = distance_sigmas * sigma[row, column]
            for direction in range(4):
                qi = i + _FOUR[direction, 0]
                qj = j + _FOUR[direction, 1]
                if qi < 0 or qj < 0 or qi >= height or qj >= width:
                    continue
                other = labels[qi, qj]
                if other <= 0:
                    continue
                if abs(distance[qi, qj] - here) > depth_jump * min(distance[qi, qj], here):
                    continue
                gap = _noise_distance(planes, other, x, y, z, here)
                if gap <= best_gap:
                    best = other
                    best_gap = gap
            chosen[k] = best
            changed += best > 0
        if changed == 0:
            break
        remaining = 0
        for k in range(n_free):
            i = free_rows[k]
            j = free_cols[k]
            best = chosen[k]
            if best > 0:
                labels[i, j] = best
                _add_moments(moments, best, points[i, j, 0], points[i, j, 1], points[i, j, 2], 1.0)
            else:
                free_rows[remaining] = i
                free_cols[remaining] = j
                remaining += 1
        n_free = remaining
    return free_rows[:n_free], free_cols[:n_free]


# --------------------------------------------------------------------------
# Moments.
# --------------------------------------------------------------------------


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



@numba.njit(**_JIT, inline="always")
def _run_add(run, x, y, z):  # pragma: no cover - compiled
    """`add_point` on a run of moments held as a tuple (in registers, not memory)."""
    return (run[0] + 1.0, run[1] + x, run[2] + y, run[3] + z, run[4] + x * x, run[5] + x * y,
            run[6] + x * z, run[7] + y * y, run[8] + y * z, run[9] + z * z)


@numba.njit(**_JIT, inline="always")
def _run_add_weighted(run, x, y, z, w):  # pragma: no cover - compiled
    """`_run_add` with the point weighted by ``w`` (every sum, the count too)."""
    wx, wy, wz = w * x, w * y, w * z
    return (run[0] + w, run[1] + wx, run[2] + wy, run[3] + wz, run[4] + wx * x, run[5] + wx * y,
            run[6] + wx * z, run[7] + wy * y, run[8] + wy * z, run[9] + wz * z)


@numba.njit(**_JIT, inline="always")
def _run_flush(moments, label, run):  # pragma: no cover - compiled
    """Add a run's moments to ``label``'s row (nothing for label <= 0)."""
    if label > 0:
        for k in range(10):
            moments[label, k] += run[k]


# A run starts empty. Kernels add a point to the run of its label inline, flushing the previous label's
# run first (a helper returning the label and the run together would pass the tuple through memory,
# which costs four times as much).
_EMPTY_RUN = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@numba.njit(**_JIT)
def _agreeing_labels(labels, planes, normals, cos_angle):  # pragma: no cover - compiled
    """``labels`` with 0 where a pixel's normal (unoriented, NaN included) is off its label's plane by more than ``acos(cos_angle)``."""
    agreeing = labels.copy()
    if cos_angle < -0.5:
        return agreeing
    height, width = labels.shape
    for i in range(height):
        for j in range(width):
            label = labels[i, j]
            if label > 0:
                dot = planes[label, 0] * normals[i, j, 0] + planes[label, 1] * normals[i, j, 1] + planes[label, 2] * normals[i, j, 2]
                if not abs(dot) >= cos_angle:
                    agreeing[i, j] = 0
    return agreeing


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
                current, run = label, _EMPTY_RUN
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
                x, y, z = np.float64(points[i, j, 0]), np.float64(points[i, j, 1]), np.float64(points[i, j, 2])
                if label != current:
                    _run_flush(moments, current, run)
                    current, run = label, _EMPTY_RUN
                run = _run_add(run, x, y, z)
    _run_flush(moments, current, run)
    return moments



def _label_moments(points: np.ndarray, labels: np.ndarray, n_labels: int) -> np.ndarray:
    """Point moments (n_labels, 10) of every label (row 0: unlabelled, left empty)."""
    return _masked_moments(points, labels, labels > 0, n_labels)
