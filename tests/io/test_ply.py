"""PLY reader and writer: Stanford bunny range images, generic grids, round trips, bad input."""

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
from rangesurf.io.ply import read_ply, read_stanford_conf, write_ply

BUNNY_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "bunny"
BUNNY_SCANS = ("bun000.ply", "bun045.ply", "bun090.ply", "top2.ply", "chin.ply")
# The virtual Cyberware sensor: p_scan = R^T p_sensor + o.
CYBERWARE_ORIGIN = np.array([0.0, 0.179, 1.327])
CYBERWARE_ROTATION = np.diag([1.0, -1.0, -1.0])

needs_bunny_data = pytest.mark.skipif(
    not (BUNNY_DATA / "bun000.ply").is_file(),
    reason=f"Stanford bunny scans not found at {BUNNY_DATA} (shared test data lives beside the project)",
)


def _read(path, **options) -> rs.RangeFrame:
    frames = list(read_ply(path, **options))
    assert len(frames) == 1
    return frames[0]


@pytest.fixture(scope="module")
def bunny_scans():
    """bun000 and bun045 as read by `read_ply`."""
    if not (BUNNY_DATA / "bun000.ply").is_file():
        pytest.skip(f"Stanford bunny scans not found at {BUNNY_DATA}")
    return _read(BUNNY_DATA / "bun000.ply"), _read(BUNNY_DATA / "bun045.ply")


