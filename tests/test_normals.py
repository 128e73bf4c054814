"""Normals against analytic planes, the NumPy references and simulator ground truth."""

import numpy as np
import pytest

from rangesurf import simulate
from rangesurf.denoise import denoise_range
from rangesurf.edges import surface_boundaries
from rangesurf.frame import PinholeProjection, get_sensor
from rangesurf._grid import point_ranges
from rangesurf._planefit import add_point
from rangesurf.normals import (
    _box_normals_reference,
    _inverse_depth_reference,
    _plane_fit_reference,
    _plane_normals,
    _spikes_and_jumps,
    depth_discontinuities,
    estimate_normals,
    normal_angle_error,
)

SR3000 = get_sensor("sr3000")


def plane_points(normal, d, projection=SR3000.projection, shape=SR3000.shape):
    """Sensor-frame points of the plane n . p + d = 0 seen through a pinhole (NaN where behind)."""
    rays = projection.directions(*shape)
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    with np.errstate(divide="ignore"):
        depth = -d / (rays @ normal)
    depth[depth <= 0] = np.nan
    return (rays * depth[..., None]).astype(np.float32)


def errors(normals, normal):
    reference = np.broadcast_to(np.asarray(normal, float) / np.linalg.norm(normal), normals.shape)
    return normal_angle_error(normals, reference)


TILTED = (0.3, -0.5, -0.81)


@pytest.mark.parametrize("method", ["adaptive", "box", "cross"])
@pytest.mark.parametrize("pinhole", [True, False])
def test_noise_free_plane_is_exact(method, pinhole):
    points = plane_points(TILTED, 2.0)
    normals = estimate_normals(points, method=method, projection=SR3000.projection if pinhole else None)
    assert np.nanmax(errors(normals, TILTED)) < 0.05
    assert np.isfinite(normals).all()


def test_normals_face_the_sensor():
    frames, _ = simulate.simulate_sequence("arena", "sr3000", 1, seed=2)
    frame = frames[0]
    normals = estimate_normals(frame.points, projection=frame.sensor.projection)
    facing = np.einsum("ijk,ijk->ij", normals, frame.points)
    assert np.nanmax(facing) <= 0
    assert np.allclose(np.linalg.norm(normals[np.isfinite(normals[..., 0])], axis=1), 1, atol=1e-5)


def test_generic_kernel_matches_numpy_reference():
    rng = np.random.default_rng(3)
    points = plane_points(TILTED, 2.0, shape=(30, 40))
    points[..., 2] += rng.normal(0, 0.003, points.shape[:2]).astype(np.float32)
    points[5, 7] = np.nan
    normals, radius = estimate_normals(points, method="box", window=5, return_window=True)
    reference = _box_normals_reference(points, radius)
    usable = radius >= 1
    assert usable.mean() > 0.9
    assert np.nanmax(normal_angle_error(normals, reference)[usable]) < 0.05  # float32 input


@pytest.mark.parametrize("size", [5, 9])
def test_pinhole_kernel_matches_numpy_reference(size):
    """Every pixel that took the window, the border's clipped windows included."""
    rng = np.random.default_rng(4)
    projection = PinholeProjection(fx=100.0, fy=100.0, cx=20.0, cy=15.0)
    points = plane_points(TILTED, 2.0, projection=projection, shape=(30, 40))
    points *= (1 + rng.normal(0, 0.002, points.shape[:2]))[..., None].astype(np.float32)
    normals, radius = estimate_normals(points, projection=projection, method="box", window=size, return_window=True)
    reference = _inverse_depth_reference(points, projection, size)
    used = radius == size // 2
    assert used.sum() > 1000 and used[0, 0] and used[-1, 20]
    assert np.isfinite(reference[used]).all()
    assert np.max(normal_angle_error(normals, reference)[used]) < 0.05


