"""``hapticd bringup PROFILE``: the check a researcher runs before a subject touches the rig.

In order: the devices are found and calibrated (each opened, asked, closed); the
limits and the workspaces are shown; the servo loop starts, built exactly as
``hapticd run`` builds it, with one change to its renderer: a last stage
(hapticd.loop.pulse) replaces the rendered forces with scripted pulses (zero between
them), so nothing of the scene is felt and the object stays at its starting
pose. The positions are shown live (world frame, device frame, object frame and
the gap to the object's surface, per finger); then each actuated direction of
each finger gets a small smooth pulse (at most 0.5 N) through the loop's safety
chain and device bank, and the user answers whether it was felt in the expected
direction (y, n, or r to repeat it). A summary says PASS or FAIL, and a JSON and
a text file with the date in their names keep it (docs/hardware.md).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import math
import select
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from hapticd_drivers import BackendUnavailableError, Device, registry

from hapticd import __version__
from hapticd.daemon.build import build_mounts, build_scene
from hapticd.daemon.session import Session, build_session, record_directory
from hapticd.loop.commands import Command
from hapticd.loop.mount import Mount, Reach, workspace_reach
from hapticd.loop.pulse import MAX_PULSE_N, PulseStage
from hapticd.profile import ProfileError, load_profile
from hapticd.recording import RecordingError

if TYPE_CHECKING:
    from hapticd.loop.servo import ServoLoop

PULSE_RAMP_S = 0.2
PULSE_HOLD_S = 0.3
# A direction is repeated at most this often ("r"), then counts as not confirmed.
MAX_REPEATS = 5
# A pulse that reached its device with less than this share of its amplitude was held
# back by the safety chain (a released deadman, a rate limit, a fault): not a pass.
MIN_SENT_SHARE = 0.9
LIVE_REFRESH_S = 0.1
START_TIMEOUT_S = 10.0  # wall time for the loop to open the devices and run a tick
STOP_TIMEOUT_S = 10.0  # beyond the stop ramp


class Outcome(Enum):
    """How a bring-up ended (the command line turns it into its exit code)."""

    PASS = "pass"
    FAIL = "fail"  # a check failed, or the report could not be saved
    BAD_INPUT = "bad input"  # the profile, a backend or the recording directory
    FAULT = "fault"  # a fault latched


def parse_answers(text: str) -> str:
    """``--answers``: y, n and r, in order (spaces and commas ignored)."""
    ans = "".join(c for c in text.lower() if c not in " ,")
    bad = sorted({c for c in ans if c not in "ynr"})
    if not ans or bad:
        raise argparse.ArgumentTypeError(
            f"expected answers y (felt as expected), n (not) or r (repeat), e.g. yyn; got {text!r}"
        )
    return ans


def _number(text: str, ok: Callable[[float], bool], expected: str) -> float:
    """``text`` as a number for which ``ok`` holds; ArgumentTypeError saying ``expected``
    (NaN and text that is not a number fail every check)."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not ok(v):
        raise argparse.ArgumentTypeError(f"{expected}, got {text}")
    return v


def parse_pulse_n(text: str) -> float:
    """``--pulse-n``: the pulse's amplitude, N, in (0, MAX_PULSE_N]."""
    return _number(
        text, lambda v: 0.0 < v <= MAX_PULSE_N, f"a pulse's amplitude is in (0, {MAX_PULSE_N:g}] N"
    )


