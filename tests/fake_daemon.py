"""A small stand-in for hapticd's control socket: the line protocol (hapticd.protocol) over
a Unix socket, answering ``status`` (with a ``prompt``), ``subscribe`` (telemetry frames
every ``period_s``), ``events_subscribe`` and ``respond`` as docs/control.md says a daemon
with prompts does, and recording every request it receives.

For testing what a client does with the prompt before a daemon has it. Every thread it
starts ends in ``close`` (bounded joins).
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
from pathlib import Path
from typing import Any

from hapticd import protocol as proto

# What a frame carries, enough for the page to draw a 50 mm cube and two fingertips.
SCENE = {
    "shape": "ConvexShape",
    "fixed": False,
    "bounds_m": [[-0.025] * 3, [0.025] * 3],
    "surfaces": [{"normal": [0, 0, 1], "offset_m": -0.025}],
    "finger_radii_m": [0.008, 0.008],
    "stiffness_n_per_m": 60.0,
    "damping_n_s_per_m": 0.5,
    "friction": [1.0, 0.8],
    "mass_kg": 0.06,
}


class FakeDaemon:
    """Serve ``path`` until ``close``. ``prompt``: the current prompt (a dict or None);
    ``requests``: every request line received, parsed, in order."""

    def __init__(self, path: Path, *, period_s: float = 0.02) -> None:
        self.path = path
        self.period_s = period_s
        self.prompt: dict[str, Any] | None = None
        self.screen: dict[str, Any] | None = None  # the subject's screen, as status shows it
        self.requests: list[dict[str, Any]] = []
        self.events: list[dict[str, Any]] = []  # the events it sent (response)
        self.tick = 0
        self.knows_prompt = True  # False: a daemon from before the prompt
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._conns: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(str(path))
        self._listener.listen(8)
        self._listener.settimeout(0.1)
        self._accept = threading.Thread(target=self._accept_loop, name="fake-daemon")
        self._accept.start()

    def set_prompt(self, prompt_id: int | None, question: str = "", choices=()) -> None:
        with self._lock:
            self.prompt = (
                None
                if prompt_id is None
                else {"id": prompt_id, "question": question, "choices": list(choices)}
            )

    def responds(self) -> list[dict[str, Any]]:
        with self._lock:
            return [r for r in self.requests if r.get("cmd") == "respond"]

    def close(self) -> None:
        self._stop.set()
        self._accept.join(timeout=5)
        self._listener.close()
        with self._lock:
            conns = list(self._conns)
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
        for t in self._threads:
            t.join(timeout=5)
        for c in conns:
            c.close()

    def __enter__(self) -> FakeDaemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(None)
            with self._lock:
                self._conns.append(conn)
            t = threading.Thread(target=self._serve, args=(conn,), name="fake-daemon-conn")
            self._threads.append(t)
            t.start()

    def _status(self) -> dict[str, Any]:
        with self._lock:
            self.tick += 10
            return {
                "tick": self.tick,
                "rate_hz": 1000,
                "paced": True,
                "fingers": ["thumb", "index"],
                "scene": SCENE,
                "allocator": "if",
                "prompt": self.prompt,
                "screen": self.screen,
            }

    def _frame(self) -> dict[str, Any]:
        with self._lock:
            self.tick += 1
            tick = self.tick
        return {
            "tick": tick,
            "t": tick / 1000,
            "object_pos": [0.0, 0.0, 0.0],
            "object_rot": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            "proxy_pos": [[-0.033, 0.0, 0.0], [0.033, 0.0, 0.0]],
            "device_pos": [[-0.03, 0.0, 0.0], [0.03, 0.0, 0.0]],
            "in_contact": [1, 1],
            "contact_force": [[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]],
            "rendered_force": [[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]],
            "residual_internal": 0.0,
            "residual_external": 0.0,
            "overruns": 0,
            "fault": None,
        }

    def _answer(self, req: dict[str, Any]) -> dict[str, Any]:
        cmd = req.get("cmd")
        if cmd == "status":
            return {"ok": True, "result": self._status()}
        if cmd in ("subscribe", "events_subscribe"):
            return {"ok": True, "result": {"subscribed": True}}
        if cmd == "respond" and self.knows_prompt:
            with self._lock:
                p = self.prompt
                if p is None or req.get("prompt") != p["id"]:
                    return {"ok": False, "error": {"code": "no_prompt", "message": "no such"}}
                if req.get("choice") not in p["choices"]:
                    return {"ok": False, "error": {"code": "bad_value", "message": "not offered"}}
                self.prompt = None
                ev = {"event": "response", "tick": self.tick, "prompt": p["id"]}
                ev["choice"] = req["choice"]
                self.events.append(ev)
            return {"ok": True, "result": {}}
        return {"ok": False, "error": {"code": "unknown_command", "message": f"{cmd!r}"}}

    def _serve(self, conn: socket.socket) -> None:
        """One client: requests answered in order; telemetry and events interleaved once it
        subscribed, until it or the fake closes."""
        send_lock = threading.Lock()
        done = threading.Event()
        streaming = threading.Event()
        sent_events: int | None = None  # None: not subscribed to events

        def send(obj: dict[str, Any]) -> None:
            with send_lock:
                conn.sendall(proto.encode(obj))

        def stream() -> None:
            nonlocal sent_events
            try:
                while not (done.wait(self.period_s) or self._stop.is_set()):
                    if streaming.is_set():
                        send({"telemetry": self._frame()})
                    with self._lock:
                        new = [] if sent_events is None else self.events[sent_events:]
                        if sent_events is not None:
                            sent_events = len(self.events)
                    for ev in new:
                        send(ev)
            except OSError:
                return

        streamer = threading.Thread(target=stream, name="fake-daemon-stream")
        try:
            send(json.loads(proto.greeting("fake").decode()))
            streamer.start()
            buf = b""
            while not self._stop.is_set():
                chunk = conn.recv(65536)
                if not chunk:
                    return
                buf += chunk
                while b"\n" in buf:
                    line, _, buf = buf.partition(b"\n")
                    req = json.loads(line)
                    with self._lock:
                        self.requests.append(req)
                        if req.get("cmd") == "events_subscribe":
                            sent_events = len(self.events)
                    reply = self._answer(req)
                    send({"id": req.get("id"), **reply})
                    if req.get("cmd") == "subscribe":
                        streaming.set()
        except OSError:
            return
        finally:
            done.set()
            if streamer.ident is not None:
                streamer.join(timeout=5)
