"""Scores of a range-image segmentation against ground truth (Hoover et al. 1996).

The comparison of the SegComp framework [1]_, the standard score of range
segmentation: each region of the ground truth (GT) and of the machine
segmentation (MS) is classified as a correct detection, part of an
over-segmentation or an under-segmentation, missed (GT) or noise (MS), at an
overlap tolerance ``T`` in ``(0.5, 1]``; correctly detected planes are also
compared by the angle between their normals.

References
----------
.. [1] A. Hoover, G. Jean-Baptiste, X. Jiang, P. J. Flynn, H. Bunke,
   D. B. Goldgof, K. Bowyer, D. W. Eggert, A. Fitzgibbon and R. B. Fisher,
   "An experimental comparison of range image segmentation algorithms",
   IEEE Transactions on Pattern Analysis and Machine Intelligence 18(7),
   673-689, 1996, Section 3.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from fractions import Fraction
from typing import Any

import cv2
import numpy as np

from rangesurf.segment._segmentation import Segmentation
from rangesurf.simulate import GroundTruth

__all__ = ["SegmentationScores", "evaluate_segmentation", "match_planes", "transform_planes", "truth_segmentation"]

# The tolerance is compared as a fraction num / den in integer arithmetic, so
# that an overlap of exactly T * M pixels counts (0.7 * 10 is 7.000000000000001
# in floating point). A denominator of at most 10**6 reads 0.7 as 7/10 and
# 0.6666666666666666 as 2/3, and keeps overlap * den far inside int64.
_TOLERANCE_MAX_DENOMINATOR = 10**6
_HALF = Fraction(1, 2)


@dataclass(frozen=True)
class SegmentationScores:
    """Region classification of a machine segmentation against ground truth.

    Every considered region is in exactly one class: a GT region is
    correctly detected, over-segmented, part of an under-segmentation or
    missed; a machine region is correctly detected, part of an
    over-segmentation, under-segmenting or noise. Labels are the values of
    the input label images.

    Attributes
    ----------
    tolerance : float
        Overlap tolerance ``T``, in ``(0.5, 1]``.
    n_truth : int
        GT regions considered: label > 0 with at least ``min_region_size``
        pixels.
    n_machine : int
        Machine regions considered: label > 0 with at least
        ``min_region_size`` pixels on labelled GT pixels.
    correct : int
        Correct detections (one GT and one machine region each).
    over_segmented : int
        GT regions that are over-segmented.
    under_segmented : int
        Machine regions that are under-segmentations.
    missed : int
        GT regions in no other class.
    noise : int
        Machine regions in no other class.
    correct_pairs : tuple of (int, int)
        ``(truth_label, machine_label)`` of each correct detection, by truth
        label.
    over_pairs : tuple of (int, tuple of int)
        ``(truth_label, machine_labels)`` of each over-segmentation: the GT
        region and the 2 or more machine regions it was split into.
    under_pairs : tuple of (int, tuple of int)
        ``(machine_label, truth_labels)`` of each under-segmentation: the
        machine region and the 2 or more GT regions it merged.
    missed_labels, noise_labels : tuple of int
        Labels of the missed GT regions and of the noise machine regions.
    normal_errors_deg : tuple of float
        Angle in degrees, in ``[0, 90]``, between the GT and the machine plane
        normal of each correct detection (in ``correct_pairs`` order) for
        which both planes are given and finite; empty without planes.
    """

    tolerance: float
    n_truth: int
    n_machine: int
    correct: int
    over_segmented: int
    under_segmented: int
    missed: int
    noise: int
    correct_pairs: tuple[tuple[int, int], ...]
    over_pairs: tuple[tuple[int, tuple[int, ...]], ...]
    under_pairs: tuple[tuple[int, tuple[int, ...]], ...]
    missed_labels: tuple[int, ...]
    noise_labels: tuple[int, ...]
    normal_errors_deg: tuple[float, ...]

    @property
    def correct_fraction(self) -> float:
        """Correct detections per GT region; 0 without GT regions."""
        return self.correct / self.n_truth if self.n_truth else 0.0

    @property
    def mean_normal_error_deg(self) -> float:
        """Mean of `normal_errors_deg`; NaN when it is empty."""
        return float(np.mean(self.normal_errors_deg)) if self.normal_errors_deg else math.nan

    @property
    def std_normal_error_deg(self) -> float:
        """Standard deviation (population, ``ddof=0``) of `normal_errors_deg`; NaN when it is empty."""
        return float(np.std(self.normal_errors_deg)) if self.normal_errors_deg else math.nan

    def as_dict(self) -> dict[str, Any]:
        """Fields and properties as plain lists, ints and floats (NaN as None), ready for ``json.dump``."""

        def plain(value: Any) -> Any:
            if isinstance(value, tuple):
                return [plain(item) for item in value]
            if isinstance(value, float) and math.isnan(value):
                return None
            return value

        fields = {name: plain(value) for name, value in asdict(self).items()}
        fields["correct_fraction"] = self.correct_fraction
        fields["mean_normal_error_deg"] = plain(self.mean_normal_error_deg)
        fields["std_normal_error_deg"] = plain(self.std_normal_error_deg)
        return fields


# --------------------------------------------------------------------------
# Input checks.
# --------------------------------------------------------------------------


def _check_labels(labels: Any, name: str) -> np.ndarray:
    array = np.asarray(labels)
    if array.ndim != 2:
        raise ValueError(f"{name} must be 2-D (H, W), got shape {array.shape}")
    if array.dtype == bool or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(
            f"{name} must be an integer label array (0 = no region), got dtype {array.dtype}; "
            "convert whole-number labels with .astype(np.int32)"
        )
    if array.size and np.issubdtype(array.dtype, np.signedinteger):
        lowest = int(array.min())
        if lowest < 0:
            raise ValueError(f"{name} must be >= 0 (0 = no region), got label {lowest}")
    return array


def _check_tolerance(tolerance: Any) -> tuple[float, Fraction]:
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.integer, np.floating)):
        raise ValueError(f"tolerance must be a number in (0.5, 1], got {tolerance!r}")
    value = float(tolerance)
    fraction = Fraction(value).limit_denominator(_TOLERANCE_MAX_DENOMINATOR) if math.isfinite(value) else None
    if fraction is None or not (_HALF < fraction <= 1):
        raise ValueError(
            f"tolerance must be in (0.5, 1] (read to about 1e-6), got {value}: above 0.5 a region can "
            "overlap at most one region of the other segmentation by that fraction, which makes the "
            "classes of Hoover et al. (1996) well defined, and an overlap cannot exceed the region"
        )
    return value, fraction


def _check_min_region_size(min_region_size: Any) -> int:
    if isinstance(min_region_size, bool) or not isinstance(min_region_size, (int, np.integer)):
        raise ValueError(f"min_region_size must be an integer >= 1, got {min_region_size!r}")
    if min_region_size < 1:
        raise ValueError(f"min_region_size must be >= 1 (pixels), got {min_region_size}")
    return int(min_region_size)


def _check_planes(planes: Any, name: str, largest_label: int) -> np.ndarray | dict[int, np.ndarray] | None:
    """Planes as an ``(L, 4)`` float64 array or a ``{label: (4,) float64}`` dict, or None."""
    if planes is None:
        return None
    if isinstance(planes, Mapping):
        checked = {}
        for label, plane in planes.items():
            if isinstance(label, bool) or not isinstance(label, (int, np.integer)) or label < 0:
                raise ValueError(f"{name} keys must be labels (integers >= 0), got {label!r}")
            try:
                row = np.asarray(plane, dtype=np.float64)
            except (TypeError, ValueError):
                message = f"{name}[{label}] must be a plane (nx, ny, nz, d) of 4 numbers, got {plane!r}"
                raise ValueError(message) from None
            if row.shape != (4,):
                raise ValueError(
                    f"{name}[{label}] must be a plane (nx, ny, nz, d) of shape (4,), got shape {row.shape}"
                )
            checked[int(label)] = row
        return checked
    try:
        array = np.asarray(planes, dtype=np.float64)
    except (TypeError, ValueError):
        message = f"{name} must be an (L, 4) float array or a dict {{label: (4,)}}, got {type(planes).__name__}"
        raise ValueError(message) from None
    if array.ndim != 2 or array.shape[1] != 4:
        raise ValueError(
            f"{name} must be an (L, 4) array of planes (nx, ny, nz, d), row k for label k, "
            f"or a dict {{label: (4,)}}; got shape {array.shape}"
        )
    if array.shape[0] <= largest_label:
        raise ValueError(
            f"{name} has {array.shape[0]} rows but label {largest_label} occurs; row k holds label k's "
            f"plane, so at least {largest_label + 1} rows are needed (NaN rows for labels without one)"
        )
    return array


# --------------------------------------------------------------------------
# Overlap table.
# --------------------------------------------------------------------------


def _compress(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(values, index)``: the sorted distinct labels and each pixel's index into them."""
    if labels.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.intp)
    largest = int(labels.max())
    # A lookup table indexed by label is linear time; sorting (np.unique) is
    # only needed for label values far larger than the image.
    if largest <= 4 * labels.size + 1024:
        flat = labels.astype(np.intp, copy=False)
        values = np.flatnonzero(np.bincount(flat))
        lookup = np.zeros(largest + 1, np.intp)
        lookup[values] = np.arange(values.size)
        return values, lookup[flat]
    values, index = np.unique(labels, return_inverse=True)
    return values, index.ravel().astype(np.intp, copy=False)


