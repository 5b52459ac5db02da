"""Experiment files, the trial plan, the trial store (crash and resume) and analyze."""

from __future__ import annotations

import collections
import copy
import itertools
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats

from hapticd.cli import main
from hapticd.experiment import (
    ExperimentError,
    check_experiment,
    load_experiment,
    make_plan,
    parse_experiment,
)
from hapticd.experiment.analyze import analyze
from hapticd.experiment.store import StoreError, TrialStore, open_for_analysis
from hapticd.psychophysics import Z75

ROOT = Path(__file__).resolve().parent.parent
STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"
WEIGHT = ROOT / "configs" / "experiments" / "weight-jnd.yaml"
WRITER = Path(__file__).with_name("fakes") / "trial_writer.py"


@pytest.fixture
def stiffness_data() -> dict:
    return yaml.safe_load(STIFFNESS.read_text())


def write_exp(tmp_path: Path, data: dict, name: str = "exp.yaml") -> Path:
    data = dict(data)
    data["profile"] = str(ROOT / "configs" / Path(data["profile"]).name)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.mark.parametrize("path", [STIFFNESS, WEIGHT])
def test_the_bundled_designs_are_the_seeds(path, capsys):
    exp, _ = check_experiment(path)
    assert exp.varied.standards in ((30.0, 60.0, 90.0), (0.03, 0.06, 0.09))
    assert exp.comparisons == 6 and exp.repetitions == 10
    assert exp.interval.exploration_s == 3.0
    assert exp.trials_per_block == 60 and exp.n_blocks == 6
    assert [c.values()["allocator"] for c in exp.conditions] in (["if", "pinv"], ["ef", "pinv"])
    assert main(["experiment", "check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "60 per block, 6 blocks, 360 per subject" in out
    assert "about 59 min per subject" in out


@pytest.mark.parametrize(
    ("edit", "where", "what"),
    [
        (lambda d: d["varied"].update(standard=[1]), "varied.standard", "did you mean"),
        (lambda d: d["varied"].update(param="stifness_n_per_m"), "varied.param", "did you mean"),
        (lambda d: d["varied"].update(param="allocator"), "varied.param", "not a number"),
        (lambda d: d["varied"].update(ratios=[0.7, 1.3]), "varied.ratios", "at least 3"),
        (lambda d: d["varied"].update(standards=[30, 1e5]), "varied.ratios", "110000 is out"),
        (
            lambda d: d["varied"].update(standards=[30, 2e5]),
            "varied.standards",
            "200000 is outside",
        ),
        (lambda d: d.update(version=True), "version", "expected 1"),
        (lambda d: d.update(name="a" * 5000), "name", "at most 64 characters"),
        (lambda d: d.update(procedure="quest"), "procedure", "'constant_stimuli'"),
        (
            lambda d: d["conditions"][0]["set"].update(alocator="if"),
            "conditions[0:if].set.alocator",
            "did you mean 'allocator'",
        ),
        (
            lambda d: d["conditions"][1]["set"].update(allocator="iff"),
            "conditions[1:pinv].set.allocator",
            "must be one of",
        ),
        (
            lambda d: d["conditions"][1]["set"].update(stiffness_n_per_m=50),
            "(top level)",
            "the varied parameter",
        ),
        (lambda d: d["interval"].update(exploration_s=-1), "interval.exploration_s", "greater"),
        (lambda d: d["interval"].update(question="softer"), "interval.question", "stiffer"),
        (lambda d: d.update(repetitions=9, blocks={"per_standard": 2}), "(top level)", "divide"),
        (lambda d: d.pop("randomization"), "randomization", "required key is missing"),
        # Numbers are numbers: a quoted one, a bool or a float count is refused, not converted.
        (lambda d: d["interval"].update(exploration_s="5"), "interval.exploration_s", "'5'"),
        (lambda d: d["breaks"].update(duration_s="60"), "breaks.duration_s", "'60'"),
        (lambda d: d["breaks"].update(every_blocks=1.0), "breaks.every_blocks", "1.0"),
        (lambda d: d["randomization"].update(seed=True), "randomization.seed", "True"),
        (lambda d: d["randomization"].update(per_subject=1), "randomization.per_subject", "1"),
        (lambda d: d["varied"].update(standards=["30"]), "varied.standards[0]", "'30'"),
        (lambda d: d["varied"].update(ratios=[0.7, "1", 1.3]), "varied.ratios[1]", "'1'"),
    ],
)
def test_errors_name_the_file_and_the_key(stiffness_data, edit, where, what):
    edit(stiffness_data)
    with pytest.raises(ExperimentError) as err:
        parse_experiment(stiffness_data, "x.yaml")
    msg = str(err.value)
    assert msg.startswith("x.yaml: ") and "error(s) in experiment" in msg
    line = next(ln for ln in msg.splitlines() if ln.strip().startswith(where + ":"))
    assert what in line, msg


def test_a_file_error_names_the_line(tmp_path):
    text = STIFFNESS.read_text().replace("version: 1", "version: true")
    text = text.replace("name: stiffness-jnd", "name: " + "x" * 5000)
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ExperimentError) as err:
        load_experiment(path)
    lines = text.splitlines()
    msg = str(err.value)
    assert "version: expected 1" in msg and f"(line {lines.index('version: true') + 1})" in msg
    assert f"(line {lines.index('name: ' + 'x' * 5000) + 1})" in msg
    assert len(msg) < 1000  # the 5,000 characters are not repeated back


def test_the_profile_is_checked_with_the_experiment(tmp_path, stiffness_data, capsys):
    stiffness_data["varied"] = {"param": "mass_kg", "standards": [0.05], "ratios": [0.8, 0.9, 1.1]}
    bad = write_exp(tmp_path, stiffness_data)
    with pytest.raises(ExperimentError, match=r"varied.param: mass_kg on a fixed object"):
        check_experiment(bad)
    assert main(["experiment", "check", str(bad)]) == 2
    assert "fixed" in capsys.readouterr().err
    stiffness_data["profile"] = "nowhere.yaml"
    path = tmp_path / "exp2.yaml"
    path.write_text(yaml.safe_dump(stiffness_data))
    with pytest.raises(ExperimentError, match=r"exp2.yaml: profile: no such file"):
        check_experiment(path)


def test_a_force_limit_above_the_profiles_is_refused_naming_both(tmp_path, stiffness_data):
    cap = check_experiment(write_exp(tmp_path, stiffness_data))[1].safety.max_force_n
    data = copy.deepcopy(stiffness_data)
    data["conditions"][0]["set"]["force_limit_n"] = cap + 1.0
    with pytest.raises(ExperimentError) as err:
        check_experiment(write_exp(tmp_path, data))
    msg = str(err.value)
    assert f"conditions[0:{data['conditions'][0]['name']}].set.force_limit_n" in msg
    assert f"{cap + 1.0:g} N" in msg and f"max_force_n {cap:g} N" in msg
    data = copy.deepcopy(stiffness_data)
    data["conditions"][0]["set"]["force_limit_n"] = cap  # at the limit: fine
    check_experiment(write_exp(tmp_path, data))
    # The varied force limit: its largest comparison counts.
    del data["conditions"][0]["set"]["force_limit_n"]
    data["varied"] = {"param": "force_limit_n", "standards": [cap], "ratios": [0.8, 0.9, 1.1]}
    with pytest.raises(ExperimentError, match=r"force_limit_n reaches .* safety.max_force_n"):
        check_experiment(write_exp(tmp_path, data))


def test_a_bad_base_profile_is_named(tmp_path, stiffness_data, grasp_data, capsys):
    grasp_data["scene"]["object"]["stifness_n_per_m"] = 1.0
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(grasp_data))
    stiffness_data["profile"] = "p.yaml"
    exp = tmp_path / "e.yaml"
    exp.write_text(yaml.safe_dump(stiffness_data))
    assert main(["experiment", "check", str(exp)]) == 2
    err = capsys.readouterr().err
    assert "p.yaml: 1 error(s) in profile" in err
    assert "scene.object.stifness_n_per_m: unknown key" in err


