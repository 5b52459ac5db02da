"""The control protocol and server: every error path, fuzzing, and changes at tick boundaries."""

import contextlib
import itertools
import json
import os
import random
import re
import shutil
import socket
import stat
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from hapticd import protocol as proto
from hapticd import recording
from hapticd.control import ControlClient
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from hapticd.protocol import MAX_LINE_BYTES, ProtocolError, parse_request
from tests.conftest import GRASP_PROFILE, IN_PROCESS, ServerHold, wait_for, wait_for_tick


@pytest.mark.parametrize(
    ("line", "code"),
    [
        (b"{not json", "malformed"),
        (b"[1, 2]", "malformed"),
        (b'{"cmd": "explode"}', "unknown_command"),
        (b'{"cmd": "get", "param": "colour"}', "unknown_param"),
        (b'{"cmd": "set", "param": "stiffness_n_per_m"}', "malformed"),
        (b'{"cmd": "set", "param": "stiffness_n_per_m", "value": -1}', "out_of_range"),
        (b'{"cmd": "set", "param": "stiffness_n_per_m", "value": "stiff"}', "bad_value"),
        (b'{"cmd": "set", "param": "stiffness_n_per_m", "value": NaN}', "bad_value"),
        (b'{"cmd": "set", "param": "friction", "value": [0.2, 0.5]}', "bad_value"),
        (b'{"cmd": "set", "param": "allocator", "value": "no such"}', "bad_value"),
        (b"x" * (MAX_LINE_BYTES + 1), "too_large"),
        (b"\xff\xfe", "malformed"),
        (b'{"cmd": "set", "param": "force_limit_n", "value": 100}', "out_of_range"),
        (b'{"cmd": "set", "param": "actuated_directions", "value": [[[0, 0]]]}', "bad_value"),
        (b'{"cmd": "set", "param": "actuated_directions", "value": [[[0, 0, 0]]]}', "bad_value"),
        (b'{"cmd": "set", "param": "actuated_directions", "value": "z"}', "bad_value"),
        (b'{"cmd": "record_start"}', "bad_value"),
        (b'{"cmd": "record_start", "path": ""}', "bad_value"),
        (b'{"cmd": "record_start", "path": "a\\u0000b"}', "bad_value"),
        (b'{"cmd": "record_start", "path": "/x.hrec", "overwrite": "yes"}', "bad_value"),
        (b'{"cmd": "reload", "profile": "configs/x.yaml"}', "bad_value"),
        (b'{"cmd": "subscribe", "rate_hz": 0}', "out_of_range"),
        (b'{"cmd": "subscribe", "rate_hz": 1e6}', "out_of_range"),
        (b'{"cmd": "subscribe", "rate_hz": true}', "bad_value"),
    ],
)
def test_bad_requests_are_named(line, code):
    with pytest.raises(ProtocolError) as exc:
        parse_request(line)
    assert exc.value.code == code


def test_good_requests_are_normalised():
    req = parse_request(b'{"id": 7, "cmd": "set", "param": "friction", "value": [0.8, 0.6]}')
    assert req["value"] == (0.8, 0.6) and req["id"] == 7


def test_socket_is_private_and_greets_with_versions(live):
    _, sock, _, _ = live
    assert stat.S_IMODE(os.stat(sock).st_mode) == 0o600
    with ControlClient(sock) as c:
        assert c.greeting["protocol"] == 1 and "hapticd" in c.greeting
        st = c.status()
        assert st["rate_hz"] == 1000 and st["fault"] is None and st["stages"][0] == "contact"
        assert st["passivity"] == {
            "enabled": False,
            "energy_j": [0.0, 0.0],
            "damping_n_s_per_m": [0.0, 0.0],
        }


