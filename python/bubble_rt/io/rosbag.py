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
(or no topic fits a role), :class:`~bubble_rt.io.bag_topics.BagTopicError` lists every candidate found; choose with
``topics`` (``"color=/a,depth=/b,info=/c,pressure=/d,wrench=/e"`` or a namespace such as
``"/bubble_2"``), which ``--topics`` on the command line passes through.

Frames: one per colour image that has a depth image with a header stamp within
``sync_tol_s`` (frames without depth are skipped and counted in ``skipped``). ``t`` is the
colour header stamp. The pressure has no header: its only clock is the bag's receive time,
and the firmware publishes the previous sample, so a reading received at ``r`` was sampled at
``r - pressure_delay_s`` (10 ms). The pressure of a frame is the linear interpolation of those
samples at ``t`` (the nearest sample is held outside their span; ``meta["pressure_age_s"]``
says how far). A wrench is the nearest WrenchStamped by header stamp.

Bad data: a frame whose image cannot be decoded (cut short, a wrong row step, an encoding or
size that changed mid-bag) or has no valid depth becomes a
:class:`~bubble_rt.frames.FrameFault` in :meth:`BagRecording.frames` (the same tolerant
iteration as every layout, :func:`bubble_rt.frames.tolerant`); a non-finite pressure reading
is dropped at opening and named in ``reading_faults``. A bag cut short is read up to the cut
(:mod:`bubble_rt.io.bag_recover`; ``lost`` says what was lost). The Punyo kit's pressure
topic lives in its own namespace: see :func:`bubble_rt.io.bag_topics.choose_topics`.

