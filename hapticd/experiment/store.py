"""The trial store: one SQLite file (WAL) per experiment, a row per trial, committed as
soon as the trial is answered, and each subject's plan so a run can resume."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import sqlite3
import time
from collections.abc import Iterator, Sequence
from dataclasses import astuple, fields
from pathlib import Path
from typing import Any, Literal

from hapticd import params
from hapticd.experiment.plan import PlannedTrial
from hapticd.experiment.spec import Experiment

SCHEMA_VERSION = 3
# Stores this hapticd reads; a writer brings an older one up to SCHEMA_VERSION (MIGRATIONS).
READABLE_SCHEMAS = (1, 2, 3)
# A trial's status: answered; presented but not answered (stays to be done); presented,
# but the exploration failed (the model observer's: a cube that slipped, no contact, a
# cue off), never judged, not presented again.
STATUSES = ("complete", "incomplete", "failed")
# Statuses that settle a planned trial: it is not presented again.
DONE = ("complete", "failed")

# The trials table (``name``: the table's, or IF NOT EXISTS and it) and its index: a
# planned trial is completed or failed once only.
_TRIALS = """CREATE TABLE {name} (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    subject TEXT NOT NULL,
    plan_index INTEGER NOT NULL,
    experiment TEXT NOT NULL,
    experiment_hash TEXT NOT NULL,
    condition TEXT NOT NULL,
    standard REAL NOT NULL,
    comparison REAL NOT NULL,
    comparison_first INTEGER NOT NULL,
    answer_second_more INTEGER,        -- 1: "yes, the second was stiffer/heavier"
    comparison_more INTEGER,           -- 1: the comparison was judged more
    response_time_s REAL,
    recording TEXT,
    profile_hash TEXT NOT NULL,
    seed INTEGER NOT NULL,
    time_unix_s REAL NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('complete', 'incomplete', 'failed')),
    source TEXT,                       -- key, button, respond, model (None: not answered)
    failure TEXT,                      -- status failed: why the exploration failed
    FOREIGN KEY (subject, plan_index) REFERENCES plan (subject, "index")
)"""
_INDEX = """CREATE UNIQUE INDEX IF NOT EXISTS one_answer_per_planned_trial
    ON trials (subject, plan_index) WHERE status IN ('complete', 'failed')"""

_SCHEMA = (
    """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS plan (
    subject TEXT NOT NULL,
    "index" INTEGER NOT NULL,
    block INTEGER NOT NULL,
    position INTEGER NOT NULL,
    condition TEXT NOT NULL,
    standard REAL NOT NULL,
    ratio REAL NOT NULL,
    comparison REAL NOT NULL,
    comparison_first INTEGER NOT NULL,
    break_before_s REAL NOT NULL,
    seed INTEGER NOT NULL,
    PRIMARY KEY (subject, "index")
);
"""
    + _TRIALS.format(name="IF NOT EXISTS trials")
    + ";\n"
    + _INDEX
    + ";\n"
)
_V2_COLUMNS = (
    "id, subject, plan_index, experiment, experiment_hash, condition, standard, comparison, "
    "comparison_first, answer_second_more, comparison_more, response_time_s, recording, "
    "profile_hash, seed, time_unix_s, status, source"
)
# schema n -> the statements that make it n + 1.
MIGRATIONS: dict[int, tuple[str, ...]] = {
    1: ("ALTER TABLE trials ADD COLUMN source TEXT",),  # where the answer came from
    # The status failed and its cause: SQLite changes a CHECK only by copying the table.
    2: (
        _TRIALS.format(name="trials_v3"),
        f"INSERT INTO trials_v3 ({_V2_COLUMNS}) SELECT {_V2_COLUMNS} FROM trials",
        "DROP TABLE trials",
        "ALTER TABLE trials_v3 RENAME TO trials",
        _INDEX,
    ),
}

_PLAN_COLUMNS = [f.name for f in fields(PlannedTrial)]


class StoreError(RuntimeError):
    """A trial store that cannot be used as asked; the message says why and what to do."""


class TrialStore:
    """The trials of one experiment (its name and file hash) in the SQLite file ``path``.

    A new file is created; an existing one must hold the same experiment, else
    StoreError. ``record`` commits each trial at once (synchronous=FULL), so a crash
    loses at most the trial in progress.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        experiment: str,
        experiment_hash: str,
        design: dict[str, Any] | None = None,
    ) -> None:
        self.path = Path(path)
        self.experiment, self.experiment_hash = experiment, experiment_hash
        self._design = design or {}
        self._db = _connect(self.path)
        try:
            self._init_meta()
        except BaseException:
            self._db.close()
            raise

    def _init_meta(self) -> None:
        try:
            _has_tables(self._db)
        except StoreError as exc:
            raise StoreError(f"{self.path}: {exc}") from None
        self._db.executescript(_SCHEMA)
        with self._db:
            meta = dict(self._db.execute("SELECT key, value FROM meta"))
            if not meta:
                self._db.executemany(
                    "INSERT INTO meta VALUES (?, ?)",
                    [
                        ("schema", str(SCHEMA_VERSION)),
                        ("experiment", self.experiment),
                        ("experiment_hash", self.experiment_hash),
                        ("created_unix_s", repr(time.time())),
                        ("design", json.dumps(self._design, sort_keys=True)),
                    ],
                )
                return
        _check_schema(self.path, meta)
        self._migrate(int(meta["schema"]))
        if meta.get("experiment_hash") != self.experiment_hash:
            same = meta.get("experiment") == self.experiment
            why = (
                "the experiment file changed since this database was started"
                if same
                else "it belongs to another experiment"
            )
            raise StoreError(
                f"{self.path}: refused: {why}: the database holds experiment "
                f"{meta.get('experiment')!r} (file sha256 {meta.get('experiment_hash', '')[:12]}), "
                f"this is {self.experiment!r} (sha256 {self.experiment_hash[:12]}); "
                "use another database file (or restore the experiment file it was started with)"
            )

    def _migrate(self, schema: int) -> None:
        """Bring a store of an older schema up to SCHEMA_VERSION, in one transaction."""
        if schema == SCHEMA_VERSION:
            return
        with self._db:
            self._db.execute("BEGIN IMMEDIATE")  # the DDL too: all of it or nothing
            for n in range(schema, SCHEMA_VERSION):
                for statement in MIGRATIONS[n]:
                    self._db.execute(statement)
            self._db.execute(
                "UPDATE meta SET value = ? WHERE key = 'schema'", (str(SCHEMA_VERSION),)
            )

    @classmethod
    def for_experiment(cls, path: str | Path, exp: Experiment) -> TrialStore:
        """The store of the loaded experiment ``exp`` at ``path``; its design (the
        varied parameter and unit, standards, ratios, conditions, question) goes into
        the meta table for the analysis."""
        return cls(path, experiment=exp.name, experiment_hash=exp.file_hash, design=design(exp))

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> TrialStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # The plan -----------------------------------------------------------------------

    def ensure_plan(self, subject: str, plan: Sequence[PlannedTrial], seed: int) -> None:
        """Store ``subject``'s plan, or check that the stored one is this very plan."""
        stored = self.plan(subject)
        if stored:
            old_seed = self._db.execute(
                "SELECT seed FROM plan WHERE subject = ? LIMIT 1", (subject,)
            ).fetchone()[0]
            if old_seed != seed or stored != list(plan):
                raise StoreError(
                    f"{self.path}: subject {subject!r} already has a plan of {len(stored)} "
                    f"trials (seed {old_seed}) that differs from this one ({len(plan)} trials, "
                    f"seed {seed}); resume with the same seed, or use another subject id"
                )
            return
        with self._db:
            self._db.executemany(
                f"INSERT INTO plan VALUES (?, {', '.join('?' * len(_PLAN_COLUMNS))}, ?)",
                [(subject, *astuple(t), seed) for t in plan],
            )

    def append_plan(self, subject: str, trial: PlannedTrial, seed: int) -> None:
        """Add one decided trial to ``subject``'s plan (an adaptive procedure decides each
        trial from the answers before it); StoreError unless it is the next index."""
        with self._db:
            n = self._db.execute("SELECT COUNT(*) FROM plan WHERE subject = ?", (subject,))
            if trial.index != n.fetchone()[0]:
                raise StoreError(
                    f"{self.path}: subject {subject!r}: trial {trial.index} is not the next "
                    "of its plan"
                )
            self._db.execute(
                f"INSERT INTO plan VALUES (?, {', '.join('?' * len(_PLAN_COLUMNS))}, ?)",
                (subject, *astuple(trial), seed),
            )

    def plan(self, subject: str) -> list[PlannedTrial]:
        cols = ", ".join(f'"{c}"' for c in _PLAN_COLUMNS)
        rows = self._db.execute(
            f'SELECT {cols} FROM plan WHERE subject = ? ORDER BY "index"', (subject,)
        ).fetchall()
        return [_planned(r) for r in rows]

    def remaining(self, subject: str) -> list[PlannedTrial]:
        """The planned trials of ``subject`` not done (neither complete nor failed), in
        order."""
        cols = ", ".join(f'p."{c}"' for c in _PLAN_COLUMNS)
        rows = self._db.execute(
            f"""SELECT {cols} FROM plan p WHERE p.subject = ? AND NOT EXISTS (
                    SELECT 1 FROM trials t WHERE t.subject = p.subject
                    AND t.plan_index = p."index" AND t.status IN ('complete', 'failed'))
                ORDER BY p."index" """,
            (subject,),
        ).fetchall()
        return [_planned(r) for r in rows]

    def next_trial(self, subject: str) -> PlannedTrial | None:
        rest = self.remaining(subject)
        return rest[0] if rest else None

    # Trials ------------------------------------------------------------------------

    def record(
        self,
        subject: str,
        trial: PlannedTrial,
        *,
        answer_second_more: bool | None,
        response_time_s: float | None,
        profile_hash: str,
        seed: int,
        recording: str | None = None,
        status: Literal["complete", "incomplete", "failed"] = "complete",
        time_unix_s: float | None = None,
        source: str | None = None,
        failure: str | None = None,
    ) -> int:
        """Store one trial and commit it before returning; its row id. A complete trial
        needs an answer; a failed one (its exploration failed) needs ``failure``, the
        cause, and has no answer; a planned trial is completed or failed once only.
        ``source``: where the answer came from (``key``, ``button``, ``respond``,
        ``model``)."""
        if status == "complete" and answer_second_more is None:
            raise ValueError("a complete trial needs an answer")
        if (status == "failed") != (failure is not None):
            raise ValueError("a failed trial, and only a failed one, needs its failure's cause")
        if status == "failed" and answer_second_more is not None:
            raise ValueError("a failed trial is not judged: it has no answer")
        more = None
        if answer_second_more is not None:
            # "Was the second more?": the comparison was judged more when it was second
            # and the answer is yes, or first and the answer is no.
            more = int(bool(answer_second_more) != trial.comparison_first)
        try:
            with self._db:
                cur = self._db.execute(
                    """INSERT INTO trials (subject, plan_index, experiment, experiment_hash,
                        condition, standard, comparison, comparison_first, answer_second_more,
                        comparison_more, response_time_s, recording, profile_hash, seed,
                        time_unix_s, status, source, failure) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?,
                        ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
                    (
                        subject,
                        trial.index,
                        self.experiment,
                        self.experiment_hash,
                        trial.condition,
                        trial.standard,
                        trial.comparison,
                        int(trial.comparison_first),
                        None if answer_second_more is None else int(bool(answer_second_more)),
                        more,
                        response_time_s,
                        recording,
                        profile_hash,
                        seed,
                        time.time() if time_unix_s is None else time_unix_s,
                        status,
                        source,
                        failure,
                    ),
                )
        except sqlite3.IntegrityError as exc:
            raise StoreError(
                f"{self.path}: trial {trial.index} of subject {subject!r} cannot be stored: "
                f"{exc} (already answered or failed, or not in the subject's plan)"
            ) from None
        return int(cur.lastrowid or 0)

    def trials(self, status: str | None = "complete") -> list[dict[str, Any]]:
        return read_trials(self._db, status)


@contextlib.contextmanager
def claim_subject(db: str | Path, subject: str) -> Iterator[Path]:
    """Hold ``subject``'s run on the store ``db`` for the block: an exclusive lock
    (flock) on the file ``DB.SUBJECT.lock`` beside the store, which the system releases
    when the holder ends, even by SIGKILL. StoreError when another process holds it (a
    second runner on the same subject), naming the store, the subject and the holder's
    process id. Yields the lock file's path."""
    path = Path(db)
    lock = path.with_name(f"{path.name}.{subject}.lock")
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    except OSError as exc:
        raise StoreError(f"{path}: cannot lock subject {subject!r}: {lock}: {exc}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            raise StoreError(
                f"{path}: subject {subject!r} is being run by another runner (process "
                f"{holder}): one runner per subject and store; wait for it to end, or stop it "
                f"(its lock: {lock})"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield lock
    finally:
        os.close(fd)  # releases the lock


def design(exp: Experiment) -> dict[str, Any]:
    """What the analysis needs to know of an experiment, JSON-ready."""
    return {
        "param": exp.varied.param,
        "unit": params.PARAMS[exp.varied.param].unit,
        "standards": list(exp.varied.standards),
        "ratios": list(exp.varied.ratios),
        "conditions": [c.name for c in exp.conditions],
        "question": exp.interval.question,
        "jnd_point": exp.analysis.jnd_point,
        "procedure": exp.procedure,
        "staircase": None if exp.staircase is None else exp.staircase.model_dump(),
        "quest_plus": None if exp.quest_plus is None else exp.quest_plus.model_dump(),
    }


def _connect(path: Path) -> sqlite3.Connection:
    try:
        db = sqlite3.connect(path, isolation_level="DEFERRED")
        db.execute("PRAGMA foreign_keys = ON")
        mode = db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        db.execute("PRAGMA synchronous = FULL")
    except sqlite3.DatabaseError as exc:
        raise StoreError(f"{path}: not a trial store (SQLite): {exc}") from None
    if mode != "wal":
        db.close()
        raise StoreError(f"{path}: cannot use write-ahead logging (journal mode {mode})")
    return db


def _has_tables(db: sqlite3.Connection) -> bool:
    names = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    if names and not {"meta", "plan", "trials"} <= names:
        raise StoreError("not a trial store: it holds other tables: " + ", ".join(sorted(names)))
    return bool(names)


def _check_schema(path: Path, meta: dict[str, str]) -> None:
    if meta.get("schema") not in {str(n) for n in READABLE_SCHEMAS}:
        raise StoreError(
            f"{path}: trial store schema {meta.get('schema')!r}, this hapticd reads "
            f"{', '.join(map(str, READABLE_SCHEMAS))}"
        )


def _planned(row: Sequence[Any]) -> PlannedTrial:
    d = dict(zip(_PLAN_COLUMNS, row, strict=True))
    d["comparison_first"] = bool(d["comparison_first"])
    return PlannedTrial(**d)


# The trials table's number columns (SQLite stores whatever it is given: a damaged or
# hand-edited store can hold text there), and those that may be empty.
_NUMBER_COLUMNS = (
    "plan_index",
    "standard",
    "comparison",
    "comparison_first",
    "answer_second_more",
    "comparison_more",
    "response_time_s",
    "time_unix_s",
)
_NULLABLE = {"answer_second_more", "comparison_more", "response_time_s"}


def read_trials(db: sqlite3.Connection, status: str | None = "complete") -> list[dict[str, Any]]:
    """The trials (all with ``status`` None), in the order stored, each with its plan's
    ``block``."""
    db.row_factory = sqlite3.Row
    try:
        where = "" if status is None else "WHERE t.status = ?"
        args = () if status is None else (status,)
        rows = db.execute(
            f"""SELECT t.*, p.block FROM trials t LEFT JOIN plan p
                ON p.subject = t.subject AND p."index" = t.plan_index {where} ORDER BY t.id""",
            args,
        ).fetchall()
        return [dict(r) for r in rows]
    finally:
        db.row_factory = None


def _check_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """StoreError naming the row and column of the first value that is not a number
    where a number belongs."""
    for r in rows:
        for col in _NUMBER_COLUMNS:
            v = r.get(col)
            if v is None and col in _NULLABLE:
                continue
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise StoreError(
                    f"{path}: damaged: trials row {r.get('id')} (subject {r.get('subject')!r}, "
                    f"trial {r.get('plan_index')!r}): {col} holds {v!r}, not a number; "
                    "fix or delete that row (sqlite3) and try again"
                )


def open_for_analysis(
    path: str | Path, status: str | None = "complete"
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The meta table (``design`` decoded) and the trials of the store at ``path`` (the
    complete ones; all with ``status`` None), read only (nothing in it changes).
    StoreError naming the store and what is wrong: not a store, another schema, a
    damaged file (a garbled page), a design that is not JSON, text in a number column."""
    p = Path(path)
    if not p.is_file():
        raise StoreError(f"{p}: no such trial store")
    try:
        db = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
    except sqlite3.DatabaseError as exc:
        raise StoreError(f"{p}: cannot open: {exc}") from None
    try:
        try:
            _has_tables(db)
            meta = dict(db.execute("SELECT key, value FROM meta"))
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{p}: not a trial store (SQLite): {exc}") from None
        _check_schema(p, meta)
        out: dict[str, Any] = dict(meta)
        try:
            out["design"] = json.loads(meta.get("design") or "{}")
        except ValueError as exc:
            raise StoreError(f"{p}: damaged: meta.design is not JSON ({exc})") from None
        if not isinstance(out["design"], dict):
            raise StoreError(f"{p}: damaged: meta.design is not a JSON object")
        try:
            rows = read_trials(db, status)
        except sqlite3.DatabaseError as exc:
            raise StoreError(
                f"{p}: damaged: the trials cannot be read ({exc}); sqlite3's .recover "
                "salvages what is readable into a new file"
            ) from None
        _check_rows(p, rows)
        return out, rows
    finally:
        db.close()
