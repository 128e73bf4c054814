"""TSDF fusion against ground truth: analytic spheres, a simulated box, the bunny's reference alignment."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

import rangesurf as rs
from rangesurf import simulate
from rangesurf.merge.tsdf import TSDFVolume, _pixel_normals
from rangesurf.mesh import boundary_loops

BUNNY = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "bunny"
CENTER = np.array([0.1, 0.2, 0.3])
RADIUS = 0.3
# Six views along the axes (slightly off the poles so that look_at has an up vector).
VIEW_DIRECTIONS = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0.01, 1), (0, 0.01, -1)]


def sphere_frame(sensor, eye, *, center=CENTER, radius=RADIUS, sigma=0.0, rng=None):
    """A frame of ``sensor`` at ``eye`` looking at a sphere, and its pose (analytic ray casting)."""
    eye = np.asarray(eye, dtype=np.float64)
    up = (0, 0, 1) if abs(eye[2] - center[2]) < 0.9 * np.linalg.norm(eye - center) else (0, 1, 0)
    T_world_sensor = simulate.look_at(eye, center, up=up)
    directions = sensor.rays().reshape(-1, 3).astype(np.float64) @ T_world_sensor[:3, :3].T
    offset = eye - center
    half_b = directions @ offset
    discriminant = half_b**2 - (offset @ offset - radius**2)
    with np.errstate(invalid="ignore"):
        ranges = np.where(discriminant > 0, -half_b - np.sqrt(discriminant), np.nan)
    if sigma:
        ranges = ranges + sigma * rng.standard_normal(ranges.shape)
    frame = rs.RangeFrame(rays=sensor.rays(), range=ranges.reshape(sensor.shape).astype(np.float32), sensor=sensor)
    return frame, T_world_sensor


def sphere_views(sensor, distance=1.5, **kwargs):
    return [sphere_frame(sensor, CENTER + distance * np.asarray(d, float), **kwargs) for d in VIEW_DIRECTIONS]


def sphere_error(surface):
    return np.abs(np.linalg.norm(surface.vertices - CENTER, axis=1) - RADIUS)


def euler_characteristic(surface):
    faces = surface.faces
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    return surface.n_vertices - len(edges) + surface.n_faces


def fused_sphere(sensor_name="sr3000", voxel_size=0.01, sigma=0.001, seed=0):
    sensor = rs.get_sensor(sensor_name)
    rng = np.random.default_rng(seed)
    volume = TSDFVolume(voxel_size)
    for frame, pose in sphere_views(sensor, sigma=sigma, rng=rng):
        volume.integrate(frame, pose, range_sigma=max(sigma, 1e-4))
    return volume


# --------------------------------------------------------------------------
# Geometry against ground truth.
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "sensor_name, voxel_size, distance",
    # The swept laser's 0.5 deg steps are 13 mm apart at 1.5 m: a coarser grid.
    [("sr3000", 0.01, 1.5), ("kinect", 0.01, 1.5), ("uos-laser", 0.015, 1.5)],
)
def test_sphere_from_six_views_is_closed_and_accurate(sensor_name, voxel_size, distance):
    sensor = rs.get_sensor(sensor_name)
    rng = np.random.default_rng(1)
    volume = TSDFVolume(voxel_size)
    for frame, pose in sphere_views(sensor, distance=distance, sigma=0.001, rng=rng):
        volume.integrate(frame, pose, range_sigma=0.001)
    surface = volume.extract_mesh()
    error = sphere_error(surface)
    # Noise 1 mm averaged over several readings per voxel; the zero crossing is linear between voxels.
    assert error.mean() < 0.1 * voxel_size
    assert error.max() < 0.75 * voxel_size
    assert boundary_loops(surface.faces) == []
    assert euler_characteristic(surface) == 2
    outward = (surface.vertices - CENTER) / np.linalg.norm(surface.vertices - CENTER, axis=1, keepdims=True)
    facing = np.einsum("ij,ij->i", surface.normals, outward)
    assert np.percentile(facing, 1) > 0.97 and facing.min() > 0.7
    # Faces wind counter-clockwise seen from outside: the enclosed volume is positive.
    corners = surface.vertices[surface.faces].astype(np.float64)
    volume_enclosed = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6
    assert volume_enclosed == pytest.approx(4 / 3 * np.pi * RADIUS**3, rel=0.01)
    assert surface.vertices.dtype == np.float32 and surface.faces.dtype == np.int32
    assert np.all(surface.pixels == -1) and np.all(np.isnan(surface.plane))


# Off the voxel grid, so that no face lies on a plane of voxel centres.
BOX_CENTER = np.array([0.0031, -0.0043, 1.0027])


def box_scene(half=0.2, center=BOX_CENTER):
    cx, cy, cz = center
    x0, x1, y0, y1, z0, z1 = cx - half, cx + half, cy - half, cy + half, cz - half, cz + half
    faces = [
        [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0)],
        [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)],
        [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],
        [(x0, y1, z0), (x1, y1, z0), (x1, y1, z1), (x0, y1, z1)],
        [(x0, y0, z0), (x0, y1, z0), (x0, y1, z1), (x0, y0, z1)],
        [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)],
    ]
    polygons = tuple(simulate.Polygon(k + 1, np.array(f, float), 0.6, f"box face {k}") for k, f in enumerate(faces))
    return simulate.Scene("box", polygons)


def box_distance(points, half=0.2, center=BOX_CENTER):
    """Unsigned distance of points to the surface of an axis-aligned cube."""
    q = np.abs(points - np.asarray(center)) - half
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(axis=1), 0)
    return np.abs(outside + inside)


def test_box_seen_from_its_eight_corners_is_watertight_with_flat_faces():
    scene = box_scene()
    sensor = dataclasses.replace(rs.get_sensor("sr3000"), noise=rs.RangeNoiseModel(floor=0.001))
    noise = simulate.SimulationNoise(mixed_pixels=False, salt_and_pepper=0.0)
    rng = np.random.default_rng(3)
    volume = TSDFVolume(0.01)
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                eye = BOX_CENTER + 0.75 * np.array([sx, sy + 0.1, sz])
                frame, _ = simulate.simulate_frame(scene, sensor, simulate.look_at(eye, BOX_CENTER), noise=noise, rng=rng)
                # The sensor's noise model (1 mm) weights the readings.
                volume.integrate(frame, frame.reference_pose)
    surface = volume.extract_mesh()
    error = box_distance(surface.vertices.astype(np.float64))
    assert boundary_loops(surface.faces) == []
    assert euler_characteristic(surface) == 2
    # Flat faces are exact up to the noise; edges and corners are rounded by about a voxel.
    away_from_edges = np.sort(np.abs(surface.vertices - BOX_CENTER), axis=1)[:, 1] < 0.17
    assert np.median(error[away_from_edges]) < 0.0005
    assert error.mean() < 0.001 and error.max() < 0.012
    assert surface.area() == pytest.approx(6 * 0.4**2, rel=0.03)


def test_plane_from_one_frame_lies_on_the_plane():
    sensor = rs.get_sensor("sr3000")
    frame = rs.RangeFrame(rays=sensor.rays(), range=np.float32(2.013) / sensor.rays()[..., 2], sensor=sensor)
    volume = TSDFVolume(0.02)
    volume.integrate(frame, np.eye(4), range_sigma=0.005)
    surface = volume.extract_mesh()
    assert surface.n_faces > 1000
    assert np.allclose(surface.vertices[:, 2], 2.013, atol=1e-4)
    # Normals face the sensor (at the origin, looking along +z).
    assert np.allclose(surface.normals, [0, 0, -1], atol=1e-3)
    # One observation per voxel and ray-consistent readings: no disagreement.
    assert surface.uncertainty["UL3"].max() < 1e-4


# --------------------------------------------------------------------------
# Weights and uncertainty (UL3).
# --------------------------------------------------------------------------


def test_weights_grow_with_observations_and_respect_the_cap():
    sensor = rs.get_sensor("sr3000")
    frame, pose = sphere_frame(sensor, CENTER + [1.5, 0, 0])
    surface_points = CENTER + RADIUS * np.array([[1.0, 0, 0], [0.97, 0.2, 0.1], [0.97, -0.1, -0.2]])
    volume = TSDFVolume(0.01)
    volume.integrate(frame, pose, range_sigma=0.002)
    once = volume.query(surface_points).weight
    volume.integrate(frame, pose, range_sigma=0.002)
    twice = volume.query(surface_points).weight
    assert np.all(once > 0)
    np.testing.assert_allclose(twice, 2 * once, rtol=1e-5)
    # Noisier readings weigh less (1 / sigma^2).
    volume.integrate(frame, pose, range_sigma=0.004)
    np.testing.assert_allclose(volume.query(surface_points).weight, 2.25 * once, rtol=1e-5)
    assert volume.n_frames == 3

    capped = TSDFVolume(0.01, max_weight=float(once.min()) * 1.5)
    for _ in range(4):
        capped.integrate(frame, pose, range_sigma=0.002)
    assert capped.query(surface_points).weight.max() <= once.min() * 1.5 * (1 + 1e-5)


def test_disagreement_is_larger_where_observations_conflict():
    offset = 0.004
    sensor = rs.get_sensor("sr3000")
    views = sphere_views(sensor)
    volume = TSDFVolume(0.01)
    for frame, pose in views:
        volume.integrate(frame, pose, range_sigma=0.001)
    # The +x view once more, registered 4 mm off along its line of sight.
    frame, pose = views[0]
    shifted = pose.copy()
    shifted[:3, 3] += [offset, 0, 0]
    volume.integrate(frame, shifted, range_sigma=0.001)
    surface = volume.extract_mesh()
    ul3 = surface.uncertainty["UL3"]
    direction = (surface.vertices - CENTER) / np.linalg.norm(surface.vertices - CENTER, axis=1, keepdims=True)
    conflict = direction[:, 0] > 0.97  # seen head-on by the shifted and the true +x view only
    agree = direction[:, 0] < -0.5
    # Two equal-weight readings `offset` apart: standard deviation offset / 2.
    assert np.median(ul3[conflict]) == pytest.approx(offset / 2, rel=0.25)
    assert np.median(ul3[conflict]) > 10 * np.median(ul3[agree])
    assert np.median(ul3[agree]) < 0.0005


def test_pose_covariance_enters_weights_and_ul3():
    sensor = rs.get_sensor("sr3000")
    frame, pose = sphere_frame(sensor, CENTER + [1.5, 0, 0])
    sigma_t = 0.002
    covariance = np.diag([0, 0, 0, sigma_t**2, sigma_t**2, sigma_t**2])
    plain, uncertain = TSDFVolume(0.01), TSDFVolume(0.01)
    plain.integrate(frame, pose, range_sigma=0.002)
    uncertain.integrate(frame, pose, range_sigma=0.002, pose_covariance=covariance)
    point = CENTER + [[RADIUS, 0, 0]]
    # A translation covariance projects onto any normal with its full variance.
    assert uncertain.query(point).spread[0] == pytest.approx(sigma_t, rel=0.02)
    assert uncertain.query(point).weight[0] == pytest.approx(plain.query(point).weight[0] / 2, rel=0.02)
    np.testing.assert_allclose(np.median(uncertain.extract_mesh().uncertainty["UL3"]), sigma_t, rtol=0.05)


# --------------------------------------------------------------------------
# Kernels against NumPy references.
# --------------------------------------------------------------------------


def pixel_normals_reference(points, jump=0.05):
    """Central (one-sided at steps and borders) differences, crossed, facing the sensor; NaN where unknown."""
    height, width, _ = points.shape
    ranges = np.linalg.norm(points, axis=2)
    padded = np.pad(points, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
    padded_ranges = np.pad(ranges, 1, constant_values=np.nan)

    def difference(d_row, d_col):
        forward = padded[1 + d_row : 1 + d_row + height, 1 + d_col : 1 + d_col + width]
        backward = padded[1 - d_row : 1 - d_row + height, 1 - d_col : 1 - d_col + width]
        with np.errstate(invalid="ignore"):
            ok_f = np.abs(padded_ranges[1 + d_row : 1 + d_row + height, 1 + d_col : 1 + d_col + width] - ranges) <= jump * ranges
            ok_b = np.abs(padded_ranges[1 - d_row : 1 - d_row + height, 1 - d_col : 1 - d_col + width] - ranges) <= jump * ranges
        a = np.where(ok_f[..., None], forward, points)
        b = np.where(ok_b[..., None], backward, points)
        return a - b, ok_f | ok_b

    du, ok_u = difference(0, 1)
    dv, ok_v = difference(1, 0)
    normals = np.cross(du, dv)
    length = np.linalg.norm(normals, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = normals / length
    normals[np.einsum("ijk,ijk->ij", normals, points) > 0] *= -1
    normals[~(ok_u & ok_v & np.isfinite(ranges) & (length[..., 0] > 0))] = np.nan
    return normals


def test_pixel_normals_match_numpy_reference():
    frame, truth = simulate.simulate_frame(
        "arena", "sr3000", simulate.look_at((3.0, 1.0, 0.8), (3.0, 5.0, 0.3)), rng=np.random.default_rng(0)
    )
    points = frame.points
    normals = _pixel_normals(points, frame.range, frame.rays, 0.05)
    reference = pixel_normals_reference(points.astype(np.float64))
    assert np.array_equal(np.isnan(normals[..., 0]), np.isnan(reference[..., 0]))
    known = np.isfinite(reference[..., 0])
    assert known.mean() > 0.9
    np.testing.assert_allclose(normals[known], reference[known], atol=1e-4)


def integrate_reference(volume_size, truncation, behind, points, rays, normals, weights, origin, start, n_steps):
    """Order-free sums over every (ray, voxel) pair a ray's band visits: W, D = sum(w d) / W, M2 = sum w (d - D)^2."""
    step = volume_size / 2
    samples = start[:, None] + step * np.arange(n_steps.max())[None, :]
    inside = np.arange(n_steps.max())[None, :] < n_steps[:, None]
    voxels = np.floor((origin + samples[..., None] * rays[:, None, :]) / volume_size + 0.5).astype(np.int64)
    repeated = np.zeros_like(inside)
    repeated[:, 1:] = np.all(voxels[:, 1:] == voxels[:, :-1], axis=2)
    keep = inside & ~repeated
    distance = np.einsum("rk,rsk->rs", normals, voxels * volume_size - points[:, None, :])
    distance = np.minimum(distance, truncation)
    # Full weight down to one voxel behind the reading, then a linear ramp to 0 at `behind`.
    ramp = np.where(distance < -volume_size, (behind[:, None] + distance) / (behind[:, None] - volume_size), 1.0)
    keep &= ramp > 0
    ray_index = np.broadcast_to(np.arange(len(points))[:, None], keep.shape)[keep]
    keys, inverse = np.unique(voxels[keep], axis=0, return_inverse=True)
    inverse = inverse.ravel()
    w = weights[ray_index] * ramp[keep]
    total = np.bincount(inverse, w, len(keys))
    mean = np.bincount(inverse, w * distance[keep], len(keys)) / total
    m2 = np.bincount(inverse, w * distance[keep] ** 2, len(keys)) - total * mean**2
    return keys, total, mean, m2


