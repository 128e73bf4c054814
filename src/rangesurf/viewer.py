"""Live and offline 3D viewer of the surface model and its uncertainty (viser, in the browser).

A `Viewer` serves a page (viser: https://viser.studio) showing the global
model growing frame by frame, each surface at a level of detail chosen by a
slider or automatically from the browser's camera (the screen-space rule of
`rangesurf.lod.view_level`: no two vertices in one pixel), and its
uncertainty drawn by one of the thesis's methods (Section 3.4, `METHODS`,
built by `rangesurf.glyphs`) for any subset of the levels UL1..UL4, either
cumulatively (one quantity, the root sum of squares) or separately (one
glyph and colour per level). Beside the scene: the current range image, its
edges and its segments, a per-stage timing plot, and a button that saves
the scene as a ``.viser`` file (replayable offline with viser's client).

Live use follows the pipeline's rule "no visualization branches": the main
job passes a viewer object in and calls ``viewer.update(result, pipeline)``
after every frame and ``viewer.finish(surfaces)`` at the end; a
`NullViewer` stands in when nothing is shown. ``update`` only takes
references (the frame's arrays, which the pipeline does not modify
afterwards, and -- at most every ``mesh_interval`` seconds -- the model's
already meshed patches); converting, levels of detail, glyphs and sending
happen on the viewer's own thread, which always draws the newest state and
skips what it could not draw in time. So the pipeline is never slowed by
more than the few tenths of a millisecond of ``update``.

Offline, `view_model` serves the outputs of a run (``model.ply`` and,
when present, ``trajectory.txt``, ``metrics.json``, ``timings.csv``) and
reads nothing else: each name is resolved and refused when it leads out of
the model folder (``..``, absolute names, symbolic links).

The server binds to 127.0.0.1 unless another ``host`` is given explicitly.
Values that come from the browser are checked in every GUI callback; a
value out of range is logged and ignored (the control snaps back), and no
callback raises into viser.

References
----------
.. [1] The reference thesis, Section 3.4 and Figures 3.10-3.13 (``shared/reference/thesis.md``).
.. [2] B. Yi et al., "Viser: Imperative, Web-based 3D Visualization in
   Python", arXiv:2507.22885, 2025.

Examples
--------
>>> from rangesurf import simulate
>>> from rangesurf.pipeline import Pipeline
>>> frames, _ = simulate.simulate_sequence("arena", "sr3000", 3, seed=0)
>>> pipeline = Pipeline()
>>> with Viewer(port=0) as viewer:                                    # doctest: +SKIP
...     for frame in frames:
...         viewer.update(pipeline.process(frame), pipeline)
...     viewer.finish(pipeline.finish())
...     print(viewer.url)
"""

from __future__ import annotations

import csv
import json
import logging
import math
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rangesurf.mesh import UNCERTAINTY_LEVELS, Surface

if TYPE_CHECKING:  # pragma: no cover
    from rangesurf.pipeline import FrameResult, Pipeline

__all__ = ["Viewer", "NullViewer", "ViewSettings", "ModelFiles", "view_model", "load_model", "model_file",
           "METHODS", "COMBINATIONS", "MODEL_FILES", "SCENE_FILE"]

log = logging.getLogger(__name__)

METHODS = ("none", "colour", "opacity", "points", "bars", "shells", "volume", "cones", "perturbation", "oscillation")
COMBINATIONS = ("cumulative", "separate")
# What `view_model` reads from a run's folder, and what the "save .viser" button writes there.
MODEL_FILES = ("model.ply", "trajectory.txt", "metrics.json", "timings.csv")
SCENE_FILE = "model.viser"

_LOD_RANGE = (0.01, 1.0)
_SCALE_RANGE = (0.5, 20.0)
_NEUTRAL = (176, 186, 198)  # the surface itself when the uncertainty is drawn beside it
_TIMING_FRAMES = 250  # frames shown in the timing plot
_CAMERA_INTERVAL = 0.2  # seconds between automatic-LOD re-evaluations while the camera moves
_OSCILLATION_INTERVAL = 0.1  # seconds between the frames of the oscillation animation
_OSCILLATION_PERIOD = 2.0  # seconds per oscillation
_STAGE_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#17becf")


def _require_viser():
    try:
        import viser
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError("the viewer needs viser: pip install 'rangesurf[viewer]'") from error
    return viser


# --------------------------------------------------------------------------
# Settings.
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ViewSettings:
    """What the viewer shows; the GUI edits a copy, checked field by field (`checked`).

    Parameters
    ----------
    lod_fraction : float
        Fraction of each surface's vertices shown, in [0.01, 1] (the coarsest
        precomputed level with at least that many).
    automatic_lod : bool
        Choose each surface's level from the browser's camera instead
        (`rangesurf.lod.view_level`).
    levels : tuple of str
        Uncertainty levels drawn, a subset of ``("UL1", "UL2", "UL3", "UL4")``.
    method : str
        One of `METHODS`.
    combination : {"cumulative", "separate"}
        The chosen levels as one quantity (root sum of squares) or one glyph
        (and colour, `rangesurf.glyphs.LEVEL_COLOURS`) per level.
    scale : float
        Glyph size in standard deviations, in [0.5, 20].
    """

    lod_fraction: float = 1.0
    automatic_lod: bool = False
    levels: tuple[str, ...] = UNCERTAINTY_LEVELS
    method: str = "colour"
    combination: str = "cumulative"
    scale: float = 2.0

    def checked(self) -> ViewSettings:
        """The same settings, or ValueError naming the first bad field."""
        if not (isinstance(self.lod_fraction, (int, float)) and not isinstance(self.lod_fraction, bool)
                and _LOD_RANGE[0] <= self.lod_fraction <= _LOD_RANGE[1]):
            raise ValueError(f"lod_fraction must be a number in {list(_LOD_RANGE)}, got {self.lod_fraction!r}")
        if not isinstance(self.automatic_lod, bool):
            raise ValueError(f"automatic_lod must be a bool, got {self.automatic_lod!r}")
        if not isinstance(self.levels, tuple) or any(level not in UNCERTAINTY_LEVELS for level in self.levels) \
                or len(set(self.levels)) != len(self.levels):
            raise ValueError(f"levels must be distinct names out of {UNCERTAINTY_LEVELS}, got {self.levels!r}")
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.combination not in COMBINATIONS:
            raise ValueError(f"combination must be one of {COMBINATIONS}, got {self.combination!r}")
        if not (isinstance(self.scale, (int, float)) and not isinstance(self.scale, bool)
                and _SCALE_RANGE[0] <= self.scale <= _SCALE_RANGE[1]):
            raise ValueError(f"scale must be a number in {list(_SCALE_RANGE)} (standard deviations), got {self.scale!r}")
        return self


