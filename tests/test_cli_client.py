"""The client commands of the hapticd CLI against a live loop, and the CSV export."""

from __future__ import annotations

import csv
import json

import numpy as np

from hapticd import recording
from hapticd.cli import main
from tests.conftest import wait_for_tick


def run(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_client_commands_change_and_show_the_live_loop(live, capsys, tmp_path):
    _, sock, _, _ = live
    s = str(sock)
    rc, out, _ = run(capsys, "status", "--socket", s)
    assert rc == 0 and "allocator     if" in out and "recording     " in out
    from hapticd.control import ControlClient

    with ControlClient(sock) as c:
        wait_for_tick(c, 200)
    rc, out, _ = run(capsys, "set", "stiffness", "75", "--socket", s)
    assert rc == 0 and json.loads(out)["param"] == "stiffness_n_per_m"
    rc, out, _ = run(capsys, "allocator", "pinv", "--socket", s)
    assert rc == 0 and "applied_at_tick" in json.loads(out)
    rc, out, _ = run(capsys, "status", "--json", "--socket", s)
    st = json.loads(out)
    assert st["allocator"] == "pinv" and st["scene"]["stiffness_n_per_m"] == 75.0
    rc, out, _ = run(capsys, "get", "force_limit", "--socket", s)
    assert rc == 0 and json.loads(out) == {"force_limit_n": [8.0, 8.0]}
    rc, _, err = run(capsys, "set", "stiffness", "stiff", "--socket", s)
    assert rc == 2 and "bad value 'stiff' for stiffness" in err
    rc, _, err = run(capsys, "set", "stiffness", "-5", "--socket", s)
    assert rc == 2 and "out_of_range" in err
    rc, _, _ = run(capsys, "record", "stop", "--socket", s)
    assert rc == 0
    # The daemon's state, not the arguments, is wrong: exit 1 (2 is for bad arguments).
    rc, _, err = run(capsys, "record", "stop", "--socket", s)
    assert rc == 1 and "rejected: not recording" in err
    trial = tmp_path / "t.hrec"
    trial.write_bytes(b"keep")
    rc, _, err = run(capsys, "record", "start", str(trial), "--socket", s)
    assert rc == 1 and "exists; not overwriting" in err and trial.read_bytes() == b"keep"
    rc, _, err = run(capsys, "record", "start", "/etc/t.hrec", "--socket", s)
    assert rc == 1 and "outside the recording directory" in err
    trial.unlink()
    rc, out, _ = run(capsys, "record", "start", str(trial), "--socket", s)
    assert rc == 0 and json.loads(out)["path"] == str(trial)
    rc, out, _ = run(capsys, "watch", "--count", "3", "--rate", "50", "--socket", s)
    lines = out.strip().splitlines()
    assert rc == 0 and len(lines) == 3 and all("|F|" in line for line in lines)
    rc, out, _ = run(capsys, "record", "stop", "--socket", s)
    assert rc == 0 and json.loads(out)["written"] > 0
    rc, _, _ = run(capsys, "stop", "--socket", s)
    assert rc == 0


def test_client_without_a_daemon_says_where_it_looked(capsys, tmp_path):
    rc, _, err = run(capsys, "status", "--socket", str(tmp_path / "none.sock"))
    assert rc == 1 and f"is hapticd running? (no socket at {tmp_path / 'none.sock'})" in err
    assert "Traceback" not in err


def test_export_csv_has_a_named_column_per_scalar(capsys, tmp_path):
    rec_path = tmp_path / "r.hrec"
    from tests.conftest import GRASP_PROFILE

    assert main(["run", str(GRASP_PROFILE), "--unpaced", "--no-socket", "-q",
                 "--duration", "0.5", "--record", str(rec_path)]) == 0  # fmt: skip
    capsys.readouterr()
    rc, out, _ = run(capsys, "export", str(rec_path), "--csv", str(tmp_path / "r.csv"))
    assert rc == 0 and "500 ticks" in out
    rec = recording.read(rec_path)
    with open(tmp_path / "r.csv") as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    # The allocator column holds the allocator's name (before: its index), the rest numbers.
    at = header.index("allocator")
    assert {r[at] for r in rows[1:]} == {"if"}  # the profile's allocator
    assert [rec.meta["allocators"][k] for k in rec["allocator"]] == [r[at] for r in rows[1:]]
    body = np.array([r[:at] + r[at + 1 :] for r in rows[1:]], dtype=float)
    header = header[:at] + header[at + 1 :]
    assert len(body) == 500 and len(header) == body.shape[1] == len(set(header))
    assert header[0] == "t"
    col = header.index("device_pos.index.z")
    np.testing.assert_array_equal(body[:, col], rec["device_pos"][:, 1, 2])
    col = header.index("object_rot.2.y")
    np.testing.assert_array_equal(body[:, col], rec["object_rot"][:, 2, 1])
    assert "lam_a.0" in header and "in_contact.thumb" in header
    rc, _, err = run(capsys, "export", str(tmp_path / "r.csv"))
    assert rc == 2 and "not a hapticd recording" in err


def test_export_mcap_reads_back_with_the_mcap_reader(capsys, tmp_path):
    from mcap.reader import make_reader

    from tests.conftest import GRASP_PROFILE

    rec_path = tmp_path / "r.hrec"
    assert main(["run", str(GRASP_PROFILE), "--unpaced", "--no-socket", "-q",
                 "--duration", "0.2", "--record", str(rec_path)]) == 0  # fmt: skip
    capsys.readouterr()
    out = tmp_path / "r.mcap"
    rc, text, _ = run(capsys, "export", str(rec_path), "--mcap", str(out))
    assert rc == 0 and "200 messages" in text
    rec = recording.read(rec_path)
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        msgs = list(reader.iter_messages())
        summary = reader.get_summary()
    assert len(msgs) == 200 and summary.statistics.message_count == 200
    schema, channel, message = msgs[150]
    assert channel.topic == "/hapticd/tick" and schema.encoding == "jsonschema"
    assert message.log_time == round(rec["t"][150] * 1e9)
    tick = json.loads(message.data)
    assert tick["device_pos"]["index"]["z"] == rec["device_pos"][150, 1, 2]
    assert tick["allocator"] == rec["allocator"][150]


def test_a_value_nested_too_deep_is_a_clear_error_not_a_traceback(capsys, tmp_path):
    """`hapticd set actuation` with a value nested 20,000 deep: refused before connecting,
    exit 2, the message saying how deep a value may nest (before: a RecursionError)."""
    deep = "[" * 20000 + "]" * 20000
    rc, _, err = run(capsys, "set", "actuation", deep, "--socket", str(tmp_path / "none.sock"))
    assert rc == 2, err
    assert "nested at most" in err and "Traceback" not in err
    assert len(err) < 1000  # the value is shown cut short, not all 40,000 characters
