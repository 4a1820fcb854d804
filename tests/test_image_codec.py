"""Images in recordings (bubble_rt.io.image_codec): colour as Foxglove CompressedImage (JPEG or
PNG), depth as lossless RawImage; old raw recordings still read; a corrupt image is a skipped,
counted bad frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bubble_rt.camera import Camera
from bubble_rt.frames import Frame, FrameFault
from bubble_rt.io.image_codec import (
    COLOR_CODECS,
    ImageDecodeError,
    color_image,
    fox_compressed,
    image_array,
    raw_image,
)
from bubble_rt.io.mcap import (
    TOPIC_DEPTH,
    TOPIC_PRESSURE,
    TOPIC_RGB,
    McapRecording,
    iter_messages,
)
from bubble_rt.io.mcap_writer import Recorder, write_recording
from bubble_rt.io.protocol import pb
from waiting import wait_for

pytestmark = pytest.mark.timeout(60)

H, W = 48, 64
CAM = Camera.d405(width=W, height=H, cx=W / 2, cy=H / 2)


def noisy_frame(i: int) -> Frame:
    """A frame with sensor-like noise in colour and an off-grid float depth (worst cases)."""
    rng = np.random.default_rng(i)
    y, x = np.mgrid[0:H, 0:W]
    rgb = np.clip(
        np.stack([x * 3, y * 4, (x + y) * 2], axis=-1) + rng.normal(0, 3, (H, W, 3)), 0, 255
    ).astype(np.uint8)
    depth = (0.07 + 0.002 * rng.random((H, W))).astype(np.float32)
    depth[:5, :5] = 0.0  # invalid pixels
    return Frame(rgb=rgb, depth=depth, pressure_pa=101325.0 + i, t=1000.0 + i / 30, index=i)


def test_png_colour_round_trip_is_bit_exact():
    f = noisy_frame(0)
    msg = color_image(f.rgb, 1.0, "png")
    assert msg.format == "png" and msg.frame_id == "bubble_rt_camera"
    np.testing.assert_array_equal(image_array(msg), f.rgb)


def test_jpeg_colour_is_close_and_smaller_than_raw():
    f = noisy_frame(0)
    msg = color_image(f.rgb, 1.0, "jpeg", jpeg_quality=90)
    back = image_array(msg)
    assert back.shape == f.rgb.shape and back.dtype == np.uint8
    err = np.abs(back.astype(int) - f.rgb.astype(int))
    assert err.mean() < 4.0  # a few levels: the noise, not the picture, is lost
    assert len(msg.data) < f.rgb.nbytes / 2
    # A lower quality is smaller: the setting reaches the encoder.
    assert len(color_image(f.rgb, 1.0, "jpeg", jpeg_quality=30).data) < len(msg.data)


def test_unknown_colour_codec_is_refused():
    with pytest.raises(ValueError, match="jpeg, png"):
        color_image(noisy_frame(0).rgb, 1.0, "webp")
    assert COLOR_CODECS == ("jpeg", "png")


def test_compressed_image_schema_is_foxgloves():
    """Foxglove matches the schema by name and field numbers: same as its own SDK's."""
    from google.protobuf import descriptor_pb2

    foxglove_schemas = pytest.importorskip("foxglove.schemas")
    s = foxglove_schemas.CompressedImage.get_schema()
    theirs = {
        f.name: (f.number, f.type)
        for file in descriptor_pb2.FileDescriptorSet.FromString(bytes(s.data)).file
        for m in file.message_type
        if m.name == "CompressedImage"
        for f in m.field
    }
    ours = fox_compressed.CompressedImage.DESCRIPTOR
    assert ours.full_name == s.name == "foxglove.CompressedImage"
    assert {f.name: (f.number, f.type) for f in ours.fields} == theirs


@pytest.mark.parametrize("color", COLOR_CODECS)
def test_recorder_writes_compressed_colour_and_lossless_depth(tmp_path, color):
    p = tmp_path / "r.mcap"
    frames = [noisy_frame(i) for i in range(3)]
    assert write_recording(p, frames, CAM, color=color) == 3
    msgs = {t: m for t, m, _, _ in iter_messages(p)}
    assert type(msgs[TOPIC_RGB]).DESCRIPTOR.full_name == "foxglove.CompressedImage"
    assert msgs[TOPIC_RGB].format == color
    assert type(msgs[TOPIC_DEPTH]).DESCRIPTOR.full_name == "foxglove.RawImage"
    got = list(McapRecording(p))
    assert [g.index for g in got] == [0, 1, 2]
    for a, b in zip(frames, got, strict=True):
        assert a.depth is not None and b.depth is not None
        assert a.depth.tobytes() == b.depth.tobytes()  # bit for bit, invalid pixels included
        if color == "png":
            np.testing.assert_array_equal(a.rgb, b.rgb)
        else:
            assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).mean() < 4.0


