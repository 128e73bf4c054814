"""The `rangesurf` command: info, simulate, demo, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

import rangesurf as rs
from rangesurf.cli import main


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"rangesurf {rs.__version__}"


def test_simulate_writes_frames_and_truth_that_info_describes(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "--sensor", "sr3000", "--scene", "corridor", "--frames", "3", "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in out.glob("frame*.npz")) == ["frame000000.npz", "frame000001.npz", "frame000002.npz"]
    truths = [rs.simulate.load_ground_truth(p) for p in sorted((out / "truth").glob("*.npz"))]
    assert len(truths) == 3
    frames = rs.load(out)
    for frame, truth in zip(frames, truths):
        np.testing.assert_allclose(frame.reference_pose, truth.T_world_sensor)
    capsys.readouterr()

    assert main(["info", str(out), "--json"]) == 0
    summaries = json.loads(capsys.readouterr().out)
    assert len(summaries) == 3
    for summary, frame in zip(summaries, frames):
        assert summary["sensor"] == "sr3000"
        assert summary["grid"].startswith("144x176")
        assert summary["valid"] == int(frame.valid.sum())
        assert summary["range_m"]["max"] == pytest.approx(float(np.nanmax(frame.range)), abs=1e-3)
        np.testing.assert_allclose(summary["pose"]["translation_m"], frame.pose[:3, 3], atol=1e-3)


def test_info_text_output(tmp_path, capsys):
    out = tmp_path / "sim"
    main(["simulate", "--frames", "1", "--out", str(out), "--quiet"])
    capsys.readouterr()
    assert main(["info", str(out / "frame000000.npz")]) == 0
    text = capsys.readouterr().out
    frame = rs.load(out / "frame000000.npz")[0]
    assert "sensor          sr3000" in text
    assert f"valid           {int(frame.valid.sum())} " in text


def test_demo_runs_the_main_job_against_ground_truth(tmp_path, capsys):
    """`rangesurf demo`: simulated SR-3000 frames with drifting odometry through the whole pipeline."""
    import json

    out = tmp_path / "demo"
    assert main(["demo", "--frames", "30", "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "against ground truth" in text
    for name in ("model.ply", "model.glb", "trajectory.txt", "timings.csv", "metrics.json", "report.html", "config.toml"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 30
    accuracy = metrics["accuracy"]
    assert accuracy["rpe_rotation_max_deg"] < 0.2 and accuracy["rpe_translation_max_m"] < 0.01
    assert accuracy["model_to_true_planes_median_m"] < 0.005


def test_errors_exit_2_with_a_message_naming_the_file(tmp_path, capsys):
    bad = tmp_path / "broken.pcd"
    bad.write_text("this is not a pcd\n")
    assert main(["info", str(bad)]) == 2
    assert "broken.pcd" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "missing")]) == 2
    assert "no such file or folder" in capsys.readouterr().err


def test_bad_frame_count_is_rejected(tmp_path):
    with pytest.raises(SystemExit):
        main(["simulate", "--frames", "0", "--out", str(tmp_path)])


@pytest.mark.parametrize("method", ["diffusion", "layered", "phase"])
def test_denoise_writes_a_frame_closer_to_truth_and_a_panel(tmp_path, capsys, method):
    import cv2

    main(["simulate", "--frames", "1", "--out", str(tmp_path / "sim"), "--quiet"])
    truth = rs.simulate.load_ground_truth(tmp_path / "sim" / "truth" / "truth000000.npz")
    assert main(["denoise", str(tmp_path / "sim" / "frame000000.npz"), "--method", method,
                 "--out", str(tmp_path / "den"), "--quiet"]) == 0
    raw = rs.load(tmp_path / "sim" / "frame000000.npz")[0]
    smooth = rs.load(tmp_path / "den" / "frame000000.npz")[0]
    both = raw.valid & smooth.valid & np.isfinite(truth.range)
    raw_error = np.sqrt(np.mean((raw.range - truth.range)[both] ** 2))
    smooth_error = np.sqrt(np.mean((smooth.range - truth.range)[both] ** 2))
    assert smooth_error < 0.8 * raw_error
    # Removed pixels are the ones the simulator corrupted, mostly.
    removed = raw.valid & ~smooth.valid
    assert removed.sum() > 0
    assert (truth.outlier | truth.mixed)[removed].mean() > 0.5
    panel = cv2.imread(str(tmp_path / "den" / "frame000000_panel.png"))
    assert panel is not None and panel.shape[1] == 2 * 176 * 2  # two columns of 2x-enlarged frames
    assert "outliers removed" in capsys.readouterr().out


def test_readme_error_example_is_what_a_truncated_line_gives(tmp_path, capsys):
    scan = tmp_path / "scan000.3d"
    scan.write_text("360 x 225\n" + "1 2 3\n" * 5 + "10.1 0\n")
    assert main(["info", str(scan)]) == 2
    assert "scan000.3d, line 7: expected 3 numbers like the first point line (line 2), got 2: '10.1 0'" in capsys.readouterr().err


def test_segment_writes_labels_that_match_truth_and_a_figure(tmp_path, capsys):
    import cv2

    from rangesurf.segment import evaluate_segmentation, truth_segmentation

    main(["simulate", "--frames", "1", "--out", str(tmp_path / "sim"), "--quiet"])
    truth = rs.simulate.load_ground_truth(tmp_path / "sim" / "truth" / "truth000000.npz")
    frame = rs.load(tmp_path / "sim" / "frame000000.npz")[0]
    assert main(["segment", str(tmp_path / "sim" / "frame000000.npz"), "--out", str(tmp_path / "seg"), "--quiet"]) == 0
    with np.load(tmp_path / "seg" / "frame000000_segments.npz") as saved:
        labels, planes = saved["labels"], saved["planes"]
    gt = truth_segmentation(truth, frame.rays)
    scores = evaluate_segmentation(gt.labels, labels, truth_planes=gt.planes,
                                   machine_planes=planes, min_region_size=100)
    assert scores.correct >= scores.n_truth - 1 and scores.n_truth >= 4
    figure = cv2.imread(str(tmp_path / "seg" / "frame000000_segments.png"))
    assert figure is not None and figure.shape[1] == 3 * 176 * 2
    assert len(np.unique(figure.reshape(-1, 3), axis=0)) > 8  # segments in colour, not a blank page
    out = capsys.readouterr().out
    assert "planar segments cover" in out and "rms =" in out


def test_segment_names_a_missing_file(tmp_path, capsys):
    assert main(["segment", str(tmp_path / "nothing.3d"), "--out", str(tmp_path / "seg")]) == 2
    assert "nothing.3d" in capsys.readouterr().err


def test_lod_writes_a_fine_to_coarse_figure(tmp_path, capsys):
    import cv2

    main(["simulate", "--frames", "1", "--out", str(tmp_path / "sim"), "--quiet"])
    assert main(["lod", str(tmp_path / "sim" / "frame000000.npz"), "--out", str(tmp_path / "lod"), "--quiet"]) == 0
    figure = cv2.imread(str(tmp_path / "lod" / "frame000000_lod.png"))
    assert figure is not None and figure.shape[1] == 4 * 300
    out = capsys.readouterr().out
    counts = [int(part.split(" (")[0]) for part in out.split(" at ")[1].split("; wrote")[0].split(", ")]
    assert counts == sorted(counts, reverse=True) and counts[-1] < 0.01 * counts[0]