def test_the_plan_presents_every_comparison_repetitions_times_in_seeded_order():
    exp = load_experiment(STIFFNESS)
    plan = make_plan(exp, 11)
    assert plan == make_plan(exp, 11)
    assert [t.index for t in plan] == list(range(360))
    other = make_plan(exp, 12)
    assert [t.comparison for t in plan] != [t.comparison for t in other]
    blocks = collections.defaultdict(list)
    for t in plan:
        blocks[t.block].append(t)
    assert len(blocks) == 6
    for trials in blocks.values():
        assert len({(t.condition, t.standard) for t in trials}) == 1
        counts = collections.Counter(t.ratio for t in trials)
        assert counts == dict.fromkeys(exp.varied.ratios, 10)
        assert not any(t.comparison_first for t in trials)  # standard first
        # Cycles: every comparison once in each run of six, never twice in a row.
        for c in range(10):
            assert sorted(t.ratio for t in trials[6 * c : 6 * c + 6]) == list(exp.varied.ratios)
        assert all(a.ratio != b.ratio for a, b in itertools.pairwise(trials))
        assert [t.comparison for t in trials] == [
            pytest.approx(t.standard * t.ratio) for t in trials
        ]
    # Standards increase within each condition; breaks between blocks only.
    by_cond = collections.defaultdict(list)
    for b in sorted(blocks):
        by_cond[blocks[b][0].condition].append(blocks[b][0].standard)
    assert all(v == [30.0, 60.0, 90.0] for v in by_cond.values())
    assert [t.index for t in plan if t.break_before_s] == [60, 120, 180, 240, 300]
    # Seeds per subject differ and are stable.
    assert exp.subject_seed("s01") == exp.subject_seed("s01") != exp.subject_seed("s02")


