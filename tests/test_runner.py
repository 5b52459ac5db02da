"""The subject prompt (prompt, respond, their events) and the experiment runner against a
real daemon: answers by respond, by keys and by device buttons, the rows stored, the
parameters applied, kill -9 and --resume, the daemon going away mid-trial."""

from __future__ import annotations

import dataclasses
import json
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from hapticd import protocol as proto
from hapticd import recording
from hapticd.control import ControlClient
from hapticd.experiment import load_experiment, make_plan
from hapticd.experiment import runner as rn
from hapticd.experiment.store import StoreError, TrialStore
from tests.conftest import GRASP_PROFILE, ROOT, fill_every_place, wait_for

# The periodic grasp: both fingers from 4.5 cm out to 2 cm of the cube's centre (it is
# 5 cm wide, fingertips 8 mm: contact inside 3.3 cm), held, and back; one cycle a PERIOD_S.
PERIOD_S = 0.5
OUT_M, IN_M = 0.045, 0.020
TIMES = (0.1, 0.2, 0.1, 0.1)  # in, hold, out, rest (s)


def periodic_grasp(path: Path, cycles: int, *, button_at: float | None = None, times=TIMES) -> Path:
    """A two-finger trajectory of ``cycles`` grasps and releases (sampled at 200 Hz);
    with ``button_at`` (s into each cycle, while released) button 0 of the index finger
    is down for 0.1 s once per cycle. ``times``: in, hold, out, rest (s)."""
    rate = 200.0
    period = sum(times)
    n = int(cycles * period * rate) + 1
    t = np.arange(n) / rate
    phase = np.mod(t, period)
    a, b, c, _ = times
    s = np.clip(phase / a, 0, 1)
    s = np.where(
        phase < a, s, np.where(phase < a + b, 1.0, 1.0 - np.clip((phase - a - b) / c, 0, 1))
    )
    smooth = s**3 * (10 - 15 * s + 6 * s * s)
    x = OUT_M + (IN_M - OUT_M) * smooth
    pos = np.zeros((n, 2, 3))
    pos[:, 0, 0], pos[:, 1, 0] = -x, x
    fields = recording.trajectory_fields(2)
    arrays = {"t": t, "device_pos": pos}
    if button_at is not None:
        down = ((phase >= button_at) & (phase < button_at + 0.1)).astype(np.uint32)
        arrays["buttons"] = np.stack([np.zeros(n, np.uint32), down], axis=1)
        fields = [*fields, recording.Field("buttons", "<u4", (2,))]
    recording.write(path, arrays, fields, ["thumb", "index"])
    return path


# -- the subject prompt on the daemon ---------------------------------------------------------


@pytest.fixture
def server(idle_server):
    return idle_server


def _error(client: ControlClient, **req) -> dict:
    reply = client.request(req.pop("cmd"), **req)
    assert reply["ok"] is False, reply
    return reply["error"]


def test_a_prompt_is_shown_answered_once_and_cleared(server):
    with ControlClient(server.path) as watcher, ControlClient(server.path) as c:
        watcher.events_subscribe(["prompt", "response"])
        assert c.status()["prompt"] is None
        assert _error(c, cmd="respond", prompt=3, choice="yes")["code"] == "no_prompt"
        before = c.request("get", param="mass_kg")["id"]  # the client numbers its requests
        reply = c.request(
            "prompt", prompt=3, question="Was the second cube stiffer?", choices=["no", "yes"]
        )
        # The request's own id stays the client's (replies are matched by it), not the
        # prompt's (3).
        assert before + 1 != 3 and reply == {"id": before + 1, "ok": True, "result": {}}
        want = {"id": 3, "question": "Was the second cube stiffer?", "choices": ["no", "yes"]}
        assert c.status()["prompt"] == want
        assert watcher.next_event(5)["prompt"] == 3
        # Another id, or a choice the prompt does not offer: refused, the prompt stays.
        assert _error(c, cmd="respond", prompt=4, choice="yes")["code"] == "no_prompt"
        assert _error(c, cmd="respond", prompt=3, choice="maybe")["code"] == "bad_value"
        assert c.status()["prompt"] == want
        c.respond(3, "yes")
        ev = watcher.next_event(5)
        assert (ev["event"], ev["prompt"], ev["choice"]) == ("response", 3, "yes")
        assert c.status()["prompt"] is None
        assert _error(c, cmd="respond", prompt=3, choice="yes")["code"] == "no_prompt"
        # A new prompt replaces the current one; clearing emits a prompt event with null.
        c.prompt(5, "Heavier?", ["a", "b", "c"])
        c.prompt(6, "Heavier?", ["no", "yes"])
        assert [watcher.next_event(5)["prompt"] for _ in range(2)] == [5, 6]
        assert _error(c, cmd="respond", prompt=5, choice="a")["code"] == "no_prompt"
        c.clear_prompt()
        ev = watcher.next_event(5)
        assert ev["event"] == "prompt" and ev["prompt"] is None and "tick" in ev and "t" in ev
        assert c.status()["prompt"] is None
        with pytest.raises(TimeoutError):
            watcher.next_event(0.2)  # the refused requests made no event


GOOD = {"cmd": "prompt", "prompt": 1, "question": "Stiffer?", "choices": ["no", "yes"]}


