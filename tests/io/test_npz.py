"""rangesurf .npz frames and bare .npy grids: round trips and bad files."""

from __future__ import annotations

import json

import numpy as np
import pytest

import rangesurf as rs
from rangesurf.io import FormatError
from rangesurf.io.npz import FORMAT_VERSION, read_npy, read_npz, write_npz


def _read(reader, path, **options):
    frames = list(reader(path, **options))
    assert len(frames) == 1
    return frames[0]


def _arrays(path):
    with np.load(path, allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


def _assert_same_frame(copy, original):
    np.testing.assert_array_equal(copy.range, original.range)
    np.testing.assert_array_equal(copy.rays, original.rays)
    for name in ("intensity", "pose", "reference_pose"):
        if getattr(original, name) is None:
            assert getattr(copy, name) is None
        else:
            np.testing.assert_array_equal(getattr(copy, name), getattr(original, name))
    assert copy.sensor == original.sensor
    assert copy.timestamp == original.timestamp
    assert copy.source == original.source


# --------------------------------------------------------------------------
# .npz round trips.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("sensor_name", ["sr3000", "uos-laser", "cyberware"])
def test_round_trip_is_lossless(tmp_path, fmt_plane_frame, sensor_name):
    original = fmt_plane_frame(sensor_name)
    write_npz(tmp_path / "frame.npz", original)
    _assert_same_frame(_read(read_npz, tmp_path / "frame.npz"), original)


def test_round_trip_without_optional_fields(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame(intensity=False, pose=False, reference_pose=False, timestamp=0.0)
    write_npz(tmp_path / "frame.npz", original)
    assert {"intensity", "pose", "reference_pose"}.isdisjoint(_arrays(tmp_path / "frame.npz"))
    _assert_same_frame(_read(read_npz, tmp_path / "frame.npz"), original)


def test_layout_and_custom_sensor_survive(tmp_path, fmt_plane_frame):
    base = fmt_plane_frame()
    custom = rs.SensorModel(
        name="bench-tof", width=base.sensor.width, height=base.sensor.height, projection=None,
        min_range=0.0, max_range=float("inf"), frame_rate=12.5,
        noise=rs.RangeNoiseModel(relative=0.02, asymmetry=1.3), description="rays from the data",
    )
    original = base.replace(sensor=custom)
    path = tmp_path / "frame.npz"
    write_npz(path, original)

    arrays = _arrays(path)
    assert int(arrays["format_version"]) == FORMAT_VERSION
    assert arrays["rays"].dtype == np.float32 and arrays["rays"].shape == (144, 176, 3)
    assert arrays["range"].dtype == np.float32
    assert json.loads(str(arrays["sensor"]))["name"] == "bench-tof"
    copy = _read(read_npz, path)
    _assert_same_frame(copy, original)
    assert copy.sensor.noise.asymmetry == 1.3


def test_file_name_is_kept_exactly(tmp_path, fmt_plane_frame):
    write_npz(tmp_path / "frame.data", fmt_plane_frame())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.data"]


def test_sensor_override_and_rays_from_projection(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame()
    arrays = _arrays_of(original)
    del arrays["rays"], arrays["sensor"]
    path = tmp_path / "bare.npz"
    np.savez(path, **arrays)
    sensor = rs.get_sensor("sr3000")
    copy = _read(read_npz, path, sensor=sensor)
    assert copy.sensor is sensor
    np.testing.assert_array_equal(copy.rays, sensor.rays())
    np.testing.assert_array_equal(copy.range, original.range)
    with pytest.raises(FormatError, match=r"bare\.npz, field 'rays': missing array, and the sensor has no projection"):
        _read(read_npz, path)


def test_save_and_load_dispatch_to_npz(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame()
    rs.save(tmp_path / "frame.npz", original)
    (copy,) = rs.load(tmp_path / "frame.npz")
    _assert_same_frame(copy, original)


# --------------------------------------------------------------------------
# Bad .npz files.
# --------------------------------------------------------------------------


def _arrays_of(frame):
    return {
        "format_version": np.array(FORMAT_VERSION), "range": frame.range, "rays": frame.rays,
        "timestamp": np.array(frame.timestamp), "source": np.array(frame.source),
        "sensor": np.array(json.dumps(frame.sensor.to_dict())),
    }


def test_missing_range(tmp_path, fmt_plane_frame):
    arrays = _arrays_of(fmt_plane_frame())
    del arrays["range"]
    np.savez(tmp_path / "norange.npz", **arrays)
    with pytest.raises(FormatError, match=r"norange\.npz, field 'range': missing array; the archive holds format_version, rays"):
        _read(read_npz, tmp_path / "norange.npz")


def test_inf_instead_of_nan_in_range(tmp_path, fmt_plane_frame):
    arrays = _arrays_of(fmt_plane_frame())
    arrays["range"] = np.where(np.isnan(arrays["range"]), np.inf, arrays["range"])
    np.savez(tmp_path / "inf.npz", **arrays)
    with pytest.raises(FormatError, match=r"inf\.npz, field 'range': \d+ cells are Inf; rangesurf marks missing returns with NaN"):
        _read(read_npz, tmp_path / "inf.npz")


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("range", np.zeros((144, 176), np.float32), r"field 'range': 25344 cells are <= 0"),
        ("range", np.ones(176, np.float32), r"field 'range': expected 2-D array, got shape \(176,\)"),
        ("range", np.array(["a", "b"]), r"field 'range': expected a numeric array, got dtype <U1"),
        ("rays", np.ones((144, 176, 3), np.float32), r"field 'rays': rays must be finite unit vectors"),
        ("rays", np.ones((10, 10, 3), np.float32), r"field 'rays': expected shape \(144, 176, 3\), got \(10, 10, 3\)"),
        ("intensity", np.ones((3, 3), np.float32), r"field 'intensity': expected shape \(144, 176\)"),
        ("pose", np.ones((4, 4)), r"field 'pose': pose last row must be"),
        ("timestamp", np.array([1.0, 2.0]), r"field 'timestamp': expected a scalar"),
        ("sensor", np.array("{not json"), r"field 'sensor': not a valid sensor description"),
        ("format_version", np.array(FORMAT_VERSION + 1), r"field 'format_version': format_version 2 is newer"),
    ],
)
def test_bad_arrays_are_named(tmp_path, fmt_plane_frame, name, value, message):
    arrays = _arrays_of(fmt_plane_frame())
    arrays[name] = value
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FormatError, match=r"bad\.npz, " + message):
        _read(read_npz, tmp_path / "bad.npz")


def test_empty_and_foreign_files(tmp_path):
    path = tmp_path / "x.npz"
    path.write_bytes(b"")
    with pytest.raises(FormatError, match=r"x\.npz: empty file"):
        _read(read_npz, path)
    path.write_bytes(b"this is not a zip archive")
    with pytest.raises(FormatError, match=r"x\.npz: not a readable NumPy \.npz archive"):
        _read(read_npz, path)
    with open(path, "wb") as stream:
        np.save(stream, np.ones((2, 2)))
    with pytest.raises(FormatError, match=r"x\.npz: holds a single array"):
        _read(read_npz, path)
    np.savez_compressed(path, range=np.ones((50, 50)))
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(FormatError, match=r"x\.npz: not a readable NumPy \.npz archive"):
        _read(read_npz, path)
    np.savez(path, range=np.array([{"a": 1}], dtype=object))
    with pytest.raises(FormatError, match=r"x\.npz: not a readable NumPy \.npz archive"):
        _read(read_npz, path)


# --------------------------------------------------------------------------
# Bare .npy.
# --------------------------------------------------------------------------


def test_npy_range_image_takes_the_preset_of_its_grid(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame()
    range_image = original.range.copy()
    holes = ~original.valid
    # Foreign tools mark no return as NaN, Inf, 0 or a negative number.
    marks = np.array([np.nan, np.inf, 0.0, -1.0], np.float32)
    range_image[holes] = marks[np.arange(holes.sum()) % 4]
    np.save(tmp_path / "range.npy", range_image)

    frame = _read(read_npy, tmp_path / "range.npy")
    assert frame.sensor is rs.get_sensor("sr3000")
    np.testing.assert_array_equal(frame.range, original.range)
    np.testing.assert_array_equal(frame.rays, original.rays)
    assert frame.pose is None and frame.timestamp == 0.0


def test_npy_range_image_needs_a_sensor_for_unknown_grids(tmp_path):
    np.save(tmp_path / "odd.npy", np.full((10, 12), 2.0))
    with pytest.raises(FormatError, match=r"odd\.npy: no sensor preset has a \(10, 12\) grid .*pass sensor="):
        _read(read_npy, tmp_path / "odd.npy")
    sensor = rs.SensorModel(
        name="tiny", width=12, height=10, projection=rs.PinholeProjection(20.0, 20.0, 5.5, 4.5),
        min_range=0.1, max_range=5.0, frame_rate=5.0,
    )
    frame = _read(read_npy, tmp_path / "odd.npy", sensor=sensor)
    np.testing.assert_allclose(frame.points[..., 2], 2.0 * sensor.rays()[..., 2])
    with pytest.raises(FormatError, match=r"odd\.npy: sensor 'sr3000' grid \(144, 176\) does not match range image \(10, 12\)"):
        _read(read_npy, tmp_path / "odd.npy", sensor=rs.get_sensor("sr3000"))
    with pytest.raises(FormatError, match=r"odd\.npy: sensor 'unknown' has no projection"):
        _read(read_npy, tmp_path / "odd.npy", sensor=rs.unknown_sensor(10, 12))


def test_npy_point_grid(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame(sensor="kinect")
    points = original.points.astype(np.float64)
    points[0, 0] = [np.inf, 0.0, 1.0]
    expected_valid = original.valid.copy()
    expected_valid[0, 0] = False
    np.save(tmp_path / "points.npy", points)

    frame = _read(read_npy, tmp_path / "points.npy")
    assert frame.sensor.projection is None and frame.sensor.shape == (480, 640)
    np.testing.assert_array_equal(frame.valid, expected_valid)
    np.testing.assert_allclose(frame.points[expected_valid], original.points[expected_valid], rtol=1e-6)

    with_sensor = _read(read_npy, tmp_path / "points.npy", sensor="kinect")  # a preset name will do
    assert with_sensor.sensor.name == "kinect"


def test_bad_npy_files(tmp_path):
    path = tmp_path / "bad.npy"
    np.save(path, np.ones((2, 3, 4)))
    with pytest.raises(FormatError, match=r"bad\.npy: expected a range image \(H, W\) or a point grid \(H, W, 3\), got shape \(2, 3, 4\)"):
        _read(read_npy, path)
    np.save(path, np.array([["a"]]))
    with pytest.raises(FormatError, match=r"bad\.npy: expected a numeric array, got dtype <U1"):
        _read(read_npy, path)
    path.write_bytes(b"")
    with pytest.raises(FormatError, match=r"bad\.npy: empty file"):
        _read(read_npy, path)
    path.write_bytes(b"garbage that is not npy")
    with pytest.raises(FormatError, match=r"bad\.npy: not a readable NumPy \.npy array"):
        _read(read_npy, path)
