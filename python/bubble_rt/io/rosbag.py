"""ROS 2 bags (rosbag2, MCAP or sqlite3 storage) in and out, with ``rosbags`` (no ROS needed).

Reading (:class:`BagRecording`, also reached through
:func:`bubble_rt.io.recordings.open_recording`): what TRI's punyo-bubble-kit records.

================  ==========================  ==============================================
role              message type                kit topic (pattern)
================  ==========================  ==============================================
``color``         sensor_msgs/Image           ``/bubble_N/color/image_rect_raw``; rgb8 or bgr8
``depth``         sensor_msgs/Image           ``.../aligned_depth_to_color/image_raw`` when
                                              present, else ``/bubble_N/depth/image_rect_raw``;
                                              16UC1 (``depth_unit`` metres per count, 1 mm
                                              per REP 118) or 32FC1 (metres)
``info``          sensor_msgs/CameraInfo      ``.../color/camera_info`` (k; d as plumb_bob)
``pressure``      std_msgs/Float32            ``/bubble_<id>/pressure``; absolute hPa, 100 Hz,
                                              no header
``wrench``        geometry_msgs/WrenchStamped optional ground truth (any topic)
``tf``            tf2_msgs/TFMessage          optional ``/tf_static``: a transform from
                                              ``bubble_rt_sensor`` to the camera's frame is
                                              the camera -> mesh pose
================  ==========================  ==============================================

Topics are found by message type and those name patterns. When a bag holds several sensors
(or no topic fits a role), :class:`BagTopicError` lists every candidate found; choose with
``topics`` (``"color=/a,depth=/b,info=/c,pressure=/d,wrench=/e"`` or a namespace such as
``"/bubble_2"``), which ``--topics`` on the command line passes through.

Frames: one per colour image that has a depth image with a header stamp within
``sync_tol_s`` (frames without depth are skipped and counted in ``skipped``). ``t`` is the
colour header stamp. The pressure has no header: its only clock is the bag's receive time,
and the firmware publishes the previous sample, so a reading received at ``r`` was sampled at
``r - pressure_delay_s`` (10 ms). The pressure of a frame is the linear interpolation of those
samples at ``t`` (the nearest sample is held outside their span; ``meta["pressure_age_s"]``
says how far). A wrench is the nearest WrenchStamped by header stamp.

Pose: without a ``/tf_static`` transform (see above), the Punyo layout's
:func:`~bubble_rt.io.punyo.punyo_pose`, refined in-plane from frame 0 like the Punyo
layout (the kit's sensor is the Punyo); ``pose=`` overrides.

Writing (:class:`BagWriter`, ``bubble-rt estimate RECORDING --bag OUT``): a rosbag2 (MCAP)
with, per estimated frame, on ``/bubble_rt/wrench`` a geometry_msgs/WrenchStamped (net force
on the membrane, N, in the sensor (mesh) frame ``bubble_rt_sensor``; torque about that
frame's origin, N m, as ForceFrame.net_torque: ``bubble_rt.wrench.net_torque``) and on
``/bubble_rt/nodes`` a sensor_msgs/PointCloud2 of the mesh nodes (frame ``bubble_rt_sensor``,
one point per node, all fields FLOAT32): x, y, z (node position, m, rest position plus the
measured displacement), fx, fy, fz (node contact force, N), pressure (normal contact pressure,
Pa, inward positive), contact (1.0 in contact, else 0.0). Both carry the frame's capture time
as header stamp and bag timestamp. :func:`write_bag` writes frames in the kit's layout
(fixtures, conversions).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt._validate import PathError, regular_file
from bubble_rt.camera import Camera
from bubble_rt.frames import HPA, Frame, FrameError

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
FLOAT32 = "std_msgs/msg/Float32"
WRENCH = "geometry_msgs/msg/WrenchStamped"
TF = "tf2_msgs/msg/TFMessage"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"

SENSOR_FRAME = "bubble_rt_sensor"
TOPIC_WRENCH = "/bubble_rt/wrench"
TOPIC_NODES = "/bubble_rt/nodes"
#: PointCloud2 fields written by :class:`BagWriter`, in order (all FLOAT32).
NODE_FIELDS = ("x", "y", "z", "fx", "fy", "fz", "pressure", "contact")
PRESSURE_DELAY_S = 0.010
ROLES = ("color", "depth", "info", "pressure", "wrench")


class BagTopicError(FrameError):
    """The bag's topics do not identify one sensor; the message lists what was found."""


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _stamp_s(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def is_rosbag(path: str | Path) -> bool:
    """True for a rosbag2 folder (metadata.yaml), a .db3 file, or an MCAP file with the ros2
    profile (this project's own MCAP recordings have another profile)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").exists()
    # is_file (not exists): a FIFO or device is never opened here (it would block).
    if p.suffix == ".db3":
        return p.is_file()
    if p.suffix == ".mcap" and p.is_file():
        try:
            from mcap.reader import make_reader

            with open(p, "rb") as fh:
                return make_reader(fh).get_header().profile == "ros2"
        except Exception:
            return False
    return False


def _bag_paths(path: Path) -> list[Path]:
    """What AnyReader opens: the bag folder (or the folder holding a lone .db3/.mcap file)."""
    if path.is_dir():
        return [path]
    if (path.parent / "metadata.yaml").exists():
        return [path.parent]
    return [path]


def _bag_files(path: Path) -> list[Path]:
    """The files of a bag that exist: metadata.yaml and the storage files (.db3, .mcap)."""
    if not path.is_dir():
        return [path]
    return sorted(
        f for f in path.iterdir() if f.name == "metadata.yaml" or f.suffix in (".db3", ".mcap")
    )


# ------------------------------------------------------------------------- topic choice
def parse_topics(spec: str | dict[str, str] | None) -> tuple[dict[str, str], str]:
    """(role -> topic, namespace) from ``"color=/a,depth=/b"`` / ``"/bubble_2"`` / a dict."""
    if spec is None or spec == "":
        return {}, ""
    if isinstance(spec, dict):
        return dict(spec), ""
    roles: dict[str, str] = {}
    ns = ""
    for part in (s.strip() for s in spec.split(",")):
        if not part:
            continue
        if "=" in part:
            k, v = (x.strip() for x in part.split("=", 1))
            if k not in ROLES:
                raise BagTopicError(f"--topics: unknown role {k!r}; roles are {', '.join(ROLES)}")
            roles[k] = v
        else:
            ns = part.rstrip("/")
    return roles, ns


def _rank(role: str, topic: str) -> int | None:
    """Pattern rank of a topic for a role (lower is better); None when it does not fit."""
    t = topic.lower()
    if role == "color":
        if "depth" in t or "infra" in t:
            return None
        return 0 if re.search(r"colou?r/image_(rect_)?raw$", t) else (1 if "colo" in t else 2)
    if role == "depth":
        if "aligned_depth_to_colo" in t:
            return 0
        if re.search(r"depth/image_(rect_)?raw$", t):
            return 1
        return 2 if "depth" in t else None
    if role == "info":
        if "depth" in t and "aligned_depth_to_colo" not in t:
            return 2
        return 0 if "colo" in t or "aligned_depth_to_colo" in t else 1
    if role == "pressure":
        return 0 if re.search(r"pressure$", t) else (1 if "pressure" in t else None)
    if role == "wrench":
        return 0
    return None


_ROLE_TYPES = {
    "color": IMAGE,
    "depth": IMAGE,
    "info": CAMERA_INFO,
    "pressure": FLOAT32,
    "wrench": WRENCH,
}


def choose_topics(
    found: dict[str, str], spec: str | dict[str, str] | None = None, path: str = "bag"
) -> dict[str, str]:
    """Role -> topic from ``found`` (topic -> message type); raises BagTopicError listing
    what the bag holds when a required role is missing or ambiguous."""
    given, ns = parse_topics(spec)
    chosen: dict[str, str] = {}
    problems: list[str] = []
    for role, typ in _ROLE_TYPES.items():
        if role in given:
            t = given[role]
            if t not in found:
                problems.append(f"{role}: topic {t!r} (from --topics) is not in the bag")
            elif found[t] != typ:
                problems.append(f"{role}: topic {t!r} is {found[t]}, expected {typ}")
            else:
                chosen[role] = t
            continue
        cands = [
            (r, t)
            for t, ty in found.items()
            if ty == typ
            and (not ns or t.startswith(ns + "/"))
            and (r := _rank(role, t)) is not None
            and t not in chosen.values()
        ]
        if not cands:
            if role != "wrench":
                problems.append(f"{role}: no {typ} topic" + (f" under {ns}" if ns else ""))
            continue
        best = min(r for r, _ in cands)
        tops = sorted(t for r, t in cands if r == best)
        if len(tops) > 1:
            problems.append(f"{role}: ambiguous, candidates {', '.join(tops)}")
            continue
        chosen[role] = tops[0]
    # One sensor: colour, depth, info and pressure share a namespace unless given explicitly.
    if not problems and not ns and not given:
        spaces = {_namespace(chosen[r]) for r in ("color", "depth", "pressure") if r in chosen}
        if len(spaces) > 1:
            problems.append(
                "the chosen colour/depth/pressure topics are in different namespaces "
                f"({', '.join(sorted(spaces))}); pick one sensor"
            )
    if problems:
        listing = "\n".join(f"  {t}  [{ty}]" for t, ty in sorted(found.items()))
        raise BagTopicError(
            f"{path}: cannot pick the sensor's topics:\n  - "
            + "\n  - ".join(problems)
            + f"\nthe bag holds:\n{listing}\n"
            "choose with --topics color=...,depth=...,info=...,pressure=...[,wrench=...] "
            "or a namespace, e.g. --topics /bubble_1"
        )
    return chosen


def _namespace(topic: str) -> str:
    parts = topic.strip("/").split("/")
    return "/" + parts[0] if len(parts) > 1 else "/"


# ------------------------------------------------------------------------- decoding
def image_to_array(msg: Any, depth_unit: float = 0.001) -> NDArray:
    """RGB uint8 (rgb8/bgr8/rgba8/bgra8/mono8) or depth float32 metres (16UC1/mono16, 32FC1)."""
    h, w, enc = int(msg.height), int(msg.width), str(msg.encoding).lower()
    data = np.asarray(msg.data, dtype=np.uint8)
    step = int(msg.step)
    big = bool(msg.is_bigendian)
    chans = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc3": 3}
    if enc in chans:
        c = chans[enc]
        a = data[: h * step].reshape(h, step)[:, : w * c].reshape(h, w, c)
        if enc in ("bgr8", "bgra8", "8uc3"):
            a = a[:, :, 2::-1] if c >= 3 else a
        elif c == 4:
            a = a[:, :, :3]
        if c == 1:
            a = np.repeat(a, 3, axis=2)
        return np.ascontiguousarray(a)
    if enc in ("16uc1", "mono16"):
        dt = np.dtype(">u2" if big else "<u2")
        raw = data[: h * step].reshape(h, step)[:, : w * 2].copy().view(dt).reshape(h, w)
        return raw.astype(np.float32) * np.float32(depth_unit)
    if enc == "32fc1":
        dtf = np.dtype(">f4" if big else "<f4")
        d = data[: h * step].reshape(h, step)[:, : w * 4].copy().view(dtf).reshape(h, w)
        d = d.astype(np.float32)
        return np.where(np.isfinite(d) & (d > 0), d, np.float32(0))
    raise FrameError(f"unsupported image encoding {msg.encoding!r}")


def camera_from_info(msg: Any) -> Camera:
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9 or k[0] <= 0 or k[4] <= 0:
        raise FrameError(f"camera_info: k is not a camera matrix ({k.tolist()})")
    d = [float(x) for x in np.asarray(msg.d, dtype=np.float64).reshape(-1)]
    model = str(msg.distortion_model or "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial", "") and any(d):
        raise FrameError(f"camera_info: distortion model {model!r} is not supported")
    dist = tuple((d + [0.0] * 5)[:5])
    return Camera(
        fx=float(k[0]),
        fy=float(k[4]),
        cx=float(k[2]),
        cy=float(k[5]),
        width=int(msg.width),
        height=int(msg.height),
        distortion=dist,  # type: ignore[arg-type]
    )


def _quat_matrix(q: Any) -> NDArray[np.float64]:
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    n = np.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _matrix_quat(R: NDArray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return float(x), float(y), float(z), float(w)


# ------------------------------------------------------------------------- reading
@dataclass
class _Index:
    """Where frame i's colour and depth messages are: counts of those topics' messages."""

    color: int
    depth: int
    t: float


class BagRecording:
    """A rosbag2 recording read as frames (see the module docstring).

    Attributes: ``path``, ``camera``, ``wrenches`` (n x 6 or None), ``topics`` (role ->
    topic), ``skipped`` (colour images without a matching depth image), ``layout`` "rosbag".
    Random access re-reads the bag from the start when going backwards; iterating is one pass.
    """

    layout = "rosbag"

    def __init__(
        self,
        path: str | Path,
        *,
        topics: str | dict[str, str] | None = None,
        depth_unit: float = 0.001,
        pressure_delay_s: float = PRESSURE_DELAY_S,
        sync_tol_s: float = 0.02,
        pose: NDArray[np.float64] | None = None,
        centre_from_data: bool = True,
    ) -> None:
        from rosbags.highlevel import AnyReader

        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"bag not found: {self.path}")
        for f in _bag_files(self.path):  # what rosbags opens: never a FIFO or a device
            try:
                regular_file("recording", f)
            except PathError as exc:
                raise FrameError(str(exc)) from None
        if not (np.isfinite(depth_unit) and depth_unit > 0):
            raise FrameError(f"depth unit must be positive metres per count, got {depth_unit}")
        self.depth_unit = float(depth_unit)
        self.pressure_delay_s = float(pressure_delay_s)
        self._paths = _bag_paths(self.path)
        self._ts = _typestore()
        try:
            reader = AnyReader(self._paths, default_typestore=self._ts)
            reader.open()
        except Exception as exc:
            raise FrameError(f"{self.path}: cannot open as a ROS 2 bag: {exc}") from exc
        try:
            found = {c.topic: c.msgtype for c in reader.connections}
            self.topics = choose_topics(found, topics, str(self.path))
            self._scan(reader, sync_tol_s)
        finally:
            reader.close()
        self.wrenches = (
            None
            if self._wrench is None
            else np.array([self._wrench_at(ix.t) for ix in self._index], dtype=np.float64)
        )
        camera = self._camera0
        tf_pose = self._tf_pose
        if pose is not None:
            camera = camera.with_pose(np.asarray(pose, dtype=np.float64))
            self.placement = "given pose"
        elif tf_pose is not None:
            camera = camera.with_pose(tf_pose)
            self.placement = f"/tf_static {SENSOR_FRAME}"
        else:
            from bubble_rt.io.punyo import punyo_pose

            camera = camera.with_pose(punyo_pose())
            self.placement = "punyo_pose"
        self.camera = camera
        self._cursor: tuple[Iterator[Frame], int] | None = None
        if pose is None and tf_pose is None and centre_from_data:
            from bubble_rt.estimation.fitting import centre_pose

            try:
                self.camera = centre_pose(camera, np.asarray(self._load(0).depth))
                self.placement = "centred"
            except FrameError as exc:
                self.placement += f" (not centred: {exc})"

    # ---------------------------------------------------------------- first pass
    def _scan(self, reader: Any, sync_tol_s: float) -> None:
        tp = self.topics
        want = {tp[r] for r in tp} | {c.topic for c in reader.connections if c.msgtype == TF}
        conns = [c for c in reader.connections if c.topic in want]
        color_t: list[float] = []
        depth_t: list[float] = []
        color_size: tuple[int, int] | None = None
        depth_size: tuple[int, int] | None = None
        encodings: dict[str, str] = {}
        info: Any = None
        p_t: list[float] = []
        p_v: list[float] = []
        w_t: list[float] = []
        w_v: list[list[float]] = []
        tf_msgs: list[Any] = []
        for conn, recv_ns, raw in reader.messages(connections=conns):
            topic = conn.topic
            if topic == tp["pressure"]:
                msg = reader.deserialize(raw, conn.msgtype)
                p_t.append(recv_ns * 1e-9 - self.pressure_delay_s)
                p_v.append(float(msg.data) * HPA)
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            if topic == tp["color"]:
                color_t.append(_stamp_s(msg.header))
                color_size = color_size or (int(msg.width), int(msg.height))
                encodings["color"] = str(msg.encoding)
            elif topic == tp["depth"]:
                depth_t.append(_stamp_s(msg.header))
                depth_size = depth_size or (int(msg.width), int(msg.height))
                encodings["depth"] = str(msg.encoding)
            elif topic == tp["info"]:
                info = info or msg
            elif topic == tp.get("wrench"):
                w_t.append(_stamp_s(msg.header))
                f, m = msg.wrench.force, msg.wrench.torque
                w_v.append([f.x, f.y, f.z, m.x, m.y, m.z])
            elif conn.msgtype == TF:
                tf_msgs.append(msg)
        where = str(self.path)
        missing = [
            name
            for name, seq in (
                (f"colour images on {tp['color']}", color_t),
                (f"depth images on {tp['depth']}", depth_t),
                (f"pressure readings on {tp['pressure']}", p_t),
            )
            if not seq
        ]
        if info is None:
            missing.append(f"camera_info on {tp['info']}")
        if missing:
            raise FrameError(f"{where}: no " + ", no ".join(missing))
        if color_size != depth_size:
            raise FrameError(
                f"{where}: colour {color_size[0]} x {color_size[1]} ({tp['color']}) and depth "  # type: ignore[index]
                f"{depth_size[0]} x {depth_size[1]} ({tp['depth']}) differ in size; record the "  # type: ignore[index]
                "depth aligned to colour (realsense-ros align_depth.enable:=true) or pass "
                "--topics depth=<aligned topic>"
            )
        for role in ("color", "depth"):
            enc = encodings[role].lower()
            ok: tuple[str, ...] = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8uc3")
            if role == "depth":
                ok = ("16uc1", "mono16", "32fc1")
            if enc not in ok:
                raise FrameError(f"{where}: {role} encoding {encodings[role]!r} not supported")
        self.depth_encoding = encodings["depth"]
        cam = camera_from_info(info)
        if (cam.width, cam.height) != color_size:
            raise FrameError(
                f"{where}: camera_info ({tp['info']}) is {cam.width} x {cam.height} but the "
                f"colour images are {color_size[0]} x {color_size[1]}"  # type: ignore[index]
            )
        self._camera0 = cam
        self._tf_pose = self._pose_from_tf(tf_msgs, str(info.header.frame_id))
        # Pair colour with the nearest depth image by header stamp.
        dt = np.asarray(depth_t)
        index: list[_Index] = []
        for i, t in enumerate(color_t):
            j = int(np.argmin(np.abs(dt - t)))
            if abs(dt[j] - t) <= sync_tol_s:
                index.append(_Index(color=i, depth=j, t=t))
        self.skipped = len(color_t) - len(index)
        if not index:
            raise FrameError(
                f"{where}: no colour image has a depth image within {sync_tol_s * 1e3:.0f} ms"
            )
        self._index = index
        order = np.argsort(p_t, kind="stable")
        self._p_t = np.asarray(p_t)[order]
        self._p_v = np.asarray(p_v)[order]
        self._wrench = (np.asarray(w_t), np.asarray(w_v)) if w_t else None

    def _pose_from_tf(self, msgs: list[Any], camera_frame: str) -> NDArray[np.float64] | None:
        for m in msgs:
            for tr in m.transforms:
                if tr.header.frame_id == SENSOR_FRAME and tr.child_frame_id == camera_frame:
                    T = np.eye(4)
                    T[:3, :3] = _quat_matrix(tr.transform.rotation)
                    v = tr.transform.translation
                    T[:3, 3] = [v.x, v.y, v.z]
                    return T
        return None

    def _wrench_at(self, t: float) -> NDArray[np.float64]:
        assert self._wrench is not None
        wt, wv = self._wrench
        return np.asarray(wv[int(np.argmin(np.abs(wt - t)))], dtype=np.float64)

    def pressure_at(self, t: float) -> tuple[float, float]:
        """(pressure Pa, age s) at time t from the receive-time-stamped readings."""
        ts, ps = self._p_t, self._p_v
        if t <= ts[0]:
            return float(ps[0]), float(ts[0] - t)
        if t >= ts[-1]:
            return float(ps[-1]), float(t - ts[-1])
        return float(np.interp(t, ts, ps)), 0.0

    # ---------------------------------------------------------------- frames
    def __len__(self) -> int:
        return len(self._index)

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError("recordings are indexed by int")
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range 0..{n - 1}")
        return self._load(int(i))

    def _load(self, i: int) -> Frame:
        if self._cursor is None or self._cursor[1] > i:
            if self._cursor is not None:
                self._cursor[0].close()  # type: ignore[attr-defined]
            self._cursor = (self._frames(), 0)
        it, pos = self._cursor
        while True:
            f = next(it)
            pos += 1
            self._cursor = (it, pos)
            if f.index == i:
                return f

    def __iter__(self) -> Iterator[Frame]:
        return self._frames()

    def _frames(self) -> Iterator[Frame]:
        from rosbags.highlevel import AnyReader

        tp = self.topics
        reader = AnyReader(self._paths, default_typestore=self._ts)
        reader.open()
        try:
            conns = [c for c in reader.connections if c.topic in (tp["color"], tp["depth"])]
            need_c = {ix.color: k for k, ix in enumerate(self._index)}
            need_d: dict[int, list[int]] = {}
            for k, ix in enumerate(self._index):
                need_d.setdefault(ix.depth, []).append(k)
            rgb: dict[int, NDArray] = {}
            depth: dict[int, NDArray] = {}
            nc = nd = 0
            nxt = 0
            for conn, _, raw in reader.messages(connections=conns):
                if conn.topic == tp["color"]:
                    if nc in need_c:
                        msg = reader.deserialize(raw, conn.msgtype)
                        rgb[need_c[nc]] = image_to_array(msg)
                    nc += 1
                else:
                    if nd in need_d:
                        msg = reader.deserialize(raw, conn.msgtype)
                        d = image_to_array(msg, self.depth_unit)
                        for k in need_d[nd]:
                            depth[k] = d
                    nd += 1
                while nxt in rgb and nxt in depth:
                    yield self._frame(nxt, rgb.pop(nxt), depth.pop(nxt))
                    nxt += 1
                # Depth kept for frames already emitted is dropped; stale entries cannot grow.
                for k in [k for k in depth if k < nxt]:
                    del depth[k]
        finally:
            try:
                reader.close()
            except Exception:  # e.g. a generator collected at interpreter shutdown
                pass

    def _frame(self, k: int, rgb: NDArray, depth: NDArray) -> Frame:
        t = self._index[k].t
        p, age = self.pressure_at(t)
        return Frame(
            rgb=rgb,
            depth=depth,
            pressure_pa=p,
            t=t,
            t_pressure=t,
            wrench=None if self.wrenches is None else self.wrenches[k],
            index=k,
            meta={"source": str(self.path), "pressure_age_s": age},
        ).validate(self.camera)

    def __repr__(self) -> str:
        return f"BagRecording({str(self.path)!r}, frames={len(self)}, topics={self.topics})"


# ------------------------------------------------------------------------- writing
def _header(ts: Any, t: float, frame_id: str) -> Any:
    ns = int(round(t * 1e9))
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    return Header(
        stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id
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
        self.ts = _typestore()
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
        header = _header(ts, t, self.frame_id)
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
    camera_info: bool = True,
    pressure: bool = True,
    depth_size: tuple[int, int] | None = None,
) -> Path:
    """Write frames the way punyo-bubble-kit records them (fixtures, conversions).

    Colour/depth/camera_info stamped at ``frame.t``; pressure as headerless Float32 hPa at
    ``pressure_hz`` over the frames' span, each reading (the frames' pressure, linearly
    interpolated in time, as float32) received ``pressure_delay_s`` after it was sampled;
    a WrenchStamped per frame when ``wrench`` and the frames carry one. ``tf`` adds a
    ``/tf_static`` with the camera pose; ``aligned`` names depth ``aligned_depth_to_color``.
    ``camera_info``/``pressure`` False and ``depth_size`` exist to write broken bags in tests.
    A bag's clock cannot go below 0 and the pressure stream starts ``PRESSURE_LEAD_S`` before
    the first frame: earlier frames (the simulator stamps its reference frames before 0) are
    all shifted so that the earliest is at ``PRESSURE_LEAD_S``.
    """
    shift = PRESSURE_LEAD_S - min((f.t for f in frames), default=PRESSURE_LEAD_S)
    if shift > 0:
        frames = [
            dataclasses.replace(
                f, t=f.t + shift, t_pressure=None if f.t_pressure is None else f.t_pressure + shift
            )
            for f in frames
        ]
    bag = _Bag(path, storage)
    ts = bag.ts
    ns_ = f"/{sensor}"
    t_color = f"{ns_}/color/image_rect_raw"
    t_depth = (
        f"{ns_}/aligned_depth_to_color/image_raw" if aligned else f"{ns_}/depth/image_rect_raw"
    )
    t_info = f"{ns_}/color/camera_info"
    cam_frame = f"{sensor}_color_optical_frame"
    Image = ts.types[IMAGE]
    try:
        if tf:
            P = camera.pose_matrix
            q = _matrix_quat(P[:3, :3])
            T = ts.types["geometry_msgs/msg/Transform"](
                translation=ts.types["geometry_msgs/msg/Vector3"](
                    x=float(P[0, 3]), y=float(P[1, 3]), z=float(P[2, 3])
                ),
                rotation=ts.types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            )
            t0 = frames[0].t if frames else 0.0
            tfm = ts.types[TF](
                transforms=[
                    ts.types["geometry_msgs/msg/TransformStamped"](
                        header=_header(ts, t0, SENSOR_FRAME), child_frame_id=cam_frame, transform=T
                    )
                ]
            )
            bag.write("/tf_static", TF, tfm, int(round(t0 * 1e9)))
        for f in frames:
            if f.rgb is None or f.depth is None:
                raise FrameError(f"frame {f.index}: rgb and depth are needed for a bag")
            ns = int(round(f.t * 1e9))
            hdr = _header(ts, f.t, cam_frame)
            rgb = np.ascontiguousarray(f.rgb if color_encoding == "rgb8" else f.rgb[:, :, ::-1])
            h, w = rgb.shape[:2]
            bag.write(
                t_color,
                IMAGE,
                Image(
                    header=hdr,
                    height=h,
                    width=w,
                    encoding=color_encoding,
                    is_bigendian=0,
                    step=3 * w,
                    data=rgb.reshape(-1),
                ),
                ns,
            )
            d: Any = np.asarray(f.depth, dtype=np.float32)
            if depth_size is not None:
                import cv2

                d = cv2.resize(d, depth_size, interpolation=cv2.INTER_NEAREST)
            dh, dw = d.shape
            if depth_encoding.upper() == "16UC1":
                raw = np.clip(np.rint(d / depth_unit), 0, 65535).astype("<u2")
                dmsg = Image(
                    header=hdr,
                    height=dh,
                    width=dw,
                    encoding="16UC1",
                    is_bigendian=0,
                    step=2 * dw,
                    data=raw.view(np.uint8).reshape(-1),
                )
            elif depth_encoding.upper() == "32FC1":
                raw32 = d.astype("<f4")
                dmsg = Image(
                    header=hdr,
                    height=dh,
                    width=dw,
                    encoding="32FC1",
                    is_bigendian=0,
                    step=4 * dw,
                    data=raw32.view(np.uint8).reshape(-1),
                )
            else:
                raise ValueError(f"depth encoding {depth_encoding!r}: use 16UC1 or 32FC1")
            bag.write(t_depth, IMAGE, dmsg, ns)
            if camera_info:
                k = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
                p = [
                    camera.fx,
                    0.0,
                    camera.cx,
                    0.0,
                    0.0,
                    camera.fy,
                    camera.cy,
                    0.0,
                    0.0,
                    0.0,
                    1.0,
                    0.0,
                ]
                RoI = ts.types["sensor_msgs/msg/RegionOfInterest"]
                info = ts.types[CAMERA_INFO](
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
                bag.write(t_info, CAMERA_INFO, info, ns)
            if wrench and f.wrench is not None:
                V3 = ts.types["geometry_msgs/msg/Vector3"]
                wv = [float(x) for x in f.wrench]
                bag.write(
                    "/ft_sensor/wrench",
                    WRENCH,
                    ts.types[WRENCH](
                        header=_header(ts, f.t, "ft_sensor"),
                        wrench=ts.types["geometry_msgs/msg/Wrench"](
                            force=V3(x=wv[0], y=wv[1], z=wv[2]),
                            torque=V3(x=wv[3], y=wv[4], z=wv[5]),
                        ),
                    ),
                    ns,
                )
        if pressure and frames:
            t_s = np.arange(
                frames[0].t - PRESSURE_LEAD_S, frames[-1].t + PRESSURE_LEAD_S, 1.0 / pressure_hz
            )
            F32 = ts.types[FLOAT32]
            for t in t_s:
                hpa = np.float32(_pressure_curve(frames, t) / HPA)
                bag.write(
                    f"{ns_}/pressure",
                    FLOAT32,
                    F32(data=hpa),
                    int(round((t + pressure_delay_s) * 1e9)),
                )
    finally:
        bag.close()
    return bag.path


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
