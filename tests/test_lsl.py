"""Lab Streaming Layer: an inlet receives the numeric and the marker stream, stamped as the
recording's header anchor says; the anchor itself; a vanished publisher; no pylsl."""

from __future__ import annotations

import collections
import datetime
import io
import json
import os
import signal
import sys
import threading
import time
import uuid

import numpy as np
import pylsl
import pytest
import yaml

from hapticd import protocol as proto
from hapticd import recording
from hapticd.cli import main as cli_main
from hapticd.control import ControlClient
from hapticd.daemon import lsl
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.experiment import load_experiment, make_plan
from hapticd.experiment import runner as rn
from hapticd.profile import load_profile
from hapticd.recording import format as rec_format
from hapticd.recording.export import csv_columns
from tests.conftest import GRASP_PROFILE, ROOT

# The grasp's fingers touch the cube at 1.943 s: a run a little longer holds both contacts.
RUN_S = 2.1
WAIT_S = 20.0  # for the streams to arrive (a loaded machine); a test fails at its deadline


def unpaced(tmp_path, *overrides, record=True):
    """An unpaced grasp session (its own stream name), its recording in tmp_path."""
    name = f"lsl-{uuid.uuid4().hex[:8]}"
    profile = load_profile(GRASP_PROFILE, [f"name={name}", *overrides])
    session = build_session(
        profile,
        paced=False,
        duration_s=RUN_S,
        record_path=tmp_path / "run.hrec" if record else None,
        record_dir=tmp_path,
    )
    return session, name


def pull_until(inlet, count, deadline):
    """Samples and their timestamps until ``count`` arrived; fails at ``deadline``."""
    samples, stamps = [], []
    while len(stamps) < count:
        assert time.monotonic() < deadline, f"{len(stamps)} of {count} samples arrived"
        data, ts = inlet.pull_chunk(timeout=0.05)
        samples += data
        stamps += ts
    return samples, stamps


def open_inlet(name):
    found = pylsl.resolve_byprop("name", name, timeout=WAIT_S)
    assert len(found) == 1, f"stream {name} not found"
    inlet = pylsl.StreamInlet(found[0], recover=False)
    inlet.open_stream(timeout=WAIT_S)
    return inlet


