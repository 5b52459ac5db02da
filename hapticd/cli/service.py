"""``hapticd service unit``: the systemd unit that runs this installation's daemon on a
profile as a service, for a service user and a group of experimenters (docs/daemon.md)."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import urllib.parse
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hapticd.cli.common import EXIT_BAD_INPUT, EXIT_OK
from hapticd.daemon.build import build_scene, load_trajectories
from hapticd.profile import ProfileError, load_profile
from hapticd.recording import files
from hapticd.recording.format import RecordingError

DEFAULT_PROFILE = Path("/etc/hapticd/profile.yaml")
DEFAULT_USER = "hapticd"
DEFAULT_GROUP = "hapticd"
# The docs of a source checkout (this package's parent folder), named in Documentation=.
DOCS = Path(__file__).resolve().parents[2] / "docs" / "daemon.md"
NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-.")
# An Exec argument made of these alone is written bare; any other is double-quoted.
BARE_CHARS = NAME_CHARS | frozenset("/+=:,@")
UNIT_MODE = 0o644  # systemd's units are readable by everyone (systemctl cat)


def hapticd_command() -> list[str]:
    """This installation's ``hapticd``, as absolute paths: the script beside the running
    interpreter (a venv's bin/), else that interpreter with ``-m hapticd``. The venv's
    path is kept as it is (its python is a symbolic link to the system's: resolving it
    would lose the venv)."""
    python = Path(os.path.abspath(sys.executable))
    script = python.parent / "hapticd"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [str(python), "-m", "hapticd"]


def unit_text(
    command: list[str],
    profile: Path,
    *,
    name: str,
    user: str,
    group: str,
    docs: Path | None,
    kill: str,
    environment: dict[str, str] | None = None,
) -> str:
    """The unit: ``command`` (absolute) runs ``profile`` (absolute) as ``user``, sharing
    the control socket with ``group``; ``docs`` (if any) becomes Documentation=. Every
    value is checked (``unit_value``: ValueError naming its source) and escaped for the
    place it goes: Exec arguments quoted (``exec_arg``), ``%`` doubled elsewhere."""
    for i, arg in enumerate(command):
        unit_value(arg, f"this installation's hapticd command (argument {i}: {arg!r})")
    unit_value(str(profile), "the profile's path (--profile)")
    unit_value(name, f"the profile's name (key 'name' in {profile})")
    unit_value(user, "--user")
    unit_value(group, "--group")
    unit_value(kill, "the kill command (found on PATH)")
    env = "".join(f"Environment={env_assignment(k, v)}\n" for k, v in (environment or {}).items())
    exec_start = " ".join(exec_arg(a) for a in [*command, "run", str(profile)])
    if docs is not None:
        unit_value(str(docs), "the docs' path (this installation's docs/daemon.md)")
        url = "file://" + urllib.parse.quote(str(docs))
        doc = f"Documentation={_percent(url)}\n"
    else:
        doc = ""
    # Comments are not expanded, but a control character would end one: checked above.
    shown, shown_name = str(profile), repr(name)
    description = _percent(name)
    group_arg = exec_arg(group)
    kill_arg = exec_arg(kill)
    return f"""\
# hapticd as a systemd service: made by `hapticd service unit` for profile {shown_name}.
# Install (docs/daemon.md, "Installing the service"):
#   hapticd service unit --profile {shown} | sudo tee /etc/systemd/system/hapticd.service
#   sudo systemctl daemon-reload && sudo systemctl enable --now hapticd

[Unit]
Description=hapticd haptic rendering daemon ({description})
{doc}After=systemd-udevd.service
# At most 5 starts in 2 minutes: a daemon that fails at once is not restarted forever.
StartLimitIntervalSec=120
StartLimitBurst=5

[Service]
# READY=1 once the servo loop ticks; STATUS= about once a second; WATCHDOG=1 only while
# the loop's tick count advances, so a stalled loop is restarted.
Type=notify
NotifyAccess=main
# The socket /run/hapticd/control.sock, 0660 in a 0750 directory, for group {group} only:
# its members (the experimenters) reach the daemon; clients find it without --socket.
ExecStart={exec_start} --socket-group {group_arg}
# SIGHUP reloads the profile; an invalid one is rejected and the old one keeps running.
ExecReload={kill_arg} -HUP $MAINPID
# SIGTERM ramps forces to zero, closes the devices, flushes the recording and exits 0.
KillSignal=SIGTERM
# Only the daemon gets SIGTERM; it waits for its recording writer to finish.
KillMode=mixed
TimeoutStopSec=15s
WatchdogSec=2s
# Restart after a crash (exit 1: an error, a traceback), a signal or a watchdog timeout;
# not after a clean stop (0), a profile that does not validate (2: it would fail again)
# or a latched safety fault (3: a person may be holding the devices; re-enable by hand).
Restart=on-failure
RestartPreventExitStatus=2 3
RestartSec=2s
User={user}
Group={group}
# plugdev: the devices' group in `hapticd udev-rules`.
SupplementaryGroups=plugdev
RuntimeDirectory=hapticd
RuntimeDirectoryMode=0750
# Recordings started over the socket go here (/var/lib/hapticd, $STATE_DIRECTORY) and
# nowhere else; the group may read them.
StateDirectory=hapticd
StateDirectoryMode=0750
# The compiled kernels' cache (numba; $CACHE_DIRECTORY).
CacheDirectory=hapticd
CacheDirectoryMode=0700
# Let the servo thread use SCHED_FIFO and lock its memory (loop.realtime in the profile).
# RestrictRealtime=yes would forbid SCHED_FIFO: leave it off.
LimitRTPRIO=99
LimitMEMLOCK=infinity
Environment=PYTHONUNBUFFERED=1
{env}
[Install]
WantedBy=multi-user.target
"""


def unit_value(value: str, source: str) -> str:
    """``value`` if it may go into a unit, else ValueError naming ``source`` (the key or
    argument it came from) and the rule: no control character (C0, DEL, C1), since a
    newline would start a line of its own (a ``[Service]`` or ``ExecStartPre=+...`` that
    systemd would run as root)."""
    for i, c in enumerate(value):
        if ord(c) < 0x20 or 0x7F <= ord(c) <= 0x9F:
            raise ValueError(
                f"{source}: {value!r} holds the control character {c!r} at position {i}; "
                "a systemd unit takes no control characters (newline, tab, CR, DEL, ...): "
                "rename it"
            )
    return value


def env_assignment(name: str, value: str) -> str:
    """``NAME=value`` as Environment= reads it back literally (systemd.exec): ``%``
    doubled (specifiers; ``$`` means nothing there), double-quoted with backslash escapes
    unless made of plain characters only."""
    text = unit_value(f"{name}={value}", f"the environment variable {name}")
    text = _percent(text)
    if set(text) <= BARE_CHARS:
        return text
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def sdk_environment(profile: Any, env: Mapping[str, str] | None = None) -> dict[str, str]:
    """What the service's environment needs for ``profile``'s Force Dimension devices
    (backend dhd) to find their SDK: LD_LIBRARY_PATH, the folders of the libraries the
    devices' key ``library`` names (libdrd loads libdhd from beside it), else of
    $HAPTICD_LIBDHD here (then passed on too: the service does not inherit this shell's
    environment); nothing when no device names one (the system's library is found)."""
    env = os.environ if env is None else env
    libs = [
        getattr(f.device, "library", None) or env.get("HAPTICD_LIBDHD")
        for f in profile.fingers
        if f.device.backend == "dhd"
    ]
    libs = [os.path.abspath(p) for p in libs if p]
    out: dict[str, str] = {}
    if not libs:
        return out
    folders = list(dict.fromkeys(os.path.dirname(p) for p in libs))
    for d in folders:
        if ":" in d:
            raise ValueError(
                f"the SDK's folder {d!r} holds a ':', which LD_LIBRARY_PATH cannot carry: "
                "move the SDK"
            )
    out["LD_LIBRARY_PATH"] = ":".join(folders)
    if any(
        getattr(f.device, "library", None) is None
        for f in profile.fingers
        if f.device.backend == "dhd"
    ):
        out["HAPTICD_LIBDHD"] = os.path.abspath(env["HAPTICD_LIBDHD"])
    return out


def _percent(value: str) -> str:
    """``value`` with ``%`` doubled: systemd expands ``%x`` as a specifier."""
    return value.replace("%", "%%")


def exec_arg(arg: str) -> str:
    """One Exec argument as systemd reads it back literally (systemd.service, "Command
    lines"): ``%`` doubled (specifiers), ``$`` doubled (variables), and double-quoted with
    backslash escapes unless it is made of plain characters only."""
    unit_value(arg, "an Exec argument")
    arg = arg.replace("%", "%%").replace("$", "$$")
    if arg and set(arg) <= BARE_CHARS and arg[0] not in "-+@:!":
        return arg
    return '"' + arg.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _name(value: str, what: str) -> str:
    """A user or group name as systemd takes it (letters, digits, _ - .), else ValueError."""
    if not value or not set(value) <= NAME_CHARS or value[0] in "-." or value.isdigit():
        raise ValueError(f"--{what} {value!r}: expected a user or group name (a-z, 0-9, _, -)")
    return value


def cmd_service_unit(args: argparse.Namespace) -> int:
    profile = Path(os.path.abspath(args.profile))
    try:
        user, group = _name(args.user, "user"), _name(args.group, "group")
        # Checked as `hapticd check` checks it: a unit that cannot start is refused.
        prof = load_profile(profile)
        load_trajectories(prof)
        build_scene(prof.scene, prof)
        text = unit_text(
            hapticd_command(),
            profile,
            name=prof.name,
            user=user,
            group=group,
            docs=DOCS if DOCS.is_file() else None,
            kill=shutil.which("kill") or "/bin/kill",
            environment=sdk_environment(prof),
        )
    except (ProfileError, ValueError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        print("hapticd: no unit printed: fix the profile (hapticd check) first", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.out is not None:
        # Created new, or written aside and renamed over a regular file of this user: a
        # symbolic link (or FIFO, or another user's file) planted there is refused, never
        # followed.
        try:
            fd, _ = files.create(args.out, text.encode(), overwrite=True, mode=UNIT_MODE)
        except RecordingError as exc:
            print(f"hapticd: --out {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        os.close(fd)
    else:
        sys.stdout.write(text)
    return EXIT_OK


def _add_service(sub: Any) -> None:
    svc = sub.add_parser("service", help="install hapticd as a systemd service")
    ssub = svc.add_subparsers(dest="service_command", required=True)
    unit = ssub.add_parser(
        "unit",
        help="print a systemd unit that runs this installation's hapticd on a profile",
        description="Print a systemd unit for this installation: ExecStart is this "
        "install's hapticd (absolute path) running PROFILE as USER, its control socket "
        "shared with GROUP (the experimenters); runtime, state and cache directories, "
        "real-time limits, watchdog. A profile that does not validate is refused.",
    )
    unit.add_argument(
        "--profile",
        type=Path,
        default=DEFAULT_PROFILE,
        help=f"the profile the service runs (default {DEFAULT_PROFILE})",
    )
    unit.add_argument(
        "--user", default=DEFAULT_USER, help=f"the service's user (default {DEFAULT_USER})"
    )
    unit.add_argument(
        "--group",
        default=DEFAULT_GROUP,
        help=f"the service's group, whose members may use the daemon (default {DEFAULT_GROUP})",
    )
    unit.add_argument("--out", type=Path, metavar="FILE", help="write it here instead of stdout")
    unit.set_defaults(func=cmd_service_unit)