@dataclass
class _Camera:
    """A browser camera: world pose (OpenCV axes: x right, y down, z forward) and pinhole intrinsics."""

    T_world_camera: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass
class _Entry:
    """One drawn surface: its source (for change detection), the surface with levels, its scene nodes."""

    name: str
    source: Surface
    surface: Surface
    nodes: dict[str, Any] = field(default_factory=dict)
    count: int = -1  # vertices of the level drawn


@dataclass
class _Frame:
    index: int
    range: np.ndarray
    labels: np.ndarray


# --------------------------------------------------------------------------
# The do-nothing stand-in.
# --------------------------------------------------------------------------


class NullViewer:
    """A viewer that shows nothing: what the main job uses when no viewer is asked for (KISS-ICP's StubVisualizer).

    Examples
    --------
    >>> viewer = NullViewer()
    >>> viewer.update(None, None); viewer.finish([]); viewer.close()
    """

    def update(self, result: FrameResult, pipeline: Pipeline) -> None:
        """Do nothing."""

    def finish(self, surfaces: list[Surface]) -> None:
        """Do nothing."""

    def flush(self, timeout: float = 10.0) -> bool:
        """Nothing pending: True."""
        return True

    def close(self) -> None:
        """Do nothing."""

    def __enter__(self) -> NullViewer:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


# --------------------------------------------------------------------------
# The viewer.
# --------------------------------------------------------------------------


