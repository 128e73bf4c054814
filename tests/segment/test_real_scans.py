"""Planes of the real 3DTK scans: the same walls and floor in two consecutive scans."""

from pathlib import Path

import numpy as np
import pytest

import rangesurf as rs
from rangesurf.segment import match_planes, segment_frame, transform_planes

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "uos-3dtk"


@pytest.fixture(scope="module")
def scans():
    if not (DATA / "scan001.3d").is_file():
        pytest.skip(f"3DTK scans not found at {DATA} (shared test data lives beside the project)")
    frames = [rs.load(DATA / f"scan00{k}.3d")[0] for k in (0, 1)]
    return frames, [segment_frame(frame).segmentation for frame in frames]


def large_planes_in_world(frame, segmentation, fraction=0.01):
    large = np.flatnonzero(segmentation.sizes[1:] >= fraction * segmentation.labels.size) + 1
    return transform_planes(segmentation.planes[large], frame.reference_pose)


def test_large_planes_are_found_again_in_the_next_scan(scans):
    frames, segmentations = scans
    first = large_planes_in_world(frames[0], segmentations[0])
    second = large_planes_in_world(frames[1], segmentations[1])
    matches = match_planes(first, second, max_angle=5.0, max_offset=0.10)
    assert len(first) >= 8
    assert len(matches) >= 0.6 * len(first)
    # The four largest (walls, floor, ceiling) all return, within 3 degrees (the reference pose is approximate).
    largest = {index: angle for index, _, angle, _ in matches if index < 4}
    assert len(largest) == 4 and max(largest.values()) < 3.0


def test_segments_are_flat_within_the_scanner_noise(scans):
    _, segmentations = scans
    for segmentation in segmentations:
        big = segmentation.sizes[1:] >= 1000
        assert big.sum() >= 5
        assert np.median(segmentation.residuals[1:][big]) < 0.015
