"""Shared fixtures of the io tests."""

# --- fixtures of the PCD / npz / depth PNG / ROS bag tests (prefix fmt_) ---

import numpy as np
import pytest

import rangesurf as rs


def _fmt_rotation(axis, angle):
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def _fmt_transform(axis, angle, translation):
    transform = np.eye(4)
    transform[:3, :3] = _fmt_rotation(axis, angle)
    transform[:3, 3] = translation
    return transform


def _fmt_plane_frame(sensor="sr3000", *, intensity=True, pose=True, reference_pose=True, timestamp=12.345, seed=0):
    """A frame of the plane n . p = 2.5 m seen by ``sensor``, with NaN holes.

    Ground truth for the readers: whatever they read back must be this frame.
    """
    sensor = rs.get_sensor(sensor)
    rng = np.random.default_rng(seed)
    rays = sensor.rays()
    normal = np.array([0.1, -0.2, 1.0])
    normal /= np.linalg.norm(normal)
    facing = rays.astype(np.float64) @ normal
    with np.errstate(divide="ignore"):
        range_image = np.where(facing > 0.2, 2.5 / facing, np.nan)
    holes = rng.random(sensor.shape) < 0.05
    holes[sensor.height // 4: sensor.height // 3, sensor.width // 5: sensor.width // 2] = True
    range_image[holes] = np.nan
    values = None
    if intensity:
        values = rng.random(sensor.shape).astype(np.float32)
        values[~np.isfinite(range_image)] = np.nan
    return rs.RangeFrame(
        rays=rays, range=range_image.astype(np.float32), sensor=sensor, intensity=values,
        pose=_fmt_transform([1, 2, 3], 0.7, [1.0, -2.0, 0.5]) if pose else None,
        reference_pose=_fmt_transform([0, 0, 1], -0.3, [1.1, -2.05, 0.48]) if reference_pose else None,
        timestamp=timestamp, source=f"plane seen by {sensor.name}",
    )


@pytest.fixture
def fmt_plane_frame():
    """Factory ``fmt_plane_frame(sensor="sr3000", *, intensity, pose, reference_pose, timestamp, seed)``."""
    return _fmt_plane_frame


@pytest.fixture
def fmt_transform():
    """Factory ``fmt_transform(axis, angle, translation)`` of a 4x4 rigid transform."""
    return _fmt_transform
