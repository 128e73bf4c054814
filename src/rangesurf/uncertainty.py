"""The four uncertainty levels and how well they are calibrated (thesis Section 2.4, Figure 2.16).

Every vertex of a model surface carries standard deviations in metres
along its normal:

* **UL1, sensor**: the sensor's range noise at the vertex's range and
  intensity (`SensorModel.range_sigma`), seen along the normal
  (``sigma |cos(incidence)|``), reduced by what denoising removed as the
  data shows it (a planar segment's fit residual against the noise the
  model predicts for it); for a fused vertex, the noise of the
  inverse-variance weighted mean of its observations,
  ``1 / sum(1 / sigma_i^2)``, raised where those observations scatter more
  than the model predicts once several are in, never lowered where they
  scatter less: an error every observation shares does not scatter
  (`rangesurf.merge.planar`). That shrinks with every frame fused, so
  what frames do not average must not reach the vertices: denoising's own
  systematic error (diffusion lengthens a plane's convex range image and
  rounds creases, by up to 0.1 sigma at close range) is estimated from the
  segments' noise-free planes and removed before merging
  (`rangesurf.denoise.diffusion.remove_diffusion_bias`), and the segments'
  residuals are measured about the corrected points. A bridged vertex
  (not seen, on the fitted plane) takes the UL1 and UL2 of the cells around
  its gap.
* **UL2, patch fit**: for a frame's segment, its plane fit's RMS residual;
  for a fused vertex, the part of its distance from its patch's fitted plane
  that UL1 does not explain (half that distance as one sigma: the +-2 sigma
  band reaches the plane).
* **UL3, registration and merging**: the world pose covariance of the
  frames that saw the vertex (drift included) projected on the normal
  (``J Sigma J^T`` with ``J = [p x n, n]``), and the disagreement of the
  fused observations beyond their noise; for bridged gaps, the gap. ICP's
  covariance is scaled up for the correlation of its residuals
  (`rangesurf.register.FrameTracker`, ``icp_variance_scale``); a pose
  corrected against the model keeps the share of its variance that the
  patches, placed by the same drifting sensor, share with it
  (`rangesurf.merge.GlobalModel.align`).
* **UL4, level of detail**: the RMS height error of the removed vertices nearest
  to a kept one, at the level shown (`rangesurf.lod`).

Beyond the thesis, the levels are checked against ground truth: `coverage`
measures, on simulated data, how much of the true surface lies within
``+-k sigma`` of the model, per level and for their root sum of squares;
calibrated levels put about 95 % of it inside ``+-2 sigma``
(``benchmarks/calibration.py`` reports it).

Examples
--------
>>> import numpy as np
>>> from rangesurf.mesh import Surface
>>> vertices = np.array([[0.0, 0, 2.01], [1, 0, 1.97], [0, 1, 2.0]])
>>> surface = Surface(vertices, [[0, 1, 2]], np.tile([0, 0, -1.0], (3, 1)), np.full((3, 2), -1),
...                   uncertainty={"UL1": np.full(3, 0.01)})
>>> coverage([surface], np.array([[0.0, 0, -1, 2.0]]))["UL1"]
0.6666666666666666
"""

from __future__ import annotations

import numpy as np

from rangesurf.mesh import UNCERTAINTY_LEVELS, Surface

__all__ = ["distance_to_planes", "coverage"]


def distance_to_planes(vertices: np.ndarray, normals: np.ndarray, planes: np.ndarray, *, max_angle: float = 25.0) -> np.ndarray:
    """Distance (metres) of each vertex from the nearest of ``planes`` whose normal agrees with its own.

    Parameters
    ----------
    vertices, normals : (N, 3) arrays
    planes : (P, 4) array
        ``(nx, ny, nz, d)`` with unit normals, ``n . p + d = 0``.
    max_angle : float
        Degrees between the vertex normal and a plane's normal (either
        orientation) for the plane to count; ``inf`` where none does.
    """
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    normals = np.asarray(normals, np.float64).reshape(-1, 3)
    planes = np.asarray(planes, np.float64).reshape(-1, 4)
    distance = np.abs(vertices @ planes[:, :3].T + planes[:, 3])
    agree = np.abs(normals @ planes[:, :3].T) >= np.cos(np.radians(max_angle))
    distance[~agree] = np.inf
    return distance.min(axis=1) if len(planes) else np.full(len(vertices), np.inf)


def coverage(surfaces: list[Surface], planes: np.ndarray, *, k: float = 2.0, levels: tuple[str, ...] = UNCERTAINTY_LEVELS,
             max_distance: float = 0.2) -> dict[str, float]:
    """Share of vertices whose distance to the true surface is within ``k`` of their sigma, per level and combined.

    The true surface is given as planes (a simulated scene's `Scene.planes`);
    vertices farther than ``max_distance`` from any agreeing plane (on a
    non-planar object, or misassigned) are left out and counted in
    ``"unmatched"``.

    Returns
    -------
    dict
        ``{level: share}`` for each level present, ``"combined"`` (root sum of
        squares of those levels), ``"matched"`` (vertices compared) and
        ``"unmatched"``.
    """
    if not surfaces:
        return {"combined": float("nan"), "matched": 0, "unmatched": 0}
    vertices = np.vstack([surface.vertices for surface in surfaces])
    normals = np.vstack([surface.normals for surface in surfaces])
    error = distance_to_planes(vertices, normals, planes)
    matched = np.isfinite(error) & (error <= max_distance)
    result: dict[str, float] = {}
    squares = np.zeros(len(vertices))
    for level in levels:
        if not any(level in surface.uncertainty for surface in surfaces):
            continue
        sigma = np.concatenate([np.nan_to_num(surface.uncertainty[level].astype(np.float64)) if level in surface.uncertainty
                                else np.zeros(surface.n_vertices) for surface in surfaces])
        squares += sigma**2
        result[level] = float(np.mean(error[matched] <= k * sigma[matched])) if matched.any() else float("nan")
    result["combined"] = float(np.mean(error[matched] <= k * np.sqrt(squares[matched]))) if matched.any() else float("nan")
    result["matched"] = int(matched.sum())
    result["unmatched"] = int((~matched).sum())
    return result
