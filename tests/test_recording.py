import json
import mmap
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from hapticd import recording
from hapticd.recording import MAGIC, Field, Recorder, RecordingError, loop_fields, read, ring
from tests.conftest import kill_writer, wait_for


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
    os.kill(rec.status()["writer_pid"], signal.SIGSTOP)  # the writer stalls (e.g. a slow disk)
    try:
        for i in range(40):
            rec.append(rec.as_record(_loop_row(fields, i)))
        assert rec.dropped == 8
    finally:
        os.kill(rec.status()["writer_pid"], signal.SIGCONT)
    status = rec.close()
    assert status["dropped"] == 8 and status["written"] == 32
    # The unread records were never overwritten by the dropped ones.
    np.testing.assert_array_equal(read(tmp_path / "x.hrec")["t"], np.arange(32))


def test_recorder_reports_a_writer_that_died(tmp_path):
    fields = _fields()
    rec = Recorder(tmp_path / "x.hrec", fields, ["a", "b"], capacity=16)
    rec.wait_running()
    kill_writer(rec)
    for i in range(20):
        rec.append(rec.as_record((float(i), np.zeros((2, 3)), [0, 0])))
    with pytest.raises(RecordingError, match=r"writer process .* ended .killed by signal 9"):
        rec.close()


def test_the_ring_writer_reports_a_write_failure(tmp_path):
    fields = _fields()
    rec = Recorder(tmp_path / "x.hrec", fields, ["a", "b"], capacity=16)
    rec.wait_running()
    os.kill(rec.status()["writer_pid"], signal.SIGSTOP)
    for i in range(5):
        rec.append(rec.as_record((float(i), np.zeros((2, 3)), [0, 0])))
    rec._words[ring.W_CLOSED // 8] = 1
    # The writer's own code, in this process, on a disk that is full.
    ring.drain(rec._ring_fd, os.open("/dev/full", os.O_WRONLY), "/dev/full", os.getppid())
    assert "writing /dev/full failed" in rec.error
    os.kill(rec.status()["writer_pid"], signal.SIGKILL)
    with pytest.raises(RecordingError, match="writing /dev/full failed"):
        rec.close()


def test_recorder_refuses_to_overwrite_when_asked(tmp_path):
    (tmp_path / "x.hrec").write_bytes(b"precious")
    with pytest.raises(RecordingError, match="exists; not overwriting"):
        Recorder(tmp_path / "x.hrec", _fields(), ["a", "b"], overwrite=False)
    assert (tmp_path / "x.hrec").read_bytes() == b"precious"
    with pytest.raises(RecordingError, match="cannot create"):
        Recorder(tmp_path / "missing" / "x.hrec", _fields(), ["a", "b"])


def test_a_header_count_is_never_seen_half_written_by_the_other_process(tmp_path):
    """The writer stores its drained count while the loop reads it (another process, no
    lock): every value read is one the writer stored, so the count never goes back.
    A byte-wise store (struct.pack_into) showed 0 for a moment, and a paced loop took the
    ring for full and dropped a tick."""
    path = tmp_path / "words"
    path.write_bytes(bytes(ring.HEADER_BYTES))
    n = 300_000
    code = (
        "import mmap, sys\n"
        "from hapticd.recording import ring\n"
        "with open(sys.argv[1], 'r+b') as f:\n"
        "    mm = mmap.mmap(f.fileno(), 0)\n"
        "words = ring.Words(mm)\n"
        f"for v in range(1, {n + 1}):\n"
        "    words[ring.W_DRAINED] = v\n"
    )
    with path.open("r+b") as f:
        mm = mmap.mmap(f.fileno(), 0)
    words = np.ndarray((8,), "=u8", buffer=mm, offset=0)  # as the Recorder reads them
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)])
    went_back = []
    last = 0
    try:
        deadline = time.monotonic() + 60
        while proc.poll() is None:
            v = int(words[ring.W_DRAINED // 8])
            if v < last:
                went_back.append((last, v))
            last = max(last, v)
            if time.monotonic() > deadline:
                pytest.fail(f"the storing process did not finish {n} stores in 60 s")
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        del words
        mm.close()
    assert proc.returncode == 0
    assert not went_back, f"{len(went_back)} reads went back, e.g. {went_back[:3]}"


def test_a_paced_recorder_takes_a_stale_drained_count_for_what_it_is(tmp_path):
    """The writer's drained count only grows: a lower reading is stale, never a full ring.
    Forced here: the loop has seen 5 drained, then reads 0; the next tick is kept."""
    fields = _fields()
    rec = Recorder(tmp_path / "x.hrec", fields, ["a", "b"], capacity=4)
    rec.wait_running()

    def drained(count):
        wait_for(lambda: rec.drained, f"{count} drained records", until=lambda d: d == count)

    for i in range(4):
        rec.append(rec.as_record((float(i), np.zeros((2, 3)), [0, 0])))
    drained(4)
    rec.append(rec.as_record((4.0, np.zeros((2, 3)), [0, 0])))  # the loop sees 4 drained
    drained(5)
    os.kill(rec.status()["writer_pid"], signal.SIGSTOP)  # nothing stores the count while we look
    try:
        rec._words[ring.W_DRAINED // 8] = 0  # what a half-written store showed
        rec.append(rec.as_record((5.0, np.zeros((2, 3)), [0, 0])))
        rec._words[ring.W_DRAINED // 8] = 5
    finally:
        os.kill(rec.status()["writer_pid"], signal.SIGCONT)
    status = rec.close()
    assert status["dropped"] == 0 and status["written"] == 6
    np.testing.assert_array_equal(read(tmp_path / "x.hrec")["t"], np.arange(6))


def test_csv_columns_name_every_per_finger_field_by_finger(tmp_path):
    """Every field the tick frame declares per finger (first axis "F") is labelled by finger
    name in a CSV export, 3-vectors by axis: ``contact_point.thumb.x``, ``buttons.index``."""
    from hapticd.physics.frame import FIELDS
    from hapticd.recording.export import csv_columns

    fields = loop_fields(2, 3)
    data = np.zeros(4, dtype=recording.make_dtype(fields))
    rec = recording.Recording(tmp_path / "r.hrec", data, fields, ["thumb", "index"], {}, 0)
    cols = csv_columns(rec)
    recorded = {f.name for f in fields}
    per_finger = [f for f in FIELDS if f.shape[:1] == ("F",) and f.name in recorded]
    assert {f.name for f in per_finger} >= {"contact_point", "contact_normal", "buttons"}
    for f in per_finger:
        for finger in ("thumb", "index"):
            if f.shape == ("F", 3):
                assert [f"{f.name}.{finger}.{a}" for a in "xyz"] == [
                    c for c in cols if c.startswith(f"{f.name}.{finger}.")
                ], f.name
            else:
                assert f"{f.name}.{finger}" in cols, f.name
        assert not any(c.startswith(f"{f.name}.0") for c in cols), f.name
    assert "lam_a.2" in cols and "object_pos.z" in cols and "object_rot.2.y" in cols
    assert len(cols) == len(set(cols)) == sum(int(np.prod(f.shape)) for f in fields)
