"""Anisotropic diffusion: kernel vs reference and medpy, NaN insulation, ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _synthetic import RANGE_NOISE_ONLY, range_image
from scipy import ndimage

import rangesurf as rs
from rangesurf.denoise import (
    CONDUCTIONS,
    METRIC_KAPPA_MULTIPLES,
    THESIS_PRESETS,
    DiffusionPreset,
    anisotropic_diffusion,
)
from rangesurf.denoise.diffusion import (
    _CONDUCTION_CODES,
    _diffuse,
    _diffuse_pairwise,
    _diffuse_reference,
    _pair_kappas_reference,
)
from rangesurf.denoise.metrics import resolved_jump_ratios

SHAPES = [(144, 176), (37, 53), (5, 17), (40, 1), (1, 40), (2, 2), (1, 1)]


def _assert_same_holes(result, image):
    assert result.dtype == np.float32
    assert result.shape == np.shape(image)
    np.testing.assert_array_equal(np.isnan(result), np.isnan(image))


# --------------------------------------------------------------------------
# The compiled kernels against the plain NumPy reference.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("conduction", CONDUCTIONS)
@pytest.mark.parametrize("shape", SHAPES)
def test_kernel_matches_reference_with_holes(conduction, shape):
    image = range_image(shape)
    ours = _diffuse(image, 0.0, 1.0, 0.05, 0.25, 20, _CONDUCTION_CODES[conduction])
    reference = _diffuse_reference(image, 0.05, 0.25, 20, conduction)
    _assert_same_holes(ours, image)
    np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-5, equal_nan=True)
    assert not np.array_equal(ours, image, equal_nan=True) or image.size < 4


@pytest.mark.parametrize("conduction", CONDUCTIONS)
@pytest.mark.parametrize("shape", SHAPES)
def test_pairwise_kernel_matches_reference_with_holes(conduction, shape):
    image = range_image(shape, seed=1)
    sigma = 0.005 + 0.004 * np.nan_to_num(image)  # ToF-like: grows with range
    kappas = _pair_kappas_reference(image, sigma, 2.0)
    ours = _diffuse_pairwise(image, *kappas, 0.25, 20, _CONDUCTION_CODES[conduction])
    reference = _diffuse_reference(image, kappas, 0.25, 20, conduction)
    _assert_same_holes(ours, image)
    np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-5, equal_nan=True)


def test_large_frames_match_the_reference():
    image = range_image((1200, 1600), seed=11)
    ours = anisotropic_diffusion(image, kappa=0.05, step=0.25, iterations=3)
    np.testing.assert_allclose(ours, _diffuse_reference(image, 0.05, 0.25, 3, "exponential"), atol=1e-5)


@pytest.mark.parametrize("conduction", CONDUCTIONS)
def test_range_sigma_sets_kappa_per_pair(conduction):
    """kappa of pair p, q = multiple * sqrt(2) * min(sigma_p, sigma_q); a number is one sigma for all."""
    image = range_image((50, 70), seed=10)
    sigma = 0.005 * np.where(np.isnan(image), np.nan, image) ** 2  # structured light: grows with range squared
    multiple = METRIC_KAPPA_MULTIPLES[conduction]
    result = anisotropic_diffusion(image, range_sigma=sigma, conduction=conduction, step=0.25, iterations=20)
    expected = _diffuse_reference(image, _pair_kappas_reference(image, sigma, multiple), 0.25, 20, conduction)
    _assert_same_holes(result, image)
    np.testing.assert_allclose(result, expected, rtol=0, atol=1e-5, equal_nan=True)
    np.testing.assert_array_equal(
        anisotropic_diffusion(image, range_sigma=0.01, conduction=conduction),
        anisotropic_diffusion(image, kappa=multiple * math.sqrt(2.0) * 0.01, conduction=conduction),
    )


@pytest.mark.parametrize("conduction", CONDUCTIONS)
def test_kernel_matches_reference_on_grey_levels(conduction):
    """Thesis mode's 0-255 normalisation: offset and gain, result back in metres."""
    image = range_image((60, 80), seed=2)
    low, high = float(np.nanmin(image)), float(np.nanmax(image))
    gain = 255.0 / (high - low)
    ours = _diffuse(image, low, gain, 20.0, 0.1, 10, _CONDUCTION_CODES[conduction])
    reference = _diffuse_reference(image, 20.0, 0.1, 10, conduction, offset=low, gain=gain)
    np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-5, equal_nan=True)
    np.testing.assert_allclose(anisotropic_diffusion(image, mode="thesis", conduction=conduction, kappa=20.0), ours)


