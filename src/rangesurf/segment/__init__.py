"""Planar segmentation of organized range frames (thesis Sections 2.1-2.2, 3.1).

* `grow_regions` -- region growing with incremental plane fits (Poppinga et
  al. 2008), the main segmenter;
* `nxd_transform`, `segment_nxd` -- the thesis's normal x distance space and
  segmentation by clustering in it;
* `evaluate_segmentation`, `truth_segmentation` -- the Hoover et al. 1996
  comparison against ground-truth labels (the field's standard score).

Every segmenter returns a `Segmentation` (labels, planes, residuals, sizes);
`segment_planes` runs normals and region growing (on a pooled, coarser grid for frames of 20,000 pixels or more),
`segment_frame` denoising, normals and a segmenter on one `RangeFrame`.
"""

from rangesurf.segment._frame import (SEGMENTERS, GrowingGrid, SegmentedFrame, growing_decimation, pooled_frame_grid,
                                      segment_frame, segment_planes)
from rangesurf.segment._segmentation import Segmentation
from rangesurf.segment.evaluate import (
    SegmentationScores,
    evaluate_segmentation,
    match_planes,
    transform_planes,
    truth_segmentation,
)
from rangesurf.segment.nxd import nxd_transform, segment_nxd
from rangesurf.segment.region_grow import grow_regions, refine_upsampled

__all__ = [
    "SEGMENTERS",
    "Segmentation",
    "SegmentedFrame",
    "SegmentationScores",
    "evaluate_segmentation",
    "grow_regions",
    "match_planes",
    "nxd_transform",
    "refine_upsampled",
    "segment_frame",
    "segment_nxd",
    "segment_planes",
    "growing_decimation",
    "GrowingGrid",
    "pooled_frame_grid",
    "transform_planes",
    "truth_segmentation",
]
