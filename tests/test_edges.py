"""Edges: detection against known steps and simulated ground truth, thesis clean-up, scores."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy import ndimage

from rangesurf import simulate as sim
from rangesurf.edges import (
    EDGE_METHODS,
    EdgeScores,
    clean_edges,
    combined_edges,
    crease_free_mask,
    detect_edges,
    edge_difference,
    edge_scores,
    equalize_histogram,
    normalize_range,
    surface_boundaries,
    true_depth_edges,
)

GRADIENT_METHODS = ["sobel", "prewitt", "roberts"]


# --------------------------------------------------------------------------
# Helpers and references.
# --------------------------------------------------------------------------


def _box_in_front_of_wall(background: str = "flat") -> np.ndarray:
    """(60, 80) range image: a box face at 2 m in front of a wall about 3 m away."""
    cols = np.arange(80)[None, :].repeat(60, axis=0)
    walls = {
        "flat": np.full((60, 80), 3.0),
        # A wall tilted away from the sensor: range grows along the columns.
        "tilted": 2.8 + 0.01 * cols,
        # A flat wall seen by a pinhole camera: range grows toward the sides.
        "perspective": 3.0 / np.cos(np.deg2rad(0.3 * (cols - 40))),
    }
    depth = walls[background].astype(np.float32)
    depth[15:45, 20:60] = 2.0
    return depth


def _clean_edges_reference(edges: np.ndarray, border_width: int = 2, continuity: str = "opposite") -> np.ndarray:
    """Plain loops over the thesis's rules (the reference for `clean_edges`)."""
    height, width = edges.shape
    cleared = edges.copy()
    for r in range(height):
        for c in range(width):
            if min(r, c, height - 1 - r, width - 1 - c) < border_width:
                cleared[r, c] = False

    def edge(r: int, c: int) -> bool:
        return 0 <= r < height and 0 <= c < width and bool(cleared[r, c])

    ring = [(dr, dc) for dr in range(-2, 3) for dc in range(-2, 3) if max(abs(dr), abs(dc)) == 2]
    out = cleared.copy()
    for r in range(height):
        for c in range(width):
            if not cleared[r, c]:
                continue
            if any(edge(r + dr, c + dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)):
                continue
            if continuity == "opposite":
                continued = any(edge(r + dr, c + dc) and edge(r - dr, c - dc) for dr, dc in ring)
            else:
                continued = any(edge(r + dr, c + dc) for dr, dc in ring)
            out[r, c] = continued
    return out


def _scoring_mask(truth: sim.GroundTruth, depth_edges: np.ndarray, *, band: int = 3) -> np.ndarray:
    """Pixels to score depth edges on: all but the creases and the 2-pixel border.

    A crease (two surfaces meeting without a depth jump: wall and floor) is a
    real surface boundary that the detectors rightly find, a few pixels off
    after smoothing, but it is not a depth edge; detections within ``band``
    pixels of one are neither right nor wrong. The border is what
    `clean_edges` clears, so raw and cleaned maps are scored alike.
    """
    mask = crease_free_mask(truth.surface_id, depth_edges, band=band)
    mask[:2] = mask[-2:] = False
    mask[:, :2] = mask[:, -2:] = False
    return mask


@pytest.fixture(scope="module")
def arena_frames():
    """Eight SR-3000 arena views around the loop, noise-free, with range noise only, and fully noisy."""
    poses = sim.default_trajectory("arena", 200, frame_rate=25.0)[::25]
    noises = {
        "none": sim.SimulationNoise.none(),
        "range": dataclasses.replace(sim.SimulationNoise.none(), range_noise=True),
        "full": sim.SimulationNoise(),
    }
    return {
        name: sim.simulate_sequence("arena", "sr3000", len(poses), seed=11, noise=noise, trajectory=poses)
        for name, noise in noises.items()
    }


def _scores(frames, truths, method: str, *, clean: bool = False) -> list[EdgeScores]:
    out = []
    for frame, truth in zip(frames, truths):
        depth_edges = true_depth_edges(truth.range, surface_id=truth.surface_id)
        detected = detect_edges(frame.range, method=method)
        if clean:
            detected = clean_edges(detected)
        out.append(edge_scores(detected, depth_edges, tolerance=1, mask=_scoring_mask(truth, depth_edges)))
    return out


