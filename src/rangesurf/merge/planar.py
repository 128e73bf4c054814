"""Fusion of planar surfaces seen in many frames into one patch per plane (thesis Section 3.3).

A `PlanarPatch` is a plane with a fixed frame (origin and axes u, v, n in
world coordinates) and a regular grid of cells over it. Every observed
vertex falls into one cell, and each cell keeps uncertainty-weighted sums of
what fell into it: the in-plane position, the height along n, its square,
and the noise, fit and registration variances. So:

* vertices seen again are **averaged** with their counterparts, weighted by
  their inverse variance (the thesis: "averaging close vertices");
* vertices with no counterpart **add** new cells;
* overlap leaves no double layer and needs no clipping (Turk & Levoy's
  zippering), because two observations of one spot share a cell;
* the vertex count grows with the surface area seen, never with the number
  of frames;
* small gaps between neighbouring parts (up to ``bridge`` cells) are closed
  when the mesh is made (Soucy & Laurendeau's joining of neighbours), with
  vertices on the fitted plane whose uncertainty says they were not seen.

The patch's mesh is a grid triangulation of its occupied cells, made on
demand (`PlanarPatch.surface`), with the per-vertex uncertainty levels
UL1 (fused sensor noise), UL2 (patch fit) and UL3 (registration and the
disagreement of the fused observations).

References
----------
.. [1] G. Turk and M. Levoy, "Zippered polygon meshes from range images",
   SIGGRAPH 1994.
.. [2] M. Soucy and D. Laurendeau, "A general surface approach to the
   integration of a set of range views", IEEE TPAMI 17(4), 1995.
.. [3] The reference thesis, Section 3.3 (``shared/reference/thesis.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numba
import numpy as np
from numpy.typing import ArrayLike

from rangesurf._growing import GrowingArray
from rangesurf._tilegrid import TILE, TILE_SHIFT, CellIndex, block_of, find
from rangesurf.mesh import Surface, _grid_faces

__all__ = ["PlanarPatch", "Observations", "CELL_FIELDS", "runs_of"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")
# A plane fit's pivot this small against the largest moment: the cells are collinear (`_fitted_planes`).
_SINGULAR = 1e-12
# How many observations the sensor model's noise prediction is worth against a cell's measured scatter.
_PRIOR_OBSERVATIONS = 2.0
# One sigma of patch-fit error per metre a fused vertex lies off its patch's plane (beyond its noise).
_OFF_PLANE_SIGMA = 0.5

# Per-cell sums, all weighted by the observation weight w = 1 / (total variance) except `information`
# (sum of 1 / sensor variance) and `count`. `_fuse_points` writes them by position, in this order.
CELL_FIELDS = ("weight", "u", "v", "h", "hh", "noise", "fit", "registration", "information", "count")


def _capacity_for(needed: int, capacity: int) -> int:
    """Cell storage for ``needed`` cells, grown from ``capacity`` by quarters.

    Not by doubling: a large patch that outgrows its storage late in a long
    run would double its memory for a few new cells; a quarter keeps the
    slack (and the resident memory's steps) small at amortized constant cost.
    """
    capacity = max(capacity, 64)
    while capacity < needed:
        capacity += capacity // 4
    return capacity


def runs_of(frames: ArrayLike) -> np.ndarray:
    """Runs of consecutive values in sorted, distinct frame numbers: (R, 2) first and last of each.

    >>> runs_of([3, 4, 5, 9, 11, 12]).tolist()
    [[3, 5], [9, 9], [11, 12]]
    """
    frames = np.asarray(frames, np.int64).reshape(-1)
    if not len(frames):
        return np.zeros((0, 2), np.int64)
    breaks = np.flatnonzero(np.diff(frames) != 1) + 1
    return np.column_stack([frames[np.r_[0, breaks]], frames[np.r_[breaks - 1, len(frames) - 1]]])


@dataclass
class Observations:
    """Vertices of one frame's surface on their way into a patch (world frame).

    Parameters
    ----------
    points : (N, 3) float64
        World coordinates.
    noise, fit, registration : (N,) float64
        Variances (m^2) along the normal: sensor noise (UL1 squared), patch
        fit (UL2 squared), registration (from the pose covariance).
    """

    points: np.ndarray
    noise: np.ndarray
    fit: np.ndarray
    registration: np.ndarray
    _median: float | None = field(default=None, repr=False)

    @property
    def variance(self) -> np.ndarray:
        return self.noise + self.fit + self.registration

    def reach_variance(self) -> float:
        """The median over the points of the variance (m^2) of where a point of this surface lies off its true
        plane: sensor noise and registration.

        The fit's (UL2) is left out: it measures how far the surface is from being a plane, and a segment that
        took in points of a neighbouring surface (a floor grown into a ramp across a shallow crease) would
        otherwise stretch the reach its points join a patch by (`GlobalModel`) to 10-20 cm, and the patch's
        plane would tilt toward the other surface.
        """
        if self._median is None:
            self._median = float(np.median(self.noise + self.registration)) if len(self.points) else 0.0
        return self._median


@dataclass
class PlanarPatch:
    """One planar surface of the global model: a plane frame and the cells observed on it.

    Parameters
    ----------
    origin : (3,) float64
        A point of the plane (world).
    axes : (3, 3) float64
        Rows u, v, n: in-plane axes and the normal (world, right-handed);
        the normal faces the sensor that first saw the patch.
    cell_size : float
        Grid spacing in metres.
    coordinates : (K, 2) int32
        Grid column (along u) and row (along v) of each occupied cell, in
        the order the cells were first seen.
    sums : dict of str -> (K,) float64
        The per-cell sums of `CELL_FIELDS` (the columns of one
        ``(K, len(CELL_FIELDS))`` array, `cells`; ``sums`` gives views).
    frame_runs : (R, 2) int64
        Frames that contributed, as runs of consecutive frames: the first
        and last frame of each run, in order (a list of pairs is accepted).
        A patch in view is fused frame after frame, so a few runs stand for
        thousands of frames; `frames` lists them one by one.
    moments : (9,) float64, optional
        Plane-fit sums of everything fused (from the cell means when omitted).
    misses : (K,) int32, optional
        Per cell, the free-space checks in a row that saw through it
        (`seen_through`); zeros when omitted.
    """

    origin: np.ndarray
    axes: np.ndarray
    cell_size: float
    coordinates: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int32))
    sums: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    frame_runs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    moments: np.ndarray | None = None
    misses: np.ndarray | None = field(default=None, repr=False, compare=False)
    # Bumped by every change of the cells, so that meshes and plane fits made from them can be cached.
    revision: int = field(default=0, compare=False)
    _plane: tuple[int, np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False, compare=False)
    _box: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, np.float64).reshape(3)
        self.axes = np.asarray(self.axes, np.float64).reshape(3, 3)
        coordinates = np.asarray(self.coordinates, np.int32).reshape(-1, 2)
        count = len(coordinates)
        # Cell storage grows by a quarter when full (`_grow`); a tiled index finds a cell's row from its grid
        # coordinates (`rangesurf._tilegrid`).
        capacity = _capacity_for(count, 0)
        self._coords = np.zeros((capacity, 3), np.int32)
        self._coords[:count, :2] = coordinates
        self._cells = np.zeros((capacity, len(CELL_FIELDS)))
        for index, name in enumerate(CELL_FIELDS):
            values = np.asarray(self.sums.get(name, np.zeros(count)), np.float64).reshape(-1)
            if len(values) != count:
                raise ValueError(f"patch cell field {name!r} has {len(values)} values for {count} cells")
            self._cells[:count, index] = values
        self._count = count
        self._index = CellIndex.of(coordinates)
        self._stamps = np.zeros(capacity, np.int64)
        self._stamp = 0
        self._frame_runs = GrowingArray((2,), np.int64, rows=self.frame_runs)
        self._misses = np.zeros(capacity, np.int32)
        if self.misses is not None:
            misses = np.asarray(self.misses, np.int32).reshape(-1)
            if len(misses) != count:
                raise ValueError(f"patch misses has {len(misses)} values for {count} cells")
            self._misses[:count] = misses
        self._views()
        if self.moments is None:
            # Weighted sums (w, wu, wv, wh, wuu, wuv, wvv, wuh, wvh) of everything fused, for the plane
            # fit in constant time; from the cell means when not given.
            self.moments = np.zeros(9)
            if count:
                u, v, h = self.cell_means()
                self.moments = _moments(self.sums["weight"], u, v, h)
        self.moments = np.asarray(self.moments, np.float64).reshape(9)

    def _views(self) -> None:
        """Point `coordinates`, `cells` and `sums` at the used rows (after they move or grow)."""
        self.coordinates = self._coords[: self._count, :2]
        self.cells = self._cells[: self._count]
        self.misses = self._misses[: self._count]
        self.frame_runs = self._frame_runs.values
        self.sums = {name: self.cells[:, index] for index, name in enumerate(CELL_FIELDS)}

    def _grow(self, needed: int) -> None:
        if needed <= len(self._coords):
            return
        capacity = _capacity_for(needed, len(self._coords))
        for name in ("_coords", "_cells", "_stamps", "_misses"):
            old = getattr(self, name)
            grown = np.zeros((capacity,) + old.shape[1:], old.dtype)
            grown[: self._count] = old[: self._count]
            setattr(self, name, grown)
        self._views()

    def _make_room(self, column: int, row: int) -> None:
        """Room for one more cell, at (column, row): storage and index."""
        self._grow(self._count + 1)
        self._index.make_room(column, row)

    @classmethod
    def from_plane(cls, plane: np.ndarray, points: np.ndarray, cell_size: float) -> PlanarPatch:
        """An empty patch on ``plane`` (world, ``n . p + d = 0``, n facing the sensor), centred on ``points``."""
        normal = np.asarray(plane[:3], np.float64)
        scale = np.linalg.norm(normal)
        normal, offset = normal / scale, float(plane[3]) / scale
        centre = points.mean(axis=0)
        origin = centre - (normal @ centre + offset) * normal
        # u horizontal where possible (world z up), so that walls have rows along the vertical.
        helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        u = np.cross(helper, normal)
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        return cls(origin=origin, axes=np.vstack([u, v, normal]), cell_size=float(cell_size))

    # ------------------------------------------------------------------
    # Geometry.
    # ------------------------------------------------------------------

    @property
    def n_cells(self) -> int:
        return self._count

    @property
    def frames(self) -> np.ndarray:
        """The frames that contributed, one by one, (F,) int64 (from `frame_runs`)."""
        first, last = self.frame_runs[:, 0], self.frame_runs[:, 1]
        lengths = last - first + 1
        return np.repeat(first - np.cumsum(lengths) + lengths, lengths) + np.arange(lengths.sum())

    @property
    def normal(self) -> np.ndarray:
        return self.axes[2]

    def local(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points as (u, v, h) in the patch frame."""
        return (np.asarray(points, np.float64) - self.origin) @ self.axes.T

    def cell_means(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fused (u, v, h) of every cell."""
        weight = self.sums["weight"]
        return self.sums["u"] / weight, self.sums["v"] / weight, self.sums["h"] / weight

    def fitted_plane(self) -> np.ndarray:
        """Height over the patch plane as ``h = a u + b v + c``, weighted least squares over everything fused: (a, b, c).

        From the running moments: constant time, however large the patch.
        """
        return self._planes()[0]

    def world_plane(self) -> np.ndarray:
        """The fitted plane in world coordinates, ``(nx, ny, nz, d)`` with the normal facing like the patch's."""
        return self._planes()[1].copy()

    def _planes(self) -> tuple[np.ndarray, np.ndarray]:
        """`fitted_plane` and `world_plane`, cached per revision: merging asks for them for every nearby patch,
        several times per surface, and a patch changes once per frame at most."""
        if self._plane is None or self._plane[0] != self.revision:
            self._plane = (self.revision, *_fitted_planes(self.moments, self.n_cells, self.axes, self.origin))
        return self._plane[1], self._plane[2]

    def occupancy(self, margin: int = 0) -> tuple[np.ndarray, int, int]:
        """Occupied cells as an image (rows v, columns u) with ``margin`` empty cells around; and its origin cell."""
        columns, rows = self.coordinates[:, 0], self.coordinates[:, 1]
        column0, row0 = int(columns.min()) - margin, int(rows.min()) - margin
        image = np.zeros((int(rows.max()) - row0 + 1 + margin, int(columns.max()) - column0 + 1 + margin), np.uint8)
        image[rows - row0, columns - column0] = 1
        return image, column0, row0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """A world axis-aligned box (low, high) around the patch's cells, each cell's square at its fused height.

        Counted from the cells when first asked for, then widened by the
        points each `fuse` brings (their box padded by a cell's diagonal:
        a cell's fused position is a mean of its points, its square lies
        within that of it) instead of counted again, which goes through every
        cell of a large patch for the few a frame touches. So it may be
        larger than the cells' own box (it does not shrink when cells are
        removed or move), never smaller: for telling whether a patch may be
        near something.
        """
        if self._box is None:
            if self.n_cells == 0:
                self._box = (self.origin.copy(), self.origin.copy())
            else:
                self._box = _cell_bounds(self._coords, self._cells, self._count, self.origin, self.axes, self.cell_size)
        return self._box

    def distance_to(self, points: np.ndarray) -> np.ndarray:
        """Distance of world points from the fitted plane."""
        plane = self.world_plane()
        return np.abs(np.asarray(points, np.float64) @ plane[:3] + plane[3])

    def touching(self, points: np.ndarray, reach: int, *, enough: int = 0) -> int:
        """How many of the points' cells are occupied, or within ``reach`` cells of an occupied one.

        With ``enough`` > 0 the count stops there (whether a surface touches
        the patch at all needs only a few points).
        """
        if self.n_cells == 0 or len(points) == 0:
            return 0
        # Index lookups around each point's cell, the occupied one first: cheaper than an occupancy image
        # of the whole patch once patches are large.
        index = self._index
        return int(_touching(np.ascontiguousarray(points, np.float64), self.origin, self.axes, self.cell_size, int(reach),
                             index.directory, index.blocks, index.tiles, int(enough)))

    # ------------------------------------------------------------------
    # Fusion.
    # ------------------------------------------------------------------

    def fuse(self, observations: Observations, frame: int, *, reach: float = np.inf) -> tuple[int, int, int]:
        """Add observed vertices to their cells; returns (cells updated, cells added, vertices left out).

        Vertices farther than ``reach`` (metres) from the patch's fitted
        plane are left out.
        """
        count = len(observations.points)
        if count == 0:
            return 0, 0, 0
        points = np.ascontiguousarray(observations.points, np.float64)
        noise, fit, registration = (np.ascontiguousarray(values, np.float64)
                                    for values in (observations.noise, observations.fit, observations.registration))
        plane = self.world_plane() if np.isfinite(reach) else np.zeros(4)
        self._stamp += 1
        updated = added = rejected = 0
        start = 0
        while start < count:
            # The kernel stops at a new cell with no room for it (storage full, or the index not reaching it);
            # room is made then (not before: a large patch seen again needs few new cells, and room for every
            # point would double it needlessly).
            start, self._count, new_updated, new_added, new_rejected, column, row = _fuse_points(
                points, noise, fit, registration, plane, float(reach), self.origin, self.axes, self.cell_size, start,
                self._coords, self._cells, self._count, self._index.directory, self._index.blocks, self._index.tiles,
                self._stamps, self._stamp, self._misses, self.moments)
            if start < count:
                self._make_room(column, row)
            updated += new_updated
            added += new_added
            rejected += new_rejected
        if self._box is not None:
            _widen_box(self._box[0], self._box[1], points, math.sqrt(2.0) * self.cell_size)
        return (*self._fused(frame, updated, added), rejected)

    def absorb(self, other: PlanarPatch, frame: int) -> tuple[int, int]:
        """Fuse another patch's cells into this one (two patches found to be one plane).

        Each of the other's cells moves, with all its sums, into the cell
        of this patch that its fused point falls in; its heights' spread is
        kept, so the disagreement (UL3) survives the move.
        """
        if other.n_cells == 0:
            return 0, 0
        u, v, h = other.cell_means()
        local = self.local(other.origin + np.column_stack([u, v, h]) @ other.axes)
        weight = other.sums["weight"]
        spread = np.maximum(other.sums["hh"] - other.sums["h"] ** 2 / weight, 0.0)
        contributions = {name: other.sums[name] for name in ("weight", "noise", "fit", "registration", "information", "count")}
        contributions.update(u=weight * local[:, 0], v=weight * local[:, 1], h=weight * local[:, 2],
                             hh=weight * local[:, 2] ** 2 + spread)
        self.moments += _moments(weight, local[:, 0], local[:, 1], local[:, 2])
        result = self._accumulate(local, contributions, frame)
        self._box = None  # counted afresh when next asked for
        self._frame_runs = GrowingArray((2,), np.int64, rows=runs_of(np.union1d(self.frames, other.frames)))
        self._views()
        return result

    def _accumulate(self, local: np.ndarray, contributions: dict[str, np.ndarray], frame: int) -> tuple[int, int]:
        """Add per-point sums to the cells the (u, v, h) points fall in; returns (cells updated, cells added)."""
        columns = np.floor(local[:, 0] / self.cell_size).astype(np.int32)
        rows = np.floor(local[:, 1] / self.cell_size).astype(np.int32)
        table = np.column_stack([contributions[name] for name in CELL_FIELDS])
        self._stamp += 1
        updated = added = 0
        start = 0
        while start < len(columns):
            # As in `fuse`: room is made when the kernel stops at a cell it has none for.
            start, self._count, new_updated, new_added = _accumulate_cells(
                columns, rows, table, start, self._coords, self._cells, self._count, self._index.directory,
                self._index.blocks, self._index.tiles, self._stamps, self._stamp, self._misses)
            updated += new_updated
            added += new_added
            if start < len(columns):
                self._make_room(columns[start], rows[start])
        return self._fused(frame, updated, added)

    def _fused(self, frame: int, updated: int, added: int) -> tuple[int, int]:
        """Book-keeping after cells changed: the frame list, views, the revision."""
        runs = self._frame_runs.values
        if len(runs) and runs[-1, 1] + 1 == frame:
            runs[-1, 1] = frame
        elif not len(runs) or runs[-1, 1] != frame:
            self._frame_runs.append((frame, frame))
        self._views()
        self.revision += 1
        return updated, added

    # ------------------------------------------------------------------
    # Free space.
    # ------------------------------------------------------------------

    def seen_through(self, ranges: np.ndarray, range_sigma: np.ndarray, T_sensor_world: np.ndarray,
                     intrinsics: tuple[float, float, float, float], pose_covariance: np.ndarray, *,
                     sigmas: float = 3.0, checks: int = 3) -> int:
        """Check the cells against one frame's ranges; remove those it and the checks before it saw through.

        A cell is seen through when the 3 x 3 pixels around its projection
        measure a surface farther than the cell: their median by more than
        ``sigmas`` standard deviations of the noise of the cell's fused
        position, the pose's uncertainty and the range noise (all along the
        cell's normal: at a grazing view the same gap proves less), and the
        nearest of them by more than two cells.
        A cell seen through in ``misses`` checks in a row, with no
        observation fused into it and no check finding the surface where the
        cell is in between, is removed: free space a well-placed sensor
        looked through (a copy of a wall built while the pose had slipped, or
        an object that has moved away).

        Parameters
        ----------
        ranges, range_sigma : (H, W) float
            The frame's ranges along each pixel's ray (NaN: no reading) and
            their noise sigmas, metres.
        T_sensor_world : (4, 4) array
            World to sensor.
        intrinsics : (fx, fy, cx, cy)
            The pinhole projection (`rangesurf.frame.PinholeProjection`).
        pose_covariance : (6, 6) array
            The frame pose's covariance (rotation vector, translation; left
            perturbation, world), finite.

        Returns
        -------
        int
            Cells removed.
        """
        if self._count == 0:
            return 0
        rotation = np.ascontiguousarray(T_sensor_world[:3, :3], np.float64)
        translation = np.ascontiguousarray(T_sensor_world[:3, 3], np.float64)
        fx, fy, cx, cy = (float(value) for value in intrinsics)
        low, high = self.bounds()
        if not _box_in_view(low, high, rotation, translation, fx, fy, cx, cy, *ranges.shape):
            return 0
        removed = _check_seen_through(self.origin, self.axes, self._cells, self._count, self._misses, rotation,
                                      translation, fx, fy, cx, cy, ranges, range_sigma, pose_covariance,
                                      float(sigmas), 2.0 * self.cell_size, int(checks))
        if removed:
            self.remove(self.misses >= checks)
        return removed

    def remove(self, cells: np.ndarray) -> None:
        """Drop the cells a boolean mask (K,) selects, and their share of the plane-fit moments."""
        cells = np.asarray(cells, bool)
        if not cells.any():
            return
        u, v, h = self.cell_means()
        self.moments -= _moments(self.sums["weight"][cells], u[cells], v[cells], h[cells])
        keep = ~cells
        count = int(keep.sum())
        for name in ("_coords", "_cells", "_stamps", "_misses"):
            array = getattr(self, name)
            array[:count] = array[: self._count][keep]
            array[count : self._count] = 0
        self._count = count
        self._index = CellIndex.of(self._coords[: self._count, :2])
        self._views()
        self.revision += 1

    # ------------------------------------------------------------------
    # Mesh.
    # ------------------------------------------------------------------

    def surface(self, *, bridge: int = 1, label: int = 0) -> Surface:
        """The patch as a triangulated `Surface` (world), one vertex per cell, with UL1-UL3.

        Parameters
        ----------
        bridge : int
            Gaps up to ``2 * bridge`` cells wide are closed (morphological
            closing of the occupied cells); the vertices filling them lie on
            the fitted plane and get UL3 = the gap's half width, since
            nothing was seen there, and the RMS UL1 and UL2 of the observed
            cells within ``bridge`` cells of them.
        label : int
            Stored as the surface's ``segment``.
        """
        if self.n_cells == 0:
            return Surface(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2)))
        image, column0, row0 = self.occupancy(margin=bridge)
        observed = image.astype(bool)
        if bridge > 0:
            kernel = np.ones((2 * bridge + 1, 2 * bridge + 1), np.uint8)
            # Zero outside: OpenCV's default border would let the erosion keep cells on the image edge.
            image = cv2.morphologyEx(image, cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        filled = image.astype(bool) & ~observed
        columns, rows = self.coordinates[:, 0], self.coordinates[:, 1]
        u, v, h = self.cell_means()
        weight = self.sums["weight"]
        spread = np.maximum(self.sums["hh"] / weight - h**2, 0.0)
        noise_mean = self.sums["noise"] / weight
        # Sensor noise of the fused height: the variance of an inverse-variance weighted mean of
        # independent observations, 1 / sum(1 / sigma_i^2), with the sigma_i the sensor model's (after
        # denoising) -- raised where the observations of this cell scatter more than the model predicts
        # for them: the model's prediction counts as _PRIOR_OBSERVATIONS observations, the measured
        # spread (unbiased: n / (n - 1) times the weighted spread, n - 1 degrees of freedom) as the rest.
        # Never lowered: a small scatter shows the random part of the error is small, not the part every
        # observation shares, which averaging keeps (diffusion's leftover bias: on the simulated SR-3000
        # arena, cells fused from 128 frames or more scatter 1.9 mm (median), lie 0.65 mm RMS off the true
        # plane, and a UL1 scaled down to their scatter held 58 % of those errors within +-2 UL1; this
        # rule 97 %).
        count = self.sums["count"]
        scatter = (_PRIOR_OBSERVATIONS * noise_mean + count * spread) / (_PRIOR_OBSERVATIONS + np.maximum(count - 1.0, 0.0))
        excess = np.maximum(scatter / np.maximum(noise_mean, 1e-30), 1.0)
        ul1 = np.sqrt(excess / self.sums["information"])
        a, b, c = self.fitted_plane()
        # Patch fit: a fused vertex off its patch's plane by more than its noise explains shows local
        # model error there (a rounded crease, a leftover flying pixel); half that distance counts as
        # one sigma, so that the +-2 sigma band just reaches the plane.
        off_plane = np.abs(h - (a * u + b * v + c))
        ul2 = np.sqrt(np.maximum((_OFF_PLANE_SIGMA * off_plane) ** 2 - ul1**2, 0.0))
        # Registration: the weighted mean variance of the observations' poses (world covariance, drift
        # included); merging: how much the fused heights disagree beyond what the sensor noise explains.
        ul3 = np.sqrt(self.sums["registration"] / weight + np.maximum(spread - noise_mean, 0.0))
        fill_rows, fill_columns = np.nonzero(filled)
        fill_u = (fill_columns + column0 + 0.5) * self.cell_size
        fill_v = (fill_rows + row0 + 0.5) * self.cell_size
        fill_h = a * fill_u + b * fill_v + c
        all_u, all_v, all_h = np.r_[u, fill_u], np.r_[v, fill_v], np.r_[h, fill_h]
        grid_rows = np.r_[rows - row0, fill_rows]
        grid_columns = np.r_[columns - column0, fill_columns]
        count = len(all_u)
        points = self.origin + np.column_stack([all_u, all_v, all_h]) @ self.axes
        # Grid triangulation of the cells (mesh._grid_faces with the step tests switched off).
        grid = np.full(image.shape + (3,), np.nan, np.float32)
        grid[grid_rows, grid_columns] = points
        labels = np.zeros(image.shape, np.int32)
        labels[grid_rows, grid_columns] = 1
        faces, _ = _grid_faces(grid, np.ones(image.shape, np.float32), labels, np.inf, 0.0)
        index = np.full(image.shape, -1, np.int64)
        index[grid_rows, grid_columns] = np.arange(count)
        faces = index.reshape(-1)[faces]
        if len(faces):
            corners = points[faces]
            facing = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]) @ self.normal
            faces[facing < 0] = faces[facing < 0][:, ::-1]
        gap = bridge * self.cell_size
        # A bridged vertex lies on the fitted plane but was not seen: how far the plane is from the surface
        # there is known only from the cells around the gap, so it takes their noise and fit levels (the
        # patch's median UL1 and no fit error said far too little where the plane is off the surface
        # locally: simulated SR-3000 corridor, 48 % of bridged vertices within +-2 sigma).
        fill_ul1, fill_ul2 = _levels_around(image.shape, rows - row0, columns - column0, (ul1, ul2),
                                            fill_rows, fill_columns, reach=bridge)
        uncertainty = {
            "UL1": np.r_[ul1, fill_ul1], "UL2": np.r_[ul2, fill_ul2], "UL3": np.r_[ul3, np.full(len(fill_u), gap)],
        }
        return Surface(
            vertices=points, faces=faces, normals=np.tile(self.world_plane()[:3], (count, 1)),
            pixels=np.full((count, 2), -1), plane=self.world_plane(), segment=label, uncertainty=uncertainty,
        )


