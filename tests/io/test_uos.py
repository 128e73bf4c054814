"""3DTK "uos" reader and writer: real scans, alignments, round trips, bad input."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import rangesurf as rs
from rangesurf.io.uos import read_uos, read_uos_frames, read_uos_pose, write_uos

UOS_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "uos-3dtk"
FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])

needs_uos_data = pytest.mark.skipif(
    not (UOS_DATA / "scan000.3d").is_file(),
    reason=f"3DTK example scans not found at {UOS_DATA} (shared test data lives beside the project)",
)


def _read(path, **options) -> rs.RangeFrame:
    frames = list(read_uos(path, **options))
    assert len(frames) == 1
    return frames[0]


@pytest.fixture(scope="module")
def uos_scans():
    """scan000 and scan001 as read by `read_uos`."""
    if not (UOS_DATA / "scan000.3d").is_file():
        pytest.skip(f"3DTK example scans not found at {UOS_DATA}")
    return _read(UOS_DATA / "scan000.3d"), _read(UOS_DATA / "scan001.3d")


def _raw_points_m(path: Path) -> np.ndarray:
    """The file's points in our frame (metres), parsed independently of the reader."""
    raw = np.loadtxt(path, skiprows=1)
    return raw[:, :3] * np.array([0.01, -0.01, 0.01])


# --------------------------------------------------------------------------
# Real scans.
# --------------------------------------------------------------------------


@needs_uos_data
@pytest.mark.parametrize("name", ["scan000", "scan001"])
def test_real_scan_is_a_226_by_360_grid_of_all_its_points(uos_scans, name):
    frame = uos_scans[int(name[-1])]
    raw = _raw_points_m(UOS_DATA / f"{name}.3d")
    assert len(raw) == 81_360
    assert frame.shape == (226, 360) and frame.range.size == 81_360
    assert frame.sensor.name == "uos-laser" and frame.sensor.projection is not None
    assert frame.source == str(UOS_DATA / f"{name}.3d") and frame.timestamp == int(name[-1])

    # Invalid exactly where the scanner had no return: max range or too close.
    distance = np.linalg.norm(raw, axis=1)
    no_return = (distance < 0.2) | (distance >= 32.7)
    np.testing.assert_array_equal(~frame.valid.reshape(-1), no_return)
    assert 2_000 < no_return.sum() < 4_000  # ~1,400 at max range, ~1,800 on the robot
    # Points are kept, in row-major grid order (row = scan line).
    np.testing.assert_allclose(frame.points.reshape(-1, 3)[~no_return], raw[~no_return], atol=2e-6)


@needs_uos_data
def test_real_rays_agree_with_the_preset_projection(uos_scans):
    preset = rs.get_sensor("uos-laser").rays()
    for frame in uos_scans:
        cosine = np.clip(np.sum(frame.rays * preset, axis=-1), -1, 1)
        angle_deg = np.degrees(np.arccos(cosine))
        assert angle_deg[frame.valid].max() < 0.1  # measured: 0.028 deg
        np.testing.assert_array_equal(frame.rays[~frame.valid], preset[~frame.valid])


@needs_uos_data
def test_header_and_headerless_files_load_identically(uos_scans, tmp_path):
    lines = (UOS_DATA / "scan001.3d").read_text().splitlines(keepends=True)
    assert lines[0].strip() == "360 x 225"
    (tmp_path / "scan001.3d").write_text("".join(lines[1:]))
    for suffix in (".pose", ".frames"):
        shutil.copy(UOS_DATA / f"scan001{suffix}", tmp_path / f"scan001{suffix}")
    with_header, headerless = uos_scans[1], _read(tmp_path / "scan001.3d")
    np.testing.assert_array_equal(headerless.range, with_header.range)
    np.testing.assert_array_equal(headerless.rays, with_header.rays)
    np.testing.assert_array_equal(headerless.pose, with_header.pose)
    np.testing.assert_array_equal(headerless.reference_pose, with_header.reference_pose)


