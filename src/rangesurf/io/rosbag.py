"""ROS 1 and ROS 2 bags: organized point clouds and depth images.

Needs the optional ``rosbags`` package (``pip install 'rangesurf[bags]'``);
it is imported only when a bag is read.

Accepted paths: ROS 1 ``.bag`` files, ROS 2 bag folders (with
``metadata.yaml``), and ROS 2 storage files (``.mcap``, ``.db3``). A storage
file inside a bag folder stands for the whole bag (the folder's
``metadata.yaml`` says how messages are compressed), so pass the folder, not
each file, of a bag split into several files.

Supported topics:

``sensor_msgs/msg/PointCloud2``, organized (``height > 1``)
    Float32 or float64 fields ``x y z`` located by their byte offsets,
    honouring ``point_step``, ``row_step`` and ``is_bigendian``; optional
    ``intensity``. A point with a NaN coordinate is no return. Points are kept
    as given, in the cloud's ``header.frame_id``: ROS clouds are usually in a
    body frame (REP 103: x forward, y left, z up), not the optical frame
    (x right, y down, z forward) that rangesurf's presets assume. Rays come
    from the points, so the geometry is right either way.

``sensor_msgs/msg/Image`` of depth (``16UC1``/``mono16`` in millimetres, ``32FC1`` in metres)
    With ``sensor_msgs/msg/CameraInfo`` on the same namespace (the image
    topic's last name replaced by ``camera_info``). Each image uses the
    latest CameraInfo stamped at or before it (the first one for images
    that precede every CameraInfo). Only ``K`` is used: distortion, binning
    and ROI are ignored. 0, NaN and Inf are no return. The z-depth becomes
    range along each pixel's ray.

Frames carry the message's ``header.stamp`` in seconds as ``timestamp`` and
no pose (``/tf`` is not read).
"""

from __future__ import annotations

import bisect
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rangesurf.frame import PinholeProjection, RangeFrame, SensorModel, get_sensor, unknown_sensor
from rangesurf.io._common import FormatError
from rangesurf.io.depth_png import pinhole_sensor, z_depth_to_range

__all__ = ["read_rosbag", "POINT_CLOUD_TYPE", "IMAGE_TYPE", "CAMERA_INFO_TYPE"]

POINT_CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"

# sensor_msgs/PointField datatype constants.
_POINT_FIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
# Depth encodings -> (dtype code, metres per unit or None for float metres).
_DEPTH_ENCODINGS = {"16UC1": ("u2", 1e-3), "mono16": ("u2", 1e-3), "32FC1": ("f4", None)}


def read_rosbag(
    path: str | os.PathLike,
    *,
    sensor: str | SensorModel | None = None,
    topic: str | None = None,
) -> Iterator[RangeFrame]:
    """Yield the range frames of one topic of a ROS bag, in recording order.

    Parameters
    ----------
    path : str or path-like
        A ROS 1 ``.bag``, a ROS 2 bag folder, or a ROS 2 ``.mcap``/``.db3``
        storage file.
    sensor : str or SensorModel, optional
        The sensor (or a preset name), its grid the message's ``(height, width)``. For depth
        images it must have a `PinholeProjection` and replaces CameraInfo.
        By default point clouds get `unknown_sensor` named after the
        ``frame_id``, depth images a pinhole sensor from ``K`` (a preset
        when the intrinsics match one exactly).
    topic : str, optional
        The topic to read. Default: the only supported topic; with several,
        the first message of each decides (depth encodings, ``height > 1``).

    Yields
    ------
    RangeFrame
        ``range`` (H, W) float32 metres, NaN where there is no return;
        ``intensity`` if the cloud has it; ``timestamp`` the header stamp in
        seconds; ``source`` ``"<bag>:<topic>[<index>]"``.

    Raises
    ------
    ImportError
        If ``rosbags`` is not installed.
    FormatError
        Unreadable bag, no or several candidate topics (the message lists
        them), unorganized clouds, missing CameraInfo, malformed messages.

    Examples
    --------
    >>> frames = list(read_rosbag("run.bag", topic="/camera/depth/image_raw"))   # doctest: +SKIP
    """
    any_reader, stores, get_typestore = _import_rosbags()
    path = Path(path)
    sensor = None if sensor is None else get_sensor(sensor)
    location = _bag_location(path)
    ros1 = location.is_file() and location.suffix.lower() == ".bag"
    # Used only when a bag carries no message definitions (old .db3 files).
    typestore = get_typestore(stores.ROS1_NOETIC if ros1 else stores.ROS2_HUMBLE)
    try:
        reader = any_reader([location], default_typestore=typestore)
        reader.open()
    except Exception as error:  # rosbags, sqlite3 and mcap raise many types for a bad file
        raise FormatError(path, f"cannot open as a ROS bag: {error}") from error
    try:
        chosen = _choose_topic(path, reader, topic)
        if reader.topics[chosen].msgtype == POINT_CLOUD_TYPE:
            yield from _read_clouds(path, reader, chosen, sensor)
        else:
            yield from _read_depth_images(path, reader, chosen, sensor)
    finally:
        reader.close()