class Viewer:
    """A browser viewer of the model, its uncertainty and the pipeline's progress (viser server).

    Parameters
    ----------
    host : str
        Interface to bind; ``"127.0.0.1"`` (this machine only) unless
        another is given explicitly (``"0.0.0.0"``: every interface).
    port : int
        TCP port; 0 picks a free one. viser tries the following ports when
        it is taken; `port` tells the one bound.
    folder : path-like, optional
        Where "save .viser" (and `finish`) write ``model.viser``; without
        it the button is not shown and `finish` writes nothing.
    settings : ViewSettings, optional
        Initial settings.
    mesh_interval : float
        Seconds between two looks at the model's meshes during a run (the
        images and the timing plot follow every frame the viewer's thread
        keeps up with).
    verbose : bool
        Let viser log connections.

    Attributes
    ----------
    stats : dict of str -> int or float
        ``updates`` (calls to `update`), ``frames_drawn`` (frames whose
        images and timings were sent), ``mesh_snapshots`` (looks at the
        model), ``surfaces_drawn`` (surface renderings sent), and
        ``busy_seconds`` (CPU time of the viewer's thread).

    Examples
    --------
    >>> viewer = Viewer(port=0)                                          # doctest: +SKIP
    >>> viewer.host, viewer.url.startswith("http://127.0.0.1:")          # doctest: +SKIP
    ('127.0.0.1', True)
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 8080, folder: str | Path | None = None,
                 settings: ViewSettings | None = None, mesh_interval: float = 0.5, verbose: bool = False) -> None:
        if not isinstance(host, str) or not host:
            raise ValueError(f"host must be a non-empty string, got {host!r}")
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"port must be an integer in [0, 65535], got {port!r}")
        if not (isinstance(mesh_interval, (int, float)) and mesh_interval >= 0):
            raise ValueError(f"mesh_interval must be >= 0 seconds, got {mesh_interval!r}")
        self.settings = (settings or ViewSettings()).checked()
        self.folder = None if folder is None else Path(folder)
        self.mesh_interval = float(mesh_interval)
        self.stats = {"updates": 0, "frames_drawn": 0, "mesh_snapshots": 0, "surfaces_drawn": 0, "busy_seconds": 0.0}
        viser = _require_viser()
        # viser's own default is every interface; ours is this machine only.
        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.host = host
        self.port = int(self.server.get_port())

        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._closing = False
        self._busy = False
        # Handed from the caller's thread to the viewer's thread (under the lock).
        self._pending_frame: _Frame | None = None
        self._pending_surfaces: dict[str, Surface] | None = None
        self._pending_trajectory = False
        self._redraw_all = False
        self._camera: _Camera | None = None
        self._camera_changed = False
        self._timings: deque[tuple[int, dict[str, float]]] = deque(maxlen=_TIMING_FRAMES)
        self._positions: list[np.ndarray] = []
        self._last_pose: np.ndarray | None = None
        self._last_snapshot = -math.inf
        self._placed_camera = False
        # Owned by the viewer's thread.
        self._entries: dict[str, _Entry] = {}
        self._vmax = 0.01
        self._stages: tuple[str, ...] = ()

        self._build_gui()
        self.server.on_client_connect(self._on_client_connect)
        self._thread = threading.Thread(target=self._run, name="rangesurf-viewer", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------
    # Public interface.
    # ------------------------------------------------------------------

    @property
    def url(self) -> str:
        """The page to open in a browser."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::") else self.host
        return f"http://{'[' + host + ']' if ':' in host else host}:{self.port}"

    @property
    def n_surfaces(self) -> int:
        """Surfaces drawn in the scene now."""
        return len(self._entries)

    def update(self, result: FrameResult, pipeline: Pipeline) -> None:
        """Take one processed frame (cheap: references only; drawing happens on the viewer's thread).

        Parameters
        ----------
        result : FrameResult
            From ``pipeline.process``: its denoised range, segmentation,
            timings and pose are shown.
        pipeline : Pipeline
            Its model's meshed patches are looked at every ``mesh_interval``
            seconds; only surfaces that changed are sent again.
        """
        self.stats["updates"] += 1
        now = time.perf_counter()
        snapshot = None
        if now - self._last_snapshot >= self.mesh_interval:
            self._last_snapshot = now
            snapshot = pipeline.model.meshed_surfaces()
        with self._lock:
            self._pending_frame = _Frame(result.index, result.range, result.segmentation.labels)
            self._timings.append((result.index, dict(result.timings)))
            pose = np.asarray(result.T_world_sensor, dtype=np.float64)
            self._positions.append(pose[:3, 3].copy())
            self._last_pose = pose
            self._pending_trajectory = True
            if snapshot is not None:
                self._pending_surfaces = snapshot
            self._wake.notify()

    def finish(self, surfaces: list[Surface]) -> None:
        """Show the final surfaces (replacing the live model), wait until drawn, and save the scene when a folder is set."""
        self.show_surfaces(surfaces)
        self.flush(timeout=120.0)
        if self.folder is not None:
            try:
                self.save_scene()
            except OSError as error:
                log.warning("could not save the scene into %s: %s", self.folder, error)

    def show_surfaces(self, surfaces: list[Surface]) -> None:
        """Replace the drawn model by ``surfaces`` (world frame); drawn on the viewer's thread."""
        snapshot = {f"s{index}": surface for index, surface in enumerate(surfaces) if isinstance(surface, Surface)}
        with self._lock:
            self._pending_surfaces = snapshot
            self._pending_trajectory = bool(self._positions)
            self._wake.notify()

    def show_trajectory(self, poses: np.ndarray) -> None:
        """Draw a trajectory ``(N, 4, 4)`` of ``T_world_sensor`` (offline; live runs add their poses themselves)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        with self._lock:
            self._positions = [pose[:3, 3].copy() for pose in poses]
            self._last_pose = poses[-1] if len(poses) else None
            self._pending_trajectory = True
            self._wake.notify()

    def show_timings(self, rows: list[dict[str, float]]) -> None:
        """Plot per-frame timings (rows with ``frame`` and a millisecond column per stage)."""
        with self._lock:
            for row in rows[-_TIMING_FRAMES:]:
                self._timings.append((int(row.get("frame", len(self._timings))),
                                      {key: float(value) for key, value in row.items() if key != "frame"}))
            self._pending_frame = self._pending_frame or _Frame(-1, np.zeros((0, 0), np.float32), np.zeros((0, 0), np.int32))
            self._wake.notify()

    def save_scene(self, path: str | Path | None = None, *, html: bool = True) -> Path:
        """Write the scene as it is now to a ``.viser`` file (and a page that shows it offline), atomically.

        Parameters
        ----------
        path : path-like, optional
            Default ``folder / "model.viser"``; it must lie inside ``folder``
            when one is set.
        html : bool
            Also write the same scene as a self-contained page beside it
            (``model.html``: viser's client with the scene inside; opens
            from disk in any browser with WebGL, no server).

        Returns
        -------
        Path
            The ``.viser`` file (viser's recording format, for viser's own
            playback and embedding tools).
        """
        from rangesurf.io import atomic_write

        if path is None:
            if self.folder is None:
                raise ValueError("no folder to save the scene into; pass a path")
            path = model_file(self.folder, SCENE_FILE, must_exist=False)
        elif self.folder is not None:
            path = Path(path)
            if path.parent.resolve() != self.folder.resolve():
                raise PermissionError(f"{path}: the scene is saved into the model folder {self.folder} only")
            path = model_file(self.folder, path.name, must_exist=False)
        path = Path(path)
        page = path.with_suffix(".html")
        if html and self.folder is not None:
            page = model_file(self.folder, page.name, must_exist=False)
        # One snapshot per file: a serializer can be serialized once.
        data = self.server.get_scene_serializer().serialize()
        with atomic_write(path, "wb") as stream:
            stream.write(data)
        if html:
            text = self.server.get_scene_serializer().as_html()
            with atomic_write(page, "w") as stream:
                stream.write(text)
        return path

    def flush(self, timeout: float = 10.0) -> bool:
        """Wait until everything handed over is drawn; False if ``timeout`` seconds passed first."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while self._pending_frame is not None or self._pending_surfaces is not None or self._pending_trajectory \
                    or self._redraw_all or self._busy:
                left = deadline - time.monotonic()
                if left <= 0 or self._closing:
                    return False
                self._wake.wait(min(left, 0.05))
        return True

    def apply(self, settings: ViewSettings) -> None:
        """Change what is shown (as the GUI does); the GUI controls follow."""
        settings = settings.checked()
        with self._lock:
            self.settings = settings
            self._redraw_all = True
            self._wake.notify()
        self._sync_gui(settings)

    def close(self) -> None:
        """Stop the viewer's thread and the server."""
        with self._lock:
            if self._closing:
                return
            self._closing = True
            self._wake.notify_all()
        self._thread.join(timeout=5.0)
        self.server.stop()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # ------------------------------------------------------------------
    # GUI.
    # ------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.server.gui
        settings = self.settings
        with gui.add_folder("Level of detail"):
            self._gui_lod = gui.add_slider("LOD fraction", min=_LOD_RANGE[0], max=_LOD_RANGE[1], step=0.01,
                                           initial_value=settings.lod_fraction)
            self._gui_auto = gui.add_checkbox("automatic LOD", settings.automatic_lod,
                                              hint="level per surface from the camera: no two vertices in one pixel")
        with gui.add_folder("Uncertainty"):
            self._gui_levels = {level: gui.add_checkbox(level, level in settings.levels, hint=hint) for level, hint in
                                zip(UNCERTAINTY_LEVELS, ("sensor noise", "patch fit", "registration and merging", "level of detail"))}
            self._gui_method = gui.add_dropdown("method", METHODS, initial_value=settings.method)
            self._gui_combination = gui.add_dropdown("levels shown", COMBINATIONS, initial_value=settings.combination)
            self._gui_scale = gui.add_slider("glyph scale (sigma)", min=_SCALE_RANGE[0], max=_SCALE_RANGE[1], step=0.5,
                                             initial_value=settings.scale)
        self._gui_save = None
        if self.folder is not None:
            self._gui_save = gui.add_button("save .viser", hint=f"write {SCENE_FILE} (and model.html) into {self.folder}")
            self._gui_save.on_click(self._guarded(self._on_save))
        # Hidden until a frame arrives (a saved model has none).
        self._gui_frame = gui.add_folder("Current frame", visible=False)
        with self._gui_frame:
            blank = np.zeros((8, 8, 3), np.uint8)
            self._gui_range = gui.add_image(blank, label="range", format="jpeg")
            self._gui_edges = gui.add_image(blank, label="edges", format="jpeg")
            self._gui_segments = gui.add_image(blank, label="segments", format="jpeg")
        self._gui_timings = gui.add_folder("Timings")
        with self._gui_timings:
            self._gui_plot = None
            self._gui_status = gui.add_markdown("waiting for frames")
        self._sensor_node = None
        self._trajectory_drawn = (-math.inf, 0)  # (when, poses drawn)
        # One callback per control, changing one field: a bad value in one control never blocks another.
        self._gui_lod.on_update(self._guarded(lambda _: self._set(lod_fraction=self._gui_lod.value)))
        self._gui_auto.on_update(self._guarded(lambda _: self._set(automatic_lod=self._gui_auto.value)))
        for box in self._gui_levels.values():
            box.on_update(self._guarded(lambda _: self._set(
                levels=tuple(level for level, box in self._gui_levels.items() if box.value is True))))
        self._gui_method.on_update(self._guarded(lambda _: self._set(method=self._gui_method.value)))
        self._gui_combination.on_update(self._guarded(lambda _: self._set(combination=self._gui_combination.value)))
        self._gui_scale.on_update(self._guarded(lambda _: self._set(scale=self._gui_scale.value)))

    def _guarded(self, callback):
        """A GUI callback that logs and swallows any error instead of raising into viser."""

        def guarded(event) -> None:
            try:
                callback(event)
            except Exception:  # noqa: BLE001 - a client must not take the viewer down
                log.exception("viewer: ignored a GUI event that failed")

        return guarded

    def _set(self, **change) -> None:
        """Apply one control's new value if it is valid; else log it and put the controls back."""
        with self._lock:
            current = self.settings
        try:
            candidate = replace(current, **change).checked()
        except (ValueError, TypeError) as error:
            log.warning("viewer: ignored a GUI value: %s", error)
            self._sync_gui(current)
            return
        with self._lock:
            if candidate == self.settings:
                return
            self.settings = candidate
            self._redraw_all = True
            self._wake.notify()

    def _sync_gui(self, settings: ViewSettings) -> None:
        """Set the controls to ``settings`` (their callbacks then see no change)."""
        self._gui_lod.value = settings.lod_fraction
        self._gui_auto.value = settings.automatic_lod
        for level, box in self._gui_levels.items():
            box.value = level in settings.levels
        self._gui_method.value = settings.method
        self._gui_combination.value = settings.combination
        self._gui_scale.value = settings.scale

    def _on_save(self, event) -> None:
        path = self.save_scene()
        client = getattr(event, "client", None)
        if client is not None:
            client.add_notification("scene saved", str(path), auto_close_seconds=4.0)

    def _on_client_connect(self, client) -> None:
        client.camera.on_update(self._guarded(self._on_camera))

    def _on_camera(self, camera) -> None:
        width, height, fov = int(camera.image_width), int(camera.image_height), float(camera.fov)
        position, wxyz = np.asarray(camera.position, np.float64), np.asarray(camera.wxyz, np.float64)
        if not (0 < width <= 16384 and 0 < height <= 16384 and 0 < fov < math.pi
                and np.isfinite(position).all() and np.isfinite(wxyz).all() and np.linalg.norm(wxyz) > 0):
            log.warning("viewer: ignored a camera update (size %sx%s, fov %s)", width, height, fov)
            return
        T_world_camera = np.eye(4)
        T_world_camera[:3, :3] = _rotation(wxyz / np.linalg.norm(wxyz))
        T_world_camera[:3, 3] = position
        focal = 0.5 * height / math.tan(0.5 * fov)
        with self._lock:
            self._camera = _Camera(T_world_camera, focal, focal, 0.5 * width, 0.5 * height, width, height)
            self._camera_changed = True
            self._wake.notify()

    # ------------------------------------------------------------------
    # The viewer's thread.
    # ------------------------------------------------------------------

    def _run(self) -> None:
        last_camera = -math.inf
        while True:
            with self._lock:
                while not self._closing and not self._has_work(last_camera):
                    self._wake.wait(self._wait_time(last_camera))
                if self._closing:
                    return
                frame, self._pending_frame = self._pending_frame, None
                surfaces, self._pending_surfaces = self._pending_surfaces, None
                trajectory, self._pending_trajectory = self._pending_trajectory, False
                force_trajectory = surfaces is not None
                redraw, self._redraw_all = self._redraw_all, False
                settings, camera = self.settings, self._camera
                use_camera = settings.automatic_lod and self._camera_changed and \
                    time.monotonic() - last_camera >= _CAMERA_INTERVAL
                if use_camera:
                    self._camera_changed = False
                    last_camera = time.monotonic()
                timings = list(self._timings) if frame is not None else None
                positions = list(self._positions) if trajectory else None
                pose = self._last_pose
                self._busy = True
            began = time.thread_time()
            try:
                if frame is not None:
                    self._draw_frame(frame, timings)
                if positions is not None:
                    self._draw_trajectory(positions, pose, force=force_trajectory)
                if surfaces is not None:
                    self._take_surfaces(surfaces, settings, camera)
                if redraw:
                    self._refresh(settings, camera, everything=True)
                elif use_camera:
                    self._refresh(settings, camera, everything=False)
                if settings.method == "oscillation":
                    self._refresh(settings, camera, everything=True)
            except Exception:  # noqa: BLE001 - the viewer's thread must survive a bad surface or a closed server
                log.exception("viewer: drawing failed")
            finally:
                self.stats["busy_seconds"] += time.thread_time() - began
                with self._lock:
                    self._busy = False
                    self._wake.notify_all()
            if settings.method == "oscillation":
                time.sleep(_OSCILLATION_INTERVAL)

    def _has_work(self, last_camera: float) -> bool:
        camera_due = self.settings.automatic_lod and self._camera_changed and \
            time.monotonic() - last_camera >= _CAMERA_INTERVAL
        return (self._pending_frame is not None or self._pending_surfaces is not None or self._pending_trajectory
                or self._redraw_all or camera_due or (self.settings.method == "oscillation" and bool(self._entries)))

    def _wait_time(self, last_camera: float) -> float:
        if self.settings.automatic_lod and self._camera_changed:
            return max(0.01, _CAMERA_INTERVAL - (time.monotonic() - last_camera))
        return 0.5

    # Images and plots.

    def _draw_frame(self, frame: _Frame, timings: list[tuple[int, dict[str, float]]]) -> None:
        if frame.range.size:
            from rangesurf.edges import detect_edges
            from rangesurf.report import colorize_edges, colorize_labels, colorize_range

            range_bgr = colorize_range(frame.range)
            self._gui_frame.visible = True
            self._gui_range.image = range_bgr[..., ::-1]
            if np.isfinite(frame.range).any():
                edges = detect_edges(frame.range)
                self._gui_edges.image = colorize_edges(edges, background=range_bgr)[..., ::-1]
            self._gui_segments.image = colorize_labels(np.asarray(frame.labels).astype(np.int32), background=range_bgr)[..., ::-1]
        if timings:
            self._draw_timings(timings)
        self.stats["frames_drawn"] += 1

    def _draw_timings(self, timings: list[tuple[int, dict[str, float]]]) -> None:
        stages = tuple(name for name in timings[-1][1] if name not in ("late", "deferred", "timestamp"))
        x = np.array([index for index, _ in timings], np.float64)
        columns = [np.array([row.get(stage, np.nan) for _, row in timings], np.float64) for stage in stages]
        if self._gui_plot is None or stages != self._stages:
            if self._gui_plot is not None:
                self._gui_plot.remove()
            import viser.uplot as uplot

            series = [uplot.Series(label="frame")]
            series += [uplot.Series(label=stage, stroke=_STAGE_COLOURS[k % len(_STAGE_COLOURS)], width=2 if stage == "total" else 1)
                       for k, stage in enumerate(stages)]
            with self._gui_timings:
                self._gui_plot = self.server.gui.add_uplot(
                    (x, *columns), tuple(series), title="milliseconds per stage", aspect=1.4,
                    scales={"x": uplot.Scale(time=False, auto=True), "y": uplot.Scale(auto=True)},
                )
            self._stages = stages
        else:
            self._gui_plot.data = (x, *columns)
        last = timings[-1][1]
        total = last.get("total", float("nan"))
        self._gui_status.content = f"frame {timings[-1][0]}: {total:.1f} ms in total"

    def _draw_trajectory(self, positions: list[np.ndarray], pose: np.ndarray | None, *, force: bool = False) -> None:
        scene = self.server.scene
        when, drawn = self._trajectory_drawn
        # The path grows by one pose a frame: sent again twice a second, not 25 times.
        if len(positions) >= 2 and len(positions) != drawn and (force or time.monotonic() - when >= 0.5):
            points = np.asarray(positions, np.float32)
            segments = np.stack([points[:-1], points[1:]], axis=1)
            scene.add_line_segments("/trajectory", segments, colors=(40, 110, 220), thickness=2.0, thickness_units="screen")
            self._trajectory_drawn = (time.monotonic(), len(positions))
        if pose is not None:
            if self._sensor_node is None:
                self._sensor_node = scene.add_camera_frustum("/sensor", fov=0.7, aspect=176 / 144, scale=0.15,
                                                             thickness=2.0, thickness_units="screen", color=(40, 110, 220))
            self._sensor_node.wxyz = _quaternion(pose[:3, :3])
            self._sensor_node.position = pose[:3, 3]
            if not self._placed_camera:
                # Start behind and above the first sensor pose, looking where it looks.
                forward, down = pose[:3, 2], pose[:3, 1]
                self.server.initial_camera.position = tuple(pose[:3, 3] - 2.5 * forward - 1.2 * down)
                self.server.initial_camera.look_at = tuple(pose[:3, 3] + 2.5 * forward)
                self.server.initial_camera.up = tuple(-down)
                self._placed_camera = True

    # Surfaces.

    def _take_surfaces(self, snapshot: dict[str, Surface], settings: ViewSettings, camera: _Camera | None) -> None:
        """Drop the surfaces gone from ``snapshot``, prepare and draw the new or changed ones."""
        self.stats["mesh_snapshots"] += 1
        for name in [name for name in self._entries if name not in snapshot]:
            for node in self._entries.pop(name).nodes.values():
                node.remove()
        changed = []
        for name, source in snapshot.items():
            entry = self._entries.get(name)
            if entry is not None and entry.source is source:
                continue
            prepared = _with_levels(source)
            if entry is None:
                entry = self._entries[name] = _Entry(name, source, prepared)
            else:
                entry.source, entry.surface, entry.count = source, prepared, -1
            changed.append(entry)
        if not changed:
            return
        vmax = _reference_uncertainty([entry.surface for entry in self._entries.values()], settings.levels)
        if abs(vmax - self._vmax) > 0.2 * self._vmax:
            # The colour scale moved: every surface is drawn again so that colours stay comparable.
            self._vmax = vmax
            self._refresh(settings, camera, everything=True)
            return
        for entry in changed:
            self._draw_entry(entry, settings, camera)

    def _refresh(self, settings: ViewSettings, camera: _Camera | None, *, everything: bool) -> None:
        if everything:
            self._vmax = _reference_uncertainty([entry.surface for entry in self._entries.values()], settings.levels)
        for entry in list(self._entries.values()):
            if everything:
                self._draw_entry(entry, settings, camera)
            else:
                shown = self._at_level(entry.surface, settings, camera)
                if shown.n_vertices != entry.count:
                    self._draw_entry(entry, settings, camera, shown=shown)

    def _at_level(self, surface: Surface, settings: ViewSettings, camera: _Camera | None) -> Surface:
        if not surface.levels:
            return surface
        if settings.automatic_lod and camera is not None:
            from rangesurf.lod import view_level

            level = view_level(surface, np.linalg.inv(camera.T_world_camera), fx=camera.fx, fy=camera.fy, cx=camera.cx,
                               cy=camera.cy, width=camera.width, height=camera.height)
            return surface.at_level(count=level.count)
        return surface.at_level(fraction=settings.lod_fraction)

    def _draw_entry(self, entry: _Entry, settings: ViewSettings, camera: _Camera | None, shown: Surface | None = None) -> None:
        shown = shown if shown is not None else self._at_level(entry.surface, settings, camera)
        nodes = _draw_surface(self.server.scene, f"/model/{entry.name}", shown, settings, self._vmax,
                              phase=(time.monotonic() / _OSCILLATION_PERIOD) % 1.0)
        for key in [key for key in entry.nodes if key not in nodes]:
            entry.nodes.pop(key).remove()
        entry.nodes.update(nodes)
        entry.count = shown.n_vertices
        self.stats["surfaces_drawn"] += 1


