"""Denoising metrics: RMSE by hand, edge scores of trivial and perfect denoisers, simulated frames."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

import rangesurf as rs
from rangesurf.denoise import anisotropic_diffusion
from rangesurf.denoise.metrics import DenoiseScores, range_rmse, score_denoising
from rangesurf.edges import detect_edges, edge_scores, true_depth_edges
from rangesurf.simulate import SimulationNoise

RANGE_NOISE_ONLY = SimulationNoise(mixed_pixels=False, salt_and_pepper=0.0)


def _box(shape=(60, 80)) -> np.ndarray:
    depth = np.full(shape, 3.0)
    depth[shape[0] // 4 : 3 * shape[0] // 4, shape[1] // 4 : 3 * shape[1] // 4] = 2.0
    return depth


@pytest.fixture(scope="module", params=["sr3000", "kinect"])
def simulated(request):
    frames, truths = rs.simulate.simulate_sequence("arena", request.param, 2, seed=5, noise=RANGE_NOISE_ONLY)
    return frames, truths


# --------------------------------------------------------------------------
# range_rmse.
# --------------------------------------------------------------------------


def test_rmse_of_hand_made_images():
    truth = np.zeros((2, 3))
    image = np.array([[3.0, 0.0, 0.0], [0.0, -4.0, 0.0]])
    assert range_rmse(image, truth) == pytest.approx(math.sqrt(25 / 6))
    assert range_rmse(image, image) == 0.0
    # A constant offset is the RMSE, whatever the dtype.
    assert range_rmse(np.full((4, 4), 2.5, np.float32), np.full((4, 4), 2.0)) == pytest.approx(0.5)
    assert range_rmse(np.full((4, 4), 3, np.int32), np.ones((4, 4), np.int64)) == pytest.approx(2.0)


def test_rmse_skips_invalid_pixels_and_honours_the_mask():
    truth = np.array([[1.0, 2.0, np.nan], [4.0, 5.0, 6.0]])
    image = np.array([[2.0, 2.0, 9.0], [np.nan, 5.0, 8.0]])  # errors 1, 0, -, -, 0, 2
    assert range_rmse(image, truth) == pytest.approx(math.sqrt(5 / 4))
    mask = np.array([[True, False, True], [True, True, False]])
    assert range_rmse(image, truth, mask=mask) == pytest.approx(math.sqrt(1 / 2))


def test_rmse_of_nothing_is_nan():
    assert math.isnan(range_rmse(np.full((3, 3), np.nan), np.ones((3, 3))))
    assert math.isnan(range_rmse(np.ones((0, 4)), np.ones((0, 4))))
    assert math.isnan(range_rmse(np.ones((3, 3)), np.ones((3, 3)), mask=np.zeros((3, 3), bool)))


# --------------------------------------------------------------------------
# score_denoising on hand-made images.
# --------------------------------------------------------------------------


def test_identity_denoiser_changes_nothing():
    truth = _box()
    raw = truth + np.random.default_rng(0).normal(0.0, 0.03, truth.shape)
    scores = score_denoising(raw, raw.copy(), truth)
    assert isinstance(scores, DenoiseScores)
    assert scores.rmse_ratio == 1.0
    assert scores.rmse_raw == scores.rmse_denoised == pytest.approx(range_rmse(raw, truth))
    assert scores.edge_f1_raw == scores.edge_f1_denoised
    assert scores.edge_precision_raw == scores.edge_precision_denoised
    assert scores.edge_recall_raw == scores.edge_recall_denoised
    assert scores.edge_changed_fraction == 0.0


@pytest.mark.parametrize("edge_method", ["canny", "sobel"])
def test_perfect_denoiser_has_zero_error_and_the_best_edges(edge_method):
    truth = _box()
    raw = truth + np.random.default_rng(1).normal(0.0, 0.3, truth.shape)
    scores = score_denoising(raw, truth, truth, edge_method=edge_method)
    assert scores.rmse_denoised == 0.0
    assert scores.rmse_ratio == 0.0
    assert scores.rmse_raw == pytest.approx(0.3, rel=0.1)
    assert scores.edge_f1_denoised >= 0.95
    assert scores.edge_f1_denoised > scores.edge_f1_raw
    assert scores.edge_method == edge_method
    # The scores are those of rangesurf.edges, not a re-implementation.
    expected = edge_scores(detect_edges(truth, method=edge_method), true_depth_edges(truth), tolerance=1.0)
    assert scores.edge_f1_denoised == expected.f1
    assert scores.edge_changed_fraction > 0


def test_rmse_counts_only_pixels_valid_in_all_three_images():
    truth = _box()
    raw = truth + 0.1
    denoised = truth.copy()
    raw[0, :10] = np.nan  # invalid in raw: not counted for either image
    denoised[1, :10] = np.nan
    denoised[2, 0] = 100.0  # counted
    scores = score_denoising(raw, denoised, truth)
    assert scores.rmse_raw == pytest.approx(0.1)
    assert scores.rmse_denoised == pytest.approx(math.sqrt(97.0**2 / (truth.size - 20)))


def test_creases_are_left_out_of_edge_scores():
    # A wall and a floor meeting without a depth jump (a crease), and a box in front.
    truth = _box()
    surface_id = np.ones(truth.shape, np.int32)
    surface_id[:, 40:] = 2
    surface_id[truth == 2.0] = 3
    # A "denoiser" that turns the crease into a step that detectors find.
    denoised = truth.copy()
    denoised[:, 40:] += np.where(truth[:, 40:] == 3.0, 1.0, 0.0)
    options = dict(surface_id=surface_id, edge_method="sobel")
    assert not true_depth_edges(truth, surface_id=surface_id)[:10].any()  # the crease is no depth edge
    with_band = score_denoising(truth, denoised, truth, **options)
    without_band = score_denoising(truth, denoised, truth, crease_band=0, **options)
    assert with_band.edge_precision_denoised == 1.0
    assert without_band.edge_precision_denoised < 0.9
    assert with_band.edge_recall_denoised == without_band.edge_recall_denoised == 1.0


def test_mask_restricts_rmse_and_edges():
    truth = _box()
    raw = truth + 0.2
    raw[:, :40] = truth[:, :40]
    mask = np.zeros(truth.shape, bool)
    mask[:, :40] = True
    scores = score_denoising(raw, truth, truth, mask=mask)
    assert scores.rmse_raw == 0.0
    assert math.isnan(scores.rmse_ratio)


# --------------------------------------------------------------------------
# Simulated frames.
# --------------------------------------------------------------------------


def test_diffusion_halves_the_error_of_simulated_frames(simulated):
    frames, truths = simulated
    for frame, truth in zip(frames, truths):
        sigma = frame.sensor.range_sigma(frame.range, frame.intensity)
        denoised = anisotropic_diffusion(frame.range, range_sigma=sigma)
        canny = score_denoising(frame.range, denoised, truth.range, surface_id=truth.surface_id)
        assert canny.rmse_ratio < 0.6
        assert canny.rmse_raw == pytest.approx(range_rmse(frame.range, truth.range), rel=1e-6)
        # Canny with automatic thresholds marks much noise on raw frames
        # (precision 0.05-0.15); diffusion removes a good part of it.
        assert canny.edge_precision_denoised > 1.5 * canny.edge_precision_raw
        assert canny.edge_recall_denoised >= canny.edge_recall_raw - 0.03
        # Sobel finds the depth edges well on both (measured F1 0.80-0.97).
        sobel = score_denoising(frame.range, denoised, truth.range, surface_id=truth.surface_id, edge_method="sobel")
        assert sobel.rmse_ratio == canny.rmse_ratio
        assert sobel.edge_f1_denoised >= 0.85
        assert sobel.edge_f1_denoised >= sobel.edge_f1_raw - 0.05


def test_truth_as_denoised_scores_best_on_simulated_frames(simulated):
    frames, truths = simulated
    frame, truth = frames[0], truths[0]
    perfect = score_denoising(frame.range, truth.range, truth.range, surface_id=truth.surface_id)
    smoothed = score_denoising(
        frame.range, anisotropic_diffusion(frame.range), truth.range, surface_id=truth.surface_id
    )
    assert perfect.rmse_denoised == 0.0
    assert perfect.edge_f1_denoised >= smoothed.edge_f1_denoised
    assert perfect.edge_f1_denoised >= perfect.edge_f1_raw


# --------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------


def test_shape_mismatch_names_both_shapes():
    with pytest.raises(ValueError, match=r"true range image must have the shape of the range image, got \(3, 4\) and \(4, 4\)"):
        range_rmse(np.ones((4, 4)), np.ones((3, 4)))
    with pytest.raises(ValueError, match=r"denoised range image .* got \(4, 5\) and \(4, 4\)"):
        score_denoising(np.ones((4, 4)), np.ones((4, 5)), np.ones((4, 4)))
    with pytest.raises(ValueError, match=r"surface_id .* got \(2, 2\) and \(4, 4\)"):
        score_denoising(np.ones((4, 4)), np.ones((4, 4)), np.ones((4, 4)), surface_id=np.ones((2, 2), int))
    with pytest.raises(ValueError, match=r"mask .* got \(4, 3\) and \(4, 4\)"):
        range_rmse(np.ones((4, 4)), np.ones((4, 4)), mask=np.ones((4, 3), bool))


@pytest.mark.parametrize("shape", [(144, 176, 3), (5,), ()])
def test_non_2d_input_names_the_shape(shape):
    good = np.ones((144, 176))
    bad = np.ones(shape)
    shape_text = re.escape(str(shape))
    with pytest.raises(ValueError, match=rf"range image must be 2-D \(H, W\), got shape {shape_text}"):
        range_rmse(bad, good)
    with pytest.raises(ValueError, match=rf"true range image must be 2-D \(H, W\), got shape {shape_text}"):
        score_denoising(good, good, bad)


def test_other_bad_input():
    good = np.ones((4, 4))
    with pytest.raises(ValueError, match="mask must be a bool array"):
        range_rmse(good, good, mask=np.ones((4, 4)))
    with pytest.raises(ValueError, match="must be a real numeric array"):
        range_rmse(good.astype(bool), good)
    with pytest.raises(ValueError, match="denoised range image contains Inf"):
        score_denoising(good, np.full((4, 4), np.inf), good)
    with pytest.raises(ValueError, match="crease_band must be an integer >= 0"):
        score_denoising(good, good, good, crease_band=-1)
    with pytest.raises(ValueError, match="unknown|method"):
        score_denoising(good, good, good, edge_method="laplace")


def test_all_invalid_and_tiny_images():
    nothing = np.full((6, 7), np.nan)
    scores = score_denoising(nothing, nothing, nothing)
    assert math.isnan(scores.rmse_raw) and math.isnan(scores.rmse_denoised) and math.isnan(scores.rmse_ratio)
    assert scores.edge_f1_raw == scores.edge_f1_denoised == 1.0  # no edges to find, none found
    tiny = score_denoising(np.array([[2.0]]), np.array([[2.5]]), np.array([[2.25]]))
    assert tiny.rmse_raw == tiny.rmse_denoised == pytest.approx(0.25)
    assert tiny.rmse_ratio == pytest.approx(1.0)
