"""Choose the ``punyo`` profile's estimator constants on simulated Punyo presses only.

The simulated Punyo (``profile = "punyo"`` scenes: the bubble identified in docs/sim-punyo.md)
is pressed by the paper's dataset procedure (``bubble_rt.sim.dataset``, ``PUNYO_DEPTHS``: light
touches of about 0.3-1.5 N and firm presses of about 2-6 N, several indenters, contact points
and approach directions). Each simulated frame carries its true net force as a wrench (mesh
frame, so the rotation is the identity) and its contact truth, so the project's own recording
calibration (``bubble_rt.eval.recording_calibration``: the paper's loss, force and contact
terms, every estimator linearised about its recording's reference pressure) fits the rest
tension (``ambient_pa``; ``--fit`` adds E, k_f, k_u) on them. Calibration scenes use the
master seeds ``CALIB_SEED_BASE`` and the next, the held-out check ``EVAL_SEED_BASE``; the real
press is not read here (check with ``../shared/tools/real-press-report --config OUT``).

    PYTHONPATH=python OPENBLAS_NUM_THREADS=1 python3 bench/punyo_profile_fit.py --out punyo-fit.toml

Prints: the true forces of the scenes, the fit, a grid of the loss over (ambient, E) around the
optimum (is the fit well-posed, or a ridge?), and the held-out scores of the estimator's
profile before and after: median |f_est| / |f_true| on light (1-2 N) and firm (>= 2 N) frames,
mean magnitude error on frames with 1 N or more, |f| and contact on untouched frames.
Each scene's physics is solved once and cached in ~/.cache/bubble_rt (about 10-60 s each).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from bubble_rt.eval import CALIB_SEED_BASE, EVAL_SEED_BASE, FanOut
from bubble_rt.eval.calibration import DEFAULTS, write_config
from bubble_rt.eval.recording_calibration import (
    RecordingProblem,
    RecordingSet,
    calibrate_recordings,
    fem_at_reference,
    frames_set,
)
from bubble_rt.sensor import PUNYO
from bubble_rt.sim.dataset import PUNYO_DEPTHS, DatasetSettings, dataset_scenes

#: Indenters of the calibration and held-out sets (the dataset's presets).
INDENTERS = ("round", "point", "line", "square")
#: Frames with at least this true |f| (N) count as contact frames; below FIRM_N they are light.
CONTACT_N = 1.0
FIRM_N = 2.0
#: Frames whose true |f| is below this (N) are untouched.
UNTOUCHED_N = 0.01


def punyo_scenes(seed: int, per_indenter: int, frames: int, indenters: Sequence[str]) -> list[Any]:
    """The simulated Punyo's trajectory scenes (light and firm alternate per indenter)."""
    st = DatasetSettings(
        per_indenter=per_indenter,
        frames=frames,
        indenters=tuple(indenters),
        seed=seed,
        depths=PUNYO_DEPTHS,
        profile="punyo",
    )
    return dataset_scenes(st)


def simulated_set(scene: Any) -> RecordingSet:
    """Simulate a scene and track it as a recording whose wrench is the true net force."""
    from bubble_rt.sim.simulator import Simulator

    sim = Simulator(scene)
    refs = [replace(f, wrench=np.zeros(6)) for f in sim.reference_frames(5)]
    frames = [
        replace(f, wrench=np.r_[np.asarray(f.truth.net_force, dtype=float), np.zeros(3)])
        for f in sim.frames()
    ]
    return frames_set(scene.name, refs, frames, sim.camera, mesh="medium")


def simulated_sets(scenes: Sequence[Any], fan: FanOut, cache: str = "") -> list[RecordingSet]:
    """The tracked sets of ``scenes``, kept in the pickle ``cache`` (reused for the same scenes)."""
    import pickle
    from pathlib import Path

    key = repr(list(scenes))
    if cache and Path(cache).exists():
        stored_key, sets = pickle.loads(Path(cache).read_bytes())
        if stored_key == key:
            return list(sets)
    sets = list(fan.map(simulated_set, list(scenes)))
    if cache:
        Path(cache).parent.mkdir(parents=True, exist_ok=True)
        Path(cache).write_bytes(pickle.dumps((key, sets)))
    return sets


