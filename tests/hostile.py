"""Hostile profiles, generated from the bundled ones, and a worker that checks them.

``generate()`` mutates each bundled profile (configs/*.yaml): every key the schema
knows (hapticd.profile's models, walked alongside the profile's data) gets values of
the wrong type, NaN, infinities and huge numbers; lists lose or gain a bracket level,
get too few or too many items; every mapping gets a duplicate key; and at every key
go deep nesting, anchors and aliases (an alias bomb among them), YAML tags, numbers
beyond range and odd strings. Whole-file mutations add non-UTF-8 bytes, other
encodings, NUL bytes, truncation, size and node-count bombs, documents that are not a
mapping. Every finger's trajectory is pointed at recordings that no device can play
(NaN and infinite positions, NaN, repeated and decreasing times, one sample, none). A case
is ``must_fail`` when the value is invalid for its key by
construction; the others may be accepted but must not crash or hang.

``python -m tests.hostile`` is the worker: it reads profile paths on stdin, runs
``hapticd check``'s code on each in this process and answers one JSON line per path
(exit code, stderr, and the traceback if anything escaped).
"""

from __future__ import annotations

import copy
import math
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel

ROOT = Path(__file__).resolve().parent.parent
BUNDLED = sorted((ROOT / "configs").glob("*.yaml"))
MARK = "HOSTILEVALUEMARK"
KEYMARK = "HOSTILEKEYMARK"


@dataclass(frozen=True)
class Case:
    """One hostile profile: ``name`` says what was done, ``key`` the key it was done to."""

    name: str
    data: bytes
    must_fail: bool
    key: str | None = None
    files: tuple[tuple[str, bytes], ...] = ()  # (name, bytes) written next to the profile


# -- the schema, walked alongside a profile's data --------------------------------------


@dataclass(frozen=True)
class Slot:
    """A place in a profile: its key path, what the schema wants there, whether None fits."""

    path: tuple[int | str, ...]
    kind: str  # float int bool str choice model seq device union
    optional: bool
    args: tuple[Any, ...] = ()  # seq: item annotations; union: members


def _unwrap(ann: Any) -> tuple[Any, bool]:
    """The annotation without Annotated and None, and whether None was allowed."""
    optional = False
    while True:
        origin = typing.get_origin(ann)
        if origin is typing.Annotated:
            ann = typing.get_args(ann)[0]
        elif origin in (typing.Union, types.UnionType):
            members = [a for a in typing.get_args(ann) if a is not type(None)]
            optional = optional or len(members) < len(typing.get_args(ann))
            if len(members) == 1:
                ann = members[0]
            else:
                return typing.Union[tuple(members)], optional  # noqa: UP007
        else:
            return ann, optional


def _kind(ann: Any) -> tuple[str, tuple[Any, ...]]:
    origin = typing.get_origin(ann)
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return "model", ()
    if ann in (float, int, bool, str):
        return ann.__name__, ()
    if origin is typing.Literal:
        return "choice", typing.get_args(ann)
    if origin is tuple:
        return "seq", typing.get_args(ann)
    if origin is typing.Union:
        members = typing.get_args(ann)
        if all(isinstance(m, type) and issubclass(m, BaseModel) for m in members):
            return "device", members
        return "union", members
    raise TypeError(f"no hostile values for {ann!r}")


def slots(model: type[BaseModel], data: Any, path: tuple = ()) -> Iterator[Slot]:
    """Every key of ``model`` (present in ``data`` or not) and every item of the lists
    present, recursing into the sub-models present."""
    for name, field in model.model_fields.items():
        if field.exclude:
            continue  # not a profile key (the loaded file's path)
        ann, optional = _unwrap(field.annotation)
        here = (*path, name)
        value = data.get(name) if isinstance(data, dict) else None
        yield from _slot_tree(ann, optional, here, value)


def _slot_tree(ann: Any, optional: bool, path: tuple, value: Any) -> Iterator[Slot]:
    ann, opt = _unwrap(ann)
    kind, args = _kind(ann)
    yield Slot(path, kind, optional or opt, args)
    if kind == "model" and isinstance(value, dict):
        yield from slots(ann, value, path)
    elif kind == "device" and isinstance(value, dict):
        chosen = [m for m in args if value.get("backend") in typing.get_args(_backend_of(m))]
        if chosen:
            yield from slots(chosen[0], value, path)
    elif kind == "seq" and isinstance(value, list):
        for i, item in enumerate(value):
            item_ann = (
                args[0] if len(args) == 2 and args[1] is Ellipsis else args[min(i, len(args) - 1)]
            )
            yield from _slot_tree(item_ann, False, (*path, i), item)


