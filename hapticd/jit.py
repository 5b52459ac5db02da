"""Compiles the kernels of ``hapticd.kernels`` with numba, before the first tick, cached on disk.

``choose(mode, names)`` is what a renderer is built with: ``mode`` is the profile's
``rendering.kernels`` (``python``: never compile; ``compiled`` or ``auto``:
compile ``names``, the kernels the renderer's plan uses). Any failure (numba
missing or broken, a kernel that does not compile) falls back to the Python
code with a message saying why; both paths give the same forces (tests prove it).

Kernels are compiled eagerly for one signature (the frame's and the object's
arrays; ``SIGNATURES``), so no call in the loop can trigger a compilation, and
cached (numba's ``cache=True``): a first run compiles (about 1-2 s a kernel on
this 2-core machine), later runs load the machine code in milliseconds. The cache
sits in ``__pycache__`` beside ``hapticd/kernels.py`` when that folder is writable
(a source tree, an editable install); otherwise (a system-wide install, a
service) in ``$NUMBA_CACHE_DIR`` if set, else ``$CACHE_DIRECTORY`` (systemd's
``CacheDirectory=``), ``$XDG_CACHE_HOME/hapticd/numba`` or
``~/.cache/hapticd/numba``; with none writable the kernels compile on every run.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

MODES = ("python", "compiled", "auto")

# numba's signature of each kernel: the frame's fields and the object's state are
# C-contiguous float64 (uint8 for in_contact), the scalars float64 or int64.
SIGNATURES = {
    "free_body_step": (
        "void(u1[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1], f8[::1], f8[:, ::1],"
        " f8[:, ::1], f8[:, ::1])"
    ),
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
    ``seconds``: how long compiling or loading the cache took."""

    mode: str
    used: str
    kernels: dict[str, Callable[..., None]] = field(default_factory=dict)
    message: str | None = None
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


def compile_kernels(names: Sequence[str]) -> dict[str, Callable[..., None]]:
    """The kernels ``names`` compiled (or loaded from the cache); JitUnavailableError if not."""
    missing = [n for n in names if n not in _COMPILED]
    if missing:
        from hapticd import kernels

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
        for name in missing:
            if name not in SIGNATURES:
                raise JitUnavailableError(f"no kernel {name!r}; known: {sorted(SIGNATURES)}")
            try:
                fn = numba.njit(SIGNATURES[name], cache=True, nogil=True)(getattr(kernels, name))
            except Exception as e:  # numba's errors, or no locator for the cache
                raise JitUnavailableError(
                    f"numba {numba.__version__} could not compile {name} "
                    f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
                ) from e
            _COMPILED[name] = fn
    return {n: _COMPILED[n] for n in names}


def choose(mode: str, names: Sequence[str]) -> KernelChoice:
    """The kernels for a renderer whose plan uses ``names``, as ``mode`` asks (one of MODES)."""
    if mode not in MODES:
        raise ValueError(f"unknown kernels mode {mode!r}; expected one of {list(MODES)}")
    if mode == "python" or not names:
        return KernelChoice(mode, "python")
    t0 = time.perf_counter()
    try:
        compiled = compile_kernels(names)
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
    return KernelChoice(mode, "compiled", compiled, seconds=time.perf_counter() - t0)