@dataclass
class Scores:
    """Held-out scores of one set of estimator constants."""

    light_ratio: float  # median |f_est| / |f_true|, CONTACT_N <= |f_true| < FIRM_N
    firm_ratio: float  # median |f_est| / |f_true|, |f_true| >= FIRM_N
    ratio: float  # median over both
    mean_error_n: float  # mean | |f_est| - |f_true| | over contact frames (N)
    untouched_max_n: float  # max |f_est| on untouched frames (N)
    untouched_contact: int  # untouched frames with any contact node
    missed_contact: int  # contact frames without any contact node
    n_light: int
    n_firm: int
    n_untouched: int

    def row(self) -> str:
        return (
            f"ratio light {self.light_ratio:.2f} ({self.n_light}) firm {self.firm_ratio:.2f} "
            f"({self.n_firm}) all {self.ratio:.2f}; error {self.mean_error_n:.2f} N; untouched "
            f"max {self.untouched_max_n:.2f} N, contact on {self.untouched_contact}/"
            f"{self.n_untouched}; contact frames with no contact node {self.missed_contact}"
        )


def score(sets: Sequence[RecordingSet], params: dict[str, float]) -> Scores:
    """Estimate every frame with ``params`` (E, k_f, k_u, ambient_pa) and score it."""
    truth, est, contact = [], [], []
    for s in sets:
        e = fem_at_reference(s.reference_pressure_pa, s.mesh, params)
        for fr in s.frames:
            r = e.estimate(fr.U, fr.dp)
            truth.append(float(np.linalg.norm(fr.w)))
            est.append(float(np.linalg.norm(r.net_force)))
            contact.append(bool(np.any(r.contact)))
    t, f, c = np.array(truth), np.array(est), np.array(contact)
    light = (t >= CONTACT_N) & (t < FIRM_N)
    firm = t >= FIRM_N
    touch = t >= CONTACT_N
    still = t < UNTOUCHED_N
    med = lambda m: float(np.median(f[m] / t[m])) if m.any() else float("nan")  # noqa: E731
    return Scores(
        light_ratio=med(light),
        firm_ratio=med(firm),
        ratio=med(touch),
        mean_error_n=float(np.mean(np.abs(f[touch] - t[touch]))) if touch.any() else float("nan"),
        untouched_max_n=float(f[still].max()) if still.any() else 0.0,
        untouched_contact=int(c[still].sum()),
        missed_contact=int((~c[touch]).sum()),
        n_light=int(light.sum()),
        n_firm=int(firm.sum()),
        n_untouched=int(still.sum()),
    )