@needs_uos_data
def test_pose_file_converts_to_our_frames():
    # scan001.pose: "-3.10605 -7.50803 156.917" (cm) / "1.35694 -0.852409 -0.56224" (deg)
    pose = read_uos_pose(UOS_DATA / "scan001.pose")
    in_3dtk = np.eye(4)
    in_3dtk[:3, :3] = Rotation.from_euler("XYZ", [1.35694, -0.852409, -0.56224], degrees=True).as_matrix()
    in_3dtk[:3, 3] = [-3.10605, -7.50803, 156.917]
    expected = FLIP_Y @ in_3dtk @ FLIP_Y
    expected[:3, 3] /= 100
    np.testing.assert_allclose(pose, expected, atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], [-0.0310605, 0.0750803, 1.56917])
    np.testing.assert_allclose(read_uos_pose(UOS_DATA / "scan000.pose"), np.eye(4), atol=1e-12)


@needs_uos_data
def test_frames_file_keeps_every_step_and_the_last_is_the_reference(uos_scans):
    steps = read_uos_frames(UOS_DATA / "scan001.frames")
    assert steps.shape == (3, 4, 4)
    last_line = (UOS_DATA / "scan001.frames").read_text().split("\n")[2].split()
    column_major = np.array(last_line[:16], dtype=float).reshape(4, 4).T
    expected = FLIP_Y @ column_major @ FLIP_Y
    expected[:3, 3] /= 100
    np.testing.assert_allclose(steps[-1], expected, atol=1e-5)
    np.testing.assert_allclose(steps[-1][:3, 3], [-0.036331, 0.0908315, 1.56796])
    np.testing.assert_array_equal(uos_scans[1].reference_pose, steps[-1])


