"""The control protocol: newline-delimited JSON on a Unix socket (docs/control.md).

The server greets every client with ``{"hapticd": VERSION, "protocol": 1}``. A
request is one JSON object per line: ``{"id": ANY, "cmd": NAME, ...}``; the
reply carries the same id and either ``"ok": true, "result": ...`` or
``"ok": false, "error": {"code": ..., "message": ...}``. Requests are checked
here, completely, before anything changes; a bad one changes nothing.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from hapticd.allocation import METHODS

PROTOCOL_VERSION = 1
MAX_LINE_BYTES = 64 * 1024


class ProtocolError(ValueError):
    """A request that cannot be served: ``code`` says which kind, the message what was wrong."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Param:
    """A settable parameter: its range (SI units in its name) and how to check a value."""

    name: str
    lo: float | None = None
    hi: float | None = None

    def check(self, value: Any) -> Any:
        if self.name == "allocator":
            if value not in METHODS:
                raise ProtocolError(
                    "bad_value", f"allocator must be one of {list(METHODS)}, got {value!r}"
                )
            return value
        if self.name == "actuated_directions":
            return _directions(value)
        if self.name == "friction":
            if not (isinstance(value, list | tuple) and len(value) == 2):
                raise ProtocolError("bad_value", "friction must be [static, dynamic]")
            s, d = (_number(v, "friction") for v in value)
            if not (0 <= d <= s <= 5):
                raise ProtocolError(
                    "bad_value", f"friction needs 0 <= dynamic <= static <= 5, got {value}"
                )
            return (s, d)
        x = _number(value, self.name)
        if (self.lo is not None and x < self.lo) or (self.hi is not None and x > self.hi):
            raise ProtocolError(
                "out_of_range", f"{self.name} must be in [{self.lo}, {self.hi}], got {x}"
            )
        return x


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ProtocolError("bad_value", f"{name} must be a finite number, got {value!r}")
    return float(value)


def _directions(value: Any) -> list[list[tuple[float, float, float]]]:
    """Per-finger lists of unit 3-vectors (normalised here; zero or non-finite rejected)."""
    msg = "actuated_directions must be a list per finger of [x, y, z] directions"
    if not isinstance(value, list) or not all(isinstance(ds, list) for ds in value):
        raise ProtocolError("bad_value", msg)
    out = []
    for i, ds in enumerate(value):
        finger = []
        for j, d in enumerate(ds):
            if not (isinstance(d, list) and len(d) == 3):
                raise ProtocolError("bad_value", f"{msg}; finger {i} direction {j} is {d!r}")
            x, y, z = (_number(v, f"actuated_directions[{i}][{j}]") for v in d)
            n = math.sqrt(x * x + y * y + z * z)
            if n < 1e-9:
                raise ProtocolError("bad_value", f"actuated_directions[{i}][{j}] is zero")
            finger.append((x / n, y / n, z / n))
        out.append(finger)
    return out


PARAMS: dict[str, Param] = {
    "stiffness_n_per_m": Param("stiffness_n_per_m", 1e-3, 1e5),
    "damping_n_s_per_m": Param("damping_n_s_per_m", 0.0, 1e3),
    "mass_kg": Param("mass_kg", 1e-3, 10.0),
    "friction": Param("friction"),
    "allocator": Param("allocator"),
    "force_limit_n": Param("force_limit_n", 0.01, 50.0),
    "actuated_directions": Param("actuated_directions"),
}
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
        if name not in PARAMS:
            raise ProtocolError(
                "unknown_param", f"unknown param {name!r}; params: {sorted(PARAMS)}"
            )
        if cmd == "set":
            if "value" not in req:
                raise ProtocolError("malformed", "set needs a value")
            req["value"] = PARAMS[name].check(req["value"])
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
