"""hapticd run, check, calibrate, devices, udev-rules, bringup and schema: the commands that
build a run from a profile."""

from __future__ import annotations

import argparse
import grp
import json
import logging
import signal
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

from hapticd_drivers import BackendUnavailableError, DeviceError, registry
from hapticd_drivers.registry import discover

from hapticd.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_ERROR,
    EXIT_FAULT,
    EXIT_OK,
    _add_set_option,
    _fmt,
    _overrides,
    _ProgressLine,
    _wants_progress,
)
from hapticd.cli.offline import _plot
from hapticd.control import default_socket_path
from hapticd.daemon import bringup, lsl
from hapticd.daemon.build import build_devices, build_scene, load_trajectories
from hapticd.daemon.sdnotify import ServiceNotifier
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.daemon.summary import status, summarize
from hapticd.loop.servo import ServoLoop
from hapticd.profile import ProfileError, load_profile
from hapticd.recording import RecordingError

log = logging.getLogger("hapticd")


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
        # What the device's driver counted (an SDK's saturated motors), where it is not zero.
        counted = "".join(
            f", {n} {what.replace('_', ' ')}" for what, n in f.get("device_counts", {}).items() if n
        )
        lines.append(
            f"    {name:<12} max {f['max_force_n']:.4f} N, in contact {f['contact_ticks']} ticks"
            f"{counted}"
        )
    rt = s.get("realtime")
    if rt is not None:
        policy = f"SCHED_FIFO {rt['fifo_priority']}" if rt["fifo_priority"] else "normal policy"
        lock = ", memory locked" if rt["memory_locked"] else ""
        lines.append(f"  real time       {policy}{lock}")
    rec = s.get("recording")
    if rec is not None:
        where = "(temporary, for the plot; removed)" if rec.get("temporary") else rec["path"]
        lines.append(
            f"  recording       {where}: {rec['written']} ticks written, "
            f"{rec['dropped']} dropped"
            + (f", {rec['lost']} LOST: {rec['error']}" if rec.get("lost") or rec["error"] else "")
        )
    st = s.get("lsl")
    if st is not None:
        lines.append(
            f"  lsl             {st['name']}: {st['written']} ticks published (every "
            f"{st['decimation']}), {st['dropped']} dropped, {st['markers']} markers"
            + (f", {st['markers_lost']} markers lost" if st["markers_lost"] else "")
            + (f"; {st['error']}" if st["error"] else "")
        )
    if s["fault"]:
        lines.append(f"  FAULT (latched) at tick {s['fault']['tick']}: {s['fault']['cause']}")
    return "\n".join(lines)


def _run_socket(args: argparse.Namespace) -> Path | None:
    """The control socket a run serves: none with --no-socket, and none for an --unpaced
    run (a batch render: two of them must not fight over the default socket) unless
    --socket names one; else --socket or the default."""
    if args.no_socket or (args.unpaced and args.socket is None):
        return None
    return args.socket or default_socket_path()


def _socket_group(args: argparse.Namespace) -> int | None:
    """The gid of ``--socket-group`` (a name or a number), or None."""
    name = getattr(args, "socket_group", None)
    if name is None:
        return None
    try:
        return int(name) if name.isdigit() else grp.getgrnam(name).gr_gid
    except KeyError:
        raise ProfileError(
            f"--socket-group {name}: no such group (getent group lists them)"
        ) from None


def _run_total_s(session: Any) -> float | None:
    """How long a run lasts on its nominal clock, s: --duration, else where its
    trajectories end (with their hold_s); None when nothing says (devices in the loop)."""
    loop = session.loop
    if loop.duration_s is not None:
        return float(loop.duration_s)
    if any(getattr(getattr(d, "path", None), "repeat", False) for d in loop.devices):
        return None  # a repeated path has no end
    ends = [getattr(d, "duration", None) for d in loop.devices if getattr(d, "duration", None)]
    if not ends or len(ends) != len(loop.devices):
        return None
    holds = [getattr(f.device, "hold_s", 0.0) or 0.0 for f in session.profile.fingers]
    return max(float(e) + float(h) for e, h in zip(ends, holds, strict=True))


def _start_run_progress(args: argparse.Namespace, session: Any) -> Any:
    """For an --unpaced run with a progress line: a thread that shows the loop's nominal
    time every ``_ProgressLine.PERIOD_S``; returns the function that stops it (a no-op
    otherwise). It only reads the loop's clock; the loop never waits for it."""

    if not (args.unpaced and _wants_progress(args)):
        return lambda: None
    line = _ProgressLine(f"run {args.profile} (unpaced):")
    total = _run_total_s(session)
    stop = threading.Event()

    def show() -> None:
        while not stop.wait(_ProgressLine.PERIOD_S):
            line.show(round(session.loop.now(), 1), total, "s")

    thread = threading.Thread(target=show, name="hapticd-progress", daemon=True)
    thread.start()

    def finish() -> None:
        stop.set()
        thread.join(timeout=2.0)
        line.show(round(session.loop.now(), 3), total, "s", force=True)  # where it ended
        line.done()

    return finish