# --------------------------------------------------------------------------
# Detection on a known step.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("method", EDGE_METHODS)
@pytest.mark.parametrize("background", ["flat", "tilted", "perspective"])
def test_each_method_finds_a_box_step_and_little_else(method, background):
    depth = _box_in_front_of_wall(background)
    truth = true_depth_edges(depth)
    assert truth.sum() == 2 * (2 * 30 + 2 * 40) - 4  # both sides of the outline, corners once
    scores = edge_scores(detect_edges(depth, method=method), truth, tolerance=1)
    assert scores.recall >= 0.9
    assert scores.precision >= 0.9


@pytest.mark.parametrize("method", EDGE_METHODS)
def test_step_found_after_equalisation_and_in_raw_units(method):
    depth = _box_in_front_of_wall("tilted")
    truth = true_depth_edges(depth)
    equalized = detect_edges(depth, method=method, equalize=True)
    in_metres = detect_edges(depth, method=method, normalize=False)
    for detected in (equalized, in_metres):
        scores = edge_scores(detected, truth, tolerance=1)
        assert scores.recall >= 0.9 and scores.precision >= 0.9


@pytest.mark.parametrize("method", EDGE_METHODS)
def test_no_edges_on_planes_or_constant_images(method):
    assert not detect_edges(np.full((30, 40), 2.5), method=method).any()
    ramp = np.tile(np.linspace(2.0, 4.0, 40), (30, 1))
    assert not detect_edges(ramp, method=method).any()


@pytest.mark.parametrize("method", EDGE_METHODS)
def test_invalid_pixels_make_no_edges_unless_asked(method):
    depth = _box_in_front_of_wall()
    holed = depth.copy()
    holed[:, 66:72] = np.nan  # a strip without returns on the wall
    holed[50:55, 5:12] = np.nan
    detected = detect_edges(holed, method=method)
    assert not detected[np.isnan(holed)].any()
    assert np.array_equal(detected, detect_edges(depth, method=method) & np.isfinite(holed))

    outlined = detect_edges(holed, method=method, invalid_as_edge=True)
    valid = np.isfinite(holed)
    hole_outline = valid & ndimage.binary_dilation(~valid)  # 4-neighbours of the holes
    assert np.array_equal(outlined, detected | hole_outline)


@pytest.mark.parametrize("method", EDGE_METHODS)
def test_all_invalid_and_empty_images_have_no_edges(method):
    assert not detect_edges(np.full((12, 9), np.nan, np.float32), method=method).any()
    assert detect_edges(np.zeros((0, 5)), method=method).shape == (0, 5)
    for shape in [(1, 1), (2, 2), (1, 7)]:
        assert not detect_edges(np.full(shape, 3.0), method=method).any()


@pytest.mark.parametrize("method", ["sobel", "prewitt"])
def test_gradient_threshold_is_in_grey_levels_per_pixel(method):
    ramp = np.tile(np.arange(20, dtype=np.float32), (10, 1))  # one level per pixel
    # Replicated borders halve the slope in the first and last columns.
    assert detect_edges(ramp, method=method, threshold=0.99, thin=False, normalize=False)[:, 1:-1].all()
    assert not detect_edges(ramp, method=method, threshold=1.01, thin=False, normalize=False).any()


@pytest.mark.parametrize("method", ["sobel", "prewitt"])
def test_automatic_gradient_threshold_matches_scipy_reference(method):
    rng = np.random.default_rng(5)
    depth = _box_in_front_of_wall("perspective") + rng.normal(0, 0.01, (60, 80)).astype(np.float32)
    grey = (depth - depth.min()) * (255 / (depth.max() - depth.min()))
    operator = {"sobel": (ndimage.sobel, 8), "prewitt": (ndimage.prewitt, 6)}[method]
    gx = operator[0](grey.astype(np.float64), axis=1, mode="nearest") / operator[1]
    gy = operator[0](grey.astype(np.float64), axis=0, mode="nearest") / operator[1]
    squared = gx**2 + gy**2
    # Pixels within float32 round-off of the cut-off may go either way.
    cutoff = 4 * squared.mean()
    decided = np.abs(squared - cutoff) > 1e-3 * cutoff
    detected = detect_edges(depth, method=method, thin=False)
    assert np.array_equal(detected[decided], (squared > cutoff)[decided])


