"""Malformed recordings, generated: every header field of every kind replaced by hostile
values (dtypes of every kind, order and size; negative, zero, huge and wrong-typed shapes;
repeated and wrong-typed names), top-level keys mutated, JSON nested up to 100,000 deep,
header lengths that lie, every byte flipped and the file cut at every byte. Reading each
must give a Recording or one RecordingError naming the file (never another exception, never
a hang), and whatever reads must export to CSV; the CLI says so in one line with exit 2.

Run with ``-s`` to see each category's tally (tried / clear error / accepted / crash).
"""

from __future__ import annotations

import copy
import itertools
import json
import os
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hapticd.cli import main
from hapticd.recording import MAGIC, Recording, RecordingError, loop_fields, read, write
from hapticd.recording.export import csv_columns, export_csv
from hapticd.recording.format import DTYPES

TICKS = 3


def _valid_arrays(fields) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    return {
        f.name: rng.integers(0, 2, (TICKS, *f.shape)).astype(f.dtype)
        if f.dtype in ("u1", "<u4", "<u8")
        else rng.normal(size=(TICKS, *f.shape))
        for f in fields
    }


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> tuple[dict, bytes]:
    """A loop recording of 2 fingers, 2 actuators, 3 ticks: (its header, its records)."""
    path = tmp_path_factory.mktemp("valid") / "v.hrec"
    fields = loop_fields(2, 2)
    write(path, _valid_arrays(fields), fields, ["thumb", "index"], {"rate_hz": 1000.0})
    blob = path.read_bytes()
    hlen = int.from_bytes(blob[8:12], "little")
    return json.loads(blob[12 : 12 + hlen]), blob[12 + hlen :]


def _file(header: object, body: bytes = b"", *, raw: bytes | None = None) -> bytes:
    h = raw if raw is not None else json.dumps(header, allow_nan=True).encode()
    return MAGIC + len(h).to_bytes(4, "little") + h + body


def _dtypes() -> list[object]:
    """Every kind, byte order and size numpy might parse, and values of the wrong type."""
    out: list[object] = [
        f"{o}{k}{n}"
        for o, k, n in itertools.product("<>|=", "biufcmMOSUV?", (0, 1, 2, 4, 8, 16, 32))
    ]
    out += ["O", "V0", "V", "S", "U", "<f16", "f8", "float64", "d", "i", "?", "M8[s]", ""]
    out += ["[('a', '<f8')]", "(<f8, 3)", None, 1, 8.0, True, [], ["<f8"], {"a": "<f8"}]
    return out


def _shapes() -> list[object]:
    dims = [-(2**63), -1, 0, 1, 3, 2**16, 2**31, 2**63, 10**30, 1.5, "3", True, None, [3]]
    out: list[object] = [[d] for d in dims] + [
        [a, b] for a, b in itertools.product(dims[:9], repeat=2)
    ]
    out += [[1] * n for n in (5, 32, 100)] + [[0, 0, 0], "3", 3, None, {}, [[]]]
    return out


def _names(fields: list[dict]) -> list[object]:
    return ["", "x" * 300, "x" * 100_000, fields[0]["name"], fields[-1]["name"], 1, None, [], {}]


def header_mutations(header: dict) -> Iterator[tuple[str, dict]]:
    """A scalar, a per-finger vector field and a (F,) field with dtype and shape replaced by
    each hostile value (the same check runs for every field); every field's name and unit
    replaced, and each key removed."""
    fields = header["fields"]
    by_kind = {}
    for i, f in enumerate(fields):
        by_kind.setdefault((len(f["shape"]), f["dtype"]), i)
    values = {"dtype": _dtypes(), "shape": _shapes()}
    for i, key in itertools.product(sorted(by_kind.values()), values):
        for v in values[key]:
            h = copy.deepcopy(header)
            h["fields"][i][key] = v
            yield f"fields[{i}].{key}={v!r:.40}", h
    others = {"name": _names(fields), "unit": [None, 1, [], {}, "x" * 10_000]}
    for i, key in itertools.product(range(len(fields)), ("name", "unit", "dtype", "shape")):
        for v in others.get(key, []):
            h = copy.deepcopy(header)
            h["fields"][i][key] = v
            yield f"fields[{i}].{key}={v!r:.40}", h
        h = copy.deepcopy(header)
        del h["fields"][i][key]
        yield f"fields[{i}] without {key}", h
    for i in range(len(fields)):
        for bad in (None, 1, "t", [], [fields[i]]):
            h = copy.deepcopy(header)
            h["fields"][i] = bad
            yield f"fields[{i}]={bad!r:.40}", h


