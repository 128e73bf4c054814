"""The online pipeline: one frame at a time through every stage (thesis Figure 3.1).

``denoise -> segment (normals, region growing) -> segment vertices -> register
(keyframe ICP from odometry; every few frames, the planes' fit to the model)
-> merge into the global model`` (and, when
configured, the pixels of no planar segment -- or all -- into a TSDF volume),
with the
re-meshing of changed patches and their level-of-detail order as deferrable
work: it runs every ``run.remesh_every`` frames (by default only while a
viewer shows the model live) when the frame's time budget allows, is
postponed (and counted) when it does not, and always runs in
`Pipeline.finish`. Every frame's per-stage timings and whether it overran
its budget are reported; no frame is dropped silently.

Examples
--------
>>> from rangesurf import simulate
>>> frames, truths = simulate.simulate_sequence("arena", "sr3000", n_frames=3, seed=0)
>>> pipeline = Pipeline()
>>> results = [pipeline.process(frame) for frame in frames]
>>> surfaces = pipeline.finish()
>>> sorted(results[-1].timings) == sorted(STAGES + ("total",))
True
>>> len(surfaces) >= 4 and all(surface.n_faces > 0 for surface in surfaces)
True
"""

from __future__ import annotations

import ctypes
import ctypes.util
import dataclasses
import functools
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rangesurf._grid import median_footprint, points_along_rays
from rangesurf.config import PipelineConfig
from rangesurf.denoise import denoise_range
from rangesurf.denoise.diffusion import remove_diffusion_bias
from rangesurf.frame import PinholeProjection, RangeFrame
from rangesurf.io._common import FormatError, atomic_path
from rangesurf.io.npz import load_arrays
from rangesurf.merge import GlobalModel, MergeStep, TSDFVolume
from rangesurf.mesh import Surface, segment_vertices, triangulate_segments
from rangesurf.normals import estimate_normals
from rangesurf.register import FrameTracker, RegistrationResult
from rangesurf.segment import (GrowingGrid, Segmentation, growing_decimation, pooled_frame_grid, segment_nxd,
                               segment_planes)

__all__ = ["Pipeline", "FrameResult", "STAGES"]

STAGES = ("denoise", "segment", "surfaces", "register", "merge", "volume", "deferred")
# From this many pixels on, registration and merging thin the frame (a depth camera gives far
# more points than they need).
_DENSE_FRAME = 200_000
_CHECKPOINT_VERSION = 1
# ICP's variance scale (`register.icp_variance_scale`, per full-resolution pixel) is divided by the
# registration grid's step to this power. Residuals err alike over a patch of pixels: at step 1 every
# pixel of it counts, thinned by s in both directions about 1 / s^2 of them would, if the patch were
# much wider than s. It is not much wider, so the power lies between 1 and 2: fitted with the scale on
# simulated sequences, odometry seeds 5-7, checked on 8-9 (benchmarks/calibration.py; 640x480 Kinect,
# step 3: with the old 30 at the power 1, a scale of 10, +-2 sigma held 99.8-100 % of the arena's pose
# errors over seeds 5-7; with 20 at the power 1.4, a scale of 4.3, pooled over seeds 5-9, 96.3 % (arena)
# and 93.6 % (corridor)). The scale was refitted to 26 (5.6 here) over seeds 5-9 once a correction no
# longer counted the frame's registration twice: 97.3 and 91.8 %. With keyframes kept longer (FrameTracker's
# keyframe_overlap_loss 0.05 -> 0.10) the power was refitted to 1.2 (7.0 here) over seeds 5-14: at 1.4 the
# Kinect corridor's UL3 was 89.0 % on seeds 10-14; at 1.2, 97.0 % (arena) and 92.8 % (corridor), the mean of
# the ten seeds' runs.
_ICP_STEP_EXPONENT = 1.2
# Frames between re-meshing the changed patches while a viewer shows them (run.remesh_every unset).
_LIVE_REMESH_EVERY = 25
# Time (ms) a frame must have left for handing freed memory back (malloc_trim: about 1-5 ms at 300 MB).
_RELEASE_MS = 5.0


