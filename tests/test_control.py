"""The control protocol and server: every error path, fuzzing, and changes at tick boundaries."""

import json
import os
import random
import socket
import stat
import threading
import time

import numpy as np
import pytest

from hapticd import recording
from hapticd.control import ControlClient, ControlServer
from hapticd.profile import load_profile
from hapticd.protocol import MAX_LINE_BYTES, ProtocolError, parse_request
from hapticd.runner import build_session
from tests.conftest import GRASP_PROFILE


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
        (b'{"cmd": "set", "param": "allocator", "value": "magic"}', "bad_value"),
        (b"x" * (MAX_LINE_BYTES + 1), "too_large"),
        (b"\xff\xfe", "malformed"),
    ],
)
def test_bad_requests_are_named(line, code):
    with pytest.raises(ProtocolError) as exc:
        parse_request(line)
    assert exc.value.code == code


def test_good_requests_are_normalised():
    req = parse_request(b'{"id": 7, "cmd": "set", "param": "friction", "value": [0.8, 0.6]}')
    assert req["value"] == (0.8, 0.6) and req["id"] == 7


@pytest.fixture
def live(tmp_path):
    """A paced grasp run serving its control socket in a thread: session, socket, recording, out."""
    sock = tmp_path / "hapticd.sock"
    rec = tmp_path / "live.hrec"
    session = build_session(
        load_profile(GRASP_PROFILE), paced=True, duration_s=4.0, record_path=rec
    )
    server = ControlServer(session, sock)
    server.start()
    out = {}
    runner = threading.Thread(target=lambda: out.update(summary=session.run()), name="test-loop")
    runner.start()
    try:
        yield session, sock, rec, out
    finally:
        session.loop.request_stop("test over")
        runner.join(timeout=10)
        server.close()


def wait_for_tick(client, tick, limit_s=5.0):
    deadline = time.monotonic() + limit_s
    while client.status()["tick"] < tick and time.monotonic() < deadline:
        time.sleep(0.02)


def test_socket_is_private_and_greets_with_versions(live):
    _, sock, _, _ = live
    assert stat.S_IMODE(os.stat(sock).st_mode) == 0o600
    with ControlClient(sock) as c:
        assert c.greeting["protocol"] == 1 and "hapticd" in c.greeting
        st = c.status()
        assert st["rate_hz"] == 1000 and st["fault"] is None and st["stages"][0] == "contact"


def test_a_change_lands_at_a_tick_boundary_and_in_the_recording(live, caplog):
    caplog.set_level("INFO")
    session, sock, rec, _ = live
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
    session.loop.request_stop("done")
    time.sleep(0.2)
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
    deadline = time.monotonic() + 5
    while "summary" not in out and time.monotonic() < deadline:
        time.sleep(0.02)
    assert out["summary"]["end_reason"] == "control: shutdown"
    for dev in session.devices:
        np.testing.assert_array_equal(dev.last_force, 0)
