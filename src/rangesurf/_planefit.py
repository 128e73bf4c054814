"""Plane fits from point moments, shared by the normal estimator and the segmenters.

Moments are the 10 sums ``(n, x, y, z, xx, xy, xz, yy, yz, zz)`` of a point
set; a plane fit from them costs the same for 3 points or 3 million.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "add_point", "smallest_eigen", "plane_eigen", "eigenvector", "planes_from_moments", "planes_kernel", "plane_rms",
    "ray_weight", "ray_planes_kernel",
]

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@numba.njit(**_JIT, inline="always")
def add_point(sums, x, y, z, weight=1.0):  # pragma: no cover - compiled
    """Add a point to (``weight`` 1) or take it from (``weight`` -1, with -x, -y, -z) the 10 moments ``sums``."""
    sums[0] += weight
    sums[1] += x
    sums[2] += y
    sums[3] += z
    sums[4] += weight * x * x
    sums[5] += weight * x * y
    sums[6] += weight * x * z
    sums[7] += weight * y * y
    sums[8] += weight * y * z
    sums[9] += weight * z * z


@numba.njit(**_JIT)
def smallest_eigen(sums, normal):  # pragma: no cover - compiled
    """Plane fit of window sums: unit normal of least variance into ``normal``; returns that variance.

    Returns -1 when the fit is undefined (fewer than 3 points, or no plane).
    """
    return plane_eigen(sums, normal)[0]


@numba.njit(**_JIT, inline="always")
def eigenvector(a00, a01, a02, a11, a12, a22, value):  # pragma: no cover - compiled
    """Eigenvector (unnormalised) of the symmetric 3x3 matrix ``a`` for eigenvalue ``value``, and its squared length.

    The largest cross product of two rows of ``a - value I`` (the
    eigenvector is orthogonal to all of them); a squared length of 0 means
    no direction is singled out.
    """
    r0x, r0y, r0z = a00 - value, a01, a02
    r1x, r1y, r1z = a01, a11 - value, a12
    r2x, r2y, r2z = a02, a12, a22 - value
    c0x, c0y, c0z = r0y * r1z - r0z * r1y, r0z * r1x - r0x * r1z, r0x * r1y - r0y * r1x
    c1x, c1y, c1z = r0y * r2z - r0z * r2y, r0z * r2x - r0x * r2z, r0x * r2y - r0y * r2x
    c2x, c2y, c2z = r1y * r2z - r1z * r2y, r1z * r2x - r1x * r2z, r1x * r2y - r1y * r2x
    d0 = c0x * c0x + c0y * c0y + c0z * c0z
    d1 = c1x * c1x + c1y * c1y + c1z * c1z
    d2 = c2x * c2x + c2y * c2y + c2z * c2z
    if d0 >= d1 and d0 >= d2:
        return c0x, c0y, c0z, d0
    if d1 >= d2:
        return c1x, c1y, c1z, d1
    return c2x, c2y, c2z, d2


@numba.njit(**_JIT)
def plane_eigen(sums, normal):  # pragma: no cover - compiled
    """Plane fit of moments: normal into ``normal``; returns the smallest and middle covariance eigenvalues.

    Closed-form eigenvalues of the 3x3 covariance (trigonometric method), the
    eigenvector from the largest cross product of two rows of ``C - lambda I``.
    The middle eigenvalue is the in-plane spread along the narrower
    direction. Returns (-1, -1) when the fit is undefined (fewer than 3
    points, or no plane).
    """
    n = sums[0]
    if n < 3.0:
        return -1.0, -1.0
    mx = sums[1] / n
    my = sums[2] / n
    mz = sums[3] / n
    a00 = sums[4] / n - mx * mx
    a01 = sums[5] / n - mx * my
    a02 = sums[6] / n - mx * mz
    a11 = sums[7] / n - my * my
    a12 = sums[8] / n - my * mz
    a22 = sums[9] / n - mz * mz
    off = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    b00 = a00 - q
    b11 = a11 - q
    b22 = a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off
    if p2 <= 1e-30 * (q * q + 1e-300):
        return -1.0, -1.0
    p = math.sqrt(p2 / 6.0)
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)) / (p * p * p)
    half = min(max(det / 2.0, -1.0), 1.0)
    phi = math.acos(half) / 3.0
    smallest = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    middle = 3.0 * q - smallest - (q + 2.0 * p * math.cos(phi))
    vx, vy, vz, d = eigenvector(a00, a01, a02, a11, a12, a22, smallest)
    if d <= 0.0:
        return -1.0, -1.0
    norm = math.sqrt(d)
    normal[0] = vx / norm
    normal[1] = vy / norm
    normal[2] = vz / norm
    return max(smallest, 0.0), max(middle, 0.0)


def planes_from_moments(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares planes of many point sets at once.

    Parameters
    ----------
    moments : (K, 10) float64
        One row of moments per point set.

    Returns
    -------
    planes : (K, 4) float64
        ``(nx, ny, nz, d)`` with ``n . p + d = 0``, unit ``n`` facing the
        origin (``d >= 0``); NaN for sets of fewer than 3 points.
    rms : (K,) float64
        Root-mean-square point-to-plane distance; NaN likewise.
    """
    moments = np.ascontiguousarray(np.atleast_2d(np.asarray(moments, dtype=np.float64)))
    return planes_kernel(moments)