def test_adaptive_ladder_matches_numpy_reference_at_each_size():
    """With a noise model, each pixel's normal is the reference fit over the window it chose."""
    rng = np.random.default_rng(5)
    projection = PinholeProjection(fx=100.0, fy=100.0, cx=25.0, cy=20.0)
    points = plane_points(TILTED, 2.0, projection=projection, shape=(40, 50))
    points *= (1 + rng.normal(0, 0.001, points.shape[:2]))[..., None].astype(np.float32)
    points[10:14, 30:34] = np.nan  # a hole: windows around it shrink
    normals, radius = estimate_normals(points, projection=projection, range_sigma=0.002, return_window=True)
    for half in (2, 5, 7):
        chosen = radius == half
        assert chosen.any()
        reference = _inverse_depth_reference(points, projection, 2 * half + 1)
        assert np.max(normal_angle_error(normals, reference)[chosen]) < 0.05


def test_plane_normals_match_eigh():
    """The Newton-method plane fits of the fallback against NumPy's eigen decomposition, all sets in one call."""
    rng = np.random.default_rng(6)
    spreads = (1e-3, 0.1, 0.5, 1.0)
    # One set per spread, then a collinear one and one of two points: no plane.
    sums = np.zeros((len(spreads) + 2, 10))
    references = []
    for row, spread in enumerate(spreads):
        points = rng.normal(0, 1, (25, 3)) * (1.0, 0.7, spread) + (0.2, -0.1, 2.0)
        for x, y, z in points:
            add_point.py_func(sums[row], x, y, z)
        references.append(_plane_fit_reference(points)[0])
    for t in range(5):
        add_point.py_func(sums[-2], float(t), 2.0 * t, 0.0)
    for t in range(2):
        add_point.py_func(sums[-1], float(t), 0.5, 1.0 - t)
    normals = _plane_normals(sums)
    for row, reference in enumerate(references):
        assert abs(abs(normals[:, row] @ reference) - 1) < 1e-9
    assert np.isnan(normals[:, -2:]).all()


def test_windows_never_mix_across_a_depth_step():
    """A box in front of a wall: every normal, right up to the step, is the wall's and the box's (0, 0, -1)."""
    points = plane_points((0, 0, -1), 3.0)
    rays = SR3000.projection.directions(*SR3000.shape)
    box = np.zeros(SR3000.shape, bool)
    box[40:100, 60:120] = True
    points[box] = (rays[box] * 2.0).astype(np.float32)
    for projection in (SR3000.projection, None):
        normals = estimate_normals(points, projection=projection)
        assert np.nanmax(errors(normals, (0, 0, -1))) < 0.5
    jumps = depth_discontinuities(np.linalg.norm(points, axis=2))
    assert jumps[40, 80] and jumps[39, 80] and not jumps[70, 90]


def test_holes_and_spikes_do_not_spoil_neighbours():
    points = plane_points(TILTED, 2.0)
    points[50, 50] = np.nan
    points[80, 100] *= 1.5  # a spike, 50 % too far
    for projection in (SR3000.projection, None):
        normals = estimate_normals(points, projection=projection)
        neighbours = errors(normals, TILTED)[45:56, 45:56]
        assert np.isnan(normals[50, 50]).all()
        assert np.nanmax(neighbours) < 0.05
        assert np.nanmax(errors(normals, TILTED)[75:86, 95:106]) < 0.05
    assert not depth_discontinuities(np.linalg.norm(points, axis=2))[80, 99]


