"""hapticd view: the process, its page and stream against a live daemon, its security, and
the page in a headless Chromium."""

from __future__ import annotations

import json
import os
import re
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from hapticd import params
from hapticd.cli import build_parser, main
from hapticd.control import ControlClient
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from hapticd.view import ViewServer, is_loopback
from hapticd.view.server import SUBJECT_TELEMETRY
from tests import cdp
from tests.conftest import ROOT, wait_for

URL_RE = re.compile(r"^http://(?P<host>[^/:]+|\[[^]]+\]):(?P<port>\d+)/\?key=(?P<key>[\w-]+)$")
# Direct connections only: a proxy from the environment must not see (or break) loopback.
OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))


@pytest.fixture
def daemon(tmp_path, grasp_data, write_profile):
    """A paced grasp run serving its socket in a thread; the fingers hold their last
    position after the trajectory (hold_s), so it runs until the test ends it."""
    for finger in grasp_data["fingers"]:
        finger["device"]["hold_s"] = 60.0
    profile = write_profile(grasp_data, "held.yaml")
    sock = tmp_path / "d.sock"
    session = build_session(load_profile(profile), paced=True, duration_s=60.0)
    server = ControlServer(session, sock)
    server.start()
    runner = threading.Thread(target=session.run, name="test-loop")
    runner.start()
    try:
        yield sock
    finally:
        session.loop.request_stop("test over")
        runner.join(timeout=10)
        server.close()


class View:
    """A ``hapticd view`` process: its URLs (the first two lines of stdout) and stderr."""

    def __init__(self, sock: Path, *args: str, timeout_s: float = 30.0) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hapticd", "view", "--socket", str(sock), *args],
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

    def post(self, path: str, body: bytes, ctype: str = "application/json"):
        req = urllib.request.Request(
            f"{self.base}{path}?key={self.key}",
            data=body,
            headers={"Content-Type": ctype},
            method="POST",
        )
        try:
            with OPENER.open(req, timeout=10) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            with exc:
                return exc.code, json.loads(exc.read())

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

    def start(sock: Path, *args: str) -> View:
        v = View(sock, *args)
        started.append(v)
        return v

    yield start
    codes = [v.close() for v in started]
    assert codes == [0] * len(codes), f"hapticd view exit codes {codes}"


def sse_events(response, want, timeout_s: float = 20.0):
    """Read Server-Sent Events from ``response`` until ``want(events)`` holds; fail at the
    deadline. Events are (name, data)."""
    events: list[tuple[str, object]] = []
    name, data = "message", []
    deadline = time.monotonic() + timeout_s
    while not want(events):
        if time.monotonic() > deadline:
            pytest.fail(f"the stream did not deliver in {timeout_s:g} s; got {events[-3:]}")
        line = response.readline().decode()
        if not line:
            pytest.fail(f"the stream ended; got {events[-3:]}")
        line = line.rstrip("\n")
        if line == "":
            if data:
                events.append((name, json.loads("\n".join(data))))
            name, data = "message", []
        elif line.startswith("event: "):
            name = line[len("event: ") :]
        elif line.startswith("data: "):
            data.append(line[len("data: ") :])
    return events


def ticks_of(events):
    return [d["tick"] for n, d in events if n == "telemetry"]


def test_the_url_comes_first_then_the_page_and_its_assets(daemon, view):
    v = view(daemon)
    assert v.host == "127.0.0.1"
    assert v.subject_url == v.url + "&mode=subject"
    with v.get("/", key=False) as r:
        assert r.status == 200 and r.headers["Content-Type"].startswith("text/html")
        assert "default-src 'self'" in r.headers["Content-Security-Policy"]
        html = r.read().decode()
    assert 'data-testid="tick"' in html and "/static/view.js" in html
    assets = {"view.js": "text/javascript", "view.css": "text/css"}
    text = html
    for name, ctype in assets.items():
        with v.get(f"/static/{name}", key=False) as r:
            assert r.status == 200 and r.headers["Content-Type"].startswith(ctype)
            text += r.read().decode()
    assert "requestAnimationFrame" in text and "EventSource" in text
    # Nothing from the network: no absolute URL anywhere in the page.
    assert not re.search(r"https?://", text)
    for path in ("/static/server.py", "/static/../server.py", "/nothing"):
        with pytest.raises(urllib.error.HTTPError) as exc:
            v.get(path, key=False)
        exc.value.close()
        assert exc.value.code == 404
    # The data needs the key the URL carries.
    for path in ("/events", "/api/status", "/events?key=wrong"):
        with pytest.raises(urllib.error.HTTPError) as exc:
            v.get(path, key=False)
        with exc.value:
            assert exc.value.code == 403
            assert json.loads(exc.value.read())["error"]["code"] == "forbidden"


def test_the_stream_delivers_advancing_ticks_and_what_the_page_draws(daemon, view):
    v = view(daemon)
    with v.get("/events") as r:
        assert r.headers["Content-Type"] == "text/event-stream"
        events = sse_events(
            r,
            lambda ev: len(set(ticks_of(ev))) >= 3 and any(n == "status" for n, _ in ev),
        )
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
    link = next(d for n, d in events if n == "link")
    assert link["connected"] is True and link["socket"] == str(daemon)


