"""Tidy tables written as CSV, Parquet or MATLAB files, with the same columns in each.

A ``Table`` is its columns in order: each a name, a kind (``int``, ``float`` or
``text``) and its values (a 1-D numpy array: numbers as float64 with NaN for a missing
value, text as an object array with None for one). The writers keep every column and its
order; how each format holds a missing value and a kind:

| kind | CSV | Parquet (pyarrow) | MAT (scipy.io, v5) |
|---|---|---|---|
| int | digits; empty: missing | int64; null: missing | double; NaN: missing |
| float | shortest round-trip digits; empty | float64; null | double; NaN |
| text | the text; empty | string; null | cell of char; '' |

A MAT file holds the table as a struct of column vectors (``struct2table`` makes a
MATLAB table of it) and ``columns``, a cell of the true column names in order: a name
MATLAB cannot take as a field (a dot, a leading digit, over 63 characters) has each
character outside ``[A-Za-z0-9_]`` replaced by ``_`` (and ``x`` put before a leading
digit or underscore) in the struct; ``columns`` says which it was.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

Kind = Literal["int", "float", "text"]
FormatName = Literal["csv", "parquet", "mat"]
FORMATS: tuple[str, ...] = get_args(FormatName)
SUFFIXES = {"csv": ".csv", "parquet": ".parquet", "mat": ".mat"}
MAT_NAME_CHARS = 63  # MATLAB's longest field name


class TableFormatError(ValueError):
    """A format that is not one of FORMATS; the message names it and the choices."""


@dataclass(frozen=True)
class Column:
    """One column: its name, kind and values ((rows,) float64 with NaN, or object)."""

    name: str
    kind: Kind
    values: np.ndarray


Table = list[Column]


def check_format(fmt: str) -> str:
    """``fmt`` if it is one of FORMATS; TableFormatError naming it and the choices."""
    if fmt not in FORMATS:
        raise TableFormatError(
            f"export format {fmt!r} is not one hapticd writes: one of {', '.join(FORMATS)}"
        )
    return fmt


def from_rows(
    rows: Sequence[Mapping[str, Any]], names: Sequence[str], kinds: Mapping[str, Kind]
) -> Table:
    """A table of ``rows`` (dicts; a missing key or None: a missing value) with the columns
    ``names``, each of kind ``kinds[name]`` (text when not given)."""
    out: Table = []
    for name in names:
        kind = kinds.get(name, "text")
        vals = [r.get(name) for r in rows]
        if kind == "text":
            arr = np.array([None if v is None else str(v) for v in vals] or [], dtype=object)
        else:
            arr = np.array([math.nan if v is None else float(v) for v in vals], dtype=float)
        out.append(Column(name, kind, arr))
    return out


def to_rows(table: Table) -> list[dict[str, Any]]:
    """The table's rows as dicts: ints as int, floats as float, missing values None."""
    n = len(table[0].values) if table else 0
    cols = [(c.name, _cells(c)) for c in table]
    return [{name: cells[i] for name, cells in cols} for i in range(n)]


def _cells(c: Column) -> list[Any]:
    if c.kind == "text":
        return [None if v is None else str(v) for v in c.values]
    vals = c.values.tolist()
    if c.kind == "int":
        return [None if math.isnan(v) else int(v) for v in vals]
    return [None if math.isnan(v) else v for v in vals]


def write(table: Table, out: str | Path, fmt: str, *, name: str = "table") -> None:
    """Write ``table`` to the file ``out`` as ``fmt`` (csv, parquet, mat; ``name``: the MAT
    file's struct). TableFormatError for another format; ImportError saying how to
    install pyarrow for parquet; OSError."""
    check_format(fmt)
    if fmt == "csv":
        write_csv(table, out)
    elif fmt == "parquet":
        write_parquet(table, out)
    else:
        write_mat(table, out, name)


def write_csv(table: Table, out: str | Path | Any) -> None:
    """CSV: a header row of the names, then one row per table row (missing: empty).
    ``out``: a path or an open text file."""
    if hasattr(out, "write"):
        _csv_to(table, out)
        return
    with open(out, "w", newline="", encoding="utf-8") as fh:
        _csv_to(table, fh)


