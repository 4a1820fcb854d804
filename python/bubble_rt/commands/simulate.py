"""`bubble-rt simulate SCENE -o PATH`: simulate a scene and write a recording (.npz).

Recording layout (NumPy .npz, one array per key; F frames delivered, M simulation nodes):
  format                      str "bubble_rt.sim.npz/1"
  scene_json                  str, the validated scene (JSON)
  camera_K (3 x 3), camera_size (2: width, height), camera_pose (4 x 4 camera-to-mesh),
  camera_distortion (5)
  index (F int64), t (F s), t_pressure (F s), pressure_pa (F, absolute, as the sensor read it)
  rgb (F x H x W x 3 uint8), depth (F x H x W float32 m, 0 invalid)  -- absent for "oracle"
  reference_rgb, reference_depth, reference_pressure_pa, reference_t  -- untouched tare frames
  pressure_stream_t, pressure_stream_pa  -- every pressure reading (rates.pressure_hz)
  truth_indenter_pose (F x 4 x 4), truth_net_force (F x 3 N), truth_pressure_pa (F),
  truth_node_forces (F x M x 3 N), truth_contact (F x M bool), truth_vertices (F x M x 3 m),
  truth_converged (F bool), sim_reference_vertices (M x 3), sim_triangles (T x 3)
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

HELP = "simulate a scene (built-in name or TOML file) and write a recording"
FORMAT = "bubble_rt.sim.npz/1"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", help="built-in scene name (e.g. demo) or path to a scene TOML")
    parser.add_argument("-o", "--output", required=True, help="recording path (.npz)")
    parser.add_argument("--seed", type=int, default=None, help="override the scene's seed")
    parser.add_argument("--frames", type=int, default=None, help="override the frame count")
    parser.add_argument(
        "--reference", type=int, default=5, help="untouched tare frames to include (default 5)"
    )
    parser.add_argument("--no-cache", action="store_true", help="ignore the physics cache")
    parser.add_argument("--compress", action="store_true", help="write a compressed .npz")


def write_recording(
    path: str | Path, sim: Any, frames: list[Any], reference: list[Any], compress: bool = False
) -> Path:
    """Write frames (and the simulator's camera, pressure stream, truth) in the npz layout."""
    import numpy as np

    path = Path(path)
    cam = sim.camera
    readings = sim.pressure_readings()
    out: dict[str, Any] = {
        "format": np.array(FORMAT),
        "scene_json": np.array(json.dumps(asdict(sim.scene), default=str)),
        "camera_K": cam.K,
        "camera_size": np.array([cam.width, cam.height]),
        "camera_pose": cam.pose_matrix,
        "camera_distortion": np.asarray(cam.distortion),
        "index": np.array([f.index for f in frames], np.int64),
        "t": np.array([f.t for f in frames]),
        "t_pressure": np.array([f.t_pressure for f in frames]),
        "pressure_pa": np.array([f.pressure_pa for f in frames]),
        "pressure_stream_t": readings.t,
        "pressure_stream_pa": readings.pressure_pa,
    }
    if frames and frames[0].rgb is not None:
        out["rgb"] = np.stack([f.rgb for f in frames])
        out["depth"] = np.stack([f.depth for f in frames])
    if reference and reference[0].rgb is not None:
        out["reference_rgb"] = np.stack([f.rgb for f in reference])
        out["reference_depth"] = np.stack([f.depth for f in reference])
    out["reference_pressure_pa"] = np.array([f.pressure_pa for f in reference])
    out["reference_t"] = np.array([f.t for f in reference])
    tr = [f.truth for f in frames]
    out["truth_indenter_pose"] = np.array([g.indenter_pose for g in tr]).reshape(-1, 4, 4)
    out["truth_net_force"] = np.array([g.net_force for g in tr]).reshape(-1, 3)
    out["truth_pressure_pa"] = np.array([g.pressure_pa for g in tr])
    out["truth_node_forces"] = np.array([g.node_forces for g in tr])
    out["truth_contact"] = np.array([g.contact for g in tr])
    out["truth_vertices"] = np.array([g.sim_vertices for g in tr])
    out["truth_converged"] = np.array([g.converged for g in tr], bool)
    out["sim_reference_vertices"] = sim.run.ref_vertices
    out["sim_triangles"] = sim.run.triangles
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        (np.savez_compressed if compress else np.savez)(fh, **out)
    return path


def run(args: argparse.Namespace) -> int:
    import sys

    from tqdm import tqdm

    from bubble_rt._validate import CONFIG_MAX_BYTES, output_file, regular_file
    from bubble_rt.sim.scene import SceneError, load_scene
    from bubble_rt.sim.simulator import Simulator, progress_bar

    output_file("--output", args.output)
    if Path(args.scene).exists():  # a scene TOML is read whole: a regular file, capped
        regular_file("scene", args.scene, CONFIG_MAX_BYTES)
    try:
        scene = load_scene(args.scene)
    except SceneError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    changes: dict[str, Any] = {}
    if args.seed is not None:
        changes["seed"] = args.seed
    if args.frames is not None:
        if args.frames < 1:
            print("error: --frames must be at least 1", file=sys.stderr)
            return 2
        changes["frames"] = args.frames
    scene = scene.with_changes(**changes)
    sim = Simulator(scene, use_cache=not args.no_cache, progress=progress_bar("physics"))
    _ = sim.run
    frames = list(tqdm(sim.frames(), total=scene.frames, desc="render", unit="frame"))
    reference = sim.reference_frames(args.reference)
    path = write_recording(args.output, sim, frames, reference, compress=args.compress)
    bad = sum(not f.truth.converged for f in frames)
    print(f"wrote {len(frames)} frames of scene {scene.name!r} to {path}")
    if bad:
        print(f"warning: {bad} frame(s) did not converge (truth_converged)", file=sys.stderr)
    return 0


def load_recording(path: str | Path) -> tuple[Any, list[Any], list[Any]]:
    """Read a recording written by ``write_recording``: (camera, frames, reference frames).

    Frames carry a ``GroundTruth`` rebuilt from the stored arrays (``displace`` and
    ``contact_mask`` work as in the simulator)."""
    import numpy as np

    from bubble_rt.camera import Camera
    from bubble_rt.frames import Frame
    from bubble_rt.sim.truth import GroundTruth, SurfaceLocator

    with np.load(Path(path), allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    if str(a.get("format")) != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} recording")
    K = a["camera_K"]
    w, h = (int(x) for x in a["camera_size"])
    cam = Camera(
        fx=float(K[0, 0]),
        fy=float(K[1, 1]),
        cx=float(K[0, 2]),
        cy=float(K[1, 2]),
        width=w,
        height=h,
        distortion=tuple(float(x) for x in a["camera_distortion"]),  # type: ignore[arg-type]
        pose=tuple(tuple(float(x) for x in r) for r in a["camera_pose"]),
    )
    ref_v, tris = a["sim_reference_vertices"], a["sim_triangles"]
    loc = SurfaceLocator(ref_v, tris)
    frames = []
    for i in range(len(a["index"])):
        truth = GroundTruth(
            indenter_pose=a["truth_indenter_pose"][i],
            net_force=a["truth_net_force"][i],
            node_forces=a["truth_node_forces"][i],
            pressure_pa=float(a["truth_pressure_pa"][i]),
            sim_vertices=a["truth_vertices"][i],
            sim_reference_vertices=ref_v,
            sim_triangles=tris,
            contact=a["truth_contact"][i],
            converged=bool(a["truth_converged"][i]),
            locator=loc,
        )
        frames.append(
            Frame(
                rgb=a["rgb"][i] if "rgb" in a else None,
                depth=a["depth"][i] if "depth" in a else None,
                pressure_pa=float(a["pressure_pa"][i]),
                t=float(a["t"][i]),
                t_pressure=float(a["t_pressure"][i]),
                truth=truth,
                index=int(a["index"][i]),
                meta={"source": str(path)},
            )
        )
    reference = []
    for k in range(len(a["reference_pressure_pa"])):
        reference.append(
            Frame(
                rgb=a["reference_rgb"][k] if "reference_rgb" in a else None,
                depth=a["reference_depth"][k] if "reference_depth" in a else None,
                pressure_pa=float(a["reference_pressure_pa"][k]),
                t=float(a["reference_t"][k]),
                index=k - len(a["reference_pressure_pa"]),
                meta={"source": str(path), "reference": True},
            )
        )
    return cam, frames, reference
