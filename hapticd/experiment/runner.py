"""``hapticd experiment run``: walk a subject's trial plan on a running daemon.

Two pieces, so that any observer can run the same plan into the same store:

- a **Presenter** presents one planned trial and returns what came of it::

      class Presenter(Protocol):
          def present(self, exp: Experiment, trial: PlannedTrial,
                      params: Mapping[str, Any]) -> Presented: ...
          def rest(self, seconds: float) -> None: ...

  ``params`` is the trial's condition's parameter set (hapticd.params names, SI
  values; not the varied parameter: ``interval_values(exp, trial)`` gives its value in
  each interval). ``present`` shows both intervals, asks the question and returns a
  ``Presented`` (the answer "was the second more?", the response time s, the
  recording paths, ``complete`` or ``incomplete``, and where the answer came from). It
  raises ``TrialAbortedError`` (with the recordings made so far) when the trial cannot go
  on (the daemon went away, Ctrl-C): the trial is stored incomplete and the run ends.
  ``rest`` takes a break between trials (a simulated observer returns at once).
  ``PersonPresenter`` is the one for a person at a running daemon.

- ``run_subject(store, exp, subject, seed, presenter, profile_hash=...)`` walks what
  is left of the subject's plan: breaks, ``present``, and ``TrialStore.record`` of each
  trial the moment it is answered. ``start_subject`` stores (or, resuming, checks) the
  plan first.

``OBSERVERS`` maps ``--observer`` names to presenter factories: ``person`` here,
``model`` (``hapticd.experiment.study.model_observer``: the simulated subject, which
runs the servo loop in its own process, unpaced, and needs no daemon).

The runner is a client of the control socket (hapticd.control): it never imports the
servo loop or the daemon (the model observer is imported only when chosen).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import json
import math
import os
import queue
import re
import select
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, TextIO

from hapticd import protocol as proto
from hapticd.control import ControlClient
from hapticd.experiment.plan import PlannedTrial, make_plan, make_practice
from hapticd.experiment.spec import Display, Experiment, ExperimentError, file_hash
from hapticd.experiment.store import DONE, StoreError, TrialStore, claim_subject

SUBJECT_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,64}")
CHOICES = ("no", "yes")  # the prompt's labels: "was the second more?"
# Terminal keys: the interval judged more (1 or 2), or the answer to the question.
KEYS = {"1": False, "n": False, "2": True, "y": True}
# Response labels of device buttons (docs/control.md) read as answers without --buttons.
BUTTON_LABELS = {"no": False, "n": False, "first": False, "yes": True, "y": True, "second": True}


class RunnerError(RuntimeError):
    """The run cannot start or go on; the message says why and what to do."""


class DaemonGoneError(RunnerError):
    """The daemon closed the connection or stopped answering."""


class TrialAbortedError(RunnerError):
    """A trial that cannot be finished: ``recordings`` made so far; ``interrupted``: by
    Ctrl-C, SIGTERM or SIGHUP, ``signum`` says which (else the message says what
    happened)."""

    def __init__(
        self,
        message: str,
        recordings: Sequence[str] = (),
        *,
        interrupted: bool = False,
        signum: int = signal.SIGINT,
    ) -> None:
        super().__init__(message)
        self.recordings = tuple(recordings)
        self.interrupted = interrupted
        self.signum = int(signum)


@dataclass(frozen=True)
class Presented:
    """What presenting one trial gave: the answer to "was the second more?" (None: no
    answer), the response time from the question to the answer (s), the recordings (one
    per interval), the trial's status (``failed``: the exploration failed, ``failure``
    says why; no answer) and where the answer came from (``key``,
    ``button``, ``respond`` or an observer's own name)."""

    answer_second_more: bool | None
    response_time_s: float | None
    recordings: tuple[str, ...] = ()
    status: Literal["complete", "incomplete", "failed"] = "complete"
    source: str = ""
    failure: str | None = None


class Presenter(Protocol):
    """Presents trials to an observer (see the module's docstring)."""

    def present(
        self, exp: Experiment, trial: PlannedTrial, params: Mapping[str, Any]
    ) -> Presented: ...

    def rest(self, seconds: float) -> None: ...


@dataclass(frozen=True)
class Progress:
    """Where a run is: ``done`` of ``total`` trials of the subject's plan, the next
    trial, and the estimated time left (s)."""

    done: int
    total: int
    trial: PlannedTrial | None
    left_s: float

    def line(self) -> str:
        if self.trial is None:
            return f"trial {self.done} of {self.total} done"
        t = self.trial
        return (
            f"trial {self.done + 1} of {self.total} · block {t.block + 1} ({t.condition}, "
            f"standard {t.standard:g}) · about {_minutes(self.left_s)} left"
        )


def _minutes(s: float) -> str:
    return f"{s:.0f} s" if s < 90 else f"{s / 60:.0f} min"


def interval_values(exp: Experiment, trial: PlannedTrial) -> tuple[float, float]:
    """The varied parameter's value in the first and the second interval (SI)."""
    if trial.comparison_first:
        return trial.comparison, trial.standard
    return trial.standard, trial.comparison


def question_text(exp: Experiment) -> str:
    """The question asked after the second interval."""
    q = exp.interval.question
    if q == "more":
        return f"Was {exp.varied.param} larger the second time?"
    return f"Was the second object {q}?"


def reduced(
    exp: Experiment,
    *,
    standards: Sequence[float] | None = None,
    repetitions: int | None = None,
    break_s: float | None = None,
) -> Experiment:
    """``exp`` with other standards, repetitions and/or break length (s) (a pilot's, a
    rehearsal's or a test's reduced design), validated as the file is (ExperimentError
    naming what is wrong). The break length does not change the plan."""
    if standards is None and repetitions is None and break_s is None:
        return exp
    data = exp.model_dump()
    if standards is not None:
        data["varied"]["standards"] = [float(s) for s in standards]
    if repetitions is not None:
        data["repetitions"] = int(repetitions)
    if break_s is not None:
        data["breaks"]["duration_s"] = float(break_s)
    try:
        new = Experiment.model_validate(data)
    except ValueError as exc:
        raise ExperimentError(f"{exp.source}: the reduced design is not valid: {exc}") from None
    return new.model_copy(update={"source": exp.source, "file_hash": exp.file_hash})


def profile_hash(exp: Experiment) -> str:
    """sha256 of the experiment's base profile file."""
    return file_hash(exp.profile_path())


# -- walking a plan ------------------------------------------------------------------------


def check_subject(subject: str) -> None:
    """ValueError unless ``subject`` can name files (1 to 64 of A-Z a-z 0-9 _ . -)."""
    if not SUBJECT_PATTERN.fullmatch(subject):
        raise ValueError(
            f"subject id {subject!r}: use 1 to 64 letters, digits, '_', '.' or '-' "
            "(it names the recordings)"
        )


def start_subject(
    store: TrialStore,
    exp: Experiment,
    subject: str,
    seed: int,
    *,
    resume: bool,
    subject_index: int | None = None,
) -> list[PlannedTrial]:
    """Store ``subject``'s plan (``make_plan(exp, seed, subject_index)``), or with
    ``resume`` check it is the stored one; the trials left to do. StoreError for a
    subject that already has a plan without ``resume``, none to resume, or another plan;
    ValueError for a subject id that cannot name files."""
    check_start(store, subject, resume=resume)
    store.ensure_plan(subject, make_plan(exp, seed, subject_index), seed)
    return store.remaining(subject)


def check_start(store: TrialStore, subject: str, *, resume: bool) -> None:
    """``start_subject``'s refusals, changing nothing."""
    check_subject(subject)
    # A run stopped in its practice has a plan too (an adaptive one: practice only).
    stored = store.plan(subject) or store.plan(subject, practice=True)
    if stored and not resume:
        done = len(stored) - len(store.remaining(subject))
        raise StoreError(
            f"{store.path}: subject {subject!r} already has a plan ({done} of {len(stored)} "
            "trials answered): continue it with --resume, or use another subject id"
        )
    if not stored and resume:
        raise StoreError(
            f"{store.path}: nothing to resume: subject {subject!r} has no plan here; "
            "run without --resume to start"
        )


def run_subject(
    store: TrialStore,
    exp: Experiment,
    subject: str,
    seed: int,
    presenter: Presenter,
    *,
    profile_hash: str,
    progress: Callable[[Progress], None] | None = None,
) -> int:
    """Present what is left of ``subject``'s stored plan (``start_subject`` first) and
    record each trial in ``store`` as soon as it is answered; the number of complete
    trials recorded. Breaks (``break_before_s``) go to ``presenter.rest``. A trial the
    presenter returns ``incomplete`` is stored so and the run goes on (it stays in the
    plan); one it returns ``failed`` (the model observer's exploration failed) is stored
    so, never presented again; ``TrialAbortedError`` stores the trial incomplete and is
    raised again."""
    total = len(store.plan(subject))
    todo = store.remaining(subject)
    if total == 0:
        raise RunnerError(f"{store.path}: subject {subject!r} has no plan: start_subject first")
    conditions = {c.name: c.values() for c in exp.conditions}
    spent: list[float] = []
    recorded = 0
    for k, trial in enumerate(todo):
        if progress is not None:
            per = sum(spent) / len(spent) if spent else exp.trial_s()
            breaks = sum(t.break_before_s for t in todo[k:])
            progress(Progress(total - len(todo) + k, total, trial, per * (len(todo) - k) + breaks))
        began = time.monotonic()
        got = _present(store, exp, subject, seed, presenter, trial, conditions, profile_hash)
        spent.append(time.monotonic() - began)
        recorded += got.status == "complete"
    if progress is not None:
        left = len(store.remaining(subject))
        progress(Progress(total - left, total, None, 0.0))
    return recorded


def _present(
    store: TrialStore,
    exp: Experiment,
    subject: str,
    seed: int,
    presenter: Presenter,
    trial: PlannedTrial,
    conditions: Mapping[str, Mapping[str, Any]],
    profile_hash: str,
) -> Presented:
    """The break before ``trial``, the trial presented, and its row stored at once
    (incomplete, and the error raised again, when the presenter aborts it)."""
    if trial.break_before_s > 0:
        presenter.rest(trial.break_before_s)
    try:
        got = presenter.present(exp, trial, conditions[trial.condition])
    except TrialAbortedError as exc:
        store.record(
            subject,
            trial,
            answer_second_more=None,
            response_time_s=None,
            profile_hash=profile_hash,
            seed=seed,
            recording=_recordings(exc.recordings),
            status="incomplete",
        )
        raise
    store.record(
        subject,
        trial,
        answer_second_more=got.answer_second_more,
        response_time_s=got.response_time_s,
        profile_hash=profile_hash,
        seed=seed,
        recording=_recordings(got.recordings),
        status=got.status,
        source=got.source or None,
        failure=got.failure,
    )
    return got


def run_adaptive_subject(
    store: TrialStore,
    exp: Experiment,
    subject: str,
    seed: int,
    presenter: Presenter,
    *,
    profile_hash: str,
    progress: Callable[[Progress], None] | None = None,
) -> int:
    """``run_subject`` for an adaptive procedure (``exp.proc``): each next trial is
    decided from the answers so far, stored in the plan, presented and recorded; the
    tracks are rebuilt from the stored trials first, and a trial decided but not
    answered (a run that stopped in it) is presented again as it was. The number of
    complete trials recorded now."""
    proc = exp.proc
    conditions = {c.name: c.values() for c in exp.conditions}
    rows = [r for r in store.trials(None) if r["subject"] == subject and r["status"] in DONE]
    tracks = proc.replay(exp, rows)
    most = exp.n_blocks * proc.max_trials
    recorded = 0
    while True:
        pending = store.remaining(subject)
        if pending:
            trial: PlannedTrial | None = pending[0]
        else:
            trial = proc.next_trial(exp, seed, len(store.plan(subject)), tracks)
            if trial is None:
                break
            store.append_plan(subject, trial, seed)
        assert trial is not None
        if progress is not None:
            progress(Progress(trial.index, most, trial, exp.trial_s() * (most - trial.index)))
        got = _present(store, exp, subject, seed, presenter, trial, conditions, profile_hash)
        if got.status == "complete":
            recorded += 1
            more = bool(got.answer_second_more) != trial.comparison_first
            proc.update(tracks[trial.block], more, trial.comparison)
        elif got.status == "failed":
            proc.skip(tracks[trial.block])
    if progress is not None:
        done = len(store.plan(subject))
        progress(Progress(done, done, None, 0.0))
    return recorded


def run_practice(
    store: TrialStore,
    exp: Experiment,
    subject: str,
    seed: int,
    presenter: Presenter,
    *,
    profile_hash: str,
    say: Callable[[str], None] | None = None,
) -> int:
    """Present what is left of ``subject``'s practice trials (``make_practice``: stored
    in the plan and the trials marked ``practice``, never analysed) before the session,
    each recorded as soon as it is answered; a resumed run presents those not answered
    yet. The number of complete practice trials recorded now."""
    plan = make_practice(exp, seed)
    if not plan:
        return 0
    store.ensure_plan(subject, plan, seed)
    conditions = {c.name: c.values() for c in exp.conditions}
    note = getattr(presenter, "note_progress", None)
    recorded = 0
    for trial in store.remaining(subject, practice=True):
        if say is not None:
            say(
                f"practice trial {trial.position + 1} of {len(plan)} ({trial.condition}, "
                f"standard {trial.standard:g}, comparison {trial.comparison:g})"
            )
        if note is not None:
            note(Progress(trial.position, len(plan), trial, 0.0))
        got = _present(store, exp, subject, seed, presenter, trial, conditions, profile_hash)
        recorded += got.status == "complete"
    return recorded


def _recordings(paths: Sequence[str]) -> str | None:
    """The trial's recordings as the store keeps them: a JSON list of paths."""
    return json.dumps(list(paths)) if paths else None


# -- a person at a running daemon -----------------------------------------------------------


class KeyReader:
    """Keys typed on ``fd`` (a terminal in cbreak mode: no Enter needed; a pipe: each
    byte), each with the monotonic time it was read, in a thread."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.keys: queue.Queue[tuple[str, float]] = queue.Queue()
        self._stop = threading.Event()
        self._saved: Any = None
        if os.isatty(fd):
            import termios
            import tty

            self._saved = termios.tcgetattr(fd)
            tty.setcbreak(fd)
        self._thread = threading.Thread(target=self._read, name="hapticd-keys", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], 0.1)
                if not ready:
                    continue
                data = os.read(self.fd, 64)
            except OSError:
                return
            if not data:
                return  # end of input: no more keys
            now = time.monotonic()
            for ch in data.decode("utf-8", "replace"):
                self.keys.put((ch, now))

    def drain(self) -> None:
        """Forget the keys typed so far (typed at the wrong time)."""
        with contextlib.suppress(queue.Empty):
            while True:
                self.keys.get_nowait()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        if self._saved is not None:
            import termios

            with contextlib.suppress(OSError):
                termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)


@dataclass
class PersonOptions:
    """How ``PersonPresenter`` waits: for a release before a change (s), for the first
    touch of an interval (s), for an answer (s); ``buttons`` maps device buttons'
    response labels to answers (besides ``BUTTON_LABELS``)."""

    release_wait_s: float = 60.0
    touch_wait_s: float = 300.0
    answer_wait_s: float = 600.0
    buttons: dict[str, bool] = field(default_factory=dict)


POLL_S = 0.02  # how often keys are looked at while events are awaited
# The words of the subject's screen in each state (the instructions' come from the
# experiment file); nothing in them depends on the trial's condition or values.
SCREEN_TEXT = {
    "wait": "Please wait",
    "touch": "Touch the object",
    "release": "Release the object",
    "answer": "Answer the question",
    "break": "Break",
    "end": "The session is over. Thank you!",
}
FEEDBACK_TEXT = {True: "Correct", False: "Incorrect"}
READY = "Ready to begin?"  # asked under the instructions: yes begins the session
# Prompt ids beyond any trial's index: the instructions' question, and the practice
# trials' (their plan indices are negative; a prompt's id is not).
INSTRUCTIONS_PROMPT = 1_000_000
PRACTICE_PROMPTS = 2_000_000
APPLY_WAIT_S = 5.0  # for a set's param_changed event to arrive (event delivery: 5 ms)
MAX_CHANGE_TRIES = 20  # changes touched while applied, retried, before giving up


class PersonPresenter:
    """Presents trials to a person at the daemon behind ``client`` (events subscribed
    here): the object changes only while nobody touches it; each interval is recorded
    in the daemon's recording directory; the answer comes from a key (``keys``), a
    device button mapped to a response, or a ``respond`` on the daemon's prompt (the
    browser's subject page), whichever is first. Messages to the subject go to
    ``out``."""

    def __init__(
        self,
        client: ControlClient,
        *,
        subject: str,
        keys: KeyReader | None = None,
        out: TextIO = sys.stderr,
        options: PersonOptions | None = None,
    ) -> None:
        self.client = client
        self.subject = subject
        self.keys = keys
        self.out = out
        self.opt = options or PersonOptions()
        self.contacts: set[int] = set()
        self.fault: str | None = None
        self._unmapped: set[str] = set()
        self._prompt_t: float | None = None
        self.ended: str | None = None  # why the daemon's run ended, once it said so
        # The subject's screen: the experiment's display, whether the trial shown is a
        # practice one, the progress (trial, total) shown, a daemon without screens.
        self.display = Display()
        self._practice = False
        self._progress: tuple[int, int] | None = None
        self._no_screen = False
        self.finished = False  # the session's end is on the subject's screen
        self._marks = True  # the daemon takes `mark` (an older one does not)
        self._connect()

    # -- the connection ------------------------------------------------------------------

    @contextlib.contextmanager
    def _talking(self) -> Iterator[None]:
        """Turn a lost connection (or a daemon that stopped answering) into DaemonGoneError;
        a refusal (ProtocolError) goes through."""
        try:
            yield
        except proto.ProtocolError as exc:
            if exc.code == "stopped":
                raise DaemonGoneError(str(exc)) from None
            raise
        except (OSError, ValueError) as exc:
            raise self._gone(exc) from None

    def _gone(self, exc: Exception) -> DaemonGoneError:
        """The lost connection's error: why the daemon stopped when it said so (its
        trajectories ended), else what the connection said."""
        if self.ended is not None:
            return DaemonGoneError(f"the daemon stopped: {self.ended}")
        return DaemonGoneError(f"the daemon went away ({exc})")

    def _connect(self) -> None:
        with self._talking():
            self.client.events_subscribe()
            st = self.client.status()
        self.status = st
        self.contacts = {i for i, c in enumerate(st.get("in_contact") or []) if c}
        if st.get("fault"):
            raise RunnerError(
                f"the daemon has a latched fault ({st['fault']}): clear it (hapticd enable) "
                "and start again"
            )

    def check_daemon(self, exp: Experiment, profile_name: str) -> None:
        """RunnerError unless the daemon runs the experiment's base profile, paced, and
        records nothing of someone else's; a recording left by a killed runner of this
        experiment is stopped."""
        st = self.status
        if st.get("profile") != profile_name:
            there = st.get("profile_path")
            rig = f"--profile {there}" if there else "--profile PATH (the daemon's profile file)"
            raise RunnerError(
                f"the daemon runs profile {st.get('profile')!r}; experiment {exp.name!r} is "
                f"on {profile_name!r} ({exp.profile_path()}): to run the design on the "
                f"daemon's profile pass {rig}, or start hapticd run with "
                f"{exp.profile_path()}"
            )
        rec = st.get("recording")
        if rec:
            path = str(rec.get("path", ""))
            if Path(path).name.startswith(f"{exp.name}-"):
                with self._talking():
                    self.client.record_stop()  # left by a runner that was killed
                self.say(f"stopped the recording a stopped run left: {path}")
            else:
                raise RunnerError(
                    f"the daemon is recording to {path}: stop it (hapticd record stop) first"
                )

    def take_lease(self) -> None:
        """Hold the daemon for this run (one experiment at a time; the daemon ends the
        lease when this connection closes, however the run ends); RunnerError naming the
        holder when another runner has it, before anything changed."""
        try:
            with self._talking():
                self.client.lease(self.subject)
        except proto.ProtocolError as exc:
            if exc.code != "leased":
                raise RunnerError(f"the daemon refused the lease: {exc.code}: {exc}") from None
            raise RunnerError(f"another experiment runs on this daemon: {exc}") from None

    def restore(self, values: Mapping[str, Any]) -> None:
        """Set ``values`` (the base profile's, ``base_values``) on the daemon after a run,
        however it ended, and say so; a daemon that went away or refuses is reported,
        never raised (the run's own outcome is what the caller reports)."""
        done = []
        for name, value in values.items():
            try:
                with self._talking():
                    self.client.set(name, value)
            except (RunnerError, proto.ProtocolError, OSError) as exc:
                self.say(f"could not restore {name} to the base profile's value: {exc}")
                if isinstance(exc, DaemonGoneError):
                    return
                continue
            done.append(f"{name} = {value}")
        if done:
            self.say("the daemon is back at the base profile's " + ", ".join(done))

    def say(self, text: str) -> None:
        # A terminal closed (SIGHUP) fails writes: the cleanup that follows must go on.
        with contextlib.suppress(OSError, ValueError):
            self.out.write(f"\r\x1b[K{text}\n" if self.out.isatty() else f"{text}\n")
            self.out.flush()

    # -- the subject's screen ------------------------------------------------------------

    def show(self, state: str, text: str | None = None, **extra: Any) -> None:
        """Set the subject's screen (the daemon's ``screen``, which the view's subject page
        shows): ``state`` with its words (SCREEN_TEXT's unless ``text``), marked practice
        during a practice trial, with the progress when the experiment's display asks
        for it, the scene hidden when it says so. A daemon without screens is told
        nothing again (the terminal still says everything)."""
        if self._no_screen:
            return
        screen: dict[str, Any] = {
            "state": state,
            "text": SCREEN_TEXT.get(state, "") if text is None else text,
            "practice": self._practice,
            "scene": self.display.scene,
            **extra,
        }
        if self.display.progress and self._progress is not None:
            screen["progress"] = list(self._progress)
        try:
            with self._talking():
                self.client.screen(screen)
        except proto.ProtocolError as exc:
            if exc.code != "unknown_command":
                raise RunnerError(f"the daemon refused the screen {state}: {exc}") from None
            self._no_screen = True

    def clear_screen(self) -> None:
        """Withdraw the subject's screen (a run that did not finish), if the daemon is
        still there."""
        with contextlib.suppress(Exception):
            self.client.screen(None)

    def note_progress(self, progress: Progress) -> None:
        """Where the run is, for the subject's screen (``display.progress``)."""
        t = progress.trial
        self._progress = None if t is None else (progress.done + 1, progress.total)

    def begin(self, exp: Experiment) -> None:
        """Before the session (and its practice): the experiment's instructions on the
        subject's screen until the subject answers READY yes (a key, a device button or
        the page)."""
        self.display = exp.display
        ins = exp.instructions
        if ins is None or not ins.enabled:
            return
        self.say("the instructions are on the subject's screen: waiting for them to begin")
        while True:
            self.show("instructions", ins.text)
            ready, _, _ = self._answer(INSTRUCTIONS_PROMPT, READY)
            if ready:
                break
        self.show("wait")

    def finish(self) -> None:
        """The session's end on the subject's screen (it stays until the next run)."""
        self._practice = False
        self._progress = None
        self.show("end")
        self.finished = True

    # -- events --------------------------------------------------------------------------

    def _event(self, timeout_s: float) -> dict[str, Any] | None:
        """The next event within ``timeout_s`` (None at the deadline), contacts and
        faults followed."""
        try:
            ev = self.client.next_event(max(timeout_s, 0.0))
        except TimeoutError:
            return None
        except (OSError, ValueError) as exc:
            raise self._gone(exc) from None
        name = ev.get("event")
        if name == "contact_begin":
            self.contacts.add(ev.get("finger", -1))
        elif name == "contact_end":
            self.contacts.discard(ev.get("finger", -1))
        elif name == "fault_latched":
            self.fault = f"{ev.get('cause')}: {ev.get('message', '')}".rstrip(": ")
        elif name == "trajectory_end":
            self.ended = "trajectory ended"
            self.say("the daemon's run ends (its trajectories ended)")
        return ev

    def _check_fault(self) -> None:
        if self.fault is not None:
            raise RunnerError(
                f"a safety fault latched ({self.fault}); forces are off: check the setup, "
                "hapticd enable, then --resume"
            )

    def _await(
        self, until: Callable[[dict[str, Any]], bool], timeout_s: float
    ) -> dict[str, Any] | None:
        """Events until one satisfies ``until`` (returned) or ``timeout_s`` passes (None)."""
        deadline = time.monotonic() + timeout_s
        while True:
            ev = self._event(min(POLL_S, deadline - time.monotonic()))
            self._check_fault()
            if ev is not None and until(ev):
                return ev
            if time.monotonic() >= deadline:
                return None

    def _drain(self, seconds: float) -> None:
        """Follow events for ``seconds``."""
        self._await(lambda ev: False, seconds)

    def _await_release(self) -> None:
        if not self.contacts:
            return
        self.say("please release the object")
        self.show("release")
        if self._await(lambda ev: not self.contacts, self.opt.release_wait_s) is None:
            raise RunnerError(
                f"the object was not released within {self.opt.release_wait_s:g} s "
                f"(fingers {sorted(self.contacts)} still touch it)"
            )

    # -- one trial -----------------------------------------------------------------------

    def rest(self, seconds: float) -> None:
        self.say(f"break: {seconds:g} s")
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            self.show("break", seconds=round(left, 1))  # the countdown, once a second
            self._drain(min(left, 1.0))
        self.show("wait")
        self.say("the break is over")

    def present(
        self, exp: Experiment, trial: PlannedTrial, params_: Mapping[str, Any]
    ) -> Presented:
        recordings: list[str] = []
        self.display = exp.display
        self._practice = trial.practice
        at = f"trial={trial.index}"
        try:
            self.mark(f"trial_start {at} condition={trial.condition}")
            for k, value in enumerate(interval_values(exp, trial)):
                if k == 1:
                    self._drain(exp.interval.gap_s)
                # Recording first: starting it takes a while (its writer process), and it
                # must hold the whole touch that follows the change.
                recordings.append(self._record_start(exp, trial, k + 1))
                self.change({**params_, exp.varied.param: value})
                self.mark(f"condition_set {at} interval={k + 1} {exp.varied.param}={value!r}")
                self.mark(f"interval_start {at} interval={k + 1}")
                self.explore(exp)
                self.mark(f"interval_end {at} interval={k + 1}")
                with self._talking():
                    self.client.record_stop()
            answer, rt, source = self._ask(exp, trial)
            self.mark(f"trial_end {at} answer={'second' if answer else 'first'}")
            self._give_feedback(exp, trial, answer)
        except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM/SIGHUP (ending_signals)
            self.withdraw()
            why = f"interrupted ({signal_name(exc)})"
            signum = getattr(exc, "signum", signal.SIGINT)
            raise TrialAbortedError(why, recordings, interrupted=True, signum=signum) from None
        except (RunnerError, proto.ProtocolError) as exc:
            self.withdraw()
            raise TrialAbortedError(str(exc), recordings) from None
        except Exception:  # a bug: the daemon is still left as no trial runs on it
            self.withdraw()
            raise
        return Presented(answer, rt, tuple(recordings), "complete", source)

    def withdraw(self) -> None:
        """After a trial cut short, and at the end of every run: withdraw the prompt and
        stop the recording, if the daemon is still there and has them (never raises)."""
        with contextlib.suppress(Exception):
            st = self.client.status()
            if st.get("prompt") is not None:
                self.client.clear_prompt()
            if st.get("recording"):
                self.client.record_stop()

    def _give_feedback(self, exp: Experiment, trial: PlannedTrial, answer: bool) -> None:
        """Correct or incorrect on the subject's screen for ``exp.feedback.duration_s``,
        after the trials ``exp.feedback.after`` names that have a correct answer (the
        comparison differs from the standard)."""
        fb = exp.feedback
        if fb.after == "none" or (fb.after == "practice" and not trial.practice):
            return
        first, second = interval_values(exp, trial)
        if first == second:
            return
        correct = answer == (second > first)
        self.say(f"feedback to the subject: {FEEDBACK_TEXT[correct].lower()}")
        self.show("feedback", FEEDBACK_TEXT[correct], correct=correct)
        self._drain(fb.duration_s)
        self.show("wait")

    def mark(self, text: str) -> None:
        """Have the daemon stamp ``text`` with its tick (a ``mark`` event, on its LSL marker
        stream too: docs/lsl.md); a daemon without ``mark`` is not asked again."""
        if not self._marks:
            return
        try:
            with self._talking():
                self.client.mark(text[: proto.MARK_TEXT_CHARS])
        except proto.ProtocolError as exc:
            if exc.code != "unknown_command":
                raise
            self._marks = False

    def change(self, values: Mapping[str, Any]) -> None:
        """An interval's first step: set ``values`` while nobody touches the object (wait
        for the release, set, and do it again if a touch began before the change was
        applied); RunnerError if the daemon refuses one."""
        for _ in range(MAX_CHANGE_TRIES):
            self._await_release()
            last = -1
            for name, value in values.items():
                try:
                    with self._talking():
                        last = self.client.set(name, value)["applied_at_tick"]
                except proto.ProtocolError as exc:
                    raise RunnerError(
                        f"the daemon refused {name} = {value!r}: {exc.code}: {exc}"
                    ) from None
            touched = False

            def applied(ev: dict[str, Any], last: int = last) -> bool:
                nonlocal touched
                if ev.get("event") == "contact_begin":
                    touched = True
                return ev.get("event") == "param_changed" and ev.get("tick", -1) >= last

            if self._await(applied, APPLY_WAIT_S) is None:
                raise RunnerError(
                    f"no param_changed event for tick {last} within {APPLY_WAIT_S:g} s"
                )
            if not touched and not self.contacts:
                return
            self.say("the object was touched while it changed: please release it")
        raise RunnerError(
            f"the object was touched during {MAX_CHANGE_TRIES} changes in a row; giving up"
        )

    def _record_start(self, exp: Experiment, trial: PlannedTrial, interval: int) -> str:
        """Start recording interval ``interval`` (1 or 2) in the daemon's recording
        directory; its path. A name taken (a trial done again) gets a suffix."""
        number = f"p{trial.position + 1:02d}" if trial.practice else f"{trial.index:04d}"
        base = f"{exp.name}-{self.subject}-{number}-{interval}"
        for attempt in range(1, 100):
            name = base + (f"-{attempt}" if attempt > 1 else "") + ".hrec"
            try:
                with self._talking():
                    return str(self.client.record_start(name)["path"])
            except proto.ProtocolError as exc:
                if exc.code == "recording" and "exists" in str(exc):
                    continue
                raise RunnerError(f"cannot record {name}: {exc.code}: {exc}") from None
        raise RunnerError(f"cannot record {base}: 99 files of that name exist")

    def explore(self, exp: Experiment) -> None:
        """An interval's second step: from the first touch to the release (every finger's contact
        ended) or the exploration limit, as ``interval.ends_on`` says."""
        iv = exp.interval
        self.say("touch the object")
        self.show("touch")
        if not self.contacts:
            ev = self._await(lambda e: e.get("event") == "contact_begin", self.opt.touch_wait_s)
            if ev is None:
                raise RunnerError(f"nobody touched the object within {self.opt.touch_wait_s:g} s")
        if iv.ends_on == "release":
            released = self._await(lambda e: not self.contacts, iv.exploration_s)
        else:
            self._drain(iv.exploration_s)
            released = None
        if released is None and self.contacts:
            self.say("time: please release the object")
            self.show("release")
        else:
            self.show("wait")

    def _ask(self, exp: Experiment, trial: PlannedTrial) -> tuple[bool, float, str]:
        """Ask the question; the first answer (True: the second was more), its response
        time (s) and source. Answers given before the question are ignored."""
        pid = PRACTICE_PROMPTS + trial.position if trial.practice else trial.index
        self.show("answer")
        return self._answer(pid, question_text(exp), "2/y: yes, the second · 1/n: no, the first")

    def _answer(self, pid: int, text: str, keys: str = "y: yes · n: no") -> tuple[bool, float, str]:
        """Ask ``text`` as prompt ``pid`` (choices no and yes; ``keys`` says which keys
        answer it); the first answer (True: yes), its response time (s) and source."""
        if self.keys is not None:
            self.keys.drain()
        self.say(f"{text}  [{keys}]")
        asked = time.monotonic()
        with self._talking():
            self.client.prompt(pid, text, CHOICES)
        prompt_t: float | None = None
        deadline = asked + self.opt.answer_wait_s
        answer: tuple[bool, float, str] | None = None
        while answer is None:
            if self.keys is not None:
                with contextlib.suppress(queue.Empty):
                    while answer is None:
                        key, when = self.keys.keys.get_nowait()
                        if key.lower() in KEYS:
                            answer = (KEYS[key.lower()], when - asked, "key")
                if answer is not None:
                    break
            ev = self._event(min(POLL_S, deadline - time.monotonic()))
            self._check_fault()
            if ev is not None:
                name = ev.get("event")
                if name == "prompt" and ev.get("prompt") == pid:
                    prompt_t = ev.get("t")
                elif name == "prompt" and prompt_t is not None:
                    raise RunnerError(f"another client replaced the prompt ({ev.get('prompt')})")
                elif name == "response" and ev.get("prompt") == pid:
                    answer = (ev.get("choice") == "yes", time.monotonic() - asked, "respond")
                elif name == "button_down" and ev.get("response") and prompt_t is not None:
                    # After the prompt's event: pressed after the question was asked.
                    label = ev["response"]
                    mapped = self.opt.buttons.get(label, BUTTON_LABELS.get(label))
                    if mapped is not None:
                        answer = (mapped, self._rt(ev, prompt_t, asked), "button")
                    elif label not in self._unmapped:
                        self._unmapped.add(label)
                        self.say(f"button {label!r} is not an answer (map it with --buttons)")
            if answer is None and time.monotonic() >= deadline:
                raise RunnerError(f"no answer within {self.opt.answer_wait_s:g} s")
        with self._talking():
            self.client.clear_prompt()
        return answer

    @staticmethod
    def _rt(ev: dict[str, Any], prompt_t: float | None, asked: float) -> float:
        """Response time of a button press: on the daemon's clock (from the prompt's tick
        to the press's, exact to a tick) when the prompt's event was seen, else on ours."""
        t = ev.get("t")
        if prompt_t is not None and isinstance(t, int | float) and t >= prompt_t:
            return float(t) - float(prompt_t)
        return time.monotonic() - asked


# -- the command ---------------------------------------------------------------------------


@dataclass
class RunOptions:
    """What ``hapticd experiment run`` was given besides the experiment and subject."""

    socket: Path | None = None
    keys_fd: int | None = None  # None: no terminal keys
    person: PersonOptions = field(default_factory=PersonOptions)
    out: TextIO = field(default_factory=lambda: sys.stderr)  # the stream at run time
    seed: int | None = None  # the subject's seed (run_experiment sets it)


@contextlib.contextmanager
def person_observer(exp: Experiment, subject: str, options: RunOptions) -> Iterator[Presenter]:
    """A PersonPresenter on the daemon at ``options.socket`` (checked against ``exp``)."""
    from hapticd.profile import load_profile

    profile = load_profile(exp.profile_path())
    try:
        client = ControlClient(options.socket)
    except (OSError, proto.ProtocolError) as exc:
        # A busy daemon (every place in use) or one that speaks another protocol answers
        # with a ProtocolError that says so.
        raise RunnerError(f"cannot reach the daemon: {exc}") from None
    keys = None
    checked: PersonPresenter | None = None
    try:
        presenter = PersonPresenter(
            client, subject=subject, out=options.out, options=options.person
        )
        presenter.take_lease()
        presenter.check_daemon(exp, profile.name)
        checked = presenter  # the daemon runs the base profile: restored at the end
        if options.keys_fd is not None:
            keys = KeyReader(options.keys_fd)
        presenter.keys = keys
        yield presenter
    finally:
        with ending_signals(ignore=True):  # a second signal must not cut the cleanup short
            if keys is not None:
                keys.close()
            if checked is not None:
                if not checked.finished:
                    checked.clear_screen()  # no "touch the object" left up after a stopped run
                checked.withdraw()
                checked.restore(base_values(exp, profile))
            client.close()


class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGHUP (a closed terminal) ending a run: handled as Ctrl-C is (the
    trial stored incomplete, the daemon put back); ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


ENDING_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


def signal_name(exc: BaseException) -> str:
    """The signal that ended a run, as a message says it: SIGTERM, SIGHUP or Ctrl-C."""
    return signal.Signals(exc.signum).name if isinstance(exc, Interrupted) else "Ctrl-C"


@contextlib.contextmanager
def ending_signals(*, ignore: bool = False) -> Iterator[None]:
    """SIGTERM and SIGHUP raise ``Interrupted`` in the block (``ignore``: are ignored,
    as is Ctrl-C: a cleanup under way finishes); the handlers before are put back after.
    Outside the main thread (no handlers there) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise Interrupted(signum)

    handler: Any = signal.SIG_IGN if ignore else interrupt
    which = (*ENDING_SIGNALS, signal.SIGINT) if ignore else ENDING_SIGNALS
    saved = {s: signal.signal(s, handler) for s in which}
    try:
        yield
    finally:
        for s, old in saved.items():
            signal.signal(s, old)


def base_values(exp: Experiment, profile: Any) -> dict[str, Any]:
    """The base ``profile``'s value of every parameter ``exp`` sets (the varied one, the
    allocator, the conditions' parameters), as the control protocol takes them: what a
    run puts back when it ends."""
    from hapticd.params import PARAMS

    names = [exp.varied.param, "allocator"]
    names += [n for c in exp.conditions for n in c.values() if n not in names]
    out = {}
    for name in names:
        value = _profile_value(profile, PARAMS[name].profile_key)
        if value is not None:
            out[name] = PARAMS[name].check(value)
    return out


def _profile_value(profile: Any, key: str) -> Any:
    """The value at a parameter's ``profile_key`` (``scene.object.stiffness_n_per_m``,
    ``fingers[].actuated_directions``: one list per finger; friction as [static,
    dynamic]); None where the profile has none (a fixed object's mass)."""
    head, _, rest = key.partition("[].")
    if rest:
        return [_profile_value(item, rest) for item in getattr(profile, head)]
    value = profile
    for part in key.split("."):
        value = getattr(value, part)
    if hasattr(value, "static") and hasattr(value, "dynamic"):
        return [value.static, value.dynamic]
    if isinstance(value, tuple):
        return [list(v) if isinstance(v, tuple) else v for v in value]
    return value


ObserverFactory = Callable[
    [Experiment, str, RunOptions], contextlib.AbstractContextManager[Presenter]
]
# --observer NAME -> its presenter factory (a context manager: the presenter for the run),
# as "module:function", imported only when chosen: the model observer runs the servo loop
# in this process, which a person's run (a client of the daemon's socket) never loads.
OBSERVERS: dict[str, str] = {
    "person": "hapticd.experiment.runner:person_observer",
    "model": "hapticd.experiment.study:model_observer",
}


def observer_factory(name: str) -> ObserverFactory:
    """The presenter factory of the observer called ``name``; ValueError naming the
    observers there are."""
    entry = OBSERVERS.get(name)
    if entry is None:
        raise ValueError(f"unknown observer {name!r}; observers: {', '.join(OBSERVERS)}")
    module, _, attr = entry.partition(":")
    return getattr(importlib.import_module(module), attr)


def stdin_fd() -> int | None:
    """The file descriptor of the keys (standard input), or None without one."""
    try:
        return sys.stdin.fileno()
    except (AttributeError, OSError, ValueError):
        return None


def parse_buttons(text: str | None) -> dict[str, bool]:
    """``--buttons LABEL=yes,LABEL=no`` as {label: answer}; ValueError naming the item."""
    out: dict[str, bool] = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        label, _, answer = item.partition("=")
        answer = answer.strip().lower()
        if not label.strip() or answer not in ("yes", "no"):
            raise ValueError(f"--buttons: {item!r}: expected LABEL=yes or LABEL=no")
        out[label.strip()] = answer == "yes"
    return out


def run_experiment(
    exp: Experiment,
    subject: str,
    db: Path,
    *,
    seed: int | None = None,
    resume: bool = False,
    observer: str = "person",
    options: RunOptions | None = None,
    subject_index: int | None = None,
    metadata: Mapping[str, str] | None = None,
) -> tuple[int, int]:
    """Run (or resume) ``subject`` on ``exp`` into the store ``db`` with the observer
    named ``observer``; (complete trials recorded now, trials left). ``subject_index``:
    the subject's place in a counterbalanced design (default: in the file's subjects;
    resumed: the last session's); ``metadata``: the session's (``--meta KEY=VALUE``;
    resumed: over the last session's), stored with the session. RunnerError,
    StoreError, ExperimentError, TrialAbortedError as the module says."""
    factory = observer_factory(observer)
    seed = exp.subject_seed(subject) if seed is None else seed
    options = dataclasses.replace(options or RunOptions(), seed=seed)
    out = options.out
    check_subject(subject)
    given = dict(metadata or {})
    if not resume:  # refused before the store is made
        exp.check_metadata(given)
        exp.subject_index(subject, subject_index)
    # One runner per subject: a second one is refused here, before anything is stored.
    # SIGTERM and SIGHUP end the run as Ctrl-C does: the trial incomplete, the daemon back.
    with (
        ending_signals(),
        claim_subject(db, subject),
        TrialStore.for_experiment(db, exp) as store,
    ):
        check_start(store, subject, resume=resume)
        last = (store.sessions(subject) or [{}])[-1] if resume else {}
        if subject_index is None:
            subject_index = last.get("subject_index")
        index = exp.subject_index(subject, subject_index)
        session = exp.check_metadata(given, last.get("metadata"))
        # The observer before the plan: a plan is stored only when it can be presented.
        with factory(exp, subject, options) as presenter:
            if not exp.proc.plans_ahead:
                store.add_session(subject, session, index)
                return _run_adaptive(store, exp, subject, seed, presenter, db, out)
            todo = start_subject(store, exp, subject, seed, resume=resume, subject_index=index)
            store.add_session(subject, session, index)
            return _run(store, exp, subject, seed, presenter, todo, db, out)


def _run_adaptive(
    store: TrialStore,
    exp: Experiment,
    subject: str,
    seed: int,
    presenter: Presenter,
    db: Path,
    out: TextIO,
) -> tuple[int, int]:
    """``run_adaptive_subject`` with the opening line, the instructions and practice, the
    progress lines and the end."""
    say = getattr(presenter, "say", None) or (lambda s: out.write(s + "\n"))
    say(
        f"experiment {exp.name}: subject {subject}, seed {seed}, {exp.procedure}, "
        f"{exp.n_blocks} tracks interleaved; store {db}"
    )
    _opening(store, exp, subject, seed, presenter, say)
    done = run_adaptive_subject(
        store, exp, subject, seed, presenter, profile_hash=profile_hash(exp),
        progress=_progress_lines(presenter, say),
    )  # fmt: skip
    left = len(store.remaining(subject))
    _closing(presenter, left)
    return done, left


def _opening(
    store: TrialStore,
    exp: Experiment,
    subject: str,
    seed: int,
    presenter: Presenter,
    say: Callable[[str], None],
) -> None:
    """Before the session: the instructions (a presenter with ``begin``: a person's) and
    what is left of the practice trials (a presenter that shows a screen)."""
    begin = getattr(presenter, "begin", None)
    if begin is None:
        return  # a simulated observer needs neither
    begin(exp)
    run_practice(store, exp, subject, seed, presenter, profile_hash=profile_hash(exp), say=say)


def _closing(presenter: Presenter, left: int) -> None:
    """The session's end on the subject's screen, once no trial is left."""
    finish = getattr(presenter, "finish", None)
    if finish is not None and left == 0:
        finish()


def _progress_lines(presenter: Presenter, say: Callable[[str], None]) -> Callable[[Progress], None]:
    """The progress as the terminal's lines, and for the subject's screen."""
    note = getattr(presenter, "note_progress", None)

    def show(p: Progress) -> None:
        say(p.line())
        if note is not None:
            note(p)

    return show


def _run(
    store: TrialStore,
    exp: Experiment,
    subject: str,
    seed: int,
    presenter: Presenter,
    todo: list[PlannedTrial],
    db: Path,
    out: TextIO,
) -> tuple[int, int]:
    """``run_subject`` with the opening line and the progress lines."""
    total = len(store.plan(subject))
    if not todo:
        out.write(f"subject {subject!r}: all {total} trials are answered already\n")
        return 0, 0
    say = getattr(presenter, "say", None) or (lambda s: out.write(s + "\n"))
    say(
        f"experiment {exp.name}: subject {subject}, seed {seed}, {len(todo)} of {total} "
        f"trials to do; store {db}"
    )
    _opening(store, exp, subject, seed, presenter, say)
    done = run_subject(
        store,
        exp,
        subject,
        seed,
        presenter,
        profile_hash=profile_hash(exp),
        progress=_progress_lines(presenter, say),
    )
    left = len(store.remaining(subject))
    _closing(presenter, left)
    return done, left


def float_list(text: str) -> list[float]:
    """``60,90`` as [60.0, 90.0]; ValueError for anything else (finite numbers only)."""
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"expected numbers separated by commas, got {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise ValueError(f"expected finite numbers separated by commas, got {text!r}")
    return values


__all__ = [
    "OBSERVERS",
    "DaemonGoneError",
    "PersonPresenter",
    "Presented",
    "Presenter",
    "Progress",
    "RunOptions",
    "RunnerError",
    "StoreError",
    "TrialAbortedError",
    "interval_values",
    "question_text",
    "reduced",
    "run_experiment",
    "run_subject",
    "start_subject",
]
