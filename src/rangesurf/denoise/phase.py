"""Phase-preserving wavelet denoising of range images (thesis Section 3.1).

Kovesi's method (DICTA 1999): the image is filtered with quadrature pairs
of log-Gabor wavelets, built in the frequency domain, at ``scales`` scales
(wavelengths ``min_wavelength * mult**s``) and ``orientations``
orientations. Each filter pair gives a complex response ``E + iO`` (thesis
Eq. 3.4-3.5) of amplitude ``A = |E + iO|`` and phase ``atan2(O, E)``
(Eq. 3.6-3.7). Pure noise makes ``A`` Rayleigh distributed; its scale is
estimated per orientation from the median amplitude of the smallest-scale
filter, ``mu = median(A) * sqrt(-pi / log(0.5)) / 2``,
``sigma = sqrt((4 - pi) / pi) * mu``, and divided by ``mult**s`` for larger
scales (the noise response falls with the filter's centre frequency).
Every response is shrunk towards zero by ``T = mu + k * sigma`` (Eq. 3.9)
without changing its phase: ``A -> max(A - T, 0)``. Kovesi's denoised
image is the sum of the shrunk even (real) responses.

That sum is a band-pass image: log-Gabor filters have no DC component, and
the bank's gain is not one. Range images must come out in metres, so
`phase_preserving_denoise` subtracts from the input only what the shrinkage
removed, divided by the bank's peak gain ``c`` (the largest value over all
frequencies of the sum of the filters' even transfer functions)::

    result = image - (sum of E - sum of shrunk E) / c

With no shrinkage the result is the input; frequencies below the largest
scale (the surfaces' overall shape) pass untouched. Kovesi's band-pass sum
itself is `_kovesi_band_sum` (which ``phasecongruency.ppdenoise`` matches).

References
----------
.. [1] P. Kovesi, "Phase preserving denoising of images", Proceedings of
   DICTA 1999 (Digital Image Computing: Techniques and Applications),
   Perth, 212-217, 1999.
.. [2] P. Kovesi, MATLAB and Octave functions for computer vision and image
   processing, ``noisecomp.m`` / ``ppdenoise.m``.
.. [3] The reference thesis, Section 3.1, Eq. 3.4-3.9
   (``shared/reference/thesis.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from types import MappingProxyType

import cv2
import numba
import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from rangesurf._checks import check_range_image

__all__ = ["PHASE_PRESETS", "phase_preserving_denoise"]

#: The thesis's two settings (Section 3.1) as ``(noise_std_multiplier,
#: scales, mult, orientations)`` = (NSD, NS, MF, NO). ``"thesis-a"``: best
#: before Prewitt, Sobel and Roberts edges; ``"thesis-b"``: best before Canny.
PHASE_PRESETS: Mapping[str, tuple[float, int, float, int]] = MappingProxyType({
    "thesis-a": (2.0, 7, 3.0, 8),
    "thesis-b": (5.0, 5, 2.0, 6),
})

# Rayleigh distribution: mean = median / sqrt(-4 log(1/2) / pi) ...
_MEDIAN_TO_RAYLEIGH_MEAN = 0.5 * math.sqrt(-math.pi / math.log(0.5))
# ... and standard deviation = sqrt((4 - pi) / pi) * mean.
_RAYLEIGH_STD_ON_MEAN = math.sqrt((4.0 - math.pi) / math.pi)
# Filter spectra held at once, at most this many complex64 values (about
# 32 MB, shared among the threads), so large frames do not exhaust memory.
_BATCH_VALUES = 4_000_000
# Threads sharing the orientations of one frame (`_band_sums`), and the smallest
# frame worth the hand-over.
_THREADS = 2
_PARALLEL_PIXELS = 4096

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})


# --------------------------------------------------------------------------
# Public function.
# --------------------------------------------------------------------------


def phase_preserving_denoise(
    range_image: ArrayLike,
    *,
    preset: str = "thesis-a",
    noise_std_multiplier: float | None = None,
    scales: int | None = None,
    mult: float | None = None,
    orientations: int | None = None,
    min_wavelength: float = 2.0,
    sigma_onf: float = 0.55,
    softness: float = 1.0,
) -> np.ndarray:
    """Remove noise from a range image by shrinking log-Gabor wavelet amplitudes, keeping their phase.

    Kovesi's phase-preserving denoising (thesis Eq. 3.4-3.9), in metres:
    the input minus what the amplitude shrinkage removed, scaled by the
    filter bank's peak gain (see the module notes).

    Parameters
    ----------
    range_image : (H, W) array_like
        Ranges in metres (any real dtype), NaN where there is no return.
    preset : {"thesis-a", "thesis-b"}
        Which of `PHASE_PRESETS` supplies the four options below that are
        not given: ``"thesis-a"`` (NSD, NS, MF, NO) = (2, 7, 3, 8),
        ``"thesis-b"`` = (5, 5, 2, 6).
    noise_std_multiplier : float, optional
        NSD, Kovesi's ``k``: the threshold is the noise amplitude's Rayleigh
        mean plus this many of its standard deviations (Eq. 3.9), >= 0.
    scales : int, optional
        NS, number of filter scales, >= 1.
    mult : float, optional
        MF, ratio of successive wavelengths, > 1.
    orientations : int, optional
        NO, number of filter orientations (spread over 180 degrees), >= 1.
    min_wavelength : float
        Wavelength of the smallest filter in pixels, >= 2 (Nyquist).
    sigma_onf : float
        Width of the log-Gabor transfer function: the ratio of the standard
        deviation of its Gaussian (on a log-frequency axis) to its centre
        frequency, in (0, 1). 0.55 is about two octaves.
    softness : float
        0 hard thresholding (responses below ``T`` are zeroed, the others
        kept), 1 soft (every amplitude is reduced by ``T``), or in between.

    Returns
    -------
    (H, W) float32
        Denoised ranges in metres, NaN exactly where ``range_image`` is NaN
        (an all-NaN frame stays all NaN). Holes are filled with the nearest
        valid range before filtering, so that they do not ring. Images too
        small to hold a frequency above DC (1 x 1) and constant images come
        back unchanged (up to float32 rounding).

    Raises
    ------
    ValueError
        If the image is not 2-D or not real-valued, contains Inf, the preset
        is unknown, or an option is out of range (``scales < 1``,
        ``mult <= 1``, ``orientations < 1``, ``noise_std_multiplier < 0``,
        ``min_wavelength < 2``, ``sigma_onf`` outside (0, 1), ``softness``
        outside [0, 1]).

    Notes
    -----
    Works in float32 with complex64 FFTs (OpenCV's `cv2.dft`), one forward
    transform and one inverse per filter; frames of 4096 pixels or more
    share the orientations between two threads. The filter bank is cached
    per image size and options (`functools.lru_cache`, 8 entries), so
    repeated frames of one sensor pay only for the transforms. Agrees with
    ``phasecongruency.ppdenoise`` (Kovesi's algorithm, float64) to about
    1e-6 m on Kovesi's band sum; the differences are float32 rounding and
    Kovesi's ``epsilon = 1e-5`` added to every amplitude in the shrinkage,
    which this function leaves out (in metres it is not negligible next to
    millimetre noise amplitudes).

    The FFT makes the image periodic: a range difference between opposite
    borders acts like a depth jump there, and the pixels next to the
    borders are smoothed less well. The threshold is estimated from the
    whole frame, so it assumes roughly uniform noise; time-of-flight noise
    grows with range, so far or dark surfaces keep more of theirs.

    Soft thresholding (``softness=1``, Kovesi's default and the thesis's
    setting) takes ``T`` off every response, also off the large ones at
    depth jumps, which it blurs by a few noise sigmas. On simulated SR-3000
    frames (``benchmarks/phase.py``) ``"thesis-a"`` cuts the RMSE 1.75x but
    keeps only 87 % of the resolved jumps at >= 80 % of their height;
    ``softness=0.5`` cuts it 1.63x and keeps 96 %, ``softness=0`` 1.39x and
    99 %.

    References
    ----------
    .. [1] P. Kovesi, "Phase preserving denoising of images", DICTA 1999,
       212-217.
    .. [2] The reference thesis, Section 3.1, Eq. 3.4-3.9, with the two
       settings of `PHASE_PRESETS`.

    Examples
    --------
    A 0.5 m bump on a wall 2 m away, with 2 cm noise, loses most of the noise:

    >>> import numpy as np
    >>> from rangesurf.denoise.phase import phase_preserving_denoise
    >>> rng = np.random.default_rng(0)
    >>> rows, cols = np.mgrid[0:48, 0:64]
    >>> truth = 2.0 + 0.5 * np.exp(-((rows - 24) ** 2 + (cols - 32) ** 2) / 200.0)
    >>> noisy = (truth + rng.normal(0, 0.02, truth.shape)).astype(np.float32)
    >>> clean = phase_preserving_denoise(noisy, preset="thesis-a")
    >>> rms = lambda image: float(np.sqrt(np.mean((image - truth) ** 2)))
    >>> rms(clean) < 0.4 * rms(noisy)
    True
    >>> clean.dtype, clean.shape
    (dtype('float32'), (48, 64))
    """
    image = check_range_image(range_image)
    k, n_scales, ratio, n_orientations = _resolve_options(preset, noise_std_multiplier, scales, mult, orientations)
    min_wavelength, sigma_onf, softness = _check_filter_options(min_wavelength, sigma_onf, softness)

    valid = ~np.isnan(image)
    if not valid.any():
        return image.copy()
    filled = _fill_holes(image, valid)
    bank = _filter_bank(image.shape, n_scales, ratio, n_orientations, min_wavelength, sigma_onf)
    if bank.gain == 0.0:  # no frequency but DC (1 x 1): nothing to shrink
        return image.copy()
    # The filters have no DC: removing the mean first keeps float32 precise.
    offset = float(np.mean(filled, dtype=np.float64))
    removed, _ = _band_sums(filled - np.float32(offset), bank, k, softness, 0.0)
    result = filled - removed / np.float32(bank.gain)
    result[~valid] = np.nan
    return result


# --------------------------------------------------------------------------
# Input checks.
# --------------------------------------------------------------------------


def _is_integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _resolve_options(preset, noise_std_multiplier, scales, mult, orientations) -> tuple[float, int, float, int]:
    try:
        defaults = PHASE_PRESETS[preset]
    except (KeyError, TypeError):
        raise ValueError(f"preset must be one of {', '.join(PHASE_PRESETS)}; got {preset!r}") from None
    k = defaults[0] if noise_std_multiplier is None else noise_std_multiplier
    scales = defaults[1] if scales is None else scales
    mult = defaults[2] if mult is None else mult
    orientations = defaults[3] if orientations is None else orientations
    k = float(k)
    if not (math.isfinite(k) and k >= 0):
        raise ValueError(f"noise_std_multiplier must be finite and >= 0, got {noise_std_multiplier}")
    if not (_is_integer(scales) and scales >= 1):
        raise ValueError(f"scales must be an integer >= 1, got {scales!r}")
    mult = float(mult)
    if not (math.isfinite(mult) and mult > 1):
        raise ValueError(f"mult must be finite and > 1, got {mult}")
    if not (_is_integer(orientations) and orientations >= 1):
        raise ValueError(f"orientations must be an integer >= 1, got {orientations!r}")
    return k, int(scales), mult, int(orientations)


def _check_filter_options(min_wavelength, sigma_onf, softness) -> tuple[float, float, float]:
    min_wavelength = float(min_wavelength)
    if not (math.isfinite(min_wavelength) and min_wavelength >= 2):
        raise ValueError(f"min_wavelength must be >= 2 pixels (the Nyquist limit), got {min_wavelength}")
    sigma_onf = float(sigma_onf)
    if not (0 < sigma_onf < 1):
        raise ValueError(f"sigma_onf must be in (0, 1), got {sigma_onf}")
    softness = float(softness)
    if not (0 <= softness <= 1):
        raise ValueError(f"softness must be in [0, 1], got {softness}")
    return min_wavelength, sigma_onf, softness


# --------------------------------------------------------------------------
# Filters and shrinkage.
# --------------------------------------------------------------------------


def _fill_holes(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``image`` with each NaN replaced by the nearest valid value (Euclidean, ties by scipy's order)."""
    if valid.all():
        return image.copy()
    indices = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return image[indices[0], indices[1]]


@dataclass(frozen=True, eq=False)
class _Bank:
    """Factored log-Gabor bank on the full FFT grid ``(H, W)``, float32, read-only.

    The filter of scale ``s`` and orientation ``o`` is ``radial[s] *
    angular[o]`` (``radial``: ``(NS, H, W)``, ``angular``: ``(NO, H, W)``).
    ``gain``: the largest value over all frequencies of the even
    (real-output) transfers ``(filter(f) + filter(-f)) / 2`` summed over
    every filter. ``mult``: the ratio of successive wavelengths.
    """

    radial: np.ndarray
    angular: np.ndarray
    gain: float
    shape: tuple[int, int]
    mult: float

    def __post_init__(self) -> None:
        self.radial.flags.writeable = False
        self.angular.flags.writeable = False


@lru_cache(maxsize=8)
def _filter_bank(shape, scales, mult, orientations, min_wavelength, sigma_onf, spacing_on_sigma=1.0) -> _Bank:
    """Kovesi's filters (``filtergrids``, ``loggabor``, ``gaussianangularfilter``) for an image of ``shape``."""
    rows, cols = shape
    fy = np.fft.fftfreq(rows)[:, None]
    fx = np.fft.fftfreq(cols)[None, :]
    radius = np.sqrt(fx * fx + fy * fy)
    at_dc = radius == 0
    safe = np.where(at_dc, 1.0, radius)
    sin_theta, cos_theta = fx / safe, fy / safe  # Kovesi's angles, from the vertical frequency axis
    log_sigma_squared = 2.0 * math.log(sigma_onf) ** 2
    radial = np.empty((scales, rows, cols), np.float32)
    wavelength = min_wavelength
    for s in range(scales):
        radial[s] = np.where(at_dc, 0.0, np.exp(-(np.log(safe * wavelength) ** 2) / log_sigma_squared))
        wavelength *= mult
    theta_sigma = math.pi / orientations / spacing_on_sigma
    angular = np.empty((orientations, rows, cols), np.float32)
    for o in range(orientations):
        angle = o * math.pi / orientations
        d_sin = sin_theta * math.cos(angle) - cos_theta * math.sin(angle)
        d_cos = cos_theta * math.cos(angle) + sin_theta * math.sin(angle)
        angular[o] = np.exp(-np.arctan2(d_sin, d_cos) ** 2 / (2.0 * theta_sigma**2))
    total = radial.sum(axis=0, dtype=np.float64) * angular.sum(axis=0, dtype=np.float64)
    # total(-f): the grid point at minus the frequency, on the aliased grid.
    negated = total[(-np.arange(rows)) % rows][:, (-np.arange(cols)) % cols]
    return _Bank(radial, angular, float(np.max((total + negated) / 2.0)), shape, mult)


def _band_sums(
    image: np.ndarray, bank: _Bank, k: float, softness: float, epsilon: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(sum of removed even response, sum of shrunk even response)``, each ``(H, W)`` float32.

    Orientations are independent (each has its own noise threshold). On
    frames of ``_PARALLEL_PIXELS`` or more, ``_THREADS`` threads (the
    calling one and `_executor`'s, all running single-threaded DFTs and
    kernels that release the GIL) take them one at a time, so that a thread
    slowed by other work on the machine simply takes fewer.
    """
    orientations = bank.angular.shape[0]
    spectrum = _forward_fft(image)
    threads = min(_THREADS, orientations) if image.size >= _PARALLEL_PIXELS else 1
    if threads == 1:
        return _drain(iter([np.arange(orientations)]), spectrum, bank, k, softness, epsilon, _BATCH_VALUES)
    # next() on a list iterator is atomic, so the threads share the queue without a lock.
    queue = iter([np.array([o]) for o in range(orientations)])
    arguments = (queue, spectrum, bank, k, softness, epsilon, _BATCH_VALUES // threads)
    helpers = [_executor(threads - 1).submit(_drain, *arguments) for _ in range(threads - 1)]
    removed, kept = _drain(*arguments)
    for helper in helpers:
        # A helper that has not started (a busy machine; or a forked child, which
        # has the executor but not its thread) finds the queue empty: skip it.
        if helper.cancel():
            continue
        helper_removed, helper_kept = helper.result()
        removed += helper_removed
        kept += helper_kept
    return removed, kept


@lru_cache(maxsize=None)
def _executor(workers: int) -> ThreadPoolExecutor:
    """The helper threads of `_band_sums`, started on first use."""
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="rangesurf-phase")


def _drain(queue, spectrum: np.ndarray, bank: _Bank, k: float, softness: float, epsilon: float,
           batch_values: int) -> tuple[np.ndarray, np.ndarray]:
    """`_band_sums` over the groups of orientations taken from ``queue`` (an iterator of index arrays).

    Filters of a group in order of scale, then orientation (the smallest
    scale, which sets each orientation's noise threshold, comes first), in
    batches of up to ``batch_values`` pixels.
    """
    scales = bank.radial.shape[0]
    removed = np.zeros(bank.shape, np.float32)
    kept = np.zeros(bank.shape, np.float32)
    products = None
    noise_thresholds = np.zeros(bank.angular.shape[0])
    for orientations in queue:
        scale_of = np.repeat(np.arange(scales, dtype=np.int64), orientations.size)
        orientation_of = np.tile(orientations, scales)
        n_filters = scale_of.size
        batch = max(1, min(n_filters, batch_values // spectrum.size))
        if products is None or products.shape[0] < batch:
            products = np.empty((batch,) + bank.shape, np.complex64)
        for first in range(0, n_filters, batch):
            stop = min(n_filters, first + batch)
            in_batch = slice(first, stop)
            _filter_products(
                spectrum, bank.radial, bank.angular, scale_of[in_batch], orientation_of[in_batch], products
            )
            responses = _inverse_fft(products[: stop - first])
            for index in range(first, stop):
                if scale_of[index] == 0:
                    rayleigh_mean = float(_median_amplitude(responses[index - first])) * _MEDIAN_TO_RAYLEIGH_MEAN
                    noise_thresholds[orientation_of[index]] = rayleigh_mean * (1.0 + k * _RAYLEIGH_STD_ON_MEAN)
            # The noise response falls in proportion to the filter's centre frequency.
            thresholds = noise_thresholds[orientation_of[in_batch]] / bank.mult ** scale_of[in_batch]
            _shrink_accumulate(responses, thresholds.astype(np.float32), np.float32(softness), np.float32(epsilon),
                               removed, kept)
    return removed, kept


def _inverse_fft(spectra: np.ndarray) -> np.ndarray:
    """``ifft2`` of each ``(H, W)`` spectrum in ``spectra`` (``(N, H, W)`` complex64), in place.

    OpenCV's DFT (IPP) takes about 0.4x the time of scipy.fft's pocketfft
    on these sizes (176 x 144: 31 against 78 us, single-threaded).
    """
    for spectrum in spectra:
        pairs = spectrum.view(np.float32).reshape(spectrum.shape + (2,))  # complex64 as OpenCV's 2-channel float
        cv2.dft(pairs, dst=pairs, flags=cv2.DFT_INVERSE | cv2.DFT_SCALE | cv2.DFT_COMPLEX_OUTPUT)
    return spectra


def _forward_fft(image: np.ndarray) -> np.ndarray:
    """``fft2`` of a real ``(H, W)`` float32 image, complex64."""
    pairs = cv2.dft(np.ascontiguousarray(image, np.float32), flags=cv2.DFT_COMPLEX_OUTPUT)
    return pairs.reshape(image.shape + (2,)).view(np.complex64).reshape(image.shape)


def _kovesi_band_sum(image: ArrayLike, *, k: float, scales: int, mult: float, orientations: int,
                     min_wavelength: float = 2.0, sigma_onf: float = 0.55, softness: float = 1.0,
                     epsilon: float = 1e-5) -> np.ndarray:
    """Kovesi's ``ppdenoise`` output (the sum of the shrunk even responses) of a NaN-free image, float32.

    ``epsilon`` is added to the amplitude in the shrinkage ``T * EO / (|EO| + epsilon)``,
    as in Kovesi's code (`phase_preserving_denoise` uses 0).
    """
    image = check_range_image(image)
    bank = _filter_bank(image.shape, scales, float(mult), orientations, float(min_wavelength), float(sigma_onf))
    offset = np.float32(np.mean(image, dtype=np.float64))
    return _band_sums(image - offset, bank, k, softness, epsilon)[1]


@numba.njit(**_JIT)
def _filter_products(spectrum, radial, angular, scale_of, orientation_of, out):  # pragma: no cover - compiled
    """``out[n] = spectrum * radial[scale_of[n]] * angular[orientation_of[n]]``: spectra of the responses."""
    _, rows, cols = radial.shape
    for n in range(scale_of.size):
        s = scale_of[n]
        o = orientation_of[n]
        for i in range(rows):
            for j in range(cols):
                out[n, i, j] = spectrum[i, j] * (radial[s, i, j] * angular[o, i, j])


@numba.njit(**_JIT)
def _median_amplitude(response):  # pragma: no cover - compiled
    """Median of ``|response|`` over an ``(H, W)`` complex64 image; the mean of the two middle values if even.

    Selects among the squared amplitudes, whose float32 bit patterns sort as
    unsigned integers (they are >= 0), by radix: one pass over all of them
    counts their top 11 bits and a second copies out those in the bucket(s)
    of the middle rank(s), among which two more passes of 11 and 10 bits
    select.
    """
    rows, cols = response.shape
    size = rows * cols
    squared = np.empty(size, np.float32)
    for i in range(rows):
        for j in range(cols):
            value = response[i, j]
            squared[i * cols + j] = value.real * value.real + value.imag * value.imag
    keys = squared.view(np.uint32)
    counts = np.zeros(2048, np.int64)
    for key in keys:
        counts[key >> np.uint32(21)] += 1
    upper_rank = size // 2
    lower_rank = upper_rank - 1 if size % 2 == 0 else upper_rank
    lower_digit, lower_rank = _find_digit(counts, lower_rank)
    upper_digit, upper_rank = _find_digit(counts, upper_rank)
    # The middle ranks lie in one bucket or in two neighbouring non-empty ones.
    candidates = np.empty(counts[lower_digit] + (counts[upper_digit] if upper_digit != lower_digit else 0), np.uint32)
    n = 0
    for key in keys:
        digit = key >> np.uint32(21)
        if digit == lower_digit or digit == upper_digit:
            candidates[n] = key
            n += 1
    upper = math.sqrt(_key_to_float(_select_key(candidates, upper_digit, upper_rank)))
    if size % 2:
        return upper
    return 0.5 * (math.sqrt(_key_to_float(_select_key(candidates, lower_digit, lower_rank))) + upper)


@numba.njit(**_JIT)
def _find_digit(counts, rank):  # pragma: no cover - compiled
    """``(bucket, rank within it)`` of the ``rank``-th smallest value, given the bucket ``counts``."""
    digit = 0
    while rank >= counts[digit]:
        rank -= counts[digit]
        digit += 1
    return digit, rank


@numba.njit(**_JIT)
def _key_to_float(key):  # pragma: no cover - compiled
    return np.array([key], np.uint32).view(np.float32)[0]


@numba.njit(**_JIT)
def _select_key(keys, top_digit, rank):  # pragma: no cover - compiled
    """The ``rank``-th smallest (from 0) of those ``keys`` (uint32) whose top 11 bits are ``top_digit``."""
    prefix = np.uint32(top_digit) << np.uint32(21)
    mask = np.uint32(0xFFE00000)
    counts = np.empty(2048, np.int64)
    for shift, width in ((10, 11), (0, 10)):
        counts[:] = 0
        bins = np.uint32((1 << width) - 1)
        for key in keys:
            if (key & mask) == prefix:
                counts[(key >> np.uint32(shift)) & bins] += 1
        digit, rank = _find_digit(counts, rank)
        prefix |= np.uint32(digit) << np.uint32(shift)
        mask |= bins << np.uint32(shift)
    return prefix


@numba.njit(**_JIT)
def _shrink_accumulate(responses, thresholds, softness, epsilon, removed, kept):  # pragma: no cover - compiled
    """Add each scale's shrunk even response to ``kept``, and what the shrinkage took from it to ``removed``.

    Kovesi's rule: where ``|EO| > T`` the response loses ``softness * T *
    EO / (|EO| + epsilon)``, elsewhere all of it.
    """
    scales, rows, cols = responses.shape
    for s in range(scales):
        threshold = thresholds[s]
        step = softness * threshold
        for i in range(rows):
            for j in range(cols):
                value = responses[s, i, j]
                real = value.real
                imaginary = value.imag
                amplitude = math.sqrt(real * real + imaginary * imaginary)
                shrunk = real - step * real / (amplitude + epsilon)
                shrunk = shrunk if amplitude > threshold else np.float32(0.0)
                kept[i, j] += shrunk
                removed[i, j] += real - shrunk


# --------------------------------------------------------------------------
# Plain NumPy reference (what the fast path computes, written directly).
# --------------------------------------------------------------------------


def _denoise_reference(image: np.ndarray, *, k: float, scales: int, mult: float, orientations: int,
                       min_wavelength: float = 2.0, sigma_onf: float = 0.55, softness: float = 1.0,
                       epsilon: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(metres result, Kovesi band sum)``, float64, by full complex FFTs filter by filter.

    Kovesi's ``ppdenoise`` written out in float64 (his grids, log-Gabor and
    angular Gaussian), holes filled with the nearest valid value first and
    restored as NaN in the metres result.
    """
    image = np.asarray(image, np.float64)
    valid = ~np.isnan(image)
    if not valid.any():
        return image.copy(), image.copy()
    indices = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    filled = image[indices[0], indices[1]]
    rows, cols = image.shape
    fx, fy = np.meshgrid(np.fft.fftfreq(cols), np.fft.fftfreq(rows))
    radius = np.hypot(fx, fy)
    radius_safe = radius.copy()
    radius_safe[0, 0] = 1.0
    sin_theta, cos_theta = fx / radius_safe, fy / radius_safe
    theta_sigma = np.pi / orientations
    spectrum = np.fft.fft2(filled)
    kept = np.zeros((rows, cols), complex)
    everything = np.zeros((rows, cols), complex)
    even_transfer = np.zeros((rows, cols))
    for o in range(orientations):
        angle = o * np.pi / orientations
        d_sin = sin_theta * np.cos(angle) - cos_theta * np.sin(angle)
        d_cos = cos_theta * np.cos(angle) + sin_theta * np.sin(angle)
        spread = np.exp(-np.arctan2(d_sin, d_cos) ** 2 / (2 * theta_sigma**2))
        wavelength = min_wavelength
        for s in range(scales):
            log_gabor = np.zeros((rows, cols))
            nonzero = radius > 0
            log_gabor[nonzero] = np.exp(-np.log(radius[nonzero] * wavelength) ** 2 / (2 * np.log(sigma_onf) ** 2))
            transfer = log_gabor * spread
            negated = np.roll(transfer[::-1, ::-1], 1, axis=(0, 1))  # transfer(-f)
            even_transfer += (transfer + negated) / 2
            response = np.fft.ifft2(spectrum * transfer)
            amplitude = np.abs(response)
            if s == 0:
                rayleigh_mean = np.median(amplitude) * 0.5 * np.sqrt(-np.pi / np.log(0.5))
                rayleigh_variance = (4 - np.pi) * rayleigh_mean**2 / np.pi
            threshold = (rayleigh_mean + k * np.sqrt(rayleigh_variance)) / mult**s
            above = amplitude > threshold
            shrunk = np.where(above, response - softness * threshold * response / (amplitude + epsilon), 0)
            kept += shrunk
            everything += response
            wavelength *= mult
    gain = even_transfer.max()
    if gain == 0:
        return np.where(valid, filled, np.nan), np.zeros_like(filled)
    result = filled - (everything.real - kept.real) / gain
    result[~valid] = np.nan
    return result, kept.real