def test_integration_matches_numpy_reference():
    sensor = rs.get_sensor("sr3000")
    rng = np.random.default_rng(5)
    frame, pose = sphere_frame(sensor, CENTER + [1.2, 0.3, 0.2], sigma=0.002, rng=rng)
    voxel_size, sigma = 0.02, 0.002
    volume = TSDFVolume(voxel_size, angle_weighting=False)
    volume.integrate(frame, pose, range_sigma=sigma)

    normals = _pixel_normals(frame.points, frame.range, frame.rays, 0.05).reshape(-1, 3).astype(np.float64)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    rays = frame.rays.reshape(-1, 3).astype(np.float64) @ rotation.T
    normals = normals @ rotation.T
    cosine = -np.einsum("ij,ij->i", rays, normals)
    use = np.isfinite(normals[:, 0]) & (cosine >= 0.2)
    ranges = frame.range.ravel()[use].astype(np.float64)
    points = frame.points.reshape(-1, 3)[use].astype(np.float64) @ rotation.T + origin
    stretch = 1 / np.maximum(cosine[use], 0.5)
    behind = np.full(use.sum(), 2 * voxel_size)
    start = np.maximum(ranges - volume.truncation * stretch, voxel_size / 2)
    n_steps = np.floor((ranges + behind * stretch - start) / (voxel_size / 2)).astype(np.int64) + 1
    keys, total, mean, m2 = integrate_reference(
        voxel_size, volume.truncation, behind, points, rays[use], normals[use], np.full(use.sum(), sigma**-2), origin,
        start, n_steps,
    )
    fused = volume.query(keys * voxel_size)
    np.testing.assert_allclose(fused.weight, total, rtol=1e-5)
    np.testing.assert_allclose(fused.distance, mean, atol=1e-6)
    np.testing.assert_allclose(fused.spread, np.sqrt(np.maximum(m2, 0) / total), atol=2e-5)
    # Nothing else was touched: the allocated voxels with weight are exactly the reference's.
    assert int((volume._weight[: volume.n_blocks] > 0).sum()) == len(keys)


