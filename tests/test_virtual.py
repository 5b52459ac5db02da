"""The virtual device (backend virtual): a handle moved over the control protocol (``move``)
at a bounded speed inside its workspace, rendered by the daemon like any device (contact,
events, recording); and driven from the view page in headless Chromium (a drag, the keys),
the contact event and the force shown on the page."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hapticd_drivers.base import DeviceError, DeviceState
from hapticd_drivers.virtual import VirtualDevice

from hapticd import protocol as proto
from hapticd import recording
from hapticd.control import ControlClient
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from tests import cdp
from tests.conftest import ROOT, wait_for
from tests.test_view import view  # noqa: F401  (a fixture)

VIRTUAL = ROOT / "configs" / "rehearse-virtual.yaml"
CONTACT_X = 0.025 + 0.008  # the cube's half size + the fingertip's radius, m


def test_the_handle_follows_its_target_at_its_speed_inside_its_workspace():
    now = [0.0]
    dev = VirtualDevice(max_speed_m_per_s=0.1, workspace_radius_m=0.05, clock=lambda: now[0])
    dev.open()
    state = DeviceState()
    dev.read_state(state)
    assert state.position.tolist() == [0.0, 0.0, 0.0]
    assert dev.move_to([0.03, 0.0, 0.04]) == pytest.approx((0.03, 0.0, 0.04))
    path = []
    for k in range(1, 101):
        now[0] = k * 1e-3
        dev.read_state(state)
        path.append(state.position.copy())
    steps = np.linalg.norm(np.diff(np.array(path), axis=0), axis=1)
    assert steps.max() <= 0.1 * 1e-3 * (1 + 1e-9)  # never faster than 0.1 m/s
    assert np.linalg.norm(path[-1]) == pytest.approx(0.01, rel=1e-6)  # 0.1 s at 0.1 m/s
    np.testing.assert_allclose(state.velocity, [0.06, 0.0, 0.08], rtol=1e-6)
    now[0] = 1.0  # a long pause moves it no further than MAX_STEP_S allows, then it arrives
    for k in range(1, 20):
        now[0] = 1.0 + k * 0.05
        dev.read_state(state)
    np.testing.assert_allclose(state.position, [0.03, 0.0, 0.04], atol=1e-12)
    # A target outside the workspace is brought onto its edge.
    assert np.linalg.norm(dev.move_to([1.0, 1.0, 0.0])) == pytest.approx(0.05)


@pytest.mark.parametrize("bad", [[np.nan, 0, 0], [0, 0], "abc", [0, np.inf, 0]])
def test_a_target_that_is_not_three_finite_numbers_is_refused(bad):
    dev = VirtualDevice()
    with pytest.raises(DeviceError, match="virtual"):
        dev.move_to(bad)
    assert dev.target == (0.0, 0.0, 0.0)


def test_forces_are_checked_as_firmware_would_and_kept_while_enabled():
    dev = VirtualDevice(max_force_n=2.0)
    dev.open()
    dev.write_force(np.array([1.0, 0.0, 0.0]))
    assert dev.last_force.tolist() == [0.0, 0.0, 0.0]  # forces off
    dev.enable_forces(True)
    dev.write_force(np.array([1.0, 0.0, 0.0]))
    assert dev.last_force.tolist() == [1.0, 0.0, 0.0]
    with pytest.raises(DeviceError, match="above its limit"):
        dev.write_force(np.array([3.0, 0.0, 0.0]))


@contextlib.contextmanager
def virtual_daemon(sock: Path, record_dir: Path) -> Iterator[ControlServer]:
    """A paced run of the virtual rehearsal profile serving ``sock`` in a thread (it has no
    wall-clock faults: no hardware), its kernels loaded from the run's cache (auto)."""
    profile = load_profile(VIRTUAL)
    session = build_session(profile, paced=True, duration_s=120.0, record_dir=record_dir)
    session.loop.realtime_settings = None
    server = ControlServer(session, sock)
    server.start()
    runner = threading.Thread(target=session.run, name="test-loop")
    runner.start()
    try:
        wait_for(lambda: session.loop.stats.ticks > 10, "the loop to tick", timeout_s=20)
        yield server
    finally:
        session.loop.request_stop("test over")
        runner.join(timeout=10)
        server.close()


