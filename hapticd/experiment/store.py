"""The trial store: one SQLite file (WAL) per experiment, a row per trial, committed as
soon as the trial is answered, and each subject's plan so a run can resume."""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import sqlite3
import time
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import astuple, fields
from pathlib import Path
from typing import Any, Literal

from hapticd import params
from hapticd.experiment.plan import PlannedTrial
from hapticd.experiment.spec import Experiment

SCHEMA_VERSION = 4
# Stores this hapticd reads; a writer brings an older one up to SCHEMA_VERSION (MIGRATIONS).
READABLE_SCHEMAS = (1, 2, 3, 4)
# A trial's status: answered; presented but not answered (stays to be done); presented,
# but the exploration failed (the model observer's: a cube that slipped, no contact, a
# cue off), never judged, not presented again.
STATUSES = ("complete", "incomplete", "failed")
# Statuses that settle a planned trial: it is not presented again.
DONE = ("complete", "failed")

# Schema 4: a practice trial (1; its plan index negative), never analysed.
_PRACTICE = "\n    practice INTEGER NOT NULL DEFAULT 0,"
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
    failure TEXT,                      -- status failed: why the exploration failed{practice}
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
    practice INTEGER NOT NULL DEFAULT 0,
    PRIMARY KEY (subject, "index")
);
"""
    + _TRIALS.format(name="IF NOT EXISTS trials", practice=_PRACTICE)
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
        _TRIALS.format(name="trials_v3", practice=""),
        f"INSERT INTO trials_v3 ({_V2_COLUMNS}) SELECT {_V2_COLUMNS} FROM trials",
        "DROP TABLE trials",
        "ALTER TABLE trials_v3 RENAME TO trials",
        _INDEX,
    ),
    # Practice trials: flagged in the plan and the trials.
    3: (
        "ALTER TABLE plan ADD COLUMN practice INTEGER NOT NULL DEFAULT 0",
        "ALTER TABLE trials ADD COLUMN practice INTEGER NOT NULL DEFAULT 0",
    ),
}

_PLAN_COLUMNS = [f.name for f in fields(PlannedTrial)]
# By name: a store brought up from an older schema has the practice column last.
_INSERT_PLAN = (
    "INSERT INTO plan (subject, "
    + ", ".join(f'"{c}"' for c in _PLAN_COLUMNS)
    + f", seed) VALUES (?, {', '.join('?' * len(_PLAN_COLUMNS))}, ?)"
)

# One row per run of a subject (a start or a resume) and its metadata. Its trials are
# those of the subject stored after it began: ids above ``after_trial`` (trial ids only
# grow, and one runner per subject and store runs at a time). Created when a run first
# stores a session: a store without it is read as one of no sessions.
_SESSIONS = """CREATE TABLE IF NOT EXISTS sessions (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    subject TEXT NOT NULL,
    subject_index INTEGER,             -- its place in the counterbalancing (None: none)
    after_trial INTEGER NOT NULL,      -- the largest trial id when the session began
    started_unix_s REAL NOT NULL,
    metadata TEXT NOT NULL             -- JSON object: key -> value (docs/experiments.md)
)"""


class StoreError(RuntimeError):
    """A trial store that cannot be used as asked; the message says why and what to do."""


class StoreWarning(UserWarning):
    """A trial store read with damage: what is readable is returned, the message names
    the store and the damaged pages."""


# How to salvage a damaged store (the sqlite3 shell's .recover), for the messages.
_RECOVER = (
    "sqlite3 {path} .recover | sqlite3 NEW.db salvages what is readable into NEW.db "
    "(resume or export from NEW.db)"
)


@contextlib.contextmanager
def _readable(path: Path, doing: str) -> Iterator[None]:
    """StoreError naming ``path`` for SQLite's own errors (a garbled page, text that is
    not UTF-8) while ``doing``; the store is left as it is."""
    try:
        yield
    except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
        raise StoreError(
            f"{path}: damaged: {doing} failed ({exc}); nothing was written; "
            + _RECOVER.format(path=path)
        ) from None


def damage(db: sqlite3.Connection, limit: int = 5) -> list[str]:
    """SQLite's quick check of ``db``: its first ``limit`` findings (each names the
    damaged page, cell or column); empty when the file is sound."""
    found: list[str] = []
    for (line,) in db.execute(f"PRAGMA quick_check({int(limit)})"):
        found += [x for x in str(line).splitlines() if x and not x.startswith("***")]
    return [] if found == ["ok"] else found


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
        with _readable(self.path, "opening the store"):
            self._open_meta()

    def _open_meta(self) -> None:
        try:
            exists = _has_tables(self._db)
        except StoreError as exc:
            raise StoreError(f"{self.path}: {exc}") from None
        # Before anything is written: a damaged store is refused, never written into.
        if exists and (
            bad := self._db.execute(
                f"SELECT id, status FROM trials WHERE status NOT IN "
                f"({', '.join('?' * len(STATUSES))}) ORDER BY id LIMIT 1",
                STATUSES,
            ).fetchone()
        ):
            # A hand edit past an older schema's check: upgrading would fail on it.
            raise StoreError(
                f"{self.path}: damaged: trials row {bad[0]} has status {bad[1]!r}, not one "
                f"of {', '.join(STATUSES)}; refused, nothing was changed; fix or delete that "
                "row (sqlite3) and try again"
            )
        if exists and (found := damage(self._db)):
            raise StoreError(
                f"{self.path}: damaged: {'; '.join(found)}; refused, nothing was written; "
                + _RECOVER.format(path=self.path)
            )
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
        self._migrate(_check_schema(self.path, meta, self._db))
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
        try:
            self._upgrade(schema)
        except sqlite3.DatabaseError as exc:
            raise StoreError(
                f"{self.path}: cannot bring schema {schema} up to {SCHEMA_VERSION} ({exc}); "
                "nothing was changed (the upgrade is all or nothing)"
            ) from None

    def _upgrade(self, schema: int) -> None:
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
        with _readable(self.path, f"reading subject {subject!r}'s plan"):
            self._ensure_plan(subject, plan, seed)

    def _ensure_plan(self, subject: str, plan: Sequence[PlannedTrial], seed: int) -> None:
        practice = bool(plan) and plan[0].practice
        stored = self.plan(subject, practice=practice)
        if stored:
            old_seed = self._db.execute(
                "SELECT seed FROM plan WHERE subject = ? AND practice = ? LIMIT 1",
                (subject, int(practice)),
            ).fetchone()[0]
            if old_seed != seed or stored != list(plan):
                raise StoreError(
                    f"{self.path}: subject {subject!r} already has a plan of {len(stored)} "
                    f"trials (seed {old_seed}) that differs from this one ({len(plan)} trials, "
                    f"seed {seed}); resume with the same seed, or use another subject id"
                )
            return
        with self._db:
            self._db.executemany(_INSERT_PLAN, [(subject, *astuple(t), seed) for t in plan])

    def append_plan(self, subject: str, trial: PlannedTrial, seed: int) -> None:
        """Add one decided trial to ``subject``'s plan (an adaptive procedure decides each
        trial from the answers before it); StoreError unless it is the next index."""
        with self._db:
            n = self._db.execute(
                "SELECT COUNT(*) FROM plan WHERE subject = ? AND practice = 0", (subject,)
            )
            if trial.index != n.fetchone()[0]:
                raise StoreError(
                    f"{self.path}: subject {subject!r}: trial {trial.index} is not the next "
                    "of its plan"
                )
            self._db.execute(_INSERT_PLAN, (subject, *astuple(trial), seed))

    def plan(self, subject: str, *, practice: bool = False) -> list[PlannedTrial]:
        """``subject``'s planned trials (``practice``: the practice trials instead)."""
        cols = ", ".join(f'"{c}"' for c in _PLAN_COLUMNS)
        with _readable(self.path, f"reading subject {subject!r}'s plan"):
            rows = self._db.execute(
                f'SELECT {cols} FROM plan WHERE subject = ? AND practice = ? ORDER BY "index"',
                (subject, int(practice)),
            ).fetchall()
        return [_planned(self.path, r) for r in rows]

    def remaining(self, subject: str, *, practice: bool = False) -> list[PlannedTrial]:
        """The planned trials of ``subject`` not done (neither complete nor failed), in
        order (``practice``: the practice trials instead)."""
        cols = ", ".join(f'p."{c}"' for c in _PLAN_COLUMNS)
        with _readable(self.path, f"reading subject {subject!r}'s trials"):
            rows = self._db.execute(
                f"""SELECT {cols} FROM plan p WHERE p.subject = ? AND p.practice = ?
                    AND NOT EXISTS (
                    SELECT 1 FROM trials t WHERE t.subject = p.subject
                    AND t.plan_index = p."index" AND t.status IN ('complete', 'failed'))
                ORDER BY p."index" """,
                (subject, int(practice)),
            ).fetchall()
        return [_planned(self.path, r) for r in rows]

    def next_trial(self, subject: str) -> PlannedTrial | None:
        rest = self.remaining(subject)
        return rest[0] if rest else None

    # Sessions ----------------------------------------------------------------------

    def add_session(
        self, subject: str, metadata: dict[str, Any], subject_index: int | None = None
    ) -> int:
        """Store the start of a run of ``subject`` with its ``metadata`` (JSON values) and
        counterbalancing index; its row id. The trials stored after it are its."""
        with _readable(self.path, "storing the session"), self._db:
            self._db.execute(_SESSIONS)
            cur = self._db.execute(
                """INSERT INTO sessions (subject, subject_index, after_trial, started_unix_s,
                    metadata) VALUES (?, ?, (SELECT COALESCE(MAX(id), 0) FROM trials), ?, ?)""",
                (subject, subject_index, time.time(), json.dumps(metadata, sort_keys=True)),
            )
        return int(cur.lastrowid or 0)

    def sessions(self, subject: str | None = None) -> list[dict[str, Any]]:
        """The sessions (of ``subject``; all with None), oldest first, ``metadata``
        decoded."""
        with _readable(self.path, "reading the sessions"):
            rows = read_sessions(self._db, self.path)
        return [r for r in rows if subject is None or r["subject"] == subject]

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
                        time_unix_s, status, source, failure, practice) VALUES (?, ?, ?, ?, ?,
                        ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
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
                        int(trial.practice),
                    ),
                )
        except sqlite3.IntegrityError as exc:
            raise StoreError(
                f"{self.path}: trial {trial.index} of subject {subject!r} cannot be stored: "
                f"{exc} (already answered or failed, or not in the subject's plan)"
            ) from None
        return int(cur.lastrowid or 0)

    def trials(
        self, status: str | None = "complete", *, practice: bool = False
    ) -> list[dict[str, Any]]:
        """The stored trials of ``status`` (None: all), the session's own (``practice``:
        the practice trials too), in the order stored."""
        with _readable(self.path, "reading the trials"):
            rows = read_trials(self._db, status)
        return rows if practice else [r for r in rows if not r.get("practice")]


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
    """What the analysis needs to know of an experiment, JSON-ready; an installed
    procedure's settings and package too (the analysis rebuilds the procedure from them:
    hapticd.experiment.procedure.from_design)."""
    out = {
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
        "counterbalance": exp.randomization.counterbalance,
        "metadata_keys": list(exp.metadata.names()),
        "export_format": exp.export.format,
    }
    if exp.procedure not in ("constant_stimuli", "staircase", "quest_plus"):
        from hapticd.experiment import procedure

        out |= exp.proc.design()
        out["procedure_package"] = procedure.package_of(exp.procedure)
    return out


