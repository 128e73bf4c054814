"""Grid and in-plane triangulation, outlines and holes, against analytic cases and simulated frames."""

import numpy as np
import pytest

from rangesurf import simulate
from rangesurf.frame import get_sensor
from rangesurf.mesh import Surface, boundary_loops, segment_vertices, triangulate_in_plane, triangulate_segments
from rangesurf.segment import Segmentation, segment_frame
from rangesurf.segment.evaluate import truth_segmentation

SR3000 = get_sensor("sr3000")
RAYS = SR3000.projection.directions(*SR3000.shape)


def wall(depth=2.0):
    return (RAYS * depth).astype(np.float32)


def one_segment(labels, plane=(0.0, 0.0, -1.0, 2.0)):
    count = int(labels.max())
    planes = np.full((count + 1, 4), np.nan)
    planes[1:] = plane
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    return Segmentation(labels.astype(np.int32), planes, np.r_[np.nan, np.full(count, 0.002)], sizes)


def test_full_grid_gives_two_triangles_per_cell_facing_the_sensor():
    height, width = SR3000.shape
    labels = np.ones(SR3000.shape, np.int32)
    (surface,) = triangulate_segments(wall(), one_segment(labels))
    assert surface.n_vertices == height * width
    assert surface.n_faces == 2 * (height - 1) * (width - 1)
    corners = surface.vertices[surface.faces].astype(float)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (np.einsum("ij,ij->i", normals, corners.mean(axis=1)) < 0).all()  # counter-clockwise from the sensor
    # The mesh covers the wall's visible rectangle exactly.
    x = surface.vertices[:, 0]
    y = surface.vertices[:, 1]
    assert surface.area() == pytest.approx(np.ptp(x) * np.ptp(y), rel=1e-4)
    assert np.allclose(surface.normals, [0, 0, -1])
    assert np.allclose(surface.uncertainty["UL2"], 0.002)


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_checkerboard_vertices_are_every_other_strided_pixel(stride):
    labels = np.zeros(SR3000.shape, np.int32)
    labels[10:70, 20:90], labels[80:140, 30:170] = 1, 2
    points = wall()
    points[85, 40] = np.nan  # an invalid pixel on the board gives no vertex
    sigma = np.full(SR3000.shape, 0.01)
    square = segment_vertices(points, one_segment(labels), range_sigma=sigma, stride=stride)
    board = segment_vertices(points, one_segment(labels), range_sigma=sigma, stride=stride, checkerboard=True)
    assert [surface.segment for surface in board] == [1, 2]
    for full, half in zip(square, board):
        rows, cols = full.pixels.T // stride
        black = (rows + cols) % 2 == 0
        # Exactly the square grid's vertices on the black squares, with their points and uncertainties (UL1
        # scaled to the fit residual by the RMS noise of the vertices taken, a hair different on half of them).
        assert np.array_equal(half.pixels, full.pixels[black])
        assert np.array_equal(half.vertices, full.vertices[black])
        assert np.allclose(half.uncertainty["UL1"], full.uncertainty["UL1"][black], rtol=1e-3)
        assert abs(half.n_vertices - full.n_vertices / 2) <= 1
    assert not any((surface.pixels == [85, 40]).all(axis=1).any() for surface in board)
    with pytest.raises(ValueError, match="checkerboard"):
        segment_vertices(points, one_segment(labels), checkerboard="yes")


def test_no_triangle_spans_a_depth_step():
    points = wall(3.0)
    box = np.zeros(SR3000.shape, bool)
    box[40:100, 60:120] = True
    points[box] = (RAYS[box] * 2.0).astype(np.float32)
    # One label for both on purpose: only the step test can keep them apart.
    (surface,) = triangulate_segments(points, one_segment(np.ones(SR3000.shape, np.int32)))
    depth = surface.vertices[surface.faces][..., 2]
    assert (np.ptp(depth, axis=1) < 0.1).all()
    # Two separate pieces: the box's outline and the wall's outline with its hole.
    loops = boundary_loops(surface.faces)
    assert len(loops) == 3


def test_three_corner_cells_follow_a_diagonal_outline():
    labels = np.zeros((20, 20), np.int32)
    rows, cols = np.mgrid[0:20, 0:20]
    labels[cols <= rows] = 1  # a lower triangle of the grid
    points = wall()[:20, :20]
    (surface,) = triangulate_segments(points, one_segment(labels))
    full_cells = 19 * 18 // 2
    assert surface.n_faces == 2 * full_cells + 19  # plus one triangle per diagonal cell


def test_hole_is_found():
    labels = np.ones(SR3000.shape, np.int32)
    labels[60:70, 80:95] = 0
    (surface,) = triangulate_segments(wall(), one_segment(labels))
    loops = boundary_loops(surface.faces)
    assert len(loops) == 2
    outline, hole = loops
    outline_pixels = surface.pixels[outline]
    assert outline_pixels[:, 0].min() == 0 and outline_pixels[:, 0].max() == SR3000.shape[0] - 1
    hole_pixels = surface.pixels[hole]
    assert hole_pixels[:, 0].min() == 59 and hole_pixels[:, 0].max() == 70
    assert hole_pixels[:, 1].min() == 79 and hole_pixels[:, 1].max() == 95