def test_the_plan_command_writes_the_subjects_plan(tmp_path, capsys):
    out = tmp_path / "plan.csv"
    assert main(["experiment", "plan", str(STIFFNESS), "--subject", "s03", "--csv", str(out)]) == 0
    exp = load_experiment(STIFFNESS)
    lines = out.read_text().splitlines()
    assert lines[0].split(",") == list(make_plan(exp, 0)[0].as_dict())
    assert len(lines) == 361
    first = make_plan(exp, exp.subject_seed("s03"))[0]
    assert lines[1].split(",")[3:6] == [first.condition, f"{first.standard}", f"{first.ratio}"]
    assert f"seed {exp.subject_seed('s03')}" in capsys.readouterr().out


def test_a_randomized_order_is_balanced(stiffness_data):
    stiffness_data["interval"]["order"] = "randomized"
    stiffness_data["blocks"]["within"] = "shuffle"
    plan = make_plan(parse_experiment(stiffness_data, "x.yaml"), 3)
    first = collections.Counter((t.block, t.ratio) for t in plan if t.comparison_first)
    assert set(first.values()) == {5} and len(first) == 36


def _writer(exp: Path, db: Path, subject: str, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(WRITER), str(exp), str(db), subject, *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


def _committed(db: Path, subject: str) -> list[int]:
    con = sqlite3.connect(db)
    try:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        rows = con.execute(
            "SELECT plan_index FROM trials WHERE subject = ? AND status = 'complete' ORDER BY id",
            (subject,),
        ).fetchall()
    finally:
        con.close()
    return [r[0] for r in rows]


def test_a_killed_writer_loses_at_most_the_trial_in_progress_and_resume_finishes(tmp_path):
    exp = tmp_path / "stiffness-jnd.yaml"
    exp.write_bytes(STIFFNESS.read_bytes())
    db = tmp_path / "trials.db"
    seen = []
    for kill_after in (25, 90):  # two crashes at different points, then a clean finish
        proc = _writer(exp, db, "s01")
        try:
            deadline = time.monotonic() + 30
            while len(seen) < kill_after:
                line = proc.stdout.readline()
                assert line, f"writer ended early: {proc.stderr.read()}"
                seen.append(int(line.split()[1]))
                assert time.monotonic() < deadline, "writer too slow"
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
            # What it reported before the kill and this test had not read yet: a fast
            # writer may be several trials ahead of the reader.
            seen += [int(line.split()[1]) for line in proc.stdout.read().splitlines()]
        finally:
            proc.kill()
            proc.wait(timeout=10)
            proc.stdout.close()
            proc.stderr.close()
        stored = _committed(db, "s01")
        # Every reported commit survived; at most one more (committed, not yet reported).
        assert stored[: len(seen)] == seen
        assert len(stored) - len(seen) <= 1
        assert stored == list(range(len(stored)))
        seen = stored
    proc = _writer(exp, db, "s01")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    stored = _committed(db, "s01")
    assert stored == list(range(360))  # nothing lost, nothing twice, the same plan's order
    meta, rows = open_for_analysis(db)
    assert meta["experiment"] == "stiffness-jnd" and len(rows) == 360
    plan = make_plan(load_experiment(exp), load_experiment(exp).subject_seed("s01"))
    assert [(r["condition"], r["comparison"]) for r in rows] == [
        (t.condition, t.comparison) for t in plan
    ]
    assert con_mode(db) == "wal"


def con_mode(db: Path) -> str:
    con = sqlite3.connect(db)
    try:
        return con.execute("PRAGMA journal_mode").fetchone()[0]
    finally:
        con.close()


def test_a_store_of_another_experiment_or_plan_is_refused(tmp_path, stiffness_data):
    db = tmp_path / "t.db"
    exp = load_experiment(STIFFNESS)
    seed = exp.subject_seed("s01")
    with TrialStore(db, experiment=exp.name, experiment_hash=exp.file_hash) as store:
        store.ensure_plan("s01", make_plan(exp, seed), seed)
        store.ensure_plan("s01", make_plan(exp, seed), seed)  # the same plan: fine
        with pytest.raises(StoreError, match="already has a plan"):
            store.ensure_plan("s01", make_plan(exp, seed + 1), seed + 1)
        t = store.next_trial("s01")
        store.record(
            "s01", t, answer_second_more=True, response_time_s=1.0, profile_hash="x", seed=seed
        )
        with pytest.raises(StoreError, match="already answered"):
            store.record(
                "s01", t, answer_second_more=False, response_time_s=1.0, profile_hash="x", seed=seed
            )
        # An incomplete trial is kept but the planned trial stays to do.
        t1 = store.next_trial("s01")
        store.record(
            "s01",
            t1,
            answer_second_more=None,
            response_time_s=None,
            profile_hash="x",
            seed=seed,
            status="incomplete",
        )
        assert store.next_trial("s01") == t1
    weight = load_experiment(WEIGHT)
    with pytest.raises(StoreError, match=r"another experiment.*'stiffness-jnd'.*'weight-jnd'"):
        TrialStore(db, experiment=weight.name, experiment_hash=weight.file_hash)
    with pytest.raises(StoreError, match="experiment file changed"):
        TrialStore(db, experiment=exp.name, experiment_hash="0" * 64)
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"not sqlite" * 100)
    with pytest.raises(StoreError, match=r"junk\.db"):
        TrialStore(junk, experiment=exp.name, experiment_hash=exp.file_hash)


