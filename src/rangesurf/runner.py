"""The main job: a whole sequence through the `Pipeline`, with checkpoints, outputs and a report.

`run` reads frames from any input `rangesurf.load` accepts or from a
built-in simulated sequence (``sim:arena``, ``sim:corridor``), feeds them to
a `Pipeline`, checkpoints the model atomically every ``run.checkpoint_every``
frames (``--resume`` continues from there), and writes into the output
folder (every file atomically)::

    model.ply        the surfaces, one float column per uncertainty level
    model.glb        the surfaces coloured by their combined uncertainty
    trajectory.txt   the tracked poses (TUM format)
    timings.csv      per frame: milliseconds per stage, late / deferred flags
    metrics.json     speed, sizes, uncertainty statistics, accuracy against ground truth
    report.html      the run as figures (opens offline)
    config.toml      the settings that produced all of this
    checkpoint.npz   the pipeline state, for --resume

A frame that cannot be read is reported and skipped, or stops the run with
everything merged so far written (``run.on_bad_frame``); Ctrl-C stops
cleanly the same way.
"""

from __future__ import annotations

import csv
import dataclasses
import io as _io
import json
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rangesurf.config import PipelineConfig
from rangesurf.frame import RangeFrame
from rangesurf.io import FormatError, atomic_write, data_files, iter_frames
from rangesurf.io.gltf import write_glb
from rangesurf.io.ply import write_mesh_ply
from rangesurf.io.tum import write_tum_trajectory
from rangesurf.mesh import UNCERTAINTY_LEVELS
from rangesurf.pipeline import STAGES, FrameResult, Pipeline

__all__ = ["Item", "RunSummary", "run", "open_input", "OUTPUTS"]

OUTPUTS = ("model.ply", "model.glb", "trajectory.txt", "timings.csv", "metrics.json", "report.html", "config.toml")
_CHECKPOINT = "checkpoint.npz"
_BAGS = (".bag", ".mcap", ".db3")


@dataclass(frozen=True)
class Item:
    """One input position: a frame (with its true pose when simulated), or why it could not be read.

    Positions a resumed run has already merged come without a frame.
    """

    source: str
    frame: RangeFrame | None = None
    true_pose: np.ndarray | None = None
    error: str | None = None


@dataclass
class RunSummary:
    """What `run` did; also written to ``metrics.json``."""

    out: Path
    frames: int = 0
    skipped: list[tuple[str, str]] = field(default_factory=list)
    late: int = 0
    postponed: int = 0
    seconds: float = 0.0
    stopped: str | None = None
    paused: bool = False
    metrics: dict = field(default_factory=dict)


def open_input(spec: str, *, frames: int | None = None, sensor: str | None = None, seed: int = 0,
               odometry_noise: bool = True, skip: int = 0) -> tuple[Iterator[Item], int | None, dict]:
    """Items of an input: ``sim:SCENE`` (a simulated sequence with noisy odometry) or a path.

    The first ``skip`` positions (merged before a checkpoint) come without
    frames and are neither simulated nor read, except in bags, whose frames
    can only be reached in order. Returns the items, their number if known,
    and what is known about the input (the scene's true planes for simulated ones).
    """
    if spec.startswith("sim:"):
        from rangesurf import simulate
        from rangesurf.frame import get_sensor

        scene = spec[4:]
        if scene not in simulate.SCENES:
            raise ValueError(f"unknown simulated scene {scene!r}; expected sim:{' or sim:'.join(simulate.SCENES)}")
        count = 200 if frames is None else frames
        sensor_name = sensor or "sr3000"
        true_poses = simulate.default_trajectory(scene, count, frame_rate=get_sensor(sensor_name).frame_rate)
        odometry = simulate.noisy_odometry(true_poses, seed=seed) if odometry_noise else true_poses

        def simulated() -> Iterator[Item]:
            start = min(skip, count)
            for index in range(start):
                yield Item(f"simulated:{scene}/{sensor_name}/frame{index:04d}", true_pose=true_poses[index])
            sequence = simulate.iter_sequence(scene, sensor_name, count, seed=seed, trajectory=true_poses, start=start)
            for index, (frame, truth) in enumerate(sequence, start=start):
                yield Item(frame.source, dataclasses.replace(frame, pose=odometry[index]), truth.T_world_sensor)

        planes = simulate.get_scene(scene).planes
        return simulated(), count, {"scene": scene, "sensor": sensor_name, "true_planes": planes[np.isfinite(planes).all(axis=1)]}

    path = Path(spec)
    files = data_files(path)

    def from_files() -> Iterator[Item]:
        taken = 0
        for file in files:
            if taken < skip and file.suffix.lower() not in _BAGS and not file.is_dir():
                # A one-frame file merged before the checkpoint: not read again.
                taken += 1
                yield Item(str(file))
                continue
            try:
                for frame in iter_frames(file, sensor=sensor):
                    if frames is not None and taken >= frames:
                        return
                    taken += 1
                    yield Item(frame.source or str(file), frame)
            except FormatError as error:
                yield Item(str(file), error=str(error))

    # One frame per file except for bags, whose frame count is not known before reading.
    per_file = all(file.suffix.lower() not in _BAGS and not file.is_dir() for file in files)
    total = len(files) if per_file else None
    if frames is not None:
        total = frames if total is None else min(frames, total)
    return from_files(), total, {}


