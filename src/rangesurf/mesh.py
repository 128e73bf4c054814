"""Triangulated surfaces of segments (thesis Sections 2.3 and 3.1).

A range frame is already a grid, so a segment's mesh comes almost free:
every 2x2 cell whose four corners belong to the segment gives two triangles
(split along the shorter diagonal), a cell with three gives one. Triangles
across a depth step are dropped, as the thesis drops "triangles with edge
lengths higher than a previously established threshold" -- here relative to
the range, since the spacing of grid samples grows with it: an edge longer
than ``max_edge_pixels`` pixel footprints, or a triangle seen almost edge-on
(its normal more than ``max_view_angle`` from the viewing ray), is a step,
not a surface.

Irregular vertex sets (merged or decimated surfaces) are triangulated by
Delaunay in the segment's plane (the thesis's Section 3.1 also triangulates
in 2-D, disregarding depth), with triangles longer than a limit dropped so
that concave outlines and holes survive.

`boundary_loops` finds the outline and the holes of a mesh: the edges used
by one triangle only, chained into closed loops.

References
----------
.. [1] The reference thesis, Sections 2.3 and 3.1 (``shared/reference/thesis.md``).
.. [2] G. Turk and M. Levoy, "Zippered polygon meshes from range images",
   SIGGRAPH 1994 (triangulating range grids, dropping step triangles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
import numba
import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import Delaunay, QhullError

from rangesurf._checks import check_point_grid, check_range_sigma
from rangesurf._grid import pixel_pitch, ranges
from rangesurf.segment import Segmentation

__all__ = [
    "Surface", "triangulate_segments", "segment_vertices", "triangulate_in_plane", "boundary_loops", "fill_small_holes", "UNCERTAINTY_LEVELS",
]

_JIT = dict(cache=True, nogil=True, error_model="numpy")
UNCERTAINTY_LEVELS = ("UL1", "UL2", "UL3", "UL4")


@dataclass
class Surface:
    """One triangulated patch from one segment (DESIGN: data model).

    Parameters
    ----------
    vertices : (N, 3) float32
        Metres, in the frame the points were given in (the sensor frame of
        the source frame, until registration moves it).
    faces : (M, 3) int32
        Vertex indices, counter-clockwise seen from the side the normals
        face (the sensor).
    normals : (N, 3) float32
        Unit vertex normals.
    pixels : (N, 2) int32
        ``(row, column)`` of each vertex's grid origin; -1 for vertices that
        come from no pixel (merged or interpolated ones).
    plane : (4,) float64
        ``(nx, ny, nz, d)`` of the segment's plane (``n . p + d = 0``), NaN
        where the surface is not planar.
    segment : int
        Label of the segment in its frame's `Segmentation` (0 if none).
    uncertainty : dict of str -> (N,) float32
        Per-vertex uncertainty in metres along the normal, keyed by level
        (``"UL1"`` sensor, ``"UL2"`` patch fit, ``"UL3"`` registration and
        merging, ``"UL4"`` level of detail).
    lod_order : (N,) int32
        Vertex indices, most important first (`rangesurf.lod`); the identity
        until a progressive order is built.
    lod_error : (N,) float32
        Geometric error (metres) introduced when ``lod_order[k]`` is
        removed; 0 until computed.
    levels : list of rangesurf.lod.Level
        Precomputed levels of detail, finest first (`rangesurf.lod.prepare_levels`).
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    pixels: np.ndarray
    plane: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    segment: int = 0
    uncertainty: dict[str, np.ndarray] = field(default_factory=dict)
    lod_order: np.ndarray | None = None
    lod_error: np.ndarray | None = None
    levels: list = field(default_factory=list)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32).reshape(-1, 3)
        count = len(self.vertices)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32).reshape(-1, 3)
        self.normals = np.ascontiguousarray(self.normals, dtype=np.float32).reshape(-1, 3)
        self.pixels = np.ascontiguousarray(self.pixels, dtype=np.int32).reshape(-1, 2)
        self.plane = np.asarray(self.plane, dtype=np.float64).reshape(4)
        if len(self.normals) != count or len(self.pixels) != count:
            raise ValueError(
                f"surface arrays disagree: {count} vertices, {len(self.normals)} normals, {len(self.pixels)} pixels"
            )
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= count):
            raise ValueError(f"faces index vertices 0..{count - 1}, got {self.faces.min()}..{self.faces.max()}")
        for level, values in self.uncertainty.items():
            if level not in UNCERTAINTY_LEVELS:
                raise ValueError(f"uncertainty levels are {UNCERTAINTY_LEVELS}, got {level!r}")
            values = np.asarray(values, dtype=np.float32)
            if values.shape != (count,):
                raise ValueError(f"uncertainty {level} must have one value per vertex ({count}), got shape {values.shape}")
            self.uncertainty[level] = values
        self.lod_order = np.arange(count, dtype=np.int32) if self.lod_order is None else np.asarray(self.lod_order, np.int32)
        self.lod_error = np.zeros(count, np.float32) if self.lod_error is None else np.asarray(self.lod_error, np.float32)
        if self.lod_order.shape != (count,) or self.lod_error.shape != (count,):
            raise ValueError(f"lod_order and lod_error need one entry per vertex ({count})")

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def at_level(self, *, count: int | None = None, fraction: float | None = None, max_error: float | None = None) -> Surface:
        """The surface at a level of detail: the coarsest precomputed level with at least ``count``
        vertices (or ``fraction`` of them), or within ``max_error`` metres.

        The returned surface holds the kept vertices (most important first),
        the level's triangles, and the level's per-vertex error as
        uncertainty ``"UL4"``. Without precomputed levels the surface itself
        is returned.
        """
        if not self.levels:
            return self
        from rangesurf.lod import select_level

        level = select_level(self.levels, count=count, fraction=fraction, max_error=max_error)
        kept = self.lod_order[: level.count]
        uncertainty = {name: values[kept] for name, values in self.uncertainty.items()}
        uncertainty["UL4"] = level.vertex_error
        return Surface(
            vertices=self.vertices[kept], faces=level.faces, normals=self.normals[kept], pixels=self.pixels[kept],
            plane=self.plane, segment=self.segment, uncertainty=uncertainty,
            lod_order=np.arange(level.count, dtype=np.int32), lod_error=self.lod_error[: level.count],
        )

    def area(self) -> float:
        """Total triangle area in square metres."""
        if not self.n_faces:
            return 0.0
        corners = self.vertices[self.faces].astype(np.float64)
        return float(0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum())


