"""The global model: every frame's surfaces merged in world coordinates (thesis Section 3.3).

`GlobalModel.add_frame` takes one frame's surfaces (sensor frame) and the
frame's pose, and for each planar surface finds the model patches it
continues -- same side facing, normals within ``max_normal_angle``, lying on
their plane within ``max_plane_distance``, and touching or overlapping their
cells -- then fuses it into them (`rangesurf.merge.planar`). Patches that a
surface shows to be one plane are merged. A surface that continues nothing
starts a new patch. Non-planar surfaces are kept as they are or dropped
(``nonplanar``); the volumetric path for them is `rangesurf.merge.tsdf`.
Between frames the model can correct a pose by its planes (`align`), remove
cells a frame sees through (`carve`) and fold fragments that a larger patch
has grown over into it (`fold_fragments`), so that it grows with the area
seen rather than with time.

The model also keeps the trajectory and a per-frame merge history, and
saves itself atomically (`save`, `load`), so that a run can resume from
its last checkpoint without losing any merged frame.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, fields
from pathlib import Path

import numba
import numpy as np
from numpy.typing import ArrayLike

from rangesurf._growing import GrowingArray
from rangesurf.frame import PinholeProjection, check_rigid_transform
from rangesurf.io._common import FormatError, atomic_path
from rangesurf.io.npz import load_arrays
from rangesurf.lod import progressive_order
from rangesurf.merge.planar import CELL_FIELDS, Observations, PlanarPatch, normal_variance_form, runs_of, variance_along
from rangesurf.mesh import Surface
from rangesurf.register import _exp

__all__ = ["GlobalModel", "MergeStep", "NONPLANAR_MODES"]

NONPLANAR_MODES = ("keep", "drop")
# 2: per-frame records as arrays (the history no longer JSON), cells' free-space misses.
# 3: each patch's frames as runs of consecutive frames (version 2's frame lists are still read).
_FORMAT_VERSION = 3
_READABLE_VERSIONS = (2, 3)
_UNCONSTRAINED_VARIANCE = 1e4
# Model alignment: surfaces smaller than this are not used; points per surface; how many independent points
# one plane's points count as; the largest squared Mahalanobis distance of a correction (chi-square, 6
# degrees of freedom: exceeded by chance 0.3 % of the time).
_ALIGN_MIN_VERTICES = 30
_ALIGN_POINTS = 200
_ALIGN_INDEPENDENT = 3.0
_ALIGN_GATE = 20.0
# At most this share of a pose's variance is taken to be the map's own (GlobalModel.align): the rest, which
# the planes shrink, stays invertible.
_ALIGN_MAX_SHARED = 0.99
# A surface whose normal is up to this many degrees off a patch's, lying on its plane and over its cells
# (this share of its points), is a view of the patch (`GlobalModel._covered_by`).
_COVER_ANGLE = 45.0
_COVERED = 0.8
# A patch folds into a larger one when this share of its cells lies on the larger one's plane
# (`GlobalModel.fold_fragments`).
_ON_PLANE = 0.95
_JIT = dict(cache=True, nogil=True, error_model="numpy")
# Medians over a surface's points (its distance from a plane, its variances) are taken on about this many:
# they are as well known from 2,000 points as from all of them (a 640x480 frame has 76,000).
_MEDIAN_SAMPLE = 2000


@dataclass(frozen=True)
class MergeStep:
    """What `GlobalModel.add_frame` did with one frame.

    Parameters
    ----------
    frame : int
        Index of the frame in the model (0-based).
    fused : int
        Planar surfaces fused into existing patches.
    created : int
        Planar surfaces that started a new patch.
    joined : int
        Patches merged into others because this frame showed them to be one plane.
    cells_updated, cells_added : int
        Model vertices averaged with new observations, and vertices added.
    rejected : int
        Vertices of fused surfaces left out: too far from the patch's plane.
    nonplanar : int
        Non-planar surfaces kept (``nonplanar="keep"``) or dropped.
    """

    frame: int
    fused: int
    created: int
    joined: int
    cells_updated: int
    cells_added: int
    rejected: int
    nonplanar: int


# The order of `MergeStep`'s fields, as the history stores them.
_STEP_FIELDS = tuple(field.name for field in fields(MergeStep))


@dataclass(frozen=True)
class ModelAlignment:
    """What `GlobalModel.align` did with a frame's pose.

    Parameters
    ----------
    T_world_sensor : (4, 4) float64
        The corrected pose (the given one when not applied).
    covariance : (6, 6) float64
        Its covariance.
    planes : int
        The frame's planar surfaces matched to a patch.
    distance : float
        Squared Mahalanobis distance of the correction under the given covariance.
    applied : bool
        Whether the pose was corrected (at least two planes matched, the correction within the gate).
    """

    T_world_sensor: np.ndarray
    covariance: np.ndarray
    planes: int
    distance: float
    applied: bool


class _PatchTable:
    """The patches' normals, world boxes, world planes and cell counts as arrays, for `_nearby_patches`.

    Rows are refreshed from each patch's cached `PlanarPatch.bounds` and
    `PlanarPatch.world_plane` when its revision has moved on: a frame
    changes a few patches, the model has many.
    """

    def __init__(self, count: int) -> None:
        # A list: compared with each patch's revision in a Python loop, NumPy scalars would cost ten times as much.
        self.revisions = [-1] * count
        self.normals = np.empty((count, 3))
        self.lows = np.empty((count, 3))
        self.highs = np.empty((count, 3))
        self.planes = np.empty((count, 4))
        self.sizes = np.empty(count, np.int64)

    def refresh(self, patches: list[PlanarPatch]) -> None:
        """Refresh the rows of the patches whose revision moved on."""
        for index, patch in enumerate(patches):
            if self.revisions[index] != patch.revision:
                self.revisions[index] = patch.revision
                self.normals[index] = patch.normal
                self.lows[index], self.highs[index] = patch.bounds()
                self.planes[index] = patch.world_plane()
                self.sizes[index] = patch.n_cells


class GlobalModel:
    """Surfaces of many registered frames merged into one model, in world coordinates.

    Parameters
    ----------
    cell_size : float, optional
        Spacing (metres) of the patches' vertex grid. By default the median
        vertex spacing of the first frame's surfaces, at least 5 mm.
    max_normal_angle : float
        Degrees: a surface continues a patch only if their normals are this
        close (and face the same way).
    max_plane_distance : float, optional
        Metres: the median distance of a surface's vertices from a patch's
        plane must stay below this; vertices farther than it are not fused.
        By default 3 times the surface's median standard deviation from
        sensor noise and registration (not its fit: see
        `Observations.reach_variance`), at least 2 cells.
    bridge : int
        Gaps up to ``2 * bridge`` cells are closed when meshing, and a
        surface within ``bridge + 1`` cells of a patch counts as touching it.
    min_overlap : int
        Cells a surface must share with (or have next to) a patch to continue it.
    nonplanar : {"keep", "drop"}
        Surfaces without a plane: kept as they are (world frame; they are
        not fused, so they grow with the frames) or dropped.

    Examples
    --------
    The same wall seen twice from 2 m: the second view adds no vertex.

    >>> import numpy as np
    >>> from rangesurf.mesh import Surface, triangulate_in_plane
    >>> rows, cols = np.mgrid[0:30, 0:40] * 0.02
    >>> wall = np.column_stack([cols.ravel(), rows.ravel(), np.full(1200, 2.0)])
    >>> surface = Surface(wall, triangulate_in_plane(wall, [0, 0, -1, 2.0]), np.tile([0, 0, -1.0], (1200, 1)),
    ...                   np.full((1200, 2), -1), plane=[0, 0, -1, 2.0])
    >>> model = GlobalModel(cell_size=0.02)
    >>> first = model.add_frame([surface], np.eye(4))
    >>> second = model.add_frame([surface], np.eye(4))
    >>> first.cells_added, second.cells_added, second.cells_updated, model.n_vertices
    (1200, 0, 1200, 1200)
    """

    def __init__(
        self,
        *,
        cell_size: float | None = None,
        max_normal_angle: float = 10.0,
        max_plane_distance: float | None = None,
        bridge: int = 1,
        min_overlap: int = 3,
        nonplanar: str = "keep",
    ) -> None:
        if cell_size is not None and not (isinstance(cell_size, (int, float)) and cell_size > 0):
            raise ValueError(f"cell_size must be > 0 metres, got {cell_size!r}")
        if not 0 < max_normal_angle < 90:
            raise ValueError(f"max_normal_angle must be in (0, 90) degrees, got {max_normal_angle}")
        if max_plane_distance is not None and not max_plane_distance > 0:
            raise ValueError(f"max_plane_distance must be > 0 metres, got {max_plane_distance}")
        if isinstance(bridge, bool) or not isinstance(bridge, int) or bridge < 0:
            raise ValueError(f"bridge must be an integer >= 0, got {bridge!r}")
        if isinstance(min_overlap, bool) or not isinstance(min_overlap, int) or min_overlap < 1:
            raise ValueError(f"min_overlap must be an integer >= 1, got {min_overlap!r}")
        if nonplanar not in NONPLANAR_MODES:
            raise ValueError(f"nonplanar must be one of {NONPLANAR_MODES}, got {nonplanar!r}")
        self.cell_size = None if cell_size is None else float(cell_size)
        self.max_normal_angle = float(max_normal_angle)
        self.max_plane_distance = None if max_plane_distance is None else float(max_plane_distance)
        self.bridge = bridge
        self.min_overlap = min_overlap
        self.nonplanar = nonplanar
        self.patches: list[PlanarPatch] = []
        self.others: list[Surface] = []
        # Per-frame records as arrays (a list of objects would grow the memory of a long run).
        # Per-frame records, as compact as they can be exact (a long run keeps one of each per frame):
        # a pose's last row is always 0 0 0 1, and a frame's merge counts fit 32 bits.
        self._poses = GrowingArray((3, 4))
        self._timestamps = GrowingArray()
        self._history = GrowingArray((len(fields(MergeStep)),), np.int32)
        self.cells_carved = 0
        # Per patch, what `_nearby` tests against every patch (None: to rebuild, after the list of patches
        # changed; a patch's row is refreshed when its revision moved on).
        self._table: _PatchTable | None = None
        # id(patch) -> (patch revision, with LOD order, mesh)
        self._meshes: dict[int, tuple[int, bool, Surface]] = {}

    # ------------------------------------------------------------------
    # State.
    # ------------------------------------------------------------------

    @property
    def n_frames(self) -> int:
        return len(self._poses)

    @property
    def poses(self) -> np.ndarray:
        """``T_world_sensor`` of the merged frames, (N, 4, 4) (a new array)."""
        poses = np.zeros((self.n_frames, 4, 4))
        poses[:, :3] = self._poses.values
        poses[:, 3, 3] = 1.0
        return poses

    @property
    def timestamps(self) -> np.ndarray:
        """Seconds (or frame counts) of the merged frames, (N,)."""
        return self._timestamps.values

    @property
    def history(self) -> list[MergeStep]:
        """What `add_frame` did with each frame."""
        return [MergeStep(*(int(value) for value in row)) for row in self._history.values]

    @property
    def n_vertices(self) -> int:
        """Observed vertices (one per occupied cell) of the planar patches, plus those of kept non-planar surfaces."""
        return sum(patch.n_cells for patch in self.patches) + sum(surface.n_vertices for surface in self.others)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Timestamps (N,) and ``T_world_sensor`` poses (N, 4, 4) of the merged frames."""
        return self.timestamps.copy(), self.poses

    # ------------------------------------------------------------------
    # Merging.
    # ------------------------------------------------------------------

    def add_frame(
        self,
        surfaces: list[Surface],
        T_world_sensor: ArrayLike,
        *,
        covariance: ArrayLike | None = None,
        timestamp: float | None = None,
    ) -> MergeStep:
        """Merge one frame's surfaces into the model.

        Parameters
        ----------
        surfaces : list of Surface
            In the frame's sensor coordinates (`rangesurf.mesh.triangulate_segments`);
            their ``UL1`` and ``UL2`` uncertainties (metres) weight the fusion
            where present.
        T_world_sensor : (4, 4) array
            The frame's pose.
        covariance : (6, 6) array, optional
            Covariance of the pose as a perturbation on the left in world
            coordinates (rotation vector in radians, translation in metres),
            as `rangesurf.register.compose_covariance` gives; it becomes each
            vertex's registration variance along its normal (UL3). None:
            the pose is taken as exact.
        timestamp : float, optional
            Seconds; the frame count by default.

        Returns
        -------
        MergeStep
        """
        pose = check_rigid_transform(T_world_sensor, "T_world_sensor")
        pose_covariance = None
        if covariance is not None:
            pose_covariance = np.asarray(covariance, dtype=np.float64)
            if pose_covariance.shape != (6, 6):
                raise ValueError(f"covariance must be 6x6 (rotation, translation), got shape {pose_covariance.shape}")
            if np.isnan(pose_covariance).any():
                raise ValueError("covariance contains NaN")
        for index, surface in enumerate(surfaces):
            if not isinstance(surface, Surface):
                raise TypeError(f"surfaces[{index}] must be a rangesurf.mesh.Surface, got {type(surface).__name__}")
        frame = self.n_frames
        if self.cell_size is None:
            self.cell_size = _default_cell_size(surfaces)
        counts = dict(fused=0, created=0, joined=0, cells_updated=0, cells_added=0, rejected=0, nonplanar=0)
        rotation, translation = pose[:3, :3], pose[:3, 3]
        bounded = _bounded(pose_covariance)
        for surface in surfaces:
            if surface.n_vertices == 0:
                continue
            points = _to_world(surface.vertices, rotation, translation)
            if not np.isfinite(surface.plane).all():
                counts["nonplanar"] += 1
                if self.nonplanar == "keep":
                    self.others.append(_moved(surface, points, rotation))
                continue
            normal = rotation @ surface.plane[:3]
            plane = np.empty(4)
            plane[:3], plane[3] = normal, surface.plane[3] - normal @ translation
            plane /= math.sqrt(normal @ normal)
            observations = _observations(surface, points, plane[:3], bounded)
            self._merge(plane, observations, frame, counts)
        self._poses.append(pose[:3])
        self._timestamps.append(float(frame if timestamp is None else timestamp))
        step = MergeStep(frame=frame, **counts)
        # Field by field: `dataclasses.astuple` copies each value deeply, ten times as slow.
        self._history.append(tuple(getattr(step, name) for name in _STEP_FIELDS))
        return step

    def align(self, surfaces: list[Surface], T_world_sensor: ArrayLike, covariance: ArrayLike) -> ModelAlignment:
        """Correct a frame's pose by its planar surfaces' fit to the model's patches (plane-based loop closure).

        Each planar surface that continues a patch (the tests of `add_frame`)
        pulls the pose so that its points lie on the patch's fitted plane;
        the pull of a patch is weighed by the points' own noise and by how
        well the patch is placed (the registration variance of what was fused
        into it), and the correction is the maximum a posteriori step with
        the pose's covariance as prior. The covariance it leaves does not
        count the patches as independent of the pose, though: the same
        drifting sensor placed them, and drift being a random walk, the
        pose's error holds the error of the poses that placed them. Their
        share of the pose's variance along their normals (``shared``, the
        median over the matched planes) stays, and the planes shrink only
        the rest: ``shared P + inv(inv((1 - shared) P) + planes' information)``.
        So a patch built long ago by a well-placed sensor pulls a drifted
        pose back and shrinks its covariance, while patches built just now by
        the same drifting frames cannot make it look more certain than the
        map is. A correction the prior rules out (squared Mahalanobis distance
        above 20: planes matched to the wrong patches) is not applied.

        Parameters
        ----------
        surfaces : list of Surface
            The frame's surfaces (sensor frame), as for `add_frame`.
        T_world_sensor : (4, 4) array
            The tracked pose.
        covariance : (6, 6) array
            Its covariance (rotation vector, translation; left perturbation, world).

        Returns
        -------
        ModelAlignment
        """
        pose = check_rigid_transform(T_world_sensor, "T_world_sensor")
        prior = np.asarray(covariance, dtype=np.float64)
        if prior.shape != (6, 6) or np.isnan(prior).any():
            raise ValueError(f"covariance must be a 6x6 matrix without NaN, got shape {prior.shape}")
        unchanged = ModelAlignment(pose.copy(), prior.copy(), 0, 0.0, False)
        if not self.patches or self.cell_size is None:
            return unchanged
        bounded = _bounded(prior)
        rotation, translation = pose[:3, :3], pose[:3, 3]
        pairs, shares = [], []
        for surface in surfaces:
            if surface.n_vertices < _ALIGN_MIN_VERTICES or not np.isfinite(surface.plane).all():
                continue
            points = _to_world(surface.vertices, rotation, translation)
            normal = rotation @ surface.plane[:3]
            normal = normal / np.linalg.norm(normal)
            plane = np.append(normal, -normal @ points.mean(axis=0))
            observations = _observations(surface, points, normal, bounded)
            candidates = self._candidates(plane, points, self._reach(observations.reach_variance()))
            if not candidates:
                continue
            patch = self.patches[max(candidates)[1]]
            step = max(1, len(points) // _ALIGN_POINTS)
            # Medians over about `_MEDIAN_SAMPLE` cells and points, as the reach's (a patch may have tens of
            # thousands of cells, and the median over all of them took a fifth of the alignment's time).
            every = max(1, patch.n_cells // _MEDIAN_SAMPLE)
            placed = float(np.median(patch.sums["registration"][::every] / patch.sums["weight"][::every]))
            # The patch's error is the error its placing poses shared with this one (the drift's random walk):
            # counted as independent in the covariance, patches built by the same drifting frames shrank it at
            # every alignment while the error stayed (simulated SR-3000 arena, 200 frames, odometry seeds 5-8:
            # +-2 sigma held 47-60 % of the last third's errors along the normals, the pose's normalised squared
            # error 38-49 for 6 expected; with the share kept, 99.6-100 % and 4.2-5.2).
            sample = max(1, len(points) // _MEDIAN_SAMPLE)
            shares.append(placed / max(float(np.median(observations.registration[::sample])), 1e-30))
            pairs.append((points[::step], observations.noise[::step] + observations.fit[::step], placed, patch.world_plane()))
        if len(pairs) < 2:
            return ModelAlignment(pose.copy(), prior.copy(), len(pairs), 0.0, False)
        prior_information = np.linalg.inv(bounded)
        delta = np.zeros(6)
        for _ in range(3):
            # Gauss-Newton on sum_i w_i r_i(delta)^2 + delta' P delta, r_i the distance of point i moved by
            # the left perturbation delta from its patch's plane, weighed by the points' noise and the
            # patch's registration variance as if independent of the pose's error.
            planes_information, gradient = _plane_terms(pairs, delta, with_placement=True)
            step = np.linalg.solve(prior_information + planes_information, -(prior_information @ delta + gradient))
            delta = delta + step
            if np.abs(step).max() < 1e-9:
                break
        distance = float(delta @ prior_information @ delta)
        if distance > _ALIGN_GATE:
            return ModelAlignment(pose.copy(), prior.copy(), len(pairs), distance, False)
        # The covariance it leaves: the patches' share of the pose's variance stays; the planes measure only the
        # rest. (The pull itself is left as strong as an independent map would make it: the step this model
        # gives -- prior (1 - share) P, the points' noise alone -- pulls less, and the model came out further
        # from the truth: 600-frame SR-3000 arena runs, odometry seeds 5-7, median distance of the model to the
        # true planes 7.3-7.7 mm against 5.6, the covariance as well calibrated.)
        shared = min(float(np.median(shares)), _ALIGN_MAX_SHARED)
        planes_information, _ = _plane_terms(pairs, delta, with_placement=False)
        covariance = shared * bounded + np.linalg.inv(np.linalg.inv((1.0 - shared) * bounded) + planes_information)
        return ModelAlignment(_exp(delta) @ pose, covariance, len(pairs), distance, True)

    def carve(self, ranges: ArrayLike, projection: PinholeProjection, T_world_sensor: ArrayLike, *,
              range_sigma: ArrayLike, covariance: ArrayLike | None = None, sigmas: float = 3.0, checks: int = 3) -> int:
        """Remove the cells a frame sees through (free-space carving); returns how many were removed.

        A wall built while the pose had slipped stands in front of or beside
        the real one; once the pose is right again (loop closure), the
        sensor looks through it at the real wall. Every cell in view is
        checked against the frame's ranges (`PlanarPatch.seen_through`): one
        seen through in ``checks`` checks in a row, by more than ``sigmas``
        standard deviations of its fused noise, the pose's and the range's
        uncertainty, with nothing fused into it in between, is removed, and
        a patch left without cells is dropped. So the model does not keep
        (or grow by) copies of what it already has, nor objects that have
        moved away. A copy hidden behind the real surface is never seen
        through and stays.

        Parameters
        ----------
        ranges : (H, W) array
            The frame's (denoised) ranges along the pixel rays, metres; NaN
            where there is no reading.
        projection : PinholeProjection
            The frame's projection.
        T_world_sensor : (4, 4) array
            The frame's pose (after registration).
        range_sigma : (H, W) array or float
            Range noise sigma, metres.
        covariance : (6, 6) array, optional
            The pose's covariance (as for `add_frame`); None: exact.
        sigmas, checks : float, int
            The evidence a removal takes.
        """
        ranges = np.asarray(ranges)
        if ranges.ndim != 2 or ranges.dtype.kind != "f":
            raise ValueError(f"ranges must be an (H, W) float image, got {ranges.dtype} of shape {ranges.shape}")
        if not isinstance(projection, PinholeProjection):
            raise TypeError(f"carve needs a PinholeProjection, got {type(projection).__name__}")
        sigma = np.broadcast_to(np.asarray(range_sigma, np.float64), ranges.shape)
        pose = check_rigid_transform(T_world_sensor, "T_world_sensor")
        pose_covariance = np.zeros((6, 6)) if covariance is None else np.asarray(covariance, np.float64)
        if pose_covariance.shape != (6, 6) or not np.isfinite(pose_covariance).all():
            # An unconstrained direction (inf) leaves the pose unable to prove anything seen through.
            if pose_covariance.shape == (6, 6) and not np.isnan(pose_covariance).any():
                return 0
            raise ValueError(f"covariance must be a 6x6 matrix without NaN, got shape {pose_covariance.shape}")
        T_sensor_world = np.linalg.inv(pose)
        intrinsics = (projection.fx, projection.fy, projection.cx, projection.cy)
        removed = 0
        for patch in self.patches:
            removed += patch.seen_through(ranges, sigma, T_sensor_world, intrinsics, pose_covariance,
                                          sigmas=sigmas, checks=checks)
        if removed:
            self.patches = [patch for patch in self.patches if patch.n_cells]
            self._table = None
            self.cells_carved += removed
        return removed

    def fold_fragments(self) -> int:
        """Fold each patch that another, larger one covers into it; returns how many were folded.

        A segment at a crease or a patch's ragged edge can come with a
        normal tens of degrees off; where the patch it belongs to had no
        cells yet, it started a patch of its own (`_covered_by` takes such
        views only over cells a patch already has). Once the larger patch
        has grown over it, the fragment is a second copy of the same
        surface, re-seen and kept on every lap of a long run: the model
        would grow with time instead of with the area seen. A patch whose
        cells lie on a larger patch's plane, `_COVERED` of them over its
        occupied cells, with normals up to `_COVER_ANGLE` apart, moves its
        cells into it (`PlanarPatch.absorb`: their sums and spread are
        kept). The frame of the fold is the last frame merged.
        """
        if len(self.patches) < 2:
            return 0
        frame = max(self.n_frames - 1, 0)
        folded = []
        # Smallest first: a fragment goes into the largest patch that covers it, never the reverse.
        for patch in sorted(self.patches, key=lambda patch: patch.n_cells):
            u, v, h = patch.cell_means()
            # A sample of 500 cells tells on-plane and covered shares to a few per cent.
            step = max(1, len(u) // 500)
            points = patch.origin + np.column_stack([u[::step], v[::step], h[::step]]) @ patch.axes
            variance = (patch.sums["noise"] + patch.sums["fit"] + patch.sums["registration"]) / patch.sums["weight"]
            reach = self._reach(float(np.median(variance)))
            covering = self._covered_by(patch.world_plane(), points, reach, larger_than=patch.n_cells, excluding=folded)
            # All but a few cells on the larger patch's plane, not merely most: a ramp patch that took in a band
            # of the floor at its foot has most cells over the floor and is still a ramp.
            if covering is not None and np.mean(np.abs(self.patches[covering].distance_to(points)) <= reach) >= _ON_PLANE:
                self.patches[covering].absorb(patch, frame)
                folded.append(patch)
        if folded:
            self.patches = [patch for patch in self.patches if all(patch is not other for other in folded)]
            self._table = None
        return len(folded)

    def _reach(self, variance: float) -> float:
        """How far (metres) observations may lie from a patch's plane and still be on it (`Observations.reach_variance`)."""
        return self.max_plane_distance or max(3.0 * math.sqrt(variance), 2.0 * self.cell_size)

    def _nearby(self, plane: np.ndarray, points: np.ndarray, reach: float, angle: float, larger_than: int = 0) -> list[int]:
        """Indices of the patches of more than ``larger_than`` cells within ``angle`` degrees of a surface's normal,
        whose box comes within touching distance of its world points and whose plane they lie on (median distance
        within reach)."""
        if not self.patches:
            return []
        if self._table is None or len(self._table.revisions) != len(self.patches):
            self._table = _PatchTable(len(self.patches))
        self._table.refresh(self.patches)
        table = self._table
        # Only patches whose box comes within touching distance: the cost per frame stays the same
        # however large the model grows.
        margin = reach + (self.bridge + 2) * self.cell_size
        nearby = _nearby_patches(points, max(1, len(points) // _MEDIAN_SAMPLE), margin, reach,
                                 np.ascontiguousarray(plane[:3], np.float64), math.cos(math.radians(angle)), larger_than,
                                 table.normals, table.lows, table.highs, table.planes, table.sizes)
        return nearby.tolist()

    def _candidates(self, plane: np.ndarray, points: np.ndarray, reach: float) -> list[tuple[int, int]]:
        """(cells touched, index) of the patches a planar surface's world points continue."""
        candidates = [(self.min_overlap, index) for index in self._nearby(plane, points, reach, self.max_normal_angle)
                      if self.patches[index].touching(points, self.bridge + 1, enough=self.min_overlap) >= self.min_overlap]
        if len(candidates) > 1:
            # Ranked by how much of the surface touches each (the first is the one it continues).
            candidates = [(self.patches[index].touching(points, self.bridge + 1), index) for _, index in candidates]
        return candidates

    def _covered_by(self, plane: np.ndarray, points: np.ndarray, reach: float, *, larger_than: int = 0,
                    excluding: list[PlanarPatch] = ()) -> int | None:
        """The index of the patch a surface with a doubtful normal merely sees again, if any.

        A small or noisy segment's fitted normal can be tens of degrees off
        while its points lie on a patch's plane, over cells the patch
        already has; it is a view of that patch, not a new surface (which
        would add a patch, and vertices, every time). Taken when, with the
        normal up to `_COVER_ANGLE` off, the points lie on the patch's plane
        and `_COVERED` of them fall into its occupied cells: a surface of
        its own meeting the patch at a crease does not lie over the patch's
        cells. Only patches of more than ``larger_than`` cells and not in
        ``excluding`` are considered (`fold_fragments`).
        """
        best, most = None, 0
        for index in self._nearby(plane, points, reach, _COVER_ANGLE, larger_than):
            patch = self.patches[index]
            if any(patch is other for other in excluding):
                continue
            inside = patch.touching(points, 0)
            if inside >= _COVERED * len(points) and inside > most:
                best, most = index, inside
        return best

    def _merge(self, plane: np.ndarray, observations: Observations, frame: int, counts: dict[str, int]) -> None:
        reach = self._reach(observations.reach_variance())
        cosine = math.cos(math.radians(self.max_normal_angle))
        candidates = self._candidates(plane, observations.points, reach)
        if not candidates:
            covering = self._covered_by(plane, observations.points, reach)
            if covering is not None:
                candidates = [(0, covering)]
        if not candidates:
            patch = PlanarPatch.from_plane(plane, observations.points, self.cell_size)
            self.patches.append(patch)
            self._table = None
            _, added, _ = patch.fuse(observations, frame)
            counts["created"] += 1
            counts["cells_added"] += added
            return
        candidates.sort(reverse=True)
        target = self.patches[candidates[0][1]]
        # The observation may bridge two patches that are one plane (then they join), or merely come
        # within the tolerances of two different ones (a floor and a ramp 13 degrees off it, each within
        # 10 degrees of a segment between them): join only patches that agree with the target itself.
        joined = [self.patches[index] for _, index in candidates[1:] if _coplanar(target, self.patches[index], cosine, reach)]
        for other in joined:
            target.absorb(other, frame)
        if joined:
            self.patches = [patch for patch in self.patches if all(patch is not other for other in joined)]
            self._table = None
            counts["joined"] += len(joined)
        updated, added, rejected = target.fuse(observations, frame, reach=reach)
        counts["fused"] += 1
        counts["cells_updated"] += updated
        counts["cells_added"] += added
        counts["rejected"] += rejected

    # ------------------------------------------------------------------
    # Output.
    # ------------------------------------------------------------------

    def surfaces(self, *, lod: bool = True) -> list[Surface]:
        """The model's surfaces (world): one per planar patch, then the kept non-planar ones.

        Parameters
        ----------
        lod : bool
            Give the patch surfaces their progressive order (`rangesurf.lod`);
            cached per patch until it changes.
        """
        self.refresh(lod=lod)
        result = []
        for label, patch in enumerate(self.patches, start=1):
            surface = self._meshes[id(patch)][2]
            surface.segment = label
            result.append(surface)
        return result + list(self.others)

    def meshed_surfaces(self) -> dict[str, Surface]:
        """The surfaces meshed so far, by a stable key, without meshing anything.

        A patch that changed since its last mesh shows that mesh until
        `refresh` (the pipeline's deferred work) makes a new one; for live
        display, where meshing on the caller's thread would break the
        frame budget.
        """
        snapshot = {}
        for patch in self.patches:
            entry = self._meshes.get(id(patch))
            if entry is not None:
                snapshot[f"p{id(patch):x}"] = entry[2]
        for surface in self.others:
            snapshot[f"o{id(surface):x}"] = surface
        return snapshot

    def stale_patches(self, *, lod: bool = True) -> list[PlanarPatch]:
        """The patches whose cached mesh is out of date, most cells first."""
        return sorted((patch for patch in self.patches if not self._fresh(patch, lod)), key=lambda patch: -patch.n_cells)

    def refresh(self, *, lod: bool = True, patches: list[PlanarPatch] | None = None, max_cells: int | None = None) -> list[PlanarPatch]:
        """Re-mesh patches (default: all stale ones) with their LOD order; returns those done.

        ``max_cells`` bounds the work (the pipeline's deferrable work per
        frame): patches that do not fit in what is left are skipped.
        Patches no longer in the model (joined into others) are ignored.
        """
        live = {id(patch) for patch in self.patches}
        self._meshes = {key: value for key, value in self._meshes.items() if key in live}
        done, cells = [], 0
        for patch in self.stale_patches(lod=lod) if patches is None else patches:
            if id(patch) not in live or self._fresh(patch, lod):
                continue
            if max_cells is not None and cells + patch.n_cells > max_cells:
                continue
            surface = patch.surface(bridge=self.bridge, label=0)
            if lod and surface.n_vertices:
                surface.lod_order, surface.lod_error = progressive_order(surface)
            self._meshes[id(patch)] = (patch.revision, lod, surface)
            done.append(patch)
            cells += patch.n_cells
        return done

    def _fresh(self, patch: PlanarPatch, lod: bool) -> bool:
        cached = self._meshes.get(id(patch))
        return cached is not None and cached[0] == patch.revision and (cached[1] or not lod)

    # ------------------------------------------------------------------
    # Persistence.
    # ------------------------------------------------------------------

    def save(self, path: str | os.PathLike) -> Path:
        """Write the whole model to one ``.npz`` file, atomically (temporary file, then rename).

        A crash during the write leaves the previous checkpoint in place.
        """
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"model checkpoints are .npz files, got {path.name!r}")
        with atomic_path(path) as temporary:
            np.savez(temporary, **self.to_arrays())
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> GlobalModel:
        """Read a model written by `save`.

        Raises
        ------
        FormatError
            The file is not a rangesurf model checkpoint (naming the field).
        """
        path = Path(path)
        return cls.from_arrays(load_arrays(path), source=path)

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """The model as named arrays (what `save` writes; ``prefix`` lets it share a file)."""
        settings = dict(
            cell_size=self.cell_size, max_normal_angle=self.max_normal_angle, max_plane_distance=self.max_plane_distance,
            bridge=self.bridge, min_overlap=self.min_overlap, nonplanar=self.nonplanar,
        )
        arrays: dict[str, np.ndarray] = {
            "format_version": np.array(_FORMAT_VERSION),
            "settings": np.array(json.dumps(settings)),
            "history": self._history.values.copy(),
            "poses": self.poses,
            "timestamps": self.timestamps.copy(),
            "cells_carved": np.array(self.cells_carved),
            "patch_origins": np.asarray([patch.origin for patch in self.patches], np.float64).reshape(-1, 3),
            "patch_axes": np.asarray([patch.axes for patch in self.patches], np.float64).reshape(-1, 3, 3),
            "patch_cell_sizes": np.asarray([patch.cell_size for patch in self.patches], np.float64),
            "patch_moments": np.asarray([patch.moments for patch in self.patches], np.float64).reshape(-1, 9),
            "patch_cells": np.cumsum([0] + [patch.n_cells for patch in self.patches]).astype(np.int64),
            "patch_frame_run_counts": np.cumsum([0] + [len(patch.frame_runs) for patch in self.patches]).astype(np.int64),
            "cell_coordinates": np.concatenate([patch.coordinates for patch in self.patches]).astype(np.int32)
            if self.patches else np.zeros((0, 2), np.int32),
            "patch_frame_runs": np.concatenate([patch.frame_runs for patch in self.patches]).astype(np.int64)
            if self.patches else np.zeros((0, 2), np.int64),
            "n_others": np.array(len(self.others)),
        }
        for name in CELL_FIELDS:
            arrays[f"cells_{name}"] = _concatenate([patch.sums[name] for patch in self.patches], np.float64)
        arrays["cells_misses"] = _concatenate([patch.misses for patch in self.patches], np.int32)
        for index, surface in enumerate(self.others):
            for name in ("vertices", "faces", "normals", "pixels", "plane"):
                arrays[f"other{index}_{name}"] = getattr(surface, name)
            arrays[f"other{index}_segment"] = np.array(surface.segment)
            for level, values in surface.uncertainty.items():
                arrays[f"other{index}_uncertainty_{level}"] = values
        return {prefix + name: value for name, value in arrays.items()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], *, prefix: str = "", source: str | os.PathLike = "model") -> GlobalModel:
        """Rebuild a model from `to_arrays` output; a missing or inconsistent field is a FormatError."""

        def field(name: str) -> np.ndarray:
            if prefix + name not in arrays:
                raise FormatError(source, "missing from the model checkpoint", where=f"field {prefix + name!r}")
            return arrays[prefix + name]

        version = int(field("format_version"))
        if version not in _READABLE_VERSIONS:
            raise FormatError(source, f"model format version {version}, this rangesurf reads "
                              f"{' and '.join(map(str, _READABLE_VERSIONS))}",
                              where=f"field {prefix + 'format_version'!r}")
        model = cls(**json.loads(str(field("settings"))))
        poses, timestamps, history = field("poses"), field("timestamps"), field("history")
        width = len(fields(MergeStep))
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or history.ndim != 2 or history.shape[1] != width:
            raise FormatError(source, f"poses {poses.shape} and history {history.shape} are not (N, 4, 4) and (N, {width})",
                              where=f"field {prefix + 'poses'!r}")
        if not (len(timestamps) == len(poses) == len(history)):
            raise FormatError(source, f"{len(poses)} poses, {len(timestamps)} timestamps and "
                              f"{len(history)} history entries disagree", where=f"field {prefix + 'poses'!r}")
        model._poses.extend(poses[:, :3])
        model._timestamps.extend(timestamps)
        model._history.extend(history)
        model.cells_carved = int(field("cells_carved"))
        misses = field("cells_misses")
        cells, coordinates = field("patch_cells"), field("cell_coordinates")
        if version == 2:
            lists, list_counts = field("patch_frames"), field("patch_frame_counts")
            runs = [runs_of(lists[int(start) : int(end)]) for start, end in zip(list_counts[:-1], list_counts[1:])]
            run_counts = np.cumsum([0] + [len(patch_runs) for patch_runs in runs])
            frame_runs = np.concatenate(runs) if runs else np.zeros((0, 2), np.int64)
        else:
            frame_runs, run_counts = field("patch_frame_runs"), field("patch_frame_run_counts")
            if frame_runs.ndim != 2 or frame_runs.shape[1] != 2:
                raise FormatError(source, f"patch frame runs have shape {frame_runs.shape}, expected (R, 2)",
                                  where=f"field {prefix + 'patch_frame_runs'!r}")
        sums = {name: field(f"cells_{name}") for name in CELL_FIELDS}
        patch_fields = zip(field("patch_origins"), field("patch_axes"), field("patch_cell_sizes"), field("patch_moments"))
        for index, (origin, axes, cell_size, moments) in enumerate(patch_fields):
            cell_slice = slice(int(cells[index]), int(cells[index + 1]))
            model.patches.append(PlanarPatch(
                origin=origin, axes=axes, cell_size=float(cell_size), coordinates=coordinates[cell_slice], moments=moments,
                sums={name: values[cell_slice].copy() for name, values in sums.items()}, misses=misses[cell_slice],
                frame_runs=frame_runs[int(run_counts[index]) : int(run_counts[index + 1])],
            ))
        for index in range(int(field("n_others"))):
            uncertainty = {level: field(f"other{index}_uncertainty_{level}") for level in ("UL1", "UL2", "UL3", "UL4")
                           if f"{prefix}other{index}_uncertainty_{level}" in arrays}
            model.others.append(Surface(
                *(field(f"other{index}_{name}") for name in ("vertices", "faces", "normals", "pixels")),
                plane=field(f"other{index}_plane"), segment=int(field(f"other{index}_segment")), uncertainty=uncertainty,
            ))
        return model


def _coplanar(patch: PlanarPatch, other: PlanarPatch, cosine: float, reach: float) -> bool:
    """Whether two patches' fitted planes agree: normals within the angle, the other's cells within reach of the plane."""
    plane, other_plane = patch.world_plane(), other.world_plane()
    if plane[:3] @ other_plane[:3] < cosine:
        return False
    u, v, h = other.cell_means()
    step = max(1, len(u) // _MEDIAN_SAMPLE)
    points = other.origin + np.column_stack([u[::step], v[::step], h[::step]]) @ other.axes
    return bool(np.median(patch.distance_to(points)) <= reach)


def _concatenate(parts: list[np.ndarray], dtype: type) -> np.ndarray:
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)


def _default_cell_size(surfaces: list[Surface]) -> float:
    """Median length of the surfaces' edges (their vertex spacing), at least 5 mm."""
    lengths = []
    for surface in surfaces:
        if surface.n_faces:
            corners = surface.vertices[surface.faces[:, :2]].astype(np.float64)
            lengths.append(np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1))
    if not lengths:
        return 0.01
    return max(float(np.median(np.concatenate(lengths))), 0.005)


def _plane_terms(pairs: list, delta: np.ndarray, *, with_placement: bool) -> tuple[np.ndarray, np.ndarray]:
    """J^T W J and J^T W r of a frame's points against their patches' planes, the pose moved by ``delta``.

    ``pairs``: (world points, their noise variances, the patch's registration variance, its world plane).
    The points of one plane share the frame's smoothed noise: together they count as _ALIGN_INDEPENDENT
    points. ``with_placement``: the patch's registration variance adds to the points' (as if independent).
    """
    moved_pose = _exp(delta)
    information, gradient = np.zeros((6, 6)), np.zeros(6)
    for points, variance, placed, patch_plane in pairs:
        _add_plane_terms(points, variance, placed if with_placement else 0.0, patch_plane, moved_pose,
                         min(1.0, _ALIGN_INDEPENDENT / len(points)), information, gradient)
    return information, gradient


@numba.njit(**_JIT)
def _add_plane_terms(points, variance, placed, plane, pose, share, information, gradient):  # pragma: no cover - compiled
    """Add one plane's J^T W J and J^T W r to ``information`` and ``gradient`` (`_plane_terms`): J = [p x n, n]
    and r = n . p + d of each point p moved by ``pose``, weight ``share / (variance + placed)``."""
    nx, ny, nz, offset = plane[0], plane[1], plane[2], plane[3]
    row = np.empty(6)
    for k in range(points.shape[0]):
        x, y, z = points[k, 0], points[k, 1], points[k, 2]
        mx = pose[0, 0] * x + pose[0, 1] * y + pose[0, 2] * z + pose[0, 3]
        my = pose[1, 0] * x + pose[1, 1] * y + pose[1, 2] * z + pose[1, 3]
        mz = pose[2, 0] * x + pose[2, 1] * y + pose[2, 2] * z + pose[2, 3]
        residual = mx * nx + my * ny + mz * nz + offset
        row[0], row[1], row[2] = my * nz - mz * ny, mz * nx - mx * nz, mx * ny - my * nx
        row[3], row[4], row[5] = nx, ny, nz
        weight = share / max(variance[k] + placed, 1e-12)
        for a in range(6):
            weighted = weight * row[a]
            gradient[a] += weighted * residual
            for b in range(6):
                information[a, b] += weighted * row[b]


def _bounded(covariance: np.ndarray | None) -> np.ndarray:
    """A pose covariance for `_observations`: unconstrained directions of a degenerate registration (inf) count
    as 100 m (rad) standard deviations (vertices they move get next to no weight, vertices they do not move are
    unaffected); no covariance, an exact pose."""
    return np.zeros((6, 6)) if covariance is None else np.where(np.isfinite(covariance), covariance, _UNCONSTRAINED_VARIANCE)


def _observations(surface: Surface, points: np.ndarray, normal: np.ndarray, bounded: np.ndarray) -> Observations:
    """A surface's world points with their noise, fit and registration variances along ``normal``; ``bounded``
    is the pose's covariance (`_bounded`)."""
    empty = np.zeros(0, np.float32)
    points = np.ascontiguousarray(points, np.float64)
    noise, fit, registration, median = _variances(
        points, surface.uncertainty.get("UL1", empty), surface.uncertainty.get("UL2", empty),
        np.asarray(normal, np.float64), bounded)
    return Observations(points, noise, fit, registration, median)


def _moved(surface: Surface, points: np.ndarray, rotation: np.ndarray) -> Surface:
    return Surface(
        vertices=points, faces=surface.faces, normals=surface.normals.astype(np.float64) @ rotation.T,
        pixels=surface.pixels, plane=surface.plane, segment=surface.segment,
        uncertainty={level: values.copy() for level, values in surface.uncertainty.items()},
    )


@numba.njit(**_JIT)
def _variances(points, ul1, ul2, normal, covariance):  # pragma: no cover - compiled
    """Per point, the noise (UL1^2), fit (UL2^2) and registration variances along ``normal`` (an absent
    level -- an empty array -- or a NaN counts as 0), and the median of noise plus registration over about
    `_MEDIAN_SAMPLE` of the points (`Observations.reach_variance`)."""
    count = points.shape[0]
    noise, fit, registration = np.zeros(count), np.zeros(count), np.zeros(count)
    form = normal_variance_form(normal[0], normal[1], normal[2], covariance)
    for k in range(count):
        if len(ul1) and ul1[k] == ul1[k]:
            noise[k] = np.float64(ul1[k]) ** 2
        if len(ul2) and ul2[k] == ul2[k]:
            fit[k] = np.float64(ul2[k]) ** 2
        registration[k] = max(variance_along(points[k, 0], points[k, 1], points[k, 2], form), 0.0)
    step = max(1, count // _MEDIAN_SAMPLE)
    median = np.median(noise[::step] + registration[::step]) if count else 0.0
    return noise, fit, registration, median


@numba.njit(**_JIT)
def _to_world(vertices, rotation, translation):  # pragma: no cover - compiled
    """``vertices @ rotation.T + translation`` in float64, in one pass (a 640x480 frame's 76,000 vertices, timed
    alone: 0.2 ms against NumPy's 2.6 with its float64 copy and temporaries)."""
    world = np.empty((vertices.shape[0], 3))
    for k in range(vertices.shape[0]):
        x, y, z = np.float64(vertices[k, 0]), np.float64(vertices[k, 1]), np.float64(vertices[k, 2])
        for axis in range(3):
            world[k, axis] = rotation[axis, 0] * x + rotation[axis, 1] * y + rotation[axis, 2] * z + translation[axis]
    return world


@numba.njit(**_JIT)
def _bounding_box(points):  # pragma: no cover - compiled
    """(low, high) corners of (N, 3) points, N >= 1; one pass (NumPy's min over axis 0 of a narrow array is slow)."""
    low = points[0].copy()
    high = points[0].copy()
    for k in range(1, points.shape[0]):
        for axis in range(3):
            value = points[k, axis]
            if value < low[axis]:
                low[axis] = value
            elif value > high[axis]:
                high[axis] = value
    return low, high


@numba.njit(**_JIT)
def _nearby_patches(points, step, margin, reach, normal, cosine, larger_than, normals, lows, highs, planes, sizes):  # pragma: no cover - compiled
    """`GlobalModel._nearby` on a `_PatchTable`'s arrays: indices of the patches of more than ``larger_than``
    cells whose normal is within ``cosine`` of ``normal``, whose box comes within ``margin`` of the (N, 3)
    points' box and whose plane every ``step``-th point lies on (median distance within ``reach``)."""
    low, high = _bounding_box(points)
    nearby = np.empty(normals.shape[0], np.int64)
    found = 0
    for index in range(normals.shape[0]):
        if not normals[index, 0] * normal[0] + normals[index, 1] * normal[1] + normals[index, 2] * normal[2] >= cosine:
            continue
        if sizes[index] <= larger_than:
            continue
        apart = False
        for axis in range(3):
            apart |= (lows[index, axis] > high[axis] + margin) | (highs[index, axis] < low[axis] - margin)
        if apart:
            continue
        if _median_distance(points, step, planes[index]) <= reach:
            nearby[found] = index
            found += 1
    return nearby[:found]


@numba.njit(**_JIT)
def _median_distance(points, step, plane):  # pragma: no cover - compiled
    """Median distance of every ``step``-th of the (N, 3) points from ``plane`` (unit normal, offset)."""
    sample = points[::step]
    distance = np.empty(sample.shape[0])
    for k in range(sample.shape[0]):
        distance[k] = abs(sample[k, 0] * plane[0] + sample[k, 1] * plane[1] + sample[k, 2] * plane[2] + plane[3])
    return np.median(distance)