# --------------------------------------------------------------------------
# Drawing one surface.
# --------------------------------------------------------------------------


def _draw_surface(scene, name: str, surface: Surface, settings: ViewSettings, vmax: float, *, phase: float = 0.0) -> dict:
    """Add (or replace) the scene nodes of one surface under ``name``; returns them by key."""
    from rangesurf import glyphs

    levels, method, scale = settings.levels, settings.method, settings.scale
    nodes: dict[str, Any] = {}
    if surface.n_vertices == 0:
        return nodes
    if surface.n_faces == 0:
        # Vertices without triangles (non-planar pieces kept as they are): a point cloud.
        values = glyphs.combined_uncertainty(surface, levels)
        colours = glyphs.hue_colours(values, vmax=vmax)[:, :3] if method != "none" else np.array(_NEUTRAL, np.uint8)
        nodes["surface"] = scene.add_point_cloud(f"{name}/surface", surface.vertices, colours,
                                                 point_size=_point_size(surface), point_shape="circle")
        return nodes
    normals = surface.normals
    if method == "colour":
        if settings.combination == "separate" and levels:
            colours = _dominant_level_colours(surface, levels)
        else:
            colours = glyphs.hue_colours(glyphs.combined_uncertainty(surface, levels), vmax=vmax)
        nodes["surface"] = scene.add_glb(f"{name}/surface", _glb(surface.vertices, surface.faces, colours, normals))
    elif method == "opacity":
        alpha = glyphs.opacity(glyphs.combined_uncertainty(surface, levels), vmax=vmax)
        colours = np.empty((surface.n_vertices, 4), np.uint8)
        colours[:, :3] = _NEUTRAL
        colours[:, 3] = np.round(255 * alpha).astype(np.uint8)
        nodes["surface"] = scene.add_glb(f"{name}/surface", _glb(surface.vertices, surface.faces, colours, normals))
    elif method in ("perturbation", "oscillation") and levels:
        made = (glyphs.perturbed(surface, levels, scale=scale) if method == "perturbation"
                else glyphs.oscillating(surface, levels, phase, scale=scale))
        nodes["surface"] = scene.add_glb(f"{name}/surface", _glb(made.vertices, made.faces, made.colours))
    else:
        nodes["surface"] = scene.add_mesh_simple(f"{name}/surface", surface.vertices, surface.faces, color=_NEUTRAL,
                                                 side="double")
    if levels:
        for index, made in enumerate(_glyphs(surface, settings)):
            node = _add_glyphs(scene, f"{name}/glyph{index}", made, _point_size(surface))
            if node is not None:
                nodes[f"glyph{index}"] = node
    return nodes