def _stanford_raw(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) and per-cell vertex index (-1 empty), parsed independently."""
    lines = path.read_text().splitlines()
    header_end = lines.index("end_header") + 1
    count = int(next(line for line in lines if line.startswith("element vertex")).split()[2])
    vertices = np.array([line.split() for line in lines[header_end:header_end + count]], dtype=float)
    cells = np.array([-1 if line.strip() == "0" else int(line.split()[1]) for line in lines[header_end + count:]])
    return vertices, cells


# --------------------------------------------------------------------------
# Stanford bunny.
# --------------------------------------------------------------------------


@needs_bunny_data
def test_bunny_scan_is_a_512_by_400_grid_with_40256_returns(bunny_scans):
    frame = bunny_scans[0]
    assert frame.shape == (400, 512) and frame.sensor.name == "cyberware"
    assert int(frame.valid.sum()) == 40_256
    vertices, cells = _stanford_raw(BUNNY_DATA / "bun000.ply")
    assert len(vertices) == 40_256 and len(cells) == 204_800
    np.testing.assert_array_equal(frame.valid.reshape(-1), cells >= 0)
    # Points are the file's vertices, in the virtual sensor frame.
    in_scan = frame.points.reshape(-1, 3)[cells >= 0].astype(np.float64) @ CYBERWARE_ROTATION + CYBERWARE_ORIGIN
    np.testing.assert_allclose(in_scan, vertices[cells[cells >= 0]], atol=1e-6)
    assert np.nanmin(frame.range) > 1.1 and np.nanmax(frame.range) < 1.6  # the scanner's working range


@needs_bunny_data
def test_bunny_rays_look_from_the_virtual_sensor(bunny_scans):
    frame = bunny_scans[0]
    preset = rs.get_sensor("cyberware").rays()
    angle_deg = np.degrees(np.arccos(np.clip(np.sum(frame.rays * preset, axis=-1), -1, 1)))
    # The preset pinhole approximates the scanner (columns are really
    # parallel); measured: median 0.13 deg, max 0.2 deg on bun000.
    assert np.median(angle_deg[frame.valid]) < 0.2 and angle_deg[frame.valid].max() < 0.5
    np.testing.assert_array_equal(frame.rays[~frame.valid], preset[~frame.valid])
    assert (frame.rays[..., 2] > 0.98).all()  # looking down the boresight


@needs_bunny_data
def test_stanford_conf_parses_as_world_from_scan_transforms():
    poses = read_stanford_conf(BUNNY_DATA / "bun.conf")
    assert sorted(poses) == sorted(BUNNY_SCANS)  # the camera line is not a scan
    np.testing.assert_allclose(poses["bun000.ply"], np.eye(4), atol=1e-12)
    # bmesh bun045.ply -0.0520211 -0.000383981 -0.0109223 0.00548449 -0.294635 -0.0038555 0.955586
    quaternion = [0.00548449, -0.294635, -0.0038555, 0.955586]
    expected_rotation = Rotation.from_quat(quaternion).as_matrix().T  # p_world = R^T p + t
    np.testing.assert_allclose(poses["bun045.ply"][:3, :3], expected_rotation, atol=1e-6)
    np.testing.assert_allclose(poses["bun045.ply"][:3, 3], [-0.0520211, -0.000383981, -0.0109223])


def _gap_to(tree: cKDTree, points: np.ndarray, *, overlap: float = 0.005) -> tuple[float, float, float]:
    """(median gap over the overlap, overlap fraction, median gap over all points).

    The scans see different sides of the bunny, so only points with a
    neighbour in the other scan within ``overlap`` (5 mm, ten scan spacings)
    measure the alignment; the overlap fraction tells a bad alignment apart
    as well.
    """
    gap = tree.query(points)[0]
    inside = gap < overlap
    return float(np.median(gap[inside])), float(inside.mean()), float(np.median(gap))


@needs_bunny_data
def test_conf_poses_put_bun045_onto_bun000(bunny_scans):
    scan0, scan45 = bunny_scans
    np.testing.assert_array_equal(scan45.pose, scan45.reference_pose)
    tree = cKDTree(scan0.world_points(use_reference=True))
    aligned_gap, aligned_overlap, aligned_median = _gap_to(tree, scan45.world_points(use_reference=True))
    # Wrong pose: bun045 placed as if it were taken from where bun000 was.
    wrong = scan45.points[scan45.valid].astype(np.float64) @ scan0.pose[:3, :3].T + scan0.pose[:3, 3]
    wrong_gap, wrong_overlap, wrong_median = _gap_to(tree, wrong)
    # Measured: aligned 0.32 mm over a 96 % overlap (0.33 mm over all points);
    # wrong 2.0 mm over a 17 % overlap (29 mm over all points).
    assert aligned_gap < 0.0005 and aligned_overlap > 0.9 and aligned_median < 0.0005
    assert wrong_overlap < 0.3 and wrong_median > 0.01 and wrong_gap > 3 * aligned_gap


@needs_bunny_data
def test_scan_without_a_conf_has_no_pose_but_the_same_points(bunny_scans, tmp_path):
    shutil.copy(BUNNY_DATA / "bun000.ply", tmp_path / "bun000.ply")
    (tmp_path / "other.conf").write_text("bmesh someone_else.ply 0 0 0 0 0 0 1\n")
    alone = _read(tmp_path / "bun000.ply")
    assert alone.pose is None and alone.reference_pose is None
    np.testing.assert_array_equal(alone.range, bunny_scans[0].range)
    np.testing.assert_array_equal(alone.rays, bunny_scans[0].rays)


@needs_bunny_data
def test_load_reads_the_bunny_folder_with_poses():
    frames = rs.load(BUNNY_DATA)
    assert [Path(f.source).name for f in frames] == ["bun000.ply", "bun045.ply", "bun090.ply", "chin.ply", "top2.ply"]
    assert all(f.pose is not None and f.shape == (400, 512) for f in frames)


# --------------------------------------------------------------------------
# Round trips.
# --------------------------------------------------------------------------


def _transform(rotvec, translation) -> np.ndarray:
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    transform[:3, 3] = translation
    return transform


def _ply_synthetic_frame(sensor: str | rs.SensorModel = "sr3000", *, seed: int = 0) -> rs.RangeFrame:
    """Random ranges on the sensor's rays, NaN holes, intensity, both poses."""
    sensor = rs.get_sensor(sensor)
    rng = np.random.default_rng(seed)
    rays = sensor.rays() if sensor.projection is not None else _fan_rays(sensor.shape)
    range_image = rng.uniform(0.5, 7.0, sensor.shape).astype(np.float32)
    range_image[rng.random(sensor.shape) < 0.1] = np.nan
    range_image[10:20, 30:60] = np.nan
    intensity = rng.random(sensor.shape).astype(np.float32)
    intensity[5, 5] = np.nan
    return rs.RangeFrame(
        rays=rays, range=range_image, sensor=sensor, intensity=intensity,
        pose=_transform([0.2, -0.1, 0.4], [0.5, 1.0, -2.0]),
        reference_pose=_transform([0.21, -0.12, 0.41], [0.52, 0.98, -2.01]), timestamp=123.456,
    )