def run(
    spec: str,
    out: str | os.PathLike,
    *,
    config: PipelineConfig | None = None,
    frames: int | None = None,
    sensor: str | None = None,
    seed: int = 0,
    overwrite: bool = False,
    resume: bool = False,
    until: int | None = None,
    realtime: bool = False,
    progress: bool = True,
    viewer=None,
) -> RunSummary:
    """Run the pipeline over an input and write every output into ``out``.

    Parameters
    ----------
    spec : str
        A file, folder, glob or bag (`rangesurf.load`), or ``sim:arena`` / ``sim:corridor``.
    out : path-like
        Output folder; an existing non-empty one is refused unless
        ``overwrite`` or ``resume``.
    config : PipelineConfig, optional
    frames : int, optional
        At most this many frames (simulated: exactly; default 200).
    sensor : str, optional
        Sensor preset (simulated input, or overriding a reader's guess).
    seed : int
        Simulation seed.
    overwrite : bool
        Replace the outputs of an earlier run.
    resume : bool
        Continue from ``out/checkpoint.npz``: the frames it holds are skipped.
    until : int, optional
        Stop before this input position (counted from the first, the ones a
        resumed run skips included) with the checkpoint saved and no outputs
        written: the summary says ``paused``, and a call with ``resume=True``
        goes on from there, to the same outputs as a run without stops. An
        input that ends first finishes the run as usual. (`rangesurf.batch`
        runs recordings in such parts.)
    realtime : bool
        Feed frames at the sensor's frame rate (wall clock) and count the
        frames the pipeline did not finish within their period.
    progress : bool
        Show a progress bar.
    viewer : rangesurf.viewer.Viewer, optional
        Shown every frame and the final model (`rangesurf.viewer`); a
        do-nothing `NullViewer` by default.

    Returns
    -------
    RunSummary
    """
    from rangesurf.viewer import NullViewer

    viewer = viewer if viewer is not None else NullViewer()
    out = Path(out)
    checkpoint = out / _CHECKPOINT
    # A run killed while writing leaves its temporary files (never a half-written output): clear them.
    for name in (*OUTPUTS, _CHECKPOINT):
        for leftover in out.glob(f".{name}.*"):
            leftover.unlink(missing_ok=True)
    # The input first: a path that does not exist should not leave an output folder behind.
    if not spec.startswith("sim:"):
        data_files(Path(spec))
    if resume:
        if not checkpoint.is_file():
            raise FileNotFoundError(f"{checkpoint}: no checkpoint to resume from")
        pipeline = Pipeline.resume(checkpoint)
        if config is not None and config != pipeline.config:
            raise ValueError(f"{checkpoint}: the run was made with other settings; resume without --config")
    else:
        if out.exists() and any(out.iterdir()) and not overwrite:
            raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace its outputs")
        out.mkdir(parents=True, exist_ok=True)
        if checkpoint.exists():
            checkpoint.unlink()
        pipeline = Pipeline(config)
    config = pipeline.config
    # Meshes made while the run goes on are for a viewer to show; without one they wait for the end.
    pipeline.live_meshes = not isinstance(viewer, NullViewer)
    config.save(out / "config.toml")
    # Input positions consumed before the checkpoint (frames merged plus unreadable ones skipped).
    already = int(pipeline.checkpoint_extra["positions"]) if "positions" in pipeline.checkpoint_extra else pipeline.frames
    if until is not None and until <= already:
        raise ValueError(f"until={until} must lie past the {already} input positions {checkpoint} already holds")
    items, total, known = open_input(spec, frames=frames, sensor=sensor, seed=seed, skip=already)
    summary = RunSummary(out=out)
    rows: list[dict] = _rows_from_array(pipeline.checkpoint_extra.get("timings")) if resume else []
    if resume and "skipped" in pipeline.checkpoint_extra:
        # The inputs earlier sessions could not read: the run's metrics list them all.
        summary.skipped = [(str(source), str(error)) for source, error in pipeline.checkpoint_extra["skipped"]]
    truths: list[np.ndarray | None] = []
    last: FrameResult | None = None
    last_frame: RangeFrame | None = None
    consumed = already
    started = time.perf_counter()
    wall_start = None
    from tqdm import tqdm

    bar = tqdm(total=total, desc="rangesurf run", unit="frame", disable=not progress, leave=False)
    try:
        for position, item in enumerate(items):
            if position < already:
                # Merged before the checkpoint: only its true pose is needed again.
                if item.error is None:
                    truths.append(item.true_pose)
                bar.update(1)
                continue
            if until is not None and position >= until:
                summary.paused = True
                break
            consumed = position + 1
            if item.error is not None:
                summary.skipped.append((item.source, item.error))
                if config.run.on_bad_frame == "stop":
                    summary.stopped = f"unreadable input {item.source}"
                    break
                bar.update(1)
                continue
            frame = item.frame
            if realtime:
                wall_start = wall_start or time.perf_counter() - position / frame.sensor.frame_rate
                wait = wall_start + position / frame.sensor.frame_rate - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            result = pipeline.process(frame)
            viewer.update(result, pipeline)
            last, last_frame = result, frame
            known.setdefault("frame_period_ms", config.run.budget_ms or 1000.0 / frame.sensor.frame_rate)
            truths.append(item.true_pose)
            rows.append({"frame": result.index, "timestamp": result.timestamp,
                         **{stage: result.timings[stage] for stage in STAGES}, "total": result.timings["total"],
                         "late": int(result.late), "deferred": int(result.deferred)})
            summary.frames += 1
            every = config.run.checkpoint_every
            if every and pipeline.frames % every == 0:
                pipeline.save_checkpoint(checkpoint, extra=_checkpoint_extra(rows, consumed, summary.skipped))
            bar.update(1)
    except KeyboardInterrupt:
        summary.stopped = "interrupted (Ctrl-C)"
    finally:
        bar.close()
    summary.seconds = time.perf_counter() - started
    pipeline.save_checkpoint(checkpoint, extra=_checkpoint_extra(rows, consumed, summary.skipped))
    if summary.paused:
        return summary
    surfaces = pipeline.finish()
    summary.late, summary.postponed = pipeline.late, pipeline.postponed
    _write_outputs(out, pipeline, surfaces, rows, truths, known, summary, last, last_frame)
    viewer.finish(surfaces)
    return summary


