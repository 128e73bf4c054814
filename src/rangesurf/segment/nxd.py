"""Segmentation by clustering in normal x distance (NxD) space (thesis Eq. 2.1, Section 3.1).

Every point with a normal ``N`` maps to ``X' = N * D`` (Eq. 2.1). With ``D``
the point's distance to the sensor (``distance="range"``, the thesis's
literal choice) a plane becomes a short line segment along its normal; with
``D`` the distance of the point's tangent plane to the sensor
(``distance="plane"``, ``D = -N . p``) every point of a plane maps to the
same spot, so planes become tight blobs whose spread is only the noise of
the normals and the offsets. Clusters are then the surfaces.

The thesis clusters by merging Gaussians: every point starts as the centre
of one, overlapping ones merge and move to their joint centre until nothing
changes, and clusters with too few points are dropped as noise. That is
mode seeking on the density of the NxD cloud; here it is quick shift
(Vedaldi & Soatto 2008: every point links to the nearest denser one within
the bandwidth, and the chains end at the modes) on a voxel grid of the cloud
weighted by how many points fall in each cell, so its cost grows with the
occupied volume, not with the pixel count. Each cluster maps back to the image, where its connected parts become
separate segments (two coplanar walls apart are two surfaces).

References
----------
.. [1] The reference thesis, Eq. 2.1 and Figures 2.3, 3.4 and 3.5
   (``shared/reference/thesis.md``).
.. [2] A. Vedaldi and S. Soatto, "Quick shift and kernel methods for mode
   seeking", ECCV 2008.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from rangesurf.segment._segmentation import Segmentation
from rangesurf.segment.region_grow import _check_inputs, _label_moments

__all__ = ["nxd_transform", "segment_nxd", "NXD_DISTANCES"]

NXD_DISTANCES = ("plane", "range")
# Voxel size as a fraction of the bandwidth.
_CELL = 0.3


def nxd_transform(points: ArrayLike, normals: ArrayLike, *, distance: str = "plane") -> np.ndarray:
    """Map points to the normal x distance space, ``X' = N * D`` (thesis Eq. 2.1).

    Parameters
    ----------
    points, normals : (H, W, 3) float arrays
        Sensor-frame points (metres) and unit normals facing the sensor, NaN
        where unknown.
    distance : {"plane", "range"}
        ``D``: the distance of the point's tangent plane to the sensor
        (``-N . p``; one spot per plane), or the point's own distance to the
        sensor (the thesis's Eq. 2.1; one short line per plane).

    Returns
    -------
    (H, W, 3) float32
        NaN where the point or its normal is unknown.

    Examples
    --------
    >>> import numpy as np
    >>> points = np.array([[[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]]])
    >>> normals = np.array([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]])
    >>> nxd_transform(points, normals)[0]
    array([[ 0.,  0., -2.],
           [ 0.,  0., -2.]], dtype=float32)
    """
    points, normals = _check_inputs(points, normals)
    if distance == "plane":
        scale = -np.einsum("ijk,ijk->ij", normals, points)
    elif distance == "range":
        scale = np.sqrt(np.einsum("ijk,ijk->ij", points, points))
    else:
        raise ValueError(f"distance must be one of {NXD_DISTANCES}, got {distance!r}")
    return (normals * scale[..., None]).astype(np.float32)


def segment_nxd(
    points: ArrayLike,
    normals: ArrayLike,
    *,
    bandwidth: float | None = None,
    min_size: int = 50,
    distance: str = "plane",
    split_disconnected: bool = True,
) -> Segmentation:
    """Segment a frame by mode-seeking clustering of its NxD points.

    Parameters
    ----------
    points, normals : (H, W, 3) float arrays
        As for `nxd_transform`.
    bandwidth : float, optional
        Kernel radius in NxD space (metres). By default three times the
        robust spread of NxD between neighbouring pixels, i.e. of the noise
        within a surface.
    min_size : int
        Clusters (and, with ``split_disconnected``, connected parts) with
        fewer pixels are noise (label 0), as the thesis's lower limit on the
        number of points per Gaussian.
    distance : {"plane", "range"}
        See `nxd_transform`.
    split_disconnected : bool
        Give each connected part of a cluster its own segment.

    Returns
    -------
    Segmentation
        Labels (largest first), least-squares planes, residuals, sizes.

    Examples
    --------
    A wall and a box in front of it: two planes, two spots in NxD space.

    >>> import numpy as np
    >>> rows, cols = np.mgrid[0:60, 0:80]
    >>> depth = np.where((rows > 20) & (rows < 40) & (cols > 20) & (cols < 50), 2.0, 3.0)
    >>> rays = np.dstack([(cols - 40) / 100, (rows - 30) / 100, np.ones(rows.shape)])
    >>> points = rays * depth[..., None]
    >>> normals = np.broadcast_to([0.0, 0.0, -1.0], points.shape)
    >>> segment_nxd(points, normals, bandwidth=0.2).sizes.tolist()
    [0, 4249, 551]
    """
    points, normals = _check_inputs(points, normals)
    if isinstance(min_size, bool) or not isinstance(min_size, (int, np.integer)) or min_size < 1:
        raise ValueError(f"min_size must be an integer >= 1, got {min_size!r}")
    nxd = nxd_transform(points, normals, distance=distance)
    known = np.isfinite(nxd).all(axis=2) & np.isfinite(points).all(axis=2)
    if bandwidth is None:
        bandwidth = _default_bandwidth(nxd, known)
    elif not (isinstance(bandwidth, (int, float)) and math.isfinite(bandwidth) and bandwidth > 0):
        raise ValueError(f"bandwidth must be > 0 (metres in NxD space), got {bandwidth!r}")
    clusters = np.zeros(known.shape, np.int32)
    if known.any():
        clusters[known] = _mode_seek(nxd[known].astype(np.float64), float(bandwidth), min_size)
    if split_disconnected:
        clusters = _split_connected(clusters, min_size)
    moments = _label_moments(points, clusters, int(clusters.max()) + 1)
    unlabelled = int(np.count_nonzero(np.isfinite(points).all(axis=2) & (clusters == 0)))
    return Segmentation.from_moments(clusters, moments, unlabelled)


def _default_bandwidth(nxd: np.ndarray, known: np.ndarray) -> float:
    """Three robust standard deviations of the NxD difference between horizontal neighbours."""
    both = known[:, 1:] & known[:, :-1]
    if not both.any():
        return 0.1
    step = np.linalg.norm(nxd[:, 1:][both] - nxd[:, :-1][both], axis=1)
    # Neighbours on different surfaces are the large tail; the median is the noise.
    return max(3.0 * 1.4826 * float(np.median(step)) / math.sqrt(2.0), 1e-3)


def _mode_seek(samples: np.ndarray, bandwidth: float, min_size: int) -> np.ndarray:
    """Cluster index (1..K, 0 = noise) of every sample, by quick shift on a weighted voxel grid.

    Each occupied cell's density is the number of samples within
    ``bandwidth`` (a flat kernel); each cell links to the nearest cell of
    higher density within ``bandwidth``; cells without one are modes, and
    following the links from any cell ends at its mode (quick shift, a
    mean-shift relative that needs no iteration).
    """
    cell = _CELL * bandwidth
    keys, inverse, counts = np.unique(np.floor(samples / cell).astype(np.int64), axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.zeros((len(keys), 3))
    np.add.at(sums, inverse, samples)
    centres = sums / counts[:, None]
    tree = cKDTree(centres)
    pairs = tree.sparse_distance_matrix(tree, bandwidth, output_type="coo_matrix")
    rows, cols, gaps = pairs.row, pairs.col, pairs.data
    density = np.bincount(rows, weights=counts[cols], minlength=len(centres)) + counts * (1 - np.isin(np.arange(len(centres)), rows))
    # Ties broken by index, so that links never form a cycle.
    higher = (density[cols] > density[rows]) | ((density[cols] == density[rows]) & (cols > rows))
    rows, cols, gaps = rows[higher], cols[higher], gaps[higher]
    order = np.lexsort((gaps, rows))
    first = np.unique(rows[order], return_index=True)[1]
    parent = np.arange(len(centres))
    parent[rows[order][first]] = cols[order][first]
    while True:
        grand = parent[parent]
        if np.array_equal(grand, parent):
            break
        parent = grand
    cluster_sizes = np.bincount(parent, weights=counts, minlength=len(centres))
    kept = np.flatnonzero(cluster_sizes >= min_size)
    renumber = np.zeros(len(centres), np.int32)
    renumber[kept[np.argsort(-cluster_sizes[kept], kind="stable")]] = np.arange(1, len(kept) + 1, dtype=np.int32)
    return renumber[parent][inverse]


def _split_connected(clusters: np.ndarray, min_size: int) -> np.ndarray:
    """Each 4-connected part of each cluster as its own label; parts under ``min_size`` pixels become 0."""
    result = np.zeros_like(clusters)
    next_label = 1
    for cluster in range(1, int(clusters.max()) + 1):
        count, parts, stats, _ = cv2.connectedComponentsWithStats((clusters == cluster).astype(np.uint8), connectivity=4)
        for part in range(1, count):
            if stats[part, cv2.CC_STAT_AREA] >= min_size:
                result[parts == part] = next_label
                next_label += 1
    return result
