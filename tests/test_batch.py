"""Batch runs on Dask: the same outputs as sequential runs, failures reported per input."""

from __future__ import annotations

import json
import sys

import pytest

from rangesurf.batch import output_names, run_batch
from rangesurf.runner import run

SCENES = ("sim:arena", "sim:corridor")
FRAMES = 8
# Byte-identical to a sequential run; timings.csv, metrics.json and report.html hold wall-clock times.
DETERMINISTIC = ("trajectory.txt", "model.ply", "config.toml")


@pytest.fixture(scope="module")
def distributed():
    return pytest.importorskip("distributed", reason="batch runs need dask.distributed: pip install 'rangesurf[distributed]'")


@pytest.fixture(scope="module")
def sequential(tmp_path_factory):
    """The reference: each scene through `runner.run` in this process (also fills Numba's on-disk cache).

    With BLAS on one thread, as `rangesurf run` and the batch's workers have it: a multi-threaded matrix
    product can round differently in the last bit.
    """
    from threadpoolctl import threadpool_limits

    root = tmp_path_factory.mktemp("sequential")
    with threadpool_limits(limits=1):
        return {spec: run(spec, root / spec[4:], frames=FRAMES, sensor="sr3000", progress=False).out for spec in SCENES}


@pytest.fixture(scope="module")
def local_batch(distributed, sequential, tmp_path_factory):
    """Both scenes and a missing file on a local cluster of two worker processes: three inputs on two
    workers, so each recording runs as a chain of parts (of 3 frames here)."""
    out = tmp_path_factory.mktemp("batch")
    inputs = [*SCENES, str(out / "missing" / "nothing.npz")]
    return run_batch(inputs, out / "runs", workers=2, frames=FRAMES, sensor="sr3000", part_frames=3, progress=False)


def test_local_cluster_outputs_match_sequential_runs(local_batch, sequential):
    assert local_batch.workers == 2
    items = {item.input: item for item in local_batch.items}
    for spec in SCENES:
        item = items[spec]
        assert item.ok, item.error
        assert item.out.name == f"sim-{spec[4:]}-seed0"
        assert item.summary.frames == FRAMES and item.summary.metrics["frames"] == FRAMES
        assert item.parts == 3  # 3 + 3 + 2 frames, each part resumed from the one before's checkpoint
        assert item.worker is not None and item.worker.startswith("tcp://")
        # The task's thread ran the whole recording: most of its wall time is CPU time.
        assert 0 < item.cpu_seconds <= item.seconds
        for name in DETERMINISTIC:
            assert (item.out / name).read_bytes() == (sequential[spec] / name).read_bytes(), f"{spec}: {name} differs"
        reference = json.loads((sequential[spec] / "metrics.json").read_text())
        assert item.summary.metrics["accuracy"] == reference["accuracy"]
        assert item.summary.metrics["vertices"] == reference["vertices"] > 0


def test_failed_input_is_reported_and_the_batch_goes_on(local_batch):
    failed = local_batch.failed
    assert [item.input for item in failed] == [local_batch.items[2].input]
    assert failed[0].summary is None
    assert "FormatError" in failed[0].error and "no such file or folder" in failed[0].error
    assert "nothing.npz" in failed[0].error
    report = json.loads((local_batch.out / "batch.json").read_text())
    assert report["failed"] == 1 and report["workers"] == 2
    assert [entry["ok"] for entry in report["inputs"]] == [True, True, False]
    assert [entry["frames"] for entry in report["inputs"]] == [FRAMES, FRAMES, None]
    assert report["inputs"][2]["error"] == failed[0].error


