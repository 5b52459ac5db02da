"""The view process: a link to the daemon's control socket and a WebSocket server for the page.

``DaemonLink`` holds two control connections: one subscribed to telemetry and events
(a reader thread), one that polls ``status`` every ``STATUS_PERIOD_S`` (at once after a
``prompt`` or ``response`` event) and sends the pages' commands: ``set`` (with
``--control``) and the subject's ``respond``. Both reconnect when the daemon goes away
or restarts. What they read goes to a ``Hub``, which encodes each message once as JSON
for the experimenter and once, stripped of all that could reveal the condition, for the
subject, and hands it to every open page's bounded queue.

``ViewServer`` is one port served by the ``websockets`` library's threaded server: the
page and its assets, ``/api/status`` and ``/api/params`` as plain HTTP answers to the
opening request, and ``/ws``, the one WebSocket per page (messages to the page and the
page's commands back; docs/view.md). Everything but the page and its assets needs the
key the printed URL carries, so another local user who finds the port can neither watch
nor change the run; a browser may open the WebSocket only from the page's own origin.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import email.utils
import errno
import hashlib
import hmac
import ipaddress
import json
import logging
import os
import re
import secrets
import socket
import stat
import sys
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.sync.server import Server, ServerConnection, serve

from hapticd import params
from hapticd import protocol as proto
from hapticd.control import ControlClient, NoDaemonError, check_socket_dir

STATUS_PERIOD_S = 0.5  # how often the status is polled (the panels' refresh)
RETRY_S = 0.5  # how soon a lost daemon is looked for again
CLIENT_TIMEOUT_S = 5.0  # a daemon silent this long is taken as gone
OPEN_TIMEOUT_S = 5.0  # a connection that does not finish its request in this long is dropped
MAX_CONNECTIONS = 64  # TCP connections at once (pages, requests, handshakes)
# Out of file descriptors, accept() waits this long before it tries again (the pending
# connections stay queued) instead of failing, which would end the accept loop for good.
ACCEPT_BACKOFF_S = 0.1
_OUT_OF_FDS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
# A connection is served only with this many descriptors to spare: its handler needs more
# (the library's reader makes a selector); without them it would die with a traceback.
FD_HEADROOM = 4
ACCEPT_LOG_EVERY_S = 10.0  # a shortage is said at most this often, however many episodes
PING_INTERVAL_S = 5.0  # the WebSocket's keepalive: a page that answers no ping ...
PING_TIMEOUT_S = 10.0  # ... for this long is closed
CLOSE_TIMEOUT_S = 2.0  # a closing page gets this long to answer the close
MAX_MESSAGE_BYTES = 64 * 1024  # a command from a page
MAX_STREAMS = 16  # pages open at once
PAGE_QUEUE = 256  # messages a page may fall behind before it is dropped (~4 s at 60 Hz)
PAGE_SNDBUF_BYTES = 256 * 1024  # the kernel's buffer per page: a stalled tab shows soon
SEND_TIMEOUT_S = 5.0  # a page that takes no byte of a message for this long is dropped

# What the subject's page receives: the scene's geometry and pose, the fingertips' proxies
# (where the finger is held on the surface) and contact. Not the device positions (their
# depth inside the object shows the stiffness), the forces, the allocator or any parameter.
SUBJECT_TELEMETRY = ("tick", "t", "object_pos", "object_rot", "proxy_pos", "in_contact")
SUBJECT_SCENE = ("bounds_m", "surfaces", "finger_radii_m")
# Of the status, the subject's page gets the fingers, this much of the scene, the prompt
# (the question the subject answers) and the screen (text states: instructions, touch,
# release, breaks, ...): nothing else.
SUBJECT_STATUS = ("fingers", "prompt", "screen")
# Of the screen, the keys the subject's page gets (the runner sends words, never the
# condition; the view passes nothing else on whatever a client set).
SUBJECT_SCREEN = ("state", "text", "practice", "progress", "seconds", "correct")
# The daemon's events that change the prompt or the screen: the status is polled at once.
PROMPT_EVENTS = frozenset({"prompt", "response", "screen"})
# A prompt's choice as the protocol allows it (a label the page shows on a button).
CHOICE_RE = re.compile(r"[a-z0-9_-]{1,16}")

STATIC_TYPES = {
    "index.html": "text/html; charset=utf-8",
    "view.js": "text/javascript; charset=utf-8",
    "view.css": "text/css; charset=utf-8",
}
# The page loads nothing but its own assets and talks only to this server ('self' covers
# its own ws: origin as well).
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
    "frame-ancestors 'none'; base-uri 'none'; form-action 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


def is_loopback(host: str) -> bool:
    """Whether every address ``host`` resolves to is a loopback address (127/8, ::1)."""
    try:
        infos = socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP)
    except OSError:
        return False
    addrs = {info[4][0] for info in infos}
    return bool(addrs) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addrs)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


def _message(kind: str, data: Any) -> str:
    """A message to a page: ``{"type": kind, "data": data}``."""
    return _dumps({"type": kind, "data": data})


def key_path(socket_path: Path) -> Path:
    """Where the view keeps its key: beside the control socket, readable by its user only."""
    return socket_path.with_name(socket_path.name + ".view-key")


def subject_key(key: str) -> str:
    """The subject's capability, derived from the experimenter's ``key`` (so it lasts as long
    as the key) and not reversible to it: it opens the subject's page and answers the
    current prompt, nothing else."""
    digest = hmac.new(key.encode(), b"hapticd view: the subject's page", hashlib.sha256)
    return base64.urlsafe_b64encode(digest.digest()).decode()[:24]


def load_or_make_key(path: Path, log: Callable[[str], None]) -> str:
    """The key in ``path`` (a file this user owns, mode 0600, not a link), else a new one
    written there, so a restarted view keeps its URL and its open pages reconnect. A file
    that is not safe to trust or cannot be written leaves a fresh key for this run only."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except FileNotFoundError:
        fd = None
    except OSError as exc:
        log(f"cannot read the key file {path} ({exc.strerror}): a new key for this run only")
        return secrets.token_urlsafe(18)
    if fd is not None:
        with os.fdopen(fd, "r") as f:
            st = os.fstat(f.fileno())
            key = f.read(200).strip()
        if (
            stat.S_ISREG(st.st_mode)
            and st.st_uid == os.getuid()
            and not st.st_mode & 0o077
            and re.fullmatch(r"[\w-]{16,100}", key)
        ):
            return key
        log(
            f"the key file {path} is not a 0600 file of yours holding a key: ignored "
            "(remove it); a new key for this run only"
        )
        return secrets.token_urlsafe(18)
    key = secrets.token_urlsafe(18)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(key + "\n")
    except OSError as exc:
        log(f"cannot write the key file {path} ({exc.strerror}): the key lasts this run only")
    return key


