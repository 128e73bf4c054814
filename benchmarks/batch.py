"""Batch runs on Dask: wall time of a batch of recordings on 1 and 2 worker processes.

Run: ``.venv/bin/python benchmarks/batch.py [N_FRAMES] [ROUNDS]`` (default 60 and 3);
writes ``benchmarks/results/batch.md``. Needs ``pip install 'rangesurf[distributed]'``.

A batch of four simulated SR-3000 recordings (two of the arena, two of the
corridor, each with its own seed) goes through `rangesurf.batch.run_batch`:

* end to end, with the local cluster it starts (and closes) itself, on 1
  and on 2 worker processes;
* on an already running cluster of 1 and of 2 warm worker processes,
  passed by address (the scaling of the work alone, without the cluster's
  start and the workers' first imports);
* for reference, the same four `rangesurf.runner.run` calls one after the
  other in this process;
* three of the recordings on the warm 2-worker cluster, one task per
  recording against chains of parts (`run_batch`'s ``part_frames``).

Each is timed ``ROUNDS`` times, interleaved; the table shows the fastest
(others share this machine) and every round. Every batch's trajectories
and models are compared byte for byte with the sequential runs'. Last, the
cost of one Dask task that carries a frame to a worker and its points back,
against the per-frame stages that could run as such tasks: why there are
no per-frame tasks; and the CPU time of one recording in this process, in a worker
of `run_batch`'s local cluster and in a worker of a default Dask one.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import logging  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from rangesurf.batch import PART_FRAMES, _local_cluster, output_names, run_batch  # noqa: E402
from rangesurf.bench import machine_description, write_results  # noqa: E402
from rangesurf.runner import run  # noqa: E402

INPUTS = ["sim:arena", "sim:corridor", "sim:arena", "sim:corridor"]
SEEDS = [1, 2, 3, 4]
COMPARED = ("trajectory.txt", "model.ply")


def sequential(root: Path, n_frames: int) -> float:
    started = time.perf_counter()
    with threadpool_limits(limits=1):
        for spec, seed, name in zip(INPUTS, SEEDS, output_names(INPUTS, SEEDS)):
            run(spec, root / name, frames=n_frames, seed=seed, overwrite=True, progress=False)
    return time.perf_counter() - started


def independent_stage_ms(reference: Path) -> float:
    """Median per frame of the stages that need no other frame (denoise, segment, segment vertices)."""
    import csv

    totals = []
    for name in output_names(INPUTS, SEEDS):
        with open(reference / name / "timings.csv", newline="") as stream:
            totals += [sum(float(row[stage]) for stage in ("denoise", "segment", "surfaces")) for row in csv.DictReader(stream)]
    return float(np.median(totals))


def source_times() -> dict[str, float]:
    """Modification times of the package's sources: others edit this checkout, and a change mid-run changes outputs."""
    import rangesurf

    package = Path(rangesurf.__file__).parent
    return {str(path): path.stat().st_mtime for path in package.rglob("*.py")}


def identical(reference: Path, batch_out: Path, count: int = len(INPUTS)) -> bool:
    """Whether the first ``count`` recordings' outputs are the sequential runs' bytes."""
    names = output_names(INPUTS, SEEDS)[:count]
    return all((reference / name / file).read_bytes() == (batch_out / name / file).read_bytes()
               for name in names for file in COMPARED)


def warm_cluster(workers: int):
    """The local cluster `run_batch` starts, kept running, its workers warmed up."""
    import distributed

    cluster = _local_cluster(distributed, workers)
    with distributed.Client(cluster) as client:
        # Imports and Numba's cached kernels loaded in every worker: what is left is the work.
        client.run(_warm_up)
    return cluster