# --------------------------------------------------------------------------
# The peer: medpy.filter.smoothing.anisotropic_diffusion (no NaN support).
# --------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(144, 176), (31, 47)])
@pytest.mark.parametrize("conduction", CONDUCTIONS)
def test_matches_medpy(conduction, shape):
    smoothing = pytest.importorskip("medpy.filter.smoothing", reason="medpy is the peer implementation (bench extra)")
    image = range_image(shape, holes=False)
    option = CONDUCTIONS.index(conduction) + 1
    # medpy's Tukey cut-off is sqrt(2) * kappa; ours is kappa (Black et al.).
    medpy_kappa = 0.05 / math.sqrt(2.0) if conduction == "tukey" else 0.05
    expected = smoothing.anisotropic_diffusion(image, niter=10, kappa=medpy_kappa, gamma=0.2, option=option)
    ours = anisotropic_diffusion(image, iterations=10, kappa=0.05, step=0.2, conduction=conduction)
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-5)


def test_thesis_mode_is_medpy_on_the_normalised_image():
    smoothing = pytest.importorskip("medpy.filter.smoothing", reason="medpy is the peer implementation (bench extra)")
    image = range_image((72, 88), holes=False)
    low, high = float(image.min()), float(image.max())
    grey = (image.astype(np.float64) - low) * 255.0 / (high - low)
    diffused = smoothing.anisotropic_diffusion(grey, niter=10, kappa=20, gamma=0.1, option=1)
    expected = diffused * (high - low) / 255.0 + low
    np.testing.assert_allclose(anisotropic_diffusion(image, mode="thesis"), expected, rtol=0, atol=1e-5)


# --------------------------------------------------------------------------
# Holes and borders.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("conduction", CONDUCTIONS)
def test_a_nan_wall_insulates(conduction):
    """What lies beyond a wall of NaN cannot change anything on this side."""
    image = range_image((50, 60), holes=False)
    image[:, 25:28] = np.nan
    image[10:15, 5:12] = np.nan
    changed = image.copy()
    changed[:, 28:] = np.random.default_rng(5).uniform(0.5, 7.0, changed[:, 28:].shape)
    sigma = np.full(image.shape, 0.01)
    # Local settings only: thesis mode's normalisation and the estimated
    # kappa are frame-wide by definition.
    for options in ({"kappa": 0.05}, {"range_sigma": sigma}):
        before = anisotropic_diffusion(image, conduction=conduction, step=0.25, iterations=30, **options)
        after = anisotropic_diffusion(changed, conduction=conduction, step=0.25, iterations=30, **options)
        np.testing.assert_array_equal(before[:, :25], after[:, :25])
        _assert_same_holes(before, image)
        assert np.all(np.isnan(before[10:15, 5:12])) and np.all(np.isnan(before[:, 25:28]))
        assert not np.array_equal(before[:, :25], image[:, :25], equal_nan=True)


@pytest.mark.parametrize("conduction", CONDUCTIONS)
def test_nans_of_either_sign_insulate(conduction):
    """NaN's sign bit is arbitrary (x86 makes -NaN of inf - inf); both kinds are holes."""
    image = range_image((20, 30), holes=False)
    negative_nan = np.array([0xFFC00000], np.uint32).view(np.float32)[0]
    image[5:8, 5:8] = negative_nan
    image[12, 20] = np.nan
    result = anisotropic_diffusion(image, kappa=0.05, step=0.25, iterations=20, conduction=conduction)
    _assert_same_holes(result, image)
    expected = _diffuse_reference(image, 0.05, 0.25, 20, conduction)
    np.testing.assert_allclose(result, expected, rtol=0, atol=1e-5, equal_nan=True)


