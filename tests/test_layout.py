"""The import rules of docs/architecture.md, read from every module's source (ast).

Every module of hapticd/ is in exactly one category below, and drivers/ (installed as
hapticd_drivers) is one category as a whole:

- pure: numpy in, numpy out; no I/O, no configuration, no logging;
- runtime: the servo loop and what it runs on; no configuration (it gets built objects);
- service: configuration, the daemon, the command line, recordings; anything goes;
- client: what an experiment script loads to talk to a daemon; the standard library only;
- view: ``hapticd view``, a separate process and a client of the daemon: the client
  modules, the standard library and the WebSocket library; nothing the daemon loads;
- drivers: the device layer; nothing of hapticd.

Across those, the packages are layered (LAYERS): a module imports only its own layer's and
lower layers' modules, anywhere in its source (function-local imports too).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# A name ending in ".*" is a whole package (its __init__ and every module under it).
CATEGORIES: dict[str, set[str]] = {
    "pure": {
        "hapticd.allocation.*",
        "hapticd.analysis.examples",
        "hapticd.analysis.pipeline",
        "hapticd.loop",
        "hapticd.loop.mount",
        "hapticd.loop.pulse",
        "hapticd.loop.trajectory",
        "hapticd.physics",
        "hapticd.physics.dynamics",
        "hapticd.physics.frame",
        "hapticd.physics.kernels",
        "hapticd.physics.live",
        "hapticd.physics.passivity",
        "hapticd.physics.render",
        "hapticd.physics.safety",
        "hapticd.physics.scene",
        "hapticd.physics.stages",
        # The tick's stage modules and the layout generated from their declarations.
        "hapticd.physics.tick.*",
        "hapticd.psychophysics",
    },
    "runtime": {
        "hapticd.loop.commands",
        "hapticd.loop.device_bank",
        "hapticd.loop.event_ring",
        "hapticd.loop.pacing",
        "hapticd.loop.realtime",
        "hapticd.loop.servo",
        "hapticd.loop.stats",
        # Compiles hapticd.physics.kernels (numba) and finds its cache folder.
        "hapticd.physics.jit",
        # Compiles an allocator plugin (numba) and calls it from the compiled tick.
        "hapticd.physics.native",
    },
    "service": {
        "hapticd.__main__",
        # Pipeline.from_profile reads the profile through hapticd.daemon.build.
        "hapticd.analysis",
        "hapticd.analysis.report",  # hapticd analyze's tables, JSON and plot
        "hapticd.cli.*",
        # The session built from a profile (build), the control server, the run's
        # summary and hapticd bringup (the rig checked before a subject touches it).
        "hapticd.daemon.*",
        # Experiment files, trial plan, trial store, analysis, the model observer (it
        # builds a run from the profile) and hapticd study (process pool, Dask); the
        # runner (hapticd.experiment.runner) is also in SOCKET_CLIENTS below.
        "hapticd.experiment.*",
        "hapticd.plot",  # hapticd plot's figures (matplotlib inside its functions only)
        "hapticd.profile",  # the profile's schema, read by the daemon, analysis, experiments
        "hapticd.recording.*",
    },
    "client": {
        "hapticd",  # the package's __init__: every import of hapticd.control loads it
        "hapticd.control",
        "hapticd.events",
        "hapticd.params",
        "hapticd.protocol",
    },
    # hapticd view: a client of the control socket serving a web page over WebSocket.
    "view": {"hapticd.view.*"},
    "drivers": {"hapticd_drivers.*"},
}

# Third-party packages a pure module may use.
PURE_THIRD_PARTY = {"numpy", "scipy"}
# What one pure module may use besides, and why. The allocators' registry finds a lab's
# allocators through the one discovery of plugins (hapticd_drivers.plugins: entry points'
# metadata, read once and only when a name is no built-in's; never on the tick).
PURE_EXCEPTIONS = {"hapticd.allocation.plugins": {"hapticd_drivers.plugins"}}
# Standard-library modules that do I/O, talk to other processes or log: none in pure code.
IO_STDLIB = {
    "asyncio",
    "csv",
    "ctypes",
    "io",
    "json",
    "logging",
    "mmap",
    "multiprocessing",
    "os",
    "pathlib",
    "pickle",
    "select",
    "selectors",
    "shutil",
    "signal",
    "socket",
    "sqlite3",
    "subprocess",
    "tempfile",
    "threading",
}
# Service modules that reach a daemon only through its control socket (hapticd.control):
# never the loop, the device layer or the daemon's internals.
SOCKET_CLIENTS = {"hapticd.experiment.runner"}
LOOP_SIDE = {"hapticd.daemon", "hapticd.daemon.build", "hapticd_drivers"}
# What the servo loop is built from, never what it imports.
CONFIGURATION = {"pydantic", "yaml", "hapticd.profile", "hapticd.daemon.build", "hapticd.daemon"}
FRONT = {"hapticd.cli", "hapticd.daemon"}


def _modules() -> dict[str, Path]:
    """Every module: its import name and its file."""
    out = {}
    for folder, package in (("hapticd", "hapticd"), ("drivers", "hapticd_drivers")):
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = [package, *path.relative_to(ROOT / folder).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


MODULES = _modules()


def _categories(module: str) -> list[str]:
    def matches(pattern: str) -> bool:
        if pattern.endswith(".*"):
            package = pattern[:-2]
            return module == package or module.startswith(package + ".")
        return module == pattern

    return [c for c, patterns in CATEGORIES.items() if any(matches(p) for p in patterns)]


def _type_checking_only(tree: ast.Module) -> set[int]:
    """The ids of the import nodes inside ``if TYPE_CHECKING:`` blocks (never run)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            out.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    return out


