"""The ``hapticd`` command line: run a profile (the daemon), check a profile, and the
client commands that talk to a running daemon over its control socket."""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np
from hapticd_drivers import BackendUnavailableError, DeviceError, registry
from hapticd_drivers.registry import backend_names, discover

from hapticd import __version__, bringup, params
from hapticd import events as event_kinds
from hapticd import protocol as proto
from hapticd.build import build_devices, build_mounts, build_scene, load_trajectories
from hapticd.control import ControlClient, NoDaemonError, default_socket_path
from hapticd.daemon.sdnotify import ServiceNotifier
from hapticd.daemon.server import ControlServer
from hapticd.daemon.session import build_session
from hapticd.daemon.summary import status, summarize
from hapticd.mount import Mount, Reach, workspace_reach
from hapticd.profile import ProfileError, load_profile
from hapticd.protocol import ProtocolError
from hapticd.recording import RecordingError
from hapticd.recording import read as read_recording
from hapticd.recording.export import csv_columns, export_csv, export_mcap
from hapticd.servo import ServoLoop

log = logging.getLogger("hapticd")

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
    rt = s.get("realtime")
    if rt is not None:
        policy = f"SCHED_FIFO {rt['fifo_priority']}" if rt["fifo_priority"] else "normal policy"
        lock = ", memory locked" if rt["memory_locked"] else ""
        lines.append(f"  real time       {policy}{lock}")
    rec = s.get("recording")
    if rec is not None:
        lines.append(
            f"  recording       {rec['path']}: {rec['written']} ticks written, "
            f"{rec['dropped']} dropped"
        )
    if s["fault"]:
        lines.append(f"  FAULT (latched) at tick {s['fault']['tick']}: {s['fault']['cause']}")
    return "\n".join(lines)


def _overrides(args: argparse.Namespace) -> list[str]:
    """The ``--set KEY=VALUE`` values of ``run`` and ``check`` (none for other callers)."""
    return list(getattr(args, "set", None) or [])


def _add_set_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override one profile value (repeatable): KEY a dotted key path, list items by "
        "index or name (scene.object.stiffness_n_per_m=90, fingers[thumb].device.max_force_n=5), "
        "VALUE a YAML scalar or list; validated with the profile",
    )


def _run_socket(args: argparse.Namespace) -> Path | None:
    """The control socket a run serves: none with --no-socket, and none for an --unpaced
    run (a batch render: two of them must not fight over the default socket) unless
    --socket names one; else --socket or the default."""
    if args.no_socket or (args.unpaced and args.socket is None):
        return None
    return args.socket or default_socket_path()


def _run_total_s(session: Any) -> float | None:
    """How long a run lasts on its nominal clock, s: --duration, else where its
    trajectories end (with their hold_s); None when nothing says (devices in the loop)."""
    loop = session.loop
    if loop.duration_s is not None:
        return float(loop.duration_s)
    ends = [getattr(d, "duration", None) for d in loop.devices if getattr(d, "duration", None)]
    if not ends or len(ends) != len(loop.devices):
        return None
    holds = [getattr(f.device, "hold_s", 0.0) or 0.0 for f in session.profile.fingers]
    return max(float(e) + float(h) for e, h in zip(ends, holds, strict=True))


def _start_run_progress(args: argparse.Namespace, session: Any) -> Any:
    """For an --unpaced run with a progress line: a thread that shows the loop's nominal
    time every ``_ProgressLine.PERIOD_S``; returns the function that stops it (a no-op
    otherwise). It only reads the loop's clock; the loop never waits for it."""
    import threading

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
        return _run(args, record_path)
    finally:
        if temp_dir is not None:
            temp_dir.cleanup()


