"""Small shared kernels on organized grids, against NumPy."""

import numpy as np

from rangesurf._grid import median_footprint, points_along_rays


def test_points_along_rays_are_numpys_float32_product_nan_included():
    rng = np.random.default_rng(1)
    for ray_type, range_type in ((np.float32, np.float32), (np.float64, np.float64), (np.float32, np.float64)):
        rays = rng.normal(size=(7, 9, 3)).astype(ray_type)
        ranges = rng.uniform(0.3, 7.0, size=(7, 9)).astype(range_type)
        ranges[2, 3] = np.nan
        points = points_along_rays(rays, ranges)
        assert points.dtype == np.float32 and points.flags.c_contiguous
        np.testing.assert_array_equal(points, np.multiply(rays, ranges[..., None], dtype=np.float32))
        assert np.isnan(points[2, 3]).all()


def test_median_footprint_is_numpys_median_of_the_finite_positive_products():
    rng = np.random.default_rng(2)
    for rows, columns in ((8, 4), (4, 1), (1, 1)):
        ranges = rng.uniform(0.3, 7.0, size=(30, 41)).astype(np.float32)
        ranges[rng.random(ranges.shape) < 0.2] = np.nan
        ranges[0, 1], ranges[1, 5] = np.inf, 0.0
        sample = ranges[::rows, 1::columns]
        angles = rng.uniform(0.001, 0.01, size=sample.shape).astype(np.float32)
        products = angles * sample
        expected = float(np.median(products[np.isfinite(products) & (products > 0)]))
        assert median_footprint(angles, ranges, rows, columns) == expected
    assert median_footprint(angles, np.full_like(ranges, np.nan), rows, columns) == 0.0
