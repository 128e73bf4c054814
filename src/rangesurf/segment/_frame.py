"""One frame in, planar segments out: denoise, normals, segmentation (thesis Figure 3.1, first stages)."""

from __future__ import annotations

import dataclasses
import math
import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rangesurf._checks import check_point_grid, check_range_sigma
from rangesurf.denoise import denoise_range
from rangesurf.frame import PinholeProjection, RangeFrame
from rangesurf._grid import point_ranges, points_along_rays, pooled_grid
from rangesurf.normals import _normals_and_ranges, _point_grid, estimate_normals
from rangesurf.segment._segmentation import Segmentation
from rangesurf.segment.nxd import segment_nxd
from rangesurf.segment.region_grow import _grow, _refine_upsampled, default_min_size

__all__ = [
    "SEGMENTERS", "GrowingGrid", "SegmentedFrame", "growing_decimation", "pooled_frame_grid", "segment_frame",
    "segment_planes",
]

SEGMENTERS = ("region", "nxd")


# Large frames are grown on a grid pooled to about this many pixels, then refined at full resolution;
_GROWING_PIXELS = 40_000
# and from this many pixels on, at least 2x pooled. At 176x144 (SR-3000) that took 3.3 instead of 4.6 ms a frame
# and found 107 / 101 / 98 / 102 / 104 of 110 planes (raw / diffusion / layered / phase / outlier removal only)
# against 109 / 95 / 94 / 98 / 109 (benchmarks/segmentation.py).
_POOLED_FROM = 20_000
# Largest normal window on the pooled grid: 9 coarse pixels already span 18 or more of the full grid (at
# 176x144 the full-resolution ladder's 15 found 5 fewer planes on raw frames; at 640x480, 3x, either finds all).
_COARSE_MAX_WINDOW = 9


@dataclass(frozen=True)
class GrowingGrid:
    """The grid `segment_planes` grows regions on: the frame's own, or a pooled, coarser copy (`pooled_frame_grid`).

    Parameters
    ----------
    points : (H', W', 3) float32
        Sensor-frame points (metres), NaN where invalid.
    range_sigma : (H', W') float64
        Their range noise (metres); a pooled point's is lower than a pixel's.
    projection : PinholeProjection or None
        The grid's pinhole (the frame's scaled to the coarser grid), if the frame has one.
    normals : (H', W', 3) float32 or None
        The grid's normals, once estimated.
    decimate : int
        Full-resolution pixels per grid pixel along each axis.
    """

    points: np.ndarray
    range_sigma: np.ndarray
    projection: PinholeProjection | None
    normals: np.ndarray | None
    decimate: int


def _check_decimate(decimate) -> None:
    if isinstance(decimate, bool) or not isinstance(decimate, (int, np.integer)) or decimate < 1:
        raise ValueError(f"decimate must be an integer >= 1, got {decimate!r}")


def _checked_ranges(points: np.ndarray, range_sigma) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points' ranges, valid mask and (H, W) sigma, raising on Inf points or a bad sigma."""
    distance, valid, n_infinite = point_ranges(points)
    if n_infinite:
        check_point_grid(points)  # raises, in the shared wording
    sigma = check_range_sigma(distance, np.broadcast_to(np.asarray(range_sigma, dtype=np.float64), distance.shape))
    return distance, valid, sigma


def _pooled(points, distance, valid, sigma, projection, decimate) -> GrowingGrid:
    """The grid ``decimate`` times coarser whose points pool the frame's blocks (`rangesurf._grid.pooled_grid`)."""
    coarse_projection = None
    rays = (0.0, 0.0, 0.0, 0.0)
    if projection is not None:
        rays = (float(projection.fx), float(projection.fy), float(projection.cx), float(projection.cy))
        # Coarse pixel i is centred on pixel decimate * i + (decimate - 1) / 2 of the full grid.
        half = 0.5 * (decimate - 1)
        coarse_projection = PinholeProjection(
            fx=projection.fx / decimate, fy=projection.fy / decimate,
            cx=(projection.cx - half) / decimate, cy=(projection.cy - half) / decimate,
        )
    coarse_points, coarse_sigma = pooled_grid(points, valid, distance, sigma, decimate, *rays)
    return GrowingGrid(coarse_points, coarse_sigma, coarse_projection, None, decimate)


