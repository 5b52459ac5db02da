"""Compiles the kernels of ``hapticd.physics.kernels`` with numba, before the first tick, cached on
disk.

``choose(mode, names)`` is what a renderer is built with: ``mode`` is the profile's
``rendering.kernels``, ``names`` the kernels the renderer's plan uses (none: then
numba is not even imported; ``Renderer.kernel_names`` says which).

- ``python``: never compile (a kernel that is its stage's only code runs uncompiled,
  ``hapticd.physics.kernels.uncompiled``).
- ``compiled``: compile now (a first run on a machine waits for it: 2-8 s a kernel
  on this loaded 2-core machine), or load from the cache (0.3-0.6 s).
- ``auto`` (the default): load from the cache when the kernels are in it;
  otherwise render this run with the Python code and compile them in a background
  process at the lowest priority, for the next run. No run waits for a compiler,
  and runs started while one works start none of their own: it holds a marker in
  the cache folder (``COMPILING``) until it is done; a marker older than
  ``COMPILING_MAX_AGE_S`` (a compiler that died) counts for nothing.

Any failure (numba missing or broken, a kernel that does not compile) falls back to
the Python code with a message saying why; both paths give the same forces (tests
prove it). Kernels are compiled eagerly for one signature (``SIGNATURES``: the
frame's and the object's arrays), so no call in the loop can trigger a compilation.
The cache sits in ``__pycache__`` beside ``hapticd/physics/kernels.py`` when that folder is
writable (a source tree, an editable install); otherwise (a system-wide install, a
service) in ``$NUMBA_CACHE_DIR`` if set, else ``$CACHE_DIRECTORY`` (systemd's
``CacheDirectory=``), ``$XDG_CACHE_HOME/hapticd/numba`` or
``~/.cache/hapticd/numba``; with none writable the kernels compile on every run.
Two small JSON files there say which kernels compiled (``COMPILED``) and which
failed and why (``FAILED``), keyed by numba, Python, machine and the kernels' sources
(``kernels.SOURCES``: numba's own cache knows only kernels.py's stamp).

A cache numba cannot read (damaged), or whose files hold another kernel than their
name says (swapped), is removed and compiled again (``compiled``, and the background
compiler), or removed and compiled in the background while Python renders (``auto``),
with a message naming the cache's folder; ``auto`` takes a kernel whose index is there
without its code for not cached (it would compile in the foreground).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

MODES = ("python", "compiled", "auto")

# numba's signature of each kernel called from outside hapticd.physics.kernels: the tick's one call
# (the stages' kernels and helpers are compiled into it: kernels.KERNEL_HELPERS), the
# allocation's own (ContactAllocator's, when it runs outside the call: its replay, its
# stage between the call's parts), the batch's (allocate_many) and the safety chain's
# tick. The frame's fields and the object's state are C-contiguous float64 (uint8 for
# in_contact), the scalars float64 or int64.
SIGNATURES = {
    "allocation_step": (
        "i8(u1[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1], f8[::1], f8[::1],"
        " f8[::1], f8[:, ::1], f8[::1], f8[:, ::1])"
    ),
    "allocate_grasps": (
        "void(i8, f8[:, :, ::1], f8[:, :, ::1], f8[:, ::1], f8[::1], f8, f8, b1, f8[:, ::1],"
        " f8[:, ::1])"
    ),
    "safety_step": "i8(f8[:, ::1], f8[:, ::1], u1[::1], f8[::1], f8[:, :, ::1], f8)",
    "tick_step": "i8(f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[:, :, ::1])",
}

# Compiled kernels of this process, by name: a reload compiles nothing again.
_COMPILED: dict[str, Callable[..., None]] = {}


class JitUnavailableError(RuntimeError):
    """The kernels cannot be compiled here (the message says why)."""


@dataclass(frozen=True)
class KernelChoice:
    """What a renderer renders with: ``used`` is "compiled" or "python"; ``kernels`` maps
    a kernel's name to its compiled function (empty: Python); ``message`` says why the
    Python code renders although ``mode`` asked for compiled kernels (None otherwise);
    ``note``: what happens instead, when that is expected (auto, compiling in the
    background); ``seconds``: how long compiling or loading the cache took."""

    mode: str
    used: str
    kernels: dict[str, Callable[..., None]] = field(default_factory=dict)
    message: str | None = None
    note: str | None = None
    seconds: float = 0.0


def cache_dir(
    package_dir: Path, env: Mapping[str, str], writable: Callable[[Path], bool] | None = None
) -> Path | None:
    """Where compiled kernels are cached, or None to leave it to numba (``__pycache__``
    beside the kernels' source, which is writable here, or ``$NUMBA_CACHE_DIR``).
    ``writable(folder)``: whether this process may create files there."""
    writable = writable or _writable
    if env.get("NUMBA_CACHE_DIR"):
        return None
    pycache = package_dir / "__pycache__"
    if writable(pycache if pycache.exists() else package_dir):
        return None
    candidates = []
    if env.get("CACHE_DIRECTORY"):  # systemd's CacheDirectory=: the first of its list
        candidates.append(Path(env["CACHE_DIRECTORY"].split(":")[0]) / "numba")
    if env.get("XDG_CACHE_HOME"):
        candidates.append(Path(env["XDG_CACHE_HOME"]) / "hapticd" / "numba")
    if env.get("HOME"):
        candidates.append(Path(env["HOME"]) / ".cache" / "hapticd" / "numba")
    for path in candidates:
        try:
            path.mkdir(parents=True, exist_ok=True, mode=0o700)
        except OSError:
            continue
        if writable(path):
            return path
    return None


def _writable(path: Path) -> bool:
    return path.is_dir() and os.access(path, os.W_OK | os.X_OK)


def _import_numba():
    """numba, imported with its cache folder chosen first (JitUnavailableError if it cannot
    be imported)."""
    from hapticd.physics import kernels

    where = cache_dir(Path(kernels.__file__).parent, os.environ)
    if where is not None:
        # Read by numba when it is imported; set on its config too if it already was.
        os.environ["NUMBA_CACHE_DIR"] = str(where)
    try:
        import numba
    except Exception as e:  # ImportError, or a broken install failing on import
        raise JitUnavailableError(f"numba cannot be imported ({type(e).__name__}: {e})") from e
    if where is not None:
        numba.config.CACHE_DIR = str(where)
    return numba


def _cache_folder() -> Path:
    """The folder numba caches the kernels in (set by ``_import_numba``)."""
    from hapticd.physics import kernels

    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    return Path(kernels.__file__).parent / "__pycache__"


def _keys(names: Sequence[str], version: str) -> dict[str, str]:
    """What numba's cache of each kernel depends on: numba, Python, the machine, the
    kernels' sources (``kernels.SOURCES``, numba's own stamp of each: modification time
    and size), the signature."""
    from hapticd.physics import kernels

    stamps = " ".join(f"{st.st_mtime_ns} {st.st_size}" for st in map(os.stat, kernels.SOURCES))
    base = f"numba {version}; {sys.version}; {platform.machine()}; {stamps}"
    return {n: f"{base}; {SIGNATURES.get(n)}" for n in names}


def _read_marker(name: str) -> dict[str, str]:
    try:
        data = json.loads((_cache_folder() / name).read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _write_marker(name: str, entries: dict[str, str]) -> None:
    """Add ``entries`` to the marker file ``name`` in the cache folder (atomically; a
    folder that is not writable leaves it as it was). Under a lock: two processes that
    compile different kernels at once would otherwise each write back what they read,
    and one's entries would be lost."""
    folder = _cache_folder()
    tmp = folder / f".{name}.{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with open(folder / f".{name}.lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            data = {**_read_marker(name), **entries}
            tmp.write_text(json.dumps(data, indent=1))
            os.replace(tmp, folder / name)
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _register_helpers(numba, kernels) -> None:
    """Make the kernels' helpers (``kernels.KERNEL_HELPERS``) callable from compiled code:
    numba compiles each into the kernels that call it, and leaves the function itself
    plain Python (the module is not changed)."""
    try:
        from numba.extending import overload, register_jitable

        forms = kernels.COMPILED_FORMS
        for helper in kernels.KERNEL_HELPERS:
            fn = getattr(kernels, helper) if isinstance(helper, str) else helper
            if fn in _HELPERS:
                continue
            if fn in forms:
                # Its compiled form is another function: compiled code runs that.
                floats = register_jitable(forms[fn])
                overload(fn, strict=False)(lambda *args, _f=floats, **kw: _f)
            else:
                register_jitable(fn)
            _HELPERS.add(fn)
    except Exception:
        # A broken numba: a kernel that calls a helper then fails to compile, and the
        # failure is reported under that kernel's name like any other.
        return