def test_canny_thresholds_are_in_gradient_units():
    step = np.zeros((20, 20), np.float32)
    step[:, 10:] = 40.0  # Sobel / 8 gives 40 / 2 = 20 at the step
    assert detect_edges(step, method="canny", sigma=0, normalize=False, high_threshold=19.0)[:, 9:11].any(axis=1).all()
    assert not detect_edges(step, method="canny", sigma=0, normalize=False, high_threshold=21.0).any()
    low_only = detect_edges(step, method="canny", sigma=0, normalize=False, low_threshold=5.0)
    assert low_only[:, 9:11].any(axis=1).all()


def test_valid_range_fixes_the_grey_scale():
    depth = _box_in_front_of_wall()
    # The step is 1 m; on a 0-100 m scale it is 2.55 grey levels per 2 pixels.
    assert not detect_edges(depth, method="sobel", threshold=2.0, valid_range=(0, 100)).any()
    assert detect_edges(depth, method="sobel", threshold=2.0).any()


# --------------------------------------------------------------------------
# Simulated SR-3000 frames.
# --------------------------------------------------------------------------


def _jumps_to(truth: sim.GroundTruth, *, other_surface: bool) -> np.ndarray:
    """Pixels with a 4-neighbour more than 5 % away, on another surface (or on the same one)."""
    height, width = truth.range.shape
    padded_range = np.pad(truth.range.astype(np.float64), 1, constant_values=np.nan)
    padded_id = np.pad(truth.surface_id, 1, constant_values=-1)
    found = np.zeros((height, width), bool)
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        other_range = padded_range[1 + dr : 1 + dr + height, 1 + dc : 1 + dc + width]
        other_id = padded_id[1 + dr : 1 + dr + height, 1 + dc : 1 + dc + width]
        with np.errstate(invalid="ignore"):
            jump = np.abs(truth.range - other_range) > 0.05 * np.minimum(truth.range, other_range)
        found |= jump & ((other_id != truth.surface_id) if other_surface else (other_id == truth.surface_id))
    return found


def test_true_depth_edges_lie_on_surface_changes_with_depth_jumps(arena_frames):
    _, truths = arena_frames["none"]
    creases = grazing = 0
    for truth in truths:
        labelled = true_depth_edges(truth.range, surface_id=truth.surface_id)
        changes = surface_boundaries(truth.surface_id)
        assert labelled.any()
        assert not (labelled & ~changes).any(), "a depth edge off every surface change"
        assert np.array_equal(labelled, _jumps_to(truth, other_surface=True))
        creases += int((changes & ~labelled).sum())
        # Without labels, surfaces seen at a grazing angle (a box top at the
        # sensor's height, the pillar's limb) add jumps within one surface.
        plain = true_depth_edges(truth.range)
        assert not (labelled & ~plain).any()
        assert np.array_equal(plain & ~labelled, _jumps_to(truth, other_surface=False) & ~labelled)
        grazing += int((plain & ~labelled).sum())
    assert creases > 0, "the arena's wall-floor creases are surface changes without a depth jump"
    assert grazing > 0


def test_near_side_is_the_occluding_half_of_both(arena_frames):
    _, truths = arena_frames["none"]
    for truth in truths:
        both = true_depth_edges(truth.range)
        near = true_depth_edges(truth.range, side="near")
        assert near.any() and not (near & ~both).any()
        # Every near pixel is nearer than some marked neighbour; the far half is the rest.
        far_of_near = ndimage.binary_dilation(near, ndimage.generate_binary_structure(2, 1)) & both & ~near
        assert np.array_equal(both, near | far_of_near)


@pytest.mark.parametrize("method", EDGE_METHODS)
def test_noise_free_frames_detected_with_high_f1(arena_frames, method):
    frames, truths = arena_frames["none"]
    f1 = [s.f1 for s in _scores(frames, truths, method)]
    # Measured: mean F1 0.94-0.96 over the eight views, worst view 0.72 (Sobel).
    assert np.mean(f1) >= 0.9
    assert min(f1) >= 0.65


