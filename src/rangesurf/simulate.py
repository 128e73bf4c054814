"""Synthetic range scenes and sensor noise, with exact ground truth.

A `Scene` is a set of planar convex polygons and finite vertical cylinders in
a world frame with z up (metres). `simulate_frame` casts every viewing ray of
a `SensorModel` into the scene and corrupts the true ranges the way range
sensors do (thesis Section 2.1):

* noise along the line of sight, growing with range and on dark surfaces, and
  asymmetric along it (a zero-mean split normal, `RangeNoiseModel`);
* mixed ("flying") pixels, whose footprint straddles a depth discontinuity and
  which report an amplitude-weighted mix of foreground and background;
* salt-and-pepper outliers (spurious readings, e.g. from ambient infrared);
* the cut-off: past ``max_range`` a time-of-flight camera reports the cut-off
  value itself, other sensors report nothing.

Each frame comes with a `GroundTruth`: true range, surface labels, normals,
the plane of every planar surface in the sensor frame, and masks of the
corrupted pixels, so every pipeline stage can be scored.

References
----------
.. [1] R. Lange and P. Seitz, "Solid-state time-of-flight range camera",
   IEEE Journal of Quantum Electronics 37(3), 390-397, 2001 (amplitude and
   shot-noise-limited range noise).
.. [2] M. Hebert and E. Krotkov, "3D measurements from imaging laser radars:
   how good are they?", Image and Vision Computing 10(3), 170-178, 1992
   (mixed pixels at depth discontinuities).
.. [3] The reference thesis, Section 2.1 (``shared/reference/thesis.md``).

Examples
--------
>>> import rangesurf as rs
>>> frames, truth = rs.simulate.simulate_sequence("arena", "sr3000", n_frames=2, seed=1)
>>> frames[0].shape, truth[0].planes.shape[1]
((144, 176), 4)
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from rangesurf.frame import RangeFrame, SensorModel, check_rigid_transform, get_sensor
from rangesurf.io._common import FormatError, atomic_path

__all__ = [
    "Polygon",
    "Cylinder",
    "TrajectorySpec",
    "Scene",
    "arena_scene",
    "corridor_scene",
    "SCENES",
    "get_scene",
    "look_at",
    "default_trajectory",
    "noisy_odometry",
    "iter_sequence",
    "ray_cast",
    "SimulationNoise",
    "GroundTruth",
    "simulate_frame",
    "simulate_sequence",
    "save_ground_truth",
    "load_ground_truth",
]

# A ray point counts as inside a polygon up to this distance outside its edges
# (metres), so that neighbouring polygons sharing an edge leave no gap.
_EDGE_TOLERANCE = 1e-9
# Hits closer than this to the ray origin are ignored (metres).
_MIN_HIT_DISTANCE = 1e-9
_PLANARITY_TOLERANCE = 1e-6
_GROUND_TRUTH_FORMAT_VERSION = 1


# --------------------------------------------------------------------------
# Scene geometry.
# --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Polygon:
    """A planar convex polygon, one piece of a surface.

    Parameters
    ----------
    surface_id : int
        Surface label, >= 1. Several coplanar polygons may share one label
        (a wall with a door opening is three pieces of one surface).
    vertices : (K, 3) array
        Corners in world coordinates (metres), K >= 3, in order around the
        polygon. The plane normal follows the right-hand rule over that
        order; its sign carries no meaning for the simulation.
    albedo : float
        Diffuse reflectance in [0, 1].
    label : str
        Human-readable name (``"dark box top"``), for messages.

    Attributes
    ----------
    normal : (3,) float64
        Unit plane normal ``n``.
    offset : float
        Plane offset ``d``: ``n . x + d = 0`` for points ``x`` of the plane.

    Raises
    ------
    ValueError
        If the vertices are not finite, not planar, not convex, or enclose no
        area, or if the id or albedo is out of range.
    """

    surface_id: int
    vertices: np.ndarray
    albedo: float = 0.5
    label: str = ""
    normal: np.ndarray = field(init=False, repr=False)
    offset: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        name = f"polygon {self.label or self.surface_id!r}"
        _check_surface_id(self.surface_id, name)
        _check_albedo(self.albedo, name)
        vertices = np.array(self.vertices, dtype=np.float64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
            raise ValueError(f"{name}: vertices must have shape (K >= 3, 3), got {vertices.shape}")
        if not np.all(np.isfinite(vertices)):
            raise ValueError(f"{name}: vertices contain NaN or Inf")
        # Newell's method: the area-weighted normal, robust for any vertex order.
        following = np.roll(vertices, -1, axis=0)
        area_normal = 0.5 * np.cross(vertices, following).sum(axis=0)
        area = float(np.linalg.norm(area_normal))
        if area < 1e-12:
            raise ValueError(f"{name}: vertices enclose no area")
        normal = area_normal / area
        offset = -float(np.mean(vertices @ normal))
        off_plane = np.abs(vertices @ normal + offset).max()
        if off_plane > _PLANARITY_TOLERANCE:
            raise ValueError(f"{name}: vertices are not planar (a corner lies {off_plane:.3g} m off the plane)")
        edges = following - vertices
        turns = np.cross(edges, np.roll(edges, -1, axis=0)) @ normal
        if np.any(turns < -1e-12):
            raise ValueError(f"{name}: polygon is not convex; split it into convex pieces")
        vertices.setflags(write=False)
        normal.setflags(write=False)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "normal", normal)
        object.__setattr__(self, "offset", offset)

    @property
    def plane(self) -> np.ndarray:
        """``(4,)`` float64 ``(nx, ny, nz, d)`` in world coordinates."""
        return np.append(self.normal, self.offset)


@dataclass(frozen=True)
class Cylinder:
    """A finite vertical cylinder (an open tube: no caps), e.g. a pillar.

    Parameters
    ----------
    surface_id : int
        Surface label, >= 1, not shared with any other primitive.
    center : (float, float)
        Axis position ``(x, y)`` in world coordinates (metres).
    radius : float
        Metres, > 0.
    z_min, z_max : float
        Vertical extent (metres), ``z_min < z_max``.
    albedo : float
        Diffuse reflectance in [0, 1].
    label : str
        Human-readable name.
    """

    surface_id: int
    center: tuple[float, float]
    radius: float
    z_min: float
    z_max: float
    albedo: float = 0.5
    label: str = ""

    def __post_init__(self) -> None:
        name = f"cylinder {self.label or self.surface_id!r}"
        _check_surface_id(self.surface_id, name)
        _check_albedo(self.albedo, name)
        center = tuple(float(c) for c in self.center)
        if len(center) != 2 or not all(math.isfinite(c) for c in center):
            raise ValueError(f"{name}: center must be two finite numbers (x, y), got {self.center!r}")
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"{name}: radius must be > 0, got {self.radius}")
        if not (math.isfinite(self.z_min) and math.isfinite(self.z_max) and self.z_min < self.z_max):
            raise ValueError(f"{name}: need finite z_min < z_max, got {self.z_min}, {self.z_max}")
        object.__setattr__(self, "center", center)


@dataclass(frozen=True)
class TrajectorySpec:
    """How a robot drives through a scene (see `default_trajectory`).

    Parameters
    ----------
    waypoints : sequence of (x, y)
        A closed loop in free space (world metres), driven in the given order
        along a periodic cubic spline through the points.
    sensor_height : float
        Height of the sensor above the floor (metres).
    speed : float
        Driving speed (m/s).
    pitch_deg : float
        Downward tilt of the sensor's boresight (degrees).
    yaw_offset_deg : float
        Angle between the driving direction and the boresight, positive to
        the left (degrees), e.g. to look into the middle of a room.
    yaw_sway_deg, sway_wavelength : float
        The boresight sways left and right by ``yaw_sway_deg`` once every
        ``sway_wavelength`` metres driven.
    max_step : float
        Largest distance driven between two frames (metres): slow scanners
        (the swept laser takes 10 s per scan) are assumed to scan stop-and-go.
    """

    waypoints: tuple[tuple[float, float], ...]
    sensor_height: float = 0.6
    speed: float = 0.3
    pitch_deg: float = 10.0
    yaw_offset_deg: float = 0.0
    yaw_sway_deg: float = 10.0
    sway_wavelength: float = 2.5
    max_step: float = 1.0

    def __post_init__(self) -> None:
        waypoints = np.asarray(self.waypoints, dtype=np.float64)
        if waypoints.ndim != 2 or waypoints.shape[1] != 2 or len(waypoints) < 3:
            raise ValueError(f"trajectory waypoints must have shape (K >= 3, 2), got {waypoints.shape}")
        if not np.all(np.isfinite(waypoints)):
            raise ValueError("trajectory waypoints contain NaN or Inf")
        if np.any(np.linalg.norm(waypoints - np.roll(waypoints, -1, axis=0), axis=1) < 1e-9):
            raise ValueError("trajectory waypoints must not repeat consecutively")
        for name in ("sensor_height", "speed", "sway_wavelength", "max_step"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"trajectory {name} must be > 0, got {value}")
        object.__setattr__(self, "waypoints", tuple(tuple(map(float, p)) for p in waypoints))

    @functools.cached_property
    def _path(self) -> tuple[CubicSpline, np.ndarray, np.ndarray]:
        """The loop spline and a table from arc length to spline parameter."""
        points = np.asarray(self.waypoints)
        closed = np.vstack([points, points[:1]])
        chords = np.linalg.norm(np.diff(closed, axis=0), axis=1)
        knots = np.concatenate([[0.0], np.cumsum(chords)])
        spline = CubicSpline(knots, closed, bc_type="periodic")
        parameter = np.linspace(0.0, knots[-1], 64 * len(points) + 1)
        speeds = np.linalg.norm(spline(parameter, 1), axis=1)
        # Trapezoid rule: the arc length at every table entry.
        arc = np.concatenate([[0.0], np.cumsum(0.5 * (speeds[1:] + speeds[:-1]) * np.diff(parameter))])
        return spline, arc, parameter

    @property
    def lap_length(self) -> float:
        """Length of one lap of the loop (metres)."""
        return float(self._path[1][-1])

    def at(self, distance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position ``(N, 2)`` and heading ``(N,)`` (radians) after driving ``distance`` metres."""
        spline, arc, parameter = self._path
        distance = np.mod(np.asarray(distance, dtype=np.float64), arc[-1])
        u = np.interp(distance, arc, parameter)
        tangent = spline(u, 1)
        return spline(u), np.arctan2(tangent[:, 1], tangent[:, 0])


