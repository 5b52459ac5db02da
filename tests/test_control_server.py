"""The control server under abuse: an exception in a reload, more clients than it serves,
no file descriptors left. It keeps serving and never spins."""

from __future__ import annotations

import itertools
import json
import logging
import os
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
from tests.conftest import GRASP_PROFILE, IN_PROCESS, ROOT, fill_every_place, wait_for


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
    """Every place held, by subscribers and by clients with a recent request: one more gets
    ``busy`` with the count, and the command line says the daemon is busy (not a protocol
    mismatch)."""
    limit = server.max_clients
    clients = fill_every_place(server)
    try:
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


def test_a_storm_of_turned_away_clients_writes_no_log_storm(server, caplog):
    """Clients turned away busy, many in a row: each is told ``busy``, and the log says so
    once for the storm with how many, not a line per client (before: one warning each,
    written in the server thread while the loop waited for the GIL)."""
    clients = fill_every_place(server)
    try:
        with caplog.at_level(logging.WARNING, logger="hapticd.control"):
            for _ in range(40):
                with _raw(server.path) as extra:
                    (reply,) = _lines(extra)
                assert reply["error"]["code"] == "busy"
        said = [r.getMessage() for r in caplog.records if "busy" in r.getMessage()]
        assert 1 <= len(said) <= 2, said  # the first at once; a second only past 1 s
        assert server.refused_busy == 40
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


# -- a service a lab's group shares -----------------------------------------------------------


def _reload_reply(path, profile) -> dict:
    """The reply to one ``reload`` of ``profile`` (None: the running profile's file)."""
    with ControlClient(path, timeout_s=5.0) as c:
        args = {} if profile is None else {"profile": str(profile)}
        return c.request("reload", **args)


@pytest.fixture
def shared_server(tmp_path):
    """A control server whose clients are not its user (the uid it compares the peer's
    SO_PEERCRED uid with is another), allowing reloads from tmp_path/allowed only."""
    allowed = tmp_path / "allowed"
    allowed.mkdir()
    session = build_session(load_profile(GRASP_PROFILE), paced=False)
    srv = ControlServer(session, tmp_path / "s.sock", reload_dirs=[allowed])
    srv.owner_uid = os.getuid() + 4242  # this test's client is another user to the daemon
    srv.start()
    try:
        yield srv, allowed
    finally:
        srv.close()


SECRET = "hunter2-not-for-the-group"


def test_a_client_not_the_daemons_user_reloads_only_from_the_allowed_directories(
    shared_server, tmp_path
):
    """A group member's reload of a file outside the allowed directories is refused, named
    as such, before anything is read: a path outright, one that climbs out with `..`, and a
    link inside the allowed directory to a file outside (before: any file the daemon could
    read was parsed, and its lines came back as unknown keys)."""
    srv, allowed = shared_server
    outside = tmp_path / "secret.yaml"
    outside.write_text(f"password: {SECRET}\n")
    (allowed / "link.yaml").symlink_to(outside)
    for profile in (outside, allowed / ".." / "secret.yaml", allowed / "link.yaml"):
        reply = _reload_reply(srv.path, profile)
        assert reply["ok"] is False, reply
        assert reply["error"]["code"] == "denied", reply
        assert str(allowed) in reply["error"]["message"]
        assert SECRET not in json.dumps(reply) and "password" not in json.dumps(reply)
    # Inside the allowed directory the file is read (and here refused as no profile).
    (allowed / "bad.yaml").write_text("name: x\n")
    assert _reload_reply(srv.path, allowed / "bad.yaml")["error"]["code"] == "bad_profile"


def test_an_error_reply_never_echoes_a_files_keys_or_values(shared_server, tmp_path, idle_server):
    """A profile with a secret in an unknown key: a client that is not the daemon's user
    is told the file, the count and the lines, not the key nor the value; the daemon's own
    user is told the key (a file it may read), but never the unknown key's value."""
    srv, allowed = shared_server
    bad = allowed / "secret.yaml"
    bad.write_text(f"name: x\nshadow_line: {SECRET}\nroot:$6$hash:19000: 1\n")
    reply = _reload_reply(srv.path, bad)
    text = json.dumps(reply)
    assert reply["error"]["code"] == "bad_profile", reply
    assert SECRET not in text and "shadow_line" not in text and "$6$hash" not in text
    message = reply["error"]["message"]
    assert str(bad) in message and "line(s) 2, 3" in message, message
    # The daemon's own user (the test's uid is the idle server's): the key, not its value.
    (tmp_path / "own.yaml").write_text(bad.read_text())
    own = _reload_reply(idle_server.path, tmp_path / "own.yaml")
    assert own["error"]["code"] == "bad_profile", own
    assert "shadow_line" in own["error"]["message"]
    assert SECRET not in json.dumps(own)