@pytest.mark.parametrize(
    "change, code",
    [
        ({"prompt": "7"}, "bad_value"),
        ({"prompt": -1}, "bad_value"),
        ({"prompt": True}, "bad_value"),
        ({"prompt": 1.5}, "bad_value"),
        ({"question": ""}, "bad_value"),
        ({"question": "x" * 201}, "bad_value"),
        ({"question": "two\nlines"}, "bad_value"),
        ({"question": 5}, "bad_value"),
        ({"question": None}, "bad_value"),
        ({"choices": ["yes"]}, "bad_value"),
        ({"choices": ["a", "b", "c", "d", "e"]}, "bad_value"),
        ({"choices": ["yes", "yes"]}, "bad_value"),
        ({"choices": ["No", "yes"]}, "bad_value"),
        ({"choices": ["no", "a" * 17]}, "bad_value"),
        ({"choices": ["no", ""]}, "bad_value"),
        ({"choices": ["no", 1]}, "bad_value"),
        ({"choices": "no,yes"}, "bad_value"),
        ({"choices": None}, "bad_value"),
    ],
)
def test_malformed_prompts_are_refused_naming_the_argument(change, code):
    with pytest.raises(proto.ProtocolError) as err:
        proto.check({**GOOD, **change})
    assert err.value.code == code
    key = next(iter(change))
    assert (key if key != "prompt" else "'prompt'") in str(err.value)


@pytest.mark.parametrize(
    "req, code",
    [
        ({"cmd": "prompt", "question": "Stiffer?", "choices": ["no", "yes"]}, "bad_request"),
        ({"cmd": "respond", "choice": "yes"}, "bad_request"),
        ({"cmd": "respond", "prompt": None, "choice": "yes"}, "bad_value"),
        ({"cmd": "respond", "prompt": 1}, "bad_value"),
        ({"cmd": "respond", "prompt": 1, "choice": "YES"}, "bad_value"),
        ({"cmd": "respond", "prompt": 1, "choice": ["yes"]}, "bad_value"),
        ({"cmd": "respond", "prompt": "1", "choice": "yes"}, "bad_value"),
    ],
)
def test_malformed_responses_and_prompts_without_an_id(req, code):
    with pytest.raises(proto.ProtocolError) as err:
        proto.check(req)
    assert err.value.code == code


def test_malformed_prompt_lines_get_error_replies_and_change_nothing(server):
    raw = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)  # lines no client would send
    raw.settimeout(10)
    with ControlClient(server.path) as c, raw, raw.makefile("rb") as replies:
        c.prompt(2, "Stiffer?", ["no", "yes"])
        raw.connect(str(server.path))
        assert "protocol" in json.loads(replies.readline())  # the greeting
        for line in (
            b'{"cmd":"prompt","prompt":3,"question":"","choices":["no","yes"]}\n',
            b'{"cmd":"prompt","prompt":3,"question":"q","choices":[[[["x"]]]]}\n',
            b'{"cmd":"respond","prompt":2,"choice":null}\n',
            b'{"cmd":"respond","prompt":2,"choice":"yes","extra":NaN}\n',
        ):
            raw.sendall(line)
            reply = json.loads(replies.readline())
            assert reply["ok"] is False and reply["error"]["code"] in ("bad_value", "malformed")
        assert c.status()["prompt"]["id"] == 2
        assert c.prompt(2, "Stiffer?", ["no", "yes"]) == {}


# -- walking a plan with a scripted presenter ---------------------------------------------------

STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"


class Scripted:
    """A presenter answering "yes" when the second interval held more, checking what it is
    given; ``abort_at``: the plan index whose presentation fails."""

    def __init__(self, abort_at: int | None = None) -> None:
        self.seen: list[tuple[int, dict, tuple[float, float]]] = []
        self.rests: list[float] = []
        self.abort_at = abort_at

    def present(self, exp, trial, params):
        if trial.index == self.abort_at:
            raise rn.TrialAbortedError("the daemon went away", ["a.hrec"])
        first, second = rn.interval_values(exp, trial)
        self.seen.append((trial.index, dict(params), (first, second)))
        return rn.Presented(second > first, 0.5 + trial.index, (f"{trial.index}.hrec",))

    def rest(self, seconds):
        self.rests.append(seconds)


def test_run_subject_presents_what_is_left_and_stores_each_trial(tmp_path):
    exp = rn.reduced(load_experiment(STIFFNESS), standards=[60.0], repetitions=2)
    seed = exp.subject_seed("s1")
    plan = make_plan(exp, seed)
    assert len(plan) == 2 * 6 * 2
    with TrialStore.for_experiment(tmp_path / "t.db", exp) as store:
        todo = rn.start_subject(store, exp, "s1", seed, resume=False)
        assert todo == plan
        failing = Scripted(abort_at=5)
        with pytest.raises(rn.TrialAbortedError):
            rn.run_subject(store, exp, "s1", seed, failing, profile_hash="p")
        rows = store.trials(None)
        assert [r["status"] for r in rows] == ["complete"] * 5 + ["incomplete"]
        assert rows[-1]["recording"] == '["a.hrec"]' and rows[-1]["answer_second_more"] is None
        with pytest.raises(StoreError, match="--resume"):
            rn.start_subject(store, exp, "s1", seed, resume=False)
        with pytest.raises(StoreError, match="same seed"):
            rn.start_subject(store, exp, "s1", seed + 1, resume=True)
        assert rn.start_subject(store, exp, "s1", seed, resume=True) == plan[5:]
        lines = []
        again = Scripted()
        n = rn.run_subject(
            store, exp, "s1", seed, again, profile_hash="p", progress=lambda p: lines.append(p)
        )
        assert n == len(plan) - 5 and store.remaining("s1") == []
        rows = store.trials()
    assert sorted(r["plan_index"] for r in rows) == list(range(len(plan)))
    for idx, got, (first, second) in again.seen:
        t = plan[idx]
        cond = next(c for c in exp.conditions if c.name == t.condition)
        assert got == cond.values()
        assert {first, second} == {t.standard, t.comparison}
        assert (first == t.comparison) == t.comparison_first or t.comparison == t.standard
    for r in rows:
        assert r["comparison_more"] == int(r["comparison"] > r["standard"]) or (
            r["comparison"] == r["standard"]
        )
        assert r["response_time_s"] == 0.5 + r["plan_index"]
        assert json.loads(r["recording"]) == [f"{r['plan_index']}.hrec"]
    # A break before the second block (the file's 60 s), the progress counting up to the end.
    assert again.rests == [t.break_before_s for t in plan[5:] if t.break_before_s > 0] == [60.0]
    assert [p.done for p in lines] == list(range(5, len(plan) + 1))
    assert lines[0].line().startswith(f"trial 6 of {len(plan)} · block 1")
    assert lines[-1].trial is None and lines[-1].left_s == 0.0


