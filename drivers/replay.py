"""Replay device: plays recorded fingertip positions on the servo loop's timeline.

Positions are interpolated linearly between samples when the loop rate differs
from the recording's; velocity is the slope of the current segment. Time comes
from ``clock`` (s), which the servo loop sets to each tick's nominal time, so a
paced and an unpaced run see the same positions. Forces written are checked as
firmware would and kept for inspection.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from hapticd_drivers.base import Device, DeviceError, DeviceInfo, DeviceState, check_force


class ReplayDevice(Device):
    """Plays ``positions`` (N, 3) m at ``times`` (N,) s, strictly increasing."""

    def __init__(
        self,
        times: np.ndarray,
        positions: np.ndarray,
        clock: Callable[[], float] | None = None,
        max_force_n: float = 12.0,
        serial: str = "replay",
        hold_s: float = 0.0,
        workspace_radius_m: float = 0.075,
    ) -> None:
        t = np.asarray(times, dtype=float).reshape(-1)
        x = np.asarray(positions, dtype=float)
        if x.shape != (t.size, 3):
            raise DeviceError(
                f"replay {serial}: positions {x.shape} do not match times ({t.size},)"
            )
        if t.size < 2 or not np.all(np.isfinite(t)) or not np.all(np.isfinite(x)):
            raise DeviceError(f"replay {serial}: need at least 2 finite samples")
        if not np.all(np.diff(t) > 0):
            raise DeviceError(f"replay {serial}: sample times must strictly increase")
        self.info = DeviceInfo("replay", serial, float(max_force_n), workspace_radius_m)
        self._t = (t - t[0]).tolist()
        self._x = x.tolist()
        self._slope = (np.diff(x, axis=0) / np.diff(t)[:, None]).tolist()
        self._clock = clock
        self._t0 = 0.0
        self._k = 0
        self._hold_s = float(hold_s)
        self._open = False
        self._enabled = False
        self._now = 0.0
        self._forces = np.zeros((1024, 3))
        self._force_times = np.zeros(1024)
        self._n_forces = 0

    @property
    def duration(self) -> float:
        """Length of the trajectory, s."""
        return self._t[-1]

    def open(self) -> None:
        self._t0 = time.monotonic() if self._clock is None else 0.0
        self._k = 0
        self._open = True

    def close(self) -> None:
        self._enabled = False
        self._open = False

    def _time(self) -> float:
        return self._clock() if self._clock is not None else time.monotonic() - self._t0

    def read_state(self, state: DeviceState) -> None:
        if not self._open:
            raise DeviceError(f"replay {self.info.serial}: read from a closed device")
        now = self._time()
        self._now = now
        t = self._t
        k = self._k
        last = len(t) - 1
        if now < t[k]:
            k = 0  # time went back (a new run on the same device): search from the start
        while k < last - 1 and now >= t[k + 1]:
            k += 1
        self._k = k
        x0, s = self._x[k], self._slope[k]
        if now >= t[last]:
            x1 = self._x[last]
            state.position[:] = x1
            state.velocity[:] = 0.0
        elif now < t[0]:
            state.position[:] = x0
            state.velocity[:] = 0.0
        else:
            dt = now - t[k]
            state.position[0] = x0[0] + s[0] * dt
            state.position[1] = x0[1] + s[1] * dt
            state.position[2] = x0[2] + s[2] * dt
            state.velocity[:] = s
        state.timestamp = now
        state.buttons = 0

    def write_force(self, force: np.ndarray) -> None:
        if not self._open:
            raise DeviceError(f"replay {self.info.serial}: write to a closed device")
        check_force(force, self.info.max_force_n, f"replay {self.info.serial}")
        n = self._n_forces
        if n == len(self._force_times):
            self._forces = np.concatenate([self._forces, np.zeros_like(self._forces)])
            self._force_times = np.concatenate(
                [self._force_times, np.zeros_like(self._force_times)]
            )
        self._forces[n] = force if self._enabled else 0.0
        self._force_times[n] = self._now
        self._n_forces = n + 1

    def enable_forces(self, enabled: bool) -> None:
        self._enabled = bool(enabled)

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def finished(self) -> bool:
        return self._now >= self._t[-1] + self._hold_s

    @property
    def forces(self) -> np.ndarray:
        """Every force written, (n, 3) N (zeros while disabled)."""
        return self._forces[: self._n_forces].copy()

    @property
    def force_times(self) -> np.ndarray:
        """Device time of every force written, (n,) s."""
        return self._force_times[: self._n_forces].copy()

    @property
    def last_force(self) -> np.ndarray:
        return self._forces[self._n_forces - 1].copy() if self._n_forces else np.zeros(3)
