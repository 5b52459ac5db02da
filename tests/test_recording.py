import json
import os
import signal

import numpy as np
import pytest

from hapticd import recording
from hapticd.recording import MAGIC, Field, Recorder, RecordingError, loop_fields, read, ring


def _fields():
    return [
        Field("t", "<f8", (), "s"),
        Field("device_pos", "<f8", (2, 3), "m"),
        Field("in_contact", "u1", (2,)),
    ]


def test_round_trip_named_arrays(tmp_path):
    t = np.arange(5) * 1e-3
    pos = np.random.default_rng(1).normal(size=(5, 2, 3))
    contact = np.array([[0, 1]] * 5, dtype=np.uint8)
    path = tmp_path / "a.hrec"
    recording.write(
        path,
        {"t": t, "device_pos": pos, "in_contact": contact},
        _fields(),
        ["thumb", "index"],
        {"k": 1},
    )
    rec = read(path)
    assert rec.fingers == ["thumb", "index"]
    assert rec.meta == {"k": 1}
    assert list(rec) == ["t", "device_pos", "in_contact"]
    assert rec.units()["device_pos"] == "m"
    np.testing.assert_array_equal(rec["t"], t)
    np.testing.assert_array_equal(rec["device_pos"], pos)
    assert rec["device_pos"].shape == (5, 2, 3)
    assert rec.ticks == 5
    with pytest.raises(KeyError):
        rec["nope"]


def test_torn_tail_is_dropped_not_an_error(tmp_path):
    path = tmp_path / "a.hrec"
    recording.write(
        path,
        {"t": np.arange(10.0), "device_pos": np.zeros((10, 2, 3)), "in_contact": np.zeros((10, 2))},
        _fields(),
        ["a", "b"],
    )
    blob = path.read_bytes()
    path.write_bytes(blob[:-7])  # crash in the middle of the last record
    rec = read(path)
    assert rec.ticks == 9
    assert rec.torn_bytes > 0
    np.testing.assert_array_equal(rec["t"], np.arange(9.0))


@pytest.mark.parametrize(
    ("blob", "match"),
    [
        (b"garbage", "bad magic"),
        (MAGIC + (10**6).to_bytes(4, "little") + b"{}", "header length"),
        (MAGIC + (4).to_bytes(4, "little") + b"{not", "not valid JSON"),
        (MAGIC + (2).to_bytes(4, "little") + b"[]", "must be a JSON object"),
    ],
)
def test_malformed_files_give_clear_errors(tmp_path, blob, match):
    path = tmp_path / "bad.hrec"
    path.write_bytes(blob)
    with pytest.raises(RecordingError, match=match) as exc:
        read(path)
    assert str(path) in str(exc.value)


def _with_header(tmp_path, header: dict):
    h = json.dumps(header).encode()
    path = tmp_path / "h.hrec"
    path.write_bytes(MAGIC + len(h).to_bytes(4, "little") + h)
    return path


def test_bad_header_fields_and_version(tmp_path):
    with pytest.raises(RecordingError, match="version 7 is not supported"):
        read(_with_header(tmp_path, {"version": 7, "fields": []}))
    with pytest.raises(RecordingError, match="'fields' must be a non-empty list"):
        read(_with_header(tmp_path, {"version": 1, "fields": []}))
    with pytest.raises(RecordingError, match="field 0 is malformed"):
        read(_with_header(tmp_path, {"version": 1, "fields": [{"name": "t", "dtype": "nonsense"}]}))
    with pytest.raises(RecordingError, match="cannot read"):
        read(tmp_path / "missing.hrec")


def _loop_row(fields, i):
    row = []
    for f in fields:
        value = np.full(f.shape, float(i)) if f.shape else float(i % 2 if f.dtype == "u1" else i)
        if f.name == "lam_a":
            value = np.array([i, -i], dtype=float)
        row.append(value)
    return row


def test_recorder_writes_every_row_through_the_ring_and_wraps(tmp_path):
    fields = loop_fields(2, 2)
    path = tmp_path / "loop.hrec"
    # A ring far smaller than the run: it wraps many times; unpaced, the loop waits for room.
    rec = Recorder(path, fields, ["thumb", "index"], capacity=64, block_when_full=True)
    n = 1000
    for i in range(n):
        rec.append(rec.as_record(_loop_row(fields, i)))
    status = rec.close()
    assert status["ticks"] == status["written"] == n and status["dropped"] == 0
    out = read(path)
    assert out.ticks == n
    np.testing.assert_array_equal(out["t"], np.arange(n))
    np.testing.assert_array_equal(out["device_pos"][:, 1, 2], np.arange(n))
    np.testing.assert_array_equal(out["lam_a"][:, 1], -np.arange(n))
    np.testing.assert_array_equal(out["fault"], np.arange(n) % 2)


def test_a_paced_recorder_drops_ticks_rather_than_wait_or_overwrite(tmp_path):
    fields = loop_fields(2, 2)
    rec = Recorder(tmp_path / "x.hrec", fields, ["a", "b"], capacity=32)
    rec.wait_running()
    os.kill(rec._proc.pid, signal.SIGSTOP)  # the writer stalls (e.g. a slow disk)
    try:
        for i in range(40):
            rec.append(rec.as_record(_loop_row(fields, i)))
        assert rec.dropped == 8
    finally:
        os.kill(rec._proc.pid, signal.SIGCONT)
    status = rec.close()
    assert status["dropped"] == 8 and status["written"] == 32
    # The unread records were never overwritten by the dropped ones.
    np.testing.assert_array_equal(read(tmp_path / "x.hrec")["t"], np.arange(32))


def test_recorder_reports_a_writer_that_died(tmp_path):
    fields = _fields()
    rec = Recorder(tmp_path / "x.hrec", fields, ["a", "b"], capacity=16)
    rec.wait_running()
    os.kill(rec._proc.pid, signal.SIGKILL)
    rec._proc.wait()
    for i in range(20):
        rec.append(rec.as_record((float(i), np.zeros((2, 3)), [0, 0])))
    with pytest.raises(RecordingError, match=r"writer process .* ended .killed by signal 9"):
        rec.close()


def test_the_ring_writer_reports_a_write_failure(tmp_path):
    fields = _fields()
    rec = Recorder(tmp_path / "x.hrec", fields, ["a", "b"], capacity=16)
    rec.wait_running()
    os.kill(rec._proc.pid, signal.SIGSTOP)
    for i in range(5):
        rec.append(rec.as_record((float(i), np.zeros((2, 3)), [0, 0])))
    rec._words[ring.W_CLOSED // 8] = 1
    # The writer's own code, in this process, on a disk that is full.
    ring.drain(rec._ring_fd, os.open("/dev/full", os.O_WRONLY), "/dev/full", os.getppid())
    assert "writing /dev/full failed" in rec.error
    os.kill(rec._proc.pid, signal.SIGKILL)
    with pytest.raises(RecordingError, match="No space left"):
        rec.close()


def test_recorder_refuses_to_overwrite_when_asked(tmp_path):
    (tmp_path / "x.hrec").write_bytes(b"precious")
    with pytest.raises(RecordingError, match="exists; not overwriting"):
        Recorder(tmp_path / "x.hrec", _fields(), ["a", "b"], overwrite=False)
    assert (tmp_path / "x.hrec").read_bytes() == b"precious"
    with pytest.raises(RecordingError, match="cannot create"):
        Recorder(tmp_path / "missing" / "x.hrec", _fields(), ["a", "b"])
