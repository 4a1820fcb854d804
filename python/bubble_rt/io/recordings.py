"""Readers for recorded sensor data; both layouts yield :class:`bubble_rt.frames.Frame`.

Punyo layout (the public implementation's recordings, e.g. ../shared/data/punyo-demo-0)::

    RECORDING/
      expand/rgb_<i>.npy       480 x 640 x 3 uint8, stored in RGB order
      expand/pc_<i>.npy        307200 x 3 float32 organised point cloud, camera frame, metres
                               ((0, 0, 0) = no reading; saturated points near 6.55 m)
      expand/pressure_<i>.npy  float64 scalar, hPa
      data.json                optional rows [unix_time_s, pressure_hPa, [6 joints], [6-D wrench]]

  The stored channel order is RGB: the interior is lit green and the stored first channel is
  the weak one (means about R 32, G 142, B 81), which matches green light, not a BGR swap
  that would make the white label and the lit membrane yellow. Intrinsics come from a
  least-squares pinhole fit of the point cloud (u = fx x/z + cx, v = fy y/z + cy), not from the
  README or the original code. The pose (camera -> mesh frame) is :func:`punyo_pose`.

  Footprint placement: the public implementation's own (camera frame rotated 25 degrees about
  its y axis, rim plane at z = 0.054 m, footprint centre at x = 0.04025 m, read off its
  reference mesh), checked against the data rather than trusted: its 390-node mesh lies on
  the observed cloud (median 0.25 mm), and the medium preset fitted with this pose domes to
  30.5 mm (public mesh 30.7 mm) with all nodes on the observed surface. Estimating the pose
  from the cloud with a paraboloid dome model was tried and rejected: the inflated shape is
  not a paraboloid and the fit drifts by several mm and degrees even on the public mesh.
  On top of that the in-plane placement is derived from the data when the recording is opened
  (:func:`bubble_rt.estimation.fitting.centre_pose` on frame 0): the apex of a quadratic fitted to the
  top of the observed dome is moved over the footprint centre and its long axis onto mesh x
  (on the demo recording a correction of about 0.3 mm and under a degree). Pass ``pose=`` to
  :func:`open_recording` for another sensor.

PNG folder layout (documented here; written by :func:`write_png_recording`)::

    RECORDING/
      camera.json       {"fx", "fy", "cx", "cy", "width", "height", "depth_scale",
                         optional "distortion" [k1, k2, p1, p2, k3], optional "pose" 4 x 4}
      frames.csv        header "t,pressure_pa" optionally followed by
                        ",fx,fy,fz,tx,ty,tz" (wrench, N and N m); one row per frame, in order
      rgb_0000.png      8-bit colour (standard PNG channel order)
      depth_0000.png    16-bit single channel; metres = value * depth_scale, 0 = invalid
"""

from __future__ import annotations

import csv
import json
import re
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bubble_rt._validate import PathError, regular_file
from bubble_rt.camera import Camera
from bubble_rt.frames import Frame, FrameError, FrameFault, tolerant
from bubble_rt.io.punyo import punyo_pose


def fit_intrinsics(points: NDArray, width: int, height: int) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of an organised (H*W x 3) point cloud by a linear least-squares fit."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] != width * height:
        raise FrameError(f"point cloud has {p.shape[0]} points, expected {width} x {height}")
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(p).all(axis=1) & (p[:, 2] > 1e-3) & (p[:, 2] < 2.0)
    if ok.sum() < 100:
        raise FrameError("point cloud has too few valid points to fit intrinsics")
    v, u = np.divmod(np.flatnonzero(ok), width)
    x = p[ok, 0] / p[ok, 2]
    y = p[ok, 1] / p[ok, 2]
    fx, cx = np.linalg.lstsq(np.column_stack([x, np.ones_like(x)]), u, rcond=None)[0]
    fy, cy = np.linalg.lstsq(np.column_stack([y, np.ones_like(y)]), v, rcond=None)[0]
    return float(fx), float(fy), float(cx), float(cy)


