"""The fixed-rate servo loop: read, render, make safe, write, record; then wait for the next tick.

Each tick k runs on one frame (hapticd.physics.frame) at nominal time t = k / rate_hz
(s): the device bank reads the devices into it, the renderer's stages and the
safety chain fill it, the bank writes its forces, and the recorder copies it.
Pacing (deadlines, sleep gate, overruns) is ``hapticd.loop.pacing``; control
changes are typed commands (hapticd.loop.commands) applied at a tick boundary.
Devices that play a trajectory take their time from ``ServoLoop.now``, so a
paced run and an unpaced run (no waiting: as fast as possible on the nominal
clock) compute the same forces. Garbage collection is frozen and disabled
while the loop runs.

Every way out of the loop (end of trajectory, duration, stop request, an
exception or device error) writes zero force to every device, disables
forces and closes the devices, before anything else.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import gc
import logging
import math
import operator
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from hapticd_drivers import Device, DeviceError

from hapticd.events import CAUSE_CODES, CODES
from hapticd.loop import realtime
from hapticd.loop.commands import Command
from hapticd.loop.device_bank import MAX_DEVICE_DISTANCE_M, DeviceBank
from hapticd.loop.event_ring import DEFAULT_CAPACITY, EventRing, FrameEvents
from hapticd.loop.pacing import SPIN_MARGIN_S, LoopStats, Pacer
from hapticd.params import PARAMS, ParamError
from hapticd.physics import kernels
from hapticd.physics.frame import Frame, item_view
from hapticd.physics.live import Change
from hapticd.physics.render import SAMPLES_REFUSED, Renderer
from hapticd.physics.safety import SafetyChain
from hapticd.recording import Recorder
from hapticd.recording.ring import clock_anchor

log = logging.getLogger("hapticd.loop.servo")

FAULT_LATCHED = CODES["fault_latched"]
TRAJECTORY_END = CODES["trajectory_end"]
RECORDING_STARTED = CODES["recording_started"]
OTHER_CAUSE = CAUSE_CODES["other"]
TRAJECTORY_ENDED = "trajectory ended"
SAMPLES, CHANGED = kernels.LOOP_SAMPLES, kernels.LOOP_CHANGED
# hapticd.physics.kernels.MAX_OBJECT_*: a free object beyond them has diverged.
MAX_OBJECT_DISTANCE_M = kernels.MAX_OBJECT_DISTANCE_M
MAX_OBJECT_SPEED_M_PER_S = kernels.MAX_OBJECT_SPEED_M_PER_S
MAX_OBJECT_SPIN_RAD_PER_S = kernels.MAX_OBJECT_SPIN_RAD_PER_S


class Applied:
    """Set when the loop has applied a submitted command: at ``tick``, or failed with ``error``.

    An event's ``set``, ``is_set`` and ``wait``, on a lock held until it is set: the loop's
    ``set`` is one lock release (a C call), not a condition's notify under its lock (about
    1 us of the tick that applies a command)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()
        self._set = False
        self.tick = -1
        self.error: str | None = None
        self.result: Any = None
        # The command, kept: what it prepared (and what it replaced) is freed with this, in
        # the submitter's thread, not on the servo thread.
        self.command: Command | None = None

    def set(self) -> None:
        """Mark it applied (the loop's side), waking every waiter."""
        if not self._set:
            self._set = True
            self._lock.release()

    def is_set(self) -> bool:
        return self._set

    def wait(self, timeout: float | None = None) -> bool:
        """Whether it is set, waiting up to ``timeout`` s (None: for as long as it takes)."""
        if self._set:
            return True
        if self._lock.acquire(timeout=-1 if timeout is None else max(timeout, 0.0)):
            self._lock.release()  # the next waiter's turn
        return self._set


class TickClock:
    """The nominal time of a servo loop's current tick (s), for the devices that play a
    trajectory, made before the loop that keeps it (``ServoLoop(..., clock=it)``): a
    device reads ``now()``, a callable of no arguments that runs no Python code (a
    device reads it every tick), the loop stores each tick's time in ``cell[0]``."""

    def __init__(self) -> None:
        self.cell = [0.0]
        self.now: Callable[[], float] = functools.partial(operator.getitem, self.cell, 0)


