"""Drift of frame-to-frame tracking over long simulated sequences (TUM ATE / RPE).

Run: ``.venv/bin/python benchmarks/drift.py [N_FRAMES]`` (default 200); writes
``benchmarks/results/drift.md``. For each sensor and scene, the robot's
true path is simulated with all noise effects on; its frames carry noisy
wheel odometry (`simulate.noisy_odometry`: 5 % of each step's length and
0.5 degrees per axis and step), and `register.FrameTracker` chains
frame-to-frame ICP from that odometry (denoised frames, projective
point-to-plane). Errors against the true poses, TUM conventions
(`rangesurf.trajectory`): RPE over one frame (per-frame error) and ATE
after alignment, for the tracker and for the odometry alone.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, write_results  # noqa: E402
from rangesurf.denoise import denoise_range  # noqa: E402
from rangesurf.frame import get_sensor  # noqa: E402
from rangesurf.normals import estimate_normals  # noqa: E402
from rangesurf.register import FrameTracker  # noqa: E402
from rangesurf.trajectory import absolute_trajectory_error, relative_pose_error  # noqa: E402


def prepare(frame):
    smooth = denoise_range(frame.range, sensor=frame.sensor, intensity=frame.intensity, rays=frame.rays)
    points = (frame.rays * smooth[..., None]).astype(np.float32)
    sigma = frame.sensor.range_sigma(np.where(np.isfinite(smooth), smooth, 1.0), frame.intensity)
    return points, estimate_normals(points, projection=frame.sensor.projection, range_sigma=sigma)


def run(scene: str, sensor: str, n_frames: int, seed: int) -> dict:
    true_poses = simulate.default_trajectory(scene, n_frames, frame_rate=get_sensor(sensor).frame_rate)
    odometry_poses = simulate.noisy_odometry(true_poses, seed=seed)
    tracker = FrameTracker()
    estimate, truth, icp_ms, fallbacks, degenerate = [], [], [], 0, 0
    sequence = simulate.iter_sequence(scene, sensor, n_frames, seed=seed, trajectory=true_poses)
    for k, (frame, ground) in enumerate(tqdm(sequence, total=n_frames, desc=f"{scene}/{sensor}", leave=False)):
        frame = dataclasses.replace(frame, pose=odometry_poses[k])
        points, normals = prepare(frame)
        start = time.perf_counter()
        tracked = tracker.track(points, normals, projection=frame.sensor.projection, odometry=frame.pose)
        icp_ms.append(1e3 * (time.perf_counter() - start))
        fallbacks += tracked.fallback
        degenerate += bool(tracked.registration is not None and tracked.registration.degenerate)
        estimate.append(tracked.T_world_sensor)
        truth.append(ground.T_world_sensor)
    estimate, truth = np.asarray(estimate), np.asarray(truth)
    path_length = float(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum())
    return {
        "tracker": (relative_pose_error(estimate, truth), absolute_trajectory_error(estimate, truth)),
        "odometry": (relative_pose_error(odometry_poses, truth), absolute_trajectory_error(odometry_poses, truth)),
        "path": path_length, "icp_ms": float(np.median(icp_ms[1:])), "fallbacks": fallbacks, "degenerate": degenerate,
        "end": float(np.linalg.norm(estimate[-1, :3, 3] - truth[-1, :3, 3])),
        "end_odometry": float(np.linalg.norm(odometry_poses[-1, :3, 3] - truth[-1, :3, 3])),
    }


def main() -> None:
    cv2.setNumThreads(1)
    n_frames = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    lines = [
        f"Machine: {machine_description()}. Command: `.venv/bin/python benchmarks/drift.py {n_frames}`.",
        "",
        f"{n_frames} frames per sequence; odometry noise 5 % of each step plus 1 mm, 0.5 deg per axis and step. "
        "RPE: the error of each frame-to-frame motion (rotation angle, translation length); ATE: position error "
        "after the best rigid alignment (TUM). Median ICP time per frame (one core) in the last column.",
        "",
        "| scene | sensor | path (m) | source | RPE rot max / RMSE (deg) | RPE trans max / RMSE (mm) | ATE RMSE (mm) "
        "| end-point error (mm) | degenerate / failed frames | ICP ms |",
        "|---|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for scene, sensor, seed in (("arena", "sr3000", 1), ("corridor", "sr3000", 2), ("arena", "kinect", 3)):
        result = run(scene, sensor, n_frames, seed)
        for source in ("tracker", "odometry"):
            rpe, ate = result[source]
            end = result["end" if source == "tracker" else "end_odometry"]
            extra = f"{result['degenerate']} / {result['fallbacks']} | {result['icp_ms']:.1f}" if source == "tracker" else "— | —"
            lines.append(
                f"| {scene} | {sensor} | {result['path']:.1f} | {'FrameTracker' if source == 'tracker' else 'odometry alone'} "
                f"| {rpe.rotation.max:.3f} / {rpe.rotation.rmse:.3f} | {1e3 * rpe.translation.max:.1f} / "
                f"{1e3 * rpe.translation.rmse:.1f} | {1e3 * ate.translation.rmse:.1f} | {1e3 * end:.0f} | {extra} |"
            )
        print(lines[-2], lines[-1], sep="\n")
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    write_results(Path(__file__).parent / "results", "drift.md", lines)


if __name__ == "__main__":
    main()
