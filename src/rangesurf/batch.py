"""Batch runs: many recordings through the main job (`rangesurf.runner.run`) on a Dask cluster.

`run_batch` gives every input its own output folder under ``out`` and runs
them as tasks on a ``dask.distributed`` cluster: the one at ``scheduler``,
or a local cluster of single-threaded worker processes started for the
batch. One recording is one task, or, with more recordings than worker
threads, a chain of tasks over parts of it (``part_frames``). Inside, the
frames go through the `Pipeline` in order, exactly as in ``rangesurf run``,
because registration and merging depend on the previous frame; the
parallelism is across recordings, so the outputs are the same bytes as a
sequential run's (apart from the timings). An input that fails is reported
with its error and the batch goes on; ``out/batch.json`` lists every input,
its folder and how its run ended.

Dask is an optional extra: ``pip install 'rangesurf[distributed]'``.

Why not a task per frame: a frame's independent stages (denoising,
segmentation, segment vertices, the normals for registration) take about 6
of an SR-3000 frame's 17 ms, and a Dask task that hands a frame to another
process and its results back costs about 3 ms even when many are queued
(``benchmarks/batch.py``). Why parts: with one task per recording, three
recordings on two workers take two recordings' time, the second worker idle
for the last one; as parts (50 frames each by default, about 2.5 s of
SR-3000 frames) the recordings take turns on both workers. A part starts
from its recording's checkpoint (a few MB, read in about 25 ms); the run
writes one every 25 frames anyway.

A script that starts a local cluster must call `run_batch` under
``if __name__ == "__main__":``: the worker processes are spawned, and
import the script's module again.

Examples
--------
Two short simulated recordings on a local cluster of two worker processes
(skipped here: starting a cluster takes a few seconds):

>>> from rangesurf.batch import run_batch
>>> batch = run_batch(["sim:arena", "sim:corridor"], "batch-out", frames=8, workers=2,
...                   progress=False)  # doctest: +SKIP
>>> [(item.out.name, item.summary.frames) for item in batch.items]  # doctest: +SKIP
[('sim-arena-seed0', 8), ('sim-corridor-seed0', 8)]
"""

from __future__ import annotations

import dataclasses
import json
import logging
import numbers
import os
import re
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rangesurf.config import PipelineConfig
from rangesurf.io import atomic_write
from rangesurf.runner import RunSummary

__all__ = ["BatchItem", "BatchSummary", "run_batch", "output_names"]

_EXTRA_HINT = "pip install 'rangesurf[distributed]'"
# Input positions per task when recordings run as chains of parts (about 2.5 s of SR-3000 frames).
PART_FRAMES = 50
# Worker processes of the local cluster: the pipeline is single-threaded by design, and one
# recording per core is the parallelism; threaded BLAS, OpenMP or Numba would only contend.
_ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}


@dataclass(frozen=True)
class BatchItem:
    """One input of a batch.

    Parameters
    ----------
    input : str
        The input as given.
    out : Path
        Its output folder.
    summary : RunSummary or None
        What its run did; None when it failed.
    error : str or None
        Why it failed (exception type and message); None when it ran.
    seconds : float
        Wall time of its task on the worker (0 when it never ran).
    worker : str or None
        Address of the worker that ran it.
    cpu_seconds : float
        CPU time of the thread that ran its task (0 when it never ran); less
        than ``seconds`` by the time the task waited for a core.
    parts : int
        Tasks its run took: 1, or the parts of its chain (``part_frames``);
        ``seconds``, ``cpu_seconds`` and the summary's frames and seconds
        are summed over them, ``worker`` is the last one's.
    """

    input: str
    out: Path
    summary: RunSummary | None = None
    error: str | None = None
    seconds: float = 0.0
    worker: str | None = None
    cpu_seconds: float = 0.0
    parts: int = 1

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class BatchSummary:
    """What `run_batch` did; also written to ``out/batch.json``.

    Parameters
    ----------
    out : Path
    items : list of BatchItem
        One per input, in input order.
    scheduler : str
        Address of the scheduler that ran the batch.
    workers : int
        Worker processes of the cluster when the batch started.
    seconds : float
        Wall time of the whole batch, cluster start included.
    startup_seconds : float
        Of which starting (or connecting to) the cluster.
    """

    out: Path
    items: list[BatchItem] = field(default_factory=list)
    scheduler: str = ""
    workers: int = 0
    seconds: float = 0.0
    startup_seconds: float = 0.0

    @property
    def failed(self) -> list[BatchItem]:
        return [item for item in self.items if not item.ok]


