"""Designs balanced across subjects (randomization.counterbalance, the subject list,
``hapticd experiment orders``) and session metadata (``--meta``), stored with each
session and carried into the export."""

from __future__ import annotations

import contextlib
import csv
import io
import itertools
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from hapticd.cli import main
from hapticd.experiment import ExperimentError, load_experiment, make_plan, parse_experiment
from hapticd.experiment import export as ex
from hapticd.experiment import runner as rn
from hapticd.experiment.plan import williams_rows
from hapticd.experiment.store import TrialStore
from tests.conftest import ROOT

STIFFNESS = ROOT / "configs" / "experiments" / "stiffness-jnd.yaml"
ALLOCATORS = ("if", "pinv", "ef", "pinv_exact")


def design(n_conditions: int, **randomization) -> dict:
    """A small constant-stimuli design (1 standard, 3 ratios, 2 repetitions) of
    ``n_conditions`` conditions, the conditions' order listed."""
    d = yaml.safe_load(STIFFNESS.read_text())
    d["profile"] = str(ROOT / "configs" / "grasp-stiffness.yaml")
    d["conditions"] = [{"name": a, "set": {"allocator": a}} for a in ALLOCATORS[:n_conditions]]
    d["varied"].update(standards=[60.0], ratios=[0.8, 0.9, 1.2])
    d["repetitions"] = 2
    d["blocks"]["condition_order"] = "listed"
    d["randomization"].update(randomization)
    return d


