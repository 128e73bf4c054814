"""Side-by-side benchmarks against peer libraries, reported as ratios.

Each benchmark times rangesurf and, where one exists and is installed (the
``bench`` extra), a peer doing the same work in the same process. Results are
plain dicts so that `benchmarks/` can record them and the README quote them.
"""

from __future__ import annotations

import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = [
    "time_call", "time_pair", "benchmark_simulator", "benchmark_readers", "denoising_quality",
    "run_foundation_benchmarks", "write_results",
]


def time_call(function: Callable[[], object], *, repeats: int = 5, warmup: int = 1) -> float:
    """Median wall-clock seconds of ``function()`` over ``repeats`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        function()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def time_pair(ours: Callable[[], object], peer: Callable[[], object], *, repeats: int, warmup: int = 2) -> tuple[float, float]:
    """Median seconds of two calls timed alternately, so that load on the machine hits both alike."""
    for _ in range(warmup):
        ours()
        peer()
    ours_times, peer_times = [], []
    for _ in range(repeats):
        for call, times in ((ours, ours_times), (peer, peer_times)):
            started = time.perf_counter()
            call()
            times.append(time.perf_counter() - started)
    return statistics.median(ours_times), statistics.median(peer_times)


def benchmark_simulator(*, frames: int = 10, scene: str = "arena") -> list[dict]:
    """Simulated frames per second for every sensor preset (noise and mixed pixels on)."""
    from rangesurf import simulate
    from rangesurf.frame import SENSORS

    rows = []
    for name in SENSORS:
        seconds = time_call(lambda: simulate.simulate_sequence(scene, name, frames, seed=0), repeats=3)
        rows.append({"benchmark": f"simulate {scene} {name}", "frames_per_second": frames / seconds, "seconds_per_frame": seconds / frames})
    return rows


def _open3d():
    try:
        import open3d
    except ImportError:
        return None
    return open3d


def benchmark_readers(data_root: Path) -> list[dict]:
    """Load times of the real scans, against Open3D and NumPy reading the same bytes.

    The 3DTK ``.3d`` body is an ``x y z`` text file, so Open3D's ``xyz``
    reader and ``numpy.loadtxt`` read the same file (without our organized
    grid, unit conversion, masking and poses). For PCD the peer is Open3D's
    PCD reader on the same binary file.
    """
    import rangesurf
    from rangesurf import simulate

    rows = []
    open3d = _open3d()
    scan = data_root / "uos-3dtk" / "scan000.3d"
    if scan.is_file():
        ours = time_call(lambda: rangesurf.load(scan), repeats=5)
        row = {"benchmark": "load 3DTK scan000.3d (81,360 points)", "rangesurf_s": ours}
        with tempfile.TemporaryDirectory() as folder:
            body = Path(folder) / "scan000.xyz"
            body.write_text("".join(scan.read_text().splitlines(keepends=True)[1:]))
            row["numpy_loadtxt_s"] = time_call(lambda: np.loadtxt(body), repeats=3)
            if open3d is not None:
                row["open3d_s"] = time_call(lambda: open3d.io.read_point_cloud(str(body), format="xyz"), repeats=5)
        rows.append(row)
    bunny = data_root / "bunny" / "bun000.ply"
    if bunny.is_file():
        row = {"benchmark": "load bunny bun000.ply (range_grid)", "rangesurf_s": time_call(lambda: rangesurf.load(bunny), repeats=5)}
        if open3d is not None:
            row["open3d_s"] = time_call(lambda: open3d.io.read_point_cloud(str(bunny)), repeats=5)
        rows.append(row)

    frames, _ = simulate.simulate_sequence("arena", "kinect", 1, seed=0)
    with tempfile.TemporaryDirectory() as folder:
        pcd = Path(folder) / "kinect.pcd"
        rangesurf.save(pcd, frames[0])
        row = {"benchmark": "load organized binary PCD 640x480", "rangesurf_s": time_call(lambda: rangesurf.load(pcd), repeats=5)}
        if open3d is not None:
            row["open3d_s"] = time_call(lambda: open3d.io.read_point_cloud(str(pcd), remove_nan_points=False), repeats=5)
        rows.append(row)
    for row in rows:
        for peer in ("open3d_s", "numpy_loadtxt_s"):
            if peer in row:
                row[f"speedup_vs_{peer[:-2]}"] = row[peer] / row["rangesurf_s"]
    return rows


def denoising_quality(settings: dict, frames: list, truths: list) -> list[dict]:
    """RMSE reduction and depth-jump preservation of denoising settings on simulated frames.

    Parameters
    ----------
    settings : dict of name -> callable(RangeFrame) -> (H, W) range
        The denoisers to score (include ``lambda frame: frame.range`` for raw).
    frames, truths : lists of RangeFrame and simulator GroundTruth

    Returns
    -------
    list of dict
        Per setting: mean RMSE (metres; pixels with truth, not clamped), mean
        and worst RMSE reduction, and over resolvable depth jumps
        (`denoise.metrics.resolved_jump_ratios`) the fraction keeping >= 80 %
        of their height and the median kept fraction.
    """
    from rangesurf.denoise.metrics import resolved_jump_ratios

    def rmse(estimate, frame, truth) -> float:
        scored = np.isfinite(truth.range) & np.isfinite(frame.range) & np.isfinite(estimate) & ~truth.clamped
        return float(np.sqrt(np.mean((estimate - truth.range)[scored] ** 2)))

    rows = []
    for setting, run in settings.items():
        errors, raw_errors, ratios = [], [], []
        for frame, truth in zip(frames, truths):
            estimate = run(frame)
            errors.append(rmse(estimate, frame, truth))
            raw_errors.append(rmse(frame.range, frame, truth))
            ratios.append(resolved_jump_ratios(estimate, truth.range, truth.sigma))
        ratios = np.concatenate(ratios)
        reduction = np.array(raw_errors) / np.array(errors)
        rows.append({
            "setting": setting,
            "rmse_m": float(np.mean(errors)),
            "rmse_reduction_mean": float(reduction.mean()),
            "rmse_reduction_min": float(reduction.min()),
            "jumps_kept_80_percent": float(np.mean(ratios >= 0.8)),
            "jump_ratio_median": float(np.median(ratios)),
            "jumps": int(ratios.size),
        })
    return rows


def machine_description() -> str:
    """Architecture, processor model (where the system names it), cores and Python: what a benchmark ran on.

    The model matters: a table from one machine and a table from another
    differ by more than load does (an AMD EPYC virtual machine ran the same
    scripts about half as fast as the machine before it, its peers as well).
    """
    import os

    processor = ""
    try:
        with open("/proc/cpuinfo") as stream:
            processor = next((line.split(":", 1)[1].strip() for line in stream if line.startswith("model name")), "")
    except OSError:
        pass  # not Linux: the architecture alone
    named = f"{platform.machine()} ({processor})" if processor else (platform.processor() or platform.machine())
    return f"{named}, {os.cpu_count()} cores, Python {platform.python_version()}"


def run_foundation_benchmarks(data_root: Path) -> dict:
    """All foundation benchmarks in one run; returns ``{"machine", "simulator", "readers"}``."""
    return {
        "machine": machine_description(),
        "open3d": getattr(_open3d(), "__version__", None),
        "simulator": benchmark_simulator(),
        "readers": benchmark_readers(data_root),
    }


def format_results(results: dict) -> str:
    """Markdown tables of `run_foundation_benchmarks` results."""
    lines = [f"Machine: {results['machine']}; Open3D {results['open3d'] or 'not installed'}", ""]
    lines += ["| simulator | frames/s | ms/frame |", "|---|---:|---:|"]
    for row in results["simulator"]:
        lines.append(f"| {row['benchmark']} | {row['frames_per_second']:.1f} | {1000 * row['seconds_per_frame']:.1f} |")
    lines += ["", "| reader | rangesurf ms | Open3D ms | NumPy loadtxt ms | speed-up vs Open3D | vs loadtxt |", "|---|---:|---:|---:|---:|---:|"]

    def cell(value, scale=1000.0, digits=1):
        return "—" if value is None else f"{value * scale:.{digits}f}"

    for row in results["readers"]:
        lines.append(
            f"| {row['benchmark']} | {cell(row['rangesurf_s'])} | {cell(row.get('open3d_s'))} | "
            f"{cell(row.get('numpy_loadtxt_s'))} | {cell(row.get('speedup_vs_open3d'), 1, 2)}x | "
            f"{cell(row.get('speedup_vs_numpy_loadtxt'), 1, 2)}x |"
        )
    return "\n".join(lines).replace("—x", "—")


def write_results(folder: str | os.PathLike, name: str, lines: list[str]) -> str:
    """Join a benchmark's markdown lines, write them atomically to ``folder/name``, print and return them."""
    from rangesurf.io._common import atomic_write

    table = "\n".join(lines)
    with atomic_write(Path(folder) / name, "w") as stream:
        stream.write(table + "\n")
    print(table)
    return table


