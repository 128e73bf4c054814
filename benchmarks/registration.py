"""Frame-to-frame registration against OpenCV ``ICPOdometry`` and Open3D point-to-plane ICP.

Run: ``.venv/bin/python benchmarks/registration.py``; writes
``benchmarks/results/registration.md``. Consecutive simulated arena frames
(SR-3000 176x144 and Kinect 640x480, all noise effects on, denoised), each
pair registered from a noisy odometry guess (`simulate.noisy_odometry`: 5 % of
the step and 0.5 degrees per axis off) by rangesurf `icp` (projective
point-to-plane, residuals weighted by both frames' range noise, as the
pipeline registers), OpenCV contrib ``cv2.rgbd.ICPOdometry`` (depth only, its
defaults) and Open3D ``registration_icp`` (point-to-plane, k-d tree, 2 cm
correspondences). One core each; errors against the simulator's true motion.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, time_pair, write_results  # noqa: E402
from rangesurf.denoise import denoise_range  # noqa: E402
from rangesurf.normals import estimate_normals  # noqa: E402
from rangesurf.register import icp, pose_error  # noqa: E402

# Enough pairs that the worst case is not one unlucky frame (6 pairs once put OpenCV ahead at
# 640x480 by 0.1 mm; over 50 it is behind).
PAIRS = 25


def prepare(frame):
    """Denoised points, their normals and range sigmas (the pipeline's, at the denoised range)."""
    smooth = denoise_range(frame.range, sensor=frame.sensor, intensity=frame.intensity, rays=frame.rays)
    points = (frame.rays * smooth[..., None]).astype(np.float32)
    sigma = frame.sensor.range_sigma(np.where(np.isfinite(smooth), smooth, 1.0), frame.intensity)
    return points, estimate_normals(points, projection=frame.sensor.projection, range_sigma=sigma), sigma


def main() -> None:
    import open3d as o3d

    cv2.setNumThreads(1)
    o3d.utility.set_max_threads(1) if hasattr(o3d.utility, "set_max_threads") else None
    lines = [
        f"Machine: {machine_description()}; one core each (cv2.setNumThreads(1), Open3D one thread).",
        "",
        f"{PAIRS} consecutive pairs per sensor, from a noisy odometry guess (5 % of the step, 0.5 deg per axis); errors "
        "(rotation, translation at the sensor) against the true motion, RMS and worst over the pairs; times are medians, and the ratio is "
        "peer time / rangesurf time, alternating (> 1: rangesurf faster). Inputs: the denoised frames; OpenCV gets "
        "their depth (z), Open3D their points and rangesurf's normals of the target, rangesurf also both frames' range "
        "sigmas.",
        "",
        "| sensor | method | rotation RMS / worst (deg) | translation RMS / worst (mm) | ms per pair | speed ratio |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for sensor in ("sr3000", "kinect"):
        frames, truths = simulate.simulate_sequence("arena", sensor, PAIRS + 1, seed=8)
        # Wheel-odometry-like guesses (5 % of each step, 0.5 degrees per axis), not the true motion.
        odometry_poses = simulate.noisy_odometry(np.asarray([truth.T_world_sensor for truth in truths]), seed=8)
        projection = frames[0].sensor.projection
        camera = np.array([[projection.fx, 0, projection.cx], [0, projection.fy, projection.cy], [0, 0, 1]], float)
        prepared = [prepare(frame) for frame in frames]
        rows = {"rangesurf icp": [], "OpenCV ICPOdometry": [], "Open3D registration_icp": []}
        for k in range(PAIRS):
            (target_points, target_normals, target_sigma), (source_points, _, source_sigma) = prepared[k], prepared[k + 1]
            truth = np.linalg.inv(truths[k].T_world_sensor) @ truths[k + 1].T_world_sensor
            guess = np.linalg.inv(odometry_poses[k]) @ odometry_poses[k + 1]

            def ours():
                return icp(source_points, target_points, target_normals, initial=guess, target_projection=projection,
                           source_sigma=source_sigma, target_sigma=target_sigma).T_target_source

            depth_t = np.nan_to_num(target_points[..., 2]).astype(np.float32)
            depth_s = np.nan_to_num(source_points[..., 2]).astype(np.float32)
            odometry = cv2.rgbd.ICPOdometry_create(camera)

            def opencv():
                frame_t = cv2.rgbd.OdometryFrame_create(None, depth_t, ((depth_t > 0) * 255).astype(np.uint8))
                frame_s = cv2.rgbd.OdometryFrame_create(None, depth_s, ((depth_s > 0) * 255).astype(np.uint8))
                odometry.prepareFrameCache(frame_t, cv2.rgbd.OdometryFrame_CACHE_ALL)
                odometry.prepareFrameCache(frame_s, cv2.rgbd.OdometryFrame_CACHE_ALL)
                _, transform = odometry.compute2(frame_s, frame_t, guess)
                return transform

            valid_t = np.isfinite(target_points).all(axis=2) & np.isfinite(target_normals).all(axis=2)
            cloud_t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target_points[valid_t].astype(float)))
            cloud_t.normals = o3d.utility.Vector3dVector(target_normals[valid_t].astype(float))
            cloud_s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
                source_points[np.isfinite(source_points).all(axis=2)].astype(float)))
            point_to_plane = o3d.pipelines.registration.TransformationEstimationPointToPlane()

            def open3d():
                return o3d.pipelines.registration.registration_icp(cloud_s, cloud_t, 0.02, guess, point_to_plane).transformation

            for name, run in (("rangesurf icp", ours), ("OpenCV ICPOdometry", opencv), ("Open3D registration_icp", open3d)):
                if name == "rangesurf icp":
                    ours_s, _ = time_pair(ours, ours, repeats=3)
                    ratio = 1.0
                    seconds = ours_s
                else:
                    ours_s, seconds = time_pair(ours, run, repeats=3)
                    ratio = seconds / ours_s
                rotation, translation = pose_error(np.asarray(run()), truth)
                rows[name].append((rotation, translation, seconds, ratio))
        height, width = frames[0].range.shape
        for name, values in rows.items():
            values = np.array(values)
            ratio = "—" if name == "rangesurf icp" else f"{np.median(values[:, 3]):.2f}x"
            rotation_rms, translation_rms = np.sqrt(np.mean(values[:, :2] ** 2, axis=0))
            lines.append(f"| {width}x{height} {sensor} | {name} | {rotation_rms:.4f} / {values[:, 0].max():.3f} "
                         f"| {1000 * translation_rms:.2f} / {1000 * values[:, 1].max():.2f} "
                         f"| {1000 * np.median(values[:, 2]):.1f} | {ratio} |")
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    write_results(Path(__file__).parent / "results", "registration.md", lines)


if __name__ == "__main__":
    main()
