"""Merging registered frames into one global model (thesis Section 3.3).

`GlobalModel` fuses planar surfaces into one `PlanarPatch` per plane
(`rangesurf.merge.planar`); `TSDFVolume` is the volumetric path for
non-planar objects (Curless & Levoy), with marching-cubes meshes
(`rangesurf.merge.tsdf`).
"""

from rangesurf.merge.model import NONPLANAR_MODES, GlobalModel, MergeStep, ModelAlignment
from rangesurf.merge.planar import Observations, PlanarPatch
from rangesurf.merge.tsdf import TSDFVolume, VoxelSample

__all__ = ["GlobalModel", "MergeStep", "ModelAlignment", "NONPLANAR_MODES", "PlanarPatch", "Observations", "TSDFVolume", "VoxelSample"]