def _imports(module: str, *, run_only: bool = False) -> set[str]:
    """The modules ``module`` imports, anywhere in its source (also inside functions and,
    unless ``run_only``, TYPE_CHECKING blocks), as absolute dotted names: ``from a import
    b`` is a.b when that is a module of ours, else a. (Parent packages load too: the
    package __init__s are categorised like any module.)"""
    path = MODULES[module]
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    skip = _type_checking_only(tree) if run_only else set()
    out: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            if base == "__future__":
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                out.add(sub if sub in MODULES else base)
    return out


def _top(name: str) -> str:
    return name.partition(".")[0]


def _ours(name: str) -> bool:
    return _top(name) in ("hapticd", "hapticd_drivers")


def _within(name: str, prefixes: set[str]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _in(category: str) -> list[str]:
    return [m for m in MODULES if _categories(m) == [category]]


def test_every_module_is_in_exactly_one_category():
    problems = []
    for module in MODULES:
        cats = _categories(module)
        if not cats:
            problems.append(
                f"{module} has no category: add it to one of CATEGORIES in "
                f"tests/test_layout.py ({', '.join(CATEGORIES)}; docs/architecture.md "
                "says what each may import)"
            )
        elif len(cats) > 1:
            problems.append(f"{module} is in more than one category: {cats}")
    stale = [
        p for ps in CATEGORIES.values() for p in ps if not p.endswith(".*") and p not in MODULES
    ]
    assert not problems and not stale, "\n".join(problems + [f"no module {p}" for p in stale])


# The families the code is grouped by (docs/architecture.md, "Layout"): each subpackage
# holds the categories it may, and the top level only the client, the entry point and
# the modules several families use: the profile, the figures, the psychometrics.
FAMILIES = {
    "hapticd.physics": {"pure", "runtime"},  # the tick's physics, and its compiler
    "hapticd.loop": {"pure", "runtime"},  # the servo loop, its devices' bank, pacing
    "hapticd.daemon": {"service"},  # the service: profile, build, session, server
}
TOP_LEVEL = {"hapticd.__main__", "hapticd.plot", "hapticd.profile", "hapticd.psychophysics"}


def test_each_family_holds_only_its_own_categories():
    wrong = []
    for module in MODULES:
        family = next((f for f in FAMILIES if module.startswith(f + ".")), None)
        if family is not None and not set(_categories(module)) <= FAMILIES[family]:
            wrong.append(f"{module}: {_categories(module)} in {family}")
    assert not wrong, "\n".join(wrong)


def test_the_top_level_holds_the_client_and_the_packages():
    flat = {m for m in MODULES if m.startswith("hapticd.") and m.count(".") == 1}
    flat = {m for m in flat if MODULES[m].name != "__init__.py"}
    client = {m for m in flat if _categories(m) == ["client"]}
    assert flat - client == TOP_LEVEL


@pytest.mark.parametrize("module", _in("pure"))
def test_pure_modules_do_no_io_and_read_no_configuration(module):
    bad = set()
    for name in _imports(module):
        top = _top(name)
        if name in PURE_EXCEPTIONS.get(module, ()):
            continue
        if _ours(name):
            # Only other pure modules, and the parameter spec (plain data, no I/O).
            allowed = _categories(name) == ["pure"] or name == "hapticd.params"
        else:
            allowed = top in PURE_THIRD_PARTY or (
                top in sys.stdlib_module_names and top not in IO_STDLIB
            )
        if not allowed:
            bad.add(name)
    tree = ast.parse(MODULES[module].read_text())
    calls = {
        n.func.id
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
    }
    if "open" in calls:
        bad.add("open()")
    assert not bad, f"{module} is pure (numpy in, numpy out) but uses {sorted(bad)}"


@pytest.mark.parametrize("module", _in("runtime"))
def test_the_loop_reads_no_configuration(module):
    bad = {n for n in _imports(module) if _within(n, CONFIGURATION | FRONT)}
    assert not bad, f"{module} runs the loop, which gets built objects, but imports {sorted(bad)}"


@pytest.mark.parametrize("module", _in("client"))
def test_the_client_side_imports_only_the_standard_library(module):
    client = set(_in("client"))
    bad = set()
    for name in _imports(module):
        if _ours(name):
            if name not in client:
                bad.add(name)
        elif _top(name) not in sys.stdlib_module_names:
            bad.add(name)
    assert not bad, (
        f"{module} is loaded by experiment scripts (standard library only) but imports "
        f"{sorted(bad)}"
    )


@pytest.mark.parametrize("module", sorted(SOCKET_CLIENTS))
def test_socket_clients_talk_to_the_daemon_only_through_its_socket(module):
    assert module in MODULES, f"no module {module}"
    bad = {
        n
        for n in _imports(module)
        if _within(n, LOOP_SIDE) or (_ours(n) and _categories(n) == ["runtime"])
    }
    assert not bad, (
        f"{module} is a client of the control socket but imports the loop's side: {sorted(bad)}"
    )


# What the view may import besides the standard library and the client modules.
VIEW_THIRD_PARTY = {"websockets"}


@pytest.mark.parametrize("module", _in("view"))
def test_the_view_imports_the_client_the_standard_library_and_websockets(module):
    allowed_ours = set(_in("client")) | set(_in("view"))
    bad = set()
    for name in _imports(module):
        if _ours(name):
            if name not in allowed_ours:
                bad.add(name)
        elif _top(name) not in sys.stdlib_module_names | VIEW_THIRD_PARTY:
            bad.add(name)
    assert not bad, (
        f"{module} is hapticd view (a control-socket client: the client modules, the "
        f"standard library and {sorted(VIEW_THIRD_PARTY)}) but imports {sorted(bad)}"
    )


def test_the_daemon_and_the_command_line_load_no_view_and_no_websockets():
    code = (
        "import sys; import hapticd.cli, hapticd.daemon.server, hapticd.daemon.session; "
        "print('hapticd.view' in sys.modules, 'websockets' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert out.stdout.split() == ["False", "False"], out.stdout + out.stderr


@pytest.mark.parametrize("module", _in("drivers"))
def test_drivers_import_nothing_of_hapticd(module):
    bad = {n for n in _imports(module) if _top(n) == "hapticd"}
    assert not bad, f"{module} is in the device layer, which never imports hapticd: {sorted(bad)}"


def test_an_experiment_script_loads_no_numpy_pydantic_or_yaml():
    code = (
        "import sys; from hapticd.control import ControlClient; "
        "print('numpy' in sys.modules, 'pydantic' in sys.modules, 'yaml' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert out.stdout.split() == ["False", "False", "False"], out.stdout + out.stderr


# The packages from the lowest layer up (docs/architecture.md, "Layers"): a module may
# import modules of its own layer and of the layers below, never of a layer above. A name
# ending in ".*" is a whole package, any other one module.
LAYERS: list[set[str]] = [
    # the device layer, and the client: the parameters' and events' specs, the protocol
    {"hapticd_drivers.*", "hapticd", "hapticd.params", "hapticd.events", "hapticd.protocol",
     "hapticd.control"},
    {"hapticd.allocation.*", "hapticd.psychophysics"},  # the math: G, M_a, allocators
    {"hapticd.physics.*"},  # the tick's physics, which allocates with hapticd.allocation
    {"hapticd.recording.*"},  # the frame's records on disk
    {"hapticd.loop.*"},  # the servo loop: devices, physics, recording
    {"hapticd.profile", "hapticd.plot"},  # the profile's schema; figures of recordings
    {"hapticd.daemon.*"},  # the service built from a profile
    {"hapticd.analysis.*", "hapticd.experiment.*", "hapticd.view.*"},  # what runs on it
    {"hapticd.cli.*"},  # the command line
    {"hapticd.__main__"},
]  # fmt: skip


def _layer(module: str) -> int | None:
    """The index in LAYERS of ``module``'s layer (None: none)."""
    for i, patterns in enumerate(LAYERS):
        for p in patterns:
            package = p[:-2] if p.endswith(".*") else None
            if module == p or (package and (module == package or module.startswith(package + "."))):
                return i
    return None


def test_every_module_is_in_a_layer():
    assert not [m for m in MODULES if _layer(m) is None]
    stale = [p for ps in LAYERS for p in ps if not p.endswith(".*") and p not in MODULES]
    assert not stale, stale


def test_no_module_imports_a_higher_layer():
    """Physics imports allocation, never the reverse; the loop imports physics, the daemon
    the loop, and so on up (LAYERS)."""
    wrong = []
    for module in sorted(MODULES):
        mine = _layer(module) or 0
        up = sorted(n for n in _imports(module) & MODULES.keys() if (_layer(n) or 0) > mine)
        if up:
            wrong.append(f"{module} (layer {mine}: {sorted(LAYERS[mine])}) imports {up}")
    assert not wrong, "\n".join(wrong)


# Import cycles kept on purpose: frozenset of the cycle's modules -> why it is harmless.
# Empty: a cycle means two modules each need the other, so what they share belongs in
# one of them (or in a third that both import).
ALLOWED_CYCLES: dict[frozenset[str], str] = {}


def _packages(module: str) -> set[str]:
    """The packages ``module`` is in: hapticd.cli.run -> {hapticd, hapticd.cli}."""
    parts = module.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts))}


