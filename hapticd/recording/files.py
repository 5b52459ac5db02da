"""Where recordings may be written, and creating one without following links or blocking.

``record_start`` over the control socket writes only inside the recording
directory (``recording_directory``): a relative name resolves inside it, an
absolute path must lie inside it, and no component may be a symbolic link. A
path given on the command line (``hapticd run --record PATH``) is the user's
own and may be anywhere. Either way the file is created new (``O_EXCL``,
``O_NOFOLLOW``, ``O_NONBLOCK``: never through a link, never blocking on a
FIFO), mode 0640 before the umask; ``overwrite`` writes a temporary file and
renames it over an existing regular file of the same user, and refuses
anything else (a link, a FIFO, a device, another user's file).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
from pathlib import Path, PurePosixPath

from hapticd.recording.format import RecordingError

FILE_MODE = 0o640
DIR_MODE = 0o700
MAX_NAME_BYTES = 4096
_CREATE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC


def state_directory() -> Path:
    """The service's state directory: ``$STATE_DIRECTORY`` (systemd's StateDirectory=),
    else ``$XDG_STATE_HOME/hapticd``, else ``~/.local/state/hapticd``."""
    env = os.environ
    if env.get("STATE_DIRECTORY"):
        return Path(env["STATE_DIRECTORY"].split(":")[0])
    if env.get("XDG_STATE_HOME"):
        return Path(env["XDG_STATE_HOME"]) / "hapticd"
    return Path.home() / ".local" / "state" / "hapticd"


def confine(root: Path, name: str) -> PurePosixPath:
    """``name`` (relative to ``root``, or absolute inside it) as a path relative to ``root``;
    RecordingError for anything that would leave it."""
    if not name or "\x00" in name or len(name.encode("utf-8", "replace")) > MAX_NAME_BYTES:
        raise RecordingError(f"{name!r}: not a usable file name")
    p = PurePosixPath(name)
    if p.is_absolute():
        rel = None
        for base in (root, Path(os.path.realpath(root))):
            with contextlib.suppress(ValueError):
                rel = p.relative_to(base)
                break
        if rel is None:
            raise RecordingError(
                f"{name}: outside the recording directory {root}; record_start writes only "
                "there (give a name relative to it; the directory is recording.directory in "
                "the profile or hapticd run --record-dir)"
            )
        p = rel
    if not p.parts or any(part in ("..", ".") for part in p.parts) or ".." in name.split("/"):
        raise RecordingError(
            f"{name}: must name a file inside the recording directory {root} (no '..')"
        )
    return p


def _open_dir(path: Path, *, create: bool) -> int:
    if create:
        path.mkdir(mode=DIR_MODE, parents=True, exist_ok=True)
    return os.open(path, _DIR)


def _subdir(dfd: int, part: str, shown: Path) -> int:
    """Open (creating, 0700) the directory ``part`` under ``dfd``, never through a link."""
    with contextlib.suppress(FileExistsError):
        os.mkdir(part, DIR_MODE, dir_fd=dfd)
    try:
        return os.open(part, _DIR | os.O_NOFOLLOW, dir_fd=dfd)
    except OSError as exc:
        raise RecordingError(
            f"{shown}: not a directory of its own (a symbolic link or a file?): "
            f"{exc.strerror or exc}"
        ) from None


def _kind(mode: int) -> str:
    if stat.S_ISLNK(mode):
        return "a symbolic link"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "not a regular file"


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def create(
    path: str | Path,
    header: bytes,
    *,
    overwrite: bool,
    root: Path | None = None,
    mode: int = FILE_MODE,
) -> tuple[int, Path]:
    """Create the recording ``path`` holding ``header``; return (its open fd, its path).
    ``mode``: the new file's mode before the umask.

    With ``root``, ``path`` is confined to it (``confine``) and every directory below
    ``root`` is opened without following links (missing ones are created 0700).
    RecordingError names the file and the problem; nothing existing is touched on error.
    """
    if root is not None:
        rel = confine(root, str(path))
        shown = root / rel
        try:
            dfd = _open_dir(root, create=True)
        except OSError as exc:
            raise RecordingError(
                f"recording directory {root}: cannot open: {exc.strerror or exc}"
            ) from None
        try:
            for i, part in enumerate(rel.parts[:-1]):
                sub = _subdir(dfd, part, root.joinpath(*rel.parts[: i + 1]))
                os.close(dfd)
                dfd = sub
        except BaseException:
            os.close(dfd)
            raise
        name = rel.name
    else:
        shown = Path(path)
        name = shown.name
        if not name or name in ("..", "."):
            raise RecordingError(f"{path}: not a file name")
        try:
            dfd = os.open(shown.parent, _DIR)
        except OSError as exc:
            raise RecordingError(f"{shown}: cannot create: {exc.strerror or exc}") from None
    try:
        return _create_in(dfd, name, shown, header, overwrite, mode), shown
    finally:
        os.close(dfd)


def _create_in(dfd: int, name: str, shown: Path, header: bytes, overwrite: bool, mode: int) -> int:
    if overwrite:
        try:
            st = os.stat(name, dir_fd=dfd, follow_symlinks=False)
        except FileNotFoundError:
            st = None
        except OSError as exc:
            raise RecordingError(f"{shown}: cannot create: {exc.strerror or exc}") from None
        if st is not None:
            if not stat.S_ISREG(st.st_mode):
                raise RecordingError(f"{shown}: is {_kind(st.st_mode)}; not replacing it")
            if st.st_uid != os.geteuid():
                raise RecordingError(
                    f"{shown}: belongs to another user (uid {st.st_uid}); not replacing it"
                )
        target = f".{name}.{secrets.token_hex(6)}.tmp" if st is not None else name
    else:
        target = name
    try:
        fd = os.open(target, _CREATE, mode, dir_fd=dfd)
    except FileExistsError:
        raise RecordingError(
            f"{shown}: exists; not overwriting it (overwrite replaces a regular file)"
        ) from None
    except OSError as exc:
        raise RecordingError(f"{shown}: cannot create: {exc.strerror or exc}") from None
    try:
        os.set_blocking(fd, True)
        _write_all(fd, header)
        if target != name:
            os.rename(target, name, src_dir_fd=dfd, dst_dir_fd=dfd)
    except OSError as exc:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(target, dir_fd=dfd)
        raise RecordingError(f"{shown}: cannot create: {exc.strerror or exc}") from None
    return fd


def identity(fd: int) -> tuple[int, int]:
    """(device, inode) of an open file: which file a path must still name to be ours."""
    st = os.fstat(fd)
    return st.st_dev, st.st_ino


def remove_if_ours(path: Path, ident: tuple[int, int]) -> None:
    """Delete ``path`` if it still is the file ``ident`` (a recording that never began)."""
    try:
        there = os.stat(path, follow_symlinks=False)
    except OSError:
        return
    if (there.st_dev, there.st_ino) == ident:
        with contextlib.suppress(OSError):
            os.unlink(path)
