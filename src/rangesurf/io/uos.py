"""3DTK "uos" scans: ``scanNNN.3d`` with ``scanNNN.pose`` and ``scanNNN.frames``.

The format of the 3DTK / slam6d toolkit (University of Osnabrueck)::

    360 x 225                <- optional header (older files); see below
    10.1 0 0                 <- one point per line: x y z [reflectance ...]
    10.0996 -0.0662149 0.0581712
    ...

* Points are **centimetres** in 3DTK's **left-handed** frame (x right, y up,
  z forward). rangesurf's sensor frame is right-handed camera-optical (x right,
  y down, z forward), so a point converts as ``p = (x, -y, z) / 100``.
* The points form a grid, one scan line after the other: row ``i`` is scan
  line ``i``, column ``j`` the ``j``-th point of that line. The grid width is
  the header's first number (the header's second number is unreliable: the
  University of Osnabrueck files say ``360 x 225`` but hold 226 lines), or
  360 when there is no header (newer 3DTK files). The height is the number of
  points divided by the width.
* There is no invalid marker: missing returns appear at the scanner's maximum
  range (3276.7 cm) or within a few centimetres of the sensor. Readings at or
  beyond ``sensor.max_range`` (less 5 cm) or below ``sensor.min_range``, and
  ``0 0 0`` points (what `write_uos` writes for a cell without a return),
  become NaN. The ``"uos-laser"`` preset (0.2 m to 32.767 m) applies to
  226 x 360 grids; other grids get an `unknown_sensor` (only ``0 0 0`` is
  no return) unless a sensor is given.
* A fourth column, if present on every line, is read as ``intensity``
  (``nan`` allowed there, meaning unknown); further columns are ignored.

Companion files beside ``scanNNN.3d``:

* ``scanNNN.pose`` -- odometry, two lines ``x y z`` (cm) and
  ``theta_x theta_y theta_z`` (degrees). In 3DTK coordinates a point maps to
  the world as ``R p + t`` with ``R = Rx(theta_x) Ry(theta_y) Rz(theta_z)``.
  Read as `RangeFrame.pose`.
* ``scanNNN.frames`` -- slam6d's registration, one step per line: a 4x4
  matrix in OpenGL column-major order (translation in elements 13-15, cm)
  and a colour code. The last line is the final registered pose, read as
  `RangeFrame.reference_pose`.

Both are converted to rangesurf's frames with ``C = diag(1, -1, 1)``:
``T = C4 @ T_3dtk @ C4`` with translation in metres.

References
----------
A. Nuechter, K. Lingemann et al., 3DTK -- The 3D Toolkit,
https://slam6d.sourceforge.io (file formats: ``scan_io_uos``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from rangesurf.frame import RangeFrame, SensorModel, get_sensor, unknown_sensor
from rangesurf.io._common import FormatError, atomic_write
from rangesurf.io._text import parse_numbers

__all__ = ["read_uos", "write_uos", "read_uos_pose", "read_uos_frames"]

_DEFAULT_WIDTH = 360
_CENTIMETRE = 0.01
# 3DTK's left-handed (y up) frame <-> our right-handed optical (y down) frame.
_FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])
# Readings this close to max_range are the scanner's "no return" value
# (3276.7 cm, also seen as 3275.9 cm after the file's rounding).
_MAX_RANGE_MARGIN = 0.05
_HEADER = re.compile(rb"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")
# How far a rotation read from a file may be from orthonormal before it is
# rejected (the files print 6 significant digits); within it, it is snapped.
_ROTATION_TOLERANCE = 1e-3
_FRAMES_COLOUR = 2


# --------------------------------------------------------------------------
# Reading.
# --------------------------------------------------------------------------


def read_uos(path: str | Path, *, sensor: SensorModel | str | None = None) -> Iterator[RangeFrame]:
    """Yield the one frame of a 3DTK ``.3d`` scan (with its ``.pose`` / ``.frames``).

    Parameters
    ----------
    path : path-like
        The ``scanNNN.3d`` file. ``scanNNN.pose`` and ``scanNNN.frames``
        beside it are read when present.
    sensor : SensorModel or str, optional
        The sensor; its grid must match the file's. Without a header its
        width also sets the grid width. Default: the ``"uos-laser"`` preset
        for 226 x 360 grids (the University of Osnabrueck scanner), otherwise
        an `unknown_sensor` of the file's grid: rays from the points, and only
        ``0 0 0`` points count as no return, since other scanners of the
        format reach far beyond that scanner's 32.7 m cut-off.

    Yields
    ------
    RangeFrame
        ``range`` (H, W) float32 metres, NaN where there was no return;
        ``rays`` from the points (from the sensor's projection where there
        was no return); ``pose`` from ``.pose``, ``reference_pose`` from the
        last line of ``.frames`` (None when the file is absent); ``timestamp``
        the scan number of the file name (``scan001`` -> 1.0).

    Raises
    ------
    FormatError
        If the file is empty, has a line that is not 3 or more numbers (or
        fewer numbers than the first point line), NaN or Inf coordinates, a
        point count that is not a multiple of the grid width, or a malformed
        companion file. The message names the file and the line.

    Examples
    --------
    >>> frame = next(read_uos("../shared/data/uos-3dtk/scan000.3d"))  # doctest: +SKIP
    >>> frame.shape                                                  # doctest: +SKIP
    (226, 360)
    """
    path = Path(path)
    model = None if sensor is None else get_sensor(sensor)
    data = _read_bytes(path)
    values, header_width = _parse_points(path, data)
    points_3dtk = values[:, :3]
    width = header_width or (model.width if model is not None else _DEFAULT_WIDTH)
    count = len(values)
    if count % width:
        source = f"the header's width {width}" if header_width else f"the grid width {width}"
        raise FormatError(
            path,
            f"{count} points is not a multiple of {source}; expected whole scan lines of {width} points",
            where="line 1" if header_width else None,
        )
    height = count // width
    model = _sensor_for_grid(path, model, height, width)

    points = points_3dtk.reshape(height, width, 3) * np.array([_CENTIMETRE, -_CENTIMETRE, _CENTIMETRE])
    distance = np.linalg.norm(points, axis=-1)
    no_return = (distance == 0) | (distance < model.min_range)
    if math.isfinite(model.max_range):
        no_return |= distance >= model.max_range - _MAX_RANGE_MARGIN
    points[no_return] = np.nan
    intensity = values[:, 3].reshape(height, width) if values.shape[1] > 3 else None

    pose_path, frames_path = path.with_suffix(".pose"), path.with_suffix(".frames")
    pose = read_uos_pose(pose_path) if pose_path.is_file() else None
    reference_pose = read_uos_frames(frames_path)[-1] if frames_path.is_file() else None
    yield RangeFrame.from_points(
        points, sensor=model, intensity=intensity, pose=pose, reference_pose=reference_pose,
        timestamp=_scan_number(path), source=str(path),
    )


def read_uos_pose(path: str | Path) -> np.ndarray:
    """Read a 3DTK ``.pose`` file as ``T_world_sensor`` in rangesurf's frames.

    Parameters
    ----------
    path : path-like
        Two lines: ``x y z`` (cm) and ``theta_x theta_y theta_z`` (degrees).

    Returns
    -------
    (4, 4) float64
        Rigid transform, translation in metres, right-handed optical frames.

    Raises
    ------
    FormatError
        If the file does not hold two lines of three finite numbers.
    """
    path = Path(path)
    rows = _numeric_lines(path, _read_bytes(path).decode("utf-8", errors="replace"))
    if len(rows) != 2:
        raise FormatError(path, f"expected 2 lines (x y z in cm, then theta_x theta_y theta_z in degrees), found {len(rows)}")
    for line_number, numbers in rows:
        if len(numbers) != 3 or not np.all(np.isfinite(numbers)):
            raise FormatError(path, f"expected 3 finite numbers, got {' '.join(map(str, numbers)) or 'nothing'}",
                              where=f"line {line_number}")
    translation, angles_deg = rows[0][1], rows[1][1]
    transform = np.eye(4)
    transform[:3, :3] = _euler_xyz_to_matrix(np.deg2rad(angles_deg))
    transform[:3, 3] = translation
    return _from_3dtk(transform)


def read_uos_frames(path: str | Path) -> np.ndarray:
    """Read every step of a 3DTK ``.frames`` file; the last is the final pose.

    Parameters
    ----------
    path : path-like
        One line per registration step: 16 numbers (a 4x4 matrix in OpenGL
        column-major order, translation in cm) and a colour code.

    Returns
    -------
    (K, 4, 4) float64
        ``T_world_sensor`` of each step in rangesurf's frames (metres).

    Raises
    ------
    FormatError
        If the file is empty, a line does not hold 16 or 17 finite numbers,
        or a matrix is not a rigid transform.
    """
    path = Path(path)
    rows = _numeric_lines(path, _read_bytes(path).decode("utf-8", errors="replace"))
    if not rows:
        raise FormatError(path, "empty .frames file; expected lines of 16 matrix numbers and a colour code")
    transforms = []
    for line_number, numbers in rows:
        where = f"line {line_number}"
        if len(numbers) not in (16, 17):
            raise FormatError(path, f"expected 16 numbers (4x4 column-major matrix) and a colour code, got {len(numbers)} numbers",
                              where=where)
        if not np.all(np.isfinite(numbers)):
            raise FormatError(path, "matrix contains NaN or Inf", where=where)
        matrix = numbers[:16].reshape(4, 4).T
        transforms.append(_from_3dtk(_rigid(path, matrix, where)))
    return np.stack(transforms)


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise FormatError(path, "no such file") from None
    except IsADirectoryError:
        raise FormatError(path, "is a folder, expected a file") from None


def _parse_points(path: Path, data: bytes) -> tuple[np.ndarray, int | None]:
    """The point lines of a ``.3d`` file as ``(N, C)`` float64, and the header's width."""
    start = 0
    lines_before = 0
    header_width = None
    first_line_end = data.find(b"\n")
    first_line = data if first_line_end < 0 else data[:first_line_end]
    match = _HEADER.match(first_line)
    if match:
        header_width = int(match.group(1))
        if header_width < 1:
            raise FormatError(path, f"header grid width must be positive, got {first_line.decode(errors='replace')!r}",
                              where="line 1")
        start = len(data) if first_line_end < 0 else first_line_end + 1
        lines_before = 1
    # One compiled pass gives the numbers and the tokens on every line. A bad
    # token is reported after the column checks, so that a file with both
    # kinds of damage names the same line as it always has.
    parsed = parse_numbers(data, start=start, strict=False)
    if not len(parsed.values):
        what = "no points after the header" if header_width else "empty file"
        raise FormatError(path, f"{what}; expected lines of 'x y z' in centimetres")
    counts = parsed.tokens_per_line
    point_lines = np.flatnonzero(counts)  # blank lines are skipped
    columns = int(counts[point_lines[0]])

    def where(line_index: int) -> str:
        return f"line {lines_before + line_index + 1}"

    def line_text(line_index: int) -> str:
        text = data[start:].split(b"\n", line_index + 1)[line_index].strip()
        return text[:80].decode("utf-8", errors="replace")

    if columns < 3:
        raise FormatError(path, f"expected 3 numbers (x y z) or more, got {columns}: {line_text(point_lines[0])!r}",
                          where=where(point_lines[0]))
    wrong = point_lines[counts[point_lines] != columns]
    if len(wrong):
        line = int(wrong[0])
        raise FormatError(
            path,
            f"expected {columns} numbers like the first point line ({where(point_lines[0])}), "
            f"got {counts[line]}: {line_text(line)!r}",
            where=where(line),
        )
    if parsed.bad is not None:
        raise FormatError(
            path,
            f"expected numbers, got {parsed.bad.text[:40].decode('utf-8', errors='replace')!r} "
            f"in {line_text(parsed.bad.line)!r}",
            where=where(parsed.bad.line),
        )
    values = parsed.values.reshape(-1, columns)
    # NaN reflectance means unknown; Inf is an error, and so is a value past float32 (frames keep
    # float32: it would become Inf there). Whole-array checks first: the per-point ones below are
    # only needed to name the line.
    limit = float(np.finfo(np.float32).max)
    magnitude = np.abs(np.nan_to_num(values, nan=0.0))
    if not (np.isfinite(values[:, :3]).all() and (magnitude <= limit).all()):
        finite = np.isfinite(values[:, :3]).all(axis=1) & (magnitude <= limit).all(axis=1)
        line = int(point_lines[np.argmin(finite)])
        raise FormatError(path, f"coordinates must be finite numbers, got {line_text(line)!r}", where=where(line))
    return values, header_width


