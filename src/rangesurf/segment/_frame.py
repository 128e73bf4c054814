"""One frame in, planar segments out: denoise, normals, segmentation (thesis Figure 3.1, first stages)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangesurf.denoise import denoise_range
from rangesurf.frame import PinholeProjection, RangeFrame
from rangesurf.normals import estimate_normals
from rangesurf.segment._segmentation import Segmentation
from rangesurf.segment.nxd import segment_nxd
from rangesurf.segment.region_grow import grow_regions

__all__ = ["SEGMENTERS", "SegmentedFrame", "segment_frame"]

SEGMENTERS = ("region", "nxd")


@dataclass(frozen=True)
class SegmentedFrame:
    """What `segment_frame` computed for one frame.

    Parameters
    ----------
    range : (H, W) float32
        The denoised range (metres), NaN where invalid.
    points : (H, W, 3) float32
        Sensor-frame points of ``range``.
    normals : (H, W, 3) float32
        Unit normals facing the sensor, NaN where unknown.
    range_sigma : (H, W) float64
        Noise sigma used for the thresholds (metres).
    segmentation : Segmentation
        Labels, planes, residuals, sizes.
    """

    range: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    range_sigma: np.ndarray
    segmentation: Segmentation


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
        `grow_regions` (region growing) or `segment_nxd` (the thesis's
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
    points = (frame.rays * smooth[..., None]).astype(np.float32)
    sigma = frame.sensor.range_sigma(np.where(np.isfinite(smooth), smooth, 1.0), frame.intensity)
    projection = frame.sensor.projection if isinstance(frame.sensor.projection, PinholeProjection) else None
    normals = estimate_normals(points, projection=projection, range_sigma=sigma)
    if segmenter == "region":
        segmentation = grow_regions(points, normals, range_sigma=sigma)
    else:
        segmentation = segment_nxd(points, normals)
    return SegmentedFrame(range=smooth, points=points, normals=normals, range_sigma=sigma, segmentation=segmentation)
