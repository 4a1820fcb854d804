"""The live Foxglove view beside the ZeroMQ stream: a foxglove-sdk WebSocket server fed by a
worker thread, so building the scene never delays publishing (messages from
``bubble_rt.io.foxglove``)."""

from __future__ import annotations

import logging
import threading
from typing import Any

from bubble_rt.daemon.sources import Mailbox
from bubble_rt.io.foxglove import (
    DEFAULT_ADDRESS,
    Encoded,
    SceneBuilder,
    channel_specs,
    parse_address,
)


class _OneLinePerClient(logging.Filter):
    """foxglove-sdk logs a client's connection on ``foxglove.websocket.server`` ("Registered
    client ...") and then two or three more lines when it leaves ("Connection closed by
    client", "Unregistered client", an ERROR for a reset without closing handshake, which a
    browser tab closing does). Keep the one line per connection."""

    DROP = ("Unregistered client", "Connection closed by client", "Error receiving from client")

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith(self.DROP)


_ONE_LINE = _OneLinePerClient()


def quiet_client_logs() -> None:
    """Install the one-line-per-client filter on foxglove-sdk's loggers (idempotent)."""
    for name in ("foxglove.websocket.server", "foxglove.websocket.connected_client.poller"):
        logger = logging.getLogger(name)
        if _ONE_LINE not in logger.filters:
            logger.addFilter(_ONE_LINE)


class FoxgloveView:
    """The daemon's Foxglove output: a WebSocket server plus the same channels into the
    daemon's MCAP recorder. The daemon calls ``on_frame``/``on_status`` (non-blocking: the
    newest frame waits in a one-item slot, a worker thread builds and sends it) and ``close``.
    """

    def __init__(
        self,
        address: str | None = DEFAULT_ADDRESS,
        *,
        serve: bool = True,
        builder: SceneBuilder | None = None,
    ) -> None:
        import foxglove

        self.builder = builder or SceneBuilder()
        self.context = foxglove.Context()
        self.server: Any = None
        self.address = ""
        if serve:
            quiet_client_logs()
            host, port = parse_address(address)
            self.server = foxglove.start_server(
                name="bubble_rt", host=host, port=port, context=self.context
            )
            self.address = f"ws://{host}:{self.server.port}"
        self._channels: dict[str, Any] = {}
        for spec in channel_specs():
            self._channel(spec)
        self._slot: Mailbox[tuple[Any, Any, Any, Any]] = Mailbox()
        self._stop = threading.Event()
        self.sent = 0
        self.error = ""
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._loop, name="foxglove", daemon=True)
        self._thread.start()

    @property
    def dropped(self) -> int:
        return self._slot.dropped

    # ------------------------------------------------------------ daemon hooks
    def on_frame(
        self,
        frame: Any,
        force_msg: Any,
        mesh_msg: Any,
        recorder: Any = None,
    ) -> None:
        self._slot.put((frame, force_msg, mesh_msg, recorder))

    def on_status(self, msg: Any, recorder: Any = None) -> None:
        try:
            self._emit([self.builder.status(msg)], recorder)
        except Exception as exc:
            self.error = self.error or f"{type(exc).__name__}: {exc}"

    def close(self) -> None:
        self._stop.set()
        self._slot.close()
        self._thread.join(2.0)
        if self.server is not None:
            self.server.stop()
            self.server = None

    # ------------------------------------------------------------ worker
    def _loop(self) -> None:
        while not self._stop.is_set():
            item = self._slot.get(timeout=0.1)
            if item is None:
                continue
            frame, force_msg, mesh_msg, recorder = item
            try:
                self._emit(self.builder.frame(force_msg, mesh_msg, frame), recorder)
            except Exception as exc:  # never take the daemon down; report the first fault
                self.error = self.error or f"{type(exc).__name__}: {exc}"

    def _channel(self, m: Encoded) -> Any:
        import foxglove

        ch = self._channels.get(m.topic)
        if ch is None:
            ch = foxglove.Channel(
                m.topic,
                schema=foxglove.Schema(
                    name=m.schema_name, encoding=m.schema_encoding, data=m.schema_data
                ),
                message_encoding=m.message_encoding,
                context=self.context,
            )
            self._channels[m.topic] = ch
        return ch

    def _emit(self, msgs: list[Encoded], recorder: Any) -> None:
        with self._lock:
            for m in msgs:
                self._channel(m).log(m.data, log_time=m.log_time_ns)
                if recorder is not None:
                    recorder.write_message(m.topic, m, m.log_time_ns / 1e9)
                self.sent += 1