def _overlap_pairs(truth_index: np.ndarray, machine_index: np.ndarray, n_truth: int, n_machine: int):
    """``(truth, machine, overlap)`` index arrays of every overlapping pair, sorted by (truth, machine)."""
    codes = truth_index.astype(np.int64) * n_machine + machine_index
    n_cells = n_truth * n_machine
    if n_cells <= 4 * codes.size + 4096:
        table = np.bincount(codes, minlength=n_cells)
        codes = np.flatnonzero(table)
        overlap = table[codes]
    else:
        codes, overlap = np.unique(codes, return_counts=True)
    return codes // n_machine, codes % n_machine, overlap.astype(np.int64)


def _normals(planes: np.ndarray | dict[int, np.ndarray], labels: list[int]) -> np.ndarray:
    """``(k, 3)`` normals of the given labels, NaN where no plane is given."""
    if isinstance(planes, dict):
        missing = np.full(4, np.nan)
        rows = [planes.get(label, missing) for label in labels]
        return np.array(rows, dtype=np.float64).reshape(len(labels), 4)[:, :3]
    return planes[np.asarray(labels, dtype=np.intp), :3]


def _normal_angles(truth_normals: np.ndarray, machine_normals: np.ndarray) -> tuple[float, ...]:
    truth_length = np.linalg.norm(truth_normals, axis=1)
    machine_length = np.linalg.norm(machine_normals, axis=1)
    with np.errstate(invalid="ignore"):
        usable = np.isfinite(truth_length) & np.isfinite(machine_length) & (truth_length > 0) & (machine_length > 0)
    dots = np.abs(np.einsum("ij,ij->i", truth_normals[usable], machine_normals[usable]))
    # |dot|: a plane's normal may point either way, so n and -n are the same plane.
    cosines = np.clip(dots / (truth_length[usable] * machine_length[usable]), 0.0, 1.0)
    return tuple(float(angle) for angle in np.degrees(np.arccos(cosines)))


