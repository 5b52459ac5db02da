"""Recordings: every servo tick as one fixed-size binary record (format in docs/recording.md).

A file is ``MAGIC`` (8 bytes), a little-endian uint32 header length, a UTF-8 JSON
header (fields with dtype and shape, finger names, metadata), then records
packed back to back. Records are appended and never rewritten, so a file cut
short (crash, ``kill -9``) still reads: a torn last record is dropped.

``read(path)`` returns a ``Recording``: a mapping of field name to numpy array
with the tick axis first (e.g. ``device_pos`` is (ticks, fingers, 3), m).
"""

from __future__ import annotations

import contextlib
import json
import mmap
import os
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from hapticd import ring

MAGIC = b"HAPTREC\x00"
FORMAT_VERSION = 1
_LEN = struct.Struct("<I")
MAX_HEADER_BYTES = 1 << 20
SUFFIX = ".hrec"


class RecordingError(ValueError):
    """A recording that cannot be read; the message names the file and the problem."""


@dataclass(frozen=True)
class Field:
    """One recorded quantity: name, numpy dtype string (little-endian), per-tick shape, unit."""

    name: str
    dtype: str
    shape: tuple[int, ...] = ()
    unit: str = ""

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "dtype": self.dtype,
            "shape": list(self.shape),
            "unit": self.unit,
        }


def loop_fields(n_fingers: int, n_actuators: int) -> list[Field]:
    """The fields the servo loop records every tick (see docs/recording.md)."""
    F = n_fingers
    return [
        Field("t", "<f8", (), "s"),
        Field("t_wall", "<f8", (), "s"),
        Field("compute_s", "<f8", (), "s"),
        Field("device_pos", "<f8", (F, 3), "m"),
        Field("device_vel", "<f8", (F, 3), "m/s"),
        Field("proxy_pos", "<f8", (F, 3), "m"),
        Field("in_contact", "u1", (F,), ""),
        Field("contact_force", "<f8", (F, 3), "N"),
        Field("rendered_force", "<f8", (F, 3), "N"),
        Field("device_force", "<f8", (F, 3), "N"),
        Field("lam_a", "<f8", (n_actuators,), "N"),
        Field("residual_internal", "<f8", (), "N"),
        Field("residual_external", "<f8", (), "N"),
        Field("residual_total", "<f8", (), "N"),
        Field("amplification", "<f8", (), ""),
        Field("alpha", "<f8", (), ""),
        Field("env_force", "<f8", (F, 3), "N"),
        Field("object_pos", "<f8", (3,), "m"),
        Field("object_rot", "<f8", (3, 3), ""),
        Field("fault", "u1", (), ""),
        Field("control_seq", "<u4", (), ""),
        Field("stiffness_n_per_m", "<f8", (), "N/m"),
        Field("mass_kg", "<f8", (), "kg"),
        Field("allocator", "u1", (), ""),
    ]


def trajectory_fields(n_fingers: int) -> list[Field]:
    """The fields of a trajectory that a replay device plays: time and positions."""
    return [Field("t", "<f8", (), "s"), Field("device_pos", "<f8", (n_fingers, 3), "m")]


def make_dtype(fields: Sequence[Field]) -> np.dtype:
    """Packed structured dtype of one record."""
    return np.dtype([(f.name, f.dtype, f.shape) for f in fields])


class Recording(Mapping[str, np.ndarray]):
    """A read recording: field name -> array (ticks first); plus fingers, fields, meta."""

    def __init__(
        self,
        path: Path,
        data: np.ndarray,
        fields: list[Field],
        fingers: list[str],
        meta: dict[str, Any],
        torn_bytes: int,
    ) -> None:
        self.path = path
        self._data = data
        self.fields = fields
        self.fingers = fingers
        self.meta = meta
        self.torn_bytes = torn_bytes

    def __getitem__(self, key: str) -> np.ndarray:
        try:
            return self._data[key]
        except ValueError:
            raise KeyError(key) from None

    def __iter__(self) -> Iterator[str]:
        return iter(f.name for f in self.fields)

    def __len__(self) -> int:
        return len(self.fields)

    @property
    def ticks(self) -> int:
        return int(self._data.shape[0])

    def units(self) -> dict[str, str]:
        return {f.name: f.unit for f in self.fields}


def _parse_fields(raw: object, where: str) -> list[Field]:
    if not isinstance(raw, list) or not raw:
        raise RecordingError(f"{where}: header 'fields' must be a non-empty list")
    out: list[Field] = []
    for i, item in enumerate(raw):
        try:
            f = Field(
                str(item["name"]),
                str(item["dtype"]),
                tuple(int(s) for s in item.get("shape", [])),
                str(item.get("unit", "")),
            )
            np.dtype(f.dtype)
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"{where}: header field {i} is malformed: {exc}") from None
        out.append(f)
    return out


