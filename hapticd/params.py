"""The parameters a running hapticd lets you set, each declared once (docs/control.md).

Each entry names the parameter (its SI unit in the name), its unit, its kind
of value and range, its command-line alias, what it means, which part of the
servo loop holds it (``renderer``: the scene and rendering; ``safety``: the
safety chain) and the profile key it starts from. The control protocol checks
values against it, the loop dispatches on its owner, the command line derives
its aliases from it and the profile takes its ranges from it.

Standard library only: the control client (hapticd.control) imports this, and
an experiment script that talks to a daemon must load no numpy, pydantic or yaml.
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import dataclass
from typing import Any, Literal

# How deep a value given as text (the command line, the view's form) may nest: one level
# less than a control request (hapticd.protocol.MAX_DEPTH), which holds it.
VALUE_DEPTH = 7

# The allocators (docs/allocation.md): pinv, if, ef and adaptive are singularity-robust,
# the *_exact ones the seed's formulas. Recordings store an index into this order, then the
# installed plugins' (their meta "allocators" lists it), so a new one goes at the end. A
# lab's own: an entry point of hapticd.allocators (hapticd.allocation.plugins).
ALLOCATORS: dict[str, str] = {
    "pinv": "least squares over all contact forces",
    "if": "the internal forces (the squeeze) exactly where possible, then the rest",
    "ef": "the external wrench on the object in least squares",
    "adaptive": "(1 - alpha) if + alpha ef, alpha following the task (squeezing to lifting)",
    "pinv_exact": "the seed's pinv formula with numpy's pseudoinverse (for comparison)",
    "if_exact": "the seed's IF formula with numpy's pseudoinverse (for comparison)",
    "ef_exact": "the seed's EF formula with numpy's pseudoinverse (for comparison)",
}

# The lightest object (kg): at 1 ms ticks and the largest stiffness (1e5 N/m) on two
# fingers, 1 g needs about 28 of a free step's 64 substeps; far lighter masses overflow it.
MIN_MASS_KG = 1e-3

Kind = Literal["number", "friction", "choice", "directions"]
Owner = Literal["renderer", "safety"]
OWNERS: tuple[Owner, ...] = ("renderer", "safety")


def _plugin_name(value: object) -> bool:
    """Whether ``value`` could name an entry point: 1 to 100 printable characters, no
    spaces."""
    return (
        isinstance(value, str)
        and 0 < len(value) <= 100
        and value.isprintable()
        and (not any(c.isspace() for c in value))
    )


class ParamError(ValueError):
    """A parameter name or value that cannot be used; ``code`` is the control protocol's
    error code (``unknown_param``, ``bad_value`` or ``out_of_range``)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Param:
    """One settable parameter.

    ``lo``/``hi`` bound a number, or each coefficient of ``friction``; ``lo_open``
    excludes ``lo`` itself. ``max_per_finger`` bounds the directions per finger.
    ``profile_key`` is where a profile sets its starting value.
    """

    name: str
    kind: Kind
    unit: str  # SI symbol; "" when dimensionless
    doc: str
    owner: Owner
    profile_key: str
    alias: str | None = None
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple[str, ...] = ()
    # A choice whose owner takes installed plugins' names too (it checks them: the
    # renderer, for the allocator, against hapticd.allocation.plugins).
    plugins: bool = False
    max_per_finger: int | None = None

    def in_range(self, x: float) -> bool:
        """Whether the number ``x`` is within [lo, hi] (or (lo, hi])."""
        if self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo):
            return False
        return self.hi is None or x <= self.hi

    def range_text(self) -> str:
        """The range as written in the docs and messages, e.g. ``(0, 100000] N/m``."""
        if self.kind == "number":
            lo = "-inf" if self.lo is None else f"{self.lo:g}"
            hi = "inf" if self.hi is None else f"{self.hi:g}"
            text = f"{'(' if self.lo_open or self.lo is None else '['}{lo}, {hi}]"
            return f"{text} {self.unit}".rstrip()
        if self.kind == "friction":
            return f"[static, dynamic], {self.lo:g} <= dynamic <= static <= {self.hi:g}"
        if self.kind == "choice":
            more = ", or an installed allocator plugin's name" if self.plugins else ""
            return "one of " + ", ".join(f"`{c}`" for c in self.choices) + more
        return (
            f"per finger, a list of 0 to {self.max_per_finger} directions [x, y, z] "
            "(any length but zero; normalised)"
        )

    def check(self, value: Any) -> Any:
        """``value`` (as decoded from JSON) checked and normalised; ParamError if unusable.

        Numbers come back as float, friction as (static, dynamic), directions as
        per-finger lists of unit 3-tuples.
        """
        if self.kind == "number":
            x = _number(value, self.name)
            if not self.in_range(x):
                raise ParamError(
                    "out_of_range", f"{self.name} must be in {self.range_text()}, got {x:g}"
                )
            return x
        if self.kind == "friction":
            return self._friction(value)
        if self.kind == "choice":
            if self.plugins and _plugin_name(value) and value not in self.choices:
                return value  # its owner knows the plugins installed (and refuses others)
            if not (isinstance(value, str) and value in self.choices):
                raise ParamError(
                    "bad_value", f"{self.name} must be one of {list(self.choices)}, got {value!r}"
                )
            return value
        return self._directions(value)

    def parse(self, text: str) -> Any:
        """A value from the command line (not yet checked): a number, ``STATIC,DYNAMIC``,
        a name, or directions as JSON. ParamError (``bad_value``) if it does not parse."""
        try:
            if self.kind == "number":
                return float(text)
            if self.kind == "friction":
                return [float(v) for v in text.split(",")]
            if self.kind == "directions":
                if flow_nesting_beyond(text, VALUE_DEPTH) is not None:
                    raise RecursionError
                return json.loads(text)
        except RecursionError:  # checked before parsing; the parser's own limit a backstop
            raise ParamError(
                "bad_value",
                f"{self.name} must be {self.syntax}: nested at most {VALUE_DEPTH} levels deep",
            ) from None
        except ValueError as exc:  # json.JSONDecodeError is a ValueError
            detail = f" ({exc})" if self.kind == "directions" else ""
            raise ParamError(
                "bad_value", f"{self.name} must be {self.syntax}, got {text!r}{detail}"
            ) from None
        return text

    @property
    def syntax(self) -> str:
        """How to write a value on the command line."""
        return {
            "number": f"a number ({self.unit or 'dimensionless'})",
            "friction": "two numbers STATIC,DYNAMIC",
            "choice": "a name",
            "directions": "JSON, e.g. '[[[0,0,1]],[[0,0,1]]]'",
        }[self.kind]

    def _friction(self, value: Any) -> tuple[float, float]:
        if not (isinstance(value, list | tuple) and len(value) == 2):
            raise ParamError("bad_value", f"{self.name} must be [static, dynamic], got {value!r}")
        s, d = (_number(v, self.name) for v in value)
        code = "out_of_range" if not (self.in_range(s) and self.in_range(d)) else "bad_value"
        if code == "out_of_range" or d > s:
            raise ParamError(
                code,
                f"{self.name} needs {self.lo:g} <= dynamic <= static <= {self.hi:g}, "
                f"got [{s:g}, {d:g}]",
            )
        return (s, d)

    def _directions(self, value: Any) -> list[list[tuple[float, float, float]]]:
        msg = f"{self.name} must be a list per finger of [x, y, z] directions"
        if not isinstance(value, list) or not all(isinstance(ds, list) for ds in value):
            raise ParamError("bad_value", msg)
        out = []
        for i, ds in enumerate(value):
            if self.max_per_finger is not None and len(ds) > self.max_per_finger:
                raise ParamError(
                    "bad_value",
                    f"{self.name}: at most {self.max_per_finger} directions per finger, "
                    f"finger {i} has {len(ds)}",
                )
            finger = []
            for j, d in enumerate(ds):
                if not (isinstance(d, list) and len(d) == 3):
                    raise ParamError("bad_value", f"{msg}; finger {i} direction {j} is {d!r}")
                x, y, z = (_number(v, f"{self.name}[{i}][{j}]") for v in d)
                n = math.sqrt(x * x + y * y + z * z)
                if not math.isfinite(n):  # a square overflowed (|x| > 1e154)
                    n = math.hypot(x, y, z)
                if n < 1e-9:
                    raise ParamError("bad_value", f"{self.name}[{i}][{j}] is zero")
                finger.append((x / n, y / n, z / n))
            out.append(finger)
        return out


