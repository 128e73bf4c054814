"""The global model against simulated scenes with known planes and poses."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rangesurf import simulate
from rangesurf.frame import PinholeProjection
from rangesurf.io import FormatError
from rangesurf.merge import GlobalModel
from rangesurf.mesh import Surface, triangulate_in_plane, triangulate_segments
from rangesurf.segment import segment_frame


def wall(noise=0.0, seed=0, offset=0.0, size=(30, 40), spacing=0.02, sigma=None):
    """A flat wall 2 m in front of the sensor (z forward), as one surface with known noise."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0 : size[0], 0 : size[1]] * spacing
    count = rows.size
    depth = 2.0 + offset + noise * rng.standard_normal(count)
    vertices = np.column_stack([cols.ravel(), rows.ravel(), depth])
    uncertainty = {} if sigma is None else {"UL1": np.full(count, sigma)}
    return Surface(vertices, triangulate_in_plane(vertices, [0, 0, -1, 2.0]), np.tile([0, 0, -1.0], (count, 1)),
                   np.full((count, 2), -1), plane=[0, 0, -1, 2.0 + offset], uncertainty=uncertainty)


def heights(model):
    (surface,) = model.surfaces(lod=False)
    return surface.vertices[:, 2].astype(np.float64) - 2.0, surface


def test_repeated_views_average_the_noise_and_add_no_vertex():
    model = GlobalModel(cell_size=0.02)
    sigma = 0.005
    for seed in range(16):
        model.add_frame([wall(sigma, seed, sigma=sigma)], np.eye(4))
        assert model.n_vertices == 1200
    error, surface = heights(model)
    # 16 equal observations: the fused heights scatter sigma / 4, and UL1 says so (the observations'
    # measured scatter agrees with the sensor sigma they came with).
    assert np.std(error) == pytest.approx(sigma / 4, rel=0.15)
    assert np.median(surface.uncertainty["UL1"]) == pytest.approx(sigma / 4, rel=0.15)
    # They agree within their noise, so merging adds (almost) no uncertainty.
    assert np.median(surface.uncertainty["UL3"]) < sigma / 4


def test_ul1_follows_the_scatter_up_but_not_down():
    """Views that scatter twice as much as their sigma says raise UL1 about twice; views that err alike do not
    lower it.

    Sixteen views with one and the same noise (an error every frame shares, like a denoising bias) scatter
    not at all, and their fused heights are as far off as one view: UL1 stays at the sensor model's
    sigma / 4 rather than shrinking toward zero with the scatter.
    """
    sigma = 0.005
    noisy, shared = GlobalModel(cell_size=0.02), GlobalModel(cell_size=0.02)
    for seed in range(16):
        noisy.add_frame([wall(2 * sigma, seed, sigma=sigma)], np.eye(4))
        shared.add_frame([wall(sigma, 0, sigma=sigma)], np.eye(4))
    error, surface = heights(noisy)
    assert np.std(error) == pytest.approx(2 * sigma / 4, rel=0.15)
    assert np.median(surface.uncertainty["UL1"]) == pytest.approx(2 * sigma / 4, rel=0.2)
    error, surface = heights(shared)
    assert np.std(error) == pytest.approx(sigma, rel=0.15)
    assert np.allclose(surface.uncertainty["UL1"], sigma / 4, rtol=1e-3)


def test_disagreeing_views_raise_ul3():
    """Two exact views 3 cm apart (a registration error): the fused wall sits between and UL3 says 1.5 cm."""
    model = GlobalModel(cell_size=0.02, max_plane_distance=0.1)
    model.add_frame([wall(sigma=0.001)], np.eye(4))
    model.add_frame([wall(sigma=0.001, offset=0.03)], np.eye(4))
    error, surface = heights(model)
    assert np.allclose(error, 0.015, atol=1e-6)
    assert np.median(surface.uncertainty["UL3"]) == pytest.approx(0.015, rel=0.01)


def test_pose_covariance_becomes_registration_uncertainty():
    """A pose uncertain by 1 cm along the wall's normal gives its vertices UL3 = 1 cm; sideways, nothing."""
    along_normal, sideways = np.zeros((6, 6)), np.zeros((6, 6))
    along_normal[5, 5] = sideways[3, 3] = 0.01**2
    for covariance, expected in ((along_normal, 0.01), (sideways, 0.0)):
        model = GlobalModel(cell_size=0.02)
        model.add_frame([wall(sigma=0.001)], np.eye(4), covariance=covariance)
        _, surface = heights(model)
        assert np.allclose(surface.uncertainty["UL3"], expected, atol=1e-6)


