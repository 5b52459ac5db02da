"""The view process: a link to the daemon's control socket and an HTTP server for the page.

``DaemonLink`` holds two control connections: one subscribed to telemetry (a
reader thread), one that polls ``status`` every ``STATUS_PERIOD_S`` and sends the
page's ``set`` commands (with ``--control``). Both reconnect when the daemon goes
away or restarts. What they read goes to a ``Hub``: a bounded ring of events
(telemetry, status, link state), each encoded once as JSON for the experimenter
and once, stripped of all that could reveal the condition, for the subject.

``ViewServer`` serves the page and its assets (package data), the event stream
(``/events``: Server-Sent Events), ``/api/status``, ``/api/params`` and ``/api/set``.
Everything but the page and its assets needs the key the printed URL carries, so
another local user who finds the port can neither watch nor change the run.
"""

from __future__ import annotations

import collections
import contextlib
import hmac
import ipaddress
import json
import secrets
import socket
import sys
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from hapticd import params
from hapticd import protocol as proto
from hapticd.control import ControlClient, NoDaemonError, check_socket_dir

STATUS_PERIOD_S = 0.5  # how often the status is polled (the panels' refresh)
RETRY_S = 0.5  # how soon a lost daemon is looked for again
KEEPALIVE_S = 2.0  # an idle event stream sends a comment this often
CLIENT_TIMEOUT_S = 5.0  # a daemon silent this long is taken as gone
HTTP_TIMEOUT_S = 30.0  # a browser that neither reads nor writes for this long is dropped
MAX_BODY_BYTES = 64 * 1024
MAX_STREAMS = 16  # event streams served at once
RING_EVENTS = 512  # events a slow page may fall behind before it skips some

# What the subject's page receives: the scene's geometry and pose, the fingertips' proxies
# (where the finger is held on the surface) and contact. Not the device positions (their
# depth inside the object shows the stiffness), the forces, the allocator or any parameter.
SUBJECT_TELEMETRY = ("tick", "t", "object_pos", "object_rot", "proxy_pos", "in_contact")
SUBJECT_SCENE = ("bounds_m", "surfaces", "finger_radii_m")

STATIC_TYPES = {
    "index.html": "text/html; charset=utf-8",
    "view.js": "text/javascript; charset=utf-8",
    "view.css": "text/css; charset=utf-8",
}
# The page loads nothing but its own assets and talks only to this server.
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
    "frame-ancestors 'none'; base-uri 'none'; form-action 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}
# Replies that say the request was wrong (400); any other is the daemon's state (409).
BAD_REQUEST_CODES = frozenset(
    {"malformed", "bad_request", "unknown_param", "bad_value", "out_of_range", "too_large"}
)


def is_loopback(host: str) -> bool:
    """Whether every address ``host`` resolves to is a loopback address (127/8, ::1)."""
    try:
        infos = socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP)
    except OSError:
        return False
    addrs = {info[4][0] for info in infos}
    return bool(addrs) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addrs)


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


class Hub:
    """The events the page streams: a bounded ring of (seq, event, experimenter JSON,
    subject JSON or None), and the latest of each kind for a page that just connected."""

    def __init__(self, size: int = RING_EVENTS) -> None:
        self._cond = threading.Condition()
        self._ring: collections.deque[tuple[int, str, bytes, bytes | None]] = collections.deque(
            maxlen=size
        )
        self._latest: dict[str, tuple[int, str, bytes, bytes | None]] = {}
        self._seq = 0
        self.closed = False

    def publish(self, event: str, full: Any, subject: Any | None) -> None:
        """Add an event; ``subject`` None: the subject's page does not get it."""
        item = (0, event, _dumps(full), None if subject is None else _dumps(subject))
        with self._cond:
            self._seq += 1
            item = (self._seq, *item[1:])
            self._ring.append(item)
            self._latest[event] = item
            self._cond.notify_all()

    def latest(self, event: str) -> tuple[int, str, bytes, bytes | None] | None:
        with self._cond:
            return self._latest.get(event)

    def seq(self) -> int:
        with self._cond:
            return self._seq

    def since(
        self, seq: int, timeout_s: float
    ) -> list[tuple[int, str, bytes, bytes | None]] | None:
        """Events after ``seq``, waiting up to ``timeout_s`` for one; [] on timeout, None
        once the hub is closed."""
        with self._cond:
            self._cond.wait_for(lambda: self.closed or self._seq > seq, timeout_s)
            if self.closed:
                return None
            return [item for item in self._ring if item[0] > seq]

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


def _subject_status(st: dict[str, Any]) -> dict[str, Any]:
    scene = st.get("scene") or {}
    return {
        "fingers": st.get("fingers"),
        "scene": {k: scene[k] for k in SUBJECT_SCENE if k in scene},
    }


