"""The client commands: status and the other requests to a running daemon, watch, events
and view."""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from hapticd import events as event_kinds
from hapticd import params
from hapticd import protocol as proto
from hapticd.cli.common import EXIT_BAD_INPUT, EXIT_ERROR, EXIT_OK, _port, _rate, emit
from hapticd.cli.run import _device_text
from hapticd.control import ControlClient, NoDaemonError, client_socket_path
from hapticd.protocol import ProtocolError

log = logging.getLogger("hapticd")


def format_status(st: dict[str, Any]) -> str:
    pe = st["period_error_us"]
    sc = st["scene"]
    rec = st["recording"]
    fault = st["fault"]
    rt = st.get("realtime")

    def us(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.1f} us"

    lines = [
        f"profile       {st.get('profile', '?')}   tick {st['tick']} (t = {st['t']:.3f} s)",
        f"rate          {st['rate_hz']:g} Hz; period error p50 {us(pe['p50'])}, "
        f"p99 {us(pe['p99'])}, max {us(pe['max'])}; overruns {st['overruns']}",
        f"fault         {'none' if fault is None else fault['cause']}",
        "devices       " + ", ".join(_device_text(d) for d in st["devices"]),
        f"allocator     {st['allocator']}   stages: {' '.join(st['stages'])}",
        "passivity     "
        + (
            "off"
            if not (pa := st.get("passivity")) or not pa["enabled"]
            else "energy "
            + ", ".join(f"{e:.3g}" for e in pa["energy_j"])
            + " J; damping "
            + ", ".join(f"{b:.3g}" for b in pa["damping_n_s_per_m"])
            + " N s/m"
        ),
        f"scene         {sc['shape']}, {'fixed' if sc['fixed'] else 'free'}, "
        f"stiffness {sc['stiffness_n_per_m']:g} N/m, mass {sc['mass_kg']:g} kg, "
        f"friction {sc['friction'][0]:g}/{sc['friction'][1]:g}",
        "recording     "
        + (
            "off"
            if rec is None
            else f"{rec['path']}: {rec['ticks']} ticks, {rec['written']} written, "
            f"{rec['dropped']} dropped" + (f", ERROR {rec['error']}" if rec["error"] else "")
        ),
        "real time     "
        + (
            "off"
            if rt is None
            else (f"SCHED_FIFO {rt['fifo_priority']}" if rt["fifo_priority"] else "normal policy")
            + (", memory locked" if rt["memory_locked"] else "")
            + (f", cpu {rt['cpu']}" if rt["cpu"] is not None else "")
        ),
    ]
    return "\n".join(lines)


def _client_failed(args: argparse.Namespace, exc: Exception) -> int:
    """Report a failed client command; the exit code says whose fault it was."""
    if isinstance(exc, ProtocolError):
        # busy says it all ("the daemon is busy: N clients connected ..."); others get a code.
        print(
            f"hapticd: {exc}" if exc.code == "busy" else f"hapticd: {exc.code}: {exc}",
            file=sys.stderr,
        )
        # The request was wrong (exit 2), or the daemon's state (exit 1): hapticd.protocol.
        return EXIT_BAD_INPUT if exc.code in proto.BAD_REQUEST else EXIT_ERROR
    if isinstance(exc, NoDaemonError):
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    where = args.socket or client_socket_path()
    print(f"hapticd: cannot talk to {where}: {exc}", file=sys.stderr)
    return EXIT_ERROR