# --------------------------------------------------------------------------
# Outputs.
# --------------------------------------------------------------------------


def _write_outputs(out: Path, pipeline: Pipeline, surfaces: list, rows: list[dict], truths: list, known: dict,
                   summary: RunSummary, last: FrameResult | None, last_frame: RangeFrame | None) -> None:
    timestamps, poses = pipeline.model.trajectory()
    write_tum_trajectory(out / "trajectory.txt", timestamps, poses)
    write_mesh_ply(out / "model.ply", surfaces)
    write_glb(out / "model.glb", surfaces)
    _write_timings(out / "timings.csv", rows)
    summary.metrics = _metrics(pipeline, surfaces, rows, truths, poses, known, summary)
    with atomic_write(out / "metrics.json", "w") as stream:
        json.dump(summary.metrics, stream, indent=2)
    from rangesurf.report import run_report

    html = run_report(summary.metrics, rows, surfaces, last, last_frame, poses, truths)
    with atomic_write(out / "report.html", "w") as stream:
        stream.write(html)


def _write_timings(path: Path, rows: list[dict]) -> None:
    columns = list(_TIMING_COLUMNS)
    buffer = _io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({key: (f"{value:.3f}" if isinstance(value, float) else value) for key, value in row.items()})
    with atomic_write(path, "w") as stream:
        stream.write(buffer.getvalue())


_TIMING_COLUMNS = ("frame", "timestamp", *STAGES, "total", "late", "deferred")


