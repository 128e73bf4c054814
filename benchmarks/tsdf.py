"""Volumetric (TSDF) fusion against Open3D's ``UniformTSDFVolume``.

Run: ``.venv/bin/python benchmarks/tsdf.py``; writes ``benchmarks/results/tsdf.md``.
Two inputs: the five Stanford bunny scans at their reference alignment
(``bun.conf``), fused at 1 mm, and a simulated 640x480 Kinect sequence in the
arena (every 2nd of 20 frames at the true poses, all noise effects on,
readings beyond 4 m dropped for both), fused at 2 cm. Both libraries get the
same voxel size and truncation (4 voxels), one core each
(``OMP_NUM_THREADS=1``, Open3D one thread; rangesurf's kernels are serial).
Open3D needs a pinhole depth image: the bunny grids are stored bottom-up
(``fy < 0``), so they are flipped for it; building its RGBD images is not
timed. Its dense volume is the cube around the input points (plus the
truncation). Accuracy: the distance of every input point (and, for the
simulation, every true surface point) to each mesh, point to triangle, by
Open3D's ``RaycastingScene``.

Open3D's hashed volumes were the first choice, but in the Open3D 0.20 wheel
installed here the legacy ``ScalableTSDFVolume`` returns empty meshes even
for one flat wall at 2 m, so the dense ``UniformTSDFVolume`` is the peer here.
(The tensor ``VoxelBlockGrid`` works: its empty meshes in a first trial came
from ``extract_triangle_mesh``'s default ``weight_threshold=3``, which drops
voxels seen by fewer than three frames; ``benchmarks/pipeline.py`` uses it.)
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import rangesurf  # noqa: E402
from rangesurf import simulate  # noqa: E402
from rangesurf.bench import default_data_root, machine_description, time_pair, write_results  # noqa: E402
from rangesurf.merge.tsdf import TSDFVolume  # noqa: E402

BUNNY_SCANS = ("bun000", "bun045", "bun090", "chin", "top2")
KINECT_FRAMES = 20
KINECT_STRIDE = 2
KINECT_MAX_RANGE = 4.0


def open3d_inputs(o3d, frames):
    """Per frame: Open3D RGBD image (z depth in metres, 0 where no return), intrinsic, extrinsic (T_sensor_world)."""
    inputs = []
    for frame in frames:
        projection = frame.sensor.projection
        height, width = frame.shape
        depth = np.nan_to_num(frame.range * frame.rays[..., 2], nan=0.0).astype(np.float32)
        fy, cy = projection.fy, projection.cy
        if fy < 0:  # bottom-up grid: flip it into the top-down one a pinhole camera expects
            depth, fy, cy = depth[::-1].copy(), -fy, height - 1 - cy
        intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, projection.fx, fy, projection.cx, cy)
        color = o3d.geometry.Image(np.zeros((height, width, 3), np.uint8))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            color, o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=float(frame.sensor.max_range),
            convert_rgb_to_intensity=False,
        )
        inputs.append((rgbd, intrinsic, np.linalg.inv(frame.reference_pose)))
    return inputs


def distances(o3d, vertices, faces, points):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(points, np.float32))).numpy()


def compare(o3d, name, frames, voxel_size, truth_points=None, repeats=3):
    truncation = 4 * voxel_size
    inputs = open3d_inputs(o3d, frames)

    def ours():
        volume = TSDFVolume(voxel_size, truncation=truncation)
        for frame in frames:
            volume.integrate(frame, frame.reference_pose)
        return volume

    inputs_world = np.concatenate([frame.world_points(use_reference=True) for frame in frames])
    low = inputs_world.min(axis=0) - 2 * truncation
    resolution = int(np.ceil((inputs_world.max(axis=0) + 2 * truncation - low).max() / voxel_size))

    def peer():
        volume = o3d.pipelines.integration.UniformTSDFVolume(
            length=resolution * voxel_size, resolution=resolution, sdf_trunc=truncation,
            color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor, origin=low.reshape(3, 1),
        )
        for rgbd, intrinsic, extrinsic in inputs:
            volume.integrate(rgbd, intrinsic, extrinsic)
        return volume

    ours_integrate, peer_integrate = time_pair(ours, peer, repeats=repeats, warmup=1)
    our_volume, peer_volume = ours(), peer()
    ours_extract, peer_extract = time_pair(our_volume.extract_mesh, peer_volume.extract_triangle_mesh, repeats=repeats, warmup=1)
    surface = our_volume.extract_mesh()
    peer_mesh = peer_volume.extract_triangle_mesh()
    meshes = {
        "rangesurf TSDFVolume": (surface.vertices, surface.faces),
        "Open3D UniformTSDFVolume": (np.asarray(peer_mesh.vertices), np.asarray(peer_mesh.triangles)),
    }
    rows = []
    for method, (vertices, faces) in meshes.items():
        row = {"input": name, "method": method, "vertices": len(vertices)}
        measured = distances(o3d, vertices, faces, inputs_world)
        row["input_median"], row["input_p95"] = np.median(measured), np.percentile(measured, 95)
        if truth_points is not None:
            measured = distances(o3d, vertices, faces, truth_points)
            row["truth_median"], row["truth_p95"] = np.median(measured), np.percentile(measured, 95)
        ours_method = method.startswith("rangesurf")
        row["integrate_ms"] = 1000 * (ours_integrate if ours_method else peer_integrate) / len(frames)
        row["extract_ms"] = 1000 * (ours_extract if ours_method else peer_extract)
        row["integrate_ratio"] = None if ours_method else peer_integrate / ours_integrate
        row["extract_ratio"] = None if ours_method else peer_extract / ours_extract
        rows.append(row)
    # Open3D re-projects depth through the pinhole intrinsic; where the frame's own rays differ (the
    # bunny scanner is not a pinhole), its input points move.
    moved = []
    for frame in frames:
        directions = frame.sensor.projection.directions(*frame.shape)
        depth = frame.range * frame.rays[..., 2]
        shift = np.linalg.norm(directions * depth[..., None] - frame.points, axis=-1)
        moved.append(shift[np.isfinite(shift)])
    rows[1]["reprojection"] = float(np.median(np.concatenate(moved)))
    rows[0]["blocks"] = (f"rangesurf {our_volume.n_blocks} blocks of 8^3 voxels ({our_volume.nbytes / 1e6:.0f} MB); "
                         f"Open3D dense {resolution}^3 voxels")
    return rows


def main() -> None:
    import open3d as o3d

    if hasattr(o3d.utility, "set_max_threads"):
        o3d.utility.set_max_threads(1)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    rows = []
    bunny = default_data_root() / "bunny"
    if (bunny / "bun000.ply").is_file():
        frames = [rangesurf.load(bunny / f"{scan}.ply")[0] for scan in BUNNY_SCANS]
        rows += compare(o3d, "bunny, 5 scans 512x400, 1 mm", frames, 0.001)
    frames, truths = simulate.simulate_sequence("arena", "kinect", KINECT_FRAMES, seed=4)
    frames, truths = frames[::KINECT_STRIDE], truths[::KINECT_STRIDE]
    with np.errstate(invalid="ignore"):
        frames = [frame.replace(range=np.where(frame.range <= KINECT_MAX_RANGE, frame.range, np.nan)) for frame in frames]
    truth_points = []
    for frame, truth in zip(frames, truths):
        points = frame.rays * truth.range[..., None]
        points = points[np.isfinite(frame.range) & np.isfinite(truth.range)].astype(np.float64)
        truth_points.append(points @ truth.T_world_sensor[:3, :3].T + truth.T_world_sensor[:3, 3])
    rows += compare(o3d, f"arena Kinect, {len(frames)} frames 640x480 (<= 4 m), 2 cm", frames, 0.02,
                    truth_points=np.concatenate(truth_points), repeats=3)

    def mm(value):
        return "—" if value is None else f"{1000 * value:.2f}"

    def ratio(value):
        return "—" if value is None else f"{value:.2f}x"

    lines = [
        f"Machine: {machine_description()}; Open3D {o3d.__version__}; one core each (OMP_NUM_THREADS=1, Open3D one thread).",
        "",
        "Same voxel size and truncation (4 voxels) for both; times are medians of alternating runs "
        "(`rangesurf.bench.time_pair`); ratio = Open3D time / rangesurf time (> 1: rangesurf faster). Distances are "
        "point to triangle (Open3D `RaycastingScene`), in mm: of every input point to the mesh, and for the "
        "simulation of every true surface point (noise-free ranges of the same pixels).",
        "",
        "| input | method | ms / frame integrate | ratio | ms extract | ratio | vertices | input median | input p95 "
        "| truth median | truth p95 |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(
            f"| {row['input']} | {row['method']} | {row['integrate_ms']:.1f} | {ratio(row['integrate_ratio'])} "
            f"| {row['extract_ms']:.1f} | {ratio(row['extract_ratio'])} | {row['vertices']} | {mm(row['input_median'])} "
            f"| {mm(row['input_p95'])} | {mm(row.get('truth_median'))} | {mm(row.get('truth_p95'))} |"
        )
    lines += [""] + [f"Volumes for {row['input']}: {row['blocks']}." for row in rows if "blocks" in row]
    lines += [""] + [
        f"Open3D's pinhole re-projection of the depth moves the input points of {row['input']} by "
        f"{1000 * row['reprojection']:.3f} mm (median): its input is not quite the same." for row in rows
        if "reprojection" in row and row["reprojection"] > 1e-5
    ]
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    write_results(Path(__file__).parent / "results", "tsdf.md", lines)


if __name__ == "__main__":
    main()