def test_overlapping_views_zipper_into_one_patch_that_grows_with_area():
    """Two views of one wall, shifted sideways by half its width: one patch, 1.5 walls of vertices."""
    model = GlobalModel(cell_size=0.02)
    model.add_frame([wall(sigma=0.001)], np.eye(4))
    shifted = np.eye(4)
    shifted[0, 3] = 0.4
    step = model.add_frame([wall(sigma=0.001)], shifted)
    assert (step.fused, step.created) == (1, 0)
    assert len(model.patches) == 1
    assert model.n_vertices == 30 * 60
    (surface,) = model.surfaces(lod=False)
    assert surface.area() == pytest.approx(0.58 * 1.18, rel=0.02)


def test_a_gap_of_two_cells_is_bridged_and_marked_uncertain():
    model = GlobalModel(cell_size=0.02, bridge=1)
    left = wall(size=(30, 20), sigma=0.001)
    model.add_frame([left], np.eye(4))
    shifted = np.eye(4)
    shifted[0, 3] = 0.42  # one empty column of cells between the halves
    model.add_frame([left], shifted)
    assert len(model.patches) == 1
    (surface,) = model.surfaces(lod=False)
    bridged = np.isclose(surface.uncertainty["UL3"], 0.02)
    assert bridged.sum() == 30  # the missing column, on the plane
    assert np.allclose(surface.vertices[bridged, 2], 2.0, atol=1e-4)
    assert surface.area() == pytest.approx(0.80 * 0.58, rel=0.02)


def test_separate_planes_stay_separate():
    """A parallel wall 20 cm behind, and a wall facing the other way, start their own patches."""
    model = GlobalModel(cell_size=0.02)
    model.add_frame([wall(sigma=0.001)], np.eye(4))
    behind = model.add_frame([wall(sigma=0.001, offset=0.2)], np.eye(4))
    turned = np.diag([-1.0, 1.0, -1.0, 1.0])
    turned[2, 3] = 4.0  # seen from the far side
    back = model.add_frame([wall(sigma=0.001)], turned)
    assert behind.created == 1 and back.created == 1
    assert len(model.patches) == 3


def _panel(angle_deg, x_range, sigma=0.001, spacing=0.02, height=0.6):
    """A panel through the line x = 1, z = 2 (along y), turned by ``angle_deg`` about it from the plane z = 2."""
    angle = np.radians(angle_deg)
    rows, cols = np.mgrid[0:height:spacing, x_range[0]:x_range[1]:spacing]
    along = cols.ravel() - 1.0
    vertices = np.column_stack([1.0 + along * np.cos(angle), rows.ravel(), 2.0 + along * np.sin(angle)])
    normal = np.array([np.sin(angle), 0.0, -np.cos(angle)])
    plane = np.r_[normal, -normal @ [1.0, 0.0, 2.0]]
    count = len(vertices)
    return Surface(vertices, triangulate_in_plane(vertices, plane), np.tile(normal, (count, 1)), np.full((count, 2), -1),
                   plane=plane, uncertainty={"UL1": np.full(count, sigma)})


def test_a_segment_between_two_planes_does_not_join_them():
    """A floor and a ramp 13 degrees off it meet along a crease; a segment across the crease at 6.5 degrees comes
    within the angle tolerance (10 degrees) of both, but the two patches are not one plane and stay apart."""
    model = GlobalModel(cell_size=0.02)
    model.add_frame([_panel(0.0, (0.0, 1.0))], np.eye(4))
    model.add_frame([_panel(13.0, (1.0, 2.0))], np.eye(4))
    assert len(model.patches) == 2
    step = model.add_frame([_panel(6.5, (0.8, 1.2))], np.eye(4))
    assert step.fused == 1 and step.joined == 0
    assert len(model.patches) == 2
    angles = sorted(np.degrees(np.arccos(np.clip(-patch.world_plane()[2], -1, 1))) for patch in model.patches)
    assert angles == pytest.approx([0.0, 13.0], abs=1.5)