# Helpers registered with numba in this process.
_HELPERS: set[Callable[..., None]] = set()


class DamagedCacheError(JitUnavailableError):
    """numba's cache of a kernel could not be read or held another kernel; its files are
    removed (the message names the folder)."""


def _cache_files(numba, fn: Callable[..., None]) -> tuple[Path, list[Path]]:
    """numba's cache folder for kernel ``fn`` and the files of ``fn`` in it for this Python
    (numba's names: ``kernels.NAME-LINE.pyXY.nbi``, the index, and ``...N.nbc``, the code)."""
    from numba.core.caching import FunctionCache

    folder = Path(FunctionCache(fn).cache_path)
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    return folder, sorted(folder.glob(f"kernels.{fn.__name__}-*.{tag}.*nb[ic]"))


def _mismatch(numba, disp, name: str) -> str | None:
    """What is wrong with the dispatcher ``disp`` numba made for kernel ``name``: None when
    it holds that kernel for its one signature, else what it holds instead (a cache whose
    files were swapped between kernels loads the other kernel under this one's name)."""
    from numba.core import sigutils

    args, _ = sigutils.normalize_signature(SIGNATURES[name])
    held = list(disp.overloads.values())
    if (
        len(held) == 1
        and held[0].fndesc.qualname == name
        and tuple(held[0].signature.args) == (tuple(args))
    ):
        return None
    what = ", ".join(sorted({c.fndesc.qualname for c in held})) or "nothing"
    return f"held another kernel's code ({what})"