def _numeric_lines(path: Path, text: str) -> list[tuple[int, np.ndarray]]:
    """``(line number, numbers)`` of every non-blank line."""
    rows = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            rows.append((line_number, np.array(line.split(), dtype=np.float64)))
        except ValueError:
            raise FormatError(path, f"expected numbers, got {line.strip()[:80]!r}", where=f"line {line_number}") from None
    return rows


def _sensor_for_grid(path: Path, model: SensorModel | None, height: int, width: int) -> SensorModel:
    if model is None:
        preset = get_sensor("uos-laser")
        return preset if preset.shape == (height, width) else unknown_sensor(height, width)
    if model.shape != (height, width):
        raise FormatError(
            path,
            f"grid {height}x{width} (rows x columns) does not match sensor {model.name!r} grid "
            f"{model.height}x{model.width}",
        )
    return model


def _scan_number(path: Path) -> float:
    match = re.search(r"(\d+)$", path.stem)
    return float(match.group(1)) if match else 0.0


# --------------------------------------------------------------------------
# Frames and rotations.
# --------------------------------------------------------------------------


def _euler_xyz_to_matrix(angles: np.ndarray) -> np.ndarray:
    """``Rx(a) @ Ry(b) @ Rz(c)`` for angles ``(a, b, c)`` in radians (right-handed)."""
    (ca, cb, cc), (sa, sb, sc) = np.cos(angles), np.sin(angles)
    rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return rx @ ry @ rz