@pytest.mark.parametrize("method", EDGE_METHODS)
def test_noise_lowers_f1(arena_frames, method):
    clean_f1 = np.mean([s.f1 for s in _scores(*arena_frames["none"], method)])
    for noise in ("range", "full"):
        noisy_f1 = np.mean([s.f1 for s in _scores(*arena_frames[noise], method)])
        assert noisy_f1 < clean_f1 - 0.2


@pytest.mark.parametrize("method", GRADIENT_METHODS)
def test_clean_edges_raises_precision_on_noisy_frames(arena_frames, method):
    frames, truths = arena_frames["range"]
    raw = _scores(frames, truths, method)
    cleaned = _scores(frames, truths, method, clean=True)
    raw_precision = np.array([s.precision for s in raw])
    cleaned_precision = np.array([s.precision for s in cleaned])
    assert cleaned_precision.mean() > raw_precision.mean() + 0.01
    assert (cleaned_precision >= raw_precision).sum() >= 6
    # It removes false detections, not found edges: recall falls by little.
    assert np.mean([s.recall for s in cleaned]) >= np.mean([s.recall for s in raw]) - 0.08


def test_missing_range_marks_the_cut_off_boundary():
    truth = np.array([[3.0, 3.0, np.nan, np.nan]], np.float32)
    assert not true_depth_edges(truth).any()
    assert true_depth_edges(truth, missing_range=7.5).tolist() == [[False, True, True, False]]
    assert not true_depth_edges(truth, missing_range=3.1).any()


# --------------------------------------------------------------------------
# Thesis clean-up.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("continuity", ["opposite", "any"])
@pytest.mark.parametrize("border_width", [0, 1, 2, 3])
def test_clean_edges_matches_loop_reference(continuity, border_width):
    rng = np.random.default_rng(border_width)
    shapes = [(1, 1), (2, 3), (4, 4), (5, 5), (6, 9), (30, 41)]
    for shape in shapes:
        for density in (0.02, 0.08, 0.2, 0.5):
            edges = rng.random(shape) < density
            assert np.array_equal(
                clean_edges(edges, border_width=border_width, continuity=continuity),
                _clean_edges_reference(edges, border_width, continuity),
            ), (shape, density)


def test_clean_edges_clears_two_pixel_border():
    edges = np.ones((10, 12), bool)
    cleaned = clean_edges(edges)
    assert not cleaned[:2].any() and not cleaned[-2:].any()
    assert not cleaned[:, :2].any() and not cleaned[:, -2:].any()
    assert cleaned[2:-2, 2:-2].all()
    assert not clean_edges(np.ones((4, 4), bool)).any()  # no pixel is 2 from every side
    assert np.array_equal(clean_edges(edges, border_width=0), edges)


def test_clean_edges_single_pixels():
    edges = np.zeros((11, 11), bool)
    edges[5, 5] = True
    assert not clean_edges(edges).any(), "an isolated pixel goes"

    pair = edges.copy()
    pair[6, 6] = True  # an 8-neighbour: a two-pixel edge is kept whole
    assert np.array_equal(clean_edges(pair), pair)

    # The thesis's example: first pixels left and right empty, second ones edges.
    dotted = edges.copy()
    dotted[5, 3] = dotted[5, 7] = True
    assert clean_edges(dotted)[5, 5]
    for first, second in [((3, 3), (7, 7)), ((4, 3), (6, 7)), ((3, 5), (7, 5))]:  # other lines across a gap
        line = edges.copy()
        line[first] = line[second] = True
        assert clean_edges(line)[5, 5], (first, second)

    one_sided = edges.copy()
    one_sided[5, 7] = True  # a second-order neighbour on one side only
    assert not clean_edges(one_sided).any()
    assert clean_edges(one_sided, continuity="any")[5, 5]

    bent = edges.copy()
    bent[5, 7] = bent[3, 5] = True  # two ring pixels, not opposite
    assert not clean_edges(bent)[5, 5]


