"""Compiling the kernels (hapticd.physics.kernels, by hapticd.physics.jit): a run without a working
JIT falls back to Python with a message; the background compiler, one at a time; the cache folder, a
damaged or swapped cache; hostile values through the compiled path end in zero force like
through the Python one.

Each stage's part of the tick's one call is compared compiled against uncompiled, bit for
bit, in its own file (tests/test_kernel_contact.py, test_kernel_friction.py,
test_dynamics.py, test_kernel_allocation.py, test_kernel_safety.py); whole runs of the
bundled profiles on both paths against the stored reference in
tests/test_reference_output.py."""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hapticd.allocation import kernels as allocation_kernels
from hapticd.daemon.session import build_session
from hapticd.physics import jit, kernels
from hapticd.physics.safety import SafetyChain
from hapticd.physics.scene import ConvexShape, Material, SceneObject
from hapticd.profile import load_profile
from tests.conftest import ROOT, capture_writes, wait_for

LIFT = ROOT / "configs" / "lift-weight.yaml"
GRASP = ROOT / "configs" / "grasp-stiffness.yaml"
DT = 1e-3
# The kernels the lift's renderer names (Renderer.kernel_names), in order.
LIFT_KERNELS = ("tick_step", "allocation_step")


# -- choosing, falling back, caching -----------------------------------------------------


def test_python_mode_and_no_kernels_compile_nothing():
    assert jit.choose("python", ["tick_step"]).kernels == {}
    assert jit.choose("auto", []).used == "python"
    with pytest.raises(ValueError, match="expected one of"):
        jit.choose("fast", ["tick_step"])


def test_only_what_is_called_from_outside_the_kernels_is_an_entry_point():
    """The stages' kernels are compiled into the one call (kernels.KERNEL_HELPERS), not as
    entry points of their own; every entry point is a function of hapticd.physics.kernels
    or hapticd.allocation.kernels."""
    assert set(jit.SIGNATURES) == {"tick_step", "allocation_step", "allocate_grasps", "safety_step"}
    for name in ("world_planes", "contact_step", "friction_step", "forces_step", "free_body_step"):
        assert name in kernels.KERNEL_HELPERS and name not in jit.SIGNATURES
    with pytest.raises(jit.JitUnavailableError, match="no kernel 'contact_step'"):
        jit.compile_kernels(["contact_step"])


def test_the_lift_renders_with_compiled_kernels_unless_python_is_asked():
    jit.compile_kernels(list(jit.SIGNATURES))  # in this process: auto takes them
    profile = load_profile(LIFT)
    assert profile.rendering.kernels == "auto"
    s = build_session(profile, paced=False, duration_s=0.01)
    assert list(s.renderer.kernels) == list(LIFT_KERNELS)
    # The plan in one call, compiled; the allocation stage's kernel for what it hands back.
    assert s.renderer.one_call._fn is s.renderer.kernels["tick_step"]
    assert s.renderer.allocator.kernel is s.renderer.kernels["allocation_step"]
    s.run()
    s = build_session(
        load_profile(LIFT, ["rendering.kernels=python"]), paced=False, duration_s=0.01
    )
    assert s.renderer.kernels == {}
    # The same functions, uncompiled.
    assert s.renderer.one_call._fn is kernels.uncompiled("tick_step")
    assert s.renderer.allocator.kernel is allocation_kernels.uncompiled("allocation_step")
    s.run()


NO_NUMBA = "import sys; sys.modules['numba'] = None\n"
# A numba that imports but cannot compile anything; for auto, the cache's marker says its
# kernels compiled (else auto would compile them in the background with the real numba).
BROKEN_NUMBA = """
import sys, types
fake = types.ModuleType("numba")
fake.__version__ = "0.0-broken"
fake.config = types.SimpleNamespace(CACHE_DIR=None)
def njit(*a, **k):
    raise RuntimeError("LLVM is not there")
fake.njit = njit
sys.modules["numba"] = fake
from hapticd.physics import jit
keys = jit._keys(list(jit.SIGNATURES), "0.0-broken")
jit._write_marker(jit.COMPILED, {k: "compiled" for k in keys.values()})
"""
RUN = """
from hapticd.cli import main
code = main(["run", {profile!r}, "--unpaced", "--no-socket", "--no-realtime",
             "--duration", "0.3", "--summary-json", {summary!r}, "--log-level", "debug"{extra}])
"""


