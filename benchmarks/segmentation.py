"""Normals and planar segmentation, side by side with OpenCV (rgbd) and Open3D, on simulated frames.

Run: ``.venv/bin/python benchmarks/segmentation.py`` (``--quick`` for a smoke
test: 2 frames per sensor, arena only). Writes
``benchmarks/results/segmentation.md`` and ``segmentation.json`` (raw
numbers); the README quotes the full run, so rerun without ``--quick`` after a
smoke test.

Everything runs on one core: OpenCV with ``cv2.setNumThreads(1)``, Numba
(rangesurf's kernels) with one thread, Open3D with
``open3d.utility.set_max_threads(1)`` and BLAS with ``OMP_NUM_THREADS=1``
(set before any import); only the ``phase`` denoising time (two FFT threads)
is not one core.

Normals (table 1): rangesurf's three methods against OpenCV's
``RgbdNormals`` (FALS, windows 5 and 7) on simulated SR-3000 (176x144) and
Kinect (640x480) arena frames, on the raw range and on the diffusion-denoised
range. Each row is timed alternating call by call with FALS-5
(`rangesurf.bench.time_pair`). Angular error against the simulator's true
normals, on pixels every method gives a normal for.

Segmentation (table 2): the rangesurf pipeline (points, noise sigma,
adaptive normals and region growing, `segment_planes`) on the raw range and after each denoising
method, against OpenCV's ``RgbdPlane`` (on FALS-5 normals) and Open3D's
RANSAC ``segment_plane`` repeated until the planes run out, on the same
points. Hoover et al.'s classification at T = 0.8 against
`rangesurf.segment.evaluate.truth_segmentation`. The peers' parameters are picked
on a separate tuning frame; rangesurf runs with its defaults.
"""

from __future__ import annotations

import os

# One core against one core: these must be set before NumPy, Numba and Open3D load.
for _variable in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from functools import partial  # noqa: E402
from importlib import metadata  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

from rangesurf import simulate  # noqa: E402
from rangesurf.bench import machine_description, time_call, time_pair  # noqa: E402
from rangesurf.denoise import METHODS, denoise_range  # noqa: E402
from rangesurf.edges import surface_boundaries  # noqa: E402
from rangesurf.normals import estimate_normals, normal_angle_error  # noqa: E402
from rangesurf.segment import segment_planes  # noqa: E402
from rangesurf.segment.evaluate import evaluate_segmentation, truth_segmentation  # noqa: E402

try:
    import open3d
except ImportError:  # the peer columns are left out
    open3d = None

cv2.setNumThreads(1)
numba.set_num_threads(1)
if open3d is not None:
    # Open3D 0.20 parallelises RANSAC with TBB, which ignores OMP_NUM_THREADS.
    open3d.utility.set_max_threads(1)

RESULTS = Path(__file__).parent / "results"
SENSORS = {"sr3000": "176x144 SR-3000", "kinect": "640x480 Kinect"}
# Smallest region scored: 100 px at 176x144, scaled by image area elsewhere.
BASE_MIN_REGION = 100
BASE_AREA = 176 * 144
TOLERANCE = 0.8
# Pixels within this chessboard distance of a GT boundary form the "edge" band.
EDGE_BAND = 2
NORMALS_SEED = 11
SEGMENT_SEED = 21
INPUTS = ("raw",) + tuple(METHODS)
# Peer tuning grids (on a frame not scored).
PLANE_BLOCKS = (10, 20, 40)
PLANE_THRESHOLDS = (0.01, 0.02, 0.04)
RANSAC_MULTIPLES = (2.0, 3.0, 4.0)
RANSAC_ITERATIONS = 1000
RANSAC_MAX_PLANES = 30


def min_region_size(shape: tuple[int, int]) -> int:
    return int(round(BASE_MIN_REGION * shape[0] * shape[1] / BASE_AREA))


def camera_matrix(frame) -> np.ndarray:
    p = frame.sensor.projection
    return np.array([[p.fx, 0, p.cx], [0, p.fy, p.cy], [0, 0, 1]], np.float32)


def input_range(frame, name: str) -> np.ndarray:
    if name == "raw":
        return np.asarray(frame.range, np.float32)
    return denoise_range(frame.range, method=name, sensor=frame.sensor, intensity=frame.intensity, rays=frame.rays)


def points_of(frame, range_image: np.ndarray) -> np.ndarray:
    return (frame.rays * range_image[..., None]).astype(np.float32)


# --------------------------------------------------------------------------
# Normals.
# --------------------------------------------------------------------------