def test_marching_cubes_matches_scikit_image_on_the_same_field():
    measure = pytest.importorskip("skimage.measure", reason="scikit-image (bench extra) is the reference")
    voxel_size = 0.02
    volume = fused_sphere(voxel_size=voxel_size, sigma=0.0)
    surface = volume.extract_mesh()
    low = np.floor((CENTER - RADIUS) / voxel_size).astype(int) - 3
    high = np.ceil((CENTER + RADIUS) / voxel_size).astype(int) + 4
    grid = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(low, high)], indexing="ij"), axis=-1)
    fused = volume.query(grid.reshape(-1, 3) * voxel_size)
    inside = np.linalg.norm(grid.reshape(-1, 3) * voxel_size - CENTER, axis=1) < RADIUS
    # Unobserved voxels get the true side's clipped value, so no crossing appears where ours has none.
    field = np.where(np.isnan(fused.distance), np.where(inside, -1.0, 1.0), fused.distance).reshape(grid.shape[:3])
    vertices, faces, _, _ = measure.marching_cubes(field, 0.0)
    vertices = (vertices + low) * voxel_size
    assert len(vertices) == surface.n_vertices
    distance, _ = cKDTree(vertices).query(surface.vertices)
    assert distance.max() < 1e-6
    assert len(faces) == surface.n_faces


