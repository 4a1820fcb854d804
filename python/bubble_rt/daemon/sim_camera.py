"""The simulated camera: the simulator's frames rendered in a process of their own
(:mod:`bubble_rt.daemon.sim_producer`) and fed to the daemon like a real camera's."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

from bubble_rt.daemon.sources import IterableCamera, SourceError
from bubble_rt.frames import Frame


class SimCamera(IterableCamera):
    """The simulator (``bubble_rt.sim``) on a scene, looped, paced at the scene's camera rate.

    The frames are rendered in a separate process (:mod:`bubble_rt.daemon.sim_producer`), so
    the simulated camera takes no time from the estimation threads, like a real camera; they
    carry the simulator's ground truth (``Frame.truth``). Frame indices keep counting across
    loops (``index = pass * scene.frames + i``), so frame ``k`` shows scene frame
    ``k % scene.frames``. With ``prerender`` the first pass is kept in memory and later passes
    replay it (the renderer process is then idle); it is also stored in the disk cache
    (``sim_cache.pass_cache_path``, keyed by the scene and the simulator's code), and later
    runs replay it from there from their first frame, rendering nothing. ``simulator``: the
    simulator class as ``module:attribute`` (default ``bubble_rt.sim:Simulator``; tests name a
    fake). ``stop`` ends the renderer process too.
    """

    #: The renderer process (``sim_producer.SimProducer``).
    producer: Any
    #: One rendered pass read from the disk cache (then nothing is rendered), or None.
    cached_pass: list[Any] | None = None

    def __init__(
        self,
        scene: str = "demo",
        rate_hz: float | None = None,
        loop: bool = True,
        lossless: bool = False,
        prerender: bool = True,
        simulator: str | None = None,
    ) -> None:
        from bubble_rt.daemon import sim_cache
        from bubble_rt.daemon import sim_producer as sp

        path = simulator or sp.DEFAULT_SIMULATOR
        try:
            sim = sp.load_simulator_class(path)(scene)  # the scene and camera; no physics yet
        except Exception as exc:
            raise SourceError(f"cannot load simulator scene {scene!r}: {exc}") from exc
        self._n_frames = int(sim.scene.frames)
        # A simulated sensor is its scene's profile's bubble: the layout names that profile
        # ("sim", "punyo"), so that profile = "auto" reads a simulated Punyo as a Punyo (with
        # the "sim" profile's ambient it read 0.65 of the true force).
        self.layout = str(getattr(sim.scene, "profile", "sim"))
        self.producer = sp.SimProducer(
            scene, sim, repeat=loop and not prerender, keep_pass=prerender, simulator=path
        )
        # With prerender, a pass rendered by an earlier run is read from the disk cache.
        self._pass_path = sim_cache.pass_cache_path(sim) if prerender else None
        self.cached_pass = (
            None
            if self._pass_path is None
            else sim_cache.load_pass(self._pass_path, self._n_frames)
        )
        self._prerender = prerender
        self._pass_frames: list[Frame] = []
        self._passes = 0
        self._complete = False
        hz = rate_hz or float(sim.scene.rates.camera_hz)
        super().__init__(
            self._frames_of_next_pass,
            sim.camera,
            rate_hz=None if lossless else hz,
            loop=loop,
            lossless=lossless,
            reference=lambda n: self.producer.reference_frames(n, self._stop),
            keep_index=True,
        )
        # Paced by the estimator (every frame processed): a frame waits for its true contact.
        self.producer.wait_for_truth = lossless
        self.name = f"sim:{scene}"
        self.stats.name = self.name

    def _frames_of_next_pass(self) -> Iterator[Frame]:
        """One pass over the scene: from the disk cache, the pass kept in memory, or the
        renderer (kept, and stored to disk once complete, with ``prerender``)."""
        from bubble_rt.daemon import sim_cache

        offset = self._passes * self._n_frames
        self._passes += 1
        if self.cached_pass is not None:
            for fields, arrays in self.cached_pass:
                f = self.producer.frame_of(fields, arrays)
                yield replace(f, index=f.index + offset)
            return
        if self._complete:
            for f in self._pass_frames:
                yield replace(f, index=f.index + offset)
            return
        self._pass_frames.clear()
        for f in self.producer.frames(self._stop):
            if self._prerender:
                self._pass_frames.append(f)
            yield replace(f, index=f.index + offset)
        # Only a whole pass is kept: a stop mid-pass (the daemon ending) leaves a part of one,
        # which replayed would loop over its first frames only.
        self._complete = self._prerender and len(self._pass_frames) == self._n_frames
        if self._complete and self._pass_path is not None:  # the next runs read it from disk
            threading.Thread(
                target=sim_cache.store_pass,
                args=(self._pass_path, list(self._pass_frames)),
                name="sim-pass-cache",
                daemon=True,
            ).start()

    def prepare(self) -> None:
        """Start the renderer process now, so it loads while the daemon sets up (with a cached
        pass it renders nothing: it loads the physics, then derives the true contact)."""
        self.producer.start()
        if self.cached_pass is not None:  # the physics is cached too: load it meanwhile
            threading.Thread(
                target=self.producer.preload_truth, name="sim-truth-preload", daemon=True
            ).start()

    def stop(self, timeout: float = 1.0) -> None:
        super().stop(timeout)
        self.producer.stop(timeout)
