"""``hapticd experiment export``: a trial store as a tidy table, one row per trial, for
R, pandas, MATLAB or a spreadsheet (docs/experiments.md, "Exporting trials"), and each
interval's samples from its recording.

``COLUMNS`` names each column of the store's own once, with what it holds; the
adaptive, practice, interval and per-finger columns follow (``columns``); the header
of every format, the DataFrame and the docs' table all come from them. A column's
kind (``KINDS``: int or float; text when not listed) decides how each format holds it
(hapticd.experiment.tables).
"""

from __future__ import annotations

import bisect
import datetime as dt
import json
import math
import warnings
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hapticd.experiment import tables
from hapticd.experiment.spec import STANDARD_METADATA
from hapticd.experiment.store import StoreError, open_for_analysis, open_sessions
from hapticd.recording.export import csv_columns
from hapticd.recording.format import Recording, RecordingError, read

# (column, what it holds): the export's columns, in order.
COLUMNS: tuple[tuple[str, str], ...] = (
    ("experiment", "the experiment's name"),
    ("subject", "the subject's id"),
    ("trial", "the trial's index in the subject's plan (0-based)"),
    ("block", "the block (0-based): one condition and one standard; an adaptive run's track"),
    ("condition", "the condition's name"),
    ("param", "the varied parameter (hapticd.params name)"),
    ("unit", "its SI unit"),
    ("standard", "the standard value, in unit"),
    ("comparison", "the comparison value, in unit"),
    ("comparison_first", "1: the comparison was the first interval; 0: the second"),
    ("answer_second_more", "the answer to 'was the second more?': 1 yes, 0 no; empty: none"),
    ("comparison_more", "1: the comparison was judged more; 0: the standard; empty: none"),
    ("response_time_s", "from the question to the answer, s; empty for the model observer"),
    ("source", "where the answer came from: key, button, respond, model; empty: none"),
    (
        "status",
        "complete; incomplete (not answered); failed (the exploration failed: never judged)",
    ),
    ("failure", "why the exploration failed (status failed); empty otherwise"),
    ("time_unix_s", "when the trial was stored, Unix time, s"),
    ("recording_1", "the first interval's recording (path); empty: none"),
    ("recording_2", "the second interval's recording (path); empty: none"),
    # The session the trial was run in (hapticd experiment run --meta KEY=VALUE).
    ("subject_index", "the subject's place in the counterbalancing (0-based); empty: none"),
    ("session", "the session's label (--meta session=...); empty: not given"),
    ("experimenter", "who ran the session (--meta experimenter=...); empty: not given"),
    ("notes", "the session's notes (--meta notes=...); empty: none"),
)
# After the store's own: what a lab's analysis reads beside the answers.
TRIAL_COLUMNS: tuple[tuple[str, str], ...] = (
    ("practice", "1: a practice trial (never analysed); 0: a trial of the design"),
    (
        "side",
        "the comparison's side of the standard: above or below (a staircase: its track's "
        "side); empty: on the standard",
    ),
    (
        "correct",
        "1: the answer was right (the larger judged more; a staircase: its track's rule); "
        "0: wrong; empty: no answer, or the comparison on the standard",
    ),
    (
        "reversal",
        "staircase: 1 when this answer turned its track's direction (a reversal), else 0; "
        "empty: not a staircase, or no answer",
    ),
)
# Per interval K (1, 2), from its recording (empty: none, or not found).
INTERVAL_COLUMNS: tuple[tuple[str, str], ...] = (
    ("onset_s_K", "interval K's first recorded tick on the loop's clock (its t), s"),
    ("duration_s_K", "interval K's recorded ticks x the tick period, s"),
    (
        "onset_unix_s_K",
        "interval K's onset on the wall clock, UTC Unix time, s: tick 0's (the header's clock "
        "anchor) + the tick's t_wall; empty: a recording without an anchor",
    ),
    (
        "onset_lsl_s_K",
        "interval K's onset on the LSL clock, s: tick 0's (the header's clock anchor) + the "
        "tick's t_wall; empty: a recording without an anchor",
    ),
)
# Per interval K and finger FINGER (the recordings' finger names).
FINGER_COLUMNS: tuple[tuple[str, str], ...] = (
    (
        "peak_force_n_FINGER_K",
        "the largest |device_force| (the force sent to FINGER's device) in interval K, N",
    ),
    (
        "mean_force_n_FINGER_K",
        "the mean |device_force| over the ticks FINGER was in contact, N; empty: no contact",
    ),
    ("contact_s_FINGER_K", "how long FINGER was in contact in interval K, s"),
)
INTERVALS = (1, 2)

