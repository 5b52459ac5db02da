"""Trials whose exploration failed (the model observer's cube slipped or dropped, no
contact, the EF cue off m g): stored with status failed and the cause, never judged,
never presented again, left out and counted by analyze, exported with their cause."""

from __future__ import annotations

import csv
import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import yaml

from hapticd.cli import main
from hapticd.experiment import ExperimentError, load_experiment
from hapticd.experiment import adaptive as ad
from hapticd.experiment import observer as ob
from hapticd.experiment.plan import make_plan
from hapticd.experiment.store import StoreError, TrialStore, open_for_analysis
from hapticd.experiment.study import run_model_subject, run_study

ROOT = Path(__file__).resolve().parent.parent
WEIGHT = ROOT / "configs" / "experiments" / "weight-jnd.yaml"
STAIRCASE = ROOT / "configs" / "experiments" / "stiffness-staircase.yaml"


@pytest.fixture
def heavy(tmp_path, monkeypatch) -> Path:
    """A weight design with a light standard the hand lifts and a 500 g one it cannot
    (the cube slips out of the grip), EF only, each comparison once: 6 trials. The pilot
    check, which would refuse it, is switched off: the trials themselves must fail."""
    data = yaml.safe_load(WEIGHT.read_text())
    data["profile"] = str(ROOT / "configs" / "lift-weight.yaml")
    data["varied"]["standards"] = [0.06, 0.5]
    data["varied"]["ratios"] = [0.9, 1.1, 1.2]
    data["conditions"] = [{"name": "ef", "set": {"allocator": "ef"}}]
    data["repetitions"] = 1
    path = tmp_path / "heavy.yaml"
    path.write_text(yaml.safe_dump(data))
    monkeypatch.setattr(ob, "pilot_check", lambda *a: None)
    return path


def rows(db: Path) -> list[tuple]:
    with sqlite3.connect(db) as con:
        return con.execute(
            "SELECT plan_index, standard, status, answer_second_more, comparison_more, "
            "source, failure FROM trials ORDER BY plan_index"
        ).fetchall()


def test_a_study_marks_the_trials_it_could_not_explore_and_analyze_leaves_them_out(
    heavy, tmp_path, capsys
):
    db = tmp_path / "s.db"
    res = run_study(heavy, 1, db, workers=1, seed=4)
    got = rows(db)
    assert res.answered == len(got) == 6 and res.failed == 3
    for _, standard, status, answer, more, source, failure in got:
        assert source == "model"
        if standard == pytest.approx(0.06):
            assert status == "complete" and answer in (0, 1) and failure is None
        else:  # 450-600 g: never judged
            assert status == "failed" and answer is None and more is None
            assert "the cube slipped or dropped" in failure and failure.startswith("interval ")
            assert "half width" in failure  # the cause: no pinch the 5 cm cube allows
    # Done: a re-run (resume) computes nothing, the failed trials are not tried again.
    assert run_study(heavy, 1, db, workers=1, seed=4).answered == 0
    assert rows(db) == got
    # The same trials through the runner's path (experiment run --observer model).
    with TrialStore.for_experiment(tmp_path / "r.db", load_experiment(heavy)) as store:
        assert run_model_subject(heavy, "s01", store, 4) == 6
    assert [r[:5] + r[6:] for r in rows(tmp_path / "r.db")] == [r[:5] + r[6:] for r in got]

    js = tmp_path / "a.json"
    assert main(["experiment", "analyze", str(db), "--boot", "0", "--json", str(js)]) == 0
    out = capsys.readouterr().out
    failed = json.loads(js.read_text())["failed"]
    assert failed["n"] == 3 and failed["cells"] == {"ef 0.5": 3}
    assert "3 complete trials" in out
    assert "3 trial(s) whose exploration failed are left out" in out
    assert "the cube slipped or dropped" in out and "ef 0.5: 3" in out
    # Exported with status and cause (--all); the default export has complete ones only.
    assert main(["experiment", "export", str(db), "--csv", str(tmp_path / "a.csv"), "--all"]) == 0
    assert main(["experiment", "export", str(db), "--csv", str(tmp_path / "c.csv")]) == 0
    with open(tmp_path / "a.csv") as f:
        every = list(csv.DictReader(f))
    with open(tmp_path / "c.csv") as f:
        complete = list(csv.DictReader(f))
    assert sorted(r["status"] for r in every) == ["complete"] * 3 + ["failed"] * 3
    assert all(
        r["failure"] and r["answer_second_more"] == "" for r in every if r["status"] == "failed"
    )
    assert [r["status"] for r in complete] == ["complete"] * 3 and not complete[0]["failure"]


