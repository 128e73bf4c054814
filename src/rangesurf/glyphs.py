"""Uncertainty as colour and geometry (thesis Sections 2.4 and 3.4).

Every function is pure: it takes a `rangesurf.mesh.Surface` whose
``uncertainty`` holds per-vertex standard deviations in metres along the
normal (levels ``"UL1"`` sensor, ``"UL2"`` patch fit, ``"UL3"`` registration
and merging, ``"UL4"`` level of detail) and returns arrays to draw: colours,
opacities, or a `Glyphs` bundle of points, line segments or a triangle mesh
with RGBA colours. Any subset of the levels can be shown, **cumulatively**
(one quantity: the root sum of squares of the chosen levels, as independent
errors add) or **separately** (one colour per level, `LEVEL_COLOURS`).

* attribute mapping: `hue_colours` (warmer = less certain), `opacity`
  (less certain = more transparent, down to a floor);
* added geometry: `displaced_points` (thesis Eq. 2.7), `bars` along the
  normals (stacked per level), `shells` (the two boundary meshes at
  +-``scale`` sigma), `uncertainty_volume` (the closed solid between them),
  `cones` (width from one level, height from another, Figure 3.12);
* the thesis's further proposals: `perturbed` (a surface made rough in
  proportion to its uncertainty) and `oscillating` (the vertices moved
  between the two shells over time).

``scale`` is in standard deviations: 2 draws the band that should hold 95 %
of the true surface when the levels are calibrated (`rangesurf.uncertainty`).

References
----------
.. [1] The reference thesis, Sections 2.4 and 3.4, Eq. 2.7 and Figures
   2.16-2.19, 3.10-3.13 (``shared/reference/thesis.md``).
.. [2] C. M. Wittenbrink, "Glyphs for visualizing uncertainty in vector
   fields", IEEE TVCG 2(3), 1996.
.. [3] A. Pang, C. M. Wittenbrink and S. K. Lodha, "Approaches to
   uncertainty visualization", The Visual Computer 13(8), 1997 (glyphs, fat
   surfaces, perturbation, oscillation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from rangesurf.mesh import UNCERTAINTY_LEVELS, Surface, boundary_loops

__all__ = [
    "Glyphs", "LEVEL_COLOURS", "combined_uncertainty", "level_values", "hue_colours", "opacity", "displaced_points",
    "bars", "shells", "uncertainty_volume", "cones", "perturbed", "oscillating",
]

# One RGBA colour per level for separate display (colour-blind-safe Okabe-Ito hues).
LEVEL_COLOURS = {
    "UL1": (0, 114, 178, 255),    # blue: sensor
    "UL2": (0, 158, 115, 255),    # green: patch fit
    "UL3": (230, 159, 0, 255),    # orange: registration and merging
    "UL4": (204, 121, 167, 255),  # purple: level of detail
}
_SHELL_ALPHA = 90
_JIT = dict(cache=True, nogil=True, error_model="numpy")


@dataclass(frozen=True)
class Glyphs:
    """Geometry to draw: points, line segments and/or a triangle mesh, with RGBA colours.

    Parameters
    ----------
    points : (K, 3) float32 or None
    segments : (K, 2, 3) float32 or None
        Line segments (start, end).
    vertices : (V, 3) float32 or None
    faces : (F, 3) int32 or None
        Triangles over ``vertices``, counter-clockwise seen from outside.
    colours : (K, 4) or (V, 4) uint8
        One RGBA colour per point, segment or vertex.
    """

    points: np.ndarray | None = None
    segments: np.ndarray | None = None
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    colours: np.ndarray | None = None


# --------------------------------------------------------------------------
# Values and attribute mapping.
# --------------------------------------------------------------------------


def level_values(surface: Surface, levels: tuple[str, ...] = UNCERTAINTY_LEVELS) -> np.ndarray:
    """(N, L) float64 standard deviations (metres) of the chosen levels; 0 where a level is absent or NaN."""
    for level in levels:
        if level not in UNCERTAINTY_LEVELS:
            raise ValueError(f"uncertainty levels are {UNCERTAINTY_LEVELS}, got {level!r}")
    columns = [np.nan_to_num(surface.uncertainty[level].astype(np.float64)) if level in surface.uncertainty
               else np.zeros(surface.n_vertices) for level in levels]
    return np.column_stack(columns) if columns else np.zeros((surface.n_vertices, 0))


def combined_uncertainty(surface: Surface, levels: tuple[str, ...] = UNCERTAINTY_LEVELS) -> np.ndarray:
    """Per-vertex root sum of squares of the chosen levels (metres); NaN where none of them is present."""
    for level in levels:
        if level not in UNCERTAINTY_LEVELS:
            raise ValueError(f"uncertainty levels are {UNCERTAINTY_LEVELS}, got {level!r}")
    present = [level for level in levels if level in surface.uncertainty]
    if not present:
        return np.full(surface.n_vertices, np.nan)
    return np.sqrt((level_values(surface, tuple(present)) ** 2).sum(axis=1))


def hue_colours(values: np.ndarray, *, vmax: float, vmin: float = 0.0) -> np.ndarray:
    """RGBA uint8 colours: dark purple (certain) through red to yellow (uncertain); NaN grey.

    Examples
    --------
    >>> hue_colours(np.array([0.0, 0.01, np.nan]), vmax=0.01)[:, :3].tolist()
    [[0, 0, 4], [252, 255, 164], [128, 128, 128]]
    """
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if values.size == 0:
        return np.zeros((0, 4), np.uint8)
    span = max(vmax - vmin, 1e-12)
    scaled = np.clip((np.nan_to_num(values, nan=vmin) - vmin) / span, 0.0, 1.0)
    # OpenCV's inferno map (perceptually uniform), applied to a 1-D "image" of the values.
    bgr = cv2.applyColorMap(np.round(scaled * 255).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_INFERNO).reshape(-1, 3)
    colours = np.empty((len(values), 4), np.uint8)
    colours[:, :3] = bgr[:, ::-1]
    colours[:, 3] = 255
    colours[~np.isfinite(values), :3] = 128
    return colours


def opacity(values: np.ndarray, *, vmax: float, floor: float = 0.2) -> np.ndarray:
    """Opacity in [floor, 1]: certain vertices opaque, the least certain (``>= vmax``) at ``floor``; NaN opaque.

    Examples
    --------
    >>> opacity(np.array([0.0, 0.005, 0.02]), vmax=0.01, floor=0.2).round(2).tolist()
    [1.0, 0.6, 0.2]
    """
    if not 0.0 <= floor <= 1.0:
        raise ValueError(f"floor must be in [0, 1], got {floor}")
    scaled = np.clip(np.nan_to_num(np.asarray(values, np.float64), nan=0.0) / max(vmax, 1e-12), 0.0, 1.0)
    return 1.0 - (1.0 - floor) * scaled


def _check_scale(scale: float) -> float:
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be > 0 (standard deviations), got {scale}")
    return float(scale)


def _unit_normals(surface: Surface) -> np.ndarray:
    normals = surface.normals.astype(np.float64)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def _reference(values: np.ndarray) -> float:
    """The 95th percentile of the positive values: what the colour and falloff scales are relative to."""
    positive = values[values > 0]
    return float(np.percentile(positive, 95)) if positive.size else 1.0


# --------------------------------------------------------------------------
# Added geometry.
# --------------------------------------------------------------------------


def displaced_points(surface: Surface, levels: tuple[str, ...] = UNCERTAINTY_LEVELS, *, scale: float = 2.0,
                     falloff: float = 1.0, random: bool = True, seed: int = 0, mode: str = "cumulative") -> Glyphs:
    """Points on both sides of every vertex along its normal (thesis Algorithm 1, Eq. 2.7).

    ``displacement = rand() * u**falloff * scale``, with ``u`` the vertex's
    uncertainty taken relative to the surface's 95th percentile (so that the
    falloff bends the scale without changing its units) and ``rand()``
    uniform in [0, 1] (``random=False``: 1, the points then trace the band's
    edges).

    Parameters
    ----------
    mode : {"cumulative", "separate"}
        One pair of points per vertex for the combined levels, coloured by
        hue; or one pair per level in that level's colour.

    Returns
    -------
    Glyphs
        ``points`` (2 N or 2 N L) and ``colours``.
    """
    scale = _check_scale(scale)
    if mode not in ("cumulative", "separate"):
        raise ValueError(f"mode must be 'cumulative' or 'separate', got {mode!r}")
    values = level_values(surface, levels)
    amounts = np.sqrt((values**2).sum(axis=1, keepdims=True)) if mode == "cumulative" else values
    reference = _reference(amounts)
    shaped = reference * (amounts / reference) ** falloff
    rng = np.random.default_rng(seed)
    factor = rng.uniform(0.0, 1.0, (2,) + shaped.shape) if random else np.ones((2,) + shaped.shape)
    # (side, vertex, level) -> points on the + side, then the - side.
    offsets = np.stack([factor[0] * shaped, -factor[1] * shaped]) * scale
    points = _along_normals(surface.vertices, _unit_normals(surface), offsets)
    if mode == "cumulative":
        colours = hue_colours(amounts[:, 0], vmax=reference)
        colours = np.concatenate([colours, colours])
    else:
        colours = np.tile(np.array([LEVEL_COLOURS[level] for level in levels], np.uint8), (2 * surface.n_vertices, 1))
    return Glyphs(points=points.reshape(-1, 3), colours=colours)


def bars(surface: Surface, levels: tuple[str, ...] = UNCERTAINTY_LEVELS, *, scale: float = 2.0,
         mode: str = "stacked") -> Glyphs:
    """Line segments along each vertex normal, on both sides, in one colour per level (thesis Figure 2.16).

    ``"stacked"``: the levels follow one another outwards, the k-th from the
    sum of the earlier ones' lengths (``scale`` sigma each); the bar's total
    length shows all of them. ``"separate"``: every level's bar starts at
    the surface.

    Returns
    -------
    Glyphs
        ``segments`` (2 N L, 2, 3) and ``colours``.
    """
    scale = _check_scale(scale)
    if mode not in ("stacked", "separate"):
        raise ValueError(f"mode must be 'stacked' or 'separate', got {mode!r}")
    lengths = level_values(surface, levels) * scale
    ends = np.cumsum(lengths, axis=1) if mode == "stacked" else lengths
    starts = ends - lengths if mode == "stacked" else np.zeros_like(lengths)
    # (side, vertex, level and end): each bar from its start to its end, on the + side, then the - side.
    distances = np.stack([starts, ends], axis=-1).reshape(surface.n_vertices, -1)
    segments = _along_normals(surface.vertices, _unit_normals(surface), np.stack([distances, -distances]))
    colours = np.tile(np.array([LEVEL_COLOURS[level] for level in levels], np.uint8), (2 * surface.n_vertices, 1))
    return Glyphs(segments=segments.reshape(-1, 2, 3), colours=colours)


@numba.njit(**_JIT)
def _along_normals(vertices, normals, distances):  # pragma: no cover - compiled
    """(A, N, B, 3) float32: vertex i moved ``distances[a, i, b]`` along its normal.

    One pass writing float32, what the viewer takes: NumPy's broadcast over the three coordinates (inner loops
    three values long) in float64 temporaries took 100,000 vertices' stacked bars 118 ms, the separate displaced
    points 68, where the target for any method is well under 100 (this machine; in place, in float32, 67 and 50).
    """
    sides, count, inner = distances.shape
    points = np.empty((sides, count, inner, 3), np.float32)
    for a in range(sides):
        for i in range(count):
            for b in range(inner):
                for axis in range(3):
                    points[a, i, b, axis] = vertices[i, axis] + distances[a, i, b] * normals[i, axis]
    return points


def shells(surface: Surface, levels: tuple[str, ...] = UNCERTAINTY_LEVELS, *, scale: float = 2.0) -> tuple[Glyphs, Glyphs]:
    """The two uncertainty boundary meshes, at +``scale`` and -``scale`` sigma along the normals (semi-transparent).

    Returns
    -------
    (outer, inner) : Glyphs
        Meshes with the surface's triangles (the inner one's reversed, so
        both face away from the surface), coloured by hue with alpha.
    """
    scale = _check_scale(scale)
    sigma = np.sqrt((level_values(surface, levels) ** 2).sum(axis=1))
    offset = scale * sigma[:, None] * _unit_normals(surface)
    vertices = surface.vertices.astype(np.float64)
    colours = hue_colours(sigma, vmax=_reference(sigma))
    colours[:, 3] = _SHELL_ALPHA
    faces = surface.faces.astype(np.int32)
    outer = Glyphs(vertices=(vertices + offset).astype(np.float32), faces=faces, colours=colours)
    inner = Glyphs(vertices=(vertices - offset).astype(np.float32), faces=faces[:, ::-1].copy(), colours=colours.copy())
    return outer, inner


def uncertainty_volume(surface: Surface, levels: tuple[str, ...] = UNCERTAINTY_LEVELS, *, scale: float = 2.0) -> Glyphs:
    """The closed solid between the two shells ("fat surface"): both shells joined along the outline and holes.

    For a surface whose outline is a set of simple loops the result is
    watertight; its volume is the surface's area times ``2 * scale`` sigma
    (for constant sigma).
    """
    outer, inner = shells(surface, levels, scale=scale)
    count = surface.n_vertices
    walls = []
    for loop in boundary_loops(surface.faces):
        following = np.roll(loop, -1)
        # Each boundary edge a -> b (winding of the outer faces) becomes the quad a, b, b', a'
        # (primes on the inner shell), split in two, facing outwards.
        walls.append(np.column_stack([following, loop, loop + count]))
        walls.append(np.column_stack([following, loop + count, following + count]))
    faces = np.concatenate([outer.faces, inner.faces + count, *walls]).astype(np.int32)
    colours = np.concatenate([outer.colours, inner.colours])
    return Glyphs(vertices=np.concatenate([outer.vertices, inner.vertices]), faces=faces, colours=colours)


def cones(surface: Surface, width_level: str = "UL1", height_level: str = "UL4", *, scale: float = 2.0,
          max_glyphs: int = 2000, sides: int = 8) -> Glyphs:
    """Cone glyphs carrying two levels at once (thesis Figure 3.12, bottom): base radius from one, height from the other.

    At most ``max_glyphs`` vertices carry a cone: the most important ones
    (the surface's LOD order), so that glyphs thin out with the mesh. Each
    cone stands on its vertex, apex along the normal at ``scale`` sigma of
    ``height_level``, base radius ``scale`` sigma of ``width_level``;
    coloured by hue of the height level.
    """
    scale = _check_scale(scale)
    if sides < 3:
        raise ValueError(f"cones need at least 3 sides, got {sides}")
    chosen = surface.lod_order[: max(0, int(max_glyphs))]
    values = level_values(surface, (width_level, height_level))[chosen]
    radius, height = scale * values[:, 0], scale * values[:, 1]
    normals = _unit_normals(surface)[chosen]
    base = surface.vertices.astype(np.float64)[chosen]
    # Two unit vectors across each normal.
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    across = np.cross(normals, helper)
    across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-12)
    other = np.cross(normals, across)
    angles = 2 * np.pi * np.arange(sides) / sides
    rim = base[:, None, :] + radius[:, None, None] * (np.cos(angles)[None, :, None] * across[:, None, :]
                                                       + np.sin(angles)[None, :, None] * other[:, None, :])
    apex = base + height[:, None] * normals
    # Per cone: rim vertices 0..sides-1, apex, base centre.
    vertices = np.concatenate([rim, apex[:, None, :], base[:, None, :]], axis=1)
    stride = sides + 2
    k = np.arange(sides)
    side_faces = np.column_stack([k, (k + 1) % sides, np.full(sides, sides)])
    base_faces = np.column_stack([(k + 1) % sides, k, np.full(sides, sides + 1)])
    template = np.concatenate([side_faces, base_faces])
    faces = (template[None, :, :] + stride * np.arange(len(chosen))[:, None, None]).reshape(-1, 3)
    colours = np.repeat(hue_colours(values[:, 1], vmax=_reference(values[:, 1])), stride, axis=0)
    return Glyphs(vertices=vertices.reshape(-1, 3).astype(np.float32), faces=faces.astype(np.int32), colours=colours)


def perturbed(surface: Surface, levels: tuple[str, ...] = UNCERTAINTY_LEVELS, *, scale: float = 1.0, seed: int = 0) -> Glyphs:
    """The surface made rough in proportion to its uncertainty: each vertex moved along its normal by
    ``scale * sigma`` times a standard normal draw (thesis Figure 2.13, left)."""
    scale = _check_scale(scale)
    sigma = np.sqrt((level_values(surface, levels) ** 2).sum(axis=1))
    noise = np.random.default_rng(seed).standard_normal(surface.n_vertices)
    vertices = surface.vertices.astype(np.float64) + (scale * sigma * noise)[:, None] * _unit_normals(surface)
    return Glyphs(vertices=vertices.astype(np.float32), faces=surface.faces.astype(np.int32),
                  colours=hue_colours(sigma, vmax=_reference(sigma)))


def oscillating(surface: Surface, levels: tuple[str, ...] = UNCERTAINTY_LEVELS, phase: float = 0.0, *,
                scale: float = 2.0) -> Glyphs:
    """The surface at one moment of an oscillation between the two shells: vertices at
    ``sin(2 pi phase) * scale * sigma`` along the normal (animate ``phase`` over time)."""
    scale = _check_scale(scale)
    sigma = np.sqrt((level_values(surface, levels) ** 2).sum(axis=1))
    offset = math.sin(2 * math.pi * phase) * scale * sigma
    vertices = surface.vertices.astype(np.float64) + offset[:, None] * _unit_normals(surface)
    return Glyphs(vertices=vertices.astype(np.float32), faces=surface.faces.astype(np.int32),
                  colours=hue_colours(sigma, vmax=_reference(sigma)))
