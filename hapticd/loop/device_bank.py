"""The servo loop's devices: read their state into the tick frame, write the frame's forces.

Devices speak their own frames; the tick frame holds world quantities. Each
device's mount (hapticd.loop.mount: rotation R, position t, workspace scale s) maps
between them at this seam: x_world = s R x_dev + t and v_world = s R v_dev on
reading, f_dev = R^T f_world on writing, into preallocated arrays.

A device that fails is *lost*: without reconnect mode the error ends the run;
with it, a fault is latched (forces zero on every device), the device is
closed, and it is looked for again every ``RECONNECT_PERIOD_S`` with forces
left off until someone re-enables them. A backend that tells a lost device from
one that still answers (``Device.reports_lost``) has only its DeviceLostError
looked for again; its other errors end the run as without reconnect mode. Every
way out zeroes and disables.

A sample no hand can make (a non-finite position or velocity, or a speed above
``max_speed_m_per_s`` or a position beyond ``MAX_DEVICE_DISTANCE_M``, in the device's
own frame) is a glitch: it latches a fault
(``device_state``; forces zero) and never enters the frame, which keeps the finger's
last good position at rest. The contact damping and the free object's dynamics would
otherwise turn one such velocity into an unbounded force on the object.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence

import numpy as np
from hapticd_drivers import Device, DeviceError, DeviceLostError, DeviceState

from hapticd.loop.mount import Mount
from hapticd.physics.frame import Frame, item_view
from hapticd.physics.kernels import plausible

# How often a lost device is looked for again (reconnect mode), s of loop time.
RECONNECT_PERIOD_S = 0.5
# No device's handle is this far from its origin (its own frame), m: farther is a glitch.
MAX_DEVICE_DISTANCE_M = 100.0


class DeviceBank:
    """The F devices of a run, finger i on ``devices[i]``.

    ``on_fault(tick, t, cause, kind)`` latches a fault (kind: a name of
    hapticd.events.FAULT_CAUSES); ``on_event(t, what)`` records a device event (lost,
    reconnected). ``max_speed_m_per_s``: the fastest plausible device speed, m/s.
    """

    def __init__(
        self,
        devices: Sequence[Device],
        *,
        reconnect: bool,
        on_fault: Callable[[int, float, str, str], None],
        on_event: Callable[[float, str], None],
        max_speed_m_per_s: float = math.inf,
    ) -> None:
        self.devices = list(devices)
        self.max_speed_m_per_s = max_speed_m_per_s
        self.reconnect = reconnect
        self._on_fault = on_fault
        self._on_event = on_event
        F = len(self.devices)
        # What the devices report, in their own frames: positions then velocities, (2, F, 3),
        # each device's DeviceState holding views of its rows (a device fills them in
        # place): the frame's device_sample once a frame is bound (``_sample_into``).
        self._sample_into(np.zeros((2, F, 3)))
        self.lost: list[float | None] = [None] * len(self.devices)
        self.arm_pending = False  # `enable` asked for forces: ``arm`` after the tick
        self._n_lost = 0
        self._zero = np.zeros(3)
        self._frame: Frame | None = None  # the frame ``_bind`` looked up
        self.set_mounts([Mount() for _ in self.devices])

    def set_mounts(self, mounts: Sequence[Mount]) -> None:
        """Each device's mount (device frame to world), finger i's in ``mounts[i]``."""
        if len(mounts) != len(self.devices):
            raise ValueError(f"{len(self.devices)} mounts are needed, got {len(mounts)}")
        self.mounts = list(mounts)
        # Preallocated per finger: s R, R^T, t, and the device-frame force written.
        self._sR = [np.ascontiguousarray(m.scale * m.rotation) for m in self.mounts]
        self._Rt = [np.ascontiguousarray(m.rotation.T) for m in self.mounts]
        self._t = [m.position.copy() for m in self.mounts]
        # An identity mount copies: the world values are the device's, bit for bit.
        self._mounted = [not m.is_identity for m in self.mounts]
        self._tmp = np.zeros(3)
        self._f_dev = [np.zeros(3) for _ in self.mounts]
        self._frame = None  # look the per-finger slots up again

    @property
    def finished(self) -> bool:
        """True when every device plays a trajectory that has ended."""
        # A loop, not all(generator): the loop asks after every tick.
        for d in self.devices:
            if not d.finished:
                return False
        return bool(self.devices)

    def open(self, enable: bool = True) -> None:
        """Open every device and (``enable``) enable its forces; on failure, close what was
        opened. The loop opens without enabling and calls ``arm`` just before its first
        tick: a device's watchdog counts from its enabling."""
        opened: list[Device] = []
        try:
            for dev in self.devices:
                dev.open()
                opened.append(dev)
            if enable:
                for dev in self.devices:
                    dev.enable_forces(True)
        except Exception:
            self.zero()
            for dev in opened:
                with contextlib.suppress(Exception):
                    dev.close()
            raise

    def enable(self, on: bool) -> None:
        """Off: every device's forces off, at once. On: asked for; ``arm`` enables them,
        outside any tick (enabling blocks: an SDK releases brakes and primes its
        estimator over the bus), and until then the devices render zero."""
        if on:
            self.arm_pending = True
            return
        self.arm_pending = False
        for dev in self.devices:
            dev.enable_forces(False)

    def arm(self) -> None:
        """Enable the forces of every device not lost: the blocking calls, at the start or
        between two ticks, never inside one. On failure every device is zeroed and
        disabled, and the error raised."""
        self.arm_pending = False
        try:
            for i, dev in enumerate(self.devices):
                if self.lost[i] is None:
                    dev.enable_forces(True)
        except Exception:
            self.zero()
            raise

    @property
    def max_speed_m_per_s(self) -> float:
        """The fastest speed a device may report (its own frame), m/s; faster is a glitch."""
        return self._max_speed

    @max_speed_m_per_s.setter
    def max_speed_m_per_s(self, v: float) -> None:
        if not v > 0:
            raise ValueError(f"the largest device speed must be positive, got {v}")
        self._max_speed = float(v)

    def _bind(self, frame: Frame) -> None:
        """What a tick needs of ``frame``, looked up once per frame (a reload brings a new
        one): each finger's force row, and memoryviews of the device state (a float stored
        through one is that float, bit for bit, for a fraction of a numpy item
        assignment; a memoryview copy of a block is one memcpy). The devices themselves
        are looked up on every tick: a test or a bring-up may swap one."""
        self._frame = frame
        F = len(self.devices)
        # Per finger, its position and velocity rows (a 1-d view: no index tuple to build).
        self._state_rows = [
            (item_view(frame.device_pos[i]), item_view(frame.device_vel[i])) for i in range(F)
        ]
        self._buttons_mv = item_view(frame.buttons)
        self._force_rows = [frame.device_force[i] for i in range(F)]
        self._sample_into(frame.device_sample)
        self._any_mounted = any(self._mounted)
        # device_pos and device_vel side by side in the record (hapticd.physics.frame lays them out
        # so): both, as one flat memoryview, take the devices' block in one copy.
        pos, vel = frame.device_pos, frame.device_vel
        rec = frame.record.reshape(1).view(np.uint8)
        at = pos.ctypes.data - rec.ctypes.data
        self._frame_both = (
            memoryview(rec[at : at + 2 * pos.nbytes]).cast("d")
            if vel.ctypes.data == pos.ctypes.data + pos.nbytes
            else None
        )

    def _sample_into(self, raw: np.ndarray) -> None:
        """Read the devices into ``raw`` (2, F, 3) from now on. Laid out as the frame's
        device_pos and device_vel are, so a tick whose samples all pass and need no mount
        enters the frame with one copy."""
        F = len(self.devices)
        self._raw = raw
        self._states = [DeviceState(raw[0, i], raw[1, i]) for i in range(F)]
        # Flat memoryviews: each row's floats (tolist) and the whole block (one memcpy).
        self._raw_pos = [memoryview(raw[0, i]) for i in range(F)]
        self._raw_vel = [memoryview(raw[1, i]) for i in range(F)]
        self._raw_all = memoryview(raw.reshape(-1))

    def read(self, frame: Frame, k: int, t: float, defer: bool = False) -> bool:
        """Fill ``device_pos``, ``device_vel`` and ``buttons``; a lost device keeps its last
        position, at rest, and so does a device whose sample is implausible (a fault).

        ``defer``: read every device's sample into the frame's ``device_sample`` and leave
        its check and entry to the tick's one call (hapticd.physics.kernels.tick_step, its compiled
        form of ``check``), when every device answers, none is lost and none has a mount;
        returns whether it did (False: the samples were checked and entered here)."""
        if frame is not self._frame:
            self._bind(frame)
        if not defer or self._n_lost or self._any_mounted:
            self._read(frame, k, t, 0, None)
            return False
        buttons = self._buttons_mv
        states = self._states
        i = -1  # counted by hand: enumerate's pair a finger costs more
        for dev in self.devices:
            i += 1
            st = states[i]
            try:
                dev.read_state(st)
            except BaseException as exc:
                # The fingers read so far as the checked read would have taken them, then
                # this one's error and the rest the checked way.
                self.check(frame, k, t, i)
                self._read(frame, k, t, i, exc)
                return False
            buttons[i] = st.buttons
        return True

    def check(self, frame: Frame, k: int, t: float, n: int | None = None) -> None:
        """The plausibility check of the first ``n`` fingers' samples (None: all) already
        read into ``device_sample``, entering each that passes and latching a fault for each
        that does not (a deferred read whose samples the one call refused)."""
        whole = not self._any_mounted and not self._n_lost
        n = len(self._states) if n is None else n
        for i in range(n):
            whole = self._check_one(frame, i, k, t, whole)
        if whole:
            self._enter(frame, n)

    def _read(
        self, frame: Frame, k: int, t: float, first: int, failed: BaseException | None
    ) -> None:
        """Read, check and enter the fingers from ``first`` on (``failed``: the error finger
        ``first``'s read already raised)."""
        lost = self.lost if self._n_lost else None
        states = self._states
        # The block copy below takes every finger's sample: only when each one passed and
        # needs no mount; otherwise each finger that passed is copied on its own.
        whole = not self._any_mounted and lost is None and first == 0
        i = first - 1
        for dev in self.devices[first:]:
            i += 1
            if lost is not None and lost[i] is not None:
                continue
            try:
                if failed is not None:
                    exc, failed = failed, None
                    raise exc
                dev.read_state(states[i])
            except BaseException as exc:
                if whole:  # the fingers before this one passed: into the frame first
                    self._enter(frame, i)
                    whole = False
                if not isinstance(exc, DeviceError):
                    raise
                self._lose(frame, i, k, t, exc)
                lost = self.lost
                continue
            whole = self._check_one(frame, i, k, t, whole)
        if whole:  # every finger's sample: the whole block, in one copy where it can
            self._enter(frame, len(states))

    def _check_one(self, frame: Frame, i: int, k: int, t: float, whole: bool) -> bool:
        """Finger ``i``'s sample checked (a fault if implausible) and, when it passes, into
        the frame, or (``whole``) left for the block copy; returns ``whole`` still."""
        st = self._states[i]
        px, py, pz = self._raw_pos[i].tolist()
        vx, vy, vz = self._raw_vel[i].tolist()
        if not plausible(px, py, pz, vx, vy, vz, self._max_speed, MAX_DEVICE_DISTANCE_M):
            if whole:
                self._enter(frame, i)
            self._implausible(frame, i, k, t, st)
            return False
        self._buttons_mv[i] = st.buttons
        if whole:
            return True  # copied with the others
        if self._mounted[i]:
            tmp = self._tmp
            np.matmul(self._sR[i], st.position, out=tmp)
            np.add(tmp, self._t[i], out=frame.device_pos[i])
            np.matmul(self._sR[i], st.velocity, out=frame.device_vel[i])
        else:
            pos, vel = self._state_rows[i]
            pos[:] = self._raw_pos[i]
            vel[:] = self._raw_vel[i]
        return False

    def _enter(self, frame: Frame, n: int) -> None:
        """Copy the first ``n`` fingers' samples, all passed and none mounted, into the
        frame: the whole block in one copy when ``n`` is every finger."""
        both = self._frame_both
        if n == len(self._states) and both is not None:
            both[:] = self._raw_all
            return
        frame.device_pos[:n] = self._raw[0, :n]
        frame.device_vel[:n] = self._raw[1, :n]

    def write(self, frame: Frame, k: int, t: float) -> None:
        """Command ``device_force`` (world frame) on every connected device, each in its own
        frame (R^T f), then look for lost ones."""
        if frame is not self._frame:
            self._bind(frame)
        lost = self.lost if self._n_lost else None
        mounted = self._mounted if self._any_mounted else None
        rows = self._force_rows
        i = -1
        for dev in self.devices:
            i += 1
            if lost is not None and lost[i] is not None:
                continue
            f = rows[i]
            if mounted is not None and mounted[i]:
                f = np.matmul(self._Rt[i], f, out=self._f_dev[i])
            try:
                dev.write_force(f)
            except DeviceError as exc:
                self._lose(frame, i, k, t, exc)
                lost = self.lost
        if self._n_lost:
            self._look_for_lost(t)

    def zero(self) -> list[str]:
        """Command zero force and disable every device; return the errors met (never raises)."""
        errors: list[str] = []
        for dev in self.devices:
            for action in (
                lambda d=dev: d.write_force(self._zero),
                lambda d=dev: d.enable_forces(False),
            ):
                try:
                    action()
                except Exception as exc:
                    errors.append(f"{_name(dev)}: {exc}")
        return errors

    def close(self) -> list[str]:
        """Close every device; return the errors met (never raises)."""
        errors: list[str] = []
        for dev in self.devices:
            try:
                dev.close()
            except Exception as exc:
                errors.append(f"{_name(dev)}: close: {exc}")
        return errors

    def _implausible(self, frame: Frame, i: int, k: int, t: float, st: DeviceState) -> None:
        """A sample no hand makes: latch a fault; the frame keeps the finger's last good
        position, at rest (its buttons still count: a deadman follows them)."""
        p, v = np.asarray(st.position, dtype=float), np.asarray(st.velocity, dtype=float)
        fmt = ", ".join
        if not np.all(np.isfinite(p)):
            what = f"a non-finite position ({fmt(f'{c:g}' for c in p.tolist())}) m"
        elif not math.hypot(*p.tolist()) <= MAX_DEVICE_DISTANCE_M:
            what = (
                f"a position {math.hypot(*p.tolist()):.3g} m from its origin, beyond any "
                f"workspace ({MAX_DEVICE_DISTANCE_M:g} m)"
            )
        elif not np.all(np.isfinite(v)):
            what = f"a non-finite velocity ({fmt(f'{c:g}' for c in v.tolist())}) m/s"
        else:
            speed = math.hypot(*v.tolist())
            what = (
                f"a speed of {speed:.4g} m/s (velocity ({fmt(f'{c:.4g}' for c in v.tolist())}) "
                f"m/s), above the plausible {self._max_speed:g} m/s "
                "(safety.max_device_speed_m_per_s)"
            )
        self._on_fault(
            k,
            t,
            f"device {_name(self.devices[i])} (finger {i}) reported {what}: a glitched sample; "
            "forces zeroed, its last good position kept",
            "device_state",
        )
        frame.device_vel[i] = 0.0
        frame.buttons[i] = st.buttons

    def _lose(self, frame: Frame, i: int, k: int, t: float, exc: DeviceError) -> None:
        if not self.reconnect:
            raise exc
        if self.devices[i].reports_lost and not isinstance(exc, DeviceLostError):
            raise exc  # the device still answers: a fault, not a device to look for again
        self._on_fault(k, t, f"{type(exc).__name__}: {exc}", "device")
        frame.device_force[:] = 0.0
        self.zero()
        dev = self.devices[i]
        with contextlib.suppress(Exception):
            dev.close()
        self.lost[i] = t
        self._n_lost += 1
        frame.device_vel[i] = 0.0
        self._on_event(t, f"device {_name(dev)} lost: {exc}")

    def _look_for_lost(self, t: float) -> None:
        for i, since in enumerate(self.lost):
            if since is None or t - since < RECONNECT_PERIOD_S:
                continue
            dev = self.devices[i]
            try:
                dev.open()
                dev.enable_forces(False)  # forces stay off until someone re-enables them
            except Exception:
                self.lost[i] = t  # still gone: try again later
                continue
            self.lost[i] = None
            self._n_lost -= 1
            self._on_event(t, f"device {_name(dev)} reconnected; forces stay off")


def _name(dev: Device) -> str:
    info = getattr(dev, "info", None)
    return info.serial if info is not None else type(dev).__name__
