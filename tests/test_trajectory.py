"""ATE / RPE against trajectories with known errors, and the TUM file format."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rangesurf.io import FormatError
from rangesurf.io.tum import read_tum_trajectory, write_tum_trajectory
from rangesurf.trajectory import absolute_trajectory_error, align_trajectories, associate, relative_pose_error


def circle(n=100, radius=2.0):
    """Poses driving a circle at 0.5 m height, heading along the path."""
    angle = np.linspace(0, 1.5 * np.pi, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", (angle + np.pi / 2)[:, None]).as_matrix()
    poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = radius * np.cos(angle), radius * np.sin(angle), 0.5
    return poses


def rigid(rotation_vector, translation):
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rotation_vector).as_matrix()
    transform[:3, 3] = translation
    return transform


def test_alignment_recovers_a_rigid_transform_and_ate_is_zero():
    reference = circle()
    moved = rigid([0.2, -0.1, 0.7], [3.0, -1.0, 0.4])
    estimate = moved @ reference
    alignment = align_trajectories(estimate, reference)
    assert np.allclose(alignment, np.linalg.inv(moved), atol=1e-9)
    ate = absolute_trajectory_error(estimate, reference)
    assert ate.translation.max < 1e-9 and ate.rotation.max < 1e-5


def test_ate_of_known_position_noise():
    rng = np.random.default_rng(0)
    reference = circle(2000)
    estimate = reference.copy()
    sigma = 0.01
    estimate[:, :3, 3] += rng.normal(0, sigma, (2000, 3))
    ate = absolute_trajectory_error(estimate, reference)
    # RMS of a 3-D isotropic Gaussian offset: sigma * sqrt(3).
    assert ate.translation.rmse == pytest.approx(sigma * np.sqrt(3), rel=0.05)
    assert ate.translation.count == 2000


def test_rpe_of_a_constant_per_frame_bias():
    """Every step 2 % too long and turned 0.1 deg too far: RPE over one frame is exactly that."""
    reference = circle(50)
    steps = np.linalg.inv(reference[:-1]) @ reference[1:]
    bias = rigid([0, 0, np.radians(0.1)], [0, 0, 0])
    estimate = [reference[0]]
    for step in steps:
        biased = step.copy()
        biased[:3, 3] *= 1.02
        estimate.append(estimate[-1] @ biased @ bias)
    estimate = np.asarray(estimate)
    rpe = relative_pose_error(estimate, reference)
    step_length = np.linalg.norm(steps[0][:3, 3])
    assert rpe.rotation.median == pytest.approx(0.1, abs=1e-6)
    assert rpe.translation.median == pytest.approx(0.02 * step_length, rel=1e-3)
    # Over 10 frames the drift adds up (translation at least ten steps' worth of bias).
    assert relative_pose_error(estimate, reference, delta=10).translation.median > 9 * 0.02 * step_length


def test_bad_inputs_are_refused():
    reference = circle(5)
    with pytest.raises(ValueError, match="associate"):
        absolute_trajectory_error(reference[:4], reference)
    with pytest.raises(ValueError, match="delta"):
        relative_pose_error(reference, reference, delta=0)
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        absolute_trajectory_error(np.zeros((5, 3, 4)), reference)


def test_associate_pairs_closest_stamps_once():
    # 0.036 is within reach of 0.033 too, but 0.032 is closer and takes it; 0.0 and 0.1 have no partner.
    first, second = associate([0.0, 0.033, 0.066, 0.1], [0.036, 0.032, 0.07])
    assert (first.tolist(), second.tolist()) == ([1, 2], [1, 2])


def test_tum_round_trip(tmp_path):
    poses = circle(20)
    stamps = np.arange(20) / 30.0
    path = tmp_path / "trajectory.txt"
    write_tum_trajectory(path, stamps, poses)
    read_stamps, read_poses = read_tum_trajectory(path)
    assert np.allclose(read_stamps, stamps, atol=1e-9)
    assert np.allclose(read_poses, poses, atol=1e-8)
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


@pytest.mark.parametrize(
    ("line", "message"),
    [("0.0 1 2 3 0 0 0", "expected 8 numbers"), ("0.0 1 2 x 0 0 0 1", "not a number"),
     ("0.0 1 2 3 0 0 0 2", "unit length"), ("0.0 1 2 nan 0 0 0 1", "non-finite")],
)
def test_malformed_tum_lines_name_file_and_line(tmp_path, line, message):
    path = tmp_path / "bad.txt"
    path.write_text("# header\n0.0 0 0 0 0 0 0 1\n" + line + "\n")
    with pytest.raises(FormatError, match=message) as error:
        read_tum_trajectory(path)
    assert "bad.txt, line 3" in str(error.value)
