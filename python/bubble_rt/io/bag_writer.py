"""Writing ROS 2 bags: estimator results (:class:`BagWriter`: a WrenchStamped and a node
PointCloud2 per frame) and frames the way the Punyo kit records them (:func:`write_bag`, for
fixtures and conversions)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.frames import HPA, Frame, FrameError
from bubble_rt.io.bag_messages import (
    CAMERA_INFO,
    FLOAT32,
    IMAGE,
    NODE_FIELDS,
    POINTCLOUD2,
    PRESSURE_DELAY_S,
    SENSOR_FRAME,
    TF,
    TOPIC_NODES,
    TOPIC_WRENCH,
    WRENCH,
    matrix_quat,
    stamped_header,
    typestore,
)


def _storage(storage: str) -> Any:
    from rosbags.rosbag2 import StoragePlugin

    try:
        return {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    except KeyError:
        raise ValueError(f"storage must be 'mcap' or 'sqlite3', got {storage!r}") from None


class _Bag:
    """A rosbags Writer with lazily added connections."""

    def __init__(self, path: str | Path, storage: str = "mcap") -> None:
        from rosbags.rosbag2 import Writer

        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists (rosbag2 writes a new folder)")
        self.ts = typestore()
        self._w = Writer(self.path, version=9, storage_plugin=_storage(storage))
        self._w.open()
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def write(self, topic: str, msgtype: str, msg: Any, t_ns: int) -> None:
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._w.add_connection(topic, msgtype, typestore=self.ts)
            self._conns[topic] = conn
        self._w.write(conn, int(t_ns), self.ts.serialize_cdr(msg, msgtype))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        self._w.close()


def node_cloud_fields() -> list[tuple[str, int]]:
    """(name, byte offset) of the PointCloud2 fields :class:`BagWriter` writes."""
    return [(n, 4 * i) for i, n in enumerate(NODE_FIELDS)]


class BagWriter:
    """Estimator results as a rosbag2 (see the module docstring for topics and fields)."""

    def __init__(self, path: str | Path, storage: str = "mcap", frame_id: str = SENSOR_FRAME):
        self._bag = _Bag(path, storage)
        self.path = self._bag.path
        self.frame_id = frame_id

    @property
    def counts(self) -> dict[str, int]:
        return self._bag.counts

    def write(
        self,
        t: float,
        net_force: NDArray,
        positions: NDArray,
        node_forces: NDArray,
        normal_pressure: NDArray,
        contact: NDArray,
        net_torque: NDArray | None = None,
    ) -> None:
        """One frame: ``net_torque`` (3,) N m about the sensor frame's origin (None: 0)."""
        ts = self._bag.ts
        ns = int(round(t * 1e9))
        header = stamped_header(ts, t, self.frame_id)
        V3 = ts.types["geometry_msgs/msg/Vector3"]
        f = np.asarray(net_force, dtype=np.float64).reshape(3)
        tau = np.zeros(3) if net_torque is None else np.asarray(net_torque, np.float64).reshape(3)
        wrench = ts.types[WRENCH](
            header=header,
            wrench=ts.types["geometry_msgs/msg/Wrench"](
                force=V3(x=float(f[0]), y=float(f[1]), z=float(f[2])),
                torque=V3(x=float(tau[0]), y=float(tau[1]), z=float(tau[2])),
            ),
        )
        self._bag.write(TOPIC_WRENCH, WRENCH, wrench, ns)
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        n = pos.shape[0]
        table = np.column_stack(
            [
                pos,
                np.asarray(node_forces, dtype=np.float64).reshape(n, 3),
                np.asarray(normal_pressure, dtype=np.float64).reshape(n),
                np.asarray(contact, dtype=bool).reshape(n).astype(np.float64),
            ]
        ).astype("<f4")
        PF = ts.types["sensor_msgs/msg/PointField"]
        fields = [
            PF(name=nm, offset=off, datatype=PF.FLOAT32, count=1) for nm, off in node_cloud_fields()
        ]
        step = 4 * len(NODE_FIELDS)
        cloud = ts.types[POINTCLOUD2](
            header=header,
            height=1,
            width=n,
            fields=fields,
            is_bigendian=False,
            point_step=step,
            row_step=step * n,
            data=np.frombuffer(table.tobytes(), dtype=np.uint8),
            is_dense=True,
        )
        self._bag.write(TOPIC_NODES, POINTCLOUD2, cloud, ns)

    def close(self) -> None:
        self._bag.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def read_node_cloud(msg: Any) -> dict[str, NDArray]:
    """Field name -> values of a PointCloud2 (FLOAT32 fields), e.g. from :class:`BagWriter`."""
    n = int(msg.width) * int(msg.height)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(n, int(msg.point_step))
    out = {}
    for f in msg.fields:
        if int(f.datatype) != 7:
            raise ValueError(f"field {f.name}: only FLOAT32 is read here")
        out[str(f.name)] = data[:, f.offset : f.offset + 4].copy().view("<f4").reshape(n)
    return out


