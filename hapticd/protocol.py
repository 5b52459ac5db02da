"""The control protocol: newline-delimited JSON on a Unix socket (docs/control.md).

The server greets every client with ``{"hapticd": VERSION, "protocol": 1}``. A
request is one JSON object per line: ``{"id": ANY, "cmd": NAME, ...}``; the
reply carries the same id and either ``"ok": true, "result": ...`` or
``"ok": false, "error": {"code": ..., "message": ...}``. Requests are checked
here, completely, before anything changes; a bad one changes nothing. Parameters
and their ranges are declared in ``hapticd.params``, event kinds in
``hapticd.events``. Lines that answer no request: ``{"telemetry": {...}}`` after
``subscribe``, and events (``{"event": NAME, "tick": ..., ...}``) after
``events_subscribe``. Standard library only.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

from hapticd import events, params

PROTOCOL_VERSION = 1

# Every error code a reply (or the client, for a greeting) can carry: what it means, and
# whether the request itself was at fault (True: a command line exits 2) or the state of
# the daemon or the connection (False: exit 1). docs/control.md lists them (a test checks).
ERRORS: dict[str, tuple[str, bool]] = {
    "malformed": ("not a JSON object", True),
    "bad_request": (
        "nested too deeply; an `id`, `cmd` or `param` of the wrong JSON type; a missing argument",
        True,
    ),
    "too_large": ("a line over 64 KiB: one reply, the line discarded up to its newline", True),
    "unknown_command": ("no such command", True),
    "unknown_param": ("no such parameter (hapticd.params)", True),
    "bad_value": ("a value of the wrong type or form, NaN or Infinity anywhere", True),
    "out_of_range": ("a number outside the parameter's range", True),
    "bad_profile": ("reload: the profile is not valid (the message names file and key)", True),
    "rejected": ("the loop refused (already recording, not recording, ...)", False),
    "recording": ("the recording file exists, is outside the directory, or failed", False),
    "timeout": ("the loop is not running", False),
    "stopped": ("the loop has ended (the message says why: its trajectory ended, ...)", False),
    "busy": (
        "sent instead of the greeting when every place is in use (`clients`: how many), or "
        "to a subscription beyond the subscribers' places",
        False,
    ),
    "idle": ("sent, unasked, to a connection closed for sending no request in time", False),
    "denied": (
        "reload of a profile outside the allowed directories by a client not the daemon's user",
        False,
    ),
    "no_prompt": ("`respond` to a prompt that is not the current one", False),
    "leased": (
        "another connection holds the daemon's lease (an experiment runs): the message "
        "names its subject and process",
        False,
    ),
    "internal": ("a bug in the daemon", False),
    "version": ("the daemon speaks another protocol version (the client's check)", False),
}
# The codes that say the request itself was wrong.
BAD_REQUEST = frozenset(code for code, (_, bad) in ERRORS.items() if bad)
MAX_LINE_BYTES = 64 * 1024
MAX_DEPTH = 8  # JSON nesting of a request (actuated_directions needs 4)
MAX_ID_CHARS = 256
MAX_PATH_BYTES = 4096


class ProtocolError(ValueError):
    """A request that cannot be served: ``code`` says which kind, the message what was wrong."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ProtocolError("bad_value", f"{name} must be a finite number, got {short(value)}")
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
    "events_subscribe",
    "events_unsubscribe",
    "prompt",
    "respond",
    "screen",
    "mark",
    "move",
    "lease",
    "release",
    "shutdown",
    "stop",
)
TELEMETRY_RATE_HZ = (0.1, 1000.0)
# While a connection holds the lease (an experiment runs: docs/control.md, "The lease"),
# these change the trial under it and are refused to every other connection. Taking
# forces away (disable, stop), enable, reading, subscribing, respond and move never are.
LEASED_COMMANDS = frozenset(
    {"set", "reload", "record_start", "record_stop", "prompt", "screen", "mark"}
)
LEASE_SUBJECT = re.compile(r"[A-Za-z0-9_.-]{1,64}")
# The subject prompt (docs/control.md, "The subject prompt").
PROMPT_QUESTION_CHARS = 200
PROMPT_CHOICES = (2, 4)
CHOICE_PATTERN = re.compile(r"[a-z0-9_-]{1,16}")
# The subject's screen (docs/control.md, "The subject's screen"): what the subject's page
# shows besides the prompt, text only (nothing of the condition: the runner sends words).
SCREEN_STATES = ("instructions", "wait", "touch", "release", "answer", "feedback", "break", "end")
SCREEN_TEXT_CHARS = 2000
SCREEN_MAX_S = 3600.0  # a countdown's seconds
SCREEN_MAX_TRIALS = 1_000_000  # progress: trials done and in all
# Each key of a screen and whether it must be there.
SCREEN_KEYS = {
    "state": True,
    "text": False,
    "practice": False,
    "progress": False,
    "seconds": False,
    "correct": False,
    "scene": False,
}


