"""Trajectories in the TUM RGB-D benchmark format.

One pose per line, ``timestamp tx ty tz qx qy qz qw`` (seconds, metres, unit
quaternion with the scalar last), ``#`` starts a comment. The pose maps the
sensor frame into the world (``T_world_sensor``), as in the benchmark's
ground-truth files, so the files open in the benchmark's own tools
(``evaluate_ate.py``, ``evaluate_rpe.py``) and in ``evo``.

References
----------
.. [1] J. Sturm, N. Engelhard, F. Endres, W. Burgard and D. Cremers, "A
   benchmark for the evaluation of RGB-D SLAM systems", IROS 2012.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from rangesurf.frame import check_rigid_transform
from rangesurf.io._common import FormatError, atomic_write

__all__ = ["read_tum_trajectory", "write_tum_trajectory"]


def read_tum_trajectory(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Returns
    -------
    timestamps : (N,) float64
        Seconds, in file order.
    poses : (N, 4, 4) float64
        ``T_world_sensor`` of each line.

    Raises
    ------
    FormatError
        A line without eight numbers, a non-finite value, or a quaternion
        far from unit length (naming the file and line).
    FileNotFoundError
        If the file does not exist.

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> path = tempfile.mkdtemp() + "/trajectory.txt"
    >>> write_tum_trajectory(path, [0.0, 0.04], [np.eye(4), np.eye(4)])
    >>> timestamps, poses = read_tum_trajectory(path)
    >>> timestamps.tolist(), poses.shape
    ([0.0, 0.04], (2, 4, 4))
    """
    path = Path(path)
    timestamps, poses = [], []
    with open(path, encoding="utf-8") as stream:
        for number, line in enumerate(stream, start=1):
            text = line.split("#", 1)[0].replace(",", " ").split()
            if not text:
                continue
            if len(text) != 8:
                raise FormatError(path, f"expected 8 numbers (timestamp tx ty tz qx qy qz qw), got {len(text)}",
                                  where=f"line {number}")
            try:
                values = [float(value) for value in text]
            except ValueError as error:
                raise FormatError(path, f"not a number: {error}", where=f"line {number}") from None
            if not all(math.isfinite(value) for value in values):
                raise FormatError(path, "non-finite value", where=f"line {number}")
            quaternion = np.asarray(values[4:])
            length = float(np.linalg.norm(quaternion))
            if abs(length - 1.0) > 1e-3:
                raise FormatError(path, f"quaternion (qx qy qz qw) must have unit length, got {length:.6f}",
                                  where=f"line {number}")
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_quat(quaternion / length).as_matrix()
            pose[:3, 3] = values[1:4]
            timestamps.append(values[0])
            poses.append(pose)
    return np.asarray(timestamps, np.float64), np.asarray(poses, np.float64).reshape(-1, 4, 4)


def write_tum_trajectory(path: str | os.PathLike, timestamps: ArrayLike, poses: ArrayLike) -> None:
    """Write ``T_world_sensor`` poses as a TUM trajectory file, atomically (temporary file, then rename).

    Parameters
    ----------
    path : str or path-like
    timestamps : (N,) float
        Seconds.
    poses : (N, 4, 4) float
        Rigid transforms.
    """
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(timestamps):
        raise ValueError(f"need one (4, 4) pose per timestamp: {len(timestamps)} timestamps, poses shape {poses.shape}")
    for index, pose in enumerate(poses):
        check_rigid_transform(pose, f"poses[{index}]")
    quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat() if len(poses) else np.zeros((0, 4))
    with atomic_write(path, "w") as stream:
        stream.write("# timestamp tx ty tz qx qy qz qw (T_world_sensor; written by rangesurf)\n")
        for stamp, pose, quaternion in zip(timestamps, poses, quaternions):
            numbers = [stamp, *pose[:3, 3], *quaternion]
            stream.write(" ".join(f"{value:.9g}" for value in numbers) + "\n")