def test_a_change_lands_at_a_tick_boundary_and_in_the_recording(live, caplog):
    caplog.set_level("INFO")
    session, sock, rec, out = live
    with ControlClient(sock) as c:
        wait_for_tick(c, 2700)  # in the pinch
        before = c.get("stiffness_n_per_m")
        with pytest.raises(ProtocolError, match=r"must be in"):
            c.set("stiffness_n_per_m", 1e9)
        assert c.get("stiffness_n_per_m") == before  # a rejected request changed nothing
        applied = c.set("stiffness_n_per_m", 2 * before)["applied_at_tick"]
        c.set("damping_n_s_per_m", 0)
        c.stop()
    # The loop records the change; the control thread, not the loop, logs it.
    events = [e for _, e in session.loop.events]
    assert f"control: set stiffness_n_per_m {2 * before}" in events
    assert "control: set damping_n_s_per_m 0.0" in events
    logged = [r for r in caplog.records if r.name == "hapticd.control"]
    assert logged and all(r.threadName == "hapticd-control" for r in logged)
    wait_for(lambda: out.get("summary"), "the run's end (recording closed)", until=bool)
    r = recording.read(rec)
    k = int(np.searchsorted(r["t"], applied * 1e-3 - 1e-9))
    f = np.linalg.norm(r["contact_force"][:, 0], axis=1)
    depth = np.linalg.norm(r["proxy_pos"][:, 0] - r["device_pos"][:, 0], axis=1)
    np.testing.assert_allclose(f[k - 5 : k] / depth[k - 5 : k], before, rtol=1e-9)
    np.testing.assert_allclose(f[k : k + 5] / depth[k : k + 5], 2 * before, rtol=1e-9)


def test_fuzzed_garbage_and_a_vanishing_client_harm_nothing(live):
    _, sock, _, _ = live
    rng = random.Random(1)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(3)
    s.connect(str(sock))
    f = s.makefile("rb")
    f.readline()  # greeting
    for _ in range(200):
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 80))).replace(b"\n", b" ")
        s.sendall(junk + b"\n")
        reply = json.loads(f.readline())
        assert reply["ok"] is False and reply["error"]["code"] in {"malformed", "unknown_command"}
    s.sendall(b'{"cmd": "set", "param": "stiff')  # half a request, then gone
    f.close()
    s.close()
    with ControlClient(sock) as c:  # the daemon still serves, unchanged
        assert c.status()["fault"] is None
        assert c.get("stiffness_n_per_m") == 60.0


def test_stop_ends_the_run_with_zero_force(live):
    session, sock, _, out = live
    with ControlClient(sock) as c:
        wait_for_tick(c, 200)
        assert c.stop() == {"stopping": True, "ramp_s": 0.05}
    wait_for(lambda: out.get("summary"), "the run's summary", until=bool, timeout_s=5)
    assert out["summary"]["end_reason"] == "control: shutdown"
    for dev in session.devices:
        np.testing.assert_array_equal(dev.last_force, 0)


def test_force_limit_and_actuation_change_live_and_bad_ones_change_nothing(live):
    _session, sock, rec, out = live
    with ControlClient(sock) as c:
        wait_for_tick(c, 2700)  # in the pinch
        k = c.set("force_limit_n", 0.4)["applied_at_tick"]
        assert c.get("force_limit_n") == [0.4, 0.4]
        dirs = c.get("actuated_directions")
        with pytest.raises(ProtocolError, match="per finger must stay") as exc:
            c.set("actuated_directions", [[[0, 0, 1]], [[0, 0, 1], [1, 0, 0]]])
        assert exc.value.code == "rejected"
        assert c.get("actuated_directions") == dirs
        new = [[[0.0, 0.0, 2.0]] * len(dirs[0]), [[3.0, 0.0, 0.0]] * len(dirs[1])]
        c.set("actuated_directions", new)
        assert c.get("actuated_directions")[0][0] == [0.0, 0.0, 1.0]  # normalised
        ticks = c.status()["tick"]
        wait_for_tick(c, ticks + 100)
        c.stop()
    wait_for(lambda: out.get("summary"), "the run's end (recording closed)", until=bool)
    r = recording.read(rec)
    after = np.rint(r["t"] * 1000) >= k
    mags = np.linalg.norm(r["device_force"], axis=2)
    assert mags[~after].max() > 0.4  # the limit matters here
    assert mags[after].max() <= 0.4 + 1e-12


def test_recording_starts_and_stops_over_the_socket(live, tmp_path):
    _session, sock, _, _ = live
    extra = tmp_path / "trial-01.hrec"
    with ControlClient(sock) as c:
        wait_for_tick(c, 100)
        with pytest.raises(ProtocolError, match="already recording"):
            c.record_start(extra)
        assert not extra.exists()  # a refused start leaves no file behind
        first = c.record_stop()
        assert first["written"] == first["ticks"] > 50 and first["dropped"] == 0
        with pytest.raises(ProtocolError, match="not recording"):
            c.record_stop()
        extra.write_bytes(b"keep me")
        with pytest.raises(ProtocolError, match="exists; not overwriting") as exc:
            c.record_start(extra)
        assert exc.value.code == "recording" and extra.read_bytes() == b"keep me"
        start = c.record_start(extra, overwrite=True)["applied_at_tick"]
        wait_for_tick(c, start + 200)
        stop = c.record_stop()
        assert c.status()["recording"] is None
    r = recording.read(extra)
    ticks = np.rint(r["t"] * 1000).astype(int)
    assert ticks[0] == start and ticks[-1] == stop["applied_at_tick"] - 1
    assert r.ticks == stop["written"] == stop["ticks"]
    np.testing.assert_array_equal(np.diff(ticks), 1)