def read(path: str | Path) -> Recording:
    """Read a recording; a torn final record (crash mid-write) is dropped, not an error."""
    p = Path(path)
    try:
        blob = p.read_bytes()
    except OSError as exc:
        raise RecordingError(f"{p}: cannot read recording: {exc.strerror or exc}") from None
    if len(blob) < len(MAGIC) + _LEN.size or blob[: len(MAGIC)] != MAGIC:
        raise RecordingError(f"{p}: not a hapticd recording (bad magic; expected {MAGIC!r})")
    (hlen,) = _LEN.unpack_from(blob, len(MAGIC))
    start = len(MAGIC) + _LEN.size
    if hlen > MAX_HEADER_BYTES or start + hlen > len(blob):
        raise RecordingError(f"{p}: header length {hlen} is larger than the file allows")
    try:
        header = json.loads(blob[start : start + hlen].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordingError(f"{p}: header is not valid JSON: {exc}") from None
    if not isinstance(header, dict):
        raise RecordingError(f"{p}: header must be a JSON object")
    version = header.get("version")
    if version != FORMAT_VERSION:
        raise RecordingError(f"{p}: format version {version!r} is not supported (expected 1)")
    fields = _parse_fields(header.get("fields"), str(p))
    dtype = make_dtype(fields)
    body = memoryview(blob)[start + hlen :]
    n = len(body) // dtype.itemsize
    torn = len(body) - n * dtype.itemsize
    data = np.frombuffer(body[: n * dtype.itemsize], dtype=dtype).copy()
    fingers = header.get("fingers", [])
    if not isinstance(fingers, list) or not all(isinstance(f, str) for f in fingers):
        raise RecordingError(f"{p}: header 'fingers' must be a list of names")
    meta = header.get("meta", {})
    return Recording(p, data, fields, fingers, meta if isinstance(meta, dict) else {}, torn)


class RecordingWriter:
    """Appends whole records to a recording file. Not for the servo loop's thread: see Recorder."""

    def __init__(
        self,
        path: str | Path,
        fields: Sequence[Field],
        fingers: Sequence[str],
        meta: dict[str, Any] | None = None,
    ) -> None:
        self.path = Path(path)
        self.fields = list(fields)
        self.dtype = make_dtype(self.fields)
        header = json.dumps(
            {
                "version": FORMAT_VERSION,
                "fields": [f.to_json() for f in self.fields],
                "fingers": list(fingers),
                "meta": meta or {},
            },
            sort_keys=True,
        ).encode("utf-8")
        self._f: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._f.write(MAGIC + _LEN.pack(len(header)) + header)
        self._f.flush()
        self.rows_written = 0

    def write(self, rows: np.ndarray) -> None:
        """Append records (a structured array of this writer's dtype) and flush to the OS."""
        if rows.dtype != self.dtype:
            raise TypeError("rows do not have this recording's dtype")
        self._f.write(memoryview(np.ascontiguousarray(rows)).cast("B"))
        self._f.flush()
        self.rows_written += len(rows)

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write(
    path: str | Path,
    arrays: Mapping[str, np.ndarray],
    fields: Sequence[Field],
    fingers: Sequence[str],
    meta: dict[str, Any] | None = None,
) -> None:
    """Write a whole recording from per-field arrays (ticks first)."""
    dtype = make_dtype(fields)
    n = len(arrays[fields[0].name])
    rows = np.zeros(n, dtype=dtype)
    for f in fields:
        rows[f.name] = arrays[f.name]
    with RecordingWriter(path, fields, fingers, meta) as w:
        w.write(rows)


def _ring_dir() -> Path:
    shm = Path("/dev/shm")
    return shm if shm.is_dir() and os.access(shm, os.W_OK) else Path(tempfile.gettempdir())


class Recorder:
    """Records servo ticks with no file I/O on the loop's thread (see hapticd.ring).

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
        words = np.ndarray((8,), "<u8", buffer=self._mm, offset=0)
        words[ring.W_ITEMSIZE // 8] = self.dtype.itemsize
        words[ring.W_CAPACITY // 8] = self.capacity
        self._words = words
        self._rows = np.ndarray(
            (self.capacity,), self.dtype, buffer=self._mm, offset=ring.HEADER_BYTES
        )
        self._cols = [self._rows[f.name] for f in fields]
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "hapticd.ring", ring_path, str(self.path), str(os.getpid())],
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

    def append(self, values: Sequence[Any]) -> None:
        """Record one tick; ``values`` in field order (called by the servo loop)."""
        n = self._n
        words = self._words
        full = n - int(words[4]) >= self.capacity  # W_DRAINED
        if full and not (self.block_when_full and self._wait_for_room(n)):
            self.dropped += 1
            words[6] = self.dropped  # W_DROPPED
            return
        i = n % self.capacity
        for col, v in zip(self._cols, values, strict=True):
            col[i] = v
        self._n = n + 1
        words[3] = n + 1  # W_WRITTEN: published after the record is complete

    def _wait_for_room(self, n: int) -> bool:
        while n - int(self._words[4]) >= self.capacity:
            if self._proc.poll() is not None or self.state == ring.STATE_FAILED:
                return False
            time.sleep(ring.POLL_S / 4)
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
        self._cols = []
        del self._rows, self._words
        self._mm.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._ring_path)