def _import_rosbags() -> tuple[Any, Any, Any]:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as error:
        raise ImportError("reading ROS bags needs the rosbags package: pip install 'rangesurf[bags]'") from error
    return AnyReader, Stores, get_typestore


def _bag_location(path: Path) -> Path:
    """The path to hand to rosbags: a ``.bag``, a ROS 2 folder or a bare storage file."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise FormatError(path, "folder is not a ROS 2 bag (no metadata.yaml)")
        return path
    if not path.exists():
        raise FormatError(path, "no such file or folder")
    suffix = path.suffix.lower()
    if suffix == ".bag":
        if path.stat().st_size == 0:
            raise FormatError(path, "empty file; expected a ROS 1 bag")
        return path
    if suffix in (".mcap", ".db3"):
        if path.stat().st_size == 0:
            raise FormatError(path, f"empty file; expected a ROS 2 {suffix} storage file")
        if (path.parent / "metadata.yaml").is_file():
            return path.parent
        return path
    raise FormatError(path, f"unknown bag format {suffix!r}; expected .bag, .mcap, .db3 or a ROS 2 bag folder")


# --------------------------------------------------------------------------
# Topic selection.
# --------------------------------------------------------------------------


def _choose_topic(path: Path, reader: Any, topic: str | None) -> str:
    types = {name: info.msgtype for name, info in reader.topics.items()}
    candidates = sorted(name for name, msgtype in types.items() if msgtype in (POINT_CLOUD_TYPE, IMAGE_TYPE))
    supported = "organized sensor_msgs/PointCloud2 or depth sensor_msgs/Image (16UC1, 32FC1)"
    if topic is not None:
        if topic not in types:
            raise FormatError(
                path,
                f"no such topic; range topics: {_describe(candidates, types)}; "
                f"all topics: {', '.join(sorted(types)) or 'none'}",
                where=f"topic '{topic}'",
            )
        if topic not in candidates:
            raise FormatError(path, f"has type {types[topic]}; expected {supported}", where=f"topic '{topic}'")
        return topic
    if not candidates:
        raise FormatError(
            path, f"no {supported} topic; the bag has: {_describe(sorted(types), types)}",
        )
    if len(candidates) > 1:
        # Several by type: keep those whose first message is range data
        # (a colour image shares the Image type with a depth image).
        usable = _probe_topics(reader, candidates)
        if len(usable) == 1:
            return usable[0]
        listed = usable or candidates
        raise FormatError(path, f"several range topics: {_describe(listed, types)}; pass topic= to choose one")
    return candidates[0]


def _describe(names: list[str], types: dict[str, str]) -> str:
    return ", ".join(f"{name} ({types[name]})" for name in names) or "none"


def _probe_topics(reader: Any, candidates: list[str]) -> list[str]:
    connections = [c for c in reader.connections if c.topic in candidates]
    usable = set()
    seen = set()
    for connection, _, raw in reader.messages(connections=connections):
        if connection.topic in seen:
            continue
        seen.add(connection.topic)
        message = reader.deserialize(raw, connection.msgtype)
        if connection.msgtype == POINT_CLOUD_TYPE and message.height > 1:
            usable.add(connection.topic)
        elif connection.msgtype == IMAGE_TYPE and message.encoding in _DEPTH_ENCODINGS:
            usable.add(connection.topic)
        if len(seen) == len(candidates):
            break
    return sorted(usable)


def _stamp_seconds(message: Any) -> float:
    stamp = message.header.stamp
    return stamp.sec + stamp.nanosec * 1e-9


def _stamp_nanoseconds(message: Any) -> int:
    stamp = message.header.stamp
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _check_sensor(path: Path, sensor: SensorModel, shape: tuple[int, int], where: str) -> None:
    if sensor.shape != shape:
        raise FormatError(
            path, f"sensor {sensor.name!r} grid {sensor.shape} does not match the message's {shape}", where=where,
        )


# --------------------------------------------------------------------------
# Point clouds.
# --------------------------------------------------------------------------


def _read_clouds(path: Path, reader: Any, topic: str, sensor: SensorModel | None) -> Iterator[RangeFrame]:
    connections = [c for c in reader.connections if c.topic == topic]
    sensors: dict[tuple[int, int, str], SensorModel] = {}
    for index, (connection, _, raw) in enumerate(reader.messages(connections=connections)):
        where = f"topic '{topic}', message {index}"
        message = reader.deserialize(raw, connection.msgtype)
        points, intensity = _cloud_arrays(path, message, where)
        shape = points.shape[:2]
        if sensor is not None:
            _check_sensor(path, sensor, shape, where)
            frame_sensor = sensor
        else:
            key = (*shape, message.header.frame_id)
            if key not in sensors:
                sensors[key] = unknown_sensor(*shape, name=message.header.frame_id or "unknown")
            frame_sensor = sensors[key]
        yield RangeFrame.from_points(
            points, sensor=frame_sensor, intensity=intensity, timestamp=_stamp_seconds(message),
            source=f"{path}:{topic}[{index}]",
        )


def _cloud_arrays(path: Path, message: Any, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``(H, W, 3)`` float64 points and ``(H, W)`` float32 intensity (or None) of a PointCloud2."""
    height, width = int(message.height), int(message.width)
    if height <= 1:
        raise FormatError(
            path, f"unorganized cloud (height {height}, width {width}); rangesurf needs an organized cloud (height > 1)",
            where=where,
        )
    fields = {}
    for field_ in message.fields:
        fields.setdefault(field_.name, field_)
    missing = [axis for axis in "xyz" if axis not in fields]
    if missing:
        raise FormatError(path, f"cloud lacks field(s) {', '.join(missing)}; has {', '.join(fields) or 'none'}", where=where)
    order = ">" if message.is_bigendian else "<"
    # Intensity of an unknown datatype is dropped rather than failing the cloud.
    has_intensity = "intensity" in fields and int(fields["intensity"].datatype) in _POINT_FIELD_DTYPES
    wanted = ["x", "y", "z"] + (["intensity"] if has_intensity else [])
    formats = []
    point_step, row_step = int(message.point_step), int(message.row_step)
    for name in wanted:
        code = _POINT_FIELD_DTYPES.get(int(fields[name].datatype))
        if name != "intensity" and code not in ("f4", "f8"):
            raise FormatError(
                path, f"field {name!r} has datatype {fields[name].datatype}; x, y, z must be FLOAT32 (7) or FLOAT64 (8)",
                where=where,
            )
        dtype = np.dtype(order + code)
        if int(fields[name].offset) + dtype.itemsize > point_step:
            raise FormatError(
                path, f"field {name!r} at offset {fields[name].offset} overruns point_step {point_step}", where=where,
            )
        formats.append(dtype)
    if row_step < width * point_step:
        raise FormatError(path, f"row_step {row_step} < width * point_step = {width * point_step}", where=where)
    data = np.asarray(message.data, dtype=np.uint8).ravel()
    needed = (height - 1) * row_step + width * point_step
    if data.size < needed:
        raise FormatError(
            path, f"data truncated: {data.size} bytes, need {needed} for {height} x {width} points", where=where,
        )
    if data.size < height * row_step:
        # The last row may omit its padding.
        data = np.concatenate([data, np.zeros(height * row_step - data.size, np.uint8)])
    rows = np.ascontiguousarray(data[: height * row_step].reshape(height, row_step)[:, : width * point_step])
    record = np.dtype({
        "names": wanted, "formats": formats,
        "offsets": [int(fields[name].offset) for name in wanted], "itemsize": point_step,
    })
    records = rows.view(record).reshape(height, width)
    points = np.stack([records[axis].astype(np.float64) for axis in "xyz"], axis=-1)
    intensity = None
    if has_intensity:
        intensity = records["intensity"].astype(np.float32)
        intensity[~np.isfinite(intensity)] = np.nan
    return points, intensity


