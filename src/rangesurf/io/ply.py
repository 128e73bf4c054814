"""PLY point grids, including the Stanford range images (``range_grid``).

A PLY file is a text header followed by its elements, in ASCII or binary::

    ply
    format binary_little_endian 1.0
    comment rangesurf sensor sr3000
    obj_info num_cols 176
    obj_info num_rows 144
    element vertex 24917
    property float x
    property float y
    property float z
    element range_grid 25344
    property list uchar int vertex_indices
    end_header

A frame is read from the ``vertex`` element (``x y z`` in metres, any numeric
type, and an optional ``intensity``, ``reflectance`` or ``scalar`` property)
and a grid size, from ``obj_info num_cols`` / ``num_rows`` or a
``comment width W height H`` line:

* With a ``range_grid`` element (Stanford's range images and rangesurf's own
  files), grid cell ``i`` -- row ``i // num_cols``, column ``i % num_cols`` --
  holds an empty list (no return) or the index of its vertex.
* Without one, there is one vertex per cell in row-major order; NaN vertices
  are cells without a return.

Stanford range images (``obj_info is_cyberware_data 1``, or a 512 x 400
``range_grid`` in a file without rangesurf's comments) come from a
Cyberware 3030MS triangulation scanner looking down the scan's -z axis.
Its rays converge (in the y-z plane) near
``o = (0, 0.179, 1.327)`` m of scan coordinates, and its columns are steps
of 0.5 mm in x. rangesurf places a virtual sensor at ``o`` with axes
``x_s = x``, ``y_s = -y``, ``z_s = -z``, so a scan point maps to the sensor
as ``p_s = R (p - o)`` with ``R = diag(1, -1, -1)``: the points are kept
exactly, the rays are ``p_s / |p_s|`` (within 0.4 deg of the ``"cyberware"``
preset's pinhole rays on the bunny scans). The registration of the scans comes
from a ``*.conf`` file in the same folder that lists the scan (see
`read_stanford_conf`); it sets both ``pose`` and ``reference_pose``.
Other grids are in their sensor's frame already.

`write_ply` writes binary little-endian files with a ``range_grid`` and adds
comment lines that other readers ignore: ``comment rangesurf sensor <name>``,
``comment rangesurf sensor_model <json>``, ``comment rangesurf
T_world_sensor <16 numbers, row-major>`` (likewise
``reference_T_world_sensor``) and ``comment rangesurf timestamp <seconds>``.

References
----------
G. Turk and M. Levoy, "Zippered polygon meshes from range images",
SIGGRAPH 1994 (the Stanford range data). PLY format:
https://paulbourke.net/dataformats/ply/
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rangesurf.frame import RangeFrame, SensorModel, check_rigid_transform, get_sensor, unknown_sensor
from rangesurf.io._common import FormatError, atomic_write
from rangesurf.io._text import parse_numbers, split_lists

__all__ = ["read_ply", "write_ply", "write_mesh_ply", "read_stanford_conf"]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_INTENSITY_NAMES = ("intensity", "reflectance", "scalar_intensity", "scalar_reflectance", "scalar")
_COMMENT_PREFIX = "rangesurf "
# A header longer than this is not a PLY header: stop before reading binary data.
_MAX_HEADER_LINES = 10_000

# Stanford / Cyberware 3030MS virtual sensor (see the module docstring).
_CYBERWARE_GRID = (400, 512)
_CYBERWARE_ORIGIN = np.array([0.0, 0.179, 1.327])
_CYBERWARE_ROTATION = np.diag([1.0, -1.0, -1.0])  # scan -> sensor axes


def _cyberware_scan_from_sensor() -> np.ndarray:
    """``T_scan_sensor`` of the virtual Cyberware sensor."""
    transform = np.eye(4)
    transform[:3, :3] = _CYBERWARE_ROTATION.T
    transform[:3, 3] = _CYBERWARE_ORIGIN
    return transform


# --------------------------------------------------------------------------
# Header.
# --------------------------------------------------------------------------


@dataclass
class _Property:
    name: str
    dtype: str  # numpy type code without byte order ("f4")
    count_dtype: str | None = None  # list length type; None for a scalar


@dataclass
class _Element:
    name: str
    count: int
    line: int  # header line of the ``element`` statement
    properties: list[_Property] = field(default_factory=list)

    def property(self, name: str) -> _Property | None:
        return next((p for p in self.properties if p.name == name), None)


@dataclass
class _Header:
    format: str
    elements: list[_Element]
    obj_info: dict[str, tuple[str, int]]  # key -> (value, header line)
    comments: list[tuple[str, int]]  # (text, header line)
    lines: int  # number of header lines, ``end_header`` included
    data_offset: int  # byte offset of the first element

    def element(self, name: str) -> _Element | None:
        return next((e for e in self.elements if e.name == name), None)


def _parse_header(path: Path, data: bytes) -> _Header:
    if not data.strip():
        raise FormatError(path, "empty file; expected a PLY header starting with 'ply'")
    offset = 0
    line_number = 0
    fmt = None
    elements: list[_Element] = []
    obj_info: dict[str, tuple[str, int]] = {}
    comments: list[tuple[str, int]] = []
    while True:
        end = data.find(b"\n", offset)
        if end < 0 or line_number >= _MAX_HEADER_LINES:
            raise FormatError(path, "header has no 'end_header' line; the file is truncated or not a PLY file",
                              where="header")
        raw = data[offset:end]
        offset = end + 1
        line_number += 1
        where = f"line {line_number}"
        text = raw.decode("ascii", errors="replace").strip()
        words = text.split()
        if line_number == 1:
            if text != "ply":
                raise FormatError(path, f"not a PLY file: expected 'ply', got {text[:40]!r}", where=where)
            continue
        if not words:
            continue
        keyword = words[0]
        if keyword == "end_header":
            break
        if keyword == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise FormatError(
                    path, f"expected 'format ascii|binary_little_endian|binary_big_endian 1.0', got {text!r}", where=where
                )
            fmt = words[1]
        elif keyword == "comment":
            comments.append((text[len("comment"):].strip(), line_number))
        elif keyword == "obj_info":
            if len(words) >= 2:
                obj_info[words[1]] = (" ".join(words[2:]), line_number)
        elif keyword == "element":
            if len(words) != 3 or not re.fullmatch(r"\d+", words[2]):
                raise FormatError(path, f"expected 'element <name> <count>', got {text!r}", where=where)
            elements.append(_Element(words[1], int(words[2]), line_number))
        elif keyword == "property":
            if not elements:
                raise FormatError(path, f"property before any element: {text!r}", where=where)
            elements[-1].properties.append(_parse_property(path, words, text, where))
        else:
            raise FormatError(
                path, f"unknown header keyword {keyword!r}; expected format, comment, obj_info, element, "
                      "property or end_header", where=where,
            )
    if fmt is None:
        raise FormatError(path, "header has no 'format' line", where="header")
    return _Header(fmt, elements, obj_info, comments, line_number, offset)


def _parse_property(path: Path, words: list[str], text: str, where: str) -> _Property:
    if len(words) == 5 and words[1] == "list":
        if words[2] not in _TYPES or words[3] not in _TYPES or _TYPES[words[2]][0] == "f":
            raise FormatError(path, f"expected 'property list <integer type> <type> <name>', got {text!r}", where=where)
        return _Property(words[4], _TYPES[words[3]], _TYPES[words[2]])
    if len(words) == 3 and words[1] in _TYPES:
        return _Property(words[2], _TYPES[words[1]])
    raise FormatError(
        path, f"expected 'property <type> <name>' with type one of {', '.join(sorted(_TYPES))}, got {text!r}",
        where=where,
    )


# --------------------------------------------------------------------------
# Element data.
# --------------------------------------------------------------------------

# An element's values: name -> (N,) array for a scalar property, or
# (lengths (N,), flat items) for a list property.
_Columns = dict[str, "np.ndarray | tuple[np.ndarray, np.ndarray]"]


class _AsciiBody:
    """The element lines of an ASCII PLY body, one record per line."""

    def __init__(self, path: Path, data: bytes, header: _Header) -> None:
        self.path = path
        self.data = data
        self.start = header.data_offset
        self.first_line = header.lines + 1
        # One compiled pass over the whole body: the numbers and the tokens of
        # every line. Bad tokens are kept, not raised: they only matter in the
        # elements that are read, and after each element's own layout checks.
        parsed = parse_numbers(data, start=header.data_offset, strict=False)
        self.values = parsed.values
        self.counts = parsed.tokens_per_line
        self.bad = parsed.bad
        self.cursor = 0  # next body line
        self.token = 0  # its first token
        # Lines holding data; a body ending in a newline has an empty last "line".
        # Blank lines, if any, end the body: look at its tail first.
        tail = self.counts[-64:]
        with_tokens = np.flatnonzero(tail)
        if len(with_tokens):
            self.data_lines = len(self.counts) - len(tail) + int(with_tokens[-1]) + 1
        else:
            with_tokens = np.flatnonzero(self.counts)
            self.data_lines = int(with_tokens[-1]) + 1 if len(with_tokens) else 0

    def where(self, line: int) -> str:
        return f"line {self.first_line + line}"

    def text(self, line: int) -> str:
        """Body line ``line`` for a message (errors only, so it may be slow)."""
        text = self.data[self.start:].split(b"\n", line + 1)[line]
        return text.strip()[:80].decode("utf-8", errors="replace")

    def numbers(self, begin: int, end: int) -> np.ndarray:
        """Tokens ``begin`` to ``end - 1``, which must all be numbers."""
        if self.bad is not None and begin <= self.bad.index < end:
            line = self.bad.line
            raise FormatError(self.path, f"expected numbers, got {self.text(line)!r}", where=self.where(line))
        return self.values[begin:end]

    def read(self, element: _Element) -> _Columns:
        first, last = self.cursor, self.cursor + element.count
        if last > self.data_lines:
            raise FormatError(
                self.path,
                f"file ends inside element {element.name}: expected {element.count} lines of it, "
                f"found {max(self.data_lines - first, 0)}",
                where=self.where(self.data_lines),
            )
        self.cursor = last
        counts = self.counts[first:last]
        begin = self.token
        self.token += int(counts.sum())
        lists = [p for p in element.properties if p.count_dtype is not None]
        if not lists:
            width = len(element.properties)
            wrong = np.flatnonzero(counts != width)
            if len(wrong):
                line = first + int(wrong[0])
                names = " ".join(p.name for p in element.properties)
                raise FormatError(self.path, f"expected {width} numbers ({names}) of element {element.name}, "
                                             f"got {self.text(line)!r}", where=self.where(line))
            table = self.numbers(begin, self.token).reshape(element.count, width)
            return {p.name: table[:, i] for i, p in enumerate(element.properties)}
        if len(element.properties) == 1:
            return {lists[0].name: self._read_list(element, first, begin, counts)}
        return self._read_mixed(element, first, self.numbers(begin, self.token), counts)

    def _read_list(self, element: _Element, first: int, begin: int, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Split first (a bad token is NaN there), so the checks come in the
        # order of the other elements: layout, then numbers, then lengths.
        values = self.values[begin:self.token]
        lengths, items, empty, wrong = split_lists(values, counts)
        if empty >= 0:
            raise FormatError(self.path, f"expected a list (length, then items) of element {element.name}, "
                                         "got an empty line", where=self.where(first + empty))
        self.numbers(begin, self.token)
        if wrong >= 0:
            length = values[int(counts[:wrong].sum())]
            raise FormatError(self.path, f"list length {length:g} does not match the "
                                         f"{counts[wrong] - 1} items that follow it: {self.text(first + wrong)!r}",
                              where=self.where(first + wrong))
        return lengths, items

    def _read_mixed(self, element: _Element, first: int, values: np.ndarray, counts: np.ndarray) -> _Columns:
        # Lists beside scalars in one element: walk the properties (not the
        # lines) with every line's read position at once.
        line_end = np.cumsum(counts)
        position = line_end - counts
        fits = np.ones(element.count, dtype=bool)  # each line so far matches the properties
        out: _Columns = {}
        for prop in element.properties:
            fits &= position < line_end
            value = values[np.where(fits, position, 0)] if len(values) else np.zeros(element.count)
            if prop.count_dtype is None:
                out[prop.name] = value
                position += 1
                continue
            room = line_end - position - 1  # items the rest of the line holds
            fits &= (value >= 0) & (value <= room) & (value == np.floor(value))  # False for NaN
            lengths = np.where(fits, value, 0).astype(np.int64)
            item_start = np.repeat(position + 1 - np.cumsum(lengths) + lengths, lengths)
            out[prop.name] = (lengths, values[item_start + np.arange(len(item_start))])
            position += 1 + lengths
        fits &= position == line_end
        if not fits.all():
            line = first + int(np.argmin(fits))
            raise FormatError(self.path, f"line does not match the properties of element {element.name}: "
                                         f"{self.text(line)!r}", where=self.where(line))
        return out

    def check_end(self) -> None:
        if self.data_lines > self.cursor:
            raise FormatError(self.path, "more data than the header's elements declare "
                                         f"(first extra line: {self.text(self.cursor)!r}); is an element count wrong?",
                              where=self.where(self.cursor))


class _BinaryBody:
    """The elements of a binary PLY body."""

    def __init__(self, path: Path, data: bytes, header: _Header) -> None:
        self.path = path
        self.data = data
        self.buffer = np.frombuffer(data, dtype=np.uint8)
        self.order = _FORMATS[header.format]
        self.offset = header.data_offset

    def _truncated(self, element: _Element, detail: str) -> FormatError:
        return FormatError(self.path, f"file is truncated inside element {element.name} ({detail})",
                           where=f"element {element.name}")

    def read(self, element: _Element) -> _Columns:
        if all(p.count_dtype is None for p in element.properties):
            dtype = np.dtype([(p.name, self.order + p.dtype) for p in element.properties])
            needed = dtype.itemsize * element.count
            available = len(self.data) - self.offset
            if needed > available:
                raise self._truncated(
                    element, f"{element.count} records of {dtype.itemsize} bytes need {needed} bytes "
                             f"from byte {self.offset}, the file has {available}"
                )
            table = np.frombuffer(self.data, dtype=dtype, count=element.count, offset=self.offset)
            self.offset += needed
            return {p.name: table[p.name] for p in element.properties}
        return self._read_records(element)

    def _read_records(self, element: _Element) -> _Columns:
        # Records vary in length, so their positions are found one by one.
        data, order = self.data, "little" if self.order == "<" else "big"
        # Per property: (bytes of the value or list length, bytes per list item, is a list, signed length).
        plan = []
        for prop in element.properties:
            if prop.count_dtype is None:
                plan.append((np.dtype(prop.dtype).itemsize, 0, False, False))
            else:
                count_type = np.dtype(prop.count_dtype)
                plan.append((count_type.itemsize, np.dtype(prop.dtype).itemsize, True, count_type.kind == "i"))
        # Every record takes at least its scalars and list lengths: a declared count that cannot fit in
        # the bytes left is refused before anything of that size is allocated.
        smallest = sum(size for size, _, _, _ in plan)
        available = len(data) - self.offset
        if element.count * max(smallest, 1) > available:
            raise self._truncated(element, f"{element.count} records of at least {max(smallest, 1)} bytes need "
                                           f"{element.count * max(smallest, 1)} bytes, the file has {available} left")
        positions = [[0] * element.count for _ in plan]
        position = self.offset
        try:
            if len(plan) == 1 and plan[0][0] == 1 and plan[0][2] and not plan[0][3]:
                # One list with a uchar length (range_grid, faces): the common case, kept lean.
                item_size = plan[0][1]
                starts = positions[0]
                for record in range(element.count):
                    starts[record] = position
                    position += 1 + data[position] * item_size
            else:
                for record in range(element.count):
                    for index, (size, item_size, is_list, signed) in enumerate(plan):
                        positions[index][record] = position
                        if is_list:
                            length = int.from_bytes(data[position:position + size], order, signed=signed)
                            if len(data) < position + size or length < 0:
                                raise IndexError(position)
                            position += size + length * item_size
                        else:
                            position += size
        except IndexError:
            raise self._truncated(element, f"record {record} of {element.count} starts past the end of the file") from None
        if position > len(data):
            raise self._truncated(element, f"its last record ends at byte {position}, the file has {len(data)}")
        self.offset = position

        out: _Columns = {}
        for prop, starts_list in zip(element.properties, positions):
            starts = np.array(starts_list, dtype=np.int64)
            if prop.count_dtype is None:
                out[prop.name] = self._gather(starts, self.order + prop.dtype)
            else:
                count_type = np.dtype(self.order + prop.count_dtype)
                lengths = self._gather(starts, count_type).astype(np.int64)
                item_type = np.dtype(self.order + prop.dtype)
                first_item = np.repeat(starts + count_type.itemsize, lengths)
                within = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
                out[prop.name] = (lengths, self._gather(first_item + within * item_type.itemsize, item_type))
        return out

    def _gather(self, starts: np.ndarray, dtype) -> np.ndarray:
        dtype = np.dtype(dtype)
        index = starts[:, None] + np.arange(dtype.itemsize)
        return self.buffer[index].reshape(-1).view(dtype)

    def check_end(self) -> None:
        if self.offset != len(self.data):
            raise FormatError(self.path, f"{len(self.data) - self.offset} bytes after the last element "
                                         "(is an element count wrong?)", where=f"byte {self.offset}")


def _read_elements(path: Path, data: bytes, header: _Header, wanted: set[str]) -> dict[str, _Columns]:
    """Read the header's elements up to the last of ``wanted``: name -> columns."""
    body = _AsciiBody(path, data, header) if header.format == "ascii" else _BinaryBody(path, data, header)
    out = {}
    names = [e.name for e in header.elements]
    last = max((i for i, name in enumerate(names) if name in wanted), default=-1)
    for element in header.elements[:last + 1]:
        out[element.name] = body.read(element)
    if last == len(header.elements) - 1:
        body.check_end()
    return out