def write(tmp_path: Path, data: dict, name: str = "exp.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def block_conditions(plan) -> list[str]:
    """The condition of each block of a plan, in order."""
    return [next(t.condition for t in plan if t.block == b) for b in range(plan[-1].block + 1)]


def assert_balanced(orders: list[list[str]], names: list[str]) -> None:
    """Each condition equally often at each position, each ordered pair of different
    conditions equally often as neighbours, counted here afresh."""
    for p in range(len(names)):
        at = Counter(o[p] for o in orders)
        assert set(at) == set(names) and len(set(at.values())) == 1, (p, at)
    pairs = Counter((a, b) for o in orders for a, b in itertools.pairwise(o))
    assert set(pairs) == set(itertools.permutations(names, 2)), pairs
    assert len(set(pairs.values())) == 1, pairs


@pytest.mark.parametrize(("n", "cycle"), [(4, 4), (3, 6)])
def test_twelve_subjects_plans_form_a_balanced_latin_square(n, cycle):
    data = design(n, counterbalance="latin_square")
    data["subjects"] = [f"p{k:02d}" for k in range(12)]
    exp = parse_experiment(data, "x.yaml")
    names = [c.name for c in exp.conditions]
    orders = []
    for subject in exp.subjects:
        plan = make_plan(exp, exp.subject_seed(subject), exp.subject_index(subject))
        orders.append(block_conditions(plan))
        # Counterbalancing orders the blocks; every comparison is still presented.
        per = Counter((t.condition, t.ratio) for t in plan)
        assert set(per.values()) == {2} and len(per) == 3 * n
    assert all(sorted(o) == sorted(names) for o in orders)
    # Each cycle of subjects (n rows, 2n for an odd n) is balanced on its own.
    for start in range(0, 12, cycle):
        assert_balanced(orders[start : start + cycle], names)
    if n % 2 == 0:  # an even square: once per position, each pair once, per cycle
        for start in range(0, 12, cycle):
            assert {o[0] for o in orders[start : start + cycle]} == set(names)


@given(st.integers(2, 9))
def test_williams_rows_are_balanced_for_any_number_of_conditions(n):
    rows = williams_rows(n)
    assert len(rows) == (n if n % 2 == 0 else 2 * n)
    assert all(sorted(r) == list(range(n)) for r in rows)
    assert_balanced([[str(c) for c in r] for r in rows], [str(c) for c in range(n)])


def test_abba_presents_each_condition_in_two_halves_alternating_across_subjects():
    data = design(2, counterbalance="abba")
    data["varied"]["standards"] = [30.0, 60.0]
    data["blocks"]["per_standard"] = 2
    exp = parse_experiment(data, "x.yaml")
    orders = {}
    for k in range(4):
        plan = make_plan(exp, exp.subject_seed(f"s{k}"), k)
        blocks = [(t.condition, t.standard) for t in plan if t.position == 0]
        a, b = ("if", "pinv") if k % 2 == 0 else ("pinv", "if")
        # A B B A: each half of a condition holds one block of every standard.
        assert blocks == [(c, s) for c in (a, b, b, a) for s in (30.0, 60.0)]
        assert Counter((t.condition, t.standard, t.ratio) for t in plan) == {
            (c, s, r): 2 for c in ("if", "pinv") for s in (30.0, 60.0) for r in (0.8, 0.9, 1.2)
        }
        orders[k] = [c for c, _ in blocks[::2]]
    assert orders[0] == ["if", "pinv", "pinv", "if"] and orders[1] == ["pinv", "if", "if", "pinv"]


@pytest.mark.parametrize(
    ("edit", "what"),
    [
        (lambda d: d["blocks"].update(per_standard=1), "per_standard must be even"),
        (lambda d: d["blocks"].update(condition_order="random"), "condition_order must be listed"),
    ],
)
def test_a_scheme_the_design_cannot_follow_is_refused_naming_the_key_and_line(tmp_path, edit, what):
    data = design(2, counterbalance="abba")
    data["blocks"]["per_standard"] = 2
    edit(data)
    path = write(tmp_path, data)
    with pytest.raises(ExperimentError) as err:
        load_experiment(path)
    line = path.read_text().splitlines().index("randomization:") + 1
    msg = next(x for x in str(err.value).splitlines() if x.strip().startswith("randomization:"))
    assert what in msg and f"(line {line})" in msg


def test_three_conditions_and_four_subjects_say_how_far_from_balanced(tmp_path, capsys):
    data = design(3, counterbalance="latin_square")
    data["subjects"] = ["a", "b", "c", "d"]
    path = write(tmp_path, data)
    assert main(["experiment", "orders", str(path)]) == 0
    out, err = capsys.readouterr()
    rows = [ln.split() for ln in out.splitlines()[2:6]]
    assert [r[0] for r in rows] == ["a", "b", "c", "d"]
    orders = [r[2:] for r in rows]
    # The first four of the six rows: positions hold a condition once or twice (spread
    # 1); an ordered pair is neighbours 0 to 2 times (spread 2).
    spread = max(max(c.values()) - min(c.values()) for c in map(Counter, zip(*orders, strict=True)))
    pairs = Counter((x, y) for o in orders for x, y in itertools.pairwise(o))
    counts = [pairs.get(p, 0) for p in itertools.permutations(["if", "pinv", "ef"], 2)]
    assert (spread, max(counts) - min(counts)) == (1, 2)
    assert "not balanced" in err and "up to 1 " in err and "up to 2;" in err
    assert "multiple of 6 subjects" in err
    # The same warning at check, which still succeeds.
    assert main(["experiment", "check", str(path)]) == 0
    assert "not balanced" in capsys.readouterr().err
    # Six subjects balance it: no warning.
    assert main(["experiment", "orders", str(path), "--subjects", "6"]) == 0
    out, err = capsys.readouterr()
    assert "not balanced" not in err and "balanced:" in out


def test_the_orders_report_counts_positions_and_carryover(tmp_path, capsys):
    path = write(tmp_path, design(4, counterbalance="latin_square"))
    assert main(["experiment", "orders", str(path), "--subjects", "8"]) == 0
    lines = capsys.readouterr().out.splitlines()
    at = lines.index("each condition's count at each position:")
    assert [ln.split() for ln in lines[at + 2 : at + 6]] == [
        [c, "2", "2", "2", "2"] for c in ALLOCATORS
    ]
    carry = lines.index("carryover: how often the column's condition directly follows the row's:")
    table = [ln.split()[1:] for ln in lines[carry + 2 : carry + 6]]
    assert [table[i][i] for i in range(4)] == ["0"] * 4
    assert {table[i][j] for i in range(4) for j in range(4) if i != j} == {"2"}


def test_a_counterbalanced_subject_needs_its_place(tmp_path):
    data = design(2, counterbalance="latin_square")
    data["subjects"] = ["p1", "p2"]
    exp = load_experiment(write(tmp_path, data))
    assert exp.subject_index("p2") == 1 and exp.subject_index("x", 5) == 5
    with pytest.raises(ExperimentError, match="--subject-index"):
        exp.subject_index("x")
    with pytest.raises(ExperimentError, match="'p2' is number 1"):
        exp.subject_index("p2", 0)


# -- session metadata ----------------------------------------------------------------------


def with_metadata(tmp_path: Path) -> Path:
    data = design(2)
    data["metadata"] = {
        "keys": {
            "handedness": {"required": True, "choices": ["left", "right"]},
            "age_years": {"type": "integer"},
        }
    }
    return write(tmp_path, data)


def test_unknown_missing_and_bad_metadata_are_refused_naming_key_and_line(tmp_path, capsys):
    path = with_metadata(tmp_path)
    text = path.read_text().splitlines()
    exp = load_experiment(path)
    with pytest.raises(ExperimentError) as err:
        exp.check_metadata({"colour": "red", "age_years": "old"})
    msg = {ln.split(":")[0].strip(): ln for ln in str(err.value).splitlines()[1:]}
    assert set(msg) == {"colour", "age_years", "handedness"}
    assert f"(line {text.index('  keys:') + 1})" in msg["colour"]
    assert "required" in msg["handedness"]
    assert f"(line {text.index('    handedness:') + 1})" in msg["handedness"]
    assert f"(line {text.index('    age_years:') + 1})" in msg["age_years"]
    assert exp.check_metadata({"handedness": "left", "age_years": "31", "notes": "x"}) == {
        "handedness": "left",
        "age_years": 31,
        "notes": "x",
    }
    assert main(["experiment", "check", str(path), "--meta", "handedness=up"]) == 2
    assert "handedness" in capsys.readouterr().err
    # A bad declaration is the file's own error, at its key.
    data = yaml.safe_load(path.read_text())
    data["metadata"]["keys"]["age_years"]["type"] = "float"
    with pytest.raises(ExperimentError, match=r"metadata\.keys\.age_years\.type"):
        load_experiment(write(tmp_path, data, "bad.yaml"))


class Quick:
    """Answers every trial at once; aborts the run at trial ``stop``."""

    stop: int | None = None

    def present(self, exp, trial, params):
        if trial.index == Quick.stop:
            raise rn.TrialAbortedError("stopped by the test")
        return rn.Presented(trial.index % 2 == 0, 0.1, source="key")

    def rest(self, seconds):
        pass


@contextlib.contextmanager
def quick_observer(exp, subject, options) -> Iterator[Quick]:
    yield Quick()


def test_session_metadata_is_stored_with_each_session_and_exported(tmp_path, monkeypatch):
    monkeypatch.setitem(rn.OBSERVERS, "quick", f"{__name__}:quick_observer")
    path = with_metadata(tmp_path)
    exp = load_experiment(path)
    db = tmp_path / "t.db"
    opts = rn.RunOptions(keys_fd=None, out=io.StringIO())
    run = dict(observer="quick", options=opts, subject_index=3)
    # Refused before anything is stored.
    with pytest.raises(ExperimentError, match="handedness"):
        rn.run_experiment(exp, "s01", db, metadata={"session": "1"}, **run)
    assert not db.exists()
    Quick.stop = 4
    meta = {"session": "1", "experimenter": "AB", "handedness": "left", "age_years": "30"}
    with pytest.raises(rn.TrialAbortedError):
        rn.run_experiment(exp, "s01", db, metadata=meta, **run)
    Quick.stop = None
    rn.run_experiment(exp, "s02", db, metadata={"handedness": "right"}, **run)
    # The resume keeps what it is not given again.
    _, left = rn.run_experiment(
        exp, "s01", db, resume=True, metadata={"session": "2"}, observer="quick", options=opts
    )
    assert left == 0
    out = tmp_path / "t.csv"
    ex.write_csv(db, out, status=None)
    with open(out, newline="") as f:
        reader = csv.DictReader(f)
        names, rows = list(reader.fieldnames or []), list(reader)
    assert names == [*ex.names(), "meta_handedness", "meta_age_years"]
    mine = [r for r in rows if r["subject"] == "s01"]
    first = [r for r in mine if int(r["trial"]) < 4 or r["status"] == "incomplete"]
    later = [r for r in mine if r not in first]
    assert len(first) == 5 and len(later) == 8
    assert {(r["session"], r["experimenter"], r["meta_handedness"]) for r in first} == {
        ("1", "AB", "left")
    }
    assert {(r["session"], r["meta_handedness"], r["meta_age_years"]) for r in later} == {
        ("2", "left", "30")
    }
    assert {r["subject_index"] for r in mine} == {"3"}
    other = [r for r in rows if r["subject"] == "s02"]
    assert len(other) == 12 and {(r["meta_handedness"], r["session"]) for r in other} == {
        ("right", "")
    }
    with TrialStore.for_experiment(db, exp) as store:
        assert [s["metadata"]["session"] for s in store.sessions("s01")] == ["1", "2"]
    # Parquet and MAT carry the same metadata, row for row.
    from tests.test_export_formats import _read_back

    for fmt in ("parquet", "mat"):
        ex.write_trials(db, tmp_path / f"t.{fmt}", fmt, status=None)
        back = _read_back(tmp_path / f"t.{fmt}", fmt)
        assert list(back) == names, fmt
        for name in ("subject", "session", "experimenter", "meta_handedness", "meta_age_years"):
            got = ["" if v is None else str(v) for v in back[name]]
            assert got == [r[name] for r in rows], (fmt, name)


def test_a_store_without_sessions_exports_empty_metadata(tmp_path):
    exp = load_experiment(STIFFNESS)
    db = tmp_path / "t.db"
    plan = make_plan(exp, 1)
    with TrialStore.for_experiment(db, exp) as store:
        store.ensure_plan("s01", plan, 1)
        store.record(
            "s01", plan[0], answer_second_more=True, response_time_s=0.2, profile_hash="p", seed=1
        )
    names, rows = ex.trial_table(db)
    assert names == ex.names() and len(rows) == 1
    assert all(rows[0][k] is None for k in ("subject_index", "session", "experimenter", "notes"))
