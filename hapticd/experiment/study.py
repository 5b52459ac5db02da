"""Model-observer subjects and studies: the plan walker that stores each answered trial
as a person's run does (``run_model_subject``), and ``hapticd study``: many simulated
subjects computed in parallel (a process pool, or a Dask cluster) into one trial store
that only the calling process writes."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import os
import sys
import time
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from hapticd.experiment import observer, runner
from hapticd.experiment.plan import PlannedTrial, make_plan
from hapticd.experiment.spec import Experiment, ExperimentError, check_experiment, file_hash
from hapticd.experiment.store import DONE, TrialStore

log = logging.getLogger(__name__)

# Trials per task handed to a worker: large enough that the hand-off (a few ms, 4 kB) is
# cheap beside the simulation (a trial is 30-90 ms of CPU), small enough that the progress
# bar moves and the load spreads over the workers.
CHUNK = 10

Progress = Callable[[int, int], None]


def reduce_design(
    exp: Experiment, *, standards: Sequence[float] | None = None, repetitions: int | None = None
) -> Experiment:
    """``exp`` with only ``standards`` (each one of the file's) and ``repetitions``
    presentations of each comparison: a pilot's or a test's reduced design. The file's
    hash stays: a store holds one experiment file."""
    update: dict[str, Any] = {}
    if standards is not None:
        unknown = [s for s in standards if not any(np.isclose(s, x) for x in exp.varied.standards)]
        if unknown or not standards:
            raise ExperimentError(
                f"{exp.source}: --standards {list(standards)}: each must be one of the file's "
                f"standards {list(exp.varied.standards)}"
            )
        keep = tuple(x for x in exp.varied.standards if any(np.isclose(s, x) for s in standards))
        update["varied"] = exp.varied.model_copy(update={"standards": keep})
    if repetitions is not None and not exp.proc.plans_ahead:
        raise ExperimentError(
            f"{exp.source}: --repetitions: an adaptive procedure has none (its tracks stop "
            "by themselves)"
        )
    if repetitions is not None:
        per = exp.blocks.per_standard
        if (
            repetitions < 1
            or repetitions % per
            or (exp.interval.order == "randomized" and repetitions % 2)
        ):
            raise ExperimentError(
                f"{exp.source}: --repetitions {repetitions}: must be a positive multiple of "
                f"blocks.per_standard ({per})"
                + (
                    ", and even (interval.order randomized)"
                    if exp.interval.order == "randomized"
                    else ""
                )
            )
        update["repetitions"] = repetitions
    return exp.model_copy(update=update) if update else exp


def subject_ids(n: int) -> list[str]:
    """s01, s02, ... (zero-padded to the width of ``n``, at least 2 digits)."""
    width = max(2, len(str(n)))
    return [f"s{i:0{width}d}" for i in range(1, n + 1)]


def study_seed(exp: Experiment, subject: str, seed: int | None) -> int:
    """A subject's seed (its plan's and its observer's): the experiment's per-subject seed,
    or one derived from ``seed`` and the subject's id."""
    if seed is None:
        return exp.subject_seed(subject)
    seq = np.random.SeedSequence([int(seed), zlib.crc32(subject.encode())])
    return int(seq.generate_state(1, np.uint64)[0] >> np.uint64(1))


@dataclass(frozen=True)
class Task:
    """Trials of one subject for a worker: everything it needs, picklable."""

    exp: Experiment
    profile: tuple[str, str]  # observer.profile_document
    config: observer.ObserverConfig
    subject: str
    seed: int
    trials: tuple[PlannedTrial, ...]
    # A staircase (no trials planned ahead): the subject's complete trials so far; the
    # worker runs the rest of the session from them.
    history: tuple[dict[str, Any], ...] = ()


@dataclass(frozen=True)
class Answer:
    """One computed trial, for the store: its answer, or (``failure``: why) none, when
    an exploration failed."""

    subject: str
    trial: PlannedTrial
    answer_second_more: bool | None
    seed: int
    failure: str | None = None


def answer_task(task: Task) -> list[Answer]:
    """A worker's job: the observer's answers to ``task``'s trials, or for a staircase
    the rest of the subject's session after its history (no I/O); a trial whose
    exploration failed has no answer, its failure's cause instead."""
    profile = observer.profile_from_document(task.profile)

    def answer(trial: PlannedTrial) -> Answer:
        r = observer.answer_trial(task.exp, profile, task.config, trial, task.subject, task.seed)
        return Answer(task.subject, trial, r.answer_second_more, task.seed, r.failure)

    proc = task.exp.proc
    if proc.plans_ahead:
        return [answer(trial) for trial in task.trials]
    answers: dict[int, Answer] = {}

    def judged_more(trial: PlannedTrial) -> bool | None:
        a = answers[trial.index] = answer(trial)
        return (
            None if a.answer_second_more is None else a.answer_second_more != trial.comparison_first
        )

    rest = proc.session(task.exp, task.seed, judged_more, task.history)
    return [answers[t.index] for t, _ in rest]


def _load(
    exp_or_path: Experiment | str | Path,
    standards: Sequence[float] | None,
    repetitions: int | None,
) -> Experiment:
    exp = check_experiment(exp_or_path)[0] if isinstance(exp_or_path, str | Path) else exp_or_path
    return reduce_design(exp, standards=standards, repetitions=repetitions)


def _record(store: TrialStore, a: Answer, profile_hash: str) -> None:
    store.record(
        a.subject,
        a.trial,
        answer_second_more=a.answer_second_more,
        response_time_s=None,
        profile_hash=profile_hash,
        seed=a.seed,
        recording=None,
        status="complete" if a.failure is None else "failed",
        source="model",
        failure=a.failure,
    )


class ModelPresenter:
    """The model observer as a runner's Presenter (hapticd.experiment.runner): each trial
    is answered by ``observer.answer_trial`` in this process (two simulated explorations,
    the sensory model); no recording, no response time, no breaks."""

    def __init__(
        self, exp: Experiment, subject: str, seed: int, config: observer.ObserverConfig
    ) -> None:
        self.subject, self.seed, self.config = subject, seed, config
        # Checked here (ProfileError, ExperimentError), before a plan is stored.
        self.profile = observer.profile_from_document(observer.profile_document(exp, config))

    def present(
        self, exp: Experiment, trial: PlannedTrial, params: Mapping[str, Any]
    ) -> runner.Presented:
        r = observer.answer_trial(exp, self.profile, self.config, trial, self.subject, self.seed)
        if r.failure is not None:  # stored failed, never judged from a broken cue
            return runner.Presented(None, None, status="failed", source="model", failure=r.failure)
        return runner.Presented(r.answer_second_more, None, source="model")

    def rest(self, seconds: float) -> None:
        """A simulated subject needs no break."""


@contextlib.contextmanager
def model_observer(
    exp: Experiment, subject: str, options: runner.RunOptions
) -> Iterator[ModelPresenter]:
    """``hapticd experiment run --observer model``: the model observer for ``subject``
    with the run's seed (the experiment's per-subject seed unless ``--seed``)."""
    seed = exp.subject_seed(subject) if options.seed is None else options.seed
    presenter = ModelPresenter(exp, subject, seed, observer.default_config(exp))
    # Before any trial: a design its hand cannot perform is refused with the cause.
    observer.pilot_check(exp, presenter.profile, presenter.config)
    yield presenter


def run_model_subject(
    exp_path_or_exp: Experiment | str | Path,
    subject: str,
    store: TrialStore,
    seed: int | None,
    *,
    standards: Sequence[float] | None = None,
    repetitions: int | None = None,
    progress: Progress | None = None,
    config: observer.ObserverConfig | None = None,
) -> int:
    """Walk ``subject``'s plan with the model observer in this process, storing each trial
    as soon as it is answered, as a person's run does (``ensure_plan``, ``remaining``,
    ``record``: status complete, no recording, the profile's hash, the seed). Resumes a
    subject already in the store. ``seed`` None: the experiment's per-subject seed.
    ``progress(done, total)`` after each trial. Returns the trials answered now."""
    exp = _load(exp_path_or_exp, standards, repetitions)
    s = study_seed(exp, subject, seed)
    presenter = ModelPresenter(exp, subject, s, config or observer.default_config(exp))
    if not exp.proc.plans_ahead:
        return runner.run_adaptive_subject(
            store, exp, subject, s, presenter, profile_hash=file_hash(exp.profile_path()),
            progress=None if progress is None else lambda p: progress(p.done, p.total),
        )  # fmt: skip
    store.ensure_plan(subject, make_plan(exp, s, exp.subject_index(subject)), s)
    left = len(store.remaining(subject))
    runner.run_subject(
        store,
        exp,
        subject,
        s,
        presenter,
        profile_hash=file_hash(exp.profile_path()),
        progress=None if progress is None else lambda p: progress(p.done, p.total),
    )
    return left


class ProgressBar:
    """A text progress bar over trials on ``stream`` (stderr), redrawn in place on a
    terminal, a line every 10 % otherwise."""

    def __init__(self, total: int, stream: TextIO | None = None, width: int = 30) -> None:
        self.total, self.width = total, width
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.t0 = time.monotonic()
        self._last_decile = -1
        self._first: int | None = None  # trials done before this run (a resumed study)

    def __call__(self, done: int, total: int | None = None) -> None:
        total = self.total if total is None else total
        frac = done / total if total else 1.0
        if self._first is None:
            self._first = done
        elapsed = time.monotonic() - self.t0
        rate = (done - self._first) / elapsed if elapsed > 0 else 0.0
        left = (total - done) / rate if rate > 0 else float("nan")
        n = int(frac * self.width)
        eta = f"{left / 60:.1f} min left" if left == left else "estimating"
        text = (
            f"[{'#' * n}{'.' * (self.width - n)}] {done}/{total} trials "
            f"{100 * frac:5.1f}% {rate:.1f} trials/s {eta}"
        )
        if self.tty:
            self.stream.write("\r" + text + ("\n" if done >= total else ""))
            self.stream.flush()
        elif int(10 * frac) > self._last_decile or done >= total:
            self._last_decile = int(10 * frac)
            self.stream.write(text + "\n")
            self.stream.flush()


@dataclass
class StudyResult:
    subjects: list[str]
    answered: int  # trials computed in this run
    total: int  # trials in every subject's plan
    seconds: float
    failed: int = 0  # of those computed now, trials whose exploration failed (not judged)


def _chunks(trials: Sequence[PlannedTrial], n: int) -> Iterator[tuple[PlannedTrial, ...]]:
    for i in range(0, len(trials), n):
        yield tuple(trials[i : i + n])


def run_study(
    exp_path_or_exp: Experiment | str | Path,
    n_observers: int,
    db: str | Path,
    *,
    seed: int | None = None,
    workers: int | None = None,
    standards: Sequence[float] | None = None,
    repetitions: int | None = None,
    scheduler: str | Any | None = None,
    progress: Progress | None = None,
    config: observer.ObserverConfig | None = None,
) -> StudyResult:
    """Run ``n_observers`` model subjects (s01..) into the trial store ``db``: their
    trials are computed by a process pool of ``workers`` (default: the cores; 1: in this
    process), or on the Dask cluster at ``scheduler`` (an address, or a
    ``distributed.Client``); this process alone writes the store, trial by trial as
    results come back. Re-running continues unfinished subjects. The stored answers
    depend only on the experiment, the design, ``seed`` and the subject ids."""
    if n_observers < 1:
        raise ExperimentError(f"--observers must be at least 1, got {n_observers}")
    if workers is not None and workers < 1:
        raise ExperimentError(f"--workers must be at least 1, got {workers}")
    exp = _load(exp_path_or_exp, standards, repetitions)
    config = config or observer.default_config(exp)
    profile = observer.profile_document(exp, config)
    # Before any plan is stored: a design the hand cannot perform is refused with the cause.
    observer.pilot_check(exp, observer.profile_from_document(profile), config)
    profile_hash = file_hash(exp.profile_path())
    t0 = time.monotonic()
    tasks: list[Task] = []
    total = done = 0
    subjects = subject_ids(n_observers)
    adaptive = not exp.proc.plans_ahead
    with TrialStore.for_experiment(db, exp) as store:
        for k, subject in enumerate(subjects):
            s = study_seed(exp, subject, seed)
            if adaptive:
                # Each subject's session is one task: its next trials depend on its answers.
                history = tuple(
                    r for r in store.trials(None) if r["subject"] == subject and r["status"] in DONE
                )
                total += exp.n_blocks * exp.trials_per_block
                tasks.append(Task(exp, profile, config, subject, s, (), history))
                continue
            # Subject k of the study is subject k of a counterbalanced design.
            plan = make_plan(
                exp, s, exp.subject_index(subject, None if subject in exp.subjects else k)
            )
            store.ensure_plan(subject, plan, s)
            rest = store.remaining(subject)
            total += len(plan)
            done += len(plan) - len(rest)
            tasks += [
                Task(exp, profile, config, subject, s, chunk) for chunk in _chunks(rest, CHUNK)
            ]
        if progress is not None:
            progress(done, total)
        answered = failed = 0
        for answers in _execute(tasks, workers, scheduler):
            for a in answers:
                failed += a.failure is not None
                if adaptive and a.trial.index >= len(store.plan(a.subject)):
                    store.append_plan(a.subject, a.trial, a.seed)
                _record(store, a, profile_hash)
            answered += len(answers)
            done += len(answers)
            if progress is not None:
                progress(done, total)
    return StudyResult(subjects, answered, total, time.monotonic() - t0, failed)


def _execute(
    tasks: list[Task], workers: int | None, scheduler: str | Any | None
) -> Iterable[list[Answer]]:
    """Each task's answers, in the order they finish."""
    if not tasks:
        return
    if scheduler is not None:
        yield from _on_dask(tasks, scheduler)
        return
    n = workers or os.cpu_count() or 1
    if n == 1:
        for task in tasks:
            yield answer_task(task)
        return
    with cf.ProcessPoolExecutor(max_workers=min(n, len(tasks))) as pool:
        futures = [pool.submit(answer_task, t) for t in tasks]
        try:
            for fut in cf.as_completed(futures):
                yield fut.result()
        except BaseException:
            for fut in futures:
                fut.cancel()
            raise


def _on_dask(tasks: list[Task], scheduler: str | Any) -> Iterator[list[Answer]]:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ExperimentError(
            "--scheduler needs dask.distributed: pip install 'hapticd[dask]'"
        ) from None
    own = isinstance(scheduler, str)
    client = Client(scheduler, timeout="30s") if own else scheduler
    try:
        for note in dask_advice(client):
            log.warning("%s", note)
        futures = client.map(answer_task, tasks, pure=False)
        for fut in as_completed(futures):
            yield fut.result()
    finally:
        if own:
            client.close()


def _worker_setup(dask_worker: Any) -> tuple[int, bool]:
    """A Dask worker's threads and whether its statistical profiler runs."""
    return int(dask_worker.state.nthreads), "profile" in dask_worker.periodic_callbacks


def dask_advice(client: Any) -> list[str]:
    """How the cluster's workers would compute a study faster, measured
    (docs/experiments.md): one thread each (a trial holds Python's interpreter lock),
    no statistical profiler (it cost about 7 % of a worker's CPU). Empty when they are
    so, or when the workers cannot be asked."""
    try:
        setups = list(client.run(_worker_setup).values())
    except Exception:  # a cluster that refuses run(): no advice, the study still runs
        return []
    notes = []
    threaded = [n for n, _ in setups if n > 1]
    if threaded:
        notes.append(
            f"{len(threaded)} of {len(setups)} Dask workers run {max(threaded)} threads: a "
            "study's trial holds Python's interpreter lock, so start one single-threaded "
            "worker per core (dask worker ADDRESS --nthreads 1)"
        )
    profiled = sum(p for _, p in setups)
    if profiled:
        notes.append(
            f"{profiled} of {len(setups)} Dask workers run Dask's statistical profiler "
            "(about 7 % of their CPU in a study): start them with "
            "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False"
        )
    return notes


def cmd_study(args: Any) -> int:
    """``hapticd study``: the command's work (cli.py parses its arguments). Exit 0, or 2
    with a message for bad input."""
    from hapticd.experiment.store import StoreError
    from hapticd.profile import ProfileError

    db = args.db or Path(f"study-{Path(args.experiment).stem}.sqlite")
    bar: Progress | None = None
    if not args.quiet:

        def bar(done: int, total: int) -> None:
            nonlocal real
            if real is None:
                real = ProgressBar(total)
            real(done, total)

        real: ProgressBar | None = None
    try:
        judgement = getattr(args, "judgement", None)
        angle = getattr(args, "actuation_angle_deg", None)
        config = None
        if judgement is not None or angle is not None:
            exp = check_experiment(args.experiment)[0]
            config = observer.default_config(
                exp, judgement=judgement or "weber", actuation_angle_deg=angle
            )
        result = run_study(
            args.experiment,
            args.observers,
            db,
            seed=args.seed,
            workers=args.workers,
            standards=args.standards,
            repetitions=args.repetitions,
            scheduler=args.scheduler,
            progress=bar,
            config=config,
        )
    except (ExperimentError, ProfileError, StoreError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a scheduler that cannot be reached, a db that cannot be made
        print(f"hapticd: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # Every answered trial is committed; the plans are stored: a re-run continues.
        print(
            f"\nhapticd: interrupted; the answered trials are in {db}; run the same command "
            "again to continue",
            file=sys.stderr,
        )
        return 130
    print(
        f"{db}: {len(result.subjects)} model observers ({result.subjects[0]}.."
        f"{result.subjects[-1]}), {result.total} trials, {result.answered} computed now in "
        f"{result.seconds:.1f} s"
        + (
            f" ({result.failed} of them failed: the hand's exploration, stored as failed, "
            "never judged)"
            if result.failed
            else ""
        )
        + f"; analyse with: hapticd experiment analyze {db}"
    )
    return 0
