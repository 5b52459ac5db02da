"""Replay device: plays recorded fingertip positions on the servo loop's timeline, once or
(``repeat``) again and again for as long as the run lasts.

Positions are interpolated linearly between samples when the loop rate differs
from the recording's; velocity is the slope of the current segment. Buttons, when
the trajectory has them (a recording made by the loop does), are each sample's,
held until the next: a replay presses what the recording's devices pressed. Time comes
from ``clock`` (s), which the servo loop sets to each tick's nominal time, so a
paced and an unpaced run see the same positions. Forces written are checked as
firmware would and kept for inspection.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
from hapticd_drivers.base import Device, DeviceError, DeviceInfo, DeviceState, check_force
from hapticd_drivers.trajectory import Trajectory

KEPT_FORCES = 1 << 16  # forces a device on a repeated path keeps for inspection


class ReplayDevice(Device):
    """Plays ``positions`` (N, 3) m and ``buttons`` (N,) bit sets (None: every button up) at
    ``times`` (N,) s, strictly increasing."""

    def __init__(
        self,
        times: np.ndarray,
        positions: np.ndarray,
        clock: Callable[[], float] | None = None,
        max_force_n: float = 12.0,
        serial: str = "replay",
        hold_s: float = 0.0,
        workspace_radius_m: float = 0.075,
        buttons: np.ndarray | None = None,
        repeat: bool = False,
    ) -> None:
        self.path = Trajectory(times, positions, f"replay {serial}", buttons, repeat)
        self.info = DeviceInfo("replay", serial, float(max_force_n), workspace_radius_m)
        self._who = f"{self.info.model} {self.info.serial}"  # names it in a refusal
        # Looked up once: read_state and write_force run for every device every tick.
        self._sample = self.path.sample
        self._limit_n = self.info.max_force_n
        self._clock = clock
        self._t0 = 0.0
        self._hold_s = float(hold_s)
        # When the device has finished (s of its clock; a repeated path never does): the
        # loop asks after every tick.
        self._ends_at = math.inf if repeat else self.path.duration + self._hold_s
        self._open = False
        self._enabled = False
        self._now = 0.0
        self._forces = np.zeros((1024, 3))
        self._force_times = np.zeros(1024)
        self._n_forces = 0
        # The forces kept for inspection: all of a run that ends, the latest of one that
        # does not (a repeated path): beyond KEPT_FORCES the older half is dropped.
        self._kept_max = KEPT_FORCES if repeat else None
        self._bind_kept()

    @property
    def duration(self) -> float:
        """Length of the trajectory, s."""
        return self.path.duration

    def open(self) -> None:
        self._t0 = time.monotonic() if self._clock is None else 0.0
        self._open = True

    def close(self) -> None:
        self._enabled = False
        self._open = False

    def _time(self) -> float:
        return self._clock() if self._clock is not None else time.monotonic() - self._t0

    def _require_open(self, what: str) -> None:
        if not self._open:
            raise DeviceError(f"{self.info.model} {self.info.serial}: {what} a closed device")

    def read_state(self, state: DeviceState) -> None:
        if not self._open:
            self._require_open("read from")
        clock = self._clock
        now = clock() if clock is not None else time.monotonic() - self._t0
        self._now = now
        # Written item by item into the state's arrays: no tuple per sample.
        state.buttons = self._sample(now, state.pos_view, state.vel_view)
        state.timestamp = now

    def write_force(self, force: np.ndarray) -> None:
        """Check ``force`` as firmware would, then keep it (zero while disabled), at this
        read's time."""
        if not self._open:
            self._require_open("write to")
        x, y, z = check_force(force, self._limit_n, self._who)
        # Kept here, not in a method of its own: this runs for every device every tick.
        n = self._n_forces
        if n >= self._room:
            n = self._make_room(n)
        # Stored through flat memoryviews: a float each, for a fraction of a row assignment.
        f, i = self._forces_mv, 3 * n
        if self._enabled:
            f[i] = x
            f[i + 1] = y
            f[i + 2] = z
        else:
            f[i] = f[i + 1] = f[i + 2] = 0.0
        self._times_mv[n] = self._now
        self._n_forces = n + 1

    def _make_room(self, n: int) -> int:
        """Room for the ``n``-th force kept: beyond KEPT_FORCES (a repeated path) the older
        half dropped, else the arrays doubled; returns where it goes."""
        if n == self._kept_max:
            half = n // 2
            self._forces[: n - half] = self._forces[half:n]
            self._force_times[: n - half] = self._force_times[half:n]
            n = n - half
        if n == len(self._force_times):
            self._forces = np.concatenate([self._forces, np.zeros_like(self._forces)])
            self._force_times = np.concatenate(
                [self._force_times, np.zeros_like(self._force_times)]
            )
            self._bind_kept()
        return n

    def _bind_kept(self) -> None:
        self._forces_mv = memoryview(self._forces.reshape(-1))
        self._times_mv = memoryview(self._force_times)
        # write_force makes room when the count reaches this: the arrays' end, or the most kept.
        size, most = len(self._force_times), self._kept_max
        self._room = size if most is None else min(most, size)

    def enable_forces(self, enabled: bool) -> None:
        self._enabled = bool(enabled)

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def finished(self) -> bool:
        return self._now >= self._ends_at

    @property
    def forces(self) -> np.ndarray:
        """Every force written, (n, 3) N (zeros while disabled); on a repeated path, the
        latest (at least KEPT_FORCES / 2)."""
        return self._forces[: self._n_forces].copy()

    @property
    def force_times(self) -> np.ndarray:
        """Device time of every force written, (n,) s."""
        return self._force_times[: self._n_forces].copy()

    @property
    def last_force(self) -> np.ndarray:
        return self._forces[self._n_forces - 1].copy() if self._n_forces else np.zeros(3)
