"""Progressive order and levels of detail against analytic surfaces."""

import numpy as np
import pytest

from rangesurf.lod import Level, build_levels, distance_level, prepare_levels, progressive_order, screen_space_level, select_level
from rangesurf.mesh import Surface, boundary_loops, triangulate_in_plane


def grid_surface(n, height_of, mask=None, plane=(np.nan,) * 4, interpolation="shepard"):
    rows, cols = np.mgrid[0:n, 0:n] / (n - 1)
    keep = np.ones(rows.shape, bool) if mask is None else mask(rows, cols)
    x, y = cols[keep], rows[keep]
    vertices = np.column_stack([x, y, height_of(x, y)])
    faces = triangulate_in_plane(vertices, [0, 0, -1, 2], max_edge=1.5 / (n - 1))
    surface = Surface(vertices, faces, np.tile([0, 0, -1.0], (len(vertices), 1)), np.full((len(vertices), 2), -1),
                      plane=plane)
    surface.lod_order, surface.lod_error = progressive_order(surface, interpolation=interpolation)
    return surface


def area(vertices, faces):
    corners = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()


@pytest.mark.parametrize("interpolation", ["shepard", "sibson"])
def test_a_plane_reduces_to_its_outline(interpolation):
    """An L-shaped flat patch: the coarsest level is the corners of its outline and covers the same area."""
    surface = grid_surface(21, lambda x, y: np.full(x.shape, 2.0), mask=lambda r, c: (r <= 0.5) | (c <= 0.5),
                           plane=(0.0, 0.0, -1.0, 2.0), interpolation=interpolation)
    (outline,) = boundary_loops(surface.faces)
    xy = surface.vertices[outline, :2].astype(float)
    before, after = xy - np.roll(xy, 1, axis=0), np.roll(xy, -1, axis=0) - xy
    turn = before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0]
    corners = set(outline[np.abs(turn) > 1e-9].tolist())
    # The L's six corners, with the reflex one cut by the half cell whose three corners are in the L.
    assert len(corners) == 7
    assert set(surface.lod_order[: len(corners)].tolist()) == corners
    assert np.allclose(surface.lod_error[len(corners):], 0, atol=1e-6)  # removing the rest changed nothing
    levels = build_levels(surface, min_vertices=len(corners))
    coarsest = levels[-1]
    kept = surface.vertices[surface.lod_order[: coarsest.count]].astype(float)
    assert coarsest.count < 16
    assert area(kept, coarsest.faces) == pytest.approx(area(surface.vertices.astype(float), surface.faces), rel=1e-6)


@pytest.mark.parametrize("interpolation", ["shepard", "sibson"])
def test_a_ridge_survives_coarse_levels(interpolation):
    """A roof (two planes meeting at a ridge): at 10 % of the vertices the ridge is still there."""
    surface = grid_surface(61, lambda x, y: 2.0 - 0.2 * np.abs(x - 0.5), interpolation=interpolation)
    level = select_level(build_levels(surface), fraction=0.1)
    kept = surface.lod_order[: level.count]
    vertices = surface.vertices.astype(float)
    # Height of the coarse mesh at every original vertex, by barycentric interpolation in (x, y).
    from scipy.spatial import Delaunay

    coarse = Delaunay(vertices[kept, :2])
    simplex = coarse.find_simplex(vertices[:, :2])
    inside = simplex >= 0
    transform = coarse.transform[simplex[inside]]
    b = np.einsum("ijk,ik->ij", transform[:, :2], vertices[inside, :2] - transform[:, 2])
    weights = np.column_stack([b, 1 - b.sum(axis=1)])
    estimate = (weights * vertices[kept][coarse.simplices[simplex[inside]], 2]).sum(axis=1)
    error = np.abs(estimate - vertices[inside, 2])
    ridge_height = 0.1
    assert error.max() < 0.05 * ridge_height
    assert level.error <= error.max() + 1e-9 or level.error < 0.05 * ridge_height


