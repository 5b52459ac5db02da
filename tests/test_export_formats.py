"""The trial export's analysis columns (intervals, forces, adaptive flags, practice), its
formats (CSV, Parquet, MAT: the same columns and values in each) and the samples export,
each value checked against a computation of its own on a small synthetic store."""

from __future__ import annotations

import csv
import datetime as dt
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from hapticd.cli import main
from hapticd.experiment import export as ex
from hapticd.experiment import load_experiment, make_plan
from hapticd.experiment.adaptive import session, tracks_for
from hapticd.experiment.runner import reduced
from hapticd.experiment.store import TrialStore
from hapticd.recording import loop_fields, read, write
from hapticd.recording.export import csv_columns
from tests.conftest import ROOT

EXPERIMENTS = ROOT / "configs" / "experiments"
FINGERS = ["thumb", "index"]
RATE_HZ = 1000.0
T0_UTC = "2026-12-02T05:00:00Z"
T0_LSL = 12345.5


def _recording(path: Path, n: int, first_tick: int, seed: int, anchored: bool) -> None:
    """A loop recording of ``n`` ticks from ``first_tick``: random forces, the thumb in
    contact at random, the index never; the clocks' anchors in the header or not (a file
    made before they existed)."""
    fields = loop_fields(2, 1)
    rng = np.random.default_rng(seed)
    arrays = {f.name: np.zeros((n, *f.shape), dtype=f.dtype) for f in fields}
    ticks = first_tick + np.arange(n)
    arrays["tick"] = ticks.astype("<u8")
    arrays["t"] = ticks / RATE_HZ
    arrays["t_wall"] = ticks / RATE_HZ + rng.uniform(0, 2e-4, n)
    arrays["device_force"] = rng.normal(0, 2.0, (n, 2, 3))
    arrays["in_contact"][:, 0] = rng.integers(0, 2, n)
    arrays["allocator"] = rng.integers(0, 2, n).astype("u1")
    meta = {"rate_hz": RATE_HZ, "allocators": ["pinv", "if"]}
    if anchored:
        meta |= {"t0_utc": T0_UTC, "t0_lsl": T0_LSL}
    write(path, arrays, fields, FINGERS, meta)


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    """Subject s01's first 4 trials of the stiffness design: trial 1 stored incomplete
    first; each with two recordings (the first interval's anchored, the second's an old
    file without anchors) but trial 3, whose second recording is missing."""
    root = tmp_path_factory.mktemp("store")
    exp = load_experiment(EXPERIMENTS / "stiffness-jnd.yaml")
    seed = exp.subject_seed("s01")
    plan = make_plan(exp, seed)
    db = root / "t.db"
    with TrialStore.for_experiment(db, exp) as st:
        st.ensure_plan("s01", plan, seed)
        for t in plan[:4]:
            recs = []
            for k in (1, 2):
                p = root / f"s01-{t.index:04d}-{k}.hrec"
                if not (t.index == 3 and k == 2):
                    _recording(
                        p, 50 + 10 * t.index, 1000 * t.index + 500 * k, t.index * 2 + k, k == 1
                    )
                recs.append(str(p))
            kw = dict(response_time_s=0.5, profile_hash="p", seed=seed, recording=json.dumps(recs))
            if t.index == 1:
                st.record("s01", t, answer_second_more=None, status="incomplete", **kw)
            st.record("s01", t, answer_second_more=t.index % 2 == 0, source="key", **kw)
    return db


def _expected_interval(path: Path) -> dict[str, object]:
    """The interval's columns computed here, tick by tick, from the file's arrays."""
    rec = read(path)
    n = rec.ticks
    out: dict[str, object] = {
        "onset_s_K": float(rec["t"][0]),
        "duration_s_K": n / RATE_HZ,
        "onset_unix_s_K": None,
        "onset_lsl_s_K": None,
    }
    if "t0_utc" in rec.meta:
        t0 = dt.datetime(2026, 12, 2, 5, 0, 0, tzinfo=dt.UTC).timestamp()
        out["onset_unix_s_K"] = t0 + float(rec["t_wall"][0])
        out["onset_lsl_s_K"] = T0_LSL + float(rec["t_wall"][0])
    for j, finger in enumerate(FINGERS):
        mags = [math.sqrt(sum(float(c) ** 2 for c in rec["device_force"][i, j])) for i in range(n)]
        touching = [i for i in range(n) if rec["in_contact"][i, j]]
        out[f"peak_force_n_{finger}_K"] = max(mags)
        out[f"mean_force_n_{finger}_K"] = (
            sum(mags[i] for i in touching) / len(touching) if touching else None
        )
        out[f"contact_s_{finger}_K"] = len(touching) / RATE_HZ
    return out