def top_mutations(header: dict) -> Iterator[tuple[str, dict | list | object]]:
    """Top-level keys removed or replaced by values of every type."""
    hostile = [None, True, 0, 1, 2, -1, 1.0, "1", "", [], {}, [1], {"a": 1}, 2**64]
    for key in ("version", "fields", "fingers", "meta"):
        h = copy.deepcopy(header)
        del h[key]
        yield f"without {key}", h
        for v in hostile:
            h = copy.deepcopy(header)
            h[key] = v
            yield f"{key}={v!r}", h
    for v in hostile:
        yield f"header={v!r}", v
    h = copy.deepcopy(header)
    h["fields"] = h["fields"] * 2  # every name repeated
    yield "fields twice", h
    h = copy.deepcopy(header)
    h["fields"] = [h["fields"][0]] * 2000
    yield "2000 fields", h


def deep_headers(header: dict) -> Iterator[tuple[str, bytes]]:
    """JSON nested 1 to 100,000 deep in meta, in a field and as the whole header."""
    for depth in (1, 8, 31, 32, 33, 100, 1000, 10_000, 100_000):
        nested = b"[" * depth + b"]" * depth
        base = json.dumps(header).encode()
        yield (
            f"meta {depth} deep",
            base.replace(b'"meta": {', b'"meta": {"deep": ' + nested + b", ", 1),
        )
        yield f"field unit {depth} deep", base.replace(b'"unit": "s"', b'"unit": ' + nested, 1)
        yield f"header {depth} deep", nested


def _judge(path: Path, blob: bytes, tally: Counter, problems: list, what: str) -> None:
    path.write_bytes(blob)
    try:
        rec = read(path)
    except RecordingError as exc:
        if str(path) in str(exc):
            tally["clear error"] += 1
        else:
            tally["crash"] += 1
            problems.append((what, f"message does not name the file: {exc}"))
        return
    except Exception as exc:  # any other exception is a traceback for the user
        tally["crash"] += 1
        problems.append((what, repr(exc)[:300]))
        return
    try:
        assert isinstance(rec, Recording)
        export_csv(rec, path.with_suffix(".csv"))
        assert len(csv_columns(rec)) >= len(rec.fields)
        for f in rec.fields:
            assert rec[f.name].shape == (rec.ticks, *f.shape)
            assert f.dtype in DTYPES
    except Exception as exc:
        tally["crash"] += 1
        problems.append((what, f"read, but then: {exc!r}"[:300]))
        return
    tally["accepted"] += 1


def _run(name: str, cases: Iterator[tuple[str, bytes]], tmp_path: Path) -> Counter:
    tally: Counter = Counter()
    problems: list = []
    path = tmp_path / "hostile.hrec"
    for what, blob in cases:
        _judge(path, blob, tally, problems, what)
    tried = tally["accepted"] + tally["clear error"] + tally["crash"]
    print(
        f"\nhostile recordings, {name}: {tried} tried, {tally['clear error']} clear error, "
        f"{tally['accepted']} accepted, {tally['crash']} crash, 0 hang"
    )
    assert tally["crash"] == 0, problems[:8]
    return tally


def _header_cases(valid) -> Iterator[tuple[str, bytes]]:
    header, body = valid
    for what, h in header_mutations(header):
        yield what, _file(h, body)


def _top_cases(valid) -> Iterator[tuple[str, bytes]]:
    header, body = valid
    for what, h in top_mutations(header):
        yield what, _file(h, body)


def _deep_cases(valid) -> Iterator[tuple[str, bytes]]:
    header, body = valid
    for what, raw in deep_headers(header):
        yield what, _file(None, body, raw=raw)


def _length_cases(valid) -> Iterator[tuple[str, bytes]]:
    """The header length field lying in every direction."""
    header, body = valid
    h = json.dumps(header).encode()
    for n in (
        0,
        1,
        2,
        len(h) - 1,
        len(h) + 1,
        len(h) + len(body),
        1 << 20,
        (1 << 20) + 1,
        2**32 - 1,
    ):
        yield f"length {n}", MAGIC + n.to_bytes(4, "little") + h + body


def _truncations(valid) -> Iterator[tuple[str, bytes]]:
    """The file cut at every byte: in the magic, the length, the header, every record."""
    header, body = valid
    blob = _file(header, body)
    for cut in range(len(blob)):
        yield f"cut at {cut}", blob[:cut]


def _flips(valid) -> Iterator[tuple[str, bytes]]:
    """Every byte of the magic, length and header flipped."""
    header, body = valid
    blob = _file(header, body)
    end = len(blob) - len(body)
    for i in range(end):
        yield f"byte {i} flipped", blob[:i] + bytes([blob[i] ^ 0xFF]) + blob[i + 1 :]


CATEGORIES: dict[str, Callable] = {
    "field mutations (dtype, shape, name, unit)": _header_cases,
    "top-level mutations": _top_cases,
    "deep JSON": _deep_cases,
    "lying header lengths": _length_cases,
    "truncations at every byte": _truncations,
    "flipped bytes": _flips,
}


