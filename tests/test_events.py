"""The loop's events: the ring and the frame watcher, and events delivered to subscribers
against what the recording shows, faults, a stalled subscriber and an overflowing ring."""

from __future__ import annotations

import ast
import json
import socket
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hapticd import events, recording
from hapticd.control import ControlClient
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.loop.commands import Enable
from hapticd.loop.event_ring import EventRing, FrameEvents
from hapticd.physics.frame import Frame
from hapticd.profile import load_profile
from tests.conftest import ROOT, AtTick, ServerHold, wait_for, wait_for_tick

BUNDLED = ROOT / "hapticd" / "data" / "trajectories" / "grasp-stiffness.hrec"


def write_trajectory(path: Path, t: np.ndarray, pos: np.ndarray, buttons: np.ndarray) -> Path:
    """A two-finger trajectory with buttons: times (N,) s, positions (N, 2, 3) m, buttons
    (N, 2) bit sets."""
    fields = [*recording.trajectory_fields(2), recording.Field("buttons", "<u4", (2,))]
    recording.write(
        path, {"t": t, "device_pos": pos, "buttons": buttons}, fields, ["thumb", "index"]
    )
    return path


def grasp_with_buttons(path: Path, schedule) -> Path:
    """The bundled grasp with buttons: ``schedule(t)`` gives the (N, 2) bit sets at the
    trajectory's times (N,) s."""
    base = recording.read(BUNDLED)
    t = base["t"]
    return write_trajectory(path, t, base["device_pos"], np.asarray(schedule(t), np.uint32))


def toggling(path: Path, duration_s: float, bits: int) -> Path:
    """Both fingers at rest far from the cube, their ``bits`` buttons pressed on every other
    millisecond: every tick of a 1 kHz loop changes ``bits`` buttons per finger."""
    n = int(duration_s * 1000) + 1
    t = np.arange(n) * 1e-3
    pos = np.zeros((n, 2, 3))
    pos[:, 0, 0], pos[:, 1, 0] = -0.07, 0.07
    mask = (1 << bits) - 1
    down = np.where(np.arange(n) % 2 == 1, mask, 0).astype(np.uint32)
    return write_trajectory(path, t, pos, np.stack([down, down], axis=1))


def calm(data: dict) -> dict:
    """The profile ``data`` without its wall-clock faults (watchdog, sustained overruns):
    these tests are about events, and a shared machine can stall a paced loop for 100 ms
    whatever the code does; every other fault still latches."""
    data["safety"]["watchdog_s"] = None
    data.setdefault("loop", {})["max_consecutive_overruns"] = 0
    return data


def profile_on(data: dict, trajectory: Path, write_profile, **finger_keys) -> Path:
    for finger in data["fingers"]:
        finger["device"]["trajectory"] = str(trajectory)
        finger.update(finger_keys)
    return write_profile(calm(data))


class Daemon:
    """A session serving its socket in a thread; the loop starts with ``start`` (so a test
    may subscribe first)."""

    def __init__(self, profile: Path, tmp_path: Path, **kw) -> None:
        self.session = build_session(load_profile(profile), record_dir=tmp_path, **kw)
        self.session.loop.realtime_settings = None
        self.sock = tmp_path / "ev.sock"
        self.server = ControlServer(self.session, self.sock)
        self.server.start()
        self.out: dict = {}
        self.runner = threading.Thread(
            target=lambda: self.out.update(summary=self.session.run()), name="test-loop"
        )

    def start(self) -> None:
        self.runner.start()

    def close(self) -> None:
        self.session.loop.request_stop("test over")
        if self.runner.is_alive() or self.runner.ident is not None:
            self.runner.join(timeout=20)
        self.server.close()


@pytest.fixture
def daemon(tmp_path, grasp_data, write_profile):
    made: list[Daemon] = []

    def make(profile: Path | None = None, **kw) -> Daemon:
        if profile is None:  # the bundled grasp, calm
            profile = write_profile(calm(grasp_data), "calm-grasp.yaml")
        d = Daemon(profile, tmp_path, **kw)
        made.append(d)
        return d

    yield make
    for d in made:
        d.close()


