"""A shared-memory ring of fixed-size tick records, and the writer process that drains it.

The servo loop copies each tick's record into the next slot of a file-backed
shared-memory ring and then publishes the new count; a separate process (run
as ``python -m hapticd.recording``) copies complete records out every
``POLL_S`` and appends them to the recording file. The loop never does file
I/O and never waits on the writer in a paced run; the writer never holds the
loop's GIL (it is another process).

Crash safety: records reach the kernel within ``POLL_S`` of being written. If
the daemon is killed (even ``kill -9``), the writer notices its parent is gone,
drains every complete record, and exits; if both are killed, only the last
``POLL_S`` of ticks can be missing.

Layout: a 4096-byte header of native-endian uint64 words (see the ``W_*``
offsets; both processes run on one machine) and an error text, then
``capacity`` records of ``itemsize`` bytes. Each word is read and written with
one aligned 8-byte access, never byte by byte: the two processes share them
without a lock.
This module imports nothing heavy: the writer starts in about 50 ms.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import signal
import sys
import time

MAGIC = b"HDRING1\x00"
HEADER_BYTES = 4096
# Offsets of the header's uint64 words.
W_ITEMSIZE = 8
W_CAPACITY = 16
W_WRITTEN = 24  # records published by the loop (monotonic count)
W_DRAINED = 32  # records the writer has handed to the kernel
W_CLOSED = 40  # 1: the loop has stopped recording; drain and exit
W_DROPPED = 48  # records the loop dropped because the ring was full
W_STATE = 56  # writer state, below
ERROR_AT = 64
ERROR_BYTES = 512
STATE_STARTING, STATE_RUNNING, STATE_DONE, STATE_FAILED = 0, 1, 2, 3
POLL_S = 0.01


def _get(mm: mmap.mmap, at: int) -> int:
    """The header word at byte ``at``, read with one aligned 8-byte load."""
    with memoryview(mm) as mv, mv[at : at + 8] as raw, raw.cast("Q") as word:
        return int(word[0])


def _put(mm: mmap.mmap, at: int, value: int) -> None:
    """Store the header word at byte ``at`` with one aligned 8-byte store: the other process
    reads these words with no lock, so it must never see one half-written.
    (``struct.pack_into`` stores byte by byte: a reader saw a count of 0 for a moment.)"""
    with memoryview(mm) as mv, mv[at : at + 8] as raw, raw.cast("Q") as word:
        word[0] = value


def _fail(mm: mmap.mmap, message: str) -> None:
    raw = message.encode("utf-8", "replace")[: ERROR_BYTES - 1]
    mm[ERROR_AT : ERROR_AT + ERROR_BYTES] = raw.ljust(ERROR_BYTES, b"\x00")
    _put(mm, W_STATE, STATE_FAILED)


def _write_all(fd: int, data: memoryview) -> None:
    while data:
        n = os.write(fd, data)
        data = data[n:]


def drain(ring_path: str, out_path: str, parent_pid: int) -> int:
    """Copy records from the ring at ``ring_path`` to ``out_path`` until closed; return count."""
    fd_ring = os.open(ring_path, os.O_RDWR)
    try:
        mm = mmap.mmap(fd_ring, 0)
    finally:
        os.close(fd_ring)
    if mm[:8] != MAGIC:
        raise SystemExit(f"hapticd ring writer: {ring_path} is not a tick ring")
    size = _get(mm, W_ITEMSIZE)
    cap = _get(mm, W_CAPACITY)
    try:
        fd = os.open(out_path, os.O_WRONLY | os.O_APPEND)
    except OSError as exc:
        _fail(mm, f"cannot open {out_path}: {exc.strerror or exc}")
        return 0
    _put(mm, W_STATE, STATE_RUNNING)
    view = memoryview(mm)
    done = _get(mm, W_DRAINED)
    orphaned = False
    try:
        while True:
            closed = _get(mm, W_CLOSED)
            n = _get(mm, W_WRITTEN)
            while done < n:
                i = done % cap
                k = min(n - done, cap - i)
                start = HEADER_BYTES + i * size
                _write_all(fd, view[start : start + k * size])
                done += k
                _put(mm, W_DRAINED, done)
            if closed or orphaned:
                break
            if os.getppid() != parent_pid:
                orphaned = True  # the daemon died: one more pass takes every complete record
                continue
            time.sleep(POLL_S)
    except OSError as exc:
        _fail(mm, f"writing {out_path} failed: {exc.strerror or exc}")
        return done
    finally:
        os.close(fd)
        view.release()
    _put(mm, W_STATE, STATE_DONE)
    mm.close()
    if orphaned:
        with contextlib.suppress(OSError):
            os.unlink(ring_path)  # nobody else will
    return done


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print("usage: python -m hapticd.recording RING_PATH OUT_PATH PARENT_PID", file=sys.stderr)
        return 2
    # The daemon decides when recording ends: a Ctrl-C or a service stop sent to the whole
    # group must not cut the file short while the daemon is still flushing.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    drain(argv[0], argv[1], int(argv[2]))
    return 0