def _beyond_robot(frame: rs.RangeFrame, transform: np.ndarray, *, far: float = np.inf) -> np.ndarray:
    keep = frame.valid & (frame.range >= 1.0) & (frame.range <= far)  # closer returns hit the robot
    points = frame.points[keep].astype(np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


@needs_uos_data
def test_reference_pose_brings_scan001_onto_scan000(uos_scans):
    scan0, scan1 = uos_scans
    tree = cKDTree(_beyond_robot(scan0, scan0.reference_pose))
    gap = {
        name: np.median(tree.query(_beyond_robot(scan1, transform))[0])
        for name, transform in (("identity", np.eye(4)), ("odometry", scan1.pose), ("reference", scan1.reference_pose))
    }
    # Measured: identity 10.8 cm, odometry 2.9 cm, reference 2.8 cm (median
    # nearest-neighbour gap, returns closer than 1 m excluded). It is bounded
    # below by the 0.5 deg sampling (~9 cm apart at 10 m), hence the loose bounds.
    assert gap["reference"] < 0.035
    assert gap["odometry"] < 0.035
    assert gap["identity"] > 0.08


@needs_uos_data
def test_point_to_plane_residual_ranks_reference_odometry_identity(uos_scans):
    scan0, scan1 = uos_scans
    target = _beyond_robot(scan0, np.eye(4), far=15.0)
    tree = cKDTree(target)
    _, neighbours = tree.query(target, k=10)
    patches = target[neighbours]
    centroids = patches.mean(axis=1)
    centred = patches - centroids[:, None]
    eigenvalues, eigenvectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    normals = eigenvectors[:, :, 0]
    planar = eigenvalues[:, 0] < 0.05 * eigenvalues[:, 1]

    def residual(transform):
        source = _beyond_robot(scan1, transform, far=15.0)
        distance, nearest = tree.query(source)
        use = planar[nearest] & (distance < 0.5)
        offsets = np.sum((source - centroids[nearest]) * normals[nearest], axis=1)
        return np.median(np.abs(offsets[use]))

    identity, odometry, reference = residual(np.eye(4)), residual(scan1.pose), residual(scan1.reference_pose)
    # Measured: identity 3.5 cm, odometry 1.64 cm, reference 1.42 cm
    # (data README: 2.9 / 1.6 / 1.4 cm with its own neighbourhood choice).
    assert reference < odometry < identity
    assert reference < 0.016
    assert odometry < 0.019
    assert identity > 0.025


# --------------------------------------------------------------------------
# Round trips.
# --------------------------------------------------------------------------


def _transform(rotvec, translation) -> np.ndarray:
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    transform[:3, 3] = translation
    return transform


def _uos_synthetic_frame(sensor_name: str = "uos-laser", *, seed: int = 0, intensity: bool = True) -> rs.RangeFrame:
    """A frame of random ranges on the preset's rays, with NaN holes."""
    sensor = rs.get_sensor(sensor_name)
    rng = np.random.default_rng(seed)
    low, high = max(sensor.min_range, 0.5) + 0.1, min(sensor.max_range, 20.0) - 0.1
    range_image = rng.uniform(low, high, sensor.shape).astype(np.float32)
    range_image[rng.random(sensor.shape) < 0.1] = np.nan
    range_image[:3] = np.nan  # a whole scan line without returns
    values = rng.random(sensor.shape).astype(np.float32) if intensity else None
    return rs.RangeFrame(
        rays=sensor.rays(), range=range_image, sensor=sensor, intensity=values,
        pose=_transform([0.1, -0.4, 0.25], [1.5, -0.2, 3.0]),
        reference_pose=_transform([0.12, -0.38, 0.2], [1.45, -0.25, 3.1]),
        timestamp=5.0,
    )


def _assert_same_frame(copy: rs.RangeFrame, original: rs.RangeFrame) -> None:
    np.testing.assert_array_equal(copy.valid, original.valid)
    np.testing.assert_allclose(copy.range, original.range, rtol=0, atol=5e-6)  # 1e-4 cm in the file
    np.testing.assert_allclose(copy.rays, original.rays, atol=1e-5)  # 1e-6 m over ranges >= 0.2 m
    assert copy.sensor == original.sensor


def test_write_uos_round_trips_a_synthetic_frame(tmp_path):
    frame = _uos_synthetic_frame()
    write_uos(tmp_path / "scan005.3d", frame)
    first_line = (tmp_path / "scan005.3d").read_text().split("\n", 1)[0]
    assert len(first_line.split()) == 4  # no header for 360-wide grids; intensity column
    copy = _read(tmp_path / "scan005.3d")
    _assert_same_frame(copy, frame)
    np.testing.assert_allclose(copy.intensity, frame.intensity, rtol=1e-6)
    np.testing.assert_allclose(copy.pose, frame.pose, atol=1e-9)
    np.testing.assert_allclose(copy.reference_pose, frame.reference_pose, atol=1e-12)
    assert copy.timestamp == 5.0  # from the file name


def test_write_uos_writes_3dtk_coordinates(tmp_path):
    sensor = rs.get_sensor("uos-laser")
    range_image = np.full(sensor.shape, np.nan, np.float32)
    range_image[100, 180] = 2.0  # fan angle 90 deg: straight ahead, tilted by the row
    frame = rs.RangeFrame(rays=sensor.rays(), range=range_image, sensor=sensor, pose=_transform([0, 0, 0], [0.1, 0.2, 0.3]))
    write_uos(tmp_path / "scan000.3d", frame)
    lines = (tmp_path / "scan000.3d").read_text().splitlines()
    assert len(lines) == 81_360
    assert lines[0].split() == ["0.0000", "0.0000", "0.0000"]
    x, y, z = map(float, lines[100 * 360 + 180].split())
    expected = frame.points[100, 180] * np.array([100, -100, 100])  # y up, centimetres
    np.testing.assert_allclose([x, y, z], expected, atol=1e-4)
    assert y > 0  # row 100 looks up (tilt > 0): up is +y in 3DTK
    assert (tmp_path / "scan000.pose").read_text().split() == ["10", "-20", "30", "0", "0", "0"]
    assert not (tmp_path / "scan000.frames").exists()


@needs_uos_data
def test_write_uos_round_trips_a_real_scan(uos_scans, tmp_path):
    scan = uos_scans[1]
    write_uos(tmp_path / "scan001.3d", scan)
    copy = _read(tmp_path / "scan001.3d")
    _assert_same_frame(copy, scan)
    assert copy.intensity is None
    np.testing.assert_allclose(copy.pose, scan.pose, atol=1e-9)
    np.testing.assert_allclose(copy.reference_pose, scan.reference_pose, atol=1e-12)


def test_write_uos_round_trips_other_grids_with_a_header(tmp_path):
    frame = _uos_synthetic_frame("sr3000", seed=3, intensity=False)
    write_uos(tmp_path / "cam.3d", frame)
    assert (tmp_path / "cam.3d").read_text().split("\n", 1)[0] == "176 x 144"
    _assert_same_frame(_read(tmp_path / "cam.3d", sensor="sr3000"), frame)
    inferred = _read(tmp_path / "cam.3d")  # no sensor given: rays from the points
    assert inferred.shape == (144, 176) and inferred.sensor.name == "unknown"
    np.testing.assert_array_equal(inferred.valid, frame.valid)
    np.testing.assert_allclose(inferred.range, frame.range, atol=5e-6)


def test_write_uos_handles_gimbal_lock_and_removes_stale_companions(tmp_path):
    frame = _uos_synthetic_frame(intensity=False)
    locked = frame.replace(pose=_transform([0, np.pi / 2, 0], [0, 0, 0]) @ _transform([0.3, 0, 0], [0, 0, 0]))
    write_uos(tmp_path / "scan001.3d", locked)
    np.testing.assert_allclose(_read(tmp_path / "scan001.3d").pose, locked.pose, atol=1e-9)
    write_uos(tmp_path / "scan001.3d", frame.replace(pose=None, reference_pose=None))
    assert not (tmp_path / "scan001.pose").exists() and not (tmp_path / "scan001.frames").exists()
    copy = _read(tmp_path / "scan001.3d")
    assert copy.pose is None and copy.reference_pose is None


def test_other_grids_keep_far_returns_unless_the_sensor_cuts_them(tmp_path):
    lines = ["2 x 2", "0 0 0", "100 0 5000", "0 10 15", "0 0 3276.7"]  # cm; 50 m is a real return elsewhere
    frame = _read(_write_lines(tmp_path / "far.3d", lines))
    np.testing.assert_allclose(frame.range, [[np.nan, 50.01], [0.18027756, 32.767]], rtol=1e-6)
    cut = _read(tmp_path / "far.3d", sensor=rs.get_sensor("uos-laser").with_grid(2, 2))
    np.testing.assert_array_equal(cut.valid, [[False, False], [False, False]])


def test_all_invalid_frame_round_trips(tmp_path):
    sensor = rs.get_sensor("uos-laser")
    frame = rs.RangeFrame(rays=sensor.rays(), range=np.full(sensor.shape, np.nan, np.float32), sensor=sensor)
    write_uos(tmp_path / "scan000.3d", frame)
    copy = _read(tmp_path / "scan000.3d")
    assert not copy.valid.any()
    np.testing.assert_array_equal(copy.rays, sensor.rays())


def test_write_uos_is_atomic(tmp_path, monkeypatch):
    target = tmp_path / "scan000.3d"
    target.write_text("old\n")

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)  # the last step of every atomic write
    with pytest.raises(OSError, match="disk full"):
        write_uos(target, _uos_synthetic_frame())
    assert target.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan000.3d"]  # no temporary files left