def collect(client: ControlClient, until, what: str, timeout_s: float = 20.0) -> list[dict]:
    """Events from ``client`` until ``until(event)`` holds for one; fail at the deadline."""
    got = []
    while True:
        try:
            ev = client.next_event(timeout_s)
        except TimeoutError:
            pytest.fail(f"no {what} within {timeout_s} s; events so far: {got[-5:]}")
        got.append(ev)
        if until(ev):
            return got


# -- the ring and the frame watcher ------------------------------------------------------------


def test_the_ring_keeps_order_and_counts_what_a_full_ring_drops():
    ring = EventRing(4)
    for k in range(3):
        ring.push(events.CODES["param_changed"], k, k * 1e-3, value=k)
    got, lost = ring.drain()
    assert got["tick"].tolist() == [0, 1, 2] and got["value"].tolist() == [0, 1, 2]
    assert lost == 0 and not ring.pending
    for k in range(10, 17):  # 7 into room for 4: the first 4 kept, 3 dropped, none overwritten
        ring.push(events.CODES["contact_begin"], k, 0.0, finger=1)
    assert ring.pending
    got, lost = ring.drain()
    assert got["tick"].tolist() == [10, 11, 12, 13] and lost == 3 and ring.lost_tick == 16
    assert got["finger"].tolist() == [1] * 4 and got["button"].tolist() == [-1] * 4
    got, lost = ring.drain()
    assert len(got) == 0 and lost == 0 and not ring.pending
    ring.push(events.CODES["trajectory_end"], 20, 0.02)  # wraps around the end of the buffer
    assert ring.drain()[0]["tick"].tolist() == [20]


@given(
    st.lists(
        st.tuples(
            st.lists(st.booleans(), min_size=3, max_size=3),
            st.lists(st.integers(0, 2**32 - 1), min_size=3, max_size=3),
        ),
        min_size=1,
        max_size=30,
    )
)
def test_the_watcher_finds_exactly_the_transitions_of_contact_and_buttons(ticks):
    """Against a plain reference: per tick and finger, a contact event where in_contact
    changed, a button event for every bit of buttons that changed, in finger and bit order."""
    frame = Frame(3, 1)
    ring = EventRing(4096)
    watch = FrameEvents(ring, 3)
    want = []
    was_c, was_b = [0, 0, 0], [0, 0, 0]
    for k, (contact, buttons) in enumerate(ticks):
        frame.in_contact[...] = contact
        frame.buttons[...] = buttons
        watch.after_tick(frame, k, k * 1e-3)
        for i in range(3):
            if int(contact[i]) != was_c[i]:
                want.append(("contact_begin" if contact[i] else "contact_end", k, i, -1))
        for i in range(3):
            for bit in range(32):
                a, b = (was_b[i] >> bit) & 1, (buttons[i] >> bit) & 1
                if a != b:
                    want.append(("button_down" if b else "button_up", k, i, bit))
        was_c, was_b = [int(c) for c in contact], list(buttons)
    got, lost = ring.drain()
    assert lost == 0
    names = [events.NAMES[c] for c in got["kind"].tolist()]
    have = list(
        zip(
            names, got["tick"].tolist(), got["finger"].tolist(), got["button"].tolist(), strict=True
        )
    )
    assert have == want


def test_watching_the_frame_holds_no_more_memory_as_ticks_go_by():
    """Memory held after 2,000 and after 22,000 ticks without change is the same, and the
    peak stays below one numpy array's worth (a comparison through numpy would allocate
    its result on every tick)."""
    frame = Frame(2, 2)
    frame.in_contact[...] = [1, 0]
    frame.buttons[...] = [5, 0]
    watch = FrameEvents(EventRing(16), 2)
    watch.after_tick(frame, 0, 0.0)  # the transitions, and the views made once
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        for k in range(1, 2000):
            watch.after_tick(frame, k, 0.5)
        after_few = tracemalloc.get_traced_memory()[0]
        for k in range(2000, 22_000):
            watch.after_tick(frame, k, 0.5)
        after_many, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert after_many == after_few and peak - before < 200, (after_many - after_few, peak)


