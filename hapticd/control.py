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
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from hapticd import protocol as proto

# Where the per-user fallback directory lives (a seam for the tests).
TMP_DIR = Path("/tmp")
# The installed service's socket (systemd's RuntimeDirectory=hapticd; `hapticd service
# unit`): clients find it when they have no socket of their own (a seam for the tests).
SERVICE_SOCKET = Path("/run/hapticd/control.sock")


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


def client_socket_path() -> Path:
    """Where a client looks for the daemon unless told: ``default_socket_path()`` when
    $HAPTICD_SOCKET or $RUNTIME_DIRECTORY names it or a socket is there (your own daemon),
    else the installed service's socket (SERVICE_SOCKET) when it exists, else the default
    (whose absence the connection then reports)."""
    own = default_socket_path()
    env = os.environ
    if env.get("HAPTICD_SOCKET") or env.get("RUNTIME_DIRECTORY") or os.path.lexists(own):
        return own
    return SERVICE_SOCKET if os.path.lexists(SERVICE_SOCKET) else own


def _check_group_dir(d: Path, gid: int, create: bool) -> None:
    """The directory a daemon shares with group ``gid`` (``--socket-group``): made 0700,
    then given to the group with mode 0750 (group: enter and list; nobody else
    anything) when absent. One that existed before is never changed (it may be a home
    directory, or another program's): it must already be a directory (not a symbolic
    link) of this user and of group ``gid``, mode 0750 or tighter with the group able to
    enter. Checked and changed through one descriptor opened without following a link,
    so nothing can be swapped in between."""
    made = False
    if create:
        with contextlib.suppress(FileExistsError):
            os.mkdir(d, 0o700)
            made = True
    try:
        fd = os.open(d, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        if os.path.islink(d):
            problem = f"is a symbolic link (to {os.readlink(d)}), not a directory"
        else:
            problem = f"cannot be opened as a directory ({exc.strerror or exc})"
        raise UnsafeSocketDirError(f"unsafe socket directory {d}: it {problem}") from None
    try:
        st = os.fstat(fd)
        if st.st_uid != os.getuid():
            raise UnsafeSocketDirError(
                f"unsafe socket directory {d}: it belongs to uid {st.st_uid}, not to uid "
                f"{os.getuid()}, so another user could control the socket; remove it or "
                "choose another socket with --socket"
            )
        mode = stat.S_IMODE(st.st_mode)
        if not made:
            if st.st_gid != gid or mode & 0o027 or not mode & 0o010:
                raise UnsafeSocketDirError(
                    f"socket directory {d} existed before (group {st.st_gid}, mode "
                    f"{mode:04o}): --socket-group shares only a directory hapticd makes, or "
                    f"one already of group {gid} with mode 0750, and never changes another; "
                    "give --socket a path in a directory that does not exist yet (hapticd "
                    f"makes it 0750 for the group), or, if sharing {d} is what you mean, "
                    f"chgrp {gid} {d} && chmod 750 {d}"
                )
            return
        try:
            os.fchown(fd, -1, gid)
            os.fchmod(fd, 0o750)
        except PermissionError:
            os.rmdir(d)  # made here: leave nothing behind
            raise PermissionError(
                f"cannot give the socket directory {d} to group {gid}: this user is not in "
                "that group (id -Gn lists yours)"
            ) from None
    finally:
        os.close(fd)


def share_socket(path: str | Path, gid: int) -> None:
    """Let group ``gid`` connect to the daemon's socket at ``path``: group ``gid``, mode
    0660 (it was bound 0600, so it was never open to more than this user)."""
    os.chown(path, -1, gid, follow_symlinks=False)
    os.chmod(path, 0o660)


def _check_service_dir(d: Path) -> None:
    """The installed service's socket directory, as a client checks it: a directory, not a
    symbolic link, that nobody but its owner can add to (systemd makes it under /run,
    which only root can write)."""
    try:
        st = os.lstat(d)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode) or st.st_mode & 0o022:
        if stat.S_ISLNK(st.st_mode):
            what = "a symbolic link"
        elif not stat.S_ISDIR(st.st_mode):
            what = "not a directory"
        else:
            what = f"of mode {stat.S_IMODE(st.st_mode):04o}"
        raise UnsafeSocketDirError(
            f"unsafe socket directory {d}: it is {what}, so another user could plant a "
            "socket there; the service's RuntimeDirectory= makes it a directory of mode 0750"
        )