# --------------------------------------------------------------------------
# Grid triangulation.
# --------------------------------------------------------------------------


def triangulate_segments(
    points: ArrayLike,
    segmentation: Segmentation,
    *,
    max_edge_pixels: float = 4.0,
    max_view_angle: float = 85.0,
    min_faces: int = 1,
    range_sigma: ArrayLike | None = None,
) -> list[Surface]:
    """One grid-triangulated `Surface` per segment of an organized frame.

    Parameters
    ----------
    points : (H, W, 3) float array
        Sensor-frame points (metres), NaN where invalid; the points the
        segmentation was made from.
    segmentation : Segmentation
        Labels and planes (`rangesurf.segment`).
    max_edge_pixels : float
        Longest triangle edge, in pixel footprints at the range of its
        nearer end (range times the angle between neighbouring rays): a
        longer edge spans a depth step.
    max_view_angle : float
        Degrees; triangles whose normal is farther than this from the line
        of sight are dropped (a surface seen edge-on is a step).
    min_faces : int
        Segments with fewer triangles give no surface.
    range_sigma : (H, W) float array, optional
        Range noise (metres, along the line of sight) of every pixel; each
        vertex then gets it along its normal as uncertainty ``"UL1"``.

    Returns
    -------
    list of Surface
        In label order; each surface's vertices are its segment's pixels that
        belong to a kept triangle, with the segment's plane normal (facing
        the sensor) as vertex normal where the segment is planar.

    Examples
    --------
    A 4x5 patch of a wall at 2 m: 20 vertices, 2 x 3 x 4 = 24 triangles.

    >>> import numpy as np
    >>> from rangesurf.segment import Segmentation
    >>> rows, cols = np.mgrid[0:4, 0:5].astype(np.float32)
    >>> points = np.dstack([cols * 0.01, rows * 0.01, np.full(rows.shape, 2.0, np.float32)])
    >>> labels = np.ones((4, 5), np.int32)
    >>> planes = np.array([[np.nan] * 4, [0.0, 0.0, -1.0, 2.0]])
    >>> segments = Segmentation(labels, planes, np.array([np.nan, 0.0]), np.array([0, 20]))
    >>> surface, = triangulate_segments(points, segments)
    >>> surface.n_vertices, surface.n_faces, round(surface.area(), 6)
    (20, 24, 0.0012)
    """
    points = check_point_grid(points)
    labels = np.asarray(segmentation.labels)
    if labels.shape != points.shape[:2]:
        raise ValueError(f"segmentation labels {labels.shape} do not match the points grid {points.shape[:2]}")
    if not (isinstance(max_edge_pixels, (int, float)) and max_edge_pixels > 0):
        raise ValueError(f"max_edge_pixels must be > 0, got {max_edge_pixels!r}")
    if not (isinstance(max_view_angle, (int, float)) and 0 < max_view_angle <= 90):
        raise ValueError(f"max_view_angle must be in (0, 90] degrees, got {max_view_angle!r}")
    pitch = pixel_pitch(points)
    distance, _ = ranges(points)
    if range_sigma is not None:
        range_sigma = check_range_sigma(distance, range_sigma)
    faces, face_labels = _grid_faces(
        points, distance, labels.astype(np.int32), float(max_edge_pixels * pitch), math.cos(math.radians(max_view_angle))
    )
    n_labels = segmentation.n_segments + 1
    vertex_pixels, vertex_starts, local_faces, face_starts = _group_by_label(faces, face_labels, labels.shape[1], n_labels)
    surfaces = []
    width = labels.shape[1]
    for label in range(1, n_labels):
        own = local_faces[face_starts[label] : face_starts[label + 1]]
        if len(own) < min_faces or len(own) == 0:
            continue
        used = vertex_pixels[vertex_starts[label] : vertex_starts[label + 1]]
        rows, cols = np.divmod(used, width)
        surfaces.append(_segment_surface(points, distance, range_sigma, segmentation, label, rows, cols, own))
    return surfaces


