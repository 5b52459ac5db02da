"""Compiles the kernels of ``hapticd.physics.kernels`` with numba before the first tick, cached
on disk.

``choose(mode, names)`` gives a renderer its kernels: ``mode`` is the profile's
``rendering.kernels``, ``names`` the kernels its plan uses (``Renderer.kernel_names``). The
modes, the fallback to Python, the cache folder and its files, the background compiler and
a damaged cache's repair: docs/daemon.md, "Compiled kernels".
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import platform
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from hapticd.allocation import kernels as allocation
from hapticd.control import ownership_problem
from hapticd.physics import kernels

MODES = ("python", "compiled", "auto")

# numba's signature of each kernel called from outside hapticd.physics.kernels: the tick's one call
# (the stages' kernels and helpers are compiled into it: kernels.KERNEL_HELPERS), the
# allocation's own (ContactAllocator's outside the call: its replay), the batch's
# (allocate_many) and the safety chain's
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

# The module each kernel is exported from (the tick's are defined in hapticd.physics.tick).
_MODULES = {
    "allocation_step": allocation,
    "allocate_grasps": allocation,
    "safety_step": kernels,
    "tick_step": kernels,
}

# Compiled kernels of this process, by name: a reload compiles nothing again.
_COMPILED: dict[str, Callable[..., None]] = {}

# Helpers registered with numba in this process.
_HELPERS: set[Callable[..., None]] = set()


def _kernel(name: str) -> Callable[..., object]:
    """Kernel ``name``'s Python function (in the module that exports it; a function of
    hapticd.physics.kernels when none is named, as its helpers are)."""
    return getattr(_MODULES.get(name, kernels), name)


# The folders of the files that define the entry points (numba caches each in its
# __pycache__ by default; hapticd.physics.kernels re-exports the tick's, which live in the
# stage modules of hapticd.physics.tick).
_KERNEL_DIRS = tuple(
    dict.fromkeys(Path(_kernel(n).__code__.co_filename).parent for n in SIGNATURES)
)


# Marker files in the cache folder, each keyed by ``_keys``: kernels compiled (so loading them
# is quick), and kernels that failed to compile (and why).
COMPILED = "hapticd-kernels.json"
FAILED = "hapticd-kernels-failed.json"
# The lock file of the background compiler: it holds an exclusive flock on it while it
# works, and the lock goes with the process, however it ends.
COMPILING = "hapticd-kernels.compiling"
# What numba, hapticd and a compiler may write in the cache root besides numba's folders.
_MARKERS = (COMPILED, FAILED, COMPILING, f".{COMPILED}.lock", f".{FAILED}.lock")
# Mode bits no folder or file of the cache may have: numba unpickles its index and code
# files (a pickle runs code), so nobody but their owner may write them. Reading is harmless
# (machine code of public source; an installed package's __pycache__ is 0755), which is
# why this is looser than the socket directory's 0o027.
_UNSAFE_BITS = 0o022
# Opening a marker or the lock never follows a link or waits for a FIFO's writer.
_OPEN_FLAGS = os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC


class JitUnavailableError(RuntimeError):
    """The kernels cannot be compiled here (the message says why)."""


class UnsafeCacheError(JitUnavailableError):
    """A folder or file of the kernel cache could be another user's (numba would unpickle
    it, which runs code): nothing of the cache is read (the message names it and what to
    do)."""


class DamagedCacheError(JitUnavailableError):
    """numba's cache of a kernel could not be read or held another kernel; its files are
    removed (the message names the folder)."""


@dataclass(frozen=True)
class KernelChoice:
    """What a renderer renders with. ``used``: "compiled" or "python"; ``kernels``: each
    kernel's compiled function by name (empty: Python); ``message``: why Python renders
    although ``mode`` asked for compiled kernels; ``note``: what happens instead when that is
    expected (auto, compiling in the background); ``seconds``: compiling or loading (s)."""

    mode: str
    used: str
    kernels: dict[str, Callable[..., None]] = field(default_factory=dict)
    message: str | None = None
    note: str | None = None
    seconds: float = 0.0


def cache_dir(
    package_dir: Path, env: Mapping[str, str], writable: Callable[[Path], bool] | None = None
) -> Path | None:
    """Where compiled kernels are cached, or None to leave it to numba (``$NUMBA_CACHE_DIR``,
    or ``__pycache__`` in ``package_dir`` when writable). ``writable(folder)``: whether this
    process may create files there."""
    writable = writable or _writable
    if env.get("NUMBA_CACHE_DIR"):
        return None
    pycache = package_dir / "__pycache__"
    if writable(pycache if pycache.exists() else package_dir) and _safe_or_absent(pycache):
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
        if writable(path) and _safe_or_absent(path):
            return path
    return None


def _writable(path: Path) -> bool:
    return path.is_dir() and os.access(path, os.W_OK | os.X_OK)


def _safe_or_absent(folder: Path) -> bool:
    """Whether ``folder`` is absent or a cache folder nobody else can write to."""
    try:
        return ownership_problem(folder, os.geteuid(), _UNSAFE_BITS) is None
    except FileNotFoundError:
        return True


def _unsafe(path: Path, root: Path, regular: bool = False) -> UnsafeCacheError | None:
    """The refusal of ``path``, a folder (or with ``regular`` a file) of the cache whose
    root is ``root``, when it could be another user's; None when it is absent or safe."""
    try:
        problem = ownership_problem(path, os.geteuid(), _UNSAFE_BITS, regular=regular)
    except FileNotFoundError:
        return None
    if problem is None:
        return None
    return UnsafeCacheError(
        f"the kernel cache is unsafe: {path} {problem}, and only uid {os.geteuid()} may "
        f"write a folder or file of it (numba loads its files as pickles, which run code), "
        f"so nothing of it is loaded; remove it (rm -r {root}) or set NUMBA_CACHE_DIR to a "
        "folder of your own (hapticd makes it with mode 0700)"
    )


