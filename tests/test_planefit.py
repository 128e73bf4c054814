"""Plane fits from moments: total least squares, and the fit along the rays for range-sensor points."""

import numpy as np
import pytest

from rangesurf._planefit import add_point, planes_from_moments, ray_planes_kernel, ray_weight

# A plane seen obliquely (53 degrees from the optical axis): n . p + d = 0, n facing the sensor.
NORMAL = np.array([-0.8, 0.0, -0.6])
OFFSET = 1.8


def plane_seen_from_origin(sigma: float, count: int = 16000, seed: int = 0) -> np.ndarray:
    """Points where rays in a 4.6-degree cone (a 40 cm patch) meet the plane, with range noise ``sigma`` along each ray."""
    rng = np.random.default_rng(seed)
    rays = np.column_stack([rng.uniform(-0.04, 0.04, count), rng.uniform(-0.04, 0.04, count), np.ones(count)])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    ranges = -OFFSET / (rays @ NORMAL)
    return rays * (ranges + rng.normal(0.0, sigma, count))[:, None]


def moments_of(points: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    plain, weighted = np.zeros((1, 10)), np.zeros((1, 10))
    for x, y, z in points:
        add_point(plain[0], x, y, z)
        w = ray_weight(x, y, z, sigma)
        weighted[0] += w * np.array([1, x, y, z, x * x, x * y, x * z, y * y, y * z, z * z])
    return plain, weighted


def angle_deg(plane: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(plane[:3] @ NORMAL)))))


def test_noise_free_points_give_the_plane_exactly():
    plain, weighted = moments_of(plane_seen_from_origin(0.0, count=50), 0.01)
    for plane in (planes_from_moments(plain)[0][0], ray_planes_kernel(weighted)[0]):
        np.testing.assert_allclose(plane, [*NORMAL, OFFSET], atol=1e-9)


def test_range_noise_tilts_total_least_squares_but_not_the_fit_along_the_rays():
    """SR-3000 noise (3 cm at 3 m) on a 40 cm patch seen at 53 degrees: TLS leans toward the rays, whatever the count."""
    plain, weighted = moments_of(plane_seen_from_origin(0.03), 0.03)
    tls, ray = planes_from_moments(plain)[0][0], ray_planes_kernel(weighted)[0]
    assert angle_deg(tls) > 1.5  # about sigma^2 sin(2 theta) / (2 spread), 1.9 degrees
    assert angle_deg(ray) < 0.3  # the noise alone: about 0.1 degrees for 16,000 points
    assert ray[3] == pytest.approx(OFFSET, abs=0.005)


def test_degenerate_sets_give_nan():
    empty = np.zeros((1, 10))
    one_ray = moments_of(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 3.0]]), 0.01)[1]
    for weighted in (empty, one_ray):
        assert np.isnan(ray_planes_kernel(weighted)).all()
