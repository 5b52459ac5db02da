"""``hapticd schema`` (the profile's JSON Schema), ``run -v``/``--log-level``, and the
progress line of long ``--unpaced`` runs and exports."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys

import pytest
import yaml

from hapticd import recording
from hapticd.cli import main
from hapticd.profile import Profile
from tests.conftest import GRASP_PROFILE, ROOT


def _resolve(schema: dict, node: dict) -> dict:
    ref = node.get("$ref")
    return _resolve(schema, schema["$defs"][ref.rsplit("/", 1)[1]]) if ref else node


def _keys_known(schema: dict, node: dict, data: object, where: str) -> list[str]:
    """Keys of ``data`` the schema ``node`` does not know (walks objects, arrays and the
    device union by its backend)."""
    node = _resolve(schema, node)
    bad: list[str] = []
    if isinstance(data, dict):
        options = [_resolve(schema, o) for o in node.get("anyOf", node.get("oneOf", []))]
        options = [o for o in options if "properties" in o]  # not the null of an optional
        if options:  # one model, or the device union: the member whose backend matches
            node = next(
                o
                for o in options
                if "backend" not in o["properties"]
                or data.get("backend") == o["properties"]["backend"].get("const")
                or data.get("backend") in o["properties"]["backend"].get("enum", ())
            )
        props = node.get("properties", {})
        assert node.get("additionalProperties") is False, where
        for k, v in data.items():
            if k not in props:
                bad.append(f"{where}.{k}")
            else:
                bad += _keys_known(schema, props[k], v, f"{where}.{k}")
    elif isinstance(data, list) and "items" in node:
        for i, v in enumerate(data):
            bad += _keys_known(schema, node["items"], v, f"{where}[{i}]")
    return bad


def test_schema_is_the_profiles_json_schema(tmp_path, capsys):
    assert main(["schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["additionalProperties"] is False
    keys = {k for k, f in Profile.model_fields.items() if not f.exclude}
    assert set(schema["properties"]) == keys and "source" not in schema["properties"]
    assert set(schema["required"]) == {"name", "fingers", "scene", "safety"}
    speed = _resolve(schema, schema["properties"]["safety"])["properties"]
    assert speed["max_device_speed_m_per_s"]["maximum"] == 100
    assert speed["max_device_speed_m_per_s"]["default"] == 5.0
    # Every key of the bundled profiles is one the schema knows, where it is.
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        data = yaml.safe_load(path.read_text())
        assert _keys_known(schema, schema, data, path.name) == []
    # And a misspelled key is one it does not.
    data = yaml.safe_load(GRASP_PROFILE.read_text())
    data["scene"]["object"]["stifness_n_per_m"] = 1.0
    assert _keys_known(schema, schema, data, "p") == ["p.scene.object.stifness_n_per_m"]
    out = tmp_path / "profile.schema.json"
    assert main(["schema", "--out", str(out)]) == 0
    assert json.loads(out.read_text()) == schema


RUN = ["run", str(GRASP_PROFILE), "--unpaced", "--duration", "0.05", "-q"]


def test_verbose_logs_what_the_run_was_built_from(caplog):
    caplog.set_level(logging.DEBUG)
    assert main(RUN) == 0
    assert not [r for r in caplog.records if r.levelno == logging.DEBUG]
    caplog.clear()
    assert main([*RUN, "-v"]) == 0
    debug = [r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG]
    assert any(m.startswith("loop: 1000 Hz, unpaced, stages contact") for m in debug), debug
    assert any(m.startswith("finger thumb: replay replay-thumb") for m in debug), debug
    caplog.clear()
    assert main([*RUN, "--log-level", "debug"]) == 0
    assert [r for r in caplog.records if r.levelno == logging.DEBUG]
    assert main([*RUN, "--log-level", "error"]) == 0
    assert logging.getLogger("hapticd").getEffectiveLevel() == logging.ERROR
    assert main(RUN) == 0
    assert logging.getLogger("hapticd").getEffectiveLevel() == logging.INFO


def test_progress_lines_of_an_unpaced_run_and_an_export(tmp_path, capsys):
    rec = tmp_path / "g.hrec"
    # Not a terminal, no --progress: no progress line.
    assert main(["run", str(GRASP_PROFILE), "--unpaced", "-q", "--record", str(rec)]) == 0
    assert "%" not in capsys.readouterr().err
    assert main(["export", str(rec), "--csv", str(tmp_path / "a.csv")]) == 0
    assert "%" not in capsys.readouterr().err
    # --progress: the run's line ends where the trajectory does, the export's at every tick.
    assert main(["run", str(GRASP_PROFILE), "--unpaced", "-q", "--progress"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("\rhapticd: run ") and err.endswith("\n"), repr(err)
    assert "100% (7.8 of 7.8 s)" in err, repr(err)
    ticks = recording.read(rec).ticks
    assert main(["export", str(rec), "--csv", str(tmp_path / "b.csv"), "--progress"]) == 0
    err = capsys.readouterr().err
    assert f"100% ({ticks} of {ticks} ticks)" in err, repr(err)
    # The chunked export writes what the one-piece export wrote.
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()


@pytest.mark.parametrize(
    "argv",
    [
        ["check", str(GRASP_PROFILE)],
        ["--help"],
        ["status", "--socket", "{sock}"],
        ["watch", "--rate", "50", "--count", "3", "--socket", "{sock}"],
    ],
    ids=lambda argv: " ".join(a for a in argv if a != "{sock}" and not a.startswith("/")),
)
def test_a_closed_stdout_ends_quietly(argv, idle_server):
    """``hapticd ... | head -1``: the reader of stdout is gone before a line is written.
    The command ends with the shell's usual code for that (141) or 0, and no traceback
    (before: a BrokenPipeError traceback from every command that prints)."""
    r, w = os.pipe()
    os.close(r)  # the reader has gone
    try:
        args = [a.format(sock=idle_server.path) for a in argv]
        proc = subprocess.run(
            [sys.executable, "-m", "hapticd", *args],
            cwd=ROOT,
            stdout=w,
            stderr=subprocess.PIPE,
            text=True,
            timeout=60,
        )
    finally:
        os.close(w)
    assert proc.returncode in (0, 141), proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr
    assert "BrokenPipe" not in proc.stderr and "Broken pipe" not in proc.stderr, proc.stderr
