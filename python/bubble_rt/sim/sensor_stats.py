"""Noise statistics of a depth camera, measured the same way on real and simulated frames.

Given untouched frames of one static scene (a real recording or the simulator's), this measures
what the simulator's camera effects must reproduce (docs/sim-noise.md):

* **depth noise against range**: the temporal standard deviation of each membrane pixel's depth
  (mm), binned by its median depth, with a fitted ``sigma = c * z^2`` and
  the exponent the data says;
* **holes**: the fraction of invalid pixels on the membrane, by range (the nominal dome's
  depth, so that a hole's range is known), their blob sizes, and how persistent they are;
* **depth jumps**: valid pixels more than ``jump_m`` (2 mm) off the membrane surface, per
  frame, their size and where they are (in the near-range hole zone, at a depth edge);
* **flow noise**: the optical flow (the estimator's default method, through
  :func:`bubble_rt.estimation.deformation.make_tracker`) at the nodes of a mesh between the
  first frame and each later one, in pixels, and the nodes the tracker lifts by more than
  ``jump_m`` (the phantom-force jumps of issue 18);
* **RGB noise**: the temporal standard deviation of the colour levels.

The membrane region is the nominal dome (:class:`bubble_rt.mesh.MeshGeometry`) rendered from the
frames' camera, so real and simulated frames are cut the same way whatever their depth says.
Nothing here imports the estimator's model or solver: the simulator is judged by it.

``python3 -m bubble_rt.sim.sensor_stats`` prints the real-vs-simulated table of docs/sim-noise.md.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from bubble_rt.camera import Camera
from bubble_rt.frames import Frame
from bubble_rt.mesh import Mesh
from bubble_rt.sensor import PUNYO_BUBBLE, SIM_BUBBLE

#: A depth deviation from the surface larger than this (m) is a jump, not noise.
JUMP_M = 0.002
#: Larger deviations (m) are the background seen past the membrane (a hole), not a jump.
MAX_JUMP_M = 0.05
#: Nominal range (m) below which a jump is the near-range limit's (disparity aliasing), not an
#: occluder's edge: the real frames' other jumps are mostly the cable and label in view.
NEAR_RANGE_M = 0.060
#: Range bins (m) of the noise and hole statistics: the membrane spans 50-105 mm.
RANGE_EDGES_M: tuple[float, ...] = tuple(np.round(np.arange(0.050, 0.1101, 0.005), 3))
#: Local grey-level contrast (std over 15 px, 8-bit levels) of a textured node, and of a
#: texture-less one (the flow there follows the noise).
TEXTURED_LEVELS = 20.0
TEXTURELESS_LEVELS = 10.0
#: Image gradient (8-bit levels per pixel, of the frames' mean grey image) under which a pixel
#: is flat, and the band counted as an edge, for the image noise's two sides: a camera's
#: pipeline (demosaicing, denoising) leaves more noise on edges than on flat areas.
FLAT_GRADIENT = 2.0
EDGE_GRADIENT: tuple[float, float] = (10.0, 40.0)
#: Width (px) of the band around invalid pixels counted as a depth edge.
EDGE_BAND_PX = 5
#: Scales (m, a Gaussian's standard deviation on the membrane) over which the depth noise is
#: also measured smoothed: the estimator reads depth at nodes 4-7 mm apart, where a stereo
#: camera's noise, correlated over its matching window, no longer averages away.
SMOOTH_SCALES_M: tuple[float, ...] = (1e-3, 2e-3, 4e-3)
#: Pixels (px) cut from the membrane region's edge for the smoothed noise: a smoothing window
#: there reaches past the membrane.
SMOOTH_MARGIN_PX = 30


@dataclass
class SensorStats:
    """Noise statistics of one set of untouched frames (lengths in mm unless named).

    Attributes:
        frames: frames measured; region_px: membrane pixels (nominal dome in view).
        range_mm: bin edges (mm) of the per-range statistics (len(bins) + 1 values).
        noise_mm: per range bin, the RMS over pixels of the temporal depth std (mm);
            NaN where fewer than 200 pixels are valid throughout.
        noise_c: least-squares c of sigma = c z^2 over the bins (1/m; sigma and z in m).
        noise_exponent: the fitted p of sigma ~ z^p over the bins (the stereo law: 2).
        noise_median_mm: RMS temporal depth std over all steadily valid membrane pixels.
        smoothed_noise_mm: per scale of SMOOTH_SCALES_M, the RMS of each frame's deviation
            from the surface after a Gaussian smoothing of that standard deviation on the
            membrane (holes and jumps left out of the average), over the region less
            SMOOTH_MARGIN_PX: white noise falls as 1 / scale, noise correlated over a
            stereo window much more slowly.
        step_mm: median nonzero frame-to-frame depth change under 0.5 mm (with a depth unit,
            the unit), mm.
        hole_fraction: mean fraction of membrane pixels invalid per frame.
        hole_by_range: per range bin (nominal depth), fraction invalid (NaN: < 200 pixels).
        hole_blob_px: median and 90th percentile blob area (px) of invalid connected
            components inside the region (blobs of 4 px or more).
        hole_persistence: mean IoU of consecutive frames' invalid masks in the region.
        jump_rate: valid membrane pixels off the surface by more than JUMP_M, per frame per
            10^5 membrane pixels.
        jump_by_range: per range bin (nominal depth), the jump rate there (per 10^5 pixels).
        jump_mm: 50th and 95th percentiles and maximum of |deviation| of those pixels (mm).
        jump_in_holes: share of jump pixels at pixels invalid in most frames.
        jump_at_edges: share of jump pixels within EDGE_BAND_PX of an invalid pixel.
        jump_edge_rate: jump pixels per pixel of the band within EDGE_BAND_PX of a hole's edge
            (either side), per frame: the sensor's rate, whatever edges the scene has.
        jump_near_rate: the jump rate (per frame per 10^5 pixels) on the membrane nearer than
            NEAR_RANGE_M (nominal), where the near-range limit makes them.
        jump_behind, jump_near_behind: share of the jumps (all; near-range) that read
            farther than the surface.
        flow_rms_px, flow_median_px: RMS and median over visible nodes of each node's RMS
            flow against the first frame (px); flow_textured_px: the RMS over nodes whose
            local contrast is at least TEXTURED_LEVELS, flow_textured_detrended_px the same
            less each frame's mean flow over those nodes (a rigid shift); textureless_share: share of visible
            nodes under TEXTURELESS_LEVELS (where the flow follows the noise).
        node_jump_rate: tracked nodes lifted by more than JUMP_M from their median lift over
            the frames, per frame.
        node_u_rms_mm: RMS of that lift over valid nodes (mm).
        node_gradient: median over the textured nodes of the RMS image gradient in a 15 px
            window (8-bit levels per pixel): what the flow holds on to.
        rgb_noise: RMS over the membrane of the colour levels' temporal std (8-bit levels).
        grey_noise: the same for the grey image the flow reads.
        grey_noise_flat, grey_noise_edges: the same on flat pixels (gradient under
            FLAT_GRADIENT) and on edges (gradient within EDGE_GRADIENT).
    """

    frames: int
    region_px: int
    range_mm: list[float]
    noise_mm: list[float]
    noise_c: float
    noise_exponent: float
    noise_median_mm: float
    smoothed_noise_mm: list[float]
    step_mm: float
    hole_fraction: float
    hole_by_range: list[float]
    hole_blob_px: tuple[float, float]
    hole_persistence: float
    jump_rate: float
    jump_by_range: list[float]
    jump_mm: tuple[float, float, float]
    jump_in_holes: float
    jump_at_edges: float
    jump_edge_rate: float
    jump_near_rate: float
    jump_behind: float
    jump_near_behind: float
    flow_rms_px: float = float("nan")
    flow_median_px: float = float("nan")
    flow_textured_px: float = float("nan")
    flow_textured_detrended_px: float = float("nan")
    textureless_share: float = float("nan")
    node_jump_rate: float = float("nan")
    node_u_rms_mm: float = float("nan")
    node_gradient: float = float("nan")
    rgb_noise: float = float("nan")
    grey_noise: float = float("nan")
    grey_noise_flat: float = float("nan")
    grey_noise_edges: float = float("nan")

    def noise_at(self, z_mm: float) -> float:
        """The binned temporal noise (mm) at range ``z_mm`` (NaN outside the bins)."""
        i = int(np.searchsorted(self.range_mm, z_mm, side="right")) - 1
        return self.noise_mm[i] if 0 <= i < len(self.noise_mm) else float("nan")

    def jump_at(self, z_mm: float) -> float:
        """The jump rate (per frame per 10^5 pixels) at nominal range ``z_mm``."""
        i = int(np.searchsorted(self.range_mm, z_mm, side="right")) - 1
        return self.jump_by_range[i] if 0 <= i < len(self.jump_by_range) else float("nan")

    def hole_at(self, z_mm: float) -> float:
        """The hole fraction at nominal range ``z_mm`` (NaN outside the bins)."""
        i = int(np.searchsorted(self.range_mm, z_mm, side="right")) - 1
        return self.hole_by_range[i] if 0 <= i < len(self.hole_by_range) else float("nan")


def membrane_region(camera: Camera, nodes: int = 390) -> NDArray[np.float32]:
    """Depth (m, H x W) of the nominal dome seen by ``camera``, 0 off the membrane."""
    from bubble_rt.sim.render import render_depth

    mesh = Mesh.generate(nodes)
    return render_depth(camera, mesh.vertices, mesh.triangles)


def _surface(
    D: NDArray[np.float64], valid: NDArray[np.bool_], nominal: NDArray, region: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The membrane surface depth per pixel (m) and where it is steady (valid in most frames).

    Steady pixels: their temporal median. Elsewhere (holes): the nominal dome's depth plus the
    offset of the measured surface from it, filled across holes (it varies smoothly).
    """
    import cv2

    n = len(D)
    steady = valid.sum(axis=0) * 2 > n
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(np.where(valid, D, np.nan), axis=0)
    known = (steady & region).astype(np.float32)
    off = np.where(known > 0, med - nominal, 0.0).astype(np.float32)
    fill = np.full(off.shape, float(np.median(off[known > 0])) if known.any() else 0.0, np.float32)
    # Offsets averaged over growing windows: the nearest measured surface around each hole.
    for k in (241, 121, 61, 31):
        w = cv2.blur(known, (k, k))
        m = cv2.blur(off, (k, k))
        fill = np.where(w > 0.05, m / np.maximum(w, 1e-6), fill)
    surf = np.where(steady, med, nominal + fill)
    return np.asarray(surf, dtype=np.float64), steady


