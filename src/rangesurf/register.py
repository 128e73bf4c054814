"""Registration of range frames: ICP (thesis Sections 2.2 and 3.3).

`icp` aligns a source point set to a target surface (points with normals):

* **Association**: *projective* for an organized target with a pinhole
  projection -- a source point, moved by the current estimate, is projected
  into the target's image and paired with the target point at that pixel (no
  search; the standard for depth cameras) -- or *closest point* through a k-d
  tree for any target (laser scans, the global model).
* **Error**: point-to-plane (the distance along the target normal; converges
  in a few iterations on man-made scenes) or point-to-point (Besl & McKay's
  original, solved in closed form).
* **Robustness**: pairs farther than ``max_correspondence_distance`` are
  dropped and the rest weighted by Tukey's biweight with a scale from the
  median absolute residual, so that outliers and surfaces seen by only one
  frame do not pull.
* **Coarse to fine**: the source is subsampled (every 4th, 2nd, then every
  point) while the estimate settles.
* **Initial guess**: the caller's (odometry, the previous motion); identity
  otherwise.

The result carries the quality measures a pipeline needs to trust it: RMS
residual, inlier fraction, the 6x6 covariance of the pose (rotation vector,
translation) from the Gauss-Newton information matrix, and whether the
geometry constrains all six degrees of freedom -- a single plane or a long
corridor does not, and such a result is flagged ``degenerate`` with the
unconstrained directions, not silently accepted.

References
----------
.. [1] P. J. Besl and N. D. McKay, "A method for registration of 3-D shapes",
   IEEE TPAMI 14(2), 1992 (the thesis's [3]).
.. [2] Y. Chen and G. Medioni, "Object modelling by registration of multiple
   range images", Image and Vision Computing 10(3), 1992 (point-to-plane).
.. [3] S. Rusinkiewicz and M. Levoy, "Efficient variants of the ICP
   algorithm", 3DIM 2001 (projective association, coarse to fine).
.. [4] A. Segal, D. Haehnel and S. Thrun, "Generalized-ICP", RSS 2009 (the
   degeneracy of planar scenes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numba
import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from rangesurf.frame import PinholeProjection, check_rigid_transform

__all__ = ["RegistrationResult", "icp", "pose_error", "compose_covariance", "FrameTracker", "TrackedPose", "ICP_METHODS"]

ICP_METHODS = ("point_to_plane", "point_to_point")
# Tukey's biweight constant (95 % efficiency at Gaussian noise), in robust standard deviations.
_TUKEY = 4.685
# 1 / Phi^-1(3/4): median absolute deviation to standard deviation.
_MAD_TO_SIGMA = 1.4826
# ICP's convergence: a step below these (radians, metres) ...
_DEFAULT_TOLERANCE = (1e-4, 1e-4)
# ... or, in the tracker, a translation below the last RMS residual over this.
_TOLERANCE_DIVISOR = 30.0
# Information-matrix eigenvalue ratio below which a direction counts as unconstrained.
_DEGENERATE_RATIO = 1e-3
# From this many source points on, the finest level takes every second one ...
_HALF_SOURCE = 20_000
# ... and from this many on, the coarsest every eighth.
_DENSE_SOURCE = 100_000
# Floor of (n . u)^2, the squared cosine between a target normal and a line of sight, in the variance of a
# point-to-plane residual from range noise: towards grazing incidence the range noise along the normal vanishes,
# but the normal's own error and the pixel's footprint on the surface do not (the floor is reached 80 degrees
# from the normal).
_MIN_INCIDENCE_SQUARED = 0.03
# Smallest residual variance (m^2) trusted when weighing ICP against a motion prior.
_MIN_RESIDUAL_VARIANCE = 1e-8
# Squared Mahalanobis distance between ICP's motion and the prior's beyond which ICP is not trusted
# (chi-square, 6 degrees of freedom: 20 is exceeded by chance 0.3 % of the time; on simulated
# sequences the distances have a median of 2 and a 99th percentile of 10, and ICP sliding along two
# planes' intersection by 9 cm in one frame scored 41).
_INNOVATION_GATE = 20.0
# Variance of a constant-velocity motion prior, relative to the odometry's.
_CONSTANT_VELOCITY_SCALE = 9.0
_JIT = dict(cache=True, nogil=True, error_model="numpy")
# No fastmath: a kernel compiled in this process and the same kernel loaded from Numba's on-disk cache
# (a Dask worker, a resumed run) then give the same bits; with fused multiply-adds and reordered sums
# they did not (poses a few ulps apart, seen as trajectory metrics differing in the 12th digit).
# Inlier columns the point-to-plane kernel buffers before summing them (8 x 512 float64: 32 kB).
_CHUNK = 512


@dataclass(frozen=True)
class RegistrationResult:
    """The outcome of `icp`.

    Parameters
    ----------
    T_target_source : (4, 4) float64
        Maps source points into the target's frame.
    rmse : float
        Root-mean-square point-to-plane (or point-to-point) residual of the
        inlier pairs at the end (metres). With range sigmas the robust test
        judges residuals against their own sigma, so far, noisy pairs stay
        inliers and raise it.
    inlier_fraction : float
        Share of the source points paired within the correspondence distance.
    covariance : (6, 6) float64
        Of (rotation vector in radians, translation in metres) of the
        result, from the final information matrix and residual variance;
        ``inf`` on the diagonal in degenerate directions.
    iterations : int
        Gauss-Newton (or closed-form) steps taken over all levels.
    converged : bool
        The last step moved less than the tolerances.
    degenerate : bool
        The geometry does not constrain all six degrees of freedom.
    unconstrained : (K, 6) float64
        Unit directions (rotation, translation) the data does not constrain.
    information : (6, 6) float64
        The robustly weighted Gauss-Newton information matrix ``J^T W J``
        at the end (without the residual variance): ``covariance`` is
        ``rmse**2`` times its inverse in the constrained directions. With
        range sigmas (`icp`'s ``source_sigma``, ``target_sigma``) ``W``
        also holds every residual's ``1 / sigma_r^2``, and the matrix is
        scaled by ``(rmse / normalized RMS)^2`` (the normalized residual
        being ``r / sigma_r``), so that the same relation holds and
        ``covariance`` is the normalized RMS squared times the inverse of
        ``J^T W J``.
    """

    T_target_source: np.ndarray
    rmse: float
    inlier_fraction: float
    covariance: np.ndarray
    iterations: int
    converged: bool
    degenerate: bool = False
    unconstrained: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    information: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))


def icp(
    source: ArrayLike,
    target: ArrayLike,
    target_normals: ArrayLike | None = None,
    *,
    initial: ArrayLike | None = None,
    method: str = "point_to_plane",
    target_projection: PinholeProjection | None = None,
    max_correspondence_distance: float = 0.1,
    max_iterations: int = 30,
    levels: tuple[int, ...] | None = None,
    tolerance: tuple[float, float] = _DEFAULT_TOLERANCE,
    min_inliers: int = 50,
    source_sigma: ArrayLike | None = None,
    target_sigma: ArrayLike | None = None,
) -> RegistrationResult:
    """Align source points to a target surface by iterative closest points.

    Parameters
    ----------
    source : (H, W, 3) or (N, 3) float array
        Source points in the source frame (metres); NaN rows are ignored.
    target : (H, W, 3) or (M, 3) float array
        Target points in the target frame; organized ``(H, W, 3)`` for
        projective association.
    target_normals : same shape as ``target``, optional
        Unit normals of the target points (needed for point-to-plane).
    initial : (4, 4) array, optional
        Initial ``T_target_source`` (odometry, previous motion); identity by
        default.
    method : {"point_to_plane", "point_to_point"}
    target_projection : PinholeProjection, optional
        With an organized target: pair each moved source point with the target
        pixel it projects to. Without: closest points via a k-d tree.
    max_correspondence_distance : float
        Pairs farther apart (metres) are outliers at the finest level; a
        level that takes every ``step``-th source point searches ``step``
        times as far. Also bounds the robust weights' scale.
    max_iterations : int
        Per level, at least 1.
    levels : tuple of int, optional
        Source subsampling steps, coarse to fine. Default (4, 2, 1) below
        20,000 source points, (4, 2) from there and (8, 4, 2) from 100,000
        on: beyond some 10,000 points, every second point constrains six
        parameters as well as all of them (same errors on simulated SR-3000
        and Kinect pairs, 40 % less time).
    tolerance : (rotation, translation)
        Convergence: a step smaller than this (radians, metres).
    min_inliers : int
        Fewer pairs than this: an error (the frames do not overlap, or one is
        empty).
    source_sigma, target_sigma : float arrays, optional
        Range standard deviation (metres) of every source / target point
        (``SensorModel.range_sigma`` of the range image the points come
        from), shaped like the points without their last axis; finite and
        > 0 wherever a point is valid. With either (point-to-plane only),
        each residual is weighted by the inverse of its variance from range
        noise, the sum over the frames given of ``sigma^2 (n . u)^2`` (``u``
        the point's line of sight, ``(n . u)^2`` at least 0.03), and the
        robust test runs on the residual over its standard deviation: far,
        noisy points no longer weigh as much as near ones (simulated
        denoised Kinect pairs, projective: translation RMS 11-28 % lower,
        rotation RMS 12-25 % lower, about 30 % more time; SR-3000 pairs: up
        to 6 % lower; SR-3000 through the k-d tree: no clear change). None
        (default): all residuals alike.

    Returns
    -------
    RegistrationResult

    Raises
    ------
    ValueError
        On shapes that do not fit, a missing normal field for point-to-plane,
        a non-rigid initial transform, or too few valid pairs.

    Examples
    --------
    A corner of three planes, moved by 2 degrees and 3 cm, is found again:

    >>> import numpy as np
    >>> from scipy.spatial.transform import Rotation
    >>> rng = np.random.default_rng(0)
    >>> a, b = rng.uniform(0, 1, (2, 3000))
    >>> floor = np.column_stack([a, b, np.zeros_like(a)])
    >>> wall = np.column_stack([a, np.zeros_like(a), b])
    >>> side = np.column_stack([np.zeros_like(a), a, b])
    >>> target = np.vstack([floor, wall, side])
    >>> normals = np.repeat(np.eye(3)[[2, 1, 0]], 3000, axis=0)
    >>> motion = np.eye(4)
    >>> motion[:3, :3] = Rotation.from_euler("xyz", [1.0, -1.0, 1.0], degrees=True).as_matrix()
    >>> motion[:3, 3] = (0.02, -0.01, 0.02)
    >>> source = (target - motion[:3, 3]) @ motion[:3, :3]  # the target seen from the moved sensor
    >>> result = icp(source, target, normals)
    >>> rotation, translation = pose_error(result.T_target_source, motion)
    >>> bool(rotation < 0.01 and translation < 1e-4), result.degenerate
    (True, False)
    """
    if method not in ICP_METHODS:
        raise ValueError(f"method must be one of {ICP_METHODS}, got {method!r}")
    source_points = _as_points(source, "source")
    target_array = np.asarray(target)
    if target_array.dtype.kind != "f":
        target_array = target_array.astype(np.float64)
    organized = target_array.ndim == 3
    if organized and target_array.shape[2] != 3 or not organized and (target_array.ndim != 2 or target_array.shape[1] != 3):
        raise ValueError(f"target must be (H, W, 3) or (N, 3) points, got shape {target_array.shape}")
    normals_array = None
    if target_normals is not None:
        normals_array = np.asarray(target_normals)
        if normals_array.dtype.kind != "f":
            normals_array = normals_array.astype(np.float64)
        if normals_array.shape != target_array.shape:
            raise ValueError(f"target_normals {normals_array.shape} must match target {target_array.shape}")
    if method == "point_to_plane" and normals_array is None:
        raise ValueError("point_to_plane needs target_normals (rangesurf.normals.estimate_normals)")
    if target_projection is not None and not organized:
        raise ValueError("projective association needs an organized (H, W, 3) target")
    transform = np.eye(4) if initial is None else check_rigid_transform(initial, "initial")
    if not (max_correspondence_distance > 0):
        raise ValueError(f"max_correspondence_distance must be > 0, got {max_correspondence_distance}")
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
    fast = method == "point_to_plane" and target_projection is not None
    weighted = source_sigma is not None or target_sigma is not None
    if weighted and method != "point_to_plane":
        raise ValueError("source_sigma and target_sigma weigh point-to-plane residuals: use method='point_to_plane'")
    source_noise = None if source_sigma is None else _source_noise(source_sigma, np.asarray(source))
    target_variance = None if target_sigma is None else _target_variance(target_sigma, target_array, normals_array)
    associate = _Associator(target_array, normals_array, target_projection, target_variance)

    if levels is None:
        if len(source_points) >= _DENSE_SOURCE:
            levels = (8, 4, 2)
        elif len(source_points) >= _HALF_SOURCE:
            levels = (4, 2)
        else:
            levels = (4, 2, 1)
    if not levels or any(int(step) < 1 for step in levels):
        raise ValueError(f"levels must be subsampling steps >= 1, coarse to fine, got {levels!r}")
    iterations = 0
    converged = False
    scale = None
    # Residuals over their sigma have no scale in metres: only the correspondence distance bounds them
    # until the first robust scale.
    scale_limit = math.inf if weighted else _TUKEY
    for step in levels:
        step = max(int(step), 1)
        sample = source_points[::step]
        # Coarse levels also search wider: an initial guess a few degrees off moves far points by more
        # than the final correspondence distance.
        distance = max_correspondence_distance * step
        # The robust scale of a pass comes from the previous pass's residuals (one pass per step),
        # carried over from the coarser level.
        scale = scale_limit * distance if scale is None else min(scale, scale_limit * distance)
        # Coarse levels only need to get close: their tolerance grows with the step.
        rotation_tolerance, translation_tolerance = tolerance[0] * step, tolerance[1] * step
        if fast:
            # Depth camera: the whole level compiled (pairing, normal equations, robust scale, step), with
            # no Python between its iterations.
            transform, scale, taken, converged, paired, *last_pass = associate.projective_level(
                sample, transform, distance, scale, max_iterations, rotation_tolerance, translation_tolerance, min_inliers,
                None if source_noise is None else source_noise[::step],
            )
            iterations += taken
            _require_pairs(paired, distance, min_inliers)
        else:
            sample_noise = None if source_noise is None else source_noise[::step]
            for _ in range(max_iterations):
                pairs = associate(sample, transform, distance, sample_noise)
                _require_pairs(pairs.count, distance, min_inliers)
                if method == "point_to_plane":
                    delta = _point_to_plane_step(pairs, distance)
                else:
                    delta = _point_to_point_step(pairs, distance)
                transform = _exp(delta) @ transform
                iterations += 1
                converged = _converged(delta, rotation_tolerance, translation_tolerance)
                if converged:
                    break
    # Quality at the end, on the finest level's points; the information of every point is about that
    # of its sample times the step.
    final_step = max(int(levels[-1]), 1)
    final_points = source_points[::final_step]
    if fast:
        # The finest level's last pass: its pose is the final one less the last step, which was below the
        # tolerance, and its robust scale the pass before's. A separate pass at the final pose cost the
        # pipeline's register stage 0.45 ms of 2.6-2.8 per SR-3000 frame (alternating 100-frame runs); the
        # same quality within a few per cent (test_icp_quality_is_that_of_the_final_pose); arena runs of 24
        # seeds: mean ATE 2.99 -> 3.12 mm, half the seeds identical to 0.01 mm, the rest either way (a
        # pose's covariance tips keyframe choices); UL3 coverage 95.6 -> 95.2 % (benchmarks/calibration.py).
        information, inliers, squares, normalized_squares = last_pass
        rmse = math.sqrt(squares / inliers) if inliers else math.nan
        normalized_rmse = math.sqrt(normalized_squares / inliers) if inliers else math.nan
    else:
        pairs = associate(final_points, transform, max_correspondence_distance,
                          None if source_noise is None else source_noise[::final_step])
        paired = pairs.count
        residual = pairs.residuals(method)
        weights, normalized = pairs.robust_weights(method, max_correspondence_distance)
        information = pairs.information(method, weights)
        inliers = int(np.count_nonzero(weights))
        rmse = float(np.sqrt(np.mean(residual[weights > 0] ** 2))) if inliers else math.nan
        normalized_rmse = float(np.sqrt(np.mean(normalized[weights > 0] ** 2))) if inliers else math.nan
    if weighted and normalized_rmse > 0:
        # J^T W J with W = Tukey / sigma_r^2 has a covariance of (normalized RMS)^2 times its inverse;
        # rescaled so that, as unweighted, the covariance is rmse^2 times the inverse of the information.
        information = information * (rmse / normalized_rmse) ** 2
    if paired < min_inliers:
        raise ValueError(f"only {paired} source points are paired at the end (need {min_inliers})")
    information = information * final_step
    covariance, unconstrained = _covariance(information, rmse)
    return RegistrationResult(
        T_target_source=transform,
        rmse=rmse,
        inlier_fraction=inliers / len(final_points),
        covariance=covariance,
        iterations=iterations,
        converged=bool(converged),
        degenerate=len(unconstrained) > 0,
        unconstrained=unconstrained,
        information=information,
    )


def pose_error(estimate: ArrayLike, reference: ArrayLike, *, at: ArrayLike | None = None) -> tuple[float, float]:
    """Rotation (degrees) and translation (metres) between two rigid transforms.

    Parameters
    ----------
    estimate, reference : (4, 4) arrays
        ``T_target_source`` estimated and true.
    at : (3,) array, optional
        A point of the source (e.g. the scanned object's centre): the
        translation error is how far the two transforms put it apart. By
        default the source origin (the sensor), where a small rotation error
        of a distant object also shows as translation.

    Examples
    --------
    >>> import numpy as np
    >>> shifted = np.eye(4)
    >>> shifted[0, 3] = 0.01
    >>> pose_error(shifted, np.eye(4))
    (0.0, 0.01)
    """
    estimate = np.asarray(estimate, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    difference = np.linalg.inv(reference) @ estimate
    cosine = np.clip((np.trace(difference[:3, :3]) - 1) / 2, -1.0, 1.0)
    point = np.zeros(3) if at is None else np.asarray(at, dtype=np.float64)
    gap = (estimate[:3, :3] @ point + estimate[:3, 3]) - (reference[:3, :3] @ point + reference[:3, 3])
    return float(np.degrees(np.arccos(cosine))), float(np.linalg.norm(gap))


def compose_covariance(T_world_target: ArrayLike, world_covariance: ArrayLike, relative_covariance: ArrayLike) -> np.ndarray:
    """Covariance of ``T_world_source = T_world_target @ T_target_source`` from those of its two factors.

    Both covariances are of perturbations applied on the left -- the world
    pose's in world coordinates, the registration's (`RegistrationResult.covariance`)
    in the target's -- over (rotation vector, translation); the two are
    taken as independent. The registration's is carried into world
    coordinates by the adjoint of ``T_world_target``. Chaining frame-to-frame
    results this way gives the pose uncertainty of a dead-reckoned
    trajectory, which grows with every step.

    Returns
    -------
    (6, 6) float64
        In world coordinates; ``inf`` stays ``inf`` (unconstrained directions).

    Examples
    --------
    >>> import numpy as np
    >>> step = np.diag([0.0, 0.0, 0.0, 1e-4, 1e-4, 1e-4])
    >>> turned = np.eye(4)
    >>> turned[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    >>> np.diag(compose_covariance(turned, step, step)).round(6).tolist()
    [0.0, 0.0, 0.0, 0.0002, 0.0002, 0.0002]
    """
    pose = check_rigid_transform(T_world_target, "T_world_target")
    covariances = []
    for name, value in (("world_covariance", world_covariance), ("relative_covariance", relative_covariance)):
        matrix = np.asarray(value, dtype=np.float64)
        if matrix.shape != (6, 6) or np.isnan(matrix).any():
            raise ValueError(f"{name} must be a 6x6 covariance without NaN, got shape {matrix.shape}")
        covariances.append(matrix)
    relative = covariances[1]
    if np.isfinite(relative).all():
        carried = _to_world(pose, relative)
    else:
        # inf * 0 would give NaN: carry a large finite stand-in, then mark what it reached as unknown.
        carried = _to_world(pose, np.where(np.isfinite(relative), relative, 1e300))
        carried = np.where(np.abs(carried) > 1e250, np.inf, carried)
    return covariances[0] + carried


@numba.njit(**_JIT)
def _to_world(pose, covariance):  # pragma: no cover - compiled
    """A finite covariance of a left perturbation in ``pose``'s frame carried into the world's by the adjoint.

    The adjoint of ``(R, t)`` is ``[[R, 0], [[t]x R, R]]``.
    """
    adjoint = np.zeros((6, 6))
    tx, ty, tz = pose[0, 3], pose[1, 3], pose[2, 3]
    for j in range(3):
        rx, ry, rz = pose[0, j], pose[1, j], pose[2, j]
        for i in range(3):
            adjoint[i, j] = adjoint[i + 3, j + 3] = pose[i, j]
        adjoint[3, j] = ty * rz - tz * ry
        adjoint[4, j] = tz * rx - tx * rz
        adjoint[5, j] = tx * ry - ty * rx
    return _product(_product(adjoint, covariance), adjoint.T)


@numba.njit(**_JIT)
def _fuse_with_prior(registered, prior, prior_covariance, measured, unconstrained):  # pragma: no cover - compiled
    """`FrameTracker._with_prior`'s algebra: the fused motion, its covariance, and the squared Mahalanobis
    distance between ICP's motion (``registered``, information ``measured``) and the prior's.

    ``unconstrained`` (K, 6) are the directions ICP cannot see (none: K = 0).
    """
    # Left perturbation from the prior to ICP's estimate.
    difference = _product(registered, _transform_inverse(prior))
    delta = np.empty(6)
    delta[:3] = _log(difference[:3, :3])
    delta[3:] = difference[:3, 3]
    if unconstrained.shape[0]:
        # Whatever ICP did along the directions it cannot see is noise: drop them outright.
        keep = np.eye(6) - _product(unconstrained.T, unconstrained)
        measured = _product(_product(keep, measured), keep)
        delta = _apply(keep, delta)
    covariance = _spd_inverse(measured + _spd_inverse(prior_covariance))
    # How far ICP's motion lies from the prior's, in their combined uncertainty (squared Mahalanobis
    # distance; (P + M^-1)^-1 = M - M (M + P^-1)^-1 M also holds for a singular M).
    spread = _apply(measured - _product(_product(measured, covariance), measured), delta)
    innovation = 0.0
    for k in range(6):
        innovation += delta[k] * spread[k]
    return _product(_exp(_apply(_product(covariance, measured), delta)), prior), covariance, innovation


@dataclass(frozen=True)
class TrackedPose:
    """Where `FrameTracker.track` put a frame.

    Parameters
    ----------
    T_world_sensor : (4, 4) float64
    covariance : (6, 6) float64
        Of the pose, as a left perturbation in world coordinates (rotation
        vector, translation): the chained frame-to-frame uncertainty.
    registration : RegistrationResult or None
        The frame-to-frame ICP result (None for the first frame and when
        ICP failed).
    prior : str
        Where the initial guess came from: ``"first"``, ``"odometry"``,
        ``"constant_velocity"``.
    fallback : bool
        ICP failed (too little overlap) or its motion disagreed with the
        prior's beyond both uncertainties: the prior's motion was used, with
        the prior's uncertainty.
    step_covariance : (6, 6) float64
        This frame's own registration uncertainty (against its keyframe,
        or the prior's on a fallback), in world coordinates; ``covariance``
        adds the keyframe's (the drift so far), which is what a model in
        world coordinates should weigh the frame by.
    """

    T_world_sensor: np.ndarray
    covariance: np.ndarray
    registration: RegistrationResult | None
    prior: str
    fallback: bool = False
    step_covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))


class FrameTracker:
    """Tracking by ICP against a keyframe, with odometry (or the previous motion) as prior.

    Each frame is registered onto the current keyframe, starting from the
    odometry's motion since the previous frame when the frames carry
    odometry poses, else from the previous motion (constant velocity). A
    frame becomes the next keyframe once it has moved ``keyframe_distance``
    or turned ``keyframe_angle`` from the current one, once the share of its
    points ICP could pair has dropped by ``keyframe_overlap_loss`` since the
    keyframe's first registration (the views overlap less), once the
    registration leaves a direction unconstrained that the first one onto
    the keyframe constrained, or when ICP failed, so registration errors add
    up once per keyframe rather than once per frame.
    Where ICP cannot see a direction -- a corridor along its axis, a single
    wall -- the prior's motion is kept in that direction and its
    uncertainty enters the covariance, so a degenerate scene hands over to
    odometry instead of freezing the estimate; where ICP fails outright,
    or its motion and the prior's disagree beyond both uncertainties (a
    chi-square gate: ICP slid along a direction that two planes barely
    constrain), the prior's motion is used and flagged.

    Parameters
    ----------
    max_correspondence_distance : float
        Metres (`icp`).
    odometry_sigma : (float, float)
        Standard deviation of the prior's motion per frame, per axis, at a
        standstill: rotation (radians) and translation (metres).
    odometry_relative : float
        Plus this share of the prior step's own rotation angle and
        translation length: odometry errs in proportion to the motion
        (wheel slip), so a 1 cm step between two depth-camera frames and a
        1 m step between two laser scans both get a fitting prior. A prior
        as tight as the odometry truly is matters: the chi-square gate
        catches ICP sliding along a weakly constrained direction only when
        the prior does not allow the slide.
    keyframe_distance, keyframe_angle : float
        Metres and degrees of motion from the keyframe that make a new one
        (0: every frame is a keyframe, plain frame-to-frame tracking).
    keyframe_overlap_loss : float
        A new keyframe once the share of the frame's points ICP pairs has
        dropped this much (0-1) below the first frame's after the keyframe.
        Every new keyframe adds a registration's error to the chain, and its
        covariance: at 0.05 a turning sensor took a new keyframe every 8
        frames (simulated SR-3000 arena), and the covariance grew faster
        than the error, which consecutive keyframes partly cancel. At 0.10,
        on simulated runs from drifting odometry (RMS position error, mean
        over odometry seeds 5-14, 0.05 -> 0.10): SR-3000 corridor 4.9 -> 3.5
        mm, arena 5.0 -> 4.4 (200 frames: 5.3 either way), Kinect arena 0.42
        -> 0.39, corridor 0.59 -> 0.49; the 600-frame arena's last 100
        frames without model alignment 29 -> 19 mm. 0.15 tracked about as
        well, but its covariance fell short on the 600-frame run (a third
        84 %).
    method : {"point_to_plane", "point_to_point"}
    icp_variance_scale : float
        How many times larger the true variance of ICP's motion is than
        `icp`'s covariance, which counts every residual as independent. A
        denoised frame's residuals are not: smoothing makes neighbours err
        alike, and the keyframe's own noise is shared by every frame
        registered to it. 26 is calibrated for every pixel of a frame
        (the pipeline divides it by its registration step to the power
        1.2, as thinned neighbours err less alike) on simulated SR-3000
        and Kinect sequences (fitted on odometry seeds 5-9; the step's
        power over seeds 5-14), where +-2 sigma then holds 92.7-97.0 % of
        the tracked poses' errors along the surface normals, pooled over
        seeds 5-14 (``benchmarks/calibration.py``; single runs 75.9-100 %:
        a run gives few independent pose errors). With a new keyframe at 5
        points of overlap lost no one scale kept both the turning arena and
        the corridor inside 90-98 %. It weighs ICP against the prior and
        sets the tracked covariance, hence the model's UL3.

    Examples
    --------
    >>> import numpy as np
    >>> from rangesurf import simulate
    >>> from rangesurf.normals import estimate_normals
    >>> frames, truths = simulate.simulate_sequence("arena", "sr3000", 3, seed=0)
    >>> tracker = FrameTracker()
    >>> for frame in frames:
    ...     normals = estimate_normals(frame.points, projection=frame.sensor.projection)
    ...     tracked = tracker.track(frame.points, normals, projection=frame.sensor.projection)
    >>> rotation, translation = pose_error(tracked.T_world_sensor, np.linalg.inv(truths[0].T_world_sensor) @ truths[2].T_world_sensor)
    >>> bool(rotation < 0.2 and translation < 0.01)
    True
    """

    def __init__(
        self,
        *,
        max_correspondence_distance: float = 0.1,
        odometry_sigma: tuple[float, float] = (0.01, 0.003),
        odometry_relative: float = 0.1,
        keyframe_distance: float = 0.3,
        keyframe_angle: float = 10.0,
        keyframe_overlap_loss: float = 0.10,
        method: str = "point_to_plane",
        icp_variance_scale: float = 26.0,
    ) -> None:
        if method not in ICP_METHODS:
            raise ValueError(f"method must be one of {ICP_METHODS}, got {method!r}")
        if not (len(odometry_sigma) == 2 and all(value > 0 for value in odometry_sigma)):
            raise ValueError(f"odometry_sigma must be two values > 0 (radians, metres), got {odometry_sigma!r}")
        if not (math.isfinite(odometry_relative) and odometry_relative >= 0):
            raise ValueError(f"odometry_relative must be finite and >= 0, got {odometry_relative!r}")
        if not (keyframe_distance >= 0 and keyframe_angle >= 0):
            raise ValueError("keyframe_distance and keyframe_angle must be >= 0")
        if not 0 <= keyframe_overlap_loss <= 1:
            raise ValueError(f"keyframe_overlap_loss must be a share between 0 and 1, got {keyframe_overlap_loss!r}")
        if not (math.isfinite(icp_variance_scale) and icp_variance_scale > 0):
            raise ValueError(f"icp_variance_scale must be finite and > 0, got {icp_variance_scale!r}")
        self.icp_variance_scale = float(icp_variance_scale)
        self.max_correspondence_distance = float(max_correspondence_distance)
        self.method = method
        self.keyframe_distance = float(keyframe_distance)
        self.keyframe_angle = float(keyframe_angle)
        self.keyframe_overlap_loss = float(keyframe_overlap_loss)
        self.odometry_sigma = (float(odometry_sigma[0]), float(odometry_sigma[1]))
        self.odometry_relative = float(odometry_relative)
        # The keyframe: points, normals, world pose, its covariance and the points' range sigmas.
        self._keyframe: tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray, np.ndarray | None] | None = None
        self._key_inliers: float | None = None
        # Whether the first registration onto the keyframe left a direction unconstrained.
        self._key_degenerate = False
        self._previous_odometry: np.ndarray | None = None
        # The last registration's RMS residual (metres), which sets how small a step ends ICP (`_tolerance`).
        self._last_rmse = math.nan
        self._motion = np.eye(4)
        # The last frame's motion from the keyframe is uncertain by this much (a left perturbation in the
        # keyframe's coordinates); zero when the last frame is the keyframe.
        self._relative_covariance = np.zeros((6, 6))
        self.pose = np.eye(4)
        self.covariance = np.zeros((6, 6))

    def track(
        self,
        points: ArrayLike,
        normals: ArrayLike | Callable[[], ArrayLike] | None,
        *,
        projection: PinholeProjection | None = None,
        odometry: ArrayLike | None = None,
        range_sigma: ArrayLike | None = None,
    ) -> TrackedPose:
        """Register a frame and return its world pose.

        Parameters
        ----------
        points : (H, W, 3) or (N, 3) float array
            The frame's points (sensor frame), NaN where invalid.
        normals : same shape, or a function returning them, optional
            Its normals (kept if the frame becomes a keyframe; needed for
            point-to-plane). Only a keyframe's are used: a function is
            called only if this frame becomes one (the pipeline's SR-3000
            frames: one in about ten).
        projection : PinholeProjection, optional
            For projective association of organized frames.
        odometry : (4, 4) array, optional
            The frame's odometry pose (``RangeFrame.pose``); the first
            frame's sets the world frame.
        range_sigma : float array, optional
            Range standard deviation of every point (``points``' shape
            without the last axis; ``SensorModel.range_sigma`` of the range
            image the points come from). With point-to-plane, ICP weighs its
            residuals by this frame's and the keyframe's range noise
            (`icp`'s ``source_sigma``, ``target_sigma``).
        """
        odometry_pose = None if odometry is None else check_rigid_transform(odometry, "odometry")
        points = np.asarray(points)
        if normals is not None and not callable(normals):
            normals = np.asarray(normals)
        sigma = None if range_sigma is None or self.method != "point_to_plane" else np.asarray(range_sigma)
        if self._keyframe is None:
            self.pose = np.eye(4) if odometry_pose is None else odometry_pose.copy()
            self._set_keyframe(points, normals, self.pose, self.covariance, sigma)
            self._previous_odometry = odometry_pose
            return TrackedPose(self.pose.copy(), self.covariance.copy(), None, "first")
        if odometry_pose is not None and self._previous_odometry is not None:
            step, prior_name = _product(_transform_inverse(self._previous_odometry), odometry_pose), "odometry"
            prior_covariance = self.prior_covariance(step)
        else:
            # A constant-velocity guess knows less than odometry does.
            step, prior_name = self._motion, "constant_velocity"
            prior_covariance = _CONSTANT_VELOCITY_SCALE * self.prior_covariance(step)
        key_points, key_normals, key_pose, key_covariance, key_sigma = self._keyframe
        last_motion = _product(_transform_inverse(key_pose), self.pose)
        prior = _product(last_motion, step)
        # The prior's motion from the keyframe is the last frame's, as uncertain as that was, and one step
        # more. Along directions the scene leaves unconstrained (a corridor's axis) it is all the motion
        # there is: one step's uncertainty per keyframe would let the drift there grow unseen.
        prior_covariance = self._relative_covariance + _to_world(last_motion, prior_covariance)
        result = fused = None
        try:
            result = icp(points, key_points, key_normals, initial=prior, method=self.method,
                         target_projection=projection if key_points.ndim == 3 else None,
                         max_correspondence_distance=self.max_correspondence_distance,
                         tolerance=self._tolerance(), source_sigma=sigma, target_sigma=key_sigma)
            self._last_rmse = result.rmse
            fused = self._with_prior(result, prior, prior_covariance)
        except ValueError:
            pass  # no overlap with the keyframe
        if fused is not None:
            motion, relative_covariance = fused
            pose = _product(key_pose, motion)
        else:
            # ICP failed, or the prior rules its result out: dead-reckon one step on the prior.
            result = None
            pose = _product(self.pose, step)
            relative_covariance = prior_covariance
            motion = _product(_transform_inverse(key_pose), pose)
        step_covariance = _to_world(key_pose, relative_covariance)
        covariance = key_covariance + step_covariance
        self._motion = _product(_transform_inverse(self.pose), pose)
        self.pose, self.covariance, self._relative_covariance = pose, covariance, relative_covariance
        self._previous_odometry = odometry_pose
        moved = math.sqrt(motion[0, 3] ** 2 + motion[1, 3] ** 2 + motion[2, 3] ** 2)
        cosine = (motion[0, 0] + motion[1, 1] + motion[2, 2] - 1.0) / 2.0
        turned = math.degrees(math.acos(min(max(cosine, -1.0), 1.0)))
        # The overlap with the keyframe shrinks as the sensor moves on; once the pairs found fall
        # well below what the first frame after the keyframe found, registration gets fragile.
        if self._key_inliers is None and result is not None:
            self._key_inliers, self._key_degenerate = result.inlier_fraction, result.degenerate
        overlap_lost = result is None or result.inlier_fraction < self._key_inliers - self.keyframe_overlap_loss
        # The overlap may also lose what constrained a direction (the sensor turns away from the one wall that
        # fixed it) before it loses many pairs: dead-reckoning on the prior there until the pairs run out let
        # the error grow (simulated Kinect arena, 200 frames: 10 degenerate frames in a row, 5 mm in one frame).
        # A keyframe that never constrained it (a corridor) is kept.
        structure_lost = result is not None and result.degenerate and not self._key_degenerate
        if overlap_lost or structure_lost or moved >= self.keyframe_distance or turned >= self.keyframe_angle:
            self._set_keyframe(points, normals, pose, covariance, sigma)
            self._key_inliers, self._key_degenerate = None, False
            self._relative_covariance = np.zeros((6, 6))
        return TrackedPose(pose.copy(), covariance.copy(), result, prior_name, result is None, step_covariance)

    def _tolerance(self) -> tuple[float, float]:
        """`icp`'s tolerance: a translation step below a thirtieth of the last registration's RMS residual
        (at least `icp`'s default) is finer than the residuals resolve.

        Simulated arena frames registered in the pipeline, against their true
        motion: SR-3000 (RMS residual about 5.6 mm, so 0.19 mm): 297 frames,
        translation error mean 2.376 -> 2.380 mm, 95th percentile 6.47 ->
        6.35 mm, 18 % fewer iterations; the pipeline's 100-frame arena runs,
        seeds 1-12, alike (mean ATE 2.65 mm both, model to the true planes
        median 1.47 mm both, 95th percentile 8.34 -> 8.30 mm). Kinect (1.9
        mm): the default stands; doubling it there raised the mean error from
        0.227 to 0.250 mm.
        """
        rotation, translation = _DEFAULT_TOLERANCE
        if math.isfinite(self._last_rmse):
            translation = max(translation, self._last_rmse / _TOLERANCE_DIVISOR)
        return rotation, translation

    def _set_keyframe(
        self, points: np.ndarray, normals: np.ndarray | None, pose: np.ndarray, covariance: np.ndarray,
        sigma: np.ndarray | None,
    ) -> None:
        """Keep a frame (and copies of its pose and covariance) as the keyframe the next frames register onto."""
        if callable(normals):
            normals = np.asarray(normals())
        # The points compacted: a decimated frame's are a strided view of the full-resolution grid, in which
        # every pixel the projective passes look up costs a cache line of its own (Kinect pipeline: tracking
        # about 10 % faster for one copy per keyframe), and which the keyframe would otherwise keep alive.
        self._keyframe = (np.ascontiguousarray(points), normals, pose.copy(), covariance.copy(), sigma)

    def prior_covariance(self, step: np.ndarray) -> np.ndarray:
        """Covariance (6, 6: rotation vector, translation) of a prior's motion ``step`` (4, 4)."""
        rotation_vector = _log(np.ascontiguousarray(step[:3, :3], dtype=np.float64))
        angle = math.sqrt(rotation_vector[0] ** 2 + rotation_vector[1] ** 2 + rotation_vector[2] ** 2)
        length = math.sqrt(step[0, 3] ** 2 + step[1, 3] ** 2 + step[2, 3] ** 2)
        rotation = self.odometry_sigma[0] + self.odometry_relative * angle
        translation = self.odometry_sigma[1] + self.odometry_relative * length
        return np.diag([rotation**2] * 3 + [translation**2] * 3)

    def correct(self, T_world_sensor: ArrayLike, covariance: ArrayLike) -> None:
        """Move the last tracked pose to a corrected one (e.g. `rangesurf.merge.GlobalModel.align`).

        The keyframe moves with it, by the same rigid correction, so that
        the frames that follow continue from the corrected pose. Its
        covariance is conditioned on the correction as a linear Gaussian
        model has it: the frame's pose is the keyframe's plus this frame's
        registration, so the keyframe's covariance ``K`` shrinks by
        ``G (P - P') G^T`` with ``G = K P^-1``, ``P`` and ``P'`` the frame's
        covariance before and after. The frames that follow add their own
        registration to that; a correction that measured nothing changes
        nothing.
        """
        if self._keyframe is None:
            raise ValueError("correct() needs a tracked frame first")
        pose = check_rigid_transform(T_world_sensor, "T_world_sensor")
        covariance = np.asarray(covariance, dtype=np.float64)
        if covariance.shape != (6, 6) or np.isnan(covariance).any():
            raise ValueError(f"covariance must be a 6x6 matrix without NaN, got shape {covariance.shape}")
        correction = pose @ np.linalg.inv(self.pose)
        key_points, key_normals, key_pose, key_covariance, key_sigma = self._keyframe
        if np.isfinite(self.covariance).all() and np.isfinite(key_covariance).all():
            # Handing the keyframe the frame's whole corrected covariance instead counted this frame's
            # registration again in every frame after it: one registration's worth more per alignment, so
            # the pose's uncertainty grew with how often the model was aligned to.
            gain = key_covariance @ np.linalg.pinv(self.covariance)
            key_covariance = key_covariance - gain @ (self.covariance - covariance) @ gain.T
            key_covariance = 0.5 * (key_covariance + key_covariance.T)
        else:
            # An unconstrained direction (inf) has no linear model to condition: the keyframe takes the
            # corrected covariance, and the motion from it counts as known.
            key_covariance = covariance.copy()
            self._relative_covariance = np.zeros((6, 6))
        self._keyframe = (key_points, key_normals, correction @ key_pose, key_covariance, key_sigma)
        self.pose, self.covariance = pose.copy(), covariance.copy()

    def state(self) -> dict[str, np.ndarray]:
        """Everything `track` needs to continue, as arrays (for checkpoints; see `restore`)."""
        if self._keyframe is None:
            return {"started": np.array(False)}
        key_points, key_normals, key_pose, key_covariance, key_sigma = self._keyframe
        state = {
            "started": np.array(True), "key_points": key_points, "key_pose": key_pose, "key_covariance": key_covariance,
            "key_inliers": np.array(np.nan if self._key_inliers is None else self._key_inliers),
            "key_degenerate": np.array(self._key_degenerate),
            "motion": self._motion, "pose": self.pose, "covariance": self.covariance,
            "relative_covariance": self._relative_covariance, "last_rmse": np.array(self._last_rmse),
        }
        if key_normals is not None:
            state["key_normals"] = key_normals
        if key_sigma is not None:
            state["key_sigma"] = key_sigma
        if self._previous_odometry is not None:
            state["previous_odometry"] = self._previous_odometry
        return state

    def restore(self, state: dict[str, np.ndarray]) -> None:
        """Continue from a `state` (same settings assumed)."""
        if not bool(state["started"]):
            self._keyframe = None
            return
        self._keyframe = (state["key_points"], state.get("key_normals"), state["key_pose"], state["key_covariance"],
                          state.get("key_sigma"))
        inliers = float(state["key_inliers"])
        self._key_inliers = None if math.isnan(inliers) else inliers
        self._key_degenerate = bool(state.get("key_degenerate", False))
        self._motion, self.pose, self.covariance = state["motion"], state["pose"], state["covariance"]
        self._relative_covariance = state.get("relative_covariance", np.zeros((6, 6)))
        self._last_rmse = float(state.get("last_rmse", math.nan))
        self._previous_odometry = state.get("previous_odometry")

    def _with_prior(
        self, result: RegistrationResult, prior: np.ndarray, prior_covariance: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """ICP's motion fused with the prior's, each weighted by its information (a Gauss-Newton/MAP step).

        Where the scene constrains the motion well, ICP's estimate stands;
        along weakly constrained or unconstrained directions (a corridor's
        axis) the prior's motion and its uncertainty take over. None when
        the two disagree beyond their uncertainties (ICP slid along a
        direction that two planes barely constrain, or locked onto the
        wrong structure): the caller keeps the prior.
        """
        # Floored at (0.1 mm)^2: noise-free data would otherwise claim unbounded information.
        variance = max(result.rmse**2, _MIN_RESIDUAL_VARIANCE) if math.isfinite(result.rmse) else 1.0
        measured = result.information / (variance * self.icp_variance_scale)
        motion, covariance, innovation = _fuse_with_prior(
            result.T_target_source, prior, prior_covariance, measured, np.ascontiguousarray(result.unconstrained))
        if innovation > _INNOVATION_GATE:
            return None
        return motion, covariance


# --------------------------------------------------------------------------
# Association.
# --------------------------------------------------------------------------


def _as_points(points: Any, name: str) -> np.ndarray:
    """Valid points as an (N, 3) array (float32 input stays float32: the kernels compute in float64)."""
    array = np.asarray(points)
    if array.dtype.kind != "f":
        array = array.astype(np.float64)
    if array.ndim == 2 and array.shape[1] == 3:
        array = array[np.newaxis]
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"{name} must be (H, W, 3) or (N, 3) points, got shape {np.shape(points)}")
    # Compacted straight from the grid: a thinned view (a decimated frame) would cost NumPy a slow
    # strided copy to flatten first.
    valid, infinite = _finite_rows(array)
    if infinite:
        raise ValueError(f"{name} contains Inf; mark missing points with NaN")
    return valid


def _sigma_grid(sigma: Any, points: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``sigma`` (float64) and ``points`` as (H, W) and (H, W, 3) grids (an (N, 3) array as one row).

    A ValueError unless ``sigma`` has the points' shape without the last axis.
    """
    values = np.asarray(sigma, dtype=np.float64)
    if values.shape != points.shape[:-1]:
        raise ValueError(
            f"{name} must have the points' shape without the last axis, {points.shape[:-1]}, got {values.shape}")
    return values.reshape(-1, values.shape[-1]), points.reshape(-1, *points.shape[-2:])


def _require_sigma(bad: int, name: str) -> None:
    if bad:
        raise ValueError(f"{name} must be finite and > 0 wherever there is a point; {bad} points are not")


def _source_noise(sigma: Any, points: np.ndarray) -> np.ndarray:
    """``sigma^2 / |p|^2`` (`_along_normal`) of the valid source points, compacted as `_as_points` compacts them.

    A ValueError unless ``sigma`` fits and is finite and > 0 at every point.
    """
    values, grid = _sigma_grid(sigma, points, "source_sigma")
    # Compiled, as `_as_points`: NumPy's masks cost 4 ms at 640x480, a quarter of a registration.
    kept, bad = _sigma_rows(grid, values)
    _require_sigma(bad, "source_sigma")
    return kept


def _target_variance(sigma: Any, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Per target point, the variance its range noise gives a point-to-plane residual (`_along_normal`).

    Shaped as the points without their last axis, float32 as the points (a
    weight needs no more digits); NaN where there is no point or normal. A
    ValueError unless ``sigma`` fits and is finite and > 0 at every point.
    The target's share depends on the target alone: computed once here, not
    in every pass (which then reads one number, as it reads a point).
    """
    values, grid = _sigma_grid(sigma, points, "target_sigma")
    variance, bad = _target_variance_grid(grid, normals.reshape(grid.shape), values, _MIN_INCIDENCE_SQUARED)
    _require_sigma(bad, "target_sigma")
    return variance.reshape(points.shape[:-1])


@numba.njit(**_JIT)
def _sigma_rows(grid, sigma):  # pragma: no cover - compiled
    """``sigma^2 / |p|^2`` of an (H, W, 3) grid's points p without NaN, row by row (as `_finite_rows`), and how many
    sigmas are not finite and > 0."""
    kept = np.empty(grid.shape[0] * grid.shape[1], np.float32)
    count = bad = 0
    for row in range(grid.shape[0]):
        for column in range(grid.shape[1]):
            x, y, z = grid[row, column, 0], grid[row, column, 1], grid[row, column, 2]
            if x == x and y == y and z == z:
                value = sigma[row, column]
                kept[count] = value * value / (x * x + y * y + z * z)
                count += 1
                if not (value > 0.0 and value < math.inf):
                    bad += 1
    return kept[:count], bad


@numba.njit(**_JIT)
def _target_variance_grid(grid, normals, sigma, min_incidence):  # pragma: no cover - compiled
    """`_along_normal` of every point of an (H, W, 3) grid (its ray: its own coordinates), NaN without a point or normal;
    and how many points have no finite sigma > 0."""
    variance = np.full(sigma.shape, np.nan, np.float32)
    bad = 0
    for row in range(grid.shape[0]):
        for column in range(grid.shape[1]):
            x, y, z = grid[row, column, 0], grid[row, column, 1], grid[row, column, 2]
            if not (x == x and y == y and z == z):
                continue
            value = sigma[row, column]
            if not (value > 0.0 and value < math.inf):
                bad += 1
                continue
            variance[row, column] = _along_normal(value * value / (x * x + y * y + z * z), normals[row, column, 0],
                                                  normals[row, column, 1], normals[row, column, 2], x, y, z, min_incidence)
    return variance, bad


@numba.njit(**_JIT)
def _finite_rows(grid):  # pragma: no cover - compiled
    """The points of an (H, W, 3) grid without NaN, row by row, as (N, 3); and whether one has an infinite coordinate."""
    kept = np.empty((grid.shape[0] * grid.shape[1], 3), grid.dtype)
    count = 0
    infinite = False
    for row in range(grid.shape[0]):
        for column in range(grid.shape[1]):
            x, y, z = grid[row, column, 0], grid[row, column, 1], grid[row, column, 2]
            # Written unconditionally and kept by advancing the count: no branch on the common path.
            kept[count, 0], kept[count, 1], kept[count, 2] = x, y, z
            if x - x == 0.0 and y - y == 0.0 and z - z == 0.0:  # finite (NaN and Inf give NaN)
                count += 1
            elif x == x and y == y and z == z:
                infinite = True
    return kept[:count], infinite


@dataclass
class _Pairs:
    moved: np.ndarray  # (K, 3) source points in the target frame
    target: np.ndarray  # (K, 3)
    normals: np.ndarray | None  # (K, 3)
    variance: np.ndarray | None = None  # (K,) point-to-plane residual variance from range noise (m^2)

    @property
    def count(self) -> int:
        return len(self.moved)

    def robust_weights(self, method: str, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
        """Tukey weights (over the residual variances, if known) and the residuals they judged (normalized by their sigma)."""
        residual = self.residuals(method)
        if self.variance is None:
            return _tukey(residual, _robust_scale(residual, max_distance)), residual
        # As the compiled pass: the robust test on r / sigma_r, whose scale is not bounded in metres.
        normalized = residual / np.sqrt(self.variance)
        return _tukey(normalized, _robust_scale(normalized, math.inf)) / self.variance, normalized

    def residuals(self, method: str) -> np.ndarray:
        difference = self.moved - self.target
        if method == "point_to_plane":
            return np.einsum("ij,ij->i", difference, self.normals)
        return np.linalg.norm(difference, axis=1)

    def plane_jacobian(self) -> np.ndarray:
        """(K, 6) derivatives of the point-to-plane residuals by (rotation vector, translation)."""
        return np.column_stack([np.cross(self.moved, self.normals), self.normals])

    def information(self, method: str, weights: np.ndarray) -> np.ndarray:
        """J^T W J of the pose (rotation vector, translation) at the current estimate."""
        if method == "point_to_plane":
            jacobian = self.plane_jacobian()
            return (jacobian * weights[:, None]).T @ jacobian
        # Point-to-point: three residual rows per pair, J = [-[p]x, I].
        information = np.zeros((6, 6))
        for axis in range(3):
            unit = np.zeros(3)
            unit[axis] = 1.0
            jacobian = np.column_stack([np.cross(self.moved, unit), np.broadcast_to(unit, self.moved.shape)])
            information += (jacobian * weights[:, None]).T @ jacobian
        return information


class _Associator:
    """Pairs source points (moved into the target frame) with target points and normals (and `_target_variance`)."""

    def __init__(
        self, target: np.ndarray, normals: np.ndarray | None, projection: PinholeProjection | None,
        variance: np.ndarray | None = None,
    ) -> None:
        self.projection = projection
        if projection is not None:
            self.grid, self.grid_normals = target, normals
            # An empty grid: the compiled pass then weighs without the target's noise.
            self.grid_variance = np.empty((0, 0), np.float32) if variance is None else variance
            self.height, self.width = target.shape[:2]
            self.intrinsics = np.array([projection.fx, projection.fy, projection.cx, projection.cy])
        else:
            flat = target.reshape(-1, 3)
            keep = np.isfinite(flat).all(axis=1)
            if normals is not None:
                flat_normals = normals.reshape(-1, 3)
                keep &= np.isfinite(flat_normals).all(axis=1)
                self.normals = flat_normals[keep]
            else:
                self.normals = None
            self.points = flat[keep]
            self.variance = None if variance is None else variance.reshape(-1)[keep]
            if len(self.points) == 0:
                raise ValueError("the target has no valid points")
            self.tree = cKDTree(self.points)

    def projective_level(
        self, source: np.ndarray, transform: np.ndarray, max_distance: float, scale: float, max_iterations: int,
        rotation_tolerance: float, translation_tolerance: float, min_inliers: int, source_noise: np.ndarray | None = None,
    ) -> tuple[np.ndarray, float, int, bool, int, np.ndarray, int, float, float]:
        """One level's projective point-to-plane iterations (`_projective_level`); with ``max_iterations`` 1,
        the normal equations at ``transform``."""
        weighted = source_noise is not None or self.grid_variance.size > 0
        return _projective_level(
            source, transform, self.grid, self.grid_normals, self.intrinsics, max_distance, scale, max_iterations,
            rotation_tolerance, translation_tolerance, min_inliers, np.empty(0) if source_noise is None else source_noise,
            self.grid_variance, _MIN_INCIDENCE_SQUARED, math.inf if weighted else max_distance,
        )

    def __call__(
        self, source: np.ndarray, transform: np.ndarray, max_distance: float, source_noise: np.ndarray | None = None
    ) -> _Pairs:
        moved = source @ transform[:3, :3].T + transform[:3, 3]
        if self.projection is None:
            distance, index = self.tree.query(moved, distance_upper_bound=max_distance)
            found = np.isfinite(distance)
            index = index[found]
            pairs = _Pairs(moved[found], self.points[index], None if self.normals is None else self.normals[index])
            if source_noise is not None or self.variance is not None:
                pairs.variance = _pair_variances(
                    pairs.normals, np.empty(0, np.float32) if self.variance is None else self.variance[index],
                    pairs.moved - transform[:3, 3], np.empty(0) if source_noise is None else source_noise[found],
                    _MIN_INCIDENCE_SQUARED,
                )
            return pairs
        p = self.projection
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(p.fx * moved[:, 0] / moved[:, 2] + p.cx)
            v = np.round(p.fy * moved[:, 1] / moved[:, 2] + p.cy)
        inside = (moved[:, 2] > 0) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        rows, cols = v[inside].astype(int), u[inside].astype(int)
        target = self.grid[rows, cols]
        normals = None if self.grid_normals is None else self.grid_normals[rows, cols]
        close = np.isfinite(target).all(axis=1) & (np.linalg.norm(moved[inside] - target, axis=1) <= max_distance)
        if normals is not None:
            close &= np.isfinite(normals).all(axis=1)
        return _Pairs(moved[inside][close], target[close], None if normals is None else normals[close])


# --------------------------------------------------------------------------
# Solvers.
# --------------------------------------------------------------------------


@numba.njit(**_JIT)
def _robust_scale(residual, max_distance):  # pragma: no cover - compiled
    """Tukey scale: from the median absolute residual, at most the correspondence distance."""
    # A median of 2,000 residuals is as good a scale as one of all of them (about 3 % standard error),
    # and far cheaper.
    sample = residual[:: max(1, len(residual) // 2_000)]
    median = _median(np.abs(sample)) if len(sample) else max_distance
    return min(max(_TUKEY * _MAD_TO_SIGMA * median, 1e-9), _TUKEY * max_distance)


@numba.njit(**_JIT)
def _median(values):  # pragma: no cover - compiled
    """The median of a non-empty array, reordering it (Hoare's quickselect: as fast as ``np.median``, and
    compiled in a third of the time)."""
    middle = len(values) // 2
    low, high = 0, len(values) - 1
    while low < high:
        pivot = values[(low + high) // 2]
        i, j = low, high
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        # Everything up to j is <= pivot, everything from i on >= pivot, and between them == pivot.
        if middle <= j:
            high = j
        elif middle >= i:
            low = i
        else:
            break
    upper = values[middle]
    if len(values) % 2:
        return upper
    # The lower middle value is the largest of those left of the middle (all <= upper).
    return 0.5 * (values[:middle].max() + upper)


def _tukey(residual: np.ndarray, scale: float) -> np.ndarray:
    ratio = residual / scale
    return np.where(np.abs(ratio) < 1.0, (1.0 - ratio**2) ** 2, 0.0)


def _require_pairs(count: int, distance: float, min_inliers: int) -> None:
    if count < min_inliers:
        raise ValueError(
            f"only {count} source points found a target point within {distance} m "
            f"(need {min_inliers}): the frames do not overlap, one is empty, or the initial pose is far off"
        )


@numba.njit(**_JIT)
def _cholesky(matrix, damping):  # pragma: no cover - compiled
    """The lower Cholesky factor of ``matrix + damping I`` (symmetric positive definite), written out (LAPACK
    costs seconds to compile)."""
    size = matrix.shape[0]
    lower = np.zeros((size, size))
    for i in range(size):
        for j in range(i + 1):
            total = matrix[i, j] + (damping if i == j else 0.0)
            for k in range(j):
                total -= lower[i, k] * lower[j, k]
            lower[i, j] = math.sqrt(total) if i == j else total / lower[j, j]
    return lower


@numba.njit(**_JIT)
def _cholesky_solve(lower, right):  # pragma: no cover - compiled
    """``x`` with ``L L^T x = right``, by forward and back substitution."""
    size = lower.shape[0]
    solution = np.empty(size)
    for i in range(size):
        total = right[i]
        for k in range(i):
            total -= lower[i, k] * solution[k]
        solution[i] = total / lower[i, i]
    for i in range(size - 1, -1, -1):
        total = solution[i]
        for k in range(i + 1, size):
            total -= lower[k, i] * solution[k]
        solution[i] = total / lower[i, i]
    return solution


@numba.njit(**_JIT)
def _solve(information, gradient):  # pragma: no cover - compiled
    """The Gauss-Newton step ``-(H + d I)^-1 g``, by Cholesky factors.

    A tiny damping ``d`` keeps the unconstrained directions of degenerate
    scenes still, and ``H + d I`` positive definite.
    """
    trace = 0.0
    for i in range(6):
        trace += information[i, i]
    return _cholesky_solve(_cholesky(information, 1e-9 * max(trace, 1e-12)), -gradient)


@numba.njit(**_JIT)
def _spd_inverse(matrix):  # pragma: no cover - compiled
    """The inverse of a symmetric positive definite matrix (a covariance, an information matrix), by its Cholesky
    factors."""
    size = matrix.shape[0]
    lower = _cholesky(matrix, 0.0)
    inverse = np.empty((size, size))
    unit = np.zeros(size)
    for column in range(size):
        unit[column] = 1.0
        inverse[:, column] = _cholesky_solve(lower, unit)
        unit[column] = 0.0
    return inverse


@numba.njit(**_JIT)
def _converged(delta, rotation_tolerance, translation_tolerance):  # pragma: no cover - compiled
    """The step (rotation vector, translation) is below both tolerances (radians, metres)."""
    rotation = math.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2)
    translation = math.sqrt(delta[3] ** 2 + delta[4] ** 2 + delta[5] ** 2)
    return rotation < rotation_tolerance and translation < translation_tolerance


def _point_to_plane_step(pairs: _Pairs, max_distance: float) -> np.ndarray:
    """One Gauss-Newton step of the point-to-plane error (small-angle linearisation)."""
    residual = pairs.residuals("point_to_plane")
    weights, _ = pairs.robust_weights("point_to_plane", max_distance)
    jacobian = pairs.plane_jacobian()
    weighted = jacobian * weights[:, None]
    return _solve(weighted.T @ jacobian, weighted.T @ residual)


def _point_to_point_step(pairs: _Pairs, max_distance: float) -> np.ndarray:
    """Weighted Kabsch step: the rigid motion that best maps the moved points onto their pairs."""
    weights, _ = pairs.robust_weights("point_to_point", max_distance)
    total = weights.sum()
    if total <= 0:
        return np.zeros(6)
    mean_source = weights @ pairs.moved / total
    mean_target = weights @ pairs.target / total
    cross = ((pairs.moved - mean_source) * weights[:, None]).T @ (pairs.target - mean_target)
    u, _, vt = np.linalg.svd(cross)
    correction = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    rotation = vt.T @ correction @ u.T
    translation = mean_target - rotation @ mean_source
    return np.concatenate([_log(rotation), translation])


@numba.njit(**_JIT)
def _exp(delta):  # pragma: no cover - compiled
    """(rotation vector, translation) as a 4x4 transform applied on the left (Rodrigues' formula)."""
    transform = np.eye(4)
    angle = math.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2)
    if angle > 0.0:
        # R = I + sin(a) K + (1 - cos(a)) K^2 with K the cross-product matrix of the unit axis k
        # and K^2 = k k^T - I, written out.
        kx, ky, kz = delta[0] / angle, delta[1] / angle, delta[2] / angle
        sine, versine = math.sin(angle), 1.0 - math.cos(angle)
        transform[0, 0] = 1.0 + versine * (kx * kx - 1.0)
        transform[0, 1] = versine * kx * ky - sine * kz
        transform[0, 2] = versine * kx * kz + sine * ky
        transform[1, 0] = versine * kx * ky + sine * kz
        transform[1, 1] = 1.0 + versine * (ky * ky - 1.0)
        transform[1, 2] = versine * ky * kz - sine * kx
        transform[2, 0] = versine * kx * kz - sine * ky
        transform[2, 1] = versine * ky * kz + sine * kx
        transform[2, 2] = 1.0 + versine * (kz * kz - 1.0)
    transform[0, 3], transform[1, 3], transform[2, 3] = delta[3], delta[4], delta[5]
    return transform


@numba.njit(**_JIT)
def _product(left, right):  # pragma: no cover - compiled
    """The matrix product ``left @ right`` of small matrices (written out: a BLAS call costs seconds to compile,
    and NumPy's costs microseconds of overhead on 4x4 and 6x6 matrices)."""
    product = np.zeros((left.shape[0], right.shape[1]))
    for i in range(left.shape[0]):
        for j in range(right.shape[1]):
            for k in range(left.shape[1]):
                product[i, j] += left[i, k] * right[k, j]
    return product


@numba.njit(**_JIT)
def _apply(matrix, vector):  # pragma: no cover - compiled
    """``matrix @ vector``, written out as `_product`."""
    result = np.zeros(matrix.shape[0])
    for i in range(matrix.shape[0]):
        for k in range(matrix.shape[1]):
            result[i] += matrix[i, k] * vector[k]
    return result


@numba.njit(**_JIT)
def _transform_inverse(transform):  # pragma: no cover - compiled
    """The inverse of a 4x4 transform ``[[A, t], [0, 1]]``: ``[[A^-1, -A^-1 t], [0, 1]]``, ``A^-1`` by its adjugate.

    Not ``A^T``: a pose is a rotation only to rounding, and chaining ``A^T``
    frame after frame (the constant-velocity prior) let that rounding grow
    until the pose failed `check_rigid_transform`.
    """
    a, b, c = transform[0, 0], transform[0, 1], transform[0, 2]
    d, e, f = transform[1, 0], transform[1, 1], transform[1, 2]
    g, h, k = transform[2, 0], transform[2, 1], transform[2, 2]
    cofactor_a, cofactor_b, cofactor_c = e * k - f * h, f * g - d * k, d * h - e * g
    scale = 1.0 / (a * cofactor_a + b * cofactor_b + c * cofactor_c)
    inverse = np.eye(4)
    inverse[0, 0], inverse[0, 1], inverse[0, 2] = cofactor_a * scale, (c * h - b * k) * scale, (b * f - c * e) * scale
    inverse[1, 0], inverse[1, 1], inverse[1, 2] = cofactor_b * scale, (a * k - c * g) * scale, (c * d - a * f) * scale
    inverse[2, 0], inverse[2, 1], inverse[2, 2] = cofactor_c * scale, (b * g - a * h) * scale, (a * e - b * d) * scale
    for i in range(3):
        inverse[i, 3] = -(inverse[i, 0] * transform[0, 3] + inverse[i, 1] * transform[1, 3]
                          + inverse[i, 2] * transform[2, 3])
    return inverse


@numba.njit(**_JIT)
def _log(rotation):  # pragma: no cover - compiled
    """The rotation vector of a 3x3 rotation matrix (the inverse of `_exp`'s rotation).

    Through the unit quaternion, taken from its largest component (Shepperd's
    method), so that it stays accurate at every angle up to 180 degrees.
    """
    m00, m01, m02 = rotation[0, 0], rotation[0, 1], rotation[0, 2]
    m10, m11, m12 = rotation[1, 0], rotation[1, 1], rotation[1, 2]
    m20, m21, m22 = rotation[2, 0], rotation[2, 1], rotation[2, 2]
    trace = m00 + m11 + m22
    if trace >= m00 and trace >= m11 and trace >= m22:
        w = 0.5 * math.sqrt(1.0 + trace)
        x, y, z = (m21 - m12) / (4.0 * w), (m02 - m20) / (4.0 * w), (m10 - m01) / (4.0 * w)
    elif m00 >= m11 and m00 >= m22:
        x = 0.5 * math.sqrt(1.0 + m00 - m11 - m22)
        w, y, z = (m21 - m12) / (4.0 * x), (m01 + m10) / (4.0 * x), (m02 + m20) / (4.0 * x)
    elif m11 >= m22:
        y = 0.5 * math.sqrt(1.0 - m00 + m11 - m22)
        w, x, z = (m02 - m20) / (4.0 * y), (m01 + m10) / (4.0 * y), (m12 + m21) / (4.0 * y)
    else:
        z = 0.5 * math.sqrt(1.0 - m00 - m11 + m22)
        w, x, y = (m10 - m01) / (4.0 * z), (m02 + m20) / (4.0 * z), (m12 + m21) / (4.0 * z)
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    sine = math.sqrt(x * x + y * y + z * z)
    # angle / sin(angle / 2); x, y, z are all 0 when the sine is.
    factor = 2.0 * math.atan2(sine, w) / sine if sine > 0.0 else 0.0
    return np.array([factor * x, factor * y, factor * z])


@numba.njit(**_JIT)
def _covariance(information, rmse):  # pragma: no cover - compiled
    """sigma^2 (J^T W J)^-1, and the directions the information matrix does not constrain (inf along them)."""
    values, vectors = np.linalg.eigh(information)
    size = values.shape[0]
    top = max(values[-1], 1e-300)
    weak = values < _DEGENERATE_RATIO * top
    n_weak = np.count_nonzero(weak)
    variance = rmse * rmse if math.isfinite(rmse) else np.nan
    covariance = np.empty((size, size))
    for i in range(size):
        for j in range(size):
            total = 0.0
            for k in range(size):
                total += vectors[i, k] * (math.inf if weak[k] else 1.0 / values[k]) * vectors[j, k]
            value = total * variance
            # With a weak direction, inf - inf (and 0 inf) is unknown too.
            covariance[i, j] = math.inf if n_weak and value != value else value
    unconstrained = np.empty((n_weak, size))
    row = 0
    for k in range(size):
        if weak[k]:
            unconstrained[row] = vectors[:, k]
            row += 1
    return covariance, unconstrained



# --------------------------------------------------------------------------
# Compiled projective point-to-plane (depth cameras).
# --------------------------------------------------------------------------


@numba.njit(**_JIT)
def _projective_pass(
    source, transform, grid, normals, intrinsics, max_distance, scale, residuals, rows, source_noise, target_variance,
    min_incidence,
):  # pragma: no cover - compiled
    """Pair, then accumulate J^T W J and J^T W r of the Tukey-weighted point-to-plane residuals (J = [p x n, n]).

    Every paired residual is written to ``residuals`` (for the next robust
    scale); returns (information, gradient, pairs, inliers, sum of the
    inliers' squared residuals, sum of their squared normalized residuals),
    inliers being the pairs of nonzero weight. The source points go in
    chunks of C (``rows`` is (8, C)): a branch-free loop moves and projects
    a chunk (which the compiler vectorises), a second pairs its points with
    their pixels and writes the inliers' Jacobian rows, residuals and
    weights to ``rows``, which `_accumulate` sums every C inliers. (Pairing
    point by point in one loop with the projection, and summing the 27
    products inlier by inlier, took 40 % longer.)

    With range noise (``source_noise``, sigma^2 / |p|^2 per source point,
    and the target's share of the variance ``target_variance`` per pixel;
    empty when not given)
    each residual is normalized by its standard deviation from range noise,
    ``sigma_r^2 = sum sigma^2 max((n . u)^2, min_incidence)`` over the
    frames given (`_along_normal`; ``u`` the unit line of sight to the
    point): the Tukey test (``scale`` in units of ``sigma_r``) and
    ``residuals`` take ``r / sigma_r``, the weights carry ``1 / sigma_r^2``.
    """
    sums = np.zeros((6, 7))
    # The transform and intrinsics in registers, not reloaded per point.
    t00, t01, t02, t03 = transform[0, 0], transform[0, 1], transform[0, 2], transform[0, 3]
    t10, t11, t12, t13 = transform[1, 0], transform[1, 1], transform[1, 2], transform[1, 3]
    t20, t21, t22, t23 = transform[2, 0], transform[2, 1], transform[2, 2], transform[2, 3]
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    height, width = grid.shape[0], grid.shape[1]
    targets = grid.reshape(height * width, 3)
    target_normals = normals.reshape(height * width, 3)
    limit = max_distance * max_distance
    with_source, with_target = source_noise.shape[0] > 0, target_variance.shape[0] > 0
    flat_variance = target_variance.reshape(target_variance.size)
    chunk = rows.shape[1]
    moved = np.empty((3, chunk))
    pixel = np.empty(chunk, np.int64)
    weighted = np.empty((6, chunk))
    count = inliers = filled = 0
    squares = normalized_squares = 0.0
    for begin in range(0, source.shape[0], chunk):
        end = min(begin + chunk, source.shape[0])
        for k in range(begin, end):
            x, y, z = source[k, 0], source[k, 1], source[k, 2]
            mx = t00 * x + t01 * y + t02 * z + t03
            my = t10 * x + t11 * y + t12 * z + t13
            mz = t20 * x + t21 * y + t22 * z + t23
            # Nearest pixel (truncation of a non-negative value rounds; the rest are no pixel).
            fu = fx * mx / mz + cx + 0.5
            fv = fy * my / mz + cy + 0.5
            inside = (mz > 0.0) & (fu >= 0.0) & (fv >= 0.0) & (fu < width) & (fv < height)
            moved[0, k - begin], moved[1, k - begin], moved[2, k - begin] = mx, my, mz
            pixel[k - begin] = np.int64(fv) * width + np.int64(fu) if inside else -1
        for i in range(end - begin):
            target = pixel[i]
            if target < 0:
                continue
            tz = targets[target, 2]
            nz = target_normals[target, 2]
            if not (tz == tz and nz == nz):
                continue
            mx, my, mz = moved[0, i], moved[1, i], moved[2, i]
            tx, ty = targets[target, 0], targets[target, 1]
            nx, ny = target_normals[target, 0], target_normals[target, 1]
            if (mx - tx) ** 2 + (my - ty) ** 2 + (mz - tz) ** 2 > limit:
                continue
            residual = (mx - tx) * nx + (my - ty) * ny + (mz - tz) * nz
            inverse_variance = 1.0
            normalized = residual
            if with_source or with_target:
                variance = 0.0
                if with_target:
                    variance += flat_variance[target]
                if with_source:
                    # The source's line of sight in the target frame: from its sensor (the translation) to the moved point.
                    variance += _along_normal(source_noise[begin + i], nx, ny, nz, mx - t03, my - t13, mz - t23, min_incidence)
                inverse_variance = 1.0 / variance
                # The root only where there are sigmas: unweighted, every pair would pay for it.
                normalized = residual * math.sqrt(inverse_variance)
            residuals[count] = normalized
            count += 1
            ratio = normalized / scale
            if abs(ratio) >= 1.0:
                continue
            inliers += 1
            squares += residual * residual
            normalized_squares += normalized * normalized
            rows[0, filled] = my * nz - mz * ny
            rows[1, filled] = mz * nx - mx * nz
            rows[2, filled] = mx * ny - my * nx
            rows[3, filled] = nx
            rows[4, filled] = ny
            rows[5, filled] = nz
            rows[6, filled] = residual
            rows[7, filled] = (1.0 - ratio * ratio) ** 2 * inverse_variance
            filled += 1
            if filled == chunk:
                _accumulate(rows, filled, sums, weighted)
                filled = 0
    _accumulate(rows, filled, sums, weighted)
    information = np.empty((6, 6))
    for a in range(6):
        for b in range(a, 6):
            information[a, b] = information[b, a] = sums[a, b]
    return information, sums[:, 6].copy(), count, inliers, squares, normalized_squares


@numba.njit(**_JIT)
def _along_normal(scaled, nx, ny, nz, rx, ry, rz, min_incidence):  # pragma: no cover - compiled
    """Variance along the normal n of a point at r whose range errs by sigma: sigma^2 max((n . u)^2, min_incidence), u = r / |r|.

    Range noise moves a point along its line of sight; the residual sees the
    part along the normal. From ``scaled = sigma^2 / |r|^2`` (per point, in
    advance) as ``scaled max((n . r)^2, min_incidence |r|^2)``: no root and
    no division in the passes, which run it for every pair.
    """
    along = nx * rx + ny * ry + nz * rz
    return scaled * max(along * along, min_incidence * (rx * rx + ry * ry + rz * rz))


@numba.njit(**_JIT)
def _pair_variances(normals, target_variance, rays, source_noise, min_incidence):  # pragma: no cover - compiled
    """Point-to-plane residual variances of pairs from range noise, as in `_projective_pass` (empty arrays are left out).

    ``target_variance`` is the target points' share (`_target_variance`),
    ``rays`` are the source points' lines of sight in the target frame.
    """
    variance = np.zeros(len(normals))
    for k in range(len(normals)):
        if len(target_variance):
            variance[k] = target_variance[k]
        if len(source_noise):
            variance[k] += _along_normal(source_noise[k], normals[k, 0], normals[k, 1], normals[k, 2], rays[k, 0], rays[k, 1],
                                         rays[k, 2], min_incidence)
    return variance


@numba.njit(**_JIT)
def _accumulate(rows, filled, sums, weighted):  # pragma: no cover - compiled
    """Add sum_k w_k J_ka J_kb (b < 6) and sum_k w_k J_ka r_k (b = 6) of the first ``filled`` columns of
    ``rows`` to ``sums``, a <= b; ``weighted`` (6, C) is room for w_k J_ka."""
    for a in range(6):
        for k in range(filled):
            weighted[a, k] = rows[7, k] * rows[a, k]
    for a in range(6):
        for b in range(a, 7):
            sums[a, b] += _dot(weighted[a], rows[b], filled)


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def _dot(left, right, count):  # pragma: no cover - compiled
    """``left[:count] . right[:count]``, summed in any order: the compiler vectorises it (27 of these over a
    chunk of inliers are four times faster than summing the 27 products inlier by inlier)."""
    total = 0.0
    for k in range(count):
        total += left[k] * right[k]
    return total


@numba.njit(**_JIT)
def _projective_level(
    source, transform, grid, normals, intrinsics, max_distance, scale, max_iterations, rotation_tolerance,
    translation_tolerance, min_inliers, source_noise, target_variance, min_incidence, scale_distance,
):  # pragma: no cover - compiled
    """One coarse-to-fine level of projective point-to-plane ICP: Gauss-Newton steps until one is below the tolerances.

    Each pass weighs its pairs with the robust scale of the previous pass's
    residuals (at most ``_TUKEY * scale_distance``; sigmas and
    ``min_incidence`` as in `_projective_pass`). Returns (transform, scale,
    iterations, converged, pairs of the last pass, and that pass's
    information, inliers, sum of squared and of squared normalized
    residuals); a pass with fewer than ``min_inliers`` pairs ends the level
    there.
    """
    residuals = np.empty(source.shape[0])
    rows = np.empty((8, _CHUNK))
    count = iteration = inliers = 0
    squares = normalized = 0.0
    information = np.zeros((6, 6))
    converged = False
    while iteration < max_iterations and not converged:
        information, gradient, count, inliers, squares, normalized = _projective_pass(
            source, transform, grid, normals, intrinsics, max_distance, scale, residuals, rows, source_noise,
            target_variance, min_incidence,
        )
        if count < min_inliers:
            break
        scale = _robust_scale(residuals[:count], scale_distance)
        delta = _solve(information, gradient)
        transform = _product(_exp(delta), transform)
        converged = _converged(delta, rotation_tolerance, translation_tolerance)
        iteration += 1
    return transform, scale, iteration, converged, count, information, inliers, squares, normalized