@dataclass(frozen=True, eq=False)
class Scene:
    """A static scene of planar convex polygons and vertical cylinders.

    Parameters
    ----------
    name : str
        Short name (``"arena"``), used in frame sources.
    polygons : sequence of Polygon
    cylinders : sequence of Cylinder
    trajectory : TrajectorySpec
        The path `default_trajectory` drives.

    Raises
    ------
    ValueError
        If polygons sharing a surface id are not coplanar, a cylinder shares
        its id, or the scene is empty.
    """

    name: str
    polygons: tuple[Polygon, ...]
    cylinders: tuple[Cylinder, ...] = ()
    trajectory: TrajectorySpec | None = None

    def __post_init__(self) -> None:
        polygons, cylinders = tuple(self.polygons), tuple(self.cylinders)
        if not polygons and not cylinders:
            raise ValueError(f"scene {self.name!r} has no geometry")
        if not all(isinstance(p, Polygon) for p in polygons):
            raise ValueError(f"scene {self.name!r}: polygons must be Polygon objects")
        if not all(isinstance(c, Cylinder) for c in cylinders):
            raise ValueError(f"scene {self.name!r}: cylinders must be Cylinder objects")
        planes: dict[int, np.ndarray] = {}
        for polygon in polygons:
            first = planes.setdefault(polygon.surface_id, polygon.plane)
            sign = 1.0 if first[:3] @ polygon.normal > 0 else -1.0
            if np.abs(first - sign * polygon.plane).max() > _PLANARITY_TOLERANCE:
                raise ValueError(
                    f"scene {self.name!r}: polygons sharing surface id {polygon.surface_id} are not coplanar"
                    f" ({polygon.label or 'unnamed'})"
                )
        for cylinder in cylinders:
            if cylinder.surface_id in planes:
                raise ValueError(f"scene {self.name!r}: cylinder id {cylinder.surface_id} is already used")
            planes[cylinder.surface_id] = np.full(4, np.nan)
        object.__setattr__(self, "polygons", polygons)
        object.__setattr__(self, "cylinders", cylinders)

    @property
    def n_surfaces(self) -> int:
        """The largest surface id (ground-truth tables have this many rows + 1)."""
        return max(p.surface_id for p in (*self.polygons, *self.cylinders))

    @functools.cached_property
    def planes(self) -> np.ndarray:
        """``(S + 1, 4)`` float64 world planes ``(n, d)`` by surface id; NaN rows for id 0, cylinders and unused ids."""
        table = np.full((self.n_surfaces + 1, 4), np.nan)
        for polygon in self.polygons:
            if np.isnan(table[polygon.surface_id, 0]):
                table[polygon.surface_id] = polygon.plane
        table.setflags(write=False)
        return table

    @functools.cached_property
    def _packed(self) -> _PackedScene:
        return _PackedScene.from_scene(self)


@dataclass(frozen=True, eq=False)
class _PackedScene:
    """The scene as flat arrays for the ray-casting kernel.

    Primitive ``k < P`` is polygon ``k``; ``P + c`` is cylinder ``c``.
    """

    plane_normals: np.ndarray  # (P, 3)
    plane_offsets: np.ndarray  # (P,)
    edge_normals: np.ndarray  # (P, E, 3) unit, pointing into the polygon
    edge_offsets: np.ndarray  # (P, E)
    edge_counts: np.ndarray  # (P,) int64
    cylinders: np.ndarray  # (C, 5): x, y, radius, z_min, z_max
    surface_ids: np.ndarray  # (P + C,) int32
    albedo: np.ndarray  # (P + C,) float64

    @classmethod
    def from_scene(cls, scene: Scene) -> _PackedScene:
        n_polygons = len(scene.polygons)
        max_edges = max((len(p.vertices) for p in scene.polygons), default=1)
        edge_normals = np.zeros((n_polygons, max_edges, 3))
        edge_offsets = np.zeros((n_polygons, max_edges))
        edge_counts = np.zeros(n_polygons, np.int64)
        for k, polygon in enumerate(scene.polygons):
            vertices = polygon.vertices
            edges = np.roll(vertices, -1, axis=0) - vertices
            # n x edge points into a polygon whose corners run counter-clockwise about n.
            inward = np.cross(polygon.normal, edges)
            lengths = np.linalg.norm(inward, axis=1)
            keep = lengths > 1e-12
            inward = inward[keep] / lengths[keep, None]
            edge_counts[k] = len(inward)
            edge_normals[k, : len(inward)] = inward
            edge_offsets[k, : len(inward)] = np.einsum("ij,ij->i", inward, vertices[keep])
        cylinders = np.array(
            [[*c.center, c.radius, c.z_min, c.z_max] for c in scene.cylinders], dtype=np.float64
        ).reshape(-1, 5)
        primitives = (*scene.polygons, *scene.cylinders)
        return cls(
            plane_normals=np.array([p.normal for p in scene.polygons], dtype=np.float64).reshape(-1, 3),
            plane_offsets=np.array([p.offset for p in scene.polygons], dtype=np.float64),
            edge_normals=edge_normals,
            edge_offsets=edge_offsets,
            edge_counts=edge_counts,
            cylinders=cylinders,
            surface_ids=np.array([p.surface_id for p in primitives], dtype=np.int32),
            albedo=np.array([p.albedo for p in primitives], dtype=np.float64),
        )


def _check_surface_id(surface_id: Any, name: str) -> None:
    if isinstance(surface_id, bool) or not isinstance(surface_id, (int, np.integer)) or surface_id < 1:
        raise ValueError(f"{name}: surface_id must be an integer >= 1, got {surface_id!r}")


