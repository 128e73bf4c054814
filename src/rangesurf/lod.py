"""Levels of detail: vertex importance and a progressive order (thesis Section 3.2).

The thesis orders a surface's vertices by how much each one tells: a vertex
whose height over the surface's plane its neighbours predict well can go
first. Its height is estimated from its four nearest neighbours by
inverse-distance weighting (Shepard's method, thesis Eq. 3.10) or by
natural-neighbour weights (Sibson, Eq. 3.11), and the importance is the
difference ``|h - h_estimate|``. Vertices are removed least important first;
the neighbours that estimated a removed vertex take over its error (so that
a region whose detail was removed becomes harder to thin further) and are
re-evaluated, lazily, when they next reach the front of the queue. Outline
vertices also count the distance to the segment that joins their two
outline neighbours, so outlines survive the coarse levels.

The removal order, reversed, is the progressive order (most important
first) with the error each removal introduced; `build_levels` triangulates a
ladder of vertex counts (halving) once, and `Surface.at_level`-style
selection (`select_level`) is then a lookup, cheap enough for every rendered
frame. `screen_space_level` picks the finest level whose vertices, seen
from a camera, are at least one pixel apart (the thesis's future work: no
two vertices of a mesh in one pixel); `distance_level` is the thesis's
linear rule.

References
----------
.. [1] The reference thesis, Section 3.2 and Eq. 3.10 (``shared/reference/thesis.md``).
.. [2] D. Shepard, "A two-dimensional interpolation function for
   irregularly-spaced data", ACM National Conference, 1968.
.. [3] R. Sibson, "A brief description of natural neighbour interpolation",
   in Interpreting Multivariate Data, Wiley, 1981.
.. [4] H. Hoppe, "Progressive meshes", SIGGRAPH 1996.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from scipy.spatial import cKDTree

from rangesurf.mesh import Surface, boundary_loops, delaunay_2d

__all__ = ["Level", "prepare_levels", "progressive_order", "build_levels", "build_levels_at", "view_level", "select_level", "screen_space_level", "distance_level"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")
# Neighbours that estimate a vertex's height (Shepard over the four nearest, as the thesis).
_NEIGHBOURS = 4


@dataclass(frozen=True)
class Level:
    """One precomputed level of detail of a surface.

    Parameters
    ----------
    count : int
        Vertices kept: the first ``count`` of the surface's ``lod_order``.
    faces : (M, 3) int32
        Triangles over those vertices (indices into ``lod_order[:count]``).
    error : float
        Largest error (metres) of a vertex removed to reach this level.
    spacing : float
        Median distance (metres) between neighbouring kept vertices.
    vertex_error : (count,) float32
        Per kept vertex, the RMS error of the removed vertices nearest to
        it: the level-of-detail uncertainty UL4 of the shown level.
    """

    count: int
    faces: np.ndarray
    error: float
    spacing: float
    vertex_error: np.ndarray


def _plane_frame(surface: Surface) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """In-plane coordinates (N, 2), heights (N,) and the unit normal of the surface's (or fitted) plane."""
    vertices = surface.vertices.astype(np.float64)
    plane = surface.plane
    if np.isfinite(plane).all():
        normal, offset = plane[:3] / np.linalg.norm(plane[:3]), plane[3] / np.linalg.norm(plane[:3])
    else:
        centre = vertices.mean(axis=0)
        # Full matrices: three axes even for fewer than three vertices (any plane through them will do).
        _, _, axes = np.linalg.svd(vertices - centre, full_matrices=True)
        normal = axes[2]
        offset = -float(normal @ centre)
    helper = np.eye(3)[np.argmin(np.abs(normal))]
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    return np.column_stack([vertices @ u, vertices @ v]), vertices @ normal + offset, normal


