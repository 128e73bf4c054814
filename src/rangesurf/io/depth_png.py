"""16-bit depth PNGs with pinhole intrinsics in a JSON file beside them.

A depth PNG (Kinect, RealSense, TUM RGB-D, Open3D) stores z-depth, the
distance along the optical axis, not range along the ray; pixel value 0
means no return. Its intrinsics come from, in this order:

1. ``<stem>.json`` beside the PNG (what `write_depth_png` writes),
2. ``intrinsics.json``, then ``camera_intrinsics.json`` in the same folder.

Two JSON layouts are accepted::

    {"width": 640, "height": 480, "fx": 525.0, "fy": 525.0,
     "cx": 319.5, "cy": 239.5, "depth_scale": 1000}

    {"width": 640, "height": 480,                      # Open3D
     "intrinsic_matrix": [525, 0, 0, 0, 525, 0, 319.5, 239.5, 1]}

``intrinsic_matrix`` is Open3D's column-major 3x3 matrix. ``depth_scale``
is PNG units per metre (default 1000: millimetres). Optional keys:
``sensor`` (a name), ``frame_rate``, ``timestamp`` (seconds) and ``pose``
(4x4 ``T_world_sensor``, row-major nested lists).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from rangesurf.frame import SENSORS, PinholeProjection, RangeFrame, SensorModel, check_rigid_transform, get_sensor
from rangesurf.io._common import FormatError, atomic_write

__all__ = ["read_depth_png", "write_depth_png", "pinhole_sensor", "z_depth_to_range", "INTRINSICS_NAMES"]

# Folder-wide intrinsics files, tried after <stem>.json.
INTRINSICS_NAMES = ("intrinsics.json", "camera_intrinsics.json")
DEFAULT_DEPTH_SCALE = 1000.0
# Largest depth image read (pixels): 4096 x 4096, far beyond any range sensor.
_MAX_PIXELS = 4096 * 4096
_UINT16_MAX = 65535
# Depth cameras run near this rate; the value only informs timing estimates.
_DEFAULT_FRAME_RATE = 30.0


def pinhole_sensor(
    projection: PinholeProjection,
    height: int,
    width: int,
    *,
    name: str | None = None,
    frame_rate: float = _DEFAULT_FRAME_RATE,
) -> SensorModel:
    """The sensor of a depth camera known only by its intrinsics.

    Returns the preset with identical intrinsics and grid when there is one
    (it carries a real noise model), else a generic model named ``name``
    (default ``"depth-camera"``) with no range limits and no noise model.
    """
    if name is not None and name.lower() in SENSORS:
        preset = SENSORS[name.lower()]
        if preset.projection == projection and preset.shape == (height, width):
            return preset
    for preset in SENSORS.values():
        if preset.projection == projection and preset.shape == (height, width) and name is None:
            return preset
    if name is not None and name.lower() in SENSORS:
        # A preset's name on other intrinsics would mislead later lookups.
        name = None
    return SensorModel(
        name=name or "depth-camera", width=width, height=height, projection=projection,
        min_range=0.0, max_range=math.inf, frame_rate=frame_rate,
        description="depth camera described by pinhole intrinsics",
    )


def z_depth_to_range(depth: np.ndarray, projection: PinholeProjection) -> np.ndarray:
    """Convert z-depth ``(H, W)`` metres to range along each pixel's ray, float32.

    A pixel's unnormalised direction ``d`` has ``d_z = 1``, so the point is
    ``z * d`` and its range ``z * |d|``. NaN stays NaN.
    """
    height, width = depth.shape
    stretch = np.linalg.norm(projection.directions(height, width), axis=-1)
    return (depth.astype(np.float64) * stretch).astype(np.float32)


# --------------------------------------------------------------------------
# Reading.
# --------------------------------------------------------------------------


def read_depth_png(path: str | os.PathLike, *, sensor: str | SensorModel | None = None) -> Iterator[RangeFrame]:
    """Yield the one frame of a 16-bit depth PNG.

    Parameters
    ----------
    path : str or path-like
        A single-channel uint16 PNG of z-depth in ``1 / depth_scale``
        metres; 0 is no return.
    sensor : str or SensorModel, optional
        A sensor (or preset name) with a `PinholeProjection` on the PNG's grid; it replaces
        the intrinsics of the JSON file, which is then optional (its
        ``depth_scale`` is still used; default 1000).

    Yields
    ------
    RangeFrame
        ``range`` (H, W) float32 metres along each ray, NaN where the PNG is
        0. No intensity. ``pose`` and ``timestamp`` from the JSON if given.

    Raises
    ------
    FormatError
        The PNG is not uint16 single-channel, no intrinsics JSON is found,
        or the JSON is malformed or disagrees with the PNG's size.
    """
    path = Path(path)
    sensor = None if sensor is None else get_sensor(sensor)
    depth_units = _read_png(path)
    height, width = depth_units.shape

    json_path = _find_intrinsics(path)
    if json_path is None and (sensor is None or not isinstance(sensor.projection, PinholeProjection)):
        looked = ", ".join([path.with_suffix(".json").name, *INTRINSICS_NAMES])
        raise FormatError(
            path, f"no intrinsics JSON found beside the PNG (looked for {looked}); "
            "write one or pass sensor= with a pinhole projection", where="intrinsics",
        )
    info = _read_intrinsics(json_path, height, width, need_projection=sensor is None) if json_path else {}
    depth_scale = info.get("depth_scale", DEFAULT_DEPTH_SCALE)

    if sensor is not None:
        if not isinstance(sensor.projection, PinholeProjection):
            raise FormatError(path, f"sensor {sensor.name!r} has no pinhole projection to turn z-depth into range")
        if sensor.shape != (height, width):
            raise FormatError(path, f"sensor {sensor.name!r} grid {sensor.shape} does not match the PNG's {(height, width)}")
        frame_sensor = sensor
    else:
        frame_sensor = pinhole_sensor(
            info["projection"], height, width,
            name=info.get("sensor"), frame_rate=info.get("frame_rate", _DEFAULT_FRAME_RATE),
        )

    depth = np.where(depth_units > 0, depth_units / depth_scale, np.nan)
    range_image = z_depth_to_range(depth, frame_sensor.projection)
    yield RangeFrame(
        rays=frame_sensor.rays(), range=range_image, sensor=frame_sensor, pose=info.get("pose"),
        timestamp=info.get("timestamp", 0.0), source=str(path),
    )


def _read_png(path: Path) -> np.ndarray:
    encoded = np.fromfile(path, dtype=np.uint8)
    if encoded.size == 0:
        raise FormatError(path, "empty file; expected a 16-bit depth PNG")
    # The header first (IHDR: width, height, bit depth, colour type right after the signature): a
    # hostile one would otherwise have the decoder allocate gigabytes before the pixel format is seen.
    if encoded.size >= 26 and bytes(encoded[12:16]) == b"IHDR":
        width, height = int.from_bytes(bytes(encoded[16:20]), "big"), int.from_bytes(bytes(encoded[20:24]), "big")
        bit_depth, colour_type = int(encoded[24]), int(encoded[25])
        if width * height > _MAX_PIXELS:
            raise FormatError(path, f"declares a {width} x {height} image; depth images up to {_MAX_PIXELS} pixels are read",
                              where="IHDR")
        if (bit_depth, colour_type) != (16, 0):
            raise FormatError(path, f"expected a single-channel 16-bit depth image, the header declares bit depth "
                                    f"{bit_depth} and colour type {colour_type}", where="IHDR")
    image = cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FormatError(path, "cannot decode the image; expected a 16-bit depth PNG")
    channels = 1 if image.ndim == 2 else image.shape[2]
    if image.dtype != np.uint16 or channels != 1:
        raise FormatError(
            path, f"expected a single-channel uint16 depth image, got dtype {image.dtype} with {channels} channel(s)",
            where="pixel format",
        )
    return image


def _find_intrinsics(path: Path) -> Path | None:
    for candidate in (path.with_suffix(".json"), *(path.parent / name for name in INTRINSICS_NAMES)):
        if candidate.is_file():
            return candidate
    return None


def _read_intrinsics(json_path: Path, height: int, width: int, *, need_projection: bool) -> dict[str, Any]:
    """Parse an intrinsics JSON; returns projection, depth_scale and optional extras."""
    try:
        data = json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise FormatError(json_path, f"not a readable JSON file ({error})") from None
    if not isinstance(data, dict):
        raise FormatError(json_path, f"expected a JSON object, got {type(data).__name__}")

    def number(key: str, *, default: float | None = None) -> float:
        if key not in data:
            if default is not None:
                return default
            raise FormatError(json_path, "missing number", where=f"field '{key}'")
        value = data[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise FormatError(json_path, f"expected a finite number, got {value!r}", where=f"field '{key}'")
        return float(value)

    info: dict[str, Any] = {}
    info["depth_scale"] = number("depth_scale", default=DEFAULT_DEPTH_SCALE)
    if info["depth_scale"] <= 0:
        raise FormatError(
            json_path, f"must be > 0 (units per metre), got {info['depth_scale']}", where="field 'depth_scale'",
        )

    for key, expected in (("width", width), ("height", height)):
        if key in data and number(key) != expected:
            raise FormatError(
                json_path, f"intrinsics are for {key} {data[key]}, but the PNG's {key} is {expected}",
                where=f"field '{key}'",
            )

    if need_projection or "intrinsic_matrix" in data or "fx" in data:
        if "intrinsic_matrix" in data:
            matrix = data["intrinsic_matrix"]
            if not (isinstance(matrix, list) and len(matrix) == 9 and all(isinstance(v, (int, float)) for v in matrix)):
                raise FormatError(
                    json_path, "expected 9 numbers (a column-major 3x3 matrix)", where="field 'intrinsic_matrix'",
                )
            # Open3D stores the matrix column-major: transpose to row-major K.
            k = np.asarray(matrix, dtype=np.float64).reshape(3, 3).T
            values = {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2]}
        else:
            values = {key: number(key) for key in ("fx", "fy", "cx", "cy")}
        try:
            info["projection"] = PinholeProjection(**{key: float(v) for key, v in values.items()})
        except ValueError as error:
            raise FormatError(
                json_path, str(error), where="field 'intrinsic_matrix'" if "intrinsic_matrix" in data else "field 'fx'",
            ) from None

    if "sensor" in data:
        if not isinstance(data["sensor"], str) or not data["sensor"]:
            raise FormatError(json_path, f"expected a sensor name, got {data['sensor']!r}", where="field 'sensor'")
        info["sensor"] = data["sensor"]
    if "frame_rate" in data:
        info["frame_rate"] = number("frame_rate")
        if info["frame_rate"] <= 0:
            raise FormatError(json_path, f"must be > 0, got {info['frame_rate']}", where="field 'frame_rate'")
    if "timestamp" in data:
        info["timestamp"] = number("timestamp")
    if data.get("pose") is not None:
        try:
            info["pose"] = check_rigid_transform(np.asarray(data["pose"], dtype=np.float64), "pose")
        except (ValueError, TypeError) as error:
            raise FormatError(json_path, str(error), where="field 'pose'") from None
    return info


# --------------------------------------------------------------------------
# Writing.
# --------------------------------------------------------------------------


def write_depth_png(path: str | os.PathLike, frame: RangeFrame, *, depth_scale: float = DEFAULT_DEPTH_SCALE) -> None:
    """Write a frame as a 16-bit depth PNG plus ``<stem>.json``, each atomically.

    Parameters
    ----------
    path : str or path-like
        Output PNG; the intrinsics go to the same name with ``.json``.
    frame : RangeFrame
        Its sensor needs a `PinholeProjection`. z-depth is
        ``range * ray_z`` rounded to ``1 / depth_scale`` metres; NaN becomes
        0. Intensity and ``reference_pose`` are not stored.
    depth_scale : float
        PNG units per metre (1000: millimetres, up to 65.535 m).

    Notes
    -----
    Only z-depth is stored: reading puts every point back on the sensor's
    pinhole ray, so frames whose rays differ from the projection (built
    from points) come back with the projection's rays.

    Raises
    ------
    ValueError
        The sensor has no pinhole projection, a return lies behind the
        camera, or a depth exceeds ``65535 / depth_scale`` metres or rounds
        to 0 (which would read back as no return).

    Examples
    --------
    >>> write_depth_png("depth/000000.png", frame)   # doctest: +SKIP
    """
    if not isinstance(frame, RangeFrame):
        raise TypeError(f"write_depth_png expects a RangeFrame, got {type(frame).__name__}")
    path = Path(path)
    projection = frame.sensor.projection
    if not isinstance(projection, PinholeProjection):
        kind = "no projection" if projection is None else f"a {projection.kind} projection"
        raise ValueError(f"depth PNG needs a sensor with a pinhole projection; sensor {frame.sensor.name!r} has {kind}")
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be > 0 (units per metre), got {depth_scale}")

    valid = frame.valid
    depth = frame.range.astype(np.float64) * frame.rays[..., 2].astype(np.float64)
    units = np.where(valid, np.rint(depth * depth_scale), 0.0)
    if (depth[valid] <= 0).any():
        raise ValueError(
            f"{int((depth[valid] <= 0).sum())} returns lie at or behind the camera plane (z <= 0); "
            "a depth PNG cannot hold them",
        )
    if (units > _UINT16_MAX).any():
        raise ValueError(
            f"depth up to {np.nanmax(depth[valid]):.3f} m exceeds the {_UINT16_MAX / depth_scale:.3f} m a 16-bit PNG "
            f"holds at depth_scale={depth_scale:g}; lower depth_scale"
        )
    if (units[valid] == 0).any():
        raise ValueError(
            f"{int((units[valid] == 0).sum())} depths round to 0, which reads back as no return; raise depth_scale"
        )
    ok, encoded = cv2.imencode(".png", units.astype(np.uint16))
    if not ok:
        raise OSError(f"OpenCV could not encode {path} as PNG")

    intrinsics: dict[str, Any] = {
        "width": frame.shape[1], "height": frame.shape[0],
        "fx": projection.fx, "fy": projection.fy, "cx": projection.cx, "cy": projection.cy,
        "depth_scale": depth_scale, "sensor": frame.sensor.name, "frame_rate": frame.sensor.frame_rate,
        "timestamp": frame.timestamp,
        "pose": None if frame.pose is None else frame.pose.tolist(),
    }
    # JSON first: a PNG without its intrinsics would be unreadable.
    with atomic_write(path.with_suffix(".json"), "w") as stream:
        json.dump(intrinsics, stream, indent=2)
        stream.write("\n")
    with atomic_write(path, "wb") as stream:
        stream.write(encoded.tobytes())