def worker_cpu_seconds(n_frames: int) -> dict[str, float]:
    """CPU seconds of one recording in this process, in a worker of `run_batch`'s cluster, and of Dask's default one."""
    import distributed

    folder = tempfile.mkdtemp(prefix="rangesurf-batch-cpu-")
    seconds = {"in process": min(_recording_cpu(folder, n_frames) for _ in range(2))}
    def plain():
        return distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                        scheduler_kwargs={"dashboard_address": ":0"}, silence_logs=logging.CRITICAL)

    # Default first: its nanny leaves MALLOC_TRIM_THRESHOLD_ in this process's environment for later clusters.
    for label, start in (("default Dask worker", plain), ("run_batch worker", lambda: _local_cluster(distributed, 1)),
                         ("run_batch worker after a default one", lambda: _local_cluster(distributed, 1))):
        with start() as cluster, distributed.Client(cluster) as client:
            client.submit(_recording_cpu, folder, 2, pure=False).result()
            seconds[label] = min(client.submit(_recording_cpu, folder, n_frames, pure=False).result() for _ in range(2))
    shutil.rmtree(folder, ignore_errors=True)
    return seconds


def _recording_cpu(folder: str, n_frames: int) -> float:
    started = time.thread_time()
    with threadpool_limits(limits=1):
        run("sim:arena", folder, frames=n_frames, seed=1, overwrite=True, progress=False)
    return time.thread_time() - started


def _warm_up() -> None:
    with tempfile.TemporaryDirectory() as folder:
        run("sim:arena", folder, frames=2, overwrite=True, progress=False)


def task_cost(n_tasks: int = 200) -> tuple[float, float]:
    """(ms per task one at a time, ms per task when 2 workers have many queued): a frame's points there and back."""
    import distributed

    from rangesurf import simulate

    frames, _ = simulate.simulate_sequence("arena", "sr3000", n_frames=1, seed=0)
    frame = frames[0]
    with _local_cluster(distributed, 2) as cluster, distributed.Client(cluster) as client:
        client.submit(_points, frame, pure=False).result()
        started = time.perf_counter()
        for _ in range(50):
            client.submit(_points, frame, pure=False).result()
        one = 1e3 * (time.perf_counter() - started) / 50
        started = time.perf_counter()
        client.gather(client.map(_points, [frame] * n_tasks, pure=False))
        many = 1e3 * (time.perf_counter() - started) / n_tasks
    return one, many


def _points(frame) -> np.ndarray:
    return (frame.rays * frame.range[..., None]).astype(np.float32)


def contention_text(times: dict[str, list[float]], task_sums: dict[int, list[float]],
                    cpu_sums: dict[int, list[float]]) -> str:
    """Where the warm 2-worker batch's time goes: the tasks themselves (slower side by side) or waiting."""
    # One round's 1- and 2-worker batches, which run seconds apart: the machine's speed drifts between rounds.
    best = min(range(len(times["warm 2"])), key=lambda k: times["warm 2"][k])
    wall_1, wall_2 = task_sums[1][best], task_sums[2][best]
    cpu_1, cpu_2 = cpu_sums[1][best], cpu_sums[2][best]
    return (f"In the round of the fastest warm 2-worker batch, the warm batches' tasks took {wall_1:.2f} s summed "
            f"on 1 worker and {wall_2:.2f} s on 2 "
            f"({100 * (wall_2 / wall_1 - 1):+.0f} %); their threads' CPU time {cpu_1:.2f} s and {cpu_2:.2f} s "
            f"({100 * (cpu_2 / cpu_1 - 1):+.0f} %: the tasks' own work, two at a time on cores that share caches "
            "and memory). The rest of their wall time is waiting for a core: the scheduler and the workers' own "
            "Dask threads run on the same two cores, which with one worker have a core to themselves. The 2-worker "
            "batch's "
            f"wall time is {100 * (times['warm 2'][best] / (wall_2 / 2) - 1):+.0f} % over half its tasks' sum "
            "(the two workers' shares of the work differ at the end: the last task or part runs alone).")