def _matrix_to_euler_xyz(rotation: np.ndarray) -> np.ndarray:
    """Angles ``(a, b, c)`` with ``Rx(a) @ Ry(b) @ Rz(c) == rotation``, radians."""
    # Rx Ry Rz = [[cb cc, -cb sc, sb], [., ., -sa cb], [., ., ca cb]]
    sin_b = float(np.clip(rotation[0, 2], -1.0, 1.0))
    b = math.asin(sin_b)
    if abs(sin_b) < 1 - 1e-12:
        a = math.atan2(-rotation[1, 2], rotation[2, 2])
        c = math.atan2(-rotation[0, 1], rotation[0, 0])
    else:  # gimbal lock: only a +/- c is defined; put it all in a
        a = math.atan2(rotation[2, 1], rotation[1, 1])
        c = 0.0
    return np.array([a, b, c])


def _rigid(path: Path, matrix: np.ndarray, where: str) -> np.ndarray:
    """Check a matrix read from a file is rigid; snap its rotation to orthonormal."""
    if not np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-6):
        raise FormatError(path, f"matrix last row must be 0 0 0 1, got {matrix[3].tolist()}", where=where)
    rotation = matrix[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=_ROTATION_TOLERANCE) or np.linalg.det(rotation) <= 0:
        raise FormatError(path, "matrix rotation part is not a proper rotation (orthonormal, det +1)", where=where)
    u, _, vt = np.linalg.svd(rotation)
    snapped = matrix.copy()
    snapped[:3, :3] = u @ vt
    return snapped