@pytest.mark.timing(
    "frames pile up at the rate the server streams them in wall-clock time; skipped frames "
    "need more than the socket buffers hold before the run ends"
)
def test_telemetry_streams_and_a_reader_that_stalls_blocks_no_one(live):
    _, sock, _, _ = live
    with ControlClient(sock) as watcher, ControlClient(sock) as other:
        wait_for_tick(other, 100)
        assert watcher.subscribe(50.0) == {"subscribed": True, "rate_hz": 50.0}
        frames = [watcher.next_telemetry() for _ in range(5)]
        assert all(b["tick"] > a["tick"] for a, b in itertools.pairwise(frames))
        assert len(frames[0]["force"]) == 2 and len(frames[0]["device_pos"][0]) == 3
        # Now 1 kHz of frames to a client that reads nothing for a second...
        watcher.subscribe(1000.0)
        start = other.status()["tick"]
        # ...for 1000 ticks, while another client is served all along.
        wait_for(other.status, "1000 ticks", until=lambda st: st["tick"] >= start + 1000)
        assert other.status()["fault"] is None
        reply = watcher.request("unsubscribe")  # frames in between are set aside
        assert reply["ok"] and reply["result"]["skipped_frames"] > 0


def test_the_loop_writes_one_gate_byte_per_tick_before_it_sleeps():
    session = build_session(load_profile(GRASP_PROFILE, IN_PROCESS), paced=True, duration_s=0.1)
    session.loop.realtime_settings = None
    r = session.loop.open_sleep_gate()
    try:
        session.run()
        got = os.read(r, 65536)
    finally:
        session.loop.close_sleep_gate()
        os.close(r)
    assert len(got) == session.loop.stats.ticks == 100
    assert session.loop.sleep_until > 0


@pytest.mark.timing(
    "the server's wait is bounded by the monotonic clock: the test checks when it returns"
)
def test_the_control_thread_waits_for_the_loop_to_sleep():
    import hapticd.daemon.server as control

    class FakeLoop:
        running, paced, sleep_until = True, True, 0.0
        stats = None

        def open_sleep_gate(self):
            self.r, self.w = os.pipe()
            os.set_blocking(self.r, False)
            return self.r

        def close_sleep_gate(self):
            os.close(self.w)

    loop = FakeLoop()
    gate = loop.open_sleep_gate()
    try:
        # No sleep announced: it gives up after WINDOW_MAX_WAIT_S, never sooner.
        t0 = time.monotonic()
        control.await_window(loop, gate)
        assert time.monotonic() - t0 >= control.WINDOW_MAX_WAIT_S

        # The loop announces a sleep 20 ms from now: the thread works only after that.
        def sleep_soon():
            time.sleep(0.02)
            loop.sleep_until = time.monotonic() + 0.5
            os.write(loop.w, b"\0")

        t = threading.Thread(target=sleep_soon, name="fake-loop")
        t0 = time.monotonic()
        t.start()
        control.await_window(loop, gate, max_wait_s=5.0)
        back = time.monotonic()
        t.join()
        assert 0.02 <= back - t0 < 5.0 and back < loop.sleep_until - control.WINDOW_S
        # Not running: no waiting at all.
        loop.running = False
        loop.sleep_until = 0.0
        t0 = time.monotonic()
        control.await_window(loop, gate, max_wait_s=5.0)
        assert time.monotonic() - t0 < 1.0
    finally:
        loop.close_sleep_gate()
        os.close(gate)


def test_every_command_of_the_protocol_has_a_server_handler():
    from hapticd import protocol
    from hapticd.daemon.server import _HANDLERS

    assert set(_HANDLERS) == set(protocol.COMMANDS)


# -- hostile clients: each case below was a crash, a hang or a wrong reply ---------------------