# --------------------------------------------------------------------------
# Real data: the Stanford bunny at its reference alignment.
# --------------------------------------------------------------------------


def test_bunny_scans_fuse_into_a_mesh_they_all_lie_on():
    if not (BUNNY / "bun000.ply").is_file():
        pytest.skip(f"bunny scans not found at {BUNNY} (shared test data lives beside the project)")
    frames = [rs.load(BUNNY / f"{name}.ply")[0] for name in ("bun000", "bun045", "bun090", "chin", "top2")]
    volume = TSDFVolume(0.001)
    for frame in frames:
        volume.integrate(frame, frame.reference_pose)
    surface = volume.extract_mesh()
    tree = cKDTree(surface.vertices)
    for frame in frames:
        points = frame.world_points(use_reference=True)
        _, nearest = tree.query(points)
        # Distance to the tangent plane of the nearest vertex (vertices are ~1 mm apart).
        distance = np.abs(np.einsum("ij,ij->i", points - surface.vertices[nearest], surface.normals[nearest]))
        assert np.median(distance) < 0.00015, frame.source
        assert np.percentile(distance, 90) < 0.0006, frame.source
    # The scans agree to a fraction of a millimetre: so does UL3 over most of the surface.
    assert np.median(surface.uncertainty["UL3"]) < 0.0003
    assert 0.005 < surface.area() < 0.1


