"""Trajectory accuracy with the TUM RGB-D benchmark's conventions: ATE and RPE.

* **Absolute trajectory error (ATE)**: the estimated positions are aligned
  to the reference by the rigid transform that fits them best in the least
  squares sense (Horn's closed form; no scale, as for metric sensors), and
  the error is the distance between corresponding positions. It measures
  the global consistency of a trajectory.
* **Relative pose error (RPE)**: the error of the motion over a fixed
  interval, ``inv(inv(Q_i) Q_j) inv(P_i) P_j`` for ``j = i + delta``; its
  translation and rotation angle. It measures drift per interval and needs
  no alignment.

Both take poses ``T_world_sensor`` in matching order; `associate` pairs the
lines of two TUM files by timestamp first, as the benchmark's tools do.

References
----------
.. [1] J. Sturm, N. Engelhard, F. Endres, W. Burgard and D. Cremers, "A
   benchmark for the evaluation of RGB-D SLAM systems", IROS 2012.
.. [2] B. K. P. Horn, "Closed-form solution of absolute orientation using
   unit quaternions", JOSA A 4(4), 1987 (here in its SVD form, Umeyama 1991).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["ErrorStatistics", "TrajectoryError", "align_trajectories", "absolute_trajectory_error",
           "relative_pose_error", "associate"]


@dataclass(frozen=True)
class ErrorStatistics:
    """Summary of a set of non-negative errors (metres or degrees)."""

    rmse: float
    mean: float
    median: float
    max: float
    count: int

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStatistics:
        errors = np.asarray(errors, dtype=np.float64)
        if errors.size == 0:
            return cls(np.nan, np.nan, np.nan, np.nan, 0)
        return cls(float(np.sqrt(np.mean(errors**2))), float(errors.mean()), float(np.median(errors)),
                   float(errors.max()), int(errors.size))


@dataclass(frozen=True)
class TrajectoryError:
    """ATE or RPE of an estimated trajectory.

    Parameters
    ----------
    translation : ErrorStatistics
        Metres.
    rotation : ErrorStatistics
        Degrees (for the ATE: of the aligned orientations).
    alignment : (4, 4) float64
        ``T_reference_estimate`` applied before comparing (identity for RPE).
    """

    translation: ErrorStatistics
    rotation: ErrorStatistics
    alignment: np.ndarray


def _poses(poses: ArrayLike, name: str) -> np.ndarray:
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim != 3 or array.shape[1:] != (4, 4):
        raise ValueError(f"{name} must be an (N, 4, 4) array of poses, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or Inf")
    return array


def _pair(estimate: ArrayLike, reference: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    estimate, reference = _poses(estimate, "estimate"), _poses(reference, "reference")
    if len(estimate) != len(reference):
        raise ValueError(f"estimate has {len(estimate)} poses, reference {len(reference)}; associate them first")
    return estimate, reference


def _angles(rotations: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) of each (3, 3) rotation."""
    cosine = np.clip((np.trace(rotations, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cosine))


def align_trajectories(estimate: ArrayLike, reference: ArrayLike) -> np.ndarray:
    """The rigid transform ``T_reference_estimate`` that best maps the estimated positions onto the reference ones.

    Least squares over the positions (Horn / Umeyama without scale). With
    fewer than three poses, or collinear positions, the rotation is not
    determined by the positions; then the first poses are aligned instead.

    Examples
    --------
    >>> import numpy as np
    >>> reference = np.tile(np.eye(4), (3, 1, 1))
    >>> reference[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    >>> shift = np.eye(4)
    >>> shift[2, 3] = 5.0
    >>> estimate = shift @ reference
    >>> np.round(align_trajectories(estimate, reference)[:3, 3], 6).tolist()
    [0.0, 0.0, -5.0]
    """
    estimate, reference = _pair(estimate, reference)
    if len(estimate) == 0:
        return np.eye(4)
    source, target = estimate[:, :3, 3], reference[:, :3, 3]
    source_centre, target_centre = source.mean(axis=0), target.mean(axis=0)
    covariance = (target - target_centre).T @ (source - source_centre)
    left, singular, right = np.linalg.svd(covariance)
    transform = np.eye(4)
    # Positions on a line (or a point) leave a rotation about that line free: fall back to the first pose.
    if len(estimate) < 3 or singular[1] <= 1e-9 * max(singular[0], 1e-300):
        return reference[0] @ np.linalg.inv(estimate[0])
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(left @ right)) or 1.0
    rotation = left @ np.diag(sign) @ right
    transform[:3, :3] = rotation
    transform[:3, 3] = target_centre - rotation @ source_centre
    return transform