def test_a_failed_trial_is_stored_only_with_its_cause_and_without_an_answer(tmp_path):
    exp = load_experiment(WEIGHT)
    seed = exp.subject_seed("s01")
    with TrialStore.for_experiment(tmp_path / "x.db", exp) as store:
        store.ensure_plan("s01", make_plan(exp, seed), seed)
        t = store.next_trial("s01")
        common = dict(response_time_s=None, profile_hash="x", seed=seed, source="model")
        with pytest.raises(ValueError, match="cause"):
            store.record("s01", t, answer_second_more=None, status="failed", **common)
        with pytest.raises(ValueError, match="no answer"):
            store.record("s01", t, answer_second_more=True, status="failed", failure="x", **common)
        with pytest.raises(ValueError, match="cause"):
            store.record("s01", t, answer_second_more=True, failure="x", **common)
        store.record("s01", t, answer_second_more=None, status="failed", failure="x", **common)
        assert store.next_trial("s01").index == t.index + 1
        with pytest.raises(StoreError, match="already answered or failed"):
            store.record("s01", t, answer_second_more=True, **common)


# The trials table as schema 2 wrote it (no failed status, no failure column).
V2_TRIALS = """CREATE TABLE trials (
    id INTEGER PRIMARY KEY AUTOINCREMENT, subject TEXT NOT NULL, plan_index INTEGER NOT NULL,
    experiment TEXT NOT NULL, experiment_hash TEXT NOT NULL, condition TEXT NOT NULL,
    standard REAL NOT NULL, comparison REAL NOT NULL, comparison_first INTEGER NOT NULL,
    answer_second_more INTEGER, comparison_more INTEGER, response_time_s REAL, recording TEXT,
    profile_hash TEXT NOT NULL, seed INTEGER NOT NULL, time_unix_s REAL NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('complete', 'incomplete')), source TEXT,
    FOREIGN KEY (subject, plan_index) REFERENCES plan (subject, "index"));
CREATE UNIQUE INDEX one_answer_per_planned_trial
    ON trials (subject, plan_index) WHERE status = 'complete';"""


def test_a_store_of_schema_2_is_read_and_brought_up_to_date_keeping_every_row(tmp_path):
    db = tmp_path / "old.db"
    exp = load_experiment(WEIGHT)
    seed = exp.subject_seed("s01")
    with TrialStore.for_experiment(db, exp) as store:
        store.ensure_plan("s01", make_plan(exp, seed), seed)
    with sqlite3.connect(db) as con:  # as schema 2 made it
        con.executescript("DROP TABLE trials;" + V2_TRIALS)
        con.execute("ALTER TABLE plan DROP COLUMN practice")
        con.execute("UPDATE meta SET value = '2' WHERE key = 'schema'")
        con.execute(
            "INSERT INTO trials VALUES (7, 's01', 0, ?, ?, 'ef', 0.03, 0.024, 0, 1, 0, 1.5, "
            "NULL, 'x', ?, 100.0, 'complete', 'key')",
            (exp.name, exp.file_hash, seed),
        )
    meta, old = open_for_analysis(db, None)
    assert meta["schema"] == "2" and len(old) == 1 and "failure" not in old[0]
    with TrialStore.for_experiment(db, exp) as store:
        t = store.next_trial("s01")
        store.record(
            "s01", t, answer_second_more=None, response_time_s=None, profile_hash="x",
            seed=seed, status="failed", failure="interval 1: no contact", source="model",
        )  # fmt: skip
    meta, now = open_for_analysis(db, None)
    assert meta["schema"] == "4"
    assert {k: v for k, v in now[0].items() if k not in ("failure", "practice")} == old[0]
    assert now[0]["failure"] is None and now[0]["practice"] == 0 and now[1]["id"] == 8
    assert (now[1]["status"], now[1]["failure"]) == ("failed", "interval 1: no contact")


def test_a_failed_trial_counts_towards_its_track_and_moves_nothing():
    exp = load_experiment(STAIRCASE)
    st = exp.adaptive
    # Every exploration fails: each track still ends, at its trial limit.
    out = ad.session(exp, 3, lambda trial: None)
    assert len(out) == len(ad.tracks_for(exp)) * st.max_trials
    assert {more for _, more in out} == {None}
    # Rebuilt from the store's rows: a failed trial moves its track's count, not its level.
    first = out[0][0]
    row = {"plan_index": 0, "block": first.block, "comparison": first.comparison}
    done = ad.replay(exp, [{**row, "status": "failed", "comparison_more": None}])
    fresh = ad.tracks_for(exp)[first.block]
    assert done[first.block].n == 1 and done[first.block].comparison() == fresh.comparison()
    answered = ad.replay(exp, [{**row, "status": "complete", "comparison_more": 1}])
    assert answered[first.block].n == 1
    # The next trial of a session resumed after the failed one is the uninterrupted one's.
    assert ad.session(exp, 3, lambda trial: None, [{**row, "status": "failed"}]) == out[1:]