def run_batch(
    inputs: Sequence[str],
    out: str | os.PathLike,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    config: PipelineConfig | None = None,
    frames: int | None = None,
    sensor: str | None = None,
    seed: int | Sequence[int] = 0,
    overwrite: bool = False,
    part_frames: int = PART_FRAMES,
    progress: bool = True,
) -> BatchSummary:
    """Run every input through the main job on a Dask cluster, each into its own folder.

    Parameters
    ----------
    inputs : sequence of str
        Files, folders, globs or bags (`rangesurf.load`), or simulated
        sequences ``sim:arena`` / ``sim:corridor``. Relative paths are taken
        from the current folder (a remote cluster's workers need them on a
        shared file system).
    out : path-like
        Parent folder: input ``i`` writes into ``out / output_names(...)[i]``
        (``sim-arena-seed0``, or the file or folder name without suffix;
        clashes get ``-2``, ``-3``, ...). ``out/batch.json`` lists them all.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:8786``). None
        starts a local cluster of single-threaded worker processes for the
        batch and closes it at the end.
    workers : int, optional
        Worker processes of the local cluster (default: the CPU count). Only
        with ``scheduler=None``: a running cluster has its own.
    config : PipelineConfig, optional
        Settings of every run.
    frames, sensor : optional
        As in `rangesurf.runner.run`, for every input.
    seed : int or sequence of int
        Simulation seed: one for all inputs, or one per input.
    overwrite : bool
        Replace the outputs of an earlier run in an input's folder (without
        it, an input whose folder is not empty fails).
    part_frames : int
        With more inputs than the cluster has worker threads, each recording
        runs as a chain of tasks over this many input positions each, the
        pipeline's state handed on in its checkpoint (``run(until=...)``,
        then ``resume``; the same outputs): the recordings take turns, so
        that three on two workers take about 1.5 recordings' time rather
        than two. With no more inputs than threads, one task per recording.
    progress : bool
        Show a progress bar over the recordings.

    Returns
    -------
    BatchSummary
        One `BatchItem` per input, in input order; failed ones carry their
        error instead of a `RunSummary`.

    Raises
    ------
    ImportError
        dask.distributed is not installed.
    ConnectionError
        No scheduler answers at ``scheduler``.
    ValueError
        No inputs, a seed list of another length, ``workers`` < 1 or given
        with ``scheduler``, ``part_frames`` < 1.

    Notes
    -----
    Every task runs with BLAS and OpenMP limited to one thread
    (threadpoolctl), and the local cluster's workers start with
    ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS`` and
    ``NUMBA_NUM_THREADS`` set to 1. Workers load the compiled Numba kernels
    from the same on-disk cache as the main process.
    """
    inputs = list(inputs)
    if not inputs:
        raise ValueError("run_batch needs at least one input")
    seeds = [int(seed)] * len(inputs) if isinstance(seed, numbers.Integral) else [int(value) for value in seed]
    if len(seeds) != len(inputs):
        raise ValueError(f"seed must be one int or one per input: got {len(seeds)} seeds for {len(inputs)} inputs")
    if workers is not None and scheduler is not None:
        raise ValueError(f"workers={workers} applies to a local cluster; the cluster at {scheduler!r} has its own workers")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if part_frames < 1:
        raise ValueError(f"part_frames must be at least 1, got {part_frames}")
    distributed = _import_distributed()

    out = Path(out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    folders = [out / name for name in output_names(inputs, seeds)]
    started = time.perf_counter()
    cluster, client = _connect(distributed, scheduler, workers)
    try:
        batch = BatchSummary(out=out, scheduler=client.scheduler.address, workers=len(client.nthreads()),
                             startup_seconds=time.perf_counter() - started)
        # Keys unique across batches: a shared scheduler would hand a second batch the first one's results.
        token = uuid.uuid4().hex[:12]
        # With more recordings than workers, each is a chain of tasks over parts of it (the pipeline's state
        # handed on in its checkpoint), a part submitted when the one before ends: the recordings take turns
        # and end together, where one task each would leave workers idle while the last ones run.
        chained = len(inputs) > sum(client.nthreads().values())
        futures: dict[Any, tuple[int, int]] = {}

        def submit(position: int, part: int) -> Any:
            folder = folders[position]
            future = client.submit(_run_recording, _located(inputs[position]), str(folder),
                                   config=config if part == 0 else None, frames=frames, sensor=sensor,
                                   seed=seeds[position], overwrite=overwrite, resume=part > 0,
                                   until=(part + 1) * part_frames if chained else None,
                                   key=f"rangesurf-run-{folder.name}-{part}-{token}", pure=False)
            futures[future] = (position, part)
            return future

        items: list[BatchItem | None] = [None] * len(inputs)
        parts: list[list[tuple[RunSummary, float, float, str | None]]] = [[] for _ in inputs]
        from tqdm import tqdm

        with tqdm(total=len(inputs), desc="rangesurf batch", unit="recording", disable=not progress, leave=False) as bar:
            running = distributed.as_completed([submit(position, 0) for position in range(len(inputs))])
            for future in running:
                position, part = futures.pop(future)
                try:
                    parts[position].append(future.result())
                except Exception as error:  # noqa: BLE001 - any failure of one input is reported, the batch goes on
                    items[position] = BatchItem(inputs[position], folders[position], error=_describe(error))
                    bar.update(1)
                    continue
                if parts[position][-1][0].paused:
                    running.add(submit(position, part + 1))
                    continue
                items[position] = _whole_run(inputs[position], folders[position], parts[position])
                bar.update(1)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    batch.items = items
    batch.seconds = time.perf_counter() - started
    _write_report(out / "batch.json", batch)
    return batch


def output_names(inputs: Sequence[str], seeds: Sequence[int]) -> list[str]:
    """A unique folder name per input: ``sim-SCENE-seedN``, or the file or folder name without suffix.

    Clashes (case-insensitive, as on macOS and Windows) get ``-2``, ``-3``, ... in input order.

    Examples
    --------
    >>> output_names(["sim:arena", "sim:arena", "data/scan_01.npz", "data/run/", "b/*.png"], [0, 0, 0, 0, 0])
    ['sim-arena-seed0', 'sim-arena-seed0-2', 'scan_01', 'run', 'b']
    """
    names, taken = [], set()
    for spec, seed in zip(inputs, seeds, strict=True):
        base = _base_name(spec, seed)
        name, count = base, 1
        while name.lower() in taken:
            count += 1
            name = f"{base}-{count}"
        taken.add(name.lower())
        names.append(name)
    return names


# --------------------------------------------------------------------------
# Helpers.
# --------------------------------------------------------------------------


def _base_name(spec: str, seed: int) -> str:
    if spec.startswith("sim:"):
        return _safe(f"sim-{spec[4:]}-seed{seed}") or "sim"
    path = Path(spec)
    # A glob's pattern part names nothing useful by itself ("*.png"): then its folder does.
    for part in (path.name if path.is_dir() else path.stem, path.parent.name):
        name = _safe(part)
        if name:
            return name
    return "input"


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-.")


def _located(spec: str) -> str:
    """Paths made absolute here: a worker's current folder need not be ours."""
    return spec if spec.startswith("sim:") else str(Path(spec).expanduser().absolute())


def _import_distributed() -> Any:
    try:
        import distributed
    except ImportError as error:
        raise ImportError(f"batch runs need dask.distributed, which is not installed ({error}); "
                          f"install it with: {_EXTRA_HINT}") from None
    return distributed


def _connect(distributed: Any, scheduler: str | None, workers: int | None) -> tuple[Any, Any]:
    """(cluster or None, client): a local cluster of one-thread worker processes, or the one at ``scheduler``."""
    if scheduler is not None:
        try:
            return None, distributed.Client(scheduler)
        except (OSError, ValueError, TypeError) as error:
            # TimeoutError and refused connections are OSErrors; a malformed address is a ValueError.
            raise ConnectionError(f"cannot reach the Dask scheduler at {scheduler!r}: {error}") from None
    cluster = _local_cluster(distributed, workers or os.cpu_count() or 1)
    try:
        return cluster, distributed.Client(cluster)
    except BaseException:
        cluster.close()
        raise


def _local_cluster(distributed: Any, workers: int) -> Any:
    """A local cluster of ``workers`` single-threaded worker processes, without dashboard."""
    import dask

    # Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536: glibc then hands the frame-sized
    # arrays freed after every frame back to the system and faults them in again, which makes the
    # pipeline about 1.5 times slower in a worker than in the main process (benchmarks/batch.py).
    # A nanny also leaves the variable in this process's environment, where later workers would
    # inherit it: the value Dask put there is left out while ours start.
    key = "MALLOC_TRIM_THRESHOLD_"
    dask_value = dask.config.get(f"distributed.nanny.pre-spawn-environ.{key}", default=None)
    inherited = os.environ.get(key)
    if inherited is not None and inherited == str(dask_value):
        del os.environ[key]
    try:
        # Nor do the workers run Dask's statistical profiler, whose samples (every 10 ms) only a dashboard
        # shows and which cost CPU time on the cores the recordings need: with it, a worker process spent
        # 2.2 s beside its tasks' 32.6 s (4 SR-3000 recordings of 150 frames), without it 1.0 s.
        # The scheduler's HTTP routes go on a free port rather than 8787, which another cluster may hold.
        with dask.config.set({f"distributed.nanny.pre-spawn-environ.{key}": None,
                              "distributed.worker.profile.enabled": False}):
            return distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                            env=dict(_ONE_THREAD), dashboard_address=None,
                                            scheduler_kwargs={"dashboard_address": ":0"}, silence_logs=logging.CRITICAL)
    finally:
        if inherited is not None:
            os.environ[key] = inherited