def test_the_subjects_stream_reveals_no_condition(daemon, view):
    v = view(daemon)
    with v.get("/events?mode=subject") as r:
        events = sse_events(
            r,
            lambda ev: len(ticks_of(ev)) >= 2 and any(n == "status" for n, _ in ev),
        )
    for name, data in events:
        if name == "telemetry":
            assert set(data) <= set(SUBJECT_TELEMETRY)
            assert {"object_pos", "object_rot", "proxy_pos", "tick"} <= set(data)
        elif name == "status":
            assert set(data) == {"fingers", "scene"}
            assert set(data["scene"]) == {"bounds_m", "surfaces", "finger_radii_m"}
    blob = json.dumps(events)
    for word in ("allocator", "stiffness", "force", "device_pos", "mass", "residual"):
        assert word not in blob, f"the subject's stream carries {word!r}"


def test_read_only_refuses_a_change(daemon, view):
    v = view(daemon)
    status, reply = v.post("/api/set", json.dumps({"param": "stiffness", "value": "90"}).encode())
    assert status == 403 and reply["error"]["code"] == "read_only"
    assert "--control" in reply["error"]["message"]
    with ControlClient(daemon) as c:
        assert c.get("stiffness_n_per_m") == 60.0


def test_control_applies_a_change_through_the_checked_set_command(daemon, view):
    v = view(daemon, "--control")
    body = json.dumps({"param": "stiffness", "value": "90"}).encode()
    status, reply = v.post("/api/set", body)
    assert status == 200 and reply["ok"] is True
    assert reply["result"]["param"] == "stiffness_n_per_m"
    assert reply["result"]["applied_at_tick"] > 0
    with ControlClient(daemon) as c:
        assert c.get("stiffness_n_per_m") == 90.0
    status, reply = v.post("/api/set", json.dumps({"param": "allocator", "value": "ef"}).encode())
    assert status == 200
    # Bad values are refused with the protocol's codes; nothing changes.
    for param, value, code in (
        ("stiffness", "-1", "out_of_range"),
        ("stiffness", "stiff", "bad_value"),
        ("stifness", "60", "unknown_param"),
        ("allocator", "magic", "bad_value"),
    ):
        status, reply = v.post("/api/set", json.dumps({"param": param, "value": value}).encode())
        assert (status, reply["error"]["code"]) == (400, code), (param, value, reply)
    status, reply = v.post("/api/set", b"stiffness=1", ctype="application/x-www-form-urlencoded")
    assert status == 415
    status, reply = v.post("/api/set", json.dumps({"param": "stiffness", "value": 1}).encode())
    assert status == 400 and reply["error"]["code"] == "bad_request"
    with ControlClient(daemon) as c:
        assert c.get("stiffness_n_per_m") == 90.0 and c.get("allocator") == "ef"
    assert "set stiffness_n_per_m 90" in v.stderr_so_far()


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


def test_a_page_in_headless_chromium_shows_advancing_ticks(daemon, view, tmp_path):
    exe = cdp.find_chromium()
    if exe is None:
        pytest.skip(
            "no chromium (/usr/bin/chromium): apt-get install chromium (.ci/run installs it "
            "when run as root)"
        )
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
        browser.screenshot(tmp_path / "subject.png")


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


def test_the_view_waits_for_a_daemon_and_follows_it_when_it_comes(
    tmp_path, grasp_data, write_profile
):
    sock = tmp_path / "later.sock"
    logs: list[str] = []
    with ViewServer(sock, log=logs.append) as v:
        wait_for(lambda: v.hub.latest("link"), "the link state", timeout_s=10)
        assert json.loads(v.hub.latest("link")[2])["connected"] is False
        for finger in grasp_data["fingers"]:
            finger["device"]["hold_s"] = 60.0
        session = build_session(
            load_profile(write_profile(grasp_data)), paced=True, duration_s=60.0
        )
        server = ControlServer(session, sock)
        server.start()
        runner = threading.Thread(target=session.run, name="test-loop")
        runner.start()
        try:
            wait_for(
                lambda: json.loads(v.hub.latest("link")[2])["connected"],
                "the view to connect to the daemon that came",
                timeout_s=10,
            )
            first = wait_for(lambda: v.hub.latest("telemetry"), "telemetry", timeout_s=10)
            wait_for(
                lambda: json.loads(v.hub.latest("telemetry")[2])["tick"],
                "ticks that advance",
                until=lambda k: k > json.loads(first[2])["tick"],
                timeout_s=10,
            )
        finally:
            session.loop.request_stop("test over")
            runner.join(timeout=10)
            server.close()
        wait_for(
            lambda: json.loads(v.hub.latest("link")[2])["connected"],
            "the view to see the daemon go",
            until=lambda c: c is False,
            timeout_s=15,
        )
    assert any("connected to the daemon" in m for m in logs)
    assert any(m.startswith("no daemon") for m in logs)


@pytest.mark.parametrize(
    ("greeting", "error"),
    [
        (b"", "the daemon closed the connection"),
        (b"[1, 2]\n", "the greeting is not an object"),
        (b"{not json\n", "Expecting property name"),
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