def _from_3dtk(transform: np.ndarray) -> np.ndarray:
    """3DTK transform (left-handed, cm) -> rangesurf transform (optical, m)."""
    out = _FLIP_Y @ transform @ _FLIP_Y
    out[:3, 3] *= _CENTIMETRE
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _to_3dtk(transform: np.ndarray) -> np.ndarray:
    out = _FLIP_Y @ np.asarray(transform, dtype=np.float64) @ _FLIP_Y
    out[:3, 3] /= _CENTIMETRE
    return out


# --------------------------------------------------------------------------
# Writing.
# --------------------------------------------------------------------------


def write_uos(path: str | Path, frame: RangeFrame) -> None:
    """Write a frame as a 3DTK ``.3d`` scan, with ``.pose`` and ``.frames`` if known.

    The ``.3d`` file has no header (as newer 3DTK writes) when the grid is 360
    points wide, and a ``W x H`` header otherwise so the grid reads back.
    Points are centimetres in 3DTK's left-handed frame; cells without a
    return are written as ``0 0 0``; intensity, if any, is a fourth column.
    ``.pose`` holds ``frame.pose`` and ``.frames`` one line with
    ``frame.reference_pose``; a stale companion file is removed when the
    frame has no such pose, so it cannot be read back as this frame's.

    Parameters
    ----------
    path : path-like
        The ``.3d`` file to write; companions go beside it.
    frame : RangeFrame

    Notes
    -----
    Cells whose range lies outside ``[sensor.min_range, sensor.max_range)``
    read back as no return, like the scanner's own. Each file is written
    atomically; the timestamp is not stored (3DTK has no place for it).
    """
    path = Path(path)
    height, width = frame.shape
    points = frame.points.astype(np.float64).reshape(-1, 3)
    valid = frame.valid.reshape(-1)
    coordinates = np.where(valid[:, None], points * np.array([100.0, -100.0, 100.0]), 0.0)
    columns = [coordinates]
    line_format = "%.4f %.4f %.4f"
    if frame.intensity is not None:
        columns.append(frame.intensity.astype(np.float64).reshape(-1, 1))
        line_format += " %.9g"
    table = np.hstack(columns)
    body = ((line_format + "\n") * len(table)) % tuple(table.ravel())
    header = "" if width == _DEFAULT_WIDTH else f"{width} x {height}\n"

    pose_path, frames_path = path.with_suffix(".pose"), path.with_suffix(".frames")
    if frame.pose is not None:
        transform = _to_3dtk(frame.pose)
        angles = np.rad2deg(_matrix_to_euler_xyz(transform[:3, :3]))
        with atomic_write(pose_path, "w") as stream:
            numbers = np.concatenate([transform[:3, 3], angles]) + 0.0  # no "-0"
            stream.write("%.10g %.10g %.10g\n%.10g %.10g %.10g\n" % tuple(numbers))
    else:
        pose_path.unlink(missing_ok=True)
    if frame.reference_pose is not None:
        column_major = _to_3dtk(frame.reference_pose).T.ravel() + 0.0
        with atomic_write(frames_path, "w") as stream:
            stream.write(" ".join("%.17g" % value for value in column_major) + f" {_FRAMES_COLOUR}\n")
    else:
        frames_path.unlink(missing_ok=True)
    with atomic_write(path, "w") as stream:
        stream.write(header)
        stream.write(body)