def screen_text_ok(text: object) -> bool:
    """Text a screen may show: a string of at most SCREEN_TEXT_CHARS, printable but for
    line breaks (instructions have paragraphs)."""
    return (
        isinstance(text, str)
        and len(text) <= SCREEN_TEXT_CHARS
        and text.replace("\n", "").isprintable()
    )


# A `mark`'s text: a marker for the lab's other recordings (docs/lsl.md).
MARK_TEXT_CHARS = 200


def greeting(version: str) -> bytes:
    return encode({"hapticd": version, "protocol": PROTOCOL_VERSION})


def encode(obj: dict[str, Any]) -> bytes:
    return (json.dumps(obj, separators=(",", ":")) + "\n").encode("utf-8")


def _no_constant(word: str) -> Any:
    raise ProtocolError("bad_value", f"{word} is not a number JSON allows (no NaN or Infinity)")


def too_deep(obj: Any, limit: int) -> bool:
    """True if ``obj`` (parsed JSON) nests deeper than ``limit`` (iteratively: no recursion)."""
    todo: list[tuple[Any, int]] = [(obj, 1)]
    while todo:
        node, d = todo.pop()
        if isinstance(node, dict | list):
            if d > limit:
                return True
            todo.extend((v, d + 1) for v in (node.values() if isinstance(node, dict) else node))
    return False


