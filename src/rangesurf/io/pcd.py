"""Organized PCD files (Point Cloud Library, format v0.7).

A PCD file is an ASCII header followed by the points::

    # .PCD v0.7 - Point Cloud Data file format
    # rangesurf sensor sr3000
    VERSION 0.7
    FIELDS x y z intensity
    SIZE 4 4 4 4
    TYPE F F F F
    COUNT 1 1 1 1
    WIDTH 176
    HEIGHT 144
    VIEWPOINT 0 0 0 1 0 0 0
    POINTS 25344
    DATA binary

Only organized clouds (``HEIGHT > 1``) are range grids: point ``(row, col)``
is stored at index ``row * WIDTH + col``. Points are in the sensor frame;
``VIEWPOINT tx ty tz qw qx qy qz`` is the sensor pose in the world
(PCL's ``sensor_origin_`` / ``sensor_orientation_``), read as
``RangeFrame.pose`` (``T_world_sensor``) unless it is the identity, which
PCL writes when the pose is unknown.

rangesurf adds two comment lines that other PCD readers ignore:
``# rangesurf sensor <name>`` (the sensor preset) and
``# rangesurf timestamp <seconds>``.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rangesurf.frame import SENSORS, RangeFrame, SensorModel, get_sensor, unknown_sensor
from rangesurf.io._common import FormatError, atomic_write

__all__ = ["read_pcd", "write_pcd"]

_HEADER_KEYWORDS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_DATA_KINDS = ("ascii", "binary", "binary_compressed")
_SENSOR_COMMENT = "rangesurf sensor"
_TIMESTAMP_COMMENT = "rangesurf timestamp"
# A header longer than this is not a PCD header: stop before scanning binary data.
_MAX_HEADER_LINES = 10_000


@dataclass(frozen=True)
class _Field:
    name: str
    size: int
    type: str
    count: int

    @property
    def dtype(self) -> np.dtype:
        kind = {"F": "f", "I": "i", "U": "u"}[self.type]
        return np.dtype(f"<{kind}{self.size}")

    @property
    def nbytes(self) -> int:
        return self.size * self.count


@dataclass(frozen=True)
class _Header:
    fields: tuple[_Field, ...]
    width: int
    height: int
    viewpoint: tuple[float, ...]
    data: str
    data_offset: int
    sensor_name: str | None
    timestamp: float


# --------------------------------------------------------------------------
# Reading.
# --------------------------------------------------------------------------


def read_pcd(path: str | os.PathLike, *, sensor: str | SensorModel | None = None) -> Iterator[RangeFrame]:
    """Yield the one organized range frame of a PCD file.

    Parameters
    ----------
    path : str or path-like
        A PCD v0.7 (or v0.6/v0.5) file with ``DATA ascii``, ``binary`` or
        ``binary_compressed`` (LZF). Fields ``x y z`` (float32 or float64)
        are required, ``intensity`` (any numeric type) is optional, other
        fields (``rgb``, ``normal_x``, padding ``_``...) are skipped.
    sensor : str or SensorModel, optional
        The sensor (or a preset name); its grid must match ``(HEIGHT, WIDTH)``. By default the
        preset named by a ``# rangesurf sensor <name>`` comment, else
        `unknown_sensor` (rays taken from the points).

    Yields
    ------
    RangeFrame
        ``range`` (H, W) float32 metres, NaN where a point has a NaN
        coordinate or lies at the origin; ``intensity`` (H, W) float32 if the
        file has it; ``pose`` from ``VIEWPOINT`` when it is not the identity.

    Raises
    ------
    FormatError
        Unorganized cloud (``HEIGHT 1``), missing or inconsistent header
        fields, unknown ``DATA`` kind, truncated or malformed data; the
        message names the file and the line or field.

    Examples
    --------
    >>> frame = next(read_pcd("scan.pcd"))     # doctest: +SKIP
    >>> frame.shape                            # doctest: +SKIP
    (144, 176)
    """
    path = Path(path)
    raw = path.read_bytes()
    if not raw:
        raise FormatError(path, "empty file; expected a PCD header")
    header = _parse_header(path, raw)
    columns = _read_columns(path, raw, header)

    height, width = header.height, header.width
    points = np.stack([columns["x"], columns["y"], columns["z"]], axis=-1).reshape(height, width, 3)
    intensity = columns.get("intensity")
    if intensity is not None:
        intensity = intensity.reshape(height, width).astype(np.float32)
        # RangeFrame refuses Inf intensity; an overflowed reading is unknown.
        intensity = np.where(np.isfinite(intensity), intensity, np.nan).astype(np.float32)

    frame_sensor = _choose_sensor(path, header, None if sensor is None else get_sensor(sensor))
    pose = _viewpoint_to_pose(path, header.viewpoint)
    try:
        frame = RangeFrame.from_points(
            points, sensor=frame_sensor, intensity=intensity, pose=pose,
            timestamp=header.timestamp, source=str(path),
        )
    except ValueError as error:
        raise FormatError(path, str(error)) from None
    yield frame


def _parse_header(path: Path, raw: bytes) -> _Header:
    values: dict[str, tuple[list[str], int]] = {}
    sensor_name = None
    timestamp = 0.0
    position = 0
    line_number = 0
    while True:
        line_number += 1
        end = raw.find(b"\n", position)
        if end == -1 or line_number > _MAX_HEADER_LINES:
            raise FormatError(path, "header ends without a DATA line", where="field 'DATA'")
        try:
            line = raw[position:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise FormatError(
                path, "header line is not ASCII text; is this a PCD file?", where=f"line {line_number}",
            ) from None
        position = end + 1
        if not line:
            continue
        if line.startswith("#"):
            comment = line[1:].strip()
            if comment.startswith(_SENSOR_COMMENT):
                sensor_name = comment[len(_SENSOR_COMMENT):].strip() or None
            elif comment.startswith(_TIMESTAMP_COMMENT):
                timestamp = _parse_float(path, comment[len(_TIMESTAMP_COMMENT):].strip(), f"line {line_number}", "timestamp")
            continue
        keyword, *arguments = line.split()
        keyword = keyword.upper()
        if keyword not in _HEADER_KEYWORDS:
            raise FormatError(
                path, f"unknown header keyword {keyword!r}; expected one of {', '.join(_HEADER_KEYWORDS)}",
                where=f"line {line_number}",
            )
        values[keyword] = (arguments, line_number)
        if keyword == "DATA":
            break

    fields = _parse_fields(path, values)
    width = _parse_count(path, values, "WIDTH")
    height = _parse_count(path, values, "HEIGHT")
    if height == 1:
        raise FormatError(
            path,
            f"unorganized cloud (HEIGHT 1, {width} points); rangesurf needs an organized cloud (HEIGHT > 1) "
            "with one point per sensor cell",
            where=_where(values, "HEIGHT"),
        )
    if "POINTS" in values:
        points = _parse_count(path, values, "POINTS")
        if points != width * height:
            raise FormatError(
                path, f"POINTS {points} does not equal WIDTH * HEIGHT = {width} * {height} = {width * height}",
                where=_where(values, "POINTS"),
            )

    viewpoint: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    if "VIEWPOINT" in values:
        arguments, _ = values["VIEWPOINT"]
        if len(arguments) != 7:
            raise FormatError(
                path, f"expected 7 numbers (tx ty tz qw qx qy qz), got {len(arguments)}", where=_where(values, "VIEWPOINT"),
            )
        viewpoint = tuple(_parse_float(path, a, _where(values, "VIEWPOINT"), "VIEWPOINT") for a in arguments)

    arguments, _ = values["DATA"]
    kind = arguments[0].lower() if len(arguments) == 1 else " ".join(arguments)
    if kind not in _DATA_KINDS:
        raise FormatError(
            path, f"unknown DATA kind {kind!r}; expected one of {', '.join(_DATA_KINDS)}", where=_where(values, "DATA"),
        )
    return _Header(
        fields=fields, width=width, height=height, viewpoint=viewpoint, data=kind,
        data_offset=position, sensor_name=sensor_name, timestamp=timestamp,
    )


def _where(values: dict[str, tuple[list[str], int]], keyword: str) -> str:
    if keyword in values:
        return f"line {values[keyword][1]}, field '{keyword}'"
    return f"field '{keyword}'"


def _parse_float(path: Path, text: str, where: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise FormatError(path, f"{what}: expected a number, got {text!r}", where=where) from None
    if not math.isfinite(value):
        raise FormatError(path, f"{what}: expected a finite number, got {text!r}", where=where)
    return value


def _parse_count(path: Path, values: dict[str, tuple[list[str], int]], keyword: str) -> int:
    if keyword not in values:
        raise FormatError(path, f"missing {keyword} header line", where=f"field '{keyword}'")
    arguments, _ = values[keyword]
    if len(arguments) != 1 or not arguments[0].isdigit() or int(arguments[0]) < 1:
        raise FormatError(path, f"expected one positive integer, got {' '.join(arguments)!r}", where=_where(values, keyword))
    return int(arguments[0])


def _parse_fields(path: Path, values: dict[str, tuple[list[str], int]]) -> tuple[_Field, ...]:
    for keyword in ("FIELDS", "SIZE", "TYPE"):
        if keyword not in values:
            raise FormatError(path, f"missing {keyword} header line", where=f"field '{keyword}'")
    names = values["FIELDS"][0]
    sizes = values["SIZE"][0]
    types = [t.upper() for t in values["TYPE"][0]]
    counts = values["COUNT"][0] if "COUNT" in values else ["1"] * len(names)
    for keyword, entries in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(entries) != len(names):
            raise FormatError(
                path, f"{len(entries)} entries for {len(names)} FIELDS ({' '.join(names)})", where=_where(values, keyword),
            )
    fields = []
    for name, size, kind, count in zip(names, sizes, types, counts):
        if size not in ("1", "2", "4", "8"):
            raise FormatError(
                path, f"field {name!r}: size must be 1, 2, 4 or 8 bytes, got {size!r}", where=_where(values, "SIZE"),
            )
        if kind not in ("F", "I", "U") or (kind == "F" and size not in ("4", "8")):
            raise FormatError(
                path, f"field {name!r}: unsupported TYPE {kind!r} with SIZE {size}", where=_where(values, "TYPE"),
            )
        if not count.isdigit() or int(count) < 1:
            raise FormatError(
                path, f"field {name!r}: COUNT must be a positive integer, got {count!r}", where=_where(values, "COUNT"),
            )
        fields.append(_Field(name, int(size), kind, int(count)))

    by_name = {f.name: f for f in fields}
    missing = [axis for axis in "xyz" if axis not in by_name]
    if missing:
        raise FormatError(
            path, f"needs fields x, y and z; missing {', '.join(missing)} in {' '.join(names)}",
            where=_where(values, "FIELDS"),
        )
    for axis in "xyz":
        field_ = by_name[axis]
        if field_.type != "F" or field_.count != 1:
            raise FormatError(
                path, f"field {axis!r} must be one float32 or float64 (TYPE F, SIZE 4/8, COUNT 1), "
                f"got TYPE {field_.type} SIZE {field_.size} COUNT {field_.count}", where=_where(values, "TYPE"),
            )
    return tuple(fields)


def _wanted(header: _Header) -> list[str]:
    names = [f.name for f in header.fields]
    return ["x", "y", "z"] + (["intensity"] if "intensity" in names else [])


def _read_columns(path: Path, raw: bytes, header: _Header) -> dict[str, np.ndarray]:
    """The x, y, z (and intensity) columns, each ``(N,)`` float64."""
    if header.data == "ascii":
        return _read_ascii(path, raw, header)
    if header.data == "binary":
        return _read_binary(path, raw, header)
    return _read_binary_compressed(path, raw, header)


def _read_binary(path: Path, raw: bytes, header: _Header) -> dict[str, np.ndarray]:
    count = header.width * header.height
    point_step = sum(f.nbytes for f in header.fields)
    expected = count * point_step
    available = len(raw) - header.data_offset
    if available < expected:
        raise FormatError(
            path,
            f"binary data truncated: expected {expected} bytes ({count} points of {point_step} bytes), got {available}",
            where="DATA",
        )
    offsets = {}
    offset = 0
    for f in header.fields:
        # First occurrence wins: PCL repeats only the padding name "_".
        offsets.setdefault(f.name, (offset, f))
        offset += f.nbytes
    wanted = _wanted(header)
    record = np.dtype({
        "names": wanted,
        "formats": [offsets[name][1].dtype for name in wanted],
        "offsets": [offsets[name][0] for name in wanted],
        "itemsize": point_step,
    })
    records = np.frombuffer(raw, dtype=record, count=count, offset=header.data_offset)
    return {name: records[name].astype(np.float64) for name in wanted}


def _read_binary_compressed(path: Path, raw: bytes, header: _Header) -> dict[str, np.ndarray]:
    count = header.width * header.height
    start = header.data_offset
    if len(raw) - start < 8:
        raise FormatError(path, "binary_compressed data truncated: missing the 8-byte size prefix", where="DATA")
    compressed_size, uncompressed_size = (int(v) for v in np.frombuffer(raw, "<u4", count=2, offset=start))
    available = len(raw) - start - 8
    if available < compressed_size:
        raise FormatError(
            path, f"binary_compressed data truncated: expected {compressed_size} compressed bytes, got {available}",
            where="DATA",
        )
    # PCL leaves the padding fields "_" out of compressed data; accept both.
    stored = [f for f in header.fields if f.name != "_"]
    if uncompressed_size != count * sum(f.nbytes for f in stored):
        stored = list(header.fields)
    if uncompressed_size != count * sum(f.nbytes for f in stored):
        raise FormatError(
            path, f"binary_compressed: uncompressed size {uncompressed_size} does not match "
            f"{count} points of {sum(f.nbytes for f in header.fields if f.name != '_')} bytes", where="DATA",
        )
    try:
        data = _lzf_decompress(raw[start + 8:start + 8 + compressed_size], uncompressed_size)
    except ValueError as error:
        raise FormatError(path, f"binary_compressed: corrupt LZF data ({error})", where="DATA") from None

    # Compressed data is stored field by field ("xxxx...yyyy...zzzz...").
    columns: dict[str, np.ndarray] = {}
    offset = 0
    for f in stored:
        if f.name in _wanted(header) and f.name not in columns:
            values = np.frombuffer(data, dtype=f.dtype, count=count * f.count, offset=offset)
            columns[f.name] = values[:: f.count].astype(np.float64)
        offset += count * f.nbytes
    return columns


def _read_ascii(path: Path, raw: bytes, header: _Header) -> dict[str, np.ndarray]:
    count = header.width * header.height
    per_point = sum(f.count for f in header.fields)
    text = raw[header.data_offset:].decode("ascii", errors="replace")
    tokens = text.split()
    try:
        if len(tokens) != count * per_point:
            raise ValueError
        table = np.array(tokens, dtype=np.float64).reshape(count, per_point)
    except ValueError:
        raise _ascii_error(path, raw, header, per_point) from None
    columns = {}
    column = 0
    for f in header.fields:
        if f.name in _wanted(header) and f.name not in columns:
            columns[f.name] = table[:, column]
        column += f.count
    return columns


def _ascii_error(path: Path, raw: bytes, header: _Header, per_point: int) -> FormatError:
    """Locate the first bad line of ASCII data (slow path, errors only)."""
    count = header.width * header.height
    first_line = raw[:header.data_offset].count(b"\n") + 1
    lines = raw[header.data_offset:].decode("ascii", errors="replace").splitlines()
    points_seen = 0
    for index, line in enumerate(lines):
        tokens = line.split()
        if not tokens:
            continue
        where = f"line {first_line + index}"
        if len(tokens) != per_point:
            return FormatError(path, f"expected {per_point} values per point, got {len(tokens)}: {line[:80]!r}", where=where)
        for token in tokens:
            try:
                float(token)
            except ValueError:
                return FormatError(path, f"expected numbers, got {token!r}", where=where)
        points_seen += 1
    problem = "truncated" if points_seen < count else "too long"
    return FormatError(
        path, f"ascii data {problem}: expected {count} points (WIDTH * HEIGHT), got {points_seen}", where="DATA",
    )


def _lzf_decompress(data: bytes, expected_size: int) -> bytes:
    """Decompress LZF (liblzf, as written by PCL) to exactly ``expected_size`` bytes.

    Pure Python: literal runs and back references are copied as slices, so
    the loop runs once per LZF token (at most 32 literal bytes or 264
    repeated bytes each), fast enough for camera-sized clouds.

    Raises
    ------
    ValueError
        If the stream is truncated, refers before its start, or does not
        decompress to ``expected_size`` bytes.
    """
    source = memoryview(data)
    output = bytearray()
    position = 0
    end = len(source)
    while position < end:
        control = source[position]
        position += 1
        if control < 32:
            # Literal run of control + 1 bytes.
            length = control + 1
            if position + length > end:
                raise ValueError(f"literal run of {length} bytes overruns the input at byte {position}")
            output += source[position:position + length]
            position += length
        else:
            length = control >> 5
            if length == 7:
                if position >= end:
                    raise ValueError("back reference length byte missing")
                length += source[position]
                position += 1
            if position >= end:
                raise ValueError("back reference offset byte missing")
            length += 2
            distance = ((control & 0x1F) << 8) + source[position] + 1
            position += 1
            reference = len(output) - distance
            if reference < 0:
                raise ValueError(f"back reference {distance} bytes before the start of the output")
            if distance >= length:
                output += output[reference:reference + length]
            else:
                # Overlapping copy repeats the last `distance` bytes.
                pattern = bytes(output[reference:])
                output += (pattern * (length // distance + 1))[:length]
        if len(output) > expected_size:
            raise ValueError(f"output exceeds the expected {expected_size} bytes")
    if len(output) != expected_size:
        raise ValueError(f"decompressed to {len(output)} bytes, expected {expected_size}")
    return bytes(output)


def _choose_sensor(path: Path, header: _Header, sensor: SensorModel | None) -> SensorModel:
    shape = (header.height, header.width)
    if sensor is not None:
        if sensor.shape != shape:
            raise FormatError(
                path, f"sensor {sensor.name!r} grid {sensor.shape} does not match the cloud's (HEIGHT, WIDTH) {shape}",
            )
        return sensor
    name = header.sensor_name
    if name is not None and name.lower() in SENSORS:
        if SENSORS[name.lower()].shape == shape:
            return get_sensor(name)
        # A preset's name on another grid (a crop?) would mislead later lookups.
        name = None
    return unknown_sensor(*shape, name=name or "unknown")


def _viewpoint_to_pose(path: Path, viewpoint: tuple[float, ...]) -> np.ndarray | None:
    translation = np.asarray(viewpoint[:3], dtype=np.float64)
    quaternion = np.asarray(viewpoint[3:], dtype=np.float64)
    if not np.isfinite(translation).all() or not np.isfinite(quaternion).all():
        raise FormatError(path, f"VIEWPOINT must be 7 finite numbers, got {list(viewpoint)}", where="field 'VIEWPOINT'")
    # Scaled first: the norm of huge (but finite) components would overflow.
    scale = float(np.abs(quaternion).max())
    norm = scale * float(np.linalg.norm(quaternion / scale)) if scale > 0 else 0.0
    if not (1e-9 <= norm < np.inf):
        raise FormatError(path, "VIEWPOINT quaternion (qw qx qy qz) is zero", where="field 'VIEWPOINT'")
    quaternion = quaternion / norm
    if np.all(translation == 0) and abs(abs(quaternion[0]) - 1) < 1e-12:
        return None
    pose = np.eye(4)
    pose[:3, :3] = _quaternion_to_rotation(quaternion)
    pose[:3, 3] = translation
    return pose


def _quaternion_to_rotation(quaternion: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion in PCD order ``(w, x, y, z)``."""
    return Rotation.from_quat(quaternion, scalar_first=True).as_matrix()


