"""Quality of a range-image denoiser: range error and depth-edge preservation.

A denoiser for range images should bring the ranges closer to the truth
without blurring away, or inventing, depth discontinuities (thesis Sections
2.1 and 3.1). This module scores both against a known true range image,
such as `rangesurf.simulate.GroundTruth.range`:

* `range_rmse`: root-mean-square range error over the pixels valid in both
  images;
* `score_denoising`: the RMSE of the raw and of the denoised image, and the
  precision, recall and F1 of their detected edges (`rangesurf.edges`)
  against the true depth edges, with the thesis's raw-versus-filtered edge
  difference, in one `DenoiseScores`.

References
----------
.. [1] D. Cernea, "Graphical Methods For Online Surface Fitting On 3D Range
   Sensor Point Clouds", Sections 2.1 and 3.1 (``shared/reference/thesis.md``).

Examples
--------
>>> import numpy as np
>>> from rangesurf.denoise.metrics import score_denoising
>>> truth = np.full((40, 40), 3.0)
>>> truth[10:30, 10:30] = 2.0                       # a box in front of a wall
>>> raw = truth + np.random.default_rng(0).normal(0.0, 0.02, truth.shape)
>>> scores = score_denoising(raw, truth, truth)     # a perfect denoiser
>>> scores.rmse_denoised, round(scores.rmse_raw, 2), round(scores.edge_f1_denoised, 2)
(0.0, 0.02, 0.99)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from rangesurf._checks import check_range_image

from rangesurf.edges import crease_free_mask, detect_edges, edge_difference, edge_scores, true_depth_edges

__all__ = ["DenoiseScores", "range_rmse", "resolved_jump_ratios", "score_denoising"]


def _check_shapes(reference: np.ndarray, others: dict[str, np.ndarray | None]) -> None:
    for name, array in others.items():
        if array is not None and array.shape != reference.shape:
            raise ValueError(
                f"{name} must have the shape of the range image, got {array.shape} and {reference.shape}"
            )


def _check_mask(mask: Any) -> np.ndarray | None:
    if mask is None:
        return None
    array = np.asarray(mask)
    if array.ndim != 2:
        raise ValueError(f"mask must be 2-D (H, W), got shape {array.shape}")
    if array.dtype != bool:
        raise ValueError(f"mask must be a bool array, got dtype {array.dtype}")
    return array


def _rmse(estimate: np.ndarray, truth: np.ndarray, counted: np.ndarray) -> float:
    if not counted.any():
        return math.nan
    error = estimate[counted].astype(np.float64) - truth[counted].astype(np.float64)
    return float(np.sqrt(np.mean(error * error)))


def range_rmse(range_image: np.ndarray, truth_range: np.ndarray, *, mask: np.ndarray | None = None) -> float:
    """Root-mean-square error of a range image against the true range.

    Parameters
    ----------
    range_image, truth_range : (H, W) float array
        Measured (or denoised) and true range, in one unit (metres); NaN
        where invalid.
    mask : (H, W) bool, optional
        Pixels that count; by default all.

    Returns
    -------
    float
        ``sqrt(mean((range_image - truth_range)**2))`` over the pixels that
        are finite in both images (and inside ``mask``), in the unit of the
        images; NaN when there is no such pixel.

    Raises
    ------
    ValueError
        If an input is not 2-D, not real numeric, contains Inf, or the
        shapes differ (the message names both shapes).

    Examples
    --------
    >>> import numpy as np
    >>> range_rmse(np.array([[1.0, 2.0], [3.0, np.nan]]), np.array([[1.0, 2.0], [2.0, 4.0]]))
    0.5773502691896257
    """
    image = check_range_image(range_image, "range image", dtype=None)
    truth = check_range_image(truth_range, "true range image", dtype=None)
    mask = _check_mask(mask)
    _check_shapes(image, {"true range image": truth, "mask": mask})
    counted = np.isfinite(image) & np.isfinite(truth)
    if mask is not None:
        counted &= mask
    return _rmse(image, truth, counted)


@dataclass(frozen=True)
class DenoiseScores:
    """Range error and depth-edge agreement of a raw and a denoised range image.

    Attributes
    ----------
    rmse_raw, rmse_denoised : float
        RMSE against the true range (unit of the images), over the pixels
        finite in the raw, the denoised and the true image alike.
    rmse_ratio : float
        ``rmse_denoised / rmse_raw``: below 1 when the denoiser helps; NaN
        if ``rmse_raw`` is 0 or nothing was scored.
    edge_precision_raw, edge_recall_raw, edge_f1_raw : float
        Edges detected on the raw image against the true depth edges
        (`rangesurf.edges.edge_scores`).
    edge_precision_denoised, edge_recall_denoised, edge_f1_denoised : float
        The same for the denoised image.
    edge_changed_fraction : float
        Fraction of pixels whose edge label differs between the raw and the
        denoised edge maps (`rangesurf.edges.edge_difference`, the thesis's
        measure).
    edge_method : str
        Detector used for both edge maps.
    tolerance : float
        Edge localisation tolerance in pixels.
    """

    rmse_raw: float
    rmse_denoised: float
    rmse_ratio: float
    edge_precision_raw: float
    edge_recall_raw: float
    edge_f1_raw: float
    edge_precision_denoised: float
    edge_recall_denoised: float
    edge_f1_denoised: float
    edge_changed_fraction: float
    edge_method: str
    tolerance: float


def score_denoising(
    raw: np.ndarray,
    denoised: np.ndarray,
    truth_range: np.ndarray,
    *,
    surface_id: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    edge_method: str = "canny",
    relative_jump: float = 0.05,
    missing_range: float | None = None,
    tolerance: float = 1.0,
    crease_band: int = 3,
    **detect_options: Any,
) -> DenoiseScores:
    """Score a denoised range image against the truth, next to the raw one.

    Both images are scored alike: their RMSE against ``truth_range`` over
    the pixels finite in all three images (and in ``mask``), and the
    precision, recall and F1 of their edges (`rangesurf.edges.detect_edges`
    with ``edge_method`` and ``detect_options``) against the true depth
    edges (`rangesurf.edges.true_depth_edges`).

    Parameters
    ----------
    raw, denoised : (H, W) float array
        Measured and denoised range (metres), NaN where invalid.
    truth_range : (H, W) float array
        True range, e.g. `rangesurf.simulate.GroundTruth.range`.
    surface_id : (H, W) integer array, optional
        True surface labels (``GroundTruth.surface_id``). When given, only
        jumps between different surfaces are depth edges, and creases (two
        surfaces meeting without a depth jump, such as wall and floor) are
        left out of the edge scores: detections within ``crease_band``
        pixels of a crease, and away from any depth edge, count as neither
        right nor wrong.
    mask : (H, W) bool, optional
        Pixels that count for the RMSE and the edge scores; default all.
    edge_method : {"canny", "sobel", "prewitt", "roberts"}
        Detector for both edge maps.
    relative_jump : float
        Jump, relative to the nearer range, that makes a true depth edge.
    missing_range : float, optional
        Range assumed where ``truth_range`` is NaN when finding the true
        depth edges, e.g. ``sensor.max_range`` for a sensor that reports its
        cut-off there (``beyond_max_range="clamp"``), so that the boundary of
        the clamped pixels is a depth edge (`rangesurf.edges.true_depth_edges`).
    tolerance : float
        Edge localisation tolerance in pixels (Euclidean).
    crease_band : int
        Width, in pixels, of the band left out around creases, >= 0; 0
        scores creases like any other pixel.
    **detect_options
        Further keyword options of `rangesurf.edges.detect_edges`.

    Returns
    -------
    DenoiseScores

    Raises
    ------
    ValueError
        If an image is not 2-D, not real numeric or contains Inf, the shapes differ (the
        message names both shapes), ``crease_band`` is negative, and as
        `detect_edges`, `true_depth_edges` and `edge_scores` raise.

    See Also
    --------
    rangesurf.edges.edge_scores, rangesurf.edges.edge_difference

    References
    ----------
    .. [1] Thesis Section 2.1: the edge maps of the original and the
       filtered range image measure "the proficiency of a proposed filter".

    Examples
    --------
    >>> import numpy as np
    >>> truth = np.full((40, 40), 3.0)
    >>> truth[10:30, 10:30] = 2.0
    >>> raw = truth + np.random.default_rng(1).normal(0.0, 0.05, truth.shape)
    >>> scores = score_denoising(raw, raw, truth)     # doing nothing
    >>> scores.rmse_ratio, scores.edge_f1_raw == scores.edge_f1_denoised
    (1.0, True)
    """
    raw_image = check_range_image(raw, "raw range image", dtype=None)
    denoised_image = check_range_image(denoised, "denoised range image", dtype=None)
    truth = check_range_image(truth_range, "true range image", dtype=None)
    mask = _check_mask(mask)
    if surface_id is not None:
        surface_id = np.asarray(surface_id)
    _check_shapes(
        raw_image,
        {"denoised range image": denoised_image, "true range image": truth, "surface_id": surface_id, "mask": mask},
    )
    if isinstance(crease_band, bool) or not isinstance(crease_band, (int, np.integer)) or crease_band < 0:
        raise ValueError(f"crease_band must be an integer >= 0, got {crease_band!r}")

    counted = np.isfinite(raw_image) & np.isfinite(denoised_image) & np.isfinite(truth)
    if mask is not None:
        counted &= mask
    rmse_raw = _rmse(raw_image, truth, counted)
    rmse_denoised = _rmse(denoised_image, truth, counted)
    rmse_ratio = rmse_denoised / rmse_raw if rmse_raw > 0 else math.nan

    depth_edges = true_depth_edges(
        truth, relative_jump=relative_jump, surface_id=surface_id, missing_range=missing_range
    )
    edge_mask = mask
    if surface_id is not None:
        crease_free = crease_free_mask(surface_id, depth_edges, band=int(crease_band))
        edge_mask = crease_free if mask is None else crease_free & mask
    raw_edges = detect_edges(raw_image, method=edge_method, **detect_options)
    denoised_edges = detect_edges(denoised_image, method=edge_method, **detect_options)
    raw_scores = edge_scores(raw_edges, depth_edges, tolerance=tolerance, mask=edge_mask)
    denoised_scores = edge_scores(denoised_edges, depth_edges, tolerance=tolerance, mask=edge_mask)
    return DenoiseScores(
        rmse_raw=rmse_raw,
        rmse_denoised=rmse_denoised,
        rmse_ratio=rmse_ratio,
        edge_precision_raw=raw_scores.precision,
        edge_recall_raw=raw_scores.recall,
        edge_f1_raw=raw_scores.f1,
        edge_precision_denoised=denoised_scores.precision,
        edge_recall_denoised=denoised_scores.recall,
        edge_f1_denoised=denoised_scores.f1,
        edge_changed_fraction=edge_difference(raw_edges, denoised_edges).changed_fraction,
        edge_method=edge_method,
        tolerance=float(tolerance),
    )


def resolved_jump_ratios(
    estimate: np.ndarray,
    truth_range: np.ndarray,
    truth_sigma: np.ndarray,
    *,
    relative_jump: float = 0.1,
    noise_multiple: float = 5.0,
) -> np.ndarray:
    """How much of each resolvable depth jump a denoised image keeps.

    A jump: 4-neighbours whose true ranges differ by more than
    ``relative_jump`` of the nearer one. Resolvable: the jump also exceeds
    ``noise_multiple`` standard deviations of the noise of the difference
    (about half of the SR-3000's jumps lie on dark, grazing surfaces whose
    noise is larger than the jump; no filter can keep those).

    Parameters
    ----------
    estimate, truth_range, truth_sigma : (H, W) float arrays
        Denoised range, true range (NaN where none) and the noise standard
        deviation per pixel (metres), e.g. a simulator `GroundTruth`'s
        ``range`` and ``sigma``.

    Returns
    -------
    (N,) float64
        ``|estimate jump| / |true jump|`` per resolvable jump with both
        estimate pixels valid; 1 is a perfectly kept edge, 0 a flattened one.
    """
    estimate = check_range_image(estimate, "estimate", dtype=np.float64)
    truth = check_range_image(truth_range, "true range image", dtype=np.float64)
    sigma = check_range_image(truth_sigma, "true noise sigma", dtype=np.float64)
    if not (estimate.shape == truth.shape == sigma.shape):
        raise ValueError(f"shapes differ: estimate {estimate.shape}, truth {truth.shape}, sigma {sigma.shape}")
    ratios = []
    for first, second in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))), ((slice(None, -1),), (slice(1, None),))):
        true_jump = np.abs(truth[first] - truth[second])
        noise = np.hypot(sigma[first], sigma[second])
        with np.errstate(invalid="ignore"):
            resolved = (true_jump > relative_jump * np.minimum(truth[first], truth[second])) & (true_jump > noise_multiple * noise)
        resolved &= np.isfinite(estimate[first]) & np.isfinite(estimate[second])
        ratios.append(np.abs(estimate[first] - estimate[second])[resolved] / true_jump[resolved])
    return np.concatenate(ratios)
