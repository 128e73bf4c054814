"""Uncertainty as geometry and colour (thesis Sections 2.4 and 3.4).

So far the colour mapping (thesis: hue, warmer = less certain) used by the
exports; the geometric glyphs (displaced points, bars, shells, volume,
cones) follow with the viewer.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["combined_uncertainty", "hue_colours"]


def combined_uncertainty(surface, levels: tuple[str, ...] = ("UL1", "UL2", "UL3", "UL4")) -> np.ndarray:
    """Per-vertex root sum of squares of the chosen uncertainty levels (metres); NaN where none is present."""
    present = [surface.uncertainty[level].astype(np.float64) for level in levels if level in surface.uncertainty]
    if not present:
        return np.full(surface.n_vertices, np.nan)
    return np.sqrt(np.sum([np.nan_to_num(values) ** 2 for values in present], axis=0))


def hue_colours(values: np.ndarray, *, vmax: float, vmin: float = 0.0) -> np.ndarray:
    """RGBA uint8 colours: dark purple (certain) through red to yellow (uncertain); NaN grey.

    Examples
    --------
    >>> hue_colours(np.array([0.0, 0.01, np.nan]), vmax=0.01)[:, :3].tolist()
    [[0, 0, 4], [252, 255, 164], [128, 128, 128]]
    """
    values = np.asarray(values, dtype=np.float64)
    span = max(vmax - vmin, 1e-12)
    scaled = np.clip((np.nan_to_num(values, nan=vmin) - vmin) / span, 0.0, 1.0)
    # OpenCV's inferno map (perceptually uniform), applied to a 1-D "image" of the values.
    bgr = cv2.applyColorMap(np.round(scaled * 255).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_INFERNO).reshape(-1, 3)
    colours = np.empty((len(values), 4), np.uint8)
    colours[:, :3] = bgr[:, ::-1]
    colours[:, 3] = 255
    colours[~np.isfinite(values), :3] = 128
    return colours