def test_a_segment_grown_across_a_crease_does_not_stretch_the_reach():
    """A ramp segment that took in 30 cm of the floor before its foot (a shallow crease, 16 degrees) fits its plane
    with a 2.8 cm residual (UL2). Its points join the ramp's patch within 3 sigma of noise and registration (here the
    floor of 2 cells, 4 cm), not of the fit: the floor points farther from the ramp's plane are rejected, and the
    patch gets no cell there. (With the fit counted the reach was 8.5 cm and took in the whole strip: on a 600-frame
    SR-3000 arena run such segments tilted the ramp's patch by 2.4 degrees, 70 % of its cells on the floor.)"""
    model = GlobalModel(cell_size=0.02)
    model.add_frame([_panel(0.0, (0.0, 1.0))], np.eye(4))
    model.add_frame([_panel(16.0, (1.0, 2.0))], np.eye(4))
    ramp, floor = _panel(16.0, (1.0, 1.6)), _panel(0.0, (0.7, 1.0))
    vertices = np.vstack([ramp.vertices, floor.vertices])
    fit = np.sqrt(np.mean((vertices @ ramp.plane[:3] + ramp.plane[3]) ** 2))
    assert fit == pytest.approx(0.028, abs=0.001)
    count = len(vertices)
    crossing = Surface(vertices, np.zeros((0, 3), np.int32), np.tile(ramp.plane[:3], (count, 1)), np.full((count, 2), -1),
                       plane=ramp.plane, uncertainty={"UL1": np.full(count, 0.001), "UL2": np.full(count, fit)})
    step = model.add_frame([crossing], np.eye(4))
    assert step.fused == 1 and step.created == 0
    far = np.abs(floor.vertices @ ramp.plane[:3] + ramp.plane[3]) > 0.04 + 1e-9
    assert step.rejected == far.sum() > 0
    ramp_patch = max(model.patches, key=lambda patch: abs(patch.world_plane()[0]))
    cells = ramp_patch.surface().vertices
    assert np.abs(cells @ ramp.plane[:3] + ramp.plane[3]).max() < 0.04 + 0.01


def _misfit(x_range, angle_deg=30.0):
    """Points on the plane z = 2 (a 1 mm noisy strip over x_range) whose segment reports a normal ``angle_deg`` off."""
    rng = np.random.default_rng(5)
    rows, cols = np.mgrid[0:0.3:0.02, x_range[0]:x_range[1]:0.02]
    vertices = np.column_stack([cols.ravel(), rows.ravel(), 2.0 + 0.001 * rng.standard_normal(cols.size)])
    angle = np.radians(angle_deg)
    normal = np.array([np.sin(angle), 0.0, -np.cos(angle)])
    plane = np.r_[normal, -normal @ vertices.mean(axis=0)]
    count = len(vertices)
    return Surface(vertices, np.zeros((0, 3), np.int32), np.tile(normal, (count, 1)), np.full((count, 2), -1),
                   plane=plane, uncertainty={"UL1": np.full(count, 0.001)})


def test_a_segment_with_a_wrong_normal_over_a_patch_is_a_view_of_it():
    """A strip of the floor whose segment claims a normal 30 degrees off: fused into the floor, no new patch.
    The same strip beyond the floor's cells (new area), or a panel really rising 30 degrees, starts its own."""
    model = GlobalModel(cell_size=0.02)
    model.add_frame([_panel(0.0, (0.0, 1.0))], np.eye(4))
    seen_again = model.add_frame([_misfit((0.2, 0.6))], np.eye(4))
    assert seen_again.created == 0 and seen_again.fused == 1 and seen_again.cells_added == 0
    assert len(model.patches) == 1 and model.patches[0].world_plane()[2] == pytest.approx(-1.0, abs=1e-6)
    beyond = model.add_frame([_misfit((1.2, 1.6))], np.eye(4))
    rising = model.add_frame([_panel(30.0, (1.0, 1.4))], np.eye(4))
    assert beyond.created == 1 and rising.created == 1