NAMES = tuple(name for name, _ in COLUMNS + TRIAL_COLUMNS)
KINDS: dict[str, tables.Kind] = {
    "trial": "int",
    "block": "int",
    "standard": "float",
    "comparison": "float",
    "comparison_first": "int",
    "answer_second_more": "int",
    "comparison_more": "int",
    "response_time_s": "float",
    "time_unix_s": "float",
    "practice": "int",
    "correct": "int",
    "reversal": "int",
    "subject_index": "int",
}
# A metadata key the lab declares (metadata.keys) is the column META_PREFIX + key, after
# every other column (text).
META_PREFIX = "meta_"
# Where a recording's header (its meta) anchors tick 0 on the wall and LSL clocks: the
# first of these keys present (absent in recordings made before the anchors existed).
ANCHOR_KEYS = {"unix": ("t0_utc", "t0_unix_s"), "lsl": ("t0_lsl", "t0_lsl_s")}


class ExportWarning(UserWarning):
    """Recordings the export could not read: their columns are left empty."""


def names(fingers: Sequence[str] = (), extra: Sequence[str] = ()) -> list[str]:
    """Every column, in order, of an export whose recordings hold ``fingers`` and whose
    sessions declare the metadata keys ``extra``."""
    out = list(NAMES)
    for k in INTERVALS:
        out += [_name(n, k) for n, _ in INTERVAL_COLUMNS]
        out += [_name(n, k, f) for f in fingers for n, _ in FINGER_COLUMNS]
    return out + [META_PREFIX + k for k in extra]


def kinds(fingers: Sequence[str] = (), extra: Sequence[str] = ()) -> dict[str, tables.Kind]:
    """Every column's kind (hapticd.experiment.tables): the number columns; text the rest (the
    metadata columns among them)."""
    out = dict(KINDS)
    out.update({n: "float" for n in names(fingers) if n not in NAMES})
    return out


def _name(pattern: str, k: int, finger: str = "") -> str:
    return pattern.replace("FINGER", finger).replace("_K", f"_{k}")


def _recordings(trial: dict[str, Any], path: Path) -> list[str | None]:
    try:
        recs = json.loads(trial.get("recording") or "[]")
    except ValueError:
        raise StoreError(
            f"{path}: damaged: trials row {trial.get('id')}: recording is not a JSON list"
        ) from None
    if not isinstance(recs, list):
        raise StoreError(f"{path}: damaged: trials row {trial.get('id')}: recording is not a list")
    return [*recs, None, None]


def _row(trial: dict[str, Any], design: dict[str, Any], path: Path) -> dict[str, Any]:
    recs = _recordings(trial, path)
    return {
        "experiment": trial["experiment"],
        "subject": trial["subject"],
        "trial": trial["plan_index"],
        "block": trial.get("block"),
        "condition": trial["condition"],
        "param": design.get("param"),
        "unit": design.get("unit"),
        "standard": trial["standard"],
        "comparison": trial["comparison"],
        "comparison_first": trial["comparison_first"],
        "answer_second_more": trial["answer_second_more"],
        "comparison_more": trial["comparison_more"],
        "response_time_s": trial["response_time_s"],
        "source": trial.get("source"),
        "status": trial["status"],
        "failure": trial.get("failure"),
        "time_unix_s": trial["time_unix_s"],
        "recording_1": recs[0],
        "recording_2": recs[1],
        "practice": int(bool(trial.get("practice") or 0)),
    }


# -- the adaptive columns --------------------------------------------------------------


