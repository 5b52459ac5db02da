"""The installed service: `hapticd service unit` (this install's hapticd, the profile, the
user and group, directories, limits, watchdog; verified by systemd-analyze; an invalid
profile refused), the socket shared with one group (directory 0750, socket 0660, the same
ownership and symlink checks), and clients that find the service's socket by themselves."""

from __future__ import annotations

import configparser
import grp
import json
import os
import shlex
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from hapticd import control
from hapticd.cli import main
from hapticd.cli.service import hapticd_command
from hapticd.control import ControlClient, UnsafeSocketDirError, check_socket_dir
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.profile import load_profile
from tests.conftest import GRASP_PROFILE, ROOT, wait_for

REHEARSE = ROOT / "configs" / "rehearse-grasp.yaml"


def _unit(tmp_path: Path, *args: str) -> tuple[int, str]:
    out = tmp_path / "hapticd.service"
    code = main(["service", "unit", *args, "--out", str(out)])
    return code, out.read_text() if out.exists() else ""


def _parse(text: str) -> configparser.ConfigParser:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit.read_string(text)
    return unit


def test_the_unit_runs_this_install_on_the_profile_as_the_user_for_the_group(tmp_path):
    code, text = _unit(
        tmp_path, "--profile", str(REHEARSE), "--user", "rig", "--group", "experimenters"
    )
    assert code == 0
    svc = _parse(text)["Service"]
    exec_start = svc["ExecStart"].split()
    exe = exec_start[0]
    # This installation's hapticd, by an absolute path that exists and runs.
    assert os.path.isabs(exe) and os.access(exe, os.X_OK)
    assert exec_start[: len(hapticd_command())] == hapticd_command()
    assert Path(exe).parent == Path(os.path.abspath(sys.executable)).parent
    rest = exec_start[len(hapticd_command()) :]
    assert rest == ["run", str(REHEARSE), "--socket-group", "experimenters"]
    assert svc["User"] == "rig" and svc["Group"] == "experimenters"
    assert svc["Type"] == "notify" and svc["WatchdogSec"] == "2s"
    assert svc["ExecReload"].endswith("kill -HUP $MAINPID")
    assert os.access(svc["ExecReload"].split()[0], os.X_OK)
    assert (svc["RuntimeDirectory"], svc["RuntimeDirectoryMode"]) == ("hapticd", "0750")
    assert (svc["StateDirectory"], svc["StateDirectoryMode"]) == ("hapticd", "0750")
    assert svc["LimitRTPRIO"] == "99" and svc["LimitMEMLOCK"] == "infinity"
    # A crash (exit 1 after a traceback) restarts; a clean stop, a bad profile (2) and a
    # latched fault (3) do not; a daemon failing at once is not restarted forever.
    assert svc["Restart"] == "on-failure" and svc["RestartPreventExitStatus"] == "2 3"
    unit = _parse(text)["Unit"]
    assert int(unit["StartLimitBurst"]) >= 1 and int(unit["StartLimitIntervalSec"]) > 0
    assert "LD_LIBRARY_PATH" not in text  # the rehearsal's devices need no SDK
    assert "RestrictRealtime" not in svc  # it would forbid SCHED_FIFO
    assert _parse(text)["Install"]["WantedBy"] == "multi-user.target"
    # The command it runs is the one that works: its own help, here.
    got = subprocess.run([*hapticd_command(), "run", "--help"], capture_output=True, text=True)
    assert got.returncode == 0 and "--socket-group" in got.stdout


