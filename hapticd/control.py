"""The control client for experiment scripts, and where the daemon's socket lives.

Imports only the standard library: an experiment script that talks to a
running hapticd loads no numpy, pydantic or yaml. The protocol is in
``hapticd.protocol`` (docs/control.md).
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import select
import socket
import stat
import struct
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from hapticd import protocol as proto

# Where the per-user fallback directory lives (a seam for the tests).
TMP_DIR = Path("/tmp")


class UnsafeSocketDirError(PermissionError):
    """The control socket's directory is one another user could control."""


def _own_socket_dirs(uid: int) -> list[Path]:
    """The directories hapticd makes for its socket (and so checks): $XDG_RUNTIME_DIR/hapticd
    and TMP_DIR/hapticd-UID."""
    dirs = [TMP_DIR / f"hapticd-{uid}"]
    if os.environ.get("XDG_RUNTIME_DIR"):
        dirs.append(Path(os.environ["XDG_RUNTIME_DIR"]) / "hapticd")
    return [Path(os.path.abspath(d)) for d in dirs]


def default_socket_path() -> Path:
    """Where the control socket lives unless told: $HAPTICD_SOCKET, the service's runtime
    directory ($RUNTIME_DIRECTORY, set by systemd's RuntimeDirectory=), $XDG_RUNTIME_DIR,
    or /tmp/hapticd-UID."""
    env = os.environ
    if env.get("HAPTICD_SOCKET"):
        return Path(env["HAPTICD_SOCKET"])
    if env.get("RUNTIME_DIRECTORY"):
        return Path(env["RUNTIME_DIRECTORY"].split(":")[0]) / "control.sock"
    if env.get("XDG_RUNTIME_DIR"):
        return Path(env["XDG_RUNTIME_DIR"]) / "hapticd" / "control.sock"
    return TMP_DIR / f"hapticd-{os.getuid()}" / "control.sock"


def check_socket_dir(path: str | Path, *, create: bool = False, uid: int | None = None) -> None:
    """Make sure nobody else controls the directory of the socket ``path``.

    For hapticd's own directories ($XDG_RUNTIME_DIR/hapticd, /tmp/hapticd-UID), as
    ssh-agent and tmux check theirs: not a symbolic link, a directory, owned by ``uid``
    (default: this process's), no access for group or others. ``create`` (the daemon)
    makes it with mode 0700 when absent. Any other directory was chosen by the user
    (--socket, $HAPTICD_SOCKET, systemd's RuntimeDirectory=) and is only created.
    Raises UnsafeSocketDirError saying what is wrong and what to do.
    """
    uid = os.getuid() if uid is None else uid
    d = Path(os.path.abspath(Path(path).parent))
    if d not in _own_socket_dirs(uid):
        if create:
            d.mkdir(mode=0o700, parents=True, exist_ok=True)
        return
    if create:
        with contextlib.suppress(FileExistsError):
            os.mkdir(d, 0o700)  # not its parents: $XDG_RUNTIME_DIR and /tmp must exist
    try:
        st = os.lstat(d)
    except FileNotFoundError:
        return  # the client's connect() then says no daemon is there
    fix = (
        "remove it (after a look at what it is) and start hapticd again, or choose another "
        "socket with --socket or $HAPTICD_SOCKET"
    )
    if stat.S_ISLNK(st.st_mode):
        problem = f"is a symbolic link (to {os.readlink(d)}), not a directory"
    elif not stat.S_ISDIR(st.st_mode):
        problem = "is not a directory"
    elif st.st_uid != uid:
        problem = f"belongs to uid {st.st_uid}, not to uid {uid}"
    elif st.st_mode & 0o077:
        problem = f"has mode {stat.S_IMODE(st.st_mode):04o}; it must be 0700 (only you)"
        fix = f"chmod 700 {d}, or remove it"
    else:
        return
    raise UnsafeSocketDirError(
        f"unsafe socket directory {d}: it {problem}, so another user could control the "
        f"socket; {fix}"
    )


class NoDaemonError(ConnectionError):
    """Nothing serves the control socket: no file there, or a stale one."""