def _glyphs(surface: Surface, settings: ViewSettings) -> list:
    """The added geometry of a method (none for the attribute and surface-changing methods)."""
    from rangesurf import glyphs

    levels, scale, separate = settings.levels, settings.scale, settings.combination == "separate"
    method = settings.method
    if method == "points":
        return [glyphs.displaced_points(surface, levels, scale=scale, mode="separate" if separate else "cumulative")]
    if method == "bars":
        return [glyphs.bars(surface, levels, scale=scale, mode="separate" if separate else "stacked")]
    if method in ("shells", "volume"):
        made = []
        for group in ([(level,) for level in levels] if separate else [levels]):
            parts = list(glyphs.shells(surface, group, scale=scale)) if method == "shells" else \
                [glyphs.uncertainty_volume(surface, group, scale=scale)]
            if separate:
                colour = np.array(glyphs.LEVEL_COLOURS[group[0]], np.uint8)
                parts = [replace(part, colours=np.tile(np.r_[colour[:3], part.colours[0, 3]], (len(part.colours), 1)))
                         for part in parts if part.colours is not None and len(part.colours)]
            made += parts
        return made
    if method == "cones":
        return [glyphs.cones(surface, levels[0], levels[-1], scale=scale)]
    return []


def _add_glyphs(scene, name: str, made, point_size: float):
    """One viser node for a `rangesurf.glyphs.Glyphs`: point cloud, line segments or (possibly translucent) mesh."""
    colours = made.colours
    if made.points is not None and len(made.points):
        return scene.add_point_cloud(name, made.points, colours[:, :3], point_size=point_size, point_shape="circle")
    if made.segments is not None and len(made.segments):
        return scene.add_line_segments(name, made.segments, np.repeat(colours[:, None, :3], 2, axis=1),
                                       thickness=2.0, thickness_units="screen")
    if made.vertices is not None and made.faces is not None and len(made.faces):
        return scene.add_glb(name, _glb(made.vertices, made.faces, colours))
    return None