def _connect(path: Path) -> sqlite3.Connection:
    try:
        db = sqlite3.connect(path, isolation_level="DEFERRED")
        db.execute("PRAGMA foreign_keys = ON")
        mode = db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        db.execute("PRAGMA synchronous = FULL")
    except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
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


def _tables_schema(db: sqlite3.Connection) -> int:
    """The schema the trials table's columns are: 1 has no source, 2 no failure, 3 no
    practice."""
    cols = {r[1] for r in db.execute("PRAGMA table_info(trials)")}
    if "source" not in cols:
        return 1
    return 2 if "failure" not in cols else 3 if "practice" not in cols else 4


def _check_schema(path: Path, meta: dict[str, Any], db: sqlite3.Connection) -> int:
    """The store's schema: meta's, a readable one (the text of its number) and the
    one its trials table is; StoreError otherwise, naming the value and the rule."""
    value = meta.get("schema")
    if value not in {str(n) for n in READABLE_SCHEMAS}:
        raise StoreError(
            f"{path}: trial store schema {value!r}, this hapticd reads "
            f"{', '.join(map(str, READABLE_SCHEMAS))}"
        )
    schema, tables = int(value), _tables_schema(db)
    if schema != tables:
        raise StoreError(
            f"{path}: damaged: meta.schema says {value!r} but the trials table is schema "
            f"{tables}'s; refused, nothing was changed; if the table is right, set it with "
            f"sqlite3 {path} \"UPDATE meta SET value = '{tables}' WHERE key = 'schema'\""
        )
    return schema