def _backend_of(model: type[BaseModel]) -> Any:
    return model.model_fields["backend"].annotation


# -- values -------------------------------------------------------------------------------

_NUMBERS_BAD = [math.nan, math.inf, -math.inf, 1e308, -1e308, 10**30, -(10**30)]
_CONTAINERS = [[1.0, 2.0], {"a": 1}]


def _values(slot: Slot) -> Iterator[tuple[str, Any]]:
    """(label, value) pairs, each invalid for ``slot`` by construction."""
    k = slot.kind
    if not slot.optional:
        yield "null", None
    if k in ("float", "int"):
        yield "a string", "12"
        yield "a bool", True
        yield from (("a list", _CONTAINERS[0]), ("a mapping", _CONTAINERS[1]))
        for v in _NUMBERS_BAD:
            yield repr(v), v
        if k == "int":
            yield "a float", 1.5
            yield "an integral float", 2.0
    elif k == "bool":
        yield from (("the string 'yes'", "yes"), ("1", 1), ("0.0", 0.0), ("a list", [True]))
        yield "a mapping", {"a": 1}
    elif k == "str":
        yield from (("a number", 1.5), ("an int", 7), ("a bool", False), ("a list", ["a"]))
        yield "a mapping", {"a": "b"}
    elif k == "choice":
        yield "an unknown name", "no-such-choice"
        yield from (("a number", 3.5), ("a bool", True), ("a list", ["x"]), ("a mapping", {}))
    elif k in ("model", "device"):
        yield from (("a string", "x"), ("a number", 1.0), ("a list", [{"a": 1}]))
        if k == "device":
            yield "an unknown backend", {"backend": "teleport"}
            yield "no backend", {"max_force_n": 1.0}
    elif k == "seq":
        yield from (("a string", "x"), ("a number", 1.0), ("a mapping", {"a": 1}))
    elif k == "union":  # scene.substeps: 1-64 or auto
        yield from (("a name", "many"), ("0", 0), ("65", 65), ("a float", 1.5), ("a bool", True))
        yield "a list", [1]


def _shapes(slot: Slot, value: Any) -> Iterator[tuple[str, Any]]:
    """Wrong list shapes for a list ``value`` at ``slot``: a bracket level missing or
    extra, too few or too many items."""
    if slot.kind != "seq" or not isinstance(value, list) or not value:
        return
    if all(isinstance(v, list) for v in value):
        yield "a bracket level missing", [x for v in value for x in v]
    elif all(isinstance(v, dict) for v in value):
        yield "a bracket level missing", value[0]
    else:
        yield "items of the wrong type (bracket level missing)", value[0]
    yield "an extra bracket level", [value]
    fixed = len(slot.args) != 2 or slot.args[1] is not Ellipsis
    if fixed:
        yield "too few items", value[:-1]
        yield "too many items", [*value, value[-1]]
    else:
        yield "far too many items", value * 10


# Raw YAML put where a value goes: refused by the loader at any key.
def _bomb() -> str:
    items = ["&b0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    items += [f"&b{i} [{', '.join([f'*b{i - 1}'] * 9)}]" for i in range(1, 9)]
    return "[" + ", ".join(items) + "]"


RAW_REFUSED = {
    "an alias bomb": _bomb(),
    "an anchor": "&anchor 1",
    "an undefined alias": "*nowhere",
    "5000 nested brackets": "[" * 5000 + "]" * 5000,
    "5000 nested mappings": "{a: " * 5000 + "1" + "}" * 5000,
    "a python tag": '!!python/object/apply:os.system ["true"]',
    "an unknown tag": "!hapticd 1",
    "an integer of 5000 digits": "1" + "0" * 4999,
    "a float beyond range": "1.0e+999",
    "a timestamp": "2001-12-14",
}
# Raw YAML that may be valid for some keys (strings): must not crash.
RAW_ODD = {
    "a NUL string": '"a\\0b"',
    "a 100k-character string": "x" * 100_000,
    "binary": "!!binary aGFwdGljZA==",
    "a set": "!!set {a, b}",
    "a path outside": "/etc/shadow",
}


# -- mutations ----------------------------------------------------------------------------


def _get(data: Any, path: tuple) -> Any:
    for p in path:
        data = data[p]
    return data


def _with(data: dict, path: tuple, value: Any) -> dict:
    out = copy.deepcopy(data)
    parent = _get(out, path[:-1])
    parent[path[-1]] = value
    return out


# libyaml's emitter when PyYAML has it: the pure-Python one took 8 s for the 11,000 cases.
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def _dump(data: Any) -> str:
    return yaml.dump(data, Dumper=_DUMPER, sort_keys=False, width=10**9, allow_unicode=True)


def _key_text(path: tuple) -> str:
    """The last named key of ``path``: what the error message must name."""
    return next(str(p) for p in reversed(path) if isinstance(p, str))


def _path_text(path: tuple) -> str:
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path).lstrip(".")


