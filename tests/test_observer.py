"""The model observer (a simulated subject on the sim hand) and hapticd study."""

from __future__ import annotations

import math
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from hapticd.cli import main
from hapticd.daemon.build import build_renderer
from hapticd.experiment import check_experiment
from hapticd.experiment import observer as ob
from hapticd.experiment.analyze import analyze
from hapticd.experiment.plan import PlannedTrial
from hapticd.experiment.store import StoreError, TrialStore
from hapticd.experiment.study import reduce_design, run_model_subject, run_study

ROOT = Path(__file__).resolve().parent.parent
STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"
WEIGHT = ROOT / "configs" / "experiments" / "weight-jnd.yaml"
COS30 = math.cos(math.radians(30.0))


@pytest.fixture(scope="module")
def stiff():
    exp = check_experiment(STIFFNESS)[0]
    cfg = ob.default_config(exp)
    return exp, ob.observer_profile(exp, cfg), cfg


@pytest.fixture(scope="module")
def weight():
    exp = check_experiment(WEIGHT)[0]
    cfg = ob.default_config(exp)
    return exp, ob.observer_profile(exp, cfg), cfg


def trial(cond: str, standard: float, comparison: float, first: bool = False) -> PlannedTrial:
    return PlannedTrial(0, 0, 0, cond, standard, comparison / standard, comparison, first, 0.0)


def answers(setup, t: PlannedTrial, n: int, seed: int = 7) -> list[bool]:
    exp, prof, cfg = setup
    out = []
    for i in range(n):
        ti = PlannedTrial(i, *list(t.as_dict().values())[1:])
        out.append(ob.answer_trial(exp, prof, cfg, ti, "s01", seed).answer_second_more)
    return out


def interval_rows(setup, settings, seed=3):
    exp, prof, cfg = setup
    rng = np.random.default_rng(seed)
    t, x, phases = ob.plan_path(ob.exploration_kind(exp), prof, cfg.motor, rng)
    return ob.run_interval(prof, settings, (t, x), cfg), phases


def test_a_much_stiffer_comparison_is_judged_stiffer(stiff):
    # Second interval 2x stiffer: nearly always "yes"; first 2x stiffer: nearly always "no".
    assert sum(answers(stiff, trial("pinv", 30.0, 60.0), 12)) >= 11
    assert sum(answers(stiff, trial("pinv", 30.0, 60.0, first=True), 12)) <= 1


def test_equal_stimuli_are_a_coin_toss(stiff):
    yes = sum(answers(stiff, trial("if", 60.0, 60.0), 40, seed=11))
    assert 10 <= yes <= 30  # binomial(40, 0.5): outside this p < 0.002


def test_a_much_heavier_comparison_is_judged_heavier(weight):
    assert sum(answers(weight, trial("ef", 0.03, 0.06), 8)) >= 7


def test_the_cues_are_what_the_allocators_render(stiff, weight):
    # The fixed cube squeezed along the grasp line, actuated 30 degrees up: pinv renders
    # the squeeze through |d . n| = cos 30 of it, IF renders all of it (1 / cos 30 along d).
    k = 60.0
    rows_if, _ = interval_rows(stiff, {"allocator": "if", "stiffness_n_per_m": k})
    rows_pinv, _ = interval_rows(stiff, {"allocator": "pinv", "stiffness_n_per_m": k})
    assert ob.stiffness_cue(rows_if) == pytest.approx(k / COS30, rel=0.05)
    assert ob.stiffness_cue(rows_pinv) == pytest.approx(k * COS30, rel=0.05)
    # The fingertips got what was rendered: no start-up force ramp inside the exploration.
    np.testing.assert_array_equal(rows_if["device_force"], rows_if["rendered_force"])
    assert np.abs(rows_if["device_force"]).max() > 0.2
    # Lifted and held: EF renders the weight, m g, whatever the grip.
    m = 0.06
    rows, ph = interval_rows(weight, {"allocator": "ef", "mass_kg": m})
    assert ob.weight_cue(rows, ph["judge_from"]) == pytest.approx(m * 9.81, rel=0.03)
    held = rows["t"] >= ph["judge_from"]
    assert rows["object_pos"][held][:, 2].min() > 0.005  # really lifted


