"""The control protocol: newline-delimited JSON on a Unix socket (docs/control.md).

The server greets every client with ``{"hapticd": VERSION, "protocol": 1}``. A
request is one JSON object per line: ``{"id": ANY, "cmd": NAME, ...}``; the
reply carries the same id and either ``"ok": true, "result": ...`` or
``"ok": false, "error": {"code": ..., "message": ...}``. Requests are checked
here, completely, before anything changes; a bad one changes nothing. Parameters
and their ranges are declared in ``hapticd.params``. Standard library only.
"""

from __future__ import annotations

import json
import math
from typing import Any

from hapticd import params

PROTOCOL_VERSION = 1
MAX_LINE_BYTES = 64 * 1024


class ProtocolError(ValueError):
    """A request that cannot be served: ``code`` says which kind, the message what was wrong."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ProtocolError("bad_value", f"{name} must be a finite number, got {value!r}")
    return float(value)


COMMANDS = (
    "status",
    "get",
    "set",
    "enable",
    "disable",
    "record_start",
    "record_stop",
    "reload",
    "subscribe",
    "unsubscribe",
    "shutdown",
    "stop",
)
TELEMETRY_RATE_HZ = (0.1, 1000.0)


def greeting(version: str) -> bytes:
    return encode({"hapticd": version, "protocol": PROTOCOL_VERSION})


def encode(obj: dict[str, Any]) -> bytes:
    return (json.dumps(obj, separators=(",", ":")) + "\n").encode("utf-8")


def parse_request(line: bytes) -> dict[str, Any]:
    """A checked request; ProtocolError for anything malformed, unknown or out of range."""
    if len(line) > MAX_LINE_BYTES:
        raise ProtocolError("too_large", f"request longer than {MAX_LINE_BYTES} bytes")
    try:
        req = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ProtocolError("malformed", f"not a JSON object: {exc}") from None
    if not isinstance(req, dict):
        raise ProtocolError("malformed", "a request must be a JSON object")
    cmd = req.get("cmd")
    if cmd not in COMMANDS:
        raise ProtocolError("unknown_command", f"unknown cmd {cmd!r}; commands: {list(COMMANDS)}")
    if cmd in ("get", "set"):
        name = req.get("param")
        if not (isinstance(name, str) and name in params.PARAMS):
            raise ProtocolError("unknown_param", params.unknown_message(name))
        if cmd == "set":
            if "value" not in req:
                raise ProtocolError("malformed", "set needs a value")
            try:
                req["value"] = params.PARAMS[name].check(req["value"])
            except params.ParamError as exc:
                raise ProtocolError(exc.code, str(exc)) from None
    elif cmd == "record_start":
        path = req.get("path")
        if not (isinstance(path, str) and path.startswith("/")):
            raise ProtocolError("bad_value", f"record_start needs an absolute 'path', got {path!r}")
        if not isinstance(req.get("overwrite", False), bool):
            raise ProtocolError("bad_value", "'overwrite' must be true or false")
    elif cmd == "reload":
        path = req.get("profile")
        if path is not None and not (isinstance(path, str) and path.startswith("/")):
            raise ProtocolError(
                "bad_value", f"reload's 'profile' must be an absolute path, got {path!r}"
            )
    elif cmd == "subscribe":
        rate = _number(req.get("rate_hz", 30.0), "rate_hz")
        lo, hi = TELEMETRY_RATE_HZ
        if not lo <= rate <= hi:
            raise ProtocolError("out_of_range", f"rate_hz must be in [{lo}, {hi}], got {rate}")
        req["rate_hz"] = rate
    return req


def telemetry(sample: dict[str, Any]) -> bytes:
    """A telemetry line (no id: it answers no request)."""
    return encode({"telemetry": sample})


def ok(req_id: Any, result: Any) -> bytes:
    return encode({"id": req_id, "ok": True, "result": result})


def error(req_id: Any, code: str, message: str) -> bytes:
    return encode({"id": req_id, "ok": False, "error": {"code": code, "message": message}})