def _planned(path: Path, row: Sequence[Any]) -> PlannedTrial:
    d = dict(zip(_PLAN_COLUMNS, row, strict=True))
    for col in ("index", "block", "position", "comparison_first", "practice"):
        if isinstance(d[col], bool) or not isinstance(d[col], int):
            raise StoreError(
                f"{path}: damaged: plan row {d.get('index')!r}: {col} holds {d[col]!r}, not "
                "an integer; " + _RECOVER.format(path=path)
            )
    for col in ("standard", "ratio", "comparison", "break_before_s"):
        if not _finite(d[col]):
            raise StoreError(
                f"{path}: damaged: plan row {d['index']}: {col} holds {d[col]!r}, not a "
                "finite number; " + _RECOVER.format(path=path)
            )
    if not isinstance(d["condition"], str):
        raise StoreError(f"{path}: damaged: plan row {d['index']}: condition is not text")
    d["comparison_first"] = bool(d["comparison_first"])
    d["practice"] = bool(d["practice"])
    return PlannedTrial(**d)


def _finite(v: object) -> bool:
    """A number (not a bool) that is neither inf nor NaN."""
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


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


def read_sessions(db: sqlite3.Connection, path: Path) -> list[dict[str, Any]]:
    """Every session of the store ``db`` (none when it has no sessions table), oldest
    first, ``metadata`` decoded; StoreError naming the row when it is not a JSON
    object."""
    names = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    if "sessions" not in names:
        return []
    cols = ("id", "subject", "subject_index", "after_trial", "started_unix_s", "metadata")
    rows = [
        dict(zip(cols, r, strict=True))
        for r in db.execute(f"SELECT {', '.join(cols)} FROM sessions ORDER BY id")
    ]
    for r in rows:
        try:
            r["metadata"] = json.loads(r["metadata"])
        except (TypeError, ValueError):
            r["metadata"] = None
        if not isinstance(r["metadata"], dict) or not isinstance(r["after_trial"], int):
            raise StoreError(
                f"{path}: damaged: sessions row {r['id']}: metadata is not a JSON object or "
                "after_trial not an integer; fix or delete that row (sqlite3) and try again"
            )
    return rows