def test_a_fragment_the_patch_has_grown_over_is_folded_into_it():
    """A strip seen first with a normal 30 degrees off starts a patch; the floor seen afterwards grows over it.
    Folding moves the strip's cells into the floor: one patch, no vertex more than the floor has, still flat.
    A panel rising 30 degrees from the floor's edge and a parallel board 20 cm above it are surfaces of their own."""
    model = GlobalModel(cell_size=0.02)
    model.add_frame([_misfit((1.2, 1.6))], np.eye(4))
    model.add_frame([_panel(0.0, (0.0, 2.0))], np.eye(4))
    model.add_frame([_panel(30.0, (2.0, 2.4))], np.eye(4))
    board = _panel(0.0, (0.2, 0.8))
    board.vertices[:, 2] -= 0.2
    board.plane[3] += 0.2
    model.add_frame([board], np.eye(4))
    assert len(model.patches) == 4
    strip = model.patches[0]
    floor_cells = max(patch.n_cells for patch in model.patches)
    before = model.n_vertices
    assert model.fold_fragments() == 1
    assert len(model.patches) == 3 and all(patch is not strip for patch in model.patches)
    floor = max(model.patches, key=lambda patch: patch.n_cells)
    assert floor.n_cells == floor_cells and model.n_vertices == before - strip.n_cells  # all fell on the floor's cells
    assert floor.frame_runs.tolist() == [[0, 1], [3, 3]]  # the strip's frame, and the fold's
    assert np.abs(floor.distance_to(floor.origin + np.column_stack(floor.cell_means()) @ floor.axes)).max() < 0.005
    assert model.fold_fragments() == 0  # nothing left to fold


@pytest.fixture(scope="module")
def arena_run():
    frames, truths = simulate.simulate_sequence("arena", "sr3000", 12, seed=3)
    model = GlobalModel()
    single = None
    for frame, truth in zip(frames, truths):
        segmented = segment_frame(frame)
        surfaces = triangulate_segments(segmented.points, segmented.segmentation, range_sigma=segmented.range_sigma)
        if single is None:
            single = [(surface, truth.T_world_sensor) for surface in surfaces]
        model.add_frame(surfaces, truth.T_world_sensor, timestamp=frame.timestamp)
    return model, single, truths


def _perturbed(pose, degrees, metres):
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.array([0.6, 0.0, 0.8])).as_matrix()
    turn[:3, 3] = metres
    return turn @ pose


def test_align_pulls_a_drifted_pose_back_to_the_model(arena_run):
    """The first frame's planes, from a pose 0.5 deg and 4 cm off, fit the model's patches again from the true pose."""
    model, single, _ = arena_run
    surfaces, truth = [surface for surface, _ in single], single[0][1]
    drifted = _perturbed(truth, 0.5, [0.03, -0.02, 0.02])
    covariance = np.diag([np.radians(1.0) ** 2] * 3 + [0.05**2] * 3)
    aligned = model.align(surfaces, drifted, covariance)
    assert aligned.applied and aligned.planes >= 3
    before = np.linalg.norm(drifted[:3, 3] - truth[:3, 3])
    after = np.linalg.norm(aligned.T_world_sensor[:3, 3] - truth[:3, 3])
    assert after < 0.25 * before
    assert np.trace(aligned.covariance) < np.trace(covariance)
    # A correction far outside the pose's covariance (10 cm against 1 cm, the patches within reach by a wide
    # tolerance) is refused.
    model.max_plane_distance, reach = 0.3, model.max_plane_distance
    try:
        shifted = _perturbed(truth, 0.0, [0.1, 0.0, 0.0])
        refused = model.align(surfaces, shifted, np.diag([np.radians(0.1) ** 2] * 3 + [0.01**2] * 3))
    finally:
        model.max_plane_distance = reach
    assert not refused.applied and refused.distance > 20 and np.array_equal(refused.T_world_sensor, shifted)
    assert not GlobalModel().align(surfaces, truth, covariance).applied  # an empty model


def _distance_to_scene(points):
    planes = simulate.get_scene("arena").planes
    planes = planes[np.isfinite(planes).all(axis=1)]
    return np.abs(points @ planes[:, :3].T + planes[:, 3]).min(axis=1)


def test_simulated_sequence_fuses_closer_to_the_true_planes(arena_run):
    model, single, truths = arena_run
    fused = np.vstack([s.vertices for s in model.surfaces(lod=False) if np.isfinite(s.plane).all()]).astype(np.float64)
    first = np.vstack([s.vertices.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3] for s, pose in single])
    assert np.median(_distance_to_scene(fused)) < 0.7 * np.median(_distance_to_scene(first))
    # 12 frames of a slowly moving robot: the model holds far fewer vertices than the frames did.
    assert model.n_vertices < 2.5 * len(first)
    timestamps, poses = model.trajectory()
    assert np.allclose(poses, [truth.T_world_sensor for truth in truths])
    assert len(timestamps) == 12 and (np.diff(timestamps) > 0).all()


