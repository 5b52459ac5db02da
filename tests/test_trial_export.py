"""The tidy trial export (hapticd experiment export, trials_frame) and damaged stores."""

from __future__ import annotations

import csv
import json
import sqlite3
from pathlib import Path

import pytest

from hapticd.cli import main
from hapticd.experiment import export as ex
from hapticd.experiment import load_experiment, make_plan
from hapticd.experiment.store import StoreError, TrialStore, open_for_analysis
from tests.conftest import ROOT

STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"


def small_store(db: Path, n: int = 8) -> list:
    """Subject s01's first ``n`` trials answered (trial 2 first stored incomplete, then
    answered), each with two recordings but the last; the plan."""
    exp = load_experiment(STIFFNESS)
    seed = exp.subject_seed("s01")
    plan = make_plan(exp, seed)
    with TrialStore.for_experiment(db, exp) as store:
        store.ensure_plan("s01", plan, seed)
        for t in plan[:n]:
            recs = None if t.index == n - 1 else json.dumps([f"r{t.index}-1", f"r{t.index}-2"])
            if t.index == 2:
                store.record(
                    "s01", t, answer_second_more=None, response_time_s=None, profile_hash="p",
                    seed=seed, status="incomplete", recording=recs,
                )  # fmt: skip
            store.record(
                "s01", t, answer_second_more=t.index % 3 == 0, response_time_s=0.5 + t.index,
                profile_hash="p", seed=seed, recording=recs, source="key",
            )  # fmt: skip
    return plan


def read_csv(path: Path) -> tuple[list[str], list[dict]]:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def test_export_csv_has_one_row_per_complete_trial_with_the_documented_columns(tmp_path, capsys):
    db, out = tmp_path / "t.db", tmp_path / "t.csv"
    plan = small_store(db)
    assert main(["experiment", "export", str(db), "--csv", str(out)]) == 0
    assert "8 complete trials" in capsys.readouterr().out
    header, rows = read_csv(out)
    assert header == list(ex.NAMES)
    assert [int(r["trial"]) for r in rows] == list(range(8))
    for r in rows:
        t = plan[int(r["trial"])]
        assert (r["subject"], r["experiment"], r["status"], r["source"]) == (
            "s01", "stiffness-jnd", "complete", "key"
        )  # fmt: skip
        assert int(r["block"]) == t.block and r["condition"] == t.condition
        assert float(r["standard"]) == t.standard and float(r["comparison"]) == t.comparison
        assert (r["param"], r["unit"]) == ("stiffness_n_per_m", "N/m")
        first = r["comparison_first"] == "1"
        assert first == t.comparison_first
        second_more = r["answer_second_more"] == "1"
        assert second_more == (t.index % 3 == 0)
        # The comparison was judged more: second and yes, or first and no.
        assert (r["comparison_more"] == "1") == (second_more != first)
        assert float(r["response_time_s"]) == pytest.approx(0.5 + t.index)
        assert float(r["time_unix_s"]) > 1e9
        if t.index == 7:
            assert r["recording_1"] == r["recording_2"] == ""
        else:
            assert (r["recording_1"], r["recording_2"]) == (f"r{t.index}-1", f"r{t.index}-2")
    # --all adds the incomplete one, its answer empty.
    assert main(["experiment", "export", str(db), "--csv", str(out), "--all"]) == 0
    _, every = read_csv(out)
    assert len(every) == 9
    (bad,) = [r for r in every if r["status"] == "incomplete"]
    assert bad["trial"] == "2" and bad["answer_second_more"] == bad["source"] == ""


def test_the_dataframe_holds_what_the_csv_holds(tmp_path):
    pd = pytest.importorskip("pandas")
    db = tmp_path / "t.db"
    small_store(db)
    frame = ex.trials_frame(db)
    assert list(frame.columns) == list(ex.NAMES) and len(frame) == 8
    out = tmp_path / "t.csv"
    ex.write_csv(db, out)
    back = pd.read_csv(out)
    assert back["comparison"].tolist() == frame["comparison"].tolist()
    assert back["comparison_more"].tolist() == frame["comparison_more"].tolist()
    assert len(ex.trials_frame(db, status=None)) == 9


def test_the_docs_list_the_export_columns():
    assert ex.markdown_table() in (ROOT / "docs" / "experiments.md").read_text()


def _edit(db: Path, sql: str) -> None:
    con = sqlite3.connect(db)
    try:
        with con:
            con.execute(sql)
    finally:
        con.close()  # the last connection: the change goes into the file itself


def _damage_number(db: Path) -> None:
    _edit(db, "UPDATE trials SET comparison = 'sixty' WHERE plan_index = 4")


def _damage_design(db: Path) -> None:
    _edit(db, "UPDATE meta SET value = '{\"param\": ' WHERE key = 'design'")


def _damage_page(db: Path) -> None:
    # Garble every page after the schema's (the trials, the plan and their indexes).
    con = sqlite3.connect(db)
    try:
        page = con.execute("PRAGMA page_size").fetchone()[0]
    finally:
        con.close()
    data = bytearray(db.read_bytes())
    for start in range(2 * page, len(data), page):
        data[start + 8 : start + 64] = b"\xa5" * 56
    db.write_bytes(bytes(data))


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (_damage_number, r"trials row \d+ \(subject 's01', trial 4\): comparison holds 'sixty'"),
        (_damage_design, "meta.design is not JSON"),
        (_damage_page, "damaged|not a trial store"),
    ],
)
def test_a_damaged_store_is_a_clear_error_naming_it_never_a_traceback(
    tmp_path, capsys, damage, match
):
    db = tmp_path / "t.db"
    small_store(db, n=40)
    damage(db)
    before = db.read_bytes()
    with pytest.raises(StoreError, match=match) as err:
        open_for_analysis(db)
    assert str(db) in str(err.value)
    for cmd in (["export", str(db), "--csv", str(tmp_path / "o.csv")], ["analyze", str(db)]):
        assert main(["experiment", *cmd]) == 2
        text = capsys.readouterr().err
        assert str(db) in text and "Traceback" not in text
    assert db.read_bytes() == before  # reading changed nothing
