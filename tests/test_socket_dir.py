"""The default socket directory is checked as ssh-agent and tmux check theirs: another
user who plants /tmp/hapticd-UID (a symlink to their directory, their own 0777
directory) or $XDG_RUNTIME_DIR/hapticd gets neither the daemon's socket nor a client."""

from __future__ import annotations

import os
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from hapticd import control
from hapticd.cli import main
from hapticd.control import ControlClient, UnsafeSocketDirError, check_socket_dir
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from tests.conftest import GRASP_PROFILE


@pytest.fixture(params=["tmp", "xdg"])
def own_dir(request, monkeypatch) -> Iterator[Path]:
    """hapticd's own socket directory, reached through the default path: /tmp/hapticd-UID
    (with /tmp moved into a folder of the test's) or $XDG_RUNTIME_DIR/hapticd."""
    for var in ("HAPTICD_SOCKET", "RUNTIME_DIRECTORY", "XDG_RUNTIME_DIR"):
        monkeypatch.delenv(var, raising=False)
    # A short folder in /tmp, not tmp_path: a Unix socket's path has at most 107 bytes, and
    # pytest's temporary folders grow deeper with every run on a machine.
    with tempfile.TemporaryDirectory(prefix="hd-", dir="/tmp") as short:
        yield from _own_dir(request.param, Path(short) / "base", monkeypatch)


def _own_dir(kind: str, base: Path, monkeypatch) -> Iterator[Path]:
    base.mkdir()
    if kind == "tmp":
        monkeypatch.setattr(control, "TMP_DIR", base)
        d = base / f"hapticd-{os.getuid()}"
    else:
        monkeypatch.setenv("XDG_RUNTIME_DIR", str(base))
        d = base / "hapticd"
    assert control.default_socket_path() == d / "control.sock"
    yield d


def _plant(kind: str, d: Path, tmp_path: Path) -> Path:
    """Put what an attacker would at ``d``; returns where a socket would land."""
    theirs = tmp_path / "attacker"
    theirs.mkdir(mode=0o777)
    theirs.chmod(0o777)
    if kind == "symlink":
        d.symlink_to(theirs, target_is_directory=True)
        return theirs / "control.sock"
    if kind == "0777 directory":
        d.mkdir()
        d.chmod(0o777)
        return d / "control.sock"
    d.write_text("not a directory\n")  # a file
    return d / "control.sock"


@pytest.mark.parametrize(
    ("kind", "says"),
    [
        ("symlink", "is a symbolic link"),
        ("0777 directory", "has mode 0777"),
        ("file", "is not a directory"),
    ],
)
def test_the_daemon_refuses_a_planted_socket_directory(own_dir, tmp_path, kind, says, capsys):
    landed = _plant(kind, own_dir, tmp_path)
    session = build_session(load_profile(GRASP_PROFILE), paced=False)
    server = ControlServer(session, control.default_socket_path())
    with pytest.raises(UnsafeSocketDirError, match=says):
        server.start()
    server.close()
    assert not landed.exists()
    # The same through the command line: a clear message, no traceback, exit 1.
    assert main(["run", str(GRASP_PROFILE), "--duration", "0.01", "-q"]) == 1
    err = capsys.readouterr().err
    assert f"unsafe socket directory {own_dir}" in err and says in err
    assert "Traceback" not in err
    assert not landed.exists()


@pytest.mark.parametrize("kind", ["symlink", "0777 directory"])
def test_the_client_refuses_to_talk_through_a_planted_directory(own_dir, tmp_path, kind):
    landed = _plant(kind, own_dir, tmp_path)
    # Someone else's listener waits there for what a client would send.
    trap = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    with trap:
        trap.bind(str(landed))
        trap.listen(1)
        with pytest.raises(UnsafeSocketDirError, match="unsafe socket directory"):
            ControlClient()
        assert main(["status"]) == 1


def test_a_directory_of_another_owner_is_refused(own_dir):
    # The tests run as one user: the uid compared against is the seam.
    uid = os.getuid() + 1000
    d = own_dir if own_dir.name == "hapticd" else control.TMP_DIR / f"hapticd-{uid}"
    d.mkdir(mode=0o700)  # a proper directory, but this user's, not uid's
    with pytest.raises(UnsafeSocketDirError, match=f"belongs to uid {os.getuid()}, not to uid"):
        check_socket_dir(d / "control.sock", uid=uid)
    with pytest.raises(UnsafeSocketDirError, match="belongs to uid"):
        check_socket_dir(d / "control.sock", create=True, uid=uid)


def test_an_absent_directory_is_made_0700_and_served(own_dir):
    session = build_session(load_profile(GRASP_PROFILE), paced=False)
    server = ControlServer(session, control.default_socket_path())
    server.start()
    try:
        st = own_dir.lstat()
        assert st.st_mode & 0o777 == 0o700 and st.st_uid == os.getuid()
        with ControlClient() as c:
            assert c.status()["tick"] == 0
    finally:
        server.close()


def test_a_directory_the_user_chose_is_not_second_guessed(tmp_path):
    chosen = tmp_path / "shared"
    chosen.mkdir()
    chosen.chmod(0o755)
    check_socket_dir(chosen / "control.sock", create=True)  # no error: --socket is explicit