def check_cache(names: Sequence[str]) -> Path:
    """Make sure nobody else can have written numba's cache of the kernels ``names`` before
    numba reads any of it: the cache root (``_cache_folder()``; made 0700 when absent), each
    kernel's folder and the folders between (made 0700 too, before numba makes them with
    the process's umask) must be directories, not symbolic links, of this process's user,
    writable by nobody else; the marker files and numba's index and code files regular
    files of that user, writable by nobody else. Only lstat: nothing is opened, so a FIFO
    cannot block. The folder of the kernels; UnsafeCacheError naming what is wrong."""
    root = _cache_folder()
    with contextlib.suppress(OSError):  # absent parents, a file in the way: checked below
        root.mkdir(mode=0o700, parents=True, exist_ok=True)
    if (bad := _unsafe(root, root)) is not None:
        raise bad
    for marker in _MARKERS:
        if (bad := _unsafe(root / marker, root, regular=True)) is not None:
            raise bad
    try:
        from numba.core.caching import FunctionCache, _CacheLocator
    except ImportError:  # a numba without this layout: it has no such folders to read
        return root
    folders = set()
    for name in filter(SIGNATURES.__contains__, names):
        kernel = _kernel(name)
        if os.environ.get("NUMBA_CACHE_DIR"):  # numba's folder for the kernel's source file
            sub = _CacheLocator.get_suitable_cache_subpath(kernel.__code__.co_filename)
            _check_folders(root, root / sub)
        try:  # where numba caches it (it falls back to others when one is not writable)
            folders.add(Path(FunctionCache(kernel).cache_path))
        except Exception:  # no locator: numba can neither read nor write a cache of it
            continue
    for folder in folders:
        _check_folders(root if folder.is_relative_to(root) else folder, folder)
        for f in sorted(folder.iterdir()):
            if f.suffix in (".nbi", ".nbc") and (bad := _unsafe(f, root, regular=True)):
                raise bad
    return root


def _check_folders(root: Path, folder: Path) -> None:
    """Each folder from ``root`` down to ``folder`` (made 0700 when absent) safe, else
    UnsafeCacheError."""
    path = root
    for part in (None, *folder.relative_to(root).parts):
        if part is not None:
            path = path / part
            with contextlib.suppress(OSError):
                os.mkdir(path, 0o700)
        if (bad := _unsafe(path, root)) is not None:
            raise bad


def _tighten(folder: Path) -> None:
    """No group or other write on numba's files of this user in ``folder`` (numba writes
    them with the process's umask): the next run's check must pass them."""
    for f in folder.iterdir():
        if f.suffix not in (".nbi", ".nbc"):
            continue
        with contextlib.suppress(OSError):
            st = os.lstat(f)
            if stat.S_ISREG(st.st_mode) and st.st_uid == os.geteuid() and st.st_mode & 0o022:
                os.chmod(f, stat.S_IMODE(st.st_mode) & ~0o022)


def _import_numba():
    """numba, imported after its cache folder is chosen; JitUnavailableError if it cannot be."""
    where = None
    for folder in _KERNEL_DIRS:  # one folder for all when one module's is not writable
        where = where or cache_dir(folder, os.environ)
    if where is not None:
        # numba reads the variable when it is imported; its config, if it already was.
        os.environ["NUMBA_CACHE_DIR"] = str(where)
    try:
        import numba
    except Exception as e:  # ImportError, or a broken install failing on import
        raise JitUnavailableError(f"numba cannot be imported ({type(e).__name__}: {e})") from e
    if where is not None:
        numba.config.CACHE_DIR = str(where)
    return numba


