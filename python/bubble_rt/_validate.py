"""Input checks shared by the core facades (private).

Every check raises ValueError naming the argument before anything reaches C++, so a bad call
writes nothing and leaves solver state intact.
"""

from __future__ import annotations

import math
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray


def nodes_x3(name: str, value: ArrayLike, n: int) -> NDArray[np.float64]:
    """``value`` as a C-contiguous float64 N x 3 array (no copy when it already is one)."""
    try:
        a = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name} must be an array of shape ({n}, 3): {exc}") from exc
    if a.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3), got {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be numeric, got dtype {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float64)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} has NaN or inf at node {int(np.flatnonzero(bad)[0])}")
    return a


def nodes_1d(name: str, value: ArrayLike, n: int) -> NDArray[np.float64]:
    """``value`` as a finite C-contiguous float64 vector of length n."""
    a = np.asarray(value)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    a = np.ascontiguousarray(a, dtype=np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{name} has NaN or inf at node {int(np.flatnonzero(~np.isfinite(a))[0])}")
    return a


def finite_scalar(name: str, value: object) -> float:
    """``value`` as a finite float (pascals, newtons, ...)."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number, got {value!r}") from exc
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def positive(name: str, value: object) -> float:
    v = finite_scalar(name, value)
    if v <= 0:
        raise ValueError(f"{name} must be positive, got {v}")
    return v


# ------------------------------------------------------------------------------ paths
#: Largest configuration file read whole (bytes): a real one is a few kB; the cap keeps a
#: wrong path (a huge file, /dev/zero behind a symlink that grew) from eating memory.
CONFIG_MAX_BYTES = 4 * 1024 * 1024


class PathError(ValueError):
    """A user-given path that cannot be used (missing, not a regular file, too large).

    The message names the option or key it came from and the path.
    """


def file_kind(mode: int) -> str:
    """What a ``st_mode`` is, for messages ("a FIFO", "a folder", ...)."""
    for test, name in (
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def regular_file(name: str, path: str | os.PathLike[str], max_bytes: int | None = None) -> Path:
    """``path`` as a Path after checking it is an existing regular file (symlinks followed).

    A FIFO, device, folder or socket is refused before anything opens it (opening a FIFO
    blocks until a writer comes; /dev/zero never ends). ``max_bytes``: also refuse a larger
    file (for files read whole). Raises :class:`PathError` naming ``name`` and the path.
    """
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise PathError(f"{name}: {p}: no such file") from None
    except OSError as exc:
        raise PathError(f"{name}: {p}: {exc.strerror or exc}") from exc
    if not stat.S_ISREG(st.st_mode):
        raise PathError(f"{name}: {p} is {file_kind(st.st_mode)}, not a regular file")
    if max_bytes is not None and st.st_size > max_bytes:
        raise PathError(
            f"{name}: {p} is {st.st_size} bytes, larger than the {max_bytes}-byte limit"
        )
    return p


def read_text_capped(name: str, path: str | os.PathLike[str], max_bytes: int) -> str:
    """The text of a regular file of at most ``max_bytes`` (UTF-8); :class:`PathError` else.

    Reads at most ``max_bytes + 1`` bytes, so a file that grows after the check still
    cannot eat memory.
    """
    p = regular_file(name, path, max_bytes)
    try:
        with open(p, "rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise PathError(f"{name}: cannot read {p}: {exc.strerror or exc}") from exc
    if len(data) > max_bytes:
        raise PathError(f"{name}: {p} is larger than the {max_bytes}-byte limit")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise PathError(f"{name}: {p} is not UTF-8 text: {exc}") from exc


def output_file(name: str, path: str | os.PathLike[str]) -> Path:
    """``path`` as a Path for writing: refused if it exists and is not a regular file (a FIFO
    would block the writer, a device would swallow the output). A path that does not exist
    (or cannot be looked at) is left to the writer, which names what is wrong."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:  # missing, or under a file: the writer says what is wrong with the folder
        return p
    if not stat.S_ISREG(st.st_mode):
        raise PathError(f"{name}: {p} exists and is {file_kind(st.st_mode)}, not a regular file")
    return p


# -------------------------------------------------------------------------- addresses
PORT_MIN, PORT_MAX = 1, 65535


def port_problem(port: str) -> str | None:
    """Why ``port`` (the text after the last ':') is not a TCP port in [1, 65535], or None."""
    try:
        n = int(port)
    except ValueError:
        return f"port {port!r} is not a number"
    if not PORT_MIN <= n <= PORT_MAX:
        return f"port {n} is outside {PORT_MIN}-{PORT_MAX}"
    return None


def zmq_endpoint_problem(address: str) -> str | None:
    """Why ``address`` is not a usable ZeroMQ endpoint, or None.

    ``tcp://HOST:PORT`` needs a port in [1, 65535] or ``*`` (any free port); other transports
    (ipc://, inproc://) need only a non-empty address.
    """
    scheme, sep, rest = address.partition("://")
    if not sep or not scheme or not rest:
        return f"not a ZeroMQ address: {address!r} (e.g. tcp://127.0.0.1:5555)"
    if scheme == "tcp":
        host, colon, port = rest.rpartition(":")
        if not colon or not host:
            return f"{address!r} has no port (e.g. tcp://127.0.0.1:5555, or :* for any)"
        if port != "*":
            problem = port_problem(port)
            if problem is not None:
                return f"{address!r}: {problem} (use :* for any free port)"
    return None


def zmq_endpoint(name: str, address: str) -> str:
    """``address`` after :func:`zmq_endpoint_problem`; ValueError naming ``name`` else."""
    problem = zmq_endpoint_problem(address)
    if problem is not None:
        raise ValueError(f"{name}: {problem}")
    return address


@dataclass(frozen=True)
class ParamRange:
    """Accepted values of one numeric key: finite and within [lo, hi] (``unit`` for messages;
    ``integer``: whole numbers only)."""

    lo: float
    hi: float
    unit: str = ""
    integer: bool = False

    def __str__(self) -> str:
        return self.text()

    def text(self) -> str:
        """``[lo, hi] unit`` as the messages and ``config dump`` show it."""
        unit = f" {self.unit}" if self.unit else ""
        return f"[{_num(self.lo, self.integer)}, {_num(self.hi, self.integer)}]{unit}"

    def problem(self, value: Any) -> str | None:
        """None when ``value`` is acceptable, else what is wrong with it (no key name)."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            kind = "an integer" if self.integer else "a number"
            return f"must be {kind} in {self.text()}, got {value!r}"
        if self.integer and not isinstance(value, int):
            return f"must be an integer in {self.text()}, got {value!r}"
        if not (math.isfinite(value) and self.lo <= value <= self.hi):
            return f"must be in {self.text()}, got {value!r}"
        return None


def _num(x: float, integer: bool) -> str:
    return str(int(x)) if integer else f"{x:g}"
