"""The viewer: binding, path safety, live updates from the pipeline, GUI input checks, and a real browser.

Tests that need the server skip without viser (``pip install 'rangesurf[viewer]'``);
the browser test also needs Playwright's Python package and Debian's
``chromium`` at /usr/bin/chromium (``apt-get install chromium``; Playwright's
own browser download is not used).
"""

from __future__ import annotations

import dataclasses
import http.client
import importlib.util
import io
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

from rangesurf import simulate
from rangesurf.config import PipelineConfig, RunSettings
from rangesurf.io.ply import write_mesh_ply
from rangesurf.io.tum import write_tum_trajectory
from rangesurf.mesh import Surface, triangulate_in_plane
from rangesurf.pipeline import Pipeline
from rangesurf.viewer import (
    METHODS, NullViewer, ViewSettings, Viewer, _glb, load_model, model_file,
)

HAVE_VISER = importlib.util.find_spec("viser") is not None
needs_viser = pytest.mark.skipif(not HAVE_VISER, reason="viser not installed: pip install 'rangesurf[viewer]'")
CHROMIUM = Path("/usr/bin/chromium")
BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"]


# --------------------------------------------------------------------------
# Fixtures: a small model with known uncertainty, and real pipeline results.
# --------------------------------------------------------------------------


def wall(origin, along, up, size=(1.0, 0.8), step=0.05, sigma=(0.002, 0.02)) -> Surface:
    """A planar grid patch whose UL1 grows linearly along ``along`` from sigma[0] to sigma[1] (metres)."""
    origin, along, up = (np.asarray(v, float) for v in (origin, along, up))
    u, v = np.meshgrid(np.arange(0, size[0] + 1e-9, step), np.arange(0, size[1] + 1e-9, step))
    vertices = origin + u.reshape(-1, 1) * along + v.reshape(-1, 1) * up
    normal = np.cross(along, up)
    plane = np.r_[normal, -normal @ origin]
    count = len(vertices)
    ul1 = sigma[0] + (sigma[1] - sigma[0]) * u.ravel() / size[0]
    return Surface(vertices, triangulate_in_plane(vertices, plane), np.tile(normal, (count, 1)), np.full((count, 2), -1),
                   plane=plane, uncertainty={"UL1": ul1, "UL2": np.full(count, 0.001)})


@pytest.fixture(scope="module")
def room() -> list[Surface]:
    return [wall([0, 0, 0], [1, 0, 0], [0, 0, 1]), wall([0, 0, 0], [0, 1, 0], [0, 0, 1]),
            wall([0, 0, 0], [1, 0, 0], [0, 1, 0], size=(1.0, 1.0), sigma=(0.02, 0.002))]


@pytest.fixture(scope="module")
def processed():
    """Three simulated SR-3000 frames through a pipeline that re-meshes after every frame."""
    frames, _ = simulate.simulate_sequence("arena", "sr3000", 3, seed=0)
    pipeline = Pipeline(PipelineConfig(run=RunSettings(remesh_every=1)))
    results = [pipeline.process(frame) for frame in frames]
    return pipeline, results


@pytest.fixture(scope="module")
def saved_run(tmp_path_factory, room):
    """A run's output folder: model.ply, trajectory.txt, timings.csv, metrics.json."""
    folder = tmp_path_factory.mktemp("run")
    write_mesh_ply(folder / "model.ply", room)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 0.1, 0.2]
    write_tum_trajectory(folder / "trajectory.txt", [0.0, 0.04, 0.08], poses)
    (folder / "timings.csv").write_text("frame,denoise,segment,total\n0,1.5,2.5,4.0\n1,1.4,2.6,4.0\n")
    (folder / "metrics.json").write_text(json.dumps({"frames": 3, "surfaces": 3}))
    return folder


def viewer_for(**kwargs) -> Viewer:
    return Viewer(port=0, **kwargs)


# --------------------------------------------------------------------------
# No server needed.
# --------------------------------------------------------------------------


def test_null_viewer_has_the_viewers_interface(processed):
    pipeline, results = processed
    public = {name for name in dir(NullViewer) if not name.startswith("_")}
    assert public == {"update", "finish", "flush", "close"}
    assert public <= {name for name in dir(Viewer) if not name.startswith("_")}
    with NullViewer() as viewer:
        for result in results:
            assert viewer.update(result, pipeline) is None
        assert viewer.finish(pipeline.model.surfaces()) is None
        assert viewer.flush() is True