def segment_vertices(
    points: ArrayLike, segmentation: Segmentation, *, range_sigma: ArrayLike | None = None, stride: int = 1,
    checkerboard: bool = False,
) -> list[Surface]:
    """The pixels of every segment as vertex-only surfaces (no triangles), for merging into a model.

    Cheaper than `triangulate_segments` when the triangles are not needed
    (`rangesurf.merge.GlobalModel` re-meshes what it fuses).

    Parameters
    ----------
    points : (H, W, 3) float array
        Sensor-frame points, NaN where invalid.
    segmentation : Segmentation
    range_sigma : (H, W) float array, optional
        Range noise; gives each vertex ``"UL1"`` (see `triangulate_segments`).
    stride : int
        Take every ``stride``-th row and column.
    checkerboard : bool
        Of those, take every other one, alternating from row to row (the
        black squares of a checkerboard, whose first is the top left
        pixel): half the vertices, ``sqrt(2) * stride`` pixels apart and
        spread as evenly as on a square grid (a step between strides 1 and
        2, whose vertices differ fourfold).

    Returns
    -------
    list of Surface
        One per non-empty segment, in label order, with no faces.

    Examples
    --------
    >>> import numpy as np
    >>> from rangesurf.segment import Segmentation
    >>> rows, cols = np.mgrid[0:4, 0:6].astype(np.float32)
    >>> points = np.dstack([cols * 0.01, rows * 0.01, np.full(rows.shape, 2.0, np.float32)])
    >>> labels = np.ones((4, 6), np.int32)
    >>> segments = Segmentation(labels, np.array([[np.nan] * 4, [0.0, 0.0, -1.0, 2.0]]), np.array([np.nan, 0.0]), np.array([0, 24]))
    >>> [surface.n_vertices for surface in segment_vertices(points, segments, stride=2)]
    [6]
    >>> [surface.n_vertices for surface in segment_vertices(points, segments, checkerboard=True)]
    [12]
    """
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"stride must be an integer >= 1, got {stride!r}")
    if not isinstance(checkerboard, (bool, np.bool_)):
        raise ValueError(f"checkerboard must be True or False, got {checkerboard!r}")
    labels = np.asarray(segmentation.labels)
    if labels.shape != np.shape(points)[:2]:
        raise ValueError(f"segmentation labels {labels.shape} do not match the points grid {np.shape(points)[:2]}")
    # Check and work on the strided grid only (a depth camera's frame is thinned several times);
    # pixel coordinates are mapped back at the end.
    points = check_point_grid(np.asarray(points)[::stride, ::stride])
    labels = np.ascontiguousarray(labels[::stride, ::stride], dtype=np.int32)
    distance, _ = ranges(points)
    if range_sigma is not None:
        range_sigma = check_range_sigma(distance, np.asarray(range_sigma)[::stride, ::stride] if np.ndim(range_sigma) else range_sigma)
    planes = np.asarray(segmentation.planes, dtype=np.float64)
    # One compiled pass sorts the valid pixels by segment and copies out each one's points, pixels, plane
    # normal and noise along it (each surface's are then a slice: NumPy's gathers cost as much as the pass).
    residuals = np.asarray(segmentation.residuals, dtype=np.float64)
    starts, vertices, pixels, normals, ul1 = _gather_segments(
        points, labels, distance, np.empty((0, 0)) if range_sigma is None else range_sigma, planes, residuals,
        segmentation.n_segments, stride, bool(checkerboard))
    surfaces = []
    for label in range(1, segmentation.n_segments + 1):
        begin, end = starts[label], starts[label + 1]
        if end == begin:
            continue
        uncertainty = {}
        if range_sigma is not None:
            uncertainty["UL1"] = ul1[begin:end]
        if np.isfinite(residuals[label]):
            uncertainty["UL2"] = np.full(end - begin, residuals[label], np.float32)
        surfaces.append(Surface(
            vertices=vertices[begin:end], faces=np.zeros((0, 3), np.int32), normals=normals[begin:end],
            pixels=pixels[begin:end], plane=planes[label], segment=label, uncertainty=uncertainty,
        ))
    return surfaces