def _raw(sock_path):
    """A raw connection (greeting read) and a strict reader of its reply lines."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(10)
    s.connect(str(sock_path))
    f = s.makefile("rb")
    f.readline()

    def reply():
        line = f.readline()
        assert line.endswith(b"\n"), "the daemon closed the connection"
        return json.loads(line, parse_constant=lambda w: pytest.fail(f"reply holds {w}"))

    return s, f, reply


def test_error_replies_echo_the_request_id(live):
    _, sock, _, _ = live
    s, f, reply = _raw(sock)
    with s, f:
        s.sendall(
            b'{"id": 41, "cmd": "explode"}\n'
            b'{"id": "b", "cmd": "get", "param": "colour"}\n'
            b'{"id": 43.5, "cmd": "set", "param": "mass_kg", "value": -1}\n'
            b'{"id": 44, "cmd": "get", "param": "mass_kg"}\n'
        )
        got = [reply() for _ in range(4)]
    assert [r["id"] for r in got] == [41, "b", 43.5, 44]
    assert [r["ok"] for r in got] == [False, False, False, True]


def test_nan_ids_deep_nesting_and_wrong_types_are_request_errors(live):
    _, sock, _, _ = live
    s, f, reply = _raw(sock)
    with s, f:
        s.sendall(b'{"id": NaN, "cmd": "status"}\n')
        r = reply()  # strict JSON: a NaN echoed back would fail here
        assert r["id"] is None and r["error"]["code"] == "bad_value"
        s.sendall(b'{"id": 5, "cmd": "status", "x": ' + b"[" * 1000 + b"]" * 1000 + b"}\n")
        r = reply()
        assert r["error"]["code"] == "bad_request" and "nested too deeply" in r["error"]["message"]
        s.sendall(b"[" * 60_000 + b"\n")
        assert reply()["error"]["code"] in {"bad_request", "malformed"}
        s.sendall(b'{"id": 6, "cmd": "get", "param": ["mass_kg"]}\n')
        r = reply()
        assert r["id"] == 6 and r["error"]["code"] == "bad_request"
        s.sendall(b'{"id": [1], "cmd": "status"}\n')
        assert reply()["error"]["code"] == "bad_request"


def test_a_huge_line_gets_one_reply_and_its_tail_is_not_a_request(live):
    _, sock, _, _ = live
    s, f, reply = _raw(sock)
    with s, f:
        # 10 MB whose tail looks like a request: it must be discarded with the line.
        tail = b'{"id": "tail", "cmd": "shutdown"}'
        sender = threading.Thread(
            target=s.sendall, args=(b"x" * 10_000_000 + tail + b"\n",), name="big-sender"
        )
        sender.start()
        r = reply()
        sender.join(timeout=20)
        assert r["error"]["code"] == "too_large"
        s.sendall(b'{"id": "after", "cmd": "get", "param": "mass_kg"}\n')
        r = reply()
        assert r["id"] == "after" and r["ok"], r  # the next reply answers the next request
    with ControlClient(sock) as c:
        assert c.status()["fault"] is None  # and no shutdown came of the tail


def test_a_hundred_clients_connect_at_once(live):
    _, sock, _, _ = live
    barrier = threading.Barrier(100, timeout=20)
    results: list[object] = []

    def connect():
        try:
            barrier.wait()
            with ControlClient(sock, timeout_s=20) as c:
                results.append(c.get("mass_kg"))
        except Exception as exc:
            results.append(exc)

    threads = [threading.Thread(target=connect, name=f"client-{i}") for i in range(100)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    failures = [r for r in results if isinstance(r, Exception)]
    assert len(results) == 100 and not failures, failures[:3]


def test_a_pipelined_burst_does_not_make_other_clients_wait_for_all_of_it(live):
    """Order, not time: a burst and another client's request wait together (the server's
    thread is held meanwhile); when the other client's reply arrives, most of the burst
    must still be unanswered (each client is served a few requests per turn)."""
    _, sock, _, out = live
    hold = ServerHold(out["server"])
    burst = 1200  # about 55 KB: all of it fits in the socket's buffer at once
    a = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    a.settimeout(10)
    a.connect(str(sock))
    b, fb, reply_b = _raw(sock)
    with a, b, fb:
        got = b""
        while b"\n" not in got:  # the greeting
            got += a.recv(4096)
        got = got.partition(b"\n")[2]
        hold.hold()
        a.sendall(
            b"".join(b'{"id": %d, "cmd": "get", "param": "mass_kg"}\n' % i for i in range(burst))
        )
        b.sendall(b'{"id": "b", "cmd": "get", "param": "mass_kg"}\n')
        time.sleep(0.05)  # both are in the daemon's socket buffers
        hold.release()
        assert reply_b()["id"] == "b"
        a.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            while chunk := a.recv(1 << 20):
                got += chunk
        a.settimeout(10)
        answered = got.count(b"\n")
        while got.count(b"\n") < burst:  # the rest of the burst is answered too
            got += a.recv(1 << 20)
    assert answered < burst // 3, f"the other client waited for {answered} of the burst"


def test_reload_reads_only_small_regular_files_and_never_blocks(live, tmp_path):
    _, sock, _, _ = live
    fifo = tmp_path / "profile.fifo"
    os.mkfifo(fifo)
    big = tmp_path / "big.yaml"
    big.write_bytes(b"#" * (2 << 20))
    with ControlClient(sock, timeout_s=10) as c:
        for path, why in (
            ("/dev/zero", "not a regular file"),
            (fifo, "not a regular file"),
            (big, "at most 1048576 bytes"),
            (tmp_path, "not a regular file"),
        ):
            with pytest.raises(ProtocolError, match=why) as exc:
                c.reload(path)
            assert exc.value.code == "bad_profile" and str(path) in str(exc.value)
        assert c.status()["fault"] is None


def test_record_start_over_the_socket_stays_in_the_recording_directory(live, tmp_path):
    session, sock, _, _ = live
    outside = tmp_path.parent / f"{tmp_path.name}-outside.hrec"
    victim = tmp_path / "victim.txt"
    victim.write_bytes(b"precious")
    (tmp_path / "link.hrec").symlink_to(victim)
    with ControlClient(sock) as c:
        c.record_stop()
        with pytest.raises(ProtocolError, match="outside the recording directory") as exc:
            c.record_start(outside)
        assert exc.value.code == "recording" and not outside.exists()
        with pytest.raises(ProtocolError, match="symbolic link"):
            c.record_start("link.hrec", overwrite=True)
        assert victim.read_bytes() == b"precious"
        started = c.record_start("s01/trial-01.hrec")
        assert started["path"] == str(tmp_path / "s01" / "trial-01.hrec")
        wait_for_tick(c, started["applied_at_tick"] + 100)
        assert c.record_stop()["written"] >= 100
        # A recording whose directory is removed mid-run: status says so, and record_stop.
        started = c.record_start("s02/trial-01.hrec")
        shutil.rmtree(tmp_path / "s02")
        deadline = time.monotonic() + 5
        while c.status()["recording"]["error"] is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert "deleted while recording" in c.status()["recording"]["error"]
        with pytest.raises(ProtocolError, match="deleted while recording") as exc:
            c.record_stop()
        assert exc.value.code == "recording"
    assert session.record_dir == tmp_path


def test_the_readme_python_example_runs(live, tmp_path, monkeypatch):
    """The README's control example, as written, against a live daemon whose recording
    directory is tmp_path: it records where it says."""
    _, sock, _, _ = live
    from tests.conftest import ROOT

    readme = (ROOT / "README.md").read_text()
    start = readme.index("```python\nfrom hapticd.control import ControlClient")
    code = readme[start + len("```python\n") : readme.index("```", start + 10)]
    monkeypatch.setenv("HAPTICD_SOCKET", str(sock))
    with ControlClient(sock) as c:
        c.record_stop()  # the live run records from its start
    exec(compile(code, "README.md", "exec"), {})
    with ControlClient(sock) as c:
        assert c.status()["recording"]["path"] == str(tmp_path / "s01-trial-01.hrec")
        assert c.record_stop()["written"] > 0
    assert recording.read(tmp_path / "s01-trial-01.hrec").ticks > 0


def test_every_error_code_the_sources_use_is_declared_once_and_documented():
    """Error codes live in hapticd.protocol.ERRORS: every code a reply or a ProtocolError
    names in the sources is there, and docs/control.md lists every one of them."""
    root = Path(__file__).resolve().parents[1]
    used: set[str] = set()
    for path in (root / "hapticd").rglob("*.py"):
        text = path.read_text()
        used |= set(re.findall(r'ProtocolError\(\s*"([a-z_]+)"', text))
        used |= set(re.findall(r'proto\.error\(\s*[a-z_]+,\s*"([a-z_]+)"', text))
    assert {"malformed", "bad_value", "no_prompt", "rejected", "internal"} <= used
    assert used <= set(proto.ERRORS), sorted(used - set(proto.ERRORS))
    docs = (root / "docs" / "control.md").read_text()
    missing = [code for code in proto.ERRORS if f"`{code}`" not in docs]
    assert not missing, f"docs/control.md does not name {missing}"
    assert "unknown_command" in proto.BAD_REQUEST and "timeout" not in proto.BAD_REQUEST
