"""Allocators from a lab's own package: entry points of the group ``hapticd.allocators``.

An entry point names a plain function ``f(G, M_a, lam) -> lam_a`` in the seed's notation:
G (6, 3p), M_a (3p, r), lam (3p,) N in, lam_a (r,) N out, written in the Python numba
compiles. Its name is the method's name everywhere (profiles, ``set``, recordings,
analyses). The tick runs it compiled (hapticd.allocation.native) or, where it cannot be
compiled, as Python; either way through contact onset and the safety chain.

Optional attributes of the function: ``linear`` (True: lam_a is linear in lam, which
``hapticd allocators check`` then tests) and its docstring's first line (the listing's).

The discovery's rules are hapticd_drivers.plugins' (refused by name: an entry point that
cannot be imported or has the wrong shape, a name two packages register, a built-in's
name). The shape is tried on a grasp of two contacts before the plugin is registered.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import Any

import numpy as np
from hapticd_drivers.plugins import Plugin, Problem, Registry

from hapticd import params
from hapticd.allocation import kernels

GROUP = "hapticd.allocators"
# The group of the compiler of a plugin (hapticd.physics.native.compile_plugin: numba),
# which sits above allocation: allocation knows only the group's name.
PLUGIN_COMPILERS = "hapticd.plugin_compilers"
BUILTIN: tuple[str, ...] = tuple(params.ALLOCATORS)


# Each plugin's compiled form, or why it cannot be compiled, by handle.
_NATIVES: dict[int, Any] = {}


def _probe() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grasp to try a plugin on: two contacts on the x axis 0.1 m apart, squeezing with
    2 N, each rendering along x (G (6, 6), M_a (6, 2), lam (6,) N)."""
    points = np.array([[-0.05, 0.0, 0.0], [0.05, 0.0, 0.0]])
    G = np.zeros((6, 6))
    for i, (x, y, z) in enumerate(points):
        G[:3, 3 * i : 3 * i + 3] = np.eye(3)
        G[3:, 3 * i : 3 * i + 3] = [[0, -z, y], [z, 0, -x], [-y, x, 0]]
    M = np.zeros((6, 2))
    M[0, 0] = M[3, 1] = 1.0
    lam = np.array([2.0, 0.0, 0.0, -2.0, 0.0, 0.0])
    return G, M, lam


def python_function(obj: Any) -> Callable[..., Any]:
    """The Python function of an entry point's object (a numba dispatcher's own)."""
    return getattr(obj, "py_func", obj)


def check_plugin(name: str, obj: Any) -> str | None:
    """Why an entry point's object is no allocator (None: it is one): a function taking
    G, M_a and lam whose result on a two-contact grasp is r finite forces."""
    fn = python_function(obj)
    if not inspect.isfunction(fn):
        return f"expected a function f(G, M_a, lam) -> lam_a, got {obj!r}"
    try:
        inspect.signature(fn).bind(None, None, None)
    except TypeError:
        return f"{fn.__name__}{inspect.signature(fn)} does not take (G, M_a, lam)"
    G, M, lam = _probe()
    try:
        with np.errstate(all="ignore"):
            out = np.asarray(fn(G, M, lam), dtype=float)
    except Exception as exc:  # a plugin may fail in any way: its message is the reason
        return f"it raised {type(exc).__name__}: {exc} on a two-contact grasp"
    if out.shape != (M.shape[1],):
        return (
            f"on a grasp with G {G.shape}, M_a {M.shape}, lam {lam.shape} it returned shape "
            f"{out.shape}, expected ({M.shape[1]},): one force per actuated direction"
        )
    if not np.all(np.isfinite(out)):
        return f"it returned {out.tolist()} (not finite) on a two-contact grasp"
    return None


_REGISTRY = Registry(GROUP, BUILTIN, check_plugin)


def reload_plugins() -> None:
    """Find the installed allocators again (the next lookup does)."""
    _REGISTRY.reload()


