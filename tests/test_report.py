"""Figure helpers: what they draw where."""

import numpy as np
import pytest

from rangesurf import report


def test_label_colours_are_distinct_and_zero_shows_the_background():
    labels = np.repeat(np.arange(6, dtype=np.int32), 4).reshape(4, 6)
    background = np.full((4, 6, 3), 17, np.uint8)
    image = report.colorize_labels(labels, background=background)
    assert (image[labels == 0] == 17).all()
    colours = {tuple(image[labels == k][0]) for k in range(1, 6)}
    assert len(colours) == 5


def test_colorize_labels_refuses_floats():
    with pytest.raises(ValueError, match="integer"):
        report.colorize_labels(np.zeros((3, 3)))


def test_nxd_scatter_puts_two_clusters_apart():
    nxd = np.zeros((10, 10, 3))
    nxd[:, :5] = (0, 0, -2)
    nxd[:, 5:] = (1, 0, -3)
    labels = np.where(np.arange(10) < 5, 1, 2)[None].repeat(10, 0).astype(np.int32)
    image = report.nxd_scatter(nxd, labels, size=(100, 120))
    drawn = np.argwhere((image != 255).any(axis=2))
    assert 2 <= len(drawn) <= 4  # every cluster is one spot: two points drawn (maybe one pixel wide more)
    assert np.ptp(drawn[:, 1]) > 40  # and the spots are far apart


def test_segmentation_figure_has_three_panels():
    range_image = np.linspace(1, 3, 40 * 50, dtype=np.float32).reshape(40, 50)
    labels = (range_image > 2).astype(np.int32) + 1
    nxd = np.dstack([np.zeros_like(range_image), np.zeros_like(range_image), -range_image])
    figure = report.segmentation_figure(range_image, labels, nxd)
    assert figure.shape[1] == 3 * 50 * 7  # tiles enlarged to >= 320 pixels wide