def _rms(x: NDArray) -> float:
    """Root mean square: with a quantised depth most pixels never change over a few frames,
    so a median of per-pixel spreads reads 0; the RMS reads the mean variance."""
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else float("nan")


def depth_stats(
    depths: Sequence[NDArray], camera: Camera, jump_m: float = JUMP_M
) -> dict[str, object]:
    """The depth statistics of SensorStats (every field up to ``jump_at_edges``)."""
    D = np.stack([np.asarray(d, dtype=np.float64) for d in depths])
    D = np.where(np.isfinite(D), D, 0.0)
    nominal = membrane_region(camera).astype(np.float64)
    region = nominal > 0
    valid = D > 0
    valid &= D < 1.0  # saturated readings (6.5535 m) are holes too
    surf, steady = _surface(D, valid, nominal, region)
    dev = np.where(valid, D - surf, 0.0)
    # Off by more than MAX_JUMP_M: the background seen past the membrane, not a jump.
    jump = valid & (np.abs(dev) > jump_m) & (np.abs(dev) < MAX_JUMP_M) & region
    # Temporal noise: steadily valid pixels valid in every frame, jumps left out.
    full = valid.all(axis=0) & region
    dn = np.where(np.abs(dev) > jump_m, np.nan, D)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sd = np.nanstd(dn, axis=0)
    inv = ~valid & region
    return {
        "frames": len(D),
        "region_px": int(region.sum()),
        **_by_range(D, surf, sd, full, inv, jump, nominal, region),
        "noise_median_mm": _rms(sd[full]) * 1e3 if full.any() else float("nan"),
        "smoothed_noise_mm": _smoothed_noise(
            D, valid & (np.abs(dev) <= jump_m), surf, nominal, region, camera
        ),
        **_hole_stats(inv, region),
        **_jump_stats(valid, jump, dev, steady, nominal, region),
    }