def _connect(path: Path, timeout_s: float) -> socket.socket:
    """A connected socket with ``timeout_s`` on every operation. The connect itself blocks
    (a busy daemon's full accept queue is waited out, up to ``timeout_s``) rather than
    failing at once with EAGAIN as a non-blocking connect does on a Unix socket."""
    deadline = time.monotonic() + timeout_s
    while True:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        left = max(deadline - time.monotonic(), 0.001)
        # A blocking connect on a Unix socket waits up to the send timeout for queue room.
        sec = int(left)
        sock.setsockopt(
            socket.SOL_SOCKET,
            socket.SO_SNDTIMEO,
            struct.pack("ll", sec, int((left - sec) * 1e6)),
        )
        try:
            sock.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError) as exc:
            sock.close()
            what = "no socket at" if isinstance(exc, FileNotFoundError) else "nothing serves"
            raise NoDaemonError(f"is hapticd running? ({what} {path})") from None
        except (BlockingIOError, InterruptedError):
            sock.close()
            if time.monotonic() >= deadline:
                raise TimeoutError(
                    f"{path}: the daemon accepted no connection within {timeout_s:g} s"
                ) from None
            time.sleep(0.005)
            continue
        except OSError:
            sock.close()
            raise
        sock.settimeout(timeout_s)
        return sock