def test_running_scheduler_by_address(distributed, sequential, tmp_path):
    def numba_cache_use() -> tuple[int, int]:
        """(kernels loaded from Numba's on-disk cache, kernels compiled) in this worker process."""
        import numba

        loaded = compiled = 0
        for name, module in list(sys.modules.items()):
            if name.startswith("rangesurf"):
                for value in list(vars(module).values()):
                    if isinstance(value, numba.core.registry.CPUDispatcher) and value.signatures:
                        loaded += sum(value.stats.cache_hits.values())
                        compiled += sum(value.stats.cache_misses.values())
        return loaded, compiled

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        batch = run_batch(["sim:corridor"], tmp_path, scheduler=cluster.scheduler_address, frames=FRAMES,
                          sensor="sr3000", progress=False)
        assert batch.scheduler == cluster.scheduler_address
        # The batch closes its client only: the cluster it was given keeps running.
        assert cluster.status.name == "running"
        with distributed.Client(cluster) as client:
            [(loaded, compiled)] = client.run(numba_cache_use).values()
    # The sequential runs above filled the cache: the worker process compiled nothing.
    assert loaded > 0 and compiled == 0
    [item] = batch.items
    assert item.ok, item.error
    for name in DETERMINISTIC:
        assert (item.out / name).read_bytes() == (sequential["sim:corridor"] / name).read_bytes()


def test_existing_outputs_fail_without_overwrite(distributed, tmp_path):
    (tmp_path / "sim-arena-seed0").mkdir()
    (tmp_path / "sim-arena-seed0" / "model.ply").write_text("an earlier run")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        batch = run_batch(["sim:arena"], tmp_path, scheduler=cluster.scheduler_address, frames=2, progress=False)
    [item] = batch.items
    assert not item.ok and "FileExistsError" in item.error and "--overwrite" in item.error
    assert (tmp_path / "sim-arena-seed0" / "model.ply").read_text() == "an earlier run"


def test_unreachable_scheduler_is_named(distributed, tmp_path):
    import dask

    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        with pytest.raises(ConnectionError, match=r"Dask scheduler at 'tcp://127\.0\.0\.1:1'"):
            run_batch(["sim:arena"], tmp_path, scheduler="tcp://127.0.0.1:1", progress=False)
    with pytest.raises(ConnectionError, match="missing port number"):
        run_batch(["sim:arena"], tmp_path, scheduler="localhost", progress=False)


def test_missing_extra_names_it(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match=r"pip install 'rangesurf\[distributed\]'"):
        run_batch(["sim:arena"], tmp_path)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"inputs": []}, "at least one input"),
        ({"seed": [0, 1, 2]}, "got 3 seeds for 2 inputs"),
        ({"workers": 0}, "workers must be at least 1, got 0"),
        ({"workers": 2, "scheduler": "tcp://127.0.0.1:8786"}, "has its own workers"),
        ({"part_frames": 0}, "part_frames must be at least 1, got 0"),
    ],
)
def test_bad_arguments(tmp_path, arguments, message):
    arguments = {"inputs": list(SCENES), **arguments}
    with pytest.raises(ValueError, match=message):
        run_batch(arguments.pop("inputs"), tmp_path, **arguments)


def test_output_names_are_unique_and_stable():
    inputs = ["sim:arena", "sim:arena", "sim:arena", "data/Scan.npz", "other/scan.npz", "bags/run.bag", "frames/*.png",
              "a folder/"]
    names = output_names(inputs, [0, 1, 0, 0, 0, 0, 0, 0])
    assert names == ["sim-arena-seed0", "sim-arena-seed1", "sim-arena-seed0-2", "Scan", "scan-2", "run", "frames",
                     "a-folder"]
    assert names == output_names(inputs, [0, 1, 0, 0, 0, 0, 0, 0])


def test_local_cluster_workers_do_not_profile(distributed):
    """Dask's statistical profiler samples a busy task's stack every 10 ms; the batch's own workers run none
    (it costs CPU on the cores the recordings need, and only a dashboard would show it)."""
    from rangesurf.batch import _local_cluster

    def busy() -> None:
        import time

        end = time.perf_counter() + 0.5
        while time.perf_counter() < end:
            sum(range(1000))

    def samples(cluster) -> int:
        import time

        with distributed.Client(cluster) as client:
            client.submit(busy, pure=False).result()
            time.sleep(1.5)  # a worker hands its samples over at the end of each 1-second cycle
            return client.profile()["count"]

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as plain:
        assert samples(plain) > 0  # Dask's default: the profiler runs
    with _local_cluster(distributed, 1) as ours:
        assert samples(ours) == 0
