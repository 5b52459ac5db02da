"""The control server and client: live changes to a running servo loop over a Unix socket.

The server runs in one thread that mostly waits in system calls (select,
recv), so it barely takes the GIL from the loop (see ../shared notes: a Unix
socket request thread left a FIFO loop's p99 under 10 us). Changes are not made
by this thread: it queues them, and the loop applies them at the start of its
next tick, then the reply names that tick. The socket is created with mode 0600.
"""

from __future__ import annotations

import contextlib
import logging
import os
import selectors
import socket
import threading
from pathlib import Path
from typing import Any

from hapticd import __version__
from hapticd import protocol as proto
from hapticd.servo import ServoLoop

APPLY_TIMEOUT_S = 2.0
log = logging.getLogger("hapticd.control")


class ControlServer:
    """Serves the control protocol for ``loop`` on the Unix socket at ``path``."""

    def __init__(self, loop: ServoLoop, path: str | Path) -> None:
        self.loop = loop
        self.path = Path(path)
        self._sel = selectors.DefaultSelector()
        self._stop = threading.Event()
        self._buffers: dict[socket.socket, bytearray] = {}
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self.path.exists():
            self.path.unlink()  # a stale socket from a crash
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)  # created 0600: only this user may connect
        try:
            sock.bind(str(self.path))
        finally:
            os.umask(old)
        sock.listen(8)
        sock.setblocking(False)
        self._sock = sock
        self._sel.register(sock, selectors.EVENT_READ, None)
        self._thread = threading.Thread(target=self._serve, name="hapticd-control", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for conn in list(self._buffers):
            self._drop(conn)
        if self._sock is not None:
            self._sel.unregister(self._sock)
            self._sock.close()
            self._sock = None
        self._sel.close()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    def _drop(self, conn: socket.socket) -> None:
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(conn)
        self._buffers.pop(conn, None)
        conn.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            for key, _ in self._sel.select(timeout=0.1):
                if key.fileobj is self._sock:
                    self._accept()
                else:
                    self._read(key.fileobj)  # type: ignore[arg-type]

    def _accept(self) -> None:
        assert self._sock is not None
        try:
            conn, _ = self._sock.accept()
        except BlockingIOError:
            return
        conn.setblocking(True)
        conn.settimeout(1.0)
        self._buffers[conn] = bytearray()
        self._sel.register(conn, selectors.EVENT_READ, None)
        self._send(conn, proto.greeting(__version__))

    def _send(self, conn: socket.socket, data: bytes) -> None:
        try:
            conn.sendall(data)
        except OSError:
            self._drop(conn)  # the client went away: harmless

    def _read(self, conn: socket.socket) -> None:
        try:
            data = conn.recv(65536)
        except OSError:
            data = b""
        if not data:
            self._drop(conn)
            return
        buf = self._buffers[conn]
        buf += data
        while b"\n" in buf:
            line, _, rest = bytes(buf).partition(b"\n")
            buf[:] = rest
            self._send(conn, self._handle(line))
        if len(buf) > proto.MAX_LINE_BYTES:
            buf.clear()
            self._send(conn, proto.error(None, "too_large", "request line too long; discarded"))

    def _handle(self, line: bytes) -> bytes:
        req_id = None
        try:
            req = proto.parse_request(line)
            req_id = req.get("id")
            return proto.ok(req_id, self._execute(req))
        except proto.ProtocolError as exc:
            return proto.error(req_id, exc.code, str(exc))
        except Exception as exc:  # a request must never take the daemon down
            return proto.error(req_id, "internal", f"{type(exc).__name__}: {exc}")

    def _execute(self, req: dict[str, Any]) -> Any:
        cmd = req["cmd"]
        loop = self.loop
        if cmd == "status":
            return loop.status()
        if cmd == "get":
            return {req["param"]: loop.get_param(req["param"])}
        if cmd == "stop":
            loop.request_stop("control: stop")
            return {"stopping": True}
        action: dict[str, Any] = {"cmd": cmd, "param": req.get("param"), "value": req.get("value")}
        done = loop.submit(action)
        if not done.wait(APPLY_TIMEOUT_S):
            raise proto.ProtocolError("timeout", "the loop did not reach a tick boundary in time")
        if done.error is not None:
            raise proto.ProtocolError("rejected", done.error)
        log.info(
            "control: %s applied at tick %d",
            " ".join(str(v) for v in action.values() if v is not None),
            done.tick,
        )
        return {"applied_at_tick": done.tick, **({"param": req["param"]} if cmd == "set" else {})}


class ControlClient:
    """A client for experiment scripts: ``ControlClient(path).set("stiffness_n_per_m", 60)``."""

    def __init__(self, path: str | Path, timeout_s: float = 5.0) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout_s)
        self.sock.connect(str(path))
        self._file = self.sock.makefile("rb")
        import json

        self._json = json
        self.greeting = json.loads(self._file.readline())
        self._next = 0

    def request(self, cmd: str, **args: Any) -> dict[str, Any]:
        self._next += 1
        msg = {"id": self._next, "cmd": cmd, **args}
        self.sock.sendall(proto.encode(msg))
        reply = self._json.loads(self._file.readline())
        return reply

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

    def stop(self) -> dict[str, Any]:
        return self.call("stop")

    def close(self) -> None:
        self._file.close()
        self.sock.close()

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