def fals_normals(fals, points: np.ndarray) -> np.ndarray:
    """OpenCV FALS normals of the points (NaN -> 0), turned to face the sensor."""
    normals = np.asarray(fals.apply(np.nan_to_num(points, nan=0.0)))
    flip = np.einsum("ijk,ijk->ij", normals, np.nan_to_num(points, nan=0.0)) > 0
    return np.where(flip[..., None], -normals, normals)


def normal_methods(frame, range_image: np.ndarray) -> dict:
    """Row name -> callable(points) -> normals, for one frame and input."""
    height, width = range_image.shape
    projection = frame.sensor.projection
    sigma = frame.sensor.range_sigma(range_image, frame.intensity)
    fals = {
        window: cv2.rgbd.RgbdNormals_create(height, width, cv2.CV_32F, camera_matrix(frame), window,
                                            cv2.rgbd.RgbdNormals_RGBD_NORMALS_METHOD_FALS)
        for window in (5, 7)
    }
    return {
        "rangesurf adaptive": partial(estimate_normals, projection=projection, range_sigma=sigma),
        "rangesurf box 5": partial(estimate_normals, projection=projection, method="box", window=5),
        "rangesurf cross": partial(estimate_normals, method="cross"),
        "OpenCV FALS 5": partial(fals_normals, fals[5]),
        "OpenCV FALS 7": partial(fals_normals, fals[7]),
    }


