"""Control requests (ControlRequest on the daemon's ROUTER socket): get_mesh, get_config,
get_status, set_params, tare, set_auto_zero, record_start, record_stop. Every answer is a ControlReply;
bad input is refused with a message naming what is wrong, never raised."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from bubble_rt.config import DaemonConfig, EstimatorSection, param_problem
from bubble_rt.daemon import faults
from bubble_rt.io import protocol
from bubble_rt.io.protocol import pb


class Controlled(Protocol):
    """What the requests need from the daemon (``bubble_rt.daemon.service.Daemon``)."""

    config: DaemonConfig
    mesh_msg: Any
    processor: Any
    recorder: Any

    def status_message(self, stopped: bool = False) -> Any: ...

    def request_tare(self) -> None: ...

    def start_recording(self, path: str, overwrite: bool = False) -> None: ...

    def queue_params(self, params: dict[str, float]) -> EstimatorSection: ...

    def set_auto_zero(self, enabled: bool) -> None: ...


def validate_params(
    params: dict[str, float], accepted: tuple[str, ...] | None = None
) -> str | None:
    """None when the Params are acceptable, else the error text naming the parameter.

    ``accepted``: the parameters the running estimator has (its kind's ``params``); any other
    is refused. The ranges are the configuration's (``bubble_rt.config.ESTIMATOR_RANGES``):
    nothing is applied unless every value given is acceptable."""
    if not params:
        return "set_params: no parameter given (set one of " + ", ".join(protocol.PARAM_NAMES) + ")"
    if accepted is not None:
        lacking = [k for k in params if k not in accepted]
        if lacking:
            return (
                f"set_params: the running estimator has no parameter {', '.join(lacking)} "
                f"(it has {', '.join(accepted)}); nothing changed"
            )
    for k, v in params.items():
        err = param_problem(k, v)
        if err:
            return f"set_params: {k} {err}"
    return None


def handle_request(d: Controlled, payload: bytes) -> Any:
    """Answer one serialized ControlRequest for daemon ``d`` (never raises for bad input)."""
    try:
        kind, req = protocol.parse_request(payload)
    except protocol.ProtocolError as exc:
        return protocol.error_reply(str(exc))
    if kind == "get_mesh":
        if d.mesh_msg is None:
            return protocol.error_reply(
                "mesh not ready: the daemon is still capturing the reference frames"
            )
        return protocol.ok_reply(mesh=d.mesh_msg)
    if kind == "get_config":
        return protocol.ok_reply(config_toml=d.config.to_toml())
    if kind == "get_status":
        return protocol.ok_reply(status=d.status_message())
    if kind == "set_params":
        return _set_params(d, protocol.params_dict(req.set_params))
    if kind == "tare":
        if d.processor is None:
            return protocol.error_reply("tare: the reference is still being captured")
        d.request_tare()
        return protocol.ok_reply()
    if kind == "set_auto_zero":
        d.set_auto_zero(bool(req.set_auto_zero.enabled))
        return protocol.ok_reply(status=d.status_message())
    if kind == "record_start":
        rec = d.recorder
        if rec is not None and not rec.failed:
            return protocol.error_reply(f"already recording to {rec.path}")
        try:
            path = faults.recording_path(req.record_start.path, d.config.recording.directory)
            d.start_recording(str(path), req.record_start.overwrite)
        except Exception as exc:
            return protocol.error_reply(f"record_start: refused: {exc}")
        if rec is not None:  # a failed recording is replaced by the new one
            rec.close(timeout=0.0)
        return protocol.ok_reply(recording_path=str(path.resolve()))
    if kind == "record_stop":
        rec = d.recorder
        if rec is None:
            return protocol.error_reply("record_stop: not recording")
        d.recorder = None
        ok, text = faults.stop_recorder(rec)
        if not ok:
            return protocol.error_reply(text)
        return protocol.ok_reply(recording_path=text)
    return protocol.error_reply(f"unknown request {kind!r}")  # pragma: no cover


def _set_params(d: Controlled, params: dict[str, float]) -> Any:
    from bubble_rt.estimation.registry import estimator_kind

    # The kind cannot change while running: the config's kind is the running estimator's.
    err = validate_params(params, estimator_kind(d.config.estimator.kind).params)
    if err:
        return protocol.error_reply(err)
    est = d.queue_params(params)
    rec = d.recorder
    if rec is not None:  # the recording keeps what its forces depend on
        faults.write_settings(rec, d.config)
    return protocol.ok_reply(params=pb.Params(**{k: getattr(est, k) for k in protocol.PARAM_NAMES}))


__all__ = ["handle_request", "validate_params"]


def reply_frames(frames: list[bytes], handle: Callable[[bytes], Any]) -> list[bytes]:
    """The ROUTER reply to one received multipart: the sender's envelope and the serialized
    ControlReply of ``handle`` (a malformed request, or one ``handle`` fails on, gets an
    error reply: the daemon never dies on a request)."""
    ident, rest = frames[0], frames[1:]
    envelope = [ident]
    if rest and rest[0] == b"":
        envelope.append(b"")
        rest = rest[1:]
    if len(rest) != 1:
        reply = protocol.error_reply(
            f"malformed request: expected exactly one message frame, got {len(rest)}"
        )
    else:
        try:
            reply = handle(rest[0])
        except Exception as exc:
            reply = protocol.error_reply(f"internal error: {type(exc).__name__}: {exc}")
    return [*envelope, reply.SerializeToString()]