Pose: without a ``/tf_static`` transform (see above), the Punyo layout's
:func:`~bubble_rt.io.punyo.punyo_pose`, refined in-plane from frame 0 like the Punyo
layout (the kit's sensor is the Punyo); ``pose=`` overrides.

Writing (:mod:`bubble_rt.io.bag_writer`: :class:`BagWriter`, ``bubble-rt estimate RECORDING --bag OUT``): a rosbag2 (MCAP)
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

from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt._validate import PathError, regular_file
from bubble_rt.frames import HPA, Frame, FrameError, FrameFault, tolerant
from bubble_rt.io.bag_messages import (
    PRESSURE_DELAY_S,
    SENSOR_FRAME,
    TF,
    camera_from_info,
    decode_image,
    quat_matrix,
    stamp_s,
    typestore,
)
from bubble_rt.io.bag_topics import choose_topics


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


#: Image encodings read, per role (lower case).
_ENCODINGS: dict[str, tuple[str, ...]] = {
    "color": ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8uc3"),
    "depth": ("16uc1", "mono16", "32fc1"),
}


@dataclass
class _Scanned:
    """What the first pass over a bag collects (times in seconds, pressures in Pa)."""

    color_t: list[float] = field(default_factory=list)
    depth_t: list[float] = field(default_factory=list)
    # (width, height) and encoding of each role's first image: a later change makes those
    # frames bad ones (skipped and named), not the whole bag.
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    encodings: dict[str, str] = field(default_factory=dict)
    info: Any = None
    p_t: list[float] = field(default_factory=list)
    p_v: list[float] = field(default_factory=list)
    n_pressure: int = 0
    w_t: list[float] = field(default_factory=list)
    w_v: list[list[float]] = field(default_factory=list)
    tf_msgs: list[Any] = field(default_factory=list)

    def add(self, topics: dict[str, str], conn: Any, msg: Any) -> None:
        """One message of a role other than pressure."""
        topic = conn.topic
        for role, times in (("color", self.color_t), ("depth", self.depth_t)):
            if topic == topics[role]:
                times.append(stamp_s(msg.header))
                self.sizes.setdefault(role, (int(msg.width), int(msg.height)))
                self.encodings.setdefault(role, str(msg.encoding))
                return
        if topic == topics["info"]:
            self.info = self.info or msg
        elif topic == topics.get("wrench"):
            self.w_t.append(stamp_s(msg.header))
            f, m = msg.wrench.force, msg.wrench.torque
            self.w_v.append([f.x, f.y, f.z, m.x, m.y, m.z])
        elif conn.msgtype == TF:
            self.tf_msgs.append(msg)


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
        #: Pressure readings skipped (not finite), named: frames use the other readings.
        self.reading_faults: list[FrameFault] = []
        self.depth_unit = float(depth_unit)
        self.pressure_delay_s = float(pressure_delay_s)
        self._paths = _bag_paths(self.path)
        self._ts = typestore()
        #: What a cut or damaged bag lost ("" when it was read whole).
        self.lost = ""
        try:
            reader = AnyReader(self._paths, default_typestore=self._ts)
            reader.open()
        except Exception as exc:
            reader = self._recovered(exc)
        try:
            found = {c.topic: c.msgtype for c in reader.connections}
            notes: list[str] = []
            self.topics = choose_topics(found, topics, str(self.path), notes)
            #: How the topics were paired when that is worth saying ("" otherwise).
            self.topics_note = "; ".join(notes)
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
        self._cursor: tuple[Iterator[Frame | FrameFault], int] | None = None
        if pose is None and tf_pose is None and centre_from_data:
            from bubble_rt.estimation.fitting import centre_pose

            try:
                self.camera = centre_pose(camera, np.asarray(self._load(0).depth))
                self.placement = "centred"
            except FrameError as exc:
                self.placement += f" (not centred: {exc})"

    def _recovered(self, exc: Exception) -> Any:
        """An open reader of what is readable of a cut bag (:mod:`bubble_rt.io.bag_recover`,
        in a temporary folder removed with this object); ``lost`` says what was lost."""
        import shutil
        import tempfile
        import weakref

        from rosbags.highlevel import AnyReader

        from bubble_rt.io.bag_recover import readable_copy

        cannot = f"{self.path}: cannot open as a ROS 2 bag: {exc}"
        tmp = Path(tempfile.mkdtemp(prefix="bubble_rt_bag_"))
        weakref.finalize(self, shutil.rmtree, tmp, True)
        try:
            self._paths, lost = readable_copy(_bag_files(self.path), tmp)
            reader = AnyReader(self._paths, default_typestore=self._ts)
            reader.open()
        except Exception as exc2:
            raise FrameError(f"{cannot} (and no readable part: {exc2})") from exc
        self.lost = lost.replace(str(tmp), str(self.path))
        if not any(c.msgcount for c in reader.connections):
            reader.close()
            raise FrameError(f"{cannot}; nothing before the cut is readable ({self.lost})")
        return reader

    # ---------------------------------------------------------------- first pass
    def _scan(self, reader: Any, sync_tol_s: float) -> None:
        """One pass over the messages: timestamps, sizes and encodings of the images, the
        camera info, the pressure and wrench series, /tf_static; checked, then colour paired
        with depth."""
        tp = self.topics
        want = {tp[r] for r in tp} | {c.topic for c in reader.connections if c.msgtype == TF}
        conns = [c for c in reader.connections if c.topic in want]
        sc = _Scanned()
        for conn, recv_ns, raw in reader.messages(connections=conns):
            if conn.topic == tp["pressure"]:
                self._pressure_reading(sc, reader.deserialize(raw, conn.msgtype), recv_ns)
            else:
                sc.add(tp, conn, reader.deserialize(raw, conn.msgtype))
        self._check(sc)
        self.depth_encoding = sc.encodings["depth"]
        self._camera0 = camera_from_info(sc.info)
        self._tf_pose = self._pose_from_tf(sc.tf_msgs, str(sc.info.header.frame_id))
        self._index = self._pair(sc, sync_tol_s)
        order = np.argsort(sc.p_t, kind="stable")
        self._p_t = np.asarray(sc.p_t)[order]
        self._p_v = np.asarray(sc.p_v)[order]
        self._wrench = (np.asarray(sc.w_t), np.asarray(sc.w_v)) if sc.w_t else None

    def _pressure_reading(self, sc: _Scanned, msg: Any, recv_ns: int) -> None:
        """A pressure reading (hPa, no header: sampled ``pressure_delay_s`` before it was
        received); a non-finite one is skipped and named, the frames use the others."""
        k = sc.n_pressure
        sc.n_pressure += 1
        hpa = float(msg.data)
        if not np.isfinite(hpa):
            where = f"{self.path.name} {self.topics['pressure']} reading {k}"
            reason = f"pressure reading is not finite: {hpa}"
            self.reading_faults.append(FrameFault(k, where, reason, "pressure", reading=True))
            return
        sc.p_t.append(recv_ns * 1e-9 - self.pressure_delay_s)
        sc.p_v.append(hpa * HPA)

    def _check(self, sc: _Scanned) -> None:
        """Every role present, colour and depth of one size, supported encodings, and a
        camera_info that matches the images; FrameError says what is wrong."""
        tp, where = self.topics, str(self.path)
        missing = [
            name
            for name, seq in (
                (f"colour images on {tp['color']}", sc.color_t),
                (f"depth images on {tp['depth']}", sc.depth_t),
                (f"pressure readings on {tp['pressure']}", sc.p_t),
            )
            if not seq
        ]
        if sc.info is None:
            missing.append(f"camera_info on {tp['info']}")
        if missing:
            bad = f" ({len(self.reading_faults)} not finite)" if self.reading_faults else ""
            raise FrameError(f"{where}: no " + ", no ".join(missing) + (bad if not sc.p_t else ""))
        cw, ch = sc.sizes["color"]
        if sc.sizes["color"] != sc.sizes["depth"]:
            dw, dh = sc.sizes["depth"]
            raise FrameError(
                f"{where}: colour {cw} x {ch} ({tp['color']}) and depth {dw} x {dh} "
                f"({tp['depth']}) differ in size; record the depth aligned to colour "
                "(realsense-ros align_depth.enable:=true) or pass --topics depth=<aligned topic>"
            )
        for role, ok in _ENCODINGS.items():
            if sc.encodings[role].lower() not in ok:
                raise FrameError(f"{where}: {role} encoding {sc.encodings[role]!r} not supported")
        cam = camera_from_info(sc.info)
        if (cam.width, cam.height) != (cw, ch):
            raise FrameError(
                f"{where}: camera_info ({tp['info']}) is {cam.width} x {cam.height} but the "
                f"colour images are {cw} x {ch}"
            )

    def _pair(self, sc: _Scanned, sync_tol_s: float) -> list[_Index]:
        """Colour images paired with the nearest depth image by header stamp (within
        ``sync_tol_s``); the unpaired are counted in ``skipped``."""
        dt = np.asarray(sc.depth_t)
        index: list[_Index] = []
        for i, t in enumerate(sc.color_t):
            j = int(np.argmin(np.abs(dt - t)))
            if abs(dt[j] - t) <= sync_tol_s:
                index.append(_Index(color=i, depth=j, t=t))
        self.skipped = len(sc.color_t) - len(index)
        if not index:
            raise FrameError(
                f"{self.path}: no colour image has a depth image within {sync_tol_s * 1e3:.0f} ms"
            )
        return index

    def _pose_from_tf(self, msgs: list[Any], camera_frame: str) -> NDArray[np.float64] | None:
        for m in msgs:
            for tr in m.transforms:
                if tr.header.frame_id == SENSOR_FRAME and tr.child_frame_id == camera_frame:
                    T = np.eye(4)
                    T[:3, :3] = quat_matrix(tr.transform.rotation)
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
                if isinstance(f, FrameFault):
                    raise FrameError(str(f), f.kind)
                return f

    def __iter__(self) -> Iterator[Frame]:
        return (f for f in self._frames() if isinstance(f, Frame))

    def frames(self, faults: bool = True) -> Iterator[Frame | FrameFault]:
        """Frames in order; with ``faults`` a FrameFault stands in for each bad one (image
        cut short, wrong row step or encoding, no valid depth, size change, ...)."""
        return (f for f in self._frames() if faults or isinstance(f, Frame))

    def _frames(self) -> Iterator[Frame | FrameFault]:
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
            # Decoded images, or the exception decoding raised (the frame becomes a fault).
            rgb: dict[int, Any] = {}
            depth: dict[int, Any] = {}
            nc = nd = 0
            nxt = 0
            for conn, _, raw in reader.messages(connections=conns):
                if conn.topic == tp["color"]:
                    if nc in need_c:
                        rgb[need_c[nc]] = decode_image(reader, raw, conn.msgtype, None)
                    nc += 1
                else:
                    if nd in need_d:
                        d = decode_image(reader, raw, conn.msgtype, self.depth_unit)
                        for k in need_d[nd]:
                            depth[k] = d
                    nd += 1
                while nxt in rgb and nxt in depth:
                    c_img, d_img = rgb.pop(nxt), depth.pop(nxt)
                    yield tolerant(
                        nxt,
                        f"{self.path.name} frame {nxt}",
                        partial(self._frame, nxt, c_img, d_img),
                    )
                    nxt += 1
                # Depth kept for frames already emitted is dropped; stale entries cannot grow.
                for k in [k for k in depth if k < nxt]:
                    del depth[k]
        finally:
            try:
                reader.close()
            except Exception:  # e.g. a generator collected at interpreter shutdown
                pass

    def _frame(self, k: int, rgb: Any, depth: Any) -> Frame:
        for img in (rgb, depth):
            if isinstance(img, BaseException):
                raise img
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