def test_adaptive_window_shrinks_at_a_crease():
    """Near a crease (no depth jump) the residual test picks small windows, which do not mix the two faces."""
    projection = SR3000.projection
    rays = projection.directions(*SR3000.shape)
    left, right = np.array([0.5, 0.0, -1.0]), np.array([-0.5, 0.0, -1.0])
    left, right = left / np.linalg.norm(left), right / np.linalg.norm(right)
    # A ridge pointing at the sensor: each pixel sees the nearer of the two faces.
    depth = np.minimum(2.0 / -(rays @ left), 2.0 / -(rays @ right))
    points = (rays * depth[..., None]).astype(np.float32)
    rng = np.random.default_rng(0)
    points *= (1 + rng.normal(0, 0.0005, depth.shape))[..., None].astype(np.float32)
    truth = np.where((2.0 / -(rays @ left) < 2.0 / -(rays @ right))[..., None], left, right)
    adaptive, radius = estimate_normals(points, projection=projection, range_sigma=0.001, return_window=True)
    large = estimate_normals(points, projection=projection, method="box", window=15)
    crease = int(np.argmin(np.abs(depth[72] - depth[72].max())))
    near = np.zeros(depth.shape, bool)
    near[10:-10, crease - 6 : crease + 7] = True
    far = np.zeros(depth.shape, bool)
    far[10:-10, 10:30] = True
    assert np.median(radius[near]) < np.median(radius[far]) == 7
    assert np.nanmean(normal_angle_error(adaptive, truth)[near]) < 0.5 * np.nanmean(normal_angle_error(large, truth)[near])


@pytest.mark.parametrize("sensor", ["sr3000", "kinect"])
def test_simulated_error_against_ground_truth(sensor):
    """Denoised frames: adaptive normals beat the fixed window, which beats the cross product."""
    frames, truths = simulate.simulate_sequence("arena", sensor, 1, seed=11)
    frame, truth = frames[0], truths[0]
    smooth = denoise_range(frame.range, sensor=frame.sensor, intensity=frame.intensity, rays=frame.rays)
    points = (frame.rays * smooth[..., None]).astype(np.float32)
    sigma = frame.sensor.range_sigma(smooth, frame.intensity)
    flat = ~surface_boundaries(truth.surface_id)
    flat[1:-1, 1:-1] &= flat[:-2, 1:-1] & flat[2:, 1:-1] & flat[1:-1, :-2] & flat[1:-1, 2:]
    flat &= ~truth.mixed
    mean_error = {}
    for method in ("adaptive", "box", "cross"):
        normals = estimate_normals(points, projection=frame.sensor.projection, range_sigma=sigma, method=method)
        mean_error[method] = float(np.nanmean(normal_angle_error(normals, truth.normals)[flat]))
    assert mean_error["adaptive"] < mean_error["box"] < mean_error["cross"]
    assert mean_error["adaptive"] < 5.0


@pytest.mark.parametrize(
    "points, options, message",
    [
        (np.zeros((4, 4)), {}, r"\(H, W, 3\)"),
        (np.zeros((4, 4, 2)), {}, r"\(H, W, 3\)"),
        (np.zeros((4, 4, 3), np.int32), {}, "float"),
        (np.full((4, 4, 3), np.inf), {}, "Inf"),
        (np.ones((4, 4, 3)), {"window": 4}, "odd integer"),
        (np.ones((4, 4, 3)), {"window": 1}, "odd integer"),
        (np.ones((4, 4, 3)), {"method": "svd"}, "method must be one of"),
        (np.ones((4, 4, 3)), {"depth_jump": 0}, "depth_jump"),
        (np.ones((4, 4, 3)), {"range_sigma": -1.0}, "range_sigma"),
    ],
)
def test_bad_input_is_refused(points, options, message):
    with pytest.raises(ValueError, match=message):
        estimate_normals(points, **options)


@pytest.mark.parametrize("shape", [(1, 1), (2, 2), (3, 3), (40, 50)])
@pytest.mark.parametrize("pinhole", [True, False])
def test_degenerate_frames_give_nan_not_errors(shape, pinhole):
    projection = PinholeProjection(100.0, 100.0, shape[1] / 2, shape[0] / 2) if pinhole else None
    empty = np.full(shape + (3,), np.nan, np.float32)
    assert np.isnan(estimate_normals(empty, projection=projection)).all()
    single = empty.copy()
    single[0, 0] = (0.0, 0.0, 2.0)
    assert np.isnan(estimate_normals(single, projection=projection)).all()


def test_angle_error_shapes_must_match():
    with pytest.raises(ValueError, match="same"):
        normal_angle_error(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))


