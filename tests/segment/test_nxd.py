"""NxD transform (thesis Eq. 2.1) and clustering against analytic scenes and simulator truth."""

import numpy as np
import pytest

from rangesurf import simulate
from rangesurf.segment import evaluate_segmentation, nxd_transform, segment_frame, segment_nxd, truth_segmentation


def wall_and_box():
    rows, cols = np.mgrid[0:60, 0:80]
    box = (rows > 20) & (rows < 40) & (cols > 20) & (cols < 50)
    rays = np.dstack([(cols - 40) / 100, (rows - 30) / 100, np.ones(rows.shape)])
    points = rays * np.where(box, 2.0, 3.0)[..., None]
    normals = np.broadcast_to([0.0, 0.0, -1.0], points.shape).copy()
    return points, normals, box


def test_planes_map_to_single_points_with_the_plane_distance():
    points, normals, box = wall_and_box()
    nxd = nxd_transform(points, normals)
    assert np.allclose(nxd[box], [0, 0, -2.0]) and np.allclose(nxd[~box], [0, 0, -3.0])
    # Eq. 2.1 with the range: a plane becomes a line along its normal, from its nearest to farthest point.
    along = nxd_transform(points, normals, distance="range")
    assert np.allclose(along[..., :2], 0) and along[~box, 2].min() < -3.0


def test_clusters_are_the_surfaces_and_coplanar_parts_stay_apart():
    points, normals, box = wall_and_box()
    result = segment_nxd(points, normals, bandwidth=0.2)
    assert result.n_segments == 2
    assert (result.labels[box] == 2).all() and (result.labels[~box] == 1).all()
    # Two boxes at the same distance: one NxD cluster, two segments in the image.
    second = np.zeros(box.shape, bool)
    second[45:55, 60:75] = True
    points[second] = points[second] / 3.0 * 2.0
    split = segment_nxd(points, normals, bandwidth=0.2)
    assert split.n_segments == 3
    merged = segment_nxd(points, normals, bandwidth=0.2, split_disconnected=False)
    assert merged.n_segments == 2


def test_small_clusters_are_noise():
    points, normals, box = wall_and_box()
    result = segment_nxd(points, normals, bandwidth=0.2, min_size=1000)
    assert result.n_segments == 1 and (result.labels[box] == 0).all()


def test_simulated_frame_finds_the_large_planes():
    frames, truths = simulate.simulate_sequence("arena", "sr3000", 1, seed=4)
    result = segment_frame(frames[0], segmenter="nxd")
    scores = evaluate_segmentation(truth_segmentation(truths[0], frames[0].rays).labels, result.segmentation.labels,
                                   min_region_size=2000)
    assert scores.n_truth >= 2 and scores.correct >= scores.n_truth - 1


@pytest.mark.parametrize("options, message", [({"bandwidth": 0}, "bandwidth"), ({"min_size": 0}, "min_size"),
                                              ({"distance": "depth"}, "distance")])
def test_bad_options_are_refused(options, message):
    points, normals, _ = wall_and_box()
    with pytest.raises(ValueError, match=message):
        segment_nxd(points, normals, **options)


def test_no_valid_points_gives_no_segments():
    empty = np.full((10, 12, 3), np.nan)
    assert segment_nxd(empty, empty).n_segments == 0


def test_segment_frame_refuses_an_unknown_segmenter():
    frames, _ = simulate.simulate_sequence("arena", "sr3000", 1)
    with pytest.raises(ValueError, match="segmenter"):
        segment_frame(frames[0], segmenter="ransac")
