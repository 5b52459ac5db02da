"""How near its point a staircase's JND lands (hapticd.experiment.bias): the bundled
designs on their point where their earlier settings were not, the two-sided JND under a
shifted PSE within the documented bound and off it beyond, and ``experiment check``'s
warning. Small seeded simulations (scripts/staircase_bias.py is the full study)."""

from __future__ import annotations

import pytest
import yaml
from scipy import stats

from hapticd.cli import main
from hapticd.experiment import bias, load_experiment
from tests.conftest import ROOT

STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-staircase.yaml"
WEIGHT = ROOT / "configs" / "experiments" / "weight-staircase.yaml"
# stiffness-staircase.yaml's settings before initial_rule and min_distance: its tracks
# began 0.4 from the standard and never crossed it.
EARLIER = {"start": 0.4, "initial_rule": False, "min_distance": 0.0}


def staircase(path):
    return load_experiment(path).staircase


def test_the_bundled_stiffness_design_lands_on_its_point_where_its_earlier_one_did_not():
    st = staircase(STIFFNESS)
    now = bias.simulate(st, 0.15, subjects=300, seed=1)
    before = bias.simulate(st.model_copy(update=EARLIER), 0.15, subjects=300, seed=1)
    assert now.point == pytest.approx(stats.norm.ppf(2**-0.5) * 0.15)
    assert abs(now.bias) < bias.TOLERANCE, now
    assert before.bias > 0.08, before  # above the point: nearer 74 % correct than 70.7 %
    assert before.share > 0.72 and abs(now.share - 2**-0.5) < 0.01
    assert now.missing == before.missing == 0


def test_a_shifted_pse_leaves_the_two_sided_jnd_while_within_its_bound():
    """The bound in docs/experiments.md: the track below crosses the standard
    (min_distance below 0), and |shift| + z sigma stays within 2/3 of max_distance."""
    st = staircase(STIFFNESS)
    centred = bias.simulate(st, 0.15, subjects=300, seed=2)
    shifted = bias.simulate(st, 0.15, pse=0.1, subjects=300, seed=2)
    assert abs(shifted.mean / centred.mean - 1) < 0.04, (centred, shifted)
    # Held on its side of the standard, the track below cannot follow the shift.
    kept = st.model_copy(update={"min_distance": 0.0})
    held = bias.simulate(kept, 0.15, pse=0.1, subjects=300, seed=2)
    assert held.mean / bias.simulate(kept, 0.15, subjects=300, seed=2).mean > 1.12
    # Beyond the bound (0.15 + 0.0674 is past 2/3 of the weight design's 0.2) the
    # track above is clipped at max_distance: the JND comes out low.
    w = staircase(WEIGHT)
    assert abs(bias.simulate(w, 0.1, pse=0.05, subjects=300, seed=2).bias) < bias.TOLERANCE
    assert bias.simulate(w, 0.1, pse=0.15, subjects=300, seed=2).bias < -0.1


def test_a_design_is_simulated_at_the_sigmas_its_range_reaches():
    assert bias.sigmas_for(staircase(STIFFNESS)) == bias.SIGMAS
    # 0.6745 x 0.2 = 0.135 is past 2/3 of the weight design's max_distance 0.2.
    assert bias.sigmas_for(staircase(WEIGHT)) == (0.05, 0.10, 0.15)


def write(tmp_path, path, **changes):
    """The bundled file ``path`` with ``changes`` to its staircase, its profile by
    absolute path."""
    data = yaml.safe_load(path.read_text())
    data["profile"] = str((path.parent / data["profile"]).resolve())
    data["staircase"].update(changes)
    out = tmp_path / f"changed-{path.name}"
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def test_check_shows_the_simulated_bias_and_warns_about_a_design_off_its_point(tmp_path, capsys):
    assert main(["experiment", "check", str(STIFFNESS)]) == 0
    out, err = capsys.readouterr()
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("bias"))
    assert "vs its 70.7% point" in line and "at sigma 0.3" in line
    assert "warning" not in err
    # The weight design's earlier settings: a fixed step of 0.02 (0.06 up), its tracks
    # on their side of the standard.
    earlier = write(tmp_path, WEIGHT, step=0.02, step_rule="fixed", min_step=None,
                    min_distance=0.0, stop_reversals=12, threshold_reversals=8)  # fmt: skip
    assert main(["experiment", "check", str(earlier)]) == 0  # a warning, not a refusal
    err = capsys.readouterr().err
    assert f"warning: {earlier}: staircase: the simulated JND is off its 75.0% point" in err
    assert "at sigma 0.05" in err and "min_distance below 0" in err
    assert "initial_rule" not in err  # the weighted rule has no use for it
    # Too few trials for its reversals: most simulated subjects get no JND.
    short = write(tmp_path, STIFFNESS, max_trials=20)
    assert main(["experiment", "check", str(short)]) == 0
    err = capsys.readouterr().err
    assert "of the simulated subjects get no JND" in err and "fewer than 6 reversals" in err