def _load(
    numba, kernels, name: str, may_compile: bool, notes: list[str], stale: bool
) -> Callable[..., None]:
    """Kernel ``name`` compiled with numba, or loaded from its cache. A cache that cannot be
    read or holds another kernel is removed; then it is compiled again (``may_compile``,
    adding what happened to ``notes``) or DamagedCacheError says so. ``stale``: the
    record of compiled kernels (``COMPILED``) does not have it for the present sources,
    so whatever numba has cached is removed first (numba's cache knows only
    ``kernels.py``'s stamp, not that of the closed forms the kernel compiles in)."""
    kernel = getattr(kernels, name)
    try:
        folder, files = _cache_files(numba, kernel)
    except Exception:  # a numba without this layout: nothing to check or remove
        folder, files = None, []

    def remove() -> None:
        for f in files:
            with contextlib.suppress(OSError):
                f.unlink()

    if stale and may_compile:
        remove()
        files = []
    try:
        fn = numba.njit(SIGNATURES[name], cache=True, nogil=True)(kernel)
        bad = _mismatch(numba, fn, name)
    except Exception as e:
        if not files:
            raise  # nothing was cached: compiling failed
        bad = f"could not be read ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
    if bad is None:
        return fn
    remove()
    why = f"numba's cache of {name} in {folder} {bad}: removed it"
    if not may_compile:
        raise DamagedCacheError(why)
    fn = numba.njit(SIGNATURES[name], cache=True, nogil=True)(kernel)
    still = _mismatch(numba, fn, name)
    if still is not None:
        raise JitUnavailableError(f"{why}, and compiling {name} again {still}")
    notes.append(f"{why} and compiled {name} again")
    return fn


