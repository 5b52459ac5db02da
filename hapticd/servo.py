"""The fixed-rate servo loop: read devices, render, make safe, write forces, record.

Ticks run on a grid of absolute deadlines on the monotonic clock (no drift),
waiting by sleeping to just before the deadline and spinning the rest. Each
tick k has the nominal time t = k / rate_hz (s); devices that play a
trajectory take their time from ``ServoLoop.now``, so a paced run and an
unpaced run (no waiting: as fast as possible on the nominal clock) compute the
same forces. Garbage collection is frozen and disabled while the loop runs.

Every way out of the loop (end of trajectory, duration, stop request, an
exception or device error) writes zero force to every device, disables
forces and closes the devices.
"""

from __future__ import annotations

import collections
import contextlib
import gc
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from hapticd_drivers import Device, DeviceError, DeviceState

from hapticd import realtime
from hapticd.allocation import METHODS
from hapticd.recording import Recorder
from hapticd.render import Renderer
from hapticd.safety import SafetyChain
from hapticd.stats import LogHistogram

log = logging.getLogger("hapticd.servo")

OVERRUN_FACTOR = 1.1
# Sleep until this long before a deadline, then spin: measured in docs/notes.
SPIN_MARGIN_S = 200e-6
# If the loop falls this many periods behind, it re-anchors instead of bursting.
REANCHOR_PERIODS = 10
# How often a lost device is looked for again (reconnect mode), s of loop time.
RECONNECT_PERIOD_S = 0.5


@dataclass
class LoopStats:
    """Timing and force statistics gathered while the loop runs."""

    period_error: LogHistogram = field(default_factory=LogHistogram)
    compute: LogHistogram = field(default_factory=LogHistogram)
    ticks: int = 0
    overruns: int = 0
    reanchors: int = 0
    first_start: float = 0.0
    last_start: float = 0.0
    max_force: list[float] = field(default_factory=list)
    contact_ticks: list[int] = field(default_factory=list)


def _wait_until(deadline: float, margin: float) -> None:
    remaining = deadline - time.monotonic()
    if remaining > margin:
        time.sleep(remaining - margin)
    while time.monotonic() < deadline:
        pass


class Applied(threading.Event):
    """Set when the loop has applied a submitted change: at ``tick``, or failed with ``error``."""

    def __init__(self) -> None:
        super().__init__()
        self.tick = -1
        self.error: str | None = None
        self.result: Any = None


