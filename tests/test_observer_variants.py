"""The model observer's variants: how it judges (JUDGEMENTS) and the actuation angle."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from hapticd.experiment import check_experiment
from hapticd.experiment import observer as ob
from hapticd.experiment.plan import PlannedTrial
from hapticd.experiment.spec import ExperimentError

ROOT = Path(__file__).resolve().parent.parent
STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"
WEIGHT = ROOT / "configs" / "experiments" / "weight-jnd.yaml"


@pytest.fixture(scope="module")
def stiff_exp():
    return check_experiment(STIFFNESS)[0]


def p_yes(cfg: ob.ObserverConfig, first: ob.IntervalCues, second: ob.IntervalCues, n: int) -> float:
    """Share of n trials (each its own generator) answered "the second was more"."""
    rng = np.random.default_rng(12345)
    return float(
        np.mean([ob.judge(cfg, 0, (first, second), rng).answer_second_more for _ in range(n)])
    )


def p_predicted(sd1: float, sd2: float, diff: float) -> float:
    """P(second percept > first) for Gaussian percepts ``diff`` apart."""
    return 0.5 * (1.0 + math.erf(diff / math.hypot(sd1, sd2) / math.sqrt(2.0)))


def test_the_default_observer_is_the_weber_one(stiff_exp):
    cfg = ob.default_config(stiff_exp)
    assert cfg.judgement == "weber" and cfg.actuation_angle_deg is None
    assert ob.observer_overrides(cfg) == ["loop.rate_hz=500", "safety.ramp_s=0"]
    # Its percept: the cue plus one normal draw of sd sqrt((w c)^2 + floor^2) per interval.
    cues = (ob.IntervalCues(60.0, 0.4, 0.007), ob.IntervalCues(66.0, 0.9, 0.002))
    r = ob.judge(cfg, 3, cues, np.random.default_rng(8))
    draws = np.random.default_rng(8).normal(0.0, 1.0, 2)
    want = [c.cue + d * cfg.sense.sd(c.cue) for c, d in zip(cues, draws, strict=True)]
    assert r.percepts == pytest.approx(want, rel=1e-12)
    assert r.cues == (60.0, 66.0) and r.index == 3


def test_the_rising_weber_fraction_makes_small_forces_harder(stiff_exp):
    cfg = ob.default_config(stiff_exp, judgement="rising_weber")
    w, c = cfg.sense.weber, cfg.force_threshold_n
    assert ob.rising_weber_fraction(0.2, w, c) == pytest.approx(w + c / 0.2)
    assert ob.rising_weber_fraction(2.0, w, c) < ob.rising_weber_fraction(0.2, w, c)
    # The same stiffness cues 10 % apart, felt at small or at large forces: the small
    # forces' comparison is the harder one (a Weber observer would not tell them apart).
    n = 6000
    small = p_yes(cfg, ob.IntervalCues(60.0, 0.15), ob.IntervalCues(66.0, 0.165), n)
    large = p_yes(cfg, ob.IntervalCues(60.0, 1.5), ob.IntervalCues(66.0, 1.65), n)
    sd = lambda cue, force: ob.rising_weber_fraction(force, w, c) / ob.JND_PER_NOISE_SD * cue  # noqa: E731
    want_small = p_predicted(sd(60.0, 0.15), sd(66.0, 0.165), 6.0)
    want_large = p_predicted(sd(60.0, 1.5), sd(66.0, 1.65), 6.0)
    assert want_large - want_small > 0.05
    tol = 4 * math.sqrt(0.25 / n)  # four binomial standard errors
    assert small == pytest.approx(want_small, abs=tol)
    assert large == pytest.approx(want_large, abs=tol)
    weber = ob.default_config(stiff_exp)
    same = [
        p_yes(weber, ob.IntervalCues(60.0, f), ob.IntervalCues(66.0, 1.1 * f), 2000)
        for f in (0.15, 1.5)
    ]
    assert same[0] == same[1]  # the default ignores the force level


def test_the_displacement_cue_changes_the_judgement_when_force_is_equal(stiff_exp):
    cfg = ob.default_config(stiff_exp, judgement="force_displacement")
    # Equal force, the second squeezed less far: stiffer. Equal closure, more force:
    # stiffer. Both equal: a coin toss. The stiffness cue (slope) is the same throughout,
    # so an observer that judged it alone would answer at chance in all three.
    n = 2000
    f, x = 0.4, 0.007
    less_far = p_yes(cfg, ob.IntervalCues(60.0, f, x), ob.IntervalCues(60.0, f, 0.7 * x), n)
    harder = p_yes(cfg, ob.IntervalCues(60.0, f, x), ob.IntervalCues(60.0, 1.4 * f, x), n)
    equal = p_yes(cfg, ob.IntervalCues(60.0, f, x), ob.IntervalCues(60.0, f, x), n)
    further = p_yes(cfg, ob.IntervalCues(60.0, f, 0.7 * x), ob.IntervalCues(60.0, f, x), n)
    assert less_far > 0.8 and harder > 0.8 and further < 0.2
    assert abs(equal - 0.5) < 4 * math.sqrt(0.25 / n)
    # The percept is force over closure (N/m), each with its own noise.
    rng = np.random.default_rng(1)
    p = [ob.force_displacement_percept(ob.IntervalCues(60.0, f, x), cfg, rng) for _ in range(4000)]
    assert np.median(p) == pytest.approx(f / x, rel=0.02)
    w_f = ob.rising_weber_fraction(f, cfg.force_weber, cfg.force_threshold_n)
    rel_sd = math.hypot(w_f, cfg.closure_weber) / ob.JND_PER_NOISE_SD
    assert np.std(np.log(p)) == pytest.approx(rel_sd, rel=0.1)
    # Without the closure's noise, only the force's.
    quiet = replace(cfg, closure_weber=0.0)
    p = [
        ob.force_displacement_percept(ob.IntervalCues(60.0, f, x), quiet, rng) for _ in range(4000)
    ]
    assert np.std(p) / (f / x) == pytest.approx(w_f / ob.JND_PER_NOISE_SD, rel=0.1)


def test_squeeze_cues_read_the_hold(stiff_exp):
    # Synthetic rows: the fingers touch at tick 10 and close 1 mm per 10 ticks to 8 mm
    # at tick 90, hold to tick 110; force = 50 N/m x closure along x on each finger.
    n, k = 140, 50.0
    rows = np.zeros(
        n,
        dtype=[
            ("t", "f8"),
            ("in_contact", "?", (2,)),
            ("device_pos", "f8", (2, 3)),
            ("device_force", "f8", (2, 3)),
        ],
    )
    rows["t"] = np.arange(n) * 0.002
    closure = np.clip((np.arange(n) - 10) * 1e-4, 0.0, 0.008)
    closure[110:] = np.linspace(0.008, 0.0, n - 110)
    rows["device_pos"][:, 0, 0] = -0.05 + closure
    rows["device_pos"][:, 1, 0] = 0.05 - closure
    rows["device_force"][:, 0, 0] = k * closure
    rows["device_force"][:, 1, 0] = -k * closure
    rows["in_contact"] = (np.arange(n) >= 10)[:, None] & (closure > 0)[:, None]
    rows["in_contact"][10] = True
    c = ob.squeeze_cues(rows, {"hold_from": 90 * 0.002, "hold_to": 110 * 0.002})
    assert c.cue == pytest.approx(k, rel=1e-6)
    assert c.closure_m == pytest.approx(0.008, rel=1e-6)
    assert c.force_n == pytest.approx(k * 0.008, rel=1e-6)
    # No contact in the hold: no force, no closure.
    rows["in_contact"][80:] = False
    assert ob.squeeze_cues(rows, {"hold_from": 0.18, "hold_to": 0.22}).force_n == 0.0


def test_judgements_and_angles_are_checked(stiff_exp):
    with pytest.raises(ExperimentError, match="rising_weber"):
        ob.default_config(stiff_exp, judgement="bayes")
    weight = check_experiment(WEIGHT)[0]
    with pytest.raises(ExperimentError, match="squeeze"):
        ob.default_config(weight, judgement="force_displacement")
    assert ob.default_config(weight, judgement="rising_weber").sense.cue == "weight"
    for bad in (-1.0, 85.0, float("nan")):
        with pytest.raises(ExperimentError, match="angle"):
            ob.default_config(stiff_exp, actuation_angle_deg=bad)


def test_the_actuation_angle_replaces_the_profiles_directions(stiff_exp, tmp_path):
    cfg = ob.default_config(stiff_exp, actuation_angle_deg=60.0)
    prof = ob.observer_profile(stiff_exp, cfg)
    c, s = math.cos(math.radians(60.0)), math.sin(math.radians(60.0))
    np.testing.assert_allclose(prof.fingers[0].actuated_directions, [[c, 0.0, s]], atol=1e-12)
    np.testing.assert_allclose(prof.fingers[1].actuated_directions, [[-c, 0.0, s]], atol=1e-12)
    assert prof.loop.rate_hz == 500.0
    # A profile with two directions on a finger is refused, naming the profile.
    doc = yaml.safe_load((ROOT / "configs" / "grasp-stiffness.yaml").read_text())
    doc["fingers"][0]["actuated_directions"].append([0.0, 1.0, 0.0])
    (tmp_path / "two.yaml").write_text(yaml.safe_dump(doc))
    exp_doc = yaml.safe_load(STIFFNESS.read_text())
    exp_doc["profile"] = "two.yaml"
    (tmp_path / "exp.yaml").write_text(yaml.safe_dump(exp_doc))
    exp = check_experiment(tmp_path / "exp.yaml")[0]
    with pytest.raises(ExperimentError, match=r"two\.yaml.*\[2, 1\]"):
        ob.profile_document(exp, ob.default_config(exp, actuation_angle_deg=45.0))


def squeeze(exp, cfg, allocator: str) -> ob.IntervalCues:
    prof = ob.observer_profile(exp, cfg)
    rng = np.random.default_rng(4)
    settings = {"allocator": allocator, "stiffness_n_per_m": 60.0}
    return ob.interval_cues("squeeze", prof, settings, cfg, rng)


def test_the_angle_sets_the_gain_between_if_and_pinv(stiff_exp):
    # IF renders the squeeze through 1 / cos(a) along d, pinv cos(a) of it: their cue
    # ratio is 1 / cos^2 a, 4 at 60 degrees; along the grasp line they are the same.
    cfg = ob.default_config(stiff_exp, actuation_angle_deg=60.0)
    ratio = squeeze(stiff_exp, cfg, "if").cue / squeeze(stiff_exp, cfg, "pinv").cue
    assert ratio == pytest.approx(4.0, rel=0.05)
    cfg = ob.default_config(stiff_exp, actuation_angle_deg=0.0)
    a, b = squeeze(stiff_exp, cfg, "if"), squeeze(stiff_exp, cfg, "pinv")
    assert a.cue == pytest.approx(b.cue, rel=1e-3) and a.force_n == pytest.approx(
        b.force_n, rel=1e-3
    )


def test_one_exploration_serves_every_judgement(stiff_exp):
    configs = [ob.default_config(stiff_exp, judgement=j) for j in ob.JUDGEMENTS]
    prof = ob.observer_profile(stiff_exp, configs[0])
    t = PlannedTrial(4, 0, 4, "pinv", 30.0, 1.1, 33.0, False, 0.0)
    shared = ob.answer_trial_judgements(stiff_exp, prof, configs, t, "s03", 11)
    # (The first and the last against their own runs: each run is two loop intervals.)
    for i in (0, -1):
        assert shared[i] == ob.answer_trial(stiff_exp, prof, configs[i], t, "s03", 11)
    assert len({r.percepts for r in shared}) == len(configs)  # each judged its own way
    with pytest.raises(ValueError, match="explore"):
        ob.answer_trial_judgements(
            stiff_exp, prof, [configs[0], replace(configs[0], rate_hz=1000.0)], t, "s03", 11
        )


def test_hapticd_study_selects_the_variant(tmp_path, monkeypatch, capsys):
    from hapticd.cli import main
    from hapticd.experiment import study

    seen = {}

    def fake_run_study(exp, n, db, **kw):
        seen.update(kw)
        return study.StudyResult(["s01"], 0, 0, 0.0)

    monkeypatch.setattr(study, "run_study", fake_run_study)
    args = ["study", str(STIFFNESS), "--observers", "1", "--db", str(tmp_path / "s.db"), "--quiet"]
    assert main([*args, "--judgement", "force_displacement", "--actuation-angle-deg", "45"]) == 0
    assert seen["config"].judgement == "force_displacement"
    assert seen["config"].actuation_angle_deg == 45.0
    assert main(args) == 0 and seen["config"] is None  # the default observer
    assert main([*args, "--judgement", "bayes"]) == 2
    assert "judgements: weber, rising_weber, force_displacement" in capsys.readouterr().err
    assert main([*args, "--actuation-angle-deg", "90"]) == 2
    assert "angle" in capsys.readouterr().err