@pytest.mark.parametrize("name", ["../model.ply", "..", ".", "", "/etc/passwd", "sub/model.ply", "a\\..\\b", "x\0y"])
def test_model_file_refuses_names_leading_out(tmp_path, name):
    with pytest.raises(PermissionError):
        model_file(tmp_path, name, must_exist=False)


def test_symbolic_links_out_of_the_folder_are_refused(tmp_path, room):
    outside, folder = tmp_path / "outside", tmp_path / "model"
    outside.mkdir()
    folder.mkdir()
    write_mesh_ply(outside / "model.ply", room)
    (folder / "model.ply").symlink_to(outside / "model.ply")
    with pytest.raises(PermissionError, match="outside the model folder"):
        load_model(folder)
    # An optional file that points out is refused too, not silently read or skipped.
    (folder / "model.ply").unlink()
    write_mesh_ply(folder / "model.ply", room)
    (outside / "metrics.json").write_text("{}")
    (folder / "metrics.json").symlink_to(outside / "metrics.json")
    with pytest.raises(PermissionError):
        load_model(folder)
    # A link that stays inside is fine.
    (folder / "metrics.json").unlink()
    (folder / "real.json").write_text(json.dumps({"frames": 1}))
    (folder / "metrics.json").symlink_to(folder / "real.json")
    assert load_model(folder).metrics == {"frames": 1}


def test_model_folder_reached_through_a_link_is_its_own_root(tmp_path, room):
    real = tmp_path / "real"
    real.mkdir()
    write_mesh_ply(real / "model.ply", room)
    (tmp_path / "link").symlink_to(real, target_is_directory=True)
    assert len(load_model(tmp_path / "link").surfaces) == len(room)


def test_load_model_gives_back_what_the_run_wrote(saved_run, room):
    model = load_model(saved_run)
    assert len(model.surfaces) == len(room)
    for loaded, original in zip(model.surfaces, room):
        np.testing.assert_allclose(loaded.vertices, original.vertices, atol=1e-6)
        np.testing.assert_array_equal(loaded.faces, original.faces)
        assert sorted(loaded.uncertainty) == ["UL1", "UL2"]  # the NaN columns UL3, UL4 are dropped
        np.testing.assert_allclose(loaded.uncertainty["UL1"], original.uncertainty["UL1"], rtol=1e-6)
    assert model.poses.shape == (3, 4, 4) and model.poses[2, 0, 3] == pytest.approx(0.2)
    assert [row["total"] for row in model.timings] == [4.0, 4.0]
    assert model.metrics["surfaces"] == 3


def test_load_model_without_model_ply(tmp_path):
    with pytest.raises(FileNotFoundError, match="model.ply"):
        load_model(tmp_path)


def test_glb_round_trips_through_trimesh(room):
    trimesh = pytest.importorskip("trimesh")
    surface = room[0]
    colours = np.zeros((surface.n_vertices, 4), np.uint8)
    colours[:, 0] = np.arange(surface.n_vertices) % 256
    colours[:, 3] = 128
    scene = trimesh.load(io.BytesIO(_glb(surface.vertices, surface.faces, colours, surface.normals)), file_type="glb",
                         process=False)
    mesh = next(iter(scene.geometry.values()))
    np.testing.assert_allclose(mesh.vertices, surface.vertices, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, surface.faces)
    np.testing.assert_array_equal(mesh.visual.vertex_attributes["color"], colours)
    assert mesh.visual.material.alphaMode == "BLEND"  # translucent because some alpha < 255
    opaque = trimesh.load(io.BytesIO(_glb(surface.vertices, surface.faces)), file_type="glb", process=False)
    assert next(iter(opaque.geometry.values())).visual.material.alphaMode == "OPAQUE"


def test_settings_are_checked():
    assert ViewSettings().checked() == ViewSettings()
    for bad in (dict(lod_fraction=float("nan")), dict(lod_fraction=2.0), dict(method="rm -rf"), dict(levels=("UL5",)),
                dict(levels=["UL1"]), dict(combination="both"), dict(scale=0.0), dict(automatic_lod="yes")):
        with pytest.raises(ValueError):
            ViewSettings(**bad).checked()


# --------------------------------------------------------------------------
# The server.
# --------------------------------------------------------------------------


