"""The subject's screen: the experiment file's instructions, practice, feedback and display
keys; the daemon's ``screen`` command; what the view passes on to the subject's page (text
states, nothing of the condition; no scene at all when the experiment hides it); practice
trials planned, stored with their flag, resumed and never analysed; and, in headless
Chromium, a reduced stiffness experiment answered on the subject's page."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import re
import threading
from pathlib import Path

import pytest
import yaml

from hapticd import params
from hapticd import protocol as proto
from hapticd.cli import main
from hapticd.control import ControlClient
from hapticd.experiment import load_experiment, make_plan
from hapticd.experiment import runner as rn
from hapticd.experiment.analyze import analyze, failed_trials
from hapticd.experiment.plan import make_practice
from hapticd.experiment.spec import ExperimentError
from hapticd.experiment.store import TrialStore, open_for_analysis
from hapticd.view import ViewServer
from tests import cdp
from tests.conftest import ROOT, wait_for
from tests.test_runner import Scripted, periodic_grasp, setup_files
from tests.test_view import running_daemon, statuses, ticks_of, ws_connect, ws_events

STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"
TEXT = "Feel both cubes.\nSay whether the second was stiffer."


def write_exp(tmp_path: Path, **sections) -> Path:
    """The stiffness design (its profile beside it) with ``sections`` added."""
    data = yaml.safe_load(STIFFNESS.read_text())
    data["profile"] = str(STIFFNESS.parent / data["profile"])
    data.update(sections)
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def line_of(path: Path, key: str) -> int:
    """The 1-based line of the top-level ``key:`` in ``path``."""
    lines = path.read_text().splitlines()
    return next(i for i, text in enumerate(lines, 1) if text.startswith(f"{key}:"))


# -- the experiment file ---------------------------------------------------------------------


def test_missing_instruction_text_is_refused_by_check_naming_the_key_and_line(tmp_path, capsys):
    path = write_exp(tmp_path, instructions={"enabled": True})
    assert main(["experiment", "check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "instructions:" in err and "text" in err and "missing" in err
    assert f"line {line_of(path, 'instructions')}" in err
    # Disabled, no text is needed; enabled with text, the file is good.
    load_experiment(write_exp(tmp_path, instructions={"enabled": False}))
    exp = load_experiment(write_exp(tmp_path, instructions={"text": TEXT}))
    assert exp.instructions.text == TEXT and exp.instructions.enabled


@pytest.mark.parametrize(
    ("sections", "key", "expect"),
    [
        ({"display": {"scene": "maybe"}}, "display.scene", "bool"),
        ({"display": {"colour": "red"}}, "display.colour", "unknown key"),
        ({"feedback": {"after": "sometimes"}}, "feedback.after", "none"),
        ({"feedback": {"duration_s": 0}}, "feedback.duration_s", "greater than 0"),
        ({"practice": {"trials": 0}}, "practice.trials", "greater than or equal to 1"),
        ({"practice": {"trials": 2, "conditions": ["fast"]}}, "practice", "no condition 'fast'"),
        ({"practice": {"trials": 2, "ratios": [1e6]}}, "practice", "ratios: the comparison"),
        ({"instructions": {"text": "a\x00b"}}, "instructions.text", "printable"),
        ({"instructions": {"text": "x" * 2001}}, "instructions.text", "2000"),
    ],
)
def test_bad_screen_keys_are_refused_naming_key_and_line(tmp_path, sections, key, expect):
    path = write_exp(tmp_path, **sections)
    with pytest.raises(ExperimentError) as exc:
        load_experiment(path)
    msg = str(exc.value)
    assert f"  {key}:" in msg and expect in msg, msg
    assert f"line {line_of(path, key.split('.')[0])}" in msg or "line " in msg, msg


def test_practice_trials_are_planned_apart_from_the_session():
    exp = rn.reduced(load_experiment(STIFFNESS), standards=[60.0], repetitions=1)
    exp = exp.model_validate(
        {**exp.model_dump(), "practice": {"trials": 5, "conditions": ["pinv"]}}
    ).model_copy(update={"source": exp.source, "file_hash": exp.file_hash})
    practice = make_practice(exp, 7)
    assert practice == make_practice(exp, 7) and make_plan(exp, 7)[0].index == 0
    assert [t.index for t in practice] == [-5, -4, -3, -2, -1]
    assert all(t.practice and t.block == -1 and t.condition == "pinv" for t in practice)
    # The design's easiest levels: its farthest comparisons.
    assert {t.ratio for t in practice} == {min(exp.varied.ratios), max(exp.varied.ratios)}
    assert not any(t.practice for t in make_plan(exp, 7))


# -- practice in the store, resumed, never analysed -----------------------------------------


def test_practice_is_stored_flagged_resumed_and_never_analysed(tmp_path):
    base = rn.reduced(load_experiment(STIFFNESS), standards=[60.0], repetitions=1)
    exp = base.model_validate({**base.model_dump(), "practice": {"trials": 3}}).model_copy(
        update={"source": base.source, "file_hash": base.file_hash}
    )
    seed = exp.subject_seed("s1")
    db = tmp_path / "t.db"
    with TrialStore.for_experiment(db, exp) as store:
        rn.start_subject(store, exp, "s1", seed, resume=False)
        with pytest.raises(rn.TrialAbortedError):  # stopped in the second practice trial
            rn.run_practice(store, exp, "s1", seed, Scripted(abort_at=-2), profile_hash="p")
        # A run stopped in its practice resumes; the answered practice trial is kept.
        rn.check_start(store, "s1", resume=True)
        again = Scripted()
        assert rn.run_practice(store, exp, "s1", seed, again, profile_hash="p") == 2
        assert [i for i, _, _ in again.seen] == [-2, -1]
        assert rn.run_practice(store, exp, "s1", seed, Scripted(), profile_hash="p") == 0
        rn.run_subject(store, exp, "s1", seed, Scripted(), profile_hash="p")
        assert store.remaining("s1") == [] and store.remaining("s1", practice=True) == []
        assert all(not r["practice"] for r in store.trials(None))
        everything = store.trials(None, practice=True)
    practice = [r for r in everything if r["practice"]]
    assert [(r["plan_index"], r["status"]) for r in practice] == [
        (-3, "complete"),
        (-2, "incomplete"),
        (-2, "complete"),
        (-1, "complete"),
    ]
    # The export's reader sees every trial with its flag; the analysis leaves practice out.
    _, rows = open_for_analysis(db, None)
    assert sum(bool(r["practice"]) for r in rows) == 4
    complete = [r for r in rows if r["status"] == "complete"]
    session = [r for r in complete if not r["practice"]]
    fits = analyze(complete, n_boot=0)["fits"]
    assert [f["n_trials"] for f in fits] == [
        f["n_trials"] for f in analyze(session, n_boot=0)["fits"]
    ]
    assert sum(f["n_trials"] for f in fits) == len(make_plan(exp, seed))
    assert failed_trials([{**practice[0], "failure": "x"}])["n"] == 0


# -- the daemon's screen command -------------------------------------------------------------

GOOD = {"state": "break", "text": "Break", "seconds": 12.5, "progress": [3, 24], "scene": False}


@pytest.mark.parametrize(
    "screen",
    [
        {"text": "no state"},
        {**GOOD, "state": "stiffer"},
        {**GOOD, "text": "x" * 2001},
        {**GOOD, "text": "bell\x07"},
        {**GOOD, "text": 5},
        {**GOOD, "practice": "yes"},
        {**GOOD, "scene": 0},
        {**GOOD, "progress": [4, 3]},
        {**GOOD, "progress": [1, True]},
        {**GOOD, "progress": [1]},
        {**GOOD, "seconds": -1},
        {**GOOD, "seconds": 1e9},
        {**GOOD, "seconds": "5"},
        {**GOOD, "condition": "pinv"},
        "touch",
    ],
)
def test_malformed_screens_are_refused(screen):
    with pytest.raises(proto.ProtocolError) as err:
        proto.check({"cmd": "screen", "screen": screen})
    assert err.value.code in ("bad_value", "out_of_range")


def test_a_screen_is_shown_in_the_status_announced_and_cleared(idle_server):
    with ControlClient(idle_server.path) as c, ControlClient(idle_server.path) as watcher:
        watcher.events_subscribe(["screen"])
        assert c.status()["screen"] is None
        c.screen({**GOOD, "text": TEXT})
        assert c.status()["screen"] == {**GOOD, "text": TEXT}
        assert watcher.next_event(5.0)["event"] == "screen"
        c.screen(None)
        assert c.status()["screen"] is None
        assert c.request("screen")["error"]["code"] == "bad_request"


def test_the_instructions_stay_until_the_subject_is_ready_and_practice_is_marked(idle_server):
    """A person's presenter: the file's instructions on the screen, asked "ready?" again
    after a no; a practice trial's states marked practice, with the progress and the scene
    hidden as the display asks; the end; a stopped run's screen withdrawn."""
    exp = load_experiment(
        write_exp(
            idle_server.path.parent,
            instructions={"text": TEXT},
            display={"scene": False, "progress": True},
        )
    )
    answers = iter(["no", "yes"])
    shown: list[dict] = []
    with ControlClient(idle_server.path) as subject:
        subject.events_subscribe(["prompt", "screen"])
        p = rn.PersonPresenter(ControlClient(idle_server.path), subject="s1", out=io.StringIO())

        def answer() -> None:
            for _ in range(200):  # bounded: the presenter asks twice
                try:
                    ev = subject.next_event(0.1)
                except TimeoutError:
                    continue
                if ev["event"] == "screen":
                    shown.append(subject.status()["screen"])
                elif ev["event"] == "prompt" and ev["prompt"] is not None:
                    assert ev["prompt"] == rn.INSTRUCTIONS_PROMPT
                    subject.respond(ev["prompt"], next(answers, "yes"))
                    if not list(answers):
                        return

        helper = threading.Thread(target=answer, name="test-subject")
        helper.start()
        p.begin(exp)
        helper.join(timeout=10)
        practice = dataclasses.replace(make_plan(exp, 1)[0], practice=True, index=-1)
        p.note_progress(rn.Progress(0, 1, practice, 0.0))
        p._practice = practice.practice
        p.show("touch")
        touch = subject.status()["screen"]
        p.finish()
        end = subject.status()["screen"]
        p.finished = False
        p.clear_screen()
        assert subject.status()["screen"] is None
        p.client.close()
    assert [s["state"] for s in shown[:2]] == ["instructions", "instructions"]
    assert shown[0]["text"] == TEXT and shown[0]["scene"] is False
    assert touch == {
        "state": "touch",
        "text": rn.SCREEN_TEXT["touch"],
        "practice": True,
        "scene": False,
        "progress": [1, 1],
    }
    assert end["state"] == "end" and not end["practice"] and "progress" not in end


