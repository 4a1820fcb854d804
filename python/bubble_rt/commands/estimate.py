"""`bubble-rt estimate`: run the force estimator over a recording, write per-frame JSON.

    bubble-rt estimate RECORDING --reference-frames 0-4 --mesh medium --json OUT
        [--flow dis_medium] [--flow-scale 1.0] [--frames 5-19] [--save-mesh mesh.vtk]

The reference is captured from the given untouched frames (default: the reference frames a
recording of this project holds, which its daemon captured, else frames 0-4; the JSON's
"reference_frames" then lists their negative indices); with a preset name for --mesh
("coarse" | "medium" | "fine") the preset is fitted to that reference's depth surface (a mesh
file is used as given: it must already be in the recording camera's mesh frame). Output JSON:
{"recording", "camera", "mesh", "flow", "reference_frames", "frames": [{index, t, net_force
(3, N, camera frame), net_force_mesh (3, N, mesh frame), contact_nodes, valid_node_fraction,
timings_ms, wrench (6 or null), solver_status, net_torque_mesh (3, N m, mesh frame, about its
origin, the forces at the displaced nodes: bubble_rt.wrench), patches [{centroid,
pressure_centroid (m), area (m^2), force (N), normal, peak_pressure (Pa), torque (N m, about
centroid), nodes}] (mesh frame)}]}.

RECORDING may be a ROS 2 bag (``--topics``, ``--depth-unit`` for it); ``--bag OUT`` also
writes the results as a rosbag2 (MCAP): geometry_msgs/WrenchStamped and sensor_msgs/PointCloud2
per frame (see :mod:`bubble_rt.io.rosbag`). ``--json`` or ``--bag`` (or both) is required.

A frame that cannot be read (or estimated), or a pressure reading that is not finite, is
skipped and the run goes on: the JSON lists each under "skipped" ({index, kind, where,
reason}; kind colour | depth | pressure | frame) with counts per kind in "skipped_counts",
and a line on stderr says how many. Exit status: 0 done (also with skipped frames),
2 bad arguments or a recording that cannot be opened, 3 (EXIT_NO_FRAME) no usable frame: every
reference frame or every frame to estimate was skipped, or the reference frames are refused
(the plausibility checks, or no membrane where the mesh is fitted; nothing is written).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from bubble_rt.estimation.names import IMAGE_FLOW_METHODS
from bubble_rt.frames import FaultTally, FrameFault

if TYPE_CHECKING:
    from bubble_rt.frames import Frame

#: Exit status when no usable frame is left, e.g. reference frames the plausibility checks
#: refuse (their pressure out of range, or a force read untouched: the message says what to
#: check; docs/daemon.md, "Degraded frames"). 0: done; 2: invalid arguments or input.
EXIT_NO_FRAME = 3

HELP = "run the force estimator over a recorded sequence and write per-frame results as JSON"

EPILOG = (
    "Bad frames (and non-finite pressure readings) are skipped and listed under 'skipped' in "
    "the JSON. Exit status: 0 done (also with skipped frames), 2 bad arguments or an "
    f"unreadable recording, {EXIT_NO_FRAME} no usable frame (every reference frame or every "
    "frame to estimate was skipped, or the reference frames are refused: see the message)."
)


def parse_frames(spec: str, n: int) -> list[int]:
    """Frame indices from "0-4", "0,2,5" or "3" (inclusive ranges), checked against n."""
    out: list[int] = []
    for part in spec.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-", 1)
            lo, hi = int(a), int(b)
            if hi < lo:
                raise ValueError(f"empty frame range {part!r}")
            out.extend(range(lo, hi + 1))
        else:
            out.append(int(part))
    if not out:
        raise ValueError(f"no frames in {spec!r}")
    bad = [i for i in out if not 0 <= i < n]
    if bad:
        raise ValueError(f"frame {bad[0]} out of range 0..{n - 1}")
    return out


#: The image-based flow methods (recordings carry no ground truth for "oracle").
FLOW_CHOICES = IMAGE_FLOW_METHODS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", help="recording (Punyo .npy layout, PNG folder or ROS 2 bag)")
    parser.add_argument(
        "--reference-frames",
        default=None,
        help="untouched frames for the reference (default: the reference an MCAP recording of "
        "this project holds, else 0-4)",
    )
    parser.add_argument(
        "--config",
        default=None,
        help="configuration TOML (config dump, calibrate output): estimator kind, mesh, "
        "parameters and flow settings; the flags below override it",
    )
    parser.add_argument(
        "--mesh", default=None, help="preset to fit (coarse|medium|fine) or a mesh file (medium)"
    )
    parser.add_argument("--json", default=None, help="output JSON file")
    # ---- ROS 2 bags (bubble_rt.io.rosbag) ----
    parser.add_argument("--bag", default=None, help="also write a rosbag2 (MCAP) folder here")
    parser.add_argument(
        "--topics", default=None, help="bag topics: color=..,depth=..,info=..,pressure=.. or /ns"
    )
    parser.add_argument(
        "--depth-unit", type=float, default=None, help="bag 16UC1 depth metres per count (0.001)"
    )
    # ---- end ROS 2 bags ----
    parser.add_argument(
        "--flow",
        default=None,
        choices=FLOW_CHOICES,
        help="optical flow method (default: FlowSettings' default)",
    )
    parser.add_argument("--flow-scale", type=float, default=None, help="flow image scale (0, 1]")
    parser.add_argument("--frames", default=None, help="frames to process (default: all)")
    parser.add_argument("--save-mesh", default=None, help="write the fitted mesh here")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


class _Stop(Exception):
    """Ends the run with an exit status and a message for stderr."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


