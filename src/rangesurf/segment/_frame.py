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
from rangesurf._grid import point_ranges, points_along_rays
from rangesurf.normals import _normals_and_ranges, _point_grid, estimate_normals
from rangesurf.segment._segmentation import Segmentation
from rangesurf.segment.nxd import segment_nxd
from rangesurf.segment.region_grow import _grow, _refine_upsampled

__all__ = ["SEGMENTERS", "SegmentedFrame", "growing_decimation", "segment_frame", "segment_planes"]

SEGMENTERS = ("region", "nxd")


# Large frames are grown on a grid decimated to about this many pixels, then refined at full resolution.
_GROWING_PIXELS = 40_000


def growing_decimation(height: int, width: int) -> int:
    """The decimation `segment_planes` grows a frame of this size at by default (about 40,000 pixels)."""
    return max(1, round(math.sqrt(height * width / _GROWING_PIXELS)))


def segment_planes(
    points: ArrayLike,
    *,
    range_sigma: ArrayLike | float,
    projection: PinholeProjection | None = None,
    decimate: int | None = None,
    normals: ArrayLike | None = None,
    return_normals: bool = False,
) -> Segmentation | tuple[Segmentation, np.ndarray]:
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
        Grow the regions on ``points[::decimate, ::decimate]`` and carry them
        back to full resolution (`refine_upsampled`). Default: the factor
        that leaves about 40,000 pixels to grow on (3 for 640x480, 1 for
        an SR-3000 or a 3DTK scan). On simulated 640x480 frames factors 2-4
        find the same planes as growing at full resolution, with normal
        errors as low, in a third of the time (`growing_decimation`).
    normals : array, optional
        `estimate_normals` of the points grown on (``points[::decimate,
        ::decimate]``, with the projection and sigma decimated alike), when
        the caller has them already.
    return_normals : bool
        Also return the normals grown with (those given, or those
        estimated here): registration can use them (the pipeline does).

    Returns
    -------
    segmentation : Segmentation
    normals : (H', W', 3) float32
        With ``return_normals``: the normals of ``points[::decimate,
        ::decimate]``.

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
    if isinstance(decimate, bool) or not isinstance(decimate, (int, np.integer)) or decimate < 1:
        raise ValueError(f"decimate must be an integer >= 1, got {decimate!r}")
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
        return (segmentation, normals) if return_normals else segmentation
    distance, valid, n_infinite = point_ranges(points)
    if n_infinite:
        check_point_grid(points)  # raises, in the shared wording
    sigma = check_range_sigma(
        distance, np.broadcast_to(np.asarray(range_sigma, dtype=np.float64), (height, width))
    )
    # The stages' own defaults, on inputs checked once here.
    coarse_points = check_point_grid(points[::decimate, ::decimate])
    coarse_sigma = np.ascontiguousarray(sigma[::decimate, ::decimate])
    coarse_projection = None
    if projection is not None:
        # Pixel i of the decimated grid is pixel decimate * i of the full one.
        coarse_projection = PinholeProjection(
            fx=projection.fx / decimate, fy=projection.fy / decimate, cx=projection.cx / decimate, cy=projection.cy / decimate
        )
    if normals is None:
        normals = estimate_normals(coarse_points, projection=coarse_projection, range_sigma=coarse_sigma)
    coarse = _grow(coarse_points, normals, coarse_sigma, np.ascontiguousarray(distance[::decimate, ::decimate]),
                   np.ascontiguousarray(valid[::decimate, ::decimate]))
    segmentation = _refine_upsampled(points, distance, valid, sigma, coarse, decimate)
    return (segmentation, normals) if return_normals else segmentation


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