def default_data_root() -> Path:
    """``../shared/data`` beside the repository checkout (where tests find it too)."""
    return Path(__file__).resolve().parents[2].parent / "shared" / "data"


# Every side-by-side benchmark of benchmarks/, in pipeline order, with what it compares.
SUITE = {
    "foundation": "readers and simulator against Open3D and NumPy",
    "diffusion": "anisotropic diffusion against medpy",
    "phase": "phase-preserving denoising against phasecongruency",
    "denoise_quality": "denoising quality against OpenCV, scikit-image and medpy",
    "denoise_speed": "the whole denoising stage",
    "segmentation": "normals and planar segmentation against OpenCV RgbdNormals / RgbdPlane and Open3D",
    "lod_speed": "triangulation and progressive order against fast-simplification",
    "lod_quality": "level-of-detail accuracy against fast-simplification",
    "registration": "ICP against OpenCV ICPOdometry and Open3D",
    "drift": "tracking drift over long sequences (ATE / RPE)",
    "tsdf": "volumetric fusion against Open3D",
    "glyphs": "uncertainty geometry",
    "calibration": "uncertainty calibration against ground truth",
    "pipeline": "the whole pipeline against the same pipeline assembled from OpenCV and Open3D",
    "viewer": "the live viewer on a 25 fps stream",
}


