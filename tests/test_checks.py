"""The shared input checks: what they accept, convert and refuse."""

import numpy as np
import pytest

from rangesurf._checks import check_point_grid


def test_a_decimated_point_grid_is_copied_out_and_checked_for_inf():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(12, 10, 3)).astype(np.float32)
    points[1, 1, 2] = np.nan
    points[3, 3, 0] = np.inf  # row 3 is skipped by [::2]
    view = points[::2, ::3]
    checked = check_point_grid(view)
    assert checked.flags.c_contiguous and checked.dtype == np.float32
    np.testing.assert_array_equal(checked, np.ascontiguousarray(view))
    points[4, 3, 1] = -np.inf
    points[6, 6, 2] = np.inf
    with pytest.raises(ValueError, match=r"points contain Inf \(2 values\)"):
        check_point_grid(points[::2, ::3])
    # float64 and contiguous inputs take the plain conversion, with the same check.
    with pytest.raises(ValueError, match=r"points contain Inf \(3 values\)"):
        check_point_grid(points.astype(np.float64))