def flow_nesting_beyond(text: str, limit: int) -> int | None:
    """The 1-based line where flow collections (``[``, ``{``) in ``text`` first nest more
    than ``limit`` deep, or None; quoted scalars and comments are skipped. A YAML parser may
    refuse such a document on its own while reading ahead (libyaml does, in its own words),
    before the loader's depth check sees it: this names the cause the loader would have.
    JSON is such flow text too (its strings are double-quoted YAML scalars)."""
    if text.count("[") + text.count("{") <= limit:
        return None  # cheap: too few brackets to nest that deep
    depth = 0
    line = 1
    quote = ""
    prev = "\n"
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c == "\n":
            line += 1
        if quote:
            if c == "\\" and quote == '"':
                i += 1  # the escaped character
                line += text.startswith("\n", i)
            elif c == quote:
                if quote == "'" and text.startswith("''", i):
                    i += 1
                else:
                    quote = ""
        elif c in "'\"" and prev in " \t\n[{,:":
            quote = c
        elif c == "#" and prev in " \t\n":
            end = text.find("\n", i)
            i = n if end < 0 else end
            continue
        elif c in "[{":
            depth += 1
            if depth > limit:
                return line
        elif c in "]}":
            depth = max(depth - 1, 0)
        prev = c
        i += 1
    return None