@numba.njit(**_JIT)
def _gather_segments(points, labels, distance, sigma, planes, residuals, n_segments, stride, checkerboard):  # pragma: no cover - compiled
    """The valid labelled pixels grouped by label (row-major within each), with their noise along the normal;
    with ``checkerboard`` only the pixels whose row and column add up to an even number.

    Returns ``starts`` (label k's pixels are ``starts[k]:starts[k + 1]``),
    their points (float32), ``(row, column)`` times ``stride`` (int32, the
    full grid's pixel), their segment's plane normal (float32; NaN where it
    has no plane) and their ``UL1`` (float32; empty without ``sigma``):
    ``sigma |cos(incidence)|`` (the sigma itself where the segment has no
    plane), scaled down to the segment's fit residual as `_denoised` does.
    """
    height, width = labels.shape
    # Column steps of 2 from the row's first taken column (0 or 1) on a checkerboard, else of 1.
    column_step = 2 if checkerboard else 1
    counts = np.zeros(n_segments + 2, np.int64)
    for i in range(height):
        for j in range(i & 1 if checkerboard else 0, width, column_step):
            label = labels[i, j]
            if label > 0 and distance[i, j] == distance[i, j]:
                counts[label + 1] += 1
    starts = np.cumsum(counts)
    total = starts[-1]
    vertices = np.empty((total, 3), np.float32)
    pixels = np.empty((total, 2), np.int32)
    normals = np.empty((total, 3), np.float32)
    with_sigma = sigma.shape[0] > 0
    along = np.empty(total if with_sigma else 0)
    squares = np.zeros(n_segments + 1)
    filled = starts[:-1].copy()
    for i in range(height):
        for j in range(i & 1 if checkerboard else 0, width, column_step):
            label = labels[i, j]
            if label <= 0 or distance[i, j] != distance[i, j]:
                continue
            k = filled[label]
            filled[label] += 1
            for axis in range(3):
                vertices[k, axis] = points[i, j, axis]
            pixels[k, 0], pixels[k, 1] = i * stride, j * stride
            if with_sigma:
                nx, ny, nz = planes[label, 0], planes[label, 1], planes[label, 2]
                value = sigma[i, j]
                cosine = abs(points[i, j, 0] * nx + points[i, j, 1] * ny + points[i, j, 2] * nz) / max(distance[i, j], 1e-12)
                if cosine == cosine:
                    value *= cosine
                along[k] = value
                squares[label] += value * value
    ul1 = np.empty(along.size, np.float32)
    for label in range(1, n_segments + 1):
        first, last = starts[label], starts[label + 1]
        planar = True
        for axis in range(4):
            planar &= math.isfinite(planes[label, axis])
        for k in range(first, last):
            for axis in range(3):
                normals[k, axis] = np.float32(planes[label, axis]) if planar else np.nan
        if with_sigma and last > first:
            factor = _denoising_factor(residuals[label], math.sqrt(squares[label] / (last - first)))
            for k in range(first, last):
                ul1[k] = np.float32(along[k] * factor)
    return starts, vertices, pixels, normals, ul1


@numba.njit(**_JIT)
def _denoising_factor(residual, predicted):  # pragma: no cover - compiled
    """What `_denoised` scales the sensor noise by: the fit residual over the predicted noise, at most 1."""
    if residual == residual and abs(residual) != math.inf and predicted > 0:
        return min(1.0, residual / predicted)
    return 1.0


def _denoised(along_normal: np.ndarray, residual: float, predicted: float) -> np.ndarray:
    """UL1 of a segment's vertices: the sensor noise along the normal, scaled down to what denoising left.

    A planar segment's fit residual is the noise left after denoising; where
    it is below what the sensor model predicts (``predicted``, the RMS of
    ``along_normal``), the noise is scaled down by their ratio.
    """
    return (along_normal * _denoising_factor(float(residual), float(predicted))).astype(np.float32)