def _fan_rays(shape) -> np.ndarray:
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    directions = np.stack([(cols - shape[1] / 2) / 100, (rows - shape[0] / 2) / 100, np.ones(shape)], axis=-1)
    return (directions / np.linalg.norm(directions, axis=-1, keepdims=True)).astype(np.float32)


def _assert_round_trip(copy: rs.RangeFrame, original: rs.RangeFrame) -> None:
    np.testing.assert_array_equal(copy.valid, original.valid)
    np.testing.assert_allclose(copy.range, original.range, rtol=1e-6)
    np.testing.assert_allclose(copy.rays[copy.valid], original.rays[original.valid], atol=1e-6)
    assert copy.sensor == original.sensor
    for name in ("pose", "reference_pose"):
        if getattr(original, name) is None:
            assert getattr(copy, name) is None
        else:
            np.testing.assert_array_equal(getattr(copy, name), getattr(original, name))
    assert copy.timestamp == original.timestamp


@pytest.mark.parametrize("sensor", ["sr3000", "kinect", "uos-laser"])
def test_write_ply_round_trips_a_synthetic_frame(tmp_path, sensor):
    frame = _ply_synthetic_frame(sensor)
    write_ply(tmp_path / "frame.ply", frame)
    copy = _read(tmp_path / "frame.ply")
    _assert_round_trip(copy, frame)
    np.testing.assert_array_equal(copy.rays[~copy.valid], frame.rays[~frame.valid])  # from the projection
    np.testing.assert_array_equal(copy.intensity[copy.valid], frame.intensity[frame.valid])
    assert np.isnan(copy.intensity[~copy.valid]).all()


def test_write_ply_writes_a_standard_binary_header(tmp_path):
    frame = _ply_synthetic_frame()
    write_ply(tmp_path / "frame.ply", frame)
    data = (tmp_path / "frame.ply").read_bytes()
    header = data[:data.index(b"end_header\n")].decode().splitlines()
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "comment rangesurf sensor sr3000"]
    valid = int(frame.valid.sum())
    for line in ("obj_info num_cols 176", "obj_info num_rows 144", f"element vertex {valid}",
                 "property float intensity", "element range_grid 25344", "property list uchar int vertex_indices"):
        assert line in header
    body = len(data) - data.index(b"end_header\n") - len(b"end_header\n")
    assert body == valid * 16 + 25344 + 4 * valid


def test_write_ply_round_trips_a_custom_sensor_without_projection(tmp_path):
    sensor = rs.unknown_sensor(30, 40, name="lidar-x")
    frame = _ply_synthetic_frame(sensor).replace(pose=None, intensity=None)
    write_ply(tmp_path / "frame.ply", frame)
    copy = _read(tmp_path / "frame.ply")
    _assert_round_trip(copy, frame)
    assert copy.sensor.name == "lidar-x" and copy.intensity is None


def test_write_ply_round_trips_an_all_invalid_frame(tmp_path):
    sensor = rs.get_sensor("sr3000")
    frame = rs.RangeFrame(rays=sensor.rays(), range=np.full(sensor.shape, np.nan, np.float32), sensor=sensor)
    write_ply(tmp_path / "empty.ply", frame)
    copy = _read(tmp_path / "empty.ply")
    assert not copy.valid.any()
    np.testing.assert_array_equal(copy.rays, sensor.rays())