class ServoLoop:
    """Runs ``renderer`` and ``safety`` on ``devices`` at ``rate_hz``; ``clock``: the
    devices' clock, which the loop keeps at each tick's nominal time (None: its own)."""

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
        reconnect: bool = False,
        max_consecutive_overruns: int = 0,
        stop_ramp_s: float = 0.0,
        realtime_settings: realtime.RealtimeSettings | None = None,
        switch_interval_s: float | None = None,
        spin_s: float = SPIN_MARGIN_S,
        event_capacity: int = DEFAULT_CAPACITY,
        wall_watchdog: bool = True,
        clock: TickClock | None = None,
    ) -> None:
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self.renderer = renderer
        self.safety = safety
        self.pacer = Pacer(rate_hz, paced, max_consecutive_overruns, spin_s)
        self.rate_hz = self.pacer.rate_hz
        self.period = self.pacer.period
        self.paced = paced
        self.forces_off = False  # the devices' forces were turned off for a latched fault
        # The safety watchdog times the gap between ticks on the wall clock. An unpaced run
        # whose devices all follow the loop's nominal clock (replay, sim, emulated) is a
        # simulation: a machine pausing it endangers no one, so it feeds no watchdog.
        self.wall_watchdog = wall_watchdog
        # The clock that watchdog reads (s): the monotonic one; a test's own to stall a tick.
        self.watchdog_clock: Callable[[], float] = time.monotonic
        self.duration_s = duration_s
        # Whether the run ends when every device's trajectory has (a bring-up goes on).
        self.end_with_trajectory = True
        self.recorder = recorder
        # A second ring of every tick's record, for a consumer other than the recording (the
        # LSL outlet, hapticd.daemon.lsl); attached before the run, it stays to the end.
        self.tap: Recorder | None = None
        # Tick 0's due time on the LSL clock and in UTC, s (ring.clock_anchor), from the start.
        self.anchor: tuple[float, float] | None = None
        F = len(devices)
        self.frame = Frame(F, renderer.actuation.n_actuators)
        self._bind_scalars(self.frame)
        self.bank = DeviceBank(
            devices,
            reconnect=reconnect,
            on_fault=self._trip,
            on_event=self._event,
            max_speed_m_per_s=safety.params.max_device_speed_m_per_s,
        )
        self.stats: LoopStats = self.pacer.stats
        self.stats.max_force = [0.0] * F
        self.stats.contact_ticks = [0] * F
        self._loop_of: Renderer | None = None  # the renderer whose loop block is bound
        self._speed_of = math.inf
        self._loop_block = memoryview(np.zeros(kernels.LOOP_HEAD))
        self.clock = clock if clock is not None else TickClock()
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
        # Prepared changes found stale at their tick (prepared again there, on the loop).
        self.stale_changes = 0
        self._last_recorded = -1  # tick of the last record handed to the recorder
        self.running = False
        self.end_reason = ""
        self.events: list[tuple[float, str]] = []
        # Events for the control server's subscribers (hapticd.events): the loop pushes,
        # the server drains in the loop's sleep window.
        self.event_ring = EventRing(event_capacity)
        self._frame_events = FrameEvents(self.event_ring, F)
        self._fault_seen: object = None  # the latched fault already reported as an event
        # Commands from the control thread, applied at tick boundaries (deque: thread-safe).
        # Each with its event's code (-1: none) and value, and its event log line.
        self._inbox: collections.deque[tuple[Command, Applied, int, int, str]] = collections.deque()

    # -- what other threads may use ------------------------------------------------------

    @property
    def devices(self) -> list[Device]:
        return self.bank.devices

    @property
    def sleep_until(self) -> float:
        """When the loop's current sleep ends (monotonic s), less the final spin."""
        return self.pacer.sleep_until

    def open_sleep_gate(self) -> int:
        """A pipe the loop writes a byte to just before each sleep; returns its read end.

        Another thread that waits on it (without the GIL) and then works until
        ``sleep_until`` never makes the loop wait for the GIL.
        """
        return self.pacer.open_sleep_gate()

    def close_sleep_gate(self) -> None:
        self.pacer.close_sleep_gate()

    def submit(self, command: Command) -> Applied:
        """Queue a command (from another thread); the loop applies it at its next tick start.

        The command prepares itself first, here in the caller's thread (``Command.prepare``:
        a set checks its value and works out its change): ValueError, nothing queued and
        nothing changed, for one it refuses."""
        command.prepare(self)
        done = Applied()
        done.command = command
        # What the loop reports once it applied it, made here too: the event's code and
        # value, and the event log's line.
        code = -1 if command.event is None else CODES[command.event]
        line = f"control: {command.describe()}"
        self._inbox.append((command, done, code, command.event_value(), line))
        return done

    def now(self) -> float:
        """Nominal time of the current tick, s (the clock of trajectory devices)."""
        return self._t

    @property
    def stop_reason(self) -> str | None:
        """Why the loop is stopping, once a stop was requested."""
        return self._stop_reason

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

    # -- what commands change -------------------------------------------------------------

    def _owner(self, name: str) -> Renderer | SafetyChain:
        """The part of the loop that holds parameter ``name``, as its spec (hapticd.params)
        says; looked up on every call, since a reload swaps both."""
        spec = PARAMS.get(name)
        if spec is None:
            raise ParamError("unknown_param", f"unknown parameter {name!r}")
        holders: dict[str, Renderer | SafetyChain] = {
            "renderer": self.renderer,
            "safety": self.safety,
        }
        return holders[spec.owner]

    def param(self, name: str) -> Any:
        """A parameter's current value (JSON-friendly), from whichever part holds it."""
        return self._owner(name).param(name)

    def set_param(self, name: str, value: Any) -> None:
        """Set a parameter now (at a tick boundary, or in the thread that runs the loop's
        ticks); ValueError changes nothing."""
        self.apply_change(self.prepare_set(name, value))

    def prepare_set(self, name: str, value: Any) -> Change:
        """Check a parameter's new value and prepare its change, changing nothing (from any
        thread: the control thread's share of a set). A number becomes stores into its
        slots in the running call's arrays; a change of the plan's structure a new plan,
        bound to the loop's frame, to swap in. ParamError or ValueError for a value the
        part that holds it refuses."""
        owner = self._owner(name)
        if isinstance(owner, Renderer):
            frame = self.frame
            safety = self.safety
            change = owner.prepare_set(name, value, frame, safety if safety.ready() else None)
            change.guards.append((self, "renderer", owner))
            if change.structural:  # its call is bound to the loop's frame
                change.guards.append((self, "frame", frame))
        else:
            change = owner.prepare_set(name, value)
            change.guards.append((self, "safety", owner))
        return change

    def apply_change(self, change: Change) -> None:
        """Make a prepared change (at a tick boundary): its stores, no plan or allocation. One
        prepared against what has changed since (another change, a reload) is prepared
        again here and applied; ValueError, nothing changed, if it no longer can be."""
        if not change.apply():
            self.stale_changes += 1
            self.prepare_set(change.name, change.value).apply()

    def enable(self, t: float) -> None:
        """Clear a latched fault and enable every device's forces again; they ramp up from
        zero from nominal time ``t`` (s)."""
        self.safety.reset(t)
        self.bank.enable(True)
        self.forces_off = False

    def disable(self) -> None:
        """Turn every device's forces off."""
        self.bank.enable(False)

    def start_recording(self, recorder: Recorder) -> None:
        """Record every tick with ``recorder`` (its writer already running; once the loop
        has started, anchored to its clock here); ValueError while another one records."""
        if self.recorder is not None:
            raise ValueError(f"already recording to {self.recorder.path}; stop it first")
        if self.anchor is not None:
            recorder.anchor(*self.anchor)  # its header's clock, filled by its writer
        self.recorder = recorder

    def stop_recording(self) -> Recorder:
        """Stop recording; the recorder, for the caller to close. ValueError when none
        records."""
        if self.recorder is None:
            raise ValueError("not recording")
        old, self.recorder = self.recorder, None
        return old

    def reload(
        self, renderer: Renderer, safety: SafetyChain, t: float, frame: Frame | None = None
    ) -> None:
        """Switch to another renderer and safety chain; forces ramp up again, proxies start
        anew. A latched fault stays latched (``enable`` clears it). ``frame``: a fresh frame
        for the new layout, built off the loop (else built here)."""
        if renderer.actuation.n_actuators != self.renderer.actuation.n_actuators:
            if self.recorder is not None:
                raise ValueError(
                    "the new profile changes the number of actuated directions, which would "
                    f"change the layout of the recording {self.recorder.path}; stop recording "
                    "first"
                )
            if self.tap is not None:
                raise ValueError(
                    "the new profile changes the number of actuated directions, which would "
                    f"change the channels of {self.tap.path}; restart hapticd to change them"
                )
        # A fresh frame: nothing the old renderer's stages wrote may linger; the devices'
        # last state carries over (a lost device keeps its last position).
        old_frame = self.frame
        n_act = renderer.actuation.n_actuators
        if frame is None or frame.n_fingers != old_frame.n_fingers or frame.n_actuators != n_act:
            frame = Frame(old_frame.n_fingers, n_act)
        self.frame = frame
        for name in ("device_pos", "device_vel", "buttons"):
            self.frame.get(name)[...] = old_frame.get(name)
        old = self.safety
        if old.fault is not None:
            safety.fault = old.fault
        safety.clamped_ticks += old.clamped_ticks
        safety.rate_limited_ticks += old.rate_limited_ticks
        safety.start(t)
        self.bank.max_speed_m_per_s = safety.params.max_device_speed_m_per_s
        self.renderer, self.safety = renderer, safety

    # -- the tick ---------------------------------------------------------------------------

    def _apply_inbox(self, k: int, t: float) -> None:
        while self._inbox:
            command, done, code, value, line = self._inbox.popleft()
            try:
                if self._stop_reason is not None and not command.while_stopping:
                    raise ValueError(f"the daemon is stopping ({self._stop_reason})")
                done.result = command.apply(self, t)
                self.control_seq += 1
                if code >= 0:
                    self.event_ring.push(code, k, t, value=value)
                # Recorded only: forces are live here, so the control thread does the logging.
                self.events.append((t, line))
            except ValueError as exc:
                done.error = str(exc)
            except Exception as exc:
                done.error = f"{type(exc).__name__}: {exc}"
            done.tick = k
            done.set()

    def _tick(self, k: int, t: float, start: float) -> None:
        frame = self.frame
        if self._inbox:
            self._apply_inbox(k, t)
            frame = self.frame  # a reload may have changed its layout
        if frame is not self._scalars_of:
            self._bind_scalars(frame)
        self._tick_view[()] = k
        self._t_view[()] = t
        self._t_wall_view[()] = start - self.pacer.origin
        renderer = self.renderer
        if renderer is not self._loop_of or self.bank.max_speed_m_per_s != self._speed_of:
            self._bind_renderer(renderer)
        call = renderer.one_call
        # The samples wait in the frame for the one call's check (its compiled form of the
        # bank's) once every proxy has started; the bank checks them itself otherwise.
        self._loop_block[SAMPLES] = self.bank.read(frame, k, t, call.started)
        safety = self.safety
        # The safety chain's tick runs in the renderer's one call unless a fault is latched:
        # then the object was checked there too, device_force is written (zero on a trip)
        # and each finger's largest force kept. The watchdog's clock is read after it: a
        # stalled tick trips before its force is sent. Renderer.run's one call, without the
        # method around it.
        outcome = call.run(frame, safety if safety.ready() else None)
        if outcome == SAMPLES_REFUSED:  # a sample no hand makes: the bank says which, a fault
            self.bank.check(frame, k, t)
            outcome = call.run(frame, safety if safety.ready() else None)
        t_wall = self.watchdog_clock() if self.wall_watchdog else None
        if outcome is None:
            self._check_object(frame, k, t)
            safety.run(frame, t_wall)
            self._keep_max_force(frame, False)
        elif not safety.done(outcome, k, t, t_wall):
            safety.run(frame, t_wall)  # a fault latched (a trip, the watchdog): zero force
            self._keep_max_force(frame, True)
        self.bank.write(frame, k, t)
        if self.safety.fault is not None and not self.forces_off:
            # A latched fault: after the zero force just written, the devices' forces go off
            # too (an SDK's gravity compensation would otherwise still push). Once, never
            # raising; `enable` turns them on again.
            self.forces_off = True
            self.bank.zero()

    def _bind_renderer(self, renderer: Renderer) -> None:
        """The loop's block of ``renderer``'s state (hapticd.physics.kernels.LOOP_*): the device
        bank's sample limits, each finger's largest force so far (carried over from the
        renderer before a reload) kept by the one call."""
        block = renderer.loop
        old = self._loop_of
        if old is not None and old is not renderer:
            F = len(self.stats.max_force)
            top = kernels.LOOP_HEAD
            block[top : top + F] = np.maximum(block[top : top + F], old.loop[top : top + F])
        block[kernels.LOOP_MAX_SPEED] = self._speed_of = self.bank.max_speed_m_per_s
        block[kernels.LOOP_MAX_DISTANCE] = MAX_DEVICE_DISTANCE_M
        block[kernels.LOOP_WATCH] = 1.0
        # The call says when in_contact or buttons changed against what the events
        # watcher saw last; then the watcher runs (it finds what changed).
        F = len(self.stats.max_force)
        was = kernels.LOOP_HEAD + 2 * F
        block[was : was + F], block[was + F : was + 5 * F] = self._frame_events.seen
        block[kernels.LOOP_CHANGED] = 1.0
        self._loop_of = renderer
        self._loop_block = memoryview(block)

    def _keep_max_force(self, frame: Frame, undo: bool) -> None:
        """Each finger's largest force, for a tick whose force the one call did not send:
        ``undo`` the call's count of the force it made (the chain then sent another)."""
        block = self._loop_block
        top = kernels.LOOP_HEAD
        F = len(self._force_rows)
        for i, row in enumerate(self._force_rows):
            if undo:
                block[top + i] = block[top + F + i]
            f0, f1, f2 = row.tolist()
            mag = kernels._norm3(f0, f1, f2)
            if mag > block[top + i]:
                block[top + i] = mag

    def max_force(self) -> list[float]:
        """Each finger's largest device force so far, N."""
        top = kernels.LOOP_HEAD
        return self.renderer.loop[top : top + len(self.stats.max_force)].tolist()

    def _bind_scalars(self, frame: Frame) -> None:
        """Item views (hapticd.physics.frame.item_view) of the frame's per-tick scalars the loop
        writes: a store through one costs a tenth of a numpy 0-d assignment."""
        self._scalars_of = frame
        self._control_seq_written = -1  # a new frame: write it on the next tick
        self._tick_view = item_view(frame.tick)
        self._t_view = item_view(frame.t)
        self._t_wall_view = item_view(frame.t_wall)
        self._fault_view = item_view(frame.fault)
        self._compute_view = item_view(frame.compute_s)
        self._force_rows = [item_view(row) for row in frame.device_force]

    def _trip(self, k: int, t: float, cause: str, kind: str = "device") -> None:
        # Literal kinds: a test checks every kind latched is declared (hapticd.events).
        if kind == "device_state":
            self.safety.trip(k, t, cause, "device_state")
        else:
            self.safety.trip(k, t, cause, "device")

    def _check_object(self, frame: Frame, k: int, t: float) -> None:
        """Backstop after the renderer: a free object whose state is non-finite or absurd
        (beyond ``MAX_OBJECT_*``) latches an ``object_state`` fault and ends the run (its
        dynamics cannot continue from there), instead of a math error on the next tick."""
        obj = self.renderer.obj
        if obj.fixed:
            return
        p, v, w = frame.object_pos, frame.object_vel, frame.object_omega
        hypot = math.hypot
        # NaN fails every comparison; hypot does not overflow.
        if (
            hypot(*p.tolist()) <= MAX_OBJECT_DISTANCE_M
            and hypot(*v.tolist()) <= MAX_OBJECT_SPEED_M_PER_S
            and hypot(*w.tolist()) <= MAX_OBJECT_SPIN_RAD_PER_S
        ):
            return

        def vec(a: Any) -> str:
            return "(" + ", ".join(f"{c:.3g}" for c in np.asarray(a, dtype=float).tolist()) + ")"

        self.safety.trip(
            k,
            t,
            f"the object's state diverged: position {vec(p)} m, velocity {vec(v)} m/s, spin "
            f"{vec(w)} rad/s (limits {MAX_OBJECT_DISTANCE_M:g} m, "
            f"{MAX_OBJECT_SPEED_M_PER_S:g} m/s, {MAX_OBJECT_SPIN_RAD_PER_S:g} rad/s); "
            "forces zeroed, the run ends",
            "object_state",
        )
        self.request_stop("the object's state diverged", ramp=False)

    def _arm(self, k: int, t: float) -> None:
        """Enable the forces `enable` asked for, after the tick that applied it: its blocking
        calls outside any tick. A failure latches a fault (every device zeroed and off)."""
        try:
            self.bank.arm()
        except Exception as exc:
            self.safety.trip(k, t, f"enabling forces failed: {type(exc).__name__}: {exc}", "device")
            self.forces_off = True
            self._note_fault(k, t)
            self._log_fault()

    def _note_fault(self, k: int, t: float) -> None:
        """Push a ``fault_latched`` event for a fault not reported yet (a fault cleared by
        ``enable`` and latched again is a new one)."""
        fault = self.safety.fault
        if fault is not None and fault is not self._fault_seen:
            self._fault_seen = fault
            self.event_ring.push(
                FAULT_LATCHED, k, t, value=CAUSE_CODES.get(fault.kind, OTHER_CAUSE)
            )

    def _event(self, t: float, what: str, log_now: bool = True) -> None:
        self.events.append((t, what))
        if log_now:
            # Device losses and reconnections: rare, and the forces are already zero.
            log.warning("t = %.3f s: %s", t, what)

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
        if self.end_with_trajectory and self.bank.finished:
            return TRAJECTORY_ENDED
        return None

    # -- the run ----------------------------------------------------------------------------

    def _shut_down(self) -> list[str]:
        """Zero and disable every device, then close them; never raises."""
        errors = self.bank.zero()
        self.frame.device_force[:] = 0.0
        errors += self.bank.close()
        return errors

    def _record_shutdown(self) -> None:
        """Record the zero force the shutdown sent, as one more tick after the last recorded
        (its other fields repeat that tick's): a recording ends where the devices did, at
        zero force, also when the run ended without a ramp (duration, fault, a second
        signal)."""
        rec = self.recorder
        if rec is None or rec.ticks == 0:
            return
        frame = self.frame
        k = self._last_recorded + 1
        frame.tick[()] = k
        frame.t[()] = k * self.period
        frame.t_wall[()] = time.monotonic() - self.pacer.origin
        frame.compute_s[()] = 0.0
        frame.device_force[:] = 0.0
        frame.fault[()] = self.safety.fault is not None
        frame.control_seq[()] = self.control_seq
        with contextlib.suppress(Exception):  # never stands between shutdown and its report
            rec.append(frame.recorded)

    def _setup_failed(self, exc: Exception) -> LoopStats:
        """Opening or enabling the devices failed: a latched fault at tick 0, no tick run."""
        self.safety.trip(0, 0.0, f"device setup failed: {exc}", "setup")
        self._note_fault(0, 0.0)
        self.end_reason = "fault"
        return self.stats

    def run(self) -> LoopStats:
        """Open and enable the devices, run until a stop condition, then zero and close."""
        try:
            self.bank.open(enable=False)  # closes what it opened if it fails
        except Exception as exc:
            return self._setup_failed(exc)
        gc_was_enabled = gc.isenabled()
        old_switch = sys.getswitchinterval()
        try:
            # From here on every way out, an exception included, passes the finally below.
            self.safety.start(0.0)
            if self.realtime_settings is not None:
                try:
                    self.rt_report = realtime.apply(self.realtime_settings)
                except Exception as exc:  # RealtimeError, or a setting the OS cannot take
                    why = (
                        str(exc)
                        if isinstance(exc, realtime.RealtimeError)
                        else (f"real time settings failed: {type(exc).__name__}: {exc}")
                    )
                    self.safety.trip(0, 0.0, why, "realtime")
                    self._note_fault(0, 0.0)
                    self.end_reason = "fault"
                    self._log_fault()
                    return self.stats
                for problem in self.rt_report.problems:
                    log.warning("real time: %s", problem)
            if self.paced:
                # A collection now keeps a paced loop free of a collector's pause later; an
                # unpaced run has no deadline to protect, and a full collection of a big
                # process's heap (a Dask worker's) cost more than the ticks of a short run.
                gc.collect()
            gc.freeze()
            gc.disable()
            if self.switch_interval_s is not None and self.paced:
                sys.setswitchinterval(self.switch_interval_s)
            try:
                # Enabling blocks (an SDK's brakes, its estimator): the last thing before the
                # first tick, since a device's watchdog counts from it.
                self.bank.arm()
            except Exception as exc:
                return self._setup_failed(exc)
            self.running = True
            self._loop()
        finally:
            self.running = False
            self.stats.contact_ticks[:] = self._frame_events.contact_ticks()
            with contextlib.suppress(Exception):
                self.stats.max_force[:] = self.max_force()
            # Was the last force sent not zero? Then the recording needs the shutdown's zero.
            unrecorded_zero = bool(self.frame.device_force.any())
            # The devices first: nothing below may stand between a fault and zero force.
            errors = self._shut_down()
            if unrecorded_zero:
                self._record_shutdown()
            with contextlib.suppress(Exception):
                sys.setswitchinterval(old_switch)
            if self.rt_report is not None:
                try:
                    realtime.restore(self.rt_report)  # shutdown work runs at normal priority
                except Exception as exc:
                    errors.append(f"restoring real-time settings: {exc}")
            if errors and self.safety.fault is None:
                with contextlib.suppress(Exception):
                    self.safety.trip(
                        self.stats.ticks, self._t, "shutdown: " + "; ".join(errors), "shutdown"
                    )
                    self._note_fault(self.stats.ticks, self._t)
            if gc_was_enabled:
                gc.enable()
            gc.unfreeze()
        return self.stats

    def _loop(self) -> None:
        pacer = self.pacer
        T = self.period
        pacer.start()
        self.anchor = clock_anchor(pacer.origin)
        for sink in (self.recorder, self.tap):
            if sink is not None:
                sink.anchor(*self.anchor)
        k = 0
        if self.recorder is not None:
            self.event_ring.push(RECORDING_STARTED, 0, 0.0)
        now = self.clock.cell
        while True:
            t = k * T
            self._t = now[0] = t
            start, late = pacer.begin(k)
            if late is not None:
                self.safety.trip(k, t, late, "overrun")
                self._log_fault()
            latched = self.safety.fault is not None
            try:
                self._tick(k, t, start)
            except Exception as exc:
                # A device that failed (its driver said why) is a device fault, not a stage's.
                # (Each kind a literal: a test collects every kind the code can latch.)
                if isinstance(exc, DeviceError):
                    self.safety.trip(k, t, f"{type(exc).__name__}: {exc}", "device")
                else:
                    self.safety.trip(k, t, f"{type(exc).__name__}: {exc}", "exception")
                self._note_fault(k, t)
                self.end_reason = "fault"
                pacer.end(k, start)
                self._log_fault()
                return
            # Read after the tick: a command at its start may have swapped these.
            frame = self.frame
            fault = self.safety.fault
            if fault is not None and not latched:
                self._log_fault()
            # Events read the frame the tick left, never the stages' insides: when the call
            # found in_contact or buttons changed, or did not look (hapticd.physics.kernels.LOOP_*).
            events = self._frame_events
            if self._loop_block[CHANGED]:
                events.after_tick(frame, k, t)
            else:
                events.tick = k
            if fault is not None and fault is not self._fault_seen:
                self._note_fault(k, t)
            if frame is not self._scalars_of:
                self._bind_scalars(frame)
            # (Each finger's largest force is kept by the one call, or by _tick when the
            # chain sent the force; ticks in contact by the frame watcher, at each change.)
            self._fault_view[()] = fault is not None
            if self.control_seq != self._control_seq_written:
                # It changes only when a command lands (its field stays between ticks).
                frame.control_seq[()] = self._control_seq_written = self.control_seq
            compute = pacer.end(k, start)
            rec = self.recorder
            tap = self.tap
            if rec is not None or tap is not None:
                self._compute_view[()] = compute
            if rec is not None:
                rec.append(frame.recorded)
                self._last_recorded = k
            if tap is not None:
                tap.append(frame.recorded)
            if self.bank.arm_pending:
                self._arm(k, t)
            reason = self._finished(k)
            if reason is not None:
                self.end_reason = reason
                if reason == TRAJECTORY_ENDED:
                    self.event_ring.push(TRAJECTORY_END, k, t)
                return
            k += 1
            pacer.catch_up(k)
