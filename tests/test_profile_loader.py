"""The profile loader against hostile files: aliases, duplicate keys, bad bytes, deep
nesting, wrong shapes and non-finite numbers all end in a ProfileError that names the
file, the key, the line and what was expected."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from hapticd.profile import MAX_DEPTH, MAX_NODES, ProfileError, load_profile
from tests.conftest import GRASP_PROFILE, ROOT

GRASP = GRASP_PROFILE.read_text()


def _line_of(text: str, needle: str, start: int = 0) -> int:
    """1-based line of the first ``needle`` in ``text`` at or after character ``start``."""
    return text.count("\n", 0, text.index(needle, start)) + 1


def _write(tmp_path: Path, text: str | bytes, name: str = "p.yaml") -> Path:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def _error(path: Path) -> str:
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    msg = str(exc.value)
    assert msg.startswith(str(path)), msg
    return msg


def _bomb(levels: int = 9) -> str:
    """Billion laughs: 9 anchors, each a list of nine aliases of the one before."""
    out = "lol0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"
    for i in range(1, levels):
        out += f"lol{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]\n"
    return out


def _replace_fingers(text: str, new: str) -> str:
    start, end = text.index("fingers:"), text.index("rendering:")
    return text[:start] + new + "\n" + text[end:]


def test_an_alias_bomb_under_fingers_is_refused_at_once_by_check(tmp_path):
    """It used to take minutes and gigabytes (the error's repr of the expanded input)."""
    text = _bomb() + _replace_fingers(GRASP, "fingers: *l8")
    path = _write(tmp_path, text)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "hapticd", "check", str(path)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=30,
        )
    except subprocess.TimeoutExpired:
        pytest.fail("hapticd check did not finish within 30 s on an alias bomb")
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert f"line {_line_of(text, '&l0')}" in proc.stderr
    assert "anchors and aliases (&name, *name) are not allowed" in proc.stderr


def test_a_single_alias_is_refused_with_its_line(tmp_path):
    text = GRASP.replace(
        'device: {backend: replay, trajectory: "builtin:grasp-stiffness", max_force_n: 12.0}',
        'device: &dev {backend: replay, trajectory: "builtin:grasp-stiffness", max_force_n: 12.0}',
        1,
    ).replace(
        'device: {backend: replay, trajectory: "builtin:grasp-stiffness", max_force_n: 12.0}',
        "device: *dev",
        1,
    )
    assert "*dev" in text
    msg = _error(_write(tmp_path, text))
    assert f"line {_line_of(text, '&dev')}" in msg and "anchor" in msg


def test_duplicate_keys_are_refused_with_both_lines(tmp_path):
    """A second safety block silently raised the force limit from 8 N to 12 N."""
    text = GRASP + "\nsafety:\n  max_force_n: 12.0\n"
    msg = _error(_write(tmp_path, text))
    first = _line_of(text, "safety:")
    second = _line_of(text, "safety:", text.index("safety:") + 1)
    assert "duplicate key 'safety'" in msg
    assert f"line {second}" in msg and f"line {first}" in msg


def test_a_duplicate_key_inside_a_flow_mapping_is_refused(tmp_path):
    text = GRASP.replace("max_force_n: 12.0}", "max_force_n: 12.0, max_force_n: 40.0}", 1)
    msg = _error(_write(tmp_path, text))
    assert "duplicate key 'max_force_n'" in msg
    assert f"line {_line_of(text, 'max_force_n: 40.0')}" in msg


def test_errors_carry_the_line_of_their_key(tmp_path):
    text = GRASP.replace("stiffness_n_per_m: 60.0", "stiffness_n_per_m: 1.0e+9")
    msg = _error(_write(tmp_path, text))
    line = _line_of(text, "stiffness_n_per_m: 1.0e+9")
    assert re.search(rf"scene\.object\.stiffness_n_per_m: .*100000.* \(line {line}\)", msg), msg


def test_a_missing_key_points_at_the_mapping_that_lacks_it(tmp_path):
    text = GRASP.replace("    stiffness_n_per_m: 60.0\n", "")
    msg = _error(_write(tmp_path, text))
    assert re.search(
        rf"scene\.object\.stiffness_n_per_m: required key is missing "
        rf"\(in the mapping at line {_line_of(text, '  object:')}\)",
        msg,
    ), msg


