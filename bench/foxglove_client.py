"""A minimal Foxglove WebSocket client (no project code, no websocket package): connects,
subscribes to every advertised channel and counts messages and bytes per topic.

    python3 bench/foxglove_client.py ws://127.0.0.1:8765 --seconds 10

Used by ``bench/daemon_bench.py --foxglove`` to measure the daemon with a viewer attached.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import socket
import struct
import sys
import threading
import time
from urllib.parse import urlparse


class FoxgloveClient:
    def __init__(self, host: str, port: int, timeout: float = 10.0) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
            ).encode()
        )
        self.buf = b""
        while b"\r\n\r\n" not in self.buf:
            self.buf += self._recv()
        head, self.buf = self.buf.split(b"\r\n\r\n", 1)
        if b" 101 " not in head.split(b"\r\n")[0]:
            raise ConnectionError(head.decode(errors="replace"))
        self.topics: dict[int, str] = {}
        self.counts: dict[str, int] = {}
        self.bytes = 0
        self._next_sub = 1
        self._subs: dict[int, str] = {}

    def _recv(self) -> bytes:
        chunk = self.sock.recv(1 << 20)
        if not chunk:
            raise ConnectionError("closed")
        return chunk

    def _take(self, n: int) -> bytes:
        while len(self.buf) < n:
            self.buf += self._recv()
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def recv(self) -> tuple[int, bytes]:
        data, opcode = b"", None
        while True:
            b0, b1 = self._take(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._take(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._take(8))[0]
            payload = self._take(n)
            if b0 & 0x0F in (9, 10):
                continue
            opcode = b0 & 0x0F if opcode is None else opcode
            data += payload
            if b0 & 0x80:
                return opcode, data

    def send_text(self, text: str) -> None:
        p = text.encode()
        mask = os.urandom(4)
        head = bytes([0x81])
        if len(p) < 126:
            head += bytes([0x80 | len(p)])
        else:
            head += bytes([0x80 | 126]) + struct.pack(">H", len(p))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(p)))

    def step(self) -> None:
        """Handle one message: subscribe to advertised channels, count data messages."""
        op, data = self.recv()
        if op == 1:
            m = json.loads(data)
            if m.get("op") == "advertise":
                subs = []
                for c in m["channels"]:
                    sid = self._next_sub
                    self._next_sub += 1
                    self._subs[sid] = c["topic"]
                    subs.append({"id": sid, "channelId": c["id"]})
                self.send_text(json.dumps({"op": "subscribe", "subscriptions": subs}))
        elif op == 2 and data and data[0] == 1:
            sid = struct.unpack_from("<I", data, 1)[0]
            topic = self._subs.get(sid, "?")
            self.counts[topic] = self.counts.get(topic, 0) + 1
            self.bytes += len(data)

    def run(self, stop: threading.Event) -> None:
        self.sock.settimeout(0.5)
        while not stop.is_set():
            try:
                self.step()
            except TimeoutError:
                continue
            except (ConnectionError, OSError):
                return

    def close(self) -> None:
        try:
            self.sock.sendall(bytes([0x88, 0x80]) + os.urandom(4))
        finally:
            self.sock.close()


def connect(address: str, timeout_s: float = 60.0) -> FoxgloveClient:
    """Connect, retrying until the server is up."""
    u = urlparse(address)
    end = time.monotonic() + timeout_s
    while True:
        try:
            return FoxgloveClient(u.hostname or "127.0.0.1", int(u.port or 8765))
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.2)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("address", nargs="?", default="ws://127.0.0.1:8765")
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args()
    c = connect(args.address)
    stop = threading.Event()
    th = threading.Thread(target=c.run, args=(stop,), daemon=True)
    th.start()
    time.sleep(args.seconds)
    stop.set()
    th.join(1.0)
    c.close()
    for t, n in sorted(c.counts.items()):
        print(f"{t}: {n / args.seconds:.1f} msg/s")
    print(f"total {c.bytes / args.seconds / 1e6:.2f} MB/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