def listening_addresses(port: int) -> set[str]:
    """Local addresses (hex, as /proc/net/tcp shows them) listening on ``port``."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not os.path.exists(table):
            continue
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            address, local_port = fields[1].split(":")
            if int(local_port, 16) == port and fields[3] == "0A":
                found.add(address)
    return found


def page_status(port: int, path: str = "/") -> int:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        connection.request("GET", path)
        response = connection.getresponse()
        response.read()
        return response.status
    finally:
        connection.close()  # an open connection would hold up the server's stop


@needs_viser
def test_binds_to_loopback_by_default():
    if not os.path.exists("/proc/net/tcp"):
        pytest.skip("needs /proc/net/tcp (Linux) to see the bound address")
    with viewer_for() as viewer:
        assert viewer.host == "127.0.0.1" and viewer.url == f"http://127.0.0.1:{viewer.port}"
        assert listening_addresses(viewer.port) == {"0100007F"}


@needs_viser
def test_another_interface_only_when_asked():
    if not os.path.exists("/proc/net/tcp"):
        pytest.skip("needs /proc/net/tcp (Linux) to see the bound address")
    # 127.0.0.2 is another interface address that exists on every Linux machine without exposing anything.
    with Viewer(host="127.0.0.2", port=0) as viewer:
        assert listening_addresses(viewer.port) == {"0200007F"}


@needs_viser
def test_http_serves_no_model_file_and_no_traversal(saved_run):
    from rangesurf.viewer import view_model

    viewer = view_model(saved_run, port=0, block=False, verbose=False)
    try:
        for path in ("/model.ply", "/../model.ply", "/%2e%2e/%2e%2e/etc/passwd", "/..%2f..%2fetc%2fpasswd",
                     "/assets/../../../../etc/passwd"):
            connection = http.client.HTTPConnection("127.0.0.1", viewer.port, timeout=10)
            connection.request("GET", path)
            response = connection.getresponse()
            body = response.read()
            assert response.status == 404, path
            assert b"root:" not in body and b"ply" not in body[:3]
            connection.close()
        # The page itself is served.
        assert page_status(viewer.port) == 200
    finally:
        viewer.close()


@needs_viser
def test_live_updates_grow_the_scene(processed):
    pipeline, results = processed
    with viewer_for(mesh_interval=0.0) as viewer:
        assert viewer.n_surfaces == 0
        counts = []
        for result in results:
            viewer.update(result, pipeline)
            assert viewer.flush(30)
            counts.append(viewer.n_surfaces)
        # Every frame re-meshes (remesh_every=1), so the scene shows the model's meshed patches.
        expected = len(pipeline.model.patches) + len(pipeline.model.others)
        assert counts[-1] == expected > 0
        assert viewer.stats["updates"] == 3 and viewer.stats["frames_drawn"] >= 1
        # The images are the last frame's.
        assert viewer._gui_range.image.shape[:2] == results[-1].range.shape
        assert viewer._gui_segments.image.shape[:2] == results[-1].segmentation.labels.shape
        drawn = viewer.stats["surfaces_drawn"]
        viewer.update(results[-1], pipeline)  # nothing changed in the model: nothing re-sent
        assert viewer.flush(30) and viewer.stats["surfaces_drawn"] == drawn
        surfaces = pipeline.finish()
        viewer.finish(surfaces)
        assert viewer.n_surfaces == len(surfaces)


@needs_viser
def test_lod_slider_and_camera_choose_the_level(room):
    with viewer_for() as viewer:
        viewer.show_surfaces(room)
        assert viewer.flush(30)

        def drawn_vertices() -> int:
            return sum(entry.count for entry in viewer._entries.values())

        full = drawn_vertices()
        assert full == sum(surface.n_vertices for surface in room)
        viewer.apply(ViewSettings(lod_fraction=0.1))
        assert viewer.flush(30)
        coarse = drawn_vertices()
        assert sum(0.1 * s.n_vertices for s in room) <= coarse < 0.3 * full

        class Camera:  # what viser's client camera reports (OpenCV axes, vertical fov)
            image_width, image_height, fov = 800, 600, 1.0

            def __init__(self, distance):
                self.position = np.array([0.5, 0.4, distance])
                self.wxyz = np.array([0.0, 1.0, 0.0, 0.0])  # 180 deg about x: looking down -z

        viewer.apply(ViewSettings(automatic_lod=True))
        viewer._on_camera(Camera(distance=1.5))
        time.sleep(0.3)
        assert viewer.flush(30)
        near = drawn_vertices()
        viewer._on_camera(Camera(distance=200.0))
        time.sleep(0.3)
        assert viewer.flush(30)
        far = drawn_vertices()
        assert far < near <= full


@needs_viser
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("combination", ["cumulative", "separate"])
def test_every_method_draws(room, method, combination):
    with viewer_for() as viewer:
        viewer.apply(ViewSettings(method=method, combination=combination, levels=("UL1", "UL2")))
        viewer.show_surfaces(room)
        assert viewer.flush(30)
        nodes = [set(entry.nodes) for entry in viewer._entries.values()]
        added = method in ("points", "bars", "shells", "volume", "cones")
        assert all(("glyph0" in keys) == added and "surface" in keys for keys in nodes)
        # No level chosen: no added geometry.
        viewer.apply(ViewSettings(method=method, combination=combination, levels=()))
        assert viewer.flush(30)
        assert all(set(entry.nodes) == {"surface"} for entry in viewer._entries.values())


@needs_viser
def test_gui_ignores_bad_values(room):
    with viewer_for() as viewer:
        viewer.show_surfaces(room)
        before = viewer.settings
        viewer._gui_lod.value = float("nan")
        viewer._gui_lod.value = 1e9
        viewer._gui_scale.value = -3.0
        viewer._gui_method.value = "__import__('os')"
        assert viewer.settings == before
        assert viewer._gui_method.value == before.method and viewer._gui_lod.value == before.lod_fraction
        viewer._gui_method.value = "bars"
        assert viewer.settings.method == "bars"
        assert viewer.flush(30)


@needs_viser
def test_malformed_client_messages_do_not_take_the_server_down(room, caplog):
    import msgspec
    import viser
    from websockets.sync.client import connect

    with viewer_for() as viewer:
        viewer.show_surfaces(room)
        assert viewer.flush(30)
        before = viewer.settings
        url = f"ws://127.0.0.1:{viewer.port}"
        protocol = [f"viser-v{viser.__version__}"]
        # viser registers a client at its first camera message.
        camera = {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, 3.0), "fov": 1.0,
                  "near": 0.01, "far": 100.0, "image_height": 600, "image_width": 800, "look_at": (0.0, 0.0, 0.0),
                  "up_direction": (0.0, 0.0, 1.0)}
        for payload in (b"\x00\xffnot msgpack", msgspec.msgpack.encode({"type": "NoSuchMessage"}),
                        msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": "no such control", "updates": {}}),
                        msgspec.msgpack.encode({**camera, "fov": -1.0}),
                        msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": viewer._gui_lod._impl.uuid, "updates": {"value": 1e9}}),
                        msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": viewer._gui_method._impl.uuid,
                                                "updates": {"value": "../../etc/passwd"}})):
            try:
                with connect(url, subprotocols=protocol, open_timeout=10, close_timeout=1) as socket_:
                    socket_.send(msgspec.msgpack.encode(camera))
                    time.sleep(0.1)
                    socket_.send(payload)
                    time.sleep(0.2)
            except Exception:  # noqa: BLE001 - the server may drop the offending connection
                pass
        time.sleep(0.3)
        assert viewer.settings == before
        # The two well-formed updates reached the viewer and were refused (not merely dropped by viser).
        refused = [record.getMessage() for record in caplog.records if "ignored a GUI value" in record.getMessage()]
        assert any("lod_fraction" in message for message in refused) and any("method" in message for message in refused)
        assert any("ignored a camera update" in record.getMessage() for record in caplog.records)
        assert viewer._gui_lod.value == before.lod_fraction  # the control was put back
        # Still serving, and still drawing.
        assert page_status(viewer.port) == 200
        viewer.apply(dataclasses.replace(before, method="bars"))
        assert viewer.flush(30) and all("glyph0" in entry.nodes for entry in viewer._entries.values())


@needs_viser
def test_save_scene_writes_into_the_folder_only(tmp_path, room):
    with viewer_for(folder=tmp_path) as viewer:
        viewer.show_surfaces(room)
        assert viewer.flush(30)
        path = viewer.save_scene()
        assert path == (tmp_path / "model.viser").resolve() and path.stat().st_size > 1000
        with pytest.raises(PermissionError):
            viewer.save_scene(tmp_path.parent / "elsewhere.viser")
        # The scene and a page showing it offline; no temporary file left.
        assert sorted(p.name for p in tmp_path.iterdir()) == ["model.html", "model.viser"]
        assert "<html" in (tmp_path / "model.html").read_text()[:200].lower()


@needs_viser
def test_view_model_serves_a_saved_run(saved_run, room):
    from rangesurf.viewer import view_model

    viewer = view_model(saved_run, port=0, block=False, verbose=False)
    try:
        assert viewer.flush(30)
        assert viewer.n_surfaces == len(room)
        assert viewer.host == "127.0.0.1"
    finally:
        viewer.close()


# --------------------------------------------------------------------------
# A real browser.
# --------------------------------------------------------------------------


def _screenshot(page) -> np.ndarray:
    import cv2

    # The middle of the 3-D view, left of the control panel and below viser's notifications.
    png = page.screenshot(clip={"x": 200, "y": 160, "width": 460, "height": 440})
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.float64)


def _colourfulness(image: np.ndarray) -> float:
    """Mean spread of a pixel's three channels: 0 for grey."""
    return float((image.max(axis=2) - image.min(axis=2)).mean())