def _dominant_level_colours(surface: Surface, levels: tuple[str, ...]) -> np.ndarray:
    """Per vertex the colour of the level with the largest uncertainty (grey where none is known)."""
    from rangesurf import glyphs

    values = glyphs.level_values(surface, levels)
    palette = np.array([glyphs.LEVEL_COLOURS[level] for level in levels], np.uint8)
    colours = palette[np.argmax(values, axis=1)]
    colours[~(values > 0).any(axis=1)] = (128, 128, 128, 255)
    return colours


def _point_size(surface: Surface) -> float:
    """Half the median triangle edge (metres), at least 2 mm: glyph points that neither vanish nor merge."""
    if surface.n_faces:
        corners = surface.vertices[surface.faces[:, :2]]
        edge = float(np.median(np.linalg.norm(corners[:, 0] - corners[:, 1], axis=1)))
    else:
        span = np.ptp(surface.vertices, axis=0).max() if surface.n_vertices > 1 else 0.0
        edge = float(span) / max(math.sqrt(surface.n_vertices), 1.0)
    return max(0.5 * edge, 0.002)


def _reference_uncertainty(surfaces: list[Surface], levels: tuple[str, ...]) -> float:
    """The 95th percentile of the positive combined uncertainties: the top of the colour and opacity scales."""
    from rangesurf import glyphs

    if not levels:
        return 0.01
    values = [glyphs.combined_uncertainty(surface, levels) for surface in surfaces]
    values = np.concatenate(values) if values else np.zeros(0)
    values = values[np.isfinite(values) & (values > 0)]
    return float(np.percentile(values, 95)) if values.size else 0.01


