"""Foxglove out (bubble_rt.io.foxglove): message builders, the live WebSocket server (with a
minimal WebSocket client written here, no project code) and the channels in recordings."""

from __future__ import annotations

import base64
import json
import logging
import os
import socket
import struct
import time

import numpy as np
import pytest
from bubble_rt.daemon.foxglove_view import FoxgloveView
from bubble_rt.daemon.service import Daemon
from bubble_rt.io import foxglove as fx
from bubble_rt.io.protocol import Patch
from daemon_fakes import FakeProcessor, ScriptedCamera, coarse_mesh, constant_pressure, fake_config
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

pytestmark = pytest.mark.timeout(60)


def message_class(name: str, fds_bytes: bytes):  # type: ignore[no-untyped-def]
    """A protobuf class from a schema's FileDescriptorSet (what a Foxglove client does)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(fds_bytes)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def arrow_tips(scene) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Tip points of a decoded SceneUpdate's arrows (pose position + length along rotated x)."""
    from scipy.spatial.transform import Rotation

    ent = {e.id: e for e in scene.entities}
    tips = []
    for a in ent["forces"].arrows:
        o = a.pose.orientation
        d = Rotation.from_quat([o.x, o.y, o.z, o.w]).apply([1.0, 0.0, 0.0])
        p = a.pose.position
        tips.append(np.array([p.x, p.y, p.z]) + d * (a.shaft_length + a.head_length))
    return np.array(tips)


def test_scene_update_builder_arrows_colours_patches():
    mesh = coarse_mesh()
    n = mesh.n_nodes
    nodes = np.flatnonzero(mesh.interior)[:4]
    F = np.zeros((n, 3))
    F[nodes] = [0.0, 0.1, -0.2]
    p = np.zeros(n)
    p[nodes] = 6000.0
    contact = np.zeros(n, bool)
    contact[nodes] = True
    patch = Patch(
        centroid=mesh.vertices[nodes].mean(axis=0), area=1e-4, force=F.sum(0), nodes=nodes
    )
    F[mesh.boundary[:3]] = [0.0, 0.0, 1.0]  # rim support: no arrows
    msg = fx.scene_update(
        mesh.vertices, mesh.triangles, F, p, contact, [patch], boundary=mesh.boundary, t_ns=123
    )
    schema = msg.get_schema()
    scene = message_class("foxglove.SceneUpdate", bytes(schema.data)).FromString(msg.encode())
    ent = {e.id: e for e in scene.entities}
    assert set(ent) == {"membrane", "forces", "contact"}
    tri = ent["membrane"].triangles[0]
    assert len(tri.points) == len(tri.colors) == n and len(tri.indices) == 3 * len(mesh.triangles)
    red = tri.colors[int(nodes[0])]
    assert red.r > 0.8 and red.g < 0.2  # above pressure_max_pa: red
    assert len(ent["forces"].arrows) == 4
    a = ent["forces"].arrows[0]
    assert a.shaft_length + a.head_length == pytest.approx(
        fx.ARROW_SCALE_M_PER_N * np.linalg.norm([0.1, 0.2]), rel=1e-6
    )
    np.testing.assert_allclose(arrow_tips(scene), mesh.vertices[nodes], atol=1e-6)  # tip at node
    assert len(ent["contact"].spheres) == 4
    assert ent["contact"].texts[0].text == f"patch 0: {np.linalg.norm(patch.force):.2f} N"
    assert ent["membrane"].frame_id == fx.FRAME_ID


