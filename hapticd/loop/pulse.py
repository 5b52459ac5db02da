"""A scripted force pulse, the renderer's last stage during ``hapticd bringup``.

The pulse is a force of amplitude A (N, at most ``MAX_PULSE_N``) along one unit
direction (world frame) on one finger, shaped by a smooth envelope: a
raised-cosine rise over ``ramp_s``, a plateau of ``hold_s``, a raised-cosine fall
over ``ramp_s`` (s). Its force and its rate of change are continuous; the force
never exceeds A, and changes by at most A pi / (2 ramp_s) N/s.

``PulseStage`` writes every finger's ``rendered_force`` as the pulse (zero
while none runs), in the place of the sum of the scene's forces
(``Renderer.set_output``): in a bring-up the researcher judges the pulse's
direction, and no contact force of the scene may mix into it. What it writes then passes the
safety chain and the device bank like any rendered force. It also reads the
frame's ``device_force`` (what the safety chain sent on the previous tick) to
report the peak that actually reached each device during the pulse.
"""

from __future__ import annotations

import math

import numpy as np

from hapticd.physics.frame import Frame

# The largest pulse a bring-up may send, N: felt clearly through a thimble, harmless.
MAX_PULSE_N = 0.5


def envelope(t: float, ramp_s: float, hold_s: float) -> float:
    """The pulse's shape at time ``t`` (s) from its start: 0 before, raised-cosine up to 1
    over ``ramp_s``, 1 for ``hold_s``, raised-cosine down to 0 over ``ramp_s``, 0 after."""
    if t <= 0.0:
        return 0.0
    if t < ramp_s:
        return 0.5 - 0.5 * math.cos(math.pi * t / ramp_s)
    t -= ramp_s
    if t <= hold_s:
        return 1.0
    t -= hold_s
    if t < ramp_s:
        return 0.5 + 0.5 * math.cos(math.pi * t / ramp_s)
    return 0.0


class PulseStage:
    """Renders one pulse at a time for ``n_fingers`` fingers at ``dt`` s a tick.

    ``start`` (called at a tick boundary, by a loop command) arms a pulse from tick
    ``tick``; ``run`` writes the frame's ``rendered_force``; ``done`` is True from the
    tick after the pulse's last; ``peak_sent_n`` holds, per finger, the largest force
    magnitude (N) the safety chain sent while the pulse ran.
    """

    name = "pulse"
    # device_force: the previous tick's, as the safety chain sent it.
    reads = ("tick", "device_force")
    writes = ("rendered_force",)

    def __init__(self, n_fingers: int, dt: float, ramp_s: float = 0.2, hold_s: float = 0.3) -> None:
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"the tick period must be positive, got {dt}")
        if not (0.05 <= ramp_s <= 2.0 and 0.0 <= hold_s <= 5.0):
            raise ValueError(
                f"a pulse ramps over 0.05 to 2 s and holds 0 to 5 s, got ramp {ramp_s} s, "
                f"hold {hold_s} s"
            )
        self.n_fingers = n_fingers
        self.dt = float(dt)
        self.ramp_s = float(ramp_s)
        self.hold_s = float(hold_s)
        self.finger = -1
        self.force = np.zeros(3)  # amplitude times direction, N (world frame)
        self.start_tick = -1
        self.end_tick = -1  # the first tick after the pulse (its force there is zero)
        self.peak_sent_n = [0.0] * n_fingers
        self.peak_commanded_n = 0.0
        self._last_tick = -1  # the last tick run

    @property
    def duration_s(self) -> float:
        """The pulse's length, s."""
        return 2.0 * self.ramp_s + self.hold_s

    @property
    def n_ticks(self) -> int:
        """Ticks from the pulse's first to the first after it (its force zero again)."""
        return math.ceil(self.duration_s / self.dt - 1e-9) + 1

    def start(self, tick: int, finger: int, direction: np.ndarray, amplitude_n: float) -> None:
        """Arm a pulse of ``amplitude_n`` N (0 to MAX_PULSE_N) along ``direction`` (3,) (made
        unit) on ``finger`` from tick ``tick``; ValueError (nothing armed) otherwise."""
        d = np.asarray(direction, dtype=float).reshape(3)
        n = float(np.linalg.norm(d))
        if not (math.isfinite(n) and n > 1e-9):
            raise ValueError(f"a pulse needs a finite, non-zero direction, got {d.tolist()}")
        if not (0.0 < amplitude_n <= MAX_PULSE_N):
            raise ValueError(
                f"a pulse's amplitude must be in (0, {MAX_PULSE_N:g}] N, got {amplitude_n}"
            )
        if not 0 <= finger < self.n_fingers:
            raise ValueError(f"no finger {finger}; there are {self.n_fingers}")
        if not self.done:
            raise ValueError("a pulse is still running")
        self.force = (amplitude_n / n) * d
        self.finger = finger
        self.start_tick = tick
        self.end_tick = tick + self.n_ticks
        self.peak_sent_n = [0.0] * self.n_fingers
        self.peak_commanded_n = 0.0

    @property
    def done(self) -> bool:
        """True when no pulse is armed or running."""
        return self.start_tick < 0 or self._last_tick >= self.end_tick

    def run(self, frame: Frame) -> None:
        k = int(frame.tick)
        out = frame.rendered_force
        if self.start_tick >= 0 and self.start_tick < k <= self.end_tick:
            # device_force still holds what the previous tick sent: part of this pulse.
            sent = frame.device_force
            for i in range(self.n_fingers):
                f = sent[i]
                mag = math.hypot(f[0], f[1], f[2])
                if mag > self.peak_sent_n[i]:
                    self.peak_sent_n[i] = mag
        out[...] = 0.0
        self._last_tick = k
        if self.start_tick <= k < self.end_tick:
            s = envelope((k - self.start_tick) * self.dt, self.ramp_s, self.hold_s)
            f = self.force
            out[self.finger, 0] = s * f[0]
            out[self.finger, 1] = s * f[1]
            out[self.finger, 2] = s * f[2]
            mag = s * math.hypot(f[0], f[1], f[2])
            if mag > self.peak_commanded_n:
                self.peak_commanded_n = mag
