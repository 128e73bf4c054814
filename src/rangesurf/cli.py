"""The ``rangesurf`` command.

Sub-commands:

* ``rangesurf info FILE_OR_DIR`` — sensor, grid, valid fraction, range statistics, pose.
* ``rangesurf simulate --sensor sr3000 --scene arena --frames N --out DIR`` — frames and ground truth.
* ``rangesurf demo [--out DIR]`` — simulate a short sequence, read it back, summarise it.
* ``rangesurf denoise FILE --out DIR`` — denoised frames and a figure panel per frame.
* ``rangesurf bench`` — benchmarks side by side with peer libraries.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import rangesurf
from rangesurf.frame import SENSORS, RangeFrame


def _progress(iterable, *, total: int, description: str, quiet: bool):
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=description, unit="frame", disable=quiet, file=sys.stderr)


def _frame_summary(frame: RangeFrame) -> dict:
    valid = frame.valid
    values = frame.range[valid]
    summary = {
        "source": frame.source,
        "sensor": frame.sensor.name,
        "grid": f"{frame.shape[0]}x{frame.shape[1]} (rows x cols)",
        "cells": int(valid.size),
        "valid": int(valid.sum()),
        "valid_fraction": round(float(valid.mean()), 4),
        "timestamp": frame.timestamp,
        "has_intensity": frame.intensity is not None,
    }
    if values.size:
        summary["range_m"] = {
            "min": round(float(values.min()), 4),
            "median": round(float(np.median(values)), 4),
            "max": round(float(values.max()), 4),
            "mean": round(float(values.mean()), 4),
        }
    for name in ("pose", "reference_pose"):
        transform = getattr(frame, name)
        if transform is not None:
            summary[name] = {
                "translation_m": [round(float(v), 4) for v in transform[:3, 3]],
                "rotation_deg": round(float(np.degrees(np.arccos(np.clip((np.trace(transform[:3, :3]) - 1) / 2, -1, 1)))), 3),
            }
    return summary


def _print_summary(summary: dict) -> None:
    print(f"{summary['source'] or '(frame)'}")
    print(f"  sensor          {summary['sensor']}")
    print(f"  grid            {summary['grid']}, {summary['cells']} cells")
    print(f"  valid           {summary['valid']} ({100 * summary['valid_fraction']:.1f} %)")
    if "range_m" in summary:
        r = summary["range_m"]
        print(f"  range [m]       min {r['min']:.3f}  median {r['median']:.3f}  max {r['max']:.3f}")
    for name in ("pose", "reference_pose"):
        if name in summary:
            p = summary[name]
            t = ", ".join(f"{v:.3f}" for v in p["translation_m"])
            print(f"  {name:<15} t = ({t}) m, rotation {p['rotation_deg']:.2f} deg")
    print(f"  intensity       {'yes' if summary['has_intensity'] else 'no'}")


def _command_info(args: argparse.Namespace) -> int:
    summaries = [_frame_summary(f) for f in rangesurf.io.iter_frames(args.path, sensor=args.sensor, topic=args.topic)]
    if args.json:
        print(json.dumps(summaries, indent=2))
        return 0
    for summary in summaries:
        _print_summary(summary)
    if len(summaries) > 1:
        print(f"{len(summaries)} frames")
    return 0


def _simulate_to_folder(
    *, scene: str, sensor: str, n_frames: int, seed: int, out: Path, quiet: bool
) -> tuple[list[RangeFrame], list, float]:
    """Simulate a sequence, writing frames and ground truth to ``out`` as they come.

    Returns the frames, their ground truth and the seconds spent simulating
    (writing excluded).
    """
    from rangesurf import simulate

    out.mkdir(parents=True, exist_ok=True)
    sequence = simulate.iter_sequence(scene, sensor, n_frames, seed=seed)
    frames, truths, simulating = [], [], 0.0
    for index in _progress(range(n_frames), total=n_frames, description="simulating", quiet=quiet):
        started = time.perf_counter()
        frame, truth = next(sequence)
        simulating += time.perf_counter() - started
        rangesurf.save(out / f"frame{index:06d}.npz", frame)
        simulate.save_ground_truth(out / "truth" / f"truth{index:06d}.npz", truth)
        frames.append(frame)
        truths.append(truth)
    return frames, truths, simulating


def _command_simulate(args: argparse.Namespace) -> int:
    frames, _, elapsed = _simulate_to_folder(
        scene=args.scene, sensor=args.sensor, n_frames=args.frames, seed=args.seed, out=args.out, quiet=args.quiet
    )
    print(
        f"simulated {len(frames)} {args.sensor} frames of scene '{args.scene}' in {elapsed:.2f} s "
        f"({len(frames) / elapsed:.1f} frames/s); wrote {args.out}/frame*.npz and {args.out}/truth/"
    )
    return 0


def _command_run(args: argparse.Namespace) -> int:
    from threadpoolctl import threadpool_limits

    from rangesurf.config import PipelineConfig
    from rangesurf.runner import run
    from rangesurf.viewer import NullViewer

    config = PipelineConfig.load(args.config) if args.config else None
    viewer = NullViewer()
    if getattr(args, "view", False):
        from rangesurf.viewer import Viewer

        viewer = Viewer(host=args.host, port=args.port, folder=args.out)
        print(f"rangesurf run: viewer at {viewer.url}")
    with viewer:
        # The pipeline's matrices are tiny: a threaded BLAS only adds stalls on a busy machine.
        with threadpool_limits(limits=1, user_api="blas"):
            summary = run(args.input, args.out, config=config, frames=args.frames, sensor=args.sensor, seed=args.seed,
                          overwrite=args.overwrite, resume=args.resume, realtime=args.realtime,
                          progress=not args.quiet, viewer=viewer)
        _print_run_summary(summary)
        if getattr(args, "view", False):
            print(f"rangesurf run: still serving the final model at {viewer.url}; Ctrl-C to stop")
            try:
                while True:
                    time.sleep(3600)
            except KeyboardInterrupt:
                pass
    return 0 if summary.stopped is None or summary.stopped.startswith("interrupted") else 1


def _command_batch(args: argparse.Namespace) -> int:
    from rangesurf.batch import PART_FRAMES, run_batch
    from rangesurf.config import PipelineConfig

    config = PipelineConfig.load(args.config) if args.config else None
    seed = args.seed[0] if len(args.seed) == 1 else args.seed
    batch = run_batch(args.inputs, args.out, scheduler=args.scheduler, workers=args.workers, config=config,
                      frames=args.frames, sensor=args.sensor, seed=seed, overwrite=args.overwrite,
                      part_frames=PART_FRAMES if args.part_frames is None else args.part_frames,
                      progress=not args.quiet)
    print(f"rangesurf batch: {len(batch.items)} inputs on {batch.workers} Dask worker(s) at {batch.scheduler} in "
          f"{batch.seconds:.1f} s, {len(batch.failed)} failed; summary in {batch.out / 'batch.json'}")
    for item in batch.items:
        if item.ok:
            stopped = f"; stopped: {item.summary.stopped}" if item.summary.stopped else ""
            parts = f" ({item.parts} parts)" if item.parts > 1 else ""
            print(f"  {item.input} -> {item.out}: {item.summary.frames} frames in {item.seconds:.1f} s{parts}{stopped}")
        else:
            print(f"  {item.input} -> {item.out}: FAILED: {item.error}")
    return 1 if batch.failed else 0


def _command_view(args: argparse.Namespace) -> int:
    from rangesurf.viewer import view_model

    print(f"rangesurf view: serving {args.folder} (Ctrl-C to stop)")
    view_model(args.folder, host=args.host, port=args.port)
    return 0


def _command_demo(args: argparse.Namespace) -> int:
    print(f"rangesurf {rangesurf.__version__} demo: {args.frames} simulated {args.sensor} frames of the '{args.scene}' "
          f"scene, with drifting wheel odometry, through the whole pipeline")
    args.input, args.config, args.resume, args.realtime, args.overwrite = f"sim:{args.scene}", None, False, False, True
    return _command_run(args)


def _print_run_summary(summary) -> None:
    metrics = summary.metrics
    stages = metrics.get("stage_ms_median", {})
    print(f"  {metrics['frames']} frames merged at {metrics.get('frames_per_second')} frames/s on one core "
          f"after the first ({metrics.get('first_frame_ms')} ms, compiling on a fresh install; "
          f"{summary.seconds:.1f} s in all with reading or simulating the input); "
          f"{metrics['late_frames']} over their time budget, {len(metrics['skipped'])} skipped"
          + (f"; stopped: {summary.stopped}" if summary.stopped else ""))
    if stages:
        print("  median ms per frame: " + ", ".join(f"{stage} {value:.1f}" for stage, value in stages.items()))
    print(f"  model: {metrics['surfaces']} surfaces, {metrics['vertices']} vertices, {metrics['triangles']} triangles "
          f"(cells of {1000 * (metrics['cell_size_m'] or 0):.1f} mm)")
    for level, stats in metrics.get("uncertainty_m", {}).items():
        print(f"  {level}: median {1000 * stats['median']:.2f} mm, 95th percentile {1000 * stats['p95']:.2f} mm")
    accuracy = metrics.get("accuracy")
    if accuracy:
        print(f"  against ground truth: trajectory ATE {1000 * accuracy['ate_rmse_m']:.1f} mm RMSE, per-frame error "
              f"at most {accuracy['rpe_rotation_max_deg']:.3f} deg / {1000 * accuracy['rpe_translation_max_m']:.1f} mm"
              + (f"; model vertices a median {1000 * accuracy['model_to_true_planes_median_m']:.1f} mm "
                 f"(95 %: {1000 * accuracy['model_to_true_planes_p95_m']:.1f} mm) from the true planes"
                 if "model_to_true_planes_median_m" in accuracy else ""))
    for source, error in summary.skipped[:5]:
        print(f"  skipped {source}: {error}")
    print(f"  wrote {summary.out}/: model.ply, model.glb, trajectory.txt, timings.csv, metrics.json, report.html, "
          "config.toml, checkpoint.npz")


def _command_denoise(args: argparse.Namespace) -> int:
    from rangesurf import denoise, edges, report

    frames = rangesurf.load(args.path, sensor=args.sensor, topic=args.topic)
    args.out.mkdir(parents=True, exist_ok=True)
    for index, frame in enumerate(_progress(frames, total=len(frames), description="denoising", quiet=args.quiet)):
        smooth = denoise.denoise_range(
            frame.range, method=args.method, sensor=frame.sensor, intensity=frame.intensity, rays=frame.rays,
            remove_outliers=not args.keep_outliers,
        )
        name = Path(args.path).stem if len(frames) == 1 and Path(args.path).is_file() else f"frame{index:06d}"
        rangesurf.save(args.out / f"{name}.npz", frame.replace(range=smooth))

        shared_range = tuple(np.nanpercentile(frame.range, [1, 99])) if frame.valid.any() else None
        raw_image = report.colorize_range(frame.range, valid_range=shared_range)
        smooth_image = report.colorize_range(smooth, valid_range=shared_range)
        raw_edges = edges.clean_edges(edges.detect_edges(frame.range, method=args.edges))
        smooth_edges = edges.clean_edges(edges.detect_edges(smooth, method=args.edges))
        panel = report.image_panel(
            [raw_image, smooth_image, report.colorize_edges(raw_edges, background=raw_image),
             report.colorize_edges(smooth_edges, background=smooth_image)],
            ["raw range", f"denoised ({args.method})", f"{args.edges} edges, raw", f"{args.edges} edges, denoised"],
        )
        report.write_image(args.out / f"{name}_panel.png", panel)
        removed = int((frame.valid & ~np.isfinite(smooth)).sum())
        print(
            f"{name}: {removed} outliers removed, {int(raw_edges.sum())} -> {int(smooth_edges.sum())} edge pixels; "
            f"wrote {args.out / (name + '.npz')} and {name}_panel.png"
        )
    return 0


def _command_segment(args: argparse.Namespace) -> int:
    from rangesurf import report
    from rangesurf.io._common import atomic_path
    from rangesurf.segment import nxd_transform, segment_frame

    frames = rangesurf.load(args.path, sensor=args.sensor, topic=args.topic)
    args.out.mkdir(parents=True, exist_ok=True)
    for index, frame in enumerate(_progress(frames, total=len(frames), description="segmenting", quiet=args.quiet)):
        result = segment_frame(frame, denoise=args.denoise, segmenter=args.segmenter)
        segments = result.segmentation
        name = Path(args.path).stem if len(frames) == 1 and Path(args.path).is_file() else f"frame{index:06d}"
        with atomic_path(args.out / f"{name}_segments.npz") as temporary, open(temporary, "wb") as stream:
            np.savez_compressed(
                stream, labels=segments.labels, planes=segments.planes, residuals=segments.residuals, sizes=segments.sizes
            )
        figure = report.segmentation_figure(result.range, segments.labels, nxd_transform(result.points, result.normals), title=name)
        report.write_image(args.out / f"{name}_segments.png", figure)
        covered = segments.sizes[1:].sum() / max(int(frame.valid.sum()), 1)
        print(f"{name}: {segments.n_segments} planar segments cover {100 * covered:.0f} % of the returns (planes n . p + d = 0 in the sensor frame); "
              f"wrote {name}_segments.npz and {name}_segments.png")
        for label in range(1, min(segments.n_segments, args.show) + 1):
            nx, ny, nz, d = segments.planes[label]
            print(f"  {label:3d}  {segments.sizes[label]:7d} px  n = ({nx:+.3f}, {ny:+.3f}, {nz:+.3f})  d = {d:6.3f} m  "
                  f"rms = {1000 * segments.residuals[label]:5.1f} mm")
    return 0


def _command_lod(args: argparse.Namespace) -> int:
    from rangesurf import report
    from rangesurf.lod import _plane_frame, prepare_levels
    from rangesurf.mesh import triangulate_segments
    from rangesurf.segment import segment_frame

    frames = rangesurf.load(args.path, sensor=args.sensor, topic=args.topic)
    args.out.mkdir(parents=True, exist_ok=True)
    for index, frame in enumerate(_progress(frames, total=len(frames), description="meshing", quiet=args.quiet)):
        result = segment_frame(frame)
        surfaces = triangulate_segments(result.points, result.segmentation)
        name = Path(args.path).stem if len(frames) == 1 and Path(args.path).is_file() else f"frame{index:06d}"
        if not surfaces:
            print(f"{name}: no surface to mesh")
            continue
        surface = prepare_levels(max(surfaces, key=lambda item: item.n_vertices))
        shown = [surface.levels[k] for k in np.unique(np.linspace(0, len(surface.levels) - 1, args.panels).round().astype(int))]
        xy, _, _ = _plane_frame(surface)
        report.write_image(args.out / f"{name}_lod.png", report.lod_figure(xy, shown, surface.lod_order))
        print(f"{name}: {len(surfaces)} surfaces, {sum(s.n_faces for s in surfaces)} triangles; the largest "
              f"(segment {surface.segment}, {surface.n_vertices} vertices) at "
              + ", ".join(f"{level.count} ({1000 * level.error:.1f} mm)" for level in shown)
              + f"; wrote {name}_lod.png")
    return 0


def _command_bench(args: argparse.Namespace) -> int:
    from rangesurf import bench

    folder = args.benchmarks or Path(__file__).resolve().parents[2] / "benchmarks"
    target = bench.run_suite(folder, args.names or None)
    print(f"rangesurf bench: wrote {target}")
    return 0


def _bench_names() -> list[str]:
    from rangesurf.bench import SUITE

    return list(SUITE)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rangesurf",
        description="Online multi-resolution surface models from range-sensor streams.",
    )
    parser.add_argument("--version", action="version", version=f"rangesurf {rangesurf.__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    info = commands.add_parser("info", help="describe the frames in a file or folder")
    info.add_argument("path", help="file, folder, glob or ROS bag")
    info.add_argument("--sensor", choices=sorted(SENSORS), help="override the sensor model")
    info.add_argument("--topic", help="ROS bag topic to read")
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    info.set_defaults(handler=_command_info)

    def add_simulation_options(command: argparse.ArgumentParser, *, frames: int, out: str | None) -> None:
        command.add_argument("--sensor", default="sr3000", choices=sorted(SENSORS), help="sensor preset (default sr3000)")
        command.add_argument("--scene", default="arena", help="built-in scene: arena or corridor (default arena)")
        command.add_argument("--frames", type=int, default=frames, help=f"number of frames (default {frames})")
        command.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
        if out is None:
            command.add_argument("--out", type=Path, required=True, help="output folder")
        else:
            command.add_argument("--out", type=Path, default=Path(out), help=f"output folder (default {out})")
        command.add_argument("--quiet", action="store_true", help="no progress bar")

    def add_input_options(command: argparse.ArgumentParser) -> None:
        """The options of every command that reads frames: where from, which sensor, which topic."""
        command.add_argument("path", help="file, folder, glob or ROS bag")
        command.add_argument("--sensor", choices=sorted(SENSORS), help="override the sensor model")
        command.add_argument("--topic", help="ROS bag topic to read")
        command.add_argument("--quiet", action="store_true", help="no progress bar")

    def add_viewer_options(command: argparse.ArgumentParser) -> None:
        command.add_argument("--port", type=int, default=8080, help="viewer port (default 8080; the next free one if taken)")
        command.add_argument("--host", default="127.0.0.1",
                             help="interface to bind (default 127.0.0.1: this machine only; 0.0.0.0 exposes it to the network)")

    simulate = commands.add_parser("simulate", help="simulate a sequence with ground truth")
    add_simulation_options(simulate, frames=10, out=None)
    simulate.set_defaults(handler=_command_simulate)

    run = commands.add_parser("run", help="the main job: a sequence through the whole pipeline into a model, with a report")
    run.add_argument("input", help="file, folder, glob or ROS bag, or a simulated sequence: sim:arena, sim:corridor")
    run.add_argument("--out", type=Path, required=True, help="output folder")
    run.add_argument("--config", type=Path, help="settings (TOML, as the config.toml a run writes)")
    run.add_argument("--frames", type=int, help="at most this many frames (simulated: default 200)")
    run.add_argument("--sensor", choices=sorted(SENSORS), help="sensor preset (simulated input, or overriding a reader)")
    run.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    run.add_argument("--overwrite", action="store_true", help="replace the outputs of an earlier run in --out")
    run.add_argument("--resume", action="store_true", help="continue from --out/checkpoint.npz")
    run.add_argument("--realtime", action="store_true", help="feed frames at the sensor's frame rate")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--view", action="store_true", help="show the model growing in the browser (viser; needs rangesurf[viewer])")
    add_viewer_options(run)
    run.set_defaults(handler=_command_run)

    view = commands.add_parser("view", help="show a run's saved model in the browser (viser; needs rangesurf[viewer])")
    view.add_argument("folder", type=Path, help="a run's output folder (model.ply; trajectory.txt, timings.csv, metrics.json if present)")
    add_viewer_options(view)
    view.set_defaults(handler=_command_view)

    demo = commands.add_parser("demo", help="run a built-in simulated sequence through the whole pipeline")
    add_simulation_options(demo, frames=200, out="demo-out")
    demo.set_defaults(handler=_command_demo)

    denoise = commands.add_parser("denoise", help="remove outliers and smooth range images, keeping edges")
    add_input_options(denoise)
    denoise.add_argument("--out", type=Path, required=True, help="output folder (denoised .npz + figure panel .png)")
    denoise.add_argument("--method", default="diffusion", choices=["diffusion", "layered", "phase", "none"], help="smoothing (default diffusion)")
    denoise.add_argument("--keep-outliers", action="store_true", help="skip cut-off, spike and flying-pixel removal")
    denoise.add_argument("--edges", default="canny", choices=["canny", "sobel", "prewitt", "roberts"], help="edge detector of the panel")
    denoise.set_defaults(handler=_command_denoise)

    segment = commands.add_parser("segment", help="split range images into planar segments (labels + thesis Figure 3.5 panel)")
    add_input_options(segment)
    segment.add_argument("--out", type=Path, required=True, help="output folder (labels .npz + figure .png per frame)")
    segment.add_argument("--denoise", default="diffusion", choices=["diffusion", "layered", "phase", "none"], help="denoising first (default diffusion)")
    segment.add_argument("--segmenter", default="region", choices=["region", "nxd"], help="region growing or N x D clustering (default region)")
    segment.add_argument("--show", type=int, default=5, help="planes listed per frame (default 5)")
    segment.set_defaults(handler=_command_segment)

    lod = commands.add_parser("lod", help="mesh the segments and show the largest surface from fine to coarse (thesis Figure 3.8)")
    add_input_options(lod)
    lod.add_argument("--out", type=Path, required=True, help="output folder (one figure per frame)")
    lod.add_argument("--panels", type=int, default=4, help="levels shown (default 4)")
    lod.set_defaults(handler=_command_lod)

    batch = commands.add_parser("batch", help="many recordings through the main job on a Dask cluster "
                                "(pip install 'rangesurf[distributed]')")
    batch.add_argument("inputs", nargs="+", metavar="INPUT",
                       help="files, folders, globs or ROS bags, or simulated sequences: sim:arena, sim:corridor")
    batch.add_argument("--out", type=Path, required=True, help="parent output folder: one folder per input, and batch.json")
    batch.add_argument("--scheduler", metavar="ADDRESS",
                       help="a running Dask scheduler, e.g. tcp://host:8786 (default: a local cluster for the batch)")
    batch.add_argument("--workers", type=int, help="worker processes of the local cluster (default: one per CPU core)")
    batch.add_argument("--config", type=Path, help="settings (TOML, as the config.toml a run writes)")
    batch.add_argument("--frames", type=int, help="at most this many frames per input (simulated: default 200)")
    batch.add_argument("--sensor", choices=sorted(SENSORS), help="sensor preset (simulated input, or overriding a reader)")
    batch.add_argument("--seed", type=int, nargs="+", default=[0],
                       help="simulation seed: one for all inputs or one per input (default 0)")
    batch.add_argument("--overwrite", action="store_true", help="replace the outputs of earlier runs in the input folders")
    batch.add_argument("--part-frames", type=int, default=None, metavar="N",
                       help="with more inputs than workers, run each recording as a chain of tasks of N frames, "
                            "so that the recordings take turns (default: 50)")
    batch.add_argument("--quiet", action="store_true", help="no progress bar")
    batch.set_defaults(handler=_command_batch)

    bench = commands.add_parser("bench", help="run the side-by-side benchmarks against peer libraries; gather benchmarks/results.md")
    bench.add_argument("names", nargs="*", help="benchmarks to run (default all): " + ", ".join(_bench_names()))
    bench.add_argument("--benchmarks", type=Path, help="the benchmarks/ folder (default: the checkout's)")
    bench.set_defaults(handler=_command_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "handler", None) is None:
        parser.print_help()
        return 2
    if getattr(args, "frames", None) is not None and args.frames < 1:
        parser.error(f"--frames must be at least 1, got {args.frames}")
    try:
        return args.handler(args)
    except KeyboardInterrupt:
        print(f"rangesurf {args.command}: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, ImportError) as error:
        # FormatError is a ValueError: its message already names file and field.
        print(f"rangesurf {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
