"""Hoover et al. (1996) segmentation scores: hand-made cases with known answers and a reference."""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from fractions import Fraction

import numpy as np
import pytest

from rangesurf.segment.evaluate import SegmentationScores, evaluate_segmentation


def assert_partition(scores: SegmentationScores) -> None:
    """Every considered region is in exactly one class."""
    truth_in_under = [label for _, labels in scores.under_pairs for label in labels]
    machine_in_over = [label for _, labels in scores.over_pairs for label in labels]
    truth_classified = [t for t, _ in scores.correct_pairs] + [t for t, _ in scores.over_pairs]
    truth_classified += truth_in_under + list(scores.missed_labels)
    machine_classified = [m for _, m in scores.correct_pairs] + machine_in_over
    machine_classified += [m for m, _ in scores.under_pairs] + list(scores.noise_labels)
    assert len(truth_classified) == len(set(truth_classified)) == scores.n_truth
    assert len(machine_classified) == len(set(machine_classified)) == scores.n_machine
    assert scores.correct == len(scores.correct_pairs)
    assert scores.over_segmented == len(scores.over_pairs)
    assert scores.under_segmented == len(scores.under_pairs)
    assert scores.missed == len(scores.missed_labels)
    assert scores.noise == len(scores.noise_labels)


def counts(scores: SegmentationScores) -> tuple[int, int, int, int, int]:
    return scores.correct, scores.over_segmented, scores.under_segmented, scores.missed, scores.noise


# --------------------------------------------------------------------------
# One class at a time.
# --------------------------------------------------------------------------


def quadrants() -> np.ndarray:
    truth = np.zeros((8, 8), np.int32)
    truth[:4, :4], truth[:4, 4:], truth[4:, :4], truth[4:, 4:] = 1, 2, 3, 4
    return truth


def test_perfect_match_is_all_correct_whatever_the_machine_labels():
    truth = quadrants()
    machine = np.choose(truth - 1, [40, 10, 30, 20])
    scores = evaluate_segmentation(truth, machine, tolerance=1.0)
    assert counts(scores) == (4, 0, 0, 0, 0)
    assert scores.correct_pairs == ((1, 40), (2, 10), (3, 30), (4, 20))
    assert scores.correct_fraction == 1.0
    assert (scores.n_truth, scores.n_machine) == (4, 4)
    assert_partition(scores)


@pytest.mark.parametrize("n_parts", [2, 3])
def test_region_split_into_parts_is_over_segmented(n_parts):
    truth = np.ones((6, 6), np.int32)
    truth[:, 4:] = 2
    machine = np.full((6, 6), 50, np.int32)             # region 2 found whole
    machine[:, :4] = 7 + np.arange(4) * n_parts // 4    # columns of region 1 split into n_parts
    scores = evaluate_segmentation(truth, machine)
    parts = tuple(range(7, 7 + n_parts))
    assert counts(scores) == (1, 1, 0, 0, 0)
    assert scores.over_pairs == ((1, parts),)
    assert scores.correct_pairs == ((2, 50),)
    assert scores.n_machine == n_parts + 1
    assert_partition(scores)


def test_merged_regions_are_under_segmented():
    truth = quadrants()
    machine = np.where(truth <= 2, 9, truth * 10)       # regions 1 and 2 merged into 9
    scores = evaluate_segmentation(truth, machine)
    assert counts(scores) == (2, 0, 1, 0, 0)
    assert scores.under_pairs == ((9, (1, 2)),)
    assert scores.correct_pairs == ((3, 30), (4, 40))
    assert_partition(scores)


def test_three_regions_merged_into_one():
    truth = quadrants()
    machine = np.where(truth <= 3, 5, 6)
    scores = evaluate_segmentation(truth, machine)
    assert scores.under_pairs == ((5, (1, 2, 3)),)
    assert counts(scores) == (1, 0, 1, 0, 0)


def test_uncovered_region_is_missed():
    truth = quadrants()
    machine = np.where(truth == 4, 0, truth)            # no machine region on region 4
    scores = evaluate_segmentation(truth, machine)
    assert counts(scores) == (3, 0, 0, 1, 0)
    assert scores.missed_labels == (4,)
    assert scores.correct_fraction == 0.75
    assert_partition(scores)


def test_too_small_a_fragment_leaves_a_missed_region_and_a_noise_region():
    truth = quadrants()
    machine = np.where(truth == 4, 0, truth)
    machine[6:8, 6:8] = 8                               # 4 of the 16 pixels of region 4
    scores = evaluate_segmentation(truth, machine)
    assert counts(scores) == (3, 0, 0, 1, 1)
    assert (scores.missed_labels, scores.noise_labels) == ((4,), (8,))
    assert_partition(scores)


