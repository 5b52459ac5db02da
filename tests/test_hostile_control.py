"""Hostile control messages, generated: malformed JSON, a wrong type at every field of every
command, deep nesting, huge lines, non-finite numbers, pipelined bursts and many clients at
once. Every line must get exactly one reply, strict JSON, with a request error code (never
``internal``), its id echoed when it had a valid one, within a deadline; the loop keeps
running and the recording that runs throughout loses no tick.

Run with ``-s`` to see each category's tally (tried / clear error / accepted / crash / hang).
"""

from __future__ import annotations

import itertools
import json
import random
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterator

import numpy as np
import pytest
import yaml

from hapticd import params, protocol, recording
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from tests.conftest import GRASP_PROFILE, IN_PROCESS

REPLY_TIMEOUT_S = 10.0
REQUEST_ERRORS = {
    "malformed",
    "bad_request",
    "too_large",
    "unknown_command",
    "unknown_param",
    "bad_value",
    "out_of_range",
    "rejected",
    "bad_profile",
    "recording",
}
# Valid requests of these commands act on the run (end it, swap the recording or profile):
# they are legitimate, not hostile, and are not sent.
NOT_SENT_WHEN_VALID = {"shutdown", "stop", "reload", "record_start", "record_stop"}
FIELDS = ("id", "cmd", "param", "value", "path", "overwrite", "profile", "rate_hz", "kinds")


def _scalars() -> list[object]:
    """One value of every JSON type class, with edge values of each."""
    ints = [0, 1, -1, 2**31, -(2**31), 2**63, 2**64, -(2**64), 10**30]
    floats = [0.5, -0.0, 1e-320, 1e308, -1e308, 1.7976931348623157e308]
    strings = ["", " ", "\x00", "\u202e", "é", "x" * 1000, "../../etc/passwd", "/dev/zero"]
    strings += ["/dev/stdin", "status", "stiffness_n_per_m", "NaN", "true", "{}", "\n"]
    return [None, True, False, *ints, *floats, *strings]


def _containers(leaf: object) -> list[object]:
    return [[], {}, [leaf], {"k": leaf}, [leaf, leaf, leaf], [[leaf]], [[[leaf]]], {"": {}}]


def hostile_values() -> list[object]:
    scalars = _scalars()
    return scalars + [c for leaf in (None, 1, "x", 1.5) for c in _containers(leaf)]


def _base(cmd: str) -> dict[str, object]:
    """A valid request of ``cmd``: the starting point of its mutations."""
    req: dict[str, object] = {"id": 1, "cmd": cmd}
    if cmd in ("get", "set"):
        req["param"] = "mass_kg"
    if cmd == "set":
        req["value"] = 0.2
    if cmd == "record_start":
        req["path"] = "x.hrec"
    if cmd == "subscribe":
        req["rate_hz"] = 1.0
    return req


def _dump(req: object) -> bytes:
    return json.dumps(req, allow_nan=True).encode()


def wrong_types() -> Iterator[bytes]:
    """Every command with every field replaced (or added) by every hostile value."""
    for cmd, field in itertools.product(protocol.COMMANDS, FIELDS):
        for v in hostile_values():
            req = _base(cmd)
            req[field] = v
            yield _dump(req)
        req = _base(cmd)
        if field in req:
            del req[field]
            yield _dump(req)
    for p in params.PARAMS:  # every parameter with every value
        for v in hostile_values():
            yield _dump({"id": 2, "cmd": "set", "param": p, "value": v})


def malformed_json() -> Iterator[bytes]:
    """Valid requests cut at every byte, bytes flipped, invalid UTF-8, random garbage and
    JSON that is not an object."""
    rng = random.Random(7)
    for cmd in protocol.COMMANDS:
        line = _dump(_base(cmd))
        for cut in range(len(line)):
            yield line[:cut]
        for i in rng.sample(range(len(line)), min(8, len(line))):
            yield line[:i] + bytes([line[i] ^ 0xFF]) + line[i + 1 :]
    for bad in (b"\xff", b"\xc3\x28", b"\xed\xa0\x80", b"\xf4\x90\x80\x80", b"\xc0\xaf"):
        yield b'{"id": 3, "cmd": "' + bad + b'"}'
    for v in _scalars():
        yield _dump(v)
    for _ in range(100):
        yield bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200))).replace(b"\n", b"")


def non_finite() -> Iterator[bytes]:
    """NaN and the infinities in every field of every command, and as the whole request."""
    for token, cmd, field in itertools.product(
        (b"NaN", b"Infinity", b"-Infinity"), protocol.COMMANDS, FIELDS
    ):
        req = _base(cmd)
        req[field] = "@@"
        yield _dump(req).replace(b'"@@"', token)
    yield b"NaN"
    yield b"[NaN]"