@needs_bunny_data
def test_write_ply_round_trips_a_bunny_scan(bunny_scans, tmp_path):
    scan = bunny_scans[1]
    write_ply(tmp_path / "bun045.ply", scan)
    _assert_round_trip(_read(tmp_path / "bun045.ply"), scan)


def test_write_ply_is_atomic(tmp_path, monkeypatch):
    target = tmp_path / "frame.ply"
    target.write_bytes(b"old")

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_ply(target, _ply_synthetic_frame())
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["frame.ply"]


# --------------------------------------------------------------------------
# Generic PLY grids.
# --------------------------------------------------------------------------


def _header(fmt: str, *lines: str) -> bytes:
    return ("\n".join(["ply", f"format {fmt} 1.0", *lines, "end_header"]) + "\n").encode()


def test_ascii_grid_without_range_grid_reads_row_major_with_nan_holes(tmp_path):
    points = np.arange(18, dtype=float).reshape(6, 3) + 1.0
    points[4] = np.nan
    body = "\n".join(" ".join(f"{v:g}" for v in p) + f" {i * 10}" for i, p in enumerate(points))
    header = _header("ascii", "comment width 3 height 2", "element vertex 6", "property float x",
                     "property float y", "property float z", "property uchar reflectance",
                     "element face 1", "property list uchar int vertex_indices")
    (tmp_path / "grid.ply").write_bytes(header + body.encode() + b"\n3 0 1 2\n")
    frame = _read(tmp_path / "grid.ply")
    assert frame.shape == (2, 3) and frame.sensor.name == "unknown" and frame.pose is None
    np.testing.assert_array_equal(frame.valid, [[True, True, True], [True, False, True]])
    np.testing.assert_allclose(frame.points[0, 2], points[2], rtol=1e-6)
    np.testing.assert_array_equal(frame.intensity, [[0, 10, 20], [30, 40, 50]])


@pytest.mark.parametrize("order", ["<", ">"])
def test_binary_grid_with_doubles_and_a_leading_mixed_element(tmp_path, order):
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    # A leading element with a scalar and a list: it must be skipped correctly.
    meta = b"".join(
        np.array([kind], order + "u1").tobytes() + np.array([len(values)], order + "u2").tobytes()
        + np.array(values, order + "f4").tobytes()
        for kind, values in ((1, [0.5, 1.5]), (2, []), (3, [2.5]))
    )
    points = np.random.default_rng(2).uniform(1, 2, (12, 3))
    vertices = np.empty(12, dtype=[("x", order + "f8"), ("y", order + "f8"), ("z", order + "f8"), ("intensity", order + "f4")])
    vertices["x"], vertices["y"], vertices["z"] = points.T
    vertices["intensity"] = np.arange(12)
    header = _header(fmt, "obj_info num_cols 4", "obj_info num_rows 3", "element meta 3", "property uchar kind",
                     "property list ushort float values", "element vertex 12", "property double x",
                     "property double y", "property double z", "property float intensity")
    (tmp_path / "grid.ply").write_bytes(header + meta + vertices.tobytes())
    frame = _read(tmp_path / "grid.ply", sensor=rs.unknown_sensor(3, 4))
    np.testing.assert_allclose(frame.points.reshape(-1, 3), points, rtol=1e-6)
    np.testing.assert_array_equal(frame.intensity.reshape(-1), np.arange(12))


