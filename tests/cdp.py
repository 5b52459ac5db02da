"""Headless Chromium driven over the DevTools protocol on a pipe (no WebSocket, no network).

``--remote-debugging-pipe`` makes Chromium read commands from fd 3 and write replies
and events to fd 4, each a JSON message ending in a NUL byte. Every wait here has a
deadline; ``close`` ends the browser and reaps it.
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import json
import os
import select
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "chromium", "chromium-browser")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-dev-shm-usage",
    "--no-proxy-server",
    "--remote-debugging-pipe",
)


def find_chromium() -> str | None:
    for name in CHROMIUM_CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


def _above(fd: int, lowest: int) -> int:
    """``fd`` moved to a number >= ``lowest`` (the old one closed)."""
    new = fcntl.fcntl(fd, fcntl.F_DUPFD, lowest)
    os.close(fd)
    return new


class CDPError(RuntimeError):
    """The browser answered a command with an error, or not in time."""


class Browser:
    """One headless Chromium and one page in it."""

    def __init__(
        self,
        exe: str,
        profile_dir: Path,
        width: int = 1400,
        height: int = 860,
        stderr: int | None = subprocess.DEVNULL,
    ) -> None:
        cmd_r, self._cmd_w = os.pipe()  # we write commands; Chromium reads its fd 3
        self._res_r, res_w = os.pipe()  # Chromium writes its fd 4; we read
        # Above 4, so that moving them onto 3 and 4 never closes one of them.
        cmd_r, res_w = (_above(fd, 10) for fd in (cmd_r, res_w))
        # bash puts the pipe ends on fds 3 and 4 (subprocess keeps fd numbers as they are;
        # dash takes no fd above 9 in a redirection).
        script = f'exec "$0" "$@" 3<&{cmd_r} 4>&{res_w} {cmd_r}<&- {res_w}>&-'
        args = [*FLAGS, f"--user-data-dir={profile_dir}", f"--window-size={width},{height}"]
        self.proc = subprocess.Popen(
            ["/bin/bash", "-c", script, exe, *args, "about:blank"],
            pass_fds=(cmd_r, res_w),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=stderr,
        )
        os.close(cmd_r)
        os.close(res_w)
        self._buf = b""
        self._events: list[str] = []  # events that came while waiting for a reply
        self._next = 0
        self.session: str | None = None
        self.width, self.height = width, height

    def _send(self, method: str, params: dict[str, Any] | None, session: str | None) -> int:
        self._next += 1
        msg: dict[str, Any] = {"id": self._next, "method": method, "params": params or {}}
        if session is not None:
            msg["sessionId"] = session
        os.write(self._cmd_w, json.dumps(msg).encode() + b"\0")
        return self._next

    def _read(self, deadline: float) -> dict[str, Any]:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CDPError("the browser sent nothing in time")
            ready, _, _ = select.select([self._res_r], [], [], left)
            if ready:
                chunk = os.read(self._res_r, 1 << 20)
                if not chunk:
                    raise CDPError("the browser closed its DevTools pipe")
                self._buf += chunk
        line, _, self._buf = self._buf.partition(b"\0")
        return json.loads(line)

    def call(
        self,
        method: str,
        params: dict[str, Any] | None = None,
        *,
        page: bool = True,
        timeout_s: float = 20.0,
    ) -> dict[str, Any]:
        """Send a command (to the page's session unless ``page`` is false) and return its
        result; the names of events that arrive meanwhile are kept for ``wait_event``."""
        want = self._send(method, params, self.session if page else None)
        deadline = time.monotonic() + timeout_s
        while True:
            msg = self._read(deadline)
            if msg.get("id") == want:
                if "error" in msg:
                    raise CDPError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if "method" in msg:
                self._events.append(msg["method"])

    def wait_event(self, method: str, timeout_s: float = 20.0) -> None:
        """Wait for the event ``method`` (one that came during a command counts too)."""
        deadline = time.monotonic() + timeout_s
        while method not in self._events:
            msg = self._read(deadline)
            if "method" in msg:
                self._events.append(msg["method"])
        self._events.remove(method)

    def open(self, url: str) -> None:
        """A new page at ``url``, this browser's page from now on, once it has loaded."""
        target = self.call("Target.createTarget", {"url": "about:blank"}, page=False)
        attached = self.call(
            "Target.attachToTarget", {"targetId": target["targetId"], "flatten": True}, page=False
        )
        self.session = attached["sessionId"]
        self.call(
            "Emulation.setDeviceMetricsOverride",
            {"width": self.width, "height": self.height, "deviceScaleFactor": 1, "mobile": False},
        )
        self.call("Page.enable")
        self._events.clear()
        self.call("Page.navigate", {"url": url})
        self.wait_event("Page.loadEventFired")

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (JSON-able)."""
        result = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        if "exceptionDetails" in result:
            raise CDPError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def click(self, selector: str) -> None:
        """A left click (press and release of the mouse, as a user's) at the middle of the
        element ``selector`` selects; CDPError if there is none or it is not shown."""
        rect = self.evaluate(
            f"(() => {{ const e = document.querySelector({json.dumps(selector)}); "
            "if (!e) return null; const r = e.getBoundingClientRect(); "
            "return [r.x + r.width / 2, r.y + r.height / 2, r.width * r.height]; })()"
        )
        if not rect or rect[2] <= 0:
            raise CDPError(f"nothing shown to click at {selector!r}")
        for kind in ("mousePressed", "mouseReleased"):
            self.call(
                "Input.dispatchMouseEvent",
                {"type": kind, "x": rect[0], "y": rect[1], "button": "left", "clickCount": 1},
            )

    def drag(self, start: tuple[float, float], end: tuple[float, float], steps: int = 10) -> None:
        """A left-button drag, as a user's: press at ``start`` (CSS px), move in ``steps``
        to ``end``, release there."""
        (x0, y0), (x1, y1) = start, end
        self.call(
            "Input.dispatchMouseEvent",
            {"type": "mousePressed", "x": x0, "y": y0, "button": "left", "clickCount": 1},
        )
        for k in range(1, steps + 1):
            x, y = x0 + (x1 - x0) * k / steps, y0 + (y1 - y0) * k / steps
            self.call(
                "Input.dispatchMouseEvent",
                {"type": "mouseMoved", "x": x, "y": y, "button": "left", "buttons": 1},
            )
        self.call(
            "Input.dispatchMouseEvent",
            {"type": "mouseReleased", "x": x1, "y": y1, "button": "left", "clickCount": 1},
        )

    def key(self, key: str, code: str | None = None, shift: bool = False) -> None:
        """A named key (``ArrowUp``, ...) pressed and released on the page."""
        params: dict[str, Any] = {"key": key, "code": code or key, "modifiers": 8 if shift else 0}
        for kind in ("rawKeyDown", "keyUp"):
            self.call("Input.dispatchKeyEvent", {"type": kind, **params})

    def press(self, key: str) -> None:
        """A key typed on the page (keydown and keyup of a one-character ``key``)."""
        for kind in ("keyDown", "keyUp"):
            self.call("Input.dispatchKeyEvent", {"type": kind, "key": key, "text": key})

    def screenshot(self, path: Path) -> Path:
        data = self.call("Page.captureScreenshot", {"format": "png"})["data"]
        path.write_bytes(base64.b64decode(data))
        return path

    def close(self) -> None:
        with contextlib.suppress(CDPError, OSError):
            self.call("Browser.close", page=False, timeout_s=5.0)
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
        os.close(self._cmd_w)
        os.close(self._res_r)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
