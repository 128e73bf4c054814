"""Sensor models and range frames: the data every pipeline stage consumes.

Conventions (used throughout rangesurf):

* Lengths are metres, angles radians unless a name says ``_deg``.
* Sensor frames follow the camera ("optical") convention: x right, y down,
  z forward along the boresight. Frames are right-handed.
* A transform is named by its frames: ``T_world_sensor`` maps points from the
  sensor frame into the world frame, ``p_world = T_world_sensor @ p_sensor``.
* A range image is ``(H, W) float32`` with NaN where the sensor reported no
  return; its points are ``rays * range`` with unit rays from the sensor
  origin. Denoising changes only the range, since the noise of these sensors
  lies along the line of sight (thesis Section 2.1).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numba
import numpy as np

__all__ = [
    "PinholeProjection",
    "SweptFanProjection",
    "RangeNoiseModel",
    "SensorModel",
    "RangeFrame",
    "SENSORS",
    "get_sensor",
    "unknown_sensor",
    "check_rigid_transform",
]

_RAY_NORM_TOLERANCE = 1e-3
_ROTATION_TOLERANCE = 1e-4


# --------------------------------------------------------------------------
# Projections: how a grid cell maps to a viewing ray.
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class PinholeProjection:
    """Pinhole intrinsics of a depth or time-of-flight camera, in pixels.

    Pixel ``(row, col)`` looks along ``((col - cx) / fx, (row - cy) / fy, 1)``.
    A negative ``fy`` describes a grid stored bottom-up.
    """

    fx: float
    fy: float
    cx: float
    cy: float

    kind = "pinhole"

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ValueError(f"pinhole {name} must be finite, got {value}")
        if self.fx == 0 or self.fy == 0:
            raise ValueError(f"pinhole focal lengths must be non-zero, got fx={self.fx}, fy={self.fy}")

    def directions(self, height: int, width: int) -> np.ndarray:
        """Unnormalised ray directions ``(H, W, 3)`` float64."""
        rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
        return np.stack(
            [(cols - self.cx) / self.fx, (rows - self.cy) / self.fy, np.ones_like(rows)], axis=-1
        )

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, **dataclasses.asdict(self)}


@dataclass(frozen=True)
class SweptFanProjection:
    """A 2D line scanner swept by a tilt axis (e.g. a rotating SICK LMS).

    Each grid row is one planar fan; column ``j`` lies at fan angle
    ``fan_start_deg + j * fan_step_deg`` measured from the sensor's x axis
    toward its boresight, row ``i`` at tilt ``tilt_start_deg + i * tilt_step_deg``
    (positive tilts look up, i.e. toward -y).
    """

    fan_start_deg: float
    fan_step_deg: float
    tilt_start_deg: float
    tilt_step_deg: float

    kind = "swept_fan"

    def directions(self, height: int, width: int) -> np.ndarray:
        fan = np.deg2rad(self.fan_start_deg + self.fan_step_deg * np.arange(width))[None, :]
        tilt = np.deg2rad(self.tilt_start_deg + self.tilt_step_deg * np.arange(height))[:, None]
        return np.stack(
            np.broadcast_arrays(np.cos(fan), -np.sin(fan) * np.sin(tilt), np.sin(fan) * np.cos(tilt)),
            axis=-1,
        ).astype(np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, **dataclasses.asdict(self)}


Projection = PinholeProjection | SweptFanProjection
_PROJECTIONS: dict[str, type] = {"pinhole": PinholeProjection, "swept_fan": SweptFanProjection}


@functools.lru_cache(maxsize=32)
def _cached_rays(projection: Projection, height: int, width: int) -> np.ndarray:
    directions = projection.directions(height, width)
    rays = (directions / np.linalg.norm(directions, axis=-1, keepdims=True)).astype(np.float32)
    rays.setflags(write=False)
    return rays


# --------------------------------------------------------------------------
# Range noise.
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class RangeNoiseModel:
    """Standard deviation of a range reading along its line of sight.

    ``sigma(r, I) = (floor + relative * r + quadratic * r**2) * gain(I)`` with
    ``gain(I) = max(1, (reference_intensity / I) ** intensity_exponent)``:
    returns darker than ``reference_intensity`` (normalised reflectance in
    [0, 1]) are noisier, as time-of-flight amplitude falls (Lange & Seitz
    2001: shot-noise limited, exponent 0.5). ``asymmetry`` is the ratio of the
    spread behind the surface to the spread in front of it (a zero-mean split
    normal); 1 is symmetric.

    The SwissRanger SR-3000 resolves about 1 % of range (thesis Chapter 2),
    hence ``relative=0.01`` in its preset.
    """

    relative: float = 0.0
    floor: float = 0.0
    quadratic: float = 0.0
    reference_intensity: float = 0.0
    intensity_exponent: float = 0.5
    asymmetry: float = 1.0

    def __post_init__(self) -> None:
        for name in ("relative", "floor", "quadratic", "reference_intensity", "intensity_exponent"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"noise {name} must be finite and >= 0, got {value}")
        if not (math.isfinite(self.asymmetry) and self.asymmetry > 0):
            raise ValueError(f"noise asymmetry must be > 0, got {self.asymmetry}")

    def sigma(self, range_m: np.ndarray, intensity: np.ndarray | None = None) -> np.ndarray:
        """Range standard deviation in metres, same shape as ``range_m``.

        Parameters
        ----------
        range_m : ndarray
            Ranges in metres (NaN propagates).
        intensity : ndarray, optional
            Normalised reflectance in [0, 1], same shape; ignored when the
            model has no ``reference_intensity``.
        """
        range_m = np.asarray(range_m)
        with_intensity = intensity is not None and self.reference_intensity > 0
        intensity = np.asarray(intensity) if with_intensity else range_m
        if range_m.ndim and range_m.dtype.kind == "f" and intensity.shape == range_m.shape and intensity.dtype.kind == "f":
            # One compiled pass (every frame asks twice; NumPy's ten temporaries took 0.1 ms at 176x144).
            return _noise_sigma(np.ascontiguousarray(range_m), np.ascontiguousarray(intensity), self.floor,
                                self.relative, self.quadratic, self.reference_intensity if with_intensity else 0.0,
                                self.intensity_exponent)
        range_m = range_m.astype(np.float64)
        sigma = self.floor + self.relative * range_m + self.quadratic * range_m**2
        if with_intensity:
            intensity = intensity.astype(np.float64)
            with np.errstate(divide="ignore", invalid="ignore"):
                gain = (self.reference_intensity / np.maximum(intensity, 1e-6)) ** self.intensity_exponent
            sigma = sigma * np.maximum(gain, 1.0)
        return sigma

    def split_normal_scales(self) -> tuple[float, float, float]:
        """``(near, far, offset)`` of the unit-variance, zero-mean split normal.

        A reading is ``true + sigma * (offset + z)`` with ``z`` drawn from a
        split normal of mode 0, spread ``near`` in front of and ``far``
        behind the mode.
        """
        ratio = self.asymmetry
        # Variance of a split normal: (1 - 2/pi) (s2 - s1)^2 + s1 s2.
        unit_variance = (1 - 2 / math.pi) * (ratio - 1) ** 2 + ratio
        near = 1.0 / math.sqrt(unit_variance)
        far = ratio * near
        offset = -math.sqrt(2 / math.pi) * (far - near)
        return near, far, offset


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _noise_sigma(range_m, intensity, floor, relative, quadratic, reference, exponent):  # pragma: no cover - compiled
    """`RangeNoiseModel.sigma` over same-shaped float arrays (``reference`` 0: no intensity gain), float64."""
    sigma = np.empty(range_m.shape)
    ranges, intensities, out = range_m.ravel(), intensity.ravel(), sigma.ravel()
    for k in range(ranges.size):
        r = np.float64(ranges[k])
        value = floor + relative * r + quadratic * (r * r)
        if reference > 0.0:
            brightness = np.float64(intensities[k])
            if math.isnan(brightness):
                value = math.nan
            else:
                ratio = reference / max(brightness, 1e-6)
                # sqrt for the usual shot-noise exponent: as NumPy's power does for 0.5, to the bit.
                gain = math.sqrt(ratio) if exponent == 0.5 else ratio**exponent
                if gain > 1.0:
                    value *= gain
        out[k] = value
    return sigma


# --------------------------------------------------------------------------
# Sensor model.
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorModel:
    """What a range sensor measures and how well.

    Parameters
    ----------
    name : str
        Short identifier (``"sr3000"``).
    width, height : int
        Grid size in cells; frames are ``(height, width)``.
    projection : PinholeProjection or SweptFanProjection or None
        Ray of each cell; ``None`` when rays come with each frame only
        (point grids of unknown origin).
    min_range, max_range : float
        Metres. ``max_range`` is the cut-off (non-ambiguity range of a ToF
        camera).
    frame_rate : float
        Frames per second.
    noise : RangeNoiseModel
        Range noise model.
    beyond_max_range : {"clamp", "invalid"}
        What the device reports past ``max_range``: the cut-off value itself
        (ToF cameras, the thesis's "reading equal to the threshold value"),
        or no return.
    description : str
        Human-readable description.
    """

    name: str
    width: int
    height: int
    projection: Projection | None
    min_range: float
    max_range: float
    frame_rate: float
    noise: RangeNoiseModel = field(default_factory=RangeNoiseModel)
    beyond_max_range: Literal["clamp", "invalid"] = "invalid"
    description: str = ""

    def __post_init__(self) -> None:
        if not (isinstance(self.width, int) and isinstance(self.height, int)) or self.width < 1 or self.height < 1:
            raise ValueError(f"sensor {self.name!r}: grid size must be positive integers, got {self.width}x{self.height}")
        if not (0 <= self.min_range < self.max_range):
            raise ValueError(
                f"sensor {self.name!r}: need 0 <= min_range < max_range, got {self.min_range}, {self.max_range}"
            )
        if not self.frame_rate > 0:
            raise ValueError(f"sensor {self.name!r}: frame_rate must be > 0, got {self.frame_rate}")
        if self.beyond_max_range not in ("clamp", "invalid"):
            raise ValueError(
                f"sensor {self.name!r}: beyond_max_range must be 'clamp' or 'invalid', got {self.beyond_max_range!r}"
            )

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape ``(height, width)``."""
        return (self.height, self.width)

    def rays(self) -> np.ndarray:
        """Unit viewing rays ``(H, W, 3)`` float32 (read-only, cached).

        Raises
        ------
        ValueError
            If the sensor has no projection model.
        """
        if self.projection is None:
            raise ValueError(f"sensor {self.name!r} has no projection model; its rays come with each frame")
        return _cached_rays(self.projection, self.height, self.width)

    def range_sigma(self, range_m: np.ndarray, intensity: np.ndarray | None = None) -> np.ndarray:
        """Range standard deviation (metres) per reading; see `RangeNoiseModel.sigma`."""
        return self.noise.sigma(range_m, intensity)

    def with_grid(self, height: int, width: int) -> SensorModel:
        """The same sensor on a different grid (projection dropped if the size changes)."""
        if (height, width) == self.shape:
            return self
        return dataclasses.replace(self, height=height, width=width, projection=None)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (JSON-safe) for saving beside frames."""
        out = dataclasses.asdict(self)
        out["projection"] = None if self.projection is None else self.projection.to_dict()
        if math.isinf(self.max_range):
            out["max_range"] = "inf"
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SensorModel:
        """Inverse of `to_dict`."""
        data = dict(data)
        projection = data.pop("projection", None)
        if projection is not None:
            projection = dict(projection)
            kind = projection.pop("kind", None)
            if kind not in _PROJECTIONS:
                raise ValueError(f"unknown projection kind {kind!r}; expected one of {sorted(_PROJECTIONS)}")
            projection = _PROJECTIONS[kind](**projection)
        noise = RangeNoiseModel(**data.pop("noise", {}))
        max_range = float(data.pop("max_range"))
        return cls(projection=projection, noise=noise, max_range=max_range, **data)


def unknown_sensor(height: int, width: int, *, name: str = "unknown") -> SensorModel:
    """A sensor model for grids of unknown origin: rays come from the data."""
    return SensorModel(
        name=name, width=width, height=height, projection=None,
        min_range=0.0, max_range=math.inf, frame_rate=1.0,
        description="range grid of unknown sensor; rays taken from the points",
    )


# Presets. Figures from the thesis (Chapter 2), the data sets' documentation
# (`shared/data/README.md`) and the sensors' data sheets.

SR3000 = SensorModel(
    name="sr3000",
    width=176,
    height=144,
    # 8 mm lens, 40 um pixels: f = 200 px, 47.5 x 39.6 deg field of view.
    projection=PinholeProjection(fx=200.0, fy=200.0, cx=87.5, cy=71.5),
    min_range=0.3,
    # Non-ambiguity range at the 20 MHz modulation frequency: c / (2 f).
    max_range=7.5,
    frame_rate=25.0,
    noise=RangeNoiseModel(relative=0.01, floor=0.002, reference_intensity=0.3, intensity_exponent=0.5, asymmetry=1.5),
    beyond_max_range="clamp",
    description="MESA SwissRanger SR-3000 time-of-flight camera (176x144, 25 fps, ~1% of range)",
)

UOS_LASER = SensorModel(
    name="uos-laser",
    width=360,
    height=226,
    # Measured from the 3DTK scans: 180 deg fans in 0.5 deg steps, tilted from
    # -48.7 deg to +67.6 deg over 226 lines.
    projection=SweptFanProjection(fan_start_deg=0.0, fan_step_deg=0.5, tilt_start_deg=-48.7, tilt_step_deg=116.3 / 225),
    min_range=0.2,
    # 3DTK's max-range marker: 3276.7 cm.
    max_range=32.767,
    frame_rate=0.1,
    noise=RangeNoiseModel(floor=0.01, relative=0.0),
    beyond_max_range="clamp",
    description="University of Osnabrueck swept SICK laser scanner of the 3DTK scans (360x226, 0.5 deg steps)",
)

KINECT = SensorModel(
    name="kinect",
    width=640,
    height=480,
    projection=PinholeProjection(fx=525.0, fy=525.0, cx=319.5, cy=239.5),
    min_range=0.5,
    max_range=8.0,
    frame_rate=30.0,
    # Structured light: depth noise grows with the square of range
    # (Khoshelham & Elberink 2012; Nguyen et al. 2012).
    noise=RangeNoiseModel(floor=0.0012, quadratic=0.0019),
    beyond_max_range="invalid",
    description="Kinect-class structured-light depth camera (640x480, 30 fps)",
)

CYBERWARE = SensorModel(
    name="cyberware",
    width=512,
    height=400,
    # The Cyberware 3030MS sweeps a laser sheet linearly (0.5 mm per column)
    # about 1.33 m from the object; a pinhole of matching footprint
    # approximates it. Its grids are stored bottom-up (fy < 0).
    projection=PinholeProjection(fx=2660.0, fy=-1810.0, cx=255.0, cy=225.0),
    min_range=1.1,
    max_range=1.6,
    frame_rate=1 / 17,
    noise=RangeNoiseModel(floor=1e-4),
    beyond_max_range="invalid",
    description="Cyberware 3030MS triangulation scanner of the Stanford bunny scans (512x400)",
)

SENSORS: dict[str, SensorModel] = {s.name: s for s in (SR3000, UOS_LASER, KINECT, CYBERWARE)}


def get_sensor(name: str | SensorModel) -> SensorModel:
    """Look up a sensor preset by name (``sr3000``, ``uos-laser``, ``kinect``, ``cyberware``)."""
    if isinstance(name, SensorModel):
        return name
    try:
        return SENSORS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown sensor {name!r}; expected one of {', '.join(SENSORS)}") from None


# --------------------------------------------------------------------------
# Range frame.
# --------------------------------------------------------------------------


def check_rigid_transform(transform: Any, what: str = "transform") -> np.ndarray:
    """Return ``transform`` as a ``(4, 4)`` float64 rigid transform or raise.

    Raises
    ------
    ValueError
        If it is not 4x4, not finite, its rotation is not orthonormal with
        determinant +1, or its last row is not ``[0, 0, 0, 1]``.
    """
    matrix = np.asarray(transform, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise ValueError(f"{what} must be a 4x4 matrix, got shape {matrix.shape}")
    # One compiled pass: every tracked, merged and carved frame comes here, and the NumPy checks (isfinite,
    # two max-abs, a product and a determinant) took 17 us hot, three times that in the pipeline.
    defect = _rigid_defect(matrix, _ROTATION_TOLERANCE)
    if defect == _NOT_FINITE:
        raise ValueError(f"{what} contains NaN or Inf")
    if defect == _NOT_AFFINE:
        raise ValueError(f"{what} last row must be [0, 0, 0, 1], got {matrix[3].tolist()}")
    if defect == _NOT_ROTATION:
        raise ValueError(f"{what} rotation part is not a proper rotation (orthonormal, det +1)")
    return matrix


_NOT_FINITE, _NOT_AFFINE, _NOT_ROTATION = 1, 2, 3


@numba.njit(cache=True, nogil=True)
def _rigid_defect(matrix, tolerance):  # pragma: no cover - compiled
    """What keeps a 4x4 ``matrix`` from being a rigid transform, checked in this order: 0 nothing,
    `_NOT_FINITE` (NaN or Inf), `_NOT_AFFINE` (last row off [0, 0, 0, 1] by more than 1e-9) or
    `_NOT_ROTATION` (R R^T off the identity by more than ``tolerance``, or det R < 0)."""
    for i in range(4):
        for j in range(4):
            if not math.isfinite(matrix[i, j]):
                return _NOT_FINITE
    for j in range(4):
        if abs(matrix[3, j] - (1.0 if j == 3 else 0.0)) > 1e-9:
            return _NOT_AFFINE
    for i in range(3):
        for j in range(3):
            product = matrix[i, 0] * matrix[j, 0] + matrix[i, 1] * matrix[j, 1] + matrix[i, 2] * matrix[j, 2]
            if abs(product - (1.0 if i == j else 0.0)) > tolerance:
                return _NOT_ROTATION
    determinant = (matrix[0, 0] * (matrix[1, 1] * matrix[2, 2] - matrix[1, 2] * matrix[2, 1])
                   - matrix[0, 1] * (matrix[1, 0] * matrix[2, 2] - matrix[1, 2] * matrix[2, 0])
                   + matrix[0, 2] * (matrix[1, 0] * matrix[2, 1] - matrix[1, 1] * matrix[2, 0]))
    return _NOT_ROTATION if determinant < 0.0 else 0


@dataclass(frozen=True, eq=False)
class RangeFrame:
    """One organized range scan.

    Parameters
    ----------
    rays : (H, W, 3) float32
        Unit viewing direction of every cell in the sensor frame.
    range : (H, W) float32
        Metres along the ray, NaN where there is no return.
    sensor : SensorModel
        The sensor; its grid matches ``range``.
    intensity : (H, W) float32, optional
        Return amplitude or reflectance, NaN where unknown.
    pose : (4, 4) float64, optional
        ``T_world_sensor``: initial guess (odometry) if known.
    timestamp : float
        Seconds.
    reference_pose : (4, 4) float64, optional
        ``T_world_sensor`` known independently (simulator ground truth, a
        data set's reference registration); for evaluation, never used by the
        pipeline itself.
    source : str
        Where the frame came from (file path), for messages.

    Raises
    ------
    ValueError
        If shapes disagree, rays are not unit vectors, ranges are infinite,
        zero or negative, or a pose is not a rigid transform.

    Examples
    --------
    >>> import numpy as np, rangesurf as rs
    >>> sensor = rs.get_sensor("sr3000")
    >>> frame = rs.RangeFrame(rays=sensor.rays(), range=np.full(sensor.shape, 2.0, np.float32), sensor=sensor)
    >>> frame.points.shape
    (144, 176, 3)
    """

    rays: np.ndarray
    range: np.ndarray
    sensor: SensorModel
    intensity: np.ndarray | None = None
    pose: np.ndarray | None = None
    timestamp: float = 0.0
    reference_pose: np.ndarray | None = None
    source: str = ""

    def __post_init__(self) -> None:
        where = f" ({self.source})" if self.source else ""
        range_image = np.asarray(self.range)
        if range_image.ndim != 2:
            raise ValueError(f"range image must be 2-D (H, W), got shape {range_image.shape}{where}")
        if not np.issubdtype(range_image.dtype, np.number):
            raise ValueError(f"range image must be numeric, got dtype {range_image.dtype}{where}")
        range_image = range_image.astype(np.float32, copy=False)
        shape = range_image.shape
        if np.isinf(range_image).any():
            raise ValueError(f"range image contains Inf; mark missing returns with NaN{where}")
        if (range_image <= 0).any():
            raise ValueError(
                f"range image has {(range_image <= 0).sum()} values <= 0; ranges must be positive or NaN{where}"
            )
        if shape != self.sensor.shape:
            raise ValueError(f"range image shape {shape} does not match sensor {self.sensor.name!r} grid {self.sensor.shape}{where}")

        rays = np.asarray(self.rays)
        if rays.shape != shape + (3,):
            raise ValueError(f"rays must have shape {shape + (3,)}, got {rays.shape}{where}")
        rays = rays.astype(np.float32, copy=False)
        # einsum: np.linalg.norm over a length-3 last axis is several times slower.
        squared_norms = np.einsum("...i,...i->...", rays, rays)
        if not np.all(np.abs(squared_norms - 1) < 2 * _RAY_NORM_TOLERANCE):
            worst = np.sqrt(squared_norms.flat[np.nanargmax(np.abs(squared_norms - 1))]) if np.isfinite(squared_norms).any() else np.nan
            raise ValueError(f"rays must be finite unit vectors; worst norm {worst:.4g}{where}")

        intensity = self.intensity
        if intensity is not None:
            intensity = np.asarray(intensity)
            if intensity.shape != shape:
                raise ValueError(f"intensity shape {intensity.shape} does not match range shape {shape}{where}")
            intensity = intensity.astype(np.float32, copy=False)
            if np.isinf(intensity).any():
                raise ValueError(f"intensity contains Inf{where}")

        pose = None if self.pose is None else check_rigid_transform(self.pose, f"pose{where}")
        reference = None if self.reference_pose is None else check_rigid_transform(self.reference_pose, f"reference_pose{where}")
        if not math.isfinite(float(self.timestamp)):
            raise ValueError(f"timestamp must be finite, got {self.timestamp}{where}")

        object.__setattr__(self, "range", range_image)
        object.__setattr__(self, "rays", rays)
        object.__setattr__(self, "intensity", intensity)
        object.__setattr__(self, "pose", pose)
        object.__setattr__(self, "reference_pose", reference)
        object.__setattr__(self, "timestamp", float(self.timestamp))

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape ``(H, W)``."""
        return self.range.shape

    @property
    def valid(self) -> np.ndarray:
        """``(H, W)`` bool, True where there is a return."""
        return np.isfinite(self.range)

    @property
    def points(self) -> np.ndarray:
        """``(H, W, 3)`` float32 points in the sensor frame, NaN where invalid."""
        return self.rays * self.range[..., None]

    def world_points(self, *, use_reference: bool = False) -> np.ndarray:
        """``(N, 3)`` float64 valid points in the world frame.

        Uses ``pose`` (or ``reference_pose`` when ``use_reference``); raises
        if that pose is unknown.
        """
        transform = self.reference_pose if use_reference else self.pose
        if transform is None:
            which = "reference_pose" if use_reference else "pose"
            raise ValueError(f"frame{' ' + self.source if self.source else ''} has no {which}")
        points = self.points[self.valid].astype(np.float64)
        return points @ transform[:3, :3].T + transform[:3, 3]

    def replace(self, **changes: Any) -> RangeFrame:
        """A copy with some fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_points(
        cls,
        points: np.ndarray,
        *,
        sensor: SensorModel | None = None,
        intensity: np.ndarray | None = None,
        pose: np.ndarray | None = None,
        timestamp: float = 0.0,
        reference_pose: np.ndarray | None = None,
        source: str = "",
    ) -> RangeFrame:
        """Build a frame from an organized point grid in the sensor frame.

        Parameters
        ----------
        points : (H, W, 3) array
            Points in metres; rows with any NaN (or all-zero points) are no
            return.
        sensor : SensorModel, optional
            Defaults to `unknown_sensor` of the grid's size.

        Rays of cells without a return come from the sensor's projection
        when it has one, otherwise from the nearest cell with a return.
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 3 or points.shape[2] != 3:
            raise ValueError(f"points must have shape (H, W, 3), got {points.shape}{' (' + source + ')' if source else ''}")
        height, width = points.shape[:2]
        sensor = sensor or unknown_sensor(height, width)
        with np.errstate(invalid="ignore"):
            range_image = np.linalg.norm(points, axis=-1)
            valid = np.isfinite(range_image) & (range_image > 0)
            rays = np.where(valid[..., None], points / np.where(valid, range_image, 1.0)[..., None], np.nan)
        rays = _fill_missing_rays(rays, valid, sensor)
        range_image = np.where(valid, range_image, np.nan).astype(np.float32)
        return cls(
            rays=rays, range=range_image, sensor=sensor, intensity=intensity, pose=pose,
            timestamp=timestamp, reference_pose=reference_pose, source=source,
        )


def _fill_missing_rays(rays: np.ndarray, valid: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """Give every cell without a return a plausible unit ray."""
    if valid.all():
        return rays.astype(np.float32)
    if sensor.projection is not None:
        return np.where(valid[..., None], rays, sensor.rays()).astype(np.float32)
    if not valid.any():
        filled = np.zeros(rays.shape, np.float32)
        filled[..., 2] = 1.0
        return filled
    from scipy import ndimage

    # Nearest cell with a return: a grid's rays vary smoothly across it.
    _, (nearest_rows, nearest_cols) = ndimage.distance_transform_edt(~valid, return_indices=True)
    return rays[nearest_rows, nearest_cols].astype(np.float32)