@dataclass(frozen=True)
class FrameResult:
    """What `Pipeline.process` did with one frame.

    Parameters
    ----------
    index : int
        0-based position in the run.
    timestamp : float
    T_world_sensor : (4, 4) float64
        The tracked pose.
    covariance : (6, 6) float64
        Its uncertainty (world, rotation then translation).
    range : (H, W) float32
        The denoised range.
    segmentation : Segmentation
    registration : RegistrationResult or None
    merge : MergeStep
    surfaces : list of Surface
        The frame's own triangulated segments (sensor frame) when
        ``mesh.frame_surfaces`` is on, else empty.
    timings : dict of str -> float
        Milliseconds per stage (`STAGES`) and ``"total"``.
    deferred : bool
        Re-meshing was due but postponed for lack of time.
    late : bool
        The frame took longer than its budget.
    """

    index: int
    timestamp: float
    T_world_sensor: np.ndarray
    covariance: np.ndarray
    range: np.ndarray
    segmentation: Segmentation
    registration: RegistrationResult | None
    merge: MergeStep
    surfaces: list[Surface] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    deferred: bool = False
    late: bool = False


class Pipeline:
    """Joins the stages per a `PipelineConfig` and keeps the global model.

    Parameters
    ----------
    config : PipelineConfig, optional
        Defaults when omitted.

    Attributes
    ----------
    model : GlobalModel
    tracker : FrameTracker
    frames, late, deferred_runs, postponed : int
        Frames processed, frames over budget, patches re-meshed as deferred
        work, frames that left re-meshing for later.
    live_meshes : bool
        Whether something shows the model's meshes while the run goes on (a
        viewer); with ``run.remesh_every`` unset, changed patches are then
        re-meshed every 25 frames, otherwise only in `finish`.
    """

    def __init__(self, config: PipelineConfig | None = None) -> None:
        self.config = config or PipelineConfig()
        settings = self.config.register
        self.tracker = FrameTracker(
            max_correspondence_distance=settings.max_correspondence_distance,
            odometry_sigma=(settings.odometry_sigma_rotation, settings.odometry_sigma_translation),
            odometry_relative=settings.odometry_sigma_relative,
            keyframe_distance=settings.keyframe_distance, keyframe_angle=settings.keyframe_angle,
            keyframe_overlap_loss=settings.keyframe_overlap_loss,
        )
        merge = self.config.merge
        self.model = GlobalModel(
            cell_size=merge.cell_size, max_normal_angle=merge.max_normal_angle, max_plane_distance=merge.max_plane_distance,
            bridge=merge.bridge, min_overlap=merge.min_overlap, nonplanar=merge.nonplanar,
        )
        self.volume: TSDFVolume | None = None
        self.frames = 0
        self.late = 0
        self.deferred_runs = 0
        self.postponed = 0
        self.checkpoint_extra: dict[str, np.ndarray] = {}
        self.live_meshes = False
        self._remesh_queue: list = []
        self._release_due = False
        # Measured cost of re-meshing (mesh and LOD order), per cell; a cautious start.
        self._ms_per_cell = 0.005

    # ------------------------------------------------------------------
    # Derived settings (filled from the first frame).
    # ------------------------------------------------------------------

    def _budget_ms(self, frame: RangeFrame) -> float:
        return self.config.run.budget_ms or 1000.0 / frame.sensor.frame_rate

    def _decimation(self, frame: RangeFrame) -> int:
        chosen = self.config.register.decimate
        if chosen is not None:
            return chosen
        # A dense frame registers on the grid segmentation grows on (3 at 640x480): the normals are shared,
        # and ICP needs far fewer points (simulated 640x480 arena: 0.26 mm ATE against 0.23 at every 2nd
        # pixel, register 9.6 -> 5.2 ms).
        return growing_decimation(*frame.range.shape) if frame.range.size >= _DENSE_FRAME else 1

    def _vertex_sampling(self, frame: RangeFrame, distance: np.ndarray) -> tuple[int, bool]:
        """The stride and checkerboard of `segment_vertices`: vertices about a cell apart."""
        if self.config.merge.stride is not None:
            return self.config.merge.stride, False
        # Every frame: a sparser sample than the cell size's (2.5 -> 0.4 ms at 640x480).
        footprint = _median_footprint(frame, distance, rows=8, columns=4)
        if not footprint > 0:
            return 1, False
        return _stride_and_checkerboard(self.model.cell_size / footprint)

    # ------------------------------------------------------------------
    # One frame.
    # ------------------------------------------------------------------

    def process(self, frame: RangeFrame) -> FrameResult:
        """Run one frame through every stage and merge it into the model."""
        if not isinstance(frame, RangeFrame):
            raise TypeError(f"Pipeline.process takes a RangeFrame, got {type(frame).__name__}")
        timings: dict[str, float] = {}
        start = clock = time.perf_counter()

        def lap(stage: str) -> None:
            nonlocal clock
            now = time.perf_counter()
            timings[stage] = 1e3 * (now - clock)
            clock = now

        smooth = denoise_range(frame.range, method=self.config.denoise.method, sensor=frame.sensor,
                               intensity=frame.intensity, rays=frame.rays)
        points = points_along_rays(np.ascontiguousarray(frame.rays), np.ascontiguousarray(smooth))
        finite = np.isfinite(smooth)
        sigma = frame.sensor.range_sigma(np.where(finite, smooth, 1.0), frame.intensity)
        lap("denoise")

        projection = frame.sensor.projection if isinstance(frame.sensor.projection, PinholeProjection) else None
        step = self._decimation(frame)
        grid = None
        if self.config.segment.segmenter == "region":
            segmentation, grown = segment_planes(points, range_sigma=sigma, projection=projection, return_grid=True)
            if grown.decimate == step:
                # Registration takes the grid segmentation grew on: one pooling and one normal estimate for both.
                grid = grown
        else:
            normals = estimate_normals(points, projection=projection, range_sigma=sigma)
            segmentation = segment_nxd(points, normals)
            if step == 1:
                grid = GrowingGrid(points, sigma, projection, normals, 1)
        lap("segment")

        # UL1 (sensor level): diffusion leaves a systematic error on every frame's planes (convex range
        # images, rounded creases) that fusing frames does not average away while UL1 shrinks with every
        # frame fused; so it is estimated from the segments' noise-free planes and removed from the
        # vertices before they are merged (remove_diffusion_bias, with denoise_range's diffusion settings and
        # the sensor sigmas at the denoised range; benchmarks/calibration.py: corridor SR-3000 UL1 coverage
        # 81 -> 96 %).
        vertex_points, vertex_segmentation = points, segmentation
        remove_bias = self.config.denoise.remove_bias
        if remove_bias is None:
            remove_bias = frame.range.size < _DENSE_FRAME
        if self.config.denoise.method == "diffusion" and remove_bias:
            vertex_points, residuals = remove_diffusion_bias(smooth, frame.rays, segmentation.labels, segmentation.planes,
                                                             range_sigma=sigma)
            # The residuals (UL1's share of the noise left, and the frame's UL2) as measured on the
            # corrected points: the bias varied over each segment and was counted as noise.
            vertex_segmentation = dataclasses.replace(
                segmentation, residuals=np.where(np.isfinite(segmentation.residuals), residuals, np.nan))

        if self.model.cell_size is None:
            # Two pixel footprints: the model's vertices need not be denser than the sensor's noise
            # lets them be told apart, and merging costs scale with the vertices fused.
            self.model.cell_size = max(2.0 * _median_footprint(frame, smooth), 0.01)
        stride, checkerboard = self._vertex_sampling(frame, smooth)
        vertex_sets = segment_vertices(vertex_points, vertex_segmentation, range_sigma=sigma, stride=stride,
                                       checkerboard=checkerboard)
        frame_surfaces = []
        if self.config.mesh.frame_surfaces:
            frame_surfaces = triangulate_segments(vertex_points, vertex_segmentation, max_edge_pixels=self.config.mesh.max_edge_pixels,
                                                  max_view_angle=self.config.mesh.max_view_angle, range_sigma=sigma)
        lap("surfaces")

        # ICP's residuals are correlated over a patch of the full-resolution grid; on a thinned grid
        # neighbours lie further apart and err less alike (calibrated: benchmarks/calibration.py).
        self.tracker.icp_variance_scale = self.config.register.icp_variance_scale / step**_ICP_STEP_EXPONENT
        if grid is not None:
            icp_points, normals = grid.points, grid.normals
        elif step == 1 and projection is not None:
            # Segmentation grew on a pooled grid (176x144 SR-3000 frames), registration takes every pixel: only a
            # keyframe's normals are used (ICP's target), so they are estimated only for a frame that becomes one
            # (about one in ten). On the pooled grid's points and normals as the keyframe, the SR-3000 arena drifted
            # more (600 frames, seed 5: 27 against 20 mm over the last 100 frames, keyframes alone).
            icp_points = points
            normals = functools.partial(estimate_normals, points, projection=projection, range_sigma=sigma)
        else:
            grid = pooled_frame_grid(points, range_sigma=sigma, projection=projection, decimate=step)
            icp_points, normals = grid.points, grid.normals
        icp_projection = projection if grid is None else grid.projection
        if icp_projection is None:
            # No pinhole: closest-point registration on the valid points (k-d tree).
            keep = np.isfinite(icp_points).all(axis=-1) & np.isfinite(normals).all(axis=-1)
            icp_points, normals = icp_points[keep], normals[keep]
        # Unweighted by range noise (icp's source_sigma / target_sigma): the weights lower frame-to-frame errors
        # (simulated pairs: Kinect translation RMS 0.23 -> 0.18 mm), but in the tracker the trajectory drifts
        # more (benchmarks/pipeline.py, arena: ATE SR-3000 1.9 -> 4.2 mm, Kinect 0.3 -> 2.0 mm; 100-frame SR-3000
        # arena runs, seeds 1-4, 6, 7: ATE worse on all six, 3.1 -> 4.3 mm on average, while the worst
        # frame-to-frame error fell on five) and UL3 turns overconfident (SR-3000 arena coverage 95 -> 86 %):
        # an error that accumulates, not noise. A 3 cm floor on the residual sigma takes most of it back
        # (seed 5: 4.2 -> 2.4 mm against 1.8 unweighted); suspected: systematic errors at close range (the
        # diffusion's leftover bias grows there), which the weights favour.
        tracked = self.tracker.track(icp_points, normals, projection=icp_projection, odometry=frame.pose)
        every = self.config.register.align_to_model_every
        if every and self.frames % every == 0 and self.model.patches:
            # Loop closure by planes: where the frame sees patches the model placed before, their planes
            # pull a drifted pose back (weighed by how well each is placed against the pose's covariance).
            aligned = self.model.align(vertex_sets, tracked.T_world_sensor, tracked.covariance)
            if aligned.applied:
                self.tracker.correct(aligned.T_world_sensor, aligned.covariance)
                tracked = dataclasses.replace(tracked, T_world_sensor=aligned.T_world_sensor, covariance=aligned.covariance)
        lap("register")

        # The pose's world covariance (drift included): the model is compared with the world.
        merge_step = self.model.add_frame(vertex_sets, tracked.T_world_sensor, covariance=tracked.covariance,
                                          timestamp=frame.timestamp)
        every = self.config.merge.carve_every
        if every and projection is not None and self.frames % every == 0:
            # Free space: cells this frame sees through (a copy built while the pose had slipped) go.
            self.model.carve(smooth, projection, tracked.T_world_sensor, range_sigma=sigma, covariance=tracked.covariance)
        every = self.config.merge.fold_every
        if every and (self.frames + 1) % every == 0:
            # Fragments that a patch has since grown over are folded into it: re-seen on every lap, they
            # would make the model grow with time rather than with the area seen.
            self.model.fold_fragments()
        lap("merge")

        if self.config.merge.volume != "off":
            if self.volume is None:
                self.volume = TSDFVolume(self.config.merge.voxel_size or self.model.cell_size)
            mask = finite if self.config.merge.volume == "all" else finite & (segmentation.labels == 0)
            if mask.any():
                self.volume.integrate(points, tracked.T_world_sensor, range_sigma=np.where(finite, sigma, 1.0), mask=mask,
                                      pose_covariance=tracked.covariance)
        lap("volume")

        budget = self._budget_ms(frame)
        every = self.config.run.remesh_every
        if every is None:
            every = _LIVE_REMESH_EVERY if self.live_meshes else 0
        if every and (self.frames + 1) % every == 0:
            # Due: the patches changed since they were last meshed join the queue.
            queued = {id(patch) for patch in self._remesh_queue}
            self._remesh_queue += [patch for patch in self.model.stale_patches() if id(patch) not in queued]
        deferred = False
        if self._remesh_queue:
            # Re-meshing is the thesis's deferrable work: as many queued patches as the frame's
            # remaining time allows (from the measured cost per cell), the rest on later frames.
            left_ms = budget - 1e3 * (time.perf_counter() - start)
            cells = int(left_ms / self._ms_per_cell) if left_ms > 0 else 0
            begin = time.perf_counter()
            done = self.model.refresh(patches=self._remesh_queue, max_cells=cells) if cells > 0 else []
            if done:
                spent = 1e3 * (time.perf_counter() - begin)
                self._ms_per_cell = 0.7 * self._ms_per_cell + 0.3 * spent / sum(patch.n_cells for patch in done)
                self.deferred_runs += len(done)
            live = {id(patch) for patch in self.model.patches}
            finished = {id(patch) for patch in done}
            self._remesh_queue = [patch for patch in self._remesh_queue if id(patch) in live and id(patch) not in finished]
            if self._remesh_queue:
                self.postponed += 1
                deferred = True
        every = self.config.run.release_memory_every
        if every and (self.frames + 1) % every == 0:
            self._release_due = True
        if self._release_due and budget - 1e3 * (time.perf_counter() - start) > _RELEASE_MS:
            _release_freed_memory()
            self._release_due = False
        lap("deferred")

        timings["total"] = 1e3 * (time.perf_counter() - start)
        late = timings["total"] > budget
        self.late += late
        result = FrameResult(
            index=self.frames, timestamp=frame.timestamp, T_world_sensor=tracked.T_world_sensor,
            covariance=tracked.covariance, range=smooth, segmentation=segmentation, registration=tracked.registration,
            merge=merge_step, surfaces=frame_surfaces, timings=timings, deferred=deferred, late=late,
        )
        self.frames += 1
        return result

    def finish(self) -> list[Surface]:
        """Do all deferred work and return the model's surfaces (world frame, with LOD order).

        With the volumetric path on, the volume's mesh (marching cubes) comes last.
        """
        self._remesh_queue = []
        surfaces = self.model.surfaces(lod=True)
        if self.volume is not None and self.volume.n_blocks:
            mesh = self.volume.extract_mesh()
            if mesh.n_vertices:
                surfaces.append(mesh)
        return surfaces

    # ------------------------------------------------------------------
    # Checkpoints.
    # ------------------------------------------------------------------

    def save_checkpoint(self, path: str | Path, *, extra: dict[str, np.ndarray] | None = None) -> Path:
        """Write the model, the tracker and the counters to one ``.npz``, atomically.

        `Pipeline.resume` continues from it as if the run had not stopped.
        ``extra`` arrays (names without "/") travel along and come back as
        ``checkpoint_extra`` of the resumed pipeline.
        """
        path = Path(path)
        arrays = self.model.to_arrays(prefix="model/")
        if self.volume is not None:
            arrays.update(self.volume.to_arrays(prefix="volume/"))
        arrays.update({f"extra/{name}": value for name, value in (extra or {}).items()})
        arrays.update({f"tracker/{name}": value for name, value in self.tracker.state().items()})
        arrays.update({
            "pipeline/version": np.array(_CHECKPOINT_VERSION), "pipeline/config": np.array(self.config.to_toml()),
            "pipeline/counters": np.array([self.frames, self.late, self.deferred_runs, self.postponed], np.int64),
        })
        with atomic_path(path) as temporary:
            np.savez(temporary, **arrays)
        return path

    @classmethod
    def resume(cls, path: str | Path) -> Pipeline:
        """A pipeline continuing from `save_checkpoint` (with the configuration saved in it)."""
        import tomllib

        path = Path(path)
        arrays = load_arrays(path)
        for name in ("pipeline/version", "pipeline/config", "pipeline/counters"):
            if name not in arrays:
                raise FormatError(path, "missing from the pipeline checkpoint", where=f"field {name!r}")
        if int(arrays["pipeline/version"]) != _CHECKPOINT_VERSION:
            raise FormatError(path, f"checkpoint version {int(arrays['pipeline/version'])}, this rangesurf reads "
                              f"{_CHECKPOINT_VERSION}", where="field 'pipeline/version'")
        config = PipelineConfig.from_dict(tomllib.loads(str(arrays["pipeline/config"])), source=f"{path} (config)")
        pipeline = cls(config)
        pipeline.model = GlobalModel.from_arrays(arrays, prefix="model/", source=path)
        if "volume/settings" in arrays:
            pipeline.volume = TSDFVolume.from_arrays(arrays, prefix="volume/")
        pipeline.tracker.restore({name[len("tracker/"):]: value for name, value in arrays.items() if name.startswith("tracker/")})
        pipeline.frames, pipeline.late, pipeline.deferred_runs, pipeline.postponed = (int(v) for v in arrays["pipeline/counters"])
        pipeline.checkpoint_extra = {name[len("extra/"):]: value for name, value in arrays.items() if name.startswith("extra/")}
        return pipeline