# --------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------


def _scan_text(lines: int = 720, *, header: bool = True) -> list[str]:
    rng = np.random.default_rng(1)
    points = rng.uniform(100, 500, (lines, 3))
    return (["360 x 1"] if header else []) + [f"{x:.3f} {y:.3f} {z:.3f}" for x, y, z in points]


def _write_lines(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def _error(path: Path, **options) -> str:
    with pytest.raises(rs.FormatError) as error:
        _read(path, **options)
    message = str(error.value)
    assert str(path) in message
    return message


def test_small_valid_file_reads_as_two_lines(tmp_path):
    frame = _read(_write_lines(tmp_path / "scan000.3d", _scan_text()))
    assert frame.shape == (2, 360) and frame.valid.all() and frame.pose is None


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda lines: lines[:0], r"empty file; expected lines of 'x y z'"),
        (lambda lines: lines[:1], r"no points after the header"),
        (lambda lines: lines[:5] + ["1.0 abc 3.0"] + lines[6:], r"line 6: expected numbers, got 'abc'"),
        (lambda lines: lines[:9] + ["1.0 2.0"] + lines[10:], r"line 10: expected 3 numbers like the first point line \(line 2\), got 2"),
        (lambda lines: lines[:4] + ["1 2 3 4"] + lines[5:], r"line 5: expected 3 numbers .* got 4"),
        (lambda lines: lines[:1] + ["1 2"] + lines[2:], r"line 2: expected 3 numbers \(x y z\) or more, got 2"),
        (lambda lines: lines[:7] + ["1.0 nan 3.0"] + lines[8:], r"line 8: coordinates must be finite"),
        (lambda lines: lines[:7] + ["1.0 2.0 inf"] + lines[8:], r"line 8: coordinates must be finite"),
        (lambda lines: lines[:-1], r"719 points is not a multiple of the header's width 360"),
        (lambda lines: ["0 x 0"] + lines[1:], r"line 1: header grid width must be positive"),
    ],
    ids=["empty", "header-only", "non-numeric", "short-line", "long-line", "too-few-columns", "nan", "inf",
         "partial-line", "zero-width"],
)
def test_bad_3d_file_is_a_format_error_naming_the_line(tmp_path, edit, expected):
    message = _error(_write_lines(tmp_path / "scan000.3d", edit(_scan_text())))
    assert re.search(expected, message), message


