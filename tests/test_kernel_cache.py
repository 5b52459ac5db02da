"""The kernel cache's owner and mode checks (hapticd.physics.jit.check_cache): numba unpickles
its index and code files, so a cache folder or file another user could have written is never
read, a FIFO in its place blocks nothing, and the run renders with the Python kernels, saying
what is wrong and what to do. Run in this process on a copy of the session's cache (numba's
folder follows NUMBA_CACHE_DIR and numba.config.CACHE_DIR, both set per test)."""

from __future__ import annotations

import contextlib
import os
import pickle
import shutil
import stat
import sys
import threading
from pathlib import Path

import pytest

from hapticd.physics import jit

NAMES = ["safety_step"]
OTHER_UID = 65534  # nobody
as_root = pytest.mark.skipif(os.geteuid() != 0, reason="giving a folder to another user")


class Planted:
    """A pickle that makes the folder ``path`` when it is loaded: what an attacker's index
    would run instead."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return os.mkdir, (str(self.path),)


def _use(monkeypatch, root: Path) -> None:
    """numba's cache and hapticd's markers in ``root`` for this test."""
    import numba

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(root))
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(root))


@pytest.fixture
def cache_copy(tmp_path, monkeypatch) -> tuple[Path, Path, list]:
    """A copy of the session's cache holding safety_step (its record too, so a run loads it
    from there), used by this process with nothing compiled yet; the background compiler
    recorded, not started. The root, safety_step's index file and the recorded starts."""
    jit.compile_kernels(NAMES)  # in the session's cache (compiled there if need be)
    root = tmp_path / "cache"
    skip = shutil.ignore_patterns(jit.COMPILING, "*.lock")
    shutil.copytree(os.environ["NUMBA_CACHE_DIR"], root, ignore=skip)
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    stem = Path(jit._kernel("safety_step").__code__.co_filename).stem  # its module's file
    index = next(root.rglob(f"{stem}.safety_step-*.{tag}.nbi"))
    _use(monkeypatch, root)
    monkeypatch.setattr(jit, "_COMPILED", {})
    started: list = []
    monkeypatch.setattr(jit, "spawn", lambda cmd, lock: started.append(cmd))
    return root, index, started


def _refused(target: Path, problem: str, root: Path) -> None:
    """Both modes render with Python, naming ``target``, its ``problem`` and the fix."""
    for mode in ("auto", "compiled"):
        got = jit.choose(mode, NAMES)
        assert got.used == "python" and not got.kernels, got
        assert f"the kernel cache is unsafe: {target} {problem}" in got.message, got.message
        assert f"rm -r {root}" in got.message and "NUMBA_CACHE_DIR" in got.message
        assert "Install numba" not in got.message


def test_the_session_cache_copy_loads_its_compiled_kernel(cache_copy):
    """The checks pass a cache of this user's own: the kernel is loaded, not compiled."""
    got = jit.choose("compiled", NAMES)
    assert got.used == "compiled" and got.message is None, got
    assert sum(got.kernels["safety_step"].stats.cache_hits.values()) == 1


@as_root
@pytest.mark.parametrize("owned", ["root", "kernel folder", "index"])
def test_a_cache_of_another_user_is_refused_and_its_planted_pickle_never_loaded(
    cache_copy, tmp_path, owned
):
    root, index, started = cache_copy
    ran = tmp_path / "the planted pickle ran"
    index.write_bytes(pickle.dumps(Planted(ran)))
    target = {"root": root, "kernel folder": index.parent, "index": index}[owned]
    os.chown(target, OTHER_UID, OTHER_UID)
    _refused(target, f"belongs to uid {OTHER_UID}, not to uid {os.geteuid()}", root)
    assert not ran.exists(), "numba loaded the planted index"
    assert not started, "a background compiler was started on an unsafe cache"


@pytest.mark.parametrize(
    ("where", "mode"),
    [("root", 0o777), ("root", 0o770), ("kernel folder", 0o757), ("index", 0o664)],
)
def test_a_cache_others_may_write_is_refused(cache_copy, tmp_path, where, mode):
    root, index, started = cache_copy
    ran = tmp_path / "the planted pickle ran"
    index.write_bytes(pickle.dumps(Planted(ran)))
    target = {"root": root, "kernel folder": index.parent, "index": index}[where]
    target.chmod(mode)
    _refused(target, f"has mode {mode:04o}", root)
    assert not ran.exists() and not started


