"""The ``hapticd`` command line: run a profile (the daemon), check a profile, the client
commands that talk to a running daemon, and the offline and experiment tools. One module
per group of commands; this one builds the parser and dispatches."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from pathlib import Path
from typing import Any

from hapticd_drivers.registry import backend_names

from hapticd import __version__, params
from hapticd import events as event_kinds
from hapticd.cli.client import (
    WATCH_COLUMNS,
    _add_view,
    cmd_client,
    cmd_events,
    cmd_watch,
    format_status,
)
from hapticd.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_ERROR,
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_PIPE,
    OutputClosed,
    _add_log_options,
    _add_progress_option,
    _add_set_option,
    _count,
    _log_level,
    _overrides,
    _positive,
    stdout_closed,
)
from hapticd.cli.experiment import _add_experiment, _add_study
from hapticd.cli.offline import _add_analyze, _add_plot, cmd_export
from hapticd.cli.plugins import add_commands as _add_plugin_commands
from hapticd.cli.plugins import device_name
from hapticd.cli.run import (
    _add_bringup,
    _add_schema,
    cmd_calibrate,
    cmd_check,
    cmd_devices,
    cmd_run,
    cmd_udev_rules,
)
from hapticd.cli.service import _add_service

# Used by other modules and tests as hapticd.cli.NAME.
__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_ERROR",
    "EXIT_FAULT",
    "EXIT_OK",
    "_overrides",
    "build_parser",
    "cmd_check",
    "format_status",
    "main",
]

log = logging.getLogger("hapticd")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hapticd", description="Real-time haptic rendering daemon.")
    ap.add_argument("--version", action="version", version=f"hapticd {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run the servo loop on a profile's devices")
    run.add_argument("profile", type=Path, help="YAML profile")
    run.add_argument("--duration", type=_positive, metavar="S", help="stop after S seconds")
    run.add_argument(
        "--unpaced",
        action="store_true",
        help="run as fast as possible on a simulated clock (same forces as paced)",
    )
    run.add_argument(
        "--record",
        type=Path,
        metavar="PATH",
        help="record every tick to PATH (.hrec), anywhere you may write",
    )
    run.add_argument(
        "--lsl",
        action="store_true",
        help="publish the ticks and events as Lab Streaming Layer streams, as the profile's "
        "lsl.enabled does (docs/lsl.md; pip install 'hapticd[lsl]')",
    )
    run.add_argument(
        "--record-dir",
        type=Path,
        metavar="DIR",
        help="the only folder record_start over the socket writes in (default: the profile's "
        "recording.directory, else $STATE_DIRECTORY, $XDG_STATE_HOME/hapticd or "
        "~/.local/state/hapticd)",
    )
    run.add_argument(
        "--socket",
        type=Path,
        metavar="PATH",
        help="serve the control protocol on this Unix socket (default: $HAPTICD_SOCKET, "
        "$RUNTIME_DIRECTORY/control.sock, $XDG_RUNTIME_DIR/hapticd/control.sock; an "
        "--unpaced run serves one only when given)",
    )
    run.add_argument(
        "--socket-group",
        metavar="GROUP",
        help="let this group's members connect too: the socket 0660 and its directory 0750 "
        "for that group only (the installed service's experimenters; docs/daemon.md)",
    )
    run.add_argument(
        "--reload-dir",
        type=Path,
        action="append",
        metavar="DIR",
        help="a folder a client that is not the daemon's user (a --socket-group member) may "
        "reload profiles from; repeat for more (default: the profile's own folder)",
    )
    run.add_argument(
        "--device",
        type=device_name,
        choices=backend_names(),
        help="use this backend for every finger instead of the profile's",
    )
    run.add_argument(
        "--emulate",
        action="store_true",
        help="put the device emulator under the hid, usb or falcon backend, moved along the "
        "trajectory",
    )
    run.add_argument("--summary-json", type=Path, metavar="PATH", help="write the summary as JSON")
    run.add_argument(
        "--plot",
        type=Path,
        metavar="FILE.png",
        help="plot the run when it ends (as hapticd plot; records to a temporary file unless "
        "--record is given)",
    )
    run.add_argument("-q", "--quiet", action="store_true", help="do not print the summary")
    run.set_defaults(func=cmd_run)
    chk = sub.add_parser("check", help="validate a profile and the files it names")
    chk.add_argument("profile", type=Path)
    chk.set_defaults(func=cmd_check)
    _add_set_option(run)
    _add_set_option(chk)
    _add_progress_option(run)
    _add_log_options(run)
    _add_schema(sub)
    run.add_argument(
        "--no-socket", action="store_true", help="serve no control socket (SIGHUP still reloads)"
    )
    run.add_argument(
        "--no-realtime",
        action="store_true",
        help="do not try SCHED_FIFO, mlockall or timer slack (the profile's loop.realtime)",
    )
    sock_help = "the daemon's control socket (default: $HAPTICD_SOCKET or the runtime directory)"
    param_help = ", ".join(
        f"{p.alias} ({p.name})" if p.alias else p.name for p in params.PARAMS.values()
    )
    value_help = "; ".join(f"{p.name}: {p.syntax}" for p in params.PARAMS.values())
    clients = (
        ("status", "show a running hapticd's state"),
        ("enable", "re-enable forces (clears a latched fault; forces ramp up)"),
        ("disable", "turn forces off"),
        ("stop", "stop a running hapticd (forces ramp to zero, recording flushed)"),
        ("get", "read a scene or rendering parameter"),
        ("set", "change a parameter at the next tick, e.g. set stiffness 60"),
        ("allocator", "switch the allocator at the next tick, e.g. allocator if"),
        ("record", "record start PATH / record stop"),
        ("reload", "reload the profile (or switch to PROFILE): scene, rendering, safety"),
        ("watch", "live numbers: forces, contact, object, faults"),
        ("events", "the loop's events as they happen: contacts, buttons, faults, changes"),
    )
    for name, help_text in clients:
        extra: dict[str, Any] = {}
        if name == "watch":
            extra = {
                "description": WATCH_COLUMNS,
                "formatter_class": argparse.RawDescriptionHelpFormatter,
            }
        p = sub.add_parser(name, help=help_text, **extra)
        p.add_argument("--socket", type=Path, metavar="PATH", help=sock_help)
        p.set_defaults(func=cmd_client)
        if name in ("get", "set"):
            p.add_argument("param", help=param_help)
        if name == "set":
            p.add_argument("value", help=value_help)
        if name == "allocator":
            # The daemon checks the name: it knows the allocator plugins installed there.
            p.add_argument(
                "name",
                help=f"{', '.join(params.ALLOCATORS)}, or an allocator plugin's name "
                "(hapticd allocators lists them)",
            )
        if name == "record":
            p.add_argument("action", choices=["start", "stop"])
            p.add_argument("path", nargs="?", type=Path, help="the .hrec file (start)")
            p.add_argument("--overwrite", action="store_true", help="replace an existing file")
        if name == "reload":
            p.add_argument("profile", nargs="?", type=Path, help="another profile to switch to")
        if name == "status":
            p.add_argument("--json", action="store_true", help="machine-readable output")
        if name == "watch":
            p.add_argument("--rate", type=_positive, default=10.0, help="lines per second")
            p.add_argument("--count", type=int, help="stop after this many lines")
            p.set_defaults(func=cmd_watch)
        if name == "events":
            p.add_argument("--count", type=_count, metavar="N", help="stop after N events")
            p.add_argument(
                "--json", action="store_true", help="one JSON object per line (for scripts)"
            )
            p.add_argument(
                "--kinds",
                metavar="A,B",
                help=f"only these events (default all): {','.join(event_kinds.NAMES)}",
            )
            p.set_defaults(func=cmd_events)
    _add_analyze(sub)
    _add_experiment(sub)
    _add_study(sub)
    _add_plot(sub)
    _add_view(sub, sock_help)
    _add_bringup(sub)
    _add_service(sub)
    exp = sub.add_parser("export", help="export a recording to CSV or MCAP (Foxglove)")
    exp.add_argument("recording", type=Path)
    fmt = exp.add_mutually_exclusive_group()
    fmt.add_argument("--csv", type=Path, metavar="OUT", help="default: the recording's name .csv")
    fmt.add_argument("--mcap", type=Path, metavar="OUT", help="MCAP with JSON messages")
    _add_progress_option(exp)
    exp.set_defaults(func=cmd_export)
    cal = sub.add_parser(
        "calibrate",
        help="run the SDK's automatic initialisation of a profile's devices (they move!)",
        description="Calibrate (initialise) the profile's devices that hapticd calibrates "
        "(dhd: drdAutoInit through libdrd). The devices move on their own: empty their "
        "workspaces first. Asks for a confirmation on a terminal; --yes skips it.",
    )
    cal.add_argument("profile", type=Path)
    cal.add_argument(
        "--yes", action="store_true", help="do not ask: every workspace is known to be empty"
    )
    cal.add_argument(
        "--finger", action="append", metavar="NAME", help="only this finger's device (repeat)"
    )
    cal.set_defaults(func=cmd_calibrate)
    dev = sub.add_parser("devices", help="list the haptic devices found, or why none can be")
    dev.add_argument("--json", action="store_true", help="machine-readable output")
    dev.set_defaults(func=cmd_devices)
    _add_plugin_commands(sub)
    udev = sub.add_parser("udev-rules", help="print udev rules that let users open the devices")
    udev.set_defaults(func=cmd_udev_rules)
    return ap


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(level=logging.INFO, format="hapticd: %(message)s", stream=sys.stderr)
        logging.getLogger("hapticd").setLevel(_log_level(args))
        code = int(args.func(args))
        sys.stdout.flush()
        return code
    except (BrokenPipeError, OutputClosed) as exc:
        # The reader of stdout went (`hapticd check P | head -1`): end quietly, as a program
        # ended by SIGPIPE would; a broken pipe anywhere else is a real error.
        if isinstance(exc, BrokenPipeError) and not stdout_closed():
            raise
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())  # the interpreter's last flush goes nowhere
        return EXIT_PIPE
    except KeyboardInterrupt:
        # Ctrl-C before a command's own handlers were in place (a run's start-up): nothing
        # was opened yet, so there is nothing to stop; a line, not a traceback.
        print("hapticd: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