# --------------------------------------------------------------------------
# Reading frames.
# --------------------------------------------------------------------------


def read_ply(path: str | Path, *, sensor: SensorModel | str | None = None) -> Iterator[RangeFrame]:
    """Yield the one frame of a PLY point grid or Stanford range image.

    Parameters
    ----------
    path : path-like
        An ASCII or binary PLY file with a ``vertex`` element and a grid
        size (``obj_info num_cols`` / ``num_rows`` or ``comment width W
        height H``).
    sensor : SensorModel or str, optional
        The sensor; its grid must match the file's. Default: the sensor the
        file names (``comment rangesurf sensor``), the ``"cyberware"``
        preset for Stanford range images, else an `unknown_sensor`.

    Yields
    ------
    RangeFrame
        ``range`` (H, W) float32 metres, NaN where there was no return;
        ``rays`` from the points. Stanford scans are placed in the virtual
        Cyberware sensor frame (module docstring) and take ``pose`` and
        ``reference_pose`` from a ``*.conf`` beside them that lists them.

    Raises
    ------
    FormatError
        For an empty or truncated file, a malformed header, a missing grid
        size, a vertex count that does not fit the grid, a ``range_grid``
        index out of range, or NaN / Inf where the format allows none. The
        message names the file and the line, element or field.

    Examples
    --------
    >>> frame = next(read_ply("../shared/data/bunny/bun000.ply"))  # doctest: +SKIP
    >>> frame.shape, int(frame.valid.sum())                       # doctest: +SKIP
    ((400, 512), 40256)
    """
    path = Path(path)
    model = None if sensor is None else get_sensor(sensor)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FormatError(path, "no such file") from None
    except IsADirectoryError:
        raise FormatError(path, "is a folder, expected a file") from None
    header = _parse_header(path, data)
    vertex = header.element("vertex")
    if vertex is None:
        raise FormatError(path, "no 'element vertex' in the header; expected the points as vertices", where="header")
    missing = [axis for axis in "xyz" if vertex.property(axis) is None or vertex.property(axis).count_dtype]
    if missing:
        raise FormatError(path, f"element vertex lacks scalar properties {' '.join(missing)}; expected x y z",
                          where=f"line {vertex.line}")
    height, width = _grid_size(path, header)
    notes = _rangesurf_comments(path, header)
    grid = header.element("range_grid")
    stanford = not notes and (
        header.obj_info.get("is_cyberware_data", ("0", 0))[0] == "1"
        or (grid is not None and (height, width) == _CYBERWARE_GRID)
    )

    columns = _read_elements(path, data, header, {"vertex", "range_grid"})
    vertices = np.stack([np.asarray(columns["vertex"][axis], dtype=np.float64) for axis in "xyz"], axis=-1)
    intensity_name = next((n for n in _INTENSITY_NAMES if vertex.property(n) is not None
                           and vertex.property(n).count_dtype is None), None)
    vertex_intensity = None if intensity_name is None else np.asarray(columns["vertex"][intensity_name], np.float64)
    _check_vertices(path, header, vertex, vertices, vertex_intensity, allow_nan=not stanford)

    if grid is not None:
        cell_vertex = _grid_indices(path, header, grid, columns["range_grid"], height, width, len(vertices))
    else:
        if vertex.count != height * width:
            raise FormatError(
                path, f"element vertex has {vertex.count} vertices; a grid of {height} rows x {width} columns "
                      f"without a range_grid needs one vertex per cell ({height * width})",
                where=f"line {vertex.line}",
            )
        cell_vertex = np.arange(height * width)
    has_vertex = cell_vertex >= 0
    intensity = None
    if vertex_intensity is not None:
        intensity = np.full(height * width, np.nan, np.float32)
        intensity[has_vertex] = vertex_intensity[cell_vertex[has_vertex]]
        intensity = intensity.reshape(height, width)

    pose = notes.get("T_world_sensor")
    reference_pose = notes.get("reference_T_world_sensor")
    if stanford:
        # p_s = R (p - o): the virtual Cyberware sensor frame. R is diagonal
        # (+-1), so the product is exactly a sign flip per axis.
        vertices = (vertices - _CYBERWARE_ORIGIN) * np.diagonal(_CYBERWARE_ROTATION)
        world_from_scan = _find_stanford_pose(path)
        if world_from_scan is not None:
            pose = reference_pose = world_from_scan @ _cyberware_scan_from_sensor()
    model = _sensor_for(path, model, notes, stanford, height, width)
    yield _frame_from_cells(
        vertices, cell_vertex, model, intensity=intensity, pose=pose, reference_pose=reference_pose,
        timestamp=notes.get("timestamp", 0.0), source=str(path),
    )