def test_line_numbers_count_blank_lines_and_headerless_files(tmp_path):
    lines = _scan_text(header=False)
    lines = lines[:3] + [""] + lines[3:10] + ["1 2 x"] + lines[11:]
    message = _error(_write_lines(tmp_path / "scan000.3d", lines))
    assert "line 12: expected numbers, got 'x'" in message


def test_headerless_count_must_fill_whole_lines(tmp_path):
    message = _error(_write_lines(tmp_path / "scan000.3d", _scan_text(700, header=False)))
    assert "700 points is not a multiple of the grid width 360" in message


def test_sensor_grid_must_match_the_file(tmp_path):
    path = _write_lines(tmp_path / "scan000.3d", _scan_text())
    assert "grid 2x360 (rows x columns) does not match sensor 'uos-laser' grid 226x360" in _error(path, sensor="uos-laser")


@pytest.mark.parametrize(
    ("suffix", "text", "expected"),
    [
        (".pose", "1 2 3\n", "expected 2 lines"),
        (".pose", "1 2 3\n4 5\n", "line 2: expected 3 finite numbers"),
        (".pose", "1 2 3\n4 five 6\n", "line 2: expected numbers, got '4 five 6'"),
        (".pose", "1 2 nan\n4 5 6\n", "line 1: expected 3 finite numbers"),
        (".frames", "", "empty .frames file"),
        (".frames", "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 2\n1 0 0 0 0 1 0 0 0 0 1 0 0 1 2\n", "line 2: expected 16 numbers"),
        (".frames", "2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 2\n", "line 1: matrix rotation part is not a proper rotation"),
        (".frames", "1 0 0 0 0 1 0 0 0 0 1 0 5 5 5 0 2\n", "line 1: matrix last row must be 0 0 0 1"),
    ],
)
def test_bad_companion_file_is_a_format_error_naming_it(tmp_path, suffix, text, expected):
    scan = _write_lines(tmp_path / "scan000.3d", _scan_text())
    companion = tmp_path / f"scan000{suffix}"
    companion.write_text(text)
    with pytest.raises(rs.FormatError) as error:
        _read(scan)
    assert str(companion) in str(error.value) and expected in str(error.value), str(error.value)


def test_missing_file_is_a_format_error(tmp_path):
    assert "no such file" in _error(tmp_path / "scan404.3d")


def test_reflectance_column_becomes_intensity(tmp_path):
    lines = [line + f" {index % 7}" for index, line in enumerate(_scan_text(header=False))]
    lines[0] = "0 0 0 nan"  # no return, reflectance unknown
    frame = _read(_write_lines(tmp_path / "scan3.3d", lines))
    assert frame.intensity is not None and np.isnan(frame.intensity[0, 0]) and not frame.valid[0, 0]
    assert frame.intensity[1, 5] == (365 % 7) and frame.timestamp == 3.0


def test_crlf_tabs_and_blank_lines_read_like_plain_lines(tmp_path):
    lines = _scan_text()
    plain = _read(_write_lines(tmp_path / "scan000.3d", lines))
    messy = [lines[0]] + ["\t" + line.replace(" ", " \t") + "  " for line in lines[1:]]
    messy.insert(100, "")
    (tmp_path / "scan001.3d").write_bytes(("\r\n".join(messy) + "\r\n\r\n").encode())
    copy = _read(tmp_path / "scan001.3d")
    np.testing.assert_array_equal(copy.range, plain.range)
    np.testing.assert_array_equal(copy.rays, plain.rays)


def test_bad_token_line_counts_crlf_lines(tmp_path):
    lines = _scan_text(header=False)
    lines[6] = "1.0 2.0 3,0"
    (tmp_path / "scan000.3d").write_bytes(("\r\n".join(lines) + "\r\n").encode())
    assert "line 7: expected numbers, got '3,0' in '1.0 2.0 3,0'" in _error(tmp_path / "scan000.3d")