# --------------------------------------------------------------------------
# The comparison.
# --------------------------------------------------------------------------


def evaluate_segmentation(
    truth_labels: np.ndarray,
    machine_labels: np.ndarray,
    *,
    tolerance: float = 0.8,
    truth_planes: np.ndarray | Mapping[int, Any] | None = None,
    machine_planes: np.ndarray | Mapping[int, Any] | None = None,
    min_region_size: int = 1,
) -> SegmentationScores:
    """Classify the regions of a segmentation against ground truth (Hoover et al. 1996).

    With ``M_m`` the pixels of GT region ``R_m``, ``N_n`` those of machine
    region ``R_n`` and ``O_mn`` their overlap, at tolerance ``T`` [1]_:

    * correct detection of ``R_m`` by ``R_n``: ``O_mn >= T M_m`` and
      ``O_mn >= T N_n``;
    * over-segmentation of ``R_m`` into ``R_n1 .. R_nx``, ``x >= 2``:
      ``O_mni >= T N_ni`` for every ``i`` and ``sum_i O_mni >= T M_m``;
    * under-segmentation of ``R_m1 .. R_mx``, ``x >= 2``, into ``R_n``:
      ``O_min >= T M_mi`` for every ``i`` and ``sum_i O_min >= T N_n``;
    * missed (GT) and noise (machine): a region in none of these.

    Parameters
    ----------
    truth_labels : (H, W) integer array
        Ground-truth region labels, >= 0; 0 marks pixels without a surface
        label (no range data, shadow, unlabelled boundaries), which are left
        out of the comparison entirely (see Notes).
    machine_labels : (H, W) integer array
        Machine segmentation labels, >= 0; 0 marks pixels in no region.
        Labels need not be contiguous (3, 17, 1000).
    tolerance : float
        Overlap tolerance ``T`` in ``(0.5, 1]``; 1 demands identical regions.
        Hoover et al. report scores over ``T`` from 0.51 to 0.95; 0.8 is
        their headline value. It is read as a fraction with denominator at
        most 10**6, so an overlap of exactly ``T M`` pixels counts.
    truth_planes, machine_planes : (L, 4) float array or dict, optional
        Plane ``(nx, ny, nz, d)`` of each label: row ``k`` of an array (at
        least ``max label + 1`` rows) or ``planes[k]`` of a dict ``{label:
        (4,)}``; NaN (or a missing dict key) for a region without a plane.
        Only the normal is used, at any length and either sign.
    min_region_size : int
        Regions with fewer pixels are left out: a small GT region's pixels
        are treated as unlabelled (truth label 0), a small machine region's as
        belonging to no region. Machine regions are measured on labelled GT
        pixels. Default 1 (keep all).

    Returns
    -------
    SegmentationScores
        Counts, labels of each instance, and the normal angle of each correct
        detection when both plane sets are given.

    Raises
    ------
    ValueError
        If a label image is not 2-D, not of an integer dtype or has negative
        labels, the two have different shapes, ``tolerance`` is outside
        ``(0.5, 1]``, ``min_region_size`` < 1, or planes are not an ``(L, 4)``
        array covering every label nor a dict of ``(4,)`` planes.

    Notes
    -----
    *Unlabelled GT pixels.* The ground truth of the SegComp images leaves
    pixels without a region label (no range data, shadows, and pixels whose
    surface a human could not decide), and the comparison only considers
    labelled GT pixels [1]_: the truth there is unknown, so no segmentation
    is rewarded or penalised for what it does on them. Accordingly, truth
    label 0 pixels count towards neither ``M_m``, ``N_n`` nor ``O_mn``; a
    machine region lying entirely on them is not considered at all (it is
    not noise).

    *One class per region.* For ``T > 0.5`` a region can give ``T`` or more
    of its own pixels to at most one region of the other segmentation, so
    each region takes part in at most one instance of each of
    the three classes; Hoover et al. note that a region can therefore be in
    at most three classifications, one of each [1]_. The definitions do
    allow a region to be in two: a GT region covered 90 % by one machine
    region and 10 % by a second, small one is correctly detected and, with
    the same two machine regions, over-segmented; a machine region that
    correctly detects a GT region can also be an under-segmentation of it
    and a small neighbour. Such a double classification always involves a
    correct detection (an over- and an under-segmentation sharing a region
    force that region's pair to be a correct detection), so correct
    detection takes precedence: regions of correct detections are not used
    in over- or under-segmentations (the small machine region above is
    noise, the small neighbour missed). Over- and under-segmentation
    instances are then disjoint, and every region falls in exactly one
    class. Tolerances of 0.5 or below are rejected, since one region could
    then have two correct detections.

    *Normals.* The angle is per correct detection, between the GT and the
    machine normal, ignoring their sign. Hoover et al.'s own geometric
    measure differs: they compare the angle between the normals of
    *adjacent* correctly detected GT regions with that of their machine
    counterparts.

    References
    ----------
    .. [1] A. Hoover et al., "An experimental comparison of range image
       segmentation algorithms", IEEE TPAMI 18(7), 673-689, 1996, Section 3.

    Examples
    --------
    GT region 1 is found as machine region 5; GT region 2 is split into
    machine regions 7 and 8:

    >>> import numpy as np
    >>> truth = np.array([[1, 1, 1, 1, 2, 2, 2, 2],
    ...                   [1, 1, 1, 1, 2, 2, 2, 2]])
    >>> machine = np.array([[5, 5, 5, 5, 7, 7, 8, 8],
    ...                     [5, 5, 5, 5, 7, 7, 8, 8]])
    >>> scores = evaluate_segmentation(truth, machine, tolerance=0.8)
    >>> scores.correct, scores.over_segmented, scores.missed, scores.noise
    (1, 1, 0, 0)
    >>> scores.correct_pairs, scores.over_pairs
    (((1, 5),), ((2, (7, 8)),))
    >>> scores.correct_fraction
    0.5
    """
    truth = _check_labels(truth_labels, "truth_labels")
    machine = _check_labels(machine_labels, "machine_labels")
    if truth.shape != machine.shape:
        raise ValueError(
            f"truth_labels and machine_labels must have the same shape, got {truth.shape} and {machine.shape}"
        )
    tolerance_value, fraction = _check_tolerance(tolerance)
    min_region_size = _check_min_region_size(min_region_size)
    num, den = fraction.numerator, fraction.denominator

    truth_flat, machine_flat = truth.ravel(), machine.ravel()
    largest_truth = int(truth_flat.max()) if truth.size else 0
    largest_machine = int(machine_flat.max()) if machine.size else 0
    truth_planes = _check_planes(truth_planes, "truth_planes", largest_truth)
    machine_planes = _check_planes(machine_planes, "machine_planes", largest_machine)
    if (largest_truth + 1) * (largest_machine + 1) <= 4 * truth.size + 4096:
        # Small label values index the table directly (absent labels get
        # size 0 and drop out below); no relabelling pass is needed.
        truth_values, truth_index = np.arange(largest_truth + 1), truth_flat.astype(np.intp, copy=False)
        machine_values, machine_index = np.arange(largest_machine + 1), machine_flat.astype(np.intp, copy=False)
    else:
        truth_values, truth_index = _compress(truth_flat)
        machine_values, machine_index = _compress(machine_flat)
    n_truth, n_machine = truth_values.size, machine_values.size
    pair_truth, pair_machine, overlap = _overlap_pairs(truth_index, machine_index, n_truth, n_machine)

    # Unlabelled GT pixels take no part (see Notes); machine label 0 is no region.
    keep = truth_values[pair_truth] != 0
    pair_truth, pair_machine, overlap = pair_truth[keep], pair_machine[keep], overlap[keep]

    # Region sizes from the table: M_m over all labelled pixels of R_m; N_n
    # only over pixels of the GT regions that are kept.
    truth_size = np.bincount(pair_truth, weights=overlap, minlength=n_truth).astype(np.int64)
    truth_kept = truth_size >= min_region_size
    keep = truth_kept[pair_truth] & (machine_values[pair_machine] != 0)
    pair_truth, pair_machine, overlap = pair_truth[keep], pair_machine[keep], overlap[keep]
    machine_size = np.bincount(pair_machine, weights=overlap, minlength=n_machine).astype(np.int64)
    machine_kept = machine_size >= min_region_size
    keep = machine_kept[pair_machine]
    pair_truth, pair_machine, overlap = pair_truth[keep], pair_machine[keep], overlap[keep]

    # O >= T * size, exactly: O * den >= num * size.
    scaled = overlap * den
    covers_truth = scaled >= num * truth_size[pair_truth]
    covers_machine = scaled >= num * machine_size[pair_machine]

    is_correct = covers_truth & covers_machine
    truth_correct = np.zeros(n_truth, bool)
    machine_correct = np.zeros(n_machine, bool)
    truth_correct[pair_truth[is_correct]] = True
    machine_correct[pair_machine[is_correct]] = True

    # Over-segmentation: the machine regions mostly inside a GT region (each
    # machine region is mostly inside at most one) jointly cover enough of it.
    candidate = covers_machine & ~truth_correct[pair_truth] & ~machine_correct[pair_machine]
    truth_over, machine_over, in_over = _split_regions(
        candidate, pair_truth, truth_size, pair_machine, n_machine, overlap, num, den
    )

    # Under-segmentation: the mirror image, among regions not yet classified.
    truth_used = truth_correct | truth_over
    machine_used = machine_correct | machine_over
    candidate = covers_truth & ~truth_used[pair_truth] & ~machine_used[pair_machine]
    machine_under, truth_under, in_under = _split_regions(
        candidate, pair_machine, machine_size, pair_truth, n_truth, overlap, num, den
    )

    truth_missed = truth_kept & ~(truth_correct | truth_over | truth_under)
    machine_noise = machine_kept & ~(machine_correct | machine_over | machine_under)

    correct_truth = truth_values[pair_truth[is_correct]].tolist()
    correct_machine = machine_values[pair_machine[is_correct]].tolist()
    over_pairs = _group(truth_values[pair_truth[in_over]].tolist(), machine_values[pair_machine[in_over]].tolist())
    under_pairs = _group(machine_values[pair_machine[in_under]].tolist(), truth_values[pair_truth[in_under]].tolist())

    normal_errors: tuple[float, ...] = ()
    if truth_planes is not None and machine_planes is not None and correct_truth:
        normal_errors = _normal_angles(_normals(truth_planes, correct_truth), _normals(machine_planes, correct_machine))

    return SegmentationScores(
        tolerance=tolerance_value,
        n_truth=int(truth_kept.sum()),
        n_machine=int(machine_kept.sum()),
        correct=len(correct_truth),
        over_segmented=len(over_pairs),
        under_segmented=len(under_pairs),
        missed=int(truth_missed.sum()),
        noise=int(machine_noise.sum()),
        correct_pairs=tuple(zip(correct_truth, correct_machine)),
        over_pairs=over_pairs,
        under_pairs=under_pairs,
        missed_labels=tuple(truth_values[truth_missed].tolist()),
        noise_labels=tuple(machine_values[machine_noise].tolist()),
        normal_errors_deg=normal_errors,
    )