def _python(code: str, cache: Path, timeout: float) -> subprocess.CompletedProcess:
    """Run ``code`` in a Python process of its own with numba's cache in ``cache``; it must
    succeed."""
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        env={**os.environ, "NUMBA_CACHE_DIR": str(cache)},
    )
    assert out.returncode == 0, out.stderr
    return out


def _run_lift(tmp_path: Path, setup: str, mode: str, cache: Path, *sets: str) -> tuple[str, dict]:
    """Run the lift for 0.3 s in a subprocess after ``setup`` (with ``--set`` of each of
    ``sets``); its stderr and summary."""
    summary = tmp_path / "s.json"
    extra = "".join(f", '--set', {x!r}" for x in (f"rendering.kernels={mode}", *sets))
    code = setup + "import sys\n" + RUN.format(profile=str(LIFT), summary=str(summary), extra=extra)
    out = _python(code + "sys.exit(code)\n", cache, 120)
    s = json.loads(summary.read_text())
    assert s["fault"] is None and s["ticks"] == 300
    summary.unlink()
    return out.stderr, s


@pytest.mark.parametrize(
    ("setup", "why"),
    [
        (NO_NUMBA, "numba cannot be imported (ModuleNotFoundError"),
        (BROKEN_NUMBA, "numba 0.0-broken could not compile tick_step (RuntimeError: LLVM"),
    ],
)
@pytest.mark.parametrize("mode", ["auto", "compiled"])
def test_without_a_working_jit_the_python_code_renders_with_a_message(tmp_path, setup, why, mode):
    err, _ = _run_lift(tmp_path, setup, mode, tmp_path / "cache")
    assert f"rendering.kernels is {mode}, but {why}" in err, err
    assert "the Python kernels render instead" in err
    assert "compiled or loaded" not in err


def _numba_cache_of(names: list[str], cache: Path, recorded: tuple[str, ...] = ()) -> None:
    """``cache`` as a folder holding numba's machine code of ``names`` (from the session's
    cache, compiled there first if need be) and hapticd's record that it compiled only
    ``recorded`` of them: hapticd's runs see the others never compiled, and a compiler it
    starts loads ``recorded`` and compiles the rest (a record's absence makes numba's code
    stale: hapticd.physics.jit._load). (Compiling itself is covered where the session's cache is
    filled, and by the tests that compile a kernel again: a damaged or swapped cache,
    changed helpers, the cache across runs.)"""
    jit.compile_kernels(names)
    session = Path(os.environ["NUMBA_CACHE_DIR"])
    skip = shutil.ignore_patterns(jit.COMPILED, jit.FAILED, jit.COMPILING)
    shutil.copytree(session, cache, ignore=skip)
    if recorded:
        import numba

        keys = jit._keys(recorded, numba.__version__)
        (cache / jit.COMPILED).write_text(json.dumps({k: "compiled" for k in keys.values()}))


def test_auto_compiles_in_the_background_once_and_loads_from_the_cache_after(tmp_path):
    """A first auto run does not wait for the compiler: it renders with Python and leaves
    the compiling to a process of its own; a later run loads the compiled kernel."""
    cache = tmp_path / "cache"
    names = [*LIFT_KERNELS, *SafetyChain.kernel_names]
    # The one call's record is there (its compiling, at the lowest priority, took minutes
    # on a loaded 2-core machine): the compiler loads it and compiles the safety chain's.
    _numba_cache_of(names, cache, recorded=LIFT_KERNELS)
    err, _ = _run_lift(tmp_path, "", "auto", cache)
    assert f"compiling {', '.join(names)} in the background" in err, err
    assert "compiled or loaded" not in err
    marker = cache / jit.COMPILED
    deadline = time.monotonic() + 180.0
    while len(json.loads(marker.read_text())) < len(names) or jit.compiling(cache):
        assert time.monotonic() < deadline, "the background compiler did not finish in 180 s"
        time.sleep(0.2)
    err, _ = _run_lift(tmp_path, "", "auto", cache)
    assert f"kernels {names} compiled or loaded" in err, err
    assert "background" not in err and "render instead" not in err


def test_auto_says_why_when_the_kernels_failed_to_compile_before(tmp_path):
    """A failure of the background compiler is kept: the next auto run says why it renders
    with Python instead of starting the compiler again."""
    cache = tmp_path / "cache"
    setup = (
        "import os, numba\n"
        "from hapticd.physics import jit\n"
        "jit._write_marker(jit.FAILED, {k: 'numba could not compile it (a test)' for k in "
        "jit._keys(list(jit.SIGNATURES), numba.__version__).values()})\n"
    )
    err, _ = _run_lift(tmp_path, setup, "auto", cache)
    assert "but numba could not compile it (a test) (when it was last tried)" in err, err
    assert not (cache / jit.COMPILED).exists()