@pytest.mark.parametrize("where", ["root", "kernel folder"])
def test_a_symlinked_cache_folder_is_refused(cache_copy, tmp_path, monkeypatch, where):
    root, index, _ = cache_copy
    if where == "root":
        target = tmp_path / "link"
        target.symlink_to(root)
        _use(monkeypatch, target)
        real, root = root, target
    else:
        target = index.parent
        real = tmp_path / "elsewhere"
        target.rename(real)
        target.symlink_to(real)
    _refused(target, f"is a symbolic link (to {real}), not a directory", root)


def _bounded(call, fifo: Path, what: str):
    """``call()``'s result; if it is still running after 10 s (blocked opening ``fifo``),
    give the FIFO a writer so that it ends, and fail."""
    out: list = []
    worker = threading.Thread(target=lambda: out.append(call()), daemon=True)
    worker.start()
    worker.join(10.0)
    if worker.is_alive():
        with contextlib.suppress(OSError):
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        worker.join(60.0)
        pytest.fail(f"{what} blocked on a FIFO in place of {fifo.name}")
    return out[0]


@pytest.mark.timing("a FIFO that blocks an open is caught by a deadline")
@pytest.mark.parametrize("where", ["index", "record", "lock"])
def test_a_fifo_in_the_cache_blocks_nothing_and_is_refused(cache_copy, where):
    root, index, started = cache_copy
    fifo = {"index": index, "record": root / jit.COMPILED, "lock": root / jit.COMPILING}[where]
    fifo.unlink(missing_ok=True)
    os.mkfifo(fifo, 0o600)
    assert _bounded(lambda: jit.compiling(root), fifo, "asking for the compiler's lock") is False
    got = _bounded(lambda: jit.choose("auto", NAMES), fifo, "choosing the kernels")
    assert got.used == "python", got
    assert f"the kernel cache is unsafe: {fifo} is not a regular file" in got.message, got
    assert not started


def test_the_folders_and_records_hapticd_makes_pass_its_check_under_a_loose_umask(
    tmp_path, monkeypatch
):
    """Made under umask 002 (a lab's shared default), the cache root, numba's folder in it,
    the records and the lock are writable by their owner only, so the next run uses them."""
    jit.compile_kernels(NAMES)  # numba imported, its config there to point elsewhere
    root = tmp_path / "fresh" / "cache"
    _use(monkeypatch, root)
    monkeypatch.setattr(jit, "_COMPILED", {})
    monkeypatch.setattr(jit, "spawn", lambda cmd, lock: None)
    old = os.umask(0o002)
    try:
        got = jit.choose("auto", NAMES)  # not cached: the background compiler's lock is made
        jit._write_marker(jit.COMPILED, {"a kernel": "compiled"})  # as the compiler records
    finally:
        os.umask(old)
    assert got.used == "python" and got.message is None, got
    made = [root, *root.rglob("*")]
    assert {p.name for p in made} >= {"cache", jit.COMPILED, jit.COMPILING}
    loose = {
        str(p): f"{stat.S_IMODE(p.lstat().st_mode):04o}" for p in made if p.lstat().st_mode & 0o022
    }
    assert not loose, loose
    jit.check_cache(NAMES)  # the next run's check passes


@as_root
@pytest.mark.parametrize("unsafe", ["another user's", "writable by all"])
def test_an_unsafe_package_pycache_is_skipped_for_the_users_cache(tmp_path, unsafe):
    """The in-tree cache (``__pycache__`` beside kernels.py) is numba's default only when it
    is safe; else the user's own folder is chosen (made 0700)."""
    pkg = tmp_path / "hapticd"
    pycache = pkg / "__pycache__"
    pycache.mkdir(parents=True)
    env = {"HOME": str(tmp_path / "home")}
    assert jit.cache_dir(pkg, env) is None  # safe: numba's own choice, in the tree
    if unsafe == "another user's":
        os.chown(pycache, OTHER_UID, OTHER_UID)
    else:
        pycache.chmod(0o777)
    user = tmp_path / "home" / ".cache" / "hapticd" / "numba"
    assert jit.cache_dir(pkg, env) == user
    assert stat.S_IMODE(user.stat().st_mode) == 0o700
