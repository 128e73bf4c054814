"""NumPy files: rangesurf's own ``.npz`` frames and bare ``.npy`` grids.

An ``.npz`` frame (``format_version`` 1) holds these arrays:

==================  ====================  ===========================================
name                shape, dtype          meaning
==================  ====================  ===========================================
``format_version``  () int64              1
``range``           (H, W) float32        metres, NaN where there is no return
``rays``            (H, W, 3) float32     unit viewing rays in the sensor frame
``intensity``       (H, W) float32        optional
``pose``            (4, 4) float64        optional, ``T_world_sensor``
``reference_pose``  (4, 4) float64        optional, ``T_world_sensor``
``timestamp``       () float64            seconds
``source``          () str                where the frame came from
``sensor``          () str                JSON of `SensorModel.to_dict`
==================  ====================  ===========================================

Files are read with ``allow_pickle=False``: nothing in them can run code.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rangesurf.frame import SENSORS, RangeFrame, SensorModel, check_rigid_transform, get_sensor, unknown_sensor
from rangesurf.io._common import FormatError, atomic_write

__all__ = ["read_npz", "write_npz", "read_npy", "FORMAT_VERSION"]

FORMAT_VERSION = 1


def write_npz(path: str | os.PathLike, frame: RangeFrame) -> None:
    """Write a frame losslessly as a compressed ``.npz`` archive, atomically.

    Parameters
    ----------
    path : str or path-like
        Output file; written exactly under this name (no ``.npz`` appended).
    frame : RangeFrame
        Every field is stored; see the module docstring for the layout.

    Examples
    --------
    >>> write_npz("frame.npz", frame)          # doctest: +SKIP
    >>> next(read_npz("frame.npz")).shape      # doctest: +SKIP
    (144, 176)
    """
    if not isinstance(frame, RangeFrame):
        raise TypeError(f"write_npz expects a RangeFrame, got {type(frame).__name__}")
    arrays: dict[str, np.ndarray] = {
        "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
        "range": frame.range.astype(np.float32),
        "rays": frame.rays.astype(np.float32),
        "timestamp": np.array(frame.timestamp, dtype=np.float64),
        "source": np.array(frame.source),
        "sensor": np.array(json.dumps(frame.sensor.to_dict())),
    }
    if frame.intensity is not None:
        arrays["intensity"] = frame.intensity.astype(np.float32)
    if frame.pose is not None:
        arrays["pose"] = frame.pose.astype(np.float64)
    if frame.reference_pose is not None:
        arrays["reference_pose"] = frame.reference_pose.astype(np.float64)
    # Writing to an open stream keeps numpy from appending ".npz" to the name.
    with atomic_write(path, "wb") as stream:
        np.savez_compressed(stream, **arrays)


def read_npz(path: str | os.PathLike, *, sensor: str | SensorModel | None = None) -> Iterator[RangeFrame]:
    """Yield the one frame stored in a rangesurf ``.npz`` file.

    Parameters
    ----------
    path : str or path-like
        A file written by `write_npz`. Only ``range`` is required; ``rays``
        may be absent when the sensor (stored or given) has a projection.
    sensor : str or SensorModel, optional
        Overrides the stored sensor (a model or a preset name); its grid must
        match ``range``.

    Yields
    ------
    RangeFrame

    Raises
    ------
    FormatError
        Not an ``.npz`` archive, a missing or malformed array (wrong shape,
        dtype, Inf or values <= 0 in ``range``), or a file written by a newer
        rangesurf; the message names the array (``field 'range'``).
    """
    path = Path(path)
    sensor = None if sensor is None else get_sensor(sensor)
    arrays = load_arrays(path)

    version = _scalar(path, arrays, "format_version", (np.integer,), default=FORMAT_VERSION)
    if int(version) > FORMAT_VERSION:
        raise FormatError(
            path, f"format_version {int(version)} is newer than this rangesurf reads ({FORMAT_VERSION}); upgrade rangesurf",
            where="field 'format_version'",
        )

    if "range" not in arrays:
        raise FormatError(
            path, f"missing array; the archive holds {', '.join(sorted(arrays)) or 'nothing'}", where="field 'range'",
        )
    range_image = _float_array(path, arrays, "range", ndim=2)
    shape = range_image.shape
    if np.isinf(range_image).any():
        raise FormatError(
            path, f"{int(np.isinf(range_image).sum())} cells are Inf; rangesurf marks missing returns with NaN",
            where="field 'range'",
        )
    if (range_image <= 0).any():
        raise FormatError(
            path, f"{int((range_image <= 0).sum())} cells are <= 0; ranges must be positive or NaN", where="field 'range'",
        )

    stored_sensor = _stored_sensor(path, arrays)
    frame_sensor = sensor or stored_sensor or unknown_sensor(*shape)
    if frame_sensor.shape != shape:
        where = "field 'range'" if sensor is not None else "field 'sensor'"
        raise FormatError(
            path, f"sensor {frame_sensor.name!r} grid {frame_sensor.shape} does not match range shape {shape}", where=where,
        )

    if "rays" in arrays:
        rays = _float_array(path, arrays, "rays", ndim=3)
        if rays.shape != shape + (3,):
            raise FormatError(path, f"expected shape {shape + (3,)}, got {rays.shape}", where="field 'rays'")
        if not np.all(np.isfinite(rays)) or not np.allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-3):
            raise FormatError(path, "rays must be finite unit vectors", where="field 'rays'")
    elif frame_sensor.projection is not None:
        rays = frame_sensor.rays()
    else:
        raise FormatError(path, "missing array, and the sensor has no projection to compute rays from", where="field 'rays'")

    intensity = None
    if "intensity" in arrays:
        intensity = _float_array(path, arrays, "intensity", ndim=2)
        if intensity.shape != shape:
            raise FormatError(path, f"expected shape {shape}, got {intensity.shape}", where="field 'intensity'")
        if np.isinf(intensity).any():
            raise FormatError(path, "contains Inf", where="field 'intensity'")

    poses = {name: _pose(path, arrays, name) for name in ("pose", "reference_pose")}
    timestamp = float(_scalar(path, arrays, "timestamp", (np.floating, np.integer), default=0.0))
    if not np.isfinite(timestamp):
        raise FormatError(path, f"expected a finite number, got {timestamp}", where="field 'timestamp'")
    source = str(_scalar(path, arrays, "source", (np.str_,), default="")) or str(path)

    yield RangeFrame(
        rays=rays, range=range_image.astype(np.float32), sensor=frame_sensor, intensity=intensity,
        pose=poses["pose"], timestamp=timestamp, reference_pose=poses["reference_pose"], source=source,
    )


def load_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every named array of an ``.npz`` file, read without pickles; a `FormatError` for anything else.

    Hardened by fuzzing (see below); also how model and pipeline checkpoints are read.
    """
    path = Path(path)
    if path.stat().st_size == 0:
        raise FormatError(path, "empty file; expected a NumPy .npz archive")
    try:
        archive = np.load(path, allow_pickle=False)
        if not isinstance(archive, np.lib.npyio.NpzFile):
            raise FormatError(path, "holds a single array (.npy data), not an .npz archive of named arrays")
        with archive:
            arrays = {name: archive[name] for name in archive.files}
        # A zip member that is not an .npy file comes back as raw bytes (found by fuzzing).
        for name, value in arrays.items():
            if not isinstance(value, np.ndarray):
                raise FormatError(path, "is not a NumPy array inside the archive", where=f"member '{name}'")
        return arrays
    # Fuzzing found np.load failing on hostile bytes with SyntaxError and tokenize.TokenError (the .npy
    # header is parsed as Python), TypeError, OverflowError and MemoryError (huge shapes), and zipfile
    # with NotImplementedError (unknown versions) and RuntimeError (encrypted members): any exception
    # here means the file is not a readable archive.
    except Exception as error:  # noqa: BLE001 - any failure of np.load on untrusted bytes is a bad file
        if isinstance(error, FormatError):
            raise
        # allow_pickle=False turns object arrays into ValueError too.
        raise FormatError(path, f"not a readable NumPy .npz archive ({error})") from None