def three_text(times: dict[str, list[float]], n_frames: int) -> str:
    """Three recordings on two warm workers: one task each against chains of parts."""
    ratios = [whole / parts for whole, parts in zip(times["three whole"], times["three parts"])]
    return (f"Three recordings (arena, corridor, arena) on the warm 2-worker cluster: one task per recording "
            f"(`part_frames={n_frames}`) {min(times['three whole']):.2f} s, in parts of {PART_FRAMES} frames "
            f"(the default) {min(times['three parts']):.2f} s (fastest of the rounds; every round: "
            f"{' / '.join(f'{value:.2f}' for value in times['three whole'])} s and "
            f"{' / '.join(f'{value:.2f}' for value in times['three parts'])} s); one task each over parts, per round: "
            f"{np.median(ratios):.2f}x median ({' / '.join(f'{value:.2f}' for value in ratios)}). One task each, "
            "one worker runs two recordings while the other idles after one; in parts the recordings take turns. "
            "The 4-recording batches above run in parts too (more recordings than workers).")


def main() -> None:
    n_frames = int(sys.argv[1]) if len(sys.argv) > 1 else 60
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    logging.getLogger("distributed").setLevel(logging.ERROR)
    root = Path(tempfile.mkdtemp(prefix="rangesurf-batch-bench-"))
    loads = [os.getloadavg()[0]]
    sources = source_times()
    try:
        reference = root / "sequential"
        sequential(reference, 2)  # compiles or loads the Numba kernels, filling the on-disk cache for the workers
        times: dict[str, list[float]] = {key: [] for key in ("sequential", "local 1", "local 2", "warm 1", "warm 2",
                                                             "three whole", "three parts")}
        # Per round, the warm batches' task times summed (each task's wall and thread CPU time on its worker).
        task_sums: dict[int, list[float]] = {1: [], 2: []}
        cpu_sums: dict[int, list[float]] = {1: [], 2: []}
        same = True
        warm = {workers: warm_cluster(workers) for workers in (1, 2)}
        try:
            for round_ in range(rounds):
                times["sequential"].append(sequential(reference, n_frames))
                for workers in (1, 2):
                    out = root / f"local{workers}"
                    batch = run_batch(INPUTS, out, workers=workers, frames=n_frames, seed=SEEDS, overwrite=True,
                                      progress=False)
                    assert not batch.failed, [item.error for item in batch.failed]
                    times[f"local {workers}"].append(batch.seconds)
                    same &= identical(reference, out)
                    out = root / f"warm{workers}"
                    batch = run_batch(INPUTS, out, scheduler=warm[workers].scheduler_address, frames=n_frames,
                                      seed=SEEDS, overwrite=True, progress=False)
                    assert not batch.failed, [item.error for item in batch.failed]
                    times[f"warm {workers}"].append(batch.seconds)
                    task_sums[workers].append(sum(item.seconds for item in batch.items))
                    cpu_sums[workers].append(sum(item.cpu_seconds for item in batch.items))
                    same &= identical(reference, out)
                # Three recordings on two workers: one task each (parts as long as the recordings), and in parts.
                for key, part_frames in (("three whole", n_frames), ("three parts", PART_FRAMES)):
                    out = root / key.replace(" ", "-")
                    batch = run_batch(INPUTS[:3], out, scheduler=warm[2].scheduler_address, frames=n_frames,
                                      seed=SEEDS[:3], overwrite=True, part_frames=part_frames, progress=False)
                    assert not batch.failed, [item.error for item in batch.failed]
                    times[key].append(batch.seconds)
                    same &= identical(reference, out, 3)
                loads.append(os.getloadavg()[0])
                print(f"round {round_ + 1}: " + ", ".join(f"{key} {values[-1]:.2f} s" for key, values in times.items()))
        finally:
            for cluster in warm.values():
                cluster.close()
        stage_ms = independent_stage_ms(reference)
        one, many = task_cost()
        cpu = worker_cpu_seconds(n_frames)
        loads.append(os.getloadavg()[0])
        changed = sorted(path for path, mtime in source_times().items() if sources.get(path) != mtime)
    finally:
        shutil.rmtree(root, ignore_errors=True)

    best = {key: min(values) for key, values in times.items()}

    def row(label: str, key: str, baseline: str | None) -> str:
        ratio = per_round = "—"
        if baseline:
            ratio = f"{best[baseline] / best[key]:.2f}x"
            ratios = [one / two for one, two in zip(times[baseline], times[key])]
            per_round = f"{np.median(ratios):.2f}x ({' / '.join(f'{value:.2f}' for value in ratios)})"
        versus = f"{best['sequential'] / best[key]:.2f}x"
        rounds_text = " / ".join(f"{value:.2f}" for value in times[key])
        return f"| {label} | {best[key]:.2f} | {ratio} | {per_round} | {versus} | {rounds_text} |"

    command = f".venv/bin/python benchmarks/batch.py {n_frames} {rounds}"
    lines = [
        f"Machine: {machine_description()}. Command: `{command}`.",
        "",
        f"A batch of {len(INPUTS)} simulated SR-3000 recordings of {n_frames} frames (arena, corridor, arena, "
        f"corridor; seeds {', '.join(map(str, SEEDS))}), every output written (model, report, ...), "
        f"single-threaded worker processes; with more recordings than workers, each recording runs as a chain of "
        f"tasks of {PART_FRAMES} frames (`run_batch(part_frames=...)`). Wall time in seconds, the fastest of {rounds} "
        "interleaved rounds (others share this machine). Speed-up 1 -> 2 workers: of the fastest batches, and "
        "per round (in each round the 1-worker batches run just before the 2-worker ones): the median and each "
        "round's; the machine's speed drifts between rounds, so the fastest of each may come from rounds of "
        "different speed, and the per-round median is the steadier figure.",
        "",
        "| run | wall s | speed-up 1 -> 2 workers, fastest | per round: median (each) | vs sequential "
        "| every round (s) |",
        "|---|---:|---:|---:|---:|---:|",
        row("sequential, in process (reference)", "sequential", None),
        row("run_batch, own local cluster, 1 worker", "local 1", None),
        row("run_batch, own local cluster, 2 workers", "local 2", "local 1"),
        row("run_batch, running warm cluster, 1 worker", "warm 1", None),
        row("run_batch, running warm cluster, 2 workers", "warm 2", "warm 1"),
        "",
        three_text(times, n_frames),
        "",
        contention_text(times, task_sums, cpu_sums),
        "",
        "\"Own local cluster\" includes starting the cluster, the workers' imports and loading the cached "
        "Numba kernels (a fixed cost of a few seconds per batch); \"running warm cluster\" is the work alone.",
        "",
        f"Outputs identical to the sequential runs (trajectory.txt and model.ply, byte for byte, every batch): "
        f"{'yes' if same else 'NO'}.",
        "",
        f"Per-frame tasks: one Dask task carrying an SR-3000 frame to a worker and its points back costs "
        f"{one:.1f} ms one at a time and {many:.1f} ms each when 200 are queued on 2 workers, against "
        f"{stage_ms:.1f} ms (median) for a frame's stages that need no other frame (denoise, segment, segment "
        f"vertices; timings.csv) plus the normals for registration: per-frame tasks would add about "
        f"{100 * many / stage_ms:.0f} % of that work as scheduling and copying on the same two cores (more for the "
        "segments and vertex sets they would really return), and could only help when there are fewer recordings "
        "than workers. A batch with at least as many recordings as workers keeps every worker busy, to the "
        "end when the recordings run in parts.",
        "",
        f"CPU seconds of one {n_frames}-frame recording (thread time, fastest of 2): "
        + ", ".join(f"{label} {value:.2f}" for label, value in cpu.items())
        + ". Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536 (glibc then returns every frame's "
        "freed arrays to the system and faults them in again); run_batch's local cluster unsets it.",
        "",
        *([f"WARNING: sources changed during the benchmark ({', '.join(changed)}); rerun it.", ""] if changed else []),
        "Load average (1 min) at the start, after each round and at the end: "
        + ", ".join(f"{load:.2f}" for load in loads) + ".",
    ]
    write_results(Path(__file__).parent / "results", "batch.md", lines)


if __name__ == "__main__":
    main()