def test_the_unit_prints_to_stdout_by_default(capsys):
    assert main(["service", "unit", "--profile", str(REHEARSE)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("# hapticd as a systemd service") and "[Service]" in out
    assert "User=hapticd" in out and "Group=hapticd" in out


def test_systemd_analyze_verifies_the_unit_without_a_word(tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("no systemd-analyze here (apt-get install systemd)")
    code, _ = _unit(tmp_path, "--profile", str(REHEARSE))
    assert code == 0
    got = subprocess.run(
        [analyze, "verify", str(tmp_path / "hapticd.service")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert got.returncode == 0, got.stderr
    assert got.stdout.strip() == "" and got.stderr.strip() == ""
    # It would have said so: a unit with a key systemd does not know gets a warning.
    bad = tmp_path / "bad.service"
    bad.write_text(
        (tmp_path / "hapticd.service").read_text().replace("[Service]", "[Service]\nNoSuchKey=1")
    )
    got = subprocess.run([analyze, "verify", str(bad)], capture_output=True, text=True, timeout=60)
    assert "NoSuchKey" in got.stdout + got.stderr


@pytest.mark.slow
def test_the_units_command_serves_the_group_where_systemd_would_put_it(tmp_path):
    """The unit's ExecStart= as systemd would run it (its runtime and state directories in
    the environment; the group this user's own, as the service user's is): the daemon
    serves $RUNTIME_DIRECTORY/control.sock, 0660 in a 0750 directory of that group, and a
    client reaches it there."""
    group = grp.getgrgid(os.getgid()).gr_name
    code, text = _unit(tmp_path, "--profile", str(REHEARSE), "--group", group)
    assert code == 0
    command = shlex.split(_parse(text)["Service"]["ExecStart"])
    run, state = tmp_path / "run" / "hapticd", tmp_path / "state"
    run.mkdir(parents=True)
    run.chmod(0o750)  # as RuntimeDirectory= and its Mode= leave it: of User= and Group=
    state.mkdir()
    env = {**os.environ, "RUNTIME_DIRECTORY": str(run), "STATE_DIRECTORY": str(state)}
    env.pop("HAPTICD_SOCKET", None)
    proc = subprocess.Popen(
        [*command, "--duration", "30", "--no-realtime", "-q"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    sock = run / "control.sock"
    try:
        wait_for(lambda: proc.poll() is not None or sock.exists(), "the socket", timeout_s=30)
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        st_d, st_s = os.lstat(run), os.lstat(sock)
        assert stat.S_IMODE(st_d.st_mode) == 0o750 and st_d.st_gid == os.getgid()
        assert stat.S_IMODE(st_s.st_mode) == 0o660 and st_s.st_gid == os.getgid()
        with ControlClient(sock) as c:
            assert c.status()["profile"] == "grasp-stiffness"
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    assert proc.returncode == 0


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--profile", "missing.yaml"], "missing.yaml"),
        (["--profile", "BROKEN"], "stifness"),
        (["--profile", str(REHEARSE), "--user", "root;rm"], "--user"),
        (["--profile", str(REHEARSE), "--group", ""], "--group"),
    ],
)
def test_a_unit_for_a_profile_that_does_not_validate_is_refused(
    tmp_path, capsys, monkeypatch, args, says
):
    broken = tmp_path / "broken.yaml"
    broken.write_text(
        GRASP_PROFILE.read_text().replace("stiffness_n_per_m: 60.0", "stifness_n_per_m: 60.0")
    )
    monkeypatch.chdir(tmp_path)
    args = [str(broken) if a == "BROKEN" else a for a in args]
    code, text = _unit(tmp_path, *args)
    assert code == 2 and text == ""
    err = capsys.readouterr().err
    assert says in err and "no unit printed" in err and "Traceback" not in err


# -- what the unit says, as systemd reads it back --------------------------------------------

C_ESCAPES = {"a": "\a", "b": "\b", "f": "\f", "n": "\n", "r": "\r", "t": "\t", "v": "\v"}
C_ESCAPES |= {"\\": "\\", '"': '"', "'": "'", "s": " "}


def _doubled(value: str, char: str, what: str) -> str:
    """systemd's pass over ``char`` (``%``: specifiers, the whole line; ``$``: variables, one
    Exec argument): doubled is literal; any other use would be expanded, so the test fails
    on it (the unit meant a literal)."""
    out, i = [], 0
    while i < len(value):
        if value[i] == char:
            assert value[i + 1 : i + 2] == char, f"a {what} systemd would expand: {value!r}"
            i += 1
        out.append(value[i])
        i += 1
    return "".join(out)


def _specifiers(value: str) -> str:
    return _doubled(value, "%", "specifier")


def _exec_words(line: str) -> list[str]:
    """An Exec line's arguments as systemd.service's "Command lines" reads them: specifiers,
    then words split on blanks, each bare or quoted ("..." or '...') with C escapes, then
    each word's variables."""
    line = _specifiers(line)
    words, i = [], 0
    while i < len(line):
        if line[i] in " \t":
            i += 1
            continue
        word: list[str] = []
        quote = None
        while i < len(line) and (quote is not None or line[i] not in " \t"):
            c = line[i]
            if c == "\\":
                esc = line[i + 1]
                assert esc in C_ESCAPES, f"an escape this parser does not know: {line!r}"
                word.append(C_ESCAPES[esc])
                i += 2
                continue
            if quote is None and c in "\"'" and not word:
                quote = c
            elif c == quote:
                quote = None
                assert i + 1 == len(line) or line[i + 1] in " \t", f"text after a quote: {line!r}"
            else:
                word.append(c)
            i += 1
        assert quote is None, f"an unclosed quote: {line!r}"
        words.append(_doubled("".join(word), "$", "variable"))
    return words


def _odd_profile(tmp_path: Path, folder: str, name: str) -> Path:
    d = tmp_path / folder
    d.mkdir()
    path = d / "rig.yaml"
    path.write_text(
        REHEARSE.read_text().replace("name: grasp-stiffness", f"name: {json.dumps(name)}", 1)
    )
    return path


def test_the_test_parser_reads_systemds_quoting():
    assert _exec_words(r'/bin/x "a b" c\sd "q\"x" "$$HOME" %%h') == [
        "/bin/x",
        "a b",
        "c d",
        'q"x',
        "$HOME",
        "%h",
    ]
    with pytest.raises(AssertionError, match="specifier"):
        _exec_words("/bin/x %h")
    with pytest.raises(AssertionError, match="variable"):
        _exec_words("/bin/x $HOME")


@pytest.mark.parametrize(
    ("folder", "name"),
    [
        ('100% $HOME ${USER} "it\'s" \\back', "rig 100% $USER"),
        ("plain", "%n %% $$ ; \\ \" '"),
    ],
)
def test_percent_dollar_quotes_and_spaces_reach_systemd_literally(tmp_path, folder, name):
    profile = _odd_profile(tmp_path, folder, name)
    code, text = _unit(tmp_path, "--profile", str(profile))
    assert code == 0
    svc = _parse(text)["Service"]
    assert _exec_words(svc["ExecStart"]) == [
        *hapticd_command(),
        "run",
        str(profile),
        "--socket-group",
        "hapticd",
    ]
    unit = _parse(text)["Unit"]
    assert _specifiers(unit["Description"]) == f"hapticd haptic rendering daemon ({name})"
    # The reload still signals the main process: $MAINPID is the one variable meant.
    assert svc["ExecReload"].endswith(" -HUP $MAINPID")
    if "Documentation" in unit:
        assert " " not in _specifiers(unit["Documentation"])  # one URL, not a list


@pytest.mark.parametrize("char", ["\n", "\r", "\t", "\x00", "\x1b", "\x7f", "\x85", "\x9b"])
def test_a_profile_name_with_a_control_character_is_refused(tmp_path, capsys, char):
    name = f"rig{char}[Service]{char}ExecStartPre=+/usr/bin/touch /tmp/owned"
    profile = _odd_profile(tmp_path, "p", name)
    code, text = _unit(tmp_path, "--profile", str(profile))
    assert code == 2 and text == ""
    err = capsys.readouterr().err
    assert "the profile's name" in err and "'name'" in err and str(profile) in err
    assert "control character" in err and "Traceback" not in err


def test_a_profile_path_with_a_newline_is_refused(tmp_path, capsys):
    profile = _odd_profile(tmp_path, "x\n[Service]\nExecStartPre=+touch owned\n", "rig")
    code, text = _unit(tmp_path, "--profile", str(profile))
    assert code == 2 and text == ""
    err = capsys.readouterr().err
    assert "the profile's path (--profile)" in err and "control character" in err


def test_the_unit_text_refuses_control_characters_in_every_value():
    from hapticd.cli.service import unit_text

    good = dict(name="rig", user="u", group="g", docs=None, kill="/bin/kill")
    unit_text(["/opt/h"], Path("/etc/p.yaml"), **good)  # type: ignore[arg-type]
    cases = [
        (["/opt/h\n"], Path("/p"), {}, "hapticd command"),
        (["/opt/h"], Path("/p"), {"kill": "/bin/kill\nX=1"}, "kill"),
        (["/opt/h"], Path("/p"), {"user": "u\x85"}, "--user"),
        (["/opt/h"], Path("/p"), {"group": "g\t"}, "--group"),
        (["/opt/h"], Path("/p"), {"docs": Path("/d\n.md")}, "docs"),
    ]
    for command, profile, change, source in cases:
        with pytest.raises(ValueError, match="control character") as got:
            unit_text(command, profile, **{**good, **change})  # type: ignore[arg-type]
        assert source in str(got.value)


def test_out_never_follows_a_symbolic_link_planted_there(tmp_path, capsys):
    precious = tmp_path / "shadow"
    precious.write_text("root:secret\n")
    planted = tmp_path / "hapticd.service"
    planted.symlink_to(precious)
    code = main(["service", "unit", "--profile", str(REHEARSE), "--out", str(planted)])
    assert code == 2
    assert precious.read_text() == "root:secret\n"
    assert planted.is_symlink()
    err = capsys.readouterr().err
    assert str(planted) in err and "symbolic link" in err and "Traceback" not in err
    # A dangling link is not followed either: nothing is created where it points.
    dangling = tmp_path / "other.service"
    dangling.symlink_to(tmp_path / "made-through-the-link")
    assert main(["service", "unit", "--profile", str(REHEARSE), "--out", str(dangling)]) == 2
    assert not (tmp_path / "made-through-the-link").exists()


def test_out_replaces_a_unit_of_this_user_whole(tmp_path):
    out = tmp_path / "hapticd.service"
    out.write_text("stale line\n" * 10_000)
    assert main(["service", "unit", "--profile", str(REHEARSE), "--out", str(out)]) == 0
    text = out.read_text()
    assert text.startswith("# hapticd as a systemd service") and "stale line" not in text
    assert stat.S_IMODE(os.lstat(out).st_mode) == 0o644 & ~_umask()
    assert [p.name for p in tmp_path.iterdir()] == ["hapticd.service"]  # no temp file left


def _umask() -> int:
    old = os.umask(0o22)
    os.umask(old)
    return old


# -- the socket shared with a group -------------------------------------------------------


def _server(path: Path, gid: int) -> ControlServer:
    session = build_session(load_profile(GRASP_PROFILE), paced=False)
    server = ControlServer(session, path, socket_group=gid)
    server.start()
    return server


def test_a_socket_shared_with_a_group_is_0660_in_a_0750_directory_of_that_group(tmp_path):
    gid = os.getgid()  # a group this user is in: the only kind it may give files to
    d = tmp_path / "run" / "hapticd"
    server = _server(d / "control.sock", gid)
    try:
        st_d, st_s = os.lstat(d), os.lstat(d / "control.sock")
        assert stat.S_IMODE(st_d.st_mode) == 0o750 and st_d.st_gid == gid
        assert stat.S_ISSOCK(st_s.st_mode)
        assert stat.S_IMODE(st_s.st_mode) == 0o660 and st_s.st_gid == gid
        with ControlClient(d / "control.sock") as c:
            assert c.status()["profile"] == "grasp-stiffness"
    finally:
        server.close()


def test_the_users_own_directory_shared_with_a_group_still_serves_the_user(tmp_path, monkeypatch):
    """`hapticd run --socket-group G` on the default path: $XDG_RUNTIME_DIR/hapticd becomes
    0750 of G, and the user's own clients (which check that directory) still talk."""
    for var in ("HAPTICD_SOCKET", "RUNTIME_DIRECTORY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    path = control.default_socket_path()
    server = _server(path, os.getgid())
    try:
        assert stat.S_IMODE(os.lstat(path.parent).st_mode) == 0o750
        with ControlClient() as c:
            assert c.status()["profile"] == "grasp-stiffness"
    finally:
        server.close()
    path.parent.chmod(0o770)  # a group that may write could plant a socket: refused
    with pytest.raises(UnsafeSocketDirError, match="has mode 0770"):
        check_socket_dir(path)


@pytest.mark.parametrize("mode", [0o700, 0o755, 0o777])
def test_a_directory_that_existed_before_is_never_repermissioned(tmp_path, mode):
    """A directory hapticd did not make (a home directory, root's 0700 one) is not
    opened to the group for good: refused, its mode and group as they were."""
    d = tmp_path / "existing"
    d.mkdir()
    d.chmod(mode)
    before = os.lstat(d)
    with pytest.raises(UnsafeSocketDirError, match="existed before") as got:
        check_socket_dir(d / "control.sock", create=True, group=os.getgid())
    assert "chmod 750" in str(got.value) and "--socket" in str(got.value)
    after = os.lstat(d)
    assert (after.st_mode, after.st_gid) == (before.st_mode, before.st_gid)
    assert not (d / "control.sock").exists()


def test_an_existing_directory_already_shared_with_the_group_serves_unchanged(tmp_path):
    """systemd's RuntimeDirectory= (0750, of User= and Group=), or a daemon's before."""
    d = tmp_path / "shared"
    d.mkdir()
    d.chmod(0o750)
    server = _server(d / "control.sock", os.getgid())
    try:
        assert stat.S_IMODE(os.lstat(d).st_mode) == 0o750
        with ControlClient(d / "control.sock") as c:
            assert c.status()["profile"] == "grasp-stiffness"
    finally:
        server.close()


def test_a_shared_socket_directory_that_is_a_symlink_is_refused(tmp_path):
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    theirs.chmod(0o777)
    d = tmp_path / "link"
    d.symlink_to(theirs, target_is_directory=True)
    with pytest.raises(UnsafeSocketDirError, match="is a symbolic link"):
        _server(d / "control.sock", os.getgid())
    assert not (theirs / "control.sock").exists()
    assert stat.S_IMODE(os.lstat(theirs).st_mode) == 0o777  # not followed, not changed


@pytest.mark.skipif(os.getuid() != 0, reason="needs root to make a directory of another user")
def test_a_shared_socket_directory_of_another_user_is_refused(tmp_path):
    d = tmp_path / "theirs"
    d.mkdir(mode=0o750)
    os.chown(d, 65534, -1)  # nobody's
    with pytest.raises(UnsafeSocketDirError, match="belongs to uid 65534"):
        check_socket_dir(d / "control.sock", create=True, group=os.getgid())


NOBODY = 65534
CLIENT = (
    "import sys; from hapticd.control import ControlClient\n"
    "try:\n"
    "    with ControlClient(sys.argv[1], timeout_s=10) as c: print(c.status()['profile'])\n"
    "except PermissionError as exc: print('refused', exc.errno)\n"
)


def _system_python() -> str | None:
    """An interpreter another user may run (this one may live in root's home), new
    enough for the client, which needs nothing but the standard library."""
    for exe in ("/usr/bin/python3", "/usr/local/bin/python3"):
        if os.access(exe, os.X_OK):
            got = subprocess.run(
                [exe, "-c", "import sys; print(sys.version_info >= (3, 11))"],
                capture_output=True,
                text=True,
            )
            if got.stdout.strip() == "True":
                return exe
    return None


@pytest.mark.skipif(os.getuid() != 0, reason="needs root to run a client as another user")
def test_another_user_reaches_the_daemon_only_through_the_group(tmp_path):
    """The daemon (here root, as the service user) shares its socket with a group; a client
    run as another user connects when it is in that group, and is refused when not."""
    python = _system_python()
    if python is None:
        pytest.skip("no system python3 >= 3.11 that another user may run")
    base = Path(tempfile.mkdtemp(prefix="hapticd-group-", dir="/tmp"))
    try:
        base.chmod(0o755)  # as /run: anyone may look for the socket's directory
        group = 54321  # a group of its own, as the experimenters' is
        # The client's code where the other user may read it: the clone this runs from may
        # sit below a directory only root may enter (a `mktemp -d` folder is 0700).
        lib = base / "lib"
        shutil.copytree(ROOT / "hapticd", lib / "hapticd", ignore=shutil.ignore_patterns("*.pyc"))
        for d, _, files in os.walk(lib):
            os.chmod(d, 0o755)
            for f in files:
                os.chmod(os.path.join(d, f), 0o644)
        sock = base / "hapticd" / "control.sock"
        server = _server(sock, group)
        try:
            results = {}
            for name, extra in (("member", [group]), ("stranger", [])):
                got = subprocess.run(
                    [python, "-c", CLIENT, str(sock)],
                    user=NOBODY,
                    group=NOBODY,
                    extra_groups=extra,
                    env={"PYTHONPATH": str(lib), "PATH": "/usr/bin:/bin"},
                    capture_output=True,
                    text=True,
                    timeout=60,
                )
                results[name] = (got.stdout.strip(), got.stderr.strip()[-500:])
        finally:
            server.close()
    finally:
        shutil.rmtree(base, ignore_errors=True)
    assert results["member"][0] == "grasp-stiffness", results
    assert results["stranger"][0] == "refused 13", results  # EACCES: not in the group


def test_run_names_an_unknown_socket_group(capsys):
    code = main(["run", str(GRASP_PROFILE), "--socket-group", "no-such-group-here", "-q"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--socket-group no-such-group-here: no such group" in err


# -- clients find the service's socket ------------------------------------------------------


@pytest.fixture
def no_own_socket(tmp_path, monkeypatch) -> Path:
    """A client environment with no socket of its own (as an experimenter's login shell
    has, $XDG_RUNTIME_DIR without a hapticd in it) and the service's socket moved into
    tmp_path; returns the service's socket path."""
    for var in ("HAPTICD_SOCKET", "RUNTIME_DIRECTORY"):
        monkeypatch.delenv(var, raising=False)
    xdg = tmp_path / "xdg"
    xdg.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(xdg))
    service = tmp_path / "run" / "hapticd" / "control.sock"
    monkeypatch.setattr(control, "SERVICE_SOCKET", service)
    return service


def test_a_client_finds_the_services_socket_without_being_told(no_own_socket, capsys):
    assert control.client_socket_path() == control.default_socket_path()  # no service yet
    server = _server(no_own_socket, os.getgid())
    try:
        assert control.client_socket_path() == no_own_socket
        with ControlClient() as c:
            assert c.status()["profile"] == "grasp-stiffness"
        assert main(["status"]) == 0
        assert "grasp-stiffness" in capsys.readouterr().out
    finally:
        server.close()


def test_a_clients_own_daemon_and_its_environment_come_before_the_service(
    no_own_socket, tmp_path, monkeypatch
):
    no_own_socket.parent.mkdir(parents=True)
    no_own_socket.touch()  # the service's, as far as the lookup goes
    own = control.default_socket_path()
    own.parent.mkdir(mode=0o700)
    own.touch()
    assert control.client_socket_path() == own
    own.unlink()
    assert control.client_socket_path() == no_own_socket
    monkeypatch.setenv("HAPTICD_SOCKET", str(tmp_path / "x.sock"))
    assert control.client_socket_path() == tmp_path / "x.sock"


def test_a_client_refuses_a_service_directory_others_can_write(no_own_socket):
    no_own_socket.parent.mkdir(parents=True)
    no_own_socket.parent.chmod(0o777)
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.bind(str(no_own_socket))
        with pytest.raises(UnsafeSocketDirError, match="another user could plant a socket"):
            ControlClient()


def test_the_unit_carries_the_sdks_library_path_when_the_profile_needs_one(tmp_path, monkeypatch):
    """A Force Dimension rig: the folder of the library the device key names (a space and
    a percent in it, read back literally), else of $HAPTICD_LIBDHD, which is passed on."""
    import yaml

    sdk = tmp_path / "force dimension 100%" / "lib"
    data = yaml.safe_load((ROOT / "configs" / "rigs" / "two-omega3.yaml").read_text())
    data["fingers"][0]["device"]["library"] = str(sdk / "libdrd.so.3")
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump(data))
    monkeypatch.setenv("HAPTICD_LIBDHD", "/opt/fd/lib/libdrd.so")
    code, text = _unit(tmp_path, "--profile", str(rig))
    assert code == 0, text
    env = [line.removeprefix("Environment=") for line in text.splitlines()
           if line.startswith("Environment=")]  # fmt: skip
    assert f'"LD_LIBRARY_PATH={str(sdk).replace("%", "%%")}:/opt/fd/lib"' in env
    assert "HAPTICD_LIBDHD=/opt/fd/lib/libdrd.so" in env
    analyze = shutil.which("systemd-analyze")
    if analyze is not None:  # systemd reads it back without a word
        got = subprocess.run(
            [analyze, "verify", str(tmp_path / "hapticd.service")],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert got.returncode == 0 and got.stderr.strip() == "", got.stderr