def _row_problem(path: Path, r: dict[str, Any]) -> str | None:
    """What is wrong with the trials row ``r``, naming the row and the column: a value
    that is not a finite number where one belongs (inf or NaN too: no fit takes them),
    a standard of 0, a status not one of STATUSES; None when nothing is."""
    where = f"{path}: damaged: trials row {r.get('id')} (subject {r.get('subject')!r}, "
    where += f"trial {r.get('plan_index')!r})"
    fix = "; fix or delete that row (sqlite3) and try again"
    for col in _NUMBER_COLUMNS:
        v = r.get(col)
        if v is None and col in _NULLABLE:
            continue
        if not _finite(v):
            return f"{where}: {col} holds {v!r}, not a finite number{fix}"
    if r.get("standard") == 0:
        return f"{where}: standard is 0 (a Weber fraction divides by it){fix}"
    if r.get("status") not in STATUSES:
        return f"{where}: status {r.get('status')!r}, not one of {', '.join(STATUSES)}{fix}"
    return None


def open_sessions(path: str | Path) -> list[dict[str, Any]]:
    """``read_sessions`` of the store at ``path``, opened read only; StoreError naming it
    when it cannot be read."""
    p = Path(path)
    try:
        db = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
    except sqlite3.DatabaseError as exc:
        raise StoreError(f"{p}: cannot open: {exc}") from None
    try:
        with _readable(p, "reading the sessions"):
            return read_sessions(db, p)
    finally:
        db.close()


def open_for_analysis(
    path: str | Path, status: str | None = "complete"
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The meta table (``design`` decoded) and the trials of the store at ``path`` (the
    complete ones; all with ``status`` None), read only (nothing in it changes).
    StoreError naming the store and what is wrong: not a store, another schema, a
    damaged file (a garbled page), a design that is not JSON, text in a number column.
    Damage SQLite finds (a page, cell or column) that still leaves the trials readable
    is a StoreWarning naming the store and where: what is readable is returned."""
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
        except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
            raise StoreError(f"{p}: not a trial store (SQLite): {exc}") from None
        with _readable(p, "reading the schema"):
            _check_schema(p, meta, db)
        out: dict[str, Any] = dict(meta)
        try:
            out["design"] = json.loads(meta.get("design") or "{}")
        except ValueError as exc:
            raise StoreError(f"{p}: damaged: meta.design is not JSON ({exc})") from None
        if not isinstance(out["design"], dict):
            raise StoreError(f"{p}: damaged: meta.design is not a JSON object")
        try:
            rows = read_trials(db, status)
            found = damage(db)
        except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
            raise StoreError(
                f"{p}: damaged: the trials cannot be read ({exc}); sqlite3's .recover "
                "salvages what is readable into a new file"
            ) from None
        problems = [_row_problem(p, r) for r in rows]
        if not found:
            if bad := next((x for x in problems if x is not None), None):
                raise StoreError(bad)
            return out, rows
        # SQLite found damage: a damaged page's rows are missing, or read as empty
        # ones; what is readable is returned, and said.
        good = [r for r, x in zip(rows, problems, strict=True) if x is None]
        warnings.warn(
            StoreWarning(
                f"{p}: damaged: {'; '.join(found)}; read the {len(good)} readable trials "
                f"({len(rows) - len(good)} unreadable left out), those on the damaged "
                "pages are missing; " + _RECOVER.format(path=p)
            ),
            stacklevel=2,
        )
        return out, good
    finally:
        db.close()