class DaemonLink:
    """The view's connections to the daemon (telemetry; status and set), reconnecting."""

    def __init__(
        self,
        socket_path: Path,
        hub: Hub,
        *,
        rate_hz: float,
        control: bool,
        log: Callable[[str], None],
    ) -> None:
        self.path = socket_path
        self.hub = hub
        self.rate_hz = rate_hz
        self.control = control
        self.log = log
        self._stop = threading.Event()
        self._lock = threading.Lock()  # the request connection: status polls and sets
        self._request: ControlClient | None = None
        self._telemetry: ControlClient | None = None
        self._connected: bool | None = None
        self._threads = [
            threading.Thread(target=self._telemetry_loop, name="view-telemetry", daemon=True),
            threading.Thread(target=self._status_loop, name="view-status", daemon=True),
        ]

    def start(self) -> None:
        for t in self._threads:
            t.start()

    def close(self) -> None:
        self._stop.set()
        for client in (self._telemetry, self._request):
            if client is not None:
                with contextlib.suppress(OSError):
                    client.sock.shutdown(socket.SHUT_RDWR)  # wakes a blocked read
        for t in self._threads:
            t.join(timeout=CLIENT_TIMEOUT_S + 1.0)

    def _set_link(self, connected: bool, message: str) -> None:
        if connected == self._connected:
            return
        self._connected = connected
        self.log(
            f"connected to the daemon at {self.path}" if connected else f"no daemon: {message}"
        )
        state = {"connected": connected, "socket": str(self.path), "message": message}
        self.hub.publish("link", state, {"connected": connected})

    def _telemetry_loop(self) -> None:
        while not self._stop.is_set():
            client = None
            try:
                client = ControlClient(self.path, timeout_s=CLIENT_TIMEOUT_S)
                self._telemetry = client
                if self._stop.is_set():
                    return
                client.subscribe(self.rate_hz)
                self._set_link(True, "")
                while not self._stop.is_set():
                    sample = client.next_telemetry()
                    subject = {k: sample[k] for k in SUBJECT_TELEMETRY if k in sample}
                    self.hub.publish("telemetry", sample, subject)
            # ProtocolError and JSON errors are ValueErrors; TypeError: a frame not an object.
            except (OSError, ValueError, TypeError) as exc:
                if not self._stop.is_set():
                    self._set_link(False, str(exc))
            finally:
                self._telemetry = None
                if client is not None:
                    client.close()
            self._stop.wait(RETRY_S)

    def _status_loop(self) -> None:
        last: tuple[int, float] | None = None
        while not self._stop.is_set():
            try:
                with self._lock:
                    if self._request is None:
                        self._request = ControlClient(self.path, timeout_s=CLIENT_TIMEOUT_S)
                        last = None
                    st = self._request.status()
                now = time.monotonic()
                achieved = None
                if last is not None and now > last[1] and st["tick"] >= last[0]:
                    achieved = (st["tick"] - last[0]) / (now - last[1])
                last = (st["tick"], now)
                full = {
                    **st,
                    "view": {
                        "achieved_hz": achieved,
                        "control": self.control,
                        "socket": str(self.path),
                        "telemetry_hz": self.rate_hz,
                    },
                }
                self.hub.publish("status", full, _subject_status(st))
            except (OSError, ValueError, KeyError, TypeError):
                self._drop_request()
            self._stop.wait(STATUS_PERIOD_S)
        self._drop_request()  # the view is closing: its request connection goes too

    def _drop_request(self) -> None:
        with self._lock:
            if self._request is not None:
                self._request.close()
                self._request = None

    def set(self, param: str, value: Any) -> dict[str, Any]:
        """Send ``set`` on the request connection: the daemon's result, or ProtocolError,
        NoDaemonError, OSError."""
        try:
            with self._lock:
                if self._request is None:
                    self._request = ControlClient(self.path, timeout_s=CLIENT_TIMEOUT_S)
                return self._request.set(param, value)
        except proto.ProtocolError:
            raise
        except (OSError, ValueError):
            self._drop_request()
            raise


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = False  # server_close() joins the handlers: nothing outlives close()
    block_on_close = True
    view: ViewServer