def deep_nesting() -> Iterator[bytes]:
    """Arrays and objects nested 1 to 100,000 deep, at the top, in the id and in a value."""
    for depth in (1, 2, 4, 7, 8, 9, 16, 100, 1000, 10_000, 21_000):
        arr = b"[" * depth + b"]" * depth
        obj = b'{"a":' * depth + b"1" + b"}" * depth
        for nested in (arr, obj):
            yield nested
            yield b'{"id": ' + nested + b', "cmd": "status"}'
            yield b'{"id": 4, "cmd": "set", "param": "friction", "value": ' + nested + b"}"
            yield b'{"id": 5, "cmd": "status", "extra": ' + nested + b"}"


def huge_lines() -> Iterator[bytes]:
    """Lines around the size limit, and far over it with a request as their tail."""
    limit = protocol.MAX_LINE_BYTES
    for size in (limit - 1, limit, limit + 1, 2 * limit, 1 << 20, 10_000_000):
        pad = b" " * max(size - 40, 0)
        yield b'{"id": 6, "cmd": "status"' + pad + b"}"
        yield b"x" * size + b'{"id": 7, "cmd": "shutdown"}'


CATEGORIES = {
    "malformed JSON": malformed_json,
    "wrong types": wrong_types,
    "non-finite numbers": non_finite,
    "deep nesting": deep_nesting,
    "huge lines": huge_lines,
}


def _expected(line: bytes) -> tuple[bool, object]:
    """(send it?, the id the reply must carry) for a line, judged by the protocol module."""
    try:
        req = protocol.parse_request(line)
    except protocol.ProtocolError:
        try:
            req = protocol.decode(line)
        except protocol.ProtocolError:
            return True, None
        return True, req.get("id")
    return req["cmd"] not in NOT_SENT_WHEN_VALID, req.get("id")