def _mappings(data: Any, path: tuple = ()) -> Iterator[tuple]:
    if isinstance(data, dict):
        yield path
        for k, v in data.items():
            yield from _mappings(v, (*path, k))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            yield from _mappings(v, (*path, i))


def generate(profiles: list[Path] = BUNDLED) -> Iterator[Case]:
    from hapticd.profile import Profile

    for src in profiles:
        text = src.read_text()
        data = yaml.safe_load(text)
        base = src.stem
        for slot in slots(Profile, data):
            where = f"{base}: {_path_text(slot.path)}"
            key = _key_text(slot.path)
            try:
                current = _get(data, slot.path)
            except (KeyError, IndexError):
                current = None
            for label, value in [*_values(slot), *_shapes(slot, current)]:
                doc = _dump(_with(data, slot.path, value)).encode()
                yield Case(f"{where} = {label}", doc, True, key)
            placeholder = _dump(_with(data, slot.path, MARK))
            assert placeholder.count(MARK) == 1
            for label, raw in RAW_REFUSED.items():
                doc = placeholder.replace(MARK, raw).encode()
                yield Case(f"{where} = {label}", doc, True, key)
            for label, raw in RAW_ODD.items():
                doc = placeholder.replace(MARK, raw).encode()
                yield Case(f"{where} = {label}", doc, slot.kind not in ("str", "seq"), key)
        for path in _mappings(data):
            mapping = _get(data, path)
            for k in mapping:
                dup = copy.deepcopy(data)
                target = _get(dup, path)
                target[KEYMARK] = copy.deepcopy(mapping[k])
                doc = _dump(dup).replace(KEYMARK, str(k)).encode()
                yield Case(f"{base}: {_path_text((*path, k))} given twice", doc, True, str(k))
            if path:
                merged = _dump(_with(data, (*path, "<<"), dict(mapping))).replace("'<<'", "<<")
                yield Case(f"{base}: a merge key in {_path_text(path)}", merged.encode(), True)
        yield from _trajectory_cases(base, data)
        yield from _file_mutations(base, text)


BAD_TRAJECTORY = "bad-trajectory.hrec"


def _bad_trajectories(fingers: list[str]) -> Iterator[tuple[str, bytes]]:
    """(label, recording bytes) of trajectories wrong for ``fingers[0]`` in one way each."""
    import tempfile

    import numpy as np

    from hapticd import recording

    n = 6
    for label in (
        "a NaN position",
        "an infinite position",
        "a NaN time",
        "a repeated time",
        "a decreasing time",
        "one sample",
        "no sample",
    ):
        t, x = np.arange(n) * 0.01, np.zeros((n, len(fingers), 3))
        if label == "a NaN position":
            x[3, 0, 0] = np.nan
        elif label == "an infinite position":
            x[2, 0, 2] = np.inf
        elif label == "a NaN time":
            t[4] = np.nan
        elif label == "a repeated time":
            t[2] = t[1]
        elif label == "a decreasing time":
            t[5] = 0.0
        elif label == "one sample":
            t, x = t[:1], x[:1]
        else:
            t, x = t[:0], x[:0]
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / BAD_TRAJECTORY
            fields = recording.trajectory_fields(len(fingers))
            recording.write(path, {"t": t, "device_pos": x}, fields, fingers)
            yield label, path.read_bytes()