class Page:
    """One open page: its WebSocket, whether it is the subject's, and its bounded queue of
    messages to send (filled by the hub, emptied by the page's sender thread)."""

    def __init__(self, conn: ServerConnection, subject: bool) -> None:
        self.conn = conn
        self.subject = subject
        self.peer = conn.remote_address  # for the log: once closed, a socket names no peer
        self._cond = threading.Condition()
        self._queue: collections.deque[str] = collections.deque()
        self.closed = False
        self.dropped = False  # by the hub: it fell PAGE_QUEUE messages behind

    def offer(self, message: str) -> bool:
        """Queue ``message``; False (and nothing queued) if the page is PAGE_QUEUE behind."""
        with self._cond:
            if self.closed:
                return True
            if len(self._queue) >= PAGE_QUEUE:
                return False
            self._queue.append(message)
            self._cond.notify()
            return True

    def take(self) -> list[str] | None:
        """Every queued message, waiting for one; None once the page is closed."""
        with self._cond:
            self._cond.wait_for(lambda: self.closed or self._queue)
            if self.closed:
                return None
            out = list(self._queue)
            self._queue.clear()
            return out

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def abort(self) -> None:
        """Drop the page at once: a sender blocked writing to it gets an error (shutdown
        wakes a blocked send; the hub never waits for a page)."""
        self.close()
        with contextlib.suppress(OSError):
            self.conn.socket.shutdown(socket.SHUT_RDWR)