def _subscribed(path, n) -> list[ControlClient]:
    clients = []
    try:
        for _ in range(n):
            c = ControlClient(path, timeout_s=5.0)
            clients.append(c)
            c.events_subscribe()
    except BaseException:
        for c in clients:
            c.close()
        raise
    return clients


def test_subscribers_cannot_take_the_places_of_commands(server, capsys):
    """Every subscriber place held: status, ControlClient and `hapticd stop` are still
    served (before: 32 readers of events made each of them get `busy`); one subscription
    more is refused `busy`, its connection still serving commands."""
    subs = _subscribed(server.path, server.max_subscribers)
    try:
        with ControlClient(server.path, timeout_s=5.0) as c:
            assert c.status()["tick"] == 0
            with pytest.raises(ProtocolError) as caught:
                c.events_subscribe()
            assert caught.value.code == "busy"
            assert f"{server.max_subscribers} subscriptions" in str(caught.value)
            with pytest.raises(ProtocolError) as caught:
                c.subscribe(10.0)
            assert caught.value.code == "busy"
            assert c.get("stiffness_n_per_m") == 60.0
        assert main(["status", "--socket", str(server.path)]) == 0
        assert main(["stop", "--socket", str(server.path)]) == 0
        assert server.loop.stop_reason is not None
        assert server.subscribers == server.max_subscribers
    finally:
        for c in subs:
            c.close()


def _replies(s: socket.socket, n: int, deadline_s: float) -> list[dict]:
    """The next ``n`` lines from ``s``; fails the test if they do not all come within
    ``deadline_s`` s."""
    data = b""
    end = time.monotonic() + deadline_s
    while data.count(b"\n") < n:
        left = end - time.monotonic()
        if left <= 0:
            got = data.count(b"\n")
            pytest.fail(f"{got} of {n} replies within {deadline_s:g} s: {data!r}")
        s.settimeout(left)
        try:
            chunk = s.recv(65536)
        except TimeoutError:
            continue
        assert chunk, "the server closed the connection"
        data += chunk
    return [json.loads(line) for line in data.splitlines()[:n]]


@pytest.mark.timing("changes are rate-limited per second of wall-clock time")
def test_a_client_flooding_changes_cannot_starve_another_clients_disable_or_set(live):
    """One client pipelines 500 sets (10 s of the change limit); another's set, disable and
    set are answered within a second, in order, each set after at most a few of the
    flood's (before: the slot went to whichever connection the server looked at first,
    and the second client's disable got no reply for over 45 s)."""
    session, sock, _rec, _out = live
    with ControlClient(sock, timeout_s=5.0) as c:
        wait_for(lambda: c.status()["tick"], "the loop to run", until=lambda t: t >= 50)
    with _raw(sock) as flood, _raw(sock) as other:
        _replies(flood, 1, 5.0)  # the greetings
        _replies(other, 1, 5.0)
        flood.sendall(b'{"id": 0, "cmd": "set", "param": "stiffness_n_per_m", "value": 70}\n' * 500)
        time.sleep(0.1)  # the flood holds the change slot
        t0 = time.monotonic()
        other.sendall(
            b'{"id": 1, "cmd": "set", "param": "damping_n_s_per_m", "value": 1}\n'
            b'{"id": 2, "cmd": "disable"}\n'
            b'{"id": 3, "cmd": "set", "param": "damping_n_s_per_m", "value": 2}\n'
        )
        got = _replies(other, 3, 1.0)
        took = time.monotonic() - t0
    assert [r["id"] for r in got] == [1, 2, 3], got
    assert all(r["ok"] for r in got), got
    ticks = [r["result"]["applied_at_tick"] for r in got]
    assert ticks == sorted(ticks), ticks
    assert took < 1.0
    assert session.loop.param("damping_n_s_per_m") == 2.0


def test_disable_and_stop_are_never_rate_limited(tmp_path):
    """With a change limit of an hour, a set waits its turn but disable is served at once
    (before: disable shared the change slot with every set), and so is stop while another
    client's set waits: the loop stops."""
    session = build_session(load_profile(GRASP_PROFILE, IN_PROCESS), paced=True, duration_s=30.0)
    srv = ControlServer(session, tmp_path / "d.sock", rate_limits_s={"change": 3600.0})
    srv.start()
    runner = threading.Thread(target=session.run, name="test-loop")
    runner.start()
    try:
        with _raw(srv.path) as s:
            _replies(s, 1, 5.0)
            s.sendall(b'{"id": 1, "cmd": "set", "param": "damping_n_s_per_m", "value": 1}\n')
            assert _replies(s, 1, 5.0)[0]["ok"]
            s.sendall(b'{"id": 2, "cmd": "disable"}\n')
            (reply,) = _replies(s, 1, 2.0)
            assert reply["id"] == 2 and reply["ok"], reply
            with _raw(srv.path) as waiting, _raw(srv.path) as stopper:
                _replies(waiting, 1, 5.0)
                _replies(stopper, 1, 5.0)
                waiting.sendall(b'{"id": 3, "cmd": "set", "param": "damping_n_s_per_m", '
                                b'"value": 2}\n')  # fmt: skip
                stopper.sendall(b'{"id": 4, "cmd": "stop"}\n')
                (reply,) = _replies(stopper, 1, 2.0)
                assert reply["id"] == 4 and reply["ok"], reply
                runner.join(timeout=10)
                assert not runner.is_alive(), "stop did not end the loop"
    finally:
        session.loop.request_stop("test over")
        runner.join(timeout=10)
        srv.close()