def _cache_folder() -> Path:
    """The folder numba caches the kernels in (once ``_import_numba`` chose it)."""
    return Path(os.environ.get("NUMBA_CACHE_DIR") or _KERNEL_DIRS[-1] / "__pycache__")


def _keys(names: Sequence[str], version: str) -> dict[str, str]:
    """Each kernel's key in the marker files: numba ``version``, Python, the machine, the
    stamps of ``kernels.SOURCES`` and its signature. numba's own cache knows only the stamp
    of the file defining the kernel, not those of the files whose code it compiles in."""
    stamps = " ".join(f"{st.st_mtime_ns} {st.st_size}" for st in map(os.stat, kernels.SOURCES))
    base = f"numba {version}; {sys.version}; {platform.machine()}; {stamps}"
    return {n: f"{base}; {SIGNATURES.get(n)}" for n in names}


def _read_marker(name: str) -> dict[str, str]:
    """The marker file ``name`` ({} when absent, not a regular file, or not JSON)."""
    try:
        fd = os.open(_cache_folder() / name, os.O_RDONLY | _OPEN_FLAGS)
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                return {}
            data = json.loads(f.read(16 << 20))  # a marker is a few kB
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _write_marker(name: str, entries: dict[str, str]) -> None:
    """Add ``entries`` to the marker file ``name`` (atomically; an unwritable folder leaves it
    as it was)."""
    folder = _cache_folder()
    tmp = folder / f".{name}.{os.getpid()}"
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        # Locked: two compilers finishing at once would each write back what they read, and
        # one's entries would be lost.
        lock = os.open(folder / f".{name}.lock", os.O_WRONLY | os.O_CREAT | _OPEN_FLAGS, 0o600)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX)
            text = json.dumps({**_read_marker(name), **entries}, indent=1)
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()  # a dead writer's, of the same pid
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _OPEN_FLAGS, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(text)
            os.replace(tmp, folder / name)
        finally:
            os.close(lock)
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _register_helpers() -> None:
    """Make ``kernels.KERNEL_HELPERS`` callable from compiled code (compiled into their callers;
    the Python functions stay as they are)."""
    try:
        from numba.extending import overload, register_jitable

        from hapticd.physics import native  # numba's: imported once numba is

        forms = {**kernels.COMPILED_FORMS, allocation.plugin_call: native.plugin_call_compiled}
        for helper in kernels.KERNEL_HELPERS:
            fn = getattr(kernels, helper) if isinstance(helper, str) else helper
            if fn in _HELPERS:
                continue
            if fn in forms:  # compiled code runs another function in its place
                floats = register_jitable(forms[fn])
                overload(fn, strict=False)(lambda *args, _f=floats, **kw: _f)
            else:  # the split parts of the stages' kernels inline, the rest as calls
                inline = "always" if helper in kernels.INLINED else "never"
                register_jitable(inline=inline)(fn)
            _HELPERS.add(fn)
    except Exception:
        # A broken numba: a kernel that calls a helper then fails to compile, and the
        # failure is reported under that kernel's name like any other.
        return


def _first_line(e: Exception) -> str:
    return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"


def _cache_files(fn: Callable[..., None]) -> tuple[Path, list[Path]]:
    """numba's cache folder for kernel ``fn`` and this Python's files of ``fn`` in it (the
    index ``kernels.NAME-LINE.pyXY.nbi`` and the code, ``...N.nbc``)."""
    from numba.core.caching import FunctionCache

    folder = Path(FunctionCache(fn).cache_path)
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    stem = Path(fn.__code__.co_filename).stem
    return folder, sorted(folder.glob(f"{stem}.{fn.__name__}-*.{tag}.*nb[ic]"))


def _remove(files: list[Path]) -> None:
    for f in files:
        with contextlib.suppress(OSError):
            f.unlink()


def _mismatch(disp, name: str) -> str | None:
    """None when numba's dispatcher ``disp`` holds kernel ``name`` for its one signature, else
    what it holds (files swapped between kernels load the other kernel under this name)."""
    from numba.core import sigutils

    args, _ = sigutils.normalize_signature(SIGNATURES[name])
    held = list(disp.overloads.values())
    if len(held) == 1 and held[0].fndesc.qualname == name and tuple(held[0].signature.args) == args:
        return None
    what = ", ".join(sorted({c.fndesc.qualname for c in held})) or "nothing"
    return f"held another kernel's code ({what})"


