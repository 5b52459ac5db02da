"""Recording under adversity: counts published whole, a writer or a file lost mid-run, and
record_start confined to the recording directory without following links or blocking."""

from __future__ import annotations

import mmap
import os
import shutil
import stat
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from hapticd.recording import Field, Recorder, RecordingError, read, ring
from tests.conftest import kill_writer


def _fields():
    return [Field("t", "<f8", (), "s"), Field("device_pos", "<f8", (2, 3), "m")]


def _append(rec: Recorder, n: int, start: int = 0) -> None:
    for i in range(start, start + n):
        rec.append(rec.as_record((float(i), np.zeros((2, 3)))))


# The writer's side of the ring in its own process: it publishes its drained count and reads
# the loop's written count, as drain() does, checking that the loop's count never goes back.
_WRITER_SIDE = """
import mmap, sys
from hapticd.recording import ring
mm = mmap.mmap(int(sys.argv[1]), 0)
words = ring.Words(mm)
back = last = 0
for i in range(1, 300_000):
    words[ring.W_DRAINED] = i * 257
    n = words[ring.W_WRITTEN]
    back += n < last
    last = n
words.release()
print(back)
"""


def test_ring_counts_are_published_whole_never_zeroed_or_torn():
    """A count that is zeroed before it is written (struct.pack_into) or read byte by byte
    can be seen as 0 or torn by the other process: the loop then sees a full ring and drops
    a tick although the writer has caught up."""
    fd = os.memfd_create("word-test")
    try:
        os.ftruncate(fd, ring.HEADER_BYTES)
        mm = mmap.mmap(fd, ring.HEADER_BYTES)
        child = subprocess.Popen(
            [sys.executable, "-c", _WRITER_SIDE, str(fd)],
            pass_fds=(fd,),
            stdout=subprocess.PIPE,
            text=True,
        )
    finally:
        os.close(fd)
    # The loop's side, as Recorder.append does it: numpy words.
    words = np.ndarray((8,), "<u8", buffer=mm)
    back = last = 0
    i = 0
    deadline = time.monotonic() + 30.0
    while child.poll() is None and time.monotonic() < deadline:
        i += 1
        words[ring.W_WRITTEN // 8] = i * 257
        d = int(words[ring.W_DRAINED // 8])
        back += d < last
        last = d
    out, _ = child.communicate(timeout=30)
    del words
    mm.close()
    assert child.returncode == 0
    assert last > 0 and i > 1000  # the two sides did overlap
    assert back == 0, f"the loop saw the writer's count go back {back} times"
    assert int(out) == 0, f"the writer saw the loop's count go back {out.strip()} times"


def test_a_killed_writer_shows_in_status_at_once_not_when_the_ring_fills(tmp_path):
    rec = Recorder(tmp_path / "x.hrec", _fields(), ["a", "b"], capacity=4096)
    rec.wait_running()
    _append(rec, 10)
    kill_writer(rec)
    _append(rec, 10, 10)
    st = rec.status()
    assert rec.dropped == 0 and st["ticks"] == 20  # the ring is far from full
    assert st["error"] is not None and "killed by signal 9" in st["error"]
    with pytest.raises(RecordingError, match="killed by signal 9"):
        rec.close()


def test_a_recording_whose_directory_is_removed_is_an_error_not_a_silent_loss(tmp_path):
    where = tmp_path / "session"
    where.mkdir()
    rec = Recorder(where / "x.hrec", _fields(), ["a", "b"], capacity=4096)
    rec.wait_running()
    _append(rec, 50)
    shutil.rmtree(where)
    deadline = time.monotonic() + 5.0
    while rec.status()["error"] is None and time.monotonic() < deadline:
        _append(rec, 1, rec.ticks)
        time.sleep(0.01)
    assert "deleted while recording" in (rec.status()["error"] or "")
    with pytest.raises(RecordingError, match="deleted while recording"):
        rec.close()


# -- record_start confined to its directory ----------------------------------------------


def _make(root, name, *, overwrite=False):
    rec = Recorder(name, _fields(), ["a", "b"], overwrite=overwrite, root=root)
    rec.wait_running()
    return rec


def test_relative_names_resolve_inside_the_directory_and_outside_is_refused(tmp_path):
    root = tmp_path / "records"
    rec = _make(root, "s01/trial-01.hrec")  # the directory and s01 are created
    assert rec.path == root / "s01" / "trial-01.hrec"
    rec.close()
    assert read(root / "s01" / "trial-01.hrec").ticks == 0
    assert stat.S_IMODE(os.stat(root / "s01").st_mode) == 0o700
    rec = _make(root, str(root / "abs.hrec"))  # an absolute path inside it is fine
    rec.close()
    for bad in ("/etc/hapticd.hrec", str(tmp_path / "x.hrec"), "../x.hrec", "s01/../../x.hrec"):
        with pytest.raises(RecordingError, match=r"outside the recording directory|no '\.\.'"):
            _make(root, bad)
    assert not (tmp_path / "x.hrec").exists()


def test_links_are_never_followed_and_their_targets_never_touched(tmp_path):
    root = tmp_path / "records"
    root.mkdir()
    victim = tmp_path / "victim"
    victim.write_bytes(b"precious")
    (root / "link.hrec").symlink_to(victim)
    (root / "dangling.hrec").symlink_to(tmp_path / "created-through-a-link")
    (root / "sub").symlink_to(tmp_path)
    for name in ("link.hrec", "dangling.hrec"):
        with pytest.raises(RecordingError, match="exists; not overwriting"):
            _make(root, name)
        with pytest.raises(RecordingError, match="is a symbolic link; not replacing it"):
            _make(root, name, overwrite=True)
    with pytest.raises(RecordingError, match="not a directory of its own"):
        _make(root, "sub/x.hrec")
    assert victim.read_bytes() == b"precious"
    assert not (tmp_path / "created-through-a-link").exists()
    assert not (tmp_path / "x.hrec").exists()


def test_a_fifo_is_refused_without_blocking(tmp_path):
    root = tmp_path / "records"
    root.mkdir()
    os.mkfifo(root / "f.hrec")
    errors: list[str] = []

    def attempt(overwrite: bool) -> None:
        try:
            _make(root, "f.hrec", overwrite=overwrite).close()
        except RecordingError as exc:
            errors.append(str(exc))

    for overwrite in (False, True):
        t = threading.Thread(target=attempt, args=(overwrite,), name="fifo-attempt")
        t.start()
        t.join(timeout=5.0)
        if t.is_alive():  # unblock it so the test can end, then fail
            os.close(os.open(root / "f.hrec", os.O_RDONLY | os.O_NONBLOCK))
            t.join(timeout=5.0)
            pytest.fail("record_start blocked on a FIFO")
    assert "exists; not overwriting" in errors[0] and "is a FIFO" in errors[1]
    assert stat.S_ISFIFO(os.lstat(root / "f.hrec").st_mode)


@pytest.mark.skipif(os.geteuid() != 0, reason="making another user's file needs root")
def test_another_users_file_is_not_replaced(tmp_path):
    root = tmp_path / "records"
    root.mkdir()
    theirs = root / "theirs.hrec"
    theirs.write_bytes(b"not yours")
    os.chown(theirs, 12345, 12345)
    with pytest.raises(RecordingError, match="belongs to another user"):
        _make(root, "theirs.hrec", overwrite=True)
    assert theirs.read_bytes() == b"not yours"


def test_overwrite_replaces_a_regular_file_by_rename_and_the_file_is_not_world_readable(
    tmp_path,
):
    root = tmp_path / "records"
    root.mkdir()
    (root / "old.hrec").write_bytes(b"old")
    old = os.umask(0)
    try:
        rec = _make(root, "old.hrec", overwrite=True)
        _append(rec, 5)
        rec.close()
    finally:
        os.umask(old)
    assert read(root / "old.hrec").ticks == 5
    assert stat.S_IMODE(os.stat(root / "old.hrec").st_mode) == 0o640
    assert sorted(p.name for p in root.iterdir()) == ["old.hrec"]  # no temporary left


# -- a full disk ---------------------------------------------------------------------------


def _ring_with(records: np.ndarray, capacity: int) -> int:
    """A ring (as Recorder makes it) holding ``records``, closed by the loop: its fd."""
    size = records.dtype.itemsize
    fd = os.memfd_create("test-ring", os.MFD_CLOEXEC)
    os.ftruncate(fd, ring.HEADER_BYTES + capacity * size)
    with mmap.mmap(fd, 0) as mm:
        mm[:8] = ring.MAGIC
        mm[ring.HEADER_BYTES : ring.HEADER_BYTES + records.nbytes] = records.tobytes()
        words = ring.Words(mm)
        words[ring.W_ITEMSIZE] = size
        words[ring.W_CAPACITY] = capacity
        words[ring.W_WRITTEN] = len(records)
        words[ring.W_CLOSED] = 1
        words.release()
    return fd


def test_on_a_full_disk_the_written_count_is_what_the_file_holds(tmp_path, monkeypatch):
    """The disk fills in the middle of a chunk of records: the kernel takes part of it,
    then says ENOSPC. The count is the whole records in the file, and a torn record is cut
    off, so `written` is exact (before: the chunk's part was in the file, not in the count:
    status said 1,530 written, the file held 1,537)."""
    from hapticd.recording.format import make_dtype

    dtype = make_dtype(_fields())
    records = np.zeros(40, dtype)
    records["t"] = np.arange(40)
    fd = _ring_with(records, capacity=64)
    out = tmp_path / "full.bin"
    header = b"H" * 100
    out.write_bytes(header)
    room = [len(header) + int(20.5 * dtype.itemsize)]  # bytes left on the "disk"

    def write(fd_, data):
        left = room[0] - os.fstat(fd_).st_size
        if left <= 0:
            raise OSError(28, "No space left on device")
        return os.write(fd_, data[:left])

    monkeypatch.setattr(ring, "write", write)
    out_fd = os.open(out, os.O_WRONLY | os.O_APPEND)
    try:
        done = ring.drain(fd, out_fd, str(out), os.getppid())
        with mmap.mmap(fd, 0) as mm:
            words = ring.Words(mm)
            drained, state = words[ring.W_DRAINED], words[ring.W_STATE]
            words.release()
            error = bytes(mm[ring.ERROR_AT : ring.ERROR_AT + ring.ERROR_BYTES])
    finally:
        os.close(fd)
    assert done == drained == 20
    assert out.stat().st_size == len(header) + 20 * dtype.itemsize  # the torn one cut off
    got = np.frombuffer(out.read_bytes()[len(header) :], dtype)
    assert list(got["t"]) == list(range(20))
    assert state == ring.STATE_FAILED
    assert b"after 20 ticks" in error and b"No space left" in error


def test_a_failed_recording_is_named_in_the_runs_summary(tmp_path):
    """The recording's file goes mid-run: the run's summary keeps its recording block,
    with the error and how many ticks were lost (before: no recording block at all)."""
    from hapticd.cli.run import format_summary
    from hapticd.daemon.session import build_session
    from hapticd.profile import load_profile
    from tests.conftest import GRASP_PROFILE

    where = tmp_path / "session"
    where.mkdir()
    session = build_session(
        load_profile(GRASP_PROFILE), paced=False, duration_s=0.5, record_path=where / "r.hrec"
    )

    class RemoveAt:  # a stage that removes the recording's folder at tick 100
        name = "remove"
        k = 0

        def run(self, frame):
            self.k += 1
            if self.k == 100:
                shutil.rmtree(where)

    session.loop.renderer.insert(RemoveAt(), after="allocation")
    with pytest.raises(RecordingError, match="deleted while recording") as caught:
        session.run()
    summary = caught.value.summary
    rec = summary["recording"]
    assert "deleted while recording" in rec["error"]
    assert rec["ticks"] > 100 and rec["lost"] == rec["ticks"] - rec["written"]
    summary["recording_error"] = str(caught.value)
    assert "deleted while recording" in format_summary(summary)
