"""PCD reader and writer: round trips, binary_compressed, foreign layouts, bad files."""

from __future__ import annotations

import numpy as np
import pytest

import rangesurf as rs
from rangesurf.io import FormatError
from rangesurf.io.pcd import _lzf_decompress, read_pcd, write_pcd


def _read(path, **options):
    frames = list(read_pcd(path, **options))
    assert len(frames) == 1
    return frames[0]


def _assert_same_geometry(copy, original, *, atol=2e-6):
    np.testing.assert_array_equal(np.isnan(copy.range), np.isnan(original.range))
    valid = original.valid
    np.testing.assert_allclose(copy.points[valid], original.points[valid], atol=atol)
    np.testing.assert_allclose(copy.range[valid], original.range[valid], rtol=1e-6)


def _header(fields, sizes, types, counts, width, height, data, *, points=None, viewpoint="0 0 0 1 0 0 0"):
    lines = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        f"FIELDS {' '.join(fields)}",
        f"SIZE {' '.join(map(str, sizes))}",
        f"TYPE {' '.join(types)}",
        f"COUNT {' '.join(map(str, counts))}",
        f"WIDTH {width}",
        f"HEIGHT {height}",
        f"VIEWPOINT {viewpoint}",
        f"POINTS {width * height if points is None else points}",
        f"DATA {data}",
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


# --------------------------------------------------------------------------
# Round trips.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
@pytest.mark.parametrize("sensor_name", ["sr3000", "uos-laser"])
def test_round_trip_keeps_points_intensity_pose_sensor_and_time(tmp_path, fmt_plane_frame, binary, sensor_name):
    original = fmt_plane_frame(sensor_name)
    path = tmp_path / "scan.pcd"
    write_pcd(path, original, binary=binary)
    copy = _read(path)

    _assert_same_geometry(copy, original)
    # Rays of cells with a return come from the points: the same unit rays.
    np.testing.assert_allclose(copy.rays[original.valid], original.rays[original.valid], atol=1e-6)
    np.testing.assert_array_equal(copy.intensity, original.intensity)
    np.testing.assert_allclose(copy.pose, original.pose, atol=1e-12)
    assert copy.sensor == original.sensor
    assert copy.timestamp == original.timestamp
    assert copy.reference_pose is None  # not stored in PCD
    assert copy.source == str(path)
    assert (b"DATA binary" if binary else b"DATA ascii") in path.read_bytes()[:1000]


