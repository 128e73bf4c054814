"""ROS 1 / ROS 2 bags: organized clouds, depth images + CameraInfo, topic choice."""

from __future__ import annotations

import shutil
import sys

import numpy as np
import pytest

import rangesurf as rs
from rangesurf.io import FormatError

pytest.importorskip("rosbags", reason="ROS bag tests need the rosbags extra")

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from rangesurf.io.rosbag import read_rosbag  # noqa: E402

BAG_KINDS = ["ros1", "ros2-sqlite3", "ros2-mcap"]
STAMPS_NS = [1_700_000_000_123_456_789, 1_700_000_000_223_456_789, 1_700_000_000_323_456_789]


class _Bag:
    """Writes messages built from plain values into a ROS 1 or ROS 2 bag."""

    def __init__(self, path, kind):
        self.kind = kind
        self.ros1 = kind == "ros1"
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:
            self.path = path.with_suffix(".bag")
            self.writer = Writer1(self.path)
        else:
            self.path = path
            plugin = StoragePlugin.MCAP if kind == "ros2-mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(self.path, version=9, storage_plugin=plugin)
        self.connections = {}

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def _type(self, name):
        return self.typestore.types[name]

    def header(self, stamp_ns, frame_id):
        time = self._type("builtin_interfaces/msg/Time")(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        header_type = self._type("std_msgs/msg/Header")
        if self.ros1:
            return header_type(seq=0, stamp=time, frame_id=frame_id)
        return header_type(stamp=time, frame_id=frame_id)

    def write(self, topic, msgtype, message, stamp_ns):
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.typestore)
        serialize = self.typestore.serialize_ros1 if self.ros1 else self.typestore.serialize_cdr
        self.writer.write(self.connections[topic], stamp_ns, serialize(message, msgtype))

    def cloud(self, topic, points, intensity, stamp_ns, *, frame_id="os_sensor", big_endian=False, float64=False):
        """An organized cloud with padding, an extra field and row padding."""
        height, width = points.shape[:2]
        order = ">" if big_endian else "<"
        coordinate = f"{order}f8" if float64 else f"{order}f4"
        record = np.dtype([
            ("x", coordinate), ("y", coordinate), ("z", coordinate), ("pad", "V4"),
            ("intensity", f"{order}f4"), ("ring", f"{order}u2"), ("pad2", "V2"),
        ])
        table = np.zeros((height, width), record)
        table["x"], table["y"], table["z"] = points[..., 0], points[..., 1], points[..., 2]
        table["intensity"] = intensity
        table["ring"] = np.arange(height)[:, None]
        row_step = width * record.itemsize + 12
        rows = np.zeros((height, row_step), np.uint8)
        rows[:, : width * record.itemsize] = table.view(np.uint8).reshape(height, -1)
        field = self._type("sensor_msgs/msg/PointField")
        size = 8 if float64 else 4
        fields = [
            field(name="x", offset=0, datatype=8 if float64 else 7, count=1),
            field(name="y", offset=size, datatype=8 if float64 else 7, count=1),
            field(name="z", offset=2 * size, datatype=8 if float64 else 7, count=1),
            field(name="intensity", offset=3 * size + 4, datatype=7, count=1),
            field(name="ring", offset=3 * size + 8, datatype=4, count=1),
        ]
        message = self._type("sensor_msgs/msg/PointCloud2")(
            header=self.header(stamp_ns, frame_id), height=height, width=width, fields=fields,
            is_bigendian=big_endian, point_step=record.itemsize, row_step=row_step,
            data=rows.ravel(), is_dense=False,
        )
        self.write(topic, "sensor_msgs/msg/PointCloud2", message, stamp_ns)

    def image(self, topic, pixels, encoding, stamp_ns, *, row_padding=0):
        height, width = pixels.shape[:2]
        raw = np.ascontiguousarray(pixels).view(np.uint8).reshape(height, -1)
        step = raw.shape[1] + row_padding
        rows = np.zeros((height, step), np.uint8)
        rows[:, : raw.shape[1]] = raw
        message = self._type("sensor_msgs/msg/Image")(
            header=self.header(stamp_ns, "camera_depth_optical_frame"), height=height, width=width,
            encoding=encoding, is_bigendian=0, step=step, data=rows.ravel(),
        )
        self.write(topic, "sensor_msgs/msg/Image", message, stamp_ns)

    def camera_info(self, topic, projection, shape, stamp_ns):
        k = [projection.fx, 0.0, projection.cx, 0.0, projection.fy, projection.cy, 0.0, 0.0, 1.0]
        r = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
        p = [projection.fx, 0.0, projection.cx, 0.0, 0.0, projection.fy, projection.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        roi = self._type("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        matrices = {"D": np.zeros(5), "K": np.array(k), "R": np.array(r), "P": np.array(p)}
        if not self.ros1:
            matrices = {name.lower(): value for name, value in matrices.items()}
        message = self._type("sensor_msgs/msg/CameraInfo")(
            header=self.header(stamp_ns, "camera_depth_optical_frame"), height=shape[0], width=shape[1],
            distortion_model="plumb_bob", **matrices, binning_x=0, binning_y=0, roi=roi,
        )
        self.write(topic, "sensor_msgs/msg/CameraInfo", message, stamp_ns)


def _cloud_points(seed):
    """An organized 12 x 20 body-frame cloud (x forward) with NaN points."""
    rng = np.random.default_rng(seed)
    points = np.empty((12, 20, 3))
    points[..., 0] = rng.uniform(2, 8, (12, 20))
    points[..., 1] = rng.uniform(-3, 3, (12, 20))
    points[..., 2] = rng.uniform(-1, 2, (12, 20))
    points[rng.random((12, 20)) < 0.1] = np.nan
    intensity = rng.uniform(0, 100, (12, 20)).astype(np.float32)
    return points, intensity


def _read(path, **options):
    return list(read_rosbag(path, **options))


# --------------------------------------------------------------------------
# Point clouds.
# --------------------------------------------------------------------------


@pytest.mark.parametrize("kind", BAG_KINDS)
@pytest.mark.parametrize("layout", ["float32", "float64-bigendian"])
def test_organized_clouds_read_back(tmp_path, kind, layout):
    clouds = [_cloud_points(seed) for seed in range(3)]
    float64 = layout.startswith("float64")
    with _Bag(tmp_path / "bag", kind) as bag:
        for (points, intensity), stamp in zip(clouds, STAMPS_NS):
            bag.cloud("/lidar/points", points, intensity, stamp, float64=float64, big_endian=float64)

    frames = _read(bag.path)
    assert len(frames) == 3
    for frame, (points, intensity), stamp in zip(frames, clouds, STAMPS_NS):
        valid = np.isfinite(points).all(axis=-1)
        np.testing.assert_array_equal(frame.valid, valid)
        np.testing.assert_allclose(frame.points[valid], points[valid], rtol=1e-6)
        np.testing.assert_array_equal(frame.intensity, intensity)
        assert frame.timestamp == pytest.approx(stamp * 1e-9, abs=1e-6)
        assert frame.sensor.name == "os_sensor" and frame.sensor.shape == (12, 20)
        assert frame.pose is None
        assert frame.source.endswith(":/lidar/points[%d]" % frames.index(frame))


def test_cloud_with_sensor_argument_and_grid_mismatch(tmp_path):
    points, intensity = _cloud_points(0)
    with _Bag(tmp_path / "bag", "ros1") as bag:
        bag.cloud("/lidar/points", points, intensity, STAMPS_NS[0])
    sensor = rs.unknown_sensor(12, 20, name="my-lidar")
    assert _read(bag.path, sensor=sensor)[0].sensor is sensor
    with pytest.raises(FormatError, match=r"bag\.bag, topic '/lidar/points', message 0: sensor 'sr3000' grid \(144, 176\) does not match the message's \(12, 20\)"):
        _read(bag.path, sensor=rs.get_sensor("sr3000"))


def test_unorganized_cloud_is_refused(tmp_path):
    points, intensity = _cloud_points(0)
    with _Bag(tmp_path / "bag", "ros2-sqlite3") as bag:
        bag.cloud("/scan", points.reshape(1, -1, 3), intensity.reshape(1, -1), STAMPS_NS[0])
    with pytest.raises(FormatError, match=r"bag, topic '/scan', message 0: unorganized cloud \(height 1, width 240\).*organized cloud \(height > 1\)"):
        _read(bag.path)


# --------------------------------------------------------------------------
# Depth images.
# --------------------------------------------------------------------------


def _depth_frames(fmt_plane_frame):
    return [fmt_plane_frame("sr3000", seed=seed, intensity=False, pose=False) for seed in range(3)]


@pytest.mark.parametrize("kind", BAG_KINDS)
@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_depth_images_with_camera_info(tmp_path, fmt_plane_frame, kind, encoding):
    truth = _depth_frames(fmt_plane_frame)
    sensor = rs.get_sensor("sr3000")
    with _Bag(tmp_path / "bag", kind) as bag:
        bag.camera_info("/camera/depth/camera_info", sensor.projection, sensor.shape, STAMPS_NS[0])
        for frame, stamp in zip(truth, STAMPS_NS):
            depth = frame.range.astype(np.float64) * frame.rays[..., 2]
            if encoding == "16UC1":
                pixels = np.where(frame.valid, np.rint(depth * 1000), 0).astype("<u2")
            else:
                pixels = depth.astype("<f4")  # NaN stays NaN: no return
            bag.image("/camera/depth/image_raw", pixels, encoding, stamp, row_padding=6)

    frames = _read(bag.path)
    assert [f.timestamp for f in frames] == pytest.approx([s * 1e-9 for s in STAMPS_NS], abs=1e-6)
    tolerance = 0.5e-3 if encoding == "16UC1" else 1e-6
    for frame, expected in zip(frames, truth):
        assert frame.sensor is sensor  # K matches the preset exactly
        np.testing.assert_array_equal(frame.valid, expected.valid)
        valid = expected.valid
        depth_error = np.abs(frame.points[..., 2] - expected.points[..., 2])[valid]
        assert depth_error.max() <= tolerance + 2e-6
        np.testing.assert_array_equal(frame.rays, sensor.rays())


def test_each_image_takes_the_latest_camera_info(tmp_path, fmt_plane_frame):
    truth = _depth_frames(fmt_plane_frame)
    sensor = rs.get_sensor("sr3000")
    zoomed = rs.PinholeProjection(fx=400.0, fy=400.0, cx=87.5, cy=71.5)
    with _Bag(tmp_path / "bag", "ros1") as bag:
        for frame, stamp in zip(truth, STAMPS_NS):
            if stamp == STAMPS_NS[0]:
                bag.camera_info("/cam/camera_info", sensor.projection, sensor.shape, stamp)
            if stamp == STAMPS_NS[2]:
                bag.camera_info("/cam/camera_info", zoomed, sensor.shape, stamp)
            depth = np.where(frame.valid, np.rint(frame.points[..., 2] * 1000), 0).astype("<u2")
            bag.image("/cam/depth", depth, "16UC1", stamp)

    frames = _read(bag.path)
    assert [f.sensor.projection for f in frames] == [sensor.projection, sensor.projection, zoomed]
    assert frames[2].sensor.name == "depth-camera"
    # Same z-depth through a different lens: the same z, other rays.
    np.testing.assert_allclose(frames[2].points[..., 2][truth[2].valid], truth[2].points[..., 2][truth[2].valid], atol=0.5e-3 + 2e-6)


def test_depth_image_without_camera_info(tmp_path, fmt_plane_frame):
    frame = _depth_frames(fmt_plane_frame)[0]
    with _Bag(tmp_path / "bag", "ros2-mcap") as bag:
        bag.image("/camera/depth/image_raw", frame.points[..., 2].astype("<f4"), "32FC1", STAMPS_NS[0])
    with pytest.raises(FormatError, match=r"bag, topic '/camera/depth/image_raw': no sensor_msgs/msg/CameraInfo on /camera/depth/camera_info"):
        _read(bag.path)
    (copy,) = _read(bag.path, sensor=rs.get_sensor("sr3000"))
    np.testing.assert_array_equal(copy.valid, frame.valid)


def test_colour_image_is_not_depth(tmp_path):
    with _Bag(tmp_path / "bag", "ros1") as bag:
        bag.image("/camera/color/image_raw", np.zeros((4, 5, 3), np.uint8), "rgb8", STAMPS_NS[0])
    with pytest.raises(FormatError, match=r"bag\.bag, topic '/camera/color/image_raw', message 0: image encoding 'rgb8' is not depth"):
        _read(bag.path, sensor=rs.get_sensor("sr3000"))


# --------------------------------------------------------------------------
# Topic selection and bag locations.
# --------------------------------------------------------------------------


@pytest.fixture
def mixed_bag(tmp_path, fmt_plane_frame):
    """ROS 2 bag: an organized cloud, a depth image, a colour image, CameraInfo."""
    sensor = rs.get_sensor("sr3000")
    frame = _depth_frames(fmt_plane_frame)[0]
    points, intensity = _cloud_points(0)
    with _Bag(tmp_path / "mixed", "ros2-mcap") as bag:
        bag.camera_info("/camera/depth/camera_info", sensor.projection, sensor.shape, STAMPS_NS[0])
        bag.image("/camera/depth/image_raw", frame.points[..., 2].astype("<f4"), "32FC1", STAMPS_NS[0])
        bag.image("/camera/color/image_raw", np.zeros((4, 5, 3), np.uint8), "rgb8", STAMPS_NS[0])
        bag.cloud("/lidar/points", points, intensity, STAMPS_NS[1])
    return bag.path


def test_several_candidate_topics_are_listed(mixed_bag):
    with pytest.raises(FormatError, match=r"mixed: several range topics: /camera/depth/image_raw \(sensor_msgs/msg/Image\), /lidar/points \(sensor_msgs/msg/PointCloud2\); pass topic="):
        _read(mixed_bag)
    (cloud,) = _read(mixed_bag, topic="/lidar/points")
    assert cloud.shape == (12, 20)
    (depth,) = _read(mixed_bag, topic="/camera/depth/image_raw")
    assert depth.sensor.name == "sr3000"


def test_bad_topic_names(mixed_bag):
    with pytest.raises(FormatError, match=r"mixed, topic '/nope': no such topic; range topics: .*/lidar/points"):
        _read(mixed_bag, topic="/nope")
    with pytest.raises(FormatError, match=r"mixed, topic '/camera/depth/camera_info': has type sensor_msgs/msg/CameraInfo; expected organized"):
        _read(mixed_bag, topic="/camera/depth/camera_info")


def test_colour_image_is_skipped_when_choosing(tmp_path, fmt_plane_frame):
    sensor = rs.get_sensor("sr3000")
    frame = _depth_frames(fmt_plane_frame)[0]
    with _Bag(tmp_path / "bag", "ros1") as bag:
        bag.camera_info("/camera/depth/camera_info", sensor.projection, sensor.shape, STAMPS_NS[0])
        bag.image("/camera/color/image_raw", np.zeros((4, 5, 3), np.uint8), "rgb8", STAMPS_NS[0])
        bag.image("/camera/depth/image_raw", frame.points[..., 2].astype("<f4"), "32FC1", STAMPS_NS[0])
    (copy,) = _read(bag.path)
    np.testing.assert_array_equal(copy.valid, frame.valid)


def test_bag_without_range_topics(tmp_path):
    with _Bag(tmp_path / "bag", "ros1") as bag:
        bag.camera_info("/camera/camera_info", rs.get_sensor("sr3000").projection, (144, 176), STAMPS_NS[0])
    with pytest.raises(FormatError, match=r"bag\.bag: no organized sensor_msgs/PointCloud2 or depth sensor_msgs/Image .*the bag has: /camera/camera_info"):
        _read(bag.path)


def test_storage_file_inside_and_outside_its_folder(mixed_bag, tmp_path):
    (storage,) = mixed_bag.glob("*.mcap")
    (cloud,) = _read(storage, topic="/lidar/points")  # opens the folder
    assert cloud.shape == (12, 20)
    alone = tmp_path / "alone.mcap"
    shutil.copy(storage, alone)
    (cloud,) = _read(alone, topic="/lidar/points")  # no metadata.yaml: the file itself
    assert cloud.timestamp == pytest.approx(STAMPS_NS[1] * 1e-9, abs=1e-6)


def test_load_dispatches_bags_with_topic(mixed_bag):
    frames = rs.load(mixed_bag, topic="/lidar/points")
    assert len(frames) == 1 and frames[0].shape == (12, 20)


def test_bad_bag_files(tmp_path):
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    with pytest.raises(FormatError, match=r"empty\.bag: empty file"):
        _read(empty)
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V9.9\n garbage")
    with pytest.raises(FormatError, match=r"junk\.bag: cannot open as a ROS bag"):
        _read(junk)
    junk_mcap = tmp_path / "junk.mcap"
    junk_mcap.write_bytes(b"not an mcap file at all")
    with pytest.raises(FormatError, match=r"junk\.mcap: cannot open as a ROS bag"):
        _read(junk_mcap)
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(FormatError, match=r"folder: folder is not a ROS 2 bag \(no metadata\.yaml\)"):
        _read(folder)


def test_missing_rosbags_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(ImportError, match=r"pip install 'rangesurf\[bags\]'"):
        _read(tmp_path / "any.bag")