def test_python_mode_never_imports_numba():
    code = (
        "import sys\n"
        "from hapticd.daemon.build import build_renderer\n"
        "from hapticd.profile import load_profile\n"
        f"r = build_renderer(load_profile({str(LIFT)!r}, ['rendering.kernels=python']))\n"
        "print('numba' in sys.modules, r.kernels)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert out.stdout.split() == ["False", "{}"], out.stdout + out.stderr


def test_compiled_kernels_are_cached_across_runs(tmp_path):
    """A second process loads the first one's machine code (numba's cache hits), from the
    folder NUMBA_CACHE_DIR names."""
    code = (
        "from hapticd.physics import jit\n"
        "f = jit.compile_kernels(['safety_step'])['safety_step']\n"
        "print(sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values()))\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    runs = []
    for _ in range(2):
        out = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=ROOT,
            env=env,
        )
        assert out.returncode == 0, out.stderr
        runs.append([int(x) for x in out.stdout.split()])
    assert any((tmp_path / "cache").rglob("*.nbi")), "no index file in the cache folder"
    assert runs[1][0] >= 1, runs  # the second run loaded from the cache


def test_the_cache_folder_is_the_users_when_the_package_folder_is_not_writable(tmp_path):
    pkg = tmp_path / "site-packages" / "hapticd"
    (pkg / "__pycache__").mkdir(parents=True)
    home = tmp_path / "home"
    xdg = tmp_path / "xdg"
    read_only = {pkg, pkg / "__pycache__"}

    def writable(p: Path) -> bool:
        return p.is_dir() and p not in read_only

    env = {"HOME": str(home)}
    assert jit.cache_dir(pkg, env, writable) == home / ".cache" / "hapticd" / "numba"
    assert (home / ".cache" / "hapticd" / "numba").is_dir()
    env["XDG_CACHE_HOME"] = str(xdg)
    assert jit.cache_dir(pkg, env, writable) == xdg / "hapticd" / "numba"
    env["CACHE_DIRECTORY"] = str(tmp_path / "svc")
    assert jit.cache_dir(pkg, env, writable) == tmp_path / "svc" / "numba"
    # The user's own choice, or a writable package folder: numba's defaults.
    assert jit.cache_dir(pkg, {**env, "NUMBA_CACHE_DIR": "/x"}, writable) is None
    assert jit.cache_dir(pkg, env, lambda p: p.is_dir()) is None
    # Nothing writable: None (numba then compiles on every run or fails over to Python).
    assert jit.cache_dir(pkg, env, lambda p: False) is None


# -- hostile values through both paths ------------------------------------------------


class Poison:
    """A stage after ``forces`` that puts ``value`` into finger 0's contact force from
    ``at`` (s) on: what a broken contact model could hand to allocation and dynamics."""

    name = "poison"

    corrupts = ("contact_force", "in_contact")

    def __init__(self, loop, value: float, at: float) -> None:
        self.loop, self.value, self.at = loop, value, at

    def run(self, frame) -> None:
        if self.loop.now() >= self.at:
            frame.contact_force[0] = self.value
            frame.in_contact[0] = 1


@pytest.mark.parametrize("value", [math.nan, math.inf, -1e300, 1e6])
@pytest.mark.parametrize("mode", ["python", "compiled"])
@pytest.mark.parametrize("path", [LIFT, GRASP], ids=["lift", "grasp"])
def test_hostile_forces_never_reach_a_device_from_either_path(path, mode, value):
    """Through the compiled allocation (both profiles) and free-body step (the lift)."""
    profile = load_profile(path, [f"rendering.kernels={mode}"])
    session = build_session(profile, paced=False, duration_s=3.2)
    loop = session.loop
    assert bool(session.renderer.kernels) == (mode == "compiled")
    if mode == "compiled":
        assert "allocation_step" in session.renderer.kernels
    session.renderer.insert(Poison(loop, value, 3.0), after="forces")
    written = capture_writes(session)
    summary = session.run()
    forces = np.array(written)
    limit = max(session.safety.limits)
    assert np.all(np.isfinite(forces))
    assert np.all(np.linalg.norm(forces, axis=1) <= limit + 1e-12)
    if path == GRASP and math.isfinite(value):
        # A fixed cube cannot be flung: a finite over-limit force is limited (above).
        assert np.any(np.linalg.norm(forces, axis=1) > 0.99 * limit)
        return
    # The object flung or poisoned: a latched fault, zero force from then on.
    assert summary["fault"] is not None, summary
    assert np.all(forces[-len(session.devices) :] == 0.0)


# -- one background compiler at a time -------------------------------------------------


@pytest.fixture
def empty_cache(tmp_path, monkeypatch):
    """An empty cache folder of this test's own and no kernel compiled in this process, so
    that auto asks for a background compiler; starting one is recorded, not done: the record
    keeps a copy of the descriptor the compiler would inherit (closing it ends the compiler)."""
    cache = tmp_path / "cache"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    monkeypatch.setattr(jit, "_COMPILED", {})
    started: list[tuple[list[str], int]] = []
    monkeypatch.setattr(jit, "spawn", lambda cmd, lock: started.append((cmd, os.dup(lock))))
    yield cache, started
    for _, fd in started:
        with contextlib.suppress(OSError):
            os.close(fd)


# The smallest entry point: the several-runs test waits for a real compile of it.
NAMES = ["safety_step"]


def test_runs_started_while_a_compiler_works_start_none_of_their_own(empty_cache):
    cache, started = empty_cache
    first = jit.choose("auto", NAMES)
    assert first.used == "python" and "compiling safety_step" in first.note
    assert len(started) == 1 and jit.compiling(cache)
    for _ in range(3):
        again = jit.choose("auto", NAMES)
        assert again.used == "python" and "another run's compiler" in again.note
    assert len(started) == 1
    # The compiler ends (done, or dead: the lock goes with the process), and a run after it
    # whose kernels are still not in the cache (say it failed silently) may start one again.
    os.close(started[0][1])
    assert not jit.compiling(cache)
    assert not jit.compiling(cache / "none") and not (cache / "none").exists()  # asks only
    jit.choose("auto", NAMES)
    assert len(started) == 2 and jit.compiling(cache)


def test_the_started_compiler_holds_the_lock_until_it_ends(tmp_path, monkeypatch):
    """The process ``spawn`` starts inherits the lock: the run that started it lets go of
    its own descriptor at once, and the lock lasts as long as that process."""
    cache = tmp_path / "cache"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    lock = jit._lock(cache, fcntl.LOCK_EX)
    assert lock is not None and lock >= 0
    done = tmp_path / "done"
    wait = (
        "import os, time\n"
        "for _ in range(600):\n"
        f"    if os.path.exists({str(done)!r}): break\n"
        "    time.sleep(0.05)"
    )
    try:
        jit.spawn([sys.executable, "-c", wait], lock)
    finally:
        os.close(lock)
    assert jit.compiling(cache) and jit._lock(cache, fcntl.LOCK_EX) is None
    done.touch()
    wait_for(lambda: jit.compiling(cache), "the child to end", until=lambda held: not held)


CHOOSE = """
import sys
from hapticd.physics import jit
jit.SIGNATURES.update({small!r})
real_spawn = jit.spawn


def spawn(cmd, lock):
    # python -m hapticd.physics.jit knows only the product's kernels: the same command
    # through the same spawn (the lock inherited), as a script that knows the small ones.
    assert cmd[1:3] == ["-m", "hapticd.physics.jit"], cmd
    real_spawn([cmd[0], {compiler!r}, *cmd[3:]], lock)


jit.spawn = spawn
print(jit.choose("auto", {names!r}).note)
"""
# The background compiler of the several-runs test: it starts compiling once the four runs
# have asked (``go`` exists), so none of them can find the kernels compiled already,
# however fast the machine, and the lock must last while it waits and compiles.
GATED_COMPILER = """
import os, sys, time
from hapticd.physics import jit
jit.SIGNATURES.update({small!r})
for _ in range(2400):  # bounded: 2 min
    if os.path.exists({go!r}):
        break
    time.sleep(0.05)
sys.exit(jit.main(sys.argv[1:]))
"""


def test_several_runs_at_once_start_one_compiler_that_holds_its_lock_until_done(
    tmp_path, monkeypatch
):
    """Four processes ask for the kernels at the same moment (no cache): one compiler
    starts (through jit.spawn, at the lowest priority); when its lock is free the kernels
    are in the cache. (Two small kernels given entry points, SMALL: safety_step's compile
    at the lowest priority kept this test waiting a minute on a loaded machine.)"""
    monkeypatch.setattr(jit, "SIGNATURES", {**jit.SIGNATURES, **SMALL_SIGNATURES})
    cache = tmp_path / "cache"
    go = tmp_path / "go"
    compiler = tmp_path / "compiler.py"
    compiler.write_text(GATED_COMPILER.format(small=SMALL_SIGNATURES, go=str(go)))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    code = CHOOSE.format(small=SMALL_SIGNATURES, compiler=str(compiler), names=SMALL)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT, env=env
        )
        for _ in range(4)
    ]
    notes = [p.communicate(timeout=120)[0] for p in procs]
    assert all(p.returncode == 0 for p in procs), notes
    assert sum("compiling world_planes, forces_step" in n for n in notes) == 1, notes
    assert sum("another run's compiler" in n for n in notes) == 3, notes
    assert jit.compiling(cache)  # the compiler, waiting for go, holds the lock
    go.touch()
    deadline = time.monotonic() + 180.0
    while jit.compiling(cache) or not (cache / jit.COMPILED).exists():
        assert time.monotonic() < deadline, "the background compiler did not finish in 180 s"
        time.sleep(0.2)
    keys = jit._keys(SMALL, __import__("numba").__version__)
    assert set(keys.values()) <= set(json.loads((cache / jit.COMPILED).read_text()))