def test_patches_each_lie_on_one_true_plane(arena_run):
    model, _, _ = arena_run
    planes = simulate.get_scene("arena").planes
    planes = planes[np.isfinite(planes).all(axis=1)]
    for surface in model.surfaces(lod=False):
        distance = np.abs(surface.vertices.astype(np.float64) @ planes[:, :3].T + planes[:, 3])
        distance[:, np.abs(planes[:, :3] @ surface.plane[:3]) < 0.95] = np.inf
        owner = np.bincount(distance.argmin(axis=1), minlength=len(planes))
        assert owner.max() >= 0.9 * surface.n_vertices


def test_checkpoint_resume_equals_the_uninterrupted_run(tmp_path):
    frames, truths = simulate.simulate_sequence("corridor", "sr3000", 6, seed=5)
    inputs = []
    for frame, truth in zip(frames, truths):
        segmented = segment_frame(frame)
        inputs.append((triangulate_segments(segmented.points, segmented.segmentation, range_sigma=segmented.range_sigma),
                       truth.T_world_sensor))
    covariance = np.diag([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4])
    straight = GlobalModel()
    for surfaces, pose in inputs:
        straight.add_frame(surfaces, pose, covariance=covariance)
    resumed = GlobalModel()
    for surfaces, pose in inputs[:3]:
        resumed.add_frame(surfaces, pose, covariance=covariance)
    resumed.save(tmp_path / "model.npz")
    resumed = GlobalModel.load(tmp_path / "model.npz")
    assert resumed.n_frames == 3
    for surfaces, pose in inputs[3:]:
        resumed.add_frame(surfaces, pose, covariance=covariance)
    assert resumed.history == straight.history
    for ours, theirs in zip(resumed.surfaces(lod=False), straight.surfaces(lod=False)):
        assert np.array_equal(ours.vertices, theirs.vertices) and np.array_equal(ours.faces, theirs.faces)
        for level in ("UL1", "UL2", "UL3"):
            assert np.array_equal(ours.uncertainty[level], theirs.uncertainty[level])
    assert [p.name for p in tmp_path.iterdir()] == ["model.npz"]  # nothing half-written left behind


def test_per_frame_records_are_compact_and_exact(tmp_path):
    """A long run keeps one record per frame: poses without their constant row, a patch's frames as runs."""
    model = GlobalModel(cell_size=0.02)
    shown = [0, 1, 2, 5, 6, 9]
    poses = []
    for frame in range(10):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 1e-3 * frame]).as_matrix()
        pose[:3, 3] = [np.pi * 1e-3 * frame, 0.0, 0.0]
        poses.append(pose)
        model.add_frame([wall()] if frame in shown else [], pose)
    (patch,) = model.patches
    assert patch.frame_runs.tolist() == [[0, 2], [5, 6], [9, 9]]
    assert patch.frames.tolist() == shown
    assert np.array_equal(model.poses, np.array(poses))  # bit for bit
    assert model.history[3].created == 0 and model.history[0].created == 1
    model.save(tmp_path / "model.npz")
    loaded = GlobalModel.load(tmp_path / "model.npz")
    assert loaded.patches[0].frame_runs.tolist() == [[0, 2], [5, 6], [9, 9]]
    assert np.array_equal(loaded.poses, model.poses) and loaded.history == model.history
    # A checkpoint of format 2 listed every frame; it still loads, as runs.
    arrays = dict(np.load(tmp_path / "model.npz"))
    arrays.update(format_version=np.array(2), patch_frames=np.array(shown, np.int64),
                  patch_frame_counts=np.array([0, len(shown)], np.int64), history=arrays["history"].astype(np.int64))
    for name in ("patch_frame_runs", "patch_frame_run_counts"):
        del arrays[name]
    np.savez(tmp_path / "old.npz", **arrays)
    old = GlobalModel.load(tmp_path / "old.npz")
    assert old.patches[0].frame_runs.tolist() == [[0, 2], [5, 6], [9, 9]] and old.history == model.history


def test_patch_storage_grows_by_quarters():
    """A large patch that outgrows its storage takes a quarter more room, not double."""
    model = GlobalModel(cell_size=0.02)
    model.add_frame([wall(size=(100, 100))], np.eye(4))
    (patch,) = model.patches
    before = len(patch._coords)
    assert patch.n_cells == 10_000 and before < 1.25 * 10_000 + 64
    model.add_frame([wall(size=(100, 130))], np.eye(4))
    assert patch.n_cells == 13_000
    assert 13_000 <= len(patch._coords) <= 1.25**2 * before  # grown by quarters, at most twice
    error, _ = heights(model)
    assert np.abs(error).max() < 1e-9  # every cell still found where it was


