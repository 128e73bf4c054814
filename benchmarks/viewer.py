"""Does the viewer keep up with a 25 fps SR-3000 stream?

Run: ``.venv/bin/python benchmarks/viewer.py [--frames 100] [--no-browser]``; writes
``benchmarks/results/viewer.md``.

Two measurements over the same simulated SR-3000 sequence (arena, 176x144):

1. **Replay, unpaced**: the pipeline's `FrameResult` objects and the model's
   state after every frame are computed first; then they are fed to
   ``Viewer.update`` as fast as it returns. Reported: updates per second
   the caller can make, the time per ``update`` call, and how many of the
   frames the viewer's thread actually drew (images + timing plot) per
   second -- the display rate it sustains.
2. **Live at 25 fps**: the pipeline runs frame by frame, paced to the
   sensor's 40 ms period, once with `NullViewer` and once with `Viewer`
   (same process, alternating order does not matter: each run starts from a
   fresh pipeline). Reported: the pipeline's own ms per frame, frames over
   the 40 ms budget, the cost of ``update`` and the fraction of frames drawn.

With a headless Chromium (Debian ``chromium`` via Playwright) connected to
the viewer for both, so that every message is really sent and rendered; the
page's own frame rate (requestAnimationFrame callbacks per second, software
WebGL) is reported too.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, write_results  # noqa: E402
from rangesurf.pipeline import Pipeline  # noqa: E402
from rangesurf.viewer import NullViewer, Viewer, ViewSettings  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"]
PERIOD = 1.0 / 25.0


def model_state(model) -> SimpleNamespace:
    """What `Viewer.update` reads of the model (its meshed surfaces), frozen after one frame (for the replay)."""
    surfaces = model.meshed_surfaces()
    return SimpleNamespace(model=SimpleNamespace(meshed_surfaces=lambda: surfaces))


class Browser:
    """A headless Chromium page on the viewer, counting its animation frames."""

    def __init__(self) -> None:
        from playwright.sync_api import sync_playwright

        self._context = sync_playwright()
        self._playwright = self._context.__enter__()
        self._browser = self._playwright.chromium.launch(executable_path=str(CHROMIUM), args=BROWSER_ARGS)
        self.page = self._browser.new_page(viewport={"width": 1000, "height": 700})

    def open(self, url: str) -> None:
        self.page.goto(url)
        self.page.wait_for_selector("canvas", timeout=30000)
        time.sleep(2.0)
        self.page.evaluate("() => { window.__frames = 0; const tick = () => { window.__frames++; "
                           "requestAnimationFrame(tick); }; requestAnimationFrame(tick); }")

    def frames(self) -> int:
        return int(self.page.evaluate("() => window.__frames"))

    def close(self) -> None:
        self._browser.close()
        self._context.__exit__(None, None, None)


def record(frames) -> list:
    """Each frame's result with the model's state after it (the pipeline re-meshes every 25 frames, as for a viewer)."""
    pipeline = Pipeline()
    pipeline.live_meshes = True  # as `rangesurf run --view` has it
    return [(pipeline.process(frame), model_state(pipeline.model)) for frame in frames]


def replay(recorded, browser: Browser | None, *, paced: bool) -> dict:
    """Feed recorded results to a viewer: at 25 fps, or each one drawn completely before the next (``paced=False``)."""
    with Viewer(port=0, mesh_interval=0.5 if paced else 0.0, settings=ViewSettings(method="colour")) as viewer:
        if browser:
            browser.open(viewer.url)
            rendered = browser.frames()
        calls = []
        cpu, start = time.process_time(), time.perf_counter()
        for index, (result, state) in enumerate(recorded):
            if paced:
                wait = start + index * PERIOD - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            begin = time.perf_counter()
            viewer.update(result, state)
            calls.append(time.perf_counter() - begin)
            if not paced:
                viewer.flush(60)
        viewer.flush(60)
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
        stats = dict(viewer.stats)
        client_fps = (browser.frames() - rendered) / seconds if browser else None
    fed = len(recorded)
    return {"fed": fed, "seconds": seconds, "updates_per_second": fed / seconds, "update_ms": 1e3 * np.asarray(calls),
            "drawn": stats["frames_drawn"], "snapshots": stats["mesh_snapshots"], "surfaces": stats["surfaces_drawn"],
            "thread_ms": 1e3 * stats["busy_seconds"] / fed, "process_ms": 1e3 * cpu / fed, "client_fps": client_fps}


def live(frames, viewer, browser: Browser | None) -> dict:
    """The pipeline paced to 25 fps with ``viewer`` taking every frame."""
    pipeline = Pipeline()
    pipeline.live_meshes = isinstance(viewer, Viewer)  # re-meshing while the run goes on is for a viewer
    if browser and isinstance(viewer, Viewer):
        browser.open(viewer.url)
        rendered = browser.frames()
    totals, calls, late = [], [], 0
    cpu, start = time.process_time(), time.perf_counter()
    for index, frame in enumerate(frames):
        wait = start + index * PERIOD - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        began = time.perf_counter()
        result = pipeline.process(frame)
        before = time.perf_counter()
        viewer.update(result, pipeline)
        after = time.perf_counter()
        calls.append(after - before)
        totals.append(result.timings["total"])
        late += (after - began) > PERIOD
    viewer.flush(60)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    stats = getattr(viewer, "stats", None)
    client_fps = (browser.frames() - rendered) / seconds if browser and isinstance(viewer, Viewer) else None
    return {"pipeline_ms": np.asarray(totals), "update_ms": 1e3 * np.asarray(calls), "late": late, "fed": len(frames),
            "drawn": stats["frames_drawn"] if stats else None, "process_ms": 1e3 * cpu / len(frames),
            "client_fps": client_fps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=2, help="live runs with and without the viewer, alternating")
    parser.add_argument("--no-browser", action="store_true")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    arguments = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    frames, _ = simulate.simulate_sequence("arena", "sr3000", arguments.frames, seed=0)
    recorded = record(frames)  # also warms the compiled kernels
    browser = None
    if not arguments.no_browser:
        try:
            if not CHROMIUM.exists():
                raise FileNotFoundError(CHROMIUM)
            browser = Browser()
        except (ImportError, FileNotFoundError, OSError) as error:
            print(f"no browser ({error}); measuring without a client")
    runs = []
    try:
        paced = replay(recorded, browser, paced=True)
        flat_out = replay(recorded, browser, paced=False)
        for _ in range(arguments.rounds):
            runs.append(("NullViewer", live(frames, NullViewer(), None)))
            with Viewer(port=0) as viewer:
                runs.append(("Viewer", live(frames, viewer, browser)))
    finally:
        if browser:
            browser.close()

    def spread(values: np.ndarray) -> str:
        return f"{np.median(values):.2f} / {np.percentile(values, 95):.2f} / {values.max():.2f}"

    def fps(value) -> str:
        return "-" if value is None else f"{value:.1f}"

    client = "a headless Chromium (software WebGL, same machine) connected" if browser else "no browser connected"
    lines = [f"Machine: {machine_description()}; {arguments.frames} simulated SR-3000 frames (arena, 176x144, "
             f"sensor at 25 fps); {client}.", "",
             "Command: `.venv/bin/python benchmarks/viewer.py" + ("" if browser else " --no-browser") + "`", "",
             "## The viewer alone: recorded frame results (and model states) fed to `Viewer.update`", "",
             "| feed | updates / s | frames drawn / fed | `update` ms, median / p95 / max | viewer thread CPU ms / frame "
             "| process CPU ms / frame | mesh looks, surface renderings | browser fps |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, run in (("25 fps, meshes every 0.5 s (default)", paced),
                      ("flat out, each update drawn before the next, meshes every update", flat_out)):
        lines.append(f"| {name} | {run['updates_per_second']:.1f} | {run['drawn']} / {run['fed']} | {spread(run['update_ms'])} "
                     f"| {run['thread_ms']:.1f} | {run['process_ms']:.1f} | {run['snapshots']}, {run['surfaces']} "
                     f"| {fps(run['client_fps'])} |")
    lines += ["", "## Live: the pipeline paced to 25 fps (40 ms per frame), the viewer taking every frame", "",
              "| viewer | pipeline ms / frame, median / p95 / max | `update` ms, median / p95 / max | frames over 40 ms "
              "(pipeline + update) | frames drawn / fed | process CPU ms / frame | browser fps |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for name, run in runs:
        drawn = "-" if run["drawn"] is None else f"{run['drawn']} / {run['fed']}"
        lines.append(f"| {name} | {spread(run['pipeline_ms'])} | {spread(run['update_ms'])} | {run['late']} | {drawn} "
                     f"| {run['process_ms']:.1f} | {fps(run['client_fps'])} |")
    with_viewer = np.concatenate([run["pipeline_ms"] for name, run in runs if name == "Viewer"])
    without = np.concatenate([run["pipeline_ms"] for name, run in runs if name == "NullViewer"])
    lines += ["", f"Pipeline ms per frame with the viewer / without: {np.median(with_viewer) / np.median(without):.2f}x "
              "(medians over the rounds; the viewer's thread, viser's thread and the browser share the cores, and "
              "the first two the GIL, with the pipeline).", f"Load average at the end: {os.getloadavg()[0]:.2f}.", "",
              "Reading: the process CPU time per frame (pipeline + viewer + viser's sending, not the browser) is "
              "the measure that load from other programs does not move much; the viewer's share is the difference "
              "between the Viewer and NullViewer rows. Wall-clock columns (pipeline ms, frames over 40 ms) count "
              "every other program on the machine too. The viewer keeps up when its frames drawn / fed stays near "
              "the total and its CPU per frame plus the pipeline's stays under the 40 ms period."]
    write_results(arguments.out, "viewer.md", lines)


if __name__ == "__main__":
    main()