def pooled_frame_grid(
    points: ArrayLike, *, range_sigma: ArrayLike | float, projection: PinholeProjection | None = None, decimate: int
) -> GrowingGrid:
    """The grid `segment_planes` grows on at ``decimate``, with its normals, without growing regions.

    For a caller that wants that grid at another decimation than the
    segmentation's (the pipeline registers on it). ``decimate=1`` is the
    frame itself.
    """
    _check_decimate(decimate)
    points = _point_grid(points)
    distance, valid, sigma = _checked_ranges(points, range_sigma)
    if decimate == 1:
        grid = GrowingGrid(points, np.ascontiguousarray(sigma), projection, None, 1)
        window = {}
    else:
        grid = _pooled(points, distance, valid, sigma, projection, decimate)
        window = {"max_window": _COARSE_MAX_WINDOW}
    normals = estimate_normals(grid.points, projection=grid.projection, range_sigma=grid.range_sigma, **window)
    return dataclasses.replace(grid, normals=normals)


def growing_decimation(height: int, width: int) -> int:
    """The decimation `segment_planes` grows a frame of this size at by default.

    About 40,000 pixels are left to grow on, and frames of 20,000 pixels or
    more are pooled at least 2x: 3 for 640x480, 2 for an SR-3000 (176x144)
    or a 3DTK scan (226x360), 1 below.
    """
    pixels = height * width
    return max(round(math.sqrt(pixels / _GROWING_PIXELS)), 2 if pixels >= _POOLED_FROM else 1)


def segment_planes(
    points: ArrayLike,
    *,
    range_sigma: ArrayLike | float,
    projection: PinholeProjection | None = None,
    decimate: int | None = None,
    normals: ArrayLike | None = None,
    return_grid: bool = False,
) -> Segmentation | tuple[Segmentation, GrowingGrid]:
    """Normals and region growing in one call, decimating large frames for speed.

    Parameters
    ----------
    points : (H, W, 3) float array
        Sensor-frame points (metres), NaN where invalid (preferably denoised).
    range_sigma : float or (H, W) array
        Range noise sigma (metres), e.g. ``sensor.range_sigma(range, intensity)``.
    projection : PinholeProjection, optional
        Enables the fast pinhole normal path (`estimate_normals`).
    decimate : int, optional
        Grow the regions on a grid ``decimate`` times coarser, each point
        pooling the middle of a ``decimate`` x ``decimate`` block
        (`rangesurf._grid.pooled_grid`), and carry them back to full
        resolution (`refine_upsampled`). Default: `growing_decimation` (3
        for 640x480, 2 for an SR-3000 or a 3DTK scan, 1 for frames under
        20,000 pixels). ``decimate=1`` grows every pixel: on raw 176x144
        SR-3000 frames it finds 2 more planes of 110 with normals 0.06
        degrees closer, in 1.4 times the time.
    normals : array, optional
        The normals of the grid grown on, as an earlier call's
        ``return_grid`` gave them (at ``decimate=1`` those of
        `estimate_normals`), when the caller has them already.
    return_grid : bool
        Also return the grid grown on, with its normals (those given, or
        those estimated here): registration can use them (the pipeline
        does).

    Returns
    -------
    segmentation : Segmentation
    grid : GrowingGrid
        With ``return_grid``: the grid grown on (the pooled one when
        decimated) and its normals.

    Examples
    --------
    >>> from rangesurf import simulate
    >>> frames, _ = simulate.simulate_sequence("arena", "kinect", n_frames=1)
    >>> frame = frames[0]
    >>> sigma = frame.sensor.range_sigma(frame.range, frame.intensity)
    >>> planes = segment_planes(frame.points, range_sigma=sigma, projection=frame.sensor.projection)
    >>> planes.labels.shape, planes.n_segments >= 6
    ((480, 640), True)
    """
    points = _point_grid(points)
    height, width = points.shape[:2]
    if decimate is None:
        decimate = growing_decimation(height, width)
    _check_decimate(decimate)
    if normals is not None:
        normals = np.asarray(normals)
        grown = points[::decimate, ::decimate].shape
        if normals.shape != grown:
            raise ValueError(f"normals {normals.shape} must match the points grown on, {grown} (decimated by {decimate})")
    if decimate == 1:
        # The normal estimator refuses Inf points and checks the sigma where there is a return, in its
        # own passes, and hands on the ranges it found for growing.
        sigma = np.ascontiguousarray(np.broadcast_to(np.asarray(range_sigma, dtype=np.float64), (height, width)))
        if normals is None:
            normals, _, distance, valid = _normals_and_ranges(points, projection, range_sigma=sigma)
        else:
            distance, valid, _ = point_ranges(points)
        segmentation = _grow(points, normals, sigma, distance, valid)
        if not return_grid:
            return segmentation
        return segmentation, GrowingGrid(points, sigma, projection, normals, 1)
    distance, valid, sigma = _checked_ranges(points, range_sigma)
    grid = _pooled(points, distance, valid, sigma, projection, decimate)
    if normals is None:
        normals, _, coarse_distance, coarse_valid = _normals_and_ranges(
            grid.points, grid.projection, max_window=_COARSE_MAX_WINDOW, range_sigma=grid.range_sigma
        )
    else:
        coarse_distance, coarse_valid, _ = point_ranges(grid.points)
    coarse = _grow(grid.points, normals, grid.range_sigma, coarse_distance, coarse_valid,
                   min_size=max(1, round(default_min_size(height, width) / decimate**2)))
    segmentation = _refine_upsampled(points, distance, valid, sigma, coarse, decimate, normals)
    return (segmentation, dataclasses.replace(grid, normals=normals)) if return_grid else segmentation


