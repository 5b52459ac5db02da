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
    assert header == ex.names()
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
    assert list(frame.columns) == ex.names() and len(frame) == 8
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


# Damage a writer meets (a resume) and damage a reader reads through ----------------------

RUN = ["--observer", "model", "--standards", "60", "--repetitions", "1", "--no-keys"]


def half_run_store(db: Path) -> int:
    """The store ``experiment run ... RUN --subject s01`` makes, half its trials answered;
    the number of pages."""
    from hapticd.experiment import runner as rn

    exp = rn.reduced(load_experiment(STIFFNESS), standards=[60.0], repetitions=1, break_s=None)
    seed = exp.subject_seed("s01")
    plan = make_plan(exp, seed)
    with TrialStore.for_experiment(db, exp) as store:
        store.ensure_plan("s01", plan, seed)
        for t in plan[: len(plan) // 2]:
            store.record(
                "s01", t, answer_second_more=True, response_time_s=1.0, profile_hash="p",
                seed=seed, source="key",
            )  # fmt: skip
    return _pages(db)


def _pages(db: Path) -> int:
    con = sqlite3.connect(db)
    try:
        size = con.execute("PRAGMA page_size").fetchone()[0]
    finally:
        con.close()  # the last connection: everything is in the file itself
    assert not db.with_name(db.name + "-wal").exists()
    return db.stat().st_size // size


def _garble(db: Path, page: int) -> None:
    """Overwrite page ``page``'s (1-based) cell pointers with junk."""
    size = db.stat().st_size // _pages(db)
    data = bytearray(db.read_bytes())
    start = (page - 1) * size
    data[start + 8 : start + 64] = b"\xa5" * 56
    db.write_bytes(bytes(data))


def test_a_resume_into_a_store_with_a_garbled_page_is_refused_and_writes_nothing(tmp_path, capsys):
    db = tmp_path / "t.db"
    pages = half_run_store(db)
    _garble(db, pages)  # the trials' last page
    before = db.read_bytes()
    run = ["experiment", "run", str(STIFFNESS), "--subject", "s01", "--db", str(db), *RUN]
    assert main([*run, "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"{db}: damaged" in err and "nothing was written" in err and ".recover" in err
    assert "Traceback" not in err
    assert db.read_bytes() == before
    wal = db.with_name(db.name + "-wal")
    assert not wal.exists() or wal.stat().st_size == 0  # not a trial stored
    exp = load_experiment(STIFFNESS)
    with pytest.raises(StoreError, match=r"damaged.*page"):
        TrialStore.for_experiment(db, exp)


@pytest.fixture(scope="module")
def half_run(tmp_path_factory) -> tuple[bytes, int]:
    db = tmp_path_factory.mktemp("store") / "t.db"
    pages = half_run_store(db)
    return db.read_bytes(), db.stat().st_size // pages


def test_random_bytes_in_any_page_give_the_store_error_or_a_resume(half_run, tmp_path_factory):
    """Bytes anywhere in any page: opening the store and resuming the subject give a
    StoreError naming the store, or the plan, never another exception."""
    import tempfile

    from hypothesis import assume, given, settings
    from hypothesis import strategies as st

    from hapticd.experiment import runner as rn

    good, size = half_run
    exp = rn.reduced(load_experiment(STIFFNESS), standards=[60.0], repetitions=1, break_s=None)
    seed = exp.subject_seed("s01")
    root = tmp_path_factory.mktemp("damaged")

    @settings(max_examples=60, deadline=None)
    @given(
        page=st.integers(0, len(good) // size - 1),
        offset=st.integers(0, size - 1),
        junk=st.binary(min_size=1, max_size=64),
    )
    def check(page: int, offset: int, junk: bytes) -> None:
        data = bytearray(good)
        start = page * size + offset
        end = min(start + len(junk), (page + 1) * size)
        assume(bytes(data[start:end]) != junk[: end - start])
        data[start:end] = junk[: end - start]
        with tempfile.TemporaryDirectory(dir=root) as d:
            db = Path(d) / "t.db"
            db.write_bytes(bytes(data))
            try:
                with TrialStore.for_experiment(db, exp) as store:
                    rn.check_start(store, "s01", resume=True)
                    todo = rn.start_subject(store, exp, "s01", seed, resume=True)
                    assert all(t.index >= 0 for t in todo)
                    store.trials(None)
            except StoreError as exc:
                assert str(db) in str(exc)

    check()


def test_a_garbled_last_page_is_exported_with_a_warning_naming_it(tmp_path, capsys):
    from hapticd.experiment.store import StoreWarning

    db, out = tmp_path / "t.db", tmp_path / "t.csv"
    small_store(db, n=120)
    pages = _pages(db)
    _garble(db, pages)
    with pytest.warns(StoreWarning, match=rf"{db}: damaged: .*page {pages}\b") as got:
        rows = ex.trial_rows(db)
    assert 0 < len(rows) < 120 and f"read the {len(rows)} readable trials" in str(got[0].message)
    assert main(["experiment", "export", str(db), "--csv", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"hapticd: warning: {db}: damaged" in err and f"page {pages}" in err
    assert "Traceback" not in err
    _, written = read_csv(out)
    assert [r["trial"] for r in written] == [str(r["trial"]) for r in rows]  # the good ones
    assert main(["experiment", "analyze", str(db)]) == 0
    assert f"page {pages}" in capsys.readouterr().err


@pytest.mark.parametrize("column", ["comparison", "standard", "response_time_s", "time_unix_s"])
@pytest.mark.parametrize("value", ["9e999", "-9e999"])
def test_a_trial_with_an_infinite_number_is_a_clear_error_naming_it(
    tmp_path, capsys, column, value
):
    db = tmp_path / "t.db"
    small_store(db, n=40)
    _edit(db, f"UPDATE trials SET {column} = {value} WHERE plan_index = 4")
    want = rf"trials row \d+ \(subject 's01', trial 4\): {column} holds -?inf, not a finite number"
    with pytest.raises(StoreError, match=want):
        open_for_analysis(db)
    for cmd in (["analyze", str(db)], ["export", str(db), "--csv", str(tmp_path / "o.csv")]):
        assert main(["experiment", *cmd]) == 2
        err = capsys.readouterr().err
        assert f"{db}: damaged: trials row" in err and column in err and "Traceback" not in err


def test_a_trial_with_a_standard_of_zero_is_a_clear_error(tmp_path, capsys):
    db = tmp_path / "t.db"
    small_store(db, n=40)
    _edit(db, "UPDATE trials SET standard = 0 WHERE plan_index = 5")
    with pytest.raises(StoreError, match=r"trial 5\): standard is 0"):
        open_for_analysis(db)
    assert main(["experiment", "analyze", str(db)]) == 2
    assert "standard is 0" in capsys.readouterr().err


@pytest.mark.parametrize("schema", ["1", "2", "3.0", " 3", "x"])
def test_a_store_whose_meta_schema_disagrees_with_its_tables_is_refused_unchanged(
    tmp_path, capsys, schema
):
    db = tmp_path / "t.db"
    small_store(db, n=5)
    _edit(db, f"UPDATE meta SET value = '{schema}' WHERE key = 'schema'")
    before = db.read_bytes()
    want = "meta.schema says" if schema in ("1", "2") else f"schema '{schema}', this hapticd reads"
    with pytest.raises(StoreError, match=want):
        TrialStore.for_experiment(db, load_experiment(STIFFNESS))
    with pytest.raises(StoreError, match=want):
        open_for_analysis(db)
    run = ["experiment", "run", str(STIFFNESS), "--subject", "s01", "--db", str(db), *RUN]
    for cmd in ([*run, "--resume"], ["experiment", "analyze", str(db)]):
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert str(db) in err and repr(schema) in err and "Traceback" not in err
    assert db.read_bytes() == before