def test_big_endian_range_grid(tmp_path):
    points = np.array([[0, 0, 2], [1, 0, 2], [0, 1, 3]], dtype=">f4")
    grid = b"\x00" + b"\x01" + np.array([2], ">i4").tobytes() + b"\x00" + b"\x01" + np.array([0], ">i4").tobytes() \
        + b"\x02" + np.array([1, 2], ">i4").tobytes() + b"\x00"
    header = _header("binary_big_endian", "obj_info num_cols 3", "obj_info num_rows 2", "element vertex 3",
                     "property float x", "property float y", "property float z", "element range_grid 6",
                     "property list uchar int vertex_indices")
    (tmp_path / "grid.ply").write_bytes(header + points.tobytes() + grid)
    frame = _read(tmp_path / "grid.ply")
    np.testing.assert_array_equal(frame.valid, [[False, True, False], [True, True, False]])
    np.testing.assert_allclose(frame.points[0, 1], [0, 1, 3])
    np.testing.assert_allclose(frame.points[1, 1], [1, 0, 2])  # a cell's first vertex


def _tiny_stanford(vertex_lines: list[str], grid_lines: list[str], *, cols: int = 3, rows: int = 2,
                   count: int | None = None, cells: int | None = None) -> bytes:
    header = _header(
        "ascii", "obj_info is_cyberware_data 1", f"obj_info num_cols {cols}", f"obj_info num_rows {rows}",
        f"element vertex {len(vertex_lines) if count is None else count}", "property float x", "property float y",
        "property float z", f"element range_grid {cols * rows if cells is None else cells}",
        "property list uchar int vertex_indices",
    )
    return header + "\n".join(vertex_lines + grid_lines).encode() + b"\n"


TINY_VERTICES = ["0.01 0.02 0.03", "0.02 0.02 0.03", "0.01 0.03 0.04"]
TINY_GRID = ["0", "1 0", "1 1", "0", "1 2", "0"]
TINY_HEADER_LINES = 12


def test_tiny_stanford_file_uses_the_virtual_sensor(tmp_path):
    (tmp_path / "tiny.ply").write_bytes(_tiny_stanford(TINY_VERTICES, TINY_GRID))
    (tmp_path / "tiny.conf").write_text("camera 0 0 0 0 0 0 1\n\nbmesh tiny.ply 1 2 3 0 0 0 1\n")
    frame = _read(tmp_path / "tiny.ply")
    assert frame.sensor.name == "cyberware" and frame.shape == (2, 3)
    np.testing.assert_array_equal(frame.valid, [[False, True, True], [False, True, False]])
    np.testing.assert_allclose(frame.points[0, 1], (np.array([0.01, 0.02, 0.03]) - CYBERWARE_ORIGIN) * [1, -1, -1],
                               atol=1e-7)
    world = frame.world_points()
    np.testing.assert_allclose(world[0], [1.01, 2.02, 3.03], atol=1e-6)


# --------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------


def _error(path: Path, **options) -> str:
    with pytest.raises(rs.FormatError) as error:
        _read(path, **options)
    message = str(error.value)
    assert str(path) in message
    return message