class Hub:
    """The messages the pages receive: the latest of each kind (for a page that just
    connected) and the open pages, each with its own bounded queue."""

    def __init__(self, log: Callable[[str], None] | None = None) -> None:
        self._lock = threading.Lock()
        self._latest: dict[str, tuple[Any, str, str | None]] = {}
        self._pages: set[Page] = set()
        self.closed = False
        self.log = log or (lambda msg: None)

    def publish(self, kind: str, full: Any, subject: Any | None, *, keep: bool = True) -> None:
        """Send a message to every page; ``subject`` None: the subject's pages do not get
        it. ``keep``: a page that connects later gets the latest of this kind first."""
        item = (full, _message(kind, full), None if subject is None else _message(kind, subject))
        slow: list[Page] = []
        with self._lock:
            if keep:
                self._latest[kind] = item
            for page in self._pages:
                text = item[2] if page.subject else item[1]
                if text is not None and not page.offer(text):
                    slow.append(page)
            for page in slow:
                self._pages.discard(page)
                page.dropped = True
        for page in slow:
            page.abort()
            self.log(
                f"dropped a page that stopped reading ({PAGE_QUEUE} messages behind): {page.peer}"
            )

    def latest(self, kind: str) -> Any | None:
        """The latest message of ``kind`` as published (the experimenter's), or None."""
        with self._lock:
            item = self._latest.get(kind)
        return None if item is None else item[0]

    def add(self, page: Page) -> bool:
        """Open a page: False if MAX_STREAMS are open (or the hub is closed). It gets the
        link state and the status at once."""
        with self._lock:
            if self.closed or len(self._pages) >= MAX_STREAMS:
                return False
            # First, whose page this is: the key decides (a subject's URL without
            # mode=subject is still the subject's page).
            page.offer(_message("hello", {"role": "subject" if page.subject else "experimenter"}))
            for kind in ("link", "status"):
                item = self._latest.get(kind)
                text = None if item is None else item[2] if page.subject else item[1]
                if text is not None:
                    page.offer(text)
            self._pages.add(page)
            return True

    def remove(self, page: Page) -> None:
        with self._lock:
            self._pages.discard(page)
        page.close()

    def count(self) -> int:
        with self._lock:
            return len(self._pages)

    def close(self) -> None:
        with self._lock:
            self.closed = True
            pages = list(self._pages)
        for page in pages:
            page.close()


def scene_hidden(st: dict[str, Any] | None) -> bool:
    """Whether the screen of status ``st`` hides the scene from the subject (``scene``
    false: the experiment shows text only, the object's motion being a cue)."""
    screen = (st or {}).get("screen")
    return isinstance(screen, dict) and screen.get("scene") is False


def _subject_status(st: dict[str, Any]) -> dict[str, Any]:
    scene = st.get("scene") or {}
    out = {k: st.get(k) for k in SUBJECT_STATUS}
    screen = out["screen"]
    out["screen"] = (
        {k: screen[k] for k in SUBJECT_SCREEN if k in screen} if isinstance(screen, dict) else None
    )
    # A hidden scene: no geometry either (the page draws nothing, and learns nothing).
    hidden = scene_hidden(st)
    out["scene"] = {} if hidden else {k: scene[k] for k in SUBJECT_SCENE if k in scene}
    if hidden:
        out["screen"]["scene"] = False
    return out


