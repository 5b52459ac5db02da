"""Adaptive staircases (hapticd.experiment.adaptive): the rules, convergence, the file's
checks, resume, the model observer and hapticd study running them, and analyze."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats

from hapticd.cli import main
from hapticd.experiment import ExperimentError, load_experiment, parse_experiment
from hapticd.experiment import adaptive as ad
from hapticd.experiment import runner as rn
from hapticd.experiment.spec import Staircase
from hapticd.experiment.store import TrialStore
from hapticd.experiment.study import run_study
from tests.conftest import ROOT

STAIRCASE = ROOT / "configs" / "experiments" / "stiffness-staircase.yaml"
WEIGHT_STAIRCASE = ROOT / "configs" / "experiments" / "weight-staircase.yaml"


def st(**kw) -> Staircase:
    base = dict(rule="1up2down", start=0.4, step=0.1, min_step=0.02, max_distance=0.6)
    return Staircase(**{**base, **kw})


def test_one_up_two_down_moves_reverses_and_halves_its_step():
    s = st()
    t = ad.Track(0, "if", 60.0, 1, s.start, s.step)
    t.answer(True, s)
    assert t.distance == pytest.approx(0.4)  # one correct: no move yet
    t.answer(True, s)
    assert t.distance == pytest.approx(0.3) and t.reversals == []  # two: down
    t.answer(False, s)  # one wrong: up, a reversal at 0.3, the step halves
    assert t.reversals == [pytest.approx(0.3)] and t.reversal_trials == [3]
    assert t.distance == pytest.approx(0.35) and t.step == pytest.approx(0.05)
    t.answer(True, s)
    t.answer(False, s)  # a wrong answer resets the run: no move down in between
    assert t.distance == pytest.approx(0.4) and len(t.reversals) == 1  # up again: no reversal
    assert t.comparison() == pytest.approx(60 * 1.4)
    below = ad.Track(1, "if", 60.0, -1, s.start, s.step)
    assert below.comparison() == pytest.approx(36.0)
    assert ad.is_correct(below, False) and not ad.is_correct(t, False)


def test_the_weighted_rule_steps_up_by_target_over_one_minus_target_and_clips():
    s = st(rule="weighted", target=0.75, step_rule="fixed", min_step=None)
    t = ad.Track(0, "ef", 0.06, 1, s.start, s.step)
    t.answer(True, s)
    assert t.distance == pytest.approx(0.3)  # one correct is enough
    t.answer(False, s)
    assert t.distance == pytest.approx(0.6)  # up 3 steps (0.75 / 0.25), clipped at the max
    for _ in range(20):
        t.answer(True, s)
    assert t.distance == 0.0  # never below the standard (above-track)


def test_a_track_stops_on_reversals_or_trials():
    s = st(stop_reversals=2, max_trials=5, threshold_reversals=2)
    t = ad.Track(0, "if", 60.0, 1, s.start, s.step)
    for c in (True, True, False, True, True):
        t.answer(c, s)
    assert len(t.reversals) == 2 and t.done(s)
    assert t.threshold(s) == pytest.approx(np.mean(t.reversals))
    u = ad.Track(0, "if", 60.0, 1, s.start, s.step)
    for _ in range(5):
        u.answer(True, s)
    assert u.done(s) and u.threshold(s) is None and u.n == 5


@pytest.mark.parametrize(("rule", "target"), [("1up2down", None), ("weighted", 0.75)])
def test_tracks_converge_on_the_rule_target(rule, target):
    """A simulated observer, P(judged more) = Phi((c - s) / sigma), sigma 0.2 of the
    standard: the above-track's mean threshold is the comparison where it is correct at
    the rule's target (x(0.707) or x(0.75)), within the staircase's known small bias
    (measured with 200 tracks: +2 % for 1-up-2-down, +7 % for weighted, whose up and
    down steps differ; with only 12 reversals the early, large steps bias it more)."""
    s = st(rule=rule, target=target, step=0.08, min_step=0.02, max_distance=0.9,
           stop_reversals=30, max_trials=400, threshold_reversals=20)  # fmt: skip
    sigma = 0.2
    rng = np.random.default_rng(1)
    got = []
    for _ in range(100):
        t = ad.Track(0, "if", 60.0, 1, s.start, s.step)
        while not t.done(s):
            p = stats.norm.cdf(t.distance / sigma)
            t.answer(bool(rng.random() < p), s)
        if t.threshold(s) is not None:
            got.append(t.threshold(s))
    want = sigma * stats.norm.ppf(s.target_share)
    assert len(got) == 100
    assert np.mean(got) == pytest.approx(want, rel=0.12), (np.mean(got), want)


def write_staircase(tmp_path: Path, **changes) -> Path:
    """stiffness-staircase.yaml made small (2 reversals or 10 trials a track) with
    ``changes`` to its staircase section; its profile by absolute path."""
    data = yaml.safe_load(STAIRCASE.read_text())
    data["profile"] = str(ROOT / "configs" / "grasp-stiffness.yaml")
    data["staircase"].update(stop_reversals=3, max_trials=10, threshold_reversals=2)
    data["staircase"].update(changes)
    path = tmp_path / "sc.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.mark.parametrize(
    ("edit", "where", "what"),
    [
        (lambda d: d.update(procedure="quest"), "procedure", "'staircase'"),
        (lambda d: d["staircase"].update(step=0), "staircase.step", "greater than 0"),
        (lambda d: d["staircase"].update(step=-0.1), "staircase.step", "greater than 0"),
        (lambda d: d["staircase"].update(step=0.7), "staircase", "cannot converge"),
        (lambda d: d["staircase"].update(min_step=0.5), "staircase", "larger than step"),
        (lambda d: d["staircase"].update(target=0.8), "staircase", "weighted rule"),
        (lambda d: d["staircase"].update(max_distance=1.2), "staircase", "below 1"),
        (lambda d: d["staircase"].update(rule="2up1down"), "staircase.rule", "1up2down"),
        (lambda d: d.pop("staircase"), "(top level)", "needs a staircase section"),
        (lambda d: d.update(repetitions=10), "(top level)", "for constant_stimuli"),
        (
            lambda d: d["varied"].update(param="mass_kg", standards=[9.0]),
            "(top level)",
            "outside mass_kg's range",
        ),
    ],
)
def test_a_staircase_file_that_cannot_work_is_named(edit, where, what):
    data = yaml.safe_load(STAIRCASE.read_text())
    edit(data)
    with pytest.raises(ExperimentError) as err:
        parse_experiment(data, "x.yaml")
    msg = str(err.value)
    line = next(ln for ln in msg.splitlines() if ln.strip().startswith(where + ":"))
    assert what in line, msg


class Simulated:
    """A presenter answering as P(judged more) = Phi((c - s) / (0.2 s)), drawn from the
    trial's index and seed only; it aborts the trial numbered ``abort_at``."""

    def __init__(self, seed: int, abort_at: int | None = None) -> None:
        self.seed, self.abort_at = seed, abort_at

    def present(self, exp, trial, params):
        if trial.index == self.abort_at:
            raise rn.TrialAbortedError("stopped here")
        rng = np.random.default_rng([self.seed, trial.index, 99])
        more = rng.random() < stats.norm.cdf((trial.comparison / trial.standard - 1) / 0.2)
        return rn.Presented(bool(more) != trial.comparison_first, 0.1, source="sim")

    def rest(self, seconds):
        pass