XYZ = ("property float x", "property float y", "property float z")


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (b"", r"empty file; expected a PLY header"),
        (b"\n  \n", r"empty file"),
        (b"OFF\n3 1 0\n", r"line 1: not a PLY file: expected 'ply', got 'OFF'"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\n", r"header: header has no 'end_header' line"),
        (b"ply\nformat utf8 1.0\nend_header\n", r"line 2: expected 'format ascii\|binary_little_endian"),
        (_header("ascii", "element vertex 1", "property float64x x"), r"line 4: expected 'property <type> <name>'"),
        (_header("ascii", "property float x"), r"line 3: property before any element"),
        (_header("ascii", "element vertex many"), r"line 3: expected 'element <name> <count>'"),
        (_header("ascii", "wibble"), r"line 3: unknown header keyword 'wibble'"),
        (b"ply\nelement vertex 0\nend_header\n", r"header has no 'format' line"),
        (_header("ascii", "obj_info num_cols 2", "obj_info num_rows 1", "element face 0"), r"no 'element vertex'"),
        (_header("ascii", "obj_info num_cols 2", "obj_info num_rows 1", "element vertex 2", "property float x",
                 "property float y"), r"line 5: element vertex lacks scalar properties z"),
        (_header("ascii", "element vertex 1", *XYZ) + b"1 2 3\n",
         r"header: no grid size: a PLY must carry its grid size \(obj_info num_cols / num_rows"),
        (_header("ascii", "obj_info num_cols -2", "obj_info num_rows 1", "element vertex 1", *XYZ) + b"1 2 3\n",
         r"line 3: obj_info num_cols must be a positive integer, got '-2'"),
        (_header("ascii", "obj_info num_cols 3", "obj_info num_rows 2", "element vertex 5", *XYZ) + b"1 2 3\n" * 5,
         r"line 5: element vertex has 5 vertices; a grid of 2 rows x 3 columns without a range_grid needs "
         r"one vertex per cell \(6\)"),
        (_header("ascii", "obj_info num_cols 2", "obj_info num_rows 2", "element vertex 4", *XYZ) + b"1 2 3\n" * 3,
         r"line 13: file ends inside element vertex: expected 4 lines of it, found 3"),
        (_header("ascii", "obj_info num_cols 2", "obj_info num_rows 1", "element vertex 2", *XYZ) + b"1 2 3\n1 2\n",
         r"line 11: expected 3 numbers \(x y z\) of element vertex, got '1 2'"),
        (_header("ascii", "obj_info num_cols 2", "obj_info num_rows 1", "element vertex 2", *XYZ) + b"1 2 3\n1 b 3\n",
         r"line 11: expected numbers, got '1 b 3'"),
        (_header("ascii", "obj_info num_cols 2", "obj_info num_rows 1", "element vertex 2", *XYZ) + b"1 2 3\n1 inf 3\n",
         r"line 11: vertex 1 is \[1.0, inf, 3.0\]; expected finite numbers or NaN"),
        (_header("ascii", "obj_info num_cols 1", "obj_info num_rows 1", "element vertex 1", *XYZ) + b"1 2 3\n4 5 6\n",
         r"line 11: more data than the header's elements declare"),
        (_header("binary_little_endian", "obj_info num_cols 2", "obj_info num_rows 2", "element vertex 4", *XYZ)
         + bytes(40), r"element vertex: file is truncated inside element vertex \(4 records of 12 bytes need 48 bytes"),
        (_header("binary_little_endian", "obj_info num_cols 1", "obj_info num_rows 1", "element vertex 1", *XYZ)
         + bytes(14), r"byte \d+: 2 bytes after the last element"),
        (_header("binary_little_endian", "obj_info num_cols 2", "obj_info num_rows 1", "element vertex 1", *XYZ,
                 "element range_grid 2", "property list uchar int vertex_indices") + bytes(12) + b"\x01\x00",
         r"element range_grid: file is truncated inside element range_grid"),
        (_header("binary_little_endian", "obj_info num_cols 2", "obj_info num_rows 1", "element vertex 1", *XYZ,
                 "element range_grid 2", "property list uchar int vertex_indices") + bytes(12) + b"\x00\x01\x07\x00\x00\x00",
         r"element range_grid, record 1: range_grid cell 1 \(row 0, column 1\) refers to vertex 7; expected an index in 0..0"),
        (_header("ascii", "comment rangesurf T_world_sensor 1 0 0", "obj_info num_cols 1", "obj_info num_rows 1",
                 "element vertex 1", *XYZ) + b"1 2 3\n",
         r"line 3: bad 'comment rangesurf T_world_sensor': expected 16 numbers"),
    ],
)
def test_bad_ply_is_a_format_error_naming_the_place(tmp_path, content, expected):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    message = _error(path)
    assert re.search(expected, message), message