def test_clean_edges_decides_on_the_border_cleared_map():
    edges = np.zeros((9, 9), bool)
    edges[1, 2] = edges[2, 2] = True  # (1, 2) lies in the cleared border
    assert not clean_edges(edges).any()
    assert clean_edges(edges, border_width=1)[2, 2]


# --------------------------------------------------------------------------
# Combination of two branches.
# --------------------------------------------------------------------------


def test_combined_edges_is_union_of_cleaned_branches(arena_frames):
    frames, truths = arena_frames["range"]
    frame, truth = frames[0], truths[0]
    # Stand-ins for the thesis's two denoising branches.
    median = cv2.medianBlur(frame.range, 5)
    smoothed = cv2.bilateralFilter(frame.range, 5, 0.05, 2.0)
    first = clean_edges(detect_edges(median))
    second = clean_edges(detect_edges(smoothed))
    combined = combined_edges(median, smoothed)
    assert np.array_equal(combined, first | second)
    assert np.array_equal(combined_edges(first, second), first | second)
    assert np.array_equal(combined_edges(detect_edges(median), smoothed), first | second)
    assert np.array_equal(combined_edges(median, smoothed, clean=False), detect_edges(median) | detect_edges(smoothed))
    assert np.array_equal(
        combined_edges(median, smoothed, method="sobel", threshold=20.0),
        clean_edges(detect_edges(median, method="sobel", threshold=20.0))
        | clean_edges(detect_edges(smoothed, method="sobel", threshold=20.0)),
    )

    depth_edges = true_depth_edges(truth.range, surface_id=truth.surface_id)
    mask = _scoring_mask(truth, depth_edges)
    recalls = [edge_scores(e, depth_edges, mask=mask).recall for e in (first, second, combined)]
    assert recalls[2] >= max(recalls[:2])


def test_combined_edges_of_complementary_branches():
    horizontal = np.full((30, 30), 3.0)
    horizontal[15:] = 2.0
    vertical = np.full((30, 30), 3.0)
    vertical[:, 15:] = 2.0
    truth = true_depth_edges(horizontal) | true_depth_edges(vertical)
    truth[:2] = truth[-2:] = False
    truth[:, :2] = truth[:, -2:] = False
    scores = edge_scores(combined_edges(horizontal, vertical), truth, tolerance=1)
    assert scores.recall == 1.0 and scores.precision == 1.0


# --------------------------------------------------------------------------
# Grey levels.
# --------------------------------------------------------------------------


def test_normalize_uses_valid_values_only():
    depth = np.array([[np.nan, 1.0, 2.0], [3.0, 5.0, np.nan]], np.float32)
    grey = normalize_range(depth)
    assert grey.dtype == np.uint8
    assert grey.tolist() == [[0, 0, 64], [128, 255, 0]]
    assert normalize_range(np.array([[2, 4], [6, 10]], np.int32)).tolist() == [[0, 64], [128, 255]]


def test_normalize_valid_range_clips():
    depth = np.array([[0.0, 1.0, 2.5, 4.0, 9.0]])
    assert normalize_range(depth, valid_range=(1.0, 4.0)).tolist() == [[0, 0, 128, 255, 255]]


@pytest.mark.parametrize(
    "depth",
    [
        np.full((5, 4), 2.0),
        np.full((5, 4), np.nan),
        np.array([[7.0]]),
        np.array([[np.nan]]),
        np.array([[1.0, np.nan], [1.0, 1.0]]),
    ],
    ids=["constant", "all-nan", "1x1", "1x1-nan", "2x2-constant-with-nan"],
)
def test_normalize_degenerate_images_are_black(depth):
    grey = normalize_range(depth)
    assert grey.shape == depth.shape and grey.dtype == np.uint8 and not grey.any()


def test_normalize_tiny_and_empty_images():
    assert normalize_range(np.array([[1.0, 2.0], [np.nan, 3.0]])).tolist() == [[0, 128], [0, 255]]
    assert normalize_range(np.zeros((0, 3))).shape == (0, 3)


def test_equalize_matches_opencv_without_mask():
    rng = np.random.default_rng(2)
    for shape in [(1, 1), (2, 2), (17, 23), (144, 176)]:
        for high in (3, 60, 256):
            image = rng.integers(0, high, shape, dtype=np.uint8)
            assert np.array_equal(equalize_histogram(image), cv2.equalizeHist(image)), (shape, high)


