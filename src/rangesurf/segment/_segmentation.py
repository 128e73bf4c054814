"""The result every segmenter returns."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from rangesurf._planefit import plane_rms, planes_from_moments

__all__ = ["Segmentation", "relabel"]


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
        ``(nx, ny, nz, d)`` of each segment's total-least-squares plane in the
        sensor frame: ``n . p + d = 0``, unit ``n`` facing the sensor
        (``d >= 0``). Row 0 is NaN.
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
        counts = moments[1:, 0]
        keep = np.flatnonzero(counts > 0)
        keep = keep[np.argsort(-counts[keep], kind="stable")]
        renumber = np.zeros(len(moments), np.int32)
        renumber[keep + 1] = np.arange(1, len(keep) + 1, dtype=np.int32)
        planes = np.full((len(keep) + 1, 4), np.nan)
        residuals = np.full(len(keep) + 1, np.nan)
        planes[1:], residuals[1:] = planes_from_moments((moments if fit_moments is None else fit_moments)[keep + 1])
        if fit_moments is not None:
            # The residual is every point's, about the plane fitted to some of them.
            residuals[1:] = plane_rms(moments[keep + 1], planes[1:])
        sizes = np.concatenate([[unlabelled], counts[keep]]).astype(np.int64)
        labels = relabel(labels, renumber if lookup is None else renumber[lookup])
        return cls(labels=labels, planes=planes, residuals=residuals, sizes=sizes)


def relabel(labels: np.ndarray, lookup: np.ndarray) -> np.ndarray:
    """``lookup[labels]`` as int32, for label images (a compiled loop: NumPy's fancy indexing is several times slower)."""
    labels = np.ascontiguousarray(labels)
    return _relabel_kernel(labels.reshape(-1), np.ascontiguousarray(lookup, dtype=np.int32)).reshape(labels.shape)


@numba.njit(cache=True, nogil=True)
def _relabel_kernel(labels, lookup):  # pragma: no cover - compiled
    relabelled = np.empty(labels.size, np.int32)
    for k in range(labels.size):
        relabelled[k] = lookup[labels[k]]
    return relabelled
