"""Figures of a run: image panels written with OpenCV (no plotting stack needed)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from rangesurf.io._common import atomic_path

__all__ = [
    "colorize_range", "colorize_edges", "colorize_labels", "nxd_scatter", "segmentation_figure", "wireframe",
    "lod_figure", "image_panel", "write_image",
]

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


def _label_colours(count: int) -> np.ndarray:
    """``count + 1`` BGR colours: grey for label 0, then well-separated hues (golden-ratio steps)."""
    hues = (np.arange(count) * 0.618034 % 1.0 * 180).astype(np.uint8)
    hsv = np.stack([hues, np.full(count, 200, np.uint8), np.full(count, 255, np.uint8)], axis=1)[None]
    colours = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0]
    return np.vstack([[[110, 110, 110]], colours]).astype(np.uint8)


def colorize_labels(labels: np.ndarray, *, background: np.ndarray | None = None, opacity: float = 0.65) -> np.ndarray:
    """Segments in distinct colours, blended over a background image (thesis Figure 3.5, top right).

    Parameters
    ----------
    labels : (H, W) int array
        Segment labels, 0 = none (shows the background, or grey).
    background : (H, W, 3) uint8, optional
        BGR image under the segments.
    opacity : float
        Weight of the segment colour over the background.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"labels must be a 2-D integer array, got shape {labels.shape} and dtype {labels.dtype}")
    colours = _label_colours(int(labels.max(initial=0)))
    image = colours[np.clip(labels, 0, None)]
    if background is None:
        return image
    blended = (opacity * image + (1 - opacity) * background).astype(np.uint8)
    return np.where((labels > 0)[..., None], blended, background)


def nxd_scatter(
    nxd: np.ndarray, labels: np.ndarray, *, size: tuple[int, int], azimuth: float = 35.0, elevation: float = 25.0
) -> np.ndarray:
    """The normal x distance cloud seen obliquely, each point in its segment's colour (thesis Figure 3.5, bottom).

    Parameters
    ----------
    nxd : (H, W, 3) float array
        `rangesurf.segment.nxd_transform` output, NaN where unknown.
    labels : (H, W) int array
        Segment of each pixel (0 = none, drawn grey, under the others).
    size : (height, width)
        Image size in pixels.
    azimuth, elevation : float
        Viewing direction (degrees).
    """
    height, width = size
    image = np.full((height, width, 3), 255, np.uint8)
    known = np.isfinite(nxd).all(axis=2)
    if not known.any():
        return image
    a, e = np.radians(azimuth), np.radians(elevation)
    turn = np.array([[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]])
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(e), -np.sin(e)], [0.0, np.sin(e), np.cos(e)]])
    view = (nxd[known].astype(np.float64) - np.nanmedian(nxd[known], axis=0)) @ (tilt @ turn).T
    low, high = np.percentile(view[:, :2], [0.5, 99.5], axis=0)
    scale = 0.9 * min(width / max(high[0] - low[0], 1e-9), height / max(high[1] - low[1], 1e-9))
    centre = (low + high) / 2
    columns = np.round((view[:, 0] - centre[0]) * scale + width / 2).astype(int)
    rows = np.round((view[:, 1] - centre[1]) * scale + height / 2).astype(int)
    inside = (rows >= 0) & (rows < height) & (columns >= 0) & (columns < width)
    point_labels = labels[known]
    colours = _label_colours(int(labels.max(initial=0)))
    # Unlabelled points first, so that segments are drawn over them.
    order = np.argsort(point_labels > 0, kind="stable")
    order = order[inside[order]]
    image[rows[order], columns[order]] = colours[np.clip(point_labels[order], 0, None)]
    return image


def segmentation_figure(range_image: np.ndarray, labels: np.ndarray, nxd: np.ndarray, *, title: str = "") -> np.ndarray:
    """Thesis Figure 3.5 for one frame: grey range, segments over it, and the NxD cloud coloured by segment."""
    from rangesurf.edges import normalize_range

    finite = np.isfinite(range_image)
    # Percentiles, not the extremes: a few far returns would leave the scene black.
    valid_range = tuple(np.percentile(range_image[finite], [1, 99])) if finite.sum() > 1 else None
    if valid_range is not None and not valid_range[0] < valid_range[1]:
        valid_range = None
    grey = normalize_range(range_image, valid_range=valid_range).astype(np.uint8)
    background = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    background[~np.isfinite(range_image)] = _NO_RETURN_BGR
    height, width = grey.shape
    scale = max(1, -(-320 // width))
    big = (width * scale, height * scale)
    tiles = [cv2.resize(image, big, interpolation=cv2.INTER_NEAREST) for image in (background, colorize_labels(labels, background=background))]
    tiles.append(nxd_scatter(nxd, labels, size=(height * scale, width * scale)))
    captions = ["normalized range", f"segments ({int(labels.max(initial=0))}){' - ' + title if title else ''}", "N x D space by segment"]
    return image_panel(tiles, captions, columns=3, scale=1)


def wireframe(xy: np.ndarray, faces: np.ndarray, *, size: tuple[int, int], bounds: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Triangle edges of a mesh drawn in 2-D (e.g. its plane's coordinates), dark on white.

    Parameters
    ----------
    xy : (N, 2) float array
        Vertex positions.
    faces : (M, 3) int array
    size : (height, width)
        Image size in pixels.
    bounds : (low, high), optional
        The (2,) corners mapped to the image; default the vertices' extent
        (share it between panels of one surface).
    """
    height, width = size
    image = np.full((height, width, 3), 255, np.uint8)
    if len(xy) == 0:
        return image
    low, high = bounds if bounds is not None else (xy.min(axis=0), xy.max(axis=0))
    scale = 0.94 * min(width / max(high[0] - low[0], 1e-12), height / max(high[1] - low[1], 1e-12))
    offset = np.array([width, height]) / 2 - scale * (np.asarray(low) + np.asarray(high)) / 2
    pixels = np.round(xy * scale + offset).astype(np.int32)
    if len(faces):
        cv2.polylines(image, list(pixels[np.asarray(faces)]), True, (90, 60, 30), 1, cv2.LINE_AA)
    for x, y in pixels:
        cv2.circle(image, (int(x), int(y)), 1, (0, 0, 200), -1)
    return image


def lod_figure(xy: np.ndarray, levels: list, order: np.ndarray, *, size: tuple[int, int] = (300, 300)) -> np.ndarray:
    """Thesis Figure 3.8: one surface from fine to coarse (one wireframe per level, shared scale).

    Parameters
    ----------
    xy : (N, 2) float array
        The surface's vertices in its plane's coordinates.
    levels : list of rangesurf.lod.Level
        The levels to draw, finest first.
    order : (N,) int array
        The surface's ``lod_order``.
    """
    bounds = (xy.min(axis=0), xy.max(axis=0))
    tiles = [wireframe(xy[order[: level.count]], level.faces, size=size, bounds=bounds) for level in levels]
    captions = [f"{level.count} vertices, error {1000 * level.error:.1f} mm" for level in levels]
    return image_panel(tiles, captions, columns=len(tiles), scale=1)


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