def _frame_from_cells(vertices: np.ndarray, cell_vertex: np.ndarray, sensor: SensorModel, **fields) -> RangeFrame:
    """`RangeFrame.from_points` of the grid whose cell ``i`` holds ``vertices[cell_vertex[i]]`` (none if -1).

    A range grid usually has far fewer vertices than cells (the bunny scans
    fill a fifth of theirs), so ranges and rays are computed per vertex and
    then scattered, with the sensor's rays elsewhere. The result is the
    same, bit for bit, as from_points on the full grid of points (the tests
    compare the two); a sensor without a projection fills its rays from
    neighbouring cells, which from_points does.
    """
    height, width = sensor.shape
    has_vertex = cell_vertex >= 0
    if sensor.projection is None:
        points = np.full((height * width, 3), np.nan)
        points[has_vertex] = vertices[cell_vertex[has_vertex]]
        return RangeFrame.from_points(points.reshape(height, width, 3), sensor=sensor, **fields)
    with np.errstate(invalid="ignore"):
        distance = np.linalg.norm(vertices, axis=-1)
        usable = np.isfinite(distance) & (distance > 0)  # NaN and 0 0 0 vertices are no return
        directions = vertices / np.where(usable, distance, 1.0)[:, None]
    cells = np.flatnonzero(has_vertex)
    cells = cells[usable[cell_vertex[cells]]]  # the cells with a return
    source = cell_vertex[cells]
    range_image = np.full(height * width, np.nan, dtype=np.float32)
    range_image[cells] = distance[source]
    rays = sensor.rays().reshape(-1, 3).copy()
    rays[cells] = directions[source]
    return RangeFrame(rays=rays.reshape(height, width, 3), range=range_image.reshape(height, width), sensor=sensor,
                      **fields)