def _loads(module: str) -> set[str]:
    """The modules of ours that importing ``module`` can run: each import it executes
    (at module level or in a function; not under TYPE_CHECKING) and that module's
    packages, except the packages ``module`` is in (they were loaded before it)."""
    out = set()
    for name in _imports(module, run_only=True) & MODULES.keys():
        out |= {name, *(_packages(name) - _packages(module))}
    return out & MODULES.keys() - {module}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected group of modules (Tarjan's algorithm), as a
    shortest path from the group's first module back to it: [a, b, ..., a]."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set(stack[stack.index(v) :])
            del stack[stack.index(v) :]
            if len(group) > 1:
                groups.append(group)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    out = []
    for group in groups:
        start = min(group)
        paths = {start: [start]}
        frontier = [start]
        while start not in {w for v in frontier for w in graph[v]}:
            frontier = [
                paths.setdefault(w, [*paths[v], w])[-1]
                for v in frontier
                for w in sorted(graph[v] & group)
                if w not in paths
            ]
        last = next(v for v in frontier if start in graph[v])
        out.append([*paths[last], start])
    return out


def test_the_cycle_finder_finds_a_cycle_and_only_a_cycle():
    graph = {"a": {"b"}, "b": {"c", "d"}, "c": {"a"}, "d": set(), "e": {"d"}}
    assert _cycles(graph) == [["a", "b", "c", "a"]]
    assert _cycles({**graph, "c": set()}) == []


def test_no_import_cycles():
    graph = {m: _loads(m) for m in MODULES}
    found = [c for c in _cycles(graph) if frozenset(c) not in ALLOWED_CYCLES]
    stale = [
        sorted(c) for c in ALLOWED_CYCLES if not any(frozenset(f) == c for f in _cycles(graph))
    ]
    assert not found and not stale, "\n".join(
        [f"import cycle: {' -> '.join(c)}" for c in found]
        + [f"ALLOWED_CYCLES names {c}, which is no longer a cycle" for c in stale]
    )


def test_no_test_finds_our_code_by_the_clones_folder_name():
    """A test that tells hapticd's code from its own by a path pattern naming the package's
    folder (``*/hapticd/*``) also matches the tests themselves in a clone named ``hapticd``,
    the name every user gives it; the packages' own folders (conftest.our_code_filters)
    hold wherever the clone lives."""
    import fnmatch
    import re

    from tests.conftest import our_code_filters

    found = [
        f"{path.name}:{n}"
        for path in sorted((ROOT / "tests").glob("*.py"))
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if re.search(r"""["']\*/(hapticd|drivers)/""", line)
    ]
    assert not found, found
    patterns = [f.filename_pattern for f in our_code_filters()]
    import hapticd_drivers.base

    import hapticd.physics.kernels

    for mod in (hapticd.physics.kernels, hapticd_drivers.base):
        assert any(fnmatch.fnmatch(mod.__file__, p) for p in patterns), (mod.__file__, patterns)
    assert not any(fnmatch.fnmatch(__file__, p) for p in patterns), (__file__, patterns)