def test_a_pixel_surrounded_by_holes_keeps_its_value():
    image = np.full((7, 7), 3.0, np.float32)
    image[2:5, 2:5] = np.nan
    image[3, 3] = 1.25
    image[0, 0] = 2.0
    result = anisotropic_diffusion(image, kappa=1.0, step=0.25, iterations=50)
    assert result[3, 3] == np.float32(1.25)
    _assert_same_holes(result, image)


@pytest.mark.parametrize("conduction", CONDUCTIONS)
@pytest.mark.parametrize("holes", [False, True])
def test_zero_flux_borders_and_holes_conserve_the_sum(conduction, holes):
    """Every flux leaves one pixel and enters another: the total is conserved."""
    image = range_image((45, 70), seed=3, holes=holes)
    result = anisotropic_diffusion(image, kappa=0.05, step=0.25, iterations=40, conduction=conduction)
    valid = ~np.isnan(image)
    assert math.isclose(result[valid].astype(np.float64).sum(), image[valid].astype(np.float64).sum(), rel_tol=2e-6)


# --------------------------------------------------------------------------
# Known answers.
# --------------------------------------------------------------------------


@pytest.mark.parametrize(("conduction", "conductance"), [("exponential", 1.0), ("rational", 1.0), ("tukey", 0.5)])
def test_large_kappa_is_the_linear_heat_equation(conduction, conductance):
    """With kappa >> every difference, g is constant: one explicit step of the 5-point Laplacian."""
    image = range_image((30, 41), seed=4, holes=False)
    result = anisotropic_diffusion(image, kappa=1e4, step=0.2, iterations=1, conduction=conduction)
    # Zero flux at the border: the Laplacian of an edge-replicated image.
    laplacian = ndimage.convolve(image.astype(np.float64), [[0, 1, 0], [1, -4, 1], [0, 1, 0]], mode="nearest")
    np.testing.assert_allclose(result, image + 0.2 * conductance * laplacian, rtol=0, atol=1e-5)


def test_two_pixels_follow_the_closed_form():
    """A 1x2 image: each step moves both pixels by step * g(d) * d toward each other."""
    left, right, kappa, step = 1.0, 1.3, 0.25, 0.25
    for _ in range(6):
        difference = right - left
        flux = step * difference / (1.0 + (difference / kappa) ** 2)
        left, right = left + flux, right - flux
    result = anisotropic_diffusion([[1.0, 1.3]], kappa=kappa, step=step, iterations=6, conduction="rational")
    np.testing.assert_allclose(result, [[left, right]], rtol=0, atol=1e-6)


@pytest.mark.parametrize("conduction", ["exponential", "tukey"])
def test_a_clean_step_is_a_fixed_point(conduction):
    """(The rational flux kappa**2 / d decays slowly: it leaks 1e-3 of the jump here.)"""
    image = np.where(np.arange(40) < 20, 2.0, 3.0).astype(np.float32) * np.ones((30, 1), np.float32)
    result = anisotropic_diffusion(image, kappa=0.02, step=0.25, iterations=100, conduction=conduction)
    np.testing.assert_allclose(result, image, rtol=0, atol=1e-6)


@pytest.mark.parametrize("conduction", CONDUCTIONS)
@pytest.mark.parametrize("noise_model", ["estimated", "given"])
def test_a_noisy_step_is_denoised_and_stays_sharp(conduction, noise_model):
    rng = np.random.default_rng(6)
    truth = np.where(np.arange(96) < 48, 2.0, 3.0) * np.ones((64, 1))
    noisy = (truth + rng.normal(0.0, 0.02, truth.shape)).astype(np.float32)
    sigma = 0.02 if noise_model == "given" else None
    result = anisotropic_diffusion(noisy, conduction=conduction, iterations=40, step=0.25, range_sigma=sigma)
    raw_error = np.sqrt(np.mean((noisy - truth) ** 2))
    error = np.sqrt(np.mean((result - truth) ** 2))
    assert error < 0.5 * raw_error
    jump = result[:, 48] - result[:, 47]
    assert np.all(jump > 0.9), jump.min()