def test_every_fault_kind_the_code_latches_is_a_declared_cause():
    """The fourth argument of every ``trip(...)`` call in hapticd is a FAULT_CAUSES name."""
    used = set()
    for path in (ROOT / "hapticd").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "trip"
                and len(node.args) == 4
            ):
                arg = node.args[3]
                assert isinstance(arg, ast.Constant), f"{path}: a fault kind must be a literal"
                used.add(arg.value)
    assert used and used <= set(events.FAULT_CAUSES), used - set(events.FAULT_CAUSES)
    assert {"nonfinite_force", "overrun", "device", "exception"} <= used


def test_the_docs_event_table_is_the_declaration():
    import re

    text = (ROOT / "docs" / "control.md").read_text()
    m = re.search(
        r"<!-- generated by `python -m hapticd.events`.*?-->\n(.*?)<!-- end of the event tables",
        text,
        re.S,
    )
    assert m, "docs/control.md lost its event-table markers"
    assert m.group(1).strip() == events.markdown_table().strip(), (
        "docs/control.md's event tables differ from hapticd.events: paste the output of "
        "`python -m hapticd.events` between the markers"
    )


# -- events delivered, against the recording ---------------------------------------------------


def test_contact_events_are_exactly_the_recordings_in_contact_transitions(daemon, tmp_path):
    """The bundled grasp, paced, end to end: an events subscriber from tick 0, a recording
    started and stopped over the socket around the whole grasp, a stiffness set in the
    pinch. Every contact_begin/contact_end is at a tick where the recording's in_contact
    changes, and every change has its event; the set, the recording and the trajectory's
    end each have theirs at the tick the replies name."""
    d = daemon()
    with ControlClient(d.sock) as sub, ControlClient(d.sock) as ctl:
        assert sub.events_subscribe() == {
            "subscribed": True,
            "kinds": list(events.NAMES),
            "tick": 0,
        }
        d.start()
        started = ctl.record_start("grasp.hrec")
        wait_for_tick(ctl, 2700, limit_s=20)  # in the pinch
        k_set = ctl.set("stiffness_n_per_m", 90.0)["applied_at_tick"]
        wait_for_tick(ctl, 6600, limit_s=20)  # released (about 6.06 s)
        stopped = ctl.record_stop()
        got = collect(sub, lambda e: e["event"] == "trajectory_end", "trajectory_end")
    summary = wait_for(lambda: d.out.get("summary"), "the run's summary")
    assert summary["end_reason"] == "trajectory ended"
    ticks = [e["tick"] for e in got]
    assert ticks == sorted(ticks) and all(e["t"] == pytest.approx(e["tick"] * 1e-3) for e in got)

    rec = recording.read(tmp_path / "grasp.hrec")
    rec_ticks = rec["tick"].astype(np.int64)
    assert rec_ticks[0] == started["applied_at_tick"]
    assert rec_ticks[-1] == stopped["applied_at_tick"] - 1
    np.testing.assert_array_equal(np.diff(rec_ticks), 1)
    contact = rec["in_contact"].astype(int)
    assert not contact[0].any()  # the recording began before any contact
    for i, name in enumerate(("thumb", "index")):
        change = np.diff(contact[:, i])
        begins = rec_ticks[1:][change == 1].tolist()
        ends = rec_ticks[1:][change == -1].tolist()
        assert begins and ends, f"{name} never touched: the test shows nothing"
        mine = [e for e in got if e.get("finger") == i and e["event"].startswith("contact_")]
        assert all(e["finger_name"] == name for e in mine)
        assert [e["tick"] for e in mine if e["event"] == "contact_begin"] == begins, name
        assert [e["tick"] for e in mine if e["event"] == "contact_end"] == ends, name
    assert not any(e["event"].startswith("button_") for e in got)  # no button was pressed

    def at(kind: str) -> list[int]:
        return [e["tick"] for e in got if e["event"] == kind]

    assert at("recording_started") == [started["applied_at_tick"]]
    assert at("recording_stopped") == [stopped["applied_at_tick"]]
    changed = [e for e in got if e["event"] == "param_changed"]
    assert [(e["tick"], e["param"]) for e in changed] == [(k_set, "stiffness_n_per_m")]
    assert rec["stiffness_n_per_m"][rec_ticks == k_set - 1] == 60.0
    assert rec["stiffness_n_per_m"][rec_ticks == k_set] == 90.0
    assert at("trajectory_end") == [summary["ticks"] - 1]
    assert not at("fault_latched") and not at("events_lost")