#: write_bag's pressure stream starts this long before the first frame and ends after the last.
PRESSURE_LEAD_S = 0.05


def write_bag(
    path: str | Path,
    frames: Sequence[Frame],
    camera: Camera,
    *,
    storage: str = "mcap",
    sensor: str = "bubble_1",
    depth_encoding: str = "16UC1",
    color_encoding: str = "rgb8",
    depth_unit: float = 0.001,
    pressure_hz: float = 100.0,
    pressure_delay_s: float = PRESSURE_DELAY_S,
    wrench: bool = True,
    aligned: bool = False,
    tf: bool = False,
) -> Path:
    """Write frames the way punyo-bubble-kit records them (fixtures, conversions).

    Colour/depth/camera_info stamped at ``frame.t``; pressure as headerless Float32 hPa at
    ``pressure_hz`` over the frames' span, each reading (the frames' pressure, linearly
    interpolated in time, as float32) received ``pressure_delay_s`` after it was sampled;
    a WrenchStamped per frame when ``wrench`` and the frames carry one. ``tf`` adds a
    ``/tf_static`` with the camera pose; ``aligned`` names depth ``aligned_depth_to_color``.
    A bag's clock cannot go below 0 and the pressure stream starts ``PRESSURE_LEAD_S`` before
    the first frame: earlier frames (the simulator stamps its reference frames before 0) are
    all shifted so that the earliest is at ``PRESSURE_LEAD_S``.
    """
    if depth_encoding.upper() not in ("16UC1", "32FC1"):
        raise ValueError(f"depth encoding {depth_encoding!r}: use 16UC1 or 32FC1")
    frames = _from_time_zero(frames)
    bag = _Bag(path, storage)
    ts = bag.ts
    ns_ = f"/{sensor}"
    depth_topic = "aligned_depth_to_color/image_raw" if aligned else "depth/image_rect_raw"
    cam_frame = f"{sensor}_color_optical_frame"
    try:
        if tf:
            t0 = frames[0].t if frames else 0.0
            bag.write("/tf_static", TF, _tf_static(ts, camera, t0, cam_frame), _ns(t0))
        for f in frames:
            if f.rgb is None or f.depth is None:
                raise FrameError(f"frame {f.index}: rgb and depth are needed for a bag")
            hdr = stamped_header(ts, f.t, cam_frame)
            rgb = f.rgb if color_encoding == "rgb8" else f.rgb[:, :, ::-1]
            bag.write(
                f"{ns_}/color/image_rect_raw", IMAGE, _image(ts, hdr, rgb, color_encoding), _ns(f.t)
            )
            dmsg = _depth_image(ts, hdr, f.depth, depth_encoding.upper(), depth_unit)
            bag.write(f"{ns_}/{depth_topic}", IMAGE, dmsg, _ns(f.t))
            # camera_info, one per frame as realsense-ros publishes it
            bag.write(
                f"{ns_}/color/camera_info", CAMERA_INFO, _camera_info(ts, hdr, camera), _ns(f.t)
            )
            if wrench and f.wrench is not None:
                bag.write("/ft_sensor/wrench", WRENCH, _wrench(ts, f.t, f.wrench), _ns(f.t))
        F32 = ts.types[FLOAT32]
        for t in _pressure_times(frames, pressure_hz):
            hpa = np.float32(_pressure_curve(frames, t) / HPA)
            bag.write(f"{ns_}/pressure", FLOAT32, F32(data=hpa), _ns(t + pressure_delay_s))
    finally:
        bag.close()
    return bag.path


def _ns(t: float) -> int:
    return int(round(t * 1e9))


def _from_time_zero(frames: Sequence[Frame]) -> Sequence[Frame]:
    """The frames shifted so that the earliest is at ``PRESSURE_LEAD_S`` or later (a bag's
    clock cannot go below 0, and the pressure stream starts that long before)."""
    shift = PRESSURE_LEAD_S - min((f.t for f in frames), default=PRESSURE_LEAD_S)
    if shift <= 0:
        return frames
    return [
        dataclasses.replace(
            f, t=f.t + shift, t_pressure=None if f.t_pressure is None else f.t_pressure + shift
        )
        for f in frames
    ]