def test_point_ranges_match_numpy_and_count_infinities():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(30, 40, 3)).astype(np.float32)
    points[rng.random((30, 40)) < 0.1] = np.nan
    points[2, 3] = 0.0
    points[4, 5, 1] = np.inf
    points[6, 7] = (np.nan, -np.inf, 1.0)
    distance, valid, n_infinite = point_ranges(points)
    squared = (points.astype(np.float64) ** 2).sum(axis=2)
    expected_valid = (squared > 0) & np.isfinite(squared)
    assert np.array_equal(valid, expected_valid)
    assert np.allclose(distance[valid], np.sqrt(squared[valid]), rtol=1e-6)
    assert np.isnan(distance[~valid]).all()
    assert n_infinite == 2


def spikes_and_jumps_reference(distance, valid, sigma, depth_jump):
    """``(clean, jumps)`` by the rules `depth_discontinuities` states, pixel by pixel."""
    height, width = distance.shape
    noise = np.where(np.isnan(sigma), 0.0, 16.0 * sigma.astype(np.float32) ** 2).astype(np.float32)

    def jump(a, b, limit, step):
        relative = depth_jump * min(distance[a], distance[b])
        return ((distance[a] - distance[b]) / step) ** 2 > max(relative**2, limit)

    def ramp(i, j, di, dj):
        before, after = (i - di, j - dj), (i + 2 * di, j + 2 * dj)
        if min(before) < 0 or after[0] >= height or after[1] >= width or not (valid[before] and valid[after]):
            return False
        step = distance[i + di, j + dj] - distance[i, j]
        others = (distance[i, j] - distance[before], distance[after] - distance[i + di, j + dj])
        return all(o * step > 0 and 0.5 * abs(step) <= abs(o) <= 2.0 * abs(step) for o in others)

    pairs = []
    for i in range(height):
        for j in range(width):
            for di, dj in ((0, 1), (1, 0)):
                q = (i + di, j + dj)
                if q[0] < height and q[1] < width and valid[i, j] and valid[q]:
                    if jump((i, j), q, noise[i, j] + noise[q], 1.0) and not ramp(i, j, di, dj):
                        pairs.append(((i, j), q))
    count = np.zeros((height, width), int)
    for a, b in pairs:
        count[a] += 1
        count[b] += 1
    clean = valid & (count < 3)
    jumps = np.zeros((height, width), bool)
    for a, b in pairs:
        if clean[a] and clean[b]:
            jumps[a] = jumps[b] = True
    for i in range(height):
        for j in range(width):
            for di, dj in ((0, 1), (1, 0)):
                b = (i + 2 * di, j + 2 * dj)
                if b[0] < height and b[1] < width and clean[i, j] and not valid[i + di, j + dj] and clean[b]:
                    if jump((i, j), b, noise[i, j] + noise[b], 2.0):
                        jumps[i, j] = jumps[b] = True
    return clean, jumps


@pytest.mark.parametrize("with_sigma", [True, False])
def test_spikes_and_jumps_match_reference(with_sigma):
    rng = np.random.default_rng(5)
    rows, cols = np.mgrid[0:40, 0:50]
    # A wall with a box in front, a floor-like ramp, holes, and spikes.
    distance = np.where((rows > 10) & (rows < 25) & (cols > 15) & (cols < 30), 1.5, 3.0)
    distance = np.where(rows > 32, 2.0 + 0.08 * (rows - 32), distance) + rng.normal(0, 0.003, rows.shape)
    distance[rng.random(rows.shape) < 0.03] = np.nan
    spikes = rng.random(rows.shape) < 0.02
    distance[spikes] *= 1.5
    distance = distance.astype(np.float32)
    valid = np.isfinite(distance)
    sigma = np.full(rows.shape, 0.01 if with_sigma else np.nan)
    clean, jumps, sigma_ok = _spikes_and_jumps(distance, valid, sigma, 0.05, with_sigma)
    expected_clean, expected_jumps = spikes_and_jumps_reference(distance, valid, sigma, 0.05)
    assert sigma_ok
    assert np.array_equal(clean, expected_clean) and np.array_equal(jumps, expected_jumps)
    assert (valid & ~clean).any() and jumps.any()