def test_equalize_uses_masked_pixels_only():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (40, 50), dtype=np.uint8)
    mask = rng.random((40, 50)) < 0.6
    image[~mask] = 128  # pixels that must not count (OpenCV would count them)
    out = equalize_histogram(image, mask=mask)
    # Reference: OpenCV equalising the masked pixels alone.
    expected = cv2.equalizeHist(np.ascontiguousarray(image[mask])[None, :])[0]
    assert np.array_equal(out[mask], expected)
    assert not out[~mask].any()
    assert not np.array_equal(out[mask], cv2.equalizeHist(image)[mask])


def test_equalize_degenerate_masks():
    image = np.full((3, 4), 77, np.uint8)
    assert np.array_equal(equalize_histogram(image), cv2.equalizeHist(image))  # one level keeps its value
    assert not equalize_histogram(image, mask=np.zeros((3, 4), bool)).any()
    one = np.zeros((3, 4), bool)
    one[1, 2] = True
    assert equalize_histogram(image, mask=one).tolist() == [[0] * 4, [0, 0, 77, 0], [0] * 4]
    assert equalize_histogram(np.array([[5]], np.uint8)).tolist() == [[5]]
    assert equalize_histogram(np.array([[5, 9], [9, 200]], np.uint8)).tolist() == [[0, 170], [170, 255]]


def test_equalize_spreads_a_normalised_range_image():
    depth = np.array([[1.0, 1.01, 1.02], [1.03, 5.0, np.nan]])
    grey = normalize_range(depth)
    assert grey[0].tolist() == [0, 1, 1]  # the near values crowd the dark end
    equalized = equalize_histogram(grey, mask=np.isfinite(depth))
    assert equalized.tolist() == [[0, 128, 128], [191, 255, 0]]


# --------------------------------------------------------------------------
# Scores and difference.
# --------------------------------------------------------------------------


def test_edge_scores_known_counts():
    truth = np.zeros((10, 10), bool)
    truth[2:8, 4] = True  # 6 pixels
    detected = np.zeros((10, 10), bool)
    detected[2:8, 5] = True  # beside the truth
    detected[0, 0] = detected[9, 9] = True  # 2 false positives
    exact = edge_scores(detected, truth, tolerance=0)
    assert (exact.true_positives, exact.false_positives, exact.false_negatives) == (0, 8, 6)
    assert (exact.precision, exact.recall, exact.f1) == (0.0, 0.0, 0.0)
    near = edge_scores(detected, truth, tolerance=1)
    assert (near.true_positives, near.false_positives, near.false_negatives) == (6, 2, 0)
    assert (near.n_detected, near.n_truth, near.tolerance) == (8, 6, 1.0)
    assert near.precision == pytest.approx(0.75) and near.recall == 1.0
    assert near.f1 == pytest.approx(2 * 0.75 / 1.75)


def test_edge_scores_tolerance_is_euclidean():
    truth = np.zeros((7, 7), bool)
    truth[3, 3] = True
    diagonal = np.zeros((7, 7), bool)
    diagonal[4, 4] = True
    assert edge_scores(diagonal, truth, tolerance=1).precision == 0.0
    assert edge_scores(diagonal, truth, tolerance=1.5).precision == 1.0
    two_away = np.zeros((7, 7), bool)
    two_away[3, 5] = True
    assert edge_scores(two_away, truth, tolerance=1.5).recall == 0.0
    assert edge_scores(two_away, truth, tolerance=2).recall == 1.0


def test_edge_scores_one_detection_may_match_several_truth_pixels():
    truth = np.zeros((5, 5), bool)
    truth[1:4, 2] = True
    detected = np.zeros((5, 5), bool)
    detected[2, 2] = True
    scores = edge_scores(detected, truth, tolerance=1)
    assert (scores.precision, scores.recall, scores.false_negatives) == (1.0, 1.0, 0)