def _segment_surface(points, distance, range_sigma, segmentation, label, rows, cols, faces) -> Surface:
    """One segment's vertices (given by pixel), with plane normals and UL1 / UL2 where known."""
    vertices = points[rows, cols]
    plane = np.asarray(segmentation.planes[label], dtype=np.float64)
    if np.isfinite(plane).all():
        normals = np.broadcast_to(plane[:3].astype(np.float32), vertices.shape)
    else:
        normals = _vertex_normals(vertices, faces)
    uncertainty = {}
    if range_sigma is not None:
        # Noise along the ray, seen along the normal: sigma |cos(incidence)|.
        rays = vertices / np.maximum(distance[rows, cols], 1e-12)[:, None]
        cosine = np.abs(np.einsum("ij,ij->i", rays, normals))
        along_normal = np.nan_to_num(range_sigma[rows, cols] * cosine, nan=range_sigma[rows, cols])
        predicted = float(np.sqrt(np.mean(along_normal**2))) if len(along_normal) else 0.0
        uncertainty["UL1"] = _denoised(along_normal, segmentation.residuals[label], predicted)
    if np.isfinite(segmentation.residuals[label]):
        uncertainty["UL2"] = np.full(len(rows), segmentation.residuals[label], np.float32)
    return Surface(
        vertices=vertices, faces=faces, normals=normals, pixels=np.column_stack([rows, cols]), plane=plane,
        segment=label, uncertainty=uncertainty,
    )


@numba.njit(**_JIT)
def _grid_faces(points, distance, labels, edge_per_metre, cos_view):  # pragma: no cover - compiled
    """Triangles (flat pixel indices) of every 2x2 cell, with the label they belong to.

    Four corners of one label: two triangles along the shorter diagonal.
    Three of one label: the triangle of those three. Corners run
    counter-clockwise in the image (top-left, bottom-left, bottom-right,
    top-right), so that with x right and y down every triangle winds
    counter-clockwise seen from the sensor.
    """
    height, width = labels.shape
    faces = np.empty((2 * height * width, 3), np.int32)
    face_labels = np.empty(2 * height * width, np.int32)
    count = 0
    ci = np.empty(4, np.int64)
    cj = np.empty(4, np.int64)
    value = np.empty(4, np.int32)
    for i in range(height - 1):
        for j in range(width - 1):
            ci[0], cj[0] = i, j
            ci[1], cj[1] = i + 1, j
            ci[2], cj[2] = i + 1, j + 1
            ci[3], cj[3] = i, j + 1
            for k in range(4):
                value[k] = labels[ci[k], cj[k]]
            if value[0] > 0 and value[0] == value[1] == value[2] == value[3]:
                if _squared_distance(points, ci[0], cj[0], ci[2], cj[2]) <= _squared_distance(points, ci[1], cj[1], ci[3], cj[3]):
                    first, second = (0, 1, 2), (0, 2, 3)
                else:
                    first, second = (0, 1, 3), (1, 2, 3)
                for a, b, c in (first, second):
                    if _keep(points, distance, ci[a], cj[a], ci[b], cj[b], ci[c], cj[c], edge_per_metre, cos_view):
                        faces[count, 0] = ci[a] * width + cj[a]
                        faces[count, 1] = ci[b] * width + cj[b]
                        faces[count, 2] = ci[c] * width + cj[c]
                        face_labels[count] = value[0]
                        count += 1
                continue
            for missing in range(4):
                a = (missing + 1) % 4
                b = (missing + 2) % 4
                c = (missing + 3) % 4
                if value[a] > 0 and value[a] == value[b] == value[c]:
                    if _keep(points, distance, ci[a], cj[a], ci[b], cj[b], ci[c], cj[c], edge_per_metre, cos_view):
                        faces[count, 0] = ci[a] * width + cj[a]
                        faces[count, 1] = ci[b] * width + cj[b]
                        faces[count, 2] = ci[c] * width + cj[c]
                        face_labels[count] = value[a]
                        count += 1
                    break
    return faces[:count], face_labels[:count]


@numba.njit(**_JIT, inline="always")
def _squared_distance(points, ai, aj, bi, bj):  # pragma: no cover - compiled
    dx = points[ai, aj, 0] - points[bi, bj, 0]
    dy = points[ai, aj, 1] - points[bi, bj, 1]
    dz = points[ai, aj, 2] - points[bi, bj, 2]
    return dx * dx + dy * dy + dz * dz


