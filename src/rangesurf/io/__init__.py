"""Readers and writers of range data, behind `load` and `save`.

One module per format; each offers ``read_<format>(path, *, sensor=None)``
yielding `RangeFrame` objects from one file, and ``write_<format>(path, frame)``
writing one frame atomically (temporary file, then rename).

=================  ==========================================  ==============
format             files                                        module
=================  ==========================================  ==============
3DTK "uos"         ``scanNNN.3d`` + ``.pose`` / ``.frames``     `uos`
PLY                point grids, Stanford ``range_grid`` + conf  `ply`
PCD                organized, ascii / binary                    `pcd`
NumPy              ``.npz`` (ours), ``.npy`` range or points    `npz`
depth PNG          16-bit PNG + intrinsics JSON                 `depth_png`
ROS 1 / ROS 2 bag  ``.bag``, ``.mcap``, ``.db3``, bag folders   `rosbag`
=================  ==========================================  ==============
"""

from __future__ import annotations

import glob as _glob
import importlib
import os
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

from rangesurf.frame import RangeFrame, SensorModel, get_sensor
from rangesurf.io._common import FormatError, atomic_path, atomic_write

__all__ = ["FormatError", "atomic_path", "atomic_write", "data_files", "iter_frames", "load", "save", "READERS", "WRITERS"]

# suffix -> (module, reader function)
READERS: dict[str, tuple[str, str]] = {
    ".3d": ("uos", "read_uos"),
    ".ply": ("ply", "read_ply"),
    ".pcd": ("pcd", "read_pcd"),
    ".npz": ("npz", "read_npz"),
    ".npy": ("npz", "read_npy"),
    ".png": ("depth_png", "read_depth_png"),
    ".bag": ("rosbag", "read_rosbag"),
    ".mcap": ("rosbag", "read_rosbag"),
    ".db3": ("rosbag", "read_rosbag"),
}

# suffix -> (module, writer function)
WRITERS: dict[str, tuple[str, str]] = {
    ".3d": ("uos", "write_uos"),
    ".ply": ("ply", "write_ply"),
    ".pcd": ("pcd", "write_pcd"),
    ".npz": ("npz", "write_npz"),
    ".png": ("depth_png", "write_depth_png"),
}

# Files that sit beside data files and are read by the data file's reader.
_COMPANION_SUFFIXES = {".pose", ".frames", ".conf", ".json", ".yaml", ".txt", ".md", ""}


def _function(table: dict[str, tuple[str, str]], suffix: str):
    module_name, function_name = table[suffix]
    module = importlib.import_module(f"rangesurf.io.{module_name}")
    return getattr(module, function_name)


def _natural_key(path: Path) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def _is_ros2_bag_folder(folder: Path) -> bool:
    return (folder / "metadata.yaml").is_file()


def data_files(path: str | os.PathLike) -> list[Path]:
    """The data files a path (file, folder, glob, ROS 2 bag folder) stands for, in sequence order, all of one format.

    Raises
    ------
    FormatError
        Nothing readable there, or a folder mixing formats.
    """
    path = Path(path)
    if path.is_dir():
        if _is_ros2_bag_folder(path):
            return [path]
        files = [p for p in path.iterdir() if p.is_file() and not p.name.startswith(".")]
        data = [p for p in files if p.suffix.lower() in READERS]
        unknown = sorted(p.name for p in files if p.suffix.lower() not in READERS and p.suffix.lower() not in _COMPANION_SUFFIXES)
        if not data:
            hint = f"; found {', '.join(unknown[:5])}" if unknown else ""
            raise FormatError(path, f"no range data files ({', '.join(sorted(READERS))}){hint}")
        suffixes = sorted({p.suffix.lower() for p in data})
        if len(suffixes) > 1:
            counts = ", ".join(f"{sum(p.suffix.lower() == s for p in data)} {s}" for s in suffixes)
            raise FormatError(path, f"folder mixes scan formats ({counts}); expected files of one format")
        return sorted(data, key=_natural_key)
    if path.is_file():
        if path.suffix.lower() not in READERS:
            raise FormatError(path, f"unknown format {path.suffix!r}; expected one of {', '.join(sorted(READERS))} or a folder")
        return [path]
    matches = [Path(p) for p in sorted(_glob.glob(str(path)))] if _glob.has_magic(str(path)) else []
    if matches:
        files = [p for p in matches if p.is_file()]
        suffixes = sorted({p.suffix.lower() for p in files})
        if len(suffixes) != 1 or suffixes[0] not in READERS:
            raise FormatError(path, f"glob must match files of one known format, matched suffixes {suffixes}")
        return sorted(files, key=_natural_key)
    raise FormatError(path, "no such file or folder")