def parse_live_s(text: str) -> float:
    """``--live-s``: how long positions are shown live, s (0: one snapshot)."""
    return _number(text, lambda v: 0.0 <= v <= 3600.0, "expected 0 to 3600 s")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``hapticd bringup``'s arguments (the command line is hapticd.cli's)."""
    p.add_argument("profile", type=Path)
    p.add_argument(
        "--answers",
        type=parse_answers,
        metavar="YNR",
        help="scripted answers, one per pulse, in order: y (felt in the expected direction), "
        "n (not), r (repeat the pulse); default: asked on stdin",
    )
    p.add_argument(
        "--live-s",
        type=parse_live_s,
        default=10.0,
        metavar="S",
        help="show the positions live for S seconds, or until Enter on a terminal (default 10; "
        "0: one snapshot)",
    )
    p.add_argument(
        "--pulse-n",
        type=parse_pulse_n,
        default=MAX_PULSE_N,
        metavar="N",
        help=f"the pulses' amplitude, N (at most {MAX_PULSE_N:g}, the default; the finger's force "
        "limit if lower)",
    )
    p.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="save the report here (default: the profile's recording.directory, else "
        "$STATE_DIRECTORY, $XDG_STATE_HOME/hapticd or ~/.local/state/hapticd)",
    )
    p.add_argument("--device", choices=registry.backend_names(), help="as hapticd run --device")
    p.add_argument("--emulate", action="store_true", help="as hapticd run --emulate")
    p.add_argument(
        "--unpaced",
        action="store_true",
        help="run the loop as fast as it can (simulated and emulated devices: tests)",
    )
    p.add_argument("--no-realtime", action="store_true", help="as hapticd run --no-realtime")


# -- the workspaces and the stiffness (hapticd check prints them too) ---------------------------


def _mm(v: Any) -> str:
    return "(" + ", ".join(f"{1e3 * float(c):.1f}" for c in v) + ") mm"


def reach_line(name: str, r: Reach, where: str) -> str:
    """One finger's (or the safety sphere's) workspace against the object, as text."""
    if not math.isfinite(r.workspace_radius_m):
        return (
            f"  {name}: {where}; its workspace is not known until the device is opened and "
            "identified (name its model in the device key 'model' to check it here)"
        )
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


def rendering_limits(profile: Any, devices: list[Any]) -> list[tuple[str, bool]]:
    """Per finger whose device model recommends a largest stiffness and damping
    (hapticd_drivers.models): the scene's stiffest surface and largest damping as the
    hand feels them (times the mount's workspace scale) against them: (line, within)."""
    scene = profile.scene
    surfaces = [("object", scene.object)] + [
        (name, s) for name in ("ground", "walls") if (s := getattr(scene, name)) is not None
    ]
    k_at, k = max(((n, s.stiffness_n_per_m) for n, s in surfaces), key=lambda x: x[1])
    c_at, c = max(((n, s.damping_n_s_per_m) for n, s in surfaces), key=lambda x: x[1])
    out = []
    for f, dev in zip(profile.fingers, devices, strict=True):
        info = dev.info
        k_max, c_max = info.max_stiffness_n_per_m, info.max_damping_n_s_per_m
        if not (math.isfinite(k_max) or math.isfinite(c_max)):
            continue
        scale = f.device.mount.workspace_scale
        ok = k * scale <= k_max and c * scale <= c_max
        out.append(
            (
                f"  {f.name}: the {info.model} renders at most {k_max:g} N/m and {c_max:g} "
                f"N s/m; the scene asks {k * scale:g} N/m ({k_at}) and {c * scale:g} N s/m "
                f"({c_at}): {'within' if ok else 'WARNING: above what the device renders stably'}",
                ok,
            )
        )
    return out


def workspace_report(profile: Any, devices: list[Any]) -> list[str]:
    """Per finger, how its device's workspace sphere (from the device description, placed
    by its mount) and the safety section's sphere meet the object at its starting pose."""
    lines = ["workspaces (the object at its starting pose):"]
    lines += [reach_line(*w) for w in workspace_reaches(profile, devices)]
    return lines


# -- output ------------------------------------------------------------------------------------


class Report:
    """What the bring-up prints, kept for the text file; and its findings for the JSON."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream
        self.lines: list[str] = []
        self.data: dict[str, Any] = {}
        self.failures: list[str] = []

    def say(self, text: str = "") -> None:
        print(text, file=self.stream, flush=True)
        self.lines.extend(text.split("\n"))

    def fail(self, why: str) -> None:
        self.failures.append(why)


def _v(v: Any, scale: float = 1.0, fmt: str = "{:+.1f}") -> str:
    return "(" + ", ".join(fmt.format(scale * float(c)) for c in v) + ")"


_AXES = (("+x", "-x"), ("+y", "-y"), ("up (+z)", "down (-z)"))


def towards(d: np.ndarray) -> str:
    """A unit vector in words: its main world axes, largest first (x, y, z; z up)."""
    order = sorted(range(3), key=lambda a: -abs(float(d[a])))
    parts = [_AXES[a][0 if d[a] > 0 else 1] for a in order if abs(float(d[a])) >= 0.2]
    return " and ".join(parts)


# -- the answers ------------------------------------------------------------------------------


class Answers:
    """The user's answers: scripted (``--answers``), else one line each from ``stdin``."""

    def __init__(self, scripted: str | None, stdin: IO[str], report: Report) -> None:
        self.left = list(scripted) if scripted is not None else None
        self.stdin = stdin
        self.report = report

    def ask(self, prompt: str) -> str:
        """'y', 'n' or 'r'; '' when there is none (the script ran out, end of input)."""
        if self.left is not None:
            ans = self.left.pop(0) if self.left else ""
            self.report.say(f"{prompt}{ans or '(no answer left)'} (scripted)")
            return ans
        for _ in range(5):
            print(prompt, end="", file=self.report.stream, flush=True)
            line = self.stdin.readline()
            if not line:
                self.report.say(f"{prompt}(end of input)")
                return ""
            ans = line.strip().lower()[:1]
            if ans in ("y", "n", "r"):
                self.report.lines.append(f"{prompt}{ans}")
                if not self.stdin.isatty():
                    print(ans, file=self.report.stream, flush=True)
                return ans
            print("  answer y, n or r", file=self.report.stream, flush=True)
        self.report.say(f"{prompt}(no valid answer)")
        return ""


# -- the loop's side ------------------------------------------------------------------------------


@dataclass
class StartPulse(Command):
    """Arm ``stage``'s pulse at this tick: ``amplitude_n`` N along ``direction`` (world) on
    ``finger``; the result is the pulse's first tick."""

    stage: PulseStage
    finger: int
    direction: np.ndarray
    amplitude_n: float

    while_stopping = False

    def apply(self, loop: ServoLoop, t: float) -> Any:
        k = round(t * loop.rate_hz)
        self.stage.start(k, self.finger, self.direction, self.amplitude_n)
        return k

    def describe(self) -> str:
        return f"pulse finger {self.finger} {self.amplitude_n:g} N {_v(self.direction)}"


# -- the steps --------------------------------------------------------------------------------


def _backend(args: argparse.Namespace, f: Any) -> str:
    return str(args.device or f.device.backend)


def check_devices(args: argparse.Namespace, session: Session, report: Report) -> bool:
    """Open each device, ask it whether it is calibrated, close it."""
    report.say("1. devices")
    rows = []
    ok = True
    for f, dev in zip(session.profile.fingers, session.devices, strict=True):
        row: dict[str, Any] = {"finger": f.name, "backend": _backend(args, f)}
        try:
            dev.open()
            try:
                cal = dev.calibrated() if hasattr(dev, "calibrated") else None
            finally:
                dev.close()
        except Exception as exc:
            row.update(found=False, problem=f"{type(exc).__name__}: {exc}")
            report.say(f"  {f.name}: {row['backend']}: NOT FOUND or not usable: {exc}")
            report.fail(f"{f.name}: device not usable: {exc}")
            rows.append(row)
            ok = False
            continue
        info = dev.info
        mass = getattr(dev, "effector_mass_kg", None)
        row.update(
            found=True,
            model=info.model,
            serial=info.serial,
            rated_force_n=info.max_force_n,
            workspace_radius_m=info.workspace_radius_m,
            calibrated=cal,
            effector_mass_kg=mass,
        )
        needs_cal = registry.backend(row["backend"]).calibrate is not None
        if not needs_cal:
            cal_text = "no calibration needed"
        elif cal is None:
            cal_text = "calibration UNKNOWN (the library cannot tell: use libdrd)"
        else:
            cal_text = "calibrated" if cal else "NOT CALIBRATED: run hapticd calibrate PROFILE"
        extra = ""
        if row["backend"] == "dhd":
            extra = (
                f", effector mass {mass:g} kg" if mass is not None else ", effector mass: SDK's"
            ) + " with gravity compensation"
        report.say(
            f"  {f.name}: {row['backend']} {info.model} {info.serial}: {cal_text}; rated "
            f"{info.max_force_n:g} N, workspace radius {1e3 * info.workspace_radius_m:.0f} mm"
            f"{extra}"
        )
        if needs_cal and not cal:
            ok = False
            report.fail(f"{f.name}: device {info.serial} is not known to be calibrated")
        rows.append(row)
    report.data["devices"] = rows
    report.say(f"  -> {'PASS' if ok else 'FAIL'}")
    return ok


def show_limits(session: Session, report: Report) -> bool:
    """The force limits, the safety chain's settings and where each workspace meets the object."""
    prof, safety = session.profile, session.safety
    sc = prof.safety
    names = prof.finger_names
    report.say("2. limits and workspace")
    report.say(
        "  force limit per finger (the smaller of the device's rated force and "
        "safety.max_force_n): "
        + ", ".join(f"{n} {lim:g} N" for n, lim in zip(names, safety.limits, strict=True))
    )
    dm = [f"{f.name} button {f.deadman.button}" for f in prof.fingers if f.deadman is not None]
    report.say(
        f"  safety: enable ramp {sc.ramp_s:g} s, stop ramp {sc.stop_ramp_s:g} s, rate limit "
        f"{'none' if not sc.max_force_rate_n_per_s else f'{sc.max_force_rate_n_per_s:g} N/s'}, "
        f"watchdog {'off' if not sc.watchdog_s else f'{1e3 * sc.watchdog_s:g} ms'}, "
        f"max device speed {sc.max_device_speed_m_per_s:g} m/s, deadman "
        f"{', '.join(dm) if dm else 'none'}"
    )
    for f, m in zip(prof.fingers, build_mounts(prof), strict=True):
        cfg = f.device.mount
        report.say(
            f"  {f.name} mount: position {_v(m.position, 1e3)} mm, roll/pitch/yaw "
            f"{_v(cfg.orientation_rpy_rad, 1.0, '{:+.4f}')} rad, workspace scale {m.scale:g}"
        )
    reaches = workspace_reaches(prof, session.devices)
    ok = True
    report.say("  " + workspace_report(prof, session.devices)[0])
    for name, r, where in reaches:
        report.say("  " + reach_line(name, r, where).replace("\n", "\n  "))
        if not r.reachable:
            ok = False
            report.fail(f"{name}: the object is out of reach of the workspace")
    for line, within in rendering_limits(prof, session.devices):
        report.say("  " + line)
        if not within:
            ok = False
            report.fail(line.strip())
    report.data["limits"] = {
        "force_limit_n": list(safety.limits),
        "safety": sc.model_dump(mode="json"),
        "mounts": [f.device.mount.model_dump(mode="json") for f in prof.fingers],
    }
    report.data["workspace"] = [
        {
            "name": name,
            "reachable": r.reachable,
            "contained": r.contained,
            "workspace_radius_m": r.workspace_radius_m,
            "nearest_m": r.nearest_m,
            "farthest_m": r.farthest_m,
            "object_center_device_m": r.center_device_m.tolist(),
        }
        for name, r, _ in reaches
    ]
    report.say(f"  -> {'PASS' if ok else 'FAIL'}")
    return ok


def positions(session: Session) -> list[dict[str, Any]]:
    """Each finger now: world, device-frame and object-frame positions (m), the gap from the
    fingertip to the nearest face plane of the object (m; negative: inside), buttons."""
    loop = session.loop
    frame = loop.frame
    obj = session.renderer.obj
    pos = frame.device_pos.copy()
    buttons = frame.buttons.tolist()
    out = []
    for i, (f, m) in enumerate(zip(session.profile.fingers, loop.bank.mounts, strict=True)):
        p = pos[i]
        out.append(
            {
                "finger": f.name,
                "world_m": p.tolist(),
                "device_m": m.point_to_device(p).tolist(),
                "object_m": ((p - obj.position) @ obj.rotation).tolist(),
                "gap_m": obj.polytope.signed_distance(p) - f.radius_m,
                "buttons": [b for b in range(32) if (int(buttons[i]) >> b) & 1],
            }
        )
    return out


def position_lines(rows: list[dict[str, Any]]) -> list[str]:
    width = max(len(r["finger"]) for r in rows)
    return [
        f"  {r['finger']:<{width}}  world {_v(r['world_m'], 1e3)}  device "
        f"{_v(r['device_m'], 1e3)}  object {_v(r['object_m'], 1e3)} mm  gap "
        f"{1e3 * r['gap_m']:+6.1f} mm  buttons {' '.join(map(str, r['buttons'])) or '-'}"
        for r in rows
    ]


def show_live(
    session: Session, report: Report, seconds: float, stdin: IO[str], enter_ends: bool
) -> None:
    """Positions refreshed for ``seconds`` s (or until Enter) on a terminal; one snapshot
    (the last) otherwise. The report keeps the last."""
    report.say(
        "3. positions (mm; world frame, device frame, object frame; gap: fingertip to the "
        "object's nearest face plane)"
    )
    stream = report.stream
    tty = stream.isatty()
    end = time.monotonic() + seconds
    drawn = 0
    while True:
        lines = position_lines(positions(session))
        if tty:
            if drawn:
                stream.write(f"\x1b[{drawn}F")
            stream.write("".join("\x1b[2K" + ln + "\n" for ln in lines))
            stream.flush()
            drawn = len(lines)
        left = end - time.monotonic()
        if left <= 0 or not session.loop.running:
            break
        if enter_ends:
            ready, _, _ = select.select([stdin], [], [], min(LIVE_REFRESH_S, left))
            if ready:
                stdin.readline()
                break
        else:
            time.sleep(min(LIVE_REFRESH_S, left))
    rows = positions(session)
    lines = position_lines(rows)
    if tty and drawn:
        stream.write(f"\x1b[{drawn}F" + "".join("\x1b[2K" + ln + "\n" for ln in lines))
        stream.flush()
        report.lines.extend(lines)
    else:
        report.say("\n".join(lines))
    report.data["positions"] = rows


def _wait(loop: ServoLoop, until: Any, timeout_s: float) -> bool:
    """Poll ``until()`` every 2 ms while the loop runs; False at the deadline or its end."""
    deadline = time.monotonic() + timeout_s
    while not until():
        if not loop.running or time.monotonic() >= deadline:
            return bool(until())
        time.sleep(0.002)
    return True


def pulse_once(
    session: Session, stage: PulseStage, i: int, d: np.ndarray, amp: float
) -> tuple[int, str | None]:
    """Run one pulse; (its first tick, a problem or None)."""
    loop = session.loop
    done = loop.submit(StartPulse(stage, i, d, amp))
    if not _wait(loop, done.is_set, START_TIMEOUT_S):
        return -1, "the loop did not take the pulse (it is not running)"
    if done.error is not None:
        return -1, done.error
    # Paced: the pulse's length; unpaced: far less. Margin for a loaded machine.
    timeout = stage.duration_s * (1.0 if loop.paced else 0.0) + START_TIMEOUT_S
    if not _wait(loop, lambda: stage.done, timeout):
        why = "the loop ended during the pulse" if not loop.running else "the pulse timed out"
        return int(done.result), why
    return int(done.result), None


def check_directions(
    session: Session, stage: PulseStage, report: Report, answers: Answers, amplitude: float
) -> bool:
    """Pulse every actuated direction of every finger; ask whether each was felt."""
    loop, prof, renderer = session.loop, session.profile, session.renderer
    report.say(
        f"4. force pulses: at most {amplitude:g} N, {stage.ramp_s:g} s smooth rise, "
        f"{stage.hold_s:g} s hold, {stage.ramp_s:g} s fall; through the safety chain"
    )
    # Forces ramp up after enabling (safety.ramp_s): the first pulse comes after it.
    ramp_ticks = math.ceil(prof.safety.ramp_s * loop.rate_hz) + 1
    _wait(loop, lambda: loop.stats.ticks > ramp_ticks, START_TIMEOUT_S + prof.safety.ramp_s)
    if not loop.running:
        report.say("  skipped: the loop ended")
        report.fail("the loop ended before the pulses")
        return False
    results = []
    ok = True
    for i, f in enumerate(prof.fingers):
        n_dir = len(f.actuated_directions)
        if n_dir == 0:
            report.say(f"  {f.name}: no actuated direction: nothing to check")
        amp = min(amplitude, loop.safety.limits[i])
        mount = loop.bank.mounts[i]
        for j in range(n_dir):
            pos = [tuple(map(float, p)) for p in loop.frame.device_pos.tolist()]
            d = np.array(renderer.actuation.world_directions(pos)[i][j], dtype=float)
            d /= np.linalg.norm(d)
            d_dev = mount.rotation.T @ d
            row: dict[str, Any] = {
                "finger": f.name,
                "direction": j,
                "world": d.tolist(),
                "device": d_dev.tolist(),
                "amplitude_n": amp,
                "answers": [],
            }
            hold = (
                f"; hold button {f.deadman.button} (deadman) down" if f.deadman is not None else ""
            )
            report.say(
                f"  {f.name}, direction {j + 1} of {n_dir}: {amp:g} N towards world "
                f"{towards(d)} {_v(d, 1.0, '{:+.2f}')}, device frame "
                f"{_v(d_dev, 1.0, '{:+.2f}')}{hold}"
            )
            verdict, why = "fail", "repeated without an answer"
            for _ in range(MAX_REPEATS + 1):
                start, problem = pulse_once(session, stage, i, d, amp)
                sent = stage.peak_sent_n[i]
                others = max((s for k, s in enumerate(stage.peak_sent_n) if k != i), default=0.0)
                row.update(start_tick=start, peak_sent_n=sent, peak_other_fingers_n=others)
                if problem is not None or loop.safety.fault is not None:
                    fault = loop.safety.fault
                    why = problem or f"fault: {fault.cause if fault else ''}"
                    break
                report.say(f"    sent: peak {sent:.3f} N (other fingers {others:.3f} N)")
                if sent < MIN_SENT_SHARE * amp:
                    why = (
                        f"the safety chain let at most {sent:.3f} N of {amp:g} N through "
                        "(a deadman up, a rate limit?)"
                    )
                    break
                ans = answers.ask("    felt in that direction? [y/n/r] ")
                row["answers"].append(ans)
                if ans == "r":
                    continue
                if ans == "y":
                    verdict, why = "pass", ""
                else:
                    why = "not felt in that direction" if ans == "n" else "no answer"
                break
            row.update(result=verdict, why=why)
            results.append(row)
            report.say(f"    -> {verdict.upper()}{': ' + why if why else ''}")
            if verdict != "pass":
                ok = False
                report.fail(f"{f.name} direction {j + 1}: {why}")
            if loop.safety.fault is not None or not loop.running:
                report.data["pulses"] = results
                return False
    report.data["pulses"] = results
    return ok


# -- the command --------------------------------------------------------------------------------


def _save(report: Report, profile: Any, where: Path, stamp: datetime.datetime) -> list[Path]:
    where.mkdir(parents=True, exist_ok=True)
    base = where / f"bringup-{profile.name}-{stamp.strftime('%Y%m%d-%H%M%S')}"
    paths = [base.with_suffix(".json"), base.with_suffix(".txt")]
    paths[0].write_text(json.dumps(report.data, indent=2) + "\n")
    paths[1].write_text("\n".join(report.lines) + "\n")
    return paths


def bringup(args: argparse.Namespace, stdin: IO[str] | None = None) -> Outcome:
    """Run the bring-up check (``args`` as add_arguments and ``--set`` parse them)."""
    stdin = stdin if stdin is not None else sys.stdin
    report = Report(sys.stdout)
    try:
        profile = load_profile(args.profile, list(args.set or []))
        session = build_session(
            profile,
            paced=not args.unpaced,
            device=args.device,
            emulate=args.emulate,
        )
    except (ProfileError, BackendUnavailableError, RecordingError) as exc:
        print(f"hapticd: {exc}", file=sys.stderr)
        return Outcome.BAD_INPUT
    stamp = datetime.datetime.now(datetime.UTC).replace(microsecond=0)
    loop = session.loop
    loop.duration_s = None  # ended by the bring-up (an emulated run would end with its path)
    loop.end_with_trajectory = False
    if args.no_realtime:
        loop.realtime_settings = None
    # The object stays where the subject will find it; only the pulses leave the renderer.
    session.renderer.obj.fixed = True
    session.renderer.plan()
    stage = PulseStage(len(profile.fingers), loop.period, PULSE_RAMP_S, PULSE_HOLD_S)
    session.renderer.set_output(stage)
    report.data.update(
        hapticd=__version__,
        profile=str(args.profile),
        profile_name=profile.name,
        date_utc=stamp.isoformat(),
        rate_hz=loop.rate_hz,
        paced=loop.paced,
    )
    report.say(
        f"hapticd bringup {args.profile}: profile {profile.name!r}, {loop.rate_hz:g} Hz"
        f"{'' if loop.paced else ' (unpaced)'}, {len(profile.fingers)} fingers, "
        f"{stamp.strftime('%Y-%m-%d %H:%M:%S')} UTC"
    )
    devices_ok = check_devices(args, session, report)
    limits_ok = show_limits(session, report)
    answers = Answers(args.answers, stdin, report)
    pulses_ok = False
    out: dict[str, Any] = {}
    if devices_ok:
        # SIGTERM ends a bring-up as Ctrl-C does: forces to zero, the report saved.
        old_term = None
        if threading.current_thread() is threading.main_thread():
            old_term = signal.signal(signal.SIGTERM, _interrupt)
        runner = threading.Thread(
            target=lambda: out.update(summary=session.run()), name="hapticd-bringup-loop"
        )
        runner.start()
        try:
            deadline = time.monotonic() + START_TIMEOUT_S
            while loop.stats.ticks == 0 and runner.is_alive() and time.monotonic() < deadline:
                time.sleep(0.002)
            if loop.stats.ticks == 0 and loop.safety.fault is None:
                report.fail(f"the loop did not start within {START_TIMEOUT_S:g} s")
            elif loop.safety.fault is None:
                enter = args.answers is None and stdin.isatty() and args.live_s > 0
                if enter:
                    report.say(f"  (live for {args.live_s:g} s; Enter goes on)")
                show_live(session, report, args.live_s, stdin, enter)
                pulses_ok = check_directions(session, stage, report, answers, args.pulse_n)
                if answers.left:
                    report.say(f"  ({len(answers.left)} scripted answer(s) left unused)")
        except KeyboardInterrupt:
            report.fail("interrupted")
            loop.request_stop("bring-up interrupted", ramp=False)
        finally:
            loop.request_stop("bring-up done")
            runner.join(STOP_TIMEOUT_S + session.profile.safety.stop_ramp_s)
            if runner.is_alive():
                loop.request_stop("bring-up done", ramp=False)
                runner.join(STOP_TIMEOUT_S)
            if old_term is not None:
                signal.signal(signal.SIGTERM, old_term)
    else:
        report.say("3. positions and 4. force pulses: skipped (the devices failed)")
        _close_unused(session.devices)
    fault = loop.safety.fault
    if fault is not None:
        report.say(f"FAULT at tick {fault.tick} (t = {fault.t:.3f} s): {fault.cause}")
        report.fail(f"fault: {fault.cause}")
        report.data["fault"] = {"tick": fault.tick, "t": fault.t, "cause": fault.cause}
    elif devices_ok and not out.get("summary"):
        report.fail("the loop did not end")
    passed = devices_ok and limits_ok and pulses_ok and not report.failures
    report.data.update(passed=passed, failures=report.failures)
    if passed:
        n = len(report.data.get("pulses", []))
        report.say(f"RESULT: PASS (devices, limits and workspace, {n} of {n} directions)")
    else:
        report.say("RESULT: FAIL")
        for why in report.failures:
            report.say(f"  - {why}")
    where = args.out if args.out is not None else record_directory(profile)
    try:
        paths = _save(report, profile, Path(where), stamp)
    except OSError as exc:
        print(f"hapticd: cannot save the bring-up report in {where}: {exc}", file=sys.stderr)
        return Outcome.FAIL
    print(f"saved: {paths[0]} and {paths[1].name}", file=report.stream, flush=True)
    if fault is not None:
        return Outcome.FAULT
    return Outcome.PASS if passed else Outcome.FAIL


def _interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


def _close_unused(devices: list[Device]) -> None:
    """The devices were only created (the check closed what it opened): nothing to zero,
    but a device that kept something open is closed, never raising."""
    for dev in devices:
        with contextlib.suppress(Exception):
            dev.close()