def _load(
    numba, name: str, may_compile: bool, notes: list[str], stale: bool
) -> Callable[..., None]:
    """Kernel ``name`` compiled, or loaded from numba's cache. A cache that cannot be read or
    holds another kernel is removed, then compiled again (``may_compile``; ``notes`` says so)
    or DamagedCacheError. ``stale``: not in COMPILED for the present sources, so numba's
    cache of it is removed first."""
    kernel = _kernel(name)

    def njit():
        return numba.njit(SIGNATURES[name], cache=True, nogil=True)(kernel)

    try:
        folder, files = _cache_files(kernel)
    except Exception:  # a numba without this layout: nothing to check or remove
        folder, files = None, []
    if stale and may_compile:
        _remove(files)
        files = []
    try:
        fn = njit()
        bad = _mismatch(fn, name)
    except Exception as e:
        if not files:
            raise  # nothing was cached: compiling failed
        bad = f"could not be read ({_first_line(e)})"
    if bad is None:
        return fn
    _remove(files)
    why = f"numba's cache of {name} in {folder} {bad}: removed it"
    if not may_compile:
        raise DamagedCacheError(why)
    fn = njit()
    still = _mismatch(fn, name)
    if still is not None:
        raise JitUnavailableError(f"{why}, and compiling {name} again {still}")
    notes.append(f"{why} and compiled {name} again")
    return fn


def compile_kernels(
    names: Sequence[str], *, may_compile: bool = True, notes: list[str] | None = None
) -> dict[str, Callable[..., None]]:
    """The kernels ``names`` compiled or loaded, recorded in COMPILED (or why not in FAILED);
    JitUnavailableError if not. A damaged cache is compiled again (``notes`` says so), or
    without ``may_compile`` raises DamagedCacheError."""
    notes = [] if notes is None else notes
    missing = [n for n in names if n not in _COMPILED]
    if missing:
        numba = _import_numba()
        check_cache(missing)
        _register_helpers()
        keys = _keys(missing, numba.__version__)
        done = _read_marker(COMPILED)
        for name in missing:
            if name not in SIGNATURES:
                raise JitUnavailableError(f"no kernel {name!r}; known: {sorted(SIGNATURES)}")
            try:
                fn = _load(numba, name, may_compile, notes, keys[name] not in done)
            except JitUnavailableError:
                raise
            except Exception as e:  # numba's errors, or no locator for the cache
                why = f"numba {numba.__version__} could not compile {name} ({_first_line(e)})"
                _write_marker(FAILED, {keys[name]: why})
                raise JitUnavailableError(why) from e
            _COMPILED[name] = fn
        with contextlib.suppress(Exception):  # a numba without this layout: nothing to do
            for f in {_cache_files(_kernel(n))[0] for n in missing}:
                _tighten(f)
        _write_marker(COMPILED, {keys[n]: "compiled" for n in missing})
    return {n: _COMPILED[n] for n in names}


def cached(names: Sequence[str], version: str) -> bool:
    """Whether the kernels ``names`` are in COMPILED for numba ``version`` with their index
    and code in numba's cache (an index alone would make numba compile it, in the
    foreground); JitUnavailableError if one failed to compile with the same numba, sources
    and machine, saying why."""
    check_cache(names)
    keys = _keys(names, version).values()
    done = _read_marker(COMPILED)
    failed = _read_marker(FAILED)
    for k in keys:
        if k in failed and k not in done:
            raise JitUnavailableError(f"{failed[k]} (when it was last tried)")
    if not all(k in done for k in keys):
        return False
    for n in filter(SIGNATURES.__contains__, names):
        try:
            suffixes = {f.suffix for f in _cache_files(_kernel(n))[1]}
        except Exception:  # a numba without this layout: leave it to numba
            continue
        if not {".nbi", ".nbc"} <= suffixes:
            return False
    return True


def _lock(folder: Path, how: int) -> int | None:
    """An open descriptor of COMPILING in ``folder`` locked ``how``: fcntl.LOCK_EX (made
    if need be) or LOCK_SH (only asking: nothing made); None if a compiler holds it; -1 if
    the folder cannot hold a lock (or, asking, has no COMPILING)."""
    try:
        if how == fcntl.LOCK_SH:
            fd = os.open(folder / COMPILING, os.O_RDONLY | _OPEN_FLAGS)
        else:
            folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(folder / COMPILING, os.O_CREAT | os.O_RDWR | _OPEN_FLAGS, 0o600)
    except OSError:
        return -1
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # a FIFO or device in its place
            raise OSError("not a regular file")
        fcntl.flock(fd, how | fcntl.LOCK_NB)
    except OSError as e:
        os.close(fd)
        return None if isinstance(e, BlockingIOError) else -1
    return fd