def _regular(path: Path) -> Path:
    """``path`` if it is a regular file (symlinks followed), so opening it cannot block (FIFO)
    or never end (a device): FileNotFoundError if missing, FrameError if not regular."""
    if not path.exists():
        raise FileNotFoundError(f"{path} missing")
    try:
        return regular_file("recording", path)
    except PathError as exc:
        raise FrameError(str(exc)) from None


#: The Punyo layout's file prefixes and the part of a frame each holds.
_NPY_KINDS = {"rgb": "colour", "pc": "depth", "pressure": "pressure"}


def _load_npy(path: Path, mmap_mode: Any = None) -> Any:
    """np.load naming the file when it is missing, truncated or not an .npy file."""
    kind = _NPY_KINDS.get(path.name.split("_")[0], "frame")
    try:
        return np.load(_regular(path), mmap_mode=mmap_mode, allow_pickle=False)
    except FileNotFoundError:
        raise FrameError(f"{path}: missing", kind) from None
    except FrameError as exc:
        raise FrameError(str(exc), kind) from None
    except Exception as exc:
        raise FrameError(
            f"{path}: unreadable, damaged or truncated ({type(exc).__name__}: {exc})", kind
        ) from None


class Recording:
    """A recorded sequence: ``len``, iteration and indexing yield Frames.

    Attributes:
        path: the recording folder.
        camera: Camera (derived intrinsics, pose into the mesh frame).
        wrenches: n x 6 recorded wrenches (N, N m) or None.
        layout: "punyo" or "png".
    """

    layout = ""

    def __init__(self, path: Path, camera: Camera, wrenches: NDArray | None) -> None:
        self.path = path
        self.camera = camera
        self.wrenches = wrenches

    def __len__(self) -> int:
        raise NotImplementedError

    def _load(self, i: int) -> Frame:
        raise NotImplementedError

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError("recordings are indexed by int")
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range 0..{n - 1}")
        return self._load(int(i))

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self._load(i)

    def frames(self, faults: bool = True) -> Iterator[Frame | FrameFault]:
        """Every frame in order; a frame that cannot be read becomes a :class:`FrameFault`
        (with ``faults``; otherwise it is skipped) and reading goes on with the next one."""
        for i in range(len(self)):
            f = tolerant(i, f"{self.path.name} frame {i}", partial(self._checked, i))
            if faults or isinstance(f, Frame):
                yield f

    def _checked(self, i: int) -> Frame:
        return self._load(i).validate(self.camera)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, frames={len(self)})"


