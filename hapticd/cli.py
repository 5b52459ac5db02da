"""The ``hapticd`` command line: run a profile, check a profile."""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
from pathlib import Path
from typing import Any

from hapticd_drivers import BackendUnavailableError

from hapticd import __version__
from hapticd.profile import ProfileError, load_profile
from hapticd.runner import build_session, load_trajectories
from hapticd.scene import Scene

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_BAD_INPUT = 2
EXIT_FAULT = 3


def _fmt(v: float | None, unit: str = "") -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:g}{unit}"


def format_summary(s: dict[str, Any]) -> str:
    """Human-readable run summary."""
    pe, tc = s["period_error_us"], s["tick_compute_us"]
    lines = [
        f"hapticd run: {s['ticks']} ticks ({s['duration_s']:g} s), ended: {s['end_reason']}",
        f"  rate            target {s['rate_hz']['target']:g} Hz, achieved "
        f"{_fmt(s['rate_hz']['achieved'])} Hz" + ("" if s["paced"] else " (unpaced)"),
    ]
    if s["paced"]:
        lines.append(
            f"  period error    p50 {_fmt(pe['p50'])} us, p99 {_fmt(pe['p99'])} us, "
            f"max {_fmt(pe['max'])} us; overruns {s['overruns']}"
        )
    lines += [
        f"  tick compute    p50 {_fmt(tc['p50'])} us, p99 {_fmt(tc['p99'])} us, "
        f"max {_fmt(tc['max'])} us",
        f"  allocator       {s['allocator']}",
        f"  max force       {s['max_rendered_force_n']:.4f} N "
        f"(clamped on {s['clamped_ticks']} ticks)",
    ]
    for name, f in s["fingers"].items():
        lines.append(
            f"    {name:<12} max {f['max_force_n']:.4f} N, in contact {f['contact_ticks']} ticks"
        )
    if s["fault"]:
        lines.append(f"  FAULT (latched) at tick {s['fault']['tick']}: {s['fault']['cause']}")
    return "\n".join(lines)