def test_a_fault_is_an_event_with_its_cause_and_again_after_enable(daemon):
    """NaN forces injected at ticks 300 and 500 (forces re-enabled in between): two
    fault_latched events, each at its tick with its cause and message."""
    d = daemon(paced=False, duration_s=0.7)
    loop = d.session.loop

    def nan(frame):
        frame.rendered_force[0, 0] = np.nan

    d.session.renderer.insert(AtTick(300, nan), after="allocation")
    d.session.renderer.insert(AtTick(400, lambda f: loop.submit(Enable())), after="allocation")
    d.session.renderer.insert(AtTick(500, nan), after="allocation")
    with ControlClient(d.sock) as sub:
        sub.events_subscribe(["fault_latched", "contact_begin"])
        d.start()
        first = collect(sub, lambda e: e["event"] == "fault_latched", "the first fault")
        second = collect(sub, lambda e: e["event"] == "fault_latched", "the second fault")
    assert [e["event"] for e in first + second] == ["fault_latched"] * 2  # nothing else asked
    for ev, tick in zip((first[-1], second[-1]), (300, 500), strict=True):
        assert ev["tick"] == tick and ev["cause"] == "nonfinite_force"
    assert second[-1]["message"] == "non-finite force for finger(s) [0]"
    summary = wait_for(lambda: d.out.get("summary"), "the run's summary")
    assert summary["fault"]["tick"] == 500 and summary["fault"]["kind"] == "nonfinite_force"


def test_a_stalled_subscriber_is_dropped_and_the_loop_goes_on(daemon, tmp_path, grasp_data,
                                                              write_profile):  # fmt: skip
    """Eight buttons per finger toggle on every tick (16 events a tick): a subscriber that
    reads nothing falls behind, is disconnected, and the loop keeps its ticks and forces."""
    traj = toggling(tmp_path / "toggle.hrec", 10.0, 8)
    d = daemon(profile_on(grasp_data, traj, write_profile))
    stalled = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stalled.settimeout(10)
    stalled.connect(str(d.sock))
    with stalled, ControlClient(d.sock) as other:
        stalled.sendall(b'{"id": 1, "cmd": "events_subscribe"}\n')
        head = b""
        while head.count(b"\n") < 2:  # the greeting and the reply: subscribed
            head += stalled.recv(4096)
        assert b'"subscribed":true' in head
        d.start()
        wait_for(lambda: d.server.slow_event_clients, "the stalled subscriber's drop")
        tick = other.status()["tick"]
        wait_for(other.status, "ticks after the drop", until=lambda s: s["tick"] > tick + 300)
        st = other.status()
        assert st["fault"] is None and st["devices"][0]["buttons"] in ([], list(range(8)))
        # The stalled client reads what the kernel held for it, then the end of the stream.
        got = b""
        for _ in range(10_000):
            chunk = stalled.recv(1 << 20)
            if not chunk:
                break
            got += chunk
        else:
            pytest.fail("the stalled subscriber was never disconnected")
    # What it got is a prefix of the stream: whole events, in order, from the first tick on;
    # the last line may be cut where the socket's buffer was full when the server dropped it
    # (where it is cut depends on how far the kernel had sent: a line without its newline is
    # unfinished, and a line reader never returns it).
    lines = got.split(b"\n")[:-1]
    head_ticks = [json.loads(line)["tick"] for line in lines]
    assert len(head_ticks) > 100 and head_ticks[0] == 1 and head_ticks == sorted(head_ticks)