def test_bad_inputs(tmp_path):
    model = GlobalModel()
    with pytest.raises(ValueError, match="T_world_sensor"):
        model.add_frame([wall()], np.zeros((4, 4)))
    with pytest.raises(ValueError, match="covariance must be 6x6"):
        model.add_frame([wall()], np.eye(4), covariance=np.eye(3))
    with pytest.raises(TypeError, match=r"surfaces\[0\]"):
        model.add_frame([np.zeros((3, 3))], np.eye(4))
    with pytest.raises(ValueError, match="cell_size"):
        GlobalModel(cell_size=0)
    with pytest.raises(ValueError, match="nonplanar"):
        GlobalModel(nonplanar="melt")
    assert model.n_frames == 0  # refused frames leave no trace
    empty = model.add_frame([], np.eye(4))
    assert empty.created == 0 and model.n_frames == 1 and model.surfaces() == []
    (tmp_path / "broken.npz").write_bytes(b"not a zip file")
    with pytest.raises(FormatError, match="broken.npz"):
        GlobalModel.load(tmp_path / "broken.npz")
    np.savez(tmp_path / "other.npz", poses=np.zeros((0, 4, 4)))
    with pytest.raises(FormatError, match="format_version"):
        GlobalModel.load(tmp_path / "other.npz")


def test_touching_counts_points_near_occupied_cells():
    """`PlanarPatch.touching` against a reference: the patch's occupancy image, dilated by the reach."""
    import cv2

    from rangesurf.merge.planar import Observations, PlanarPatch

    rng = np.random.default_rng(0)
    patch = PlanarPatch.from_plane(np.array([0.0, 0, 1, 0]), np.zeros((1, 3)), 0.02)
    seen = np.column_stack([rng.uniform(-0.5, 0.5, 400), rng.uniform(-0.5, 0.5, 400), rng.normal(0, 0.01, 400)])
    seen = seen[(np.abs(seen[:, 0]) < 0.2) | (seen[:, 1] > 0.3)]  # a T of cells, with holes
    patch.fuse(Observations(seen, np.full(len(seen), 1e-6), np.zeros(len(seen)), np.zeros(len(seen))), 0)
    probe = np.column_stack([rng.uniform(-1, 1, 3000), rng.uniform(-1, 1, 3000), rng.normal(0, 0.02, 3000)])
    for reach in (0, 1, 2):
        image, column0, row0 = patch.occupancy(margin=reach)
        if reach:
            image = cv2.dilate(image, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8))
        local = patch.local(probe)
        columns = np.floor(local[:, 0] / patch.cell_size).astype(int) - column0
        rows = np.floor(local[:, 1] / patch.cell_size).astype(int) - row0
        inside = (columns >= 0) & (rows >= 0) & (columns < image.shape[1]) & (rows < image.shape[0])
        expected = int(image[rows[inside], columns[inside]].sum())
        assert expected > 50 and patch.touching(probe, reach) == expected


# ----------------------------------------------------------------------
# Free-space carving.
# ----------------------------------------------------------------------

CAMERA = PinholeProjection(fx=200.0, fy=200.0, cx=88.0, cy=72.0)


def render(rectangles, shape=(144, 176)):
    """Ranges (along each pixel's ray) of fronto-parallel rectangles (z, x0, x1, y0, y1) seen from the origin."""
    directions = CAMERA.directions(*shape)
    ranges = np.full(shape, np.inf)
    for z, x0, x1, y0, y1 in rectangles:
        x, y = directions[..., 0] * z, directions[..., 1] * z
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        ranges = np.where(inside, np.minimum(ranges, z * np.linalg.norm(directions, axis=-1)), ranges)
    return np.where(np.isfinite(ranges), ranges, np.nan)


