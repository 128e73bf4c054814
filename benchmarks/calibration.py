"""Calibration of the uncertainty levels against ground truth (simulated sequences).

Run: ``.venv/bin/python benchmarks/calibration.py [N_FRAMES] [SCENE/SENSOR,...]``
(default 100 frames; Kinect sequences get half as many); writes
``benchmarks/results/calibration.md``.

A level is calibrated when +-2 of its sigmas hold about 95 % of the error it
describes, so each level is checked against its own error, isolated with the
simulator's ground truth:

* **UL1** (sensor): the sequence run with the true poses (the tracker trusts
  the odometry, which is exact), so the model's error is the sensor's alone;
  vertices whose fit level UL2 is 0 (no local model error flagged).
* **UL1+UL2** (sensor and patch fit): the same run, every vertex.
* **UL3** (registration): the normal-direction displacement that the tracked
  pose's error gives each segmented pixel of every frame,
  ``n . (T_est p - T_true p)``, against ``sqrt(J Sigma J^T)`` with the
  tracked world covariance ``Sigma`` and ``J = [p x n, n]`` (what the model's
  UL3 carries for those points); drifting odometry.
* **UL4** (level of detail): each surface of the final model at 10 % of its
  vertices; the removed vertices' height above the coarse triangulation
  against the UL4 of the nearest kept vertex.
* **combined**: the default run from drifting odometry, UL1-UL3 summed in
  squares, the final full-resolution model's vertices (UL4 = 0) against
  the true planes.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial import Delaunay, cKDTree  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, write_results  # noqa: E402
from rangesurf.config import PipelineConfig, RegisterSettings  # noqa: E402
from rangesurf.frame import get_sensor  # noqa: E402
from rangesurf.lod import _plane_frame, build_levels  # noqa: E402
from rangesurf.pipeline import Pipeline  # noqa: E402
from rangesurf.uncertainty import distance_to_planes  # noqa: E402

# Odometry sigmas that make the tracker keep the (exact) odometry pose.
_TRUSTED = PipelineConfig(register=RegisterSettings(odometry_sigma_rotation=1e-7, odometry_sigma_translation=1e-7,
                                                    odometry_sigma_relative=0.0))
# Pixels per frame scored for UL3 (every n-th segmented pixel).
_UL3_SAMPLE = 7


def run(scene: str, sensor: str, count: int, *, exact: bool):
    """The sequence through a `Pipeline`; returns it, its true poses and the UL3 samples (|error|, sigma)."""
    true_poses = simulate.default_trajectory(scene, count, frame_rate=get_sensor(sensor).frame_rate)
    odometry = true_poses if exact else simulate.noisy_odometry(true_poses, seed=5)
    pipeline = Pipeline(_TRUSTED if exact else None)
    errors, sigmas = [], []
    for k, (frame, _) in enumerate(simulate.iter_sequence(scene, sensor, count, seed=5, trajectory=true_poses)):
        result = pipeline.process(dataclasses.replace(frame, pose=odometry[k]))
        if k == 0 or exact:
            continue
        labels = result.segmentation.labels
        rows, cols = np.nonzero(labels > 0)
        rows, cols = rows[::_UL3_SAMPLE], cols[::_UL3_SAMPLE]
        points = frame.rays[rows, cols].astype(np.float64) * result.range[rows, cols, None]
        keep = np.isfinite(points).all(axis=1)
        points, normals = points[keep], result.segmentation.planes[labels[rows, cols][keep], :3]
        estimate, truth = result.T_world_sensor, true_poses[k]
        world = points @ estimate[:3, :3].T + estimate[:3, 3]
        world_normals = normals @ estimate[:3, :3].T
        moved = world - (points @ truth[:3, :3].T + truth[:3, 3])
        errors.append(np.abs(np.einsum("ij,ij->i", moved, world_normals)))
        jacobian = np.hstack([np.cross(world, world_normals), world_normals])
        sigmas.append(np.sqrt(np.einsum("ij,jk,ik->i", jacobian, result.covariance, jacobian)))
    samples = (np.concatenate(errors), np.concatenate(sigmas)) if errors else None
    return pipeline, samples


def lod_samples(surfaces, fraction: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Removed vertices' height above the coarse level, and the UL4 of their nearest kept vertex."""
    errors, sigmas = [], []
    for surface in surfaces:
        if surface.lod_order is None or surface.n_vertices < 50:
            continue
        surface.levels = surface.levels or build_levels(surface)
        coarse = surface.at_level(fraction=fraction)
        kept = surface.lod_order[: coarse.n_vertices]
        removed = surface.lod_order[coarse.n_vertices:]
        if len(kept) < 4 or not len(removed):
            continue
        xy, height, _ = _plane_frame(surface)
        triangulation = Delaunay(xy[kept])
        simplex = triangulation.find_simplex(xy[removed])
        inside = simplex >= 0
        transform = triangulation.transform[simplex[inside]]
        partial = np.einsum("ijk,ik->ij", transform[:, :2], xy[removed][inside] - transform[:, 2])
        weights = np.column_stack([partial, 1.0 - partial.sum(axis=1)])
        interpolated = (height[kept][triangulation.simplices[simplex[inside]]] * weights).sum(axis=1)
        _, nearest = cKDTree(xy[kept]).query(xy[removed][inside])
        errors.append(np.abs(height[removed][inside] - interpolated))
        sigmas.append(coarse.uncertainty["UL4"][nearest])
    return np.concatenate(errors), np.concatenate(sigmas)