def test_an_overflowing_ring_is_reported_as_lost_events_in_place(
    daemon, tmp_path, grasp_data, write_profile
):
    """A ring of 2048 events (256 ticks' worth: far more than the server lets wait when it
    runs), four buttons per finger toggling every tick (8 events a tick) and the server
    held for 400 ticks: the subscriber gets the events the
    ring held, then ``events_lost`` with the count the loop dropped, then the events after;
    together exactly the 8 a tick the trajectory makes."""
    traj = toggling(tmp_path / "toggle.hrec", 10.0, 4)
    d = daemon(profile_on(grasp_data, traj, write_profile), event_capacity=2048)
    loop = d.session.loop
    d.server.events_backlog_bytes = 64 << 20  # the subscriber reads late, and is not dropped
    hold = ServerHold(d.server)  # the server thread stops: nothing drains
    with ControlClient(d.sock) as sub, ControlClient(d.sock) as ctl:
        first = sub.events_subscribe()["tick"]
        d.start()
        wait_for_tick(ctl, 200)
        hold.hold()
        k = loop.stats.ticks
        wait_for(lambda: loop.stats.ticks, "400 held ticks", until=lambda n: n > k + 400)
        hold.release()
        got = collect(sub, lambda e: e["event"] == "events_lost", "events_lost")
        lost = got[-1]
        end = lost["tick"] + 20
        # Far enough on for every report of the overflow to have come (the server drains
        # every 5 ms).
        later = lost["tick"] + 300
        got += collect(sub, lambda e: e["tick"] >= later, f"events up to tick {later}")
    # The ring overflowed once, while the server was held (a loss that races the drain
    # that releases it is reported by the next drain: a second events_lost soon after).
    reports = [e for e in got if e["event"] == "events_lost"]
    assert reports[0] is lost and 1 <= len(reports) <= 2
    assert all(r["tick"] < lost["tick"] + 5 for r in reports)
    assert 0 < sum(r["count"] for r in reports) <= loop.event_ring.lost
    before = got[: got.index(lost)]
    after = [e for e in got[got.index(lost) + 1 :] if e["event"] != "events_lost"]
    assert before[-1]["tick"] <= lost["tick"] < after[0]["tick"]
    # Every tick from the first toggles 4 buttons of each finger: nothing missing, nothing
    # twice, except what events_lost counts.
    span = range(max(first, 1), end)
    made = sum(8 for k in span)
    seen = [e for e in before + after if e["tick"] in span]
    assert len(seen) + sum(r["count"] for r in reports) == made
    assert {e["event"] for e in seen} == {"button_down", "button_up"}


def test_hapticd_events_json_shows_the_grasps_contacts_at_the_recordings_transitions(
    daemon, tmp_path, capsys
):
    """`hapticd events --json`, subscribed before the bundled grasp starts, prints a
    contact_begin and a contact_end for each finger at exactly the ticks where the run's own
    recording (from tick 0) changes in_contact, and nothing else of those kinds."""
    from hapticd.cli import main

    d = daemon(paced=False, record_path=tmp_path / "grasp.hrec")

    def start_when_subscribed() -> None:
        try:
            deadline = time.monotonic() + 20
            while not d.server.event_subscribers:
                if time.monotonic() > deadline:
                    return  # the command fails below: it printed nothing
                time.sleep(0.005)
            d.start()
            d.runner.join(timeout=60)
        finally:
            d.server.close()  # as the daemon does when its run ends: the stream ends

    starter = threading.Thread(target=start_when_subscribed, name="test-starter")
    starter.start()
    kinds = "contact_begin,contact_end"
    code = main(["events", "--json", "--kinds", kinds, "--socket", str(d.sock)])
    starter.join(timeout=70)
    assert code == 0
    got = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    summary = d.out["summary"]
    assert summary["end_reason"] == "trajectory ended" and summary["fault"] is None
    rec = recording.read(tmp_path / "grasp.hrec")
    ticks = rec["tick"].astype(np.int64)
    np.testing.assert_array_equal(ticks, np.arange(rec.ticks))
    contact = rec["in_contact"].astype(int)
    assert not contact[0].any()
    for i, name in enumerate(("thumb", "index")):
        change = np.diff(contact[:, i])
        want = sorted(
            [(int(k), "contact_begin") for k in ticks[1:][change == 1]]
            + [(int(k), "contact_end") for k in ticks[1:][change == -1]]
        )
        assert [e for _, e in want].count("contact_begin") >= 1, f"{name} never touched"
        assert [e for _, e in want].count("contact_end") >= 1, f"{name} never let go"
        mine = [(e["tick"], e["event"]) for e in got if e["finger"] == i]
        assert mine == want, name
        assert all(e["finger_name"] == name for e in got if e["finger"] == i)
    assert {e["event"] for e in got} == {"contact_begin", "contact_end"}
    assert all(e["t"] == pytest.approx(e["tick"] * 1e-3) for e in got)