def _rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0``."""
    return Rotation.from_matrix(rotation).as_quat(canonical=True, scalar_first=True)


# --------------------------------------------------------------------------
# Writing.
# --------------------------------------------------------------------------


def write_pcd(path: str | os.PathLike, frame: RangeFrame, *, binary: bool = True) -> None:
    """Write a frame as an organized PCD v0.7 file, atomically.

    Parameters
    ----------
    path : str or path-like
        Output file (``.pcd``).
    frame : RangeFrame
        Written as float32 ``x y z`` in the sensor frame (NaN where there is
        no return) plus ``intensity`` if the frame has it; ``pose`` goes into
        ``VIEWPOINT`` (identity when unknown), the sensor name and timestamp
        into ``# rangesurf`` comments. ``reference_pose`` is not stored: use
        ``.npz`` for a lossless copy.
    binary : bool
        ``DATA binary`` (default) or ``DATA ascii``.

    Examples
    --------
    >>> write_pcd("scan.pcd", frame, binary=False)   # doctest: +SKIP
    """
    if not isinstance(frame, RangeFrame):
        raise TypeError(f"write_pcd expects a RangeFrame, got {type(frame).__name__}")
    height, width = frame.shape
    columns = [frame.points.reshape(-1, 3).astype(np.float32)]
    names = ["x", "y", "z"]
    if frame.intensity is not None:
        columns.append(frame.intensity.reshape(-1, 1).astype(np.float32))
        names.append("intensity")
    table = np.concatenate(columns, axis=1)

    if frame.pose is None:
        viewpoint = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    else:
        viewpoint = [*frame.pose[:3, 3], *_rotation_to_quaternion(frame.pose[:3, :3])]
    header = "\n".join([
        "# .PCD v0.7 - Point Cloud Data file format",
        f"# {_SENSOR_COMMENT} {frame.sensor.name}",
        f"# {_TIMESTAMP_COMMENT} {frame.timestamp!r}",
        "VERSION 0.7",
        f"FIELDS {' '.join(names)}",
        f"SIZE {' '.join(['4'] * len(names))}",
        f"TYPE {' '.join(['F'] * len(names))}",
        f"COUNT {' '.join(['1'] * len(names))}",
        f"WIDTH {width}",
        f"HEIGHT {height}",
        f"VIEWPOINT {' '.join(repr(float(v)) for v in viewpoint)}",
        f"POINTS {width * height}",
        f"DATA {'binary' if binary else 'ascii'}",
        "",
    ])
    with atomic_write(path, "wb") as stream:
        stream.write(header.encode("ascii"))
        if binary:
            stream.write(np.ascontiguousarray(table, dtype="<f4").tobytes())
        else:
            text = io.StringIO()
            # %.9g round-trips float32 exactly; NaN prints as "nan" as PCL writes it.
            np.savetxt(text, table, fmt="%.9g", delimiter=" ")
            stream.write(text.getvalue().encode("ascii"))