RECORD = """
from hapticd.physics import jit
for i in range(300):
    jit._write_marker(jit.COMPILED, {{f"{tag} {{i}}": "compiled"}})
"""


def test_processes_recording_kernels_at_once_lose_none_of_them(tmp_path):
    """Two compilers that finish different kernels at the same moment both keep their
    record of them (each adds its own under a lock; without one, a writer wrote back what
    it had read before the other's entries, and those kernels counted as not compiled)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    procs = [
        subprocess.Popen([sys.executable, "-c", RECORD.format(tag=tag)], cwd=ROOT, env=env)
        for tag in ("a", "b")
    ]
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    record = json.loads((tmp_path / "cache" / jit.COMPILED).read_text())
    assert set(record) == {f"{tag} {i}" for tag in "ab" for i in range(300)}


def test_a_moved_object_has_its_polytope_at_its_new_pose():
    """The polytope is the object's faces at its pose when it is read: moved in place, the
    offsets follow the move along each normal."""
    obj = SceneObject(
        ConvexShape.box(np.full(3, 0.05)), Material(200.0, 0.0), np.zeros(3), np.eye(3)
    )
    first = obj.polytope
    obj.position[:] = (0.01, 0.0, 0.0)
    moved = obj.polytope
    np.testing.assert_array_equal(moved.normals, first.normals)
    np.testing.assert_allclose(
        moved.offsets - first.offsets, moved.normals[:, 0] * 0.01, atol=1e-15
    )
    np.testing.assert_array_equal(moved.center, (0.01, 0.0, 0.0))
    np.testing.assert_array_equal(first.center, (0.0, 0.0, 0.0))


# -- a damaged or mismatched cache -----------------------------------------------------

# Two small functions of hapticd.physics.kernels (parts of the one call), given entry points of
# their own in these tests' processes only: the cache's handling is the same for any
# kernel, and the product's entry points take far longer to compile.
SMALL_SIGNATURES = {
    "world_planes": "void(f8[:, ::1], f8[::1], f8[:, ::1], f8[::1], f8[:, ::1])",
    "forces_step": (
        "void(u1[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1],"
        " f8[::1])"
    ),
}
SMALL = list(SMALL_SIGNATURES)
WITH_SMALL = f"from hapticd.physics import jit\njit.SIGNATURES.update({SMALL_SIGNATURES!r})\n"
# In a process of its own (numba's cache folder is chosen when it is imported): choose the
# kernels, with the background compiler recorded instead of started, and call world_planes
# (a swapped cache held forces_step's code there: "No matching definition" at the first tick).
DAMAGED = """
import json, sys
import numpy as np
started = []
jit.spawn = lambda cmd, lock: started.append(cmd)
c = jit.choose({mode!r}, {names!r})
out = None
if c.used == "compiled":
    planes = np.zeros((1, 4))
    c.kernels["world_planes"](np.eye(3), np.ones(3), np.eye(3)[:1].copy(), np.ones(1), planes)
    out = planes[0].tolist()