def answer_flags(
    trials: Sequence[Mapping[str, Any]], design: Mapping[str, Any]
) -> dict[int, dict[str, Any]]:
    """side, correct and reversal of each trial (store rows: id, subject, plan_index,
    block, standard, comparison, status, comparison_more), keyed by row id. A staircase's
    tracks are replayed from their complete trials in plan order (``Track.answer``, the
    runner's own rule); any other procedure's side is the comparison's and its answer is
    correct when the larger was judged more."""
    from hapticd.experiment.adaptive import Track, is_correct
    from hapticd.experiment.spec import Staircase

    out: dict[int, dict[str, Any]] = {}
    for t in trials:
        side = None
        if t["comparison"] != t["standard"]:
            side = "above" if t["comparison"] > t["standard"] else "below"
        correct = None
        if t["comparison_more"] is not None and side is not None:
            correct = int(bool(t["comparison_more"]) == (side == "above"))
        out[t["id"]] = {"side": side, "correct": correct, "reversal": None}
    if design.get("procedure") != "staircase" or not design.get("staircase"):
        return out
    try:
        st = Staircase.model_validate(design["staircase"])
    except ValueError as exc:
        raise StoreError(f"damaged: meta.design's staircase is not one ({exc})") from None
    by: dict[tuple[str, int], list[Mapping[str, Any]]] = {}
    for t in trials:
        if t.get("block") is not None:
            by.setdefault((t["subject"], int(t["block"])), []).append(t)
    for rows in by.values():
        rows = sorted(rows, key=lambda r: (r["plan_index"], r["id"]))
        # A track starts `start` from the standard, never on it: its first trial's side.
        first = rows[0]
        sign = 1 if first["comparison"] > first["standard"] else -1
        track = Track.new(-1, first["condition"], float(first["standard"]), sign, st)
        for r in rows:
            flags = out[r["id"]]
            flags["side"] = track.side
            if r["status"] != "complete" or r["comparison_more"] is None:
                flags["correct"] = None
                continue
            right = is_correct(track, bool(r["comparison_more"]))
            before = len(track.reversals)
            track.answer(right, st)
            flags["correct"], flags["reversal"] = int(right), int(len(track.reversals) > before)
    return out


# -- the interval columns, from the recordings -----------------------------------------


def tick_period_s(rec: Recording) -> float:
    """Seconds between two records of ``rec``: the loop's period (meta ``rate_hz``) times
    the recording's decimation (meta ``record_every``, 1 when absent); from its ``t``
    when the header has no rate."""
    rate = rec.meta.get("rate_hz")
    every = rec.meta.get("record_every", 1)
    every = every if isinstance(every, int) and every >= 1 else 1
    if isinstance(rate, int | float) and not isinstance(rate, bool) and rate > 0:
        return every / float(rate)
    if "t" in rec and rec.ticks >= 2:
        return float(np.median(np.diff(rec["t"])))
    return math.nan


def anchor(meta: Mapping[str, Any], clock: str) -> float | None:
    """The ``clock``'s (``unix`` or ``lsl``) time of tick 0, s, from a recording's meta
    (ANCHOR_KEYS): a number, or for the wall clock an ISO 8601 text (UTC when it has no
    offset); None when absent or not a finite time."""
    for key in ANCHOR_KEYS[clock]:
        v = meta.get(key)
        if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v):
            return float(v)
        if clock == "unix" and isinstance(v, str):
            try:
                when = dt.datetime.fromisoformat(v.replace("Z", "+00:00"))
            except ValueError:
                continue
            if when.tzinfo is None:
                when = when.replace(tzinfo=dt.UTC)
            return when.timestamp()
    return None


def tick0(rec: Recording) -> dict[str, float | None]:
    """Tick 0 of ``rec`` on the wall (``unix``, UTC Unix s) and LSL (``lsl``, s) clocks:
    its header's clock anchor, else the meta keys ANCHOR_KEYS; None for a clock neither
    has (a recording made before the anchor existed)."""
    clock = rec.clock
    if clock is not None:
        return {"unix": float(clock["utc_unix_s"]), "lsl": float(clock["lsl_s"])}
    return {c: anchor(rec.meta, c) for c in ANCHOR_KEYS}


