"""Uncertainty geometry against analytic cases: a flat patch with known per-level sigmas."""

import numpy as np
import pytest

from rangesurf.glyphs import (
    LEVEL_COLOURS, bars, combined_uncertainty, cones, displaced_points, hue_colours, opacity, oscillating, perturbed,
    shells, uncertainty_volume,
)
from rangesurf.mesh import Surface, triangulate_in_plane


def patch(n=11, ul1=0.01, ul4=0.02, size=1.0):
    """A flat n x n patch at z = 2 facing -z (toward a sensor at the origin), UL1 and UL4 constant."""
    rows, cols = np.mgrid[0:n, 0:n] / (n - 1) * size
    vertices = np.column_stack([cols.ravel(), rows.ravel(), np.full(n * n, 2.0)])
    faces = triangulate_in_plane(vertices, [0, 0, -1, 2.0])
    uncertainty = {"UL1": np.full(n * n, ul1), "UL4": np.full(n * n, ul4)}
    return Surface(vertices, faces, np.tile([0, 0, -1.0], (n * n, 1)), np.full((n * n, 2), -1), plane=[0, 0, -1, 2.0],
                   uncertainty=uncertainty)


def test_combined_uncertainty_is_the_root_sum_of_squares():
    surface = patch()
    assert np.allclose(combined_uncertainty(surface), np.hypot(0.01, 0.02))
    assert np.allclose(combined_uncertainty(surface, ("UL1",)), 0.01)
    assert np.isnan(combined_uncertainty(surface, ("UL2", "UL3"))).all()
    with pytest.raises(ValueError, match="UL5"):
        combined_uncertainty(surface, ("UL5",))


def test_colour_and_opacity_mapping():
    colours = hue_colours(np.array([0.0, 0.005, 0.01]), vmax=0.01)
    brightness = colours[:, :3].astype(int).sum(axis=1)
    assert (np.diff(brightness) > 0).all()  # warmer and brighter = less certain
    assert opacity(np.array([0.0, 1.0]), vmax=0.5, floor=0.3) == pytest.approx([1.0, 0.3])
    with pytest.raises(ValueError, match="floor"):
        opacity(np.zeros(2), vmax=1.0, floor=1.5)


def test_shells_lie_at_plus_minus_scale_sigma():
    surface = patch()
    outer, inner = shells(surface, scale=2.0)
    sigma = np.hypot(0.01, 0.02)
    # The normal faces -z: the outer shell is nearer the sensor.
    assert np.allclose(outer.vertices[:, 2], 2.0 - 2 * sigma, atol=1e-6)
    assert np.allclose(inner.vertices[:, 2], 2.0 + 2 * sigma, atol=1e-6)
    assert (outer.colours[:, 3] < 255).all()  # semi-transparent
    outer_only, _ = shells(surface, ("UL1",), scale=1.0)
    assert np.allclose(outer_only.vertices[:, 2], 1.99, atol=1e-6)


def test_uncertainty_volume_is_a_closed_solid_of_the_right_size():
    import trimesh

    surface = patch(size=0.5)
    volume = uncertainty_volume(surface, ("UL1",), scale=2.0)
    mesh = trimesh.Trimesh(volume.vertices, volume.faces, process=True)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(0.25 * 4 * 0.01, rel=1e-3)  # area x 2 x 2 sigma, outward faces


def test_stacked_bars_add_up_and_separate_bars_start_at_the_surface():
    surface = patch(n=3)
    stacked = bars(surface, ("UL1", "UL4"), scale=1.0, mode="stacked")
    assert stacked.segments.shape == (2 * 9 * 2, 2, 3)
    lengths = np.linalg.norm(stacked.segments[:, 1] - stacked.segments[:, 0], axis=1)
    assert np.allclose(np.sort(np.unique(lengths.round(6))), [0.01, 0.02])
    reach = np.abs(stacked.segments[:, :, 2] - 2.0).max()
    assert reach == pytest.approx(0.03, abs=1e-6)  # 1 cm + 2 cm, stacked
    separate = bars(surface, ("UL1", "UL4"), scale=1.0, mode="separate")
    assert np.allclose(separate.segments[:, 0, 2], 2.0, atol=1e-6)
    assert np.abs(separate.segments[:, :, 2] - 2.0).max() == pytest.approx(0.02, abs=1e-6)
    assert tuple(stacked.colours[0]) == LEVEL_COLOURS["UL1"] and tuple(stacked.colours[1]) == LEVEL_COLOURS["UL4"]