def _wait_for_picture(page, accept, timeout=30.0) -> np.ndarray:
    deadline = time.monotonic() + timeout
    while True:
        image = _screenshot(page)
        if accept(image) or time.monotonic() > deadline:
            return image
        time.sleep(0.5)


@needs_viser
@pytest.mark.slow
def test_browser_shows_the_model_and_follows_a_toggle(room):
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed: pip install playwright")
    if not CHROMIUM.exists():
        pytest.skip("Debian chromium missing: apt-get install chromium")
    with viewer_for(settings=ViewSettings(method="colour", levels=("UL1",))) as viewer:
        viewer.server.initial_camera.position = (2.2, 2.4, 1.6)
        viewer.server.initial_camera.look_at = (0.4, 0.4, 0.3)
        viewer.show_surfaces(room)
        assert viewer.flush(30)
        with sync_api.sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=BROWSER_ARGS)
            try:
                page = browser.new_page(viewport={"width": 1000, "height": 700})
                page.goto(viewer.url)
                page.wait_for_selector("canvas", timeout=30000)
                first = _wait_for_picture(page, lambda image: image.std() > 20)
                assert first.std() > 20, "the 3-D view stayed blank"
                # The page reported its camera (what automatic LOD works from).
                camera = viewer._camera
                assert camera is not None and 0 < camera.width <= 1000 and 0 < camera.height <= 700
                np.testing.assert_allclose(camera.T_world_camera[:3, 3], (2.2, 2.4, 1.6), atol=1e-3)
                # Flip the UL1 checkbox in the page: the surfaces lose their only level and turn grey.
                page.get_by_label("UL1", exact=True).click()
                deadline = time.monotonic() + 10
                while "UL1" in viewer.settings.levels and time.monotonic() < deadline:
                    time.sleep(0.1)
                assert viewer.settings.levels == ()
                assert viewer.flush(30)
                second = _wait_for_picture(page, lambda image: _colourfulness(image) < 0.5 * _colourfulness(first))
            finally:
                browser.close()
    # Grey, not blank. (The mean pixel change, 7.5 here, fell to 4.9 once under load: colour is the steadier sign.)
    assert _colourfulness(second) < 0.5 * _colourfulness(first), "flipping the toggle did not turn the surfaces grey"
    assert second.std() > 5


@needs_viser
@pytest.mark.slow
def test_saved_page_shows_the_scene_without_a_server(tmp_path, room):
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed: pip install playwright")
    if not CHROMIUM.exists():
        pytest.skip("Debian chromium missing: apt-get install chromium")
    with viewer_for(folder=tmp_path) as viewer:
        viewer.server.initial_camera.position = (2.2, 2.4, 1.6)
        viewer.server.initial_camera.look_at = (0.4, 0.4, 0.3)
        viewer.show_surfaces(room)
        assert viewer.flush(30)
        viewer.save_scene()
    # The server is gone: the page draws the scene from the data inside it.
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=BROWSER_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            page.goto((tmp_path / "model.html").as_uri())
            page.wait_for_selector("canvas", timeout=30000)
            image = _wait_for_picture(page, lambda image: image.std() > 20)
        finally:
            browser.close()
    assert image.std() > 20, "the saved page shows no scene"