def test_a_store_of_the_first_schema_is_read_and_brought_up_to_date(tmp_path):
    """A store written before answers had a source (schema 1) is analysed as it is, and a
    writer adds the column, keeping every row."""
    db = tmp_path / "old.db"
    exp = load_experiment(STIFFNESS)
    seed = exp.subject_seed("s01")
    with TrialStore.for_experiment(db, exp) as store:
        store.ensure_plan("s01", make_plan(exp, seed), seed)
        t = store.next_trial("s01")
        store.record(
            "s01", t, answer_second_more=True, response_time_s=1.0, profile_hash="x", seed=seed
        )
    with sqlite3.connect(db) as con:  # as schema 1 wrote it
        con.execute("ALTER TABLE trials DROP COLUMN source")
        con.execute("ALTER TABLE trials DROP COLUMN practice")
        con.execute("ALTER TABLE plan DROP COLUMN practice")
        con.execute("UPDATE meta SET value = '1' WHERE key = 'schema'")
    meta, rows = open_for_analysis(db)
    assert meta["schema"] == "1" and len(rows) == 1 and "source" not in rows[0]
    with TrialStore.for_experiment(db, exp) as store:
        t = store.next_trial("s01")
        store.record(
            "s01", t, answer_second_more=False, response_time_s=2.0, profile_hash="x", seed=seed,
            source="key",
        )  # fmt: skip
        got = store.trials()
    assert [(r["plan_index"], r["source"]) for r in got] == [(0, None), (1, "key")]
    meta, _ = open_for_analysis(db)
    assert meta["schema"] == "4"
    with sqlite3.connect(db) as con:
        con.execute("UPDATE meta SET value = '99' WHERE key = 'schema'")
    with pytest.raises(StoreError, match="schema '99', this hapticd reads 1, 2, 3, 4"):
        open_for_analysis(db)


