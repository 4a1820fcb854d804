"""The MCAP recording writer: :class:`Recorder` (the daemon's, from a background thread) and
:func:`write_recording` (frames produced offline). The channels, reading and recovery are in
:mod:`bubble_rt.io.mcap`.

Images are encoded on the recorder's thread, never on the caller's. The writer never writes a
negative time: a time before the Unix epoch is written as 0 and counted in
``Recorder.clamped``. Chunks are flushed to disk at least every ``flush_s`` seconds, so after
a crash the file is readable up to the last flushed chunk.

A write failure (disk full, device gone) never reaches the caller: the recorder stops
writing, keeps the reason in ``Recorder.failed`` and drops (counts) what it is given after.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from bubble_rt.camera import Camera
from bubble_rt.frames import Frame
from bubble_rt.io.image_codec import color_image, raw_image
from bubble_rt.io.mcap import (
    TOPIC_CAMERA_INFO,
    TOPIC_DEPTH,
    TOPIC_FORCE,
    TOPIC_MESH,
    TOPIC_PRESSURE,
    TOPIC_REF_DEPTH,
    TOPIC_REF_PRESSURE,
    TOPIC_REF_RGB,
    TOPIC_REF_WRENCH,
    TOPIC_RGB,
    TOPIC_STATUS,
    TOPIC_WRENCH,
    camera_info,
    open_new_file,
    to_ns,
)
from bubble_rt.io.protocol import pb

log = logging.getLogger("bubble_rt.io.mcap")  # the recording's logger, as before the split


class Recorder:
    """Writes an MCAP recording from a background thread through a bounded queue.

    ``write_*`` never block the caller: when the writer falls behind by ``queue_size``
    messages, new messages are dropped and counted in ``dropped``. All file work (chunks,
    flushes, the summary and footer) happens on the writer thread; the constructor only opens
    the file (:func:`~bubble_rt.io.mcap.open_new_file`, non-blocking, refusing existing files
    unless ``overwrite``). A write failure sets ``failed`` (the reason) at once and never raises.
    """

    def __init__(
        self,
        path: str | Path,
        camera: Camera | None = None,
        mesh: Any | None = None,
        *,
        inputs: bool = True,
        chunk_size: int = 4 * 1024 * 1024,
        compression: str = "zstd",
        color: str = "jpeg",
        jpeg_quality: int = 90,
        queue_size: int = 64,
        flush_s: float = 1.0,
        overwrite: bool = False,
        file: Any = None,
    ) -> None:
        from mcap.writer import CompressionType
        from mcap.writer import Writer as McapWriter

        self.path = Path(path)
        self.inputs = inputs
        #: Colour encoding (:data:`bubble_rt.io.image_codec.COLOR_CODECS`) and JPEG quality.
        self.color = color
        self.jpeg_quality = jpeg_quality
        self.flush_s = flush_s
        comp = {
            "lz4": CompressionType.LZ4,
            "zstd": CompressionType.ZSTD,
            "none": CompressionType.NONE,
        }[compression]
        # Buffered; flushed to the OS every flush_s (a flushed chunk survives a crash).
        self._file = file if file is not None else open_new_file(self.path, overwrite)
        self._writer = McapWriter(self._file, chunk_size=chunk_size, compression=comp)
        self._channels: dict[str, int] = {}
        self._queue: queue.Queue[tuple[str, Callable[[], Any], int, int] | None] = queue.Queue(
            queue_size
        )
        self.dropped = 0
        self.written = 0
        #: Log times before the Unix epoch written as 0.
        self.clamped = 0
        #: First message that could not be built or encoded (the recording goes on).
        self.error = ""
        #: Why writing stopped (disk full, device gone): the file is incomplete. "" while fine.
        self.failed = ""
        #: Set once the file is finalised (or abandoned after a failure) by the writer thread.
        self.finished = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name="recorder", daemon=True)
        self._thread.start()
        if camera is not None:
            self._put(TOPIC_CAMERA_INFO, lambda: camera_info(camera, time.time()), time.time(), 0)
        if mesh is not None:
            self._put(TOPIC_MESH, lambda: mesh, time.time(), 0)

    # ---------------------------------------------------------------- producer side
    def _put(self, topic: str, build: Callable[[], Any], t: float, seq: int) -> bool:
        if self._closed or self.failed:
            if self.failed:
                self.dropped += 1
            return False
        ns = to_ns(t)
        if ns < 0:
            self.clamped += 1
            ns = 0
        try:
            self._queue.put_nowait((topic, build, ns, int(seq)))
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def write_frame(self, frame: Frame, reference: bool = False) -> None:
        """Record one input frame (RGB, depth, pressure), sequence = ``frame.index``."""
        if not self.inputs:
            return
        topics = (
            (TOPIC_REF_RGB, TOPIC_REF_DEPTH, TOPIC_REF_PRESSURE)
            if reference
            else (TOPIC_RGB, TOPIC_DEPTH, TOPIC_PRESSURE)
        )
        t, idx = frame.t, frame.index
        if frame.rgb is not None:
            rgb, codec, q = frame.rgb, self.color, self.jpeg_quality
            # Encoded on the writer thread (the lambda runs there), never the caller's.
            self._put(topics[0], lambda: color_image(rgb, t, codec, q), t, idx)
        if frame.depth is not None:
            depth = frame.depth
            self._put(topics[1], lambda: raw_image(depth, t), t, idx)
        if frame.wrench is not None:  # before the pressure, which completes the frame
            w = [float(x) for x in frame.wrench]
            self._put(
                TOPIC_REF_WRENCH if reference else TOPIC_WRENCH,
                lambda: pb.WrenchSample(
                    time_ns=to_ns(t), frame_index=idx, force=w[:3], torque=w[3:]
                ),
                t,
                idx,
            )
        p = float(frame.pressure_pa)
        tp = frame.t_pressure if frame.t_pressure is not None else t
        self._put(
            topics[2],
            lambda: pb.PressureSample(time_ns=to_ns(tp), pressure_pa=p, frame_index=idx),
            t,
            idx,
        )

    def write_reference(self, frames: Iterable[Frame]) -> None:
        for f in frames:
            self.write_frame(f, reference=True)

    def write_message(self, topic: str, msg: Any, t: float | None = None, seq: int = 0) -> None:
        self._put(topic, lambda: msg, time.time() if t is None else t, seq)

    def write_force(self, msg: Any) -> None:
        self._put(TOPIC_FORCE, lambda: msg, msg.capture_time_ns / 1e9, msg.frame_index)

    def write_status(self, msg: Any) -> None:
        self._put(TOPIC_STATUS, lambda: msg, msg.time_ns / 1e9, 0)

    # ---------------------------------------------------------------- writer thread
    def _channel(self, topic: str, msg: Any) -> int:
        cid = self._channels.get(topic)
        if cid is None and hasattr(msg, "schema_name"):  # pre-encoded (bubble_rt.io.foxglove)
            sid = self._writer.register_schema(
                name=msg.schema_name, encoding=msg.schema_encoding, data=msg.schema_data
            )
            cid = self._writer.register_channel(
                topic=topic, message_encoding=msg.message_encoding, schema_id=sid
            )
            self._channels[topic] = cid
        if cid is None:
            from mcap.well_known import MessageEncoding
            from mcap_protobuf.schema import register_schema

            sid = register_schema(self._writer, type(msg))
            cid = self._writer.register_channel(
                topic=topic, message_encoding=MessageEncoding.Protobuf, schema_id=sid
            )
            self._channels[topic] = cid
        return cid

    def _fail(self, exc: BaseException) -> None:
        reason = f"{type(exc).__name__}: {exc}"
        self.failed = f"writing {self.path} failed: {reason}"
        log.error("recording stopped: %s", self.failed)

    def _drain(self) -> None:
        """After a failure: take (and count) what producers still queue, until closed."""
        while not self._closed:
            try:
                if self._queue.get(timeout=0.1) is not None:
                    self.dropped += 1
            except queue.Empty:
                pass

    def _loop(self) -> None:
        try:
            # The header goes to disk at once: an unwritable target fails now, not in 1 s.
            self._writer.start(profile="", library="bubble_rt")
            self._writer.flush()
            self._write_queued()
            self._writer.finish()
            self._file.flush()
        except Exception as exc:  # disk full, device gone: report, never raise
            self._fail(exc)
            self._drain()
        finally:
            try:
                self._file.close()
            except Exception as exc:
                if not self.failed:
                    self._fail(exc)
            self.finished.set()

    def _write_queued(self) -> None:
        last_flush = time.monotonic()
        while True:
            try:
                item = self._queue.get(timeout=0.1)
            except queue.Empty:
                item = None
                if self._closed:
                    break
            if item is not None:
                topic, build, log_ns, seq = item
                try:
                    msg = build()
                    data = msg.SerializeToString()
                    cid = self._channel(topic, msg)
                except Exception as exc:  # a bad message: keep recording the rest
                    self.error = self.error or f"{type(exc).__name__}: {exc}"
                else:
                    self._writer.add_message(
                        channel_id=cid,
                        log_time=log_ns,
                        publish_time=log_ns,
                        data=data,
                        sequence=seq & 0xFFFFFFFF,
                    )
                    self.written += 1
            if time.monotonic() - last_flush > self.flush_s:
                self._writer.flush()  # ends the chunk in progress: it survives a crash
                last_flush = time.monotonic()
            if self._closed and self._queue.empty():
                break

    def close(self, timeout: float = 1.5) -> bool:
        """Write what is queued, then the index and footer (on the writer thread).

        Waits at most ``timeout`` seconds; True when the file is finalised (False: still
        writing in the background, or ``failed``). Never raises.
        """
        self._closed = True
        self.finished.wait(timeout)
        return self.finished.is_set() and not self.failed

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def write_recording(
    path: str | Path,
    frames: Iterable[Frame],
    camera: Camera,
    reference: Iterable[Frame] = (),
    overwrite: bool = False,
    color: str = "png",
) -> int:
    """Write frames (and optional reference frames) as a recording; returns frames written.

    Used by anything that produces frames offline (e.g. the simulator); nothing is dropped,
    and the colour is lossless by default (``color``: "png" or "jpeg" at quality 90).
    """
    n = 0
    rec = Recorder(path, camera, queue_size=1 << 30, overwrite=overwrite, color=color)
    try:
        rec.write_reference(reference)
        for f in frames:
            rec.write_frame(f)
            n += 1
    finally:
        rec.close(timeout=600.0)
    if rec.failed:
        raise OSError(rec.failed)
    return n