@numba.njit(**_JIT)
def planes_kernel(moments):  # pragma: no cover - compiled
    """`planes_from_moments` on a C-contiguous float64 array (for other kernels to call)."""
    count = moments.shape[0]
    planes = np.full((count, 4), np.nan)
    rms = np.full(count, np.nan)
    normal = np.empty(3)
    for k in range(count):
        n = moments[k, 0]
        if n < 3.0:
            continue
        smallest, _ = plane_eigen(moments[k], normal)
        if smallest < 0.0:
            continue
        d = -(normal[0] * moments[k, 1] + normal[1] * moments[k, 2] + normal[2] * moments[k, 3]) / n
        sign = -1.0 if d < 0.0 else 1.0
        for j in range(3):
            planes[k, j] = sign * normal[j]
        planes[k, 3] = sign * d
        rms[k] = math.sqrt(smallest)
    return planes, rms


@numba.njit(**_JIT)
def plane_rms(moments, planes):  # pragma: no cover - compiled
    """Root-mean-square distance of each point set (moments ``(K, 10)``) to a given plane ``(K, 4)``, both float64.

    ``E[(n . p + d)^2] = n^T E[p p^T] n + 2 d n . E[p] + d^2``, from the moments alone.
    """
    count = moments.shape[0]
    rms = np.empty(count)
    for k in range(count):
        n = moments[k, 0]
        nx, ny, nz, d = planes[k, 0], planes[k, 1], planes[k, 2], planes[k, 3]
        quadratic = (nx * nx * (moments[k, 4] / n) + ny * ny * (moments[k, 7] / n) + nz * nz * (moments[k, 9] / n)
                     + 2.0 * (nx * ny * (moments[k, 5] / n) + nx * nz * (moments[k, 6] / n) + ny * nz * (moments[k, 8] / n)))
        along = nx * (moments[k, 1] / n) + ny * (moments[k, 2] / n) + nz * (moments[k, 3] / n)
        rms[k] = math.sqrt(max(quadratic + 2.0 * d * along + d * d, 0.0))
    return rms


# --------------------------------------------------------------------------
# Planes of points whose noise lies along the sensor's rays.
# --------------------------------------------------------------------------


@numba.njit(**_JIT, inline="always")
def ray_weight(x, y, z, sigma):  # pragma: no cover - compiled
    """Weight of a point in `ray_planes_kernel`'s moments: squared range over squared range noise."""
    return (x * x + y * y + z * z) / (sigma * sigma)


@numba.njit(**_JIT)
def ray_planes_kernel(weighted):  # pragma: no cover - compiled
    """Planes of point sets seen from the origin whose noise lies along the rays.

    ``weighted`` (K, 10) are moments of each set with each point weighted by
    `ray_weight`: ``(sum w, sum w x, sum w y, sum w z, sum w x x, ..., sum w z z)``.

    Range sensors err along the ray, not along the surface normal. A total
    least-squares fit treats the error as isotropic and, on a plane seen
    obliquely, tilts the normal toward the ray by about
    ``sigma^2 sin(2 theta) / (2 spread)`` (``theta`` the incidence angle,
    ``spread`` the in-plane variance) however many points it has: 3-4 degrees
    on a raw SR-3000 patch. Here the fit is on inverse range, which is
    linear on a plane: ``a . u = 1 / rho`` for the unit ray ``u``, with
    ``a = -n / d``. Weighted by the inverse range's variance ``sigma^2 / rho^4``
    that is the algebraic fit ``a . p = 1`` weighted by ``rho^2 / sigma^2``,
    whose normal equations ``(sum w p p^T) a = sum w p`` come from the
    moments alone. Its only error is the noise, which averages out.

    Returns (K, 4) planes as `planes_kernel` (unit ``n`` facing the origin,
    ``d >= 0``); NaN where the set has fewer than 3 points or the system is
    singular (all points on one ray, or a plane through the origin).
    """
    count = weighted.shape[0]
    planes = np.full((count, 4), np.nan)
    for k in range(count):
        if weighted[k, 0] <= 0.0:
            continue
        m00, m01, m02 = weighted[k, 4], weighted[k, 5], weighted[k, 6]
        m11, m12, m22 = weighted[k, 7], weighted[k, 8], weighted[k, 9]
        b0, b1, b2 = weighted[k, 1], weighted[k, 2], weighted[k, 3]
        # The inverse by cofactors (the matrix is symmetric).
        c00 = m11 * m22 - m12 * m12
        c01 = m02 * m12 - m01 * m22
        c02 = m01 * m12 - m02 * m11
        c11 = m00 * m22 - m02 * m02
        c12 = m01 * m02 - m00 * m12
        c22 = m00 * m11 - m01 * m01
        det = m00 * c00 + m01 * c01 + m02 * c02
        scale = m00 * m00 + m11 * m11 + m22 * m22
        if not det > 1e-12 * scale * math.sqrt(scale):
            continue
        a0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
        a1 = (c01 * b0 + c11 * b1 + c12 * b2) / det
        a2 = (c02 * b0 + c12 * b1 + c22 * b2) / det
        length = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        if not length > 0.0:
            continue
        planes[k, 0] = -a0 / length
        planes[k, 1] = -a1 / length
        planes[k, 2] = -a2 / length
        planes[k, 3] = 1.0 / length
    return planes