@pytest.mark.parametrize("method", ["if", "pinv", "ef", "adaptive"])
def test_allocator_forces_are_the_loops_contact_onset_included(stiff, method):
    # The loop's own allocation replayed on the recorded contacts gives what the loop
    # rendered (fixed cube: no ground or walls) on every tick with both fingers in
    # contact, the contact onset blend's included.
    _, prof, _ = stiff
    rows, _ = interval_rows(stiff, {"allocator": method, "stiffness_n_per_m": 60.0})
    renderer = build_renderer(prof)
    robust, adaptive = renderer.allocator.robust, renderer.allocator.adaptive
    again = ob.allocator_forces(rows, renderer.actuation, method, robust=robust, adaptive=adaptive)
    both = rows[rows["in_contact"].all(axis=1)]
    weakest = np.linalg.norm(both["contact_force"], axis=2).min(axis=1)
    assert (weakest < robust.contact_onset_n).sum() >= 3  # ticks inside the onset blend
    assert (weakest > 0.2).sum() > 20
    np.testing.assert_allclose(again, both["rendered_force"], rtol=0, atol=1e-12)
    other = ob.allocator_forces(rows, renderer.actuation, "pinv" if method != "pinv" else "if")
    assert not np.allclose(other, again)


def test_the_same_seed_gives_the_same_trial(stiff):
    exp, prof, cfg = stiff
    t = trial("pinv", 60.0, 66.0)
    a = ob.answer_trial(exp, prof, cfg, t, "s01", 5)
    b = ob.answer_trial(exp, prof, cfg, t, "s01", 5)
    c = ob.answer_trial(exp, prof, cfg, t, "s01", 6)
    assert a == b
    assert c.cues != a.cues and c.percepts != a.percepts


def stored(db: Path) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        return con.execute(
            "SELECT subject, plan_index, condition, standard, comparison, comparison_first, "
            "answer_second_more, comparison_more, seed, status, recording FROM trials "
            "ORDER BY subject, plan_index"
        ).fetchall()
    finally:
        con.close()


def test_a_reduced_study_end_to_end(tmp_path, capsys):
    db = tmp_path / "s.sqlite"
    args = ["study", str(STIFFNESS), "--observers", "2", "--db", str(db)]
    args += ["--standards", "60", "--repetitions", "2", "--workers", "2", "--seed", "1"]
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert "48 trials" in out and "48/48 trials" in err
    rows = stored(db)
    assert len(rows) == 48 and {r[0] for r in rows} == {"s01", "s02"}
    assert all(r[9] == "complete" and r[10] is None for r in rows)
    with TrialStore.for_experiment(db, check_experiment(STIFFNESS)[0]) as store:
        assert store.remaining("s01") == [] and store.remaining("s02") == []
        result = analyze(store.trials(), n_boot=0)
    assert {(g["condition"], g["standard"]) for g in result["groups"]} == {
        ("if", 60.0),
        ("pinv", 60.0),
    }
    # Again: nothing left to do, nothing added.
    assert main(args) == 0
    assert "0 computed now" in capsys.readouterr().out
    assert stored(db) == rows


def test_an_interrupted_subject_resumes(tmp_path, stiff):
    exp = stiff[0]
    db = tmp_path / "r.sqlite"

    class StopError(Exception):
        pass

    def stop_after_5(done: int, total: int) -> None:
        if done == 5:
            raise StopError

    with TrialStore.for_experiment(db, exp) as store, pytest.raises(StopError):
        run_model_subject(
            exp, "s01", store, 3, standards=[30.0], repetitions=2, progress=stop_after_5
        )
    assert len(stored(db)) == 5
    run_study(exp, 1, db, seed=3, workers=1, standards=[30.0], repetitions=2)
    rows = stored(db)
    assert [r[1] for r in rows] == list(range(24))
    # The same answers as one uninterrupted subject.
    whole = tmp_path / "w.sqlite"
    with TrialStore.for_experiment(whole, exp) as store:
        assert run_model_subject(exp, "s01", store, 3, standards=[30.0], repetitions=2) == 24
    assert stored(whole) == rows