def _run_recording(spec: str, out: str, *, config: PipelineConfig | None, frames: int | None, sensor: str | None,
                   seed: int, overwrite: bool, resume: bool = False,
                   until: int | None = None) -> tuple[RunSummary, float, float, str | None]:
    """The task: a recording, or a part of it, through `rangesurf.runner.run` on a worker, BLAS and OpenMP on one
    thread.

    Returns the summary, the task's wall and thread CPU seconds, and the worker's address.
    """
    from threadpoolctl import threadpool_limits

    from rangesurf.runner import run

    started, cpu_started = time.perf_counter(), time.thread_time()
    with threadpool_limits(limits=1):
        summary = run(spec, out, config=config, frames=frames, sensor=sensor, seed=seed, overwrite=overwrite,
                      resume=resume, until=until, progress=False)
    try:
        from distributed import get_worker

        worker = get_worker().address
    except (ImportError, ValueError):
        worker = None
    return summary, time.perf_counter() - started, time.thread_time() - cpu_started, worker


def _whole_run(spec: str, folder: Path, parts: list[tuple[RunSummary, float, float, str | None]]) -> BatchItem:
    """A recording's `BatchItem` from the (summary, seconds, CPU seconds, worker) of its parts: the last part's
    summary (whose skipped inputs are all parts') with the frames and seconds of all summed, the worker of the
    last."""
    summaries = [summary for summary, _, _, _ in parts]
    whole = dataclasses.replace(summaries[-1], frames=sum(summary.frames for summary in summaries),
                                seconds=sum(summary.seconds for summary in summaries))
    return BatchItem(spec, folder, whole, None, sum(part[1] for part in parts), parts[-1][3],
                     sum(part[2] for part in parts), len(parts))


def _describe(error: BaseException) -> str:
    return f"{type(error).__name__}: {error}"


def _write_report(path: Path, batch: BatchSummary) -> None:
    report = {
        "scheduler": batch.scheduler,
        "workers": batch.workers,
        "seconds": round(batch.seconds, 3),
        "startup_seconds": round(batch.startup_seconds, 3),
        "failed": len(batch.failed),
        "inputs": [
            {
                "input": item.input,
                "out": item.out.name,
                "ok": item.ok,
                "error": item.error,
                "seconds": round(item.seconds, 3),
                "cpu_seconds": round(item.cpu_seconds, 3),
                "parts": item.parts,
                "worker": item.worker,
                "frames": item.summary.frames if item.summary else None,
                "skipped": len(item.summary.skipped) if item.summary else None,
                "stopped": item.summary.stopped if item.summary else None,
            }
            for item in batch.items
        ],
    }
    with atomic_write(path, "w") as stream:
        json.dump(report, stream, indent=2)