def _split_regions(candidate, whole_index, whole_size, part_index, n_parts, overlap, num, den):
    """Regions split into 2 or more candidate parts that jointly cover at least T of them, those parts, and the pairs.

    Over-segmentation with GT regions as the wholes and machine regions as the
    parts; under-segmentation the other way round.
    """
    parts = np.bincount(whole_index[candidate], minlength=len(whole_size))
    covered = np.bincount(whole_index[candidate], weights=overlap[candidate], minlength=len(whole_size)).astype(np.int64)
    split = (parts >= 2) & (covered * den >= num * whole_size)
    in_split = candidate & split[whole_index]
    part_flags = np.zeros(n_parts, bool)
    part_flags[part_index[in_split]] = True
    return split, part_flags, in_split


def _group(keys: list[int], members: list[int]) -> tuple[tuple[int, tuple[int, ...]], ...]:
    """``((key, (members...)), ...)`` sorted by key, members sorted."""
    groups: dict[int, list[int]] = {}
    for key, member in zip(keys, members):
        groups.setdefault(key, []).append(member)
    return tuple((key, tuple(sorted(groups[key]))) for key in sorted(groups))


def _truth_labels(
    truth: GroundTruth, rays: np.ndarray, *, max_incidence: float = 80.0, planar_only: bool = True
) -> np.ndarray:
    """Ground-truth label image of a simulated frame for `evaluate_segmentation`.

    Hoover et al.'s ground truth labels only what a range sensor can
    measure; pixels it cannot are left unlabelled and do not count. Here
    that means:

    * pixels whose true incidence angle exceeds ``max_incidence`` degrees (a
      surface seen edge-on: one pixel's footprint spans many times the pixel
      pitch in depth, so neither its position nor its normal is measured);
    * mixed (flying) pixels and salt-and-pepper readings;
    * with ``planar_only``, surfaces that are not planes (the cylinder), for
      scoring a plane segmentation.

    Parameters
    ----------
    truth : GroundTruth
        From `rangesurf.simulate.simulate_frame`.
    rays : (H, W, 3) float array
        Unit viewing directions of the frame (``frame.rays``).
    max_incidence : float
        Degrees in (0, 90].
    planar_only : bool
        Keep only planar surfaces.

    Returns
    -------
    (H, W) int32
        Surface ids, 0 where unlabelled.

    Examples
    --------
    >>> from rangesurf import simulate
    >>> frames, truths = simulate.simulate_sequence("arena", "sr3000", n_frames=1)
    >>> labels = _truth_labels(truths[0], frames[0].rays)
    >>> bool((labels > 0).mean() > 0.8)
    True
    """
    if not (isinstance(max_incidence, (int, float)) and 0 < max_incidence <= 90):
        raise ValueError(f"max_incidence must be in (0, 90] degrees, got {max_incidence!r}")
    labels = np.asarray(truth.surface_id, dtype=np.int32).copy()
    rays = np.asarray(rays, dtype=np.float64)
    if rays.shape != labels.shape + (3,):
        raise ValueError(f"rays must have shape {labels.shape + (3,)} to match the ground truth, got {rays.shape}")
    with np.errstate(invalid="ignore"):
        cosine = np.abs(np.einsum("ijk,ijk->ij", truth.normals.astype(np.float64), rays))
    grazing = ~(cosine >= math.cos(math.radians(max_incidence)))
    labels[grazing | truth.mixed | truth.outlier] = 0
    if planar_only:
        planar = np.isfinite(truth.planes[:, 0])
        labels[~planar[np.clip(labels, 0, len(planar) - 1)] | (labels >= len(planar))] = 0
    return labels



