"""Distance-layered denoising: ground-truth RMSE, seams, NaN handling, bad input."""

from __future__ import annotations

import numpy as np
import pytest

import rangesurf as rs
from rangesurf.denoise.diffusion import anisotropic_diffusion
from rangesurf.denoise.layered import layer_weights, layered_denoise
from rangesurf.denoise.outliers import remove_cutoff
from rangesurf.simulate import SimulationNoise, look_at, simulate_sequence

SR3000 = rs.get_sensor("sr3000")
RANGE_NOISE_ONLY = SimulationNoise(mixed_pixels=False, salt_and_pepper=0.0)
OPTIONS = {"iterations": 10}


def _rmse(image, truth, where):
    return float(np.sqrt(np.mean((image[where] - truth[where]) ** 2)))


def _compare(frame, truth):
    """RMSE (raw, single frame-wide kappa, layered) against the true range."""
    image = remove_cutoff(frame.range, max_range=SR3000.max_range)
    sigma = SR3000.range_sigma(image, frame.intensity)
    sigma = np.where(np.isfinite(sigma), sigma, 1.0)
    valid = np.isfinite(image) & np.isfinite(truth.range)
    frame_sigma = float(np.median(sigma[np.isfinite(image)]))
    single = anisotropic_diffusion(image, range_sigma=frame_sigma, **OPTIONS)
    layered = layered_denoise(image, layers=3, range_sigma=sigma, denoiser_options=OPTIONS)
    np.testing.assert_array_equal(np.isnan(layered), np.isnan(image))
    return _rmse(image, truth.range, valid), _rmse(single, truth.range, valid), _rmse(layered, truth.range, valid)


def _ramp(noise, seed=0):
    """A plane slanted away from the sensor: range 1 m to 6 m down the rows, relative noise."""
    rng = np.random.default_rng(seed)
    truth = np.linspace(1.0, 6.0, 144)[:, None] * np.ones((1, 176))
    noisy = (truth * (1 + noise * rng.standard_normal(truth.shape))).astype(np.float32)
    return truth, noisy, np.maximum(0.01 * noisy, 1e-3)


# --------------------------------------------------------------------------
# Ground truth.
# --------------------------------------------------------------------------


def test_layered_wins_over_a_wide_range_span():
    # Looking along the corridor from 0.8 m to the 7.5 m cut-off: the noise
    # varies ninefold across the frame, so one frame-wide kappa is wrong
    # nearly everywhere.
    pose = look_at((1.0, 0.5, 1.2), (8.0, -1.0, 0.3))
    frames, truths = simulate_sequence("corridor", "sr3000", 1, seed=3, noise=RANGE_NOISE_ONLY, trajectory=pose[None])
    raw, single, layered = _compare(frames[0], truths[0])
    # Measured: raw 54 mm, single 44 mm, layered 33 mm.
    assert layered < 0.85 * single, (raw, single, layered)
    assert layered < 0.7 * raw


def test_layered_matches_single_over_a_narrow_range_span():
    # The arena spans about 2-5 m: layers barely differ in noise, and layered
    # denoising is as good as (not better than) one frame-wide kappa.
    frames, truths = simulate_sequence("arena", "sr3000", 3, seed=3, noise=RANGE_NOISE_ONLY)
    for frame, truth in zip(frames, truths):
        raw, single, layered = _compare(frame, truth)
        # Measured: raw 38 mm, single 18.2-18.8 mm, layered 18.3-18.9 mm.
        assert layered < 1.03 * single, (raw, single, layered)
        assert layered < 0.55 * raw