class PunyoRecording(Recording):
    """The public implementation's layout (see module docstring)."""

    layout = "punyo"

    def __init__(
        self,
        path: Path,
        max_depth_m: float = 0.5,
        pose: NDArray[np.float64] | None = None,
        centre_from_data: bool = True,
    ) -> None:
        exp = path / "expand"
        idx = sorted(
            int(m.group(1))
            for f in exp.glob("rgb_*.npy")
            if (m := re.fullmatch(r"rgb_(\d+)\.npy", f.name))
        )
        if not idx:
            raise FileNotFoundError(f"{exp}: no rgb_<i>.npy files")
        if idx != list(range(len(idx))):
            raise FrameError(f"{exp}: frame numbers are not contiguous from 0")
        self._n = len(idx)
        self._exp = exp
        self.max_depth_m = max_depth_m
        self.rows: list[Any] | None = None
        wrenches = None
        dj = path / "data.json"
        if dj.exists():
            rows = json.loads(_regular(dj).read_text())
            if len(rows) < self._n:
                raise FrameError(f"{dj}: {len(rows)} rows for {self._n} frames")
            self.rows = rows
            wrenches = np.array([np.asarray(r[3], dtype=np.float64) for r in rows[: self._n]])
        rgb0 = _load_npy(exp / "rgb_0.npy", mmap_mode="r")
        if rgb0.ndim != 3 or rgb0.shape[2] != 3:
            raise FrameError(f"{exp / 'rgb_0.npy'}: rgb must be H x W x 3, got {rgb0.shape}")
        h, w = int(rgb0.shape[0]), int(rgb0.shape[1])
        fx, fy, cx, cy = fit_intrinsics(_load_npy(exp / "pc_0.npy"), w, h)
        camera = Camera(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h)
        camera = camera.with_pose(punyo_pose() if pose is None else np.asarray(pose))
        super().__init__(path, camera, wrenches)
        #: "centred" when the in-plane placement was derived from the data, else why not.
        self.placement = "given pose" if pose is not None else "punyo_pose"
        if centre_from_data:
            from bubble_rt.estimation.fitting import centre_pose

            # In-plane placement from the data: the observed dome's apex over the footprint
            # centre, its long axis along x (the rim plane itself stays punyo_pose's).
            try:
                self.camera = centre_pose(camera, np.asarray(self._load(0).depth))
                self.placement = "centred"
            except FrameError as exc:
                self.placement += f" (not centred: {exc})"

    def __len__(self) -> int:
        return self._n

    def _load(self, i: int) -> Frame:
        rgb = _load_npy(self._exp / f"rgb_{i}.npy")
        pc = _load_npy(self._exp / f"pc_{i}.npy")
        pressure = _load_npy(self._exp / f"pressure_{i}.npy")
        if rgb.shape != (self.camera.height, self.camera.width, 3) or rgb.dtype != np.uint8:
            raise FrameError(
                f"{self._exp / f'rgb_{i}.npy'}: {' x '.join(map(str, rgb.shape))} {rgb.dtype}, "
                f"expected {self.camera.height} x {self.camera.width} x 3 uint8",
                "colour",
            )
        if np.size(pressure) != 1 or not np.isfinite(np.asarray(pressure, dtype=float)).all():
            raise FrameError(
                f"{self._exp / f'pressure_{i}.npy'}: not a finite scalar: {pressure}", "pressure"
            )
        t = float(i)
        wrench = None
        meta: dict[str, Any] = {"source": str(self.path)}
        if self.rows is not None:
            row = self.rows[i]
            t = float(row[0])
            meta["joints"] = [float(q) for q in row[2]]
            wrench = np.asarray(row[3], dtype=np.float64)
        return Frame.from_pointcloud(
            np.ascontiguousarray(rgb),
            pc,
            float(pressure),
            self.camera,
            pressure_unit="hPa",
            max_depth_m=self.max_depth_m,
            t=t,
            t_pressure=t,
            wrench=wrench,
            index=i,
            meta=meta,
        )


class PngRecording(Recording):
    """A folder of PNG images with camera.json and frames.csv (see module docstring)."""

    layout = "png"

    def __init__(self, path: Path) -> None:
        cj = path / "camera.json"
        if not cj.exists():
            raise FileNotFoundError(f"{cj} missing (PNG recordings need camera intrinsics)")
        c = json.loads(_regular(cj).read_text())
        try:
            self.depth_scale = float(c["depth_scale"])
            kwargs: dict[str, Any] = {k: c[k] for k in ("fx", "fy", "cx", "cy")}
            kwargs.update(width=int(c["width"]), height=int(c["height"]))
        except KeyError as exc:
            raise FrameError(f"{cj}: missing key {exc}") from exc
        if "distortion" in c:
            kwargs["distortion"] = tuple(c["distortion"])
        camera = Camera(**kwargs)
        if "pose" in c:
            camera = camera.with_pose(np.asarray(c["pose"], dtype=np.float64))
        with open(_regular(path / "frames.csv"), newline="") as fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader)]
            rows = [[float(x) for x in r] for r in reader if r]
        if header[:2] != ["t", "pressure_pa"]:
            raise FrameError(f"{path / 'frames.csv'}: header must start with t,pressure_pa")
        has_wrench = header[2:8] == ["fx", "fy", "fz", "tx", "ty", "tz"]
        self._rows = rows
        wrenches = np.array([r[2:8] for r in rows]) if has_wrench else None
        for i in range(len(rows)):
            for kind in ("rgb", "depth"):
                _regular(path / f"{kind}_{i:04d}.png")
        super().__init__(path, camera, wrenches)

    def __len__(self) -> int:
        return len(self._rows)

    def _load(self, i: int) -> Frame:
        import cv2

        bgr = cv2.imread(str(self.path / f"rgb_{i:04d}.png"), cv2.IMREAD_COLOR)
        depth = cv2.imread(str(self.path / f"depth_{i:04d}.png"), cv2.IMREAD_UNCHANGED)
        if bgr is None or depth is None:
            raise FrameError(f"{self.path}: cannot read frame {i} images")
        row = self._rows[i]
        return Frame.from_uint16(
            np.ascontiguousarray(bgr[:, :, ::-1]),
            depth,  # type: ignore[arg-type]
            self.depth_scale,
            row[1],
            pressure_unit="Pa",
            camera=self.camera,
            t=row[0],
            t_pressure=row[0],
            wrench=None if self.wrenches is None else self.wrenches[i],
            index=i,
            meta={"source": str(self.path)},
        )