def problems() -> list[Problem]:
    """The ``hapticd.allocators`` entry points refused, with why."""
    return _REGISTRY.problems()


def names() -> tuple[str, ...]:
    """Every allocator's name: the built-ins (hapticd.params.ALLOCATORS), then the installed
    ones. Recordings store an index into this order (their meta "allocators" lists it)."""
    return (*BUILTIN, *sorted(_REGISTRY.plugins()))


def get(name: str) -> Plugin | None:
    """The installed allocator ``name`` (None: a built-in's name, or none installed)."""
    return None if name in BUILTIN else _REGISTRY.plugins().get(name)


def is_known(name: str) -> bool:
    """Whether ``name`` is a built-in or an installed allocator (plugins are looked for
    only when it is no built-in)."""
    return name in BUILTIN or get(name) is not None


def unknown(name: object) -> str:
    """Why ``name`` is no allocator: the refused plugin's package, entry point and reason,
    or the names there are."""
    refused = _REGISTRY.refused(str(name))
    if refused is not None:
        return f"allocator {name!r} is refused: {refused.message()}"
    return (
        f"unknown allocator {name!r}; expected one of {list(names())} (a lab's own: an "
        f"entry point of {GROUP}, docs/allocation.md)"
    )


def package_of(name: str) -> str:
    """The package an allocator comes from: hapticd for a built-in."""
    plugin = get(name)
    return "hapticd" if plugin is None else plugin.package


def describe(name: str) -> str:
    """A plugin's one-line description (its docstring's first line), or a built-in's."""
    plugin = get(name)
    if plugin is None:
        return params.ALLOCATORS.get(name, "")
    doc = inspect.getdoc(python_function(plugin.obj)) or ""
    return doc.splitlines()[0] if doc else ""


def linear(name: str) -> bool:
    """Whether the plugin claims lam_a linear in lam (its function's ``linear``)."""
    plugin = get(name)
    return plugin is not None and getattr(plugin.obj, "linear", False) is True


def handle(name: str) -> int:
    """The kernel's handle of the installed allocator ``name`` (KeyError: none)."""
    return kernels.register_plugin(python_function(_REGISTRY.plugins()[name].obj))


def native_address(h: int) -> tuple[int, str | None]:
    """Handle ``h``'s plugin compiled, once per process, by the compiler the install
    provides (entry point group PLUGIN_COMPILERS: hapticd.physics.native's): the address
    the compiled tick calls, or 0 and why it cannot be compiled."""
    if h not in _NATIVES:
        compilers = sorted(entry_points(group=PLUGIN_COMPILERS), key=lambda e: e.name)
        if not compilers:
            _NATIVES[h] = f"no compiler is installed (entry points {PLUGIN_COMPILERS})"
        else:
            try:
                _NATIVES[h] = compilers[0].load()(kernels.plugin_function(h))
            except Exception as exc:  # numba's typing errors, or no numba: said, as Python
                _NATIVES[h] = _reason(exc)
    got = _NATIVES[h]
    return (0, got) if isinstance(got, str) else (got.address, None)


def _reason(exc: Exception) -> str:
    """numba's error in a line: its first that names the problem (numba wraps it in lines
    of the pipeline's passes and the source's place)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    told = [ln for ln in lines if not ln.startswith(("Failed in", "During", "File ", "^"))]
    text = (told or lines or [""])[0]
    for escape in ("\x1b[1m", "\x1b[0m"):  # numba's highlighting
        text = text.replace(escape, "")
    return f"{type(exc).__name__}: {text}"


def listing() -> list[dict[str, Any]]:
    """Every allocator, built-in and installed, with its package and description; then the
    refused entry points (``problem``: why)."""
    rows: list[dict[str, Any]] = [
        {"name": n, "package": package_of(n), "doc": describe(n), "problem": None} for n in names()
    ]
    rows += [
        {"name": p.name, "package": ", ".join(p.packages), "problem": p.message()}
        for p in problems()
    ]
    return rows