class _Handler(BaseHTTPRequestHandler):
    server: _HTTPServer
    server_version = "hapticd-view"
    protocol_version = "HTTP/1.0"  # one request per connection; a stream ends by closing
    timeout = HTTP_TIMEOUT_S

    def log_message(self, format: str, *args: Any) -> None:
        pass  # the browser's requests are no news; errors are answered, not logged

    # -- replies ------------------------------------------------------------------------

    def _head(self, status: int, ctype: str, length: int | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        if length is not None:
            self.send_header("Content-Length", str(length))
        for k, v in SECURITY_HEADERS.items():
            self.send_header(k, v)
        self.end_headers()

    def _json(self, status: int, body: Any) -> None:
        data = _dumps(body)
        self._head(status, "application/json", len(data))
        self.wfile.write(data)

    def _error(self, status: int, code: str, message: str) -> None:
        self._json(status, {"ok": False, "error": {"code": code, "message": message}})

    def _authorised(self, query: dict[str, list[str]]) -> bool:
        key = query.get("key", [""])[0]
        if hmac.compare_digest(key.encode(), self.server.view.key.encode()):
            return True
        self._error(
            HTTPStatus.FORBIDDEN,
            "forbidden",
            "this needs the key in the URL that hapticd view printed (open that URL)",
        )
        return False

    # -- requests -----------------------------------------------------------------------

    def do_GET(self) -> None:
        url = urlsplit(self.path)
        query = parse_qs(url.query)
        path = url.path
        if path in ("/", "/index.html"):
            self._static("index.html")
        elif path.startswith("/static/") and path[len("/static/") :] in STATIC_TYPES:
            self._static(path[len("/static/") :])
        elif path == "/events":
            if self._authorised(query):
                self._events(query.get("mode", ["experimenter"])[0] == "subject")
        elif path == "/api/status":
            if self._authorised(query):
                item = self.server.view.hub.latest("status")
                link = self.server.view.hub.latest("link")
                body = {
                    "status": None if item is None else json.loads(item[2]),
                    "link": None if link is None else json.loads(link[2]),
                }
                self._json(HTTPStatus.OK, body)
        elif path == "/api/params":
            if self._authorised(query):
                self._json(HTTPStatus.OK, self.server.view.params_json())
        else:
            self._error(HTTPStatus.NOT_FOUND, "not_found", f"no page {path!r}")

    def do_POST(self) -> None:
        url = urlsplit(self.path)
        if url.path != "/api/set":
            self._error(HTTPStatus.NOT_FOUND, "not_found", f"no page {url.path!r}")
            return
        if not self._authorised(parse_qs(url.query)):
            return
        view = self.server.view
        if not view.control:
            self._error(
                HTTPStatus.FORBIDDEN,
                "read_only",
                "this view is read-only: start hapticd view with --control to allow changes",
            )
            return
        ctype = self.headers.get("Content-Type", "").split(";")[0].strip()
        if ctype != "application/json":
            self._error(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "bad_request", "send application/json")
            return
        try:
            length = int(self.headers.get("Content-Length", ""))
        except ValueError:
            length = -1
        if not 0 <= length <= MAX_BODY_BYTES:
            self._error(
                HTTPStatus.BAD_REQUEST,
                "bad_request",
                f"a body of 0 to {MAX_BODY_BYTES} bytes with its Content-Length is needed",
            )
            return
        try:
            body = json.loads(self.rfile.read(length))
        except (ValueError, OSError):
            body = None
        if not (
            isinstance(body, dict)
            and isinstance(body.get("param"), str)
            and isinstance(body.get("value"), str)
        ):
            self._error(
                HTTPStatus.BAD_REQUEST,
                "bad_request",
                'expected {"param": NAME, "value": TEXT}, the value as on the command line',
            )
            return
        status, reply = view.set(body["param"], body["value"])
        self._json(status, reply)

    def _static(self, name: str) -> None:
        data = (resources.files("hapticd.view") / "static" / name).read_bytes()
        self._head(HTTPStatus.OK, STATIC_TYPES[name], len(data))
        self.wfile.write(data)

    def _events(self, subject: bool) -> None:
        """Stream the hub's events as Server-Sent Events until the page or the view goes."""
        view = self.server.view
        if not view.stream_opened(self.connection):
            self._error(HTTPStatus.SERVICE_UNAVAILABLE, "busy", "too many pages open")
            return
        try:
            self._head(HTTPStatus.OK, "text/event-stream")
            hub = view.hub
            seq = hub.seq()
            # A page that just connected gets the link state and status at once.
            first = [i for i in (hub.latest("link"), hub.latest("status")) if i is not None]
            self.wfile.write(b"retry: 1000\n\n" + self._encode(first, subject))
            while True:
                items = hub.since(seq, KEEPALIVE_S)
                if items is None:
                    return
                if items:
                    seq = items[-1][0]
                    self.wfile.write(self._encode(items, subject) or b": idle\n\n")
                else:
                    self.wfile.write(b": keepalive\n\n")
        except OSError:
            return  # the page went away (or the view is closing)
        finally:
            view.stream_closed(self.connection)

    @staticmethod
    def _encode(items: list[tuple[int, str, bytes, bytes | None]], subject: bool) -> bytes:
        out = []
        for seq, event, full, subj in items:
            data = subj if subject else full
            if data is not None:
                out.append(b"id: %d\nevent: %s\ndata: %s\n\n" % (seq, event.encode(), data))
        return b"".join(out)


class ViewServer:
    """The view: a link to the daemon at ``socket_path`` and the page served on
    ``host``:``port`` (0: a free port). ``control``: the page may send ``set``."""

    def __init__(
        self,
        socket_path: str | Path,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        control: bool = False,
        rate_hz: float = 60.0,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.socket_path = Path(socket_path)
        # A directory another user controls is refused before anything is served.
        check_socket_dir(self.socket_path)
        self.host = host
        self.control = control
        self.key = secrets.token_urlsafe(18)
        self.log = log or (lambda msg: print(f"hapticd view: {msg}", file=sys.stderr, flush=True))
        self.hub = Hub()
        self.link = DaemonLink(
            self.socket_path, self.hub, rate_hz=rate_hz, control=control, log=self.log
        )
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        server_cls = type("_HTTPServerFamily", (_HTTPServer,), {"address_family": family})
        self.httpd: _HTTPServer = server_cls((host, port), _Handler)
        self.httpd.view = self
        self._streams: set[socket.socket] = set()
        self._streams_lock = threading.Lock()
        self._thread = threading.Thread(
            target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1}, name="view-http"
        )

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.httpd.server_address[:2]
        return str(host), int(port)

    @property
    def url(self) -> str:
        """The experimenter's page, with its key."""
        host, port = self.address
        if host in ("0.0.0.0", "::"):
            host = socket.gethostname()  # reachable from elsewhere: the machine's name
        elif ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{port}/?key={self.key}"

    @property
    def subject_url(self) -> str:
        """The subject's page: the scene alone."""
        return f"{self.url}&mode=subject"

    def start(self) -> None:
        self.link.start()
        self._thread.start()

    def close(self) -> None:
        self.hub.close()
        with self._streams_lock:
            for conn in self._streams:
                with contextlib.suppress(OSError):
                    conn.shutdown(socket.SHUT_RDWR)
        self.httpd.shutdown()
        self._thread.join()
        self.httpd.server_close()
        self.link.close()

    def __enter__(self) -> ViewServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def stream_opened(self, conn: socket.socket) -> bool:
        with self._streams_lock:
            if len(self._streams) >= MAX_STREAMS or self.hub.closed:
                return False
            self._streams.add(conn)
            return True

    def stream_closed(self, conn: socket.socket) -> None:
        with self._streams_lock:
            self._streams.discard(conn)

    def params_json(self) -> dict[str, Any]:
        """The settable parameters, for the page's form."""
        return {
            "control": self.control,
            "params": [
                {
                    "name": p.name,
                    "alias": p.alias,
                    "unit": p.unit,
                    "doc": p.doc,
                    "syntax": p.syntax,
                    "range": p.range_text(),
                    "choices": list(p.choices),
                }
                for p in params.PARAMS.values()
            ],
        }

    def set(self, name: str, text: str) -> tuple[int, dict[str, Any]]:
        """A change from the page, checked as ``hapticd set NAME TEXT`` checks it and sent
        as the same ``set`` command: (HTTP status, reply)."""
        try:
            spec = params.lookup(name)
            spec.check(spec.parse(text))
        except params.ParamError as exc:
            return HTTPStatus.BAD_REQUEST, {
                "ok": False,
                "error": {"code": exc.code, "message": str(exc)},
            }
        # The value goes as parsed (JSON-able), not as checked (tuples): the daemon checks it.
        try:
            result = self.link.set(spec.name, spec.parse(text))
        except proto.ProtocolError as exc:
            status = (
                HTTPStatus.BAD_REQUEST if exc.code in BAD_REQUEST_CODES else HTTPStatus.CONFLICT
            )
            return status, {"ok": False, "error": {"code": exc.code, "message": str(exc)}}
        except NoDaemonError as exc:
            return HTTPStatus.SERVICE_UNAVAILABLE, {
                "ok": False,
                "error": {"code": "no_daemon", "message": str(exc)},
            }
        except (OSError, ValueError) as exc:
            return HTTPStatus.SERVICE_UNAVAILABLE, {
                "ok": False,
                "error": {
                    "code": "no_daemon",
                    "message": f"cannot talk to {self.socket_path}: {exc}",
                },
            }
        self.log(f"set {spec.name} {text} (applied at tick {result.get('applied_at_tick')})")
        return HTTPStatus.OK, {"ok": True, "result": result}