class DaemonLink:
    """The view's connections to the daemon (telemetry and events; status and commands),
    reconnecting."""

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
        self._poll_now = threading.Event()  # a prompt came or went: poll the status now
        self._lock = threading.Lock()  # the request connection: status polls and commands
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
        self._poll_now.set()
        for client in (self._telemetry, self._request):
            if client is not None:
                with contextlib.suppress(OSError):
                    client.sock.shutdown(socket.SHUT_RDWR)  # wakes a blocked read
        for t in self._threads:
            t.join(timeout=CLIENT_TIMEOUT_S + 1.0)

    def poll_status_now(self) -> None:
        self._poll_now.set()

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
                # Every kind: a daemon that knows prompts sends theirs; one that does not
                # refuses no subscription for them.
                client.events_subscribe()
                # Pages get the link, then a status, then telemetry: the page draws the
                # scene the status describes.
                first = client.status()
                self._set_link(True, "")
                self._publish_status(first, None)
                self.poll_status_now()
                while not self._stop.is_set():
                    sample = client.next_telemetry()
                    subject = (
                        None  # the scene is hidden: the subject's page gets no motion at all
                        if scene_hidden(self.hub.latest("status"))
                        else {k: sample[k] for k in SUBJECT_TELEMETRY if k in sample}
                    )
                    self.hub.publish("telemetry", sample, subject)
                    while client.pending_events:
                        self._on_event(client.pending_events.popleft())
            # ProtocolError and JSON errors are ValueErrors; TypeError: a frame not an object.
            except (OSError, ValueError, TypeError) as exc:
                if not self._stop.is_set():
                    self._set_link(False, str(exc))
            finally:
                self._telemetry = None
                if client is not None:
                    client.close()
            self._stop.wait(RETRY_S)

    def _on_event(self, ev: dict[str, Any]) -> None:
        """An event from the daemon: the experimenter's page lists it; a prompt's coming or
        going is polled at once (the subject's buttons follow it)."""
        if ev.get("event") in PROMPT_EVENTS:
            self.poll_status_now()
        self.hub.publish("event", ev, None, keep=False)

    def _status_loop(self) -> None:
        last: tuple[int, float] | None = None
        while not self._stop.is_set():
            self._poll_now.clear()
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
                # Pages hear the link come up before any status (the telemetry loop
                # publishes the first status itself when it connects).
                if self._connected:
                    self._publish_status(st, achieved)
            except (OSError, ValueError, KeyError, TypeError):
                self._drop_request()
            self._poll_now.wait(STATUS_PERIOD_S)
        self._drop_request()  # the view is closing: its request connection goes too

    def _publish_status(self, st: dict[str, Any], achieved: float | None) -> None:
        """Publish a status to the pages: the daemon's, with the view's own state."""
        if not isinstance(st, dict):  # a lost link to the caller, not a dead thread
            raise TypeError(f"the daemon's status is not an object: {type(st).__name__}")
        st.setdefault("prompt", None)  # a daemon without prompts has none
        st.setdefault("screen", None)  # nor a screen
        view = {
            "achieved_hz": achieved,
            "control": self.control,
            "socket": str(self.path),
            "telemetry_hz": self.rate_hz,
        }
        self.hub.publish("status", {**st, "view": view}, _subject_status(st))

    def _drop_request(self) -> None:
        with self._lock:
            if self._request is not None:
                self._request.close()
                self._request = None

    def call(self, cmd: str, **args: Any) -> dict[str, Any]:
        """Send a command on the request connection: the daemon's result, or ProtocolError,
        NoDaemonError, OSError."""
        try:
            with self._lock:
                if self._request is None:
                    self._request = ControlClient(self.path, timeout_s=CLIENT_TIMEOUT_S)
                return self._request.call(cmd, **args)
        except proto.ProtocolError:
            raise
        except (OSError, ValueError):
            self._drop_request()
            raise


def _error(code: str, message: str) -> dict[str, Any]:
    return {"ok": False, "error": {"code": code, "message": message}}


class _LogBridge(logging.Handler):
    """The websockets library's errors, one line each, on the view's log."""

    def __init__(self, log: Callable[[str], None]) -> None:
        super().__init__(logging.ERROR)
        self._log = log

    def emit(self, record: logging.LogRecord) -> None:
        exc = record.exc_info[1] if record.exc_info else None
        if record.getMessage() == "keepalive ping failed" and isinstance(exc, ConnectionClosed):
            # A page that went (or was dropped) while a ping was out: no news, unless the
            # library closed it for answering no ping.
            if exc.sent is not None and exc.sent.reason == "keepalive ping timeout":
                self._log(f"dropped a page that answered no ping for {PING_TIMEOUT_S:g} s")
            return
        self._log(f"websockets: {record.getMessage()}" + (f": {exc!r}" if exc else ""))