def _stride_and_checkerboard(cells_per_pixel: float) -> tuple[int, bool]:
    """The stride and checkerboard (`rangesurf.mesh.segment_vertices`) that merge vertices about a cell apart.

    ``cells_per_pixel`` is the cell size over the pixel footprint. Strides
    are rounded, except between 1 and 2, a fourfold step in vertices: there
    the checkerboard of the full grid, vertices ``sqrt(2)`` pixels apart,
    is taken where it is the nearest of the three by ratio (from 2^(1/4) to
    2^(3/4) cells per pixel). Simulated SR-3000 arena, 100 frames, seeds 5-8,
    where later frames see far walls (about 1.4 cells per pixel): half the
    vertices merged there; the model's distance to the true planes at the
    95th percentile 8.4 / 10.2 / 8.4 / 7.8 mm against 8.6 / 10.3 / 8.5 / 8.0
    with stride 1, the median within 0.05 mm; ATE 2.44 / 2.92 / 2.55 / 2.05
    mm against 2.28 / 2.99 / 2.61 / 1.98. Over the 200 frames of `rangesurf
    demo` the model's median / 95th percentile went from 2.2 / 8.5 to 2.1 /
    9.1 mm, and in the calibration's 200-frame run from 2.1 / 9.3 to 2.3 /
    9.0 mm: differences of the size seeds make.

    >>> [_stride_and_checkerboard(ratio) for ratio in (1.0, 1.43, 1.9, 2.7)]
    [(1, False), (1, True), (2, False), (3, False)]
    """
    if cells_per_pixel < 2.0 ** 0.25:
        return 1, False
    if cells_per_pixel < 2.0 ** 0.75:
        return 1, True
    return max(2, round(cells_per_pixel)), False


