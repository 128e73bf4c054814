"""Crash safety: the main job killed (SIGKILL) at random moments and resumed loses nothing.

Ten trials: each starts `rangesurf run`, kills it at a random moment, resumes it from its checkpoint
(or starts over when it died before the first one), and compares the outputs with an uninterrupted
run: the model and the trajectory must be identical, byte for byte, and no output file is ever
half-written.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rangesurf.io.tum import read_tum_trajectory
from rangesurf.runner import OUTPUTS

ARGS = ["sim:corridor", "--frames", "14", "--seed", "3", "--quiet"]


def rangesurf(*arguments: str, config: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rangesurf.cli", "run", *ARGS, "--config", str(config), *arguments],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env={**os.environ, "OMP_NUM_THREADS": "1"})


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    folder = tmp_path_factory.mktemp("crash")
    config = folder / "config.toml"
    config.write_text("[run]\ncheckpoint_every = 2\n")
    out = folder / "reference"
    start = time.perf_counter()
    process = rangesurf("--out", str(out), config=config)
    assert process.wait(timeout=600) == 0, process.stderr.read().decode()
    return folder, config, out, time.perf_counter() - start


def check_complete(folder: Path) -> None:
    """Every output present is whole: the trajectory parses, the PLY holds what its header declares."""
    if (folder / "trajectory.txt").exists():
        read_tum_trajectory(folder / "trajectory.txt")
    if (folder / "model.ply").exists():
        data = (folder / "model.ply").read_bytes()
        header = data[: data.index(b"end_header\n")].decode().splitlines()
        vertices = int(next(line for line in header if line.startswith("element vertex")).split()[-1])
        faces = int(next(line for line in header if line.startswith("element face")).split()[-1])
        properties = sum(line.startswith("property float") or line.startswith("property int") for line in header)
        assert len(data) == data.index(b"end_header\n") + 11 + 4 * properties * vertices + 13 * faces
    if (folder / "checkpoint.npz").exists():
        with np.load(folder / "checkpoint.npz") as archive:
            assert "pipeline/counters" in archive.files


def test_ten_kills_and_resumes_lose_nothing(reference):
    folder, config, reference_out, duration = reference
    rng = np.random.default_rng(11)
    resumed = 0
    for trial in range(10):
        out = folder / f"trial{trial}"
        process = rangesurf("--out", str(out), config=config)
        if trial % 2:
            time.sleep(rng.uniform(0.3, duration))
        else:
            # Half the kills land a random moment after the first checkpoint, however loaded the machine
            # (a busy machine would otherwise kill most runs before it): the resume path is always tested.
            waited = time.perf_counter()
            while not (out / "checkpoint.npz").exists() and process.poll() is None and time.perf_counter() - waited < 600:
                time.sleep(0.01)
            time.sleep(rng.uniform(0.0, 0.3 * duration))
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=60)
        check_complete(out) if out.exists() else None
        resumable = (out / "checkpoint.npz").exists()
        resumed += resumable
        again = rangesurf("--out", str(out), *(["--resume"] if resumable else ["--overwrite"]), config=config)
        assert again.wait(timeout=600) == 0, again.stderr.read().decode()
        check_complete(out)
        for name in ("trajectory.txt", "model.ply"):
            assert (out / name).read_bytes() == (reference_out / name).read_bytes(), f"trial {trial}: {name} differs"
        assert not [path.name for path in out.iterdir() if path.name.startswith(".")]
        assert all((out / name).exists() for name in OUTPUTS)
    assert resumed >= 3  # most kills land after a checkpoint: the resume path is what is tested