# --------------------------------------------------------------------------
# Edge cases and bad input.
# --------------------------------------------------------------------------


def test_empty_volume_and_all_invalid_frame_give_an_empty_surface():
    sensor = rs.get_sensor("sr3000")
    volume = TSDFVolume(0.01)
    assert volume.extract_mesh().n_vertices == 0
    frame = rs.RangeFrame(rays=sensor.rays(), range=np.full(sensor.shape, np.nan, np.float32), sensor=sensor)
    volume.integrate(frame, np.eye(4))
    surface = volume.extract_mesh()
    assert volume.n_blocks == 0 and surface.n_faces == 0 and surface.uncertainty["UL3"].shape == (0,)
    # A single reading has no neighbours, hence no normal: nothing is fused.
    lonely = np.full((3, 3, 3), np.nan)
    lonely[1, 1] = [0, 0, 1]
    volume.integrate(lonely, np.eye(4))
    assert volume.n_blocks == 0 and volume.n_frames == 2


def test_point_grid_input_equals_frame_input():
    sensor = rs.get_sensor("sr3000")
    frame, pose = sphere_frame(sensor, CENTER + [1.5, 0, 0])
    from_frame, from_points = TSDFVolume(0.01), TSDFVolume(0.01)
    from_frame.integrate(frame, pose, range_sigma=0.001)
    from_points.integrate(frame.points, pose, range_sigma=0.001)
    a, b = from_frame.extract_mesh(), from_points.extract_mesh()
    assert a.n_faces == b.n_faces
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-5)