def _tf_static(ts: Any, camera: Camera, t0: float, cam_frame: str) -> Any:
    """A TFMessage with the camera pose: sensor frame -> camera optical frame."""
    P = camera.pose_matrix
    q = matrix_quat(P[:3, :3])
    V3, Q = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
    T = ts.types["geometry_msgs/msg/Transform"](
        translation=V3(x=float(P[0, 3]), y=float(P[1, 3]), z=float(P[2, 3])),
        rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    stamped = ts.types["geometry_msgs/msg/TransformStamped"](
        header=stamped_header(ts, t0, SENSOR_FRAME), child_frame_id=cam_frame, transform=T
    )
    return ts.types[TF](transforms=[stamped])


def _image(ts: Any, hdr: Any, rgb: NDArray, encoding: str) -> Any:
    """An H x W x 3 uint8 colour image as sensor_msgs/Image."""
    rgb = np.ascontiguousarray(rgb)
    h, w = rgb.shape[:2]
    return ts.types[IMAGE](
        header=hdr, height=h, width=w, encoding=encoding, is_bigendian=0, step=3 * w,
        data=rgb.reshape(-1),
    )  # fmt: skip


def _depth_image(ts: Any, hdr: Any, depth: NDArray, encoding: str, unit: float) -> Any:
    """Depth (H x W, m) as sensor_msgs/Image: 16UC1 in counts of ``unit`` m, or 32FC1 in m."""
    d = np.asarray(depth, dtype=np.float32)
    if encoding == "16UC1":
        raw: NDArray = np.clip(np.rint(d / unit), 0, 65535).astype("<u2")
    else:
        raw = d.astype("<f4")
    dh, dw = d.shape
    return ts.types[IMAGE](
        header=hdr, height=dh, width=dw, encoding=encoding, is_bigendian=0,
        step=raw.itemsize * dw, data=raw.view(np.uint8).reshape(-1),
    )  # fmt: skip


def _camera_info(ts: Any, hdr: Any, camera: Camera) -> Any:
    """The camera's intrinsics and distortion as sensor_msgs/CameraInfo (plumb_bob)."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    p = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    RoI = ts.types["sensor_msgs/msg/RegionOfInterest"]
    return ts.types[CAMERA_INFO](
        header=hdr,
        height=camera.height,
        width=camera.width,
        distortion_model="plumb_bob",
        d=np.asarray(camera.distortion, dtype=np.float64),
        k=np.asarray(k, dtype=np.float64),
        r=np.eye(3).reshape(-1),
        p=np.asarray(p, dtype=np.float64),
        binning_x=0,
        binning_y=0,
        roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def _wrench(ts: Any, t: float, wrench: NDArray) -> Any:
    """A force/torque reading (6,) as geometry_msgs/WrenchStamped in frame ft_sensor."""
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    wv = [float(x) for x in wrench]
    return ts.types[WRENCH](
        header=stamped_header(ts, t, "ft_sensor"),
        wrench=ts.types["geometry_msgs/msg/Wrench"](
            force=V3(x=wv[0], y=wv[1], z=wv[2]), torque=V3(x=wv[3], y=wv[4], z=wv[5])
        ),
    )


def _pressure_times(frames: Sequence[Frame], hz: float) -> NDArray[np.float64]:
    """Sample times (s) of the pressure stream: from ``PRESSURE_LEAD_S`` before the first
    frame to as long after the last, at ``hz``."""
    if not frames:
        return np.zeros(0)
    return np.arange(frames[0].t - PRESSURE_LEAD_S, frames[-1].t + PRESSURE_LEAD_S, 1.0 / hz)


def _pressure_curve(frames: Sequence[Frame], t: float) -> float:
    """The frames' pressure (Pa) at time t: linear between frames, extended linearly past
    the ends (so a pressure ramp stays a ramp)."""
    ft = np.array([f.t for f in frames])
    fp = np.array([f.pressure_pa for f in frames])
    if len(ft) < 2:
        return float(fp[0])
    if t < ft[0]:
        return float(fp[0] + (t - ft[0]) * (fp[1] - fp[0]) / (ft[1] - ft[0]))
    if t > ft[-1]:
        return float(fp[-1] + (t - ft[-1]) * (fp[-1] - fp[-2]) / (ft[-1] - ft[-2]))
    return float(np.interp(t, ft, fp))