def truth_segmentation(
    truth: GroundTruth, rays: np.ndarray, *, max_incidence: float = 80.0, planar_only: bool = True
) -> Segmentation:
    """The ground truth of a simulated frame as a `Segmentation` to score against.

    As `_truth_labels`, and each surface split into its 4-connected parts:
    SegComp's ground-truth regions are connected, and the simulator gives
    one id to every piece of a surface (a wall interrupted by a door is two
    regions to find, not one). Each part keeps its surface's plane.

    Parameters
    ----------
    truth : GroundTruth
        From `rangesurf.simulate.simulate_frame`.
    rays : (H, W, 3) float array
        Unit viewing directions of the frame (``frame.rays``).
    max_incidence, planar_only
        As for `_truth_labels`.

    Returns
    -------
    Segmentation
        ``labels`` the parts (largest first), ``planes`` their surfaces' true
        planes (sensor frame), ``residuals`` 0, ``sizes`` pixel counts.

    Examples
    --------
    >>> from rangesurf import simulate
    >>> frames, truths = simulate.simulate_sequence("corridor", "sr3000", n_frames=1)
    >>> parts = truth_segmentation(truths[0], frames[0].rays)
    >>> bool(parts.n_segments > len(np.unique(_truth_labels(truths[0], frames[0].rays))) - 1)
    True
    """
    labels = _truth_labels(truth, rays, max_incidence=max_incidence, planar_only=planar_only)
    parts = np.zeros(labels.shape, np.int32)
    surface_of_part = [0]
    for surface in np.unique(labels[labels > 0]):
        count, components = cv2.connectedComponents((labels == surface).astype(np.uint8), connectivity=4)
        inside = components > 0
        parts[inside] = components[inside] + len(surface_of_part) - 1
        surface_of_part += [int(surface)] * (count - 1)
    surface_of_part = np.asarray(surface_of_part)
    sizes = np.bincount(parts.ravel(), minlength=len(surface_of_part))
    order = np.argsort(-sizes[1:], kind="stable") + 1
    renumber = np.zeros(len(surface_of_part), np.int32)
    renumber[order] = np.arange(1, len(order) + 1, dtype=np.int32)
    planes = np.full((len(order) + 1, 4), np.nan)
    planes[1:] = np.asarray(truth.planes)[surface_of_part[order]]
    residuals = np.zeros(len(order) + 1)
    residuals[0] = np.nan
    unlabelled = int(np.count_nonzero(np.isfinite(truth.range) & (labels == 0)))
    return Segmentation(
        labels=renumber[parts], planes=planes, residuals=residuals,
        sizes=np.concatenate([[unlabelled], sizes[order]]).astype(np.int64),
    )