def test_an_ef_lift_whose_vertical_cue_is_off_m_g_is_a_failure():
    exp = load_experiment(WEIGHT)
    cfg = ob.default_config(exp)
    prof = ob.observer_profile(exp, cfg)
    t, x, phases = ob.plan_path("lift", prof, cfg.motor, np.random.default_rng(1),
                                settings={"mass_kg": 0.06}, hand=cfg.hand)  # fmt: skip
    rows_ = ob.run_interval(prof, {"allocator": "ef", "mass_kg": 0.06}, (t, x), cfg)
    mg = 0.06 * 9.81
    ef = {"allocator": "ef", "mass_kg": 0.06}
    assert ob.exploration_failure("lift", rows_, phases, x, prof, ef, mg) is None
    off = ob.exploration_failure("lift", rows_, phases, x, prof, ef, 0.8 * mg)
    assert off is not None and off.startswith("cue off")
    # Not an EF rendering: its vertical cue is not m g, and is not checked against it.
    pinv = {"allocator": "pinv", "mass_kg": 0.06}
    assert ob.exploration_failure("lift", rows_, phases, x, prof, pinv, 0.8 * mg) is None


@pytest.mark.parametrize(("standard", "too_wide"), [(0.25, False), (0.5, True)])
def test_heavy_lifts_are_refused_before_a_study_with_the_cause(tmp_path, standard, too_wide):
    # The hand lifts 30-108 g; at 200-300 g the cube slips in its pinch, from 400 g no
    # pinch the 5 cm cube allows carries it (docs/experiments.md, measured).
    data = yaml.safe_load(WEIGHT.read_text())
    data["profile"] = str(ROOT / "configs" / "lift-weight.yaml")
    data["varied"]["standards"] = [standard]
    path = tmp_path / "w.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ExperimentError, match="cannot perform this design") as err:
        run_study(path, 1, tmp_path / "x.db", workers=1)
    assert "the cube slipped or dropped" in str(err.value)
    # The pinch it would need, named where no pinch the cube allows is enough.
    assert ("more than the cube's 25.0 mm half width" in str(err.value)) == too_wide
    assert not (tmp_path / "x.db").exists() or not rows(tmp_path / "x.db")  # nothing stored


def test_a_schema_2_store_with_a_status_schema_3_refuses_is_not_upgraded(tmp_path, capsys):
    db = tmp_path / "old.db"
    exp = load_experiment(WEIGHT)
    seed = exp.subject_seed("s01")
    with TrialStore.for_experiment(db, exp) as store:
        store.ensure_plan("s01", make_plan(exp, seed), seed)
    con = sqlite3.connect(db)
    with con:  # as schema 2 made it, then a hand edit past its check
        con.executescript("DROP TABLE trials;" + V2_TRIALS)
        con.execute("UPDATE meta SET value = '2' WHERE key = 'schema'")
        con.execute("PRAGMA ignore_check_constraints = ON")
        con.execute(
            "INSERT INTO trials VALUES (7, 's01', 0, ?, ?, 'ef', 0.03, 0.024, 0, 1, 0, 1.5, "
            "NULL, 'x', ?, 100.0, 'aborted', 'key')",
            (exp.name, exp.file_hash, seed),
        )
    con.close()
    before = db.read_bytes()
    with pytest.raises(StoreError, match=r"trials row 7 has status 'aborted', not one of"):
        TrialStore.for_experiment(db, exp)
    with pytest.raises(StoreError, match=r"trials row 7 .*status 'aborted', not one of"):
        open_for_analysis(db, None)
    run = ["experiment", "run", str(WEIGHT), "--subject", "s01", "--db", str(db), "--resume"]
    assert main([*run, "--observer", "model", "--no-keys"]) == 2
    err = capsys.readouterr().err
    assert str(db) in err and "'aborted'" in err and "nothing was changed" in err
    assert "Traceback" not in err
    assert db.read_bytes() == before
    con = sqlite3.connect(db)
    try:
        assert con.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone() == ("2",)
        assert con.execute("SELECT id, status FROM trials").fetchall() == [(7, "aborted")]
    finally:
        con.close()