def write_raw_recording(path: Path, frames: list[Frame]) -> None:
    """A recording as the writer wrote them before compression: RawImage rgb8 + 32FC1 in lz4
    chunks (the old path, message for message)."""
    rec = Recorder(path, CAM, compression="lz4", queue_size=10_000)
    for f in frames:
        assert f.rgb is not None and f.depth is not None
        rec.write_message(TOPIC_RGB, raw_image(f.rgb, f.t), f.t, f.index)
        rec.write_message(TOPIC_DEPTH, raw_image(f.depth, f.t), f.t, f.index)
        msg = pb.PressureSample(
            time_ns=int(f.t * 1e9), pressure_pa=f.pressure_pa, frame_index=f.index
        )
        rec.write_message(TOPIC_PRESSURE, msg, f.t, f.index)
    assert rec.close(timeout=30)


def test_old_raw_image_recordings_still_replay(tmp_path):
    p = tmp_path / "old.mcap"
    frames = [noisy_frame(i) for i in range(4)]
    write_raw_recording(p, frames)
    msgs = {t: m for t, m, _, _ in iter_messages(p)}
    assert msgs[TOPIC_RGB].encoding == "rgb8"  # really the old layout
    got = list(McapRecording(p))
    assert [g.index for g in got] == [0, 1, 2, 3]
    for a, b in zip(frames, got, strict=True):
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)


def _with_bad_colour(path: Path, bad: dict[int, object]) -> None:
    """Frames 0-5 with the colour message of each index in ``bad`` replaced by the given
    CompressedImage (corrupt data)."""
    rec = Recorder(path, CAM, queue_size=10_000)
    for i in range(6):
        f = noisy_frame(i)
        assert f.rgb is not None and f.depth is not None
        msg = bad.get(i) or color_image(f.rgb, f.t, "jpeg")
        rec.write_message(TOPIC_RGB, msg, f.t, i)
        rec.write_message(TOPIC_DEPTH, raw_image(f.depth, f.t), f.t, i)
        rec.write_message(
            TOPIC_PRESSURE, pb.PressureSample(time_ns=0, pressure_pa=1e5, frame_index=i), f.t, i
        )
    assert rec.close(timeout=30)


def test_corrupt_jpeg_and_png_are_skipped_counted_frames(tmp_path):
    good = color_image(noisy_frame(1).rgb, 0.0, "jpeg")
    cut = fox_compressed.CompressedImage(format="jpeg", data=good.data[: len(good.data) // 2])
    png = color_image(noisy_frame(3).rgb, 0.0, "png")
    flipped = bytearray(png.data)
    flipped[len(flipped) // 2] ^= 0xFF  # inside the image data: its CRC no longer matches
    garbage = fox_compressed.CompressedImage(format="png", data=bytes(flipped))
    empty = fox_compressed.CompressedImage(format="jpeg", data=b"")
    p = tmp_path / "bad.mcap"
    _with_bad_colour(p, {1: cut, 3: garbage, 4: empty})
    rec = McapRecording(p)
    got = list(rec.frames(faults=True))
    faults = [g for g in got if isinstance(g, FrameFault)]
    assert [g.index for g in got] == [0, 1, 2, 3, 4, 5]
    assert [f.index for f in faults] == [1, 3, 4]
    assert "cut short" in faults[0].reason and "does not decode" in faults[1].reason
    assert all(TOPIC_RGB in f.reason and "bad.mcap frame" in f.where for f in faults)
    assert [f.index for f in rec] == [0, 2, 5]  # plain iteration skips them


def test_decoding_errors_are_value_errors():
    """What the readers catch: every undecodable image raises ImageDecodeError."""
    short = raw_image(noisy_frame(0).rgb, 0.0)
    short.data = short.data[:-7]
    unknown = fox_compressed.CompressedImage(format="avif", data=b"\x00" * 10)
    for msg in (short, unknown):
        with pytest.raises(ImageDecodeError):
            image_array(msg)
    assert issubclass(ImageDecodeError, ValueError)


def test_replay_skips_counts_and_names_a_corrupt_image_and_goes_on(tmp_path):
    """Through the daemon's replay source: the run goes on past the bad frames."""

    from bubble_rt.daemon.service import Daemon
    from bubble_rt.daemon.sources import ReplayCamera
    from daemon_fakes import FakeProcessor, constant_pressure, fake_config

    good = color_image(noisy_frame(2).rgb, 0.0, "jpeg")
    cut = fox_compressed.CompressedImage(format="jpeg", data=good.data[:-100])
    p = tmp_path / "bad.mcap"
    _with_bad_colour(p, {2: cut, 4: fox_compressed.CompressedImage(format="png", data=b"\x89PNG")})
    src = ReplayCamera(str(p), realtime=False, loop=False)
    cfg = fake_config(**{"camera.pace": "fast", "camera.loop": False, "reference.frames": 1})
    d = Daemon(cfg, camera=src, pressure=constant_pressure(), processor_factory=FakeProcessor)
    d.start()
    try:
        wait_for(lambda: src.finished.is_set() and d.frames_published >= 3, 20, "the replay")
    finally:
        d.stop()
    assert src.stats.errors == {"bad_frame": 2} and src.stats.received == 4
    assert [b.split(":")[0] for b in src.bad_frames] == ["bad.mcap frame 2", "bad.mcap frame 4"]
    assert d.frames_published >= 3  # frame 0 is the reference; 1, 3 and 5 are solved
