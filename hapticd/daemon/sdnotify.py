"""Service-manager notifications (systemd's sd_notify protocol, in our own few lines).

The protocol: one datagram of ``KEY=VALUE`` lines to the AF_UNIX socket named
in ``$NOTIFY_SOCKET`` (a leading ``@`` means the abstract namespace). Without
that variable (not started by systemd with Type=notify) every call does nothing.

``ServiceNotifier.poll`` runs in the control thread about every 0.1 s: READY=1
once the servo loop has ticked, STATUS= with its rate and faults about once a
second, and WATCHDOG=1 every half of ``$WATCHDOG_USEC``, but only while the
loop's tick count advances, so a stalled loop is restarted by systemd.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable


def notify(message: str, env: dict[str, str] | None = None) -> bool:
    """Send ``message`` (e.g. "READY=1") to the service manager; False if there is none."""
    addr = (env if env is not None else os.environ).get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):
        addr = "\0" + addr[1:]
    try:  # creating the socket fails too when the process is out of file descriptors
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            # Never wait: a manager that does not read (its queue holds ~10 datagrams)
            # must not stop the control thread, which sends these between requests.
            s.setblocking(False)
            s.sendto(message.encode("utf-8"), addr)
    except OSError:
        return False
    return True


class ServiceNotifier:
    """Tells the service manager about the loop: ``ticks()`` is its tick count and
    ``status()`` a one-line status text."""

    def __init__(
        self,
        ticks: Callable[[], int],
        status: Callable[[], str],
        env: dict[str, str] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.env = dict(os.environ if env is None else env)
        self.enabled = bool(self.env.get("NOTIFY_SOCKET"))
        self._ticks = ticks
        self._status = status
        self._clock = clock
        usec = self.env.get("WATCHDOG_USEC", "")
        pid = self.env.get("WATCHDOG_PID", "")
        mine = not pid or pid == str(os.getpid())
        self.watchdog_s = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 and mine else None
        self.ready = False
        self._last_ticks = -1
        self._next_watchdog = 0.0
        self._next_status = 0.0
        self._stopped = False
        # poll runs in the control thread, stopping in the main one: the lock keeps
        # a last WATCHDOG=1 from following STOPPING=1.
        self._lock = threading.Lock()

    def poll(self) -> None:
        if not self.enabled:
            return
        with self._lock:
            if not self._stopped:
                self._poll()

    def _poll(self) -> None:
        now = self._clock()
        ticks = self._ticks()
        if not self.ready and ticks > 0:
            self.ready = True
            notify(f"READY=1\nSTATUS={self._status()}\nMAINPID={os.getpid()}", self.env)
            self._next_status = now + 1.0
        if self.ready and now >= self._next_status:
            notify(f"STATUS={self._status()}", self.env)
            self._next_status = now + 1.0
        if self.watchdog_s is not None and now >= self._next_watchdog:
            if ticks > self._last_ticks:  # alive: the loop moved since the last ping
                notify("WATCHDOG=1", self.env)
            self._last_ticks = ticks
            self._next_watchdog = now + self.watchdog_s

    def stopping(self) -> None:
        """Send STOPPING=1, the last message: later polls send nothing."""
        if not self.enabled:
            return
        with self._lock:
            self._stopped = True
            notify("STOPPING=1", self.env)