def _check_albedo(albedo: float, name: str) -> None:
    if not (math.isfinite(albedo) and 0.0 <= albedo <= 1.0):
        raise ValueError(f"{name}: albedo must lie in [0, 1], got {albedo}")


# --------------------------------------------------------------------------
# Built-in scenes.
# --------------------------------------------------------------------------


class _SceneBuilder:
    """Collects primitives and hands out consecutive surface ids."""

    def __init__(self) -> None:
        self.polygons: list[Polygon] = []
        self.cylinders: list[Cylinder] = []
        self._next_id = 1

    def new_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    def polygon(self, vertices, albedo: float, label: str, surface_id: int | None = None) -> int:
        surface_id = self.new_id() if surface_id is None else surface_id
        self.polygons.append(Polygon(surface_id, np.asarray(vertices, dtype=np.float64), albedo, label))
        return surface_id

    def vertical_rectangle(self, start, end, z_min, z_max, albedo, label, surface_id=None) -> int:
        """A vertical rectangle over the floor segment ``start``-``end`` (x, y)."""
        (x0, y0), (x1, y1) = start, end
        corners = [(x0, y0, z_min), (x1, y1, z_min), (x1, y1, z_max), (x0, y0, z_max)]
        return self.polygon(corners, albedo, label, surface_id)

    def horizontal_rectangle(self, x_min, x_max, y_min, y_max, z, albedo, label, surface_id=None) -> int:
        corners = [(x_min, y_min, z), (x_max, y_min, z), (x_max, y_max, z), (x_min, y_max, z)]
        return self.polygon(corners, albedo, label, surface_id)

    def box(self, x_min, x_max, y_min, y_max, height, albedo, label) -> None:
        """A box standing on the floor: top and four sides, each its own surface."""
        self.horizontal_rectangle(x_min, x_max, y_min, y_max, height, albedo, f"{label} top")
        for side, start, end in (
            ("south", (x_min, y_min), (x_max, y_min)),
            ("east", (x_max, y_min), (x_max, y_max)),
            ("north", (x_max, y_max), (x_min, y_max)),
            ("west", (x_min, y_max), (x_min, y_min)),
        ):
            self.vertical_rectangle(start, end, 0.0, height, albedo, f"{label} {side}")

    def cylinder(self, center, radius, z_min, z_max, albedo, label) -> int:
        surface_id = self.new_id()
        self.cylinders.append(Cylinder(surface_id, center, radius, z_min, z_max, albedo, label))
        return surface_id

    def scene(self, name: str, trajectory: TrajectorySpec) -> Scene:
        return Scene(name, tuple(self.polygons), tuple(self.cylinders), trajectory)


def _stadium_waypoints(x_start: float, x_end: float, y_low: float, y_high: float, *, spacing: float) -> tuple:
    """A closed loop: along ``y_low`` toward +x, a half circle, back along ``y_high``, a half circle.

    Waypoints lie about ``spacing`` apart so that the spline through them
    keeps the straight runs straight.
    """
    radius, centre_y = (y_high - y_low) / 2, (y_high + y_low) / 2
    straight = np.linspace(x_start, x_end, max(2, int(round((x_end - x_start) / spacing)) + 1))[:-1]
    # The half circles get denser waypoints: a cubic spline rings where curvature jumps.
    turn = np.linspace(-np.pi / 2, np.pi / 2, max(3, int(round(np.pi * radius / (spacing / 5))) + 1))[:-1]
    points = [(x, y_low) for x in straight]
    points += [(x_end + radius * math.cos(a), centre_y + radius * math.sin(a)) for a in turn]
    points += [(x_start + x_end - x, y_high) for x in straight]
    points += [(x_start - radius * math.cos(a), centre_y - radius * math.sin(a)) for a in turn]
    return tuple((float(x), float(y)) for x, y in points)


def arena_scene() -> Scene:
    """A rescue-arena-like room, 6 m x 5 m with 2 m walls and no ceiling.

    Floor and four walls; four boxes (a bright one, a dark one of albedo 0.1,
    a grey one, a small white crate), each face its own surface; a ramp
    (inclined top, triangular sides, back); three stairs (treads, risers, back
    and stepped sides, each riser and tread its own surface); and a pillar (a
    cylinder of radius 0.15 m) in the middle. The robot circles the pillar on
    an elliptical loop, looking 25 degrees inward.

    Returns
    -------
    Scene
    """
    build = _SceneBuilder()
    width, depth, wall_height = 6.0, 5.0, 2.0
    build.horizontal_rectangle(0.0, width, 0.0, depth, 0.0, 0.35, "floor")
    corners = [(0.0, 0.0), (width, 0.0), (width, depth), (0.0, depth)]
    for name, start, end in zip(("south", "east", "north", "west"), corners, corners[1:] + corners[:1]):
        build.vertical_rectangle(end, start, 0.0, wall_height, 0.6, f"{name} wall")

    build.box(0.4, 1.0, 0.4, 1.0, 0.6, 0.7, "bright box")
    build.box(2.6, 3.3, 4.1, 4.7, 0.5, 0.1, "dark box")
    build.box(4.9, 5.6, 0.4, 1.1, 0.8, 0.45, "grey box")
    build.box(1.8, 2.1, 4.3, 4.6, 0.3, 0.9, "white crate")

    # Ramp against the west wall, rising 0.4 m over 1.2 m toward the wall.
    low, high, y0, y1, rise = 1.4, 0.2, 1.9, 2.9, 0.4
    build.polygon([(low, y0, 0.0), (low, y1, 0.0), (high, y1, rise), (high, y0, rise)], 0.5, "ramp top")
    build.polygon([(low, y0, 0.0), (high, y0, 0.0), (high, y0, rise)], 0.5, "ramp south side")
    build.polygon([(high, y1, 0.0), (low, y1, 0.0), (high, y1, rise)], 0.5, "ramp north side")
    build.vertical_rectangle((high, y0), (high, y1), 0.0, rise, 0.5, "ramp back")

    # Stairs against the east wall, climbing toward +x.
    start, tread, riser, steps, y0, y1 = 4.8, 0.3, 0.15, 3, 1.9, 2.9
    for k in range(steps):
        x = start + k * tread
        build.vertical_rectangle((x, y1), (x, y0), k * riser, (k + 1) * riser, 0.55, f"stair riser {k + 1}")
        build.horizontal_rectangle(x, x + tread, y0, y1, (k + 1) * riser, 0.55, f"stair tread {k + 1}")
    end = start + steps * tread
    build.vertical_rectangle((end, y0), (end, y1), 0.0, steps * riser, 0.55, "stair back")
    for side, y in (("south", y0), ("north", y1)):
        side_id = build.new_id()
        for k in range(steps):
            x = start + k * tread
            build.vertical_rectangle((x, y), (x + tread, y), 0.0, (k + 1) * riser, 0.55, f"stair {side} side", side_id)

    build.cylinder((3.0, 2.5), 0.15, 0.0, wall_height, 0.5, "pillar")

    angles = np.linspace(0.0, 2 * np.pi, 12, endpoint=False)
    loop = tuple((3.0 + 1.3 * math.cos(a), 2.5 + 0.9 * math.sin(a)) for a in angles)
    trajectory = TrajectorySpec(
        waypoints=loop, sensor_height=0.6, speed=0.3, pitch_deg=10.0,
        yaw_offset_deg=25.0, yaw_sway_deg=15.0, sway_wavelength=2.5,
    )
    return build.scene("arena", trajectory)