def transform_planes(planes: np.ndarray, T_target_source: np.ndarray) -> np.ndarray:
    """Planes ``(K, 4)`` (``n . p + d = 0`` in the source frame) expressed in the target frame.

    Examples
    --------
    >>> T = np.eye(4); T[:3, 3] = (0, 0, 1)  # the source frame sits 1 m along target z
    >>> transform_planes(np.array([[0.0, 0.0, -1.0, 2.0]]), T)
    array([[ 0.,  0., -1.,  3.]])
    """
    planes = np.atleast_2d(np.asarray(planes, dtype=np.float64))
    rotation, translation = T_target_source[:3, :3], T_target_source[:3, 3]
    normals = planes[:, :3] @ rotation.T
    return np.column_stack([normals, planes[:, 3] - normals @ translation])


def match_planes(
    planes: np.ndarray, others: np.ndarray, *, max_angle: float = 5.0, max_offset: float = 0.1
) -> list[tuple[int, int, float, float]]:
    """Pair each plane with the most parallel plane of another set that lies within an offset.

    Parameters
    ----------
    planes, others : (K, 4) and (L, 4) float arrays
        ``(nx, ny, nz, d)`` in one frame (see `transform_planes`); NaN rows
        are skipped.
    max_angle : float
        Degrees between the normals (sign ignored).
    max_offset : float
        Metres between the planes' distances from the origin.

    Returns
    -------
    list of (index, other_index, angle_deg, offset_m)
        One entry per matched row of ``planes``.
    """
    planes = np.atleast_2d(np.asarray(planes, dtype=np.float64))
    others = np.atleast_2d(np.asarray(others, dtype=np.float64))
    matches = []
    for index, (normal, offset) in enumerate(zip(planes[:, :3], planes[:, 3])):
        if not np.isfinite(normal).all():
            continue
        cosine = others[:, :3] @ normal
        sign = np.where(cosine < 0, -1.0, 1.0)
        angles = np.degrees(np.arccos(np.clip(np.abs(cosine), 0.0, 1.0)))
        offsets = np.abs(sign * others[:, 3] - offset)
        fits = np.flatnonzero((angles <= max_angle) & (offsets <= max_offset))
        if fits.size:
            best = fits[np.argmin(angles[fits])]
            matches.append((index, int(best), float(angles[best]), float(offsets[best])))
    return matches
