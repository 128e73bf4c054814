"""Edge-preserving anisotropic diffusion of range images (thesis Section 3.1).

Perona and Malik's explicit four-neighbour scheme (thesis Eq. 3.1)::

    I[t+1] = I[t] + step * sum over N, S, E, W of g(delta) * delta

where ``delta`` is the difference to a neighbour and ``g`` the conduction
("edge-stopping") function: ``exp(-(delta/kappa)**2)`` (Eq. 3.2),
``1 / (1 + (delta/kappa)**2)`` (Eq. 3.3), or Tukey's biweight
``0.5 * (1 - (delta/kappa)**2)**2`` for ``|delta| <= kappa``, else 0
(Black, Sapiro, Marimont and Heeger 1998).

Range images have holes (NaN, no return). A hole is an insulator: no flux
crosses a pair of pixels of which one is NaN, NaN pixels stay NaN and NaN
never spreads. Image borders are insulating too (zero flux, Neumann).

Two ways to set the scale ``kappa`` (`anisotropic_diffusion`'s ``mode``):

* ``"thesis"``: the valid ranges are mapped linearly onto 0-255 grey levels
  (min to max), diffused with the thesis's ``kappa = 20``, ``step = 0.1``,
  and mapped back to metres (`THESIS_PRESETS` holds the thesis's two
  settings).
* ``"metric"``: the ranges are diffused in metres and ``kappa`` is scaled to
  the noise: a multiple (`METRIC_KAPPA_MULTIPLES`) of the standard deviation
  of the difference of two neighbouring readings, either from the sensor's
  noise model (``range_sigma``, per pixel: time-of-flight noise grows with
  range and on dark surfaces, so the threshold does too) or, without one,
  estimated robustly from the frame itself. A pair's threshold comes from
  the less noisy of its two readings (``sqrt(2) * min(sigma_p, sigma_q)``):
  on one surface the two are nearly equal, and across a depth jump the far,
  noisier side would otherwise raise the threshold until the jump leaks.
  Metric mode's default step is 0.18 (diffusion time 1.8 in the default 10
  iterations), about twice the thesis's.

References
----------
.. [1] P. Perona and J. Malik, "Scale-space and edge detection using
   anisotropic diffusion", IEEE Transactions on Pattern Analysis and Machine
   Intelligence 12(7), 629-639, 1990.
.. [2] M. J. Black, G. Sapiro, D. H. Marimont and D. Heeger, "Robust
   anisotropic diffusion", IEEE Transactions on Image Processing 7(3),
   421-432, 1998.
.. [3] The reference thesis, Sections 2.1 and 3.1, Eq. 3.1-3.3
   (``shared/reference/thesis.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic
from numpy.typing import ArrayLike

from rangesurf._checks import check_range_image

__all__ = [
    "anisotropic_diffusion",
    "diffusion_bias",
    "remove_diffusion_bias",
    "CONDUCTIONS",
    "METRIC_KAPPA_MULTIPLES",
    "MAX_STABLE_STEP",
    "DiffusionPreset",
    "THESIS_PRESETS",
]

Conduction = Literal["exponential", "rational", "tukey"]
Mode = Literal["metric", "thesis"]

#: Conduction functions, in the order of medpy's ``option`` 1, 2, 3.
CONDUCTIONS: tuple[str, ...] = ("exponential", "rational", "tukey")

#: Largest ``step`` for which the explicit four-neighbour scheme is stable
#: (von Neumann: ``4 * step * max(g) <= 1`` with ``max(g) = 1``).
MAX_STABLE_STEP = 0.25

#: Metric mode's automatic ``kappa`` as a multiple of the standard deviation
#: of the difference of two neighbouring readings. Tukey's is Black et al.'s
#: sigma = sqrt(5) sigma_e. The other two were tuned on simulated SR-3000
#: frames (``benchmarks/diffusion.py``): the largest RMSE reduction that
#: keeps every depth jump the data resolves (> 10 % of range and > 5 noise
#: sigmas) as sharp as in the raw frame, with and without ``range_sigma``.
METRIC_KAPPA_MULTIPLES: Mapping[str, float] = MappingProxyType(
    {"exponential": 2.5, "rational": 1.25, "tukey": math.sqrt(5.0)}
)

_THESIS_KAPPA = 20.0
# Default step per mode: the thesis's lambda; in metres the largest step
# whose RMSE on the benchmarks' simulated frames (SR-3000 and Kinect,
# `benchmarks/denoise_quality.py` and `benchmarks/diffusion.py`) is no worse
# than that of 0.1 with sqrt(sigma_p**2 + sigma_q**2) pair kappas, the
# earlier default, with clearly sharper depth edges.
_DEFAULT_STEPS = {"thesis": 0.1, "metric": 0.18}
_THESIS_GREY_LEVELS = 255.0
# 1 / Phi^-1(3/4): turns the median absolute deviation of normal data into
# its standard deviation (as in Black et al. 1998).
_MAD_TO_SIGMA = 1.4826
# Neighbour differences the automatic kappa is estimated from, at most
# (about): enough for a 1 % standard error, cheap next to the diffusion.
_NOISE_SAMPLE = 16384
_CONDUCTION_CODES = {name: code for code, name in enumerate(CONDUCTIONS)}

# Kernels: compiled once and cached; numpy error model (no zero-division
# checks, which would stop vectorisation); contraction into FMAs allowed.
_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
# No contraction: the scaled copy must be recomputed bit for bit.
_EXACT_JIT = dict(cache=True, nogil=True, error_model="numpy")


# --------------------------------------------------------------------------
# Public function.
# --------------------------------------------------------------------------


def anisotropic_diffusion(
    range_image: ArrayLike,
    *,
    iterations: int = 10,
    kappa: float | None = None,
    step: float | None = None,
    conduction: Conduction = "exponential",
    mode: Mode = "metric",
    range_sigma: ArrayLike | float | None = None,
) -> np.ndarray:
    """Smooth a range image within surfaces, not across their edges.

    Perona-Malik diffusion with the explicit four-neighbour scheme of the
    thesis (Eq. 3.1-3.3), insulated at image borders and at pixels with no
    return (NaN).

    Parameters
    ----------
    range_image : (H, W) array_like
        Ranges in metres (any real dtype), NaN where there is no return.
    iterations : int
        Number of explicit steps, >= 0. The diffusion time is
        ``iterations * step``.
    kappa : float, optional
        Edge-stopping scale, > 0, in the units being diffused: grey levels
        of the 0-255 image in ``"thesis"`` mode, metres in ``"metric"``
        mode. Differences well above ``kappa`` barely conduct (exponential,
        rational) or not at all (Tukey: ``|delta| > kappa``). Default:
        ``"thesis"`` 20 (the thesis's value) for exponential and rational,
        and for Tukey Black et al.'s automatic ``sqrt(5) * sigma_e`` of the
        normalised image; ``"metric"`` ``METRIC_KAPPA_MULTIPLES[conduction]``
        times the noise standard deviation of a neighbour difference (see
        ``range_sigma``).
    step : float, optional
        Diffusion speed lambda per iteration, in ``(0, 0.25]``; larger steps
        make the explicit scheme oscillate. Default: ``"thesis"`` 0.1 (the
        thesis's value); ``"metric"`` 0.18, which on simulated SR-3000 and
        Kinect frames (``benchmarks/denoise_quality.py``) gives a lower RMSE
        and sharper depth edges than 0.1 with the sensor noise model.
    conduction : {"exponential", "rational", "tukey"}
        Edge-stopping function ``g``: ``exp(-(d/kappa)**2)`` (thesis Eq. 3.2,
        medpy ``option=1``), ``1 / (1 + (d/kappa)**2)`` (Eq. 3.3, medpy
        ``option=2``), or Tukey's biweight ``0.5 * (1 - (d/kappa)**2)**2``
        for ``|d| <= kappa``, else 0 (Black et al. 1998; medpy's
        ``option=3`` uses ``sqrt(2) * kappa`` as the cut-off).
    mode : {"metric", "thesis"}
        ``"metric"`` diffuses metres; ``"thesis"`` diffuses the valid
        ranges mapped linearly onto 0-255 (min to max) and maps the result
        back to metres.
    range_sigma : (H, W) array_like or float, optional
        ``"metric"`` mode without ``kappa`` only: standard deviation of each
        reading (metres), e.g. ``sensor.range_sigma(frame.range,
        frame.intensity)``, > 0 wherever there is a return. The pair of
        pixels ``p, q`` then has ``kappa = multiple * sqrt(2) *
        min(sigma_p, sigma_q)``, so that the edge threshold follows range-
        and brightness-dependent time-of-flight noise: the noise of a
        difference on a surface, where the two sigmas are nearly equal, but
        across a depth jump that of the nearer, less noisy side. A number
        is one sigma for the whole frame. Without it the noise standard
        deviation of a neighbour difference is estimated from the frame:
        ``1.4826 * MAD`` of the valid neighbour differences (robust to the
        minority of differences that cross edges; from evenly spaced rows,
        about 16 000 differences, in large frames). That estimate is
        frame-wide, so a region's result then depends on the rest of the
        frame; give ``kappa`` or ``range_sigma`` for a purely local filter.

    Returns
    -------
    (H, W) float32
        Smoothed ranges in metres, NaN exactly where ``range_image`` is NaN.
        A frame with no valid pixel (all NaN) is returned as all NaN; a frame
        without anything to smooth (constant, or an automatic ``kappa`` of
        zero because most neighbour differences are exactly zero) is
        returned unchanged.

    Raises
    ------
    ValueError
        If the image is not 2-D or not real-valued, contains Inf, or an
        option is out of range (``iterations < 0``, ``kappa <= 0``, ``step``
        outside ``(0, 0.25]``, unknown ``conduction`` or ``mode``,
        ``range_sigma`` of the wrong shape, not positive where there is a
        return, or given together with ``kappa`` or in ``"thesis"`` mode).

    Notes
    -----
    Each iteration evaluates the conduction once per neighbour pair, in
    float32. The kernel is compiled with Numba (cached on disk after the
    first call) and single-threaded; it evaluates the exponential as a
    vectorised polynomial ``2**x`` (relative error < 3e-6), and matches
    medpy and a plain NumPy implementation with ``numpy.exp`` to about
    1e-6 of the range span.

    Perona-Malik diffusion flattens towards piecewise constant range: it
    smooths little across strongly slanted surfaces (floors and walls seen
    at grazing angles), whose neighbour differences look like edges.

    References
    ----------
    .. [1] P. Perona and J. Malik, "Scale-space and edge detection using
       anisotropic diffusion", IEEE TPAMI 12(7), 629-639, 1990.
    .. [2] M. J. Black, G. Sapiro, D. H. Marimont and D. Heeger, "Robust
       anisotropic diffusion", IEEE Transactions on Image Processing 7(3),
       421-432, 1998.
    .. [3] The reference thesis, Section 3.1, Eq. 3.1-3.3 (``k = 20``,
       ``lambda = 0.1`` on normalised distance images).

    Examples
    --------
    A noisy step of 2 m to 3 m keeps its edge and loses most of its noise:

    >>> import numpy as np
    >>> from rangesurf.denoise import anisotropic_diffusion
    >>> rng = np.random.default_rng(0)
    >>> truth = np.where(np.arange(64) < 32, 2.0, 3.0) * np.ones((48, 1))
    >>> noisy = (truth + rng.normal(0, 0.02, truth.shape)).astype(np.float32)
    >>> smooth = anisotropic_diffusion(noisy, iterations=20, step=0.2)
    >>> rms = lambda image: float(np.sqrt(np.mean((image - truth) ** 2)))
    >>> rms(smooth) < 0.4 * rms(noisy)
    True
    >>> bool(np.all(smooth[:, 32] - smooth[:, 31] > 0.9))
    True
    """
    image = check_range_image(range_image)
    iterations = _check_iterations(iterations)
    _check_mode(mode)
    step = _check_step(_DEFAULT_STEPS[mode] if step is None else step)
    code = _check_conduction(conduction)
    if kappa is not None:
        kappa = _check_kappa(kappa)
    multiple = METRIC_KAPPA_MULTIPLES[conduction]
    pair_scales = None
    if range_sigma is not None:
        if mode != "metric":
            raise ValueError("range_sigma applies to mode='metric' only; thesis mode uses grey levels")
        if kappa is not None:
            raise ValueError("give either kappa (metres) or range_sigma (to derive kappa from), not both")
        if np.ndim(range_sigma) > 0:
            pair_scales = _pair_scales(image, range_sigma, multiple, code)
        else:
            sigma = float(range_sigma)
            if not (math.isfinite(sigma) and sigma > 0):
                raise ValueError(f"range_sigma must be finite and > 0, got {range_sigma}")
            kappa = multiple * math.sqrt(2.0) * sigma

    if mode == "thesis" or iterations == 0:
        n_valid, lowest, highest = _valid_extent(image)
        if iterations == 0 or n_valid == 0 or lowest == highest:
            return image.copy()
        gain = _THESIS_GREY_LEVELS / (highest - lowest)
        if kappa is None:
            if conduction == "tukey":
                # Black et al.: sigma = sqrt(5) sigma_e of the image being diffused.
                kappa = math.sqrt(5.0) * _difference_sigma(image) * gain
            else:
                kappa = _THESIS_KAPPA
        if not kappa > 0:
            return image.copy()
        return _diffuse(image, lowest, gain, kappa, step, iterations, code)

    # Metric mode: the kernels check the frame for Inf as they copy it.
    if pair_scales is not None:
        outcome = _diffuse_pairwise_kernel(image, *pair_scales, np.float32(step), iterations, code)
        return _checked(*outcome, kappa=None)
    if kappa is None:
        kappa = multiple * _difference_sigma(image)
        if not (math.isfinite(kappa) and kappa > 0):
            _valid_extent(image)  # raises on Inf
            if kappa == 0:  # constant, all NaN, or most differences exactly 0: nothing to smooth
                return image.copy()
            raise ValueError(f"cannot estimate the noise of this range image: kappa would be {kappa}")
    return _diffuse(image, 0.0, 1.0, kappa, step, iterations, code)


def diffusion_bias(
    model_range: ArrayLike,
    *,
    range_sigma: ArrayLike | float,
    iterations: int = 10,
    step: float | None = None,
    conduction: Conduction = "exponential",
) -> np.ndarray:
    """The systematic change `anisotropic_diffusion` makes to a noise-free range image (metric mode).

    Diffusion smooths the range *image*, so it moves every range that is not
    an affine function of the pixel coordinates, noise or not: a plane's
    range ``-d / (n . ray)`` is convex over the image, most at close range
    and oblique views, so smoothing lengthens it; creases are rounded, and
    the insulating holes and image borders skew their surroundings. Every
    frame makes this error again, so averaging frames does not remove it,
    unlike the noise. Run through the same filter, a noise-free model of the
    frame (its fitted planes' ranges) shows it; subtract the result from the
    denoised range.

    On simulated SR-3000 corridor frames, away from depth edges, the mean
    error of 60 denoised noise draws of one frame is +2.6 mm at 0-2 m range
    (+0.09 sigma) and +2.5 mm at 2-4 m, this function gives +3.0 and
    +2.7 mm from the true ranges, and per pixel the two correlate at 0.99.

    Parameters
    ----------
    model_range : (H, W) array_like
        Noise-free ranges (metres) of the frame's surfaces, NaN exactly where
        the denoised frame has no return (holes insulate the filter).
    range_sigma : (H, W) array_like or float
        The sensor noise sigmas the frame was denoised with (they set the
        edge-stopping scale; see `anisotropic_diffusion`).
    iterations, step, conduction
        As given to `anisotropic_diffusion` for the frame.

    Returns
    -------
    (H, W) float32
        Diffused minus original range, metres (positive: the filter
        lengthens the range); NaN where ``model_range`` is NaN.

    Examples
    --------
    A wall seen obliquely at 1 m (the SR-3000 focal length, 200 pixels): the
    filter lengthens the noise-free ranges by a fraction of a millimetre.

    >>> import numpy as np
    >>> rows, columns = np.mgrid[-72:72, -88:88] / 200.0
    >>> rays = np.dstack([columns, rows, np.ones_like(rows)])
    >>> rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    >>> normal = np.array([0.6, 0.0, -0.8])  # facing the sensor, 37 degrees off the view axis
    >>> wall = (1.0 / -(rays @ normal)).astype(np.float32)
    >>> bias = diffusion_bias(wall, range_sigma=0.01)
    >>> bool(0 < np.median(bias) < 1e-3)
    True
    """
    model_range = check_range_image(model_range)
    smoothed = anisotropic_diffusion(model_range, iterations=iterations, step=step, conduction=conduction,
                                     range_sigma=range_sigma)
    return smoothed - model_range


def remove_diffusion_bias(
    smooth: ArrayLike,
    rays: ArrayLike,
    labels: ArrayLike,
    planes: ArrayLike,
    *,
    range_sigma: ArrayLike,
    iterations: int = 10,
    step: float | None = None,
    conduction: Conduction = "exponential",
) -> tuple[np.ndarray, np.ndarray]:
    """Take the bias of diffusion (`diffusion_bias`) out of a denoised frame's planar segments.

    The noise-free model of the frame is each segmented pixel's range on its
    segment's plane (``-d / (n . ray)``), and the denoised range itself where
    a pixel has no segment or lies farther from its plane than three sensor
    sigmas (a crease, a stray pixel: the plane does not model it). The
    filter's effect on that model is subtracted from the segmented pixels.

    Parameters
    ----------
    smooth : (H, W) array_like
        The denoised range, metres, NaN where there is none.
    rays : (H, W, 3) array_like
        Unit viewing rays.
    labels : (H, W) int array_like
        Segment of each pixel, 0 for none (`rangesurf.segment.Segmentation`).
    planes : (K + 1, 4) array_like
        ``(nx, ny, nz, d)`` per segment in the sensor frame, ``n . p + d = 0``;
        row 0 unused.
    range_sigma : (H, W) array_like
        The sensor noise sigmas the frame was denoised with, finite and > 0
        wherever ``smooth`` is.
    iterations, step, conduction
        As the frame was denoised with (`anisotropic_diffusion`).

    Returns
    -------
    points : (H, W, 3) float32
        Sensor-frame points ``ray * range`` of ``smooth`` less the bias on
        segmented pixels, of ``smooth`` as given elsewhere (NaN where it is).
    residuals : (K + 1,) float64
        Per segment, the standard deviation (metres) of its corrected points'
        signed distances from its plane: the noise denoising left, now
        without the bias, which varies over a segment (their mean is an
        offset of the plane, which the bias shifted, not noise). NaN for
        row 0 and segments without points.

    Examples
    --------
    An oblique wall 1 m away, seen by an SR-3000-like camera (focal length
    200 pixels): denoising moves even its noise-free ranges (most at the
    insulating image borders), and the correction puts them back.

    >>> import numpy as np
    >>> rows, columns = np.mgrid[-72:72, -88:88] / 200.0
    >>> rays = np.dstack([columns, rows, np.ones_like(rows)])
    >>> rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    >>> plane = np.array([[np.nan] * 4, [0.6, 0.0, -0.8, 1.0]])
    >>> wall = (1.0 / -(rays @ plane[1, :3])).astype(np.float32)
    >>> sigma = np.full(wall.shape, 0.01)
    >>> smooth = anisotropic_diffusion(wall, range_sigma=sigma)
    >>> bool(np.abs(smooth - wall).max() > 1e-3)
    True
    >>> points, residuals = remove_diffusion_bias(smooth, rays, np.ones(wall.shape, int), plane, range_sigma=sigma)
    >>> bool(np.abs(np.linalg.norm(points, axis=-1) - wall).max() < 1e-5), bool(residuals[1] < 1e-5)
    (True, True)
    """
    smooth = check_range_image(smooth, "denoised range image")
    shape = smooth.shape
    # The pipeline's float32 rays and int32 labels go to the kernels as they are (no per-frame copies).
    rays = np.asarray(rays)
    rays = np.ascontiguousarray(rays, rays.dtype if rays.dtype in (np.float32, np.float64) else np.float64)
    labels = np.asarray(labels)
    if labels.dtype.kind not in "iu":
        raise ValueError(f"labels must be integers, got dtype {labels.dtype}")
    labels = np.ascontiguousarray(labels)
    planes = np.ascontiguousarray(planes, np.float64)
    sigma = np.ascontiguousarray(range_sigma, np.float64)
    if rays.shape != shape + (3,):
        raise ValueError(f"rays must have shape {shape + (3,)}, got {rays.shape}")
    if labels.shape != shape or sigma.shape != shape:
        raise ValueError(f"labels and range_sigma must have the range image's shape {shape}, got {labels.shape} "
                         f"and {sigma.shape}")
    if planes.ndim != 2 or planes.shape[1] != 4 or labels.size and not 0 <= labels.min() <= labels.max() < len(planes):
        raise ValueError(f"planes must be (K + 1, 4) with a row for every label, got shape {planes.shape} for "
                         f"labels up to {labels.max() if labels.size else 0}")
    model = _plane_model_kernel(smooth, rays, labels, planes, sigma)
    bias = diffusion_bias(model, range_sigma=sigma, iterations=iterations, step=step, conduction=conduction)
    return _subtract_bias_kernel(smooth, bias, rays, labels, planes)


@numba.njit(**_EXACT_JIT)
def _plane_model_kernel(smooth, rays, labels, planes, sigma):  # pragma: no cover - compiled
    """`remove_diffusion_bias`'s noise-free model: the plane's range on its pixels, ``smooth`` elsewhere."""
    height, width = smooth.shape
    model = np.empty((height, width), np.float32)
    for i in range(height):
        for j in range(width):
            value = smooth[i, j]
            label = labels[i, j]
            if label > 0 and value == value:
                cosine = rays[i, j, 0] * planes[label, 0] + rays[i, j, 1] * planes[label, 1] + rays[i, j, 2] * planes[label, 2]
                on_plane = -planes[label, 3] / cosine
                if abs(on_plane - value) <= 3.0 * sigma[i, j]:
                    value = on_plane
            model[i, j] = value
    return model


@numba.njit(**_EXACT_JIT)
def _subtract_bias_kernel(smooth, bias, rays, labels, planes):  # pragma: no cover - compiled
    """The points of ``smooth - bias`` (segmented pixels) or ``smooth`` (others), and the spread of the
    corrected points about their planes; one pass, so that the pipeline needs no second one for its points."""
    height, width = smooth.shape
    size = planes.shape[0]
    points = np.empty((height, width, 3), np.float32)
    count = np.zeros(size)
    total = np.zeros(size)
    squares = np.zeros(size)
    for i in range(height):
        # Sums over a run of pixels of one segment are kept in registers and added to the segment's
        # totals when the run ends (adding into the arrays pixel by pixel chains every add to the last).
        run_label, run_count, run_total, run_squares = 0, 0.0, 0.0, 0.0
        for j in range(width):
            value = smooth[i, j]
            label = labels[i, j]
            correction = bias[i, j]
            if label > 0 and correction == correction:
                value -= correction
                distance = value * (rays[i, j, 0] * planes[label, 0] + rays[i, j, 1] * planes[label, 1]
                                    + rays[i, j, 2] * planes[label, 2]) + planes[label, 3]
                if distance == distance:
                    if label != run_label:
                        count[run_label] += run_count
                        total[run_label] += run_total
                        squares[run_label] += run_squares
                        run_label, run_count, run_total, run_squares = label, 0.0, 0.0, 0.0
                    run_count += 1.0
                    run_total += distance
                    run_squares += distance * distance
            points[i, j, 0] = rays[i, j, 0] * value
            points[i, j, 1] = rays[i, j, 1] * value
            points[i, j, 2] = rays[i, j, 2] * value
        count[run_label] += run_count
        total[run_label] += run_total
        squares[run_label] += run_squares
    residuals = np.full(size, np.nan)
    for label in range(1, size):
        if count[label] > 0:
            mean = total[label] / count[label]
            residuals[label] = np.sqrt(max(squares[label] / count[label] - mean * mean, 0.0))
    return points, residuals


def _remove_diffusion_bias_reference(smooth, rays, labels, planes, sigma, **settings):
    """`remove_diffusion_bias` in plain NumPy (what the kernels compute)."""
    smooth = np.asarray(smooth, np.float32)
    plane = np.asarray(planes, np.float64)[labels]
    with np.errstate(divide="ignore", invalid="ignore"):
        cosine = np.einsum("ijk,ijk->ij", np.asarray(rays, np.float64), plane[..., :3])
        on_plane = -plane[..., 3] / cosine
        modelled = (labels > 0) & (np.abs(on_plane - smooth) <= 3.0 * sigma)
    model = np.where(modelled, on_plane, smooth).astype(np.float32)
    bias = diffusion_bias(model, range_sigma=sigma, **settings)
    segmented = (labels > 0) & np.isfinite(bias)
    corrected = np.where(segmented, smooth - bias, smooth).astype(np.float32)
    distance = corrected.astype(np.float64) * cosine + plane[..., 3]
    counted = segmented & np.isfinite(distance)
    residuals = np.full(len(planes), np.nan)
    for label in np.unique(labels[counted]):
        residuals[label] = np.std(distance[counted & (labels == label)])
    return (np.asarray(rays, np.float32) * corrected[..., None]).astype(np.float32), residuals


@dataclass(frozen=True)
class DiffusionPreset:
    """A named setting of `anisotropic_diffusion`, applied ``passes`` times.

    Parameters
    ----------
    name : str
        Short identifier.
    iterations, kappa, step, conduction, mode
        Keyword arguments of `anisotropic_diffusion`.
    passes : int
        How many times the filter runs on its own output (each pass of
        ``"thesis"`` mode normalises its input to 0-255 again).
    description : str
        Where the setting comes from.

    Examples
    --------
    >>> import numpy as np
    >>> from rangesurf.denoise import THESIS_PRESETS
    >>> rng = np.random.default_rng(1)
    >>> step = np.where(np.arange(40) < 20, 1.0, 2.0) * np.ones((30, 1))
    >>> noisy = (step + rng.normal(0.0, 0.01, step.shape)).astype(np.float32)
    >>> smooth = THESIS_PRESETS["edges"].apply(noisy)
    >>> bool(np.std(smooth - step) < 0.5 * np.std(noisy - step))
    True
    >>> THESIS_PRESETS["canny"].passes, THESIS_PRESETS["canny"].step
    (3, 0.15)
    """

    name: str
    iterations: int
    kappa: float | None
    step: float
    conduction: Conduction = "exponential"
    mode: Mode = "thesis"
    passes: int = 1
    description: str = ""

    def __post_init__(self) -> None:
        if not (isinstance(self.passes, int) and self.passes >= 1):
            raise ValueError(f"preset {self.name!r}: passes must be an integer >= 1, got {self.passes!r}")
        _check_iterations(self.iterations)
        _check_step(self.step)
        _check_conduction(self.conduction)
        if self.kappa is not None:
            _check_kappa(self.kappa)
        _check_mode(self.mode)

    def apply(self, range_image: ArrayLike) -> np.ndarray:
        """Run the preset on a ``(H, W)`` range image (metres, NaN = no return); returns ``(H, W)`` float32."""
        result = range_image
        for _ in range(self.passes):
            result = anisotropic_diffusion(
                result, iterations=self.iterations, kappa=self.kappa, step=self.step,
                conduction=self.conduction, mode=self.mode,
            )
        return result


# --------------------------------------------------------------------------
# Input checks.
# --------------------------------------------------------------------------


def _check_iterations(iterations: int) -> int:
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)):
        raise ValueError(f"iterations must be an integer, got {iterations!r}")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    return int(iterations)


def _check_step(step: float) -> float:
    step = float(step)
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"step must be > 0, got {step}")
    if step > MAX_STABLE_STEP:
        raise ValueError(
            f"step must be <= {MAX_STABLE_STEP} for the explicit four-neighbour scheme to be stable, got {step}; "
            "use more iterations with a smaller step"
        )
    return step


def _check_kappa(kappa: float) -> float:
    kappa = float(kappa)
    if not (math.isfinite(kappa) and kappa > 0):
        raise ValueError(f"kappa must be finite and > 0, got {kappa}")
    return kappa


def _check_mode(mode: str) -> None:
    if mode not in ("metric", "thesis"):
        raise ValueError(f"mode must be 'metric' or 'thesis', got {mode!r}")


def _check_conduction(conduction: str) -> int:
    try:
        return _CONDUCTION_CODES[conduction]
    except (KeyError, TypeError):
        raise ValueError(f"conduction must be one of {', '.join(CONDUCTIONS)}; got {conduction!r}") from None


# --------------------------------------------------------------------------
# Noise scale.
# --------------------------------------------------------------------------


def _difference_sigma(image: np.ndarray) -> float:
    """Robust standard deviation of neighbour differences: ``1.4826 * MAD``, metres.

    Black et al. write sigma_e = 1.4826 MAD(grad I); on signed differences
    (used here) it is a consistent estimate of the standard deviation of the
    noise of a difference, the quantity a sensor noise model predicts as
    ``sqrt(sigma_p**2 + sigma_q**2)``; differences across edges are a
    minority and do not move it. Frames with more than ``_NOISE_SAMPLE``
    neighbour pairs use the pairs of every k-th row (evenly spread, about
    ``_NOISE_SAMPLE`` of them: about 1 % standard error). 0 when there are no
    valid pairs.
    """
    height, width = image.shape
    pairs = 2 * height * width
    row_stride = max(1, -(-pairs // _NOISE_SAMPLE))
    return _MAD_TO_SIGMA * float(_median_absolute_deviation(image, row_stride))


@numba.njit(**_EXACT_JIT)
def _median_absolute_deviation(image, row_stride):  # pragma: no cover - compiled
    """MAD of the valid east and south differences of rows ``0, row_stride, ...``; 0 if there are none."""
    height, width = image.shape
    sample = np.empty(2 * width * ((height + row_stride - 1) // row_stride), np.float32)
    count = 0
    for i in range(0, height, row_stride):
        for j in range(width - 1):
            delta = image[i, j + 1] - image[i, j]
            if delta == delta:
                sample[count] = delta
                count += 1
        if i + 1 < height:
            for j in range(width):
                delta = image[i + 1, j] - image[i, j]
                if delta == delta:
                    sample[count] = delta
                    count += 1
    if count == 0:
        return np.float32(0.0)
    differences = sample[:count]
    median = np.median(differences)
    return np.median(np.abs(differences - median))


def _pair_scales(
    image: np.ndarray, range_sigma: ArrayLike, multiple: float, code: int
) -> tuple[np.ndarray, np.ndarray]:
    """The kernel's per-pair scales (`_pair_scales_kernel`) from per-pixel sigmas, checked."""
    sigma = np.asarray(range_sigma)
    if sigma.shape != image.shape:
        raise ValueError(
            f"range_sigma must be a number or have the range image's shape {image.shape}, got shape {sigma.shape}"
        )
    if sigma.dtype.kind not in "iuf":
        raise ValueError(f"range_sigma must be real numbers, got dtype {sigma.dtype}")
    sigma = np.ascontiguousarray(sigma, dtype=np.float64)
    scale_east, scale_south, n_bad = _pair_scales_kernel(image, sigma, _conduction_scale(code) / multiple)
    if n_bad:
        raise ValueError(f"range_sigma must be finite and > 0 wherever there is a return; {n_bad} pixels are not")
    return scale_east, scale_south


# --------------------------------------------------------------------------
# Numba kernels.
# --------------------------------------------------------------------------
#
# The kernel diffuses a scaled copy in which kappa is 1, so that the
# conduction needs one multiply for (delta/kappa)**2. For the exponential it
# scales by sqrt(log2 e) / kappa as well and evaluates 2**-(u) with the
# exponent split into an integer (added to the float's exponent bits) and a
# fraction in [-0.5, 0.5] (a degree-4 polynomial, relative error 2.6e-6):
# written this way LLVM vectorises the whole flux. The copy is padded with
# NaN (a row below, columns to a whole number of vectors plus one vector,
# rows 64-byte aligned) so that every pixel has an east and a south
# neighbour, the loops have no border cases or scalar remainders, and the
# compiler's overlap checks see only the array itself. The result is
# returned as input + change / scale, so that pixels that do not move stay
# bit-identical.

_SQRT_LOG2E = math.sqrt(1.0 / math.log(2.0))
# Near-minimax fit of 2**f on [-0.5, 0.5], maximum relative error 2.6e-6.
_P0, _P1, _P2, _P3, _P4 = (np.float32(c) for c in (0.99999926, 0.69312182, 0.24024747, 0.05591785, 0.00957001))
# 1.5 * 2**23: adding it rounds a float32 of magnitude < 2**22 to an integer
# held in the low mantissa bits.
_ROUNDING = np.float32(12582912.0)
# Beyond this u = (delta/kappa)**2 * log2(e), 2**-u < 1e-30 counts as 0;
# below it the exponent arithmetic stays in normal floats.
_LARGEST_EXPONENT = np.float32(100.0)
_LARGEST_EXPONENT_BITS = np.uint32(_LARGEST_EXPONENT.view(np.uint32))
# float32 lanes of an AVX-512 register: rows are padded to a multiple of it.
_VECTOR = 16
_SQRT2 = math.sqrt(2.0)
# Largest magnitude of a scaled value: differences of two stay finite.
_LARGEST_SCALED = np.float32(1e37)


@intrinsic
def _float_bits(typingctx, value):  # pragma: no cover - compiled
    """The bits of a float32 as an int32 (a no-op reinterpretation)."""
    if value != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.int32(types.float32), codegen


@intrinsic
def _float_from_bits(typingctx, bits):  # pragma: no cover - compiled
    """The float32 with the given low 32 bits (a no-op reinterpretation)."""
    if not isinstance(bits, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        value = args[0]
        if bits.bitwidth > 32:
            value = builder.trunc(value, ir.IntType(32))
        elif bits.bitwidth < 32:
            value = builder.sext(value, ir.IntType(32))
        return builder.bitcast(value, ir.FloatType())

    return types.float32(bits), codegen


@numba.njit(inline="always", **_JIT)
def _exp2_negative(u):  # pragma: no cover - compiled
    """``2 ** -u`` for float32 ``0 <= u <= 100`` (relative error < 3e-6; garbage outside)."""
    rounded = _ROUNDING - u  # low mantissa bits hold -round(u)
    f = (_ROUNDING - rounded) - u  # round(u) - u, in [-0.5, 0.5]
    p = _P4
    p = p * f + _P3
    p = p * f + _P2
    p = p * f + _P1
    p = p * f + _P0
    # Shifting the rounded float's bits by 23 leaves exactly -round(u) << 23.
    return _float_from_bits(_float_bits(p) + (_float_bits(rounded) << np.int32(23)))


@numba.njit(inline="always", **_JIT)
def _flux(delta, scaled, code):  # pragma: no cover - compiled
    """``g * delta`` for a difference ``delta`` whose scaled value ``scaled`` has kappa 1.

    For the exponential ``scaled`` includes sqrt(log2 e). A difference with
    a NaN end is NaN, and each branch's comparison is false for NaN: no flux
    to or from a pixel without a return.
    """
    u = scaled * scaled
    if code == 0:
        # Also zero beyond u = 100 (g < 1e-30), where 2**-u is not evaluated.
        # For u >= 0 the bits as unsigned integers order like the floats, and
        # every NaN, of either sign, lies above: an integer comparison (a few
        # per cent faster than the float one).
        below = np.uint32(_float_bits(u)) <= _LARGEST_EXPONENT_BITS
        return _exp2_negative(u) * delta if below else np.float32(0.0)
    if code == 1:
        return delta / (np.float32(1.0) + u) if delta == delta else np.float32(0.0)
    w = np.float32(1.0) - u
    return np.float32(0.5) * w * w * delta if u <= np.float32(1.0) else np.float32(0.0)


@numba.njit(inline="always", **_JIT)
def _iterate(source, target, east, north, step, code):  # pragma: no cover - compiled
    """One explicit step on a padded image (see `_padded_work`) whose kappa is 1."""
    height = source.shape[0] - 1
    width = source.shape[1] - _VECTOR
    for j in range(width):
        north[j] = np.float32(0.0)
    for i in range(height):
        for j in range(width):
            delta = source[i, j + 1] - source[i, j]
            east[j + 1] = _flux(delta, delta, code)
        for j in range(width):
            delta = source[i + 1, j] - source[i, j]
            south = _flux(delta, delta, code)
            target[i, j] = source[i, j] + step * ((east[j + 1] - east[j]) + (south - north[j]))
            north[j] = south


@numba.njit(inline="always", **_JIT)
def _iterate_pairwise(source, target, scale_east, scale_south, east, north, step, code):  # pragma: no cover - compiled
    """One explicit step with a scale ``1 / kappa`` per neighbour pair (``(H, L)``, see `_padded_work`)."""
    height = source.shape[0] - 1
    width = source.shape[1] - _VECTOR
    for j in range(width):
        north[j] = np.float32(0.0)
    for i in range(height):
        for j in range(width):
            delta = source[i, j + 1] - source[i, j]
            east[j + 1] = _flux(delta, delta * scale_east[i, j], code)
        for j in range(width):
            delta = source[i + 1, j] - source[i, j]
            south = _flux(delta, delta * scale_south[i, j], code)
            target[i, j] = source[i, j] + step * ((east[j + 1] - east[j]) + (south - north[j]))
            north[j] = south


def _padded_width(width: int) -> int:
    """Row length the kernels loop over: a multiple of 16 float32 (one AVX-512 register), >= ``width``."""
    return -(-width // _VECTOR) * _VECTOR


@numba.njit(**_EXACT_JIT)
def _padded_work(image, offset, scale):  # pragma: no cover - compiled
    """Two ``(H + 1, L + 16)`` float32 buffers: ``(image - offset) * scale`` padded with NaN.

    ``L`` is the width rounded up to whole vectors (`_padded_width`), and
    rows start on 64-byte boundaries. The NaN row and columns give every
    pixel an east and a south neighbour that conducts nothing, so the loops
    over ``L`` columns need no border cases or remainders. Also returns the
    number of Inf pixels and of finite pixels scaled beyond 1e37 (too close
    to float32 overflow for their differences).
    """
    height, width = image.shape
    columns = (width + _VECTOR - 1) // _VECTOR * _VECTOR + _VECTOR
    size = 2 * (height + 1) * columns
    flat = np.empty(size + _VECTOR, np.float32)
    start = (-(flat.ctypes.data // 4)) % _VECTOR
    work = flat[start : start + size].reshape((2, height + 1, columns))
    for k in range(2):
        for i in range(height + 1):
            for j in range(width if i < height else 0, columns):
                work[k, i, j] = np.nan
    n_infinite = 0
    n_too_large = 0
    for i in range(height):
        for j in range(width):
            value = image[i, j]
            scaled = (value - offset) * scale
            work[0, i, j] = scaled
            finite = abs(value) < np.inf
            n_infinite += (abs(value) == np.inf)
            n_too_large += (abs(scaled) > _LARGEST_SCALED) & finite
    return work, n_infinite, n_too_large


@numba.njit(**_EXACT_JIT)
def _result(image, work, current, offset, scale):  # pragma: no cover - compiled
    height, width = image.shape
    result = np.empty((height, width), np.float32)
    inverse = np.float32(1.0) / scale
    for i in range(height):
        for j in range(width):
            change = work[current, i, j] - (image[i, j] - offset) * scale
            result[i, j] = image[i, j] + change * inverse
    return result


@numba.njit(**_JIT)
def _diffuse_kernel(image, offset, scale, step, iterations, code):  # pragma: no cover - compiled
    """``(result, number of Inf pixels, number of pixels too large once scaled)``; no result if either."""
    work, n_infinite, n_too_large = _padded_work(image, offset, scale)
    if n_infinite or n_too_large:
        return np.empty((0, 0), np.float32), n_infinite, n_too_large
    width = work.shape[2] - _VECTOR
    east = np.zeros(width + 1, np.float32)
    north = np.zeros(width, np.float32)
    current = 0
    for _ in range(iterations):
        # Literal codes, so that each conduction gets its own vectorised loops.
        if code == 0:
            _iterate(work[current], work[1 - current], east, north, step, 0)
        elif code == 1:
            _iterate(work[current], work[1 - current], east, north, step, 1)
        else:
            _iterate(work[current], work[1 - current], east, north, step, 2)
        current = 1 - current
    return _result(image, work, current, offset, scale), 0, 0


@numba.njit(**_EXACT_JIT)
def _pair_scales_kernel(image, sigma, factor):  # pragma: no cover - compiled
    """``factor / (sqrt(2) * min(sigma_p, sigma_q))`` per east and south pair, ``(H, L)`` float32 each.

    0 for pairs with a NaN end (their flux is zeroed anyway); saturated at
    the largest float32 rather than Inf, whose product with a zero
    difference would be NaN. Also returns the number of pixels with a return
    whose sigma is not finite and > 0.
    """
    height, width = image.shape
    columns = (width + _VECTOR - 1) // _VECTOR * _VECTOR
    scale_east = np.zeros((height, columns), np.float32)
    scale_south = np.zeros((height, columns), np.float32)
    largest = np.finfo(np.float32).max
    n_bad = 0
    # Row by row, in branch-free loops the compiler vectorises (a branch per pixel took three times as long).
    # With a bad sigma anywhere the scales are not used (the caller raises), so only pairs of two readings
    # need their scale right.
    for i in range(height):
        here, noise = image[i], sigma[i]
        for j in range(width):
            n_bad += np.int64((here[j] == here[j]) & ~((noise[j] > 0) & (noise[j] < np.inf)))
        east = scale_east[i]
        for j in range(width - 1):
            value = min(factor / (_SQRT2 * min(noise[j], noise[j + 1])), largest)
            east[j] = value if (here[j] == here[j]) & (here[j + 1] == here[j + 1]) else np.float32(0.0)
        if i + 1 < height:
            below, noise_below, south = image[i + 1], sigma[i + 1], scale_south[i]
            for j in range(width):
                value = min(factor / (_SQRT2 * min(noise[j], noise_below[j])), largest)
                south[j] = value if (here[j] == here[j]) & (below[j] == below[j]) else np.float32(0.0)
    return scale_east, scale_south, n_bad


@numba.njit(**_JIT)
def _diffuse_pairwise_kernel(image, scale_east, scale_south, step, iterations, code):  # pragma: no cover - compiled
    """Like `_diffuse_kernel`, in metres with per-pair scales (`_pair_scales_kernel`)."""
    work, n_infinite, n_too_large = _padded_work(image, np.float32(0.0), np.float32(1.0))
    if n_infinite or n_too_large:
        return np.empty((0, 0), np.float32), n_infinite, n_too_large
    width = work.shape[2] - _VECTOR
    east = np.zeros(width + 1, np.float32)
    north = np.zeros(width, np.float32)
    current = 0
    for _ in range(iterations):
        if code == 0:
            _iterate_pairwise(work[current], work[1 - current], scale_east, scale_south, east, north, step, 0)
        elif code == 1:
            _iterate_pairwise(work[current], work[1 - current], scale_east, scale_south, east, north, step, 1)
        else:
            _iterate_pairwise(work[current], work[1 - current], scale_east, scale_south, east, north, step, 2)
        current = 1 - current
    return _result(image, work, current, np.float32(0.0), np.float32(1.0)), 0, 0


@numba.njit(**_JIT)
def _scan(image):  # pragma: no cover - compiled
    """``(number of non-NaN pixels, their min, their max, number of Inf)`` of a float32 image."""
    height, width = image.shape
    # Per-column accumulators: the row loop has no loop-carried dependency and vectorises.
    counts = np.zeros(width, np.int32)
    infinite = np.zeros(width, np.int32)
    lowest = np.full(width, np.inf, np.float32)
    highest = np.full(width, -np.inf, np.float32)
    for i in range(height):
        for j in range(width):
            value = image[i, j]
            counts[j] += np.int32(value == value)
            infinite[j] += np.int32(abs(value) == np.float32(np.inf))
            # Comparisons with NaN are false: NaN never becomes the min or max.
            lowest[j] = value if value < lowest[j] else lowest[j]
            highest[j] = value if value > highest[j] else highest[j]
    if width == 0:
        return 0, np.float32(np.inf), np.float32(-np.inf), 0
    return counts.sum(), lowest.min(), highest.max(), infinite.sum()


def _valid_extent(image: np.ndarray) -> tuple[int, float, float]:
    """``(number of pixels with a return, their min, their max)``; raises if the frame holds Inf."""
    n_valid, lowest, highest, n_infinite = _scan(image)
    _raise_if_infinite(n_infinite)
    return int(n_valid), float(lowest), float(highest)


def _raise_if_infinite(n_infinite: int) -> None:
    if n_infinite:
        raise ValueError(f"range image contains {n_infinite} Inf values; mark missing returns with NaN")


def _checked(result: np.ndarray, n_infinite: int, n_too_large: int, *, kappa: float | None) -> np.ndarray:
    """A kernel's result, or the error its counts of bad pixels stand for."""
    _raise_if_infinite(n_infinite)
    if n_too_large:
        raise ValueError(f"kappa {kappa} is too small for these range values: (value / kappa) overflows float32")
    return result


def _conduction_scale(code: int) -> float:
    """Extra scale of the kernel's differences: sqrt(log2 e) turns exp into 2**."""
    return _SQRT_LOG2E if code == 0 else 1.0


def _diffuse(
    image: np.ndarray, offset: float, gain: float, kappa: float, step: float, iterations: int, code: int
) -> np.ndarray:
    """Diffuse ``(image - offset) * gain`` with a uniform ``kappa``; result in the units of ``image``.

    ``image`` is ``(H, W)`` float32 C-contiguous; ``code`` indexes `CONDUCTIONS`.
    """
    scale = gain * _conduction_scale(code) / kappa
    # The kernel works on float32 values divided by kappa: the scale must be
    # a normal float32 (and the scaled values finite, which the kernel checks).
    if not scale >= 1e-37:
        raise ValueError(f"kappa {kappa} is too large: {kappa:g} / {gain:g} does not fit a float32 scale")
    if scale > 1e37:
        raise ValueError(f"kappa {kappa} is too small: {gain:g} / {kappa:g} does not fit a float32 scale")
    outcome = _diffuse_kernel(image, np.float32(offset), np.float32(scale), np.float32(step), iterations, code)
    return _checked(*outcome, kappa=kappa)


def _diffuse_pairwise(
    image: np.ndarray, kappa_east: np.ndarray, kappa_south: np.ndarray, step: float, iterations: int, code: int
) -> np.ndarray:
    """Diffuse metres with ``kappa`` per neighbour pair: east ``(H, W - 1)``, south ``(H - 1, W)`` (NaN: no pair).

    Any per-pair kappa, for testing `_diffuse_pairwise_kernel`; `anisotropic_diffusion` builds
    its scales from per-pixel sigmas in `_pair_scales` instead.
    """
    height, width = image.shape
    extra = _conduction_scale(code)
    scale_east = np.zeros((height, _padded_width(width)), np.float32)
    scale_south = np.zeros((height, _padded_width(width)), np.float32)
    # A pair with a NaN end gets scale 0 (its flux is zeroed anyway); a tiny
    # kappa saturates at the largest float32 (no conduction), not at Inf,
    # whose product with a zero difference would be NaN.
    largest = float(np.finfo(np.float32).max)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        scale_east[:, : width - 1] = np.nan_to_num(np.minimum(extra / kappa_east, largest), nan=0.0)
        scale_south[: height - 1, :width] = np.nan_to_num(np.minimum(extra / kappa_south, largest), nan=0.0)
    outcome = _diffuse_pairwise_kernel(image, scale_east, scale_south, np.float32(step), iterations, code)
    return _checked(*outcome, kappa=None)


# --------------------------------------------------------------------------
# Plain NumPy reference (what the kernels compute, written directly).
# --------------------------------------------------------------------------


def _pair_kappas_reference(image: np.ndarray, sigma: np.ndarray, multiple: float) -> tuple[np.ndarray, np.ndarray]:
    """``multiple * sqrt(2) * min(sigma_p, sigma_q)`` per east ``(H, W - 1)`` and south ``(H - 1, W)`` pair.

    NaN for pairs with a hole at either end.
    """
    sigma = np.where(np.isnan(image), np.nan, np.asarray(sigma, np.float64))
    return (
        multiple * math.sqrt(2.0) * np.minimum(sigma[:, :-1], sigma[:, 1:]),
        multiple * math.sqrt(2.0) * np.minimum(sigma[:-1, :], sigma[1:, :]),
    )


def _conductance_reference(ratio: np.ndarray, conduction: str) -> np.ndarray:
    squared = ratio * ratio
    if conduction == "exponential":
        return np.exp(-squared)
    if conduction == "rational":
        return 1.0 / (1.0 + squared)
    return np.where(squared <= 1.0, 0.5 * (1.0 - squared) ** 2, 0.0)


def _diffuse_reference(
    image: np.ndarray,
    kappa: float | tuple[np.ndarray, np.ndarray],
    step: float,
    iterations: int,
    conduction: str,
    *,
    offset: float = 0.0,
    gain: float = 1.0,
) -> np.ndarray:
    """Perona-Malik diffusion of ``(image - offset) * gain`` in float32 NumPy, result in the units of ``image``.

    ``kappa`` is a number or the pair ``(kappa_east (H, W - 1), kappa_south (H - 1, W))``.
    """
    kappa_east, kappa_south = kappa if isinstance(kappa, tuple) else (kappa, kappa)
    work = ((np.asarray(image, np.float32) - np.float32(offset)) * np.float32(gain)).astype(np.float32)
    kappa_east = np.asarray(kappa_east, np.float32)
    kappa_south = np.asarray(kappa_south, np.float32)
    with np.errstate(invalid="ignore"):
        for _ in range(iterations):
            east = np.diff(work, axis=1)
            south = np.diff(work, axis=0)
            flux_east = np.where(np.isnan(east), 0, _conductance_reference(east / kappa_east, conduction) * east)
            flux_south = np.where(np.isnan(south), 0, _conductance_reference(south / kappa_south, conduction) * south)
            change = np.zeros_like(work)
            change[:, :-1] += flux_east
            change[:, 1:] -= flux_east
            change[:-1, :] += flux_south
            change[1:, :] -= flux_south
            work = (work + np.float32(step) * change).astype(np.float32)
    return (work / np.float32(gain) + np.float32(offset)).astype(np.float32)


# --------------------------------------------------------------------------
# The thesis's settings.
# --------------------------------------------------------------------------

#: The thesis's two settings (Section 3.1). ``"edges"``: k = 20, lambda = 0.1,
#: exponential conduction, best before Prewitt, Sobel and Roberts edges.
#: ``"canny"``: k = 20, lambda = 0.3, run three times, best before Canny. A
#: step of 0.3 is beyond the explicit scheme's stability bound of 0.25 (it
#: leaves a checkerboard of about kappa grey levels on SR-3000 frames), so
#: the preset makes each of its steps as two stable steps of 0.15: the same
#: diffusion time, 3.0 per pass. The thesis does not give its iteration
#: count; both presets assume this module's default of 10 (20 half steps).
THESIS_PRESETS: Mapping[str, DiffusionPreset] = MappingProxyType({
    "edges": DiffusionPreset(
        name="edges", iterations=10, kappa=_THESIS_KAPPA, step=0.1,
        description="thesis Section 3.1: k=20, lambda=0.1, exponential (Prewitt, Sobel, Roberts)",
    ),
    "canny": DiffusionPreset(
        name="canny", iterations=20, kappa=_THESIS_KAPPA, step=0.15, passes=3,
        description="thesis Section 3.1: k=20, lambda=0.3 (as 2 x 0.15), exponential, three passes (Canny)",
    ),
})