def _with_levels(source: Surface) -> Surface:
    """A copy of ``source`` with its levels of detail (ordering it first when it has no LOD order)."""
    from rangesurf.lod import build_levels, prepare_levels

    surface = replace(source, uncertainty=dict(source.uncertainty), levels=[])
    if surface.n_faces == 0 or surface.n_vertices < 4:
        return surface
    try:
        ordered = bool(surface.lod_error.any())
        if ordered:
            surface.levels = build_levels(surface)
        else:
            prepare_levels(surface)
    except (ValueError, ArithmeticError, IndexError) as error:
        # Degenerate geometry (collinear vertices, a sliver): shown at full detail only.
        log.debug("viewer: no levels of detail for a surface of %d vertices: %s", surface.n_vertices, error)
        surface.levels = []
    return surface


# --------------------------------------------------------------------------
# Small helpers.
# --------------------------------------------------------------------------


def _rotation(wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = wxyz
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _quaternion(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method)."""
    m = np.asarray(rotation, np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q / np.linalg.norm(q)


def _glb(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None = None,
         normals: np.ndarray | None = None) -> bytes:
    """A binary glTF 2.0 of one triangle mesh with RGBA vertex colours (blended when any alpha < 255).

    viser's simple mesh has one colour; per-vertex colour and opacity go
    through a glTF (three.js reads COLOR_0 with alpha). Without normals the
    client shades flat.
    """
    vertices = np.ascontiguousarray(vertices, np.float32).reshape(-1, 3)
    faces = np.ascontiguousarray(faces, np.uint32).reshape(-1, 3)
    chunks: list[bytes] = []
    views: list[dict] = []
    accessors: list[dict] = []
    offset = 0

    def add(array: np.ndarray, target: int, accessor: dict) -> int:
        nonlocal offset
        data = np.ascontiguousarray(array).tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data), "target": target})
        data += b"\0" * (-len(data) % 4)
        chunks.append(data)
        offset += len(data)
        accessors.append({"bufferView": len(views) - 1, **accessor})
        return len(accessors) - 1

    finite = vertices[np.isfinite(vertices).all(axis=1)]
    low = finite.min(axis=0).tolist() if len(finite) else [0.0] * 3
    high = finite.max(axis=0).tolist() if len(finite) else [0.0] * 3
    attributes = {"POSITION": add(vertices, 34962, {"componentType": 5126, "count": len(vertices), "type": "VEC3",
                                                    "min": low, "max": high})}
    if normals is not None:
        attributes["NORMAL"] = add(np.asarray(normals, np.float32).reshape(-1, 3), 34962,
                                   {"componentType": 5126, "count": len(vertices), "type": "VEC3"})
    blend = False
    if colours is not None:
        colours = np.asarray(colours, np.uint8).reshape(len(vertices), -1)
        if colours.shape[1] == 3:
            colours = np.column_stack([colours, np.full(len(colours), 255, np.uint8)])
        blend = bool((colours[:, 3] < 255).any())
        attributes["COLOR_0"] = add(colours, 34962, {"componentType": 5121, "normalized": True, "count": len(vertices),
                                                     "type": "VEC4"})
    indices = add(faces.reshape(-1), 34963, {"componentType": 5125, "count": faces.size, "type": "SCALAR"})
    document = {
        "asset": {"version": "2.0", "generator": "rangesurf"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": indices, "material": 0, "mode": 4}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0,
                                                "roughnessFactor": 0.9},
                       "doubleSided": True, "alphaMode": "BLEND" if blend else "OPAQUE"}],
        "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": offset}],
    }
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    binary = b"".join(chunks)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<II", len(text), 0x4E4F534A) + text
            + struct.pack("<II", len(binary), 0x004E4942) + binary)


# --------------------------------------------------------------------------
# Offline: a run's output folder.
# --------------------------------------------------------------------------


@dataclass
class ModelFiles:
    """What `load_model` read from a run's folder.

    Parameters
    ----------
    surfaces : list of Surface
        From ``model.ply`` (world frame), one per ``surface`` id, with the
        uncertainty levels the file holds (NaN columns dropped).
    poses : (N, 4, 4) float64 or None
        ``trajectory.txt``.
    timings : list of dict or None
        ``timings.csv`` rows (milliseconds per stage).
    metrics : dict or None
        ``metrics.json``.
    """

    surfaces: list[Surface]
    poses: np.ndarray | None = None
    timings: list[dict] | None = None
    metrics: dict | None = None


def model_file(folder: str | Path, name: str, *, must_exist: bool = True) -> Path:
    """The path of ``name`` inside ``folder``, refusing any name that leads out of it.

    Parameters
    ----------
    folder : path-like
        The model folder.
    name : str
        A plain file name (no directory part, not ``.`` or ``..``).
    must_exist : bool
        Raise FileNotFoundError when the file is missing.

    Raises
    ------
    PermissionError
        If ``name`` has a directory part, or the file (a symbolic link, or
        a folder reached through one) resolves outside ``folder``.

    Examples
    --------
    >>> import tempfile
    >>> folder = tempfile.mkdtemp()
    >>> model_file(folder, "model.ply", must_exist=False).name
    'model.ply'
    >>> model_file(folder, "../secret.txt", must_exist=False)
    Traceback (most recent call last):
    ...
    PermissionError: '../secret.txt': only plain file names inside the model folder are read
    """
    if not isinstance(name, str) or name in ("", ".", "..") or Path(name).name != name or "/" in name or "\\" in name \
            or "\0" in name:
        raise PermissionError(f"{name!r}: only plain file names inside the model folder are read")
    root = Path(folder).resolve()
    path = (root / name).resolve()
    if path.parent != root:
        raise PermissionError(f"{Path(folder) / name} resolves to {path}, outside the model folder {root}")
    if must_exist and not path.is_file():
        raise FileNotFoundError(f"{Path(folder) / name}: no such file in the model folder")
    return path


def load_model(folder: str | Path) -> ModelFiles:
    """Read a run's outputs from ``folder``: ``model.ply`` (required) and the optional `MODEL_FILES`.

    Nothing outside ``folder`` is read (`model_file`).

    Raises
    ------
    FileNotFoundError
        If the folder or its ``model.ply`` is missing.
    PermissionError
        If one of the files leads out of the folder.
    FormatError
        If ``model.ply`` is not a mesh as `rangesurf.io.ply.write_mesh_ply` writes.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such model folder")
    surfaces = _read_model_ply(model_file(folder, "model.ply"))
    result = ModelFiles(surfaces)
    optional = {name: _optional(folder, name) for name in MODEL_FILES[1:]}
    if optional["trajectory.txt"] is not None:
        from rangesurf.io.tum import read_tum_trajectory

        result.poses = read_tum_trajectory(optional["trajectory.txt"])[1]
    if optional["metrics.json"] is not None:
        result.metrics = json.loads(optional["metrics.json"].read_text(encoding="utf-8"))
    if optional["timings.csv"] is not None:
        with open(optional["timings.csv"], encoding="utf-8", newline="") as stream:
            result.timings = [{key: float(value) for key, value in row.items() if value not in (None, "")}
                              for row in csv.DictReader(stream)]
    return result


def _optional(folder: Path, name: str) -> Path | None:
    try:
        return model_file(folder, name)
    except FileNotFoundError:
        return None


def _read_model_ply(path: Path) -> list[Surface]:
    """Surfaces of a binary mesh PLY (`rangesurf.io.ply.write_mesh_ply`): grouped by the ``surface`` column."""
    from rangesurf.io import FormatError
    from rangesurf.io.ply import _parse_header, _read_elements

    data = path.read_bytes()
    header = _parse_header(path, data)
    vertex, face = header.element("vertex"), header.element("face")
    if vertex is None or face is None:
        raise FormatError(path, "expected 'vertex' and 'face' elements (a mesh written by rangesurf run)")
    columns = _read_elements(path, data, header, {"vertex", "face"})
    points, faces_in = columns["vertex"], columns["face"]
    for name in ("x", "y", "z"):
        if name not in points:
            raise FormatError(path, f"vertex property {name!r} missing", where="header")
    vertices = np.column_stack([points[name] for name in ("x", "y", "z")]).astype(np.float32)
    count = len(vertices)
    normals = (np.column_stack([points[name] for name in ("nx", "ny", "nz")]).astype(np.float32)
               if all(name in points for name in ("nx", "ny", "nz")) else np.zeros((count, 3), np.float32))
    owner = np.asarray(points["surface"], np.int64) if "surface" in points else np.ones(count, np.int64)
    lists = faces_in.get("vertex_indices")
    if not isinstance(lists, tuple):
        raise FormatError(path, "face property 'vertex_indices' must be a list", where="header")
    lengths, flat = lists
    if len(lengths) and not (np.asarray(lengths) == 3).all():
        raise FormatError(path, "only triangles are read; a face has another number of corners", where="element face")
    faces = np.asarray(flat, np.int64).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= count):
        raise FormatError(path, f"face indices must lie in 0..{count - 1}", where="element face")
    surfaces = []
    face_owner = owner[faces[:, 0]] if len(faces) else np.zeros(0, np.int64)
    for label in np.unique(owner):
        own = np.flatnonzero(owner == label)
        remap = np.full(count, -1, np.int64)
        remap[own] = np.arange(len(own))
        own_faces = remap[faces[face_owner == label]]
        own_faces = own_faces[(own_faces >= 0).all(axis=1)]
        uncertainty = {}
        for level in UNCERTAINTY_LEVELS:
            column = points.get(level.lower())
            if column is not None and np.isfinite(column[own]).any():
                uncertainty[level] = np.asarray(column[own], np.float32)
        surfaces.append(Surface(vertices[own], own_faces, normals[own], np.full((len(own), 2), -1), segment=int(label),
                                uncertainty=uncertainty))
    return surfaces