def _grid_size(path: Path, header: _Header) -> tuple[int, int]:
    size = {}
    for key in ("num_cols", "num_rows"):
        if key in header.obj_info:
            value, line = header.obj_info[key]
            if not re.fullmatch(r"\d+", value) or int(value) < 1:
                raise FormatError(path, f"obj_info {key} must be a positive integer, got {value!r}", where=f"line {line}")
            size[key] = int(value)
    if len(size) == 2:
        return size["num_rows"], size["num_cols"]
    for text, _ in header.comments:
        match = re.fullmatch(r"width\s+(\d+)\s+height\s+(\d+)", text)
        if match and int(match.group(1)) > 0 and int(match.group(2)) > 0:
            return int(match.group(2)), int(match.group(1))
    raise FormatError(
        path, "no grid size: a PLY must carry its grid size (obj_info num_cols / num_rows, or "
              "'comment width W height H') to load as an organized frame", where="header",
    )


def _check_vertices(path: Path, header: _Header, vertex: _Element, vertices: np.ndarray,
                    intensity: np.ndarray | None, *, allow_nan: bool) -> None:
    if np.isfinite(vertices).all() and (intensity is None or not np.isinf(intensity).any()):
        return  # the usual case, without the per-vertex reductions below
    bad = np.isinf(vertices).any(axis=1)
    if intensity is not None:
        bad |= np.isinf(intensity)
    if not allow_nan:
        bad |= np.isnan(vertices).any(axis=1)
    if bad.any():
        index = int(np.argmax(bad))
        expectation = "finite numbers (Stanford range data has no NaN)" if not allow_nan else "finite numbers or NaN"
        raise FormatError(path, f"vertex {index} is {vertices[index].tolist()}; expected {expectation}",
                          where=_vertex_where(header, vertex, index))


