"""The online pipeline: stages joined per config, budget accounting, deferred work, checkpoints."""

import os

import numpy as np
import pytest

from rangesurf import simulate
from rangesurf.config import PipelineConfig
from rangesurf.pipeline import STAGES, Pipeline, _malloc_trim, _release_freed_memory


@pytest.fixture(scope="module")
def frames():
    return simulate.simulate_sequence("arena", "sr3000", 6, seed=2)


def test_every_frame_reports_its_stages_and_is_tracked(frames):
    sequence, truths = frames
    pipeline = Pipeline()
    results = [pipeline.process(frame) for frame in sequence]
    for result, truth in zip(results, truths):
        assert set(result.timings) == set(STAGES) | {"total"}
        assert result.timings["total"] >= sum(result.timings[stage] for stage in STAGES) * 0.99
        # Simulated frames carry the true pose as odometry: tracking stays on it.
        assert np.linalg.norm(result.T_world_sensor[:3, 3] - truth.T_world_sensor[:3, 3]) < 0.005
    assert pipeline.frames == 6 and pipeline.model.n_frames == 6
    assert results[-1].merge.cells_updated > results[-1].merge.cells_added


def test_frames_over_budget_are_counted_and_deferred_work_waits(frames):
    sequence, _ = frames
    config = PipelineConfig.from_dict({"run": {"budget_ms": 0.001, "remesh_every": 2}})
    pipeline = Pipeline(config)
    results = [pipeline.process(frame) for frame in sequence]
    assert pipeline.late == 6 and all(result.late for result in results)
    # No time left in any frame: the re-meshing due every 2nd frame is postponed, never dropped ...
    assert pipeline.deferred_runs == 0 and pipeline.postponed > 0 and results[-1].deferred
    # ... and done at the end.
    surfaces = pipeline.finish()
    assert surfaces and all(surface.n_faces > 0 and surface.lod_error.any() for surface in surfaces if surface.n_vertices > 10)


def test_deferred_work_runs_when_there_is_time(frames):
    sequence, _ = frames
    pipeline = Pipeline(PipelineConfig.from_dict({"run": {"budget_ms": 10_000.0, "remesh_every": 2}}))
    for frame in sequence:
        pipeline.process(frame)
    assert pipeline.deferred_runs > 0 and pipeline.late == 0


def test_frame_surfaces_on_request(frames):
    sequence, _ = frames
    pipeline = Pipeline(PipelineConfig.from_dict({"mesh": {"frame_surfaces": True}}))
    result = pipeline.process(sequence[0])
    assert result.surfaces and all(surface.n_faces > 0 for surface in result.surfaces)
    assert Pipeline().process(sequence[0]).surfaces == []


def test_checkpoint_round_trip_continues_identically(frames, tmp_path):
    sequence, _ = frames
    straight = Pipeline()
    for frame in sequence:
        straight.process(frame)
    first = Pipeline()
    for frame in sequence[:3]:
        first.process(frame)
    first.save_checkpoint(tmp_path / "checkpoint.npz", extra={"note": np.arange(3)})
    resumed = Pipeline.resume(tmp_path / "checkpoint.npz")
    assert resumed.frames == 3 and resumed.checkpoint_extra["note"].tolist() == [0, 1, 2]
    for frame in sequence[3:]:
        resumed.process(frame)
    assert np.array_equal(resumed.model.trajectory()[1], straight.model.trajectory()[1])
    for ours, theirs in zip(resumed.model.surfaces(lod=False), straight.model.surfaces(lod=False)):
        assert np.array_equal(ours.vertices, theirs.vertices)


def test_bad_inputs(tmp_path):
    with pytest.raises(TypeError, match="RangeFrame"):
        Pipeline().process(np.zeros((10, 10)))
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="junk.npz"):
        Pipeline.resume(tmp_path / "junk.npz")


def test_the_volumetric_path_meshes_the_round_pillar(tmp_path):
    """With merge.volume = "all" every pixel also goes into a TSDF volume; the arena's round pillar
    (axis (3.0, 2.5), radius 0.15 m), seen around frame 60, comes out round."""
    frames, _ = simulate.simulate_sequence("arena", "sr3000", 64, seed=3)
    frames = frames[56:]
    config = PipelineConfig.from_dict({"merge": {"volume": "all", "voxel_size": 0.02}})
    pipeline = Pipeline(config)
    for frame in frames[:4]:
        pipeline.process(frame)
    pipeline.save_checkpoint(tmp_path / "checkpoint.npz")
    resumed = Pipeline.resume(tmp_path / "checkpoint.npz")
    for frame in frames[4:]:
        pipeline.process(frame)
        resumed.process(frame)
    volume_mesh = pipeline.finish()[-1]
    assert not np.isfinite(volume_mesh.plane).any() and "UL3" in volume_mesh.uncertainty
    radial = np.hypot(volume_mesh.vertices[:, 0] - 3.0, volume_mesh.vertices[:, 1] - 2.5)
    on_pillar = np.abs(radial - 0.15) < 0.06
    assert on_pillar.sum() > 100
    assert np.median(np.abs(radial[on_pillar] - 0.15)) < 0.01
    # The volume travels in the checkpoint.
    assert np.array_equal(resumed.finish()[-1].vertices, volume_mesh.vertices)