def test_carving_removes_a_copy_the_sensor_sees_through_and_keeps_the_real_wall():
    """A wall's copy 30 cm in front of it (built while the pose was off) goes after three checks that see the wall."""
    model = GlobalModel(cell_size=0.02, max_plane_distance=0.1)
    model.add_frame([wall()], np.eye(4))
    model.add_frame([wall(offset=-0.3)], np.eye(4))
    real, copy = model.patches
    assert copy.n_cells == real.n_cells == 1200
    ranges = render([(2.0, 0.0, 0.78, 0.0, 0.58)])
    for check in range(3):
        removed = model.carve(ranges, CAMERA, np.eye(4), range_sigma=0.005)
        assert (removed > 0) == (check == 2)
    assert model.patches[0] is real and real.n_cells == 1200
    assert model.cells_carved == removed == 1200 - copy.n_cells
    # What is left of the copy is what no pixel looked through: cells whose rays (or their 3x3 pixels')
    # pass beside the wall.
    u, v, _ = copy.cell_means()
    x, y = (copy.origin + np.column_stack([u, v, np.zeros_like(u)]) @ copy.axes)[:, :2].T * 2.0 / 1.7
    behind = (x > 0.02) & (x < 0.78 - 0.02) & (y > 0.02) & (y < 0.58 - 0.02)
    assert not behind.any() and removed > 700


def test_carving_needs_consecutive_unconfirmed_checks_and_a_certain_pose():
    model = GlobalModel(cell_size=0.02, max_plane_distance=0.1)
    model.add_frame([wall()], np.eye(4))
    model.add_frame([wall(offset=-0.3)], np.eye(4))
    copy = model.patches[1]
    ranges = render([(2.0, 0.0, 0.78, 0.0, 0.58)])
    for _ in range(2):
        model.carve(ranges, CAMERA, np.eye(4), range_sigma=0.005)
    # Seen again where it is: the count of checks in a row starts over.
    model.add_frame([wall(offset=-0.3)], np.eye(4))
    for _ in range(2):
        assert model.carve(ranges, CAMERA, np.eye(4), range_sigma=0.005) == 0
    assert copy.n_cells == 1200
    # A pose uncertain by 20 cm along the view proves nothing about a 30 cm gap.
    uncertain = np.diag([0, 0, 0, 0, 0, 0.2**2])
    for _ in range(5):
        assert model.carve(ranges, CAMERA, np.eye(4), range_sigma=0.005, covariance=uncertain) == 0
    # Nor does a frame without readings there.
    assert model.carve(np.full_like(ranges, np.nan), CAMERA, np.eye(4), range_sigma=0.005) == 0
    assert copy.n_cells == 1200


def test_carving_does_not_erode_a_surface_in_front_of_another():
    """A box face 50 cm in front of the wall: the wall behind it shows around its edges, for many checks."""
    model = GlobalModel(cell_size=0.02, max_plane_distance=0.1)
    model.add_frame([wall()], np.eye(4))
    box = wall(offset=-0.5, size=(10, 10))
    model.add_frame([box], np.eye(4))
    ranges = render([(2.0, 0.0, 0.78, 0.0, 0.58), (1.5, 0.0, 0.19, 0.0, 0.19)])
    for _ in range(10):
        assert model.carve(ranges, CAMERA, np.eye(4), range_sigma=0.005) == 0
    assert [patch.n_cells for patch in model.patches] == [1200, 100]


def test_carving_evidence_survives_a_checkpoint(tmp_path):
    """Two checks, save, load, one more check: the copy goes, as it does without the restart."""
    model = GlobalModel(cell_size=0.02, max_plane_distance=0.1)
    model.add_frame([wall()], np.eye(4))
    model.add_frame([wall(offset=-0.3)], np.eye(4))
    ranges = render([(2.0, 0.0, 0.78, 0.0, 0.58)])
    for _ in range(2):
        model.carve(ranges, CAMERA, np.eye(4), range_sigma=0.005)
    resumed = GlobalModel.load(model.save(tmp_path / "model.npz"))
    assert resumed.carve(ranges, CAMERA, np.eye(4), range_sigma=0.005) == model.carve(ranges, CAMERA, np.eye(4), range_sigma=0.005) > 0
    assert resumed.n_vertices == model.n_vertices and resumed.cells_carved == model.cells_carved


def test_carving_rejects_what_it_cannot_use():
    model = GlobalModel(cell_size=0.02)
    model.add_frame([wall()], np.eye(4))
    with pytest.raises(ValueError, match="ranges must be an"):
        model.carve(np.zeros(5), CAMERA, np.eye(4), range_sigma=0.005)
    with pytest.raises(TypeError, match="PinholeProjection"):
        model.carve(np.zeros((4, 4)), None, np.eye(4), range_sigma=0.005)
    with pytest.raises(ValueError, match="covariance"):
        model.carve(np.zeros((4, 4)), CAMERA, np.eye(4), range_sigma=0.005, covariance=np.full((6, 6), np.nan))