def _checkpoint_extra(rows: list[dict], consumed: int, skipped: list[tuple[str, str]]) -> dict[str, np.ndarray]:
    """What a resumed run needs beside the pipeline: the timing rows, the input positions consumed, the inputs
    skipped as unreadable."""
    return {"timings": _rows_to_array(rows), "positions": np.array(consumed),
            "skipped": np.array(skipped, dtype=str).reshape(-1, 2)}


def _rows_to_array(rows: list[dict]) -> np.ndarray:
    """Timing rows as an (N, columns) float array, for the checkpoint."""
    return np.array([[row[name] for name in _TIMING_COLUMNS] for row in rows], np.float64).reshape(-1, len(_TIMING_COLUMNS))


def _rows_from_array(table: np.ndarray | None) -> list[dict]:
    if table is None:
        return []
    integer = ("frame", "late", "deferred")
    return [{name: (int(value) if name in integer else float(value)) for name, value in zip(_TIMING_COLUMNS, row)} for row in table]


def _metrics(pipeline: Pipeline, surfaces: list, rows: list[dict], truths: list, poses: np.ndarray, known: dict,
             summary: RunSummary) -> dict:
    totals = np.array([row["total"] for row in rows]) if rows else np.zeros(0)
    steady = totals[1:] if totals.size > 1 else totals
    metrics: dict = {
        "frames": pipeline.frames,
        "frames_this_session": summary.frames,
        "skipped": [{"source": source, "error": error} for source, error in summary.skipped],
        "stopped": summary.stopped,
        "seconds": round(summary.seconds, 3),
        # The pipeline's own rate (its per-frame times) after the first frame, whose time on a fresh
        # install is mostly compiling the kernels (reported on its own), and the whole loop's rate
        # including reading or simulating the input.
        "frames_per_second": round(1000.0 * len(steady) / steady.sum(), 2) if steady.size and steady.sum() > 0 else None,
        "first_frame_ms": round(float(totals[0]), 1) if totals.size else None,
        "frames_per_second_with_input": round(summary.frames / summary.seconds, 2) if summary.seconds > 0 else None,
        "late_frames": pipeline.late,
        "remeshes_postponed": pipeline.postponed,
        "stage_ms_median": {stage: round(float(np.median([row[stage] for row in rows])), 3) for stage in (*STAGES, "total")}
        if rows else {},
        "total_ms_p95": round(float(np.percentile(totals, 95)), 3) if totals.size else None,
        "surfaces": len(surfaces),
        "vertices": int(sum(surface.n_vertices for surface in surfaces)),
        "triangles": int(sum(surface.n_faces for surface in surfaces)),
        "cell_size_m": pipeline.model.cell_size,
        "uncertainty_m": {},
    }
    for level in UNCERTAINTY_LEVELS:
        present = [surface.uncertainty[level] for surface in surfaces if level in surface.uncertainty]
        values = np.concatenate(present) if present else np.zeros(0)
        values = values[np.isfinite(values)]
        if values.size:
            metrics["uncertainty_m"][level] = {"median": float(np.median(values)), "p95": float(np.percentile(values, 95))}
    truth_poses = [pose for pose in truths if pose is not None]
    if truth_poses and len(truth_poses) == len(poses):
        from rangesurf.trajectory import absolute_trajectory_error, relative_pose_error

        reference = np.asarray(truth_poses)
        ate = absolute_trajectory_error(poses, reference)
        rpe = relative_pose_error(poses, reference)
        accuracy = {
            "ate_rmse_m": ate.translation.rmse, "rpe_translation_max_m": rpe.translation.max,
            "rpe_translation_rmse_m": rpe.translation.rmse, "rpe_rotation_max_deg": rpe.rotation.max,
            "rpe_rotation_rmse_deg": rpe.rotation.rmse,
        }
        planes = known.get("true_planes")
        if planes is not None and surfaces:
            vertices = np.vstack([surface.vertices for surface in surfaces]).astype(np.float64)
            distance = np.abs(vertices @ planes[:, :3].T + planes[:, 3]).min(axis=1)
            accuracy["model_to_true_planes_median_m"] = float(np.median(distance))
            accuracy["model_to_true_planes_p95_m"] = float(np.percentile(distance, 95))
        metrics["accuracy"] = accuracy
    for key in ("scene", "sensor"):
        if key in known:
            metrics[key] = known[key]
    if "frame_period_ms" in known:
        metrics["sensor_frame_period_ms"] = known["frame_period_ms"]
    return metrics