@pytest.mark.parametrize(
    ("vertices", "grid", "options", "expected"),
    [
        (TINY_VERTICES, TINY_GRID[:3] + ["1 3"] + TINY_GRID[4:], {},
         rf"line {TINY_HEADER_LINES + 3 + 4}: range_grid cell 3 \(row 1, column 0\) refers to vertex 3; "
         r"expected an index in 0..2"),
        (TINY_VERTICES[:1] + ["0.02 nan 0.03"] + TINY_VERTICES[2:], TINY_GRID, {},
         rf"line {TINY_HEADER_LINES + 2}: vertex 1 is \[0.02, nan, 0.03\]; expected finite numbers \(Stanford range data has no NaN\)"),
        (TINY_VERTICES, TINY_GRID[:2] + ["2 1"] + TINY_GRID[3:], {},
         rf"line {TINY_HEADER_LINES + 3 + 3}: list length 2 does not match the 1 items that follow it"),
        (TINY_VERTICES, TINY_GRID[:2] + [""] + TINY_GRID[3:], {},
         rf"line {TINY_HEADER_LINES + 3 + 3}: expected a list .* got an empty line"),
        (TINY_VERTICES, TINY_GRID[:-1], {"cells": 5}, r"element range_grid has 5 cells; expected num_rows x num_cols = 2 x 3 = 6"),
        (TINY_VERTICES, TINY_GRID, {"count": 4}, r"line \d+: (expected 3 numbers|file ends inside)"),
    ],
    ids=["index-out-of-range", "nan-vertex", "list-length", "empty-cell-line", "cell-count", "vertex-count"],
)
def test_bad_stanford_file_is_a_format_error_naming_the_line(tmp_path, vertices, grid, options, expected):
    path = tmp_path / "tiny.ply"
    path.write_bytes(_tiny_stanford(vertices, grid, **options))
    message = _error(path)
    assert re.search(expected, message), message


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("bmesh tiny.ply 1 2 3 0 0 0\n", "line 1: expected 'bmesh FILE tx ty tz qx qy qz qw'"),
        ("camera 0 0 0 0 0 0 1\nbmesh tiny.ply 1 2 x 0 0 0 1\n", "line 2: expected 7 numbers after the file name"),
        ("bmesh tiny.ply 1 2 3 0 0 0 0\n", "line 1: expected a finite translation and a non-zero quaternion"),
        ("scan tiny.ply 1 2 3 0 0 0 1\n", "line 1: unknown keyword 'scan'"),
    ],
)
def test_bad_conf_is_a_format_error_naming_it(tmp_path, text, expected):
    (tmp_path / "tiny.ply").write_bytes(_tiny_stanford(TINY_VERTICES, TINY_GRID))
    conf = tmp_path / "tiny.conf"
    conf.write_text(text)
    with pytest.raises(rs.FormatError) as error:
        _read(tmp_path / "tiny.ply")
    assert str(conf) in str(error.value) and expected in str(error.value), str(error.value)


def test_sensor_grid_must_match_the_file(tmp_path):
    (tmp_path / "tiny.ply").write_bytes(_tiny_stanford(TINY_VERTICES, TINY_GRID))
    message = _error(tmp_path / "tiny.ply", sensor="cyberware")
    assert "grid 2x3 (rows x columns) does not match sensor 'cyberware' grid 400x512" in message


def test_missing_file_is_a_format_error(tmp_path):
    assert "no such file" in _error(tmp_path / "absent.ply")


# --------------------------------------------------------------------------
# ASCII bodies: mixed elements, unread elements, the per-vertex frame builder.
# --------------------------------------------------------------------------

MIXED_HEADER = _header(
    "ascii", "obj_info num_cols 2", "obj_info num_rows 2", "element meta 3", "property uchar kind",
    "property list ushort float values", "property float weight", "element vertex 4", *XYZ,
    "element face 1", "property list uchar int vertex_indices",
)
MIXED_META = ["1 2 0.5 1.5 9", "2 0 8", "3 1 2.5 7"]
MIXED_VERTICES = ["1 2 3", "4 5 6", "0 0 0", "nan 1 2"]