@numba.njit(**_JIT, inline="always")
def _keep(points, distance, ai, aj, bi, bj, ci, cj, edge_per_metre, cos_view):  # pragma: no cover - compiled
    """Whether triangle (a, b, c) is a surface: no edge over the step limit, not seen edge-on."""
    ax, ay, az = points[ai, aj, 0], points[ai, aj, 1], points[ai, aj, 2]
    bx, by, bz = points[bi, bj, 0], points[bi, bj, 1], points[bi, bj, 2]
    cx, cy, cz = points[ci, cj, 0], points[ci, cj, 1], points[ci, cj, 2]
    ra = distance[ai, aj]
    rb = distance[bi, bj]
    rc = distance[ci, cj]
    if not (ra > 0 and rb > 0 and rc > 0):
        return False
    limit_ab = edge_per_metre * min(ra, rb)
    limit_bc = edge_per_metre * min(rb, rc)
    limit_ca = edge_per_metre * min(rc, ra)
    if (ax - bx) ** 2 + (ay - by) ** 2 + (az - bz) ** 2 > limit_ab * limit_ab:
        return False
    if (bx - cx) ** 2 + (by - cy) ** 2 + (bz - cz) ** 2 > limit_bc * limit_bc:
        return False
    if (cx - ax) ** 2 + (cy - ay) ** 2 + (cz - az) ** 2 > limit_ca * limit_ca:
        return False
    nx = (by - ay) * (cz - az) - (bz - az) * (cy - ay)
    ny = (bz - az) * (cx - ax) - (bx - ax) * (cz - az)
    nz = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    if norm == 0.0:
        return False
    mx = (ax + bx + cx) / 3.0
    my = (ay + by + cy) / 3.0
    mz = (az + bz + cz) / 3.0
    return abs(nx * mx + ny * my + nz * mz) >= cos_view * norm * math.sqrt(mx * mx + my * my + mz * mz)


