"""Recordings: every servo tick as one fixed-size binary record (format in docs/recording.md).

A file is ``MAGIC`` (8 bytes), a little-endian uint32 header length, a UTF-8 JSON
header (fields with dtype and shape, finger names, metadata, the clock anchor),
then records packed back to back. Records are appended and never rewritten, so a file cut
short (crash, ``kill -9``) still reads: a torn last record is dropped.

``read(path)`` returns a ``Recording``: a mapping of field name to numpy array
with the tick axis first (e.g. ``device_pos`` is (ticks, fingers, 3), m).
"""

from __future__ import annotations

import errno
import json
import os
import stat
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from hapticd.physics.frame import FIELDS, fields_for
from hapticd.protocol import too_deep

MAGIC = b"HAPTREC\x00"
FORMAT_VERSION = 1
_LEN = struct.Struct("<I")
MAX_HEADER_BYTES = 1 << 20
SUFFIX = ".hrec"
# The dtypes a recording may hold: those of the tick frame's fields (trajectories use <f8).
DTYPES = frozenset(f.dtype for f in FIELDS) | {"<f8"}
MAX_FIELDS = 1024
MAX_DIMS = 4
MAX_RECORD_BYTES = 1 << 20  # one tick's record
MAX_NAME_CHARS = 256
MAX_HEADER_DEPTH = 32  # JSON nesting of the header (it needs 4)
# A recording made by the loop keeps this many bytes at the start of its header for the
# clock anchor (``clock``), filled in when the loop reaches tick 0 (hapticd.recording.ring).
CLOCK_WIDTH = 160
CLOCK_PENDING = "not anchored: the loop did not reach its first tick"


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
    """The fields the servo loop records every tick: the tick frame's recorded fields."""
    return [
        Field(f.name, f.dtype, shape, f.unit)
        for f, shape in fields_for(n_fingers, n_actuators)
        if f.recorded
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
        clock: dict[str, Any] | None = None,
    ) -> None:
        self.path = path
        # Tick 0's due time on the LSL clock (``lsl_s``) and in UTC (``utc``, ``utc_unix_s``);
        # a tick's LSL time is ``lsl_s + t_wall``. None: a file from before the anchor, or
        # from a run that ended before its first tick.
        self.clock = clock
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
    if len(raw) > MAX_FIELDS:
        raise RecordingError(f"{where}: header has {len(raw)} fields; at most {MAX_FIELDS}")
    out: list[Field] = []
    seen: set[str] = set()
    for i, item in enumerate(raw):
        bad = f"{where}: header field {i} is malformed:"
        if not isinstance(item, dict):
            raise RecordingError(f"{bad} expected an object with name, dtype, shape, unit")
        name, dtype = item.get("name"), item.get("dtype")
        shape, unit = item.get("shape", []), item.get("unit", "")
        if not isinstance(name, str) or not 0 < len(name) <= MAX_NAME_CHARS:
            raise RecordingError(f"{bad} 'name' must be a string of 1 to {MAX_NAME_CHARS} chars")
        if name in seen:
            raise RecordingError(f"{bad} the name {name!r} is repeated")
        seen.add(name)
        if not isinstance(dtype, str) or dtype not in DTYPES:
            raise RecordingError(
                f"{bad} {name}: dtype {dtype!r} is not one a recording holds "
                f"(one of {', '.join(sorted(DTYPES))})"
            )
        if (
            not isinstance(shape, list)
            or len(shape) > MAX_DIMS
            or not all(type(n) is int and n >= 1 for n in shape)
        ):
            raise RecordingError(
                f"{bad} {name}: 'shape' must be a list of at most {MAX_DIMS} positive "
                f"integers, got {shape!r}"[:300]
            )
        if not isinstance(unit, str):
            raise RecordingError(f"{bad} {name}: 'unit' must be a string")
        out.append(Field(name, dtype, tuple(shape), unit))
    size = sum(np.dtype(f.dtype).itemsize * int(np.prod(f.shape, dtype=object)) for f in out)
    if size > MAX_RECORD_BYTES:
        raise RecordingError(
            f"{where}: a record of these fields would be {size} bytes; at most {MAX_RECORD_BYTES}"
        )
    return out


def _no_nan(word: str) -> float:
    raise ValueError(f"{word} is not valid JSON")