def test_start_subject_refusals(tmp_path):
    exp = rn.reduced(load_experiment(STIFFNESS), standards=[30.0], repetitions=1)
    with TrialStore.for_experiment(tmp_path / "t.db", exp) as store:
        with pytest.raises(StoreError, match="nothing to resume"):
            rn.start_subject(store, exp, "s2", 1, resume=True)
        with pytest.raises(ValueError, match="subject id"):
            rn.start_subject(store, exp, "../x", 1, resume=False)
    with pytest.raises(ValueError, match="repetitions"):
        rn.reduced(exp, repetitions=0)
    with pytest.raises(ValueError, match="range"):
        rn.reduced(exp, standards=[1e9])
    with pytest.raises(ValueError, match="duration_s"):
        rn.reduced(exp, break_s=-1.0)


def test_a_shorter_break_keeps_the_plan():
    exp = load_experiment(STIFFNESS)
    short = rn.reduced(exp, break_s=2.0)
    assert short.breaks.duration_s == 2.0 and exp.breaks.duration_s == 60.0
    assert short.n_breaks() == exp.n_breaks() >= 1
    # The same trials in the same order; only the breaks before some are shorter.
    a, b = make_plan(short, 7), make_plan(exp, 7)
    assert [dataclasses.replace(t, break_before_s=0.0) for t in a] == [
        dataclasses.replace(t, break_before_s=0.0) for t in b
    ]
    assert [t.break_before_s for t in b if t.break_before_s] == [60.0] * exp.n_breaks()
    assert [t.break_before_s for t in a if t.break_before_s] == [2.0] * exp.n_breaks()


# -- the runner against a real daemon -----------------------------------------------------------

HAPTICD = [sys.executable, "-m", "hapticd"]
RATIOS = [0.8, 1.0, 1.2]  # 3 comparisons x 2 conditions x 1 repetition: 6 trials


def setup_files(
    tmp_path: Path, *, buttons: bool = False, one_condition: bool = False
) -> tuple[Path, Path]:
    """A calm grasp profile on the periodic grasp (with the index finger's button 0 a
    ``yes`` response key pressed once a cycle when ``buttons``) recording into
    tmp_path/recs, and a short stiffness experiment on it (``one_condition``: pinv
    only): (profile, experiment)."""
    traj = periodic_grasp(tmp_path / "grasp.hrec", 150, button_at=0.42 if buttons else None)
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    for f in data["fingers"]:
        f["device"]["trajectory"] = str(traj)
    if buttons:
        data["fingers"][1]["buttons"] = [{"button": 0, "role": "response", "label": "yes"}]
    # A shared 2-core machine can stall a paced loop for 100 ms: no wall-clock faults here.
    data["safety"]["watchdog_s"] = None
    data.setdefault("loop", {})["max_consecutive_overruns"] = 0
    data["loop"]["spin_s"] = 0  # nothing here measures periods: no spinning beside the suite
    (tmp_path / "recs").mkdir()
    data["recording"] = {"directory": str(tmp_path / "recs")}
    profile = tmp_path / "profile.yaml"
    profile.write_text(yaml.safe_dump(data, sort_keys=False))
    exp = yaml.safe_load(STIFFNESS.read_text())
    exp["profile"] = "profile.yaml"
    exp["varied"]["ratios"] = RATIOS
    exp["interval"].update(gap_s=0.1, exploration_s=1.0)
    exp["breaks"] = {"every_blocks": 1, "duration_s": 0.3}
    if one_condition:
        exp["conditions"] = exp["conditions"][1:]
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(exp, sort_keys=False))
    return profile, path


class Daemon:
    """``hapticd run PROFILE`` in a subprocess serving ``sock``."""

    def __init__(self, profile: Path, sock: Path) -> None:
        self.sock = sock
        self.log = open(sock.with_suffix(".log"), "w")  # noqa: SIM115
        self.proc = subprocess.Popen(
            [*HAPTICD, "run", str(profile), "--socket", str(sock)],
            stdout=self.log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
        )
        wait_for(self._ready, "the daemon's socket", timeout_s=30)

    def _ready(self) -> bool:
        assert self.proc.poll() is None, sock_log(self.sock)
        try:
            with ControlClient(self.sock, timeout_s=2.0) as c:
                return c.status()["tick"] > 0
        except OSError:
            return False

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


def sock_log(sock: Path) -> str:
    return sock.with_suffix(".log").read_text()[-2000:]


