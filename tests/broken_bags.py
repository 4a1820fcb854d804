"""ROS 2 bags for tests, good and damaged: ``bag_frames`` (small synthetic frames),
``rewrite_bag`` (copy a bag message by message through an edit: drop, damage or replace a
message) and ``damaged_bag`` (one named damage per variant). Damage lives here, not in
``bubble_rt.io.bag_writer.write_bag``: the library writes good bags only."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from bubble_rt.camera import Camera
from bubble_rt.frames import Frame
from bubble_rt.io.bag_writer import write_bag
from synth_rgbd import dome_depth, texture

T0 = 1_700_000_000.0
RAMP_PA_PER_S = 300.0  # pressure ramp: interpolation between 100 Hz readings is exact

COLOR = "/bubble_1/color/image_rect_raw"
DEPTH = "/bubble_1/depth/image_rect_raw"
INFO = "/bubble_1/color/camera_info"
PRESSURE = "/bubble_1/pressure"


def bag_frames(n: int = 5, wrench: bool = True, mm: bool = True) -> tuple[list[Frame], Camera]:
    """``n`` frames of an 80 x 60 camera looking at a dome: the texture still over frames 0-1
    (an untouched reference), then sliding 1 px a frame; pressure ramping at RAMP_PA_PER_S;
    30 Hz from T0. Written with ``tf=True`` the bag carries the camera pose, which the
    estimator needs (the Punyo pose does not fit this synthetic dome)."""
    cam = Camera(fx=60.0, fy=60.0, cx=39.5, cy=29.5, width=80, height=60)
    d = dome_depth(cam).astype(np.float32)
    if mm:  # 16UC1 carries whole millimetres
        d = (np.round(d * 1000) / 1000).astype(np.float32)
    rgb = texture(cam.height, cam.width)
    frames = [
        Frame(
            rgb=np.roll(rgb, max(i - 1, 0), axis=1),
            depth=d,
            pressure_pa=101_300.0 + RAMP_PA_PER_S * (i / 30),
            t=T0 + i / 30,
            wrench=np.arange(6.0) + i if wrench else None,
            index=i,
        )
        for i in range(n)
    ]
    return frames, cam


#: edit(topic, k, msg) -> the message to write instead, or None to drop it (k counts the
#: topic's messages from 0).
Edit = Callable[[str, int, Any], Any]


def rewrite_bag(
    src: Path,
    dst: Path,
    edit: Edit,
    topics: dict[str, str] | None = None,
    storage: str = "mcap",
) -> Path:
    """Copy the rosbag2 ``src`` to ``dst`` (``storage`` "mcap" or "sqlite3") through ``edit``,
    in time order; ``topics`` renames topics (old -> new) after the edit."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    counts: dict[str, int] = {}
    conns: dict[str, Any] = {}
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    writer = Writer(dst, version=9, storage_plugin=plugin)
    writer.open()
    try:
        with Reader(src) as reader:
            for conn, t_ns, raw in reader.messages():
                k = counts[conn.topic] = counts.get(conn.topic, -1) + 1
                msg = edit(conn.topic, k, ts.deserialize_cdr(raw, conn.msgtype))
                if msg is None:
                    continue
                topic = (topics or {}).get(conn.topic, conn.topic)
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, conn.msgtype, typestore=ts)
                writer.write(conns[topic], t_ns, ts.serialize_cdr(msg, conn.msgtype))
    finally:
        writer.close()
    return dst


def without(root: Path, topic: str, frames: list[Frame], cam: Camera, name: str) -> Path:
    """A bag of ``frames`` without ``topic``'s messages (no camera_info, no pressure)."""
    good = write_bag(root / f"{name}-good", frames, cam)
    return rewrite_bag(good, root / name, lambda t, k, m: None if t == topic else m)


