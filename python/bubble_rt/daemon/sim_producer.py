"""The simulated camera's renderer in its own process, so it takes no time from the estimator.

Rendering a simulated 640 x 480 RGBD frame (ray casting, texture, noise) costs tens of
milliseconds of Python and numpy; in the daemon's process it held the GIL the estimation
threads need. Here a child process (``python -m bubble_rt.daemon.sim_producer``) renders the
frames and writes them to a pipe; the daemon reads them in its capture thread (the reads
release the GIL) and pairs each one with the simulator's ground truth, which it computes itself
from the cached physics (cheap array lookups). The frames are deterministic given the scene and
its seed, so where they are rendered changes nothing in them.

The truth's contact on the estimator's mesh (``ForceFrame.sim_truth``) is also derived in the
child: locating an estimator mesh on the simulation surface takes seconds the first time and
~20 ms a frame after, which stalled the daemon's solve thread. Once the daemon has its mesh it
sends it; the child computes the true contact on it for every pressing scene frame (between
rendered frames) and the parent keeps the table. A frame whose contact is not in the table yet
is published without ``sim_truth`` (realtime pace; the first pass after start-up), or waits
for it (``lossless`` pace, where every frame is processed anyway).

Parent -> child (stdin, one command a line): ``reference N`` (N frames of the untouched
membrane, answered first), ``stream`` (the scene's frames, one pass, or pass after pass
with ``--repeat``) and ``mesh {json}`` (id, vertices, triangles, boundary of the estimator's
mesh). Closing stdin (the daemon stopping, or dying) ends the child.

Child -> parent (stdout): messages, each a JSON header line ``{"kind": ..., "arrays": [[name,
dtype, shape], ...], ...}`` followed by the raw bytes of those arrays. Kinds: ``progress``
(physics steps done/total), ``physics`` (seconds, whether it was computed now), ``reference``
and ``frame`` (a Frame without truth), ``reference_end``, ``pass_end``, ``mask`` (true contact
of one scene frame on a mesh) and ``error``.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import queue
import select
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from bubble_rt.daemon.sim_cache import load_reference, reference_cache_path, store_reference
from bubble_rt.daemon.sim_wire import frame_message, message_frame, read_message, write_message
from bubble_rt.frames import Frame

log = logging.getLogger("bubble_rt.daemon.sources")

#: Where the simulator class comes from (``module:attribute``); tests name a fake.
DEFAULT_SIMULATOR = "bubble_rt.sim:Simulator"
#: Frames the parent holds ahead of the camera's pacing when it does not keep the whole pass.
AHEAD_FRAMES = 8
_F_SETPIPE_SZ = 1031  # Linux fcntl: a 1 MB pipe moves a frame in 3 writes instead of 33


def load_simulator_class(path: str) -> Any:
    """The class named ``module:attribute``."""
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


# ------------------------------------------------------------------------------ child
def _commands(fd: int, pending: bytearray, block: bool) -> list[str] | None:
    """Command lines available on ``fd`` (waiting for one when ``block``); None at EOF."""
    ready, _, _ = select.select([fd], [], [], None if block else 0.0)
    if not ready:
        return []
    while ready:  # everything there now (a mesh command is tens of kB)
        chunk = os.read(fd, 1 << 16)
        if not chunk:
            return None
        pending.extend(chunk)
        ready, _, _ = select.select([fd], [], [], 0.0)
    *lines, rest = bytes(pending).split(b"\n")
    pending[:] = rest
    return [ln.decode().strip() for ln in lines if ln.strip()]


def child_main(argv: list[str] | None = None) -> int:
    """The producer process: renders what the parent asks for until stdin closes."""
    import argparse
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the daemon's to handle
    ap = argparse.ArgumentParser(prog="bubble_rt.daemon.sim_producer")
    ap.add_argument("scene")
    ap.add_argument("--repeat", action="store_true", help="stream pass after pass")
    ap.add_argument("--simulator", default=DEFAULT_SIMULATOR)
    args = ap.parse_args(argv)
    out = sys.stdout.buffer
    fd = sys.stdin.fileno()

    def progress(done: int, total: int) -> None:
        write_message(out, "progress", done=done, total=total)

    try:
        sim = load_simulator_class(args.simulator)(args.scene, progress=progress)
        t0 = time.perf_counter()
        if hasattr(type(sim), "run"):  # (on the instance, hasattr would run the physics)
            cold = not _physics_cached(sim)
            _ = sim.run  # the physics: from the cache, or computed (and cached) now
            write_message(out, "physics", seconds=time.perf_counter() - t0, cold=cold)
    except OSError:  # BrokenPipeError: the daemon went away (e.g. it failed to start)
        return _parent_gone()
    except Exception as exc:
        write_message(out, "error", text=f"{type(exc).__name__}: {exc}")
        return 1
    pending = bytearray()
    refs: list[int] = []
    streaming = False
    frames: Iterator[Frame] | None = None
    masks: list[tuple[int, Any, int]] = []  # (mesh id, Mesh, scene frame) still to derive
    turn = False
    try:
        while True:
            cmds = _commands(fd, pending, block=not (streaming or refs or masks))
            if cmds is None:
                return 0  # the daemon closed stdin (stopped, or died)
            for c in cmds:
                if c.startswith("reference "):
                    refs.append(int(c.split()[1]))
                elif c == "stream":
                    streaming = True
                elif c.startswith("mesh "):
                    masks = _mask_jobs(sim, json.loads(c[5:]))
            if refs:  # the reference first: the daemon's start waits on it
                for f in sim.reference_frames(refs.pop(0)):
                    fields, arrays = frame_message(f)
                    write_message(out, "reference", arrays, **fields)
                write_message(out, "reference_end")
                continue
            turn = not turn
            if masks and (turn or not streaming):  # alternate with the frames
                mesh_id, mesh, i = masks.pop(0)
                mask = np.asarray(sim.truth(i).contact_mask(mesh), dtype=bool)
                write_message(out, "mask", {"mask": mask}, mesh=mesh_id, index=i)
                continue
            if streaming:
                frames = frames or iter(sim.frames())
                f = next(frames, None)
                if f is None:
                    write_message(out, "pass_end")
                    frames = None
                    streaming = args.repeat
                    continue
                fields, arrays = frame_message(f)
                write_message(out, "frame", arrays, **fields)
    except OSError:  # BrokenPipeError: the daemon went away
        return _parent_gone()
    except Exception as exc:
        write_message(out, "error", text=f"{type(exc).__name__}: {exc}")
        return 1


def _parent_gone() -> int:
    """The daemon closed the pipe: end quietly (stdout pointed at /dev/null, so that the
    interpreter's final flush does not print a broken-pipe traceback)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    return 0


def _mask_jobs(sim: Any, spec: dict[str, Any]) -> list[tuple[int, Any, int]]:
    """(mesh id, mesh, scene frame) for every scene frame with contact (the others have none)."""
    from bubble_rt.mesh import Mesh

    if not hasattr(sim, "truth"):
        return []
    mesh = Mesh(
        np.asarray(spec["vertices"], dtype=np.float64),
        np.asarray(spec["triangles"], dtype=np.int32),
        np.asarray(spec["boundary"], dtype=np.int32),
    )
    n = int(sim.scene.frames)
    return [(int(spec["id"]), mesh, i) for i in range(n) if bool(np.any(sim.truth(i).contact))]


def _physics_cached(sim: Any) -> bool:
    from bubble_rt.sim import cache

    try:
        return bool(cache.cache_path(sim.physics_key()).exists())
    except Exception:
        return False


# ------------------------------------------------------------------------------ parent
class ProducedTruth:
    """A simulated frame's ground truth as the daemon reads it (``bubble_rt.daemon.sim_truth``):
    the simulator's :class:`~bubble_rt.sim.truth.GroundTruth` (every attribute, built on first
    use: it needs the physics), except that ``contact_mask(mesh)`` comes from the producer
    process (None: not derived yet)."""

    def __init__(self, truth_of: Any, index: int | None, producer: SimProducer) -> None:
        self._truth_of = truth_of
        self._index = index
        self._producer = producer
        self._truth: Any = None

    def _get(self) -> Any:
        if self._truth is None:
            self._truth = self._truth_of(self._index)
        return self._truth

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._get(), name)

    def contact_mask(self, mesh: Any) -> np.ndarray | None:
        if self._index is None or not np.any(self._get().contact):
            return np.zeros(len(mesh.vertices), bool)  # no contact anywhere: nothing to derive
        return self._producer.contact_mask(self._index, mesh)


