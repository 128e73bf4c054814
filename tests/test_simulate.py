"""Simulator: scene geometry, ray casting, sensor noise and ground truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import rangesurf as rs
from rangesurf import simulate as sim
from rangesurf.io import FormatError

SENSOR_NAMES = ["sr3000", "uos-laser", "kinect", "cyberware"]
SCENE_NAMES = ["arena", "corridor"]
ROOM_BOUNDS = {"arena": (6.0, 5.0), "corridor": (20.0, 2.4)}
# A box corner in each scene, and an eye about 1.35 m from it: inside even the
# Cyberware scanner's 1.1-1.6 m range.
CLOSE_UP = {"arena": ((1.0, 1.0, 0.6), (1.75, 1.75, 1.3)), "corridor": ((7.0, 0.5, 0.6), (7.75, 1.25, 1.3))}


def _surface_id(scene: sim.Scene, label: str) -> int:
    (surface_id,) = {p.surface_id for p in (*scene.polygons, *scene.cylinders) if p.label == label}
    return surface_id


def _world_directions(sensor: rs.SensorModel, pose: np.ndarray) -> np.ndarray:
    return sensor.rays().reshape(-1, 3).astype(np.float64) @ pose[:3, :3].T


def _true_distance(scene, sensor, pose) -> np.ndarray:
    """Unclipped distance of every centre ray, inf where it hits nothing."""
    distance, _, _ = sim.ray_cast(scene, pose[:3, 3], _world_directions(sensor, pose))
    return distance.reshape(sensor.shape)


def _noise_free(scene, sensor, pose):
    return sim.simulate_frame(scene, sensor, pose, noise=sim.SimulationNoise.none(), rng=np.random.default_rng(0))


def _split_normal_skewness(near: float, far: float) -> float:
    root = math.sqrt(2 / math.pi)
    mean = root * (far - near)
    second = near**2 - near * far + far**2
    third = 2 * root * (far**4 - near**4) / (near + far)
    central_third = third - 3 * mean * second + 2 * mean**3
    return central_third / (second - mean**2) ** 1.5


def _wall_scene(distances_and_albedo: list[tuple[float, float, float, float]]) -> sim.Scene:
    """Walls facing a sensor on the x axis: (x, y_min, y_max, albedo) each, 4 m tall."""
    polygons = [
        sim.Polygon(k + 1, [(x, y0, -2.0), (x, y1, -2.0), (x, y1, 2.0), (x, y0, 2.0)], albedo)
        for k, (x, y0, y1, albedo) in enumerate(distances_and_albedo)
    ]
    return sim.Scene("walls", tuple(polygons))


# --------------------------------------------------------------------------
# Ray casting.
# --------------------------------------------------------------------------


def test_ray_cast_hits_walls_floor_and_pillar_where_computed_by_hand():
    scene = sim.get_scene("arena")
    origin = np.array([3.0, 1.0, 1.0])
    directions = np.array([
        [0.0, -1.0, 0.0],  # south wall, y = 0
        [1.0, 0.0, 0.0],  # east wall, x = 6 (over the 0.8 m grey box)
        [0.0, 0.0, -1.0],  # floor
        [0.0, 1.0, 0.0],  # pillar: centre (3, 2.5), radius 0.15
        [0.0, 0.0, 1.0],  # open sky
    ])
    distance, surface_id, normal = sim.ray_cast(scene, origin, directions)
    np.testing.assert_allclose(distance[:4], [1.0, 3.0, 1.0, 1.35], atol=1e-12)
    assert distance[4] == np.inf
    assert surface_id.tolist() == [
        _surface_id(scene, "south wall"), _surface_id(scene, "east wall"),
        _surface_id(scene, "floor"), _surface_id(scene, "pillar"), 0,
    ]
    np.testing.assert_allclose(normal[:4], [[0, 1, 0], [-1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    assert np.isnan(normal[4]).all()


def test_ray_cast_cylinder_normal_is_radial_and_height_is_finite():
    scene = sim.get_scene("arena")
    pillar = _surface_id(scene, "pillar")
    # Diagonal approach: the hit lies 0.15 m short of the axis, normal back along the ray.
    origin = np.array([2.0, 1.5, 1.0])
    distance, surface_id, normal = sim.ray_cast(scene, origin, [[1.0, 1.0, 0.0]])
    assert surface_id[0] == pillar
    assert distance[0] == pytest.approx(math.sqrt(2) - 0.15, abs=1e-12)
    np.testing.assert_allclose(normal[0], [-math.sqrt(0.5), -math.sqrt(0.5), 0.0], atol=1e-12)
    # Above the 2 m pillar and walls: nothing.
    distance, surface_id, _ = sim.ray_cast(scene, (1.5, 2.5, 2.5), [[1.0, 0.0, 0.0]])
    assert surface_id[0] == 0 and distance[0] == np.inf


def test_ray_cast_normals_face_the_origin_from_either_side():
    scene = sim.Scene("plate", (sim.Polygon(1, [(0, -1, -1), (0, 1, -1), (0, 1, 1), (0, -1, 1)]),))
    for origin, direction in (((-2.0, 0, 0), (1.0, 0, 0)), ((2.0, 0, 0), (-1.0, 0, 0))):
        distance, _, normal = sim.ray_cast(scene, origin, [direction])
        assert distance[0] == pytest.approx(2.0)
        assert normal[0] @ np.array(direction) < 0


@pytest.mark.parametrize("scene_name", SCENE_NAMES)
def test_ray_cast_kernel_matches_numpy_reference(scene_name):
    scene = sim.get_scene(scene_name)
    rng = np.random.default_rng(5)
    directions = rng.normal(size=(4000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for origin in (np.array([2.0, 1.2, 0.7]), np.array([3.0, 2.0, 1.5])):
        distance, primitive = sim._nearest_hits(scene._packed, origin, directions)
        expected_distance, expected_primitive = sim._nearest_hits_reference(scene._packed, origin, directions)
        np.testing.assert_allclose(distance, expected_distance, rtol=1e-12)
        # Rays through a shared edge may pick either polygon, at the same distance.
        assert (primitive != expected_primitive).sum() <= 2
        assert (primitive >= 0).mean() > 0.4


def test_ray_cast_rejects_bad_inputs():
    with pytest.raises(ValueError, match=r"directions must have shape \(N, 3\)"):
        sim.ray_cast("arena", (0, 0, 1), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="zero length"):
        sim.ray_cast("arena", (1, 1, 1), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="origin"):
        sim.ray_cast("arena", (1, 1), [[1.0, 0, 0]])


# --------------------------------------------------------------------------
# Scenes and trajectories.
# --------------------------------------------------------------------------


def test_polygon_and_scene_validation():
    with pytest.raises(ValueError, match="not convex"):
        sim.Polygon(1, [(0, 0, 0), (2, 0, 0), (1, 0.2, 0), (2, 2, 0), (0, 2, 0)])
    with pytest.raises(ValueError, match="not planar"):
        sim.Polygon(1, [(0, 0, 0), (1, 0, 0), (1, 1, 0.1), (0, 1, 0)])
    with pytest.raises(ValueError, match="surface_id"):
        sim.Polygon(0, [(0, 0, 0), (1, 0, 0), (1, 1, 0)])
    with pytest.raises(ValueError, match="albedo"):
        sim.Polygon(1, [(0, 0, 0), (1, 0, 0), (1, 1, 0)], albedo=1.5)
    floor = sim.Polygon(1, [(0, 0, 0), (1, 0, 0), (1, 1, 0)])
    raised = sim.Polygon(1, [(0, 0, 1), (1, 0, 1), (1, 1, 1)])
    with pytest.raises(ValueError, match="not coplanar"):
        sim.Scene("bad", (floor, raised))


@pytest.mark.parametrize("scene_name", SCENE_NAMES)
def test_scene_surfaces_have_unit_planes_and_expected_parts(scene_name):
    scene = sim.get_scene(scene_name)
    planes = scene.planes
    assert planes.shape == (scene.n_surfaces + 1, 4)
    assert np.isnan(planes[0]).all()
    planar = [p.surface_id for p in scene.polygons]
    np.testing.assert_allclose(np.linalg.norm(planes[planar, :3], axis=1), 1.0)
    for polygon in scene.polygons:
        plane = planes[polygon.surface_id]
        np.testing.assert_allclose(polygon.vertices @ plane[:3] + plane[3], 0, atol=1e-9)
    labels = {p.label for p in (*scene.polygons, *scene.cylinders)}
    assert "floor" in labels
    albedo = [p.albedo for p in scene.polygons]
    assert min(albedo) <= 0.12  # a dark surface
    if scene_name == "arena":
        assert {"ramp top", "stair tread 1", "stair riser 1", "pillar", "dark box top"} <= labels
        for cylinder in scene.cylinders:
            assert np.isnan(planes[cylinder.surface_id]).all()


def test_get_scene_lists_the_names():
    with pytest.raises(ValueError, match="arena, corridor"):
        sim.get_scene("warehouse")
    scene = sim.get_scene("arena")
    assert sim.get_scene(scene) is scene


@pytest.mark.parametrize("scene_name", SCENE_NAMES)
def test_default_trajectory_is_a_proper_robot_path_in_free_space(scene_name):
    scene = sim.get_scene(scene_name)
    frame_rate = 25.0
    poses = sim.default_trajectory(scene, 1000, frame_rate=frame_rate)
    assert poses.shape == (1000, 4, 4) and poses.dtype == np.float64
    rotations = poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.tile(np.eye(3), (1000, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-12)
    forward, down = rotations[:, :, 2], rotations[:, :, 1]
    # Boresight slightly below the horizon; image "down" points down in the world.
    assert np.all((forward[:, 2] < 0) & (forward[:, 2] > -math.sin(math.radians(20))))
    assert np.all(down[:, 2] < -0.9)
    positions = poses[:, :3, 3]
    assert np.all((positions[:, 2] >= 0.5) & (positions[:, 2] <= 1.0))
    speeds = np.linalg.norm(np.diff(positions, axis=0), axis=1) * frame_rate
    assert np.all((speeds > 0.2) & (speeds < 0.5))
    yaw = np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))
    assert np.abs(np.diff(yaw)).max() * frame_rate < 1.2  # rad/s: slow yawing
    length, width = ROOM_BOUNDS[scene_name]
    assert np.all((positions[:, 0] > 0.5) & (positions[:, 0] < length - 0.5))
    assert np.all((positions[:, 1] > 0.5) & (positions[:, 1] < width - 0.5))
    # Free space: horizontal rays just above the floor find nothing within 0.3 m,
    # and the floor lies right below the sensor.
    angles = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    horizontal = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])
    floor = _surface_id(scene, "floor")
    for position in positions[::10]:
        distance, _, _ = sim.ray_cast(scene, (position[0], position[1], 0.1), horizontal)
        assert distance.min() > 0.3
        distance, surface_id, _ = sim.ray_cast(scene, position, [[0.0, 0.0, -1.0]])
        assert surface_id[0] == floor and distance[0] == pytest.approx(position[2])


def test_default_trajectory_frames_do_not_depend_on_length_and_slow_scanners_step_stop_and_go():
    short = sim.default_trajectory("arena", 5, frame_rate=25.0)
    long = sim.default_trajectory("arena", 50, frame_rate=25.0)
    np.testing.assert_array_equal(short, long[:5])
    laser = sim.default_trajectory("arena", 4, frame_rate=0.1)
    steps = np.linalg.norm(np.diff(laser[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.5) & (steps <= 1.0 + 1e-9))
    assert sim.default_trajectory("arena", 0, frame_rate=1.0).shape == (0, 4, 4)
    with pytest.raises(ValueError, match="frame_rate"):
        sim.default_trajectory("arena", 3, frame_rate=0.0)


def test_look_at_points_the_boresight_at_the_target():
    sensor = rs.get_sensor("sr3000")
    pose = sim.look_at((2.0, 1.0, 1.0), (2.0, 5.0, 1.0))
    distance, surface_id, _ = sim.ray_cast("arena", pose[:3, 3], [pose[:3, 2]])
    assert surface_id[0] == _surface_id(sim.get_scene("arena"), "north wall")
    assert distance[0] == pytest.approx(4.0)
    assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)
    # The top image row looks above the bottom row.
    rays = _world_directions(sensor, pose).reshape(sensor.shape + (3,))
    assert rays[0, 88, 2] > 0 > rays[-1, 88, 2]


# --------------------------------------------------------------------------
# Noise-free frames: exact geometry.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("scene_name", SCENE_NAMES)
@pytest.mark.parametrize("sensor_name", SENSOR_NAMES)
def test_noise_free_frames_match_ground_truth_geometry(scene_name, sensor_name):
    scene, sensor = sim.get_scene(scene_name), rs.get_sensor(sensor_name)
    target, eye = CLOSE_UP[scene_name]
    poses = [sim.look_at(eye, target), sim.default_trajectory(scene, 4, frame_rate=sensor.frame_rate)[3]]
    for pose in poses:
        frame, truth = _noise_free(scene, sensor, pose)
        valid = np.isfinite(truth.range)
        np.testing.assert_array_equal(frame.range[valid], truth.range[valid])
        np.testing.assert_array_equal(frame.pose, pose)
        np.testing.assert_array_equal(frame.reference_pose, pose)
        assert not (truth.mixed.any() or truth.outlier.any())
        assert np.all(truth.sigma[np.isfinite(truth.sigma)] == 0)
        # Pixels outside the sensor's range follow its cut-off rule.
        outside = ~valid & truth.clamped
        if sensor.beyond_max_range == "clamp":
            assert np.all(frame.range[outside] == np.float32(sensor.max_range))
        else:
            assert np.isnan(frame.range[outside]).all()
        assert np.all(truth.surface_id[~valid] == 0)

        points = frame.points
        for surface_id in np.unique(truth.surface_id[valid]):
            plane = truth.planes[surface_id]
            mask = truth.surface_id == surface_id
            if np.isnan(plane).any():  # the pillar
                continue
            residual = points[mask].astype(np.float64) @ plane[:3] + plane[3]
            assert np.abs(residual).max() < 1e-4
            np.testing.assert_allclose(truth.normals[mask], np.broadcast_to(plane[:3], (mask.sum(), 3)), atol=1e-5)
        # Normals are unit and face the sensor.
        normals = truth.normals[valid]
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
        assert np.all(np.einsum("ij,ij->i", normals, frame.rays[valid]) < 0)
        assert np.all((truth.intensity[valid] >= 0) & (truth.intensity[valid] <= 1))
        assert np.isnan(truth.intensity[~valid]).all()
    # The close-up always shows a box corner: top and two sides.
    frame, truth = _noise_free(scene, sensor, poses[0])
    assert len(np.unique(truth.surface_id[truth.surface_id > 0])) >= 3


def test_intensity_is_albedo_times_cosine_of_incidence():
    scene = _wall_scene([(3.0, -5.0, 5.0, 0.6)])
    sensor = rs.get_sensor("sr3000")
    pose = sim.look_at((0, 0, 0), (1, 0, 0))
    frame, truth = _noise_free(scene, sensor, pose)
    # Sensor x axis: the wall normal (toward the sensor) is -z in the sensor frame.
    expected = 0.6 * np.abs(frame.rays[..., 2])
    np.testing.assert_allclose(truth.intensity, expected, atol=1e-6)
    np.testing.assert_allclose(frame.intensity, truth.intensity)
    np.testing.assert_allclose(truth.range, 3.0 / frame.rays[..., 2], rtol=1e-6)


def test_planes_are_given_in_the_sensor_frame():
    scene = sim.get_scene("arena")
    pose = sim.default_trajectory(scene, 8, frame_rate=25.0)[7]
    _, truth = _noise_free(scene, "sr3000", pose)
    for polygon in scene.polygons:
        corners_sensor = (polygon.vertices - pose[:3, 3]) @ pose[:3, :3]
        plane = truth.planes[polygon.surface_id]
        np.testing.assert_allclose(corners_sensor @ plane[:3] + plane[3], 0.0, atol=1e-9)
        assert plane[3] >= 0
    assert np.isnan(truth.planes[0]).all()
    assert np.isnan(truth.planes[_surface_id(scene, "pillar")]).all()


# --------------------------------------------------------------------------
# Noise.
# --------------------------------------------------------------------------


def test_range_noise_statistics_match_the_split_normal_model():
    sensor = rs.get_sensor("sr3000")
    frames, truths = sim.simulate_sequence("arena", sensor, n_frames=8, seed=11)
    standardised = []
    for frame, truth in zip(frames, truths):
        usable = (
            np.isfinite(truth.range) & ~truth.mixed & ~truth.outlier & ~truth.clamped
            # Readings near the cut-offs are clipped by the limits, not by the noise model.
            & (truth.range < sensor.max_range - 6 * truth.sigma) & (truth.range > sensor.min_range + 6 * truth.sigma)
        )
        residual = frame.range[usable].astype(np.float64) - truth.range[usable]
        standardised.append(residual / truth.sigma[usable])
    z = np.concatenate(standardised)
    assert len(z) > 150_000
    near, far, _ = sensor.noise.split_normal_scales()
    assert abs(z.mean()) < 0.02
    assert z.std() == pytest.approx(1.0, abs=0.03)
    skewness = np.mean((z - z.mean()) ** 3) / z.std() ** 3
    assert skewness == pytest.approx(_split_normal_skewness(near, far), abs=0.05)
    assert skewness > 0.2  # readings spread further behind the surface than in front


def test_dark_surfaces_are_noisier_than_bright_ones_at_the_same_range():
    sensor = rs.get_sensor("sr3000")
    scene = _wall_scene([(3.0, -5.0, 0.0, 0.8), (3.0, 0.0, 5.0, 0.08)])  # bright right, dark left of the sensor
    pose = sim.look_at((0, 0, 0), (1, 0, 0))
    noise = sim.SimulationNoise(mixed_pixels=False, salt_and_pepper=0.0)
    spreads = {}
    for k in range(3):
        frame, truth = sim.simulate_frame(scene, sensor, pose, noise=noise, rng=np.random.default_rng(k))
        residual = (frame.range.astype(np.float64) - truth.range) / (0.002 + 0.01 * truth.range.astype(np.float64))
        for surface_id in (1, 2):
            spreads.setdefault(surface_id, []).append(residual[truth.surface_id == surface_id])
    bright, dark = (np.concatenate(spreads[s]).std() for s in (1, 2))
    assert bright == pytest.approx(1.0, abs=0.03)
    # Gain sqrt(0.3 / (0.08 cos)) >= 1.94 on the dark half.
    assert dark > 1.9 * bright


def test_noise_grows_about_one_percent_of_range():
    sensor = rs.get_sensor("sr3000")
    pose = sim.look_at((0, 0, 0), (1, 0, 0))
    noise = sim.SimulationNoise(mixed_pixels=False, salt_and_pepper=0.0)
    spreads = []
    for distance in (1.0, 2.5, 5.0):
        scene = _wall_scene([(distance, -10.0, 10.0, 0.9)])
        frame, truth = sim.simulate_frame(scene, sensor, pose, noise=noise, rng=np.random.default_rng(1))
        relative = (frame.range.astype(np.float64) - truth.range) / truth.range
        spreads.append(relative.std())
        expected = 0.002 / distance + 0.01  # floor + 1 % of range, relative to range
        assert relative.std() == pytest.approx(expected, rel=0.05)
        np.testing.assert_allclose(truth.sigma, 0.002 + 0.01 * truth.range, rtol=1e-5)
    assert spreads[0] > spreads[1] > spreads[2]  # relative spread shrinks toward 1 % ...
    absolute = [s * d for s, d in zip(spreads, (1.0, 2.5, 5.0))]
    assert absolute[0] < absolute[1] < absolute[2]  # ... while the absolute spread grows


# --------------------------------------------------------------------------
# Range limits, mixed pixels, outliers.
# --------------------------------------------------------------------------


def test_sr3000_reads_exactly_its_cut_off_beyond_7_5_m():
    scene, sensor = sim.get_scene("corridor"), rs.get_sensor("sr3000")
    pose = sim.look_at((1.0, 1.2, 1.2), (19.0, 1.2, 1.2))
    noise = sim.SimulationNoise(salt_and_pepper=0.0)
    frame, truth = sim.simulate_frame(scene, sensor, pose, noise=noise, rng=np.random.default_rng(3))
    distance = _true_distance(scene, sensor, pose)
    # Well past the cut-off, whatever the noise; mixed pixels may mix in a nearer surface.
    far = (distance > 7.5 * 1.1) & ~truth.mixed
    assert far.mean() > 0.1
    assert np.all(frame.range[far] == np.float32(7.5))
    assert truth.clamped[far].all()
    assert np.isnan(truth.range[far]).all() and np.all(truth.surface_id[far] == 0)
    assert np.all(truth.clamped[frame.range == np.float32(7.5)])
    assert np.all(frame.intensity[truth.clamped] == 0)  # no usable return
    near = distance < 7.5 * 0.9
    assert near.mean() > 0.2 and np.all(frame.range[near] < 7.5)


def test_sensors_that_report_nothing_past_their_range_give_nan():
    scene, sensor = sim.get_scene("corridor"), rs.get_sensor("kinect")
    pose = sim.look_at((1.0, 1.2, 1.2), (19.0, 1.2, 1.2))
    noise = sim.SimulationNoise(salt_and_pepper=0.0)
    frame, truth = sim.simulate_frame(scene, sensor, pose, noise=noise, rng=np.random.default_rng(3))
    distance = _true_distance(scene, sensor, pose)
    assert np.isnan(frame.range[(distance > 8.0 * 1.2) & ~truth.mixed]).all()
    assert np.all(frame.range[np.isfinite(frame.range)] <= 8.0)


def test_ideal_sensor_without_clamping_reports_every_hit():
    scene, sensor = sim.get_scene("corridor"), rs.get_sensor("sr3000")
    pose = sim.look_at((1.0, 1.2, 1.2), (19.0, 1.2, 1.2))
    noise = dataclasses.replace(sim.SimulationNoise.none(), clamp=False)
    frame, truth = sim.simulate_frame(scene, sensor, pose, noise=noise, rng=np.random.default_rng(0))
    distance = _true_distance(scene, sensor, pose)
    np.testing.assert_allclose(frame.range, distance, rtol=1e-6)
    assert np.nanmax(frame.range) > 15.0 and not truth.clamped.any()


def test_uos_laser_sees_open_sky_over_the_arena_as_max_range():
    sensor = rs.get_sensor("uos-laser")
    pose = sim.default_trajectory("arena", 1, frame_rate=sensor.frame_rate)[0]
    frame, truth = _noise_free("arena", sensor, pose)
    sky = np.isinf(_true_distance("arena", sensor, pose))
    assert sky.mean() > 0.05
    assert np.all(frame.range[sky] == np.float32(sensor.max_range)) and truth.clamped[sky].all()


def test_mixed_pixels_lie_strictly_between_foreground_and_background():
    scene, sensor = sim.get_scene("arena"), rs.get_sensor("sr3000")
    noise = sim.SimulationNoise(range_noise=False, salt_and_pepper=0.0)
    poses = sim.default_trajectory(scene, 60, frame_rate=sensor.frame_rate)[::20]
    total = 0
    for pose in poses:
        frame, truth = sim.simulate_frame(scene, sensor, pose, noise=noise, rng=np.random.default_rng(0))
        distance = _true_distance(scene, sensor, pose)
        padded = np.pad(np.where(np.isfinite(distance), distance, np.nan), 1, constant_values=np.nan)
        window = np.lib.stride_tricks.sliding_window_view(padded, (3, 3))
        foreground, background = np.nanmin(window, axis=(2, 3)), np.nanmax(window, axis=(2, 3))
        mixed = truth.mixed & ~truth.clamped
        total += mixed.sum()
        reading = frame.range[mixed].astype(np.float64)
        assert np.all(reading > foreground[mixed] + 1e-4)
        assert np.all(reading < background[mixed] - 1e-4)
        # Real depth jumps, not creases: the neighbourhood spans more than 5 %.
        assert np.all(background[mixed] > 1.05 * foreground[mixed])
        # Everything else is untouched.
        clean = np.isfinite(truth.range) & ~truth.mixed
        np.testing.assert_array_equal(frame.range[clean], truth.range[clean])
    assert total > 50


def test_salt_and_pepper_fraction_and_values():
    sensor = rs.get_sensor("sr3000")
    noise = dataclasses.replace(sim.SimulationNoise.none(), salt_and_pepper=0.05)
    frames, truths = sim.simulate_sequence("arena", sensor, n_frames=4, seed=2, noise=noise)
    outlier = np.stack([t.outlier for t in truths])
    readings = np.stack([f.range for f in frames])
    assert outlier.mean() == pytest.approx(0.05, abs=0.004)
    values = readings[outlier]
    assert np.all((values >= sensor.min_range) & (values <= sensor.max_range))
    assert values.mean() == pytest.approx((sensor.min_range + sensor.max_range) / 2, abs=0.15)
    true_range = np.stack([t.range for t in truths])
    clean = ~outlier & np.isfinite(true_range)
    np.testing.assert_array_equal(readings[clean], true_range[clean])


# --------------------------------------------------------------------------
# Sequences, determinism, saving, input checks.
# --------------------------------------------------------------------------


def test_same_seed_gives_identical_frames_and_different_seeds_differ():
    first_frames, first_truth = sim.simulate_sequence("arena", "sr3000", n_frames=3, seed=4)
    again_frames, again_truth = sim.simulate_sequence("arena", "sr3000", n_frames=3, seed=4)
    for a, b, ta, tb in zip(first_frames, again_frames, first_truth, again_truth):
        np.testing.assert_array_equal(a.range, b.range)
        np.testing.assert_array_equal(a.intensity, b.intensity)
        np.testing.assert_array_equal(ta.outlier, tb.outlier)
        np.testing.assert_array_equal(ta.sigma, tb.sigma)
    other_frames, _ = sim.simulate_sequence("arena", "sr3000", n_frames=3, seed=5)
    assert not np.array_equal(first_frames[2].range, other_frames[2].range, equal_nan=True)
    # Frame k does not depend on how many frames are simulated.
    longer, _ = sim.simulate_sequence("arena", "sr3000", n_frames=5, seed=4)
    np.testing.assert_array_equal(longer[2].range, first_frames[2].range)


def test_sequence_metadata():
    sensor = rs.get_sensor("sr3000")
    frames, truths = sim.simulate_sequence("corridor", sensor, n_frames=3, seed=0)
    assert [f.source for f in frames] == [f"simulated:corridor/sr3000/frame{k:04d}" for k in range(3)]
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 0.04, 0.08])
    poses = sim.default_trajectory("corridor", 3, frame_rate=sensor.frame_rate)
    for frame, truth, pose in zip(frames, truths, poses):
        np.testing.assert_array_equal(frame.reference_pose, pose)
        np.testing.assert_array_equal(truth.T_world_sensor, pose)
        assert frame.rays is sensor.rays() or np.array_equal(frame.rays, sensor.rays())
        assert frame.range.dtype == np.float32 and truth.surface_id.dtype == np.int32
        assert truth.normals.shape == sensor.shape + (3,)
    custom = sim.simulate_sequence("arena", "sr3000", n_frames=2, trajectory=poses[:2])[0]
    np.testing.assert_array_equal(custom[1].pose, poses[1])


def test_frames_keep_their_pose_when_the_callers_array_changes():
    pose = sim.look_at((2.0, 1.0, 1.0), (2.0, 5.0, 1.0))
    frame, truth = _noise_free("arena", "sr3000", pose)
    expected = pose.copy()
    pose[:3, 3] = 0.0
    for stored in (frame.pose, frame.reference_pose, truth.T_world_sensor):
        np.testing.assert_array_equal(stored, expected)


def test_ground_truth_save_load_round_trip(tmp_path):
    _, truths = sim.simulate_sequence("arena", "sr3000", n_frames=1, seed=9)
    truth = truths[0]
    path = tmp_path / "truth" / "frame0000.npz"
    sim.save_ground_truth(path, truth)
    loaded = sim.load_ground_truth(path)
    for field in dataclasses.fields(sim.GroundTruth):
        original, restored = getattr(truth, field.name), getattr(loaded, field.name)
        assert restored.dtype == np.asarray(original).dtype
        np.testing.assert_array_equal(restored, original)
    assert sorted(p.name for p in path.parent.iterdir()) == ["frame0000.npz"]  # no temporary left
    np.savez(tmp_path / "other.npz", range=np.zeros((2, 2)))
    with pytest.raises(FormatError, match="missing ground-truth field"):
        sim.load_ground_truth(tmp_path / "other.npz")


def test_bad_inputs_raise_clear_errors():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="unknown scene 'lab'"):
        sim.simulate_sequence("lab", "sr3000", n_frames=1)
    with pytest.raises(ValueError, match="unknown sensor 'sr4000'"):
        sim.simulate_sequence("arena", "sr4000", n_frames=1)
    with pytest.raises(ValueError, match=r"T_world_sensor must be a 4x4 matrix, got shape \(3, 4\)"):
        sim.simulate_frame("arena", "sr3000", np.eye(4)[:3], rng=rng)
    with pytest.raises(ValueError, match="proper rotation"):
        sim.simulate_frame("arena", "sr3000", np.diag([1.0, 1.0, -1.0, 1.0]), rng=rng)
    with pytest.raises(ValueError, match=r"trajectory must have shape \(2, 4, 4\)"):
        sim.simulate_sequence("arena", "sr3000", n_frames=2, trajectory=np.eye(4)[None])
    with pytest.raises(ValueError, match="n_frames"):
        sim.simulate_sequence("arena", "sr3000", n_frames=-1)
    with pytest.raises(ValueError, match="no projection model"):
        sim.simulate_frame("arena", rs.unknown_sensor(4, 4), np.eye(4), rng=rng)
    with pytest.raises(TypeError, match="Generator"):
        sim.simulate_frame("arena", "sr3000", np.eye(4), rng=0)
    with pytest.raises(ValueError, match="salt_and_pepper"):
        sim.SimulationNoise(salt_and_pepper=1.5)


def test_frame_outside_every_surface_is_all_cut_off():
    # Looking up out of the roofless arena: nothing but sky.
    sensor = rs.get_sensor("sr3000")
    pose = sim.look_at((3.0, 2.0, 3.0), (3.0, 2.0, 10.0), up=(0.0, 1.0, 0.0))
    frame, truth = sim.simulate_frame("arena", sensor, pose, rng=np.random.default_rng(0))
    assert np.isnan(truth.range).all() and np.isnan(truth.sigma).all()
    assert truth.clamped[~truth.outlier].all()
    assert np.all(frame.range[~truth.outlier] == np.float32(7.5))
    assert not truth.mixed.any()


def test_iter_sequence_streams_the_same_frames_as_simulate_sequence():
    frames, truths = sim.simulate_sequence("corridor", "sr3000", 3, seed=11)
    for k, (frame, truth) in enumerate(sim.iter_sequence("corridor", "sr3000", 3, seed=11)):
        np.testing.assert_array_equal(frame.range, frames[k].range)
        np.testing.assert_array_equal(truth.surface_id, truths[k].surface_id)
    with pytest.raises(ValueError, match="unknown scene"):
        sim.iter_sequence("moon", "sr3000", 3)  # checked before the first frame is asked for