@pytest.fixture
def daemons():
    made: list[Daemon] = []

    def start(profile: Path, sock: Path) -> Daemon:
        made.append(Daemon(profile, sock))
        return made[-1]

    yield start
    for d in made:
        d.close()


# ``python -m hapticd`` with Ctrl-C's default meaning: a suite started as a background job
# (``pytest &``) passes SIGINT on ignored, and Python then installs no KeyboardInterrupt.
INTERRUPTIBLE = [
    sys.executable,
    "-c",
    "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "sys.argv[0] = 'hapticd'; runpy.run_module('hapticd', run_name='__main__')",
]


def runner(
    exp: Path,
    db: Path,
    sock: Path,
    *extra: str,
    stdin=subprocess.DEVNULL,
    interruptible: bool = False,
) -> subprocess.Popen:
    """``hapticd experiment run`` of subject s1, the reduced design, in a subprocess; its
    output in files next to the store (stdin a pipe the test may type into;
    ``interruptible``: SIGINT is Ctrl-C whatever the suite's own SIGINT is)."""
    args = ["experiment", "run", str(exp), "--subject", "s1", "--db", str(db)]
    args += ["--socket", str(sock), "--standards", "60", "--repetitions", "1", *extra]
    cmd = [*(INTERRUPTIBLE if interruptible else HAPTICD), *args]
    with open(db.with_suffix(".out"), "w") as out, open(db.with_suffix(".err"), "w") as err:
        proc = subprocess.Popen(cmd, stdin=stdin, stdout=out, stderr=err, text=True, cwd=ROOT)
    proc.db = db  # type: ignore[attr-defined]
    return proc


def finish(proc: subprocess.Popen, timeout_s: float = 60) -> tuple[int, str, str]:
    """Wait for the runner (fail at ``timeout_s``): exit code, stdout, stderr."""
    db = proc.db  # type: ignore[attr-defined]
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    finally:
        if proc.stdin is not None:
            proc.stdin.close()
    out, err = db.with_suffix(".out").read_text(), db.with_suffix(".err").read_text()
    if proc.returncode == -signal.SIGKILL and timeout_s:
        pytest.fail(f"the runner did not finish within {timeout_s} s:\n{err[-3000:]}")
    return proc.returncode, out, err


def rows(db: Path, status: str | None = None) -> list[dict]:
    con = sqlite3.connect(db)
    con.row_factory = sqlite3.Row
    try:
        where, args = ("WHERE status = ?", (status,)) if status else ("", ())
        return [dict(r) for r in con.execute(f"SELECT * FROM trials {where} ORDER BY id", args)]
    except sqlite3.OperationalError:
        return []  # not created yet
    finally:
        con.close()


class Answerer:
    """Answers each prompt the daemon shows: ``how(prompt_id)`` gives ("respond", choice)
    (a respond from this client, as the browser's page sends it), ("key", KEY) (typed
    into the runner's stdin) or None (no answer); keeps what it answered."""

    def __init__(self, sock: Path, how, stdin=None) -> None:
        self.client = ControlClient(sock, timeout_s=5.0)
        self.client.events_subscribe(["prompt"])
        self.how, self.stdin = how, stdin
        self.answered: dict[int, str] = {}
        self.errors: list[str] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="test-answerer")
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ev = self.client.next_event(0.1)
            except TimeoutError:
                continue
            except OSError:
                return
            pid = ev.get("prompt")
            if pid is None or pid in self.answered:
                continue
            planned = self.how(pid)
            if planned is None:  # this prompt is left unanswered
                continue
            kind, what = planned
            self.answered[pid] = what
            try:
                if kind == "respond":
                    self.client.respond(pid, what)
                else:
                    self.stdin.write(what)
                    self.stdin.flush()
            except (OSError, ValueError) as exc:
                self.errors.append(f"{pid}: {exc}")

    def close(self) -> None:
        self._stop.set()
        self.thread.join(timeout=5)
        self.client.close()


def check_recordings(row: dict, plan, exp) -> None:
    """Each interval's recording exists and rendered the trial's condition and value."""
    paths = json.loads(row["recording"])
    assert len(paths) == 2
    t = plan[row["plan_index"]]
    cond = next(c for c in exp.conditions if c.name == t.condition).values()
    for path, value in zip(paths, rn.interval_values(exp, t), strict=True):
        rec = recording.read(path)
        # The interval: the recording's last touch, whole (the recording began before it,
        # and may hold the end of an earlier touch and the change), felt at the value.
        touching = rec["in_contact"].any(axis=1)
        last = np.flatnonzero(touching)[-1]
        first = np.flatnonzero(~touching[:last])[-1] + 1
        assert last - first > 100
        # It ended on the release (interval.ends_on), well before the 1 s limit.
        assert len(touching) - 1 - last < 200
        assert set(rec["stiffness_n_per_m"][first : last + 1].tolist()) == {value}
        used = {rec.meta["allocators"][k] for k in rec["allocator"][first : last + 1].tolist()}
        assert used == {cond["allocator"]}