@numba.njit(**_JIT)
def _group_by_label(faces, face_labels, width, n_labels):  # pragma: no cover - compiled
    """Faces and their vertices grouped by label (counting sort), with faces renumbered per label.

    Returns the flat pixel index of every used vertex, grouped by label and
    in raster order within a label; where each label's vertices start; the
    faces with local vertex indices, grouped by label; and where each
    label's faces start.
    """
    n_faces = faces.shape[0]
    face_starts = np.zeros(n_labels + 1, np.int64)
    for f in range(n_faces):
        face_starts[face_labels[f] + 1] += 1
    for label in range(n_labels):
        face_starts[label + 1] += face_starts[label]
    # Mark used pixels; a pixel belongs to one label only.
    n_pixels = 0
    for f in range(n_faces):
        for k in range(3):
            n_pixels = max(n_pixels, faces[f, k] + 1)
    owner = np.full(n_pixels, -1, np.int32)
    for f in range(n_faces):
        for k in range(3):
            owner[faces[f, k]] = face_labels[f]
    vertex_starts = np.zeros(n_labels + 1, np.int64)
    for pixel in range(n_pixels):
        if owner[pixel] >= 0:
            vertex_starts[owner[pixel] + 1] += 1
    for label in range(n_labels):
        vertex_starts[label + 1] += vertex_starts[label]
    fill = vertex_starts[:-1].copy()
    vertex_pixels = np.empty(vertex_starts[n_labels], np.int64)
    local = np.full(n_pixels, -1, np.int64)
    for pixel in range(n_pixels):
        label = owner[pixel]
        if label >= 0:
            local[pixel] = fill[label] - vertex_starts[label]
            vertex_pixels[fill[label]] = pixel
            fill[label] += 1
    local_faces = np.empty((n_faces, 3), np.int32)
    placed = face_starts[:-1].copy()
    for f in range(n_faces):
        label = face_labels[f]
        row = placed[label]
        for k in range(3):
            local_faces[row, k] = local[faces[f, k]]
        placed[label] += 1
    return vertex_pixels, vertex_starts, local_faces, face_starts


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, turned to face the origin (the sensor)."""
    corners = vertices[faces].astype(np.float64)
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros((len(vertices), 3))
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.full_like(normals, np.nan), where=length > 0)
    flip = np.einsum("ij,ij->i", normals, vertices) > 0
    normals[flip] *= -1
    return normals.astype(np.float32)


# --------------------------------------------------------------------------
# Irregular vertex sets.
# --------------------------------------------------------------------------


def delaunay_2d(flat: np.ndarray) -> tuple[np.ndarray, Delaunay | None]:
    """Delaunay triangles of 2-D points, counter-clockwise, without slivers of no area; and the triangulation.

    Empty (and None) for fewer than 3 points or collinear or duplicate-only ones.
    """
    if len(flat) < 3:
        return np.zeros((0, 3), np.int32), None
    try:
        triangulation = Delaunay(flat)
    except QhullError:
        return np.zeros((0, 3), np.int32), None  # no area to triangulate
    triangles = triangulation.simplices
    corners = flat[triangles]
    # Counter-clockwise in (u, v) is counter-clockwise seen from +normal.
    signed = (corners[:, 1, 0] - corners[:, 0, 0]) * (corners[:, 2, 1] - corners[:, 0, 1]) - (
        corners[:, 1, 1] - corners[:, 0, 1]
    ) * (corners[:, 2, 0] - corners[:, 0, 0])
    triangles = np.where((signed < 0)[:, None], triangles[:, [0, 2, 1]], triangles)
    return triangles[np.abs(signed) > 1e-12 * max(np.ptp(flat), 1e-9) ** 2].astype(np.int32), triangulation


def triangulate_in_plane(vertices: ArrayLike, plane: ArrayLike, *, max_edge: float | None = None) -> np.ndarray:
    """Delaunay triangles of points on (or near) a plane, computed in the plane's 2-D coordinates.

    Parameters
    ----------
    vertices : (N, 3) float array
        Points (metres).
    plane : (4,) float array
        ``(nx, ny, nz, d)``; only the normal is used (the 2-D frame).
    max_edge : float, optional
        Triangles with an edge longer than this (metres) are dropped, so
        that concave outlines and holes stay open. Default: 3 times the
        median nearest-neighbour spacing.

    Returns
    -------
    (M, 3) int32
        Vertex indices, counter-clockwise seen from the side the normal
        points to. Empty for fewer than 3 distinct points or collinear ones.

    Examples
    --------
    >>> import numpy as np
    >>> square = np.array([[0, 0, 2], [1, 0, 2], [1, 1, 2], [0, 1, 2]], float)
    >>> len(triangulate_in_plane(square, [0, 0, -1, 2]))
    2
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (N, 3), got shape {vertices.shape}")
    if not np.isfinite(vertices).all():
        raise ValueError("vertices must be finite")
    normal = np.asarray(plane, dtype=np.float64).reshape(-1)[:3]
    if normal.shape != (3,) or not np.isfinite(normal).all() or np.linalg.norm(normal) == 0:
        raise ValueError(f"plane must start with a finite, non-zero normal, got {plane!r}")
    normal = normal / np.linalg.norm(normal)
    empty = np.zeros((0, 3), np.int32)
    if len(vertices) < 3:
        return empty
    # An orthonormal frame (u, v) of the plane; (u, v, normal) right-handed.
    helper = np.eye(3)[np.argmin(np.abs(normal))]
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    flat = np.column_stack([vertices @ u, vertices @ v])
    triangles, _ = delaunay_2d(flat)
    if not len(triangles):
        return empty
    if max_edge is None:
        spacing = _nearest_spacing(flat)
        max_edge = 3.0 * spacing if spacing > 0 else np.inf
    edges = np.linalg.norm(vertices[triangles] - vertices[np.roll(triangles, 1, axis=1)], axis=2)
    return triangles[(edges <= max_edge).all(axis=1)].astype(np.int32)