def run(args: argparse.Namespace) -> int:
    import sys

    try:
        _run(args)
    except _Stop as stop:
        print(f"bubble-rt estimate: {stop}", file=sys.stderr)
        return stop.code
    return 0


def _run(args: argparse.Namespace) -> None:
    import sys

    from bubble_rt.frames import FrameError
    from bubble_rt.mesh import PRESET_NODES

    _check_outputs(args)
    cfg = _configuration(args)
    rec, ref_idx, todo, layout = _open(args)
    tally = FaultTally()
    for fault in getattr(rec, "reading_faults", []):  # bag pressure readings skipped
        tally.add(fault)
    for note in (getattr(rec, "topics_note", ""), getattr(rec, "lost", "")):
        if note:  # topics paired across namespaces; what a cut bag lost
            print(f"bubble-rt estimate: {note}", file=sys.stderr)
    if ref_idx:
        ref_frames = [f for _, f in _pick(rec, ref_idx, tally)]
    else:  # the reference the recording's daemon captured, before its stream
        ref_frames = rec.reference_frames(sys.maxsize)
        ref_idx = [f.index for f in ref_frames]
    if not ref_frames:
        raise _Stop(
            EXIT_NO_FRAME,
            f"no usable reference frame ({tally.summary()}): "
            + "; ".join(str(f) for f in tally.faults[-len(ref_idx) :]),
        )
    from bubble_rt.estimation.pipeline import Pipeline, capture_settings

    settings = capture_settings(cfg, realtime=False, layout=layout)
    settings["fit"] = settings["fit"] and cfg.estimator.mesh in PRESET_NODES
    try:
        pipeline = Pipeline.capture(ref_frames, rec.camera, **settings)
    except FrameError as exc:  # plausibility.ReferenceRefused; a mesh that cannot be fitted
        raise _Stop(
            EXIT_NO_FRAME,
            f"the reference frames are not usable: {exc} (camera pose from "
            f"{getattr(rec, 'placement', layout)})",
        ) from None
    results = _estimate(args, rec, pipeline, todo, tally)
    if tally.total:
        print(f"bubble-rt estimate: {tally.summary()}", file=sys.stderr)
    if not results:
        raise _Stop(EXIT_NO_FRAME, f"no usable frame to estimate ({tally.summary()})")
    if args.save_mesh:
        pipeline.mesh.save(args.save_mesh)
    frames_out = _write_frames(args, pipeline.mesh, rec.camera, results)
    if args.json:
        import json
        from pathlib import Path

        out = _summary(args, cfg, rec, layout, pipeline, settings, ref_idx)
        out.update(
            frames=frames_out,
            skipped=[f.as_dict() for f in tally.faults],
            skipped_counts=dict(tally.counts),
        )
        Path(args.json).write_text(json.dumps(out, indent=1))