def _log_build(args: argparse.Namespace, session: Any, socket_path: Path | None) -> None:
    """What the run was built from, at debug level (-v)."""
    if not log.isEnabledFor(logging.DEBUG):
        return
    prof = session.profile
    log.debug(
        "profile %s (%s)%s",
        prof.source,
        prof.name,
        "".join(f" --set {o}" for o in _overrides(args)),
    )
    for f, dev in zip(prof.fingers, session.devices, strict=True):
        info = dev.info
        log.debug(
            "finger %s: %s %s, rated %g N, workspace radius %g m",
            f.name, info.model, info.serial, info.max_force_n, info.workspace_radius_m,
        )  # fmt: skip
    loop = session.loop
    log.debug(
        "loop: %g Hz, %s, stages %s, force limits %s N",
        loop.rate_hz,
        "paced" if loop.paced else "unpaced",
        " ".join(loop.renderer.stage_names),
        ", ".join(f"{v:g}" for v in loop.safety.limits),
    )
    log.debug("control socket: %s", socket_path or "none")


def cmd_run(args: argparse.Namespace) -> int:
    temp_dir = None
    record_path = args.record
    if args.plot is not None and record_path is None:
        # The plot is made from the run's recording: a temporary one unless --record names one.
        temp_dir = tempfile.TemporaryDirectory(prefix="hapticd-run-")
        record_path = Path(temp_dir.name) / "run.hrec"
    try:
        return _run(args, record_path, temporary=temp_dir is not None)
    finally:
        if temp_dir is not None:
            temp_dir.cleanup()