def read(path: str | Path) -> Recording:
    """Read a recording; a torn final record (crash mid-write) is dropped, not an error."""
    p = Path(path)
    try:
        blob = _read_regular(p)
    except OSError as exc:
        raise RecordingError(f"{p}: cannot read recording: {exc.strerror or exc}") from None
    if len(blob) < len(MAGIC) + _LEN.size or blob[: len(MAGIC)] != MAGIC:
        raise RecordingError(f"{p}: not a hapticd recording (bad magic; expected {MAGIC!r})")
    (hlen,) = _LEN.unpack_from(blob, len(MAGIC))
    start = len(MAGIC) + _LEN.size
    if hlen > MAX_HEADER_BYTES or start + hlen > len(blob):
        raise RecordingError(f"{p}: header length {hlen} is larger than the file allows")
    try:
        header = json.loads(blob[start : start + hlen].decode("utf-8"), parse_constant=_no_nan)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        # ValueError: JSONDecodeError or NaN/Infinity; RecursionError: nested far too deep.
        raise RecordingError(f"{p}: header is not valid JSON: {exc}") from None
    if not isinstance(header, dict):
        raise RecordingError(f"{p}: header must be a JSON object")
    if too_deep(header, MAX_HEADER_DEPTH):
        raise RecordingError(f"{p}: header nests deeper than {MAX_HEADER_DEPTH} levels")
    version = header.get("version")
    if type(version) is not int or version != FORMAT_VERSION:  # not True, not 1.0
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
    if not isinstance(meta, dict):
        raise RecordingError(f"{p}: header 'meta' must be a JSON object")
    return Recording(p, data, fields, fingers, meta, torn, _parse_clock(header, p))


def _parse_clock(header: dict[str, Any], p: Path) -> dict[str, Any] | None:
    """The header's clock anchor (``Recording.clock``); None when it has none (an older file)
    or holds the place of one never filled in."""
    clock = header.get("clock")
    if clock is None or isinstance(clock, str):
        return None
    if not (
        isinstance(clock, dict)
        and all(
            type(clock.get(k)) in (int, float) and np.isfinite(clock[k])
            for k in ("lsl_s", "utc_unix_s")
        )
        and isinstance(clock.get("utc"), str)
    ):
        raise RecordingError(
            f"{p}: header 'clock' must be an object with lsl_s and utc_unix_s (numbers, s) "
            "and utc (ISO 8601 text)"
        )
    return dict(clock)


def _read_regular(p: Path) -> bytes:
    """The bytes of the regular file ``p``, opened without blocking (a FIFO is refused)."""
    fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, "not a regular file")
        os.set_blocking(fd, True)
        with os.fdopen(os.dup(fd), "rb") as fh:
            return fh.read()
    finally:
        os.close(fd)


def header_bytes(
    fields: Sequence[Field],
    fingers: Sequence[str],
    meta: dict[str, Any] | None = None,
    *,
    clock_place: bool = False,
) -> bytes:
    """The start of a recording file: magic, header length, JSON header. ``clock_place``:
    the header starts with a place of ``CLOCK_WIDTH`` bytes for the clock anchor, at
    ``clock_offset()`` (filled in by the writer once the loop has started)."""
    bad = [f.dtype for f in fields if f.dtype not in DTYPES]
    if bad:
        raise RecordingError(f"dtypes {bad} are not ones a recording holds: {sorted(DTYPES)}")
    header = json.dumps(
        {
            **({"clock": CLOCK_PENDING.ljust(CLOCK_WIDTH - 2)} if clock_place else {}),
            "version": FORMAT_VERSION,
            "fields": [f.to_json() for f in fields],
            "fingers": list(fingers),
            "meta": meta or {},
        },
        sort_keys=True,
    ).encode("utf-8")
    if clock_place:
        assert header[clock_offset() - len(MAGIC) - _LEN.size :].startswith(b'"not anchored')
    return MAGIC + _LEN.pack(len(header)) + header


def clock_offset() -> int:
    """Where a header's place for the clock (``header_bytes(clock_place=True)``) begins in
    the file: ``clock`` sorts first among the header's keys, so its value follows
    ``{"clock": ``."""
    return len(MAGIC) + _LEN.size + len('{"clock": ')


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
        header = header_bytes(self.fields, fingers, meta)
        self._f: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._f.write(header)
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
