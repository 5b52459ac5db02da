"""The service: sd_notify messages, the default socket path (the unit: test_service_unit)."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hapticd.control import default_socket_path
from hapticd.daemon import sdnotify
from hapticd.daemon.server import ControlServer, SocketInUseError
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from tests.conftest import GRASP_PROFILE, ROOT, wait_for


def _listen(path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(str(path))
    s.settimeout(0.05)
    return s


def _collect(s: socket.socket, until: float) -> list[str]:
    got = []
    while time.monotonic() < until:
        with contextlib.suppress(TimeoutError):
            got.append(s.recv(4096).decode())
    return got


def test_daemon_tells_systemd_ready_status_watchdog_and_stopping(tmp_path):
    with _listen(tmp_path / "notify") as s:
        env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "200000"}
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "hapticd",
                "run",
                str(GRASP_PROFILE),
                "--no-realtime",
                "-q",
                "--socket",
                str(tmp_path / "c.sock"),
                # Not the loop's own 0.1 s watchdog under test (tests/test_safety.py): a
                # loaded machine stalled this run 135 ms, and it ended with a fault.
                "--set",
                "safety.watchdog_s=2.0",
            ],
            cwd=ROOT,
            env=env,
            stderr=subprocess.PIPE,
        )
        got: list[str] = []

        def heard() -> list[str]:
            with contextlib.suppress(TimeoutError):
                got.append(s.recv(4096).decode())
            return got

        # Events, not a span of wall-clock time: 10 pings (one every 0.1 s for a 0.2 s
        # watchdog) and a status line (one a second) after READY.
        try:
            wait_for(
                heard,
                "10 watchdog pings and a status line",
                until=lambda g: (
                    sum(m == "WATCHDOG=1" for m in g) >= 10
                    and any(m.startswith("STATUS=") for m in g)
                ),
                timeout_s=30,
                poll_s=0,
            )
        except BaseException:
            proc.kill()
            proc.communicate()
            raise
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
        got += _collect(s, time.monotonic() + 0.2)
    assert proc.returncode == 0, err
    ready = [m for m in got if "READY=1" in m]
    assert len(ready) == 1 and f"MAINPID={proc.pid}" in ready[0]
    assert got.index(ready[0]) < min(i for i, m in enumerate(got) if m == "WATCHDOG=1") + 2
    status = [m for m in got if m.startswith("STATUS=")]
    assert status and "1000 Hz" in status[-1] and "no fault" in status[-1]
    assert got[-1] == "STOPPING=1"


def test_watchdog_pings_stop_when_the_loop_stalls(tmp_path):
    ticks = {"n": 0}
    now = {"t": 0.0}
    with _listen(tmp_path / "n") as s:
        env = {"NOTIFY_SOCKET": str(tmp_path / "n"), "WATCHDOG_USEC": "1000000"}
        n = sdnotify.ServiceNotifier(lambda: ticks["n"], lambda: "ok", env, lambda: now["t"])
        sent = []
        for step in range(40):  # 4 s in 0.1 s steps; the loop stalls after 2 s
            now["t"] = step * 0.1
            if now["t"] < 2.0:
                ticks["n"] += 100
            n.poll()
            try:
                while True:
                    sent.append((now["t"], s.recv(4096).decode()))
            except TimeoutError:
                pass
    pings = [t for t, m in sent if m == "WATCHDOG=1"]
    assert pings and max(pings) < 2.0 + 0.51  # none once ticks stopped advancing
    assert sum(1 for _, m in sent if m.startswith("READY=1")) == 1


def test_nothing_follows_stopping(tmp_path):
    # The control thread may poll after the main thread said STOPPING=1: the
    # service manager must not see a watchdog ping after it.
    now = {"t": 0.0}
    with _listen(tmp_path / "n") as s:
        env = {"NOTIFY_SOCKET": str(tmp_path / "n"), "WATCHDOG_USEC": "200000"}
        ticks = {"n": 0}
        n = sdnotify.ServiceNotifier(lambda: ticks["n"], lambda: "ok", env, lambda: now["t"])
        sent = []
        for step in range(10):
            now["t"] = step * 0.1
            ticks["n"] += 100
            if step == 5:
                n.stopping()
            n.poll()
            try:
                while True:
                    sent.append(s.recv(4096).decode())
            except TimeoutError:
                pass
    assert "WATCHDOG=1" in sent[: sent.index("STOPPING=1")]
    assert sent[-1] == "STOPPING=1" and sent.count("STOPPING=1") == 1


def test_notify_without_a_service_manager_does_nothing():
    assert sdnotify.notify("READY=1", {}) is False
    n = sdnotify.ServiceNotifier(lambda: 1, lambda: "x", {})
    n.poll()
    assert not n.enabled and not n.ready


def test_notify_reaches_an_abstract_socket():
    name = f"hapticd-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.bind("\0" + name)
        assert sdnotify.notify("STATUS=hi", {"NOTIFY_SOCKET": "@" + name})
        assert s.recv(100) == b"STATUS=hi"


def test_default_socket_path_follows_the_environment(monkeypatch, tmp_path):
    for var in ("HAPTICD_SOCKET", "RUNTIME_DIRECTORY", "XDG_RUNTIME_DIR"):
        monkeypatch.delenv(var, raising=False)
    assert str(default_socket_path()) == f"/tmp/hapticd-{os.getuid()}/control.sock"
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/run/user/1000")
    assert str(default_socket_path()) == "/run/user/1000/hapticd/control.sock"
    monkeypatch.setenv("RUNTIME_DIRECTORY", "/run/hapticd")
    assert str(default_socket_path()) == "/run/hapticd/control.sock"
    monkeypatch.setenv("HAPTICD_SOCKET", str(tmp_path / "x.sock"))
    assert default_socket_path() == tmp_path / "x.sock"


def test_the_recording_directory_follows_the_environment_the_profile_and_the_flag(
    monkeypatch, tmp_path, grasp_data, write_profile
):
    from hapticd.daemon.session import record_directory
    from hapticd.recording.files import state_directory

    for var in ("STATE_DIRECTORY", "XDG_STATE_HOME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert state_directory() == tmp_path / "home" / ".local" / "state" / "hapticd"
    monkeypatch.setenv("XDG_STATE_HOME", "/x/state")
    assert state_directory() == Path("/x/state/hapticd")
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/hapticd:/other")
    assert state_directory() == Path("/var/lib/hapticd")
    profile = load_profile(GRASP_PROFILE)
    assert record_directory(profile) == Path("/var/lib/hapticd")
    grasp_data["recording"] = {"directory": "recordings"}
    profile = load_profile(write_profile(grasp_data))
    assert record_directory(profile) == tmp_path / "recordings"  # beside the profile
    assert record_directory(profile, tmp_path / "flag") == tmp_path / "flag"


def test_a_live_socket_is_not_stolen_and_a_stale_one_is_replaced(tmp_path):
    path = tmp_path / "run" / "c.sock"
    sessions = [build_session(load_profile(GRASP_PROFILE), paced=False) for _ in range(2)]
    first = ControlServer(sessions[0], path)
    first.start()
    try:
        assert (path.parent.stat().st_mode & 0o777) == 0o700
        with pytest.raises(SocketInUseError, match="another hapticd is serving"):
            ControlServer(sessions[1], path).start()
    finally:
        first.close()
    # A socket file left by a crashed daemon (nobody listening) is replaced.
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()
    second = ControlServer(sessions[1], path)
    second.start()
    second.close()
    assert not path.exists()


def test_a_manager_that_does_not_read_never_blocks_a_notification(tmp_path):
    """The control thread sends these between requests: a notification socket whose queue
    is full (a manager that stopped reading) drops the message instead of blocking the
    control thread for good (before: status went unanswered once ~10 pings queued)."""
    path = tmp_path / "notify"
    env = {"NOTIFY_SOCKET": str(path)}
    sent: list[bool] = []
    sender = threading.Thread(
        target=lambda: sent.extend(sdnotify.notify("WATCHDOG=1", env) for _ in range(1000))
    )
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as manager:
        manager.bind(str(path))
        sender.start()
        sender.join(timeout=10)
        blocked = sender.is_alive()
    sender.join(timeout=5)  # the manager's socket is closed: a blocked send fails now
    assert not blocked, f"blocked after {len(sent)} notifications"
    assert sent[0] is True and sent[-1] is False  # the queue filled; nothing waited
