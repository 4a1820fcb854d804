"""Waiting on state, never on the clock: :func:`wait_for` a condition, :class:`ServedProcess`
for a daemon subprocess bound to any free port (``tcp://127.0.0.1:*``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

#: Any free port: ZeroMQ binds it and reports the endpoint it chose (``ZMQ_LAST_ENDPOINT``).
ANY_PORT = "tcp://127.0.0.1:*"


def wait_for(pred: Callable[[], Any], timeout: float = 10.0, what: str = "") -> bool:
    """Poll ``pred`` every 10 ms until it is truthy; True, or AssertionError naming ``what``
    (or the predicate's source line) after ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while True:
        if pred():
            return True
        if time.monotonic() >= end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what or _name(pred)}")
        time.sleep(0.01)


def _name(pred: Callable[[], Any]) -> str:
    import inspect

    try:
        return inspect.getsource(pred).strip()
    except (OSError, TypeError):
        return repr(pred)


def child_env() -> dict[str, str]:
    """The environment for a `bubble-rt` subprocess: this interpreter's import path (the package
    under test and the tests' helper modules) and one BLAS thread."""
    env = dict(os.environ)
    tests = os.path.dirname(os.path.abspath(__file__))
    env["PYTHONPATH"] = os.pathsep.join([tests] + [p for p in sys.path if p])
    env["OPENBLAS_NUM_THREADS"] = "1"
    return env


_ADDRESSES = re.compile(r"publishing on (\S+), control on (\S+)")


class ServedProcess:
    """``cmd`` (a `bubble-rt serve`-like command binding ``--pub``/``--control`` to
    :data:`ANY_PORT`) in a subprocess; its stderr is read on a thread and kept in :attr:`err`.

    :meth:`addresses` waits for the line where serve names the endpoints it bound (printed once
    the sockets are bound, before the reference is captured)."""

    def __init__(self, cmd: Sequence[str], env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            list(cmd), env=env or dict(os.environ), stderr=subprocess.PIPE, text=True
        )
        self._lines: list[str] = []
        self._found = threading.Event()
        self._pub = self._ctl = ""
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self._lines.append(line)
            m = _ADDRESSES.search(line)
            if m and not self._found.is_set():
                self._pub, self._ctl = m.group(1), m.group(2)
                self._found.set()
        self._found.set()  # the process ended: no address will come

    def addresses(self, timeout: float = 60.0) -> tuple[str, str]:
        """(pub, control) endpoints the daemon bound; AssertionError with its stderr if it
        exits or says nothing within ``timeout`` seconds."""
        if not self._found.wait(timeout) or not self._pub:
            raise AssertionError(f"serve named no bound addresses; stderr:\n{self.err}")
        return self._pub, self._ctl

    @property
    def err(self) -> str:
        return "".join(self._lines)

    def finish(self, timeout: float = 30.0) -> int:
        """Wait up to ``timeout`` s for the process to exit by itself and for all of its
        stderr; its exit code (AssertionError with its stderr if it does not exit)."""
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"still running {timeout} s later; stderr:\n{self.err}") from None
        self._reader.join(10)
        return int(self.proc.returncode)

    def kill(self) -> None:
        """Kill the process if it still runs (a ``finally`` after a failed test)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._reader.join(10)


def nobody_listens(folder: Any) -> str:
    """A ZeroMQ endpoint no daemon binds (an IPC path in the test's own ``folder``): for the
    no-daemon cases, with no port that something else could take meanwhile."""
    return f"ipc://{folder}/nobody"
