"""A virtual device: a handle with no hardware, moved by a person through the daemon (the
view page's mouse and keys send its targets over the control protocol), after CHAI3D's
virtual device. The loop renders it like any device: contact, events, recording.

The handle goes to its latest target in a straight line at most ``max_speed_m_per_s``
(a jump of the mouse is not a jump of the fingertip, which the device bank would refuse
as a glitch) on ``clock``, the servo loop's nominal time (so a late tick is no jump
either), and never leaves its workspace (a sphere of ``workspace_radius_m`` about the
device's origin, in its own frame). Forces written are checked as firmware would and the
last one is kept; nothing feels them. Units: m, m/s, N, s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
from hapticd_drivers.base import Device, DeviceError, DeviceInfo, DeviceState, check_force

MAX_STEP_S = 0.05  # a longer gap between reads (a paused loop) moves the handle no further


class VirtualDevice(Device):
    """A handle at its device's origin until moved (``move_to``, from any thread)."""

    def __init__(
        self,
        serial: str = "virtual",
        max_force_n: float = 12.0,
        max_speed_m_per_s: float = 0.25,
        workspace_radius_m: float = 0.075,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (max_speed_m_per_s > 0 and workspace_radius_m > 0 and max_force_n > 0):
            raise DeviceError(
                f"virtual {serial}: speed, workspace radius and force limit must be positive"
            )
        self.info = DeviceInfo("virtual", serial, float(max_force_n), float(workspace_radius_m))
        self.max_speed = float(max_speed_m_per_s)
        self._clock = clock
        self._who = f"virtual {serial}"
        self._target = (0.0, 0.0, 0.0)
        self._x = [0.0, 0.0, 0.0]
        self._last: float | None = None
        self._open = False
        self._enabled = False
        self.last_force = np.zeros(3)

    @property
    def target(self) -> tuple[float, float, float]:
        """Where the handle is going, m (device frame)."""
        return self._target

    def move_to(self, position: tuple[float, float, float] | list[float]) -> tuple[float, ...]:
        """Send the handle towards ``position`` (3,) m in the device's frame, brought inside
        the workspace; returns the target taken. DeviceError for anything but 3 finite
        numbers. One assignment: safe while the loop reads."""
        try:
            x, y, z = (float(c) for c in position)
        except (TypeError, ValueError):
            raise DeviceError(f"{self._who}: a position is 3 numbers in m") from None
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            raise DeviceError(f"{self._who}: a position must be finite, got {position!r}")
        r = math.hypot(x, y, z)
        limit = self.info.workspace_radius_m
        if r > limit:
            x, y, z = x * limit / r, y * limit / r, z * limit / r
        self._target = (x, y, z)
        return self._target

    def open(self) -> None:
        self._x = [0.0, 0.0, 0.0]
        self._target = (0.0, 0.0, 0.0)
        self._last = None
        self._open = True

    def close(self) -> None:
        self._enabled = False
        self._open = False

    def read_state(self, state: DeviceState) -> None:
        if not self._open:
            raise DeviceError(f"{self._who}: read from a closed device")
        now = self._clock()
        dt = 0.0 if self._last is None else min(max(now - self._last, 0.0), MAX_STEP_S)
        self._last = now
        x = self._x
        tx, ty, tz = self._target
        dx, dy, dz = tx - x[0], ty - x[1], tz - x[2]
        gap = math.hypot(dx, dy, dz)
        reach = self.max_speed * dt
        k = 1.0 if gap <= reach else reach / gap
        v = state.velocity
        if dt > 0.0:
            v[0], v[1], v[2] = k * dx / dt, k * dy / dt, k * dz / dt
        else:
            v[0] = v[1] = v[2] = 0.0
        x[0] += k * dx
        x[1] += k * dy
        x[2] += k * dz
        p = state.position
        p[0], p[1], p[2] = x
        state.buttons = 0
        state.timestamp = now

    def write_force(self, force: np.ndarray) -> None:
        if not self._open:
            raise DeviceError(f"{self._who}: write to a closed device")
        check_force(force, self.info.max_force_n, self._who)
        self.last_force[:] = force if self._enabled else 0.0

    def enable_forces(self, enabled: bool) -> None:
        self._enabled = bool(enabled)
