"""Anisotropic diffusion: speed against medpy, and denoising quality on simulated SR-3000 frames.

Run: ``.venv/bin/python benchmarks/diffusion.py`` (``pip install medpy`` for
the peer columns). Writes ``benchmarks/results/diffusion.{json,md}``.

Speed: `rangesurf.denoise.anisotropic_diffusion` and
``medpy.filter.smoothing.anisotropic_diffusion`` with the same parameters
(10 iterations, kappa, lambda = ``step`` = ``gamma``; medpy's Tukey
cut-off is ``sqrt(2) * kappa``, so it gets ``kappa / sqrt(2)``) on the same
NaN-free simulated range images (medpy knows no holes), in one process;
median wall-clock time of several runs after a warm-up, as a ratio (each
timed on its own, and alternating call by call), with the largest
difference between the two results. Then frames per second of the other
settings (automatic kappa, the sensor's noise model, thesis presets) on
the same frames.

Quality: RMSE against the true range, and how much of each depth jump
survives, over simulated SR-3000 frames of the arena with range noise only.
"""

from __future__ import annotations

import json
import math
from functools import partial
from pathlib import Path

import numpy as np

import rangesurf as rs
from rangesurf.bench import denoising_quality, time_pair, machine_description, time_call
from rangesurf.denoise import THESIS_PRESETS, anisotropic_diffusion
from rangesurf.simulate import SimulationNoise

ITERATIONS = 10
STEP = 0.1
KAPPA = 0.05  # metres: a few noise sigmas of a neighbour difference at 2-3 m
SIZES = {"176x144 (SR-3000)": "sr3000", "640x480 (Kinect)": "kinect"}
RANGE_NOISE_ONLY = SimulationNoise(mixed_pixels=False, salt_and_pepper=0.0)


def _medpy():
    try:
        from medpy.filter.smoothing import anisotropic_diffusion as medpy_diffusion
    except ImportError:
        return None
    return medpy_diffusion


def _frame(sensor: str) -> rs.RangeFrame:
    frames, _ = rs.simulate.simulate_sequence("arena", sensor, 1, seed=0, noise=RANGE_NOISE_ONLY)
    return frames[0]


def _versus_medpy(size: str, setting: str, ours, peer, *, repeats: int) -> dict:
    """One table row: our time and medpy's, their ratio, and the largest difference of the results (metres).

    Each timed on its own (warm caches, as `rangesurf.bench.time_call`), and
    again alternating call by call, where each evicts the other's data from
    the caches, as in a pipeline that does other work between frames.
    """
    row = {"size": size, "setting": setting, "rangesurf_s": time_call(ours, repeats=repeats, warmup=2)}
    if peer is not None:
        row["medpy_s"] = time_call(peer, repeats=repeats, warmup=2)
        row["speedup_vs_medpy"] = row["medpy_s"] / row["rangesurf_s"]
        ours_alternating, peer_alternating = time_pair(ours, peer, repeats=repeats)
        row["speedup_vs_medpy_alternating"] = peer_alternating / ours_alternating
        row["max_abs_difference_m"] = float(np.max(np.abs(ours() - peer())))
    row["frames_per_second"] = 1 / row["rangesurf_s"]
    return row


def benchmark_speed(*, repeats: int = 21) -> list[dict]:
    """Ours vs medpy per size and conduction, plus frames/s of our other settings."""
    medpy_diffusion = _medpy()
    rows = []
    for size, sensor in SIZES.items():
        frame = _frame(sensor)
        image = frame.range
        if np.isnan(image).any():  # medpy has no notion of holes
            image = np.where(np.isnan(image), np.nanmean(image), image).astype(np.float32)
        for option, conduction in enumerate(("exponential", "rational", "tukey"), start=1):
            # medpy's Tukey cut-off is sqrt(2) * kappa; ours is kappa.
            medpy_kappa = KAPPA / math.sqrt(2.0) if conduction == "tukey" else KAPPA
            ours = partial(
                anisotropic_diffusion, image, iterations=ITERATIONS, kappa=KAPPA, step=STEP, conduction=conduction
            )
            peer = medpy_diffusion and partial(
                medpy_diffusion, image, niter=ITERATIONS, kappa=medpy_kappa, gamma=STEP, option=option
            )
            rows.append(_versus_medpy(size, f"{conduction}, kappa={KAPPA} m", ours, peer, repeats=repeats))

        # The thesis's setting: medpy on the frame normalised to 0-255 grey levels, mapped back.
        low, high = float(image.min()), float(image.max())

        def thesis_peer():
            grey = (image - low) * (255.0 / (high - low))
            diffused = medpy_diffusion(grey, niter=ITERATIONS, kappa=20, gamma=STEP, option=1)
            return diffused * ((high - low) / 255.0) + low

        ours = partial(anisotropic_diffusion, image, mode="thesis", iterations=ITERATIONS, kappa=20.0, step=STEP)
        setting = "thesis: grey levels 0-255, kappa=20, exponential"
        rows.append(_versus_medpy(size, setting, ours, medpy_diffusion and thesis_peer, repeats=repeats))

        sigma = frame.sensor.range_sigma(frame.range, frame.intensity)
        others = {
            "metric, automatic kappa (frame-wide noise estimate)": partial(anisotropic_diffusion, frame.range),
            "metric, kappa from the sensor noise model": partial(anisotropic_diffusion, frame.range, range_sigma=sigma),
            "thesis preset 'canny' (3 passes x 20 x 0.15)": partial(THESIS_PRESETS["canny"].apply, frame.range),
        }
        for setting, call in others.items():
            seconds = time_call(call, repeats=repeats, warmup=2)
            rows.append({"size": size, "setting": setting, "rangesurf_s": seconds, "frames_per_second": 1 / seconds})
    return rows