# -- what the subject's page receives --------------------------------------------------------

# Words that would tell the subject the condition or the values (the condition's names,
# the parameters, the allocators): none reaches the subject's page.
LEAKS = ("allocator", "stiffness", "force", "device_pos", "mass", "pinv", "ef", "60")


def test_the_subjects_page_gets_the_screens_words_only_and_no_scene_when_hidden(fake):
    """A screen that somehow carries more than its words (a client's extra key): the
    subject's page gets only the text states; with the scene hidden it gets no telemetry
    and no geometry at all, while the experimenter's page still sees everything."""
    fake.screen = {"state": "touch", "text": "Touch the object", "practice": True}
    with ViewServer(fake.path, log=lambda m: None) as v:
        port = v.address[1]
        with ws_connect(port, v.key, "subject") as subj:
            events = ws_events(subj, lambda ev: len(ticks_of(ev)) >= 2 and statuses(ev))
            assert statuses(events)[-1]["screen"] == fake.screen
            assert statuses(events)[-1]["scene"]["bounds_m"]  # drawn while shown
            fake.screen = {
                "state": "break",
                "text": "Break",
                "seconds": 4.0,
                "progress": [3, 6],
                "scene": False,
                "allocator": "pinv",  # what no daemon sends: the view passes it on to no one
                "stiffness_n_per_m": 60.0,
            }
            want = {"state": "break", "text": "Break", "seconds": 4.0, "progress": [3, 6]}
            hidden = ws_events(
                subj,
                lambda ev: bool(statuses(ev)) and statuses(ev)[-1]["screen"].get("seconds"),
            )
            after = len(hidden)
            # A second of telemetry at 60 Hz, none of it to the subject now.
            with ws_connect(port, v.key) as page:
                seen = ws_events(
                    page,
                    lambda ev: (
                        len(ticks_of(ev)) >= 20
                        and any(s["screen"] and s["screen"].get("seconds") for s in statuses(ev))
                    ),
                )
                ws_events(subj, lambda ev: len(statuses(ev)) >= 2, events=[])
        last = statuses(hidden)[-1]
    assert last["screen"] == {**want, "scene": False}
    assert last["scene"] == {} and set(last) == {"fingers", "scene", "prompt", "screen"}
    assert not ticks_of(hidden[after:])
    assert "pinv" in json.dumps(seen)  # the experimenter's page is told everything
    blob = json.dumps(events + hidden)
    for word in LEAKS:
        assert f'"{word}' not in blob and f'{word}"' not in blob, word


