"""Client side of the bubble_rt protocol: a frame :class:`Subscriber` and a :class:`Controller`.

Needs only pyzmq, NumPy and the generated protocol (``bubble_rt.io.protocol``); it never imports
the estimator or the C++ core, so it runs anywhere the wheel installs.

    from bubble_rt.io.client import Subscriber
    with Subscriber("tcp://127.0.0.1:5555") as sub:
        print(sub.mesh.n_nodes)
        for frame in sub.frames(count=10):
            print(frame.seq, frame.net_force, frame.contact.sum())
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import zmq

from bubble_rt.io import protocol
from bubble_rt.io.protocol import ForceFrameData, MeshData, StatusData

DEFAULT_PUB = "tcp://127.0.0.1:5555"
DEFAULT_CONTROL = "tcp://127.0.0.1:5556"


class ControlError(RuntimeError):
    """The daemon answered a control request with an error (the text names the problem)."""


def control_address_for(pub_address: str) -> str | None:
    """The daemon's default control address beside a PUB address (tcp port + 1)."""
    if pub_address.startswith("tcp://") and ":" in pub_address[6:]:
        host, _, port = pub_address[6:].rpartition(":")
        if port.isdigit():
            return f"tcp://{host}:{int(port) + 1}"
    return None


class Controller:
    """Thin synchronous control client (REQ socket; one request at a time).

    Every call waits at most ``timeout_s``; on timeout the socket is reset (a REQ socket
    without a reply cannot send again) and :class:`TimeoutError` is raised.
    """

    def __init__(
        self,
        address: str = DEFAULT_CONTROL,
        timeout_s: float = 2.0,
        context: zmq.Context | None = None,
    ) -> None:
        self.address = address
        self.timeout_s = timeout_s
        self._ctx = context or zmq.Context.instance()
        self._sock: zmq.Socket | None = None

    def _socket(self) -> zmq.Socket:
        if self._sock is None:
            s = self._ctx.socket(zmq.REQ)
            s.setsockopt(zmq.LINGER, 0)
            s.connect(self.address)
            self._sock = s
        return self._sock

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close(linger=0)
            self._sock = None

    def __enter__(self) -> Controller:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def send_raw(self, payload: bytes, timeout_s: float | None = None) -> Any:
        """Send raw bytes as a request and return the decoded reply (errors included).

        A request over the control socket's ZMQ_MAXMSGSIZE is not sent (ZeroMQ would drop the
        connection without a reply): the error reply is made here.
        """
        if len(payload) > protocol.MAX_MESSAGE_BYTES:
            return protocol.error_reply(protocol.too_large(len(payload)))
        sock = self._socket()
        sock.send(payload)
        if not sock.poll(int(1000 * (timeout_s or self.timeout_s))):
            self.close()
            raise TimeoutError(
                f"no reply from {self.address} within {timeout_s or self.timeout_s} s"
            )
        return protocol.parse_reply(sock.recv())

    def request(self, kind: str, **fields: Any) -> Any:
        """Send a request; returns the reply, raises :class:`ControlError` if not ok."""
        rep = self.send_raw(protocol.make_request(kind, **fields).SerializeToString())
        if not rep.ok:
            raise ControlError(rep.error)
        return rep

    def get_mesh(self) -> MeshData:
        return protocol.decode_mesh(self.request("get_mesh").mesh)

    def get_config(self) -> str:
        """The daemon's effective configuration, TOML text."""
        return self.request("get_config").config_toml

    def set_params(self, **params: float) -> dict[str, float]:
        """Change estimator parameters (k_f, k_u, youngs_modulus, k_const, k_linear)."""
        return protocol.params_dict(self.request("set_params", **params).params)

    def tare(self) -> None:
        self.request("tare")

    def set_auto_zero(self, enabled: bool) -> None:
        """Turn re-zeroing (following the drift while untouched) on or off."""
        self.request("set_auto_zero", enabled=enabled)

    def record_start(self, path: str = "", overwrite: bool = False) -> str:
        """Start recording to ``path`` on the daemon's host (an existing file is refused
        unless ``overwrite``); returns the path being written."""
        return self.request("record_start", path=path, overwrite=overwrite).recording_path

    def record_stop(self) -> str:
        return self.request("record_stop").recording_path

    def status(self) -> StatusData:
        return protocol.decode_status(self.request("get_status").status)


class Subscriber:
    """Receives force frames (and status) from a daemon's PUB socket.

    ``sensor_id`` "" subscribes to every sensor on the socket. ``mesh`` is fetched over the
    control socket on first use (waiting while the daemon is still starting).
    """

    def __init__(
        self,
        address: str = DEFAULT_PUB,
        control: str | None = None,
        sensor_id: str = "",
        timeout_s: float = 10.0,
        conflate: bool = False,
        context: zmq.Context | None = None,
    ) -> None:
        self.address = address
        self.control_address = control or control_address_for(address)
        self.sensor_id = sensor_id
        self.timeout_s = timeout_s
        self._ctx = context or zmq.Context.instance()
        self._sock = self._ctx.socket(zmq.SUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.RCVHWM, 1 if conflate else 100)
        self._sock.setsockopt(zmq.SUBSCRIBE, protocol.force_topic(sensor_id))
        self._sock.setsockopt(zmq.SUBSCRIBE, protocol.status_topic(sensor_id))
        self._sock.connect(address)
        self._mesh: MeshData | None = None
        self.status: StatusData | None = None

    def close(self) -> None:
        self._sock.close(linger=0)

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def mesh(self) -> MeshData:
        if self._mesh is None:
            self._mesh = self.fetch_mesh(self.timeout_s)
        return self._mesh

    def fetch_mesh(self, timeout_s: float = 10.0) -> MeshData:
        """Ask the control socket for the mesh, retrying while the daemon starts."""
        if not self.control_address:
            raise ControlError("no control address: pass control=... to Subscriber")
        end = time.monotonic() + timeout_s
        last = ""
        with Controller(
            self.control_address, timeout_s=min(2.0, timeout_s), context=self._ctx
        ) as c:
            while time.monotonic() < end:
                try:
                    self._mesh = c.get_mesh()
                    return self._mesh
                except (ControlError, TimeoutError) as exc:
                    last = str(exc)
                    time.sleep(0.1)
        raise TimeoutError(f"no mesh from {self.control_address} within {timeout_s} s: {last}")

    def recv(self, timeout_s: float | None = None) -> ForceFrameData | StatusData | None:
        """The next message (frame or status), or None after ``timeout_s``."""
        t = self.timeout_s if timeout_s is None else timeout_s
        if not self._sock.poll(int(1000 * t)):
            return None
        parts = self._sock.recv_multipart()
        if len(parts) != 2:
            return None
        topic, payload = parts
        if topic.startswith(protocol.FORCE_PREFIX.encode()):
            return protocol.decode_force_frame(payload)
        if topic.startswith(protocol.STATUS_PREFIX.encode()):
            self.status = protocol.decode_status(payload)
            return self.status
        return None

    def frames(
        self, count: int | None = None, timeout_s: float | None = None
    ) -> Iterator[ForceFrameData]:
        """Yield force frames; stops after ``count`` frames or ``timeout_s`` without one."""
        n = 0
        t = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + t
        while count is None or n < count:
            left = deadline - time.monotonic()
            if left <= 0:
                return
            msg = self.recv(left)
            if isinstance(msg, ForceFrameData):
                n += 1
                deadline = time.monotonic() + t
                yield msg

    def __iter__(self) -> Iterator[ForceFrameData]:
        return self.frames()