def _run(args: argparse.Namespace, record_path: Path | None) -> int:
    try:
        profile = load_profile(args.profile, _overrides(args))
        session = build_session(
            profile,
            paced=not args.unpaced,
            duration_s=args.duration,
            record_path=record_path,
            device=args.device,
            emulate=args.emulate,
            record_dir=args.record_dir,
        )
    except (ProfileError, BackendUnavailableError, RecordingError) as exc:
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
    server = ControlServer(session, socket_path, periodic=[notifier.poll])
    try:
        server.start()
    except OSError as exc:
        if session.loop.recorder is not None:
            session.loop.recorder.close()
        print(f"hapticd: cannot serve the control socket {socket_path}: {exc}", file=sys.stderr)
        return EXIT_ERROR

    def on_stop(signum: int, _frame: object) -> None:
        # First signal: forces ramp to zero, then the run ends; a second one ends it now.
        loop.request_stop(f"signal {signal.Signals(signum).name}")

    def on_hup(_signum: int, _frame: object) -> None:
        server.request_reload()  # the control thread does the work, not the servo thread

    handlers = {signal.SIGINT: on_stop, signal.SIGTERM: on_stop, signal.SIGHUP: on_hup}
    old = {s: signal.signal(s, h) for s, h in handlers.items()}
    if socket_path is not None and not args.quiet:
        print(f"hapticd: control socket {socket_path}", file=sys.stderr)
    _log_build(args, session, socket_path)
    stop_progress = _start_run_progress(args, session)
    try:
        summary = session.run()
    except RecordingError as exc:
        # The loop ended safely; only the file is in doubt, and the message says how.
        print(f"hapticd: {exc}", file=sys.stderr)
        summary = summarize(loop, session.profile.finger_names)
        summary["recording_error"] = str(exc)
    finally:
        stop_progress()
        notifier.stopping()
        server.close()
        for s, h in old.items():
            signal.signal(s, h)
    summary["profile"] = str(args.profile)
    summary["reloads"] = server.reloads
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


def _mm(v: Any) -> str:
    return "(" + ", ".join(f"{1e3 * float(c):.1f}" for c in v) + ") mm"


def _reach_line(name: str, r: Reach, where: str) -> str:
    if r.contained:
        verdict = "the whole object is inside"
    elif r.reachable:
        verdict = "the object is reachable (part of it lies outside)"
    else:
        verdict = "WARNING: the object is out of reach"
    pad = " " * (len(name) + 4)
    return (
        f"  {name}: {where}, radius {1e3 * r.workspace_radius_m:.1f} mm; the object's centre is "
        f"at {_mm(r.center_device_m)} in its coordinates\n{pad}"
        f"({1e3 * r.center_distance_m:.1f} mm from its centre; nearest object point "
        f"{1e3 * r.nearest_m:.1f} mm, farthest {1e3 * r.farthest_m:.1f} mm): {verdict}"
    )


def workspace_reaches(profile: Any, devices: list[Any]) -> list[tuple[str, Reach, str]]:
    """Per finger, then the safety section's sphere (if set): (name, how the workspace
    meets the object at its starting pose, where the workspace is)."""
    obj = build_scene(profile.scene, profile).object
    poly, verts = obj.polytope, obj.vertices_world()
    out = []
    for f, dev, mount in zip(profile.fingers, devices, build_mounts(profile), strict=True):
        r = workspace_reach(
            mount,
            dev.info.workspace_radius_m,
            poly.normals,
            poly.offsets,
            verts,
            obj.center,
            f.radius_m,
        )
        out.append((f.name, r, f"device workspace about {_mm(mount.position)} (world)"))
    sc = profile.safety
    if sc.workspace_radius_m is not None:
        safety = Mount(position=np.array(sc.workspace_center_m, dtype=float))
        r = workspace_reach(
            safety, sc.workspace_radius_m, poly.normals, poly.offsets, verts, obj.center, 0.0
        )
        out.append(("safety", r, "workspace (world)"))
    return out


def workspace_report(profile: Any, devices: list[Any]) -> list[str]:
    """Per finger, how its device's workspace sphere (from the device description, placed
    by its mount) and the safety section's sphere meet the object at its starting pose."""
    lines = ["workspaces (the object at its starting pose):"]
    lines += [_reach_line(*w) for w in workspace_reaches(profile, devices)]
    return lines