def scored_pixels(frame, truth, range_image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(flat, edge)`` masks: valid pixels away from GT boundaries and mixed pixels, and near boundaries."""
    kernel = np.ones((2 * EDGE_BAND + 1, 2 * EDGE_BAND + 1), np.uint8)
    boundary = cv2.dilate(surface_boundaries(truth.surface_id).astype(np.uint8), kernel) > 0
    near_mixed = cv2.dilate(truth.mixed.astype(np.uint8), kernel) > 0
    valid = np.isfinite(range_image) & np.isfinite(truth.normals).all(axis=2) & ~truth.outlier & ~truth.mixed
    return valid & ~boundary & ~near_mixed, valid & boundary


def benchmark_normals(sensor: str, n_frames: int, repeats: int) -> list[dict]:
    frames, truths = simulate.simulate_sequence("arena", sensor, n_frames, seed=NORMALS_SEED)
    records = []
    for input_name in ("raw", "diffusion"):
        for index, (frame, truth) in enumerate(zip(frames, truths)):
            range_image = input_range(frame, input_name)
            points = points_of(frame, range_image)
            methods = normal_methods(frame, range_image)
            flat, edge = scored_pixels(frame, truth, range_image)
            results = {name: run(points) for name, run in methods.items()}
            # Score every method on the same pixels: those all of them give a normal for.
            common = np.logical_and.reduce([np.isfinite(n).all(axis=2) for n in results.values()])
            reference = methods["OpenCV FALS 5"]
            for name, run in methods.items():
                ours_s, peer_s = time_pair(partial(run, points), partial(reference, points), repeats=repeats)
                error = normal_angle_error(results[name], truth.normals)
                has_normal = np.isfinite(results[name]).all(axis=2)
                records.append({
                    "sensor": sensor, "input": input_name, "frame": index, "method": name,
                    "seconds": ours_s, "fals5_seconds": peer_s, "speed_ratio_vs_fals5": peer_s / ours_s,
                    "flat_errors_deg": error[flat & common].tolist(),
                    "edge_errors_deg": error[edge & common].tolist(),
                    "flat_coverage": float(has_normal[flat].mean()),
                    "edge_coverage": float(has_normal[edge].mean()),
                })
    return records


def summarise_normals(records: list[dict]) -> list[dict]:
    rows = []
    keys = dict.fromkeys((r["sensor"], r["input"], r["method"]) for r in records)
    for sensor, input_name, method in keys:
        group = [r for r in records if (r["sensor"], r["input"], r["method"]) == (sensor, input_name, method)]
        flat = np.concatenate([r["flat_errors_deg"] for r in group])
        edge = np.concatenate([r["edge_errors_deg"] for r in group])
        rows.append({
            "sensor": sensor, "input": input_name, "method": method, "frames": len(group),
            "ms_per_frame": 1e3 * statistics.median(r["seconds"] for r in group),
            "speed_ratio_vs_fals5": statistics.median(r["speed_ratio_vs_fals5"] for r in group),
            "flat_mean_deg": float(flat.mean()), "flat_median_deg": float(np.median(flat)), "flat_pixels": int(flat.size),
            "edge_mean_deg": float(edge.mean()), "edge_median_deg": float(np.median(edge)), "edge_pixels": int(edge.size),
            "flat_coverage": float(np.mean([r["flat_coverage"] for r in group])),
            "edge_coverage": float(np.mean([r["edge_coverage"] for r in group])),
        })
    return rows


# --------------------------------------------------------------------------
# Segmenters: each takes the frame's input range and returns (labels, planes).
# --------------------------------------------------------------------------


def rangesurf_segment(frame, range_image: np.ndarray):
    points = points_of(frame, range_image)
    sigma = frame.sensor.range_sigma(range_image, frame.intensity)
    segmentation = segment_planes(points, range_sigma=sigma, projection=frame.sensor.projection)
    return segmentation.labels, segmentation.planes


class RgbdPlaneSegmenter:
    """OpenCV ``RgbdPlane`` on FALS-5 normals; its mask is 255 where no plane, else the plane's index."""

    def __init__(self, frame, *, block_size: int, threshold: float, sensor_error: bool, min_size: int):
        height, width = frame.range.shape
        noise = frame.sensor.noise
        errors = (noise.quadratic, noise.relative, noise.floor) if sensor_error else (0.0, 0.0, 0.0)
        self.setting = {"block_size": block_size, "min_size": min_size, "threshold": threshold,
                        "sensor_error_abc": list(errors)}
        self.fals = cv2.rgbd.RgbdNormals_create(height, width, cv2.CV_32F, camera_matrix(frame), 5,
                                                cv2.rgbd.RgbdNormals_RGBD_NORMALS_METHOD_FALS)
        self.plane = cv2.rgbd.RgbdPlane_create(cv2.rgbd.RgbdPlane_RGBD_PLANE_METHOD_DEFAULT, block_size, min_size,
                                               threshold, *errors)

    def prepare(self, frame, range_image):
        """``(points with NaN -> 0, FALS normals)``: the input of `planes_only`."""
        points = np.nan_to_num(points_of(frame, range_image), nan=0.0)
        return points, np.asarray(self.fals.apply(points))

    def planes_only(self, points, normals):
        mask, coefficients = self.plane.apply(points, normals)
        mask = np.asarray(mask)
        labels = np.where(mask == 255, 0, mask.astype(np.int32) + 1)
        # With no plane found the coefficients come back as a 1-element placeholder.
        coefficients = np.asarray(coefficients, dtype=np.float64).ravel()
        coefficients = coefficients[: coefficients.size // 4 * 4].reshape(-1, 4)
        planes = np.full((max(int(labels.max()), len(coefficients)) + 1, 4), np.nan)
        planes[1:len(coefficients) + 1] = coefficients
        return labels, planes

    def __call__(self, frame, range_image):
        return self.planes_only(*self.prepare(frame, range_image))


class RansacSegmenter:
    """Open3D ``segment_plane`` repeated on the remaining valid points."""

    def __init__(self, *, multiple: float, min_size: int, seed: int = 0):
        self.multiple, self.min_size, self.seed = multiple, min_size, seed
        self.setting = {"distance_threshold": f"{multiple:g} x median sensor sigma", "ransac_n": 3,
                        "num_iterations": RANSAC_ITERATIONS, "max_planes": RANSAC_MAX_PLANES, "min_inliers": min_size}

    def __call__(self, frame, range_image):
        open3d.utility.random.seed(self.seed)
        points = points_of(frame, range_image)
        valid = np.isfinite(points).all(axis=2).ravel()
        threshold = self.multiple * float(np.nanmedian(frame.sensor.range_sigma(range_image, frame.intensity)))
        index = np.flatnonzero(valid)
        cloud = open3d.geometry.PointCloud(open3d.utility.Vector3dVector(points.reshape(-1, 3)[index].astype(np.float64)))
        labels = np.zeros(valid.size, np.int32)
        planes = [np.full(4, np.nan)]
        while len(index) >= self.min_size and len(planes) <= RANSAC_MAX_PLANES:
            model, inliers = cloud.segment_plane(distance_threshold=threshold, ransac_n=3,
                                                 num_iterations=RANSAC_ITERATIONS)
            if len(inliers) < self.min_size:
                break
            inliers = np.asarray(inliers, dtype=np.int64)
            labels[index[inliers]] = len(planes)
            planes.append(np.asarray(model, dtype=np.float64))
            keep = np.ones(len(index), bool)
            keep[inliers] = False
            # select_by_index keeps the order of the points left, so `index` still maps them to pixels.
            cloud = cloud.select_by_index(inliers, invert=True)
            index = index[keep]
        return labels.reshape(range_image.shape), np.array(planes)


def score(truth, frame, labels, planes) -> dict:
    gt = truth_segmentation(truth, frame.rays)
    scores = evaluate_segmentation(gt.labels, labels, tolerance=TOLERANCE,
                                   truth_planes=gt.planes, machine_planes=planes,
                                   min_region_size=min_region_size(labels.shape))
    return {"n_truth": scores.n_truth, "n_machine": scores.n_machine, "correct": scores.correct,
            "over": scores.over_segmented, "under": scores.under_segmented, "missed": scores.missed,
            "noise": scores.noise, "normal_errors_deg": list(scores.normal_errors_deg)}


def tune(candidates: list, frame, truth, inputs: dict) -> tuple[object, list[dict]]:
    """The candidate with most correct detections over all inputs of the tuning frame (then fewest errors)."""
    trials = []
    for candidate in candidates:
        total = {"correct": 0, "errors": 0}
        for range_image in inputs.values():
            result = score(truth, frame, *candidate(frame, range_image))
            total["correct"] += result["correct"]
            total["errors"] += result["over"] + result["under"] + result["missed"] + result["noise"]
        trials.append({"setting": candidate.setting, **total})
    best = max(range(len(candidates)), key=lambda i: (trials[i]["correct"], -trials[i]["errors"], -i))
    return candidates[best], trials


def time_stream(ours: list, peer: list, *, passes: int) -> list[tuple[float, float]]:
    """(ours, peer) seconds of each frame's calls, the frames taken in turn ``passes`` times after one pass of warm-up.

    A stream brings a new frame every call; calling one frame again and again (`time_pair`) lets the processor's
    branch predictor learn that frame, which flatters branchy code (the region-growing steps took about twice as
    long on frames in turn as on one frame repeated).
    """
    for call in (*ours, *peer):
        call()
    times = []
    for _ in range(passes):
        for ours_call, peer_call in zip(ours, peer):
            started = time.perf_counter()
            ours_call()
            middle = time.perf_counter()
            peer_call()
            times.append((middle - started, time.perf_counter() - middle))
    return times


def benchmark_segmentation(sensor: str, scenes: tuple[str, ...], n_frames: int, repeats: int) -> dict:
    records, tuning, streamed = [], {}, []
    for scene in scenes:
        # The tuning frame: one more frame of the scene, after those scored.
        frames, truths = simulate.simulate_sequence(scene, sensor, n_frames + 1, seed=SEGMENT_SEED)
        tuning_frame, tuning_truth = frames[-1], truths[-1]
        min_size = min_region_size(tuning_frame.range.shape)
        tuning_inputs = {name: input_range(tuning_frame, name) for name in INPUTS}
        plane_candidates = [
            RgbdPlaneSegmenter(tuning_frame, block_size=block, threshold=threshold, sensor_error=error, min_size=min_size)
            for block in PLANE_BLOCKS for threshold in PLANE_THRESHOLDS for error in (False, True)
        ]
        plane, plane_trials = tune(plane_candidates, tuning_frame, tuning_truth, tuning_inputs)
        ransac_best, ransac_trials = None, []
        if open3d is not None:
            ransac_candidates = [RansacSegmenter(multiple=m, min_size=min_size) for m in RANSAC_MULTIPLES]
            ransac_best, ransac_trials = tune(ransac_candidates, tuning_frame, tuning_truth, tuning_inputs)
        tuning[scene] = {
            "rgbd_plane_setting": plane.setting, "rgbd_plane_tuning": plane_trials,
            "ransac_setting": None if ransac_best is None else ransac_best.setting, "ransac_tuning": ransac_trials,
        }
        for index, (frame, truth) in enumerate(zip(frames[:n_frames], truths[:n_frames])):
            for input_name in INPUTS:
                denoise_s = 0.0 if input_name == "raw" else time_call(lambda: input_range(frame, input_name), repeats=repeats)
                range_image = input_range(frame, input_name)
                base = {"sensor": sensor, "scene": scene, "frame": index, "input": input_name, "denoise_seconds": denoise_s}
                ours = partial(rangesurf_segment, frame, range_image)
                peer = partial(plane, frame, range_image)
                ours_s, peer_s = time_pair(ours, peer, repeats=repeats)
                prepared = plane.prepare(frame, range_image)
                plane_only_s = time_call(partial(plane.planes_only, *prepared), repeats=repeats)
                # Per stage, each timed on its own.
                points = points_of(frame, range_image)
                sigma = frame.sensor.range_sigma(range_image, frame.intensity)
                stages = {
                    "points_sigma_seconds": time_call(
                        lambda: (points_of(frame, range_image), frame.sensor.range_sigma(range_image, frame.intensity)),
                        repeats=repeats),
                    "segment_planes_seconds": time_call(
                        partial(segment_planes, points, range_sigma=sigma, projection=frame.sensor.projection),
                        repeats=repeats),
                    # segment_planes estimates its normals on its (decimated) growing grid; there is no
                    # separate full-resolution normal step to subtract.
                    "seconds_without_normals": float("nan"),
                }
                records.append({**base, "segmenter": "rangesurf", "seconds": ours_s, **stages,
                                **score(truth, frame, *ours())})
                records.append({**base, "segmenter": "OpenCV RgbdPlane", "seconds": peer_s,
                                "seconds_without_normals": plane_only_s, "rangesurf_seconds_paired": ours_s,
                                **score(truth, frame, *peer())})
                if ransac_best is not None:
                    run = partial(ransac_best, frame, range_image)
                    ransac_s = time_call(run, repeats=max(1, repeats // 2), warmup=0)
                    records.append({**base, "segmenter": "Open3D RANSAC", "seconds": ransac_s,
                                    "seconds_without_normals": ransac_s,
                                    **score(truth, frame, *run())})
        for input_name in INPUTS:
            inputs = [(frame, input_range(frame, input_name)) for frame in frames[:n_frames]]
            times = time_stream([partial(rangesurf_segment, *pair) for pair in inputs],
                                [partial(plane, *pair) for pair in inputs], passes=repeats)
            streamed.append({"scene": scene, "input": input_name, "seconds": times})
    return {
        "sensor": sensor, "min_region_size": min_size, "tuning": tuning,
        "records": records, "streamed": streamed,
    }


def summarise_segmentation(records: list[dict]) -> list[dict]:
    rows = []
    keys = dict.fromkeys((r["sensor"], r["scene"], r["input"], r["segmenter"]) for r in records)
    for key in keys:
        group = [r for r in records if (r["sensor"], r["scene"], r["input"], r["segmenter"]) == key]
        errors = [e for r in group for e in r["normal_errors_deg"]]
        row = dict(zip(("sensor", "scene", "input", "segmenter"), key))
        row.update({
            "frames": len(group),
            **{k: sum(r[k] for r in group) for k in ("n_truth", "correct", "over", "under", "missed", "noise")},
            "normal_error_deg": float(np.mean(errors)) if errors else None,
            "ms_per_frame": 1e3 * statistics.median(r["seconds"] for r in group),
            "denoise_ms_per_frame": 1e3 * statistics.median(r["denoise_seconds"] for r in group),
        })
        row["ms_per_frame_without_normals"] = 1e3 * statistics.median(r["seconds_without_normals"] for r in group)
        if "rangesurf_seconds_paired" in group[0]:
            row["speed_ratio"] = statistics.median(r["seconds"] / r["rangesurf_seconds_paired"] for r in group)
        rows.append(row)
    return rows


def comparison(records: list[dict], streamed: dict[str, list[dict]]) -> list[dict]:
    """Per sensor and input, over scenes and frames: rangesurf's correct minus each peer's, and the speed ratios
    (each frame repeated, and the frames streamed: `time_stream`)."""
    rows = []
    for sensor, input_name in dict.fromkeys((r["sensor"], r["input"]) for r in records):
        stream = [pair for run in streamed[sensor] if run["input"] == input_name for pair in run["seconds"]]
        group = [r for r in records if r["sensor"] == sensor and r["input"] == input_name]
        correct = {}
        for r in group:
            correct[r["segmenter"]] = correct.get(r["segmenter"], 0) + r["correct"]
        planes = [r for r in group if r["segmenter"] == "OpenCV RgbdPlane"]
        rows.append({
            "sensor": sensor, "input": input_name,
            "n_truth": sum(r["n_truth"] for r in planes),
            "correct": correct,
            "minus_rgbd_plane": correct["rangesurf"] - correct["OpenCV RgbdPlane"],
            "minus_ransac": correct["rangesurf"] - correct["Open3D RANSAC"] if "Open3D RANSAC" in correct else None,
            "speed_ratio_vs_rgbd_plane": statistics.median(r["seconds"] / r["rangesurf_seconds_paired"] for r in planes),
            "speed_ratio_vs_rgbd_plane_without_normals": statistics.median(
                r["seconds_without_normals"] / r["rangesurf_seconds_paired"] for r in planes),
            "streamed_ratio_vs_rgbd_plane": statistics.median(peer / ours for ours, peer in stream),
        })
    return rows


# --------------------------------------------------------------------------
# Report.
# --------------------------------------------------------------------------


def source_state() -> str:
    """Newest modification time of the rangesurf sources (others edit them; a run must not straddle a change)."""
    import rangesurf

    newest = max(path.stat().st_mtime for path in Path(rangesurf.__file__).parent.rglob("*.py"))
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(newest))


def versions() -> dict:
    found = {"opencv": cv2.__version__, "numpy": np.__version__, "numba": numba.__version__,
             "open3d": getattr(open3d, "__version__", None)}
    try:
        found["rangesurf"] = metadata.version("rangesurf")
    except metadata.PackageNotFoundError:
        found["rangesurf"] = None
    return found


def format_report(results: dict) -> str:
    config = results["config"]
    v = results["versions"]
    lines = [
        "# Normals and planar segmentation against OpenCV and Open3D",
        "",
        f"Command: `{results['command']}`",
        "",
        f"Machine: {results['machine']}; OpenCV {v['opencv']} (contrib, `cv2.rgbd`), Open3D {v['open3d']}, "
        f"NumPy {v['numpy']}, Numba {v['numba']}. Total run time {results['run_seconds'] / 60:.1f} min. "
        f"rangesurf sources last modified {results['source_modified'][0]}"
        + ("" if results["source_modified"][0] == results["source_modified"][1] else
           f" and again during the run ({results['source_modified'][1]}): the numbers mix two versions, rerun")
        + ".",
        "",
        "One core against one core: `cv2.setNumThreads(1)`, Numba with one thread (rangesurf's kernels are "
        "single-threaded), `open3d.utility.set_max_threads(1)` (Open3D 0.20's RANSAC runs on TBB threads, which "
        "`OMP_NUM_THREADS` does not limit) and `OMP_NUM_THREADS=1` for BLAS; the one exception is the `phase` "
        "denoising column (rangesurf's FFT stage uses two threads), which no peer is compared with. Times are medians over frames of each frame's "
        "median wall-clock time (after warm-up calls); speed ratios are peer time / rangesurf time (> 1: rangesurf "
        "faster), the median over frames of ratios from calls timed alternately (`rangesurf.bench.time_pair`), so "
        "load on the machine hits both alike.",
        "",
        "## Normals",
        "",
        f"{config['normal_frames']} simulated arena frames per sensor (seed {NORMALS_SEED}, all noise effects on), on the "
        "raw range and on the `diffusion`-denoised range (`denoise_range`, which first removes outliers). rangesurf "
        "adaptive gets the sensor's projection and the noise sigma of the input range; box (window 5) the projection; "
        "cross neither. OpenCV `RgbdNormals` FALS gets the camera matrix and the points with NaN set to 0; its normals "
        "are turned to face the sensor before scoring. Error: angle to the simulator's true normal. *Flat* pixels: "
        f"valid (input range finite, not a salt-and-pepper or mixed pixel), more than {EDGE_BAND} pixels "
        f"(chessboard) from a ground-truth surface boundary and from a mixed pixel; *edge*: valid and within {EDGE_BAND} "
        "pixels of a boundary. Errors are over the pixels every method gives a normal for (the same pixels for all "
        "rows of a sensor and input); coverage is the share of flat / edge pixels the method gives a normal for. "
        "Each row is timed alternating with FALS-5.",
        "",
        "| sensor | input | method | ms/frame | speed ratio vs FALS-5 | flat mean (deg) | flat median (deg) "
        "| edge mean (deg) | coverage flat / edge |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in results["normals"]:
        lines.append(
            f"| {SENSORS[row['sensor']]} | {row['input']} | {row['method']} | {row['ms_per_frame']:.2f} "
            f"| {row['speed_ratio_vs_fals5']:.2f}x | {row['flat_mean_deg']:.2f} | {row['flat_median_deg']:.2f} "
            f"| {row['edge_mean_deg']:.2f} | {100 * row['flat_coverage']:.1f} % / {100 * row['edge_coverage']:.1f} % |"
        )
    counts = {(r["sensor"], r["input"]): (r["flat_pixels"], r["edge_pixels"]) for r in results["normals"]}
    lines += ["", "Scored pixels (flat / edge, all frames): " + "; ".join(
        f"{SENSORS[s]} {i}: {f:,} / {e:,}" for (s, i), (f, e) in counts.items()) + "."]

    seg = results["segmentation"]
    scenes = " and ".join(config["scenes"])
    lines += [
        "",
        "## Planar segmentation",
        "",
        f"Simulated {scenes} frames (seed {SEGMENT_SEED}, all noise effects on): "
        + ", ".join(f"{config['segment_frames'][s]} per scene at {SENSORS[s]}" for s in config["sensors"]) + ". "
        f"Hoover et al.'s classification at T = {TOLERANCE} (`evaluate_segmentation`) against `truth_segmentation` (grazing "
        "> 80 deg, mixed, salt-and-pepper and non-planar pixels unlabelled; every surface split into its connected "
        "parts, as SegComp's ground-truth regions are connected: a wall interrupted by a door recess is two regions). Regions smaller than 100 px at 176x144, "
        "scaled by image area elsewhere ("
        + ", ".join(f"{SENSORS[s]}: {seg[s]['min_region_size']} px" for s in config["sensors"])
        + "), are left out of the scoring for every segmenter. *correct* is summed over frames, out of all GT "
        "regions of those frames; over / under / missed / noise likewise; normal error is the mean angle between "
        "GT and machine plane normals over the correct detections.",
        "",
        "Inputs: `raw` is the simulated range as read; the others are `denoise_range(method=...)` (each first removes "
        "cut-off readings, isolated spikes and flying pixels; `none` does only that). Denoising time is its own "
        "column and is in no segmenter's time. rangesurf: points, noise sigma and `segment_planes` (adaptive "
        "normals and `grow_regions` on a grid decimated to about 40,000 pixels -- none at 176x144, 3x at 640x480 -- "
        "then `refine_upsampled` at full resolution) with its defaults, untuned; its time covers all of it. OpenCV `RgbdPlane`: points "
        "(NaN -> 0) and FALS-5 normals, time including the FALS normals and, separately, `RgbdPlane.apply` alone. "
        f"Open3D: `segment_plane(distance_threshold, ransac_n=3, num_iterations={RANSAC_ITERATIONS})` repeated on the "
        f"points not yet taken until a plane has fewer than the minimum region size of inliers, or "
        f"{RANSAC_MAX_PLANES} planes; one label per plane (a RANSAC plane may cover several coplanar, disconnected "
        "surfaces, which then scores as an under-segmentation or noise); random seed fixed.",
        "",
        "Peer parameters were picked per sensor and scene on one further frame of that scene's sequence (not "
        "scored), by the most correct detections summed over all five inputs, then the fewest other "
        "classifications. RgbdPlane grid: block_size "
        f"{'/'.join(map(str, PLANE_BLOCKS))}, threshold {'/'.join(map(str, PLANE_THRESHOLDS))} m, sensor error "
        "(a, b, c) zero or the sensor model's (quadratic, relative, floor) terms; min_size = the minimum region "
        f"size. Open3D: distance threshold {'/'.join(f'{m:g}' for m in RANSAC_MULTIPLES)} x the frame's median "
        "noise sigma. Chosen (correct detections on the tuning frame over the five inputs, best and worst of the "
        "grid):",
        "",
    ]
    for sensor in config["sensors"]:
        for scene, s in seg[sensor]["tuning"].items():
            best = next(t for t in s["rgbd_plane_tuning"] if t["setting"] == s["rgbd_plane_setting"])
            setting = s["rgbd_plane_setting"]
            line = (f"* {SENSORS[sensor]}, {scene}: RgbdPlane block_size {setting['block_size']}, threshold "
                    f"{setting['threshold']} m, sensor error {'model' if any(setting['sensor_error_abc']) else 'zero'} "
                    f"({best['correct']} correct; grid {min(t['correct'] for t in s['rgbd_plane_tuning'])}"
                    f"-{best['correct']})")
            if s["ransac_setting"] is not None:
                tried = ", ".join(f"{m:g}x: {t['correct']}" for m, t in zip(RANSAC_MULTIPLES, s["ransac_tuning"]))
                line += f"; Open3D {s['ransac_setting']['distance_threshold']} ({tried})"
            lines.append(line + ".")
    lines += [
        "",
        "| sensor | scene | input | denoise ms | segmenter | correct / GT | over | under | missed | noise "
        "| normal error (deg) | ms/frame | ms/frame without normals |",
        "|---|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for sensor in config["sensors"]:
        for row in seg[sensor]["summary"]:
            pct = 100 * row["correct"] / row["n_truth"] if row["n_truth"] else float("nan")
            error = "—" if row["normal_error_deg"] is None else f"{row['normal_error_deg']:.2f}"
            denoise = "—" if row["input"] == "raw" else f"{row['denoise_ms_per_frame']:.1f}"
            lines.append(
                f"| {SENSORS[sensor]} | {row['scene']} | {row['input']} | {denoise} | {row['segmenter']} "
                f"| {row['correct']} / {row['n_truth']} ({pct:.0f} %) | {row['over']} | {row['under']} "
                f"| {row['missed']} | {row['noise']} | {error} | {row['ms_per_frame']:.1f} "
                f"| {'—' if row['ms_per_frame_without_normals'] != row['ms_per_frame_without_normals'] else format(row['ms_per_frame_without_normals'], '.1f')} |"
            )
    lines += [
        "",
        "Summary per sensor and input, over scenes and frames: rangesurf's correct detections minus each peer's, and "
        "the speed ratio against RgbdPlane (RgbdPlane time / rangesurf time, alternating; with RgbdPlane's FALS "
        "normals, and with `RgbdPlane.apply` alone against the whole rangesurf pipeline). *Streamed*: the same "
        "ratio (with FALS) with a new frame every call, the sequence's frames taken in turn, as a stream brings "
        "them (`time_stream`); the other columns call each frame repeatedly, which lets the processor's branch "
        "predictor learn it.",
        "",
        "| sensor | input | GT regions | correct: rangesurf / RgbdPlane / Open3D | rangesurf - RgbdPlane "
        "| rangesurf - Open3D | speed ratio vs RgbdPlane (with FALS) | (RgbdPlane.apply alone) | streamed |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in results["comparison"]:
        c = row["correct"]
        lines.append(
            f"| {SENSORS[row['sensor']]} | {row['input']} | {row['n_truth']} | {c['rangesurf']} / "
            f"{c['OpenCV RgbdPlane']} / {c.get('Open3D RANSAC', '—')} | {row['minus_rgbd_plane']:+d} "
            f"| {'—' if row['minus_ransac'] is None else format(row['minus_ransac'], '+d')} "
            f"| {row['speed_ratio_vs_rgbd_plane']:.2f}x | {row['speed_ratio_vs_rgbd_plane_without_normals']:.2f}x "
            f"| {row['streamed_ratio_vs_rgbd_plane']:.2f}x |"
        )
    if "kinect" in seg:
        lines += [
            "",
            "rangesurf per stage at 640x480 (each timed on its own with `time_call`; median over frames and "
            "scenes). `segment_planes` grows regions on the grid decimated 3x (normals included) and refines them at "
            "full resolution:",
            "",
            "| input | points + sigma ms | segment_planes ms |",
            "|---|---:|---:|",
        ]
        for input_name in INPUTS:
            group = [r for r in seg["kinect"]["records"] if r["segmenter"] == "rangesurf" and r["input"] == input_name]
            prep = 1e3 * statistics.median(r["points_sigma_seconds"] for r in group)
            planes = 1e3 * statistics.median(r["segment_planes_seconds"] for r in group)
            lines.append(f"| {input_name} | {prep:.1f} | {planes:.1f} |")
    lines += [
        "",
        f"Load average (1, 5, 15 min) at the end of the run: {', '.join(f'{x:.2f}' for x in results['load_average'])}; "
        "the machine's two cores are shared with other work, so single timings vary by several per cent between "
        "runs; the alternating ratios are steadier than the absolute times.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 frames per sensor, arena only (smoke test)")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    source_before = source_state()
    sensors = tuple(SENSORS)
    config = {
        "quick": args.quick,
        "sensors": sensors,
        "scenes": ("arena",) if args.quick else ("arena", "corridor"),
        "normal_frames": 2 if args.quick else 6,
        "segment_frames": {"sr3000": 2, "kinect": 2} if args.quick else {"sr3000": 8, "kinect": 4},
        "repeats": 3 if args.quick else 5,
        "tolerance": TOLERANCE,
    }
    normal_records = []
    for sensor in sensors:
        normal_records += benchmark_normals(sensor, config["normal_frames"], config["repeats"])
        print(f"normals {sensor} done ({time.perf_counter() - started:.0f} s)", file=sys.stderr)
    segmentation = {}
    for sensor in sensors:
        result = benchmark_segmentation(sensor, config["scenes"], config["segment_frames"][sensor], config["repeats"])
        result["summary"] = summarise_segmentation(result["records"])
        segmentation[sensor] = result
        print(f"segmentation {sensor} done ({time.perf_counter() - started:.0f} s)", file=sys.stderr)
    records = [r for s in segmentation.values() for r in s["records"]]
    results = {
        "command": ".venv/bin/python benchmarks/segmentation.py" + (" --quick" if args.quick else ""),
        "machine": machine_description(),
        "versions": versions(),
        "config": config,
        "normals": summarise_normals(normal_records),
        "segmentation": segmentation,
        "comparison": comparison(records, {sensor: result["streamed"] for sensor, result in segmentation.items()}),
    }
    results["run_seconds"] = time.perf_counter() - started
    results["source_modified"] = [source_before, source_state()]
    results["load_average"] = list(os.getloadavg())
    text = format_report(results)
    (RESULTS / "segmentation.md").write_text(text)
    raw = dict(results, normal_records=[
        {k: v for k, v in r.items() if not k.endswith("errors_deg")} for r in normal_records])
    (RESULTS / "segmentation.json").write_text(json.dumps(raw, indent=1, default=float) + "\n")
    print(text)
    return results


if __name__ == "__main__":
    main()