class SimProducer:
    """The daemon's side of the producer process: starts it, asks for frames, reads them.

    ``reference_frames(n)`` blocks until the child rendered them; ``frames()`` yields the
    stream, one pass per call (the child renders ahead: the whole pass when ``keep_pass``,
    else up to ``AHEAD_FRAMES`` frames). Truth (``Frame.truth``) is rebuilt here from the
    simulator's ``truth(i)`` when it has one.
    """

    def __init__(
        self,
        scene: str,
        sim: Any,
        repeat: bool,
        keep_pass: bool,
        simulator: str = DEFAULT_SIMULATOR,
    ) -> None:
        self.scene = scene
        self.sim = sim
        self.repeat = repeat
        self.keep_pass = keep_pass
        self.simulator = simulator
        self._proc: subprocess.Popen[bytes] | None = None
        self._reader: threading.Thread | None = None
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._preload_lock = threading.Lock()
        self._refs: queue.Queue[Any] = queue.Queue()
        self._stream: queue.Queue[Any] = queue.Queue(0 if keep_pass else AHEAD_FRAMES)
        self._truths: dict[int | None, Any] = {}
        #: The estimator mesh the child derives true contact on, its id, and the table.
        self._mesh: Any = None
        self._mesh_id = 0
        self._masks: dict[tuple[int, int], np.ndarray] = {}
        self._masks_cond = threading.Condition()
        #: Wait for a frame's true contact instead of publishing the frame without it.
        self.wait_for_truth = False
        self._streaming = False
        self._stopped = False
        #: Frames received from the child (stream and reference).
        self.frames_received = 0
        self.error = ""

    # ---------------------------------------------------------------- process
    def start(self) -> None:
        """Start the child (idempotent; again after it ended)."""
        with self._lock:
            if self._stopped or (self._proc is not None and self._proc.poll() is None):
                return
            cmd = [sys.executable, "-m", "bubble_rt.daemon.sim_producer", self.scene]
            cmd += ["--simulator", self.simulator] + (["--repeat"] if self.repeat else [])
            # The child imports what this process can (the simulator class named by path).
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
            self._proc = subprocess.Popen(
                cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env
            )
            self._streaming = False
            try:
                import fcntl

                assert self._proc.stdout is not None
                fcntl.fcntl(self._proc.stdout.fileno(), _F_SETPIPE_SZ, 1 << 20)
            except (OSError, ImportError, AttributeError):
                pass  # a smaller pipe only means more, smaller reads
            self._reader = threading.Thread(
                target=self._read, args=(self._proc,), name="sim-producer-reader", daemon=True
            )
            self._reader.start()

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def _send(self, command: str) -> None:
        proc = self._proc
        if proc is None or proc.stdin is None:
            raise RuntimeError("simulator process not started")
        try:
            with self._send_lock:
                proc.stdin.write(command.encode() + b"\n")
                proc.stdin.flush()
        except (BrokenPipeError, ValueError, OSError) as exc:
            raise RuntimeError(f"simulator process ended: {self.error or exc}") from exc

    def stop(self, timeout: float = 1.0) -> None:
        """Close the child's stdin (it then exits); after ``timeout`` s, kill it."""
        self._stopped = True
        proc = self._proc
        if proc is None:
            return
        if proc.stdin is not None and not proc.stdin.closed:
            try:
                proc.stdin.close()
            except OSError:
                pass
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            if timeout > 0:
                proc.kill()
                proc.wait(1.0)
        if proc.poll() is not None and self._reader is not None:
            self._reader.join(1.0)

    # ---------------------------------------------------------------- reading
    def _read(self, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdout is not None
        bar: Any = None
        while True:
            try:
                msg = read_message(proc.stdout)
            except (OSError, ValueError) as exc:
                self.error = self.error or f"simulator process: {exc}"
                msg = None
            if msg is None:
                break
            header, arrays = msg
            kind = header["kind"]
            if kind == "progress":
                if bar is None:  # one bar (drawn on a terminal), and a log line
                    from bubble_rt.sim.simulator import progress_bar

                    log.info(
                        "simulating the physics of scene %r (first run only, cached)", self.scene
                    )
                    bar = progress_bar(f"physics of scene {self.scene!r}")
                bar(header["done"], header["total"])
            elif kind == "physics":
                self.preload_truth()
                if header["cold"]:
                    log.info(
                        "physics of scene %r simulated in %.1f s (cached for the next runs)",
                        self.scene,
                        header["seconds"],
                    )
            elif kind in ("reference", "frame"):
                self.frames_received += 1
                idx = None if kind == "reference" else int(header["index"])
                frame = message_frame(header, arrays, self._truth(idx))
                self._put(self._refs if kind == "reference" else self._stream, frame)
            elif kind == "mask":
                with self._masks_cond:
                    self._masks[(int(header["mesh"]), int(header["index"]))] = arrays["mask"]
                    self._masks_cond.notify_all()
            elif kind == "reference_end":
                self._refs.put(None)
            elif kind == "pass_end":
                self._put(self._stream, None)
            elif kind == "error":
                self.error = f"simulator process: {header['text']}"
                log.warning("%s", self.error)
        proc.stdout.close()
        with self._masks_cond:
            self._masks_cond.notify_all()
        self._refs.put(EOFError(self.error or "simulator process ended"))
        self._put(self._stream, EOFError(self.error or "simulator process ended"))

    def _put(self, q: queue.Queue[Any], item: Any) -> None:
        while not self._stopped:
            try:
                q.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _truth(self, index: int | None) -> Any:
        """The simulator's ground truth of scene frame ``index`` (None: the reference), kept
        per frame so that what is derived from it (contact on a mesh) is derived once."""
        truth_of = getattr(self.sim, "truth", None)
        if truth_of is None:
            return None
        if index not in self._truths:
            self._truths[index] = ProducedTruth(truth_of, index, self)
        return self._truths[index]

    def preload_truth(self) -> None:
        """Load the (cached) physics and what every truth shares (the surface locator) now,
        not in the solve thread at the first frame's truth; idempotent, thread-safe."""
        with self._preload_lock:
            truth = self._truth(None)
            if truth is not None:
                try:
                    truth._get()
                except Exception as exc:  # no physics yet (the child computes it): later
                    log.debug("truth not preloaded: %s", exc)

    def frame_of(self, fields: dict[str, Any], arrays: dict[str, np.ndarray]) -> Frame:
        """A frame of the stream from its (fields, arrays), with its truth."""
        return message_frame(fields, arrays, self._truth(int(fields["index"])))

    def contact_mask(self, index: int, mesh: Any) -> np.ndarray | None:
        """The true contact of scene frame ``index`` on ``mesh``'s nodes, derived by the child;
        None when it is not there yet (unless ``wait_for_truth``)."""
        self.start()  # not started yet when the frames came from the pass cache
        with self._masks_cond:
            if mesh is not self._mesh:
                self._send_mesh(mesh)
            key = (self._mesh_id, int(index))
            while key not in self._masks and self.wait_for_truth and self.alive:
                self._masks_cond.wait(0.1)
            return self._masks.get(key)

    def _send_mesh(self, mesh: Any) -> None:
        self._mesh_id += 1
        self._mesh = mesh
        spec = {
            "id": self._mesh_id,
            "vertices": np.asarray(mesh.vertices).tolist(),
            "triangles": np.asarray(mesh.triangles).tolist(),
            "boundary": np.asarray(mesh.boundary).tolist(),
        }
        command = "mesh " + json.dumps(spec)

        def send() -> None:  # off the caller's (solve) thread: the pipe may be full
            try:
                self._send(command)
            except RuntimeError as exc:
                self.error = self.error or str(exc)

        threading.Thread(target=send, name="sim-producer-mesh", daemon=True).start()

    # ---------------------------------------------------------------- requests
    def reference_frames(self, n: int, stop: threading.Event) -> list[Frame] | None:
        """``n`` reference frames (None when ``stop`` was set first): from the on-disk cache
        (:func:`~bubble_rt.daemon.sim_cache.reference_cache_path`) when rendered before, else
        rendered by the child (and then cached)."""
        self.start()
        path = reference_cache_path(self.sim, n)
        cached = None if path is None else load_reference(path)
        if cached is not None and len(cached) == n:
            return [message_frame(h, a, self._truth(None)) for h, a in cached]
        self._send(f"reference {n}")
        out: list[Frame] = []
        while not stop.is_set():
            try:
                item = self._refs.get(timeout=0.1)
            except queue.Empty:
                continue
            if isinstance(item, EOFError):
                raise RuntimeError(str(item))
            if item is None:
                if path is not None:
                    threading.Thread(
                        target=store_reference, args=(path, out), name="sim-ref-cache", daemon=True
                    ).start()
                return out
            out.append(item)
        return None

    def frames(self, stop: threading.Event) -> Iterator[Frame]:
        """One pass of the scene's frames as the child renders them."""
        self.start()
        if not self._streaming or not self.repeat:
            self._send("stream")
            self._streaming = True
        while not stop.is_set():
            try:
                item = self._stream.get(timeout=0.1)
            except queue.Empty:
                continue
            if isinstance(item, EOFError):
                raise RuntimeError(str(item))
            if item is None:
                return
            yield item


if __name__ == "__main__":
    try:
        sys.exit(child_main())
    except BrokenPipeError:  # the daemon is gone (stopped, or failed to start): nobody to tell
        sys.exit(_parent_gone())