def test_edge_scores_empty_maps():
    empty = np.zeros((4, 6), bool)
    some = empty.copy()
    some[2, 3] = True
    both_empty = edge_scores(empty, empty)
    assert (both_empty.precision, both_empty.recall, both_empty.f1) == (1.0, 1.0, 1.0)
    nothing_found = edge_scores(empty, some)
    assert (nothing_found.precision, nothing_found.recall, nothing_found.f1) == (1.0, 0.0, 0.0)
    assert nothing_found.false_negatives == 1
    nothing_to_find = edge_scores(some, empty)
    assert (nothing_to_find.precision, nothing_to_find.recall, nothing_to_find.f1) == (0.0, 1.0, 0.0)
    assert nothing_to_find.false_positives == 1
    zero_size = edge_scores(np.zeros((0, 3), bool), np.zeros((0, 3), bool))
    assert (zero_size.n_detected, zero_size.f1) == (0, 1.0)


def test_edge_scores_mask_excludes_pixels_from_counts():
    truth = np.zeros((6, 6), bool)
    truth[:, 3] = True
    detected = truth.copy()
    detected[0, 0] = True
    mask = np.ones((6, 6), bool)
    mask[0] = False
    scores = edge_scores(detected, truth, mask=mask)
    assert (scores.n_detected, scores.n_truth, scores.precision) == (5, 5, 1.0)


def test_edge_difference_counts():
    raw = np.zeros((3, 4), bool)
    raw[0, :3] = True
    filtered = np.zeros((3, 4), bool)
    filtered[0, 1:] = True
    filtered[2, 2] = True
    result = edge_difference(raw, filtered)
    assert result.difference.dtype == np.int8
    assert result.difference.tolist() == [[-1, 0, 0, 1], [0, 0, 0, 0], [0, 0, 1, 0]]
    assert (result.removed, result.added, result.kept) == (1, 2, 2)
    assert result.changed_fraction == pytest.approx(3 / 12)
    same = edge_difference(raw, raw)
    assert (same.added, same.removed, same.changed_fraction) == (0, 0, 0.0)
    assert edge_difference(np.zeros((0, 2), bool), np.zeros((0, 2), bool)).changed_fraction == 0.0


def test_edge_difference_of_denoising_removes_noise_edges(arena_frames):
    noisy_frames, _ = arena_frames["range"]
    clean_frames, _ = arena_frames["none"]
    for noisy, clean in zip(noisy_frames[:3], clean_frames[:3]):
        raw = detect_edges(noisy.range, method="sobel")
        denoised = detect_edges(cv2.medianBlur(noisy.range, 5), method="sobel")
        ideal = detect_edges(clean.range, method="sobel")
        # A perfect "filter" (the noise-free frame) removes more than it adds.
        assert edge_difference(raw, ideal).removed > edge_difference(raw, ideal).added
        assert edge_difference(raw, denoised).removed > 0


# --------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "function",
    [normalize_range, detect_edges, lambda image: true_depth_edges(image)],
    ids=["normalize_range", "detect_edges", "true_depth_edges"],
)
def test_range_functions_reject_bad_images(function):
    with pytest.raises(ValueError, match=r"must be 2-D \(H, W\), got shape \(3, 4, 2\)"):
        function(np.zeros((3, 4, 2)))
    with pytest.raises(ValueError, match=r"must be 2-D \(H, W\), got shape \(5,\)"):
        function(np.zeros(5))
    with pytest.raises(ValueError, match="real numeric array.*dtype bool"):
        function(np.zeros((3, 3), bool))
    with pytest.raises(ValueError, match="real numeric array.*dtype complex128"):
        function(np.zeros((3, 3), complex))
    with pytest.raises(ValueError, match="real numeric array.*dtype <U1"):
        function(np.full((3, 3), "a"))
    with pytest.raises(ValueError, match="contains Inf"):
        function(np.array([[1.0, np.inf]]))