def interval_stats(rec: Recording) -> dict[str, Any]:
    """One interval's columns from its recording (names with ``_K`` and ``FINGER``):
    onsets (loop, wall, LSL clocks), duration, and per finger the peak and in-contact
    mean of |device_force| (N) and the contact time (s). NaN/None for what the recording
    does not hold."""
    period = tick_period_s(rec)
    out: dict[str, Any] = {n: None for n, _ in INTERVAL_COLUMNS}
    if rec.ticks == 0:
        out["duration_s_K"] = 0.0
        return out
    out["onset_s_K"] = float(rec["t"][0]) if "t" in rec else None
    out["duration_s_K"] = rec.ticks * period
    if "t_wall" in rec:
        start = float(rec["t_wall"][0])
        anchors = tick0(rec)
        for clock, col in (("unix", "onset_unix_s_K"), ("lsl", "onset_lsl_s_K")):
            if (t0 := anchors[clock]) is not None:
                out[col] = t0 + start
    if "device_force" not in rec or "in_contact" not in rec:
        return out
    force = np.linalg.norm(np.asarray(rec["device_force"], dtype=float), axis=-1)  # (n, F)
    touching = np.asarray(rec["in_contact"]) != 0
    for j, finger in enumerate(rec.fingers[: force.shape[1]]):
        f, c = force[:, j], touching[:, j]
        out[f"peak_force_n_{finger}_K"] = float(f.max())
        out[f"mean_force_n_{finger}_K"] = float(f[c].mean()) if c.any() else None
        out[f"contact_s_{finger}_K"] = float(c.sum()) * period
    return out


def find_recording(stored: str, recordings_dir: Path | None) -> Path:
    """Where the recording stored as ``stored`` is: that path, else its file name in
    ``recordings_dir`` (recordings copied off the rig)."""
    p = Path(stored)
    if p.is_file() or recordings_dir is None:
        return p
    return Path(recordings_dir) / p.name


def _read_recording(
    stored: str, recordings_dir: Path | None, unread: list[str]
) -> Recording | None:
    try:
        return read(find_recording(stored, recordings_dir))
    except RecordingError as exc:
        unread.append(str(exc))
        return None


# -- the table -------------------------------------------------------------------------


def trial_rows(
    db: str | Path,
    *,
    status: str | None = "complete",
    recordings: bool = True,
    recordings_dir: str | Path | None = None,
) -> list[dict[str, Any]]:
    """``rows_and_fingers``'s rows."""
    return rows_and_fingers(
        db, status=status, recordings=recordings, recordings_dir=recordings_dir
    )[0]


def _sessions_of(
    trials: list[dict[str, Any]], sessions: list[dict[str, Any]]
) -> list[dict[str, Any] | None]:
    """Each trial's session: its subject's last one begun before the trial was stored
    (``after_trial`` below the trial's id); None before any."""
    by_subject: dict[str, list[dict[str, Any]]] = {}
    for s in sorted(sessions, key=lambda s: s["after_trial"]):
        by_subject.setdefault(s["subject"], []).append(s)
    out: list[dict[str, Any] | None] = []
    for t in trials:
        mine = by_subject.get(t["subject"], [])
        k = bisect.bisect_left([s["after_trial"] for s in mine], t["id"])
        out.append(mine[k - 1] if k else None)
    return out


def _with_sessions(
    db: str | Path, meta: dict[str, Any], trials: list[dict[str, Any]], rows: list[dict[str, Any]]
) -> list[str]:
    """Add each row's session columns (subject_index, the standard metadata, a
    ``meta_KEY`` per declared key) in place; the declared keys, in order."""
    sessions = open_sessions(db)
    declared = list(meta["design"].get("metadata_keys") or ())
    for s in sessions:
        declared += [k for k in s["metadata"] if k not in declared]
    extra = [k for k in declared if k not in STANDARD_METADATA]
    for row, s in zip(rows, _sessions_of(trials, sessions), strict=True):
        values = {} if s is None else s["metadata"]
        row["subject_index"] = None if s is None else s["subject_index"]
        row.update({k: values.get(k) for k in STANDARD_METADATA})
        row.update({META_PREFIX + k: values.get(k) for k in extra})
    return extra