def compile_kernels(
    names: Sequence[str], *, may_compile: bool = True, notes: list[str] | None = None
) -> dict[str, Callable[..., None]]:
    """The kernels ``names`` compiled (or loaded from the cache); JitUnavailableError if not.
    Marks them compiled in the cache folder (``is_cached``), or records why they failed.
    A damaged cache (see ``_load``) is compiled again, or, without ``may_compile``,
    raises DamagedCacheError; ``notes`` collects what was repaired."""
    notes = [] if notes is None else notes
    missing = [n for n in names if n not in _COMPILED]
    if missing:
        from hapticd.physics import kernels

        numba = _import_numba()
        _register_helpers(numba, kernels)
        keys = _keys(missing, numba.__version__)
        done = _read_marker(COMPILED)
        for name in missing:
            if name not in SIGNATURES:
                raise JitUnavailableError(f"no kernel {name!r}; known: {sorted(SIGNATURES)}")
            try:
                fn = _load(numba, kernels, name, may_compile, notes, keys[name] not in done)
            except JitUnavailableError:
                raise
            except Exception as e:  # numba's errors, or no locator for the cache
                why = (
                    f"numba {numba.__version__} could not compile {name} "
                    f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
                )
                _write_marker(FAILED, {keys[name]: why})
                raise JitUnavailableError(why) from e
            _COMPILED[name] = fn
        _write_marker(COMPILED, {keys[n]: "compiled" for n in missing})
    return {n: _COMPILED[n] for n in names}


# Marker files in the cache folder: kernels compiled (so loading them is quick), and
# kernels that failed to compile (and why), each under its ``_keys`` key.
COMPILED = "hapticd-kernels.json"
FAILED = "hapticd-kernels-failed.json"


def cached(names: Sequence[str], version: str) -> tuple[bool, str | None]:
    """Whether the kernels ``names`` are compiled in the cache folder for numba ``version``,
    and, if one failed to compile with the same numba, source and machine, why."""
    keys = _keys(names, version)
    done = _read_marker(COMPILED)
    failed = _read_marker(FAILED)
    for k in keys.values():
        if k in failed and k not in done:
            return False, failed[k]
    return all(k in done for k in keys.values()), None


def _all_complete(names: Sequence[str]) -> bool:
    """Whether numba's cache holds the index and the code of every kernel in ``names`` (an
    index alone would make numba compile it, in the foreground)."""
    from hapticd.physics import kernels

    numba = _import_numba()
    for n in filter(SIGNATURES.__contains__, names):
        try:
            suffixes = {f.suffix for f in _cache_files(numba, getattr(kernels, n))[1]}
        except Exception:  # a numba without this layout: leave it to numba
            continue
        if not {".nbi", ".nbc"} <= suffixes:
            return False
    return True


# The marker of a background compiler at work, in the cache folder: runs started while it
# works (a lab script starting runs, the test suite) start no compiler of their own. One
# that died leaves it behind: older than COMPILING_MAX_AGE_S (s), it counts for nothing.
COMPILING = "hapticd-kernels.compiling"
COMPILING_MAX_AGE_S = 600.0


def _claim_compiling(now: float) -> str | None:
    """Create the compiling marker (atomically: of several runs at once, one succeeds) and
    return the token written in it; None if a compiler younger than COMPILING_MAX_AGE_S
    holds it. A stale marker is replaced (two runs that find the same stale marker at the
    same moment may both start a compiler: harmless, numba writes its cache atomically).
    An empty token: the folder cannot hold a marker (compile anyway)."""
    folder = _cache_folder()
    path = folder / COMPILING
    token = f"{os.getpid()} {time.time_ns()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return ""
    for _ in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        except FileExistsError:
            try:
                age = now - path.stat().st_mtime
            except FileNotFoundError:
                continue  # released meanwhile: try again
            if age < COMPILING_MAX_AGE_S:
                return None
            with contextlib.suppress(FileNotFoundError):
                path.unlink()  # a compiler that died: its marker expired
            continue
        except OSError:
            return ""
        with os.fdopen(fd, "w") as f:
            f.write(token)
        return token
    return None


def release_compiling(token: str) -> None:
    """Remove the compiling marker if it is still ``token``'s (a compiler that finished)."""
    path = _cache_folder() / COMPILING
    with contextlib.suppress(OSError):
        if token and path.read_text() == token:
            path.unlink()