def test_simulated_frame_meshes_every_segment_without_steps():
    frames, truths = simulate.simulate_sequence("arena", "sr3000", 1, seed=2)
    result = segment_frame(frames[0])
    surfaces = triangulate_segments(result.points, result.segmentation)
    assert len(surfaces) >= result.segmentation.n_segments - 1
    # True planes; grazing (> 80 degrees), mixed and spike pixels are 0.
    truth = truth_segmentation(truths[0], frames[0].rays).labels
    for surface in surfaces:
        label = surface.segment
        assert (result.segmentation.labels[surface.pixels[:, 0], surface.pixels[:, 1]] == label).all()
        offsets = np.abs(surface.vertices @ surface.plane[:3] + surface.plane[3])
        # Vertices near their plane (denoised points): within the pixels' own range noise (the segments' join test;
        # pixels of a box's grazing top, 21 cm sigma, may be 20 cm off), and but a few further than 7 cm.
        sigma = result.range_sigma[surface.pixels[:, 0], surface.pixels[:, 1]]
        assert (offsets < 3 * sigma).all() and np.percentile(offsets, 99) < 0.07
        # Most of the segment's pixels are vertices if it is mostly one true plane. Not so where it holds
        # surface seen almost edge-on (a box top at eye level), whose triangles are dropped as steps:
        # seed 2 has a 230-pixel segment of several surfaces near a box's grazing top.
        on_truth = truth[result.segmentation.labels == label]
        if np.bincount(on_truth[on_truth > 0]).max(initial=0) > 0.5 * on_truth.size:
            assert surface.n_vertices >= 0.9 * result.segmentation.sizes[label]


def test_delaunay_in_plane_covers_a_square_and_keeps_a_hole_open():
    rows, cols = np.mgrid[0:11, 0:11] * 0.1
    keep = ~((rows > 0.35) & (rows < 0.65) & (cols > 0.35) & (cols < 0.65))
    points = np.column_stack([cols[keep], rows[keep], np.full(keep.sum(), 2.0)])
    faces = triangulate_in_plane(points, [0, 0, -1, 2], max_edge=0.15)
    corners = points[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (normals[:, 2] < 0).all()  # counter-clockwise seen from the normal's side (-z)
    area = 0.5 * np.linalg.norm(normals, axis=1).sum()
    # The square minus the hole: 4x4 cells around the 3x3 missing points, less the half cells at its
    # corners, whose three remaining corners make a short-edged triangle.
    assert area == pytest.approx(1.0 - 0.16 + 4 * 0.005, abs=1e-9)
    assert len(boundary_loops(faces)) == 2
    # The default edge limit (3 spacings) cuts the hole's corners but leaves it open.
    default = triangulate_in_plane(points, [0, 0, -1, 2])
    assert len(boundary_loops(default)) == 2 and len(default) > len(faces)


@pytest.mark.parametrize("points", [np.zeros((0, 3)), np.ones((1, 3)), np.ones((2, 3)),
                                    np.array([[0, 0, 2], [1, 0, 2], [2, 0, 2]], float),
                                    np.array([[0, 0, 2], [0, 0, 2], [0, 0, 2]], float)])
def test_degenerate_vertex_sets_give_no_triangles(points):
    assert triangulate_in_plane(points, [0, 0, -1, 2]).shape == (0, 3)


def test_duplicate_vertices_are_harmless():
    square = np.array([[0, 0, 2], [1, 0, 2], [1, 1, 2], [0, 1, 2], [1, 1, 2]], float)
    faces = triangulate_in_plane(square, [0, 0, -1, 2])
    assert len(faces) == 2


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        triangulate_in_plane(np.zeros((4, 2)), [0, 0, 1, 0])
    with pytest.raises(ValueError, match="normal"):
        triangulate_in_plane(np.zeros((4, 3)), [0, 0, 0, 0])
    with pytest.raises(ValueError, match="do not match"):
        triangulate_segments(wall(), one_segment(np.ones((10, 10), np.int32)))
    with pytest.raises(ValueError, match="disagree"):
        Surface(vertices=np.zeros((3, 3)), faces=[[0, 1, 2]], normals=np.zeros((2, 3)), pixels=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="index vertices"):
        Surface(vertices=np.zeros((3, 3)), faces=[[0, 1, 3]], normals=np.zeros((3, 3)), pixels=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="UL"):
        Surface(vertices=np.zeros((3, 3)), faces=[[0, 1, 2]], normals=np.zeros((3, 3)), pixels=np.zeros((3, 2)),
                uncertainty={"UL9": np.zeros(3)})


def test_empty_segmentation_gives_no_surfaces():
    labels = np.zeros(SR3000.shape, np.int32)
    empty = Segmentation(labels, np.full((1, 4), np.nan), np.full(1, np.nan), np.array([0]))
    assert triangulate_segments(wall(), empty) == []


def test_small_holes_are_filled_and_large_ones_kept():
    from rangesurf.mesh import fill_small_holes

    labels = np.ones(SR3000.shape, np.int32)
    labels[60:62, 80:82] = 0  # a small hole (a few centimetres around at 2 m)
    labels[20:50, 20:60] = 0  # a large one
    (surface,) = triangulate_segments(wall(), one_segment(labels))
    loops = boundary_loops(surface.faces)
    assert len(loops) == 3
    filled = fill_small_holes(surface, max_perimeter=0.2)
    assert len(boundary_loops(filled.faces)) == 2
    assert filled.n_vertices == surface.n_vertices + 1
    assert filled.area() > surface.area()
    assert (filled.pixels[-1] == -1).all() and filled.uncertainty["UL2"][-1] == pytest.approx(0.002)
    new = filled.vertices[-1]
    assert new[2] == pytest.approx(2.0, abs=1e-5)  # on the wall's plane
    corners = filled.vertices[filled.faces[-8:]].astype(float)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (normals[:, 2] < 0).all()  # wound like the rest: facing the sensor
    assert fill_small_holes(surface, max_perimeter=0.0) is surface
    with pytest.raises(ValueError, match="max_perimeter"):
        fill_small_holes(surface, max_perimeter=-1)