def _same(a: object, b: object) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, float) or isinstance(b, float):
        return float(a) == pytest.approx(float(b), rel=1e-12, abs=1e-12)
    return a == b


def test_each_interval_and_finger_column_matches_its_recording(store):
    with pytest.warns(ex.ExportWarning, match=r"1 recording\(s\).*s01-0003-2"):
        rows, fingers = ex.rows_and_fingers(store)
    assert fingers == FINGERS
    assert [r["trial"] for r in rows] == [0, 1, 2, 3]
    for r in rows:
        for k in (1, 2):
            path = Path(r[f"recording_{k}"])
            if not path.exists():
                assert all(r[ex._name(n, k)] is None for n, _ in ex.INTERVAL_COLUMNS)
                continue
            for name, want in _expected_interval(path).items():
                got = r[name.replace("_K", f"_{k}")]
                assert _same(got, want), (r["trial"], k, name, got, want)
    # The second interval's file has no anchors: onsets on the loop's clock only.
    assert rows[0]["onset_unix_s_2"] is None and rows[0]["onset_s_2"] is not None
    assert rows[0]["mean_force_n_index_1"] is None  # the index never touched
    assert all(r["practice"] == 0 for r in rows)


def test_a_recording_moved_off_the_rig_is_found_by_name_in_recordings_dir(store, tmp_path):
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "s01-0000-1.hrec").write_bytes((store.parent / "s01-0000-1.hrec").read_bytes())
    db = tmp_path / "t.db"
    db.write_bytes(store.read_bytes())
    con = __import__("sqlite3").connect(db)
    with con:
        con.execute("UPDATE trials SET recording = ? WHERE plan_index = 0",
                    (json.dumps(["/nowhere/s01-0000-1.hrec", None]),))  # fmt: skip
    con.close()
    with pytest.warns(ex.ExportWarning):
        (lost,) = [r for r in ex.trial_rows(db) if r["trial"] == 0]
    assert lost["onset_s_1"] is None
    with pytest.warns(ex.ExportWarning):
        (found,) = [r for r in ex.trial_rows(db, recordings_dir=moved) if r["trial"] == 0]
    assert found["onset_s_1"] == pytest.approx(
        _expected_interval(moved / "s01-0000-1.hrec")["onset_s_K"]
    )


def _read_back(path: Path, fmt: str) -> dict[str, list]:
    """The file read with the format's own reader: csv, pyarrow, scipy.io.loadmat."""
    if fmt == "csv":
        with open(path, newline="") as f:
            body = list(csv.reader(f))
        return {h: [r[i] or None for r in body[1:]] for i, h in enumerate(body[0])}
    if fmt == "parquet":
        import pyarrow.parquet as pq

        return pq.read_table(path).to_pydict()
    from scipy.io import loadmat

    m = loadmat(path, simplify_cells=True)
    names = list(m["columns"])
    struct = m["trials"] if "trials" in m else m["samples"]
    out = {}
    for name in names:
        field = name.replace(".", "_")
        vals = []
        for v in np.atleast_1d(struct[field]):
            if isinstance(v, np.ndarray) and v.size == 0:
                v = None  # an empty char: missing text
            elif isinstance(v, float | np.floating) and np.isnan(v):
                v = None
            vals.append(v.item() if isinstance(v, np.generic) else v)
        out[name] = vals
    return out


def _equal_cell(got: object, want: object, kind: str) -> bool:
    if want is None:
        return got is None
    if kind == "text":
        return str(got) == str(want)
    return float(got) == pytest.approx(float(want), rel=1e-15, abs=0)


@pytest.mark.parametrize("fmt", ["csv", "parquet", "mat"])
def test_every_format_holds_the_same_columns_and_values(store, tmp_path, fmt):
    with pytest.warns(ex.ExportWarning):
        rows, fingers = ex.rows_and_fingers(store, status=None)
    out = tmp_path / f"t.{fmt}"
    with pytest.warns(ex.ExportWarning):
        assert ex.write_trials(store, out, fmt, status=None) == 5
    back = _read_back(out, fmt)
    assert list(back) == ex.names(FINGERS)
    kinds = ex.kinds(fingers)
    for name in back:
        assert len(back[name]) == len(rows)
        for got, r in zip(back[name], rows, strict=True):
            assert _equal_cell(got, r[name], kinds.get(name, "text")), (fmt, name, got, r[name])