def profile_params() -> dict[str, float]:
    """The ``punyo`` profile's estimator constants, named as calibration names them."""
    return {**DEFAULTS, "E": PUNYO.youngs_modulus, "ambient_pa": PUNYO.ambient_pa}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=[CALIB_SEED_BASE, CALIB_SEED_BASE + 1],
        help="the calibration sets' master seeds",
    )
    ap.add_argument("--per-indenter", type=int, default=2, help="calibration scenes per indenter")
    ap.add_argument("--eval-per-indenter", type=int, default=2)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--indenters", nargs="+", default=list(INDENTERS))
    ap.add_argument(
        "--fit", nargs="+", default=["ambient_pa"], help="E, k_f, k_u held at the estimator's"
    )
    ap.add_argument(
        "--start-ambient-pa",
        type=float,
        default=PUNYO.bubble.ambient_pa,
        help="where the search starts (default: the simulated bubble's true ambient)",
    )
    ap.add_argument("--max-evals", type=int, default=30)
    ap.add_argument("--grid", type=int, default=5, help="grid points per axis (0: no grid)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="", help="write the fitted [estimator] keys here")
    ap.add_argument("--cache", default="", help="folder for the tracked frames (pickles)")
    ap.add_argument("--json", default="", help="write the fit and the scores here")
    a = ap.parse_args()

    t0 = time.perf_counter()
    fan = FanOut(a.workers)
    try:
        cache = lambda name: f"{a.cache}/{name}.pkl" if a.cache else ""  # noqa: E731
        calib = [
            s
            for seed in a.seeds
            for s in simulated_sets(
                punyo_scenes(seed, a.per_indenter, a.frames, a.indenters),
                fan,
                cache(f"calibration-{seed}"),
            )
        ]
        held = simulated_sets(
            punyo_scenes(EVAL_SEED_BASE, a.eval_per_indenter, a.frames, a.indenters),
            fan,
            cache("held-out"),
        )
        print(
            f"simulated and tracked {len(calib)} + {len(held)} scenes in "
            f"{time.perf_counter() - t0:.0f} s"
        )
        for s in calib + held:
            peak = max(float(np.linalg.norm(f.w)) for f in s.frames)
            print(
                f"  {s.name:10s} rest {s.reference_pressure_pa:.0f} Pa, peak |f| {peak:.2f} N, "
                f"{len(s.frames)} frames"
            )

        problem = RecordingProblem(calib, rotation=np.eye(3))
        start = {**DEFAULTS, "ambient_pa": a.start_ambient_pa}
        cal = calibrate_recordings(
            problem, initial=start, fit=a.fit, max_evals=a.max_evals, fan=fan
        )
        res = cal.result
        fitted = {k: res.params[k] for k in ("E", "k_f", "k_u", "ambient_pa")}
        print(
            f"fit {a.fit}: {fitted}  loss {res.initial_loss:.2f} -> {res.loss:.2f} "
            f"({res.evaluations} evaluations, {res.seconds:.0f} s)"
        )

        if a.grid:
            rest = problem.rest_pressure_pa or 0.0
            g0 = rest - fitted["ambient_pa"]
            gauges = g0 * np.geomspace(0.7, 1.4, a.grid)
            Es = fitted["E"] * np.geomspace(0.5, 2.0, a.grid)
            n = len(problem.frames)
            print(
                "loss grid (loss; mean force error N; mean contact term x 10): rows gauge "
                "(Pa) = rest - ambient, columns E (MPa)"
            )
            print("          " + " ".join(f"{E / 1e6:19.2f}" for E in Es))
            for g in gauges:
                ev = [problem.evaluate({**fitted, "ambient_pa": rest - g, "E": E}, fan) for E in Es]
                print(
                    f"{g:9.0f} "
                    + " ".join(
                        f"{v.loss:7.1f};{v.force_term / n:5.2f};{10 * v.contact_term / n:5.2f}"
                        for v in ev
                    )
                )

        report: dict[str, Any] = {"fit": a.fit, "seeds": a.seeds, "fitted_params": fitted}
        for name, params in (
            ("true gauge (ambient = the bubble's), E default", start),
            ("punyo profile (bubble_rt.sensor)", profile_params()),
            ("fitted", fitted),
        ):
            sc, sh = score(calib, params), score(held, params)
            print(f"calibration  {name}: {sc.row()}")
            print(f"held-out     {name}: {sh.row()}")
            report[name] = {"params": params, "calibration": asdict(sc), "held_out": asdict(sh)}
        if a.json:
            import json
            from pathlib import Path

            Path(a.json).write_text(json.dumps(report, indent=1))
        if a.out:
            write_config(
                a.out,
                res,
                {**cal.info(), "scenes": [s.name for s in calib], "seeds": a.seeds},
            )
            print(f"wrote {a.out}")
    finally:
        fan.close()
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