@pytest.mark.parametrize(
    ("old", "new", "where", "what"),
    [
        # Item types the old formatter assumed were mappings.
        ("size_m: [0.05, 0.05, 0.05]", "size_m: [a, b, c]", "scene.object.size_m[0]", "number"),
        (
            "- [0.8660254, 0.0, 0.5]",
            "- [1, 0]",
            "fingers[0:thumb].actuated_directions[0]",
            "too few items",
        ),
        (
            "actuated_directions:\n      - [0.8660254, 0.0, 0.5]",
            "actuated_directions: [0.866, 0, 0.5]",
            "fingers[0:thumb].actuated_directions[0]",
            "should be a list",
        ),
        # Strict types: a bool is not a number, a string is not a number.
        ("stiffness_n_per_m: 60.0", "stiffness_n_per_m: true", "stiffness_n_per_m", "number"),
        ("stiffness_n_per_m: 60.0", "stiffness_n_per_m: '60'", "stiffness_n_per_m", "number"),
        # Non-finite and huge numbers: reported as such, never as "should be <= 50 (got nan)".
        ("max_force_n: 8.0", "max_force_n: .nan", "safety.max_force_n", "finite number"),
        ("position_m: [0.0, 0.0, 0.0]", "position_m: [1.0e+308, 0, 0]", "position_m[0]", "1"),
        ("position_m: [0.0, 0.0, 0.0]", "position_m: [.inf, 0, 0]", "position_m[0]", "finite"),
        (
            "position_m: [0.0, 0.0, 0.0]",
            "position_m: [0, 0, 0]\n    orientation_rpy_rad: [.nan, 0, 0]",
            "orientation_rpy_rad[0]",
            "finite",
        ),
        (
            "  object:",
            "  gravity_m_s2: [0, 0, .nan]\n  object:",
            "scene.gravity_m_s2[2]",
            "finite",
        ),
        ("max_force_n: 12.0}", "max_force_n: .inf}", "device.max_force_n", "finite"),
        ("max_force_n: 12.0}", "max_force_n: 1.0e+308}", "device.max_force_n", "100"),
        ("max_force_n: 12.0}", "max_force_n: 12.0, hold_s: .inf}", "device.hold_s", "finite"),
        (
            "max_force_n: 8.0",
            "max_force_n: 8.0\n  max_force_rate_n_per_s: .inf",
            "safety.max_force_rate_n_per_s",
            "finite",
        ),
        (
            "rate_hz: 1000",
            "rate_hz: 1000\n  realtime: {cpu: 1000000000000000000000000000000}",
            "loop.realtime.cpu",
            "less than or equal",
        ),
        ("rate_hz: 1000", "rate_hz: 1000.5e+0\n  max_consecutive_overruns: 2.0", "overruns", "int"),
        (
            "- [0.8660254, 0.0, 0.5]",
            "- [2.0e+154, 0, 0]",
            "fingers[0:thumb].actuated_directions",
            "unit vector",
        ),
        # A union's member names ("int", "literal['auto']") are not keys the user wrote.
        ("  object:", "  substeps: many\n  object:", "scene.substeps", "1-64 or auto"),
        ("  object:", "  substeps: 0\n  object:", "scene.substeps", "1-64 or auto"),
    ],
)
def test_bad_shapes_and_numbers_name_key_line_and_expectation(tmp_path, old, new, where, what):
    assert old in GRASP
    text = GRASP.replace(old, new, 1)
    msg = _error(_write(tmp_path, text))
    assert "Traceback" not in msg
    line = next((ln for ln in msg.splitlines()[1:] if where in ln), None)
    assert line is not None, msg
    assert what in line, msg
    assert re.search(r"\(line \d+\)|\(in the mapping at line \d+\)", line), msg
    for label in ("int]", ".int", "literal[", "function-", "float]"):
        assert label not in msg, msg
    assert not re.search(r"less than.*\(got nan\)", msg), msg


def test_non_utf8_bytes_are_reported_with_their_line(tmp_path):
    raw = GRASP.encode().replace(b"name: grasp-stiffness", b"name: grasp-\xff\xfe")
    msg = _error(_write(tmp_path, raw))
    assert "not UTF-8" in msg
    assert f"line {_line_of(GRASP, 'name: grasp-stiffness')}" in msg


def test_deep_nesting_is_refused_without_recursion(tmp_path):
    deep = "[" * 5000 + "]" * 5000
    text = GRASP.replace("size_m: [0.05, 0.05, 0.05]", f"size_m: {deep}")
    msg = _error(_write(tmp_path, text))
    assert f"nested more than {MAX_DEPTH} levels" in msg
    assert f"line {_line_of(text, 'size_m')}" in msg


def test_too_many_nodes_and_too_large_files_are_refused(tmp_path):
    many = "[" + ", ".join(["0"] * (MAX_NODES + 10)) + "]"
    msg = _error(_write(tmp_path, GRASP.replace("[0.05, 0.05, 0.05]", many)))
    assert f"more than {MAX_NODES} values" in msg
    big = GRASP + "#" * (2 << 20) + "\n"
    msg = _error(_write(tmp_path, big, "big.yaml"))
    assert "larger than" in msg


def test_an_error_shows_a_long_value_cut_short(tmp_path):
    text = GRASP.replace("allocator: if ", f"allocator: {'x' * 5000} ")
    msg = _error(_write(tmp_path, text))
    assert len(msg) < 2000 and "..." in msg


def test_many_errors_are_capped(tmp_path):
    text = GRASP + "".join(f"unknown_{i}: 1\n" for i in range(200))
    msg = _error(_write(tmp_path, text))
    assert "200 error(s)" in msg
    assert len(msg.splitlines()) < 40
    assert msg.splitlines()[-1].strip() == "... and 180 more"


def test_the_internal_source_field_is_not_a_profile_key(tmp_path):
    msg = _error(_write(tmp_path, GRASP + "source: /etc/passwd\n"))
    assert "source: unknown key" in msg


def test_a_fifo_or_a_directory_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)  # opening it for reading would wait for a writer forever
    assert "not a regular file" in _error(fifo)
    assert "cannot read profile" in _error(tmp_path)
