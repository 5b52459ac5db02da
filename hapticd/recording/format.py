"""Recordings: every servo tick as one fixed-size binary record (format in docs/recording.md).

A file is ``MAGIC`` (8 bytes), a little-endian uint32 header length, a UTF-8 JSON
header (fields with dtype and shape, finger names, metadata), then records
packed back to back. Records are appended and never rewritten, so a file cut
short (crash, ``kill -9``) still reads: a torn last record is dropped.

``read(path)`` returns a ``Recording``: a mapping of field name to numpy array
with the tick axis first (e.g. ``device_pos`` is (ticks, fingers, 3), m).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from hapticd.frame import fields_for

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