def _events(client: ControlClient, kind: str, finger: int, timeout_s: float) -> dict:
    def next_one():
        with contextlib.suppress(TimeoutError):
            ev = client.next_event(0.1)
            if ev.get("event") == kind and ev.get("finger") == finger:
                return ev
        return None

    return wait_for(next_one, f"a {kind} event of finger {finger}", timeout_s=timeout_s)


def test_a_virtual_device_moved_over_the_socket_touches_the_cube_and_is_recorded(tmp_path):
    sock = tmp_path / "d.sock"
    with virtual_daemon(sock, tmp_path) as server, ControlClient(sock) as c:
        c.events_subscribe(["contact_begin", "contact_end"])
        c.record_start("virtual.hrec")
        got = c.move("thumb", [-(CONTACT_X - 0.004), 0.0, 0.0])  # 4 mm into the face
        assert got["finger"] == "thumb"
        assert got["target_m"] == pytest.approx([-(CONTACT_X - 0.004), 0.0, 0.0])
        began = _events(c, "contact_begin", 0, 10)
        wait_for(lambda: c.status()["in_contact"] == [True, False], "thumb alone in contact")
        # Once there: k x, 60 N/m over 4 mm, pushing the thumb out of the cube (-x).
        wait_for(
            lambda: float(server.loop.frame.contact_force[0][0]),
            "the thumb's contact force",
            until=lambda f: f == pytest.approx(-60.0 * 0.004, rel=0.02),
            timeout_s=5,
        )
        c.move(0, [-0.06, 0.0, 0.0])  # back where it started (by index)
        ended = _events(c, "contact_end", 0, 10)
        assert ended["tick"] > began["tick"]
        stopped = c.record_stop()
        # A target beyond its workspace (75 mm about its origin, at x = -60 mm) stops there.
        far = c.move("index", [0.5, 0.0, 0.0])["target_m"]
        assert far == pytest.approx([0.06 + 0.075, 0.0, 0.0])
    rec = recording.read(stopped["path"])
    x = rec["device_pos"][:, 0, 0]
    assert x.max() == pytest.approx(-(CONTACT_X - 0.004), abs=1e-6)  # it got there
    assert rec["in_contact"][:, 0].any() and not rec["in_contact"][:, 1].any()
    speed = np.abs(np.diff(x)) * 1000.0  # m/s at 1 kHz
    assert speed.max() <= 0.25 * 1.05  # the speed limit, with a paused loop's slack


@pytest.mark.parametrize(
    ("req", "code"),
    [
        ({"finger": "pinky", "position_m": [0, 0, 0]}, "bad_value"),
        ({"finger": 7, "position_m": [0, 0, 0]}, "bad_value"),
        ({"finger": "thumb", "position_m": [0, 0]}, "bad_value"),
        ({"finger": "thumb", "position_m": [0, 0, 1e9]}, "bad_value"),
        ({"finger": True, "position_m": [0, 0, 0]}, "bad_value"),
        ({"position_m": [0, 0, 0]}, "bad_value"),
    ],
)
def test_a_malformed_move_is_refused_naming_what(idle_server, req, code):
    with ControlClient(idle_server.path) as c, pytest.raises(proto.ProtocolError) as got:
        c.call("move", **req)
    assert got.value.code == code


def test_a_move_to_a_device_that_is_not_virtual_is_rejected(idle_server):
    client = ControlClient(idle_server.path)
    with client as c, pytest.raises(proto.ProtocolError, match="is not virtual") as got:
        c.move("thumb", [0.0, 0.0, 0.0])
    assert got.value.code == "rejected"