def _vertex_where(header: _Header, vertex: _Element, index: int) -> str:
    if header.format == "ascii" and header.elements[0] is vertex:
        return f"line {header.lines + 1 + index}"
    return f"element vertex, record {index}"


def _grid_indices(path: Path, header: _Header, grid: _Element, column, height: int, width: int,
                  vertex_count: int) -> np.ndarray:
    """Vertex index of every grid cell, -1 where the cell is empty."""
    if grid.count != height * width:
        raise FormatError(path, f"element range_grid has {grid.count} cells; expected num_rows x num_cols = "
                                f"{height} x {width} = {height * width}", where=f"line {grid.line}")
    if not (len(grid.properties) == 1 and grid.properties[0].count_dtype is not None):
        raise FormatError(path, "element range_grid must have one list property (vertex_indices)",
                          where=f"line {grid.line}")
    lengths, items = column[grid.properties[0].name]
    cells = np.full(grid.count, -1, dtype=np.int64)
    filled = lengths > 0
    # A cell lists its vertex first; Stanford cells list one at most.
    first_item = (np.cumsum(lengths) - lengths)[filled]
    index = items[first_item]
    bad = (index < 0) | (index >= vertex_count) | (index != np.round(index))
    if bad.any():
        cell = int(np.flatnonzero(filled)[np.argmax(bad)])
        if header.format == "ascii":
            before = sum(e.count for e in header.elements[:header.elements.index(grid)])
            where = f"line {header.lines + 1 + before + cell}"
        else:
            where = f"element range_grid, record {cell}"
        raise FormatError(
            path, f"range_grid cell {cell} (row {cell // width}, column {cell % width}) refers to vertex "
                  f"{index[np.argmax(bad)]:g}; expected an index in 0..{vertex_count - 1}", where=where,
        )
    cells[filled] = index.astype(np.int64)
    return cells