def test_no_seams_on_a_slanted_plane():
    truth, clean, sigma = _ramp(0.0)
    interior = slice(8, -8)  # diffusion bends a ramp at the image border, with or without layers

    def worst_row_error(image):
        return float(np.abs((image - truth).mean(axis=1)[interior]).max())

    blended = layered_denoise(clean, layers=3, overlap=0.1, range_sigma=sigma, denoiser_options={"iterations": 20})
    hard = layered_denoise(clean, layers=3, overlap=0.0, range_sigma=sigma, denoiser_options={"iterations": 20})
    # Measured: blended 2.5 mm, hard cuts 40 mm (each layer's cut edge insulates and bends).
    assert worst_row_error(blended) < 0.005
    assert worst_row_error(hard) > 3 * worst_row_error(blended)

    truth, noisy, sigma = _ramp(0.01, seed=1)
    smooth = layered_denoise(noisy, layers=3, overlap=0.1, range_sigma=sigma, denoiser_options={"iterations": 20})
    single = anisotropic_diffusion(noisy, range_sigma=sigma, iterations=20)
    # Measured: 3.3 mm for both (noise 10-60 mm).
    assert worst_row_error(smooth) < 2 * worst_row_error(single) + 0.001
    assert _rmse(smooth, truth, np.s_[interior]) < 0.3 * _rmse(noisy, truth, np.s_[interior])


# --------------------------------------------------------------------------
# Weights, NaN, options.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("overlap", [0.0, 0.05, 0.3, 0.9])
def test_weights_are_a_partition_of_unity(overlap):
    ranges = np.linspace(0.5, 8.0, 500)[None]
    weights = layer_weights(ranges, [1.0, 1.2, 4.0], overlap=overlap)
    assert weights.shape == (4, 1, 500)
    assert (weights >= 0).all()
    np.testing.assert_allclose(weights.sum(axis=0), 1.0)
    assert (layer_weights([[np.nan]], [1.0]) == 0).all()


def test_nan_does_not_spread_and_all_nan():
    truth, noisy, sigma = _ramp(0.01)
    noisy[::7, ::5] = np.nan
    noisy[60:70, :40] = np.nan
    out = layered_denoise(noisy, layers=4, denoiser_options=OPTIONS)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(noisy))
    assert out.dtype == np.float32
    nan = np.full((6, 7), np.nan, np.float32)
    assert np.isnan(layered_denoise(nan)).all()
    assert layered_denoise(np.array([[2.0]]))[0, 0] == np.float32(2.0)


def test_one_layer_is_the_denoiser_with_the_median_noise():
    _, noisy, sigma = _ramp(0.01)
    out = layered_denoise(noisy, layers=1, range_sigma=sigma, denoiser_options=OPTIONS)
    expected = anisotropic_diffusion(noisy, range_sigma=float(np.median(sigma)), **OPTIONS)
    np.testing.assert_array_equal(out, expected)


def test_explicit_boundaries_and_custom_denoiser():
    _, noisy, _ = _ramp(0.01)
    seen = []

    def mean_of_layer(image, *, range_sigma):
        seen.append(range_sigma)
        return np.where(np.isnan(image), np.nan, np.nanmean(image))

    out = layered_denoise(noisy, layers=[3.0], overlap=0.0, range_sigma=0.02, denoiser=mean_of_layer)
    assert seen == [0.02, 0.02]
    near = noisy < 3.0
    np.testing.assert_allclose(out[near], noisy[near].mean(), rtol=1e-5)
    np.testing.assert_allclose(out[~near], noisy[~near].mean(), rtol=1e-5)


def test_many_equal_ranges_merge_layers():
    image = np.full((20, 20), 7.5, np.float32)
    image[:5] = np.linspace(1, 7, 20, dtype=np.float32)
    out = layered_denoise(image, layers=4, denoiser_options=OPTIONS)
    np.testing.assert_allclose(out[5:], 7.5)


@pytest.mark.parametrize(
    "options",
    [
        {"layers": 0},
        {"layers": True},
        {"layers": [3.0, 2.0]},
        {"layers": [-1.0]},
        {"layers": [np.inf]},
        {"overlap": 1.0},
        {"overlap": -0.1},
        {"range_sigma": 0.0},
        {"range_sigma": np.ones((3, 3))},
        {"denoiser_options": {"range_sigma": 0.01}},
        {"denoiser": lambda image, **kw: image[:1]},
    ],
)
def test_bad_options(options):
    with pytest.raises(ValueError):
        layered_denoise(np.full((4, 4), 2.0, np.float32), **options)


@pytest.mark.parametrize("bad", [np.ones(5), np.ones((3, 3, 3)), np.array([[1.0, np.inf]])])
def test_bad_images(bad):
    with pytest.raises(ValueError):
        layered_denoise(bad)