def _check_outputs(args: argparse.Namespace) -> None:
    """Outputs refused before any work (a FIFO would block the final write)."""
    from pathlib import Path

    from bubble_rt._validate import PathError, output_file

    if not args.json and not args.bag:
        raise _Stop(2, "give --json OUT and/or --bag OUT")
    try:
        for option, out_path in (("--json", args.json), ("--save-mesh", args.save_mesh)):
            if out_path:
                output_file(option, out_path)
    except PathError as exc:
        raise _Stop(2, str(exc)) from None
    if args.bag and Path(args.bag).exists():
        raise _Stop(2, f"--bag: {args.bag} exists (a new folder is written)")


def _configuration(args: argparse.Namespace) -> Any:
    """The configuration with the command line's overrides; a mesh file is loaded now, so
    that a bad one is refused with its key before the recording is read."""
    from bubble_rt.config import ConfigError, DaemonConfig
    from bubble_rt.mesh import PRESET_NODES, Mesh

    try:
        cfg = DaemonConfig.load(args.config, "--config") if args.config else DaemonConfig()
        cfg = cfg.with_overrides(
            **{"estimator.mesh": args.mesh, "flow.method": args.flow, "flow.scale": args.flow_scale}
        )
    except ConfigError as exc:
        raise _Stop(2, f"invalid configuration: {exc}") from None
    if cfg.estimator.mesh not in PRESET_NODES:
        try:
            Mesh.load(cfg.estimator.mesh)
        except (ValueError, OSError) as exc:  # MeshError, missing file
            key = "--mesh" if args.mesh else "estimator.mesh"
            raise _Stop(2, f"{key}: {exc}") from None
    return cfg


def _open(args: argparse.Namespace) -> tuple[Any, list[int], list[int], str]:
    """The recording, the reference frame positions (empty: the reference it holds), the
    positions to estimate, and its layout."""
    from bubble_rt.io.recordings import open_recording

    try:
        rec = open_recording(args.recording, topics=args.topics, depth_unit=args.depth_unit)
    except (ValueError, FileNotFoundError) as exc:  # FrameError, BagTopicError
        raise _Stop(2, str(exc)) from None
    n = len(rec)
    if n == 0:  # e.g. an MCAP file cut after its reference frames
        raise _Stop(EXIT_NO_FRAME, f"{args.recording}: no frame in the recording")
    try:
        # A recording of this project holds its daemon's reference: the frames it was
        # captured from, untouched even when the stream starts in contact.
        recorded = args.reference_frames is None and bool(getattr(rec, "has_reference", False))
        ref_idx = [] if recorded else parse_frames(args.reference_frames or "0-4", n)
        todo = parse_frames(args.frames, n) if args.frames else list(range(n))
    except ValueError as exc:
        raise _Stop(2, str(exc)) from None
    # (this project's MCAP recordings give the profile their daemon ran with, else "mcap")
    return rec, ref_idx, todo, getattr(rec, "layout", "mcap")


def _estimate(
    args: argparse.Namespace, rec: Any, pipeline: Any, todo: list[int], tally: FaultTally
) -> list[tuple[Frame, Any]]:
    """(frame, Estimate) of every frame to estimate that could be read and estimated; the
    others go to ``tally``."""
    from pathlib import Path

    import numpy as np
    from tqdm import tqdm

    from bubble_rt.frames import FrameError, fault_of

    results: list[tuple[Frame, Any]] = []
    bar = tqdm(total=len(todo), desc="estimate", unit="frame", disable=args.no_progress)
    for pos, frame in _pick(rec, todo, tally):
        bar.update(1)
        try:
            e = pipeline.process(frame)
            if not np.all(np.isfinite(np.asarray(e.net_force, dtype=np.float64))):
                raise FrameError("the estimate is not finite")
        except Exception as exc:  # one frame the estimator cannot take ends that frame only
            tally.add(fault_of(exc, pos, f"{Path(args.recording).name} frame {pos}"))
            continue
        results.append((frame, e))
    bar.close()
    return results


