"""hapticd view: the process, its page and stream against a live daemon, its security, and
the page in a headless Chromium."""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import os
import re
import select
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from hapticd import params
from hapticd.cli import build_parser, main
from hapticd.control import ControlClient
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from hapticd.view import ViewServer, is_loopback
from hapticd.view.server import (
    MAX_CONNECTIONS,
    MAX_STREAMS,
    SUBJECT_TELEMETRY,
    key_path,
    load_or_make_key,
)
from tests import cdp
from tests.conftest import IN_PROCESS, ROOT, wait_for
from tests.fake_daemon import FakeDaemon

URL_RE = re.compile(r"^http://(?P<host>[^/:]+|\[[^]]+\]):(?P<port>\d+)/\?key=(?P<key>[\w-]+)$")
# Direct connections only: a proxy from the environment must not see (or break) loopback.
OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))


@contextlib.contextmanager
def running_daemon(sock: Path, profile: Path, *, lsl: bool = False):
    """A paced run of ``profile`` serving ``sock`` in a thread until the block ends; it
    records beside the socket (never in the user's state directory). ``lsl``: with its
    Lab Streaming Layer outlets, as ``hapticd run --lsl`` starts them."""
    from hapticd.daemon import lsl as lsl_outlets

    session = build_session(
        load_profile(profile, IN_PROCESS), paced=True, duration_s=60.0, record_dir=sock.parent
    )
    server = ControlServer(session, sock)
    outlet = lsl_outlets.attach(session, server) if lsl else None
    server.start()
    runner = threading.Thread(target=session.run, name="test-loop")
    runner.start()
    try:
        yield sock
    finally:
        session.loop.request_stop("test over")
        runner.join(timeout=10)
        server.close()
        if outlet is not None:
            status = lsl_outlets.detach(session, outlet)
            assert status["error"] is None, status


@pytest.fixture
def held_profile(grasp_data, write_profile) -> Path:
    """The grasp profile with the fingers holding their last position after the trajectory
    (hold_s), so a run goes on until the test ends it."""
    for finger in grasp_data["fingers"]:
        finger["device"]["hold_s"] = 60.0
    return write_profile(grasp_data, "held.yaml")


@pytest.fixture
def daemon(tmp_path, held_profile):
    """A paced grasp run serving its socket in a thread until the test ends."""
    with running_daemon(tmp_path / "d.sock", held_profile) as sock:
        yield sock


@pytest.fixture
def fake(tmp_path):
    """A fake daemon (tests/fake_daemon.py) that knows the subject prompt."""
    with FakeDaemon(tmp_path / "fake.sock") as f:
        yield f


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


NOFILE_MAIN = (
    "import resource, runpy, sys; resource.setrlimit(resource.RLIMIT_NOFILE, ({n}, {n})); "
    "sys.argv[0] = 'hapticd'; runpy.run_module('hapticd', run_name='__main__')"
)