def benchmark_quality(*, n_frames: int = 6, seed: int = 3) -> list[dict]:
    """RMSE reduction and edge sharpness per setting on simulated SR-3000 arena frames."""
    frames, truths = rs.simulate.simulate_sequence("arena", "sr3000", n_frames, seed=seed, noise=RANGE_NOISE_ONLY)
    settings = {
        "raw": lambda frame: frame.range,
        "metric, exponential, automatic kappa": lambda frame: anisotropic_diffusion(frame.range),
        "metric, exponential, sensor noise model": lambda frame: anisotropic_diffusion(
            frame.range, range_sigma=frame.sensor.range_sigma(frame.range, frame.intensity)
        ),
        "metric, rational, automatic kappa": lambda frame: anisotropic_diffusion(frame.range, conduction="rational"),
        "metric, rational, sensor noise model": lambda frame: anisotropic_diffusion(
            frame.range, conduction="rational", range_sigma=frame.sensor.range_sigma(frame.range, frame.intensity)
        ),
        "metric, tukey, sensor noise model": lambda frame: anisotropic_diffusion(
            frame.range, conduction="tukey", range_sigma=frame.sensor.range_sigma(frame.range, frame.intensity)
        ),
        "thesis preset 'edges'": lambda frame: THESIS_PRESETS["edges"].apply(frame.range),
        "thesis preset 'canny'": lambda frame: THESIS_PRESETS["canny"].apply(frame.range),
    }
    return denoising_quality(settings, frames, truths)


def format_results(results: dict) -> str:
    def cell(value, fmt):
        return "—" if value is None else format(value, fmt)

    lines = [
        f"Machine: {results['machine']}; medpy {results['medpy'] or 'not installed'}; "
        f"{ITERATIONS} iterations, step (lambda, medpy gamma) {STEP}; single-threaded.",
        "",
        "| size | setting | rangesurf ms | medpy ms | speed-up vs medpy | (alternating) | frames/s "
        "| max abs diff to medpy (m) |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in results["speed"]:
        times = "x" if "speedup_vs_medpy" in row else ""
        lines.append(
            f"| {row['size']} | {row['setting']} | {1000 * row['rangesurf_s']:.3f} | "
            f"{cell(row.get('medpy_s') and 1000 * row['medpy_s'], '.2f')} | "
            f"{cell(row.get('speedup_vs_medpy'), '.1f')}{times} | "
            f"{cell(row.get('speedup_vs_medpy_alternating'), '.1f')}{times} | "
            f"{row['frames_per_second']:.0f} | {cell(row.get('max_abs_difference_m'), '.1e')} |"
        )
    quality = results["quality"]
    lines += [
        "",
        f"Quality on {quality['frames']} simulated SR-3000 arena frames (range noise only, seed {quality['seed']}); "
        "jumps: neighbours whose true ranges differ by > 10 % and > 5 noise sigmas.",
        "",
        "| setting | RMSE (mm) | RMSE reduction (mean, min) | jumps keeping >= 80 % | median jump kept |",
        "|---|---:|---:|---:|---:|",
    ]
    for row in quality["rows"]:
        lines.append(
            f"| {row['setting']} | {1000 * row['rmse_m']:.1f} | "
            f"{row['rmse_reduction_mean']:.2f}x, {row['rmse_reduction_min']:.2f}x | "
            f"{100 * row['jumps_kept_80_percent']:.1f} % of {row['jumps']} | {100 * row['jump_ratio_median']:.1f} % |"
        )
    return "\n".join(lines)


def main() -> None:
    medpy_diffusion = _medpy()
    if medpy_diffusion is None:
        print("medpy is not installed (pip install medpy): timing rangesurf only")
    medpy_version = None
    if medpy_diffusion is not None:
        from importlib.metadata import version

        medpy_version = version("medpy")
    quality_frames, quality_seed = 6, 3
    results = {
        "machine": machine_description(),
        "medpy": medpy_version,
        "speed": benchmark_speed(),
        "quality": {
            "frames": quality_frames,
            "seed": quality_seed,
            "rows": benchmark_quality(n_frames=quality_frames, seed=quality_seed),
        },
    }
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / "diffusion.json").write_text(json.dumps(results, indent=2) + "\n")
    table = format_results(results)
    (out / "diffusion.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