def session_rows(db: Path) -> list[tuple]:
    with sqlite3.connect(db) as con:
        return con.execute(
            "SELECT plan_index, condition, standard, comparison, comparison_first, "
            "comparison_more FROM trials WHERE status = 'complete' ORDER BY subject, plan_index"
        ).fetchall()


def test_a_resumed_session_continues_exactly_where_it_stopped(tmp_path):
    exp = load_experiment(write_staircase(tmp_path))
    seed = 5
    with TrialStore.for_experiment(tmp_path / "whole.db", exp) as store:
        n = rn.run_adaptive_subject(store, exp, "s1", seed, Simulated(seed), profile_hash="p")
    whole = session_rows(tmp_path / "whole.db")
    assert n == len(whole) > 40
    # Every track ran (12 of them), each until its stop rule.
    assert len({(r[1], r[2]) for r in whole}) == 6
    with TrialStore.for_experiment(tmp_path / "cut.db", exp) as store:
        with pytest.raises(rn.TrialAbortedError):
            rn.run_adaptive_subject(
                store, exp, "s1", seed, Simulated(seed, abort_at=23), profile_hash="p"
            )
        assert len(store.trials()) == 23 and len(store.trials("incomplete")) == 1
    # A new process's worth of state: the tracks rebuilt from the store alone.
    with TrialStore.for_experiment(tmp_path / "cut.db", exp) as store:
        again = store.plan("s1")[23]
        rn.run_adaptive_subject(store, exp, "s1", seed, Simulated(seed), profile_hash="p")
        assert store.plan("s1")[23] == again  # the stopped trial presented as it was
    assert session_rows(tmp_path / "cut.db") == whole