def test_region_straddling_two_correct_regions_is_noise():
    truth = np.ones((10, 10), np.int32)
    truth[:, 5:] = 2
    machine = np.where(truth == 1, 5, 6)
    machine[:2, 3:7] = 7                                # 4 pixels in each region
    scores = evaluate_segmentation(truth, machine)
    assert counts(scores) == (2, 0, 0, 0, 1)
    assert scores.noise_labels == (7,)
    assert_partition(scores)


def test_mixture_of_every_class_has_the_exact_counts():
    truth = np.zeros((20, 40), np.int32)
    truth[:10, 0:10], truth[:10, 10:20], truth[:10, 20:30], truth[:10, 30:40] = 1, 2, 3, 4
    truth[10:, :20], truth[10:, 20:] = 5, 6
    machine = np.zeros_like(truth)
    machine[:10, 0:10] = 11                             # correct
    machine[:10, 10:15], machine[:10, 15:20] = 21, 22   # region 2 split
    machine[:10, 20:40] = 34                            # regions 3 and 4 merged
    machine[10:12, :20] = 55                            # region 5: 40 of 200 pixels, so missed; 55 is noise
    machine[10:, 20:] = 66
    machine[10:13, 20:23] = 77                          # a 9-pixel speck inside correctly detected region 6
    scores = evaluate_segmentation(truth, machine, tolerance=0.8)
    assert counts(scores) == (2, 1, 1, 1, 2)
    assert (scores.n_truth, scores.n_machine) == (6, 7)
    assert scores.correct_pairs == ((1, 11), (6, 66))
    assert scores.over_pairs == ((2, (21, 22)),)
    assert scores.under_pairs == ((34, (3, 4)),)
    assert scores.missed_labels == (5,)
    assert scores.noise_labels == (55, 77)
    assert scores.correct_fraction == pytest.approx(2 / 6)
    assert_partition(scores)


# --------------------------------------------------------------------------
# Precedence, tolerance and label 0.
# --------------------------------------------------------------------------


def test_correct_detection_takes_precedence_over_over_segmentation():
    # Region 1 (100 px): machine 5 holds 90 px, machine 6 the other 10. Both
    # (1, 5) correct and (1; 5, 6) over-segmented satisfy the definitions.
    truth = np.ones((10, 10), np.int32)
    machine = np.full((10, 10), 5, np.int32)
    machine[9] = 6
    scores = evaluate_segmentation(truth, machine, tolerance=0.8)
    assert counts(scores) == (1, 0, 0, 0, 1)
    assert scores.correct_pairs == ((1, 5),)
    assert scores.noise_labels == (6,)


def test_correct_detection_takes_precedence_over_under_segmentation():
    # Machine 5 (110 px) holds 90 of region 1's 100 px and all of region 2's
    # 20: (1, 5) correct and (5; 1, 2) under-segmented both hold.
    truth = np.zeros((11, 12), np.int32)
    truth[:10, :10] = 1
    truth[:10, 10:12] = 2
    machine = np.full_like(truth, 5)
    machine[9, :10] = 0
    scores = evaluate_segmentation(truth, machine, tolerance=0.8)
    assert (scores.n_truth, scores.n_machine) == (2, 1)
    assert counts(scores) == (1, 0, 0, 1, 0)
    assert scores.missed_labels == (2,)


@pytest.mark.parametrize(
    ("tolerance", "covered", "is_correct"),
    [(0.8, 8, True), (0.8, 7, False), (0.7, 7, True), (0.7, 6, False), (0.6, 6, True), (0.9, 9, True), (0.9, 8, False)],
)
def test_overlap_of_exactly_t_times_the_truth_region_counts(tolerance, covered, is_correct):
    # 0.7 * 10 is 7.000000000000001 in floating point: the boundary must still count.
    truth = np.ones((1, 10), np.int32)
    machine = np.zeros((1, 10), np.int32)
    machine[0, :covered] = 5
    scores = evaluate_segmentation(truth, machine, tolerance=tolerance)
    assert scores.correct_pairs == (((1, 5),) if is_correct else ())
    assert scores.missed == (0 if is_correct else 1)
    assert scores.noise == (0 if is_correct else 1)