class ControlClient:
    """A client for experiment scripts::

    with ControlClient() as hd:          # the default socket path
        hd.set("stiffness_n_per_m", 60)
        hd.record_start("s01-trial-07.hrec")   # in the daemon's recording directory
        for ev in hd.events(["button_down"]):  # the loop's events, in order
            ...

    ``timeout_s`` bounds connecting and waiting for each reply (TimeoutError).
    """

    def __init__(self, path: str | Path | None = None, timeout_s: float = 5.0) -> None:
        self.path = Path(path) if path is not None else default_socket_path()
        self.timeout_s = timeout_s
        check_socket_dir(self.path)  # never talk through a directory someone else controls
        self.sock = _connect(self.path, timeout_s)
        self._buf = bytearray()
        try:
            self.greeting = self._line()
        except BaseException:
            self.sock.close()
            raise
        if not isinstance(self.greeting, dict):
            self.close()
            raise proto.ProtocolError("malformed", f"{self.path}: the greeting is not an object")
        refused = self.greeting.get("error")
        if self.greeting.get("ok") is False and isinstance(refused, dict):
            # Not a greeting: the daemon turned this connection away (busy) and closed it.
            self.close()
            raise proto.ProtocolError(
                str(refused.get("code", "error")),
                str(refused.get("message", "the daemon refused the connection")),
            )
        if self.greeting.get("protocol") != proto.PROTOCOL_VERSION:
            self.close()
            raise proto.ProtocolError(
                "version",
                f"{self.path} speaks protocol {self.greeting.get('protocol')!r}, "
                f"this client {proto.PROTOCOL_VERSION}",
            )
        self._next = 0
        self.telemetry: list[dict[str, Any]] = []  # frames that arrived while awaiting a reply
        # Events that arrived while awaiting a reply or a telemetry frame, in order.
        self.pending_events: collections.deque[dict[str, Any]] = collections.deque()

    def _line(self, timeout_s: float | None = -1.0) -> dict[str, Any]:
        """The next line from the daemon, parsed; TimeoutError after ``timeout_s`` s (default
        the client's timeout; None: wait as long as it takes), and the connection stays
        usable; ConnectionError when the daemon closed it."""
        if timeout_s is not None and timeout_s < 0:
            timeout_s = self.timeout_s
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            cut = self._buf.find(b"\n")
            if cut >= 0:
                line = bytes(self._buf[:cut])
                del self._buf[: cut + 1]
                return json.loads(line)
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise TimeoutError(f"{self.path}: nothing from the daemon in {timeout_s:g} s")
            ready, _, _ = select.select([self.sock], [], [], left)
            if not ready:
                continue
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError(f"{self.path}: the daemon closed the connection")
            self._buf += chunk

    def request(self, cmd: str, **args: Any) -> dict[str, Any]:
        self._next += 1
        self.sock.sendall(proto.encode({"id": self._next, "cmd": cmd, **args}))
        while True:
            msg = self._line()
            if "telemetry" in msg:
                self.telemetry.append(msg["telemetry"])
                continue
            if proto.is_event(msg):
                self.pending_events.append(msg)
                continue
            return msg

    def call(self, cmd: str, **args: Any) -> Any:
        reply = self.request(cmd, **args)
        if not reply.get("ok"):
            err = reply.get("error", {})
            raise proto.ProtocolError(
                err.get("code", "error"), err.get("message", "request failed")
            )
        return reply["result"]

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def set(self, param: str, value: Any) -> dict[str, Any]:
        return self.call("set", param=param, value=value)

    def get(self, param: str) -> Any:
        return self.call("get", param=param)[param]

    def record_start(self, path: str | Path, overwrite: bool = False) -> dict[str, Any]:
        """Record every tick to ``path``: a name in the daemon's recording directory (or an
        absolute path inside it). The result's ``path`` is where the file is."""
        return self.call("record_start", path=str(path), overwrite=overwrite)

    def record_stop(self) -> dict[str, Any]:
        return self.call("record_stop")

    def reload(self, profile: str | Path | None = None) -> dict[str, Any]:
        args = {} if profile is None else {"profile": str(Path(profile).absolute())}
        return self.call("reload", **args)

    def subscribe(self, rate_hz: float = 30.0) -> dict[str, Any]:
        return self.call("subscribe", rate_hz=rate_hz)

    def next_telemetry(self) -> dict[str, Any]:
        """The next telemetry frame (after ``subscribe``)."""
        if self.telemetry:
            return self.telemetry.pop(0)
        while True:
            msg = self._line()
            if "telemetry" in msg:
                return msg["telemetry"]
            if proto.is_event(msg):
                self.pending_events.append(msg)

    def events_subscribe(self, kinds: Sequence[str] | None = None) -> dict[str, Any]:
        """Receive the loop's events (hapticd.events; all kinds, or those named in ``kinds``)
        from the tick the result names (``tick``) on."""
        args = {} if kinds is None else {"kinds": list(kinds)}
        return self.call("events_subscribe", **args)

    def events_unsubscribe(self) -> dict[str, Any]:
        return self.call("events_unsubscribe")

    def next_event(self, timeout_s: float | None = None) -> dict[str, Any]:
        """The next event (after ``events_subscribe``): a dict with ``event``, ``tick``, ``t``
        and the fields its kind carries (docs/control.md). Waits up to ``timeout_s`` s (None:
        as long as it takes) and then raises TimeoutError; ConnectionError when the daemon
        closed the connection (the run ended, or this client fell too far behind)."""
        if self.pending_events:
            return self.pending_events.popleft()
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            left = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            msg = self._line(left)
            if proto.is_event(msg):
                return msg
            if "telemetry" in msg:
                self.telemetry.append(msg["telemetry"])

    def events(
        self, kinds: Sequence[str] | None = None, *, timeout_s: float | None = None
    ) -> Iterator[dict[str, Any]]:
        """Subscribe to the loop's events (all kinds, or ``kinds``) and yield them in order
        until the daemon closes the connection (the run ended). ``timeout_s``: at most this
        long between two events, then TimeoutError (None: no limit)."""
        self.events_subscribe(kinds)
        while True:
            try:
                ev = self.next_event(timeout_s)
            except ConnectionError:
                return
            yield ev

    def prompt(self, prompt_id: int, question: str, choices: Sequence[str]) -> dict[str, Any]:
        """Set the daemon's subject prompt (replacing any): ``prompt_id`` an int >= 0,
        ``question`` 1 to 200 printable characters, 2 to 4 distinct ``choices``
        ([a-z0-9_-]{1,16}). Subscribers get a ``prompt`` event; a ``respond`` answers it."""
        return self.call("prompt", prompt=prompt_id, question=question, choices=list(choices))

    def clear_prompt(self) -> dict[str, Any]:
        """Clear the daemon's subject prompt (a ``prompt`` event with ``prompt`` null)."""
        return self.call("prompt", prompt=None)

    def respond(self, prompt_id: int, choice: str) -> dict[str, Any]:
        """Answer the current prompt ``prompt_id`` with ``choice``; ProtocolError
        ``no_prompt`` when another or none is current, ``bad_value`` for a choice it does
        not offer."""
        return self.call("respond", prompt=prompt_id, choice=choice)

    def stop(self) -> dict[str, Any]:
        return self.call("shutdown")

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