def trial_table(
    db: str | Path,
    *,
    status: str | None = "complete",
    recordings: bool = True,
    recordings_dir: str | Path | None = None,
) -> tuple[list[str], list[dict[str, Any]]]:
    """The column names and the rows of ``_table``."""
    rows, fingers, extra = _table(
        db, status=status, recordings=recordings, recordings_dir=recordings_dir
    )
    return names(fingers, extra), rows


def rows_and_fingers(
    db: str | Path,
    *,
    status: str | None = "complete",
    recordings: bool = True,
    recordings_dir: str | Path | None = None,
) -> tuple[list[dict[str, Any]], list[str]]:
    """``_table``'s rows and fingers."""
    rows, fingers, _ = _table(
        db, status=status, recordings=recordings, recordings_dir=recordings_dir
    )
    return rows, fingers


def _table(
    db: str | Path,
    *,
    status: str | None = "complete",
    recordings: bool = True,
    recordings_dir: str | Path | None = None,
) -> tuple[list[dict[str, Any]], list[str], list[str]]:
    """The trials of the store ``db`` (the complete ones; every one with ``status``
    None) as dicts keyed by ``names(fingers, extra)``, in the order they were stored, the
    fingers of their recordings (read unless ``recordings`` is False; a recording not at
    its stored path is looked for by name in ``recordings_dir``; one that cannot be read
    leaves its columns empty, said in one ExportWarning). StoreError naming the store and
    what is wrong with it."""
    meta, trials = open_for_analysis(db, status)
    design, path = meta["design"], Path(db)
    flags = answer_flags(_answer_context(db, trials, status), design)
    rows = [{**_row(t, design, path), **flags[t["id"]]} for t in trials]
    extra = _with_sessions(db, meta, trials, rows)
    fingers: list[str] = []
    unread: list[str] = []
    rdir = None if recordings_dir is None else Path(recordings_dir)
    for row in rows:
        for k in INTERVALS:
            stored = row[f"recording_{k}"]
            rec = None
            if recordings and stored:
                rec = _read_recording(stored, rdir, unread)
            stats = interval_stats(rec) if rec is not None else {}
            fingers += [f for f in (rec.fingers if rec else []) if f not in fingers]
            row.update({_name(n, k): v for n, v in stats.items()})
    if unread:
        warnings.warn(
            ExportWarning(
                f"{len(unread)} recording(s) could not be read, their interval columns are "
                f"empty (give --recordings DIR where they are): {unread[0]}"
                + (f"; and {len(unread) - 1} more" if len(unread) > 1 else "")
            ),
            stacklevel=2,
        )
    return [{n: r.get(n) for n in names(fingers, extra)} for r in rows], fingers, extra


def _answer_context(
    db: str | Path, trials: list[dict[str, Any]], status: str | None
) -> list[dict[str, Any]]:
    """The trials a staircase's flags are replayed from: every complete one, whichever
    ``status`` is exported."""
    if status == "complete":
        return trials
    _, complete = open_for_analysis(db, "complete")
    seen = {t["id"] for t in trials}
    return trials + [t for t in complete if t["id"] not in seen]


def trials_table(
    db: str | Path,
    *,
    status: str | None = "complete",
    recordings: bool = True,
    recordings_dir: str | Path | None = None,
) -> tables.Table:
    """``trial_rows`` as a hapticd.experiment.tables Table (every column, each of its kind)."""
    rows, fingers, extra = _table(
        db, status=status, recordings=recordings, recordings_dir=recordings_dir
    )
    return tables.from_rows(rows, names(fingers, extra), kinds(fingers, extra))


def write_trials(
    db: str | Path,
    out: str | Path,
    fmt: str = "csv",
    *,
    status: str | None = "complete",
    recordings: bool = True,
    recordings_dir: str | Path | None = None,
) -> int:
    """Write the store ``db``'s trials to ``out`` as ``fmt`` (csv, parquet or mat; the
    same columns in each); the number of rows. TableFormatError, StoreError, OSError,
    ImportError (pyarrow, for parquet)."""
    tables.check_format(fmt)
    table = trials_table(db, status=status, recordings=recordings, recordings_dir=recordings_dir)
    tables.write(table, out, fmt, name="trials")
    return len(table[0].values)