def test_frame_without_pose_or_intensity_writes_identity_viewpoint(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame(intensity=False, pose=False)
    path = tmp_path / "scan.pcd"
    write_pcd(path, original)
    assert b"VIEWPOINT 0.0 0.0 0.0 1.0 0.0 0.0 0.0\n" in path.read_bytes()
    assert b"FIELDS x y z\n" in path.read_bytes()
    copy = _read(path)
    assert copy.pose is None
    assert copy.intensity is None
    _assert_same_geometry(copy, original)


@pytest.mark.parametrize("angle", [0.0, np.pi, np.pi - 1e-9, 2.5])
def test_viewpoint_quaternion_round_trips_rotations_near_half_turn(tmp_path, fmt_plane_frame, fmt_transform, angle):
    pose = fmt_transform([0.3, -1, 0.2], angle, [0.0, 0.0, 1.0])
    original = fmt_plane_frame().replace(pose=pose)
    write_pcd(tmp_path / "scan.pcd", original)
    np.testing.assert_allclose(_read(tmp_path / "scan.pcd").pose, pose, atol=1e-12)


def test_nan_cells_written_as_nan(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame(intensity=False)
    write_pcd(tmp_path / "scan.pcd", original, binary=False)
    lines = (tmp_path / "scan.pcd").read_text().splitlines()
    data = lines[lines.index("DATA ascii") + 1:]
    assert len(data) == original.range.size
    row, col = np.argwhere(~original.valid)[0]
    assert data[row * original.shape[1] + col] == "nan nan nan"


def test_custom_sensor_name_becomes_unknown_sensor_of_that_name(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame()
    custom = rs.SensorModel(
        name="my-tof", width=original.sensor.width, height=original.sensor.height,
        projection=original.sensor.projection, min_range=0.1, max_range=5.0, frame_rate=10.0,
    )
    write_pcd(tmp_path / "scan.pcd", original.replace(sensor=custom))
    copy = _read(tmp_path / "scan.pcd")
    assert copy.sensor.name == "my-tof"
    assert copy.sensor.projection is None
    _assert_same_geometry(copy, original)
    # The caller can supply the model the file cannot carry.
    assert _read(tmp_path / "scan.pcd", sensor=custom).sensor is custom


def test_sensor_of_other_grid_is_rejected(tmp_path, fmt_plane_frame):
    write_pcd(tmp_path / "scan.pcd", fmt_plane_frame())
    with pytest.raises(FormatError, match=r"scan\.pcd.*kinect.*\(480, 640\).*\(144, 176\)"):
        _read(tmp_path / "scan.pcd", sensor=rs.get_sensor("kinect"))


def test_save_and_load_dispatch_to_pcd(tmp_path, fmt_plane_frame):
    original = fmt_plane_frame()
    rs.save(tmp_path / "scan.pcd", original)
    (copy,) = rs.load(tmp_path / "scan.pcd")
    _assert_same_geometry(copy, original)


# --------------------------------------------------------------------------
# Layouts written by other tools.
# --------------------------------------------------------------------------


def _known_grid(height=5, width=7):
    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, (height, width, 3))
    points[..., 2] = rng.uniform(1, 3, (height, width))
    points[1, 2] = np.nan
    points[3, 0, 1] = np.nan  # one NaN coordinate is enough for no return
    intensity = rng.integers(0, 4000, (height, width)).astype(np.uint16)
    return points, intensity


def test_binary_extra_fields_float64_and_integer_intensity_are_read_by_offset(tmp_path):
    points, intensity = _known_grid()
    height, width = points.shape[:2]
    record = np.dtype([
        ("rgb", "<u4"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("_", "u1", (3,)),
        ("normal", "<f4", (3,)), ("intensity", "<u2"),
    ])
    table = np.zeros(height * width, record)
    table["rgb"] = 0xFF8000
    table["x"], table["y"], table["z"] = (points[..., axis].ravel() for axis in range(3))
    table["normal"] = [0.0, 0.0, -1.0]
    table["intensity"] = intensity.ravel()
    header = _header(
        ["rgb", "x", "y", "z", "_", "normal_x", "intensity"], [4, 8, 8, 8, 1, 4, 2],
        ["U", "F", "F", "F", "U", "F", "U"], [1, 1, 1, 1, 3, 3, 1], width, height, "binary",
    )
    path = tmp_path / "foreign.pcd"
    path.write_bytes(header + table.tobytes())

    frame = _read(path)
    valid = np.isfinite(points).all(axis=-1)
    np.testing.assert_array_equal(frame.valid, valid)
    np.testing.assert_allclose(frame.points[valid], points[valid], rtol=1e-6)
    np.testing.assert_array_equal(frame.intensity, intensity.astype(np.float32))
    assert frame.pose is None
    assert frame.sensor.name == "unknown"


def test_ascii_with_extra_fields_and_counts(tmp_path):
    points, intensity = _known_grid()
    height, width = points.shape[:2]
    lines = [
        f"{p[0]:.17g} {p[1]:.17g} {p[2]:.17g} 4.2108e+06 0.1 0.2 0.3 {i}"
        for p, i in zip(points.reshape(-1, 3), intensity.ravel())
    ]
    header = _header(
        ["x", "y", "z", "rgb", "normal", "intensity"], [4, 4, 4, 4, 4, 2], ["F", "F", "F", "F", "F", "U"],
        [1, 1, 1, 1, 3, 1], width, height, "ascii", viewpoint="1 2 3 0 0 0 1",
    )
    path = tmp_path / "foreign.pcd"
    path.write_bytes(header + "\n".join(lines).encode() + b"\n")

    frame = _read(path)
    valid = np.isfinite(points).all(axis=-1)
    np.testing.assert_allclose(frame.points[valid], points[valid], rtol=1e-6)
    np.testing.assert_array_equal(frame.intensity, intensity.astype(np.float32))
    # VIEWPOINT qw=0, qz=1: half turn about z, then the translation.
    np.testing.assert_allclose(frame.pose, [[-1, 0, 0, 1], [0, -1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], atol=1e-12)


# --------------------------------------------------------------------------
# binary_compressed (LZF).
# --------------------------------------------------------------------------


def _lzf_literals(data: bytes) -> bytes:
    """LZF made of literal runs only: valid, if no smaller."""
    out = bytearray()
    for start in range(0, len(data), 32):
        chunk = data[start:start + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def _lzf_compress(data: bytes) -> bytes:
    """A small greedy LZF compressor (3-byte hash of the last position)."""
    out = bytearray()
    literal = bytearray()
    last_seen: dict[bytes, int] = {}

    def flush():
        for start in range(0, len(literal), 32):
            chunk = literal[start:start + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        literal.clear()

    position = 0
    while position < len(data):
        key = data[position:position + 3]
        candidate = last_seen.get(key) if len(key) == 3 else None
        last_seen[key] = position
        if candidate is not None and 0 < position - candidate <= 8192:
            length = 0
            while position + length < len(data) and length < 264 and data[candidate + length] == data[position + length]:
                length += 1
            if length >= 3:
                flush()
                distance = position - candidate - 1
                stored = length - 2
                if stored < 7:
                    out.append((stored << 5) | (distance >> 8))
                else:
                    out.append((7 << 5) | (distance >> 8))
                    out.append(stored - 7)
                out.append(distance & 0xFF)
                position += length
                continue
        literal.append(data[position])
        position += 1
    flush()
    return bytes(out)


def test_lzf_decompress_handles_overlapping_back_references():
    # "ab" then a back reference 2 bytes back, 7 long: the pattern repeats.
    stream = bytes([1]) + b"ab" + bytes([(5 << 5) | 0, 1])
    assert _lzf_decompress(stream, 9) == b"ababababa"
    data = bytes(range(50)) * 40 + b"\x00" * 1000
    assert _lzf_decompress(_lzf_compress(data), len(data)) == data
    assert len(_lzf_compress(data)) < len(data) / 5


@pytest.mark.parametrize("compressor", [_lzf_literals, _lzf_compress], ids=["literal-runs", "greedy"])
def test_binary_compressed_field_major_layout_with_padding(tmp_path, compressor):
    points, intensity = _known_grid(6, 9)
    height, width = points.shape[:2]
    count = height * width
    # Compressed data is field by field; PCL leaves the "_" padding field out.
    blocks = [
        points[..., 0].astype("<f4").tobytes(), points[..., 1].astype("<f4").tobytes(),
        points[..., 2].astype("<f4").tobytes(),
        np.full((count, 2), 7.0, "<f4").tobytes(),
        intensity.astype("<u2").tobytes(),
    ]
    payload = b"".join(blocks)
    compressed = compressor(payload)
    header = _header(
        ["x", "y", "z", "_", "curvature", "intensity"], [4, 4, 4, 1, 4, 2], ["F", "F", "F", "U", "F", "U"],
        [1, 1, 1, 4, 2, 1], width, height, "binary_compressed",
    )
    path = tmp_path / "compressed.pcd"
    path.write_bytes(header + np.array([len(compressed), len(payload)], "<u4").tobytes() + compressed)

    frame = _read(path)
    valid = np.isfinite(points).all(axis=-1)
    np.testing.assert_array_equal(frame.valid, valid)
    np.testing.assert_allclose(frame.points[valid], points[valid].astype(np.float32), rtol=1e-6)
    np.testing.assert_array_equal(frame.intensity, intensity.astype(np.float32))


def test_binary_compressed_corrupt_stream_is_reported(tmp_path):
    points, _ = _known_grid()
    payload = points.astype("<f4").transpose(2, 0, 1).tobytes()
    compressed = bytearray(_lzf_literals(payload))
    compressed[0] = 0xE0  # a back reference before the start of the output
    header = _header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], [1, 1, 1], 7, 5, "binary_compressed")
    path = tmp_path / "corrupt.pcd"
    path.write_bytes(header + np.array([len(compressed), len(payload)], "<u4").tobytes() + bytes(compressed))
    with pytest.raises(FormatError, match=r"corrupt\.pcd, DATA: binary_compressed: corrupt LZF"):
        _read(path)


# --------------------------------------------------------------------------
# Bad files.
# --------------------------------------------------------------------------


@pytest.fixture
def good_binary(tmp_path, fmt_plane_frame):
    path = tmp_path / "good.pcd"
    write_pcd(path, fmt_plane_frame(intensity=False, pose=False))
    return path.read_bytes()


def _replace_line(raw: bytes, old: bytes, new: bytes) -> bytes:
    assert old in raw
    return raw.replace(old, new, 1)


def test_truncated_binary_data(tmp_path, good_binary):
    path = tmp_path / "cut.pcd"
    path.write_bytes(good_binary[:-100])
    with pytest.raises(FormatError, match=r"cut\.pcd, DATA: binary data truncated: expected 304128 bytes"):
        _read(path)


def test_truncated_ascii_data(tmp_path, fmt_plane_frame):
    path = tmp_path / "cut.pcd"
    write_pcd(path, fmt_plane_frame(), binary=False)
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:-3]) + "\n")
    with pytest.raises(FormatError, match=r"cut\.pcd, DATA: ascii data truncated: expected 25344 points"):
        _read(path)


def test_ascii_bad_line_is_named(tmp_path):
    header = _header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], [1, 1, 1], 2, 2, "ascii")
    path = tmp_path / "bad.pcd"
    path.write_bytes(header + b"1 2 3\n1 2 3\n1 2\n1 2 3\n")
    with pytest.raises(FormatError, match=r"bad\.pcd, line 14: expected 3 values per point, got 2"):
        _read(path)
    path.write_bytes(header + b"1 2 3\n1 2 3\n1 2 x\n1 2 3\n")
    with pytest.raises(FormatError, match=r"bad\.pcd, line 14: expected numbers, got 'x'"):
        _read(path)