def _wall_with_doors(
    build: _SceneBuilder, y: float, length: float, height: float, doors: Sequence[tuple[float, float]],
    *, outward: float, label: str, floor_id: int,
) -> None:
    """A wall along x at ``y`` with recessed doors ``(x_start, x_end)``.

    The wall pieces share one surface id; each door recess has its own door
    panel, jambs and head, set back ``0.2`` m in the ``outward`` direction (+1
    or -1 along y).
    """
    door_height, depth = 2.0, 0.2
    wall_id = build.new_id()
    edges = [0.0] + [x for door in doors for x in door] + [length]
    # Wall normals point into the corridor: the start-end order flips with the side.
    def piece(x0, x1, z0, z1):
        start, end = ((x0, y), (x1, y)) if outward < 0 else ((x1, y), (x0, y))
        build.vertical_rectangle(start, end, z0, z1, 0.6, label, wall_id)

    for x0, x1 in zip(edges[0::2], edges[1::2]):
        piece(x0, x1, 0.0, height)
    for k, (x0, x1) in enumerate(doors):
        piece(x0, x1, door_height, height)
        back = y + outward * depth
        name = f"{label} door {k + 1}"
        build.vertical_rectangle((x0, back), (x1, back), 0.0, door_height, 0.3, f"{name} panel")
        build.vertical_rectangle((x0, y), (x0, back), 0.0, door_height, 0.6, f"{name} jamb")
        build.vertical_rectangle((x1, back), (x1, y), 0.0, door_height, 0.6, f"{name} jamb")
        build.horizontal_rectangle(x0, x1, min(y, back), max(y, back), door_height, 0.6, f"{name} head")
        build.horizontal_rectangle(x0, x1, min(y, back), max(y, back), 0.0, 0.35, "floor", floor_id)


def corridor_scene() -> Scene:
    """A corridor 20 m long, 2.4 m wide and 2.5 m high, closed at both ends.

    Floor, ceiling, two end walls and two side walls with three recessed
    doors (door panel, jambs and head each a surface); two boxes and a dark
    cabinet (albedo 0.12) along the walls. The robot drives down the corridor
    and back on a long loop, looking ahead. Far parts lie beyond the
    SR-3000's 7.5 m cut-off.

    Returns
    -------
    Scene
    """
    build = _SceneBuilder()
    length, width, height = 20.0, 2.4, 2.5
    floor_id = build.horizontal_rectangle(0.0, length, 0.0, width, 0.0, 0.35, "floor")
    build.horizontal_rectangle(0.0, length, 0.0, width, height, 0.8, "ceiling")
    build.vertical_rectangle((0.0, 0.0), (0.0, width), 0.0, height, 0.6, "west end wall")
    build.vertical_rectangle((length, width), (length, 0.0), 0.0, height, 0.6, "east end wall")
    south_doors, north_doors = [(4.0, 4.9), (14.0, 14.9)], [(9.0, 9.9)]
    _wall_with_doors(build, 0.0, length, height, south_doors, outward=-1.0, label="south wall", floor_id=floor_id)
    _wall_with_doors(build, width, length, height, north_doors, outward=1.0, label="north wall", floor_id=floor_id)

    build.box(6.5, 7.0, 0.05, 0.5, 0.6, 0.6, "box")
    build.box(12.0, 12.6, 1.95, 2.35, 1.2, 0.12, "dark cabinet")
    build.box(16.5, 17.1, 0.05, 0.5, 0.4, 0.8, "white box")

    loop = _stadium_waypoints(2.0, 17.6, 0.85, 1.55, spacing=0.5)
    trajectory = TrajectorySpec(
        waypoints=loop, sensor_height=0.7, speed=0.3, pitch_deg=5.0,
        yaw_offset_deg=0.0, yaw_sway_deg=8.0, sway_wavelength=3.0,
    )
    return build.scene("corridor", trajectory)


SCENES = {"arena": arena_scene, "corridor": corridor_scene}


@functools.lru_cache(maxsize=None)
def _builtin_scene(name: str) -> Scene:
    return SCENES[name]()


def get_scene(name: str | Scene) -> Scene:
    """Look up a built-in scene by name (``arena``, ``corridor``); a `Scene` passes through.

    Raises
    ------
    ValueError
        If the name is unknown.
    """
    if isinstance(name, Scene):
        return name
    if not isinstance(name, str) or name.lower() not in SCENES:
        raise ValueError(f"unknown scene {name!r}; expected one of {', '.join(SCENES)} or a Scene")
    return _builtin_scene(name.lower())


# --------------------------------------------------------------------------
# Poses.
# --------------------------------------------------------------------------


def _optical_rotation(forward: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Rotation whose columns are the sensor's x (right), y (down), z (forward) axes in the world."""
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=-1)


def look_at(eye: Sequence[float], target: Sequence[float], *, up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_sensor`` (4, 4) float64 of a sensor at ``eye`` looking at ``target``.

    The boresight (sensor z) points at the target, sensor x to the right and
    sensor y down with respect to the world direction ``up``.

    Raises
    ------
    ValueError
        If ``eye`` equals ``target`` or the view direction is parallel to ``up``.

    Examples
    --------
    >>> T = look_at((0, 0, 1), (5, 0, 1))
    >>> T[:3, 2].round(6).tolist()  # boresight along world x
    [1.0, 0.0, 0.0]
    """
    eye, target, up = (np.asarray(v, dtype=np.float64).reshape(3) for v in (eye, target, up))
    forward = target - eye
    if np.linalg.norm(forward) < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: view direction is parallel to 'up'; pass another up vector")
    right /= np.linalg.norm(right)
    transform = np.eye(4)
    transform[:3, :3] = _optical_rotation(forward, right)
    transform[:3, 3] = eye
    return transform


def default_trajectory(scene: str | Scene, n_frames: int, *, frame_rate: float) -> np.ndarray:
    """Sensor poses of a robot driving the scene's loop.

    The robot starts at the loop's first waypoint and drives at the scene's
    speed (capped at ``max_step`` per frame for slow scanners), its sensor
    at a fixed height, pitched slightly down, yawing with the path and a slow
    sway. Frame ``k`` is taken at time ``k / frame_rate``; its pose does not
    depend on ``n_frames``.

    Parameters
    ----------
    scene : str or Scene
    n_frames : int
        Number of poses, >= 0.
    frame_rate : float
        Frames per second (``sensor.frame_rate``).

    Returns
    -------
    (N, 4, 4) float64
        ``T_world_sensor`` of each frame (camera-optical sensor axes).

    Raises
    ------
    ValueError
        If ``n_frames`` or ``frame_rate`` is invalid, or the scene has no
        trajectory.
    """
    scene = get_scene(scene)
    spec = scene.trajectory
    if spec is None:
        raise ValueError(f"scene {scene.name!r} has no trajectory; pass poses explicitly")
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 0:
        raise ValueError(f"n_frames must be an integer >= 0, got {n_frames!r}")
    if not (math.isfinite(frame_rate) and frame_rate > 0):
        raise ValueError(f"frame_rate must be > 0, got {frame_rate}")
    step = min(spec.speed / frame_rate, spec.max_step)
    driven = step * np.arange(n_frames, dtype=np.float64)
    position, heading = spec.at(driven)
    yaw = (
        heading
        + math.radians(spec.yaw_offset_deg)
        + math.radians(spec.yaw_sway_deg) * np.sin(2 * np.pi * driven / spec.sway_wavelength)
    )
    pitch = math.radians(spec.pitch_deg)
    forward = np.stack(
        [math.cos(pitch) * np.cos(yaw), math.cos(pitch) * np.sin(yaw), np.full_like(yaw, -math.sin(pitch))], axis=-1
    )
    right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=-1)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    poses[:, :3, :3] = _optical_rotation(forward, right)
    poses[:, :2, 3] = position
    poses[:, 2, 3] = spec.sensor_height
    return poses


def noisy_odometry(
    poses: np.ndarray, *, seed: int = 0, translation_noise: float = 0.05, rotation_noise_deg: float = 0.5
) -> np.ndarray:
    """Wheel-odometry-like poses: the true steps with random errors, integrated (so they drift).

    Each step ``inv(P_k-1) P_k`` is perturbed by a translation error of
    ``translation_noise`` times its length (per axis, standard deviation,
    plus 1 mm) and a rotation error of ``rotation_noise_deg`` degrees (per
    axis); the first pose is exact.

    Parameters
    ----------
    poses : (N, 4, 4) array
        True ``T_world_sensor``.

    Returns
    -------
    (N, 4, 4) float64
        Odometry poses, for ``RangeFrame.pose`` (``dataclasses.replace(frame, pose=...)``).

    Examples
    --------
    >>> poses = default_trajectory("arena", 50, frame_rate=25.0)
    >>> odometry = noisy_odometry(poses, seed=1)
    >>> bool(np.allclose(odometry[0], poses[0])), bool(np.linalg.norm(odometry[-1, :3, 3] - poses[-1, :3, 3]) > 1e-3)
    (True, True)
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (N, 4, 4), got {poses.shape}")
    if not (translation_noise >= 0 and rotation_noise_deg >= 0):
        raise ValueError("odometry noise levels must be >= 0")
    rng = np.random.default_rng(seed)
    odometry = poses.copy()
    for k in range(1, len(poses)):
        step = np.linalg.inv(poses[k - 1]) @ poses[k]
        length = float(np.linalg.norm(step[:3, 3]))
        error = np.eye(4)
        error[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, math.radians(rotation_noise_deg), 3)).as_matrix()
        error[:3, 3] = rng.normal(0.0, translation_noise * length + 1e-3, 3)
        odometry[k] = odometry[k - 1] @ step @ error
    return odometry