@pytest.mark.parametrize(("split", "is_correct"), [(10, True), (11, False)])
def test_overlap_of_exactly_t_times_the_machine_region_counts(split, is_correct):
    truth = np.array([[1] * 8 + [2] * 12])
    machine = np.array([[5] * split + [6] * (20 - split)])
    scores = evaluate_segmentation(truth, machine, tolerance=0.8)
    assert ((1, 5) in scores.correct_pairs) is is_correct
    assert_partition(scores)


def test_tolerance_one_demands_identical_regions():
    truth = quadrants()
    machine = truth.copy()
    machine[0, 0] = 2
    scores = evaluate_segmentation(truth, machine, tolerance=1.0)
    assert scores.correct_pairs == ((3, 3), (4, 4))
    assert evaluate_segmentation(truth, truth, tolerance=1.0).correct == 4


def test_unlabelled_truth_pixels_count_for_no_region():
    truth = np.zeros((4, 10), np.int32)
    truth[:, :5] = 1
    machine = np.full((4, 10), 5, np.int32)             # half of it on unlabelled pixels
    machine[0, 9] = 6                                   # entirely on unlabelled pixels
    scores = evaluate_segmentation(truth, machine, tolerance=0.95)
    assert scores.correct_pairs == ((1, 5),)
    assert (scores.n_truth, scores.n_machine, scores.noise) == (1, 1, 0)


def test_machine_label_zero_is_no_region():
    truth = np.ones((1, 10), np.int32)
    machine = np.array([[0, 0, 0, 4, 4, 4, 4, 4, 4, 4]])
    assert evaluate_segmentation(truth, machine, tolerance=0.8).missed_labels == (1,)
    scores = evaluate_segmentation(truth, machine, tolerance=0.7)
    assert scores.correct_pairs == ((1, 4),)
    assert scores.n_machine == 1


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.int32, np.int64, np.uint64])
def test_non_contiguous_labels_of_any_integer_dtype(dtype):
    truth = np.choose(quadrants() - 1, [3, 17, 200, 100]).astype(dtype)
    machine = np.where(truth == 3, 17, truth).astype(dtype)
    machine[machine == 200] = 250
    scores = evaluate_segmentation(truth, machine)
    assert scores.correct_pairs == ((100, 100), (200, 250))
    assert scores.under_pairs == ((17, (3, 17)),)


def test_huge_label_values():
    truth = quadrants().astype(np.int64) * 10**12
    machine = np.choose(quadrants() - 1, [2**40, 1000, 1000, 2**62]).astype(np.int64)
    scores = evaluate_segmentation(truth, machine)
    assert scores.correct_pairs == ((10**12, 2**40), (4 * 10**12, 2**62))
    assert scores.under_pairs == ((1000, (2 * 10**12, 3 * 10**12)),)
    assert all(isinstance(label, int) for label in scores.correct_pairs[0])


# --------------------------------------------------------------------------
# Normals.
# --------------------------------------------------------------------------


def tilted(degrees: float, *, scale: float = 1.0, sign: float = 1.0) -> list[float]:
    angle = math.radians(degrees)
    return [0.0, sign * scale * math.sin(angle), sign * scale * math.cos(angle), 2.0]


def test_normal_errors_from_known_planes():
    truth = quadrants()
    machine = truth * 10
    truth_planes = np.full((5, 4), np.nan)
    truth_planes[1:] = [tilted(0), tilted(0), tilted(30), tilted(45)]
    machine_planes = {
        10: tilted(0, scale=3.0),                       # same plane, normal of another length
        20: tilted(10),                                 # tilted by 10 degrees
        30: tilted(30, sign=-1.0),                      # same plane, normal flipped
        40: [np.nan] * 4,                               # no plane
    }
    scores = evaluate_segmentation(truth, machine, truth_planes=truth_planes, machine_planes=machine_planes)
    np.testing.assert_allclose(scores.normal_errors_deg, [0.0, 10.0, 0.0], atol=1e-6)
    assert scores.mean_normal_error_deg == pytest.approx(10 / 3)
    assert scores.std_normal_error_deg == pytest.approx(np.std([0.0, 10.0, 0.0]))


def test_normal_errors_with_array_planes_and_a_missing_dict_key():
    truth = quadrants()
    planes = np.zeros((41, 4))
    planes[:, 2] = 1.0
    planes[40] = tilted(20)
    scores = evaluate_segmentation(truth, truth * 10, truth_planes={1: tilted(0), 4: tilted(0)}, machine_planes=planes)
    np.testing.assert_allclose(scores.normal_errors_deg, [0.0, 20.0], atol=1e-6)