def run_suite(benchmarks: str | os.PathLike, names: list[str] | None = None) -> Path:
    """Run benchmark scripts of ``benchmarks/`` one after another and gather their tables in ``benchmarks/results.md``.

    Each script writes its own ``results/<name>.md``; scripts not run this
    time keep their last recorded results, which are gathered as well (with
    their date), so the file always shows every comparison.
    """
    import subprocess
    import sys
    import time

    from rangesurf.io._common import atomic_write

    folder = Path(benchmarks)
    names = list(SUITE) if names is None else names
    unknown = [name for name in names if name not in SUITE]
    if unknown:
        raise ValueError(f"unknown benchmark(s) {', '.join(unknown)}; expected some of {', '.join(SUITE)}")
    ran = {}
    for name in names:
        script = folder / f"{name}.py"
        if not script.is_file():
            raise FileNotFoundError(f"{script}: benchmark script not found (rangesurf bench runs from a source checkout)")
        print(f"== {name}: {SUITE[name]}", flush=True)
        start = time.perf_counter()
        process = subprocess.run([sys.executable, str(script)], env={**os.environ, "OMP_NUM_THREADS": "1"})
        ran[name] = (process.returncode, time.perf_counter() - start)
    lines = ["# rangesurf benchmarks", "", f"Machine: {machine_description()}. Regenerate with `rangesurf bench` "
             "(all, about half an hour) or `rangesurf bench NAME ...`; each section is the named script's "
             "`benchmarks/results/NAME.md`.", ""]
    for name, description in SUITE.items():
        result = folder / "results" / f"{name}.md"
        status = ""
        if name in ran:
            code, seconds = ran[name]
            status = f" (run now, {seconds:.0f} s{', FAILED' if code else ''})"
        elif result.is_file():
            status = " (last recorded run)"
        lines += [f"## {name}: {description}{status}", ""]
        lines += [result.read_text().strip(), ""] if result.is_file() else ["Not recorded yet.", ""]
    target = folder / "results.md"
    with atomic_write(target, "w") as stream:
        stream.write("\n".join(lines))
    return target