def decode(line: bytes) -> dict[str, Any]:
    """One request line as a JSON object, its ``id`` checked; ProtocolError otherwise."""
    if len(line) > MAX_LINE_BYTES:
        raise ProtocolError("too_large", f"request longer than {MAX_LINE_BYTES} bytes")
    try:
        req = json.loads(line.decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ProtocolError("malformed", f"not a JSON object: {exc}") from None
    except RecursionError:
        raise ProtocolError(
            "bad_request", f"request nested too deeply (at most {MAX_DEPTH} levels)"
        ) from None
    if not isinstance(req, dict):
        raise ProtocolError("malformed", "a request must be a JSON object")
    if too_deep(req, MAX_DEPTH):
        raise ProtocolError(
            "bad_request", f"request nested too deeply (at most {MAX_DEPTH} levels)"
        )
    rid = req.get("id")
    ok_id = rid is None or (
        (isinstance(rid, str) and len(rid) <= MAX_ID_CHARS)
        or (isinstance(rid, int) and not isinstance(rid, bool) and abs(rid) < 2**63)
        or (isinstance(rid, float) and math.isfinite(rid))
    )
    if not ok_id:
        req.pop("id", None)  # not echoed: the reply's id is null
        raise ProtocolError(
            "bad_request",
            f"'id' must be a string of at most {MAX_ID_CHARS} characters, a number or null",
        )
    return req


def request_id(req: dict[str, Any]) -> Any:
    """The id to echo in the reply to ``req`` (a decoded request)."""
    return req.get("id")


def parse_request(line: bytes) -> dict[str, Any]:
    """A checked request; ProtocolError for anything malformed, unknown or out of range."""
    return check(decode(line))


def check(req: dict[str, Any]) -> dict[str, Any]:
    """Check a decoded request completely; ProtocolError names what is wrong."""
    cmd = req.get("cmd")
    if not isinstance(cmd, str):
        raise ProtocolError(
            "bad_request" if "cmd" in req else "unknown_command",
            f"'cmd' must be a command name; commands: {list(COMMANDS)}",
        )
    if cmd not in COMMANDS:
        raise ProtocolError(
            "unknown_command", f"unknown cmd {cmd[:64]!r}; commands: {list(COMMANDS)}"
        )
    if cmd in ("get", "set"):
        name = req.get("param")
        if name is not None and not isinstance(name, str):
            raise ProtocolError(
                "bad_request",
                f"'param' must be a parameter's name (a string); params: "
                f"{', '.join(params.PARAMS)}",
            )
        if not (isinstance(name, str) and name in params.PARAMS):
            shown = name if name is None or len(name) <= 64 else name[:64] + "..."
            raise ProtocolError("unknown_param", params.unknown_message(shown))
        if cmd == "set":
            if "value" not in req:
                raise ProtocolError("malformed", "set needs a value")
            try:
                req["value"] = params.PARAMS[name].check(req["value"])
            except params.ParamError as exc:
                raise ProtocolError(exc.code, str(exc)) from None
    elif cmd == "record_start":
        path = req.get("path")
        if not (
            isinstance(path, str)
            and path
            and "\x00" not in path
            and len(path.encode("utf-8", "replace")) <= MAX_PATH_BYTES
        ):
            raise ProtocolError(
                "bad_value",
                "record_start needs a 'path': a file name in the daemon's recording "
                f"directory (or an absolute path inside it), got {short(path)}",
            )
        if not isinstance(req.get("overwrite", False), bool):
            raise ProtocolError("bad_value", "'overwrite' must be true or false")
    elif cmd == "reload":
        path = req.get("profile")
        if path is not None and not (
            isinstance(path, str)
            and path.startswith("/")
            and "\x00" not in path
            and len(path.encode("utf-8", "replace")) <= MAX_PATH_BYTES
        ):
            raise ProtocolError(
                "bad_value", f"reload's 'profile' must be an absolute path, got {short(path)}"
            )
    elif cmd == "subscribe":
        rate = _number(req.get("rate_hz", 30.0), "rate_hz")
        lo, hi = TELEMETRY_RATE_HZ
        if not lo <= rate <= hi:
            raise ProtocolError("out_of_range", f"rate_hz must be in [{lo}, {hi}], got {rate}")
        req["rate_hz"] = rate
    elif cmd == "events_subscribe" and "kinds" in req:
        kinds = req["kinds"]
        if not (
            isinstance(kinds, list)
            and kinds
            and len(kinds) <= len(events.NAMES)
            and all(isinstance(k, str) and k in events.CODES for k in kinds)
        ):
            raise ProtocolError(
                "bad_value",
                f"'kinds' must be a list of event names from {list(events.NAMES)}, "
                f"got {short(kinds)}",
            )
    elif cmd == "lease":
        subject = req.get("subject")
        if not (isinstance(subject, str) and LEASE_SUBJECT.fullmatch(subject)):
            raise ProtocolError(
                "bad_request" if subject is None else "bad_value",
                f"lease needs a 'subject': 1 to 64 of A-Z a-z 0-9 _ . -, got {short(subject)}",
            )
        pid = req.get("pid")
        if pid is not None and (isinstance(pid, bool) or not isinstance(pid, int) or pid < 0):
            raise ProtocolError(
                "bad_value", f"lease's 'pid' must be an integer >= 0, got {short(pid)}"
            )
    elif cmd == "prompt":
        _check_prompt(req)
    elif cmd == "screen":
        _check_screen(req)
    elif cmd == "move":
        _check_move(req)
    elif cmd == "mark":
        text = req.get("text")
        if not (isinstance(text, str) and 1 <= len(text) <= MARK_TEXT_CHARS and text.isprintable()):
            raise ProtocolError(
                "bad_value",
                f"mark needs a 'text': printable text (no control characters) of 1 to "
                f"{MARK_TEXT_CHARS} characters, got {short(text)}",
            )
    elif cmd == "respond":
        _prompt_id(req, "respond")
        choice = req.get("choice")
        if not (isinstance(choice, str) and CHOICE_PATTERN.fullmatch(choice)):
            raise ProtocolError(
                "bad_value",
                f"respond needs a 'choice': one of the prompt's labels ([a-z0-9_-], 1 to 16 "
                f"characters), got {short(choice)}",
            )
    return req


MOVE_MAX_M = 10.0  # a move's coordinates, m: far beyond any workspace, but finite


def _check_move(req: dict[str, Any]) -> None:
    """A move request: ``finger`` (its name or index) and ``position_m`` (3 finite numbers,
    m, world frame, each within MOVE_MAX_M)."""
    finger = req.get("finger")
    if not (
        (isinstance(finger, str) and 1 <= len(finger) <= 64)
        or (isinstance(finger, int) and not isinstance(finger, bool) and 0 <= finger < 256)
    ):
        raise ProtocolError(
            "bad_value", f"move needs a 'finger': its name or index, got {short(finger)}"
        )
    pos = req.get("position_m")
    if not (
        isinstance(pos, list)
        and len(pos) == 3
        and all(
            isinstance(c, int | float)
            and not isinstance(c, bool)
            and math.isfinite(c)
            and abs(c) <= MOVE_MAX_M
            for c in pos
        )
    ):
        raise ProtocolError(
            "bad_value",
            f"move needs 'position_m': 3 finite numbers (m, world frame, within "
            f"{MOVE_MAX_M:g} m), got {short(pos)}",
        )


def _prompt_id(req: dict[str, Any], cmd: str) -> int:
    """The prompt's id of a prompt or respond request (its ``prompt`` key): an int >= 0.
    Not the request's ``id``, which stays the client's to match replies."""
    if "prompt" not in req:
        raise ProtocolError(
            "bad_request", f"{cmd} needs a 'prompt': the prompt's id, an integer >= 0"
        )
    pid = req["prompt"]
    if isinstance(pid, bool) or not isinstance(pid, int) or pid < 0:
        raise ProtocolError(
            "bad_value",
            f"{cmd}'s 'prompt' must be the prompt's id, an integer >= 0, got {short(pid)}",
        )
    return pid


def _check_prompt(req: dict[str, Any]) -> None:
    """A prompt request: ``prompt`` null clears; else ``question`` and ``choices`` as the spec
    (docs/control.md) says."""
    if "prompt" in req and req["prompt"] is None:
        return
    _prompt_id(req, "prompt")
    question = req.get("question")
    if not (
        isinstance(question, str)
        and 1 <= len(question) <= PROMPT_QUESTION_CHARS
        and question.isprintable()
    ):
        raise ProtocolError(
            "bad_value",
            f"prompt needs a 'question': printable text of 1 to {PROMPT_QUESTION_CHARS} "
            f"characters, got {short(question)}",
        )
    choices = req.get("choices")
    lo, hi = PROMPT_CHOICES
    if not (
        isinstance(choices, list)
        and lo <= len(choices) <= hi
        and all(isinstance(c, str) and CHOICE_PATTERN.fullmatch(c) for c in choices)
        and len(set(choices)) == len(choices)
    ):
        raise ProtocolError(
            "bad_value",
            f"prompt needs 'choices': {lo} to {hi} distinct labels of 1 to 16 characters "
            f"from a-z, 0-9, _ and -, got {short(choices)}",
        )


def _check_screen(req: dict[str, Any]) -> None:
    """A screen request: ``screen`` null clears; else an object of SCREEN_KEYS: ``state``
    one of SCREEN_STATES, ``text`` (screen_text_ok), ``practice``, ``correct`` and
    ``scene`` booleans (``correct`` may be null), ``progress`` [done, total] (0 <= done
    <= total <= SCREEN_MAX_TRIALS) or null, ``seconds`` (a countdown, 0 to SCREEN_MAX_S)
    or null."""
    if "screen" not in req:
        raise ProtocolError("bad_request", "screen needs a 'screen': an object, or null to clear")
    sc = req["screen"]
    if sc is None:
        return
    if not isinstance(sc, dict):
        raise ProtocolError("bad_value", f"'screen' must be an object or null, got {short(sc)}")
    unknown = [k for k in sc if k not in SCREEN_KEYS]
    if unknown:
        raise ProtocolError(
            "bad_value",
            f"screen: unknown key {short(unknown[0])}; the keys: {', '.join(SCREEN_KEYS)}",
        )
    if sc.get("state") not in SCREEN_STATES:
        raise ProtocolError(
            "bad_value",
            f"screen needs a 'state', one of {', '.join(SCREEN_STATES)}, got "
            f"{short(sc.get('state'))}",
        )
    if "text" in sc and not screen_text_ok(sc["text"]):
        raise ProtocolError(
            "bad_value",
            f"screen's 'text' must be printable text (line breaks allowed) of at most "
            f"{SCREEN_TEXT_CHARS} characters, got {short(sc['text'])}",
        )
    for key in ("practice", "scene", "correct"):
        v = sc.get(key, False)
        if not (isinstance(v, bool) or (key == "correct" and v is None)):
            raise ProtocolError("bad_value", f"screen's '{key}' must be true or false")
    prog = sc.get("progress")
    if prog is not None and not (
        isinstance(prog, list)
        and len(prog) == 2
        and all(isinstance(n, int) and not isinstance(n, bool) for n in prog)
        and 0 <= prog[0] <= prog[1] <= SCREEN_MAX_TRIALS
    ):
        raise ProtocolError(
            "bad_value",
            f"screen's 'progress' must be [done, total], integers 0 <= done <= total <= "
            f"{SCREEN_MAX_TRIALS}, or null, got {short(prog)}",
        )
    secs = sc.get("seconds")
    if secs is not None and not (0 <= _number(secs, "screen's 'seconds'") <= SCREEN_MAX_S):
        raise ProtocolError(
            "out_of_range", f"screen's 'seconds' must be in [0, {SCREEN_MAX_S:g}], got {secs}"
        )


def short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def is_event(msg: dict[str, Any]) -> bool:
    """Is this line from the server an event (not a reply, not telemetry)?"""
    return "event" in msg and "ok" not in msg


def telemetry(sample: dict[str, Any]) -> bytes:
    """A telemetry line (no id: it answers no request)."""
    return encode({"telemetry": sample})


def ok(req_id: Any, result: Any) -> bytes:
    return encode({"id": req_id, "ok": True, "result": result})


def error(req_id: Any, code: str, message: str, **more: Any) -> bytes:
    """An error reply; ``code`` one of ERRORS (a test checks every code the sources use);
    ``more``: further fields of the error object (``busy``: ``clients``)."""
    err = {"code": code, "message": message, **more}
    return encode({"id": req_id, "ok": False, "error": err})
