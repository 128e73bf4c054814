"""The main job end to end: outputs checked against the simulator's ground truth, resume, bad input."""

import json
from pathlib import Path

import numpy as np
import pytest

import rangesurf as rs
from rangesurf import simulate
from rangesurf.config import ConfigError, PipelineConfig
from rangesurf.io.tum import read_tum_trajectory
from rangesurf.pipeline import Pipeline
from rangesurf.runner import OUTPUTS, run


def read_mesh_ply(path):
    """Our binary PLY mesh back as a structured vertex array and faces (header parsed by hand)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    vertex_count = int(next(line for line in header if line.startswith("element vertex")).split()[-1])
    face_count = int(next(line for line in header if line.startswith("element face")).split()[-1])
    names = [line.split()[-1] for line in header if line.startswith("property float") or line.startswith("property int")]
    kinds = ["<i4" if line.startswith("property int") else "<f4" for line in header if line.startswith("property float") or line.startswith("property int")]
    vertices = np.frombuffer(data, dtype=list(zip(names, kinds)), count=vertex_count, offset=end)
    records = np.frombuffer(data, dtype=[("count", "u1"), ("indices", "<i4", (3,))], count=face_count,
                            offset=end + vertices.nbytes)
    return vertices, records["indices"]


@pytest.fixture(scope="module")
def arena_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    summary = run("sim:arena", out, frames=12, progress=False)
    return out, summary


def test_outputs_match_ground_truth(arena_run):
    out, summary = arena_run
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    assert summary.frames == 12 and not summary.skipped and summary.stopped is None
    # The trajectory against the simulator's true poses.
    _, poses = read_tum_trajectory(out / "trajectory.txt")
    true_poses = simulate.default_trajectory("arena", 12, frame_rate=rs.get_sensor("sr3000").frame_rate)
    assert np.linalg.norm(poses[:, :3, 3] - true_poses[:, :3, 3], axis=1).max() < 0.01
    # The model's vertices against the scene's true planes.
    vertices, faces = read_mesh_ply(out / "model.ply")
    planes = simulate.get_scene("arena").planes
    planes = planes[np.isfinite(planes).all(axis=1)]
    points = np.column_stack([vertices["x"], vertices["y"], vertices["z"]]).astype(np.float64)
    distance = np.abs(points @ planes[:, :3].T + planes[:, 3]).min(axis=1)
    assert np.median(distance) < 0.004
    assert len(faces) > len(vertices) and faces.max() < len(vertices)
    assert np.isfinite(vertices["ul1"]).all() and (vertices["ul1"] > 0).all()
    # metrics.json says the same.
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 12 and metrics["vertices"] == len(vertices)
    assert metrics["accuracy"]["model_to_true_planes_median_m"] == pytest.approx(np.median(distance), rel=1e-3)
    assert set(metrics["stage_ms_median"]) >= {"denoise", "segment", "register", "merge", "total"}
    # The report opens offline: one page, images inline, no external resources.
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 4 and "http" not in html.replace("http-equiv", "")
    assert PipelineConfig.load(out / "config.toml") == PipelineConfig()


def test_glb_holds_the_model(arena_run):
    import trimesh

    out, _ = arena_run
    scene = trimesh.load(out / "model.glb")
    vertices, _ = read_mesh_ply(out / "model.ply")
    assert sum(len(geometry.vertices) for geometry in scene.geometry.values()) == len(vertices)


def test_an_existing_output_folder_is_refused(arena_run):
    out, _ = arena_run
    with pytest.raises(FileExistsError, match="--overwrite"):
        run("sim:arena", out, frames=2, progress=False)


def test_resume_continues_as_if_uninterrupted(tmp_path):
    straight = run("sim:corridor", tmp_path / "straight", frames=9, seed=4, progress=False)
    run("sim:corridor", tmp_path / "resumed", frames=5, seed=4, progress=False)
    resumed = run("sim:corridor", tmp_path / "resumed", frames=9, seed=4, resume=True, progress=False)
    assert resumed.frames == 4 and straight.frames == 9
    assert (tmp_path / "resumed" / "trajectory.txt").read_bytes() == (tmp_path / "straight" / "trajectory.txt").read_bytes()
    assert (tmp_path / "resumed" / "model.ply").read_bytes() == (tmp_path / "straight" / "model.ply").read_bytes()
    timings = (tmp_path / "resumed" / "timings.csv").read_text().splitlines()
    assert len(timings) == 1 + 9  # the earlier session's rows travel in the checkpoint


def test_a_run_in_parts_gives_the_outputs_of_one_run(tmp_path):
    straight = run("sim:arena", tmp_path / "straight", frames=9, seed=2, progress=False)
    parts = tmp_path / "parts"
    first = run("sim:arena", parts, frames=9, seed=2, until=4, progress=False)
    assert first.paused and first.frames == 4
    assert not (parts / "model.ply").exists()  # paused: the checkpoint only
    second = run("sim:arena", parts, frames=9, seed=2, resume=True, until=7, progress=False)
    assert second.paused and second.frames == 3
    last = run("sim:arena", parts, frames=9, seed=2, resume=True, until=20, progress=False)
    assert not last.paused and last.frames == 2  # the input ended first: the run finished
    for name in ("trajectory.txt", "model.ply"):
        assert (parts / name).read_bytes() == (tmp_path / "straight" / name).read_bytes()
    assert last.metrics["accuracy"] == straight.metrics["accuracy"]
    with pytest.raises(ValueError, match="until=9 must lie past the 9 input positions"):
        run("sim:arena", parts, frames=9, seed=2, resume=True, until=9, progress=False)


def test_ctrl_c_stops_cleanly_with_a_resumable_checkpoint(tmp_path, monkeypatch):
    original = Pipeline.process

    def interrupted(self, frame):
        if self.frames == 3:
            raise KeyboardInterrupt
        return original(self, frame)

    monkeypatch.setattr(Pipeline, "process", interrupted)
    summary = run("sim:arena", tmp_path / "out", frames=8, progress=False)
    assert summary.stopped.startswith("interrupted") and summary.frames == 3
    assert Pipeline.resume(tmp_path / "out" / "checkpoint.npz").frames == 3
    _, poses = read_tum_trajectory(tmp_path / "out" / "trajectory.txt")
    assert len(poses) == 3


def _frames_with_a_broken_one(folder):
    frames, _ = simulate.simulate_sequence("arena", "sr3000", 4, seed=1)
    rs.save(folder, frames)
    files = sorted(folder.glob("*.npz"))
    files[2].write_bytes(b"this is not an npz file")
    return files


def test_an_unreadable_frame_is_reported_and_skipped(tmp_path):
    files = _frames_with_a_broken_one(tmp_path / "frames")
    summary = run(str(tmp_path / "frames"), tmp_path / "out", progress=False)
    assert summary.frames == 3 and summary.stopped is None
    (source, error), = summary.skipped
    assert files[2].name in source and files[2].name in error
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["skipped"][0]["source"] == source


def test_a_resumed_run_lists_the_frames_skipped_before(tmp_path):
    files = _frames_with_a_broken_one(tmp_path / "frames")
    paused = run(str(tmp_path / "frames"), tmp_path / "out", until=3, progress=False)
    assert paused.paused and paused.frames == 2 and len(paused.skipped) == 1
    summary = run(str(tmp_path / "frames"), tmp_path / "out", resume=True, progress=False)
    assert summary.frames == 1
    (source, error), = summary.skipped
    assert files[2].name in source and files[2].name in error
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert [entry["source"] for entry in metrics["skipped"]] == [source] and metrics["frames"] == 3


def test_an_unreadable_frame_can_stop_the_run(tmp_path):
    _frames_with_a_broken_one(tmp_path / "frames")
    config = PipelineConfig.from_dict({"run": {"on_bad_frame": "stop"}})
    summary = run(str(tmp_path / "frames"), tmp_path / "out", config=config, progress=False)
    assert summary.frames == 2 and "unreadable" in summary.stopped
    _, poses = read_tum_trajectory(tmp_path / "out" / "trajectory.txt")
    assert len(poses) == 2  # everything merged so far is written


def test_bad_config_files_name_the_key(tmp_path):
    path = tmp_path / "config.toml"
    path.write_text("[merge]\ncell_size = 'big'\n")
    with pytest.raises(ConfigError, match=r"merge.cell_size must be float"):
        PipelineConfig.load(path)
    path.write_text("[register]\nkeyframe_distanse = 0.2\n")
    with pytest.raises(ConfigError, match=r"unknown key 'register.keyframe_distanse'"):
        PipelineConfig.load(path)
    path.write_text("[run]\non_bad_frame = 'ignore'\n")
    with pytest.raises(ConfigError, match="run.on_bad_frame must be one of skip, stop"):
        PipelineConfig.load(path)
    path.write_text("[register]\nkeyframe_overlap_loss = 1.5\n")
    with pytest.raises(ConfigError, match="register.keyframe_overlap_loss must be between 0 and 1, got 1.5"):
        PipelineConfig.load(path)
    path.write_text("[run\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        PipelineConfig.load(path)


def test_resume_reads_nothing_it_merged_before(tmp_path, monkeypatch):
    """A resumed run neither re-reads nor re-simulates the frames its checkpoint holds, and counts an
    unreadable frame skipped before the checkpoint as consumed (not as a frame still to merge)."""
    files = _frames_with_a_broken_one(tmp_path / "frames")
    config = PipelineConfig.from_dict({"run": {"checkpoint_every": 1}})
    first = run(str(tmp_path / "frames"), tmp_path / "out", config=config, frames=2, progress=False)
    assert first.frames == 2 and len(first.skipped) == 1  # frames 0, 1 merged, frame 2 unreadable
    import rangesurf.runner as runner

    read = []
    original = runner.iter_frames
    monkeypatch.setattr(runner, "iter_frames", lambda path, **options: (read.append(Path(path).name), original(path, **options))[1])
    resumed = run(str(tmp_path / "frames"), tmp_path / "out", resume=True, progress=False)
    # Frame 2 is not read again; the run's list of skipped inputs still has it, once.
    assert read == [files[3].name] and resumed.frames == 1 and resumed.skipped == first.skipped
    _, poses = read_tum_trajectory(tmp_path / "out" / "trajectory.txt")
    assert len(poses) == 3