print(json.dumps({{"used": c.used, "message": c.message, "note": c.note, "started": len(started),
                  "out": out}}))
"""


def _choose_in(cache: Path, mode: str) -> dict:
    out = _python(WITH_SMALL + DAMAGED.format(mode=mode, names=SMALL), cache, 300)
    return json.loads(out.stdout.splitlines()[-1])


@pytest.fixture(scope="module")
def small_cache(tmp_path_factory) -> Path:
    """A cache folder holding SMALL compiled (copy it before damaging it)."""
    cache = tmp_path_factory.mktemp("small") / "cache"
    assert _choose_in(cache, "compiled")["used"] == "compiled"
    return cache


def _copy(small_cache: Path, tmp_path: Path) -> tuple[Path, dict[str, Path]]:
    """A copy of ``small_cache`` and its code file (.nbc) of each kernel of SMALL."""
    cache = tmp_path / "cache"
    shutil.copytree(small_cache, cache)
    code = {n: next(cache.rglob(f"{_stem(n)}.{n}-*.nbc")) for n in SMALL}
    return cache, code


def _stem(name: str) -> str:
    """The name of the file kernel ``name`` is defined in, without its suffix (numba names
    its cache files after it)."""
    return Path(jit._kernel(name).__code__.co_filename).stem


def _swap(code: dict[str, Path]) -> None:
    a, b = code["world_planes"], code["forces_step"]
    data = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(data)


PLANES = [1.0, 0.0, 0.0, 2.0]  # world_planes at x = (1, 1, 1) for the normal (1, 0, 0), d = 1


def test_a_damaged_or_swapped_cache_is_compiled_again(small_cache, tmp_path):
    """forces_step's code file holds world_planes' code (a swap), world_planes' is cut
    short (damaged): both are removed and compiled again, and a message names the cache."""
    cache, code = _copy(small_cache, tmp_path)
    data = code["world_planes"].read_bytes()
    code["forces_step"].write_bytes(data)
    code["world_planes"].write_bytes(data[:100])
    got = _choose_in(cache, "compiled")
    assert got["used"] == "compiled" and got["out"] == PLANES, got
    folder = code["world_planes"].parent
    assert f"numba's cache of world_planes in {folder} could not be read" in got["note"], got
    assert (
        f"numba's cache of forces_step in {folder} held another kernel's code (world_planes)"
        in got["note"]
    ), got
    # Repaired: the next run loads them without a word.
    again = _choose_in(cache, "compiled")
    assert again["note"] is None and again["out"] == PLANES, again


def test_auto_renders_python_and_compiles_in_the_background_after_a_swapped_cache(
    small_cache, tmp_path
):
    cache, code = _copy(small_cache, tmp_path)
    _swap(code)
    got = _choose_in(cache, "auto")
    assert got["used"] == "python" and got["started"] == 1, got
    assert f"numba's cache of world_planes in {code['world_planes'].parent}" in got["message"]
    assert "compiling world_planes, forces_step in the background" in got["message"]
    assert not code["world_planes"].exists()  # removed: the compiler writes it anew


def test_auto_takes_an_index_without_its_code_for_not_cached(small_cache, tmp_path):
    """numba would compile such a kernel in the foreground (seconds at the first tick's
    door); auto leaves it to the background compiler like any kernel not cached."""
    cache, code = _copy(small_cache, tmp_path)
    code["forces_step"].unlink()
    got = _choose_in(cache, "auto")
    assert got["used"] == "python" and got["started"] == 1, got
    assert "compiling world_planes, forces_step in the background" in got["note"]


STAMPED = """
import json
from hapticd.physics import kernels
kernels.SOURCES = (*kernels.SOURCES, *{extra!r})
f = jit.compile_kernels(["world_planes"])["world_planes"]
print(json.dumps([sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values())]))
"""


def test_a_kernel_whose_helpers_changed_is_compiled_again(small_cache, tmp_path):
    """numba's cache knows only kernels.py's stamp; a kernel compiles in code from other
    files too (the allocation's closed forms), so a change to any of ``kernels.SOURCES``
    must not load the old machine code."""
    cache, _ = _copy(small_cache, tmp_path)
    helper = tmp_path / "helper.py"
    helper.write_text("x = 1\n")

    def hits_and_misses(extra: list[str]) -> list[int]:
        out = _python(WITH_SMALL + STAMPED.format(extra=extra), cache, 300)
        return json.loads(out.stdout.splitlines()[-1])

    assert hits_and_misses([]) == [1, 0]  # unchanged: loaded
    assert hits_and_misses([str(helper)]) == [0, 1]  # a source it depends on: compiled
    assert hits_and_misses([str(helper)]) == [1, 0]  # and cached for that source