@pytest.fixture
def fake(tmp_path):
    from tests.fake_daemon import FakeDaemon

    with FakeDaemon(tmp_path / "fake.sock") as f:
        yield f


# -- the whole run, answered on the subject's page in headless Chromium ----------------------

SCREEN_SEEN = "document.querySelector('[data-testid=screen]').dataset.seen || ''"
SCREEN_STATE = (
    "(() => { const s = document.querySelector('[data-testid=screen]'); "
    "return s.hidden ? null : [s.dataset.state, s.innerText]; })()"
)
PROMPT = (
    "(() => { const p = document.querySelector('[data-testid=prompt]'); "
    "return p.hidden ? null : document.getElementById('prompt-question').textContent; })()"
)


class Stamped(io.StringIO):
    """The runner's lines, each with the time it was written."""

    def write(self, text: str) -> int:
        import time

        return super().write(f"{time.monotonic():.2f} {text}")


class MarkerLog:
    """The daemon's LSL marker stream, pulled in a thread until closed: (stamp, event)."""

    def __init__(self, name: str) -> None:
        import pylsl

        found = pylsl.resolve_byprop("name", name, timeout=20.0)
        assert len(found) == 1, f"marker stream {name} not found"
        self.inlet: pylsl.StreamInlet | None = pylsl.StreamInlet(found[0], recover=False)
        self.inlet.open_stream(timeout=20.0)
        self.got: list[tuple[float, dict]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pull, name="test-markers")
        self._thread.start()

    def _pull(self) -> None:
        while not self._stop.is_set():
            data, stamps = self.inlet.pull_chunk(timeout=0.05)
            self.got += [(t, json.loads(m[0])) for m, t in zip(data, stamps, strict=True)]

    def wait_for(self, event: str, count: int) -> None:
        wait_for(
            lambda: sum(e["event"] == event for _, e in self.got),
            f"{count} {event} marker(s)",
            until=lambda n: n >= count,
            timeout_s=20,
        )

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        # liblsl's sockets close when the inlet is destroyed: no reference may be left.
        self.inlet.close_stream()
        self.inlet = None