def matched_errors(surfaces, planes) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Distance of every vertex to its true plane and its UL1-UL3, for the vertices on a plane (within 20 cm)."""
    vertices = np.vstack([s.vertices for s in surfaces])
    error = distance_to_planes(vertices, np.vstack([s.normals for s in surfaces]), planes)
    matched = np.isfinite(error) & (error <= 0.2)
    levels = {level: np.concatenate([s.uncertainty[level] for s in surfaces])[matched] for level in ("UL1", "UL2", "UL3")}
    return error[matched], levels


def main() -> None:
    n_frames = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    chosen = sys.argv[2].split(",") if len(sys.argv) > 2 else ["arena/sr3000", "corridor/sr3000", "arena/kinect", "corridor/kinect"]
    lines = [f"Machine: {machine_description()}. Command: `.venv/bin/python benchmarks/calibration.py {n_frames}`.", "",
             f"{n_frames} frames per sequence (Kinect: half as many), default pipeline. Coverage: share of errors "
             "within +-2 sigma, each level against the error it describes (see the script's notes): UL1 and "
             "UL1+UL2 on a run with the true poses, UL3 per frame on a run from drifting odometry, UL4 at 10 % of "
             "the vertices, *combined* (root sum of squares of UL1-UL3) on the final, full-resolution model of the drifting run. "
             "Calibrated: 90-98 %.", "",
             "| scene | sensor | UL1 | UL1+UL2 | UL3 | UL4 | combined | vertices | error median / p95 (mm) "
             "| UL1 / UL2 / UL3 median (mm) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for scene, sensor in (tuple(item.split("/")) for item in chosen):
        count = n_frames if sensor == "sr3000" else n_frames // 2
        planes = simulate.get_scene(scene).planes
        planes = planes[np.isfinite(planes).all(axis=1)]

        exact, _ = run(scene, sensor, count, exact=True)
        error, levels = matched_errors(exact.finish(), planes)
        unflagged = levels["UL2"] == 0
        sensor_only = np.mean(error[unflagged] <= 2 * levels["UL1"][unflagged])
        with_fit = np.mean(error <= 2 * np.hypot(levels["UL1"], levels["UL2"]))

        drifting, (ul3_error, ul3_sigma) = run(scene, sensor, count, exact=False)
        surfaces = drifting.finish()
        ul4_error, ul4_sigma = lod_samples(surfaces)
        # The full-resolution model, where UL4 is 0.
        error, levels = matched_errors(surfaces, planes)
        combined = np.mean(error <= 2 * np.sqrt(levels["UL1"] ** 2 + levels["UL2"] ** 2 + levels["UL3"] ** 2))
        medians = [1e3 * np.median(levels[level]) for level in ("UL1", "UL2", "UL3")]
        lines.append(
            f"| {scene} | {sensor} | {sensor_only:.1%} | {with_fit:.1%} | {np.mean(ul3_error <= 2 * ul3_sigma):.1%} "
            f"| {np.mean(ul4_error <= 2 * ul4_sigma):.1%} | {combined:.1%} | {len(error):,} "
            f"| {1e3 * np.median(error):.1f} / {1e3 * np.percentile(error, 95):.1f} "
            f"| {medians[0]:.2f} / {medians[1]:.2f} / {medians[2]:.2f} |")
        print(lines[-1], flush=True)
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    write_results(Path(__file__).parent / "results", "calibration.md", lines)


if __name__ == "__main__":
    main()