# --------------------------------------------------------------------------
# Ray casting.
# --------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _nearest_hits_kernel(
    origin, directions, plane_normals, plane_offsets, edge_normals, edge_offsets, edge_counts, cylinders,
    distance, primitive,
):  # pragma: no cover - compiled
    n_polygons = plane_normals.shape[0]
    n_cylinders = cylinders.shape[0]
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in range(directions.shape[0]):
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        best = np.inf
        best_primitive = -1
        for p in range(n_polygons):
            nx, ny, nz = plane_normals[p, 0], plane_normals[p, 1], plane_normals[p, 2]
            denominator = nx * dx + ny * dy + nz * dz
            if abs(denominator) < 1e-12:
                continue
            t = -(nx * ox + ny * oy + nz * oz + plane_offsets[p]) / denominator
            if t <= _MIN_HIT_DISTANCE or t >= best:
                continue
            px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
            inside = True
            for e in range(edge_counts[p]):
                side = edge_normals[p, e, 0] * px + edge_normals[p, e, 1] * py + edge_normals[p, e, 2] * pz
                if side < edge_offsets[p, e] - _EDGE_TOLERANCE:
                    inside = False
                    break
            if inside:
                best = t
                best_primitive = p
        a = dx * dx + dy * dy
        if a > 1e-18:
            for c in range(n_cylinders):
                fx, fy = ox - cylinders[c, 0], oy - cylinders[c, 1]
                half_b = fx * dx + fy * dy
                discriminant = half_b * half_b - a * (fx * fx + fy * fy - cylinders[c, 2] ** 2)
                if discriminant < 0:
                    continue
                root = math.sqrt(discriminant)
                # Entry first; the exit (inner wall of the open tube) only if the entry misses its height.
                for t in ((-half_b - root) / a, (-half_b + root) / a):
                    if t > _MIN_HIT_DISTANCE and t < best:
                        z = oz + t * dz
                        if cylinders[c, 3] <= z <= cylinders[c, 4]:
                            best = t
                            best_primitive = n_polygons + c
                            break
        distance[i] = best
        primitive[i] = best_primitive