def test_scene_draws_the_wrench_on_its_line_of_action_and_patch_outlines():
    from scipy.spatial.transform import Rotation

    mesh = coarse_mesh()
    n = mesh.n_nodes
    a = int(np.flatnonzero(mesh.interior)[10])
    ring = mesh.adjacency()[a].indices
    nodes = np.concatenate([[a], ring])
    contact = np.zeros(n, bool)
    contact[nodes] = True
    F = np.zeros((n, 3))
    F[nodes] = [0.0, 0.0, -0.5]
    c = mesh.vertices[a]
    patch = Patch(centroid=c, area=1e-4, force=F.sum(0), nodes=nodes)
    f = F.sum(0)
    tau = np.cross(c, f)  # the force acts through the patch's centre
    msg = fx.scene_update(
        mesh.vertices, mesh.triangles, F, np.zeros(n), contact, [patch], net_force=f, net_torque=tau
    )
    scene = message_class("foxglove.SceneUpdate", bytes(msg.get_schema().data)).FromString(
        msg.encode()
    )
    ent = {e.id: e for e in scene.entities}
    force_arrow, torque_arrow = ent["wrench"].arrows
    o = force_arrow.pose.orientation
    d = Rotation.from_quat([o.x, o.y, o.z, o.w]).apply([1.0, 0.0, 0.0])
    p = force_arrow.pose.position
    tip = np.array([p.x, p.y, p.z]) + d * (force_arrow.shaft_length + force_arrow.head_length)
    np.testing.assert_allclose(tip, c, atol=1e-9)  # the line of action through the centroid
    np.testing.assert_allclose(d, f / np.linalg.norm(f), atol=1e-9)
    assert torque_arrow.shaft_length + torque_arrow.head_length == pytest.approx(
        fx.TORQUE_SCALE_M_PER_NM * np.linalg.norm(tau)
    )
    # The outline of a node and its ring of neighbours is the ring: one edge per ring segment.
    (line,) = ent["contact"].lines
    pts = np.array([[q.x, q.y, q.z] for q in line.points]).reshape(-1, 2, 3)
    assert len(pts) == len(ring)
    assert not np.any(np.all(np.isclose(pts, c), axis=2))  # the centre node is inside


def test_scene_draws_the_membrane_where_the_frame_says_it_is():
    """The frame's node_displacements move the mesh and the arrows that end on it (a
    recording replayed into Foxglove shows the dent, not the untouched dome)."""
    from bubble_rt.io import protocol

    mesh = coarse_mesh()
    n = mesh.n_nodes
    nodes = np.flatnonzero(mesh.interior)[:3]
    F = np.zeros((n, 3))
    F[nodes, 2] = -1.0
    contact = np.zeros(n, bool)
    contact[nodes] = True
    u = np.zeros((n, 3))
    u[nodes] = [0.001, -0.002, -0.004]
    mesh_msg = protocol.encode_mesh("s", mesh.vertices, mesh.triangles, mesh.boundary)
    tips = []
    for disp in (None, u):
        msg = protocol.encode_force_frame(
            sensor_id="s",
            seq=0,
            frame_index=0,
            capture_time_ns=1,
            mesh_id=mesh_msg.mesh_id,
            net_force=F.sum(axis=0),
            node_forces=F,
            normal_pressure=np.zeros(n),
            contact=contact,
            node_displacements=disp,
        )
        (m,) = [e for e in fx.SceneBuilder().frame(msg, mesh_msg) if e.topic == fx.TOPIC_SCENE]
        tips.append(arrow_tips(message_class(m.schema_name, m.schema_data).FromString(m.data)))
    np.testing.assert_allclose(tips[0], mesh.vertices[nodes], atol=1e-6)
    np.testing.assert_allclose(tips[1], mesh.vertices[nodes] + u[nodes], atol=1e-6)