def cmd_client(args: argparse.Namespace) -> int:
    if args.command == "record" and args.action == "start" and args.path is None:
        print("hapticd: record start needs a PATH", file=sys.stderr)
        return EXIT_BAD_INPUT
    spec: params.Param | None = None
    param = ""
    value: Any = None
    if args.command in ("get", "set"):
        # Checked here, before connecting: a typo needs no running daemon to be reported.
        try:
            spec = params.lookup(args.param)
            if args.command == "set":
                value = spec.parse(args.value)
                spec.check(value)
        except params.ParamError as exc:
            # The same "code: message" as a reply from the daemon would print.
            what = "" if spec is None else f"bad value {proto.short(args.value)} for {args.param}: "
            print(f"hapticd: {exc.code}: {what}{exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        param = spec.name
    try:
        with ControlClient(args.socket) as client:
            cmd = args.command
            if cmd == "set":
                result = client.set(param, value)
            elif cmd == "allocator":
                result = client.set("allocator", args.name)
            elif cmd == "get":
                result = {param: client.get(param)}
            elif cmd == "record":
                if args.action == "start":
                    result = client.record_start(args.path, overwrite=args.overwrite)
                else:
                    result = client.record_stop()
            elif cmd == "reload":
                result = client.reload(args.profile)
            elif cmd == "stop":
                result = client.stop()
            elif cmd == "status":
                result = client.status()
                if not args.json:
                    emit(format_status(result))
                    return EXIT_OK
            else:
                result = client.call(cmd)
    except (OSError, ValueError) as exc:
        return _client_failed(args, exc)
    print(json.dumps(result, indent=2 if getattr(args, "json", False) else None))
    return EXIT_OK


WATCH_COLUMNS = """\
Live numbers from a running hapticd, one line per telemetry frame, for example
(devices named by their serials, here A and B):

  t    3.100 s  A: |F|  1.104 N *  B: |F|  0.000 N    obj z    0.00 mm  if  overruns 0

columns:
  t 3.100 s              the loop's time, tick / rate (s)
  SERIAL: |F| 1.104 N    per device: the magnitude of the force sent to it, after the
                         safety chain (N)
  *                      after a device's force: that finger is in contact with the object
  obj z 0.00 mm          the height of the object's centre of mass (mm)
  if                     the allocator
  overruns 0             loop periods longer than 1.1x nominal so far
  FAULT                  a safety fault is latched: forces are zero until hapticd enable

For a picture of the scene and the forces, see hapticd view (docs/view.md)."""


def cmd_watch(args: argparse.Namespace) -> int:
    """Live numbers from a running daemon, one line per frame, until Ctrl-C or --count."""
    shown = 0
    try:
        with ControlClient(args.socket) as client:
            client.subscribe(args.rate)
            names = client.status()["devices"]
            while args.count is None or shown < args.count:
                fr = client.next_telemetry()
                parts = [f"t {fr['t']:8.3f} s"]
                for i, d in enumerate(names):
                    f = fr["force"][i]
                    mag = math.sqrt(sum(v * v for v in f))
                    parts.append(
                        f"{d['serial']}: |F| {mag:6.3f} N{' *' if fr['in_contact'][i] else '  '}"
                    )
                parts.append(f"obj z {fr['object_pos'][2] * 1e3:7.2f} mm")
                parts.append(f"{fr['allocator']}  overruns {fr['overruns']}")
                if fr["fault"]:
                    parts.append("FAULT")
                emit("  ".join(parts))
                shown += 1
    except KeyboardInterrupt:
        return EXIT_OK
    except (OSError, ValueError) as exc:
        return _client_failed(args, exc)
    return EXIT_OK


def format_event(ev: dict[str, Any]) -> str:
    """One event as a readable line: time, tick, kind and what it carries."""
    parts = [f"t {ev.get('t', 0.0):9.3f} s", f"tick {ev.get('tick', 0):>8}", f"{ev['event']:<18}"]
    if "finger" in ev:
        parts.append(str(ev.get("finger_name") or f"finger {ev['finger']}"))
    if "button" in ev:
        parts.append(f"button {ev['button']}")
    if "response" in ev:
        parts.append(f"response {ev['response']}")
    if "param" in ev:
        parts.append(str(ev["param"]))
    if "cause" in ev:
        parts.append(str(ev["cause"]) + (f": {ev['message']}" if ev.get("message") else ""))
    if "count" in ev:
        parts.append(f"{ev['count']} events lost")
    return "  ".join(parts).rstrip()


def cmd_events(args: argparse.Namespace) -> int:
    """The loop's events as they happen, one line each, until Ctrl-C, --count or the end of
    the run."""
    kinds = None
    if args.kinds is not None:
        kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
        unknown = [k for k in kinds if k not in event_kinds.CODES]
        if unknown or not kinds:
            print(
                f"hapticd: bad_value: unknown event(s) {unknown or args.kinds!r}; events: "
                f"{', '.join(event_kinds.NAMES)}",
                file=sys.stderr,
            )
            return EXIT_BAD_INPUT
    shown = 0
    try:
        with ControlClient(args.socket) as client:
            for ev in client.events(kinds):
                emit(json.dumps(ev) if args.json else format_event(ev))
                shown += 1
                if args.count is not None and shown >= args.count:
                    break
    except KeyboardInterrupt:
        return EXIT_OK
    except (OSError, ValueError) as exc:
        return _client_failed(args, exc)
    return EXIT_OK


def cmd_view(args: argparse.Namespace) -> int:
    """Serve the web view of a running daemon until Ctrl-C or SIGTERM (docs/view.md)."""
    from hapticd.control import UnsafeSocketDirError
    from hapticd.view import ViewServer, is_loopback

    socket_path = args.socket or client_socket_path()
    try:
        view = ViewServer(
            socket_path, host=args.host, port=args.port, control=args.control, rate_hz=args.rate
        )
    except UnsafeSocketDirError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(
            f"hapticd: cannot serve the view on {args.host} port {args.port}: "
            f"{exc.strerror or exc}",
            file=sys.stderr,
        )
        return EXIT_ERROR
    host, port = view.address
    if not is_loopback(host):
        what = "watch the run and change its parameters" if args.control else "watch the run"
        print(
            f"hapticd view: WARNING: serving on {host} port {port}, not loopback: other "
            f"machines can reach this page, and anyone with its URL (it carries the key) can "
            f"{what}; the traffic is not encrypted",
            file=sys.stderr,
        )
    # The URLs first, on stdout: the experimenter's, then the subject's.
    print(view.url)
    print(view.subject_url, flush=True)
    if not args.quiet:
        print(
            "hapticd view: the first URL is the experimenter's page, the second the subject's "
            "(the scene alone); "
            + ("--control: the page may set parameters" if args.control else "read-only")
            + f"; daemon socket {socket_path}; Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )
    stop = threading.Event()

    def on_stop(_signum: int, _frame: object) -> None:
        stop.set()

    old = {s: signal.signal(s, on_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        view.start()
        while not stop.wait(0.5):
            pass
    finally:
        view.close()
        for s, h in old.items():
            signal.signal(s, h)
    return EXIT_OK


def _add_view(sub: Any, sock_help: str) -> None:
    """The view subcommand's arguments."""
    v = sub.add_parser(
        "view",
        help="serve a web page of a running hapticd: the scene, forces, loop, faults",
        description="A separate process, a client of the control socket, that serves a web "
        "page drawing the scene live (the object at its pose, each fingertip's device and "
        "proxy, the full and rendered forces) with the loop's panels, and a subject's page "
        "with the scene alone. Prints the experimenter's URL, then the subject's. Loopback "
        "only unless --host says otherwise; read-only unless --control. See docs/view.md.",
    )
    v.add_argument("--socket", type=Path, metavar="PATH", help=sock_help)
    v.add_argument(
        "--host",
        default="127.0.0.1",
        help="the address to serve on (default 127.0.0.1, this machine only; any other "
        "address is reachable from elsewhere and prints a warning)",
    )
    v.add_argument("--port", type=_port, default=0, help="TCP port (default 0: a free one)")
    v.add_argument(
        "--control",
        action="store_true",
        help="let the page change parameters (the same checked set commands as hapticd set); "
        "the subject's answers to a prompt need no --control",
    )
    v.add_argument(
        "--rate", type=_rate, default=60.0, help="telemetry frames per second (default 60)"
    )
    v.add_argument("-q", "--quiet", action="store_true", help="only the URLs and warnings")
    v.set_defaults(func=cmd_view)
