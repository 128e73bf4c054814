"""`rangesurf.load` / `save` dispatch: formats, folders, globs, mixed input."""

from __future__ import annotations

import numpy as np
import pytest

import rangesurf as rs


def _wall_frame(distance: float, timestamp: float = 0.0) -> rs.RangeFrame:
    sensor = rs.get_sensor("sr3000")
    rays = sensor.rays()
    range_image = (distance / rays[..., 2]).astype(np.float32)
    range_image[0, :5] = np.nan
    return rs.RangeFrame(rays=rays, range=range_image, sensor=sensor, pose=np.eye(4), timestamp=timestamp)


def test_save_folder_then_load_keeps_order_and_content(tmp_path):
    frames = [_wall_frame(1.0 + 0.1 * i, timestamp=i) for i in range(12)]
    written = rs.save(tmp_path / "seq", frames)
    assert [p.name for p in written][:2] == ["frame000000.npz", "frame000001.npz"]
    loaded = rs.load(tmp_path / "seq")
    assert [f.timestamp for f in loaded] == list(range(12))
    for original, copy in zip(frames, loaded):
        np.testing.assert_array_equal(copy.range, original.range)
        assert copy.sensor == original.sensor


def test_folder_order_is_natural_not_lexicographic(tmp_path):
    for index in (10, 2, 1):
        rs.save(tmp_path / f"scan{index}.npz", _wall_frame(float(index), timestamp=index))
    assert [f.timestamp for f in rs.load(tmp_path)] == [1, 2, 10]


def test_glob_loads_matching_files(tmp_path):
    for index in range(3):
        rs.save(tmp_path / f"a{index}.npz", _wall_frame(1.0 + index, timestamp=index))
    rs.save(tmp_path / "b0.npz", _wall_frame(9.0, timestamp=9))
    assert [f.timestamp for f in rs.load(tmp_path / "a*.npz")] == [0, 1, 2]


def test_iter_frames_is_lazy(tmp_path):
    rs.save(tmp_path / "seq", [_wall_frame(1.0), _wall_frame(2.0)])
    frames = rs.io.iter_frames(tmp_path / "seq")
    first = next(frames)
    assert first.range[10, 88] == pytest.approx(1.0 / rs.get_sensor("sr3000").rays()[10, 88, 2])
    # The second file is read only when asked for: removing it now shows up now.
    (tmp_path / "seq" / "frame000001.npz").unlink()
    with pytest.raises((OSError, rs.FormatError)):
        next(frames)


def test_mixed_folder_is_an_error_naming_the_formats(tmp_path):
    rs.save(tmp_path / "a.npz", _wall_frame(1.0))
    rs.save(tmp_path / "b.pcd", _wall_frame(1.0))
    with pytest.raises(rs.FormatError, match=r"mixes scan formats \(1 \.npz, 1 \.pcd\)") as error:
        rs.load(tmp_path)
    assert str(tmp_path) in str(error.value)


def test_unknown_suffix_missing_path_and_empty_folder(tmp_path):
    unknown = tmp_path / "scan.xyz"
    unknown.write_text("1 2 3\n")
    with pytest.raises(rs.FormatError, match=r"scan.xyz: unknown format '.xyz'"):
        rs.load(unknown)
    with pytest.raises(rs.FormatError, match="nothing.npz: no such file or folder"):
        rs.load(tmp_path / "nothing.npz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(rs.FormatError, match="no range data files"):
        rs.load(tmp_path / "empty")


def test_save_rejects_unknown_formats_and_many_frames_in_one_file(tmp_path):
    frame = _wall_frame(1.0)
    with pytest.raises(ValueError, match="unknown output format 'xyz'"):
        rs.save(tmp_path / "out", [frame], format="xyz")
    with pytest.raises(ValueError, match="holds one frame, got 2"):
        rs.save(tmp_path / "two.npz", [frame, frame])
    with pytest.raises(ValueError, match="unknown output suffix '.xyz'"):
        rs.save(tmp_path / "one.xyz", frame)


def test_sensor_override_applies_to_every_frame(tmp_path):
    rs.save(tmp_path / "a.npz", _wall_frame(1.0))
    with pytest.raises(ValueError, match="unknown sensor"):
        rs.load(tmp_path, sensor="nonexistent")


def test_written_files_get_ordinary_permissions(tmp_path):
    """Atomic writes go through a private temporary file; the result must not stay private."""
    import os
    import stat

    frame = rs.RangeFrame(rays=rs.get_sensor("sr3000").rays(), range=np.full((144, 176), 2.0, np.float32),
                          sensor=rs.get_sensor("sr3000"))
    (out,) = rs.save(tmp_path / "frame.npz", frame)
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(os.stat(out).st_mode) == 0o666 & ~mask