# -- from the view page, in headless Chromium ------------------------------------------------

VIRTUAL_AT = "JSON.parse(document.querySelector('[data-testid=scene]').dataset.virtual || 'null')"


def _force_shown(browser: cdp.Browser, i: int) -> float:
    got = browser.evaluate(
        f"(() => {{ const e = document.querySelector('[data-testid=virtual-{i}]'); "
        "return e ? [Number(e.dataset.force), e.textContent] : null; })()"
    )
    return got[0] if got and "touching" in got[1] else 0.0


def test_the_view_page_drags_a_virtual_fingertip_into_the_cube(tmp_path, view, chromium):  # noqa: F811
    sock = tmp_path / "d.sock"
    with virtual_daemon(sock, tmp_path) as server, ControlClient(sock) as c:
        c.events_subscribe(["contact_begin"])
        v = view(sock, "--control")
        with cdp.Browser(chromium, tmp_path / "chromium") as browser:
            browser.open(v.url)
            at = wait_for(
                lambda: browser.evaluate(VIRTUAL_AT),
                "the page to draw the virtual fingertips",
                until=lambda a: a and a["fingers"].get("0") and a["object"],
                timeout_s=20,
            )
            assert browser.evaluate("document.getElementById('virtual').hidden") is False
            # Drag the thumb onto the middle of the drawn cube: it goes into the cube.
            browser.drag(tuple(at["fingers"]["0"]), tuple(at["object"]), steps=12)
            ev = _events(c, "contact_begin", 0, 15)
            assert ev["event"] == "contact_begin"
            force = wait_for(
                lambda: _force_shown(browser, 0),
                "the page to show the thumb's rendered force",
                until=lambda f: f > 0.05,
                timeout_s=10,
            )
            assert force > 0.05
            assert server.loop.frame.in_contact[0]
            # The keys: squeeze the index finger in too (2 mm a press), then lift (up).
            x0 = float(server.loop.frame.device_pos[1][0])
            for _ in range(16):
                browser.press("s")
            wait_for(
                lambda: float(server.loop.frame.device_pos[1][0]),
                "the index finger to come 32 mm closer",
                until=lambda x: x < x0 - 0.030,
                timeout_s=10,
            )
            _events(c, "contact_begin", 1, 10)
            z0 = float(server.loop.frame.device_pos[1][2])
            browser.key("ArrowUp", shift=True)
            wait_for(
                lambda: float(server.loop.frame.device_pos[1][2]),
                "the index finger to rise 5 mm",
                until=lambda z: z > z0 + 0.0045,
                timeout_s=10,
            )
            browser.screenshot(tmp_path / "virtual.png")


def test_a_read_only_view_and_the_subject_page_move_nothing(tmp_path, view):  # noqa: F811
    sock = tmp_path / "d.sock"
    with virtual_daemon(sock, tmp_path) as server:
        ro = view(sock)
        rw = view(sock, "--control")
        msg = json.dumps({"type": "move", "ref": 1, "finger": 0, "position_m": [-0.03, 0, 0]})
        for v, mode in ((ro, None), (rw, "subject")):
            with v.ws(mode) as ws:
                ws.send(msg)
                reply = wait_for(
                    lambda ws=ws: json.loads(ws.recv(timeout=5)),
                    "the reply",
                    until=lambda m: m.get("type") == "reply",
                )
                assert reply["ok"] is False and reply["error"]["code"] == "read_only"
        assert server.session.devices[0].target == (0.0, 0.0, 0.0)
        with rw.ws() as ws:
            ws.send(msg)
            reply = wait_for(
                lambda: json.loads(ws.recv(timeout=5)),
                "the reply",
                until=lambda m: m.get("type") == "reply",
            )
        assert reply["ok"] is True
        assert reply["result"]["target_m"] == pytest.approx([-0.03, 0.0, 0.0])
