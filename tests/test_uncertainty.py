"""The uncertainty levels against ground truth: calibrated bands on a simulated sequence."""

import dataclasses

import numpy as np
import pytest

from rangesurf import simulate
from rangesurf.config import PipelineConfig, RegisterSettings
from rangesurf.frame import get_sensor
from rangesurf.mesh import Surface
from rangesurf.pipeline import Pipeline
from rangesurf.uncertainty import coverage, distance_to_planes


def test_coverage_counts_vertices_inside_the_band():
    vertices = np.array([[0.0, 0, 2.00], [1, 0, 2.015], [0, 1, 2.03], [1, 1, 1.95]])
    surface = Surface(vertices, [[0, 1, 2], [1, 3, 2]], np.tile([0, 0, -1.0], (4, 1)), np.full((4, 2), -1),
                      uncertainty={"UL1": np.full(4, 0.01), "UL3": np.array([0.0, 0.0, 0.02, 0.0])})
    shares = coverage([surface], np.array([[0.0, 0, 1, -2.0]]), k=2.0)
    assert shares["UL1"] == 0.5                     # errors 0, 15, 30, 50 mm: within 2 x 10 mm the first two
    assert shares["combined"] == 0.75               # UL3 widens the third vertex's band to 2 x 22 mm
    assert shares["matched"] == 4 and shares["unmatched"] == 0
    assert np.isinf(distance_to_planes(vertices, np.tile([1.0, 0, 0], (4, 1)), np.array([[0.0, 0, 1, -2.0]]))).all()


def _arena_run(exact: bool, n_frames: int = 40):
    """SR-3000 arena from the true poses (trusted) or from drifting odometry: (pipeline, frame results, true poses)."""
    true_poses = simulate.default_trajectory("arena", n_frames, frame_rate=get_sensor("sr3000").frame_rate)
    odometry = true_poses if exact else simulate.noisy_odometry(true_poses, seed=5)
    config = PipelineConfig(register=RegisterSettings(odometry_sigma_rotation=1e-7, odometry_sigma_translation=1e-7)) if exact else None
    pipeline = Pipeline(config)
    results = [pipeline.process(dataclasses.replace(frame, pose=odometry[k]))
               for k, (frame, _) in enumerate(simulate.iter_sequence("arena", "sr3000", n_frames, seed=5, trajectory=true_poses))]
    return pipeline, results, true_poses


def test_the_sensor_level_holds_the_error_of_a_model_made_from_true_poses():
    """With exact poses only the sensor errs: +-2 UL1 holds 90-98 % of the vertices' errors (UL2 = 0 ones)."""
    pipeline, _, _ = _arena_run(exact=True)
    surfaces = pipeline.finish()
    planes = simulate.get_scene("arena").planes
    error = distance_to_planes(np.vstack([s.vertices for s in surfaces]), np.vstack([s.normals for s in surfaces]), planes)
    ul1, ul2 = (np.concatenate([s.uncertainty[level] for s in surfaces]) for level in ("UL1", "UL2"))
    scored = np.isfinite(error) & (error <= 0.2) & (ul2 == 0)
    assert scored.sum() > 10_000
    assert 0.9 <= np.mean(error[scored] <= 2 * ul1[scored]) <= 0.98


def test_the_registration_level_holds_the_pose_errors_and_all_levels_the_model_error():
    """Drifting odometry: +-2 sigma of the tracked covariance holds most normal-direction pose errors, and the
    combined band about 95 % of the final model's error."""
    pipeline, results, true_poses = _arena_run(exact=False)
    inside = []
    for result, truth in zip(results[1:], true_poses[1:]):
        rows, cols = np.nonzero(result.segmentation.labels > 0)
        rays = get_sensor("sr3000").rays()[rows, cols].astype(np.float64)
        points, normals = rays * result.range[rows, cols, None], result.segmentation.planes[result.segmentation.labels[rows, cols], :3]
        estimate = result.T_world_sensor
        world, world_normals = points @ estimate[:3, :3].T + estimate[:3, 3], normals @ estimate[:3, :3].T
        error = np.einsum("ij,ij->i", world - (points @ truth[:3, :3].T + truth[:3, 3]), world_normals)
        jacobian = np.hstack([np.cross(world, world_normals), world_normals])
        sigma = np.sqrt(np.einsum("ij,jk,ik->i", jacobian, result.covariance, jacobian))
        inside.append(np.abs(error) <= 2 * sigma)
    assert 0.85 <= np.mean(np.concatenate(inside)) <= 0.99
    planes = simulate.get_scene("arena").planes
    shares = coverage(pipeline.finish(), planes[np.isfinite(planes).all(axis=1)])
    assert shares["matched"] > 10_000
    assert 0.9 <= shares["combined"] <= 0.98
    assert shares["combined"] >= max(shares[level] for level in ("UL1", "UL2", "UL3"))


@pytest.mark.parametrize("k, expected", [(1.0, 0.5), (3.0, 1.0)])
def test_coverage_grows_with_the_band(k, expected):
    vertices = np.array([[0.0, 0, 2.005], [1, 0, 2.015], [0, 1, 2.025], [1, 1, 2.0]])
    surface = Surface(vertices, [[0, 1, 2]], np.tile([0, 0, -1.0], (4, 1)), np.full((4, 2), -1),
                      uncertainty={"UL1": np.full(4, 0.01)})
    assert coverage([surface], np.array([[0.0, 0, 1, -2.0]]), k=k)["UL1"] == pytest.approx(expected)