# --------------------------------------------------------------------------
# Depth images.
# --------------------------------------------------------------------------


def _read_depth_images(path: Path, reader: Any, topic: str, sensor: SensorModel | None) -> Iterator[RangeFrame]:
    if sensor is not None and not isinstance(sensor.projection, PinholeProjection):
        raise FormatError(
            path, f"sensor {sensor.name!r} has no pinhole projection to turn z-depth into range", where=f"topic '{topic}'",
        )
    infos = [] if sensor is not None else _camera_infos(path, reader, topic)
    info_stamps = [stamp for stamp, _, _ in infos]
    sensors: dict[tuple[PinholeProjection, int, int], SensorModel] = {}

    connections = [c for c in reader.connections if c.topic == topic]
    for index, (connection, _, raw) in enumerate(reader.messages(connections=connections)):
        where = f"topic '{topic}', message {index}"
        message = reader.deserialize(raw, connection.msgtype)
        depth = _depth_metres(path, message, where)
        shape = depth.shape
        if sensor is not None:
            _check_sensor(path, sensor, shape, where)
            frame_sensor = sensor
        else:
            # Latest CameraInfo at or before the image; the first for earlier images.
            slot = max(bisect.bisect_right(info_stamps, _stamp_nanoseconds(message)) - 1, 0)
            _, projection, info_shape = infos[slot]
            if info_shape != shape and info_shape != (0, 0):
                raise FormatError(
                    path, f"image is {shape} (height, width) but its CameraInfo says {info_shape}", where=where,
                )
            key = (projection, *shape)
            if key not in sensors:
                sensors[key] = pinhole_sensor(projection, *shape)
            frame_sensor = sensors[key]
        yield RangeFrame(
            rays=frame_sensor.rays(), range=z_depth_to_range(depth, frame_sensor.projection), sensor=frame_sensor,
            timestamp=_stamp_seconds(message), source=f"{path}:{topic}[{index}]",
        )