def view_model(folder: str | Path, *, host: str = "127.0.0.1", port: int = 8080, settings: ViewSettings | None = None,
               block: bool = True, verbose: bool = True) -> Viewer:
    """Serve a run's saved model (``rangesurf view DIR``).

    Parameters
    ----------
    folder : path-like
        A run's output folder (`rangesurf.runner.run`): ``model.ply`` and,
        if present, ``trajectory.txt``, ``metrics.json``, ``timings.csv``.
        "save .viser" writes ``model.viser`` there.
    host : str
        ``"127.0.0.1"`` unless another interface is asked for explicitly.
    port : int
    settings : ViewSettings, optional
    block : bool
        Serve until Ctrl-C (then close); False returns the running viewer.
    verbose : bool
        Let viser print the address and connections.

    Returns
    -------
    Viewer
        Closed when ``block``.
    """
    model = load_model(folder)
    viewer = Viewer(host=host, port=port, folder=folder, settings=settings, verbose=verbose)
    try:
        if model.poses is not None and len(model.poses):
            viewer.show_trajectory(model.poses)
        if model.timings:
            viewer.show_timings(model.timings)
        viewer.show_surfaces(model.surfaces)
        if model.metrics:
            summary = {key: model.metrics.get(key) for key in ("frames", "frames_per_second", "surfaces", "vertices")}
            viewer.server.gui.add_markdown("  \n".join(f"**{key}**: {value}" for key, value in summary.items()))
        if block:
            try:
                while True:
                    time.sleep(3600)
            except KeyboardInterrupt:
                pass
            viewer.close()
    except BaseException:
        viewer.close()
        raise
    return viewer