def _nearest_spacing(flat: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    distances, _ = cKDTree(flat).query(flat, k=2)
    positive = distances[:, 1][distances[:, 1] > 0]
    return float(np.median(positive)) if positive.size else 0.0


# --------------------------------------------------------------------------
# Outlines and holes.
# --------------------------------------------------------------------------


def boundary_loops(faces: ArrayLike) -> list[np.ndarray]:
    """Closed loops of boundary edges (edges of exactly one triangle), longest first.

    For a mesh of a patch, the first loop is usually its outline and the
    others its holes (`Surface` vertices in the loop's order). A vertex
    where two loops touch (a pinch) is visited once per loop.

    Parameters
    ----------
    faces : (M, 3) int array

    Returns
    -------
    list of (K,) int32 arrays
        Vertex indices of each loop, in order, following the faces' winding.

    Examples
    --------
    >>> boundary_loops([[0, 1, 2], [0, 2, 3]])[0].tolist()
    [0, 1, 2, 3]
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if faces.size == 0:
        return []
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    # An edge is on the boundary when only one face uses it. Sort the undirected edges with the
    # direction in the lowest bit (one sort, no search): a boundary edge is a run of length one.
    base = int(faces.max()) + 1
    low, high = directed.min(axis=1), directed.max(axis=1)
    codes = np.sort(((low * base + high) << 1) | (directed[:, 0] > directed[:, 1]))
    edges = codes >> 1
    single = np.ones(len(codes), bool)
    repeated = edges[1:] == edges[:-1]
    single[1:] &= ~repeated
    single[:-1] &= ~repeated
    boundary, flipped = edges[single], (codes[single] & 1).astype(bool)
    starts = np.where(flipped, boundary % base, boundary // base)
    ends = np.where(flipped, boundary // base, boundary % base)
    successors: dict[int, list[int]] = {}
    for a, b in zip(starts.tolist(), ends.tolist()):
        successors.setdefault(a, []).append(b)
    loops = []
    while successors:
        start = min(successors)
        loop = [start]
        current = start
        while True:
            following = successors[current]
            nxt = following.pop()
            if not following:
                del successors[current]
            if nxt == start:
                break
            loop.append(nxt)
            current = nxt
            if current not in successors:
                break
        loops.append(np.asarray(loop, dtype=np.int32))
    loops.sort(key=len, reverse=True)
    return loops



def fill_small_holes(surface: Surface, *, max_perimeter: float) -> Surface:
    """Close the holes whose outline is shorter than ``max_perimeter`` metres (deferrable work).

    Each such hole gets one new vertex at the centre of its outline (moved
    onto the surface's plane where it has one) and a fan of triangles to
    the outline, wound like their neighbours. The outline of the surface
    (its longest boundary loop) is never filled. New vertices have no grid
    pixel (-1, -1) and the mean uncertainty of their hole's outline; the
    level-of-detail order is reset (rebuild it with
    `rangesurf.lod.prepare_levels`).

    Returns
    -------
    Surface
        A new surface (the input is unchanged).

    Examples
    --------
    >>> import numpy as np
    >>> rows, cols = np.mgrid[0:7, 0:7] * 0.1
    >>> keep = ~((np.abs(rows - 0.35) < 0.06) & (np.abs(cols - 0.35) < 0.06))  # a 2x2 block of points missing
    >>> vertices = np.column_stack([cols[keep], rows[keep], np.full(keep.sum(), 2.0)])
    >>> faces = triangulate_in_plane(vertices, [0, 0, -1, 2], max_edge=0.15)
    >>> holed = Surface(vertices, faces, np.tile([0, 0, -1.0], (len(vertices), 1)), np.full((len(vertices), 2), -1))
    >>> len(boundary_loops(holed.faces)), len(boundary_loops(fill_small_holes(holed, max_perimeter=1.0).faces))
    (2, 1)
    """
    if not (isinstance(max_perimeter, (int, float)) and max_perimeter >= 0):
        raise ValueError(f"max_perimeter must be >= 0 metres, got {max_perimeter!r}")
    loops = boundary_loops(surface.faces)
    vertices = surface.vertices.astype(np.float64)
    perimeters = [float(np.linalg.norm(vertices[loop] - vertices[np.roll(loop, -1)], axis=1).sum()) for loop in loops]
    outline = int(np.argmax(perimeters)) if loops else -1
    new_vertices, new_faces, new_uncertainty = [], [], {name: [] for name in surface.uncertainty}
    next_index = surface.n_vertices
    for index, (loop, perimeter) in enumerate(zip(loops, perimeters)):
        if index == outline or perimeter > max_perimeter or len(loop) < 3:
            continue
        centre = vertices[loop].mean(axis=0)
        if np.isfinite(surface.plane).all():
            normal = surface.plane[:3] / np.linalg.norm(surface.plane[:3])
            centre -= (normal @ centre + surface.plane[3] / np.linalg.norm(surface.plane[:3])) * normal
        new_vertices.append(centre)
        # The boundary edge a -> b belongs to a face wound a -> b; the new face runs b -> a.
        for a, b in zip(loop, np.roll(loop, -1)):
            new_faces.append((b, a, next_index))
        for name, values in surface.uncertainty.items():
            new_uncertainty[name].append(float(values[loop].mean()))
        next_index += 1
    if not new_vertices:
        return surface
    count = len(new_vertices)
    normals = surface.normals[: 1].repeat(count, axis=0) if np.isfinite(surface.plane).all() else _vertex_normals(
        np.vstack([vertices, new_vertices]), np.vstack([surface.faces, new_faces]))[-count:]
    return Surface(
        vertices=np.vstack([vertices, new_vertices]),
        faces=np.vstack([surface.faces, np.asarray(new_faces)]),
        normals=np.vstack([surface.normals, normals]),
        pixels=np.vstack([surface.pixels, np.full((count, 2), -1)]),
        plane=surface.plane,
        segment=surface.segment,
        uncertainty={name: np.concatenate([values, new_uncertainty[name]]) for name, values in surface.uncertainty.items()},
    )