# PsychoPy's options: 2 up 3 down after a one-up-one-down start, the end on both
# reversals and trials; and the tracks may cross the standard.
PSYCHOPY_OPTIONS = dict(rule="updown", n_up=2, n_down=3, initial_rule=True, stop="both",
                        min_trials=12, max_trials=30, start=0.1, step=0.05, min_step=0.01,
                        min_distance=-0.6)  # fmt: skip


def test_a_resumed_session_with_psychopys_options_continues_exactly(tmp_path):
    exp = rn.reduced(
        load_experiment(write_staircase(tmp_path, **PSYCHOPY_OPTIONS)), standards=[60.0]
    )
    seed = 11
    with TrialStore.for_experiment(tmp_path / "whole.db", exp) as store:
        rn.run_adaptive_subject(store, exp, "s1", seed, Simulated(seed), profile_hash="p")
        rows = store.trials()
    whole = session_rows(tmp_path / "whole.db")
    assert len(whole) > 20
    cut = tmp_path / "cut.db"
    with TrialStore.for_experiment(cut, exp) as store, pytest.raises(rn.TrialAbortedError):
        rn.run_adaptive_subject(
            store, exp, "s1", seed, Simulated(seed, abort_at=13), profile_hash="p"
        )
    with TrialStore.for_experiment(cut, exp) as store:
        rn.run_adaptive_subject(store, exp, "s1", seed, Simulated(seed), profile_hash="p")
    assert session_rows(cut) == whole
    # Every track ran to its own end: replayed from the rows, each is done by its rule.
    tracks = ad.tracks_from_rows(rows, exp.staircase)
    assert len(tracks) == 4 and all(t.done(exp.staircase) for t in tracks.values())
    assert all(t.n >= 12 for t in tracks.values())  # stop both: min_trials too
    # Some comparisons on the other side of their track's standard.
    assert any(
        (r["block"] % 2 == 0) == (r["comparison"] < r["standard"])
        for r in rows
        if r["comparison"] != r["standard"]
    )


def test_a_store_written_before_psychopys_options_keeps_its_rules():
    """A store's staircase design as written before these keys: they take the values
    that move its tracks as they moved then."""
    earlier = dict(rule="1up2down", sides="both", start=0.4, step=0.1, step_rule="halve",
                   min_step=0.02, max_distance=0.6, stop_reversals=10, max_trials=50,
                   threshold_reversals=6)  # fmt: skip
    s = Staircase.model_validate(earlier)
    assert (s.step_type, s.min_distance, s.initial_rule, s.stop, s.min_trials) == (
        "lin",
        0.0,
        False,
        "either",
        0,
    )
    assert s.moves == (1, 2) and s.up_factor == 1.0