class ServoLoop:
    """Runs the rendering pipeline on ``devices`` at ``rate_hz``."""

    def __init__(
        self,
        devices: Sequence[Device],
        renderer: Renderer,
        safety: SafetyChain,
        rate_hz: float,
        *,
        paced: bool = True,
        duration_s: float | None = None,
        recorder: Recorder | None = None,
        object_pos: Callable[[], np.ndarray] | None = None,
        reconnect: bool = False,
        max_consecutive_overruns: int = 0,
        stop_ramp_s: float = 0.0,
        realtime_settings: realtime.RealtimeSettings | None = None,
        switch_interval_s: float | None = None,
    ) -> None:
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self.devices = list(devices)
        self.renderer = renderer
        self.safety = safety
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.paced = paced
        self.duration_s = duration_s
        self.recorder = recorder
        # Read through self: a profile reload swaps the renderer.
        self._object_pos = object_pos or (lambda: self.renderer.obj.center)
        F = len(self.devices)
        self._states = [DeviceState() for _ in range(F)]
        self.device_pos = np.zeros((F, 3))
        self.device_vel = np.zeros((F, 3))
        self._t = 0.0
        self._stop_reason: str | None = None
        self._stop_now = False
        self._stopping_at: float | None = None
        self.stop_ramp_s = float(stop_ramp_s)
        self.realtime_settings = realtime_settings
        # Python's GIL switch interval while the loop runs: how long the loop can wait for
        # the GIL when another thread (the control server) holds it (docs/daemon.md).
        self.switch_interval_s = switch_interval_s
        self.rt_report: realtime.RealtimeReport | None = None
        # Counts applied control changes; recorded every tick, so a change is findable.
        self.control_seq = 0
        # The sleep gate: a byte per tick, written just before the loop sleeps (-1: off).
        self._gate_w = -1
        self.sleep_until = 0.0
        self.running = False
        self.end_reason = ""
        self.stats = LoopStats(max_force=[0.0] * F, contact_ticks=[0] * F)
        # Reconnect mode: a device error latches a fault but the loop goes on, looking for
        # the device again; forces stay off until the fault is reset.
        self.reconnect = reconnect
        # Sustained lateness (a loop that cannot keep its rate) latches a fault; 0: off.
        self.max_consecutive_overruns = max_consecutive_overruns if paced else 0
        self._lost: list[float | None] = [None] * F
        self._n_lost = 0
        self.events: list[tuple[float, str]] = []
        # Changes from the control thread, applied at tick boundaries (deque: thread-safe ends).
        self._inbox: collections.deque[tuple[dict[str, Any], Applied]] = collections.deque()

    def open_sleep_gate(self) -> int:
        """A pipe the loop writes a byte to just before each sleep; returns its read end.

        Another thread that waits on it (without the GIL) and then works until
        ``sleep_until`` (monotonic s) never makes the loop wait for the GIL.
        """
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.set_blocking(w, False)
        self._gate_w = w
        return r

    def close_sleep_gate(self) -> None:
        w, self._gate_w = self._gate_w, -1
        if w >= 0:
            os.close(w)

    def submit(self, action: dict[str, Any]) -> Applied:
        """Queue a change (from another thread); the loop applies it at its next tick start."""
        done = Applied()
        self._inbox.append((action, done))
        return done

    def _apply_inbox(self, k: int, t: float) -> None:
        while self._inbox:
            action, done = self._inbox.popleft()
            try:
                done.result = self._apply(action, t)
                self.control_seq += 1
                what = " ".join(
                    str(action[x]) for x in ("cmd", "param", "value") if action.get(x) is not None
                )
                # Recorded only: forces are live here, so the control thread does the logging.
                self._event(t, f"control: {what}", log_now=False)
            except ValueError as exc:
                done.error = str(exc)
            except Exception as exc:
                done.error = f"{type(exc).__name__}: {exc}"
            done.tick = k
            done.set()

    def _apply(self, action: dict[str, Any], t: float) -> Any:
        """Make one control change; raise (changing nothing) if it cannot be made."""
        cmd = action["cmd"]
        if self._stop_reason is not None and cmd in ("enable", "reload"):
            # Either would restart the force ramp and undo the stop's ramp to zero.
            raise ValueError(f"the daemon is stopping ({self._stop_reason})")
        if cmd == "set":
            param, value = action["param"], action["value"]
            if param == "force_limit_n":
                self.safety.set_limits(
                    [min(d.info.max_force_n, float(value)) for d in self.devices]
                )
            else:
                self.renderer.update(**{param: value})
        elif cmd == "enable":
            self.safety.reset(t)
            for dev in self.devices:
                dev.enable_forces(True)
        elif cmd == "disable":
            for dev in self.devices:
                dev.enable_forces(False)
        elif cmd == "record_start":
            if self.recorder is not None:
                raise ValueError(f"already recording to {self.recorder.path}; stop it first")
            self.recorder = action["recorder"]
        elif cmd == "record_stop":
            if self.recorder is None:
                raise ValueError("not recording")
            old, self.recorder = self.recorder, None
            return old
        elif cmd == "reload":
            renderer, safety = action["renderer"], action["safety"]
            if self.recorder is not None and renderer.lam_a.shape != self.renderer.lam_a.shape:
                raise ValueError(
                    "the new profile changes the number of actuated directions, which would "
                    f"change the layout of the recording {self.recorder.path}; stop recording first"
                )
            old = self.safety
            if old.fault is not None:
                safety.fault = old.fault  # a reload never clears a fault: enable does
            safety.clamped_ticks += old.clamped_ticks
            safety.rate_limited_ticks += old.rate_limited_ticks
            safety.start(t)  # forces ramp up again in the new scene; proxies start anew
            self.renderer, self.safety = renderer, safety
        else:
            raise ValueError(f"the loop cannot apply {cmd!r}")
        return None

    def get_param(self, name: str) -> Any:
        r = self.renderer
        m = r.obj.material
        return {
            "stiffness_n_per_m": m.stiffness,
            "damping_n_s_per_m": m.damping,
            "friction": [m.mu_static, m.mu_dynamic],
            "mass_kg": r.obj.mass,
            "allocator": r.allocator,
            "force_limit_n": list(self.safety.limits),
            "actuated_directions": [[list(d) for d in ds] for ds in r.actuation.local],
        }[name]

    def scene_status(self) -> dict[str, Any]:
        r = self.renderer
        m = r.obj.material
        return {
            "shape": type(r.obj.shape).__name__,
            "fixed": r.obj.fixed,
            "mass_kg": r.obj.mass,
            "stiffness_n_per_m": m.stiffness,
            "damping_n_s_per_m": m.damping,
            "friction": [m.mu_static, m.mu_dynamic],
            "position_m": [float(v) for v in r.obj.center],
        }

    def telemetry(self) -> dict[str, Any]:
        """A sample of the live state for watchers (read from another thread: it may mix
        two adjacent ticks; the recording is the exact record). Forces in N, positions m."""
        r = self.renderer
        return {
            "tick": self.stats.ticks,
            "t": self._t,
            "fault": self.safety.fault is not None,
            "device_pos": self.device_pos.tolist(),
            "proxy_pos": r.proxy_pos.tolist(),
            "in_contact": r.in_contact.tolist(),
            "force": self.safety.output.tolist(),
            "object_pos": [float(v) for v in r.obj.center],
            "allocator": r.allocator,
            "overruns": self.stats.overruns,
        }

    def status(self) -> dict[str, Any]:
        """A snapshot for the control API (read from another thread: plain values only)."""
        st = self.stats
        fault = self.safety.fault
        return {
            "tick": st.ticks,
            "t": self._t,
            "rate_hz": self.rate_hz,
            "paced": self.paced,
            "overruns": st.overruns,
            "period_error_us": {
                "p50": st.period_error.percentile(50) * 1e6 if st.period_error.count else None,
                "p99": st.period_error.percentile(99) * 1e6 if st.period_error.count else None,
                "max": st.period_error.max * 1e6,
            },
            "fault": None
            if fault is None
            else {"tick": fault.tick, "t": fault.t, "cause": fault.cause},
            "devices": [
                {
                    "serial": d.info.serial,
                    "connected": self._lost[i] is None,
                    "force_limit_n": self.safety.limits[i],
                }
                for i, d in enumerate(self.devices)
            ],
            "allocator": self.renderer.allocator,
            "stages": self.renderer.stages,
            "scene": self.scene_status(),
            "control_seq": self.control_seq,
            "recording": None if self.recorder is None else self.recorder.status(),
            "realtime": None if self.rt_report is None else self.rt_report.to_json(),
            "stopping": self._stop_reason,
        }

    def now(self) -> float:
        """Nominal time of the current tick, s (the clock of trajectory devices)."""
        return self._t

    def request_stop(self, reason: str = "stop requested", *, ramp: bool = True) -> None:
        """Ask the loop to stop (safe from a signal handler and from other threads).

        With ``ramp`` forces first fall to zero over ``stop_ramp_s``; a second request, or
        ``ramp=False``, stops after the current tick.
        """
        if self._stop_reason is None:
            self._stop_reason = reason
            self._stop_now = not ramp
        else:
            self._stop_now = True

    def _tick(self, k: int, t: float) -> None:
        if self._inbox:
            self._apply_inbox(k, t)
        pos, vel = self.device_pos, self.device_vel
        lost = self._lost
        for i, dev in enumerate(self.devices):
            if lost[i] is not None:
                continue  # disconnected: keep its last position, at rest
            st = self._states[i]
            try:
                dev.read_state(st)
            except DeviceError as exc:
                self._lose(i, k, t, exc)
                continue
            pos[i] = st.position
            vel[i] = st.velocity
        self.renderer.step(pos, vel)
        out = self.safety.apply(self.renderer.rendered_force, k, t, pos, time.monotonic())
        for i, dev in enumerate(self.devices):
            if lost[i] is None:
                try:
                    dev.write_force(out[i])
                except DeviceError as exc:
                    self._lose(i, k, t, exc)
        if self._n_lost:
            self._try_reconnect(t)

    def _lose(self, i: int, k: int, t: float, exc: DeviceError) -> None:
        """A device failed: latch the fault and zero every force; without reconnect, stop."""
        if not self.reconnect:
            raise exc
        self.safety.trip(k, t, f"{type(exc).__name__}: {exc}")
        self._zero_all()
        dev = self.devices[i]
        with contextlib.suppress(Exception):
            dev.close()
        self._lost[i] = t
        self._n_lost += 1
        self.device_vel[i] = 0.0
        self._event(t, f"device {dev.info.serial} lost: {exc}")

    def _try_reconnect(self, t: float) -> None:
        for i, since in enumerate(self._lost):
            if since is None or t - since < RECONNECT_PERIOD_S:
                continue
            dev = self.devices[i]
            try:
                dev.open()
                dev.enable_forces(False)  # forces stay off until someone re-enables them
            except Exception:
                self._lost[i] = t  # still gone: try again later
                continue
            self._lost[i] = None
            self._n_lost -= 1
            self._event(t, f"device {dev.info.serial} reconnected; forces stay off")

    def _event(self, t: float, what: str, log_now: bool = True) -> None:
        self.events.append((t, what))
        if log_now:
            # Device losses and reconnections: rare, and the forces are already zero.
            log.warning("t = %.3f s: %s", t, what)

    def _record(self, rec: Recorder, t: float, t_wall: float, compute: float) -> None:
        r = self.renderer
        rec.append(
            (
                t,
                t_wall,
                compute,
                self.device_pos,
                self.device_vel,
                r.proxy_pos,
                r.in_contact,
                r.contact_force,
                r.rendered_force,
                self.safety.output,
                r.lam_a,
                r.accuracy[0],
                r.accuracy[1],
                r.accuracy[2],
                r.accuracy[3],
                r.alpha,
                r.env_force,
                self._object_pos(),
                r.obj.rotation,
                self.safety.latched,
                self.control_seq,
                r.obj.material.stiffness,
                r.obj.mass,
                METHODS.index(r.allocator),
            )
        )

    def _zero_all(self) -> list[str]:
        """Command zero force and disable every device; return the errors met."""
        errors: list[str] = []
        zero = np.zeros(3)
        for dev in self.devices:
            for action in (lambda d=dev: d.write_force(zero), lambda d=dev: d.enable_forces(False)):
                try:
                    action()
                except Exception as exc:
                    errors.append(f"{dev.info.serial}: {exc}")
        return errors

    def _log_fault(self) -> None:
        f = self.safety.fault
        if f is not None:
            log.error(
                "fault latched at tick %d (t = %.3f s), forces zeroed: %s", f.tick, f.t, f.cause
            )

    def _finished(self, k: int) -> str | None:
        if self._stop_reason is not None:
            if self._stop_now or self.safety.fault is not None or self.stop_ramp_s <= 0:
                return self._stop_reason
            t = k * self.period
            if self._stopping_at is None:
                # Ramp forces to zero before the devices are disabled (no jolt on stop).
                self._stopping_at = t
                self.safety.ramp_down(t + self.period, self.stop_ramp_s)
            return self._stop_reason if self.safety.ramped_down(t) else None
        if self.duration_s is not None and (k + 1) * self.period >= self.duration_s - 1e-12:
            return "duration reached"
        if self.devices and all(d.finished for d in self.devices):
            return "trajectory ended"
        return None

    def run(self) -> LoopStats:
        """Open and enable the devices, run until a stop condition, then zero and close."""
        opened: list[Device] = []
        try:
            for dev in self.devices:
                dev.open()
                opened.append(dev)
            for dev in self.devices:
                dev.enable_forces(True)
            self.safety.start(0.0)
        except Exception as exc:
            self.safety.trip(0, 0.0, f"device setup failed: {exc}")
            self.end_reason = "fault"
            self._zero_all()
            for dev in opened:
                dev.close()
            return self.stats
        if self.realtime_settings is not None:
            try:
                self.rt_report = realtime.apply(self.realtime_settings)
            except realtime.RealtimeError as exc:
                self.safety.trip(0, 0.0, str(exc))
                self.end_reason = "fault"
                self._log_fault()
                self._zero_all()
                for dev in self.devices:
                    dev.close()
                return self.stats
            for problem in self.rt_report.problems:
                log.warning("real time: %s", problem)
        gc.collect()
        gc.freeze()
        gc_was_enabled = gc.isenabled()
        gc.disable()
        old_switch = sys.getswitchinterval()
        if self.switch_interval_s is not None and self.paced:
            sys.setswitchinterval(self.switch_interval_s)
        self.running = True
        try:
            self._loop()
        finally:
            self.running = False
            sys.setswitchinterval(old_switch)
            if self.rt_report is not None:
                realtime.restore(self.rt_report)  # shutdown work runs at normal priority
            errors = self._zero_all()
            for dev in self.devices:
                try:
                    dev.close()
                except Exception as exc:
                    errors.append(f"{dev.info.serial}: close: {exc}")
            if errors and self.safety.fault is None:
                self.safety.trip(self.stats.ticks, self._t, "shutdown: " + "; ".join(errors))
            if gc_was_enabled:
                gc.enable()
            gc.unfreeze()
        return self.stats

    def _loop(self) -> None:
        T = self.period
        st = self.stats
        margin = min(SPIN_MARGIN_S, 0.5 * T)
        paced = self.paced
        F = len(self.devices)
        t0 = time.monotonic() + (2e-3 if paced else 0.0)
        prev = 0.0
        k = 0
        late = 0
        while True:
            t = k * T
            self._t = t
            deadline = t0 + t
            if paced:
                if self._gate_w >= 0:
                    # Tell the control thread the loop is about to sleep: its window to take
                    # the GIL without making the loop wait for it (docs/daemon.md).
                    self.sleep_until = deadline - margin
                    try:  # noqa: SIM105 - suppress() would allocate every tick
                        os.write(self._gate_w, b"\0")
                    except BlockingIOError:
                        pass  # nobody is waiting; the pipe is full of old news
                _wait_until(deadline, margin)
            start = time.monotonic()
            if k == 0:
                st.first_start = start
            else:
                period = start - prev
                st.period_error.add(abs(period - T))
                if period > OVERRUN_FACTOR * T:
                    st.overruns += 1
                    late += 1
                    if late == self.max_consecutive_overruns:
                        cause = f"overrun: {late} consecutive ticks longer than {OVERRUN_FACTOR:g}x"
                        self.safety.trip(k, t, cause + " the period")
                        self._log_fault()
                else:
                    late = 0
            prev = start
            latched = self.safety.fault is not None
            try:
                self._tick(k, t)
            except Exception as exc:
                self.safety.trip(k, t, f"{type(exc).__name__}: {exc}")
                self.end_reason = "fault"
                st.ticks = k + 1
                st.last_start = start
                self._log_fault()
                return
            # Read after the tick: a control change at its start may have swapped these.
            safety, renderer = self.safety, self.renderer
            if not latched and safety.fault is not None:
                self._log_fault()
            out = safety.output
            for i in range(F):
                f = out[i]
                mag = math.hypot(f[0], f[1], f[2])
                if mag > st.max_force[i]:
                    st.max_force[i] = mag
                if renderer.in_contact[i]:
                    st.contact_ticks[i] += 1
            compute = time.monotonic() - start
            st.compute.add(compute)
            rec = self.recorder
            if rec is not None:
                self._record(rec, t, start - t0, compute)
            st.ticks = k + 1
            st.last_start = start
            reason = self._finished(k)
            if reason is not None:
                self.end_reason = reason
                return
            k += 1
            if paced and time.monotonic() - (t0 + k * T) > REANCHOR_PERIODS * T:
                t0 = time.monotonic() - k * T
                st.reanchors += 1


