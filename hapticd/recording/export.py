"""Exports of a recording for other tools: CSV (a column per scalar) and MCAP (Foxglove).

Both are offline conversions of a read ``Recording``; neither runs in the daemon.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hapticd.physics.frame import FIELDS
from hapticd.recording.format import Field, Recording

# Per-finger fields (a first axis of one entry per finger, labelled by finger name): as
# the tick frame declares them (hapticd.physics.frame).
PER_FINGER = frozenset(f.name for f in FIELDS if f.shape[:1] == ("F",))
_DECLARED = {f.name: f.shape for f in FIELDS}


def _labels(symbol: int | str, n: int, last: bool, fingers: list[str]) -> list[str]:
    """Labels of an axis of ``n`` entries declared as ``symbol`` ("F", "r" or a size); an
    axis whose size is not what the declaration says (a file from elsewhere) by index."""
    if symbol == "F" and n == len(fingers):
        return list(fingers)
    if symbol == 3 and n == 3 and last:
        return ["x", "y", "z"]
    return [str(j) for j in range(n)]


def csv_columns(rec: Recording) -> list[str]:
    """Column names of a CSV export: one per scalar, e.g. ``device_pos.thumb.x`` (units in
    docs/recording.md), from the tick frame's declaration of each field: a finger axis
    uses the finger names, a last axis of 3 x/y/z, any other axis its index
    (``object_rot.2.y`` is R[2, 1], ``lam_a.0`` the first actuated direction). A field
    the frame does not declare reads its axes by size."""
    cols: list[str] = []
    for f in rec.fields:
        declared = _DECLARED.get(f.name, ())
        symbols = declared if len(declared) == len(f.shape) else f.shape
        names = [f.name]
        for axis_i, (symbol, n) in enumerate(zip(symbols, f.shape, strict=True)):
            labels = _labels(symbol, n, axis_i == len(f.shape) - 1, rec.fingers)
            names = [f"{a}.{b}" for a in names for b in labels]
        cols += names
    return cols


def flat_values(
    arrays: Mapping[str, np.ndarray] | np.ndarray, fields: Sequence[Field], ticks: int
) -> np.ndarray:
    """The ``fields`` of ``ticks`` ticks (``arrays``: a Recording, or records of its dtype)
    as one float64 array (ticks, scalars), its columns in ``csv_columns``' order."""
    # Explicit widths: with 0 ticks (a run killed right after it began) -1 is ambiguous.
    return np.concatenate(
        [
            np.asarray(arrays[f.name], dtype=float).reshape(ticks, math.prod(f.shape))
            for f in fields
        ],
        axis=1,
    )


# Ticks written between two calls of an export's ``progress``.
PROGRESS_CHUNK = 10_000

Progress = Callable[[int, int], None]  # (ticks done, ticks in all)


def export_csv(rec: Recording, out: str | Path, progress: Progress | None = None) -> int:
    """Write ``rec`` as CSV (a header row, then one row per tick); returns the rows written.
    ``progress(done, total)`` is called after each chunk of ticks."""
    cols = csv_columns(rec)
    flat = flat_values(rec, rec.fields, rec.ticks)
    assert flat.shape[1] == len(cols)
    # The allocator column holds names (meta.allocators), not the recorded indices.
    names = rec.meta.get("allocators")
    at = cols.index("allocator") if "allocator" in cols and isinstance(names, list) else None
    with open(out, "w", encoding="utf-8") as fh:
        fh.write(",".join(cols) + "\n")
        for start in range(0, rec.ticks, PROGRESS_CHUNK):
            chunk = flat[start : start + PROGRESS_CHUNK]
            if at is None:
                np.savetxt(fh, chunk, delimiter=",", fmt="%.17g")
            else:
                buf = io.StringIO()
                np.savetxt(buf, chunk, delimiter=",", fmt="%.17g")
                for line in buf.getvalue().splitlines():
                    row = line.split(",")
                    v = float(row[at])
                    k = int(v) if math.isfinite(v) and v == int(v) else -1
                    row[at] = str(names[k]) if 0 <= k < len(names) else row[at]
                    fh.write(",".join(row) + "\n")
            if progress is not None:
                progress(min(start + PROGRESS_CHUNK, rec.ticks), rec.ticks)
    return rec.ticks


def _tick_message(rec: Recording, i: int) -> dict[str, Any]:
    """Tick ``i`` as nested JSON: per-finger fields keyed by finger, 3-vectors as x/y/z."""
    msg: dict[str, Any] = {}
    F = len(rec.fingers)
    for f in rec.fields:
        v = rec[f.name][i]
        if f.name in PER_FINGER and f.shape[:1] == (F,):
            msg[f.name] = {name: _jsonable(v[j]) for j, name in enumerate(rec.fingers)}
        else:
            msg[f.name] = _jsonable(v)
    return msg


def _jsonable(v: np.ndarray | np.generic) -> Any:
    a = np.asarray(v)
    if a.shape == (3,):
        return {"x": float(a[0]), "y": float(a[1]), "z": float(a[2])}
    if a.ndim == 0:
        return a.item()
    return a.tolist()


def export_mcap(
    rec: Recording,
    out: str | Path,
    topic: str = "/hapticd/tick",
    progress: Progress | None = None,
) -> int:
    """Write ``rec`` as MCAP: one JSON message per tick on ``topic``, stamped with the
    tick's nominal time, for viewing and plotting in Foxglove. Needs ``pip install mcap``
    (the ``mcap`` extra). Returns the messages written; ``progress(done, total)`` is
    called after each chunk of ticks."""
    try:
        from mcap.writer import Writer
    except ImportError as exc:
        raise RuntimeError(
            "MCAP export needs the mcap package: pip install 'hapticd[mcap]'"
        ) from exc
    with open(out, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="hapticd")
        schema = w.register_schema(
            name="hapticd.Tick",
            encoding="jsonschema",
            data=json.dumps(
                {
                    "type": "object",
                    "title": "hapticd.Tick",
                    "description": "one servo tick; units in hapticd docs/recording.md",
                }
            ).encode(),
        )
        channel = w.register_channel(
            topic=topic,
            message_encoding="json",
            schema_id=schema,
            metadata={"fingers": ",".join(rec.fingers)},
        )
        w.add_metadata("hapticd", {k: str(v) for k, v in rec.meta.items()})
        t = rec["t"] if "t" in rec else np.arange(rec.ticks, dtype=float)
        for i in range(rec.ticks):
            ns = round(float(t[i]) * 1e9)
            w.add_message(
                channel_id=channel,
                log_time=ns,
                publish_time=ns,
                sequence=i,
                data=json.dumps(_tick_message(rec, i), separators=(",", ":")).encode(),
            )
            if progress is not None and ((i + 1) % PROGRESS_CHUNK == 0 or i + 1 == rec.ticks):
                progress(i + 1, rec.ticks)
        w.finish()
    return rec.ticks