def test_a_person_answers_by_respond_and_by_keys(tmp_path, daemons):
    profile, exp_path = setup_files(tmp_path)
    sock = tmp_path / "d.sock"
    daemons(profile, sock)
    db = tmp_path / "t.db"
    proc = runner(exp_path, db, sock, stdin=subprocess.PIPE)
    # A key typed before any question, and a respond to no prompt: both ignored.
    proc.stdin.write("2")
    proc.stdin.flush()
    with ControlClient(sock) as c:
        assert c.request("respond", prompt=0, choice="yes")["error"]["code"] == "no_prompt"
    script = {0: ("respond", "no"), 1: ("key", "y"), 2: ("key", "1"), 3: ("respond", "yes")}
    answers = Answerer(sock, lambda pid: script.get(pid, ("key", "n")), stdin=proc.stdin)
    try:
        code, out, err = finish(proc)
    finally:
        answers.close()
    assert code == 0, err
    assert not answers.errors
    assert "6 trial(s) answered; 0 left: done" in out
    assert "trial 1 of 6 · block 1" in err and "break: 0.3 s" in err
    # The last trial was pinv at 48, 60 or 72 N/m; the daemon is back at the profile's.
    assert_base_profile(sock, err)
    exp = rn.reduced(load_experiment(exp_path), standards=[60.0], repetitions=1)
    plan = make_plan(exp, exp.subject_seed("s1"))
    got = rows(db)
    assert [r["plan_index"] for r in got] == list(range(6))
    yes = {"yes": 1, "no": 0, "y": 1, "2": 1, "n": 0, "1": 0}
    for r in got:
        assert r["status"] == "complete"
        assert r["answer_second_more"] == yes[answers.answered[r["plan_index"]]]
        assert r["source"] == script.get(r["plan_index"], ("key", "n"))[0]
        assert 0 < r["response_time_s"] < 30
        assert (r["condition"], r["comparison"]) == (
            plan[r["plan_index"]].condition,
            plan[r["plan_index"]].comparison,
        )
        check_recordings(r, plan, exp)


def test_no_answer_in_time_stops_the_run_with_the_trial_incomplete(tmp_path, daemons):
    """``--answer-wait-s``: a question nobody answers ends the run (exit 1, a message),
    the trial stored incomplete with both intervals' recordings, the prompt cleared, no
    recording left running; the answered trials before it kept."""
    profile, exp_path = setup_files(tmp_path, one_condition=True)
    sock = tmp_path / "d.sock"
    daemons(profile, sock)
    db = tmp_path / "t.db"
    answers = Answerer(sock, lambda pid: ("respond", "yes") if pid == 0 else None)
    try:
        code, _, err = finish(runner(exp_path, db, sock, "--answer-wait-s", "1.5"))
    finally:
        answers.close()
    assert code == 1, err
    assert "no answer within 1.5 s" in err and "--resume" in err and "Traceback" not in err
    got = rows(db)
    assert [(r["plan_index"], r["status"], r["source"]) for r in got] == [
        (0, "complete", "respond"),
        (1, "incomplete", None),
    ]
    made = json.loads(got[1]["recording"])
    assert len(made) == 2 and all(Path(p).exists() for p in made)
    with ControlClient(sock) as c:
        st = c.status()
    assert st["prompt"] is None and st["recording"] is None
    assert_base_profile(sock, err)  # a failed run too


def test_ctrl_c_sigterm_and_sighup_mid_trial_put_the_daemon_back(tmp_path, daemons):
    """Ctrl-C while the question is up, then (resumed) SIGTERM while an interval is
    recorded, then SIGHUP (a closed terminal) at the question: each run ends the same way,
    the recording closed, the prompt withdrawn, the lease gone, the parameters the base
    profile's (pinv, not the profile's if), the trial stored incomplete."""
    profile, exp_path = setup_files(tmp_path, one_condition=True)
    sock = tmp_path / "d.sock"
    daemons(profile, sock)
    db = tmp_path / "t.db"

    def status() -> dict:
        with ControlClient(sock) as c:
            return c.status()

    ends = (
        (signal.SIGINT, (), "prompt", "Ctrl-C"),
        (signal.SIGTERM, ("--resume",), "recording", "SIGTERM"),
        (signal.SIGHUP, ("--resume",), "prompt", "SIGHUP"),
    )
    for sig, extra, state, name in ends:
        proc = runner(exp_path, db, sock, *extra, interruptible=sig == signal.SIGINT)
        wait_for(lambda state=state: status()[state] is not None, state, timeout_s=60)
        proc.send_signal(sig)
        # Its cleanup talks to the daemon: the trial's recording, the prompt, the base
        # profile's values. (It once seemed to take over a minute: the suite ran as a
        # background job, and the runner ignored SIGINT until the daemon's run ended.)
        code, _, err = finish(proc, timeout_s=60)
        assert code == 128 + sig, err
        assert f"interrupted ({name})" in err and "Traceback" not in err
        st = status()
        assert st["prompt"] is None and st["recording"] is None and st["lease"] is None
        assert_base_profile(sock, err)
    assert [r["status"] for r in rows(db)] == ["incomplete"] * 3


def assert_base_profile(sock: Path, err: str) -> None:
    """The daemon's stiffness and allocator are the base profile's (60 N/m, if) after a
    run that set others (pinv, the comparisons), and the runner said so."""
    with ControlClient(sock) as c:
        assert (c.get("stiffness_n_per_m"), c.get("allocator")) == (60.0, "if")
    assert (
        "the daemon is back at the base profile's stiffness_n_per_m = 60.0, allocator = if" in err
    )


