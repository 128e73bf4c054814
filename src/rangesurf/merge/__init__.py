"""Merging registered frames into one global model (thesis Section 3.3).

`GlobalModel` fuses planar surfaces into one `PlanarPatch` per plane
(`rangesurf.merge.planar`); the volumetric path for non-planar objects is
`rangesurf.merge.tsdf`.
"""

from rangesurf.merge.model import NONPLANAR_MODES, GlobalModel, MergeStep
from rangesurf.merge.planar import Observations, PlanarPatch

__all__ = ["GlobalModel", "MergeStep", "NONPLANAR_MODES", "PlanarPatch", "Observations"]