@pytest.mark.parametrize("conduction", ["exponential", "rational"])
def test_a_jump_to_a_noisier_surface_stays_sharp(conduction):
    """Near and precise against far and noisy: the pair's kappa comes from the precise side.

    The jump (0.15 m) is about the pair kappa that the far side's noise alone
    would give (2.5 * 0.06 m), so with the noisier sigma setting the
    threshold it would leak; with the nearer side's it is 4 kappas.
    """
    rng = np.random.default_rng(8)
    far = np.arange(96) >= 48
    truth = np.where(far, 2.15, 2.0) * np.ones((64, 1))
    sigma = np.where(far, 0.06, 0.01) * np.ones((64, 1))
    noisy = (truth + rng.normal(0.0, 1.0, truth.shape) * sigma).astype(np.float32)
    result = anisotropic_diffusion(noisy, range_sigma=sigma, conduction=conduction)
    for side in (~far, far):
        raw_error = np.sqrt(np.mean((noisy - truth)[:, side] ** 2))
        assert np.sqrt(np.mean((result - truth)[:, side] ** 2)) < 0.7 * raw_error
    jump = np.median(result[:, 48] - result[:, 47])
    assert jump > 0.8 * 0.15, jump


def test_default_step_depends_on_the_mode():
    """Metric mode steps 0.18 by default, thesis mode the thesis's 0.1."""
    image = range_image((30, 40), seed=12)
    np.testing.assert_array_equal(anisotropic_diffusion(image), anisotropic_diffusion(image, step=0.18))
    np.testing.assert_array_equal(
        anisotropic_diffusion(image, mode="thesis"), anisotropic_diffusion(image, mode="thesis", step=0.1)
    )


# --------------------------------------------------------------------------
# Simulated time-of-flight frames with ground truth.
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sr3000_frames():
    frames, truth = rs.simulate.simulate_sequence("arena", "sr3000", 3, seed=3, noise=RANGE_NOISE_ONLY)
    return list(zip(frames, truth))


def _rmse(estimate, frame, truth):
    """Root mean square range error (metres) where there is a true range, a reading and an estimate."""
    scored = np.isfinite(truth.range) & np.isfinite(frame.range) & np.isfinite(estimate) & ~truth.clamped
    return float(np.sqrt(np.mean((estimate - truth.range)[scored] ** 2)))


def _jump_ratios(estimate, truth):
    """Kept fraction of each resolvable depth jump (see `resolved_jump_ratios`)."""
    return resolved_jump_ratios(estimate, truth.range, truth.sigma)


@pytest.mark.parametrize(
    ("options", "max_error_ratio"),
    [
        ({"noise": "sensor"}, 0.5),  # measured 0.35-0.38 (0.36-0.40 before kappa from the smaller sigma, step 0.18)
        ({}, 0.55),  # frame-wide noise estimate; measured 0.45-0.46
        ({"conduction": "rational", "noise": "sensor"}, 0.5),  # measured 0.33-0.35
    ],
    ids=["sensor-noise-model", "estimated-noise", "rational-sensor-noise-model"],
)
def test_metric_mode_halves_the_error_on_sr3000_and_keeps_edges(sr3000_frames, options, max_error_ratio):
    options = dict(options)
    use_sensor = options.pop("noise", None) == "sensor"
    ratios = []
    for frame, truth in sr3000_frames:
        sigma = frame.sensor.range_sigma(frame.range, frame.intensity) if use_sensor else None
        result = anisotropic_diffusion(frame.range, range_sigma=sigma, **options)
        _assert_same_holes(result, frame.range)
        assert _rmse(result, frame, truth) < max_error_ratio * _rmse(frame.range, frame, truth)
        ratios.append(_jump_ratios(result, truth))
    _assert_edges_stay_sharp(np.concatenate(ratios), sr3000_frames)


def _assert_edges_stay_sharp(ratios, frames_and_truth):
    """At least 95 % of the resolved jumps keep 80 % of their height, as in the raw frames (97 %)."""
    raw = np.concatenate([_jump_ratios(frame.range, truth) for frame, truth in frames_and_truth])
    assert ratios.size == raw.size > 150
    assert np.mean(ratios >= 0.8) >= min(0.95, np.mean(raw >= 0.8))
    assert np.median(ratios) >= 0.95


