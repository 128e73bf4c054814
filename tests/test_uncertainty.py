"""The uncertainty levels against ground truth: calibrated bands on a simulated sequence."""

import dataclasses

import numpy as np
import pytest

from rangesurf import simulate
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


def test_the_levels_are_calibrated_on_a_simulated_sequence():
    """SR-3000 arena, 40 frames from drifting odometry: the combined +-2 sigma band holds about 95 % of the true surface."""
    true_poses = simulate.default_trajectory("arena", 40, frame_rate=get_sensor("sr3000").frame_rate)
    odometry = simulate.noisy_odometry(true_poses, seed=5)
    pipeline = Pipeline()
    for k, (frame, _) in enumerate(simulate.iter_sequence("arena", "sr3000", 40, seed=5, trajectory=true_poses)):
        pipeline.process(dataclasses.replace(frame, pose=odometry[k]))
    planes = simulate.get_scene("arena").planes
    shares = coverage(pipeline.finish(), planes[np.isfinite(planes).all(axis=1)])
    assert shares["matched"] > 10_000
    assert 0.9 <= shares["combined"] <= 0.995
    assert shares["UL1"] >= 0.8
    assert shares["combined"] >= max(shares[level] for level in ("UL1", "UL2", "UL3"))


@pytest.mark.parametrize("k, expected", [(1.0, 0.5), (3.0, 1.0)])
def test_coverage_grows_with_the_band(k, expected):
    vertices = np.array([[0.0, 0, 2.005], [1, 0, 2.015], [0, 1, 2.025], [1, 1, 2.0]])
    surface = Surface(vertices, [[0, 1, 2]], np.tile([0, 0, -1.0], (4, 1)), np.full((4, 2), -1),
                      uncertainty={"UL1": np.full(4, 0.01)})
    assert coverage([surface], np.array([[0.0, 0, 1, -2.0]]), k=k)["UL1"] == pytest.approx(expected)