def _camera_infos(path: Path, reader: Any, topic: str) -> list[tuple[int, PinholeProjection, tuple[int, int]]]:
    """``(stamp_ns, projection, (height, width))`` of every CameraInfo beside ``topic``, by stamp."""
    info_topic = topic.rsplit("/", 1)[0] + "/camera_info"
    connections = [c for c in reader.connections if c.topic == info_topic and c.msgtype == CAMERA_INFO_TYPE]
    if not connections:
        raise FormatError(
            path,
            f"no {CAMERA_INFO_TYPE} on {info_topic} for the depth image's intrinsics; "
            "pass sensor= with a pinhole projection",
            where=f"topic '{topic}'",
        )
    infos = []
    for index, (connection, _, raw) in enumerate(reader.messages(connections=connections)):
        message = reader.deserialize(raw, connection.msgtype)
        # ROS 1 spells the matrix K, ROS 2 k.
        k = np.asarray(message.k if hasattr(message, "k") else message.K, dtype=np.float64)
        where = f"topic '{info_topic}', message {index}"
        if k.shape != (9,) or k[0] == 0 or k[4] == 0:
            raise FormatError(path, f"K has no focal lengths ({k.tolist()}): uncalibrated camera", where=where)
        try:
            projection = PinholeProjection(fx=float(k[0]), fy=float(k[4]), cx=float(k[2]), cy=float(k[5]))
        except ValueError as error:
            raise FormatError(path, str(error), where=where) from None
        infos.append((_stamp_nanoseconds(message), projection, (int(message.height), int(message.width))))
    if not infos:
        raise FormatError(path, "CameraInfo topic has no messages", where=f"topic '{info_topic}'")
    infos.sort(key=lambda info: info[0])
    return infos


def _depth_metres(path: Path, message: Any, where: str) -> np.ndarray:
    """``(H, W)`` float64 z-depth in metres of a depth Image, NaN where no return."""
    encoding = message.encoding
    if encoding not in _DEPTH_ENCODINGS:
        raise FormatError(
            path, f"image encoding {encoding!r} is not depth; expected one of {', '.join(_DEPTH_ENCODINGS)}", where=where,
        )
    code, metres_per_unit = _DEPTH_ENCODINGS[encoding]
    dtype = np.dtype((">" if message.is_bigendian else "<") + code)
    height, width, step = int(message.height), int(message.width), int(message.step)
    if height < 1 or width < 1:
        raise FormatError(path, f"empty image ({height} x {width})", where=where)
    if step < width * dtype.itemsize:
        raise FormatError(path, f"step {step} < width * {dtype.itemsize} bytes = {width * dtype.itemsize}", where=where)
    data = np.asarray(message.data, dtype=np.uint8).ravel()
    needed = (height - 1) * step + width * dtype.itemsize
    if data.size < needed:
        raise FormatError(
            path, f"data truncated: {data.size} bytes, need {needed} for {height} x {width} {encoding}", where=where,
        )
    if data.size < height * step:
        data = np.concatenate([data, np.zeros(height * step - data.size, np.uint8)])
    rows = np.ascontiguousarray(data[: height * step].reshape(height, step)[:, : width * dtype.itemsize])
    values = rows.view(dtype).reshape(height, width).astype(np.float64)
    if metres_per_unit is not None:
        values *= metres_per_unit
    with np.errstate(invalid="ignore"):
        values[~(np.isfinite(values) & (values > 0))] = np.nan
    return values