def cmd_run(args: argparse.Namespace) -> int:
    try:
        profile = load_profile(args.profile)
        session = build_session(
            profile,
            paced=not args.unpaced,
            duration_s=args.duration,
            record_path=args.record,
            device=args.device,
            emulate=args.emulate,
        )
    except (ProfileError, BackendUnavailableError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR

    def on_signal(signum: int, _frame: object) -> None:
        session.loop.request_stop(f"signal {signal.Signals(signum).name}")

    server = None
    if args.socket is not None:
        from hapticd.control import ControlServer

        server = ControlServer(session.loop, args.socket)
        try:
            server.start()
        except OSError as exc:
            print(f"hapticd: cannot serve the control socket {args.socket}: {exc}", file=sys.stderr)
            return EXIT_ERROR
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        summary = session.run()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if server is not None:
            server.close()
    summary["profile"] = str(args.profile)
    if args.record:
        summary["recording"] = str(args.record)
    if args.summary_json:
        Path(args.summary_json).write_text(json.dumps(summary, indent=2) + "\n")
    if not args.quiet:
        print(format_summary(summary))
    return EXIT_FAULT if summary["fault"] else EXIT_OK


def cmd_check(args: argparse.Namespace) -> int:
    try:
        profile = load_profile(args.profile)
        load_trajectories(profile)
        Scene.from_config(profile.scene, profile)
    except ProfileError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    fingers = ", ".join(
        f"{f.name} ({f.device.backend}, {len(f.actuated_directions)} actuated)"
        for f in profile.fingers
    )
    print(
        f"{args.profile}: OK: profile {profile.name!r}, {profile.loop.rate_hz:g} Hz, "
        f"allocator {profile.rendering.allocator}, fingers: {fingers}"
    )
    return EXIT_OK


def cmd_client(args: argparse.Namespace) -> int:
    from hapticd.control import ControlClient
    from hapticd.protocol import ProtocolError

    try:
        with ControlClient(args.socket) as client:
            if args.command == "set":
                value: Any = args.value
                if args.param == "friction":
                    value = [float(v) for v in args.value.split(",")]
                elif args.param != "allocator":
                    value = float(args.value)
                result = client.set(args.param, value)
            elif args.command == "get":
                result = {args.param: client.get(args.param)}
            else:
                result = client.call(args.command)
    except (OSError, ValueError) as exc:
        if isinstance(exc, ProtocolError):
            print(f"hapticd: {exc.code}: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f"hapticd: cannot talk to {args.socket}: {exc}", file=sys.stderr)
        return EXIT_ERROR
    print(json.dumps(result, indent=2 if getattr(args, "json", False) else None))
    return EXIT_OK


def cmd_devices(args: argparse.Namespace) -> int:
    from hapticd_drivers.udev import discover

    report = discover()
    if args.json:
        print(json.dumps(report, indent=2))
        return EXIT_OK
    for entry in report:
        if "problem" in entry:
            print(f"{entry['backend']:<4} cannot look: {entry['problem']}")
        elif entry["found"]:
            print(f"{entry['backend']:<4} {entry['model']}: {', '.join(map(str, entry['found']))}")
        else:
            print(f"{entry['backend']:<4} {entry['model']}: none found (plugged in? udev rules?)")
    return EXIT_OK


def cmd_udev_rules(args: argparse.Namespace) -> int:
    from hapticd_drivers.udev import rules

    sys.stdout.write(rules())
    return EXIT_OK


def _positive(text: str) -> float:
    v = float(text)
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text}")
    return v


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
        "--record", type=Path, metavar="PATH", help="record every tick to PATH (.hrec)"
    )
    run.add_argument(
        "--socket", type=Path, metavar="PATH", help="serve the control protocol on this Unix socket"
    )
    run.add_argument(
        "--device",
        choices=["replay", "sim", "hid", "usb"],
        help="use this backend for every finger instead of the profile's",
    )
    run.add_argument(
        "--emulate",
        action="store_true",
        help="put the device emulator under the hid or usb backend, moved along the trajectory",
    )
    run.add_argument("--summary-json", type=Path, metavar="PATH", help="write the summary as JSON")
    run.add_argument("-q", "--quiet", action="store_true", help="do not print the summary")
    run.set_defaults(func=cmd_run)
    chk = sub.add_parser("check", help="validate a profile and the files it names")
    chk.add_argument("profile", type=Path)
    chk.set_defaults(func=cmd_check)
    for name, help_text in (
        ("status", "show a running hapticd's state"),
        ("enable", "re-enable forces (clears a latched fault; forces ramp up)"),
        ("disable", "turn forces off"),
        ("stop", "stop a running hapticd (forces to zero, devices closed)"),
        ("get", "read a scene or rendering parameter"),
        ("set", "change a parameter at the next tick, e.g. set stiffness_n_per_m 60"),
    ):
        p = sub.add_parser(name, help=help_text)
        p.add_argument("--socket", type=Path, required=True, metavar="PATH")
        if name in ("get", "set"):
            p.add_argument(
                "param", help="stiffness_n_per_m, damping_n_s_per_m, friction, mass_kg, allocator"
            )
        if name == "set":
            p.add_argument("value", help="a number; friction as STATIC,DYNAMIC; an allocator name")
        if name == "status":
            p.add_argument("--json", action="store_true")
        p.set_defaults(func=cmd_client)
    dev = sub.add_parser("devices", help="list the haptic devices found, or why none can be")
    dev.add_argument("--json", action="store_true", help="machine-readable output")
    dev.set_defaults(func=cmd_devices)
    udev = sub.add_parser("udev-rules", help="print udev rules that let users open the devices")
    udev.set_defaults(func=cmd_udev_rules)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="hapticd: %(message)s", stream=sys.stderr)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