def test_sibson_reproduces_a_tilted_plane_from_scattered_neighbours():
    """Natural-neighbour weights have linear precision, inverse-distance weights do not.

    Jittered vertices on a plane tilted against the surface's reference
    plane: inside the patch Sibson predicts every height exactly, so the
    first quarter removed costs nothing; Shepard sees a (false) error.
    """
    rng = np.random.default_rng(1)
    n = 30
    rows, cols = np.mgrid[0:n, 0:n] / (n - 1)
    x = cols.ravel() + rng.uniform(-0.3, 0.3, n * n) / (n - 1)
    y = rows.ravel() + rng.uniform(-0.3, 0.3, n * n) / (n - 1)
    vertices = np.column_stack([x, y, 2 + 0.3 * x + 0.2 * y])
    surface = Surface(vertices, triangulate_in_plane(vertices, [0, 0, -1, 2]), np.tile([0, 0, -1.0], (n * n, 1)),
                      np.full((n * n, 2), -1), plane=(0, 0, -1, 2))
    first_quarter = {}
    for interpolation in ("shepard", "sibson"):
        _, error = progressive_order(surface, interpolation=interpolation)
        first_quarter[interpolation] = error[::-1][: n * n // 4].max()
    assert first_quarter["sibson"] < 1e-6
    assert first_quarter["shepard"] > 100 * first_quarter["sibson"]


def test_unknown_interpolation_is_refused():
    surface = grid_surface(5, lambda x, y: np.full(x.shape, 2.0))
    with pytest.raises(ValueError, match="interpolation"):
        progressive_order(surface, interpolation="kriging")


def test_order_is_a_permutation_and_errors_grow_towards_the_coarse_end():
    rng = np.random.default_rng(0)
    surface = grid_surface(25, lambda x, y: 2.0 + 0.01 * rng.standard_normal(x.shape))
    assert sorted(surface.lod_order.tolist()) == list(range(surface.n_vertices))
    assert (np.diff(surface.lod_error) <= 1e-7).all()  # order[k] removed later (more important) -> larger error


def test_levels_are_valid_meshes_with_per_vertex_error():
    surface = grid_surface(31, lambda x, y: 2.0 + 0.05 * np.sin(6 * x) * np.cos(5 * y))
    levels = build_levels(surface)
    assert levels[0].count == surface.n_vertices and levels[0].error == 0.0
    for level in levels:
        assert level.faces.size == 0 or level.faces.max() < level.count
        assert level.vertex_error.shape == (level.count,)
    counts = [level.count for level in levels]
    assert counts == sorted(counts, reverse=True)
    errors = [level.error for level in levels]
    assert errors == sorted(errors)
    # A finer level's outline is the full one.
    assert len(boundary_loops(levels[0].faces)) == 1


def test_level_selection():
    levels = [Level(count, np.zeros((0, 3), np.int32), error, spacing, np.zeros(count, np.float32))
              for count, error, spacing in ((1000, 0.0, 0.01), (500, 0.001, 0.014), (250, 0.004, 0.02))]
    assert select_level(levels, count=600).count == 1000
    assert select_level(levels, count=400).count == 500
    assert select_level(levels, fraction=0.25).count == 250
    assert select_level(levels, max_error=0.002).count == 500
    # Screen space, focal length 500 px: the finest level whose spacing is >= 1 px on screen.
    assert screen_space_level(levels, 2.0, 500.0).count == 1000  # 0.01 m at 2 m: 2.5 px
    assert screen_space_level(levels, 6.0, 500.0).count == 500  # 0.83 px, 1.17 px
    assert screen_space_level(levels, 10.0, 500.0).count == 250  # 0.02 m at 10 m: 1 px
    assert screen_space_level(levels, 30.0, 500.0).count == 250  # nothing is 1 px apart: the coarsest
    assert screen_space_level(levels, float("inf"), 500.0).count == 250  # behind or out of view
    assert distance_level(levels, 0.5).count == 1000 and distance_level(levels, 4.0).count == 250
    with pytest.raises(ValueError, match="exactly one"):
        select_level(levels, count=1, max_error=1.0)


@pytest.mark.parametrize("n_vertices", [0, 1, 2, 3])
def test_tiny_surfaces(n_vertices):
    vertices = np.column_stack([np.arange(n_vertices), np.zeros(n_vertices), np.full(n_vertices, 2.0)])
    faces = np.array([[0, 1, 2]]) if n_vertices == 3 else np.zeros((0, 3), int)
    surface = Surface(vertices, faces, np.tile([0, 0, -1.0], (n_vertices, 1)), np.full((n_vertices, 2), -1),
                      plane=(0, 0, -1, 2))
    order, error = progressive_order(surface)
    assert sorted(order.tolist()) == list(range(n_vertices)) and error.shape == (n_vertices,)


def test_coarse_levels_keep_holes_open():
    hole = lambda r, c: ~((np.abs(r - 0.5) < 0.2) & (np.abs(c - 0.5) < 0.2))
    surface = grid_surface(31, lambda x, y: np.full(x.shape, 2.0), mask=hole, plane=(0.0, 0.0, -1.0, 2.0))
    full = area(surface.vertices.astype(float), surface.faces)
    for level in build_levels(surface, min_vertices=8):
        kept = surface.vertices[surface.lod_order[: level.count]].astype(float)
        # Never over the hole; the unconstrained Delaunay may miss slivers along it.
        assert 0.95 * full <= area(kept, level.faces) <= full * (1 + 1e-6)
        assert len(boundary_loops(level.faces)) >= 2


def test_view_level_follows_distance_and_culls():
    from rangesurf.lod import prepare_levels, view_level

    surface = grid_surface(41, lambda x, y: 2.0 + 0.02 * np.sin(8 * x))
    prepare_levels(surface)
    view = dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)

    def at(distance, sideways=0.0):
        transform = np.eye(4)
        transform[:3, 3] = (sideways - 0.5, -0.5, distance - 2.0)  # the patch's centre `distance` ahead
        return view_level(surface, transform, **view).count

    near, middle, far = at(1.5), at(20.0), at(200.0)
    assert near >= middle >= far and near > far
    assert far == surface.levels[-1].count or far < middle
    assert at(5.0, sideways=100.0) == surface.levels[-1].count  # far off to the side: out of view
    behind = np.diag([1.0, 1.0, -1.0, 1.0])
    assert view_level(surface, behind, **view).count == surface.levels[-1].count


