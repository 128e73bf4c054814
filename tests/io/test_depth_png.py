"""16-bit depth PNG + intrinsics JSON: round trips, JSON layouts, bad files."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import rangesurf as rs
from rangesurf.io import FormatError
from rangesurf.io.depth_png import read_depth_png, write_depth_png


def _read(path, **options):
    frames = list(read_depth_png(path, **options))
    assert len(frames) == 1
    return frames[0]


def _z(frame):
    return frame.range.astype(np.float64) * frame.rays[..., 2]


def _write_png(path, image):
    assert cv2.imwrite(str(path), image)


# --------------------------------------------------------------------------
# Round trips.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("sensor_name", ["sr3000", "kinect", "cyberware"])
def test_round_trip_exact_to_the_millimetre(tmp_path, fmt_plane_frame, sensor_name):
    original = fmt_plane_frame(sensor_name)
    path = tmp_path / "depth" / "000000.png"
    write_depth_png(path, original)
    assert sorted(p.name for p in path.parent.iterdir()) == ["000000.json", "000000.png"]

    copy = _read(path)
    assert copy.sensor is rs.get_sensor(sensor_name)
    np.testing.assert_array_equal(copy.valid, original.valid)
    valid = original.valid
    # Depth is quantised to 1 mm: half a unit plus float32 rounding.
    assert np.max(np.abs(_z(copy)[valid] - _z(original)[valid])) <= 0.5e-3 + 1e-6
    # Range error is that depth error stretched along the ray.
    range_error = np.abs(copy.range - original.range)[valid]
    assert np.all(range_error <= 0.5e-3 / original.rays[..., 2][valid] + 2e-6)
    np.testing.assert_array_equal(copy.rays, original.rays)
    np.testing.assert_allclose(copy.pose, original.pose, atol=1e-15)
    assert copy.timestamp == original.timestamp
    assert copy.intensity is None and copy.reference_pose is None


def test_png_holds_z_depth_in_units_of_depth_scale(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame(pose=False)
    path = tmp_path / "d.png"
    write_depth_png(path, original, depth_scale=5000)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint16 and image.shape == (144, 176)
    np.testing.assert_array_equal(image[~original.valid], 0)
    expected = np.rint(_z(original)[original.valid] * 5000)
    np.testing.assert_array_equal(image[original.valid], expected)
    assert json.loads(path.with_suffix(".json").read_text())["depth_scale"] == 5000
    copy = _read(path)
    assert np.max(np.abs(_z(copy)[original.valid] - _z(original)[original.valid])) <= 0.5 / 5000 + 1e-6
    assert copy.pose is None


def test_save_and_load_dispatch_to_depth_png(tmp_path, fmt_plane_frame):
    frames = [fmt_plane_frame(timestamp=t) for t in (1.0, 2.0)]
    rs.save(tmp_path / "seq", frames, format="png")
    copies = rs.load(tmp_path / "seq")
    assert [f.timestamp for f in copies] == [1.0, 2.0]
    np.testing.assert_array_equal(copies[1].valid, frames[1].valid)


# --------------------------------------------------------------------------
# Intrinsics written by other tools.
# --------------------------------------------------------------------------


def _plane_depth_units(projection, shape, depth_scale):
    """Ground truth: the plane z = 1.5 + 0.2 x, its PNG and its ranges."""
    directions = projection.directions(*shape)
    # z = 1.5 + 0.2 * x with x = z * dx  =>  z = 1.5 / (1 - 0.2 * dx).
    depth = 1.5 / (1 - 0.2 * directions[..., 0])
    units = np.rint(depth * depth_scale).astype(np.uint16)
    units[:3, :4] = 0
    depth = units / depth_scale
    return units, depth * np.linalg.norm(directions, axis=-1)


def test_open3d_intrinsics_json_in_the_folder(tmp_path):
    projection = rs.PinholeProjection(fx=300.0, fy=310.0, cx=40.5, cy=29.0)
    units, expected_range = _plane_depth_units(projection, (60, 80), 5000.0)
    _write_png(tmp_path / "frame_0001.png", units)
    # Open3D's column-major intrinsic matrix.
    k = np.array([[300.0, 0, 40.5], [0, 310.0, 29.0], [0, 0, 1]])
    (tmp_path / "intrinsics.json").write_text(json.dumps(
        {"width": 80, "height": 60, "intrinsic_matrix": k.T.ravel().tolist(), "depth_scale": 5000.0}
    ))

    frame = _read(tmp_path / "frame_0001.png")
    assert frame.sensor.name == "depth-camera"
    assert frame.sensor.projection == projection
    assert np.isnan(frame.range[:3, :4]).all()
    valid = units > 0
    np.testing.assert_allclose(frame.range[valid], expected_range[valid], rtol=1e-6)
    # The points lie on the plane the depth came from.
    points = frame.points[valid].astype(np.float64)
    np.testing.assert_allclose(points[:, 2], 1.5 + 0.2 * points[:, 0], atol=2e-4)


def test_our_intrinsics_in_camera_intrinsics_json_with_default_scale(tmp_path):
    kinect = rs.get_sensor("kinect")
    units, expected_range = _plane_depth_units(kinect.projection, kinect.shape, 1000.0)
    _write_png(tmp_path / "a.png", units)
    (tmp_path / "camera_intrinsics.json").write_text(json.dumps(
        {"width": 640, "height": 480, "fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5}
    ))
    frame = _read(tmp_path / "a.png")
    assert frame.sensor is kinect  # identical intrinsics: the preset
    valid = units > 0
    np.testing.assert_allclose(frame.range[valid], expected_range[valid], rtol=1e-6)


def test_stem_json_wins_and_names_the_sensor(tmp_path):
    projection = rs.PinholeProjection(fx=100.0, fy=100.0, cx=9.5, cy=7.5)
    units, _ = _plane_depth_units(projection, (16, 20), 1000.0)
    _write_png(tmp_path / "a.png", units)
    (tmp_path / "a.json").write_text(json.dumps(
        {"width": 20, "height": 16, "fx": 100.0, "fy": 100.0, "cx": 9.5, "cy": 7.5, "sensor": "bench-cam", "frame_rate": 15}
    ))
    (tmp_path / "intrinsics.json").write_text(json.dumps({"width": 1, "height": 1, "fx": 1, "fy": 1, "cx": 0, "cy": 0}))
    frame = _read(tmp_path / "a.png")
    assert frame.sensor.name == "bench-cam" and frame.sensor.frame_rate == 15.0


def test_sensor_argument_replaces_missing_intrinsics(tmp_path):
    sr3000 = rs.get_sensor("sr3000")
    units, expected_range = _plane_depth_units(sr3000.projection, sr3000.shape, 1000.0)
    _write_png(tmp_path / "a.png", units)
    frame = _read(tmp_path / "a.png", sensor=sr3000)
    valid = units > 0
    np.testing.assert_allclose(frame.range[valid], expected_range[valid], rtol=1e-6)


# --------------------------------------------------------------------------
# Refused writes.
# --------------------------------------------------------------------------


def test_depth_beyond_16_bits_is_refused_not_clipped(tmp_path, fmt_plane_frame):
    frame = fmt_plane_frame()
    far = frame.replace(range=np.where(frame.valid, frame.range * 30, np.nan))
    with pytest.raises(ValueError, match=r"exceeds the 65\.535 m a 16-bit PNG holds at depth_scale=1000"):
        write_depth_png(tmp_path / "far.png", far)
    with pytest.raises(ValueError, match=r"exceeds the 2\.184 m .* at depth_scale=30000; lower depth_scale"):
        write_depth_png(tmp_path / "far.png", frame, depth_scale=30000)
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_non_pinhole_sensor_is_refused(tmp_path, fmt_plane_frame):
    with pytest.raises(ValueError, match=r"pinhole projection; sensor 'uos-laser' has a swept_fan projection"):
        write_depth_png(tmp_path / "a.png", fmt_plane_frame("uos-laser"))
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------
# Bad files.
# --------------------------------------------------------------------------


def test_wrong_dtype_or_channels(tmp_path):
    (tmp_path / "intrinsics.json").write_text(json.dumps({"fx": 10, "fy": 10, "cx": 2, "cy": 2}))
    _write_png(tmp_path / "gray8.png", np.full((5, 5), 7, np.uint8))
    with pytest.raises(FormatError, match=r"gray8\.png, IHDR: expected a single-channel 16-bit depth image, the header declares bit depth 8 and colour type 0"):
        _read(tmp_path / "gray8.png")
    _write_png(tmp_path / "color16.png", np.full((5, 5, 3), 7, np.uint16))
    with pytest.raises(FormatError, match=r"color16\.png, IHDR: .*bit depth 16 and colour type 2"):
        _read(tmp_path / "color16.png")


def test_missing_intrinsics_json(tmp_path):
    _write_png(tmp_path / "alone.png", np.full((5, 5), 1000, np.uint16))
    with pytest.raises(FormatError, match=r"alone\.png, intrinsics: no intrinsics JSON found .*alone\.json, intrinsics\.json, camera_intrinsics\.json"):
        _read(tmp_path / "alone.png")


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ({"width": 6, "height": 5, "fx": 10, "fy": 10, "cx": 2, "cy": 2}, r"field 'width': intrinsics are for width 6, but the PNG's width is 5"),
        ({"fx": 10, "fy": 10, "cx": 2}, r"field 'cy': missing number"),
        ({"fx": "ten", "fy": 10, "cx": 2, "cy": 2}, r"field 'fx': expected a finite number, got 'ten'"),
        ({"intrinsic_matrix": [1, 2, 3]}, r"field 'intrinsic_matrix': expected 9 numbers"),
        ({"fx": 10, "fy": 10, "cx": 2, "cy": 2, "depth_scale": 0}, r"field 'depth_scale': must be > 0"),
        ({"fx": 10, "fy": 10, "cx": 2, "cy": 2, "pose": [[1, 0], [0, 1]]}, r"field 'pose': pose must be a 4x4 matrix"),
        ([1, 2], r"expected a JSON object, got list"),
    ],
)
def test_bad_intrinsics_are_named(tmp_path, content, message):
    _write_png(tmp_path / "a.png", np.full((5, 5), 1000, np.uint16))
    (tmp_path / "a.json").write_text(json.dumps(content))
    with pytest.raises(FormatError, match=r"a\.json, " * (not message.startswith("expected")) + message):
        _read(tmp_path / "a.png")


def test_empty_and_undecodable_files(tmp_path):
    (tmp_path / "intrinsics.json").write_text("{not json")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(FormatError, match=r"empty\.png: empty file"):
        _read(tmp_path / "empty.png")
    (tmp_path / "junk.png").write_bytes(b"\x89PNG junk")
    with pytest.raises(FormatError, match=r"junk\.png: cannot decode the image"):
        _read(tmp_path / "junk.png")
    _write_png(tmp_path / "ok.png", np.full((5, 5), 1000, np.uint16))
    with pytest.raises(FormatError, match=r"intrinsics\.json: not a readable JSON file"):
        _read(tmp_path / "ok.png")
