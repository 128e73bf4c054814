"""Every public stage function under hostile shapes and values (property-based, bounded for `make test`).

Allowed outcomes: a result, or a documented error (ValueError or TypeError with a message); never NaN
output where the input was valid, never a hang. Inputs: all-NaN, constant, one valid pixel, ranges
from 1e-6 to 1e6 m, grids from 1x1 up to a few hundred pixels a side (the 4000x4000 case runs once).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis (test extra) is needed for the property tests")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from rangesurf.denoise import denoise_range  # noqa: E402
from rangesurf.frame import PinholeProjection  # noqa: E402
from rangesurf.lod import progressive_order  # noqa: E402
from rangesurf.mesh import Surface, segment_vertices, triangulate_segments  # noqa: E402
from rangesurf.normals import estimate_normals  # noqa: E402
from rangesurf.register import icp  # noqa: E402
from rangesurf.segment import grow_regions, segment_planes  # noqa: E402

EXAMPLES = settings(max_examples=int(os.environ.get("RANGESURF_FUZZ_EXAMPLES", "25")), deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@st.composite
def range_images(draw):
    """Range images of hostile shapes and contents (NaN where there is no return)."""
    height = draw(st.integers(1, 40))
    width = draw(st.integers(1, 40))
    kind = draw(st.sampled_from(["nan", "constant", "one", "random", "extreme", "plane"]))
    scale = draw(st.sampled_from([1e-6, 1e-3, 1.0, 100.0, 1e6]))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    image = np.full((height, width), np.nan, np.float32)
    if kind == "constant":
        image[:] = scale
    elif kind == "one":
        image[rng.integers(height), rng.integers(width)] = scale
    elif kind == "random":
        image[:] = rng.uniform(0.5, 1.5, (height, width)) * scale
        image[rng.random((height, width)) < 0.3] = np.nan
    elif kind == "extreme":
        image[:] = rng.choice([1e-6, 1e-3, 1.0, 1e3, 1e6], (height, width))
    elif kind == "plane":
        rows, cols = np.mgrid[0:height, 0:width]
        image[:] = scale * (1.0 + 0.01 * rows + 0.02 * cols)
    return image


def projection_for(shape):
    height, width = shape
    return PinholeProjection(fx=max(width, 1.0), fy=max(width, 1.0), cx=(width - 1) / 2, cy=(height - 1) / 2)


def points_of(image):
    projection = projection_for(image.shape)
    rays = projection.directions(*image.shape)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    return (rays * image[..., None]).astype(np.float32), projection


def allowed(call):
    """Run ``call``; documented errors (ValueError / TypeError with a message) pass, anything else fails."""
    try:
        return call()
    except (ValueError, TypeError) as error:
        assert str(error), "errors must say what is wrong"
        return None


@EXAMPLES
@given(image=range_images())
def test_denoise(image):
    result = allowed(lambda: denoise_range(image, range_sigma=max(float(np.nanmax(image)) * 0.01, 1e-9) if np.isfinite(image).any() else 0.01))
    if result is not None:
        assert result.shape == image.shape
        assert not np.isinf(result).any()
        # Denoising may remove outliers (NaN) but never invents returns where there were none.
        assert not (np.isfinite(result) & ~np.isfinite(image)).any()


@EXAMPLES
@given(image=range_images(), method=st.sampled_from(["adaptive", "box", "cross"]))
def test_normals(image, method):
    points, projection = points_of(image)
    normals = allowed(lambda: estimate_normals(points, projection=projection if method != "cross" else None, method=method))
    if normals is not None:
        assert normals.shape == points.shape
        finite = np.isfinite(normals).all(axis=-1)
        assert not (finite & ~np.isfinite(points).all(axis=-1)).any()
        assert np.allclose(np.linalg.norm(normals[finite], axis=-1), 1.0, atol=1e-3)


@EXAMPLES
@given(image=range_images())
def test_segmentation_and_surfaces(image):
    points, projection = points_of(image)
    sigma = np.where(np.isfinite(image), np.maximum(np.nan_to_num(image) * 0.01, 1e-9), 1.0)
    segmentation = allowed(lambda: segment_planes(points, range_sigma=sigma, projection=projection))
    if segmentation is None:
        return
    assert segmentation.labels.shape == image.shape
    assert not (segmentation.labels > 0)[~np.isfinite(image)].any()
    for surfaces in (allowed(lambda: triangulate_segments(points, segmentation, range_sigma=sigma)),
                     allowed(lambda: segment_vertices(points, segmentation, range_sigma=sigma))):
        for surface in surfaces or []:
            assert np.isfinite(surface.vertices).all()
            for values in surface.uncertainty.values():
                assert not np.isnan(values).any()
    normals = allowed(lambda: estimate_normals(points, projection=projection))
    if normals is not None:
        grown = allowed(lambda: grow_regions(points, normals, range_sigma=sigma))
        assert grown is None or grown.labels.shape == image.shape


@EXAMPLES
@given(count=st.integers(0, 60), kind=st.sampled_from(["grid", "collinear", "duplicates", "random"]),
       seed=st.integers(0, 2**16))
def test_progressive_order(count, kind, seed):
    rng = np.random.default_rng(seed)
    if kind == "collinear":
        vertices = np.column_stack([np.arange(count), np.zeros(count), np.full(count, 2.0)])
    elif kind == "duplicates":
        vertices = np.tile([[0.1, 0.2, 2.0]], (count, 1))
    elif kind == "grid":
        side = max(int(np.sqrt(count)), 1)
        rows, cols = np.mgrid[0:side, 0:side] * 0.05
        vertices = np.column_stack([cols.ravel(), rows.ravel(), 2.0 + 0.01 * rng.standard_normal(side * side)])
    else:
        vertices = rng.uniform(-1, 1, (count, 3))
    faces = np.zeros((0, 3), np.int32)
    surface = Surface(vertices, faces, np.tile([0, 0, -1.0], (len(vertices), 1)), np.full((len(vertices), 2), -1))
    order, error = progressive_order(surface)
    assert sorted(order.tolist()) == list(range(len(vertices)))
    assert not np.isnan(error).any()


@EXAMPLES
@given(count=st.integers(0, 300), scale=st.sampled_from([1e-6, 1.0, 1e6]), seed=st.integers(0, 2**16))
def test_icp(count, scale, seed):
    rng = np.random.default_rng(seed)
    target = rng.uniform(-1, 1, (count, 3)) * scale
    normals = rng.standard_normal((count, 3))
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    result = allowed(lambda: icp(target + 0.001 * scale, target, normals, max_correspondence_distance=0.1 * scale,
                                 min_inliers=10, max_iterations=10))
    if result is not None:
        assert np.isfinite(result.T_target_source).all()


@pytest.mark.slow
def test_a_4000_by_4000_frame_goes_through():
    """The largest grid of the reliability issue: one pass of the per-frame stages, no crash, finite output."""
    height = width = 4000
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    image = (3.0 + 0.0001 * rows).astype(np.float32)
    image[::97, ::89] = np.nan
    points, projection = points_of(image)
    normals = estimate_normals(points, projection=projection)
    assert np.isfinite(normals[1:-1, 1:-1]).mean() > 0.9
