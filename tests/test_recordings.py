"""Recording readers: Punyo .npy layout and PNG folder layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bubble_rt.daemon.sources import ReplayCamera, SourceError
from bubble_rt.estimation.deformation import Reference
from bubble_rt.frames import FrameError
from bubble_rt.io.recordings import (
    PngRecording,
    PunyoRecording,
    open_recording,
    punyo_pose,
    write_png_recording,
)
from recording_fakes import CX, CY, FX, FY, H, W, make_punyo, plane_cloud, png_frames

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "punyo-demo-0"


def test_punyo_reader_on_fixture(tmp_path):
    make_punyo(tmp_path)
    rec = open_recording(tmp_path)
    assert isinstance(rec, PunyoRecording)
    assert len(rec) == 3
    cam = rec.camera
    assert (cam.width, cam.height) == (W, H)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [FX, FY, CX, CY], atol=1e-3)
    np.testing.assert_allclose(cam.pose_matrix, punyo_pose())  # a plane: nothing to centre
    assert rec.placement.startswith("punyo_pose (not centred")
    f = rec[1]
    assert f.index == 1
    assert f.pressure_pa == pytest.approx(106600.0)
    assert f.t == pytest.approx(1000.0 + 1 / 30)
    np.testing.assert_allclose(f.wrench, [0.5, -0.2, 2.0, 0, 0, 0.01])
    assert f.rgb[0, 0, 0] == 10 and f.rgb[0, 0, 1] == 200  # channel order kept (RGB)
    d = f.depth.ravel()
    assert (d[:5] == 0).all() and d[7] == 0  # invalid and saturated points
    np.testing.assert_allclose(d[8:], plane_cloud(0.081)[8:, 2], rtol=1e-6)
    assert rec.wrenches.shape == (3, 6)
    assert [g.index for g in rec] == [0, 1, 2]
    assert rec[-1].index == 2
    with pytest.raises(IndexError):
        rec[3]


def test_punyo_reader_without_data_json(tmp_path):
    make_punyo(tmp_path, n=2, with_json=False)
    rec = open_recording(tmp_path)
    assert rec.wrenches is None
    assert rec[1].wrench is None and rec[1].t == 1.0


def test_punyo_reader_rejects_gaps(tmp_path):
    make_punyo(tmp_path, n=3)
    (tmp_path / "expand" / "rgb_1.npy").unlink()
    with pytest.raises(FrameError, match="contiguous"):
        open_recording(tmp_path)


def test_png_reader_round_trip(tmp_path):
    frames, cam = png_frames(3, wrench=True)
    write_png_recording(tmp_path / "rec", frames, cam, depth_scale=1e-4)
    rec = open_recording(tmp_path / "rec")
    assert isinstance(rec, PngRecording)
    assert len(rec) == 3
    assert (rec.camera.fx, rec.camera.cy, rec.camera.width) == (FX, CY, W)
    for src, got in zip(frames, rec, strict=True):
        np.testing.assert_array_equal(got.rgb, src.rgb)
        np.testing.assert_allclose(got.depth, src.depth, atol=0.5e-4)
        assert got.depth[0, 0] == 0.0
        assert got.pressure_pa == src.pressure_pa
        assert got.t == src.t
        np.testing.assert_allclose(got.wrench, src.wrench)
    assert rec.wrenches.shape == (3, 6)


def test_png_reader_without_wrench_columns(tmp_path):
    frames, cam = png_frames(2, wrench=False)
    write_png_recording(tmp_path, frames, cam)
    rec = open_recording(tmp_path)
    assert rec.wrenches is None and rec[0].wrench is None


def test_png_reader_missing_camera_json(tmp_path):
    frames, cam = png_frames(1, wrench=False)
    write_png_recording(tmp_path, frames, cam)
    (tmp_path / "camera.json").unlink()
    with pytest.raises(FileNotFoundError, match="camera.json"):
        open_recording(tmp_path)


def test_unknown_layout(tmp_path):
    with pytest.raises(FrameError, match="neither"):
        open_recording(tmp_path)
    with pytest.raises(FileNotFoundError):
        open_recording(tmp_path / "nope")


needs_data = pytest.mark.skipif(not DATA.exists(), reason="../shared/data/punyo-demo-0 absent")


@needs_data
def test_real_recording_reader():
    rec = open_recording(DATA)
    assert len(rec) == 20
    assert rec.placement == "centred"
    cam = rec.camera
    # Pinhole fit of the cloud (docs/deformation.md's figures), not the original code's 385.263.
    np.testing.assert_allclose(
        [cam.fx, cam.fy, cam.cx, cam.cy], [434.3, 433.4, 313.7, 247.5], atol=1.0
    )
    f = rec[0]
    assert f.rgb.shape == (480, 640, 3) and f.depth.shape == (480, 640)
    assert f.pressure_pa == pytest.approx(106581.08, abs=0.1)
    assert f.wrench.shape == (6,)
    valid = f.depth > 0
    assert 0.6 < valid.mean() < 0.75
    assert 0.05 < np.median(f.depth[valid]) < 0.10
    assert f.depth.max() < 0.5  # saturated readings dropped
    assert rec[19].t > rec[0].t
    # Green-lit interior: the stored (RGB) green channel dominates.
    means = f.rgb.reshape(-1, 3).mean(axis=0)
    assert means[1] > means[2] > means[0]


@needs_data
def test_real_reference_capture():
    rec = open_recording(DATA)
    frames = [rec[i] for i in range(5)]
    ref = Reference.capture(frames)
    assert ref.n_frames == 5
    assert ref.pressure_pa == pytest.approx(np.mean([f.pressure_pa for f in frames]))
    single = frames[0].depth > 0
    assert (ref.depth > 0).sum() >= single.sum()
    both = (ref.depth > 0) & single
    # Averaging five frames: close to each single frame, within sensor noise.
    assert np.median(np.abs(ref.depth[both] - frames[0].depth[both])) < 3e-4
    assert ref.rgb.shape == (480, 640, 3) and ref.rgb.dtype == np.uint8


def test_truncated_rgb_0_npy_gives_a_clear_error(tmp_path):
    """Used to exit with a bare `mmap length is greater than file size` traceback."""
    root = tmp_path / "rec"
    make_punyo(root, n=3)
    f = root / "expand" / "rgb_0.npy"
    f.write_bytes(f.read_bytes()[:200])
    with pytest.raises(FrameError, match=r"rgb_0\.npy: unreadable, damaged or truncated"):
        open_recording(root)
    with pytest.raises(SourceError, match=r"rgb_0\.npy"):
        ReplayCamera(str(root))
    from bubble_rt.cli import main

    assert main(["serve", "--camera", f"replay:{root}", "--duration", "0.1"]) == 1