def _run(args: argparse.Namespace, record_path: Path | None, *, temporary: bool = False) -> int:
    """Run the daemon; ``temporary``: ``record_path`` is removed afterwards (--plot without
    --record), so the summary does not name it."""
    from hapticd.cli.plugins import warn_backend_problems

    warn_backend_problems()
    try:
        group = _socket_group(args)
        profile = load_profile(args.profile, _overrides(args))
        use_lsl = args.lsl or profile.lsl.enabled
        if use_lsl:
            # Before any device is made: a run asked to stream never starts without it.
            lsl.require_pylsl("--lsl" if args.lsl else f"{args.profile}: lsl.enabled")
        session = build_session(
            profile,
            paced=not args.unpaced,
            duration_s=args.duration,
            record_path=record_path,
            device=args.device,
            emulate=args.emulate,
            record_dir=args.record_dir,
        )
    except (ProfileError, BackendUnavailableError, RecordingError, lsl.LslUnavailableError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    if args.no_realtime:
        session.loop.realtime_settings = None
    session.overrides = _overrides(args)
    loop = session.loop
    notifier = ServiceNotifier(lambda: loop.stats.ticks, lambda: _service_status(loop))
    socket_path = _run_socket(args)
    server = ControlServer(
        session,
        socket_path,
        periodic=[notifier.poll],
        socket_group=group,
        reload_dirs=args.reload_dir,
    )

    def on_stop(signum: int, _frame: object) -> None:
        # First signal: forces ramp to zero, then the run ends; a second one ends it now.
        loop.request_stop(f"signal {signal.Signals(signum).name}")

    def on_hup(_signum: int, _frame: object) -> None:
        server.request_reload()  # the control thread does the work, not the servo thread

    outlet = None
    if use_lsl:
        try:
            outlet = lsl.attach(session, server)
        except (RecordingError, OSError) as exc:
            if session.loop.recorder is not None:
                session.loop.recorder.close()
            print(f"hapticd: cannot publish LSL streams: {exc}", file=sys.stderr)
            return EXIT_ERROR
    # Before the socket exists: a client (or systemd) that sees it may signal the daemon at
    # once, and a SIGTERM before the handlers were in place killed it without its orderly
    # stop (seen: a test that stopped the daemon as soon as its socket appeared).
    handlers = {signal.SIGINT: on_stop, signal.SIGTERM: on_stop, signal.SIGHUP: on_hup}
    old = {s: signal.signal(s, h) for s, h in handlers.items()}
    try:
        server.start()
    except OSError as exc:
        for s, h in old.items():
            signal.signal(s, h)
        if session.loop.recorder is not None:
            session.loop.recorder.close()
        if outlet is not None:
            lsl.detach(session, outlet)
        print(f"hapticd: cannot serve the control socket {socket_path}: {exc}", file=sys.stderr)
        return EXIT_ERROR
    if socket_path is not None and not args.quiet:
        print(f"hapticd: control socket {socket_path}", file=sys.stderr)
    _log_build(args, session, socket_path)
    stop_progress = _start_run_progress(args, session)
    try:
        summary = session.run()
    except RecordingError as exc:
        # The loop ended safely; only the file is in doubt, and the message says how.
        print(f"hapticd: {exc}", file=sys.stderr)
        summary = getattr(exc, "summary", None) or summarize(loop, session.profile.finger_names)
        summary["recording_error"] = str(exc)
    finally:
        stop_progress()
        notifier.stopping()
        server.close()
        # After the server: the run's last events are on the marker stream.
        lsl_status = None if outlet is None else lsl.detach(session, outlet)
        for s, h in old.items():
            signal.signal(s, h)
    summary["profile"] = str(args.profile)
    if lsl_status is not None:
        summary["lsl"] = lsl_status
    summary["reloads"] = server.reloads
    if temporary and summary.get("recording"):
        # Made only for the plot and removed after it: no path to a file that is gone.
        summary["recording"] = {**summary["recording"], "path": None, "temporary": True}
    if loop.rt_report is not None:
        summary["realtime"] = loop.rt_report.to_json()
    if args.summary_json:
        Path(args.summary_json).write_text(json.dumps(summary, indent=2) + "\n")
    if not args.quiet:
        print(format_summary(summary))
    if args.plot is not None and record_path is not None and "recording_error" not in summary:
        code = _plot(record_path, args.plot, None)
        if code != EXIT_OK:
            return code
    if summary["fault"]:
        return EXIT_FAULT
    return EXIT_ERROR if "recording_error" in summary else EXIT_OK


def _service_status(loop: ServoLoop) -> str:
    st = status(loop)
    p99 = st["period_error_us"]["p99"]
    fault = st["fault"]
    return (
        f"{st['rate_hz']:g} Hz, tick {st['tick']}, p99 period error "
        f"{'n/a' if p99 is None else f'{p99:.1f} us'}, overruns {st['overruns']}, "
        f"{'FAULT: ' + fault['cause'] if fault else 'no fault'}"
    )


def cmd_check(args: argparse.Namespace) -> int:
    from hapticd.cli.plugins import warn_backend_problems

    warn_backend_problems()
    try:
        profile = load_profile(args.profile, _overrides(args))
        load_trajectories(profile)
        build_scene(profile.scene, profile)
        # The devices are created (not opened): a backend's library or driver is checked.
        devices, _ = build_devices(profile, clock=lambda: 0.0)
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
    print("\n".join(bringup.workspace_report(profile, devices)))
    limits = bringup.rendering_limits(profile, devices)
    if limits:
        print("stiffness and damping (the device models' recommended maxima):")
        print("\n".join(line for line, _ in limits))
    return EXIT_OK


def _device_text(d: dict[str, Any]) -> str:
    """One device in ``hapticd status``: connection, force limit, buttons held, deadman."""
    down = d.get("buttons") or []
    parts = [
        "connected" if d["connected"] else "LOST",
        f"limit {d['force_limit_n']:g} N",
        "buttons " + (" ".join(str(b) for b in down) if down else "none") + " down",
    ]
    dm = d.get("deadman")
    if dm is not None:
        state = "held" if dm["held"] else "RELEASED: no force"
        parts.append(f"deadman {dm['button']} {state}")
    return f"{d['serial']} ({', '.join(parts)})"


CALIBRATE_WARNING = """\
hapticd calibrate: these devices will MOVE ON THEIR OWN, one after the other, to find
their end stops (the SDK's automatic initialisation):
{devices}
Before you go on, empty every workspace: no hand on or near a thimble, no cable or
object within reach of the arms. Their forces are off afterwards."""


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Run the SDK's automatic initialisation on the profile's devices that need it."""
    try:
        profile = load_profile(args.profile)
    except ProfileError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    targets = [
        (i, f)
        for i, f in enumerate(profile.fingers)
        if registry.backend(f.device.backend).calibrate
    ]
    if args.finger:
        targets = [(i, f) for i, f in targets if f.name in args.finger]
        missing = set(args.finger) - {f.name for _, f in targets}
        if missing:
            print(
                f"hapticd: {args.profile}: no finger {sorted(missing)} whose device hapticd "
                "calibrates",
                file=sys.stderr,
            )
            return EXIT_BAD_INPUT
    if not targets:
        calibrating = [b.name for b in registry.BACKENDS.values() if b.calibrate]
        print(
            f"hapticd: {args.profile}: nothing to calibrate: hapticd calibrates the "
            f"{', '.join(calibrating)} backend(s), and no finger uses one",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    kwargs_of = {}
    for i, f in targets:
        kw = f.device.model_dump()
        for key in ("backend", "mount", "trajectory", "finger"):
            kw.pop(key, None)
        kwargs_of[i] = kw
    listed = "\n".join(
        f"  {f.name}: {f.device.backend} "
        + (
            f"serial number {kwargs_of[i]['serial_number']}"
            if kwargs_of[i].get("serial_number") is not None
            else f"index {kwargs_of[i].get('index', 0)}"
        )
        for i, f in targets
    )
    moving = [
        (i, f) for i, f in targets if not registry.backend(f.device.backend).calibrate_by_hand
    ]
    if moving:
        print(CALIBRATE_WARNING.format(devices=listed), flush=True)
    else:  # nothing moves on its own: the user moves each device in turn
        print(f"hapticd calibrate: one after the other:\n{listed}", flush=True)
    if moving and not args.yes:
        if not sys.stdin.isatty():
            print(
                "hapticd: refusing to calibrate without a confirmation: stdin is not a "
                "terminal; make sure every workspace is empty, then pass --yes",
                file=sys.stderr,
            )
            return EXIT_BAD_INPUT
        try:
            answer = input("Is every workspace empty? Type 'yes' to calibrate: ")
        except EOFError:
            answer = ""
        if answer.strip().lower() != "yes":
            print("hapticd: calibration cancelled; nothing moved", file=sys.stderr)
            return EXIT_ERROR
    failed = False
    for i, f in targets:
        by_hand = registry.backend(f.device.backend).calibrate_by_hand
        if by_hand:
            print(f"  {f.name}: now {by_hand}", flush=True)
        try:
            out = registry.calibrate(f.device.backend, **kwargs_of[i])
        except DeviceError as exc:
            print(f"hapticd: {f.name}: {exc}", file=sys.stderr)
            failed = True
            continue
        before = "already calibrated, done again" if out["was_calibrated"] else "was not"
        print(f"  {f.name}: {out['model']} {out['serial']} calibrated ({before})")
    return EXIT_ERROR if failed else EXIT_OK


def cmd_devices(args: argparse.Namespace) -> int:
    report = discover()
    if args.json:
        print(json.dumps(report, indent=2))
        return EXIT_OK
    for entry in report:
        if "problem" in entry:
            print(f"{entry['backend']:<4} cannot look: {entry['problem']}")
        elif entry["found"]:
            sdk = f" (SDK {entry['sdk']})" if entry.get("sdk") else ""
            found = ", ".join(map(str, entry["found"]))
            print(f"{entry['backend']:<4} {entry['model']}{sdk}: {found}")
        else:
            print(f"{entry['backend']:<4} {entry['model']}: none found (plugged in? udev rules?)")
    return EXIT_OK


def cmd_udev_rules(args: argparse.Namespace) -> int:
    from hapticd_drivers.udev import rules

    sys.stdout.write(rules())
    return EXIT_OK


def _add_bringup(sub: Any) -> None:
    """``hapticd bringup``: its arguments are hapticd.daemon.bringup's, and so is the work."""
    p = sub.add_parser(
        "bringup",
        help="check a rig before a subject touches it: devices, limits, positions, force pulses",
        description="Check the rig: devices found and calibrated, limits and workspaces, live "
        "positions, a small force pulse (at most 0.5 N) per actuated direction that you "
        "confirm (y/n/r), a PASS/FAIL summary saved as JSON and text (docs/hardware.md).",
    )
    bringup.add_arguments(p)
    _add_set_option(p)
    p.set_defaults(func=cmd_bringup)


# 0 PASS, 1 FAIL, 2 bad input, 3 a fault latched.
BRINGUP_EXIT = {
    bringup.Outcome.PASS: EXIT_OK,
    bringup.Outcome.FAIL: EXIT_ERROR,
    bringup.Outcome.BAD_INPUT: EXIT_BAD_INPUT,
    bringup.Outcome.FAULT: EXIT_FAULT,
}


def cmd_bringup(args: argparse.Namespace) -> int:
    return BRINGUP_EXIT[bringup.bringup(args)]


def _add_schema(sub: Any) -> None:
    sch = sub.add_parser(
        "schema",
        help="print the profile's JSON Schema (for editors: docs/profiles.md)",
        description="Print the JSON Schema of a profile (keys, types, bounds, defaults, "
        "descriptions). hapticd check remains the authority: some checks are not in it.",
    )
    sch.add_argument("--out", type=Path, metavar="PATH", help="write it here (default: stdout)")
    sch.set_defaults(func=cmd_schema)


def cmd_schema(args: argparse.Namespace) -> int:
    from hapticd.profile import json_schema

    text = json.dumps(json_schema(), indent=2) + "\n"
    if args.out is None:
        sys.stdout.write(text)
        return EXIT_OK
    try:
        args.out.write_text(text)
    except OSError as exc:
        print(f"hapticd: cannot write the schema: {exc}", file=sys.stderr)
        return EXIT_ERROR
    print(f"{args.out}: the profile's JSON Schema")
    return EXIT_OK
