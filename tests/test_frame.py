"""SensorModel, noise model and RangeFrame: geometry and validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

import rangesurf as rs
from rangesurf.frame import check_rigid_transform


def _rotation_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    transform = np.eye(4)
    transform[:2, :2] = [[c, -s], [s, c]]
    return transform


@pytest.mark.parametrize("name", sorted(rs.SENSORS))
def test_preset_rays_are_unit_and_match_grid(name):
    sensor = rs.get_sensor(name)
    rays = sensor.rays()
    assert rays.shape == (sensor.height, sensor.width, 3)
    assert rays.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-6)
    assert not rays.flags.writeable


@pytest.mark.parametrize("name", ["sr3000", "kinect"])
def test_pinhole_rays_project_back_to_their_pixels(name):
    sensor = rs.get_sensor(name)
    projection = sensor.projection
    rays = sensor.rays().astype(np.float64)
    cols = projection.fx * rays[..., 0] / rays[..., 2] + projection.cx
    rows = projection.fy * rays[..., 1] / rays[..., 2] + projection.cy
    expected_rows, expected_cols = np.mgrid[0 : sensor.height, 0 : sensor.width]
    np.testing.assert_allclose(cols, expected_cols, atol=1e-3)
    np.testing.assert_allclose(rows, expected_rows, atol=1e-3)


def test_sr3000_field_of_view_matches_data_sheet():
    # 47.5 x 39.6 degrees (MESA SR-3000 with its standard lens).
    rays = rs.get_sensor("sr3000").rays()
    horizontal = math.degrees(math.acos(float(np.dot(rays[72, 0], rays[72, -1]))))
    vertical = math.degrees(math.acos(float(np.dot(rays[0, 88], rays[-1, 88]))))
    assert horizontal == pytest.approx(47.5, abs=0.5)
    assert vertical == pytest.approx(39.6, abs=0.5)


def test_swept_fan_rays_match_a_measured_3dtk_direction():
    # scan000.3d, line 0, point 180: (0, -38.2, 33.5) cm in 3DTK's y-up frame,
    # i.e. (0, 38.2, 33.5) in the y-down sensor frame; point 0 lies on +x.
    rays = rs.get_sensor("uos-laser").rays()
    expected = np.array([0.0, 38.2, 33.5]) / np.hypot(38.2, 33.5)
    assert math.degrees(math.acos(float(np.dot(rays[0, 180], expected)))) < 0.2
    np.testing.assert_allclose(rays[100, 0], [1, 0, 0], atol=1e-6)


def test_sr3000_noise_is_one_percent_of_range_and_grows_for_dark_surfaces():
    sensor = rs.get_sensor("sr3000")
    bright = sensor.range_sigma(np.array([1.0, 5.0]), np.array([0.8, 0.8]))
    # floor + 1 % of range
    np.testing.assert_allclose(bright, [0.002 + 0.01, 0.002 + 0.05])
    dark = sensor.range_sigma(np.array([5.0]), np.array([0.075]))
    # a quarter of the reference intensity doubles the spread (exponent 0.5)
    np.testing.assert_allclose(dark, 2 * bright[1])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_noise_sigma_of_images_is_the_formula_to_the_bit(dtype):
    """Frames take the compiled path; it must give what the documented formula gives, NaN and odd values included."""
    noise = rs.RangeNoiseModel(relative=0.01, floor=0.002, quadratic=0.001, reference_intensity=0.3, intensity_exponent=0.5)
    rng = np.random.default_rng(1)
    ranges = rng.uniform(0.01, 60.0, (30, 40)).astype(dtype)
    intensity = rng.uniform(0.0, 1.2, ranges.shape).astype(dtype)
    ranges[0, :3] = [np.nan, np.inf, 0.0]
    intensity[1, :4] = [np.nan, 0.0, np.inf, -1.0]
    r, i = ranges.astype(np.float64), intensity.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        expected = (0.002 + 0.01 * r + 0.001 * r**2) * np.maximum((0.3 / np.maximum(i, 1e-6)) ** 0.5, 1.0)
        no_gain = 0.002 + 0.01 * r + 0.001 * r**2
    assert np.array_equal(noise.sigma(ranges, intensity), expected, equal_nan=True)
    assert np.array_equal(noise.sigma(ranges), no_gain, equal_nan=True)
    assert noise.sigma(2.0) == pytest.approx(0.002 + 0.02 + 0.004)  # scalars too


def test_kinect_noise_grows_quadratically():
    sigma = rs.get_sensor("kinect").range_sigma(np.array([1.0, 2.0, 4.0]))
    growth = np.diff(sigma)
    assert growth[1] > 2 * growth[0]


@pytest.mark.parametrize("asymmetry", [1.0, 1.5, 3.0])
def test_split_normal_has_zero_mean_and_unit_variance(asymmetry):
    noise = rs.RangeNoiseModel(relative=0.01, asymmetry=asymmetry)
    near, far, offset = noise.split_normal_scales()
    # Moments by quadrature of the split-normal density with mode 0.
    z = np.linspace(-12, 12, 200_001)
    scale = np.where(z < 0, near, far)
    density = np.exp(-0.5 * (z / scale) ** 2) * 2 / (math.sqrt(2 * math.pi) * (near + far))
    step = z[1] - z[0]
    assert density.sum() * step == pytest.approx(1.0, abs=1e-6)
    mean = (z * density).sum() * step
    variance = ((z - mean) ** 2 * density).sum() * step
    assert mean + offset == pytest.approx(0.0, abs=1e-6)
    assert variance == pytest.approx(1.0, abs=1e-6)
    assert far / near == pytest.approx(asymmetry)


def test_sensor_model_dict_round_trip():
    for sensor in rs.SENSORS.values():
        assert rs.SensorModel.from_dict(sensor.to_dict()) == sensor
    unknown = rs.unknown_sensor(4, 5)
    assert rs.SensorModel.from_dict(unknown.to_dict()) == unknown


def test_unknown_sensor_name_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown sensor 'sr4000'.*sr3000"):
        rs.get_sensor("sr4000")


def test_sensor_model_rejects_bad_parameters():
    with pytest.raises(ValueError, match="min_range < max_range"):
        rs.SensorModel(name="x", width=2, height=2, projection=None, min_range=5.0, max_range=1.0, frame_rate=1.0)
    with pytest.raises(ValueError, match="asymmetry"):
        rs.RangeNoiseModel(asymmetry=0.0)
    with pytest.raises(ValueError, match="no projection"):
        rs.unknown_sensor(3, 3).rays()


def _plane_frame(sensor_name="sr3000", distance=2.0):
    sensor = rs.get_sensor(sensor_name)
    rays = sensor.rays()
    # A wall at z = distance: range = distance / ray_z.
    range_image = (distance / rays[..., 2]).astype(np.float32)
    return sensor, rays, range_image


def test_frame_points_lie_on_the_simulated_wall():
    sensor, rays, range_image = _plane_frame()
    range_image[:10] = np.nan
    frame = rs.RangeFrame(rays=rays, range=range_image, sensor=sensor, pose=_rotation_z(0.3))
    points = frame.points
    np.testing.assert_allclose(points[frame.valid][:, 2], 2.0, rtol=1e-6)
    assert np.isnan(points[:10]).all()
    world = frame.world_points()
    assert world.shape == (int(frame.valid.sum()), 3)
    np.testing.assert_allclose(world[:, 2], 2.0, rtol=1e-6)  # rotation about z keeps z


def test_from_points_recovers_rays_and_range_and_fills_missing_rays():
    sensor, rays, range_image = _plane_frame()
    points = rays * range_image[..., None]
    points[5, 7] = np.nan
    points[6, 8] = 0.0  # zero points are "no return" in many formats
    frame = rs.RangeFrame.from_points(points, sensor=sensor)
    assert not frame.valid[5, 7] and not frame.valid[6, 8]
    np.testing.assert_allclose(frame.range[frame.valid], range_image[frame.valid], rtol=1e-6)
    np.testing.assert_allclose(frame.rays, rays, atol=1e-6)  # missing ones from the projection

    unknown = rs.RangeFrame.from_points(points)  # no projection: nearest valid ray
    assert unknown.sensor.projection is None
    angle = np.degrees(np.arccos(np.clip(np.sum(unknown.rays[5, 7] * rays[5, 7]), -1, 1)))
    assert angle < 0.5


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda r: r[..., None], "must be 2-D"),
        (lambda r: np.where(np.arange(r.size).reshape(r.shape) == 3, np.inf, r), "contains Inf"),
        (lambda r: np.where(np.arange(r.size).reshape(r.shape) == 3, -1.0, r), "values <= 0"),
        (lambda r: r[:-1], "does not match sensor"),
    ],
)
def test_frame_rejects_bad_range_images(change, message):
    sensor, rays, range_image = _plane_frame()
    with pytest.raises(ValueError, match=message):
        rs.RangeFrame(rays=rays, range=change(range_image), sensor=sensor)


def test_frame_rejects_bad_rays_intensity_and_poses():
    sensor, rays, range_image = _plane_frame()
    with pytest.raises(ValueError, match="unit vectors"):
        rs.RangeFrame(rays=rays * 2, range=range_image, sensor=sensor)
    with pytest.raises(ValueError, match=r"rays must have shape \(144, 176, 3\)"):
        rs.RangeFrame(rays=rays[:, :, :2], range=range_image, sensor=sensor)
    with pytest.raises(ValueError, match="intensity shape"):
        rs.RangeFrame(rays=rays, range=range_image, sensor=sensor, intensity=np.ones((3, 3)))
    with pytest.raises(ValueError, match="4x4"):
        rs.RangeFrame(rays=rays, range=range_image, sensor=sensor, pose=np.eye(3))
    reflection = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="proper rotation"):
        rs.RangeFrame(rays=rays, range=range_image, sensor=sensor, pose=reflection)
    with pytest.raises(ValueError, match="reference_pose"):
        rs.RangeFrame(rays=rays, range=range_image, sensor=sensor, reference_pose=np.full((4, 4), np.nan))


def test_frame_without_pose_cannot_give_world_points():
    sensor, rays, range_image = _plane_frame()
    frame = rs.RangeFrame(rays=rays, range=range_image, sensor=sensor, source="wall.npz")
    with pytest.raises(ValueError, match="wall.npz has no pose"):
        frame.world_points()


def test_check_rigid_transform_accepts_rotations():
    transform = _rotation_z(1.0)
    transform[:3, 3] = [1, 2, 3]
    np.testing.assert_array_equal(check_rigid_transform(transform), transform)
    with pytest.raises(ValueError, match="last row"):
        bad = transform.copy()
        bad[3, 0] = 1
        check_rigid_transform(bad)


@pytest.mark.parametrize(
    "defect, message",
    [("nan", "NaN or Inf"), ("inf", "NaN or Inf"), ("scale", "not a proper rotation"),
     ("shear", "not a proper rotation"), ("mirror", "not a proper rotation"), ("row", "last row")],
)
def test_check_rigid_transform_names_each_defect(defect, message):
    transform = _rotation_z(0.3)
    transform[:3, 3] = [0.5, -1.0, 2.0]
    bad = transform.copy()
    if defect == "nan":
        bad[1, 3] = np.nan
    elif defect == "inf":
        bad[0, 0] = np.inf
    elif defect == "scale":
        bad[:3, :3] *= 1.001  # R R^T off the identity by 2e-3
    elif defect == "shear":
        bad[0, 1] += 1e-3
    elif defect == "mirror":
        bad[:3, 2] *= -1.0  # orthonormal, determinant -1
    else:
        bad[3, 3] = 1.0 + 1e-6
    with pytest.raises(ValueError, match=f"odometry.*{message}"):
        check_rigid_transform(bad, "odometry")
    # Within the tolerances: accepted as given.
    nearly = transform.copy()
    nearly[:3, :3] *= 1.0 + 1e-6
    nearly[3, 3] = 1.0 + 1e-10
    np.testing.assert_array_equal(check_rigid_transform(nearly), nearly)