def test_no_normal_errors_without_both_plane_sets():
    truth = quadrants()
    planes = np.tile(tilted(0), (5, 1))
    for given in ({"truth_planes": planes}, {"machine_planes": planes}, {}):
        scores = evaluate_segmentation(truth, truth, **given)
        assert scores.normal_errors_deg == ()
        assert math.isnan(scores.mean_normal_error_deg) and math.isnan(scores.std_normal_error_deg)


# --------------------------------------------------------------------------
# Region size, empty images, results.
# --------------------------------------------------------------------------


def test_min_region_size_drops_small_truth_regions_and_their_pixels():
    truth = np.zeros((1, 13), np.int32)
    truth[0, :10], truth[0, 10:] = 1, 9                 # region 9 has 3 pixels
    machine = np.full((1, 13), 5, np.int32)
    scores = evaluate_segmentation(truth, machine)
    assert scores.under_pairs == ((5, (1, 9)),)         # 10 >= 0.8 * 13 fails, so not correct
    scores = evaluate_segmentation(truth, machine, min_region_size=4)
    assert scores.correct_pairs == ((1, 5),)            # region 9's pixels are unlabelled now
    assert (scores.n_truth, scores.missed) == (1, 0)


def test_min_region_size_drops_small_machine_regions():
    truth = quadrants()
    machine = truth.copy()
    machine[0, 0:2] = 7                                 # a 2-pixel speck
    assert evaluate_segmentation(truth, machine).noise_labels == (7,)
    scores = evaluate_segmentation(truth, machine, min_region_size=3)
    assert (scores.noise, scores.n_machine, scores.correct) == (0, 4, 4)


@pytest.mark.parametrize("shape", [(0, 0), (0, 5), (3, 4)])
def test_no_truth_regions_gives_zero_scores(shape):
    truth = np.zeros(shape, np.int32)
    machine = np.ones(shape, np.int32)
    scores = evaluate_segmentation(truth, machine)
    assert (scores.n_truth, scores.n_machine) == (0, 0)
    assert counts(scores) == (0, 0, 0, 0, 0)
    assert scores.correct_fraction == 0.0


def test_empty_machine_segmentation_misses_everything():
    scores = evaluate_segmentation(quadrants(), np.zeros((8, 8), np.int32))
    assert counts(scores) == (0, 0, 0, 4, 0)
    assert scores.missed_labels == (1, 2, 3, 4)


def test_as_dict_is_strict_json():
    scores = evaluate_segmentation(quadrants(), quadrants(), truth_planes=None)
    data = json.loads(json.dumps(scores.as_dict(), allow_nan=False))
    assert data["correct"] == 4 and data["correct_fraction"] == 1.0
    assert data["correct_pairs"] == [[1, 1], [2, 2], [3, 3], [4, 4]]
    assert data["mean_normal_error_deg"] is None
    merged = evaluate_segmentation(quadrants(), np.ones((8, 8), np.int32)).as_dict()
    assert merged["under_pairs"] == [[1, [1, 2, 3, 4]]]


def test_scores_are_frozen():
    scores = evaluate_segmentation(quadrants(), quadrants())
    with pytest.raises(dataclasses.FrozenInstanceError):
        scores.correct = 0  # type: ignore[misc]


# --------------------------------------------------------------------------
# Bad inputs.
# --------------------------------------------------------------------------


ONES = np.ones((2, 2), int)