def spawn(cmd: list[str]) -> None:
    """Start ``cmd`` at the lowest priority through a shell that exits at once: the process
    belongs to no one here and outlives a short run. How the background compiler is
    started: a seam (the tests record the command instead)."""
    script = 'nice -n 19 "$@" </dev/null >/dev/null 2>&1 &'
    subprocess.run(["/bin/sh", "-c", script, "sh", *cmd], check=False, timeout=30)


def compile_in_background(names: Sequence[str]) -> bool:
    """Compile ``names`` into the cache in a process of its own at the lowest priority
    (``python -m hapticd.physics.jit --marker TOKEN NAME...``), unless another run's compiler is
    at work (its marker, see COMPILING); True if this call started one."""
    token = _claim_compiling(time.time())
    if token is None:
        return False
    cmd = [
        sys.executable,
        "-m",
        "hapticd.physics.jit",
        *(["--marker", token] if token else []),
        *names,
    ]
    try:
        spawn(cmd)
    except BaseException:
        release_compiling(token)
        raise
    return True


def choose(mode: str, names: Sequence[str]) -> KernelChoice:
    """The kernels for a renderer whose plan uses ``names``, as ``mode`` asks (one of MODES).

    ``compiled`` compiles them now if they are not in the cache (a first run waits for
    it). ``auto`` uses them if they are in the cache; otherwise this run renders with
    the Python code while a background process compiles them for the next run.
    """
    if mode not in MODES:
        raise ValueError(f"unknown kernels mode {mode!r}; expected one of {list(MODES)}")
    if mode == "python" or not names:
        return KernelChoice(mode, "python")
    t0 = time.perf_counter()
    notes: list[str] = []
    try:
        auto = mode == "auto" and any(n not in _COMPILED for n in names)
        if auto:
            ready, failed = cached(names, _import_numba().__version__)
            if failed is not None:
                raise JitUnavailableError(f"{failed} (when it was last tried)")
            if not ready or not _all_complete(names):
                return _in_background(mode, names, None, t0)
        try:
            compiled = compile_kernels(names, may_compile=not auto, notes=notes)
        except DamagedCacheError as e:
            return _in_background(mode, names, str(e), t0)
    except JitUnavailableError as e:
        return KernelChoice(
            mode,
            "python",
            message=(
                f"rendering.kernels is {mode}, but {e}: the Python kernels render instead "
                "(the same forces; a slower tick). Install numba (pip install numba) or set "
                "rendering.kernels: python to silence this"
            ),
        )
    note = "; ".join(notes) if notes else None
    return KernelChoice(mode, "compiled", compiled, note=note, seconds=time.perf_counter() - t0)


def _in_background(mode: str, names: Sequence[str], damaged: str | None, t0: float) -> KernelChoice:
    """Python renders this run while a background process compiles ``names`` (auto), after
    a damaged cache (``damaged`` says which) or none."""
    started = compile_in_background(names)
    what = (
        f"compiling {', '.join(names)} in the background (once, into {_cache_folder()})"
        if started
        else f"another run's compiler is compiling the kernels into {_cache_folder()}"
    )
    text = (
        f"rendering.kernels is auto: {what}; this run renders with "
        "the Python kernels (the same forces; a slower tick)"
    )
    if damaged is not None:
        return KernelChoice(
            mode, "python", message=f"{damaged}; {text}", seconds=time.perf_counter() - t0
        )
    return KernelChoice(mode, "python", note=text, seconds=time.perf_counter() - t0)


def main(argv: Sequence[str]) -> int:
    """``python -m hapticd.physics.jit [--marker TOKEN] NAME...``: compile kernels into the cache,
    at low priority; then remove the compiling marker ``TOKEN`` (see COMPILING) if given."""
    with contextlib.suppress(OSError):
        os.nice(19)
    names = list(argv)
    token = ""
    if names[:1] == ["--marker"] and len(names) >= 2:
        token, names = names[1], names[2:]
    try:
        compile_kernels(names)
    except JitUnavailableError as e:
        print(f"hapticd.physics.jit: {e}", file=sys.stderr)
        return 1
    finally:
        release_compiling(token)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