def test_align_cannot_make_a_pose_more_certain_than_the_map_is(arena_run):
    """Patches placed by poses as uncertain as this one share its error: aligning to them leaves the covariance.

    Drift is a random walk: the poses that placed the patches carried part of
    this pose's error, which no fit to those patches can remove. Placed with
    the pose's own covariance, the patches do not shrink its covariance;
    placed with 1/16 of it (long ago, before the drift), they pull the pose
    back and shrink its covariance, but never below that 1/16.
    """
    _, single, truths = arena_run
    surfaces, truth = [surface for surface, _ in single], single[0][1]
    placed = np.diag([np.radians(0.3) ** 2] * 3 + [0.01**2] * 3)
    model = GlobalModel()
    for surface, pose in single:
        model.add_frame([surface], pose, covariance=placed)
    shared = model.align(surfaces, truth, placed)
    assert shared.planes >= 3
    assert np.allclose(shared.covariance, placed, rtol=0.03, atol=0.01 * placed[0, 0])
    drifted = _perturbed(truth, 0.2, [0.02, -0.015, 0.01])
    later = model.align(surfaces, drifted, 16 * placed)
    assert later.applied
    assert np.trace(later.covariance) < 0.5 * np.trace(16 * placed)
    assert np.linalg.eigvalsh(later.covariance - 0.9 * placed).min() > 0
    before = np.linalg.norm(drifted[:3, 3] - truth[:3, 3])
    assert np.linalg.norm(later.T_world_sensor[:3, 3] - truth[:3, 3]) < 0.5 * before


def patch_of(u, v, h, weight):
    """A patch in the world frame (origin 0, axes x, y, z) with one cell per (u, v): means (u, v, h) of weight."""
    from rangesurf.merge.planar import PlanarPatch

    sums = {"weight": weight, "u": u * weight, "v": v * weight, "h": h * weight}
    coordinates = np.column_stack([np.floor(u / 0.1), np.floor(v / 0.1)]).astype(np.int32)
    return PlanarPatch(origin=np.zeros(3), axes=np.eye(3), cell_size=0.1, coordinates=coordinates, sums=sums)


def test_patch_plane_fit_matches_weighted_least_squares_and_keeps_collinear_cells_level():
    rng = np.random.default_rng(3)
    u, v = np.repeat(np.arange(8) * 0.1, 6) + 0.05, np.tile(np.arange(6) * 0.1, 8) + 0.05
    weight = rng.uniform(0.5, 2.0, u.size)
    h = 0.2 * u - 0.1 * v + 0.3 + 0.01 * rng.standard_normal(u.size)
    patch = patch_of(u, v, h, weight)
    design = np.column_stack([u, v, np.ones_like(u)]) * np.sqrt(weight)[:, None]
    expected = np.linalg.lstsq(design, h * np.sqrt(weight), rcond=None)[0]
    np.testing.assert_allclose(patch.fitted_plane(), expected, rtol=1e-9, atol=1e-12)
    # The world plane is h - a u - b v - c = 0 with a unit normal facing +z (the patch normal).
    normal = np.array([-expected[0], -expected[1], 1.0]) / np.linalg.norm([expected[0], expected[1], 1.0])
    np.testing.assert_allclose(patch.world_plane(), [*normal, -expected[2] * normal[2]], atol=1e-12)
    # One row of cells: the tilt across it is unknown, so the patch stays level at the weighted mean height.
    row = patch_of(u[::6], np.full(8, 0.05), h[::6], weight[::6])
    np.testing.assert_allclose(row.fitted_plane(), [0.0, 0.0, np.average(h[::6], weights=weight[::6])], atol=1e-12)


def test_median_of_nine_network_matches_numpy_on_ties_and_every_order():
    from itertools import permutations

    from rangesurf.merge.planar import _median_of_nine

    rng = np.random.default_rng(4)
    for values in [*rng.normal(size=(2000, 9)), *rng.integers(0, 3, size=(500, 9)).astype(float)]:
        assert _median_of_nine(*values) == np.median(values)
    ordered = np.arange(9.0)
    assert all(_median_of_nine(*order) == 4.0 for order in list(permutations(ordered))[::97])