@pytest.mark.parametrize(
    ("truth", "machine", "options", "message"),
    [
        (np.ones((2, 2, 2), int), ONES, {}, r"truth_labels must be 2-D \(H, W\), got shape \(2, 2, 2\)"),
        (np.ones((2, 2), int), np.ones(4, int), {}, r"machine_labels must be 2-D .*got shape \(4,\)"),
        (np.ones((2, 2), int), np.ones((2, 3), int), {}, r"same shape, got \(2, 2\) and \(2, 3\)"),
        (np.ones((2, 2)), np.ones((2, 2), int), {}, r"truth_labels must be an integer label array .*float64"),
        (np.ones((2, 2), int), np.ones((2, 2), bool), {}, r"machine_labels must be an integer .*bool"),
        (np.array([[1, -2]]), np.ones((1, 2), int), {}, r"truth_labels must be >= 0 .*-2"),
        (ONES, ONES, {"tolerance": 0.5}, r"tolerance must be in \(0.5, 1\].*got 0.5"),
        (ONES, ONES, {"tolerance": 0.3}, r"tolerance must be in \(0.5, 1\]"),
        (ONES, ONES, {"tolerance": 1.01}, r"tolerance must be in \(0.5, 1\]"),
        (ONES, ONES, {"tolerance": math.nan}, r"tolerance must be in \(0.5, 1\]"),
        (ONES, ONES, {"tolerance": "0.8"}, r"tolerance must be a number"),
        (ONES, ONES, {"tolerance": True}, r"tolerance must be a number"),
        (ONES, ONES, {"min_region_size": 0}, r"min_region_size must be >= 1"),
        (ONES, ONES, {"min_region_size": 2.5}, r"min_region_size must be an integer"),
        (ONES, ONES, {"truth_planes": np.zeros((2, 3))}, r"truth_planes must be an \(L, 4\) array .*shape \(2, 3\)"),
        (7 * ONES, ONES, {"truth_planes": np.zeros((7, 4))}, r"truth_planes has 7 rows but label 7 occurs.*at least 8"),
        (ONES, ONES, {"machine_planes": {1: [0, 0, 1]}}, r"machine_planes\[1\] must be a plane .*shape \(3,\)"),
        (ONES, ONES, {"machine_planes": {-1: [0, 0, 1, 0]}}, r"machine_planes keys must be labels"),
    ],
)
def test_bad_inputs_are_rejected_with_a_clear_message(truth, machine, options, message):
    with pytest.raises(ValueError, match=message):
        evaluate_segmentation(truth, machine, **options)


# --------------------------------------------------------------------------
# Against a reference written straight from the definitions.
# --------------------------------------------------------------------------


def reference_scores(truth: np.ndarray, machine: np.ndarray, tolerance: float, min_region_size: int = 1) -> dict:
    """Hoover et al.'s classes by loops over regions, with exact fractions.

    Each class is first found as the paper defines it, independently of the
    others; correct detections then take precedence (their regions leave
    any over- or under-segmentation). Along the way it checks the claims
    the fast implementation relies on: with correct detections set aside, no
    other instance uses their regions, and over- and under-segmentations
    share no region.
    """
    T = Fraction(str(tolerance))
    truth_size = Counter(int(t) for t in truth.ravel() if t > 0)
    truth_kept = {label for label, size in truth_size.items() if size >= min_region_size}
    pixels = [(int(t), int(m)) for t, m in zip(truth.ravel(), machine.ravel()) if int(t) in truth_kept]
    machine_size = Counter(m for _, m in pixels if m > 0)
    machine_kept = {label for label, size in machine_size.items() if size >= min_region_size}
    overlap = Counter((t, m) for t, m in pixels if m in machine_kept)
    M = {label: truth_size[label] for label in truth_kept}
    N = {label: machine_size[label] for label in machine_kept}

    def O(t: int, m: int) -> int:
        return overlap.get((t, m), 0)

    correct = sorted((t, m) for t in M for m in N if O(t, m) >= T * M[t] and O(t, m) >= T * N[m])
    # An over-segmentation of t exists iff the largest qualifying set of
    # machine regions (all with O_tm >= T N_m) covers T M_t: any qualifying
    # set is a subset of it. Likewise for under-segmentations.
    over_literal = {}
    for t in M:
        parts = sorted(m for m in N if O(t, m) > 0 and O(t, m) >= T * N[m])
        if len(parts) >= 2 and sum(O(t, m) for m in parts) >= T * M[t]:
            over_literal[t] = tuple(parts)
    under_literal = {}
    for m in N:
        parts = sorted(t for t in M if O(t, m) > 0 and O(t, m) >= T * M[t])
        if len(parts) >= 2 and sum(O(t, m) for t in parts) >= T * N[m]:
            under_literal[m] = tuple(parts)

    correct_truth = {t for t, _ in correct}
    correct_machine = {m for _, m in correct}
    over = {t: parts for t, parts in over_literal.items() if t not in correct_truth}
    under = {m: parts for m, parts in under_literal.items() if m not in correct_machine}
    over_machine = {m for parts in over.values() for m in parts}
    under_truth = {t for parts in under.values() for t in parts}
    assert not over_machine & correct_machine and not under_truth & correct_truth
    assert not over_machine & set(under) and not set(over) & under_truth
    missed = sorted(set(M) - correct_truth - set(over) - under_truth)
    noise = sorted(set(N) - correct_machine - over_machine - set(under))
    return {
        "n_truth": len(M),
        "n_machine": len(N),
        "correct_pairs": tuple(correct),
        "over_pairs": tuple(sorted(over.items())),
        "under_pairs": tuple(sorted(under.items())),
        "missed_labels": tuple(missed),
        "noise_labels": tuple(noise),
    }