def test_every_request_after_stop_gets_a_reply(live):
    """A reload and a set sent just after stop are answered `stopped` at once, and so is
    every request still waiting when the server closes (before: a reload about 1 ms after
    stop got no reply at all)."""
    session, sock, _rec, _out = live
    with _raw(sock) as s:
        _replies(s, 1, 5.0)
        s.sendall(b'{"id": 1, "cmd": "stop"}\n')
        time.sleep(0.001)
        s.sendall(
            b'{"id": 2, "cmd": "reload"}\n'
            b'{"id": 3, "cmd": "set", "param": "stiffness_n_per_m", "value": 70}\n'
            b'{"id": 4, "cmd": "status"}\n'
        )
        got = _replies(s, 4, 5.0)
    assert [r["id"] for r in got] == [1, 2, 3, 4], got
    assert got[0]["ok"] and got[3]["ok"], got
    for r in got[1:3]:
        assert r["error"]["code"] == "stopped", r
        assert "stopping" in r["error"]["message"]
    assert session.loop.param("stiffness_n_per_m") == 60.0


def test_requests_waiting_when_the_server_closes_are_answered(tmp_path):
    """Reloads waiting for their rate limit when the server closes each get `stopped`."""
    session = build_session(load_profile(GRASP_PROFILE), paced=False)
    srv = ControlServer(session, tmp_path / "w.sock", rate_limits_s={"reload": 3600.0})
    srv.start()
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\n")
    try:
        with _raw(srv.path) as s:
            _replies(s, 1, 5.0)
            line = json.dumps({"cmd": "reload", "profile": str(bad)})
            s.sendall(b"".join(f'{{"id": {i}, {line[1:]}\n'.encode() for i in (1, 2, 3)))
            assert _replies(s, 1, 5.0)[0]["error"]["code"] == "bad_profile"
            wait_for(lambda: srv.deferred, "the second reload to wait")
            srv.close()
            got = _replies(s, 2, 5.0)
    finally:
        srv.close()
    assert [(r["id"], r["error"]["code"]) for r in got] == [(2, "stopped"), (3, "stopped")]


def test_a_client_closed_for_idling_is_told_so(quick_server):
    """A ControlClient that idled past the request timeout gets a ProtocolError `idle`
    saying the daemon closed the idle connection, and the command line prints it (before:
    a bare BrokenPipeError)."""
    c = ControlClient(quick_server.path, timeout_s=5.0)
    try:
        wait_for(lambda: quick_server.idle_closed, "the server to close the idle client")
        with pytest.raises(ProtocolError) as caught:
            c.status()
        assert caught.value.code == "idle"
        assert "closed this idle connection" in str(caught.value)
    finally:
        c.close()


def test_a_burst_of_connections_is_accepted_a_few_a_round_in_the_loops_sleep(tmp_path):
    """Twenty clients connecting at once: the server waits for the loop's sleep (its I/O
    window) before it accepts, and takes at most ACCEPTS_PER_ROUND of them before it
    serves the others' requests and waits again, so a storm of clients delays replies,
    not ticks."""
    from hapticd.daemon import server as server_mod

    session = build_session(load_profile(GRASP_PROFILE, IN_PROCESS), paced=False)
    srv = ControlServer(session, tmp_path / "d.sock")
    seen: list[str] = []
    gate = threading.Event()
    window, accept = srv._await_io_window, srv._accept

    def waiting_window() -> None:
        gate.wait(10)  # the first round waits until the burst is queued
        seen.append("window")
        window()

    def counted_accept() -> bool:
        took = accept()
        if took:
            seen.append("accept")
        return took

    srv._await_io_window, srv._accept = waiting_window, counted_accept
    srv.start()
    clients: list[socket.socket] = []
    try:
        n = 20
        assert n <= server_mod.BACKLOG
        clients = [_raw(srv.path) for _ in range(n)]
        gate.set()
        wait_for(lambda: seen.count("accept"), "every client accepted", until=lambda k: k == n)
    finally:
        for c in clients:
            c.close()
        srv.close()
    assert seen[0] == "window"  # nothing accepted before the loop's sleep
    runs, run = [], 0
    for what in seen:
        if what == "accept":
            run += 1
        elif run:
            runs.append(run)
            run = 0
    runs.append(run)
    assert max(runs) == server_mod.ACCEPTS_PER_ROUND, runs