def test_mask_fuses_only_the_selected_pixels():
    sensor = rs.get_sensor("sr3000")
    frame, pose = sphere_frame(sensor, CENTER + [1.5, 0, 0])
    left = np.zeros(frame.shape, bool)
    left[:, : frame.shape[1] // 2] = True
    volume = TSDFVolume(0.01)
    volume.integrate(frame, pose, range_sigma=0.001, mask=left)
    surface = volume.extract_mesh()
    # The sensor looks along world -x, its x axis (image right) along world +y: the left half sees y < centre.
    assert surface.n_faces > 500
    assert np.all(surface.vertices[:, 1] < CENTER[1] + 0.02)
    assert surface.vertices[:, 1].min() < CENTER[1] - 0.2
    with pytest.raises(ValueError, match="mask must be a boolean array"):
        volume.integrate(frame, pose, mask=np.ones((2, 2), bool))


def test_blocks_grow_past_the_initial_table():
    volume = fused_sphere(voxel_size=0.005, sigma=0.0)
    assert volume.n_blocks > 1000
    coordinates = volume.block_coordinates
    assert len(np.unique(coordinates, axis=0)) == len(coordinates)
    assert volume.nbytes >= volume.n_blocks * 8**3 * 12


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"voxel_size": 0.0}, "voxel_size"),
        ({"voxel_size": np.nan}, "voxel_size"),
        ({"voxel_size": 0.01, "truncation": 0.005}, "truncation"),
        ({"voxel_size": 0.01, "max_weight": -1.0}, "max_weight"),
    ],
)
def test_bad_volume_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        TSDFVolume(**kwargs)


def test_bad_integration_input_is_refused():
    sensor = rs.get_sensor("sr3000")
    frame, pose = sphere_frame(sensor, CENTER + [1.5, 0, 0])
    volume = TSDFVolume(0.01)
    with pytest.raises(ValueError, match=r"\(H, W, 3\).*\(144, 176\)"):
        volume.integrate(frame.range, pose)
    with pytest.raises(ValueError, match="4x4"):
        volume.integrate(frame, np.eye(3))
    with pytest.raises(ValueError, match="rotation"):
        volume.integrate(frame, np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="range_sigma"):
        volume.integrate(frame, pose, range_sigma=-1.0)
    with pytest.raises(ValueError, match="range_sigma shape"):
        volume.integrate(frame, pose, range_sigma=np.ones((2, 2)))
    with pytest.raises(ValueError, match="pose_covariance must be a \\(6, 6\\)"):
        volume.integrate(frame, pose, pose_covariance=np.eye(3))
    with pytest.raises(ValueError, match="finite"):
        volume.integrate(frame, pose, pose_covariance=np.diag([np.inf] + [1.0] * 5))
    far = pose.copy()
    far[:3, 3] = 1e9
    with pytest.raises(ValueError, match="too far"):
        TSDFVolume(0.001).integrate(frame, far)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        volume.query(np.zeros(3))
    with pytest.raises(ValueError, match="min_weight"):
        volume.extract_mesh(min_weight=-1)
    # Refused input leaves the volume as it was.
    assert volume.n_blocks == 0 and volume.n_frames == 0