def absolute_trajectory_error(estimate: ArrayLike, reference: ArrayLike, *, align: bool = True) -> TrajectoryError:
    """The absolute trajectory error (TUM ATE) of ``estimate`` against ``reference``.

    Parameters
    ----------
    estimate, reference : (N, 4, 4) arrays
        ``T_world_sensor`` poses in matching order.
    align : bool
        Align the estimate to the reference first (`align_trajectories`),
        as the benchmark does; without, both must share a world frame.

    Returns
    -------
    TrajectoryError
        Position errors after alignment (metres) and the angles of the
        aligned orientations' differences (degrees).

    Examples
    --------
    >>> import numpy as np
    >>> reference = np.tile(np.eye(4), (4, 1, 1))
    >>> reference[:, 0, 3] = [0, 1, 2, 3]
    >>> estimate = reference.copy()
    >>> estimate[3, 1, 3] = 0.1
    >>> round(absolute_trajectory_error(estimate, reference, align=False).translation.max, 6)
    0.1
    """
    estimate, reference = _pair(estimate, reference)
    alignment = align_trajectories(estimate, reference) if align else np.eye(4)
    aligned = alignment @ estimate
    translation = np.linalg.norm(aligned[:, :3, 3] - reference[:, :3, 3], axis=1)
    rotation = _angles(np.transpose(reference[:, :3, :3], (0, 2, 1)) @ aligned[:, :3, :3])
    return TrajectoryError(ErrorStatistics.of(translation), ErrorStatistics.of(rotation), alignment)


def relative_pose_error(estimate: ArrayLike, reference: ArrayLike, *, delta: int = 1) -> TrajectoryError:
    """The relative pose error (TUM RPE) over intervals of ``delta`` frames.

    Parameters
    ----------
    estimate, reference : (N, 4, 4) arrays
        ``T_world_sensor`` poses in matching order.
    delta : int
        Interval in frames (1: frame-to-frame drift; the benchmark also
        uses the frame count of one second).

    Examples
    --------
    >>> import numpy as np
    >>> reference = np.tile(np.eye(4), (3, 1, 1))
    >>> reference[:, 0, 3] = [0.0, 0.1, 0.2]
    >>> estimate = reference.copy()
    >>> estimate[2, 0, 3] = 0.21  # the last step 1 cm too long
    >>> rpe = relative_pose_error(estimate, reference)
    >>> round(rpe.translation.max, 6), rpe.translation.count
    (0.01, 2)
    """
    estimate, reference = _pair(estimate, reference)
    if isinstance(delta, bool) or not isinstance(delta, (int, np.integer)) or delta < 1:
        raise ValueError(f"delta must be an integer >= 1, got {delta!r}")
    if len(estimate) <= delta:
        empty = ErrorStatistics.of(np.zeros(0))
        return TrajectoryError(empty, empty, np.eye(4))
    reference_motion = np.linalg.inv(reference[:-delta]) @ reference[delta:]
    estimate_motion = np.linalg.inv(estimate[:-delta]) @ estimate[delta:]
    error = np.linalg.inv(reference_motion) @ estimate_motion
    translation = np.linalg.norm(error[:, :3, 3], axis=1)
    return TrajectoryError(ErrorStatistics.of(translation), ErrorStatistics.of(_angles(error[:, :3, :3])), np.eye(4))


def associate(first: ArrayLike, second: ArrayLike, *, max_difference: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Pair two timestamp lists: each pair the closest in time, within ``max_difference`` seconds, used once.

    Returns
    -------
    first_index, second_index : (K,) int64
        Matching indices, in the order of ``first``.

    Examples
    --------
    >>> associate([0.0, 0.033, 0.066], [0.001, 0.07])
    (array([0, 2]), array([0, 1]))
    """
    first = np.asarray(first, dtype=np.float64).reshape(-1)
    second = np.asarray(second, dtype=np.float64).reshape(-1)
    if len(first) == 0 or len(second) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # Greedy over all candidate pairs, closest first (as the benchmark's associate.py).
    order = np.argsort(second)
    sorted_second = second[order]
    candidates = []
    for index, stamp in enumerate(first):
        low = np.searchsorted(sorted_second, stamp - max_difference, side="left")
        high = np.searchsorted(sorted_second, stamp + max_difference, side="right")
        for position in range(low, high):
            candidates.append((abs(sorted_second[position] - stamp), index, int(order[position])))
    candidates.sort()
    used_first, used_second, pairs = set(), set(), []
    for _, a, b in candidates:
        if a not in used_first and b not in used_second:
            used_first.add(a)
            used_second.add(b)
            pairs.append((a, b))
    pairs.sort()
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs_array = np.asarray(pairs, np.int64)
    return pairs_array[:, 0], pairs_array[:, 1]