# Five simulated subjects: the comparison is judged more with probability
# Phi((c - s) / sigma), sigma = Weber x standard / 0.6745; IF (or EF) twice as sharp.
TRUE_WEBER = {"if": 0.08, "pinv": 0.16}


def synthetic_store(db: Path) -> None:
    exp = load_experiment(STIFFNESS)
    rng = np.random.default_rng(2013)
    with TrialStore.for_experiment(db, exp) as store:
        for s in range(5):
            subject = f"s{s + 1:02d}"
            seed = exp.subject_seed(subject)
            store.ensure_plan(subject, make_plan(exp, seed), seed)
            scale = 1 + 0.1 * (s - 2)  # subjects differ a little
            for t in store.remaining(subject):
                sigma = TRUE_WEBER[t.condition] * scale * t.standard / Z75
                more = rng.random() < stats.norm.cdf((t.comparison - t.standard) / sigma)
                store.record(
                    subject,
                    t,
                    answer_second_more=bool(more) != t.comparison_first,
                    response_time_s=1.0,
                    profile_hash="p",
                    seed=seed,
                )


def test_analyze_recovers_the_weber_fractions_and_the_direction_of_the_test(tmp_path, capsys):
    db = tmp_path / "trials.db"
    synthetic_store(db)
    _, rows = open_for_analysis(db)
    # 20 bootstrap refits a fit, not 100: what is checked below (the point fits' Weber
    # fractions, the t-tests) does not depend on them (fit_psychometric's point estimate
    # comes before its bootstrap), and 20 still give every fit its interval.
    result = analyze(rows, n_boot=20)
    assert len(result["fits"]) == 30
    for f in result["fits"]:
        assert set(f) >= {
            "subject",
            "condition",
            "standard",
            "pse",
            "jnd",
            "weber",
            "jnd_ci",
            "n_trials",
        }
        assert f["n_trials"] == 60
        assert (f["jnd_ci"] is not None) == f["estimable"]
    groups = {(g["condition"], g["standard"]): g for g in result["groups"]}
    for (cond, _), g in groups.items():
        assert g["n_subjects"] >= 4
        assert g["weber_mean"] == pytest.approx(TRUE_WEBER[cond], rel=0.3)
    for t in result["tests"]:
        assert t["conditions"] == ["if", "pinv"]
        assert t["df"] == t["n_subjects"] - 1
        assert t["t"] < 0  # IF's Weber fractions are smaller at every standard
    # Five subjects and 60 trials per fit: a halved Weber fraction is significant at
    # 0.05 at most standards (here t = -4.7, -3.5, -2.5; p 0.018, 0.024, 0.067).
    assert sum(t["p"] < 0.05 for t in result["tests"]) >= 2
    out = tmp_path / "a.json"
    plots = tmp_path / "plots"
    assert (
        main(
            [
                "experiment",
                "analyze",
                str(db),
                "--json",
                str(out),
                "--plots",
                str(plots),
                "--boot",
                "0",
                "--param",
                "stiffness_n_per_m",
                "--unit",
                "N/m",
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "varied stiffness_n_per_m (N/m), 1800 complete trials" in text  # the store's design
    assert "paired t-tests" in text and "t(4)" in text
    data = json.loads(out.read_text())
    assert set(data) == {"jnd_point", "fitter", "fits", "groups", "tests"}
    assert data["jnd_point"] == 0.75 and "JND = x(0.75) - x(0.5)" in text
    assert {p.name for p in plots.iterdir()} == {"jnd-ratio.png"} | {
        f"psychometric-s{i:02d}.png" for i in range(1, 6)
    }


def test_analyze_reports_what_it_cannot_fit():
    rows = [
        {"subject": "a", "condition": "if", "standard": 60.0, "comparison": c, "comparison_more": 1}
        for c in (42.0, 48.0, 54.0, 66.0, 72.0, 78.0)
        for _ in range(10)
    ]
    result = analyze(rows, n_boot=0)
    (fit,) = result["fits"]
    assert fit["estimable"] is False and "every answer was 'yes'" in fit["reason"]
    assert fit["weber"] is None
    json.dumps(result["fits"], allow_nan=False)
    assert result["groups"][0]["weber_mean"] is None


def _rows(counts: list[int], subject: str = "a") -> list[dict]:
    """Trial rows of one subject, condition if, standard 60: counts[i] of 10 "more" at
    the six comparisons 42..78."""
    return [
        {"subject": subject, "condition": "if", "standard": 60.0, "comparison": c,
         "comparison_more": int(j < k)}
        for c, k in zip((42.0, 48.0, 54.0, 66.0, 72.0, 78.0), counts, strict=True)
        for j in range(10)
    ]  # fmt: skip


def test_the_jnd_point_and_an_unbounded_interval_show_in_the_report_and_plot(tmp_path):
    from hapticd.experiment.analyze import format_report, plot

    rows = _rows([1, 2, 4, 6, 8, 9]) + _rows([3, 4, 4, 5, 6, 6], subject="b")
    r75 = analyze(rows, n_boot=200)
    r84 = analyze(rows, n_boot=0, jnd_point=0.84)
    a75, a84 = r75["fits"][0], r84["fits"][0]
    assert a84["weber"] / a75["weber"] == pytest.approx(
        stats.norm.ppf(0.84) / stats.norm.ppf(0.75), rel=1e-6
    )
    flat = r75["fits"][1]
    assert flat["estimable"] and flat["jnd_ci"][1] is None  # the near-flat one
    text = format_report(r75, "N/m")
    assert "JND = x(0.75) - x(0.5)" in text and "inf)" in text
    assert "JND = x(0.84) - x(0.5)" in format_report(r84, "N/m")
    written = plot(r75, tmp_path, param="stiffness_n_per_m", unit="N/m")
    assert {p.name for p in written} == {
        "psychometric-a.png",
        "psychometric-b.png",
        "jnd-ratio.png",
    }
    with pytest.raises(ValueError, match="unknown fitter"):
        analyze(rows, fitter="nope")