@pytest.mark.parametrize("case", ["empty", "one", "three", "collinear", "duplicates"])
def test_levels_of_degenerate_surfaces(case):
    from rangesurf.lod import prepare_levels

    vertices = {
        "empty": np.zeros((0, 3)),
        "one": np.array([[0.0, 0.0, 2.0]]),
        "three": np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0], [0.0, 0.1, 2.0]]),
        "collinear": np.column_stack([np.linspace(0, 1, 10), np.zeros(10), np.full(10, 2.0)]),
        "duplicates": np.array([[0.0, 0.0, 2.0]] * 5 + [[0.1, 0.0, 2.0], [0.0, 0.1, 2.0]]),
    }[case]
    faces = triangulate_in_plane(vertices, [0, 0, -1, 2]) if len(vertices) else np.zeros((0, 3), int)
    surface = Surface(vertices, faces, np.tile([0, 0, -1.0], (len(vertices), 1)), np.full((len(vertices), 2), -1),
                      plane=(0, 0, -1, 2))
    prepare_levels(surface)
    assert sorted(surface.lod_order.tolist()) == list(range(len(vertices)))
    coarse = surface.at_level(fraction=0.5)
    assert coarse.n_vertices <= surface.n_vertices
    assert coarse.faces.size == 0 or coarse.faces.max() < coarse.n_vertices


def test_ul4_holds_the_removed_vertices_heights():
    """At 10 % of the vertices, +-2 UL4 of the nearest kept vertex holds about 95 % of the removed vertices'
    heights above the level's triangles (measured here with SciPy's Delaunay), not all of them: a sigma."""
    from scipy.spatial import Delaunay, cKDTree

    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[0:60, 0:60] * 0.02
    x, y = cols.ravel(), rows.ravel()
    vertices = np.column_stack([x, y, 2.0 + 0.02 * np.sin(5 * x) * np.cos(4 * y) + 0.001 * rng.standard_normal(x.size)])
    surface = prepare_levels(Surface(vertices, triangulate_in_plane(vertices, [0, 0, -1, 2.0]), np.tile([0, 0, -1.0], (x.size, 1)),
                                     np.full((x.size, 2), -1), plane=[0, 0, -1, 2.0]))
    coarse = surface.at_level(fraction=0.1)
    kept, removed = surface.lod_order[: coarse.n_vertices], surface.lod_order[coarse.n_vertices :]
    triangulation = Delaunay(vertices[kept, :2])
    simplex = triangulation.find_simplex(vertices[removed, :2])
    inside = simplex >= 0
    affine = triangulation.transform[simplex[inside]]
    partial = np.einsum("ijk,ik->ij", affine[:, :2], vertices[removed][inside, :2] - affine[:, 2])
    weights = np.column_stack([partial, 1 - partial.sum(axis=1)])
    height = (vertices[kept, 2][triangulation.simplices[simplex[inside]]] * weights).sum(axis=1)
    error = np.abs(vertices[removed][inside, 2] - height)
    _, nearest = cKDTree(vertices[kept, :2]).query(vertices[removed][inside, :2])
    share = np.mean(error <= 2 * coarse.uncertainty["UL4"][nearest])
    assert inside.sum() > 2000 and 0.85 <= share <= 0.98  # measured 0.90 (0.99 with the running maxima)