def progressive_order(surface: Surface, *, min_vertices: int = 3, interpolation: str = "shepard") -> tuple[np.ndarray, np.ndarray]:
    """Order a surface's vertices from most to least important.

    Parameters
    ----------
    surface : Surface
        With faces (outline vertices are found from them).
    min_vertices : int
        Vertices never removed (the last ones left are ordered by their
        final importance).
    interpolation : {"shepard", "sibson"}
        How the four nearest neighbours estimate a vertex's height:
        inverse-distance weighting (Shepard, thesis Eq. 3.10, with weights
        ``1/d**2``) or natural-neighbour weights (Sibson, Eq. 3.11: the area
        the vertex's Voronoi cell takes from each neighbour's; Shepard where
        that cell is unbounded, outside the neighbours' hull). The thesis
        found both give similar orders; Sibson costs about 3.5x the time.

    Returns
    -------
    order : (N,) int32
        Vertex indices, most important first (`Surface.lod_order`).
    error : (N,) float32
        ``error[k]``: the height error (metres) that removing ``order[k]``
        introduced, the running maximum over the removal so far (so that it
        never decreases from coarse to fine); the vertices never removed
        get the largest.

    Examples
    --------
    A flat square patch keeps its four corners to the end:

    >>> import numpy as np
    >>> from rangesurf.mesh import Surface, triangulate_in_plane
    >>> rows, cols = np.mgrid[0:6, 0:6]
    >>> vertices = np.column_stack([cols.ravel(), rows.ravel(), np.full(36, 2.0)]) * 0.1
    >>> faces = triangulate_in_plane(vertices, [0, 0, -1, 0.2])
    >>> surface = Surface(vertices, faces, np.tile([0, 0, -1.0], (36, 1)), np.full((36, 2), -1), plane=[0, 0, -1, 0.2])
    >>> order, error = progressive_order(surface, min_vertices=4)
    >>> sorted(order[:4].tolist())
    [0, 5, 30, 35]
    """
    if interpolation not in ("shepard", "sibson"):
        raise ValueError(f"interpolation must be 'shepard' or 'sibson', got {interpolation!r}")
    count = surface.n_vertices
    if count == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.float32)
    xy, height, _ = _plane_frame(surface)
    previous = np.full(count, -1, np.int64)
    following = np.full(count, -1, np.int64)
    for loop in boundary_loops(surface.faces):
        previous[loop] = np.roll(loop, 1)
        following[loop] = np.roll(loop, -1)
    removed, errors, remaining = _remove_greedily(xy, height, previous, following, max(int(min_vertices), 1), interpolation == "sibson")
    order = np.concatenate([remaining, removed[::-1]]).astype(np.int32)
    error = np.concatenate([np.full(len(remaining), errors.max(initial=0.0)), np.maximum.accumulate(errors)[::-1]])
    return order, error.astype(np.float32)


def prepare_levels(surface: Surface, *, min_vertices: int = 3) -> Surface:
    """Order a surface's vertices and precompute its levels, in place; returns the surface.

    Afterwards ``surface.at_level(count=..., fraction=..., max_error=...)`` is a lookup.

    Examples
    --------
    >>> import numpy as np
    >>> from rangesurf.mesh import Surface, triangulate_in_plane
    >>> rows, cols = np.mgrid[0:20, 0:20] * 0.05
    >>> vertices = np.column_stack([cols.ravel(), rows.ravel(), 2.0 + 0.1 * np.sin(4 * cols.ravel())])
    >>> faces = triangulate_in_plane(vertices, [0, 0, -1, 2])
    >>> surface = prepare_levels(Surface(vertices, faces, np.tile([0, 0, -1.0], (400, 1)), np.full((400, 2), -1)))
    >>> coarse = surface.at_level(fraction=0.1)
    >>> coarse.n_vertices, "UL4" in coarse.uncertainty
    (50, True)
    """
    surface.lod_order, surface.lod_error = progressive_order(surface, min_vertices=min_vertices)
    surface.levels = build_levels(surface, min_vertices=min_vertices)
    return surface


def build_levels(surface: Surface, *, min_vertices: int = 3, ratio: float = 0.5) -> list[Level]:
    """Triangulate a ladder of levels (vertex counts ``N, N*ratio, N*ratio^2, ...``) of an ordered surface.

    The surface's ``lod_order`` and ``lod_error`` must be set (`progressive_order`).
    Coarse levels are Delaunay triangulations of the kept vertices in the
    surface's plane, keeping the triangles whose centroid lies inside the
    full-resolution outline; the triangulation is not constrained to the
    outline, so along concave outlines and holes a coarse level can miss
    thin slivers (up to 2.5 % of the area in the tests) but never covers a hole.

    Returns
    -------
    list of Level
        Finest first.
    """
    if not 0 < ratio < 1:
        raise ValueError(f"ratio must be in (0, 1), got {ratio}")
    counts = []
    count = surface.n_vertices
    while count >= min_vertices:
        counts.append(count)
        next_count = int(count * ratio)
        if next_count < min_vertices or next_count == count:
            break
        count = next_count
    return build_levels_at(surface, counts)