def test_ascii_mixed_element_before_the_vertices_is_read_and_skipped(tmp_path):
    from rangesurf.io.ply import _parse_header, _read_elements

    data = MIXED_HEADER + "\n".join(MIXED_META + MIXED_VERTICES + ["3 0 1 2"]).encode() + b"\n"
    columns = _read_elements(tmp_path / "m.ply", data, _parse_header(tmp_path / "m.ply", data), {"meta"})
    np.testing.assert_array_equal(columns["meta"]["kind"], [1, 2, 3])
    np.testing.assert_array_equal(columns["meta"]["weight"], [9, 8, 7])
    lengths, items = columns["meta"]["values"]
    np.testing.assert_array_equal(lengths, [2, 0, 1])
    np.testing.assert_array_equal(items, [0.5, 1.5, 2.5])
    (tmp_path / "m.ply").write_bytes(data)
    frame = _read(tmp_path / "m.ply")
    np.testing.assert_array_equal(frame.valid, [[True, True], [False, False]])  # 0 0 0 and NaN: no return
    np.testing.assert_allclose(frame.range[0], [np.sqrt(14), np.sqrt(77)], rtol=1e-6)


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("1 2 0.5 9", "line does not match the properties of element meta: '1 2 0.5 9'"),
        ("1 -1 9", "line does not match the properties of element meta"),
        ("1 1.5 0.5 9", "line does not match the properties of element meta"),
        ("1 nan 0.5 9", "line does not match the properties of element meta"),
        ("", "line does not match the properties of element meta: ''"),
        ("1 x 0.5 1.5 9", "expected numbers, got '1 x 0.5 1.5 9'"),
    ],
)
def test_bad_ascii_mixed_line_names_the_line(tmp_path, line, expected):
    path = tmp_path / "m.ply"
    path.write_bytes(MIXED_HEADER + "\n".join([line] + MIXED_META[1:] + MIXED_VERTICES).encode() + b"\n")
    message = _error(path)
    assert f"line 16: {expected}" in message, message  # 15 header lines


def test_unread_trailing_element_may_hold_anything(tmp_path):
    # Faces after the vertices are not read, so they are not checked either.
    path = tmp_path / "m.ply"
    path.write_bytes(MIXED_HEADER + "\n".join(MIXED_META + MIXED_VERTICES + ["3 0 one 2", "junk"]).encode() + b"\n")
    assert _read(path).shape == (2, 2)


def test_crlf_ascii_body_reads_like_lf(tmp_path):
    lf = _tiny_stanford(TINY_VERTICES, TINY_GRID)
    head, body = lf.split(b"end_header\n")
    (tmp_path / "lf.ply").write_bytes(lf)
    (tmp_path / "crlf.ply").write_bytes(head + b"end_header\n" + body.replace(b"\n", b" \t\r\n"))
    np.testing.assert_array_equal(_read(tmp_path / "crlf.ply").range, _read(tmp_path / "lf.ply").range)


@pytest.mark.parametrize("sensor", ["sr3000", rs.unknown_sensor(144, 176)])
def test_frame_from_cells_is_from_points_bit_for_bit(sensor):
    from rangesurf.io.ply import _frame_from_cells

    sensor = rs.get_sensor(sensor)
    rng = np.random.default_rng(4)
    cells = sensor.height * sensor.width
    vertices = rng.normal(0, 1, (cells // 3, 3)) + [0, 0, 3]
    vertices[::17] = np.nan  # no return
    vertices[5::23] = 0.0  # 0 0 0: no return either
    cell_vertex = np.full(cells, -1)
    chosen = rng.choice(cells, len(vertices), replace=False)
    cell_vertex[chosen] = np.arange(len(vertices))
    points = np.full((cells, 3), np.nan)
    points[chosen] = vertices
    expected = rs.RangeFrame.from_points(points.reshape(*sensor.shape, 3), sensor=sensor, timestamp=2.0)
    frame = _frame_from_cells(vertices, cell_vertex, sensor, timestamp=2.0)
    assert frame.range.tobytes() == expected.range.tobytes()
    assert frame.rays.tobytes() == expected.rays.tobytes()
    assert frame.sensor == expected.sensor and frame.timestamp == 2.0
