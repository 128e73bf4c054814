"""Edges of range images: detection, thesis clean-up, ground truth and scores.

Edge maps are the thesis's measure of a denoising filter (Sections 2.1 and
3.1): a filter is good when the edges of the filtered range image keep the
real surface boundaries and lose the false ones. This module provides

* `normalize_range` and `equalize_histogram`: the 0-255 grey-level image of
  a range image the thesis computes its edges on, and its histogram
  equalisation over the valid pixels only;
* `detect_edges`: Canny, Sobel, Prewitt and Roberts edges with automatic
  thresholds like MATLAB's ``edge``, which the thesis used, that invent no
  edge along the boundary of the invalid (NaN) pixels;
* `clean_edges`: the thesis's clean-up of an edge map (border clearing and
  single-pixel removal);
* `combined_edges`: the union of the cleaned edge maps of two filtering
  branches (thesis Figures 3.6 and 3.7);
* `true_depth_edges`: depth discontinuities of a true range image, such as
  `rangesurf.simulate.GroundTruth.range`;
* `edge_scores` and `edge_difference`: precision and recall of an edge map
  against a reference within a distance tolerance, and the thesis's
  difference between the edge maps of a raw and a filtered image.

Edge maps are ``(H, W) bool`` arrays, True on an edge pixel.

References
----------
.. [1] D. Cernea, "Graphical Methods For Online Surface Fitting On 3D Range
   Sensor Point Clouds", Sections 2.1 and 3.1 (``shared/reference/thesis.md``).
.. [2] J. Canny, "A computational approach to edge detection", IEEE
   Transactions on Pattern Analysis and Machine Intelligence 8(6), 679-698,
   1986.
.. [3] A. K. Cherri and M. A. Karim, "Optical symbolic substitution: edge
   detection using Prewitt, Sobel, and Roberts operators", Applied Optics
   28(21), 4644-4648, 1989.

Examples
--------
>>> import numpy as np
>>> from rangesurf.edges import detect_edges, edge_scores, true_depth_edges
>>> depth = np.full((40, 40), 3.0, np.float32)
>>> depth[10:30, 10:30] = 2.0                      # a box in front of a wall
>>> truth = true_depth_edges(depth)
>>> scores = edge_scores(detect_edges(depth, method="sobel"), truth, tolerance=1)
>>> bool(scores.precision == 1.0 and scores.recall > 0.9)
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from scipy import ndimage

from rangesurf._checks import check_range_image

__all__ = [
    "EDGE_METHODS",
    "EdgeScores",
    "EdgeDifference",
    "normalize_range",
    "equalize_histogram",
    "detect_edges",
    "clean_edges",
    "combined_edges",
    "true_depth_edges",
    "surface_boundaries",
    "crease_free_mask",
    "edge_scores",
    "edge_difference",
]

EDGE_METHODS = ("canny", "sobel", "prewitt", "roberts")

# MATLAB's ``edge`` defaults, which the thesis's experiments used.
_CANNY_SIGMA = math.sqrt(2.0)
_CANNY_NOT_EDGE_FRACTION = 0.7
_CANNY_LOW_RATIO = 0.4
_CANNY_HISTOGRAM_BINS = 64
_GRADIENT_THRESHOLD_SCALE = 4.0

# Gradient kernels scaled as MATLAB's ``edge`` scales them, so that a ramp of
# one grey level per pixel has a Sobel or Prewitt gradient of 1.
_SOBEL_X = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], np.float32) / 8
_PREWITT_X = np.array([[-1, 0, 1], [-1, 0, 1], [-1, 0, 1]], np.float32) / 6
_ROBERTS_MAIN = np.array([[1, 0], [0, -1]], np.float32) / 2
_ROBERTS_ANTI = np.array([[0, 1], [-1, 0]], np.float32) / 2

# Offsets of the 8 first-order neighbours and of the 16 second-order ones
# (the ring of the 5 x 5 window); the ring as 8 diametrically opposite pairs.
_NEIGHBOURS = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
_RING = [(dr, dc) for dr in range(-2, 3) for dc in range(-2, 3) if max(abs(dr), abs(dc)) == 2]
_OPPOSITE_PAIRS = [((dr, dc), (-dr, -dc)) for dr, dc in _RING if dr > 0 or (dr == 0 and dc > 0)]


# --------------------------------------------------------------------------
# Input checks.
# --------------------------------------------------------------------------


def _check_edge_map(edges: Any, name: str = "edge map") -> np.ndarray:
    array = np.asarray(edges)
    if array.ndim != 2:
        raise ValueError(f"{name} must be 2-D (H, W), got shape {array.shape}")
    if array.dtype != bool:
        raise ValueError(f"{name} must be a bool array (e.g. edges > 0), got dtype {array.dtype}")
    return array


def _check_same_shape(first: np.ndarray, second: np.ndarray, names: str) -> None:
    if first.shape != second.shape:
        raise ValueError(f"{names} must have the same shape, got {first.shape} and {second.shape}")


def _check_valid_range(valid_range: Any) -> tuple[float, float] | None:
    if valid_range is None:
        return None
    try:
        low, high = (float(value) for value in valid_range)
    except (TypeError, ValueError):
        raise ValueError(f"valid_range must be a pair (low, high), got {valid_range!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ValueError(f"valid_range must be finite with low < high, got ({low}, {high})")
    return low, high


def _check_non_negative(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return value


# --------------------------------------------------------------------------
# Grey-level images.
# --------------------------------------------------------------------------


def _grey_levels(image: np.ndarray, valid: np.ndarray, valid_range: tuple[float, float] | None) -> np.ndarray:
    """Float32 grey levels in [0, 255] (unrounded), 0 where invalid."""
    grey = np.zeros(image.shape, np.float32)
    if not valid.any():
        return grey
    values = image[valid].astype(np.float64)
    low, high = (values.min(), values.max()) if valid_range is None else valid_range
    if high > low:
        grey[valid] = (np.clip(values, low, high) - low) * (255.0 / (high - low))
    return grey


def normalize_range(range_image: np.ndarray, *, valid_range: tuple[float, float] | None = None) -> np.ndarray:
    """Map a range image linearly to 0-255 grey levels.

    The thesis computes its edges on this "normalized grayscale distance
    image": the nearest valid range becomes 0 (black), the farthest 255.

    Parameters
    ----------
    range_image : (H, W) float or integer array
        Range (any unit), NaN where there is no return.
    valid_range : (low, high), optional
        Range mapped to 0 and to 255; values outside are clipped. Default: the
        smallest and largest valid value of the image. Pass a fixed range
        (e.g. the sensor's ``(min_range, max_range)``) to compare grey levels
        across frames.

    Returns
    -------
    (H, W) uint8
        ``round(255 * (r - low) / (high - low))`` on valid pixels. Invalid
        (NaN) pixels are 0, like the nearest range: the grey image alone does
        not tell them apart, so keep ``np.isfinite(range_image)`` as the mask
        (`equalize_histogram` and `detect_edges` take it). A constant image
        (``low == high``) and an all-NaN image are all 0.

    Raises
    ------
    ValueError
        If the image is not 2-D, not real numeric, contains Inf, or
        ``valid_range`` is not a finite pair with ``low < high``.

    References
    ----------
    .. [1] Thesis Section 2.1: "the normalized mapping of the scanned distance
       to the color space (0-255 values for a color encoding of 1 byte per
       channel)".

    Examples
    --------
    >>> import numpy as np
    >>> normalize_range(np.array([[1.0, 2.0], [3.0, np.nan]]))
    array([[  0, 128],
           [255,   0]], dtype=uint8)
    """
    image = check_range_image(range_image, dtype=None)
    limits = _check_valid_range(valid_range)
    grey = _grey_levels(image, np.isfinite(image), limits)
    return np.rint(grey).astype(np.uint8)


def equalize_histogram(image: np.ndarray, *, mask: np.ndarray | None = None) -> np.ndarray:
    """Histogram-equalise a grey-level image over the pixels of a mask.

    The grey-level histogram of the masked pixels only is spread over 0-255,
    with OpenCV's mapping (``cv2.equalizeHist``, which has no mask):
    ``lut[v] = round(255 * (cdf(v) - cdf(v_min)) / (n - cdf(v_min)))`` where
    ``cdf`` counts masked pixels of level ``<= v``, ``v_min`` is the smallest
    masked level and ``n`` the number of masked pixels. Without a mask the
    result equals ``cv2.equalizeHist(image)``.

    Parameters
    ----------
    image : (H, W) uint8
        Grey levels, e.g. from `normalize_range`.
    mask : (H, W) bool, optional
        Pixels to equalise, e.g. ``np.isfinite(range_image)``; default all.

    Returns
    -------
    (H, W) uint8
        Equalised levels on masked pixels, 0 elsewhere. If all masked pixels
        share one level they keep it (as OpenCV does); an empty mask gives
        all 0.

    Raises
    ------
    ValueError
        If the image is not 2-D uint8 or the mask is not a bool array of the
        same shape.

    References
    ----------
    .. [1] L. G. Shapiro and G. C. Stockman, "Computer Vision", Prentice Hall,
       2001, Chapter 5 (the thesis's [51]).

    Examples
    --------
    >>> import numpy as np
    >>> depth = np.array([[1.0, 1.1], [1.2, np.nan]])
    >>> equalize_histogram(normalize_range(depth), mask=np.isfinite(depth))
    array([[  0, 128],
           [255,   0]], dtype=uint8)
    """
    grey = np.asarray(image)
    if grey.ndim != 2:
        raise ValueError(f"grey-level image must be 2-D (H, W), got shape {grey.shape}")
    if grey.dtype != np.uint8:
        raise ValueError(f"grey-level image must be uint8 (see normalize_range), got dtype {grey.dtype}")
    if mask is None:
        mask = np.ones(grey.shape, bool)
    else:
        mask = _check_edge_map(mask, "mask")
        _check_same_shape(grey, mask, "grey-level image and mask")
    out = np.zeros(grey.shape, np.uint8)
    values = grey[mask]
    if values.size == 0:
        return out
    counts = np.bincount(values, minlength=256)
    lowest = int(values.min())
    if counts[lowest] == values.size:
        out[mask] = lowest
        return out
    cdf = np.cumsum(counts)
    scale = 255.0 / (values.size - counts[lowest])
    # cdf(v) - cdf(v_min): the same sum OpenCV accumulates from v_min + 1 on.
    lut = np.clip(np.rint((cdf - counts[lowest]) * scale), 0, 255).astype(np.uint8)
    lut[:lowest] = 0
    out[mask] = lut[values]
    return out


# --------------------------------------------------------------------------
# Edge detection.
# --------------------------------------------------------------------------


def _fill_invalid(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Copy the nearest valid value into every invalid pixel (needs one valid pixel)."""
    if valid.all():
        return image
    _, (rows, cols) = ndimage.distance_transform_edt(~valid, return_indices=True)
    return image[rows, cols]


def _smooth(image: np.ndarray, sigma: float) -> np.ndarray:
    if sigma == 0:
        return image
    # MATLAB's edge uses a kernel of 8 sigma + 1 taps (odd).
    size = 2 * math.ceil(4 * sigma) + 1
    return cv2.GaussianBlur(image, (size, size), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REPLICATE)


def _gradients(image: np.ndarray, method: str) -> tuple[np.ndarray, np.ndarray]:
    """``(gx, gy)`` float32: derivative along columns and rows (grey levels per pixel)."""
    border = cv2.BORDER_REPLICATE
    if method in ("canny", "sobel"):
        return (
            cv2.filter2D(image, cv2.CV_32F, _SOBEL_X, borderType=border),
            cv2.filter2D(image, cv2.CV_32F, _SOBEL_X.T.copy(), borderType=border),
        )
    if method == "prewitt":
        return (
            cv2.filter2D(image, cv2.CV_32F, _PREWITT_X, borderType=border),
            cv2.filter2D(image, cv2.CV_32F, _PREWITT_X.T.copy(), borderType=border),
        )
    # Roberts: the two diagonal differences of the 2 x 2 window whose top-left
    # pixel is the output pixel (MATLAB's origin), turned into the derivatives
    # along columns and rows so that thinning can use them.
    main = cv2.filter2D(image, cv2.CV_32F, _ROBERTS_MAIN, anchor=(0, 0), borderType=border)
    anti = cv2.filter2D(image, cv2.CV_32F, _ROBERTS_ANTI, anchor=(0, 0), borderType=border)
    return anti - main, -(anti + main)


def _thin(magnitude_sq: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Local maxima of the magnitude across the dominant gradient axis (MATLAB's thinning)."""
    padded = np.pad(magnitude_sq, 1, mode="edge")
    centre = padded[1:-1, 1:-1]
    horizontal = (np.abs(gx) >= np.abs(gy)) & (centre > padded[1:-1, :-2]) & (centre >= padded[1:-1, 2:])
    vertical = (np.abs(gy) >= np.abs(gx)) & (centre > padded[:-2, 1:-1]) & (centre >= padded[2:, 1:-1])
    return horizontal | vertical


def _automatic_canny_threshold(magnitude: np.ndarray) -> float:
    """MATLAB's automatic high threshold of Canny (``edge``), from valid magnitudes.

    The magnitudes, divided by their maximum, go into a 64-bin histogram
    (MATLAB's ``imhist``: bin ``k`` centred on ``k / 63``); the threshold is
    ``(k + 1) / 64`` times the maximum for the first bin ``k`` (from 0) at
    which more than 70 % of the pixels have been counted. Rounding up to the
    bin keeps a plateau of equal magnitudes (a tilted plane) below the
    threshold, which the plain 70 % quantile would not.
    """
    largest = float(magnitude.max())
    if largest == 0:
        return 0.0
    bins = np.floor(magnitude / largest * (_CANNY_HISTOGRAM_BINS - 1) + 0.5).astype(np.intp)
    counts = np.cumsum(np.bincount(bins, minlength=_CANNY_HISTOGRAM_BINS))
    first = int(np.argmax(counts > _CANNY_NOT_EDGE_FRACTION * magnitude.size))
    return (first + 1) / _CANNY_HISTOGRAM_BINS * largest


def _canny(
    gx: np.ndarray, gy: np.ndarray, valid: np.ndarray, low: float | None, high: float | None
) -> np.ndarray:
    magnitude = np.hypot(gx, gy)
    largest = float(magnitude.max())
    if largest == 0:
        return np.zeros(gx.shape, bool)
    if high is None:
        high = _automatic_canny_threshold(magnitude[valid])
        low = _CANNY_LOW_RATIO * high if low is None else low
    elif low is None:
        low = _CANNY_LOW_RATIO * high
    if high >= largest:
        return np.zeros(gx.shape, bool)
    # cv2.Canny takes 16-bit derivatives: scale the largest magnitude to the
    # int16 limit (non-maximum suppression and hysteresis are OpenCV's).
    scale = 32767.0 / largest
    dx = np.rint(gx * scale).astype(np.int16)
    dy = np.rint(gy * scale).astype(np.int16)
    edges = cv2.Canny(dx, dy, low * scale, high * scale, L2gradient=True)
    return edges > 0


def detect_edges(
    range_image: np.ndarray,
    *,
    method: Literal["canny", "sobel", "prewitt", "roberts"] = "canny",
    threshold: float | None = None,
    low_threshold: float | None = None,
    high_threshold: float | None = None,
    sigma: float | None = None,
    thin: bool = True,
    normalize: bool = True,
    valid_range: tuple[float, float] | None = None,
    equalize: bool = False,
    invalid_as_edge: bool = False,
) -> np.ndarray:
    """Edge map of a range image (Canny, Sobel, Prewitt or Roberts).

    The image is mapped to grey levels (`normalize_range`, unrounded) and,
    optionally, histogram-equalised, as in the thesis; invalid pixels take
    the value of the nearest valid pixel so that the filters see no step at
    the boundary of a hole; then

    * ``"canny"``: Gaussian smoothing (``sigma``), Sobel derivatives,
      OpenCV's non-maximum suppression and hysteresis (`cv2.Canny` on the
      derivatives, L2 magnitude) between ``low_threshold`` and
      ``high_threshold``;
    * ``"sobel"``, ``"prewitt"``, ``"roberts"``: the gradient magnitude of
      the operator (scaled like MATLAB's: 1/8, 1/6, 1/2) above ``threshold``,
      thinned to local maxima across the edge when ``thin``.

    The filters replicate the image border, so the border itself is no
    step (but see `clean_edges` for the thesis's border clearing).

    Parameters
    ----------
    range_image : (H, W) float or integer array
        Range, NaN where there is no return; or any grey-level image (a
        filtered range image) with ``normalize=False``.
    method : {"canny", "sobel", "prewitt", "roberts"}
    threshold : float, optional
        Gradient-magnitude threshold of the Sobel, Prewitt and Roberts
        methods, in grey levels per pixel (image units per pixel with
        ``normalize=False``). Default, as MATLAB's ``edge``:
        ``sqrt(4 * mean(magnitude ** 2))`` over the valid pixels.
    low_threshold, high_threshold : float, optional
        Canny hysteresis thresholds, same units. Default, as MATLAB's
        ``edge``: ``high`` leaves 70 % of the valid pixels' magnitudes below
        it, read off a 64-bin histogram of the magnitudes and rounded up to
        a bin (see Notes), and ``low = 0.4 * high``.
    sigma : float, optional
        Standard deviation (pixels) of the Gaussian smoothing before
        differentiation; 0 for none. Default ``sqrt(2)`` (MATLAB's) for
        Canny, 0 for the other methods.
    thin : bool
        Keep only pixels whose magnitude is a local maximum along the
        dominant gradient axis (MATLAB's default). Canny always thins (by
        non-maximum suppression) and rejects ``thin=False``.
    normalize : bool
        Map the valid values to 0-255 grey levels first, from ``valid_range``
        or the image's own extent; thresholds are then in grey levels. With
        ``False`` the values are used as they are.
    valid_range : (low, high), optional
        Passed to the normalisation (requires ``normalize``).
    equalize : bool
        Histogram-equalise the grey levels over the valid pixels
        (`equalize_histogram`) before detecting, as the thesis suggests for
        more contrast between surfaces (requires ``normalize``).
    invalid_as_edge : bool
        Also mark valid pixels that have an invalid 4-neighbour (the outline
        of every hole). By default the boundary of the invalid region is not
        an edge, and invalid pixels are never edges.

    Returns
    -------
    (H, W) bool
        True on edge pixels. An image without valid pixels has no edges.

    Raises
    ------
    ValueError
        If the image is not 2-D real numeric or contains Inf; the method is
        unknown; a threshold is negative, not a number, or belongs to the
        other kind of method; ``low_threshold > high_threshold``;
        ``thin=False`` with Canny; or ``valid_range``/``equalize`` without
        ``normalize``.

    Notes
    -----
    Automatic thresholds follow MATLAB's ``edge``, which the thesis used.
    Canny: with ``m`` the largest valid magnitude, the valid magnitudes
    divided by ``m`` fill a 64-bin histogram whose bin ``k`` (from 0) is
    centred on ``k / 63``; ``high = (k + 1) / 64 * m`` for the first bin at
    which the cumulative count exceeds 70 % of the valid pixels. Reading the
    threshold off the histogram rounds it up past a plateau of equal
    magnitudes, so a tilted plane (a ramp of grey levels) yields no Canny
    edges; the bare 70 % quantile would mark it. Sobel, Prewitt, Roberts:
    ``threshold = sqrt(4 * mean(gx**2 + gy**2))`` over the valid pixels.
    Both rules are relative: an image without edges still has magnitudes
    above them (noise, curvature) and a noisy image gives many false
    edges, which is what the thesis's denoising is for.

    Canny's thresholds are in the units of the other methods (Sobel
    gradient divided by 8); the derivatives are rescaled to 16 bits for
    `cv2.Canny`, which loses nothing visible (1 part in 32767 of the
    largest magnitude).

    The grey levels are not rounded to integers before detection (rounding
    is a storage artefact; its staircase adds false Canny edges on smooth
    surfaces), except with ``equalize``, which works on the 256 levels.

    References
    ----------
    .. [1] J. Canny, "A computational approach to edge detection", IEEE
       TPAMI 8(6), 679-698, 1986.
    .. [2] A. K. Cherri and M. A. Karim, "Optical symbolic substitution: edge
       detection using Prewitt, Sobel, and Roberts operators", Applied Optics
       28(21), 4644-4648, 1989 (the thesis's [10]).
    .. [3] Thesis Section 3.1: the edge detectors "use an automatic parameter
       calibration where required".

    Examples
    --------
    >>> import numpy as np
    >>> depth = np.full((20, 20), 4.0)
    >>> depth[:, 10:] = 2.0                            # a vertical step
    >>> np.flatnonzero(detect_edges(depth, method="canny").any(axis=0)).tolist()
    [9]
    >>> depth[:, :5] = np.nan                          # a hole: no edge at its outline
    >>> np.flatnonzero(detect_edges(depth, method="prewitt").any(axis=0)).tolist()
    [9]
    """
    image = check_range_image(range_image, dtype=None)
    if method not in EDGE_METHODS:
        raise ValueError(f"unknown edge method {method!r}; expected one of {', '.join(EDGE_METHODS)}")
    if method == "canny":
        if threshold is not None:
            raise ValueError(
                "threshold applies to sobel, prewitt and roberts; use low_threshold/high_threshold for canny"
            )
        if not thin:
            raise ValueError("canny always thins its edges (non-maximum suppression); thin=False is not supported")
    elif low_threshold is not None or high_threshold is not None:
        raise ValueError(f"low_threshold/high_threshold apply to canny; use threshold for {method}")
    threshold = None if threshold is None else _check_non_negative(threshold, "threshold")
    low = None if low_threshold is None else _check_non_negative(low_threshold, "low_threshold")
    high = None if high_threshold is None else _check_non_negative(high_threshold, "high_threshold")
    if low is not None and high is not None and low > high:
        raise ValueError(f"low_threshold must not exceed high_threshold, got {low} > {high}")
    if sigma is None:
        sigma = _CANNY_SIGMA if method == "canny" else 0.0
    sigma = _check_non_negative(sigma, "sigma")
    if not normalize and (valid_range is not None or equalize):
        raise ValueError("valid_range and equalize apply to the normalised image; they need normalize=True")
    limits = _check_valid_range(valid_range)

    valid = np.isfinite(image) if np.issubdtype(image.dtype, np.floating) else np.ones(image.shape, bool)
    edges = np.zeros(image.shape, bool)
    if not valid.any():
        return edges

    if normalize:
        grey = _grey_levels(image, valid, limits)
        if equalize:
            grey = equalize_histogram(np.rint(grey).astype(np.uint8), mask=valid).astype(np.float32)
    else:
        grey = np.where(valid, image, 0).astype(np.float32)
    grey = _smooth(_fill_invalid(grey, valid), sigma)
    gx, gy = _gradients(grey, method)

    if method == "canny":
        edges = _canny(gx, gy, valid, low, high)
    else:
        magnitude_sq = gx * gx + gy * gy
        if threshold is None:
            cutoff = _GRADIENT_THRESHOLD_SCALE * float(magnitude_sq[valid].mean())
        else:
            cutoff = threshold * threshold
        edges = magnitude_sq > cutoff
        if thin:
            edges &= _thin(magnitude_sq, gx, gy)
    edges &= valid
    if invalid_as_edge:
        edges |= valid & ndimage.binary_dilation(~valid, structure=ndimage.generate_binary_structure(2, 1))
    return edges


# --------------------------------------------------------------------------
# Thesis clean-up and combination.
# --------------------------------------------------------------------------


def _shifted(padded: np.ndarray, pad: int, dr: int, dc: int, shape: tuple[int, int]) -> np.ndarray:
    """``out[r, c] = original[r + dr, c + dc]`` (False outside), from a zero-padded copy."""
    height, width = shape
    return padded[pad + dr : pad + dr + height, pad + dc : pad + dc + width]


def clean_edges(
    edges: np.ndarray,
    *,
    border_width: int = 2,
    continuity: Literal["opposite", "any"] = "opposite",
) -> np.ndarray:
    """The thesis's edge clean-up: clear the border, drop single pixels.

    1. Remove every edge pixel closer than ``border_width`` pixels to the
       image boundary: with the default 2, rows and columns 0 and 1 from each
       side (a pixel in row ``i`` lies ``i`` pixels from the boundary).
    2. Of the remaining edge pixels, an edge pixel none of whose 8 neighbours
       is an edge pixel (a single pixel) is removed unless its second-order
       neighbours (the ring of its 5 x 5 window) continue it:
       ``continuity="opposite"`` (default) needs two diametrically opposite
       ring pixels that are both edge pixels (the thesis's example: "the
       second ones to the left and right"), i.e. a line through the pixel
       across one-pixel gaps; ``"any"`` keeps it if any ring pixel is an edge
       pixel. Every decision uses the border-cleared map (one pass).
       Pixels with an edge 8-neighbour are always kept.

    Parameters
    ----------
    edges : (H, W) bool
    border_width : int
        Width of the cleared frame, >= 0.
    continuity : {"opposite", "any"}
        Which second-order neighbours save a single pixel.

    Returns
    -------
    (H, W) bool
        A subset of ``edges``.

    Raises
    ------
    ValueError
        If ``edges`` is not a 2-D bool array, ``border_width`` is not an
        integer >= 0 or ``continuity`` is unknown.

    Notes
    -----
    Thesis Section 3.1: "the edge image [...] is rapidly post-processed by
    removing any edges closer than two pixels to the image boundaries and
    any simple pixel edges that do not present the possibility of
    continuity. More clearly, if a pixel is considered on an edge, but none
    of the 8 neighbors is a border, it will not be automatically removed and
    the second order neighbors are checked to see if there is a continuity
    (i.e. if the first pixel to the left and right are not borders but the
    second ones to the left and right of the current edge pixel are, then
    the edge pixel is not removed)." ("Border" there means an edge pixel.)

    References
    ----------
    .. [1] Thesis Section 3.1 and Figures 3.6 and 3.7 ("border pixels removal
       and single pixel removal").

    Examples
    --------
    >>> import numpy as np
    >>> edges = np.zeros((7, 9), bool)
    >>> edges[3, [2, 4, 6]] = True                     # a dotted line ...
    >>> edges[0, 0] = True                             # ... and a corner pixel
    >>> clean_edges(edges).astype(int)[3].tolist()     # only the middle dot has both ends
    [0, 0, 0, 0, 1, 0, 0, 0, 0]
    >>> clean_edges(edges, continuity="any").astype(int)[3].tolist()
    [0, 0, 1, 0, 1, 0, 1, 0, 0]
    """
    edges = _check_edge_map(edges)
    if isinstance(border_width, bool) or not isinstance(border_width, (int, np.integer)) or border_width < 0:
        raise ValueError(f"border_width must be an integer >= 0, got {border_width!r}")
    if continuity not in ("opposite", "any"):
        raise ValueError(f"continuity must be 'opposite' or 'any', got {continuity!r}")
    height, width = edges.shape
    cleared = np.zeros_like(edges)
    if height > 2 * border_width and width > 2 * border_width:
        inner = (slice(border_width, height - border_width), slice(border_width, width - border_width))
        cleared[inner] = edges[inner]
    if not cleared.any():
        return cleared

    padded = np.pad(cleared, 2)
    has_neighbour = np.zeros_like(cleared)
    for dr, dc in _NEIGHBOURS:
        has_neighbour |= _shifted(padded, 2, dr, dc, cleared.shape)
    continued = np.zeros_like(cleared)
    if continuity == "opposite":
        for (dr1, dc1), (dr2, dc2) in _OPPOSITE_PAIRS:
            continued |= _shifted(padded, 2, dr1, dc1, cleared.shape) & _shifted(padded, 2, dr2, dc2, cleared.shape)
    else:
        for dr, dc in _RING:
            continued |= _shifted(padded, 2, dr, dc, cleared.shape)
    return cleared & (has_neighbour | continued)


def combined_edges(
    first: np.ndarray,
    second: np.ndarray,
    *,
    clean: bool = True,
    border_width: int = 2,
    continuity: Literal["opposite", "any"] = "opposite",
    **detect_options: Any,
) -> np.ndarray:
    """Union of the edge maps of two filtering branches (thesis Figs. 3.6, 3.7).

    The thesis's edge "preservation and enhancement scheme": each branch
    filters the original range image differently, its Canny edges are cleaned
    (`clean_edges`), and the two edge maps are summed into one binary image.
    In the thesis the first branch ("E1") is anisotropic diffusion (lambda
    0.3, k 20, up to three passes) and the second ("E2") is phase-preserving
    wavelet denoising (5 standard deviations, 5 scales, factor 2, 6
    orientations) followed by anisotropic diffusion (lambda 0.1, k 20). This
    function takes the branches' outputs, so any filters can be combined.

    Parameters
    ----------
    first, second : (H, W) array
        Each either a filtered range image (float or integer, NaN where
        invalid), whose edges are detected with `detect_edges`, or an edge
        map already (bool), used as it is.
    clean : bool
        Apply `clean_edges` to each branch's edge map before the union, as
        the thesis does.
    border_width, continuity
        Passed to `clean_edges`.
    **detect_options
        Keyword options of `detect_edges` for the range-image inputs (default
        Canny, as in the thesis's figures).

    Returns
    -------
    (H, W) bool
        ``E1 | E2``.

    Raises
    ------
    ValueError
        If the inputs differ in shape, are not 2-D, are neither bool nor
        real numeric, or ``detect_options`` are given but both inputs are
        edge maps; and as `detect_edges` and `clean_edges` raise.

    Notes
    -----
    The thesis's steps end with "Convolve E1 and E2 to obtain the final edge
    image"; the figure captions call the result the "binary sum of the edge
    detection images", read here as the pixel-wise OR. The captions call the
    first branch "denoising (1)" where the text has anisotropic diffusion.

    References
    ----------
    .. [1] Thesis Section 3.1, Figures 3.6 and 3.7.

    Examples
    --------
    >>> import numpy as np
    >>> diffused = np.full((30, 30), 3.0)
    >>> diffused[:, 15:] = 2.0                         # branch 1 keeps the vertical step
    >>> denoised = np.full((30, 30), 3.0)
    >>> denoised[15:, :] = 2.0                         # branch 2 keeps the horizontal one
    >>> edges = combined_edges(diffused, denoised)
    >>> bool(edges[:, 14].sum() > 20 and edges[14, :].sum() > 20)
    True
    """
    first_array, second_array = np.asarray(first), np.asarray(second)
    _check_same_shape(first_array, second_array, "branch images")
    if detect_options and first_array.dtype == bool and second_array.dtype == bool:
        raise ValueError(f"both branches are edge maps; detect options {sorted(detect_options)} would be ignored")
    maps = []
    for name, branch in (("first branch", first_array), ("second branch", second_array)):
        if branch.dtype == bool:
            edges = _check_edge_map(branch, name)
        else:
            edges = detect_edges(check_range_image(branch, name, dtype=None), **detect_options)
        maps.append(clean_edges(edges, border_width=border_width, continuity=continuity) if clean else edges)
    return maps[0] | maps[1]


# --------------------------------------------------------------------------
# Ground truth and scores.
# --------------------------------------------------------------------------


def true_depth_edges(
    truth_range: np.ndarray,
    *,
    relative_jump: float = 0.05,
    surface_id: np.ndarray | None = None,
    side: Literal["both", "near"] = "both",
    missing_range: float | None = None,
) -> np.ndarray:
    """Depth discontinuities of a true range image.

    Two 4-neighbours ``p`` and ``q`` straddle a discontinuity when
    ``|r_p - r_q| > relative_jump * min(r_p, r_q)``, the criterion the
    simulator uses for mixed pixels (`SimulationNoise.mixed_pixel_jump`).

    Parameters
    ----------
    truth_range : (H, W) float array
        True range, e.g. `rangesurf.simulate.GroundTruth.range`; NaN where
        the ray hits nothing within the sensor's range.
    relative_jump : float
        Jump relative to the nearer range, > 0.
    surface_id : (H, W) integer array, optional
        Surface labels (``GroundTruth.surface_id``): when given, a jump counts
        only between different surfaces, which excludes steep but continuous
        surfaces (a floor seen at a grazing angle).
    side : {"both", "near"}
        Mark both pixels of a discontinuity (a two-pixel-wide edge, which
        a one-pixel-wide detection on either side matches within tolerance
        1), or only the nearer one (the occluding contour).
    missing_range : float, optional
        Range assumed where ``truth_range`` is NaN, e.g. the sensor's
        ``max_range`` for a time-of-flight camera that reports the cut-off
        there. By default a NaN pixel has no range: it and its neighbours
        never form a discontinuity (matching ``detect_edges``'s
        ``invalid_as_edge=False``).

    Returns
    -------
    (H, W) bool

    Raises
    ------
    ValueError
        If the inputs are not 2-D, of different shapes, ``surface_id`` is not
        integer, ``relative_jump`` is not > 0, ``missing_range`` is not finite
        or ``side`` is unknown.

    Examples
    --------
    >>> import numpy as np
    >>> depth = np.array([[2.0, 2.0, 4.0, 4.0, np.nan]])
    >>> true_depth_edges(depth).astype(int).tolist()
    [[0, 1, 1, 0, 0]]
    >>> true_depth_edges(depth, side="near", missing_range=7.5).astype(int).tolist()
    [[0, 1, 0, 1, 0]]
    """
    truth = check_range_image(truth_range, "true range image", dtype=None).astype(np.float64)
    if isinstance(relative_jump, bool) or not isinstance(relative_jump, (int, float, np.integer, np.floating)):
        raise ValueError(f"relative_jump must be a number, got {relative_jump!r}")
    if not (math.isfinite(relative_jump) and relative_jump > 0):
        raise ValueError(f"relative_jump must be finite and > 0, got {relative_jump}")
    if side not in ("both", "near"):
        raise ValueError(f"side must be 'both' or 'near', got {side!r}")
    if surface_id is not None:
        surface_id = np.asarray(surface_id)
        _check_same_shape(truth, surface_id, "true range image and surface_id")
        if surface_id.dtype == bool or not np.issubdtype(surface_id.dtype, np.integer):
            raise ValueError(f"surface_id must be an integer array, got dtype {surface_id.dtype}")
    if missing_range is not None:
        missing_range = _check_non_negative(missing_range, "missing_range")
        truth = np.where(np.isnan(truth), missing_range, truth)

    edges = np.zeros(truth.shape, bool)
    for axis in (0, 1):
        if truth.shape[axis] < 2:
            continue
        first = truth[:-1] if axis == 0 else truth[:, :-1]
        second = truth[1:] if axis == 0 else truth[:, 1:]
        with np.errstate(invalid="ignore"):
            jump = np.abs(first - second) > relative_jump * np.minimum(first, second)
        if surface_id is not None:
            jump &= (surface_id[:-1] != surface_id[1:]) if axis == 0 else (surface_id[:, :-1] != surface_id[:, 1:])
        mark_first = jump if side == "both" else jump & (first < second)
        mark_second = jump if side == "both" else jump & (second < first)
        if axis == 0:
            edges[:-1] |= mark_first
            edges[1:] |= mark_second
        else:
            edges[:, :-1] |= mark_first
            edges[:, 1:] |= mark_second
    return edges


@dataclass(frozen=True)
class EdgeScores:
    """Agreement of a detected edge map with a reference, within a tolerance.

    Attributes
    ----------
    precision : float
        Fraction of detected pixels with a reference edge within
        ``tolerance``; 1 when nothing was detected.
    recall : float
        Fraction of reference pixels with a detection within ``tolerance``;
        1 when the reference has no edges.
    f1 : float
        Harmonic mean of precision and recall; 0 when both are 0.
    true_positives : int
        Detected pixels with a reference edge within ``tolerance``.
    false_positives : int
        Detected pixels without one.
    false_negatives : int
        Reference pixels without a detection within ``tolerance``.
    n_detected, n_truth : int
        Edge pixels in the detected and reference maps (inside the mask).
    tolerance : float
        Pixels (Euclidean).
    """

    precision: float
    recall: float
    f1: float
    true_positives: int
    false_positives: int
    false_negatives: int
    n_detected: int
    n_truth: int
    tolerance: float


def edge_scores(
    detected: np.ndarray,
    truth: np.ndarray,
    *,
    tolerance: float = 1.0,
    mask: np.ndarray | None = None,
) -> EdgeScores:
    """Precision, recall and F1 of an edge map within a distance tolerance.

    A detected pixel is correct if a reference edge pixel lies within
    ``tolerance`` pixels of it (Euclidean distance, so 1 admits the four
    direct neighbours and ``sqrt(2)`` the eight); a reference pixel is found
    if a detected pixel lies within ``tolerance`` of it. Distances come from
    `scipy.ndimage.distance_transform_edt`. Unlike the bipartite matching of
    the Berkeley benchmark, one detection may account for several reference
    pixels.

    Parameters
    ----------
    detected, truth : (H, W) bool
        Detected and reference edge maps.
    tolerance : float
        Pixels, >= 0; 0 demands exact coincidence.
    mask : (H, W) bool, optional
        Pixels that count (e.g. valid pixels, or all but the border cleared
        by `clean_edges`); edges outside the mask are neither scored nor
        needed, though they still serve as nearby matches.

    Returns
    -------
    EdgeScores
        With no detections, precision is 1 (no false detection); with no
        reference edges, recall is 1 (nothing missed); so two empty maps
        score 1, 1, 1 and an empty map against a non-empty one F1 0.

    Raises
    ------
    ValueError
        If the maps are not 2-D bool arrays of one shape or ``tolerance`` is
        negative or not finite.

    References
    ----------
    .. [1] D. R. Martin, C. C. Fowlkes and J. Malik, "Learning to detect
       natural image boundaries using local brightness, color, and texture
       cues", IEEE TPAMI 26(5), 530-549, 2004 (precision and recall of edge
       maps with a localisation tolerance).

    Examples
    --------
    >>> import numpy as np
    >>> truth = np.zeros((5, 5), bool); truth[:, 2] = True
    >>> detected = np.zeros((5, 5), bool); detected[:, 3] = True; detected[0, 0] = True
    >>> scores = edge_scores(detected, truth, tolerance=1)
    >>> scores.true_positives, scores.false_positives, scores.false_negatives, scores.recall
    (5, 1, 0, 1.0)
    """
    detected = _check_edge_map(detected, "detected edge map")
    truth = _check_edge_map(truth, "reference edge map")
    _check_same_shape(detected, truth, "detected and reference edge maps")
    tolerance = _check_non_negative(tolerance, "tolerance")
    if mask is not None:
        mask = _check_edge_map(mask, "mask")
        _check_same_shape(detected, mask, "edge maps and mask")
    counted_detected = detected if mask is None else detected & mask
    counted_truth = truth if mask is None else truth & mask

    def near(edges: np.ndarray) -> np.ndarray:
        if not edges.any():
            return np.zeros(edges.shape, bool)
        return ndimage.distance_transform_edt(~edges) <= tolerance

    true_positives = int((counted_detected & near(truth)).sum())
    found = int((counted_truth & near(detected)).sum())
    n_detected, n_truth = int(counted_detected.sum()), int(counted_truth.sum())
    precision = true_positives / n_detected if n_detected else 1.0
    recall = found / n_truth if n_truth else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return EdgeScores(
        precision=precision, recall=recall, f1=f1,
        true_positives=true_positives, false_positives=n_detected - true_positives,
        false_negatives=n_truth - found, n_detected=n_detected, n_truth=n_truth, tolerance=tolerance,
    )


@dataclass(frozen=True, eq=False)
class EdgeDifference:
    """Difference between the edge maps of a raw and a filtered image.

    Attributes
    ----------
    difference : (H, W) int8
        ``filtered - raw``: +1 where the filter added an edge pixel, -1 where
        it removed one, 0 where both agree.
    added : int
        Edge pixels of the filtered map only.
    removed : int
        Edge pixels of the raw map only.
    kept : int
        Edge pixels of both.
    changed_fraction : float
        ``(added + removed) / (H * W)``: the mean absolute difference, 0 for
        an empty image.
    """

    difference: np.ndarray
    added: int
    removed: int
    kept: int
    changed_fraction: float


def edge_difference(raw_edges: np.ndarray, filtered_edges: np.ndarray) -> EdgeDifference:
    """The thesis's matrix difference between raw and filtered edge maps.

    Parameters
    ----------
    raw_edges, filtered_edges : (H, W) bool
        Edge maps of the original range image and of the filtered one, from
        the same detector and settings.

    Returns
    -------
    EdgeDifference
        The signed difference image and its counts.

    Raises
    ------
    ValueError
        If the maps are not 2-D bool arrays of one shape.

    Notes
    -----
    Thesis Section 2.1: "by computing a matrix difference between two images
    obtained by using an edge detection method on the original range image
    and the filtered one, and evaluating the resulting grayscale image, one
    could express the proficiency of a proposed filter". The thesis does not
    say how the difference image is evaluated; it is read here as the signed
    difference ``filtered - raw`` (the "grayscale image", values -1, 0, 1)
    summarised by its counts of removed and added edge pixels and its mean
    absolute value. The difference is pixel-exact: an edge moved by one pixel
    counts as removed and added; use `edge_scores` with a tolerance to
    compare edge maps up to small displacements.

    References
    ----------
    .. [1] Thesis Section 2.1 and Figure 2.7.

    Examples
    --------
    >>> import numpy as np
    >>> raw = np.array([[True, True, False, False]])
    >>> filtered = np.array([[True, False, False, True]])
    >>> result = edge_difference(raw, filtered)
    >>> result.difference.tolist(), result.removed, result.added, result.kept, result.changed_fraction
    ([[0, -1, 0, 1]], 1, 1, 1, 0.5)
    """
    raw = _check_edge_map(raw_edges, "raw edge map")
    filtered = _check_edge_map(filtered_edges, "filtered edge map")
    _check_same_shape(raw, filtered, "raw and filtered edge maps")
    difference = filtered.astype(np.int8) - raw.astype(np.int8)
    added, removed = int((difference > 0).sum()), int((difference < 0).sum())
    return EdgeDifference(
        difference=difference, added=added, removed=removed, kept=int((raw & filtered).sum()),
        changed_fraction=(added + removed) / raw.size if raw.size else 0.0,
    )


def surface_boundaries(surface_id: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixels with a 4-neighbour on another surface (ground-truth ids)."""
    surface_id = np.asarray(surface_id)
    if surface_id.ndim != 2:
        raise ValueError(f"surface ids must be 2-D (H, W), got shape {surface_id.shape}")
    changes = np.zeros(surface_id.shape, bool)
    vertical = surface_id[:-1] != surface_id[1:]
    horizontal = surface_id[:, :-1] != surface_id[:, 1:]
    changes[:-1] |= vertical
    changes[1:] |= vertical
    changes[:, :-1] |= horizontal
    changes[:, 1:] |= horizontal
    return changes


def crease_free_mask(surface_id: np.ndarray, depth_edges: np.ndarray, *, band: int = 3) -> np.ndarray:
    """Pixels on which to score depth edges: all but those near a crease.

    A crease (two surfaces meeting without a depth jump: wall and floor) is a
    real surface boundary that edge detectors rightly find, a few pixels off
    after smoothing, but it is not a depth edge; detections within ``band``
    pixels of one (and not next to a depth edge) are neither right nor wrong.

    Parameters
    ----------
    surface_id : (H, W) int
        Ground-truth surface ids (simulator).
    depth_edges : (H, W) bool
        True depth discontinuities (`true_depth_edges`).
    band : int
        Pixels around a crease left out, >= 0.

    Returns
    -------
    (H, W) bool
        True where a detection is scored.
    """
    depth_edges = _check_edge_map(depth_edges, "depth edges")
    if band < 0:
        raise ValueError(f"band must be >= 0, got {band}")
    creases = surface_boundaries(surface_id) & ~depth_edges
    if band == 0 or not creases.any():
        return np.ones(depth_edges.shape, bool)
    dont_care = ndimage.binary_dilation(creases, iterations=band) & ~ndimage.binary_dilation(depth_edges)
    return ~dont_care