@pytest.mark.timing("the subject grasps on a clock: every state is shown as the run goes")
def test_the_reduced_experiment_is_answered_on_the_subjects_page(tmp_path, chromium):
    """The reduced stiffness experiment (one condition, 3 comparisons, once each) with
    instructions, one practice trial, feedback, a break, the progress and the scene hidden,
    against a daemon publishing its LSL streams (as ``hapticd run --lsl``) whose hand
    grasps every 0.5 s: every answer, the instructions' "ready" too, is a click on the
    subject's page, which shows the instructions, touch, release, answer, feedback, the
    break's countdown and the end; the store holds the practice trial flagged and the
    session's trials answered as clicked; an LSL inlet receives every trial's and
    interval's marker, the prompts, the answers and the contacts, each stamped with its
    tick's time in the interval's recording, and the export's LSL onsets bracket them."""
    import uuid

    profile, exp_path = setup_files(tmp_path, one_condition=True)
    # A longer rest between grasps than the runner tests' (0.3 s of 0.65 s): every change
    # of the object lands while it is released, the first time.
    traj = periodic_grasp(tmp_path / "rest.hrec", 100, times=(0.1, 0.15, 0.1, 0.3))
    prof = yaml.safe_load(profile.read_text())
    prof["name"] = f"screen-{uuid.uuid4().hex[:8]}"  # its own LSL streams (xdist workers)
    for f in prof["fingers"]:
        f["device"]["trajectory"] = str(traj)
    profile.write_text(yaml.safe_dump(prof, sort_keys=False))
    data = yaml.safe_load(exp_path.read_text())
    data.update(
        instructions={"text": TEXT},
        practice={"trials": 1},
        feedback={"after": "all", "duration_s": 0.2},
        display={"scene": False, "progress": True},
        breaks={"every_blocks": 1, "every_trials": 2, "duration_s": 2.0},
    )
    exp_path.write_text(yaml.safe_dump(data, sort_keys=False))
    exp = rn.reduced(load_experiment(exp_path), standards=[60.0], repetitions=1)
    sock, db = tmp_path / "d.sock", tmp_path / "t.db"
    out = Stamped()
    result: dict = {}

    def run() -> None:
        try:
            result["done"] = rn.run_experiment(
                exp, "s1", db, options=rn.RunOptions(socket=sock, out=out)
            )
        except Exception as exc:  # the test reports it
            result["error"] = exc

    from hapticd.daemon import lsl

    clicks: dict[str, list[str]] = {}
    countdown: list[str] = []
    with (
        running_daemon(sock, profile, lsl=True),
        ViewServer(sock, log=lambda m: None) as view,
        cdp.Browser(chromium, tmp_path / "chromium") as browser,
    ):
        markers = MarkerLog(lsl.stream_name(prof["name"]) + "-markers")
        try:
            browser.open(view.subject_url)
            wait_for(lambda: browser.evaluate("document.body.className"), "the page", until=bool)
            runner = threading.Thread(target=run, name="test-runner")
            runner.start()
            try:
                # 1 "ready" + 1 practice trial + 3 trials: each question answered by a click.
                for n in range(5):
                    question = wait_for(
                        lambda: browser.evaluate(PROMPT),
                        f"question {n + 1} on the subject's page",
                        until=lambda q: q is not None and q not in clicks.get("_last", []),
                        timeout_s=30,
                    )
                    if n == 0:
                        assert question == rn.READY
                        state = browser.evaluate(SCREEN_STATE)
                        assert state[0] == "instructions" and TEXT.replace("\n", "") in state[
                            1
                        ].replace("\n", "")
                    choice = "yes" if n % 2 == 0 else "no"
                    browser.click(f"[data-testid=answer-{choice}]")
                    clicks.setdefault("choices", []).append(choice)
                    clicks["_last"] = [question]
                    wait_for(
                        lambda: browser.evaluate(PROMPT),
                        "the question to go",
                        until=lambda q: q is None,
                        timeout_s=10,
                    )
                    clicks["_last"] = []
                    if n == 3:  # the break after the session's second trial
                        wait_for(
                            lambda: browser.evaluate(SCREEN_STATE),
                            "the break",
                            until=lambda s: s is not None and s[0] == "break",
                            timeout_s=20,
                        )
                        for _ in range(2):
                            countdown.append(browser.evaluate(SCREEN_STATE)[1])
                            wait_for(
                                lambda: browser.evaluate(SCREEN_STATE),
                                "the countdown to move",
                                until=lambda s, was=countdown[-1]: s is None or s[1] != was,
                                timeout_s=5,
                            )
                runner.join(timeout=30)
                assert not runner.is_alive(), "the run did not end"
                assert "error" not in result, f"{result.get('error')}\n{out.getvalue()[-2000:]}"
                end = wait_for(
                    lambda: browser.evaluate(SCREEN_STATE),
                    "the end on the subject's page",
                    until=lambda s: s is not None and s[0] == "end",
                )
                seen = browser.evaluate(SCREEN_SEEN).split()
                canvas = browser.evaluate(
                    "document.querySelector('[data-testid=scene]').dataset.scene"
                )
                text = browser.evaluate("document.documentElement.textContent")
                markers.wait_for("mark", 4 * 8)  # per trial: start, 2 x (set, start, end), end
                markers.wait_for("response", 5)
            finally:
                runner.join(timeout=30)
        finally:
            markers.close()
    assert "error" not in result, f"{result.get('error')}\n{out.getvalue()[-2000:]}"
    assert result["done"] == (3, 0)
    assert end[1] == rn.SCREEN_TEXT["end"]
    with TrialStore.for_experiment(db, exp) as store:
        rows = store.trials(None, practice=True)
    assert seen[0] == "instructions"
    assert "touch:practice" in seen and "answer:practice" in seen, seen  # marked as practice
    states = [s.split(":")[0] for s in seen]
    for state in ("touch", "release", "answer", "break", "end"):
        assert state in seen, (state, seen)
    # The break's countdown goes down on the subject's page.
    secs = [int(re.search(r"\d+", c).group()) for c in countdown]
    assert secs[0] > secs[1], countdown
    # Feedback where a trial has a correct answer (its comparison is not the standard).
    assert states.count("feedback") == sum(r["comparison"] != r["standard"] for r in rows)
    assert canvas == "hidden"
    # Nothing in the subject's document names the condition or a value.
    for name in params.ALLOCATORS:
        assert not re.search(rf"\b{re.escape(name)}\b", text), name
    assert not re.search(r"\d\s*N\b|N/m|\b(48|60|72)\b", text), text
    assert sorted(r["practice"] for r in rows) == [0, 0, 0, 1]
    session = [r for r in rows if not r["practice"]]  # in the order stored: answered
    yes = [c == "yes" for c in clicks["choices"][2:]]
    assert [bool(r["answer_second_more"]) for r in session] == yes
    assert all(r["source"] == "respond" and r["status"] == "complete" for r in rows)
    _markers_line_up(markers.got, rows, tmp_path)
    with contextlib.suppress(OSError):
        sock.unlink()