def test_parse_address():
    assert fx.parse_address(None) == ("127.0.0.1", 8765)
    assert fx.parse_address("ws://0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert fx.parse_address(":*") == ("127.0.0.1", 0)  # any free port
    assert fx.parse_address("ws://[::1]") == ("::1", 8765)
    with pytest.raises(ValueError, match="ws://"):
        fx.parse_address("http://x:1")


# ------------------------------------------------------------------ a minimal WebSocket client
class WsClient:
    def __init__(self, port: int, subprotocol: str = "foxglove.sdk.v1") -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {subprotocol}\r\n\r\n"
            ).encode()
        )
        self.buf = b""
        while b"\r\n\r\n" not in self.buf:
            self.buf += self._recv()
        head, self.buf = self.buf.split(b"\r\n\r\n", 1)
        assert b" 101 " in head.split(b"\r\n")[0], head

    def _recv(self) -> bytes:
        chunk = self.sock.recv(1 << 16)
        if not chunk:
            raise ConnectionError("closed")
        return chunk

    def _take(self, n: int) -> bytes:
        while len(self.buf) < n:
            self.buf += self._recv()
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def recv(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next complete message."""
        data, opcode = b"", None
        while True:
            b0, b1 = self._take(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._take(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._take(8))[0]
            payload = self._take(n)
            op = b0 & 0x0F
            if op == 9:  # ping
                continue
            opcode = op if opcode is None else opcode
            data += payload
            if b0 & 0x80:
                return opcode, data

    def send_text(self, text: str) -> None:
        p = text.encode()
        mask = os.urandom(4)
        head = bytes([0x81])
        if len(p) < 126:
            head += bytes([0x80 | len(p)])
        else:
            head += bytes([0x80 | 126]) + struct.pack(">H", len(p))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(p)))

    def close(self) -> None:
        self.sock.sendall(bytes([0x88, 0x80]) + os.urandom(4))  # masked close frame
        self.sock.close()


def test_live_server_scene_arrows_and_recorded_channels(tmp_path):
    from mcap.reader import make_reader

    rec_path = tmp_path / "rec.mcap"
    d = Daemon(
        fake_config(**{"recording.path": str(rec_path)}),
        camera=ScriptedCamera(),
        pressure=constant_pressure(),
        processor_factory=FakeProcessor,
    )
    view = FoxgloveView("ws://127.0.0.1:*")
    d.viewers.append(view)
    d.start()
    try:
        assert d.wait_ready(20.0)
        port = int(view.address.rsplit(":", 1)[1])
        ws = WsClient(port)
        channels: dict[str, dict] = {}
        end = time.monotonic() + 15
        while fx.TOPIC_SCENE not in channels and time.monotonic() < end:
            op, data = ws.recv()
            if op == 1:
                m = json.loads(data)
                if m.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in m["channels"]})
        ch = channels[fx.TOPIC_SCENE]
        assert ch["schemaName"] == "foxglove.SceneUpdate" and ch["encoding"] == "protobuf"
        ws.send_text(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": ch["id"]}]})
        )
        cls = message_class("foxglove.SceneUpdate", base64.b64decode(ch["schema"]))
        # Four scenes sent: the view has written them to the recording too (checked below).
        scenes = []
        while len(scenes) < 4:
            op, data = ws.recv()
            if op == 2 and data[0] == 1:  # messageData
                sub, _log_ns = struct.unpack_from("<IQ", data, 1)
                assert sub == 7
                scenes.append(cls.FromString(data[13:]))
        scene = scenes[0]
        ws.close()
        # FakeProcessor: 5 interior nodes pushed along -z, in total 1..5 N.
        arrows = {e.id: e for e in scene.entities}["forces"].arrows
        assert len(arrows) == 5
        lengths = [a.shaft_length + a.head_length for a in arrows]
        assert np.ptp(lengths) < 1e-9
        total = lengths[0] / fx.ARROW_SCALE_M_PER_N * 5
        assert min(abs(total - k) for k in (1, 2, 3, 4, 5)) < 1e-6
        mesh = coarse_mesh()
        nodes = np.flatnonzero(mesh.interior)[:5]
        np.testing.assert_allclose(arrow_tips(scene), mesh.vertices[nodes], atol=1e-6)
        assert {fx.TOPIC_NET_FORCE, fx.TOPIC_TRUE_FORCE, fx.TOPIC_IMAGE, fx.TOPIC_STATUS} <= set(
            channels
        )
    finally:
        d.stop()
    assert view.error == ""
    with open(rec_path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        schemas = {
            c.topic: (summary.schemas[c.schema_id].name, c.message_encoding)
            for c in summary.channels.values()
        }
        assert schemas[fx.TOPIC_SCENE] == ("foxglove.SceneUpdate", "protobuf")
        assert schemas[fx.TOPIC_IMAGE] == ("foxglove.CompressedImage", "protobuf")
        assert schemas[fx.TOPIC_NET_FORCE] == ("bubble_rt.NetForce", "json")
        assert schemas[fx.TOPIC_STATUS] == ("bubble_rt.Status", "json")
        assert schemas["/bubble_rt/force"][0] == "bubble_rt.v1.ForceFrame"  # still there
        n_scene = 0
        for schema, channel, message in reader.iter_messages(
            topics=[fx.TOPIC_SCENE, fx.TOPIC_NET_FORCE]
        ):
            if channel.topic == fx.TOPIC_SCENE:
                scene = message_class(schema.name, schema.data).FromString(message.data)
                assert len({e.id: e for e in scene.entities}["forces"].arrows) == 5
                n_scene += 1
            else:
                nf = json.loads(message.data)
                assert nf["magnitude"] == pytest.approx(np.linalg.norm([nf["x"], nf["y"], nf["z"]]))
                assert nf["z"] < 0
        assert n_scene > 3


def test_replay_of_a_bag_at_recorded_pace(tmp_path):
    from broken_bags import bag_frames
    from bubble_rt.daemon.sources import ReplayCamera
    from bubble_rt.io.bag_writer import write_bag

    frames, cam = bag_frames(12)
    bag = write_bag(tmp_path / "bag", frames, cam)
    src = ReplayCamera(str(bag), realtime=True)
    assert src.name == "replay:bag"
    src.start()
    got: list = []
    stamps: dict[int, float] = {}
    end = time.monotonic() + 10
    while (not got or got[-1].index < 11) and time.monotonic() < end:
        f = src.output.get(timeout=0.5)
        if f is not None:
            stamps[f.index] = time.monotonic()
            got.append(f)
    src.stop(0.5)
    idx = [f.index for f in got]
    # (the source may replace frame 0 by frame 1 right after opening: it does not catch up)
    assert idx == sorted(set(idx)) and idx[-1] == 11 and len(idx) >= 10
    # the bag's 30 Hz, not as fast as possible
    assert stamps[11] - stamps[3] == pytest.approx(8 / 30, abs=0.1)
    k = idx.index(5)
    np.testing.assert_array_equal(got[k].rgb, frames[5].rgb)


def test_serve_flags_foxglove_default_and_bag_replay_options(tmp_path):
    import argparse

    from broken_bags import bag_frames
    from bubble_rt.commands import serve
    from bubble_rt.io.bag_writer import write_bag

    parser = argparse.ArgumentParser()
    serve.add_arguments(parser)
    assert parser.parse_args([]).foxglove is None  # off by default
    assert parser.parse_args(["--foxglove"]).foxglove == fx.DEFAULT_ADDRESS
    assert parser.parse_args(["--foxglove", "ws://0.0.0.0:9"]).foxglove == "ws://0.0.0.0:9"
    frames, cam = bag_frames(3)
    bag = write_bag(tmp_path / "bag", frames, cam)
    args = parser.parse_args(["--camera", f"replay:{bag}", "--topics", "/bubble_1"])
    src = serve.bag_replay_source(serve.build_config(args), args)
    assert src is not None and src.name == "replay:bag"
    args = parser.parse_args(["--camera", f"replay:{bag}", "--topics", "/bubble_9"])
    from bubble_rt.daemon.sources import SourceError

    with pytest.raises(SourceError, match="color: no sensor_msgs/msg/Image topic under /bubble_9"):
        serve.bag_replay_source(serve.build_config(args), args)
    assert serve.bag_replay_source(serve.build_config(parser.parse_args([])), args) is None


def test_one_log_line_per_client_connection(caplog):
    """foxglove-sdk logged three or four lines for one client connecting and leaving (its
    messages, as it logs them; the live level cannot be set in a process that already ran a
    server: foxglove-sdk reads it once)."""
    view = FoxgloveView("ws://127.0.0.1:*")
    view.close()  # its loggers now carry the filter
    c = "127.0.0.1:40000"
    emitted = [
        ("foxglove.websocket.server", logging.INFO, f"Registered client {c}"),
        (
            "foxglove.websocket.connected_client.poller",
            logging.ERROR,
            f"Error receiving from client {c}: WebSocket protocol error: Connection reset "
            "without closing handshake",
        ),
        (
            "foxglove.websocket.connected_client.poller",
            logging.INFO,
            f"Connection closed by client {c}",
        ),
        ("foxglove.websocket.server", logging.INFO, f"Unregistered client {c}"),
    ]
    with caplog.at_level(logging.INFO, logger="foxglove"):
        for name, level, text in emitted:
            logging.getLogger(name).log(level, text)
    assert [r.getMessage() for r in caplog.records] == [f"Registered client {c}"]
