"""The real press's membrane away from the load, against the simulated Punyo pressing alike.

Tracks the hold frames (26-30) of ``../shared/data/punyo-demo-0-press`` (reference 0-4) and
two simulated presses of the Punyo bubble (``profile = "punyo"``: the built-in ``punyo``
scene's 10.4 mm sphere, which ``bubble_rt.eval.press_physics`` matches to the real dent, at the
real dent's centre; friction 0.5, gas compression and the D405 effects; along the surface
normal, and tilted ``--tilt`` degrees towards +x as the real press leans), all on the fitted
medium mesh with the Punyo profile. For each it prints, by distance from the load's centre (the deepest node):

- the tracked normal displacement ``U . n`` (mm, outward positive): the dent and, beyond it,
  the membrane's bulge under the pressure rise;
- the mean normal part of the lasso's correction ``V - U`` off the support (mm): what the
  estimator's model does not explain and either corrects (k_f 0.05) or, below about k_f
  0.045, turns into forces (docs/sim-noise.md, "the k_f edge").

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=python python3 bench/press_far_field.py [--tilt 20]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from bubble_rt.estimation.estimator import EstimatorConfig, ForceEstimator
from bubble_rt.estimation.pipeline import Pipeline
from bubble_rt.sensor import PUNYO
from mesh_convergence import REAL  # bench/ is on the path of a script run from it

BINS_MM = ((0, 5), (5, 10), (10, 15), (15, 20), (20, 30), (30, 40), (40, 60))
#: The press depth past first touch (m) that gives about the real hold's force when tilted; the
#: sphere is the built-in `punyo` scene's, the one press_physics matches to the real dent.
DEPTH_M = 5.05e-3


def profile(pipe: Pipeline, frames: list[Any]) -> tuple[np.ndarray, np.ndarray]:
    """Median over frames of the mean U . n and of the mean off-support correction per bin."""
    mesh = pipe.mesh
    V = np.asarray(mesh.vertices)
    n = np.asarray(mesh.vertex_normals())
    est = ForceEstimator(
        mesh,
        EstimatorConfig(ambient_pa=PUNYO.ambient_pa),
        SimpleNamespace(pressure_pa=pipe.reference.pressure_pa),
    )
    un_rows, dn_rows = [], []
    for f in frames:
        d = pipe.deform(f)
        U = np.asarray(d.U)
        e = est.estimate(U, float(d.dp))
        un = np.sum(U * n, axis=1) * 1e3
        dn = np.sum((np.asarray(e.displacements) - U) * n, axis=1) * 1e3
        r = np.linalg.norm(V - V[np.argmin(un)], axis=1) * 1e3
        ok = np.asarray(d.valid)
        bins = [(r >= lo) & (r < hi) for lo, hi in BINS_MM]
        un_rows.append([un[ok & b].mean() for b in bins])
        dn_rows.append([dn[b & ~e.support].mean() if (b & ~e.support).any() else 0.0 for b in bins])
    return np.median(un_rows, axis=0), np.median(dn_rows, axis=0)


def simulated_press(tilt_deg: float, at: tuple[float, float]) -> tuple[list[Any], list[Any], Any]:
    """Reference frames, the hold's last 3 frames and the camera of a simulated Punyo press."""
    from bubble_rt.sim.scene import load_scene, scene_from_dict
    from bubble_rt.sim.simulator import Simulator

    sphere = asdict(load_scene("punyo").indenter.shapes[0])
    t = np.radians(tilt_deg)
    approach = [float(np.sin(t)), 0.0, -float(np.cos(t))]

    def key(time: float, depth: float) -> dict[str, Any]:
        return {"t": time, "at": list(at), "depth": depth, "approach": approach}

    scene = scene_from_dict(
        {
            "name": "far-field",
            "profile": "punyo",
            "frames": 12,
            "seed": 5,
            "indenter": {"shapes": [{"type": "sphere", "radius": sphere["radius"]}]},
            "trajectory": {"keyframes": [key(0.0, -1e-3), key(0.25, DEPTH_M), key(0.4, DEPTH_M)]},
            "effects": {
                "gas_compression": True,
                "friction": {"mu": 0.5},
                "depth_noise": {},
                "depth_dropouts": {},
                "depth_jumps": {},
                "rgb_noise": {},
            },
        }
    )
    sim = Simulator(scene)
    return sim.reference_frames(5), list(sim.frames())[-3:], sim.camera


def row(name: str, force: float, dp: float, un: np.ndarray, dn: np.ndarray, out: dict) -> str:
    out[name] = {"force_n": force, "dp_pa": dp, "u_n_mm": un.tolist(), "correction_mm": dn.tolist()}
    cells = " | ".join(f"{a:+.2f} / {b:+.2f}" for a, b in zip(un, dn, strict=True))
    return f"| {name} | {force:.1f} | {dp:.0f} | {cells} |"


def main() -> None:
    from bubble_rt.eval.press_physics import hold_summary, real_press
    from bubble_rt.io.recordings import open_recording

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tilt", type=float, default=20.0, help="the tilted press's angle (deg)")
    ap.add_argument("--json", help="write the rows here (bins in mm: BINS_MM)")
    args = ap.parse_args()
    out: dict[str, Any] = {"bins_mm": BINS_MM}
    cfg = EstimatorConfig(ambient_pa=PUNYO.ambient_pa)
    head = " | ".join(f"{lo}-{hi} mm" for lo, hi in BINS_MM)
    print("U . n / mean correction off the support (mm, outward +), by distance from the load\n")
    print(f"| press | \\|f\\| (N) | dp (Pa) | {head} |")
    print("|---|---|---|" + "---|" * len(BINS_MM))
    rec = open_recording(str(REAL))
    pipe = Pipeline.capture([rec[i] for i in range(5)], rec.camera, mesh="medium", config=cfg)
    hold = [rec[i] for i in range(26, 31)]
    wr = np.array([f.wrench[:3] for f in hold]) - np.mean([rec[i].wrench[:3] for i in range(5)], 0)
    dp = np.median([f.pressure_pa for f in hold]) - pipe.reference.pressure_pa
    print(
        row(
            "real hold 26-30",
            float(np.median(np.linalg.norm(wr, axis=1))),
            dp,
            *profile(pipe, hold),
            out,
        )
    )
    centre = hold_summary(real_press(str(REAL))).centre_m
    assert centre is not None
    for tilt in (0.0, args.tilt):
        refs, frames, cam = simulated_press(tilt, (float(centre[0]), float(centre[1])))
        sp = Pipeline.capture(refs, cam, mesh="medium", config=cfg)
        force = float(np.median([np.linalg.norm(f.truth.net_force) for f in frames]))
        dp = float(np.median([f.pressure_pa for f in frames])) - sp.reference.pressure_pa
        print(row(f"simulated, tilt {tilt:.0f} deg", force, dp, *profile(sp, frames), out))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