def test_the_model_observer_and_study_run_a_staircase_with_the_same_answers(tmp_path, capsys):
    path = write_staircase(tmp_path)
    db = tmp_path / "run.db"
    base = ["experiment", "run", str(path), "--subject", "s01", "--observer", "model"]
    assert main([*base, "--standards", "60", "--no-keys", "--db", str(db)]) == 0
    out = capsys.readouterr().out
    assert "left: done" in out
    run_study(path, 2, tmp_path / "one.db", workers=1, standards=[60.0])
    run_study(path, 2, tmp_path / "pool.db", workers=2, standards=[60.0])
    one, pool = session_rows(tmp_path / "one.db"), session_rows(tmp_path / "pool.db")
    assert one == pool and len(one) > 20
    try:
        import distributed  # noqa: F401
    except ImportError:
        pass  # pip install 'hapticd[dask]' to test it on Dask too
    else:
        # In a child process: a Dask cluster leaves threads and processes behind.
        script = DASK_SCRIPT.format(exp=str(path), db=str(tmp_path / "dask.db"))
        proc = subprocess.run(
            [sys.executable, "-c", script], capture_output=True, text=True, timeout=400,
            cwd=ROOT,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert session_rows(tmp_path / "dask.db") == one
    with sqlite3.connect(tmp_path / "one.db") as con:
        s01 = con.execute(
            "SELECT plan_index, condition, standard, comparison, comparison_first, "
            "comparison_more FROM trials WHERE subject = 's01' ORDER BY plan_index"
        ).fetchall()
    assert s01 == session_rows(db)  # the runner's subject is the study's s01
    # Analyze: per track thresholds, the fit, a plot per subject's tracks.
    plots = tmp_path / "plots"
    assert main(["experiment", "analyze", str(tmp_path / "one.db"), "--boot", "0",
                 "--plots", str(plots)]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "staircase tracks (1up2down, converging on 70.7% correct" in text
    assert "thresholds from the reversals" in text and "if vs pinv" in text
    assert {"staircase-s01.png", "staircase-s02.png"} <= {p.name for p in plots.iterdir()}
    # Export: one row per complete trial.
    out_csv = tmp_path / "t.csv"
    assert main(["experiment", "export", str(tmp_path / "one.db"), "--csv", str(out_csv)]) == 0
    assert len(out_csv.read_text().splitlines()) == len(one) + 1


DASK_SCRIPT = """
import distributed
from hapticd.experiment.study import run_study

if __name__ == "__main__":
    with distributed.LocalCluster(
        processes=True, n_workers=2, threads_per_worker=1, dashboard_address=None
    ) as cluster, distributed.Client(cluster) as client:
        run_study({exp!r}, 2, {db!r}, scheduler=client, standards=[60.0])
"""


def test_the_bundled_staircases_check(capsys):
    for path in (STAIRCASE, WEIGHT_STAIRCASE):
        assert main(["experiment", "check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert (
        "staircase 1up2down (converges on 70.7% correct; one up, one down until the first "
        "reversal; crossing the standard by up to 0.6), 12 tracks" in out
    )
    assert "staircase weighted (converges on 75.0% correct; crossing the standard by up to " in out
    assert "warning" not in err  # both land on their point (tests/test_staircase_bias.py)


def test_quest_plus_resumes_exactly_and_estimates_the_observer(tmp_path, capsys):
    pytest.importorskip("questplus")
    from hapticd.experiment.analyze import analyze_quest
    from hapticd.experiment.store import design as store_design

    data = yaml.safe_load((ROOT / "configs" / "experiments" / "stiffness-quest.yaml").read_text())
    data["profile"] = str(ROOT / "configs" / "grasp-stiffness.yaml")
    data["quest_plus"]["trials"] = 30
    path = tmp_path / "q.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    exp = rn.reduced(load_experiment(path), standards=[60.0])
    with TrialStore.for_experiment(tmp_path / "whole.db", exp) as store:
        rn.run_adaptive_subject(store, exp, "s1", 3, Simulated(3), profile_hash="p")
        rows = store.trials()
    whole = session_rows(tmp_path / "whole.db")
    assert len(whole) == 60  # two tracks of 30
    assert len({r[3] for r in whole}) > 5  # QUEST+ moves the comparison
    cut = tmp_path / "cut.db"
    with TrialStore.for_experiment(cut, exp) as store, pytest.raises(rn.TrialAbortedError):
        rn.run_adaptive_subject(store, exp, "s1", 3, Simulated(3, abort_at=17), profile_hash="p")
    with TrialStore.for_experiment(cut, exp) as store:
        rn.run_adaptive_subject(store, exp, "s1", 3, Simulated(3), profile_hash="p")
    assert session_rows(tmp_path / "cut.db") == whole
    # The simulated observer's sigma is 0.2 of the standard: JND 0.6745 x 12 = 8.1 N/m.
    result = analyze_quest(rows, store_design(exp)["quest_plus"], 0.75)
    for t in result["tracks"]:
        assert t["trials"] == 30
        assert 8.1 / 2 < t["jnd"] < 8.1 * 2, t
        assert abs(t["pse"] - 60) < 8, t


@pytest.mark.parametrize(
    ("key", "value"),
    [("step", '"0.1"'), ("start", '"0.3"'), ("max_trials", '"10"'), ("stop_reversals", "3.0")],
)
def test_a_number_written_as_a_string_or_a_float_count_is_refused_with_its_line(
    tmp_path, key, value
):
    # Quoted YAML is a string: "0.1" must not become a step of 0.1 behind the user's back.
    text = write_staircase(tmp_path).read_text()
    lines = text.splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.strip().startswith(f"{key}:"))
    lines[at] = lines[at].split(":")[0] + f": {value}"
    path = tmp_path / "typed.yaml"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ExperimentError) as err:
        load_experiment(path)
    msg = str(err.value)
    line = next(ln for ln in msg.splitlines() if ln.strip().startswith(f"staircase.{key}:"))
    assert f"(line {at + 1})" in line and value.strip('"') in line, msg