def _write_frames(
    args: argparse.Namespace, mesh: Any, camera: Any, results: list[tuple[Frame, Any]]
) -> list[dict[str, Any]]:
    """The frames' JSON records; with ``--bag``, the same frames into the bag."""
    import numpy as np

    from bubble_rt.wrench import PatchFinder

    bag = None
    if args.bag:
        from bubble_rt.io.bag_writer import BagWriter

        bag = BagWriter(args.bag)
    finder = PatchFinder(mesh)
    R = camera.pose_matrix[:3, :3]  # camera -> mesh rotation
    frames_out = []
    try:
        for frame, e in results:
            tau_mesh = finder.net_torque_of(e)
            if bag is not None:
                bag.write(
                    frame.t,
                    np.asarray(e.net_force, dtype=np.float64),
                    np.asarray(mesh.vertices) + np.nan_to_num(np.asarray(e.displacements)),
                    e.node_forces,
                    e.normal_pressure,
                    e.contact,
                    net_torque=tau_mesh,
                )
            frames_out.append(_frame_record(frame, e, finder, R, tau_mesh))
    finally:
        if bag is not None:
            bag.close()
    return frames_out


def _frame_record(frame: Frame, e: Any, finder: Any, R: Any, tau_mesh: Any) -> dict[str, Any]:
    """One frame's JSON record (see the module docstring)."""
    import numpy as np

    f_mesh = np.asarray(e.net_force, dtype=np.float64)
    patches = finder.patches_of(e)
    return {
        "index": int(frame.index),
        "t": float(frame.t),
        "net_force": (R.T @ f_mesh).tolist(),
        "net_force_mesh": f_mesh.tolist(),
        "contact_nodes": int(np.count_nonzero(e.contact)),
        "valid_node_fraction": float(e.valid_node_fraction),
        "degraded": bool(e.degraded_reasons),  # docs/daemon.md, "Degraded frames"
        "degraded_reasons": list(e.degraded_reasons),
        "timings_ms": {k: float(v) for k, v in e.timings_ms.items()},
        "wrench": None if frame.wrench is None else np.asarray(frame.wrench).tolist(),
        "solver_status": getattr(e.info, "status", None),
        "net_torque_mesh": tau_mesh.tolist(),
        "patches": [
            {
                "centroid": p.centroid.tolist(),
                "pressure_centroid": p.pressure_centroid.tolist(),
                "area": p.area,
                "force": p.force.tolist(),
                "normal": p.normal.tolist(),
                "peak_pressure": p.peak_pressure,
                "torque": p.torque.tolist(),
                "nodes": p.nodes.tolist(),
            }
            for p in patches
        ],
    }


def _summary(
    args: argparse.Namespace,
    cfg: Any,
    rec: Any,
    layout: str,
    pipeline: Any,
    settings: dict[str, Any],
    ref_idx: list[int],
) -> dict[str, Any]:
    """The JSON's header: recording, camera, mesh, flow, reference, topics."""
    from pathlib import Path

    from bubble_rt.mesh import PRESET_NODES

    mesh, cam = pipeline.mesh, rec.camera
    mesh_info: dict[str, Any] = (
        {"preset": cfg.estimator.mesh, "fitted": settings["fit"]}
        if cfg.estimator.mesh in PRESET_NODES
        else {"file": str(cfg.estimator.mesh), "fitted": False}
    )
    mesh_info.update(nodes=mesh.n_nodes, min_angle_deg=mesh.min_angle_deg())
    return {
        "recording": str(Path(args.recording).resolve()),
        "layout": layout,
        "camera": {
            "fx": cam.fx,
            "fy": cam.fy,
            "cx": cam.cx,
            "cy": cam.cy,
            "width": cam.width,
            "height": cam.height,
            "pose": cam.pose_matrix.tolist(),
        },
        "mesh": mesh_info,
        "flow": {"method": settings["flow"].method, "scale": settings["flow"].scale},
        "reference_frames": ref_idx,
        "reference_pressure_pa": pipeline.reference.pressure_pa,
        "ambient_pa": settings["config"].ambient_pa,
        "topics": getattr(rec, "topics", None),
        "lost": getattr(rec, "lost", ""),
    }


def _pick(rec: Any, positions: list[int], tally: FaultTally) -> Iterator[tuple[int, Frame]]:
    """(position, frame) of the recording's frames at ``positions``, in recording order, in one
    pass (every layout, bags and MCAP files included); a bad frame among them is added to
    ``tally`` and skipped. Positions count frames and frame faults alike (0..len(rec)-1)."""
    want = set(positions)
    last = max(want)
    it = rec.frames(faults=True)
    try:
        for pos, f in enumerate(it):
            if pos in want:
                if isinstance(f, FrameFault):
                    tally.add(f)
                else:
                    yield pos, f
            if pos >= last:
                break
    finally:
        close = getattr(it, "close", None)
        if close is not None:
            close()
