"""Calibration of the uncertainty levels against ground truth (simulated sequences).

Run: ``.venv/bin/python benchmarks/calibration.py [N_FRAMES]`` (default 100);
writes ``benchmarks/results/calibration.md``. Each sequence runs through the
default `Pipeline` from drifting odometry; the model's vertices are compared
with the scene's true planes (`rangesurf.uncertainty.coverage`): the share
of them within +-2 sigma of the true surface, for each level alone and for
their root sum of squares. Calibrated levels cover about 95 % combined.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, write_results  # noqa: E402
from rangesurf.frame import get_sensor  # noqa: E402
from rangesurf.pipeline import Pipeline  # noqa: E402
from rangesurf.uncertainty import coverage, distance_to_planes  # noqa: E402


def main() -> None:
    n_frames = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    lines = [f"Machine: {machine_description()}. Command: `.venv/bin/python benchmarks/calibration.py {n_frames}`.", "",
             f"{n_frames} frames per sequence (Kinect: half as many), default pipeline, noisy odometry. Coverage: share "
             "of model vertices within +-2 sigma of the true plane, per level and combined (root sum of squares).", "",
             "| scene | sensor | vertices | error median / p95 (mm) | UL1 | UL2 | UL3 | combined | UL1 median (mm) | UL2 median | UL3 median |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for scene, sensor in [tuple(x.split("/")) for x in (sys.argv[2].split(",") if len(sys.argv) > 2 else ["arena/sr3000", "corridor/sr3000", "arena/kinect", "corridor/kinect"])]:
        count = n_frames if sensor == "sr3000" else n_frames // 2
        true_poses = simulate.default_trajectory(scene, count, frame_rate=get_sensor(sensor).frame_rate)
        odometry = simulate.noisy_odometry(true_poses, seed=5)
        pipeline = Pipeline()
        for k, (frame, _) in enumerate(simulate.iter_sequence(scene, sensor, count, seed=5, trajectory=true_poses)):
            pipeline.process(dataclasses.replace(frame, pose=odometry[k]))
        surfaces = pipeline.finish()
        planes = simulate.get_scene(scene).planes
        planes = planes[np.isfinite(planes).all(axis=1)]
        shares = coverage(surfaces, planes)
        error = distance_to_planes(np.vstack([s.vertices for s in surfaces]), np.vstack([s.normals for s in surfaces]), planes)
        error = error[np.isfinite(error) & (error <= 0.2)]
        medians = {level: 1e3 * np.median(np.concatenate([s.uncertainty[level] for s in surfaces if level in s.uncertainty]))
                   for level in ("UL1", "UL2", "UL3")}
        lines.append(f"| {scene} | {sensor} | {shares['matched']} | {1e3 * np.median(error):.1f} / {1e3 * np.percentile(error, 95):.1f} "
                     f"| {shares['UL1']:.1%} | {shares['UL2']:.1%} | {shares['UL3']:.1%} | {shares['combined']:.1%} "
                     f"| {medians['UL1']:.2f} | {medians['UL2']:.2f} | {medians['UL3']:.2f} |")
        print(lines[-1])
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    write_results(Path(__file__).parent / "results", "calibration.md", lines)


if __name__ == "__main__":
    main()