def summarize(loop: ServoLoop, allocator: str, finger_names: Sequence[str]) -> dict[str, Any]:
    """The run summary (see docs/recording.md): timing in us, forces in N."""
    st = loop.stats
    span = st.last_start - st.first_start
    achieved = (st.ticks - 1) / span if st.ticks > 1 and span > 0 else float("nan")

    def us(h: LogHistogram, q: float | None) -> float | None:
        if h.count == 0:
            return None
        v = h.max if q is None else h.percentile(q)
        return round(v * 1e6, 3)

    pe = st.period_error if loop.paced else LogHistogram()
    fault = loop.safety.fault
    return {
        "ticks": st.ticks,
        "duration_s": round(st.ticks * loop.period, 6),
        "paced": loop.paced,
        "rate_hz": {"target": loop.rate_hz, "achieved": round(achieved, 3)},
        "period_error_us": {
            "p50": us(pe, 50),
            "p99": us(pe, 99),
            "p99.9": us(pe, 99.9),
            "max": us(pe, None),
        },
        "period_error_hist_us": [[round(e * 1e6, 4), c] for e, c in pe.nonzero()],
        "overruns": st.overruns if loop.paced else 0,
        "overruns_per_10k": round(1e4 * st.overruns / max(st.ticks - 1, 1), 3) if loop.paced else 0,
        "reanchors": st.reanchors,
        "tick_compute_us": {
            "p50": us(st.compute, 50),
            "p99": us(st.compute, 99),
            "p99.9": us(st.compute, 99.9),
            "max": us(st.compute, None),
        },
        "allocator": allocator,
        "max_rendered_force_n": round(max(st.max_force, default=0.0), 6),
        "fingers": {
            name: {"max_force_n": round(st.max_force[i], 6), "contact_ticks": st.contact_ticks[i]}
            for i, name in enumerate(finger_names)
        },
        "clamped_ticks": loop.safety.clamped_ticks,
        "rate_limited_ticks": loop.safety.rate_limited_ticks,
        "end_reason": loop.end_reason,
        "events": [{"t": round(t, 6), "event": e} for t, e in loop.events],
        "fault": None
        if fault is None
        else {"tick": fault.tick, "t": fault.t, "cause": fault.cause},
    }