def test_detect_edges_rejects_bad_options():
    depth = _box_in_front_of_wall()
    with pytest.raises(ValueError, match="unknown edge method 'laplacian'; expected one of canny, sobel"):
        detect_edges(depth, method="laplacian")
    with pytest.raises(ValueError, match="threshold applies to sobel.*low_threshold/high_threshold for canny"):
        detect_edges(depth, method="canny", threshold=3.0)
    with pytest.raises(ValueError, match="low_threshold/high_threshold apply to canny; use threshold for roberts"):
        detect_edges(depth, method="roberts", high_threshold=3.0)
    with pytest.raises(ValueError, match="threshold must be finite and >= 0, got -1.0"):
        detect_edges(depth, method="sobel", threshold=-1)
    with pytest.raises(ValueError, match="low_threshold must not exceed high_threshold, got 5.0 > 2.0"):
        detect_edges(depth, low_threshold=5, high_threshold=2)
    with pytest.raises(ValueError, match="sigma must be finite and >= 0, got nan"):
        detect_edges(depth, sigma=float("nan"))
    with pytest.raises(ValueError, match="thin=False is not supported"):
        detect_edges(depth, thin=False)
    with pytest.raises(ValueError, match="need normalize=True"):
        detect_edges(depth, normalize=False, equalize=True)
    with pytest.raises(ValueError, match=r"valid_range must be finite with low < high, got \(3.0, 1.0\)"):
        detect_edges(depth, valid_range=(3.0, 1.0))
    with pytest.raises(ValueError, match="valid_range must be a pair"):
        normalize_range(depth, valid_range=5.0)


def test_edge_map_functions_reject_bad_maps():
    edges = np.zeros((6, 6), bool)
    with pytest.raises(ValueError, match="edge map must be a bool array.*got dtype uint8"):
        clean_edges(np.zeros((6, 6), np.uint8))
    with pytest.raises(ValueError, match=r"edge map must be 2-D \(H, W\), got shape \(6,\)"):
        clean_edges(np.zeros(6, bool))
    with pytest.raises(ValueError, match="border_width must be an integer >= 0, got -1"):
        clean_edges(edges, border_width=-1)
    with pytest.raises(ValueError, match="continuity must be 'opposite' or 'any', got 'line'"):
        clean_edges(edges, continuity="line")
    with pytest.raises(ValueError, match="detected edge map must be a bool array.*float64"):
        edge_scores(np.zeros((6, 6)), edges)
    with pytest.raises(ValueError, match=r"same shape, got \(6, 6\) and \(6, 5\)"):
        edge_scores(edges, np.zeros((6, 5), bool))
    with pytest.raises(ValueError, match="tolerance must be finite and >= 0, got -0.5"):
        edge_scores(edges, edges, tolerance=-0.5)
    with pytest.raises(ValueError, match=r"raw and filtered edge maps must have the same shape"):
        edge_difference(edges, np.zeros((5, 6), bool))
    with pytest.raises(ValueError, match="filtered edge map must be a bool array"):
        edge_difference(edges, np.zeros((6, 6), np.int64))


def test_other_functions_reject_bad_input():
    with pytest.raises(ValueError, match="grey-level image must be uint8 .*got dtype float64"):
        equalize_histogram(np.zeros((4, 4)))
    with pytest.raises(ValueError, match=r"grey-level image and mask must have the same shape"):
        equalize_histogram(np.zeros((4, 4), np.uint8), mask=np.ones((4, 5), bool))
    with pytest.raises(ValueError, match="mask must be a bool array"):
        equalize_histogram(np.zeros((4, 4), np.uint8), mask=np.ones((4, 4)))
    depth = _box_in_front_of_wall()
    with pytest.raises(ValueError, match="relative_jump must be finite and > 0, got 0"):
        true_depth_edges(depth, relative_jump=0)
    with pytest.raises(ValueError, match="side must be 'both' or 'near', got 'far'"):
        true_depth_edges(depth, side="far")
    with pytest.raises(ValueError, match="surface_id must be an integer array, got dtype float64"):
        true_depth_edges(depth, surface_id=np.zeros(depth.shape))
    with pytest.raises(ValueError, match="true range image and surface_id must have the same shape"):
        true_depth_edges(depth, surface_id=np.zeros((3, 3), int))
    with pytest.raises(ValueError, match=r"branch images must have the same shape"):
        combined_edges(depth, depth[:10])
    with pytest.raises(ValueError, match="both branches are edge maps; detect options \\['method'\\]"):
        combined_edges(np.zeros((5, 5), bool), np.zeros((5, 5), bool), method="sobel")
    with pytest.raises(ValueError, match="second branch must be a real numeric array"):
        combined_edges(depth, depth.astype(complex))
