"""Figures of a run: image panels written with OpenCV (no plotting stack needed)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from rangesurf.io._common import atomic_path

__all__ = ["colorize_range", "colorize_edges", "image_panel", "write_image"]

_NO_RETURN_BGR = (64, 64, 64)
_LABEL_HEIGHT = 22


def colorize_range(range_image: np.ndarray, *, valid_range: tuple[float, float] | None = None) -> np.ndarray:
    """A warm colour map of a range image, as thesis Figure 2.5 shows them.

    Parameters
    ----------
    range_image : (H, W) float array
        Metres, NaN where there is no return (drawn dark grey).
    valid_range : (low, high), optional
        Metres mapped to the ends of the colour map; default the 1st and
        99th percentiles of the valid ranges (spikes would otherwise squeeze
        the scene into a few colours). Panels of one frame should share it.

    Returns
    -------
    (H, W, 3) uint8
        BGR image (OpenCV order).
    """
    range_image = np.asarray(range_image, dtype=np.float64)
    if range_image.ndim != 2:
        raise ValueError(f"range image must be 2-D, got shape {range_image.shape}")
    valid = np.isfinite(range_image)
    if valid.any():
        low, high = valid_range if valid_range is not None else np.percentile(range_image[valid], [1, 99])
    else:
        low, high = 0.0, 1.0
    scale = 255.0 / (high - low) if high > low else 0.0
    grey = np.clip((np.where(valid, range_image, low) - low) * scale, 0, 255).astype(np.uint8)
    # Near is bright: COLORMAP_HOT runs black-red-yellow-white, so invert.
    image = cv2.applyColorMap(255 - grey, cv2.COLORMAP_HOT)
    image[~valid] = _NO_RETURN_BGR
    return image


def colorize_edges(edges: np.ndarray, *, background: np.ndarray | None = None) -> np.ndarray:
    """Edge pixels in white over a dimmed background (or black)."""
    edges = np.asarray(edges, dtype=bool)
    if edges.ndim != 2:
        raise ValueError(f"edge map must be 2-D, got shape {edges.shape}")
    image = np.zeros(edges.shape + (3,), np.uint8) if background is None else (background // 3).astype(np.uint8)
    image[edges] = 255
    return image


def image_panel(images: Sequence[np.ndarray], labels: Sequence[str], *, columns: int = 2, scale: int | None = None) -> np.ndarray:
    """Tile equally sized BGR images into a labelled grid.

    ``scale`` enlarges small range images (nearest neighbour, so pixels stay
    visible); default: enough to make each tile at least 320 pixels wide.
    """
    if not images or len(images) != len(labels):
        raise ValueError(f"need one label per image, got {len(images)} images and {len(labels)} labels")
    height, width = images[0].shape[:2]
    if any(image.shape[:2] != (height, width) for image in images):
        raise ValueError("panel images must share one size")
    scale = scale or max(1, -(-320 // width))
    tiles = []
    for image, label in zip(images, labels):
        tile = cv2.resize(image, (width * scale, height * scale), interpolation=cv2.INTER_NEAREST)
        caption = np.full((_LABEL_HEIGHT, tile.shape[1], 3), 255, np.uint8)
        cv2.putText(caption, label, (4, _LABEL_HEIGHT - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(np.vstack([caption, tile]))
    blank = np.full_like(tiles[0], 255)
    while len(tiles) % columns:
        tiles.append(blank)
    rows = [np.hstack(tiles[i : i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows)


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an image atomically (format from the suffix, e.g. ``.png``)."""
    path = Path(path)
    with atomic_path(path) as temporary:
        if not cv2.imwrite(str(temporary), image):
            raise OSError(f"{path}: OpenCV could not write a {path.suffix} image")
    return path
