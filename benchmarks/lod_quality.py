"""Accuracy of coarse levels against quadric-error decimation at the same vertex count.

Run: ``.venv/bin/python benchmarks/lod_quality.py``; writes
``benchmarks/results/lod_quality.md``. Every surface of at least 400 vertices
of simulated arena and corridor frames (denoised, segmented, grid
triangulated) is reduced to 10 % of its vertices by rangesurf's progressive
order (`build_levels_at`) and by `fast_simplification.simplify` (bench
extra), and compared with the full-resolution surface:

* RMS and Hausdorff distance, both ways: every full-resolution vertex to the
  coarse mesh and every coarse vertex to the full mesh (Open3D's
  ``RaycastingScene.compute_distance``, exact point-to-triangle);
* outline error: the Hausdorff distance between the two meshes' boundary
  edges, each sampled every 2 mm.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, write_results  # noqa: E402
from rangesurf.lod import build_levels_at, progressive_order  # noqa: E402
from rangesurf.mesh import boundary_loops, triangulate_segments  # noqa: E402
from rangesurf.segment import segment_frame  # noqa: E402

FRACTION = 0.1
MIN_VERTICES = 400


def distances_to(mesh_vertices, mesh_faces, points) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh_vertices.astype(np.float32)), o3d.core.Tensor(mesh_faces.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def boundary_samples(vertices, faces, step=0.002) -> np.ndarray:
    samples = []
    for loop in boundary_loops(faces):
        start, end = vertices[loop], vertices[np.roll(loop, -1)]
        for a, b in zip(start, end):
            n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
            samples.append(a + np.linspace(0, 1, n)[:, None] * (b - a))
    return np.concatenate(samples) if samples else np.zeros((0, 3))


def compare(full_vertices, full_faces, coarse_vertices, coarse_faces) -> dict:
    one = distances_to(coarse_vertices, coarse_faces, full_vertices)
    two = distances_to(full_vertices, full_faces, coarse_vertices)
    both = np.concatenate([one, two])
    outline_full = boundary_samples(full_vertices, full_faces)
    outline_coarse = boundary_samples(coarse_vertices, coarse_faces)
    outline = max(cKDTree(outline_coarse).query(outline_full)[0].max(), cKDTree(outline_full).query(outline_coarse)[0].max())
    return {"rms": float(np.sqrt(np.mean(both**2))), "hausdorff": float(both.max()), "outline": float(outline)}


def main() -> None:
    import fast_simplification

    rows = []
    for sensor, scene, n_frames in (("sr3000", "arena", 2), ("sr3000", "corridor", 2), ("kinect", "arena", 1), ("kinect", "corridor", 1)):
        frames, _ = simulate.simulate_sequence(scene, sensor, n_frames, seed=4)
        for frame in frames:
            result = segment_frame(frame)
            for surface in triangulate_segments(result.points, result.segmentation):
                if surface.n_vertices < MIN_VERTICES or surface.n_faces < 10:
                    continue
                vertices = surface.vertices.astype(np.float64)
                count = int(FRACTION * surface.n_vertices)
                surface.lod_order, surface.lod_error = progressive_order(surface)
                (level,) = build_levels_at(surface, [count])
                ours = compare(vertices, surface.faces, vertices[surface.lod_order[:count]], level.faces)
                surface.lod_order, surface.lod_error = progressive_order(surface, interpolation="sibson")
                (level,) = build_levels_at(surface, [count])
                sibson = compare(vertices, surface.faces, vertices[surface.lod_order[:count]], level.faces)
                # fast-simplification counts triangles; ask for the share of triangles that leaves
                # about `count` vertices (a mesh has about twice as many triangles as vertices).
                points, faces = fast_simplification.simplify(
                    vertices.astype(np.float32), surface.faces.astype(np.int64),
                    target_count=int(round(count * surface.n_faces / surface.n_vertices)))
                theirs = compare(vertices, surface.faces, np.asarray(points, np.float64), np.asarray(faces))
                rows.append({"sensor": sensor, "scene": scene, "vertices": surface.n_vertices, "kept": count,
                             "peer_kept": len(points), "ours": ours, "sibson": sibson, "peer": theirs})
    lines = [
        f"Machine: {machine_description()}. Command: `.venv/bin/python benchmarks/lod_quality.py`.",
        "",
        f"{len(rows)} surfaces of >= {MIN_VERTICES} vertices (simulated arena and corridor, SR-3000 and Kinect, "
        f"denoised and segmented with the defaults), each reduced to {FRACTION:.0%} of its vertices (fast-simplification "
        "asked for the matching share of triangles; its vertex count is in brackets). Distances in mm; "
        "medians over surfaces, and the share of surfaces where rangesurf is at least as good.",
        "",
        "rangesurf orders with Shepard interpolation (the default); the Sibson column is the same order "
        "with natural-neighbour interpolation (`interpolation=\"sibson\"`).",
        "",
        "| measure | rangesurf (median) | fast-simplification (median) | rangesurf <= peer | rangesurf Sibson (median) | Sibson <= peer |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for key, name in (("rms", "RMS distance, both ways"), ("hausdorff", "Hausdorff distance"), ("outline", "outline Hausdorff")):
        ours = np.array([r["ours"][key] for r in rows]) * 1000
        peer = np.array([r["peer"][key] for r in rows]) * 1000
        sibson = np.array([r["sibson"][key] for r in rows]) * 1000
        lines.append(f"| {name} | {np.median(ours):.2f} | {np.median(peer):.2f} | {np.mean(ours <= peer * 1.0001):.0%} "
                     f"| {np.median(sibson):.2f} | {np.mean(sibson <= peer * 1.0001):.0%} |")
    lines += ["", "Per surface:", "", "| sensor | scene | vertices | kept (peer) | RMS mm ours / peer | Hausdorff mm ours / peer | outline mm ours / peer |", "|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['sensor']} | {r['scene']} | {r['vertices']} | {r['kept']} ({r['peer_kept']}) | "
                     f"{1000 * r['ours']['rms']:.2f} / {1000 * r['peer']['rms']:.2f} | "
                     f"{1000 * r['ours']['hausdorff']:.1f} / {1000 * r['peer']['hausdorff']:.1f} | "
                     f"{1000 * r['ours']['outline']:.1f} / {1000 * r['peer']['outline']:.1f} |")
    write_results(Path(__file__).parent / "results", "lod_quality.md", lines)


if __name__ == "__main__":
    main()
