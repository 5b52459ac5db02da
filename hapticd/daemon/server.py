"""The control server: live changes to a running servo loop over a Unix socket.

The server runs in one thread that mostly waits in system calls (select,
recv, send), so it barely takes the GIL from the loop (measured in
docs/daemon.md). It makes no change itself: it hands each change to the loop,
which applies it at the start of its next tick, and the reply names that tick.
Sockets are non-blocking with a bounded output buffer per client, so a client
that stops reading is dropped instead of stalling everyone. The same thread
streams telemetry to subscribers, drains the loop's event ring and delivers its
events in order to event subscribers (hapticd.events), performs reloads asked
for by SIGHUP (a signal handler only writes one byte to a pipe) and sends the
service manager its notifications. The socket is created with mode 0600 (0660 for
one group with ``socket_group``: the service's experimenters); no TCP listener.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import re
import select
import selectors
import socket
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hapticd import __version__, events
from hapticd import protocol as proto
from hapticd.control import check_socket_dir, share_socket
from hapticd.daemon import summary as views
from hapticd.loop.commands import Command, Disable, Enable, SetParam
from hapticd.params import PARAMS, ParamError
from hapticd.profile import ProfileError
from hapticd.recording import RecordingError

if TYPE_CHECKING:
    from hapticd.daemon.session import Session

log = logging.getLogger("hapticd.control")


MAX_OUTPUT_BYTES = 1 << 20  # a client this far behind is dropped
MAX_PENDING_BYTES = 256 * 1024  # unread requests held per client; beyond, reading pauses
LINES_PER_TURN = 4  # requests served per client before the next client's turn
# Connections accepted (or turned away busy) per round of the server thread: a storm of
# connects waits in the kernel's backlog, not in the loop's GIL.
ACCEPTS_PER_ROUND = 8
# Clients turned away busy are logged at most this often, with their count.
BUSY_LOG_PERIOD_S = 1.0
BACKLOG = socket.SOMAXCONN  # connections waiting to be accepted
TELEMETRY_BACKLOG_BYTES = 64 * 1024  # above this a telemetry frame is skipped, not queued
# An event subscriber this far behind is dropped: events are never skipped silently.
EVENTS_BACKLOG_BYTES = 256 * 1024
# How often event subscribers get what the loop's ring holds, s (it holds seconds of events).
EVENT_PERIOD_S = 0.005
EVENTS_LOST = events.CODES["events_lost"]
PARAM_NAMES = tuple(PARAMS)
CAUSE_NAMES = tuple(events.FAULT_CAUSES)
PERIODIC_S = 0.1
# Work in the server thread waits for the loop to go to sleep with this much time left...
WINDOW_S = 200e-6
# ...but no longer than this (at high rates the loop's sleep may never be that long).
WINDOW_MAX_WAIT_S = 0.005
# Connections served at once (a runaway script cannot take every fd), and of those, how many
# may hold a subscription: readers of telemetry or events never take the places of commands.
MAX_CLIENTS = 64
MAX_SUBSCRIBERS = 32
# A connection must send a complete request line this soon after connecting, and finish
# any line it begins this soon after its first byte; else it is told so and closed. A
# connection with a subscription (telemetry or events) is never closed for being quiet.
REQUEST_TIMEOUT_S = 5.0
# The loop first: requests that rebuild or change the loop are served at most this often,
# whoever sends them (the server's own minimum interval per kind, s). One due sooner waits
# at the head of its connection (that client's later requests wait behind it, in order)
# and in a queue of its kind, first come, first served across clients: a storm of them
# slows the replies, not the loop, and one client's storm cannot starve another's change.
# `disable` and `stop` are never limited: taking forces away must not wait for anyone.
RATE_LIMITS_S = {"reload": 1.0, "change": 0.02, "mark": 0.005}
LIMITED = {
    "mark": "mark",
    "reload": "reload",
    "set": "change",
    "enable": "change",
    "record_start": "change",
    "record_stop": "change",
}
# Refused with `stopped` once a stop was requested: they would change a loop on its way out.
REFUSED_WHEN_STOPPING = frozenset({"set", "enable", "reload", "record_start", "move"})
# While a reload parses and builds (Python work in this thread), the GIL is handed to the
# loop within this long when the loop wakes (the loop's own setting is 0.5 ms, more than
# its wake-up margin of 0.2 ms).
RELOAD_SWITCH_INTERVAL_S = 5e-5
# When accept() fails for want of file descriptors the connection stays queued and the
# listener readable; it is left unwatched this long instead of being retried in a spin.
ACCEPT_BACKOFF_S = 0.1
_OUT_OF_FDS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)


def await_window(loop: Any, gate_fd: int, max_wait_s: float = WINDOW_MAX_WAIT_S) -> None:
    """Wait, without holding the GIL, until the servo ``loop`` (running and paced) has just
    gone to sleep with at least WINDOW_S left, so Python work in the calling thread does
    not make the loop wait for the GIL (measured in docs/daemon.md). ``gate_fd`` is the
    read end of the loop's sleep gate (``loop.open_sleep_gate()``: a byte each time it goes
    to sleep); gives up after ``max_wait_s`` s."""
    if not loop.running or not loop.paced:
        return
    give_up = time.monotonic() + max_wait_s
    while True:
        with contextlib.suppress(BlockingIOError):
            while os.read(gate_fd, 4096):
                pass
        now = time.monotonic()
        if now < loop.sleep_until - WINDOW_S or now >= give_up:
            return
        select.select([gate_fd], [], [], give_up - now)


class SocketInUseError(OSError):
    """Another live hapticd already serves this socket."""


def busy_error(clients: int, limit: int) -> bytes:
    """The line a client gets instead of the greeting when every place is in use."""
    return proto.error(
        None,
        "busy",
        f"the daemon is busy: {clients} clients connected (at most {limit}, each with a "
        "recent request or a subscription); close one and try again",
        clients=clients,
    )


def peer_cred(sock: socket.socket) -> tuple[int | None, int | None]:
    """The pid and uid of the process at the other end of the Unix socket ``sock``
    (SO_PEERCRED), each None if the kernel does not say."""
    size = struct.calcsize("3i")
    try:
        pid, uid, _gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, PEERCRED, size))
    except (OSError, struct.error):
        return None, None
    return pid, uid


def _abspath(path: str | Path | None) -> str | None:
    """``path`` made absolute (the daemon's working directory is not its clients'), or None."""
    return None if path is None else os.path.abspath(path)


def peer_uid(sock: socket.socket) -> int | None:
    """The uid of the process at the other end of the Unix socket ``sock``, or None."""
    return peer_cred(sock)[1]


PEERCRED = getattr(socket, "SO_PEERCRED", 17)  # 17 on Linux, the only platform served


def within(path: str, dirs: Sequence[str]) -> bool:
    """Is ``path`` (resolved) inside one of ``dirs`` (resolved directories)?"""
    return any(os.path.commonpath([path, d]) == d for d in dirs)


_LINE_NOTE = re.compile(r"\(line (\d+)\)$|^\S.*?: line (\d+):", re.MULTILINE)
_ERROR_COUNT = re.compile(r": (\d+) error\(s\) in profile$")


def redacted_profile_error(path: str, message: str) -> str:
    """What a client that is not the daemon's user is told of a profile ``message`` about
    ``path``: the file, how many errors and their lines, never a key or a value from the
    file (it may be one only the daemon can read)."""
    first = message.splitlines()[0] if message else ""
    count = _ERROR_COUNT.search(first)
    lines = sorted({int(a or b) for a, b in _LINE_NOTE.findall(message)})
    what = f"{count.group(1)} error(s)" if count else "not usable"
    at = f", at line(s) {', '.join(map(str, lines))}" if lines else ""
    return (
        f"{path}: not a valid profile ({what}{at}); the daemon shows its file's keys and "
        f"values only to its own user: `hapticd check {path}` shows them to anyone who may "
        "read the file"
    )


@dataclass
class _Conn:
    sock: socket.socket
    inbuf: bytearray = field(default_factory=bytearray)
    outbuf: bytearray = field(default_factory=bytearray)
    discarding: bool = False  # inside a line that was too long: skip to its newline
    rate_hz: float = 0.0  # telemetry subscription; 0: none
    next_due: float = 0.0
    skipped: int = 0
    event_kinds: frozenset[int] | None = None  # event subscription (kind codes); None: none
    events_from: int = 0  # the first tick whose events this subscriber gets
    active_at: float = field(default_factory=time.monotonic)  # connected, or last request
    served: int = 0  # complete requests served
    line_since: float | None = None  # when the unfinished line in inbuf began
    wait_until: float = 0.0  # its next request is rate-limited until then (inf: queued)
    uid: int | None = None  # the client's uid (SO_PEERCRED); None: unknown
    pid: int | None = None  # the client's process (SO_PEERCRED); None: unknown

    @property
    def subscribed(self) -> bool:
        return bool(self.rate_hz) or self.event_kinds is not None


class ControlServer:
    """Serves the control protocol for ``session`` on the Unix socket at ``path``.

    ``path`` None serves no socket but still handles SIGHUP reloads and service
    notifications. ``periodic`` callables run in the server thread about every 0.1 s.
    """

    def __init__(
        self,
        session: Session,
        path: str | Path | None,
        *,
        periodic: list[Callable[[], None]] | None = None,
        max_clients: int = MAX_CLIENTS,
        max_subscribers: int = MAX_SUBSCRIBERS,
        request_timeout_s: float = REQUEST_TIMEOUT_S,
        rate_limits_s: dict[str, float] | None = None,
        socket_group: int | None = None,
        reload_dirs: Sequence[str | Path] | None = None,
    ) -> None:
        self.session = session
        # The group (gid) whose members may connect too (--socket-group), else only this user.
        self.socket_group = socket_group
        # Clients of another uid than this (a --socket-group member) reload only profiles in
        # these directories (default: the running profile's own), resolved: no `..` or link
        # leads out of them.
        self.owner_uid = os.getuid()
        source = session.profile.source
        given = (
            reload_dirs
            if reload_dirs is not None
            else []
            if source is None
            else [Path(source).parent]
        )
        self.reload_dirs = [os.path.realpath(d) for d in given]
        self.max_clients = max_clients
        self.max_subscribers = max_subscribers
        self.request_timeout_s = request_timeout_s
        self.idle_closed = 0  # connections closed for sending no complete request in time
        self.loop = session.loop
        self.path = Path(path) if path is not None else None
        self.periodic = [*(periodic or []), self._watch_recording]
        self._reported: object = None  # the recorder whose failure was last logged
        self._sel = selectors.DefaultSelector()
        self._stop = threading.Event()
        self._conns: dict[socket.socket, _Conn] = {}
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._wake_r = self._wake_w = -1
        self._gate_r = -1
        self.reloads: list[str] = []  # outcome of each SIGHUP reload, for status and tests
        self.events_backlog_bytes = EVENTS_BACKLOG_BYTES
        self.slow_event_clients = 0  # event subscribers dropped for falling behind
        # Called in this thread with each batch of event lines, in order, as subscribers get
        # them (the LSL marker outlet, hapticd.daemon.lsl); each must return at once.
        self.event_sinks: list[Callable[[list[bytes]], None]] = []
        self._responses: dict[tuple[int, int], str] = {}
        self._responses_of: object = None  # the profile _responses was made from
        # The subject prompt (id, question, choices), or None; answered by `respond`.
        self.prompt: dict[str, Any] | None = None
        # The lease (one experiment at a time): the connection holding it and what it said
        # of itself ({"subject", "pid"}); ended by release or by that connection closing.
        self.lease: tuple[_Conn, dict[str, Any]] | None = None
        # What the lease's holder found (every parameter's value, the recorder), so that a
        # holder whose connection closes before it put things back leaves the daemon so.
        self._lease_found: tuple[dict[str, Any], object] = ({}, None)
        # What the subject's screen shows besides the prompt (`screen`), or None.
        self.screen: dict[str, Any] | None = None
        self.rate_limits_s = {**RATE_LIMITS_S, **(rate_limits_s or {})}
        self._next_allowed = dict.fromkeys(self.rate_limits_s, 0.0)  # per kind, monotonic s
        # Per kind, the connections whose next request waits for that kind's slot, in the
        # order they asked: the head takes the next slot, the others wait their turn.
        self._queues: dict[str, deque[_Conn]] = {k: deque() for k in self.rate_limits_s}
        self.deferred = 0  # requests that waited for their rate limit
        self._sighup_pending = False  # a SIGHUP reload waits for the reload limit
        self._accept_paused_until: float | None = None  # out of file descriptors
        self.accept_failures = 0  # accept() calls that failed so, since the last success
        self.refused_busy = 0  # clients turned away busy, in all
        self._busy_logged = (0, -math.inf)  # refused_busy and monotonic time at the last log

    @property
    def clients(self) -> int:
        """The connections served now (at most max_clients)."""
        return len(self._conns)

    @property
    def subscribers(self) -> int:
        """The connections holding a subscription (telemetry or events) now."""
        return sum(c.subscribed for c in list(self._conns.values()))

    @property
    def event_subscribers(self) -> int:
        """The connections subscribed to events now."""
        return sum(c.event_kinds is not None for c in list(self._conns.values()))

    @property
    def serving(self) -> bool:
        """Whether the server thread runs (from start until close)."""
        return self._thread is not None and self._thread.is_alive()

    # -- lifecycle ---------------------------------------------------------------------

    def start(self) -> None:
        """Bind the socket (SocketInUseError if a live daemon has it) and start serving."""
        if self.path is not None:
            self._sock = self._bind(self.path, self.socket_group)
            self._sel.register(self._sock, selectors.EVENT_READ, None)
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._gate_r = self.loop.open_sleep_gate()
        self._thread = threading.Thread(target=self._serve, name="hapticd-control", daemon=True)
        self._thread.start()

    @staticmethod
    def _bind(path: Path, group: int | None = None) -> socket.socket:
        # UnsafeSocketDirError: someone else's directory
        check_socket_dir(path, create=True, group=group)
        if path.exists() or path.is_symlink():
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                probe.connect(str(path))
            except OSError:
                path.unlink()  # stale: left by a daemon that crashed
            else:
                raise SocketInUseError(f"another hapticd is serving {path}")
            finally:
                probe.close()
        # Bound under a name of its own, given its mode and group, listening, and only then
        # linked at ``path``: a client never finds the socket there before its group may
        # connect. link(), unlike rename(), fails if another daemon took ``path`` meanwhile.
        made = path.with_name(f".{path.name}.{os.getpid()}")
        with contextlib.suppress(FileNotFoundError):
            made.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)  # created 0600: only this user may connect
        try:
            try:
                sock.bind(str(made))
            finally:
                os.umask(old)
            if group is not None:
                share_socket(made, group)  # then 0660 for that group only
            sock.listen(BACKLOG)
            try:
                os.link(made, path)
            except FileExistsError:
                raise SocketInUseError(f"another hapticd is serving {path}") from None
        except OSError:
            sock.close()
            raise
        finally:
            with contextlib.suppress(OSError):
                made.unlink()
        sock.setblocking(False)
        return sock

    def close(self) -> None:
        """Stop the thread, drop the clients, remove the socket; never raises."""
        self._stop.set()
        self._wake(b"Q")
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for conn in list(self._conns.values()):
            with contextlib.suppress(Exception):
                self._refuse_waiting(conn)
            with contextlib.suppress(Exception):
                self._drop(conn.sock)
        if self._sock is not None:
            with contextlib.suppress(Exception):
                self._sel.unregister(self._sock)
            with contextlib.suppress(Exception):
                self._sock.close()
            self._sock = None
            if self.path is not None:
                with contextlib.suppress(OSError):
                    self.path.unlink()
        with contextlib.suppress(Exception):
            self._sel.close()
        if self._gate_r >= 0:
            with contextlib.suppress(Exception):
                self.loop.close_sleep_gate()
        for fd in (self._wake_r, self._wake_w, self._gate_r):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._wake_r = self._wake_w = self._gate_r = -1

    def _refuse_waiting(self, conn: _Conn) -> None:
        """Answer every complete request still waiting on ``conn`` with ``stopped`` (the
        server is closing: each request gets a reply), best effort, without blocking."""
        why = self.loop.end_reason or self.loop.stop_reason or "the control server closed"
        while (cut := conn.inbuf.find(b"\n")) >= 0:
            line = bytes(conn.inbuf[:cut])
            del conn.inbuf[: cut + 1]
            try:
                req_id = proto.request_id(proto.decode(line))
            except proto.ProtocolError:
                req_id = None
            conn.outbuf += proto.error(req_id, "stopped", f"the daemon stopped: {why}")
        with contextlib.suppress(OSError):
            conn.sock.send(conn.outbuf)

    def _wake(self, what: bytes) -> None:
        if self._wake_w < 0:
            return
        with contextlib.suppress(OSError):  # full pipe: a wake-up is already pending
            os.write(self._wake_w, what)

    def _await_window(self) -> None:
        await_window(self.loop, self._gate_r)

    def _await_io_window(self) -> None:
        """Before accepting, reading and writing sockets: they are Python work too, done in
        the loop's sleep as every request's is, so a storm of clients delays the replies,
        not the ticks (scripts/bench_hostile.py measures it)."""
        self._await_window()

    def request_reload(self) -> None:
        """Reload the profile from its file in the server thread (safe in a signal handler)."""
        self._wake(b"R")

    # -- the server thread -------------------------------------------------------------

    def _serve(self) -> None:
        next_periodic = time.monotonic()
        while not self._stop.is_set():
            try:
                next_periodic = self._serve_once(next_periodic)
            except Exception:
                # Nothing may end this thread: it serves the socket, SIGHUP reloads and the
                # service manager's watchdog. Log, pause a little (no hot error loop), go on.
                log.exception("control thread: unexpected error; serving on")
                self._stop.wait(0.05)
        # The run is over (or the server closing): what the loop's last ticks reported.
        with contextlib.suppress(Exception):
            self._deliver_events()

    def _serve_once(self, next_periodic: float) -> float:
        """One round: wait for sockets or the next due time, serve, run periodic tasks."""
        now = time.monotonic()
        due = [next_periodic] + [c.next_due for c in self._conns.values() if c.rate_hz]
        if self._accept_paused_until is not None:
            due.append(self._accept_paused_until)
        due.extend(c.wait_until for c in self._conns.values() if c.wait_until > now)
        if self._sighup_pending:
            due.append(self._next_allowed["reload"])
        if any(c.event_kinds is not None for c in self._conns.values()):
            due.append(now + EVENT_PERIOD_S)
        timeout = 0.0 if self._pending() else max(0.0, min(due) - now)
        ready_now = self._sel.select(timeout=timeout)
        if ready_now:
            self._await_io_window()
        for key, ready in ready_now:
            obj = key.fileobj
            if obj is self._sock:
                for _ in range(ACCEPTS_PER_ROUND):
                    if not self._accept():
                        break
            elif obj == self._wake_r:
                self._woken()
            elif isinstance(obj, socket.socket) and obj in self._conns:
                if ready & selectors.EVENT_WRITE:
                    self._flush(self._conns[obj])
                if ready & selectors.EVENT_READ and obj in self._conns:
                    self._read(self._conns[obj])
        self._serve_turns()
        now = time.monotonic()
        if self._sighup_pending and now >= self._next_allowed["reload"]:
            self._reload_from_signal()
        if self._accept_paused_until is not None and now >= self._accept_paused_until:
            self._resume_accept()
        self._stream(now)
        self._deliver_events()
        if now >= next_periodic:
            next_periodic = now + PERIODIC_S
            self._reap_idle(now)
            # Also empties the sleep gate's pipe, which otherwise fills (a byte a tick).
            self._await_window()
            for fn in self.periodic:
                try:
                    fn()
                except Exception as exc:  # a notification must not end the server
                    log.warning("periodic task failed: %s", exc)
        return next_periodic

    def _watch_recording(self) -> None:
        """Log, once, a recording that is failing (its writer died, its file was deleted):
        status and record_stop report it too, but nobody may be asking."""
        rec = self.loop.recorder
        if rec is None or rec is self._reported:
            return
        error = rec.error
        if error is not None:
            self._reported = rec
            log.error("recording %s is failing: %s", rec.path, error)

    def _woken(self) -> None:
        try:
            data = os.read(self._wake_r, 64)
        except BlockingIOError:
            return
        if b"R" in data:
            self._sighup_pending = True  # done when the reload limit allows (_serve_once)

    def _reload_from_signal(self) -> None:
        self._sighup_pending = False
        self._next_allowed["reload"] = time.monotonic() + self.rate_limits_s["reload"]
        try:
            result = self._reload_gently()
        except (ProfileError, ValueError, TimeoutError, OSError) as exc:
            msg = f"reload rejected, the running profile stays: {exc}"
            log.error("%s", msg)
        except Exception as exc:  # whatever a profile provokes, the daemon serves on
            msg = f"reload rejected, the running profile stays: {type(exc).__name__}: {exc}"
            log.exception("%s", msg)
        else:
            msg = f"reloaded {result['path']} at tick {result['applied_at_tick']}"
            log.info("%s", msg)
        self.reloads.append(msg)

    def _accept(self) -> bool:
        """Take one waiting connection: served, or turned away busy. False when none was
        waiting (or accepting failed), so the round accepts no more."""
        assert self._sock is not None
        try:
            sock, _ = self._sock.accept()
        except BlockingIOError:
            return False
        except OSError as exc:
            if exc.errno in _OUT_OF_FDS:
                self._pause_accept(exc)
            return False  # otherwise that client went away before we got to it
        self.accept_failures = 0
        if len(self._conns) >= self.max_clients and not self._evict_idle():
            n = len(self._conns)
            self.refused_busy += 1
            self._log_busy(n)
            with contextlib.suppress(OSError):
                sock.send(busy_error(n, self.max_clients))
            sock.close()
            return True
        sock.setblocking(False)
        pid, uid = peer_cred(sock)
        conn = _Conn(sock, uid=uid, pid=pid)
        self._conns[sock] = conn
        self._sel.register(sock, selectors.EVENT_READ, None)
        self._send(conn, proto.greeting(__version__))
        return True

    def _log_busy(self, connected: int) -> None:
        """Say that clients were turned away busy: at once for the first of a while, then at
        most once every BUSY_LOG_PERIOD_S with how many (a storm writes no log storm)."""
        count, at = self._busy_logged
        now = time.monotonic()
        if now - at < BUSY_LOG_PERIOD_S:
            return
        n = self.refused_busy - count
        log.warning(
            "refused %d control client(s)%s: the daemon is busy, %d connected",
            n,
            "" if at == -math.inf else f" in the last {now - at:.1f} s",
            connected,
        )
        self._busy_logged = (self.refused_busy, now)

    def _idle(self, conn: _Conn, now: float) -> bool:
        """A connection that may give up its place: no subscription, no request waiting,
        and either none sent yet or none for ``request_timeout_s``."""
        return (
            not conn.subscribed
            and b"\n" not in conn.inbuf
            and (conn.served == 0 or now - conn.active_at >= self.request_timeout_s)
        )

    def _evict_idle(self) -> bool:
        """At the cap, close the idle connection that has waited longest to make room for a
        new one (one that never sent a request first); False if every one is in use."""
        now = time.monotonic()
        idle = [c for c in self._conns.values() if self._idle(c, now)]
        if not idle:
            return False
        victim = min(idle, key=lambda c: (c.served > 0, c.active_at))
        self._close_idle(victim, "to make room for another client")
        return True

    def _close_idle(self, conn: _Conn, why: str) -> None:
        """Tell ``conn`` why it is closed (one ``idle`` error line, best effort) and close it."""
        self.idle_closed += 1
        with contextlib.suppress(OSError):
            conn.sock.send(
                bytes(conn.outbuf)
                + proto.error(
                    None,
                    "idle",
                    f"the daemon closed this idle connection ({why}): no complete request "
                    f"within {self.request_timeout_s:g} s; connect again (a subscription "
                    "keeps a connection open)",
                )
            )
        self._drop(conn.sock)

    def _reap_idle(self, now: float) -> None:
        """Close the connections that sent no complete request in time: none since they
        connected, or a line begun ``request_timeout_s`` ago and not finished."""
        limit = self.request_timeout_s
        for conn in list(self._conns.values()):
            unfinished = conn.line_since is not None and now - conn.line_since >= limit
            silent = conn.served == 0 and not conn.subscribed and now - conn.active_at >= limit
            if (unfinished or silent) and b"\n" not in conn.inbuf:
                why = "a request line left unfinished" if unfinished else "no request sent"
                self._close_idle(conn, why)

    def _pause_accept(self, exc: OSError) -> None:
        """Stop watching the listener for ACCEPT_BACKOFF_S (out of file descriptors)."""
        if self._sock is None or self._accept_paused_until is not None:
            return
        self.accept_failures += 1
        if self.accept_failures == 1:  # once per episode, not every retry
            log.warning(
                "cannot accept a control client: %s; retrying every %g s",
                exc.strerror or exc,
                ACCEPT_BACKOFF_S,
            )
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(self._sock)
        self._accept_paused_until = time.monotonic() + ACCEPT_BACKOFF_S

    def _resume_accept(self) -> None:
        self._accept_paused_until = None
        if self._sock is not None:
            with contextlib.suppress(KeyError, ValueError):
                self._sel.register(self._sock, selectors.EVENT_READ, None)

    def _drop(self, sock: socket.socket) -> None:
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(sock)
        conn = self._conns.pop(sock, None)
        if conn is not None:
            self._leave_queues(conn)
            if self.lease is not None and self.lease[0] is conn:
                self._end_lease("its connection closed")
        sock.close()

    def _end_lease(self, why: str) -> None:
        """End the lease; a holder that went away leaves no prompt up for the subject."""
        assert self.lease is not None
        holder = self.lease[1]
        self.lease = None
        log.info("lease of subject %s (pid %s) ended: %s", holder["subject"], holder["pid"], why)
        if why != "released" and self.prompt is not None:
            self.prompt = None
            with contextlib.suppress(Exception):
                self._server_event("prompt", prompt=None)
        if why != "released" and self.screen is not None and self.screen.get("state") != "end":
            self.screen = None
            with contextlib.suppress(Exception):
                self._server_event("screen")
        if why != "released":
            self._put_back(holder)

    def _put_back(self, holder: dict[str, Any]) -> None:
        """After a holder went away mid-run: every parameter it changed set back to what it
        found, and the recording it started closed (whole, every tick in it); each failure
        logged, never raised (the daemon serves on)."""
        values, recorder = self._lease_found
        who = f"subject {holder['subject']} (pid {holder['pid']})"
        put = []
        for name, value in values.items():
            try:
                if self.loop.param(name) != value:
                    self.session.apply(SetParam(name, value))
                    put.append(name)
            except Exception as exc:  # the next parameter is still put back
                log.warning("could not put %s back after %s went away: %s", name, who, exc)
        if put:
            log.warning("%s went away mid-run: put back %s", who, ", ".join(put))
        if self.loop.recorder is not None and self.loop.recorder is not recorder:
            try:
                status = self.session.record_stop()
                log.warning("%s went away mid-run: closed its recording %s", who, status["path"])
            except Exception as exc:
                log.warning("could not close the recording %s left open: %s", who, exc)

    def _leave_queues(self, conn: _Conn) -> None:
        """Take ``conn`` out of the rate-limit queues; a new head may go at its kind's slot."""
        for kind, queue in self._queues.items():
            if conn in queue:
                head = queue[0] is conn
                queue.remove(conn)
                if head and queue:
                    queue[0].wait_until = self._next_allowed[kind]

    def _send(self, conn: _Conn, data: bytes) -> None:
        conn.outbuf += data
        if len(conn.outbuf) > MAX_OUTPUT_BYTES:
            log.warning("dropping a control client that stopped reading")
            self._drop(conn.sock)
            return
        self._flush(conn)

    def _flush(self, conn: _Conn) -> None:
        try:
            n = conn.sock.send(conn.outbuf) if conn.outbuf else 0
        except BlockingIOError:
            n = 0
        except OSError:
            self._drop(conn.sock)  # the client went away: harmless
            return
        del conn.outbuf[:n]
        self._update_events(conn)

    def _read(self, conn: _Conn) -> None:
        """Take what the client sent; requests are served later, a few per turn."""
        try:
            data = conn.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._drop(conn.sock)
            return
        if conn.discarding:
            cut = data.find(b"\n")
            if cut < 0:
                return
            conn.discarding = False
            data = data[cut + 1 :]
        conn.inbuf += data
        tail = len(conn.inbuf) - (conn.inbuf.rfind(b"\n") + 1)
        if not tail:
            conn.line_since = None
        elif conn.line_since is None or b"\n" in data:
            conn.line_since = time.monotonic()  # a new line begins in this chunk
        if tail > proto.MAX_LINE_BYTES:
            # One reply for the whole line, then everything up to its newline is dropped.
            del conn.inbuf[len(conn.inbuf) - tail :]
            conn.discarding = True
            self._send(
                conn,
                proto.error(
                    None,
                    "too_large",
                    f"request line longer than {proto.MAX_LINE_BYTES} bytes; discarded",
                ),
            )
        self._update_events(conn)

    def _pending(self) -> bool:
        """Does a client have a whole request waiting that may be served now?"""
        now = time.monotonic()
        return any(b"\n" in c.inbuf and c.wait_until <= now for c in self._conns.values())

    def _limited(self, conn: _Conn, line: bytes) -> bool:
        """Is ``line`` a request of a rate-limited kind that may not be served yet? Then
        ``conn`` keeps (or takes) its place in that kind's queue and waits: the head of the
        queue until the kind's next slot, the others until they are the head. Otherwise a
        limited request books its kind's next slot."""
        if not any(cmd.encode() in line for cmd in LIMITED):
            return False  # cheap: most lines name no limited command at all
        # Parsing is Python work: in the loop's sleep, as every request's (this runs at
        # any time, woken by a deferred request's due time).
        self._await_window()
        try:
            req = proto.decode(line)
        except proto.ProtocolError:
            return False  # answered as the error it is
        cmd = req.get("cmd")
        kind = LIMITED.get(cmd) if isinstance(cmd, str) else None
        if kind is None or self.loop.stop_reason is not None:
            return False  # a request refused while stopping is answered at once
        queue = self._queues[kind]
        now = time.monotonic()
        if queue and queue[0] is not conn:
            if conn not in queue:
                queue.append(conn)  # its place, kept until it is served or goes
                self.deferred += 1
            conn.wait_until = math.inf  # until it is the head (_leave_queues, below)
            return True
        if now < self._next_allowed[kind]:
            if not queue:
                queue.append(conn)
                self.deferred += 1
            conn.wait_until = self._next_allowed[kind]
            return True
        if queue:
            queue.popleft()
        self._next_allowed[kind] = now + self.rate_limits_s[kind]
        if queue:
            queue[0].wait_until = self._next_allowed[kind]
        return False

    def _serve_turns(self) -> None:
        """Serve up to LINES_PER_TURN waiting requests of each client, round-robin: one
        client's burst of pipelined requests does not delay the others. A rate-limited
        request not yet due stops its client's turn (RATE_LIMITS_S)."""
        now = time.monotonic()
        for conn in list(self._conns.values()):
            if conn.wait_until > now:
                continue
            for _ in range(LINES_PER_TURN):
                if conn.sock not in self._conns:
                    break
                cut = conn.inbuf.find(b"\n")
                if cut < 0:
                    break
                line = bytes(conn.inbuf[:cut])
                if self._limited(conn, line):
                    break
                del conn.inbuf[: cut + 1]
                conn.served += 1
                conn.active_at = time.monotonic()
                self._send(conn, self._handle(conn, line))
            if conn.sock in self._conns:
                self._update_events(conn)

    def _update_events(self, conn: _Conn) -> None:
        """Read while fewer than MAX_PENDING_BYTES of requests wait; write while output does."""
        want = (selectors.EVENT_READ if len(conn.inbuf) < MAX_PENDING_BYTES else 0) | (
            selectors.EVENT_WRITE if conn.outbuf else 0
        )
        if conn.sock not in self._conns:
            return
        try:
            events = self._sel.get_key(conn.sock).events
        except KeyError:
            events = 0
        if events == want:
            return
        if not want:
            self._sel.unregister(conn.sock)  # paused until its waiting requests are served
        elif not events:
            self._sel.register(conn.sock, want, None)
        else:
            self._sel.modify(conn.sock, want, None)

    def _stream(self, now: float) -> None:
        sample: dict[str, Any] | None = None
        for conn in list(self._conns.values()):
            if not conn.rate_hz or now < conn.next_due:
                continue
            period = 1.0 / conn.rate_hz
            conn.next_due = max(conn.next_due + period, now)  # no bursts to catch up
            if len(conn.outbuf) > TELEMETRY_BACKLOG_BYTES:
                conn.skipped += 1
                continue
            if sample is None:
                self._await_window()
                sample = views.telemetry(self.loop)
            self._send(conn, proto.telemetry(sample))

    # -- events ------------------------------------------------------------------------

    def _response_map(self) -> dict[tuple[int, int], str]:
        """(finger, button) -> response label, from the running profile (a reload may
        change it)."""
        profile = self.session.profile
        if profile is not self._responses_of:
            self._responses = {
                (i, b): label
                for i, f in enumerate(profile.fingers)
                for b, label in f.responses().items()
            }
            self._responses_of = profile
        return self._responses

    def _deliver_events(self) -> None:
        """Drain the loop's event ring (in its sleep window) and send each subscriber the
        events it asked for, in order, then ``events_lost`` if the ring overflowed. A
        subscriber more than ``events_backlog_bytes`` behind is dropped."""
        ring = self.loop.event_ring
        if not ring.pending:
            return
        self._await_window()
        records, lost = ring.drain()
        subs = [c for c in self._conns.values() if c.event_kinds is not None]
        if not subs and not self.event_sinks:
            return
        names = self.session.profile.finger_names
        responses = self._response_map()
        fault = self.loop.safety.fault
        out: list[tuple[int, int, bytes]] = []
        for code, finger, button, value, tick, t in records.tolist():
            kind = events.EVENTS[code]
            ev: dict[str, Any] = {"event": kind.name, "tick": tick, "t": t}
            if "finger" in kind.fields:
                ev["finger"] = finger
                ev["finger_name"] = names[finger] if 0 <= finger < len(names) else None
            if "button" in kind.fields:
                ev["button"] = button
                label = responses.get((finger, button))
                if label is not None:
                    ev["response"] = label
            if "cause" in kind.fields:
                ev["cause"] = CAUSE_NAMES[value] if 0 <= value < len(CAUSE_NAMES) else "other"
                if fault is not None and fault.tick == tick:
                    ev["message"] = fault.cause
            if "param" in kind.fields:
                ev["param"] = PARAM_NAMES[value] if 0 <= value < len(PARAM_NAMES) else None
            out.append((code, tick, proto.encode(ev)))
        if lost:
            lost_ev = {
                "event": "events_lost",
                "tick": ring.lost_tick,
                "t": ring.lost_t,
                "count": lost,
            }
            out.append((EVENTS_LOST, ring.lost_tick, proto.encode(lost_ev)))
        for sink in self.event_sinks:
            sink([line for _, _, line in out])
        for conn in subs:
            kinds, first = conn.event_kinds, conn.events_from
            assert kinds is not None
            data = b"".join(line for code, tick, line in out if tick >= first and code in kinds)
            if data and conn.sock in self._conns:
                self._send_events(conn, data)

    def _send_events(self, conn: _Conn, data: bytes) -> None:
        """Queue event lines for ``conn``; a subscriber more than ``events_backlog_bytes``
        behind is dropped (it stopped reading), never waited for."""
        conn.outbuf += data
        if len(conn.outbuf) > self.events_backlog_bytes:
            log.warning(
                "dropping an event subscriber %d bytes behind (it stopped reading)",
                len(conn.outbuf),
            )
            self.slow_event_clients += 1
            self._drop(conn.sock)
            return
        self._flush(conn)

    # -- requests ----------------------------------------------------------------------

    def _handle(self, conn: _Conn, line: bytes) -> bytes:
        """The reply to one request line; an error reply echoes the request's id whenever
        the line could be read as a JSON object with a valid id."""
        req_id = None
        req: dict[str, Any] = {}
        self._await_window()
        try:
            req = proto.decode(line)
            req_id = proto.request_id(req)
            return proto.ok(req_id, self._execute(conn, proto.check(req)))
        except proto.ProtocolError as exc:
            return proto.error(req_id, exc.code, str(exc))
        except ProfileError as exc:
            message = str(exc)
            if not self._is_owner(conn):
                source = self.session.profile.source
                message = redacted_profile_error(str(req.get("profile") or source), message)
            return proto.error(req_id, "bad_profile", message)
        except RecordingError as exc:
            return proto.error(req_id, "recording", str(exc))
        except TimeoutError as exc:
            return proto.error(req_id, "timeout", str(exc))
        except ParamError as exc:  # a value only the loop could check (a plugin's name)
            return proto.error(req_id, exc.code, str(exc))
        except ValueError as exc:
            return proto.error(req_id, "rejected", str(exc))
        except Exception as exc:  # a request must never take the daemon down
            log.exception("control request failed")
            return proto.error(req_id, "internal", f"{type(exc).__name__}: {exc}")

    def _is_owner(self, conn: _Conn) -> bool:
        """Is the client the daemon's own user (who may read whatever the daemon reads)?"""
        return conn.uid is not None and conn.uid == self.owner_uid

    def _execute(self, conn: _Conn, req: dict[str, Any]) -> Any:
        stopping = self.loop.stop_reason
        if stopping is not None and req["cmd"] in REFUSED_WHEN_STOPPING:
            raise proto.ProtocolError(
                "stopped", f"the daemon is stopping ({stopping}): {req['cmd']} changes nothing"
            )
        leased = proto.LEASED_COMMANDS | {"lease"}
        if self.lease is not None and self.lease[0] is not conn and req["cmd"] in leased:
            raise proto.ProtocolError("leased", self._leased_message(req["cmd"]))
        result = _HANDLERS[req["cmd"]](self, conn, req)
        if "applied_at_tick" in result:
            what = " ".join(str(req[k]) for k in ("cmd", "param", "value", "path") if k in req)
            log.info("control: %s applied at tick %d", what, result["applied_at_tick"])
        return result

    # -- one handler per request (the protocol checked its arguments) -------------------

    def _status(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        return {
            **views.status(self.loop),
            "profile": self.session.profile.name,
            "fingers": list(self.session.profile.finger_names),
            "reloads": self.reloads,
            "prompt": self.prompt,
            "lease": None if self.lease is None else self.lease[1],
            "profile_path": _abspath(self.session.profile.source),
            "screen": self.screen,
        }

    def _leased_message(self, cmd: str) -> str:
        assert self.lease is not None
        h = self.lease[1]
        return (
            f"{cmd} refused: the daemon is held by an experiment on subject {h['subject']!r} "
            f"(process {h['pid']}); wait for it to end, or end it (its terminal, kill "
            f"{h['pid']}); disable and stop always work"
        )

    def _lease(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        holder = {"subject": req["subject"], "pid": req.get("pid", conn.pid)}
        self.lease = (conn, holder)
        self._lease_found = ({n: self.loop.param(n) for n in PARAMS}, self.loop.recorder)
        log.info("lease taken by subject %s (pid %s)", holder["subject"], holder["pid"])
        return {"holder": holder}

    def _release(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        if self.lease is None or self.lease[0] is not conn:
            return {"released": False}
        self._end_lease("released")
        return {"released": True}

    def _get(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        return {req["param"]: self.loop.param(req["param"])}

    def _stop(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        self.loop.request_stop(f"control: {req['cmd']}")
        return {"stopping": True, "ramp_s": self.loop.stop_ramp_s}

    def _check_subscriber_place(self, conn: _Conn) -> None:
        """ProtocolError ``busy`` if ``conn`` would be one subscriber too many: the places
        beyond max_subscribers are kept for commands (status, disable, stop)."""
        n = self.subscribers
        if not conn.subscribed and n >= self.max_subscribers:
            raise proto.ProtocolError(
                "busy",
                f"the daemon is busy: {n} subscriptions (at most {self.max_subscribers}; the "
                "other places are kept for commands); end one and try again",
            )

    def _subscribe(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        self._check_subscriber_place(conn)
        conn.rate_hz = req["rate_hz"]
        conn.next_due = time.monotonic()
        return {"subscribed": True, "rate_hz": conn.rate_hz}

    def _unsubscribe(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        conn.rate_hz = 0.0
        return {"subscribed": False, "skipped_frames": conn.skipped}

    def _events_subscribe(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        self._check_subscriber_place(conn)
        names = req.get("kinds") or list(events.NAMES)
        conn.event_kinds = frozenset(events.CODES[n] for n in names)
        # Events of this tick on: those of earlier ticks still in the ring are not sent.
        conn.events_from = self.loop.stats.ticks
        kinds = [n for n in events.NAMES if events.CODES[n] in conn.event_kinds]
        return {"subscribed": True, "kinds": kinds, "tick": conn.events_from}

    def _events_unsubscribe(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        conn.event_kinds = None
        return {"subscribed": False}

    def _prompt(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        pid = req.get("prompt")
        if pid is None:
            self.prompt = None
        else:
            self.prompt = {"id": pid, "question": req["question"], "choices": list(req["choices"])}
        self._server_event("prompt", prompt=pid)
        return {}

    def _respond(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        now, pid = self.prompt, req["prompt"]
        if now is None or now["id"] != pid:
            current = "no prompt is current" if now is None else f"the prompt is {now['id']}"
            raise proto.ProtocolError("no_prompt", f"no prompt {pid} to answer: {current}")
        if req["choice"] not in now["choices"]:
            raise proto.ProtocolError(
                "bad_value",
                f"prompt {pid} offers {now['choices']}, not {req['choice']!r}",
            )
        self.prompt = None
        self._server_event("response", prompt=pid, choice=req["choice"])
        return {}

    def _screen(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        self.screen = None if req["screen"] is None else dict(req["screen"])
        self._server_event("screen")
        return {}

    def _server_event(self, name: str, **fields: Any) -> int:
        """Send the server-made event ``name`` to its subscribers (and the event sinks),
        after the loop's events still in the ring (so every subscriber sees them in order),
        stamped with the current tick and its time; returns that tick."""
        self._deliver_events()
        code = events.CODES[name]
        tick = self.loop.stats.ticks
        line = proto.encode({"event": name, "tick": tick, "t": self.loop.now(), **fields})
        for sink in self.event_sinks:
            sink([line])
        for conn in list(self._conns.values()):
            kinds = conn.event_kinds
            if kinds is not None and code in kinds and tick >= conn.events_from:
                self._send_events(conn, line)
        return tick

    def _mark(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        return {"tick": self._server_event("mark", text=req["text"])}

    def _record_start(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        return self.session.record_start(req["path"], overwrite=req.get("overwrite", False))

    def _record_stop(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        return self.session.record_stop()

    def _reload(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        path = req.get("profile")
        if path is not None and not self._is_owner(conn):
            # The resolved path is checked and read: `..` or a link cannot lead elsewhere.
            path = os.path.realpath(path)
            if not within(path, self.reload_dirs):
                allowed = ", ".join(self.reload_dirs) or "none"
                raise proto.ProtocolError(
                    "denied",
                    f"reload {req['profile']}: a client of uid {conn.uid} (not the daemon's "
                    f"user) may reload only profiles in the directories the daemon allows "
                    f"(hapticd run --reload-dir): {allowed}",
                )
        return self._reload_gently(path)

    def _reload_gently(self, path: str | None = None) -> dict[str, Any]:
        """``session.reload`` with a short GIL switch interval: its parsing and building, in
        this thread, hand the GIL to the loop soon after the loop wakes."""
        old = sys.getswitchinterval()
        sys.setswitchinterval(min(old, RELOAD_SWITCH_INTERVAL_S))
        try:
            return self.session.reload(path)
        finally:
            sys.setswitchinterval(old)

    def _set(self, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        # Prepared here (a new plan for the allocator or the directions): with reload's short
        # GIL switch interval, so that the loop waking meanwhile soon gets the GIL.
        old = sys.getswitchinterval()
        sys.setswitchinterval(min(old, RELOAD_SWITCH_INTERVAL_S))
        try:
            done = self.session.apply(SetParam(req["param"], req["value"]))
        finally:
            sys.setswitchinterval(old)
        return {"applied_at_tick": done.tick, "param": req["param"]}


def _apply(command: type[Command]) -> Callable[[ControlServer, _Conn, dict[str, Any]], Any]:
    """A handler that applies ``command`` (no arguments) at the next tick boundary."""

    def handle(server: ControlServer, conn: _Conn, req: dict[str, Any]) -> dict[str, Any]:
        return {"applied_at_tick": server.session.apply(command()).tick}

    return handle


_HANDLERS: dict[str, Callable[[ControlServer, _Conn, dict[str, Any]], dict[str, Any]]] = {
    "status": ControlServer._status,
    "get": ControlServer._get,
    "set": ControlServer._set,
    "enable": _apply(Enable),
    "disable": _apply(Disable),
    "record_start": ControlServer._record_start,
    "record_stop": ControlServer._record_stop,
    "reload": ControlServer._reload,
    "subscribe": ControlServer._subscribe,
    "unsubscribe": ControlServer._unsubscribe,
    "events_subscribe": ControlServer._events_subscribe,
    "events_unsubscribe": ControlServer._events_unsubscribe,
    "prompt": ControlServer._prompt,
    "respond": ControlServer._respond,
    "screen": ControlServer._screen,
    "mark": ControlServer._mark,
    "move": lambda server, conn, req: server.session.move(req["finger"], req["position_m"]),
    "lease": ControlServer._lease,
    "release": ControlServer._release,
    "shutdown": ControlServer._stop,
    "stop": ControlServer._stop,
}