def test_experiment_run_with_the_model_observer_is_the_same_subject(tmp_path, stiff, capsys):
    """``hapticd experiment run --observer model`` walks the plan through the runner's
    run_subject with no daemon, and stores what run_model_subject stores."""
    db = tmp_path / "run.sqlite"
    base = ["experiment", "run", str(STIFFNESS), "--subject", "s01", "--observer", "model"]
    base += ["--standards", "30", "--repetitions", "2", "--no-keys", "--db", str(db)]
    assert main(base) == 0
    out, err = capsys.readouterr()
    assert "24 trial(s) answered; 0 left: done" in out, out + err
    assert "trial 1 of 24" in err
    exp = reduce_design(stiff[0], standards=[30.0], repetitions=2)
    with TrialStore.for_experiment(tmp_path / "walk.sqlite", exp) as store:
        assert run_model_subject(exp, "s01", store, None) == 24
    rows = stored(db)
    assert len(rows) == 24 and rows == stored(tmp_path / "walk.sqlite")
    assert len({r[6] for r in rows}) == 2  # both answers occur: not a constant
    with sqlite3.connect(db) as con:
        assert con.execute("SELECT DISTINCT source FROM trials").fetchall() == [("model",)]
    # Resumed when it is done: nothing added.
    assert main([*base, "--resume"]) == 0
    assert "all 24 trials are answered already" in capsys.readouterr().err
    assert stored(db) == rows


def test_pool_one_worker_and_dask_store_the_same_answers(tmp_path, stiff):
    exp = stiff[0]
    # One repetition, 12 trials a subject: still two chunks of a subject's plan (10 and 2,
    # study.CHUNK), the second starting mid-plan, on two processes finishing in any order
    # (each trial's seed and its place in the plan are what the answers must come from);
    # two repetitions ran the same checks on twice the simulated trials.
    design = dict(seed=9, standards=[90.0], repetitions=1)
    run_study(exp, 2, tmp_path / "one.sqlite", workers=1, **design)
    run_study(exp, 2, tmp_path / "pool.sqlite", workers=2, **design)
    one, pool = stored(tmp_path / "one.sqlite"), stored(tmp_path / "pool.sqlite")
    assert len(one) == 24 and one == pool
    pytest.importorskip(
        "distributed", reason="dask.distributed is not installed (pip install 'hapticd[dask]')"
    )
    # In a child process: a Dask cluster leaves threads and processes of its own behind
    # in whatever process ran it. Bounded by the timeout.
    script = DASK_SCRIPT.format(exp=str(STIFFNESS), db=str(tmp_path / "dask.sqlite"))
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=240
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert stored(tmp_path / "dask.sqlite") == one


DASK_SCRIPT = """
import distributed
from hapticd.experiment.study import run_study

if __name__ == "__main__":
    with distributed.LocalCluster(
        processes=True, n_workers=2, threads_per_worker=1, dashboard_address=None
    ) as cluster, distributed.Client(cluster) as client:
        run_study({exp!r}, 2, {db!r}, scheduler=client, seed=9, standards=[90.0], repetitions=1)
"""


