"""The servo loop's recorder: tick records into a shared-memory ring, written by another process.

See ``hapticd.recording.ring`` for the ring and the writer process, and
docs/recording.md for the file format.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hapticd.recording import ring
from hapticd.recording.format import Field, RecordingError, RecordingWriter, make_dtype


def _ring_dir() -> Path:
    shm = Path("/dev/shm")
    return shm if shm.is_dir() and os.access(shm, os.W_OK) else Path(tempfile.gettempdir())


class Recorder:
    """Records servo ticks with no file I/O on the loop's thread (see hapticd.recording.ring).

    The header is written here; a writer process appends the records that the
    loop puts into a shared-memory ring. In a paced run a full ring drops the
    tick (counted in ``dropped``) rather than make the loop wait; unpaced
    (``block_when_full``) the loop waits for the writer instead.
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
    ) -> None:
        self.path = Path(path)
        if not overwrite and self.path.exists():
            raise RecordingError(f"{self.path}: exists; not overwriting it")
        try:
            RecordingWriter(self.path, fields, fingers, meta).close()
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot create: {exc.strerror or exc}") from None
        self.dtype = make_dtype(fields)
        self.capacity = int(capacity)
        self.block_when_full = block_when_full
        self.dropped = 0
        self._n = 0
        self._drained = 0  # the most the writer has been seen to have drained
        self._closed = False
        size = ring.HEADER_BYTES + self.capacity * self.dtype.itemsize
        fd, ring_path = tempfile.mkstemp(prefix=f"hapticd-ring-{os.getpid()}-", dir=_ring_dir())
        self._ring_path = ring_path
        try:
            os.ftruncate(fd, size)
            self._mm = mmap.mmap(fd, size)
        finally:
            os.close(fd)
        self._mm[:8] = ring.MAGIC
        # Native uint64 at an aligned offset: each word is one 8-byte load or store (ring.py).
        words = np.ndarray((8,), "=u8", buffer=self._mm, offset=0)
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
        self._proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "hapticd.recording",
                ring_path,
                str(self.path),
                str(os.getpid()),
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
        )

    def wait_running(self, timeout_s: float = 5.0) -> None:
        """Wait until the writer process has opened the file; RecordingError if it failed."""
        deadline = time.monotonic() + timeout_s
        while self.state == ring.STATE_STARTING:
            if self._proc.poll() is not None or time.monotonic() > deadline:
                break
            time.sleep(0.005)
        if self.state != ring.STATE_RUNNING:
            err = self.error or "the writer process did not start"
            self._shutdown()
            raise RecordingError(f"{self.path}: {err}")

    @property
    def state(self) -> int:
        return int(self._words[ring.W_STATE // 8])

    @property
    def error(self) -> str | None:
        """The writer's error message, if it failed."""
        if self.state != ring.STATE_FAILED:
            return None
        raw = bytes(self._mm[ring.ERROR_AT : ring.ERROR_AT + ring.ERROR_BYTES])
        return raw.rstrip(b"\x00").decode("utf-8", "replace")

    @property
    def ticks(self) -> int:
        """Records handed to the ring so far."""
        return self._n

    @property
    def drained(self) -> int:
        """Records the writer has written to the file."""
        return int(self._words[ring.W_DRAINED // 8])

    def append(self, record: np.ndarray) -> None:
        """Record one tick: ``record`` is its bytes, uint8 (itemsize,) in this recording's
        layout (the tick frame's ``recorded``; ``as_record`` makes one from values)."""
        n = self._n
        words = self._words
        drained = int(words[4])  # W_DRAINED
        if drained > self._drained:
            self._drained = drained  # it only grows: a lower reading is stale, not a full ring
        full = n - self._drained >= self.capacity
        if full and not (self.block_when_full and self._wait_for_room(n)):
            self.dropped += 1
            words[6] = self.dropped  # W_DROPPED
            return
        self._slots[n % self.capacity] = record
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
        if st["error"] is not None:
            raise RecordingError(f"{self.path}: {st['error']}")
        if st["written"] != st["ticks"]:
            raise RecordingError(
                f"{self.path}: the writer stopped after {st['written']} of {st['ticks']} ticks"
            )
        return st

    def _shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._proc.poll() is None:
            self._proc.kill()
        self._proc.wait()
        del self._slots, self._words
        self._mm.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._ring_path)