def iter_frames(
    path: str | os.PathLike,
    *,
    sensor: str | SensorModel | None = None,
    topic: str | None = None,
) -> Iterator[RangeFrame]:
    """Yield the frames stored at ``path`` one at a time, in sequence order.

    Parameters
    ----------
    path : str or path-like
        A file, a folder of files of one format (read in natural name order:
        ``scan2`` before ``scan10``), a glob pattern, or a ROS 2 bag folder.
    sensor : str or SensorModel, optional
        Overrides the sensor a reader would infer (a preset name or a model).
    topic : str, optional
        For bags: the topic to read (default: the only range topic).

    Raises
    ------
    FormatError
        Unknown format, mixed folder, or a file that does not parse; the
        message names the file and the line or field.
    """
    path = Path(path)
    sensor_model = None if sensor is None else get_sensor(sensor)
    for file in data_files(path):
        suffix = ".bag" if file.is_dir() else file.suffix.lower()
        reader = _function(READERS, suffix)
        options = {"sensor": sensor_model}
        if suffix in (".bag", ".mcap", ".db3"):
            options["topic"] = topic
        elif topic is not None:
            raise ValueError(f"topic={topic!r} applies to ROS bags only, not {file}")
        try:
            yield from reader(file, **options)
        except FormatError:
            raise
        except ValueError as error:
            # A frame refused what the file holds (Inf ranges, a grid that fits no sensor): still a
            # problem of the file, reported as one.
            raise FormatError(file, f"holds values a frame cannot take: {error}") from error


def load(
    path: str | os.PathLike,
    *,
    sensor: str | SensorModel | None = None,
    topic: str | None = None,
) -> list[RangeFrame]:
    """Load every frame stored at ``path``; see `iter_frames` for the arguments.

    Examples
    --------
    >>> import rangesurf as rs
    >>> frames = rs.load("../shared/data/uos-3dtk")        # doctest: +SKIP
    >>> frames[0].shape                                   # doctest: +SKIP
    (226, 360)
    """
    return list(iter_frames(path, sensor=sensor, topic=topic))


def save(path: str | os.PathLike, frames: RangeFrame | Iterable[RangeFrame], *, format: str = "npz") -> list[Path]:
    """Write frames atomically; return the paths written.

    Parameters
    ----------
    path : str or path-like
        A file name whose suffix picks the format (``.npz``, ``.pcd``,
        ``.ply``, ``.3d``, ``.png``) for a single frame, or a folder for a
        sequence, written as ``frame000000.<format>`` and so on.
    frames : RangeFrame or iterable of RangeFrame
    format : str
        Suffix (without dot) used when ``path`` is a folder.
    """
    path = Path(path)
    single = isinstance(frames, RangeFrame)
    frame_list = [frames] if single else list(frames)
    if not all(isinstance(f, RangeFrame) for f in frame_list):
        raise TypeError("save expects RangeFrame objects")
    if path.suffix.lower() in WRITERS and not path.is_dir():
        if len(frame_list) != 1:
            raise ValueError(f"{path}: a {path.suffix} file holds one frame, got {len(frame_list)}; pass a folder")
        _function(WRITERS, path.suffix.lower())(path, frame_list[0])
        return [path]
    suffix = "." + format.lower().lstrip(".")
    if suffix not in WRITERS:
        raise ValueError(f"unknown output format {format!r}; expected one of {', '.join(s[1:] for s in WRITERS)}")
    if path.suffix and not path.is_dir():
        raise ValueError(f"{path}: unknown output suffix {path.suffix!r}; expected one of {', '.join(WRITERS)} or a folder")
    path.mkdir(parents=True, exist_ok=True)
    writer = _function(WRITERS, suffix)
    written = []
    for index, frame in enumerate(frame_list):
        target = path / f"frame{index:06d}{suffix}"
        writer(target, frame)
        written.append(target)
    return written