def test_thesis_mode_reduces_the_error_on_sr3000(sr3000_frames):
    ratios = []
    for frame, truth in sr3000_frames:
        result = anisotropic_diffusion(frame.range, mode="thesis", kappa=20.0, step=0.1)
        assert _rmse(result, frame, truth) < 0.6 * _rmse(frame.range, frame, truth)  # measured 0.42
        np.testing.assert_array_equal(result, THESIS_PRESETS["edges"].apply(frame.range))
        ratios.append(_jump_ratios(result, truth))
    _assert_edges_stay_sharp(np.concatenate(ratios), sr3000_frames)


def test_sr3000_frames_with_dropped_dark_pixels_keep_their_holes(sr3000_frames):
    """Time-of-flight drivers drop low-amplitude returns: holes, and the noisiest pixels gone."""
    for frame, truth in sr3000_frames:
        dark = frame.intensity < 0.05
        assert 100 < dark.sum() < 0.5 * dark.size
        image = np.where(dark, np.nan, frame.range).astype(np.float32)
        result = anisotropic_diffusion(image, range_sigma=frame.sensor.range_sigma(image, frame.intensity))
        _assert_same_holes(result, image)
        assert _rmse(result, frame, truth) < 0.5 * _rmse(image, frame, truth)


# --------------------------------------------------------------------------
# Presets.
# --------------------------------------------------------------------------


def test_thesis_presets():
    edges, canny = THESIS_PRESETS["edges"], THESIS_PRESETS["canny"]
    settings = (edges.kappa, edges.step, edges.conduction, edges.mode, edges.passes)
    assert settings == (20.0, 0.1, "exponential", "thesis", 1)
    # The thesis's lambda = 0.3 as two stable half steps: the same diffusion time.
    assert canny.step <= 0.25 and math.isclose(canny.step * canny.iterations, 0.3 * 10)
    assert canny.passes == 3
    image = range_image((40, 50), seed=7)
    expected = image
    for _ in range(3):
        expected = anisotropic_diffusion(expected, mode="thesis", kappa=20.0, step=0.15, iterations=20)
    np.testing.assert_array_equal(canny.apply(image), expected)


def test_preset_checks_its_settings():
    with pytest.raises(ValueError, match="passes"):
        DiffusionPreset(name="x", iterations=10, kappa=20.0, step=0.1, passes=0)
    with pytest.raises(ValueError, match="0.25"):
        DiffusionPreset(name="x", iterations=10, kappa=20.0, step=0.3)


# --------------------------------------------------------------------------
# Degenerate inputs.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["metric", "thesis"])
@pytest.mark.parametrize("conduction", CONDUCTIONS)
def test_constant_frames_are_unchanged(mode, conduction):
    image = np.full((9, 11), 2.75, np.float32)
    image[3, 4] = np.nan
    result = anisotropic_diffusion(image, mode=mode, conduction=conduction)
    np.testing.assert_array_equal(result, image)
    result = anisotropic_diffusion(image, mode=mode, conduction=conduction, kappa=1.0)
    np.testing.assert_array_equal(result, image)


@pytest.mark.parametrize("shape", [(144, 176), (1, 1), (0, 5)])
def test_all_nan_frames_stay_all_nan(shape):
    result = anisotropic_diffusion(np.full(shape, np.nan))
    assert result.dtype == np.float32 and result.shape == shape and np.all(np.isnan(result))


def test_tiny_frames():
    assert anisotropic_diffusion([[1.5]], kappa=1.0).tolist() == [[1.5]]
    result = anisotropic_diffusion([[1.0, 2.0], [3.0, 4.0]], kappa=10.0, iterations=200, step=0.25)
    np.testing.assert_allclose(result, 2.5, atol=1e-4)  # converges to the mean
    _assert_same_holes(anisotropic_diffusion([[1.0, np.nan], [3.0, 4.0]], kappa=1.0), [[1.0, np.nan], [3.0, 4.0]])


