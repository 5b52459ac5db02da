"""The control server under abuse: an exception in a reload, more clients than it serves,
no file descriptors left. It keeps serving and never spins."""

from __future__ import annotations

import itertools
import json
import socket
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from hapticd.cli import main
from hapticd.control import ControlClient
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from hapticd.protocol import ProtocolError
from tests.conftest import GRASP_PROFILE, IN_PROCESS, ROOT, wait_for


@pytest.fixture
def server(idle_server):
    return idle_server


@pytest.mark.parametrize("exc", [RuntimeError("boom"), RecursionError("too deep")])
def test_an_unexpected_error_in_a_sighup_reload_is_reported_and_serving_goes_on(server, exc):
    def reload(path=None):
        raise exc

    server.session.reload = reload
    server.request_reload()
    wait_for(lambda: server.reloads, "the reload's outcome", timeout_s=5.0)
    assert server.reloads[0].startswith("reload rejected, the running profile stays:")
    assert type(exc).__name__ in server.reloads[0]
    assert server.serving
    with ControlClient(server.path, timeout_s=2.0) as c:
        assert c.status()["reloads"] == server.reloads


def _raw(path) -> socket.socket:
    """A bare connection to the control socket (the greeting left unread)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(5.0)
    s.connect(str(path))
    return s


def _lines(s: socket.socket) -> list[dict]:
    """Every line the server sent ``s`` until it closed it (bounded by the socket timeout)."""
    data = b""
    while chunk := s.recv(65536):
        data += chunk
    return [json.loads(line) for line in data.splitlines()]


def test_sixty_four_idle_connections_lock_nobody_out(server):
    """Connections that never send a request give up their places to new clients: with 64
    held, status still answers (before: the 33rd client on was refused, and the CLI said
    the daemon spoke protocol None)."""
    limit = server.max_clients
    held = [_raw(server.path) for _ in range(2 * limit)]
    try:
        with ControlClient(server.path, timeout_s=5.0) as c:
            assert c.status()["tick"] == 0
        # The oldest idle connections were told why and closed; the newest are still held.
        first = _lines(held[0])
        assert first[-1]["ok"] is False and first[-1]["error"]["code"] == "idle"
        assert server.clients <= limit
    finally:
        for s in held:
            s.close()


def test_busy_is_said_plainly_when_every_place_is_in_use(server, capsys):
    """32 clients that each hold a subscription: one more gets ``busy`` with the count, and
    the command line says the daemon is busy (not a protocol mismatch)."""
    limit = server.max_clients
    clients = [ControlClient(server.path, timeout_s=2.0) for _ in range(limit)]
    try:
        for c in clients:
            c.events_subscribe()
        with _raw(server.path) as extra:
            (reply,) = _lines(extra)
        assert reply["ok"] is False and reply["error"]["code"] == "busy"
        assert reply["error"]["clients"] == limit
        with pytest.raises(ProtocolError) as caught:
            ControlClient(server.path, timeout_s=2.0)
        assert caught.value.code == "busy"
        assert main(["status", "--socket", str(server.path)]) == 1
        err = capsys.readouterr().err
        assert f"the daemon is busy: {limit} clients connected" in err
        assert "protocol" not in err
        assert clients[0].status()["tick"] == 0  # the others are served
        clients.pop().close()
        wait_for(lambda: server.clients < limit, "the server to see the client go", timeout_s=5.0)
        with ControlClient(server.path, timeout_s=2.0) as again:
            assert again.status()["tick"] == 0
    finally:
        for c in clients:
            c.close()


@pytest.fixture
def quick_server(tmp_path):
    """A control server that gives a connection 0.3 s to send a complete request."""
    session = build_session(load_profile(GRASP_PROFILE), paced=False)
    srv = ControlServer(session, tmp_path / "q.sock", request_timeout_s=0.3)
    srv.start()
    try:
        yield srv
    finally:
        srv.close()


def test_a_connection_that_sends_no_complete_request_in_time_is_closed(quick_server):
    """Silent, or a line begun and never finished: told ``idle`` and closed within the
    timeout (plus the 0.1 s reaping period). A subscriber that is quiet stays, and so does
    a client between two requests."""
    path = quick_server.path
    with (
        _raw(path) as silent,
        _raw(path) as slow,
        ControlClient(path, timeout_s=5.0) as events,
        ControlClient(path, timeout_s=5.0) as between,
    ):
        slow.sendall(b'{"cmd": "sta')
        events.events_subscribe()
        between.status()
        t0 = time.monotonic()
        for s in (silent, slow):
            lines = _lines(s)
            assert lines[-1]["error"]["code"] == "idle", lines
            assert "0.3 s" in lines[-1]["error"]["message"]
        assert time.monotonic() - t0 < 3.0
        time.sleep(0.6)
        assert events.status()["tick"] == 0
        assert between.status()["tick"] == 0
        assert quick_server.idle_closed == 2


_EMFILE_CHILD = textwrap.dedent(
    """
    import os, resource, sys, time
    from hapticd.daemon.server import ControlServer
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile

    session = build_session(load_profile(sys.argv[2]), paced=False)
    server = ControlServer(session, sys.argv[1])
    calls = [0]
    inner = server._accept
    def counting():
        calls[0] += 1
        inner()
    server._accept = counting
    server.start()
    # Use up every file descriptor this process may have.
    open_now = len(os.listdir("/proc/self/fd"))
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    resource.setrlimit(resource.RLIMIT_NOFILE, (open_now + 8, hard))
    held = []
    try:
        while True:
            held.append(os.dup(0))
    except OSError:
        pass
    print("ready", flush=True)
    sys.stdin.readline()  # the parent has connected: accept() now fails with EMFILE
    calls[0] = 0
    time.sleep(1.0)
    print("calls", calls[0], flush=True)
    for fd in held:
        os.close(fd)
    deadline = time.monotonic() + 5
    while not server.clients and time.monotonic() < deadline:
        time.sleep(0.01)
    print("accepted", server.clients, flush=True)
    sys.stdin.readline()
    server.close()
    """
)


@pytest.mark.timing("counts accept() retries over a 1 s window")
def test_out_of_file_descriptors_the_server_backs_off_instead_of_spinning(tmp_path):
    """accept() failing with EMFILE left the listener readable: the control thread spun
    at 100% CPU. Counted over 1 s: a few retries, not thousands (a 1 s window, so this
    touches wall-clock time; the bound is loose by a factor of 10)."""
    sock = tmp_path / "hapticd.sock"
    child = subprocess.Popen(
        [sys.executable, "-c", _EMFILE_CHILD, str(sock), str(GRASP_PROFILE)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    client.settimeout(10.0)
    try:
        assert child.stdout.readline().strip() == "ready", child.stderr.read()
        client.connect(str(sock))  # queued: the child cannot accept it
        child.stdin.write("go\n")
        child.stdin.flush()
        calls = int(child.stdout.readline().split()[1])
        assert calls <= 1.0 / 0.1 * 10, f"{calls} accept() attempts in 1 s: spinning"
        assert child.stdout.readline().split() == ["accepted", "1"]
        greeting = json.loads(client.makefile("rb").readline())
        assert "protocol" in greeting
        child.stdin.write("done\n")
        child.stdin.flush()
        _out, err = child.communicate(timeout=10)
    finally:
        client.close()
        if child.poll() is None:
            child.kill()
            child.communicate()
    assert child.returncode == 0, err
    assert err.count("cannot accept a control client") == 1, err


def test_a_service_notification_out_of_file_descriptors_is_not_an_exception(monkeypatch):
    """STOPPING=1 is sent on every way out of `hapticd run`: it must not raise there."""
    import errno

    from hapticd.daemon import sdnotify

    def no_fds(*args, **kwargs):
        raise OSError(errno.EMFILE, "Too many open files")

    monkeypatch.setattr(sdnotify.socket, "socket", no_fds)
    assert sdnotify.notify("STOPPING=1", {"NOTIFY_SOCKET": "/run/systemd/notify"}) is False


@pytest.mark.timing("the reload limit is per second of the paced loop's wall-clock time")
def test_a_reload_storm_is_served_one_reload_a_second(tmp_path):
    """Reloads pipelined by two clients all get their replies, but the loop applies at most
    one a second (docs/control.md): a storm slows the replies, not the loop (before: 2,324
    reloads in 15 s, each a tick's worth of work and a swap)."""
    session = build_session(load_profile(GRASP_PROFILE, IN_PROCESS), paced=True, duration_s=30.0)
    server = ControlServer(session, tmp_path / "r.sock")
    server.start()
    runner = threading.Thread(target=session.run, name="test-loop")
    runner.start()
    try:
        with ControlClient(server.path, timeout_s=10.0) as a, _raw(server.path) as b:
            # The storm begins once the loop runs: its start (real-time settings, the
            # collection) may fall behind on a busy machine, and a loop that re-anchors
            # counts fewer ticks a second.
            wait_for(
                lambda: a.status()["tick"], "the loop's first 500 ticks", until=lambda t: t >= 500
            )
            b.sendall(b'{"id": 1, "cmd": "reload"}\n' * 3)
            ticks = [a.reload()["applied_at_tick"] for _ in range(2)]
            replies = b.makefile("rb")
            replies.readline()  # the greeting
            for _ in range(3):
                reply = json.loads(replies.readline())
                assert reply["ok"], reply
                ticks.append(reply["result"]["applied_at_tick"])
        ticks.sort()
        gaps = [b - a for a, b in itertools.pairwise(ticks)]
        # 1 s apart at 1 kHz; a loop that fell behind re-anchors, so fewer ticks may pass.
        assert min(gaps) >= 500, ticks
        assert server.deferred >= 4
    finally:
        session.loop.request_stop("test over")
        runner.join(timeout=10)
        server.close()


@pytest.mark.parametrize("cmd", [["set"], {"reload": 1}, ["enable", "record_start"]])
def test_a_command_of_the_wrong_type_naming_a_limited_one_gets_its_error(server, cmd):
    """The rate limit looks at a line's command before it is served: one that is not a
    string (here naming limited commands) is answered as the bad request it is, and the
    connection goes on."""
    with _raw(server.path) as s:
        replies = s.makefile("rb")
        replies.readline()  # the greeting
        s.sendall(json.dumps({"id": 1, "cmd": cmd}).encode() + b"\n")
        s.sendall(b'{"id": 2, "cmd": "get", "param": "mass_kg"}\n')
        first, second = (json.loads(replies.readline()) for _ in range(2))
    assert first["id"] == 1 and first["error"]["code"] == "bad_request"
    assert second["id"] == 2 and second["ok"]


def test_a_reply_left_by_an_interrupted_request_is_not_taken_for_the_next_ones(server):
    """A request whose wait was interrupted (Ctrl-C between sending and reading) leaves its
    reply on the connection; the next request skips it and gets its own (before: each
    later request got the reply of the one before, so a runner's restore after Ctrl-C set
    the stiffness and took the stiffness's reply for the allocator's)."""
    with ControlClient(server.path, timeout_s=10.0) as c:
        c.timeout_s = 0.0  # the request is sent, and its wait ends before its reply comes
        with pytest.raises(TimeoutError):
            c.get("mass_kg")
        c.timeout_s = 10.0
        assert c.get("stiffness_n_per_m") == 60.0
        assert c.get("allocator") == "if"
        assert c.status()["tick"] == 0
