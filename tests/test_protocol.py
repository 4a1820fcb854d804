"""Protocol: generated code up to date, round trips, request parsing."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bubble_rt.io import protocol
from bubble_rt.io.protocol import Patch, ProtocolError, pb

PROTO_DIR = Path(__file__).resolve().parents[1] / "proto"


def _serialized_descriptor(generated: Path) -> bytes:
    tree = ast.parse(generated.read_text())
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and getattr(node.func, "attr", "") == "AddSerializedFile"
            and node.args
        ):
            return ast.literal_eval(node.args[0])
    raise AssertionError(f"no AddSerializedFile in {generated}")


@pytest.mark.parametrize("stem", ["bubble_rt", "foxglove_raw_image", "foxglove_compressed_image"])
def test_generated_code_is_up_to_date(stem, tmp_path):
    import importlib

    protos = sorted((PROTO_DIR / "bubble_rt" / "v1").glob("*.proto"))
    assert protos, "proto/bubble_rt/v1 holds the schema"
    subprocess.run(
        [sys.executable, "-m", "grpc_tools.protoc", f"-I{PROTO_DIR}", f"--python_out={tmp_path}"]
        + [str(p) for p in protos],
        check=True,
    )
    fresh = _serialized_descriptor(tmp_path / "bubble_rt" / "v1" / f"{stem}_pb2.py")
    installed = importlib.import_module(f"bubble_rt.proto_gen.bubble_rt.v1.{stem}_pb2")
    assert installed.DESCRIPTOR.serialized_pb == fresh, (
        f"{stem}_pb2 is stale: rebuild (bash .ci/dev-build.sh) after editing proto/"
    )


def test_package_is_versioned():
    assert pb.DESCRIPTOR.package == "bubble_rt.v1"
    assert pb.PROTOCOL_VERSION_1 == protocol.PROTOCOL_VERSION


def test_force_frame_round_trip():
    rng = np.random.default_rng(1)
    n = 11
    forces = rng.normal(size=(n, 3))
    contact = rng.random(n) > 0.5
    patch = Patch(
        centroid=np.array([0.01, 0.0, 0.02]),
        area=1e-4,
        force=np.array([0, 0, -1.0]),
        nodes=np.array([1, 2]),
    )
    info = type(
        "I",
        (),
        {
            "status": "solved",
            "iterations": 7,
            "primal_residual": 1e-5,
            "dual_residual": 2e-5,
            "objective": float("nan"),
        },
    )()
    msg = protocol.encode_force_frame(
        sensor_id="s",
        seq=3,
        frame_index=9,
        capture_time_ns=1000,
        mesh_id="m",
        net_force=forces.sum(0),
        node_forces=forces,
        normal_pressure=np.arange(n, dtype=float),
        contact=contact,
        patches=[patch],
        pressure_delta_pa=12.5,
        pressure_pa=101337.5,
        timings_ms={"flow": 3.0, "solve": 4.0},
        solver_info=info,
        valid_node_fraction=0.9,
        degraded_reasons=["pressure stale (300 ms)"],
    )
    protocol.stamp_publish(msg, 5_001_000)
    f = protocol.decode_force_frame(msg.SerializeToString())
    np.testing.assert_array_equal(f.node_forces, forces)
    np.testing.assert_array_equal(f.contact, contact)
    assert f.seq == 3 and f.frame_index == 9 and f.latency_ms == pytest.approx(5.0)
    assert f.timings_ms == {"flow": 3.0, "solve": 4.0}
    assert f.solver_status == "solved" and f.solver_iterations == 7
    assert f.degraded and f.degraded_reasons == ["pressure stale (300 ms)"]
    assert len(f.patches) == 1 and list(f.patches[0].nodes) == [1, 2]
    assert msg.solver.objective == 0.0  # non-finite values are not sent
    s = f.summary()
    assert s["contact_nodes"] == int(contact.sum()) and s["degraded"]


def test_mesh_round_trip_and_id():
    v = np.random.default_rng(2).random((4, 3))
    t = np.array([[0, 1, 2], [0, 2, 3]])
    m = protocol.decode_mesh(protocol.encode_mesh("s", v, t, [0, 1], np.ones(4)))
    np.testing.assert_array_equal(m.vertices, v)
    np.testing.assert_array_equal(m.triangles, t)
    assert m.mesh_id == protocol.mesh_id_of(v, t) and len(m.mesh_id) == 16
    assert protocol.mesh_id_of(v + 1e-9, t) != m.mesh_id


def test_decode_mesh_rejects_bad_indices():
    msg = protocol.encode_mesh("s", np.zeros((3, 3)), np.array([[0, 1, 5]]), [])
    with pytest.raises(ProtocolError, match="out of range"):
        protocol.decode_mesh(msg)


def test_decode_force_frame_rejects_garbage():
    with pytest.raises(ProtocolError):
        protocol.decode_force_frame(b"\xff\xff\xff\xff")


def test_topics():
    assert protocol.force_topic("b0") == b"force.b0"
    assert protocol.status_topic("b0") == b"status.b0"


def test_parse_request_kinds():
    for kind in protocol.REQUESTS:
        got, _ = protocol.parse_request(protocol.make_request(kind).SerializeToString())
        assert got == kind


def test_make_request_rejects_unknown():
    with pytest.raises(ProtocolError, match="unknown request"):
        protocol.make_request("reboot")
    with pytest.raises(ProtocolError, match="unknown parameter"):
        protocol.make_request("set_params", nu=0.3)


def test_set_params_only_sends_given_fields():
    _, req = protocol.parse_request(
        protocol.make_request("set_params", k_f=0.4).SerializeToString()
    )
    assert protocol.params_dict(req.set_params) == {"k_f": 0.4}


def test_oversized_request_named():
    with pytest.raises(ProtocolError, match="too large"):
        protocol.parse_request(b"\x00" * (protocol.MAX_REQUEST_BYTES + 1))


def test_status_decode():
    msg = pb.Status(state=pb.Status.DEGRADED, reason="camera stalled", frames_dropped=4)
    msg.sources.add(name="cam", received=3, errors=1, last_error="x", age_s=0.5)
    s = protocol.decode_status(msg.SerializeToString())
    assert s.state == "degraded" and s.reason == "camera stalled" and s.frames_dropped == 4
    assert s.sources["cam"]["errors"] == 1


def test_client_imports_no_estimator():
    code = (
        "import sys, bubble_rt.io.client\n"
        "bad = [m for m in sys.modules if m.startswith(('bubble_rt._core', 'bubble_rt.estimation.estimator',"
        " 'bubble_rt.daemon.service', 'bubble_rt.daemon.sources', 'scipy', 'cv2'))]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def _frame_msg(patches=(), net_torque=None, node_displacements=None):
    n = 4
    return protocol.encode_force_frame(
        sensor_id="s",
        seq=0,
        frame_index=0,
        capture_time_ns=0,
        mesh_id="m",
        net_force=np.zeros(3),
        node_forces=np.zeros((n, 3)),
        normal_pressure=np.zeros(n),
        contact=np.zeros(n, bool),
        patches=patches,
        net_torque=net_torque,
        node_displacements=node_displacements,
    )


def test_wrench_and_patch_geometry_round_trip():
    patch = Patch(
        centroid=np.array([0.01, 0.0, 0.02]),
        area=1e-4,
        force=np.array([0.1, 0, -1.0]),
        nodes=np.array([1, 2]),
        normal=np.array([0.0, 0.6, 0.8]),
        peak_pressure=4321.5,
        torque=np.array([1e-4, -2e-4, 3e-5]),
        pressure_centroid=np.array([0.011, 0.001, 0.0199]),
    )
    tau = np.array([0.012, -0.034, 0.0005])
    u = np.arange(12.0).reshape(4, 3) * 1e-4
    f = protocol.decode_force_frame(_frame_msg([patch], tau, u).SerializeToString())
    np.testing.assert_array_equal(f.net_torque, tau)
    np.testing.assert_array_equal(f.node_displacements, u)
    (p,) = f.patches
    for name in ("centroid", "force", "normal", "torque", "pressure_centroid"):
        np.testing.assert_array_equal(getattr(p, name), getattr(patch, name))
    assert p.peak_pressure == 4321.5
    s = f.summary()
    assert s["net_torque"] == pytest.approx(tau.tolist())
    assert s["patches"][0]["peak_pressure"] == 4321.5
    assert s["patches"][0]["normal"] == pytest.approx([0.0, 0.6, 0.8])


def test_a_frame_without_the_wrench_fields_decodes_them_as_absent():
    old = Patch(centroid=np.zeros(3), area=1e-4, force=np.zeros(3), nodes=np.array([0]))
    f = protocol.decode_force_frame(_frame_msg([old]).SerializeToString())
    assert f.net_torque is None and f.summary()["net_torque"] is None
    assert f.node_displacements is None
    assert f.patches[0].normal.size == 0 and f.patches[0].torque.size == 0
    assert f.patches[0].peak_pressure == 0.0


def test_a_torque_of_the_wrong_size_is_refused():
    msg = _frame_msg(net_torque=np.zeros(2))
    with pytest.raises(ProtocolError, match="net_torque must hold 3 values"):
        protocol.decode_force_frame(msg.SerializeToString())


def test_displacements_of_the_wrong_size_are_refused():
    msg = _frame_msg(node_displacements=np.zeros(5))
    with pytest.raises(ProtocolError, match="node_displacements must hold 3 values per node"):
        protocol.decode_force_frame(msg.SerializeToString())