def cmd_check(args: argparse.Namespace) -> int:
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
    print("\n".join(workspace_report(profile, devices)))
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
    print(CALIBRATE_WARNING.format(devices=listed), flush=True)
    if not args.yes:
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
        try:
            out = registry.calibrate(f.device.backend, **kwargs_of[i])
        except DeviceError as exc:
            print(f"hapticd: {f.name}: {exc}", file=sys.stderr)
            failed = True
            continue
        before = "already calibrated, done again" if out["was_calibrated"] else "was not"
        print(f"  {f.name}: {out['model']} {out['serial']} calibrated ({before})")
    return EXIT_ERROR if failed else EXIT_OK


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
        print(f"hapticd: {exc.code}: {exc}", file=sys.stderr)
        # The request was wrong (exit 2), or the daemon's state (exit 1): hapticd.protocol.
        return EXIT_BAD_INPUT if exc.code in proto.BAD_REQUEST else EXIT_ERROR
    if isinstance(exc, NoDaemonError):
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    where = args.socket or default_socket_path()
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
            what = "" if spec is None else f"bad value {args.value!r} for {args.param}: "
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
                    print(format_status(result))
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
                print("  ".join(parts), flush=True)
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
                text = json.dumps(ev) if args.json else format_event(ev)
                print(text, flush=True)
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

    socket_path = args.socket or default_socket_path()
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


def _rate(text: str) -> float:
    v = float(text)
    if not 0.1 <= v <= 1000:
        raise argparse.ArgumentTypeError(f"expected a rate in [0.1, 1000] Hz, got {text}")
    return v


def _port(text: str) -> int:
    v = int(text)
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"expected a TCP port in [0, 65535], got {text}")
    return v


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


def _at(text: list[str], n_fingers: int) -> list[float]:
    if len(text) != 3 * n_fingers:
        raise ValueError(
            f"--at needs {3 * n_fingers} numbers (x y z in m for each of {n_fingers} fingers), "
            f"got {len(text)}"
        )
    try:
        return [float(v) for v in text]
    except ValueError as exc:
        raise ValueError(f"--at: {exc}") from None