def test_a_bad_format_is_refused_naming_it_and_the_choices(store, tmp_path, capsys):
    out = tmp_path / "t.xlsx"
    assert main(["experiment", "export", str(store), "--format", "xlsx", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "'xlsx'" in err and "csv, parquet, mat" in err
    assert not out.exists()


def test_parquet_without_pyarrow_says_how_to_install_it(store, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    out = tmp_path / "t.parquet"
    argv = ["experiment", "export", str(store), "--format", "parquet", "--out", str(out)]
    assert main([*argv, "--no-recordings"]) == 1
    assert "pip install 'hapticd[export]'" in capsys.readouterr().err


@pytest.mark.parametrize("fmt", ["csv", "parquet", "mat"])
def test_each_intervals_samples_are_exported_with_the_recordings_columns(store, tmp_path, fmt):
    with pytest.warns(ex.ExportWarning):
        paths = ex.write_samples(store, tmp_path / "samples", fmt)
    assert len(paths) == 7  # 4 trials x 2 intervals, one missing
    path = next(p for p in paths if p.stem == "s01-0002-1")
    rec = read(store.parent / "s01-0002-1.hrec")
    back = _read_back(path, fmt)
    assert list(back) == [*ex.SAMPLE_KEYS, *csv_columns(rec)]
    assert [int(v) for v in back["trial"]] == [2] * rec.ticks
    assert [int(v) for v in back["interval"]] == [1] * rec.ticks
    assert {str(v) for v in back["subject"]} == {"s01"}
    for col, want in (
        ("device_force.index.y", rec["device_force"][:, 1, 1]),
        ("t_wall", rec["t_wall"]),
        ("in_contact.thumb", rec["in_contact"][:, 0]),
        ("tick", rec["tick"]),
    ):
        assert [float(v) for v in back[col]] == want.astype(float).tolist(), col
    names = rec.meta["allocators"]
    assert [str(v) for v in back["allocator"]] == [names[int(k)] for k in rec["allocator"]]


def test_staircase_rows_carry_their_tracks_side_correctness_and_reversals(tmp_path):
    exp = reduced(load_experiment(EXPERIMENTS / "stiffness-staircase.yaml"), standards=[60.0])
    tracks = tracks_for(exp)
    # The same answers on every track, by its trial's position: right, right (down), wrong
    # (up: a reversal), right, right (down: a reversal), wrong (up: a reversal), wrong.
    right = [True, True, False, True, True, False, False]
    reversal = [0, 0, 1, 0, 1, 1, 0]

    def answer(trial):
        return right[trial.position % 7] == (tracks[trial.block].sign > 0)

    seed = 7
    trials = [(t, m) for t, m in session(exp, seed, answer) if t.position < 7]
    db = tmp_path / "s.db"
    with TrialStore.for_experiment(db, exp) as st:
        for index, (t, more) in enumerate(trials):
            t = t.__class__(**{**t.as_dict(), "index": index})
            st.append_plan("s01", t, seed)
            st.record("s01", t, answer_second_more=more != t.comparison_first, response_time_s=None,
                      profile_hash="p", seed=seed, source="model")  # fmt: skip
    rows = ex.trial_rows(db, recordings=False)
    assert len(rows) == len(trials) and len({r["block"] for r in rows}) == len(tracks)
    for r, (t, _) in zip(rows, trials, strict=True):
        side = "above" if tracks[t.block].sign > 0 else "below"
        assert (r["side"], r["correct"], r["reversal"]) == (
            side, int(right[t.position]), reversal[t.position]
        ), t  # fmt: skip


def test_a_decimated_recording_keeps_every_nth_tick_and_loses_what_docs_say(store, tmp_path):
    """recording.rate_hz: the writer keeps ticks 0, N, 2N, ... of the ring (a small ring
    that wraps); the export's times count in steps of N ticks, within N ticks of the full
    recording's, and a peak can only be lower."""
    from hapticd.recording import Recorder

    full = read(store.parent / "s01-0002-1.hrec")
    every = 4
    meta = {**full.meta, "record_every": every}
    rec = Recorder(tmp_path / "d.hrec", full.fields, full.fingers, meta, capacity=16,
                   block_when_full=True, record_every=every)  # fmt: skip
    rows = full._data  # the records as the loop hands them, one per tick
    for i in range(full.ticks):
        rec.append(rows[i : i + 1].view(np.uint8).reshape(-1))
    assert rec.close()["written"] == full.ticks
    kept = read(tmp_path / "d.hrec")
    assert kept.ticks == math.ceil(full.ticks / every)
    np.testing.assert_array_equal(kept["tick"], full["tick"][::every])
    np.testing.assert_array_equal(kept["device_force"], full["device_force"][::every])
    a, b = ex.interval_stats(full), ex.interval_stats(kept)
    period = every / RATE_HZ
    assert a["onset_s_K"] == b["onset_s_K"]
    assert abs(a["duration_s_K"] - b["duration_s_K"]) < period
    assert b["duration_s_K"] == pytest.approx(kept.ticks * period)
    assert b["peak_force_n_thumb_K"] <= a["peak_force_n_thumb_K"]
    assert b["contact_s_thumb_K"] == pytest.approx(kept["in_contact"][:, 0].sum() * period)


def test_a_recording_rate_that_does_not_divide_the_loops_is_refused(tmp_path):
    from hapticd.profile import ProfileError, load_profile

    src = (ROOT / "configs" / "grasp-stiffness.yaml").read_text()
    for rate, ok in ((250.0, True), (300.0, False), (2000.0, False)):
        p = tmp_path / "grasp-stiffness.yaml"
        p.write_text(src + f"\nrecording:\n  rate_hz: {rate}\n")
        if ok:
            assert load_profile(p).recording.record_every(1000.0) == 4
        else:
            with pytest.raises(ProfileError, match=r"recording.*rate_hz.*whole number"):
                load_profile(p)


def test_an_experiment_files_export_format_is_checked_and_is_the_default(tmp_path, capsys):
    src = (EXPERIMENTS / "stiffness-jnd.yaml").read_text()
    profile = (ROOT / "configs" / "grasp-stiffness.yaml").as_posix()
    src = src.replace("profile: ../grasp-stiffness.yaml", f"profile: {profile}")
    bad = tmp_path / "bad.yaml"
    bad.write_text(src + "export:\n  format: xlsx\n")
    assert main(["experiment", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "export.format" in err and f"line {src.count(chr(10)) + 2}" in err
    good = tmp_path / "good.yaml"
    good.write_text(src + "export:\n  format: mat\n")
    exp = load_experiment(good)
    db = tmp_path / "t.db"
    with TrialStore.for_experiment(db, exp) as st:
        seed = exp.subject_seed("s01")
        plan = make_plan(exp, seed)
        st.ensure_plan("s01", plan, seed)
        st.record("s01", plan[0], answer_second_more=True, response_time_s=None,
                  profile_hash="p", seed=seed)  # fmt: skip
    out = tmp_path / "t.out"
    assert main(["experiment", "export", str(db), "--out", str(out), "--no-recordings"]) == 0
    assert _read_back(out, "mat")["trial"] == [0]


def test_quest_plus_and_constant_stimuli_rows_carry_side_and_correctness_without_reversals():
    """Outside a staircase (QUEST+, constant stimuli) a trial's side is its comparison's,
    its answer correct when the larger stimulus was judged more; no reversal is claimed,
    and a comparison equal to the standard (or an unanswered trial) has no correct answer."""
    trials = [  # id, comparison (standard 60), judged the comparison more
        (1, 72.0, True), (2, 72.0, False), (3, 48.0, False), (4, 48.0, True),
        (5, 60.0, True), (6, 66.0, None),
    ]  # fmt: skip
    rows = [
        {"id": i, "subject": "s01", "plan_index": i, "block": 0, "standard": 60.0,
         "comparison": c, "status": "complete" if more is not None else "incomplete",
         "comparison_more": more, "condition": "pinv"}
        for i, c, more in trials
    ]  # fmt: skip
    for procedure in ("quest_plus", "constant"):
        flags = ex.answer_flags(rows, {"procedure": procedure})
        got = [(flags[i]["side"], flags[i]["correct"], flags[i]["reversal"]) for i, *_ in trials]
        assert got == [
            ("above", 1, None), ("above", 0, None), ("below", 1, None), ("below", 0, None),
            (None, None, None), ("above", None, None),
        ], procedure  # fmt: skip