def test_kill_9_mid_experiment_then_resume_finishes_the_plan_once(tmp_path, daemons):
    profile, exp_path = setup_files(tmp_path, one_condition=True)
    sock = tmp_path / "d.sock"
    daemons(profile, sock)
    db = tmp_path / "t.db"
    answers = Answerer(sock, lambda pid: ("respond", "yes" if pid % 2 else "no"))
    try:
        proc = runner(exp_path, db, sock)
        wait_for(lambda: len(rows(db)), "a first stored trial", timeout_s=30)
        # Mid-trial: the second trial's first interval is being recorded.
        wait_for(
            lambda: list((tmp_path / "recs").glob("*-0001-1.hrec")),
            "the second trial's recording",
            timeout_s=10,
        )
        proc.kill()
        code, _, _ = finish(proc, 0)
        assert code == -signal.SIGKILL
        assert [r["plan_index"] for r in rows(db)] == [0]
        with ControlClient(sock) as c:
            # The killed runner's lease ended with its connection: the daemon closed the
            # recording it left open, with its ticks.
            wait_for(
                lambda: c.status()["recording"],
                "the left recording closed",
                until=lambda r: r is None,
            )
        left = sorted((tmp_path / "recs").glob("*-0001-1.hrec"))
        assert len(left) == 1 and recording.read(left[0]).ticks > 0
        # Without --resume the subject's plan is not started again.
        code, _, err = finish(runner(exp_path, db, sock))
        assert code == 2 and "--resume" in err
        code, out, err = finish(runner(exp_path, db, sock, "--resume"))
    finally:
        answers.close()
    assert code == 0, err
    assert "stopped the recording a stopped run left" not in err  # nothing was left
    assert "2 of 3 trials to do" in err and "2 trial(s) answered; 0 left: done" in out
    got = rows(db)
    assert sorted(r["plan_index"] for r in got) == [0, 1, 2]
    assert all(r["status"] == "complete" for r in got)
    assert [r["answer_second_more"] for r in got] == [0, 1, 0]
    with sqlite3.connect(db) as con:
        assert con.execute("PRAGMA integrity_check").fetchone() == ("ok",)
    # The second trial, done again, recorded under new names.
    second = json.loads(got[1]["recording"])
    assert all(Path(p).exists() for p in second) and Path(second[0]).name.endswith("-1-2.hrec")


def test_the_daemon_going_away_mid_trial_stores_it_incomplete(tmp_path, daemons):
    """Answers by the device's response button; then the daemon is killed mid-trial."""
    profile, exp_path = setup_files(tmp_path, buttons=True, one_condition=True)
    sock = tmp_path / "d.sock"
    daemon = daemons(profile, sock)
    db = tmp_path / "t.db"
    proc = runner(exp_path, db, sock, "--no-keys")
    wait_for(lambda: len(rows(db)), "a first stored trial", timeout_s=30)
    wait_for(
        lambda: list((tmp_path / "recs").glob("*-0001-2.hrec")),
        "the second trial's second interval",
        timeout_s=10,
    )
    daemon.proc.kill()
    daemon.proc.wait()
    code, _, err = finish(proc, 30)
    assert code == 1
    assert "the daemon went away" in err and "--resume" in err
    assert "Traceback" not in err
    got = rows(db)
    assert [(r["plan_index"], r["status"]) for r in got] == [(0, "complete"), (1, "incomplete")]
    first = got[0]
    assert first["answer_second_more"] == 1  # the button is labelled yes
    assert (first["source"], got[1]["source"]) == ("button", None)
    assert 0 <= first["response_time_s"] < PERIOD_S + 0.05  # it comes once a cycle
    assert all(Path(p).exists() for p in json.loads(first["recording"]))
    # Its recordings so far (the second's reply may have been lost with the daemon).
    assert got[1]["answer_second_more"] is None
    made = json.loads(got[1]["recording"])
    assert 1 <= len(made) <= 2 and all(Path(p).exists() for p in made)
    with TrialStore.for_experiment(db, load_experiment(exp_path)) as store:
        assert [t.index for t in store.remaining("s1")] == [1, 2]


def test_a_refused_parameter_and_a_daemon_not_ready_for_the_experiment(live, tmp_path):
    """In-process: the bundled grasp, paced, recording to live.hrec (someone else's)."""
    import io

    _, sock, _, _ = live
    exp = load_experiment(STIFFNESS)
    out = io.StringIO()
    with ControlClient(sock) as c:
        p = rn.PersonPresenter(c, subject="s1", out=out)
        with pytest.raises(rn.RunnerError, match=r"is recording to .*live.hrec.*stop it"):
            p.check_daemon(exp, "grasp-stiffness")
        # Which profile to pass: the daemon's own file (its cwd is not the runner's).
        with pytest.raises(rn.RunnerError, match=r"runs profile .grasp-stiffness") as info:
            p.check_daemon(exp, "lift-weight")
        assert f"pass --profile {GRASP_PROFILE}" in str(info.value)
        # Two directions per finger where the running profile has one: the daemon refuses.
        two = [[[0.8660254, 0.0, 0.5], [0.0, 1.0, 0.0]], [[-0.8660254, 0.0, 0.5], [0.0, 1.0, 0.0]]]
        with pytest.raises(rn.RunnerError, match="the daemon refused actuated_directions"):
            p.change({"allocator": "pinv", "actuated_directions": two})
        assert c.get("allocator") == "pinv"  # what came before the refusal was applied
        p.change({"allocator": "if", "stiffness_n_per_m": 45.0})
        assert (c.get("allocator"), c.get("stiffness_n_per_m")) == ("if", 45.0)


