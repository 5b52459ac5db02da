"""A shared-memory ring of fixed-size tick records, and the writer process that drains it.

The servo loop copies each tick's record into the next slot of a shared-memory
ring and then publishes the new count; a separate process (run as
``python -m hapticd.recording``) copies complete records out every ``POLL_S``
and appends them to the recording file. The loop never does file I/O and never
waits on the writer in a paced run; the writer never holds the loop's GIL (it
is another process).

The ring is an anonymous memory file (``memfd_create``): it has no name in
/dev/shm, so nothing is left behind however the processes end. The daemon
passes the ring's and the recording's file descriptors to the writer; the
writer never opens a path.

Crash safety: records reach the kernel within ``POLL_S`` of being written. If
the daemon is killed (even ``kill -9``), the writer notices its parent is gone,
drains every complete record, and exits; if both are killed, only the last
``POLL_S`` of ticks can be missing. A recording file deleted while recording
(its directory removed) is noticed within ``CHECK_S`` and reported as an error.

Layout: a 4096-byte header of little-endian uint64 words (see the ``W_*``
offsets) and an error text, then ``capacity`` records of ``itemsize`` bytes.

Publication: every word is read and written whole, with one aligned 8-byte load
or store (``Words``: a memoryview of the words as native uint64; ``struct``
would zero the word before writing it and read it byte by byte, so the other
side could see 0 or a torn count). The loop stores a record, then the count;
the writer loads the count, then the records. That order is kept by the CPU on
x86 and x86-64 (total store order); on weakly ordered CPUs (ARM) it is not
guaranteed and ``ORDERED_STORES`` is False (docs/daemon.md states the limit).
This module imports nothing heavy: the writer starts in about 50 ms.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import mmap
import os
import platform
import signal
import stat
import struct
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
# The loop's clock anchor (``Words.anchor``), after the error text: tick 0's due time on
# the LSL clock and in UTC (float64 bits), then 1 once both are stored; and where the
# recording's header keeps a place for it (byte offset and width; 0: no place).
W_ANCHOR_LSL = 576
W_ANCHOR_UTC = 584
W_ANCHORED = 592
W_CLOCK_AT = 600
W_CLOCK_WIDTH = 608
STATE_STARTING, STATE_RUNNING, STATE_DONE, STATE_FAILED = 0, 1, 2, 3
POLL_S = 0.01
CHECK_S = 0.1  # how often the writer checks that its file still exists
# Stores become visible in program order only on these CPUs (see the module docstring).
ORDERED_STORES = platform.machine().lower() in {"x86_64", "amd64", "i386", "i686", "x86"}
if sys.byteorder != "little":  # the words are little-endian and read as native uint64
    raise ImportError("hapticd recording rings need a little-endian CPU")


class Words:
    """The ring header's uint64 words, each read and written with one aligned 8-byte access."""

    def __init__(self, mm: mmap.mmap) -> None:
        # An mmap starts on a page boundary, so every word is 8-byte aligned.
        self._view = memoryview(mm)[:HEADER_BYTES].cast("Q")

    def __getitem__(self, at: int) -> int:
        return self._view[at // 8]

    def __setitem__(self, at: int, value: int) -> None:
        self._view[at // 8] = value

    def release(self) -> None:
        self._view.release()

    def set_anchor(self, lsl_s: float, utc_unix_s: float) -> None:
        """Store the loop's clock anchor (``clock_anchor``), then mark it stored."""
        self[W_ANCHOR_LSL] = _bits(lsl_s)
        self[W_ANCHOR_UTC] = _bits(utc_unix_s)
        self[W_ANCHORED] = 1

    def anchor(self) -> tuple[float, float] | None:
        """The anchor ``set_anchor`` stored: (LSL clock s, UTC Unix time s), or None."""
        if not self[W_ANCHORED]:
            return None
        return _float(self[W_ANCHOR_LSL]), _float(self[W_ANCHOR_UTC])


def _bits(x: float) -> int:
    return int.from_bytes(struct.pack("<d", x), "little")


def _float(word: int) -> float:
    return float(struct.unpack("<d", word.to_bytes(8, "little"))[0])


def clock_anchor(origin_monotonic_s: float) -> tuple[float, float]:
    """The loop's clock anchor for its origin (tick 0's due time, monotonic s): that instant
    on the LSL clock (liblsl's local_clock is std::chrono::steady_clock: CLOCK_MONOTONIC on
    Linux, the clock of ``time.monotonic``, so it is the origin itself) and in UTC (Unix
    time s, from the realtime clock read beside the monotonic one)."""
    mono, real = time.monotonic(), time.time()
    return origin_monotonic_s, real - (mono - origin_monotonic_s)


def clock_json(lsl_s: float, utc_unix_s: float) -> dict[str, object]:
    """A recording header's ``clock``: tick 0's due time on the LSL clock (s) and in UTC
    (ISO 8601 and Unix time s); a tick's LSL time is ``lsl_s + t_wall``."""
    utc = datetime.datetime.fromtimestamp(utc_unix_s, datetime.UTC)
    return {
        "lsl_s": lsl_s,
        "utc": utc.isoformat(timespec="microseconds").replace("+00:00", "Z"),
        "utc_unix_s": utc_unix_s,
    }


def clock_patch(words: Words, width: int) -> bytes | None:
    """The bytes that fill a header's place for its clock (``width`` bytes: the JSON of
    ``clock_json``, padded with spaces), once the loop's anchor is stored; else None."""
    anchor = words.anchor()
    if anchor is None:
        return None
    raw = json.dumps(clock_json(*anchor), sort_keys=True).encode()
    return raw.ljust(width) if len(raw) <= width else None


def fail(mm: mmap.mmap, words: Words, message: str) -> None:
    """Mark the ring's writer failed with ``message`` (read back by the daemon)."""
    raw = message.encode("utf-8", "replace")[: ERROR_BYTES - 1]
    mm[ERROR_AT : ERROR_AT + ERROR_BYTES] = raw.ljust(ERROR_BYTES, b"\x00")
    words[W_STATE] = STATE_FAILED


# How the writer writes a file descriptor: os.write; a seam (the tests make it fail as a
# full disk does).
write = os.write


class _ShortWriteError(OSError):
    """A write failed after ``written`` bytes of its data reached the file."""

    def __init__(self, exc: OSError, written: int) -> None:
        super().__init__(exc.errno, exc.strerror)
        self.written = written


def _write_all(fd: int, data: memoryview) -> None:
    """Write all of ``data``; _ShortWriteError (saying how much did get written) if not."""
    total = len(data)
    while data:
        try:
            n = write(fd, data)
        except OSError as exc:
            raise _ShortWriteError(exc, total - len(data)) from None
        data = data[n:]


def _deleted(fd: int) -> bool:
    """True when the open file has no name left (deleted, or its directory removed)."""
    st = os.fstat(fd)
    return stat.S_ISREG(st.st_mode) and st.st_nlink == 0


def drain(ring_fd: int, out_fd: int, out_path: str, parent_pid: int, every: int = 1) -> int:
    """Copy records from the ring ``ring_fd`` to the file ``out_fd`` (named ``out_path`` in
    messages) until the loop closes the ring or its parent dies; return the count taken
    from the ring. ``every`` > 1: only records 0, every, 2 every, ... go to the file."""
    mm = mmap.mmap(ring_fd, 0)
    if mm[:8] != MAGIC:
        raise SystemExit(f"hapticd ring writer: fd {ring_fd} is not a tick ring")
    words = Words(mm)
    view = memoryview(mm)
    try:
        done = _drain(words, view, out_fd, out_path, parent_pid, every)
    except _WriterFailedError as exc:
        fail(mm, words, str(exc))
        done = exc.done
    else:
        words[W_STATE] = STATE_DONE
    finally:
        os.close(out_fd)
        view.release()
        words.release()
        mm.close()
    return done


class _WriterFailedError(Exception):
    def __init__(self, message: str, done: int) -> None:
        super().__init__(message)
        self.done = done


def _drain(
    words: Words, view: memoryview, out_fd: int, out_path: str, parent_pid: int, every: int = 1
) -> int:
    size = words[W_ITEMSIZE]
    cap = words[W_CAPACITY]
    done = words[W_DRAINED]
    words[W_STATE] = STATE_RUNNING
    orphaned = False
    clock_at, clock_width = words[W_CLOCK_AT], words[W_CLOCK_WIDTH]
    next_check = time.monotonic() + CHECK_S
    lost = f"{out_path} was deleted while recording (its directory removed?): every tick is lost"
    try:
        while True:
            closed = words[W_CLOSED]
            n = words[W_WRITTEN]
            if clock_at and (patch := clock_patch(words, clock_width)) is not None:
                # The header's place for the clock (the loop had not started when it was
                # written): filled in place, before or after any record (pwrite leaves the
                # file's offset, where records go, alone).
                os.pwrite(out_fd, patch, clock_at)
                clock_at = 0
            while done < n and every > 1:
                # Decimated: one record at a time, those whose index is a multiple.
                if done % every == 0:
                    start = HEADER_BYTES + (done % cap) * size
                    _write_all(out_fd, view[start : start + size])
                done += 1
                words[W_DRAINED] = done
            while done < n:
                i = done % cap
                k = min(n - done, cap - i)
                start = HEADER_BYTES + i * size
                _write_all(out_fd, view[start : start + k * size])
                done += k
                words[W_DRAINED] = done
            if closed or orphaned:
                break
            if os.getppid() != parent_pid:
                orphaned = True  # the daemon died: one more pass takes every complete record
                continue
            now = time.monotonic()
            if now >= next_check:
                next_check = now + CHECK_S
                if _deleted(out_fd):
                    raise _WriterFailedError(lost, done)
            time.sleep(POLL_S)
        if _deleted(out_fd):
            raise _WriterFailedError(lost, done)
    except OSError as exc:
        if isinstance(exc, _ShortWriteError):
            # Part of the last chunk reached the file (a disk fills mid-write): count its
            # whole records, and cut a torn one off, so the file holds exactly ``done``.
            whole, torn = divmod(exc.written, size)
            done += whole if every == 1 else 0  # decimated: one record per write
            words[W_DRAINED] = done
            if torn:
                with contextlib.suppress(OSError):
                    os.ftruncate(out_fd, os.fstat(out_fd).st_size - torn)
        why = (
            f"writing {out_path} failed after {done} ticks: {exc.strerror or exc}; "
            "later ticks are not recorded"
        )
        raise _WriterFailedError(why, done) from None
    return done


def main(argv: list[str]) -> int:
    if len(argv) not in (4, 5):
        print(
            "usage: python -m hapticd.recording RING_FD OUT_FD OUT_PATH PARENT_PID [EVERY]",
            file=sys.stderr,
        )
        return 2
    # The daemon decides when recording ends: a Ctrl-C or a service stop sent to the whole
    # group must not cut the file short while the daemon is still flushing.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    drain(int(argv[0]), int(argv[1]), argv[2], int(argv[3]), int(argv[4]) if argv[4:] else 1)
    return 0