def ownership_problem(
    path: str | Path, uid: int, mode_bits: int, *, regular: bool = False
) -> str | None:
    """Why ``path`` could be in another user's hands, as the words after "it" ("is a symbolic
    link (to X), not a directory", "is not a directory", "belongs to uid N, not to uid M",
    "has mode 0777"), or None when it is a directory (``regular``: a regular file), not a
    symbolic link, of uid ``uid``, with none of ``mode_bits`` set. Read with lstat, so
    nothing is followed or opened (a FIFO cannot block); FileNotFoundError when absent."""
    st = os.lstat(path)
    kind = "a regular file" if regular else "a directory"
    if stat.S_ISLNK(st.st_mode):
        return f"is a symbolic link (to {os.readlink(path)}), not {kind}"
    if not (stat.S_ISREG if regular else stat.S_ISDIR)(st.st_mode):
        return f"is not {kind}"
    if st.st_uid != uid:
        return f"belongs to uid {st.st_uid}, not to uid {uid}"
    if st.st_mode & mode_bits:
        return f"has mode {stat.S_IMODE(st.st_mode):04o}"
    return None


def check_socket_dir(
    path: str | Path, *, create: bool = False, uid: int | None = None, group: int | None = None
) -> None:
    """Make sure nobody else controls the directory of the socket ``path``.

    For hapticd's own directories ($XDG_RUNTIME_DIR/hapticd, /tmp/hapticd-UID), as
    ssh-agent and tmux check theirs: not a symbolic link, a directory, owned by ``uid``
    (default: this process's), no access for others and no writing for the group (0700,
    or 0750 when a daemon shares it with ``--socket-group``). ``create`` (the daemon)
    makes it with mode 0700 when absent. Any other directory was chosen by the user
    (--socket, $HAPTICD_SOCKET, systemd's RuntimeDirectory=) and is only created; the
    installed service's (SERVICE_SOCKET's) must be one nobody else can add to. With
    ``group`` (a daemon sharing its socket: ``--socket-group``) any directory is checked
    and shared with that group only (mode 0750). Raises UnsafeSocketDirError saying what
    is wrong and what to do.
    """
    uid = os.getuid() if uid is None else uid
    d = Path(os.path.abspath(Path(path).parent))
    if group is not None:
        if create:
            d.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        _check_group_dir(d, group, create)
        return
    if d == Path(os.path.abspath(SERVICE_SOCKET.parent)) and not create:
        _check_service_dir(d)
        return
    if d not in _own_socket_dirs(uid):
        if create:
            d.mkdir(mode=0o700, parents=True, exist_ok=True)
        return
    if create:
        with contextlib.suppress(FileExistsError):
            os.mkdir(d, 0o700)  # not its parents: $XDG_RUNTIME_DIR and /tmp must exist
    try:
        # Group r-x (0750) is a daemon's --socket-group share: the group can enter, not write.
        problem = ownership_problem(d, uid, 0o027)
    except FileNotFoundError:
        return  # the client's connect() then says no daemon is there
    if problem is None:
        return
    fix = (
        "remove it (after a look at what it is) and start hapticd again, or choose another "
        "socket with --socket or $HAPTICD_SOCKET"
    )
    if problem.startswith("has mode"):
        problem += "; it must be 0700 (only you) or 0750 (a group may enter, not write)"
        fix = f"chmod 700 {d}, or remove it"
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
        self.path = Path(path) if path is not None else client_socket_path()
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
                try:
                    return json.loads(line)
                except ValueError:
                    shown = line[:60].decode("utf-8", "replace")
                    raise proto.ProtocolError(
                        "malformed",
                        f"{self.path}: the daemon sent a line that is not JSON: {shown!r}",
                    ) from None
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
        """Send ``cmd`` and return its reply. A reply to an earlier request whose wait was
        interrupted (Ctrl-C, a timeout) is skipped: it is not this one's."""
        self._next += 1
        try:
            self.sock.sendall(proto.encode({"id": self._next, "cmd": cmd, **args}))
        except (BrokenPipeError, ConnectionResetError):
            raise self._closed_by_daemon() from None
        while True:
            msg = self._line()
            if "telemetry" in msg:
                self.telemetry.append(msg["telemetry"])
                continue
            if proto.is_event(msg):
                self.pending_events.append(msg)
                continue
            rid = msg.get("id")
            if isinstance(rid, int) and not isinstance(rid, bool) and rid < self._next:
                continue
            return msg

    def _closed_by_daemon(self) -> Exception:
        """Why the daemon closed this connection, as an exception to raise: its last line
        (``idle``: closed for sending no request in time) as a ProtocolError, else a
        ConnectionError saying the daemon closed it."""
        with contextlib.suppress(OSError, ValueError):
            while True:
                msg = self._line(0.05)
                if not isinstance(msg, dict):
                    continue
                err = msg.get("error")
                if msg.get("ok") is False and isinstance(err, dict) and msg.get("id") is None:
                    return proto.ProtocolError(
                        str(err.get("code", "error")), str(err.get("message", "closed"))
                    )
        return ConnectionError(
            f"{self.path}: the daemon closed the connection (it closes one that sends no "
            "request soon after connecting, or the run ended); connect again"
        )

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

    def screen(self, screen: Mapping[str, Any] | None) -> dict[str, Any]:
        """Set what the subject's screen shows besides the prompt (docs/control.md, "The
        subject's screen": ``state``, ``text``, ``practice``, ``progress``, ``seconds``,
        ``correct``, ``scene``), or clear it (None). Subscribers get a ``screen`` event."""
        return self.call("screen", screen=None if screen is None else dict(screen))

    def respond(self, prompt_id: int, choice: str) -> dict[str, Any]:
        """Answer the current prompt ``prompt_id`` with ``choice``; ProtocolError
        ``no_prompt`` when another or none is current, ``bad_value`` for a choice it does
        not offer."""
        return self.call("respond", prompt=prompt_id, choice=choice)

    def mark(self, text: str) -> dict[str, Any]:
        """Have the daemon stamp ``text`` (1 to 200 printable characters) with its current
        tick and publish it: a ``mark`` event, on the LSL marker stream too (``--lsl``);
        the result's ``tick`` is the tick it was stamped with."""
        return self.call("mark", text=text)

    def move(self, finger: str | int, position_m: Sequence[float]) -> dict[str, Any]:
        """Send finger ``finger``'s (name or index) virtual device towards ``position_m``
        (3 numbers, m, world frame); the result's ``target_m`` is where it goes (inside its
        workspace). ProtocolError ``rejected`` for a device that is not virtual."""
        return self.call("move", finger=finger, position_m=[float(c) for c in position_m])

    def lease(self, subject: str) -> dict[str, Any]:
        """Hold the daemon for an experiment on ``subject`` (this process's pid named):
        other connections' set, reload, record_start, record_stop and prompt are refused
        until ``release`` or this connection closes. ProtocolError ``leased`` (naming the
        holder's subject and process) when another connection holds it."""
        return self.call("lease", subject=subject, pid=os.getpid())

    def release(self) -> dict[str, Any]:
        """Give the daemon's lease back (``{"released": false}`` if this did not hold it)."""
        return self.call("release")

    def stop(self) -> dict[str, Any]:
        return self.call("shutdown")

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