@pytest.mark.timing("waits for LSL's delivery over loopback, within a deadline")
def test_an_inlet_receives_both_streams_stamped_on_the_recordings_clock(tmp_path):
    session, name = unpaced(tmp_path, "lsl.decimation=2")
    server = ControlServer(session, tmp_path / "d.sock")
    outlet = lsl.attach(session, server)
    server.start()
    inlets, numeric, markers = [], None, None
    try:
        stream = lsl.stream_name(name)
        numeric, markers = open_inlet(stream), open_inlet(stream + "-markers")
        inlets = [numeric, markers]
        with ControlClient(tmp_path / "d.sock") as c:
            marked = c.mark("trial_start trial=0")["tick"]
            with pytest.raises(proto.ProtocolError) as bad:
                c.mark("two\nlines")
            assert bad.value.code == "bad_value"
        run = threading.Thread(target=session.run, name="test-loop")
        run.start()
        run.join(timeout=WAIT_S)
        assert not run.is_alive()
        deadline = time.monotonic() + WAIT_S
        rec = recording.read(tmp_path / "run.hrec")
        ticks = session.loop.stats.ticks
        samples, stamps = pull_until(numeric, (ticks + 1) // 2, deadline)
        got, stamps_m = [], []
        while sum('"contact_begin"' in m for m in got) < 2:
            assert time.monotonic() < deadline, f"markers so far: {got}"
            data, ts = markers.pull_chunk(timeout=0.05)
            got += [m[0] for m in data]
            stamps_m += ts
        info = numeric.info(timeout=WAIT_S)
    finally:
        # liblsl's sockets close with the inlets (lsl_destroy_inlet): no reference is left.
        while inlets:
            inlets.pop().close_stream()
        numeric = markers = None
        server.close()
        status = lsl.detach(session, outlet)
        if session.loop.recorder is not None:  # the run never began
            session.loop.recorder.discard()
    assert status["error"] is None and status["dropped"] == 0
    # The channels are the CSV export's columns, per-finger contact among them.
    cols = csv_columns(rec)
    assert "in_contact.thumb" in cols and "in_contact.index" in cols
    assert info.channel_count() == len(cols)
    assert info.nominal_srate() == pytest.approx(session.loop.rate_hz / 2)
    ch, labels, units = info.desc().child("channels").child("channel"), [], {}
    while not ch.empty():
        labels.append(ch.child_value("label"))
        units[labels[-1]] = (ch.child_value("unit"), ch.child_value("finger"))
        ch = ch.next_sibling()
    assert labels == cols
    assert units["device_pos.thumb.x"] == ("m", "thumb")
    assert units["device_force.index.z"] == ("N", "index")
    fingers = info.desc().child("fingers").child("finger")
    assert [fingers.child_value(), fingers.next_sibling().child_value()] == ["thumb", "index"]
    # Every second tick, each stamped with its start on the LSL clock: the recording's
    # anchor plus its t_wall.
    values = np.asarray(samples)
    tick = values[:, cols.index("tick")].astype(int)
    assert tick.tolist() == list(range(0, ticks, 2))
    lsl0 = rec.clock["lsl_s"]
    np.testing.assert_allclose(stamps, lsl0 + rec["t_wall"][tick], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(
        values[:, cols.index("in_contact.index")], rec["in_contact"][tick, 1]
    )
    # Markers: the client's mark, and each finger's contact begin, at the tick the
    # recording shows it, stamped with that tick's time.
    evs = [json.loads(m) for m in got]
    assert evs[0] == {"event": "mark", "tick": marked, "t": 0.0, "text": "trial_start trial=0"}
    assert stamps_m[0] == pytest.approx(lsl0 + rec["t_wall"][marked], abs=1e-9)
    contact = rec["in_contact"]
    for i, finger in enumerate(["thumb", "index"]):
        begins = [
            (e, s) for e, s in zip(evs, stamps_m, strict=True)
            if e["event"] == "contact_begin" and e["finger_name"] == finger
        ]  # fmt: skip
        assert len(begins) == 1
        ev, stamp = begins[0]
        k = ev["tick"]
        assert contact[k, i] == 1 and contact[k - 1, i] == 0
        assert stamp == pytest.approx(lsl0 + rec["t_wall"][k], abs=1e-9)


@pytest.mark.timing("waits for LSL's delivery over loopback, within a deadline")
def test_buttons_and_a_fault_reach_the_marker_stream_at_their_ticks(tmp_path, grasp_data):
    """The index finger's button pressed and released once a grasp cycle, and NaN forces at
    tick 900: each button_down and button_up (after the fault too), with its finger and
    button, and the fault_latched with its cause, arrive on the marker stream stamped with
    their tick's time on the recording's clock."""
    from tests.conftest import AtTick
    from tests.test_runner import periodic_grasp

    traj = periodic_grasp(tmp_path / "buttons.hrec", 3, button_at=0.05)
    name = f"lsl-{uuid.uuid4().hex[:8]}"
    for f in grasp_data["fingers"]:
        f["device"]["trajectory"] = str(traj)
    path = tmp_path / "profile.yaml"
    path.write_text(yaml.safe_dump(grasp_data, sort_keys=False))
    session = build_session(
        load_profile(path, [f"name={name}"]),
        paced=False,
        duration_s=1.2,
        record_path=tmp_path / "run.hrec",
        record_dir=tmp_path,
    )

    def nan(frame):
        frame.rendered_force[0, 0] = np.nan

    session.renderer.insert(AtTick(900, nan), after="allocation")
    server = ControlServer(session, tmp_path / "d.sock")
    outlet = lsl.attach(session, server)
    server.start()
    inlets = []
    try:
        markers = open_inlet(lsl.stream_name(name) + "-markers")
        inlets = [markers]
        run = threading.Thread(target=session.run, name="test-loop")
        run.start()
        run.join(timeout=WAIT_S)
        assert not run.is_alive()
        presses = recording.read(tmp_path / "run.hrec")["buttons"][:, 1]
        changes = int(np.count_nonzero(np.diff(presses.astype(int))))
        deadline = time.monotonic() + WAIT_S
        got, stamps = [], []
        while (
            sum('"button_' in m for m in got) < changes
            or not any('"fault_latched"' in m for m in got)
        ):  # fmt: skip
            assert time.monotonic() < deadline, f"markers so far: {got}"
            data, ts = markers.pull_chunk(timeout=0.05)
            got += [m[0] for m in data]
            stamps += ts
    finally:
        while inlets:
            inlets.pop().close_stream()
        markers = None
        server.close()
        lsl.detach(session, outlet)
    rec = recording.read(tmp_path / "run.hrec")
    lsl0 = rec.clock["lsl_s"]
    evs = list(zip((json.loads(m) for m in got), stamps, strict=True))
    for kind, before, after in (("button_down", 0, 1), ("button_up", 1, 0)):
        seen = [(e, t) for e, t in evs if e["event"] == kind]
        want = np.flatnonzero((presses[:-1] == before) & (presses[1:] == after)) + 1
        assert [e["tick"] for e, _ in seen] == want.tolist(), kind  # the fault stops none
        assert seen and all(e["finger_name"] == "index" and e["button"] == 0 for e, _ in seen)
        for e, t in seen:
            assert t == pytest.approx(lsl0 + rec["t_wall"][e["tick"]], abs=1e-9)
    ((fault, t),) = [(e, t) for e, t in evs if e["event"] == "fault_latched"]
    assert fault["tick"] == 900 and fault["cause"] == "nonfinite_force"
    assert t == pytest.approx(lsl0 + rec["t_wall"][900], abs=1e-9)


def test_the_lsl_clock_is_the_monotonic_clock():
    """liblsl's local_clock is std::chrono::steady_clock: CLOCK_MONOTONIC, time.monotonic."""
    before = time.monotonic()
    now = pylsl.local_clock()
    after = time.monotonic()
    assert before <= now <= after


def test_a_recordings_header_holds_tick_0_on_the_lsl_clock_and_in_utc(tmp_path):
    session, _ = unpaced(tmp_path)
    session.loop.duration_s = 0.05
    before = time.monotonic()
    offset = time.time() - time.monotonic()  # UTC minus the monotonic clock, s
    session.run()
    rec = recording.read(tmp_path / "run.hrec")
    clock = rec.clock
    # Tick 0 was due when the loop started, and its first tick started then.
    assert before <= clock["lsl_s"] <= before + rec["t_wall"][-1] + 5.0
    assert 0 <= rec["t_wall"][0] < 1.0
    assert clock["utc_unix_s"] - clock["lsl_s"] == pytest.approx(offset, abs=0.05)
    utc = datetime.datetime.fromisoformat(clock["utc"].replace("Z", "+00:00"))
    assert utc.tzinfo == datetime.UTC
    assert utc.timestamp() == pytest.approx(clock["utc_unix_s"], abs=1e-5)


def test_a_header_without_an_anchor_reads_and_a_bad_one_is_named(tmp_path):
    fields = [recording.Field("t", "<f8", (), "s")]
    old = tmp_path / "old.hrec"
    recording.write(old, {"t": np.arange(3.0)}, fields, ["thumb"])  # as before the anchor
    assert recording.read(old).clock is None and recording.read(old).ticks == 3
    # A run that ended before its first tick: the place for the anchor, never filled.
    unfilled = tmp_path / "unfilled.hrec"
    unfilled.write_bytes(rec_format.header_bytes(fields, ["thumb"], clock_place=True))
    assert recording.read(unfilled).clock is None
    bad = tmp_path / "bad.hrec"
    blob = bytearray(unfilled.read_bytes())
    at = rec_format.clock_offset()
    patch = b'{"lsl_s": "soon"}'.ljust(rec_format.CLOCK_WIDTH)
    blob[at : at + len(patch)] = patch
    bad.write_bytes(bytes(blob))
    with pytest.raises(recording.RecordingError, match=r"bad\.hrec: header 'clock'"):
        recording.read(bad)


def test_a_publisher_that_vanishes_costs_the_run_nothing_and_loses_nothing_recorded(tmp_path):
    session, _ = unpaced(tmp_path)
    session.loop.duration_s = 5.0  # more ticks than the stream's ring holds
    outlet = lsl.attach(session, None)
    os.kill(outlet.status()["writer_pid"], signal.SIGKILL)
    summary = session.run()
    status = lsl.detach(session, outlet)
    assert summary["fault"] is None and summary["end_reason"] == "duration reached"
    rec = recording.read(tmp_path / "run.hrec")
    assert rec.ticks >= summary["ticks"] == 5000
    np.testing.assert_array_equal(rec["tick"][:5000], np.arange(5000))
    assert status["dropped"] == 5000 - outlet.capacity
    assert "ended (killed by signal 9)" in status["error"]


@pytest.mark.timing("waits for LSL's delivery over loopback, within a deadline")
def test_hapticd_run_with_lsl_publishes_both_streams_until_it_stops(tmp_path):
    """The command a lab types, ``hapticd run PROFILE --lsl``: both streams appear under the
    profile's name, ticks arrive at the loop's rate with a tick counter that advances, a
    client's mark reaches the marker stream, and SIGTERM ends the run cleanly (exit 0)
    with both streams gone."""
    import subprocess

    name = f"lsl-cli-{uuid.uuid4().hex[:8]}"
    sock = tmp_path / "d.sock"
    cmd = [sys.executable, "-m", "hapticd", "run", str(GRASP_PROFILE), "--lsl", "-q"]
    cmd += ["--set", f"name={name}", "--set", "fingers[0].device.hold_s=60"]
    cmd += ["--set", "fingers[1].device.hold_s=60", "--socket", str(sock)]
    cmd += ["--record-dir", str(tmp_path), "--duration", "30"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, stderr=subprocess.PIPE, text=True)
    inlets = []
    try:
        stream = lsl.stream_name(name)
        numeric, markers = open_inlet(stream), open_inlet(stream + "-markers")
        inlets = [numeric, markers]
        assert numeric.info(timeout=WAIT_S).nominal_srate() == pytest.approx(1000.0)
        deadline = time.monotonic() + WAIT_S
        samples, _ = pull_until(numeric, 200, deadline)
        deadline = time.monotonic() + WAIT_S
        while not sock.exists():
            assert time.monotonic() < deadline, "no control socket"
            time.sleep(0.05)
        with ControlClient(sock) as c:
            marked = c.mark("block 1")["tick"]
        got: list[str] = []
        while not any('"block 1"' in m for m in got):
            assert time.monotonic() < deadline, f"markers so far: {got}"
            data, _ = markers.pull_chunk(timeout=0.05)
            got += [m[0] for m in data]
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=WAIT_S)
    finally:
        while inlets:
            inlets.pop().close_stream()
        numeric = markers = None
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    cols = csv_columns_for(name)
    tick = np.asarray(samples)[:, cols.index("tick")]
    np.testing.assert_array_equal(np.diff(tick), 1)  # every tick, in order
    mark = next(json.loads(m) for m in got if '"block 1"' in m)
    assert mark["tick"] == marked
    assert not pylsl.resolve_byprop("name", lsl.stream_name(name), timeout=0.5)


def csv_columns_for(name: str) -> list[str]:
    """The numeric stream's channel labels (the CSV export's columns) for the grasp profile."""
    from hapticd.recording import loop_fields

    profile = load_profile(GRASP_PROFILE, [f"name={name}"])
    fields = loop_fields(len(profile.fingers), 2)
    return [c["label"] for c in lsl.channels(fields, profile.finger_names)]


@pytest.mark.timing("a paced run, its inlet closed while it runs")
def test_an_inlet_that_goes_away_mid_run_costs_the_run_nothing_and_loses_nothing(tmp_path):
    """A consumer that vanishes (LabRecorder closed mid-session): the run goes on to its
    end, every tick is recorded in order, and the publisher reports no error and drops
    nothing."""
    name = f"lsl-{uuid.uuid4().hex[:8]}"
    session = build_session(
        load_profile(GRASP_PROFILE, [f"name={name}"]),
        paced=True,
        duration_s=1.5,
        record_path=tmp_path / "run.hrec",
        record_dir=tmp_path,
    )
    outlet = lsl.attach(session, None)
    inlet = open_inlet(lsl.stream_name(name))
    summary: dict = {}
    run = threading.Thread(target=lambda: summary.update(session.run()), name="test-loop")
    run.start()
    try:
        pull_until(inlet, 100, time.monotonic() + WAIT_S)
        inlet.close_stream()
        inlet = None  # liblsl's sockets close with the inlet
        assert run.is_alive(), "the run ended before the inlet went"
        run.join(timeout=WAIT_S)
        assert not run.is_alive()
    finally:
        status = lsl.detach(session, outlet)
    assert status["error"] is None and status["dropped"] == 0, status
    rec = recording.read(tmp_path / "run.hrec")
    ticks = session.loop.stats.ticks
    assert summary["fault"] is None and summary["end_reason"] == "duration reached"
    assert ticks == summary["ticks"] == 1500
    np.testing.assert_array_equal(rec["tick"][:ticks], np.arange(ticks))


@pytest.mark.parametrize("how", ["--lsl", "profile"])
def test_without_pylsl_a_run_says_how_to_install_it_before_any_device(
    how, tmp_path, monkeypatch, capsys, write_profile, grasp_data
):
    monkeypatch.setitem(sys.modules, "pylsl", None)  # `import pylsl` raises ImportError
    made = []
    monkeypatch.setattr("hapticd.cli.run.build_session", lambda *a, **k: made.append(a))
    if how == "profile":
        grasp_data["lsl"] = {"enabled": True}
    path = write_profile(grasp_data)
    args = ["run", str(path), "--duration", "0.1", "--no-socket", "-q"]
    code = cli_main([*args, "--lsl"] if how == "--lsl" else args)
    err = capsys.readouterr().err
    assert code == 2 and not made
    assert "pip install 'hapticd[lsl]'" in err
    assert ("--lsl" if how == "--lsl" else "lsl.enabled") in err


@pytest.mark.parametrize(
    "text", ["", "x" * (proto.MARK_TEXT_CHARS + 1), "a\x1bb", "tab\there", 7, None]
)
def test_a_mark_needs_short_printable_text(text):
    with pytest.raises(proto.ProtocolError) as exc:
        proto.check({"cmd": "mark", "text": text})
    assert exc.value.code == "bad_value"
    proto.check({"cmd": "mark", "text": "trial_start trial=3 · condition=pinv"})


class ScriptedDaemon:
    """A control client's stand-in for one trial: each change is applied at once, then the
    subject touches and releases, and answers the prompt; it keeps the marks sent."""

    def __init__(self, *, knows_mark: bool = True) -> None:
        self.knows_mark = knows_mark
        self.events: collections.deque = collections.deque()
        self.marks: list[str] = []
        self.tick = 0
        self.touch_due = False

    def events_subscribe(self, kinds=None):
        return {"subscribed": True}

    def status(self):
        return {"profile": "grasp-stiffness", "in_contact": [0, 0], "fault": None}

    def record_start(self, name):
        return {"path": name}

    def record_stop(self):
        return {}

    def set(self, name, value):
        self.tick += 1
        self.events.append({"event": "param_changed", "tick": self.tick})
        self.touch_due = True
        return {"applied_at_tick": self.tick}

    def next_event(self, timeout_s):
        if not self.events and self.touch_due:
            self.touch_due = False
            for name in ("contact_begin", "contact_end"):
                self.events.append({"event": name, "tick": self.tick, "finger": 0})
        if self.events:
            return self.events.popleft()
        time.sleep(min(timeout_s, 0.005))
        raise TimeoutError

    def prompt(self, prompt_id, question, choices):
        self.events.append({"event": "prompt", "prompt": prompt_id, "t": 0.0})
        self.events.append({"event": "response", "prompt": prompt_id, "choice": "yes"})
        return {}

    def clear_prompt(self):
        return {}

    def screen(self, screen):
        return {}

    def mark(self, text):
        if not self.knows_mark:
            raise proto.ProtocolError("unknown_command", "unknown cmd 'mark'")
        self.marks.append(text)
        return {"tick": self.tick}


def test_the_runner_marks_each_trial_interval_and_condition(tmp_path):
    data = yaml.safe_load((ROOT / "configs" / "experiments" / "stiffness-jnd.yaml").read_text())
    data["profile"] = str(GRASP_PROFILE)
    data["interval"]["gap_s"] = 0.01
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(data))
    exp = rn.reduced(load_experiment(path), standards=[60.0], repetitions=1)
    trial = make_plan(exp, exp.subject_seed("s1"))[0]
    daemon = ScriptedDaemon()
    out = io.StringIO()
    presenter = rn.PersonPresenter(daemon, subject="s1", out=out)
    got = presenter.present(exp, trial, {})
    assert got.answer_second_more is True
    first, second = rn.interval_values(exp, trial)
    at = f"trial={trial.index}"
    param = exp.varied.param
    assert daemon.marks == [
        f"trial_start {at} condition={trial.condition}",
        f"condition_set {at} interval=1 {param}={first!r}",
        f"interval_start {at} interval=1",
        f"interval_end {at} interval=1",
        f"condition_set {at} interval=2 {param}={second!r}",
        f"interval_start {at} interval=2",
        f"interval_end {at} interval=2",
        f"trial_end {at} answer=second",
    ]
    # A daemon without `mark` (an older one): the trial goes on, and it is not asked again.
    old = ScriptedDaemon(knows_mark=False)
    presenter = rn.PersonPresenter(old, subject="s1", out=out)
    assert presenter.present(exp, trial, {}).answer_second_more is True
    assert old.marks == [] and presenter._marks is False