class Conn:
    """A raw client connection that reads reply lines (skipping telemetry and events) with a
    deadline."""

    def __init__(self, path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(REPLY_TIMEOUT_S)
        self.sock.connect(str(path))
        self.buf = b""
        self.next_line()  # greeting

    def next_line(self) -> bytes | None:
        """The next line, or None if none came within the deadline (a hang)."""
        deadline = time.monotonic() + REPLY_TIMEOUT_S
        while b"\n" not in self.buf:
            if time.monotonic() > deadline:
                return None
            try:
                chunk = self.sock.recv(1 << 20)
            except TimeoutError:
                return None
            if not chunk:
                raise ConnectionError("the daemon closed the connection")
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        return line

    def reply(self) -> dict | None:
        while True:
            line = self.next_line()
            if line is None:
                return None
            msg = json.loads(line, parse_constant=_reject)
            if "telemetry" not in msg and not protocol.is_event(msg):
                return msg

    def close(self) -> None:
        self.sock.close()


def _reject(word: str) -> object:
    raise ValueError(f"a reply holds {word}: not JSON")


def judge(reply: dict | None, want_id: object, tally: Counter, problems: list) -> None:
    """Count one reply: accepted, a clear error, a crash (internal, bad JSON) or a hang."""
    if reply is None:
        tally["hang"] += 1
        problems.append(("hang", want_id))
        return
    if reply.get("ok") is True:
        tally["accepted"] += 1
    elif reply.get("error", {}).get("code") in REQUEST_ERRORS and reply["error"].get("message"):
        tally["clear error"] += 1
    else:
        tally["crash"] += 1
        problems.append(("crash", reply))
    if reply.get("id") != want_id and not (want_id is None and reply.get("id") is None):
        tally["wrong id"] += 1
        problems.append(("wrong id", want_id, reply))


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    """A paced grasp run that does not end on its own (the devices hold their last
    position), serving a socket and recording every tick."""
    tmp = tmp_path_factory.mktemp("hostile")
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    for finger in data["fingers"]:
        finger["device"]["hold_s"] = 3600.0
    path = tmp / "profile.yaml"
    path.write_text(yaml.safe_dump(data))
    # A hostile line that stalls the loop for a second still latches a fault.
    profile = load_profile(path, IN_PROCESS)
    session = build_session(profile, paced=True, record_dir=tmp)
    session.loop.realtime_settings = None
    sock = tmp / "h.sock"
    # Thousands of valid sets and dozens of reloads among the hostile lines: at the
    # default limits they would stretch this suite by a minute or more, and this loop
    # runs without real-time priority, so a loaded machine can stall it past the watchdog
    # meanwhile. The limits themselves are tested in test_control_server.py; here every
    # request still passes through them, with no wait.
    server = ControlServer(session, sock, rate_limits_s={"change": 0.0, "reload": 0.0})
    server.start()
    out: dict = {}
    runner = threading.Thread(target=lambda: out.update(s=session.run()), name="hostile-loop")
    runner.start()
    deadline = time.monotonic() + 10
    while session.loop.stats.ticks < 50 and time.monotonic() < deadline:
        time.sleep(0.01)
    started = session.record_start("throughout.hrec")
    try:
        yield session, sock, tmp
    finally:
        session.loop.request_stop("hostile suite over")
        runner.join(timeout=20)
        server.close()
    # No tick recorded while the hostile traffic ran is lost.
    rec = recording.read(tmp / "throughout.hrec")
    assert rec.ticks > 100
    ticks = rec["tick"].astype(np.int64)
    assert ticks[0] == started["applied_at_tick"]
    np.testing.assert_array_equal(np.diff(ticks), 1)
    assert out["s"]["recording"]["dropped"] == 0
    assert out["s"]["recording"]["written"] == rec.ticks


def _report(name: str, tally: Counter) -> None:
    tried = sum(tally[k] for k in ("accepted", "clear error", "crash", "hang"))
    print(
        f"\nhostile control, {name}: {tried} tried, {tally['clear error']} clear error, "
        f"{tally['accepted']} accepted, {tally['crash']} crash, {tally['hang']} hang, "
        f"{tally['wrong id']} wrong id, {tally['not sent']} valid and not sent"
    )


def _check_alive(session) -> None:
    assert session.loop.running and session.loop.safety.fault is None
    st = session.loop.recorder.status()
    assert st["error"] is None and st["dropped"] == 0


@pytest.mark.parametrize("category", list(CATEGORIES))
def test_every_hostile_line_gets_one_clear_reply_pipelined(daemon, category):
    """All of a category's lines in one burst on one connection: replies in order, ids
    echoed, no crash, no hang."""
    session, sock, _ = daemon
    lines, want = [], []
    tally: Counter = Counter()
    for line in CATEGORIES[category]():
        send, rid = _expected(line)
        if not send:
            tally["not sent"] += 1
            continue
        lines.append(line)
        want.append(rid)
    conn = Conn(sock)
    problems: list = []
    try:
        sender = threading.Thread(
            target=conn.sock.sendall, args=(b"\n".join(lines) + b"\n",), name="hostile-sender"
        )
        sender.start()
        for rid in want:
            judge(conn.reply(), rid, tally, problems)
            if tally["hang"]:
                break
        sender.join(timeout=30)
        conn.sock.sendall(b'{"id": "last", "cmd": "get", "param": "mass_kg"}\n')
        assert conn.reply()["id"] == "last"  # nothing extra was queued: one reply per line
    finally:
        conn.close()
    _report(category, tally)
    assert tally["crash"] == tally["hang"] == tally["wrong id"] == 0, problems[:5]
    _check_alive(session)


def test_hostile_lines_from_many_clients_at_once(daemon):
    """Twenty clients each send their share of every category at the same time."""
    session, sock, _ = daemon
    work = []
    for make in CATEGORIES.values():
        for line in itertools.islice(make(), 0, None, 7):  # every 7th: a spread of each
            send, rid = _expected(line)
            if send and len(line) < 2 * protocol.MAX_LINE_BYTES:
                work.append((line, rid))
    n = 20
    tally: Counter = Counter()
    problems: list = []
    lock = threading.Lock()
    barrier = threading.Barrier(n, timeout=20)

    def client(share):
        local: Counter = Counter()
        mine: list = []
        conn = Conn(sock)
        try:
            barrier.wait()
            conn.sock.sendall(b"".join(line + b"\n" for line, _ in share))
            for _, rid in share:
                judge(conn.reply(), rid, local, mine)
                if local["hang"]:
                    break
        except Exception as exc:
            local["crash"] += 1
            mine.append(("client failed", repr(exc)))
        finally:
            conn.close()
        with lock:
            tally.update(local)
            problems.extend(mine)

    threads = [
        threading.Thread(target=client, args=(work[i::n],), name=f"hostile-{i}") for i in range(n)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not any(t.is_alive() for t in threads)
    _report("concurrent clients", tally)
    assert sum(tally[k] for k in ("accepted", "clear error")) == len(work), problems[:5]
    assert tally["crash"] == tally["hang"] == tally["wrong id"] == 0, problems[:5]
    _check_alive(session)