def cmd_analyze(args: argparse.Namespace) -> int:
    """Barbagli & Salisbury's analysis of a profile's rendering (docs/analysis.md)."""
    import numpy as np

    from hapticd.analysis import Pipeline, report

    try:
        profile = load_profile(args.profile)
        allocators = args.allocators.split(",") if args.allocators else None
        pipe = Pipeline.from_profile(profile, allocators=allocators)
    except ProfileError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ValueError as exc:
        print(f"hapticd: --allocators: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    obj = profile.scene.object
    head = (
        f"hapticd analyze {args.profile}: profile {profile.name!r}, {obj.shape} "
        f"{'fixed' if obj.fixed else 'free (held at its pose)'}, "
        f"{pipe.scene.object.material.stiffness:g} N/m, "
        f"{'friction' if pipe.has_friction else 'frictionless'}, "
        f"{profile.rendering.actuation_frame}-frame actuation; at rest (zero velocity), "
        "before safety"
    )
    out: dict[str, Any] = {"profile": str(args.profile), "allocators": list(pipe.allocators)}
    try:
        if args.recording is not None:
            rec = read_recording(args.recording)
            if "device_pos" not in rec:
                raise RecordingError(f"{args.recording}: no device_pos field")
            pos = rec["device_pos"]
            note = ""
            if list(rec.fingers) != list(pipe.finger_names):
                if pos.ndim != 3 or pos.shape[1] != pipe.n_fingers:
                    raise RecordingError(
                        f"{args.recording} has fingers {rec.fingers}, the profile "
                        f"{list(pipe.finger_names)}"
                    )
                note = f"; its fingers {', '.join(rec.fingers)} taken in the profile's order"
            extra = {
                k: rec[k] for k in ("object_pos", "object_rot", "stiffness_n_per_m") if k in rec
            }
            times = rec["t"] if "t" in rec else np.arange(len(pos)) * pipe.dt
            show = args.progress or sys.stderr.isatty()
            samples = pipe.along(
                pos,
                args.every,
                object_pos=extra.get("object_pos"),
                object_rot=extra.get("object_rot"),
                stiffness=extra.get("stiffness_n_per_m"),
                progress=report.Progress("analyze") if show else None,
            )
            recorded = ", ".join(extra) or "none"
            print(head)
            print(
                f"recording {args.recording}: {len(pos)} ticks; every {args.every}th: "
                f"{len(samples)} samples (recorded scene state applied: {recorded}){note}\n"
            )
            print(report.format_samples(samples, times, pipe.allocators), end="")
            out["recording"] = str(args.recording)
            out["every"] = args.every
            out["samples"] = report.samples_json(samples, times)
            plot_kw: dict[str, Any] = {"samples": samples, "times": times}
        else:
            if args.at is not None:
                x = np.array(_at(args.at, pipe.n_fingers)).reshape(-1, 3)
                how = "given with --at"
            else:
                x, how = report.default_configuration(pipe)
            results = pipe.linearize(x)
            print(
                report.format_linearization(results, header=[head, f"configuration: {how}"]),
                end="",
            )
            out["configuration"] = {"x_m": x.tolist(), "how": how}
            out["results"] = report.to_json(results)
            plot_kw = {"results": results}
    except (ValueError, RecordingError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        if args.json is not None:
            args.json.write_text(json.dumps(out, indent=1, allow_nan=False) + "\n")
        if args.plot is not None:
            try:
                report.plot(
                    args.plot,
                    pipe.allocators,
                    title=f"{profile.name}: asymmetry and work per loop area, per allocator",
                    **plot_kw,
                )
            except ImportError:
                print(
                    "hapticd: --plot needs matplotlib: pip install matplotlib "
                    "(or the 'bench' extra)",
                    file=sys.stderr,
                )
                return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK


def _every(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive number of ticks, got {text}")
    return v


def _add_analyze(sub: Any) -> None:
    """The analyze subcommand's arguments."""
    ana = sub.add_parser(
        "analyze",
        help="Barbagli & Salisbury's asymmetry analysis of a profile's rendering, per allocator",
        description="Linearize the rendering of PROFILE (central differences on the loop's own "
        "stages, at rest, before safety): K_full (the seed's F_L), K_rendered (M_A F_L M_S), "
        "asymmetry, controllability, observability, the directions without rendered stiffness "
        "and the work per unit loop area, for each allocator. See docs/analysis.md.",
    )
    ana.add_argument("profile", type=Path)
    where = ana.add_mutually_exclusive_group()
    where.add_argument(
        "--at",
        nargs="+",
        metavar="M",
        help="finger positions, x y z in m per finger (default: each finger 2 mm inside the "
        "object along its x axis, the first on the -x side)",
    )
    where.add_argument(
        "--recording", type=Path, metavar="REC", help="analyse the ticks of a recording"
    )
    ana.add_argument(
        "--every", type=_every, default=10, metavar="K", help="every K-th tick (default 10)"
    )
    ana.add_argument(
        "--allocators",
        metavar="A,B",
        help=f"allocators to compare (default: pinv,if,ef,adaptive; any of "
        f"{','.join(params.ALLOCATORS)})",
    )
    ana.add_argument("--json", type=Path, metavar="OUT", help="write every number as JSON")
    ana.add_argument("--plot", type=Path, metavar="OUT.png", help="plot (needs matplotlib)")
    ana.add_argument(
        "--progress", action="store_true", help="show progress on stderr even when not a terminal"
    )
    ana.set_defaults(func=cmd_analyze)


def cmd_experiment_check(args: argparse.Namespace) -> int:
    """Validate an experiment file and its base profile; print the design."""
    from hapticd.experiment import ExperimentError, check_experiment, make_plan

    try:
        exp, profile = check_experiment(args.experiment)
        load_trajectories(profile)
        build_scene(profile.scene, profile)
        build_devices(profile, clock=lambda: 0.0)
    except (ExperimentError, ProfileError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    v, spec = exp.varied, params.PARAMS[exp.varied.param]
    plan = make_plan(exp, exp.subject_seed("example"))
    total = len(plan)
    dur = exp.duration_s()
    conds = ", ".join(
        f"{c.name} ({', '.join(f'{k}={val}' for k, val in c.values().items())})"
        for c in exp.conditions
    )
    print(
        f"{args.experiment}: OK: experiment {exp.name!r} on profile {profile.name!r} "
        f"({exp.profile_path()})\n"
        f"  varied       {v.param} ({spec.unit}): standards "
        f"{', '.join(f'{s:g}' for s in v.standards)}; ratios "
        f"{', '.join(f'{r:g}' for r in v.ratios)}\n"
        f"  conditions   {conds}\n"
        f"  trials       {exp.comparisons} comparisons x {exp.repetitions} repetitions per "
        f"standard and condition; {exp.trials_per_block} per block, {exp.n_blocks} blocks, "
        f"{total} per subject\n"
        f"  interval     {exp.interval.order}, 'was the second {exp.interval.question}?', "
        f"at most {exp.interval.exploration_s:g} s, ends on {exp.interval.ends_on}\n"
        f"  breaks       {exp.n_breaks()} of {exp.breaks.duration_s:g} s\n"
        f"  duration     about {dur / 60:.0f} min per subject ({exp.trial_s():g} s per trial "
        "with every interval at its limit, and the breaks)"
    )
    return EXIT_OK


def cmd_experiment_plan(args: argparse.Namespace) -> int:
    """One subject's trial plan as CSV (stdout or --csv)."""
    import csv
    import io

    from hapticd.experiment import ExperimentError, load_experiment, make_plan

    try:
        exp = load_experiment(args.experiment)
    except ExperimentError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    seed = exp.subject_seed(args.subject) if args.seed is None else args.seed
    plan = make_plan(exp, seed)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(plan[0].as_dict()), lineterminator="\n")
    writer.writeheader()
    writer.writerows(t.as_dict() for t in plan)
    if args.csv is None:
        sys.stdout.write(buf.getvalue())
        return EXIT_OK
    try:
        args.csv.write_text(buf.getvalue())
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR
    print(f"{args.csv}: {len(plan)} trials of subject {args.subject!r} (seed {seed})")
    return EXIT_OK


def cmd_experiment_analyze(args: argparse.Namespace) -> int:
    """Fits, group means and paired t-tests from trial stores."""
    from hapticd.experiment import analyze as ana
    from hapticd.experiment.store import StoreError, open_for_analysis

    trials: list[dict[str, Any]] = []
    first: dict[str, Any] | None = None
    try:
        for db in args.db:
            meta, rows = open_for_analysis(db)
            if first is not None and meta.get("experiment_hash") != first.get("experiment_hash"):
                raise StoreError(
                    f"{db}: holds experiment {meta.get('experiment')!r} with another file hash "
                    f"than {args.db[0]} ({first.get('experiment')!r}): not analysed together"
                )
            first = first or meta
            trials += rows
    except StoreError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not trials:
        print(f"hapticd: {', '.join(map(str, args.db))}: no complete trials", file=sys.stderr)
        return EXIT_BAD_INPUT
    assert first is not None
    design = first.get("design") or {}
    result = ana.analyze(
        trials, conditions=design.get("conditions"), n_boot=args.boot, seed=args.seed
    )
    param = args.param or design.get("param", "stimulus")
    unit = args.unit or design.get("unit", "SI units")
    print(
        f"hapticd experiment analyze: experiment {first.get('experiment')!r}, varied {param} "
        f"({unit}), {len(trials)} complete trials"
    )
    print(ana.format_report(result, unit), end="")
    try:
        if args.json is not None:
            args.json.write_text(json.dumps(ana.to_json(result), indent=1, allow_nan=False) + "\n")
        if args.plots is not None:
            try:
                for path in ana.plot(result, args.plots, param=param, unit=unit):
                    print(f"plot: {path}")
            except ImportError:
                print("hapticd: --plots needs matplotlib: pip install matplotlib", file=sys.stderr)
                return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write: {exc}", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK


def cmd_experiment_run(args: argparse.Namespace) -> int:
    """Run (or resume) one subject on a running daemon (hapticd.experiment.runner)."""
    from hapticd.experiment import ExperimentError, check_experiment
    from hapticd.experiment import runner as rn

    try:
        exp, _ = check_experiment(args.experiment)
        standards = None if args.standards is None else rn.float_list(args.standards)
        exp = rn.reduced(exp, standards=standards, repetitions=args.repetitions)
        opts = rn.RunOptions(
            socket=args.socket,
            keys_fd=None if args.no_keys else rn.stdin_fd(),
            person=rn.PersonOptions(buttons=rn.parse_buttons(args.buttons)),
        )
        db = args.db or Path(f"{exp.name}-trials.db")
        done, left = rn.run_experiment(
            exp, args.subject, db, seed=args.seed, resume=args.resume,
            observer=args.observer, options=opts,
        )  # fmt: skip
    except (ExperimentError, ProfileError, rn.StoreError, ValueError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except rn.TrialAbortedError as exc:
        why = "interrupted (Ctrl-C)" if exc.interrupted else str(exc)
        print(
            f"hapticd: {why}: the trial in progress is stored incomplete, the answered ones "
            f"are kept; continue with --resume",
            file=sys.stderr,
        )
        return 130 if exc.interrupted else EXIT_ERROR
    except rn.RunnerError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("hapticd: interrupted between trials; continue with --resume", file=sys.stderr)
        return 130
    print(f"hapticd: {done} trial(s) answered; {left} left" + ("" if left else ": done"))
    return EXIT_OK


def _add_experiment_run(esub: Any) -> None:
    run = esub.add_parser(
        "run",
        help="run a subject on a running daemon (answers: keys 1/n or 2/y, buttons, browser)",
    )
    run.add_argument("experiment", type=Path)
    run.add_argument("--subject", required=True, help="the subject's id (names the recordings)")
    run.add_argument("--db", type=Path, help="the trial store (default: NAME-trials.db here)")
    run.add_argument("--seed", type=int, help="use this seed instead of the subject's")
    run.add_argument("--repetitions", type=int, help="a reduced design: repetitions")
    run.add_argument("--standards", metavar="LIST", help="a reduced design: e.g. 60 or 30,90")
    run.add_argument("--resume", action="store_true", help="continue the subject's stored plan")
    run.add_argument("--socket", type=Path, help="the daemon's control socket")
    run.add_argument(
        "--observer",
        default="person",
        help="who answers: person (at a running daemon; the default) or model (the simulated "
        "subject, in this process, no daemon)",
    )
    run.add_argument("--buttons", metavar="MAP", help="response labels as answers: L=yes,L=no")
    run.add_argument("--no-keys", action="store_true", help="read no answers from the terminal")
    run.set_defaults(func=cmd_experiment_run)


def _add_experiment(sub: Any) -> None:
    """The experiment subcommand: check a design, analyze trial stores."""
    exp = sub.add_parser("experiment", help="JND experiments: check a design, analyze trials")
    esub = exp.add_subparsers(dest="experiment_command", required=True)
    chk = esub.add_parser("check", help="validate an experiment file and its profile")
    chk.add_argument("experiment", type=Path)
    chk.set_defaults(func=cmd_experiment_check)
    _add_experiment_run(esub)
    pl = esub.add_parser("plan", help="one subject's trial plan as CSV")
    pl.add_argument("experiment", type=Path)
    pl.add_argument("--subject", required=True, help="the subject's id (its seed derives from it)")
    pl.add_argument("--seed", type=int, help="use this seed instead of the subject's")
    pl.add_argument("--csv", type=Path, metavar="OUT", help="write here (default: stdout)")
    pl.set_defaults(func=cmd_experiment_plan)
    ana = esub.add_parser(
        "analyze",
        help="psychometric fits, Weber fractions and paired t-tests from trial stores",
    )
    ana.add_argument("db", type=Path, nargs="+", help="trial store(s) of one experiment")
    ana.add_argument("--json", type=Path, metavar="OUT", help="write the results as JSON")
    ana.add_argument("--plots", type=Path, metavar="DIR", help="write the plots here")
    ana.add_argument("--boot", type=int, default=1000, help="bootstrap refits per fit")
    ana.add_argument("--seed", type=int, default=0, help="bootstrap seed")
    ana.add_argument(
        "--param", help="the varied parameter, for labels (default: the store's design)"
    )
    ana.add_argument("--unit", help="its unit, for labels (default: the store's design)")
    ana.set_defaults(func=cmd_experiment_analyze)


def _add_study(sub: Any) -> None:
    """hapticd study: model-observer subjects in parallel (hapticd.experiment.study)."""

    def run(args: argparse.Namespace) -> int:
        from hapticd.experiment.study import cmd_study

        return cmd_study(args)

    st = sub.add_parser("study", help="run simulated subjects (the model observer) in parallel")
    st.add_argument("experiment", type=Path)
    st.add_argument("--observers", type=int, required=True, metavar="N", help="subjects s01..")
    st.add_argument("--db", type=Path, help="trial store (default: study-EXPERIMENT.sqlite)")
    st.add_argument("--seed", type=int, help="derive each subject's seed from this")
    st.add_argument("--workers", type=int, metavar="K", help="processes (default: the cores)")
    st.add_argument("--standards", type=lambda s: [float(x) for x in s.split(",")], metavar="A,B")
    st.add_argument("--repetitions", type=int, metavar="N", help="per comparison (reduced)")
    st.add_argument("--scheduler", metavar="ADDRESS", help="a Dask scheduler (pip: hapticd[dask])")
    st.add_argument("--quiet", action="store_true", help="no progress bar")
    st.set_defaults(func=run)


def _wants_progress(args: argparse.Namespace) -> bool:
    """A progress line on stderr: with --progress, or when stderr is a terminal."""
    return bool(getattr(args, "progress", False)) or sys.stderr.isatty()


class _ProgressLine:
    """One line on stderr, rewritten in place (at most every ``PERIOD_S``), ended by
    ``done``: ``hapticd: LABEL 41% (3.2 of 7.8 s)``."""

    PERIOD_S = 0.25

    def __init__(self, label: str) -> None:
        self.label = label
        self._last = -math.inf
        self._shown = False

    def show(self, done: float, total: float | None, unit: str, *, force: bool = False) -> None:
        import time

        now = time.monotonic()
        if not force and now - self._last < self.PERIOD_S:
            return
        self._last = now
        if total:
            text = f"{100.0 * min(done / total, 1.0):3.0f}% ({done:g} of {total:g} {unit})"
        else:
            text = f"{done:g} {unit}"
        sys.stderr.write(f"\rhapticd: {self.label} {text}\x1b[K")
        sys.stderr.flush()
        self._shown = True

    def done(self) -> None:
        if self._shown:
            sys.stderr.write("\n")
            sys.stderr.flush()


def _export_progress(args: argparse.Namespace) -> tuple[Any, _ProgressLine | None]:
    """The ``progress`` callback of an export (None without a progress line)."""
    if not _wants_progress(args):
        return None, None
    line = _ProgressLine(f"export {args.recording}:")

    def progress(done: int, total: int) -> None:
        line.show(done, total, "ticks", force=done == total)

    return progress, line


def _plot(source: Path, out: Path, panels: list[str] | None) -> int:
    """Draw ``source`` (a recording or a run summary) into ``out``; print where it went."""
    from hapticd import plot

    try:
        fig = plot.figure_for(source, panels)
        plot.save(fig, out)
    except plot.PlotError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ImportError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write the plot {out}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_ERROR
    print(f"plot: {out}")
    return EXIT_OK


def cmd_plot(args: argparse.Namespace) -> int:
    from hapticd import plot

    try:
        panels = plot.parse_panels(args.fields)
    except plot.PlotError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    out = args.out or Path(tempfile.gettempdir()) / f"hapticd-plot-{args.source.stem}.png"
    return _plot(args.source, out, panels)


def _add_plot(sub: Any) -> None:
    """The plot subcommand's arguments."""
    from hapticd.plot import PANELS

    pl = sub.add_parser(
        "plot",
        help="plot a recording (forces, contact, residuals, object, timing) or a run summary",
        description="Draw a recording (.hrec) as panels over time, or a run summary "
        "(hapticd run --summary-json) as its period error histogram, into a PNG. Panels: "
        + "; ".join(f"{p.name}: {p.doc}" for p in PANELS)
        + ". Needs matplotlib (the 'plot' extra).",
    )
    pl.add_argument("source", type=Path, metavar="REC", help="a recording or a summary JSON")
    pl.add_argument(
        "--out",
        type=Path,
        metavar="FILE.png",
        help="where the figure goes (default: hapticd-plot-NAME.png in the temp dir)",
    )
    pl.add_argument(
        "--fields",
        metavar="A,B",
        help=f"the panels to draw, by name ({','.join(p.name for p in PANELS)}) or by a field "
        "they draw (default: every panel the recording can fill)",
    )
    pl.set_defaults(func=cmd_plot)


def cmd_export(args: argparse.Namespace) -> int:
    progress, line = _export_progress(args)
    try:
        rec = read_recording(args.recording)
        if args.mcap is not None:
            out, rows = args.mcap, export_mcap(rec, args.mcap, progress=progress)
            what = "messages on /hapticd/tick"
        else:
            out = args.csv or args.recording.with_suffix(".csv")
            rows = export_csv(rec, out, progress=progress)
            what = f"ticks, {len(csv_columns(rec))} columns"
    except RecordingError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except RuntimeError as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(f"hapticd: cannot write the export: {exc}", file=sys.stderr)
        return EXIT_ERROR
    finally:
        if line is not None:
            line.done()
    torn = f" (a torn last record of {rec.torn_bytes} bytes was dropped)" if rec.torn_bytes else ""
    print(f"{out}: {rows} {what}{torn}")
    return EXIT_OK


def cmd_devices(args: argparse.Namespace) -> int:
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


def _count(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive number of events, got {text}")
    return v


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
        "--record",
        type=Path,
        metavar="PATH",
        help="record every tick to PATH (.hrec), anywhere you may write",
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
        "--device",
        choices=backend_names(),
        help="use this backend for every finger instead of the profile's",
    )
    run.add_argument(
        "--emulate",
        action="store_true",
        help="put the device emulator under the hid or usb backend, moved along the trajectory",
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
            p.add_argument("name", choices=list(params.ALLOCATORS))
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
    udev = sub.add_parser("udev-rules", help="print udev rules that let users open the devices")
    udev.set_defaults(func=cmd_udev_rules)
    return ap


def _add_bringup(sub: Any) -> None:
    """``hapticd bringup``: its arguments are hapticd.bringup's, and so is the work."""
    p = sub.add_parser(
        "bringup",
        help="check a rig before a subject touches it: devices, limits, positions, force pulses",
        description="Check the rig: devices found and calibrated, limits and workspaces, live "
        "positions, a small force pulse (at most 0.5 N) per actuated direction that you "
        "confirm (y/n/r), a PASS/FAIL summary saved as JSON and text (docs/hardware.md).",
    )
    bringup.add_arguments(p)
    _add_set_option(p)
    p.set_defaults(func=bringup.bringup)


def _add_progress_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--progress",
        action="store_true",
        help="show a progress line on stderr (default: when stderr is a terminal; a run "
        "shows one only --unpaced)",
    )


LOG_LEVELS = ("debug", "info", "warning", "error")


def _add_log_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--log-level",
        choices=LOG_LEVELS,
        help="what the log on stderr shows (default info: faults, device events, control "
        "changes; debug adds what the run was built from)",
    )
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="the same as --log-level debug"
    )


def _log_level(args: argparse.Namespace) -> int:
    """The logging level ``args`` ask for (INFO unless -v or --log-level say otherwise)."""
    if getattr(args, "verbose", False):
        return logging.DEBUG
    name = getattr(args, "log_level", None)
    return getattr(logging, name.upper()) if name else logging.INFO


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


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="hapticd: %(message)s", stream=sys.stderr)
    logging.getLogger("hapticd").setLevel(_log_level(args))
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
