"""Frames per second of the whole denoise stage (`denoise_range`) at 176x144 and 640x480.

Run: ``.venv/bin/python benchmarks/denoise_speed.py``; writes
``benchmarks/results/denoise_speed.md``. Frames are simulated in the arena with
every noise effect on (range noise, mixed pixels, spikes, cut-off); RMSE is
against ground truth on pixels valid before and after.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangesurf import denoise, simulate
from rangesurf.bench import machine_description, time_call, write_results


def main() -> None:
    lines = [
        f"Machine: {machine_description()}; one frame at a time, single-threaded kernels (phase uses 2 FFT threads).",
        "",
        "| sensor | method (after outlier removal) | ms/frame | frames/s | RMSE raw mm | RMSE denoised mm |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for sensor in ("sr3000", "kinect"):
        frames, truths = simulate.simulate_sequence("arena", sensor, 3, seed=5)
        for method in ("none", "diffusion", "layered", "phase"):
            seconds, raw_errors, denoised_errors = [], [], []
            for frame, truth in zip(frames, truths):
                def run(frame=frame):
                    return denoise.denoise_range(
                        frame.range, method=method, sensor=frame.sensor, intensity=frame.intensity, rays=frame.rays
                    )
                seconds.append(time_call(run, repeats=5))
                result = run()
                both = np.isfinite(result) & np.isfinite(frame.range) & np.isfinite(truth.range)
                raw_errors.append((frame.range - truth.range)[both])
                denoised_errors.append((result - truth.range)[both])
            per_frame = float(np.median(seconds))
            raw = 1000 * np.sqrt(np.mean(np.concatenate(raw_errors) ** 2))
            smooth = 1000 * np.sqrt(np.mean(np.concatenate(denoised_errors) ** 2))
            lines.append(f"| {sensor} | {method} | {1000 * per_frame:.2f} | {1 / per_frame:.0f} | {raw:.1f} | {smooth:.1f} |")
    write_results(Path(__file__).parent / "results", "denoise_speed.md", lines)


if __name__ == "__main__":
    main()
