"""springtip: a simulated fingertip as a hapticd device backend, from a lab's package.

The fingertip follows the profile's trajectory through a first-order lag (time constant
``lag_s``, s): x' = (path(t) - x) / lag_s, integrated exactly over each read's step, on
``clock``, the servo loop's nominal time (s). Forces are refused when non-finite or
over the rated force (``check_force``, as firmware would), and the last accepted one is
kept (``last_force``, N); nothing feels them. Units: m, m/s, N, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from hapticd_drivers.base import Device, DeviceError, DeviceInfo, DeviceState, check_force
from hapticd_drivers.registry import REQUIRED, Backend, Key


class SpringTip(Device):
    """A fingertip lagging ``lag_s`` s behind ``positions`` (N, 3) m at ``times`` (N,) s."""

    def __init__(
        self,
        times: np.ndarray,
        positions: np.ndarray,
        clock: Callable[[], float],
        serial: str = "springtip",
        max_force_n: float = 10.0,
        lag_s: float = 0.005,
        buttons: np.ndarray | None = None,
    ) -> None:
        times, positions = np.asarray(times, float), np.asarray(positions, float)
        if times.ndim != 1 or positions.shape != (len(times), 3) or len(times) < 2:
            raise DeviceError(f"springtip {serial}: expected times (N,) and positions (N, 3)")
        if not (lag_s > 0 and max_force_n > 0):
            raise DeviceError(f"springtip {serial}: lag_s and max_force_n must be positive")
        self.info = DeviceInfo("springtip", serial, float(max_force_n), 0.1)
        self._times, self._positions = times, positions
        self._clock, self._lag = clock, float(lag_s)
        self._who = f"springtip {serial}"
        self._x = positions[0].copy()
        self._last: float | None = None
        self._open = self._enabled = False
        self.last_force = np.zeros(3)

    def open(self) -> None:
        self._x[:] = self._positions[0]
        self._last = None
        self._open = True

    def close(self) -> None:
        self._enabled = self._open = False

    @property
    def finished(self) -> bool:
        # The run ends when the trajectory does (like the replay backend).
        return self._last is not None and self._last > self._times[-1]

    def read_state(self, state: DeviceState) -> None:
        if not self._open:
            raise DeviceError(f"{self._who}: read from a closed device")
        now = self._clock()
        dt = 0.0 if self._last is None else max(now - self._last, 0.0)
        self._last = now
        goal = [float(np.interp(now, self._times, self._positions[:, i])) for i in range(3)]
        k = 1.0 - math.exp(-dt / self._lag)  # the exact step of the lag over dt
        for i in range(3):
            step = k * (goal[i] - self._x[i])
            self._x[i] += step
            state.velocity[i] = step / dt if dt > 0 else 0.0
            state.position[i] = self._x[i]
        state.buttons = 0
        state.timestamp = now

    def write_force(self, force: np.ndarray) -> None:
        if not self._open:
            raise DeviceError(f"{self._who}: write to a closed device")
        check_force(force, self.info.max_force_n, self._who)
        self.last_force[:] = force if self._enabled else 0.0

    def enable_forces(self, enabled: bool) -> None:
        self._enabled = bool(enabled)


# The registry entry the entry point names: the profile keys (with units and bounds) are
# what a profile's `device: {backend: springtip, ...}` may give.
BACKEND = Backend(
    "springtip",
    __name__,
    "SpringTip",
    "a simulated fingertip lagging behind a trajectory (the example backend package)",
    (
        Key("trajectory", str, REQUIRED, "the fingertip's path: a recording or 'builtin:NAME'"),
        Key("finger", str, None, "the recording's finger to play (this one's)", True),
        Key("max_force_n", float, 10.0, "the device's rated force, N", gt=0.0, le=100.0),
        Key("lag_s", float, 0.005, "the fingertip's lag behind the path, s", gt=0.0, le=1.0),
    ),
    plays_trajectory=True,
    status="example plugin",
)