def _rangesurf_comments(path: Path, header: _Header) -> dict:
    """What rangesurf's own comment lines say (empty for other files)."""
    notes: dict = {}
    for text, line in header.comments:
        if not text.startswith(_COMMENT_PREFIX):
            continue
        key, _, value = text[len(_COMMENT_PREFIX):].partition(" ")
        value = value.strip()
        where = f"line {line}"
        try:
            if key in ("T_world_sensor", "reference_T_world_sensor"):
                numbers = np.array(value.split(), dtype=np.float64)
                if numbers.shape != (16,):
                    raise ValueError(f"expected 16 numbers (a row-major 4x4 matrix), got {len(numbers)}")
                notes[key] = check_rigid_transform(numbers.reshape(4, 4), key)
            elif key == "timestamp":
                notes[key] = float(value)
                if not math.isfinite(notes[key]):
                    raise ValueError(f"expected a finite number of seconds, got {value!r}")
            elif key == "sensor":
                notes[key] = value
            elif key == "sensor_model":
                notes[key] = SensorModel.from_dict(json.loads(value))
        except (ValueError, TypeError, KeyError) as error:
            raise FormatError(path, f"bad 'comment rangesurf {key}': {error}", where=where) from None
    return notes


def _sensor_for(path: Path, model: SensorModel | None, notes: dict, stanford: bool,
                height: int, width: int) -> SensorModel:
    if model is not None:
        if model.shape != (height, width):
            raise FormatError(path, f"grid {height}x{width} (rows x columns) does not match sensor "
                                    f"{model.name!r} grid {model.height}x{model.width}")
        return model
    stored = notes.get("sensor_model")
    if stored is not None and stored.shape == (height, width):
        return stored
    name = notes.get("sensor")
    if name:
        try:
            preset = get_sensor(name)
        except ValueError:
            return unknown_sensor(height, width, name=name)
        return preset.with_grid(height, width)
    if stanford:
        return get_sensor("cyberware").with_grid(height, width)
    return unknown_sensor(height, width)