def _markers_line_up(got: list[tuple[float, dict]], rows: list[dict], tmp_path: Path) -> None:
    """Every trial's and interval's marker, the prompts, the answers and both fingers'
    contacts reached the inlet; a marker at a tick an interval recorded is stamped with
    that tick's time (the recording's LSL anchor plus its t_wall); the export's LSL onset
    of each interval comes before its interval_start marker, and its end after."""
    from hapticd import recording
    from hapticd.experiment.export import interval_stats

    events = [e["event"] for _, e in got]
    texts = [e["text"].split()[0] for _, e in got if e["event"] == "mark"]
    for kind, count in (("trial_start", 4), ("condition_set", 8), ("interval_start", 8)):
        assert texts.count(kind) == count, (kind, texts)
    assert texts.count("interval_end") == 8 and texts.count("trial_end") == 4, texts
    assert events.count("prompt") >= 5 and events.count("response") == 5, events
    for kind in ("contact_begin", "contact_end"):
        fingers = {e.get("finger_name") for _, e in got if e["event"] == kind}
        assert fingers == {"thumb", "index"}, (kind, fingers)
    checked = 0
    for r in rows:
        for path in json.loads(r["recording"]):
            rec = recording.read(path)
            lsl0, ticks = rec.clock["lsl_s"], rec["tick"].astype(int).tolist()
            row_of = {k: i for i, k in enumerate(ticks)}
            for stamp, e in got:
                if e.get("tick") in row_of:
                    want = lsl0 + rec["t_wall"][row_of[e["tick"]]]
                    assert stamp == pytest.approx(want, abs=1e-6), e
                    checked += 1
            stats = interval_stats(rec)
            onset, span = stats["onset_lsl_s_K"], stats["duration_s_K"]
            starts = [
                t
                for t, e in got
                if e["event"] == "mark"
                and e["text"].startswith("interval_start")
                and onset <= t <= onset + span
            ]
            assert len(starts) == 1, (path, onset, span)
    assert checked >= 8, checked
