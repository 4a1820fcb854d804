"""ROS 2 bags in and out (bubble_rt.io.rosbag): bags written here with rosbags."""

from __future__ import annotations

import json

import numpy as np
import pytest
from broken_bags import INFO, PRESSURE, RAMP_PA_PER_S, T0, bag_frames, with_depth_size, without
from bubble_rt.camera import Camera
from bubble_rt.cli import main
from bubble_rt.frames import Frame, FrameError
from bubble_rt.io.bag_messages import NODE_FIELDS
from bubble_rt.io.bag_topics import BagTopicError, choose_topics
from bubble_rt.io.bag_writer import read_node_cloud, write_bag
from bubble_rt.io.recordings import open_recording
from bubble_rt.io.rosbag import BagRecording, is_rosbag
from synth_rgbd import dome_depth, texture


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
@pytest.mark.parametrize("wrench", [True, False])
def test_bag_round_trip_frame_for_frame(tmp_path, storage, encoding, wrench):
    frames, cam = bag_frames(wrench=wrench, mm=encoding == "16UC1")
    path = write_bag(
        tmp_path / "bag", frames, cam, storage=storage, depth_encoding=encoding, wrench=wrench
    )
    assert is_rosbag(path)
    rec = open_recording(path)
    assert isinstance(rec, BagRecording) and rec.layout == "rosbag"
    assert len(rec) == len(frames) and rec.skipped == 0
    assert rec.topics["pressure"] == "/bubble_1/pressure"
    assert (rec.camera.fx, rec.camera.cx, rec.camera.width) == (cam.fx, cam.cx, cam.width)
    got = list(rec)
    for f, g in zip(got, frames, strict=True):
        assert f.index == g.index
        assert f.t == pytest.approx(g.t, abs=1e-9)
        np.testing.assert_array_equal(f.rgb, g.rgb)
        np.testing.assert_allclose(f.depth, g.depth, atol=1e-6)
        # Headerless pressure, received 10 ms after sampling, matched at the frame's time.
        assert f.pressure_pa == pytest.approx(g.pressure_pa, abs=0.02)
        if wrench:
            np.testing.assert_array_equal(f.wrench, g.wrench)
        else:
            assert f.wrench is None
    assert (rec.wrenches is not None) == wrench
    # Random access (backwards re-reads) gives the same frames.
    np.testing.assert_array_equal(rec[3].rgb, frames[3].rgb)
    np.testing.assert_array_equal(rec[1].rgb, frames[1].rgb)


def test_own_mcap_recordings_are_not_bags(tmp_path):
    from bubble_rt.io.mcap_writer import write_recording

    frames, cam = bag_frames(2)
    p = tmp_path / "run.mcap"
    write_recording(p, frames, cam)
    assert not is_rosbag(p) and not is_rosbag(tmp_path)
    bag = write_bag(tmp_path / "bag", frames, cam)
    assert is_rosbag(next(bag.glob("*.mcap")))  # a lone bag file opens too
    assert len(open_recording(next(bag.glob("*.mcap")))) == 2


def test_pressure_receive_time_and_firmware_delay(tmp_path):
    frames, cam = bag_frames()
    path = write_bag(tmp_path / "bag", frames, cam)
    late = BagRecording(path, pressure_delay_s=0.0)  # ignoring the 10 ms firmware lag
    for f, g in zip(late, frames, strict=True):
        # read 10 ms too early on the ramp: exactly the lag times the slope
        assert f.pressure_pa == pytest.approx(g.pressure_pa - 0.010 * RAMP_PA_PER_S, abs=0.02)


def test_bgr8_colour_and_aligned_depth_and_tf_pose(tmp_path):
    frames, cam = bag_frames(3)
    cam = cam.with_pose(np.array([[1, 0, 0, 0.001], [0, 1, 0, 0], [0, 0, 1, -0.07], [0, 0, 0, 1]]))
    path = write_bag(tmp_path / "bag", frames, cam, color_encoding="bgr8", aligned=True, tf=True)
    rec = open_recording(path)
    assert "aligned_depth_to_color" in rec.topics["depth"]
    np.testing.assert_array_equal(rec[0].rgb, frames[0].rgb)
    np.testing.assert_allclose(rec.camera.pose_matrix, cam.pose_matrix, atol=1e-9)
    assert rec.placement.startswith("/tf_static")


def test_depth_unit_setting(tmp_path):
    frames, cam = bag_frames(2, mm=False)
    path = write_bag(tmp_path / "bag", frames, cam, depth_unit=1e-4)  # a 0.1 mm driver
    rec = open_recording(path, depth_unit=1e-4)
    np.testing.assert_allclose(rec[0].depth, frames[0].depth, atol=6e-5)


def test_incomplete_bags_name_what_is_missing(tmp_path):
    frames, cam = bag_frames(2)
    p = without(tmp_path, INFO, frames, cam, "noinfo")
    with pytest.raises(FrameError, match=r"info: no sensor_msgs/msg/CameraInfo"):
        open_recording(p)
    p = without(tmp_path, PRESSURE, frames, cam, "nopressure")
    with pytest.raises(BagTopicError, match=r"pressure: no std_msgs/msg/Float32") as exc:
        open_recording(p)
    assert "/bubble_1/color/image_rect_raw  [sensor_msgs/msg/Image]" in str(exc.value)
    p = with_depth_size(tmp_path, frames, cam, (40, 30))
    with pytest.raises(FrameError, match=r"colour 80 x 60 .* and depth 40 x 30 .* differ"):
        open_recording(p)
    with pytest.raises(FrameError, match="depth unit must be positive"):
        BagRecording(tmp_path / "sizes", depth_unit=0.0)