def _trajectory_cases(base: str, data: dict) -> Iterator[Case]:
    """Each finger's trajectory replaced by one no device can play (``run`` refuses it,
    so ``check`` must)."""
    for i, finger in enumerate(data.get("fingers") or []):
        if not isinstance(finger.get("device"), dict) or "trajectory" not in finger["device"]:
            continue
        doc = _with(data, ("fingers", i, "device", "trajectory"), BAD_TRAJECTORY)
        doc["fingers"][i]["device"]["finger"] = "played"
        for label, blob in _bad_trajectories(["played"]):
            yield Case(
                f"{base}: fingers[{i}].device.trajectory: {label}",
                _dump(doc).encode(),
                True,
                "trajectory",
                ((BAD_TRAJECTORY, blob),),
            )


def _file_mutations(base: str, text: str) -> Iterator[Case]:
    raw = text.encode()
    n = len(raw)
    for frac in (0.0, 0.3, 0.6, 0.95):
        at = int(n * frac)
        yield Case(f"{base}: byte 0xff at {frac:.0%}", raw[:at] + b"\xff" + raw[at:], True)
    yield Case(f"{base}: latin-1 in a comment", b"# caf\xe9\n" + raw, True)
    yield Case(f"{base}: UTF-16", text.encode("utf-16"), True)
    yield Case(f"{base}: a NUL byte", raw.replace(b"\nname:", b"\n\x00name:", 1), True)
    yield Case(f"{base}: UTF-8 with a BOM", b"\xef\xbb\xbf" + raw, False)
    yield Case(f"{base}: CRLF line ends", raw.replace(b"\n", b"\r\n"), False)
    yield Case(f"{base}: tabs for indentation", raw.replace(b"\n  ", b"\n\t"), True)
    for frac in (0.1, 0.5, 0.9):
        yield Case(f"{base}: cut at {frac:.0%}", raw[: int(n * frac)], False)
    yield Case(f"{base}: 2 MiB of comment", raw + b"#" * (2 << 20) + b"\n", True)
    many = "[" + ", ".join(["0"] * 30_000) + "]"
    yield Case(f"{base}: 30,000 values", raw + f"extra: {many}\n".encode(), True)
    yield Case(f"{base}: a second document", raw + b"---\n" + raw, True)
    yield Case(f"{base}: a list", b"- " + raw.replace(b"\n", b"\n  "), True)
    yield Case(f"{base}: an integer key", raw + b"1: one\n", True)
    yield Case(f"{base}: a list as a key", raw + b"[a, b]: c\n", True)
    yield Case(f"{base}: a null key", raw + b"~: c\n", True)
    yield Case(f"{base}: a source key", raw + b"source: /etc/passwd\n", True, "source")
    for what in (b"", b"---\n", b"null\n", b"42\n", b"just text\n", b"[]\n", b"{}\n"):
        yield Case(f"a document of {what!r}", what, True)


# -- the worker ---------------------------------------------------------------------------


def _worker() -> None:  # pragma: no cover - runs in a subprocess
    import argparse
    import contextlib
    import io
    import json
    import resource
    import sys
    import time
    import traceback

    # A bomb that got through would be a MemoryError (a crash), not a swapping machine.
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, resource.RLIM_INFINITY))
    from hapticd.cli import build_parser, cmd_check

    def capture(fn: Any, *args: Any) -> tuple[Any, str, str | None]:
        out, err = io.StringIO(), io.StringIO()
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                return fn(*args), err.getvalue()[:20_000], None
        except BaseException:
            return None, err.getvalue()[:20_000], traceback.format_exc()

    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        path = line.strip()
        t0 = time.perf_counter()
        # cmd_check is what `hapticd check PATH` runs (less argument parsing).
        rc, err, crash = capture(cmd_check, argparse.Namespace(profile=Path(path)))
        res = {"rc": rc, "err": err, "crash": crash, "s": time.perf_counter() - t0}
        if rc == 0:
            # What check accepts must run: 50 ticks, unpaced, no socket.
            args = build_parser().parse_args(
                ["run", path, "--unpaced", "--duration", "0.05", "--no-socket", "-q"]
            )
            res["run_rc"], res["run_err"], res["run_crash"] = capture(args.func, args)
        print(json.dumps(res), flush=True)


if __name__ == "__main__":
    _worker()
