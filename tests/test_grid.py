"""Small shared kernels on organized grids, against NumPy."""

import numpy as np

from rangesurf._grid import points_along_rays


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