def _nearest_hits(packed: _PackedScene, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance ``(N,)`` (inf where none) and primitive index ``(N,)`` (-1 where none) of the nearest hits."""
    directions = np.ascontiguousarray(directions, dtype=np.float64)
    distance = np.empty(len(directions))
    primitive = np.empty(len(directions), np.int64)
    _nearest_hits_kernel(
        np.ascontiguousarray(origin, dtype=np.float64), directions, packed.plane_normals, packed.plane_offsets,
        packed.edge_normals, packed.edge_offsets, packed.edge_counts, packed.cylinders, distance, primitive,
    )
    return distance, primitive


def _nearest_hits_reference(
    packed: _PackedScene, origin: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Plain NumPy version of `_nearest_hits_kernel` (loop over primitives, vectorised over rays)."""
    directions = np.asarray(directions, dtype=np.float64)
    best = np.full(len(directions), np.inf)
    primitive = np.full(len(directions), -1, np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        for p, (normal, offset) in enumerate(zip(packed.plane_normals, packed.plane_offsets)):
            denominator = directions @ normal
            t = -(normal @ origin + offset) / denominator
            hit = (np.abs(denominator) >= 1e-12) & (t > _MIN_HIT_DISTANCE) & (t < best)
            points = origin + t[:, None] * directions
            for e in range(packed.edge_counts[p]):
                hit &= points @ packed.edge_normals[p, e] >= packed.edge_offsets[p, e] - _EDGE_TOLERANCE
            best[hit] = t[hit]
            primitive[hit] = p
        a = directions[:, 0] ** 2 + directions[:, 1] ** 2
        for c, (x, y, radius, z_min, z_max) in enumerate(packed.cylinders):
            fx, fy = origin[0] - x, origin[1] - y
            half_b = fx * directions[:, 0] + fy * directions[:, 1]
            discriminant = half_b**2 - a * (fx**2 + fy**2 - radius**2)
            usable = (a > 1e-18) & (discriminant >= 0)
            root = np.sqrt(np.where(usable, discriminant, 0.0))
            taken = np.zeros(len(directions), bool)
            for t in ((-half_b - root) / a, (-half_b + root) / a):
                z = origin[2] + t * directions[:, 2]
                hit = usable & ~taken & (t > _MIN_HIT_DISTANCE) & (t < best) & (z >= z_min) & (z <= z_max)
                best[hit] = t[hit]
                primitive[hit] = len(packed.plane_normals) + c
                taken |= hit
    return best, primitive


def _hit_normals(
    packed: _PackedScene, origin: np.ndarray, directions: np.ndarray, distance: np.ndarray, primitive: np.ndarray
) -> np.ndarray:
    """Unit world normals ``(N, 3)`` at the hits, facing the ray origin; NaN where nothing was hit."""
    n_polygons = len(packed.plane_normals)
    normals = np.full(directions.shape, np.nan)
    on_polygon = (primitive >= 0) & (primitive < n_polygons)
    normals[on_polygon] = packed.plane_normals[primitive[on_polygon]]
    on_cylinder = primitive >= n_polygons
    if on_cylinder.any():
        axis = packed.cylinders[primitive[on_cylinder] - n_polygons]
        points = origin[:2] + distance[on_cylinder, None] * directions[on_cylinder, :2]
        normals[on_cylinder, :2] = (points - axis[:, :2]) / axis[:, 2:3]
        normals[on_cylinder, 2] = 0.0
    flip = np.einsum("ij,ij->i", normals, directions) > 0
    normals[flip] *= -1
    return normals


def ray_cast(
    scene: str | Scene, origin: Sequence[float], directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest intersection of rays from one origin with the scene.

    Parameters
    ----------
    scene : str or Scene
    origin : (3,) array
        Ray origin in world coordinates (metres).
    directions : (N, 3) array
        Ray directions in world coordinates; normalised here.

    Returns
    -------
    distance : (N,) float64
        Metres along the ray to the nearest hit, ``inf`` where nothing is hit.
    surface_id : (N,) int32
        Surface label of the hit, 0 where nothing is hit.
    normal : (N, 3) float64
        Unit world normal at the hit, facing the origin (``normal . direction
        <= 0``); radial on cylinders; NaN where nothing is hit.

    Raises
    ------
    ValueError
        If shapes are wrong or values not finite, or a direction is zero.

    Examples
    --------
    >>> distance, surface_id, normal = ray_cast("arena", (3.0, 1.0, 0.6), [[0.0, 0.0, -1.0]])
    >>> float(distance[0]), int(surface_id[0]), normal[0].tolist()
    (0.6, 1, [0.0, 0.0, 1.0])
    """
    scene = get_scene(scene)
    origin = np.asarray(origin, dtype=np.float64)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise ValueError(f"origin must be 3 finite numbers, got shape {origin.shape}")
    directions = np.asarray(directions, dtype=np.float64)
    if directions.ndim != 2 or directions.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3), got {directions.shape}")
    if not np.all(np.isfinite(directions)):
        raise ValueError("directions contain NaN or Inf")
    lengths = np.linalg.norm(directions, axis=1)
    if np.any(lengths < 1e-12):
        raise ValueError(f"{int((lengths < 1e-12).sum())} direction(s) have zero length")
    directions = directions / lengths[:, None]
    packed = scene._packed
    distance, primitive = _nearest_hits(packed, origin, directions)
    surface_id = np.where(primitive >= 0, packed.surface_ids[primitive], 0).astype(np.int32)
    return distance, surface_id, _hit_normals(packed, origin, directions, distance, primitive)


# --------------------------------------------------------------------------
# Sensor simulation.
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class SimulationNoise:
    """Which sensor effects `simulate_frame` applies, and how strongly.

    Parameters
    ----------
    range_noise : bool
        Add noise along the line of sight: ``reading = true + sigma * (offset
        + z)`` with ``sigma = sensor.noise.sigma(range, intensity)`` and ``z``
        drawn from the sensor's zero-mean split normal
        (`RangeNoiseModel.split_normal_scales`).
    mixed_pixels : bool
        Pixels whose footprint straddles a depth discontinuity read the
        amplitude-weighted mean range of 3 x 3 sub-rays (flying pixels).
    salt_and_pepper : float
        Fraction of pixels, in [0, 1], replaced by ranges drawn uniformly
        from ``[min_range, max_range]``.
    clamp : bool
        Apply the sensor's range limits: readings past ``max_range`` and rays
        that hit nothing follow ``sensor.beyond_max_range`` (``"clamp"``:
        exactly ``max_range``; ``"invalid"``: NaN), readings below
        ``min_range`` become NaN. With ``False`` the sensor is ideal: every
        hit is reported, whatever its range.
    mixed_pixel_jump : float
        Relative range jump, ``|r1 - r2| / min(r1, r2)``, that makes a depth
        discontinuity between neighbouring pixels (and between sub-rays of a
        mixed pixel).

    Notes
    -----
    `none` switches off every random corruption but keeps ``clamp`` on: the
    cut-off is what the sensor can report at all, not noise. Use
    ``dataclasses.replace(SimulationNoise.none(), clamp=False)`` for an ideal
    sensor.
    """

    range_noise: bool = True
    mixed_pixels: bool = True
    salt_and_pepper: float = 0.002
    clamp: bool = True
    mixed_pixel_jump: float = 0.05

    def __post_init__(self) -> None:
        if not (math.isfinite(self.salt_and_pepper) and 0.0 <= self.salt_and_pepper <= 1.0):
            raise ValueError(f"salt_and_pepper must be a fraction in [0, 1], got {self.salt_and_pepper}")
        if not (math.isfinite(self.mixed_pixel_jump) and self.mixed_pixel_jump > 0):
            raise ValueError(f"mixed_pixel_jump must be > 0, got {self.mixed_pixel_jump}")

    @classmethod
    def none(cls) -> SimulationNoise:
        """No noise, mixed pixels or outliers; the sensor's cut-off still applies."""
        return cls(range_noise=False, mixed_pixels=False, salt_and_pepper=0.0, clamp=True)


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What a simulated frame should have measured.

    ``surface_id``, ``normals`` and ``intensity`` describe the surface hit by
    each pixel's centre ray where that hit lies within the sensor's range
    (``range`` finite), and are 0 / NaN elsewhere.

    Parameters
    ----------
    range : (H, W) float32
        True range of the centre ray (metres); NaN where it hits nothing or
        the hit lies outside ``[min_range, max_range]``.
    surface_id : (H, W) int32
        Surface label, 0 where ``range`` is NaN.
    normals : (H, W, 3) float32
        Unit surface normals in the sensor frame facing the sensor
        (``normal . ray < 0``); NaN where ``range`` is NaN.
    planes : (S + 1, 4) float64
        ``(nx, ny, nz, d)`` of every planar surface in the sensor frame,
        indexed by surface id: ``n . p + d = 0`` for sensor-frame points
        ``p``, oriented toward the sensor (``d >= 0``). Row 0, cylinders and
        unused ids are NaN.
    T_world_sensor : (4, 4) float64
        The true pose.
    intensity : (H, W) float32
        Range-compensated reflectance ``albedo * |cos(incidence)|`` in
        [0, 1]; NaN where ``range`` is NaN.
    mixed : (H, W) bool
        Mixed (flying) pixels: the reading mixes several surfaces.
    outlier : (H, W) bool
        Salt-and-pepper pixels: the reading is random.
    clamped : (H, W) bool
        The reading lay past ``max_range`` (or the ray hit nothing) and
        follows ``sensor.beyond_max_range``.
    sigma : (H, W) float32
        Standard deviation of the range noise added (metres); 0 without range
        noise, NaN where the ray hits nothing.
    """

    range: np.ndarray
    surface_id: np.ndarray
    normals: np.ndarray
    planes: np.ndarray
    T_world_sensor: np.ndarray
    intensity: np.ndarray
    mixed: np.ndarray
    outlier: np.ndarray
    clamped: np.ndarray
    sigma: np.ndarray

    def __post_init__(self) -> None:
        shape = np.shape(self.range)
        if len(shape) != 2:
            raise ValueError(f"ground-truth range must be 2-D (H, W), got shape {shape}")
        expected = {
            "surface_id": shape, "normals": shape + (3,), "intensity": shape,
            "mixed": shape, "outlier": shape, "clamped": shape, "sigma": shape, "T_world_sensor": (4, 4),
        }
        for name, wanted in expected.items():
            if np.shape(getattr(self, name)) != wanted:
                raise ValueError(f"ground-truth {name} must have shape {wanted}, got {np.shape(getattr(self, name))}")
        planes = np.shape(self.planes)
        if len(planes) != 2 or planes[1] != 4 or planes[0] < 1:
            raise ValueError(f"ground-truth planes must have shape (S + 1, 4), got {planes}")


def simulate_frame(
    scene: str | Scene,
    sensor: str | SensorModel,
    T_world_sensor: np.ndarray,
    *,
    noise: SimulationNoise | None = None,
    rng: np.random.Generator,
    timestamp: float = 0.0,
    source: str | None = None,
) -> tuple[RangeFrame, GroundTruth]:
    """Simulate one frame of ``sensor`` at pose ``T_world_sensor`` in ``scene``.

    Parameters
    ----------
    scene : str or Scene
    sensor : str or SensorModel
        A preset name or a model with a projection.
    T_world_sensor : (4, 4) array
        Sensor pose (camera-optical sensor axes: x right, y down, z forward).
    noise : SimulationNoise, optional
        Effects to apply; default ``SimulationNoise()``.
    rng : numpy.random.Generator
        Source of all randomness of the frame.
    timestamp : float
        Seconds, copied to the frame.
    source : str, optional
        Frame source; default ``"simulated:<scene>/<sensor>"``.

    Returns
    -------
    frame : RangeFrame
        Rays from the sensor, the corrupted range, the measured intensity
        (the true intensity, mixed like the range on mixed pixels, 0 where a
        reading carries no return: clamped pixels; NaN where there is no
        reading), ``pose`` and ``reference_pose`` both the true pose.
    truth : GroundTruth

    Raises
    ------
    ValueError
        Unknown scene or sensor name, a sensor without projection, or a pose
        that is not a 4x4 rigid transform.
    TypeError
        If ``rng`` is not a `numpy.random.Generator`.

    Notes
    -----
    In order: cast centre rays; replace mixed pixels by their sub-ray mix;
    add range noise; apply the range limits; replace outliers. Intensity is
    the normalised reflectance ``albedo * |cos(incidence)|``: range-compensated,
    as ToF cameras' amplitude images are usually normalised, so it drives the
    intensity term of the noise model independently of range.

    Examples
    --------
    >>> import numpy as np
    >>> frame, truth = simulate_frame("arena", "sr3000", look_at((3, 1, 0.6), (3, 5, 0.6)),
    ...                               noise=SimulationNoise.none(), rng=np.random.default_rng(0))
    >>> bool(np.allclose(frame.range[truth.surface_id > 0], truth.range[truth.surface_id > 0]))
    True
    """
    scene = get_scene(scene)
    sensor = get_sensor(sensor)
    noise = SimulationNoise() if noise is None else noise
    if not isinstance(noise, SimulationNoise):
        raise ValueError(f"noise must be a SimulationNoise, got {type(noise).__name__}")
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {type(rng).__name__}")
    # A copy: the frame and the truth must not change with the caller's array.
    pose = check_rigid_transform(T_world_sensor, "T_world_sensor").copy()
    rays = sensor.rays()
    shape = sensor.shape
    rotation, origin = pose[:3, :3], pose[:3, 3].copy()
    packed = scene._packed

    directions = rays.reshape(-1, 3).astype(np.float64) @ rotation.T
    distance, primitive = _nearest_hits(packed, origin, directions)
    hit = primitive >= 0
    normals_world = _hit_normals(packed, origin, directions, distance, primitive)
    with np.errstate(invalid="ignore"):
        incidence = np.abs(np.einsum("ij,ij->i", normals_world, directions))
    intensity = np.where(hit, packed.albedo[primitive] * incidence, np.nan)

    reading = np.where(hit, distance, np.nan)
    measured_intensity = np.where(hit, intensity, 0.0)
    mixed = np.zeros(len(reading), bool)
    if noise.mixed_pixels:
        pixels, mixed_range, mixed_intensity = _mixed_pixels(
            packed, sensor, rotation, origin, np.where(hit, distance, np.inf).reshape(shape), noise.mixed_pixel_jump
        )
        reading[pixels] = mixed_range
        measured_intensity[pixels] = mixed_intensity
        mixed[pixels] = True

    sigma = sensor.noise.sigma(reading, measured_intensity)
    if noise.range_noise:
        near, far, offset = sensor.noise.split_normal_scales()
        magnitude = np.abs(rng.standard_normal(len(reading)))
        # A split normal picks its side with probability proportional to that side's spread.
        behind = rng.random(len(reading)) < far / (near + far)
        reading = reading + sigma * (offset + np.where(behind, far * magnitude, -near * magnitude))
    else:
        sigma = np.where(np.isnan(reading), np.nan, 0.0)

    clamped = np.zeros(len(reading), bool)
    with np.errstate(invalid="ignore"):
        if noise.clamp:
            clamped = np.isnan(reading) | (reading > sensor.max_range)
            reading[reading < sensor.min_range] = np.nan
            reading[clamped] = sensor.max_range if sensor.beyond_max_range == "clamp" else np.nan
            measured_intensity[clamped] = 0.0
        reading[reading <= 0] = np.nan

    outlier = np.zeros(len(reading), bool)
    if noise.salt_and_pepper > 0:
        outlier = rng.random(len(reading)) < noise.salt_and_pepper
        low = max(sensor.min_range, 1e-3)
        # A sensor without a cut-off draws up to the farthest surface in view.
        high = sensor.max_range if math.isfinite(sensor.max_range) else max(distance[hit].max(initial=0.0), low + 1.0)
        reading[outlier] = rng.uniform(low, high, int(outlier.sum()))
        mixed &= ~outlier
        clamped &= ~outlier
    measured_intensity[np.isnan(reading)] = np.nan

    in_range = hit & (distance >= sensor.min_range) & (distance <= sensor.max_range)
    normals_sensor = np.where(in_range[:, None], normals_world @ rotation, np.nan)
    truth = GroundTruth(
        range=np.where(in_range, distance, np.nan).reshape(shape).astype(np.float32),
        surface_id=np.where(in_range, packed.surface_ids[primitive], 0).reshape(shape).astype(np.int32),
        normals=normals_sensor.reshape(shape + (3,)).astype(np.float32),
        planes=_planes_in_sensor_frame(scene.planes, pose),
        T_world_sensor=pose.copy(),
        intensity=np.where(in_range, intensity, np.nan).reshape(shape).astype(np.float32),
        mixed=mixed.reshape(shape),
        outlier=outlier.reshape(shape),
        clamped=clamped.reshape(shape),
        sigma=sigma.reshape(shape).astype(np.float32),
    )
    frame = RangeFrame(
        rays=rays,
        range=reading.reshape(shape).astype(np.float32),
        sensor=sensor,
        intensity=measured_intensity.reshape(shape).astype(np.float32),
        pose=pose,
        timestamp=timestamp,
        reference_pose=pose.copy(),
        source=source if source is not None else f"simulated:{scene.name}/{sensor.name}",
    )
    return frame, truth


def _planes_in_sensor_frame(planes_world: np.ndarray, T_world_sensor: np.ndarray) -> np.ndarray:
    """World planes ``(S + 1, 4)`` in the sensor frame, oriented toward the sensor."""
    rotation, translation = T_world_sensor[:3, :3], T_world_sensor[:3, 3]
    normals = planes_world[:, :3] @ rotation  # R^T n, row-wise
    offsets = planes_world[:, :3] @ translation + planes_world[:, 3]
    # The sensor origin lies on the positive side: n . 0 + d > 0.
    sign = np.where(offsets < 0, -1.0, 1.0)
    return np.column_stack([normals * sign[:, None], offsets * sign])


@functools.lru_cache(maxsize=8)
def _ray_steps(sensor: SensorModel) -> tuple[np.ndarray, np.ndarray]:
    """Change of the viewing ray per pixel along rows and columns, ``(H, W, 3)`` float64 each."""
    rays = sensor.rays().astype(np.float64)
    steps = [
        np.gradient(rays, axis=axis) if rays.shape[axis] > 1 else np.zeros_like(rays) for axis in (0, 1)
    ]
    return steps[0], steps[1]


# Sub-ray offsets within a pixel footprint (in pixels): the centres of a 3 x 3 split.
_SUB_OFFSETS = np.array([(a, b) for a in (-1 / 3, 0.0, 1 / 3) for b in (-1 / 3, 0.0, 1 / 3)])


def _depth_jumps(first: np.ndarray, second: np.ndarray, jump: float) -> np.ndarray:
    """True where two ranges (inf = no hit) differ by more than ``jump`` relative to the nearer."""
    first_hit, second_hit = np.isfinite(first), np.isfinite(second)
    with np.errstate(invalid="ignore"):
        large = np.abs(first - second) > jump * np.minimum(first, second)
    return (first_hit != second_hit) | (first_hit & second_hit & large)


def _mixed_pixels(
    packed: _PackedScene, sensor: SensorModel, rotation: np.ndarray, origin: np.ndarray,
    true_range: np.ndarray, jump: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat indices, mixed readings and mixed intensities of the pixels that straddle a discontinuity.

    Only pixels with a 4-neighbour across a range jump are supersampled. A
    pixel is mixed when its sub-rays return from ranges spread by more than
    ``jump``; it then reads the mean of the sub-ray ranges weighted by their
    amplitude, ``albedo * |cos| / r**2`` (Lange & Seitz 2001), which lies
    strictly between the nearest and farthest sub-ray ranges.
    """
    height, width = true_range.shape
    candidate = np.zeros(true_range.shape, bool)
    vertical = _depth_jumps(true_range[:-1], true_range[1:], jump)
    horizontal = _depth_jumps(true_range[:, :-1], true_range[:, 1:], jump)
    candidate[:-1] |= vertical
    candidate[1:] |= vertical
    candidate[:, :-1] |= horizontal
    candidate[:, 1:] |= horizontal
    rows, cols = np.nonzero(candidate)
    if len(rows) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)

    # Sub-rays step a third of a pixel along the local change of the ray:
    # projection-agnostic (pinhole and swept fan) and exact to first order.
    row_step, col_step = _ray_steps(sensor)
    centre = sensor.rays()[rows, cols].astype(np.float64)
    sub_rays = (
        centre[:, None, :]
        + _SUB_OFFSETS[None, :, 0, None] * row_step[rows, cols][:, None, :]
        + _SUB_OFFSETS[None, :, 1, None] * col_step[rows, cols][:, None, :]
    ).reshape(-1, 3)
    sub_rays /= np.linalg.norm(sub_rays, axis=1, keepdims=True)
    directions = sub_rays @ rotation.T
    distance, primitive = _nearest_hits(packed, origin, directions)
    hit = primitive >= 0
    normals = _hit_normals(packed, origin, directions, distance, primitive)
    with np.errstate(invalid="ignore", divide="ignore"):
        reflectance = np.where(hit, packed.albedo[primitive] * np.abs(np.einsum("ij,ij->i", normals, directions)), 0.0)
        weight = np.where(hit, reflectance / distance**2, 0.0).reshape(-1, 9)
    distance = distance.reshape(-1, 9)
    returns = weight > 0
    nearest = np.where(returns, distance, np.inf).min(axis=1)
    farthest = np.where(returns, distance, -np.inf).max(axis=1)
    is_mixed = (returns.sum(axis=1) >= 2) & (farthest - nearest > jump * nearest)
    weight, distance = weight[is_mixed], distance[is_mixed]
    mixed_range = (weight * np.where(weight > 0, distance, 0.0)).sum(axis=1) / weight.sum(axis=1)
    reflectance = reflectance.reshape(-1, 9)[is_mixed]
    mixed_intensity = reflectance.sum(axis=1) / returns[is_mixed].sum(axis=1)
    pixels = rows[is_mixed] * width + cols[is_mixed]
    return pixels, mixed_range, mixed_intensity


def iter_sequence(
    scene: str | Scene = "arena",
    sensor: str | SensorModel = "sr3000",
    n_frames: int = 10,
    *,
    seed: int = 0,
    noise: SimulationNoise | None = None,
    trajectory: np.ndarray | None = None,
    start: int = 0,
) -> Iterator[tuple[RangeFrame, GroundTruth]]:
    """Yield ``(frame, truth)`` of a robot recording ``n_frames`` frames in a scene.

    Arguments are checked at once; frames are simulated as they are asked for.

    Parameters
    ----------
    scene : str or Scene
        ``"arena"``, ``"corridor"`` or a `Scene`.
    sensor : str or SensorModel
        A preset name (``"sr3000"``, ``"uos-laser"``, ``"kinect"``,
        ``"cyberware"``) or a model with a projection.
    n_frames : int
        Number of frames, >= 0.
    seed : int
        Seed of all randomness. Frame ``k`` draws from the ``k``-th child of
        ``numpy.random.SeedSequence(seed)``, so it is bit-identical for a
        given seed whatever ``n_frames`` is.
    noise : SimulationNoise, optional
        Default ``SimulationNoise()``.
    trajectory : (n_frames, 4, 4) array, optional
        ``T_world_sensor`` per frame; default `default_trajectory` at the
        sensor's frame rate.
    start : int
        Begin at frame ``start`` (the same frames as the whole sequence's
        from there on, without simulating those before: a resumed run).

    Yields
    ------
    frame : RangeFrame
        Timestamp ``k / sensor.frame_rate``, source
        ``"simulated:<scene>/<sensor>/frame0003"``.
    truth : GroundTruth

    Raises
    ------
    ValueError
        Unknown scene or sensor, bad ``n_frames``, or a trajectory of the wrong
        shape.

    Examples
    --------
    >>> frame, truth = next(iter_sequence("corridor", "sr3000", n_frames=2, seed=7))
    >>> frame.source
    'simulated:corridor/sr3000/frame0000'
    """
    scene = get_scene(scene)
    sensor = get_sensor(sensor)
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 0:
        raise ValueError(f"n_frames must be an integer >= 0, got {n_frames!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    if trajectory is None:
        poses = default_trajectory(scene, n_frames, frame_rate=sensor.frame_rate)
    else:
        poses = np.asarray(trajectory, dtype=np.float64)
        if poses.shape != (n_frames, 4, 4):
            raise ValueError(
                f"trajectory must have shape ({n_frames}, 4, 4) for n_frames={n_frames}, got {poses.shape}"
            )
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or not 0 <= start <= n_frames:
        raise ValueError(f"start must be an integer in [0, {n_frames}], got {start!r}")
    children = np.random.SeedSequence(seed).spawn(n_frames)
    return _simulated_frames(scene, sensor, poses, children, noise, int(start))


def _simulated_frames(
    scene: Scene, sensor: SensorModel, poses: np.ndarray, children: list, noise: SimulationNoise | None, start: int
) -> Iterator[tuple[RangeFrame, GroundTruth]]:
    for k in range(start, len(poses)):
        pose, child = poses[k], children[k]
        yield simulate_frame(
            scene, sensor, pose, noise=noise, rng=np.random.default_rng(child), timestamp=k / sensor.frame_rate,
            source=f"simulated:{scene.name}/{sensor.name}/frame{k:04d}",
        )


def simulate_sequence(
    scene: str | Scene = "arena",
    sensor: str | SensorModel = "sr3000",
    n_frames: int = 10,
    *,
    seed: int = 0,
    noise: SimulationNoise | None = None,
    trajectory: np.ndarray | None = None,
) -> tuple[list[RangeFrame], list[GroundTruth]]:
    """Simulate a robot recording ``n_frames`` frames in a scene.

    All frames at once; `iter_sequence` yields them one at a time with the
    same arguments and identical results.

    Examples
    --------
    >>> frames, truth = simulate_sequence("corridor", "sr3000", n_frames=2, seed=7)
    >>> frames[1].source
    'simulated:corridor/sr3000/frame0001'
    """
    pairs = list(iter_sequence(scene, sensor, n_frames, seed=seed, noise=noise, trajectory=trajectory))
    return [frame for frame, _ in pairs], [truth for _, truth in pairs]


# --------------------------------------------------------------------------
# Saving ground truth.
# --------------------------------------------------------------------------

_TRUTH_FIELDS = [f.name for f in dataclasses.fields(GroundTruth)]


def save_ground_truth(path: str | os.PathLike, truth: GroundTruth) -> None:
    """Write ``truth`` to a compressed ``.npz`` file atomically (temporary file, then rename).

    Parameters
    ----------
    path : str or path-like
        Output file; written as given (no suffix is added).
    truth : GroundTruth
    """
    if not isinstance(truth, GroundTruth):
        raise ValueError(f"save_ground_truth expects a GroundTruth, got {type(truth).__name__}")
    arrays = {name: np.asarray(getattr(truth, name)) for name in _TRUTH_FIELDS}
    with atomic_path(path) as temporary, open(temporary, "wb") as stream:
        np.savez_compressed(stream, format_version=np.int64(_GROUND_TRUTH_FORMAT_VERSION), **arrays)


def load_ground_truth(path: str | os.PathLike) -> GroundTruth:
    """Read a file written by `save_ground_truth`.

    Raises
    ------
    FormatError
        If the file lacks a field, has an unknown version, or its arrays
        disagree in shape.
    """
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise FormatError(path, f"not a ground-truth .npz file ({error})") from None
    with archive:
        missing = [name for name in ["format_version", *_TRUTH_FIELDS] if name not in archive.files]
        if missing:
            raise FormatError(path, f"missing ground-truth field(s) {', '.join(missing)}")
        version = int(archive["format_version"])
        if version != _GROUND_TRUTH_FORMAT_VERSION:
            expected = _GROUND_TRUTH_FORMAT_VERSION
            raise FormatError(path, f"ground-truth format version {version} is not supported (expected {expected})")
        arrays = {name: archive[name] for name in _TRUTH_FIELDS}
    try:
        return GroundTruth(**arrays)
    except ValueError as error:
        raise FormatError(path, str(error)) from None