def compiling(folder: Path) -> bool:
    """Whether a background compiler is at work on the cache ``folder`` (holds its lock)."""
    fd = _lock(folder, fcntl.LOCK_SH)
    if fd is not None and fd >= 0:
        os.close(fd)
    return fd is None


def spawn(cmd: list[str], lock: int) -> None:
    """Start ``cmd`` at the lowest priority through a shell that exits at once, so that the
    process outlives a short run; it inherits the descriptor ``lock`` (-1: none), and with
    it COMPILING's lock. A seam: the tests record the command instead."""
    script = 'nice -n 19 "$@" </dev/null >/dev/null 2>&1 &'
    fds = () if lock < 0 else (lock,)
    subprocess.run(["/bin/sh", "-c", script, "sh", *cmd], check=False, timeout=30, pass_fds=fds)


def compile_in_background(names: Sequence[str]) -> bool:
    """Start ``python -m hapticd.physics.jit`` on ``names`` unless another run's compiler holds
    COMPILING; True if this call started one."""
    lock = _lock(_cache_folder(), fcntl.LOCK_EX)
    if lock is None:
        return False
    try:
        spawn([sys.executable, "-m", "hapticd.physics.jit", *names], lock)
    finally:
        if lock >= 0:
            os.close(lock)  # the compiler holds the lock now
    return True


def choose(mode: str, names: Sequence[str]) -> KernelChoice:
    """The kernels ``names`` of a renderer's plan, as ``mode`` (one of MODES) asks; ValueError
    for another mode."""
    if mode not in MODES:
        raise ValueError(f"unknown kernels mode {mode!r}; expected one of {list(MODES)}")
    if mode == "python" or not names:
        return KernelChoice(mode, "python")
    t0 = time.perf_counter()
    notes: list[str] = []
    try:
        auto = mode == "auto" and any(n not in _COMPILED for n in names)
        if auto and not cached(names, _import_numba().__version__):
            return _in_background(mode, names, None, t0)
        try:
            compiled = compile_kernels(names, may_compile=not auto, notes=notes)
        except DamagedCacheError as e:
            return _in_background(mode, names, str(e), t0)
    except JitUnavailableError as e:
        # The unsafe cache's message says what to do; numba itself is there.
        fix = (
            "Set" if isinstance(e, UnsafeCacheError) else "Install numba (pip install numba) or set"
        )
        return KernelChoice(
            mode,
            "python",
            message=(
                f"rendering.kernels is {mode}, but {e}: the Python kernels render instead "
                f"(the same forces; a slower tick). {fix} rendering.kernels: python to "
                "silence this"
            ),
        )
    note = "; ".join(notes) if notes else None
    return KernelChoice(mode, "compiled", compiled, note=note, seconds=time.perf_counter() - t0)


def _in_background(mode: str, names: Sequence[str], damaged: str | None, t0: float) -> KernelChoice:
    """Python renders this run while a background process compiles ``names``; ``damaged``:
    why the cache was removed (then the text is a message, else a note)."""
    if compile_in_background(names):
        what = f"compiling {', '.join(names)} in the background (once, into {_cache_folder()})"
    else:
        what = f"another run's compiler is compiling the kernels into {_cache_folder()}"
    text = (
        f"rendering.kernels is auto: {what}; this run renders with "
        "the Python kernels (the same forces; a slower tick)"
    )
    seconds = time.perf_counter() - t0
    if damaged is not None:
        return KernelChoice(mode, "python", message=f"{damaged}; {text}", seconds=seconds)
    return KernelChoice(mode, "python", note=text, seconds=seconds)


def compiled(name: str) -> Callable[..., None] | None:
    """Kernel ``name`` compiled (or loaded from the cache), or None when it cannot be here:
    the ``hapticd.compilers`` entry point, through which allocation's ``allocate_many``
    takes its compiled batch kernel without importing physics."""
    try:
        return compile_kernels([name])[name]
    except JitUnavailableError:
        return None


def main(argv: Sequence[str]) -> int:
    """``python -m hapticd.physics.jit NAME...``: compile kernels into the cache at low
    priority (holding COMPILING's lock, inherited from the run that started it)."""
    with contextlib.suppress(OSError):
        os.nice(19)
    try:
        compile_kernels(list(argv))
    except JitUnavailableError as e:
        print(f"hapticd.physics.jit: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