def test_cli_refusals_before_any_trial(tmp_path, capsys):
    from hapticd.cli import main

    weight = ROOT / "configs" / "experiments" / "weight-jnd.yaml"
    db = tmp_path / "t.db"
    TrialStore.for_experiment(db, load_experiment(weight)).close()
    base = ["experiment", "run", str(STIFFNESS), "--subject", "s1", "--no-keys"]
    sock = ["--socket", str(tmp_path / "none.sock")]
    assert main([*base, "--db", str(db), *sock]) == 2
    assert "belongs to another experiment" in capsys.readouterr().err
    fresh = tmp_path / "fresh.db"
    assert main([*base, "--db", str(fresh), *sock]) == 1
    assert "cannot reach the daemon: is hapticd running?" in capsys.readouterr().err
    with TrialStore.for_experiment(fresh, load_experiment(STIFFNESS)) as store:
        assert store.plan("s1") == []  # no plan stored without a daemon to present it
    for extra, what in (
        (["--observer", "robot"], "unknown observer 'robot'; observers: person, model"),
        (["--standards", "60,x"], "expected numbers separated by commas"),
        (["--standards", "1e9"], "the reduced design is not valid"),
        (["--repetitions", "3", "--standards", "60"], None),
        (["--buttons", "thumb-0=maybe"], "expected LABEL=yes or LABEL=no"),
    ):
        code = main([*base, "--db", str(fresh), *sock, *extra])
        err = capsys.readouterr().err
        if what is None:  # valid: fails only for want of a daemon
            assert code == 1 and "cannot reach the daemon" in err
        else:
            assert code == 2 and what in err, err
    assert main([*base[:3], "--subject", "a/b", "--db", str(fresh), *sock]) == 2
    assert "subject id 'a/b'" in capsys.readouterr().err


def test_a_second_runner_on_one_subject_is_refused_at_start(tmp_path, capsys):
    import os

    from hapticd.cli import main
    from hapticd.experiment.store import claim_subject

    db = tmp_path / "t.db"
    base = ["experiment", "run", str(STIFFNESS), "--subject", "s1", "--no-keys", "--db", str(db)]
    base += ["--observer", "model", "--standards", "60", "--repetitions", "1"]
    with claim_subject(db, "s1"):  # the first runner, here
        assert main(base) == 2
        err = capsys.readouterr().err
        assert f"subject 's1' is being run by another runner (process {os.getpid()})" in err
        with pytest.raises(StoreError, match="another runner"), claim_subject(db, "s1"):
            pass
        with claim_subject(db, "s2"):  # another subject is free
            pass
    with TrialStore.for_experiment(db, load_experiment(STIFFNESS)) as store:
        assert store.plan("s1") == [] and store.trials(None) == []  # nothing presented
    with claim_subject(db, "s1"):  # released when its holder ends
        pass


@pytest.mark.parametrize("ends_on", ["release", "time_limit"])
def test_an_interval_held_past_its_limit_ends_there(live, ends_on):
    """The bundled grasp squeezes for seconds: the interval ends at exploration_s and the
    subject is told to release."""
    import io

    _, sock, _, _ = live
    exp = load_experiment(STIFFNESS)
    exp = exp.model_copy(
        update={
            "interval": exp.interval.model_copy(update={"exploration_s": 0.3, "ends_on": ends_on})
        }
    )
    out = io.StringIO()
    with ControlClient(sock) as c:
        p = rn.PersonPresenter(c, subject="s1", out=out)
        p.explore(exp)  # waits for the first touch (about 1.9 s into the run)
        began = time.monotonic()
        assert p.contacts == {0, 1}
        p.explore(exp)  # still touching: the interval begins at once
        assert time.monotonic() - began >= 0.3
    assert out.getvalue().count("time: please release the object") == 2


def test_keys_on_a_terminal_need_no_enter_and_the_terminal_is_restored():
    import os
    import termios

    master, slave = os.openpty()
    try:
        before = termios.tcgetattr(slave)
        keys = rn.KeyReader(slave)
        try:
            assert not termios.tcgetattr(slave)[3] & termios.ICANON  # cbreak: key by key
            os.write(master, b"2")
            key, when = keys.keys.get(timeout=5)
            assert key == "2" and when <= time.monotonic()
            os.write(master, b"y")
            wait_for(lambda: not keys.keys.empty(), "the second key", timeout_s=5)
            keys.drain()
            assert keys.keys.empty()
        finally:
            keys.close()
        assert termios.tcgetattr(slave) == before
    finally:
        os.close(master)
        os.close(slave)


def test_a_busy_daemon_is_a_clear_error_before_any_trial(idle_server):
    """Every place of the daemon held: the runner says it cannot reach the
    daemon because it is busy (a protocol error from the daemon, not a traceback)."""
    exp = load_experiment(STIFFNESS)
    clients = fill_every_place(idle_server)
    try:
        with (
            pytest.raises(rn.RunnerError, match=r"cannot reach the daemon: .*busy"),
            rn.person_observer(exp, "s1", rn.RunOptions(socket=idle_server.path)),
        ):
            pytest.fail("a presenter on a busy daemon")
    finally:
        for c in clients:
            c.close()