def build_levels_at(surface: Surface, counts: list[int]) -> list[Level]:
    """Triangulate the levels of an ordered surface at the given vertex counts (see `build_levels`)."""
    xy, height, _ = _plane_frame(surface)
    order, error = surface.lod_order, surface.lod_error
    # Coarse levels are Delaunay triangulations of the kept vertices, which fill the convex hull;
    # a triangle stays only if its centroid lies inside the full-resolution outline (even-odd over
    # all boundary loops, so holes stay holes).
    coverage = _Coverage(xy, boundary_loops(surface.faces))
    levels = []
    for count in counts:
        if not 1 <= count <= surface.n_vertices:
            raise ValueError(f"level vertex counts must be in 1..{surface.n_vertices}, got {count}")
        kept = order[:count]
        triangulation = None
        if count == surface.n_vertices:
            faces = _reindex(surface.faces, order)
        else:
            # In the plane frame of `_plane_frame`, the one `triangulate_in_plane` uses too.
            faces, triangulation = delaunay_2d(xy[kept])
            if len(faces):
                faces = faces[coverage.contains(xy[kept][faces].mean(axis=1))]
        tree = cKDTree(xy[kept])
        spacing = float(np.median(tree.query(xy[kept], k=2)[0][:, 1])) if count > 1 else 0.0
        vertex_error = np.zeros(count, np.float32)
        if count < surface.n_vertices:
            # A standard deviation, like the other levels: the RMS height of the removed vertices nearest
            # to each kept one above the level's triangles.
            # The errors recorded at removal run high (they are running maxima); how high is measured on
            # a sample of the removed vertices against the level's triangles, and taken out.
            removed = order[count:]
            _, nearest = tree.query(xy[removed])
            recorded = error[count:].astype(np.float64)
            step = max(1, len(removed) // _UL4_SAMPLE)
            sample = removed[::step]
            measured = _height_above(triangulation, height[kept], xy[sample], height[sample], recorded[::step])
            scale = math.sqrt(float(measured @ measured) / float(recorded[::step] @ recorded[::step])) if recorded[::step].any() else 1.0
            squares = np.bincount(nearest, weights=recorded**2, minlength=count)
            vertex_error = (scale * np.sqrt(squares / np.maximum(np.bincount(nearest, minlength=count), 1))).astype(np.float32)
        levels.append(
            Level(count=count, faces=faces.astype(np.int32), error=float(error[count]) if count < len(error) else 0.0,
                  spacing=spacing, vertex_error=vertex_error)
        )
    return levels


def _height_above(triangulation, kept_height, removed_xy, removed_height, removal_error) -> np.ndarray:
    """How far each removed vertex lies from the kept ones' Delaunay triangles (by height in the plane frame);
    outside their hull, or with no triangulation, the error recorded when it was removed."""
    deviation = np.abs(removal_error).astype(np.float64)
    if triangulation is None:
        return deviation
    simplex = triangulation.find_simplex(removed_xy)
    inside = simplex >= 0
    affine = triangulation.transform[simplex[inside]]
    partial = np.einsum("ijk,ik->ij", affine[:, :2], removed_xy[inside] - affine[:, 2])
    weights = np.column_stack([partial, 1.0 - partial.sum(axis=1)])
    surface_height = (kept_height[triangulation.simplices[simplex[inside]]] * weights).sum(axis=1)
    deviation[inside] = np.abs(removed_height[inside] - surface_height)
    return deviation


# Removed vertices per level whose height above the level's triangles is measured (to scale UL4).
_UL4_SAMPLE = 2000


class _Coverage:
    """The full-resolution outline (with holes) rasterized in plane coordinates, for inside tests."""

    def __init__(self, xy: np.ndarray, loops: list[np.ndarray]) -> None:
        self.low = xy.min(axis=0) if len(xy) else np.zeros(2)
        extent = float(np.ptp(xy, axis=0).max()) if len(xy) else 0.0
        # About 1000 cells across: finer than the vertex spacing of any surface of a range frame row.
        self.cell = max(extent / 1000.0, 1e-9)
        size = np.ceil((xy.max(axis=0) - self.low) / self.cell).astype(int) + 2 if len(xy) else np.array([1, 1])
        self.mask = np.zeros((size[1], size[0]), np.uint8)
        contours = [np.round((xy[loop] - self.low) / self.cell).astype(np.int32) for loop in loops if len(loop) >= 3]
        if contours:
            # Outline and holes together: fillPoly's even-odd filling leaves the holes empty.
            cv2.fillPoly(self.mask, contours, 1)
        self.empty = not contours

    def contains(self, points: np.ndarray) -> np.ndarray:
        if self.empty:
            return np.ones(len(points), bool)
        cells = np.round((points - self.low) / self.cell).astype(int)
        cells[:, 0] = np.clip(cells[:, 0], 0, self.mask.shape[1] - 1)
        cells[:, 1] = np.clip(cells[:, 1], 0, self.mask.shape[0] - 1)
        return self.mask[cells[:, 1], cells[:, 0]].astype(bool)


def _reindex(faces: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Faces over original vertex ids, re-expressed as positions in ``order``."""
    position = np.empty(len(order), np.int64)
    position[order] = np.arange(len(order))
    return position[faces]


def select_level(levels: list[Level], *, count: int | None = None, fraction: float | None = None,
                 max_error: float | None = None) -> Level:
    """The level to show: the coarsest with at least ``count`` vertices (or ``fraction`` of them),
    or the coarsest whose error stays within ``max_error``. Exactly one criterion.

    Examples
    --------
    >>> levels = [Level(100, np.zeros((0, 3)), 0.0, 0.01, np.zeros(100)), Level(50, np.zeros((0, 3)), 0.002, 0.02, np.zeros(50))]
    >>> select_level(levels, count=60).count, select_level(levels, max_error=0.005).count
    (100, 50)
    """
    if sum(option is not None for option in (count, fraction, max_error)) != 1:
        raise ValueError("give exactly one of count, fraction or max_error")
    if not levels:
        raise ValueError("no levels to select from (build_levels gave none)")
    if fraction is not None:
        if not 0 <= fraction <= 1:
            raise ValueError(f"fraction must be in [0, 1], got {fraction}")
        count = math.ceil(fraction * levels[0].count)
    if count is not None:
        fitting = [level for level in levels if level.count >= count]
        return fitting[-1] if fitting else levels[0]
    fitting = [level for level in levels if level.error <= max_error]
    return fitting[-1] if fitting else levels[0]


def distance_level(levels: list[Level], distance: float, *, full_detail_distance: float = 1.0) -> Level:
    """The thesis's rule: the vertex count falls linearly with viewing distance (full detail up to ``full_detail_distance``)."""
    if distance <= full_detail_distance:
        return levels[0]
    return select_level(levels, fraction=min(1.0, full_detail_distance / distance))


def screen_space_level(levels: list[Level], distance: float, focal_length_px: float) -> Level:
    """The finest level whose vertices are at least one pixel apart on screen (no two in one pixel).

    The coarsest level when even it is denser than that, or when the
    surface is behind the camera or out of view.

    Parameters
    ----------
    levels : list of Level
        From `build_levels`, finest first.
    distance : float
        Metres from the camera to the surface (``inf`` or negative -- behind
        the camera or outside the view -- gives the coarsest level).
    focal_length_px : float
        The viewing camera's focal length in pixels.
    """
    if not (distance > 0 and math.isfinite(distance)):
        return levels[-1]
    # A level is worth showing when its spacing projects to at least one pixel; finer levels
    # would put several vertices into one pixel.
    chosen = levels[-1]
    for level in reversed(levels):
        if level.spacing * focal_length_px / distance >= 1.0:
            chosen = level
        else:
            break
    return chosen


def view_level(surface: Surface, T_camera_surface: np.ndarray, *, fx: float, fy: float, cx: float, cy: float,
               width: int, height: int, near: float = 0.05) -> Level:
    """The level to render a surface with, from a camera: screen-space rule, coarsest when out of view.

    Parameters
    ----------
    surface : Surface
        With levels (`prepare_levels`).
    T_camera_surface : (4, 4) array
        The surface's frame (its vertices' frame) in the camera's optical
        frame (x right, y down, z forward).
    fx, fy, cx, cy : float
        Pinhole intrinsics of the view, in pixels.
    width, height : int
        Viewport size in pixels.
    near : float
        Near clipping distance (metres).

    Returns
    -------
    Level
        The finest level whose vertices stay at least one pixel apart at
        the surface's nearest distance; the coarsest level when the surface's
        bounding sphere lies behind the camera or outside the viewport.

    Examples
    --------
    >>> import numpy as np
    >>> from rangesurf.mesh import Surface, triangulate_in_plane
    >>> rows, cols = np.mgrid[0:20, 0:20] * 0.05
    >>> vertices = np.column_stack([cols.ravel(), rows.ravel(), 2.0 + 0.1 * np.sin(4 * cols.ravel())])
    >>> surface = prepare_levels(Surface(vertices, triangulate_in_plane(vertices, [0, 0, -1, 2]),
    ...                                  np.tile([0, 0, -1.0], (400, 1)), np.full((400, 2), -1)))
    >>> view = dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    >>> view_level(surface, np.eye(4), **view).count == surface.levels[0].count
    True
    >>> behind = np.diag([1.0, 1.0, -1.0, 1.0])
    >>> view_level(surface, behind, **view).count == surface.levels[-1].count
    True
    """
    if not surface.levels:
        raise ValueError("the surface has no levels; call prepare_levels first")
    vertices = surface.vertices.astype(np.float64)
    centre_surface = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    radius = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)) / 2)
    transform = np.asarray(T_camera_surface, dtype=np.float64)
    centre = transform[:3, :3] @ centre_surface + transform[:3, 3]
    if centre[2] + radius < near:
        return surface.levels[-1]
    depth = max(centre[2], near)
    # The sphere's image: its centre projected, widened by its radius at that depth.
    u, v = fx * centre[0] / depth + cx, fy * centre[1] / depth + cy
    reach_u, reach_v = fx * radius / depth, fy * radius / depth
    if u + reach_u < 0 or u - reach_u > width or v + reach_v < 0 or v - reach_v > height:
        return surface.levels[-1]
    return screen_space_level(surface.levels, max(centre[2] - radius, near), fx)