def test_bad_input_is_named(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    data = yaml.safe_load(STIFFNESS.read_text())
    data["profile"] = str(ROOT / "configs" / "grasp-stiffness.yaml")
    data["repetitions"] = "ten"
    bad.write_text(yaml.safe_dump(data))
    assert main(["study", str(bad), "--observers", "1", "--db", str(tmp_path / "a.db")]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "repetitions" in err
    assert main(["study", str(STIFFNESS), "--observers", "0", "--db", str(tmp_path / "b.db")]) == 2
    assert "--observers must be at least 1" in capsys.readouterr().err
    # A store of the weight experiment refuses the stiffness one.
    other = tmp_path / "w.db"
    TrialStore.for_experiment(other, check_experiment(WEIGHT)[0]).close()
    assert main(["study", str(STIFFNESS), "--observers", "1", "--db", str(other)]) == 2
    assert "another experiment" in capsys.readouterr().err
    assert (
        main(
            [
                "study",
                str(STIFFNESS),
                "--observers",
                "1",
                "--standards",
                "45",
                "--db",
                str(tmp_path / "c.db"),
            ]
        )
        == 2
    )
    assert "must be one of the file's standards" in capsys.readouterr().err
    data = yaml.safe_load(STIFFNESS.read_text())
    data["profile"] = str(ROOT / "configs" / "grasp-stiffness.yaml")
    data["varied"]["param"] = "damping_n_s_per_m"
    data["varied"]["standards"] = [1.0, 2.0]
    damping = tmp_path / "damping.yaml"
    damping.write_text(yaml.safe_dump(data))
    assert main(["study", str(damping), "--observers", "1", "--db", str(tmp_path / "d.db")]) == 2
    err = capsys.readouterr().err
    assert "damping.yaml: varied.param" in err and "not damping_n_s_per_m" in err
    assert not (tmp_path / "d.db").exists()
    with pytest.raises(StoreError):
        TrialStore.for_experiment(other, check_experiment(STIFFNESS)[0])


def test_reduce_design_keeps_the_file(stiff):
    exp = stiff[0]
    small = reduce_design(exp, standards=[90.0, 30.0], repetitions=4)
    assert small.varied.standards == (30.0, 90.0) and small.repetitions == 4
    assert small.file_hash == exp.file_hash and small.varied.ratios == exp.varied.ratios


@pytest.mark.parametrize("mass", [0.03, 0.175, 0.25])
def test_the_grip_scales_with_the_load_so_heavier_cubes_are_lifted(weight, mass):
    """With the nominal 8 mm pinch a 175 g cube slipped and stayed on the ground (its EF
    cue 1.43 N against m g 1.72 N); the grip scaled to the load and the friction lifts
    it, and the EF cue is m g."""
    _, prof, cfg = weight
    settings = {"allocator": "ef", "mass_kg": mass}
    t, x, phases = ob.plan_path(
        "lift", prof, cfg.motor, np.random.default_rng(1), settings=settings, hand=cfg.hand
    )
    rows = ob.run_interval(prof, settings, (t, x), cfg)
    held = rows["t"] >= phases["judge_from"]
    rose = rows["object_pos"][held][:, 2].mean() - rows["object_pos"][0, 2]
    assert rose > 0.005, rose  # off the ground: carried, not slipping in place
    assert ob.weight_cue(rows, phases["judge_from"]) == pytest.approx(mass * 9.81, rel=0.05)


def test_the_grip_depth_follows_mass_and_friction(weight):
    _, prof, cfg = weight
    light = ob.grip_depth(prof, {"mass_kg": 0.06}, cfg.motor, cfg.hand)
    heavy = ob.grip_depth(prof, {"mass_kg": 0.24}, cfg.motor, cfg.hand)
    slippery = ob.grip_depth(prof, {"mass_kg": 0.06, "friction": [0.4, 0.2]}, cfg.motor, cfg.hand)
    assert heavy == pytest.approx(4 * light) and slippery == pytest.approx(4 * light)
    assert light < cfg.motor.grip_depth_m[0]  # the bundled masses keep the nominal pinch


def test_a_design_the_hand_cannot_perform_is_refused_with_the_cause(tmp_path, capsys):
    """A 500 g cube slips out of the model hand's pinch: ``study`` and ``experiment run
    --observer model`` refuse the design after a few pilot intervals, naming the cause,
    and store nothing."""
    data = yaml.safe_load(WEIGHT.read_text())
    data["profile"] = str(ROOT / "configs" / "lift-weight.yaml")
    data["varied"]["standards"] = [0.5]
    path = tmp_path / "heavy.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    db = tmp_path / "s.sqlite"
    assert main(["study", str(path), "--observers", "1", "--db", str(db), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "the model observer's hand cannot perform this design" in err
    assert "the cube slipped or dropped" in err and "mass_kg 0.6" in err
    run = ["experiment", "run", str(path), "--subject", "m1", "--observer", "model"]
    assert main([*run, "--no-keys", "--db", str(tmp_path / "r.sqlite")]) == 2
    assert "cannot perform this design" in capsys.readouterr().err
    for store in (db, tmp_path / "r.sqlite"):
        if store.exists():
            with sqlite3.connect(store) as con:
                assert con.execute("SELECT COUNT(*) FROM plan").fetchone()[0] == 0


def test_the_bundled_designs_pass_the_pilot(stiff, weight):
    for exp, prof, cfg in (stiff, weight):
        ob.pilot_check(exp, prof, cfg)  # raises naming the cause otherwise