def test_topic_choice_ambiguous_and_overrides():
    found = {
        "/bubble_1/color/image_rect_raw": "sensor_msgs/msg/Image",
        "/bubble_1/depth/image_rect_raw": "sensor_msgs/msg/Image",
        "/bubble_1/color/camera_info": "sensor_msgs/msg/CameraInfo",
        "/bubble_1/pressure": "std_msgs/msg/Float32",
        "/bubble_2/color/image_rect_raw": "sensor_msgs/msg/Image",
        "/bubble_2/depth/image_rect_raw": "sensor_msgs/msg/Image",
        "/bubble_2/aligned_depth_to_color/image_raw": "sensor_msgs/msg/Image",
        "/bubble_2/color/camera_info": "sensor_msgs/msg/CameraInfo",
        "/bubble_2/pressure": "std_msgs/msg/Float32",
    }
    with pytest.raises(BagTopicError, match="color: ambiguous") as exc:
        choose_topics(found)
    msg = str(exc.value)
    assert "/bubble_2/pressure  [std_msgs/msg/Float32]" in msg and "--topics" in msg
    one = choose_topics(found, "/bubble_1")
    assert one == {
        "color": "/bubble_1/color/image_rect_raw",
        "depth": "/bubble_1/depth/image_rect_raw",
        "info": "/bubble_1/color/camera_info",
        "pressure": "/bubble_1/pressure",
    }
    two = choose_topics(found, "/bubble_2")
    assert two["depth"] == "/bubble_2/aligned_depth_to_color/image_raw"  # preferred
    given = choose_topics(
        found,
        "color=/bubble_2/color/image_rect_raw,depth=/bubble_2/depth/image_rect_raw,"
        "info=/bubble_2/color/camera_info,pressure=/bubble_2/pressure",
    )
    assert given["depth"] == "/bubble_2/depth/image_rect_raw"
    with pytest.raises(BagTopicError, match="not in the bag"):
        choose_topics(found, "/bubble_1,pressure=/nope")
    with pytest.raises(BagTopicError, match="unknown role"):
        choose_topics(found, "colour=/x")


def test_estimate_writes_a_bag_read_back_with_rosbags(tmp_path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    cam = Camera.d405()
    depth = (np.round(dome_depth(cam) * 1000) / 1000).astype(np.float32)
    img = texture(cam.height, cam.width)
    frames = [
        Frame(img, depth, 101_300.0 + 10 * i, t=T0 + 0.1 * i, wrench=np.zeros(6), index=i)
        for i in range(4)
    ]
    src = write_bag(tmp_path / "in", frames, cam, tf=True)
    out = tmp_path / "out"
    js = tmp_path / "out.json"
    args = ["estimate", str(src), "--reference-frames", "0-1", "--mesh", "coarse"]
    assert main([*args, "--bag", str(out), "--json", str(js), "--no-progress"]) == 0
    res = json.loads(js.read_text())
    assert res["layout"] == "rosbag" and len(res["frames"]) == 4
    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {
            "/bubble_rt/wrench": "geometry_msgs/msg/WrenchStamped",
            "/bubble_rt/nodes": "sensor_msgs/msg/PointCloud2",
        }
        wrenches, clouds = [], []
        for conn, t_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            (wrenches if conn.topic == "/bubble_rt/wrench" else clouds).append((t_ns, msg))
    assert len(wrenches) == len(clouds) == 4
    for k, ((tw, w), (tc, c)) in enumerate(zip(wrenches, clouds, strict=True)):
        assert tw == tc == int(round(frames[k].t * 1e9))
        assert w.header.frame_id == c.header.frame_id == "bubble_rt_sensor"
        f = res["frames"][k]["net_force_mesh"]
        assert [w.wrench.force.x, w.wrench.force.y, w.wrench.force.z] == pytest.approx(f)
        tau = res["frames"][k]["net_torque_mesh"]
        assert [w.wrench.torque.x, w.wrench.torque.y, w.wrench.torque.z] == pytest.approx(tau)
        assert [fl.name for fl in c.fields] == list(NODE_FIELDS)
        cloud = read_node_cloud(c)
        assert len(cloud["x"]) == c.width > 50
        assert set(np.unique(cloud["contact"])) <= {0.0, 1.0}
        assert all(np.isfinite(cloud[k]).all() for k in NODE_FIELDS)


def test_estimate_bag_errors_are_clear(tmp_path, capsys):
    frames, cam = bag_frames(2)
    p = without(tmp_path, PRESSURE, frames, cam, "nopressure")
    assert main(["estimate", str(p), "--json", str(tmp_path / "o.json")]) == 2
    assert "pressure: no std_msgs/msg/Float32" in capsys.readouterr().err


def test_bag_wrench_carries_the_torque(tmp_path):
    from bubble_rt.io.bag_writer import BagWriter
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    n = 3
    tau = np.array([0.012, -0.034, 0.0005])
    with BagWriter(tmp_path / "out") as bag:
        bag.write(
            T0,
            np.array([0.1, 0.2, -3.0]),
            np.zeros((n, 3)),
            np.zeros((n, 3)),
            np.zeros(n),
            np.zeros(n, bool),
            net_torque=tau,
        )
    with AnyReader([tmp_path / "out"], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        (w,) = [
            r.deserialize(raw, c.msgtype)
            for c, _, raw in r.messages()
            if c.topic == "/bubble_rt/wrench"
        ]
    t = w.wrench.torque
    assert [t.x, t.y, t.z] == pytest.approx(tau.tolist())
    assert w.wrench.force.z == pytest.approx(-3.0)
