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
    "lod_figure", "image_panel", "write_image", "line_chart", "top_view", "run_report",
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


# --------------------------------------------------------------------------
# Charts and the run report.
# --------------------------------------------------------------------------

_SERIES_BGR = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140), (194, 119, 227)]


def line_chart(series: dict[str, tuple[np.ndarray, np.ndarray]], *, size: tuple[int, int] = (320, 900), x_label: str = "",
               y_label: str = "", equal_axes: bool = False, hline: tuple[float, str] | None = None) -> np.ndarray:
    """Lines of (x, y) series on white, with axis ranges, labels and a legend (BGR image).

    Parameters
    ----------
    series : dict of name -> (x, y)
    size : (height, width)
    equal_axes : bool
        One scale for both axes (maps, trajectories).
    hline : (value, label), optional
        A dashed horizontal reference line (a time budget).
    """
    height, width = size
    image = np.full((height, width, 3), 255, np.uint8)
    margin_left, margin_right, margin_top, margin_bottom = 70, 20, 30, 40
    xs = [np.asarray(x, np.float64) for x, _ in series.values()]
    ys = [np.asarray(y, np.float64) for _, y in series.values()]
    finite_x = np.concatenate([x[np.isfinite(x)] for x in xs]) if xs else np.zeros(0)
    finite_y = np.concatenate([y[np.isfinite(y)] for y in ys] + ([np.array([hline[0]])] if hline else [])) if ys else np.zeros(0)
    if finite_x.size == 0 or finite_y.size == 0:
        return image
    x_low, x_high = float(finite_x.min()), float(finite_x.max())
    y_low, y_high = float(finite_y.min()), float(finite_y.max())
    if not equal_axes:
        y_low = min(y_low, 0.0)
    x_high, y_high = max(x_high, x_low + 1e-9), max(y_high, y_low + 1e-9)
    plot_width, plot_height = width - margin_left - margin_right, height - margin_top - margin_bottom
    x_scale, y_scale = plot_width / (x_high - x_low), plot_height / (y_high - y_low)
    if equal_axes:
        x_scale = y_scale = min(x_scale, y_scale)

    def to_pixels(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.column_stack([margin_left + (x - x_low) * x_scale, height - margin_bottom - (y - y_low) * y_scale]).round().astype(np.int32)

    cv2.rectangle(image, (margin_left, margin_top), (width - margin_right, height - margin_bottom), (200, 200, 200), 1)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for value, position in ((y_low, height - margin_bottom), (y_high if not equal_axes else y_low + plot_height / y_scale, margin_top + 10)):
        cv2.putText(image, f"{value:.3g}", (4, position), font, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    cv2.putText(image, f"{x_low:.3g}", (margin_left, height - margin_bottom + 15), font, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    right_value = x_high if not equal_axes else x_low + plot_width / x_scale
    cv2.putText(image, f"{right_value:.3g}", (width - margin_right - 40, height - margin_bottom + 15), font, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    cv2.putText(image, x_label, (width // 2 - 40, height - 8), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(image, y_label, (4, 18), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if hline is not None:
        (_, line_y), = to_pixels(np.array([x_low]), np.array([hline[0]]))
        for start in range(margin_left, width - margin_right, 12):
            cv2.line(image, (start, int(line_y)), (min(start + 6, width - margin_right), int(line_y)), (0, 0, 180), 1)
        cv2.putText(image, hline[1], (width - margin_right - 160, int(line_y) - 4), font, 0.4, (0, 0, 180), 1, cv2.LINE_AA)
    legend_x = margin_left + 8
    for index, ((name, _), x, y) in enumerate(zip(series.items(), xs, ys)):
        colour = _SERIES_BGR[index % len(_SERIES_BGR)]
        keep = np.isfinite(x) & np.isfinite(y)
        if keep.sum() >= 2:
            cv2.polylines(image, [to_pixels(x[keep], y[keep])], False, colour, 1, cv2.LINE_AA)
        elif keep.sum() == 1:
            cv2.circle(image, tuple(int(v) for v in to_pixels(x[keep], y[keep])[0]), 3, colour, -1)
        cv2.putText(image, name, (legend_x, margin_top - 10), font, 0.42, colour, 1, cv2.LINE_AA)
        legend_x += 12 + 8 * len(name)
    return image


def top_view(surfaces: list, colours: list[np.ndarray], *, size: int = 640) -> np.ndarray:
    """The surfaces seen from above (world x right, y up), vertices drawn lowest first in their colours (BGR)."""
    image = np.full((size, size, 3), 255, np.uint8)
    if not surfaces or not sum(surface.n_vertices for surface in surfaces):
        return image
    vertices = np.vstack([surface.vertices for surface in surfaces]).astype(np.float64)
    colour = np.vstack(colours)[:, :3][:, ::-1]
    low, high = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
    scale = 0.94 * size / max(float((high - low).max()), 1e-9)
    offset = size / 2 - scale * (low + high) / 2
    columns = np.clip(np.round(vertices[:, 0] * scale + offset[0]), 0, size - 1).astype(int)
    rows = np.clip(np.round(size - 1 - (vertices[:, 1] * scale + offset[1])), 0, size - 1).astype(int)
    order = np.argsort(vertices[:, 2])
    image[rows[order], columns[order]] = colour[order]
    return image


def _png(image: np.ndarray) -> str:
    import base64

    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise OSError("OpenCV could not encode a PNG")
    return "data:image/png;base64," + base64.b64encode(data.tobytes()).decode("ascii")


def run_report(metrics: dict, rows: list[dict], surfaces: list, last, last_frame, poses: np.ndarray, truths: list) -> str:
    """``report.html`` of a run: one self-contained page (images inline), as a reader of the thesis would want it.

    Sections: the summary; the last frame raw, denoised and segmented; the
    model from above coloured by uncertainty and by surface; the largest
    surface at several levels of detail; the per-stage timings over the
    run; the trajectory against ground truth when there is one.
    """
    import html

    from rangesurf.glyphs import combined_uncertainty, hue_colours
    from rangesurf.pipeline import STAGES

    figures: list[tuple[str, str, str]] = []
    if last is not None and last_frame is not None:
        finite = np.isfinite(last_frame.range)
        valid_range = tuple(np.percentile(last_frame.range[finite], [1, 99])) if finite.sum() > 1 else None
        background = colorize_range(last.range, valid_range=valid_range)
        panel = image_panel(
            [colorize_range(last_frame.range, valid_range=valid_range), background,
             colorize_labels(last.segmentation.labels, background=background)],
            ["raw range", "denoised", f"{last.segmentation.n_segments} planar segments"], columns=3)
        figures.append(("The last frame", "Range image as read, after denoising, and its planar segments "
                        "(thesis Figures 2.5 and 3.5).", _png(panel)))
    if surfaces:
        values = [combined_uncertainty(surface) for surface in surfaces]
        finite_values = np.concatenate([value[np.isfinite(value)] for value in values])
        vmax = float(np.percentile(finite_values, 95)) if finite_values.size else 1.0
        by_uncertainty = top_view(surfaces, [hue_colours(value, vmax=vmax) for value in values])
        label_colours = _label_colours(len(surfaces) + 1)
        by_surface = top_view(surfaces, [np.column_stack([np.tile(label_colours[index + 1][::-1], (surface.n_vertices, 1)),
                                                          np.full(surface.n_vertices, 255)]) for index, surface in enumerate(surfaces)])
        figures.append(("The model from above", f"Left: combined uncertainty (UL1-UL4, root sum of squares), dark = "
                        f"certain, yellow = {1000 * vmax:.1f} mm or more. Right: one colour per surface.",
                        _png(image_panel([by_uncertainty, by_surface], ["uncertainty", "surfaces"], columns=2, scale=1))))
        planar = [surface for surface in surfaces if np.isfinite(surface.plane).all() and surface.n_faces]
        if planar:
            from rangesurf.lod import _plane_frame, prepare_levels

            largest = max(planar, key=lambda surface: surface.n_vertices)
            largest = prepare_levels(largest.__class__(largest.vertices, largest.faces, largest.normals, largest.pixels,
                                                       plane=largest.plane, uncertainty=dict(largest.uncertainty)))
            shown = [largest.levels[k] for k in np.unique(np.linspace(0, len(largest.levels) - 1, 4).round().astype(int))]
            xy, _, _ = _plane_frame(largest)
            figures.append(("Levels of detail", "The largest surface from fine to coarse (thesis Figure 3.8); the "
                            "error is the largest height error a removal introduced (UL4).",
                            _png(lod_figure(xy, shown, largest.lod_order, size=(260, 260)))))
    if rows:
        frame_index = np.array([row["frame"] for row in rows], np.float64)
        series = {stage: (frame_index, np.array([row[stage] for row in rows])) for stage in STAGES if stage != "deferred"}
        series["total"] = (frame_index, np.array([row["total"] for row in rows]))
        budget = None
        if metrics.get("sensor_frame_period_ms"):
            budget = (metrics["sensor_frame_period_ms"], "frame period")
        figures.append(("Time per stage", "Milliseconds per frame and stage over the run, one core.",
                        _png(line_chart(series, x_label="frame", y_label="ms", hline=budget))))
    if len(poses):
        paths = {"tracked": (poses[:, 0, 3], poses[:, 1, 3])}
        truth_poses = [pose for pose in truths if pose is not None]
        if len(truth_poses) == len(poses):
            reference = np.asarray(truth_poses)
            paths["ground truth"] = (reference[:, 0, 3], reference[:, 1, 3])
        figures.append(("Trajectory", "Sensor positions from above (metres).",
                        _png(line_chart(paths, size=(420, 700), x_label="x (m)", y_label="y (m)", equal_axes=True))))

    def table(entries: dict) -> str:
        cells = "".join(f"<tr><th>{html.escape(str(key))}</th><td>{html.escape(_format(value))}</td></tr>" for key, value in entries.items())
        return f"<table>{cells}</table>"

    summary = {key: value for key, value in metrics.items() if not isinstance(value, (dict, list))}
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>rangesurf run</title>",
             "<style>body{font-family:sans-serif;max-width:1000px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse;margin:0.5em 0 1.5em}th,td{border:1px solid #ccc;padding:3px 8px;text-align:left}"
             "th{background:#f4f4f4;font-weight:normal}img{max-width:100%;border:1px solid #ddd}</style></head><body>",
             "<h1>rangesurf run</h1>", "<h2>Summary</h2>", table(summary)]
    for key in ("stage_ms_median", "accuracy"):
        if metrics.get(key):
            parts += [f"<h3>{html.escape(key.replace('_', ' '))}</h3>", table(metrics[key])]
    if metrics.get("uncertainty_m"):
        parts += ["<h3>uncertainty (metres along the normal)</h3>",
                  table({level: f"median {stats['median']:.4f}, p95 {stats['p95']:.4f}" for level, stats in metrics["uncertainty_m"].items()})]
    if metrics.get("skipped"):
        parts += ["<h3>skipped inputs</h3>", table({item["source"]: item["error"] for item in metrics["skipped"]})]
    for title, caption, image in figures:
        parts += [f"<h2>{html.escape(title)}</h2>", f"<p>{html.escape(caption)}</p>", f"<img alt='{html.escape(title)}' src='{image}'>"]
    parts.append("</body></html>")
    return "\n".join(parts)


def _format(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)