def test_missing_width(tmp_path, good_binary):
    path = tmp_path / "nowidth.pcd"
    path.write_bytes(_replace_line(good_binary, b"WIDTH 176\n", b""))
    with pytest.raises(FormatError, match=r"nowidth\.pcd, field 'WIDTH': missing WIDTH header line"):
        _read(path)


def test_points_not_width_times_height(tmp_path, good_binary):
    path = tmp_path / "points.pcd"
    path.write_bytes(_replace_line(good_binary, b"POINTS 25344\n", b"POINTS 25000\n"))
    with pytest.raises(FormatError, match=r"points\.pcd, line 12, field 'POINTS': POINTS 25000 does not equal WIDTH \* HEIGHT"):
        _read(path)


def test_unknown_data_kind(tmp_path, good_binary):
    path = tmp_path / "kind.pcd"
    path.write_bytes(_replace_line(good_binary, b"DATA binary\n", b"DATA binary_lz4\n"))
    with pytest.raises(FormatError, match=r"kind\.pcd, line 13, field 'DATA': unknown DATA kind 'binary_lz4'"):
        _read(path)


def test_unorganized_cloud_is_refused(tmp_path):
    header = _header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], [1, 1, 1], 4, 1, "ascii")
    path = tmp_path / "flat.pcd"
    path.write_bytes(header + b"1 2 3\n" * 4)
    with pytest.raises(FormatError, match=r"flat\.pcd, line 8, field 'HEIGHT': unorganized cloud .*organized cloud \(HEIGHT > 1\)"):
        _read(path)