# --------------------------------------------------------------------------
# Kernels.
# --------------------------------------------------------------------------


@numba.njit(**_JIT)
def _remove_greedily(xy, height, previous, following, min_vertices, sibson):  # pragma: no cover - compiled
    """Remove vertices least important first; returns removal order, errors, and the vertices kept."""
    count = xy.shape[0]
    alive = np.ones(count, np.bool_)
    absorbed = np.zeros(count)
    grid = _build_grid(xy, alive, count)
    # Each vertex's neighbours at its last evaluation (-1: none) and the error of the height they
    # estimate. Vertices are only ever removed, so while all of them live they stay its nearest
    # and the error stays valid.
    nearest = np.full((count, _NEIGHBOURS), -1, np.int64)
    fit_error = np.empty(count)
    scratch = np.empty(_NEIGHBOURS)
    polygons = np.empty((8, 4 * _NEIGHBOURS + 8))
    # A min-heap holding every alive vertex once, four children per node (half the depth of a
    # binary heap, and siblings share a cache line).
    heap_keys = np.empty(count)
    heap_ids = np.arange(count)
    for vertex in range(count):
        fit_error[vertex] = _fit_error(vertex, xy, height, alive, grid, nearest[vertex], scratch, polygons, sibson)
        heap_keys[vertex] = fit_error[vertex] + _outline_error(vertex, xy, height, previous, following)
    for position in range((count - 2) // 4, -1, -1):
        _sift_down(heap_keys, heap_ids, count, position)
    size = count
    removed = np.empty(count, np.int64)
    errors = np.empty(count)
    n_removed = 0
    # Lazy re-evaluation: a removal only marks the vertices around it stale; a stale vertex is
    # re-evaluated when it reaches the top of the heap and sinks to its new importance.
    # Importances mostly grow as neighbours are removed (absorbed error), so the stored key is
    # close to a lower bound, and a vertex marked many times is evaluated once.
    stale = np.zeros(count, np.bool_)
    while size > min_vertices:
        vertex = heap_ids[0]
        if stale[vertex]:
            stale[vertex] = False
            for other in nearest[vertex]:
                if other >= 0 and not alive[other]:
                    fit_error[vertex] = _fit_error(vertex, xy, height, alive, grid, nearest[vertex], scratch, polygons, sibson)
                    break
            heap_keys[0] = fit_error[vertex] + _outline_error(vertex, xy, height, previous, following) + absorbed[vertex]
            _sift_down(heap_keys, heap_ids, size, 0)
            continue
        importance = heap_keys[0]
        size -= 1
        heap_keys[0], heap_ids[0] = heap_keys[size], heap_ids[size]
        _sift_down(heap_keys, heap_ids, size, 0)
        alive[vertex] = False
        removed[n_removed] = vertex
        errors[n_removed] = importance
        n_removed += 1
        # Relink the outline around a removed outline vertex.
        if previous[vertex] >= 0:
            before, after = previous[vertex], following[vertex]
            following[before] = after
            previous[after] = before
            stale[before] = True
            stale[after] = True
        if size * 2 < grid[0].shape[0] and size > 16:
            grid = _build_grid(xy, alive, size)
        # The neighbours that estimated the removed vertex take over its error.
        for other in nearest[vertex]:
            if other >= 0 and alive[other]:
                absorbed[other] = max(absorbed[other], importance)
                stale[other] = True
    remaining = np.flatnonzero(alive)
    # Most important of the kept ones first.
    kept_importance = np.empty(remaining.shape[0])
    for k in range(remaining.shape[0]):
        vertex = remaining[k]
        kept_importance[k] = (_fit_error(vertex, xy, height, alive, grid, nearest[vertex], scratch, polygons, sibson)
                              + _outline_error(vertex, xy, height, previous, following) + absorbed[vertex])
    remaining = remaining[np.argsort(-kept_importance, kind="mergesort")]
    return removed[:n_removed], errors[:n_removed], remaining


@numba.njit(**_JIT)
def _build_grid(xy, alive, n_alive):  # pragma: no cover - compiled
    """Uniform bucket grid over the alive vertices: (cell start, items, origin x, origin y, cell size, columns, rows)."""
    low_x, low_y = np.inf, np.inf
    high_x, high_y = -np.inf, -np.inf
    for k in range(xy.shape[0]):
        if alive[k]:
            low_x = min(low_x, xy[k, 0])
            low_y = min(low_y, xy[k, 1])
            high_x = max(high_x, xy[k, 0])
            high_y = max(high_y, xy[k, 1])
    extent = max(high_x - low_x, high_y - low_y, 1e-9)
    # About two vertices per cell.
    cells_per_side = max(1, int(math.sqrt(max(n_alive, 1) / 2.0)))
    cell = extent / cells_per_side * 1.0000001
    columns = int((high_x - low_x) / cell) + 1
    rows = int((high_y - low_y) / cell) + 1
    start = np.zeros(columns * rows + 1, np.int64)
    for k in range(xy.shape[0]):
        if alive[k]:
            index = int((xy[k, 1] - low_y) / cell) * columns + int((xy[k, 0] - low_x) / cell)
            start[index + 1] += 1
    for c in range(columns * rows):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    items = np.empty(start[-1], np.int64)
    for k in range(xy.shape[0]):
        if alive[k]:
            index = int((xy[k, 1] - low_y) / cell) * columns + int((xy[k, 0] - low_x) / cell)
            items[fill[index]] = k
            fill[index] += 1
    return items, start, low_x, low_y, cell, columns, rows


@numba.njit(**_JIT, inline="always")
def _scan_cell(index, x, y, exclude, xy, alive, items, start, best_d, out, found, k):  # pragma: no cover - compiled
    for slot in range(start[index], start[index + 1]):
        other = items[slot]
        if other == exclude or not alive[other]:
            continue
        d = (xy[other, 0] - x) ** 2 + (xy[other, 1] - y) ** 2
        if found < k or d < best_d[k - 1]:
            position = min(found, k - 1)
            while position > 0 and best_d[position - 1] > d:
                best_d[position] = best_d[position - 1]
                out[position] = out[position - 1]
                position -= 1
            best_d[position] = d
            out[position] = other
            if found < k:
                found += 1
    return found


@numba.njit(**_JIT, inline="always")
def _nearest(x, y, exclude, xy, alive, grid, out, best_d, k):  # pragma: no cover - compiled
    """Up to ``k`` nearest alive vertices to (x, y), nearest first, into ``out`` (squared distances into
    ``best_d``); returns how many."""
    items, start, low_x, low_y, cell, columns, rows = grid
    best_d[:k] = np.inf
    found = 0
    fx = (x - low_x) / cell
    fy = (y - low_y) / cell
    cx = min(max(int(fx), 0), columns - 1)
    cy = min(max(int(fy), 0), rows - 1)
    # Distance from the query to the border of its own cell: rings 0..r have seen every vertex
    # within (r + margin) cells.
    margin = max(min(fx - cx, cx + 1 - fx, fy - cy, cy + 1 - fy), 0.0)
    ring = 0
    while True:
        if ring == 0:
            found = _scan_cell(cy * columns + cx, x, y, exclude, xy, alive, items, start, best_d, out, found, k)
        else:
            for gx in range(max(cx - ring, 0), min(cx + ring, columns - 1) + 1):
                for gy in (cy - ring, cy + ring):
                    if 0 <= gy < rows:
                        found = _scan_cell(gy * columns + gx, x, y, exclude, xy, alive, items, start, best_d, out, found, k)
            for gy in range(max(cy - ring + 1, 0), min(cy + ring - 1, rows - 1) + 1):
                for gx in (cx - ring, cx + ring):
                    if 0 <= gx < columns:
                        found = _scan_cell(gy * columns + gx, x, y, exclude, xy, alive, items, start, best_d, out, found, k)
        if found == k and best_d[k - 1] <= ((ring + margin) * cell) ** 2:
            break
        if ring > columns + rows:
            break
        ring += 1
    return found


@numba.njit(**_JIT, inline="always")
def _fit_error(vertex, xy, height, alive, grid, neighbours, distances, polygons, sibson):  # pragma: no cover - compiled
    """|h - the height estimated from the nearest alive neighbours| (found into ``neighbours``)."""
    found = _nearest(xy[vertex, 0], xy[vertex, 1], vertex, xy, alive, grid, neighbours, distances, _NEIGHBOURS)
    for k in range(found, _NEIGHBOURS):
        neighbours[k] = -1
    if found == 0:
        return np.inf
    if distances[0] == 0.0:
        return abs(height[vertex] - height[neighbours[0]])
    if sibson and _sibson_weights(vertex, xy, neighbours, found, distances, polygons):
        # ``distances`` now holds the natural-neighbour weights.
        pass
    else:
        # Shepard (Eq. 3.10) with the classic power 2.
        for k in range(found):
            distances[k] = 1.0 / distances[k]
    weight_sum = 0.0
    estimate = 0.0
    for k in range(found):
        weight_sum += distances[k]
        estimate += distances[k] * height[neighbours[k]]
    return abs(height[vertex] - estimate / weight_sum)


@numba.njit(**_JIT)
def _sibson_weights(vertex, xy, neighbours, found, weights, polygons):  # pragma: no cover - compiled
    """Natural-neighbour (Sibson, Eq. 3.11) weights of the found neighbours, into ``weights``.

    The vertex is inserted into the Voronoi diagram of its neighbours: each
    weight is the area its new cell takes from that neighbour's cell. False
    (weights untouched) when the cell is unbounded, i.e. the vertex lies
    outside its neighbours' hull, as on an outline.
    """
    x0, y0 = xy[vertex, 0], xy[vertex, 1]
    reach = 0.0
    for k in range(found):
        reach = max(reach, abs(xy[neighbours[k], 0] - x0), abs(xy[neighbours[k], 1] - y0))
    box = 4.0 * reach
    # The vertex's cell: a box around it cut by the bisector with each neighbour.
    cell_x, cell_y = polygons[0], polygons[1]
    cell_x[0], cell_y[0] = -box, -box
    cell_x[1], cell_y[1] = box, -box
    cell_x[2], cell_y[2] = box, box
    cell_x[3], cell_y[3] = -box, box
    n = 4
    for k in range(found):
        px, py = xy[neighbours[k], 0] - x0, xy[neighbours[k], 1] - y0
        n = _clip(polygons, 0, n, px, py, 0.5 * (px * px + py * py))
    for k in range(n):
        if max(abs(cell_x[k]), abs(cell_y[k])) >= 0.999 * box:
            return False
    # The part of it each neighbour was nearest to before the insertion.
    for i in range(found):
        pix, piy = xy[neighbours[i], 0] - x0, xy[neighbours[i], 1] - y0
        polygons[2, :n] = cell_x[:n]
        polygons[3, :n] = cell_y[:n]
        m = n
        for j in range(found):
            if j != i and m > 0:
                pjx, pjy = xy[neighbours[j], 0] - x0, xy[neighbours[j], 1] - y0
                m = _clip(polygons, 2, m, pjx - pix, pjy - piy, 0.5 * (pjx * pjx + pjy * pjy - pix * pix - piy * piy))
        weights[i] = _area(polygons[2], polygons[3], m)
    return True


@numba.njit(**_JIT)
def _clip(polygons, row, n, ax, ay, b):  # pragma: no cover - compiled
    """Clip the convex polygon in rows ``row``, ``row + 1`` to ``a . q <= b``; returns its new vertex count."""
    xs, ys = polygons[row], polygons[row + 1]
    out_x, out_y = polygons[6], polygons[7]
    m = 0
    for i in range(n):
        j = i + 1 if i + 1 < n else 0
        si = ax * xs[i] + ay * ys[i] - b
        sj = ax * xs[j] + ay * ys[j] - b
        if si <= 0.0:
            out_x[m], out_y[m] = xs[i], ys[i]
            m += 1
        if (si < 0.0 < sj) or (sj < 0.0 < si):
            t = si / (si - sj)
            out_x[m], out_y[m] = xs[i] + t * (xs[j] - xs[i]), ys[i] + t * (ys[j] - ys[i])
            m += 1
    xs[:m] = out_x[:m]
    ys[:m] = out_y[:m]
    return m


@numba.njit(**_JIT, inline="always")
def _area(xs, ys, n):  # pragma: no cover - compiled
    total = 0.0
    for i in range(n):
        j = i + 1 if i + 1 < n else 0
        total += xs[i] * ys[j] - xs[j] * ys[i]
    return 0.5 * abs(total)


@numba.njit(**_JIT, inline="always")
def _outline_error(vertex, xy, height, previous, following):  # pragma: no cover - compiled
    """An outline vertex's distance (in-plane position and height) to the segment joining its two
    outline neighbours; 0 inside. Counting the height keeps outline corners that only bend in depth,
    such as where a ridge meets the outline."""
    if previous[vertex] < 0:
        return 0.0
    a, b = previous[vertex], following[vertex]
    px, py, pz = xy[vertex, 0] - xy[a, 0], xy[vertex, 1] - xy[a, 1], height[vertex] - height[a]
    dx, dy, dz = xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1], height[b] - height[a]
    length2 = dx * dx + dy * dy + dz * dz
    t = 0.0 if length2 == 0.0 else min(max((px * dx + py * dy + pz * dz) / length2, 0.0), 1.0)
    return math.sqrt((px - t * dx) ** 2 + (py - t * dy) ** 2 + (pz - t * dz) ** 2)


@numba.njit(**_JIT)
def _sift_down(keys, ids, size, position):  # pragma: no cover - compiled
    """Restore the four-ary heap below ``position`` after its key grew (or it was replaced)."""
    key, item = keys[position], ids[position]
    while True:
        first = 4 * position + 1
        if first >= size:
            break
        child = first
        for other in range(first + 1, min(first + 4, size)):
            if keys[other] < keys[child]:
                child = other
        if key <= keys[child]:
            break
        keys[position], ids[position] = keys[child], ids[child]
        position = child
    keys[position], ids[position] = key, item