class View:
    """A ``hapticd view`` process: its URLs (the first two lines of stdout) and stderr."""

    def __init__(
        self, sock: Path, *args: str, timeout_s: float = 30.0, nofile: int | None = None
    ) -> None:
        # ``nofile``: the view runs with at most this many file descriptors.
        limit = [] if nofile is None else ["-c", NOFILE_MAIN.format(n=nofile)]
        self.proc = subprocess.Popen(
            [sys.executable, *(limit or ["-m", "hapticd"]), "view", "--socket", str(sock), *args],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        self._err = b""
        try:
            lines = self._lines(self.proc.stdout, 2, timeout_s)
        except BaseException:
            self.close()
            raise
        self.url, self.subject_url = lines
        m = URL_RE.match(self.url)
        assert m, f"the first line is not the page's URL: {self.url!r}"
        self.host, self.port, self.key = m["host"], int(m["port"]), m["key"]
        self.base = f"http://127.0.0.1:{self.port}"

    def _lines(self, pipe, n: int, timeout_s: float) -> list[str]:
        buf = b""
        deadline = time.monotonic() + timeout_s
        while buf.count(b"\n") < n:
            left = deadline - time.monotonic()
            ready, _, _ = select.select([pipe], [], [], max(left, 0))
            if not ready:
                pytest.fail(f"hapticd view printed no URL within {timeout_s:g} s: {buf!r}")
            chunk = os.read(pipe.fileno(), 4096)
            if not chunk:
                err = self.proc.stderr.read().decode()
                pytest.fail(f"hapticd view ended before printing its URL: {buf!r} {err}")
            buf += chunk
        return buf.decode().splitlines()[:n]

    def stderr_so_far(self, wait_s: float = 0.0) -> str:
        """What the view printed on stderr (waiting up to ``wait_s`` for more)."""
        deadline = time.monotonic() + wait_s
        while True:
            ready, _, _ = select.select([self.proc.stderr], [], [], 0)
            if ready:
                chunk = os.read(self.proc.stderr.fileno(), 65536)
                if chunk:
                    self._err += chunk
                    continue
            if time.monotonic() >= deadline:
                return self._err.decode()
            time.sleep(0.05)

    def get(self, path: str, *, key: bool = True, timeout_s: float = 10.0):
        sep = "&" if "?" in path else "?"
        url = self.base + path + (f"{sep}key={self.key}" if key else "")
        return OPENER.open(url, timeout=timeout_s)

    def ws(self, mode: str | None = None, *, key: str | None = None, **kw) -> ClientConnection:
        """A WebSocket to the view, as a page's (``mode`` "subject": the subject's)."""
        return ws_connect(self.port, self.key if key is None else key, mode, **kw)

    def close(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
            pytest.fail("hapticd view did not end within 15 s of SIGTERM")
        self.proc.stdout.close()
        self.proc.stderr.close()
        return rc


@pytest.fixture
def view():
    """Start ``hapticd view`` processes; each is stopped (SIGTERM) at the end and must exit 0."""
    started: list[View] = []

    def start(sock: Path, *args: str, nofile: int | None = None) -> View:
        v = View(sock, *args, nofile=nofile)
        started.append(v)
        return v

    yield start
    codes = [v.close() for v in started]
    assert codes == [0] * len(codes), f"hapticd view exit codes {codes}"


def _without_id(requests: list[dict]) -> list[dict]:
    """Requests as sent, less the request's own ``id`` (the client's counter)."""
    return [{k: v for k, v in r.items() if k != "id"} for r in requests]


def ws_connect(port: int, key: str, mode: str | None = None, **kw) -> ClientConnection:
    """A page's WebSocket. It reads all the view sends as it comes (no flow control,
    ``max_queue=None``), as a browser's page does, whether or not the test is reading its
    messages yet: only a page meant to stall does (``_stalled_page``)."""
    query = f"key={key}" + (f"&mode={mode}" if mode else "")
    kw = {"proxy": None, "open_timeout": 10, "max_queue": None, **kw}
    return connect(f"ws://127.0.0.1:{port}/ws?{query}", **kw)


def ws_events(ws: ClientConnection, want, timeout_s: float = 20.0, events=None):
    """Read the view's messages from ``ws`` until ``want(events)`` holds; fail at the
    deadline. Events are (type, data) (a reply: ("reply", the whole message)), appended
    to ``events`` if given."""
    events = [] if events is None else events
    deadline = time.monotonic() + timeout_s
    while not want(events):
        left = deadline - time.monotonic()
        if left <= 0:
            pytest.fail(f"the socket did not deliver in {timeout_s:g} s; got {events[-3:]}")
        try:
            msg = json.loads(ws.recv(timeout=left))
        except TimeoutError:
            continue
        events.append((msg["type"], msg if msg["type"] == "reply" else msg["data"]))
    return events


def reply_to(ws: ClientConnection, msg: dict, timeout_s: float = 20.0) -> dict:
    """Send a command with a fresh ``ref`` and return the view's reply to it."""
    ref = int(time.monotonic_ns() % 1_000_000_000)
    ws.send(json.dumps({**msg, "ref": ref}))
    events = ws_events(
        ws, lambda ev: any(n == "reply" and d["ref"] == ref for n, d in ev), timeout_s
    )
    return next(d for n, d in events if n == "reply" and d["ref"] == ref)


def statuses(events):
    return [d for n, d in events if n == "status"]


def ticks_of(events):
    return [d["tick"] for n, d in events if n == "telemetry"]


def test_the_url_comes_first_then_the_page_and_its_assets(daemon, view):
    v = view(daemon)
    assert v.host == "127.0.0.1"
    # The subject's URL carries the subject's capability, not the experimenter's key.
    assert v.subject_url.endswith("&mode=subject") and v.key not in v.subject_url
    assert URL_RE.match(v.subject_url.removesuffix("&mode=subject"))
    with v.get("/", key=False) as r:
        assert r.status == 200 and r.headers["Content-Type"].startswith("text/html")
        assert "default-src 'self'" in r.headers["Content-Security-Policy"]
        assert r.headers["X-Content-Type-Options"] == "nosniff"
        html = r.read().decode()
    assert 'data-testid="tick"' in html and "/static/view.js" in html
    assets = {"view.js": "text/javascript", "view.css": "text/css"}
    text = html
    for name, ctype in assets.items():
        with v.get(f"/static/{name}", key=False) as r:
            assert r.status == 200 and r.headers["Content-Type"].startswith(ctype)
            text += r.read().decode()
    assert "requestAnimationFrame" in text and "new WebSocket(" in text
    assert "EventSource" not in text  # one stream, not two
    # Nothing from the network: no absolute URL anywhere in the page.
    assert not re.search(r"https?://", text)
    for path in ("/static/server.py", "/static/../server.py", "/nothing", "/events"):
        with pytest.raises(urllib.error.HTTPError) as exc:
            v.get(path, key=False)
        exc.value.close()
        assert exc.value.code == 404
    # The data needs the key the URL carries.
    for path in ("/ws", "/api/status", "/api/params", "/ws?key=wrong"):
        with pytest.raises(urllib.error.HTTPError) as exc:
            v.get(path, key=False)
        with exc.value:
            assert exc.value.code == 403
            assert json.loads(exc.value.read())["error"]["code"] == "forbidden"


def test_the_socket_delivers_advancing_ticks_and_what_the_page_draws(daemon, view):
    v = view(daemon)
    with v.ws() as ws:
        events = ws_events(
            ws,
            lambda ev: len(set(ticks_of(ev))) >= 3 and any(n == "status" for n, _ in ev),
        )
    # The link state and the status come first, before any telemetry.
    assert [n for n, _ in events[:3]] == ["hello", "link", "status"]
    assert events[0][1] == {"role": "experimenter"}
    ticks = ticks_of(events)
    assert ticks == sorted(ticks) and ticks[-1] > ticks[0]
    sample = next(d for n, d in events if n == "telemetry")
    for k in ("device_pos", "proxy_pos", "object_pos", "object_rot", "in_contact"):
        assert k in sample
    assert len(sample["contact_force"]) == 2 and len(sample["rendered_force"][1]) == 3
    assert len(sample["object_rot"]) == 3 and len(sample["object_rot"][0]) == 3
    status = next(d for n, d in events if n == "status")
    scene = status["scene"]
    assert scene["bounds_m"] == [[-0.025] * 3, [0.025] * 3]  # the profile's 50 mm cube
    assert scene["finger_radii_m"] == [0.008, 0.008] and scene["surfaces"] == []
    assert status["fingers"] == ["thumb", "index"] and status["view"]["control"] is False
    assert status["prompt"] is None  # this daemon asks nothing
    link = next(d for n, d in events if n == "link")
    assert link["connected"] is True and link["socket"] == str(daemon)


def test_the_subjects_socket_reveals_no_condition(daemon, view):
    v = view(daemon, "--control")
    with v.ws("subject") as ws:
        events = ws_events(
            ws,
            lambda ev: len(ticks_of(ev)) >= 2 and any(n == "status" for n, _ in ev),
        )
        # Nor does the subject's page change anything, even on a view with --control.
        reply = reply_to(ws, {"type": "set", "param": "stiffness", "value": "90"})
        assert reply["ok"] is False and reply["error"]["code"] == "read_only"
    for name, data in events:
        assert name in ("hello", "link", "status", "telemetry"), name  # no daemon events
        if name == "telemetry":
            assert set(data) <= set(SUBJECT_TELEMETRY)
            assert {"object_pos", "object_rot", "proxy_pos", "tick"} <= set(data)
        elif name == "status":
            assert set(data) == {"fingers", "scene", "prompt", "screen"}
            assert set(data["scene"]) == {"bounds_m", "surfaces", "finger_radii_m"}
            assert data["screen"] is None  # no runner: nothing on the subject's screen
        elif name == "link":
            assert set(data) == {"connected"}
        elif name == "hello":
            assert data == {"role": "subject"}
    blob = json.dumps(events)
    for word in ("allocator", "stiffness", "force", "device_pos", "mass", "residual"):
        assert word not in blob, f"the subject's socket carries {word!r}"
    with ControlClient(daemon) as c:
        assert c.get("stiffness_n_per_m") == 60.0


def _subject_key(v) -> str:
    m = URL_RE.match(v.subject_url.removesuffix("&mode=subject"))
    assert m
    return m["key"]


def test_the_subjects_capability_opens_only_the_subjects_page(daemon, view):
    """The subject's URL without mode=subject: still the subject's stream (no condition),
    no change even on a view with --control, no parameters, the stripped status; before,
    it carried the experimenter's key and gave the experimenter's page."""
    v = view(daemon, "--control")
    cap = _subject_key(v)
    with ws_connect(v.port, cap) as ws:  # no mode: the capability decides
        events = ws_events(
            ws, lambda ev: len(ticks_of(ev)) >= 2 and any(n == "status" for n, _ in ev)
        )
        reply = reply_to(ws, {"type": "set", "param": "stiffness", "value": "90"})
        assert reply["ok"] is False and reply["error"]["code"] == "read_only"
        # It may answer a prompt: the daemon checks the answer (none is asked here).
        reply = reply_to(ws, {"type": "respond", "prompt": 1, "choice": "yes"})
        assert reply["error"]["code"] == "no_prompt"
    assert events[0] == ("hello", {"role": "subject"})
    blob = json.dumps(events)
    for word in ("allocator", "stiffness", "force", "device_pos", "mass", "residual", v.key):
        assert word not in blob, f"the subject's socket carries {word!r}"
    with pytest.raises(urllib.error.HTTPError) as exc:
        OPENER.open(f"{v.base}/api/params?key={cap}", timeout=10)
    with exc.value:  # its response's socket, else open until a garbage collection
        assert exc.value.code == 403
    with OPENER.open(f"{v.base}/api/status?key={cap}", timeout=10) as r:
        body = json.loads(r.read())
    assert set(body["status"] or {}) <= {"fingers", "scene", "prompt", "screen"}
    assert body["link"] == {"connected": True}
    with ControlClient(daemon) as c:
        assert c.get("stiffness_n_per_m") == 60.0


def test_a_websocket_needs_the_key_and_the_pages_own_origin(daemon, view):
    v = view(daemon)
    for key, origin, status in (
        ("", None, 403),
        ("wrong", None, 403),
        (v.key, "http://evil.example", 403),  # another site's script in the browser
        (v.key, f"http://127.0.0.1:{v.port + 1}", 403),  # another port is another origin
        (v.key, f"http://localhost:{v.port}", 403),  # not the host the page was loaded from
    ):
        with pytest.raises(InvalidStatus) as exc:
            v.ws(key=key, origin=origin)
        assert exc.value.response.status_code == status, (key, origin)
        body = json.loads(exc.value.response.body)
        assert body["error"]["code"] == ("forbidden" if origin is None else "bad_origin")
    # The page's own origin (a browser sends it), and no origin at all (not a browser).
    for origin in (f"http://127.0.0.1:{v.port}", None):
        with v.ws(origin=origin) as ws:
            ws_events(ws, lambda ev: bool(ticks_of(ev)))


def test_deeply_nested_json_from_a_page_gets_a_clear_error_and_the_page_lives(daemon, view):
    """'[' * 30000: the parser's recursion limit, not a reason to close the page (before:
    its handler died, close 1011)."""
    v = view(daemon)
    with v.ws() as ws:
        ws.send("[" * 30000 + "]" * 30000)
        events = ws_events(ws, lambda ev: any(n == "reply" for n, _ in ev))
        reply = next(d for n, d in events if n == "reply")
        assert reply["ok"] is False and reply["error"]["code"] == "bad_request"
        assert "nested" in reply["error"]["message"]
        ws_events(ws, lambda ev: len(ticks_of(ev)) >= 2)  # still streaming
        reply = reply_to(ws, {"type": "set", "param": "stiffness", "value": "90"})
        assert reply["error"]["code"] == "read_only"  # and still answering
        # More hostile messages, each one reply with a clear code, the page living on.
        hostile = [
            b"\xff\xfe",
            "null",
            "[]",
            '{"type": 5}',
            '{"type": "set", "param": [], "value": {}}',
            '{"type": "respond", "prompt": -1, "choice": "yes"}',
            '{"type": "respond", "prompt": 1e400, "choice": "yes"}',
            '{"type": "respond", "prompt": 1, "choice": "' + "y" * 5000 + '"}',
            '{"ref": {"a": [1]}, "type": "respond"}',
            "{" * 20000,
        ]
        for raw in hostile:
            ws.send(raw)
        events = ws_events(
            ws, lambda ev: sum(n == "reply" for n, _ in ev) >= len(hostile), timeout_s=20
        )
        replies = [d for n, d in events if n == "reply"]
        assert all(r["ok"] is False and r["error"]["code"] for r in replies), replies
        ws_events(ws, lambda ev: len(ticks_of(ev)) >= 2)  # and still streaming


def test_read_only_refuses_a_change(daemon, view):
    v = view(daemon)
    with v.ws() as ws:
        reply = reply_to(ws, {"type": "set", "param": "stiffness", "value": "90"})
    assert reply["ok"] is False and reply["error"]["code"] == "read_only"
    assert "--control" in reply["error"]["message"]
    with ControlClient(daemon) as c:
        assert c.get("stiffness_n_per_m") == 60.0


def test_control_applies_a_change_through_the_checked_set_command(daemon, view):
    v = view(daemon, "--control")
    with v.ws() as ws:
        reply = reply_to(ws, {"type": "set", "param": "stiffness", "value": "90"})
        assert reply["ok"] is True, reply
        assert reply["result"]["param"] == "stiffness_n_per_m"
        assert reply["result"]["applied_at_tick"] > 0
        with ControlClient(daemon) as c:
            assert c.get("stiffness_n_per_m") == 90.0
        reply = reply_to(ws, {"type": "set", "param": "allocator", "value": "ef"})
        assert reply["ok"] is True, reply
        # Bad values are refused with the protocol's codes; nothing changes.
        for param, value, code in (
            ("stiffness", "-1", "out_of_range"),
            ("stiffness", "stiff", "bad_value"),
            ("stifness", "60", "unknown_param"),
            ("allocator", "magic", "bad_value"),
            # Nested 20,000 deep: a clear error, not the page handler's RecursionError.
            ("actuation", "[" * 20000 + "]" * 20000, "bad_value"),
        ):
            reply = reply_to(ws, {"type": "set", "param": param, "value": value})
            assert reply["error"]["code"] == code, (param, value, reply)
        for bad in (
            {"type": "set", "param": "stiffness", "value": 1},
            {"type": "set", "param": "stiffness"},
            {"type": "shutdown"},
        ):
            reply = reply_to(ws, bad)
            assert reply["ok"] is False and reply["error"]["code"] == "bad_request", bad
        ws.send("not json")
        events = ws_events(ws, lambda ev: any(n == "reply" and d["ref"] is None for n, d in ev))
        assert next(d for n, d in events if n == "reply")["error"]["code"] == "bad_request"
        # The socket still serves after all that.
        ws_events(ws, lambda ev: len(ticks_of(ev)) >= 2)
    with ControlClient(daemon) as c:
        assert c.get("stiffness_n_per_m") == 90.0 and c.get("allocator") == "ef"
    assert "set stiffness_n_per_m 90" in v.stderr_so_far()


def test_many_pages_each_get_the_stream_and_one_too_many_is_refused(daemon, view):
    v = view(daemon)
    with contextlib.ExitStack() as stack:
        pages = [
            stack.enter_context(v.ws("subject" if i % 2 else None)) for i in range(MAX_STREAMS)
        ]
        for ws in pages:
            ticks = ticks_of(ws_events(ws, lambda ev: len(set(ticks_of(ev))) >= 2))
            assert ticks[-1] > ticks[0]
        with pytest.raises(InvalidStatus) as exc:
            v.ws()
        assert exc.value.response.status_code == 503
        assert json.loads(exc.value.response.body)["error"]["code"] == "busy"
    # Closed pages make room again.
    with v.ws() as ws:
        ws_events(ws, lambda ev: bool(ticks_of(ev)))


def _stalled_page(port: int, key: str) -> socket.socket:
    """A WebSocket opened by hand that will never read: a tab that stopped reading (a
    small receive buffer, so the view's writes to it soon block)."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.settimeout(10)
    s.connect(("127.0.0.1", port))
    s.sendall(
        (
            f"GET /ws?key={key} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
            "Upgrade: websocket\r\nConnection: Upgrade\r\n"
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = s.recv(1)
        assert chunk, f"the view closed the handshake: {head!r}"
        head += chunk
    assert head.startswith(b"HTTP/1.1 101"), head
    return s


def test_a_page_that_stops_reading_is_dropped_and_the_others_go_on(daemon, view):
    v = view(daemon, "--rate", "1000")
    stalled = _stalled_page(v.port, v.key)
    try:
        with v.ws() as ws:
            # Reading all along (a page that reads is never behind), until the drop.
            events = ws_events(
                ws,
                lambda ev: "dropped a page that stopped reading" in v.stderr_so_far(),
                timeout_s=30,
            )
            assert v.stderr_so_far().count("dropped a page") == 1  # not the reading page
            # The page that reads goes on: ticks keep coming after the drop.
            first = ticks_of(events)[-1]
            ws_events(ws, lambda ev: ticks_of(ev)[-1] > first + 100, events=events)
        # The stalled page's connection was closed by the view: what it holds, then EOF.
        deadline = time.monotonic() + 10
        while stalled.recv(65536):
            assert time.monotonic() < deadline, "the stalled page was never closed"
    finally:
        stalled.close()
    with ControlClient(daemon) as c:
        assert c.status()["fault"] is None


@pytest.mark.timing("a rate of frames over wall-clock time is what is limited")
def _flood(port: int, n: int) -> list[socket.socket]:
    """``n`` bare TCP connections to ``port`` that send nothing (connecting, not waiting)."""
    out = []
    for _ in range(n):
        s = socket.socket()
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", port))
        out.append(s)
    return out


def test_after_a_flood_at_the_descriptor_limit_the_view_serves_again(tmp_path, view):
    """300 bare connections to a view limited to 40 descriptors: accept() runs out of them,
    waits and tries again (saying so once), and when the flood ends the page is served
    within seconds (before: the library's accept loop ended at the first EMFILE and the
    view never served again)."""
    v = view(tmp_path / "none.sock", "-q", nofile=40)
    flood = _flood(v.port, 300)
    try:
        wait_for(
            lambda: v.stderr_so_far(),
            "the view to say it cannot accept",
            until=lambda err: "cannot accept a connection" in err,
            timeout_s=10,
        )
    finally:
        for s in flood:
            s.close()
    t0 = time.monotonic()
    with v.get("/", key=False, timeout_s=10.0) as r:
        assert r.status == 200
    assert time.monotonic() - t0 < 5.0
    err = v.stderr_so_far(wait_s=0.5)
    assert err.count("cannot accept a connection") == 1, err  # said once, not per retry
    assert "accepting connections again" in err
    assert "Traceback" not in err  # no connection's handler died for want of descriptors


def test_idle_connections_give_their_places_to_a_page(daemon, view):
    """More bare connections than the view serves at once: the oldest idle ones are closed,
    and a page still opens and streams."""
    v = view(daemon)
    flood = _flood(v.port, 2 * MAX_CONNECTIONS)
    try:
        time.sleep(0.5)
        with v.ws() as ws:
            ws_events(ws, lambda ev: len(ticks_of(ev)) >= 2)
        with v.get("/api/status") as r:
            assert r.status == 200
    finally:
        for s in flood:
            s.close()


def test_telemetry_to_the_pages_is_rate_limited(daemon, view):
    v = view(daemon, "--rate", "20")
    with v.ws() as ws:
        ws_events(ws, lambda ev: bool(ticks_of(ev)))  # connected and streaming
        t0 = time.monotonic()
        ticks = ticks_of(ws_events(ws, lambda ev: len(ticks_of(ev)) >= 12))
        span = time.monotonic() - t0
    # 11 intervals at 20 Hz are 0.55 s of a 1 kHz loop: ~50 ticks apart, never every tick.
    assert span > 0.3, f"12 frames in {span:.3f} s: faster than 20 Hz"
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    assert statistics.median(gaps) >= 25, gaps


def test_the_host_is_loopback_unless_given_and_another_warns(daemon, view):
    assert build_parser().parse_args(["view"]).host == "127.0.0.1"
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.0.2.1")
    quiet = view(daemon)
    assert "WARNING" not in quiet.stderr_so_far(wait_s=0.5)
    loud = view(daemon, "--host", "0.0.0.0")
    err = loud.stderr_so_far(wait_s=0.5)
    assert "WARNING: serving on 0.0.0.0" in err and "not loopback" in err
    assert loud.host != "127.0.0.1"  # the URL names the machine, reachable from elsewhere
    with loud.get("/", key=False) as r:  # it still answers on loopback
        assert r.status == 200


def test_without_a_daemon_the_page_says_so(tmp_path, view):
    v = view(tmp_path / "nobody.sock")

    def link():
        with v.get("/api/status") as r:
            return json.loads(r.read())["link"]

    state = wait_for(link, "the view's link state", until=lambda s: s is not None, timeout_s=10)
    assert state["connected"] is False and "is hapticd running?" in state["message"]


# The scene canvas's pixels: {(r, g, b): count} (JSON keys "r,g,b").
CANVAS_COLOURS = """(() => {
  const c = document.querySelector('[data-testid=scene]');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  const n = {};
  for (let i = 0; i < d.length; i += 4) {
    const k = d[i] + ',' + d[i + 1] + ',' + d[i + 2];
    n[k] = (n[k] || 0) + 1;
  }
  return n;
})()"""


def canvas_colours(browser) -> dict[tuple[int, int, int], int]:
    raw = browser.evaluate(CANVAS_COLOURS)
    return {tuple(int(x) for x in k.split(",")): n for k, n in raw.items()}


def blend(under: tuple[float, ...], over: tuple[int, int, int], alpha: float) -> tuple[float, ...]:
    """``over`` painted at ``alpha`` on ``under`` (sRGB, as the 2D canvas composites)."""
    return tuple(alpha * o + (1 - alpha) * u for u, o in zip(under, over, strict=True))


def pixels_near(colours, rgb, tol: float = 3.0) -> int:
    """How many pixels are within ``tol`` (per channel) of ``rgb``."""
    return sum(
        n for c, n in colours.items() if all(abs(a - b) <= tol for a, b in zip(c, rgb, strict=True))
    )


def hex_rgb(h: str) -> tuple[int, int, int]:
    return int(h[1:3], 16), int(h[3:5], 16), int(h[5:7], 16)


TICK = "document.querySelector('[data-testid=tick]').textContent"
BANNER = (
    "(() => { const b = document.querySelector('[data-testid=banner]'); "
    "return b.hidden ? null : b.textContent; })()"
)
PROMPT_SHOWN = "!document.querySelector('[data-testid=prompt]').hidden"
ANSWERS = (
    "[...document.querySelectorAll('#prompt-choices button')].map((b) => "
    "[b.dataset.choice, b.textContent, b.getBoundingClientRect().width, "
    "b.getBoundingClientRect().height, b.disabled])"
)


def test_a_page_in_headless_chromium_shows_advancing_ticks(daemon, view, tmp_path, chromium):
    exe = chromium
    v = view(daemon)
    tick = "document.querySelector('[data-testid=tick]').textContent"
    frames = "Number(document.querySelector('[data-testid=scene]').dataset.frames)"
    stiffness = "document.querySelector('[data-testid=stiffness]').textContent"
    with cdp.Browser(exe, tmp_path / "chromium") as browser:
        browser.open(v.url)
        first = wait_for(
            lambda: browser.evaluate(tick),
            "a tick on the page",
            until=lambda s: s.isdigit(),
            timeout_s=20,
        )
        later = wait_for(
            lambda: browser.evaluate(tick),
            f"the tick to pass {first}",
            until=lambda s: s.isdigit() and int(s) > int(first) + 50,
            timeout_s=20,
        )
        assert int(later) > int(first)
        f0 = browser.evaluate(frames)
        wait_for(lambda: browser.evaluate(frames), "drawn frames", until=lambda f: f > f0 + 2)
        assert (
            browser.evaluate("document.querySelector('[data-testid=allocator]').textContent")
            == "if"
        )
        assert browser.evaluate("document.getElementById('control').hidden") is True
        # The canvas is drawn, not blank: the background and more; and the object is there.
        # Every pixel inside a convex box's outline is under one far face and one near face
        # (view.js: rgba(120,160,220) at 0.40 then 0.28), on the background #f4f5f7 or on
        # the object's shadow (rgba(20,30,50) at 0.12) over it.
        colours = wait_for(
            lambda: canvas_colours(browser),
            "the scene canvas to hold more than one colour",
            until=lambda c: len(c) > 1,
            timeout_s=10,
        )
        face = (120, 160, 220)
        bg = hex_rgb("#f4f5f7")
        in_box = [
            blend(blend(under, face, 0.40), face, 0.28)
            for under in (bg, blend(bg, (20, 30, 50), 0.12))
        ]
        box_px = sum(pixels_near(colours, c) for c in in_box)
        total = sum(colours.values())
        assert box_px > 0.01 * total, (
            f"the object's colour {[tuple(round(x) for x in c) for c in in_box]} covers "
            f"{box_px} of {total} pixels"
        )
        shot = browser.screenshot(tmp_path / "experimenter.png")
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        # A change made over the control socket (not by the page) shows on the page.
        assert browser.evaluate(stiffness) == "60 N/m"
        with ControlClient(daemon) as c:
            c.set("stiffness_n_per_m", 90)
        wait_for(
            lambda: browser.evaluate(stiffness),
            "the page to show the new stiffness",
            until=lambda s: s == "90 N/m",
            timeout_s=5,
        )
        # No prompt from this daemon: no answer buttons on the subject's page.
        assert browser.evaluate("document.getElementById('prompt-state').textContent") == "none"
        # The subject's page: the scene alone, still drawn; the panels are not shown.
        browser.open(v.subject_url)
        wait_for(
            lambda: browser.evaluate(frames), "the subject's page drawing", until=lambda f: f > 2
        )
        panels = "getComputedStyle(document.getElementById('panels')).display"
        assert browser.evaluate(panels) == "none"
        # Drawn too: the object (rgba(120,160,220) at 0.55, twice) on the dark background.
        # (It is one colour until the first status and telemetry come: wait for them.)
        colours = wait_for(
            lambda: canvas_colours(browser),
            "the subject's canvas to hold more than one colour",
            until=lambda c: len(c) > 1,
            timeout_s=10,
        )
        bg = hex_rgb("#20242c")
        in_box = [
            blend(blend(under, face, 0.55), face, 0.55)
            for under in (bg, blend(bg, (0, 0, 0), 0.35))
        ]
        assert sum(pixels_near(colours, c) for c in in_box) > 0.01 * sum(colours.values())
        # Nothing in the subject's document reveals the condition: not hidden, absent.
        text = browser.evaluate("document.documentElement.textContent")
        shown = browser.evaluate("document.body.innerText")
        for name in params.ALLOCATORS:
            assert not re.search(rf"\b{re.escape(name)}\b", text), f"allocator {name!r} in {text!r}"
        assert not re.search(r"\d\s*N\b|N/m|\b[69]0\b", text), text
        assert not re.search(r"\d", shown), f"the subject's page shows {shown!r}"
        assert browser.evaluate(PROMPT_SHOWN) is False
        browser.screenshot(tmp_path / "subject.png")


SET_FROM_PAGE = (
    "(() => { const q = new URLSearchParams(location.search); window.__reply = null; "
    "const w = new WebSocket(`ws://${location.host}/ws?key=${q.get('key')}`); "
    "w.onmessage = (e) => { const m = JSON.parse(e.data); "
    "if (m.type === 'reply') window.__reply = m; }; "
    "w.onopen = () => w.send(JSON.stringify({type: 'set', ref: 1, param: 'stiffness', "
    "value: '90'})); return true; })()"
)


def test_the_subjects_url_without_its_mode_is_still_the_subjects_page(
    daemon, view, tmp_path, chromium
):
    """In the browser: the subject's URL with mode=subject removed shows the subject's page
    (no panels, no condition in the document), holds no experimenter's key, and a change
    sent from it over the page's WebSocket is refused, on a view with --control."""
    v = view(daemon, "--control")
    bare = v.subject_url.removesuffix("&mode=subject")
    frames = "Number(document.querySelector('[data-testid=scene]').dataset.frames)"
    with cdp.Browser(chromium, tmp_path / "chromium") as browser:
        browser.open(bare)

        def body_class() -> str:
            # While the page redraws itself as the subject's there may be no body, or no
            # document at all: the browser answers a question asked then with an error
            # (asked again until wait_for's deadline).
            try:
                return browser.evaluate("document.body ? document.body.className : ''")
            except cdp.CDPError:
                return ""

        wait_for(body_class, "the page to become the subject's", until=lambda c: c == "subject")
        wait_for(lambda: browser.evaluate(frames), "the subject's page drawing", until=bool)
        panels = "getComputedStyle(document.getElementById('panels')).display"
        assert browser.evaluate(panels) == "none"
        html = browser.evaluate("document.documentElement.outerHTML")
        text = browser.evaluate("document.documentElement.textContent")
        assert v.key not in browser.evaluate("location.href") + html
        for name in params.ALLOCATORS:
            assert not re.search(rf"\b{re.escape(name)}\b", text), name
        assert not re.search(r"\d\s*N\b|N/m|\b60\b", text), text
        browser.evaluate(SET_FROM_PAGE)
        reply = wait_for(
            lambda: browser.evaluate("window.__reply"), "the reply to the page's change"
        )
        assert reply["ok"] is False and reply["error"]["code"] == "read_only"
    with ControlClient(daemon) as c:
        assert c.get("stiffness_n_per_m") == 60.0


def test_the_subjects_page_shows_the_prompt_as_buttons_and_a_click_answers(
    fake, view, tmp_path, chromium
):
    """Against a fake daemon with the prompt: the subject's page shows the question and
    one large button per choice only while a prompt is current; a mouse click, or a key,
    sends the answer the daemon receives as ``respond``."""
    v = view(fake.path)
    with cdp.Browser(chromium, tmp_path / "chromium") as browser:
        browser.open(v.subject_url)
        wait_for(lambda: browser.evaluate(TICK), "telemetry", until=lambda s: s.isdigit())
        assert browser.evaluate(PROMPT_SHOWN) is False  # no prompt yet: no buttons
        fake.set_prompt(7, "Was the second cube stiffer?", ["no", "yes"])
        wait_for(lambda: browser.evaluate(PROMPT_SHOWN), "the prompt on the subject's page")
        assert (
            browser.evaluate("document.getElementById('prompt-question').textContent")
            == "Was the second cube stiffer?"
        )
        answers = browser.evaluate(ANSWERS)
        assert [a[0] for a in answers] == ["no", "yes"]
        assert [a[1] for a in answers] == ["nokey n or 1", "yeskey y or 2"]
        assert all(a[2] >= 150 and a[3] >= 60 and not a[4] for a in answers), answers
        browser.screenshot(tmp_path / "subject-prompt.png")
        browser.click("[data-testid=answer-yes]")
        wait_for(fake.responds, "the answer at the daemon", until=lambda r: len(r) == 1)
        assert _without_id(fake.responds()) == [{"prompt": 7, "cmd": "respond", "choice": "yes"}]
        wait_for(
            lambda: browser.evaluate(PROMPT_SHOWN),
            "the buttons to go with the prompt",
            until=lambda shown: shown is False,
            timeout_s=5,
        )
        # Keys: a choice's first letter, or its number.
        fake.set_prompt(8, "Which side was heavier?", ["left", "right"])
        wait_for(lambda: browser.evaluate(PROMPT_SHOWN), "the next prompt")
        browser.press("r")
        wait_for(fake.responds, "the key's answer", until=lambda r: len(r) == 2)
        assert _without_id(fake.responds())[-1] == {
            "prompt": 8,
            "cmd": "respond",
            "choice": "right",
        }
        fake.set_prompt(9, "Again?", ["no", "yes"])
        wait_for(
            lambda: browser.evaluate("document.getElementById('prompt-question').textContent"),
            "the third prompt",
            until=lambda q: q == "Again?",
        )
        browser.press("1")
        wait_for(fake.responds, "the number key's answer", until=lambda r: len(r) == 3)
        assert _without_id(fake.responds())[-1] == {"prompt": 9, "cmd": "respond", "choice": "no"}
        wait_for(
            lambda: browser.evaluate(PROMPT_SHOWN),
            "the buttons to go",
            until=lambda shown: shown is False,
            timeout_s=5,
        )
        # A key with no prompt current sends nothing.
        browser.press("y")
        # The experimenter's page shows the prompt (no buttons) and the last answer.
        fake.set_prompt(10, "Was the first cube stiffer?", ["no", "yes"])
        browser.open(v.url)
        wait_for(
            lambda: browser.evaluate("document.getElementById('prompt-state').textContent"),
            "the prompt on the experimenter's page",
            until=lambda t: "Was the first cube stiffer?" in t,
        )
        assert browser.evaluate(PROMPT_SHOWN) is False
    assert len(fake.responds()) == 3


def test_an_answer_on_the_subjects_page_reaches_the_daemon_as_a_response_event(
    daemon, view, tmp_path, chromium
):
    """End to end: a client sets the prompt, the subject clicks an answer, the daemon
    emits ``response`` (the experiment runner's way of hearing it)."""
    with ControlClient(daemon) as client, ControlClient(daemon) as runner:
        client.prompt(3, "Was the second cube stiffer?", ["no", "yes"])
        runner.events_subscribe(["response"])
        v = view(daemon)
        with cdp.Browser(chromium, tmp_path / "chromium") as browser:
            browser.open(v.subject_url)
            wait_for(lambda: browser.evaluate(PROMPT_SHOWN), "the prompt's buttons")
            browser.click("[data-testid=answer-yes]")
            ev = runner.next_event(timeout_s=10)
            assert (ev["event"], ev["prompt"], ev["choice"]) == ("response", 3, "yes")
            wait_for(
                lambda: browser.evaluate(PROMPT_SHOWN),
                "the buttons to go with the prompt",
                until=lambda shown: shown is False,
                timeout_s=5,
            )
        assert client.status()["prompt"] is None


def test_the_page_says_when_the_daemon_or_the_view_goes_and_follows_them_back(
    tmp_path, held_profile, view, chromium
):
    sock = tmp_path / "d.sock"
    port = free_port()
    first = view(sock, "--port", str(port))
    with cdp.Browser(chromium, tmp_path / "chromium") as browser:
        browser.open(first.url)
        for _run in range(2):  # the daemon comes, goes, and comes again
            with running_daemon(sock, held_profile):
                wait_for(
                    lambda: browser.evaluate(BANNER),
                    "the page to see the daemon",
                    until=lambda b: b is None,
                    timeout_s=15,
                )
                first_tick = wait_for(
                    lambda: browser.evaluate(TICK), "ticks", until=lambda s: s.isdigit()
                )
                wait_for(
                    lambda: browser.evaluate(TICK),
                    "ticks that advance",
                    until=lambda s, t0=first_tick: int(s) != int(t0),
                )
            wait_for(
                lambda: browser.evaluate(BANNER),
                "the page to say the daemon is gone",
                until=lambda b: b is not None and b.startswith("no daemon:"),
                timeout_s=15,
            )
        with running_daemon(sock, held_profile):
            wait_for(lambda: browser.evaluate(BANNER), "the daemon", until=lambda b: b is None)
            assert first.close() == 0
            wait_for(
                lambda: browser.evaluate(BANNER),
                "the page to say the view is gone",
                until=lambda b: b is not None and "cannot reach hapticd view" in b,
                timeout_s=10,
            )
            stopped = browser.evaluate(TICK)
            # The view again, on the same port and socket: the same key, so the URL holds.
            second = view(sock, "--port", str(port))
            assert second.url == first.url
            wait_for(
                lambda: browser.evaluate(BANNER),
                "the page to say it reconnected",
                until=lambda b: b == "reconnected to hapticd view",
                timeout_s=15,
            )
            wait_for(
                lambda: browser.evaluate(TICK),
                "ticks again",
                until=lambda s: int(s) > int(stopped),
                timeout_s=10,
            )
            # The note goes; nothing is wrong any more.
            wait_for(
                lambda: browser.evaluate(BANNER),
                "the note to go",
                until=lambda b: b is None,
                timeout_s=10,
            )


def test_watch_explains_its_columns_and_its_lines_match(daemon, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["watch", "--help"])
    assert exc.value.code == 0
    help_text = capsys.readouterr().out
    assert "that finger is in contact with the object" in help_text
    example = next(line.strip() for line in help_text.splitlines() if line.startswith("  t "))
    assert main(["watch", "--socket", str(daemon), "--count", "2", "--rate", "20"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    # The help's example has the shape of a real line (its device names aside).
    mark = r"N(?: \*|  )  "  # " *" in contact, else two spaces; then the separator
    shape = (
        rf"t +\d+\.\d{{3}} s  DEV_A: \|F\| +\d+\.\d{{3}} {mark}DEV_B: \|F\| +\d+\.\d{{3}} {mark}"
    )
    shape += r"obj z +-?\d+\.\d{2} mm  \w+  overruns \d+"
    assert re.fullmatch(shape.replace("DEV_A", "A").replace("DEV_B", "B"), example), example
    for line in lines:
        real = shape.replace("DEV_A", "replay-thumb").replace("DEV_B", "replay-index")
        assert re.fullmatch(real, line), line


SUBJECT_GONE = [("link", {"connected": False})]  # all the subject's page hears of it


def test_a_page_hears_the_daemon_come_go_and_come_back(tmp_path, held_profile):
    """The view waits for a daemon, follows it when it comes, says so when it goes, and
    reconnects to the next one on the same socket: each page hears every change."""
    sock = tmp_path / "later.sock"
    logs: list[str] = []

    def linked(ev, connected: bool) -> bool:
        return bool(ev) and ev[-1][0] == "link" and ev[-1][1]["connected"] is connected

    with ViewServer(sock, log=logs.append) as v:
        port = v.address[1]
        with ws_connect(port, v.key) as page, ws_connect(port, v.key, "subject") as subj:
            events = ws_events(page, lambda ev: any(n == "link" for n, _ in ev))
            link = next(d for n, d in events if n == "link")
            assert link["connected"] is False and "is hapticd running?" in link["message"]
            first = ws_events(subj, lambda ev: len(ev) >= 2)[:2]
            assert first == [("hello", {"role": "subject"}), ("link", {"connected": False})]
            for _run in range(2):
                with running_daemon(sock, held_profile):
                    events = ws_events(page, lambda ev: linked(ev, True), timeout_s=15)
                    ticks = ticks_of(ws_events(page, lambda ev: len(set(ticks_of(ev))) >= 3))
                    assert ticks[-1] > ticks[0]
                    ws_events(subj, lambda ev: len(ticks_of(ev)) >= 2, timeout_s=15)
                # Gone: both pages hear it (after whatever telemetry was on its way).
                ws_events(page, lambda ev: linked(ev, False), timeout_s=15)
                ws_events(subj, lambda ev: ev[-1:] == SUBJECT_GONE, timeout_s=15)
    assert sum("connected to the daemon" in m for m in logs) == 2
    assert sum(m.startswith("no daemon") for m in logs) == 3


def test_the_key_is_kept_beside_the_socket_for_a_restarted_view(tmp_path):
    logs: list[str] = []
    path = key_path(tmp_path / "d.sock")
    assert path == tmp_path / "d.sock.view-key"
    key = load_or_make_key(path, logs.append)
    assert oct(path.stat().st_mode & 0o777) == "0o600" and path.read_text() == key + "\n"
    assert load_or_make_key(path, logs.append) == key and logs == []
    # A file others may read is not trusted: a fresh key, for this run only, and why.
    path.chmod(0o644)
    other = load_or_make_key(path, logs.append)
    assert other != key and path.read_text() == key + "\n"
    assert "not a 0600 file of yours" in logs[-1]
    # Nor is a link (another user could point it anywhere).
    path.unlink()
    target = tmp_path / "elsewhere"
    target.write_text("x" * 24 + "\n")
    target.chmod(0o600)
    path.symlink_to(target)
    assert load_or_make_key(path, logs.append) != "x" * 24
    assert "a new key for this run only" in logs[-1]
    # A view on the same socket uses the kept key: its URLs stay the same.
    path.unlink()
    with ViewServer(tmp_path / "d.sock", log=logs.append) as a:
        url = a.url.split(":")[-1].split("/", 1)[1]
    with ViewServer(tmp_path / "d.sock", log=logs.append) as b:
        assert (
            b.url.split(":")[-1].split("/", 1)[1] == url
            and b.key == key_path(tmp_path / "d.sock").read_text().strip()
        )


def test_the_prompt_reaches_both_pages_and_the_answer_reaches_the_daemon(fake):
    """Against a fake daemon with the prompt (tests/fake_daemon.py): the view forwards the
    prompt to both pages and the subject's answer as the protocol's respond; a read-only
    view too, since an answer changes no parameter."""
    logs: list[str] = []
    fake.set_prompt(7, "Was the second cube stiffer?", ["no", "yes"])
    with ViewServer(fake.path, log=logs.append) as v:
        port = v.address[1]
        with ws_connect(port, v.key) as page, ws_connect(port, v.key, "subject") as subj:
            want = {"id": 7, "question": "Was the second cube stiffer?", "choices": ["no", "yes"]}
            for ws in (page, subj):
                events = ws_events(ws, lambda ev: bool(statuses(ev)))
                assert statuses(events)[-1]["prompt"] == want
            # Answers the view refuses itself, the daemon never sees.
            for bad, code in (
                ({"prompt": "7", "choice": "yes"}, "bad_request"),
                ({"prompt": -1, "choice": "yes"}, "bad_request"),
                ({"prompt": True, "choice": "yes"}, "bad_request"),
                ({"prompt": 7, "choice": "YES!"}, "bad_value"),
                ({"prompt": 7}, "bad_value"),
            ):
                reply = reply_to(subj, {"type": "respond", **bad})
                assert reply["ok"] is False and reply["error"]["code"] == code, (bad, reply)
            assert fake.responds() == []
            # The daemon's refusals come back with its code.
            reply = reply_to(subj, {"type": "respond", "prompt": 6, "choice": "yes"})
            assert reply["error"]["code"] == "no_prompt"
            reply = reply_to(subj, {"type": "respond", "prompt": 7, "choice": "maybe"})
            assert reply["error"]["code"] == "bad_value"
            # The answer: the same line a control client sends.
            reply = reply_to(subj, {"type": "respond", "prompt": 7, "choice": "yes"})
            assert reply["ok"] is True, reply
            assert _without_id(fake.responds())[-1] == {
                "prompt": 7,
                "cmd": "respond",
                "choice": "yes",
            }
            # The prompt is gone at once on both pages; the experimenter hears the answer.
            for ws in (page, subj):
                ws_events(ws, lambda ev: statuses(ev) and statuses(ev)[-1]["prompt"] is None)
            events = ws_events(page, lambda ev: any(n == "event" for n, _ in ev))
            ev = next(d for n, d in events if n == "event")
            assert ev == {"event": "response", "tick": ev["tick"], "prompt": 7, "choice": "yes"}
    assert "the subject answered prompt 7: yes" in logs


def test_a_daemon_without_prompts_says_so_to_the_page(fake):
    fake.knows_prompt = False
    with ViewServer(fake.path, log=lambda m: None) as v, ws_connect(v.address[1], v.key) as ws:
        reply = reply_to(ws, {"type": "respond", "prompt": 1, "choice": "yes"})
    assert (
        reply["error"]["code"] == "unsupported"
        and "no respond command" in reply["error"]["message"]
    )


@pytest.mark.parametrize(
    ("greeting", "error"),
    [
        (b"", "the daemon closed the connection"),
        (b"[1, 2]\n", "the greeting is not an object"),
        (b"{not json\n", "the daemon sent a line that is not JSON: '{not json'"),
    ],
)
def test_a_daemon_that_closes_before_greeting_leaves_no_socket_open(tmp_path, greeting, error):
    """The view reconnects while a daemon starts and stops: a connection that gets no
    proper greeting raises and is closed (the no_leaks fixture checks the sockets)."""
    path = tmp_path / "mute.sock"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.listen(1)

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.sendall(greeting)

    t = threading.Thread(target=serve, name="mute-daemon")
    t.start()
    try:
        with pytest.raises((ConnectionError, ValueError), match=error):
            ControlClient(path, timeout_s=5)
    finally:
        t.join(timeout=5)
        listener.close()


def test_the_libraries_errors_reach_the_views_log_without_the_noise_of_a_page_going():
    from websockets.exceptions import ConnectionClosedError
    from websockets.frames import Close

    from hapticd.view.server import _LogBridge

    logs: list[str] = []
    bridge = _LogBridge(logs.append)

    def record(message: str, exc: BaseException | None) -> logging.LogRecord:
        info = None if exc is None else (type(exc), exc, None)
        return logging.LogRecord("ws", logging.ERROR, __file__, 1, message, (), info)

    timed_out = ConnectionClosedError(None, Close(1011, "keepalive ping timeout"))
    bridge.emit(record("keepalive ping failed", ConnectionClosedError(None, None)))
    assert logs == []  # a page that went while a ping was out
    bridge.emit(record("keepalive ping failed", timed_out))
    assert logs == ["dropped a page that answered no ping for 10 s"]
    bridge.emit(record("connection handler failed", ValueError("a bug")))
    assert logs[-1] == "websockets: connection handler failed: ValueError('a bug')"