def with_depth_size(root: Path, frames: list[Frame], cam: Camera, size: tuple[int, int]) -> Path:
    """A bag whose depth images are ``size`` (w, h), nearest-neighbour resized (16UC1)."""
    import cv2

    def resize(t: str, k: int, m: Any) -> Any:
        if t != DEPTH:
            return m
        d = np.frombuffer(m.data.tobytes(), "<u2").reshape(m.height, m.width)
        r = np.ascontiguousarray(cv2.resize(d, size, interpolation=cv2.INTER_NEAREST))
        return dataclasses.replace(
            m, width=size[0], height=size[1], step=2 * size[0], data=r.view(np.uint8).reshape(-1)
        )

    return rewrite_bag(write_bag(root / "sizes-good", frames, cam), root / "sizes", resize)


def _float_image(msg: Any, values: np.ndarray) -> Any:
    """A 32FC1 depth message with ``values`` (H x W) in place of ``msg``'s image."""
    v = np.ascontiguousarray(values, dtype="<f4")
    return dataclasses.replace(
        msg, encoding="32FC1", step=4 * v.shape[1], data=v.view(np.uint8).reshape(-1)
    )


def _damage(variant: str, cam: Camera) -> tuple[str, Callable[[Any], Any], str]:
    """(topic, damage of one message, the reason's expected text, lower case)."""
    h, w = cam.height, cam.width
    if variant == "all_nan_depth_32fc1":
        return DEPTH, lambda m: _float_image(m, np.full((h, w), np.nan)), "no valid pixel"
    if variant == "zero_depth":
        return DEPTH, lambda m: dataclasses.replace(m, data=np.zeros_like(m.data)), "no valid pixel"
    if variant == "negative_depth":
        return DEPTH, lambda m: _float_image(m, np.full((h, w), -0.05)), "no valid pixel"
    if variant == "short_colour":
        return COLOR, lambda m: dataclasses.replace(m, data=m.data[: m.data.size // 2]), "cut short"
    if variant == "short_depth":
        return DEPTH, lambda m: dataclasses.replace(m, data=m.data[:100]), "cut short"
    if variant == "wrong_row_step":
        return COLOR, lambda m: dataclasses.replace(m, step=m.step - 3), "row step"
    if variant == "encoding_change":
        return COLOR, lambda m: dataclasses.replace(m, encoding="yuv422"), "unsupported image"
    if variant == "size_change":
        small = np.zeros((h // 2, w // 2, 3), np.uint8)

        def half(m: Any) -> Any:
            return dataclasses.replace(
                m, height=h // 2, width=w // 2, step=3 * (w // 2), data=small.reshape(-1)
            )

        return COLOR, half, "differs from"
    if variant == "depth_size_change":
        small_d = np.full((h // 2, w // 2), 80, "<u2")

        def half_depth(m: Any) -> Any:
            return dataclasses.replace(
                m, height=h // 2, width=w // 2, step=w, data=small_d.view(np.uint8).reshape(-1)
            )

        return DEPTH, half_depth, "differs from"
    if variant in ("nan_pressure", "inf_pressure"):
        bad = np.float32("nan" if variant == "nan_pressure" else "inf")
        return PRESSURE, lambda m: dataclasses.replace(m, data=bad), "not finite"
    raise AssertionError(variant)


#: Each damage names one test per consumer (estimate, replay). A pressure variant damages a
#: reading, the others one frame's image.
DAMAGED_VARIANTS = (
    "all_nan_depth_32fc1",
    "zero_depth",
    "negative_depth",
    "short_colour",
    "short_depth",
    "wrong_row_step",
    "encoding_change",
    "size_change",
    "depth_size_change",
    "nan_pressure",
    "inf_pressure",
)


def damaged_bag(
    root: Path, variant: str, n: int = 6, bad: int = 3
) -> tuple[Path, list[Frame], Camera, str]:
    """A bag of ``n`` frames whose frame ``bad`` (or pressure reading ``bad``) carries the
    damage ``variant``: (bag, frames, camera, expected reason text)."""
    frames, cam = bag_frames(n)
    depth_encoding = "32FC1" if variant in ("all_nan_depth_32fc1", "negative_depth") else "16UC1"
    good = write_bag(root / f"{variant}-good", frames, cam, depth_encoding=depth_encoding, tf=True)
    topic, damage, reason = _damage(variant, cam)

    def edit(t: str, k: int, msg: Any) -> Any:
        return damage(msg) if t == topic and k == bad else msg

    return rewrite_bag(good, root / variant, edit), frames, cam, reason