def test_integer_millimetres_and_the_input_is_untouched():
    millimetres = (np.nan_to_num(range_image((20, 30), seed=8), nan=0.0) * 1000).astype(np.uint16)
    copy = millimetres.copy()
    result = anisotropic_diffusion(millimetres, kappa=30.0)
    assert result.dtype == np.float32 and np.array_equal(millimetres, copy)
    image = range_image((20, 30), seed=8)
    before = image.copy()
    anisotropic_diffusion(image)
    np.testing.assert_array_equal(image, before)


def test_zero_iterations_return_a_copy():
    image = range_image((10, 12))
    result = anisotropic_diffusion(image, iterations=0)
    np.testing.assert_array_equal(result, image)
    assert result is not image


def test_automatic_kappa_follows_the_noise():
    """Scaling ranges and noise together scales the result: kappa is set from the noise, not a constant."""
    image = range_image((60, 80), seed=9)
    np.testing.assert_allclose(
        anisotropic_diffusion(image * np.float32(4.0)), 4.0 * anisotropic_diffusion(image), rtol=0, atol=1e-5
    )
    assert set(METRIC_KAPPA_MULTIPLES) == set(CONDUCTIONS)


# --------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (np.zeros((144, 176, 3)), r"2-D.*\(144, 176, 3\)"),
        (np.zeros(5), r"2-D.*\(5,\)"),
        (np.array([["a", "b"]]), "real numeric array.*<U1"),
        (np.ones((3, 3), bool), "real numeric array.*bool"),
        (np.ones((3, 3), complex), "real numeric array.*complex"),
        (np.ones((3, 3), object), "real numeric array.*object"),
        (np.array([[1.0, np.inf], [2.0, 3.0]]), "Inf"),
    ],
)
def test_bad_images(image, message):
    with pytest.raises(ValueError, match=message):
        anisotropic_diffusion(image)


@pytest.mark.parametrize(
    "options",
    [{}, {"kappa": 0.1}, {"range_sigma": np.full((10, 12), 0.01)}, {"mode": "thesis"}, {"iterations": 0}],
    ids=["automatic-kappa", "kappa", "range-sigma", "thesis", "no-iterations"],
)
def test_inf_is_refused_whatever_the_options(options):
    for where in ((0, 0), (9, 11), (5, 6)):
        image = range_image((10, 12), holes=False)
        image[where] = -np.inf
        with pytest.raises(ValueError, match=r"contains Inf \(1 values\); mark missing returns with NaN"):
            anisotropic_diffusion(image, **options)


def test_values_that_overflow_once_divided_by_kappa_are_refused():
    with pytest.raises(ValueError, match="kappa 1e-30 is too small"):
        anisotropic_diffusion([[1e10, 2e10]], kappa=1e-30)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"kappa": 0.0}, "kappa must be finite and > 0, got 0.0"),
        ({"kappa": -1.0}, "kappa must be"),
        ({"kappa": float("nan")}, "kappa must be"),
        ({"kappa": 1e-40}, "kappa .* too small"),
        ({"step": 0.3}, r"step must be <= 0.25 .*stable.*got 0.3"),
        ({"step": 0.0}, "step must be > 0"),
        ({"step": -0.1}, "step must be > 0"),
        ({"iterations": -1}, "iterations must be >= 0, got -1"),
        ({"iterations": 2.5}, "iterations must be an integer"),
        ({"conduction": "gaussian"}, "conduction must be one of exponential, rational, tukey"),
        ({"mode": "raw"}, "mode must be 'metric' or 'thesis'"),
        ({"mode": "thesis", "range_sigma": 0.01}, "range_sigma applies to mode='metric' only"),
        ({"kappa": 0.1, "range_sigma": 0.01}, "either kappa .* or range_sigma"),
        ({"range_sigma": np.full((3, 3), 0.01)}, r"range_sigma .* shape \(10, 12\), got shape \(3, 3\)"),
        ({"range_sigma": np.zeros((10, 12))}, "range_sigma must be finite and > 0 wherever there is a return"),
        ({"range_sigma": -0.01}, "range_sigma must be finite and > 0"),
    ],
)
def test_bad_options(options, message):
    with pytest.raises(ValueError, match=message):
        anisotropic_diffusion(range_image((10, 12)), **options)
