"""The result every segmenter returns."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from rangesurf._planefit import plane_rms, planes_kernel

__all__ = ["Segmentation"]


@dataclass(frozen=True)
class Segmentation:
    """Planar segments of one organized frame.

    Parameters
    ----------
    labels : (H, W) int32
        Segment of every pixel, 1..K, largest segment first; 0 where the pixel
        belongs to no surface (no return, a depth edge, noise, or a segment
        too small to keep).
    planes : (K + 1, 4) float64
        ``(nx, ny, nz, d)`` of each segment's plane in the sensor frame:
        ``n . p + d = 0``, unit ``n`` facing the sensor (``d >= 0``). Region
        growing fits it along the rays, where range noise lies
        (`rangesurf._planefit.ray_planes_kernel`); the N x D clustering by
        total least squares. Row 0 is NaN.
    residuals : (K + 1,) float64
        Root-mean-square point-to-plane distance of each segment's points
        (metres); the patch-fit uncertainty (level UL2). Row 0 is NaN.
    sizes : (K + 1,) int64
        Pixels per segment; ``sizes[0]`` counts the unlabelled valid pixels.
    """

    labels: np.ndarray
    planes: np.ndarray
    residuals: np.ndarray
    sizes: np.ndarray

    @property
    def n_segments(self) -> int:
        """Number of segments ``K``."""
        return len(self.planes) - 1

    @classmethod
    def from_moments(
        cls,
        labels: np.ndarray,
        moments: np.ndarray,
        unlabelled: int,
        fit_moments: np.ndarray | None = None,
        lookup: np.ndarray | None = None,
    ) -> Segmentation:
        """Build from per-segment point moments ``(K + 1, 10)`` (n, sums of x, y, z, and of their products).

        Segments are renumbered by size, largest first; empty ones are dropped.
        Planes come from ``fit_moments`` when given (the moments of the points
        to fit, e.g. a segment's interior); residuals are always those of all
        the segment's points. A pixel labelled k belongs to segment
        ``lookup[k]`` when ``lookup`` is given (a merge: the label image is
        then mapped once, not twice).
        """
        moments = np.ascontiguousarray(moments, dtype=np.float64)
        fit = moments if fit_moments is None else np.ascontiguousarray(fit_moments, dtype=np.float64)
        if lookup is None:
            lookup = np.arange(len(moments), dtype=np.int32)
        labels, planes, residuals, sizes = _from_moments_kernel(
            np.ascontiguousarray(labels), moments, planes_kernel(fit)[0], np.ascontiguousarray(lookup, dtype=np.int32),
            unlabelled,
        )
        return cls(labels=labels, planes=planes, residuals=residuals, sizes=sizes)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _from_moments_kernel(labels, moments, fitted, lookup, unlabelled):  # pragma: no cover - compiled
    """`Segmentation.from_moments` in one compiled call (at 176x144 its NumPy steps cost as much as a kernel pass).

    ``fitted`` holds a plane per row of ``moments``; the residuals are every
    point's, about that plane.
    """
    counts = moments[1:, 0]
    keep = np.flatnonzero(counts > 0)
    # Largest first; a stable sort keeps equal sizes in label order.
    keep = keep[np.argsort(-counts[keep], kind="mergesort")]
    kept = keep.size
    renumber = np.zeros(moments.shape[0], np.int32)
    all_rows = np.empty((kept, 10))
    planes = np.full((kept + 1, 4), np.nan)
    sizes = np.empty(kept + 1, np.int64)
    sizes[0] = unlabelled
    for r in range(kept):
        renumber[keep[r] + 1] = r + 1
        planes[r + 1] = fitted[keep[r] + 1]
        all_rows[r] = moments[keep[r] + 1]
        sizes[r + 1] = np.int64(counts[keep[r]])
    residuals = np.full(kept + 1, np.nan)
    residuals[1:] = plane_rms(all_rows, planes[1:])
    # Label k of the image is segment lookup[k], which is renumbered: one mapping of the image.
    composed = np.empty(lookup.size, np.int32)
    for k in range(lookup.size):
        composed[k] = renumber[lookup[k]]
    return _relabel_kernel(labels.reshape(labels.size), composed).reshape(labels.shape), planes, residuals, sizes


@numba.njit(cache=True, nogil=True)
def _relabel_kernel(labels, lookup):  # pragma: no cover - compiled
    """``lookup[labels]`` as int32, for flat label images (a compiled loop: NumPy's fancy indexing is several times slower)."""
    relabelled = np.empty(labels.size, np.int32)
    for k in range(labels.size):
        relabelled[k] = lookup[labels[k]]
    return relabelled