def _normal_errors_within_2_sigma(frame, result, true_pose):
    """Share of a frame's segmented points (every 7th) whose displacement along their plane's normal by the pose's
    error, ``n . (T_est p - T_true p)``, lies within 2 sigma of the tracked covariance (``sqrt(J Sigma J^T)``,
    ``J = [p x n, n]``, what the points' UL3 is made of)."""
    labels = result.segmentation.labels
    rows, cols = np.nonzero(labels > 0)
    rows, cols = rows[::7], cols[::7]
    points = frame.rays[rows, cols].astype(np.float64) * result.range[rows, cols, None]
    keep = np.isfinite(points).all(axis=1)
    points, normals = points[keep], result.segmentation.planes[labels[rows, cols][keep], :3]
    estimate = result.T_world_sensor
    world, world_normals = points @ estimate[:3, :3].T + estimate[:3, 3], normals @ estimate[:3, :3].T
    error = np.einsum("ij,ij->i", world - (points @ true_pose[:3, :3].T + true_pose[:3, 3]), world_normals)
    jacobian = np.hstack([np.cross(world, world_normals), world_normals])
    sigma = np.sqrt(np.einsum("ij,jk,ik->i", jacobian, result.covariance, jacobian))
    return np.mean(np.abs(error) <= 2 * sigma)


def test_aligning_to_the_model_bounds_the_drift_of_a_long_run():
    """600 SR-3000 frames circling the arena from drifting odometry: with the planes' fit to the model every 10th
    frame, the pose error over the last 100 frames is well below the keyframe chain's alone, and the tracked
    covariance stays honest all along: +-2 sigma holds at least 90 % of the pose's errors along the surface normals
    in every third of the run."""
    import dataclasses

    from rangesurf.config import RegisterSettings

    true_poses = simulate.default_trajectory("arena", 600, frame_rate=25)
    odometry = simulate.noisy_odometry(true_poses, seed=5)
    frames = [dataclasses.replace(frame, pose=odometry[k])
              for k, (frame, _) in enumerate(simulate.iter_sequence("arena", "sr3000", 600, seed=5, trajectory=true_poses))]
    late, covered = {}, []
    for every in (0, 10):
        pipeline = Pipeline(PipelineConfig(register=RegisterSettings(align_to_model_every=every)))
        errors = []
        for frame, pose in zip(frames, true_poses):
            result = pipeline.process(frame)
            errors.append(np.linalg.norm(result.T_world_sensor[:3, 3] - pose[:3, 3]))
            if every and len(errors) > 1:
                covered.append(_normal_errors_within_2_sigma(frame, result, pose))
        late[every] = np.array(errors[500:])
    # Measured per third: 96.1, 100, 100 % (97.4, 99.1, 100 % with a new keyframe at 5 points of overlap lost, 91.0,
    # 83.5, 100 % at 15 and no new keyframe when a registration turned degenerate; 97.1, 100, 100 % while a
    # correction counted the frame's registration twice, ICP's variance scale at 20; 98.7, 99.9, 100 % with that
    # and the scale at 30; 98.7, 80.3, 100 % while a segment's fit residual stretched the reach it joined patches
    # by; on odometry seeds 6 and 7 the middle third held 67 % while the drift along unconstrained directions grew
    # once per keyframe).
    assert min(np.mean(third) for third in np.array_split(covered, 3)) >= 0.9
    # Measured: 10.8 (at most 20.4) against 19.0 mm (10.6 and 13.2 against 18.5 without a new keyframe when a
    # registration turns degenerate; 12.6 and 16.7 against 29.2 with a new keyframe at 5 points of overlap lost;
    # 11.0 and 16.0 against 29.5 while a correction counted the frame's registration twice; 10.6 and 14.9 against 29.3 with that and ICP's variance scale at 30).
    # Before: 17.0 while the alignments shrank the covariance as if the patches were independent of the pose; 15.6
    # while the drift along unconstrained directions grew once per keyframe (the covariance is the alignment's prior:
    # larger, it lets a correction pull more); 13.7 while a segment's fit residual stretched the reach it joined
    # patches by (a floor grown into the ramp tilted the ramp's patch 2.4 degrees, which pulled the aligned poses
    # off). Odometry seeds 6 and 7: ratios 0.54, 0.55 (keyframes at 5 points of overlap lost). The chain alone got
    # better with keyframes kept longer: the ratio is now 0.57.
    assert late[10].mean() < 0.65 * late[0].mean()
    assert late[10].mean() < 0.0125
    assert late[10].max() < 0.025


def resident_mb():
    with open("/proc/self/statm") as stream:
        return int(stream.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.skipif(_malloc_trim() is None or not os.path.exists("/proc/self/statm"),
                    reason="needs glibc's malloc_trim and Linux /proc")
def test_freed_heap_memory_goes_back_to_the_system():
    """200 MB of 2 KB blocks, freed among a few that live on, stay resident until the pipeline's release."""
    blocks, live = [], []
    for index in range(100_000):
        blocks.append(bytearray(2048))
        if index % 1000 == 0:
            live.append(bytearray(2048))  # as a long run's objects sit between its temporaries
    held = resident_mb()
    del blocks
    assert resident_mb() > held - 50  # freed, but the allocator keeps the pages
    _release_freed_memory()
    assert resident_mb() < held - 100
    assert len(live) == 100