@dataclass(frozen=True)
class SegmentedFrame:
    """What `segment_frame` computed for one frame.

    Parameters
    ----------
    range : (H, W) float32
        The denoised range (metres), NaN where invalid.
    points : (H, W, 3) float32
        Sensor-frame points of ``range``.
    range_sigma : (H, W) float64
        Noise sigma used for the thresholds (metres).
    segmentation : Segmentation
        Labels, planes, residuals, sizes.
    projection : PinholeProjection or None
        The camera's, for the fast normal path.
    """

    range: np.ndarray
    points: np.ndarray
    range_sigma: np.ndarray
    segmentation: Segmentation
    projection: PinholeProjection | None = None

    @functools.cached_property
    def normals(self) -> np.ndarray:
        """(H, W, 3) float32 full-resolution normals (`estimate_normals`), computed on first use."""
        return estimate_normals(self.points, projection=self.projection, range_sigma=self.range_sigma)


def segment_frame(frame: RangeFrame, *, denoise: str = "diffusion", segmenter: str = "region") -> SegmentedFrame:
    """Denoise a frame, estimate its normals and split it into planar segments.

    Parameters
    ----------
    frame : RangeFrame
        Any frame `rangesurf.load` returns; its sensor model supplies the
        noise sigma of every threshold and, for a pinhole camera, the fast
        normal path.
    denoise : {"diffusion", "layered", "phase", "none"}
        `rangesurf.denoise.denoise_range` method ("none": outlier removal only).
    segmenter : {"region", "nxd"}
        `segment_planes` (region growing) or `segment_nxd` (the thesis's
        clustering in normal x distance space).

    Returns
    -------
    SegmentedFrame

    Examples
    --------
    >>> from rangesurf import simulate
    >>> from rangesurf.segment import segment_frame
    >>> frames, truths = simulate.simulate_sequence("arena", "sr3000", n_frames=1)
    >>> result = segment_frame(frames[0])
    >>> result.segmentation.n_segments >= 4
    True
    """
    if segmenter not in SEGMENTERS:
        raise ValueError(f"segmenter must be one of {SEGMENTERS}, got {segmenter!r}")
    smooth = denoise_range(frame.range, method=denoise, sensor=frame.sensor, intensity=frame.intensity, rays=frame.rays)
    points = points_along_rays(np.ascontiguousarray(frame.rays), np.ascontiguousarray(smooth))
    sigma = frame.sensor.range_sigma(np.where(np.isfinite(smooth), smooth, 1.0), frame.intensity)
    projection = frame.sensor.projection if isinstance(frame.sensor.projection, PinholeProjection) else None
    result = SegmentedFrame(range=smooth, points=points, range_sigma=sigma, segmentation=None, projection=projection)
    if segmenter == "region":
        segmentation = segment_planes(points, range_sigma=sigma, projection=projection)
    else:
        segmentation = segment_nxd(points, result.normals)
    return dataclasses.replace(result, segmentation=segmentation)