def _number(value: Any, name: str) -> float:
    # JSON true/false decode to bool, a subclass of int: not a number here.
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ParamError("bad_value", f"{name} must be a finite number, got {value!r}")
    try:
        x = float(value)  # an integer beyond float's range: OverflowError
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        shown = "a huge integer" if isinstance(value, int) else repr(value)
        raise ParamError("bad_value", f"{name} must be a finite number, got {shown}")
    return x


PARAMS: dict[str, Param] = {
    p.name: p
    for p in (
        Param(
            "stiffness_n_per_m",
            "number",
            "N/m",
            "the object's contact stiffness",
            "renderer",
            "scene.object.stiffness_n_per_m",
            alias="stiffness",
            lo=0.0,
            lo_open=True,
            hi=1e5,
        ),
        Param(
            "damping_n_s_per_m",
            "number",
            "N s/m",
            "the object's contact damping",
            "renderer",
            "scene.object.damping_n_s_per_m",
            alias="damping",
            lo=0.0,
            hi=1e3,
        ),
        Param(
            "friction",
            "friction",
            "",
            "the object's Coulomb friction coefficients; [0, 0] turns friction off",
            "renderer",
            "scene.object.friction",
            lo=0.0,
            hi=5.0,
        ),
        Param(
            "mass_kg",
            "number",
            "kg",
            "the object's mass (moves a free object); at least 1 g, and no lighter than "
            "the free object's step integrates with its stiffness and damping (a live "
            "change says how light)",
            "renderer",
            "scene.object.mass_kg",
            alias="mass",
            lo=MIN_MASS_KG,
            hi=10.0,
        ),
        Param(
            "allocator",
            "choice",
            "",
            "how contact forces map onto the actuated directions (below)",
            "renderer",
            "rendering.allocator",
            choices=tuple(ALLOCATORS),
            plugins=True,
        ),
        Param(
            "force_limit_n",
            "number",
            "N",
            "force limit per finger; each finger gets the smaller of this and its device's limit",
            "safety",
            "safety.max_force_n",
            alias="force_limit",
            lo=0.0,
            lo_open=True,
            hi=50.0,
        ),
        Param(
            "actuated_directions",
            "directions",
            "",
            "the force directions each finger renders, in the profile's actuation frame; "
            "the number per finger cannot change live (it fixes the recording's layout: "
            "change it in the profile and reload)",
            "renderer",
            "fingers[].actuated_directions",
            alias="actuation",
            max_per_finger=3,
        ),
    )
}

ALIASES: dict[str, str] = {p.alias: p.name for p in PARAMS.values() if p.alias is not None}


def lookup(name_or_alias: str) -> Param:
    """The parameter called ``name_or_alias`` (its name or its CLI alias); ParamError
    (``unknown_param``) naming the parameters, with a guess, if there is none."""
    name = ALIASES.get(name_or_alias, name_or_alias)
    try:
        return PARAMS[name]
    except (KeyError, TypeError):
        raise ParamError("unknown_param", unknown_message(name_or_alias)) from None


def unknown_message(name: object) -> str:
    """Why ``name`` is not a parameter, and which are."""
    known = [*PARAMS, *ALIASES]
    close = difflib.get_close_matches(name, known, n=1) if isinstance(name, str) else []
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"unknown param {name!r}{hint}; params: {', '.join(PARAMS)}"


def markdown_table() -> str:
    """The parameter table of docs/control.md, then the allocator table."""
    rows = [
        "| param | CLI alias | value (SI) | set in | profile key | meaning |",
        "|---|---|---|---|---|---|",
    ]
    for p in PARAMS.values():
        alias = f"`{p.alias}`" if p.alias else ""
        rows.append(
            f"| `{p.name}` | {alias} | {p.range_text()} | {p.owner} | `{p.profile_key}` | {p.doc} |"
        )
    rows += ["", "| allocator | what it renders |", "|---|---|"]
    rows += [f"| `{name}` | {doc} |" for name, doc in ALLOCATORS.items()]
    return "\n".join(rows) + "\n"


if __name__ == "__main__":
    print(markdown_table(), end="")
