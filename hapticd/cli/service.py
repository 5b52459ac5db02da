"""``hapticd service unit``: the systemd unit that runs this installation's daemon on a
profile as a service, for a service user and a group of experimenters (docs/daemon.md)."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path
from typing import Any

from hapticd.cli.common import EXIT_BAD_INPUT, EXIT_OK
from hapticd.daemon.build import build_scene, load_trajectories
from hapticd.profile import ProfileError, load_profile

DEFAULT_PROFILE = Path("/etc/hapticd/profile.yaml")
DEFAULT_USER = "hapticd"
DEFAULT_GROUP = "hapticd"
# The docs of a source checkout (this package's parent folder), named in Documentation=.
DOCS = Path(__file__).resolve().parents[2] / "docs" / "daemon.md"
NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-.")


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
) -> str:
    """The unit: ``command`` (absolute) runs ``profile`` (absolute) as ``user``, sharing
    the control socket with ``group``; ``docs`` (if any) becomes Documentation=."""
    exec_start = " ".join(_quote(a) for a in [*command, "run", str(profile)])
    doc = f"Documentation=file://{docs}\n" if docs is not None else ""
    return f"""\
# hapticd as a systemd service: made by `hapticd service unit` for profile {name!r}.
# Install (docs/daemon.md, "Installing the service"):
#   hapticd service unit --profile {profile} | sudo tee /etc/systemd/system/hapticd.service
#   sudo systemctl daemon-reload && sudo systemctl enable --now hapticd

[Unit]
Description=hapticd haptic rendering daemon ({name})
{doc}After=systemd-udevd.service

[Service]
# READY=1 once the servo loop ticks; STATUS= about once a second; WATCHDOG=1 only while
# the loop's tick count advances, so a stalled loop is restarted.
Type=notify
NotifyAccess=main
# The socket /run/hapticd/control.sock, 0660 in a 0750 directory, for group {group} only:
# its members (the experimenters) reach the daemon; clients find it without --socket.
ExecStart={exec_start} --socket-group {group}
# SIGHUP reloads the profile; an invalid one is rejected and the old one keeps running.
ExecReload={kill} -HUP $MAINPID
# SIGTERM ramps forces to zero, closes the devices, flushes the recording and exits 0.
KillSignal=SIGTERM
# Only the daemon gets SIGTERM; it waits for its recording writer to finish.
KillMode=mixed
TimeoutStopSec=15s
WatchdogSec=2s
# Restart after a crash, a signal or a watchdog timeout, but not after a latched safety
# fault (exit code 3): a person may be holding the devices; re-enable by hand.
Restart=on-abnormal
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

[Install]
WantedBy=multi-user.target
"""


def _quote(arg: str) -> str:
    """One ExecStart= argument: double-quoted when it holds a space or a quote."""
    if any(c in arg for c in " \t\"'\\"):
        return '"' + arg.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return arg


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
    except (ProfileError, ValueError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        print("hapticd: no unit printed: fix the profile (hapticd check) first", file=sys.stderr)
        return EXIT_BAD_INPUT
    text = unit_text(
        hapticd_command(),
        profile,
        name=prof.name,
        user=user,
        group=group,
        docs=DOCS if DOCS.is_file() else None,
        kill=shutil.which("kill") or "/bin/kill",
    )
    if args.out is not None:
        args.out.write_text(text)
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