def _csv_to(table: Table, fh: Any) -> None:
    writer = csv.writer(fh, lineterminator="\n")
    writer.writerow([c.name for c in table])
    cols = [_cells(c) for c in table]
    writer.writerows(zip(*cols, strict=True) if cols else [])


def write_parquet(table: Table, out: str | Path) -> None:
    """Parquet, with pyarrow (the ``export`` extra): int64, float64 and string columns,
    nulls for the missing values."""
    pa, pq = _pyarrow()
    types = {"int": pa.int64(), "float": pa.float64(), "text": pa.string()}
    arrays = []
    for c in table:
        if c.kind == "text":
            arrays.append(pa.array(list(c.values), type=pa.string()))
        else:
            missing = np.isnan(c.values)
            vals = np.where(missing, 0, c.values)
            if c.kind == "int":
                vals = vals.astype(np.int64)
            arrays.append(pa.array(vals, type=types[c.kind], mask=missing))
    pq.write_table(pa.Table.from_arrays(arrays, names=[c.name for c in table]), str(out))


def _pyarrow() -> tuple[Any, Any]:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise ImportError(
            "the parquet format needs pyarrow: pip install 'hapticd[export]' (or pip install "
            "pyarrow); csv and mat need nothing more"
        ) from None
    return pa, pq


def mat_names(names: Iterable[str]) -> list[str]:
    """The struct field names MATLAB takes for ``names``, in order, each unique."""
    out: list[str] = []
    for name in names:
        field = re.sub(r"[^A-Za-z0-9_]", "_", name)
        if not field or not field[0].isalpha():
            field = "x" + field
        field = field[:MAT_NAME_CHARS]
        base, k = field, 2
        while field in out:
            tail = f"_{k}"
            field, k = base[: MAT_NAME_CHARS - len(tail)] + tail, k + 1
        out.append(field)
    return out


def write_mat(table: Table, out: str | Path, name: str = "table") -> None:
    """MATLAB (v5, scipy.io.savemat): the struct ``name`` of column vectors (ints and
    floats as double, NaN missing; text as a cell, '' missing) and ``columns``, the true
    names."""
    from scipy.io import savemat

    fields = mat_names(c.name for c in table)
    struct: dict[str, np.ndarray] = {}
    for field, c in zip(fields, table, strict=True):
        if c.kind == "text":
            struct[field] = np.array(["" if v is None else str(v) for v in c.values], dtype=object)
        else:
            struct[field] = np.asarray(c.values, dtype=float)
    savemat(
        str(out),
        {name: struct, "columns": np.array([c.name for c in table], dtype=object)},
        oned_as="column",
        long_field_names=True,
        do_compression=True,
    )


def read(path: str | Path, fmt: str, *, name: str = "table") -> dict[str, list[Any]]:
    """A table written by ``write``, read back: {column: values} in order (ints int,
    floats float, text str, missing None). For the tests and for checking a file."""
    check_format(fmt)
    if fmt == "csv":
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
        header, body = rows[0], rows[1:]
        return {h: [r[i] if r[i] != "" else None for r in body] for i, h in enumerate(header)}
    if fmt == "parquet":
        _, pq = _pyarrow()
        return pq.read_table(str(path)).to_pydict()
    from scipy.io import loadmat

    m = loadmat(str(path), simplify_cells=True)
    names = [str(n) for n in np.atleast_1d(m["columns"])]
    struct = m[name]
    out: dict[str, list[Any]] = {}
    for field, col in zip(mat_names(names), names, strict=True):
        vals = np.atleast_1d(struct[field])
        out[col] = [
            (None if isinstance(v, np.ndarray) and v.size == 0 else v.item())
            if isinstance(v, np.ndarray | np.generic)
            else (v or None)
            for v in vals
        ]
        out[col] = [None if isinstance(v, float) and math.isnan(v) else v for v in out[col]]
    return out