class _Connection(ServerConnection):
    """A connection whose reader, started without a descriptor to spare for its selector
    (a flood at the limit), drops the connection quietly instead of dying with a
    traceback; the handshake then ends and the handler closes the socket."""

    def recv_events(self) -> None:
        try:
            super().recv_events()
        except OSError as exc:
            if exc.errno not in _OUT_OF_FDS:
                raise
            self.close_socket()


class _Listener(socket.socket):
    """The view's listening socket: an ``accept`` that outlives a shortage of file
    descriptors and keeps the connections bounded.

    The ``websockets`` server's accept loop ends at the first error ``accept`` raises, so
    a flood of connections at the descriptor limit would leave the view alive but deaf.
    Here ``accept`` waits ``ACCEPT_BACKOFF_S`` and tries again (saying so once per
    episode), and raises only once the socket is closed (the server shutting down). With
    ``MAX_CONNECTIONS`` open, a new connection takes the place of the oldest that has not
    become an open page (an idle or half-sent request), or is closed at once if every one
    is a page."""

    server: Server | None = None  # set once the server exists
    log: Callable[[str], None] = staticmethod(lambda msg: None)
    # The connections accepted and not yet seen closed, oldest first.
    _accepted: dict[socket.socket, None]
    _quiet_until = 0.0  # no shortage is logged before then
    _muted = False  # the last shortage was not logged: nor is its end

    def accept(self) -> tuple[socket.socket, Any]:
        failing = False
        while True:
            if self.fileno() < 0:
                raise OSError(errno.EBADF, "the view's listening socket is closed")
            try:
                sock, addr = super().accept()
                if not self._headroom():
                    sock.close()  # it could not be served: as if accept() had failed
                    raise OSError(errno.EMFILE, os.strerror(errno.EMFILE))
            except OSError as exc:
                if exc.errno not in _OUT_OF_FDS:
                    raise
                if not failing:
                    failing = True
                    self._say(
                        f"cannot accept a connection: {exc.strerror or exc}; retrying every "
                        f"{ACCEPT_BACKOFF_S:g} s"
                    )
                time.sleep(ACCEPT_BACKOFF_S)
                continue
            if failing:
                self._say("accepting connections again")
                failing = False
            if self._room_for_one(sock):
                return sock, addr
            with contextlib.suppress(OSError):
                sock.close()

    def _say(self, message: str) -> None:
        """Log a shortage (or its end) once per ACCEPT_LOG_EVERY_S, not once per episode:
        a flood that comes and goes would otherwise fill the log."""
        now = time.monotonic()
        if message.startswith("cannot"):
            if now < self._quiet_until:
                self._muted = True
                return
            self._quiet_until = now + ACCEPT_LOG_EVERY_S
            self._muted = False
        elif self._muted:
            return
        self.log(message)

    def _headroom(self) -> bool:
        """Whether FD_HEADROOM more descriptors can be opened (and are closed again)."""
        fds: list[int] = []
        try:
            for _ in range(FD_HEADROOM):
                fds.append(os.dup(self.fileno()))
            return True
        except OSError:
            return False
        finally:
            for fd in fds:
                os.close(fd)

    def _room_for_one(self, sock: socket.socket) -> bool:
        """Whether ``sock``, just accepted, may be served, making room if need be."""
        live = self._accepted
        for old in [s for s in live if s.fileno() < 0]:
            del live[old]  # closed by its handler
        if len(live) >= MAX_CONNECTIONS:
            pages = set() if self.server is None else {c.socket for c in self.server.connections}
            # The oldest connection that is not an open page gives up its place: its
            # handshake (or request) ends at once and its handler closes it.
            victim = next((s for s in live if s not in pages), None)
            if victim is None:
                return False
            del live[victim]
            with contextlib.suppress(OSError):
                victim.shutdown(socket.SHUT_RDWR)
        live[sock] = None
        return True


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
        self.log = log or (lambda msg: print(f"hapticd view: {msg}", file=sys.stderr, flush=True))
        self.key = load_or_make_key(key_path(self.socket_path), self.log)
        self.subject_key = subject_key(self.key)
        self.hub = Hub(self.log)
        self.link = DaemonLink(
            self.socket_path, self.hub, rate_hz=rate_hz, control=control, log=self.log
        )
        logger = logging.getLogger(f"hapticd.view.websockets.{id(self)}")
        logger.propagate = False
        logger.setLevel(logging.ERROR)
        logger.addHandler(_LogBridge(self.log))
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        bound = socket.create_server((host, port), family=family)
        listener = _Listener(bound.family, bound.type, bound.proto, fileno=bound.detach())
        listener.log = self.log
        listener._accepted = {}
        self.server: Server = serve(
            self._page,
            sock=listener,
            create_connection=_Connection,
            process_request=self._http,
            server_header="hapticd-view",
            compression=None,  # loopback: the CPU matters more than the bytes
            open_timeout=OPEN_TIMEOUT_S,
            ping_interval=PING_INTERVAL_S,
            ping_timeout=PING_TIMEOUT_S,
            close_timeout=CLOSE_TIMEOUT_S,
            max_size=MAX_MESSAGE_BYTES,
            logger=logger,
        )
        listener.server = self.server
        self._thread = threading.Thread(target=self.server.serve_forever, name="view-ws")

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.server.socket.getsockname()[:2]
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
        """The subject's page: the scene alone. It carries the subject's capability, not
        the experimenter's key: without ``mode=subject`` it is still the subject's page."""
        return self.url.replace(f"key={self.key}", f"key={self.subject_key}") + "&mode=subject"

    def start(self) -> None:
        self.link.start()
        self._thread.start()

    def close(self) -> None:
        self.hub.close()
        self.server.shutdown()  # closes the pages (each has CLOSE_TIMEOUT_S) and joins them
        self._thread.join()
        self.link.close()

    def __enter__(self) -> ViewServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- HTTP: the page, its assets, the small JSON answers, and the WebSocket's checks -----

    @staticmethod
    def _response(status: int, ctype: str, body: bytes) -> Response:
        headers = Headers(
            [
                ("Date", email.utils.formatdate(usegmt=True)),
                ("Connection", "close"),
                ("Content-Type", ctype),
                ("Content-Length", str(len(body))),
                *SECURITY_HEADERS.items(),
            ]
        )
        status = HTTPStatus(status)
        return Response(status.value, status.phrase, headers, body)

    def _json(self, status: int, body: Any) -> Response:
        return self._response(status, "application/json", _dumps(body).encode())

    def _role(self, query: dict[str, list[str]]) -> str | None:
        """Whose key ``query`` carries: "experimenter", "subject" (the subject's capability,
        or the experimenter's key asking for the subject's page), or None (no valid key)."""
        key = query.get("key", [""])[0].encode()
        # Both compared, in constant time, whichever matches.
        experimenter = hmac.compare_digest(key, self.key.encode())
        subject = hmac.compare_digest(key, self.subject_key.encode())
        if experimenter:
            return "subject" if query.get("mode", [""])[0] == "subject" else "experimenter"
        return "subject" if subject else None

    def _http(self, conn: ServerConnection, request: Request) -> Response | None:
        """Answer a request: the page, an asset, a JSON answer or an error; None lets the
        WebSocket open (``/ws`` with the key, from the page's origin, while there is room)."""
        url = urlsplit(request.path)
        query = parse_qs(url.query)
        path = url.path
        if path in ("/", "/index.html"):
            return self._static("index.html")
        if path.startswith("/static/") and path[len("/static/") :] in STATIC_TYPES:
            return self._static(path[len("/static/") :])
        if path not in ("/ws", "/api/status", "/api/params"):
            return self._json(HTTPStatus.NOT_FOUND, _error("not_found", f"no page {path!r}"))
        role = self._role(query)
        if role is None:
            return self._json(
                HTTPStatus.FORBIDDEN,
                _error(
                    "forbidden",
                    "this needs the key in the URL that hapticd view printed (open that URL)",
                ),
            )
        if path == "/api/status":
            if role == "subject":
                status = self.hub.latest("status")
                body = {
                    "status": None if status is None else _subject_status(status),
                    "link": {"connected": bool((self.hub.latest("link") or {}).get("connected"))},
                }
            else:
                body = {"status": self.hub.latest("status"), "link": self.hub.latest("link")}
            return self._json(HTTPStatus.OK, body)
        if path == "/api/params":
            if role == "subject":
                return self._json(
                    HTTPStatus.FORBIDDEN,
                    _error("forbidden", "the subject's page has no parameters"),
                )
            return self._json(HTTPStatus.OK, self.params_json())
        # /ws: a browser says where the page that opens it came from; only this server's
        # own pages may (another site's script in the same browser may not). A client that
        # is not a browser sends no Origin and needs the key alone.
        origin = request.headers.get("Origin")
        host = request.headers.get("Host")
        if origin is not None and (host is None or origin.lower() != f"http://{host}".lower()):
            return self._json(
                HTTPStatus.FORBIDDEN,
                _error("bad_origin", f"a page from {origin[:100]!r} may not open this stream"),
            )
        if self.hub.count() >= MAX_STREAMS:
            return self._json(HTTPStatus.SERVICE_UNAVAILABLE, _error("busy", "too many pages open"))
        return None

    def _static(self, name: str) -> Response:
        data = (resources.files("hapticd.view") / "static" / name).read_bytes()
        return self._response(HTTPStatus.OK, STATIC_TYPES[name], data)

    # -- the WebSocket: one per page ---------------------------------------------------------

    def _page(self, conn: ServerConnection) -> None:
        """Serve one page: a sender thread empties its queue into the socket while this
        thread reads its commands, until either side ends."""
        query = parse_qs(urlsplit(conn.request.path if conn.request else "").query)
        # The key decides, not the page: the subject's capability is the subject's page
        # whatever its URL says (the HTTP check let in only a valid key).
        page = Page(conn, self._role(query) != "experimenter")
        with contextlib.suppress(OSError):
            conn.socket.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, PAGE_SNDBUF_BYTES)
        # Bounds every write to the page (the library's reads wait in select, unaffected):
        # a page that stopped reading can hold its sender, and the view's close, this long.
        conn.socket.settimeout(SEND_TIMEOUT_S)
        if not self.hub.add(page):
            conn.close(1013, "too many pages open")  # 1013: try again later
            return
        sender = threading.Thread(target=self._send, args=(page,), name="view-page-send")
        sender.start()
        try:
            for raw in conn:
                page.offer(_dumps(self.command(raw, subject=page.subject)))
        except ConnectionClosed:
            pass
        finally:
            self.hub.remove(page)
            sender.join()

    def _send(self, page: Page) -> None:
        try:
            while (batch := page.take()) is not None:
                for text in batch:
                    page.conn.send(text)
        except ConnectionClosed as exc:
            if isinstance(exc.__cause__, TimeoutError) and not page.closed:
                page.dropped = True
                self.log(f"dropped a page that took no data for {SEND_TIMEOUT_S:g} s: {page.peer}")
        except OSError:
            pass
        finally:
            page.close()
            if page.dropped:
                page.conn.close_socket()  # the reader thread then ends too

    def command(self, raw: str | bytes, *, subject: bool) -> dict[str, Any]:
        """A command from a page, answered: ``{"type": "reply", "ref": REF, "ok": ...}``
        (``ref`` as the page sent it, so it can tell its replies apart)."""
        try:
            msg = json.loads(raw)
        except ValueError:
            msg = None
        except RecursionError:  # nested deeper than the parser goes: the page lives on
            return {"type": "reply", "ref": None, **_error("bad_request", "nested too deeply")}
        if not isinstance(msg, dict):
            return {"type": "reply", "ref": None, **_error("bad_request", "a JSON object")}
        ref = msg.get("ref") if isinstance(msg.get("ref"), int | str) else None
        kind = msg.get("type")
        if kind == "set":
            if subject:
                reply = _error("read_only", "the subject's page changes nothing")
            elif not self.control:
                reply = _error(
                    "read_only",
                    "this view is read-only: start hapticd view with --control to allow changes",
                )
            elif not (isinstance(msg.get("param"), str) and isinstance(msg.get("value"), str)):
                reply = _error(
                    "bad_request",
                    'expected {"type": "set", "param": NAME, "value": TEXT}, the value as on '
                    "the command line",
                )
            else:
                reply = self.set(msg["param"], msg["value"])
        elif kind == "respond":
            reply = self.respond(msg.get("prompt"), msg.get("choice"))
        elif kind == "move":
            reply = self._page_move(msg, subject=subject)
        else:
            reply = _error("bad_request", f"unknown message type {str(kind)[:32]!r}")
        return {"type": "reply", "ref": ref, **reply}

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

    def _daemon(self, cmd: str, **args: Any) -> dict[str, Any]:
        """Send a command to the daemon: ``{"ok": True, "result": ...}`` or an error reply
        with the daemon's code (``no_daemon`` when it cannot be reached)."""
        try:
            return {"ok": True, "result": self.link.call(cmd, **args)}
        except proto.ProtocolError as exc:
            return _error(exc.code, str(exc))
        except NoDaemonError as exc:
            return _error("no_daemon", str(exc))
        except (OSError, ValueError) as exc:
            return _error("no_daemon", f"cannot talk to {self.socket_path}: {exc}")

    def set(self, name: str, text: str) -> dict[str, Any]:
        """A change from the page, checked as ``hapticd set NAME TEXT`` checks it and sent
        as the same ``set`` command."""
        try:
            spec = params.lookup(name)
            spec.check(spec.parse(text))
        except params.ParamError as exc:
            return _error(exc.code, str(exc))
        # The value goes as parsed (JSON-able), not as checked (tuples): the daemon checks it.
        reply = self._daemon("set", param=spec.name, value=spec.parse(text))
        if reply["ok"]:
            tick = reply["result"].get("applied_at_tick")
            self.log(f"set {spec.name} {text} (applied at tick {tick})")
        return reply

    def _page_move(self, msg: dict[str, Any], *, subject: bool) -> dict[str, Any]:
        """A virtual device moved from the experimenter's page (``--control`` only): sent as
        the daemon's ``move``, which checks it again (docs/control.md)."""
        if subject or not self.control:
            return _error("read_only", "only the experimenter's page of a --control view moves")
        finger, pos = msg.get("finger"), msg.get("position_m")
        if not (
            isinstance(finger, int | str)
            and not isinstance(finger, bool)
            and isinstance(pos, list)
            and len(pos) == 3
            and all(isinstance(c, int | float) and not isinstance(c, bool) for c in pos)
        ):
            return _error(
                "bad_request",
                'expected {"type": "move", "finger": NAME_OR_INDEX, "position_m": [x, y, z]}',
            )
        return self._daemon("move", finger=finger, position_m=pos)

    def respond(self, prompt_id: Any, choice: Any) -> dict[str, Any]:
        """The subject's answer to the current prompt, sent as the daemon's ``respond``
        command (which checks it against the prompt). It changes no parameter, so every
        page may send it, read-only or not."""
        if not (isinstance(prompt_id, int) and not isinstance(prompt_id, bool) and prompt_id >= 0):
            return _error("bad_request", "'prompt' must be the prompt's id (an int >= 0)")
        if not (isinstance(choice, str) and CHOICE_RE.fullmatch(choice)):
            return _error("bad_value", "'choice' must be one of the prompt's choices")
        reply = self._daemon("respond", prompt=prompt_id, choice=choice)
        if reply["ok"]:
            self.log(f"the subject answered prompt {prompt_id}: {choice}")
            self.link.poll_status_now()  # the prompt is gone: the buttons go too
        elif reply["error"]["code"] == "unknown_command":
            reply = _error(
                "unsupported",
                "this hapticd takes no answers (it has no respond command): update it",
            )
        return reply