def test_one_experiment_at_a_time_the_lease_names_its_holder_and_ends_with_it(idle_server):
    """A runner holds the daemon: another runner (any subject) is refused at start, named
    the holder and changing nothing; other clients' trial changes are refused, disable
    and stop never are; the lease (and its prompt) ends when its connection closes."""
    import os

    exp = load_experiment(STIFFNESS)
    path = idle_server.path
    with ControlClient(path) as other:
        holder = ControlClient(path)
        try:
            assert holder.lease("s1") == {"holder": {"subject": "s1", "pid": os.getpid()}}
            holder.prompt(3, "Was the second stiffer?", ["no", "yes"])
            assert other.status()["lease"] == {"subject": "s1", "pid": os.getpid()}
            with (
                pytest.raises(rn.RunnerError, match=rf"subject 's1' \(process {os.getpid()}\)"),
                rn.person_observer(exp, "s2", rn.RunOptions(socket=path)),
            ):
                pytest.fail("a second runner on a held daemon")
            for cmd, args in (
                ("set", {"param": "stiffness_n_per_m", "value": 30.0}),
                ("prompt", {"prompt": None}),
                ("record_start", {"path": "x.hrec"}),
                ("reload", {}),
            ):
                assert other.request(cmd, **args)["error"]["code"] == "leased", cmd
            assert other.status()["prompt"]["id"] == 3  # nothing changed
            # Forces off and the subject's answer are never held up by the lease.
            assert other.request("disable").get("error", {}).get("code") != "leased"
            other.respond(3, "yes")
            assert holder.release() == {"released": True}
            assert other.lease("s2")["holder"]["subject"] == "s2"
            assert other.release() == {"released": True}
            holder.lease("s1")
            holder.prompt(4, "Was the second stiffer?", ["no", "yes"])
        finally:
            holder.close()  # a runner killed with its prompt up
        wait_for(lambda: other.status()["lease"] is None, "the lease to end", timeout_s=5)
        assert other.status()["prompt"] is None
        assert other.request("lease", subject="s2")["ok"]


def test_a_holder_whose_connection_closes_mid_run_leaves_the_daemon_as_it_found_it(
    tmp_path, grasp_data, write_profile
):
    """A runner whose connection to a running daemon closes mid-trial (the runner alive, its
    socket gone) cannot put anything back itself: the daemon does, at the lease's end. The
    trial's stiffness and allocator go back to what the holder found, the recording it
    started is closed with its ticks, and a change made before the lease stays."""
    from hapticd import recording
    from tests.test_view import running_daemon

    for finger in grasp_data["fingers"]:
        finger["device"]["hold_s"] = 60.0
    profile = write_profile(grasp_data, "held.yaml")
    with running_daemon(tmp_path / "d.sock", profile) as sock, ControlClient(sock) as other:
        other.set("damping_n_s_per_m", 2.5)  # before any lease: the daemon's own state
        found = {n: other.get(n) for n in ("stiffness_n_per_m", "allocator", "friction")}
        holder = ControlClient(sock)
        try:
            holder.lease("s1")
            holder.set("stiffness_n_per_m", found["stiffness_n_per_m"] * 0.5)
            holder.set("allocator", "pinv" if found["allocator"] != "pinv" else "IF")
            path = holder.record_start("trial.hrec")["path"]
            wait_for(lambda: other.status()["recording"]["written"] > 50, "ticks in the recording")
        finally:
            holder.close()  # the runner's socket gone, the runner itself not told
        wait_for(lambda: other.status()["lease"] is None, "the lease to end", timeout_s=5)
        wait_for(lambda: other.status()["recording"] is None, "the recording closed", timeout_s=5)
        for name, value in found.items():
            assert other.get(name) == value, name
        assert other.get("damping_n_s_per_m") == 2.5
    rec = recording.read(path)
    assert len(rec["tick"]) > 50


def test_experiment_run_with_profile_presents_the_design_on_the_rigs_profile(
    tmp_path, monkeypatch, capsys
):
    """``hapticd experiment run EXP --profile RIG.yaml``: every trial stored is of the
    rig's base profile (its file's hash), not the one the experiment file names; a design
    the rig cannot run is refused before anything is stored."""
    from hapticd.cli import main
    from hapticd.experiment.spec import file_hash

    monkeypatch.setitem(rn.OBSERVERS, "quick", "tests.test_counterbalance:quick_observer")
    rig = ROOT / "configs" / "rehearse-grasp.yaml"
    base = ["--subject", "s1", "--observer", "quick", "--standards", "60"]
    base += ["--repetitions", "1", "--no-keys"]
    for db, extra in ((tmp_path / "rig.db", ["--profile", str(rig)]), (tmp_path / "own.db", [])):
        argv = ["experiment", "run", str(STIFFNESS), "--db", str(db), *base, *extra]
        assert main(argv) == 0, capsys.readouterr().err
    own = load_experiment(STIFFNESS).profile_path()
    assert file_hash(rig) != file_hash(own)
    assert {r["profile_hash"] for r in rows(tmp_path / "rig.db")} == {file_hash(rig)}
    assert {r["profile_hash"] for r in rows(tmp_path / "own.db")} == {file_hash(own)}
    weight = ROOT / "configs" / "experiments" / "weight-jnd.yaml"
    db = tmp_path / "w.db"
    argv = ["experiment", "run", str(weight), "--db", str(db), *base, "--profile"]
    assert main([*argv, str(GRASP_PROFILE)]) == 2
    assert "mass_kg on a fixed object" in capsys.readouterr().err
    assert not db.exists()


def test_a_design_runs_on_another_base_profile(tmp_path, capsys):
    from hapticd.cli import main

    rig = ROOT / "configs" / "rehearse-grasp.yaml"
    assert main(["experiment", "check", str(STIFFNESS), "--profile", str(rig)]) == 0
    assert f"({rig})" in capsys.readouterr().out
    weight = ROOT / "configs" / "experiments" / "weight-jnd.yaml"
    assert main(["experiment", "check", str(weight), "--profile", str(GRASP_PROFILE)]) == 2
    assert "mass_kg on a fixed object" in capsys.readouterr().err
