"""The servo loop's recorder: tick records into a shared-memory ring, written by another process.

See ``hapticd.recording.ring`` for the ring and the writer process, and
docs/recording.md for the file format.
"""

from __future__ import annotations

import mmap
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hapticd.recording import files, ring
from hapticd.recording.format import (
    CLOCK_WIDTH,
    Field,
    RecordingError,
    clock_offset,
    header_bytes,
    make_dtype,
)


class Recorder:
    """Records servo ticks with no file I/O on the loop's thread (see hapticd.recording.ring).

    The file is created and its header written here (``files.create``: confined to
    ``root`` when given, never through a link); a writer process appends the records
    that the loop puts into a shared-memory ring. In a paced run a full ring drops the
    tick (counted in ``dropped``) rather than make the loop wait; unpaced
    (``block_when_full``) the loop waits for the writer instead. ``record_every`` > 1: the
    writer keeps every such tick of the ring (the first, then each ``record_every``-th)
    and drops the others; the loop's side is the same.
    """

    def __init__(
        self,
        path: str | Path,
        fields: Sequence[Field],
        fingers: Sequence[str],
        meta: dict[str, Any] | None = None,
        *,
        capacity: int = 4096,
        block_when_full: bool = False,
        overwrite: bool = True,
        root: Path | None = None,
        record_every: int = 1,
    ) -> None:
        if int(record_every) < 1:
            raise ValueError(f"record_every must be 1 or more, got {record_every!r}")
        self.dtype = make_dtype(fields)
        out_fd, self.path = files.create(
            path,
            header_bytes(fields, fingers, meta, clock_place=True),
            overwrite=overwrite,
            root=root,
        )
        self._file_id = files.identity(out_fd)
        try:
            self._start_ring(
                capacity,
                block_when_full,
                "hapticd.recording",
                [str(out_fd), str(self.path), str(os.getpid()), str(int(record_every))],
                (out_fd,),
                clock_at=clock_offset(),
            )
        except BaseException:
            files.remove_if_ours(self.path, self._file_id)
            raise
        finally:
            os.close(out_fd)  # the writer has its own copy

    def _start_ring(
        self,
        capacity: int,
        block_when_full: bool,
        module: str,
        args: list[str],
        fds: tuple[int, ...],
        *,
        clock_at: int = 0,
    ) -> None:
        """Make the ring and start its consumer, ``python -m module RING_FD *args`` (given
        ``fds`` too); ``clock_at``: where the consumer writes the clock anchor in its file
        (0: nowhere)."""
        self.capacity = int(capacity)
        self.block_when_full = block_when_full
        self.dropped = 0
        self._n = 0
        self._drained = 0  # the most the writer has been seen to have drained
        self._closed = False
        self._final: dict[str, Any] | None = None
        size = ring.HEADER_BYTES + self.capacity * self.dtype.itemsize
        # An anonymous memory file: no name to leave behind in /dev/shm, whatever happens.
        ring_fd = os.memfd_create("hapticd-ring", os.MFD_CLOEXEC)
        self._ring_fd = ring_fd  # closed with the recorder
        try:
            os.ftruncate(ring_fd, size)
            self._mm = mmap.mmap(ring_fd, size)
            self._mm[:8] = ring.MAGIC
            words = np.ndarray((8,), "<u8", buffer=self._mm, offset=0)
            words[ring.W_ITEMSIZE // 8] = self.dtype.itemsize
            words[ring.W_CAPACITY // 8] = self.capacity
            self._words = words
            # Slots of raw bytes: a tick is recorded with one copy of its record.
            self._slots = np.ndarray(
                (self.capacity, self.dtype.itemsize),
                np.uint8,
                buffer=self._mm,
                offset=ring.HEADER_BYTES,
            )
            self._itemsize = self.dtype.itemsize
            # Every page of the slots written once now, here: the memory file's pages are
            # made on their first write, and a page first written in the loop cost that
            # tick a fault (several us, one tick in each page's few records).
            flat = self._slots.reshape(-1)
            flat[:: mmap.PAGESIZE] = 0
            flat[-1:] = 0
            base = memoryview(self._mm)
            self._word_view = base[: ring.HEADER_BYTES].cast("Q")
            self._slot_view = base[ring.HEADER_BYTES :]
            self._anchor_words = ring.Words(self._mm)
            self._anchor_words[ring.W_CLOCK_AT] = clock_at
            self._anchor_words[ring.W_CLOCK_WIDTH] = CLOCK_WIDTH
            # Released on close.
            self._ring_views = (self._word_view, self._slot_view, base, self._anchor_words)
            self._record: np.ndarray | None = None  # the last record appended, and its view
            self._record_view = memoryview(b"")
            self._proc = subprocess.Popen(
                [sys.executable, "-m", module, str(ring_fd), *args],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                pass_fds=(ring_fd, *fds),
            )
        except BaseException:
            os.close(ring_fd)
            raise

    def anchor(self, lsl_s: float, utc_unix_s: float) -> None:
        """Hand the consumer the loop's clock anchor (``ring.clock_anchor``: tick 0's due time
        on the LSL clock and in UTC, s); the writer fills the header's place with it."""
        self._anchor_words.set_anchor(lsl_s, utc_unix_s)

    def wait_running(self, timeout_s: float = 5.0) -> None:
        """Wait until the writer process has opened the file; RecordingError if it failed."""
        deadline = time.monotonic() + timeout_s
        while self.state == ring.STATE_STARTING:
            if self._proc.poll() is not None or time.monotonic() > deadline:
                break
            time.sleep(0.005)
        if self.state != ring.STATE_RUNNING:
            err = self.error or "the writer process did not start"
            self.discard()
            raise RecordingError(f"{self.path}: {err}")

    @property
    def state(self) -> int:
        return int(self._words[ring.W_STATE // 8])

    @property
    def error(self) -> str | None:
        """Why the recording is failing, if it is: the writer's own message, or that the
        writer process is gone (seen at once, not when the ring fills)."""
        if self._closed:
            return None if self._final is None else self._final["error"]
        if self.state == ring.STATE_FAILED:
            raw = bytes(self._mm[ring.ERROR_AT : ring.ERROR_AT + ring.ERROR_BYTES])
            return raw.rstrip(b"\x00").decode("utf-8", "replace")
        if not self._closed and self.state != ring.STATE_DONE:
            rc = self._proc.poll()
            if rc is not None:
                how = f"killed by signal {-rc}" if rc < 0 else f"exit status {rc}"
                return (
                    f"the writer process {self._proc.pid} ended ({how}); ticks after the "
                    f"{self.drained} written are not recorded"
                )
        return None

    @property
    def ticks(self) -> int:
        """Records handed to the ring so far."""
        return self._n

    @property
    def drained(self) -> int:
        """Records the writer has taken from the ring (into the file, or skipped by
        ``record_every``)."""
        return int(self._words[ring.W_DRAINED // 8])

    def append(self, record: np.ndarray) -> None:
        """Record one tick: ``record`` is its bytes, uint8 (itemsize,) in this recording's
        layout (the tick frame's ``recorded``; ``as_record`` makes one from values)."""
        n = self._n
        # The ring's words and slots through memoryviews: each word one aligned 8-byte load
        # or store, as the writer's (hapticd.recording.ring); a record one memcpy.
        words = self._word_view
        drained = words[4]  # W_DRAINED
        if drained > self._drained:
            self._drained = drained  # it only grows: a lower reading is stale, not a full ring
        if n - self._drained >= self.capacity and not (
            self.block_when_full and self._wait_for_room(n)
        ):
            self.dropped += 1
            words[6] = self.dropped  # W_DROPPED
            return
        if record is not self._record:  # the frame's bytes: the same array on every tick
            self._record, self._record_view = record, memoryview(record)
        at = (n % self.capacity) * self._itemsize
        self._slot_view[at : at + self._itemsize] = self._record_view
        self._n = n + 1
        words[3] = n + 1  # W_WRITTEN: published after the record is complete

    def as_record(self, values: Sequence[Any]) -> np.ndarray:
        """The bytes of a record holding ``values`` in field order (not for the servo loop)."""
        row = np.zeros(1, dtype=self.dtype)
        for name, v in zip(self.dtype.names or (), values, strict=True):
            row[name] = v
        return row.view(np.uint8)

    def _wait_for_room(self, n: int) -> bool:
        while n - self._drained >= self.capacity:
            if self._proc.poll() is not None or self.state == ring.STATE_FAILED:
                return False
            time.sleep(ring.POLL_S / 4)
            self._drained = max(self._drained, int(self._words[4]))
        return True

    def status(self) -> dict[str, Any]:
        """path, ticks (handed to the ring), written (in the file), dropped, error, writer_pid."""
        if self._final is not None:
            return dict(self._final)
        return {
            "path": str(self.path),
            "ticks": self._n,
            "written": self.drained,
            "dropped": self.dropped,
            "error": self.error,
            "writer_pid": self._proc.pid,
        }

    def close(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """Let the writer drain everything and exit; RecordingError if anything was lost."""
        if self._closed:
            return self.status()
        self._words[ring.W_CLOSED // 8] = 1
        try:
            self._proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        st = self.status()
        self._shutdown()
        self._final = st
        if st["error"] is not None:
            error = st["error"]
            raise RecordingError(
                error if error.startswith(str(self.path)) else f"{self.path}: {error}"
            )
        if st["written"] != st["ticks"]:
            raise RecordingError(
                f"{self.path}: the writer stopped after {st['written']} of {st['ticks']} ticks"
            )
        return st

    def discard(self) -> None:
        """Stop the writer and delete the file (a recording that never began)."""
        if not self._closed:
            self._final = {**self.status(), "error": "discarded"}
        self._shutdown()
        files.remove_if_ours(self.path, self._file_id)

    def _shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._proc.poll() is None:
            self._proc.kill()
        self._proc.wait()
        del self._slots, self._words
        for view in self._ring_views:
            view.release()  # a memoryview, or the anchor's Words
        self._mm.close()
        os.close(self._ring_fd)