@pytest.mark.parametrize("category", list(CATEGORIES))
def test_every_malformed_recording_reads_or_gives_one_clear_error(valid, category, tmp_path):
    tally = _run(category, CATEGORIES[category](valid), tmp_path)
    assert tally["clear error"] > 0


def test_truncated_files_keep_every_whole_tick(valid, tmp_path):
    """A file cut inside its records keeps every whole record before the cut, exactly."""
    header, body = valid
    blob = _file(header, body)
    full = len(blob) - len(body)
    path = tmp_path / "t.hrec"
    path.write_bytes(blob)
    whole = read(path)
    size = len(body) // TICKS
    # Every byte of the first record, and either side of every record boundary.
    cuts = set(range(full, full + size + 1))
    cuts |= {full + k * size + d for k in range(TICKS + 1) for d in (-1, 0, 1)}
    for cut in sorted(c for c in cuts if full <= c <= len(blob)):
        path.write_bytes(blob[:cut])
        rec = read(path)
        assert rec.ticks == (cut - full) // size and rec.torn_bytes == (cut - full) % size
        for f in rec.fields:
            np.testing.assert_array_equal(rec[f.name], whole[f.name][: rec.ticks])


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=4), children, max_size=4)
    ),
    max_leaves=20,
)


@given(
    field=st.fixed_dictionaries(
        {},
        optional={
            "name": _json,
            "dtype": st.sampled_from(_dtypes()) | _json,
            "shape": _json,
            "unit": _json,
        },
    ),
    top=st.dictionaries(
        st.sampled_from(["version", "fields", "fingers", "meta", "x"]), _json, max_size=4
    ),
)
def test_arbitrary_json_headers_read_or_give_one_clear_error(valid, tmp_path_factory, field, top):
    header, body = valid
    h = copy.deepcopy(header)
    h["fields"][1] = field
    h.update(top)
    path = tmp_path_factory.getbasetemp() / "hypothesis.hrec"
    tally: Counter = Counter()
    problems: list = []
    _judge(path, _file(h, body), tally, problems, "generated")
    assert tally["crash"] == 0, problems


def test_a_fifo_or_a_device_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "f.hrec"
    os.mkfifo(fifo)
    errors: list[str] = []

    def attempt(p):
        try:
            read(p)
        except RecordingError as exc:
            errors.append(str(exc))

    for p in (fifo, Path("/dev/zero"), tmp_path):
        t = threading.Thread(target=attempt, args=(p,), name="read-attempt")
        t.start()
        t.join(timeout=5.0)
        if t.is_alive():
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))  # unblock, then fail
            t.join(timeout=5.0)
            pytest.fail(f"reading {p} blocked")
    assert len(errors) == 3 and all("cannot read" in e for e in errors)


@pytest.mark.parametrize(
    "mutate",
    [
        lambda h: h["fields"][0].update(dtype="O"),
        lambda h: h["fields"][1].update(shape=[-1, 3]),
        lambda h: [f.update(shape=[0]) for f in h["fields"]],
        lambda h: h["fields"][1].update(name=h["fields"][0]["name"]),
        lambda h: h["fields"][0].update(dtype="<f16"),
    ],
    ids=["dtype O", "negative shape", "all-zero shapes", "repeated name", "f16"],
)
def test_the_cli_reports_a_malformed_recording_in_one_line(
    valid, tmp_path, capsys, mutate, grasp_data, write_profile
):
    header, body = valid
    h = copy.deepcopy(header)
    mutate(h)
    path = tmp_path / "bad.hrec"
    path.write_bytes(_file(h, body))
    assert main(["export", str(path), "--csv", str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"hapticd: {path}: ") and err.count("\n") == 1 and "Traceback" not in err
    # The same file as a replay trajectory: check and run name the profile key and the file.
    for finger in grasp_data["fingers"]:
        finger["device"]["trajectory"] = str(path)
    profile = write_profile(grasp_data)
    for argv in (["check", str(profile)], ["run", str(profile), "--unpaced", "--no-socket"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "trajectory" in err and str(path) in err and "Traceback" not in err


def test_a_recording_with_no_ticks_exports(valid, tmp_path, capsys):
    """A daemon killed right after record start leaves a header and no record."""
    header, _ = valid
    path = tmp_path / "empty.hrec"
    path.write_bytes(_file(header))
    assert main(["export", str(path), "--csv", str(tmp_path / "e.csv")]) == 0
    assert "0 ticks" in capsys.readouterr().out
    text = (tmp_path / "e.csv").read_text().splitlines()
    assert len(text) == 1 and text[0].startswith("t,t_wall,")