# --------------------------------------------------------------------------
# Stanford registration files.
# --------------------------------------------------------------------------


def read_stanford_conf(path: str | Path) -> dict[str, np.ndarray]:
    """Read a Stanford ``.conf`` registration file: scan name -> ``T_world_scan``.

    Parameters
    ----------
    path : path-like
        Lines ``bmesh FILE tx ty tz qx qy qz qw`` (``mesh`` also accepted);
        ``camera`` lines (a viewing camera) and blank lines are skipped.

    Returns
    -------
    dict of str to (4, 4) float64
        ``T_world_scan`` of each listed file: with ``R`` the rotation of the
        quaternion (scalar last), a scan point maps to the common frame as
        ``R.T @ p + t``. These act on the scan's own coordinates; `read_ply`
        composes them with the virtual sensor frame.

    Raises
    ------
    FormatError
        For an unknown keyword, a line without 7 finite numbers after the
        file name, or a zero quaternion.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise FormatError(path, "no such file") from None
    poses = {}
    for line_number, line in enumerate(text.splitlines(), start=1):
        words = line.split()
        where = f"line {line_number}"
        if not words or words[0].startswith("#") or words[0] == "camera":
            continue
        if words[0] not in ("bmesh", "mesh"):
            raise FormatError(path, f"unknown keyword {words[0]!r}; expected 'bmesh FILE tx ty tz qx qy qz qw' "
                                    "or 'camera ...'", where=where)
        if len(words) != 9:
            raise FormatError(path, f"expected 'bmesh FILE tx ty tz qx qy qz qw', got {line.strip()[:80]!r}", where=where)
        try:
            numbers = np.array(words[2:], dtype=np.float64)
        except ValueError:
            raise FormatError(path, f"expected 7 numbers after the file name, got {line.strip()[:80]!r}",
                              where=where) from None
        quaternion_norm = np.linalg.norm(numbers[3:])
        if not np.all(np.isfinite(numbers)) or quaternion_norm < 1e-9:
            raise FormatError(path, "expected a finite translation and a non-zero quaternion", where=where)
        transform = np.eye(4)
        transform[:3, :3] = Rotation.from_quat(numbers[3:] / quaternion_norm).as_matrix().T
        transform[:3, 3] = numbers[:3]
        poses[words[1]] = transform
    return poses


def _find_stanford_pose(path: Path) -> np.ndarray | None:
    """``T_world_scan`` from the first ``*.conf`` beside ``path`` that lists it."""
    for conf in sorted(path.parent.glob("*.conf")):
        poses = read_stanford_conf(conf)
        if path.name in poses:
            return poses[path.name]
    return None


# --------------------------------------------------------------------------
# Writing.
# --------------------------------------------------------------------------


def write_ply(path: str | Path, frame: RangeFrame) -> None:
    """Write a frame as a binary little-endian PLY with a ``range_grid``.

    The ``vertex`` element holds the points with a return (``x y z`` float32
    in the sensor frame, metres, and ``intensity`` float32 when the frame has
    one); the ``range_grid`` element lists each cell's vertex, so the grid
    reads back. The sensor, poses and timestamp go into ``comment rangesurf``
    lines (module docstring). Written atomically.

    Parameters
    ----------
    path : path-like
    frame : RangeFrame

    Notes
    -----
    Rays of cells without a return are not stored; on reading they come
    from the sensor's projection (or the nearest cell with a return).

    Examples
    --------
    >>> import numpy as np, rangesurf as rs
    >>> sensor = rs.get_sensor("sr3000")
    >>> frame = rs.RangeFrame(rays=sensor.rays(), range=np.full(sensor.shape, 2.0, np.float32), sensor=sensor)
    >>> write_ply("frame.ply", frame)                         # doctest: +SKIP
    """
    height, width = frame.shape
    valid = frame.valid.reshape(-1)
    points = frame.points.reshape(-1, 3)[valid]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if frame.intensity is not None:
        fields.append(("intensity", "<f4"))
    vertices = np.empty(len(points), dtype=fields)
    for axis, name in enumerate("xyz"):
        vertices[name] = points[:, axis]
    if frame.intensity is not None:
        vertices["intensity"] = frame.intensity.reshape(-1)[valid]

    # range_grid records: b"\x00" for an empty cell, b"\x01" + int32 index.
    record_start = np.arange(valid.size) + 4 * (np.cumsum(valid) - valid)
    grid = np.zeros(valid.size + 4 * len(points), dtype=np.uint8)
    grid[record_start] = valid
    index_bytes = np.arange(len(points), dtype="<i4").view(np.uint8).reshape(-1, 4)
    grid[(record_start[valid] + 1)[:, None] + np.arange(4)] = index_bytes

    lines = ["ply", "format binary_little_endian 1.0", f"comment {_COMMENT_PREFIX}sensor {frame.sensor.name}"]
    lines.append(f"comment {_COMMENT_PREFIX}sensor_model {json.dumps(frame.sensor.to_dict(), separators=(',', ':'))}")
    for key, transform in (("T_world_sensor", frame.pose), ("reference_T_world_sensor", frame.reference_pose)):
        if transform is not None:
            lines.append(f"comment {_COMMENT_PREFIX}{key} " + " ".join(repr(float(v)) for v in transform.ravel()))
    lines.append(f"comment {_COMMENT_PREFIX}timestamp {frame.timestamp!r}")
    lines += [f"obj_info num_cols {width}", f"obj_info num_rows {height}", f"element vertex {len(points)}"]
    lines += [f"property float {name}" for name, _ in fields]
    lines += [f"element range_grid {height * width}", "property list uchar int vertex_indices"]
    _write_binary(path, lines, vertices, grid)


def _write_binary(path: str | Path, header: list[str], *blocks: np.ndarray) -> None:
    """Header lines (``end_header`` added) and binary element blocks, written atomically."""
    with atomic_write(path, "wb") as stream:
        stream.write(("\n".join([*header, "end_header"]) + "\n").encode("utf-8"))
        for block in blocks:
            stream.write(block.tobytes())


def write_mesh_ply(path: str | Path, surfaces: list) -> None:
    """Write triangulated surfaces as one binary little-endian PLY mesh, atomically.

    Vertex properties: ``x y z nx ny nz`` (float32, metres), one float32
    column per uncertainty level ``ul1 ul2 ul3 ul4`` (metres along the
    normal, NaN where a surface does not carry that level) and ``surface``
    (int32, 1-based index of the surface in ``surfaces``); faces as
    ``vertex_indices`` lists. Opens in MeshLab, CloudCompare, Open3D and trimesh.

    Parameters
    ----------
    path : path-like
    surfaces : list of rangesurf.mesh.Surface

    Examples
    --------
    >>> import numpy as np
    >>> from rangesurf.mesh import Surface
    >>> square = Surface(np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1.0]]), [[0, 1, 2], [0, 2, 3]],
    ...                  np.tile([0, 0, -1.0], (4, 1)), np.full((4, 2), -1), uncertainty={"UL1": np.full(4, 0.01)})
    >>> write_mesh_ply("model.ply", [square])                          # doctest: +SKIP
    """
    from rangesurf.mesh import UNCERTAINTY_LEVELS

    fields = [(name, "<f4") for name in ("x", "y", "z", "nx", "ny", "nz")]
    fields += [(level.lower(), "<f4") for level in UNCERTAINTY_LEVELS] + [("surface", "<i4")]
    total = sum(surface.n_vertices for surface in surfaces)
    vertices = np.empty(total, dtype=fields)
    faces = []
    start = 0
    for index, surface in enumerate(surfaces, start=1):
        rows = slice(start, start + surface.n_vertices)
        for axis, name in enumerate("xyz"):
            vertices[name][rows] = surface.vertices[:, axis]
            vertices["n" + name][rows] = surface.normals[:, axis]
        for level in UNCERTAINTY_LEVELS:
            vertices[level.lower()][rows] = surface.uncertainty.get(level, np.nan)
        vertices["surface"][rows] = index
        faces.append(surface.faces.astype(np.int64) + start)
        start += surface.n_vertices
    face_array = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
    records = np.empty(len(face_array), dtype=[("count", "u1"), ("indices", "<i4", (3,))])
    records["count"] = 3
    records["indices"] = face_array
    lines = ["ply", "format binary_little_endian 1.0", "comment rangesurf model: uncertainty levels in metres along the normal",
             f"element vertex {total}"]
    lines += [f"property {'int' if kind == '<i4' else 'float'} {name}" for name, kind in fields]
    lines += [f"element face {len(face_array)}", "property list uchar int vertex_indices"]
    _write_binary(path, lines, vertices, records)
