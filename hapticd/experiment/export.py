"""``hapticd experiment export``: a trial store as a tidy table, one row per trial, for
R, pandas or a spreadsheet (docs/experiments.md, "Exporting trials").

``COLUMNS`` names each column once, with what it holds; the CSV header, the DataFrame
and the docs' table all come from it.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from hapticd.experiment.store import StoreError, open_for_analysis

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
)
NAMES = tuple(name for name, _ in COLUMNS)


def _row(trial: dict[str, Any], design: dict[str, Any], path: Path) -> dict[str, Any]:
    try:
        recs = json.loads(trial.get("recording") or "[]")
    except ValueError:
        raise StoreError(
            f"{path}: damaged: trials row {trial.get('id')}: recording is not a JSON list"
        ) from None
    if not isinstance(recs, list):
        raise StoreError(f"{path}: damaged: trials row {trial.get('id')}: recording is not a list")
    recs = [*recs, None, None]
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
    }


def trial_rows(db: str | Path, *, status: str | None = "complete") -> list[dict[str, Any]]:
    """The trials of the store ``db`` (the complete ones; every one with ``status``
    None) as dicts keyed by ``NAMES``, in the order they were stored. StoreError naming
    the store and what is wrong with it."""
    meta, trials = open_for_analysis(db, status)
    return [_row(t, meta["design"], Path(db)) for t in trials]


def write_csv(db: str | Path, out: str | Path, *, status: str | None = "complete") -> int:
    """Write the store ``db``'s trials to the CSV file ``out`` (a header of ``NAMES``;
    empty fields for missing values); the number of rows. StoreError, OSError."""
    rows = trial_rows(db, status=status)
    with open(out, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=NAMES, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return len(rows)


def trials_frame(db: str | Path, *, status: str | None = "complete") -> Any:
    """The store ``db``'s trials as a pandas DataFrame with the columns ``NAMES``
    (pandas is optional: ``pip install 'hapticd[pandas]'``; ImportError saying so)."""
    try:
        import pandas as pd
    except ImportError:
        raise ImportError("trials_frame needs pandas: pip install 'hapticd[pandas]'") from None
    return pd.DataFrame(trial_rows(db, status=status), columns=list(NAMES))


def markdown_table() -> str:
    """The columns as the docs' table."""
    lines = ["| column | what it holds |", "|---|---|"]
    lines += [f"| `{name}` | {doc} |" for name, doc in COLUMNS]
    return "\n".join(lines) + "\n"