def test_missing_xyz_and_bad_types(tmp_path):
    path = tmp_path / "fields.pcd"
    path.write_bytes(_header(["x", "y", "rgb"], [4, 4, 4], ["F", "F", "U"], [1, 1, 1], 2, 2, "ascii") + b"0 0 0\n" * 4)
    with pytest.raises(FormatError, match=r"fields\.pcd, line 3, field 'FIELDS': needs fields x, y and z; missing z"):
        _read(path)
    path.write_bytes(_header(["x", "y", "z"], [4, 4, 2], ["F", "F", "U"], [1, 1, 1], 2, 2, "ascii") + b"0 0 0\n" * 4)
    with pytest.raises(FormatError, match=r"fields\.pcd, line 5, field 'TYPE': field 'z' must be one float32 or float64"):
        _read(path)
    path.write_bytes(_header(["x", "y", "z"], [4, 4], ["F", "F", "F"], [1, 1, 1], 2, 2, "ascii") + b"0 0 0\n" * 4)
    with pytest.raises(FormatError, match=r"fields\.pcd, line 4, field 'SIZE': 2 entries for 3 FIELDS"):
        _read(path)


def test_empty_and_headerless_files(tmp_path):
    path = tmp_path / "empty.pcd"
    path.write_bytes(b"")
    with pytest.raises(FormatError, match=r"empty\.pcd: empty file"):
        _read(path)
    path.write_bytes(b"ply\nformat ascii 1.0\n")
    with pytest.raises(FormatError, match=r"empty\.pcd, line 1: unknown header keyword 'PLY'"):
        _read(path)
    path.write_bytes(b"VERSION 0.7\nFIELDS x y z\n")
    with pytest.raises(FormatError, match=r"empty\.pcd, field 'DATA': header ends without a DATA line"):
        _read(path)


def test_failed_write_leaves_no_file(tmp_path):
    with pytest.raises(TypeError):
        write_pcd(tmp_path / "scan.pcd", np.zeros((4, 4)))
    assert list(tmp_path.iterdir()) == []
