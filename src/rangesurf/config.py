"""Settings of the pipeline: one frozen dataclass per stage, all defaults here, TOML in and out.

`PipelineConfig` holds one section per stage; a stage function never sees
the whole config (the pipeline unpacks it). Defaults that depend on the
data -- the model's cell size, the frame time budget -- are ``None`` here and
filled in one place, `Pipeline`, from the first frame's sensor.

Examples
--------
>>> config = PipelineConfig.from_dict({"denoise": {"method": "phase"}, "merge": {"cell_size": 0.02}})
>>> config.denoise.method, config.merge.cell_size, config.register.keyframe_distance
('phase', 0.02, 0.3)
>>> PipelineConfig.from_dict({"merge": {"cell_sise": 0.02}})
Traceback (most recent call last):
...
rangesurf.config.ConfigError: config: unknown key 'merge.cell_sise'; the merge section has: bridge, carve_every, cell_size, fold_every, max_normal_angle, max_plane_distance, min_overlap, nonplanar, stride, volume, voxel_size
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rangesurf.io._common import atomic_write

__all__ = [
    "ConfigError", "PipelineConfig", "DenoiseSettings", "SegmentSettings", "RegisterSettings", "MergeSettings",
    "MeshSettings", "RunSettings",
]


class ConfigError(ValueError):
    """A configuration file or dictionary that does not fit `PipelineConfig` (names the key)."""


@dataclass(frozen=True)
class DenoiseSettings:
    """`rangesurf.denoise.denoise_range`: ``method`` one of diffusion, layered, phase, none.

    ``remove_bias``: take diffusion's systematic error out of the vertices
    merged into the model (`rangesurf.denoise.diffusion.remove_diffusion_bias`);
    None: on frames under 200,000 pixels. It costs 0.2-0.3 ms at 176x144 and
    4-5 ms at 640x480, where the error is far smaller (it grows with the
    square of the angle between neighbouring pixels) and the model's UL1
    holds 98 % of its error without it.
    """

    method: str = "diffusion"
    remove_bias: bool | None = None


@dataclass(frozen=True)
class SegmentSettings:
    """`rangesurf.segment`: ``segmenter`` "region" (region growing) or "nxd" (the thesis's NxD clustering)."""

    segmenter: str = "region"


@dataclass(frozen=True)
class RegisterSettings:
    """`rangesurf.register.FrameTracker`.

    ``decimate``: register on every n-th row and column (None: from 200,000
    pixels on, the grid segmentation grows on -- 3 at 640x480 -- else 1):
    ICP needs far fewer points than a depth camera gives. ``icp_variance_scale``: how much ICP's independent-residual
    covariance understates its error (see `FrameTracker`). ``keyframe_overlap_loss``: a new keyframe once the share
    of points ICP pairs has dropped this much (see `FrameTracker`).
    ``odometry_sigma_rotation`` (radians) and ``odometry_sigma_translation``
    (metres): the odometry's error per frame and axis at a standstill, plus
    ``odometry_sigma_relative`` times the step's own angle and length.
    ``align_to_model_every``: every n-th frame's pose is corrected by its
    planes' fit to the model (`GlobalModel.align`: revisited places pull a
    drifted pose back); 0 switches it off.
    """

    max_correspondence_distance: float = 0.1
    odometry_sigma_rotation: float = 0.01
    odometry_sigma_translation: float = 0.003
    odometry_sigma_relative: float = 0.1
    keyframe_distance: float = 0.3
    keyframe_angle: float = 10.0
    keyframe_overlap_loss: float = 0.10
    decimate: int | None = None
    icp_variance_scale: float = 26.0
    align_to_model_every: int = 10


@dataclass(frozen=True)
class MergeSettings:
    """`rangesurf.merge.GlobalModel`.

    ``cell_size`` None: twice the first frame's median pixel footprint, at
    least 1 cm. ``stride``: merge every n-th row and column of a frame (None: as
    many pixels as fall into a cell are skipped, about one per cell; between
    strides 1 and 2, every other pixel of a checkerboard where that is
    nearer, `rangesurf.pipeline._stride_and_checkerboard`).
    ``volume``: the volumetric (TSDF) path, `rangesurf.merge.TSDFVolume`:
    "off", "unsegmented" (the pixels in no planar segment: objects that are
    not planes) or "all" (every pixel: a scanned object like the bunny);
    ``voxel_size`` None: the cell size. ``carve_every``: every n-th frame
    removes the model's cells it sees through (`GlobalModel.carve`: copies
    built while the pose had slipped, objects that moved away); 0 switches
    it off. ``fold_every``: every n-th frame folds patches that a larger
    one has grown over into it (`GlobalModel.fold_fragments`); 0 switches
    it off.
    """

    cell_size: float | None = None
    max_normal_angle: float = 10.0
    max_plane_distance: float | None = None
    bridge: int = 1
    min_overlap: int = 3
    nonplanar: str = "keep"
    stride: int | None = None
    volume: str = "off"
    voxel_size: float | None = None
    carve_every: int = 10
    fold_every: int = 50


@dataclass(frozen=True)
class MeshSettings:
    """Per-frame surfaces (`rangesurf.mesh.triangulate_segments`).

    ``frame_surfaces``: triangulate every frame's segments for its
    `FrameResult` (the model does not need them: it meshes its patches).
    """

    frame_surfaces: bool = False
    max_edge_pixels: float = 4.0
    max_view_angle: float = 85.0


@dataclass(frozen=True)
class RunSettings:
    """The online loop.

    ``budget_ms`` None: the sensor's frame period. ``remesh_every``: frames
    between re-meshing the changed patches with their level-of-detail order
    (deferrable work; always done at the end); None: every 25 frames while a
    viewer shows the model (`Pipeline.live_meshes`), otherwise only at the
    end, since nothing looks at the meshes before. ``checkpoint_every``: frames
    between atomic checkpoints of the model (0: none). ``on_bad_frame``:
    "skip" (report it and go on) or "stop" (save what was merged and stop).
    ``release_memory_every``: frames between handing the memory that
    temporaries freed back to the system (glibc's ``malloc_trim``; deferrable
    work), so that a long run's resident memory follows what it holds, not
    its peaks; 0: never.
    """

    budget_ms: float | None = None
    remesh_every: int | None = None
    checkpoint_every: int = 25
    on_bad_frame: str = "skip"
    release_memory_every: int = 100


@dataclass(frozen=True)
class PipelineConfig:
    """All settings of a run (saved beside its results as ``config.toml``)."""

    denoise: DenoiseSettings = field(default_factory=DenoiseSettings)
    segment: SegmentSettings = field(default_factory=SegmentSettings)
    register: RegisterSettings = field(default_factory=RegisterSettings)
    merge: MergeSettings = field(default_factory=MergeSettings)
    mesh: MeshSettings = field(default_factory=MeshSettings)
    run: RunSettings = field(default_factory=RunSettings)

    def __post_init__(self) -> None:
        _check_choice("denoise.method", self.denoise.method, ("diffusion", "layered", "phase", "none"))
        _check_choice("segment.segmenter", self.segment.segmenter, ("region", "nxd"))
        _check_choice("merge.nonplanar", self.merge.nonplanar, ("keep", "drop"))
        _check_choice("merge.volume", self.merge.volume, ("off", "unsegmented", "all"))
        _check_choice("run.on_bad_frame", self.run.on_bad_frame, ("skip", "stop"))
        for name in ("register.max_correspondence_distance", "register.odometry_sigma_rotation",
                     "register.odometry_sigma_translation", "register.icp_variance_scale", "merge.max_normal_angle", "mesh.max_edge_pixels",
                     "mesh.max_view_angle"):
            _check_positive(name, self._get(name))
        for name in ("merge.cell_size", "merge.max_plane_distance", "merge.voxel_size", "run.budget_ms"):
            if self._get(name) is not None:
                _check_positive(name, self._get(name))
        for name in ("register.decimate", "merge.stride"):
            value = self._get(name)
            if value is not None and value < 1:
                raise ConfigError(f"config: {name} must be >= 1 or unset, got {value}")
        for name in ("register.keyframe_distance", "register.keyframe_angle", "register.align_to_model_every",
                     "register.odometry_sigma_relative",
                     "merge.carve_every", "merge.fold_every", "run.remesh_every", "run.checkpoint_every", "run.release_memory_every",
                     "merge.bridge"):
            if self._get(name) is not None and self._get(name) < 0:
                raise ConfigError(f"config: {name} must be >= 0, got {self._get(name)}")
        if not 0 <= self.register.keyframe_overlap_loss <= 1:
            raise ConfigError(f"config: register.keyframe_overlap_loss must be between 0 and 1, got "
                              f"{self.register.keyframe_overlap_loss}")
        if self.merge.min_overlap < 1:
            raise ConfigError(f"config: merge.min_overlap must be >= 1, got {self.merge.min_overlap}")

    def _get(self, dotted: str) -> Any:
        section, key = dotted.split(".")
        return getattr(getattr(self, section), key)

    # ------------------------------------------------------------------
    # Dictionaries and TOML.
    # ------------------------------------------------------------------

    @classmethod
    def from_dict(cls, values: dict[str, Any], *, source: str = "config") -> PipelineConfig:
        """Build from nested ``{section: {key: value}}``; unknown keys and wrong types are errors naming the key."""
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: expected a table of sections, got {type(values).__name__}")
        sections = {section.name: section for section in dataclasses.fields(cls)}
        built = {}
        for name, table in values.items():
            if name not in sections:
                raise ConfigError(f"{source}: unknown section {name!r}; expected one of {', '.join(sections)}")
            if not isinstance(table, dict):
                raise ConfigError(f"{source}: section {name!r} must be a table, got {type(table).__name__}")
            settings_type = _resolve(sections[name].type)
            keys = {item.name: item for item in dataclasses.fields(settings_type)}
            converted = {}
            for key, value in table.items():
                if key not in keys:
                    raise ConfigError(f"{source}: unknown key '{name}.{key}'; the {name} section has: "
                                      f"{', '.join(sorted(keys))}")
                converted[key] = _convert(f"{source}: {name}.{key}", value, keys[key].type)
            built[name] = settings_type(**converted)
        return cls(**built)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)

    @classmethod
    def load(cls, path: str | os.PathLike) -> PipelineConfig:
        """Read a TOML file (sections as in `to_toml`; missing keys keep their defaults)."""
        path = Path(path)
        try:
            values = tomllib.loads(path.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as error:
            raise ConfigError(f"{path}: not valid TOML ({error})") from None
        return cls.from_dict(values, source=str(path))

    def to_toml(self) -> str:
        """The whole configuration as TOML; unset (automatic) values are written as comments."""
        lines = ["# rangesurf pipeline configuration", ""]
        for section, table in self.to_dict().items():
            lines.append(f"[{section}]")
            for key, value in table.items():
                lines.append(f"# {key} = (automatic)" if value is None else f"{key} = {_toml_value(value)}")
            lines.append("")
        return "\n".join(lines)

    def save(self, path: str | os.PathLike) -> None:
        """Write `to_toml` atomically."""
        with atomic_write(path, "w") as stream:
            stream.write(self.to_toml())


def _resolve(annotation: Any) -> Any:
    """Field annotations are strings (``from __future__ import annotations``); evaluate them here."""
    if isinstance(annotation, str):
        return eval(annotation, globals())  # noqa: S307 - our own dataclass annotations only
    return annotation


def _convert(name: str, value: Any, annotation: Any) -> Any:
    annotation = _resolve(annotation)
    allowed = typing.get_args(annotation) if isinstance(annotation, types.UnionType) else (annotation,)
    if value is None and type(None) in allowed:
        return None
    for kind in allowed:
        if kind is bool and isinstance(value, bool):
            return value
        if kind is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if kind is str and isinstance(value, str):
            return value
    expected = " or ".join(kind.__name__ for kind in allowed if kind is not type(None))
    raise ConfigError(f"{name} must be {expected}, got {value!r}")


def _check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"config: {name} must be one of {', '.join(choices)}, got {value!r}")


def _check_positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"config: {name} must be a finite number > 0, got {value!r}")


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)