def random_case(seed: int) -> tuple[np.ndarray, np.ndarray, float, int]:
    """A Voronoi ground truth and a machine segmentation that splits, merges, drops, shifts and adds regions."""
    rng = np.random.default_rng(seed)
    height, width = (int(size) for size in rng.integers(20, 48, size=2))
    n_regions = int(rng.integers(2, 16))
    centres = rng.random((n_regions, 2)) * [height, width]
    rows, cols = np.mgrid[:height, :width]
    nearest = np.argmin((rows[..., None] - centres[:, 0]) ** 2 + (cols[..., None] - centres[:, 1]) ** 2, axis=-1)
    truth_values = rng.choice(np.arange(1, 5000), n_regions, replace=False)
    truth = truth_values[nearest]

    machine = rng.choice(np.arange(1, 5000), n_regions, replace=False)[nearest]
    next_label = 5000
    for region in range(n_regions):
        inside = nearest == region
        action = rng.choice(["keep", "keep", "split", "split3", "merge", "drop"])
        if action in ("split", "split3"):
            pieces = 2 if action == "split" else 3
            edges = np.quantile(cols[inside], np.linspace(0, 1, pieces + 1)[1:-1])
            piece = np.searchsorted(edges, cols, side="right")
            machine[inside] = next_label + piece[inside]
            next_label += pieces
        elif action == "merge":
            machine[inside] = machine[nearest == rng.integers(n_regions)][0]
        elif action == "drop":
            machine[inside] = 0
    if rng.random() < 0.5:                                         # boundaries off by a pixel
        machine = np.roll(machine, tuple(int(shift) for shift in rng.integers(-1, 2, size=2)), axis=(0, 1))
    for _ in range(int(rng.integers(0, 4))):                       # noise blobs
        top, left = int(rng.integers(height)), int(rng.integers(width))
        machine[top:top + int(rng.integers(1, 8)), left:left + int(rng.integers(1, 8))] = next_label
        next_label += 1
    truth[rng.random((height, width)) < rng.uniform(0, 0.15)] = 0   # unlabelled pixels
    if rng.random() < 0.3:
        truth[:, : int(rng.integers(1, 6))] = 0                    # an unlabelled band
    tolerance = float(rng.choice([0.51, 0.6, 0.7, 0.75, 0.8, 0.8, 0.9, 0.95, 1.0]))
    min_region_size = int(rng.choice([1, 1, 1, 6]))
    return truth, machine, tolerance, min_region_size


def as_reference(scores: SegmentationScores) -> dict:
    return {
        "n_truth": scores.n_truth,
        "n_machine": scores.n_machine,
        "correct_pairs": scores.correct_pairs,
        "over_pairs": scores.over_pairs,
        "under_pairs": scores.under_pairs,
        "missed_labels": scores.missed_labels,
        "noise_labels": scores.noise_labels,
    }


@pytest.mark.parametrize("seed", range(30))
def test_matches_the_reference_on_random_segmentations(seed):
    truth, machine, tolerance, min_region_size = random_case(seed)
    scores = evaluate_segmentation(truth, machine, tolerance=tolerance, min_region_size=min_region_size)
    assert as_reference(scores) == reference_scores(truth, machine, tolerance, min_region_size)
    assert_partition(scores)


def test_random_segmentations_exercise_every_class():
    totals = Counter()
    for seed in range(30):
        truth, machine, tolerance, min_region_size = random_case(seed)
        scores = evaluate_segmentation(truth, machine, tolerance=tolerance, min_region_size=min_region_size)
        totals.update(dict(zip(["correct", "over", "under", "missed", "noise"], counts(scores))))
    assert min(totals.values()) >= 3, totals


@pytest.mark.parametrize("tolerance", [0.51, 0.8, 0.95])
def test_matches_the_reference_on_a_random_label_soup(tolerance):
    # Unstructured labels: many small overlaps and ties near the thresholds.
    rng = np.random.default_rng(7)
    truth = rng.integers(0, 6, size=(12, 12))
    machine = np.where(rng.random((12, 12)) < 0.8, truth * 3, rng.integers(0, 20, size=(12, 12)))
    scores = evaluate_segmentation(truth, machine, tolerance=tolerance)
    assert as_reference(scores) == reference_scores(truth, machine, tolerance)