def test_displaced_points_follow_eq_2_7():
    surface = patch()
    sigma = np.hypot(0.01, 0.02)
    edges = displaced_points(surface, scale=2.0, random=False)
    assert np.allclose(np.abs(edges.points[:, 2] - 2.0), 2 * sigma, atol=1e-6)
    spread = displaced_points(surface, scale=2.0, random=True, seed=1)
    offset = np.abs(spread.points[:, 2] - 2.0)
    assert offset.max() <= 2 * sigma + 1e-6 and offset.mean() == pytest.approx(sigma, rel=0.15)  # uniform [0, 2 sigma]
    separate = displaced_points(surface, ("UL1", "UL4"), scale=1.0, random=False, mode="separate")
    assert len(separate.points) == 2 * surface.n_vertices * 2
    assert set(np.round(np.abs(separate.points[:, 2].astype(np.float64) - 2.0), 5).tolist()) == {0.01, 0.02}


def test_falloff_bends_the_scale_but_keeps_the_reference():
    surface = patch()
    surface.uncertainty["UL1"] = np.linspace(0.001, 0.02, surface.n_vertices)
    surface.uncertainty.pop("UL4")
    linear = np.abs(displaced_points(surface, ("UL1",), random=False, scale=1.0).points[:, 2] - 2.0)
    steep = np.abs(displaced_points(surface, ("UL1",), random=False, scale=1.0, falloff=2.0).points[:, 2] - 2.0)
    assert (steep[: surface.n_vertices][:10] < linear[: surface.n_vertices][:10]).all()  # small values shrink


def test_cones_carry_two_levels():
    surface = patch(n=5)
    glyphs = cones(surface, "UL1", "UL4", scale=2.0, sides=6)
    per_cone = 6 + 2
    assert len(glyphs.vertices) == 25 * per_cone and len(glyphs.faces) == 25 * 12
    first = glyphs.vertices[:per_cone].astype(np.float64)
    base = surface.vertices[surface.lod_order[0]]
    assert np.allclose(np.linalg.norm(first[:6] - base, axis=1), 0.02, atol=1e-6)  # radius 2 x UL1
    assert np.allclose(first[6], base + [0, 0, -0.04], atol=1e-6)                  # apex 2 x UL4 along the normal
    assert len(cones(surface, max_glyphs=7).vertices) == 7 * (8 + 2)


def test_perturbation_and_oscillation():
    surface = patch(n=40)
    rough = perturbed(surface, ("UL1",), scale=1.0, seed=3)
    assert np.std(rough.vertices[:, 2] - 2.0) == pytest.approx(0.01, rel=0.1)
    assert np.array_equal(rough.faces, surface.faces)
    top = oscillating(surface, ("UL1",), phase=0.25, scale=2.0)
    assert np.allclose(top.vertices[:, 2], 2.0 - 0.02, atol=1e-6)
    rest = oscillating(surface, ("UL1",), phase=0.5, scale=2.0)
    assert np.allclose(rest.vertices[:, 2], 2.0, atol=1e-6)


def test_missing_levels_and_bad_settings():
    surface = patch()
    none = bars(surface, ("UL2",), scale=2.0)
    assert np.allclose(none.segments[:, 0], none.segments[:, 1])  # no UL2: zero-length bars
    with pytest.raises(ValueError, match="scale"):
        shells(surface, scale=0)
    with pytest.raises(ValueError, match="mode"):
        bars(surface, mode="sideways")
    empty = Surface(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2)))
    assert len(uncertainty_volume(empty).vertices) == 0 and len(cones(empty).vertices) == 0