def _float_array(path: Path, arrays: dict[str, np.ndarray], name: str, *, ndim: int) -> np.ndarray:
    array = arrays[name]
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise FormatError(path, f"expected a numeric array, got dtype {array.dtype}", where=f"field '{name}'")
    if array.ndim != ndim:
        raise FormatError(path, f"expected {ndim}-D array, got shape {array.shape}", where=f"field '{name}'")
    return array.astype(np.float32, copy=False)


def _scalar(path: Path, arrays: dict[str, np.ndarray], name: str, kinds: tuple[type, ...], *, default: Any) -> Any:
    if name not in arrays:
        return default
    array = arrays[name]
    if array.shape != () or not any(np.issubdtype(array.dtype, kind) for kind in kinds):
        expected = " or ".join(kind.__name__ for kind in kinds)
        raise FormatError(
            path, f"expected a scalar ({expected}), got dtype {array.dtype} shape {array.shape}", where=f"field '{name}'",
        )
    return array[()]


def _pose(path: Path, arrays: dict[str, np.ndarray], name: str) -> np.ndarray | None:
    if name not in arrays:
        return None
    try:
        return check_rigid_transform(arrays[name], name)
    except ValueError as error:
        raise FormatError(path, str(error), where=f"field '{name}'") from None


def _stored_sensor(path: Path, arrays: dict[str, np.ndarray]) -> SensorModel | None:
    if "sensor" not in arrays:
        return None
    text = _scalar(path, arrays, "sensor", (np.str_,), default="")
    try:
        return SensorModel.from_dict(json.loads(str(text)))
    except (ValueError, TypeError, KeyError) as error:
        raise FormatError(path, f"not a valid sensor description ({error})", where="field 'sensor'") from None


