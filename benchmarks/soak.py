"""Soak: a long simulated run through the pipeline, with memory (RSS) and per-frame time sampled.

Run: ``.venv/bin/python benchmarks/soak.py [N_FRAMES] [--sway lap|drifting]`` (default 10,000, lap);
writes ``benchmarks/results/soak.md`` (``soak_drifting_sway.md`` for ``--sway drifting``). The SR-3000
robot patrols the arena's loop again and again (drifting odometry); what must stay flat after warm-up
is the process's resident memory and the pipeline's time per frame. Reported: RSS and the median frame
time at frames 1,000 and N, their growth, and the least-squares slopes from frame 1,000 on. Beside
them, what the memory holds: the model's vertices, and the surface area the sensor has truly seen so
far (the simulator's true hits of every 5th frame and every 2nd pixel, counted as distinct cubes of three
times the model's cell size: every 2nd pixel lies at most 6 cm from the next in the arena, so each cube in
view gets a hit, and the count grows with new surface, not with laps that sample the same surface anew).

The sensor sways left and right as the robot drives. With ``--sway lap`` (the soak proper) the sway
repeats every lap (three sways per lap of the loop), so after the first lap the robot sees nothing new
and a model that grows with the area seen, not with time, stays flat: any growth is accumulation.
With ``--sway drifting`` it is the scene's default trajectory, whose sway (2.5 m) does not divide the
lap (7.0 m): every lap looks a little differently, and new bits of the arena come into view for
thousands of frames, which the model rightly grows with.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, write_results  # noqa: E402
from rangesurf.frame import get_sensor  # noqa: E402
from rangesurf.pipeline import Pipeline  # noqa: E402


def rss_mb() -> float:
    """Current resident set size (Linux /proc), megabytes."""
    with open("/proc/self/statm") as stream:
        pages = int(stream.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


# Cube edge of the surface-seen count, in model cells (see the module's notes).
_SEEN_CUBE_CELLS = 3


class SeenArea:
    """Distinct cubes of ``cell`` metres holding a true surface hit of the frames shown to it."""

    def __init__(self, cell: float) -> None:
        self.cell = cell
        self.seen = np.zeros(0, np.int64)
        self.pending: list[np.ndarray] = []

    def add(self, frame, truth) -> None:
        ranges = truth.range[::2, ::2]
        hit = np.isfinite(ranges) & (truth.surface_id[::2, ::2] > 0)
        points = frame.rays[::2, ::2][hit] * ranges[hit][:, None]
        world = points @ truth.T_world_sensor[:3, :3].T + truth.T_world_sensor[:3, 3]
        cube = np.floor(world / self.cell).astype(np.int64) + 2**20
        self.pending.append((cube[:, 0] << 42) | (cube[:, 1] << 21) | cube[:, 2])

    def count(self) -> int:
        if self.pending:
            self.seen = np.union1d(self.seen, np.concatenate(self.pending))
            self.pending = []
        return len(self.seen)


def later_growth(table: np.ndarray, start: int) -> list[str]:
    """A sentence on the growth from frame ``start`` on (once the surface seen has nearly stopped growing)."""
    rows = table[table[:, 0] >= start]
    if len(rows) < 10 or rows[-1, 0] < 2 * start:
        return []
    first, last = np.median(rows[:5], axis=0), np.median(rows[-5:], axis=0)
    growth = [100 * (last[column] / first[column] - 1) for column in (1, 3, 4)]
    return ["", f"From frame {start:,} to {int(rows[-1, 0]):,} (the same five-sample medians): resident memory {growth[0]:+.2f} %, model vertices "
                f"{growth[1]:+.2f} %, surface seen {growth[2]:+.2f} %."]


def lap_times(times: np.ndarray, lap: int, start: int) -> list[str]:
    """Sentences on the time per frame over whole laps: the first from ``start`` and the last.

    The 500-frame windows at the ends of the span catch different stretches
    of the lap, whose views cost differently; whole laps see the same. The
    stages that see only the frame (denoise, segment, surfaces) do not depend
    on the model, so their change between the laps is the machine's own
    speed, which the total's change is set against.
    """
    if len(times) < start + 2 * lap:
        return []
    first, last = np.median(times[start : start + lap], axis=0), np.median(times[-lap:], axis=0)
    growth = 100 * (last / first - 1)
    relative = 100 * ((last[0] / last[1]) / (first[0] / first[1]) - 1)
    return ["", f"Whole laps ({lap} frames), medians: the first from frame {start:,} and the last take {first[0]:.2f} and "
                f"{last[0]:.2f} ms per frame ({growth[0]:+.1f} %); their stages that see only the frame (denoise, segment, "
                f"surfaces), {first[1]:.2f} and {last[1]:.2f} ms ({growth[1]:+.1f} %: the machine's speed); the total "
                f"relative to those {relative:+.1f} %."]


def patrol(scene: str) -> simulate.Scene:
    """The scene with its trajectory's sway fitted to the lap: three whole sways per lap, so every lap is the same."""
    scene = simulate.get_scene(scene)
    spec = scene.trajectory
    return dataclasses.replace(scene, trajectory=dataclasses.replace(spec, sway_wavelength=spec.lap_length / 3))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("n_frames", nargs="?", type=int, default=10_000)
    parser.add_argument("--sway", choices=("lap", "drifting"), default="lap")
    arguments = parser.parse_args()
    n_frames, sway = arguments.n_frames, arguments.sway
    sensor = get_sensor("sr3000")
    scene = patrol("arena") if sway == "lap" else simulate.get_scene("arena")
    true_poses = simulate.default_trajectory(scene, n_frames, frame_rate=sensor.frame_rate)
    odometry = simulate.noisy_odometry(true_poses, seed=9)
    pipeline = Pipeline()
    samples = []  # (frame, rss MB, median ms of the last 100 frames, model vertices, cubes of surface seen)
    seen = None
    window = []
    stage_times = []  # per frame: total ms, and the stages that see only the frame
    started = time.perf_counter()
    with threadpool_limits(limits=1, user_api="blas"):
        sequence = simulate.iter_sequence("arena", sensor, n_frames, seed=9, trajectory=true_poses)
        for index, (frame, truth) in enumerate(sequence):
            result = pipeline.process(dataclasses.replace(frame, pose=odometry[index]))
            window.append(result.timings["total"])
            stage_times.append((result.timings["total"],
                                sum(result.timings[stage] for stage in ("denoise", "segment", "surfaces"))))
            seen = seen or SeenArea(_SEEN_CUBE_CELLS * pipeline.model.cell_size)
            if index % 5 == 0:
                seen.add(frame, truth)
            if (index + 1) % 100 == 0:
                samples.append((index + 1, rss_mb(), float(np.median(window)), pipeline.model.n_vertices, seen.count()))
                window = []
                if (index + 1) % 1000 == 0:
                    print(f"frame {index + 1}: RSS {samples[-1][1]:.1f} MB, {samples[-1][2]:.2f} ms/frame, "
                          f"{samples[-1][4]} cubes of surface seen, "
                          f"{pipeline.model.n_vertices} model vertices", flush=True)
    elapsed = time.perf_counter() - started
    lap_frames = round(scene.trajectory.lap_length / min(scene.trajectory.speed / sensor.frame_rate, scene.trajectory.max_step))
    table = np.array(samples)
    after = table[table[:, 0] >= min(1000, n_frames // 2)]
    # Each end's figure is the median of the five samples (500 frames) at that end of the span: one
    # sample can catch a frame's temporaries (a re-meshed large patch) before the pipeline hands them back.
    first, last = np.median(after[:5], axis=0), np.median(after[-5:], axis=0)
    first[0], last[0] = after[0, 0], after[-1, 0]
    rss_slope = np.polyfit(after[:, 0], after[:, 1], 1)[0] * 1000
    time_slope = np.polyfit(after[:, 0], after[:, 2], 1)[0] * 1000
    lines = [
        f"Machine: {machine_description()}. Command: `.venv/bin/python benchmarks/soak.py {n_frames}"
        f"{' --sway drifting' if sway == 'drifting' else ''}`.", "",
        f"{n_frames} SR-3000 frames of the arena, default pipeline, drifting odometry; "
        + ("the robot patrols the loop, its sway repeating every lap (three per lap), so after the first lap "
           f"({lap_frames} "
           "frames) it sees nothing new; " if sway == "lap" else
           "the scene's default trajectory, whose sway does not repeat with the lap, so new bits of the arena come "
           "into view for thousands of frames; ") +
        f"{elapsed / 60:.1f} min including the simulation. Sampled every 100 frames (time per frame: the median of "
        "those 100, pipeline only); the figures at each end are the medians of the five samples at that end of the span "
        f"({int(after[0, 0])}-{int(after[4, 0])} and {int(after[-5, 0])}-{int(after[-1, 0])}).", "",
        "| measure | at frame {:d} | at frame {:d} | growth | slope per 1,000 frames |".format(int(first[0]), int(last[0])),
        "|---|---:|---:|---:|---:|",
        f"| resident memory (MB) | {first[1]:.1f} | {last[1]:.1f} | {100 * (last[1] / first[1] - 1):+.2f} % | {rss_slope:+.3f} MB |",
        f"| time per frame (ms) | {first[2]:.2f} | {last[2]:.2f} | {100 * (last[2] / first[2] - 1):+.2f} % | {time_slope:+.4f} ms |",
        f"| model vertices | {first[3]:,.0f} | {last[3]:,.0f} | {100 * (last[3] / first[3] - 1):+.2f} % | |",
        f"| surface seen (cubes of {seen.cell * 1000:.1f} mm) | {first[4]:,.0f} | {last[4]:,.0f} | "
        f"{100 * (last[4] / first[4] - 1):+.2f} % | |",
        *later_growth(table, 3000),
        *lap_times(np.array(stage_times), lap_frames, min(1000, n_frames // 2)),
        "", f"Peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB; model at the end: "
        f"{pipeline.model.n_vertices} vertices in {len(pipeline.model.patches)} patches; {pipeline.model.cells_carved} cells "
        f"carved as seen-through free space; late frames {pipeline.late}.",
        "", f"Load average at the end: {os.getloadavg()[0]:.2f}.",
    ]
    write_results(Path(__file__).parent / "results", "soak.md" if sway == "lap" else "soak_drifting_sway.md", lines)


if __name__ == "__main__":
    main()