def _levels_around(shape: tuple[int, int], rows: np.ndarray, columns: np.ndarray, levels: tuple[np.ndarray, ...],
                   at_rows: np.ndarray, at_columns: np.ndarray, *, reach: int) -> list[np.ndarray]:
    """Root mean square of each level over the cells within ``reach`` cells (chessboard) of given grid places.

    ``rows, columns`` place the cells whose ``levels`` (each ``(K,)``) are
    known on a grid of ``shape``; returns, per level, an ``(M,)`` array for
    the places ``at_rows, at_columns`` (0 where no known cell is in reach;
    a closing of the cells leaves none such).
    """
    window = (2 * reach + 1, 2 * reach + 1)

    def window_sums(values: np.ndarray) -> np.ndarray:
        grid = np.zeros(shape, np.float32)
        grid[rows, columns] = values
        summed = cv2.boxFilter(grid, -1, window, normalize=False, borderType=cv2.BORDER_CONSTANT)
        return summed[at_rows, at_columns].astype(np.float64)

    count = np.maximum(window_sums(np.ones(len(rows))), 1.0)
    return [np.sqrt(window_sums(np.square(level)) / count) for level in levels]


def _moments(weight: np.ndarray, u: np.ndarray, v: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(w, wu, wv, wh, wuu, wuv, wvv, wuh, wvh) summed; element-wise products, no BLAS (it can stall when threaded)."""
    wu, wv = weight * u, weight * v
    return np.array([weight.sum(), wu.sum(), wv.sum(), (weight * h).sum(), (wu * u).sum(), (wu * v).sum(),
                     (wv * v).sum(), (wu * h).sum(), (wv * h).sum()])


@numba.njit(**_JIT)
def _fitted_planes(moments, n_cells, axes, origin):  # pragma: no cover - compiled
    """`PlanarPatch.fitted_plane` (a, b, c) from the moments and the patch frame's `world_plane`, in one compiled call.

    The 3x3 normal equations are solved by Gaussian elimination with partial
    pivoting; a pivot below `_SINGULAR` of the largest entry (collinear
    cells: the tilt across them is unknown, and rounding decides what a
    solver returns) keeps the patch's own plane at the mean height. Fewer
    than three cells: that plane at height 0. (``np.linalg.solve`` and the
    arrays around it cost ten times the arithmetic.)
    """
    sw, su, sv, sh, suu, suv, svv, suh, svh = (moments[0], moments[1], moments[2], moments[3], moments[4], moments[5],
                                               moments[6], moments[7], moments[8])
    solution = np.zeros(3)
    if n_cells >= 3 and sw > 0:
        system = np.array([[suu, suv, su, suh], [suv, svv, sv, svh], [su, sv, sw, sh]])
        singular = False
        largest = 0.0
        for row in range(3):
            for column in range(3):
                largest = max(largest, abs(system[row, column]))
        for column in range(3):
            pivot = column
            for row in range(column + 1, 3):
                if abs(system[row, column]) > abs(system[pivot, column]):
                    pivot = row
            if abs(system[pivot, column]) <= _SINGULAR * largest:
                singular = True
                break
            for k in range(4):
                system[column, k], system[pivot, k] = system[pivot, k], system[column, k]
            for row in range(column + 1, 3):
                factor = system[row, column] / system[column, column]
                for k in range(column, 4):
                    system[row, k] -= factor * system[column, k]
        if singular:
            solution[2] = sh / sw
        else:
            for row in range(2, -1, -1):
                value = system[row, 3]
                for k in range(row + 1, 3):
                    value -= system[row, k] * solution[k]
                solution[row] = value / system[row, row]
    a, b, c = solution[0], solution[1], solution[2]
    # h - a u - b v - c = 0 in the patch frame.
    plane = np.empty(4)
    for axis in range(3):
        plane[axis] = -a * axes[0, axis] - b * axes[1, axis] + axes[2, axis]
    plane[3] = -c - (plane[0] * origin[0] + plane[1] * origin[1] + plane[2] * origin[2])
    norm = math.sqrt(plane[0] * plane[0] + plane[1] * plane[1] + plane[2] * plane[2])
    for k in range(4):
        plane[k] /= norm
    return solution, plane


@numba.njit(**_JIT)
def _touching(points, origin, axes, cell_size, reach, directory, blocks, tiles, enough):  # pragma: no cover - compiled
    """Points whose cell in the patch frame has an occupied cell within ``reach`` cells (chessboard distance),
    counted up to ``enough`` (all when 0)."""
    count = 0
    for k in range(points.shape[0]):
        if count == enough > 0:
            break
        dx, dy, dz = points[k, 0] - origin[0], points[k, 1] - origin[1], points[k, 2] - origin[2]
        column = np.int32(np.floor((dx * axes[0, 0] + dy * axes[0, 1] + dz * axes[0, 2]) / cell_size))
        row = np.int32(np.floor((dx * axes[1, 0] + dy * axes[1, 1] + dz * axes[1, 2]) / cell_size))
        if find(directory, blocks, tiles, column, row) >= 0:
            count += 1
            continue
        found = False
        for di in range(-reach, reach + 1):
            for dj in range(-reach, reach + 1):
                if find(directory, blocks, tiles, column + np.int32(dj), row + np.int32(di)) >= 0:
                    found = True
                    break
            if found:
                break
        count += found
    return count


@numba.njit(**_JIT)
def _fuse_points(points, noise, fit, registration, plane, reach, origin, axes, cell_size, start, coords, cells, count,
                 directory, blocks, tiles, stamps, stamp, misses, moments):  # pragma: no cover - compiled
    """`PlanarPatch.fuse` from point ``start`` on, in one pass: each point within ``reach`` of ``plane``
    into the patch frame, its weight 1 / (total variance), its sums (the `CELL_FIELDS`) into its cell and
    the patch's plane-fit moments.

    Stops early like `_accumulate_cells` (which it mirrors, for fusion's own sums) at a new cell it has
    no room for; returns (next point, cell count, cells updated, cells added, points beyond reach, and the
    column and row of the cell it stopped at).
    """
    updated = 0
    added = 0
    rejected = 0
    # The points of a frame's surface come in scan order, so nearly always from the tile of the point before:
    # its block is kept, and the directory consulted only when the tile changes (a branch that is almost never
    # taken, where trying the previous point's cell first was one taken a third of the time, at random).
    last_tile_column, last_tile_row, block = np.int32(0), np.int32(0), -1
    # The moments are summed in registers (in the same order, so to the same bits) and stored at the end.
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = (moments[0], moments[1], moments[2], moments[3], moments[4], moments[5],
                                          moments[6], moments[7], moments[8])
    # The loop's constants as scalars: the compiler cannot keep array elements in registers across the stores
    # into the cells (for all it knows, those could change them).
    p0, p1, p2, p3 = plane[0], plane[1], plane[2], plane[3]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    a00, a01, a02 = axes[0, 0], axes[0, 1], axes[0, 2]
    a10, a11, a12 = axes[1, 0], axes[1, 1], axes[1, 2]
    a20, a21, a22 = axes[2, 0], axes[2, 1], axes[2, 2]
    stop, stop_column, stop_row = points.shape[0], np.int32(0), np.int32(0)
    for k in range(start, points.shape[0]):
        if abs(points[k, 0] * p0 + points[k, 1] * p1 + points[k, 2] * p2 + p3) > reach:
            rejected += 1
            continue
        dx, dy, dz = points[k, 0] - o0, points[k, 1] - o1, points[k, 2] - o2
        u = dx * a00 + dy * a01 + dz * a02
        v = dx * a10 + dy * a11 + dz * a12
        h = dx * a20 + dy * a21 + dz * a22
        column, row = np.int32(np.floor(u / cell_size)), np.int32(np.floor(v / cell_size))
        tile_column, tile_row = column >> TILE_SHIFT, row >> TILE_SHIFT
        if block < 0 or tile_column != last_tile_column or tile_row != last_tile_row:
            block = block_of(directory, blocks, tiles, column, row)
            last_tile_column, last_tile_row = tile_column, tile_row
        # `_slot_in`, written out: as a call (inlined or not, with one return or several) the loop took more
        # than twice as long (94 against 42 ns per point on a pipeline's calls, results the same).
        slot, is_updated, is_added = -1, 0, 0
        if block >= 0:
            slot = blocks[block, row & (TILE - 1), column & (TILE - 1)]
            if slot >= 0:
                is_updated = np.int64(stamps[slot] != stamp)
            elif count < coords.shape[0]:
                slot = count
                coords[slot, 0], coords[slot, 1], coords[slot, 2] = column, row, 0
                blocks[block, row & (TILE - 1), column & (TILE - 1)] = slot
                count += 1
                is_added = 1
            if slot >= 0:
                stamps[slot] = stamp
                misses[slot] = 0
        if slot < 0:
            stop, stop_column, stop_row = k, column, row
            break
        updated += is_updated
        added += is_added
        weight = 1.0 / max(noise[k] + fit[k] + registration[k], 1e-12)
        wu, wv, wh = weight * u, weight * v, weight * h
        cells[slot, 0] += weight
        cells[slot, 1] += wu
        cells[slot, 2] += wv
        cells[slot, 3] += wh
        cells[slot, 4] += wh * h
        cells[slot, 5] += weight * noise[k]
        cells[slot, 6] += weight * fit[k]
        cells[slot, 7] += weight * registration[k]
        cells[slot, 8] += 1.0 / max(noise[k], 1e-12)
        cells[slot, 9] += 1.0
        m0 += weight
        m1 += wu
        m2 += wv
        m3 += wh
        m4 += wu * u
        m5 += wu * v
        m6 += wv * v
        m7 += wu * h
        m8 += wv * h
    moments[0], moments[1], moments[2], moments[3], moments[4] = m0, m1, m2, m3, m4
    moments[5], moments[6], moments[7], moments[8] = m5, m6, m7, m8
    return stop, count, updated, added, rejected, stop_column, stop_row


@numba.njit(**_JIT, inline="always")
def _cell_slot(column, row, coords, count, directory, blocks, tiles, stamps, stamp, misses):  # pragma: no cover - compiled
    """The storage slot of cell (column, row), opened if new, and marked seen (`_slot_in`); -1 as the slot
    also when the index does not reach the cell."""
    block = block_of(directory, blocks, tiles, column, row)
    if block < 0:
        return -1, count, 0, 0
    return _slot_in(block, column, row, coords, count, blocks, stamps, stamp, misses)


@numba.njit(**_JIT, inline="always")
def _slot_in(block, column, row, coords, count, blocks, stamps, stamp, misses):  # pragma: no cover - compiled
    """The storage slot of cell (column, row), whose tile's block is ``block``, opened if new, and marked seen
    (``misses`` 0).

    Returns (slot, cell count, updated, added): -1 as the slot when a new
    cell finds no room (`PlanarPatch._make_room`); ``updated`` and ``added``
    are 1 when this call first touches an existing cell in this round
    (``stamp``) or opens one, else 0.
    """
    slot = blocks[block, row & (TILE - 1), column & (TILE - 1)]
    if slot < 0:
        if count >= coords.shape[0]:
            return -1, count, 0, 0
        slot = count
        coords[slot, 0], coords[slot, 1], coords[slot, 2] = column, row, 0
        blocks[block, row & (TILE - 1), column & (TILE - 1)] = slot
        stamps[slot] = stamp
        misses[slot] = 0
        return slot, count + 1, 0, 1
    updated = 0
    if stamps[slot] != stamp:
        stamps[slot] = stamp
        updated = 1
    misses[slot] = 0
    return slot, count, updated, 0


@numba.njit(**_JIT)
def _accumulate_cells(columns, rows, table, start, coords, cells, count, directory, blocks, tiles, stamps, stamp,
                      misses):  # pragma: no cover - compiled
    """Add rows of ``table`` into the cells at (column, row), opening cells as needed, from point ``start``.

    Stops early (returning where) at a new cell it has no room for; returns
    (next point, cell count, cells updated, cells added), counting each cell
    once per call (``stamp``).
    """
    updated = 0
    added = 0
    fields = table.shape[1]
    for k in range(start, columns.shape[0]):
        slot, count, is_updated, is_added = _cell_slot(columns[k], rows[k], coords, count, directory, blocks, tiles,
                                                       stamps, stamp, misses)
        if slot < 0:
            return k, count, updated, added
        updated += is_updated
        added += is_added
        for f in range(fields):
            cells[slot, f] += table[k, f]
    return columns.shape[0], count, updated, added


@numba.njit(**_JIT)
def normal_variance_form(nx, ny, nz, covariance):  # pragma: no cover - compiled
    """The pose covariance's variance along the normal n as a quadratic in the world point p (`variance_along`).

    A left perturbation (w, t) moves p by w x p + t; along n that is
    w . a + t . n with a = p x n, so the variance is J S J' with
    J = [a, n] = M p + b, linear in p: p' (M' S M) p + 2 (M' S b) . p + b' S b.
    Returned as ``(q00, q11, q22, 2 q01, 2 q02, 2 q12, 2 l0, 2 l1, 2 l2, c)``: a
    dozen products per point instead of the 42 of J S J' (merging evaluates it
    for every vertex of a frame, carving for every cell of a patch).
    """
    m = np.zeros((6, 3))
    m[0, 1], m[0, 2] = nz, -ny
    m[1, 0], m[1, 2] = -nz, nx
    m[2, 0], m[2, 1] = ny, -nx
    b = np.zeros(6)
    b[3], b[4], b[5] = nx, ny, nz
    sm = covariance @ m
    q = m.T @ sm
    linear = sm.T @ b
    return (q[0, 0], q[1, 1], q[2, 2], 2.0 * q[0, 1], 2.0 * q[0, 2], 2.0 * q[1, 2], 2.0 * linear[0], 2.0 * linear[1],
            2.0 * linear[2], b @ (covariance @ b))


@numba.njit(**_JIT, inline="always")
def variance_along(x, y, z, form):  # pragma: no cover - compiled
    """Variance along a normal of the world point (x, y, z) from a pose covariance, by `normal_variance_form`."""
    q00, q11, q22, q01, q02, q12, l0, l1, l2, c = form
    return x * (q00 * x + q01 * y + q02 * z + l0) + y * (q11 * y + q12 * z + l1) + z * (q22 * z + l2) + c


@numba.njit(**_JIT)
def _box_in_view(low, high, rotation, translation, fx, fy, cx, cy, height, width):  # pragma: no cover - compiled
    """Whether any of a world box can project into the image (False only when it surely cannot)."""
    left = top = np.inf
    right = bottom = -np.inf
    in_front = False
    for corner in range(8):
        wx = high[0] if corner & 1 else low[0]
        wy = high[1] if corner & 2 else low[1]
        wz = high[2] if corner & 4 else low[2]
        x = rotation[0, 0] * wx + rotation[0, 1] * wy + rotation[0, 2] * wz + translation[0]
        y = rotation[1, 0] * wx + rotation[1, 1] * wy + rotation[1, 2] * wz + translation[1]
        z = rotation[2, 0] * wx + rotation[2, 1] * wy + rotation[2, 2] * wz + translation[2]
        if z <= 0.0:
            # A corner at or behind the sensor: the box's image is unbounded unless all of it is behind.
            left, right, top, bottom = -np.inf, np.inf, -np.inf, np.inf
            continue
        in_front = True
        column, row = fx * x / z + cx, fy * y / z + cy
        left, right = min(left, column), max(right, column)
        top, bottom = min(top, row), max(bottom, row)
    if not in_front:
        return False  # all of it behind the sensor
    return right >= 0.0 and left <= width - 1 and bottom >= 0.0 and top <= height - 1


@numba.njit(**_JIT)
def _check_seen_through(origin, axes, cells, count, misses, rotation, translation, fx, fy, cx, cy, ranges, range_sigma,
                        covariance, sigmas, floor, limit):  # pragma: no cover - compiled
    """`PlanarPatch.seen_through`'s test of every cell: updates ``misses``, returns how many reached ``limit``."""
    height, width = ranges.shape
    # The patch normal in the sensor frame (for the view angle) and in the world (for the pose's share).
    nx, ny, nz = axes[2, 0], axes[2, 1], axes[2, 2]
    snx = rotation[0, 0] * nx + rotation[0, 1] * ny + rotation[0, 2] * nz
    sny = rotation[1, 0] * nx + rotation[1, 1] * ny + rotation[1, 2] * nz
    snz = rotation[2, 0] * nx + rotation[2, 1] * ny + rotation[2, 2] * nz
    form = normal_variance_form(nx, ny, nz, covariance)
    reached = 0
    for slot in range(count):
        weight = cells[slot, 0]
        u, v, h = cells[slot, 1] / weight, cells[slot, 2] / weight, cells[slot, 3] / weight
        wx = origin[0] + u * axes[0, 0] + v * axes[1, 0] + h * axes[2, 0]
        wy = origin[1] + u * axes[0, 1] + v * axes[1, 1] + h * axes[2, 1]
        wz = origin[2] + u * axes[0, 2] + v * axes[1, 2] + h * axes[2, 2]
        x = rotation[0, 0] * wx + rotation[0, 1] * wy + rotation[0, 2] * wz + translation[0]
        y = rotation[1, 0] * wx + rotation[1, 1] * wy + rotation[1, 2] * wz + translation[1]
        z = rotation[2, 0] * wx + rotation[2, 1] * wy + rotation[2, 2] * wz + translation[2]
        if z <= 0.0:
            continue
        column = int(np.floor(fx * x / z + cx + 0.5))
        row = int(np.floor(fy * y / z + cy + 0.5))
        if column < 1 or row < 1 or column >= width - 1 or row >= height - 1:
            continue
        # The 3 x 3 pixels around the projection: their median and nearest, unless one has no reading (no
        # evidence). A sorting network, without branches: an insertion sort's were taken at random.
        r0, r1, r2 = ranges[row - 1, column - 1], ranges[row - 1, column], ranges[row - 1, column + 1]
        r3, r4, r5 = ranges[row, column - 1], ranges[row, column], ranges[row, column + 1]
        r6, r7, r8 = ranges[row + 1, column - 1], ranges[row + 1, column], ranges[row + 1, column + 1]
        if not ((r0 == r0) & (r1 == r1) & (r2 == r2) & (r3 == r3) & (r4 == r4) & (r5 == r5) & (r6 == r6) & (r7 == r7)
                & (r8 == r8)):
            continue
        median = _median_of_nine(r0, r1, r2, r3, r4, r5, r6, r7, r8)
        nearest = min(min(min(r0, r1), min(r2, r3)), min(min(r4, r5), min(r6, min(r7, r8))))
        expected = np.sqrt(x * x + y * y + z * z)
        cosine = abs(snx * x + sny * y + snz * z) / expected
        # The statistical test on the median; the nearest pixel must be behind the cell too: a cell at a
        # silhouette, beside which the sensor sees the background, has its own surface among the nine.
        gap = (median - expected) * cosine
        # The noise of the cell's fused mean, the pose's share, the range noise.
        variance = (1.0 / cells[slot, 8] + variance_along(wx, wy, wz, form)
                    + (range_sigma[row, column] * cosine) ** 2)
        tolerance = sigmas * np.sqrt(variance)
        if gap > tolerance and nearest - expected > floor:
            misses[slot] += 1
            if misses[slot] == limit:
                reached += 1
        elif abs(gap) <= tolerance:
            misses[slot] = 0  # the surface is where the cell is
    return reached


@numba.njit(**_JIT, inline="always")
def _median_of_nine(p0, p1, p2, p3, p4, p5, p6, p7, p8):  # pragma: no cover - compiled
    """The median of nine values (no NaN) by a network of 19 compare-exchanges (Paeth's; Devillard,
    "Fast median search", 1998), each a minimum and a maximum."""
    p1, p2 = min(p1, p2), max(p1, p2)
    p4, p5 = min(p4, p5), max(p4, p5)
    p7, p8 = min(p7, p8), max(p7, p8)
    p0, p1 = min(p0, p1), max(p0, p1)
    p3, p4 = min(p3, p4), max(p3, p4)
    p6, p7 = min(p6, p7), max(p6, p7)
    p1, p2 = min(p1, p2), max(p1, p2)
    p4, p5 = min(p4, p5), max(p4, p5)
    p7, p8 = min(p7, p8), max(p7, p8)
    p3 = max(p0, p3)
    p5 = min(p5, p8)
    p4, p7 = min(p4, p7), max(p4, p7)
    p6 = max(p3, p6)
    p4 = max(p1, p4)
    p2 = min(p2, p5)
    p4 = min(p4, p7)
    p4, p2 = min(p4, p2), max(p4, p2)
    p4 = max(p6, p4)
    return min(p4, p2)


@numba.njit(**_JIT)
def _widen_box(low, high, points, pad):  # pragma: no cover - compiled
    """Widen the box (low, high) in place to hold the (N, 3) points padded by ``pad``."""
    for k in range(points.shape[0]):
        for axis in range(3):
            low[axis] = min(low[axis], points[k, axis] - pad)
            high[axis] = max(high[axis], points[k, axis] + pad)


@numba.njit(**_JIT)
def _cell_bounds(coords, cells, count, origin, axes, cell_size):  # pragma: no cover - compiled
    """World axis-aligned box (low, high) around ``count`` >= 1 cells: their in-plane extent, their heights' range."""
    column_low, column_high = coords[0, 0], coords[0, 0]
    row_low, row_high = coords[0, 1], coords[0, 1]
    height_low = height_high = cells[0, 3] / cells[0, 0]
    for slot in range(1, count):
        column_low, column_high = min(column_low, coords[slot, 0]), max(column_high, coords[slot, 0])
        row_low, row_high = min(row_low, coords[slot, 1]), max(row_high, coords[slot, 1])
        height = cells[slot, 3] / cells[slot, 0]
        height_low, height_high = min(height_low, height), max(height_high, height)
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for u in (column_low * cell_size, (column_high + 1) * cell_size):
        for v in (row_low * cell_size, (row_high + 1) * cell_size):
            for h in (height_low, height_high):
                for axis in range(3):
                    corner = origin[axis] + u * axes[0, axis] + v * axes[1, axis] + h * axes[2, axis]
                    low[axis] = min(low[axis], corner)
                    high[axis] = max(high[axis], corner)
    return low, high