def _median_footprint(frame: RangeFrame, distance: np.ndarray, *, rows: int = 4, columns: int = 1) -> float:
    """Median distance (metres) between horizontally neighbouring rays at their range.

    On every ``rows``-th row, the ray pairs starting at every ``columns``-th column.
    """
    return median_footprint(_ray_angles(frame.rays, rows, columns), distance, rows, columns)


def _ray_angles(rays: np.ndarray, rows: int, columns: int) -> np.ndarray:
    """Angles between horizontally neighbouring rays, sampled as `_median_footprint` samples them.

    A sensor's rays are one read-only array that all its frames share
    (`SensorModel.rays`): their angles are kept for the next frame (at 640x480
    the arc cosines took 0.3 ms of every frame).
    """
    cached = _RAY_ANGLES.get((rows, columns))
    if cached is not None and cached[0] is rays:
        return cached[1]
    sampled = rays[::rows]
    right, left = sampled[:, 1::columns], sampled[:, : sampled.shape[1] - 1 : columns]
    # Component by component: NumPy's sum over a strided last axis of 3 took ten times as long.
    dot = right[..., 0] * left[..., 0] + right[..., 1] * left[..., 1] + right[..., 2] * left[..., 2]
    angles = np.arccos(np.clip(dot, -1.0, 1.0))
    if not rays.flags.writeable:
        _RAY_ANGLES[(rows, columns)] = (rays, angles)
    return angles


# (rows, columns) -> (the read-only rays, their sampled angles): `_ray_angles`.
_RAY_ANGLES: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None where the C library has none (musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(name), "malloc_trim", None) if name else None
    except OSError:
        return None


def _release_freed_memory() -> None:
    """Hand the heap pages that freed temporaries left behind back to the system.

    glibc keeps freed memory for reuse and raises its threshold for using
    fresh pages after large frees, so a long run's resident memory ratchets
    up to its peaks (a re-meshed large patch, two patches joined) and stays
    there; trimming lets it follow what the process actually holds.
    """
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