def _smoothed_noise(
    D: NDArray, ok: NDArray, surf: NDArray, nominal: NDArray, region: NDArray, camera: Camera
) -> list[float]:
    """``smoothed_noise_mm`` of SensorStats: per scale, the RMS (mm) of the frames' smoothed
    deviations from the surface (a normalised convolution over the valid pixels)."""
    import cv2

    core = cv2.erode(region.astype(np.uint8), np.ones((2 * SMOOTH_MARGIN_PX + 1,) * 2, np.uint8))
    m_per_px = float(np.median(nominal[region])) / float(camera.K[0, 0])
    out = []
    for scale in SMOOTH_SCALES_M:
        s = scale / m_per_px
        sq, n = 0.0, 0
        for d, v in zip(D, ok, strict=True):
            w = v.astype(np.float64)
            num = cv2.GaussianBlur(np.where(v, d - surf, 0.0), (0, 0), s)
            den = cv2.GaussianBlur(w, (0, 0), s)
            keep = (core > 0) & (den > 0.3)
            x = num[keep] / den[keep]
            sq += float(np.sum(x * x))
            n += x.size
        out.append(float(np.sqrt(sq / n)) * 1e3 if n else float("nan"))
    return out


def _by_range(
    D: NDArray, surf: NDArray, sd: NDArray, full: NDArray, inv: NDArray, jump: NDArray,
    nominal: NDArray, region: NDArray,
) -> dict[str, object]:  # fmt: skip
    """Noise, holes and jumps per range bin; the noise law sigma = c z^2 and its fitted
    exponent; the depth quantisation step."""
    n = len(D)
    edges = np.asarray(RANGE_EDGES_M)
    noise, holes, jumps, zc = [], [], [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = full & (surf >= lo) & (surf < hi)
        noise.append(_rms(sd[m]) * 1e3 if m.sum() >= 200 else float("nan"))
        zc.append(0.5 * (lo + hi))
        h = region & (nominal >= lo) & (nominal < hi)
        holes.append(float(inv[:, h].mean()) if h.sum() >= 200 else float("nan"))
        jumps.append(
            float(jump[:, h].sum() / n / h.sum() * 1e5) if h.sum() >= 200 else float("nan")
        )
    nz = np.asarray(noise) * 1e-3
    ok = np.isfinite(nz)
    z2 = np.asarray(zc)[ok] ** 2
    c = float(z2 @ nz[ok] / (z2 @ z2)) if ok.any() else float("nan")
    # What the data says: the exponent p of sigma ~ z^p (2 for the textbook stereo law).
    expo = (
        float(np.polyfit(np.log(np.asarray(zc)[ok]), np.log(nz[ok]), 1)[0])
        if ok.sum() >= 2 and (nz[ok] > 0).all()
        else float("nan")
    )
    diffs = np.abs(np.diff(D[:, full], axis=0))
    diffs = diffs[(diffs > 1e-7) & (diffs < 5e-4)]
    return {
        "range_mm": [float(e * 1e3) for e in edges],
        "noise_mm": noise,
        "noise_c": c,
        "noise_exponent": expo,
        "step_mm": float(np.median(diffs) * 1e3) if diffs.size else 0.0,
        "hole_by_range": holes,
        "jump_by_range": jumps,
    }


def _hole_stats(inv: NDArray, region: NDArray) -> dict[str, object]:
    """Holes: the fraction of the membrane, blob sizes per frame, persistence between
    consecutive frames (IoU)."""
    import cv2

    n = len(inv)
    areas: list[int] = []
    for k in range(n):
        _n, _lab, st, _c = cv2.connectedComponentsWithStats(inv[k].astype(np.uint8), connectivity=8)
        areas.extend(int(a) for a in st[1:, cv2.CC_STAT_AREA] if a >= 4)
    iou = [
        float((inv[k] & inv[k + 1]).sum() / max((inv[k] | inv[k + 1]).sum(), 1))
        for k in range(n - 1)
    ]
    return {
        "hole_fraction": float(inv.sum() / (n * max(int(region.sum()), 1))),
        "hole_blob_px": (
            (float(np.median(areas)), float(np.quantile(areas, 0.9))) if areas else (0.0, 0.0)
        ),
        "hole_persistence": float(np.mean(iou)) if iou else float("nan"),
    }


def _jump_stats(
    valid: NDArray, jump: NDArray, dev: NDArray, steady: NDArray, nominal: NDArray,
    region: NDArray,
) -> dict[str, object]:  # fmt: skip
    """Jumps: their rate, size, and where they are (in holes, at hole edges, near range)."""
    import cv2

    n = len(valid)
    kernel = np.ones((2 * EDGE_BAND_PX + 1,) * 2, np.uint8)
    near_edge = np.stack([cv2.dilate((~valid[k]).astype(np.uint8), kernel) > 0 for k in range(n)])
    near_valid = np.stack([cv2.dilate(valid[k].astype(np.uint8), kernel) > 0 for k in range(n)])
    # The band on both sides of a hole's edge, over the membrane.
    band = ((near_edge & valid) | (near_valid & ~valid)) & region
    nj = int(jump.sum())
    mags = np.abs(dev[jump]) * 1e3
    near = region & (nominal < NEAR_RANGE_M)
    return {
        "jump_rate": float(nj / n / max(int(region.sum()), 1) * 1e5),
        "jump_mm": (
            (float(np.median(mags)), float(np.quantile(mags, 0.95)), float(mags.max()))
            if nj
            else (0.0, 0.0, 0.0)
        ),
        "jump_in_holes": float((jump & ~steady).sum() / nj) if nj else float("nan"),
        "jump_at_edges": float((jump & near_edge).sum() / nj) if nj else float("nan"),
        "jump_edge_rate": float((jump & band).sum() / max(int(band.sum()), 1)),
        "jump_near_rate": float(jump[:, near].sum() / n / max(int(near.sum()), 1) * 1e5),
        "jump_behind": float((dev[jump] > 0).mean()) if nj else float("nan"),
        "jump_near_behind": (
            float((dev[:, near][jump[:, near]] > 0).mean()) if jump[:, near].any() else float("nan")
        ),
    }


def _grey(rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
    import cv2

    return np.asarray(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), dtype=np.float32)


def local_contrast(rgb: NDArray[np.uint8], window_px: int = 15) -> NDArray[np.float32]:
    """Standard deviation of the grey level over a ``window_px`` square around each pixel."""
    import cv2

    g = _grey(rgb)
    mu = cv2.blur(g, (window_px, window_px))
    return np.sqrt(np.maximum(cv2.blur(g * g, (window_px, window_px)) - mu * mu, 0.0))


def gradient(grey: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The image gradient (levels per pixel, H x W each along x and y): Sobel over 8."""
    import cv2

    return (
        np.asarray(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), np.float32) / np.float32(8),
        np.asarray(cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3), np.float32) / np.float32(8),
    )


def local_gradient(rgb: NDArray[np.uint8], window_px: int = 15) -> NDArray[np.float32]:
    """RMS image gradient (levels per pixel) over a ``window_px`` square around each pixel."""
    import cv2

    gx, gy = gradient(_grey(rgb))
    return np.sqrt(np.asarray(cv2.blur(gx * gx + gy * gy, (window_px, window_px))))


def flow_stats(
    frames: Sequence[Frame], camera: Camera, nodes: str = "medium", jump_m: float = JUMP_M
) -> dict[str, float]:
    """Flow and node-lift noise of the default tracker against the first frame.

    Returns flow_rms_px, flow_median_px (per-node RMS over frames, then RMS and median over
    visible nodes), flow_textured_px (RMS over nodes whose local contrast is at least
    TEXTURED_LEVELS), textureless_share (visible nodes under TEXTURELESS_LEVELS),
    node_jump_rate (valid nodes lifted by more than ``jump_m`` from their median lift over
    the frames, per frame) and node_u_rms_mm (the same lift, valid nodes).
    """
    from bubble_rt.estimation.deformation import FlowSettings, Reference, make_tracker

    mesh = Mesh.from_spec(nodes)
    tracker = make_tracker(mesh, camera, Reference.capture(frames[0]), FlowSettings())
    vis = np.asarray(getattr(tracker, "visible", np.ones(mesh.n_nodes, bool)))
    uv = np.asarray(getattr(tracker, "uv_ref", np.zeros((mesh.n_nodes, 2))))
    tracked = [tracker.track(f) for f in frames]
    flows = [
        np.zeros((mesh.n_nodes, 2)) if d.flow is None else np.asarray(d.flow) for d in tracked[1:]
    ]
    # Each node's lift against its median over the frames, not against the first frame's: a
    # jump in the first frame would count again in every later frame (one node made 18 of a
    # seed's 30 "lifts" that way).
    U = np.stack([d.U for d in tracked])
    valid = np.stack([d.valid for d in tracked])
    dev = np.linalg.norm(U - np.median(U, axis=0), axis=2)
    u = dev[valid] if valid.any() else np.zeros(1)
    jumps = int((u > jump_m).sum())
    F = np.stack(flows)[:, vis]
    per_node = np.sqrt((F**2).sum(axis=2).mean(axis=0))
    px = np.clip(np.round(uv[vis]).astype(int), 0, [camera.width - 1, camera.height - 1])
    contrast = local_contrast(frames[0].rgb)[px[:, 1], px[:, 0]]  # type: ignore[arg-type]
    grad = local_gradient(frames[0].rgb)[px[:, 1], px[:, 0]]  # type: ignore[arg-type]
    textured = contrast >= TEXTURED_LEVELS
    # Less each frame's mean flow over the textured nodes: what a rigid shift of the whole
    # membrane in the image (the arm moving the real sensor) does not explain.
    shift = F[:, textured].mean(axis=1, keepdims=True) if textured.any() else 0.0
    detrended = np.sqrt(((F - shift) ** 2).sum(axis=2).mean(axis=0))
    k = max(len(frames), 1)
    return {
        "flow_rms_px": float(np.sqrt(np.mean(per_node**2))),
        "flow_median_px": float(np.median(per_node)),
        "flow_textured_px": (
            float(np.sqrt(np.mean(per_node[textured] ** 2))) if textured.any() else float("nan")
        ),
        "flow_textured_detrended_px": (
            float(np.sqrt(np.mean(detrended[textured] ** 2))) if textured.any() else float("nan")
        ),
        "textureless_share": float(np.mean(contrast < TEXTURELESS_LEVELS)),
        "node_jump_rate": jumps / k,
        "node_u_rms_mm": float(np.sqrt(np.mean(u**2)) * 1e3),
        "node_gradient": float(np.median(grad[textured])) if textured.any() else float("nan"),
    }


def rgb_stats(frames: Sequence[Frame], camera: Camera) -> dict[str, float]:
    """rgb_noise and grey_noise: RMS over the membrane of the temporal std (8-bit levels);
    grey_noise_flat and grey_noise_edges: the grey one on flat pixels and on edges."""
    region = membrane_region(camera) > 0
    imgs = [np.asarray(f.rgb) for f in frames if f.rgb is not None]
    if len(imgs) < 2:
        return {}
    rgb = np.stack([im[region].astype(np.float32) for im in imgs])
    greys = np.stack([_grey(im) for im in imgs])
    gx, gy = gradient(np.ascontiguousarray(greys.mean(axis=0)))
    g = np.hypot(gx, gy)[region]
    sd = greys[:, region].std(axis=0)
    flat, edges = g < FLAT_GRADIENT, (g >= EDGE_GRADIENT[0]) & (g < EDGE_GRADIENT[1])
    return {
        "rgb_noise": _rms(rgb.std(axis=0)),
        "grey_noise": _rms(sd),
        "grey_noise_flat": _rms(sd[flat]) if flat.any() else float("nan"),
        "grey_noise_edges": _rms(sd[edges]) if edges.any() else float("nan"),
    }


def measure(frames: Sequence[Frame], camera: Camera, flow: bool = True) -> SensorStats:
    """All statistics of untouched ``frames`` seen by ``camera`` (pose: camera -> mesh)."""
    frames = list(frames)
    if len(frames) < 3:
        raise ValueError(f"need at least 3 untouched frames, got {len(frames)}")
    if any(f.depth is None for f in frames):
        raise ValueError("every frame needs a depth image (an oracle scene renders none)")
    kw: dict = dict(depth_stats([np.asarray(f.depth) for f in frames], camera))
    if flow and all(f.rgb is not None for f in frames):
        kw.update(flow_stats(frames, camera))
    if all(f.rgb is not None for f in frames):
        kw.update(rgb_stats(frames, camera))
    return SensorStats(**kw)


# ---------------------------------------------------------------------- the two sides
def real_frames(path: str, indices: Sequence[int] | None = None) -> tuple[list[Frame], Camera]:
    """Untouched frames of a real recording and its camera (pose from the recording)."""
    from bubble_rt.io.recordings import open_recording

    rec = open_recording(path)
    idx = range(len(rec)) if indices is None else indices
    return [rec[i] for i in idx], rec.camera


#: A real frame is taken with the arm still when the arm's joints moved less than this (rad)
#: from the frame before and to the frame after (at rest the readings step by 4-6e-5 rad; a
#: moving arm by 1e-3 to 1e-1).
ARM_STILL_RAD = 1e-4


def arm_still(path: str) -> list[int]:
    """The frames of a Punyo recording (its data.json joint angles) taken with the arm still
    (:data:`ARM_STILL_RAD`); empty when the recording has no joint angles."""
    from bubble_rt.io.recordings import open_recording

    rec = open_recording(path)
    rows = getattr(rec, "rows", None)
    if not rows:
        return []
    q = np.array([np.asarray(r[2], dtype=np.float64) for r in rows[: len(rec)]])
    step = np.linalg.norm(np.diff(q, axis=0), axis=1)
    before = np.concatenate([[0.0], step])
    after = np.concatenate([step, [0.0]])
    return [int(i) for i in np.flatnonzero((before <= ARM_STILL_RAD) & (after <= ARM_STILL_RAD))]


def sim_frames(
    n: int = 12,
    effects: dict[str, dict[str, float]] | None = None,
    camera_pose: NDArray[np.float64] | None = None,
    seed: int = 0,
    sim_nodes: int = 800,
    physics: object | None = None,
    texture: str = SIM_BUBBLE.texture,
) -> tuple[list[Frame], Camera]:
    """``n`` untouched simulated frames (the reference state, fresh noise each) and the camera.

    ``effects``: the camera effects and their parameters (default: the D405 effects with
    EFFECT_DEFAULTS); ``camera_pose``: 4 x 4 camera -> mesh (default: the scene's default,
    straight below the dome; pass :func:`bubble_rt.io.punyo.punyo_pose` for the Punyo's view);
    ``physics``: a physics backend for the Simulator (default: the real one, cached);
    ``texture``: the membrane's pattern (``bubble_rt.sim.texture.PATTERNS``; "punyo" for the
    Punyo's).
    """
    from bubble_rt.sim.scene import (
        EFFECT_DEFAULTS,
        Keyframe,
        Scene,
        SensorSpec,
        TrajectorySpec,
        _parse_effects,
    )
    from bubble_rt.sim.simulator import Simulator

    eff = effects if effects is not None else {k: {} for k in D405_EFFECTS}
    for k in eff:
        if k not in EFFECT_DEFAULTS:
            raise ValueError(f"unknown effect {k!r}")
    pose = None
    if camera_pose is not None:
        pose = tuple(tuple(float(x) for x in r) for r in np.asarray(camera_pose))
    scene = Scene(
        name="untouched",
        # One frame with the indenter 30 mm clear of the dome: the physics is the inflation.
        trajectory=TrajectorySpec(keyframes=(Keyframe(t=0.0, at=(0.0, 0.0), depth=-0.03),)),
        frames=1,
        seed=seed,
        sensor=SensorSpec(camera_pose=pose, sim_nodes=sim_nodes, texture=texture),
        effects=_parse_effects(eff),
    )
    sim = Simulator(scene, physics=physics)  # type: ignore[arg-type]
    return sim.reference_frames(n), sim.camera


#: The camera effects that model a D405 (the dataset's and the demo's image effects).
D405_EFFECTS: tuple[str, ...] = ("depth_noise", "depth_dropouts", "depth_jumps", "rgb_noise")


def table(real: SensorStats, sims: dict[str, SensorStats]) -> str:
    """A Markdown table: one row per statistic, one column per set of frames."""
    cols = {"real": real, **sims}
    rows: list[tuple[str, list[str]]] = []

    def add(name: str, fn: object) -> None:
        rows.append((name, [fn(s) for s in cols.values()]))  # type: ignore[operator]

    for z in (62.5, 72.5, 82.5, 92.5, 97.5):
        add(f"depth noise at {z:.0f} mm (mm)", lambda s, z=z: f"{s.noise_at(z):.3f}")
    add("depth noise, all pixels, RMS (mm)", lambda s: f"{s.noise_median_mm:.3f}")
    for i, scale in enumerate(SMOOTH_SCALES_M):
        add(
            f"depth noise smoothed over {scale * 1e3:.0f} mm, RMS (mm)",
            lambda s, i=i: f"{s.smoothed_noise_mm[i]:.4f}",
        )
    add("typical depth step (mm)", lambda s: f"{s.step_mm:.3f}")
    add("c in sigma = c z^2 (1/m)", lambda s: f"{s.noise_c:.4f}")
    add("fitted p in sigma ~ z^p", lambda s: f"{s.noise_exponent:.1f}")
    add("hole fraction", lambda s: f"{s.hole_fraction:.3f}")
    for z in (52.5, 57.5, 62.5, 72.5, 82.5, 92.5):
        add(f"holes at {z:.0f} mm", lambda s, z=z: f"{s.hole_at(z):.3f}")
    add(
        "hole blob px (median / p90)",
        lambda s: f"{s.hole_blob_px[0]:.0f} / {s.hole_blob_px[1]:.0f}",
    )
    add("hole persistence (IoU)", lambda s: f"{s.hole_persistence:.2f}")
    add("jumps > 2 mm per frame per 1e5 px", lambda s: f"{s.jump_rate:.1f}")
    add("jumps per hole-edge pixel (%)", lambda s: f"{100 * s.jump_edge_rate:.2f}")
    add(f"jumps under {NEAR_RANGE_M * 1e3:.0f} mm per 1e5 px", lambda s: f"{s.jump_near_rate:.1f}")
    add(
        "jumps behind the surface, all / near",
        lambda s: f"{s.jump_behind:.2f} / {s.jump_near_behind:.2f}",
    )
    for z in (57.5, 72.5, 87.5):
        add(f"jumps at {z:.0f} mm per 1e5 px", lambda s, z=z: f"{s.jump_at(z):.1f}")
    add("jump size p50 / p95 / max (mm)", lambda s: "{:.1f} / {:.1f} / {:.1f}".format(*s.jump_mm))
    add(
        "jumps in holes / at depth edges",
        lambda s: f"{s.jump_in_holes:.2f} / {s.jump_at_edges:.2f}",
    )
    add(
        "flow at nodes, RMS / median (px)",
        lambda s: f"{s.flow_rms_px:.3f} / {s.flow_median_px:.3f}",
    )
    add("flow at textured nodes, RMS (px)", lambda s: f"{s.flow_textured_px:.3f}")
    add("the same less each frame's mean (px)", lambda s: f"{s.flow_textured_detrended_px:.3f}")
    add("texture-less nodes (share)", lambda s: f"{s.textureless_share:.2f}")
    add("nodes lifted > 2 mm per frame", lambda s: f"{s.node_jump_rate:.2f}")
    add("node displacement RMS (mm)", lambda s: f"{s.node_u_rms_mm:.3f}")
    add("image gradient at textured nodes, median (levels/px)", lambda s: f"{s.node_gradient:.1f}")
    add("RGB noise (levels)", lambda s: f"{s.rgb_noise:.2f}")
    add("grey noise (levels)", lambda s: f"{s.grey_noise:.2f}")
    add(
        "grey noise on flat areas / on edges (levels)",
        lambda s: f"{s.grey_noise_flat:.2f} / {s.grey_noise_edges:.2f}",
    )
    head = "| statistic | " + " | ".join(cols) + " |\n|---|" + "---|" * len(cols) + "\n"
    return head + "\n".join(f"| {n} | " + " | ".join(v) + " |" for n, v in rows)


def main() -> None:  # pragma: no cover - a report, run by hand (docs/sim-noise.md)
    import argparse

    from bubble_rt.io.punyo import punyo_pose

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--real", default="../shared/data/punyo-demo-0")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--no-flow", action="store_true")
    ap.add_argument(
        "--effects",
        default=None,
        help="the simulated camera effects as JSON {name: {param: value}} (default: the D405 "
        "effects with EFFECT_DEFAULTS)",
    )
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    eff = None if a.effects is None else json.loads(a.effects)
    frames, cam = real_frames(a.real, range(a.frames))
    real = measure(frames, cam, flow=not a.no_flow)
    still = [i for i in arm_still(a.real) if i < a.frames]
    sims = {}
    views = (
        ("sim, Punyo view", punyo_pose(), PUNYO_BUBBLE.texture),
        ("sim, default view", None, SIM_BUBBLE.texture),
    )
    for name, pose, texture in views:
        f, c = sim_frames(a.frames, effects=eff, camera_pose=pose, seed=a.seed, texture=texture)
        sims[name] = measure(f, c, flow=not a.no_flow)
    print(table(real, sims))
    if not a.no_flow and len(still) >= 2:
        st = flow_stats(real_frames(a.real, still)[0], cam)
        print(
            f"\nreal, frames {still[0]}-{still[-1]} (the arm still): flow at textured nodes, "
            f"less each frame's mean, {st['flow_textured_detrended_px']:.3f} px"
        )


if __name__ == "__main__":  # pragma: no cover
    main()