def read_npy(path: str | os.PathLike, *, sensor: str | SensorModel | None = None) -> Iterator[RangeFrame]:
    """Yield the frame stored as a bare ``.npy`` array.

    Parameters
    ----------
    path : str or path-like
        Either a range image ``(H, W)`` in metres along each ray, or an
        organized point grid ``(H, W, 3)`` in metres in the sensor frame.
    sensor : str or SensorModel, optional
        A model or a preset name. For a range image: the sensor giving the rays; it needs a projection
        and an ``(H, W)`` grid. Without it the one preset with an ``(H, W)``
        grid is used; if no preset or several match, pass ``sensor=``. For a
        point grid: optional (default `unknown_sensor`, rays from points).

    Yields
    ------
    RangeFrame
        Timestamp 0, no pose.

    Notes
    -----
    In a range image, NaN, +-Inf, zero and negative values all mean "no
    return" and become NaN: bare arrays from other tools mark missing
    returns in all these ways. In a point grid, a point with any NaN or
    Inf coordinate, or at the origin, is no return.

    Raises
    ------
    FormatError
        Not an ``.npy`` file, a non-numeric array, an unsupported shape, or
        no sensor to give a range image its rays.
    """
    path = Path(path)
    sensor = None if sensor is None else get_sensor(sensor)
    if path.stat().st_size == 0:
        raise FormatError(path, "empty file; expected a NumPy .npy array")
    try:
        array = np.load(path, allow_pickle=False)
    except Exception as error:  # noqa: BLE001 - any failure of np.load on untrusted bytes is a bad file
        raise FormatError(path, f"not a readable NumPy .npy array ({error})") from None
    if not isinstance(array, np.ndarray):
        raise FormatError(path, "holds an .npz archive; name it .npz to read it as a rangesurf frame")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise FormatError(path, f"expected a numeric array, got dtype {array.dtype}")

    if array.ndim == 3 and array.shape[2] == 3:
        grid_sensor = sensor
        if grid_sensor is not None and grid_sensor.shape != array.shape[:2]:
            raise FormatError(
                path, f"sensor {grid_sensor.name!r} grid {grid_sensor.shape} does not match point grid {array.shape[:2]}",
            )
        with np.errstate(invalid="ignore"):
            points = np.where(np.isfinite(array).all(axis=-1, keepdims=True), array.astype(np.float64), np.nan)
        yield RangeFrame.from_points(points, sensor=grid_sensor, source=str(path))
        return
    if array.ndim != 2:
        raise FormatError(path, f"expected a range image (H, W) or a point grid (H, W, 3), got shape {array.shape}")

    shape = array.shape
    range_sensor = sensor if sensor is not None else _preset_for_grid(path, shape)
    if range_sensor.shape != shape:
        raise FormatError(path, f"sensor {range_sensor.name!r} grid {range_sensor.shape} does not match range image {shape}")
    if range_sensor.projection is None:
        raise FormatError(
            path,
            f"sensor {range_sensor.name!r} has no projection, so a range image has no rays; save points (H, W, 3) instead",
        )
    range_image = array.astype(np.float32)
    with np.errstate(invalid="ignore"):
        range_image[~(np.isfinite(range_image) & (range_image > 0))] = np.nan
    yield RangeFrame(rays=range_sensor.rays(), range=range_image, sensor=range_sensor, source=str(path))


def _preset_for_grid(path: Path, shape: tuple[int, int]) -> SensorModel:
    matches = [s for s in SENSORS.values() if s.shape == shape and s.projection is not None]
    if len(matches) == 1:
        return matches[0]
    if matches:
        names = ", ".join(s.name for s in matches)
        raise FormatError(path, f"range image {shape} matches several sensor presets ({names}); pass sensor= to choose")
    presets = ", ".join(f"{s.name} {s.shape}" for s in SENSORS.values())
    raise FormatError(path, f"no sensor preset has a {shape} grid ({presets}); pass sensor= with a projection for this grid")
