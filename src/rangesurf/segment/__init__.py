"""Planar segmentation of organized range frames (thesis Sections 2.1-2.2, 3.1).

* `grow_regions` -- region growing with incremental plane fits (Poppinga et
  al. 2008), the main segmenter;
* `nxd_transform`, `cluster_nxd` -- the thesis's normal x distance space and
  its clustering into surfaces;
* `evaluate_segmentation` -- the Hoover et al. 1996 comparison against
  ground-truth labels (the field's standard score).

Every segmenter returns a `Segmentation` (labels, planes, residuals, sizes).
"""

from rangesurf.segment._segmentation import Segmentation
from rangesurf.segment.region_grow import grow_regions

__all__ = ["Segmentation", "grow_regions"]
