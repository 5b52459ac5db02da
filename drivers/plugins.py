"""Plugins from other packages, found through entry points (``importlib.metadata``).

One discovery for every kind hapticd takes from a lab's own package: device backends
(group ``hapticd.backends``, the registry's) and procedures (``hapticd.procedures``,
hapticd.experiment's). The rules are the same for each kind:

- an entry point that cannot be loaded, or whose object has the wrong shape (the
  kind's ``check`` says what is wrong), is not registered: its problem names the
  package and the entry point;
- a name that two packages register is registered for neither: the problem names both;
- a built-in's name cannot be taken: the problem names the package.

Standard library only (this package never imports ``hapticd``).
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Plugin:
    """One registered plugin: its name (the entry point's), the package (distribution)
    that provides it, the entry point's value ("module:attribute") and the object."""

    name: str
    package: str
    value: str
    obj: Any


@dataclass(frozen=True)
class Problem:
    """An entry point that was refused: its group, name, the package(s) and why."""

    group: str
    name: str
    packages: tuple[str, ...]
    value: str
    reason: str

    def message(self) -> str:
        pkgs = " and ".join(f"package {p!r}" for p in self.packages)
        return f"{self.group} entry point {self.name!r} ({self.value}) of {pkgs}: {self.reason}"


def _package(ep: importlib.metadata.EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return str(dist.name) if dist is not None and dist.name else "an unknown package"


def discover(
    group: str,
    builtins: Collection[str],
    check: Callable[[str, Any], str | None],
) -> tuple[dict[str, Plugin], list[Problem]]:
    """Every entry point of ``group``, loaded and checked: the plugins registered (by
    name) and the problems of those refused. ``check(name, obj)`` returns why ``obj`` is
    not of the kind (None: it is). Nothing is raised: a broken plugin must not stop the
    built-ins or the other plugins from working."""
    eps = importlib.metadata.entry_points(group=group)
    # The same distribution seen twice on the path (an editable and a target install)
    # is one registration.
    by_name: dict[str, dict[tuple[str, str], importlib.metadata.EntryPoint]] = {}
    for ep in eps:
        by_name.setdefault(ep.name, {})[(_package(ep), ep.value)] = ep
    found: dict[str, Plugin] = {}
    problems: list[Problem] = []
    for name in sorted(by_name):
        entries = by_name[name]
        packages = tuple(sorted({pkg for pkg, _ in entries}))
        value = ", ".join(sorted({v for _, v in entries}))
        if name in builtins:
            problems.append(
                Problem(
                    group, name, packages, value,
                    f"{name!r} is a built-in's name; a plugin cannot shadow it (rename the "
                    "entry point)",
                )
            )  # fmt: skip
            continue
        if len(entries) > 1:
            problems.append(
                Problem(
                    group, name, packages, value,
                    "more than one package registers this name: neither is used (uninstall "
                    "one, or rename its entry point)",
                )
            )  # fmt: skip
            continue
        ((package, value), ep) = next(iter(entries.items()))
        try:
            obj = ep.load()
        except Exception as exc:  # a plugin's import may fail in any way: it is reported
            problems.append(
                Problem(
                    group, name, packages, value,
                    f"cannot be imported: {type(exc).__name__}: {exc}",
                )
            )  # fmt: skip
            continue
        try:
            why = check(name, obj)
        except Exception as exc:  # a shape check that trips over the object: wrong shape
            why = f"{type(exc).__name__}: {exc}"
        if why:
            problems.append(Problem(group, name, packages, value, f"has the wrong shape: {why}"))
            continue
        found[name] = Plugin(name, package, value, obj)
    return found, problems


class Registry:
    """One kind's plugins, found on first use (``discover``) and again after ``reload``."""

    def __init__(
        self, group: str, builtins: Collection[str], check: Callable[[str, Any], str | None]
    ) -> None:
        self.group, self.builtins, self.check = group, builtins, check
        self._found: dict[str, Plugin] | None = None
        self._problems: list[Problem] = []

    def plugins(self) -> dict[str, Plugin]:
        """The registered plugins by name (found now if not yet)."""
        if self._found is None:
            self._found, self._problems = discover(self.group, self.builtins, self.check)
        return self._found

    def problems(self) -> list[Problem]:
        """The entry points refused, with why."""
        self.plugins()
        return list(self._problems)

    def refused(self, name: str) -> Problem | None:
        """The refusal of the entry point ``name`` (None: not refused)."""
        return next((p for p in self.problems() if p.name == name), None)

    def reload(self) -> None:
        """Find the installed plugins again (the next lookup does)."""
        self._found = None