def open_recording(
    path: str | Path,
    pose: NDArray[np.float64] | None = None,
    centre_from_data: bool = True,
    **bag_options: Any,
) -> Recording:
    """Open a recording, detecting its layout (Punyo .npy, PNG folder, ROS 2 bag or the
    project's own MCAP file).

    ``pose`` (4 x 4 camera -> mesh) overrides the Punyo layout's default :func:`punyo_pose`;
    ``centre_from_data`` refines its in-plane placement from frame 0 (Punyo layout, bags).
    A ROS 2 bag (folder with metadata.yaml, .db3, or ros2-profile .mcap) opens as
    :class:`bubble_rt.io.rosbag.BagRecording`; ``bag_options`` (``topics``, ``depth_unit``,
    ...) go to it.
    """
    p = Path(path)
    # ---- ROS 2 bags (bubble_rt.io.rosbag) ----
    from bubble_rt.io.rosbag import BagRecording, is_rosbag

    if is_rosbag(p):
        opts = {k: v for k, v in bag_options.items() if v is not None}
        return BagRecording(p, pose=pose, centre_from_data=centre_from_data, **opts)  # type: ignore[return-value]
    # ---- end ROS 2 bags ----
    # ---- the project's own MCAP recordings (bubble_rt.io.mcap; a bag was caught above) ----
    if p.exists() and not p.is_dir():  # a file layout: never open a FIFO or a device
        try:
            regular_file("recording", p)
        except PathError as exc:
            raise FrameError(str(exc)) from None
    if p.suffix == ".mcap" and p.is_file():
        from bubble_rt.io.mcap import McapRecording

        return McapRecording(p)  # type: ignore[return-value]
    # ---- end MCAP ----
    if not p.is_dir():
        raise FileNotFoundError(f"recording folder not found: {p}")
    if (p / "expand").is_dir():
        return PunyoRecording(p, pose=pose, centre_from_data=centre_from_data)
    if (p / "frames.csv").exists():
        return PngRecording(p)
    raise FrameError(
        f"{p}: neither a Punyo recording (expand/), a PNG folder (frames.csv) nor a ROS 2 bag "
        "(metadata.yaml)"
    )


def write_png_recording(
    path: str | Path,
    frames: list[Frame],
    camera: Camera,
    depth_scale: float = 1e-4,
) -> Path:
    """Write frames in the PNG folder layout (for fixtures and exports)."""
    import cv2

    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    cam: dict[str, Any] = dict(
        fx=camera.fx,
        fy=camera.fy,
        cx=camera.cx,
        cy=camera.cy,
        width=camera.width,
        height=camera.height,
        depth_scale=depth_scale,
        distortion=list(camera.distortion),
        pose=camera.pose_matrix.tolist(),
    )
    (p / "camera.json").write_text(json.dumps(cam, indent=1))
    has_wrench = all(f.wrench is not None for f in frames)
    with open(p / "frames.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            ["t", "pressure_pa"] + (["fx", "fy", "fz", "tx", "ty", "tz"] if has_wrench else [])
        )
        for i, f in enumerate(frames):
            if f.rgb is None or f.depth is None:
                raise FrameError(f"frame {i}: rgb and depth are needed for the PNG layout")
            w.writerow([f.t, f.pressure_pa] + (list(f.wrench) if has_wrench else []))  # type: ignore[arg-type]
            cv2.imwrite(str(p / f"rgb_{i:04d}.png"), np.ascontiguousarray(f.rgb[:, :, ::-1]))
            raw = np.clip(np.rint(f.depth / depth_scale), 0, 65535).astype(np.uint16)
            cv2.imwrite(str(p / f"depth_{i:04d}.png"), raw)
    return p
