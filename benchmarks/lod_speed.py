"""Speed of the surface stage: grid triangulation of a frame, progressive order, level selection.

Run: ``.venv/bin/python benchmarks/lod_speed.py``; writes ``benchmarks/results/lod_speed.md``.
The progressive order of a 25,600-vertex surface (a 160x160 roof: two planes
meeting at a ridge) is timed against `fast_simplification.simplify` taking
the same mesh to 10 % of its vertices (quadric error decimation; bench
extra), one core each.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, time_call, time_pair, write_results  # noqa: E402
from rangesurf.lod import build_levels, progressive_order, select_level  # noqa: E402
from rangesurf.mesh import Surface, triangulate_in_plane, triangulate_segments  # noqa: E402
from rangesurf.segment import segment_frame  # noqa: E402


def roof(n: int = 160) -> Surface:
    rows, cols = np.mgrid[0:n, 0:n] / (n - 1)
    x, y = cols.ravel(), rows.ravel()
    vertices = np.column_stack([x, y, 2.0 - 0.2 * np.abs(x - 0.5)])
    faces = triangulate_in_plane(vertices, [0, 0, -1, 2])
    return Surface(vertices, faces, np.tile([0, 0, -1.0], (len(vertices), 1)), np.full((len(vertices), 2), -1))


def main() -> None:
    cv2.setNumThreads(1)
    lines = [f"Machine: {machine_description()}; one core (OpenCV and fast-simplification single-threaded).", ""]
    lines += ["| step | size | ms | note |", "|---|---|---:|---|"]
    for sensor in ("sr3000", "kinect"):
        frames, _ = simulate.simulate_sequence("arena", sensor, 1, seed=2)
        result = segment_frame(frames[0])
        seconds = time_call(lambda: triangulate_segments(result.points, result.segmentation), repeats=10)
        surfaces = triangulate_segments(result.points, result.segmentation)
        faces = sum(surface.n_faces for surface in surfaces)
        height, width = result.range.shape
        lines.append(f"| triangulate_segments (all segments of a frame) | {width}x{height} | {1e3 * seconds:.1f} "
                     f"| {len(surfaces)} surfaces, {faces} triangles |")
    surface = roof()
    order_seconds = time_call(lambda: progressive_order(surface), repeats=5)
    surface.lod_order, surface.lod_error = progressive_order(surface)
    levels_seconds = time_call(lambda: build_levels(surface), repeats=3)
    surface.levels = build_levels(surface)
    select_seconds = time_call(lambda: select_level(surface.levels, fraction=0.1), repeats=1000)
    lines.append(f"| progressive_order | {surface.n_vertices} vertices | {1e3 * order_seconds:.1f} | |")
    lines.append(f"| build_levels (ladder of halvings, triangulated once) | {surface.n_vertices} vertices | "
                 f"{1e3 * levels_seconds:.1f} | {len(surface.levels)} levels |")
    lines.append(f"| select_level (per rendered frame) | {len(surface.levels)} levels | {1e3 * select_seconds:.4f} | |")
    try:
        import fast_simplification
    except ImportError:
        lines.append("| fast_simplification.simplify to 10 % | — | — | not installed (bench extra) |")
    else:
        points, triangles = surface.vertices.astype(np.float32), surface.faces.astype(np.int64)
        ours, peer = time_pair(lambda: progressive_order(surface),
                               lambda: fast_simplification.simplify(points, triangles, target_reduction=0.9), repeats=5)
        lines.append(f"| fast_simplification.simplify to 10 % | {surface.n_vertices} vertices | {1e3 * peer:.1f} "
                     f"| progressive_order / simplify (alternating): {ours / peer:.2f}x the time |")
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    write_results(Path(__file__).parent / "results", "lod_speed.md", lines)


if __name__ == "__main__":
    main()