def write_csv(db: str | Path, out: str | Path, *, status: str | None = "complete") -> int:
    """``write_trials`` as CSV."""
    return write_trials(db, out, "csv", status=status)


def trials_frame(db: str | Path, *, status: str | None = "complete") -> Any:
    """The store ``db``'s trials as a pandas DataFrame with the export's columns
    (pandas is optional: ``pip install 'hapticd[pandas]'``; ImportError saying so)."""
    try:
        import pandas as pd
    except ImportError:
        raise ImportError("trials_frame needs pandas: pip install 'hapticd[pandas]'") from None
    cols, rows = trial_table(db, status=status)
    return pd.DataFrame(rows, columns=cols)


# -- each interval's samples -----------------------------------------------------------

SAMPLE_KEYS = ("subject", "trial", "interval")


def samples_table(rec: Recording, subject: str, trial: int, interval: int) -> tables.Table:
    """One interval's recording as a table: ``subject``, ``trial``, ``interval``, then a
    column per scalar named as the recording's CSV export names it (``csv_columns``);
    integer fields as int, ``allocator`` as the allocator's name (meta.allocators)."""
    n = rec.ticks
    out: tables.Table = [
        tables.Column("subject", "text", np.full(n, subject, dtype=object)),
        tables.Column("trial", "int", np.full(n, float(trial))),
        tables.Column("interval", "int", np.full(n, float(interval))),
    ]
    cols = iter(csv_columns(rec))
    allocators = rec.meta.get("allocators")
    for f in rec.fields:
        width = math.prod(f.shape)
        values = np.asarray(rec[f.name]).reshape(n, width)
        kind: tables.Kind = "int" if np.dtype(f.dtype).kind in "ui" else "float"
        for j in range(width):
            name = next(cols)
            col = values[:, j].astype(float)
            if f.name == "allocator" and isinstance(allocators, list):
                text = [_allocator(allocators, v) for v in col]
                out.append(tables.Column(name, "text", np.array(text, dtype=object)))
            else:
                out.append(tables.Column(name, kind, col))
    return out


def _allocator(names_: list[Any], v: float) -> str:
    k = int(v)
    return str(names_[k]) if 0 <= k < len(names_) else str(k)


def write_samples(
    db: str | Path,
    out_dir: str | Path,
    fmt: str = "csv",
    *,
    status: str | None = "complete",
    recordings_dir: str | Path | None = None,
) -> list[Path]:
    """Write each interval's samples (``samples_table``) of the store ``db``'s trials
    into ``out_dir`` (created), one file per interval named as its recording with the
    format's suffix; the files written. A recording that cannot be read is skipped, said
    in one ExportWarning."""
    tables.check_format(fmt)
    _, trials = open_for_analysis(db, status)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rdir = None if recordings_dir is None else Path(recordings_dir)
    written: list[Path] = []
    unread: list[str] = []
    for t in trials:
        for k, stored in zip(INTERVALS, _recordings(t, Path(db)), strict=False):
            if not stored or (rec := _read_recording(stored, rdir, unread)) is None:
                continue
            target = out / (Path(stored).stem + tables.SUFFIXES[fmt])
            tables.write(samples_table(rec, t["subject"], t["plan_index"], k), target, fmt,
                         name="samples")  # fmt: skip
            written.append(target)
    if unread:
        warnings.warn(
            ExportWarning(
                f"{len(unread)} recording(s) could not be read and were skipped: {unread[0]}"
            ),
            stacklevel=2,
        )
    return written


def markdown_table(columns: Iterable[tuple[str, str]] | None = None) -> str:
    """The columns as the docs' table (every group, the patterned ones as patterns)."""
    cols = COLUMNS + TRIAL_COLUMNS + INTERVAL_COLUMNS + FINGER_COLUMNS
    lines = ["| column | what it holds |", "|---|---|"]
    lines += [f"| `{name}` | {doc} |" for name, doc in (columns or cols)]
    return "\n".join(lines) + "\n"
